"""Refresh the byte fields of `splatstream eval` reports' preset rows from fresh encodes, leaving PSNR and peers.

    PYTHONPATH=. python bench/eval_refresh_bytes.py REPORT.json [...] [--inputs DIR ...] [--only a,b] [--dry-run]

The eval's sizes are the full-detail payloads and manifest without LOD (`sizes.disk`), and a zstd setting is
lossless: when a change of the encoder moves only the bytes (issue 32, eval32: lossydec's zstd settings), every
preset row's texels and so its PSNR and SSIM are what the report measured, and only its bytes are stale. This
re-encodes each preset row (kind `preset`) with the report's options (its preset and overrides, the cameras' up,
`encode_options`) exactly as `evaluate` encodes it, checks that the formats, SH codebook entries and GPU bytes are the
report's (the texels' shape: a row where they differ is not a bytes-only change and stops the script), and rewrites
`disk_bytes`, `disk_bytes_per_splat`, `compression`, `bytes_on_disk_total`, `leaf_bytes_on_disk` and the per-attribute
`disk_bytes`; the row records the bytes it had and this commit under `bytes_refreshed`. Peer rows (kind `compare`) and
every quality field stay as measured; so do `encode_seconds` (a time of the eval's run, not of this one). Each
report's `.md` beside it is rewritten from the JSON (evaluate.report_markdown).

The scene is read from the report's input path, else from a file of the same name under one of `--inputs` (the
reports name the worktree they ran in); its size and splat count must be the report's.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_gaussians  # noqa: E402
from splatstream.evaluate import report_markdown, source_version  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402

# the fields a fresh encode rewrites (per-attribute disk bytes too); every other field is the report's
BYTE_FIELDS = ("disk_bytes", "disk_bytes_per_splat", "compression", "bytes_on_disk_total", "leaf_bytes_on_disk")


def scene_path(report: dict, inputs: list[str]) -> str:
    """The report's input file: its path, else the same name under one of `inputs`, with the report's size."""
    recorded = report["input"]["path"]
    candidates = [recorded] + [os.path.join(d, os.path.basename(recorded)) for d in inputs]
    for path in candidates:
        if os.path.isfile(path):
            if os.path.getsize(path) != report["input"]["bytes"]:
                raise ValueError(f"{path}: {os.path.getsize(path)} bytes, the report's input has "
                                 f"{report['input']['bytes']}")
            return path
    raise ValueError(f"input {recorded} not found (looked under {', '.join(inputs) or 'no --inputs'})")


def fresh_bytes(g, row: dict, report: dict, out: str) -> dict:
    """The byte fields of `row` from a fresh encode of its preset, as `evaluate` encodes it."""
    eo = EncodeOptions(preset=row["preset"], overrides=dict(row.get("overrides") or {}), lod=report["encode_options"]
                       .get("lod", False), up=tuple(report["camera_rule"]["up"]),
                       **{k: v for k, v in report["encode_options"].items() if k not in ("lod", "zstd_level")})
    if report["encode_options"].get("zstd_level") is not None:
        eo.zstd_level = report["encode_options"]["zstd_level"]
    m = encode_gaussians(g, out, eo, source_name=report["input"]["path"])
    shape = {"formats": dict(m.formats), "gpu_bytes": m.gpu_bytes,
             "sh_codebook_entries": m.sh_codebook.entries if m.sh_codebook else None}
    for key, value in shape.items():
        if row.get(key) != value:
            raise ValueError(f"{row['label']}: {key} {value!r}, the report's {row.get(key)!r}: not a bytes-only change")
    disk = m.bytes_on_disk
    return {"disk_bytes": disk, "disk_bytes_per_splat": round(disk / len(g), 6),
            "compression": round(report["input"]["bytes"] / disk, 6), "bytes_on_disk_total": disk,
            "leaf_bytes_on_disk": m.leaf_bytes_on_disk,
            "attributes": {a: s.to_dict() for a, s in m.attributes.items()}}


def refresh(report: dict, inputs: list[str], only: set[str] | None = None,
            log=lambda msg: None) -> list[tuple[str, int, int]]:
    """Rewrite the byte fields of `report`'s preset rows (in place); (label, bytes before, after) per row."""
    path = scene_path(report, inputs)
    g = read_gaussians(path)
    if len(g) != report["input"]["splats"]:
        raise ValueError(f"{path}: {len(g)} splats, the report's input has {report['input']['splats']}")
    commit = source_version()["commit"]
    changed = []
    tmp = tempfile.mkdtemp(prefix="splatstream-refresh-")
    try:
        for i, row in enumerate(report["rows"]):
            if row["kind"] != "preset" or (only and row["label"] not in only):
                continue
            new = fresh_bytes(g, row, report, os.path.join(tmp, str(i)))
            before = row["disk_bytes"]
            row["bytes_refreshed"] = {"commit": commit, "disk_bytes_before": before}
            row.update(new)
            changed.append((row["label"], before, new["disk_bytes"]))
            log(f"{row['label']:>20}: {before} -> {new['disk_bytes']} B ({new['disk_bytes'] / before - 1:+.2%}), "
                f"{new['disk_bytes_per_splat']:.2f} B/splat")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--inputs", nargs="*", default=[], metavar="DIR", help="where to look for the scenes by name")
    ap.add_argument("--only", default="", help="comma-separated preset labels to refresh; default: every preset row")
    ap.add_argument("--dry-run", action="store_true", help="print the new bytes, write nothing")
    args = ap.parse_args(argv)
    only = {x for x in args.only.split(",") if x} or None
    for path in args.reports:
        report = json.load(open(path))
        print(f"== {path}", flush=True)
        try:
            refresh(report, args.inputs, only, log=lambda msg: print(msg, flush=True))
        except ValueError as e:
            print(f"{path}: not refreshed: {e}", file=sys.stderr)
            return 1
        if args.dry_run:
            continue
        write_report(path, report)
    return 0


def write_report(path: str, report: dict) -> None:
    """The report's JSON replaced whole (written beside it, then renamed) and its .md, where there is one, from it."""
    with open(path + ".part", "w") as f:
        json.dump(report, f, indent=1)
    os.replace(path + ".part", path)
    md = os.path.splitext(path)[0] + ".md"
    if os.path.exists(md):
        with open(md, "w") as f:
            f.write(report_markdown(report))


if __name__ == "__main__":
    sys.exit(main())
