"""The cube presets' rows before and after a change, per scene, from two `splatstream eval` reports of the same
scene and cameras (issue 32, rotrange32: `cube565` rotations for `low`, `very-low-rgb127`, `very-low`).

    python bench/rot_range_table.py NAME=BEFORE.json,AFTER.json [...] [--held-out NAME,...] [--markdown OUT.md]
        [--json OUT.json]

Per scene and preset: disk B/splat and mean PSNR before -> after; then whether `very-low-rgb127` lies strictly
between `very-low` and `low` in both (after), and each preset's range of changes over the choice scenes and over
the held-out ones (--held-out names them; the rest are the choice scenes). Last, the ladder check: how far each new
point lies above (+) or below (-) the line from the preset's point before to the next larger preset's point before
(`very-low` -> `very-low-rgb127` -> `low` -> `low-plus`), in dB at the new point's bytes: below it, the same extra
bytes spent by moving toward the larger preset would have bought more.
"""
from __future__ import annotations

import argparse
import json
import sys

PRESETS = ("low", "very-low-rgb127", "very-low")
NEXT_LARGER = {"very-low": "very-low-rgb127", "very-low-rgb127": "low", "low": "low-plus"}


def preset_rows(path: str) -> dict[str, dict]:
    return {r["preset"]: r for r in json.load(open(path))["rows"] if r.get("kind", "preset") == "preset"
            and "preset" in r and not r.get("overrides")}


def scene_rows(before: str, after: str) -> dict[str, dict]:
    old, new = preset_rows(before), preset_rows(after)
    out = {}
    for p in PRESETS:
        o, n = old[p], new[p]
        out[p] = {"bytes_before": o["disk_bytes_per_splat"], "bytes_after": n["disk_bytes_per_splat"],
                  "psnr_before": o["psnr_mean"], "psnr_after": n["psnr_mean"],
                  "bytes_change": n["disk_bytes_per_splat"] / o["disk_bytes_per_splat"] - 1,
                  "psnr_change": n["psnr_mean"] - o["psnr_mean"]}
    for p, up in NEXT_LARGER.items():
        b1, q1 = old[p]["disk_bytes_per_splat"], old[p]["psnr_mean"]
        b2, q2 = old[up]["disk_bytes_per_splat"], old[up]["psnr_mean"]
        bn = new[p]["disk_bytes_per_splat"]
        out[p]["above_ladder_db"] = new[p]["psnr_mean"] - (q1 + (bn - b1) / (b2 - b1) * (q2 - q1))
    b = {p: new[p]["disk_bytes_per_splat"] for p in PRESETS}
    q = {p: new[p]["psnr_mean"] for p in PRESETS}
    out["between"] = bool(b["very-low"] < b["very-low-rgb127"] < b["low"] and q["very-low"] < q["very-low-rgb127"]
                          < q["low"])
    out["steps"] = (b["very-low-rgb127"] / b["very-low"], b["low"] / b["very-low-rgb127"])
    return out


def summary(scenes: dict[str, dict], names: list[str]) -> dict[str, str]:
    out = {}
    for p in PRESETS:
        if not names:
            continue
        db = [scenes[s][p]["psnr_change"] for s in names]
        dz = [100 * scenes[s][p]["bytes_change"] for s in names]
        up = sum(d > 0 for d in db)
        out[p] = (f"PSNR up on {up} of {len(names)} ({min(db):+.2f} to {max(db):+.2f} dB), bytes {min(dz):+.1f} to "
                  f"{max(dz):+.1f} %")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", metavar="NAME=BEFORE.json,AFTER.json")
    ap.add_argument("--held-out", default="")
    ap.add_argument("--markdown")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    scenes = {}
    for pair in args.pairs:
        name, files = pair.split("=", 1)
        before, after = files.split(",")
        scenes[name] = scene_rows(before, after)
    held = [s for s in args.held_out.split(",") if s]
    choice = [s for s in scenes if s not in held]
    lines = ["| scene | `low`: B/splat; PSNR dB | `very-low-rgb127` | `very-low` | rgb127 between |",
             "|---|---|---|---|---|"]
    for name, r in scenes.items():
        cells = [f"{r[p]['bytes_before']:.2f} -> {r[p]['bytes_after']:.2f} ({100 * r[p]['bytes_change']:+.1f}%); "
                 f"{r[p]['psnr_before']:.2f} -> {r[p]['psnr_after']:.2f} ({r[p]['psnr_change']:+.2f})" for p in PRESETS]
        mark = " (held out)" if name in held else ""
        lines.append(f"| {name}{mark} | {' | '.join(cells)} | {'yes' if r['between'] else 'NO'} "
                     f"({r['steps'][0]:.2f}x, {r['steps'][1]:.2f}x) |")
    lines += ["", "| scene | " + " | ".join(f"`{p}` above its ladder line, dB" for p in PRESETS) + " |",
              "|---|" + "---|" * len(PRESETS)]
    for name, r in scenes.items():
        lines.append(f"| {name} | " + " | ".join(f"{r[p]['above_ladder_db']:+.2f}" for p in PRESETS) + " |")
    lines.append("")
    for p in PRESETS:
        above = sum(r[p]["above_ladder_db"] > 0 for r in scenes.values())
        lines.append(f"* `{p}` above its ladder line on {above} of {len(scenes)} scenes")
    for label, names in (("choice scenes", choice), ("held out", held)):
        for p, text in summary(scenes, names).items():
            lines.append(f"* {label} ({len(names)}), `{p}`: {text}")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.markdown:
        open(args.markdown, "w").write(text)
    if args.json:
        json.dump({"scenes": scenes, "held_out": held, "choice": choice}, open(args.json, "w"), indent=1)
    return 0 if all(r["between"] for r in scenes.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
