"""Encode time of presets against `medium` on one scene (issue 32: every preset within 2x of medium's, LOD tree on).

    python bench/encode_ab.py SCENE PRESET ... [--every 4] [--json OUT]

Runs `splatstream encode SCENE TMP --preset P -q` (the LOD tree on, the default) in a fresh process per preset, in
the order given, with a `medium` run first and again after every `--every` presets, and reports each run's CPU
seconds (user + sys of the child: on a shared machine the wall time follows the other jobs, the CPU time much less)
and its ratio to the median of the medium runs. The medium runs' spread is printed too: it is the noise a ratio
carries. One process at a time; nothing runs in parallel.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time


def cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def encode(scene: str, preset: str, root: str) -> dict:
    out = tempfile.mkdtemp(dir=root)
    before, t = cpu_children(), time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "cli", "encode", scene, os.path.join(out, "s"), "--preset", preset,
                        "-q"], capture_output=True, text=True, cwd=os.path.join(os.path.dirname(__file__), ".."))
    wall, cpu = time.perf_counter() - t, cpu_children() - before
    if r.returncode:
        raise SystemExit(f"encode --preset {preset} failed:\n{r.stderr}")
    subprocess.run(["rm", "-rf", out], check=True)
    return {"preset": preset, "cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "load": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("presets", nargs="+")
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--json")
    args = ap.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as root:
        for i, p in enumerate(args.presets):
            if i % args.every == 0:
                runs.append(encode(args.scene, "medium", root))
                print(runs[-1], flush=True)
            runs.append(encode(args.scene, p, root))
            print(runs[-1], flush=True)
        runs.append(encode(args.scene, "medium", root))
        print(runs[-1], flush=True)
    med = [r["cpu_s"] for r in runs if r["preset"] == "medium"]
    m = statistics.median(med)
    print(f"\nmedium: {m:.2f} CPU s (median of {len(med)}: {', '.join(f'{x:.2f}' for x in med)})")
    print("| preset | CPU s | / medium |\n|---|---:|---:|")
    for r in runs:
        if r["preset"] != "medium":
            print(f"| {r['preset']} | {r['cpu_s']:.2f} | {r['cpu_s'] / m:.2f} |")
    if args.json:
        json.dump({"scene": args.scene, "medium_cpu_s": med, "runs": runs}, open(args.json, "w"), indent=1)


if __name__ == "__main__":
    main()
