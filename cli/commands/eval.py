"""`splatstream eval INPUT [--presets ...] [--views N] [--size WxH] [--json OUT] [--plot OUT.png] [--encoded DIR]
[--compare FILE ...]`: rate-distortion table of the presets (and of other tools' outputs) on one scene."""
from __future__ import annotations

import argparse
import json
import os
import sys

from splatstream.atomic import check_output
from splatstream.errors import InputError, UsageError
from splatstream.evaluate import PRESET_ORDER, EvalOptions, evaluate, plot_rate_distortion, report_markdown
from splatstream.readers.sog import sog_kind
from splatstream.store import is_scene_dir

from .args import DROP_INVALID_HELP, parse_size, parse_vector
from .renderers import RENDERER_CHOICES, pick_renderer


def parse_list(text: str) -> list[str]:
    return [p.strip() for p in text.split(",") if p.strip()]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval", help="rate-distortion evaluation: PSNR/SSIM and bytes per splat of every preset on a scene",
        description="Encode INPUT with each preset, decode it, render the original and every version from N "
                    "orbit views around the scene and report PSNR and SSIM against the original's renders, bytes "
                    "per splat in GPU memory and on disk, compression against the input file, encode time. "
                    "Writes a Markdown table to stdout, and optionally JSON (with the cameras) and a plot.",
    )
    p.add_argument("input", metavar="INPUT", help="input scene (standard 3DGS PLY or another supported format)")
    p.add_argument("--presets", default=",".join(PRESET_ORDER),
                   help=f"comma-separated presets (default {','.join(PRESET_ORDER)}); 'none' for peers only")
    p.add_argument("--views", type=int, default=8, help="number of orbit views (default 8)")
    p.add_argument("--size", default="512x512", help="render size WIDTHxHEIGHT (default 512x512)")
    p.add_argument("--up", help="scene up vector for the orbit (default: detected as `encode` does)")
    p.add_argument("--elevation", type=float, default=25.0, help="orbit elevation in degrees (default 25)")
    p.add_argument("--json", dest="json_out", metavar="OUT.json", help="write the full report as JSON")
    p.add_argument("--plot", metavar="OUT.png", help="write a rate-versus-PSNR plot (PNG)")
    p.add_argument("--markdown", metavar="OUT.md", help="also write the table to this file")
    p.add_argument("--encoded", metavar="DIR", help="keep the encoded scenes under DIR/<preset> (default: discard)")
    p.add_argument("--spz-axes", choices=("rub", "rdf", "auto"), default=None,
                   help="axes of SPZ files given to --compare: rub, as the format specifies (Niantic's library, "
                        "splat-transform 2.x; default: a file that reads turned against the input is warned about), "
                        "rdf, stored without the axis turn (splat-transform 3.x), or auto: whichever matches the input")
    p.add_argument("--compare", nargs="+", default=[], metavar="[LABEL=]FILE[@SIZED]",
                   help="other tools' outputs to put in the table: any file convert reads (PLY, compressed PLY, "
                        "SPZ, .splat, SOG, ...), its own size counted; @SIZED names another file or directory "
                        "whose size counts instead (e.g. the .sog a PLY was decoded from)")
    p.add_argument("--attribution", default="", metavar="PRESETS",
                   help="for these presets, also encode with one attribute lossless (f32x4) at a time and with "
                        "only one attribute quantised, to show which attribute's error dominates")
    p.add_argument("--variants", nargs="+", default=[], metavar="NAME:PRESET[,ATTR=FORMAT...][,sh_degree=D]",
                   help="extra encodes to put in the table and plot, e.g. low-sh2:low,sh_degree=2 or "
                        "low-rot565:low,rotation=norm565")
    p.add_argument("--renderer", choices=RENDERER_CHOICES, default="auto",
                   help="auto: the GL client if available, else the numpy reference rasterizer")
    p.add_argument("--lod", action="store_true", help="encode the LOD tree too and count its bytes on disk")
    p.add_argument("--reference-table", action="store_true",
                   help="also print the published preset table of a Unity splat renderer (Aras P., 2023; bike scene) "
                        "as a labelled reference")
    p.add_argument("--drop-invalid", action="store_true", help=DROP_INVALID_HELP)
    p.add_argument("--quiet", "-q", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # A SOG's directory (meta.json and its planes; a streamed SOG's lod-meta.json and its units) is read as
    # convert, encode and render read it: eval refused it, saying it takes a format `convert` reads.
    if os.path.isdir(args.input) and sog_kind(args.input) is None:
        hint = (" (this is a splatstream scene: `splatstream decode` writes its splats to a file)"
                if is_scene_dir(args.input) else "")
        raise InputError(args.input, None, "is a directory; eval takes the original splat file (a 3DGS PLY or "
                         "another format `convert` reads: a SOG's meta.json or lod-meta.json, or its directory) "
                         f"and encodes it itself{hint}")
    if not os.path.exists(args.input):
        raise InputError(args.input, None, "no such file")
    w, h = parse_size(args.size, smallest=11, largest=8192)
    presets = [] if args.presets.strip().lower() == "none" else parse_list(args.presets)
    if not presets and not args.compare and not args.variants:
        raise UsageError("nothing to evaluate: give --presets, --variants or --compare")
    # Each was taken without a word (newuser61): the axes of no --compare file; an orbit over the pole (its views
    # upside down, the up vector unchanged).
    if args.spz_axes is not None and not args.compare:
        raise UsageError(f"--spz-axes {args.spz_axes}: the axes of SPZ files given to --compare, and none is given")
    if not -90.0 < args.elevation < 90.0:
        raise UsageError(f"--elevation {args.elevation:g}: expected degrees in (-90, 90)")
    # Checked before the encodes and renders: the plot is written last, and PIL picks its format by extension.
    if args.plot and os.path.splitext(args.plot)[1].lower() != ".png":
        raise UsageError(f"--plot: only .png images are written, got {args.plot!r}")
    # A missing or unwritable directory, or a directory where the file goes, is found now: a --json into a
    # read-only directory failed after every encode and render, with exit 1 and only the system's words.
    for out in (args.json_out, args.plot, args.markdown):
        if out:
            check_output(out)
    if args.encoded and presets:  # the scenes go in directories below it, one per preset
        check_output(os.path.join(args.encoded, presets[0]), directory=True)
    up = parse_vector(args.up, "--up", nonzero=True) if args.up else None
    opts = EvalOptions(presets=presets, views=args.views, width=w, height=h, up=up,
                       elevation_deg=args.elevation, encoded_dir=args.encoded, compare=args.compare,
                       spz_axes=args.spz_axes or "rub", lod=args.lod, attribution=parse_list(args.attribution),
                       variants=args.variants, drop_invalid=args.drop_invalid)
    log = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    report = evaluate(args.input, opts, log, pick_renderer(args.renderer))
    md = report_markdown(report, reference_table=args.reference_table)
    sys.stdout.write(md)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(md)
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(report, f, indent=1, allow_nan=False)
    if args.plot:
        plot_rate_distortion(report, args.plot)
    return 0
