"""The encode driver: a splat file into a scene, on the engine that fits it.

The input is opened once (io.open_input: its format sniffed, a PLY's header parsed), the options checked before
anything is read or written, then one engine runs: in memory (local.encode_to) when the scene fits, else by
partitions (partitioned.encode_partitioned) in this process (local.LocalEngine) or on Dask
(distributed.DaskEngine). The output is the same in every case (tests/test_encode_bytes.py).
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import replace

from ..atomic import check_output
from ..camera import check_azimuth
from ..edit import Pipeline
from ..errors import UsageError
from ..format.manifest import Manifest
from ..format.names import MANIFEST_NAME
from ..format.presets import DEFAULT_PRESET
from ..gaussians import Gaussians
from ..io import SplatInput, open_input, read_gaussians, read_merged
from ..lod import LOD_MERGES, Tile
from ..ply import RowStats, VertexLayout, check_rows, read_ply_rows
from ..store import check_store_reachable, is_url, local_path, open_writer
from ..vq import parse_entries
from .distributed import DaskEngine
from .local import LocalEngine, default_memory_per_worker, encode_to
from .options import EncodeOptions, Progress, no_progress
from .partitioned import PARTITION_MEMORY_FACTOR, ConcatRows, encode_partitioned, open_rows, routed_row_bytes
from .plan import log, plan_formats
from .scratch import Scratch


def fits_in_process(layout: VertexLayout | None | list[VertexLayout | None], opts: EncodeOptions,
                    memory: int) -> bool:
    """Whether the whole scene is encoded in memory (as encode_gaussians does) rather than by partitions: no LOD,
    an input that is read whole anyway (`layout` None: not a binary PLY; of merged inputs, any one), or one whose
    build, and the refiner's fit where it says its memory (LodRefiner's peak_bytes), fit the memory. The output is
    the same (with auto, for a scene of one merge domain: partitioned.py)."""
    layouts = layout if isinstance(layout, list) else [layout]
    if not opts.lod or any(x is None for x in layouts):
        return True
    top = max(x.sh_degree for x in layouts)  # type: ignore[union-attr]
    degree = top if opts.sh_degree is None else min(opts.sh_degree, top)
    rows = sum(x.rows for x in layouts)  # type: ignore[union-attr]
    need = rows * routed_row_bytes(degree) * PARTITION_MEMORY_FACTOR
    peak = getattr(opts.lod_refiner, "peak_bytes", None)
    if peak is not None:  # the fit follows the build: the tree held (about twice the splats) and the fit's own peak
        need = max(need, 2 * rows * routed_row_bytes(degree) + peak(rows, routed_row_bytes(degree)))
    return need <= memory


def _paths(input_path: str | os.PathLike | Sequence[str | os.PathLike]) -> list[str]:
    if isinstance(input_path, (str, os.PathLike)):
        return [local_path(input_path)]
    paths = [local_path(p) for p in input_path]
    if not paths:
        raise UsageError("no input given")
    return paths


def _declared_up(sources: list[SplatInput]):
    """The up direction the inputs state, when every one states the same (else detected from the merged splats)."""
    stated = [s.declared_up() for s in sources]
    if stated[0] is None or any(x is None or x.up != stated[0].up for x in stated):
        return None
    return stated[0]


# Why a whole-scene edit (the density filter) and a partitioned encode do not go together, and what to do instead.
_WHOLE_SCENE_EDITS = ("--filter-density counts each splat's neighbours over the whole scene, which the partitioned "
                      "encoder (edits chunk by chunk; --workers, --scheduler, or a scene larger than "
                      "--memory-per-worker) cannot do exactly: give a --memory-per-worker the scene fits in, or "
                      "clean it first with `splatstream convert IN clean.ply --filter-density ...` and encode that")
_COST_MERGE_IN_PROCESS = ("--lod-merge {} groups each LOD level over the whole scene, which the partitioned encoder "
                          "(subtrees built apart; --workers, --scheduler, or a scene larger than "
                          "--memory-per-worker) cannot do: give a --memory-per-worker the scene fits in, or use "
                          "--lod-merge auto (inside each partition) or grid")

_REFINE_NO_LOD = "--lod-refine refines the merged levels of the LOD tree: not with --no-lod"
# A refiner that says it runs by partitions (LodRefiner.runs_by_partitions: refine_cpu's) refines a partitioned
# encode's merge domains in their own tasks (lod.md 6, "The refinement by partitions"); the others only in memory.
_REFINE_IN_PROCESS = ("{} refines in-memory encodes only, not a partitioned one (--workers, --scheduler, or a scene "
                      "larger than --memory-per-worker): its fit is not measured by partitions, and on Dask every "
                      "worker process would hold a CUDA context of its own on the GPU; refine with --lod-refine cpu, "
                      "or give a --memory-per-worker the scene fits in")


def encode_file(input_path: str | os.PathLike | Sequence[str | os.PathLike], out_dir: str | os.PathLike,
                preset: str | None = None,
                drop_invalid: bool = False, progress: Progress | None = None, workers: int | None = None,
                scheduler: str | None = None, memory_per_worker: int | None = None, scratch: str | None = None,
                edits: Pipeline | None = None, on_read: Callable[[int], None] | None = None,
                **options) -> Manifest:
    """Read any supported splat file, or several merged (read_merged; a list of paths), and encode it into `out_dir`
    (a directory or an fsspec URL).

    By default in this process: in memory when the scene fits half the available memory (or `memory_per_worker`),
    else by partitions (encode/partitioned.py), reading the input by row ranges. `workers` (a local Dask cluster
    of that many processes) or `scheduler` (an existing Dask cluster) run the partitions on Dask
    (encode/distributed.py). `edits` (edit.Pipeline) run on the splats as read, whole or chunk by chunk. The output
    is the same in every case, except that the default merge (auto) by partitions groups inside merge domains of at
    most `lod_merge_domain_splats` splats: a scene above that encodes otherwise in memory (partitioned.py).
    `on_read` hears the SH degree of the input as read (merged inputs: the highest) before anything is encoded or
    written, on either engine: a caller's check that needs the input (the CLI's of options an SH0 input gives nothing
    to, `encode --sh`) raises there, and nothing is written."""
    opts = EncodeOptions(preset=preset or DEFAULT_PRESET, reorder_input=True, **options)
    plan_formats(opts)  # fail before the (possibly long) read
    if opts.lod_merge is not None and opts.lod_merge not in LOD_MERGES:
        raise UsageError(f"unknown LOD merge {opts.lod_merge!r} (one of {', '.join(LOD_MERGES)})")
    try:
        check_azimuth(opts.camera_azimuth_deg)
    except ValueError as exc:
        raise UsageError(f"camera azimuth: {exc}") from None
    if opts.sh_codebook is not None:
        parse_entries(opts.sh_codebook, 1)
    # a missing, unreadable or unknown input fails before any output or progress
    sources = [open_input(p) for p in _paths(input_path)]
    source = sources[0]
    out = _checked_output(out_dir)
    if opts.up is None:  # a PLY header that names its up axis is believed before the scene's shape
        stated = _declared_up(sources)
        if stated is not None:
            log.info("up %s: %s (--up overrides it)", ",".join(f"{v:g}" for v in stated.up), stated.reason)
            opts = replace(opts, up=stated.up)
    progress = progress or no_progress
    out_name = os.path.basename(os.path.abspath(out)) if not is_url(out) else out.rstrip("/").rsplit("/", 1)[-1]
    distributed = workers is not None or scheduler is not None
    # The row layout (a stat of the file: its header is parsed already) where rows may be read by ranges.
    layouts = [s.vertex_layout() if opts.lod or distributed else None for s in sources]
    in_memory = not distributed and fits_in_process(layouts, opts, memory_per_worker or default_memory_per_worker())
    if edits and not edits.per_splat and not in_memory:
        raise UsageError(_WHOLE_SCENE_EDITS)
    if opts.lod_refiner is not None and not opts.lod:
        raise UsageError(_REFINE_NO_LOD)
    if opts.lod_refiner is not None and not in_memory and not getattr(opts.lod_refiner, "runs_by_partitions", False):
        raise UsageError(_REFINE_IN_PROCESS.format(getattr(opts.lod_refiner, "name", "this --lod-refine")))
    if opts.lod and opts.lod_merge == "cost" and not in_memory:
        raise UsageError(_COST_MERGE_IN_PROCESS.format(opts.lod_merge))
    # No merge named (None): auto on either engine (default_lod_merge); encode_partitioned runs it inside each
    # partition and takes the grid where a partition of auto's size does not fit a worker (said in the log).
    if in_memory:
        progress("read", 0.0)
        g = read_merged(sources, drop_invalid)
        if on_read is not None:
            on_read(g.sh_degree)
        if edits:
            g = edits.apply(g)
        progress("read", 1.0)
        with open_writer(out) as writer:
            # a transform may carry values out of the format's domain: screened again then
            screened = not (edits and edits.transforms)
            return encode_to(g, writer, opts, progress, source.path, out_name, screened=screened)
    if distributed:
        engine = DaskEngine(workers=workers, scheduler=scheduler, memory_per_worker=memory_per_worker)
    else:
        engine = LocalEngine(memory_per_worker)
    try:
        with open_writer(out) as writer:
            if scratch is None:
                local_cluster = not distributed or scheduler is None
                scratch = (out if is_url(out) and not local_cluster else
                           tempfile.gettempdir() if is_url(out) else os.path.dirname(os.path.abspath(out)))
            space = Scratch.create(scratch)
            try:
                parts = [open_rows(s, layout, space, 1 << 20, drop_invalid, progress, f"input{k}")
                         for k, (s, layout) in enumerate(zip(sources, layouts, strict=True))]
                rows = parts[0] if len(parts) == 1 else ConcatRows(parts)
                if on_read is not None:
                    on_read(rows.sh_degree)
                return encode_partitioned(rows, writer, opts, engine, space, progress, source.path, out_name,
                                          drop_invalid, edits)
            finally:
                space.remove()
    finally:
        engine.close()



def _checked_output(out_dir: str | os.PathLike) -> str:
    """The output directory or fsspec URL, checked before anything is written (fsspec present, path writable)."""
    out = os.fspath(out_dir)
    if is_url(out):
        check_store_reachable(out)
        return out
    out = local_path(out)
    check_output(out, directory=True, holds=MANIFEST_NAME)
    return out


def encode_built_tree(g: Gaussians, tiles: list[Tile], out_dir: str | os.PathLike, opts: EncodeOptions,
                      progress: Progress | None = None, source_name: str | None = None) -> Manifest:
    """Splats whose LOD tree is built already (a foreign tree kept as it is: sog_import, rad_import) encoded in
    memory into `out_dir` (a directory or an fsspec URL), as encode_file writes a scene."""
    out = _checked_output(out_dir)
    out_name = os.path.basename(os.path.abspath(out)) if not is_url(out) else out.rstrip("/").rsplit("/", 1)[-1]
    with open_writer(out) as writer:
        return encode_to(g, writer, opts, progress or no_progress, source_name, out_name, tiles=tiles)


# Rows a dry run reads at once from a binary PLY: its memory stays bounded whatever the scene's size.
DRY_RUN_ROWS = 1 << 20


def count_edits(input_path: str | os.PathLike | Sequence[str | os.PathLike], edits: Pipeline,
                drop_invalid: bool = False) -> tuple[str, int, list[tuple[str, int]]]:
    """What `edits` would keep of an input (or of several merged), without writing anything: the format (of the
    first input), the splats read, and per step (edit.Pipeline.steps) its label and the splats it keeps. A binary
    PLY is read by row ranges."""
    sources = [open_input(p) for p in _paths(input_path)]
    read = 0
    totals: list[tuple[str, int]] = [(step.label, 0) for step in edits.steps]

    def add(g: Gaussians) -> None:
        nonlocal read, totals
        read += len(g)
        _, counts = edits.run(g)
        totals = [(label, total + kept) for (label, total), (_, kept) in zip(totals, counts, strict=True)]

    if not edits.per_splat:  # a whole-scene edit: the merged scene read whole, as the encoder reads it
        g = read_merged(sources, drop_invalid)
        _, counts = edits.run(g)
        return sources[0].format, len(g), counts
    for source in sources:
        layout = source.vertex_layout()
        if layout is None:
            add(read_gaussians(source, drop_invalid=drop_invalid))
            continue
        stats = RowStats()
        for start in range(0, layout.rows, DRY_RUN_ROWS):
            g, st = read_ply_rows(layout, start, start + DRY_RUN_ROWS)
            stats = stats + st
            add(g)
        check_rows(source.path, stats, drop_invalid)
    return sources[0].format, read, totals
