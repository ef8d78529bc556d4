"""Each preset's bytes and PSNR over the real-scene eval reports, against the figures its summary quotes (issue 32,
tidy32: presets.PRESET_SUMMARY, what `encode --help` and `info` print, kept true to the reports).

    PYTHONPATH=. python bench/preset_summary_ranges.py [REPORT.json ...] [--tolerance 0.03]

REPORT.json defaults to bench/results/eval_real/*.json (`splatstream eval` reports, bytes refreshed by
bench/eval_refresh_bytes.py). Per preset and SH degree it prints the disk B/splat range (full detail, manifest
included, no LOD) and the mean-PSNR range over the scenes, then every "N B/splat at SHk" / "N-M at SHk" figure of the
preset's summary that lies outside the reports' range at SHk by more than the tolerance (exit status 1 if any).

What counts as SHk: the report's input SH degree, except that a scene whose SH bands cost under 0.5 B/splat in every
preset (lod_tile_sh3_zero_rest: SH3 with every band coefficient 0) counts as SH0, which is what its bytes are. A
per-splat SH preset without a row on an SH0 scene is its base there (preset_dominance.SH_BASE: the same planes and,
since tidy32, the same zstd settings). Rows with format overrides are not their preset and are left out.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from preset_dominance import SH_BASE  # noqa: E402

from splatstream.format.presets import PRESET_SUMMARY  # noqa: E402

REPORTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "eval_real", "*.json")
# below this many SH bytes a splat in every preset row, a scene's SH bands carry nothing (all coefficients 0)
EMPTY_SH_BYTES_PER_SPLAT = 0.5
# "45.6 at SH3", "13-15.5 B/splat at SH3", "about 18 B/splat at SH0": a figure or range, then "at SHk"
FIGURE = re.compile(r"(\d+(?:\.\d+)?)(?:-(\d+(?:\.\d+)?))?(?: B/splat)? at SH(\d)")


def scene_sh(report: dict) -> int:
    """The SH degree a report's bytes are of: the input's, 0 where its SH bands cost next to nothing."""
    rows = [r for r in report["rows"] if r["kind"] == "preset" and "sh" in (r.get("attributes") or {})]
    if rows and all(r["attributes"]["sh"]["disk_bytes"] / r["splats"] < EMPTY_SH_BYTES_PER_SPLAT for r in rows):
        return 0
    return int(report["input"]["sh_degree"])


def points(reports: list[dict]) -> dict[str, dict[int, list[tuple[float, float | None]]]]:
    """preset -> SH degree -> [(disk B/splat, mean PSNR or None for lossless)], one per scene."""
    out: dict[str, dict[int, list]] = {}
    for report in reports:
        sh = scene_sh(report)
        rows = {r["label"]: r for r in report["rows"]
                if r["kind"] == "preset" and r["label"] == r.get("preset") and not r.get("overrides")}
        for name in PRESET_SUMMARY:
            row = rows.get(name)
            if row is None and sh == 0 and name in SH_BASE:
                row = rows.get(SH_BASE[name])
            if row is not None:
                out.setdefault(name, {}).setdefault(sh, []).append((row["disk_bytes_per_splat"], row["psnr_mean"]))
    return out


def ranges(reports: list[dict]) -> dict[str, dict[int, dict]]:
    """preset -> SH degree -> {"bytes": (least, most), "psnr": (least, most) or None (lossless), "scenes": n}."""
    out: dict[str, dict[int, dict]] = {}
    for name, by_sh in points(reports).items():
        for sh, pts in by_sh.items():
            sizes = [b for b, _ in pts]
            psnrs = [p for _, p in pts if p is not None]
            out.setdefault(name, {})[sh] = {"bytes": (min(sizes), max(sizes)),
                                            "psnr": (min(psnrs), max(psnrs)) if psnrs else None, "scenes": len(pts)}
    return out


def quoted(summary: str) -> list[tuple[float, float, int]]:
    """The (least, most, SH degree) B/splat figures a summary quotes ("about 18 B/splat at SH0": (18, 18, 0))."""
    return [(float(lo), float(hi or lo), int(sh)) for lo, hi, sh in FIGURE.findall(summary)]


def mismatches(summaries: dict[str, str], table: dict[str, dict[int, dict]], tolerance: float) -> list[str]:
    """Each quoted figure outside the reports' range at its SH degree by more than `tolerance` (a fraction), or at an
    SH degree no report measured the preset at."""
    out = []
    for name, text in summaries.items():
        for lo, hi, sh in quoted(text):
            r = table.get(name, {}).get(sh)
            if r is None:
                out.append(f"{name}: {lo:g}-{hi:g} B/splat at SH{sh}: no report measures it at SH{sh}")
                continue
            least, most = r["bytes"]
            if lo < least * (1 - tolerance) or hi > most * (1 + tolerance):
                out.append(f"{name}: {lo:g}-{hi:g} B/splat at SH{sh}, the reports {least:.2f}-{most:.2f}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="*")
    ap.add_argument("--tolerance", type=float, default=0.03)
    args = ap.parse_args()
    reports = [json.load(open(p)) for p in sorted(args.reports or glob.glob(REPORTS))]
    table = ranges(reports)
    print(f"{len(reports)} reports")
    for name in PRESET_SUMMARY:
        cells = []
        for sh in sorted(table.get(name, {})):
            r = table[name][sh]
            psnr = "identical render" if r["psnr"] is None else f"{r['psnr'][0]:.1f}-{r['psnr'][1]:.1f} dB"
            cells.append(f"SH{sh} ({r['scenes']}): {r['bytes'][0]:.2f}-{r['bytes'][1]:.2f} B/splat, {psnr}")
        everywhere = [p for by_sh in points(reports).get(name, {}).values() for _, p in by_sh if p is not None]
        if everywhere:
            cells.append(f"all scenes {min(everywhere):.1f}-{max(everywhere):.1f} dB")
        print(f"{name}: " + "; ".join(cells))
    bad = mismatches(PRESET_SUMMARY, table, args.tolerance)
    for line in bad:
        print("outside:", line)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
