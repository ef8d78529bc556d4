"""A tile tree of ours (format_spec/lod.md) as a PlayCanvas streamed SOG: `lod-meta.json` plus SOG units
(format_spec/foreign_formats.md, "Our streamed SOG export").

Streamed SOG describes LOD differently from our tree. Its `tree` is a spatial tree whose **leaves** each hold, for
every LOD level (0 the finest), a row range `{file, offset, count}` of one SOG unit; every unit belongs to one
level. PlayCanvas's engine reads only the leaves (it ignores interior nodes) and picks a level per leaf from its
distance to the camera. Our tree instead refines by REPLACE: a tile at depth d stands for its whole subtree.

The mapping (pure; `splatstream/sog_export.py` wires it to a scene):

* SOG leaves are our leaf tiles (in depth-first order); SOG level L holds our tiles of depth D - L (D = the depth
  of the deepest leaf), so level 0 is our leaves and level D our root.
* A leaf's reference at level L holds the splats of its ancestor (or itself) at depth D - L that fall to it:
  each splat of an interior tile goes to the one leaf below that tile whose box of splat centres is nearest to its
  centre (inside: distance 0; the leaves of our kd tree partition space, so almost every splat is inside exactly
  one). Every splat of every tile lands in exactly one leaf: level L is exactly our depth D - L, split by leaf.
* A leaf shallower than D repeats its own splats at the finer levels (a unit belongs to one level; without them
  the engine would draw nothing there at close range).
* Units `L_i/meta.json` take the references of level L in leaf order, a new unit once one holds more than
  `unit_splats` splats (splat-transform's packing); units keep the given order (no Morton reordering: the ranges
  are the references).
* Node bounds: a leaf's box holds the 3-sigma boxes of every splat it references at any level; an interior
  node's, its children's. Our interior tiles with one child add no node.
"""
from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..gaussians import Gaussians, covariances
from ..progress import Tally
from .sog import GENERATOR, SogUnit, sog_unit, write_unit

LOD_META_NAME = "lod-meta.json"
LOD_META_VERSION = 1
# splat-transform's default unit size (--lod-chunk-count 512, in thousands of splats).
UNIT_SPLATS = 512 * 1024
SIGMAS = 3.0
ROUTE_BLOCK = 1 << 16


@dataclass(frozen=True)
class TreeTile:
    """One tile of our tree as the export needs it: its depth, children and decoded splats."""

    id: int
    level: int
    children: tuple[int, ...]
    splats: Gaussians


@dataclass(frozen=True)
class SogLodFiles:
    meta: dict
    units: dict[str, SogUnit]  # by directory name ("L_i")

    def meta_bytes(self) -> bytes:
        return json.dumps(self.meta, separators=(",", ":")).encode("utf-8")


def _leaves_below(tiles: dict[int, TreeTile], root: int) -> dict[int, list[int]]:
    """Per tile, its leaves in depth-first order."""
    below: dict[int, list[int]] = {}

    def visit(tid: int) -> list[int]:
        t = tiles[tid]
        below[tid] = [tid] if not t.children else [leaf for c in t.children for leaf in visit(c)]
        return below[tid]

    visit(root)
    return below


def _route(positions: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Index of the box (lo, hi: (L, 3)) nearest to each position (squared distance to the box; first on ties)."""
    out = np.empty(len(positions), np.int64)
    step = max(1, ROUTE_BLOCK // max(1, len(lo)))
    for i in range(0, len(positions), step):
        p = positions[i:i + step, None, :].astype(np.float64)
        gap = np.maximum(lo[None] - p, 0) + np.maximum(p - hi[None], 0)
        out[i:i + step] = np.argmin((gap ** 2).sum(axis=2), axis=1)
    return out


def extent_box(g: Gaussians) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of the splats' 3-sigma ellipsoids (lod.extent_bounds is in a sibling layer, which writers
    may not import; this is its box without the sphere)."""
    half = SIGMAS * np.sqrt(np.maximum(np.diagonal(covariances(g), axis1=1, axis2=2), 0))
    p = g.positions.astype(np.float64)
    return (p - half).min(axis=0), (p + half).max(axis=0)


def _pack(parts: list[tuple[int, Gaussians]], unit_splats: int) -> list[list[tuple[int, Gaussians]]]:
    """Consecutive runs of (leaf, splats), a run closed once it holds more than `unit_splats` splats."""
    runs: list[list[tuple[int, Gaussians]]] = [[]]
    size = 0
    for leaf, part in parts:
        runs[-1].append((leaf, part))
        size += len(part)
        if size > unit_splats:
            runs.append([])
            size = 0
    return [run for run in runs if run]


def streamed_sog(tiles: dict[int, TreeTile], root: int, unit_splats: int = UNIT_SPLATS,
                 progress: Callable[[float], None] | None = None) -> SogLodFiles:
    """The lod-meta.json object and the units of a tree of ours (see the module's docstring). `progress` hears
    the share of the splats packed into units, and inside a unit the share of its SOG encode done (its WebP planes,
    then its SH palette's k-means by cell): that encode is the slow part (about 28 s for playbot's 919,279 splats on
    a busy 2-core machine, 30-35 s a 524,288-splat unit of a 2M-splat scene at a load of 6)."""
    below = _leaves_below(tiles, root)
    leaves = below[root]
    depth = max(tiles[leaf].level for leaf in leaves)
    levels = depth + 1
    parent: dict[int, int] = {c: t.id for t in tiles.values() for c in t.children}
    # Boxes of the leaves' splat centres, for routing the splats of the tiles above them.
    centre_lo, centre_hi = {}, {}
    for leaf in leaves:
        p = tiles[leaf].splats.positions.astype(np.float64)
        centre_lo[leaf] = p.min(axis=0) if len(p) else np.full(3, np.inf)
        centre_hi[leaf] = p.max(axis=0) if len(p) else np.full(3, -np.inf)
    # share[tile][leaf]: the rows of the tile's splats that fall to that leaf.
    share: dict[int, dict[int, np.ndarray]] = {}
    for tid, t in tiles.items():
        under = below[tid]
        if len(under) == 1:
            share[tid] = {under[0]: np.arange(len(t.splats))}
            continue
        lo = np.stack([centre_lo[leaf] for leaf in under])
        hi = np.stack([centre_hi[leaf] for leaf in under])
        to = _route(t.splats.positions, lo, hi)
        share[tid] = {leaf: np.flatnonzero(to == k) for k, leaf in enumerate(under)}
    # Each leaf's chain of tiles from the root, by depth.
    chain: dict[int, list[int]] = {}
    for leaf in leaves:
        path = [leaf]
        while path[-1] in parent:
            path.append(parent[path[-1]])
        chain[leaf] = path[::-1]
    filenames: list[str] = []
    units: dict[str, SogUnit] = {}
    counts = [0] * levels
    references: dict[int, dict[str, dict]] = {leaf: {} for leaf in leaves}
    referenced: dict[int, list[Gaussians]] = {leaf: [] for leaf in leaves}
    packed = Tally(progress, sum(len(share[path[min(depth - level, len(path) - 1)]][leaf])
                                 for leaf, path in chain.items() for level in range(levels)))
    for level in range(levels):
        parts = []
        for leaf in leaves:
            path = chain[leaf]
            tile = path[min(depth - level, len(path) - 1)]
            part = tiles[tile].splats.subset(share[tile][leaf])
            if len(part):
                parts.append((leaf, part))
                referenced[leaf].append(part)
        for index, members in enumerate(_pack(parts, unit_splats)):
            name = f"{level}_{index}"
            filenames.append(f"{name}/meta.json")
            offset = 0
            for leaf, part in members:
                references[leaf][str(level)] = {"file": len(filenames) - 1, "offset": offset, "count": len(part)}
                offset += len(part)
            counts[level] += offset
            units[name] = sog_unit(Gaussians.concatenate([part for _, part in members]), reorder=False,
                                   progress=lambda fraction, n=offset: packed.within(n, fraction))
            packed.add(offset)

    def node(tid: int) -> dict:
        t = tiles[tid]
        if not t.children:
            lo, hi = extent_box(Gaussians.concatenate(referenced[tid])) if referenced[tid] else \
                (np.zeros(3), np.zeros(3))
            return {"bound": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]},
                    "lods": references[tid]}
        if len(t.children) == 1:
            return node(t.children[0])
        kids = [node(c) for c in t.children]
        lo = np.min([k["bound"]["min"] for k in kids], axis=0)
        hi = np.max([k["bound"]["max"] for k in kids], axis=0)
        return {"bound": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]}, "children": kids}

    meta = {"version": LOD_META_VERSION, "asset": {"generator": GENERATOR, "chunkGaussians": unit_splats},
            "count": sum(counts), "counts": counts, "lodLevels": levels, "filenames": filenames,
            "tree": node(root)}
    return SogLodFiles(meta, units)


def write_streamed_sog(sog: SogLodFiles, directory: str) -> None:
    """Write the units, then lod-meta.json, into `directory` (which the caller writes atomically)."""
    for name, unit in sog.units.items():
        write_unit(unit, os.path.join(directory, name))
    with open(os.path.join(directory, LOD_META_NAME), "wb") as f:
        f.write(sog.meta_bytes())
