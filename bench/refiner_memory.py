"""The CPU refiner's peak memory against its model (`CpuLevelRefiner.peak_bytes`; issue 31, branch refinefast31): for
each size, a spatial slice of a scene (the splats of least x, as bench/results/tier31/refiner_memory_probe.py took
them), its tree built with `auto` as a merge domain's is (leaves of at most 16,384 splats, and at most a quarter of the
slice so that a small one has merged levels too), then one `refine_tree` at
the refiner's defaults (256 px, 32 + 16 near and each level's far cameras) but `--iterations` steps (the peak does not
grow with the steps: every step's buffers are the first's). Each size runs in its own process, so that one fit's
memory is not another's; RSS sampled every 2 ms. One JSON line a size: the peak RSS above the tree (MiB), the model
(MiB) with the scene's own pairs a pixel (`with_scene_pairs`, estimated from the slice before its fit: branch
memmodel31) and with the constant 32 (`constant_model_mib`), their ratios (model / measured: they must stay >= 1), the
estimate (before PAIRS_MARGIN) and its CPU seconds, the largest level's pair lists and training pairs a training
pixel (near at the size, far at their crop), CPU seconds.

    PYTHONPATH=. nice -n 19 python bench/refiner_memory.py SCENE.ply 16384 32768 65536 131072 262144 \
        [--json OUT.jsonl]
    # on the GPU machine (16 cores, 128 GB), a scene of 2^21 splats or more first (donut copies: nothing outside the
    # repository), then one size a call:
    python bench/tile_scene.py samples/donut.ply --splats 2100000 --out /tmp/big.ply
    PYTHONPATH=. python bench/refiner_memory.py /tmp/big.ply 1048576 --json refiner_memory_gpu.jsonl
    PYTHONPATH=. python bench/refiner_memory.py /tmp/big.ply 2097152 --json refiner_memory_gpu.jsonl

A size above the scene's splats is skipped.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def one_size(path: str, splats: int, iterations: int, size: int) -> dict:
    """The peak above the tree of one refine_tree over `splats` splats of `path` (run in a process of its own)."""
    import numpy as np

    from refine_cpu.levels import PAIRS_MARGIN, CpuLevelRefiner, CpuRefineSettings
    from splatstream.encode.partitioned import routed_row_bytes
    from splatstream.io import read_gaussians
    from splatstream.lod import build_tiles
    from splatstream.lod_refine import refine_tree

    g = read_gaussians(path)
    if splats > len(g):
        return {"splats": splats, "skipped": f"the scene has {len(g):,} splats"}
    order = np.argsort(g.positions[:, 0], kind="stable")[:splats]  # a spatially contiguous slice
    g = g.subset(np.sort(order))
    leaf = min(16384, max(256, splats // 4))
    tiles = build_tiles(g, leaf, 2.0, merge="auto")
    refiner = CpuLevelRefiner(CpuRefineSettings(iterations=iterations, size=size))
    peak, stop = [0], [False]

    def sample() -> None:
        while not stop[0]:
            peak[0] = max(peak[0], rss_bytes())
            time.sleep(0.002)

    before = rss_bytes()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.process_time()
    refine_tree(g, tiles, (0.0, 0.0, 1.0), refiner, lambda phase, f: None)
    cpu = time.process_time() - t0
    stop[0] = True
    sampler.join()
    up = (0.0, 0.0, 1.0)
    constant = refiner.peak_bytes(len(g), routed_row_bytes(g.sh_degree))  # PAIRS_PER_PIXEL, as before memmodel31
    t1 = time.process_time()
    scene = refiner.with_scene_pairs(g, len(g), g.positions, up)  # the scene's own pairs a pixel (x PAIRS_MARGIN)
    estimate_cpu = time.process_time() - t1
    model = scene.peak_bytes(len(g), routed_row_bytes(g.sh_degree))
    above = peak[0] - before
    s = refiner.settings
    # the largest level's training pairs over the training pixels the model counts (near at the size, far at theirs)
    far_px = max((r["far_px"] for r in refiner.report), default=0)
    training_pixels = s.training_cameras * size * size + s.far_training_cameras * far_px * far_px
    import numba
    return {"input": path, "splats": len(g), "sh": g.sh_degree, "leaf": leaf, "size": size, "iterations": iterations,
            "levels": len(refiner.report), "numba_threads": numba.get_num_threads(),
            "before_mib": round(before / 2**20, 1), "peak_above_mib": round(above / 2**20, 1),
            "model_mib": round(model / 2**20, 1), "model_over_measured": round(model / max(above, 1), 2),
            "constant_model_mib": round(constant / 2**20, 1),
            "constant_over_measured": round(constant / max(above, 1), 2),
            "estimated_pairs_per_pixel": round(scene.settings.pairs_per_pixel / PAIRS_MARGIN, 2),
            "pairs_margin": PAIRS_MARGIN, "estimate_cpu_s": round(estimate_cpu, 2),
            "max_training_pairs_per_pixel": round(max(r["training_pairs"] for r in refiner.report)
                                                  / max(training_pixels, 1), 2),
            "max_training_pair_mib": round(max(r["training_pair_bytes"] for r in refiner.report) / 2**20, 1),
            "max_pair_mib": round(max(r["pair_bytes"] for r in refiner.report) / 2**20, 1),
            "max_pairs_per_near_pixel": round(max(r["pairs"] for r in refiner.report)
                                                  / ((refiner.settings.training_cameras
                                                      + refiner.settings.validation_cameras) * size * size), 1),
            "max_level_splats": max(r["splats"] for r in refiner.report),
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024, "cpu_s": round(cpu, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ply")
    ap.add_argument("splats", type=int, nargs="+")
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--json", help="append each line to this file")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one_size(args.ply, args.splats[0], args.iterations, args.size)), flush=True)
        return
    for n in args.splats:
        out = subprocess.run([sys.executable, os.path.abspath(__file__), args.ply, str(n), "--child",
                              "--iterations", str(args.iterations), "--size", str(args.size)],
                             check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1]
        print(out, flush=True)
        if args.json:
            with open(args.json, "a") as f:
                f.write(out + "\n")


if __name__ == "__main__":
    main()
