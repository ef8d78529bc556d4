"""The LOD tree alone, as the encoder builds it, by several checkouts: paired and interleaved process CPU and wall.

    python bench/lod_tree_ab.py SCENE --rounds 8 /tmp/base /work/wt_new

Each run is a fresh process of one checkout (its directory both the working directory and PYTHONPATH) that reads
SCENE and times one `lod.build_tiles(g, reorder_input=True)` (encode_file's default: the input reordered in place,
the tree's own thread pool): process CPU (every thread) and wall. Every round runs every checkout once, the order
turned by one each round, so that a slow minute of a shared machine falls on all of them. Prints per checkout the
median and minimum CPU, and the last checkout's CPU over the first's per round.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

ONE_BUILD = r'''
import json, os, sys, time
from splatstream import lod
from splatstream.io import read_gaussians
g = read_gaussians(sys.argv[1])
cpu, wall = time.process_time(), time.perf_counter()
lod.build_tiles(g, reorder_input=True)
print(json.dumps({"cpu": time.process_time() - cpu, "wall": time.perf_counter() - wall, "load": os.getloadavg()[0]}))
'''


def one_build(scene: str, code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", ONE_BUILD, scene], cwd=code, env={**os.environ, "PYTHONPATH": code},
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("codes", nargs="+", help="checkout directories")
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args()
    runs: dict[str, list[dict]] = {code: [] for code in args.codes}
    for r in range(args.rounds):
        turn = r % len(args.codes)
        for code in args.codes[turn:] + args.codes[:turn]:
            runs[code].append(one_build(args.scene, code))
    for code, rows in runs.items():
        cpu = [row["cpu"] for row in rows]
        wall = statistics.median(row["wall"] for row in rows)
        print(f"{code}: CPU median {statistics.median(cpu):.3f} s, min {min(cpu):.3f} s "
              f"[{' '.join(f'{c:.3f}' for c in cpu)}]; wall median {wall:.3f} s; "
              f"load {' '.join(format(row['load'], '.1f') for row in rows)}")
    first, last = runs[args.codes[0]], runs[args.codes[-1]]
    ratios = [b["cpu"] / a["cpu"] for a, b in zip(first, last, strict=True)]
    print("CPU, last / first, per round:", " ".join(f"{x:.3f}" for x in ratios))


if __name__ == "__main__":
    main()
