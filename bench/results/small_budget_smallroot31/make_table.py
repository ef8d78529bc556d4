"""The tables of BENCHMARKS.md "A small root manifest" (branch smallroot31) from this directory's JSONs:
`python bench/results/small_budget_smallroot31/make_table.py`.

unpaged/: bench/small_budget_bytes.py on the 13 scenes as encoded today (unpaged; pages31's encodes and cameras), the
branch's base code (main at 7909191); small_root_before/ and small_root_after/: the same scenes repaged with a small
root manifest (`bench/bench_pages.py --repage SCENE OUT --default-levels 5`: levels 0-4, the shallowest level
holding 2 % of the splats on every one of them, then pages of 5 levels), the base's client and this branch's;
k4/: the k = 4 encodes of pages31 and pagebudget31, before and after; estimate/: bench/small_root_estimate.py
(`--share 0.02` and `0.06`) from unpaged/."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ["donut", "biker", "statue-massa", "playbot", "statue-st-peter", "statue-angel",
          "statue-angel-with-candlestick", "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling",
          "winter_fountain", "flowers"]
CHOSEN = ("donut", "biker")
SMALL = [s for s in SCENES if s not in CHOSEN + ("playbot", "flowers")]  # the nine held-out 45-150k-splat scenes


def load(*parts: str):
    path = os.path.join(HERE, *parts)
    return json.load(open(path)) if os.path.exists(path) else None


def mean(views: list[dict], key: str) -> float:
    return sum(v[key] for v in views) / len(views)


def bold(x: float) -> str:
    return f"**{x:.2f}**" if x <= 1.2 + 1e-9 else f"{x:.2f}"


def same_cut(a: dict, b: dict) -> bool:
    """Every view drew the same tiles at convergence (the same cut: the same payloads, the same picture)."""
    return all(sorted(x["draw"]) == sorted(y["draw"]) for x, y in zip(a["views"], b["views"], strict=True))


def rt(views: list[dict], key: str) -> str:
    return "/".join(map(str, sorted({v[key] for v in views})))


def main_table() -> tuple[list[str], dict]:
    out = ["| scene | budget | drawn B (tiles) | unpaged today: downloaded / drawn (without the manifest), round "
           "trips | small root, client before: downloaded / drawn, given-up payloads B | small root, this branch: "
           "downloaded / drawn (without the manifest), pages read (used), given-up B, round trips | same cut as "
           "unpaged | estimates: 1.5 pages without waste, one shared page |",
           "|---|---|---:|---|---|---|---|---|"]
    summary: dict = {}
    for s in SCENES:
        un, b, a = load("unpaged", f"{s}_np.json"), load("small_root_before", f"{s}_np.json"), \
            load("small_root_after", f"{s}_np.json")
        est = load("estimate", f"{s}_0.02.json")
        if un is None or a is None:
            continue
        for i, (ru, rb, ra) in enumerate(zip(un["rows"], b["rows"], a["rows"], strict=True)):
            vu, vb, va = ru["views"], rb["views"], ra["views"]
            e = est["rows"][i] if est else None
            same = ("yes" if same_cut(ra, ru) else "**no**") + ("" if same_cut(rb, ru) else " (client before: no)")
            summary.setdefault(round(ra["fraction"] * 100), []).append(
                (s, ru["ratio"], rb["ratio"], ra["ratio"], e["pages15"] if e else None, e["shared"] if e else None))
            out.append("| " + " | ".join([
                s if i == 0 else "", f"{round(ra['fraction'] * 100)} % ({ra['budget']:,})",
                f"{mean(va, 'drawn'):,.0f} ({mean(va, 'drawn_tiles'):.0f})",
                f"{bold(ru['ratio'])} ({ru['ratio_no_manifest']:.2f}), {rt(vu, 'rt_first_frame')}, "
                f"{rt(vu, 'rt_converged')}",
                f"{rb['ratio']:.2f}, {mean(vb, 'other'):,.0f}",
                f"{bold(ra['ratio'])} ({ra['ratio_no_manifest']:.2f}), {mean(va, 'n_pages'):.1f} "
                f"({mean(va, 'n_pages_used'):.1f}), {mean(va, 'other'):,.0f}, {rt(va, 'rt_first_frame')}, "
                f"{rt(va, 'rt_converged')}",
                same,
                f"{e['pages15']:.2f}, {e['shared']:.2f} (round trips {e['shared_rt']})" if e else "-"]) + " |")
    return out, summary


def summary_table(summary: dict) -> list[str]:
    out = ["| budget | unpaged today (held out) | small root, client before (held out) | small root, this branch "
           "(held out) | donut, biker (chosen on): today -> this branch | 1.5 pages without waste (held out) | one "
           "shared page, estimate (held out) |", "|---|---|---|---|---|---|---|"]

    def rng(rows, k):
        xs = [r[k] for r in rows if r[0] in SMALL and r[k] is not None]
        return f"{min(xs):.2f}-{max(xs):.2f}" if xs else "-"

    for pct, rows in sorted(summary.items()):
        chosen = {r[0]: r for r in rows if r[0] in CHOSEN}
        out.append("| " + " | ".join([f"{pct} %", rng(rows, 1), rng(rows, 2), rng(rows, 3),
                                      ", ".join(f"{chosen[c][1]:.2f} -> {chosen[c][3]:.2f}" for c in CHOSEN
                                                if c in chosen), rng(rows, 4), rng(rows, 5)]) + " |")
    return out


def k4_table() -> list[str]:
    out = ["| scene, `--page-levels 4` | budget | pages read (used) | given-up payloads B before -> after | "
           "downloaded / drawn, before -> after | round trips: first frame, converged, before -> after | same cut |",
           "|---|---|---|---|---|---|---|"]
    for s in ("donut", "biker", "playbot", "statue-massa", "statue-st-peter"):
        b, a = load("k4", f"{s}_k4_before.json"), load("k4", f"{s}_k4_after.json")
        if b is None or a is None:
            continue
        for i, (rb, ra) in enumerate(zip(b["rows"], a["rows"], strict=True)):
            vb, va = rb["views"], ra["views"]
            out.append("| " + " | ".join([
                s if i == 0 else "", f"{round(ra['fraction'] * 100)} %",
                f"{mean(vb, 'n_pages'):.1f} ({mean(vb, 'n_pages_used'):.1f}) -> {mean(va, 'n_pages'):.1f} "
                f"({mean(va, 'n_pages_used'):.1f})",
                f"{mean(vb, 'other'):,.0f} -> {mean(va, 'other'):,.0f}", f"{rb['ratio']:.2f} -> {bold(ra['ratio'])}",
                f"{rt(vb, 'rt_first_frame')}, {rt(vb, 'rt_converged')} -> {rt(va, 'rt_first_frame')}, "
                f"{rt(va, 'rt_converged')}", "yes" if same_cut(ra, rb) else "**no**"]) + " |")
    return out


def manifests() -> list[str]:
    out = ["| scene | whole manifest B | root to level a | root manifest, 1.5 pages (k = a + 1) B | its pages B | one "
           "shared page: root, page B |", "|---|---:|---|---:|---:|---|"]
    for share in ("0.02", "0.06"):
        for s in SCENES:
            e = load("estimate", f"{s}_{share}.json")
            if e is None:
                continue
            out.append(f"| {s} ({share}) | {e['whole_manifest']:,} | {e['level']} | {e['pages15_root']:,} | "
                       f"{e['pages15_pages']:,} | {', '.join(f'{x:,}' for x in e['shared_parts'])} |")
    return out


if __name__ == "__main__":
    rows, summary = main_table()
    for block in (rows, summary_table(summary), k4_table(), manifests()):
        print("\n".join(block) + "\n")
