"""The half-turn presets' measured rotation choice, paired (issue 32, cube8x4all32): per scene one `splatstream eval`
report holding each preset as wired (its measured choice, `norm8x4` half turns or `cube8x4`) and the variant
`ht-PRESET` (`PRESET,rotation=norm8x4`, the half turns it wrote before), same cameras.

    python bench/rot_choice_paired.py NAME=PAIRED.json[,STORED.json] [...] --choice fruit,guitar
        [--markdown OUT.md] [--json OUT.json]

Per preset and scene: the rotation chosen, disk B/splat and mean PSNR half turns -> chosen; with STORED (the stored
report of that scene) whether the half-turn arm reproduces the stored row (bytes exactly, PSNR within 0.001 dB, the
GL renders' noise), and whether the preset lies strictly between its ladder neighbours (rot_choice_table.neighbours:
rows within 1 % of its bytes left out) before (stored rows) and after (every preset of this report replaced by its
chosen row). The rule (BENCHMARKS.md, "The other half-turn presets measure `cube8x4` too"): a preset takes the
choice if on every --choice scene its PSNR does not fall, its bytes rise by at most 3 %, and it stays between its
neighbours wherever it was before. Held-out scenes (the others) are reported beside, not used.
"""
from __future__ import annotations

import argparse
import json
import sys

from rot_choice_table import PSNR_NOISE, neighbours  # bench/ is the script's directory

MAX_BYTES_RISE = 0.03  # cube32's bound


def _rows(path: str) -> list[dict]:
    return json.load(open(path))["rows"]


def paired_rows(path: str) -> dict[str, tuple[dict, dict]]:
    """preset -> (half-turn row, chosen row) of one paired report."""
    rows = _rows(path)
    chosen = {r["preset"]: r for r in rows if r["kind"] == "preset" and not r.get("overrides")}
    half = {r["label"][3:]: r for r in rows if r["label"].startswith("ht-")}
    return {p: (half[p], chosen[p]) for p in chosen if p in half}


def _between(rows: dict[str, dict], preset: str) -> bool | None:
    try:
        lo, hi = (rows[p] for p in neighbours(rows, preset))
    except ValueError:  # no neighbour on one side
        return None
    r = rows[preset]
    psnr = [float("inf") if x["psnr_mean"] is None else x["psnr_mean"] for x in (lo, r, hi)]  # None: identical
    return bool(lo["disk_bytes_per_splat"] < r["disk_bytes_per_splat"] < hi["disk_bytes_per_splat"]
                and psnr[0] < psnr[1] < psnr[2])


def scene_table(paired: str, stored: str | None, admitted: set[str] | None = None) -> dict[str, dict]:
    """Per preset of the paired report, its pair; "after" replaces the stored rows of the `admitted` presets (all
    of the report's when None) by their chosen rows, the others keep the half turns."""
    pairs = paired_rows(paired)
    before = after = None
    if stored:
        base = {r["preset"]: r for r in _rows(stored) if r["kind"] == "preset" and not r.get("overrides")}
        before = {**base, **{p: h for p, (h, _) in pairs.items() if p not in base}}
        after = {**before, **{p: c for p, (_, c) in pairs.items() if admitted is None or p in admitted}}
    out = {}
    for p, (h, c) in pairs.items():
        row = {"rotation": c["formats"]["rotation"],
               "bytes_half_turns": h["disk_bytes_per_splat"], "bytes_chosen": c["disk_bytes_per_splat"],
               "psnr_half_turns": h["psnr_mean"], "psnr_chosen": c["psnr_mean"],
               "bytes_change": c["disk_bytes_per_splat"] / h["disk_bytes_per_splat"] - 1,
               "psnr_change": c["psnr_mean"] - h["psnr_mean"]}
        if stored:
            s = base.get(p)
            row["stored"] = s is not None
            row["reproduces_stored"] = None if s is None else bool(
                s["disk_bytes"] == h["disk_bytes"] and abs(s["psnr_mean"] - h["psnr_mean"]) <= PSNR_NOISE)
            row["between_before"] = _between(before, p)
            row["between_after"] = _between(after, p)
        out[p] = row
    return out


def passes(row: dict) -> bool:
    """The rule on one choice scene."""
    return bool(row["psnr_change"] >= 0 and row["bytes_change"] <= MAX_BYTES_RISE
                and (not row.get("between_before") or row.get("between_after")))


def tabulate(scenes: dict[str, dict[str, dict]], choice: list[str]) -> dict:
    presets = list(dict.fromkeys(p for t in scenes.values() for p in t))
    verdict = {}
    for p in presets:
        on_choice = [scenes[s][p] for s in choice if p in scenes.get(s, {})]
        held = [t[p] for s, t in scenes.items() if s not in choice and p in t and t[p]["rotation"] != "norm8x4"]
        verdict[p] = {"admitted": len(on_choice) == len(choice) and all(passes(r) for r in on_choice),
                      "held_out_psnr_up": sum(r["psnr_change"] > PSNR_NOISE for r in held),
                      "held_out_psnr_down": sum(r["psnr_change"] < -PSNR_NOISE for r in held),
                      "held_out_changed": len(held)}
    return {"scenes": scenes, "choice": choice, "verdict": verdict}


def markdown(result: dict) -> str:
    def yn(v):
        return "-" if v is None else ("yes" if v else "no")
    lines = []
    for p, v in result["verdict"].items():
        lines += [f"### {p}: {'takes the measured choice' if v['admitted'] else 'keeps the half turns'}", "",
                  f"held out, where `cube8x4` was chosen: PSNR up on {v['held_out_psnr_up']}, down on "
                  f"{v['held_out_psnr_down']} of {v['held_out_changed']}", "",
                  "| scene | chosen | B/splat half turns -> chosen | PSNR dB | reproduces stored "
                  "| between before/after |",
                  "|---|---|---|---|---|---|"]
        for s, t in result["scenes"].items():
            if p not in t:
                continue
            r = t[p]
            tag = "choice" if s in result["choice"] else "held out"
            lines.append(f"| {s} ({tag}) | `{r['rotation']}` | {r['bytes_half_turns']:.3f} -> {r['bytes_chosen']:.3f} "
                         f"({100 * r['bytes_change']:+.2f} %) | {r['psnr_half_turns']:.3f} -> {r['psnr_chosen']:.3f} "
                         f"({r['psnr_change']:+.3f}) | {yn(r.get('reproduces_stored'))} | "
                         f"{yn(r.get('between_before'))} / {yn(r.get('between_after'))} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", metavar="NAME=PAIRED.json[,STORED.json]")
    ap.add_argument("--choice", default="fruit,guitar", help="the choice scenes (the rest are held out)")
    ap.add_argument("--markdown")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    inputs = {}
    for item in args.scenes:
        name, _, paths = item.partition("=")
        paired, _, stored = paths.partition(",")
        inputs[name] = (paired, stored or None)
    admitted, seen = None, []
    while admitted not in seen:  # "after" holds the admitted presets' choice only: repeat to a fixed point
        seen.append(admitted)
        result = tabulate({n: scene_table(*paths, admitted) for n, paths in inputs.items()}, args.choice.split(","))
        admitted = {p for p, v in result["verdict"].items() if v["admitted"]}
    text = markdown(result)
    if args.markdown:
        open(args.markdown, "w").write(text)
    if args.json:
        json.dump(result, open(args.json, "w"), indent=1)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
