"""`splatstream view SOURCE [--headless]`: stream a scene (URL, scene directory or splat file) into a window, or
headless for scripts and benchmarks."""
from __future__ import annotations

import argparse
import math
import os
import sys

from splatstream.atomic import check_output
from splatstream.camera import DEFAULT_FOV_Y_DEG, Camera, look_at_near_far
from splatstream.camera_path import load_camera_path
from splatstream.errors import UsageError
from splatstream.format.names import MANIFEST_NAME
from splatstream.progress import mib

from .args import DROP_INVALID_HELP, check_look, check_sort_draw, parse_azimuth, parse_size, parse_vector
from .renderers import gl_client

DRAWS = ["auto", "compute", "fetch", "points", "instanced", "triangles"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view", help="stream a scene into a window (or headless): coarse tiles first, detail and SH bands as needed",
        description="Stream SOURCE, an http(s):// scene URL served by `splatstream serve` (or any static server), a "
                    "local scene directory, a PlayCanvas streamed SOG (lod-meta.json or its directory: its own LOD "
                    "tree, converted into ours and encoded in memory first), a Spark .rad (its LoD tree, likewise), "
                    "or a splat file (encoded in memory "
                    "first). Tiles are chosen by "
                    "screen-space error within a GPU memory budget, fetched by priority, decoded off the render "
                    "thread and drawn coarse to fine; SH bands follow where they change the picture "
                    "(format_spec/client.md). Without --headless a window opens with orbit and fly cameras and an "
                    "overlay (H shows the controls).")
    p.add_argument("source", metavar="SOURCE",
                   help="http(s)://HOST/scenes/ID, a scene directory, a streamed SOG (lod-meta.json or its "
                        "directory), a Spark .rad, or a splat file (.ply, .spz, ...; a SOG: .sog, meta.json "
                        "or its directory)")
    p.add_argument("--headless", action="store_true", help="no window: stream, then write what is asked for")
    cam = p.add_argument_group("camera (default: the scene's suggested camera)")
    cam.add_argument("--eye", help="camera position X,Y,Z")
    cam.add_argument("--target", help="point looked at X,Y,Z")
    cam.add_argument("--up", help="up vector X,Y,Z (default: the scene's)")
    cam.add_argument("--fov-y", type=float, help="vertical field of view in degrees")
    cam.add_argument("--size", default="1280x720", help="image (framebuffer) size WxH (default 1280x720)")
    cam.add_argument("--camera-azimuth", metavar="DEG",
                     help="open at the scene's camera turned by DEG degrees about up, around what it looks at (180: "
                          "the other side; positive: counter-clockwise seen from above; R returns there)")
    cam.add_argument("--camera-path", metavar="PATH.json",
                     help="keyframes {time, eye, target[, up][, fov_y]} played on the wall clock")
    s = p.add_argument_group("streaming")
    s.add_argument("--gpu-mem-mb", type=float, default=1024.0, help="GPU memory for splat data, MiB (default 1024)")
    s.add_argument("--max-splats", type=int, help="splats drawn at most (default: as the memory allows)")
    s.add_argument("--max-sse", type=float, default=1.5,
                   help="screen-space error in pixels under which a tile is not refined (default 1.5; 0: full detail)")
    s.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], help="SH bands fetched and drawn at most")
    s.add_argument("--sh-bands", default="need", metavar="need|all|S1,S2,S3",
                   help="need (default): SH bands only for the tiles that cover most of the view (bands 1, 2, 3 until "
                        "they cover 97, 90, 80 %% of its area); all: every band of every selected tile; S1,S2,S3: "
                        "those shares of the area (0-1) instead")
    s.add_argument("--no-cache", action="store_true", help="do not use the disk cache of payloads")
    s.add_argument("--no-prefetch", action="store_true", help="fetch only what the view needs now")
    s.add_argument("--skip-levels", action="store_true",
                   help="fetch the wanted tiles without the LOD levels above them (fewer bytes; the picture stays "
                        "coarse longer and then changes in larger steps)")
    s.add_argument("--fill-gap", type=int, default=4, metavar="N",
                   help="fill in the LOD level N levels above each wanted tile, then every fourth level up to the "
                        "root (default 4: coarse to fine in 16x steps of splats; 1: from the parents up)")
    s.add_argument("--fill-min-kb", type=float, metavar="KB",
                   help="fill in the LOD levels above the wanted tiles (the root included) only while more than KB "
                        "KiB of the wanted tiles are missing (default: the client's, 64: a small cut is fetched and "
                        "drawn directly; 0: always coarse to fine)")
    s.add_argument("--fill-root-kb", type=float, metavar="KB",
                   help="where more than --fill-min-kb but at most KB KiB of the wanted tiles are missing, fetch the "
                        "root, then the wanted tiles, without the levels between (default: the client's, 512; 0: "
                        "coarse to fine above --fill-min-kb)")
    s.add_argument("--sort", default="auto", choices=["auto", "cpu", "gpu"], help="depth sort (as `render`)")
    s.add_argument("--draw", default="auto", choices=DRAWS,
                   help="GPU-path rasterizer (as `render`: a draw named takes the GPU sort; not with --sort cpu)")
    h = p.add_argument_group("headless output")
    h.add_argument("--until-converged", action="store_true",
                   help="with --camera-path: keep going after the path ends until the view has converged")
    h.add_argument("--timeout", type=float, default=120.0, metavar="S",
                   help="give up after S seconds (exit 1; default 120)")
    h.add_argument("--record", metavar="METRICS.json", help="write first-frame and convergence times, bytes and a "
                   "per-frame series")
    h.add_argument("--screenshot", metavar="FINAL.png",
                   help="write the converged frame (headless: the last one; a window that stays open: the first "
                        "converged one, without the overlay)")
    h.add_argument("--frames-dir", metavar="DIR", help="write a PNG every --frame-every frames")
    h.add_argument("--frame-every", type=int, default=None, metavar="N",
                   help="with --frames-dir: a PNG every N frames (default 10)")
    h.add_argument("--measure-frames", type=int, default=0, metavar="N",
                   help="once converged, time N more frames (GPU work included) into --record's measured_frames_ms")
    w = p.add_argument_group("window")
    w.add_argument("--exit-when-converged", action="store_true",
                   help="close the window once the view has converged (after --screenshot, if given)")
    w.add_argument("--no-vsync", action="store_true", help="draw as fast as possible")
    w.add_argument("--no-overlay", action="store_true", help="open with the overlay hidden (O shows it)")
    p.add_argument("--drop-invalid", action="store_true", help=DROP_INVALID_HELP)
    p.add_argument("--quiet", "-q", action="store_true", help="no progress line")
    p.set_defaults(func=run)


def _options(args):
    # The GL client (the optional [view] extra, moderngl) is imported only by a command that draws, after gl_client()
    # has said how to install it where it is missing, and so that other commands start without it
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.streaming import ViewOptions

    if not (args.gpu_mem_mb > 0 and math.isfinite(args.gpu_mem_mb)):
        raise UsageError(f"--gpu-mem-mb {args.gpu_mem_mb:g}: expected a positive number of megabytes")
    if not (args.max_sse >= 0 and math.isfinite(args.max_sse)):
        raise UsageError(f"--max-sse {args.max_sse:g}: expected 0 or more pixels")
    if args.max_splats is not None and args.max_splats < 1:
        raise UsageError(f"--max-splats {args.max_splats}: expected at least 1")
    if not args.timeout > 0:
        raise UsageError(f"--timeout {args.timeout:g}: expected a positive number of seconds")
    if args.frame_every is not None and args.frame_every < 1:
        raise UsageError(f"--frame-every {args.frame_every}: expected at least 1")
    if args.measure_frames < 0:  # was taken as 0 without a word
        raise UsageError(f"--measure-frames {args.measure_frames}: expected 0 or more frames")
    if args.fill_min_kb is not None and not (args.fill_min_kb >= 0 and math.isfinite(args.fill_min_kb)):
        raise UsageError(f"--fill-min-kb {args.fill_min_kb:g}: expected 0 or more kilobytes")
    if args.fill_root_kb is not None and not (args.fill_root_kb >= 0 and math.isfinite(args.fill_root_kb)):
        raise UsageError(f"--fill-root-kb {args.fill_root_kb:g}: expected 0 or more kilobytes")
    if args.fill_gap < 1:
        raise UsageError(f"--fill-gap {args.fill_gap}: expected 1 or more levels")
    if args.fov_y is not None and not 0 < args.fov_y < 180:
        raise UsageError(f"--fov-y {args.fov_y:g}: expected degrees in (0, 180)")
    check_sort_draw(args.sort, args.draw)
    return ViewOptions(gpu_mem_mb=args.gpu_mem_mb, max_splats=args.max_splats, max_sse=args.max_sse,
                       sh_degree=3 if args.sh_degree is None else args.sh_degree, prefetch=not args.no_prefetch,
                       fill_levels=not args.skip_levels, fill_gap=args.fill_gap,
                       fill_min_bytes=ViewOptions.fill_min_bytes if args.fill_min_kb is None
                       else int(args.fill_min_kb * 1024),
                       fill_root_bytes=ViewOptions.fill_root_bytes if args.fill_root_kb is None
                       else int(args.fill_root_kb * 1024),
                       cache=not args.no_cache, drop_invalid=args.drop_invalid,
                       render=RenderOptions(sort=args.sort, draw=args.draw),
                       **_band_shares(args.sh_bands))


def _band_shares(text: str) -> dict:
    """--sh-bands: need (the default shares), all, or three shares of the view's area for bands 1..3."""
    if text == "need":
        return {}
    if text == "all":
        return {"band_area_share": (1.0, 1.0, 1.0)}
    try:
        shares = tuple(float(v) for v in text.split(","))
    except ValueError:
        shares = ()
    if len(shares) != 3 or not all(0.0 <= v <= 1.0 for v in shares):
        raise UsageError(f"--sh-bands {text}: expected need, all, or three shares of the view's area in [0, 1] "
                         "(e.g. 0.97,0.9,0.8)")
    return {"band_area_share": shares}


def _fixed_camera(args, size):
    """A camera from --eye/--target (both needed), or None for the scene's suggested camera. Its up is +z until
    the scene's is known (view_headless.start_camera) where --up is not given."""
    if args.eye is None and args.target is None:
        return None
    if args.eye is None or args.target is None:
        raise UsageError("--eye and --target go together (or give neither for the scene's camera)")
    eye, target = parse_vector(args.eye, "--eye"), parse_vector(args.target, "--target")
    up = parse_vector(args.up, "--up", nonzero=True) if args.up else (0.0, 0.0, 1.0)
    check_look(eye, target, args.fov_y)
    try:
        return Camera(eye, target, up, args.fov_y or DEFAULT_FOV_Y_DEG, size[0], size[1],
                      *look_at_near_far(eye, target))
    except ValueError as exc:
        raise UsageError(f"bad camera: {exc}") from None


# What `view` reads only from a local path: another tool's LOD tree or a splat file is encoded in memory first, and
# over HTTP the client reads our scene layout alone (http://HOST/scenes/ID).
_LOCAL_ONLY_SUFFIXES = ("lod-meta.json", "meta.json", ".rad", ".ply", ".spz", ".splat", ".sog", ".glb", ".gltf")


def check_served_source(source: str) -> None:
    """A URL naming a streamed SOG, a .rad or a splat file fails here in one line saying what `view` reads over
    HTTP, instead of a 404 for '.../lod-meta.json/manifest.msgpack' (a new user's `view
    http://HOST/playbot/lod-meta.json`)."""
    if not source.lower().startswith(("http://", "https://")):
        return
    path = source.split("?", 1)[0].split("#", 1)[0].rstrip("/").lower()
    if path.endswith(_LOCAL_ONLY_SUFFIXES):
        raise UsageError(f"{source}: over HTTP `view` streams a served scene (http://HOST/scenes/ID, `splatstream "
                         "serve`); a streamed SOG, a .rad or a splat file it reads from a local path (download it, "
                         "or encode it and serve the scene)")


def _check_outputs(args) -> None:
    for out in (args.record, args.screenshot):
        if out:
            check_output(out)
    if args.screenshot and os.path.splitext(args.screenshot)[1].lower() not in (".png", ""):
        raise UsageError(f"--screenshot: only .png images are written, got {args.screenshot!r}")
    # A window wrote no frames for --frames-dir and kept nothing of --until-converged, without a word (newuser60)
    for flag, given in (("--frames-dir", args.frames_dir), ("--until-converged", args.until_converged)):
        if given and not args.headless:
            raise UsageError(f"{flag}: only with --headless (a window saves its frame with P, or --screenshot)")
    # and the window's own options with --headless, or --frame-every without frames to space, were taken without a
    # word (newuser61)
    for flag, given in (("--exit-when-converged", args.exit_when_converged), ("--no-vsync", args.no_vsync),
                        ("--no-overlay", args.no_overlay)):
        if given and args.headless:
            raise UsageError(f"{flag} and --headless: {flag} is a window's (--headless shows no window, draws no "
                             "overlay and ends by itself)")
    if args.frame_every is not None and not args.frames_dir:
        raise UsageError(f"--frame-every {args.frame_every}: spaces the PNGs of --frames-dir, and none is given")
    if args.frames_dir:
        if not os.path.isdir(args.frames_dir):
            raise UsageError(f"--frames-dir {args.frames_dir}: no such directory")


def run(args: argparse.Namespace) -> int:
    offscreen = gl_client()  # first: the options below import the client
    size = parse_size(args.size)
    options = _options(args)
    camera = _fixed_camera(args, size)
    up = parse_vector(args.up, "--up", nonzero=True) if args.up else None
    azimuth = parse_azimuth(args.camera_azimuth)
    if args.camera_azimuth is not None and (camera is not None or args.camera_path):
        other = "--eye/--target" if camera is not None else "--camera-path"
        raise UsageError(f"--camera-azimuth turns the scene's camera; {other} gives another camera: give one of them")
    # The path's keyframes place the camera: --eye/--target, --up and --fov-y beside it were ignored without a word,
    # and so was --until-converged without a path (newuser61)
    if args.camera_path:
        beside = [flag for flag, given in (("--eye/--target", camera is not None), ("--up", args.up is not None),
                                           ("--fov-y", args.fov_y is not None)) if given]
        if beside:
            raise UsageError(f"--camera-path and {', '.join(beside)}: the path's keyframes place the camera (their "
                             "eye, target, up and fov_y); give one or the other")
    elif args.until_converged and args.headless:  # (in a window: refused as a headless option, below)
        raise UsageError("--until-converged: keeps a --camera-path view going after the path ends, and no "
                         "--camera-path is given (without one the view runs until converged anyway)")
    path = None
    if args.camera_path:
        path = load_camera_path(args.camera_path)
    _check_outputs(args)
    check_served_source(os.fspath(args.source))
    if not args.headless:
        from client_gl.window import WindowRun, run_window  # the GL client: see _options

        return run_window(WindowRun(args.source, options, size, camera, path, screenshot=args.screenshot,
                                    exit_when_converged=args.exit_when_converged, vsync=not args.no_vsync,
                                    timeout_s=args.timeout, quiet=args.quiet, sh_degree=args.sh_degree,
                                    record=args.record, measure_frames=args.measure_frames,
                                    overlay=not args.no_overlay, camera_azimuth_deg=azimuth, up=up,
                                    fov_y=args.fov_y))
    from client_gl.view_headless import HeadlessRun, run_headless  # the GL client: see _options

    ctx = offscreen.create_context()
    try:
        code, report = run_headless(HeadlessRun(
            args.source, options, size, camera, path, until_converged=args.until_converged or path is None,
            timeout_s=args.timeout, record=args.record, screenshot=args.screenshot, frames_dir=args.frames_dir,
            frame_every=10 if args.frame_every is None else args.frame_every, sh_degree=args.sh_degree,
            quiet=args.quiet,
            measure_frames=args.measure_frames, camera_azimuth_deg=azimuth, up=up, fov_y=args.fov_y), ctx)
    finally:
        ctx.release()
    if not args.quiet:
        ff = report["first_frame_s"]
        conv = report["converged_s"]
        print(f"view: first frame {ff:.3f} s, " if ff is not None else "view: no frame drawn, ", end="",
              file=sys.stderr)
        print(f"converged {conv:.3f} s, " if conv is not None else "not converged, ", end="", file=sys.stderr)
        print(transfer_and_memory(report, args.max_splats), file=sys.stderr)
    return code


def transfer_and_memory(report: dict, max_splats: int | None = None) -> str:
    """'4,721 splats drawn, 1.80 MB read, GPU 3.1 MiB for 4,721 resident splats (budget 1024 MiB)': the splats the
    last frame drew (against --max-splats where one is set: resident splats alone, which keep the coarser tiles
    drawn on the way, read as over the budget), bytes read from a local scene or downloaded from a server (and those
    taken from the disk cache), and the GPU memory the resident splats use against the budget as given (the pool
    itself is allocated whole up front: its size says nothing about the scene)."""
    local = report.get("fetch", {}).get("manifest_source") == "local"
    splats = report.get("resident_splats", 0)
    drawn = report.get("drawn_splats")
    shown = "" if drawn is None else f"{drawn:,} splat{'' if drawn == 1 else 's'} drawn" + (
        f" (--max-splats {max_splats:,})" if max_splats is not None else "") + ", "
    # A splat file, SOG or .rad is read whole and encoded in memory before the first frame; the bytes counted are
    # the tiles taken from that encode: 'guitar.spz ... 0.52 MB read' read as if 0.52 of its 1.40 MB were read.
    source = report.get("source")
    if local and isinstance(source, str) and not os.path.isfile(os.path.join(source, MANIFEST_NAME)):
        local_word = "read from its in-memory encode (the file read whole first)"
    else:
        local_word = "read"
    # Payloads taken from the disk cache are neither read from the scene nor downloaded: a second view of a served
    # scene said '0.00 MB downloaded' and no more, as if nothing had been loaded.
    cached = report.get("fetch", {}).get("bytes_from_cache", 0)
    from_cache = f" ({cached / 1e6:.2f} MB from the disk cache)" if cached else ""
    # The budget as given (--gpu-mem-mb 0.5 printed 'budget 0 MiB' beside 'GPU 0.5 MiB', read as over it).
    return (f"{shown}{report['bytes_downloaded'] / 1e6:.2f} MB {local_word if local else 'downloaded'}{from_cache}, "
            f"GPU {report['resident_gpu_bytes'] / 2**20:.1f} MiB for {splats:,} resident "
            f"splat{'' if splats == 1 else 's'} (budget {mib(report['gpu_budget_bytes'])} MiB)")
