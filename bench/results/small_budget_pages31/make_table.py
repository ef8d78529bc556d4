"""The table of BENCHMARKS.md "What a small budget reads, file by file" from this directory's JSONs:
`python bench/results/small_budget_pages31/make_table.py` (bytes/: bench/small_budget_bytes.py per scene, `np`
--no-prefetch, `pf` the default prefetch, `g5` --fill-gap 5; band/: bench/band_pages_estimate.py --rule 0.02,2;
lod_vs_peers/: the benchmark's own run, for PSNR)."""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ["donut", "biker", "statue-massa", "playbot", "statue-st-peter", "statue-angel",
          "statue-angel-with-candlestick", "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling",
          "winter_fountain", "flowers"]
HEADER = ["scene", "budget", "root manifest B", "drawn B (tiles)", "ancestors B (tiles)", "downloaded / drawn",
          "without the manifest", "floor (without the root)", "round trips: first frame, converged", "with prefetch",
          "`--fill-gap 5`", "band pages (estimate), with `--fill-gap 5`", "fill", "PSNR"]


def load(*parts: str):
    p = os.path.join(HERE, *parts)
    return json.load(open(p)) if os.path.exists(p) else None


def mean(views: list[dict], key: str) -> float:
    return sum(v[key] for v in views) / len(views)


def bold(x: float) -> str:
    return f"**{x:.2f}**" if x <= 1.2 + 1e-9 else f"{x:.2f}"


def rows() -> list[str]:
    out = ["| " + " | ".join(HEADER) + " |", "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---|---|---:|"]
    for s in SCENES:
        np_, pf, g5 = load("bytes", f"{s}_np.json"), load("bytes", f"{s}_pf.json"), load("bytes", f"{s}_g5.json")
        band, lv = load("band", f"{s}.json"), load("lod_vs_peers", f"{s}.json")
        if np_ is None:
            continue
        ours = {r["budget"]: r for r in lv["ours"]} if lv else {}
        for i, r in enumerate(np_["rows"]):
            v, n = r["views"], r["budget"]
            o = ours.get(n)
            fills = [x["drawn_splats"] / n for x in v]
            first = "/".join(map(str, sorted({x["rt_first_frame"] for x in v})))
            converged = "/".join(map(str, sorted({x["rt_converged"] for x in v})))
            pfr = pf["rows"][i] if pf else None
            g5r = g5["rows"][i] if g5 else None
            bc = band[0]["cells"][i] if band else None
            band_cell = "-"
            if bc is not None:
                band_cell = bold(bc["ratio"])
                if g5r is not None:
                    band_cell += ", " + bold(bc["ratio"] - (r["ratio_no_manifest"] - g5r["ratio_no_manifest"]))
            pf_cell = "-"
            if pfr is not None:
                other = mean(pfr["views"], "other")
                pf_cell = bold(pfr["ratio"]) + (f" (+{other:,.0f} B)" if other else "")
            cells = [s if i == 0 else "", f"{round(r['fraction'] * 100)} % ({n:,})", f"{mean(v, 'manifest'):,.0f}",
                     f"{mean(v, 'drawn'):,.0f} ({mean(v, 'drawn_tiles'):.0f})",
                     f"{mean(v, 'ancestors'):,.0f} ({mean(v, 'n_ancestors'):.1f})", bold(r["ratio"]),
                     f"{r['ratio_no_manifest']:.2f}",
                     f"{r['least_ratio']:.2f} ({r['least_ratio_without_root']:.2f})", f"{first}, {converged}",
                     pf_cell, "-" if g5r is None else bold(g5r["ratio"]), band_cell,
                     f"{min(fills):.3f}-{max(fills):.3f}", "-" if o is None else f"{o['psnr_mean']:.2f}"]
            out.append("| " + " | ".join(cells) + " |")
    return out


if __name__ == "__main__":
    print("\n".join(rows()))
