"""The tables of BENCHMARKS.md "Format 1.15" (issue 31, branch digest31) from this directory's JSONs:
`python bench/results/digest31/make_table.py`.

after/: bench/small_budget_bytes.py (--no-prefetch, the 4 orbit views of lod_vs_peers_manifest31's JSONs) on the 13
scenes as this branch's encoder writes them (format 1.15: short digests and radii), this branch's client; before/:
the same on the same inputs encoded by the branch's base (main at 6640cdb, format 1.12), the base's code; the same
payloads (their bytes), so "same cut" compares each view's drawn tile ids and bytes; digest_only/: donut and biker
with the digests short but the spheres whole (an intermediate encoder of this branch); manifest_columns.json:
bench/manifest_columns.py; estimate/ and estimate_before/: bench/small_root_estimate.py --share 0.02 on after/ and
before/ (one shared page below levels 0-4, with 1.15's and 1.12's tables)."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
BEFORE = HERE
SCENES = ["donut", "biker", "statue-massa", "statue-st-peter", "statue-angel", "statue-angel-with-candlestick",
          "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling", "winter_fountain", "flowers",
          "playbot"]
CHOSEN = ("donut", "biker")
SMALL = [s for s in SCENES if s not in CHOSEN + ("playbot", "flowers")]  # the nine held-out 45-150k-splat scenes


def load(path: str):
    return json.load(open(path)) if os.path.exists(path) else None


def mean(views: list[dict], key: str) -> float:
    return sum(v[key] for v in views) / len(views)


def bold(x: float) -> str:
    return f"**{x:.2f}**" if x <= 1.2 + 1e-9 else f"{x:.2f}"


def same_cut(a: dict, b: dict) -> bool:
    return all(sorted(x["draw"]) == sorted(y["draw"]) and x["drawn_tile_bytes"] == y["drawn_tile_bytes"]
               for x, y in zip(a["views"], b["views"], strict=True))


def rt(views: list[dict], key: str) -> str:
    return "/".join(map(str, sorted({v[key] for v in views})))


def ratios(row: dict) -> tuple[float, float]:
    drawn = mean(row["views"], "drawn_tile_bytes")
    return mean(row["views"], "downloaded") / drawn, (mean(row["views"], "downloaded")
                                                       - mean(row["views"], "manifest")) / drawn


def main() -> None:
    cols = {r["scene"]: r for r in json.load(open(os.path.join(HERE, "manifest_columns.json")))}
    out = ["| scene | manifest B, 1.12 -> 1.15 (digests) | budget | drawn B (tiles) | 1.12: downloaded / drawn "
           "(without the manifest) | 1.15: downloaded / drawn (without the manifest) | round trips 1.15: first "
           "frame, converged | same cut |", "|---|---|---|---:|---|---|---|---|"]
    summary: dict = {}
    for s in SCENES:
        before = load(os.path.join(BEFORE, "before", f"{s}_np.json"))
        after = load(os.path.join(HERE, "after", f"{s}_np.json"))
        if before is None or after is None:
            continue
        c = cols[s]
        mcell = (f"{c['before']['manifest']:,} -> {c['after']['manifest']:,} "
                 f"({c['before']['column_marginal']['sha256']:,} -> {c['after']['column_marginal']['digest16']:,})")
        for i, (b, a) in enumerate(zip(before["rows"], after["rows"], strict=True)):
            rb, rb0 = ratios(b)
            ra, ra0 = ratios(a)
            drawn = mean(a["views"], "drawn_tile_bytes")
            tiles = mean(a["views"], "drawn_tiles")
            cut = same_cut(a, b)
            out.append(f"| {s if i == 0 else ''} | {mcell if i == 0 else ''} | {a['fraction'] * 100:.0f} % "
                       f"({a['budget']:,}) | {drawn:,.0f} ({tiles:.0f}) | {bold(rb)} ({rb0:.2f}) | {bold(ra)} "
                       f"({ra0:.2f}) | {rt(a['views'], 'rt_first_frame')}, {rt(a['views'], 'rt_converged')} | "
                       f"{'yes' if cut else 'NO'} |")
            summary.setdefault(a["fraction"], {})[s] = (rb, ra, cut)
    print("\n".join(out))
    print()
    print("| budget | held out (nine): 1.12 -> 1.15 | donut, biker (chosen on) | statue-massa | playbot | flowers | "
          "cells at most 1.2, held out: 1.12 -> 1.15 | same cut |")
    print("|---|---|---|---|---|---|---|---|")
    for f, d in sorted(summary.items()):
        held = [d[s] for s in SMALL if s in d]
        lo_b, hi_b = min(x[0] for x in held), max(x[0] for x in held)
        lo_a, hi_a = min(x[1] for x in held), max(x[1] for x in held)
        ch = ", ".join(f"{d[s][0]:.2f} -> {d[s][1]:.2f}" for s in CHOSEN if s in d)
        one = {s: (f"{d[s][0]:.2f} -> {d[s][1]:.2f}" if s in d else "") for s in ("statue-massa", "playbot",
                                                                                  "flowers")}
        n_b, n_a = sum(x[0] <= 1.2 for x in held), sum(x[1] <= 1.2 for x in held)
        cuts = sum(x[2] for x in d.values())
        print(f"| {f * 100:.0f} % | {lo_b:.2f}-{hi_b:.2f} -> {lo_a:.2f}-{hi_a:.2f} | {ch} | {one['statue-massa']} | "
              f"{one['playbot']} | {one['flowers']} | {n_b} -> {n_a} of {len(held)} | {cuts} of {len(d)} |")
    print()
    print("| scene | 2 %: today 1.15, one shared page 1.12 -> 1.15 (estimate), its parts B | 6 %: today 1.15, one "
          "shared page 1.12 -> 1.15 |")
    print("|---|---|---|")
    for s in SCENES:
        e = load(os.path.join(HERE, "estimate", f"{s}_0.02.json"))
        e0 = load(os.path.join(BEFORE, "estimate_before", f"{s}_0.02.json"))
        if e is None or e0 is None:
            continue
        cells = []
        for i in (0, 1):
            r, r0 = e["rows"][i], e0["rows"][i]
            cells.append(f"{r['today']:.2f}, {r0['shared']:.2f} -> {bold(r['shared'])} (round trips "
                         f"{r['shared_rt']})" + (f", {e0['shared_parts']} -> {e['shared_parts']}" if i == 0 else ""))
        print(f"| {s} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
