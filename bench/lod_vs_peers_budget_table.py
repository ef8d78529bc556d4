#!/usr/bin/env python3
"""Issue 31's own table for one scene: per budget N the best peer level of N splats (a level the source ships
itself with exactly N splats, splat-transform's adaptive level, Spark's cut), our default encode and a second
encode of ours (e.g. `--lod-refine`), from two bench/lod_vs_peers.py runs of the same cameras.

    python bench/lod_vs_peers_budget_table.py bench/results/lod_vs_peers_heldout/playbot.json \
        bench/results/lod_vs_peers_heldout_refined/playbot.json --manifest-a /tmp/ours/playbot/manifest.msgpack \
        --manifest-b /work/heldout/refined/playbot/manifest.msgpack

PSNR: of the mean MSE over the views (SSIM their mean); "fill": splats drawn / N, lowest and highest view;
"MB": bytes downloaded (`--no-prefetch`, mean of the views; the root manifest file included) and the bytes of the
tiles drawn; "x": downloaded over drawn, and in brackets with the manifest file's bytes taken out.
"""
from __future__ import annotations

import argparse
import json
import os


def peers_at(res: dict, n: int) -> list[tuple[float, float, str]]:
    """(PSNR, SSIM, label) of every peer level of n splats."""
    out = []
    for key, label in (("peers", "st"), ("spark", "spark"), ("spark_clamp", "spark clamp")):
        out += [(r["psnr_mean"], r["ssim_mean"], label) for r in res.get(key, [])
                if r["budget"] == n and r["psnr_mean"] is not None]
    out += [(r["psnr_mean"], r["ssim_mean"], f"shipped L{r['level']}") for r in res.get("shipped", [])
            if r["splats_drawn"] == n]
    return out


def ours_cell(o: dict | None, manifest_bytes: int) -> tuple[str, str, str]:
    if o is None:
        return "-", "-", "-"
    d = o["splats_drawn_per_view"]
    fill = f"{min(d) / o['budget']:.3f}-{max(d) / o['budget']:.3f}" + (" (over)" if max(d) > o["budget"] else "")
    dl, drawn = o["bytes_downloaded_mean"], o["drawn_tile_bytes_mean"]
    mb = (f"{dl / 1e6:.2f} / {drawn / 1e6:.2f} ({dl / drawn:.2f}x; {(dl - manifest_bytes) / drawn:.2f}x)"
          if drawn else "-")
    return f"{o['psnr_mean']:.2f} / {o['ssim_mean']:.4f}", fill, mb


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="SCENE.json of the run with the peers and our default encode")
    ap.add_argument("b", help="SCENE.json of the second encode (same cameras)")
    ap.add_argument("--manifest-a", required=True)
    ap.add_argument("--manifest-b", required=True)
    ap.add_argument("--names", default="default,refined")
    args = ap.parse_args()
    a, b = json.load(open(args.a)), json.load(open(args.b))
    if a["cameras"] != b["cameras"]:
        raise SystemExit("the two runs used other cameras")
    ma, mb = os.path.getsize(args.manifest_a), os.path.getsize(args.manifest_b)
    na, nb = args.names.split(",")
    oa = {r["budget"]: r for r in a["ours"]}
    ob = {r["budget"]: r for r in b["ours"]}
    rows = [f"| budget N | best peer of N splats | every peer level of N splats (PSNR / SSIM) "
            f"| ours {na} (PSNR / SSIM) "
            f"| {na} - best peer | ours {nb} | {nb} - best peer | fill {na} | fill {nb} "
            f"| MB downloaded / drawn tiles {na} | {nb} |",
            "|---:|---:|---|---:|---:|---:|---:|---|---|---|---|"]
    for n in sorted(a["budget_splats"], reverse=True):
        ps = peers_at(a, n)
        best = max(ps) if ps else None
        q_a, f_a, m_a = ours_cell(oa.get(n), ma)
        q_b, f_b, m_b = ours_cell(ob.get(n), mb)
        gain = f"{ob[n]['psnr_mean'] - best[0]:+.2f}" if best and n in ob else "-"
        gain_a = f"{oa[n]['psnr_mean'] - best[0]:+.2f}" if best and n in oa else "-"
        every = "; ".join(f"{lab} {p:.2f} / {s:.4f}" for p, s, lab in sorted(ps, reverse=True))
        peer = f"{best[0]:.2f} ({best[2]}) | {every}" if best else "- | -"
        rows.append(f"| {n:,} | {peer} | {q_a} | {gain_a} | {q_b} | {gain} | {f_a} | {f_b} | {m_a} | {m_b} |")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
