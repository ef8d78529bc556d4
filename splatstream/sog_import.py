"""A PlayCanvas streamed SOG's whole LOD tree as a tree of ours (format_spec/foreign_formats.md, "Streamed SOG
into our tree"), so our client streams it coarse to fine (`view`: encode_streamed_sog, in memory) and `encode`
writes it as a scene with their levels kept (encode_tree_to; `encode --rebuild-lod` reads their finest level and
builds our own tree instead).

The route: convert on the fly into our tile tree and encode that (in memory for `view`), rather than teaching the
client a second tree format. Our client's selection, residency and hole-free refinement all work on one tree
shape (REPLACE tiles with bounds and geometric errors); a streamed SOG's levels map onto that shape without loss
of any splat, and the encoder's formats then apply to their splats as to ours.

The mapping (the inverse of writers/sog_lod.py): with K levels, our tile at depth d holds SOG level K - 1 - d of
the leaves below one node of their tree at depth d (a node at depth d, or a leaf above it repeated down a chain);
so our root holds their coarsest level, our leaves (depth K - 1) their level 0. Children of a tile together hold
the next finer level of the same leaves: REPLACE holds. Their tree has no errors our client can use (the engine
picks levels by distance), so each interior tile's geometric error is measured as our encoder measures its own
(lod.md 3): every original (level 0) of the tile's leaves, or an even sample of them, is taken as a member of its
nearest splat of the tile, and the tile's error is the error statistic of those members' Hausdorff bounds; then
made non-increasing towards the leaves. Bounds are the 3-sigma extents, parents holding their children.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np

from .encode.driver import encode_built_tree
from .encode.local import encode_in_memory
from .encode.options import EncodeOptions, Progress, no_progress
from .errors import InputError
from .format.manifest import Manifest
from .gaussians import Gaussians
from .io import screen_gaussians
from .lod import Tile, extent_bounds, interior_bounds, merge_errors, original_reach, tile_error
from .readers.sog import LodNode, StreamedSog, read_streamed_sog
from .store import MemoryStore

# Members sampled per tile for its error: the statistic is a quantile, which a few thousand members fix well,
# and the nearest-splat search costs members x splats.
ERROR_SAMPLE = 8192
NEAREST_BLOCK_BYTES = 32 << 20


@dataclass
class _Node:
    depth: int
    splats: Gaussians
    owner: np.ndarray  # per splat, the index (among the node's leaves) of the leaf it came from
    originals: Gaussians  # level 0 of the node's leaves
    original_owner: np.ndarray
    children: list[_Node]


def _nearest(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest centre of every point (squared Euclidean), in blocks of bounded memory."""
    if len(centres) == 1:
        return np.zeros(len(points), np.int64)
    p = points.astype(np.float64)
    c = centres.astype(np.float64)
    cc = (c ** 2).sum(axis=1)
    out = np.empty(len(p), np.int64)
    step = max(1, NEAREST_BLOCK_BYTES // (8 * len(c)))
    for i in range(0, len(p), step):
        d = p[i:i + step] @ c.T
        d *= -2.0
        d += cc[None, :]
        out[i:i + step] = np.argmin(d, axis=1)
    return out


def _level_splats(sog: StreamedSog, leaves: list[LodNode], level: int) -> tuple[Gaussians, np.ndarray]:
    """The splats of `level` of these leaves, or of the nearest finer level that has any (so no tile is empty),
    with the index of the leaf each came from."""
    for lv in range(level, -1, -1):
        parts = [(k, sog.splats[id(leaf)][lv]) for k, leaf in enumerate(leaves) if lv in sog.splats[id(leaf)]]
        if parts:
            owner = np.concatenate([np.full(len(g), k, np.int64) for k, g in parts])
            return Gaussians.concatenate([g for _, g in parts]), owner
    return Gaussians.empty(), np.zeros(0, np.int64)


def tree_tiles(sog: StreamedSog, progress: Progress | None = None) -> list[Tile]:
    """Our tile tree of a streamed SOG: breadth-first, root first, with bounds and geometric errors. `progress`
    hears stage "tree" as the tiles' errors are measured, by tile: that search is the slow part (playbot's 13
    tiles, 500,000 splats: about 10 s on a busy 2-core machine, with nothing shown before)."""
    progress = progress or no_progress
    last = sog.levels - 1

    def build(node: LodNode, depth: int) -> _Node | None:
        leaves = node.leaves()
        splats, owner = _level_splats(sog, leaves, last - depth)
        if len(splats) == 0:
            return None
        originals, original_owner = _level_splats(sog, leaves, 0)
        kids: list[_Node] = []
        if depth < last:
            below = node.children if node.children else (node,)
            kids = [k for k in (build(child, depth + 1) for child in below) if k is not None]
        return _Node(depth, splats, owner, originals, original_owner, kids)

    progress("tree", 0.0)
    root = build(sog.tree, 0)
    if root is None:
        raise InputError("<streamed SOG>", "tree", "holds no splats")
    # Bottom-up: bounds and errors (a parent's need its children's); children kept aside until numbered.
    kids_of: dict[int, list[Tile]] = {}
    total, done = _count(root), 0

    def finish(n: _Node) -> Tile:
        nonlocal done
        kids = [finish(k) for k in n.children]
        if not kids:
            lo, hi, centre, radius = extent_bounds(n.splats)
            tile = Tile(-1, n.depth, [], n.splats, 0.0, lo, hi, centre, radius)
        else:
            lo, hi, centre, radius = interior_bounds(n.splats, kids)
            tile = Tile(-1, n.depth, [], n.splats, max(_error(n), max(k.geometric_error for k in kids)),
                        lo, hi, centre, radius)
        kids_of[id(tile)] = kids
        done += 1
        progress("tree", done / total)
        return tile

    # Breadth-first ids (lod.md 1).
    order: list[Tile] = []
    queue = [finish(root)]
    while queue:
        order.extend(queue)
        queue = [k for t in queue for k in kids_of[id(t)]]
    ids = {id(t): i for i, t in enumerate(order)}
    return [replace(t, id=ids[id(t)], children=[ids[id(k)] for k in kids_of[id(t)]]) for t in order]


def _count(n: _Node) -> int:
    return 1 + sum(_count(k) for k in n.children)


def _error(n: _Node) -> float:
    """The tile's geometric error from its originals taken as members of their nearest splat (lod.md 3), searched
    among the splats of the original's own leaf (their regions are disjoint; all of the tile's if it has none)."""
    rows = np.arange(len(n.originals))
    if len(rows) > ERROR_SAMPLE:
        rows = np.linspace(0, len(rows) - 1, ERROR_SAMPLE).astype(np.int64)
    originals, owner = n.originals.subset(rows), n.original_owner[rows]
    members = np.empty(len(originals), np.int64)
    for leaf in np.unique(owner):
        mine = np.flatnonzero(owner == leaf)
        candidates = np.flatnonzero(n.owner == leaf)
        if not len(candidates):
            candidates = np.arange(len(n.splats))
        members[mine] = candidates[_nearest(originals.positions[mine], n.splats.positions[candidates])]
    errors = merge_errors(originals.positions, original_reach(originals), n.splats, members)
    return tile_error(errors, np.bincount(members, minlength=len(n.splats)))


def encode_streamed_sog(path: str | os.PathLike, opts: EncodeOptions | None = None,
                        progress: Progress | None = None) -> MemoryStore:
    """Read a streamed SOG whole and encode it in memory with its own LOD tree."""
    progress = progress or no_progress
    return encode_tree(read_tree(path, progress), os.fspath(path), opts, progress)


def read_tree(path: str | os.PathLike, progress: Progress | None = None) -> StreamedSog:
    """A streamed SOG read whole, every level's splats screened as any input's are."""
    progress = progress or no_progress
    label = os.fspath(path)
    progress("read", 0.0)
    sog = read_streamed_sog(path)
    for leaf_splats in sog.splats.values():
        for level, g in leaf_splats.items():
            leaf_splats[level] = screen_gaussians(g, label)
    if sog.environment is not None and len(sog.environment):
        # An environment unit (a sky, drawn at every distance) has no place in a REPLACE tree without copying it
        # into every tile of every cut.
        raise InputError(label, "environment", f"an environment unit ({len(sog.environment)} splats) cannot be "
                         "streamed as a tree; convert the scene to a single file first (convert reads it)")
    progress("read", 1.0)
    return sog


def encode_tree(sog: StreamedSog, label: str, opts: EncodeOptions | None = None,
                progress: Progress | None = None) -> MemoryStore:
    """Encode a streamed SOG's tree (screened splats) in memory as our tree: what `view` streams (also RAD's,
    laid out as a streamed SOG by rad_import)."""
    progress = progress or no_progress
    g, opts, tiles = _tree_input(sog, opts, progress)
    return encode_in_memory(g, opts, progress, name=label, tiles=tiles)


def encode_tree_to(sog: StreamedSog, out_dir: str | os.PathLike, label: str, opts: EncodeOptions | None = None,
                   progress: Progress | None = None) -> Manifest:
    """Encode a streamed SOG's tree (screened splats) into a scene directory (or fsspec URL) as our tree, their
    levels kept: what `encode` does with a streamed SOG or a .rad."""
    g, opts, tiles = _tree_input(sog, opts, progress)
    return encode_built_tree(g, tiles, out_dir, opts, progress, label)


def _tree_input(sog: StreamedSog, opts: EncodeOptions | None,
                progress: Progress | None) -> tuple[Gaussians, EncodeOptions, list[Tile]]:
    """The splats (the leaves' together), the options (leaf size and reduction those of their tree) and our tiles
    of a streamed SOG's tree."""
    tiles = tree_tiles(sog, progress)
    leaves = [t for t in tiles if not t.children]
    g = Gaussians.concatenate([t.gaussians for t in leaves])
    levels = max(t.level for t in tiles) + 1
    per_level = [sum(len(t.gaussians) for t in tiles if t.level == d) for d in range(levels)]
    reduction = float(np.exp(np.mean(np.log(np.array(per_level[1:], float) / np.array(per_level[:-1], float))))) \
        if levels > 1 else 2.0
    base = opts if opts is not None else EncodeOptions(lod=True)
    return g, replace(base, lod=True, max_leaf_splats=max(len(t.gaussians) for t in leaves), reduction=reduction,
                      imported_tree=True), tiles
