"""The rotation gauge's A/B table (issue 32, rot32): per scene and preset, B/splat on disk and mean PSNR as the preset
was and with each gauge, from `bench/eval_probe.py` reports whose configs are labelled BASE (gauge off), and BASE
plus a suffix per gauge (`h`: half-turns, `g` or `c`: cube), e.g. m / mh / mg for medium.

    python bench/rot_gauge_table.py SCENE=REPORT.json[,REPORT.json...] ... [--markdown OUT.md]
"""
from __future__ import annotations

import argparse
import json
import sys

BASES = {"m": "medium", "ml": "medium-low", "lo": "low", "vl": "very-low", "vr": "very-low-rgb127"}
GAUGE_SUFFIX = {"h": "half-turns", "g": "cube", "c": "cube"}


def rows_of(paths: list[str]) -> tuple[dict[str, dict], str]:
    rows, setting = {}, ""
    for path in paths:
        with open(path) as f:
            d = json.load(f)
        w, h = d["size"] if isinstance(d["size"], list) else (d["size"], d["size"])
        setting = f"{len(d['cameras'])} x {w}"
        for r in d["rows"]:
            rows[r["label"].removeprefix("probe-")] = r
    return rows, setting


def table(scenes: list[tuple[str, list[str]]]) -> str:
    lines = ["| scene (views x px) | preset | as it was: B/splat, PSNR dB | half-turns | cube |",
             "|---|---|---|---|---|"]
    for scene, paths in scenes:
        rows, setting = rows_of(paths)
        for base, preset in BASES.items():
            if base not in rows:
                continue
            b0, p0 = rows[base]["disk_bytes_per_splat"], rows[base]["psnr_mean"]
            cells = {}
            for suffix, gauge in GAUGE_SUFFIX.items():
                r = rows.get(base + suffix)
                if r is not None:
                    b, p = r["disk_bytes_per_splat"], r["psnr_mean"]
                    cells[gauge] = f"{b:.2f} ({100 * (b / b0 - 1):+.1f} %), {p:.2f} ({p - p0:+.2f})"
            lines.append(f"| {scene} ({setting}) | `{preset}` | {b0:.2f}, {p0:.2f} | {cells.get('half-turns', '')} | "
                         f"{cells.get('cube', '')} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="SCENE=REPORT.json[,REPORT.json...]")
    ap.add_argument("--markdown")
    args = ap.parse_args()
    scenes = [(s.split("=", 1)[0], s.split("=", 1)[1].split(",")) for s in args.scenes]
    text = table(scenes)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
