"""Issue 32, scene palettes: the SOG statues with palette planes, keyed positions at G = 2047 and the LOD tree,
against SOG's point (the round's eval: the `st-sog` row of bench/results/eval_real/statue-<name>.json).

    python bench/sog_palette_lod_table.py DIR [--one-tile-psnr bench/results/eval_real/probes_pal]
        [--tuned massa,angel-kneeling]

DIR holds `lod_statue-<name>.json` (bench/eval_probe.py --lod: the PSNR of the LOD tree's full-detail leaves) and
`bytes_statue-<name>.json` (bench/sog_palette_lod.py). The one-tile rows take their PSNR from the earlier round's
eval of the same quantisation (`probe-pal2047` of `pal_statue-<name>.json`: the palettes are exact wherever they
are stored and the keyed transport only reorders texels inside a chunk). Met: at most 0.90 of SOG's bytes at its
PSNR or more. A second table, where DIR holds `lodpal_statue-<name>.json` and `bytespal_statue-<name>.json`:
palettes alone (`medium-low-12bit`'s own positions) against `medium-low-12bit`, both keyed, with the LOD tree.
"""
from __future__ import annotations

import argparse
import json
import os

STATUES = ("massa", "angel-kneeling", "angel", "angel-with-candlestick", "narcissus", "st-peter", "trumpet")


def load(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def cell(b: float, p: float, sog: tuple[float, float]) -> str:
    ratio, dp = b / sog[0], p - sog[1]
    met = " met" if ratio <= 0.90 and dp >= 0 else ""
    return f"{b:.2f} B, {p:.2f} dB ({ratio:.3f}, {dp:+.2f}{met})"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("--one-tile-psnr", default=os.path.join(os.path.dirname(__file__), "results", "eval_real",
                                                            "probes_pal"))
    ap.add_argument("--peers", default=os.path.join(os.path.dirname(__file__), "results", "eval_real"))
    ap.add_argument("--tuned", default="massa,angel-kneeling")
    args = ap.parse_args()
    tuned = args.tuned.split(",")
    print("| statue (SOG B/splat, dB) | LOD tree: leaves + manifest | leaves alone | whole tree: scene palettes / "
          "per-tile / `medium-low-12bit` keyed | one tile, scene palettes |")
    print("|---|---|---|---|---|")
    for s in STATUES:
        lod_path = os.path.join(args.dir, f"lod_statue-{s}.json")
        bytes_path = os.path.join(args.dir, f"bytes_statue-{s}.json")
        if not (os.path.exists(lod_path) and os.path.exists(bytes_path)):
            continue
        lod, by, peer = load(lod_path), load(bytes_path), load(os.path.join(args.peers, f"statue-{s}.json"))
        for key in ("size", "renderer", "cameras"):
            if lod[key] != peer[key]:
                raise SystemExit(f"{s}: {key} differs from the peer report")
        sog = next((r["disk_bytes_per_splat"], r["psnr_mean"]) for r in peer["rows"] if r["label"] == "st-sog")
        psnr = next(r["psnr_mean"] for r in lod["rows"] if r["label"] == "probe-pal2047k")
        one = load(os.path.join(args.one_tile_psnr, f"pal_statue-{s}.json"))
        psnr_one = next(r["psnr_mean"] for r in one["rows"] if r["label"] == "probe-pal2047")
        rows = by["rows"]
        r = rows["pal2047k"]
        if "pal2047k-tilepal" not in rows:  # only the LOD tree measured (a manifest change: bench/manifest_bytes.py)
            name = f"{s} ({'tuned' if s in tuned else 'held out'}) ({sog[0]:.2f}, {sog[1]:.2f})"
            print(f"| {name} | {cell(r['full_detail_b_per_splat'], psnr, sog)} | "
                  f"{cell(r['leaf_payload_b_per_splat'], psnr, sog)} | manifest {r['manifest_bytes']} B "
                  f"({r['manifest_bytes'] / by['splats']:.2f} B/splat, {r['manifest_bytes'] / r['tiles']:.0f} B a "
                  f"tile, version {r['version'][0]}.{r['version'][1]}) | |")
            continue
        tree = f"{r['tree_b_per_splat']:.2f} / {rows['pal2047k-tilepal']['tree_b_per_splat']:.2f} / " \
               f"{rows['ml12k']['tree_b_per_splat']:.2f} B"
        name = f"{s} ({'tuned' if s in tuned else 'held out'}) ({sog[0]:.2f}, {sog[1]:.2f})"
        print(f"| {name} | {cell(r['full_detail_b_per_splat'], psnr, sog)} | "
              f"{cell(r['leaf_payload_b_per_splat'], psnr, sog)} | {tree} | "
              f"{cell(rows['pal2047k-onetile']['full_detail_b_per_splat'], psnr_one, sog)} |")
    print("\n| statue | `medium-low-12bit` keyed: tree B/splat, dB | with scene palettes | with per-tile palettes |")
    print("|---|---|---|---|")
    for s in STATUES:
        lod_path = os.path.join(args.dir, f"lodpal_statue-{s}.json")
        bytes_path = os.path.join(args.dir, f"bytespal_statue-{s}.json")
        if not (os.path.exists(lod_path) and os.path.exists(bytes_path)):
            continue
        psnr = {r["label"]: r["psnr_mean"] for r in load(lod_path)["rows"]}
        rows = load(bytes_path)["rows"]
        base = rows["ml12k"]["tree_b_per_splat"]
        pal, tiles = rows["palk"]["tree_b_per_splat"], rows["palk-tilepal"]["tree_b_per_splat"]
        print(f"| {s} | {base:.2f} B, {psnr['probe-ml12k']:.2f} dB | {pal:.2f} B ({pal / base - 1:+.1%}), "
              f"{psnr['probe-palk']:.2f} dB | {tiles:.2f} B ({tiles / base - 1:+.1%}) |")


if __name__ == "__main__":
    main()
