"""Reference numpy rasterizer of the 3DGS forward pass.

It follows the original CUDA rasterizer (graphdeco-inria/diff-gaussian-rasterization, forward.cu) step by step:

preprocess (per splat)
  * cull when the view depth t.z <= camera.near (the reference: 0.2);
  * Sigma = R S S^T R^T; EWA: Sigma' = J W Sigma W^T J^T with t.x/t.z and t.y/t.z clamped to +-1.3 tan(fov/2);
    0.3 px^2 added to the diagonal (low-pass); culled when det == 0; conic = inverse of Sigma';
  * radius = ceil(3 sqrt(lambda_max)), lambda_max = mid + sqrt(max(0.1, mid^2 - det));
  * mean in pixel-index coordinates: ((ndc + 1) * size - 1) / 2, i.e. pixel (col, row) sits at (col, row);
  * the splat touches the 16x16 tiles of its radius box (getRect, integer truncation), culled if none;
  * colour = max(SH(normalize(mean - eye)) + 0.5, 0).
render (per tile, splats in depth order, ties by splat index)
  * power = -0.5 (a dx^2 + c dy^2) - b dx dy; skip if power > 0;
  * alpha = min(0.99, opacity exp(power)); skip if alpha < 1/255;
  * stop (this splat excluded) once T (1 - alpha) < 1e-4; C += colour alpha T; T *= 1 - alpha;
  * pixel = C + T background.

Differences from the CUDA code: float64 arithmetic instead of float32, and the 1e-7 the reference adds to w in the
projection is left out. Work is vectorised per tile over batches of splats (batch x 256 pixels).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .gaussians import Gaussians, covariances
from .sh import eval_sh, view_directions

TILE = 16
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
LOW_PASS = 0.3
FRUSTUM_CLAMP = 1.3
RADIUS_SIGMAS = 3.0


@dataclass
class Projected:
    """Splats that survived preprocessing, in depth order (front first)."""

    index: np.ndarray      # (M,) index into the input Gaussians
    xy: np.ndarray         # (M, 2) mean in pixel-index coordinates (pixel (col, row) centre = (col, row))
    depth: np.ndarray      # (M,) view depth
    conic: np.ndarray      # (M, 3) inverse 2D covariance (a, b, c)
    opacity: np.ndarray    # (M,)
    radius: np.ndarray     # (M,) int, pixels
    rect_min: np.ndarray   # (M, 2) int, first tile (x, y)
    rect_max: np.ndarray   # (M, 2) int, one past the last tile (x, y)
    color: np.ndarray      # (M, 3) float64


def cov2d(means: np.ndarray, cov3d: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """EWA screen-space covariance (N, 3) = (xx, xy, yy) with the low-pass, and view-space means (N, 3)."""
    m = camera.world_to_camera_cv()
    w = m[:3, :3]
    t = means @ w.T + m[:3, 3]
    fx, fy = camera.focal
    limx = FRUSTUM_CLAMP * camera.tan_half_fov_x
    limy = FRUSTUM_CLAMP * camera.tan_half_fov_y
    tz = t[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.clip(t[:, 0] / tz, -limx, limx) * tz
        ty = np.clip(t[:, 1] / tz, -limy, limy) * tz
        j = np.zeros((len(t), 2, 3))
        j[:, 0, 0] = fx / tz
        j[:, 0, 2] = -fx * tx / (tz * tz)
        j[:, 1, 1] = fy / tz
        j[:, 1, 2] = -fy * ty / (tz * tz)
    tm = j @ w
    c = tm @ cov3d @ np.transpose(tm, (0, 2, 1))
    out = np.stack([c[:, 0, 0] + LOW_PASS, c[:, 0, 1], c[:, 1, 1] + LOW_PASS], axis=1)
    return out, t


def preprocess(g: Gaussians, camera: Camera, sh_degree: int | None = None) -> Projected:
    """Project, cull and colour the splats; returns the survivors sorted by depth (stable)."""
    width, height = camera.width, camera.height
    grid_x = (width + TILE - 1) // TILE
    grid_y = (height + TILE - 1) // TILE
    pos = g.positions.astype(np.float64)
    m = camera.world_to_camera_cv()
    depth_all = pos @ m[2, :3] + m[2, 3]
    keep = np.nonzero(depth_all > camera.near)[0]
    pos = pos[keep]
    cov, t = cov2d(pos, covariances(g.subset(keep)), camera)
    a, b, c = cov[:, 0], cov[:, 1], cov[:, 2]
    det = a * c - b * b
    ok = (det != 0) & np.isfinite(det)
    with np.errstate(divide="ignore", invalid="ignore"):
        det_inv = 1.0 / det
        conic = np.stack([c * det_inv, -b * det_inv, a * det_inv], axis=1)
        mid = 0.5 * (a + c)
        lam1 = mid + np.sqrt(np.maximum(0.1, mid * mid - det))
        lam2 = mid - np.sqrt(np.maximum(0.1, mid * mid - det))
        radius = np.ceil(RADIUS_SIGMAS * np.sqrt(np.maximum(lam1, lam2)))
        fx, fy = camera.focal
        # ndc2Pix(ndc, S) = ((ndc + 1) S - 1) / 2 with ndc = t / (t.z tan_half_fov)
        px = ((t[:, 0] / (t[:, 2] * camera.tan_half_fov_x) + 1.0) * width - 1.0) * 0.5
        py = ((t[:, 1] / (t[:, 2] * camera.tan_half_fov_y) + 1.0) * height - 1.0) * 0.5
    ok &= np.isfinite(radius) & np.isfinite(px) & np.isfinite(py) & np.all(np.isfinite(conic), axis=1)
    radius = np.where(ok, radius, 0.0)
    px = np.where(ok, px, 0.0)
    py = np.where(ok, py, 0.0)
    # getRect: (int) truncates towards zero, then clamps to [0, grid]
    big = 1e9
    rx0 = np.clip(np.trunc(np.clip((px - radius) / TILE, -big, big)), 0, grid_x).astype(np.int64)
    ry0 = np.clip(np.trunc(np.clip((py - radius) / TILE, -big, big)), 0, grid_y).astype(np.int64)
    rx1 = np.clip(np.trunc(np.clip((px + radius + TILE - 1) / TILE, -big, big)), 0, grid_x).astype(np.int64)
    ry1 = np.clip(np.trunc(np.clip((py + radius + TILE - 1) / TILE, -big, big)), 0, grid_y).astype(np.int64)
    ok &= (radius > 0) & ((rx1 - rx0) * (ry1 - ry0) > 0)
    sel = np.nonzero(ok)[0]
    order = sel[np.argsort(t[sel, 2], kind="stable")]
    idx = keep[order]
    eye = np.asarray(camera.eye)
    colors = eval_sh(g.sh_dc[idx], g.sh_rest[idx], view_directions(g.positions[idx], eye), sh_degree)
    return Projected(
        index=idx,
        xy=np.stack([px[order], py[order]], axis=1),
        depth=t[order, 2],
        conic=conic[order],
        opacity=g.opacities[idx].astype(np.float64),
        radius=radius[order].astype(np.int64),
        rect_min=np.stack([rx0[order], ry0[order]], axis=1),
        rect_max=np.stack([rx1[order], ry1[order]], axis=1),
        color=colors,
    )


def tile_lists(p: Projected, grid_x: int, grid_y: int) -> tuple[np.ndarray, np.ndarray]:
    """(splat ids in tile-major, depth-minor order, start offset of each tile (grid_x*grid_y + 1,))."""
    w = p.rect_max[:, 0] - p.rect_min[:, 0]
    h = p.rect_max[:, 1] - p.rect_min[:, 1]
    counts = w * h
    total = int(counts.sum())
    ntiles = grid_x * grid_y
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(ntiles + 1, np.int64)
    splat = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    local = np.arange(total) - starts[splat]
    tx = p.rect_min[splat, 0] + local % w[splat]
    ty = p.rect_min[splat, 1] + local // w[splat]
    tile = ty * grid_x + tx
    # splats are already in depth order: stable keeps it per tile. A stable order is unique, so a 16-bit key
    # (numpy's radix sort, linear) gives the same order as the int64 one (a merge sort) where the tiles fit
    key = tile.astype(np.int16) if ntiles <= np.iinfo(np.int16).max else tile
    order = np.argsort(key, kind="stable")
    offsets = np.zeros(ntiles + 1, np.int64)
    np.cumsum(np.bincount(tile, minlength=ntiles), out=offsets[1:])
    return splat[order], offsets


def rasterize(p: Projected, width: int, height: int, background=(0.0, 0.0, 0.0),
              max_batch: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Blend projected splats; returns (image (H, W, 3) float64, final transmittance (H, W))."""
    grid_x = (width + TILE - 1) // TILE
    grid_y = (height + TILE - 1) // TILE
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    ids, offsets = tile_lists(p, grid_x, grid_y)
    img = np.zeros((grid_y * TILE, grid_x * TILE, 3))
    trans = np.ones((grid_y * TILE, grid_x * TILE))
    ly, lx = np.divmod(np.arange(TILE * TILE), TILE)
    ca, cb, cc = p.conic[:, 0], p.conic[:, 1], p.conic[:, 2]
    for tyi in range(grid_y):
        for txi in range(grid_x):
            k = tyi * grid_x + txi
            lst = ids[offsets[k]:offsets[k + 1]]
            if len(lst) == 0:
                continue
            pxs = (txi * TILE + lx).astype(np.float64)
            pys = (tyi * TILE + ly).astype(np.float64)
            t_cur = np.ones(TILE * TILE)
            col = np.zeros((TILE * TILE, 3))
            done = np.zeros(TILE * TILE, bool)
            pos, batch = 0, 16
            while pos < len(lst):
                s = lst[pos:pos + batch]
                pos += batch
                batch = min(batch * 2, max_batch)
                # pixel-major (256, batch) arrays: the running product runs along contiguous memory
                dx = p.xy[s, 0][None, :] - pxs[:, None]
                dy = p.xy[s, 1][None, :] - pys[:, None]
                power = -0.5 * (ca[None, s] * dx * dx + cc[None, s] * dy * dy) - cb[None, s] * dx * dy
                alpha = np.minimum(ALPHA_MAX, p.opacity[None, s] * np.exp(np.minimum(power, 0.0)))
                alpha[(power > 0) | (alpha < ALPHA_MIN)] = 0.0
                alpha[done] = 0.0
                tcum = np.empty((TILE * TILE, len(s) + 1))
                tcum[:, 0] = t_cur
                np.subtract(1.0, alpha, out=tcum[:, 1:])
                np.cumprod(tcum, axis=1, out=tcum)
                valid = tcum[:, 1:] >= T_MIN  # a prefix per pixel: T never grows
                n_valid = valid.sum(axis=1)
                weights = np.where(valid, alpha * tcum[:, :-1], 0.0)
                col += weights @ p.color[s]
                t_cur = tcum[np.arange(TILE * TILE), n_valid]
                done |= n_valid < len(s)
                if done.all():
                    break
            ys = slice(tyi * TILE, (tyi + 1) * TILE)
            xs = slice(txi * TILE, (txi + 1) * TILE)
            img[ys, xs] = col.reshape(TILE, TILE, 3)
            trans[ys, xs] = t_cur.reshape(TILE, TILE)
    img = img[:height, :width] + trans[:height, :width, None] * bg
    return img, trans[:height, :width]


def render(g: Gaussians, camera: Camera, sh_degree: int | None = None,
           background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Render `g` from `camera`: (height, width, 3) float32 linear colour, not clamped above."""
    return render_with_alpha(g, camera, sh_degree, background)[0]


def render_with_alpha(g: Gaussians, camera: Camera, sh_degree: int | None = None,
                      background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) float32, coverage 1 - T (H, W) float32)."""
    if len(g) == 0:
        img = np.broadcast_to(np.asarray(background, np.float32), (camera.height, camera.width, 3)).copy()
        return img, np.zeros((camera.height, camera.width), np.float32)
    p = preprocess(g, camera, sh_degree)
    img, trans = rasterize(p, camera.width, camera.height, background)
    return img.astype(np.float32), (1.0 - trans).astype(np.float32)
