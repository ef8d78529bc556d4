"""The tables of BENCHMARKS.md "A small cut fetched directly" from this directory's JSONs and pages31's (before):
`python bench/results/small_budget_smallcut31/make_table.py`. bytes/: bench/small_budget_bytes.py per scene on the
scenes of small_budget_pages31 (the same encodes and cameras), `np` --no-prefetch, `pf` the default prefetch;
`paged/`: donut and biker encoded with `--page-tiles 1 --page-levels 4/5`, `before` this branch's base, `after` it."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
BEFORE = os.path.join(os.path.dirname(HERE), "small_budget_pages31", "bytes")
SCENES = ["donut", "biker", "statue-massa", "playbot", "statue-st-peter", "statue-angel",
          "statue-angel-with-candlestick", "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling",
          "winter_fountain", "flowers"]


def load(path: str):
    return json.load(open(path)) if os.path.exists(path) else None


def mean(views: list[dict], key: str) -> float:
    return sum(v[key] for v in views) / len(views)


def bold(x: float) -> str:
    return f"**{x:.2f}**" if x <= 1.2 + 1e-9 else f"{x:.2f}"


def same_cut(a: dict, b: dict) -> bool:
    """Every view drew the same splats and tile bytes at convergence (the same cut: the same payloads)."""
    return all(x["drawn_splats"] == y["drawn_splats"] and x["drawn_tile_bytes"] == y["drawn_tile_bytes"]
               for x, y in zip(a["views"], b["views"], strict=True))


def rt(views: list[dict], key: str) -> str:
    return "/".join(map(str, sorted({v[key] for v in views})))


def unpaged() -> list[str]:
    out = ["| scene | budget | drawn B (tiles) | ancestors B before -> after | downloaded / drawn, before -> after "
           "| without the manifest, after | with prefetch, after | round trips: first frame, converged | same cut |",
           "|---|---|---:|---|---|---:|---:|---|---|"]
    for s in SCENES:
        before = load(os.path.join(BEFORE, f"{s}_np.json"))
        after, pf = load(os.path.join(HERE, "bytes", f"{s}_np.json")), load(os.path.join(HERE, "bytes", f"{s}_pf.json"))
        if before is None or after is None:
            continue
        for i, (b, a) in enumerate(zip(before["rows"], after["rows"], strict=True)):
            v = a["views"]
            p = pf["rows"][i] if pf else None
            out.append("| " + " | ".join([
                s if i == 0 else "", f"{round(a['fraction'] * 100)} % ({a['budget']:,})",
                f"{mean(v, 'drawn'):,.0f} ({mean(v, 'drawn_tiles'):.0f})",
                f"{mean(b['views'], 'ancestors'):,.0f} -> {mean(v, 'ancestors'):,.0f}",
                f"{b['ratio']:.2f} -> {bold(a['ratio'])}", f"{a['ratio_no_manifest']:.2f}",
                bold(p["ratio"]) if p else "-", f"{rt(v, 'rt_first_frame')}, {rt(v, 'rt_converged')}",
                "yes" if same_cut(a, b) and (p is None or same_cut(p, b)) else "**no**"]) + " |")
    return out


def paged() -> list[str]:
    out = ["| scene, pages | budget | pages read (B) before -> after | ancestors B before -> after | other B "
           "before -> after | downloaded / drawn, before -> after | round trips: first frame, converged, before -> "
           "after | same cut |", "|---|---|---|---|---|---|---|---|"]
    for s in ("donut_k4", "donut_k5", "biker_k4", "biker_k5"):
        before, after = load(os.path.join(HERE, "paged", f"{s}_before.json")), \
            load(os.path.join(HERE, "paged", f"{s}_after.json"))
        if before is None or after is None:
            continue
        for i, (b, a) in enumerate(zip(before["rows"], after["rows"], strict=True)):
            bv, av = b["views"], a["views"]
            out.append("| " + " | ".join([
                s.replace("_k", ", k = ") if i == 0 else "", f"{round(a['fraction'] * 100)} %",
                f"{mean(bv, 'n_pages'):.1f} ({mean(bv, 'pages'):,.0f}) -> {mean(av, 'n_pages'):.1f} "
                f"({mean(av, 'pages'):,.0f})",
                f"{mean(bv, 'ancestors'):,.0f} -> {mean(av, 'ancestors'):,.0f}",
                f"{mean(bv, 'other'):,.0f} -> {mean(av, 'other'):,.0f}", f"{b['ratio']:.2f} -> {bold(a['ratio'])}",
                f"{rt(bv, 'rt_first_frame')}, {rt(bv, 'rt_converged')} -> {rt(av, 'rt_first_frame')}, "
                f"{rt(av, 'rt_converged')}", "yes" if same_cut(a, b) else "**no**"]) + " |")
    return out


if __name__ == "__main__":
    print("\n".join(unpaged()))
    print()
    print("\n".join(paged()))
