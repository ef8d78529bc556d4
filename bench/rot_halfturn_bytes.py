"""Bytes of smallest-three presets with and without the half-turn rotation gauge (issue 32, evalrefresh32).

    PYTHONPATH=. python bench/rot_halfturn_bytes.py REPORT.json [...] [--inputs DIR ...] [--presets a,b]
        --json OUT.json [--markdown OUT.md]

The half-turn gauge (rotation_canon.canonical_gauge "half-turns"; presets.PRESET_ROTATION_GAUGE) stores the same
smallest-three components in another order with the scales kept: the same texels' picture, so only the bytes can
move. Each preset is encoded twice per scene, the gauge off and on, exactly as `splatstream eval` encodes it for the
report (its cameras' up and `encode_options`, full detail without LOD: `sizes.disk`, as bench/eval_refresh_bytes.py),
and the disk bytes of both are recorded, with the half-turn encode's byte fields (`half_turns_fields`, what
bench/eval_refresh_bytes.py would write into the report's row once the preset takes the gauge). The report only
gives the scene and its options; its rows are not read. The default presets are every preset whose rotation is
smallest-three (norm10_2, norm8x4).

    PYTHONPATH=. python bench/rot_halfturn_bytes.py REPORT.json [...] --apply AB.json --presets a,b

With `--apply`, nothing is encoded: the preset rows of `--presets` in each REPORT take the byte fields of AB.json's
half-turn encode of their scene (the report's name, a `_4x384`-style suffix dropped: the bytes do not depend on the
cameras), as bench/eval_refresh_bytes.py would write them (PSNR and SSIM stay: the same picture). A row whose bytes
are neither the A/B's gauge-off nor its half-turn bytes (to MANIFEST_SLACK), or whose GPU bytes differ, stops the
script: its bytes are stale for another reason.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from eval_refresh_bytes import scene_path, write_report  # noqa: E402

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_gaussians  # noqa: E402
from splatstream.evaluate import source_version  # noqa: E402
from splatstream.format import presets as P  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402

SMALLEST_THREE = ("norm10_2", "norm8x4")
# bytes by which two encodes of the same texels may differ: the manifest records the encode's seconds
MANIFEST_SLACK = 16


def smallest_three_presets() -> list[str]:
    return [p for p, f in P.PRESETS.items() if f["rotation"] in SMALLEST_THREE]


def encoded_bytes(g, preset: str, report: dict, gauge: str | None, out: str) -> dict:
    """The byte fields (bench/eval_refresh_bytes.py's) of `preset` on `g` with the report's options and the gauge
    set as given: full detail, no LOD."""
    saved = P.PRESET_ROTATION_GAUGE.get(preset)
    P.PRESET_ROTATION_GAUGE.pop(preset, None)
    if gauge:
        P.PRESET_ROTATION_GAUGE[preset] = gauge
    try:
        opts = report["encode_options"]
        eo = EncodeOptions(preset=preset, lod=opts.get("lod", False), up=tuple(report["camera_rule"]["up"]),
                           **{k: v for k, v in opts.items() if k not in ("lod", "zstd_level")})
        if opts.get("zstd_level") is not None:
            eo.zstd_level = opts["zstd_level"]
        m = encode_gaussians(g, out, eo, source_name=report["input"]["path"])
        disk = m.bytes_on_disk
        return {"disk_bytes": disk, "disk_bytes_per_splat": round(disk / len(g), 6),
                "compression": round(report["input"]["bytes"] / disk, 6), "bytes_on_disk_total": disk,
                "leaf_bytes_on_disk": m.leaf_bytes_on_disk, "gpu_bytes": m.gpu_bytes,
                "attributes": {a: s.to_dict() for a, s in m.attributes.items()}}
    finally:
        shutil.rmtree(out, ignore_errors=True)
        P.PRESET_ROTATION_GAUGE.pop(preset, None)
        if saved:
            P.PRESET_ROTATION_GAUGE[preset] = saved


def markdown(results: list[dict], presets: list[str]) -> str:
    lines = ["| preset | scenes smaller | median | min | max | largest scene |", "|---|---|---|---|---|---|"]
    for p in presets:
        rs = [r for r in results if r["preset"] == p]
        ch = sorted(r["half_turns"] / r["off"] - 1 for r in rs)
        worst = max(rs, key=lambda r: r["half_turns"] / r["off"])
        lines.append(f"| `{p}` | {sum(c < 0 for c in ch)} of {len(ch)} | {statistics.median(ch):+.2%} | {ch[0]:+.2%} | "
                     f"{ch[-1]:+.2%} | {worst['scene']} |")
    lines += ["", "| scene | " + " | ".join(f"`{p}`" for p in presets) + " |", "|---|" + "---|" * len(presets)]
    for scene in dict.fromkeys(r["scene"] for r in results):
        cells = []
        for p in presets:
            r = next((r for r in results if r["scene"] == scene and r["preset"] == p), None)
            cells.append(f"{r['off'] / r['splats']:.2f} -> {r['half_turns'] / r['splats']:.2f} "
                         f"({r['half_turns'] / r['off'] - 1:+.2%})" if r else "")
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def scene_of(report_path: str) -> str:
    """The A/B's scene name of a report: its file name without `.json` and without a `_VIEWSxPX` suffix."""
    return re.sub(r"_\d+x\d+$", "", os.path.splitext(os.path.basename(report_path))[0])


def apply(report: dict, scene: str, results: list[dict], presets: list[str], commit: str) -> list[tuple[str, int, int]]:
    """Rewrite `report`'s rows of `presets` (in place) with the A/B's half-turn byte fields for `scene`."""
    by_preset = {r["preset"]: r for r in results if r["scene"] == scene}
    changed = []
    for row in report["rows"]:
        if row["kind"] != "preset" or row["label"] not in presets or row.get("overrides") or row["label"] != row.get(
                "preset"):
            continue
        ab = by_preset.get(row["label"])
        if ab is None:
            raise ValueError(f"{scene} {row['label']}: not in the A/B")
        new = dict(ab["half_turns_fields"])
        if row.get("gpu_bytes") != new.pop("gpu_bytes"):
            raise ValueError(f"{scene} {row['label']}: GPU bytes {row.get('gpu_bytes')} differ from the A/B's")
        before = row["disk_bytes"]
        if abs(before - ab["half_turns"]) <= MANIFEST_SLACK:
            continue
        if abs(before - ab["off"]) > MANIFEST_SLACK:
            raise ValueError(f"{scene} {row['label']}: {before} B is neither the A/B's gauge-off {ab['off']} nor "
                             f"its half-turn {ab['half_turns']} B: stale for another reason")
        row["bytes_refreshed"] = {"commit": commit, "disk_bytes_before": before,
                                  "by": "bench/rot_halfturn_bytes.py --apply (half-turn rotation gauge)"}
        row.update(new)
        changed.append((row["label"], before, new["disk_bytes"]))
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--inputs", nargs="*", default=[], metavar="DIR")
    ap.add_argument("--presets", default="", help="comma-separated; default every smallest-three preset")
    ap.add_argument("--json", help="the A/B's results (read first, extended, written)")
    ap.add_argument("--apply", metavar="AB.json", help="rewrite the reports' rows from this A/B instead")
    ap.add_argument("--markdown")
    args = ap.parse_args(argv)
    presets = [p for p in args.presets.split(",") if p] or smallest_three_presets()
    if args.apply:
        results = json.load(open(args.apply))
        commit = source_version()["commit"]
        for path in args.reports:
            report = json.load(open(path))
            try:
                changed = apply(report, scene_of(path), results, presets, commit)
            except ValueError as e:
                print(f"{path}: not refreshed: {e}", file=sys.stderr)
                return 1
            for label, before, after in changed:
                print(f"{path}: {label:>20} {before} -> {after} B ({after / before - 1:+.2%})")
            write_report(path, report)
        return 0
    if not args.json:
        ap.error("--json is needed to measure")
    results = json.load(open(args.json)) if os.path.exists(args.json) else []
    done = {(r["scene"], r["preset"]) for r in results}
    tmp = tempfile.mkdtemp(prefix="splatstream-halfturn-")
    try:
        for path in args.reports:
            report = json.load(open(path))
            scene = os.path.splitext(os.path.basename(path))[0]
            todo = [p for p in presets if (scene, p) not in done]
            if not todo:
                continue
            g = read_gaussians(scene_path(report, args.inputs))
            for p in todo:
                off = encoded_bytes(g, p, report, None, os.path.join(tmp, "off"))
                half = encoded_bytes(g, p, report, "half-turns", os.path.join(tmp, "half"))
                results.append({"scene": scene, "preset": p, "splats": len(g), "off": off["disk_bytes"],
                                "half_turns": half["disk_bytes"], "half_turns_fields": half})
                r = results[-1]
                print(f"{scene:>30} {p:>20}: {r['off'] / len(g):.3f} -> {r['half_turns'] / len(g):.3f} B/splat "
                      f"({r['half_turns'] / r['off'] - 1:+.2%})", flush=True)
                with open(args.json + ".part", "w") as f:
                    json.dump(results, f, indent=1)
                os.replace(args.json + ".part", args.json)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(markdown(results, [p for p in presets if any(r["preset"] == p for r in results)]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
