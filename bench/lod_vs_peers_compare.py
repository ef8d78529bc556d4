#!/usr/bin/env python3
"""Our side of two bench/lod_vs_peers.py runs against the best peer (issue 31): a markdown table per scene and budget.

    python bench/lod_vs_peers_compare.py bench/results/lod_vs_peers_auto bench/results/lod_vs_peers_auto50 \
        [--manifest-dir /tmp/ours]    # where the new run's encoded scenes are, for the manifest's bytes

"best peer": the higher of splat-transform's level and Spark's better drawing (inflate or clamp), from the new run's
JSON (its peer rows, kept from the earlier runs); "fill": splats drawn / budget, lowest and highest view; "bytes": the
new run's bytes downloaded less the root manifest file (pages fetched, if any, counted in), over the bytes of the
tiles drawn, mean of the views. Scenes in the order of lod_vs_peers.SCENES that have a JSON in the new directory.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics

from lod_vs_peers import SCENES  # bench/ is the script's directory: the scenes and their order, one list


def best_peer(res: dict, budget: int) -> tuple[float | None, str]:
    cands = [(r["psnr_mean"], label) for key, label in (("peers", "st"), ("spark", "spark"), ("spark_clamp", "spark"))
             for r in res.get(key, []) if r["budget"] == budget and r["psnr_mean"] is not None]
    return max(cands) if cands else (None, "-")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old_dir")
    ap.add_argument("new_dir")
    ap.add_argument("--manifest-dir", default=None, help="the new run's --our-scene-dir (manifest bytes)")
    args = ap.parse_args()
    rows = ["| scene | budget | best peer | stored auto | today | today - stored | today - best peer | fill | bytes |",
            "|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    d_peer, d_old_peer, d_stored = [], [], []
    for name in SCENES:
        npath = os.path.join(args.new_dir, f"{name}.json")
        if not os.path.exists(npath):
            continue
        new = json.load(open(npath))
        old = json.load(open(os.path.join(args.old_dir, f"{name}.json")))
        old_ours = {r["budget"]: r for r in old["ours"]}
        manifest = 0
        if args.manifest_dir:
            manifest = os.path.getsize(os.path.join(args.manifest_dir, name, "manifest.msgpack"))
        for frac, r in zip(new["budgets"], new["ours"], strict=False):
            nb = r["budget"]
            peer, who = best_peer(new, nb)
            o = old_ours.get(nb)
            today = r["psnr_mean"]
            fills = [d / nb for d in r["splats_drawn_per_view"]]
            byte_ratio = (r["bytes_downloaded_mean"] - manifest) / r["drawn_tile_bytes_mean"]
            diff_old = today - o["psnr_mean"] if o else None
            diff_peer = today - peer if peer is not None else None
            if diff_peer is not None:
                d_peer.append(diff_peer)
                if o:
                    d_old_peer.append(o["psnr_mean"] - peer)
            if diff_old is not None:
                d_stored.append(diff_old)
            rows.append(f"| {name} | {nb:,} ({frac * 100:g} %) | {peer:.2f} ({who}) | "
                        f"{o['psnr_mean']:.2f} | {today:.2f} | {diff_old:+.2f} | {diff_peer:+.2f} | "
                        f"{min(fills):.3f}-{max(fills):.3f} | {byte_ratio:.2f} |")
    print("\n".join(rows))
    if d_peer:
        print(f"\npoints: {len(d_peer)}; today - best peer: median {statistics.median(d_peer):+.2f} dB, "
              f"range {min(d_peer):+.2f} to {max(d_peer):+.2f}, {sum(d >= 1 for d in d_peer)} points >= +1 dB; "
              f"stored auto - best peer on the same points: median {statistics.median(d_old_peer):+.2f}, "
              f"{sum(d >= 1 for d in d_old_peer)} points >= +1 dB; today - stored: median "
              f"{statistics.median(d_stored):+.2f} (range {min(d_stored):+.2f} to {max(d_stored):+.2f}, "
              f"{sum(d > 0 for d in d_stored)} of {len(d_stored)} up)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
