"""Tables of bench/results/sh_coding.md from sh_coding_probe.py result directories (issue 32).

    python bench/sh_coding_table.py NAME=DIR ...

For each scene: every named preset's and peer's bytes and PSNR, and for every peer point the smallest named preset
at equal or higher mean PSNR with its byte ratio (goal <= 0.90, as bench/preset_dominance.py), or where none meets
it the best preset within 0.90 of the peer's bytes.
"""
from __future__ import annotations

import glob
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.format.presets import PRESETS  # noqa: E402

GOAL = 0.90
# probe labels of named presets (configs equal to the preset) -> preset name
ALIASES = {"mh": "medium-high", "ml16": "medium-low-sh16", "ml-s16i": "medium-low-sh16", "ml8": "medium-low-sh8",
           "ml-s8i": "medium-low-sh8", "lp9-s6i": "low-plus-9bit-sh6", "lp9sh6": "low-plus-9bit-sh6"}


def load(d: str) -> tuple[dict, dict]:
    presets, peers = {}, {}
    for f in glob.glob(os.path.join(d, "res_*.json")):
        r = json.load(open(f))
        name = ALIASES.get(r["label"], r["label"])
        if name in PRESETS and not f.endswith("_lod.json"):
            presets[name] = r
    for f in glob.glob(os.path.join(d, "peer_*.json")):
        r = json.load(open(f))
        peers[r["label"]] = r
    return presets, peers


def main() -> None:
    out = []
    for arg in sys.argv[1:]:
        scene, d = arg.split("=", 1)
        presets, peers = load(d)
        out.append(f"\n### {scene}\n\n| encode | B/splat | mean PSNR dB |\n|---|---:|---:|")
        for name in PRESETS:
            if name in presets:
                r = presets[name]
                out.append(f"| {name} | {r['bytes_per_splat']:.2f} | {r['psnr']:.2f} |")
        for label, r in sorted(peers.items()):
            out.append(f"| splat-transform {label} | {r['bytes_per_splat']:.2f} | {r['psnr']:.2f} |")
        out.append("\n| peer | peer B/splat | peer dB | smallest preset at >= its PSNR | ratio | goal <= 0.90 |\n"
                   "|---|---:|---:|---|---:|---|")
        for label, p in sorted(peers.items()):
            ok = sorted((r["bytes_per_splat"], n) for n, r in presets.items() if r["psnr"] >= p["psnr"])
            within = [(r["psnr"], n) for n, r in presets.items() if r["bytes_per_splat"] <= GOAL * p["bytes_per_splat"]]
            if ok:
                b, n = ok[0]
                ratio = b / p["bytes_per_splat"]
                found = f"{n} ({b:.2f} B, {presets[n]['psnr']:.2f} dB)"
            else:
                ratio, found = None, "none"
            if ratio is not None and ratio <= GOAL:
                verdict = "met"
            else:
                best = max(within) if within else None
                verdict = "**not met**: at <= 0.90 of its bytes the best is " + (
                    "none" if best is None else
                    f"{best[1]} ({presets[best[1]]['bytes_per_splat']:.2f} B, {best[0]:.2f} dB, "
                    f"{best[0] - p['psnr']:+.2f} dB)")
            out.append(f"| {label} | {p['bytes_per_splat']:.2f} | {p['psnr']:.2f} | {found} | "
                       f"{'' if ratio is None else f'{ratio:.2f}'} | {verdict} |")
    print("\n".join(out))


if __name__ == "__main__":
    main()
