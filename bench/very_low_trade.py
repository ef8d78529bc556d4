"""`very-low`'s rotations, `norm565` or `cube565` (issue 32, cube32): each point's trade against today's
`very-low-rgb127`, s = (PSNR_R - PSNR_V) / ln(B_R / B_V), dB given up per e-fold of bytes saved (smaller is better),
from the stored reports before rotrange32 (git revision BEFORE: `norm565`) and today's (`cube565`).

    python bench/very_low_trade.py [--before b27fe68^] [--held-out NAME,...] [--markdown OUT.md] REPORT.json ...

The rule it applies is bench/results/cube32/very_low_rule.md (written before the held-out rows were tabulated).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys


def rows(text: str) -> dict[str, dict]:
    return {r["label"]: r for r in json.loads(text)["rows"] if r.get("kind") == "preset" and not r.get("overrides")}


def trade(ref: dict, v: dict) -> float:
    return (ref["psnr_mean"] - v["psnr_mean"]) / math.log(ref["disk_bytes_per_splat"] / v["disk_bytes_per_splat"])


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--before", default="b27fe68^")
    ap.add_argument("--held-out", default="")
    ap.add_argument("--markdown")
    a = ap.parse_args(argv)
    held = [s for s in a.held_out.split(",") if s]
    lines = ["| scene | `very-low-rgb127` | `very-low` norm565 | s (dB per e-fold) | `very-low` cube565 | s | better |",
             "|---|---|---|---|---|---|---|"]
    wins = {"choice": 0, "held": 0}
    counts = {"choice": 0, "held": 0}
    for path in a.reports:
        name = os.path.splitext(os.path.basename(path))[0]
        now = rows(open(path).read())
        old = rows(subprocess.run(["git", "show", f"{a.before}:{path}"], check=True, capture_output=True,
                                  text=True).stdout)
        ref, vn, vc = now["very-low-rgb127"], old["very-low"], now["very-low"]
        assert vn["formats"]["rotation"] == "norm565" and vc["formats"]["rotation"] == "cube565", name
        below = all(v["disk_bytes_per_splat"] < ref["disk_bytes_per_splat"] and v["psnr_mean"] < ref["psnr_mean"]
                    for v in (vn, vc))
        sn, sc = trade(ref, vn), trade(ref, vc)
        kind = "held" if name in held else "choice"
        counts[kind] += 1
        wins[kind] += sn < sc
        lines.append(f"| {name}{'' if kind == 'held' else ' (choice)'} | {ref['disk_bytes_per_splat']:.2f} B, "
                     f"{ref['psnr_mean']:.2f} dB | {vn['disk_bytes_per_splat']:.2f} B, {vn['psnr_mean']:.2f} dB | "
                     f"{sn:.2f} | {vc['disk_bytes_per_splat']:.2f} B, {vc['psnr_mean']:.2f} dB | {sc:.2f} | "
                     f"{'norm565' if sn < sc else 'cube565'}{'' if below else ' (not below rgb127)'} |")
    lines += ["", f"* norm565 the better trade on {wins['choice']} of {counts['choice']} choice scenes and "
              f"{wins['held']} of {counts['held']} held out"]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.markdown:
        open(a.markdown, "w").write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
