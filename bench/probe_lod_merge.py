"""Probe: merge groups chosen by cost instead of the Morton grid (issue 31; BENCHMARKS.md, "LOD merges").

Builds the LOD tree of a scene with lod.merge_gaussians replaced by greedy pair merges over nearest neighbours,
scored by one of: `l2` (the field-L2 cost of splat-transform's decimator, amplitude opacity x colour), `l2a` (the
same with opacity alone as the amplitude, plus a colour term in proportion to the pair's energy) or `ward` (Ward's
criterion on the merge weights, times a colour term), optionally held inside the Morton grid's cells (`--cells F`:
cells of target / F groups). Every whole level is drawn by the GL renderer from 4 orbit views at 384 px and
compared with the full-detail render. `--cost grid` measures the product's Morton grid.

    python bench/probe_lod_merge.py SCENE.ply --cost grid --cost l2 --cost l2a:4 --cost ward:1 [--cells 1]

Measured (2x tree, no scale growth): free pair merges were up to 1.6 dB sharper than the grid on the donut and up
to 3.5 dB blurrier on a crop of the flowers capture; inside the grid's cells they equal the grid within 0.05 dB;
with cells of 8x the volume, +1 to +1.6 dB on the donut and -0.5 to -0.8 dB on the flowers crop. Not adopted.
Needs scipy (cKDTree), which the product does not.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from splatstream import lod
from splatstream.gaussians import Gaussians, rotation_matrices
from splatstream.lod import _group_starts, _morton
from splatstream.lod_groups import _area6, _quad6  # the closed forms the grouping module holds

MERGE_NEIGHBOURS = 5
MERGE_COST = "l2"
MERGE_COLOUR_WEIGHT = 0.0
MERGE_IN_CELLS = False
MERGE_CELL_FACTOR = 1.0


_C0 = 0.28209479177387814
_TWO_PI_1_5 = (2 * math.pi) ** 1.5
_PI_1_5 = math.pi ** 1.5


def _det6(c: np.ndarray) -> np.ndarray:
    xx, xy, xz, yy, yz, zz = (c[:, k] for k in range(6))
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def _field_l2_cost(mu, cov, alpha, w, col, i, j):
    """Squared L2 norm of (a_i c_i G_i + a_j c_j G_j - a_m c_m G_m), G the unnormalised Gaussian kernel (what the
    rasteriser draws), m the moment-matched merge of i and j (splat-transform's decimator's cost)."""
    wi, wj = w[i], w[j]
    W = wi + wj
    pi = wi / W
    pj = 1 - pi
    d = mu[i] - mu[j]
    di = d * pj[:, None]
    dj = -d * pi[:, None]
    ci, cj = cov[i], cov[j]
    cm = np.empty_like(ci)
    for k, (a, b) in enumerate(_SYM6):
        cm[:, k] = pi * (di[:, a] * di[:, b] + ci[:, k]) + pj * (dj[:, a] * dj[:, b] + cj[:, k])
    cm[:, [0, 3, 5]] += 1e-20
    sdm = np.sqrt(np.maximum(_det6(cm), 1e-300))
    am = np.minimum(1.0, W / np.maximum(_area6(cm), 1e-300))
    sdi = np.sqrt(np.maximum(_det6(ci), 1e-300))
    sdj = np.sqrt(np.maximum(_det6(cj), 1e-300))
    bi, bj = col[i], col[j]
    bij = np.einsum("ij,ij->i", bi, bj)
    bni, bnj = np.einsum("ij,ij->i", bi, bi), np.einsum("ij,ij->i", bj, bj)
    bim, bjm = pi * bni + pj * bij, pi * bij + pj * bnj
    bnm = pi * pi * bni + 2 * pi * pj * bij + pj * pj * bnj
    ai, aj = alpha[i], alpha[j]

    def cross(sda, sdb, csum, dd):
        q, det = _quad6(csum, dd)
        return _TWO_PI_1_5 * sda * sdb / np.sqrt(det) * np.exp(-0.5 * q)

    e = (_PI_1_5 * (ai * ai * bni * sdi + aj * aj * bnj * sdj + am * am * bnm * sdm)
         + 2 * ai * aj * bij * cross(sdi, sdj, ci + cj, d)
         - 2 * ai * am * bim * cross(sdi, sdm, ci + cm, di)
         - 2 * aj * am * bjm * cross(sdj, sdm, cj + cm, dj))
    return np.maximum(e, 0.0), bni + bnj - 2 * bij


_SYM6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _greedy_pairs(count: int, i: np.ndarray, j: np.ndarray, cost: np.ndarray, quota: int,
                  passes: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A matching of about the cheapest edges (i, j) of `cost`, at most `quota` pairs: repeated passes in which
    every node still free takes its cheapest edge to a free node, and pairs whose two nodes took each other are
    matched (the greedy matching's first choices, found in bulk)."""
    ii = np.concatenate([i, j])
    jj = np.concatenate([j, i])
    cc = np.concatenate([cost, cost])
    order = np.argsort(cc, kind="stable")  # by cost, ties in edge order: the same pairs on every machine
    ii, jj, cc = ii[order], jj[order], cc[order]
    free = np.ones(count, bool)
    got_a: list[np.ndarray] = []
    got_c: list[np.ndarray] = []
    got_b: list[np.ndarray] = []
    matched = 0
    ids = np.arange(count)
    for _ in range(passes):
        live = free[ii] & free[jj]
        if not live.any() or matched >= quota:
            break
        ii, jj, cc = ii[live], jj[live], cc[live]
        best = np.full(count, -1)
        best[ii[::-1]] = jj[::-1]  # the first (cheapest) live edge of each node
        best_cost = np.full(count, np.inf)
        best_cost[ii[::-1]] = cc[::-1]
        ok = best >= 0
        mutual = ok & (best[np.where(ok, best, 0)] == ids) & (ids < best)
        pa = np.flatnonzero(mutual)
        if not len(pa):
            break
        pb = best[pa]
        if matched + len(pa) > quota:
            keep = np.sort(np.argsort(best_cost[pa], kind="stable")[:quota - matched])
            pa, pb = pa[keep], pb[keep]
        free[pa] = free[pb] = False
        got_a.append(pa)
        got_b.append(pb)
        got_c.append(best_cost[pa])
        matched += len(pa)
    if not got_a:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(got_a), np.concatenate(got_b)



def _pair_merge_groups(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Groups of about `target` by rounds of pair merges of the cheapest neighbours (same return as _group_starts).

    Each round: every cluster's K nearest clusters (moment-matched centres), the field-L2 cost of merging each pair
    (_field_l2_cost), and every pair that is each other's cheapest merged at once, cheapest first, no more than the
    count left to remove."""
    from scipy.spatial import cKDTree  # only this probe needs scipy

    n = len(g)
    if target >= n:
        order = np.argsort(_morton(g.positions), kind="stable")
        return order, np.arange(n)
    label = np.arange(n)
    w = mass.astype(np.float64) + 1e-30
    p = g.positions.astype(np.float64)
    origin = p.mean(axis=0)
    mu = p - origin
    rot = rotation_matrices(g.rotations)
    m = rot * np.exp(g.log_scales.astype(np.float64))[:, None, :]
    cov = np.empty((n, 6))
    for k, (a, b) in enumerate(_SYM6):
        cov[:, k] = m[:, a, 0] * m[:, b, 0] + m[:, a, 1] * m[:, b, 1] + m[:, a, 2] * m[:, b, 2]
    del m, rot
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    col = 0.5 + _C0 * g.sh_dc.astype(np.float64)
    count = n
    cell = None
    if MERGE_IN_CELLS:
        # merges stay inside the cells of the Morton grid of `target` cells: every merged splat spans at most a cell
        # of the level's uniform resolution, the cost decides which merges inside them come first
        gorder, gstarts = _group_starts(g.positions, max(1, int(target / MERGE_CELL_FACTOR)))
        cell = np.empty(n, np.int64)
        cell[gorder] = np.repeat(np.arange(len(gstarts)), np.diff(np.append(gstarts, n)))
    while count > target:
        k = min(MERGE_NEIGHBOURS, count - 1)
        _, nb = cKDTree(mu).query(mu, k=k + 1)
        i = np.repeat(np.arange(count), k)
        j = nb[:, 1:].reshape(-1)
        ok = (j < count) & (j != i)
        if cell is not None:
            ok &= cell[i] == cell[np.minimum(j, count - 1)]
        i, j = i[ok], j[ok]
        if MERGE_COST == "ward":
            dd = mu[i] - mu[j]
            e = w[i] * w[j] / (w[i] + w[j]) * np.einsum("ij,ij->i", dd, dd)
            dc = col[i] - col[j]
            dc2 = np.einsum("ij,ij->i", dc, dc)
        elif MERGE_COST == "l2a":
            # coverage (alpha) as the amplitude: what a splat hides matters as much as what it emits; colour
            # differences cost in proportion to the pair's own energy
            ones = np.ones((count, 1))
            e, _ = _field_l2_cost(mu, cov, alpha, w, ones, i, j)
            dc = col[i] - col[j]
            dc2 = np.einsum("ij,ij->i", dc, dc)
            energy = _PI_1_5 * (alpha[i] ** 2 * np.sqrt(np.maximum(_det6(cov[i]), 1e-300))
                                + alpha[j] ** 2 * np.sqrt(np.maximum(_det6(cov[j]), 1e-300)))
            e = e + MERGE_COLOUR_WEIGHT * energy * dc2
        else:
            e, dc2 = _field_l2_cost(mu, cov, alpha, w, col, i, j)
        cost = e
        if MERGE_COLOUR_WEIGHT and MERGE_COST != "l2a":
            cost = e + MERGE_COLOUR_WEIGHT * float(np.median(e)) * dc2 / (float(np.mean(dc2)) + 1e-12)
        pa, pb = _greedy_pairs(count, i, j, cost, count - target)
        if not len(pa):
            break
        wa, wb = w[pa], w[pb]
        ws = wa + wb
        fa, fb = wa / ws, wb / ws
        d = mu[pa] - mu[pb]
        da, db = d * fb[:, None], -d * fa[:, None]
        cm = np.empty((len(pa), 6))
        for k6, (a, b) in enumerate(_SYM6):
            cm[:, k6] = fa * (da[:, a] * da[:, b] + cov[pa, k6]) + fb * (db[:, a] * db[:, b] + cov[pb, k6])
        mu[pa] = mu[pa] * fa[:, None] + mu[pb] * fb[:, None]
        col[pa] = col[pa] * fa[:, None] + col[pb] * fb[:, None]
        cov[pa] = cm
        alpha[pa] = np.minimum(1.0, ws / np.maximum(_area6(cm), 1e-300))
        w[pa] = ws
        alive = np.ones(count, bool)
        alive[pb] = False
        into = np.arange(count)
        into[pb] = pa
        new_id = np.cumsum(alive) - 1
        label = new_id[into[label]]
        mu, cov, alpha, col, w = mu[alive], cov[alive], alpha[alive], col[alive], w[alive]
        if cell is not None:
            cell = cell[alive]
        count = len(w)
    groups = count
    if count > target:
        # no mutual pair left (coincident centres): finish on the Morton grid over the clusters
        corder, cstarts = _group_starts(mu + origin, target)
        cgroup = np.empty(count, np.int64)
        cgroup[corder] = np.repeat(np.arange(len(cstarts)), np.diff(np.append(cstarts, count)))
        label = cgroup[label]
        groups = len(cstarts)
    centre = np.zeros((groups, 3))
    np.add.at(centre, label, p - origin)
    centre /= np.bincount(label, minlength=groups)[:, None]
    rank = np.empty(groups, np.int64)
    rank[np.argsort(_morton(centre + origin), kind="stable")] = np.arange(groups)
    key = rank[label]
    order = np.argsort(key, kind="stable")
    starts = np.concatenate([[0], np.flatnonzero(np.diff(key[order])) + 1])
    return order, starts


def _pair_merge(g: Gaussians, mass: np.ndarray, target: int):
    if len(g) == 0:
        return g, mass, np.zeros(0, np.int64)
    return lod.merge_groups(g, mass, *_pair_merge_groups(g, mass, max(1, target)))


def main() -> None:
    global MERGE_COST, MERGE_COLOUR_WEIGHT, MERGE_IN_CELLS, MERGE_CELL_FACTOR
    from client_gl.offscreen import render_image
    from splatstream.camera import scene_orbit_views
    from splatstream.io import read_gaussians
    from splatstream.metrics import psnr_from_mse
    from splatstream.orientation import detect_up

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--cost", action="append", default=[], help="grid | l2 | l2a | ward, optionally :COLOUR_WEIGHT")
    ap.add_argument("--cells", type=float, default=0.0, help="hold merges inside grid cells of target/F groups")
    ap.add_argument("--reduction", type=float, default=2.0)
    ap.add_argument("--max-leaf-splats", type=int, default=16384)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=384)
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    cams = scene_orbit_views(g.positions, args.views, args.size, args.size, up=detect_up(g).up)
    refs = [render_image(g, c) for c in cams]
    grid = lod.merge_gaussians
    for spec in args.cost or ["grid"]:
        name, _, weight = spec.partition(":")
        MERGE_COST, MERGE_COLOUR_WEIGHT = name, float(weight or 0.0)
        MERGE_IN_CELLS, MERGE_CELL_FACTOR = args.cells > 0, args.cells or 1.0
        lod.merge_gaussians = grid if name == "grid" else _pair_merge
        try:
            tiles = lod.build_tiles(g, args.max_leaf_splats, args.reduction)
        finally:
            lod.merge_gaussians = grid
        levels: dict[int, list[Gaussians]] = {}
        for t in tiles:
            levels.setdefault(t.level, []).append(t.gaussians)
        row = []
        for level in sorted(levels)[:-1]:
            s = Gaussians.concatenate(levels[level])
            mse = np.mean([np.mean((np.clip(render_image(s, c), 0, 1) - np.clip(r, 0, 1)) ** 2)
                           for c, r in zip(cams, refs, strict=True)])
            row.append(f"{len(s)}: {psnr_from_mse(float(mse)):.2f} dB")
        print(f"{spec:10s} " + ", ".join(row), flush=True)


if __name__ == "__main__":
    main()
