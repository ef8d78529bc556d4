"""Spherical-harmonics colour, as the reference 3DGS rasterizer evaluates it (computeColorFromSH).

The constants and the basis below are the single source of truth: the GL shader generator reads
`SH_C0..SH_C3` and `SH_BASIS` (one (constant name, index, GLSL/Python expression) row per coefficient) instead of
copying numbers. Coefficient k of the basis multiplies SH coefficient k (k = 0 is the DC term, k = 1.. are the
rows of `Gaussians.sh_rest`). Directions are unit vectors dir = normalize(position - eye) with components x, y, z.

colour = max(sum_k basis_k(dir) * sh_k + 0.5, 0)   (clamped at 0 only, as the reference does)
"""
from __future__ import annotations

import os
import warnings

import numpy as np

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

# (sign * constant, polynomial in x, y, z) per coefficient, in the reference's order. Valid as GLSL and Python.
SH_BASIS: tuple[tuple[str, str], ...] = (
    ("SH_C0", "1.0"),
    ("-SH_C1", "y"),
    ("SH_C1", "z"),
    ("-SH_C1", "x"),
    ("SH_C2[0]", "x * y"),
    ("SH_C2[1]", "y * z"),
    ("SH_C2[2]", "(2.0 * z * z - x * x - y * y)"),
    ("SH_C2[3]", "x * z"),
    ("SH_C2[4]", "(x * x - y * y)"),
    ("SH_C3[0]", "y * (3.0 * x * x - y * y)"),
    ("SH_C3[1]", "x * y * z"),
    ("SH_C3[2]", "y * (4.0 * z * z - x * x - y * y)"),
    ("SH_C3[3]", "z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y)"),
    ("SH_C3[4]", "x * (4.0 * z * z - x * x - y * y)"),
    ("SH_C3[5]", "z * (x * x - y * y)"),
    ("SH_C3[6]", "x * (x * x - 3.0 * y * y)"),
)
SH_COEFFS_FOR_DEGREE = (1, 4, 9, 16)
COLOR_OFFSET = 0.5


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """(N, (degree+1)^2) basis values for unit directions (N, 3), float64."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = np.empty((len(d), SH_COEFFS_FOR_DEGREE[degree]), np.float64)
    out[:, 0] = SH_C0
    if degree > 0:
        out[:, 1] = -SH_C1 * y
        out[:, 2] = SH_C1 * z
        out[:, 3] = -SH_C1 * x
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out[:, 4] = SH_C2[0] * xy
        out[:, 5] = SH_C2[1] * yz
        out[:, 6] = SH_C2[2] * (2.0 * zz - xx - yy)
        out[:, 7] = SH_C2[3] * xz
        out[:, 8] = SH_C2[4] * (xx - yy)
    if degree > 2:
        out[:, 9] = SH_C3[0] * y * (3.0 * xx - yy)
        out[:, 10] = SH_C3[1] * xy * z
        out[:, 11] = SH_C3[2] * y * (4.0 * zz - xx - yy)
        out[:, 12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        out[:, 13] = SH_C3[4] * x * (4.0 * zz - xx - yy)
        out[:, 14] = SH_C3[5] * z * (xx - yy)
        out[:, 15] = SH_C3[6] * x * (xx - 3.0 * yy)
    return out


def view_directions(positions: np.ndarray, eye: np.ndarray | tuple) -> np.ndarray:
    """normalize(position - eye), float64; a splat exactly at the eye gets a zero direction."""
    d = np.asarray(positions, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, n, out=np.zeros_like(d), where=n > 0)


def eval_sh(sh_dc: np.ndarray, sh_rest: np.ndarray, dirs: np.ndarray, degree: int | None = None,
            clamp: bool = True) -> np.ndarray:
    """Colour (N, 3) float64 from DC (N, 3) and rest (N, K, 3) coefficients for unit directions (N, 3).

    `degree` (default: the degree the rest coefficients hold) may only lower the degree. Adds 0.5 and clamps at 0
    (no upper clamp), as the reference does.
    """
    if 1 + sh_rest.shape[1] not in SH_COEFFS_FOR_DEGREE:
        raise ValueError(f"sh_rest holds {sh_rest.shape[1]} coefficients per channel; expected 0, 3, 8 or 15")
    have = SH_COEFFS_FOR_DEGREE.index(1 + sh_rest.shape[1])
    degree = have if degree is None else min(int(degree), have)
    basis = sh_basis(dirs, degree)
    coeffs = np.concatenate([np.asarray(sh_dc, np.float64)[:, None, :],
                             np.asarray(sh_rest[:, :SH_COEFFS_FOR_DEGREE[degree] - 1], np.float64)], axis=1)
    rgb = np.einsum("nk,nkc->nc", basis, coeffs) + COLOR_OFFSET
    return np.maximum(rgb, 0.0) if clamp else rgb


def splat_colors(g, eye, degree: int | None = None) -> np.ndarray:
    """Colour of every splat of `g` (a Gaussians) seen from `eye`, (N, 3) float64, clamped at 0."""
    return eval_sh(g.sh_dc, g.sh_rest, view_directions(g.positions, eye), degree)


def warn_sh_degree_above(asked: int | None, scene_degree: int, where: str | os.PathLike,
                         asked_as: str | None = None) -> None:
    """Warn (one line: the CLI shows a warning as 'splatstream: warning: ...') that more SH bands were asked for
    than the scene has, e.g. '--sh-degree 3: out/playbot has SH degree 2; 2 is used'. The scene's bands are used,
    not refused: a script that asks every scene for degree 3 keeps working (decode, view, render, the exports,
    encode and eval's variants took it without a word: newuser64). `asked_as`: how it was asked for (default
    '--sh-degree N')."""
    if asked is not None and asked > scene_degree:
        said = asked_as or f"--sh-degree {asked}"
        warnings.warn(f"{said}: {os.fspath(where)} has SH degree {scene_degree}; {scene_degree} is used", stacklevel=2)
