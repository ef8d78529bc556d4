#!/usr/bin/env python3
"""The table of BENCHMARKS.md "Pages landing a frame apart" from the JSONs in bytes/ beside this script
(bench/small_budget_bytes.py runs at 2 and 25 %, --no-prefetch: SCENE_k4_np_{before,after}_rN.json, "before" on
the branch's base, "after" with the wait behind pages on their way; the runs of a pair back to back)."""
from __future__ import annotations

import glob
import json
import os
import statistics
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ["donut", "biker", "playbot", "statue-massa", "statue-st-peter"]


def _runs(folder: str, scene: str, side: str) -> list[dict]:
    return [json.load(open(f)) for f in sorted(glob.glob(os.path.join(folder, f"{scene}_k4_np_{side}_r*.json")))]


def _mean(views: list[dict], k: str) -> float:
    return sum(v[k] for v in views) / len(views)


def main(folder: str = os.path.join(HERE, "bytes")) -> None:
    print("| scene (k = 4, no-prefetch) | budget | runs | pages read, mean (range of runs) before -> after | used, "
          "before -> after | read and not used, views x runs with any: before -> after | views whose pages read vary "
          "from run to run, before -> after | downloaded / drawn, mean (range) before -> after | same cut |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene in SCENES:
        b, a = _runs(folder, scene, "before"), _runs(folder, scene, "after")
        if not b or not a:
            continue
        for i in range(len(b[0]["rows"])):
            rows = {"before": [r["rows"][i] for r in b], "after": [r["rows"][i] for r in a]}
            cell = {}
            for side, rs in rows.items():
                read = [_mean(r["views"], "n_pages") for r in rs]
                used = [_mean(r["views"], "n_pages_used") for r in rs]
                unused = [v["n_pages"] - v["n_pages_used"] for r in rs for v in r["views"]]
                ratio = [r["ratio"] for r in rs]
                cell[side] = (read, used, unused, ratio)
            same = all(len({tuple(r["views"][k]["draw"]) for side in rows for r in rows[side]}) == 1
                       for k in range(len(rows["before"][0]["views"])))
            nviews = len(rows["before"][0]["views"])
            # views whose pages read (their count) differ from run to run
            vary = {side: sum(len({r["views"][k]["n_pages"] for r in rows[side]}) > 1 for k in range(nviews))
                    for side in rows}
            r0 = rows["before"][0]

            def f(x):
                return f"{statistics.mean(x):.2f} ({min(x):.2f}-{max(x):.2f})"
            cb, ca = cell["before"], cell["after"]
            label = scene if i == 0 else ""
            head = f"| {label} | {r0['fraction'] * 100:.0f} % ({r0['budget']:,}) | {len(b)}, {len(a)} | "
            print(head + f"{f(cb[0])} -> {f(ca[0])} | {statistics.mean(cb[1]):.2f} -> {statistics.mean(ca[1]):.2f} | "
                  f"{sum(u > 0 for u in cb[2])} of {len(cb[2])} (max {max(cb[2])}) -> "
                  f"{sum(u > 0 for u in ca[2])} of {len(ca[2])} (max {max(ca[2])}) | "
                  f"{vary['before']} -> {vary['after']} of {nviews} | {f(cb[3])} -> {f(ca[3])} | "
                  f"{'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main(*sys.argv[1:])
