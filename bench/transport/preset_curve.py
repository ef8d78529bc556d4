"""Proposed presets against the peers, per scene, from eval reports re-coded by recode_scene.py --eval.

    python bench/transport/preset_curve.py EVAL_DIR [--markdown OUT.md]

EVAL_DIR holds <scene>*.json reports (several per scene are merged; later files win on equal labels). Each proposed
preset is mapped to the report row that has its formats (PROPOSED below). For every peer point (rows of kind
`compare`) it prints the smallest proposed preset with at least the peer's mean PSNR, and the byte ratio; the goal
of issue 15 is a ratio of at most 0.90. Bytes: disk bytes per splat under the transport coding (manifest included).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
from collections import defaultdict

# preset -> (position, rotation, scale, color, sh formats, SH codebook size rule: None, "auto" or "auto16")
PROPOSED = {
    "very-high": ("f32x4", "f32x4", "f32x4", "f32x4", "f32x4", None),
    "high": ("f16x4", "norm10_2", "norm11", "f16x4", "norm11", None),
    "medium": ("norm11", "norm10_2", "norm11", "norm8x4", "norm565", None),
    "medium-low": ("norm11", "norm8x4", "norm8x4", "norm8x4", "norm565", "auto16"),
    "low-plus": ("norm8x4", "norm8x4", "norm8x4", "norm8x4", "norm565", "auto"),
    "low": ("norm8x4", "norm565", "norm8x4", "norm8x4", "norm565", "auto"),
    "very-low": ("norm8x4", "norm565", "norm565", "bc7", "norm565", "auto"),
}


def codebook_entries(rule: str | None, splats: int) -> int | None:
    """Entries the rule gives: "auto" is vq.auto_entries (a power of two near N / 64, 64..65536); "auto16" a power
    of two near N / 16, 256..65536 (the larger codebook medium-low needs on real SH3: fruit_drops 43.0 dB with 64
    entries, 46.6 dB with 256)."""
    import math

    if rule is None:
        return None
    per, low = (64, 64) if rule == "auto" else (16, 256)
    k = 2 ** int(round(math.log2(max(1.0, splats / per))))
    return int(min(65536, max(low, k)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("eval_dir")
    ap.add_argument("--markdown")
    args = ap.parse_args()
    scenes: dict[str, dict] = defaultdict(lambda: {"rows": {}, "peers": {}, "input": None})
    for path in sorted(glob.glob(os.path.join(args.eval_dir, "*.json"))):
        report = json.load(open(path))
        name = os.path.basename(report["input"]["path"])
        s = scenes[name]
        s["input"] = report["input"]
        for row in report["rows"]:
            if row["kind"] == "compare":
                s["peers"][row["label"]] = row
            elif row["kind"] in ("preset", "variant") and "transport_disk_bytes_per_splat" in row:
                f = row["formats"]
                s["rows"][(f["position"], f["rotation"], f["scale"], f["color"], f["sh"],
                           row.get("sh_codebook_entries"))] = row
    lines = []
    for name, s in scenes.items():
        sh = s["input"]["sh_degree"]
        lines += [f"**{name}** ({s['input']['splats']:,} splats, SH{sh})", "",
                  "| preset | B/splat (transport) | B/splat today | PSNR dB (worst) |", "|---|---|---|---|"]
        points = {}
        for preset, formats in PROPOSED.items():
            entries = codebook_entries(formats[5], s["input"]["splats"]) if sh > 0 else None
            candidates = [(k[5], r) for k, r in s["rows"].items() if k[:4] == formats[:4]
                          and (sh == 0 or (k[4] == formats[4] and bool(k[5]) == bool(entries)))]
            # the rule's entry count; else (a scene with fewer distinct SH rows than that, or a variant run with
            # another size) the nearest size measured, named in the table
            candidates.sort(key=lambda c: (abs((c[0] or 0) - (entries or 0)), -(c[0] or 0)))
            row = candidates[0][1] if candidates else None
            note = "" if row is None or not entries or candidates[0][0] == entries else \
                f" (codebook {candidates[0][0]}, rule {entries})"
            if row is None:
                lines.append(f"| {preset} | not measured | | |")
                continue
            psnr = row["psnr_mean"]
            points[preset] = (row["transport_disk_bytes_per_splat"], psnr if psnr is not None else float("inf"))
            lines.append(f"| {preset}{note} | {row['transport_disk_bytes_per_splat']:.2f} | "
                         f"{row['disk_bytes_per_splat']:.2f} | "
                         f"{'inf' if psnr is None else format(psnr, '.2f')} "
                         f"({'inf' if row['psnr_worst'] is None else format(row['psnr_worst'], '.2f')}) |")
        lines += ["", "| peer | B/splat | PSNR dB | best named preset at >= its PSNR | bytes ratio | goal <= 0.90 |",
                  "|---|---|---|---|---|---|"]
        for label, peer in s["peers"].items():
            ok = [(b, p, n) for n, (b, p) in points.items() if p >= peer["psnr_mean"]]
            if not ok:
                lines.append(f"| {label} | {peer['disk_bytes_per_splat']:.2f} | {peer['psnr_mean']:.2f} | none | | "
                             "NOT met |")
                continue
            b, p, n = min(ok)
            ratio = b / peer["disk_bytes_per_splat"]
            lines.append(f"| {label} | {peer['disk_bytes_per_splat']:.2f} | {peer['psnr_mean']:.2f} | {n} ({b:.2f} B, "
                         f"{p:.2f} dB) | {ratio:.2f} | {'met' if ratio <= 0.90 else 'NOT met'} |")
        lines.append("")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        open(args.markdown, "w").write(text + "\n")


if __name__ == "__main__":
    main()
