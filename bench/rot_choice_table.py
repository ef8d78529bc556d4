"""`medium-low`'s row before and after its measured rotation choice (issue 32, cube32: norm8x4 half turns or, format
1.14, cube8x4), from a stored `splatstream eval` report and a fresh one of the same scene and cameras; `--preset`
another preset's row (its per-splat SH variants `medium-low-sh16`, `-sh8`, which measure the same since shvariants32).

    python bench/rot_choice_table.py NAME=STORED.json,NEW.json [...] [--held-out NAME,...] [--markdown OUT.md]
        [--json OUT.json] [--preset PRESET]

Per scene: the rotation format the encoder chose, disk B/splat and mean PSNR before -> after; whether `medium-low`
lies strictly between its neighbours in bytes and in PSNR, before and after (its neighbours: the stored report's
preset rows next to its stored point in bytes, one each side, leaving out rows within 1 % of its bytes: on the SH0
scenes `medium-low-sh16` and `-sh8` are its planes at another zstd level); and which other preset rows of the stored
report changed side of it (in bytes, or in PSNR by more than 0.001 dB, the GL renders' noise between runs): none, if
the choice moved no preset past it. Ranges over the choice
scenes and over the held-out ones (--held-out names them; the rest are the choice scenes).
"""
from __future__ import annotations

import argparse
import json
import sys

from rot_range_table import preset_rows  # bench/ is the script's directory

PRESET = "medium-low"
TWIN = 1.01  # rows within 1 % of medium-low's bytes are not its neighbours
PSNR_NOISE = 0.001  # dB: the same encode drawn twice by the GL client differs by up to 5e-5 dB


def neighbours(rows: dict[str, dict], preset: str = PRESET) -> tuple[str, str]:
    """The preset rows next to `preset`'s in bytes: (the nearest smaller, the nearest larger)."""
    size = {p: r["disk_bytes_per_splat"] for p, r in rows.items()}
    b = size[preset]
    return (max((p for p in size if size[p] < b / TWIN), key=size.__getitem__),
            min((p for p in size if size[p] > b * TWIN), key=size.__getitem__))


def _between(rows: dict[str, dict], row: dict, preset: str = PRESET) -> bool:
    lo, hi = (rows[p] for p in neighbours(rows, preset))
    return bool(lo["disk_bytes_per_splat"] < row["disk_bytes_per_splat"] < hi["disk_bytes_per_splat"]
                and lo["psnr_mean"] < row["psnr_mean"] < hi["psnr_mean"])


def _side(a: float | None, b: float, tolerance: float = 0.0) -> int:
    a = float("inf") if a is None else a  # an identical render (very-high) is written as null
    return 0 if abs(a - b) <= tolerance else (a > b) - (a < b)


def scene_row(stored: str, new: str, preset: str = PRESET) -> dict:
    rows = preset_rows(stored)
    old, fresh = rows[preset], preset_rows(new)[preset]
    crossed = [p for p, r in rows.items() if p != preset and (
        _side(r["disk_bytes_per_splat"], old["disk_bytes_per_splat"])
        != _side(r["disk_bytes_per_splat"], fresh["disk_bytes_per_splat"])
        or _side(r["psnr_mean"], old["psnr_mean"], PSNR_NOISE)
        != _side(r["psnr_mean"], fresh["psnr_mean"], PSNR_NOISE))]
    return {"rotation": fresh["formats"]["rotation"], "neighbours": neighbours(rows, preset),
            "bytes_before": old["disk_bytes_per_splat"], "bytes_after": fresh["disk_bytes_per_splat"],
            "psnr_before": old["psnr_mean"], "psnr_after": fresh["psnr_mean"],
            "bytes_change": fresh["disk_bytes_per_splat"] / old["disk_bytes_per_splat"] - 1,
            "psnr_change": fresh["psnr_mean"] - old["psnr_mean"],
            "between_before": _between(rows, old, preset), "between_after": _between(rows, fresh, preset),
            "crossed": crossed}


def summary(scenes: dict[str, dict], names: list[str]) -> str:
    if not names:
        return "-"
    db = [scenes[s]["psnr_change"] for s in names]
    dz = [100 * scenes[s]["bytes_change"] for s in names]
    cube = sum(scenes[s]["rotation"] == "cube8x4" for s in names)
    return (f"cube8x4 on {cube} of {len(names)}; PSNR {min(db):+.2f} to {max(db):+.2f} dB, bytes {min(dz):+.1f} to "
            f"{max(dz):+.1f} %")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", nargs="+", help="NAME=STORED.json,NEW.json")
    ap.add_argument("--held-out", default="", help="comma-separated scene names not chosen on")
    ap.add_argument("--markdown")
    ap.add_argument("--json")
    ap.add_argument("--preset", default=PRESET, help=f"the preset whose row is compared (default {PRESET})")
    a = ap.parse_args(argv)
    scenes = {}
    for pair in a.pairs:
        name, paths = pair.split("=", 1)
        stored, new = paths.split(",")
        scenes[name] = scene_row(stored, new, a.preset)
    held = [s for s in a.held_out.split(",") if s]
    chosen = [s for s in scenes if s not in held]
    lines = [f"| scene | rotation chosen | `{a.preset}` B/splat | PSNR dB | its neighbours (smaller, larger) | "
             "strictly between them (before -> after) | presets that changed side |", "|---|---|---|---|---|---|---|"]
    for name, r in scenes.items():
        mark = "" if name in held else " (choice)"
        lines.append(f"| {name}{mark} | {r['rotation']} | {r['bytes_before']:.2f} -> {r['bytes_after']:.2f} "
                     f"({100 * r['bytes_change']:+.1f} %) | {r['psnr_before']:.2f} -> {r['psnr_after']:.2f} "
                     f"({r['psnr_change']:+.2f}) | {', '.join(r['neighbours'])} | "
                     f"{'yes' if r['between_before'] else 'no'} -> "
                     f"{'yes' if r['between_after'] else 'no'} | {', '.join(r['crossed']) or 'none'} |")
    lines += ["", f"* choice scenes ({len(chosen)}): {summary(scenes, chosen)}",
              f"* held out ({len(held)}): {summary(scenes, held)}"]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.markdown:
        open(a.markdown, "w").write(text)
    if a.json:
        json.dump({"scenes": scenes, "choice": chosen, "held_out": held}, open(a.json, "w"), indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
