#!/usr/bin/env python3
"""fill31's tables from runs/SCENE_LINK.json (bench/small_budget_bytes.py --link ... --fill-min-kb 0,64,97.65625,128
--repeat 3): per scene and budget, each threshold's downloaded / drawn, first picture and converged picture
(median of the runs, range), and against 64 KiB the median of the paired differences (the same view and repeat,
run one after the other); whether every run drew the same cut."""
from __future__ import annotations

import glob
import json
import os
import statistics

HERE = os.path.dirname(os.path.abspath(__file__))
NAMES = {0.0: "0", 64.0: "64 KiB", 97.65625: "100 KB", 128.0: "128 KiB"}
SCENES = ["donut", "biker", "statue-angel", "statue-narcissus", "statue-angel-with-candlestick", "guitar",
          "winter_fountain"]


def ms(x: float) -> str:
    return f"{x * 1000:.0f}"


def cell(v: dict) -> str:
    return f"{ms(v['median'])} ({ms(v['min'])}-{ms(v['max'])})"


def label(r: dict) -> str:
    return r["variant"] if "variant" in r else NAMES[r["fill_min_kb"]]


def is_ref(r: dict) -> bool:
    return r.get("fill_min_kb") == 64.0 or r.get("variant") == "--fill-min-kb 64"


def table(link: str, prefix: str = "") -> str:
    out = [f"### {'Variants, ' if prefix else ''}Link {link} (times in ms from the manifest request: median of the "
           "runs (range); "
           "Δ: median of the paired differences against 64 KiB)", "",
           "| scene | budget | cut B (tiles) | threshold | downloaded / drawn | ancestors B | first picture ms | "
           "converged ms | Δ first vs 64 KiB | Δ converged vs 64 KiB | runs | same cut |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene in SCENES:
        path = os.path.join(HERE, "runs", f"{prefix}{scene}_{link.replace(':', '-')}.json")
        if not os.path.exists(path):
            continue
        d = json.load(open(path))
        by_budget: dict[int, list[dict]] = {}
        for r in d["rows"]:
            by_budget.setdefault(r["budget"], []).append(r)
        for n, rows in sorted(by_budget.items()):
            ref = next(r for r in rows if is_ref(r))
            key = {(v["view"], v["repeat"]): v for v in ref["views"]}
            cuts = {}
            for r in rows:
                for v in r["views"]:
                    cuts.setdefault(v["view"], set()).add(tuple(v["draw"]))
            same = all(len(c) == 1 for c in cuts.values())
            drawn = statistics.mean(v["drawn_tile_bytes"] for v in ref["views"])
            tiles = statistics.mean(v["drawn_tiles"] for v in ref["views"])
            for i, r in enumerate(rows):
                anc = statistics.mean(v["ancestors"] for v in r["views"])
                dff = [v["first_frame_s"] - key[(v["view"], v["repeat"])]["first_frame_s"] for v in r["views"]]
                dcv = [v["converged_s"] - key[(v["view"], v["repeat"])]["converged_s"] for v in r["views"]]
                delta = "" if is_ref(r) else \
                    f"{statistics.median(dff) * 1000:+.0f} | {statistics.median(dcv) * 1000:+.0f}"
                first = i == 0
                budget = f"{r['fraction']:.0%} ({n:,})" if first else ""
                cut = f"{drawn:,.0f} ({tiles:.1f})" if first else ""
                same_cut = ("yes" if same else "NO") if first else ""
                out.append(f"| {scene if first and n == min(by_budget) else ''} | {budget} | {cut} | "
                           f"{label(r)} | {r['ratio']:.3f} | {anc:,.0f} | {cell(r['first_frame_s'])} | "
                           f"{cell(r['converged_s'])} | {delta or '- | -'} | {r['first_frame_s']['n']} | {same_cut} |")
        out.append(f"| | | | | | | | | | | load average {d['load_average_start'][0]:.1f} -> "
                   f"{d['load_average_end'][0]:.1f} ({scene}) | |")
    return "\n".join(out) + "\n"


def main() -> None:
    def links(prefix: str) -> list[str]:
        return sorted({os.path.basename(p).rsplit("_", 1)[1][:-5].replace("-", ":")
                       for p in glob.glob(os.path.join(HERE, "runs", f"{prefix}*.json"))}, reverse=True)

    text = "\n".join([table(link) for link in links("")] + [table(link, "variant_") for link in links("variant_")])
    open(os.path.join(HERE, "table.md"), "w").write(text)
    print(text)


if __name__ == "__main__":
    main()
