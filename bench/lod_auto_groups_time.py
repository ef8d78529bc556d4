"""CPU time of the auto merge's grouping (lod.level_auto_groups) level by level, and a digest of its groups.

    PYTHONPATH=. python bench/lod_auto_groups_time.py SCENE [--repeat R] [--threads T]

Builds the LOD tree of SCENE as the encoder does (default leaf size and reduction, `merge="auto"`), recording
the inputs of every level's level_auto_groups, then runs each level's grouping again R times and prints the
least CPU seconds per level and in all, with a digest of the groups and grid choices: run it with two checkouts'
code (PYTHONPATH) to see that a change keeps the groups to the bit and what it saves. CPU seconds are the figure
to compare on a shared machine (BENCHMARKS.md, "Encoder"); the level inputs are held in memory (a 150k-splat
scene: about 20 MB).
"""
from __future__ import annotations

import argparse
import hashlib
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from splatstream import lod
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1, help="a pool of this many threads for the reruns (1: none)")
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    levels = []
    original = lod.level_auto_groups

    def record(members, masses, targets, cap, blurs, *rest, **kw):
        slim = [Gaussians(m.positions.copy(), m.rotations.copy(), m.log_scales.copy(), m.opacity_logits.copy(),
                          m.sh_dc.copy(), np.zeros((len(m), 0, 3), np.float32)) for m in members]
        levels.append((slim, [x.copy() for x in masses], list(targets), cap, list(blurs)))
        return original(members, masses, targets, cap, blurs, *rest, **kw)

    lod.level_auto_groups = record
    try:
        t0, w0 = time.process_time(), time.perf_counter()
        lod.build_tiles(g, merge="auto")
        tree_cpu, tree_wall = time.process_time() - t0, time.perf_counter() - w0
    finally:
        lod.level_auto_groups = original
    pool = ThreadPoolExecutor(max_workers=args.threads) if args.threads > 1 else None
    h = hashlib.sha256()
    total = total_wall = 0.0
    for k, (members, masses, targets, cap, blurs) in enumerate(levels):
        best = best_wall = float("inf")
        for _ in range(args.repeat):
            t0, w0 = time.process_time(), time.perf_counter()
            groups, chosen = lod.level_auto_groups(members, masses, targets, cap, blurs, pool=pool)
            best = min(best, time.process_time() - t0)
            best_wall = min(best_wall, time.perf_counter() - w0)
        for order, starts in groups:
            h.update(np.asarray(order, np.int64).tobytes())
            h.update(np.asarray(starts, np.int64).tobytes())
        h.update(np.asarray(chosen, bool).tobytes())
        total += best
        total_wall += best_wall
        print(f"level {k} (first merged = 0): {sum(len(m) for m in members):,} splats, {len(members)} tiles, "
              f"grid chosen on {sum(chosen)}, {best:.3f} CPU s, {best_wall:.3f} s wall")
    print(f"tree (merge auto) {tree_cpu:.2f} CPU s, {tree_wall:.2f} s wall; level_auto_groups "
          f"({args.threads} threads) {total:.2f} CPU s, {total_wall:.2f} s wall in all; "
          f"groups {h.hexdigest()[:16]}")


if __name__ == "__main__":
    main()
