"""The in-memory engine: plan, then the per-tile jobs on a thread pool, then reduce; written atomically. Also
the in-process engine of the partitioned encoder (LocalEngine); driver.py picks between them.

The payload jobs run on one worker thread (the main thread only collects): two cost 1.5x the CPU and more wall time
(BENCHMARKS.md, "Where the grid encode's CPU goes"). Results come back in submission order, so the output does not
depend on scheduling.
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

from ..cores import available_cores
from ..format.manifest import Manifest, TileEntry
from ..gaussians import Gaussians
from ..lod import Tile
from ..store import DirectoryWriter, MemoryStore, MemoryWriter, SceneWriter, write_scene_manifest
from .forked import PayloadChildren, encode_tile, payload_processes
from .jobs import encode_codebook, encode_group, tile_entry, tile_group_names, tile_order
from .options import EncodeOptions, Progress, no_progress
from .plan import TileContext, plan_camera, plan_encode
from .reduce import build_manifest


def encode_to(g: Gaussians, writer: SceneWriter, opts: EncodeOptions, progress: Progress = no_progress,
              source_name: str | None = None, out_name: str | None = None, screened: bool = False,
              tiles: list[Tile] | None = None, processes: int | None = None) -> Manifest:
    """Encode Gaussians through a writer (payloads as they are made, the manifest last); returns the manifest.
    `screened`: `g` comes from io.read_gaussians (plan.plan_encode). `tiles`: an LOD tree built already
    (plan_encode). `processes`: child processes that encode payloads beside this one (forked.py; default
    forked.payload_processes: one less than the cores available, at most 2, 0 for a writer they cannot share);
    the bytes are the same with any number."""
    if processes is None:
        processes = payload_processes(writer)
    children: PayloadChildren | None = None

    def on_level(ctx: TileContext, level: list[Tile]) -> None:
        # The first level is the leaves, laid out before the tree's merge pool starts: the children are forked
        # then (no other thread runs), and each later level is queued for them as it is final.
        nonlocal children
        if children is None:
            children = PayloadChildren(processes, tile_group_names(ctx), ctx, writer.payload_writer())
            children.start(level)
        else:
            children.offer(level)

    try:
        plan = plan_encode(g, opts, progress, source_name, out_name, screened, tiles,
                           on_level=on_level if processes else None)
        ctx = plan.context
        codebook = encode_codebook(ctx.codebook, ctx, writer) if ctx.codebook is not None else None
        if processes and len(plan.tiles) > 1 and children is None and opts.lod_refiner is None:
            # a tree handed in: fork before the payloads (not after a refinement, whose own threads may still run)
            children = PayloadChildren(processes, tile_group_names(ctx), ctx, writer.payload_writer())
            children.start(plan.tiles)
        if children is not None and children.started:
            entries = _forked_entries(plan.tiles, children, ctx, writer, progress)
        else:
            entries = _threaded_entries(plan.tiles, ctx, writer, progress)
        m = build_manifest(plan.scene, plan_camera(plan), entries, codebook)
    finally:
        if children is not None:
            children.close()  # children still running (an encode that failed) stopped before the writer cleans up
    return write_scene_manifest(writer, m, opts.page_tiles, opts.page_levels, opts.compact_table,
                                opts.short_digests, short_names=ctx.short_names,
                                relative_boxes=opts.relative_boxes)


def _forked_entries(tiles: list[Tile], children: PayloadChildren, ctx: TileContext, writer: SceneWriter,
                    progress: Progress) -> list[TileEntry]:
    """The tiles' entries, their payloads encoded by the children and this process (forked.py)."""
    groups = tile_group_names(ctx)
    progress("encode", 0.0)
    # The bar counts every tile's splats once its payloads are written, the children's included (they may have
    # done most of them while the tree merged: the bar starts there).
    payloads = children.finish(tiles, lambda tile: encode_tile(tile.gaussians, groups, ctx, writer),
                               lambda share: progress("encode", share))
    progress("encode", 1.0)
    return [tile_entry(tile, payloads[tile.id]) for tile in tiles]


def _threaded_entries(tiles: list[Tile], ctx: TileContext, writer: SceneWriter, progress: Progress
                      ) -> list[TileEntry]:
    """The tiles' entries, their payloads encoded in this process."""
    groups = tile_group_names(ctx)
    total = sum(len(t.gaussians) for t in tiles) * len(groups)
    entries: list[TileEntry] = []
    # One worker: most payload jobs are many small numpy calls (a layer's mode trials on ~6 blocks), so two threads
    # spend their time handing the interpreter lock back and forth rather than overlapping.
    with _pool(1) as pool:
        orders = list(pool.map(lambda t: tile_order(t.gaussians, ctx), tiles))
        # A single tile's bounds (the LOD tree computes its own) beside the payload jobs.
        bounds = {id(t): pool.submit(tile_entry, t, {}) for t in tiles if t.box_min is None}
        jobs = [(tile, order, group) for tile, order in zip(tiles, orders, strict=True) for group in groups]
        results = iter(pool.map(lambda job: encode_group(job[0].gaussians, job[1], job[2], ctx, writer), jobs))
        done = 0
        for tile in tiles:
            if id(tile) in bounds:
                bounds[id(tile)].result()
            payloads = {}
            for group in groups:  # progress per payload: a large tile's groups take seconds each
                payloads[group] = next(results)
                done += len(tile.gaussians)
                progress("encode", done / total)
            entries.append(tile_entry(tile, payloads))
    return entries


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
                     progress: Progress | None = None, source_name: str | None = None,
                     tiles: list[Tile] | None = None) -> Manifest:
    """Encode Gaussians into a scene directory (replaced in one step when everything is written). `tiles`: an LOD
    tree built already (plan_tiles: several encodes of one scene share it)."""
    out_dir = os.fspath(out_dir)
    with DirectoryWriter(out_dir) as writer:
        return encode_to(g, writer, opts or EncodeOptions(), progress or no_progress, source_name,
                         os.path.basename(os.path.abspath(out_dir)), tiles=tiles)


def encode_in_memory(g: Gaussians, opts: EncodeOptions | None = None, progress: Progress | None = None,
                     name: str = "<memory>", tiles: list[Tile] | None = None) -> MemoryStore:
    """Encode Gaussians into memory: a scene any reader (decoder, renderer, streaming client) opens like a
    directory. `tiles`: an LOD tree built already (plan_encode)."""
    writer = MemoryWriter(name)
    encode_to(g, writer, opts or EncodeOptions(), progress or no_progress, name, name, tiles=tiles)
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
        self.threads_per_task = threads or min(2, available_cores())

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
