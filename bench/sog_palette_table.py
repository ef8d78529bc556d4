"""Issue 32: palette planes (pal8x4) plus coarser positions against SOG on the statue scans, from eval reports.

    python bench/sog_palette_table.py REPORT_DIR [--tuned massa,angel-kneeling] [--peers bench/results/eval_real]

REPORT_DIR holds `pal_statue-<name>.json` (`bench/eval_probe.py` reports with variants `probe-palG`: medium-low-12bit
with `scale=pal8x4,color=pal8x4,pos_g=G`, and `probe-ml12`); the SOG point of each statue is the `st-sog` row of
`<peers>/statue-<name>.json` (the round's eval, same cameras, size and renderer: checked here). For every G it prints
each statue's ratio of bytes to SOG's and the PSNR margin; the G chosen is the one with the fewest bytes at which
every *tuned* statue is at or above SOG's PSNR at <= 0.90 of its bytes (if any), and the table says whether the
other statues (held out) are too.
"""
from __future__ import annotations

import argparse
import json
import os

STATUES = ("massa", "angel-kneeling", "angel", "angel-with-candlestick", "narcissus", "st-peter", "trumpet")


def load(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def rows(report: dict) -> dict[str, tuple[float, float]]:
    return {r["label"]: (r["disk_bytes_per_splat"], r["psnr_mean"]) for r in report["rows"]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("reports")
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
        for key in ("size", "renderer"):
            if rep[key] != peer[key]:
                raise SystemExit(f"{s}: {key} differs from the peer report ({rep[key]} against {peer[key]})")
        if rep["cameras"] != peer["cameras"]:
            raise SystemExit(f"{s}: cameras differ from the peer report")
        data[s] = rows(rep)
        sog[s] = rows(peer)["st-sog"]
    labels = sorted({k for r in data.values() for k in r if k.startswith("probe-pal")}, key=lambda k: int(k[9:]))
    print("| statue | SOG B/splat, dB | " + " | ".join(k[6:] for k in labels) + " | ml12 |")
    print("|---|---|" + "---|" * (len(labels) + 1))
    for s, r in data.items():
        b0, p0 = sog[s]
        cells = []
        for k in labels + ["probe-ml12"]:
            if k not in r:
                cells.append("")
                continue
            b, p = r[k]
            ok = b <= 0.90 * b0 and p >= p0
            cells.append(f"{b:.2f} B, {p:.2f} dB: {b / b0:.3f}, {p - p0:+.2f}{' met' if ok else ''}")
        print(f"| {s}{' (tuned)' if s in tuned else ' (held out)'} | {b0:.2f} B, {p0:.2f} dB | " + " | ".join(cells)
              + " |")
    chosen = None
    for k in labels:
        if all(k in data[s] and data[s][k][0] <= 0.90 * sog[s][0] and data[s][k][1] >= sog[s][1]
               for s in tuned if s in data):
            chosen = k
            break
    if chosen is None:
        print("\nno G meets SOG at <= 0.90 of its bytes on every tuned statue")
        return
    held = [s for s in data if s not in tuned]
    met = [s for s in held if data[s][chosen][0] <= 0.90 * sog[s][0] and data[s][chosen][1] >= sog[s][1]]
    print(f"\nchosen on {', '.join(tuned)}: {chosen}; held out met: {len(met)} of {len(held)} ({', '.join(met)})")


if __name__ == "__main__":
    main()
