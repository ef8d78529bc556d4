"""Encode benchmark: time, splats/s, peak memory, GPU and disk bytes per splat for every preset.

    python bench/bench_encode.py [--splats 1000000] [--seed 0] [--presets ...] [--no-lod] [--json OUT]

Builds the scene with ../shared/tools/make_scene.py (command and seed quoted in the output), then runs
`splatstream encode` once per preset in a fresh process, so peak RSS is that of a real encode. Prints a
Markdown table with the seed's (Aras P., "Making Gaussian Splats smaller") sizes beside ours.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

from splatstream.format.presets import PRESETS as ALL_PRESETS

ROOT = pathlib.Path(__file__).resolve().parents[1]
MAKE_SCENE = ROOT.parent / "shared" / "tools" / "make_scene.py"
# The seed's table: compression ratio against the 248-byte PLY splat, and PSNR (bike scene).
SEED = {"very-high": (0.8, None), "high": (2.9, 54.82), "medium": (5.2, 47.82), "low": (12.2, 34.79),
        "very-low": (18.7, 24.02)}
PRESETS = list(ALL_PRESETS)  # the seed's five and the two between medium and low (no seed figure for those)


def make_scene(splats: int, seed: int, out: pathlib.Path) -> list[str]:
    cmd = [sys.executable, str(MAKE_SCENE), "--splats", str(splats), "--seed", str(seed), "--out", str(out)]
    if not out.exists():
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return cmd


def run_encode(src: pathlib.Path, out: pathlib.Path, preset: str, extra: list[str]) -> dict:
    code = (
        "import resource, sys, time\n"
        "from cli.main import main\n"
        "t = time.perf_counter()\n"
        "rc = main(sys.argv[1:])\n"
        "wall = time.perf_counter() - t\n"
        "print('BENCH', rc, wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n"
    )
    cmd = [sys.executable, "-c", code, "encode", str(src), str(out), "--preset", preset, "-q", *extra]
    r = subprocess.run(cmd, capture_output=True, text=True)
    line = next((ln for ln in r.stderr.splitlines() if ln.startswith("BENCH")), None)
    if r.returncode != 0 or line is None:
        raise SystemExit(f"encode failed for {preset}:\n{r.stderr}")
    _, rc, wall, maxrss_kb = line.split()
    info = json.loads(subprocess.run([sys.executable, "-m", "cli", "info", str(out), "--json"],
                                     capture_output=True, text=True, check=True).stdout)
    return {
        "preset": preset, "wall_s": float(wall), "encode_s": float(wall), "peak_rss_mb": int(maxrss_kb) / 1024,
        "splats": info["splats"], "tiles": info["tiles"], "levels": info["levels"],
        "gpu_bytes_per_splat": info["gpu_bytes_per_splat"],
        "disk_bytes_per_splat": info["bytes_on_disk"] / info["splats"],
        "leaf_disk_bytes_per_splat": info["leaf_bytes_on_disk"] / info["splats"],
        "attributes": info["attributes"], "bytes_per_level": info["bytes_per_level"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--no-lod", action="store_true")
    ap.add_argument("--workdir", default=None, help="where to keep the scene (default: a temporary directory)")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args()
    work = pathlib.Path(a.workdir or tempfile.mkdtemp(prefix="ssbench-"))
    work.mkdir(parents=True, exist_ok=True)
    src = work / f"scene_{a.splats}_{a.seed}.ply"
    cmd = make_scene(a.splats, a.seed, src)
    size = src.stat().st_size
    extra = ["--no-lod"] if a.no_lod else []
    results = []
    for preset in a.presets.split(","):
        r = run_encode(src, work / f"enc_{preset}", preset, extra)
        r["input_bytes"] = size
        results.append(r)
        print(f"{preset}: {r['encode_s']:.2f}s encode, {r['wall_s']:.2f}s with read, peak {r['peak_rss_mb']:.0f} MB",
              file=sys.stderr)
    print(f"scene: `{' '.join(pathlib.Path(c).name if i < 2 else c for i, c in enumerate(cmd))}` "
          f"({a.splats} splats, {size / 1e6:.1f} MB); machine: {os.cpu_count()} cores; "
          f"lod: {'off' if a.no_lod else 'on'}\n")
    print("| preset | encode s | splats/s (encode) | wall s (read+encode) | peak RSS MB (x input) | tiles/levels "
          "| GPU B/splat | seed GPU B/splat | disk B/splat (all levels) | disk B/splat (leaves) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        seed = f"{248 / SEED[r['preset']][0]:.1f}" if r["preset"] in SEED else "-"
        print(f"| {r['preset']} | {r['encode_s']:.2f} | {r['splats'] / r['encode_s'] / 1e6:.2f} M | {r['wall_s']:.2f} "
              f"| {r['peak_rss_mb']:.0f} ({r['peak_rss_mb'] * 2**20 / size:.2f}x) | {r['tiles']}/{r['levels']} "
              f"| {r['gpu_bytes_per_splat']:.2f} | {seed} | {r['disk_bytes_per_splat']:.2f} "
              f"| {r['leaf_disk_bytes_per_splat']:.2f} |")
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps({"command": cmd, "results": results}, indent=1))


if __name__ == "__main__":
    main()
