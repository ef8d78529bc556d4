"""LOD tile tree: a spatial tree of tiles whose leaves partition the original splats and whose interior tiles
hold merged (moment-matched) Gaussians standing in for their whole subtree (normative text: format_spec/lod.md).

Shape. A balanced kd-tree of median splits on the longest axis of the splat centres cuts the scene into 2**d
leaves of at most `max_leaf_splats` splats each (median splits adapt to density: dense regions get small tiles).
Tile levels are `reduction` apart in splats, from the leaves up to a root of about 0.25 % of the scene; each level
sits at the deepest kd depth whose tiles still hold a minimum of splats, so the top levels are many small tiles
and the levels just above the leaves are chains (one child covering the same region): TreeShape. A splat budget
is then spent in small steps. Refinement is REPLACE.

Merging. An interior tile merges the concatenation of its children's sets down to ceil(count / reduction)
(never above max_leaf_splats). Groups are cells of a binary Morton-prefix grid over the tile: the longest prefix
with at most that many cells, the most populated cells split once more to hit the count. A uniform grid per tile,
so sparse regions keep their splats and dense ones merge. Each group becomes one Gaussian by moment matching
with weights w = opacity * (mean cross-section s1 s2 + s2 s3 + s1 s3); w is carried up the tree, so every level
matches the moments of the ORIGINAL mixture. Opacity and base colour are then matched to the originals as the
rasteriser shows them at the tile's viewing scale (finish_appearance), higher SH bands are the w-weighted means;
the scales stay as moment matching made them.

Geometric error (world units): per merged splat, a bound on the Hausdorff distance between its original members'
1-sigma balls and its own; a tile's error is the 99th percentile of that over the originals it stands for (each
original counts with its merged splat's error), at least its children's errors (monotone), 0 for leaves.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .cores import available_cores
from .format.layout import morton_codes
from .format.limits import MAX_LOG_SCALE, MIN_LOG_SCALE
from .gaussians import SH_C0, Gaussians, normalize_quaternions, rotation_matrices, scaled_rotation_columns
from .lod_groups import GroupRule, grid_group_starts, group_errors, group_ids_of, group_runs, member_terms

# Bounds and errors use this many standard deviations (the 3DGS rasteriser's cut-off and KHR "ellipse" kernel).
EXTENT_SIGMAS = 3.0
# Merged opacity ceiling (the rasteriser's own clamp); a splat standing for a single original keeps its opacity.
MAX_MERGED_OPACITY = 0.99
# Variance (px^2) the rasteriser adds to projected covariances (reference 3DGS), and the screen-space error (px)
# at which coarse tiles are meant to be seen: their opacities and colours are matched at that scale. Not the
# 1 px of a view without a budget: under a splat budget a tile is drawn several times nearer than that, where
# the 1-px blur made merged splats too opaque. 2 px: budgeted views gain, levels seen at 1 px lose little; 4 px
# gains more under a budget but loses too much at 1 px (BENCHMARKS.md, "LOD against peers", the viewing scale;
# format_spec/lod.md 6, step 5).
# OPACITY_MATCH_SSE_PX is the scale of the first merged level (tiles whose children are the originals);
# OPACITY_MATCH_FAR_SSE_PX that of every level above it (lod.md 6, step 5). Module constants so that a bench or
# probe can set them (viewing_scale_px reads them at call time). 8 px above the first merged level: under a splat
# budget those levels are drawn at 7-30 px, and it gained a median +0.74 dB there (48 points, 45 up, none down by
# more than 0.2), while whole frames without a budget moved a median +0.04 dB (-0.90 to +0.84; BENCHMARKS.md, "The
# 2 + 8 px rule in frames without a budget", and "The default viewing scale: 2 + 8 px").
LOW_PASS_PX2 = 0.3
OPACITY_MATCH_SSE_PX = 2.0
OPACITY_MATCH_FAR_SSE_PX = 8.0
# The levels above the first merged one at OPACITY_MATCH_FAR_SSE_PX x GROWTH^(k - 1) px, k levels above it, at most
# CAP px (viewing_scale_px): 8, 12, 16, 16, ... A budget draws the coarser levels further away (7-30 px): growth 1.5
# up to 16 px (chosen leaving one scene out) gained a median +0.24 / +0.19 dB at 2 / 6 % budgets over 8 px on every
# level above (none of 48 points down by more than 0.07), and frames without a budget moved a median -0.01 dB (-0.91
# to +0.77; BENCHMARKS.md, "A viewing scale growing with the level"). Growth 1 (or a cap at or under
# OPACITY_MATCH_FAR_SSE_PX) is one scale above the first merged level, the rule before 2026-11-30.
OPACITY_MATCH_FAR_GROWTH = 1.5
OPACITY_MATCH_FAR_CAP_SSE_PX = 16.0
# Error statistic over a tile's ORIGINAL splats, each taking the error of the merged splat that stands for it
# (so untouched singletons cannot hide a merged blob): "max" is a strict bound; a quantile ignores a few outliers.
ERROR_STAT: str | float = 0.99
# Standard deviations of the balls the error compares: at 1 sigma, merging two point-like splats d apart costs
# about d, the size of the detail lost (3 sigma would double it; the client's threshold would absorb the factor).
ERROR_SIGMAS = 1.0
# Shape of the tile tree (TreeShape.of): the root holds about ROOT_FRACTION of the splats, within these bounds; the
# smallest tiles of the top levels about 1/MIN_TILES_FOR_SMALLEST of the scene (never under MIN_TILE_SPLATS); at
# least MIN_LEAF_TILES leaves of at least MIN_LEAF_TILE_SPLATS each. So a splat budget of a few percent of the
# scene is spent in steps of a fraction of a percent (format_spec/lod.md 1).
ROOT_FRACTION = 0.0025
ROOT_MIN_SPLATS = 128
ROOT_MAX_SPLATS = 4096
MIN_TILES_FOR_SMALLEST = 1024
MIN_TILE_SPLATS = 64
MIN_LEAF_TILES = 32
MIN_LEAF_TILE_SPLATS = 1024
# The tree's merges (format_spec/lod.md 6): "grid" groups each tile's members by a uniform Morton grid, every tile
# reduced by the same ratio; "cost" groups a whole tree level at once by merge cost (lod_groups.group_ids: field-L2
# of the footprints projected along x, y and z plus a colour term, greedy matchings of pairs until they stall, then
# groups of up to 4 of the level's splats), groups held inside the level's tiles, so the count each tile keeps is
# decided by cost across the scene (the level's total is the grid's). Pairs first, not groups of up to 4 from the
# start: chosen on statue-angel and donut, where capping at 4 at once lost 0.7-1.7 dB on the donut (BENCHMARKS.md,
# "LOD against peers", cost merge).
# "auto" builds both groupings of every tile of a level, the grid at the count the cost merge gave the tile (so
# the level's allocation is the cost merge's), and keeps the one whose merged splats are closer to their members
# by choice_error (level_auto_groups). Neither grouping held on every scene: the cost merge gains on the donut,
# guitar and winter_fountain and loses on flowers, biker's coarse levels and statue-st-peter at 50 % (BENCHMARKS.md,
# "LOD against peers", per-tile choice).
LOD_MERGES = ("grid", "cost", "auto")
COST_RULE = GroupRule(proj=1, first_cap=2, max_group=4)
# "auto"'s own grouping: the cost merge's rule, but once a stage's merges still needed are at most 5 % of the
# clusters one round takes them all (share 0.5 left 10+ rounds of a few hundred merges, each a pass over every edge
# row); its choice judges every AUTO_CHOICE_SAMPLE-th group of each grouping, at the first merged level only (the
# grid was taken on 0-3 % of the tiles above it). About 0.7x the CPU of the grouping before, the streaming cut
# within 0.1 dB (BENCHMARKS.md, "LOD groups by cost", the auto merge cheaper).
AUTO_RULE = GroupRule(proj=1, first_cap=2, max_group=4, tail=0.05)
# The first merged level's own rule (level_auto_groups: every tile at blur 0), today AUTO_RULE's. Branch edges31
# measured cheaper graphs there and above (4-6 neighbours, 2 Morton orders, a wider candidate window: GroupRule's
# neighbours, shifts, window): 1.17-1.44x less tree CPU, but every one that saved 1.15x or more moved the streamed
# points by -0.1 to -0.6 dB somewhere (2-6 % with fewer edges above the first level; statue-massa's 50 % fell below
# splat-transform), so none is the default (BENCHMARKS.md, "LOD tree", fewer costed edges).
AUTO_FIRST_RULE = GroupRule(proj=1, first_cap=2, max_group=4, tail=0.05)
AUTO_CHOICE_SAMPLE = 2
Progress = Callable[[str, float], None]


@dataclass
class Tile:
    id: int  # 0 = root, breadth-first numbering, children ids > parent id
    level: int  # 0 = root
    children: list[int]  # empty for leaves; refinement is REPLACE: children together replace the tile
    gaussians: Gaussians  # leaves: the original splats (exact partition); interior: merged splats
    geometric_error: float  # world units, 0 for leaves, non-increasing from root to leaves
    # (3,) axis-aligned box covering the splats' 3-sigma extents (and the children's boxes). None only while a
    # caller that built a single tile itself has not computed them yet (the encoder does so on its worker pool).
    box_min: np.ndarray | None
    box_max: np.ndarray | None
    sphere_center: np.ndarray | None  # (3,) bounding sphere covering the same extents
    sphere_radius: float


# ---------------------------------------------------------------------------------------------- geometry


def _sigma_axes(rotations: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """(N, 3) world-axis standard deviations sqrt(diag Sigma): the half-extents of the 1-sigma ellipsoid's box."""
    r = rotation_matrices(rotations)
    s2 = np.exp(2.0 * log_scales.astype(np.float64))
    return np.sqrt(np.einsum("nij,nj->ni", r * r, s2))


EXTENT_BLOCK_ROWS = 1 << 17


def extent_bounds(g: Gaussians, sigmas: float = EXTENT_SIGMAS) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Exact box of the splats' `sigmas`-sigma ellipsoids, and a sphere (centred on the box) covering them."""
    if len(g) == 0:
        z = np.zeros(3)
        return z, z.copy(), z.copy(), 0.0
    # In row blocks: over a whole 1M-splat tile the float64 rotation matrices and their temporaries took 200 MB,
    # the peak of an encode without LOD. Minima and maxima are exact in any grouping, so the result is the same.
    n = len(g)
    lows, highs = [], []
    for a in range(0, n, EXTENT_BLOCK_ROWS):
        rows = slice(a, a + EXTENT_BLOCK_ROWS)
        p = g.positions[rows].astype(np.float64)
        half = sigmas * _sigma_axes(g.rotations[rows], g.log_scales[rows])
        lows.append(column_min(p - half))
        highs.append(column_max(p + half))
    lo, hi = np.min(lows, axis=0), np.max(highs, axis=0)
    center = (lo + hi) / 2
    radius = 0.0
    for a in range(0, n, EXTENT_BLOCK_ROWS):
        p = g.positions[a:a + EXTENT_BLOCK_ROWS].astype(np.float64)
        reach = sigmas * np.exp(_row_max(g.log_scales[a:a + EXTENT_BLOCK_ROWS]).astype(np.float64))
        radius = max(radius, float((_row_norm(p - center) + reach).max()))
    return lo, hi, center, radius


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _row_max(a: np.ndarray) -> np.ndarray:
    # Column-wise maximum of an (N, 3) array: much faster than a.max(axis=1) on short rows.
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _row_min(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _row_norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1] + a[:, 2] * a[:, 2])


def column_min(a: np.ndarray) -> np.ndarray:
    """a.min(axis=0) of an (N, k) array, column by column: numpy's axis=0 reduction is ~30x slower on this shape."""
    return np.array([a[:, k].min() for k in range(a.shape[1])])


def column_max(a: np.ndarray) -> np.ndarray:
    """a.max(axis=0) of an (N, k) array, column by column (as column_min)."""
    return np.array([a[:, k].max() for k in range(a.shape[1])])


def _rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """a[index] for integer `index` along the first axis: np.take gives the same rows 3-7x faster than fancy indexing
    on the (N, 3) and (N, 4) arrays of splats (numpy 2.4; 1M rows in random order: 0.012 s against 0.046 s)."""
    return np.take(a, index, axis=0)


def _morton(positions: np.ndarray) -> np.ndarray:
    """Morton codes over the positions' own box (layout.morton_codes, box computed column-wise)."""
    return morton_codes(positions, column_min(positions), column_max(positions))


def _orientation(r: np.ndarray) -> np.ndarray:
    """np.sign(np.linalg.det(r)) of (N, 3, 3) orthonormal matrices (eigh's eigenbases), by the triple product of the
    columns: |det| is 1 within rounding, so the sign is the same as the LU determinant's (NaN rows stay NaN); 5x
    cheaper than a batched LU."""
    c0 = r[:, 1, 1] * r[:, 2, 2] - r[:, 2, 1] * r[:, 1, 2]
    c1 = r[:, 0, 1] * r[:, 2, 2] - r[:, 2, 1] * r[:, 0, 2]
    c2 = r[:, 0, 1] * r[:, 1, 2] - r[:, 1, 1] * r[:, 0, 2]
    return np.sign(r[:, 0, 0] * c0 - r[:, 1, 0] * c1 + r[:, 2, 0] * c2)


# Shepperd's four candidate quaternions (w, x, y, z) of a rotation matrix m (its 9 entries row by row, s[3 i + j] =
# m[i, j]), each well conditioned when its leading component is the largest.
_QUATERNION_CANDIDATES = (
    lambda s: (1 + s[0] + s[4] + s[8], s[7] - s[5], s[2] - s[6], s[3] - s[1]),
    lambda s: (s[7] - s[5], 1 + s[0] - s[4] - s[8], s[1] + s[3], s[2] + s[6]),
    lambda s: (s[2] - s[6], s[1] + s[3], 1 - s[0] + s[4] - s[8], s[5] + s[7]),
    lambda s: (s[3] - s[1], s[2] + s[6], s[5] + s[7], 1 - s[0] - s[4] + s[8]),
)


def _matrices_to_quaternions(r: np.ndarray) -> np.ndarray:
    """(N, 4) unit (w, x, y, z) quaternions of proper rotation matrices, branch-free (Shepperd's method)."""
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    pick = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], 1), axis=1)
    # Each row's picked candidate only (the same elementwise expressions as all four stacked, then picked).
    q = np.empty((len(r), 4))
    entries = r.reshape(len(r), 9)
    for k, candidate in enumerate(_QUATERNION_CANDIDATES):
        rows = np.flatnonzero(pick == k)
        q[rows] = np.stack(candidate(_rows(entries, rows).T), 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return normalize_quaternions(q)


def _coverage_area(log_scales: np.ndarray, blur: float = 0.0) -> np.ndarray:
    """Mean cross-section proxy s1*s2 + s2*s3 + s1*s3 (float64): what a splat covers from a random direction,
    after adding `blur` (a variance, world units squared) to every axis."""
    s = np.sqrt(np.exp(2.0 * log_scales.astype(np.float64)) + blur)
    return s[:, 0] * s[:, 1] + s[:, 1] * s[:, 2] + s[:, 0] * s[:, 2]


def splat_mass(g: Gaussians) -> np.ndarray:
    """Merge weight of original splats: opacity * coverage area."""
    with np.errstate(over="ignore"):  # a logit below -709: exp overflows to inf, alpha is exactly 0
        alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    return alpha * _coverage_area(g.log_scales)


# ---------------------------------------------------------------------------------------------- grouping


def _group_starts(positions: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """The Morton grid's groups (lod_groups.grid_group_starts): Morton order and each group's start in it."""
    return grid_group_starts(positions, target)


def merge_gaussians(g: Gaussians, mass: np.ndarray, target: int) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """Merge `g` (with carried masses) into about `target` Gaussians in Morton order.

    Returns the merged Gaussians, their masses (sums of the members' masses) and for each input splat the
    index of the merged splat it went into."""
    if len(g) == 0:
        return g, mass, np.zeros(0, np.int64)
    return merge_groups(g, mass, *_group_starts(g.positions, max(1, target)))


def merge_groups(g: Gaussians, mass: np.ndarray, order: np.ndarray, starts: np.ndarray
                 ) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """Merge `g` (with carried masses) group by group: the groups are runs of `order` starting at `starts`.
    Returns what merge_gaussians returns."""
    n = len(g)
    counts = np.diff(np.append(starts, n))
    group_of = np.repeat(np.arange(len(starts)), counts)

    mass = np.take(mass, order)
    w = mass + 1e-300  # all-transparent groups still get a defined (uniform) mean
    wsum = np.add.reduceat(w, starts)
    wn = w / np.take(wsum, group_of)  # normalised weights, sum to 1 per group

    p = _rows(g.positions, order).astype(np.float64)
    origin = p.mean(axis=0)  # work relative to the set's centre for precision
    p -= origin
    mu = np.add.reduceat(p * wn[:, None], starts)
    d = p - _rows(mu, group_of)
    log_s = _rows(g.log_scales, order)
    # M = R S as nine contiguous columns (the same numbers as rotation_matrices(q) * s[:, None, :]): the products
    # run on contiguous arrays, the same operations in the same order as on M's (N, 3, 3) strides.
    m = scaled_rotation_columns(_rows(g.rotations, order), log_s)
    # The six distinct entries of w (Sigma_i + d d^T), reduced per group (cheaper than (N, 3, 3) products).
    cov = np.empty((n, 6))
    for k, (i, j) in enumerate(_SYM):
        cov[:, k] = (m[3 * i] * m[3 * j] + m[3 * i + 1] * m[3 * j + 1] + m[3 * i + 2] * m[3 * j + 2]
                     + d[:, i] * d[:, j])
    cov *= wn[:, None]
    six = np.add.reduceat(cov, starts)
    merged_cov = np.empty((len(starts), 3, 3))
    for k, (i, j) in enumerate(_SYM):
        merged_cov[:, i, j] = merged_cov[:, j, i] = six[:, k]
    del cov, m

    evals, evecs = np.linalg.eigh(merged_cov)
    # A proper rotation: flip one axis of left-handed eigenbases.
    evecs[:, :, 0] *= _orientation(evecs)[:, None]
    # Flat members stay flat but not flatter than their flattest member (eigh can return ~0 or tiny negatives).
    floor = np.exp(2.0 * np.minimum.reduceat(_row_min(log_s), starts).astype(np.float64))
    evals = np.maximum(evals, floor[:, None])
    # Inside the format's log-scale domain (format.md 4.8): members spread over a huge box merge into a splat
    # whose moment-matched size can exceed what any member had.
    merged_log_scales = np.clip(0.5 * np.log(evals), MIN_LOG_SCALE, MAX_LOG_SCALE)
    merged_rot = _matrices_to_quaternions(evecs)

    merged_mass = np.add.reduceat(mass, starts)
    alpha = merged_mass / _coverage_area(merged_log_scales)
    alpha = np.clip(alpha, 1e-7, MAX_MERGED_OPACITY)
    single = counts == 1
    single_logits = np.take(g.opacity_logits, np.take(order, starts))
    merged_logits = np.where(single, single_logits, np.log(alpha / (1.0 - alpha)))

    wn32 = wn.astype(np.float32)
    sh_dc = _rows(g.sh_dc, order)
    sh_dc *= wn32[:, None]
    sh_dc = np.add.reduceat(sh_dc, starts)
    if g.sh_rest.shape[1]:
        # The largest stream (45 floats a splat at degree 3): gather once, weight in place, reduce as 2D rows.
        sh_rest = _rows(g.sh_rest.reshape(n, -1), order)
        sh_rest *= wn32[:, None]
        sh_rest = group_sums(sh_rest, starts).reshape(len(starts), -1, 3)
    else:
        sh_rest = np.zeros((len(starts), 0, 3), np.float32)

    merged = Gaussians(mu + origin, merged_rot, merged_log_scales, merged_logits, sh_dc, sh_rest)
    assign = np.empty(n, np.int64)
    assign[order] = group_of
    return merged, merged_mass, assign


# Groups of at most this many rows are summed by group_sums itself; numpy's pairwise sum adds fewer than 8 terms
# left to right (numpy/_core/src/umath/loops_utils.h.src, pairwise_sum), so such a group is its first row plus the
# plain sum of the others.
GROUP_SUM_ROWS = 8


def group_sums(a: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """np.add.reduceat(a, starts, axis=0) to the bit, for rows of many columns: reduceat's inner loop runs once per
    group and column (1M rows of 45 float32 in groups of 1-3: 0.83 s), this once per row position in a group
    (0.10 s). numpy's add.reduceat makes each group's sum as its first row plus the pairwise sum of the rest, which
    under 8 terms is a left-to-right sum (GROUP_SUM_ROWS); larger groups take reduceat itself. Equal bits (signed
    zeros, NaN, float32 and float64) are tested against reduceat (tests/test_lod.py)."""
    n = len(a)
    counts = np.diff(np.append(starts, n))
    out = np.take(a, starts, axis=0)
    several = np.flatnonzero((counts > 1) & (counts <= GROUP_SUM_ROWS))
    if len(several):
        rows = starts[several] + 1
        rest = np.take(a, rows, axis=0)  # the pairwise sum of the other rows: the second row, then one by one
        at, left = np.arange(len(several)), counts[several] - 2
        while True:
            more = np.flatnonzero(left > 0)
            if not len(more):
                break
            at, rows, left = at[more], rows[more] + 1, left[more] - 1
            rest[at] += np.take(a, rows, axis=0)
        out[several] += rest
    large = np.flatnonzero(counts > GROUP_SUM_ROWS)
    if len(large):
        sizes = counts[large]
        sub = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        rows = np.repeat(starts[large] - sub, sizes) + np.arange(int(sizes.sum()))
        out[large] = np.add.reduceat(np.take(a, rows, axis=0), sub, axis=0)
    return out


def _alpha(logits: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # a logit below -709: exp overflows to inf, alpha is exactly 0
        return 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))


def level_cost_groups(members: list[Gaussians], masses: list[np.ndarray], targets: list[int], cap: int,
                      rule: GroupRule = COST_RULE, pool: Executor | None = None
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The "cost" merge of one tree level (LOD_MERGES): the groups of every tile's members (`members[t]`, carried
    `masses[t]`), as (order, starts) runs for merge_groups. The level keeps sum(targets) splats in all; where they
    go is decided by cost over the whole level (lod_groups.group_ids with the tiles as regions), not by a ratio per
    tile. A tile left with more than `cap` groups takes the grid at `cap` instead (the tile size limit).
    `pool`: threads for the grouping's k-NN and edge cost blocks (group_ids; the same groups with or without)."""
    counts = np.array([len(m) for m in members], np.int64)
    live = [t for t in range(len(members)) if counts[t]]
    out: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(0, np.int64), np.zeros(0, np.int64))] * len(members)
    if not live:
        return out
    cat = [members[t] for t in live]
    target = sum(max(1, min(targets[t], int(counts[t]))) for t in live)
    # The level's arrays held by the dict only: group_ids_of frees them once it has its own copies.
    ids = group_ids_of({"positions": np.concatenate([m.positions for m in cat]),
                        "log_scales": np.concatenate([m.log_scales for m in cat]),
                        "rotations": np.concatenate([m.rotations for m in cat]),
                        "opacities": _alpha(np.concatenate([m.opacity_logits for m in cat])),
                        "colours": 0.5 + SH_C0 * np.concatenate([m.sh_dc for m in cat]).astype(np.float64),
                        "masses": np.concatenate([masses[t] for t in live]),
                        "region": np.repeat(np.arange(len(live)), counts[live])}, target, rule, pool=pool)
    del cat
    at = 0
    for t in live:
        own = ids[at:at + counts[t]]
        at += int(counts[t])
        order, starts = group_runs(own)
        if len(starts) > cap:
            order, starts = _group_starts(members[t].positions, cap)
        out[t] = (order, starts)
    return out


def choice_error(members: Gaussians, ids: np.ndarray, blur: float, prepared: tuple | None = None) -> float:
    """How far one tile's merged splats are from their members, to choose between groupings (level_auto_groups):
    the squared L2 norm of the colour-premultiplied footprints projected along x, y and z (lod_groups.group_errors)
    of the members against the splats the groups `ids` merge into, both drawn at the viewing blur `blur` (a
    variance added to every axis, as the rasteriser's low-pass) and the merged opacity matched to the members'
    shown coverage at that blur (finish_appearance's rule; the shown coverage also weighs the moments here).
    `prepared`: choice_members(members, blur), when several groupings of the same members are judged."""
    args, terms = prepared or choice_members(members, blur)
    return float(group_errors(members.positions, *args, ids, proj=True, terms=terms).sum())


def choice_members(members: Gaussians, blur: float) -> tuple[tuple, tuple[np.ndarray, np.ndarray]]:
    """choice_error's per-member inputs at `blur`, whatever the grouping: (log scales, rotations, alpha, colours,
    shown coverage) and lod_groups.member_terms of them."""
    with np.errstate(over="ignore"):  # a logit below -709: exp overflows to inf, alpha is exactly 0
        alpha = 1.0 / (1.0 + np.exp(-members.opacity_logits.astype(np.float64)))
    variances = np.exp(2.0 * members.log_scales.astype(np.float64)) + blur
    shown = alpha * _coverage_area(members.log_scales, blur)
    colours = 0.5 + SH_C0 * members.sh_dc.astype(np.float64)
    args = (0.5 * np.log(variances), members.rotations, alpha, colours, shown)
    return args, member_terms(*args[:4], proj=True)


def _take(members: Gaussians, rows: np.ndarray) -> Gaussians:
    """The attributes choice_members reads, of `rows` of `members` (no SH rest: the choice never reads it)."""
    return Gaussians(_rows(members.positions, rows), _rows(members.rotations, rows), _rows(members.log_scales, rows),
                     np.take(members.opacity_logits, rows), _rows(members.sh_dc, rows),
                     np.zeros((len(rows), 0, 3), np.float32))


def _sampled_choice_error(members: Gaussians, ids: np.ndarray, inside: np.ndarray, sample: int, blur: float,
                          prepared: tuple) -> float:
    """choice_error of the groups whose ids are multiples of `sample` (`inside`: their members), from the
    per-member inputs `prepared` of `members` (rows sliced: the same numbers as taken for those rows alone)."""
    args, terms = prepared
    rows = np.flatnonzero(inside)
    return float(group_errors(_rows(members.positions, rows), *(_rows(a, rows) for a in args),
                              np.take(ids, rows) // sample, proj=True,
                              terms=tuple(_rows(t, rows) for t in terms)).sum())


def _run_ids(order: np.ndarray, starts: np.ndarray, n: int) -> np.ndarray:
    ids = np.empty(n, np.int64)
    ids[order] = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, n)))
    return ids


def level_auto_groups(members: list[Gaussians], masses: list[np.ndarray], targets: list[int], cap: int,
                      blurs: list[float], rule: GroupRule | None = None, pool: Executor | None = None,
                      sample: int = AUTO_CHOICE_SAMPLE, judge_every_level: bool = False
                      ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[bool]]:
    """The "auto" merge of one tree level (LOD_MERGES): the cost merge's groups (level_cost_groups), then per tile
    the Morton grid at the same count, and the tile keeps whichever has the smaller choice_error at `blurs[t]`
    (ties: the cost merge; auto_tile_choice, judging every `sample`-th group of each grouping), on the tiles of
    blur 0 (the first merged level) only, or on every tile with `judge_every_level`. The level's total and every
    tile's count are the cost merge's. Returns the groups and, per tile, whether the grid was chosen. `pool`:
    threads for the grouping's blocks and the tiles' choices (each a pure function of its tile: the same result
    with or without)."""
    if rule is None:
        rule = AUTO_FIRST_RULE if all(b == 0.0 for b in blurs) else AUTO_RULE
    groups = level_cost_groups(members, masses, targets, cap, rule, pool)
    # Judged only where the members are the originals (blur 0: the first merged level), unless judge_every_level.
    # Above it the choice took the grid on 0-3 % of the tiles (format_spec/lod.md 6) for as much CPU as the first
    # level's choice; there the cost merge's groups are kept.
    jobs = [t for t in range(len(members)) if judge_every_level or blurs[t] == 0.0]
    if pool is None:
        judged = [auto_tile_choice(members[t], groups[t], blurs[t], sample) for t in jobs]
    else:
        judged = list(pool.map(lambda t: auto_tile_choice(members[t], groups[t], blurs[t], sample), jobs))
    chosen = [(grp, False) for grp in groups]
    for t, pick in zip(jobs, judged, strict=True):
        chosen[t] = pick
    return [grp for grp, _ in chosen], [grid for _, grid in chosen]


def auto_tile_choice(members: Gaussians, groups: tuple[np.ndarray, np.ndarray], blur: float,
                     sample: int = 1) -> tuple[tuple[np.ndarray, np.ndarray], bool]:
    """level_auto_groups' choice for one tile: its cost merge `groups` (order, starts) or the Morton grid at the
    same count, whichever has the smaller choice_error at `blur` (ties: the cost merge); and whether the grid
    was chosen. `sample` > 1: each grouping judged by its groups whose ids (Morton ranks, so spread over the tile)
    are multiples of `sample`, on their members only. Pure: the tiles of a level are judged on any threads in any
    order."""
    order, starts = groups
    n, k = len(members), len(starts)
    if n == 0 or k >= n:
        return groups, False
    g_order, g_starts = _group_starts(members.positions, k)
    if len(g_starts) != k:  # the grid can fall short of a count (too few cells to split): the cost merge
        return groups, False
    cost_ids, grid_ids = _run_ids(order, starts, n), _run_ids(g_order, g_starts, n)
    if sample > 1:  # every sample-th group of each grouping (ids follow the Morton order: spread over the tile)
        cost_in, grid_in = cost_ids % sample == 0, grid_ids % sample == 0
        judged = np.flatnonzero(cost_in | grid_in)
        members, cost_ids, grid_ids = _take(members, judged), np.take(cost_ids, judged), np.take(grid_ids, judged)
        cost_in, grid_in = np.take(cost_in, judged), np.take(grid_in, judged)
    prepared = choice_members(members, blur)  # the same members judged twice
    if sample > 1:
        cost_err = _sampled_choice_error(members, cost_ids, cost_in, sample, blur, prepared)
        grid_err = _sampled_choice_error(members, grid_ids, grid_in, sample, blur, prepared)
    else:
        cost_err = choice_error(members, cost_ids, blur, prepared)
        grid_err = choice_error(members, grid_ids, blur, prepared)
    if grid_err < cost_err:
        return (g_order, g_starts), True
    return groups, False


# ---------------------------------------------------------------------------------------------- tree shape


@dataclass(frozen=True)
class TreeShape:
    """The shape of the tile tree of `splats` splats. It depends on the splat count and the options only, so every
    worker of a partitioned encode derives the same ids from it."""

    splats: int
    max_leaf_splats: int
    reduction: float
    depth: int  # kd depth of the leaves
    kd_depths: tuple[int, ...]  # kd depth of each tile level, the root's (0) first; equal depths: a chain
    first_id: tuple[int, ...]  # first tile id of each level (breadth-first); the last entry is the tile count

    @staticmethod
    def of(splats: int, max_leaf_splats: int, reduction: float) -> TreeShape:
        """Levels `reduction` apart in splats (the leaves N, the level above N / reduction, ...) up to a root of
        about 0.25 % of the scene (ROOT_FRACTION, between ROOT_MIN_SPLATS and ROOT_MAX_SPLATS). The kd depth of a
        level is the deepest whose tiles still hold about `min_tile_splats` splats: the top levels are many small
        tiles (so a splat budget can be spent in small steps), and below the leaves' kd depth a level is a chain
        (each tile one child covering the same region with `reduction` times its splats)."""
        if max_leaf_splats < 1:
            raise ValueError(f"max_leaf_splats must be at least 1, got {max_leaf_splats}")
        if not reduction > 1.0:
            raise ValueError(f"reduction must be above 1, got {reduction}")
        if splats <= max_leaf_splats:
            return TreeShape(splats, max_leaf_splats, float(reduction), 0, (0,), (0, 1))
        depth = math.ceil(math.log2(splats / max_leaf_splats))
        # At least MIN_LEAF_TILES leaves where each keeps MIN_LEAF_TILE_SPLATS: the budgets of a few percent of a
        # scene of 32k to 500k splats need tiles that small to be spent without waste.
        if splats >= MIN_LEAF_TILES * MIN_LEAF_TILE_SPLATS:
            depth = max(depth, int(math.log2(MIN_LEAF_TILES)))
        root = min(ROOT_MAX_SPLATS, max(ROOT_MIN_SPLATS, ROOT_FRACTION * splats))
        above = max(1, math.ceil(math.log(splats / root) / math.log(reduction) - 1e-9))
        tile_min = min(max(splats / MIN_TILES_FOR_SMALLEST, MIN_TILE_SPLATS), max_leaf_splats / 4)
        kd = [0]
        for lvl in range(1, above):
            level_splats = splats / reduction ** (above - lvl)
            fits = int(math.floor(math.log2(max(1.0, level_splats / tile_min))))
            kd.append(min(depth, max(kd[-1], fits)))
        kd.append(depth)
        first_id = tuple(int(v) for v in np.cumsum([0] + [2**k for k in kd]))
        return TreeShape(splats, max_leaf_splats, float(reduction), depth, tuple(kd), first_id)

    def target(self, members: int) -> int:
        """Splats of an interior tile whose children hold `members` splats."""
        return max(1, min(self.max_leaf_splats, math.ceil(members / self.reduction)))

    @property
    def leaf_level(self) -> int:
        return len(self.kd_depths) - 1

    @property
    def tiles(self) -> int:
        return self.first_id[-1]

    def tile_id(self, level: int, position: int) -> int:
        """Id of the `position`-th tile (kd order) of tile level `level`."""
        return self.first_id[level] + position

    def fan(self, level: int) -> int:
        """Children of each tile of `level`."""
        return 2 ** (self.kd_depths[level + 1] - self.kd_depths[level])

    def children(self, level: int, position: int) -> list[int]:
        fan = self.fan(level)
        return [self.tile_id(level + 1, position * fan + k) for k in range(fan)]


# ---------------------------------------------------------------------------------------------- kd splits


def sort_keys(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """uint64 keys that order splats by (value, global index): the float32 value's bits made order-preserving in
    the high half (-0.0 sorts before +0.0), the splat's index in the input in the low half. Keys are unique, so a
    median split by key is the same on every machine and in every partitioning (numpy's argpartition on the values
    alone puts ties on either side arbitrarily)."""
    bits = np.ascontiguousarray(values, np.float32).view(np.uint32)
    ordered = np.where(bits >> np.uint32(31), ~bits, bits | np.uint32(0x80000000))
    return (ordered.astype(np.uint64) << np.uint64(32)) | index.astype(np.uint64)


def split_axis(lo: np.ndarray, hi: np.ndarray) -> int:
    """The kd split axis of a node from its centre box (float32 min and max): the longest side, first on ties."""
    return int(np.argmax(hi - lo))


def kd_split(positions: np.ndarray, index: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Median split of the splats `rows` (ascending): (lower rows, upper rows, axis, pivot key). The lower half
    holds the len(rows) // 2 splats of smallest key on the longest axis; both halves stay ascending."""
    p = _rows(positions, rows)
    axis = split_axis(column_min(p), column_max(p))
    keys = sort_keys(p[:, axis], index[rows])
    pivot = np.partition(keys, len(rows) // 2)[len(rows) // 2]
    below = keys < pivot
    return rows[below], rows[~below], axis, int(pivot)


def kd_route(positions: np.ndarray, index: np.ndarray, splits: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The kd node (at depth len(splits)) of every splat, from the splits of the levels above: per level, each
    node's axis and pivot key (a splat goes up when its key is >= the pivot)."""
    node = np.zeros(len(positions), np.int64)
    rows = np.arange(len(positions))
    for axes, pivots in splits:
        keys = sort_keys(positions[rows, axes[node]], index)
        node = 2 * node + (keys >= pivots[node])
    return node


def _kd_leaves(positions: np.ndarray, index: np.ndarray, levels: int, progress: Progress) -> list[np.ndarray]:
    """`levels` rounds of median splits; leaf row sets (ascending) in kd order."""
    nodes = [np.arange(len(positions))]
    for level in range(levels):
        nodes = [half for rows in nodes for half in kd_split(positions, index, rows)[:2]]
        progress("lod-split", (level + 1) / levels)
    return nodes


def _leaf_orders(positions: np.ndarray, leaves: list[np.ndarray]) -> np.ndarray:
    """Concatenated leaf row sets, each in 3D Morton order over its own centre box (ties: input order)."""
    return np.concatenate([rows[np.argsort(_morton(_rows(positions, rows)), kind="stable")] for rows in leaves])


def _permute(g: Gaussians, perm: np.ndarray) -> Gaussians:
    # One gather per attribute; leaves are then slices (views) of these arrays.
    return Gaussians(*(_rows(getattr(g, name), perm) for name in
                       ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest")))


def _permute_in_place(g: Gaussians, perm: np.ndarray, block_floats: int = 12) -> Gaussians:
    """Reorder the rows of `g`'s own arrays by `perm`, a few columns at a time, so the extra memory is
    n * block_floats floats instead of a second copy of the scene."""
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        arr = getattr(g, name)
        flat = arr.reshape(len(arr), -1)  # a view: the arrays are C-contiguous
        for c in range(0, flat.shape[1], block_floats):
            flat[:, c:c + block_floats] = _rows(flat[:, c:c + block_floats], perm)
    return g


def _slice(g: Gaussians, a: int, b: int) -> Gaussians:
    return Gaussians(g.positions[a:b], g.rotations[a:b], g.log_scales[a:b], g.opacity_logits[a:b],
                     g.sh_dc[a:b], g.sh_rest[a:b])


# ---------------------------------------------------------------------------------------------- reductions over
# the ORIGINAL splats a merged splat stands for. A partitioned encode computes them for the tiles above its
# partitions from the workers' partial results, so each is either exact in any order (max, min, integer counts)
# or a float sum taken in one fixed order: per leaf tile (np.bincount, in the leaf's row order), then the leaves'
# sums added in kd order (fold_leaf_sums). The same code runs whether the leaves sit on one machine or many.


def original_reach(g: Gaussians | np.ndarray) -> np.ndarray:
    """Radius of each splat's ERROR_SIGMAS ball along its largest axis (world units), from splats or log scales."""
    log_scales = g.log_scales if isinstance(g, Gaussians) else g
    return ERROR_SIGMAS * np.exp(_row_max(log_scales).astype(np.float64))


def error_extremes(positions: np.ndarray, reach: np.ndarray, merged_positions: np.ndarray, rep: np.ndarray,
                   size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per merged splat, max of (d_i + r_i) and min of (d_i - r_i) over the originals i it stands for (d_i: the
    distance of their centres). Exact in any order: partial results combine with np.maximum / np.minimum."""
    mu = _rows(merged_positions.astype(np.float64), rep)
    dist = _row_norm(positions.astype(np.float64) - mu)
    far = np.full(size, -np.inf)
    np.maximum.at(far, rep, dist + reach)
    near = np.full(size, np.inf)
    np.minimum.at(near, rep, dist - reach)
    return far, near


def errors_from_extremes(far: np.ndarray, near: np.ndarray, merged: Gaussians | np.ndarray) -> np.ndarray:
    """Per merged splat, the Hausdorff bound e_m of lod.md section 3 (world units), from error_extremes: the union
    of the members' balls sticks out of the merged ball by max(d + r) - R; the merged ball reaches beyond the best
    covering member by min(d - r) + R. (Subtracting R after the max is the same float result as before it.)"""
    radius = original_reach(merged) if isinstance(merged, Gaussians) else merged
    return np.maximum(np.maximum(far - radius, near + radius), 0.0)


def merge_errors(originals_pos: np.ndarray, originals_reach: np.ndarray, merged: Gaussians,
                 assign: np.ndarray) -> np.ndarray:
    """Per merged splat, a bound on the Hausdorff distance between the union of its ORIGINAL members' balls and
    its own ball (balls of ERROR_SIGMAS standard deviations along the largest axis), in world units."""
    far, near = error_extremes(originals_pos, originals_reach, merged.positions, assign, len(merged))
    return errors_from_extremes(far, near, merged)


def tile_error(errors: np.ndarray, counts: np.ndarray) -> float:
    """ERROR_STAT over a tile's originals, each original counting with its merged splat's error, from the
    (error, member count) pairs: np.quantile(np.repeat(errors, counts), q) (linear interpolation) without the
    repeat, so counts summed over workers give the exact value."""
    keep = counts > 0
    e, c = errors[keep], counts[keep]
    if not len(e):
        return 0.0
    if ERROR_STAT == "max":
        return float(e.max())
    order = np.argsort(e, kind="stable")
    e = e[order]
    ends = np.cumsum(c[order])
    n = int(ends[-1])
    q = float(ERROR_STAT)
    virtual = (n - 1) * q
    below = min(int(math.floor(virtual)), n - 1)
    frac = virtual - below
    a = e[np.searchsorted(ends, below, side="right")]
    b = e[np.searchsorted(ends, min(below + 1, n - 1), side="right")]
    return float(a + (b - a) * frac) if frac < 0.5 else float(b - (b - a) * (1.0 - frac))


def viewing_blur(error: float) -> float:
    """The low-pass variance (world units squared) of a tile drawn at OPACITY_MATCH_SSE_PX screen-space error."""
    pixel = error / OPACITY_MATCH_SSE_PX
    return LOW_PASS_PX2 * pixel * pixel


def viewing_scale_px(child_error: float, above: int = 1) -> float:
    """The screen-space error (px) at which an interior tile's opacities and colours are matched: the first merged
    level (its children are the originals: their error is 0) at OPACITY_MATCH_SSE_PX, the level `above` levels above
    it at OPACITY_MATCH_FAR_SSE_PX x OPACITY_MATCH_FAR_GROWTH^(above - 1), at most OPACITY_MATCH_FAR_CAP_SSE_PX
    (lod.md 6, step 5; with the defaults every level above at OPACITY_MATCH_FAR_SSE_PX). `above`: the tree's leaf
    level - 1 - the tile's level, which both encoders know."""
    if child_error == 0.0:
        return OPACITY_MATCH_SSE_PX
    if OPACITY_MATCH_FAR_GROWTH == 1.0:
        return min(OPACITY_MATCH_FAR_SSE_PX, OPACITY_MATCH_FAR_CAP_SSE_PX)
    return min(OPACITY_MATCH_FAR_SSE_PX * OPACITY_MATCH_FAR_GROWTH ** (max(above, 1) - 1),
               OPACITY_MATCH_FAR_CAP_SSE_PX)


def viewing_scales_px() -> tuple[float, ...] | None:
    """Step 5's viewing scales as the encoder uses them now (read at the call, so a bench's or test's change of the
    constants is what the manifest records): px on the first merged level, then on each level above it up to the
    first at the cap, the last on every level above (viewing_scale_px of k = 0, 1, ...): (2, 8) where the levels above
    share one scale (the 1.9 record), (2, 8, 12, 16) with the defaults (the 1.10 record). None (not recorded) where the
    scale grows without a cap: no finite list says it."""
    scales = [float(OPACITY_MATCH_SSE_PX), float(viewing_scale_px(1.0, 1))]
    if OPACITY_MATCH_FAR_GROWTH == 1.0 or scales[1] >= OPACITY_MATCH_FAR_CAP_SSE_PX:
        return tuple(scales)
    if not (OPACITY_MATCH_FAR_GROWTH > 1.0 and math.isfinite(OPACITY_MATCH_FAR_CAP_SSE_PX)):
        return None
    while scales[-1] < OPACITY_MATCH_FAR_CAP_SSE_PX:
        scales.append(float(viewing_scale_px(1.0, len(scales))))
    return tuple(scales)


def tile_viewing_blur(error: float, child_error: float, above: int = 1) -> float:
    """The viewing blur of a tile of geometric error `error` whose children's largest error is `child_error`, `above`
    levels above the first merged one: at viewing_scale_px(child_error, above). Where that is OPACITY_MATCH_SSE_PX it
    is viewing_blur(error) itself, which the older probes (bench/probe_lod_*.py) replace to try other scales."""
    px = viewing_scale_px(child_error, above)
    if px == OPACITY_MATCH_SSE_PX:
        return viewing_blur(error)
    return LOW_PASS_PX2 * (error / px) ** 2


APPEARANCE_TERMS = 5  # shown coverage, colour weight, colour weight x SH band 0 (3)


def appearance_terms(opacity_logits: np.ndarray, log_scales: np.ndarray, sh_dc: np.ndarray,
                     blur: float) -> np.ndarray:
    """(5, N) per original: its coverage as the rasteriser shows it after the blur (alpha x dilated area), the
    colour weight (the same, kept positive) and the weight times each SH band 0 channel."""
    with np.errstate(over="ignore"):  # a logit below -709: exp overflows to inf, alpha is exactly 0
        alpha = 1.0 / (1.0 + np.exp(-opacity_logits.astype(np.float64)))
    shown = alpha * _coverage_area(log_scales, blur)
    weight = shown + 1e-300  # all-transparent groups still get a defined colour
    return np.stack([shown, weight, weight * sh_dc[:, 0], weight * sh_dc[:, 1], weight * sh_dc[:, 2]])


def leaf_sums(rep: np.ndarray, terms: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """One leaf's sums of `terms` per merged splat: (merged splats present, (terms, present) sums in row order)."""
    present = np.flatnonzero(np.bincount(rep, minlength=size))
    return present, np.stack([np.bincount(rep, weights=t, minlength=size)[present] for t in terms])


def fold_leaf_sums(parts: list[tuple[np.ndarray, np.ndarray]], size: int) -> np.ndarray:
    """The leaves' sums (leaf_sums, in kd order) added one leaf after the other: (terms, size)."""
    acc = np.zeros((APPEARANCE_TERMS, size))
    for present, sums in parts:
        acc[:, present] += sums
    return acc


def finish_appearance(merged: Gaussians, counts: np.ndarray, sums: np.ndarray, blur: float) -> None:
    """Set the opacities and base colours (SH band 0) of merged splats, in place, from their ORIGINAL members as
    the renderer draws them at the tile's viewing scale (`sums`: fold_leaf_sums of appearance_terms).

    3DGS rasterisers add a 0.3 px^2 low-pass to every projected covariance without lowering the opacity, so a
    sub-pixel splat covers about opacity * (dilated area), far more than its mass. Coarse tiles are drawn when
    their members are small on screen (b: a pixel where the tile's error spans OPACITY_MATCH_SSE_PX). Plain mass
    preservation then loses coverage (holes, dark silhouettes) and lets big members outweigh the many small ones
    that dominate the picture (fine sprinkles on a donut's icing).
    Both sides are therefore measured after the same blur b: alpha = sum alpha_i A(Sigma_i + b) / A(Sigma + b),
    colour = mean of the members' colours weighted by alpha_i A(Sigma_i + b). Higher SH bands keep the
    hierarchical mass-weighted mean (view-dependent residuals, cheap).

    Scales are left as moment matching made them. Growing them where alpha hits the ceiling (up to 1.25x, the
    rule of the 4x tree) compounded level after level on the 2x tree and lowered every level's PSNR (BENCHMARKS.md,
    "LOD merges")."""
    covered, total = sums[0], sums[1]
    single = counts == 1
    alpha = np.clip(covered / _coverage_area(merged.log_scales, blur), 1e-7, MAX_MERGED_OPACITY)
    logits = np.log(alpha / (1.0 - alpha)).astype(np.float32)
    sh_dc = sums[2:5].T / total[:, None]
    # A splat standing for one original is that original (merge_gaussians copies singletons).
    merged.opacity_logits = np.where(single, merged.opacity_logits, logits)
    merged.sh_dc = np.where(single[:, None], merged.sh_dc, sh_dc.astype(np.float32))


def tile_error_first(merged: Gaussians, counts: np.ndarray, far: np.ndarray, near: np.ndarray,
                     child_error: float) -> tuple[np.ndarray, float]:
    """An interior tile's per-splat errors and its error (at least its children's), before its appearance."""
    errors = errors_from_extremes(far, near, merged)
    return errors, max(tile_error(errors, counts), child_error)


def finish_tile_appearance(merged: Gaussians, counts: np.ndarray, far: np.ndarray, near: np.ndarray,
                           errors: np.ndarray, error: float, sums: np.ndarray, child_error: float,
                           above: int = 1) -> float:
    """Opacities and colours matched at the viewing scale of `error` (`sums`: the folded appearance_terms at
    tile_viewing_blur(error, child_error, above)); returns the tile's error."""
    finish_appearance(merged, counts, sums, tile_viewing_blur(error, child_error, above))
    return error


def finish_tile(merged: Gaussians, counts: np.ndarray, far: np.ndarray, near: np.ndarray, child_error: float,
                appearance: Callable[[float], np.ndarray], above: int = 1) -> float:
    """The last steps of an interior tile, the same wherever its originals are: the error, then opacities and
    colours matched at that error's viewing scale (`appearance(blur)` gives the folded sums; `above`: the tile's
    levels above the first merged one, viewing_scale_px). Returns the tile's geometric error; `merged` is changed in
    place."""
    errors, error = tile_error_first(merged, counts, far, near, child_error)
    sums = appearance(tile_viewing_blur(error, child_error, above))
    return finish_tile_appearance(merged, counts, far, near, errors, error, sums, child_error, above)


def interior_bounds(merged: Gaussians, kids: list[Tile]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Box and sphere of an interior tile: its merged splats' extents and its children's volumes (so culling a
    parent never hides a child)."""
    lo, hi, own_c, own_r = extent_bounds(merged)
    lo = np.minimum(lo, np.min([k.box_min for k in kids], axis=0))
    hi = np.maximum(hi, np.max([k.box_max for k in kids], axis=0))
    c = (lo + hi) / 2
    r = max(float(np.linalg.norm(k.sphere_center - c)) + k.sphere_radius for k in kids)
    r = max(r, float(np.linalg.norm(own_c - c)) + own_r)
    return lo, hi, c, r


# ---------------------------------------------------------------------------------------------- tree


@dataclass
class Subtree:
    """The tiles of one subtree (the whole tree, or a partition of a partitioned encode) and what the tiles above
    it need from its originals."""

    tiles: dict[int, Tile]  # by global id
    root: Tile
    root_mass: np.ndarray  # carried merge weights of the root's splats
    ordered: Gaussians  # the subtree's original splats in leaf order; leaves are slices of it
    leaf_starts: np.ndarray  # (leaves + 1,) row offsets of the leaves in `ordered`
    represented_by: np.ndarray  # per row of `ordered`: the root splat standing for it


# The default thread count of a tree's merges: most of the work holds the interpreter lock, so more threads add CPU
# and memory, not speed. The 1M encode on the GPU machine's 16 cores (BENCHMARKS.md, "Payload processes forked
# before the tree's threads", the lead's thread-count runs): 16 threads 20.2 / 21.7 s wall, 59-62 CPU s, 1,103 MB
# PSS; 4: 20.4 / 18.1 s, 45-51 CPU s; 2: 20.4 / 19.8 s, 42-43 CPU s, 846-930 MB; 1: 23.3 / 28.4 s.
TREE_THREADS = 2


def build_subtree(g: Gaussians, index: np.ndarray, shape: TreeShape, level: int = 0, position: int = 0,
                  progress: Progress | None = None, reorder_input: bool = False, threads: int | None = None,
                  merge: str = "grid", on_level: Callable[[list[Tile]], None] | None = None) -> Subtree:
    """The tiles under tile `position` of tile level `level` (the whole tree for level 0), from exactly that
    subtree's splats `g`, whose global indices `index` are ascending (the input's order). `merge`: LOD_MERGES.

    Leaves are slices of one array per attribute holding the splats in leaf order: a copy of `g` by default, or,
    with `reorder_input`, `g`'s own arrays reordered in place, which saves a copy. `on_level` hears each level's
    tiles once they are final (the leaves first, then each merged level): their splats are not written again, so
    a caller may encode them while the levels above are merged (encode/forked.py). The leaves' call comes before
    the merge pool's threads start (forked.py forks its children there)."""
    if merge not in LOD_MERGES:
        raise ValueError(f"unknown LOD merge {merge!r} (one of {', '.join(LOD_MERGES)})")
    progress = progress or (lambda stage, fraction: None)
    kd0 = shape.kd_depths[level]
    leaves = _kd_leaves(g.positions, index, shape.depth - kd0, progress)
    perm = _leaf_orders(g.positions, leaves)
    ordered = _permute_in_place(g, perm) if reorder_input else _permute(g, perm)
    del perm
    progress("lod-leaves", 1.0)

    def span(lvl: int) -> int:  # tiles of tile level `lvl` in this subtree
        return 2 ** (shape.kd_depths[lvl] - kd0)

    leaf_level = shape.leaf_level
    leaf_starts = np.cumsum([0] + [len(rows) for rows in leaves])
    del leaves
    tiles: dict[int, Tile] = {}
    spans: dict[int, tuple[int, int]] = {}  # tile id -> its leaves (first, end) in leaf order
    masses: dict[int, np.ndarray] = {}
    # For each original splat of the tile's span: index of the tile splat that represents it.
    represented_by: dict[int, np.ndarray] = {}
    for j in range(span(leaf_level)):
        tid = shape.tile_id(leaf_level, position * span(leaf_level) + j)
        a, b = int(leaf_starts[j]), int(leaf_starts[j + 1])
        part = _slice(ordered, a, b)
        spans[tid] = (j, j + 1)
        lo, hi, c, r = extent_bounds(part)
        tiles[tid] = Tile(tid, leaf_level, [], part, 0.0, lo, hi, c, r)
        masses[tid] = splat_mass(part)
        represented_by[tid] = np.arange(b - a)
    reach = original_reach(ordered)
    if on_level is not None:
        on_level([tiles[shape.tile_id(leaf_level, position * span(leaf_level) + j)] for j in range(span(leaf_level))])

    total_merges = sum(span(lvl) for lvl in range(level, leaf_level))
    merges_done = 0

    def tile_members(lvl: int, kids: list[Tile], first: int, end: int) -> Gaussians:
        # Leaf children are adjacent slices of `ordered`: merge them in place instead of copying.
        if lvl == leaf_level - 1:
            return _slice(ordered, int(leaf_starts[first]), int(leaf_starts[end]))
        return Gaussians.concatenate([k.gaussians for k in kids])

    def merge_tile(lvl: int, tid: int, child_ids: list[int], kids: list[Tile], member_mass: np.ndarray,
                   kid_reps: list[np.ndarray], first: int, end: int,
                   groups: tuple[np.ndarray, np.ndarray] | None = None, members: Gaussians | None = None
                   ) -> tuple[Tile, np.ndarray, np.ndarray]:
        """One interior tile from its children (pure: reads `ordered`, writes nothing shared); `groups`: the
        level's cost merge for this tile (level_cost_groups) with the `members` it grouped, else the grid."""
        a, b = int(leaf_starts[first]), int(leaf_starts[end])
        if members is None:
            members = tile_members(lvl, kids, first, end)
        if groups is None:
            merged, merged_mass, assign = merge_gaussians(members, member_mass, shape.target(len(members)))
        else:
            merged, merged_mass, assign = merge_groups(members, member_mass, *groups)
        del members
        offsets = np.cumsum([0] + [len(k.gaussians) for k in kids])
        rep = np.take(assign, np.concatenate([r + offsets[k] for k, r in enumerate(kid_reps)]))
        size = len(merged)
        # Errors and appearance are measured against the originals (lod.md 3, 6).
        far, near = error_extremes(ordered.positions[a:b], reach[a:b], merged.positions, rep, size)

        def appearance(blur: float) -> np.ndarray:
            parts = []
            for leaf in range(first, end):
                s, e = int(leaf_starts[leaf]), int(leaf_starts[leaf + 1])
                terms = appearance_terms(ordered.opacity_logits[s:e], ordered.log_scales[s:e],
                                         ordered.sh_dc[s:e], blur)
                parts.append(leaf_sums(rep[s - a:e - a], terms, size))
            return fold_leaf_sums(parts, size)

        error = finish_tile(merged, np.bincount(rep, minlength=size), far, near,
                            max(k.geometric_error for k in kids), appearance, leaf_level - 1 - lvl)
        lo, hi, c, r = interior_bounds(merged, kids)
        return Tile(tid, lvl, child_ids, merged, error, lo, hi, c, r), merged_mass, rep

    # The tiles of one level are independent: merged on threads (numpy's sorts, reductions and eigh release the
    # interpreter), each a pure function of its children, so the tree is the same with any number of threads.
    with ThreadPoolExecutor(max_workers=max(1, threads or min(TREE_THREADS, available_cores()))) as pool:
        for lvl in range(leaf_level - 1, level - 1, -1):
            jobs = []
            level_tiles = []
            for j in range(span(lvl)):
                tid = shape.tile_id(lvl, position * span(lvl) + j)
                child_ids = shape.children(lvl, position * span(lvl) + j)
                first, end = spans[child_ids[0]][0], spans[child_ids[-1]][1]
                spans[tid] = (first, end)
                level_tiles.append((tid, child_ids, first, end))
            groups: list = [None] * len(level_tiles)
            sets: list = [None] * len(level_tiles)
            member_masses = [np.concatenate([masses.pop(c) for c in kids]) for _, kids, _, _ in level_tiles]
            if merge != "grid":  # one grouping over the whole level (the tiles as regions), then merged per tile
                # (the members and masses gathered once: merge_tile takes the same sets). The grouping's k-NN
                # and edge cost blocks, and auto's per-tile choices, run on the pool (the same groups as on one
                # thread: each block and tile is a pure function of its inputs).
                sets = [tile_members(lvl, [tiles[c] for c in kids], first, end)
                        for _, kids, first, end in level_tiles]
                targets = [shape.target(len(m)) for m in sets]
                if merge == "cost":
                    groups = level_cost_groups(sets, member_masses, targets, shape.max_leaf_splats, pool=pool)
                else:  # "auto": judged at the viewing scale of the children's error (0 above the leaves)
                    blurs = [viewing_blur(max(tiles[c].geometric_error for c in kids))
                             for _, kids, _, _ in level_tiles]
                    groups, _ = level_auto_groups(sets, member_masses, targets, shape.max_leaf_splats, blurs,
                                                  pool=pool)
            for i, ((tid, child_ids, first, end), grp) in enumerate(zip(level_tiles, groups, strict=True)):
                jobs.append(pool.submit(merge_tile, lvl, tid, child_ids, [tiles[c] for c in child_ids],
                                        member_masses[i], [represented_by.pop(c) for c in child_ids], first, end,
                                        grp, sets[i]))
                sets[i] = member_masses[i] = groups[i] = None  # the job holds them now; merge_tile frees them
            for job in jobs:
                tile, merged_mass, rep = job.result()
                tiles[tile.id] = tile
                masses[tile.id] = merged_mass
                represented_by[tile.id] = rep
                merges_done += 1
                progress("lod-merge", merges_done / total_merges)
            if on_level is not None:
                on_level([tiles[tid] for tid, _, _, _ in level_tiles])
    root_id = shape.tile_id(level, position)
    if not total_merges:
        progress("lod-merge", 1.0)
    return Subtree(tiles, tiles[root_id], masses[root_id], ordered, leaf_starts, represented_by[root_id])


def build_tiles(g: Gaussians, max_leaf_splats: int = 16384, reduction: float = 2.0,
                progress: Progress | None = None, reorder_input: bool = False, merge: str = "grid",
                on_level: Callable[[list[Tile]], None] | None = None) -> list[Tile]:
    """The LOD tile tree of `g`, as a list indexed by tile id (0 = root, breadth-first); `merge`: LOD_MERGES.

    Leaves are slices of one array per attribute holding the splats in leaf order: a copy of `g` by default, or,
    with `reorder_input`, `g`'s own arrays reordered in place (the caller's `g` then holds the same splats in
    another order), which saves a copy of the whole scene. `on_level`: build_subtree's."""
    shape = TreeShape.of(len(g), max_leaf_splats, reduction)
    if len(g) == 0:
        progress and progress("lod-merge", 1.0)
        return [Tile(0, 0, [], g, 0.0, *extent_bounds(g))]
    sub = build_subtree(g, np.arange(len(g)), shape, 0, 0, progress, reorder_input, merge=merge, on_level=on_level)
    return [sub.tiles[i] for i in range(shape.tiles)]
