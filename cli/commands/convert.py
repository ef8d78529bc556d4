"""`splatstream convert IN OUT`: any readable splat format to .ply, .splat, .spz, .glb or .sog."""
from __future__ import annotations

import argparse
import os
import sys
import time

from splatstream.atomic import check_output
from splatstream.axes import RDF_TO_RUB, turn
from splatstream.errors import InputError, UsageError
from splatstream.gaussians import Gaussians
from splatstream.io import (
    FORMAT_NAMES,
    open_input,
    output_format,
    read_gaussians,
    screen_gaussians,
    write_gaussians,
    written_sh_degree,
)
from splatstream.progress import ProgressPrinter, count
from splatstream.readers.sog import read_sog_level

from .args import DROP_INVALID_HELP, add_edit_arguments, edit_report, edits_from


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "convert", help="convert between splat file formats",
        description="Read a splat scene (standard 3DGS PLY, PlayCanvas compressed PLY, Niantic SPZ v2-v4, "
                    "antimatter15 .splat, PlayCanvas SOG as a .sog file, a meta.json or its directory, streamed SOG "
                    "as a lod-meta.json or its directory (finest level), a Spark .rad (finest level), glTF/GLB with "
                    "KHR_gaussian_splatting; "
                    "recognised by content) and write it as a standard 3DGS PLY (.ply), .splat, SPZ (.spz), "
                    "glTF binary with KHR_gaussian_splatting (.glb) or PlayCanvas SOG (.sog, version 2, bundled), "
                    "chosen by OUT's extension. The output appears "
                    "only when complete. What each format keeps is documented in format_spec/foreign_formats.md.")
    p.add_argument("input", nargs="+", metavar="INPUT",
                   help="input splat file or SOG directory; several are merged into one scene, in "
                        "the order given (SH bands an input lacks are zeros; the edits apply "
                        "to the merged splats)")
    p.add_argument("output", metavar="OUT", help="output file (.ply, .splat, .spz, .glb or .sog)")
    p.add_argument("--spz-axes", choices=("rub", "rdf"), default="rub",
                   help="axes of an SPZ input: rub, as the format specifies (Niantic's library, splat-transform 2.x; "
                        "default), or rdf for files stored without the axis turn (splat-transform 3.x), which read "
                        "turned 180 degrees about x otherwise")
    p.add_argument("--spz-version", type=int, choices=(3, 4), default=None,
                   help="SPZ version for .spz output: 4 (zstd streams, default) or 3 (gzip, for older readers)")
    p.add_argument("--glb-compression", choices=("none", "spz"), default=None,
                   help="for .glb output: plain float accessors (default) or SPZ-compressed content "
                        "(KHR_gaussian_splatting_compression_spz_2)")
    p.add_argument("--lod-level", type=int, default=None, metavar="L",
                   help="for a streamed SOG input: the LOD level to convert (0, the finest, by default; every level "
                        "of the tree is readable)")
    p.add_argument("--drop-invalid", action="store_true", help=DROP_INVALID_HELP)
    add_edit_arguments(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out_format = output_format(args.output)  # refuse an unwritable output before reading anything
    sources = [open_input(p) for p in args.input]  # sniffed once: the reader takes what sniffing parsed
    for path in args.input:
        if os.path.exists(args.output) and os.path.samefile(path, args.output):
            raise UsageError(f"{args.output}: output is the input file")
    for flag, wanted, given in (("--lod-level", "lod_sog", args.lod_level is not None),
                                ("--spz-axes rdf", "spz", args.spz_axes == "rdf")):
        wrong = [s.path for s in sources if s.format != wanted]
        if given and wrong:
            raise UsageError(f"{flag}: {wrong[0]} is not {'a streamed SOG' if wanted == 'lod_sog' else 'an SPZ file'}")
    # An output option for another format was taken without a word (`x.ply --spz-version 3` wrote a PLY).
    for flag, value, wanted in (("--spz-version", args.spz_version, "spz"),
                                ("--glb-compression", args.glb_compression, "gltf")):
        if value is not None and out_format != wanted:
            raise UsageError(f"{flag} {value}: only for {'.spz' if wanted == 'spz' else '.glb'} output, and "
                             f"{args.output} is written as {FORMAT_NAMES[out_format]}")
    spz_version = args.spz_version or 4
    glb_compression = args.glb_compression or "none"
    check_output(args.output)
    edits = edits_from(args)  # a bad edit value is refused before the (possibly long) read, as encode does
    start = time.perf_counter()

    def say(message: str) -> None:
        if not args.quiet:
            print(f"convert: {message} ({time.perf_counter() - start:.1f}s)", file=sys.stderr, flush=True)

    parts = []
    for source in sources:
        say(f"reading {source.path} ({FORMAT_NAMES[source.format]})")
        if args.lod_level is not None:
            g = screen_gaussians(read_sog_level(source.path, args.lod_level), source.path, args.drop_invalid)
        else:
            g = read_gaussians(source, drop_invalid=args.drop_invalid)
        if len(g) == 0:  # an empty .splat (or any format without a count) could not be read back
            raise InputError(source.path, None, "holds no splats (none, or none left after dropping invalid ones); "
                             "nothing to convert")
        if args.spz_axes == "rdf":
            g = turn(g, RDF_TO_RUB)  # undo the reader's RUB -> RDF turn: the file held RDF already
        parts.append(g)
    # merged as io.read_merged merges them: missing SH bands are zeros, so every input looks as it did
    g = Gaussians.concatenate(parts)
    say(f"read {count(len(g), 'splat')}, SH degree {g.sh_degree}")
    read = len(g)
    g, counts = edits.run(g)
    for label, kept in counts:
        say(f"{label}: {count(kept, 'splat')} kept")
    if args.dry_run:
        print(edit_report(" + ".join(args.input), read, counts))
        return 0
    if len(g) == 0:
        raise UsageError(f"{' + '.join(args.input)}: the edits keep no splats; nothing to convert")
    if (kept_sh := written_sh_degree(out_format, g.sh_degree)) < g.sh_degree:
        say(f"note: .splat has no SH bands; bands {kept_sh + 1}..{g.sh_degree} are dropped")
    glb = "SPZ-compressed splats" if glb_compression == "spz" else "uncompressed splats"
    detail = {"spz": f", version {spz_version}", "gltf": f", {glb}"}
    say(f"writing {args.output} ({FORMAT_NAMES[out_format]}{detail.get(out_format, '')})")
    # A .sog's SH palette fit takes seconds (5.6 s on playbot) and was one silent step: its share is shown.
    bar = ProgressPrinter("convert", enabled=not args.quiet)
    write_gaussians(g, args.output, spz_version=spz_version, glb_compression=glb_compression,
                    progress=lambda fraction: bar("writing", fraction))
    # what was written and where, as decode and encode end (it said 'done' alone: newuser63)
    say(f"wrote {args.output}: {count(len(g), 'splat')}, SH degree {kept_sh}, {os.path.getsize(args.output):,} bytes")
    return 0
