"""Issue 32: a position step from the splats' size (TileStep.per_size), chosen leave-one-statue-out against SOG.

`probes_possize/merge_rgb` holds the same probes with SH0's colour palette merged pairwise
(bench/palette_merge_probe.py, MERGE=color:0), where the rule holds held out on all seven.
TileStep.per_size and eval_probe's `pos_k=` were taken out after the measurement (BENCHMARKS.md, "A position step
from the splats' size"); they are in commit 7a03e24 (`git show 7a03e24`), which the reports were made with.

    python bench/pos_size_rule.py REPORT_DIR [REPORT_DIR ...] [--peers bench/results/eval_real] [--stats SCENE ...]

Each REPORT_DIR holds `k_statue-<name>.json`, `bench/eval_probe.py` reports (one tile, the eval's cameras) with variants
`probe-palkK`: `medium-low-12bit,scale=pal8x4,color=pal8x4,pos_k=K,transport=keyed`, i.e. scene palettes, keyed
positions on a step of the tile's median splat size (largest axis of exp(log scale)) / K. The SOG point of each
statue is the `st-sog` row of `<peers>/statue-<name>.json` (its size, renderer and cameras are checked against the
report's). Met: at most 0.90 of SOG's bytes at its PSNR or more.

For each statue held out, K is chosen on the other six: the K of the grid that meets the most of them, ties by the
largest least PSNR margin among them (`margin`; a K missing one by bytes counts as -99 dB there) or by the fewest
bytes (`fewest`: the smallest K, as the round before chose G); the held-out statue's result at that K is its row.
`--what-if-smaller` uses `margin`. `--stats SCENE ...` prints, per scene file, the median chunk extent E (the largest
axis of each 256-splat chunk in Morton order, one tile), the median splat size and the levels E / size x K that a
K gives the median chunk (the equivalent fixed G).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

STATUES = ("massa", "angel-kneeling", "angel", "angel-with-candlestick", "narcissus", "st-peter", "trumpet")


def load(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def size_ratio(path: str) -> tuple[int, float, float]:
    """(splats, median chunk extent E, median splat size) of a scene as one tile."""
    from splatstream.format.layout import CHUNK_SIZE, morton_order
    from splatstream.io import read_gaussians

    g = read_gaussians(path)
    p = g.positions[morton_order(g.positions)]
    full = len(p) // CHUNK_SIZE * CHUNK_SIZE
    c = p[:full].reshape(-1, CHUNK_SIZE, 3)
    extent = float(np.median((c.max(axis=1) - c.min(axis=1)).max(axis=1)))
    sizes = np.exp(np.asarray(g.log_scales, np.float64).max(axis=1))  # the largest axis, as TileStep.per_size
    return len(p), extent, float(np.median(sizes))


def results(report_dirs: list[str], peers: str) -> dict[str, dict[int, dict]]:
    out: dict[str, dict[int, dict]] = {}
    for name in STATUES:
        for report_dir in report_dirs:
            path = os.path.join(report_dir, f"k_statue-{name}.json")
            if os.path.exists(path):
                statue(out, name, load(path), load(os.path.join(peers, f"statue-{name}.json")))
    return out


def statue(out: dict[str, dict[int, dict]], name: str, rep: dict, ref: dict) -> None:
    """One statue's report `rep` against the peers' report `ref` (the same cameras, size and renderer)."""
    for key in ("cameras", "size", "renderer"):
        if rep[key] != ref[key]:
            raise SystemExit(f"{name}: {key} differs from the peers' report")
    sog = next(r for r in ref["rows"] if r["label"] == "st-sog")
    for r in rep["rows"]:
        m = re.fullmatch(r"probe-palk(\d+)", r["label"])
        if m:
            out.setdefault(name, {})[int(m.group(1))] = {
                "ratio": r["disk_bytes"] / sog["disk_bytes"], "db": r["psnr_mean"] - sog["psnr_mean"],
                "bps": r["disk_bytes_per_splat"], "psnr": r["psnr_mean"],
                "sog": (sog["disk_bytes_per_splat"], sog["psnr_mean"])}


def met(v: dict) -> bool:
    return v["ratio"] <= 0.90 and v["db"] >= 0


def choose(res: dict[str, dict[int, dict]], names: list[str], rule: str = "margin") -> tuple[int, int, float]:
    """(K, statues met, least margin) over `names`: the K meeting the most, then with rule `margin` the largest
    least margin (a K missing one by bytes counts -99 dB there), with `fewest` the smallest K (the fewest bytes:
    the round before's choice of G)."""
    ks = sorted(set.intersection(*(set(res[n]) for n in names)))

    def score(k: int) -> tuple[int, float]:
        return (sum(met(res[n][k]) for n in names),
                min(res[n][k]["db"] if res[n][k]["ratio"] <= 0.90 else -99.0 for n in names))
    if rule == "fewest":
        most = max(score(k)[0] for k in ks)
        k = min(k for k in ks if score(k)[0] == most)
    else:
        k = max(ks, key=score)
    return (k, *score(k))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("report_dirs", nargs="*")
    ap.add_argument("--peers", default="bench/results/eval_real")
    ap.add_argument("--stats", nargs="+", metavar="SCENE")
    ap.add_argument("--what-if-smaller", type=float, nargs="+", metavar="FRACTION",
                    help="the held-out count were every variant this fraction smaller (0.01: 1 %% fewer bytes)")
    args = ap.parse_args()
    if args.stats:
        print("| scene | splats | median chunk extent E | median splat size | E / size | G at K = 68 / 72 / 80 |")
        print("|---|---|---|---|---|---|")
        for path in args.stats:
            n, e, s = size_ratio(path)
            gs = " / ".join(f"{min(4095.0, k * e / s):.0f}" for k in (68, 72, 80))
            label = os.path.basename(os.path.dirname(path)) if path.endswith("full.ply") else os.path.basename(path)
            print(f"| {label} | {n:,} | {e:.4f} | {s:.5f} | {e / s:.1f} | {gs} |")
        if not args.report_dirs:
            return
    res = results(args.report_dirs, args.peers)
    names = [n for n in STATUES if n in res]
    ks = sorted(set.intersection(*(set(res[n]) for n in names)))
    print("| statue (SOG B/splat, dB) | " + " | ".join(f"K = {k}" for k in ks) + " |")
    print("|---|" + "---|" * len(ks))
    for n in names:
        sog = res[n][ks[0]]["sog"]
        cells = [f"{res[n][k]['ratio']:.3f}, {res[n][k]['db']:+.2f}{' met' if met(res[n][k]) else ''}" for k in ks]
        print(f"| {n} ({sog[0]:.2f}, {sog[1]:.2f}) | " + " | ".join(cells) + " |")
    print("| met | " + " | ".join(f"{sum(met(res[n][k]) for n in names)} of {len(names)}" for k in ks) + " |")
    print()
    for rule in ("margin", "fewest"):
        print(f"\nK chosen on the other six by `{rule}` (choose()):\n")
        print("| held out | K | the six at that K | held out: B/splat, dB | ratio to SOG, dB | result |")
        print("|---|---|---|---|---|---|")
        held = 0
        for h in names:
            k, count, margin = choose(res, [n for n in names if n != h], rule)
            v = res[h][k]
            held += met(v)
            print(f"| {h} | {k} | {count} of {len(names) - 1} met (least margin {margin:+.2f} dB) | {v['bps']:.2f} B, "
                  f"{v['psnr']:.2f} dB | {v['ratio']:.3f}, {v['db']:+.2f} | {'met' if met(v) else 'missed'} |")
        print(f"\nHeld out (`{rule}`): met on {held} of {len(names)}.")
    k, count, margin = choose(res, names)
    print(f"Chosen on all {len(names)}: K = {k}, {count} met (least margin {margin:+.2f} dB).")
    for x in args.what_if_smaller or ():
        scaled = {n: {k: {**v, "ratio": v["ratio"] * (1 - x)} for k, v in res[n].items()} for n in names}
        rows = []
        for h in names:
            k, _, _ = choose(scaled, [n for n in names if n != h])
            v = scaled[h][k]
            rows.append(f"{h} K = {k}: {v['ratio']:.3f}, {v['db']:+.2f} {'met' if met(v) else 'missed'}")
        print(f"What if {x:.1%} smaller: held out met on {sum(r.endswith(' met') for r in rows)} of {len(names)}: "
              + "; ".join(rows))


if __name__ == "__main__":
    main()
