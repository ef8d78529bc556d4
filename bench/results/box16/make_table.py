"""The tables of BENCHMARKS.md "Format 1.16" (issue 31, branch box16) from this directory's JSONs:
`python bench/results/box16/make_table.py`.

after/: bench/small_budget_bytes.py (--no-prefetch, the 4 orbit views of lod_vs_peers_manifest31's JSONs) on the 12
scenes as this branch's encoder writes them (format 1.16: boxes relative to the parent's, radii as steps of the half
diagonal), this branch's client; before/: the same on the same inputs encoded by the branch's base (main at
1bbadf3, format 1.15), the base's code. The payloads are the same bytes, so "same cut" compares each view's drawn
tile ids and bytes at convergence. manifest_columns.json: bench/manifest_columns.py (before:after pairs);
bounds.json: bench/results/box16/bounds_stats.py (the codec on each scene's f64 tree)."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ["donut", "biker", "statue-massa", "statue-st-peter", "statue-angel", "statue-angel-with-candlestick",
          "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling", "winter_fountain", "flowers"]
CHOSEN = ("donut", "biker")  # digest31's and earlier manifest work chose on these; nothing was chosen here
SMALL = [s for s in SCENES if s not in CHOSEN + ("flowers",)]  # the nine held-out 45-150k-splat scenes


def load(path: str):
    return json.load(open(path)) if os.path.exists(path) else None


def mean(views: list[dict], key: str) -> float:
    return sum(v[key] for v in views) / len(views)


def bold(x: float) -> str:
    return f"**{x:.2f}**" if x <= 1.2 + 1e-9 else f"{x:.2f}"


def moved_views(a: dict, b: dict) -> list[int]:
    return [i for i, (x, y) in enumerate(zip(a["views"], b["views"], strict=True))
            if sorted(x["draw"]) != sorted(y["draw"]) or x["drawn_tile_bytes"] != y["drawn_tile_bytes"]]


def rt(views: list[dict], key: str) -> str:
    return "/".join(map(str, sorted({v[key] for v in views})))


def ratios(row: dict) -> tuple[float, float]:
    drawn = mean(row["views"], "drawn_tile_bytes")
    return mean(row["views"], "downloaded") / drawn, (mean(row["views"], "downloaded")
                                                       - mean(row["views"], "manifest")) / drawn


def columns_table() -> list[str]:
    cols = {r["scene"]: r for r in json.load(open(os.path.join(HERE, "manifest_columns.json")))}
    out = ["| scene | manifest B, 1.15 -> 1.16 | table B | bounds B (box + radius -> anchor_box + box8 + radius8 + "
           "radius_far, together) | 1.16's columns alone: box8, radius8, anchor_box, radius_far B |",
           "|---|---|---|---|---|"]
    for s in SCENES:
        if s not in cols:
            continue
        b, a = cols[s]["before"], cols[s]["after"]
        m = a["column_marginal"]
        out.append(f"| {s} | {b['manifest']:,} -> {a['manifest']:,} | {b['table']:,} -> {a['table']:,} | "
                   f"{b['bounds_marginal']:,} -> {a['bounds_marginal']:,} | {m.get('box8', 0):,}, "
                   f"{m.get('radius8', 0):,}, {m.get('anchor_box', 0):,}, {m.get('radius_far', 0):,} |")
    return out


def main() -> None:
    print("\n".join(columns_table()))
    print()
    cols = {r["scene"]: r for r in json.load(open(os.path.join(HERE, "manifest_columns.json")))}
    out = ["| scene | manifest B, 1.15 -> 1.16 | budget | drawn B (tiles) | 1.15: downloaded / drawn (without the "
           "manifest) | 1.16: downloaded / drawn (without the manifest) | round trips 1.16: first frame, converged | "
           "same cut |", "|---|---|---|---:|---|---|---|---|"]
    summary: dict = {}
    moved_cells = []
    for s in SCENES:
        before = load(os.path.join(HERE, "before", f"{s}_np.json"))
        after = load(os.path.join(HERE, "after", f"{s}_np.json"))
        if before is None or after is None:
            continue
        c = cols[s]
        mcell = f"{c['before']['manifest']:,} -> {c['after']['manifest']:,}"
        for i, (b, a) in enumerate(zip(before["rows"], after["rows"], strict=True)):
            rb, rb0 = ratios(b)
            ra, ra0 = ratios(a)
            drawn = mean(a["views"], "drawn_tile_bytes")
            tiles = mean(a["views"], "drawn_tiles")
            moved = moved_views(a, b)
            if moved:
                moved_cells.append((s, a["fraction"], moved, [(mean(b["views"], "drawn_tile_bytes"), drawn)]))
            cut = "yes" if not moved else f"NO (views {', '.join(map(str, moved))})"
            out.append(f"| {s if i == 0 else ''} | {mcell if i == 0 else ''} | {a['fraction'] * 100:.0f} % "
                       f"({a['budget']:,}) | {drawn:,.0f} ({tiles:.0f}) | {bold(rb)} ({rb0:.2f}) | {bold(ra)} "
                       f"({ra0:.2f}) | {rt(a['views'], 'rt_first_frame')}, {rt(a['views'], 'rt_converged')} | "
                       f"{cut} |")
            summary.setdefault(a["fraction"], {})[s] = (rb, ra, not moved)
    print("\n".join(out))
    print()
    print("| budget | held out (nine): 1.15 -> 1.16 | donut, biker (chosen on before) | flowers | cells at most "
          "1.2, held out: 1.15 -> 1.16 | same cut |")
    print("|---|---|---|---|---|---|")
    for f, d in sorted(summary.items()):
        held = [d[s] for s in SMALL if s in d]
        if not held:
            continue
        lo_b, hi_b = min(x[0] for x in held), max(x[0] for x in held)
        lo_a, hi_a = min(x[1] for x in held), max(x[1] for x in held)
        chosen = ", ".join(f"{d[s][0]:.2f} -> {d[s][1]:.2f}" for s in CHOSEN if s in d)
        fl = f"{d['flowers'][0]:.2f} -> {d['flowers'][1]:.2f}" if "flowers" in d else "-"
        n_b = sum(x[0] <= 1.2 + 1e-9 for x in held)
        n_a = sum(x[1] <= 1.2 + 1e-9 for x in held)
        same = sum(x[2] for x in d.values())
        print(f"| {f * 100:.0f} % | {lo_b:.2f}-{hi_b:.2f} -> {lo_a:.2f}-{hi_a:.2f} | {chosen} | {fl} | "
              f"{n_b} -> {n_a} of {len(held)} | {same} of {len(d)} |")
    print()
    print("moved cells (scene, budget, views, mean drawn bytes before -> after):", moved_cells or "none")


if __name__ == "__main__":
    main()
