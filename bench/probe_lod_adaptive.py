"""Probe: merge groups of adaptive size (issue 31; BENCHMARKS.md, "LOD merges").

splat-transform's adaptive decimator keeps about half of a 50 % level as untouched originals and merges the rest
three or more at a time (statue-angel: 54 % of its 35,680-splat level are originals, 47 % of its 17,840-splat
level). Our Morton grid halves every region alike. Here the grid stays (groups are runs of the Morton order, so
they stay compact), but which cells are split is chosen by cost: start from the grid's cells at target / F groups
and split, cell by cell, the one whose merge loses most until there are `target` groups. Cost of a cell: the
mass-weighted scatter of its members' centres around their mean (Ward's sum of squares), plus LAMBDA times the
mass-weighted scatter of their base colours scaled by the cell's mean member variance (so both are lengths
squared times mass).

    python bench/probe_lod_adaptive.py SCENE --cost grid --cost gen:16@0 --cost ward:16:0@0 [--crop 0.25]
        [--peer-level bench/peers_cache/statue-angel/st-adaptive_35680.ply]

Costs: `grid` (the product), `sse:F:LAMBDA` (the grid's cells split by cost), `agg:K:MAX_GROUP:COLOUR`
(splat-transform's one-pass selection), `gen:K:COLOUR:SHARE` (generations of greedy matchings, re-costed by
field-L2), `ward|dist|bhatt:K:COLOUR:SHARE` (the same generations by Ward's criterion, centre distance or the
Bhattacharyya distance); `@K` scales the viewing blur of the opacity and colour step (0: none). Results:
BENCHMARKS.md, "LOD merges". Needs scipy (cKDTree).

Every whole level is drawn by the GL renderer from 4 orbit views at 384 px and compared with the full-detail
render, as bench/probe_lod_merge.py does.
"""
from __future__ import annotations

import argparse
import heapq
import math
import sys
from pathlib import Path

import numpy as np

from client_gl.offscreen import render_image
from splatstream import lod
from splatstream.camera import scene_orbit_views
from splatstream.gaussians import Gaussians, rotation_matrices
from splatstream.io import read_gaussians
from splatstream.lod import _group_starts, _morton
from splatstream.metrics import psnr_from_mse
from splatstream.orientation import detect_up

sys.path.insert(0, str(Path(__file__).parent))
SPLIT_FACTOR = 4.0
GEN_SHARE = 0.5
GEN_COST = "l2"
BHATT_COLOUR = 1.0
COLOUR_WEIGHT = 0.0


def _cell_split(codes: np.ndarray, a: int, b: int) -> int:
    """Index in (a, b) where the run codes[a:b] (sorted, not all equal) splits at its highest differing bit."""
    x = int(codes[a]) ^ int(codes[b - 1])
    bit = x.bit_length() - 1
    pivot = ((int(codes[a]) >> bit) | 1) << bit
    return a + int(np.searchsorted(codes[a:b], np.uint64(pivot), side="left"))


def adaptive_group_starts(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    n = len(g)
    order, base = _group_starts(g.positions, max(1, int(target / SPLIT_FACTOR)))
    if target >= n or len(base) >= target:
        return order, base
    codes = _morton(g.positions)[order]
    m = mass[order].astype(np.float64) + 1e-300
    p = g.positions[order].astype(np.float64)
    p -= p.mean(axis=0)
    c = g.sh_dc[order].astype(np.float64)
    var = np.exp(2.0 * g.log_scales[order].astype(np.float64)).mean(axis=1)

    def prefix(a: np.ndarray) -> np.ndarray:
        return np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])

    pw, pwx, pwxx = prefix(m), prefix(m[:, None] * p), prefix(m * np.einsum("ij,ij->i", p, p))
    pwc, pwcc, pwv = prefix(m[:, None] * c), prefix(m * np.einsum("ij,ij->i", c, c)), prefix(m * var)

    def cost(a: int, b: int) -> float:
        w = pw[b] - pw[a]
        sx = pwx[b] - pwx[a]
        sse = pwxx[b] - pwxx[a] - float(sx @ sx) / w
        if COLOUR_WEIGHT:
            sc = pwc[b] - pwc[a]
            sse_c = pwcc[b] - pwcc[a] - float(sc @ sc) / w
            sse += COLOUR_WEIGHT * sse_c * (pwv[b] - pwv[a]) / w
        return sse

    ends = np.append(base[1:], n)
    heap = [(-cost(int(a), int(b)), int(a), int(b)) for a, b in zip(base, ends, strict=True) if b - a > 1
            and codes[a] != codes[b - 1]]
    heapq.heapify(heap)
    starts = set(int(s) for s in base)
    while len(starts) < target and heap:
        _, a, b = heapq.heappop(heap)
        s = _cell_split(codes, a, b)
        starts.add(s)
        for lo, hi in ((a, s), (s, b)):
            if hi - lo > 1 and codes[lo] != codes[hi - 1]:
                heapq.heappush(heap, (-cost(lo, hi), lo, hi))
    return order, np.array(sorted(starts), np.int64)


AGG_NEIGHBOURS = 16
AGG_MAX_GROUP = 4
AGG_COLOUR_WEIGHT = 4 * np.pi * 1e-6  # splat-transform's COLOR_WEIGHT (base-colour space)


def agglomerate_group_starts(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """splat-transform's selectMerges: candidate edges to the K nearest splats, costed by the field-L2 error of
    the pair's moment-matched merge plus a colour term, walked cheapest first and unioned (union-find, groups
    capped at AGG_MAX_GROUP) until n - target splats are removed. Groups, then singletons, in Morton order of
    their centres (same return as _group_starts)."""
    from probe_lod_merge import _SYM6, _field_l2_cost
    from scipy.spatial import cKDTree


    n = len(g)
    if target >= n:
        return np.argsort(_morton(g.positions), kind="stable"), np.arange(n)
    p = g.positions.astype(np.float64)
    mu = p - p.mean(axis=0)
    k = min(AGG_NEIGHBOURS, n - 1)
    _, nb = cKDTree(mu).query(mu, k=k + 1)
    i = np.repeat(np.arange(n), k)
    j = nb[:, 1:].reshape(-1)
    ok = (j < n) & (i < j)  # each undirected edge once
    i, j = i[ok], j[ok]
    rot = rotation_matrices(g.rotations)
    m = rot * np.exp(g.log_scales.astype(np.float64))[:, None, :]
    cov = np.empty((n, 6))
    for c, (a, b) in enumerate(_SYM6):
        cov[:, c] = m[:, a, 0] * m[:, b, 0] + m[:, a, 1] * m[:, b, 1] + m[:, a, 2] * m[:, b, 2]
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    col = 0.5 + 0.28209479177387814 * g.sh_dc.astype(np.float64)
    w = mass.astype(np.float64) + 1e-30
    e, dc2 = _field_l2_cost(mu, cov, alpha, w, col, i, j)
    cost = e + AGG_COLOUR_WEIGHT * np.maximum(dc2, 0.0)
    order = np.argsort(cost, kind="stable")
    parent = list(range(n))
    size = [1] * n
    need = n - target
    removed = 0

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in zip(i[order].tolist(), j[order].tolist(), strict=True):
        if removed >= need:
            break
        ra, rb = find(a), find(b)
        if ra == rb or size[ra] + size[rb] > AGG_MAX_GROUP:
            continue
        if size[ra] < size[rb]:
            ra, rb = rb, ra
        parent[rb] = ra
        size[ra] += size[rb]
        removed += 1
    label = np.array([find(x) for x in range(n)])
    _, label = np.unique(label, return_inverse=True)
    groups = int(label.max()) + 1
    centre = np.zeros((groups, 3))
    np.add.at(centre, label, p)
    centre /= np.bincount(label, minlength=groups)[:, None]
    rank = np.empty(groups, np.int64)
    rank[np.argsort(_morton(centre), kind="stable")] = np.arange(groups)
    key = rank[label]
    order = np.argsort(key, kind="stable")
    starts = np.concatenate([[0], np.flatnonzero(np.diff(key[order])) + 1])
    if len(starts) > target:  # not enough cheap edges: the grid over the groups' centres finishes it
        corder, cstarts = _group_starts(centre, target)
        cgroup = np.empty(groups, np.int64)
        cgroup[corder] = np.repeat(np.arange(len(cstarts)), np.diff(np.append(cstarts, groups)))
        key = cgroup[label]
        order = np.argsort(key, kind="stable")
        starts = np.concatenate([[0], np.flatnonzero(np.diff(key[order])) + 1])
    return order, starts


def generation_group_starts(g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Generations of greedy matchings: each generation costs the edges between every cluster (moment-matched
    Gaussian of its members) and its K nearest clusters (field-L2 of the pair's merge plus splat-transform's colour
    term), walks them cheapest first and merges pairs of still-unmatched clusters until the count reaches
    `target` or the edges run out; then the next generation re-costs on the merged clusters. Costs are never
    stale, and cheap regions merge again and again while costly splats stay single."""
    from probe_lod_merge import _SYM6, _area6, _det6, _field_l2_cost, _quad6
    from scipy.spatial import cKDTree


    n = len(g)
    if target >= n:
        return np.argsort(_morton(g.positions), kind="stable"), np.arange(n)
    p = g.positions.astype(np.float64)
    origin = p.mean(axis=0)
    mu = p - origin
    rot = rotation_matrices(g.rotations)
    m = rot * np.exp(g.log_scales.astype(np.float64))[:, None, :]
    cov = np.empty((n, 6))
    for c, (a, b) in enumerate(_SYM6):
        cov[:, c] = m[:, a, 0] * m[:, b, 0] + m[:, a, 1] * m[:, b, 1] + m[:, a, 2] * m[:, b, 2]
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    col = 0.5 + 0.28209479177387814 * g.sh_dc.astype(np.float64)
    w = mass.astype(np.float64) + 1e-30
    label = np.arange(n)
    count = n
    while count > target:
        k = min(AGG_NEIGHBOURS, count - 1)
        _, nb = cKDTree(mu).query(mu, k=k + 1)
        i = np.repeat(np.arange(count), k)
        j = nb[:, 1:].reshape(-1)
        ok = (j < count) & (i != j)
        i, j = np.minimum(i[ok], j[ok]), np.maximum(i[ok], j[ok])
        if GEN_COST in ("dist", "ward"):
            # how far apart the centres are (Ward: times the pair's reduced mass), plus a colour distance scaled
            # by the mean squared centre distance of the candidate edges, so BHATT_COLOUR is unit-free
            dd = mu[i] - mu[j]
            cost = np.einsum("ij,ij->i", dd, dd)
            scale = float(np.mean(cost)) + 1e-300
            if GEN_COST == "ward":
                red = w[i] * w[j] / (w[i] + w[j])
                cost = cost * red
                scale *= float(np.mean(red))
            dcol = col[i] - col[j]
            cost = cost + BHATT_COLOUR * scale * np.einsum("ij,ij->i", dcol, dcol)
        elif GEN_COST == "bhatt":
            # Bhattacharyya distance of the two Gaussians (scale-free: how much they overlap, whatever their
            # opacity) plus a colour distance: Spark's bhatt_lod scores pairs by the coefficient times colour
            # similarity.
            cs = 0.5 * (cov[i] + cov[j])
            q, det_s = _quad6(cs, mu[i] - mu[j])
            det_a = np.maximum(_det6(cov[i]), 1e-300)
            det_b = np.maximum(_det6(cov[j]), 1e-300)
            cost = 0.125 * q + 0.5 * np.log(det_s / np.sqrt(det_a * det_b))
            dcol = col[i] - col[j]
            cost = cost + BHATT_COLOUR * np.einsum("ij,ij->i", dcol, dcol)
        else:
            e, dc2 = _field_l2_cost(mu, cov, alpha, w, col, i, j)
            cost = e + AGG_COLOUR_WEIGHT * np.maximum(dc2, 0.0)
        order = np.lexsort((j, i, cost))
        free = np.ones(count, bool)
        pa, pb = [], []
        # Only the cheapest share of what is left to remove, so that cheap clusters merge again in the next
        # generation while costly splats stay single (one generation removing all of it is a near-perfect matching).
        need = max(1, math.ceil((count - target) * GEN_SHARE))
        for a, b in zip(i[order].tolist(), j[order].tolist(), strict=True):
            if free[a] and free[b]:
                free[a] = free[b] = False
                pa.append(a)
                pb.append(b)
                if len(pa) >= need:
                    break
        if not pa:
            break
        pa, pb = np.array(pa), np.array(pb)
        wa, wb = w[pa], w[pb]
        ws = wa + wb
        fa, fb = wa / ws, wb / ws
        d = mu[pa] - mu[pb]
        da, db = d * fb[:, None], -d * fa[:, None]
        cm = np.empty((len(pa), 6))
        for c, (a, b) in enumerate(_SYM6):
            cm[:, c] = fa * (da[:, a] * da[:, b] + cov[pa, c]) + fb * (db[:, a] * db[:, b] + cov[pb, c])
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
        count = len(w)
    groups = count
    if count > target:  # no edge left (coincident or isolated clusters): the grid over the clusters finishes it
        corder, cstarts = _group_starts(mu + origin, target)
        cgroup = np.empty(count, np.int64)
        cgroup[corder] = np.repeat(np.arange(len(cstarts)), np.diff(np.append(cstarts, count)))
        label = cgroup[label]
        groups = len(cstarts)
    centre = np.zeros((groups, 3))
    np.add.at(centre, label, p)
    centre /= np.bincount(label, minlength=groups)[:, None]
    rank = np.empty(groups, np.int64)
    rank[np.argsort(_morton(centre), kind="stable")] = np.arange(groups)
    key = rank[label]
    order = np.argsort(key, kind="stable")
    return order, np.concatenate([[0], np.flatnonzero(np.diff(key[order])) + 1])


def generation_merge(g: Gaussians, mass: np.ndarray, target: int):
    if len(g) == 0:
        return g, mass, np.zeros(0, np.int64)
    return lod.merge_groups(g, mass, *generation_group_starts(g, mass, max(1, target)))


def agglomerate_merge(g: Gaussians, mass: np.ndarray, target: int):
    if len(g) == 0:
        return g, mass, np.zeros(0, np.int64)
    return lod.merge_groups(g, mass, *agglomerate_group_starts(g, mass, max(1, target)))


def adaptive_merge(g: Gaussians, mass: np.ndarray, target: int):
    if len(g) == 0:
        return g, mass, np.zeros(0, np.int64)
    return lod.merge_groups(g, mass, *adaptive_group_starts(g, mass, max(1, target)))


def _psnr(s: Gaussians, cams, refs) -> float:
    mse = np.mean([np.mean((np.clip(render_image(s, c), 0, 1) - np.clip(r, 0, 1)) ** 2)
                   for c, r in zip(cams, refs, strict=True)])
    return psnr_from_mse(float(mse))


def peer_groups(g: Gaussians, peer: Gaussians, cams, refs) -> None:
    """Is a peer's level better for its choice of groups or for its merge? Its untouched originals (centres equal
    to 1e-5) are kept, and the rest merged by lod.merge_groups: in our grid, and in the peer's groups, inferred
    by giving each original to the merged splat of highest density among its 16 nearest merged centres."""
    from scipy.spatial import cKDTree

    def key(p: np.ndarray) -> list[tuple]:
        return [tuple(x) for x in np.round(p, 5)]

    index = {k: i for i, k in enumerate(key(g.positions))}
    kept = np.array([index.get(k, -1) for k in key(peer.positions)])
    originals = kept[kept >= 0]
    rest = np.setdiff1d(np.arange(len(g)), originals)
    merged_peer = peer.subset(np.flatnonzero(kept < 0))
    mass = lod.splat_mass(g)
    r = g.subset(rest)
    grid_rest = lod.merge_gaussians(r, mass[rest], len(merged_peer))[0]
    rot = rotation_matrices(merged_peer.rotations).astype(np.float64)
    scales = np.exp(merged_peer.log_scales.astype(np.float64))
    pr = r.positions.astype(np.float64)
    _, nb = cKDTree(merged_peer.positions).query(pr, 16)
    best, best_d = np.zeros(len(rest), np.int64), np.full(len(rest), np.inf)
    for k in range(nb.shape[1]):
        j = nb[:, k]
        local = np.einsum("nij,ni->nj", rot[j], pr - merged_peer.positions[j]) / scales[j]
        d = (local ** 2).sum(axis=1)
        better = d < best_d
        best_d[better], best[better] = d[better], j[better]
    order = np.argsort(best, kind="stable")
    starts = np.concatenate([[0], np.flatnonzero(np.diff(best[order])) + 1])
    peer_rest = lod.merge_groups(r, mass[rest], order, starts)[0]
    kept_g = g.subset(originals)
    print(f"peer level {len(peer)}: {_psnr(peer, cams, refs):.2f} dB; {len(originals)} untouched originals; the rest "
          f"in our grid {_psnr(Gaussians.concatenate([kept_g, grid_rest]), cams, refs):.2f} dB, in its groups "
          f"({len(starts)}) {_psnr(Gaussians.concatenate([kept_g, peer_rest]), cams, refs):.2f} dB", flush=True)


def main() -> None:
    global SPLIT_FACTOR, GEN_SHARE, GEN_COST, BHATT_COLOUR, COLOUR_WEIGHT
    global AGG_NEIGHBOURS, AGG_MAX_GROUP, AGG_COLOUR_WEIGHT

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--cost", action="append", default=[], help="grid | sse:F:LAMBDA | agg:K:MAX_GROUP:COLOUR | "
                    "gen:K:COLOUR:SHARE | "
                    "ward|dist|bhatt:K:COLOUR:SHARE, optionally @K: the viewing blur times K")
    ap.add_argument("--peer-level", help="a peer's decimated level (PLY) of the same scene: score it, our merge of "
                    "the rest around its untouched originals in our grid, and in its own groups (inferred)")
    ap.add_argument("--crop", type=float, default=0.0, help="keep splats within this quantile of per-axis distance")
    ap.add_argument("--max-leaf-splats", type=int, default=16384)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=384)
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    if args.crop:
        d = np.abs(g.positions - np.median(g.positions, axis=0))
        cheb = d.max(axis=1)  # the nearest `crop` of the splats to the median, by the largest per-axis distance
        g = g.subset(np.flatnonzero(cheb <= np.quantile(cheb, args.crop)))
    cams = scene_orbit_views(g.positions, args.views, args.size, args.size, up=detect_up(g).up)
    refs = [render_image(g, c) for c in cams]
    if args.peer_level:
        peer_groups(g, read_gaussians(args.peer_level), cams, refs)
    grid = lod.merge_gaussians
    blur = lod.viewing_blur
    for spec in args.cost or ["grid"]:
        spec, _, blur_scale = spec.partition("@")
        lod.viewing_blur = (lambda e, k=float(blur_scale): k * blur(e)) if blur_scale else blur
        name, *rest = spec.split(":")
        if name == "sse":
            SPLIT_FACTOR, COLOUR_WEIGHT = float(rest[0]), float(rest[1]) if len(rest) > 1 else 0.0
        if name == "bhatt":  # bhatt:K:COLOUR:SHARE (generations scored by the Bhattacharyya distance)
            AGG_NEIGHBOURS = int(rest[0]) if rest else 16
            BHATT_COLOUR = float(rest[1]) if len(rest) > 1 else 1.0
            GEN_SHARE = float(rest[2]) if len(rest) > 2 else 0.5
        if name in ("dist", "ward"):  # dist|ward:K:COLOUR:SHARE
            AGG_NEIGHBOURS = int(rest[0]) if rest else 16
            BHATT_COLOUR = float(rest[1]) if len(rest) > 1 else 1.0
            GEN_SHARE = float(rest[2]) if len(rest) > 2 else 0.5
        GEN_COST = name if name in ("bhatt", "dist", "ward") else "l2"
        if name == "gen":  # gen:K:COLOUR_SCALE:SHARE
            AGG_NEIGHBOURS = int(rest[0]) if rest else 16
            AGG_COLOUR_WEIGHT = 4 * np.pi * 1e-6 * (float(rest[1]) if len(rest) > 1 else 1.0)
            GEN_SHARE = float(rest[2]) if len(rest) > 2 else 0.5
        if name == "agg":  # agg:K:MAX_GROUP:COLOUR_SCALE
            AGG_NEIGHBOURS = int(rest[0]) if rest else 16
            AGG_MAX_GROUP = int(rest[1]) if len(rest) > 1 else 4
            AGG_COLOUR_WEIGHT = 4 * np.pi * 1e-6 * (float(rest[2]) if len(rest) > 2 else 1.0)
        lod.merge_gaussians = {"grid": grid, "sse": adaptive_merge, "agg": agglomerate_merge,
                              "gen": generation_merge,
                              "bhatt": generation_merge, "dist": generation_merge, "ward": generation_merge}[name]
        try:
            tiles = lod.build_tiles(g, args.max_leaf_splats, 2.0)
        finally:
            lod.merge_gaussians = grid
        levels: dict[int, list[Gaussians]] = {}
        for t in tiles:
            levels.setdefault(t.level, []).append(t.gaussians)
        row = []
        for level in sorted(levels)[:-1][-5:]:
            s = Gaussians.concatenate(levels[level])
            row.append(f"{len(s)}: {_psnr(s, cams, refs):.2f}")
        print(f"{spec:12s} " + ", ".join(row), flush=True)


if __name__ == "__main__":
    main()
