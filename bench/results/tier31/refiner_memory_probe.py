"""Peak memory of the CPU refiner over one tree (what a refined partition task holds beyond its tree), RSS sampled
every 5 ms (branch tier31; BENCHMARKS.md, "Upper domains"). One JSON line.

    PYTHONPATH=. python bench/results/tier31/refiner_memory_probe.py FULL.ply SPLATS SIZE_PX
"""
import json
import sys
import threading
import time

import numpy as np

from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings
from splatstream.io import read_gaussians
from splatstream.lod import build_tiles
from splatstream.lod_refine import refine_tree


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


def main() -> None:
    path, n, size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    g = read_gaussians(path)
    order = np.argsort(g.positions[:, 0], kind="stable")[:n]  # a spatially contiguous slice
    g = g.subset(np.sort(order))
    tiles = build_tiles(g, 16384, 2.0, merge="auto")
    peak = [0]
    stop = [False]

    def sample() -> None:
        while not stop[0]:
            peak[0] = max(peak[0], rss())
            time.sleep(0.005)

    before = rss()
    t = threading.Thread(target=sample)
    t.start()
    ref = CpuLevelRefiner(CpuRefineSettings(iterations=1, size=size))
    t0 = time.process_time()
    refine_tree(g, tiles, (0.0, 0.0, 1.0), ref, lambda s, f: None)
    stop[0] = True
    t.join()
    pairs = max(r["pair_bytes"] for r in ref.report)
    print(json.dumps({"splats": n, "size": size, "sh": g.sh_degree, "levels": len(ref.report),
                      "before_mb": before / 2**20, "peak_above_mb": (peak[0] - before) / 2**20,
                      "max_pair_mb": pairs / 2**20, "max_level_splats": max(r["splats"] for r in ref.report),
                      "cpu_s": time.process_time() - t0}))


if __name__ == "__main__":
    main()
