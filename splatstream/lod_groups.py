"""Merge groups chosen by cost (issue 31): which splats of a level become one splat of the next.

The tree's merge (lod.merge_groups: mass weights, moment matching) is kept; this module only chooses the groups,
as plain functions over numpy arrays that return, for every splat, the id of its group (exactly `target` groups,
deterministic). The Morton grid the tree uses today (grid_group_starts) lives here too.

group_ids: rounds of greedy matchings between clusters (at first every splat is a cluster). In each round every
cluster is the moment-matched Gaussian of its members; the edges of the level's k-NN graph (approximate: the
nearest among the neighbours in three shifted Morton orders, numpy only) are mapped onto clusters and costed, and
pairs are matched cheapest first (every free cluster takes its cheapest free neighbour, mutual choices are matched,
repeated) up to `share` of what is left to remove, so cheap regions merge again in the next round while costly
splats stay single. Groups are capped per level (`max_group` members; optionally a first stage of pairs only). A
last pass over Morton-adjacent clusters finishes the count where no edge is left (coincident or isolated
clusters). Cost of merging a and b into m: the squared L2 norm of a_a c_a G_a + a_b c_b G_b - a_m c_m G_m (the
colour-premultiplied footprints; opacity of m = mass / area, as merge_groups makes it), in 3D as splat-transform's
decimator (`proj=0`) or summed over the footprints projected along x, y and z (`proj=1`: a flat or thin splat keeps
its weight, where in 3D its sqrt(det) makes it free to merge), plus splat-transform's scale-free colour term.

hybrid_group_ids: no single rule held on every scene (BENCHMARKS.md, "LOD groups by cost": the cap-4 rule keeps
faint or isolated splats apart and wins on fruit_drops and the statues' finest levels, pairs first win on the donut
and the statues' coarse levels, the grid on the flowers' finest level). So each level takes the candidate whose
merged splats, drawn by proxy_views (6 orthographic views, footprints alpha-composited front to back in numpy),
are closest to the level's own splats drawn the same way.
"""
from __future__ import annotations

import math
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from .format.layout import morton_codes
from .gaussians import scaled_rotation_columns

_SYM6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_TWO_PI_1_5 = (2 * math.pi) ** 1.5
_PI_1_5 = math.pi ** 1.5
# The three axis-aligned views: the two axes kept and the (uu, uv, vv) entries of the six.
_PLANES = (((1, 2), (3, 4, 5)), ((0, 2), (0, 2, 5)), ((0, 1), (0, 1, 3)))
# splat-transform's colour weight in base-colour space (4 pi 1e-6 over f_dc): keeps light and dark apart at any size.
COLOUR_WEIGHT = 4 * math.pi * 1e-6


@dataclass(frozen=True)
class GroupRule:
    neighbours: int = 8  # K nearest clusters costed per cluster and round
    shifts: int = 3  # shifted Morton orders the approximate k-NN draws its candidates from
    window: int = 0  # candidates at ranks +-1 .. +-window in each order (0: neighbours)
    share: float = 0.5  # each round removes at most this share of what is left to remove
    colour: float = 1.0  # times COLOUR_WEIGHT
    proj: int = 0  # 1: field-L2 of the splats' footprints projected along x, y and z (2D), summed; 0: in 3D
    first_cap: int = 0  # first rounds with groups of at most this many members (0: none; at least n / target)
    first_share: float = 1.0  # share of the level's merges the first stage makes at most
    max_group: int = 0  # then groups of at most this many members (splats of the level; 0: no cap; at least
    # twice n / target)
    max_rounds: int = 64
    tail: float = 0.0  # a round whose merges still needed are at most this share of the clusters takes them all


DEFAULT_RULE = GroupRule()


# ---------------------------------------------------------------------------------------------- 3x3 helpers


def _det6(c: np.ndarray) -> np.ndarray:
    xx, xy, xz, yy, yz, zz = (c[:, k] for k in range(6))
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def _quad6(c: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d^T C^-1 d and det C for symmetric 3x3 C stored as (xx, xy, xz, yy, yz, zz)."""
    xx, xy, xz, yy, yz, zz = (c[:, k] for k in range(6))
    c00, c01, c02 = yy * zz - yz * yz, xz * yz - xy * zz, xy * yz - xz * yy
    c11, c12, c22 = xx * zz - xz * xz, xy * xz - xx * yz, xx * yy - xy * xy
    det = np.maximum(xx * c00 + xy * c01 + xz * c02, 1e-300)
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    q = c00 * dx * dx + c11 * dy * dy + c22 * dz * dz + 2 * (c01 * dx * dy + c02 * dx * dz + c12 * dy * dz)
    return q / det, det


def _eig6(c: np.ndarray) -> np.ndarray:
    """(N, 3) eigenvalues of symmetric 3x3 matrices (closed form, largest first)."""
    return np.maximum(np.stack(_eig6_columns(c), 1), 1e-300)


def _eig6_columns(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_eig6's three columns before the floor at 1e-300 (largest first). Each difference xx - q and the factor
    2 p taken once (they were written twice), the rest in place: the same operations on the same numbers."""
    xx, xy, xz, yy, yz, zz = (c[:, k] for k in range(6))
    q = xx + yy
    q += zz
    q /= 3
    p1 = xy * xy
    p1 += xz * xz
    p1 += yz * yz
    b00, b11, b22 = xx - q, yy - q, zz - q  # (xx - q) etc., divided by p below
    p2 = np.square(b00)
    p2 += np.square(b11)
    p2 += np.square(b22)
    p1 *= 2
    p2 += p1
    p2 /= 6
    p = np.sqrt(np.maximum(p2, 1e-300, out=p2), out=p2)
    b00 /= p
    b11 /= p
    b22 /= p
    b01, b02, b12 = xy / p, xz / p, yz / p
    det_b = b11 * b22
    det_b -= b12 * b12
    det_b *= b00
    t = b01 * b22
    t -= b12 * b02
    t *= b01
    det_b -= t
    t = b01 * b12
    t -= b11 * b02
    t *= b02
    det_b += t
    det_b /= 2
    phi = np.arccos(np.clip(det_b, -1, 1, out=det_b), out=det_b)
    phi /= 3
    p *= 2
    e0 = np.cos(phi)
    e0 *= p
    e0 += q
    phi += 2 * math.pi / 3
    e2 = np.cos(phi, out=phi)
    e2 *= p
    e2 += q
    q *= 3
    q -= e0
    q -= e2
    return e0, q, e2


def _area6(c: np.ndarray) -> np.ndarray:
    """Mean cross-section proxy s1 s2 + s2 s3 + s1 s3 (lod._coverage_area) of covariances stored as six."""
    s0, s1, s2 = (np.sqrt(np.maximum(e, 1e-300, out=e), out=e) for e in _eig6_columns(c))
    return s0 * s1 + s1 * s2 + s0 * s2


def covariances6(rotations: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """(N, 6) covariances (xx, xy, xz, yy, yz, zz) of unit quaternions (w, x, y, z) and log scales."""
    # M = R S as nine contiguous columns (the same numbers as rotation_matrices(q) * s[:, None, :]), so the products
    # below run on contiguous arrays: the same operations in the same order as on M's (N, 3, 3) strides, 2-3x faster.
    m = scaled_rotation_columns(rotations, log_scales)
    cov = np.empty((len(rotations), 6))
    for k, (a, b) in enumerate(_SYM6):
        cov[:, k] = m[3 * a] * m[3 * b] + m[3 * a + 1] * m[3 * b + 1] + m[3 * a + 2] * m[3 * b + 2]
    return cov


# ---------------------------------------------------------------------------------------------- the Morton grid


def morton(positions: np.ndarray) -> np.ndarray:
    """Morton codes over the positions' own box (per-column reductions: numpy's axis=0 is slow on (N, 3))."""
    lo = np.array([positions[:, k].min() for k in range(3)])
    hi = np.array([positions[:, k].max() for k in range(3)])
    return morton_codes(positions, lo, hi)


def grid_group_starts(positions: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Morton order of the splats and the start index of each group in that order (about `target` groups).

    Groups are cells of the binary Morton-prefix grid (prefix length b splits the box b times, cycling x, y, z).
    We take the longest prefix with at most `target` cells, then split the most populated cells once more."""
    n = len(positions)
    codes = morton(positions)
    order = np.argsort(codes, kind="stable")
    codes = np.take(codes, order)
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


# ---------------------------------------------------------------------------------------------- neighbours


def neighbour_edges(p: np.ndarray, k: int, shifts: int = 3, block: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges (i < j) from every point to about its k nearest: the k nearest among the 2k points around
    it in each of `shifts` Morton orders of shifted boxes (numpy only; exact k-NN is not needed for grouping).
    Ties in distance go to the lower id. The candidates are gathered `block` points at a time (each point's
    neighbours depend on the orders only), so the (points, 2k shifts) work arrays stay a few MB at any size."""
    parts = list(_neighbour_blocks(p, k, shifts, block))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j = np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts])
    return np.minimum(i, j), np.maximum(i, j)  # an edge both ends found comes twice: harmless for the matching


def neighbour_keys(p: np.ndarray, k: int, shifts: int = 3, block: int = 4096, pool: Executor | None = None,
                   window: int = 0) -> np.ndarray:
    """The distinct edges of neighbour_edges as sorted keys i * n + j (i < j), for group_ids: made block by block
    (each block's repeats dropped at once), so the level's edges are never held as four (2 k n) index arrays.
    `pool`: threads to make the blocks on (each block is a pure function of the orders, and numpy's sorts and
    gathers release the interpreter), in any order; the keys are the same."""
    n = len(p)

    def block_keys(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        # A block's keys come in runs (row by row, each row's neighbours in id order): the stable sort (a timsort
        # of integers) takes them 2x faster than the default; the integers sorted are the same.
        return _distinct(np.minimum(i, j) * n + np.maximum(i, j), kind="stable")

    if pool is None or n <= block:
        keys = [block_keys(i, j) for i, j in _neighbour_blocks(p, k, shifts, block, ordered=False, window=window)]
    else:
        ctx = _neighbour_context(p, k, shifts, window)
        keys = list(pool.map(lambda r0: block_keys(*_neighbour_block(ctx, r0, block, False)), range(0, n, block)))
        del ctx
    if not keys:
        return np.zeros(0, np.int64)
    every = np.concatenate(keys)
    del keys  # the blocks' keys freed before the sort, which is in place: two copies of the keys at most, not four
    every.sort(kind="stable")  # sorted runs (the blocks' keys): merged by the timsort, 20x the default sort
    return np.compress(np.concatenate([[True], every[1:] != every[:-1]]), every)


def _shifted_orders(p: np.ndarray, k: int, shifts: int, window: int = 0) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The (shifts, n) Morton orders of the shifted boxes and each point's rank in them (int64), and the k and
    the window w (candidates at ranks +-1 .. +-w) that n points allow; n at least 2."""
    n = len(p)
    k = min(k, n - 1)
    w = min(max(k, window), (n - 1) // 2 + 1)
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = float((hi - lo).max()) or 1.0
    orders = np.empty((shifts, n), np.int32 if n < 2**31 else np.int64)
    ranks = np.empty((shifts, n), np.int64)
    for s in range(shifts):
        off = span * np.array([0.0, 0.0, 0.0]) if s == 0 else span * np.array([0.31, 0.17, 0.43]) * s / shifts
        codes = morton_codes(p, lo - off, lo - off + 2.0 * span if s else hi)
        order = np.argsort(codes, kind="stable")
        ranks[s, order] = np.arange(n)
        orders[s] = order
    return orders, ranks, k, w


def _neighbour_context(p: np.ndarray, k: int, shifts: int, window: int = 0) -> tuple:
    """What every block of _neighbour_blocks reads: the shifted orders and ranks, k, the rank steps and the
    coordinates as contiguous columns; n at least 2."""
    orders, ranks, k, w = _shifted_orders(p, k, shifts, window)
    steps = np.stack([np.arange(1, w + 1), -np.arange(1, w + 1)], axis=1).reshape(-1)  # +1, -1, +2, -2, ...
    px, py, pz = (np.ascontiguousarray(p[:, a]) for a in range(3))
    return len(p), orders, ranks, k, steps, px, py, pz


def _neighbour_block(ctx: tuple, r0: int, block: int, ordered: bool) -> tuple[np.ndarray, np.ndarray]:
    """The (points, neighbours) index arrays of points r0 .. r0 + block (_neighbour_blocks); pure."""
    n, orders, ranks, k, steps, px, py, pz = ctx
    r1 = min(n, r0 + block)
    rows = np.arange(r0, r1)
    # np.take, rank rows as a slice: the same candidates as order[clip(rank[rows, None] + steps)], 0.87x the time.
    c = np.concatenate([np.take(order, np.clip(rank[r0:r1, None] + steps, 0, n - 1))
                        for order, rank in zip(orders, ranks, strict=True)], axis=1)
    # (rows, 2 w shifts) candidates, self and duplicates included. Duplicates: keep the first of each
    # candidate (sort by id, mark repeats); then the squared distances of the sorted ids.
    cs = np.sort(c, axis=1)  # integers: any sort gives the same rows (the SIMD quicksort is ~13x the stable)
    del c
    # dx dx + dy dy + dz dz, in place, the gathers by intp ids (an int32 index is converted on every gather).
    at = cs.astype(np.intp)
    d2s = np.take(px, at)  # np.take: 0.7x the fancy gather's time
    d2s -= px[r0:r1, None]
    d2s *= d2s
    for pc in (py, pz):
        t = np.take(pc, at)
        t -= pc[r0:r1, None]
        t *= t
        d2s += t
    del at, t
    # Self and repeats (a candidate equal to the one before it in its sorted row) as one mask, one masked write.
    # The repeats compared over the flat rows at once (one contiguous pass, not one short loop per row), each row's
    # first column then cleared: the same mask as cs[:, 1:] == cs[:, :-1] beside a False column.
    drop = np.empty(cs.shape, bool)
    flat, dflat = cs.reshape(-1), drop.reshape(-1)
    np.equal(flat[1:], flat[:-1], out=dflat[1:])
    drop[:, 0] = False
    drop |= cs == rows[:, None]
    np.copyto(d2s, np.inf, where=drop)
    del drop
    if not ordered:  # the k smallest, ties to the lower id (the earlier column), as the stable sort picks
        thr = np.partition(d2s, k - 1, axis=1)[:, k - 1:k]
        thr[np.isnan(thr)] = np.inf  # fewer than k numbers: all the finite ones, as below
        sel = d2s <= thr  # k per row (at most k - 1 below the k-th smallest), but where the k-th is tied
        over = np.flatnonzero(np.count_nonzero(sel, axis=1) > k)
        if len(over):  # of the ties at the k-th, the first ones (lower ids) up to k
            d, t = d2s[over], thr[over]
            less, tie = d < t, d == t
            sel[over] = less | (tie & (np.cumsum(tie, axis=1) <= (k - less.sum(axis=1))[:, None]))
        short = np.flatnonzero(np.isinf(thr[:, 0]))  # rows of fewer than k candidates: their finite ones
        if len(short):
            sel[short] &= np.isfinite(d2s[short])
        # The selected (row, column) pairs in row-major order, as np.nonzero(sel) lists them (0.87x its time).
        return np.repeat(rows, np.count_nonzero(sel, axis=1)), np.compress(sel.reshape(-1), cs).astype(np.int64)
    pick = np.argsort(d2s, axis=1, kind="stable")[:, :k]
    nb = np.take_along_axis(cs, pick, axis=1).reshape(-1)
    ok = np.isfinite(np.take_along_axis(d2s, pick, axis=1)).reshape(-1)
    return np.repeat(rows, k)[ok], nb[ok].astype(np.int64)


def _neighbour_blocks(p: np.ndarray, k: int, shifts: int, block: int, ordered: bool = True, window: int = 0):
    """neighbour_edges' (points, neighbours) index arrays, `block` points at a time; each point's neighbours
    nearest first, or (`ordered` False) the same neighbours in id order, chosen by a partition, not a sort."""
    n = len(p)
    if n < 2:
        return
    ctx = _neighbour_context(p, k, shifts, window)
    for r0 in range(0, n, block):
        yield _neighbour_block(ctx, r0, block, ordered)


# ---------------------------------------------------------------------------------------------- costs


def row_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.einsum("ij,ij->i", a, b) of (N, 3) float64 rows, to the bit, in under half its time (einsum's loop per row
    of three is the cost): numpy's sum-of-products loop adds a row's products as ((a0 b0 + a2 b2) + a1 b1) onto its
    zero start (+ 0.0, which turns -0.0 into 0.0). The grouping's choices hang on these bits, so
    tests/test_lod_groups.py checks them against einsum on rows of special values (signed zeros, subnormals, inf,
    NaN) and random rows."""
    with np.errstate(over="ignore", invalid="ignore"):  # einsum warns of nothing
        out = a[:, 0] * b[:, 0]
        out += a[:, 2] * b[:, 2]
        out += a[:, 1] * b[:, 1]
        out += 0.0
    return out


def _energy(alpha: np.ndarray, col2: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """<f, f> of one splat's colour-premultiplied field a c G: a^2 |c|^2 pi^1.5 sqrt(det)."""
    return _PI_1_5 * alpha * alpha * col2 * np.sqrt(np.maximum(_det6(cov), 1e-300))


def edge_costs(mu, cov, alpha, col, w, i, j, rule: GroupRule, block: int = 16384,
               pool: Executor | None = None) -> np.ndarray:
    """Cost of merging clusters i and j (arrays of edges) under `rule`, `block` edges at a time (the costs are
    per edge, so blocks only bound the work arrays: about 40 float64 per edge and block, not per edge of a level).
    `pool`: threads to cost the blocks on (numpy's ufuncs release the interpreter); each block's numbers are the
    same whoever computes them."""
    out = np.empty(len(i))
    if not len(i):
        return out
    # Positions and covariances as rows of one coordinate (3, N) and (6, N): every term below is then computed on
    # contiguous arrays (the same operations, in the same order, as on the columns of (N, 3) and (N, 6)).
    mu_t, cov_t = np.ascontiguousarray(mu.T), np.ascontiguousarray(cov.T)

    def one(s: int) -> None:
        out[s:s + block] = _edge_costs(mu_t, cov_t, alpha, col, w, i[s:s + block], j[s:s + block], rule)

    _run_blocks(one, len(i), block, pool)
    return out


def _run_blocks(one, n: int, block: int, pool: Executor | None) -> None:
    """one(s) for the start s of every block of `block` of n items: on `pool` where there is more than one block."""
    if pool is None or n <= block:
        for s in range(0, n, block):
            one(s)
    else:
        for _ in pool.map(one, range(0, n, block)):
            pass


def _rows_where(mask: np.ndarray, dtype, chunk: int = 1 << 20) -> np.ndarray:
    """np.flatnonzero(mask) as `dtype` (int32 where the rows allow), a chunk at a time: no int64 copy of them."""
    return np.concatenate([np.flatnonzero(mask[s:s + chunk]).astype(dtype) + dtype(s)
                           for s in range(0, len(mask), chunk)] or [np.zeros(0, dtype)])


def edge_costs_at(out: np.ndarray, rows: np.ndarray, mu, cov, alpha, col, w, i, j, rule: GroupRule,
                  block: int = 16384, pool: Executor | None = None) -> None:
    """out[rows] = edge_costs of the edges (i[rows], j[rows]), a cost that is not finite written as the largest
    float64: the same blocks of `block` edges as edge_costs(..., i[rows], j[rows]) (so the same numbers to the
    bit), without the (rows) copies of the ends and of the costs."""
    if not len(rows):
        return
    mu_t, cov_t = np.ascontiguousarray(mu.T), np.ascontiguousarray(cov.T)

    def one(s: int) -> None:
        r = rows[s:s + block]
        c = _edge_costs(mu_t, cov_t, alpha, col, w, np.take(i, r), np.take(j, r), rule)
        c[~np.isfinite(c)] = np.finfo(np.float64).max
        out[r] = c

    _run_blocks(one, len(rows), block, pool)


def _cross3(sda, sdb, csum, dd):
    q, det = _quad6(csum, dd)
    return _TWO_PI_1_5 * sda * sdb / np.sqrt(det) * np.exp(-0.5 * q)


def _cross2(ca, cb, da, db, dd, u, v):
    """<G_a, G_b> of 2D Gaussians (uu, uv, vv) ca and cb with determinants da and db, centres dd apart."""
    # In place on four work arrays: the operations (and their order) of
    #     det = max(a cc - b b, 1e-300), q = (cc du du - 2 b du dv + a dv dv) / det,
    #     g = 2 pi sqrt(da db / det) exp(-0.5 q)
    # with a, b, cc the sums of the two footprints' entries: the same numbers, without a new array per operation.
    a, b, cc = np.add(ca[0], cb[0]), np.add(ca[1], cb[1]), np.add(ca[2], cb[2])
    du, dv = dd[u], dd[v]
    det = np.multiply(a, cc)
    t = np.multiply(b, b)
    det -= t
    np.maximum(det, 1e-300, out=det)
    with np.errstate(over="ignore", invalid="ignore"):
        # At the domain's edges (centres 1e18 apart, footprints nearly flat) q and the factor overflow to inf: the
        # overlap's limit there is 0, not the NaN that inf * 0 gives.
        q = np.multiply(cc, du, out=cc)
        q *= du
        np.multiply(b, 2, out=b)
        b *= du
        b *= dv
        q -= b
        np.multiply(a, dv, out=a)
        a *= dv
        q += a
        q /= det
        g = np.multiply(da, db, out=t)
        g /= det
        np.sqrt(g, out=g)
        g *= 2 * math.pi
        q *= -0.5
        np.exp(q, out=q)
        g *= q
    np.copyto(g, 0.0, where=np.isnan(g))
    return g


def _det2(c):
    a, b, cc = c
    det = a * cc
    det -= b * b
    return np.maximum(det, 1e-300, out=det)


def _edge_costs(mu_t, cov_t, alpha, col, w, i, j, rule: GroupRule) -> np.ndarray:
    """edge_costs of one block; mu_t (3, clusters) and cov_t (6, clusters): positions and covariances by row."""
    i, j = i.astype(np.intp, copy=False), j.astype(np.intp, copy=False)  # once, not at each of the gathers below
    wi, wj = np.take(w, i), np.take(w, j)
    W = wi + wj
    pi = wi / W
    pj = 1 - pi
    d = np.take(mu_t, i, axis=1) - np.take(mu_t, j, axis=1)  # (3, N)
    di = d * pj
    dj = -d * pi
    ci, cj = np.take(cov_t, i, axis=1), np.take(cov_t, j, axis=1)  # (6, N)
    # cm[k] = pi * (di[a] * di[b] + ci[k]) + pj * (dj[a] * dj[b] + cj[k]), the diagonal + 1e-20: the same operations
    # in the same order (products commute exactly), in place in cm's rows and one work array.
    cm = np.empty_like(ci)
    t = np.empty_like(pi)
    for k, (a, b) in enumerate(_SYM6):
        x = np.multiply(di[a], di[b], out=cm[k])
        x += ci[k]
        x *= pi
        np.multiply(dj[a], dj[b], out=t)
        t += cj[k]
        t *= pj
        x += t
        if a == b:
            x += 1e-20
    area_m = np.maximum(_area6(cm.T), 1e-300)
    am = np.minimum(1.0, W / area_m)
    bi, bj = np.take(col, i, axis=0), np.take(col, j, axis=0)  # rows: np.take is 4x fancy indexing
    bij = row_dots(bi, bj)
    bni, bnj = row_dots(bi, bi), row_dots(bj, bj)
    bim, bjm = pi * bni + pj * bij, pi * bij + pj * bnj
    bnm = pi * pi * bni + 2 * pi * pj * bij + pj * pj * bnj
    ai, aj = np.take(alpha, i), np.take(alpha, j)
    if rule.proj:
        # Per plane the same products as one expression per term (left to right): the planes share their
        # prefixes (pi a_i^2 |b_i|^2, 2 a_i a_j b_ij, ...) and each 2D determinant is taken once.
        fi, fj, fm = math.pi * ai * ai * bni, math.pi * aj * aj * bnj, math.pi * am * am * bnm
        gij, gim, gjm = 2 * ai * aj * bij, 2 * ai * am * bim, 2 * aj * am * bjm
        e = np.zeros(len(i))
        with np.errstate(over="ignore", invalid="ignore"):
            for (u, v), (kuu, kuv, kvv) in _PLANES:
                pi_ = ci[kuu], ci[kuv], ci[kvv]
                pj_ = cj[kuu], cj[kuv], cj[kvv]
                pm_ = cm[kuu], cm[kuv], cm[kvv]
                hi, hj, hm = _det2(pi_), _det2(pj_), _det2(pm_)
                # fi sqrt(hi) + fj sqrt(hj) + fm sqrt(hm) + gij X_ij - gim X_im - gjm X_jm, left to right as one
                # expression adds them, accumulated in place (no new array per term).
                t = np.sqrt(hi)
                t *= fi
                for f_, h_ in ((fj, hj), (fm, hm)):
                    x = np.sqrt(h_)
                    x *= f_
                    t += x
                x = _cross2(pi_, pj_, hi, hj, d, u, v)
                x *= gij
                t += x
                x = _cross2(pi_, pm_, hi, hm, di, u, v)
                x *= gim
                t -= x
                x = _cross2(pj_, pm_, hj, hm, dj, u, v)
                x *= gjm
                t -= x
                e += t
        # Overlaps that overflow (flat footprints on one centre, the domain's edges) leave inf - inf: a cost not
        # known, taken as the largest, as the NaN it was sorted last before.
        np.copyto(e, np.inf, where=np.isnan(e))
    else:
        sdm = np.sqrt(np.maximum(_det6(cm.T), 1e-300))
        sdi = np.sqrt(np.maximum(_det6(ci.T), 1e-300))
        sdj = np.sqrt(np.maximum(_det6(cj.T), 1e-300))
        e = (_PI_1_5 * ai * ai * bni * sdi + _PI_1_5 * aj * aj * bnj * sdj + _PI_1_5 * am * am * bnm * sdm
             + 2 * ai * aj * bij * _cross3(sdi, sdj, (ci + cj).T, d.T)
             - 2 * ai * am * bim * _cross3(sdi, sdm, (ci + cm).T, di.T)
             - 2 * aj * am * bjm * _cross3(sdj, sdm, (cj + cm).T, dj.T))
    return np.maximum(e, 0.0) + rule.colour * COLOUR_WEIGHT * np.maximum(bni + bnj - 2 * bij, 0.0)


# ---------------------------------------------------------------------------------------------- matching


def _greedy_pairs(count: int, i: np.ndarray, j: np.ndarray, cost: np.ndarray, quota: int,
                  passes: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """About the cheapest matching of at most `quota` pairs: in repeated passes every free node takes its cheapest
    edge to a free node, and pairs whose two nodes took each other are matched (cheapest first if over quota)."""
    ii = np.concatenate([i, j])
    jj = np.concatenate([j, i])
    cc = np.concatenate([cost, cost])
    order = _cost_order(i, j, cost, count)
    # Gathers by np.take, picks by np.compress: the same rows as fancy and boolean indexing, in less time.
    ii, jj, cc = np.take(ii, order), np.take(jj, order), np.take(cc, order)
    del order
    free = np.ones(count, bool)
    got_a, got_b = [], []
    matched = 0
    ids = np.arange(count)
    for _ in range(passes):
        live = np.take(free, ii)
        live &= np.take(free, jj)
        if not live.any() or matched >= quota:
            break
        ii, jj, cc = np.compress(live, ii), np.compress(live, jj), np.compress(live, cc)
        best = np.full(count, -1)
        best[ii[::-1]] = jj[::-1]  # the first (cheapest) live edge of each node
        ok = best >= 0
        mutual = ok & (np.take(best, np.where(ok, best, 0)) == ids) & (ids < best)
        pa = np.flatnonzero(mutual)
        if not len(pa):
            break
        pb = np.take(best, pa)
        if matched + len(pa) > quota:  # each node's cheapest cost, needed only here
            best_cost = np.full(count, np.inf)
            best_cost[ii[::-1]] = cc[::-1]
            keep = np.sort(np.argsort(best_cost[pa], kind="stable")[:quota - matched])
            pa, pb = pa[keep], pb[keep]
        free[pa] = free[pb] = False
        got_a.append(pa)
        got_b.append(pb)
        matched += len(pa)
    if not got_a:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(got_a), np.concatenate(got_b)


def _cost_order(i: np.ndarray, j: np.ndarray, cost: np.ndarray, count: int) -> np.ndarray:
    """The order of the rows (i, j) then (j, i) of every edge (_greedy_pairs' ii, jj) by cost, ties by ids: the same
    pairs on every machine. As np.lexsort((jj, ii, cc)) orders them (rows equal in all three are interchangeable),
    found from the edges' costs alone: their default (SIMD) sort gives the one sorted order where costs are
    distinct, and an edge's two rows come lower id first (2.5x less than the stable sort of the rows put in id
    order first). Runs of edges of equal cost are then put in that order among themselves."""
    m = len(cost)
    by_cost = np.argsort(cost)
    low_first = np.take(i, by_cost) < np.take(j, by_cost)
    order = np.empty(2 * m, np.int64)
    order[0::2] = np.where(low_first, by_cost, by_cost + m)
    order[1::2] = np.where(low_first, by_cost + m, by_cost)
    s = np.take(cost, by_cost)
    same = s[1:] == s[:-1]
    if same.any():
        tied = np.zeros(m, bool)
        tied[1:] = same
        tied[:-1] |= same
        rows = np.flatnonzero(np.repeat(tied, 2))  # both rows of every edge in a tie, in cost order
        sub = order[rows]
        ii, jj = np.concatenate([i, j])[sub], np.concatenate([j, i])[sub]
        by_ids = np.argsort(ii.astype(np.int64) * count + jj)
        order[rows] = sub[by_ids[np.argsort(np.concatenate([cost, cost])[sub][by_ids], kind="stable")]]
    return order


def _cheapest_share(i, j, cost, take: int, mult: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The edges whose cost is among the cheapest: a matching of `take` pairs needs about 2 take edges offered
    (each node's cheapest), so edges above the cost of the (4 take)-th cheapest are dropped. `mult`: how many
    edges each row stands for (group_ids folds the splat edges between two clusters into one row)."""
    total = len(cost) if mult is None else int(mult.sum())
    limit = min(total, 4 * take)
    if limit < total:
        every = cost if mult is None or total == len(cost) else np.repeat(cost, mult)
        thr = np.partition(every, limit - 1)[limit - 1]
        keep = cost <= thr
        return np.compress(keep, i), np.compress(keep, j), np.compress(keep, cost)
    return i, j, cost


# ---------------------------------------------------------------------------------------------- grouping


def _merge_pairs(state: dict, pa: np.ndarray, pb: np.ndarray) -> None:
    mu, cov, alpha, col, w = state["mu"], state["cov"], state["alpha"], state["col"], state["w"]
    wa, wb = np.take(w, pa), np.take(w, pb)
    ws = wa + wb
    fa, fb = wa / ws, wb / ws
    # Rows gathered by np.take (the same rows as mu[pa], 3-7x faster than fancy indexing on (N, 3) and (N, 6)).
    mu_a, mu_b = np.take(mu, pa, axis=0), np.take(mu, pb, axis=0)
    cov_a, cov_b = np.take(cov, pa, axis=0), np.take(cov, pb, axis=0)
    d = mu_a - mu_b
    da, db = d * fb[:, None], -d * fa[:, None]
    cm = np.empty((len(pa), 6))
    for c, (a, b) in enumerate(_SYM6):
        cm[:, c] = fa * (da[:, a] * da[:, b] + cov_a[:, c]) + fb * (db[:, a] * db[:, b] + cov_b[:, c])
    mu[pa] = mu_a * fa[:, None] + mu_b * fb[:, None]
    col[pa] = np.take(col, pa, axis=0) * fa[:, None] + np.take(col, pb, axis=0) * fb[:, None]
    cov[pa] = cm
    alpha[pa] = np.minimum(1.0, ws / np.maximum(_area6(cm), 1e-300))
    w[pa] = ws


def _drop(state: dict, label: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    count = len(state["w"])
    alive = np.ones(count, bool)
    alive[pb] = False
    into = np.arange(count)
    into[pb] = pa
    new_id = np.cumsum(alive) - 1
    for key in state:  # mu, cov, alpha, col, w and, with regions, region; np.compress: 2-4x a[alive]'s speed
        state[key] = np.compress(alive, state[key], axis=0)
    return np.take(new_id, np.take(into, label))


def _morton_finish(state: dict, label: np.ndarray, target: int) -> np.ndarray:
    """Merge Morton-adjacent clusters, nearest pairs first, until `target` remain (always reaches it). With
    regions (state["region"]), clusters are ordered by region, then Morton code, and only neighbours of one region
    merge: the target is reached while it is at least the number of regions."""
    region = state.get("region")
    while len(state["w"]) > target:
        count = len(state["w"])
        codes = morton_codes(state["mu"])
        order = (np.argsort(codes, kind="stable") if region is None
                 else np.lexsort((codes, state["region"])))
        a, b = order[:-1], order[1:]
        if region is not None:
            same = state["region"][a] == state["region"][b]
            a, b = a[same], b[same]
            if not len(a):
                break
        d2 = ((state["mu"][a] - state["mu"][b]) ** 2).sum(axis=1)
        pa, pb = _greedy_pairs(count, a, b, d2, count - target)
        if not len(pa):  # cannot happen with count >= 2 (the cheapest adjacent pair is mutual)
            pa, pb = a[:1], b[:1]
        _merge_pairs(state, pa, pb)
        label = _drop(state, label, pa, pb)
    return label


def stable_int_argsort(ids: np.ndarray) -> np.ndarray:
    """np.argsort(ids, kind="stable") of non-negative integers (id * len(ids) within int64): the keys
    id * n + position are distinct, so numpy's default (SIMD) sort gives the stable order, 4x faster."""
    n = len(ids)
    return np.argsort(ids.astype(np.int64) * n + np.arange(n))


def _distinct(keys: np.ndarray, kind: str | None = None) -> np.ndarray:
    """np.unique of int64 keys (sorted, distinct) by a sort (`kind`: np.sort's), in place of a copy of the keys."""
    keys = np.sort(keys, kind=kind)
    return np.compress(np.concatenate([[True], keys[1:] != keys[:-1]]), keys) if len(keys) else keys


def _sorted_unique(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """np.unique of int64 keys (sorted, distinct), with the sorting order and where each distinct key starts in it
    (np.unique hashes integer keys: 0.33 s for the 570k edge keys of a 71k-splat level, np.sort 0.006 s).
    group_ids' keys come mostly in order (edge rows stay sorted by their first end): the stable sort (a timsort
    of integers, which takes the sorted runs as they are) is 3.4x the default on them (biker's first two levels)."""
    order = np.argsort(keys, kind="stable")  # equal keys fold integer counts only: any order of them would do
    s = np.take(keys, order)
    first = np.flatnonzero(np.concatenate([[True], s[1:] != s[:-1]])) if len(s) else np.zeros(0, np.int64)
    return np.take(s, first), order, first


class _ParkedRows:
    """group_ids_of's edge rows parked over a stage's cap: chunks of (ends, multiplicities), each in the cluster ids
    of the round that parked it, with the remaps of the rounds after it (ids of round r -> of round r + 1). A chunk's
    rows are not folded: a pair may come in several rows, and rows inside one cluster are dropped only by join."""

    def __init__(self) -> None:
        self.chunks: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self.remaps: list[np.ndarray] = []

    def add(self, i: np.ndarray, j: np.ndarray, mult: np.ndarray) -> None:
        if len(i):
            self.chunks.append((len(self.remaps), i, j, mult))

    def step(self, remap: np.ndarray) -> None:
        if self.chunks:  # before the first chunk no remap is needed
            self.remaps.append(remap)

    def join(self, ei: np.ndarray, ej: np.ndarray, mult: np.ndarray, ecost: np.ndarray, count: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The live rows and the parked ones mapped onto today's clusters (rows inside one cluster dropped, rows of
        one pair folded: their multiplicities summed), the parked ones with no cost (NaN). A parked pair is never a
        live one (its clusters' sizes are over the cap, a live pair's under it), so no row folds into a live one."""
        if not self.chunks:
            return ei, ej, mult, ecost
        to_now: list[np.ndarray | None] = [None] * (len(self.remaps) + 1)  # ids of round r -> today's (None: same)
        for r in range(len(self.remaps) - 1, -1, -1):
            later = to_now[r + 1]
            to_now[r] = self.remaps[r] if later is None else np.take(later, self.remaps[r])
        pi = np.concatenate([i if to_now[r] is None else np.take(to_now[r], i) for r, i, _, _ in self.chunks])
        pj = np.concatenate([j if to_now[r] is None else np.take(to_now[r], j) for r, _, j, _ in self.chunks])
        pm = np.concatenate([m for _, _, _, m in self.chunks])
        self.chunks, self.remaps = [], []
        del to_now
        apart = pi != pj
        pi, pj, pm = np.compress(apart, pi), np.compress(apart, pj), np.compress(apart, pm)
        key, order, first = _sorted_unique(pi.astype(np.int64) * count + pj)
        folded = np.add.reduceat(np.take(pm, order), first) if len(key) else pm[:0]
        row = np.take(order, first)
        return (np.concatenate([ei, np.take(pi, row)]), np.concatenate([ej, np.take(pj, row)]),
                np.concatenate([mult, folded]).astype(mult.dtype, copy=False),
                np.concatenate([ecost, np.full(len(key), np.nan)]))


def group_ids(positions: np.ndarray, log_scales: np.ndarray, rotations: np.ndarray, opacities: np.ndarray,
              colours: np.ndarray, masses: np.ndarray, target: int, rule: GroupRule = DEFAULT_RULE,
              edges: tuple[np.ndarray, np.ndarray] | None = None, region: np.ndarray | None = None,
              pool: Executor | None = None) -> np.ndarray:
    """Group id (0 .. target-1) of every splat: exactly min(target, n) groups, a partition of the splats.

    positions (N, 3), log_scales (N, 3), rotations (N, 4) unit (w, x, y, z), opacities (N,) linear alpha,
    colours (N, 3) base colour (0.5 + C0 * SH band 0), masses (N,) the merge weights carried up the tree
    (lod.splat_mass of the originals). Deterministic: a function of the arrays only. Ids follow the Morton order
    of the groups' mass-weighted centres. `edges`: neighbour_edges(positions, rule.neighbours), when known.

    `region` (N,) integer labels: groups never span two regions (the tiles of a tree level, lod.build_subtree's
    cost merge), while the count each region keeps follows from the costs over all regions (the cheapest merges
    of the whole level are made first); every region keeps at least one group, so `target` must be at least the
    number of regions present. `pool`: threads for the k-NN blocks and the edge costs' blocks (the groups are
    the same with any pool or none)."""
    return group_ids_of({"positions": positions, "log_scales": log_scales, "rotations": rotations,
                         "opacities": opacities, "colours": colours, "masses": masses, "region": region},
                        target, rule, edges, pool)


def group_ids_of(inputs: dict, target: int, rule: GroupRule = DEFAULT_RULE,
                 edges: tuple[np.ndarray, np.ndarray] | None = None, pool: Executor | None = None) -> np.ndarray:
    """group_ids of the arrays in `inputs` (its arguments by name: positions, log_scales, rotations, opacities,
    colours, masses and region, None for none), which it empties once its own float64 copies are made: a caller
    that holds the arrays nowhere else (lod.level_cost_groups' concatenations of a whole level) has them freed
    before the neighbour graph and its edge rows, the grouping's peak."""
    positions = inputs.pop("positions")
    n = len(positions)
    target = max(1, int(target))
    if target >= n:
        inputs.clear()
        return np.arange(n, dtype=np.int64)
    p = positions.astype(np.float64)
    del positions
    origin = p.mean(axis=0)
    p -= origin  # in place: the same numbers as p - origin
    state = {"mu": p, "cov": covariances6(inputs.pop("rotations"), inputs.pop("log_scales")),
             "alpha": np.clip(inputs.pop("opacities").astype(np.float64), 0.0, 1.0),
             "col": inputs.pop("colours").astype(np.float64, copy=True),
             "w": inputs.pop("masses").astype(np.float64) + 1e-30}
    del p  # the state holds it
    region = inputs.pop("region", None)
    inputs.clear()
    label = np.arange(n)
    size = np.ones(n, np.int32 if n < 2**31 else np.int64)  # cluster sizes: gathered per edge for the cap mask
    # The neighbour graph of the level's splats, found once: a cluster's candidates are its members' neighbours.
    # As sorted distinct keys i * n + j (i < j).
    key = (neighbour_keys(state["mu"], rule.neighbours, rule.shifts, pool=pool, window=rule.window) if edges is None
           else _distinct(edges[0] * n + edges[1]))
    if region is not None:
        region = np.asarray(region, np.int64)
        if target < len(_distinct(region)):
            raise ValueError(f"target {target} is below the number of regions")
        state["region"] = region  # _drop replaces the state's arrays, never writes into them
    # The edges' ends and multiplicities as 32-bit integers where the level allows (ids below 2^31): the edge rows
    # are the grouping's peak memory (a few per splat: 8-NN), and keys are formed from them in int64 (below).
    index = np.int32 if n < 2**31 else np.int64
    ei, ej = (a.astype(index) for a in np.divmod(key, n))  # one pass (int64 division has no SIMD loop)
    del key
    if region is not None:
        inside = np.take(region, ei) == np.take(region, ej)
        ei, ej = np.compress(inside, ei), np.compress(inside, ej)
        del inside
    del region
    # The edges between clusters: each splat edge mapped onto the clusters at its ends, as (label[ei], label[ej])
    # (ordered: a pair's cost is not exactly symmetric in floating point), one row per ordered pair with `mult`, the
    # number of splat edges it stands for (the cheapest share counts them), and its cost, kept while neither
    # cluster at its ends changes (NaN: not known yet). Each pair is costed once, not once per splat edge.
    mult = np.ones(len(ei), index)
    ecost = np.full(len(ei), np.nan)
    # Caps grow with the reduction (a 4x level needs groups of 4 on average): pairs first means groups of about
    # n / target, the cap twice that.
    ratio = max(1, round(n / target))
    first_cap = max(rule.first_cap, ratio) if rule.first_cap else 0
    max_group = max(rule.max_group, 2 * ratio) if rule.max_group else 0
    stages = [(first_cap, target + math.floor((n - target) * (1.0 - rule.first_share)))] if first_cap else []
    final_stage = len(stages)
    for stage, (cap, stage_target) in enumerate(stages + [(max_group, target)]):
        # A row over the stage's cap stays over it (cluster sizes only grow), so it is parked: not gathered, masked,
        # remapped or folded at every round, only mapped onto the clusters and folded once when the stage ends (the
        # rows are then the same set of (pair, multiplicity) as if it had been, and the rows' order never decides a
        # group: _cheapest_share and _greedy_pairs order them by cost and ids). The live rows are then exactly the
        # rows under the cap. After the last stage no row is read, so none is joined.
        parked = _ParkedRows()
        if cap:
            ok = np.take(size, ei) + np.take(size, ej) <= cap
            if not ok.all():
                out = ~ok
                parked.add(np.compress(out, ei), np.compress(out, ej), np.compress(out, mult))
                ei, ej, mult, ecost = (np.compress(ok, a) for a in (ei, ej, mult, ecost))
                del out
            del ok
        for _ in range(rule.max_rounds):
            count = len(state["w"])
            if count <= stage_target:
                break
            todo = _rows_where(np.isnan(ecost), index)
            edge_costs_at(ecost, todo, state["mu"], state["cov"], state["alpha"], state["col"], state["w"], ei, ej,
                          rule, pool=pool)
            del todo
            if not len(ei):
                break
            need = count - stage_target
            take = (need if rule.share >= 1 or need <= rule.tail * count
                    else max(1, math.ceil(need * rule.share)))
            ci, cj, cost = _cheapest_share(ei, ej, ecost, take, mult)
            pa, pb = _greedy_pairs(count, ci, cj, cost, take)
            del ci, cj, cost
            if not len(pa):
                break
            _merge_pairs(state, pa, pb)
            size[pa] += size[pb]
            changed = np.zeros(count, bool)
            changed[pa] = changed[pb] = True
            alive = np.ones(count, bool)
            alive[pb] = False
            size = np.compress(alive, size)
            # The new ids as `index` (the edge rows' type): the rows gathered through it need no conversion.
            remap = _drop(state, np.arange(count), pa, pb).astype(index, copy=False)
            label = np.take(remap, label)
            parked.step(remap)
            # Edges between unchanged clusters keep their rows and costs; the others are mapped onto the merged
            # clusters, those now over the cap parked as they are (folded at the stage's end: in the pairs stage
            # that is every one of them), the others' rows inside one cluster dropped and the pairs that now
            # coincide folded into one row.
            touched = np.take(changed, ei)
            touched |= np.take(changed, ej)
            kept = ~touched
            ti, tj = np.take(remap, np.compress(touched, ei)), np.take(remap, np.compress(touched, ej))
            tm = np.compress(touched, mult)
            del touched
            if cap:
                under = np.take(size, ti)
                under += np.take(size, tj)
                under = under <= cap
                if not under.all():
                    over = ~under
                    parked.add(np.compress(over, ti), np.compress(over, tj), np.compress(over, tm))
                    ti, tj, tm = np.compress(under, ti), np.compress(under, tj), np.compress(under, tm)
                    del over
                del under
            apart = ti != tj
            ti, tj, tm = np.compress(apart, ti), np.compress(apart, tj), np.compress(apart, tm)
            count = len(size)
            key, order, first = _sorted_unique(ti.astype(np.int64) * count + tj)
            folded = np.add.reduceat(np.take(tm, order), first) if len(key) else tm[:0]
            row = np.take(order, first)  # a row of each distinct pair: its ends (key // count, key % count)
            ti, tj = np.take(ti, row), np.take(tj, row)
            ei = np.concatenate([np.take(remap, np.compress(kept, ei)), ti])
            ej = np.concatenate([np.take(remap, np.compress(kept, ej)), tj])
            mult = np.concatenate([np.compress(kept, mult), folded]).astype(index, copy=False)
            ecost = np.concatenate([np.compress(kept, ecost), np.full(len(ti), np.nan)])
        if stage < final_stage:
            ei, ej, mult, ecost = parked.join(ei, ej, mult, ecost, len(state["w"]))
        del parked
    label = _morton_finish(state, label, target)
    groups = len(state["w"])
    if groups != target:  # only with regions: a region that cannot merge further (one cluster left) is a bug
        raise ValueError(f"grouping reached {groups} groups, not {target}")
    rank = np.empty(groups, np.int64)
    rank[np.argsort(morton_codes(state["mu"]), kind="stable")] = np.arange(groups)
    return np.take(rank, label)


def group_runs(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, starts) of group ids, as lod.merge_groups takes them: members of group g are order[starts[g]:...]."""
    order = stable_int_argsort(ids)
    starts = np.concatenate([[0], np.flatnonzero(np.diff(np.take(ids, order))) + 1])
    return order, starts


def _field_dot(ai, ci, covi, mui, aj, cj, covj, muj, proj: bool) -> np.ndarray:
    """<a_i c_i G_i, a_j c_j G_j> per row (summed over the colour channels): in 3D, or summed over the three
    axis-aligned projections."""
    amp = ai * aj * row_dots(ci, cj)
    d = mui - muj
    if not proj:
        q, det = _quad6(covi + covj, d)
        sdi = np.sqrt(np.maximum(_det6(covi), 1e-300))
        sdj = np.sqrt(np.maximum(_det6(covj), 1e-300))
        return amp * _TWO_PI_1_5 * sdi * sdj / np.sqrt(det) * np.exp(-0.5 * q)
    out = np.zeros(len(ai))
    for (u, v), (kuu, kuv, kvv) in _PLANES:
        a1, b1, c1 = covi[:, kuu], covi[:, kuv], covi[:, kvv]
        a2, b2, c2 = covj[:, kuu], covj[:, kuv], covj[:, kvv]
        a, b, c = a1 + a2, b1 + b2, c1 + c2
        det = np.maximum(a * c - b * b, 1e-300)
        d1 = np.maximum(a1 * c1 - b1 * b1, 1e-300)
        d2 = np.maximum(a2 * c2 - b2 * b2, 1e-300)
        du, dv = d[:, u], d[:, v]
        q = (c * du * du - 2 * b * du * dv + a * dv * dv) / det
        out += 2 * math.pi * np.sqrt(d1 * d2 / det) * np.exp(-0.5 * q)
    return amp * out


def member_terms(log_scales, rotations, opacities, colours, proj: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """What group_errors computes per member whatever the grouping: the covariances (covariances6) and each
    member's own <f, f> (no centre offset, so the positions do not enter). Row by row, so taken once for the
    members in their own order and gathered per grouping, the numbers are the same bits (level_auto_groups judges
    two groupings of every tile's members)."""
    cov = covariances6(rotations, log_scales)
    a = np.clip(opacities.astype(np.float64), 0.0, 1.0)
    c = colours.astype(np.float64)
    zero = np.zeros((len(a), 3))
    return cov, _field_dot(a, c, cov, zero, a, c, cov, zero, proj)


def group_errors(positions, log_scales, rotations, opacities, colours, masses, ids, proj: bool = True,
                 max_offset: int = 16, terms: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Per group: the squared L2 norm of (sum of its members' colour-premultiplied fields - the merged splat's),
    the merged splat moment-matched with weights `masses`, opacity mass / area (capped at 1). Member pairs further
    than `max_offset` apart in the group's member list are left out (large groups). `terms`: member_terms of the
    same members (and `proj`), when known."""
    n = len(positions)
    order = stable_int_argsort(ids)
    sid = np.take(ids, order)
    groups = int(ids.max()) + 1 if n else 0
    p = np.take(positions.astype(np.float64), order, axis=0)  # rows: np.take, 3-7x fancy indexing
    p -= p.mean(axis=0) if n else 0.0
    if terms is None:
        terms = member_terms(log_scales, rotations, opacities, colours, proj)
    cov, own = np.take(terms[0], order, axis=0), np.take(terms[1], order)
    a = np.clip(opacities.astype(np.float64)[order], 0.0, 1.0)
    c = np.take(colours.astype(np.float64), order, axis=0)
    w = masses.astype(np.float64)[order] + 1e-30
    W = np.bincount(sid, weights=w, minlength=groups)
    f = w / W[sid]
    mu = np.stack([np.bincount(sid, weights=f * p[:, k], minlength=groups) for k in range(3)], 1)
    mu_s = np.take(mu, sid, axis=0)
    dm = p - mu_s
    cm = np.empty((groups, 6))
    for k, (x, y) in enumerate(_SYM6):
        cm[:, k] = np.bincount(sid, weights=f * (dm[:, x] * dm[:, y] + cov[:, k]), minlength=groups)
    for k in (0, 3, 5):  # in place: the same sums as through a fancy-indexed copy
        cm[:, k] += 1e-20
    am = np.minimum(1.0, W / np.maximum(_area6(cm), 1e-300))
    col_m = np.stack([np.bincount(sid, weights=f * c[:, k], minlength=groups) for k in range(3)], 1)
    err = np.bincount(sid, weights=own, minlength=groups)
    err -= 2 * np.bincount(sid, weights=_field_dot(a, c, cov, p, am[sid], np.take(col_m, sid, axis=0),
                                                      np.take(cm, sid, axis=0), mu_s, proj),
                           minlength=groups)
    err += _field_dot(am, col_m, cm, mu, am, col_m, cm, mu, proj)
    for off in range(1, max_offset + 1):
        same = sid[:n - off] == sid[off:]  # members x and x + off in one group
        if not same.any():
            break
        x = np.flatnonzero(same)
        y = x + off
        rx = [np.take(t, x, axis=0) for t in (c, cov, p)]
        ry = [np.take(t, y, axis=0) for t in (c, cov, p)]
        err += 2 * np.bincount(sid[x], weights=_field_dot(a[x], *rx, a[y], *ry, proj), minlength=groups)
    return np.maximum(err, 0.0)


# ---------------------------------------------------------------------------------------------- the rendered proxy

PROXY_MAX_RADIUS = 12  # px: footprints of (2 r + 1)^2 pixels, r = 3 sigma of the projected splat, at most this
PROXY_LOW_PASS = 0.3  # px^2, as the 3DGS rasteriser
PROXY_ALPHA_MAX = 0.99
PROXY_ALPHA_MIN = 1.0 / 255.0


def proxy_views(positions: np.ndarray, cov: np.ndarray, alpha: np.ndarray, colours: np.ndarray, box: tuple,
                size: int) -> np.ndarray:
    """(6, size, size, 3) orthographic renders along -x, +x, -y, +y, -z, +z over `box` (lo, hi): each splat's
    footprint (its covariance projected, plus the rasteriser's low-pass) on the (2r+1)^2 pixels around its centre
    (r: 3 sigma, at most PROXY_MAX_RADIUS),
    alpha-composited front to back per pixel, black background. A coarse numpy stand-in for the GL renderer, used
    to choose between groupings."""
    lo, hi = (np.asarray(b, np.float64) for b in box)
    out = np.zeros((6, size, size, 3))
    col = np.maximum(colours, 0.0)
    for axis, ((u, v), (kuu, kuv, kvv)) in enumerate(_PLANES):
        h = max(float(hi[u] - lo[u]), float(hi[v] - lo[v]), 1e-30) / size
        cu = (positions[:, u] - lo[u]) / h
        cv = (positions[:, v] - lo[v]) / h
        a = cov[:, kuu] / (h * h) + PROXY_LOW_PASS
        b = cov[:, kuv] / (h * h)
        c = cov[:, kvv] / (h * h) + PROXY_LOW_PASS
        det = np.maximum(a * c - b * b, 1e-30)
        ia, ib, ic = c / det, -b / det, a / det
        mid = 0.5 * (a + c)
        lam = mid + np.sqrt(np.maximum(0.1, mid * mid - det))
        radius = np.clip(np.ceil(3.0 * np.sqrt(lam)), 1, PROXY_MAX_RADIUS).astype(np.int64)
        parts = []
        for r in np.unique(radius):  # one stencil per radius: (2r+1)^2 pixels around the centre
            sel = np.flatnonzero(radius == r)
            off = np.arange(-r, r + 1)
            ox, oy = (t.reshape(-1) for t in np.meshgrid(off, off, indexing="ij"))
            px = np.floor(cu[sel]).astype(np.int64)[:, None] + ox[None, :]
            py = np.floor(cv[sel]).astype(np.int64)[:, None] + oy[None, :]
            du = px + 0.5 - cu[sel, None]
            dv = py + 0.5 - cv[sel, None]
            power = -0.5 * (ia[sel, None] * du * du + ic[sel, None] * dv * dv) - ib[sel, None] * du * dv
            fa = np.minimum(PROXY_ALPHA_MAX, alpha[sel, None] * np.exp(power))
            keep = (fa >= PROXY_ALPHA_MIN) & (px >= 0) & (px < size) & (py >= 0) & (py < size)
            parts.append((np.broadcast_to(sel[:, None], keep.shape)[keep], (py * size + px)[keep], fa[keep]))
        splat = np.concatenate([t[0] for t in parts])
        pix = np.concatenate([t[1] for t in parts])
        fa = np.concatenate([t[2] for t in parts])
        n = len(positions)
        for view, sign in enumerate((1.0, -1.0)):  # looking along -axis (nearest: largest coordinate) and +axis
            rank = np.empty(n, np.int64)  # depth rank, ties by index: one int64 key sorts fragments front to back
            rank[np.argsort(-sign * positions[:, axis], kind="stable")] = np.arange(n)
            order = np.argsort(pix * n + rank[splat])
            p_, a_ = pix[order], fa[order]
            la = np.log1p(-a_)
            cs = np.cumsum(la)
            first = np.concatenate([[True], p_[1:] != p_[:-1]])
            seg = np.cumsum(first) - 1
            base = (cs - la)[first]  # exclusive cumulative sum at each pixel's first fragment
            trans = np.exp(cs - la - base[seg])
            wgt = a_ * trans
            img = out[2 * axis + view].reshape(-1, 3)
            for k in range(3):
                img[:, k] = np.bincount(p_, weights=wgt * col[splat[order], k], minlength=size * size)
    return out


def _moments(p, cov, alpha, col, w, ids, groups):
    """Moment-matched Gaussians of the groups (mean, six, opacity mass / area capped at 0.99, mean colour)."""
    W = np.bincount(ids, weights=w, minlength=groups)
    f = w / W[ids]
    mu = np.stack([np.bincount(ids, weights=f * p[:, k], minlength=groups) for k in range(3)], 1)
    dm = p - mu[ids]
    cm = np.empty((groups, 6))
    for k, (x, y) in enumerate(_SYM6):
        cm[:, k] = np.bincount(ids, weights=f * (dm[:, x] * dm[:, y] + cov[:, k]), minlength=groups)
    single = np.bincount(ids, minlength=groups) == 1
    am = np.minimum(PROXY_ALPHA_MAX, W / np.maximum(_area6(cm), 1e-300))
    am[single] = np.bincount(ids, weights=alpha, minlength=groups)[single]
    cl = np.stack([np.bincount(ids, weights=f * col[:, k], minlength=groups) for k in range(3)], 1)
    return mu, cm, am, cl


HYBRID_RULES = (GroupRule(proj=1, max_group=4), GroupRule(proj=1, first_cap=2, max_group=4))


def hybrid_group_ids(positions: np.ndarray, log_scales: np.ndarray, rotations: np.ndarray, opacities: np.ndarray,
                     colours: np.ndarray, masses: np.ndarray, target: int, rules: tuple = HYBRID_RULES,
                     grid: bool = True, size: int = 0) -> tuple[np.ndarray, int]:
    """The best of several groupings (each rule of `rules` and, with `grid`, the Morton grid) by the rendered
    proxy: the level's splats and each candidate's merged splats drawn by proxy_views (6 axis views, `size` px,
    default 2 sqrt(target) within 64..128) and compared by squared error. Returns the ids and the index of the
    chosen candidate (rules first, then the grid)."""
    n = len(positions)
    target = max(1, int(target))
    if target >= n:
        return np.arange(n, dtype=np.int64), 0
    p = positions.astype(np.float64)
    cov = covariances6(rotations, log_scales)
    alpha = np.clip(opacities.astype(np.float64), 0.0, 1.0)
    col = colours.astype(np.float64)
    w = masses.astype(np.float64) + 1e-30
    size = size or int(min(128, max(64, 2 * math.sqrt(target))))
    box = (p.min(axis=0), p.max(axis=0))
    ref = proxy_views(p, cov, alpha, col, box, size)
    edges = {}
    cands = []
    for r in rules:  # rules of the same K share the neighbour graph
        if r.neighbours not in edges:
            edges[r.neighbours] = neighbour_edges(p - p.mean(axis=0), r.neighbours)
        cands.append(group_ids(positions, log_scales, rotations, opacities, colours, masses, target, r,
                               edges[r.neighbours]))
    if grid:
        order, starts = grid_group_starts(positions, target)
        ids = np.empty(n, np.int64)
        ids[order] = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, n)))
        if len(starts) == target:  # the grid can fall short of the count (too few cells to split)
            cands.append(ids)
    errs = []
    for ids in cands:
        groups = int(ids.max()) + 1
        mu, cm, am, cl = _moments(p, cov, alpha, col, w, ids, groups)
        errs.append(float(np.mean((proxy_views(mu, cm, am, cl, box, size) - ref) ** 2)))
    best = int(np.argmin(errs))
    return cands[best], best
