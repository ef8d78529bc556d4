"""LOD tile tree: a spatial tree of tiles whose leaves partition the original splats and whose interior tiles
hold merged (moment-matched) Gaussians standing in for their whole subtree (normative text: format_spec/lod.md).

Shape. A balanced kd-tree of median splits on the longest axis of the splat centres cuts the scene into 2**d
leaves of at most `max_leaf_splats` splats each (median splits adapt to density: dense regions get small tiles).
Tile levels take every log2(branching) kd depths, branching = 2**round(log2(reduction)): with reduction 4 a tile
has 4 children, with 8 it has 8; the root may have fewer. Refinement is REPLACE.

Merging. An interior tile merges the concatenation of its children's sets down to ceil(count / reduction)
(never above max_leaf_splats). Groups are cells of a binary Morton-prefix grid over the tile: the longest prefix
with at most that many cells, the most populated cells split once more to hit the count. A uniform grid per tile,
so sparse regions keep their splats and dense ones merge. Each group becomes one Gaussian by moment matching
with weights w = opacity * (mean cross-section s1 s2 + s2 s3 + s1 s3); w is carried up the tree, so every level
matches the moments of the ORIGINAL mixture. Opacity and base colour are then matched to the originals as the
rasteriser shows them at the tile's viewing scale (see match_screen_appearance), higher SH bands are the
w-weighted means.

Geometric error (world units): per merged splat, a bound on the Hausdorff distance between its original members'
1-sigma balls and its own; a tile's error is the 99th percentile of that over the originals it stands for (each
original counts with its merged splat's error), at least its children's errors (monotone), 0 for leaves.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .format.layout import morton_codes
from .format.limits import MAX_LOG_SCALE, MIN_LOG_SCALE
from .gaussians import Gaussians, normalize_quaternions, rotation_matrices

# Bounds and errors use this many standard deviations (the 3DGS rasteriser's cut-off and KHR "ellipse" kernel).
EXTENT_SIGMAS = 3.0
# Merged opacity ceiling (the rasteriser's own clamp); a splat standing for a single original keeps its opacity.
MAX_MERGED_OPACITY = 0.99
# Variance (px^2) the rasteriser adds to projected covariances (reference 3DGS), and the screen-space error (px)
# at which coarse tiles are meant to be seen: their opacities are matched at that scale.
LOW_PASS_PX2 = 0.3
OPACITY_MATCH_SSE_PX = 1.0
# Error statistic over a tile's ORIGINAL splats, each taking the error of the merged splat that stands for it
# (so untouched singletons cannot hide a merged blob): "max" is a strict bound; a quantile ignores a few outliers.
ERROR_STAT: str | float = 0.99
# Standard deviations of the balls the error compares: at 1 sigma, merging two point-like splats d apart costs
# about d, the size of the detail lost (3 sigma would double it; the client's threshold would absorb the factor).
ERROR_SIGMAS = 1.0
# Largest growth of a merged splat's scales spent on coverage its opacity cannot carry (see
# match_screen_appearance). Measured on the real scenes: 1.0 loses up to 19 % of a far root's coverage, 1.5 puts
# faint halos around small objects, 1.25 keeps coverage within 13 % without halos.
MAX_INFLATION = 1.25

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


def _sigma_axes(g: Gaussians) -> np.ndarray:
    """(N, 3) world-axis standard deviations sqrt(diag Sigma): the half-extents of the 1-sigma ellipsoid's box."""
    r = rotation_matrices(g.rotations)
    s2 = np.exp(2.0 * g.log_scales.astype(np.float64))
    return np.sqrt(np.einsum("nij,nj->ni", r * r, s2))


def extent_bounds(g: Gaussians, sigmas: float = EXTENT_SIGMAS) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Exact box of the splats' `sigmas`-sigma ellipsoids, and a sphere (centred on the box) covering them."""
    if len(g) == 0:
        z = np.zeros(3)
        return z, z.copy(), z.copy(), 0.0
    p = g.positions.astype(np.float64)
    half = sigmas * _sigma_axes(g)
    lo = _col_min(p - half)
    hi = _col_max(p + half)
    center = (lo + hi) / 2
    reach = sigmas * np.exp(_row_max(g.log_scales).astype(np.float64))
    radius = float((_row_norm(p - center) + reach).max())
    return lo, hi, center, radius


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _row_max(a: np.ndarray) -> np.ndarray:
    # Column-wise maximum of an (N, 3) array: much faster than a.max(axis=1) on short rows.
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _row_min(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _row_norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1] + a[:, 2] * a[:, 2])


def _col_min(a: np.ndarray) -> np.ndarray:
    # Per-column reductions of an (N, 3) array; numpy's axis=0 reduction is ~30x slower on this shape.
    return np.array([a[:, k].min() for k in range(a.shape[1])])


def _col_max(a: np.ndarray) -> np.ndarray:
    return np.array([a[:, k].max() for k in range(a.shape[1])])


def _morton(positions: np.ndarray) -> np.ndarray:
    """Morton codes over the positions' own box (layout.morton_codes, box computed column-wise)."""
    return morton_codes(positions, _col_min(positions), _col_max(positions))


def _matrices_to_quaternions(r: np.ndarray) -> np.ndarray:
    """(N, 4) unit (w, x, y, z) quaternions of proper rotation matrices, branch-free (Shepperd's method)."""
    m00, m01, m02 = r[:, 0, 0], r[:, 0, 1], r[:, 0, 2]
    m10, m11, m12 = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    m20, m21, m22 = r[:, 2, 0], r[:, 2, 1], r[:, 2, 2]
    # Four candidate solutions, each well conditioned when its leading component is the largest.
    cands = np.stack([
        np.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], 1),
        np.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], 1),
        np.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], 1),
        np.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], 1),
    ], 1)
    pick = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], 1), axis=1)
    q = cands[np.arange(len(r)), pick]
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
    """Morton order of the splats and the start index of each group in that order (about `target` groups).

    Groups are cells of the binary Morton-prefix grid (prefix length b splits the box b times, cycling x, y, z).
    We take the longest prefix with at most `target` cells, then split the most populated cells once more."""
    n = len(positions)
    codes = _morton(positions)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    if target >= n:
        return order, np.arange(n)

    def boundaries(bits: int) -> np.ndarray:
        key = codes >> np.uint64(63 - bits)
        return key[1:] != key[:-1]

    lo_bits, hi_bits = 0, 63  # invariant: cells(lo_bits) <= target
    if 1 + int(np.count_nonzero(boundaries(hi_bits))) <= target:
        lo_bits = hi_bits
    while hi_bits - lo_bits > 1:
        mid = (lo_bits + hi_bits) // 2
        if 1 + int(np.count_nonzero(boundaries(mid))) <= target:
            lo_bits = mid
        else:
            hi_bits = mid
    bnd = boundaries(lo_bits)
    cells = 1 + int(np.count_nonzero(bnd))
    if cells < target and lo_bits < 63:
        finer = boundaries(lo_bits + 1)
        cell_of = np.concatenate([[0], np.cumsum(bnd)])  # cell index per splat (sorted order)
        cell_start = np.concatenate([[0], np.flatnonzero(bnd) + 1])
        sizes = np.diff(np.append(cell_start, n))
        splittable = np.zeros(cells, bool)
        splittable[cell_of[1:][finer & ~bnd]] = True
        # Split the biggest cells first: evens out group sizes, which keeps merged splats of similar size.
        candidates = np.flatnonzero(splittable)
        extra = min(target - cells, len(candidates))
        chosen = candidates[np.argsort(-sizes[candidates], kind="stable")[:extra]]
        split = np.zeros(cells, bool)
        split[chosen] = True
        bnd = bnd | (finer & split[cell_of[1:]])
    starts = np.concatenate([[0], np.flatnonzero(bnd) + 1])
    return order, starts


def merge_gaussians(g: Gaussians, mass: np.ndarray, target: int) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """Merge `g` (with carried masses) into about `target` Gaussians in Morton order.

    Returns the merged Gaussians, their masses (sums of the members' masses) and for each input splat the
    index of the merged splat it went into."""
    n = len(g)
    if n == 0:
        return g, mass, np.zeros(0, np.int64)
    order, starts = _group_starts(g.positions, max(1, target))
    counts = np.diff(np.append(starts, n))
    group_of = np.repeat(np.arange(len(starts)), counts)

    mass = mass[order]
    w = mass + 1e-300  # all-transparent groups still get a defined (uniform) mean
    wsum = np.add.reduceat(w, starts)
    wn = w / wsum[group_of]  # normalised weights, sum to 1 per group

    p = g.positions[order].astype(np.float64)
    origin = p.mean(axis=0)  # work relative to the set's centre for precision
    p -= origin
    mu = np.add.reduceat(p * wn[:, None], starts)
    d = p - mu[group_of]
    rot = rotation_matrices(g.rotations[order])
    log_s = g.log_scales[order]
    m = rot * np.exp(log_s.astype(np.float64))[:, None, :]
    # The six distinct entries of w (Sigma_i + d d^T), reduced per group (cheaper than (N, 3, 3) products).
    cov = np.empty((n, 6))
    for k, (i, j) in enumerate(_SYM):
        cov[:, k] = (m[:, i, 0] * m[:, j, 0] + m[:, i, 1] * m[:, j, 1] + m[:, i, 2] * m[:, j, 2] + d[:, i] * d[:, j])
    cov *= wn[:, None]
    six = np.add.reduceat(cov, starts)
    merged_cov = np.empty((len(starts), 3, 3))
    for k, (i, j) in enumerate(_SYM):
        merged_cov[:, i, j] = merged_cov[:, j, i] = six[:, k]
    del cov, m, rot

    evals, evecs = np.linalg.eigh(merged_cov)
    # A proper rotation: flip one axis of left-handed eigenbases.
    evecs[:, :, 0] *= np.sign(np.linalg.det(evecs))[:, None]
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
    merged_logits = np.where(single, g.opacity_logits[order][starts], np.log(alpha / (1.0 - alpha)))

    wn32 = wn.astype(np.float32)
    sh_dc = g.sh_dc[order]
    sh_dc *= wn32[:, None]
    sh_dc = np.add.reduceat(sh_dc, starts)
    if g.sh_rest.shape[1]:
        # The largest stream (45 floats a splat at degree 3): gather once, weight in place, reduce as 2D rows.
        sh_rest = g.sh_rest.reshape(n, -1)[order]
        sh_rest *= wn32[:, None]
        sh_rest = np.add.reduceat(sh_rest, starts).reshape(len(starts), -1, 3)
    else:
        sh_rest = np.zeros((len(starts), 0, 3), np.float32)

    merged = Gaussians(mu + origin, merged_rot, merged_log_scales, merged_logits, sh_dc, sh_rest)
    assign = np.empty(n, np.int64)
    assign[order] = group_of
    return merged, merged_mass, assign


# ---------------------------------------------------------------------------------------------- tree


def merge_errors(originals_pos: np.ndarray, originals_reach: np.ndarray, merged: Gaussians,
                 assign: np.ndarray) -> np.ndarray:
    """Per merged splat, a bound on the Hausdorff distance between the union of its ORIGINAL members' balls and
    its own ball (balls of ERROR_SIGMAS standard deviations along the largest axis), in world units.

    The union's farthest point outside the merged ball is max(dist + r_i - R); the merged ball's farthest point
    outside the union is at most min(dist + R - r_i) (its distance to any one member ball bounds it)."""
    mu = merged.positions.astype(np.float64)[assign]
    big = ERROR_SIGMAS * np.exp(_row_max(merged.log_scales).astype(np.float64))
    dist = _row_norm(originals_pos.astype(np.float64) - mu)
    poke = np.full(len(merged), -np.inf)
    np.maximum.at(poke, assign, dist + originals_reach - big[assign])
    overreach = np.full(len(merged), np.inf)
    np.minimum.at(overreach, assign, dist - originals_reach + big[assign])
    return np.maximum(np.maximum(poke, overreach), 0.0)


def match_screen_appearance(merged: Gaussians, originals: Gaussians, represented_by: np.ndarray,
                            pixel: float) -> np.ndarray:
    """Set the opacities and base colours (SH band 0) of merged splats, in place, from their ORIGINAL members
    as the renderer draws them at the tile's viewing scale: pixels of `pixel` world units.

    3DGS rasterisers add a 0.3 px^2 low-pass to every projected covariance without lowering the opacity, so a
    sub-pixel splat covers about opacity * (dilated area), far more than its mass. Coarse tiles are drawn exactly
    when their members are sub-pixel. Plain mass preservation then loses coverage (holes, dark silhouettes) and
    lets big members outweigh the many small ones that dominate the picture (fine sprinkles on a donut's icing).
    Both sides are therefore measured after the same blur b: alpha = sum alpha_i A(Sigma_i + b) / A(Sigma + b),
    colour = mean of the members' colours weighted by alpha_i A(Sigma_i + b). Higher SH bands keep the
    hierarchical mass-weighted mean (view-dependent residuals, cheap). Where alpha would exceed the ceiling the
    scales grow by up to MAX_INFLATION instead; returns the indices of the merged splats that grew."""
    blur = LOW_PASS_PX2 * pixel * pixel
    with np.errstate(over="ignore"):
        alpha_i = 1.0 / (1.0 + np.exp(-originals.opacity_logits.astype(np.float64)))
    shown = alpha_i * _coverage_area(originals.log_scales, blur)
    covered = np.bincount(represented_by, weights=shown, minlength=len(merged))
    single = np.bincount(represented_by, minlength=len(merged)) == 1
    need = covered / _coverage_area(merged.log_scales, blur)
    grow_rows = np.zeros(0, np.int64)
    if MAX_INFLATION > 1.0:
        # More coverage than one Gaussian can give under the opacity ceiling: the members' sum is flat-topped
        # with a sharp rim, the merged Gaussian peaked and soft, so clamping drops coverage at silhouettes.
        # Spend the excess on size: the smallest growth k of the scales with cap * A(k^2 Sigma + b) >= covered.
        grow_rows = np.flatnonzero((need > MAX_MERGED_OPACITY) & ~single)
        if len(grow_rows):
            ls = merged.log_scales[grow_rows].astype(np.float64)
            lo_k, hi_k = np.zeros(len(grow_rows)), np.full(len(grow_rows), math.log(MAX_INFLATION))
            for _ in range(20):
                mid = (lo_k + hi_k) / 2
                ok = MAX_MERGED_OPACITY * _coverage_area(ls + mid[:, None], blur) >= covered[grow_rows]
                hi_k = np.where(ok, mid, hi_k)
                lo_k = np.where(ok, lo_k, mid)
            merged.log_scales[grow_rows] = np.minimum(ls + hi_k[:, None], MAX_LOG_SCALE).astype(np.float32)
            need[grow_rows] = covered[grow_rows] / _coverage_area(merged.log_scales[grow_rows], blur)
    alpha = np.clip(need, 1e-7, MAX_MERGED_OPACITY)
    logits = np.log(alpha / (1.0 - alpha)).astype(np.float32)
    weight = shown + 1e-300
    total = np.bincount(represented_by, weights=weight, minlength=len(merged))
    sh_dc = np.stack([np.bincount(represented_by, weights=weight * originals.sh_dc[:, k], minlength=len(merged))
                      for k in range(3)], 1) / total[:, None]
    # A splat standing for one original is that original (merge_gaussians copies singletons).
    merged.opacity_logits = np.where(single, merged.opacity_logits, logits)
    merged.sh_dc = np.where(single[:, None], merged.sh_dc, sh_dc.astype(np.float32))
    return grow_rows


def _tile_error(errors: np.ndarray) -> float:
    if not len(errors):
        return 0.0
    if ERROR_STAT == "max":
        return float(errors.max())
    return float(np.quantile(errors, float(ERROR_STAT)))


def _kd_leaves(positions: np.ndarray, depth: int, progress: Progress) -> list[np.ndarray]:
    """Balanced kd-tree by median splits on the longest centre-box axis; leaf index sets in kd order."""
    nodes = [np.arange(len(positions))]
    for level in range(depth):
        split: list[np.ndarray] = []
        for idx in nodes:
            p = positions[idx]
            axis = int(np.argmax(_col_max(p) - _col_min(p)))
            half = len(idx) // 2
            part = np.argpartition(p[:, axis], half)
            split += [idx[part[:half]], idx[part[half:]]]
        nodes = split
        progress("lod-split", (level + 1) / depth)
    return nodes


def _leaf_orders(positions: np.ndarray, leaves: list[np.ndarray]) -> np.ndarray:
    """Concatenated leaf index sets, each in 3D Morton order over its own centre box."""
    return np.concatenate([idx[np.argsort(_morton(positions[idx]), kind="stable")] for idx in leaves])


def _permute(g: Gaussians, perm: np.ndarray) -> Gaussians:
    # One gather per attribute; leaves are then slices (views) of these arrays.
    return Gaussians(g.positions[perm], g.rotations[perm], g.log_scales[perm], g.opacity_logits[perm],
                     g.sh_dc[perm], g.sh_rest[perm])


def _permute_in_place(g: Gaussians, perm: np.ndarray, block_floats: int = 12) -> Gaussians:
    """Reorder the rows of `g`'s own arrays by `perm`, a few columns at a time, so the extra memory is
    n * block_floats floats instead of a second copy of the scene."""
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        arr = getattr(g, name)
        flat = arr.reshape(len(arr), -1)  # a view: the arrays are C-contiguous
        for c in range(0, flat.shape[1], block_floats):
            flat[:, c:c + block_floats] = flat[perm, c:c + block_floats]
    return g


def _slice(g: Gaussians, a: int, b: int) -> Gaussians:
    return Gaussians(g.positions[a:b], g.rotations[a:b], g.log_scales[a:b], g.opacity_logits[a:b],
                     g.sh_dc[a:b], g.sh_rest[a:b])


def build_tiles(g: Gaussians, max_leaf_splats: int = 65536, reduction: float = 4.0,
                progress: Progress | None = None, reorder_input: bool = False) -> list[Tile]:
    """The LOD tile tree of `g`, as a list indexed by tile id (0 = root, breadth-first).

    Leaves are slices of one array per attribute holding the splats in leaf order: a copy of `g` by default, or,
    with `reorder_input`, `g`'s own arrays reordered in place (the caller's `g` then holds the same splats in
    another order), which saves a copy of the whole scene."""
    if max_leaf_splats < 1:
        raise ValueError(f"max_leaf_splats must be at least 1, got {max_leaf_splats}")
    if not reduction > 1.0:
        raise ValueError(f"reduction must be above 1, got {reduction}")
    progress = progress or (lambda stage, fraction: None)
    n = len(g)
    if n <= max_leaf_splats:
        order = np.argsort(_morton(g.positions), kind="stable") if n else np.zeros(0, np.int64)
        leaf = _permute_in_place(g, order) if reorder_input else _permute(g, order)
        lo, hi, c, r = extent_bounds(leaf)
        progress("lod-merge", 1.0)
        return [Tile(0, 0, [], leaf, 0.0, lo, hi, c, r)]

    depth = math.ceil(math.log2(n / max_leaf_splats))
    step = max(1, round(math.log2(reduction)))  # kd depths per tile level
    # kd depths that are tile levels: the leaves, every `step` above them, and the root.
    kd_depths = sorted({0, *range(depth, 0, -step)})
    leaves = _kd_leaves(g.positions, depth, progress)
    perm = _leaf_orders(g.positions, leaves)
    ordered = _permute_in_place(g, perm) if reorder_input else _permute(g, perm)
    del perm
    progress("lod-leaves", 1.0)

    # Breadth-first ids: level L holds 2**kd_depths[L] tiles in kd order. A tile's subtree covers one
    # contiguous range of `ordered` (leaves are kd-ordered), which the error pass compares against.
    first_id = np.cumsum([0] + [2**k for k in kd_depths])
    tiles: list[Tile | None] = [None] * int(first_id[-1])
    spans: dict[int, tuple[int, int]] = {}
    masses: dict[int, np.ndarray] = {}
    # For each original splat of the tile's span: index of the tile splat that represents it.
    represented_by: dict[int, np.ndarray] = {}
    leaf_level = len(kd_depths) - 1
    start = 0
    for j, idx in enumerate(leaves):
        tid = int(first_id[leaf_level]) + j
        part = _slice(ordered, start, start + len(idx))
        spans[tid] = (start, start + len(idx))
        start += len(idx)
        lo, hi, c, r = extent_bounds(part)
        tiles[tid] = Tile(tid, leaf_level, [], part, 0.0, lo, hi, c, r)
        masses[tid] = splat_mass(part)
        represented_by[tid] = np.arange(len(idx))
    del leaves
    reach = ERROR_SIGMAS * np.exp(_row_max(ordered.log_scales).astype(np.float64))

    total_merges = int(first_id[leaf_level])
    merges_done = 0
    for level in range(leaf_level - 1, -1, -1):
        fan = 2 ** (kd_depths[level + 1] - kd_depths[level])
        for j in range(2 ** kd_depths[level]):
            tid = int(first_id[level]) + j
            child_ids = [int(first_id[level + 1]) + j * fan + k for k in range(fan)]
            kids = [tiles[c] for c in child_ids]
            a, b = spans[child_ids[0]][0], spans[child_ids[-1]][1]
            spans[tid] = (a, b)
            # Leaf children are adjacent slices of `ordered`: merge them in place instead of copying.
            members = (_slice(ordered, a, b) if level == leaf_level - 1
                       else Gaussians.concatenate([k.gaussians for k in kids]))
            member_mass = np.concatenate([masses.pop(c) for c in child_ids])
            target = min(max_leaf_splats, math.ceil(len(members) / reduction))
            merged, merged_mass, assign = merge_gaussians(members, member_mass, target)
            del members, member_mass
            offsets = np.cumsum([0] + [len(k.gaussians) for k in kids])
            represented_by[tid] = assign[np.concatenate(
                [represented_by.pop(c) + offsets[k] for k, c in enumerate(child_ids)])]
            originals = _slice(ordered, a, b)
            masses[tid] = merged_mass
            # Errors are measured against the originals; the max with the children keeps them monotone.
            rep = represented_by[tid]
            errors = merge_errors(originals.positions, reach[a:b], merged, rep)
            error = max(_tile_error(errors[rep]), *(k.geometric_error for k in kids))
            grown = match_screen_appearance(merged, originals, rep, error / OPACITY_MATCH_SSE_PX)
            if len(grown):
                # Some splats grew to carry their coverage: measure those again, keep the larger tile error.
                is_grown = np.zeros(len(merged), bool)
                is_grown[grown] = True
                sel = is_grown[rep]
                errors[grown] = merge_errors(originals.positions[sel], reach[a:b][sel], merged, rep[sel])[grown]
                error = max(error, _tile_error(errors[rep]))
            lo, hi, own_c, own_r = extent_bounds(merged)
            # The parent's volume also encloses its children's, so culling a parent never hides a child.
            lo = np.minimum(lo, np.min([k.box_min for k in kids], axis=0))
            hi = np.maximum(hi, np.max([k.box_max for k in kids], axis=0))
            c = (lo + hi) / 2
            r = max(float(np.linalg.norm(k.sphere_center - c)) + k.sphere_radius for k in kids)
            r = max(r, float(np.linalg.norm(own_c - c)) + own_r)
            tiles[tid] = Tile(tid, level, child_ids, merged, error, lo, hi, c, r)
            merges_done += 1
            progress("lod-merge", merges_done / total_merges)
    return tiles  # type: ignore[return-value]
