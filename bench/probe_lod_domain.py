"""Probe: the merge domain, hierarchy first and tiles after (issue 31; BENCHMARKS.md, "LOD merges").

The product's tree (lod.build_subtree) cuts the scene into kd regions first and merges inside each tile, so the
levels just above the leaves are chains whose merges never cross a leaf region's border. Here the order is
reversed, and the format stays as it is (REPLACE, leaves an exact partition of the originals, format_spec/lod.md
1-3):

1. Levels, globally: level L is merged from level L + 1 over the whole scene (about 1 / reduction of its splats,
   as many levels as lod.TreeShape gives the scene), every merged splat knowing its members one level down. The
   groups come from a grouping function `(splats, masses, target) -> (order, starts)` (lod._group_starts'
   return), so any grouping plugs in: `grid` (the Morton grid over the whole scene), `agg` (splat-transform's
   one-pass selection: bench/probe_lod_adaptive.agglomerate_group_starts).
2. Tiles, top-down: the root tile is the coarsest level; the content of a tile's children one level down is
   exactly the members of its splats, cut by kd median splits of their centres into lod.TreeShape's fan for that
   level (1: a chain). A tile is replaced only when all its children are drawn, so any partition of the members
   is valid REPLACE.
3. Errors, opacities and colours bottom-up, per tile, as lod.md 3 and 6 say: each merged splat's error against its
   ORIGINAL members, the tile's 99th percentile raised to its children's, opacity and base colour matched at the
   tile's viewing blur; bounds contain the children's.

    python bench/probe_lod_domain.py SCENE [--grouping tree --grouping grid --grouping 'grid|grid-kd5' ...]
        [--crop 0.25] [--blur-scale 0] [--no-render] [--encode-dir DIR]

Groupings: `tree` (the product's lod.build_tiles, for comparison), `grid`, `agg`, `grid-kdK` / `agg-kdK` (held
inside the 2**K kd regions of each level, every region reduced alike), `agg-bordersK` (the regions' borders
without that allocation), `grid-shift1..3` (the grid's walls moved), `grid-tiles` (the grid in as many kd regions
as the level has tiles), `A|B` (per level the candidate of lower mean error over the originals, or with
--choose-by-render the one rendering closer to full detail), and with --fixed-tiles `grid-fixed`, `agg-fixed`,
`agg-fixed-free`. Prints the PSNR of every whole level (4 orbit views at 384 px, GL renderer, against the
full-detail render) and per level the error proxies; with --encode-dir writes the scene encoded with the last
grouping's tree into DIR (default preset), for bench/lod_vs_peers.py --skip-peers --our-scene-dir. Needs scipy
for `agg`.

Measured (BENCHMARKS.md, "LOD merges", "Merge domain"): tile borders cost nothing measurable (`grid-kd5` equals
the product tree within 0.06 dB but at the donut's coarsest level; `agg-borders5` is within -0.2 to +0.7 dB of
`agg` with no borders); what the domain changes is how the reduction is allocated across the scene, worth -1.1 to
+1.4 dB with the grid depending on the scene (the real cut: statue-angel -0.4 to +1.3, st-peter +0.7 to +1.0,
flowers +0.2 to +1.3, donut -0.7 to +0.3, guitar -0.8 to -0.05). Per level the candidate that renders better
(`--choose-by-render --grouping 'grid|grid-tiles'`) came closest: on the real cut of all 12 scenes 12 of 48 points
+0.3 to +1.5 dB, median +0.02, three -0.2 to -0.4 dB; fruit_drops' coarse levels -0.8 to -1.2 dB; 16x the build
time on flowers. No rule held on every scene; not adopted. Inside the product's own tiles (`--fixed-tiles`;
`grid-fixed` is the product tree to the last digit), `agg` with a scene-wide allocation (`agg-fixed-free`) gains
what the whole-scene domain gave it (+0.1 to +2.4 dB against `agg-fixed`, guitar -0.04 to -0.5): the next step is
that allocation with a cost that holds on every scene, not a new domain.
"""
from __future__ import annotations

import argparse
import math
import resource
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client_gl.offscreen import render_image
from splatstream import lod
from splatstream.camera import DEFAULT_FOV_Y_DEG, fit_distance, orbit_views, robust_bounds, scene_orbit_views
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.metrics import psnr_from_mse
from splatstream.orientation import detect_up

sys.path.insert(0, str(Path(__file__).parent))

CHOOSE_VIEWS: tuple | None = None  # (cameras, full-detail renders): A|B chooses by PSNR from these views instead
# `--fixed-tiles`: merges held inside the product's tiles (kd regions of the ORIGINALS at each level's TreeShape
# depth, fixed from level to level), and the tree cut along them, so tiles, leaves and ids are the product's.
FIXED: dict = {"on": False, "leaf_of": None, "region": None, "leaves": None, "depth": 0}
LEVEL_KD = [0]  # the TreeShape kd depth of the level being merged (`grid-tiles`: as many regions as its tiles)
CHOICES: list[int] = []  # per level built, finest first: which candidate grouping was taken
PROXIES: list[tuple] = []  # per level built: (splats, mean e, mass-rms e, mass-rms centre shift, colour mse)
Grouping = Callable[[Gaussians, np.ndarray, int], tuple[np.ndarray, np.ndarray]]


def grid_groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """The product's Morton grid, over the whole set."""
    return lod._group_starts(g.positions, target)


def agg_groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    from probe_lod_adaptive import agglomerate_group_starts
    return agglomerate_group_starts(g, mass, target)


def _agg_bordered(g: Gaussians, mass: np.ndarray, target: int, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`agg` over the whole set with its nearest-neighbour candidates in another region dropped (not replaced)."""
    import scipy.spatial

    tree_class = scipy.spatial.cKDTree

    class Bordered:  # nearest neighbours inside the splat's own region only (others reported missing: n)
        def __init__(self, data):
            self.tree = tree_class(data)

        def query(self, x, k):
            d, nb = self.tree.query(x, k=k)
            n = len(region)
            cross = region[np.minimum(nb, n - 1)] != region[:, None]
            return d, np.where(cross, n, nb)

    scipy.spatial.cKDTree = Bordered
    try:
        return agg_groups(g, mass, target)
    finally:
        scipy.spatial.cKDTree = tree_class


def agg_with_borders(depth: int) -> Grouping:
    """`agg` over the whole level with its candidate pairs across the borders of the level's 2**depth kd regions
    dropped: the borders of in_kd_domains(agg_groups, depth) without its allocation (each region reduced alike);
    the cheapest-first walk still spends the reduction where it is cheapest over the whole scene."""
    def groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
        index = np.arange(len(g))
        regions = [index]
        for _ in range(depth):
            regions = [h for r in regions for h in (lod.kd_split(g.positions, index, r)[:2] if len(r) > 1
                                                    else (r, r[:0]))]
        region = np.empty(len(g), np.int64)
        for k, rows in enumerate(regions):
            region[rows] = k
        return _agg_bordered(g, mass, target, region)
    return groups


def in_kd_domains(grouping: Grouping, depth: int) -> Grouping:
    """`grouping` held inside the 2**depth kd regions (median splits) of the level being merged: merges never
    cross a region's border, and every region is reduced alike (what the product's per-tile merge does, but over
    regions of the level itself, not the tiles')."""
    def groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
        index = np.arange(len(g))
        regions = [index]
        for _ in range(depth):
            regions = [h for r in regions for h in (lod.kd_split(g.positions, index, r)[:2] if len(r) > 1
                                                    else (r, r[:0]))]
        orders, starts, at = [], [], 0
        for rows in regions:
            if not len(rows):
                continue
            sub = g.subset(rows)
            o, s = grouping(sub, mass[rows], max(1, math.ceil(len(rows) * target / len(g))))
            orders.append(rows[o])
            starts.append(s + at)
            at += len(rows)
        return np.concatenate(orders), np.concatenate(starts)
    return groups


def shifted_grid(pad_lo: float, pad_hi: float) -> Grouping:
    """The Morton grid over a box grown by these fractions of its size below and above: the same rule with its
    cell walls elsewhere (how much of a difference is where the walls fall)."""
    def groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = lod.column_min(g.positions), lod.column_max(g.positions)
        size = hi - lo
        morton = lod._morton
        lod._morton = lambda p: lod.morton_codes(p, lo - pad_lo * size, hi + pad_hi * size)
        try:
            return lod._group_starts(g.positions, target)
        finally:
            lod._morton = morton
    return groups


GROUPINGS: dict[str, Grouping] = {"grid": grid_groups, "agg": agg_groups,
                                  "grid-shift1": shifted_grid(0.1, 0.0), "grid-shift2": shifted_grid(0.0, 0.1),
                                  "grid-shift3": shifted_grid(0.05, 0.05)}
def _tile_count_domains(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    return in_kd_domains(grid_groups, LEVEL_KD[0])(g, mass, target)


def _fixed_domains(grouping: Grouping, allocate: bool) -> Grouping:
    """`grouping` inside the fixed regions (FIXED): `allocate` False: each region reduced alike (the product);
    True: the nearest-neighbour candidates of `agg` cut at the regions' borders, the reduction spent over the
    whole scene (a scene-wide allocation inside the product's tiles)."""
    def groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
        region = FIXED["region"]
        if allocate:
            return _agg_bordered(g, mass, target, region)
        labels = np.unique(region)
        regions = [np.flatnonzero(region == r) for r in labels]
        orders, starts, at = [], [], 0
        for rows in regions:
            o, st = grouping(g.subset(rows), mass[rows], max(1, math.ceil(len(rows) / 2.0)))
            orders.append(rows[o])
            starts.append(st + at)
            at += len(rows)
        return np.concatenate(orders), np.concatenate(starts)
    return groups


GROUPINGS["grid-fixed"] = _fixed_domains(grid_groups, False)
GROUPINGS["agg-fixed"] = _fixed_domains(agg_groups, False)
GROUPINGS["agg-fixed-free"] = _fixed_domains(agg_groups, True)
GROUPINGS["grid-tiles"] = _tile_count_domains  # the grid in as many kd regions as the level has tiles
for _k in range(1, 9):
    GROUPINGS[f"grid-kd{_k}"] = in_kd_domains(grid_groups, _k)
    GROUPINGS[f"agg-kd{_k}"] = in_kd_domains(agg_groups, _k)
    GROUPINGS[f"agg-borders{_k}"] = agg_with_borders(_k)


@dataclass
class Hierarchy:
    """Whole-scene levels, coarsest first; the last level is the originals. parents[L] (L >= 1): for every splat
    of level L the index of the splat of level L - 1 it was merged into."""

    levels: list[Gaussians]
    masses: list[np.ndarray]
    parents: list[np.ndarray | None]


def build_hierarchy(g: Gaussians, levels: int, reduction: float, grouping: Grouping | list[Grouping],
                    kd_depths: tuple[int, ...] | None = None) -> Hierarchy:
    """`levels` merges, each over the whole previous level, chained finest to coarsest. With several groupings,
    each level takes the candidate whose mean error over the originals (lod.md 3's e_m of the merged splat each
    original went into) is lowest: a choice made from the splats alone, no renders, no constant."""
    candidates = grouping if isinstance(grouping, list) else [grouping]
    sets, masses, parents = [g], [lod.splat_mass(g)], []
    reach = lod.original_reach(g)
    rep = np.arange(len(g))
    leaf = FIXED["leaf_of"]
    leaves = [leaf] if leaf is not None else []
    for step in range(levels):
        LEVEL_KD[0] = kd_depths[levels - 1 - step] if kd_depths else 0
        if leaf is not None:  # the fixed region (tile of the level being made) of every splat merged now
            FIXED["region"] = leaf >> (FIXED["depth"] - LEVEL_KD[0])
        cur, m = sets[-1], masses[-1]
        target = max(1, math.ceil(len(cur) / reduction))
        best = None
        for k, group in enumerate(candidates):
            order, starts = group(cur, m, target)
            merged, merged_mass, assign = lod.merge_groups(cur, m, order, starts)
            score = 0.0
            if len(candidates) > 1:
                r = assign[rep]
                far, near = lod.error_extremes(g.positions, reach, merged.positions, r, len(merged))
                errors = lod.errors_from_extremes(far, near, merged)
                if CHOOSE_VIEWS:
                    score = -_psnr(_level_look(g, merged, r, errors), *CHOOSE_VIEWS)
                else:
                    score = float(np.mean(errors[r]))
            if best is None or score < best[0]:
                best = (score, merged, merged_mass, assign, k)
        _, merged, merged_mass, assign, k = best
        CHOICES.append(k)
        if leaf is not None:
            up = np.full(len(merged), np.iinfo(np.int64).max)
            np.minimum.at(up, assign, leaf)
            leaf = up
            leaves.append(leaf)
        rep = assign[rep]
        sets.append(merged)
        masses.append(merged_mass)
        parents.append(assign)
    FIXED["leaves"] = leaves[::-1]
    return Hierarchy(sets[::-1], masses[::-1], [None] + parents[::-1])


def _level_look(g: Gaussians, merged: Gaussians, rep: np.ndarray, errors: np.ndarray) -> Gaussians:
    """A candidate level as it would look: opacity and colour matched at the viewing blur of the whole level's error
    (the tiles' errors are not known yet)."""
    counts = np.bincount(rep, minlength=len(merged))
    blur = lod.viewing_blur(lod.tile_error(errors, counts))
    look = Gaussians(merged.positions, merged.rotations, merged.log_scales, merged.opacity_logits.copy(),
                     merged.sh_dc.copy(), merged.sh_rest)
    terms = lod.appearance_terms(g.opacity_logits, g.log_scales, g.sh_dc, blur)
    sums = np.stack([np.bincount(rep, weights=t, minlength=len(merged)) for t in terms])
    lod.finish_appearance(look, counts, sums, blur)
    return look


def _runs(labels: np.ndarray, count: int) -> list[np.ndarray]:
    """For each label 0..count-1 the ascending indices holding it."""
    order = np.argsort(labels, kind="stable")
    cuts = np.searchsorted(labels[order], np.arange(count + 1))
    return [order[cuts[k]:cuts[k + 1]] for k in range(count)]


def cut_tiles(h: Hierarchy, shape: lod.TreeShape) -> list[list[np.ndarray]]:
    """Per tile level, the node sets (indices into that level) of its tiles in breadth-first order: the root is
    the coarsest level; a tile's children share out its nodes' members by kd median splits (shape.fan)."""
    tiles = [[np.arange(len(h.levels[0]))]]
    for level in range(shape.leaf_level):
        parent = h.parents[level + 1]
        tile_of_node = np.empty(len(h.levels[level]), np.int64)
        for t, nodes in enumerate(tiles[level]):
            tile_of_node[nodes] = t
        members = _runs(tile_of_node[parent], len(tiles[level]))
        pos = h.levels[level + 1].positions
        index = np.arange(len(pos))
        splits = int(round(math.log2(shape.fan(level))))
        nxt = []
        for rows in members:
            parts = [rows]
            for _ in range(splits):
                parts = [half for p in parts for half in (lod.kd_split(pos, index, p)[:2] if len(p) > 1
                                                          else (p, p[:0]))]
            nxt.extend(parts)
        tiles.append(nxt)
    return tiles


def _finish(merged: Gaussians, counts: np.ndarray, sums: np.ndarray, blur: np.ndarray) -> None:
    """lod.finish_appearance with one viewing blur per merged splat (its tile's)."""
    covered, total = sums[0], sums[1]
    single = counts == 1
    area = lod._coverage_area(merged.log_scales, blur[:, None])
    alpha = np.clip(covered / area, 1e-7, lod.MAX_MERGED_OPACITY)
    logits = np.log(alpha / (1.0 - alpha)).astype(np.float32)
    sh_dc = sums[2:5].T / total[:, None]
    merged.opacity_logits = np.where(single, merged.opacity_logits, logits)
    merged.sh_dc = np.where(single[:, None], merged.sh_dc, sh_dc.astype(np.float32))


def build_tree(g: Gaussians, max_leaf_splats: int = 16384, reduction: float = 2.0,
               grouping: Grouping | list[Grouping] = grid_groups) -> list[lod.Tile]:
    """The tile tree, hierarchy first and tiles after (module docstring); same shape and ids as lod.build_tiles."""
    shape = lod.TreeShape.of(len(g), max_leaf_splats, reduction)
    if shape.leaf_level == 0:
        return lod.build_tiles(g, max_leaf_splats, reduction)
    if FIXED["on"]:
        rows = lod._kd_leaves(g.positions, np.arange(len(g)), shape.depth, lambda *a: None)
        FIXED["leaf_of"] = np.empty(len(g), np.int64)
        for k, r in enumerate(rows):
            FIXED["leaf_of"][r] = k
        FIXED["depth"] = shape.depth
    h = build_hierarchy(g, shape.leaf_level, reduction, grouping, shape.kd_depths)
    if FIXED["on"]:  # the product's tiles: tile j of level L = the splats in the kd region j at depth d_L
        sets = [_runs(FIXED["leaves"][lvl] >> (shape.depth - shape.kd_depths[lvl]), 2 ** shape.kd_depths[lvl])
                for lvl in range(shape.leaf_level + 1)]
        FIXED.update(leaf_of=None, region=None, leaves=None)
    else:
        sets = cut_tiles(h, shape)
    leaf = shape.leaf_level
    orig = h.levels[leaf]
    reach = lod.original_reach(orig)
    tiles: dict[int, lod.Tile] = {}
    for j, rows in enumerate(sets[leaf]):
        part = orig.subset(rows)
        tid = shape.tile_id(leaf, j)
        tiles[tid] = lod.Tile(tid, leaf, [], part, 0.0, *lod.extent_bounds(part))
    rep = np.arange(len(orig))
    alpha = 1.0 / (1.0 + np.exp(-np.clip(orig.opacity_logits.astype(np.float64), -700, 700)))
    for level in range(leaf - 1, -1, -1):
        rep = h.parents[level + 1][rep]
        merged = h.levels[level]
        size = len(merged)
        merged = Gaussians(merged.positions, merged.rotations, merged.log_scales, merged.opacity_logits.copy(),
                           merged.sh_dc.copy(), merged.sh_rest)
        counts = np.bincount(rep, minlength=size)
        far, near = lod.error_extremes(orig.positions, reach, merged.positions, rep, size)
        errors = lod.errors_from_extremes(far, near, merged)
        blur = np.empty(size)
        errs = []
        for j, nodes in enumerate(sets[level]):
            kids = shape.children(level, j)
            e = max(lod.tile_error(errors[nodes], counts[nodes]), max(tiles[k].geometric_error for k in kids))
            errs.append(e)
            blur[nodes] = lod.viewing_blur(e)
        b = blur[rep]
        s = np.sqrt(np.exp(2.0 * orig.log_scales.astype(np.float64)) + b[:, None])
        shown = alpha * (s[:, 0] * s[:, 1] + s[:, 1] * s[:, 2] + s[:, 0] * s[:, 2])
        weight = shown + 1e-300
        sums = np.stack([np.bincount(rep, weights=w, minlength=size) for w in
                         (shown, weight, weight * orig.sh_dc[:, 0], weight * orig.sh_dc[:, 1],
                          weight * orig.sh_dc[:, 2])])
        _finish(merged, counts, sums, blur)
        m0 = lod.splat_mass(orig)
        d2 = np.sum((orig.positions.astype(np.float64) - merged.positions[rep]) ** 2, axis=1)
        c2 = np.sum((orig.sh_dc.astype(np.float64) - merged.sh_dc[rep]) ** 2, axis=1)
        e = errors[rep]
        PROXIES.append((size, float(np.mean(e)), float(np.sqrt(np.sum(m0 * e * e) / m0.sum())),
                        float(np.sqrt(np.sum(m0 * d2) / m0.sum())), float(np.sum(weight * c2) / weight.sum())))
        for j, nodes in enumerate(sets[level]):
            tid = shape.tile_id(level, j)
            kids = shape.children(level, j)
            part = merged.subset(nodes)
            lo, hi, c, r = lod.interior_bounds(part, [tiles[k] for k in kids])
            tiles[tid] = lod.Tile(tid, level, kids, part, errs[j], lo, hi, c, r)
    return [tiles[i] for i in range(shape.tiles)]


def _psnr(s: Gaussians, cams, refs) -> float:
    mse = np.mean([np.mean((np.clip(render_image(s, c), 0, 1) - np.clip(r, 0, 1)) ** 2)
                   for c, r in zip(cams, refs, strict=True)])
    return psnr_from_mse(float(mse))


def level_row(tiles: list[lod.Tile], cams, refs, last: int = 5) -> str:
    levels: dict[int, list[Gaussians]] = {}
    for t in tiles:
        levels.setdefault(t.level, []).append(t.gaussians)
    row = []
    for level in sorted(levels)[:-1][-last:]:
        s = Gaussians.concatenate(levels[level])
        row.append(f"{len(s)}: {_psnr(s, cams, refs):.2f}")
    return ", ".join(row)


def check_tree(tiles: list[lod.Tile], n: int) -> str:
    """REPLACE and bounds as lod.md 1-3 ask: leaves an exact partition (by count: rows are subsets of one array),
    errors non-increasing, parents' boxes holding the children's; leaf and tile sizes."""
    leaves = [t for t in tiles if not t.children]
    assert sum(len(t.gaussians) for t in leaves) == n
    for t in tiles:
        for k in t.children:
            c = tiles[k]
            assert c.geometric_error <= t.geometric_error
            assert np.all(t.box_min <= c.box_min) and np.all(t.box_max >= c.box_max)
    sizes = [len(t.gaussians) for t in tiles]
    leaf_sizes = [len(t.gaussians) for t in leaves]
    return (f"{len(tiles)} tiles, tile splats {min(sizes)}-{max(sizes)}, leaves {len(leaves)} of "
            f"{min(leaf_sizes)}-{max(leaf_sizes)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--grouping", action="append", default=[],
                    help="grid | agg | grid-kdK | agg-kdK (repeatable); `tree`: the product; A|B: per level the "
                    "candidate of lowest mean error")
    ap.add_argument("--crop", type=float, default=0.0, help="keep splats within this quantile of per-axis distance")
    ap.add_argument("--max-leaf-splats", type=int, default=16384)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--blur-scale", type=float, default=1.0, help="the viewing blur of the opacity and colour step "
                    "times this (0: none), for every tree built")
    ap.add_argument("--choose-by-render", action="store_true", help="A|B: per level the candidate rendering closer "
                    "to full detail from 4 other views (elevation 50 degrees, azimuths between the measured ones, "
                    "128 px) instead of the lower mean error")
    ap.add_argument("--fixed-tiles", action="store_true", help="grid-fixed | agg-fixed | agg-fixed-free: merges "
                    "and tiles held in the product's kd tiles (fixed regions of the originals)")
    ap.add_argument("--no-render", action="store_true", help="build and check only (time, memory)")
    ap.add_argument("--encode-dir", help="encode the scene with the last grouping's tree into this directory")
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    if args.crop:
        d = np.abs(g.positions - np.median(g.positions, axis=0))
        cheb = d.max(axis=1)
        g = g.subset(np.flatnonzero(cheb <= np.quantile(cheb, args.crop)))
    cams = refs = None
    if args.blur_scale != 1.0:
        blur = lod.viewing_blur
        lod.viewing_blur = lambda e: args.blur_scale * blur(e)
    if not args.no_render:
        cams = scene_orbit_views(g.positions, args.views, args.size, args.size, up=detect_up(g).up)
        refs = [render_image(g, c) for c in cams]
    if args.choose_by_render:
        global CHOOSE_VIEWS
        med, lo, hi = robust_bounds(g.positions, 95.0)
        radius = float(np.linalg.norm(np.maximum(hi - med, med - lo))) or 1.0
        sel = orbit_views(med, fit_distance(radius, DEFAULT_FOV_Y_DEG, 1.0), 4, detect_up(g).up, 50.0,
                          width=128, height=128, start_deg=270.0)
        CHOOSE_VIEWS = (sel, [render_image(g, c) for c in sel])
    FIXED["on"] = args.fixed_tiles
    tiles = None
    for name in args.grouping or ["tree", "grid"]:
        PROXIES.clear()
        t0 = time.perf_counter()
        if name == "tree":
            tiles = lod.build_tiles(g, args.max_leaf_splats, 2.0)
        else:
            groups = [GROUPINGS[n] for n in name.split("|")]
            tiles = build_tree(g, args.max_leaf_splats, 2.0, groups if len(groups) > 1 else groups[0])
            if len(groups) > 1:
                print(f"  {name} chose (finest level first): {CHOICES}")
            CHOICES.clear()
        secs = time.perf_counter() - t0
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        info = check_tree(tiles, len(g))
        for p in sorted(PROXIES)[-5:]:
            print(f"  proxy {name} {p[0]}: mean e {p[1]:.4g}, rms e {p[2]:.4g}, rms shift {p[3]:.4g}, "
                  f"colour {p[4]:.4g}")
        PROXIES.clear()
        print(f"{name:6s} built in {secs:.1f} s (peak RSS so far {rss:.0f} MB); {info}", flush=True)
        if not args.no_render:
            print(f"{name:6s} {level_row(tiles, cams, refs)}", flush=True)
    if args.encode_dir and tiles is not None:
        from splatstream.encode.local import encode_to
        from splatstream.encode.options import EncodeOptions
        from splatstream.store import DirectoryWriter
        leaves = Gaussians.concatenate([t.gaussians for t in tiles if not t.children])
        with DirectoryWriter(args.encode_dir) as writer:
            encode_to(leaves, writer, EncodeOptions(), source_name=args.scene, out_name=Path(args.encode_dir).name,
                      tiles=tiles)
        print(f"encoded into {args.encode_dir}", flush=True)


if __name__ == "__main__":
    main()
