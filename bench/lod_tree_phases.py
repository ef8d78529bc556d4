"""The LOD tree's CPU per phase, and a digest of the whole tree: what a change to the tree's CPU saves, and that it
keeps every tile to the bit.

    PYTHONPATH=. python bench/lod_tree_phases.py SCENE [--merge auto] [--threads]

Builds SCENE's tile tree as the encoder does (`build_tiles`, default leaf size and reduction, the input reordered
in place) with the tree's thread pool replaced by an inline executor (every job on the calling thread, so each
wrapped function's process CPU is its own work, inclusive; `--threads` keeps the pool as shipped). Prints the
tree's CPU and wall seconds, ru_maxrss, the load, a digest of every tile's arrays, error, bounds and children
(run it with two checkouts' code on PYTHONPATH: the digests must be equal), then the CPU seconds per phase.
"""
from __future__ import annotations

import argparse
import functools
import hashlib
import os
import resource
import time

import numpy as np
from encode_phases import InlineExecutor  # bench/ is the script's directory

import splatstream.lod as lod
import splatstream.lod_groups as lod_groups
from splatstream.io import read_gaussians

PHASES = (
    (lod, "_kd_leaves"), (lod, "_leaf_orders"), (lod, "level_auto_groups"), (lod, "level_cost_groups"),
    (lod, "group_ids_of"), (lod, "auto_tile_choice"), (lod, "merge_groups"), (lod, "merge_gaussians"),
    (lod, "finish_tile"), (lod, "extent_bounds"), (lod, "error_extremes"), (lod, "interior_bounds"),
    (lod_groups, "neighbour_keys"), (lod_groups, "edge_costs_at"), (lod_groups, "_greedy_pairs"),
    (lod_groups, "_cheapest_share"), (lod_groups, "_merge_pairs"), (lod_groups, "_drop"),
    (lod_groups, "covariances6"), (lod_groups, "_sorted_unique"), (lod_groups, "_morton_finish"),
)


def tree_digest(tiles: list) -> str:
    h = hashlib.sha256()
    for t in tiles:
        g = t.gaussians
        for a in (g.positions, g.rotations, g.log_scales, g.opacity_logits, g.sh_dc, g.sh_rest):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(np.float64(t.geometric_error).tobytes() + np.asarray(t.box_min).tobytes()
                 + np.asarray(t.box_max).tobytes() + np.float64(t.sphere_radius).tobytes() + str(t.children).encode())
    return h.hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--merge", default="auto", choices=lod.LOD_MERGES)
    ap.add_argument("--threads", action="store_true", help="keep the tree's thread pool")
    args = ap.parse_args()
    cpu: dict[str, float] = {}

    def wrap(module, name: str) -> None:
        inner = getattr(module, name)

        @functools.wraps(inner)
        def timed(*a, **k):
            t0 = time.process_time()
            try:
                return inner(*a, **k)
            finally:
                cpu[name] = cpu.get(name, 0.0) + time.process_time() - t0
        setattr(module, name, timed)

    for module, name in PHASES:
        wrap(module, name)
    g = read_gaussians(args.scene)
    if not args.threads:
        lod.ThreadPoolExecutor = InlineExecutor
    t0, w0 = time.process_time(), time.perf_counter()
    tiles = lod.build_tiles(g, merge=args.merge, reorder_input=True)
    tree_cpu, wall = time.process_time() - t0, time.perf_counter() - w0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"digest {tree_digest(tiles)} tree cpu {tree_cpu:.2f} s wall {wall:.2f} s ru_maxrss {rss:.0f} MB "
          f"load {os.getloadavg()[0]:.1f}")
    print("  ".join(f"{name}={seconds:.2f}" for name, seconds in cpu.items()))


if __name__ == "__main__":
    main()
