"""Encode one scene as one variant of BENCHMARKS.md's "Refining the merged levels by partitions" (issue 31, branch
partrefine31) and print one JSON line: wall and CPU seconds, the peak RSS of this process (the in-process engine:
every partition runs here, one after another) and the manifest's refinement record.

    PYTHONPATH=. python bench/probe_partrefine31.py IN.ply OUT/SCENE 30 40000 refined   # domains <= 40,000 splats
    PYTHONPATH=. python bench/probe_partrefine31.py IN.ply OUT/SCENE 30 40000 domains   # the levels above unrefined
    PYTHONPATH=. python bench/probe_partrefine31.py IN.ply OUT/SCENE 30 40000 plain     # not refined
    PYTHONPATH=. python bench/probe_partrefine31.py IN.ply OUT/SCENE 40 46000 refined 1 # on a local Dask worker

Arguments: input (a binary PLY: read by rows, so partitioned in one process), output directory, --memory-per-worker
in MiB, EncodeOptions.lod_merge_domain_splats, and the variant: `refined` (encode --lod-refine cpu: the domains and
the levels above them), `domains` (partitioned.REFINE_UPPER_LEVELS off: the levels above the partitions as built),
`plain` (no refinement); optionally a worker count (a local Dask cluster: partitioned whatever the memory, so a
domain over the scene's in-process share can be forced; its CPU seconds are the workers', not counted here). The CPU
refiner's defaults throughout (refine_cpu.levels.CpuRefineSettings).
"""
import json
import logging
import resource
import sys
import time

from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings
from splatstream.encode import partitioned
from splatstream.encode.driver import encode_file
from splatstream.store import open_store, read_manifest


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    src, out, memory, domain, variant = sys.argv[1:6]
    kw: dict = {"lod_merge_domain_splats": int(domain)}
    if len(sys.argv) > 6:
        kw["workers"] = int(sys.argv[6])
    if variant != "plain":
        kw["lod_refiner"] = CpuLevelRefiner(CpuRefineSettings(log=lambda m: print(m, file=sys.stderr, flush=True)))
    partitioned.REFINE_UPPER_LEVELS = variant != "domains"
    t0 = time.time()
    encode_file(src, out, memory_per_worker=int(float(memory) * 2**20), **kw)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    m = read_manifest(open_store(out))
    print(json.dumps({"out": out, "variant": variant, "memory_mb": memory, "domain": domain,
                      "workers": kw.get("workers"),
                      "wall_s": round(time.time() - t0, 1), "cpu_s": round(ru.ru_utime + ru.ru_stime, 1),
                      "peak_rss_mb": round(ru.ru_maxrss / 1024), "bytes_on_disk": m.bytes_on_disk,
                      "refinement": m.lod.refinement.to_dict() if m.lod.refinement else None}))


if __name__ == "__main__":
    main()
