"""`splatstream decode SCENE_DIR OUT.ply`."""
from __future__ import annotations

import argparse
import sys
import time

from splatstream.atomic import check_output
from splatstream.errors import UsageError
from splatstream.io import FORMAT_NAMES, output_format, write_gaussians, written_sh_degree
from splatstream.scene_decode import decode_scene


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decode", help="decode a scene directory back to a standard 3DGS PLY",
                       description="Decode the full-detail splats of a scene directory (all leaf tiles) and write a "
                                   "standard binary 3DGS PLY. Every payload's checksum is verified.")
    p.add_argument("scene_dir", help="encoded scene directory")
    p.add_argument("output", help="output file (.ply; other writable formats by extension)")
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], help="decode SH bands up to this degree only")
    p.add_argument("--tiles", help="comma-separated tile ids to decode instead of the leaves (e.g. 0 for the root)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    tiles: str | list[int] = "leaves"
    if args.tiles is not None:  # "" is a list of no ids, not the leaves (newuser61)
        try:
            tiles = [int(t) for t in args.tiles.split(",")]
        except ValueError:
            raise UsageError(f"--tiles: expected comma-separated integers, got {args.tiles!r}") from None
    out_format = output_format(args.output)
    check_output(args.output)
    start = time.perf_counter()
    g = decode_scene(args.scene_dir, sh_degree=args.sh_degree, tiles=tiles)
    # Writing can be the long part (a .sog's SH palette and WebP planes: 11 s for playbot's 500,000 splats on a busy
    # 2-core machine, with nothing printed before): say what is being written, as convert does.
    print(f"decode: {len(g):,} splats decoded ({time.perf_counter() - start:.1f}s); writing {args.output} "
          f"({FORMAT_NAMES[out_format]})", file=sys.stderr, flush=True)
    sh_degree = written_sh_degree(out_format, g.sh_degree)
    if sh_degree < g.sh_degree:  # as convert says it (decode said 'SH degree 2' of a .splat, which holds none)
        print(f"decode: note: {FORMAT_NAMES[out_format]} has no SH bands; bands {sh_degree + 1}..{g.sh_degree} are "
              f"dropped", file=sys.stderr, flush=True)
    write_gaussians(g, args.output)
    print(f"wrote {args.output}: {len(g):,} splats, SH degree {sh_degree} ({time.perf_counter() - start:.1f}s)",
          file=sys.stderr)
    return 0
