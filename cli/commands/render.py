"""`splatstream render SCENE --out IMAGE.png`: headless GPU render (EGL) of an encoded scene or a splat file."""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from splatstream.atomic import atomic_file
from splatstream.camera import DEFAULT_FOV_Y_DEG, REFERENCE_NEAR, Camera, suggested_camera, turn_about_up
from splatstream.errors import InputError, UsageError
from splatstream.format.names import TILESET_NAME
from splatstream.format.presets import PRESETS
from splatstream.io import read_gaussians, scene_up
from splatstream.orientation import view_side
from splatstream.progress import count
from splatstream.readers.sog import sog_kind
from splatstream.sh import warn_sh_degree_above
from splatstream.store import is_scene_dir, load_manifest

from .args import DROP_INVALID_HELP, check_look, check_sort_draw, parse_azimuth, parse_size, parse_vector
from .renderers import gl_client

DEFAULT_SIZE = (1280, 720)


def _optional_vector(text: str | None, what: str) -> tuple[float, float, float] | None:
    return None if text is None else parse_vector(text, what)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="render a scene to an image on the GPU (headless, EGL)",
        description="Render an encoded scene directory (its splats stay in their texel formats on the GPU) or a "
                    "splat file (encoded in memory at --preset) with the GL renderer. Camera defaults come from "
                    "the manifest's suggested camera, or for files from the scene's robust bounds.",
    )
    p.add_argument("scene", metavar="SCENE", help="scene directory (manifest.msgpack) or splat file (.ply, ...)")
    p.add_argument("--out", "-o", required=True, help="output image (.png)")
    p.add_argument("--eye", help="camera position X,Y,Z")
    p.add_argument("--target", help="point looked at X,Y,Z")
    p.add_argument("--up", help="up vector X,Y,Z (default: the scene's; for a splat file, detected as `encode` does)")
    p.add_argument("--fov-y", type=float, help=f"vertical field of view in degrees (default {DEFAULT_FOV_Y_DEG:g})")
    p.add_argument("--camera-azimuth", metavar="DEG",
                   help="draw from the scene's camera (the manifest's; for a splat file, the suggested camera framing "
                        "its splats) turned by DEG degrees about up, around what it looks at (180: the other side; "
                        "positive: counter-clockwise seen from above), as `encode` and `view` take it; not with "
                        "--eye/--target")
    p.add_argument("--size", default=f"{DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]}", help="image size WxH (default 1280x720)")
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], help="SH bands to evaluate (default: all)")
    p.add_argument("--background", default="0,0,0", help="background colour R,G,B in [0, 1] (default black)")
    p.add_argument("--sort", default="auto", choices=["auto", "cpu", "gpu"],
                   help="depth sort: gpu (compute-shader radix sort), cpu (numpy on a worker thread), or auto "
                        "(gpu unless compute shaders are missing or the GL is a software renderer)")
    p.add_argument("--draw", default="auto", choices=["auto", "compute", "fetch", "points", "instanced", "triangles"],
                   help="GPU-path rasterizer: compute (compute-shader tile rasterizer), the hardware raster draws "
                        "fetch, points, instanced, triangles, or auto (compute on a hardware GL); a draw named takes "
                        "the GPU sort (also on a software GL; not with --sort cpu)")
    p.add_argument("--preset", default=None,
                   help="texel formats for a splat file encoded in memory (default very-high: f32 planes; a scene "
                        "directory is drawn in its own)")
    p.add_argument("--max-sse", type=float, metavar="PX",
                   help="draw the tiles and SH bands `view` streams for this camera at this screen-space error "
                        "(default: every full-detail tile with all its bands); the last line names the cut's tiles and "
                        "levels")
    p.add_argument("--drop-invalid", action="store_true", help=DROP_INVALID_HELP)
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")
    p.set_defaults(func=run)


def _camera(args, scene_camera: dict | None, positions: np.ndarray | None, scene_up, size,
            side: float = 0.0, opacity_logits: np.ndarray | None = None,
            log_scales: np.ndarray | None = None) -> Camera:
    width, height = size
    up = _optional_vector(args.up, "--up") or tuple(scene_up)
    if scene_camera is not None:
        default = Camera(scene_camera["eye"], scene_camera["target"], scene_camera.get("up", up),
                         scene_camera.get("fov_y", scene_camera.get("fov_y_deg", DEFAULT_FOV_Y_DEG)), width, height)
    else:
        default = suggested_camera(positions, up=up, width=width, height=height, side=side,
                                   opacity_logits=opacity_logits, log_scales=log_scales)
    azimuth = _azimuth(args)
    if azimuth:  # about the camera's own up (the scene's), as encode stores and view opens it (camera.md)
        default = Camera(turn_about_up(default.eye, default.target, default.up, azimuth), default.target, default.up,
                         default.fov_y_deg, width, height, default.near, default.far)
    eye = _optional_vector(args.eye, "--eye") or default.eye
    target = _optional_vector(args.target, "--target") or default.target
    if args.up is None and scene_camera is not None:
        up = default.up
    fov = args.fov_y if args.fov_y is not None else default.fov_y_deg
    check_look(eye, target, args.fov_y)
    dist = float(np.linalg.norm(np.subtract(eye, target)))
    near = min(REFERENCE_NEAR, 0.01 * dist) if dist > 0 else REFERENCE_NEAR
    try:
        return Camera(eye, target, up, fov, width, height, near, max(1000.0, 100.0 * dist))
    except ValueError as exc:
        raise UsageError(f"bad camera: {exc}") from None


def _azimuth(args) -> float:
    """--camera-azimuth in degrees (0 where not given), refused beside --eye/--target as `view` refuses it: it turns
    the scene's camera, which they replace."""
    if args.camera_azimuth is not None and (args.eye is not None or args.target is not None):
        given = "/".join(flag for flag, value in (("--eye", args.eye), ("--target", args.target)) if value is not None)
        raise UsageError(f"--camera-azimuth turns the scene's camera; {given} gives another camera: give one of them")
    return parse_azimuth(args.camera_azimuth)


def run(args: argparse.Namespace) -> int:
    offscreen = gl_client()
    size = parse_size(args.size)
    background = _optional_vector(args.background, "--background")
    if background is not None and not all(0.0 <= v <= 1.0 for v in background):
        # The help says [0, 1]; `--background 2,0,0` or `-1,0,0` (a 0..255 colour, a typo) drew without a word.
        raise UsageError(f"--background {args.background}: expected R,G,B each in [0, 1] (1,1,1 is white)")
    check_sort_draw(args.sort, args.draw)
    _azimuth(args)  # refused before a splat file is read
    preset = args.preset or "very-high"
    if preset not in PRESETS:
        raise UsageError(f"unknown preset {args.preset!r} (choose one of {', '.join(PRESETS)})")
    ext = os.path.splitext(args.out)[1].lower()
    if ext not in (".png", ""):
        raise UsageError(f"--out: only .png images are written, got {args.out!r}")
    if args.max_sse is not None and not args.max_sse >= 0:
        raise UsageError(f"--max-sse {args.max_sse:g}: expected 0 or more pixels")
    t0 = time.perf_counter()
    # A directory is an encoded scene (or a damaged one: it has data/), else a SOG scene directory or nothing
    # readable, which read_gaussians reports.
    if os.path.isdir(args.scene) and (is_scene_dir(args.scene) or os.path.isdir(os.path.join(args.scene, "data"))):
        if args.preset is not None:  # was ignored without a word
            raise UsageError(f"--preset {args.preset}: {args.scene} is an encoded scene, drawn in the formats it was "
                             "encoded with; --preset sets those of a splat file encoded in memory")
        if args.drop_invalid:  # (an encoded scene's splats were screened when it was encoded)
            raise UsageError(f"--drop-invalid: drops invalid splats of a splat file; {args.scene} is an encoded scene")
        manifest = load_manifest(args.scene)
        warn_sh_degree_above(args.sh_degree, manifest.sh_degree, args.scene)
        cam = _camera(args, manifest.camera.to_dict(), None, manifest.up, size)
        source = ("scene", args.scene)
        splats = manifest.splats
    else:
        if args.max_sse is not None:  # was ignored without a word: every splat was drawn
            raise UsageError(f"--max-sse {args.max_sse:g}: draws the tiles `view` streams, which an encoded scene "
                             f"directory has; {args.scene} is a splat file or SOG, drawn whole (encode it first)")
        if os.path.isdir(args.scene) and sog_kind(args.scene) is None and \
                not os.path.isfile(os.path.join(args.scene, TILESET_NAME)):
            # read_gaussians said 'expected a splat file or a SOG scene directory', naming neither of render's
            # own kinds of directory, an encoded scene (newuser64)
            raise InputError(args.scene, None, "not a scene directory (no manifest.msgpack) nor a SOG directory (no "
                             "meta.json or lod-meta.json): render takes an encoded scene, a SOG or a splat file")
        g = read_gaussians(args.scene, drop_invalid=args.drop_invalid)
        if len(g) == 0:
            raise UsageError(f"{args.scene}: no splats to render")
        warn_sh_degree_above(args.sh_degree, g.sh_degree, args.scene)
        up = _optional_vector(args.up, "--up") or scene_up(args.scene, g).up
        cam = _camera(args, None, g.positions, up, size, view_side(g, up), g.opacity_logits, g.log_scales)
        source = ("gaussians", g)
        splats = len(g)
        if not args.quiet:
            # A splat file is encoded in memory before it is drawn: seconds for a large one (playbot's 500,000
            # splats: 13 s of "load" on a busy 2-core machine, with nothing printed before the last line).
            print(f"render: {count(len(g), 'splat')} read from {args.scene} ({time.perf_counter() - t0:.1f}s); "
                  f"encoding them at {preset} for the GPU", file=sys.stderr, flush=True)
    renderer = offscreen.HeadlessRenderer(offscreen.RenderOptions(sort=args.sort, draw=args.draw))
    cut = ""
    try:
        if source[0] == "scene" and args.max_sse is not None:
            # The GL client (the optional [view] extra, moderngl) is imported only by a command that draws, after
            # gl_client() has said how to install it where it is missing, and so that other commands start without it
            from client_gl.scene import tiles_for_view
            from client_gl.stream.selection import SelectionOptions

            scene = tiles_for_view(source[1], cam, SelectionOptions(max_sse=args.max_sse), args.sh_degree,
                                   with_mirror=renderer.needs_host_mirror)
            renderer.load_tiles(scene)
            splats = scene.splats
            cut = _cut_words(scene.manifest, list(scene.tiles), args.max_sse)
        elif source[0] == "scene":
            renderer.load_scene(source[1], args.sh_degree)
        else:
            renderer.load_gaussians(source[1], preset, args.sh_degree)
        t1 = time.perf_counter()
        img = renderer.render(cam, args.sh_degree, background)
        t2 = time.perf_counter()
        gl_name = renderer.ctx.info.get("GL_RENDERER", "?")
        sort = renderer.sort_mode
        if sort == "gpu":
            sort += f", draw {renderer.renderer.draw_mode}"
        per_splat = renderer.scene.manifest.gpu_bytes_per_splat  # the scene's, as `info` reports it
    finally:
        renderer.close()
    _write_png(args.out, img)
    if not args.quiet:
        print(f"wrote {args.out}: {cam.width}x{cam.height}, {count(splats, 'splat')}{cut}, sort {sort}, {gl_name}, "
              f"{per_splat:.1f} GPU B/splat, load {t1 - t0:.2f}s, render {(t2 - t1) * 1e3:.0f} ms", file=sys.stderr)
    return 0


def _cut_words(manifest, tile_ids: list[int], max_sse: float) -> str:
    """What `--max-sse` drew, for the last line: the cut's tiles and levels, and whether they are all leaves. A tree
    whose errors are large on screen (flowers_lod's kept tree: its finest interior tiles 17-128 px from the suggested
    camera at 720 rows) refines to every leaf at any K below those, and said nothing of it: the same splat count at
    K = 1, 4 and 16 read as --max-sse being ignored (newuser62)."""
    levels = sorted({manifest.tile(i).level for i in tile_ids})
    deepest = max(t.level for t in manifest.tiles)
    drawn = f"level {levels[0]}" if len(levels) == 1 else f"levels {levels[0]}-{levels[-1]}"
    leaves = all(not manifest.tile(i).children for i in tile_ids)
    return (f" (--max-sse {max_sse:g}: {len(tile_ids)} of {len(manifest.tiles)} tiles, {drawn} of 0-{deepest}"
            f"{'; every tile drawn is a leaf: full detail' if leaves else ''})")


def _write_png(path: str, img: np.ndarray) -> None:
    from PIL import Image  # Pillow only when an image is written: it slowed every command's start-up

    rgb8 = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_file(path) as f:
        Image.fromarray(rgb8, "RGB").save(f, format="PNG")
