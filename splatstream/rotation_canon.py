"""Canonical rotations: of the 24 (rotation, scales) pairs that give a splat the same covariance, the one whose
rotation is closest to the identity (issue 32, branch rot32).

A Gaussian's covariance R diag(s)^2 R^T does not change when R's columns are permuted together with the scales and
their signs flipped, as long as R stays a rotation: R -> R P, s -> P^T s for the 24 signed permutation matrices P of
determinant 1 (the rotations of a cube; as quaternions q -> q * g for g in the 24 unit quaternions of CUBE_GROUP).
Trained scenes store whichever of the 24 their optimiser happened on, so their rotations spread over the whole
sphere of quaternions. `canonical_gauge` picks, per splat, the one with the largest |w| (the rotation by the smallest
angle): then |x|, |y|, |z| <= tan(pi/8) w (w >= 0.854), so a smallest-three texel
always stores w as its largest component (a constant index) and x, y, z in the middle of their range, which zstd
codes in fewer bits: the same covariances, no change a decoder sees (format.md 4.5 "Rotations").

Pure numpy, exact up to the float32 rounding of the returned quaternion: the covariance changes by at most 1e-6 of
the largest scale squared (tests/test_rotation_canon.py checks it splat by splat).
"""
from __future__ import annotations

import itertools

import numpy as np

from .gaussians import normalize_quaternions


def _cube_group() -> np.ndarray:
    """(24, 4) float64 unit quaternions (w, x, y, z), w >= 0 where w != 0: the rotations of the cube. 1, i, j, k;
    (+-1 +-i +-j +-k) / 2; and (+-a +-b) / sqrt(2) for two of 1, i, j, k, each once up to sign."""
    out = []
    for support in range(1, 5):
        if support == 3:
            continue  # no unit quaternion of three equal-magnitude components is a cube rotation
        mag = 1.0 / np.sqrt(support)
        for where in itertools.combinations(range(4), support):
            for signs in itertools.product((1.0, -1.0), repeat=support - 1):
                q = np.zeros(4)
                q[list(where)] = mag * np.array((1.0, *signs))  # the first non-zero component positive: one of +-q
                out.append(q)
    return np.array(out)


CUBE_GROUP = _cube_group()
# The subgroup of half turns about the axes, 1, i, j, k: q g permutes q's components and flips signs, and the scales
# stay as they are, so a rotation on a smallest-three grid (another tool's 8- or 10-bit quaternions) stays on it.
HALF_TURNS = np.flatnonzero(np.count_nonzero(CUBE_GROUP, axis=1) == 1)
GAUGES = ("cube", "half-turns")
# For each element g: the permutation the scales take, s'[j] = s[SCALE_PERMUTATION[g, j]] (R(g)'s column j is
# +-e_{SCALE_PERMUTATION[g, j]}).
SCALE_PERMUTATION = np.argmax(np.abs(np.stack([
    np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
              [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
              [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]) for w, x, y, z in CUBE_GROUP])),
    axis=1)


def canonical_gauge(rotations: np.ndarray, log_scales: np.ndarray, gauge: str = "cube"
                    ) -> tuple[np.ndarray, np.ndarray]:
    """((N, 4) float32 unit quaternions (w, x, y, z), (N, 3) log scales of the same dtype as `log_scales`): for each
    splat the (q g, its scales permuted) of the element g with the largest |w| (the first such element on a tie),
    which gives the same covariance: of CUBE_GROUP (`cube`: w >= |x|, |y|, |z| / tan(pi/8)) or of HALF_TURNS
    (`half-turns`: w the largest component, the scales unchanged, the components the input's permuted and
    negated). Zero quaternions stay zero, their scales as they are."""
    if gauge not in GAUGES:
        raise ValueError(f"gauge {gauge!r} is not one of {GAUGES}")
    group = CUBE_GROUP if gauge == "cube" else CUBE_GROUP[HALF_TURNS]
    permutation = SCALE_PERMUTATION if gauge == "cube" else SCALE_PERMUTATION[HALF_TURNS]
    q = np.asarray(rotations, np.float64)
    ls = np.asarray(log_scales)
    if len(q) == 0:
        return normalize_quaternions(q), ls.copy()
    w, x, y, z = (q[:, i] for i in range(4))
    # w of q * g for every g: the one component to compare; the whole product only for the chosen g.
    gw, gx, gy, gz = (group[:, i][:, None] for i in range(4))
    best = np.argmax(np.abs(w * gw - x * gx - y * gy - z * gz), axis=0)
    g = group[best]
    a, b, c, d = (g[:, i] for i in range(4))
    product = np.stack([w * a - x * b - y * c - z * d, w * b + x * a + y * d - z * c,
                        w * c - x * d + y * a + z * b, w * d + x * c - y * b + z * a], axis=1)
    return normalize_quaternions(product), np.take_along_axis(ls, permutation[best], axis=1)
