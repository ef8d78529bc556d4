"""Time to convergence over the reference link for the small-root donut and biker, the branch's base (before) and
this branch (after): `python bench/results/small_budget_smallroot31/link_table.py`. link/SCENE_SIDE.jsonl are
bench/results/small_budget_pagepair31/link_convergence.py's lines (3 runs a block, 4 views, 6 / 25 / 50 %), the
blocks run before, after, after, before; streams are paired by block, run, budget and view (before's first block
with after's first, its second with after's second)."""
import collections
import json
import os
import statistics

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "link")


def rows(scene: str, side: str) -> list[dict]:
    out, seen = [], collections.Counter()
    for line in open(os.path.join(HERE, f"{scene}_{side}.jsonl")):
        x = json.loads(line)
        key = (x["run"], x["budget"], x["view"])
        x["block"] = seen[key]
        seen[key] += 1
        out.append(x)
    return out


def main() -> None:
    print("| scene, budget | before: median (range), CPU, pages, bytes | after | paired: after longer in, median "
          "difference | same cut |")
    print("|---|---|---|---|---|")
    for scene in ("donut", "biker"):
        if not os.path.exists(os.path.join(HERE, f"{scene}_after.jsonl")):
            continue
        sides = {s: rows(scene, s) for s in ("before", "after")}
        for b in sorted({x["budget"] for x in sides["before"]}):
            cells, cuts = [], collections.defaultdict(set)
            for rs in sides.values():
                rs = [x for x in rs if x["budget"] == b]
                for x in rs:
                    cuts[x["view"]].add(tuple(x["draw"]))
                t = [x["converged_s"] for x in rs]
                cells.append(f"{statistics.median(t):.2f} s ({min(t):.2f}-{max(t):.2f}), "
                             f"{statistics.mean(x['cpu_s'] for x in rs):.2f} s, "
                             f"{statistics.mean(x['pages'] for x in rs):.1f}, "
                             f"{statistics.mean(x['downloaded'] for x in rs):,.0f} B")
            before = {(x["block"], x["run"], x["view"]): x["converged_s"] for x in sides["before"] if x["budget"] == b}
            after = {(x["block"], x["run"], x["view"]): x["converged_s"] for x in sides["after"] if x["budget"] == b}
            d = [after[k] - before[k] for k in before if k in after]
            longer = sum(x > 0 for x in d)
            same = all(len(c) == 1 for c in cuts.values())
            print(f"| {scene} {b * 100:.0f} % | {cells[0]} | {cells[1]} | {longer} of {len(d)}, "
                  f"{statistics.median(d):+.2f} s | {'yes' if same else 'no'} |")


if __name__ == "__main__":
    main()
