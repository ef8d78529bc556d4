#!/usr/bin/env python3
"""Summarise bench/probe_statue31.py --json files of the `opmax=` variants (issue 31, branch `lodop31`): per
variant, each whole level's PSNR change against `base` by k, the level's rank above the first merged one (k = 0:
about 50 % of the scene, k = 5: about 1.6 %), the gate of the brief (k >= 2 median >= +0.3 dB, no level below
-0.3 dB), and a markdown table per scene.

    python bench/lodop31_summary.py bench/results/lodop31/probe_*.json
"""
from __future__ import annotations

import json
import statistics
import sys

VARIANTS = ("opmax=1.5", "opmax=2", "opmax=4", "opmax=8", "opmax=2@far=8")


def deltas(files: list[str]) -> dict[str, list[tuple[str, int, int, float]]]:
    """{variant: [(scene, level, k, variant - base dB)]}; a scene's files are merged (later files add variants)."""
    scenes: dict[str, dict] = {}
    for f in files:
        with open(f) as fh:
            d = json.load(fh)
        scenes.setdefault(d["scene"], {}).update(d["variants"])
    rows: dict[str, list[tuple[str, int, int, float]]] = {}
    for scene, variants in sorted(scenes.items()):
        base = {r["level"]: r["psnr"] for r in variants["base"]}
        first = max(base)  # the largest level of 1-60 % of the scene: the first merged one (about 50 %)
        for v in VARIANTS:
            for r in variants.get(v, []):
                rows.setdefault(v, []).append((scene, r["level"], first - r["level"], r["psnr"] - base[r["level"]]))
    return rows


def main(files: list[str]) -> int:
    for v, rs in deltas(files).items():
        coarse = [d for _s, _l, k, d in rs if k >= 2]
        every = [d for *_x, d in rs]
        held = statistics.median(coarse) >= 0.3 and min(every) >= -0.3
        print(f"{v}: {len({r[0] for r in rs})} scenes; k >= 2 median {statistics.median(coarse):+.2f} "
              f"({sum(d >= 0.3 for d in coarse)}/{len(coarse)} >= +0.3); worst level {min(every):+.2f} "
              f"({sum(d < -0.3 for d in every)}/{len(every)} below -0.3): {'holds' if held else 'fails'}")
        for k in sorted({r[2] for r in rs}):
            ks = [d for _s, _l, kk, d in rs if kk == k]
            print(f"  k={k}: median {statistics.median(ks):+.2f}, min {min(ks):+.2f}, max {max(ks):+.2f} ({len(ks)})")
        print("  | scene | k = " + " | ".join(str(k) for k in sorted({r[2] for r in rs}, reverse=True)) + " |")
        for scene in sorted({r[0] for r in rs}):
            cells = [f"{d:+.2f}" for _s, _l, _k, d in sorted((r for r in rs if r[0] == scene), key=lambda r: r[1])]
            print(f"  | {scene} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
