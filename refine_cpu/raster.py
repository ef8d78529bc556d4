"""A numba rasteriser with our renderer's conventions, and for fixed geometry its per-pixel pair lists, forward and
backward over opacity and DC colour (the CPU refinement of the merged LOD levels, lod.md 6).

The conventions are splatstream/render_ref.py's (its numpy reference, whose `preprocess` this module reuses as is):
the pinhole of `Camera` with pixel (col, row) at (col, row) after ndc2Pix, EWA with the 0.3 px^2 low-pass, splats
with depth <= near culled, depth order (stable, ties by index), alpha = min(0.99, o g) with g = exp(power), skipped
when power > 0 or alpha < 1/255, a pixel stops once T (1 - alpha) < 1e-4, colour max(SH(dir) + 0.5, 0), black
background. refine_gpu/levels.py's docstring lists the same (gsplat's, matched there).

With the geometry fixed (positions, rotations, scales), what a pixel sees is a fixed list of (splat, g) pairs in
depth order: only opacities and colours change. `PairLists` holds them for a set of cameras (CSR over pixels: the
pairs with g >= 1/255, as o <= 1 makes any other alpha fall under the cut), and `loss_and_grad` is a forward and a
backward pass over them: the MSE of the clamped images against targets, its gradient with respect to each splat's
opacity and to the pre-clamp colour's DC term (the view-dependent SH rest is fixed per camera and splat).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numba
import numpy as np

from splatstream.camera import Camera
from splatstream.gaussians import Gaussians, covariances
from splatstream.render_ref import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, preprocess, tile_lists
from splatstream.sh import SH_C0, eval_sh, view_directions

# numba's workqueue threading layer unless the user names one: between the parallel loops (the pair lists, the fit's
# steps) the refiner runs serial numpy, and OpenMP's threads spin-wait through it. On a 16-core host (donut, `encode
# --lod-refine cpu`) OpenMP took 557 s of CPU for 79 s of wall clock, workqueue 363 s for 76 s, the same bytes
# (BENCHMARKS.md, "Both refiners on the GPU machine"). Read when the first parallel loop starts, so set at import.
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"

# Pairs are kept while T under the ORIGINAL opacities stays above this (a pixel stops at T_MIN = 1e-4): a fitted
# opacity a little lower than built still finds the pairs behind (three splats at 0.99 reach 1e-6).
T_STORE = 1e-6
# exp(power) < ALPHA_MIN for any power below this (a margin of 1e-6 in the log, far above exp's rounding): the
# kernels skip such a splat before its exp, where the exp would only have led to the same skip (g < 1/255, or with an
# opacity <= 1 alpha < 1/255). Most of a tile's splats miss most of its pixels, so most exps are saved.
POWER_SKIP = math.log(ALPHA_MIN) - 1e-6


@dataclass
class Projection:
    """One camera's projected splats (render_ref.preprocess, depth order) and its tile lists."""
    index: np.ndarray      # (M,) int64 splat index into the splat set
    xy: np.ndarray         # (M, 2) float64 pixel-index coordinates
    conic: np.ndarray      # (M, 3) float64
    base: np.ndarray       # (M, 3) float64: SH(dir) + 0.5 without the DC term (the fixed, view-dependent part)
    tile_ids: np.ndarray   # tile-major, depth-minor projected ids
    tile_offsets: np.ndarray
    width: int
    height: int


def project(g: Gaussians, cam: Camera, sh_degree: int | None = None, cov3d: np.ndarray | None = None) -> Projection:
    """`cov3d`: covariances(g), computed once where one splat set is projected for many cameras."""
    # preprocess's own colours (DC included) are not needed: `base` below is the view-dependent part
    p = preprocess(g, cam, sh_degree, cov3d=cov3d, color=False)
    grid_x, grid_y = -(-cam.width // TILE), -(-cam.height // TILE)
    ids, offsets = tile_lists(p, grid_x, grid_y)
    zero_dc = np.zeros((len(p.index), 3))
    base = eval_sh(zero_dc, g.sh_rest[p.index], view_directions(g.positions[p.index], np.asarray(cam.eye)),
                   sh_degree, clamp=False)
    return Projection(p.index, p.xy, p.conic, base, ids, offsets, cam.width, cam.height)


def colours_of(proj: Projection, sh_dc: np.ndarray) -> np.ndarray:
    return np.maximum(proj.base + SH_C0 * np.asarray(sh_dc, np.float64)[proj.index], 0.0)


def render(g: Gaussians, cam: Camera, sh_degree: int | None = None, cov3d: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) float32, not clamped above: render_ref.render's picture, compiled. `cov3d` as in `project`."""
    if len(g) == 0:
        return np.zeros((cam.height, cam.width, 3), np.float32)
    proj = project(g, cam, sh_degree, cov3d)
    return render_projection(proj, g.opacities.astype(np.float64)[proj.index], colours_of(proj, g.sh_dc))


def render_projection(proj: Projection, opacity: np.ndarray, colour: np.ndarray) -> np.ndarray:
    """The picture of projected splats with these opacities and colours (per projected splat)."""
    img = np.zeros((proj.height, proj.width, 3), np.float64)
    if len(proj.index):
        _render_tiles(proj.xy, proj.conic, np.ascontiguousarray(opacity, np.float64),
                      np.ascontiguousarray(colour, np.float64), proj.tile_ids, proj.tile_offsets,
                      proj.width, proj.height, img)
    return img.astype(np.float32)


@numba.njit(parallel=True, cache=True)
def _render_tiles(xy, conic, opacity, colour, tile_ids, tile_offsets, width, height, img):
    grid_x = (width + TILE - 1) // TILE
    grid_y = (height + TILE - 1) // TILE
    for t in numba.prange(grid_x * grid_y):
        ty = t // grid_x
        tx = t - ty * grid_x
        s, e = tile_offsets[t], tile_offsets[t + 1]
        for ly in range(TILE):
            y = ty * TILE + ly
            if y >= height:
                break
            for lx in range(TILE):
                x = tx * TILE + lx
                if x >= width:
                    break
                trans = 1.0
                r = 0.0
                gr = 0.0
                b = 0.0
                for k in range(s, e):
                    i = tile_ids[k]
                    dx = xy[i, 0] - x
                    dy = xy[i, 1] - y
                    power = -0.5 * (conic[i, 0] * dx * dx + conic[i, 2] * dy * dy) - conic[i, 1] * dx * dy
                    if power > 0.0:
                        continue
                    if power < POWER_SKIP and opacity[i] <= 1.0:
                        continue
                    alpha = min(ALPHA_MAX, opacity[i] * math.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    tn = trans * (1.0 - alpha)
                    if tn < T_MIN:
                        break
                    w = alpha * trans
                    r += w * colour[i, 0]
                    gr += w * colour[i, 1]
                    b += w * colour[i, 2]
                    trans = tn
                img[y, x, 0] = r
                img[y, x, 1] = gr
                img[y, x, 2] = b


# --- pair lists (fixed geometry) -----------------------------------------------------------------------------------

@numba.njit(parallel=True, cache=True)
def _pairs_per_pixel(xy, conic, opacity, tile_ids, tile_offsets, width, height, counts, fill, out_off, out_proj,
                     out_g):
    """Pass 1 (fill False): counts[pixel]; pass 2 (fill True): the pairs at out_off[pixel]."""
    grid_x = (width + TILE - 1) // TILE
    grid_y = (height + TILE - 1) // TILE
    for t in numba.prange(grid_x * grid_y):
        ty = t // grid_x
        tx = t - ty * grid_x
        s, e = tile_offsets[t], tile_offsets[t + 1]
        for ly in range(TILE):
            y = ty * TILE + ly
            if y >= height:
                break
            for lx in range(TILE):
                x = tx * TILE + lx
                if x >= width:
                    break
                pix = y * width + x
                n = 0
                pos = out_off[pix] if fill else 0
                trans = 1.0
                for k in range(s, e):
                    i = tile_ids[k]
                    dx = xy[i, 0] - x
                    dy = xy[i, 1] - y
                    power = -0.5 * (conic[i, 0] * dx * dx + conic[i, 2] * dy * dy) - conic[i, 1] * dx * dy
                    if power > 0.0 or power < POWER_SKIP:
                        continue
                    g = math.exp(power)
                    if g < ALPHA_MIN:
                        continue
                    if fill:
                        out_proj[pos + n] = i
                        out_g[pos + n] = g
                    n += 1
                    alpha = min(ALPHA_MAX, opacity[i] * g)
                    if alpha >= ALPHA_MIN:
                        trans *= 1.0 - alpha
                        if trans < T_STORE:
                            break
                if not fill:
                    counts[pix] = n


@dataclass
class PairLists:
    """The pairs of several cameras of one size, one splat set, fixed geometry. Pixel q of camera c is row
    c * H * W + q of `pixel_offsets` (CSR); a pair's `proj` indexes the cameras' projected splats, concatenated
    (`splat`: their index in the splat set, `base`: their fixed colour part)."""
    pixel_offsets: np.ndarray  # (C * H * W + 1,) int64
    proj: np.ndarray           # (P,) int32
    g: np.ndarray              # (P,) float32
    splat: np.ndarray          # (M,) int32
    base: np.ndarray           # (M, 3) float32
    cameras: int
    width: int
    height: int

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.pixel_offsets, self.proj, self.g, self.splat, self.base))

    @property
    def max_pairs(self) -> int:
        return int(np.diff(self.pixel_offsets).max(initial=0))


def pair_lists(g: Gaussians, cams: list[Camera], sh_degree: int | None = None) -> PairLists:
    """The pair lists of `g` seen from `cams` (all of one size).

    Two passes, so the pairs are written once into arrays of their final size (no per-camera pieces concatenated:
    that held the pairs twice at the peak): each camera's projection and per-pixel counts first, then the pairs."""
    width, height = cams[0].width, cams[0].height
    if any((cam.width, cam.height) != (width, height) for cam in cams):
        raise ValueError("pair_lists: the cameras differ in size")
    hw = width * height
    opacity_all = g.opacities.astype(np.float64)
    cov3d = covariances(g) if len(g) else None
    empty_i = np.zeros(0, np.int32)
    empty_f = np.zeros(0, np.float32)
    no_counts = np.zeros(0, np.int64)  # pass 2 writes no counts (an int64 array: pass 1's compiled signature)
    pixel_offsets = np.zeros(len(cams) * hw + 1, np.int64)
    projections = []
    total = 0
    for c, cam in enumerate(cams):
        p = project(g, cam, sh_degree, cov3d)
        counts = np.zeros(hw, np.int64)
        if len(p.index):
            _pairs_per_pixel(p.xy, p.conic, opacity_all[p.index], p.tile_ids, p.tile_offsets, width, height, counts,
                             False, counts, empty_i, empty_f)
        off = pixel_offsets[c * hw:(c + 1) * hw + 1]
        np.cumsum(counts, out=off[1:])
        off[1:] += total
        total = int(off[-1])
        projections.append(p)
    proj = np.empty(total, np.int32)
    pair_g = np.empty(total, np.float32)
    proj_total = 0
    for c, p in enumerate(projections):
        s, e = pixel_offsets[c * hw], pixel_offsets[(c + 1) * hw]
        if e > s:
            _pairs_per_pixel(p.xy, p.conic, opacity_all[p.index], p.tile_ids, p.tile_offsets, width, height,
                             no_counts, True, pixel_offsets[c * hw:(c + 1) * hw + 1], proj, pair_g)
            proj[s:e] += proj_total
        proj_total += len(p.index)
    splat = np.concatenate([p.index.astype(np.int32) for p in projections])
    base = np.concatenate([p.base.astype(np.float32) for p in projections]).reshape(-1, 3)
    return PairLists(pixel_offsets, proj, pair_g, splat, base, len(cams), width, height)


def threads() -> int:
    # each thread keeps a gradient row of the whole splat set: at most 8 rows
    return max(1, min(numba.get_num_threads(), os.cpu_count() or 1, 8))


def loss_and_grad(pl: PairLists, opacity: np.ndarray, dc_colour: np.ndarray, target: np.ndarray,
                  grad: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """The mean over pixels and channels of (clamp(C, 0, 1) - target)^2 (target (C, H, W, 3)), and, where `grad`,
    its gradient with respect to each splat's opacity (N,) and to its colour's DC term SH_C0 sh_dc (N, 3), through
    the max(., 0) colour clamp, the image clamp and the 0.99 alpha clamp (zero past each). `opacity` (N,) and
    `dc_colour` (N, 3) = SH_C0 sh_dc are per splat of the set the lists were made of."""
    n = len(opacity)
    nt = threads()
    g_op = np.zeros((nt, n if grad else 0))
    g_dc = np.zeros((nt, n if grad else 0, 3))
    losses = np.zeros(pl.cameras)
    tgt = np.ascontiguousarray(target, np.float32).reshape(pl.cameras, -1, 3)
    scale = 2.0 / (tgt.size)
    _loss_grad(pl.pixel_offsets, pl.proj, pl.g, pl.splat, pl.base, np.ascontiguousarray(opacity, np.float64),
               np.ascontiguousarray(dc_colour, np.float64), tgt, pl.cameras, pl.width * pl.height,
               max(1, pl.max_pairs), grad, scale, nt, losses, g_op, g_dc)
    loss = float(losses.sum()) / tgt.size
    if not grad:
        return loss, np.zeros(0), np.zeros((0, 3))
    return loss, g_op.sum(0), g_dc.sum(0)


@numba.njit(parallel=True, cache=True)
def _loss_grad(pixel_offsets, proj, pg, splat, base, opacity, dc, target, ncam, hw, max_pairs, grad, scale, nt,
               losses, g_op, g_dc):
    for t in numba.prange(nt):
        # what the forward pass met, per blended pair, for the backward pass (no second gather of the same values)
        alphas = np.empty(max_pairs)
        ks = np.empty(max_pairs, np.int64)
        splats = np.empty(max_pairs, np.int64)
        cols = np.empty((max_pairs, 3))
        for c in range(ncam):
            if c % nt != t:  # cameras round-robin over threads, each thread its own gradient row
                continue
            cam_loss = 0.0
            for q in range(hw):
                row = c * hw + q
                s, e = pixel_offsets[row], pixel_offsets[row + 1]
                trans = 1.0
                r0 = 0.0
                r1 = 0.0
                r2 = 0.0
                m = 0
                for k in range(s, e):
                    i = splat[proj[k]]
                    alpha = opacity[i] * pg[k]
                    if alpha > ALPHA_MAX:
                        alpha = ALPHA_MAX
                    if alpha < ALPHA_MIN:
                        continue
                    tn = trans * (1.0 - alpha)
                    if tn < T_MIN:
                        break
                    b = proj[k]
                    w = alpha * trans
                    c0 = max(base[b, 0] + dc[i, 0], 0.0)
                    c1 = max(base[b, 1] + dc[i, 1], 0.0)
                    c2 = max(base[b, 2] + dc[i, 2], 0.0)
                    r0 += w * c0
                    r1 += w * c1
                    r2 += w * c2
                    alphas[m] = alpha
                    ks[m] = k
                    splats[m] = i
                    cols[m, 0] = c0
                    cols[m, 1] = c1
                    cols[m, 2] = c2
                    m += 1
                    trans = tn
                d0 = min(r0, 1.0) - target[c, q, 0]
                d1 = min(r1, 1.0) - target[c, q, 1]
                d2 = min(r2, 1.0) - target[c, q, 2]
                cam_loss += d0 * d0 + d1 * d1 + d2 * d2
                if not grad:
                    continue
                # dL/dC through clamp(C, 0, 1) (C >= 0 always)
                e0 = scale * d0 if r0 < 1.0 else 0.0
                e1 = scale * d1 if r1 < 1.0 else 0.0
                e2 = scale * d2 if r2 < 1.0 else 0.0
                if e0 == 0.0 and e1 == 0.0 and e2 == 0.0:
                    continue
                # back to front: T_j = T_{j+1} / (1 - a_j); behind = sum over later splats of c a T
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                tj = trans
                for j in range(m - 1, -1, -1):
                    a = alphas[j]
                    i = splats[j]
                    tj = tj / (1.0 - a)
                    c0 = cols[j, 0]
                    c1 = cols[j, 1]
                    c2 = cols[j, 2]
                    w = a * tj
                    # max(p, 0) > 0 exactly where p > 0: the gradient through the colour clamp
                    if c0 > 0.0:
                        g_dc[t, i, 0] += e0 * w
                    if c1 > 0.0:
                        g_dc[t, i, 1] += e1 * w
                    if c2 > 0.0:
                        g_dc[t, i, 2] += e2 * w
                    inv = 1.0 / (1.0 - a)
                    da = (e0 * (c0 * tj - s0 * inv) + e1 * (c1 * tj - s1 * inv) + e2 * (c2 * tj - s2 * inv))
                    if a < ALPHA_MAX:  # the 0.99 clamp: alpha < 0.99 exactly where o g < 0.99
                        g_op[t, i] += da * pg[ks[j]]
                    s0 += c0 * w
                    s1 += c1 * w
                    s2 += c2 * w
            losses[c] = cam_loss
