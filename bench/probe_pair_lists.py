"""The CPU refinement's pair lists alone (issue 31, branch pairwalk31): `raster.pair_lists` of a scene's 32 near
training cameras at the refiner's defaults (256 px), CPU seconds a call and the six arrays' sha256 (to compare two
versions' lists), the peak RSS before and after the calls, and with `--renders` the 32 full-detail renders' CPU
seconds. The splats: the finest merged level (the leaves cut at 16,384, `auto` merge: as the refiner's largest level;
refinewall31's micro-run's) or, with `--full-detail`, the scene itself.

    PYTHONPATH=TREE nice -n 19 python bench/probe_pair_lists.py CACHE/SCENE/full.ply --label main --reps 3 [--renders]
"""
from __future__ import annotations

import argparse
import hashlib
import os
import resource
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from refine_cpu import raster  # noqa: E402
from refine_cpu.levels import CpuRefineSettings  # noqa: E402
from splatstream.gaussians import Gaussians, covariances  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.lod import build_tiles  # noqa: E402
from splatstream.lod_refine import level_cuts  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("full_ply")
    ap.add_argument("--label", default="")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--full-detail", action="store_true", help="the scene's own splats, not its finest merged level")
    ap.add_argument("--renders", action="store_true", help="also time the 32 full-detail renders")
    args = ap.parse_args()
    g = read_gaussians(args.full_ply)
    train, _ = CpuRefineSettings().cameras(g.positions, (0.0, 0.0, 1.0))
    if args.full_detail:
        whole = g
    else:
        tiles = build_tiles(g, 16384, 2.0, merge="auto")
        cut = level_cuts(tiles)[-1]
        whole = Gaussians.concatenate([tiles[i].gaussians for i in cut.fixed]
                                      + [tiles[i].gaussians for i in cut.merged])
    pl = raster.pair_lists(whole, train[:2])  # the kernels loaded (or compiled) outside the timing
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    times = []
    for _ in range(args.reps):
        del pl
        t0 = time.process_time()
        pl = raster.pair_lists(whole, train)
        times.append(time.process_time() - t0)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    h = hashlib.sha256()
    for a in (pl.pixel_offsets, pl.proj, pl.g, pl.splat, pl.base, pl.projected):
        h.update(np.ascontiguousarray(a).tobytes())
    line = (f"{args.label}: {len(whole):,} splats, pair_lists CPU {' '.join(f'{t:.2f}' for t in times)} s; "
            f"pairs {len(pl.g):,} ({pl.nbytes / 2**20:.0f} MiB); lists sha256 {h.hexdigest()[:16]}; "
            f"peak RSS {rss0:.0f} -> {rss:.0f} MiB")
    if args.renders:
        cov = covariances(g)
        raster.render(g, train[0], None, cov)
        renders = []
        for _ in range(args.reps):
            t0 = time.process_time()
            for c in train:
                raster.render(g, c, None, cov)
            renders.append(time.process_time() - t0)
        line += f"; 32 renders CPU {' '.join(f'{t:.2f}' for t in renders)} s"
    print(f"{line}; load {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main()
