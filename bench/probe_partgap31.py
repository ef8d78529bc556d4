"""The experiments of BENCHMARKS.md "Closing the partitioned refinement's gap" (issue 31, branch partgap31): one
refined partitioned encode of IN.ply (domains forced small, as bench/probe_partrefine31.py forces them) with the
domains' fit as VARIANT, printing one JSON line (wall and CPU s, peak RSS, the refinement record).

    PYTHONPATH=. python bench/probe_partgap31.py IN.ply OUT/SCENE 30 40000 scene

Arguments: input (a binary PLY), output directory, --memory-per-worker in MiB, lod_merge_domain_splats, variant:
`scene` (the encoder's since partgap31, experiment a: every fit's cameras, near and far, placed by the whole scene's
frame, lod_refine.CameraFrame, as the in-memory encode's; the domain alone in that frame), `own` (before partgap31:
each fit's cameras around its own splats, the frame dropped), `context` (experiment b's bound: `scene`, and every
domain drawn with the rest of the scene's ORIGINALS as fixed context, in its targets and in every level cut it fits,
as if its neighbours were drawn at full detail; a bound, not a design: the originals are not in a domain's task).
"""
import json
import logging
import resource
import sys
import time
from dataclasses import replace

import numpy as np

from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings
from splatstream.encode import partitioned
from splatstream.encode.driver import encode_file
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.store import open_store, read_manifest


def with_context(scene, refine_subtree):
    """refine_subtree with, for a domain (its full detail: rows of the scene), the scene's other originals as one
    more leaf at the domain root's level: fixed in every level cut and in the targets."""
    keys = {r.tobytes(): i for i, r in enumerate(np.ascontiguousarray(scene.positions))}

    def refine(g, tiles, up, refiner, progress, frame=None):
        rows = [keys.get(r.tobytes()) for r in np.ascontiguousarray(g.positions)]
        if any(r is None for r in rows):  # not a domain: the levels above the partitions
            return refine_subtree(g, tiles, up, refiner, progress, frame)
        # (rows of one position: the last of them matched, the others left in the context; biker: 6 of 152,746)
        rest = np.setdiff1d(np.arange(len(scene)), np.asarray(rows))
        context = scene.subset(rest)
        top = min(tiles, key=lambda t: tiles[t].level)
        extra = max(tiles) + 1
        with_ctx = dict(tiles)
        with_ctx[extra] = replace(tiles[top], id=extra, children=[], gaussians=context, geometric_error=0.0)
        print(f"domain of {len(g):,} splats, context {len(context):,}", file=sys.stderr, flush=True)
        out, record = refine_subtree(Gaussians.concatenate([g, context]), with_ctx, up, refiner, progress, frame)
        del out[extra]
        return out, record

    return refine


def without_frame(refine_subtree):
    """refine_subtree with the scene's frame dropped: each fit's cameras around its own splats (before partgap31)."""
    return lambda g, tiles, up, refiner, progress, frame=None: refine_subtree(g, tiles, up, refiner, progress)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    src, out, memory, domain, variant = sys.argv[1:6]
    if variant == "context":
        partitioned.refine_subtree = with_context(read_gaussians(src), partitioned.refine_subtree)
    elif variant == "own":
        partitioned.refine_subtree = without_frame(partitioned.refine_subtree)
    elif variant != "scene":
        raise SystemExit(f"unknown variant {variant}")
    refiner = CpuLevelRefiner(CpuRefineSettings(log=lambda m: print(m, file=sys.stderr, flush=True)))
    t0 = time.time()
    encode_file(src, out, memory_per_worker=int(float(memory) * 2**20), lod_merge_domain_splats=int(domain),
                lod_refiner=refiner)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    m = read_manifest(open_store(out))
    print(json.dumps({"out": out, "variant": variant, "memory_mb": memory, "domain": domain,
                      "wall_s": round(time.time() - t0, 1), "cpu_s": round(ru.ru_utime + ru.ru_stime, 1),
                      "peak_rss_mb": round(ru.ru_maxrss / 1024), "bytes_on_disk": m.bytes_on_disk,
                      "refinement": m.lod.refinement.to_dict() if m.lod.refinement else None}))


if __name__ == "__main__":
    main()
