"""A Spark 2 RAD file's LoD tree as a tree of ours (format_spec/foreign_formats.md, "RAD into our tree"), so our
client streams it coarse to fine (`view`, in memory) and `encode` writes it as a scene with its levels kept
(sog_import.encode_tree_to; `encode --rebuild-lod` reads its finest level and builds our own tree instead).
`convert` reads its finest level (readers/rad.read_rad).

The route is sog_import's: RAD's tree of splats is laid out as a streamed SOG in memory (a root over leaves, each
leaf with one row set per level) and converted and encoded by sog_import, so both foreign trees reach our client
through one conversion (bounds, geometric errors measured as our encoder measures its own, REPLACE).

The mapping: RAD's tree is one of splats, ours one of tiles. With a cut at splat depth d meaning the splats at
depth d plus the leaves above it (what Spark draws once it has refined everything above d):

* k is the shallowest depth whose cut holds at least GROUP_MIN splats (a single-splat root, as our export and
  Spark's builders write, is never a tile of its own); depths above k are dropped.
* Our root tile holds the cut at depth k. Its children are groups of consecutive depth-k splats (file order,
  which Spark's builders and our export keep spatially coherent) with their subtrees, a group closed once its
  finest level holds GROUP_SPLATS splats; leaves above k go to the group of their nearest depth-k splat.
* Below the root, a group is a chain of tiles, the one at depth j holding the group's cut at depth k + j.

So our cut at depth j is RAD's cut at depth k + j, splat for splat: a RAD written by export-rad (k = 1: its
root splat stands for our root tile) comes back with every level of the original tree.
"""
from __future__ import annotations

import os

import numpy as np

from .encode.options import EncodeOptions, Progress, no_progress
from .errors import InputError
from .io import screen_gaussians
from .readers.rad import read_rad_tree
from .readers.sog import LodNode, StreamedSog
from .sog_import import encode_tree
from .store import MemoryStore
from .writers.rad import RadTree, nearest

GROUP_MIN = 16
GROUP_SPLATS = 4096


def _top_depth(tree: RadTree) -> int:
    levels = tree.levels()
    for d in range(levels):
        if len(tree.cut(d)) >= GROUP_MIN:
            return d
    return levels - 1


def _descendants_group(tree: RadTree, k: int) -> np.ndarray:
    """Per splat, the index (in file order) of its depth-k ancestor or itself, -1 above k."""
    group = np.full(len(tree.splats), -1, np.int64)
    heads = np.flatnonzero(tree.depth == k)
    group[heads] = np.arange(len(heads))
    frontier = heads
    while len(frontier):
        parents = frontier[tree.child_count[frontier] > 0]
        if not len(parents):
            break
        c = tree.child_count[parents].astype(np.int64)
        kids = np.repeat(tree.child_start[parents].astype(np.int64) - np.concatenate([[0], np.cumsum(c)[:-1]]), c) \
            + np.arange(int(c.sum()))
        group[kids] = np.repeat(group[parents], c)
        frontier = kids
    return group


def rad_as_streamed_sog(tree: RadTree) -> StreamedSog:
    """RAD's splat tree as a streamed SOG in memory (see the module's docstring)."""
    levels = tree.levels()
    k = _top_depth(tree)
    head = _descendants_group(tree, k)
    heads = np.flatnonzero(tree.depth == k)
    shallow = np.flatnonzero((tree.depth < k) & (tree.child_count == 0))
    if len(shallow):
        head[shallow] = nearest(tree.splats.positions[shallow].astype(np.float64),
                                tree.splats.positions[heads].astype(np.float64))
    leaf_rows = np.flatnonzero(tree.child_count == 0)
    # Consecutive heads into groups of about GROUP_SPLATS finest splats.
    finest = np.bincount(head[leaf_rows], minlength=len(heads))
    group_of_head = np.zeros(len(heads), np.int64)
    size, g = 0, 0
    for i, n in enumerate(finest):
        group_of_head[i] = g
        size += int(n)
        if size >= GROUP_SPLATS:
            g, size = g + 1, 0
    group = np.where(head >= 0, group_of_head[np.maximum(head, 0)], -1)
    depth = tree.depth
    leaf = tree.child_count == 0
    nodes, splats = [], {}
    for gi in range(int(group.max()) + 1):
        mine = group == gi
        if not mine.any():
            continue
        per_level = {}
        for level in range(levels - k):
            d = levels - 1 - level
            rows = np.flatnonzero(mine & ((depth == d) | ((depth < d) & leaf)))
            if len(rows):
                per_level[level] = tree.splats.subset(rows)
        p = tree.splats.positions[mine]
        node = LodNode(p.min(axis=0), p.max(axis=0))
        nodes.append(node)
        splats[id(node)] = per_level
    p = tree.splats.positions
    root = LodNode(p.min(axis=0), p.max(axis=0), tuple(nodes))
    return StreamedSog(levels - k, root, splats, None)


def encode_rad(path: str | os.PathLike, opts: EncodeOptions | None = None,
               progress: Progress | None = None) -> MemoryStore:
    """Read a .rad whole and encode it in memory with its own LoD tree."""
    progress = progress or no_progress
    return encode_tree(read_tree(path, progress), os.fspath(path), opts, progress)


def read_tree(path: str | os.PathLike, progress: Progress | None = None) -> StreamedSog:
    """A .rad read whole, its tree laid out as a streamed SOG (rad_as_streamed_sog), every splat screened as any
    input's are: what sog_import.encode_tree (for `view`) and encode_tree_to (for `encode`) take."""
    progress = progress or no_progress
    label = os.fspath(path)
    progress("read", 0.0)
    tree = read_rad_tree(path)
    if not len(tree.splats):
        raise InputError(label, "count", "0 splats (expected at least one)")
    sog = rad_as_streamed_sog(tree)
    for leaf_splats in sog.splats.values():
        for level, g in leaf_splats.items():
            leaf_splats[level] = screen_gaussians(g, label)
    progress("read", 1.0)
    return sog
