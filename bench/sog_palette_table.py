"""Issue 32: palette planes (pal8x4) plus coarser positions against SOG on the statue scans.

    python bench/sog_palette_table.py REPORT_DIR [--bytes BYTES_DIR] [--tuned massa,angel-kneeling]
                                      [--peers bench/results/eval_real]

REPORT_DIR holds `pal_statue-<name>.json`, `bench/eval_probe.py` reports with variants `probe-palG` (medium-low-12bit
with `scale=pal8x4,color=pal8x4,pos_g=G`) and `probe-ml12` (medium-low-12bit): their PSNR. BYTES_DIR holds
`bytes_statue-<name>.json` from `bench/sog_palette_bytes.py` (disk bytes only): where given, its rows are the
columns, each with the PSNR of the report's variant of the same quantisation (`palfG` and `palG` -> `probe-palG`,
`ml12k` -> `probe-ml12`: a transport stores the same texels, so the eval's PSNR is the same). The SOG point of each
statue is the `st-sog` row of `<peers>/statue-<name>.json` (the round's eval: its size, renderer and cameras are
checked against the report's). The G chosen is the one of the `palG` columns with the fewest bytes at which every
*tuned* statue is at or above SOG's PSNR at <= 0.90 of its bytes; the last line says on how many held-out statues
the same holds.
"""
from __future__ import annotations

import argparse
import json
import os
import re

STATUES = ("massa", "angel-kneeling", "angel", "angel-with-candlestick", "narcissus", "st-peter", "trumpet")


def load(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def psnr_label(label: str) -> str:
    """The eval variant whose quantisation a bytes row shares."""
    m = re.fullmatch(r"probe-palf?(\d+)", label)
    if m:
        return f"probe-pal{m.group(1)}"
    return "probe-ml12" if label in ("probe-ml12k", "probe-ml12") else label


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("reports")
    ap.add_argument("--bytes")
    ap.add_argument("--tuned", default="massa,angel-kneeling")
    ap.add_argument("--peers", default=os.path.join(os.path.dirname(__file__), "results", "eval_real"))
    args = ap.parse_args()
    tuned = args.tuned.split(",")
    data, sog = {}, {}
    for s in STATUES:
        path = os.path.join(args.reports, f"pal_statue-{s}.json")
        if not os.path.exists(path):
            continue
        rep, peer = load(path), load(os.path.join(args.peers, f"statue-{s}.json"))
        for key in ("size", "renderer", "cameras"):
            if rep[key] != peer[key]:
                raise SystemExit(f"{s}: {key} differs from the peer report")
        psnr = {r["label"]: r["psnr_mean"] for r in rep["rows"]}
        if args.bytes:
            bpath = os.path.join(args.bytes, f"bytes_statue-{s}.json")
            if not os.path.exists(bpath):
                continue
            rows = {k: (v["disk_bytes_per_splat"], psnr[psnr_label(k)]) for k, v in load(bpath)["rows"].items()
                    if psnr_label(k) in psnr}
        else:
            rows = {r["label"]: (r["disk_bytes_per_splat"], r["psnr_mean"]) for r in rep["rows"]}
        data[s] = rows
        sog[s] = next((r["disk_bytes_per_splat"], r["psnr_mean"]) for r in peer["rows"] if r["label"] == "st-sog")
    labels = list(next(iter(data.values())))
    print("| statue | SOG B/splat, dB | " + " | ".join(k[6:] for k in labels) + " |")
    print("|---|---|" + "---|" * len(labels))
    for s, r in data.items():
        b0, p0 = sog[s]
        cells = []
        for k in labels:
            b, p = r[k]
            ok = b <= 0.90 * b0 and p >= p0
            cells.append(f"{b:.2f} B, {p:.2f} dB: {b / b0:.3f}, {p - p0:+.2f}{' **met**' if ok else ''}")
        print(f"| {s}{' (tuned)' if s in tuned else ' (held out)'} | {b0:.2f} B, {p0:.2f} dB | " + " | ".join(cells)
              + " |")
    steps = sorted((k for k in labels if re.fullmatch(r"probe-pal\d+", k)), key=lambda k: int(k[9:]))
    chosen = next((k for k in steps if all(data[s][k][0] <= 0.90 * sog[s][0] and data[s][k][1] >= sog[s][1]
                                           for s in tuned if s in data)), None)
    if chosen is None:
        print("\nno G meets SOG at <= 0.90 of its bytes on every tuned statue")
        return
    held = [s for s in data if s not in tuned]
    met = [s for s in held if data[s][chosen][0] <= 0.90 * sog[s][0] and data[s][chosen][1] >= sog[s][1]]
    print(f"\nchosen on {', '.join(tuned)}: {chosen[6:]}; held out met: {len(met)} of {len(held)}"
          f" ({', '.join(met) or 'none'})")


if __name__ == "__main__":
    main()
