"""The pictures of the cells whose cut moved with format 1.16 (issue 31, branch psnr16): today's default encode and
client (format 1.16 + the root, then the cut) against the stored default rows the README's "29 of 48" comes from
(bench/results/lod_vs_peers_farpx31_g15c16), per scene and budget; the cut of each view against those rows and
against box16's 1.15 ("before") and 1.16 ("after", main's client before rootcut31) runs of the same cameras.

    python bench/results/psnr16/compare.py [--manifest-dir /tmp/psnr16_ours] > bench/results/psnr16/compare.md

"best peer": the higher of splat-transform's level and Spark's better drawing (inflate or clamp), as
bench/lod_vs_peers_compare.py; "fill": splats drawn / budget, lowest and highest view; "x": bytes downloaded over the
drawn tiles' bytes, mean of the views, the root manifest file included (the stored rows were a 1.10 manifest, so
their x is not comparable in the manifest's share); in brackets today's without the manifest file (--manifest-dir).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.dirname(HERE)
sys.path.insert(0, os.path.dirname(RESULTS))  # bench/
from eval_merge import same_cameras  # noqa: E402
from lod_vs_peers import SCENES  # noqa: E402
from lod_vs_peers_compare import best_peer  # noqa: E402

STORED = os.path.join(RESULTS, "lod_vs_peers_farpx31_g15c16")
BOX16 = os.path.join(RESULTS, "box16")


def cuts_np(path: str) -> dict[int, list[frozenset]]:
    """budget -> per-view drawn tile ids of a bench/small_budget_bytes.py JSON."""
    if not os.path.exists(path):
        return {}
    return {r["budget"]: [frozenset(v["draw"]) for v in r["views"]] for r in json.load(open(path))["rows"]}


def fetched_np(path: str) -> dict[int, float]:
    """budget -> bytes downloaded less the root manifest file, mean of the views (small_budget_bytes.py JSON)."""
    if not os.path.exists(path):
        return {}
    return {r["budget"]: statistics.mean(v["downloaded"] - v["manifest"] for v in r["views"])
            for r in json.load(open(path))["rows"]}


def moved(a: list[frozenset], b: list[frozenset] | None) -> str:
    if not b:
        return "?"
    m = [str(i) for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y]
    return "same" if not m else "v" + ",".join(m)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--new-dir", default=HERE)
    ap.add_argument("--manifest-dir", default=None)
    args = ap.parse_args()
    rows = ["| scene | budget | best peer | PSNR stored -> today (change) | SSIM stored -> today | today - best peer "
            "(stored) | fill stored -> today | x stored -> today (no manifest) | cut vs stored / 1.15 / 1.16 | "
            "fetched without the manifest, box16 1.16 -> today |",
            "|---|---:|---:|---|---|---|---|---|---|---|"]
    margins_new, margins_old, changes, detail = [], [], [], []
    for name in SCENES:
        npath, spath = os.path.join(args.new_dir, f"{name}.json"), os.path.join(STORED, f"{name}.json")
        if not os.path.exists(npath):
            continue
        new, old = json.load(open(npath)), json.load(open(spath))
        assert same_cameras(new["cameras"], old["cameras"]), name
        mbytes = 0
        if args.manifest_dir:
            mbytes = os.path.getsize(os.path.join(args.manifest_dir, name, "manifest.msgpack"))
        before = cuts_np(os.path.join(BOX16, "before", f"{name}_np.json"))
        after = cuts_np(os.path.join(BOX16, "after", f"{name}_np.json"))
        fetched = fetched_np(os.path.join(BOX16, "after", f"{name}_np.json"))
        olds = {r["budget"]: r for r in old["ours"]}
        for b, nb in zip(new["budgets"], new["budget_splats"], strict=True):
            o = next(r for r in new["ours"] if r["budget"] == nb)
            s = olds[nb]
            peer, who = best_peer(new, nb)
            d, dold = o["psnr_mean"] - peer, s["psnr_mean"] - peer
            margins_new.append((name, b, d))
            margins_old.append((name, b, dold))
            changes.append(o["psnr_mean"] - s["psnr_mean"])
            cut = [frozenset(v) for v in o["drawn_tile_ids_per_view"]]
            scut = [frozenset(v) for v in s["drawn_tile_ids_per_view"]]

            def fill(r):
                f = [x / r["budget"] for x in r["splats_drawn_per_view"]]
                return f"{min(f) * 100:.1f}-{max(f) * 100:.1f} %"

            x_new = o["bytes_downloaded_mean"] / o["drawn_tile_bytes_mean"]
            x_nom = (o["bytes_downloaded_mean"] - mbytes) / o["drawn_tile_bytes_mean"]
            x_old = s["bytes_downloaded_mean"] / s["drawn_tile_bytes_mean"]
            rows.append(
                f"| {name} | {b * 100:g} % ({nb:,}) | {peer:.2f} ({who}) | {s['psnr_mean']:.3f} -> "
                f"{o['psnr_mean']:.3f} ({o['psnr_mean'] - s['psnr_mean']:+.3f}) | {s['ssim_mean']:.4f} -> "
                f"{o['ssim_mean']:.4f} | **{d:+.2f}** ({dold:+.2f}) | {fill(s)} -> {fill(o)} | {x_old:.2f} -> "
                f"{x_new:.2f} ({x_nom:.2f}) | {moved(cut, scut)} / {moved(cut, before.get(nb))} / "
                f"{moved(cut, after.get(nb))} | "
                + (f"{fetched[nb]:,.0f} -> {o['bytes_downloaded_mean'] - mbytes:,.0f} "
                   f"({(o['bytes_downloaded_mean'] - mbytes) / fetched[nb]:.2f}x) |" if nb in fetched and mbytes
                   else "- |"))
            for i, (x, y) in enumerate(zip(cut, scut, strict=True)):
                if x != y:
                    detail.append(f"| {name} | {b * 100:g} % | {i} | {s['splats_drawn_per_view'][i]:,} -> "
                                  f"{o['splats_drawn_per_view'][i]:,} | {s['psnr_per_view'][i]:.3f} -> "
                                  f"{o['psnr_per_view'][i]:.3f} ({o['psnr_per_view'][i] - s['psnr_per_view'][i]:+.3f})"
                                  f" | {s['ssim_per_view'][i]:.4f} -> {o['ssim_per_view'][i]:.4f} | "
                                  f"{sorted(y - x)} -> {sorted(x - y)} |")
    print("\n".join(rows))
    print("\nViews whose cut differs from the stored rows' (tiles only in the stored cut -> only in today's):\n")
    print("| scene | budget | view | drawn stored -> today | PSNR stored -> today | SSIM | tiles |")
    print("|---|---:|---:|---|---|---|---|")
    print("\n".join(detail))
    n1 = sum(d >= 1.0 for _, _, d in margins_new)
    o1 = sum(d >= 1.0 for _, _, d in margins_old)
    print(f"\ncells: {len(margins_new)}; PSNR today - stored: {min(changes):+.3f} to {max(changes):+.3f} dB "
          f"(median {statistics.median(changes):+.3f}); >= 1 dB above the best peer: stored {o1}, today {n1}; "
          f"median margin stored {statistics.median(d for *_, d in margins_old):+.2f}, "
          f"today {statistics.median(d for *_, d in margins_new):+.2f}")
    below = [f"{n} {b * 100:g} % ({d:+.2f})" for n, b, d in margins_new if d < 0]
    print("below the best peer today: " + ", ".join(below))
    near = [f"{n} {b * 100:g} % ({d:+.2f})" for n, b, d in margins_new if 0 <= d < 1.0]
    print("0 to 1 dB above today: " + ", ".join(near))
    return 0


if __name__ == "__main__":
    sys.exit(main())
