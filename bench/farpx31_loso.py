#!/usr/bin/env python3
"""Leave-one-scene-out choice of the viewing scale above the first merged level (issue 31, branch `farpx31`;
BENCHMARKS.md, "A viewing scale growing with the level").

Reads bench/probe_statue31.py's `--json` files (one per scene, the same variants, `base` among them) and prints,
per variant, each level's PSNR change against `base` (the encoder's rule) by how many levels it lies above the first
merged one, then the leave-one-scene-out choice: for each scene, the variant with the largest mean change over the
other scenes' levels among those that lose at most --max-loss dB at every level of those scenes (`base` always
qualifies), judged on the held-out scene.

    python bench/farpx31_loso.py bench/results/farpx31/probe_*.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys


def level_changes(doc: dict) -> dict[str, dict[int, float]]:
    """{variant: {levels above the first merged one: PSNR change against base}} (the first merged level, 0, is the
    largest level the probe drew, about 50 % of the scene)."""
    base = {r["level"]: r["psnr"] for r in doc["variants"]["base"]}
    first = max(base)
    return {v: {first - r["level"]: round(r["psnr"] - base[r["level"]], 2) for r in rows if r["level"] in base}
            for v, rows in doc["variants"].items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("probes", nargs="+")
    ap.add_argument("--max-loss", type=float, default=0.2)
    args = ap.parse_args(argv)
    docs = [json.load(open(p)) for p in args.probes]
    changes = {d["scene"]: level_changes(d) for d in docs}
    variants = list(docs[0]["variants"])
    scenes = list(changes)
    print("| variant | " + " | ".join(scenes) + " | mean | min |")
    print("|---|" + "---|" * (len(scenes) + 2))
    for v in variants:
        cells, every = [], []
        for s in scenes:
            by_k = changes[s].get(v, {})
            ks = sorted(k for k in by_k if k > 0)
            cells.append(" ".join(f"{by_k[k]:+.2f}" for k in ks))
            every += [by_k[k] for k in ks]
        print(f"| {v} | " + " | ".join(cells) + f" | {statistics.mean(every):+.2f} | {min(every):+.2f} |")

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
