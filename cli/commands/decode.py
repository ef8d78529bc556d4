"""`splatstream decode SCENE_DIR OUT.ply`."""
from __future__ import annotations

import argparse
import sys

from splatstream.decoder import decode_scene
from splatstream.io import write_gaussians


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
    from splatstream.errors import UsageError

    tiles: str | list[int] = "leaves"
    if args.tiles:
        try:
            tiles = [int(t) for t in args.tiles.split(",")]
        except ValueError:
            raise UsageError(f"--tiles: expected comma-separated integers, got {args.tiles!r}") from None
    from splatstream.atomic import check_output
    from splatstream.io import output_format

    output_format(args.output)
    check_output(args.output)
    g = decode_scene(args.scene_dir, sh_degree=args.sh_degree, tiles=tiles)
    write_gaussians(g, args.output)
    print(f"wrote {args.output}: {len(g)} splats, SH degree {g.sh_degree}", file=sys.stderr)
    return 0
