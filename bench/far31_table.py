#!/usr/bin/env python3
"""far31's tables (issue 31, the CPU refinement's far cameras): per scene and budget the default encode, the CPU
refinement before far31 and with its far cameras, and the best peer; then the frames without a budget (views moved
back 2-32x) of the same three encodes.

    cd bench && python far31_table.py \
        --default results/lod_vs_peers_farpx31_g15c16 --default results/lod_vs_peers_heldout \
        --before results/cpurefine31/refined --before results/cpurefine31/refined_rest \
        --before results/cpurefine31/refined_heldout --before results/cpurefine31/refined_heldout_small \
        --after results/far31/budgets --far-before results/cpurefine31/far_frames_rest.json \
        --far-after results/far31/far_frames.json --markdown results/far31/table.md

Budget rows: every scene with an --after JSON (lod_vs_peers' `ours` rows); best peer as cpurefine31_table.best_peer
(from the default JSON). Far rows: --far-before is probe_lod28_far's default ("before") -> refined ("after") run,
--far-after its refined ("before") -> far31 ("after") run of the same cameras; per factor the mean PSNR (dB of the
mean MSE over the views) and the views below the default encode's.
"""
from __future__ import annotations

import argparse
import json
import os

from cpurefine31_table import _f, best_peer, load_scene
from lod_vs_peers import SCENES


def budget_rows(name: str, default_dirs: list[str], before_dirs: list[str], after_dirs: list[str]) -> list[str]:
    loaded, before = load_scene(name, default_dirs, after_dirs), load_scene(name, default_dirs, before_dirs)
    if loaded is None:
        return []
    default, after = loaded
    old = {r["budget"]: r["psnr_mean"] for r in default["ours"]}
    frac = dict(zip(default["budget_splats"], default["budgets"], strict=True))
    prev = before[1] if before else {}
    out = []
    order = {n: i for i, n in enumerate(default["budget_splats"])}
    for i, n in enumerate(sorted(after, key=lambda n: order.get(n, len(order)))):
        peer, who = best_peer(default, n)
        a = after[n]["psnr_mean"]
        b = prev[n]["psnr_mean"] if n in prev else None
        f = frac.get(n, 2)
        label = f"{100 * f:g} % ({n:,})" if f <= 1 else f"{n:,}"
        out.append(f"| {name if i == 0 else ''} | {label} | {_f(old.get(n))} | {_f(b)} | {_f(a)} | "
                   f"{_f(a - b if b is not None else None, True)} | {_f(peer)} ({who}) | "
                   f"**{_f(a - peer if peer is not None else None, True)}** "
                   f"({_f(b - peer if b is not None and peer is not None else None, True)}) |")
    return out


def far_rows(before: dict, after: dict) -> list[str]:
    """One row per scene and factor present in both runs."""
    prev = {(r["scene"], r["factor"]): r for r in before["rows"]}
    out = []
    for r in after["rows"]:
        p = prev.get((r["scene"], r["factor"]))
        if p is None:
            continue
        default, mid, new = p["before"], r["before"], r["after"]
        lost_mid = sum(m < d for m, d in zip(mid["psnr_views"], default["psnr_views"], strict=True))
        lost_new = sum(m < d for m, d in zip(new["psnr_views"], default["psnr_views"], strict=True))
        worst = min(m - d for m, d in zip(new["psnr_views"], default["psnr_views"], strict=True))
        out.append(f"| {r['scene']} | {r['factor']:g}x | {min(new['drawn_splats']):,}-{max(new['drawn_splats']):,} | "
                   f"{default['psnr']:.2f} | {mid['psnr']:.2f} | {new['psnr']:.2f} | "
                   f"{new['psnr'] - mid['psnr']:+.2f} | {mid['psnr'] - default['psnr']:+.2f} ({lost_mid}) | "
                   f"**{new['psnr'] - default['psnr']:+.2f}** ({lost_new}; worst view {worst:+.2f}) |")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--default", action="append", required=True)
    ap.add_argument("--before", action="append", required=True)
    ap.add_argument("--after", action="append", required=True)
    ap.add_argument("--far-before", action="append", default=[])
    ap.add_argument("--far-after", action="append", default=[])
    ap.add_argument("--markdown", required=True)
    args = ap.parse_args(argv)
    lines = ["| scene | budget | default | refined before far31 | with far cameras | change | best peer | "
             "margin (before far31's) |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in dict.fromkeys([*SCENES, "playbot"]):  # playbot once, whether SCENES names it or not
        lines += budget_rows(name, args.default, args.before, args.after)
    if args.far_before:
        lines += ["", "| scene | factor | splats drawn | default | refined before far31 | with far cameras | change | "
                  "before far31 - default (views below) | far31 - default (views below) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        befores = [json.load(open(p)) for p in args.far_before]
        merged_before = {"rows": [r for b in befores for r in b["rows"]]}
        for p in args.far_after:
            lines += far_rows(merged_before, json.load(open(p)))
    os.makedirs(os.path.dirname(os.path.abspath(args.markdown)), exist_ok=True)
    with open(args.markdown, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
