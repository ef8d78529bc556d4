"""Axis conventions of foreign formats, and the 180-degree turns between them.

Our model (`Gaussians`) keeps the axes of the 3DGS PLY: x right, y down, z forward (RDF). Other formats store
other axes, always related to RDF by a 180-degree rotation about one coordinate axis (a proper rotation, so no
handedness change):

* SPZ stores RUB (x right, y up, z back): 180 degrees about x, signs (+1, -1, -1).
* glTF (KHR_gaussian_splatting) is LUF (x left, y up, z forward): 180 degrees about z, signs (-1, -1, +1).
  This is also what splat-transform's .glb writer produces from a PLY (its PLY -> engine transform).

Such a turn D = diag(signs) maps a position p to D p, a rotation R to D R D (for a quaternion (w, v):
(w, D v), since det D = +1), leaves scales and opacity alone, and multiplies each SH coefficient by the parity of
its basis function under d -> D d (each basis polynomial is odd or even in every coordinate).
"""
from __future__ import annotations

import numpy as np

from .gaussians import Gaussians
from .sh import sh_basis

RDF_TO_RUB = (1.0, -1.0, -1.0)  # SPZ
RDF_TO_LUF = (-1.0, -1.0, 1.0)  # glTF


def sh_parity(signs: tuple[float, float, float], degree: int = 3) -> np.ndarray:
    """(K,) sign of each rest coefficient (bands 1..degree) under d -> diag(signs) d."""
    if sorted(abs(s) for s in signs) != [1.0, 1.0, 1.0] or np.prod(signs) != 1.0:
        raise ValueError(f"axis signs {signs} are not a proper 180-degree turn (expected +-1 with product +1)")
    # Every basis polynomial is a monomial mix of one parity per coordinate, so one generic direction decides.
    d = np.array([[0.36, 0.48, 0.8]])
    ratio = sh_basis(d * np.asarray(signs), degree)[0, 1:] / sh_basis(d, degree)[0, 1:]
    return np.sign(ratio).astype(np.float32)


def turn(g: Gaussians, signs: tuple[float, float, float]) -> Gaussians:
    """`g` with every attribute expressed in the axes diag(signs) applied to its own (an involution)."""
    s = np.asarray(signs, np.float32)
    rotations = g.rotations.copy()
    rotations[:, 1:] *= s
    k = g.sh_rest.shape[1]
    parity = sh_parity(signs, g.sh_degree)[:k] if k else np.zeros(0, np.float32)
    return Gaussians(g.positions * s, rotations, g.log_scales, g.opacity_logits, g.sh_dc,
                     g.sh_rest * parity[None, :, None])


def turned_against(g: Gaussians, reference: Gaussians, signs: tuple[float, float, float]) -> bool:
    """Whether `g` (another tool's output of the scene in `reference`) is that scene turned by diag(signs): its
    positions' 5th, 50th and 95th percentiles per axis lie much closer to the turned reference's than to the
    reference's. Used to catch an SPZ written without its RUB axis turn (splat-transform 3.x), which a reader that
    follows the format returns turned 180 degrees about x."""
    if len(g) < 16 or len(reference) < 16:
        return False
    q = [5.0, 50.0, 95.0]

    def marks(p: np.ndarray) -> np.ndarray:
        p = p[np.isfinite(p).all(axis=1)].astype(np.float64)
        return np.percentile(p, q, axis=0) if len(p) else np.zeros((3, 3))

    ref = marks(reference.positions)
    extent = np.maximum(ref[2] - ref[0], 1e-12)
    mine = marks(g.positions)
    straight = float(np.abs((mine - ref) / extent).sum())
    flipped = marks(reference.positions * np.asarray(signs, np.float32))
    turned = float(np.abs((mine - flipped) / extent).sum())
    return straight > 0.3 and turned < 0.25 * straight
