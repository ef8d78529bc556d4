"""The tables of BENCHMARKS.md "Level bands estimated" (issue 31, branch bandpage) from this directory's JSONs:
`python bench/results/bandpage/make_table.py`.

two_bands/, band1_one_level/, three_bands/: bench/small_root_estimate.py --band-shares 0.02,0.10 / 0.02,0.06 /
0.02,0.10,0.25 on the 13 scenes' format 1.15 encodes (main at 02fd8b8, the default options), the cuts and payload
bytes of bench/results/digest31/after/SCENE_np.json (the real client, --no-prefetch, 4 orbit views), and the
`--pages-run`s runs/SCENE_k5.json and runs/SCENE_k7.json (the real client on format 1.5 copies paged below levels 4
and 6: which views today's page rule would read band 1 or band 2 in, at 2 and 6 %)."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ["donut", "biker", "statue-massa", "statue-st-peter", "statue-angel", "statue-angel-with-candlestick",
          "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling", "winter_fountain", "flowers",
          "playbot"]
CHOSEN = ("donut", "biker")
SMALL = [s for s in SCENES if s not in CHOSEN + ("playbot", "flowers")]  # the nine held-out 45-150k-splat scenes
EPS = 0.005  # "no worse": within half a hundredth (the tables print two decimals)


def load(layout: str, scene: str):
    p = os.path.join(HERE, layout, f"{scene}.json")
    return json.load(open(p)) if os.path.exists(p) else None


def bold(x: float) -> str:
    return f"**{x:.2f}**" if x <= 1.2 + 1e-9 else f"{x:.2f}"


def reads(bands: list[int]) -> str:
    return "".join("R12"[b] if b < 3 else str(b) for b in bands)


def rng(rows: list[tuple], i: int) -> str:
    return f"{min(x[i] for x in rows):.2f}-{max(x[i] for x in rows):.2f}"


def main() -> None:
    print("| scene | whole manifest B | root, band 1, band 2 B (levels) | budget | drawn B | 1.15 today: downloaded "
          "/ drawn, round trips | two bands, floor | two bands, today's page rule: downloaded / drawn, last part "
          "read per view (R root, 1, 2), round trips |")
    print("|---|---:|---|---|---:|---|---|---|")
    summary: dict = {}
    for s in SCENES:
        e = load("two_bands", s)
        if e is None:
            continue
        ed = e["share_edges"]
        lv = f"0-{ed[0]}, {ed[0] + 1}-{ed[1]}, {ed[1] + 1}-9"
        parts = ", ".join(f"{p:,}" for p in e["share_parts"])
        for i, r in enumerate(e["rows"]):
            rule = r.get("shares_rule", r["shares"])
            print(f"| {s if i == 0 else ''} | {e['whole_manifest'] if i == 0 else ''} | "
                  f"{parts + ' (' + lv + ')' if i == 0 else ''} | {r['fraction'] * 100:.0f} % | {r['drawn']:,.0f} | "
                  f"{bold(r['today'])}, {r['today_rt']} | {bold(r['shares'])}, {r['shares_rt']} | {bold(rule)}, "
                  f"{reads(r.get('shares_rule_bands_read', r['shares_bands_read']))}, {r.get('shares_rule_rt', '')} |")
            summary.setdefault(r["fraction"], {})[s] = (r["today"], r["shares"], rule)
    print()
    print("| budget | held out (nine): 1.15 today | two bands, floor | two bands, today's page rule | at most 1.2 "
          "(held out): today, floor, rule | no worse than today (held out, within 0.005): floor, rule | donut, biker "
          "(chosen on): today -> floor, rule | playbot, flowers: today -> floor, rule |")
    print("|---|---|---|---|---|---|---|---|")
    for f, d in sorted(summary.items()):
        held = [d[s] for s in SMALL if s in d]

        le = [sum(x[i] <= 1.2 + 1e-9 for x in held) for i in range(3)]
        nw = [sum(x[i] <= x[0] + EPS for x in held) for i in (1, 2)]
        ch = ", ".join(f"{d[s][0]:.2f} -> {d[s][1]:.2f}, {d[s][2]:.2f}" for s in CHOSEN if s in d)
        big = ", ".join(f"{d[s][0]:.2f} -> {d[s][1]:.2f}, {d[s][2]:.2f}" for s in ("playbot", "flowers") if s in d)
        print(f"| {f * 100:.0f} % | {rng(held, 0)} | {rng(held, 1)} | {rng(held, 2)} | {le[0]}, {le[1]}, {le[2]} "
              f"of {len(held)} | {nw[0]}, {nw[1]} of {len(held)} | {ch} | {big} |")
    print()
    print("| layout (`--band-shares`) | levels of the parts | 2 % held out: floor, rule | 6 % | 25 % | 50 % | "
          "round trips at 2 / 6 / 25 / 50 % (today 2) |")
    print("|---|---|---|---|---|---|---|")
    for layout, shares in (("two_bands", "0.02,0.10"), ("band1_one_level", "0.02,0.06"),
                           ("three_bands", "0.02,0.10,0.25")):
        es = [load(layout, s) for s in SMALL]
        if any(e is None for e in es):
            continue
        edges = {tuple(e["share_edges"]) for e in es}
        cells, rts = [], []
        for i in range(4):
            fl = [e["rows"][i]["shares"] for e in es]
            ru = [e["rows"][i].get("shares_rule", e["rows"][i]["shares"]) for e in es]
            cells.append(f"{min(fl):.2f}-{max(fl):.2f}, {min(ru):.2f}-{max(ru):.2f}")
            rts.append(str(max(e["rows"][i].get("shares_rule_rt", e["rows"][i]["shares_rt"]) for e in es)))
        print(f"| {layout} ({shares}) | {sorted(edges)} | {' | '.join(cells)} | {' / '.join(rts)} |")


if __name__ == "__main__":
    main()
