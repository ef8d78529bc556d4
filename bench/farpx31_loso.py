#!/usr/bin/env python3
"""Leave-one-scene-out choice of the viewing scale above the first merged level (issue 31, branch `farpx31`;
BENCHMARKS.md, "A viewing scale growing with the level").

Reads bench/probe_statue31.py's `--json` files (one per scene, the same variants, `base` among them) and prints,
per variant, each level's PSNR change against `base` (the encoder's rule) by how many levels it lies above the first
merged one, then the leave-one-scene-out choice: for each scene, the variant with the largest mean change over the
other scenes' levels among those that lose at most --max-loss dB at every level of those scenes (`base` always
qualifies), judged on the held-out scene.

    python bench/farpx31_loso.py bench/results/farpx31/probe_*.json

With --cuts TODAY NEW...: instead the real streaming cut (bench/lod_vs_peers.py JSONs, one directory per rule):
per scene and budget the best peer, TODAY's PSNR and each NEW rule's change against it, then a summary by budget.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys


def level_changes(doc: dict) -> dict[str, dict[int, float]]:
    """{variant: {levels above the first merged one: PSNR change against base}} (the first merged level, 0, is the
    largest level the probe drew, about 50 % of the scene)."""
    base = {r["level"]: r["psnr"] for r in doc["variants"]["base"]}
    first = max(base)
    return {v: {first - r["level"]: round(r["psnr"] - base[r["level"]], 2) for r in rows if r["level"] in base}
            for v, rows in doc["variants"].items()}


def cuts(today_dir: str, new_dirs: list[str]) -> None:
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from lod_vs_peers import SCENES
    from lod_vs_peers_compare import best_peer

    def ours(path: str) -> dict[int, float]:
        return {r["budget"]: r["psnr_mean"] for r in json.load(open(path))["ours"]}

    names = [os.path.basename(d.rstrip("/")) for d in new_dirs]
    print("| scene | budget | best peer | today | " + " | ".join(f"{n} - today" for n in names)
          + " | " + " | ".join(f"{n} - best peer" for n in names) + " |")
    print("|---|---:|---:|---:|" + "---:|" * (2 * len(names)))
    rows = []  # (budget index, today - peer, [new - today], [new - peer])
    for scene in SCENES:
        paths = [os.path.join(d, f"{scene}.json") for d in [today_dir, *new_dirs]]
        if not all(os.path.exists(p) for p in paths):
            continue
        res = json.load(open(paths[0]))
        today, news = ours(paths[0]), [ours(p) for p in paths[1:]]
        for i, budget in enumerate(sorted(today)):
            peer, who = best_peer(res, budget)
            d_new = [n[budget] - today[budget] for n in news]
            d_peer = [n[budget] - peer for n in news]
            rows.append((i, today[budget] - peer, d_new, d_peer))
            print(f"| {scene} | {budget:,} | {peer:.2f} ({who}) | {today[budget]:.2f} | "
                  + " | ".join(f"{d:+.2f}" for d in d_new) + " | " + " | ".join(f"{d:+.2f}" for d in d_peer) + " |")
    print()
    for j, name in enumerate(names):
        for i, label in enumerate(["2 %", "6 %", "25 %", "50 %", "all"]):
            sel = [r for r in rows if r[0] == i or label == "all"]
            ch = [r[2][j] for r in sel]
            print(f"{name} {label}: change median {statistics.median(ch):+.2f} ({min(ch):+.2f} to {max(ch):+.2f}, "
                  f"{sum(c > 0.005 for c in ch)} of {len(ch)} up); over the best peer median "
                  f"{statistics.median(r[1] for r in sel):+.2f} -> {statistics.median(r[3][j] for r in sel):+.2f}, "
                  f"at least 1 dB above {sum(r[1] >= 1 for r in sel)} -> {sum(r[3][j] >= 1 for r in sel)}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("probes", nargs="+")
    ap.add_argument("--max-loss", type=float, default=0.2)
    ap.add_argument("--cuts", action="store_true", help="PROBES are lod_vs_peers result directories: TODAY NEW...")
    args = ap.parse_args(argv)
    if args.cuts:
        cuts(args.probes[0], args.probes[1:])
        return 0
    docs = [json.load(open(p)) for p in args.probes]
    changes = {d["scene"]: level_changes(d) for d in docs}
    variants = list(docs[0]["variants"])
    scenes = list(changes)
    # One row per scene, one column per variant other than base: the change at k = 1, 2, ... (25 %, 12.5 %, ...).
    others = [v for v in variants if v != "base"]
    print("| scene | " + " | ".join(others) + " |")
    print("|---|" + "---|" * len(others))
    every: dict[str, list[float]] = {v: [] for v in others}
    for s in scenes:
        cells = []
        for v in others:
            by_k = changes[s].get(v, {})
            ks = sorted(k for k in by_k if k > 0)
            cells.append(" ".join(f"{by_k[k]:+.2f}" for k in ks))
            every[v] += [by_k[k] for k in ks]
        print(f"| {s} | " + " | ".join(cells) + " |")
    print("| mean / min / levels below -0.2 dB | " + " | ".join(
        f"{statistics.mean(every[v]):+.2f} / {min(every[v]):+.2f} / {sum(c < -0.2 for c in every[v])}" for v in others)
        + " |")

    def score(v: str, among: list[str]) -> tuple[float, float]:
        vals = [c for s in among for k, c in changes[s].get(v, {}).items() if k > 0]
        return statistics.mean(vals), min(vals)

    print("\nleave one scene out (chosen on the other scenes: largest mean change, none below "
          f"-{args.max_loss} dB):")
    print("| held out | chosen | its mean / min on the others | on the held-out scene, per level k = 1.. | mean |")
    print("|---|---|---|---|---:|")
    for s in scenes:
        others = [o for o in scenes if o != s]
        ok = [v for v in variants if v == "base" or score(v, others)[1] >= -args.max_loss]
        best = max(ok, key=lambda v: score(v, others)[0])
        mean, low = score(best, others)
        held = changes[s][best]
        ks = sorted(k for k in held if k > 0)
        print(f"| {s} | {best} | {mean:+.2f} / {low:+.2f} | " + " ".join(f"{held[k]:+.2f}" for k in ks)
              + f" | {statistics.mean(held[k] for k in ks):+.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
