"""A streamed scene on a GL context: the engine (client_gl/stream, GL-free) wired to a GPU pool and a renderer.

    session = StreamingSession.open("http://127.0.0.1:8000/scenes/garden", ctx, ViewOptions(gpu_mem_mb=1024))
    frame = session.frame(camera)          # select, fetch, decode, upload, draw (into the renderer's framebuffer)
    image = session.read_image()           # (H, W, 3) float32
    session.close()

Both the headless runner (client_gl/view_headless.py) and the window (client_gl/window.py) drive this class, so the
picture, the budgets and the metrics are the same with and without a display. Metrics follow issue 13:
`first_frame_s` counts from the start of the manifest request to the first frame with splats drawn.
"""
from __future__ import annotations

import gc
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from splatstream.camera import Camera
from splatstream.errors import UsageError
from splatstream.format.manifest import Manifest

from .gpu.pool import ChunkPool
from .gpu.renderer import (
    FrameStats,
    RenderOptions,
    SplatRenderer,
    draws_cpu_first,
    is_software,
    prepare_target,
    resolve_sort,
)
from .gpu.residency_layout import CodebookLayout, PoolLayout
from .stream.cache import DiskCache
from .stream.engine import DECODE_WAIT_S, FrameUpdate, StreamEngine, StreamOptions
from .stream.fetch import Fetcher
from .stream.selection import SelectionOptions
from .stream.sources import FetchError, Progress, SceneSource, open_source

DEFAULT_GPU_MEM_MB = 1024.0
# The first frame waits at most this long for a decode under way (the root's base, taken while the renderer was
# built): it then uploads and draws the root instead of drawing nothing while the decode waits for the frame loop.
FIRST_FRAME_DECODE_WAIT_S = 0.1


@dataclass(frozen=True)
class ViewOptions:
    """What a user sets about streaming (the command line's --gpu-mem-mb, --max-splats, --max-sse, ...)."""

    gpu_mem_mb: float = DEFAULT_GPU_MEM_MB  # splat data on the GPU at most (the pool's atlases and range table)
    max_splats: int | None = None
    max_sse: float = SelectionOptions.max_sse
    sh_degree: int = 3
    band_area_share: tuple[float, float, float] = SelectionOptions.band_area_share
    prefetch: bool = True
    fill_levels: bool = StreamOptions.fill_levels  # coarse to fine through every level (False: --skip-levels)
    fill_gap: int = StreamOptions.fill_gap
    fill_min_bytes: int = StreamOptions.fill_min_bytes  # coarse to fine only above these missing bytes (--fill-min-kb)
    # above fill_min_bytes and up to these missing bytes: the root, then the cut (--fill-root-kb)
    fill_root_bytes: int = StreamOptions.fill_root_bytes
    cache: bool = True  # disk cache of payloads (HTTP sources)
    drop_invalid: bool = False  # a splat file's invalid splats dropped (a warning), not refused (io.read_gaussians)
    cache_dir: str | None = None
    max_in_flight: int = 6
    upload_bytes_per_frame: int = StreamOptions.upload_bytes_per_frame
    decode_workers: int = StreamOptions.decode_workers
    decode_processes: int = StreamOptions.decode_processes
    decode_workers_moving: int = StreamOptions.decode_workers_moving
    decode_batch: bool = StreamOptions.decode_batch
    render: RenderOptions = field(default_factory=RenderOptions)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    request_timeout_s: float = 15.0
    stall_timeout_s: float = 10.0
    request_deadline_s: float = 60.0  # one request in all (a server dripping bytes resets no stall timer)
    manifest_timeout_s: float = 30.0  # the manifest in all, retries included (view: at most its --timeout)

    def selection(self) -> SelectionOptions:
        return SelectionOptions(max_sse=self.max_sse, max_splats=self.max_splats, sh_degree=self.sh_degree,
                                band_area_share=self.band_area_share)


@dataclass
class FrameRecord:
    """One frame of the metrics series (METRICS.json "frames")."""

    t: float  # seconds since the manifest request started
    bytes: int  # downloaded so far (network; cache reads not counted)
    drawn_splats: int
    resident_splats: int
    resident_tiles: int
    in_flight: int
    gpu_bytes: int
    frame_ms: float  # CPU time of the frame on the render thread (select, uploads, draw submission)
    uploaded_bytes: int
    converged: bool
    update_ms: float = 0.0  # of frame_ms: the engine (selection, wish list, uploads), the rest is the draw's submission
    resident_gpu_bytes: int = 0  # of gpu_bytes (the whole pool): what the resident splats' slots and the codebook use

    def to_json(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


@dataclass
class StreamMetrics:
    start: float  # perf_counter at the manifest request
    gpu_budget_bytes: int
    first_frame_s: float | None = None
    bytes_first_frame: int | None = None
    converged_s: float | None = None
    gpu_bytes_peak: int = 0  # the GPU pool allocated (it is made whole, for the budget)
    resident_gpu_bytes_peak: int = 0  # of it, the most the resident splats used
    work_bytes_peak: int = 0  # the renderer's per-frame buffers (sort, draw), beside the budgeted pool
    evictions: int = 0
    process_decodes: int = 0  # payloads decoded in decode processes (ViewOptions.decode_processes)
    # Where the time to the first frame went: the manifest fetched and parsed, then the GPU pool, the renderer's
    # buffers and programs and the engine built (seconds from `start`).
    manifest_s: float | None = None
    pool_s: float | None = None
    built_s: float | None = None
    frames: list[FrameRecord] = field(default_factory=list)

    def to_json(self, fetch_stats=None) -> dict:
        last = self.frames[-1] if self.frames else None
        out = {
            "first_frame_s": self.first_frame_s, "converged_s": self.converged_s,
            "bytes_downloaded": last.bytes if last else 0, "bytes_first_frame": self.bytes_first_frame,
            "gpu_bytes_peak": self.gpu_bytes_peak, "gpu_budget_bytes": self.gpu_budget_bytes,
            "resident_gpu_bytes": last.resident_gpu_bytes if last else 0,
            "resident_gpu_bytes_peak": self.resident_gpu_bytes_peak,
            "resident_splats": last.resident_splats if last else 0,
            "drawn_splats": last.drawn_splats if last else 0,  # at most --max-splats; resident adds stand-ins
            "work_bytes_peak": self.work_bytes_peak,
            "manifest_s": self.manifest_s, "pool_s": self.pool_s, "built_s": self.built_s,
            "frames": [f.to_json() for f in self.frames],
        }
        if fetch_stats is not None:
            out["fetch"] = {k: v for k, v in fetch_stats.__dict__.items()}
        out["evictions"] = self.evictions
        out["process_decodes"] = self.process_decodes
        return out


@dataclass
class PreparedSource:
    """The GL-free first half of a session: the source opened (a splat file encoded), the fetcher running and the
    manifest fetched and validated. A window prepares it on a worker thread, so it never freezes meanwhile."""

    source: SceneSource
    fetcher: Fetcher
    manifest: Manifest
    start: float  # perf_counter when the manifest request started
    manifest_s: float = 0.0  # seconds from start until the manifest was parsed

    @classmethod
    def open(cls, spec: str | os.PathLike | SceneSource, options: ViewOptions = ViewOptions(),
             progress: Progress | None = None,
             while_fetching: Callable[[], None] | None = None) -> PreparedSource:
        """while_fetching: called once the manifest is asked for, before it is waited for (early_target's work)."""
        start = time.perf_counter()
        source = spec if isinstance(spec, SceneSource) else open_source(spec, progress=progress,
                                                                        drop_invalid=options.drop_invalid)
        cache = None
        if options.cache and getattr(source, "cache_key", None):
            cache = DiskCache(options.cache_dir)
        fetcher = Fetcher(source, cache=cache, max_in_flight=options.max_in_flight,
                          request_timeout_s=options.request_timeout_s, stall_timeout_s=options.stall_timeout_s,
                          request_deadline_s=options.request_deadline_s,
                          manifest_timeout_s=options.manifest_timeout_s)
        fetcher.start()
        try:
            if while_fetching is not None:
                while_fetching()
            manifest = fetcher.manifest()  # parsed once, there; the engine is handed this one
        except BaseException:
            fetcher.close()
            raise
        # The root's base is wanted whatever the view (but where the splat budget keeps the cut small enough to be
        # fetched directly: root_wanted): ask for it now, so it arrives while the GPU pool and the shaders are built
        # (the engine's first wish list names it again; the fetcher takes it once).
        root = manifest.tile(manifest.root)
        if root_wanted(manifest, options):
            fetcher.want([(1.0, (root.id, "base"), root.groups["base"])])
        return cls(source, fetcher, manifest, start, time.perf_counter() - start)


class StreamingSession:
    def __init__(self, prepared: PreparedSource, ctx, options: ViewOptions = ViewOptions()):
        self.options = options
        self.ctx = ctx
        self.source = prepared.source
        self.fetcher = prepared.fetcher
        self.manifest: Manifest = prepared.manifest
        try:
            self._build(ctx, options)
        except BaseException:
            self.fetcher.close()
            raise
        self.metrics = StreamMetrics(prepared.start, self.budget, manifest_s=prepared.manifest_s,
                                     pool_s=self._pool_done - prepared.start,
                                     built_s=time.perf_counter() - prepared.start)
        self.last: FrameUpdate | None = None
        self.last_stats: FrameStats | None = None
        self._drawn_with: tuple | None = None
        self.paused = False
        self.manifest_changes = 0  # new versions of the scene continued with (_follow_new_manifest)

    def _build(self, ctx, options: ViewOptions) -> None:
        """The GPU pool, the renderer and the engine for these options (again when the budget changes)."""
        m = self.manifest
        degree = min(options.sh_degree, m.sh_degree)
        codebook = CodebookLayout(m.sh_codebook.format, m.sh_codebook.entries) if m.sh_codebook else None
        self.budget = int(options.gpu_mem_mb * (1 << 20))
        check_root_fits(m, self.budget, degree, codebook, options.gpu_mem_mb)
        # The CPU sort culls on the host: its pool keeps a host mirror that the tiles bring, also for the first
        # frames of a GPU-path renderer that draws them with the CPU sort (RenderOptions.cpu_first; dropped at its
        # switch to the GPU path, frame()).
        self.with_mirror = resolve_sort(ctx, options.render) == "cpu" or draws_cpu_first(ctx, options.render)
        self.pool = ChunkPool.for_budget(ctx, self.budget, m.formats, degree, codebook=codebook,
                                         host_mirror=self.with_mirror, prime=options.render.atlas_prime)
        self._pool_done = time.perf_counter()
        layout: PoolLayout = self.pool.layout
        stream_opts = StreamOptions(selection=replace(options.selection(), sh_degree=degree),
                                    upload_bytes_per_frame=options.upload_bytes_per_frame, prefetch=options.prefetch,
                                    fill_levels=options.fill_levels, fill_gap=options.fill_gap,
                                    fill_min_bytes=options.fill_min_bytes, fill_root_bytes=options.fill_root_bytes,
                                    root_first=root_wanted(m, options),
                                    decode_workers=options.decode_workers,
                                    decode_processes=options.decode_processes,
                                    decode_workers_moving=options.decode_workers_moving,
                                    decode_batch=options.decode_batch)
        self.engine = StreamEngine(self.fetcher, self.pool, stream_opts, slot_bytes=layout.slot_bytes(),
                                   manifest=m, with_mirror=self.with_mirror, location=self.source.location)
        self.fetcher.yield_to(self.engine.loop_idle, DECODE_WAIT_S)
        # The engine before the renderer, so that the root's base (asked for with the manifest, PreparedSource.open)
        # is decoding before the first frame: its update then uploads it, and no frame draws nothing while it
        # decodes. Asked before and after the renderer's programs: moderngl holds the interpreter lock while it
        # compiles, so the fetcher and the decode threads run between the compiles, not during them.
        try:
            self.engine.take_arrived()
            self.renderer = SplatRenderer(ctx, self.pool, options.render)
            if options.max_splats is not None:  # the budget's work buffers now, not in the frames that reach it
                self.renderer.reserve_work(options.max_splats)
            self.engine.take_arrived()
        except BaseException:
            self.engine.close()
            raise

    @classmethod
    def open(cls, spec: str | os.PathLike, ctx, options: ViewOptions = ViewOptions(),
             progress: Progress | None = None, target_size: tuple[int, int] | None = None) -> StreamingSession:
        """A session for a URL, a scene directory or a splat file (encoded in memory, with progress). target_size:
        the (width, height) its frames will have, where known before the manifest (`view --headless`): the first
        frame's framebuffer is then made and cleared while the manifest is fetched (early_target)."""
        return cls(PreparedSource.open(spec, options, progress, early_target(ctx, options, target_size)), ctx, options)

    def reconfigure(self, options: ViewOptions) -> None:
        """New streaming options: the selection's change at once; a new GPU budget, SH degree or draw path builds
        a new pool (what was resident is fetched again, from the disk cache for HTTP scenes)."""
        rebuild = (options.gpu_mem_mb != self.options.gpu_mem_mb or options.sh_degree != self.options.sh_degree
                   or options.render != self.options.render)
        self.options = options
        if rebuild:
            self.engine.close()
            self.renderer.release()
            self.pool.release()
            self._build(self.ctx, options)
            self.metrics.gpu_budget_bytes = self.budget
        else:
            degree = min(options.sh_degree, self.manifest.sh_degree)
            self.engine.options = replace(self.engine.options,
                                          selection=replace(options.selection(), sh_degree=degree),
                                          prefetch=options.prefetch)

    def _follow_new_manifest(self) -> None:
        """The scene was re-encoded while streamed (payloads answered 404, the fetcher found a new manifest:
        http.md 10): continue with the new version, a new pool and engine (what was resident comes back from
        the disk cache where payloads did not change)."""
        new = self.fetcher.take_new_manifest()
        if new is None:
            return
        self.manifest = new[1]
        self.engine.close()
        self.renderer.release()
        self.pool.release()
        self._build(self.ctx, self.options)
        self.last = None
        self.manifest_changes += 1

    # --- the frame ----------------------------------------------------------------------------------------------
    def frame(self, cam: Camera, sh_degree: int | None = None, clear: bool = True,
              timing: bool = False) -> FrameRecord:
        """Stream (unless paused) and draw one frame into the renderer's framebuffer. Raises FetchError (an
        InputError: the CLI's exit 2) when a local scene's payload is damaged or missing (check_damaged)."""
        self.check_damaged()
        if self.last is None and not self.paused:
            # Nothing drawn yet: the decode under way is the root's base, work that the frames until it is uploaded
            # would wait for anyway; done first, it is drawn in this frame (one empty frame fewer: its draw is the
            # framebuffer's first allocation and clear, which the drawn frame then does instead).
            self.engine.wait(FIRST_FRAME_DECODE_WAIT_S)
        t0 = time.perf_counter()
        if not self.paused:
            self._follow_new_manifest()
        self._drawn_with = (cam, sh_degree, clear)
        self.engine.frame_started()
        try:
            if not self.paused:
                self.last = self.engine.update(cam)
            t1 = time.perf_counter()
            draw = self.last.draw if self.last is not None else []
            self.last_stats = self.renderer.render(cam, sh_degree=sh_degree, background=self.options.background,
                                                   clear=clear, timing=timing, draw_set=draw)
            if self.renderer.check_bins():  # the compute draw's entry buffer grew: draw this frame again
                self.last_stats = self.renderer.render(cam, sh_degree=sh_degree,
                                                       background=self.options.background, clear=clear,
                                                       timing=timing, draw_set=draw)
        finally:
            self.engine.frame_submitted()
        if self.with_mirror and self.renderer.sort_mode == "gpu":
            self._drop_host_mirror()
        t2 = time.perf_counter()
        return self._record((t2 - t0) * 1e3, (t1 - t0) * 1e3)

    def _drop_host_mirror(self) -> None:
        """The renderer switched from its CPU-first frames to the GPU path: the pool keeps no host mirror any more
        and the decode workers compute none (tiles decoded with one before join as well: the pool ignores it)."""
        self.pool.drop_host_mirror()
        self.engine.with_mirror = False
        self.with_mirror = False

    def _record(self, frame_ms: float, update_ms: float) -> FrameRecord:
        u = self.last
        stats = self.fetcher.stats()
        now = time.perf_counter() - self.metrics.start
        gpu = self.pool.gpu_bytes
        rec = FrameRecord(now, stats.bytes_downloaded, u.drawn_splats if u else 0, u.resident_splats if u else 0,
                          u.resident_tiles if u else 0, u.in_flight if u else 0, gpu, frame_ms,
                          u.uploaded_bytes if u else 0, bool(u and u.converged), update_ms, self.pool.resident_bytes)
        m = self.metrics
        m.frames.append(rec)
        m.gpu_bytes_peak = max(m.gpu_bytes_peak, gpu)
        m.resident_gpu_bytes_peak = max(m.resident_gpu_bytes_peak, rec.resident_gpu_bytes)
        m.work_bytes_peak = max(m.work_bytes_peak, self.renderer.work_bytes)
        m.evictions = self.engine.evictions
        m.process_decodes = self.engine.process_decodes
        if m.first_frame_s is None and rec.drawn_splats > 0:
            m.first_frame_s, m.bytes_first_frame = now, rec.bytes
        if rec.converged and m.converged_s is None:
            m.converged_s = now
        elif not rec.converged:
            m.converged_s = None  # converged means: and stayed so until now
        return rec

    def check_damaged(self) -> None:
        """Raise the first permanent failure of a local store's payload (Fetcher.damaged: its size or SHA-256
        against the manifest, or the file missing), one line naming the file: the view will not converge, and
        waiting for its timeout would read the same bytes again. HTTP scenes never raise here (retried)."""
        damaged = self.fetcher.damaged()
        if damaged:
            first = damaged[0]
            more = f" ({len(damaged) - 1} more payloads damaged)" if len(damaged) > 1 else ""
            raise FetchError(first.path or self.source.location, first.kind, first.problem + more,
                             transient=False, field=first.field)

    def problem(self) -> str | None:
        """One line naming what keeps the view from converging, or None: a payload that does not decode (the
        scene is broken), else the payload failing most often (its URL and last failure), else the last failure."""
        if self.engine.failed:
            first = next(iter(self.engine.failed.values()))
            more = len(self.engine.failed) - 1
            return f"{first} (does not decode{f'; {more} more payloads neither' if more else ''})"
        failing = self.fetcher.failing()
        if failing:
            _, message, attempts = failing[0]
            more = len(failing) - 1
            return (f"{message} ({attempts} failed attempt{'s' if attempts > 1 else ''}"
                    f"{f'; {more} more payloads failing' if more else ''})")
        return None

    @property
    def drawn_camera(self) -> Camera | None:
        """The camera of the last frame drawn (what read_image shows)."""
        return self._drawn_with[0] if self._drawn_with is not None else None

    @property
    def converged(self) -> bool:
        return bool(self.last and self.last.converged)

    def wait(self, timeout_s: float = 0.01) -> None:
        """Block briefly for a decode to finish (loops without vsync use it instead of spinning)."""
        self.engine.wait(timeout_s)

    def read_image(self) -> np.ndarray:
        """The last frame (H, W, 3); drawn again first if the compute draw's entries overflowed in it (the
        per-frame check looks at an earlier frame's count, so as not to wait for the GPU)."""
        if self._drawn_with is not None and self.renderer.check_bins(exact=True):
            cam, degree, clear = self._drawn_with
            draw = self.last.draw if self.last is not None else []
            self.renderer.render(cam, sh_degree=degree, background=self.options.background, clear=clear,
                                 draw_set=draw)
        return self.renderer.read_image()[..., :3]

    def close(self) -> None:
        self.fetcher.close()
        self.engine.close()
        self.renderer.release()
        self.pool.release()


def early_target(ctx, options: ViewOptions, size: tuple[int, int] | None) -> Callable[[], None] | None:
    """PreparedSource.open's while_fetching for a session whose output size is known before its manifest: the first
    frame's framebuffer made and cleared (renderer.prepare_target; RenderOptions.early_target), so that a cold
    driver's first clear runs while the manifest is in flight instead of inside the first frame. None without a size,
    with early_target off (the window: its loading frames already clear while the manifest is fetched) and on a
    software GL: llvmpipe's clear is a fill of the target by its threads, 4-43 ms at 1920x1080 on the shared 2-core
    VM, which the first frame's own clear then does again (6-43 ms), so early it is only more work beside the
    manifest's parse (BENCHMARKS.md, "The first frame's prime and framebuffer off the serial path")."""
    if size is None or not options.render.early_target or is_software(ctx):
        return None
    width, height = size
    return lambda: prepare_target(ctx, int(width), int(height), options.render.color_dtype)


def freeze_long_lived() -> None:
    """For frame loops (the shells call it once a session is open): the manifest's tens of thousands of objects
    live as long as the session, and a full garbage collection walked them every few seconds, a 12-20 ms stall in
    whichever frame allocated next. gc.freeze() moves what exists now out of the collector's walks (no collection
    first: that would be the same stall before the first frame)."""
    gc.freeze()


def root_wanted(manifest: Manifest, options: ViewOptions) -> bool:
    """Whether the first frame will want the root's base before any view is known: not where the splat budget
    bounds the cut's base payloads (estimated at the root's bytes a splat) to fill_min_bytes or less, since the
    engine then fetches the cut itself, without its ancestors (StreamEngine._ancestors_worth). Above it the root
    comes first either way: coarse to fine, or (up to fill_root_bytes) the root, then the cut (_root_worth)."""
    if not options.fill_levels or options.fill_min_bytes <= 0 or options.max_splats is None:
        return True
    root = manifest.tile(manifest.root)
    if options.max_splats <= root.splats:  # the cut is the root
        return True
    per_splat = root.groups["base"].bytes / max(root.splats, 1)
    return options.max_splats * per_splat > options.fill_min_bytes


def check_root_fits(manifest: Manifest, budget: int, sh_degree: int, codebook: CodebookLayout | None,
                    gpu_mem_mb: float) -> None:
    """UsageError naming the minimum when the GPU budget cannot hold the scene's root tile (nothing would ever be
    drawn: every view starts from the root)."""
    layout = PoolLayout(manifest.formats, sh_degree, codebook)
    root = manifest.tile(manifest.root)
    need = layout.fixed_bytes() + layout.slot_bytes() * max(1, root.chunks)
    if budget < need:
        minimum = math.ceil(need / (1 << 20) * 100) / 100
        raise UsageError(f"--gpu-mem-mb {gpu_mem_mb:g}: too small for this scene: its root tile alone takes "
                         f"{need:,} bytes of GPU memory (give --gpu-mem-mb {minimum:g} or more)")


def check_gpu_budget(options: ViewOptions) -> None:
    if not options.gpu_mem_mb > 0:
        raise UsageError(f"--gpu-mem-mb {options.gpu_mem_mb}: expected a positive number of megabytes")
