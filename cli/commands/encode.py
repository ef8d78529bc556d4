"""`splatstream encode INPUT OUTPUT_DIR`."""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable

from splatstream.cores import available_cores
from splatstream.encode import encode_file
from splatstream.encode.codebook import refuse_without_sh_bands
from splatstream.encode.driver import count_edits
from splatstream.encode.options import EncodeOptions, default_lod_merge
from splatstream.errors import UsageError
from splatstream.evaluate import EvalOptions, evaluate, preset_for_target
from splatstream.format.container import DEFAULT_ZSTD_LEVEL
from splatstream.format.presets import (
    ATTRIBUTES,
    DEFAULT_PRESET,
    PRESET_SH_CODEBOOK,
    PRESET_SUMMARY,
    PRESET_ZSTD_LEVEL,
    PRESETS,
)
from splatstream.format.texformats import VALUE_FORMATS
from splatstream.format.transport import TRANSPORTS
from splatstream.io import FORMAT_NAMES, open_input
from splatstream.lod import LOD_MERGES
from splatstream.lod_refine import CPU_ITERATIONS, CPU_SIZE_PX, GPU_ITERATIONS, GPU_SIZE_PX, LodRefiner
from splatstream.progress import ProgressPrinter, count
from splatstream.rad_import import read_tree as rad_read_tree
from splatstream.sh import warn_sh_degree_above
from splatstream.sog_import import encode_tree_to
from splatstream.sog_import import read_tree as sog_read_tree

from .args import (
    DROP_INVALID_HELP,
    MAX_RENDER_SIDE,
    add_edit_arguments,
    edit_report,
    edits_from,
    parse_azimuth,
    parse_bytes,
    parse_vector,
)
from .renderers import pick_renderer

# The views --target-psnr / --target-size measure presets on: `splatstream eval`'s defaults.
TARGET_VIEWS = 8
TARGET_SIZE = 512


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "encode", help="encode a splat file into a compact, streamable scene directory",
        description="Read a 3DGS scene (standard PLY and other supported formats) and write a scene directory: "
                    "Morton-ordered 256-splat chunks quantised per chunk into GPU texture planes, SH bands in "
                    "separate payloads, LOD tiles, a msgpack manifest. Presets (texel formats per attribute): "
                    + "; ".join(f"{k}: " + ", ".join(f"{a}={f}" for a, f in v.items()) for k, v in PRESETS.items())
                    + ". SH bands 1..3 in a scene-wide codebook: "
                    + ", ".join(f"{k} ({v})" for k, v in PRESET_SH_CODEBOOK.items()),
    )
    p.add_argument("input", nargs="+", metavar="INPUT",
                   help="input splat file (.ply; other formats are detected by content); several "
                        "are merged into one scene, in the order given (SH bands an input "
                        "lacks are zeros; the edits apply to the merged splats)")
    p.add_argument("output_dir", metavar="OUTPUT_DIR",
                   help="scene directory to write (replaced atomically if it exists), or an fsspec URL "
                        "(s3://bucket/scene, gs://..., needs the cluster extra): payloads first, the "
                        "manifest last")
    p.add_argument("--preset", default=None, choices=list(PRESETS), metavar="PRESET",
                   help="quality preset, from the largest files to the smallest: "
                        + "; ".join(f"{k} ({v})" for k, v in PRESET_SUMMARY.items()).replace("%", "%%")
                        + f". Default {DEFAULT_PRESET}")
    target = p.add_mutually_exclusive_group()
    target.add_argument("--target-psnr", type=float, metavar="DB",
                        help="instead of --preset: measure every preset on this scene as `splatstream eval` does "
                             f"(--target-views orbit views at {TARGET_SIZE}x{TARGET_SIZE}, PSNR against the "
                             "original, the GL renderer where it opens, else the numpy reference) and encode with "
                             "the one of the smallest files whose mean PSNR is at least DB")
    target.add_argument("--target-size", type=float, metavar="B",
                        help="instead of --preset: as --target-psnr, the preset of the highest PSNR whose scene "
                             "as written takes at most B bytes per splat on disk (every file: with the LOD tree's "
                             "coarse levels unless --no-lod; the presets are measured with this encode's LOD, "
                             "page, transport and chunk-order options)")
    p.add_argument("--target-views", type=int, default=TARGET_VIEWS, metavar="N",
                   help=f"orbit views --target-psnr / --target-size measure on (default {TARGET_VIEWS}: fewer, "
                        "faster and noisier)")
    for attr in ATTRIBUTES:
        p.add_argument(f"--{attr}", dest=f"fmt_{attr}", choices=list(VALUE_FORMATS), metavar="FORMAT",
                       help=f"texel format of {attr}, overriding the preset ({', '.join(VALUE_FORMATS)})"
                            + ("; refused where the scene keeps no SH band 1..3 (an SH0 input, --sh-degree 0)"
                               if attr == "sh" else ""))
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], help="drop SH bands above this degree")
    p.add_argument("--sh-codebook", metavar="off|auto|fine|large|N",
                   help="vector-quantise SH bands 1..3 into a scene-wide codebook of N entries (at most 65536; "
                        "auto: about one per 64 splats; fine: about one per 16, 256..16384; large: about one per 8, "
                        "256..65536) with a 16-bit index per splat; the sh format then applies to the codebook; "
                        "refused, but for off, where the scene keeps no SH band (an SH0 input, --sh-degree 0). "
                        "Default: the preset's choice ("
                        + ", ".join(f"{k}: {v}" for k, v in PRESET_SH_CODEBOOK.items()) + "; the others: off)")
    p.add_argument("--no-lod", action="store_true", help="write one tile holding every splat (no LOD tree)")
    p.add_argument("--rebuild-lod", action="store_true",
                   help="a streamed SOG (lod-meta.json) or a Spark .rad: build our own LOD tree from its finest "
                        "level (default: keep its own tree, level for level; --max-leaf-splats and --reduction then "
                        "follow it); refused where no input has a tree of its own")
    p.add_argument("--max-leaf-splats", type=int, default=None,
                   help="splats per leaf tile at most (default 16384: measured best for streaming)")
    p.add_argument("--reduction", type=float, default=None,
                   help="each LOD level keeps about 1/REDUCTION of the splats of the level below (default 2)")
    p.add_argument("--lod-merge", choices=LOD_MERGES, default=EncodeOptions.lod_merge,
                   help="how LOD levels are merged: grid (a Morton grid per tile, every tile halved) or "
                        "cost (groups by merge cost over each whole level, the splats each tile keeps decided "
                        "across the scene) or auto (the cost merge's counts, and per tile the cost merge's groups or "
                        "the grid's, whichever is closer to the tile's splats); cost in-process encodes only. "
                        "Default: auto (sharper at most splat budgets, 1.4-1.9x the grid's encode CPU: "
                        "BENCHMARKS.md, LOD against peers); a partitioned encode (--workers, --scheduler, a scene "
                        "over --memory-per-worker) runs it inside partitions of at most "
                        f"{EncodeOptions.lod_merge_domain_splats:,} splats and over the levels above them, and "
                        "takes the grid where such a partition does not fit a worker")
    p.add_argument("--page-tiles", type=int, default=None,
                   help="write a tree of more than N tiles as a root manifest and manifest pages, so a client needs "
                        f"only the tree's top before its first frame (format 1.5; 0: never; default "
                        f"{EncodeOptions.page_tiles}: measured, BENCHMARKS.md)")
    p.add_argument("--page-levels", type=int, default=None,
                   help=f"tree levels in the root manifest and in each page (default {EncodeOptions.page_levels})")
    p.add_argument("--no-compact-table", action="store_true",
                   help="write a tree's tiles as format 1.8's tile table, not the compact one of 1.12 (f32 bounds "
                        "rounded outward, zstd: a third of the manifest's bytes, which a small budget reads before "
                        "any tile; BENCHMARKS.md), for readers older than 1.12")
    p.add_argument("--no-short-digests", action="store_true",
                   help="name a tree's files by their whole SHA-256 (format 1.12), not by its first 16 bytes as "
                        "1.15 does (16 B a payload less in the manifest a small budget reads first), for readers "
                        "older than 1.15")
    p.add_argument("--no-relative-boxes", action="store_true",
                   help="write a tree's boxes and radii as f32 (format 1.15), not as u8 steps of the parent's box and "
                        "of the half diagonal as 1.16 does (about 1.2 KB less in the manifest), for readers older "
                        "than 1.16")
    p.add_argument("--zstd-level", type=int, default=None,
                   help=f"zstd level of the payloads (1..22; default {DEFAULT_ZSTD_LEVEL}, "
                        + ", ".join(f"{k} {v}" for k, v in PRESET_ZSTD_LEVEL.items())
                        + ": level 1 is as small as level 3 on the transport-coded planes and twice as fast; "
                        "higher levels gain 0-4%% at 5-50x the time, and on SH planes with the LOD tree they can "
                        "write more: BENCHMARKS.md)")
    p.add_argument("--transport", default=None, choices=list(TRANSPORTS),
                   help="how payload sections are stored: fields (default; the fields1 coding where it is smaller "
                        "than the byte shuffle, format 1.2), keyed (fields, and norm16x4 positions sorted inside "
                        "chunks and stored as Morton key differences where smaller, format 1.6: about 0.3 B/splat "
                        "smaller at 12-bit positions, slower to decode), shuffle (format 1.0/1.1, for readers before "
                        "1.2), none")
    p.add_argument("--chunk-order", default="auto", choices=["auto", "morton", "luminance"],
                   help="order of splats inside each chunk: luminance groups similar colours into the same BC block; "
                        "auto (default) uses it when colour or SH, but not position/rotation/scale, are BC-compressed")
    p.add_argument("--name", help="scene name recorded in the manifest (default: the input file's name; for a "
                   "lod-meta.json or meta.json, its directory's)")
    p.add_argument("--up", help="up vector of the scene, e.g. 0,-1,0 (3DGS/COLMAP captures) or 0,0,1 (z-up tools); "
                               "default: detected (y down unless the splats' surfaces show z up)")
    p.add_argument("--camera-azimuth", metavar="DEG",
                   help="turn the scene's suggested camera (the manifest's camera: where a viewer opens) by DEG "
                        "degrees about up, around what it looks at (180: the other side; positive: counter-clockwise "
                        "seen from above); default 0, the suggested camera as framed")
    p.add_argument("--drop-invalid", action="store_true", help=DROP_INVALID_HELP)
    cluster = p.add_argument_group(
        "large scenes and clusters",
        "Scenes that do not fit in memory are encoded by partitions (subtrees of the tile tree), in this process or "
        "on Dask (pip install 'splatstream[cluster]'). The output is identical whatever the engine, the number of "
        "workers or partitions.")
    cluster.add_argument("--workers", metavar="N|auto",
                         help="encode on a local Dask cluster of N worker processes (auto: one per core)")
    cluster.add_argument("--scheduler", metavar="ADDRESS",
                         help="encode on an existing Dask cluster (tcp://host:8786); input, output and --scratch "
                              "must be reachable from every worker (a shared file system or URLs)")
    cluster.add_argument("--memory-per-worker", metavar="SIZE",
                         help="memory a worker may use (e.g. 4GB): decides the partition size (default: half the "
                              "worker's Dask memory limit; in this process half the available memory)")
    cluster.add_argument("--scratch", metavar="PATH|URL",
                         help="where partitions are spilled (default: next to the output, or the system's temporary "
                              "directory for a URL output)")
    refine = p.add_argument_group(
        "refining the LOD levels (optional)",
        "The merged LOD levels fitted to renders of the full detail after the tree is built (format_spec/lod.md 6); "
        "the full detail is unchanged. On a GPU (--lod-refine, or --lod-refine gpu): torch, gsplat and a CUDA GPU "
        "(pip install 'splatstream[refine]'). On the CPU (--lod-refine cpu): numba (pip install "
        "'splatstream[fast]'), the merged splats' opacity and DC colour only.")
    refine.add_argument("--lod-refine", nargs="?", const="gpu", type=_refiner_name, metavar="{gpu,cpu}", default=None,
                        help="refine every merged level against renders of the full-detail scene from cameras around "
                             "it, judged on other cameras (a level stays as built where no fit beats it); recorded in "
                             "the manifest (format 1.11). gpu (the default): gsplat, two variants per level (B: "
                             "opacity, DC colour, scales; C: also positions and rotations); cpu: a numba rasteriser, "
                             "variant A (opacity and DC colour, the geometry fixed), also by partitions (--workers, "
                             "--scheduler, a scene over the memory: each merge domain against its own originals, the "
                             "levels above them against the domains' refined roots; format_spec/lod.md 6). gpu: "
                             "in-memory encodes only")
    refine.add_argument("--lod-refine-iters", type=int, default=None, metavar="N",
                        help=f"optimiser steps per level and variant (default {GPU_ITERATIONS} on the GPU, "
                             f"{CPU_ITERATIONS} steps on the CPU, each over half its cameras)")
    refine.add_argument("--lod-refine-size", type=int, default=None, metavar="PX",
                        help=f"square size of the training and validation renders (default {GPU_SIZE_PX} on the GPU, "
                             f"{CPU_SIZE_PX} on the CPU)")
    add_edit_arguments(p, taken=("--scale",))
    p.add_argument("--quiet", "-q", action="store_true", help="no progress display")
    p.set_defaults(func=run)


def _refiner_name(value: str) -> str:
    # The value is optional, so argparse gives --lod-refine the next word whatever it is: a scene or an output
    # directory after the option would read as the refiner's name; the message says how to write it instead.
    if value in ("gpu", "cpu"):
        return value
    raise argparse.ArgumentTypeError(f"{value!r} is neither gpu nor cpu (to refine on the GPU with the scene or "
                                     "output directory after it, write --lod-refine=gpu, or put the option last)")


def _tree_options_given(args: argparse.Namespace) -> list[str]:
    """The options of the LOD tree we build given on the command line (each None where not given)."""
    return [flag for flag, given in (("--max-leaf-splats", args.max_leaf_splats is not None),
                                     ("--reduction", args.reduction is not None),
                                     ("--lod-merge", args.lod_merge is not None),
                                     ("--page-tiles", args.page_tiles is not None),
                                     ("--page-levels", args.page_levels is not None),
                                     ("--rebuild-lod", args.rebuild_lod)) if given]


def run(args: argparse.Namespace) -> int:
    # --no-lod writes one tile: the tree's options were taken without a word (newuser61)
    tree_given = _tree_options_given(args)
    if args.no_lod and tree_given:
        named = ", ".join(tree_given)
        raise UsageError(f"--no-lod and {named}: --no-lod writes one tile holding every splat, with no LOD tree for "
                         f"{named} to shape; give one or the other")
    args.tree_options_given = tree_given
    defaults = EncodeOptions()
    args.max_leaf_splats = defaults.max_leaf_splats if args.max_leaf_splats is None else args.max_leaf_splats
    args.reduction = defaults.reduction if args.reduction is None else args.reduction
    args.page_tiles = defaults.page_tiles if args.page_tiles is None else args.page_tiles
    args.page_levels = defaults.page_levels if args.page_levels is None else args.page_levels
    overrides = {a: getattr(args, f"fmt_{a}") for a in ATTRIBUTES if getattr(args, f"fmt_{a}")}
    if args.max_leaf_splats < 256:
        raise UsageError("--max-leaf-splats must be at least 256 (one chunk)")
    if args.reduction <= 1.0:
        raise UsageError("--reduction must be greater than 1")
    if args.page_tiles < 0 or args.page_levels < 1:
        raise UsageError("--page-tiles must be 0 or more and --page-levels at least 1")
    if args.zstd_level is not None and not 1 <= args.zstd_level <= 22:
        raise UsageError("--zstd-level must be between 1 and 22")
    up = parse_vector(args.up, "--up", nonzero=True) if args.up else None
    azimuth = parse_azimuth(args.camera_azimuth)
    workers = None
    if args.workers is not None:
        if args.workers == "auto":
            workers = available_cores()
        elif args.workers.isdigit() and int(args.workers) >= 1:
            workers = int(args.workers)
        else:
            raise UsageError(f"--workers: expected a worker count of at least 1 or auto, got {args.workers!r}")
    if workers is not None and args.scheduler:
        raise UsageError("--workers starts a local cluster, --scheduler uses an existing one: give one of them")
    memory = parse_bytes(args.memory_per_worker, "--memory-per-worker") if args.memory_per_worker else None
    edits = edits_from(args)
    if args.dry_run:
        print(edit_report(" + ".join(args.input), *count_edits(args.input, edits, args.drop_invalid)[1:]))
        return 0
    if not args.lod_refine and (args.lod_refine_iters is not None or args.lod_refine_size is not None):
        raise UsageError("--lod-refine-iters and --lod-refine-size set the refinement: give them with --lod-refine "
                         "(gpu or cpu)")
    lod_refiner = _lod_refiner(args, workers) if args.lod_refine else None
    tree_kind = _foreign_tree(args)
    t0 = time.perf_counter()
    preset = args.preset or DEFAULT_PRESET
    if args.target_psnr is not None or args.target_size is not None:
        if edits or len(args.input) > 1:
            raise UsageError("--target-psnr / --target-size measure one input as read: give them one input, without "
                             "edits")
        if args.preset or overrides or args.sh_degree is not None or args.sh_codebook is not None:
            raise UsageError("--target-psnr / --target-size choose the preset: give them without --preset, texel "
                             "formats, --sh-degree or --sh-codebook")
        preset = _preset_for_target(args, up, distributed=workers is not None or bool(args.scheduler))
    progress = ProgressPrinter("encode", enabled=not args.quiet)

    def check_read(sh_degree: int) -> None:
        _check_sh_format(args, overrides, " + ".join(args.input), sh_degree)
        warn_sh_degree_above(args.sh_degree, sh_degree, " + ".join(args.input))

    with progress.library_notes():
        if tree_kind is not None:
            m = _encode_foreign_tree(args, tree_kind, preset, overrides, up, azimuth, progress)
        else:
            m = encode_file(args.input, args.output_dir, preset=preset, drop_invalid=args.drop_invalid,
                            progress=progress, workers=workers, scheduler=args.scheduler, memory_per_worker=memory,
                            scratch=args.scratch, edits=edits, overrides=overrides, sh_degree=args.sh_degree,
                            zstd_level=args.zstd_level, transport=args.transport,
                            lod=not args.no_lod, max_leaf_splats=args.max_leaf_splats, reduction=args.reduction,
                            lod_merge=args.lod_merge, name=args.name, up=up, chunk_order=args.chunk_order,
                            sh_codebook=args.sh_codebook, page_tiles=args.page_tiles, page_levels=args.page_levels,
                            compact_table=not args.no_compact_table, short_digests=not args.no_short_digests,
                            relative_boxes=not args.no_relative_boxes, lod_refiner=lod_refiner,
                            camera_azimuth_deg=azimuth, on_read=check_read)
    if not args.quiet:
        print(f"wrote {args.output_dir}: {count(m.splats, 'splat')}, SH degree {m.sh_degree}, preset {m.preset}, "
              f"{count(len(m.tiles), 'tile')}, {_disk_size(m.bytes_on_disk)} on disk "
              f"({m.leaf_bytes_on_disk / m.splats:,.2f} B/splat at full detail, {m.bytes_on_disk / m.splats:,.2f} "
              f"with all LOD levels), {m.gpu_bytes_per_splat:,.2f} B/splat on the GPU, "
              f"{time.perf_counter() - t0:.2f}s", file=sys.stderr)
    return 0


def _check_sh_format(args: argparse.Namespace, overrides: dict, source: str, sh_degree: int) -> None:
    """Refuse `--sh FORMAT` where the scene keeps no SH band 1..3 for it to format (an SH0 input, or --sh-degree 0),
    as --sh-codebook is. Here, once the input is read, and not in the core: eval's attribution runs give every scene
    an `sh` override, and a preset's own SH format encodes any input."""
    fmt = overrides.get("sh")
    if fmt is not None:
        refuse_without_sh_bands(f"--sh {fmt}", source, sh_degree, args.sh_degree, "an SH format")


def _lod_refiner(args: argparse.Namespace, workers: int | None) -> LodRefiner:
    """The refiner of --lod-refine (refine_gpu.levels on a GPU, refine_cpu.levels on the CPU), or a UsageError naming
    what is missing or what does not go with it: checked before the scene is read (importing torch takes seconds;
    gsplat builds its CUDA extension on first use, then keeps it)."""
    if args.no_lod:
        raise UsageError("--lod-refine refines the LOD tree's merged levels: not with --no-lod")
    if args.lod_refine == "gpu" and (workers is not None or args.scheduler):
        raise UsageError("--lod-refine gpu refines in-memory encodes only, not with --workers or --scheduler (a "
                         "partitioned encode): its fit is not measured by partitions, and every Dask worker process "
                         "would hold a CUDA context of its own on the GPU; refine with --lod-refine cpu")
    if args.target_psnr is not None or args.target_size is not None:
        raise UsageError("--lod-refine: not with --target-psnr / --target-size (they measure unrefined encodes)")
    if args.lod_refine_iters is not None and args.lod_refine_iters < 1:
        raise UsageError(f"--lod-refine-iters {args.lod_refine_iters}: expected at least 1 step")
    # at most render's and view's largest side: a larger one would fail only once its renders are allocated
    if args.lod_refine_size is not None and not 16 <= args.lod_refine_size <= MAX_RENDER_SIDE:
        raise UsageError(f"--lod-refine-size {args.lod_refine_size}: expected 16 to {MAX_RENDER_SIDE} px")

    def log(msg: str) -> None:
        if not args.quiet:
            print(f"lod-refine: {msg}", file=sys.stderr, flush=True)

    if args.lod_refine == "cpu":
        return _cpu_refiner(args, log, workers)
    # The GPU shell, an optional extra: imported only when asked for. (It needs numpy and the core alone; an install
    # made before the package existed does not see it.)
    try:
        from refine_gpu.levels import EXTRA, LevelRefiner, RefineSettings, missing
    except ImportError as exc:
        raise UsageError(f"--lod-refine: the refine_gpu package of this splatstream cannot be imported ({exc}); "
                         "reinstall splatstream (pip install -e '.[refine]' in a checkout)") from None

    lack = missing()
    if lack is not None:
        raise UsageError(f"--lod-refine needs torch, gsplat and a CUDA GPU: {lack} (install the extra: {EXTRA}; "
                         "or refine on the CPU: --lod-refine cpu)")
    return LevelRefiner(RefineSettings(iterations=args.lod_refine_iters or GPU_ITERATIONS,
                                       size=args.lod_refine_size or GPU_SIZE_PX, log=log))


def _cpu_refiner(args: argparse.Namespace, log: Callable[[str], None], workers: int | None) -> LodRefiner:
    """refine_cpu.levels.CpuLevelRefiner (numba, the `fast` extra), imported only when asked for."""
    try:
        import numba  # noqa: F401
    except ImportError:
        raise UsageError("--lod-refine cpu needs numba, which is not installed (install the extra: pip install "
                         "'splatstream[fast]')") from None
    try:
        from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings
    except ImportError as exc:
        raise UsageError(f"--lod-refine cpu: the refine_cpu package of this splatstream cannot be imported ({exc}); "
                         "reinstall splatstream (pip install -e '.[fast]' in a checkout)") from None
    # --workers N on this machine: the fits that run at once share its cores (CpuLevelRefiner.for_concurrent_fits,
    # asked by the partitioned encode); an existing cluster's workers keep numba's default: their machines are not this
    return CpuLevelRefiner(CpuRefineSettings(iterations=args.lod_refine_iters or CPU_ITERATIONS,
                                        size=args.lod_refine_size or CPU_SIZE_PX, log=log,
                                        share_cores=workers is not None))


def _foreign_tree(args: argparse.Namespace) -> str | None:
    """"lod_sog" or "rad" where the one input is an LOD tree of a peer's that `encode` keeps, else None."""
    if len(args.input) > 1 and not args.no_lod:
        # Several inputs are merged into one splat set whose tree is ours: a peer's tree among them is not kept.
        for path in args.input:
            if os.path.exists(path) and open_input(path).format in ("lod_sog", "rad"):
                print(f"encode: {path} holds its own LOD tree; merged with the other inputs its finest level is "
                      "read and our tree built over all of them", file=sys.stderr)
    if args.rebuild_lod and all(os.path.exists(path) for path in args.input):
        # taken without a word where no input has a tree of its own (a SOG v1, a PLY): ours is built anyway (newuser62)
        kinds = [open_input(path).format for path in args.input]
        if not {"lod_sog", "rad"} & set(kinds):
            held = "; ".join(f"{path} is a {FORMAT_NAMES.get(kind, kind)}" for path, kind in zip(args.input, kinds,
                                                                                                  strict=True))
            raise UsageError(f"--rebuild-lod builds our LOD tree in place of a streamed SOG's (lod-meta.json) or a "
                             f".rad's own; {held}, with no tree of its own: ours is built anyway, leave the option out")
    if len(args.input) != 1 or args.no_lod or args.rebuild_lod or not os.path.exists(args.input[0]):
        return None  # (a missing input fails in encode_file, with its usual message)
    kind = open_input(args.input[0]).format
    if kind not in ("lod_sog", "rad"):
        return None
    given = [flag for flag, on in (("edits", bool(edits_from(args))), ("--workers", args.workers is not None),
                                   ("--scheduler", bool(args.scheduler)), ("--lod-refine", args.lod_refine),
                                   ("--target-psnr/--target-size",
                                    args.target_psnr is not None or args.target_size is not None),
                                   # its tree kept: these were taken without a word (newuser61)
                                   *((flag, True) for flag in args.tree_options_given
                                     if flag in ("--max-leaf-splats", "--reduction", "--lod-merge"))) if on]
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        # --no-lod goes with neither --lod-refine nor the tree's own options
        no_lod = not (args.lod_refine or set(given) & {"--max-leaf-splats", "--reduction", "--lod-merge"})
        raise UsageError(f"{args.input[0]} holds its own LOD tree, which encode keeps (in memory, as read): "
                         f"{', '.join(given)} {verb} only to a tree we build; add --rebuild-lod to build ours from "
                         "its finest level" + (", or --no-lod for its finest level alone" if no_lod else ""))
    return kind


def _encode_foreign_tree(args: argparse.Namespace, kind: str, preset: str, overrides: dict, up, azimuth: float,
                         progress):
    """Their tree kept: read whole (sog_import / rad_import.read_tree) and encoded level for level."""
    reader = sog_read_tree if kind == "lod_sog" else rad_read_tree
    opts = EncodeOptions(preset=preset, overrides=overrides, sh_degree=args.sh_degree,
                         zstd_level=args.zstd_level, transport=args.transport, name=args.name, up=up,
                         chunk_order=args.chunk_order, sh_codebook=args.sh_codebook, page_tiles=args.page_tiles,
                         page_levels=args.page_levels, compact_table=not args.no_compact_table,
                         short_digests=not args.no_short_digests, relative_boxes=not args.no_relative_boxes,
                         camera_azimuth_deg=azimuth)
    tree = reader(args.input[0], progress)
    if "sh" in overrides:
        _check_sh_format(args, overrides, args.input[0],
                         max((g.sh_degree for levels in tree.splats.values() for g in levels.values()), default=0))
    return encode_tree_to(tree, args.output_dir, args.input[0], opts, progress)


def target_lod_merge(named: str | None, distributed: bool) -> str:
    """The LOD merge --target-psnr / --target-size measure presets with: the one the encode will build (the
    default is auto on either engine), so that the bytes compared are the output's."""
    return named if named is not None else default_lod_merge(in_memory=not distributed)


def _disk_size(nbytes: int) -> str:
    """'4.42 MB', or '2,149 bytes' below 10 kB (a tiny scene read '0.00 MB on disk': newuser63)."""
    return f"{nbytes / 1e6:.2f} MB" if nbytes >= 10_000 else f"{nbytes:,} bytes"


def _preset_for_target(args: argparse.Namespace, up: tuple[float, float, float] | None, distributed: bool) -> str:
    """Measure every preset on the input (splatstream.evaluate) and pick the one the target asks for."""
    if args.target_psnr is not None and not args.target_psnr > 0:
        raise UsageError(f"--target-psnr {args.target_psnr:g}: expected a PSNR above 0 dB")
    if args.target_size is not None and not args.target_size > 0:
        raise UsageError(f"--target-size {args.target_size:g}: expected a size above 0 bytes per splat")
    if args.target_views < 1:
        raise UsageError(f"--target-views {args.target_views}: expected at least 1")

    def log(msg: str) -> None:
        if not args.quiet:
            # rstrip only: the rows' labels are padded so that their numbers stand in columns
            print(f"target: {msg.rstrip()}", file=sys.stderr)

    # Every preset encoded as this encode will write it (the LOD tree and its options, pages, transport, chunk
    # order), so the bytes compared with --target-size are those of the scene on disk, not of its full detail only.
    opts = EvalOptions(views=args.target_views, width=TARGET_SIZE, height=TARGET_SIZE, up=up,
                       zstd_level=args.zstd_level, lod=not args.no_lod,
                       encode_options={"max_leaf_splats": args.max_leaf_splats, "reduction": args.reduction,
                                       "lod_merge": target_lod_merge(args.lod_merge, distributed),
                                       "page_tiles": args.page_tiles, "page_levels": args.page_levels,
                                       "compact_table": not args.no_compact_table,
                                       "short_digests": not args.no_short_digests,
                                       "relative_boxes": not args.no_relative_boxes,
                                       "transport": args.transport,
                                       "chunk_order": args.chunk_order})
    report = evaluate(args.input[0], opts, log=log, renderer=pick_renderer("auto"))
    try:
        row = preset_for_target(report["rows"], target_psnr=args.target_psnr, target_bytes=args.target_size)
    except UsageError as exc:
        if args.target_size is None or not opts.lod:
            raise
        # the coarse levels about double a scene's bytes (reduction 2): a size met at full detail may not be met here
        raise UsageError(f"{exc}, all LOD levels counted (--no-lod: the full detail "
                         "alone)") from None
    psnr = "identical" if row["psnr_mean"] is None else f"{row['psnr_mean']:.2f} dB"
    what = f"PSNR >= {args.target_psnr:g} dB" if args.target_psnr is not None else f"<= {args.target_size:g} B/splat"
    sized = "with all LOD levels" if opts.lod else "without an LOD tree (--no-lod)"
    log(f"{what}: preset {row['label']} ({row['disk_bytes_per_splat']:.2f} B/splat on disk {sized}, "
        f"{row['leaf_bytes_on_disk'] / row['splats']:.2f} at full detail; {psnr} mean PSNR of the full detail over "
        f"{count(args.target_views, 'view')})")
    return str(row["label"])
