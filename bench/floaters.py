"""What the density filter (--filter-density SIZE,MIN: floater removal, splatstream/edit.py DensityFilter) removes
on the real scenes of ../shared/data/real/, at cell sizes relative to each scene's robust extent (the largest side
of its 1st..99th percentile box), and how long it takes. Prints a Markdown table for BENCHMARKS.md.

    python bench/floaters.py
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np

from splatstream.edit import DensityFilter
from splatstream.io import read_gaussians

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REAL = os.path.join(os.environ.get("SPLATSTREAM_SHARED", os.path.join(ROOT, "..", "shared")), "data", "real")
SCENES = ["fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply", "donut_sh0_no_normals.ply", "guitar.compressed.ply",
          "winter_fountain.splat", "biker.compressed.ply", "statues/st-peter.sog", "statues/massa.sog"]
FRACTIONS = (1 / 50, 1 / 100)
MINIMA = (2, 4, 8)


def main() -> int:
    print("| scene | splats | extent | cell | " + " | ".join(f"MIN {m}: dropped" for m in MINIMA) + " | seconds |")
    print("| --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in MINIMA) + " | ---: |")
    for name in SCENES:
        path = os.path.join(REAL, name)
        if not os.path.exists(path):
            print(f"{name}: not in {REAL}", file=sys.stderr)
            continue
        g = read_gaussians(path)
        lo, hi = np.percentile(g.positions, [1, 99], axis=0)
        extent = float(np.max(hi - lo))
        for f in FRACTIONS:
            size = extent * f
            t = time.perf_counter()
            counts = DensityFilter(size, 1).neighbour_counts(g)
            seconds = time.perf_counter() - t
            dropped = [int(np.count_nonzero(counts < m)) for m in MINIMA]
            cells = " | ".join(f"{d} ({100 * d / len(g):.2f}%)" for d in dropped)
            print(f"| {name} | {len(g)} | {extent:.3g} | {size:.3g} (1/{round(1 / f)}) | {cells} | {seconds:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
