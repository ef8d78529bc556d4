"""`splatstream export-sog-lod SCENE_DIR OUT_DIR`: a scene's LOD tree as a PlayCanvas streamed SOG
(lod-meta.json + SOG units; format_spec/foreign_formats.md)."""
from __future__ import annotations

import argparse
import sys
import time

from splatstream.errors import UsageError
from splatstream.progress import ProgressPrinter, count
from splatstream.sog_export import export_streamed_sog
from splatstream.writers.sog_lod import UNIT_SPLATS

from .args import check_directory_output


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-sog-lod", help="export a scene as a PlayCanvas streamed SOG (lod-meta.json, PlayCanvas engine, "
                               "SuperSplat)",
        description="Write an encoded scene's LOD tree as a PlayCanvas streamed SOG: OUT_DIR/lod-meta.json (a tree "
                    "whose leaves are our leaf tiles, each with a row range per LOD level; level 0 is our full "
                    "detail, level L our tiles L levels above the leaves) and one SOG version 2 unit per level and "
                    "about --unit-splats splats (OUT_DIR/<level>_<i>/meta.json + lossless WebP planes). OUT_DIR is "
                    "replaced atomically. Mapping and what is lost: format_spec/foreign_formats.md.")
    p.add_argument("scene", metavar="SCENE_DIR", help="scene directory (manifest.msgpack)")
    p.add_argument("output_dir", metavar="OUT_DIR",
                   help="streamed SOG directory to write (replaced atomically if it exists)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), help="SH bands to export (default: all)")
    p.add_argument("--unit-splats", type=int, default=None,
                   help="splats per SOG unit before a new one starts (default 524288, splat-transform's)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.unit_splats is not None and args.unit_splats < 1:  # the library's 'unit size 0' named no option
        raise UsageError(f"--unit-splats {args.unit_splats}: expected at least 1 splat")
    check_directory_output(args.output_dir, "export-sog-lod", "lod-meta.json", (".sog",))
    start = time.perf_counter()
    progress = ProgressPrinter("export-sog-lod", enabled=not args.quiet)
    report = export_streamed_sog(args.scene, args.output_dir, args.sh_degree,
                                 UNIT_SPLATS if args.unit_splats is None else args.unit_splats, progress)
    if not args.quiet:
        print(f"export-sog-lod: {count(report.tiles, 'tile')} -> {count(report.levels, 'LOD level')}, "
              f"{count(report.units, 'SOG unit')}, {count(report.leaf_splats, 'splat')} at level 0 "
              f"({report.splats:,} over all levels), {report.bytes:,} bytes -> {args.output_dir} "
              f"({time.perf_counter() - start:.1f}s)",
              file=sys.stderr)
    return 0
