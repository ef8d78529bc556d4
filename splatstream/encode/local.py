"""Encoding on this machine: plan, then the per-tile jobs on a thread pool, then reduce; written atomically. Also
the in-process engine of the partitioned encoder (LocalEngine) and `encode_file`, which picks the way.

numpy, zstd and etcpak release the GIL, so two worker threads keep both cores of a small machine busy. Results
come back in submission order, so the output does not depend on scheduling.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

from ..format.manifest import Manifest, TileEntry
from ..gaussians import Gaussians
from ..lod import Tile
from ..store import DirectoryWriter, MemoryStore, MemoryWriter, SceneWriter
from .jobs import encode_codebook, encode_group, splat_order, tile_entry, tile_group_names
from .options import EncodeOptions, Progress, no_progress
from .plan import plan_camera, plan_encode
from .reduce import build_manifest


def encode_to(g: Gaussians, writer: SceneWriter, opts: EncodeOptions, progress: Progress = no_progress,
              source_name: str | None = None, out_name: str | None = None, tiles: list[Tile] | None = None
              ) -> Manifest:
    """Encode Gaussians through a writer (payloads as they are made, the manifest last); returns the manifest.
    `tiles`: an LOD tree built already (plan_encode)."""
    plan = plan_encode(g, opts, progress, source_name, out_name, tiles)
    ctx = plan.context
    groups = tile_group_names(ctx)
    total = sum(len(t.gaussians) for t in plan.tiles) * len(groups)
    codebook = encode_codebook(ctx.codebook, ctx, writer) if ctx.codebook is not None else None
    entries: list[TileEntry] = []
    with _pool(min(2, os.cpu_count() or 1)) as pool:
        orders = list(pool.map(lambda t: splat_order(t.gaussians, ctx.chunk_order), plan.tiles))
        camera = pool.submit(plan_camera, plan)
        # A single tile's bounds (the LOD tree computes its own) beside the payload jobs.
        bounds = {id(t): pool.submit(tile_entry, t, {}) for t in plan.tiles if t.box_min is None}
        jobs = [(tile, order, group) for tile, order in zip(plan.tiles, orders, strict=True) for group in groups]
        results = iter(pool.map(lambda job: encode_group(job[0].gaussians, job[1], job[2], ctx, writer), jobs))
        done = 0
        for tile in plan.tiles:
            if id(tile) in bounds:
                bounds[id(tile)].result()
            payloads = {}
            for group in groups:  # progress per payload: a large tile's groups take seconds each
                payloads[group] = next(results)
                done += len(tile.gaussians)
                progress("encode", done / total)
            entries.append(tile_entry(tile, payloads))
        m = build_manifest(plan, camera.result(), entries, codebook)
    writer.write_manifest(m)
    return m


@contextlib.contextmanager
def _pool(workers: int) -> Iterator[ThreadPoolExecutor]:
    """A worker pool that, when the encode fails or is interrupted (Ctrl-C, SIGTERM), drops the jobs not yet
    started and waits only for the running ones, so the writer can remove its temporary directory at once."""
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def encode_gaussians(g: Gaussians, out_dir: str | os.PathLike, opts: EncodeOptions | None = None,
                     progress: Progress | None = None, source_name: str | None = None) -> Manifest:
    """Encode Gaussians into a scene directory (replaced in one step when everything is written)."""
    out_dir = os.fspath(out_dir)
    with DirectoryWriter(out_dir) as writer:
        return encode_to(g, writer, opts or EncodeOptions(), progress or no_progress, source_name,
                         os.path.basename(os.path.abspath(out_dir)))


def encode_in_memory(g: Gaussians, opts: EncodeOptions | None = None, progress: Progress | None = None,
                     name: str = "<memory>", tiles: list[Tile] | None = None) -> MemoryStore:
    """Encode Gaussians into memory: a scene any reader (decoder, renderer, streaming client) opens like a
    directory. `tiles`: an LOD tree built already (plan_encode)."""
    writer = MemoryWriter(name)
    encode_to(g, writer, opts or EncodeOptions(), progress or no_progress, name, name, tiles)
    return writer.store()


def default_memory_per_worker(workers: int = 1) -> int:
    """Half of this machine's available memory, shared by the workers (4 GiB where it cannot be read)."""
    try:
        with open("/proc/meminfo") as f:
            info = {line.split(":")[0]: int(line.split()[1]) * 1024 for line in f}
        available = info.get("MemAvailable", info["MemTotal"])
    except (OSError, KeyError, ValueError, IndexError):
        available = 8 << 30
    return int(available * 0.5 / max(1, workers))


class LocalEngine:
    """The partitioned encoder's tasks in this process: light passes on a few threads, one partition at a time
    (each with `threads` threads for its payloads: numpy, zstd and etcpak release the GIL)."""

    workers = 1

    def __init__(self, memory_per_worker: int | None = None, threads: int | None = None):
        self.memory_per_worker = int(memory_per_worker or default_memory_per_worker())
        self.threads_per_task = threads or min(2, os.cpu_count() or 1)

    def map(self, fn, args: list[tuple], stage: str, progress: Progress, heavy: bool = False,
            task_progress: bool = False) -> list:
        progress(stage, 0.0)  # the stage starts now (a long first task would otherwise show the stage before)
        results = []
        if heavy or task_progress or self.threads_per_task <= 1 or len(args) <= 1:
            for i, a in enumerate(args):
                if task_progress:
                    a = (*a, lambda f, i=i: progress(stage, (i + f) / len(args)))
                results.append(fn(*a))
                progress(stage, (i + 1) / len(args))
            return results
        with ThreadPoolExecutor(max_workers=self.threads_per_task) as pool:
            for i, r in enumerate(pool.map(lambda a: fn(*a), args)):
                results.append(r)
                progress(stage, (i + 1) / len(args))
        return results

    def map_behind(self, fn, args: list[tuple], stage: str) -> None:
        """At once: in one process nothing else could run beside them."""
        for a in args:
            fn(*a)

    def settle(self) -> None:
        return None

    def close(self) -> None:
        return None


def _fits_in_process(path: str, opts: EncodeOptions, memory: int) -> bool:
    """Whether the whole scene is encoded in memory (as encode_gaussians does) rather than by partitions: no LOD,
    an input that is read whole anyway, or one whose build fits the memory. The output is the same."""
    from ..io import sniff_format
    from ..ply import vertex_layout
    from .partitioned import PARTITION_MEMORY_FACTOR, _row_bytes

    if not opts.lod or sniff_format(path) != "ply":
        return True
    layout = vertex_layout(path)
    if layout is None:
        return True
    degree = layout.sh_degree if opts.sh_degree is None else min(opts.sh_degree, layout.sh_degree)
    return layout.rows * _row_bytes(degree) * PARTITION_MEMORY_FACTOR <= memory


def encode_file(input_path: str | os.PathLike, out_dir: str | os.PathLike, preset: str | None = None,
                drop_invalid: bool = False, progress: Progress | None = None, workers: int | None = None,
                scheduler: str | None = None, memory_per_worker: int | None = None, scratch: str | None = None,
                **options) -> Manifest:
    """Read any supported splat file and encode it into `out_dir` (a directory or an fsspec URL).

    By default in this process: in memory when the scene fits half the available memory (or `memory_per_worker`),
    else by partitions (encode/partitioned.py), reading the input by row ranges. `workers` (a local Dask cluster
    of that many processes) or `scheduler` (an existing Dask cluster) run the partitions on Dask
    (encode/distributed.py). The output is the same in every case."""
    from ..atomic import check_output
    from ..format.presets import DEFAULT_PRESET, resolve_formats
    from ..io import read_gaussians, sniff_format
    from ..store import _fsspec, is_url, local_path, open_writer
    from ..vq import parse_entries
    from .partitioned import encode_partitioned, open_rows
    from .scratch import Scratch

    opts = EncodeOptions(preset=preset or DEFAULT_PRESET, reorder_input=True, **options)
    resolve_formats(opts.preset, opts.overrides)  # fail before the (possibly long) read
    if opts.sh_codebook is not None:
        parse_entries(opts.sh_codebook, 1)
    input_path = local_path(input_path)
    sniff_format(input_path)  # a missing, unreadable or unknown input fails before any output or progress
    out = os.fspath(out_dir)
    if is_url(out):
        _fsspec(out)
    else:
        out = local_path(out)
        check_output(out, directory=True)
    if opts.up is None:  # a PLY header that names its up axis is believed before the scene's shape
        from ..io import declared_up
        from .plan import log

        stated = declared_up(input_path)
        if stated is not None:
            log.info("up %s: %s (--up overrides it)", ",".join(f"{v:g}" for v in stated.up), stated.reason)
            opts = replace(opts, up=stated.up)
    progress = progress or no_progress
    out_name = os.path.basename(os.path.abspath(out)) if not is_url(out) else out.rstrip("/").rsplit("/", 1)[-1]
    source_name = os.fspath(input_path)
    distributed = workers is not None or scheduler is not None
    if not distributed and _fits_in_process(input_path, opts, memory_per_worker or default_memory_per_worker()):
        progress("read", 0.0)
        g = read_gaussians(input_path, drop_invalid=drop_invalid)
        progress("read", 1.0)
        with open_writer(out) as writer:
            return encode_to(g, writer, opts, progress, source_name, out_name)
    if distributed:
        from .distributed import DaskEngine

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
                rows = open_rows(input_path, space, 1 << 20, drop_invalid, progress)
                return encode_partitioned(rows, writer, opts, engine, space, progress, source_name, out_name,
                                          drop_invalid)
            finally:
                space.remove()
    finally:
        engine.close()
