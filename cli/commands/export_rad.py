"""`splatstream export-rad SCENE_DIR OUT.rad`: a scene's LOD tree as Spark 2's .rad (LoD splat tree and paging
chunks; format_spec/foreign_formats.md)."""
from __future__ import annotations

import argparse
import os
import sys
import time

from splatstream.errors import UsageError
from splatstream.progress import ProgressPrinter, count
from splatstream.rad_export import export_rad
from splatstream.writers.rad import ENCODINGS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-rad", help="export a scene as Spark 2's .rad (LoD tree, paged by Spark's loader)",
        description="Write an encoded scene's LOD tree as one Spark 2 .rad file: a LoD tree of splats (a root "
                    "splat, then our tiles' splats depth by depth, each splat of a tile the child of the nearest "
                    "splat of its parent tile) in chunks of 65536 splats that Spark's paged loader fetches by "
                    "range request. OUT is replaced atomically. Mapping and what is lost: "
                    "format_spec/foreign_formats.md.")
    p.add_argument("scene", metavar="SCENE_DIR", help="scene directory (manifest.msgpack)")
    p.add_argument("output", metavar="OUT", help=".rad file to write (replaced atomically if it exists)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), help="SH bands to export (default: all)")
    p.add_argument("--encoding", choices=ENCODINGS, default="exact",
                   help="exact (default): our decoded values, f32 centres and scales, f16 colour, opacity and SH; "
                        "spark: Spark's own 8-bit defaults (about half the size, quantised again)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # A .rad under another name (a typed .ply, say) is a file no reader of that name could read: refuse it before
    # the export's work, as convert refuses an extension it cannot write.
    if not os.path.isdir(args.output) and os.path.splitext(args.output)[1].lower() != ".rad":  # a directory: below
        raise UsageError(f"{args.output}: expected an output file ending in .rad (export-rad writes Spark's .rad)")
    start = time.perf_counter()
    progress = ProgressPrinter("export-rad", enabled=not args.quiet)
    report = export_rad(args.scene, args.output, args.sh_degree, progress, args.encoding)
    if not args.quiet:
        print(f"export-rad: {count(report.tiles, 'tile')} -> {count(report.levels, 'tree level')}, "
              f"{count(report.chunks, 'chunk')}, {count(report.leaf_splats, 'splat')} of full detail "
              f"({report.splats:,} over all levels), {report.bytes:,} bytes -> {args.output} "
              f"({time.perf_counter() - start:.1f}s)",
              file=sys.stderr)
    return 0
