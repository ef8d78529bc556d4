"""Benchmark of the LOD tile tree (splatstream/lod.py) on make_scene scenes.

    .venv/bin/python bench/bench_lod.py [--splats 1000000 6000000] [--reductions 4 8] [--max-leaf 65536]
                                        [--reorder-input]

Each (scene, reduction) runs in its own process, so the peak resident size (getrusage ru_maxrss) is that run's:
reading the PLY (the reader's own peak included), then building the tree; "build MB" is the peak of the build's
own allocations (tracemalloc), on top of the input that the caller already holds. Scenes are made with
/work/shared/tools/make_scene.py (seed 0) in a temporary directory and deleted afterwards.
Prints one JSON line per run and a table at the end.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("SPLATSTREAM_SHARED", ROOT.parent / "shared"))
MAKE_SCENE = SHARED / "tools" / "make_scene.py"


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def run_one(path: str, reduction: float, max_leaf: int, reorder_input: bool) -> dict:
    """Read `path`, build the tree, return the measurements (runs inside the child process)."""
    sys.path.insert(0, str(ROOT))
    from splatstream.lod import build_tiles
    from splatstream.ply import read_gaussians_ply

    g = read_gaussians_ply(path)
    input_mb = sum(getattr(g, f).nbytes for f in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc",
                                                  "sh_rest")) / 2**20
    after_read = peak_mb()
    stages: dict[str, float] = {}
    last = [time.perf_counter()]

    def progress(stage: str, fraction: float) -> None:
        now = time.perf_counter()
        stages[stage] = stages.get(stage, 0.0) + now - last[0]
        last[0] = now

    cpu0, t0 = time.process_time(), time.perf_counter()
    tracemalloc.start()  # numpy reports its buffers to tracemalloc: the build's own allocations, input excluded
    tiles = build_tiles(g, max_leaf_splats=max_leaf, reduction=reduction, progress=progress,
                        reorder_input=reorder_input)
    build_peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    levels = max(t.level for t in tiles) + 1
    per_level = [sum(len(t.gaussians) for t in tiles if t.level == level) for level in range(levels)]
    tiles_per_level = [sum(1 for t in tiles if t.level == level) for level in range(levels)]
    return {
        "splats": len(g), "sh_degree": g.sh_degree, "reduction": reduction, "max_leaf_splats": max_leaf,
        "reorder_input": reorder_input,
        "build_s": round(wall, 2), "build_cpu_s": round(cpu, 2),
        "stages_s": {k: round(v, 2) for k, v in stages.items()},
        "input_mb": round(input_mb), "peak_rss_mb_after_read": round(after_read), "peak_rss_mb": round(peak_mb()),
        "peak_over_input": round(peak_mb() / input_mb, 2), "build_alloc_peak_mb": round(build_peak),
        "input_plus_build_over_input": round((input_mb + build_peak) / input_mb, 2),
        "tiles": len(tiles), "levels": levels, "tiles_per_level": tiles_per_level, "splats_per_level": per_level,
        "geometric_error_per_level": [round(max(t.geometric_error for t in tiles if t.level == level), 4)
                                      for level in range(levels)],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", type=int, nargs="+", default=[1_000_000, 6_000_000])
    ap.add_argument("--reductions", type=float, nargs="+", default=[4.0, 8.0])
    ap.add_argument("--max-leaf", type=int, default=65536)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reorder-input", action="store_true", help="build_tiles(..., reorder_input=True)")
    ap.add_argument("--child", nargs=4, metavar=("PATH", "REDUCTION", "MAX_LEAF", "REORDER"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(run_one(a.child[0], float(a.child[1]), int(a.child[2]), a.child[3] == "1")))
        return
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_lod_") as tmp:
        for n in a.splats:
            path = os.path.join(tmp, f"scene_{n}.ply")
            subprocess.run([sys.executable, str(MAKE_SCENE), "--splats", str(n), "--seed", str(a.seed), "--out", path],
                           check=True, stdout=subprocess.DEVNULL)
            for r in a.reductions:
                out = subprocess.run([sys.executable, __file__, "--child", path, str(r), str(a.max_leaf),
                                      str(int(a.reorder_input))], check=True, capture_output=True, text=True).stdout
                result = json.loads(out.strip().splitlines()[-1])
                print(json.dumps(result), flush=True)
                results.append(result)
            os.remove(path)
    print(f"\n{'splats':>9} {'red':>4} {'build s':>8} {'cpu s':>6} {'input MB':>8} {'build MB':>8} {'rss MB':>7} "
          f"{'tiles':>6} levels: splats per level (root first)")
    for r in results:
        print(f"{r['splats']:>9} {r['reduction']:>4g} {r['build_s']:>8} {r['build_cpu_s']:>6} {r['input_mb']:>8} "
              f"{r['build_alloc_peak_mb']:>8} {r['peak_rss_mb']:>7} {r['tiles']:>6} {r['levels']}: "
              f"{r['splats_per_level']}")


if __name__ == "__main__":
    main()
