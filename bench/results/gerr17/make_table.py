"""gerr17: table.md from probe_SCENE.json (384 px, 2-100 %), sse_SCENE.json (100 %, 48/96/192 px, pictures where a
cut moved) and bytes_estimate.json.

    python bench/results/gerr17/make_table.py > bench/results/gerr17/table.md
"""
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ["statue-angel", "statue-angel-kneeling", "statue-angel-with-candlestick", "statue-massa",
          "statue-narcissus", "statue-st-peter", "statue-trumpet", "guitar", "winter_fountain"]


def load(prefix):
    return {s: json.load(open(p)) for s in SCENES if os.path.exists(p := os.path.join(HERE, f"{prefix}_{s}.json"))}


def main() -> None:
    probe, sse = load("probe"), load("sse")
    est = json.load(open(os.path.join(HERE, "bytes_estimate.json")))
    print("## The held-out cells (384 px, lod_vs_peers_manifest31 cameras, --no-prefetch): views whose cut moved\n")
    variants = ["lin255", "log16", "log1"]
    print("| scene | " + " | ".join(f"{b} %" for b in ("2", "6", "25", "50", "100")) + " |")
    print("|---|" + "---|" * 5)
    tot = {v: [0, 0] for v in variants}
    for s, d in probe.items():
        cells = []
        for f in (0.02, 0.06, 0.25, 0.5, 1.0):
            rows = [r for r in d["rows"] if r["fraction"] == f]
            parts = []
            for v in variants:
                if v in d["variants"]:
                    m = sum(not r[v]["same_cut"] for r in rows)
                    tot[v][0] += m
                    tot[v][1] += len(rows)
                    parts.append(f"{v} {m}/{len(rows)}")
            cells.append(", ".join(parts))
        print(f"| {s} | " + " | ".join(cells) + " |")
    print("\nViews moved in all: " + "; ".join(f"{v} {a} of {b}" for v, (a, b) in tot.items()) + "\n")

    print("## Where the screen-space error binds (100 %: no budget; 48 / 96 / 192 px windows)\n")
    print("| scene | px | f32 drawn splats (4 views) | lin255: moved, splats, drawn bytes, PSNR f32 -> lin255 |"
          " log16: moved, splats, drawn bytes, PSNR f32 -> log16 |")
    print("|---|---|---|---|---|")
    agg = {v: {"moved": 0, "views": 0, "dpsnr": [], "dsplats": [], "dbytes": []} for v in ("lin255", "log16")}
    for s, d in sse.items():
        for size in sorted({r["size"] for r in d["rows"]}):
            rows = [r for r in d["rows"] if r["size"] == size]
            cols = []
            for v in ("lin255", "log16"):
                mv = [r for r in rows if not r[v]["same_cut"]]
                a = agg[v]
                a["moved"] += len(mv)
                a["views"] += len(rows)
                if not mv:
                    cols.append("0")
                    continue
                ds = [r[v]["drawn_splats"] / r["f32"]["drawn_splats"] - 1 for r in mv]
                db = [r[v]["drawn_tile_bytes"] / r["f32"]["drawn_tile_bytes"] - 1 for r in mv]
                dp = [r[v]["psnr"] - r["f32"]["psnr"] for r in mv]
                a["dsplats"] += ds
                a["dbytes"] += db
                a["dpsnr"] += dp
                cols.append(f"{len(mv)} (views {','.join(str(r['view']) for r in mv)}): splats "
                            f"{min(ds) * 100:+.1f} to {max(ds) * 100:+.1f} %, bytes {min(db) * 100:+.1f} to "
                            f"{max(db) * 100:+.1f} %, " + ", ".join(f"{r['f32']['psnr']:.2f} -> {r[v]['psnr']:.2f}"
                                                                    for r in mv))
            drawn = ", ".join(f"{r['f32']['drawn_splats']:,}" for r in rows)
            print(f"| {s} | {size} | {drawn} | {cols[0]} | {cols[1]} |")
    print()
    for v, a in agg.items():
        if a["moved"]:
            print(f"* {v}: {a['moved']} of {a['views']} views moved; drawn splats {min(a['dsplats']) * 100:+.1f} to "
                  f"{max(a['dsplats']) * 100:+.1f} %, drawn bytes {min(a['dbytes']) * 100:+.1f} to "
                  f"{max(a['dbytes']) * 100:+.1f} %, PSNR against full detail {min(a['dpsnr']):+.3f} to "
                  f"{max(a['dpsnr']):+.3f} dB")
        else:
            print(f"* {v}: 0 of {a['views']} views moved")

    print("\n## Bytes (estimate: the f32 runs' downloaded less the table's saving, over the drawn tiles' bytes)\n")
    print("| scene | table B: lin255 / log16 less | 2 % | 6 % | 25 % | 50 % |")
    print("|---|---|---|---|---|---|")
    for s, d in probe.items():
        e = est[s]
        cells = []
        for f in (0.02, 0.06, 0.25, 0.5):
            rows = [r["f32"] for r in d["rows"] if r["fraction"] == f]
            dl = sum(r["downloaded"] for r in rows) / len(rows)
            dr = sum(r["drawn_tile_bytes"] for r in rows) / len(rows)
            cells.append(f"{dl / dr:.3f} -> {(dl - e['lin255_less']) / dr:.3f}")
        print(f"| {s} | {e['table']:,}: -{e['lin255_less']} / -{e['log16_less']} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
