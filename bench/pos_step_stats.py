"""Issue 32 (branch logo32): the scene statistics a position step could be taken from, per real scene.

    python bench/pos_step_stats.py [--markdown OUT.md]

Per scene, as one tile: the median chunk extent E (the largest axis of each 256-splat chunk in Morton order, as
bench/pos_size_rule.py), the median splat size by its largest, middle and smallest axis (exp(log scale)), the
splats' opacity quartiles, and E / size with and without the median opacity as a factor: the levels per K that a
size-relative step (TileStep.per_size) gives the median chunk. Scenes missing here are skipped with a line.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

REAL = "/work/shared/data/real/"
SCENES = {"biker": REAL + "biker.compressed.ply", "guitar": REAL + "guitar.compressed.ply",
          "donut": REAL + "donut_sh0_no_normals.ply", "fruit_drops": REAL + "fruit_drops_sh3.ply",
          "lod_tile": REAL + "lod_tile_sh3_zero_rest.ply", "winter_fountain": REAL + "winter_fountain.splat",
          "flowers": REAL + "flowers_lod/lod-meta.json", "playbot": "/work/heldout/playbot/lod-meta.json",
          "playcanvas-logo": "/work/heldout/playcanvas-logo/meta.json",
          **{f"statue-{s}": f"{REAL}statues/{s}.sog" for s in ("massa", "angel-kneeling", "angel",
                                                               "angel-with-candlestick", "narcissus", "st-peter",
                                                               "trumpet")}}


def row(name: str, path: str) -> str:
    from splatstream.format.layout import CHUNK_SIZE, morton_order
    from splatstream.io import read_gaussians

    g = read_gaussians(path)
    p = g.positions[morton_order(g.positions)]
    full = len(p) // CHUNK_SIZE * CHUNK_SIZE
    c = p[:full].reshape(-1, CHUNK_SIZE, 3)
    extent = float(np.median((c.max(axis=1) - c.min(axis=1)).max(axis=1)))
    axes = np.exp(np.sort(np.asarray(g.log_scales, np.float64), axis=1))
    largest, middle, smallest = (float(np.median(axes[:, i])) for i in (2, 1, 0))
    opacity = np.asarray(g.opacities, np.float64)
    q = np.percentile(opacity, [25, 50, 75])
    return (f"| {name} | {len(p):,} | {extent:.4f} | {largest:.5f} | {middle:.5f} | {smallest:.6f} | "
            f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | {extent / largest:.1f} | {extent / middle:.1f} | "
            f"{extent * q[1] / largest:.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--markdown")
    args = ap.parse_args()
    lines = ["| scene | splats | median chunk extent E | median size: largest axis | middle | smallest | "
             "opacity p25 / p50 / p75 | E / largest | E / middle | E x opacity p50 / largest |",
             "|---|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
    for name, path in SCENES.items():
        if not os.path.exists(path):
            print(f"{name}: {path} not here, skipped", file=sys.stderr)
            continue
        lines.append(row(name, path))
        print(lines[-1], flush=True)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
