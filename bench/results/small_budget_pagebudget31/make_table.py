#!/usr/bin/env python3
"""The tables of BENCHMARKS.md "Pages a budget cannot use" from the JSONs beside this script
(bench/small_budget_bytes.py runs: NAME_before.json on the branch's base, NAME_after.json with the page rule)."""
from __future__ import annotations

import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
RUNS = ["donut_k5_np", "donut_k4_np", "biker_k5_np", "biker_k4_np", "donut_k5_pf", "biker_k4_pf", "playbot_k4_np",
        "statue-massa_k4_np", "statue-st-peter_k4_np"]


def mean(views, k):
    return sum(v[k] for v in views) / len(views)


def main(folder: str = HERE) -> None:
    print("| scene, pages, prefetch | budget | pages read (B) before -> after | of them used, before -> after | "
          "downloaded / drawn, before -> after | without the manifest, after | without manifest and pages, after | "
          "round trips: first frame, converged, before -> after | fill (after) | same cut |")
    print("|---|---|---|---|---|---:|---:|---|---|---|")
    for name in RUNS:
        fb, fa = os.path.join(folder, f"{name}_before.json"), os.path.join(folder, f"{name}_after.json")
        if not (os.path.exists(fb) and os.path.exists(fa)):
            continue
        b, a = json.load(open(fb)), json.load(open(fa))
        scene, k, pf = name.split("_")
        label = f"{scene}, {k[0]} = {k[1:]}, {'prefetch' if pf == 'pf' else 'no-prefetch'}"
        for i, (rb, ra) in enumerate(zip(b["rows"], a["rows"], strict=True)):
            vb, va = rb["views"], ra["views"]
            same = all(x["draw"] == y["draw"] for x, y in zip(vb, va, strict=True))
            rt = lambda vs: f"{max(v['rt_first_frame'] for v in vs)}, {max(v['rt_converged'] for v in vs)}"  # noqa: E731
            fill = [v["drawn_splats"] / ra["budget"] for v in va]
            print(f"| {label if i == 0 else ''} | {rb['fraction'] * 100:.0f} % ({rb['budget']:,}) | "
                  f"{mean(vb, 'n_pages'):.1f} ({mean(vb, 'pages'):,.0f}) -> {mean(va, 'n_pages'):.1f} "
                  f"({mean(va, 'pages'):,.0f}) | {mean(vb, 'n_pages_used'):.1f} -> {mean(va, 'n_pages_used'):.1f} | "
                  f"{rb['ratio']:.2f} -> {ra['ratio']:.2f} | {ra['ratio_no_manifest']:.2f} | "
                  f"{ra['ratio_no_manifest_or_pages']:.2f} | {rt(vb)} -> {rt(va)} | {min(fill):.3f}-{max(fill):.3f} | "
                  f"{'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main(*sys.argv[1:])
