"""The bytes tables of BENCHMARKS.md's fillmin31 section: `python bench/results/small_budget_fillmin31/make_table.py`.
before: today's client (`--fill-min-kb 64`), smallroot31's unpaged run (bench/results/small_budget_smallroot31/
unpaged); bytes/fm160 and bytes/gap5: bench/small_budget_bytes.py with `--view-args "--fill-min-kb 160"` and
`"--fill-gap 5"`, the same encodes and cameras, --no-prefetch. Downloaded / drawn with the manifest (without it)."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
BEFORE = os.path.join(HERE, "..", "small_budget_smallroot31", "unpaged")
SCENES = ["donut", "biker", "statue-massa", "statue-st-peter", "statue-angel", "statue-angel-with-candlestick",
          "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling", "winter_fountain", "flowers",
          "playbot"]
CHOSEN = {"donut", "biker"}
LARGE = {"flowers", "playbot"}
SIDES = [("before", BEFORE), ("fm160", os.path.join(HERE, "bytes", "fm160")),
         ("gap5", os.path.join(HERE, "bytes", "gap5"))]


def load(folder: str, scene: str) -> dict | None:
    path = os.path.join(folder, f"{scene}_np.json")
    if not os.path.exists(path):
        return None
    return {r["fraction"]: r for r in json.load(open(path))["rows"]}


def main() -> None:
    print("| scene | budget | drawn B (tiles) | 64 KiB (today) | 160 KiB | `--fill-gap 5` | same cut | "
          "round trips: first frame, converged (64 / 160 / gap 5) |")
    print("|---|---|---:|---|---|---|---|---|")
    summary: dict = {}
    for s in SCENES:
        rows = {name: load(f, s) for name, f in SIDES}
        for i, fr in enumerate(sorted(rows["before"])):
            b = rows["before"][fr]
            v = b["views"]
            drawn = sum(x["drawn"] for x in v) / len(v)
            tiles = sum(x["drawn_tiles"] for x in v) / len(v)
            cells, same, rts = [], True, []
            for name, _ in SIDES:
                r = (rows[name] or {}).get(fr)
                if r is None:
                    cells.append("-")
                    continue
                bold = "**" if round(r["ratio"], 2) <= 1.2 else ""
                cells.append(f"{bold}{r['ratio']:.2f}{bold} ({r['ratio_no_manifest']:.2f})")
                same &= [x["draw"] for x in r["views"]] == [x["draw"] for x in v]
                first = max(x["rt_first_frame"] for x in r["views"])
                rts.append(f"{first}, {max(x['rt_converged'] for x in r['views'])}")
                group = "chosen" if s in CHOSEN else "large" if s in LARGE else "held"
                summary.setdefault((fr, group, name), []).append(r["ratio"])
            print(f"| {s if i == 0 else ''} | {fr * 100:.0f} % ({b['budget']:,}) | {drawn:,.0f} ({tiles:.0f}) | "
                  f"{' | '.join(cells)} | {'yes' if same else 'NO'} | {' / '.join(rts)} |")
    print()
    print("| budget | held out (nine): 64 KiB -> 160 KiB -> gap 5 | donut, biker | flowers, playbot |")
    print("|---|---|---|---|")
    for fr in (0.02, 0.06, 0.25, 0.5):
        def rng(group, fr=fr):
            out = []
            for name, _ in SIDES:
                xs = summary.get((fr, group, name))
                out.append(f"{min(xs):.2f}-{max(xs):.2f}" if xs else "-")
            return " -> ".join(out)
        print(f"| {fr * 100:.0f} % | {rng('held')} | {rng('chosen')} | {rng('large')} |")


if __name__ == "__main__":
    main()
