"""Encoding on this machine: plan, then the per-tile jobs on a thread pool, then reduce; written atomically.

numpy, zstd and etcpak release the GIL, so two worker threads keep both cores of a small machine busy. Results
come back in submission order, so the output does not depend on scheduling.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

from ..format.manifest import Manifest, TileEntry
from ..gaussians import Gaussians
from ..store import DirectoryWriter, MemoryStore, MemoryWriter, SceneWriter
from .jobs import encode_codebook, encode_group, splat_order, tile_entry, tile_group_names
from .options import EncodeOptions, Progress, no_progress
from .plan import plan_camera, plan_encode
from .reduce import build_manifest


def encode_to(g: Gaussians, writer: SceneWriter, opts: EncodeOptions, progress: Progress = no_progress,
              source_name: str | None = None, out_name: str | None = None) -> Manifest:
    """Encode Gaussians through a writer (payloads as they are made, the manifest last); returns the manifest."""
    t0 = time.perf_counter()
    plan = plan_encode(g, opts, progress, source_name, out_name)
    ctx = plan.context
    groups = tile_group_names(ctx)
    total = sum(len(t.gaussians) for t in plan.tiles) * len(groups)
    codebook = encode_codebook(ctx.codebook, ctx, writer) if ctx.codebook is not None else None
    entries: list[TileEntry] = []
    with _pool(min(2, os.cpu_count() or 1)) as pool:
        orders = list(pool.map(lambda t: splat_order(t.gaussians, ctx.chunk_order), plan.tiles))
        camera = pool.submit(plan_camera, g, plan.up)
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
        m = build_manifest(plan, camera.result(), entries, codebook, time.perf_counter() - t0)
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
                     name: str = "<memory>") -> MemoryStore:
    """Encode Gaussians into memory: a scene any reader (decoder, renderer, streaming client) opens like a
    directory."""
    writer = MemoryWriter(name)
    encode_to(g, writer, opts or EncodeOptions(), progress or no_progress, name, name)
    return writer.store()


def encode_file(input_path: str | os.PathLike, out_dir: str | os.PathLike, preset: str | None = None,
                drop_invalid: bool = False, progress: Progress | None = None, **options) -> Manifest:
    """Read any supported splat file and encode it into `out_dir`."""
    from ..atomic import check_output
    from ..format.presets import DEFAULT_PRESET, resolve_formats
    from ..io import read_gaussians, sniff_format
    from ..vq import parse_entries

    opts = EncodeOptions(preset=preset or DEFAULT_PRESET, reorder_input=True, **options)
    resolve_formats(opts.preset, opts.overrides)  # fail before the (possibly long) read
    if opts.sh_codebook is not None:
        parse_entries(opts.sh_codebook, 1)
    sniff_format(input_path)  # a missing, unreadable or unknown input fails before any output or progress
    check_output(out_dir, directory=True)
    if progress:
        progress("read", 0.0)
    g = read_gaussians(input_path, drop_invalid=drop_invalid)
    if progress:
        progress("read", 1.0)
    return encode_gaussians(g, out_dir, opts, progress, source_name=os.fspath(input_path))
