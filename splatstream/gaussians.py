"""The in-memory scene every reader produces and every writer, encoder and renderer consumes.

Attributes are kept in the parametrisation of the reference 3DGS training code (log scales, opacity
logits, SH coefficients), because that is what every file format round-trips to and what the
quantizers work on. Arrays are float32, C-contiguous, one row per splat.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SH_C0 = 0.28209479177387814
# Number of non-DC SH coefficients per colour channel for degree 0..3, and per band.
SH_REST_COEFFS = (0, 3, 8, 15)
SH_BAND_COEFFS = {1: 3, 2: 5, 3: 7}
# First rest-coefficient index of each band inside the (K, 3) rest array.
SH_BAND_START = {1: 0, 2: 3, 3: 8}


def sh_degree_for_rest_coeffs(k: int) -> int:
    """SH degree from the number of rest coefficients per channel (0, 3, 8, 15)."""
    try:
        return SH_REST_COEFFS.index(k)
    except ValueError:
        raise ValueError(f"{k} rest coefficients per channel is no SH degree (expected 0, 3, 8 or 15)") from None


def sigmoid(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # exp overflows to inf below -88: the sigmoid is then exactly 0
        return (1.0 / (1.0 + np.exp(-x.astype(np.float32)))).astype(np.float32)


def logit(p: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    p = np.clip(p.astype(np.float64), eps, 1.0 - eps)
    return np.log(p / (1.0 - p)).astype(np.float32)


@dataclass
class Gaussians:
    """A set of 3D Gaussians.

    positions:      (N, 3) world-space centres
    rotations:      (N, 4) unit quaternions, (w, x, y, z)
    log_scales:     (N, 3) natural log of the standard deviations along the local axes
    opacity_logits: (N,)   opacity before the sigmoid
    sh_dc:          (N, 3) SH band 0 (f_dc_0..2); colour = 0.5 + SH_C0 * sh_dc
    sh_rest:        (N, K, 3) SH bands 1..degree, coefficient-major, channels last (K = 0, 3, 8 or 15)
    """

    positions: np.ndarray
    rotations: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.positions)
        shapes = {
            "positions": (n, 3), "rotations": (n, 4), "log_scales": (n, 3),
            "opacity_logits": (n,), "sh_dc": (n, 3),
        }
        for name, shape in shapes.items():
            # float64 values beyond float32 become +-inf without a warning: readers screen every value afterwards
            # (io.read_gaussians), and the encoder checks its input, naming the field.
            with np.errstate(over="ignore"):
                arr = np.ascontiguousarray(getattr(self, name), dtype=np.float32)
            if arr.shape != shape:
                raise ValueError(f"Gaussians.{name}: shape {arr.shape}, expected {shape}")
            setattr(self, name, arr)
        with np.errstate(over="ignore"):
            rest = np.ascontiguousarray(self.sh_rest, dtype=np.float32)
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"Gaussians.sh_rest: shape {rest.shape}, expected ({n}, K, 3)")
        sh_degree_for_rest_coeffs(rest.shape[1])
        self.sh_rest = rest

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def sh_degree(self) -> int:
        return sh_degree_for_rest_coeffs(self.sh_rest.shape[1])

    @property
    def opacities(self) -> np.ndarray:
        return sigmoid(self.opacity_logits)

    @property
    def scales(self) -> np.ndarray:
        return np.exp(self.log_scales)

    @property
    def base_colors(self) -> np.ndarray:
        """View-independent colour (SH band 0 only), before clamping."""
        return (0.5 + SH_C0 * self.sh_dc).astype(np.float32)

    def band(self, band: int) -> np.ndarray:
        """SH coefficients of one band (1..3) as (N, 2*band+1, 3)."""
        start = SH_BAND_START[band]
        return self.sh_rest[:, start:start + SH_BAND_COEFFS[band]]

    def subset(self, index: np.ndarray) -> Gaussians:
        return Gaussians(self.positions[index], self.rotations[index], self.log_scales[index],
                         self.opacity_logits[index], self.sh_dc[index], self.sh_rest[index])

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Drop bands above `degree`, or pad missing bands with zeros."""
        k = SH_REST_COEFFS[degree]
        rest = self.sh_rest[:, :k]
        if rest.shape[1] < k:
            rest = np.concatenate([rest, np.zeros((len(self), k - rest.shape[1], 3), np.float32)], axis=1)
        return Gaussians(self.positions, self.rotations, self.log_scales, self.opacity_logits, self.sh_dc, rest)

    @staticmethod
    def concatenate(parts: list[Gaussians]) -> Gaussians:
        if not parts:
            raise ValueError("no Gaussians to concatenate")
        degree = max(p.sh_degree for p in parts)
        parts = [p.with_sh_degree(degree) for p in parts]
        return Gaussians(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                           ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest")))

    @staticmethod
    def empty(sh_degree: int = 0) -> Gaussians:
        k = SH_REST_COEFFS[sh_degree]
        return Gaussians(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)),
                         np.zeros((0, k, 3)))


def normalize_quaternions(q: np.ndarray) -> np.ndarray:
    """Unit quaternions with w >= 0 (q and -q are the same rotation). Zero-length rows stay zero."""
    q = q.astype(np.float32, copy=True)
    with np.errstate(over="ignore", invalid="ignore"):
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        # Finite components beyond 1.8e19 overflow the squares: those rows (only) are divided by their largest
        # component first (still a valid direction). Non-finite rows stay non-finite for the readers to report.
        infinite = np.flatnonzero(np.isinf(norm[:, 0]))  # few or none: the finite test on those rows only
        overflow = infinite[np.isfinite(q[infinite]).all(axis=1)]
        if len(overflow):
            q[overflow] /= np.abs(q[overflow]).max(axis=1, keepdims=True)
            norm[overflow] = np.linalg.norm(q[overflow], axis=1, keepdims=True)
        np.divide(q, norm, out=q, where=norm > 0)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0).astype(np.float32)
    return q


def rotation_columns(q: np.ndarray) -> list[np.ndarray]:
    """The nine entries of rotation_matrices(q) row by row (r[3 a + b] = R[:, a, b]), each a contiguous (N,) float64
    array: products of the entries then run on contiguous arrays (numpy's SIMD loops), not on (N, 3, 3) strides."""
    w, x, y, z = (q[:, i].astype(np.float64) for i in range(4))
    # Each product once (each was used twice): the same values, 9 multiplications a row fewer.
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)]


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices from unit (w, x, y, z) quaternions."""
    r = np.empty((len(q), 3, 3), np.float64)
    for k, column in enumerate(rotation_columns(q)):
        r[:, k // 3, k % 3] = column
    return r


def scaled_rotation_columns(q: np.ndarray, log_scales: np.ndarray) -> list[np.ndarray]:
    """The nine entries of M = R diag(exp(log_scales)) row by row, contiguous (N,) float64: the same numbers as
    rotation_matrices(q) * np.exp(log_scales.astype(np.float64))[:, None, :] (each entry R[a, b] * s[b])."""
    m = rotation_columns(q)
    s = np.exp(log_scales.astype(np.float64))
    scales = [np.ascontiguousarray(s[:, b]) for b in range(3)]
    for k in range(9):
        m[k] *= scales[k % 3]
    return m


def covariances(g: Gaussians) -> np.ndarray:
    """(N, 3, 3) world-space covariance R S S^T R^T, float64."""
    r = rotation_matrices(g.rotations)
    s = np.exp(g.log_scales.astype(np.float64))
    m = r * s[:, None, :]
    return m @ np.transpose(m, (0, 2, 1))
