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

# preset -> the formats it stands for (position, rotation, scale, color, sh, SH codebook on?)
PROPOSED = {
    "very-high": ("f32x4", "f32x4", "f32x4", "f32x4", "f32x4", False),
    "high": ("f16x4", "norm10_2", "norm11", "f16x4", "norm11", False),
    "medium": ("norm11", "norm10_2", "norm11", "norm8x4", "norm565", False),
    "medium-low": ("norm11", "norm8x4", "norm8x4", "norm8x4", "norm565", True),
    "low-plus": ("norm8x4", "norm8x4", "norm8x4", "norm8x4", "norm565", True),
    "low": ("norm8x4", "norm565", "norm8x4", "norm8x4", "norm565", True),
    "very-low": ("norm8x4", "norm565", "norm565", "bc7", "norm565", True),
}
TODAY = {"low": ("norm8x4", "norm565", "norm8x4", "bc7", "norm565", True)}


def key(row: dict, sh_degree: int) -> tuple:
    f = row["formats"]
    codebook = bool(row.get("sh_codebook_entries")) if sh_degree > 0 else True
    auto = row.get("overrides", {}) is not None and "sh_codebook" not in str(row.get("label", ""))
    return (f["position"], f["rotation"], f["scale"], f["color"], f["sh"] if sh_degree > 0 else "norm565",
            codebook), auto


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
                # codebook sizes other than auto are separate points, not the presets
                if row["kind"] == "variant" and any(k in row["label"] for k in ("cb", "vq1024", "vq4096", "vq256")):
                    continue
                (k, _) = key(row, report["input"]["sh_degree"])
                s["rows"][k] = row
    lines = []
    for name, s in scenes.items():
        sh = s["input"]["sh_degree"]
        lines += [f"**{name}** ({s['input']['splats']:,} splats, SH{sh})", "",
                  "| preset | B/splat (transport) | B/splat today | PSNR dB (worst) |", "|---|---|---|---|"]
        points = {}
        for preset, formats in PROPOSED.items():
            f = formats if sh > 0 else formats[:4] + ("norm565", True)
            row = s["rows"].get(f)
            if row is None and sh == 0:
                row = s["rows"].get(formats[:4] + ("norm565", False))
            if row is None:
                lines.append(f"| {preset} | not measured | | |")
                continue
            psnr = row["psnr_mean"]
            points[preset] = (row["transport_disk_bytes_per_splat"], psnr if psnr is not None else float("inf"))
            lines.append(f"| {preset} | {row['transport_disk_bytes_per_splat']:.2f} | "
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
