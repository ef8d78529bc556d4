"""Partitioned encoding: scenes larger than one machine's memory, on any engine that can map tasks (this process,
encode/local.py; a Dask cluster, encode/distributed.py). Design and guarantees: format_spec/lod.md section 6,
ARCHITECTURE.md "Distributed encoding".

1. scan: the input is read in row ranges (a binary PLY's fixed-size records: one byte range each); each task
   checks its rows, writes their centres to scratch and returns its counts and centre box.
2. top splits: the kd median splits above the partitions, exact, over the keys (value, input index) of
   lod.sort_keys: one pass per level that counts the keys below a bracket taken from the scan's sample and gathers
   those inside it; radix selection (counting passes, then a gather of the few candidates) where a bracket misses.
3. route: every row goes to its partition (a subtree of the tile tree); each chunk writes one scratch file with a
   section per partition, and its part of the scene samples (sample.py).
4. plan: the SH codebook, up and camera from the samples, on the client.
5. partitions: each task reads its sections, builds its subtree (lod.build_subtree, the code the single-process
   encoder runs on the whole scene), writes its tiles' payloads (content-addressed: no coordination) and keeps its
   originals in scratch for the tiles above.
6. upper tiles: level by level on the client from the partition roots' splats; the errors and appearance they
   take from the ORIGINAL splats come from two passes over the partitions (max/min and integer counts, which
   combine exactly; per-leaf sums, folded in kd order, as lod.build_subtree folds them).
7. the manifest, last.
With `--lod-refine cpu` (EncodeOptions.lod_refiner) the partitions are the merge domains whatever the merge, each
task of step 5 refines its subtree against its own originals, from the whole scene's cameras (lod_refine.CameraFrame),
before encoding it, and the levels of step 6 are refined
by upper domains, tier after tier (refine_upper: a task per upper domain against its roots as refined), before they
are encoded (lod.md 6, "The refinement by partitions").

The output is byte-identical whatever the engine, the number of workers and partitions and the chunking. With the
grid merge it is encode_to's; with "auto" (the default) the partitions are auto's merge domains, a tile level fixed
by the scene's splat count (merge_domain_level): each partition groups the levels inside it over its own splats, and
the levels above the partitions are grouped by upper domains (upper_domain_levels: tiers of kd subtrees of at most
EncodeOptions.lod_upper_domain_roots roots each, a task per domain and level, merge_level), so it is encode_to's where
the scene is one domain (at most EncodeOptions.lod_merge_domain_splats splats) and differs from it above that.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from ..edit import Pipeline
from ..errors import UsageError
from ..format.manifest import Box, LodRefinement, TileEntry
from ..gaussians import SH_REST_COEFFS, Gaussians
from ..io import SplatInput, read_gaussians
from ..lod import (
    Tile,
    TreeShape,
    appearance_terms,
    build_subtree,
    column_max,
    column_min,
    error_extremes,
    finish_tile_appearance,
    fold_leaf_sums,
    interior_bounds,
    kd_route,
    leaf_sums,
    level_auto_groups,
    merge_gaussians,
    merge_groups,
    original_reach,
    sort_keys,
    split_axis,
    tile_error_first,
    tile_viewing_blur,
    viewing_blur,
)
from ..lod_refine import CameraFrame, LodRefiner, domains_record, refine_subtree
from ..ply import RowStats, VertexLayout, check_rows, read_ply_rows
from ..progress import count
from ..store import SceneWriter, write_scene_manifest
from .codebook import check_codebook_option, codebook_choice
from .jobs import encode_codebook, encode_tile
from .options import EncodeOptions, Progress, no_progress
from .plan import TileContext, log, palette_planes, plan_formats, plan_scene, scene_name
from .reduce import build_manifest
from .sample import SceneSample
from .scratch import Scratch

# Bytes a partition task needs per splat of its partition, as a multiple of its Gaussians' bytes: the splats, the
# build's temporaries (kd index sets, Morton orders, the first merge's float64 moments) and the encoder's.
PARTITION_MEMORY_FACTOR = 4.0
# Largest count of candidate keys per node gathered to the client to finish a median selection.
GATHER_KEYS = 1 << 22
# Centres the scan keeps as the sample that brackets each kd median (every n-th row; about this many in all).
SPLIT_SAMPLE = 1 << 20
# The LOD merges a partitioned encode builds (lod.LOD_MERGES): "cost" groups a whole level of the scene at once.
PARTITIONED_MERGES = ("grid", "auto")
# Bytes a partition task of the "auto" merge needs per splat beyond the grid's PARTITION_MEMORY_FACTOR: the cost
# grouping's arrays (lod_groups.group_ids_of), whatever the SH degree. Measured (tracemalloc over lod.build_tiles,
# branch partauto31): auto's peak above the grid's about 450-480 bytes a splat on biker (SH0) and a 135k slice of
# flowers (SH2).
AUTO_GROUPING_BYTES = 512
# Upper tiles merged at once on the client (their splats and their members): bounds the client's memory.
UPPER_BATCH_SPLATS = 1 << 20
ATTRIBUTES = ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


class Engine(Protocol):
    """Runs tasks: module-level functions and picklable arguments, results in the order of the arguments."""

    workers: int
    memory_per_worker: int  # bytes a task may use
    threads_per_task: int

    def map(self, fn: Callable, args: list[tuple], stage: str, progress: Progress, heavy: bool = False,
            task_progress: bool = False) -> list:
        """`heavy`: tasks that need a worker's memory (one at a time per worker). `task_progress`: each task gets
        one more argument, a callable fraction -> None reporting its own progress (from wherever it runs)."""
        ...

    def map_behind(self, fn: Callable, args: list[tuple], stage: str) -> None:
        """Tasks nobody waits for now (scratch deletes): run when a worker has nothing else to do, after the tasks
        `map` submits; their errors come out of `settle`."""
        ...

    def settle(self) -> None:
        """Wait for every task of `map_behind`; raises the first one's error."""
        ...


# ---------------------------------------------------------------------------------------------- input rows


@dataclass
class PlyRows:
    """A binary 3DGS PLY: each chunk of rows is one byte range of the file."""

    layout: VertexLayout
    path: str

    @property
    def rows(self) -> int:
        return self.layout.rows

    @property
    def sh_degree(self) -> int:
        return self.layout.sh_degree

    def read(self, start: int, stop: int) -> tuple[Gaussians, RowStats]:
        return read_ply_rows(self.layout, start, stop)


@dataclass
class ArrayRows:
    """Gaussians already in memory (tests, and inputs read whole): chunks are slices."""

    g: Gaussians

    @property
    def rows(self) -> int:
        return len(self.g)

    @property
    def sh_degree(self) -> int:
        return self.g.sh_degree

    def read(self, start: int, stop: int) -> tuple[Gaussians, RowStats]:
        part = self.g.subset(slice(start, stop))
        return part, RowStats(rows=len(part))


@dataclass
class SpilledRows:
    """An input that cannot be read by rows (compressed formats, ASCII PLY), read once and written to scratch in
    chunks."""

    scratch: Scratch
    chunk_rows: int
    rows: int
    sh_degree: int
    prefix: str = "input"  # one per input of a merge, so that their chunks do not collide in scratch

    def read(self, start: int, stop: int) -> tuple[Gaussians, RowStats]:
        # The rows asked for, whichever spilled chunks hold them: the encoder's chunks are not the spill's (its
        # own size, from the memory per worker), nor are a merge's (ConcatRows reads each input from an offset).
        stop = min(stop, self.rows)
        pieces = []
        for c in range(start // self.chunk_rows, -(-stop // self.chunk_rows)):
            a = self.scratch.load(f"{self.prefix}/{c}")
            lo, hi = max(start - c * self.chunk_rows, 0), min(stop - c * self.chunk_rows, self.chunk_rows)
            pieces.append(Gaussians(*(a[k][lo:hi] for k in ATTRIBUTES)))
        if not pieces:
            return Gaussians.empty(self.sh_degree), RowStats()
        g = pieces[0] if len(pieces) == 1 else Gaussians.concatenate(pieces)
        return g, RowStats(rows=len(g))


@dataclass
class ConcatRows:
    """Several inputs merged (issue 36: `encode a.ply b.spz out`): their rows one after the other, in the order given,
    every chunk padded with zero SH bands to the highest degree among them (as Gaussians.concatenate pads the whole
    scenes in memory), so any chunking gives the rows of the merged scene."""

    parts: list[PlyRows | ArrayRows | SpilledRows]

    @property
    def rows(self) -> int:
        return sum(p.rows for p in self.parts)

    @property
    def sh_degree(self) -> int:
        return max(p.sh_degree for p in self.parts)

    def read(self, start: int, stop: int) -> tuple[Gaussians, RowStats]:
        pieces, stats, offset = [], RowStats(), 0
        for part in self.parts:
            lo, hi = max(start - offset, 0), min(stop - offset, part.rows)
            if lo < hi:
                g, st = part.read(lo, hi)
                pieces.append(g.with_sh_degree(self.sh_degree))
                stats = stats + st
            offset += part.rows
        return (Gaussians.concatenate(pieces) if pieces else Gaussians.empty(self.sh_degree)), stats


@dataclass
class EditedRows:
    """Rows with the edits of issue 36 (edit.Pipeline) applied to each chunk as it is read: every edit is a
    function of one splat, so the kept rows and their values are those of the whole scene edited at once."""

    inner: PlyRows | ArrayRows | SpilledRows | ConcatRows
    edits: Pipeline

    @property
    def rows(self) -> int:
        return self.inner.rows

    @property
    def sh_degree(self) -> int:
        return self.inner.sh_degree

    def read(self, start: int, stop: int) -> tuple[Gaussians, RowStats]:
        g, stats = self.inner.read(start, stop)
        return self.edits.apply(g), stats


def open_rows(source: SplatInput, layout: VertexLayout | None, scratch: Scratch, chunk_rows: int,
              drop_invalid: bool, progress: Progress, prefix: str = "input"):
    """The input as rows to read in chunks: a binary PLY in byte ranges (its `layout`, from
    SplatInput.vertex_layout), anything else read once and spilled (under `prefix` in scratch)."""
    if layout is not None:
        return PlyRows(layout, source.path)
    progress("read", 0.0)
    g = read_gaussians(source, drop_invalid=drop_invalid)
    for i, start in enumerate(range(0, len(g), chunk_rows)):
        part = g.subset(slice(start, start + chunk_rows))
        scratch.save(f"{prefix}/{i}", **{k: getattr(part, k) for k in ATTRIBUTES})
    progress("read", 1.0)
    return SpilledRows(scratch, chunk_rows, len(g), g.sh_degree, prefix)

# ---------------------------------------------------------------------------------------------- tasks


def scan_chunk(rows, i: int, start: int, stop: int, scratch: Scratch, stride: int = 1
               ) -> tuple[int, RowStats, np.ndarray, np.ndarray, np.ndarray]:
    """Read one chunk: its valid row count, what was wrong, its centre box, and every `stride`-th valid row's centre
    (the split sample; row i * stride of the chunk's valid rows); its centres go to scratch."""
    g, stats = rows.read(start, stop)
    scratch.save(f"pos/{i}", p=g.positions)
    sample = np.ascontiguousarray(g.positions[::stride])
    if not len(g):
        return 0, stats, np.full(3, np.inf, np.float32), np.full(3, -np.inf, np.float32), sample
    return len(g), stats, column_min(g.positions), column_max(g.positions), sample


def _chunk_keys(scratch: Scratch, i: int, offset: int, splits: list, routed: bool = False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One chunk's centres, their kd nodes at depth len(splits) and their input indices. `routed`: the chunk's nodes
    one level up are in scratch (saved by chunk_bracket), so one routing step is left."""
    p = scratch.load(f"pos/{i}")["p"]
    index = offset + np.arange(len(p), dtype=np.int64)
    if routed and splits:
        above = scratch.load(f"node/{len(splits) - 1}/{i}")["n"].astype(np.int64)
        axes, pivots = splits[-1]
        node = 2 * above + (sort_keys(p[np.arange(len(p)), axes[above]], index) >= pivots[above])
    else:
        node = kd_route(p, index, splits)
    return p, node, index


def chunk_boxes(scratch: Scratch, i: int, offset: int, splits: list, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Centre box of every kd node (at depth len(splits)) over one chunk."""
    p, node, _ = _chunk_keys(scratch, i, offset, splits)
    lo = np.full((nodes, 3), np.inf, np.float32)
    hi = np.full((nodes, 3), -np.inf, np.float32)
    for k in range(3):
        np.minimum.at(lo[:, k], node, p[:, k])
        np.maximum.at(hi[:, k], node, p[:, k])
    return lo, hi


def chunk_select(scratch: Scratch, i: int, offset: int, splits: list, axes: np.ndarray, prefix: np.ndarray,
                 bits: np.ndarray, gather: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray] | np.ndarray]:
    """One counting pass of the radix selection over one chunk. For every node still open: the keys that share
    its `bits`-bit prefix either counted by their next 16 bits, or (where `gather`) returned."""
    p, node, index = _chunk_keys(scratch, i, offset, splits)
    keys = sort_keys(p[np.arange(len(p)), axes[node]], index)
    out: dict[int, tuple[np.ndarray, np.ndarray] | np.ndarray] = {}
    order = np.argsort(node, kind="stable")
    bounds = np.searchsorted(node[order], np.arange(len(axes) + 1))
    for j in np.flatnonzero(bits >= 0):
        k = keys[order[bounds[j]:bounds[j + 1]]]
        b = int(bits[j])
        if b:
            k = k[(k >> np.uint64(64 - b)) == (np.uint64(prefix[j]) >> np.uint64(64 - b))]
        if gather[j]:
            out[int(j)] = k
        else:
            digits, counts = np.unique((k >> np.uint64(48 - b)) & np.uint64(0xFFFF), return_counts=True)
            out[int(j)] = (digits, counts)
    return out


def chunk_bracket(scratch: Scratch, i: int, offset: int, splits: list, axes: np.ndarray, lo_key: np.ndarray,
                  hi_key: np.ndarray, routed: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One pass of the bracketed median selection over one chunk: per node (at depth len(splits)), the count of its
    keys below `lo_key`, the centre boxes of its splats below and above the bracket [lo_key, hi_key] (`boxes`:
    [below/above][lo/hi][node]), and the node, key and centre of every splat inside the bracket. The chunk's nodes
    at this depth go to scratch; `routed`: the pass of the level above saved its own, so one routing step is left."""
    p, node, index = _chunk_keys(scratch, i, offset, splits, routed)
    nodes = len(axes)
    scratch.save(f"node/{len(splits)}/{i}", n=node.astype(np.uint16 if nodes <= 1 << 16 else np.int64))
    keys = sort_keys(p[np.arange(len(p)), axes[node]], index)
    is_below = keys < lo_key[node]
    is_above = keys > hi_key[node]
    below = np.bincount(node[is_below], minlength=nodes)
    # groups 2 node (below) and 2 node + 1 (above); splats inside the bracket go to a last group, left out
    group = np.where(is_below | is_above, 2 * node + is_above, 2 * nodes)
    columns = np.ascontiguousarray(p.T)
    lo = np.full((3, 2 * nodes + 1), np.inf, np.float32)
    hi = np.full((3, 2 * nodes + 1), -np.inf, np.float32)
    for k in range(3):
        np.minimum.at(lo[k], group, columns[k])
        np.maximum.at(hi[k], group, columns[k])
    boxes = np.stack([lo[:, :-1].T.reshape(nodes, 2, 3), hi[:, :-1].T.reshape(nodes, 2, 3)])  # [lo/hi][node][side]
    inside = np.flatnonzero(~(is_below | is_above))
    return below, boxes.transpose(2, 0, 1, 3), node[inside], keys[inside], p[inside]


def _section_widths(sh_degree: int) -> list[tuple[str, int]]:
    return [("positions", 3), ("rotations", 4), ("log_scales", 3), ("opacity_logits", 1), ("sh_dc", 3),
            ("sh_rest", 3 * SH_REST_COEFFS[sh_degree])]


def routed_row_bytes(sh_degree: int) -> int:
    """Bytes of one splat in a routed scratch section (route_chunk): its float32 attributes and its int64 input
    index; also the driver's measure of a scene's build memory (fits_in_process)."""
    return 4 * sum(w for _, w in _section_widths(sh_degree)) + 8


def route_chunk(rows, i: int, start: int, stop: int, offset: int, splits: list, partitions: int, scratch: Scratch,
                sh_degree: int, splats: int, with_codebook: bool,
                palette_planes: tuple[str, ...] = ()) -> tuple[np.ndarray, SceneSample]:
    """Send every row of a chunk to its partition: one scratch file, a section per partition (each attribute's
    rows, then their input indices), rows in input order. Returns the rows per partition and the chunk's part of
    the scene samples."""
    g, _ = rows.read(start, stop)
    if sh_degree != g.sh_degree:
        g = g.with_sh_degree(sh_degree)
    index = offset + np.arange(len(g), dtype=np.int64)
    part = kd_route(g.positions, index, splits) if splits else np.zeros(len(g), np.int64)
    order = np.argsort(part, kind="stable")
    counts = np.bincount(part, minlength=partitions)
    starts = np.concatenate([[0], np.cumsum(counts)])
    blocks: list[bytes] = []
    for q in range(partitions):
        rows_q = order[starts[q]:starts[q + 1]]
        for name, _ in _section_widths(sh_degree):
            blocks.append(getattr(g, name)[rows_q].tobytes())
        blocks.append(index[rows_q].tobytes())
    scratch.write(f"route/{i}", blocks)
    return counts, SceneSample.part(g, offset, splats, with_codebook, palette_planes)


def _read_partition(scratch: Scratch, p: int, chunk_counts: list[np.ndarray], sh_degree: int
                    ) -> tuple[Gaussians, np.ndarray]:
    widths = _section_widths(sh_degree)
    row_bytes = routed_row_bytes(sh_degree)
    n = int(sum(int(c[p]) for c in chunk_counts))
    arrays = {name: np.empty((n, w), np.float32) for name, w in widths}
    index = np.empty(n, np.int64)
    at = 0
    for i, counts in enumerate(chunk_counts):
        m = int(counts[p])
        if not m:
            continue
        first = int(counts[:p].sum()) * row_bytes
        data = scratch.read(f"route/{i}", first, first + m * row_bytes)
        pos = 0
        for name, w in widths:
            arrays[name][at:at + m] = np.frombuffer(data, np.float32, m * w, pos).reshape(m, w)
            pos += 4 * m * w
        index[at:at + m] = np.frombuffer(data, np.int64, m, pos)
        at += m
    g = Gaussians(arrays["positions"], arrays["rotations"], arrays["log_scales"], arrays["opacity_logits"][:, 0],
                  arrays["sh_dc"], arrays["sh_rest"].reshape(n, SH_REST_COEFFS[sh_degree], 3))
    return g, index


def _save_tile(scratch: Scratch, tile: Tile, mass: np.ndarray, prefix: str = "tile") -> None:
    g = tile.gaussians
    scratch.save(f"{prefix}/{tile.id}", mass=mass, level=np.array(tile.level), error=np.array(tile.geometric_error),
                 box_min=tile.box_min, box_max=tile.box_max, sphere_center=tile.sphere_center,
                 sphere_radius=np.array(tile.sphere_radius), children=np.array(tile.children, np.int64),
                 **{k: getattr(g, k) for k in ATTRIBUTES})


def _load_tile(scratch: Scratch, tid: int, prefix: str = "tile") -> tuple[Tile, np.ndarray]:
    a = scratch.load(f"{prefix}/{tid}")
    g = Gaussians(*(a[k] for k in ATTRIBUTES))
    tile = Tile(tid, int(a["level"]), [int(c) for c in a["children"]], g, float(a["error"]), a["box_min"],
                a["box_max"], a["sphere_center"], float(a["sphere_radius"]))
    return tile, a["mass"]


def _encode_tiles(tiles: list[Tile], ctx: TileContext, writer, threads: int,
                  done: Callable[[float], None]) -> list[TileEntry]:
    out = []
    if threads <= 1 or len(tiles) <= 1:
        for t in tiles:
            out.append(encode_tile(t, ctx, writer))
            done(len(out) / len(tiles))
        return out
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for entry in pool.map(lambda t: encode_tile(t, ctx, writer), tiles):
            out.append(entry)
            done(len(out) / len(tiles))
    return out


@dataclass
class PartitionResult:
    entries: list[TileEntry]
    root_splats: int
    splats: int
    refinement: LodRefinement | None = None  # the partition's own levels refined (lod_refine.refine_subtree)


def build_partition(p: int, level: int, shape: TreeShape, chunk_counts: list[np.ndarray], scratch: Scratch,
                    ctx: TileContext, writer, threads: int, keep_originals: bool, merge: str,
                    refiner: LodRefiner | None, up: tuple[float, float, float] | None,
                    frame: CameraFrame | None, report: Callable[[float], None]) -> PartitionResult:
    """One partition: read its rows, build its subtree with the LOD merge `merge` (for "auto", the partition's
    splats are the whole scene of the levels inside its subtree: the partition is auto's merge domain), refine its
    merged levels against its own originals where `refiner` is given (lod.md 6, "The refinement by partitions"; its
    cameras placed by the whole scene's `frame`), write its tiles' payloads; its root and (for the tiles above) its
    originals go to scratch. `report(fraction)`: the task's progress."""
    g, index = _read_partition(scratch, p, chunk_counts, ctx.sh_degree)
    n = len(g)
    refining = refiner is not None and level < shape.leaf_level
    # the task's progress: the build, the refinement (the longest part where asked for), the payloads
    spans = (0.1, 0.75) if refining else (0.6, 0.0)

    def build_progress(stage: str, fraction: float) -> None:
        if stage == "lod-merge":
            report(spans[0] * fraction)

    # `threads` as for the tiles' encode: the engine already runs partitions side by side
    sub = build_subtree(g, index, shape, level, p, progress=build_progress, reorder_input=True, threads=threads,
                        merge=merge)
    del g, index
    tiles, root, record = sub.tiles, sub.root, None
    if refining:
        def refine_progress(stage: str, fraction: float) -> None:
            if stage == "refine":
                report(spans[0] + spans[1] * fraction)

        # the subtree's own originals (leaf order: the leaves' splats) are its full detail, as the whole scene's
        # are in memory; its cameras the whole scene's (`frame`): the domain alone, seen from where the scene is seen
        # (its own frame, nearer, cost 0.2-1.2 dB on 3 of 4 scenes: BENCHMARKS.md "Closing the partitioned
        # refinement's gap")
        tiles, record = refine_subtree(sub.ordered, sub.tiles, up, refiner, refine_progress, frame)
        root = tiles[sub.root.id]
    done = spans[0] + spans[1]
    entries = _encode_tiles(list(tiles.values()), ctx, writer, threads, lambda f: report(done + (1 - done) * f))
    if keep_originals:
        o = sub.ordered
        scratch.save(f"originals/{p}", positions=o.positions, log_scales=o.log_scales, opacity=o.opacity_logits,
                     sh_dc=o.sh_dc, rep=sub.represented_by.astype(np.int32), leaf_starts=sub.leaf_starts)
        # The levels above are merged from the root as built (as in memory, where the whole tree is built before it
        # is refined: the tree's shape and errors those of the encode without refinement), inside the root's final
        # bounds (its parents cover them); the refined root is the full detail of the levels above (refine_upper).
        _save_tile(scratch, replace(root, gaussians=sub.root.gaussians), sub.root_mass)
        if record is not None:
            _save_tile(scratch, root, sub.root_mass, "refined")
    return PartitionResult(entries, len(sub.root.gaussians), n, record)


def merge_children(scratch: Scratch, shape: TreeShape, lvl: int, j: int
                   ) -> tuple[Gaussians, np.ndarray, np.ndarray, np.ndarray, list[Tile]]:
    """Tile j of level lvl (above the partitions) from its children's splats, as lod.build_subtree merges them:
    (merged splats, their mass, each member's merged splat, the children's offsets among the members, the children
    without their splats: only their bounds are needed from here on)."""
    kids = [_load_tile(scratch, c) for c in shape.children(lvl, j)]
    members = Gaussians.concatenate([k.gaussians for k, _ in kids])
    target = min(shape.max_leaf_splats, math.ceil(len(members) / shape.reduction))
    g, mass, assign = merge_gaussians(members, np.concatenate([m for _, m in kids]), target)
    return g, mass, assign, *_released(kids)


def _released(kids: list[tuple[Tile, np.ndarray]]) -> tuple[np.ndarray, list[Tile]]:
    """The children's offsets among their merged members, and the children without their splats (only their bounds
    are needed from here on)."""
    offsets = np.cumsum([0] + [len(k.gaussians) for k, _ in kids])
    for k, _ in kids:
        k.gaussians = Gaussians.empty(0)
    return offsets, [k for k, _ in kids]


def merge_level(scratch: Scratch, shape: TreeShape, lvl: int, threads: int, top: int = 0, domain: int = 0
                ) -> list[tuple[Gaussians, np.ndarray, np.ndarray, np.ndarray, list[Tile]]]:
    """The tiles of level lvl (above the partitions) under tile `domain` of level `top` (their upper domain,
    upper_domain_levels; top 0: the whole level) from their children's splats by the "auto" merge over those tiles
    at once (lod.level_auto_groups, as lod.build_subtree groups a level: the count and each tile's decided by cost
    across the domain's tiles), each tile as merge_children returns it. Its members are the roots' splats under the
    domain or fewer (at most max_leaf_splats per root)."""
    kids_of = [[_load_tile(scratch, c) for c in shape.children(lvl, j)] for j in _tiles_under(shape, top, domain, lvl)]
    sets = [Gaussians.concatenate([k.gaussians for k, _ in kids]) for kids in kids_of]
    masses = [np.concatenate([m for _, m in kids]) for kids in kids_of]
    targets = [shape.target(len(m)) for m in sets]
    blurs = [viewing_blur(max(k.geometric_error for k, _ in kids)) for kids in kids_of]
    # the same groups on any number of threads (level_auto_groups: each block and tile a pure function)
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        groups, _ = level_auto_groups(sets, masses, targets, shape.max_leaf_splats, blurs, pool=pool)
    out = []
    for kids, members, mass, grp in zip(kids_of, sets, masses, groups, strict=True):
        g, merged_mass, assign = merge_groups(members, mass, *grp)
        out.append((g, merged_mass, assign, *_released(kids)))
    return out


def _tiles_under(shape: TreeShape, top: int, j: int, lvl: int) -> range:
    """Positions (kd order) of the tiles of level `lvl` under tile j of level `top` (lvl >= top)."""
    per = 2 ** (shape.kd_depths[lvl] - shape.kd_depths[top])
    return range(j * per, (j + 1) * per)


def upper_domain_levels(shape: TreeShape, level: int, roots_per_domain: int) -> list[int]:
    """The tiers of upper domains above the partition level `level` (lod.md 6, "The auto merge by partitions"): each
    tier's top level, lowest first, the last 0 (the root). A tier whose roots (the partitions' roots, or the tier
    below's tops) are at level b has as its top the shallowest level t < b whose tiles cover at most
    `roots_per_domain` of them (2^(kd(b) - kd(t)); at least one level a tier): each tile of t is an upper domain, its
    levels t..b-1 grouped over its own tiles only. A function of the tree's shape alone (kd subtrees: spatially
    contiguous, kd order)."""
    tops: list[int] = []
    b = level
    while b > 0:
        t = next((t for t in range(b) if 2 ** (shape.kd_depths[b] - shape.kd_depths[t]) <= roots_per_domain), b - 1)
        tops.append(t)
        b = t
    return tops


def _upper_domain_of(tops: list[int], lvl: int) -> int:
    """The top level of the tier that holds upper level `lvl` (its tiles are grouped under that level's tiles)."""
    return next(t for t in tops if t <= lvl)


def partition_extremes(scratch: Scratch, p: int, mapping: np.ndarray, merged_positions: np.ndarray, size: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pass A over a partition's originals for its ancestor tile: per merged splat present, member counts and the
    error extremes (lod.error_extremes)."""
    a = scratch.load(f"originals/{p}")
    rep = mapping[a["rep"]]
    far, near = error_extremes(a["positions"], original_reach(a["log_scales"]), merged_positions, rep, size)
    counts = np.bincount(rep, minlength=size)
    present = np.flatnonzero(counts)
    return present, counts[present], far[present], near[present]


def partition_sums(scratch: Scratch, p: int, mapping: np.ndarray, size: int, blur: float
                   ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pass B: the appearance sums of each of the partition's leaves (lod.leaf_sums), in kd order."""
    a = scratch.load(f"originals/{p}")
    rep = mapping[a["rep"]]
    starts = a["leaf_starts"]
    parts = []
    for s, e in zip(starts[:-1], starts[1:], strict=True):
        terms = appearance_terms(a["opacity"][s:e], a["log_scales"][s:e], a["sh_dc"][s:e], blur)
        parts.append(leaf_sums(rep[s:e], terms, size))
    return parts


def delete_scratch(scratch: Scratch, names: list[str]) -> None:
    """Scratch objects no longer needed, deleted on the workers behind the stages that follow (Engine.map_behind):
    a 60M-splat scene spills about 18 GB, and deleting it all at the end, in one process, took about 10 s of a 118 s
    encode on 16 workers (the kernel frees every cached page of a deleted file); deleted in rounds of their own
    between the stages, 5.6 s of a 111 s one."""
    scratch.delete(names)


def encode_saved_tile(scratch: Scratch, tid: int, ctx: TileContext, writer) -> TileEntry:
    tile, _ = _load_tile(scratch, tid)
    return encode_tile(tile, ctx, writer)


# ---------------------------------------------------------------------------------------------- the client


def merge_domain_level(shape: TreeShape, domain_splats: int) -> int:
    """The tile level whose subtrees are the "auto" merge's domains in a partitioned encode: the shallowest whose
    tiles hold at most `domain_splats` originals (ceil(splats / 2^kd), a function of the tree's shape alone, so the
    output is the same whatever the engine, workers and memory per worker)."""
    for lvl, kd in enumerate(shape.kd_depths):
        if -(-shape.splats // 2**kd) <= domain_splats:
            return lvl
    return shape.leaf_level


def _auto_partitions(shape: TreeShape, row_bytes: int, engine: Engine, opts: EncodeOptions, level: int
                     ) -> tuple[str, int]:
    """The merge and partition level of a partitioned "auto" encode: the partitions are auto's merge domains
    (merge_domain_level), whatever the workers; where a domain does not fit a worker's memory, the grid at the
    grid's partition level (refused when the caller named auto)."""
    domain, largest, need = _merge_domains(shape, row_bytes, opts, AUTO_GROUPING_BYTES)
    if opts.lod_refiner is not None:  # the domains are the refinement's too
        _check_refined_need(shape, row_bytes, opts, engine, domain, largest, need)
    if need <= engine.memory_per_worker:
        partitions = 2 ** shape.kd_depths[domain]
        log.info("LOD merge auto%s, inside %s of at most %s splats and over the levels above them",
                 "" if opts.lod_merge is not None else " (the default)",
                 count(partitions, "partition"), f"{largest:,}")
        return "auto", domain
    message = (f"its merge domains (subtrees of at most {opts.lod_merge_domain_splats:,} splats) need "
               f"{math.ceil(need / 2**20):,} MiB per worker, more than the memory per worker "
               f"({engine.memory_per_worker // 2**20:,} MiB)")
    if opts.lod_merge is not None:
        raise UsageError(f"--lod-merge auto: {message}: give more --memory-per-worker or --lod-merge grid")
    log.warning("LOD merge grid: %s", message)
    return "grid", level


def _merge_domains(shape: TreeShape, row_bytes: int, opts: EncodeOptions, extra_bytes: int) -> tuple[int, int, int]:
    """The merge domains' tile level (merge_domain_level), the largest domain's splats, and the bytes a task needs to
    hold it (`extra_bytes` a splat beyond the grid's build)."""
    domain = merge_domain_level(shape, opts.lod_merge_domain_splats)
    largest = -(-shape.splats // 2 ** shape.kd_depths[domain])
    return domain, largest, largest * (row_bytes * PARTITION_MEMORY_FACTOR + extra_bytes)


def _refined_domain_too_big(opts: EncodeOptions, need: int, engine: Engine, fit: int = 0, at_least: bool = False
                            ) -> UsageError:
    """The refusal of a refined task over the memory per worker; `at_least`: `need` is a lower bound (the refiner's
    pairs not yet counted: _check_refined_need before the scene's sample)."""
    fit_part = (f" (the refiner's renders, targets and pair lists {math.ceil(fit / 2**20):,} MiB of it: a smaller "
                f"--lod-refine-size takes less)") if fit else ""
    return UsageError(f"--lod-refine by partitions refines each merge domain (a subtree of at most "
                      f"{opts.lod_merge_domain_splats:,} splats) in one task, which needs "
                      f"{'at least ' if at_least else ''}"
                      f"{math.ceil(need / 2**20):,} MiB per worker{fit_part}, more than the memory per worker "
                      f"({engine.memory_per_worker // 2**20:,} MiB): give more --memory-per-worker")


def refined_task_need(shape: TreeShape, row_bytes: int, opts: EncodeOptions, domain: int, largest: int,
                      build_need: int, refiner_at: Callable[[int], LodRefiner] | None = None) -> tuple[int, int]:
    """Bytes the largest refined task needs (a merge domain's, or an upper domain's: upper_domain_levels), and of
    them the refiner's own fit (LodRefiner's optional peak_bytes; 0 where it has none). A domain's fit follows its
    build in the same task, the build's temporaries freed: the tree held (its originals and merged levels, about
    twice the originals) and the fit's peak; an upper domain's task holds its roots (at most max_leaf_splats each) as
    its full detail, and the tiles above them. `refiner_at(level)`: the refiner whose peak_bytes counts a fit over
    one tile of that level (its pairs a pixel the scene's own there: _check_scene_pairs); else opts.lod_refiner's."""
    peak = getattr(opts.lod_refiner, "peak_bytes", None)
    if peak is None:
        return build_need, 0

    def peak_at(level: int) -> Callable[[int, int], int]:
        return peak if refiner_at is None else refiner_at(level).peak_bytes  # type: ignore[attr-defined]

    need, fit = build_need, 0
    if domain < shape.leaf_level:  # a partition of a single leaf has no merged level of its own
        fit = peak_at(domain)(largest, row_bytes)
        need = max(build_need, 2 * largest * row_bytes + fit)
    bottom = domain
    for top in upper_domain_levels(shape, domain, opts.lod_upper_domain_roots):
        roots = 2 ** (shape.kd_depths[bottom] - shape.kd_depths[top]) * shape.max_leaf_splats
        upper_fit = peak_at(top)(roots, row_bytes)
        if 2 * roots * row_bytes + upper_fit > need:
            need, fit = 2 * roots * row_bytes + upper_fit, upper_fit
        bottom = top
    return need, fit


def _check_refined_need(shape: TreeShape, row_bytes: int, opts: EncodeOptions, engine: Engine, domain: int,
                        largest: int, build_need: int) -> None:
    """Refused (UsageError, one line naming --memory-per-worker) where a refined task does not fit a worker. Before
    the scene's sample (the route's), a refiner that estimates its pairs from the scene (`scene_pairs`) counts
    none (`with_pairs_per_pixel(0)`: a lower bound, so that what cannot fit is refused before the route pass);
    _check_scene_pairs checks again with the scene's own once the sample is in."""
    estimates = getattr(opts.lod_refiner, "scene_pairs", None)
    if estimates is not None:
        opts = replace(opts, lod_refiner=opts.lod_refiner.with_pairs_per_pixel(0.0))  # type: ignore[union-attr]
    need, fit = refined_task_need(shape, row_bytes, opts, domain, largest, build_need)
    if need > engine.memory_per_worker:
        raise _refined_domain_too_big(opts, need, engine, fit, at_least=estimates is not None)


def _check_scene_pairs(shape: TreeShape, row_bytes: int, opts: EncodeOptions, engine: Engine, merge: str,
                       sample: SceneSample, frame: CameraFrame, up) -> None:
    """The refined tasks' need with the pairs a pixel the refiner estimates from the scene (`scene_pairs`: the
    route's sample of splats, every k-th, seen from the fits' own cameras, the whole scene's frame and up; for a
    merge domain's fit the most over the sample's kd cells of the domains' depth, for each tier of upper domains
    that of its level's depth, at most the refiner's constant); refused as _check_refined_need refuses. The sample
    is the same whatever the engine and workers, and so is the refusal. Without such a refiner, nothing to check."""
    refiner = opts.lod_refiner
    if getattr(refiner, "scene_pairs", None) is None:
        return
    domain, largest, build_need = _merge_domains(shape, row_bytes, opts,
                                                 AUTO_GROUPING_BYTES if merge == "auto" else 0)
    levels = [domain, *upper_domain_levels(shape, domain, opts.lod_upper_domain_roots)]
    depths = tuple(sorted({shape.kd_depths[lvl] for lvl in levels}))
    pairs = refiner.scene_pairs(sample.orient, shape.splats, frame, up, depths)  # type: ignore[union-attr]
    # the levels above the domains are fitted over their roots (merged splats, not the sample's originals): their
    # cells' estimate where it is under the refiner's constant, else the constant, as before the estimate
    upper = getattr(refiner, "default_pairs_per_pixel", math.inf)
    at = {lvl: refiner.with_pairs_per_pixel(  # type: ignore[union-attr]
        pairs[shape.kd_depths[lvl]] if lvl == domain else min(upper, pairs[shape.kd_depths[lvl]])) for lvl in levels}
    need, fit = refined_task_need(shape, row_bytes, opts, domain, largest, build_need, at.__getitem__)
    if need > engine.memory_per_worker:
        raise _refined_domain_too_big(opts, need, engine, fit)


def _domain_level(shape: TreeShape, row_bytes: int, engine: Engine, opts: EncodeOptions, extra_bytes: int) -> int:
    """The partition level of a refined partitioned encode: the merge domains, whatever the merge, so that each level
    is refined over the same splats whatever the engine, workers and memory per worker; refused (UsageError) where a
    domain, with its refiner's fit, does not fit a worker."""
    domain, largest, need = _merge_domains(shape, row_bytes, opts, extra_bytes)
    _check_refined_need(shape, row_bytes, opts, engine, domain, largest, need)
    return domain


def partition_level(shape: TreeShape, row_bytes: int, engine: Engine) -> int:
    """The tile level whose tiles are the partitions: the shallowest whose subtrees fit a worker's memory, and
    deep enough to give every worker a partition. The output does not depend on it."""
    fits = [lvl for lvl, kd in enumerate(shape.kd_depths)
            if shape.splats / 2**kd * row_bytes * PARTITION_MEMORY_FACTOR <= engine.memory_per_worker]
    level = fits[0] if fits else shape.leaf_level
    while level < shape.leaf_level and 2 ** shape.kd_depths[level] < engine.workers:
        level += 1
    return level


def _select_pivots(engine: Engine, scratch: Scratch, chunks: list[tuple[int, int]], splits: list,
                   axes: np.ndarray, ranks: np.ndarray, progress: Progress, stage: str) -> np.ndarray:
    """Exact radix selection: for every node, the key of rank `ranks[node]` (0-based) among its splats' keys."""
    nodes = len(axes)
    prefix = np.zeros(nodes, np.uint64)
    bits = np.zeros(nodes, np.int64)  # -1: resolved
    remaining = ranks.astype(np.int64).copy()
    candidates = np.full(nodes, np.iinfo(np.int64).max)
    pivots = np.zeros(nodes, np.uint64)
    while (bits >= 0).any():
        gather = (candidates <= max(1 << 16, GATHER_KEYS // nodes)) | (bits >= 64)
        results = engine.map(chunk_select, [(scratch, i, offset, splits, axes, prefix, bits, gather)
                                            for i, (offset, _) in enumerate(chunks)], stage, progress)
        for j in np.flatnonzero(bits >= 0):
            if gather[j]:
                keys = np.sort(np.concatenate([r[int(j)] for r in results]))
                pivots[j] = keys[remaining[j]]
                bits[j] = -1
                continue
            digits = np.concatenate([r[int(j)][0] for r in results])
            counts = np.concatenate([r[int(j)][1] for r in results])
            total = np.bincount(digits.astype(np.int64), weights=counts, minlength=1 << 16).astype(np.int64)
            ends = np.cumsum(total)
            digit = int(np.searchsorted(ends, remaining[j], side="right"))
            remaining[j] -= int(ends[digit] - total[digit])
            b = int(bits[j])
            prefix[j] = prefix[j] | (np.uint64(digit) << np.uint64(48 - b))
            bits[j] = b + 16
            candidates[j] = int(total[digit])
    return pivots


def _brackets(sample: tuple[np.ndarray, np.ndarray], node: np.ndarray, axes: np.ndarray, ranks: np.ndarray,
              sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Per node, a key interval that holds its key of rank `ranks[node]` unless the sample misleads: the sample's
    keys 4 standard deviations of a sampled median's rank either side. `node`: each sample's node. Returns the
    intervals' ends and the samples' keys, or None when the intervals would gather too many keys."""
    positions, index = sample
    nodes = len(axes)
    lo_key = np.zeros(nodes, np.uint64)
    hi_key = np.full(nodes, np.iinfo(np.uint64).max, np.uint64)
    keys = sort_keys(positions[np.arange(len(positions)), axes[node]], index)
    order = np.argsort(node, kind="stable")
    bounds = np.searchsorted(node[order], np.arange(nodes + 1))
    gathered = 0.0
    for j in range(nodes):
        n = int(bounds[j + 1] - bounds[j])
        if n < 64:
            gathered += sizes[j]
            continue
        at = ranks[j] * n / sizes[j]
        margin = 2.0 * math.sqrt(n) + 16.0  # the sampled rank's standard deviation is about sqrt(n) / 2
        a, b = max(math.floor(at - margin), 0), min(math.ceil(at + margin), n - 1)
        ks = np.partition(keys[order[bounds[j]:bounds[j + 1]]], [a, b])
        if a > 0:
            lo_key[j] = ks[a]
        if b < n - 1:
            hi_key[j] = ks[b]
        gathered += (b - a + 1) * sizes[j] / n
    return (lo_key, hi_key, keys) if gathered <= GATHER_KEYS else None


def _bracketed_pivots(engine: Engine, scratch: Scratch, chunks: list[tuple[int, int]], splits: list, axes: np.ndarray,
                      sizes: np.ndarray, sample: tuple[np.ndarray, np.ndarray], sample_node: np.ndarray,
                      routed: bool, progress: Progress
                      ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray] | None:
    """The exact median keys of every node in one pass over the centres, the centre boxes of the nodes one level
    down and the samples' nodes there, when the sample's brackets hold every median; None otherwise (the radix
    selection then decides)."""
    ranks = sizes // 2
    brackets = _brackets(sample, sample_node, axes, ranks, sizes)
    if brackets is None:
        return None
    lo_key, hi_key, sample_keys = brackets
    nodes = len(axes)
    results = engine.map(chunk_bracket, [(scratch, i, offset, splits, axes, lo_key, hi_key, routed)
                                         for i, (offset, _) in enumerate(chunks)], "split", progress)
    below = np.sum([r[0] for r in results], axis=0)
    side_lo = np.min([r[1][:, 0] for r in results], axis=0)  # [below/above][node]
    side_hi = np.max([r[1][:, 1] for r in results], axis=0)
    node = np.concatenate([r[2] for r in results])
    keys = np.concatenate([r[3] for r in results])
    centres = np.concatenate([r[4] for r in results])
    order = np.lexsort((keys, node))
    node, keys, centres = node[order], keys[order], centres[order]
    bounds = np.searchsorted(node, np.arange(nodes + 1))
    pivots = np.zeros(nodes, np.uint64)
    lo = np.full((2 * nodes, 3), np.inf, np.float32)
    hi = np.full((2 * nodes, 3), -np.inf, np.float32)
    for j in range(nodes):
        r = int(ranks[j] - below[j])
        a, b = bounds[j], bounds[j + 1]
        if not 0 <= r < b - a:
            return None
        pivots[j] = keys[a + r]
        for child, side, part in ((2 * j, 0, centres[a:a + r]), (2 * j + 1, 1, centres[a + r:b])):
            lo[child] = np.minimum(side_lo[side, j], part.min(axis=0) if len(part) else np.inf)
            hi[child] = np.maximum(side_hi[side, j], part.max(axis=0) if len(part) else -np.inf)
    return pivots, (lo, hi), 2 * sample_node + (sample_keys >= pivots[sample_node])


def _top_splits(engine: Engine, scratch: Scratch, chunks: list[tuple[int, int]], depth: int, splats: int,
                bounds: tuple[np.ndarray, np.ndarray], sample: tuple[np.ndarray, np.ndarray], progress: Progress
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The kd splits above the partitions (per level: each node's axis and median key), exact. Each level is one
    pass over the centres when the sample brackets every median (the pass also gives the next level's boxes), and
    a box pass plus radix selection rounds when it does not."""
    splits: list[tuple[np.ndarray, np.ndarray]] = []
    sizes = np.array([splats], np.int64)
    boxes: tuple[np.ndarray, np.ndarray] | None = (bounds[0][None], bounds[1][None])  # the root's: from the scan
    sample_node = np.zeros(len(sample[0]), np.int64)
    boxes_from_bracket = False  # the level above was a bracketed pass (which saved each chunk's nodes)
    for d in range(depth):
        nodes = 2 ** d
        if boxes is None:
            found = engine.map(chunk_boxes, [(scratch, i, offset, splits, nodes)
                                             for i, (offset, _) in enumerate(chunks)], "split", progress)
            boxes = np.min([b[0] for b in found], axis=0), np.max([b[1] for b in found], axis=0)
        lo, hi = boxes
        axes = np.array([split_axis(lo[j], hi[j]) for j in range(nodes)], np.int64)
        bracketed = _bracketed_pivots(engine, scratch, chunks, splits, axes, sizes, sample, sample_node,
                                      routed=boxes_from_bracket, progress=progress)
        boxes_from_bracket = bracketed is not None
        if bracketed is not None:
            pivots, boxes, sample_node = bracketed
        else:
            pivots, boxes = _select_pivots(engine, scratch, chunks, splits, axes, sizes // 2, progress, "split"), None
            sample_node = kd_route(*sample, [*splits, (axes, pivots)])
        splits.append((axes, pivots))
        sizes = np.stack([sizes // 2, sizes - sizes // 2], 1).reshape(-1)
    return splits


def _scan(engine: Engine, rows, spans: list[tuple[int, int]], scratch: Scratch, progress: Progress,
          ply_path: str | None, drop_invalid: bool
          ) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Stage 1, the scan: each chunk's kept rows as a range of input indices, the centres' box and the split sample
    (centres and their input indices). `ply_path`: a PLY read by rows, whose invalid rows are reported here for
    the whole file at once (ply.check_rows)."""
    stride = max(1, rows.rows // SPLIT_SAMPLE)
    scans = engine.map(scan_chunk, [(rows, i, s, e, scratch, stride) for i, (s, e) in enumerate(spans)], "read",
                       progress)
    stats = RowStats()
    for _, st, _, _, _ in scans:
        stats = stats + st
    if ply_path is not None:
        check_rows(ply_path, stats, drop_invalid)
    kept = np.array([s[0] for s in scans], np.int64)
    splats = int(kept.sum())
    if splats == 0:
        raise UsageError("the input holds no splats; nothing to encode")
    if splats >= 1 << 32:
        raise UsageError(f"{splats} splats: a partitioned encode handles at most 2^32 - 1")
    offsets = np.concatenate([[0], np.cumsum(kept)])
    chunks = [(int(offsets[i]), int(offsets[i + 1])) for i in range(len(spans))]
    lo = np.min([s[2] for s in scans], axis=0)
    hi = np.max([s[3] for s in scans], axis=0)
    split_sample = (np.concatenate([s[4] for s in scans]),
                    np.concatenate([offsets[i] + stride * np.arange(len(s[4]), dtype=np.int64)
                                    for i, s in enumerate(scans)]))
    return chunks, lo, hi, split_sample


def _ply_paths(rows) -> str | None:
    """The PLY input(s) read by rows, whose invalid rows the scan reports (one message naming them all), or None."""
    parts = rows.parts if isinstance(rows, ConcatRows) else [rows]
    paths = [p.path for p in parts if isinstance(p, PlyRows)]
    return " + ".join(paths) if paths else None


def encode_partitioned(rows, writer: SceneWriter, opts: EncodeOptions, engine: Engine, scratch: Scratch,
                       progress: Progress = no_progress, source_name: str | None = None,
                       out_name: str | None = None, drop_invalid: bool = False, edits: Pipeline | None = None):
    """Encode the rows of an input (PlyRows, ArrayRows, SpilledRows) through a writer on an engine, edited by
    `edits` (chunk by chunk, EditedRows)."""
    source_rows = rows
    if edits and not edits.per_splat:
        raise UsageError("an edit of the whole scene (--filter-density) cannot run chunk by chunk: a partitioned "
                         "encode applies only edits of one splat at a time")
    if edits:
        rows = EditedRows(rows, edits)
    formats, chunk_order = plan_formats(opts)
    if not opts.lod:
        raise UsageError("a partitioned encode needs LOD (--no-lod keeps the whole scene in one tile)")
    merge = opts.resolved_lod_merge(in_memory=False)
    if merge not in PARTITIONED_MERGES:
        # The cost merge groups a whole tree level at once; partitions build their subtrees apart (issue 31).
        raise UsageError(f"--lod-merge {merge} runs only in-process (one machine, the scene in memory): a "
                         f"partitioned encode merges with {' or '.join(PARTITIONED_MERGES)}")
    check_codebook_option(opts, rows.sh_degree, source_name)
    sh_degree = opts.sh_degree if opts.sh_degree is not None else rows.sh_degree
    sh_degree = min(sh_degree, rows.sh_degree)
    row_bytes = routed_row_bytes(sh_degree)
    # Chunks small enough for a worker's memory and numerous enough to keep every worker busy in the passes.
    chunk_rows = min(engine.memory_per_worker // (8 * row_bytes), -(-rows.rows // (4 * engine.workers)))
    chunk_rows = int(min(1 << 22, max(1 << 16, chunk_rows)))
    spans = [(s, min(s + chunk_rows, rows.rows)) for s in range(0, rows.rows, chunk_rows)]

    chunks, lo, hi, split_sample = _scan(engine, rows, spans, scratch, progress,
                                         _ply_paths(source_rows),
                                         drop_invalid)
    splats = chunks[-1][1]
    bounds = Box(tuple(float(v) for v in lo), tuple(float(v) for v in hi))

    shape = TreeShape.of(splats, opts.max_leaf_splats, opts.reduction)
    level = partition_level(shape, row_bytes, engine)
    if merge == "auto":
        merge, level = _auto_partitions(shape, row_bytes, engine, opts, level)
    elif opts.lod_refiner is not None:
        level = _domain_level(shape, row_bytes, engine, opts, 0)
    kd = shape.kd_depths[level]
    partitions = 2 ** kd
    if merge == "grid":
        # The auto merge says its partitions (_auto_partitions); the grid said none, so `--workers 2
        # --memory-per-worker 20MB` on guitar (8 partitions) read as if nothing had been split.
        log.info("LOD merge grid, inside %s of at most %s splats", count(partitions, "partition"),
                 f"{-(-splats // partitions):,}")
    splits = _top_splits(engine, scratch, chunks, kd, splats, (lo, hi), split_sample, progress)
    del split_sample

    choice = codebook_choice(opts, sh_degree)
    routed = engine.map(route_chunk, [(rows, i, s, e, chunks[i][0], splits, partitions, scratch, sh_degree, splats,
                                       choice != "off", palette_planes(formats))
                                      for i, (s, e) in enumerate(spans)], "route", progress)
    chunk_counts = [r[0] for r in routed]
    engine.map_behind(delete_scratch, [(scratch, [f"pos/{i}", *(f"node/{d}/{i}" for d in range(kd))])
                                       for i in range(len(spans))], "cleanup")
    sample = SceneSample.join([r[1] for r in routed])
    del routed
    # The chunk order stays morton where the in-memory engine may keep an input's order (plan_encode): that needs
    # the whole scene in one tile, which a partitioned encode never has for more than one leaf of splats.
    scene, sample = plan_scene(opts, formats, chunk_order, sh_degree, sample, splats, bounds,
                               scene_name(opts, source_name, out_name), progress, merge, tree=shape.tiles > 1)
    ctx = scene.context
    payloads = writer.payload_writer()
    codebook_entry = encode_codebook(ctx.codebook, ctx, payloads) if ctx.codebook is not None else None

    refiner = opts.lod_refiner
    # where every refined fit's cameras are placed (the domains' and the levels above's): the whole scene's frame,
    # from the scene's sample of centres (every centre up to 2M: the in-memory encode's frame)
    frame = CameraFrame.of(sample.positions) if refiner is not None else None
    if frame is not None:  # the refined tasks' memory with the scene's own pairs a pixel, before any task runs
        _check_scene_pairs(shape, row_bytes, opts, engine, merge, sample, frame, scene.up)
    # the refiner for the fits that run at once: the partitions (at most one per worker); each tier of upper domains
    # asks again in _upper_tiles
    partition_refiner = _for_fits(refiner, min(engine.workers, partitions))
    results = engine.map(build_partition, [(p, level, shape, chunk_counts, scratch, ctx, payloads,
                                            engine.threads_per_task, level > 0, merge, partition_refiner, scene.up,
                                            frame)
                                           for p in range(partitions)],
                         "tiles", progress, heavy=True, task_progress=True)
    entries = [e for r in results for e in r.entries]
    engine.map_behind(delete_scratch, [(scratch, [f"route/{i}"]) for i in range(len(spans))], "cleanup")
    upper, above = _upper_tiles(engine, scratch, shape, level, [r.root_splats for r in results], ctx, payloads,
                                progress, merge, refiner if REFINE_UPPER_LEVELS else None, scene.up,
                                opts.lod_upper_domain_roots, frame)
    entries += upper
    if level > 0:
        refined_roots = refiner is not None and level < shape.leaf_level
        engine.map_behind(delete_scratch, [(scratch, [f"originals/{p}"] + ([f"refined/{shape.tile_id(level, p)}"]
                                                                          if refined_roots else []))
                                           for p in range(partitions)], "cleanup")
    records = [r.refinement for r in results if r.refinement is not None]
    if records or above is not None:
        scene = replace(scene, lod_refinement=domains_record(records, above))
        _log_domains(records, above)
    elif refiner is not None:
        log.info("LOD refinement: the tree is one tile (%s splats, under --max-leaf-splats), with no merged level; "
                 "nothing refined", f"{splats:,}")
    m = build_manifest(scene, sample.camera(scene.up, scene.camera_azimuth_deg), sorted(entries, key=lambda t: t.id),
                       codebook_entry)
    engine.settle()
    return write_scene_manifest(writer, m, opts.page_tiles, opts.page_levels, opts.compact_table,
                                opts.short_digests, short_names=ctx.short_names,
                                relative_boxes=opts.relative_boxes)


# The levels above the partitions refined (refine_upper) in a refined partitioned encode; False leaves them as built
# (a switch for the measurement that chose it: BENCHMARKS.md, "Refining the merged levels by partitions").
REFINE_UPPER_LEVELS = True


def _log_domains(records: list[LodRefinement], above: LodRefinement | None) -> None:
    """One line: what each refined level kept, and in how many of the merge domains (lod_refine.domains_record
    folds them into the manifest's record)."""
    counts: dict[int, dict[str, int]] = {}
    for r in records:
        for lv in r.levels:
            counts.setdefault(lv.level, {}).setdefault(lv.kept, 0)
            counts[lv.level][lv.kept] += 1
    parts = [f"level {lv.level} {lv.kept} (above the partitions)" for lv in (above.levels if above else ())]
    parts += [f"level {level} " + ", ".join(f"{k} in {c}" for k, c in sorted(kept.items()))
              for level, kept in sorted(counts.items())]
    log.info("LOD refinement by %s: kept %s", count(len(records), "merge domain"), "; ".join(parts))


def _for_fits(refiner: LodRefiner | None, fits: int) -> LodRefiner | None:
    """The refiner to run when `fits` fits run at once (its `for_concurrent_fits`, where it has one: lod_refine)."""
    share = getattr(refiner, "for_concurrent_fits", None)
    return share(fits) if share else refiner


def _upper_tiles(engine: Engine, scratch: Scratch, shape: TreeShape, level: int, root_splats: list[int],
                 ctx: TileContext, payloads, progress: Progress, merge: str = "grid",
                 refiner: LodRefiner | None = None, up: tuple[float, float, float] | None = None,
                 roots_per_domain: int = EncodeOptions.lod_upper_domain_roots,
                 frame: CameraFrame | None = None) -> tuple[list[TileEntry], LodRefinement | None]:
    """The tiles above the partitions, level by level (in batches of tiles, for the client's memory; "auto": a
    level at once, grouped by merge_level in a task per upper domain, upper_domain_levels), and where `refiner` is
    given their levels refined tier by tier, a task per upper domain (refine_upper), before any of them is encoded,
    with that refinement's record."""
    entries: list[TileEntry] = []
    upper_ids: list[int] = []
    kd_p = shape.kd_depths[level]
    tops = upper_domain_levels(shape, level, roots_per_domain)
    maps = [np.arange(n) for n in root_splats]  # per partition: its root's splats -> the current ancestor's
    for lvl in range(level - 1, -1, -1):
        per_tile = 2 ** (kd_p - shape.kd_depths[lvl])  # partitions under each tile of this level
        per_child = 2 ** (kd_p - shape.kd_depths[lvl + 1])
        tiles_here = 2 ** shape.kd_depths[lvl]
        above = shape.leaf_level - 1 - lvl  # levels above the first merged one (lod.viewing_scale_px)
        batch_tiles = tiles_here if merge == "auto" else max(1, UPPER_BATCH_SPLATS // shape.max_leaf_splats)
        for first in range(0, tiles_here, batch_tiles):
            batch = range(first, min(tiles_here, first + batch_tiles))
            if merge == "auto":
                top = _upper_domain_of(tops, lvl)  # a task per upper domain: its tiles of this level grouped at once
                domains = range(2 ** shape.kd_depths[top])
                found = engine.map(merge_level, [(scratch, shape, lvl, engine.threads_per_task, top, d)
                                                 for d in domains],
                                   "upper", progress, heavy=True)
                merged = dict(enumerate(m for ms in found for m in ms))  # domains in kd order: the level's tiles
            else:
                merged = dict(zip(batch, engine.map(merge_children, [(scratch, shape, lvl, j) for j in batch],
                                                    "upper", progress), strict=True))
            parts = [p for j in batch for p in range(j * per_tile, (j + 1) * per_tile)]
            for p in parts:
                j = p // per_tile
                g, mass, assign, offsets, kids = merged[j]
                maps[p] = assign[offsets[p // per_child - j * shape.fan(lvl)] + maps[p]]
            ext = engine.map(partition_extremes, [(scratch, p, maps[p], merged[p // per_tile][0].positions,
                                                   len(merged[p // per_tile][0])) for p in parts], "upper", progress)
            state = {}
            for j in batch:
                g = merged[j][0]
                size = len(g)
                counts = np.zeros(size, np.int64)
                far = np.full(size, -np.inf)
                near = np.full(size, np.inf)
                for p, (present, c, f, n) in zip(parts, ext, strict=True):
                    if p // per_tile == j:
                        counts[present] += c
                        far[present] = np.maximum(far[present], f)
                        near[present] = np.minimum(near[present], n)
                child_error = max(k.geometric_error for k in merged[j][4])
                errors, error = tile_error_first(g, counts, far, near, child_error)
                state[j] = (counts, far, near, errors, error, child_error)
            sums = engine.map(partition_sums, [(scratch, p, maps[p], len(merged[p // per_tile][0]),
                                                tile_viewing_blur(state[p // per_tile][4], state[p // per_tile][5],
                                                                  above))
                                               for p in parts],
                              "upper", progress)
            for j in batch:
                g, mass, _, _, kids = merged[j]
                leaf_parts = [lp for p, s in zip(parts, sums, strict=True) if p // per_tile == j for lp in s]
                counts, far, near, errors, error, child_error = state[j]
                error = finish_tile_appearance(g, counts, far, near, errors, error, fold_leaf_sums(leaf_parts, len(g)),
                                               child_error, above)
                lo, hi, c, r = interior_bounds(g, kids)
                tid = shape.tile_id(lvl, j)
                _save_tile(scratch, Tile(tid, lvl, [k.id for k in kids], g, error, lo, hi, c, r), mass)
            del merged, state, sums, ext
            if refiner is not None:  # encoded once refined, below
                upper_ids += [shape.tile_id(lvl, j) for j in batch]
                continue
            entries += engine.map(encode_saved_tile, [(scratch, shape.tile_id(lvl, j), ctx, payloads)
                                                      for j in batch], "upper", progress)
    record = None
    if refiner is not None and upper_ids:
        # tier after tier (upper_domain_levels), each upper domain in its own task against its roots as refined
        bottom, tiers = level, []
        for top in tops:
            domains = range(2 ** shape.kd_depths[top])
            fits = min(engine.workers, len(domains))
            tier_refiner = _for_fits(refiner, fits)
            # the partitions' roots as refined (a partition that is a leaf: its originals); a higher tier's roots:
            # the tier below's tops, refined in place
            prefix = "refined" if bottom == level and level < shape.leaf_level else "tile"
            records = engine.map(refine_upper, [(scratch, shape, bottom, top, d, tier_refiner, up, prefix, frame)
                                                for d in domains], "refine-upper", progress, heavy=True,
                                 task_progress=True)
            tiers.append(records)
            bottom = top
        # each level once, the root's tier first (lod_refine.domains_record lists `above`'s levels first), a tier of
        # several domains as the partitions' (kept where any kept it, the domains' mean validation MSE)
        for records in reversed(tiers):
            record = records[0] if len(records) == 1 and record is None else domains_record(records, record)
        entries += engine.map(encode_saved_tile, [(scratch, tid, ctx, payloads) for tid in upper_ids], "upper",
                              progress)
    return entries, record


def refine_upper(scratch: Scratch, shape: TreeShape, level: int, top: int, domain: int, refiner: LodRefiner,
                 up: tuple[float, float, float] | None, roots_prefix: str, frame: CameraFrame | None,
                 report: Callable[[float], None]) -> LodRefinement:
    """The levels top..level-1 of one upper domain (tile `domain` of level `top`; upper_domain_levels) refined in
    one task (lod.md 6, "The refinement by partitions"): the originals are not here (the whole scene), so their full
    detail is the domain's roots at `level` as refined (under `roots_prefix` in scratch: the partitions' roots, or
    the tier below's tops), the finest level this task holds (at most max_leaf_splats a root), the subtree above them
    cut with those roots as its leaves; the cameras placed by the whole scene's `frame`. The refined tiles go back to
    scratch, to be encoded (and a top to be the next tier's root)."""
    tiles: dict[int, Tile] = {}
    masses: dict[int, np.ndarray] = {}
    for lvl in range(top, level + 1):
        for j in _tiles_under(shape, top, domain, lvl):
            tid = shape.tile_id(lvl, j)
            tiles[tid], masses[tid] = _load_tile(scratch, tid)
    roots = [tid for tid, t in tiles.items() if t.level == level]
    for tid in roots:  # the leaves of the tree refined here, as refined
        root = _load_tile(scratch, tid, roots_prefix)[0] if roots_prefix != "tile" else tiles[tid]
        tiles[tid] = replace(root, children=[])
    # the bounds above the roots from the roots as refined (a tier's tops refined after the tier above was merged;
    # the partitions' roots were saved with their refined bounds, so there this is the merge's own result)
    for tid in sorted((t for t in tiles if tiles[t].level < level), reverse=True):
        t = tiles[tid]
        lo, hi, c, r = interior_bounds(t.gaussians, [tiles[k] for k in t.children])
        tiles[tid] = replace(t, box_min=lo, box_max=hi, sphere_center=c, sphere_radius=r)
    g = Gaussians.concatenate([tiles[tid].gaussians for tid in sorted(roots)])

    def refine_progress(stage: str, fraction: float) -> None:
        if stage == "refine":
            report(fraction)

    refined, record = refine_subtree(g, tiles, up, refiner, refine_progress, frame)
    for tid, t in refined.items():
        if t.level < level:
            _save_tile(scratch, t, masses[tid])
    return record
