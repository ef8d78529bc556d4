"""Which way is up in a scene (format_spec/foreign_formats.md, "Up direction").

Every reader returns splats in the axes of the reference 3DGS training code (COLMAP: x right, y down, z forward),
so the common case is up = -y. Scenes made in z-up tools (Blender-style synthetic captures, z-up tilers) come in
the same file formats with up = +z. `detect_up` tells them apart by the surfaces the splats lie on: flat splats
on horizontal surfaces (ground, table tops) face up, so when flat splats facing +-z clearly dominate and the scene
is not itself a thin sheet facing the camera's z axis (a card or a wall seen from the front), the scene is z-up.
The choice and its reason are reported; `--up` overrides it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gaussians import Gaussians, rotation_matrices

Y_DOWN_UP = (0.0, -1.0, 0.0)  # the reference trainer's (COLMAP) convention: y points down
Z_UP = (0.0, 0.0, 1.0)
SAMPLE = 200_000
# A splat is flat when its middle axis is at least e^FLAT_LOG_RATIO times its smallest one.
FLAT_LOG_RATIO = 1.0
# Its normal counts for an axis when within ~25 degrees of it.
ALIGNED_COS = 0.9
# z-up when at least this share of flat splats (opacity-weighted) face +-z, at least Z_DOMINANCE times the share
# facing either other axis, and the scene's z extent is at least MIN_Z_EXTENT of its largest extent. Measured on the
# real scenes (shares x, y, z; z extent / largest): donut (z-up) 0.07 0.07 0.28, 0.42; lod tile (z-up) 0.01 0.01
# 0.50, 0.40; fruit_drops, a card facing the camera (y-down) 0.04 0.03 0.60, 0.045; winter fountain (y-down)
# 0.10 0.21 0.11; guitar (y-down) 0.27 0.18 0.10; biker (y-down) 0.14 0.08 0.17.
MIN_Z_SHARE = 0.2
Z_DOMINANCE = 2.0
MIN_Z_EXTENT = 0.25


@dataclass(frozen=True)
class UpChoice:
    up: tuple[float, float, float]
    reason: str


def flat_normal_shares(g: Gaussians) -> np.ndarray:
    """(3,) opacity-weighted share of flat splats whose normal (shortest axis) lies along x, y and z."""
    if len(g) > SAMPLE:
        g = g.subset(np.linspace(0, len(g) - 1, SAMPLE).astype(np.int64))
    s = g.log_scales.astype(np.float64)
    order = np.argsort(s, axis=1)
    smallest = order[:, 0]
    flat = (np.take_along_axis(s, order[:, 1:2], 1)[:, 0] - s[np.arange(len(g)), smallest]) > FLAT_LOG_RATIO
    normals = rotation_matrices(g.rotations)[np.arange(len(g)), :, smallest]
    with np.errstate(over="ignore"):  # a logit below -709 is alpha 0 (exp overflows to inf)
        weight = flat / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    total = weight.sum()
    if total <= 0:
        return np.zeros(3)
    return np.array([(weight * (np.abs(normals[:, a]) > ALIGNED_COS)).sum() / total for a in range(3)])


def detect_up(g: Gaussians, positions: np.ndarray | None = None) -> UpChoice:
    """The up vector of splats in the 3DGS (COLMAP) axes: -y, unless the scene is recognisably z-up.

    `positions`: the centres whose 5-95 % extent is measured (default all of `g`'s; the encoder passes its
    deterministic sample of the scene, encode/sample.py, so that a partitioned encode decides the same)."""
    if len(g) == 0:
        return UpChoice(Y_DOWN_UP, "the 3DGS convention (y down)")
    shares = flat_normal_shares(g)
    p = g.positions if positions is None else positions
    p = p[np.isfinite(p).all(axis=1)]
    extent = np.percentile(p, 95, axis=0) - np.percentile(p, 5, axis=0) if len(p) else np.ones(3)
    z_thick = extent[2] >= MIN_Z_EXTENT * max(float(extent.max()), 1e-30)
    if shares[2] >= MIN_Z_SHARE and shares[2] >= Z_DOMINANCE * max(shares[0], shares[1]) and z_thick:
        return UpChoice(Z_UP, f"z up: {shares[2]:.0%} of flat splats face +-z (horizontal surfaces)")
    layer = ground_layer_axis(g, extent)
    if layer == 2:
        return UpChoice(Z_UP, "z up: the splats lie spread over a ground plane in x and y (z extent "
                              f"{extent[2] / min(extent[0], extent[1]):.0%} of theirs)")
    if layer == 1:
        return UpChoice(Y_DOWN_UP, "y down: the splats lie spread over a ground plane in x and z (the 3DGS "
                                   "convention)")
    return UpChoice(Y_DOWN_UP, "the 3DGS convention (y down), assumed: neither the file nor the scene's shape "
                               "says otherwise")


# A scene spread over a ground plane (a city block, objects on a field): one axis' extent is at most LAYER_THIN of
# both others', and yet at least LAYER_MIN_SIZES median splat sizes, so that it is not a single sheet of splats (a
# card or a wall seen from the front: fruit_drops, 3 sizes thick). Measured (thin axis' share of the smaller other
# extent; its thickness in median splat sizes): make_scene.py's 1M scene (z up) 0.08, 116; fruit_drops 0.09, 3;
# every other real scene 0.4 or more.
LAYER_THIN = 0.25
LAYER_MIN_SIZES = 20.0


def ground_layer_axis(g: Gaussians, extent: np.ndarray) -> int | None:
    """The axis (0, 1, 2) normal to a ground plane the scene lies spread over, or None (see LAYER_THIN)."""
    if len(g) < 16 or not np.all(np.isfinite(extent)) or extent.max() <= 0:
        return None
    thin = int(np.argmin(extent))
    others = [extent[a] for a in range(3) if a != thin]
    if extent[thin] > LAYER_THIN * min(others):
        return None
    sizes = np.exp(g.log_scales.astype(np.float64)).max(axis=1)
    size = float(np.median(sizes[np.isfinite(sizes)])) if np.isfinite(sizes).any() else 0.0
    if not size > 0 or extent[thin] < LAYER_MIN_SIZES * size:
        return None
    return thin


# For a y-down scene the default view is along the capture's z axis (camera.py). Which end: captures put large,
# soft splats (background, haze) behind what the cameras saw, so the eye goes on the other side when their mean z
# differs from the small splats' by at least this fraction of the z extent (fruit_drops: 1.18: its label reads
# from +z; the winter fountain, guitar and biker: under 0.07, seen from -z, the convention's front).
BACKGROUND_SIDE_MIN = 0.25


def view_side(g: Gaussians, up: tuple[float, float, float]) -> float:
    """+1 to look at a y-down scene from +z, -1 from -z (the default); 0 when `up` is not along y."""
    if abs(up[1]) < 0.9 or len(g) < 16:
        return 0.0
    if len(g) > SAMPLE:
        g = g.subset(np.linspace(0, len(g) - 1, SAMPLE).astype(np.int64))
    size = np.exp(g.log_scales.astype(np.float64)).max(axis=1)
    with np.errstate(over="ignore"):
        weight = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    z = g.positions[:, 2].astype(np.float64)
    ok = np.isfinite(z) & np.isfinite(size)
    z, size, weight = z[ok], size[ok], weight[ok]
    extent = np.percentile(z, 95) - np.percentile(z, 5)
    big = size > np.percentile(size, 90)
    if not big.any() or big.all() or extent <= 0 or weight[big].sum() <= 0 or weight[~big].sum() <= 0:
        return -1.0
    shift = (np.average(z[big], weights=weight[big]) - np.average(z[~big], weights=weight[~big])) / extent
    return 1.0 if shift <= -BACKGROUND_SIDE_MIN else -1.0
