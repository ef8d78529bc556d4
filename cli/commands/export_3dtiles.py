"""`splatstream export-3dtiles SCENE_DIR OUT_DIR`: a scene as an OGC 3D Tiles 1.1 tileset of glTF
KHR_gaussian_splatting tiles (format_spec/tiles3d.md)."""
from __future__ import annotations

import argparse
import sys
import time

from splatstream.errors import UsageError
from splatstream.progress import ProgressPrinter, count


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-3dtiles", help="export a scene as a 3D Tiles 1.1 tileset (CesiumJS and other 3D Tiles clients)",
        description="Write an encoded scene's LOD tree as an OGC 3D Tiles 1.1 tileset: OUT_DIR/tileset.json "
                    "(REPLACE refinement, our 3-sigma boxes and geometric errors, taken as metres) and one glTF "
                    "binary per tile (OUT_DIR/tiles/<sha256>.glb, KHR_gaussian_splatting, SPZ-compressed by "
                    "default). The scene stands upright (its manifest's up becomes the local up) and is placed on "
                    "the WGS84 globe: at --longitude/--latitude/--height with --heading for a georeferenced "
                    "capture (its origin at that point), else with the bottom centre of its box at longitude 0, "
                    "latitude 0, height 0. A paged scene's tree is split as its manifest is: tileset.json holds the "
                    "root manifest's levels and each manifest page becomes an external tileset "
                    "(OUT_DIR/tiles/<sha256>.json, see --external-tilesets). OUT_DIR is replaced atomically. "
                    "Conventions: format_spec/tiles3d.md.")
    p.add_argument("scene", metavar="SCENE_DIR", help="scene directory (manifest.msgpack)")
    p.add_argument("output_dir", metavar="OUT_DIR",
                   help="tileset directory to write (replaced atomically if it exists)")
    p.add_argument("--content", choices=("spz", "plain"), default="spz",
                   help="tile content: spz (KHR_gaussian_splatting_compression_spz_2, default; what CesiumJS draws as "
                        "splats) or plain (float accessors: larger, read by glTF tools; CesiumJS 1.145 draws only "
                        "SPZ content as splats)")
    p.add_argument("--longitude", type=float, help="degrees east, -180..180 (places a georeferenced capture)")
    p.add_argument("--latitude", type=float, help="degrees north, -90..90")
    p.add_argument("--height", type=float, help="metres above the WGS84 ellipsoid (default 0)")
    p.add_argument("--heading", type=float, default=0.0,
                   help="compass bearing, degrees clockwise from north, of the scene's local north (default 0: the "
                        "scene's x axis east; for 3DGS captures the cameras' forward points north)")
    p.add_argument("--anchor", choices=("origin", "ground"),
                   help="the scene point put at the position: origin (its coordinate origin; default with "
                        "--longitude/--latitude) or ground (the centre of the bottom of its box; default without)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), help="SH bands to export (default: all)")
    p.add_argument("--spz-axes", choices=("luf", "rub"), default=None,
                   help="how SPZ content stores glTF's axes: luf (glTF values unconverted: what CesiumJS reads, the "
                        "default) or rub (the extension text's SPZ axes)")
    p.add_argument("--spz-version", type=int, choices=(3, 4), default=None,
                   help="SPZ version of the content: 3 (gzip, default; what the extension references) or 4 (zstd)")
    p.add_argument("--external-tilesets", choices=("auto", "always", "never"), default="auto",
                   help="auto (default): a paged scene (encode --page-tiles) as a root tileset.json of the root "
                        "manifest's levels and one external tileset per manifest page (tiles/<sha256>.json), read "
                        "by a client as it refines; an unpaged scene as one tileset.json. always: an unpaged scene "
                        "split the same way every 6 levels. never: one tileset.json listing every tile")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Imported when the command runs: the exporter and the glTF and SPZ writers it pulls in took about a tenth of
    # the start-up of every other command (python -X importtime), which builds this parser too.
    from splatstream.tiles3d import DEFAULT_SPZ_AXES, DEFAULT_SPZ_VERSION, ExportOptions, Placement, export_tileset

    from .args import check_directory_output

    located = args.longitude is not None or args.latitude is not None or args.height is not None
    if located and (args.longitude is None or args.latitude is None):
        raise UsageError("--longitude and --latitude go together (and --height needs both)")
    placement = Placement(longitude=args.longitude or 0.0, latitude=args.latitude or 0.0,
                          height=args.height or 0.0, heading=args.heading,
                          anchor=args.anchor or ("origin" if located else "ground"), georeferenced=located)
    # --spz-version with plain content was taken without a word (newuser61), where --spz-axes was refused
    for flag, value in (("--spz-axes", args.spz_axes), ("--spz-version", args.spz_version)):
        if value is not None and args.content != "spz":
            raise UsageError(f"{flag} {value} and --content {args.content}: {flag} applies to --content spz only")
    options = ExportOptions(content=args.content, spz_axes=args.spz_axes or DEFAULT_SPZ_AXES,
                            spz_version=args.spz_version or DEFAULT_SPZ_VERSION,
                            placement=placement, sh_degree=args.sh_degree,
                            external_tilesets=args.external_tilesets)
    check_directory_output(args.output_dir, "export-3dtiles", "tileset.json")
    start = time.perf_counter()
    progress = ProgressPrinter("export-3dtiles", enabled=not args.quiet)
    report = export_tileset(args.scene, args.output_dir, options, progress)
    if not args.quiet:
        where = (f"longitude {placement.longitude:g}, latitude {placement.latitude:g}, height {placement.height:g} m"
                 if located else "longitude 0, latitude 0 (not georeferenced)")
        external = (f", {count(report.external_tilesets, 'external tileset')} of {report.external_bytes:,} bytes"
                    if report.external_tilesets else "")
        print(f"export-3dtiles: {count(report.tiles, 'tile')} ({count(report.files, 'file')}, "
              f"{report.content_bytes:,} bytes of "
              f"{args.content} content, tileset.json {report.tileset_bytes:,} bytes{external}) at {where}, heading "
              f"{placement.heading:g}, anchor {placement.anchor} -> {args.output_dir} "
              f"({time.perf_counter() - start:.1f}s)", file=sys.stderr)
    return 0
