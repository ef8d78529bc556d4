"""The streaming engine: from a camera per frame to what is resident on the GPU and what is drawn.

    engine = StreamEngine(fetcher, residency, StreamOptions(...))     # fetcher: fetch.py; residency: a GPU pool
    update = engine.update(camera)                                   # once per frame, on the render thread
    renderer.render(camera, draw_set=update.draw)                    # tile ids, a hole-free REPLACE cut

Each frame: select the wanted cut and bands (selection.py), tell the fetcher the complete priority-ordered list
of payloads wanted now (it cancels what fell off it), hand fetched, verified payloads to decode workers (decode, off
the render thread), upload decoded tiles into the pool under a per-frame byte budget (evicting the least recently
drawn tiles nobody wants when slots run out; the root is never evicted), and compute the draw set. No GL here:
`residency` is anything with the pool's residency API (client_gl.gpu.pool.ChunkPool; tests use a plain one).
"""
from __future__ import annotations

import gc
import os
import queue
import subprocess
import sys
import threading
import time
from collections import deque
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import chain, compress, filterfalse, repeat
from multiprocessing import get_context
from operator import is_
from typing import Any, Protocol

import numpy as np

from splatstream.camera import Camera, framing_box
from splatstream.errors import SplatstreamError, UsageError
from splatstream.format.codec import decode_plane, palette_as_ranged
from splatstream.format.container import VerifiedPayload
from splatstream.format.decode import codebook_index, decode_payload, decode_payloads
from splatstream.format.manifest import Manifest, PayloadEntry, indexable
from splatstream.format.planes import band_of

from ..tiledata import TileData, host_mirror
from .pages import PAGE_GROUP, PagedTree
from .selection import (
    PartialView,
    Selection,
    SelectionOptions,
    TileView,
    ViewBuffers,
    cut_a_page_may_undo,
    draw_set,
    pages_the_budget_can_use,
    prefetch,
    select,
    select_near,
    view_numbers,
    wanted_bands_at,
)

Key = tuple[int | None, str]  # (tile id, group) or (None, "sh<b>") for a band of the SH codebook
_GROUP_BAND = {"base": 0, "sh1": 1, "sh2": 2, "sh3": 3}


class Residency(Protocol):
    """What the engine needs of a GPU pool (client_gl.gpu.pool.ChunkPool provides it)."""

    @property
    def capacity_slots(self) -> int: ...

    @property
    def free_slots(self) -> int: ...

    def join(self, tile_id: int, tile: Any) -> Any: ...

    def add_band(self, tile_id: int, band: int, planes: dict) -> None: ...

    def leave(self, tile_id: int) -> None: ...

    def set_codebook_band(self, band: int, plane: Any) -> None: ...


class FetcherLike(Protocol):
    def manifest(self) -> Manifest: ...  # parsed once, by the fetcher

    def want(self, requests: list[tuple[float, Key, PayloadEntry]]) -> None: ...

    def done(self) -> list[tuple[Key, PayloadEntry, VerifiedPayload | bytes]]: ...

    def stats(self) -> Any: ...  # with .in_flight and .queued (fetch.FetchStats)


DECODE_WAIT_S = 0.05  # a decode thread waits at most this long for the frame loop to finish its CPU work


@dataclass(frozen=True)
class StreamOptions:
    selection: SelectionOptions = SelectionOptions()
    upload_bytes_per_frame: int = 16 << 20  # decoded bytes uploaded per frame at most (one payload always goes)
    target_fraction: float = 0.8  # of the pool the wanted cut may fill; the rest holds tiles in transition
    prefetch: bool = True
    # Coarse to fine: a tile of the cut that is not resident also wants its ancestors, fetched level by level, so
    # the picture improves with every level that arrives (a cut is drawn in place of an ancestor only once all of
    # the ancestor's part of it is there). False skips straight to the cut (fewer bytes, long plateaus).
    fill_levels: bool = True
    # The finest ancestor filled in is this many levels above its cut tile, then every fill_step-th level up to the
    # root: with levels 2x apart in splats, 4 and 4 add about 1/15 of the cut's bytes (3 and 3: 1/7, measured 1.19-1.3x
    # the drawn tiles' bytes with the root; 1 and 1: about as many again). The `--fill-gap` default of
    # commands/view.py is the same 4.
    fill_gap: int = 4
    fill_step: int = 4
    # Coarse to fine only where it pays (issue 31): the ancestors, the root included, are wanted only while the cut's
    # missing base payloads (a page head whose page is loading counted as `lod.reduction` times its own, what its
    # children will be) exceed this many bytes. Below it the cut itself arrives about as soon as an ancestor would:
    # 64 KiB is under the reference link's bandwidth-delay product (20 Mbit/s x 40 ms = 100 KB) and above the 2 %
    # cuts of donut and biker (17 and 49 KB), the scenes it was chosen on; the ancestors were then 0.09-0.10x of the
    # drawn bytes on top (BENCHMARKS.md, "A small cut fetched directly"). 0: always coarse to fine (as before).
    # The `--fill-min-kb` default of commands/view.py is this one.
    fill_min_bytes: int = 64 << 10
    # The root, then the cut (issue 31, rootcut31): where the cut's missing base payloads (counted as for
    # fill_min_bytes) exceed fill_min_bytes but not this many bytes, the wish list is the root's base, then the cut's
    # bases in the cut's order, without the ancestors between (what --skip-levels fetches at these cuts). Over
    # HTTP/1.1 with 6 requests in flight such a cut is bound by request rounds, not bytes: the root gives the first
    # picture in one round, as coarse to fine does, and the cut, freed of the ancestors' requests, converges sooner
    # with fewer bytes. 512 KiB: chosen on donut and biker on the 20 Mbit/s, 40 ms link by
    # bench/results/rootcut31/RULE.md (cuts of 126-459 KB: first picture -9..+6 ms, converged 48-490 ms sooner,
    # 0.07-0.12 fewer bytes a drawn byte; the root alone 274-365 ms where coarse to fine refined it after 28-180 ms;
    # BENCHMARKS.md, "The root, then the cut"). Above it, coarse to fine (not measured above 459 KB).
    # 0 (or at most fill_min_bytes): no such band, coarse to fine above fill_min_bytes as before.
    # The `--fill-root-kb` default of commands/view.py is this one.
    fill_root_bytes: int = 512 << 10
    # The root's base stays in the wish list of a small cut too: set by a session that asked for the root with the
    # manifest, before the view was known (streaming.root_wanted: no splat budget that bounds the cut), so that the
    # root it fetched anyway is drawn first, as before, rather than dropped.
    root_first: bool = False
    # While the camera rests, a paged scene's page is wanted only where the budget (--max-splats, the pool's byte
    # share) could let its head's children into the cut (selection.pages_the_budget_can_use, client.md 1.11): a
    # page it cannot use is neither fetched nor parsed (donut and biker, --page-levels 4 and 5, at 2-50 %:
    # BENCHMARKS.md, "Pages a budget cannot use"). False (and while the camera moves): the page of every cut tile
    # the view would refine, as before.
    pages_by_budget: bool = True
    decode_workers: int = 2
    # Decode threads that run while the camera moves (all decode_workers while it rests): each thread decoding
    # Python takes the interpreter lock from the frame loop in the frames of a flight (the slow frames of the 250M
    # fly-through held about 2.5 ms of each decode thread's CPU: BENCHMARKS.md, "Manifest pages"). 0: no limit.
    decode_workers_moving: int = 1
    # The payloads of one group that arrive in one collect decoded together (format.decode.decode_payloads: the
    # same planes, bit for bit, in fewer and longer numpy calls, so fewer hand-overs of the interpreter lock per
    # splat), in jobs of at most decode_batch_splats splats (a payload above it alone). A decode thread waits for
    # the frame loop only between steps, and a batch's step is a plane of all its payloads: on the 2-core VM a
    # step of 12 batched 4k-splat payloads took 1.5 ms at p99 against 0.2 ms for one, for a few percent less CPU;
    # small tiles are where a payload's fixed cost is most of its decode (BENCHMARKS.md, "Manifest pages").
    # False: one job a payload.
    decode_batch: bool = True
    decode_batch_splats: int = 4096
    # Decode in this many worker processes instead of threads (0: threads). Processes keep the decoders' Python off
    # the render thread's interpreter lock; until they have started, payloads are decoded on the threads.
    decode_processes: int = 0
    ready_bytes: int = 512 << 20  # decoded payloads waiting for upload (prefetched ones are dropped first)
    # A paged scene's tree held at most this many tiles beyond what the view uses: pages whose tiles are neither
    # resident, nor in the cut, nor being decoded are dropped, least recently drawn first, and read again when a cut
    # reaches them. A tile held takes about 2.8 KB (SH0) to 4.0 KB (SH3) with its arrays, so 24,576 tiles are at
    # most about 100 MB; a street-level path across 250M splats holds 21,138 tiles, 59 MB (BENCHMARKS.md,
    # "Manifest pages").
    max_tree_tiles: int = 24576
    # A pass that drops pages drops them down to this share of max_tree_tiles below it (a low-water mark), so that
    # passes are rarer: a pass still groups the whole tree held by page (PagedTree.held, 0.2-0.3 ms at 16,384 tiles
    # on the shared VM; renumbering it in order was 7-12 ms before tiles moved into the holes), dropping 2 pages or
    # 20 (BENCHMARKS.md, "Manifest pages"). 0: down to max_tree_tiles.
    tree_low_water: float = 1 / 16
    # After a frame adds pages, move every object that exists then out of the garbage collector's walks
    # (gc.freeze(), process-wide, as the shells do once a session is open: streaming.freeze_long_lived). A held tree
    # is tens of thousands of parsed tiles; a full collection walked all of them mid-frame (5 passes of up to 785 ms
    # on a 250M-splat path: BENCHMARKS.md, "Manifest pages"). Frozen objects are still freed when no longer
    # referenced (a dropped page's tiles hold no reference cycles); only cyclic garbage existing at that moment is
    # kept. False: the collector as configured.
    freeze_pages: bool = True
    # The numpy path's rule (the compiled selection, once ready, selects near the cut whatever the tiles held):
    # from this many tiles held the selection looks near the cut only (selection.select_near); below it, over every
    # tile (view_numbers and select): the same cut, and numpy over a few thousand tiles costs less than finding the
    # tiles near the cut (interleaved on the 2-core VM: 1,536 tiles held 1.5 against 2.0 ms, 6,548 5.1 against
    # 5.1, 20,402 10.6 against 6.6; BENCHMARKS.md, "Manifest pages").
    select_near_from: int = 4096
    # The selection near the cut compiled (selection_jit, numba: the optional extra `fast`), the same cut as the
    # numpy path in a fraction of its time (BENCHMARKS.md, "Manifest pages"). Its kernels are compiled or loaded
    # from numba's cache on a worker thread from the first frame that selects near the cut or follows a page's
    # arrival, and used once ready whatever the tiles held; the numpy path runs until they are ready, and always
    # where numba is not installed. False: the numpy path always.
    compiled_selection: bool = True
    # The interpreter's switch interval (seconds, sys.setswitchinterval) while the frame loop computes the view's
    # numbers and the cut (the compiled selection's; the numpy path's untouched), the process's own restored after.
    # Process-wide while it is set: a short one makes the frame loop ask for the lock back sooner where it let it
    # go, and makes the decode threads waiting ask it to hand the lock over as soon. None (the default): untouched.
    # 0.2 ms was the default while the view and the cut let the lock go about 15 times a selection (numpy's fills,
    # BLAS dots, copies: the GPU machine at 60M, the selection's p99 1.66-1.69 -> 1.23-1.37 ms, r14); since they
    # keep it (0.1 a selection, when the tree's arrays grow), 0.2 ms only hands the lock over: on the VM with two
    # busy threads, 0.24-1.20 waits a selection at 0.2 ms against 0.02-0.10 untouched (0.00 at 20 ms, which would
    # make a wait at a release left up to 20 ms), the wall median 0.62-0.84 ms against 0.48-0.70 (BENCHMARKS.md,
    # "Manifest pages", branch selgil).
    select_switch_interval: float | None = None


class CompiledSelection:
    """selection_jit.select_near_compiled once its kernels are ready: `get` starts their compilation (or their
    loading from numba's cache) on a worker thread the first time it is asked and answers None until it is done, so
    that no frame waits for numba (importing it takes 0.3-0.6 s, compiling the kernels seconds: BENCHMARKS.md,
    "Manifest pages"). None for good where numba is not installed. One per process: every engine shares it."""

    def __init__(self) -> None:
        self._fn = None
        self._draw = None  # selection_jit.draw_set_compiled, ready with _fn
        # selection_jit itself, ready with _fn: the engine's other kernels that keep the interpreter lock (the wish
        # list's coarse-to-fine climb, the per-tile state grown by a page)
        self.kernels = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.error: BaseException | None = None  # why it is not available (numba missing, a failed compilation)
        self.decode_error: BaseException | None = None  # why the compiled fields1 decoder is not installed

    def get(self, start: bool = True):
        """The compiled function, or None while it is not ready; `start` False: never starts loading it (a caller
        that uses it only if another has loaded it)."""
        fn = self._fn
        if fn is None and start and self._thread is None:
            with self._lock:
                if self._thread is None:
                    self._thread = threading.Thread(target=self._load, name="splatstream-selection-jit", daemon=True)
                    self._thread.start()
        return fn

    def draw(self):
        """The compiled draw set (selection_jit.draw_set_compiled), or None while the kernels are not ready (never
        starts loading them: the selection does)."""
        return self._draw

    def wait(self, timeout: float | None = None):
        """Start it if not started, wait until it is ready or has failed: the function or None (benchmarks, tests)."""
        self.get()
        assert self._thread is not None
        self._thread.join(timeout)
        return self._fn

    def _load(self) -> None:
        # First in a child process, which compiles the kernels into numba's cache where they are not there yet
        # (4-5 s of CPU) without this process's interpreter lock: compiled on this thread, it slowed the frame loop
        # fourfold for 10 s on the 2-core VM (BENCHMARKS.md, "Manifest pages"). Then here, from the cache.
        # A child that fails (numba missing) leaves it to this thread; a frozen application has no interpreter to
        # start (sys.executable is the application).
        if not getattr(sys, "frozen", False):
            subprocess.run([sys.executable, "-c", _WARM_UP, str(os.getpid())], capture_output=True, check=False)
        try:
            # imported here: numba is an optional extra, and its import is what this thread keeps off the frames
            from . import selection_jit
            selection_jit.warm_up()
        except Exception as exc:  # ImportError without numba; anything else also leaves the numpy path (same cut)
            self.error = exc
            return
        try:
            # the compiled fields1 decoder too (decode_jit): the decode threads of this process take it from the
            # next payload on (the same bytes as the numpy path; issue 32's decode speed). Decode processes keep
            # numpy.
            from . import decode_jit
            decode_jit.install()
        except Exception as exc:  # a failed compilation leaves the numpy path (the same bytes)
            self.decode_error = exc
        self._draw = selection_jit.draw_set_compiled
        self.kernels = selection_jit
        self._fn = selection_jit.select_near_compiled


# The child leaves when its parent does: a viewer killed while the child compiles (SIGTERM, SIGKILL: nothing runs
# subprocess.run's clean-up) would otherwise leave it compiling on, and a run of such kills left a dozen of them
# fighting over numba's cache for minutes on the 2-core VM. On Linux the kernel kills it (PR_SET_PDEATHSIG, asked
# for first thing; argv[1], the parent's pid, catches a parent gone before that); elsewhere a thread watches the
# parent, which a compile in progress can starve until it ends.
_WARM_UP = ("import os, sys, threading, time\n"
            "parent = int(sys.argv[1])\n"
            "if sys.platform.startswith('linux'):\n"
            "    import ctypes, signal\n"
            "    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)\n"
            "def leave_with_parent():\n"
            "    while os.getppid() == parent:\n"
            "        time.sleep(0.25)\n"
            "    os._exit(1)\n"
            "if os.getppid() != parent:\n"
            "    os._exit(1)\n"
            "threading.Thread(target=leave_with_parent, daemon=True).start()\n"
            "from client_gl.stream import selection_jit, decode_jit\n"
            "selection_jit.warm_up()\n"
            "decode_jit.warm_up()\n")


COMPILED_SELECTION = CompiledSelection()


@dataclass
class FrameUpdate:
    draw: list[int]  # tile ids to draw
    converged: bool  # nothing the view wants is missing, nothing in flight
    uploaded_bytes: int
    resident_tiles: int
    resident_splats: int
    drawn_splats: int
    wanted_tiles: int
    in_flight: int
    selection: Selection | None = None
    events: list[str] = field(default_factory=list)


@dataclass
class _Ready:
    key: Key
    planes: dict
    extra: Any
    nbytes: int


def decode_job(data: VerifiedPayload | bytes, entry: PayloadEntry, group: str, where: str, codebook_tile: bool,
               splats: int, codebook_entries: int, with_mirror: bool, palettes=None,
               between=None) -> tuple[dict, Any] | str:
    """A payload decoded into planes (and the CPU-sort path's host mirror of a base): on a decode thread or in a
    decode process (plain arguments, so it pickles). A VerifiedPayload (the fetcher's) is not hashed again; bytes
    from a fetcher that does not verify are verified here. A payload that does not decode gives the error's message:
    the bytes matched their checksum, so the scene is broken, not the link. between: a decode thread's wait for the
    frame loop, between the payload's steps (decode_payload). palettes: the scene's palettes (format.md 4.3.2), for
    a base payload whose palette planes index them."""
    try:
        planes = decode_payload(data, entry, group, where, codebook_tile, between, palettes)
        return _as_held(planes, group, where, codebook_tile, splats, codebook_entries, with_mirror)
    except SplatstreamError as exc:
        return str(exc)


def _as_held(planes: dict, group: str, where: str, codebook_tile: bool, splats: int, codebook_entries: int,
             with_mirror: bool) -> tuple[dict, Any]:
    """A payload's decoded planes as the pool takes them, and the host mirror of a base where asked."""
    # Palette planes (format.md 4.3.2) as the pool holds them, here on the decode side: about 2 ms a plane of a
    # 16,384-splat tile, which the pool's join would otherwise spend on the render thread.
    planes = {k: palette_as_ranged(p, splats) for k, p in planes.items()}
    if codebook_tile and group == "sh1":
        codebook_index(planes, splats, codebook_entries, where)
    return planes, (host_mirror(planes, splats) if with_mirror else None)


def _internal_error(key: Key, exc: Exception) -> str:
    """A decode thread's error that is not the payload's (decode_job returns those as their message): the payload
    is marked failed with this line, which the errors list and the window show, where the exception used to stay in
    the pool's future, unseen, and the payload in _decoding for ever, so that the view never converged."""
    return f"tile {key[0]} {key[1]}: decoding failed inside splatstream: {type(exc).__name__}: {exc}"


def decode_batch_job(jobs: list[tuple], between=None) -> list[tuple[dict, Any] | str]:
    """decode_job of several payloads of one group (each item decode_job's arguments) in one decode_payloads call:
    the same results, bit for bit. A batch that does not decode is decoded again one payload at a time, so that the
    payload at fault is the one named, and the others are kept."""
    try:
        palettes = jobs[0][8] if len(jobs[0]) > 8 else None  # the scene's (format.md 4.3.2), the same in every job
        planes = decode_payloads([(j[0], j[1]) for j in jobs], jobs[0][2], [j[3] for j in jobs], jobs[0][4], between,
                                 palettes=palettes)
    except SplatstreamError:
        return [decode_job(*j, between=between) for j in jobs]
    out: list[tuple[dict, Any] | str] = []
    for p, (_, _, group, where, codebook_tile, splats, entries, with_mirror, *_) in zip(planes, jobs, strict=True):
        try:
            out.append(_as_held(p, group, where, codebook_tile, splats, entries, with_mirror))
        except SplatstreamError as exc:
            out.append(str(exc))
        if between is not None:
            between()
    return out


def root_frame_box(planes: dict, splats: int) -> tuple[np.ndarray, np.ndarray]:
    """camera.framing_box of a tile's splats from its decoded base planes (positions, opacities from the colour
    plane's alpha, and log scales, which frame splats all at one point). The root tile holds the whole scene,
    coarsely: its box is the scene's within a few % (BENCHMARKS.md, "The F key frames the scene")."""
    positions = decode_plane(planes["position"], splats)[:, 0]
    try:
        alpha = np.clip(decode_plane(planes["color"], splats)[:, 0, 3].astype(np.float64), 1e-6, 1.0 - 1e-6)
        logits = np.log(alpha) - np.log1p(-alpha)
    except UsageError:  # BC7 colour without the 'bc' extra (the GPU decodes it, this could not): every splat
        logits = None
    lo, hi = framing_box(positions, logits)
    if np.linalg.norm(hi - lo) > 0:
        return lo, hi
    # every splat at one point (a 1-splat scene): framed by their size, so the scale plane is decoded only then
    return framing_box(positions, logits, log_scales=decode_plane(planes["scale"], splats)[:, 0])


def _warm_up() -> bool:
    """Runs once in each decode process before it takes payloads: the imports are done by then."""
    return True


def planes_nbytes(planes: dict) -> int:
    total = 0
    for p in planes.values():
        total += sum(int(np.asarray(layer).nbytes) for layer in p.layers)
        if p.ranges is not None:
            total += int(p.ranges.nbytes)
    return total


class _Prefetch:
    """Iterates over the base keys that prefetch() names for a view, computed on first use and kept."""

    def __init__(self, arrays, view, sel, opts, ids, cost, kernels=None) -> None:
        self._args, self._ids, self._keys = (arrays, view, sel, opts, cost), ids, None
        # the widened frustum's box test compiled where the selection's kernels are loaded (the same tiles)
        self._boxes = kernels.boxes_at if kernels is not None else None

    def __iter__(self):
        if self._keys is None:
            ids = self._ids
            self._keys = [(int(ids[i]), "base") for _, i in prefetch(*self._args, boxes=self._boxes)]
        return iter(self._keys)


class StreamEngine:
    def __init__(self, fetcher: FetcherLike, residency: Residency, options: StreamOptions = StreamOptions(),
                 slot_bytes: int = 1, manifest: Manifest | None = None, with_mirror: bool = False,
                 location: str = "scene"):
        """`slot_bytes`: GPU bytes of one 256-splat slot (tile costs are counted in them); `with_mirror`: decode
        workers also compute each tile's host mirror (pools of the CPU-sort path keep one)."""
        self.fetcher = fetcher
        self.residency = residency
        self.options = options
        self.location = location
        m = manifest if manifest is not None else fetcher.manifest()
        # A paged scene (format.md 6.1): the tree grows as the cut reaches its pages (pages.py); its tiles keep
        # their positions, so the per-tile arrays below only grow. A manifest with every tile is not paged here.
        # (its arrays' storage made for the bound and a quarter more, or the whole tree where smaller: not doubled
        # in the frames of the path, PagedTree's rows_ahead)
        self.pages = PagedTree(m, location, min(m.paged.tiles, options.max_tree_tiles * 5 // 4)) \
            if m.paged is not None and len(m.tiles) < m.paged.tiles else None
        if self.pages is not None:
            m = self.pages.manifest
        self.slot_bytes = slot_bytes
        self.codebook = m.uses_codebook
        self.with_mirror = with_mirror
        self.resident = np.zeros(0, bool)
        self.slots_needed = np.zeros(0, np.int64)  # 256-splat slots per tile
        self.bands = np.zeros(0, np.int64)  # SH bands resident per tile
        self.last_drawn = np.zeros(0, np.int64)
        self._filling = np.zeros(0, bool)  # ancestors of the cut in that list (fill_levels)
        self._adopt(m)
        max_splats = options.selection.max_splats
        root_splats = int(self.arrays.splats[self.root])
        if max_splats is not None and max_splats < root_splats:
            raise UsageError(f"{location}: --max-splats {max_splats:,} is below the scene's coarsest level (its root "
                             f"tile holds {root_splats:,} splats): expected at least {root_splats:,}")
        self.codebook_bands: set[int] = set()
        self._pages_wanted: list[Key] = []
        self._heads_waiting: list[Key] = []  # heads the budget could refine whose pages wait (pages_by_budget)
        # cut tiles (positions) whose place in the cut a wanted page could undo: not fetched while it loads
        self._held_cut = np.zeros(0, np.intp)
        self._moving = False  # the camera differs from the last frame's (_set_moving)
        self._pages_arrived: dict[int, Future] = {}  # tile id -> its page's tiles, being parsed
        self._page_frame: dict[int, int] = {}  # tile id -> the frame its page was added in
        self._last_cut = np.zeros(0, np.intp)  # the last selection's cut (positions): kept from eviction, and where
        # the next frame's selection starts looking
        self._bases = np.zeros(0, np.intp)  # positions of the wish list's bases (_coarse_to_fine)
        self._up: tuple[np.ndarray, np.ndarray] | None = None  # (the tree's parents, with a spare row: _coarse_to_fine)
        # The compiled selection's per-tile arrays, kept from frame to frame (ViewBuffers): a frame's view owns them
        # until the next selection (the engine uses a view only in the frame that made it, or while it is cached)
        self._view_buffers = ViewBuffers(self.pages.rows_ahead if self.pages is not None else 0)
        if options.compiled_selection:  # made here, not in the first frame's selection (ViewBuffers.prepare)
            self._view_buffers.prepare(len(self.resident))
        self._pages_checked: tuple[int, int] = (0, 0)  # (tiles held, payload evictions) at the last eviction pass
        self.frame = 0
        self.refined = np.zeros(0, np.intp)  # the last selection's refined tiles (positions: its hysteresis)
        # the cut's positions and their bands wanted (arrays, in the cut's order)
        self._bands_wanted: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.intp), np.zeros(0, np.int64))
        # The SH part of the last keys `wanted` made, as blocks of the same keys in the same order: (keys, bases in
        # them, [(group, band, positions)]), positions None for a band of the codebook (one key). _tell_fetcher
        # takes what is missing of them in numpy, a block at a time, instead of a _have per key.
        self._sh_blocks: tuple[list, int, list[tuple[str, int, np.ndarray | None]]] | None = None
        # Caches that let a still camera with nothing arriving skip the per-frame work (selection, wish list,
        # draw set): _version counts changes of what is held (resident, decoding, ready).
        self._wanted_cache: tuple | None = None
        self._wanted_serial = 0
        self._version = 0
        self._state_seen: tuple | None = None
        self._missing: list[Key] = []
        self._keys: list[Key] = []  # the wish list of the current state (with the ancestors being filled in)
        self._order_of: tuple[list[Key], dict[Key, int]] | None = None  # a wish list and its keys' ranks (_upload)
        self._upload_idle: tuple[int, list[Key]] | None = None  # (version, wish list) with nothing to upload
        self._listed: tuple = ()
        self._priority_list: list[float] = []  # the wish list's priorities, kept (_priorities)
        self._draw_cache: tuple | None = None
        self._drawn_ids: np.ndarray | None = None  # the ids of the last draw set that was not empty (_draw_counts)
        self._root_first = False  # a small cut waited for pages before the first frame: the root is wanted until then
        self._ready: dict[Key, _Ready] = {}
        self._ready_bytes = 0
        self._decoding: set[Key] = set()
        self._decoded: queue.Queue = queue.Queue()
        # The root tile's framing box (camera.framing_box of its splats: the rule of the suggested camera), once its
        # base has decoded: what the viewer's F key frames (the bounding sphere holds every stray splat). Computed
        # when first asked for (frame_box), from the root's planes kept here: computed in the frame that collected
        # the root, it held the first frame's engine.update at 50-80 ms where it had taken 5-7 (the GPU machine, 1M
        # splats, r23: frame31's box on the frame loop, beside the decode kernels' loading)
        self._frame_box: tuple[np.ndarray, np.ndarray] | None = None
        self._root_planes: tuple[dict, int] | None = None
        self._pool = ThreadPoolExecutor(max_workers=options.decode_workers, thread_name_prefix="splat-decode")
        self._closing = False
        # Set while the frame loop is not in its CPU work (engine update, draw submission): decode threads run each
        # step of a payload only then, and the fetcher handles its I/O only then (Fetcher.yield_to). Their Python
        # took the interpreter lock from the frame loop at each of its numpy calls: frames spent most of their time
        # waiting for it (BENCHMARKS.md). A frame loop that never says when it works (tests, tools) leaves it set.
        self._loop_idle = threading.Event()
        self._loop_idle.set()
        # How many decode jobs may run at once (decode_workers_moving while the camera moves), and how many do.
        self._decode_turns = threading.Condition()
        self._decode_limit = options.decode_workers
        self._decode_running = 0
        self._last_camera: tuple | None = None
        self.moving_frames = 0  # frames whose camera moved since the last (decode_workers_moving applied)
        self.decode_jobs = 0  # jobs handed to the decode threads, and the payloads in them (decode_batch's effect)
        self.decode_job_payloads = 0
        self._processes: ProcessPoolExecutor | None = None
        self._processes_ready: Future = Future()
        if options.decode_processes > 0:
            # forkserver: a clean child (this process has GL and network threads that a fork would copy mid-state)
            self._processes = ProcessPoolExecutor(options.decode_processes, get_context("forkserver"))
            self._processes_ready = self._processes.submit(_warm_up)
        self._entries: dict[Key, PayloadEntry] = {}
        self.errors: list[str] = []
        # Payloads that verified but do not decode: never wanted again, nor the bands above them (issue 37).
        self.failed: dict[Key, str] = {}
        self.process_decodes = 0  # payloads decoded in the decode processes (decode_processes > 0)
        self.uploaded_bytes_total = 0
        self.evictions = 0

    def _adopt(self, m: Manifest) -> None:
        """Take a manifest whose tiles start with those held so far, in the same positions (a paged scene's tree,
        grown by a page): the arrays over its tiles, the per-tile state grown with zeros."""
        self.manifest = m
        self.arrays = m.arrays
        self.root = m.index_of[m.root]
        self.ids = self.arrays.ids
        grow = len(m.tiles) - len(self.resident)
        # Compiled (selection_jit.grown, slot_cost) once the selection's kernels are loaded: the same arrays, made
        # keeping the interpreter lock (numpy's concatenations, zeros and the costs' product over the tree held let
        # it go 7 times an adoption: BENCHMARKS.md, "Manifest pages", branch updgil)
        jit = self._kernels
        if not grow:  # an eviction's tree (its per-tile state taken in _evict_pages)
            self.cost = self._slot_cost(jit)
            return
        # the new tiles' only (a page's tiles are appended; eviction takes the kept rows before adopting)
        chunks = np.array([t.chunks for t in m.tiles[len(self.resident):]], np.int64)
        n = len(m.tiles)
        if jit is not None:
            slots = jit.grown(self.slots_needed, n)
            slots[n - grow:] = chunks
            self.slots_needed = slots
            self.resident, self.bands, self.last_drawn, self._filling = (
                jit.grown(state, n) for state in (self.resident, self.bands, self.last_drawn, self._filling))
        else:
            self.slots_needed = np.concatenate([self.slots_needed, chunks])
            self.resident = np.concatenate([self.resident, np.zeros(grow, bool)])
            self.bands = np.concatenate([self.bands, np.zeros(grow, np.int64)])
            self.last_drawn = np.concatenate([self.last_drawn, np.zeros(grow, np.int64)])
            self._filling = np.concatenate([self._filling, np.zeros(grow, bool)])
        self.cost = self._slot_cost(jit)

    @property
    def _kernels(self):
        """selection_jit where the compiled selection is asked for and its kernels are loaded (the frame loop's
        kernels that keep the interpreter lock), else None: the numpy paths."""
        return COMPILED_SELECTION.kernels if self.options.compiled_selection else None

    def _slot_cost(self, jit) -> np.ndarray:
        """Each tile's bytes in the pool (its slots' bytes), the selection's cost."""
        if jit is not None:
            return jit.slot_cost(self.slots_needed, self.slot_bytes)
        return self.slots_needed.astype(np.float64) * float(self.slot_bytes)

    def _add_pages(self) -> None:
        """Pages parsed (on the decode workers: a page of a large tree is milliseconds of Python the frame loop
        would otherwise spend): the tree grows below their tiles, and this frame selects over the grown tree
        (adopted once for all of them: the arrays grown by their tiles, whose rows the workers took)."""
        for tile_id, future in [(t, f) for t, f in self._pages_arrived.items() if f.done()]:
            del self._pages_arrived[tile_id]
            try:
                self.pages.insert(tile_id, future.result())
                self._page_frame[tile_id] = self.frame
            except SplatstreamError as exc:  # verified bytes that do not parse: the scene is broken, not the link
                self.errors.append(str(exc))
                self.failed[(tile_id, PAGE_GROUP)] = str(exc)
        self._adopt(self.pages.manifest)
        if self.options.freeze_pages:
            gc.freeze()
        self._wanted_cache = None  # the same camera selects again, over the new tiles
        self._draw_cache = None
        self._version += 1

    def _evict_pages(self) -> None:
        """Drop pages until the tree held is within max_tree_tiles, down to its low-water mark (_pages_to_drop), the
        per-tile state taken through the positions kept and the per-key state of the tiles dropped forgotten."""
        heads = self._pages_to_drop()
        if not heads:
            return
        # the moves in place by the compiled kernel where it is loaded (it keeps the interpreter lock: numpy's let
        # it go once an array, 18 a pass; BENCHMARKS.md "Manifest pages", evict38)
        jit = self._kernels
        move_rows = jit.move_rows if jit is not None else None
        keep = self.pages.evict(heads, move_rows)  # (its arrays' storage rewritten: self.ids, the last view's)
        k = len(keep)
        # the tree's one compaction map (new position of each old one, -1 dropped; the moves' targets and sources)
        new_of, moved, src = self.pages.compaction
        self._forget(self.pages.dropped_ids, heads)
        # the tiles kept keep their positions but for the last ones, moved into the holes (PagedTree.evict): their
        # state moved in place and the arrays cut to the tiles kept (taking every row through `keep` wrote new
        # memory, page faults over the tiles held)
        for name in ("resident", "bands", "last_drawn", "_filling", "slots_needed"):
            state = getattr(self, name)
            if move_rows is not None:
                move_rows(state, moved, src)
            else:
                state[moved] = state[src]
            setattr(self, name, state[:k])
        refined, last_cut = new_of[self.refined], new_of[self._last_cut]
        self.refined, self._last_cut = refined[refined >= 0], last_cut[last_cut >= 0]
        self._adopt(self.pages.manifest)
        self._wanted_cache = self._draw_cache = self._order_of = self._upload_idle = None
        self._version += 1

    def _forget(self, gone: list[int], heads: list[int]) -> None:
        """The per-key state of tiles dropped with their pages (ids `gone`), and the page frames of the pages
        dropped (`heads`, and the pages held below them among `gone`): kept, the entry cache and page frames grew
        with every tile ever seen on a long flight (issue 38). A dropped tile's entries are looked up again from
        its page when a cut reads it again. What stays: a tile dropped is never decoding, decoded or resident
        (_pages_to_drop), the fetcher keeps per-key state of listed keys only, and `failed` (payloads that verified
        but did not decode, and pages that did not parse) is kept on purpose: it is bounded by the broken
        payloads, not the tiles seen, and keeps a broken payload from being fetched again when its page is."""
        pop = self._entries.pop
        for group in _GROUP_BAND:
            deque(map(pop, zip(gone, repeat(group)), repeat(None)), 0)
        frame_pop = self._page_frame.pop
        deque(map(frame_pop, gone, repeat(None)), 0)
        deque(map(frame_pop, heads, repeat(None)), 0)

    def _pages_to_drop(self) -> list[int]:
        """The heads of the pages to drop, in order, for the tree held beyond max_tree_tiles to be within its
        low-water mark (StreamOptions.tree_low_water): pages unused (no
        tile below their head resident, in the last cut, decoding or decoded, nor a page below it being fetched or
        parsed), the least recently drawn first, then the larger, then the lower head id. The tiles below each head
        are found by grouping the tiles held by page (PagedTree.held), in array operations: a walk of the tree below
        every page held took 73-107 ms of a frame at 250M splats (issue 38, BENCHMARKS.md "Manifest pages")."""
        n = len(self.resident)
        in_cut = np.zeros(n, bool)
        in_cut[self._last_cut] = True
        since = self.frame - 1
        # First a cheap look (most passes follow a page added beyond the bound and drop nothing: 34 of 40 on the
        # bench's path at 16,384 tiles, 0.5 ms each for the grouping below): a page to drop has all its own tiles
        # unused (neither resident nor in the last cut), its head not in the cut, and was not added since the last
        # selection; none such, nothing to drop (the busy pages only take candidates away, so not needed here).
        maybe = self.pages.heads_unused(self.resident | in_cut)
        page_frame = self._page_frame
        if not any(page_frame.get(h, 0) < since for h in self.ids[maybe[~in_cut[maybe]]].tolist()):
            return []
        held = self.pages.held()
        busy_ids = {k[0] for k in self._ready} | {k[0] for k in self._decoding} | set(self._pages_arrived) | \
            {k[0] for k in self._listed if k[1] == PAGE_GROUP}  # pages in flight or being parsed stay
        index_of = self.manifest.index_of
        used = self.resident | in_cut
        used[[index_of[t] for t in busy_ids if t in index_of]] = True
        count = held.tiles_below  # tiles below each head
        used_below = held.below(used.astype(np.int64), np.add, 0)
        last = held.below(self.last_drawn, np.maximum, np.iinfo(np.int64).min)
        recent = np.fromiter(map(page_frame.get, held.ids.tolist(), repeat(0)), np.int64, len(held.ids)) >= since
        # not added since the last selection, nor its tile in the cut (the page would be wanted again)
        candidates = np.flatnonzero(~recent & ~in_cut[held.heads] & (count > 0) & (used_below == 0))
        order = candidates[np.lexsort((held.ids[candidates], -count[candidates], last[candidates]))]
        bound = self.options.max_tree_tiles
        # beyond the bound, down to the low-water mark below it (passes rarer: StreamOptions.tree_low_water)
        excess = len(self.manifest.tiles) - bound + int(bound * self.options.tree_low_water) \
            if len(self.manifest.tiles) > bound else 0
        # the fewest in that order whose tiles make up the excess (counted as they stand: a page below another
        # taken counts twice, as it always has)
        taken = min(len(order), int(np.searchsorted(np.cumsum(count[order]), excess)) + 1) if excess > 0 else 0
        return held.ids[order[:taken]].tolist()

    # --- keys -------------------------------------------------------------------------------------------------
    def entry(self, key: Key) -> PayloadEntry:
        # Kept once looked up: a moving camera's wish list names a few hundred payloads a frame, and the lazily
        # checked manifest's lookup took 2 us each (0.3-0.5 ms a frame on the 6M tiled donut).
        entry = self._entries.get(key)
        if entry is None:
            tile_id, group = key
            entry = (self.manifest.sh_codebook.groups[group] if tile_id is None
                     else self.manifest.tile(tile_id).groups[group])
            self._entries[key] = entry
        return entry

    def _have(self, key: Key) -> bool:
        tile_id, group = key
        band = _GROUP_BAND[group]
        if tile_id is None:
            return band in self.codebook_bands
        i = self.manifest.index_of[tile_id]
        return bool(self.resident[i]) and (band == 0 or self.bands[i] >= band)

    # --- the frame --------------------------------------------------------------------------------------------
    def wanted(self, cam: Camera) -> tuple[PartialView | TileView, Selection, np.ndarray, list[Key], list[Key]]:
        """(view, selection, bands per cut tile (in the cut's order), keys wanted now in priority order, prefetch keys).

        The same camera and options give the same answer (the selection is idempotent under its own hysteresis),
        so a still camera costs nothing here after its first frame."""
        key = (cam.eye, cam.target, cam.up, cam.fov_y_deg, cam.width, cam.height, self.options,
               self.residency.capacity_slots, self._moving)
        if self._wanted_cache is not None and self._wanted_cache[0] == key:
            return self._wanted_cache[1]
        a, opts = self.arrays, self.options.selection
        # A large tree held: the numbers of the tiles the selection reaches only, from the last frame's cut
        # (client.md 1.2): the children of its cut and refined tiles first, in one batch; the same cut as select
        # over every tile held (tests/test_stream_select_near.py checks it), at a cost that follows the cut.
        budget = self.residency.capacity_slots * self.slot_bytes * self.options.target_fraction
        sel_opts = SelectionOptions(**{**opts.__dict__, "budget": min(budget, opts.budget or budget)})
        view: PartialView | TileView
        near_cut = len(self.resident) >= self.options.select_near_from
        compiled = None
        if self.options.compiled_selection:
            # Loaded from the first frame that selects near the cut or after a page arrives (a paged scene's
            # first frame needs the root manifest only, and its first frames hold a few thousand tiles at most); once
            # ready, used whatever the tiles held: below select_near_from the numpy path selects over every tile
            # (view_numbers and select), which was the first seconds' slowest selections at 250M splats, 1-4 ms of CPU
            # a frame against 0.3-0.6 ms compiled (BENCHMARKS.md, "Manifest pages").
            paged = self.pages is not None and self.pages.pages_read > 0
            compiled = COMPILED_SELECTION.get(start=near_cut or paged)
        if compiled is not None:  # it takes the tiles whose children to look at first, and finds them itself
            interval = self.options.select_switch_interval
            if interval is not None:
                process_interval = sys.getswitchinterval()
                sys.setswitchinterval(interval)
            try:
                view = PartialView(a, cam, opts, self.manifest.lod.reduction, self._view_buffers)
                sel = compiled(a, view, self.cost, self.root, sel_opts, self.refined,
                               near_parents=(self.refined, self._last_cut))
            finally:
                if interval is not None:
                    sys.setswitchinterval(process_interval)
        elif near_cut:
            view = PartialView(a, cam, opts, self.manifest.lod.reduction)
            children = indexable(a.children)
            near = [k for i in self.refined.tolist() for k in children[i]] + \
                [k for i in self._last_cut.tolist() for k in children[i]]
            sel = select_near(a, view, self.cost, self.root, sel_opts, self.refined, near)
        else:
            view = view_numbers(a, cam, opts)
            sel = select(a, view, self.cost, self.root, sel_opts, self.refined, self.manifest.lod.reduction)
        # the selection's arrays as they are (no per-frame tuple, set or dict of the cut: BENCHMARKS.md, "Manifest
        # pages")
        cut = sel.cut_at
        self.refined, self._last_cut = sel.refined_at, cut
        if self.pages is not None:  # pages below cut tiles the view would refine: fetched before their payloads
            heads = self.pages.heads_to_refine(cut, view.sse, view.visible, opts.max_sse)
            waiting = heads[:0]
            held = cut[:0]
            # and, while the camera rests, whose children the budget could let in. While it moves every such page
            # is wanted, as before: a page the budget cannot use in this frame is often used a few frames on (on
            # bench_pages' city path at 250M, refusing them in motion read 0.8 % more payload bytes, and setting
            # aside the heads' likely additions 1.7 % more at 60M; BENCHMARKS.md, "Pages a budget cannot use")
            if len(heads) and self.options.pages_by_budget and not self._moving:
                now, _ = pages_the_budget_can_use(a, view, self.cost, self.root, sel, heads, sel_opts,
                                                  self.manifest.lod.reduction, self.manifest.chunk_size,
                                                  self.slot_bytes)
                heads, waiting = heads[now], heads[~now]
                if len(heads):  # and the cut tiles their pages (and the waiting ones') could take out of the cut
                    held = cut[cut_a_page_may_undo(a, view, self.cost, self.root, sel,
                                                   np.concatenate([heads, waiting]), sel_opts,
                                                   self.manifest.lod.reduction)]
            self._held_cut = held
            self._pages_wanted = [k for k in zip(self.ids[heads].tolist(), repeat(PAGE_GROUP))
                                  if k not in self.failed]
            # The other heads the view would refine are not fetched while pages are wanted (as when every such
            # page was wanted): the pages that come can move the budget, and a head fetched now was then often
            # left out of the cut (donut, --page-levels 4, at 25 %: 27-35 KB of such payloads against 0-7 KB)
            self._heads_waiting = [k for k in zip(self.ids[waiting].tolist(), repeat(PAGE_GROUP))
                                   if k not in self.failed]
        bands = wanted_bands_at(a, view, cut, opts, self.manifest.sh_degree)  # the cut's, in its order
        self._bands_wanted = (cut, bands)
        keys = self._make_keys(cut, bands)
        # prefetch only when asked for (update asks only when nothing the view wants is missing): 0.2-0.3 ms a frame
        extra = _Prefetch(a, view, sel, opts, self.ids, self.cost, self._kernels) if self.options.prefetch else ()
        result = (view, sel, bands, keys, extra)
        self._wanted_cache = (key, result)
        self._wanted_serial += 1
        return result

    def _make_keys(self, cut: np.ndarray, bands: np.ndarray) -> list[Key]:
        """The keys a cut wants, in priority order: the root's base, the cut's bases (in its order), then its SH
        bands (the codebook's bands and each tile's index, or each band's payloads band by band). The tile ids come
        from one numpy call a block and the tuples from zip (C loops, not a comprehension a key: 20-25 % less CPU
        for the keys at 250M splats with SH3, BENCHMARKS.md, "Manifest pages")."""
        ids = self.ids
        keys: list[Key] = [(int(ids[self.root]), "base")]
        keys += zip(ids[cut[cut != self.root]].tolist(), repeat("base"))
        bases = len(keys)
        blocks: list[tuple[str, int, np.ndarray | None]] = []
        top = int(bands.max()) if len(bands) else 0
        if self.codebook:
            blocks += [(f"sh{b}", b, None) for b in range(1, top + 1)]
            if top >= 1:
                blocks.append(("sh1", 1, cut[bands >= 1]))
        else:
            blocks += [(f"sh{b}", b, cut[bands >= b]) for b in range(1, top + 1)]
        for group, _, at in blocks:
            if at is None:
                keys.append((None, group))
            else:
                keys += zip(ids[at].tolist(), repeat(group))
        self._sh_blocks = (keys, bases, blocks)
        return keys

    def update(self, cam: Camera) -> FrameUpdate:
        self.frame += 1
        camera = (cam.eye, cam.target, cam.up, cam.fov_y_deg, cam.width, cam.height)
        self._set_moving(self._last_camera is not None and camera != self._last_camera)
        self._last_camera = camera
        self._tend_pages()
        view, sel, bands, keys, extra = self.wanted(cam)
        state = (self._wanted_serial, self._version)
        if state != self._state_seen:  # the wish list or what we hold changed: tell the fetcher what is missing now
            self._tell_fetcher(keys, extra, sel)
            self._state_seen = state
        self._collect()
        keys = self._keys
        uploaded, events = self._upload(self._missing, keys, sel) if self._ready else (0, [])
        if uploaded or events or self._draw_cache is None or self._draw_cache[0] != state:
            self._draw_cache = self._draw_counts(view, sel)
        _, drawn, (draw_ids, resident_tiles, resident_splats, drawn_splats) = self._draw_cache
        self.last_drawn[drawn] = self.frame
        stats = self.fetcher.stats()
        in_flight = stats.in_flight + stats.queued
        still_missing = any(not self._have(k) for k in self._missing) if self._missing else False
        converged = not still_missing and not self._decoding and in_flight == 0 and not self._pages_wanted \
            and not self._pages_arrived
        return FrameUpdate(
            draw=list(draw_ids), converged=converged, uploaded_bytes=uploaded, resident_tiles=resident_tiles,
            resident_splats=resident_splats, drawn_splats=drawn_splats, wanted_tiles=len(sel.cut_at),
            in_flight=in_flight + len(self._decoding), selection=sel, events=events)

    def _tend_pages(self) -> None:
        """A frame's start: the pages parsed since the last frame join the tree; pages are dropped beyond the
        tree's bound."""
        if self._pages_arrived and any(f.done() for f in self._pages_arrived.values()):
            self._add_pages()
        # pages are dropped only where the tree grew or tiles left the pool since the last look (a pass is
        # O(tiles held))
        if self.pages is not None and len(self.manifest.tiles) > self.options.max_tree_tiles and \
                (len(self.manifest.tiles), self.evictions) != self._pages_checked:
            self._evict_pages()
            self._pages_checked = (len(self.manifest.tiles), self.evictions)

    def _tell_fetcher(self, keys: list[Key], extra: list[Key], sel: Selection) -> None:
        """The wish list from this frame's selection, handed to the fetcher when it changed: what is missing, coarse
        to fine, pages right after the root's base, prefetch only when nothing is missing."""
        self._keys = self._coarse_to_fine(keys, sel) if self.options.fill_levels else keys
        if self.options.fill_levels and not self.failed:  # the bases' residency in numpy (_coarse_to_fine's order)
            base = self._bases
            self._missing = list(zip(self.ids[base[~self.resident[base]]].tolist(), repeat("base")))
            self._missing += self._sh_missing(keys, self._keys[len(base):])
            if self._pages_wanted and len(self._held_cut):  # (the blocks name the held tiles' bands too)
                out = set(self.ids[self._held_cut].tolist())
                self._missing = [k for k in self._missing if k[0] not in out]
        else:
            self._missing = [k for k in self._keys if not self._have(k) and not self._blocked(k)]
        busy = self._ready.keys() | self._decoding if self._ready or self._decoding else None
        want = self._missing if busy is None else list(filterfalse(busy.__contains__, self._missing))
        pre = [] if want else [k for k in extra if not self._have(k) and k not in self._ready
                               and k not in self._decoding]
        # pages right after the root's base (the first frame draws the root; a page only lets the cut refine)
        root_key = (int(self.ids[self.root]), "base")
        head = want[:1] if want[:1] == [root_key] else []
        pages = [k for k in self._pages_wanted if k[0] not in self._pages_arrived]  # not those being parsed
        listed = tuple(head + pages + want[len(head):] + pre)
        if len(listed) != len(self._listed) or listed != self._listed:  # (a tuple's != compares items first)
            self.fetcher.want(self._requests(listed, len(head), len(pages)))
            self._listed = listed

    def _sh_missing(self, keys: list[Key], sh_keys: list[Key]) -> list[Key]:
        """What is not held of the wish list's SH keys `sh_keys` (those of `keys`, in their order): from the blocks
        _make_keys made them from, in numpy (a tile's band is held once it is resident with that band), else a
        _have per key (keys made elsewhere)."""
        made = self._sh_blocks
        if made is None or made[0] is not keys:
            return [k for k in sh_keys if not self._have(k)]
        out: list[Key] = []
        resident, bands, ids = self.resident, self.bands, self.ids
        for group, band, at in made[2]:
            if at is None:
                if band not in self.codebook_bands:
                    out.append((None, group))
            elif len(at):
                out += zip(ids[at[~(resident[at] & (bands[at] >= band))]].tolist(), repeat(group))
        return out

    def _requests(self, listed: tuple[Key, ...], head: int, pages: int) -> list[tuple[float, Key, PayloadEntry]]:
        """The fetcher's requests for a wish list: (priority, key, entry), the first key's priority the list's
        length, down to 1; listed[head:head + pages] are pages (their entries the tree's). Entries kept from earlier
        frames are taken by one map over the cache (C loops, not a call of `entry` a key: with the rest of this
        branch about 20 % less CPU for the wish list, BENCHMARKS.md, "Manifest pages"); those not kept yet are
        looked up."""
        n = len(listed)
        entries: list[PayloadEntry | None] = list(map(self._entries.get, listed))
        page_entry = self.pages.entry if pages else None
        for r in range(head, head + pages):
            entries[r] = page_entry(listed[r][0])
        for r in compress(range(n), map(is_, entries, repeat(None))):  # keys asked for the first time
            entries[r] = self.entry(listed[r])
        return list(zip(self._priorities(n), listed, entries, strict=True))

    def _priorities(self, n: int) -> list[float]:
        """n, n - 1, .., 1 as floats (np.arange(n, 0, -1, float64).tolist()'s values): the tail of a list kept from
        the longest wish list so far (a list's slice keeps the interpreter lock; np.arange over 500 keys let it go
        every frame, and Python's map(float, range) cost 2.5x the arange), made again, longer, in pieces of 500
        under the lock's threshold."""
        kept = self._priority_list
        if n > len(kept):
            top = max(n, 2 * len(kept))
            kept = self._priority_list = list(chain.from_iterable(
                np.arange(hi, max(hi - 500, 0), -1, dtype=np.float64).tolist() for hi in range(top, 0, -500)))
        return kept[len(kept) - n:]

    def _draw_counts(self, view, sel: Selection) -> tuple:
        """The draw set and what a frame reports of it and of the residency, kept while neither changes (a still,
        converged view then costs no numpy work a frame)."""
        # compiled with the selection (the same tiles in the same order; the Python walk was about 1 ms a frame at
        # 250M splats: BENCHMARKS.md, "Manifest pages"), else the numpy reference
        compiled = COMPILED_SELECTION.draw() if self.options.compiled_selection else None
        max_splats = self.options.selection.max_splats
        drawn, resident_tiles, resident_splats, drawn_splats = self._draw_set_of(view, sel, compiled, True)
        # Descendants standing in for a wanted tile not loaded yet (the cut coarsened) hold more splats than it:
        # over the splat budget, ancestors cover it instead (client.md 2: the budget holds in every frame)
        if max_splats is not None and drawn_splats > max_splats:
            held = self._draw_set_of(view, sel, compiled, False)
            if len(held[0]):
                drawn, resident_tiles, resident_splats, drawn_splats = held
            elif not self.resident[self.root]:  # no ancestor covers it (the root was not fetched): the last set
                drawn, drawn_splats = drawn[:0], 0
        if len(drawn):
            self._drawn_ids = self.ids[drawn]
        elif self._drawn_ids is not None and not self.resident[self.root]:
            # Without the root (a small cut fetched directly: _ancestors_worth) nothing covers a region whose cut
            # tile is missing, and the walk draws nothing: the last set drawn stands in while its tiles are
            # resident (they are never evicted while drawn; a region the camera turned to stays empty meanwhile)
            index_of = self.manifest.index_of
            held = [index_of.get(t) for t in self._drawn_ids.tolist()]
            if all(i is not None and self.resident[i] for i in held):
                splats = int(self.arrays.splats[held].sum())
                if max_splats is None or splats <= max_splats:  # (the budget holds in every frame: 2)
                    drawn, drawn_splats = np.array(held, np.intp), splats
        counts = (self.ids[drawn].tolist(), resident_tiles, resident_splats, drawn_splats)
        return (self._wanted_serial, self._version), drawn, counts

    def _draw_set_of(self, view, sel: Selection, compiled, stand_ins: bool) -> tuple[np.ndarray, int, int, int]:
        """The draw set (positions), the tiles resident, their splats and the drawn splats."""
        if compiled is not None:  # with the residency's sums (whole numbers: numpy's)
            sums = np.zeros(3, np.int64)
            drawn = compiled(self.arrays, view, sel, self.resident, self.root, sums, stand_ins)
            resident_tiles, resident_splats, drawn_splats = sums.tolist()
            return drawn, resident_tiles, resident_splats, drawn_splats
        drawn = np.asarray(draw_set(self.arrays, view, sel, self.resident, self.root, stand_ins), np.intp)
        drawn_splats = int(self.arrays.splats[drawn].sum()) if len(drawn) else 0
        return drawn, int(self.resident.sum()), int(self.arrays.splats[self.resident].sum()), drawn_splats

    def _coarse_to_fine(self, keys: list[Key], sel: Selection) -> list[Key]:
        """The wish list with the ancestors of every cut tile not resident yet, bases ordered by level (then by
        the cut's priority: an ancestor takes the rank of its first descendant), SH bands after every base."""
        cut = sel.cut_at
        # A page head whose page is loading stands for the children the cut wants: an ancestor, not a cut tile
        loading = np.isin(self.ids[cut], [k[0] for k in chain(self._pages_wanted, self._heads_waiting)]) \
            if self._pages_wanted else None  # (no head waits where no page is wanted)
        # and a cut tile whose place in the cut a wanted page could undo is not fetched while it loads (client.md
        # 1.11): the page's children take budget that refinement had (donut --page-levels 5 at 50 %: 158 KB a
        # view fetched and given up, against 355 KB drawn)
        held = self._held_cut if self._pages_wanted and len(self._held_cut) else None
        need = self._missing_need(cut, loading)
        if self._ancestors_worth(need):
            base = self._with_ancestors(cut, loading)
        else:
            base = self._cut_alone(cut, loading if held is None else np.isin(cut, held) | (
                False if loading is None else loading), with_root=self._root_worth(need))
        if held is not None:
            base = base[~np.isin(base, held)]
        self._bases = base  # positions of the list's bases, in its order
        made = self._sh_blocks  # the keys' SH part (after their bases) as _make_keys made it
        sh = keys[made[1]:] if made is not None and made[0] is keys else [k for k in keys if k[1] != "base"]
        if held is not None:
            out = set(self.ids[held].tolist())
            sh = [k for k in sh if k[0] not in out]
        return list(zip(self.ids[base].tolist(), repeat("base"))) + sh

    def _cut_alone(self, cut: np.ndarray, loading: np.ndarray | None, with_root: bool = False) -> np.ndarray:
        """The bases of a cut fetched without its ancestors, self._filling cleared: the root first where with_root
        (the root, then the cut: fill_root_bytes), else only where it is a cut tile (a small cut)."""
        base = cut if loading is None else cut[~loading]
        if self._drawn_ids is None and (with_root or loading is not None and loading.any()):
            # (with_root: the root, once named, stays named until the first frame draws, also when the cut's missing
            # bytes then fall under fill_min_bytes: a request in flight is not cancelled for a later first picture)
            self._root_first = True
        if (with_root or self.options.root_first or self._root_first and self._drawn_ids is None) and \
                not (base == self.root).any():
            # nothing drawn yet and part of the cut waits for its page (a round trip more than the root): the
            # root, until the first frame draws, so that it comes as soon as without paging (root_first: always)
            base = np.concatenate(([self.root], base)).astype(np.intp)
        self._filling = np.zeros(len(self.resident), bool)
        return base

    def _with_ancestors(self, cut: np.ndarray, loading: np.ndarray | None) -> np.ndarray:
        """The bases of the cut and of its ancestors, coarse to fine, self._filling set (fill_levels)."""
        a = self.arrays
        gap, step = self.options.fill_gap, self.options.fill_step
        # Every fill_step-th ancestor, from fill_gap levels up, of each cut tile not resident: levels `reduction`
        # apart in splats would otherwise add about as many bytes as the cut itself (1/2 + 1/4 + ... at reduction
        # 2); a tile's rank is the least rank of the cut tiles that name it.
        jit = self._kernels
        if jit is not None:  # the same bases and flags compiled, keeping the interpreter lock (numpy let it go
            # about 12 times here a frame at 250M splats: arrays over the tree held, ufunc.at, lexsort)
            base, self._filling = jit.coarse_to_fine_compiled(a.parent, a.level, self.resident, cut, self.root,
                                                              gap, step)
        else:
            base = self._coarse_to_fine_numpy(cut, gap, step)
        if loading is not None and loading.any():
            # a head whose page loads is not fetched either: its children replace it a round trip later, and the
            # fill rule names levels fill_gap apart, not the level just above them (it was drawn, then replaced:
            # 0.53-0.59x of the drawn bytes at 50 % with --page-levels 4); its ancestors are named from it
            base = base[~np.isin(base, cut[loading])]
        return base

    def _missing_need(self, cut: np.ndarray, loading: np.ndarray | None) -> int:
        """The cut's missing base payloads' bytes, the measure of the fill rule (_ancestors_worth, _root_worth): a
        head whose page is loading counts `lod.reduction` times its own (its children's)."""
        missing = ~self.resident[cut]
        nbytes = self.arrays.base_bytes
        if loading is None:
            return int(nbytes[cut[missing]].sum())
        return int(nbytes[cut[missing & ~loading]].sum()) + \
            int(float(self.manifest.lod.reduction) * nbytes[cut[missing & loading]].sum())

    def _ancestors_worth(self, need: int) -> bool:
        """Whether the cut's ancestors (the root included) are worth fetching coarse to fine: its missing base
        payloads (`need`, _missing_need) exceed fill_min_bytes and, where fill_root_bytes is above fill_min_bytes,
        fill_root_bytes too (between the two: the root, then the cut, _root_worth)."""
        low, high = self.options.fill_min_bytes, self.options.fill_root_bytes
        if low <= 0:
            return True
        return need > max(low, high)

    def _root_worth(self, need: int) -> bool:
        """Whether a cut fetched without its ancestors wants the root first: its missing base payloads (`need`)
        exceed fill_min_bytes (at most, fill_root_bytes: above it _ancestors_worth holds)."""
        return 0 < self.options.fill_min_bytes < need

    def _coarse_to_fine_numpy(self, cut: np.ndarray, gap: int, step: int) -> np.ndarray:
        """_coarse_to_fine's bases in their order, and self._filling set, in numpy (the reference of
        selection_jit.coarse_to_fine_compiled). All cut tiles climb together, a level a step (numpy over the cut: a
        Python walk per tile cost 1-2 ms a frame at 250M). The climb goes past the root into a last, spare row
        (parent -1 is numpy's last row, whose parent is -1): one numpy call a level, no array shrunk as tiles reach
        the root, and as many levels as the deepest climbing tile's (a tile's level is its depth: validate.py)."""
        a = self.arrays
        n = len(self.resident)
        up = self._parents_or_spare(a.parent)
        none = n + len(cut)
        rank = np.full(n + 1, none, np.int64)
        rank[cut] = np.arange(len(cut))
        climb = ~self.resident[cut]
        at, r = cut[climb], np.flatnonzero(climb)
        for d in range(1, int(a.level[at].max()) + 1 if at.size else 0):
            at = up[at]
            if d >= gap and (d - gap) % step == 0:
                np.minimum.at(rank, at, r)
        rank = rank[:n]
        rank[self.root] = -1
        named = np.flatnonzero(rank < none)
        base = named[np.lexsort((rank[named], a.level[named]))]  # (level, rank): no two alike
        self._filling = np.zeros(n, bool)
        self._filling[named] = True
        self._filling[cut] = False
        return base

    def _parents_or_spare(self, parent: np.ndarray) -> np.ndarray:
        """The tree's parents with a spare last row whose parent is itself (-1): kept while the tree's arrays
        are the same (made again after a page is adopted or dropped)."""
        kept = self._up
        if kept is None or kept[0] is not parent:
            kept = self._up = (parent, np.append(parent, -1))
        return kept[1]

    # --- decode -----------------------------------------------------------------------------------------------
    def _collect(self) -> None:
        # payloads by group (decode_batch on threads; decode processes take one payload a job)
        batch: dict[str, list] | None = {} if self.options.decode_batch and not self._use_processes() else None
        for key, entry, data in self.fetcher.done():
            if key[1] == PAGE_GROUP:  # parsed on a decode worker, added at a frame's start (_add_pages)
                if key[0] in self.pages.pending and key[0] not in self._pages_arrived:
                    self._pages_arrived[key[0]] = self._pool.submit(self.pages.read, key[0], data,
                                                                         self._wait_for_loop)
                    self._version += 1  # the wish list leaves it out now
                continue
            if self._have(key) or key in self._ready or key in self._decoding:
                continue
            self._decoding.add(key)
            self._version += 1
            if batch is None:
                self._submit(key, entry, data)
            else:
                batch.setdefault(key[1], []).append((key, entry, data))
        for items in (batch or {}).values():
            self._submit_batch(items)
        while True:
            try:
                item = self._decoded.get_nowait()
            except queue.Empty:
                break
            key = item[0]
            self._decoding.discard(key)
            self._version += 1
            if isinstance(item[1], str):
                self.errors.append(item[1])
                self.failed[key] = item[1]
                reject = getattr(self.fetcher, "reject", None)
                if reject is not None:
                    reject(self.entry(key))
                continue
            ready = item[1]
            if self._frame_box is None and key[1] == "base" and key[0] == self.manifest.root:
                self._root_planes = (ready.planes, self.manifest.tile(key[0]).splats)
            self._ready[key] = ready
            self._ready_bytes += ready.nbytes

    def _blocked(self, key: Key) -> bool:
        """The payload, or a lower band of its tile, did not decode (self.failed): it cannot be drawn."""
        if not self.failed:
            return False
        tile_id, group = key
        band = _GROUP_BAND[group]
        # a page that did not parse blocks no payload: its tile is drawn as a leaf
        return any(k[0] == tile_id and _GROUP_BAND.get(k[1], 4) <= band for k in self.failed)

    @property
    def frame_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The root tile's framing box (root_frame_box), None until its base has decoded; computed once, when first
        asked for (the viewer's F key)."""
        if self._frame_box is None and self._root_planes is not None:
            self._frame_box = root_frame_box(*self._root_planes)
            self._root_planes = None
        return self._frame_box

    @property
    def loop_idle(self) -> threading.Event:
        """Set while the frame loop is not in its CPU work (frame_started / frame_submitted): what background
        threads that run Python wait for (the decode threads here; the fetcher through Fetcher.yield_to)."""
        return self._loop_idle

    def frame_started(self) -> None:
        """The frame loop begins its CPU work (update, uploads, draw submission): decoding and fetching wait."""
        self._loop_idle.clear()

    def frame_submitted(self) -> None:
        """The frame loop waits for the GPU or the display now: decoding and fetching may run."""
        self._loop_idle.set()

    def _decode(self, key: Key, entry: PayloadEntry, data: VerifiedPayload | bytes) -> None:
        # Between every step of the payload, not only before it: a decode running into the frame loop's CPU work
        # takes the interpreter lock from it at each of its numpy calls (a payload has hundreds), and every hand-over
        # cost the loop about 0.1 ms on the GPU machine: 10-20 ms in the frames that upload.
        self._take_turn()
        try:
            self._wait_for_loop()
            result = decode_job(*self._job_args(key, entry, data), between=self._wait_for_loop)
        except Exception as exc:  # not the payload's fault (decode_job says those): see _internal_error
            result = _internal_error(key, exc)
        finally:
            self._end_turn()
        self._decoded.put((key, self._finish(key, result)))

    def _decode_many(self, items: list[tuple[Key, PayloadEntry, VerifiedPayload | bytes]]) -> None:
        """Payloads of one group decoded as one job (decode_batch_job), results handed over as _decode's."""
        self._take_turn()
        try:
            self._wait_for_loop()
            results = decode_batch_job([self._job_args(*item) for item in items], between=self._wait_for_loop)
        except Exception as exc:  # as _decode's
            results = [_internal_error(item[0], exc) for item in items]
        finally:
            self._end_turn()
        for (key, _, _), result in zip(items, results, strict=True):
            self._decoded.put((key, self._finish(key, result)))

    def _take_turn(self) -> None:
        """Wait until fewer decode jobs run than the frame allows now (decode_workers_moving while the camera
        moves)."""
        with self._decode_turns:
            while self._decode_running >= self._decode_limit and not self._closing:
                self._decode_turns.wait(DECODE_WAIT_S)
            self._decode_running += 1

    def _end_turn(self) -> None:
        with self._decode_turns:
            self._decode_running -= 1
            self._decode_turns.notify()

    def _set_moving(self, moving: bool) -> None:
        """Fewer decode threads while the camera moves, all of them while it rests."""
        self._moving = moving
        few = self.options.decode_workers_moving
        limit = few if moving and 0 < few < self.options.decode_workers else self.options.decode_workers
        self.moving_frames += moving
        if limit != self._decode_limit:
            with self._decode_turns:
                self._decode_limit = limit
                self._decode_turns.notify_all()

    def _wait_for_loop(self) -> None:
        self._loop_idle.wait(DECODE_WAIT_S)

    def _job_args(self, key: Key, entry: PayloadEntry, data: VerifiedPayload | bytes) -> tuple:
        tile_id, group = key
        codebook_tile = self.codebook and tile_id is not None
        splats = self.manifest.tile(tile_id).splats if tile_id is not None else 0
        entries = self.manifest.sh_codebook.entries if codebook_tile else 0
        where = self.fetcher.where(entry) if hasattr(self.fetcher, "where") else f"{self.location}/{entry.file}"
        return (data, entry, group, where, codebook_tile, splats, entries,
                self.with_mirror and group == "base" and tile_id is not None,
                self.manifest.scene_palettes if group == "base" else None)

    def _finish(self, key: Key, result: tuple | str) -> _Ready | str:
        if isinstance(result, str):
            return result
        planes, extra = result
        return _Ready(key, planes, extra, planes_nbytes(planes))

    def _use_processes(self) -> bool:
        procs = self._processes
        return procs is not None and self._processes_ready.done() and not self._processes_ready.exception()

    def _submit_batch(self, items: list[tuple[Key, PayloadEntry, VerifiedPayload | bytes]]) -> None:
        """One group's payloads of a collect, in the collect's order (the wish list's): consecutive payloads
        together up to decode_batch_splats splats a job, each job a decode_payloads call."""
        cap = self.options.decode_batch_splats
        shares: list[list] = []
        held = 0
        for item in items:
            tile_id = item[0][0]
            splats = self.manifest.tile(tile_id).splats if tile_id is not None else cap
            if not shares or held + splats > cap:
                shares.append([])
                held = 0
            shares[-1].append(item)
            held += splats
        for share in shares:
            self.decode_jobs += 1
            self.decode_job_payloads += len(share)
            if len(share) == 1:
                self._pool.submit(self._decode, *share[0])
            else:
                self._pool.submit(self._decode_many, share)

    def _submit(self, key: Key, entry: PayloadEntry, data: VerifiedPayload | bytes) -> None:
        procs = self._processes
        if self._use_processes():
            future = procs.submit(decode_job, *self._job_args(key, entry, data))

            def done(f, key=key):
                try:
                    item = self._finish(key, f.result())
                except Exception as exc:  # a worker process died: decode here instead
                    if not self._closing and not isinstance(exc, CancelledError):
                        self._pool.submit(self._decode, key, entry, data)
                    return
                self.process_decodes += 1
                self._decoded.put((key, item))
            future.add_done_callback(done)
        else:
            self.decode_jobs += 1
            self.decode_job_payloads += 1
            self._pool.submit(self._decode, key, entry, data)

    # --- residency --------------------------------------------------------------------------------------------
    def _protected(self, sel: Selection) -> np.ndarray:
        """Tiles that must not be evicted now: the root, the wanted cut and everything drawn this frame."""
        keep = np.zeros(len(self.resident), bool)
        keep[self.root] = True
        keep[sel.cut_at] = True
        keep[self.last_drawn >= self.frame - 1] = True
        return keep

    def _make_room(self, slots: int, sel: Selection) -> bool:
        """Evict until `slots` are free: first tiles nobody wants (least recently drawn first), then ancestors
        being filled in that are not drawn (the finest first), never the cut or what is drawn."""
        free = self.residency.free_slots
        if free >= slots:
            return True
        keep = self._protected(sel)
        spare = np.nonzero(self.resident & ~keep & ~self._filling)[0]
        filling = np.nonzero(self.resident & ~keep & self._filling)[0]
        order = [spare[np.argsort(self.last_drawn[spare], kind="stable")],
                 filling[np.argsort(-self.arrays.level[filling], kind="stable")]]
        for i in np.concatenate(order):
            self._evict(int(i))
            free = self.residency.free_slots
            if free >= slots:
                return True
        return False

    def _evict(self, i: int) -> None:
        self.evictions += 1
        self._version += 1
        self.residency.leave(int(self.ids[i]))
        self.resident[i] = False
        self.bands[i] = 0

    def _upload(self, missing: list[Key], keys: list[Key], sel: Selection) -> tuple[int, list[str]]:
        budget = self.options.upload_bytes_per_frame
        done = 0
        events: list[str] = []
        idle = self._upload_idle
        if idle is not None and idle[0] == self._version and idle[1] is keys:
            return 0, events  # nothing ready is wanted, and neither the payloads nor the wish list changed since
        # The wish list's ranks, made again only with a new list: a still view with prefetched payloads waiting in
        # `_ready` comes here every frame, and the ranks of a 6M-splat cut (hundreds of keys) cost more than the rest
        # of its frame's bookkeeping together.
        if self._order_of is None or self._order_of[0] is not keys:
            self._order_of = (keys, dict(zip(keys, range(len(keys)), strict=True)))
        order = self._order_of[1]
        wanted_ready = False
        for key in sorted(self._ready, key=lambda k: order.get(k, len(order))):
            if done >= budget and done > 0:
                break
            if key not in order:
                continue  # prefetched, not wanted yet: stays ready
            wanted_ready = True
            r = self._ready[key]
            tile_id, group = key
            if tile_id is None:
                band = band_of(group)
                if band - 1 not in self.codebook_bands and band > 1:
                    continue  # codebook bands join in order
                self.residency.set_codebook_band(band, r.planes[group])
                self.codebook_bands.add(band)
            else:
                i = self.manifest.index_of[tile_id]
                if group == "base":
                    if self.resident[i]:
                        pass
                    elif not self._make_room(int(self.slots_needed[i]), sel):
                        continue  # no room now (everything resident is wanted or drawn): try next frame
                    else:
                        self.residency.join(tile_id, TileData(self.manifest.tile(tile_id).splats, r.planes, r.extra))
                        self.resident[i] = True
                        self.bands[i] = 0
                        events.append(f"join {tile_id}")
                else:
                    band = band_of(group)
                    if not self.resident[i] or self.bands[i] != band - 1:
                        continue  # bands join in order, after the base
                    self.residency.add_band(tile_id, band, r.planes)
                    self.bands[i] = band
            del self._ready[key]
            self._version += 1
            self._ready_bytes -= r.nbytes
            done += r.nbytes
        if self.codebook:
            self._codebook_tile_bands(sel)
        self._trim_ready(order)
        self.uploaded_bytes_total += done
        # Only prefetched payloads wait (a still, converged view): the next frames skip this until one of them is
        # wanted or another arrives (each changes the version or the list). Not after a payload that found no room:
        # room depends on what was drawn lately, and is tried again every frame.
        self._upload_idle = None if wanted_ready else (self._version, keys)
        return done, events

    def _codebook_tile_bands(self, sel: Selection) -> None:
        """With an SH codebook a tile's bands 2 and 3 need no payload of its own: once its index (band 1) and the
        codebook's band are resident, the tile gains the band."""
        cut, bands = self._bands_wanted
        for i, want in zip(cut.tolist(), bands.tolist(), strict=True):
            tile_id = int(self.ids[i])
            while self.resident[i] and 1 <= self.bands[i] < want and self.bands[i] + 1 in self.codebook_bands:
                self.residency.add_band(tile_id, int(self.bands[i]) + 1, {})
                self.bands[i] += 1
                self._version += 1

    def _trim_ready(self, order: dict) -> None:
        if self._ready_bytes <= self.options.ready_bytes:
            return
        for key in sorted(self._ready, key=lambda k: -order.get(k, len(order) + 1)):
            if self._ready_bytes <= self.options.ready_bytes:
                break
            self._ready_bytes -= self._ready.pop(key).nbytes
            self._version += 1

    def take_arrived(self) -> int:
        """Hand the payloads the fetcher finished to the decode threads now, outside a frame (what each update's
        collect does first); returns how many decodes run. A session calls it while it builds the renderer: the
        root's base, asked for with the manifest, then decodes before the first frame instead of after its update
        (client.md 6)."""
        self._collect()
        return len(self._decoding)

    def wait(self, timeout_s: float = 0.05) -> None:
        """Block briefly until a decode or a page's parse finishes (loops without a display use it instead of
        spinning)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            decoding = self._decoding and self._decoded.empty()
            parsing = self._pages_arrived and not any(f.done() for f in self._pages_arrived.values())
            if not (decoding or parsing):
                return
            time.sleep(0.002)

    def close(self) -> None:
        self._closing = True
        if self._processes is not None:
            self._processes.shutdown(wait=True, cancel_futures=True)
        self._pool.shutdown(wait=True, cancel_futures=True)
