"""The value domain of a scene (format_spec/format.md 4.8): the values an encoder accepts and a reader may meet.

Every stored quantity must decode, and be drawn, without leaving float32: positions within +-1e18 (differences
and squared distances stay finite in f32), log scales within [-80, 40] (exp(2 * 40) is a finite f32 variance;
exp(-80) is far below any visible size), SH coefficients within float16's +-65504 (their per-chunk ranges are
f16, so a larger value would make the stored range infinite), finite opacity logits, non-zero quaternions.
Readers of foreign files screen what they read against it (io.read_gaussians), the encoder checks its input
(plan.py) and the scene readers check every range section (container.py), so no value outside it is ever
written or decoded.
"""
from __future__ import annotations

import numpy as np

from ..gaussians import Gaussians
from ..progress import some_of

MAX_ABS_POSITION = 1e18
MIN_LOG_SCALE = -80.0
MAX_LOG_SCALE = 40.0
MAX_ABS_SH = 65504.0  # the largest finite float16
BLOCK_ROWS = 1 << 18  # rows checked at a time (bounds the temporaries on scenes of millions of splats)


def plane_limits(plane: str) -> tuple[float, float]:
    """[lo, hi] the values of a ranged plane (format.md 4.4) lie in: the domain of its quantity."""
    return {"position": (-MAX_ABS_POSITION, MAX_ABS_POSITION),
            "scale": (MIN_LOG_SCALE, MAX_LOG_SCALE)}.get(plane, (-MAX_ABS_SH, MAX_ABS_SH))


def _within(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Rows of (N, ...) values whose every entry is finite and in [lo, hi] (NaN compares False)."""
    flat = values.reshape(len(values), int(np.prod(values.shape[1:], dtype=np.int64)))
    ok = np.empty(len(values), bool)
    for start in range(0, len(values), BLOCK_ROWS):
        block = flat[start:start + BLOCK_ROWS]
        ok[start:start + BLOCK_ROWS] = ((block >= lo) & (block <= hi)).all(axis=1)
    return ok


def domain_violations(g: Gaussians) -> list[tuple[str, np.ndarray]]:
    """[(what is wrong, (N,) mask of the splats it applies to)] for every limit some splat breaks; [] if none."""
    checks = [
        (f"position (x, y, z) not finite or beyond +-{MAX_ABS_POSITION:g}",
         ~_within(g.positions, -MAX_ABS_POSITION, MAX_ABS_POSITION)),
        (f"log scale (scale_0..2) not finite or outside [{MIN_LOG_SCALE:g}, {MAX_LOG_SCALE:g}]",
         ~_within(g.log_scales, MIN_LOG_SCALE, MAX_LOG_SCALE)),
        ("opacity logit not finite", ~np.isfinite(g.opacity_logits)),
        (f"SH0 (f_dc_0..2) not finite or beyond +-{MAX_ABS_SH:g}", ~_within(g.sh_dc, -MAX_ABS_SH, MAX_ABS_SH)),
        ("rotation not finite or zero-length",
         ~np.isfinite(g.rotations).all(axis=1) | ~(g.rotations != 0).any(axis=1)),
    ]
    if g.sh_rest.shape[1]:
        checks.append((f"SH bands 1-{g.sh_degree} (f_rest_*) not finite or beyond +-{MAX_ABS_SH:g}",
                       ~_within(g.sh_rest, -MAX_ABS_SH, MAX_ABS_SH)))
    return [(what, mask) for what, mask in checks if mask.any()]


def describe_violations(violations: list[tuple[str, np.ndarray]], n: int) -> tuple[np.ndarray, str]:
    """(mask of every offending splat, 'K of N splats ... (field: count, ...)')."""
    bad = np.zeros(n, bool)
    for _, mask in violations:
        bad |= mask
    detail = ", ".join(f"{what}: {int(mask.sum())}" for what, mask in violations)
    first = int(np.argmax(bad))
    return bad, (f"{some_of(int(bad.sum()), n, 'splats', ('has', 'have'))} values outside what a scene can hold "
                 f"({detail}; first at splat {first}; format_spec/format.md 4.8)")
