"""Manifest pages (format.md 6.1): root manifest bytes, page sizes and fetches, and the client's selection time, on
trees of the encoder's exact shape (lod.TreeShape) for 1M to 250M splats, without encoding them.

A tree of N splats is built as the encoder shapes it (levels `reduction` apart, kd depths of TreeShape.of) over a
flat city-like region (kd cells split alternately along x and y); every tile's payload entries are those of a real
encoded tile (an SH0 scene by default: the 250M run is SH0), renamed per tile, so a tile costs the manifest what an
encoded one does. Then, for each page size (levels per page) k: the root manifest's bytes (what a client reads
before its first frame), the pages and their bytes; and, for a ground-level view under a splat budget, the pages
the client reads until its cut stops (pages.PagedTree, as the engine reads them), the tiles it then holds, and the
median time of one frame's view numbers + selection over the tiles held against over the whole tree.

    PYTHONPATH=. python bench/bench_pages.py [--splats 1e6,6e6,60e6,250e6] [--levels 4,5,6,8] [--sh-degree 0]
    PYTHONPATH=. python bench/bench_pages.py --repage SCENE OUT   # OUT: SCENE paged (payloads hard-linked), to
                                                                  # stream both (bench_first_frame.py, bench_stream.py)
    PYTHONPATH=. python bench/bench_pages.py --first-frame SCENE [SCENE ...]  # served on loopback (`serve`): the
        manifest bytes and seconds from opening the stream to the first frame that draws the root (engine, fetcher
        and HTTP as `view` runs them, no GL: a pool that counts slots), median of --runs
    PYTHONPATH=. python bench/bench_pages.py --engine --splats 6e6,60e6,250e6 [--frames 300] [--profile]
            [--numpy-selection | --no-wait] [--parts-json F_N.json] [--busy-threads 1] [--max-tree-tiles 8192]
    PYTHONPATH=. python bench/bench_pages.py --jit-cost [--runs 7]   # the compiled selection's cost before its first
        # use: numba's import, then its kernels compiled (the first run, an empty cache) or loaded (the others)
        # a StreamEngine over the paged tree along a street-level path (pages and payloads arrive --per-frame a
        # frame, payloads not decoded, a pool that counts): per-frame update times, median, p99, max; the compiled
        # selection (numba, the `fast` extra) unless --numpy-selection; each part of the update per frame (thread
        # CPU and wall: the view, the cut, the pages wanted, bands, keys, wish list, page adoption, draw set), and
        # a digest of every frame's cut and draw set and of the fetcher's requests (equal digests: the same frames)
"""
from __future__ import annotations

import argparse
import cProfile
import functools
import gc
import hashlib
import json
import math
import os
import pstats
import random
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
from dataclasses import replace
from types import SimpleNamespace

try:
    import resource  # the frame loop's voluntary context switches (Unix only)
except ImportError:  # pragma: no cover (Windows)
    resource = None

import numpy as np

from client_gl.stream import engine as engine_module
from client_gl.stream.engine import COMPILED_SELECTION, StreamEngine, StreamOptions, _Ready
from client_gl.stream.fetch import Fetcher
from client_gl.stream.pages import PagedTree
from client_gl.stream.selection import SelectionOptions, select, view_numbers
from client_gl.stream.sources import HttpSource
from splatstream.camera import Camera
from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.format.manifest import (
    Box,
    LodInfo,
    Manifest,
    PayloadEntry,
    TileEntry,
    pack_manifest,
    parse_manifest,
    read_page,
    split_pages,
    tile_rows,
)
from splatstream.format.names import DATA_DIR, MANIFEST_NAME, payload_name
from splatstream.format.texformats import FORMATS, blob_size
from splatstream.format.transport import FIELDS1, content_bounds
from splatstream.gaussians import Gaussians
from splatstream.lod import TreeShape
from splatstream.store import load_manifest, read_manifest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_stream import serve_scene  # noqa: E402 (bench/ is on the path: scripts run from it)


def template(sh_degree: int) -> Manifest:
    """A real encoded scene (the medium preset) whose first leaf's payload entries every synthetic tile copies."""
    rng = np.random.default_rng(0)
    n = 20000
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                  np.full((n, 3), -3.0, np.float32), np.zeros(n, np.float32), rng.random((n, 3)).astype(np.float32),
                  rng.normal(0, 0.1, (n, (sh_degree + 1) ** 2 - 1, 3)).astype(np.float32))
    return read_manifest(encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=16384)))


@functools.lru_cache(maxsize=256)
def fitted(p: PayloadEntry, chunks: int, texture: tuple[int, int]) -> PayloadEntry:
    """The template's payload entry made valid for a tile of `chunks` and `texture` (format.md 5, Validation; 1.8
    checks a tile table whole when it is parsed): texels of the tile's texture, stored sizes scaled by its texels
    (fields1 within its bounds), ranges of its chunks; offsets at 16-byte alignment, file bytes scaled too."""
    sections, end = [], 0
    for s in p.sections:
        if s.kind == "texels":
            w, h = texture
            gpu = blob_size(FORMATS[s.format], w, h, s.layers)
            if s.filter == FIELDS1:
                lo, hi = content_bounds(s.format, w, h, s.layers)
                size = min(hi, max(lo, round(s.size * w * h / (s.width * s.height))))
            else:
                size = gpu
            s = replace(s, width=w, height=h, size=size)
        elif s.shape and not s.name.endswith(".palette"):
            shape = (chunks, *s.shape[1:])
            s = replace(s, shape=shape, size=(4 if s.dtype == "f32" else 2) * math.prod(shape))
        end += (-end) % 16
        sections.append(replace(s, offset=end))
        end += s.size
    return replace(p, sections=tuple(sections), raw_bytes=end, bytes=max(1, round(p.bytes * end / p.raw_bytes)),
                   gpu_bytes=sum(s.gpu_size for s in sections))


def synthetic_tree(splats: int, base: Manifest, seed: int = 0) -> Manifest:
    groups: dict[str, PayloadEntry] = dict(base.leaves[0].groups)
    shape = TreeShape.of(splats, 16384, 2.0)
    kd, levels = shape.kd_depths, len(shape.kd_depths)
    side = 2000.0 * math.sqrt(splats / 250e6)  # a city of 250M splats about 2 km across
    rnd = random.Random(seed)
    tiles: list[TileEntry] = []
    level_splats = [splats / 2.0 ** (levels - 1 - lv) for lv in range(levels)]
    for lv in range(levels):
        d = kd[lv]
        nx, ny = 2 ** ((d + 1) // 2), 2 ** (d // 2)  # x split first
        per_tile = max(1, round(level_splats[lv] / 2 ** d))
        chunks = -(-per_tile // 256)
        w = math.ceil(math.sqrt(chunks))
        texture = (16 * w, 16 * -(-chunks // w))
        err = 0.0 if lv == levels - 1 else side / nx * 0.02 * 2 ** ((levels - 2 - lv) / 2)
        child_shift = kd[lv + 1] - d if lv + 1 < levels else None
        for j in range(2 ** d):
            # cell j of depth d: bits alternate x, y from the top
            x = y = 0
            for b in range(d):
                bit = (j >> (d - 1 - b)) & 1
                if b % 2 == 0:
                    x = 2 * x + bit
                else:
                    y = 2 * y + bit
            lo = (x * side / nx, y * side / ny, 0.0)
            hi = ((x + 1) * side / nx, (y + 1) * side / ny, 30.0)
            center = tuple((a + b) / 2 for a, b in zip(lo, hi, strict=True))
            radius = math.dist(lo, hi) / 2
            tid = shape.first_id[lv] + j
            children = () if child_shift is None else tuple(
                shape.first_id[lv + 1] + (j << child_shift) + c for c in range(2 ** child_shift))
            own = {}
            for name, p in groups.items():
                sha = f"{rnd.getrandbits(256):064x}"
                own[name] = replace(fitted(p, chunks, texture), file=payload_name(sha), sha256=sha)
            tiles.append(TileEntry(tid, lv, children, per_tile, chunks, texture, Box(lo, hi), center, radius, err,
                                   own))
    leaf_sum = sum(t.splats for t in tiles if not t.children)
    return replace(base, splats=leaf_sum, leaf_splats=leaf_sum, tiles=tuple(tiles), root=0,
                   lod=LodInfo(True, 16384, 2.0, "replace"),
                   bounds=Box((0.0, 0.0, 0.0), (side, side, 30.0)), extent_bounds=tiles[0].box)


def ground_camera(m: Manifest) -> Camera:
    side = m.bounds.max[0]
    return Camera((side * 0.3, side * 0.25, 20.0), (side * 0.55, side * 0.6, 5.0), (0.0, 0.0, 1.0), 60.0, 1920,
                  1080, near=0.1)


def select_once(m: Manifest, cam: Camera, opts: SelectionOptions):
    a = m.arrays
    cost = np.array([t.chunks for t in m.tiles], np.float64)
    view = view_numbers(a, cam, opts)
    return view, select(a, view, cost, m.index_of[m.root], opts, frozenset(), 2.0)


def timed(m: Manifest, cam: Camera, opts: SelectionOptions, reps: int = 15) -> float:
    _ = m.arrays  # built once per tree, as the engine does (a page arrival rebuilds it)
    select_once(m, cam, opts)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        select_once(m, cam, opts)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def repage(src: str, dst: str, k: int) -> None:
    """A copy of scene `src` written paged (what `encode --page-tiles 1 --page-levels k` writes), its payload files
    hard-linked: the same scene, so paged and unpaged stream the same bytes but for the manifest."""
    whole = load_manifest(src)
    paged = split_pages(whole, k)
    os.makedirs(os.path.join(dst, DATA_DIR))
    for name in os.listdir(os.path.join(src, DATA_DIR)):
        os.link(os.path.join(src, DATA_DIR, name), os.path.join(dst, DATA_DIR, name))
    for ref, raw in paged.pages:
        with open(os.path.join(dst, ref.file), "wb") as f:
            f.write(raw)
    tmp = os.path.join(dst, ".manifest.tmp")
    with open(tmp, "wb") as f:
        f.write(pack_manifest(paged.root))
    os.replace(tmp, os.path.join(dst, MANIFEST_NAME))
    print(f"{dst}: {len(paged.pages)} pages ({paged.root.paged.page_bytes / 1e3:.1f} KB), root manifest "
          f"{os.path.getsize(os.path.join(dst, MANIFEST_NAME)) / 1e3:.1f} KB (unpaged: "
          f"{os.path.getsize(os.path.join(src, MANIFEST_NAME)) / 1e3:.1f} KB)")


class _Slots:
    """A GPU pool that only counts (the engine's Residency; the GL pool's time is the same paged or not)."""

    capacity_slots = free_slots = 1 << 20

    def join(self, tile_id, tile):
        return None

    def add_band(self, tile_id, band, planes):
        return None

    def leave(self, tile_id):
        return None

    def set_codebook_band(self, band, plane):
        return None


class _PathFetcher:
    """A fetcher over a paged synthetic tree (bench `--engine`): pages are the real page bytes; payloads arrive as
    empty bytes (`_NoDecodeEngine` does not decode them). At most `per_frame` items a frame, in the wish list's
    order, as a link that delivers a few payloads per frame would."""

    def __init__(self, root: Manifest, files: dict[str, bytes], per_frame: int):
        self._root, self._files, self._per_frame = root, files, per_frame
        self._wanted: list = []
        # every wish list handed over (priorities, keys, entries, in order), hashed after the path (out of the
        # frames' time): the same digest before and after a change of the engine's bookkeeping, the same requests
        self.lists: list = []
        self.read: dict[str, tuple[int, int]] = {}  # group -> (files, bytes) handed over

    def manifest(self) -> Manifest:
        return self._root

    def want(self, requests) -> None:
        self._wanted = [(key, entry) for _, key, entry in requests]
        self.lists.append(requests)

    def requests_digest(self) -> str:
        h = hashlib.sha256()
        for requests in self.lists:
            h.update(repr([(p, key, entry.file, entry.bytes) for p, key, entry in requests]).encode() + b"|")
        return h.hexdigest()[:16]

    def done(self):
        out, self._wanted = self._wanted[:self._per_frame], self._wanted[self._per_frame:]
        for key, entry in out:  # what the path read: pages, and payloads by group (issue 31)
            n, nbytes = self.read.get(key[1], (0, 0))
            self.read[key[1]] = (n + 1, nbytes + int(entry.bytes))
        return [(key, entry, self._files.get(entry.file, b"")) for key, entry in out]

    def stats(self):
        return SimpleNamespace(in_flight=0, queued=len(self._wanted))


class _NoDecodeEngine(StreamEngine):
    """The engine with payloads 'decoded' at once into nothing: the bench times the frame loop's bookkeeping."""

    whole: Manifest | None = None  # the synthetic tree its payload entries are read from

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # the root's framing box is read from its decoded positions, which this engine does not make: a box set
        # now (the engine then reads none; without it the first collect of the root failed, KeyError 'position')
        self._frame_box = (np.zeros(3), np.ones(3))

    def _submit(self, key, entry, data) -> None:
        self._decoded.put((key, _Ready(key, {}, None, int(entry.bytes))))

    def _submit_batch(self, items) -> None:  # a collect's batch (StreamOptions.decode_batch): the same, a payload each
        for item in items:
            self._submit(*item)

    def entry(self, key):
        # The synthetic tiles' payload entries (one real tile's, copied to tiles of other sizes) do not pass the
        # lazy check of a parsed page (section shapes follow a tile's splats): they are taken from the whole tree.
        # The pages themselves are parsed for real (PagedTree.read), their entries held unchecked, as a client's.
        # Kept once looked up, as StreamEngine.entry keeps them (the product's cost a key is a dict look-up).
        tile_id, group = key
        if tile_id is None or self.whole is None:
            return super().entry(key)
        entry = self._entries.get(key)
        if entry is None:
            entry = self._entries[key] = self.whole.tile(tile_id).groups[group]
        return entry


def tree_memory_mb(held: PagedTree, paged) -> float:
    """MB of Python memory (tracemalloc) of a PagedTree holding the same pages as `held`: its tiles, as parsed from
    the page bytes, and the arrays the selection runs over (what the client keeps for the tree)."""
    files = {ref.file: raw for ref, raw in paged.pages}
    heads = held.held_pages()
    level = {t.id: t.level for t in held.manifest.tiles}
    gc.collect()
    tracemalloc.start()
    t0 = tracemalloc.get_traced_memory()[0]
    tree = PagedTree(paged.root)
    for head in sorted(heads, key=lambda h: level[h]):
        tree.add_page(head, files[tree.entry(head).file])
    _ = tree.manifest.arrays.box_corners, tree.manifest.arrays.has_children, tree.manifest.arrays.splats_list
    used = tracemalloc.get_traced_memory()[0] - t0
    tracemalloc.stop()
    assert len(tree.manifest.tiles) == len(held.manifest.tiles)
    return used / 1e6


def street_camera(frame: int, frames: int, side: float) -> Camera:
    """The --engine path's camera at `frame` of `frames`: across the city at street level, turning as it goes."""
    s = frame / max(1, frames - 1)
    eye = np.array([0.2 + 0.6 * s, 0.25 + 0.5 * s, 0.01]) * [side, side, 2000.0]
    target = eye + [side * 0.3, side * 0.3 * math.cos(3 * s), -15.0]
    return Camera(tuple(eye), tuple(target), (0.0, 0.0, 1.0), 60.0, 1920, 1080, near=0.1)


def engine_path(whole: Manifest, k: int, frames: int, max_splats: int, per_frame: int, profile: bool,
                compiled: bool = True, wait: bool = True, parts_json: str | None = None,
                busy_threads: int = 0, max_tree_tiles: int | None = None,
                busy_pattern: tuple[float, float] | None = None,
                select_switch_interval: float | None = None) -> None:
    """A StreamEngine over the paged tree along a camera flying across the city at street level: per-frame
    update times (median, p99, max) and, with --profile, where they go. `compiled`: the compiled selection
    (selection_jit, waited for before the path, so every frame near the cut uses it), else the numpy path.
    `max_tree_tiles`: the engine's bound on the tree held (StreamOptions' default if None); a bound below the tiles
    the path holds makes it drop pages (its eviction timed as "page eviction"). `busy_pattern` (hold, rest ms): the
    busy threads hold the interpreter lock for `hold` ms of Python, then rest `rest` ms without it (a decode
    thread's Python around its nogil kernels), instead of holding it always."""
    paged = split_pages(whole, k)
    files = {ref.file: raw for ref, raw in paged.pages}
    bound = {} if max_tree_tiles is None else {"max_tree_tiles": max_tree_tiles}
    if select_switch_interval is not None:  # 0: untouched; None: the option's default
        bound["select_switch_interval"] = select_switch_interval or None
    fetcher = _PathFetcher(paged.root, files, per_frame)
    engine = _NoDecodeEngine(fetcher, _Slots(),
                             StreamOptions(SelectionOptions(max_splats=max_splats), upload_bytes_per_frame=1 << 40,
                                           compiled_selection=compiled, **bound))
    if compiled and wait:
        t0 = time.perf_counter()
        if COMPILED_SELECTION.wait() is None:
            raise SystemExit(f"the compiled selection is not available: {COMPILED_SELECTION.error!r}")
        print(f"compiled selection ready after {time.perf_counter() - t0:.2f} s (numba import, compilation or cache)")
    engine.whole = whole
    _ = whole.tile_by_id  # the whole tree's index, built once here, not in the first frame that looks an entry up
    side = whole.bounds.max[0]
    prof = cProfile.Profile(time.thread_time) if profile else None  # CPU: the VM is shared
    times, cpu = [], []
    switches: list[tuple[int, int]] = []  # the update's (waits, preemptions): voluntary and involuntary switches
    adopted: list[bool] = []  # frames that adopted (or dropped) pages
    ready: list[bool] = []  # frames after which the compiled selection was ready
    # The bench's whole tree is no client's: out of the collector's passes, whose full passes over it took 120-150 ms
    # (the spikes of a first version of this bench). The client's own objects (the root manifest, the pages it
    # parses: real page bytes through PagedTree.read, as the engine's decode workers parse them) are collected as
    # usual, and the full passes over them are reported.
    gc.collect()
    gc.freeze()
    started: dict[int, float] = {}
    full_passes: list[float] = []
    looked: list[int] = []
    wanted_s: list[float] = []
    wanted = engine.wanted

    def timed_wanted(cam):
        t0 = time.thread_time()
        out = wanted(cam)
        wanted_s.append(time.thread_time() - t0)
        looked.append(getattr(out[0], "looked_at", len(engine.manifest.tiles)))
        return out
    engine.wanted = timed_wanted
    select_s: list[float] = []  # the selection's function alone (select_near, compiled or numpy; select)

    def timing(fn):
        def timed_select(*args, **kw):
            t0 = time.thread_time()
            out = fn(*args, **kw)
            select_s.append(time.thread_time() - t0)
            return out
        return timed_select
    patched = {name: getattr(engine_module, name) for name in ("select", "select_near")}
    for name, fn in patched.items():
        setattr(engine_module, name, timing(fn))
    compiled_fn = COMPILED_SELECTION._fn
    if compiled_fn is not None:
        COMPILED_SELECTION._fn = timing(compiled_fn)

    # Per frame, each part's thread CPU and wall (ms, summed over its calls in the frame): the selection's parts
    # (the view's numbers, the cut, the pages wanted, the SH bands, the keys: the rest of `wanted`), the wish list,
    # the page adoption and the draw set. Module functions are wrapped where the engine looks them up.
    parts_now: dict[str, list[float]] = {}
    parts: list[dict[str, list[float]]] = []
    held_tiles: list[int] = []
    # every frame's cut (tile ids, in the cut's order) and draw set, hashed: the same digests before and after a
    # change of the selection's code mean the same frames
    cuts, draws = hashlib.sha256(), hashlib.sha256()

    def part(label, fn):
        def timed_part(*args, **kw):
            t0, c0, (v0, i0) = time.perf_counter(), time.thread_time(), _context_switches()
            try:
                return fn(*args, **kw)
            finally:
                acc = parts_now.setdefault(label, [0.0, 0.0, 0.0, 0.0])
                v1, i1 = _context_switches()
                acc[0] += (time.thread_time() - c0) * 1e3
                acc[1] += (time.perf_counter() - t0) * 1e3
                acc[2] += v1 - v0
                acc[3] += i1 - i0
        return timed_part
    for label, name in (("view", "view_numbers"), ("view", "PartialView"), ("bands", "wanted_bands_at"),
                        ("draw set", "draw_set")):
        fn = getattr(engine_module, name)
        patched.setdefault(name, fn)
        setattr(engine_module, name, part(label, getattr(engine_module, name)))
    for name in ("select", "select_near"):  # already timed into select_s
        setattr(engine_module, name, part("cut", getattr(engine_module, name)))
    if COMPILED_SELECTION._fn is not None:
        COMPILED_SELECTION._fn = part("cut", COMPILED_SELECTION._fn)
    compiled_draw = COMPILED_SELECTION._draw  # the compiled draw set (ready with the compiled selection)
    if compiled_draw is not None:
        COMPILED_SELECTION._draw = part("draw set", compiled_draw)
    if engine.pages is not None:
        engine.pages.wanted_pages = part("pages wanted", engine.pages.wanted_pages)
        engine.pages.evict = part("page eviction: evict", engine.pages.evict)  # the tree's renumbering
    for label, name in (("wanted", "wanted"), ("wish list", "_tell_fetcher"), ("page adoption", "_add_pages"),
                        ("page eviction", "_evict_pages"), ("page eviction: choice", "_pages_to_drop"),
                        ("page eviction: forget", "_forget"),
                        ("collect", "_collect"), ("upload", "_upload"),
                        ("wish list: coarse to fine", "_coarse_to_fine"), ("wish list: requests", "_requests")):
        if hasattr(engine, name):  # _requests: the wish list's requests built apart (branch wishlist)
            setattr(engine, name, part(label, getattr(engine, name)))

    def on_gc(phase: str, info: dict) -> None:
        if info["generation"] == 2:
            if phase == "start":
                started[2] = time.perf_counter()
            else:
                full_passes.append(time.perf_counter() - started.pop(2, time.perf_counter()))
    gc.callbacks.append(on_gc)
    stop = threading.Event()

    holds: list[tuple[int, float]] = []  # each busy thread's holds done and its CPU: what an interval costs them

    def busy() -> None:  # Python that holds the interpreter lock until the switch interval takes it (a page parse)
        if busy_pattern is not None:
            hold, rest = busy_pattern[0] / 1e3, busy_pattern[1] / 1e3
            clock = time.perf_counter
            done, c0 = 0, time.thread_time()
            while not stop.is_set():
                until = clock() + hold
                while clock() < until:
                    pass
                time.sleep(rest)  # the lock released, as a nogil kernel or zstd releases it
                done += 1
            holds.append((done, time.thread_time() - c0))
            return
        while not stop.is_set():
            sum(i * i for i in range(2000))
    others = [threading.Thread(target=busy, daemon=True) for _ in range(busy_threads)]
    for th in others:
        th.start()
    path_start = time.perf_counter()
    try:
        for f in range(frames):
            cam = street_camera(f, frames, side)
            # the page parses finish before the frame (a real client's finish between frames)
            for fut in list(engine._pages_arrived.values()):
                fut.result()
            if prof is not None:
                prof.enable()
            held = (engine.pages.pages_read, engine.pages.evicted)
            t0, c0, (v0, i0) = time.perf_counter(), time.thread_time(), _context_switches()
            u = engine.update(cam)
            times.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
            v1, i1 = _context_switches()
            switches.append((v1 - v0, i1 - i0))
            parts.append(parts_now)
            ids = engine.ids
            cuts.update(np.array([int(ids[i]) for i in u.selection.cut], np.int64).tobytes() + b"|")
            draws.update(np.array(u.draw, np.int64).tobytes() + b"|")
            held_tiles.append(len(engine.manifest.tiles))
            parts_now = {}
            adopted.append(held != (engine.pages.pages_read, engine.pages.evicted))
            ready.append(COMPILED_SELECTION._fn is not None)
            if prof is not None:
                prof.disable()
    finally:
        path_s = time.perf_counter() - path_start
        stop.set()
        for th in others:
            th.join()
        gc.callbacks.remove(on_gc)
        gc.unfreeze()
        engine.close()
        for name, fn in patched.items():
            setattr(engine_module, name, fn)
        if compiled_fn is not None:
            COMPILED_SELECTION._fn = compiled_fn
        if compiled_draw is not None:
            COMPILED_SELECTION._draw = compiled_draw
    ts, cs = np.array(times) * 1e3, np.array(cpu) * 1e3
    ws = np.array(wanted_s) * 1e3
    tree_mb = tree_memory_mb(engine.pages, paged)
    print(f"{whole.splats / 1e6:.0f}M engine path ({frames} frames, {per_frame} payloads/pages a frame, "
          f"{'compiled' if compiled else 'numpy'} selection): update "
          f"median {np.median(ts):.2f} ms, p99 {np.percentile(ts, 99):.2f} ms, max {ts.max():.1f} ms (its thread's "
          f"CPU: median {np.median(cs):.2f}, p99 {np.percentile(cs, 99):.2f}, max {cs.max():.1f} ms); selection's CPU "
          f"(wanted: view numbers, select, bands, keys) median {np.median(ws):.2f} ms, p99 "
          f"{np.percentile(ws, 99):.2f} ms over {len(ws)} selections, of which the cut's function (select_near or "
          f"select) median {np.median(select_s) * 1e3:.2f} ms, p99 {np.percentile(select_s, 99) * 1e3:.2f} ms; "
          f"tiles looked at a selection median "
          f"{int(np.median(looked)) if looked else 0}, max {max(looked, default=0)}; tiles held "
          f"{len(engine.manifest.tiles)}, pages read {engine.pages.pages_read}, evicted {engine.pages.evicted}; "
          f"{len(full_passes)} full collections ({sum(full_passes) * 1e3:.1f} ms in all, longest "
          f"{max(full_passes, default=0) * 1e3:.1f} ms); tree held {tree_mb:.1f} MB")
    ad = np.array(adopted, bool)
    for name, part in (("frames adopting or dropping pages", cs[ad]), ("other frames", cs[~ad])):
        if part.size:
            print(f"  {name}: {part.size}, update CPU median {np.median(part):.2f}, p99 "
                  f"{np.percentile(part, 99):.2f}, max {part.max():.1f} ms")
    rd = np.array(ready, bool)
    if compiled and not wait:  # the frames while the kernels were loaded on the worker thread, and after
        for name, part in (("frames before the compiled selection was ready", ~rd), ("frames after", rd)):
            if part.any():
                print(f"  {name}: {part.sum()}, update wall median {np.median(ts[part]):.2f}, max "
                      f"{ts[part].max():.1f} ms; CPU median {np.median(cs[part]):.2f}, max {cs[part].max():.1f} ms; "
                      f"{sum(times[i] for i in np.flatnonzero(part)):.2f} s in all")
    print_parts(parts, cs, ts)
    sw = np.array(switches, np.float64).reshape(-1, 2)
    print(f"  the whole update's waits a frame (voluntary context switches): mean {sw[:, 0].mean():.2f}, p99 "
          f"{np.percentile(sw[:, 0], 99):.0f}, frames with one {int((sw[:, 0] > 0).sum())}; preemptions a frame mean "
          f"{sw[:, 1].mean():.2f}")
    if holds:
        done, busy_cpu = sum(h[0] for h in holds), sum(h[1] for h in holds)
        print(f"  busy threads: {done} holds done in {path_s:.2f} s ({done / path_s:.0f} a second), their CPU "
              f"{busy_cpu:.2f} s; switch interval during the selection: "
              f"{engine.options.select_switch_interval}")
    # the engine's per-key maps after the path: bounded by the tiles held when pages are dropped (issue 38)
    print(f"  per-key maps after the path: entries {len(engine._entries)}, page frames {len(engine._page_frame)}, "
          f"failed {len(engine.failed)}, ready {len(engine._ready)}, decoding {len(engine._decoding)} "
          f"({len(engine.manifest.tiles)} tiles held, {len(engine.pages.held_pages())} pages held)")
    print(f"  every frame's cut: sha256 {cuts.hexdigest()[:16]}, draw set: {draws.hexdigest()[:16]}; the last cut "
          f"{len(u.selection.cut)} tiles, {u.selection.splats} splats; the fetcher's requests: sha256 "
          f"{fetcher.requests_digest()} over {len(fetcher.lists)} wish lists")
    print("  read along the path: " + ", ".join(f"{g}: {n} files, {b / 1e6:.2f} MB"
                                                  for g, (n, b) in sorted(fetcher.read.items())))
    if parts_json:
        with open(parts_json, "w") as f:
            json.dump([{"frame": i, "update_cpu": round(float(cs[i]), 3), "update_wall": round(float(ts[i]), 3),
                        "tiles": n, "adopted": bool(ad[i]), **{k: [round(x, 3) for x in v] for k, v in p.items()}}
                       for i, (p, n) in enumerate(zip(parts, held_tiles, strict=True))], f)
    if prof is not None:
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
        pstats.Stats(prof).sort_stats("cumulative").print_stats("selection.py|engine.py", 25)


def _context_switches() -> tuple[int, int]:
    """The calling thread's (voluntary, involuntary) context switches so far (Linux: RUSAGE_THREAD; 0 elsewhere).
    A voluntary one in the frame loop is a wait: for the interpreter lock after it gave the lock up, or any other
    block; an involuntary one is the OS preempting it (this shared 2-core VM: other processes, the busy threads)."""
    who = getattr(resource, "RUSAGE_THREAD", None) if resource is not None else None
    if who is None:
        return 0, 0
    r = resource.getrusage(who)
    return r.ru_nvcsw, r.ru_nivcsw


def print_parts(parts: list[dict[str, list[float]]], cpu: np.ndarray, wall: np.ndarray) -> None:
    """Each part's thread CPU and wall per frame (0 in frames without it; the page adoption, eviction and upload
    over the frames they ran in): median, p99, max, and in how many frames it ran. `selection` is the view's
    numbers and the cut (what bench_flythrough.py's --breakdown counts as the selection); `wanted` the whole
    selection (with the pages wanted, the bands and the keys); `keys etc.` is `wanted` less its timed parts."""
    names = ["view", "cut", "pages wanted", "bands", "wanted", "wish list", "wish list: coarse to fine",
             "wish list: requests", "page adoption", "page eviction",
             "page eviction: choice", "page eviction: evict", "page eviction: forget", "draw set", "collect", "upload"]

    def col(name: str, k: int) -> np.ndarray:
        return np.array([p.get(name, [0.0, 0.0, 0.0, 0.0])[k] for p in parts])
    rows = {n: (col(n, 0), col(n, 1), col(n, 2), col(n, 3)) for n in names}
    rows["selection (view + cut)"] = tuple(rows["view"][k] + rows["cut"][k] for k in range(4))
    rest = [rows[n] for n in ("view", "cut", "pages wanted", "bands")]
    rows["keys etc. (wanted less the above)"] = tuple(rows["wanted"][k] - sum(r[k] for r in rest) for k in range(4))
    rows["update"] = (cpu, wall, None, None)
    # waits: the frame loop's voluntary context switches inside the part (getrusage of its thread), a frame: each
    # is a time it gave up the interpreter lock (or blocked otherwise) and slept until it had it back; "pre": its
    # involuntary ones (the OS preempted it); "gaps": frames whose wall exceeds their CPU by more than 0.5 ms
    print(f"  {'part (ms a frame)':36s} {'CPU median':>10s} {'p99':>7s} {'max':>7s} | {'wall median':>11s} "
          f"{'p99':>7s} {'max':>7s} | frames | waits mean, p99, pre mean, gaps")
    for n, (c, w, v, pre) in rows.items():
        ran_in = w > 0
        if n.startswith("page ") or n == "upload":  # over the frames it ran in
            c, w = c[ran_in], w[ran_in]
            v, pre = (v[ran_in], pre[ran_in]) if v is not None else (None, None)
        ran = int(np.count_nonzero(w)) if n != "update" else len(w)
        if not ran:
            continue
        waits = "" if v is None else (f" | {v.mean():.2f}, {np.percentile(v, 99):.0f}, {pre.mean():.2f}, "
                                      f"{int(np.count_nonzero(w - c > 0.5))}")
        print(f"  {n:36s} {np.median(c):10.3f} {np.percentile(c, 99):7.3f} {c.max():7.3f} | {np.median(w):11.3f} "
              f"{np.percentile(w, 99):7.3f} {w.max():7.3f} | {ran}{waits}")


_JIT_COST = """
import json, time
w, c = time.perf_counter(), time.process_time()
import numba
w1, c1 = time.perf_counter(), time.process_time()
from client_gl.stream import selection_jit
w2, c2 = time.perf_counter(), time.process_time()
selection_jit.warm_up()
w3, c3 = time.perf_counter(), time.process_time()
print(json.dumps([w1 - w, c1 - c, w2 - w1, c2 - c1, w3 - w2, c3 - c2]))
"""


def jit_cost(runs: int) -> None:
    """What the compiled selection costs before its first use, in a fresh process: importing numba, the module, and
    compiling its kernels (an empty numba cache) or loading them (the cache the first run wrote), wall and CPU."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for run in range(runs):
            out = subprocess.run([sys.executable, "-c", _JIT_COST], env=env, check=True, capture_output=True,
                                 text=True).stdout
            v = json.loads(out)
            print(f"{'cold cache' if run == 0 else 'warm cache'}: import numba {v[0]:.2f} s (CPU {v[1]:.2f}), "
                  f"import selection_jit {v[2]:.2f} s (CPU {v[3]:.2f}), warm_up (compile or load) {v[4]:.2f} s "
                  f"(CPU {v[5]:.2f}); in all {v[0] + v[2] + v[4]:.2f} s (CPU {v[1] + v[3] + v[5]:.2f})")


def first_frame(scenes: list[str], runs: int, converge: bool = False) -> None:
    """Seconds from a new fetcher to the first frame that draws (the root), over loopback HTTP, and the manifest
    bytes fetched before it."""
    for scene in scenes:
        proc, url = serve_scene(scene)
        try:
            times, converged, manifest_bytes = [], [], 0
            for _ in range(runs):
                t0 = time.perf_counter()
                f = Fetcher(HttpSource(url)).start()
                try:
                    engine = StreamEngine(f, _Slots(), StreamOptions(SelectionOptions(max_splats=3_000_000)))
                    cam = ground_camera_of(engine.manifest)
                    while not engine.update(cam).draw:
                        engine.wait(0.002)
                    times.append(time.perf_counter() - t0)
                    manifest_bytes = len(f.manifest_bytes)
                    if converge:
                        while not engine.update(cam).converged:
                            engine.wait(0.002)
                            time.sleep(0.002)
                        converged.append(time.perf_counter() - t0)
                    engine.close()
                finally:
                    f.close()
            print(f"{scene}: first frame {statistics.median(times) * 1e3:.0f} ms median of {runs} (min "
                  f"{min(times) * 1e3:.0f}, max {max(times) * 1e3:.0f}), {manifest_bytes / 1e3:.1f} KB of manifest "
                  "before it" + (f"; converged {statistics.median(converged):.2f} s median (min {min(converged):.2f}, "
                                 f"max {max(converged):.2f})" if converged else ""))
        finally:
            proc.terminate()
            proc.wait()


def ground_camera_of(m: Manifest) -> Camera:
    root = m.tile(m.root)
    c, r = np.array(root.sphere_center), root.sphere_radius
    return Camera(tuple(c + r * np.array([1.2, 0.3, 0.5])), tuple(c), (0.0, 0.0, 1.0), 60.0, 1920, 1080,
                  near=0.01 * r)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--first-frame", nargs="+", metavar="SCENE")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--converge", action="store_true", help="--first-frame: also the time until the view converged")
    ap.add_argument("--repage", nargs=2, metavar=("SCENE", "OUT"))
    ap.add_argument("--splats", default="1e6,6e6,60e6,250e6")
    ap.add_argument("--levels", default="4,5,6,8")
    ap.add_argument("--default-levels", type=int, default=EncodeOptions.page_levels)
    ap.add_argument("--sh-degree", type=int, default=0)
    ap.add_argument("--version", default=None, help="write the trees as this format version (1.7: tile maps; 1.8, "
                    "what the encoder writes an LOD tree as: tile tables, format.md 6.2)")
    ap.add_argument("--max-splats", type=int, default=3_000_000)
    ap.add_argument("--engine", action="store_true", help="a StreamEngine along a street-level path (per frame)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--per-frame", type=int, default=8, help="--engine: payloads or pages arriving a frame")
    ap.add_argument("--profile", action="store_true", help="--engine: where the update's time goes")
    ap.add_argument("--numpy-selection", action="store_true",
                    help="--engine: the numpy selection, not the compiled one (selection_jit, numba)")
    ap.add_argument("--no-wait", action="store_true",
                    help="--engine: do not wait for the compiled selection before the path (the engine loads it on "
                         "a worker thread from its first frame near the cut): the frames before it was ready")
    ap.add_argument("--parts-json", metavar="FILE",
                    help="--engine: each frame's parts (CPU and wall ms) to FILE (N in it: the scene's size)")
    ap.add_argument("--busy-threads", type=int, default=0,
                    help="--engine: threads of pure Python beside the frame loop (as a page parse or a decode step "
                         "that runs into a frame): the frame's wall then shows each hand-over of the interpreter lock")
    ap.add_argument("--busy-pattern", default=None, metavar="HOLD,REST",
                    help="--engine: the busy threads hold the interpreter lock HOLD ms, then rest REST ms without it "
                         "(as a decode thread's Python between its nogil kernels: 0.15,0.3), instead of always")
    ap.add_argument("--select-switch-interval", type=float, default=None, metavar="S",
                    help="--engine: StreamOptions.select_switch_interval (the switch interval while the frame loop "
                         "selects, seconds; 0: untouched; default: the option's default)")
    ap.add_argument("--max-tree-tiles", type=int, default=None,
                    help="--engine: the engine's bound on the tiles held (StreamOptions.max_tree_tiles; default its "
                         "default): below the tiles the path holds, pages are dropped and their eviction timed")
    ap.add_argument("--jit-cost", action="store_true",
                    help="the compiled selection's import and compilation (cold numba cache) or loading (warm)")
    args = ap.parse_args()
    if args.jit_cost:
        jit_cost(args.runs)
        return
    if args.engine:
        base = template(args.sh_degree)
        for n in [int(float(s)) for s in args.splats.split(",")]:
            engine_path(synthetic_tree(n, base), args.default_levels, args.frames, args.max_splats, args.per_frame,
                        args.profile, not args.numpy_selection, not args.no_wait,
                        args.parts_json.replace("N", f"{n / 1e6:.0f}M") if args.parts_json else None,
                        args.busy_threads, args.max_tree_tiles,
                        tuple(float(x) for x in args.busy_pattern.split(",")) if args.busy_pattern else None,
                        args.select_switch_interval)
        return
    if args.repage:
        repage(*args.repage, args.default_levels)
        return
    if args.first_frame:
        first_frame(args.first_frame, args.runs, args.converge)
        return
    base = template(args.sh_degree)
    if args.version:
        base = replace(base, version=tuple(int(v) for v in args.version.split(".")))
    opts = SelectionOptions(max_sse=1.5, max_splats=args.max_splats)
    print("splats  tiles  levels  manifest_MB | k  root_KB  pages  page_KB_median  page_KB_max")
    for n in [int(float(s)) for s in args.splats.split(",")]:
        whole = synthetic_tree(n, base)
        whole_bytes = len(pack_manifest(whole))
        print(f"{n / 1e6:6.0f}M {len(whole.tiles):6d} {whole.levels:6d} {whole_bytes / 1e6:10.2f}")
        for k in [int(v) for v in args.levels.split(",")]:
            paged = split_pages(whole, k)
            sizes = [ref.bytes for ref, _ in paged.pages]
            print(f"{'':32s}| {k}  {len(pack_manifest(paged.root)) / 1e3:7.1f}  {len(sizes):5d}  "
                  f"{statistics.median(sizes) / 1e3 if sizes else 0:14.1f}  {max(sizes, default=0) / 1e3:11.1f}")
        paged = split_pages(whole, args.default_levels)
        files = {ref.file: raw for ref, raw in paged.pages}
        root_raw = pack_manifest(paged.root)
        tree = PagedTree(parse_manifest(root_raw, "root", lazy_payloads=True))
        cam = ground_camera(whole)
        t0 = time.perf_counter()
        rounds = 0
        while True:  # the client's rounds: select over the tiles held, read the pages the cut reaches
            view, sel = select_once(tree.manifest, cam, opts)
            wanted = tree.wanted_pages(sel.cut, view.sse, view.visible, opts.max_sse)
            if not wanted:
                break
            rounds += 1
            for tile_id, _ in wanted:
                tree.add_page(tile_id, files[tree.entry(tile_id).file])
        stream_s = time.perf_counter() - t0
        _, sel_whole = select_once(whole, cam, opts)
        _, sel_paged = select_once(tree.manifest, cam, opts)
        same = sorted(int(whole.arrays.ids[i]) for i in sel_whole.cut) == \
            sorted(int(tree.manifest.arrays.ids[i]) for i in sel_paged.cut)
        t_whole, t_held = timed(whole, cam, opts), timed(tree.manifest, cam, opts)
        parse_ms, parse_tiles = page_parse_times(paged, files)
        print(f"   ground view, k={args.default_levels}: first frame needs {len(root_raw) / 1e3:.1f} KB of "
              f"manifest (whole: {whole_bytes / 1e3:.1f} KB); cut of {len(sel_paged.cut)} tiles, "
              f"{sel_paged.splats / 1e6:.2f}M splats, same as the whole tree's: {same}; {tree.pages_read} pages "
              f"({tree.page_bytes / 1e3:.1f} KB) in {rounds} rounds ({stream_s:.2f} s of page reading and selection); "
              f"tiles held {len(tree.manifest.tiles)} of {len(whole.tiles)}; selection per frame "
              f"{t_held * 1e3:.2f} ms over the tiles held, {t_whole * 1e3:.2f} ms over the whole tree; a page's parse "
              f"(read_page + tile_rows, as PagedTree.read on a decode thread) {statistics.median(parse_ms):.2f} ms "
              f"of CPU median, {max(parse_ms):.2f} max, pages of {statistics.median(parse_tiles):.0f} tiles median "
              f"(version {whole.version[0]}.{whole.version[1]})")


def page_parse_times(paged, files: dict[str, bytes], limit: int = 200) -> tuple[list[float], list[int]]:
    """CPU ms of read_page (the bytes' SHA-256 taken as checked, as the client's) and tile_rows on each of the
    first `limit` pages (the deepest first: the tree's most common page), and the tiles of each page."""
    parents = {t.page.sha256: t for t in _all_tiles(paged) if t.page is not None}
    ms, tiles = [], []
    for ref, raw in paged.pages[:limit]:
        parent = parents[ref.sha256]
        gc.collect()
        t0 = time.process_time()
        got = read_page(raw, ref, paged.root, parent, "page", lazy_payloads=True, hashed=True)
        tile_rows(got)
        ms.append((time.process_time() - t0) * 1e3)
        tiles.append(len(got))
    return ms, tiles


def _all_tiles(paged):
    """Every tile of a PagedScene: the root manifest's and each page's (read back unchecked)."""
    out = list(paged.root.tiles)
    by_sha = {ref.sha256: (ref, raw) for ref, raw in paged.pages}
    todo = [t for t in out if t.page is not None]
    while todo:
        t = todo.pop()
        ref, raw = by_sha[t.page.sha256]
        got = read_page(raw, ref, paged.root, t, "page", lazy_payloads=True, hashed=True)
        out += got
        todo += [c for c in got if c.page is not None]
    return out


if __name__ == "__main__":
    main()
