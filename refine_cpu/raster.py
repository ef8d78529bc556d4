"""A numba rasteriser with our renderer's conventions, and for fixed geometry its per-pixel pair lists, forward and
backward over opacity and DC colour (the CPU refinement of the merged LOD levels, lod.md 6).

The conventions are splatstream/render_ref.py's (its numpy reference, whose `preprocess`, `tile_lists` and SH colour
`project` computes bit for bit, compiled): the pinhole of `Camera` with pixel (col, row) at (col, row) after ndc2Pix,
EWA with the 0.3 px^2 low-pass, splats with depth <= near culled, depth order (stable, ties by index), alpha =
min(0.99, o g) with g = exp(power), skipped when power > 0 or alpha < 1/255, a pixel stops once T (1 - alpha) < 1e-4,
colour max(SH(dir) + 0.5, 0), black background. refine_gpu/levels.py's docstring lists the same (gsplat's, matched
there).

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
from numba import types
from numba.extending import intrinsic

from splatstream.camera import Camera
from splatstream.gaussians import Gaussians, covariances
from splatstream.render_ref import (
    ALPHA_MAX,
    ALPHA_MIN,
    FRUSTUM_CLAMP,
    LOW_PASS,
    RADIUS_SIGMAS,
    T_MIN,
    TILE,
)
from splatstream.sh import COLOR_OFFSET, SH_C0, SH_C1, SH_C2, SH_C3, SH_COEFFS_FOR_DEGREE

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
# The tile walk first lists, per pixel row, the splats that can reach it and the columns they can reach: those where
# power >= ROW_POWER, an ellipse solved per row (POWER_SKIP less 0.5: a margin in the exponent far above the rounding
# of either computation), widened by a pixel each side. Outside it, power < POWER_SKIP for certain, where the kernels
# skip the splat anyway, so the row lists change no bit; inside, each pixel runs the kernels' own test. Splats too
# far out or too wide (ROW_MAX px) for that bound to hold are kept for the whole row.
ROW_POWER = POWER_SKIP - 0.5
ROW_MAX = 1e6


@numba.njit(inline="always")
def _row_candidates(xy, conic, opacity, tile_ids, s, e, y, x0, x1, cull_any_opacity, row_i, row_lo, row_hi):
    """Of the tile's splats tile_ids[s:e] (depth order), those that can pass the POWER_SKIP test somewhere on pixel
    row y within columns [x0, x1), with the first and last column they can (row_i, row_lo, row_hi; returns how
    many). `cull_any_opacity` False: a splat with an opacity above 1 is kept whole (the render skips below POWER_SKIP
    only where the opacity is at most 1)."""
    reach = -2.0 * ROW_POWER
    n = 0
    for k in range(s, e):
        i = tile_ids[k]
        lo = x0
        hi = x1 - 1
        a = conic[i, 0]
        b = conic[i, 1]
        c = conic[i, 2]
        cx = xy[i, 0]
        dy = xy[i, 1] - y
        if ((cull_any_opacity or opacity[i] <= 1.0) and a > 0.0 and abs(cx) <= ROW_MAX
                and abs(xy[i, 1]) <= ROW_MAX):
            det = a * c - b * b
            if det > 0.0:
                # power >= ROW_POWER  <=>  a dx^2 + 2 b dy dx + c dy^2 <= reach, dx = cx - x: a quadratic in x
                bd = b * dy
                wide = (abs(bd) + math.sqrt(a * reach + (b * b + a * c) * dy * dy)) / a
                if wide <= ROW_MAX:
                    disc = a * reach - det * dy * dy
                    if disc < 0.0:
                        continue
                    sq = math.sqrt(disc)
                    first = math.floor(cx + (bd - sq) / a) - 1
                    last = math.ceil(cx + (bd + sq) / a) + 1
                    lo = max(lo, first)
                    hi = min(hi, last)
                    if lo > hi:
                        continue
        row_i[n] = i
        row_lo[n] = lo
        row_hi[n] = hi
        n += 1
    return n


@dataclass
class Projection:
    """One camera's projected splats (render_ref.preprocess's, depth order) and its tile lists."""
    index: np.ndarray      # (M,) int64 splat index into the splat set
    xy: np.ndarray         # (M, 2) float64 pixel-index coordinates
    conic: np.ndarray      # (M, 3) float64
    base: np.ndarray       # (M, 3) float64: SH(dir) + 0.5 without the DC term (the fixed, view-dependent part)
    tile_ids: np.ndarray   # tile-major, depth-minor projected ids
    tile_offsets: np.ndarray
    width: int
    height: int


def project(g: Gaussians, cam: Camera, sh_degree: int | None = None, cov3d: np.ndarray | None = None) -> Projection:
    """render_ref.preprocess (depth order), tile_lists and the view-dependent colour part, compiled and bit for bit
    the numpy path's (per splat in parallel; only the depth sort is numpy's). `cov3d`: covariances(g), computed once
    where one splat set is projected for many cameras."""
    n = len(g)
    width, height = cam.width, cam.height
    grid_x, grid_y = -(-width // TILE), -(-height // TILE)
    if cov3d is None:
        cov3d = covariances(g)
    ok = np.empty(n, np.uint8)
    depth = np.empty(n)
    xy = np.empty((n, 2))
    conic = np.empty((n, 3))
    rect = np.empty((n, 4), np.int64)
    fx, fy = cam.focal
    tan_x, tan_y = cam.tan_half_fov_x, cam.tan_half_fov_y
    if n:
        _project_splats(g.positions, cov3d, cam.world_to_camera_cv(), fx, fy, tan_x, tan_y, FRUSTUM_CLAMP * tan_x,
                        FRUSTUM_CLAMP * tan_y, cam.near, width, height, grid_x, grid_y, ok, depth, xy, conic, rect)
    sel = np.flatnonzero(ok)
    order = sel[np.argsort(depth[sel], kind="stable")]  # ties by index, as preprocess's
    del depth
    # a run of `order` per thread, and only where the runs are long enough to pay for their per-tile counts
    chunks = max(1, min(numba.get_num_threads(), len(order) // 65536))
    ids, offsets = _bin_tiles(order, rect, grid_x, grid_x * grid_y, chunks)
    have = g.sh_degree
    degree = have if sh_degree is None else min(int(sh_degree), have)
    base = np.empty((n, 3))
    if len(order):
        _view_colours(ok, g.positions, g.sh_rest, np.asarray(cam.eye, np.float64), SH_COEFFS_FOR_DEGREE[degree], base)
    xy_o, conic_o, base_o = _gather_rows(order, xy, conic, base)
    return Projection(order, xy_o, conic_o, base_o, ids, offsets, width, height)


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
        row_i = np.empty(e - s, np.int64)
        row_lo = np.empty(e - s, np.int64)
        row_hi = np.empty(e - s, np.int64)
        x0 = tx * TILE
        x1 = min(x0 + TILE, width)
        for ly in range(TILE):
            y = ty * TILE + ly
            if y >= height:
                break
            n = _row_candidates(xy, conic, opacity, tile_ids, s, e, y, x0, x1, False, row_i, row_lo, row_hi)
            for x in range(x0, x1):
                trans = 1.0
                r = 0.0
                gr = 0.0
                b = 0.0
                for k in range(n):
                    if x < row_lo[k] or x > row_hi[k]:
                        continue
                    i = row_i[k]
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


# --- the projection, compiled (render_ref.preprocess + tile_lists + the view-dependent colour part) -----------------
#
# Bit for bit render_ref's numpy path (tests/test_refine_cpu.py checks every array): the same float64 operations in
# the same order, and where numpy hands a product to OpenBLAS (the view transform, the EWA Jacobian and covariance
# products) the kernel computes what OpenBLAS's x86-64 dgemm/dgemv kernels compute for these 3-long dot products,
# a chain of fused multiply-adds in index order (fma(a2, b2, fma(a1, b1, a0 b0)), then 0 + that: beta = 0 zeroes C
# first). Where the two disagreed the refined scene's bytes would move, not only the images' last bits.

@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's llvm.fma: one instruction where the CPU has FMA)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return sig, codegen


@numba.njit(inline="always")
def _dot3(a0, a1, a2, b0, b1, b2):
    # OpenBLAS's sum of a 3-long product (the dgemm/dgemv kernels' FMA chain in index order, C zeroed first)
    return 0.0 + _fma(a2, b2, _fma(a1, b1, a0 * b0))


@numba.njit(inline="always")
def _clip(x, lo, hi):
    # np.clip: a NaN stays NaN
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _project_splats(pos, cov3d, m, fx, fy, tan_x, tan_y, lim_x, lim_y, near, width, height, grid_x, grid_y,
                    ok, depth, xy, conic, rect):
    """render_ref.preprocess per splat, before the depth sort: ok[i] 1 where splat i survives (in front of the near
    plane, a finite invertible 2D covariance, a radius > 0 touching at least one tile), its view depth, pixel
    position, conic and tile rectangle (x0, y0, x1, y1)."""
    big = 1e9
    for i in numba.prange(pos.shape[0]):
        ok[i] = 0
        p0 = np.float64(pos[i, 0])
        p1 = np.float64(pos[i, 1])
        p2 = np.float64(pos[i, 2])
        # depth_all = pos @ m[2, :3] + m[2, 3] (a dgemv) decides the near cull; the sort's depth is the dgemm's t.z
        if not _dot3(p0, p1, p2, m[2, 0], m[2, 1], m[2, 2]) + m[2, 3] > near:
            continue
        t0 = _dot3(p0, p1, p2, m[0, 0], m[0, 1], m[0, 2]) + m[0, 3]
        t1 = _dot3(p0, p1, p2, m[1, 0], m[1, 1], m[1, 2]) + m[1, 3]
        tz = _dot3(p0, p1, p2, m[2, 0], m[2, 1], m[2, 2]) + m[2, 3]
        # cov2d: the EWA Jacobian J (2 x 3, J[0, 1] = J[1, 0] = 0), T = J W, Sigma' = (T Sigma) T^T
        tx = _clip(t0 / tz, -lim_x, lim_x) * tz
        ty = _clip(t1 / tz, -lim_y, lim_y) * tz
        tz2 = tz * tz
        j00 = fx / tz
        j02 = -fx * tx / tz2
        j11 = fy / tz
        j12 = -fy * ty / tz2
        a00 = _dot3(j00, 0.0, j02, m[0, 0], m[1, 0], m[2, 0])
        a01 = _dot3(j00, 0.0, j02, m[0, 1], m[1, 1], m[2, 1])
        a02 = _dot3(j00, 0.0, j02, m[0, 2], m[1, 2], m[2, 2])
        a10 = _dot3(0.0, j11, j12, m[0, 0], m[1, 0], m[2, 0])
        a11 = _dot3(0.0, j11, j12, m[0, 1], m[1, 1], m[2, 1])
        a12 = _dot3(0.0, j11, j12, m[0, 2], m[1, 2], m[2, 2])
        c = cov3d[i]
        d00 = _dot3(a00, a01, a02, c[0, 0], c[1, 0], c[2, 0])
        d01 = _dot3(a00, a01, a02, c[0, 1], c[1, 1], c[2, 1])
        d02 = _dot3(a00, a01, a02, c[0, 2], c[1, 2], c[2, 2])
        d10 = _dot3(a10, a11, a12, c[0, 0], c[1, 0], c[2, 0])
        d11 = _dot3(a10, a11, a12, c[0, 1], c[1, 1], c[2, 1])
        d12 = _dot3(a10, a11, a12, c[0, 2], c[1, 2], c[2, 2])
        ca = _dot3(d00, d01, d02, a00, a01, a02) + LOW_PASS
        cb = _dot3(d00, d01, d02, a10, a11, a12)
        cc = _dot3(d10, d11, d12, a10, a11, a12) + LOW_PASS
        det = ca * cc - cb * cb
        if det == 0.0 or not np.isfinite(det):
            continue
        det_inv = 1.0 / det
        k0 = cc * det_inv
        k1 = -cb * det_inv
        k2 = ca * det_inv
        mid = 0.5 * (ca + cc)
        v = mid * mid - det
        if v < 0.1:  # np.maximum(0.1, v): a NaN stays NaN
            v = 0.1
        sq = np.sqrt(v)
        lam1 = mid + sq
        lam2 = mid - sq
        lam = lam1 if lam1 >= lam2 or np.isnan(lam1) else lam2
        if np.isnan(lam2):
            lam = lam2
        radius = np.ceil(RADIUS_SIGMAS * np.sqrt(lam))
        px = ((t0 / (tz * tan_x) + 1.0) * width - 1.0) * 0.5
        py = ((t1 / (tz * tan_y) + 1.0) * height - 1.0) * 0.5
        if not (np.isfinite(radius) and np.isfinite(px) and np.isfinite(py) and np.isfinite(k0)
                and np.isfinite(k1) and np.isfinite(k2)):
            continue
        # getRect: (int) truncates towards zero, then clamps to [0, grid]
        rx0 = np.int64(_clip(np.trunc(_clip((px - radius) / TILE, -big, big)), 0, grid_x))
        ry0 = np.int64(_clip(np.trunc(_clip((py - radius) / TILE, -big, big)), 0, grid_y))
        rx1 = np.int64(_clip(np.trunc(_clip((px + radius + TILE - 1) / TILE, -big, big)), 0, grid_x))
        ry1 = np.int64(_clip(np.trunc(_clip((py + radius + TILE - 1) / TILE, -big, big)), 0, grid_y))
        if not (radius > 0 and (rx1 - rx0) * (ry1 - ry0) > 0):
            continue
        ok[i] = 1
        depth[i] = tz
        xy[i, 0] = px
        xy[i, 1] = py
        conic[i, 0] = k0
        conic[i, 1] = k1
        conic[i, 2] = k2
        rect[i, 0] = rx0
        rect[i, 1] = ry0
        rect[i, 2] = rx1
        rect[i, 3] = ry1


@numba.njit(parallel=True, cache=True)
def _bin_tiles(order, rect, grid_x, ntiles, chunks):
    """render_ref.tile_lists of the splats `order` (depth order): each tile's projected ids (positions in `order`)
    in depth order, by a counting sort (stable, so numpy's stable argsort's order, which is unique). In parallel
    over `chunks` consecutive runs of `order`: each run's count per tile, then each run fills from its own start in
    every tile (the runs' starts in run order keep the sort stable)."""
    n = order.shape[0]
    step = (n + chunks - 1) // chunks
    counts = np.zeros((chunks, ntiles), np.int64)
    for c in numba.prange(chunks):
        for j in range(c * step, min(n, (c + 1) * step)):
            i = order[j]
            for ty in range(rect[i, 1], rect[i, 3]):
                for tx in range(rect[i, 0], rect[i, 2]):
                    counts[c, ty * grid_x + tx] += 1
    offsets = np.zeros(ntiles + 1, np.int64)
    start = np.empty((chunks, ntiles), np.int64)
    total = 0
    for t in range(ntiles):
        offsets[t] = total
        for c in range(chunks):
            start[c, t] = total
            total += counts[c, t]
    offsets[ntiles] = total
    ids = np.empty(total, np.int64)
    for c in numba.prange(chunks):
        cursor = start[c]
        for j in range(c * step, min(n, (c + 1) * step)):
            i = order[j]
            for ty in range(rect[i, 1], rect[i, 3]):
                for tx in range(rect[i, 0], rect[i, 2]):
                    t = ty * grid_x + tx
                    ids[cursor[t]] = j
                    cursor[t] += 1
    return ids, offsets


@numba.njit(parallel=True, cache=True)
def _gather_rows(order, xy, conic, base):
    """xy[order], conic[order], base[order], in parallel."""
    m = order.shape[0]
    xy_o = np.empty((m, 2))
    conic_o = np.empty((m, 3))
    base_o = np.empty((m, 3))
    for j in numba.prange(m):
        i = order[j]
        xy_o[j, 0] = xy[i, 0]
        xy_o[j, 1] = xy[i, 1]
        for k in range(3):
            conic_o[j, k] = conic[i, k]
            base_o[j, k] = base[i, k]
    return xy_o, conic_o, base_o


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _view_colours(ok, pos, sh_rest, eye, coeffs, base):
    """base[i] = eval_sh(0, sh_rest, view_directions(pos, eye), clamp=False) of each splat with ok[i]: the
    view-dependent part of its colour and the 0.5 offset (sh.sh_basis's products and einsum's sum, in their order;
    `coeffs`: the basis size, (degree + 1)^2). In splat order, not depth order: the SH rows are read in sequence."""
    for i in numba.prange(ok.shape[0]):
        if not ok[i]:
            continue
        d0 = np.float64(pos[i, 0]) - eye[0]
        d1 = np.float64(pos[i, 1]) - eye[1]
        d2 = np.float64(pos[i, 2]) - eye[2]
        n = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        x = y = z = 0.0  # a splat at the eye: the zero direction
        if n > 0:
            x = d0 / n
            y = d1 / n
            z = d2 / n
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        for ch in range(3):
            # sh_basis's products, summed in einsum's order (the DC term, zero here, first: colours_of adds it)
            acc = SH_C0 * 0.0
            if coeffs > 1:
                acc += -SH_C1 * y * np.float64(sh_rest[i, 0, ch])
                acc += SH_C1 * z * np.float64(sh_rest[i, 1, ch])
                acc += -SH_C1 * x * np.float64(sh_rest[i, 2, ch])
            if coeffs > 4:
                acc += SH_C2[0] * xy * np.float64(sh_rest[i, 3, ch])
                acc += SH_C2[1] * yz * np.float64(sh_rest[i, 4, ch])
                acc += SH_C2[2] * (2.0 * zz - xx - yy) * np.float64(sh_rest[i, 5, ch])
                acc += SH_C2[3] * xz * np.float64(sh_rest[i, 6, ch])
                acc += SH_C2[4] * (xx - yy) * np.float64(sh_rest[i, 7, ch])
            if coeffs > 9:
                acc += SH_C3[0] * y * (3.0 * xx - yy) * np.float64(sh_rest[i, 8, ch])
                acc += SH_C3[1] * xy * z * np.float64(sh_rest[i, 9, ch])
                acc += SH_C3[2] * y * (4.0 * zz - xx - yy) * np.float64(sh_rest[i, 10, ch])
                acc += SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * np.float64(sh_rest[i, 11, ch])
                acc += SH_C3[4] * x * (4.0 * zz - xx - yy) * np.float64(sh_rest[i, 12, ch])
                acc += SH_C3[5] * z * (xx - yy) * np.float64(sh_rest[i, 13, ch])
                acc += SH_C3[6] * x * (xx - 3.0 * yy) * np.float64(sh_rest[i, 14, ch])
            base[i, ch] = acc + COLOR_OFFSET


# --- pair lists (fixed geometry) -----------------------------------------------------------------------------------

@intrinsic
def _fetch_add(typingctx, ary, val):
    """ary[0] += val as one atomic step; returns ary[0] before it (llvm's atomicrmw add)."""
    sig = types.int64(ary, types.int64)

    def codegen(context, builder, signature, args):
        a = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", a.data, args[1], "monotonic")
    return sig, codegen


@numba.njit(cache=True)
def _grown(proj, g, n, room):
    """proj, g with room for `room`, their first n kept."""
    grown_proj = np.empty(room, np.int32)
    grown_g = np.empty(room, np.float32)
    grown_proj[:n] = proj[:n]
    grown_g[:n] = g[:n]
    return grown_proj, grown_g


@numba.njit(cache=True)
def _walk_tile(xy, conic, opacity, tile_ids, tile_offsets, width, height, t, counts):
    """Tile t's pairs (its pixels row-major, each pixel's in depth order: the splats with g >= ALPHA_MIN until T under
    the opacities passes under T_STORE) and counts[pixel] of its pixels; returns (pairs, proj, g), the arrays grown as
    the pairs come (a tile's count is known only at its end)."""
    grid_x = (width + TILE - 1) // TILE
    ty = t // grid_x
    tx = t - ty * grid_x
    s, e = tile_offsets[t], tile_offsets[t + 1]
    row_i = np.empty(e - s, np.int64)
    row_lo = np.empty(e - s, np.int64)
    row_hi = np.empty(e - s, np.int64)
    room = max(1024, 4 * (e - s))
    own_proj = np.empty(room, np.int32)
    own_g = np.empty(room, np.float32)
    nt = 0
    x0 = tx * TILE
    x1 = min(x0 + TILE, width)
    for y in range(ty * TILE, min(ty * TILE + TILE, height)):
        nr = _row_candidates(xy, conic, opacity, tile_ids, s, e, y, x0, x1, True, row_i, row_lo, row_hi)
        # the row's pairs are at most its candidates' columns: room for them before the row, not a check a pair
        most = nt
        for k in range(nr):
            most += row_hi[k] - row_lo[k] + 1
        if most > room:
            room = max(2 * room, most)
            own_proj, own_g = _grown(own_proj, own_g, nt, room)
        for x in range(x0, x1):
            n0 = nt
            trans = 1.0
            for k in range(nr):
                if x < row_lo[k] or x > row_hi[k]:
                    continue
                i = row_i[k]
                dx = xy[i, 0] - x
                dy = xy[i, 1] - y
                power = -0.5 * (conic[i, 0] * dx * dx + conic[i, 2] * dy * dy) - conic[i, 1] * dx * dy
                if power > 0.0 or power < POWER_SKIP:
                    continue
                g = math.exp(power)
                if g < ALPHA_MIN:
                    continue
                own_proj[nt] = i
                own_g[nt] = g
                nt += 1
                alpha = min(ALPHA_MAX, opacity[i] * g)
                if alpha >= ALPHA_MIN:
                    trans *= 1.0 - alpha
                    if trans < T_STORE:
                        break
            counts[y * width + x] = nt - n0
    return nt, own_proj, own_g


@numba.njit(parallel=True, cache=True)
def _walk_tiles(xy, conic, opacity, tile_ids, tile_offsets, width, height, tiles, counts, tile_pairs, tile_start,
                cursor, out_proj, out_g):
    """One walk over the tiles `tiles` of a camera (_walk_tile each): counts[pixel] (every pixel of the tiles),
    tile_pairs[tile], and each tile's pairs copied to out_proj / out_g from tile_start[tile], a run reserved at
    cursor[0] (atomically: the tiles finish in any order). A tile whose run would pass the arrays' end keeps
    tile_start -1 and writes nothing there (pair_lists walks it again with room)."""
    cap = len(out_proj)
    for j in numba.prange(len(tiles)):
        t = tiles[j]
        nt, own_proj, own_g = _walk_tile(xy, conic, opacity, tile_ids, tile_offsets, width, height, t, counts)
        tile_pairs[t] = nt
        at = _fetch_add(cursor, nt) if nt else 0
        if at + nt > cap:
            tile_start[t] = -1
        else:
            tile_start[t] = at
            out_proj[at:at + nt] = own_proj[:nt]
            out_g[at:at + nt] = own_g[:nt]


@numba.njit(parallel=True, cache=True)
def _place_pairs(width, height, counts, tile_start, walked_proj, walked_g, pixel_offsets, first, shift, proj, pair_g):
    """The walked pairs (tile by tile, _walk_tiles') into the lists' pixel order: pixel q's at pixel_offsets[q] -
    first of proj / pair_g, their projected ids plus `shift` (the camera's first projected splat)."""
    grid_x = (width + TILE - 1) // TILE
    grid_y = (height + TILE - 1) // TILE
    for t in numba.prange(grid_x * grid_y):
        ty = t // grid_x
        tx = t - ty * grid_x
        at = tile_start[t]
        x0 = tx * TILE
        x1 = min(x0 + TILE, width)
        for y in range(ty * TILE, min(ty * TILE + TILE, height)):
            for x in range(x0, x1):
                pix = y * width + x
                to = pixel_offsets[pix] - first
                for k in range(counts[pix]):
                    proj[to + k] = walked_proj[at + k] + shift
                    pair_g[to + k] = walked_g[at + k]
                at += counts[pix]


# The walk's first room, in pairs a pixel of one camera (grown to the largest camera's pairs and a quarter as they
# come; a camera that passes it walks its tiles that did not fit again, once the room is there)
WALK_ROOM_PAIRS = 32


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
    projected: np.ndarray      # (C + 1,) int64: camera c's projected splats are [projected[c], projected[c + 1])

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.pixel_offsets, self.proj, self.g, self.splat, self.base, self.projected))

    @property
    def max_projected(self) -> int:
        """The most projected splats of one camera (the size of loss_and_grad's per-camera table)."""
        return int(np.diff(self.projected).max(initial=0))

    @property
    def max_pairs(self) -> int:
        return int(np.diff(self.pixel_offsets).max(initial=0))


def pair_lists(g: Gaussians, cams: list[Camera], sh_degree: int | None = None) -> PairLists:
    """The pair lists of `g` seen from `cams` (all of one size).

    One walk a camera: its tiles' pairs go to a walk buffer (one camera's, reused), then into the lists in pixel
    order; the lists' arrays grow by each camera's pairs in place (ndarray.resize: a large array's realloc moves its
    pages, it does not copy them), so the pairs are held once at the peak, with one camera's more (the walk buffer:
    WALK_ROOM_PAIRS a pixel, or a quarter over the largest camera's pairs; while the lists are built the fit's
    tables and gradient rows, which CpuLevelRefiner.peak_bytes counts, are not held). Before (branch pairwalk31): a
    count walk over every camera, then a fill walk projecting each camera again, the same arrays at 1.5-2x the CPU
    (BENCHMARKS.md, "The pair lists in one walk")."""
    width, height = cams[0].width, cams[0].height
    if any((cam.width, cam.height) != (width, height) for cam in cams):
        raise ValueError("pair_lists: the cameras differ in size")
    hw = width * height
    n_tiles = -(-width // TILE) * -(-height // TILE)
    opacity_all = g.opacities.astype(np.float64)
    cov3d = covariances(g)
    pixel_offsets = np.zeros(len(cams) * hw + 1, np.int64)
    projected = np.zeros(len(cams) + 1, np.int64)  # camera c's projected splats: [projected[c], projected[c + 1])
    proj = np.empty(0, np.int32)
    pair_g = np.empty(0, np.float32)
    splat = np.empty(0, np.int32)
    base = np.empty((0, 3), np.float32)
    walked_proj = np.empty(WALK_ROOM_PAIRS * hw, np.int32)
    walked_g = np.empty(WALK_ROOM_PAIRS * hw, np.float32)
    counts = np.empty(hw, np.int64)
    tile_pairs = np.empty(n_tiles, np.int64)
    tile_start = np.empty(n_tiles, np.int64)
    cursor = np.zeros(1, np.int64)
    every_tile = np.arange(n_tiles, dtype=np.int64)
    total = 0
    for c, cam in enumerate(cams):
        p = project(g, cam, sh_degree, cov3d)
        m = len(p.index)
        projected[c + 1] = projected[c] + m
        off = pixel_offsets[c * hw:(c + 1) * hw + 1]
        if m == 0:
            off[:] = total
            continue
        splat.resize(projected[c + 1], refcheck=False)
        base.resize((projected[c + 1], 3), refcheck=False)
        splat[projected[c]:] = p.index
        base[projected[c]:] = p.base
        opacity = opacity_all[p.index]
        tiles = every_tile
        cursor[0] = 0
        while True:
            _walk_tiles(p.xy, p.conic, opacity, p.tile_ids, p.tile_offsets, width, height, tiles, counts, tile_pairs,
                        tile_start, cursor, walked_proj, walked_g)
            missed = tiles[tile_start[tiles] < 0]
            if not len(missed):
                break
            # the tiles that fitted hold [0, used) (every reservation before the first that passed the end fitted,
            # every one after it passed it too); make room for the others and the camera's next a quarter more
            used = int(tile_pairs.sum() - tile_pairs[missed].sum())
            room = int(1.25 * tile_pairs.sum()) + 1
            walked_proj.resize(room, refcheck=False)
            walked_g.resize(room, refcheck=False)
            cursor[0] = used
            tiles = missed
        np.cumsum(counts, out=off[1:])
        off[0] = 0
        off += total
        first, total = total, int(off[-1])
        proj.resize(total, refcheck=False)
        pair_g.resize(total, refcheck=False)
        _place_pairs(width, height, counts, tile_start, walked_proj, walked_g, off, first, np.int32(projected[c]),
                     proj[first:], pair_g[first:])
        del p
    return PairLists(pixel_offsets, proj, pair_g, splat, base, len(cams), width, height, projected)


# The gradient rows of loss_and_grad (cameras round-robin over them, each row summed alone, the rows added in order):
# a constant, not the thread count, so that the fit's floats, and the refined bytes, are the same on any number of
# threads (a partitioned encode refines in Dask workers and in this process alike; branch partrefine31). The rows are
# the fit's most threads: 16, so that a 16-core host (the GPU machine) fits on all its cores, not 8 (refinewall31;
# 32 training cameras, two a row, 16 far ones, one a row). Each row is GRADIENT_COLUMNS float64 a splat of the set;
# fewer threads take rows in turn.
GRADIENT_ROWS = 16
GRADIENT_COLUMNS = 4  # a splat's opacity gradient and its three DC ones, side by side


def loss_and_grad(pl: PairLists, opacity: np.ndarray, dc_colour: np.ndarray, target: np.ndarray,
                  grad: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """The mean over pixels and channels of (clamp(C, 0, 1) - target)^2 (target (C, H, W, 3)), and, where `grad`,
    its gradient with respect to each splat's opacity (N,) and to its colour's DC term SH_C0 sh_dc (N, 3), through
    the max(., 0) colour clamp, the image clamp and the 0.99 alpha clamp (zero past each). `opacity` (N,) and
    `dc_colour` (N, 3) = SH_C0 sh_dc are per splat of the set the lists were made of."""
    n = len(opacity)
    nt = GRADIENT_ROWS
    # each row's opacity and DC gradients side by side (a splat's four in one cache line of the scatter)
    grads = np.zeros((nt, n if grad else 0, GRADIENT_COLUMNS))
    losses = np.zeros(pl.cameras)
    tgt = np.ascontiguousarray(target, np.float32).reshape(pl.cameras, -1, 3)
    scale = 2.0 / (tgt.size)
    _loss_grad(pl.pixel_offsets, pl.proj, pl.g, pl.splat, pl.base, pl.projected,
               np.ascontiguousarray(opacity, np.float64), np.ascontiguousarray(dc_colour, np.float64), tgt,
               pl.cameras, pl.width * pl.height, max(1, pl.max_pairs), max(1, pl.max_projected), grad, scale, nt,
               losses, grads)
    loss = float(losses.sum()) / tgt.size
    if not grad:
        return loss, np.zeros(0), np.zeros((0, 3))
    # the rows added in order, as numpy's grads.sum(0) adds them (the same bits), in parallel over the splats: with 16
    # rows a serial sum would be a step's largest serial part on many cores
    g_op = np.empty(n)
    g_dc = np.empty((n, 3))
    _sum_rows(grads, g_op, g_dc)
    return loss, g_op, g_dc


@numba.njit(parallel=True, cache=True)
def _sum_rows(grads, g_op, g_dc):
    """g_op[i], g_dc[i] = grads[0, i] + grads[1, i] + ... in row order (numpy's sum over axis 0, bit for bit)."""
    for i in numba.prange(grads.shape[1]):
        a0 = grads[0, i, 0]
        a1 = grads[0, i, 1]
        a2 = grads[0, i, 2]
        a3 = grads[0, i, 3]
        for r in range(1, grads.shape[0]):
            a0 += grads[r, i, 0]
            a1 += grads[r, i, 1]
            a2 += grads[r, i, 2]
            a3 += grads[r, i, 3]
        g_op[i] = a0
        g_dc[i, 0] = a1
        g_dc[i, 1] = a2
        g_dc[i, 2] = a3


# A projected splat's row of a camera's table (_pack_camera): its opacity and its clamped colour (3), 32 bytes, so
# that a pair's forward reads one row where it read the splat index, the opacity, the fixed colour part and the DC
# term (four places in memory: the pair loops' cost is those reads more than their arithmetic).
PACKED_COLUMNS = 4


@numba.njit(inline="always")
def _pack_camera(splat, base, opacity, dc, lo, hi, packed):
    """packed[b - lo] = (opacity, max(base + dc, 0) per channel) of projected splats lo <= b < hi (one camera's;
    splat[b] its splat): the values _loss_grad's pairs read, each computed once a camera and step rather than once a
    pair, by the same operations (so the same bits)."""
    for b in range(lo, hi):
        i = splat[b]
        packed[b - lo, 0] = opacity[i]
        packed[b - lo, 1] = max(base[b, 0] + dc[i, 0], 0.0)
        packed[b - lo, 2] = max(base[b, 1] + dc[i, 1], 0.0)
        packed[b - lo, 3] = max(base[b, 2] + dc[i, 2], 0.0)


@numba.njit(parallel=True, cache=True)
def _loss_grad(pixel_offsets, proj, pg, splat, base, projected, opacity, dc, target, ncam, hw, max_pairs,
               max_projected, grad, scale, nt, losses, grads):
    for t in numba.prange(nt):
        packed = np.empty((max_projected, PACKED_COLUMNS))
        # what the forward pass met, per blended pair, for the backward pass (no second gather of the same values),
        # and the transmittance in front of it (the backward reads it rather than dividing it back out)
        alphas = np.empty(max_pairs)
        gs = np.empty(max_pairs)
        bs = np.empty(max_pairs, np.int64)
        ts = np.empty(max_pairs)
        for c in range(ncam):
            if c % nt != t:  # cameras round-robin over threads, each thread its own gradient row
                continue
            lo = projected[c]
            _pack_camera(splat, base, opacity, dc, lo, projected[c + 1], packed)
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
                    b = proj[k] - lo
                    gk = np.float64(pg[k])
                    alpha = packed[b, 0] * gk
                    if alpha > ALPHA_MAX:
                        alpha = ALPHA_MAX
                    # a pair under the cut blends as alpha 0, without a branch the CPU would mispredict: T * (1 - 0)
                    # is T and r + 0 c is r (r >= 0), bit for bit, and it is not counted (m) for the backward pass
                    keep = alpha >= ALPHA_MIN
                    if not keep:
                        alpha = 0.0
                    tn = trans * (1.0 - alpha)
                    if tn < T_MIN:
                        break
                    w = alpha * trans
                    r0 += w * packed[b, 1]
                    r1 += w * packed[b, 2]
                    r2 += w * packed[b, 3]
                    alphas[m] = alpha
                    gs[m] = gk
                    bs[m] = b
                    ts[m] = trans
                    m += keep
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
                # back to front; behind = sum over later splats of c a T. T_j is the forward's own (stored), not
                # T_{j+1} / (1 - a_j) divided back from the last: no serial chain of divisions a pixel (the loop's
                # latency), and the T the forward blended with rather than one carrying every later division's
                # rounding (amplified by 1 / (1 - a) up to 100x at the 0.99 clamp; tests/test_refine_cpu.py)
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                for j in range(m - 1, -1, -1):
                    a = alphas[j]
                    b = bs[j]
                    i = splat[b + lo]
                    tj = ts[j]
                    c0 = packed[b, 1]
                    c1 = packed[b, 2]
                    c2 = packed[b, 3]
                    w = a * tj
                    # max(p, 0) > 0 exactly where p > 0: the gradient through the colour clamp
                    if c0 > 0.0:
                        grads[t, i, 1] += e0 * w
                    if c1 > 0.0:
                        grads[t, i, 2] += e1 * w
                    if c2 > 0.0:
                        grads[t, i, 3] += e2 * w
                    inv = 1.0 / (1.0 - a)
                    da = (e0 * (c0 * tj - s0 * inv) + e1 * (c1 * tj - s1 * inv) + e2 * (c2 * tj - s2 * inv))
                    if a < ALPHA_MAX:  # the 0.99 clamp: alpha < 0.99 exactly where o g < 0.99
                        grads[t, i, 0] += da * gs[j]
                    s0 += c0 * w
                    s1 += c1 * w
                    s2 += c2 * w
            losses[c] = cam_loss
