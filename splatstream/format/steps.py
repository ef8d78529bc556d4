"""Tile-wide quantisation steps: a coarser grid than the texel format's, written by widening chunk ranges
(format_spec/format.md 4.3.1). Encoder only: a reader decodes such a plane like any other.

A ranged plane quantises chunk c's component k on `levels` steps of (max - min) / levels. Per-chunk ranges give every
chunk the same number of levels, so a chunk whose values spread wide gets a coarse step and a tight chunk a fine
one. With a tile step, every chunk of a tile takes the same step s_k = (median over the tile's chunks of their
extent) / `levels[k]`: a chunk of extent e stores `max' = min + L (e / n)`, n = clamp(e / s_k, 1, L) its number of
steps and L the format's levels, so its values quantise to q = 0..n (texel codes stay small and their Morton deltas
cheap) at step e / n = s_k, or finer where a chunk spreads wider than L steps. One absolute step for positions,
scales and colour is smaller than per-chunk grids at the same PSNR (issue 15; BENCHMARKS.md, "Figures behind
library defaults").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import UsageError
from .f16 import f16_ceil, f16_floor
from .texformats import get_format


@dataclass(frozen=True)
class TileStep:
    """Levels the median chunk of a tile gets, per component. The first `shared` components share one step: the
    median over chunks of their largest extent / levels[0] (positions: the same error along every axis; log scales
    and SH0 R, G, B alike); every later component has its own, the median chunk's extent / its levels."""

    levels: tuple[float, ...]
    shared: int = 1
    # Importance scaling (SH bands, issue 32): with a per-chunk importance w_c (the encoder's: mean opacity x
    # footprint of the chunk's splats), chunk c's step is s_k * (median w / w_c) ** importance, clamped to
    # [1 / IMPORTANCE_RANGE, IMPORTANCE_RANGE] x s_k. 0.5 is the step that minimises importance-weighted squared
    # error for the bits of a uniform quantiser (error ~ step^2, bits ~ -log2 step); 0 is off.
    importance: float = 0.0
    # Zero on the grid (SH bands, issue 32): lower each chunk's min by less than one step so that 0 is a grid point.
    # Most SH coefficients lie near 0; on a grid anchored at the chunk's minimum they round to the nearest of two
    # codes about a step apart, on a zero-anchored grid to one code that decodes to (almost) 0: less error and fewer
    # distinct codes for the same step. A chunk already using all of its format's levels keeps its range.
    zero: bool = False
    # Rounding offset towards 0 (with `zero`): a value u steps from the zero code is coded as sign(u) floor(|u| +
    # rounding), 0.5 being plain rounding. Below 0.5 the zero code's bin widens and every code moves towards 0 (the
    # dead zone of video coders): fewer distinct codes for a little more error. Decoders see ordinary codes.
    rounding: float = 0.5
    # One step over every layer and component of the plane (SH bands, issue 32): the median over chunks, layers and
    # components of the extent / levels[0]. Mean over view directions, every real SH coefficient of every colour
    # channel weighs the same in the colour error (an orthonormal basis), so equal squared error per coefficient,
    # i.e. one step for all, is what spends the bits best; a step per coefficient from its own spread gives
    # coefficients of small spread finer steps than they deserve.
    pooled: bool = False
    # Size-relative step (positions, issue 32): with per_size = K > 0 the step of the shared components is the
    # tile's median splat size (the largest axis of exp(log scale) unless size_axis says, splat_sizes) / K, in
    # place of the median chunk's extent / levels[0]; the median chunk then gets K x (its extent / the median size)
    # levels, clamped to [size_levels_min, levels[0]]. A position error hurts a splat in proportion to its size,
    # so a scene of small splats in wide chunks gets a fine step and one of large splats a coarse one (statue scans:
    # BENCHMARKS.md, "A position step from the splats' size").
    per_size: float = 0.0
    size_levels_min: float = 1.0
    # Which axis of exp(log scale) is a splat's size for per_size, counted from the smallest (0) to the largest
    # (2). The middle axis is the width of a thin strand (issue 32, branch logo32: a rule on it was measured on
    # playcanvas-logo and not wired, no preset uses it; BENCHMARKS.md, "Why the presets lose on the held-out logo").
    size_axis: int = 2

    def check(self, fmt_name: str, components: int) -> None:
        fmt = get_format(fmt_name)
        if fmt.levels[0] == 0 or fmt.block > 1:
            raise UsageError(f"a tile step needs an integer texel format, not {fmt_name}")
        if len(self.levels) != components or min(self.levels) < 1 or not 1 <= self.shared <= components:
            raise UsageError(f"tile step levels {self.levels} (shared {self.shared}) for {components} components")
        if self.size_axis not in (0, 1, 2):
            raise UsageError(f"tile step size axis {self.size_axis}: 0 (smallest), 1 (middle) or 2 (largest)")


def step_sizes(extent: np.ndarray, step: TileStep, median_size: float | None = None) -> np.ndarray:
    """(C,) step per component from the chunks' extents (chunks, C); `median_size`: the tile's median splat size
    for a size-relative step (TileStep.per_size, shared_levels)."""
    size = np.median(extent, axis=0) / np.array(step.levels, np.float64)
    shared_extent = float(np.median(extent[:, :step.shared].max(axis=1)))
    size[:step.shared] = shared_extent / shared_levels(shared_extent, step, median_size)
    return size


def shared_levels(median_extent: float, step: TileStep, median_size: float | None) -> float:
    """Levels of the median chunk for the shared components: levels[0], or with a size-relative step
    (TileStep.per_size) per_size x median_extent / median_size clamped to [size_levels_min, levels[0]]."""
    if not step.per_size or median_size is None or not median_size > 0 or not median_extent > 0:
        return step.levels[0]
    return float(np.clip(step.per_size * median_extent / median_size, step.size_levels_min, step.levels[0]))


def splat_sizes(log_scales: np.ndarray, axis: int = 2) -> np.ndarray:
    """(N,) a splat's size for a size-relative step: the `axis`-th smallest axis of exp(log scale) (2: the largest,
    1: the middle one; TileStep.size_axis)."""
    ls = np.asarray(log_scales, np.float64)
    if axis == 2:
        return np.exp(ls.max(axis=1))
    return np.exp(np.sort(ls, axis=1)[:, axis])


def pooled_step_size(extents: np.ndarray, step: TileStep) -> float:
    """TileStep.pooled's one step: the median of every chunk's, layer's and component's extent (any shape) /
    levels[0]."""
    return float(np.median(extents)) / step.levels[0]


IMPORTANCE_RANGE = 64.0


def importance_factors(chunk_importance: np.ndarray, exponent: float) -> np.ndarray:
    """(chunks,) step multiplier per chunk: (median / w_c) ** exponent, clamped to [1/64, 64] (TileStep.importance);
    chunks of zero importance get the coarsest."""
    w = np.asarray(chunk_importance, np.float64)
    positive = w[w > 0]
    if exponent == 0 or len(positive) == 0:
        return np.ones(len(w))
    ratio = np.divide(np.median(positive), w, out=np.full(len(w), np.inf), where=w > 0)
    return np.clip(ratio ** exponent, 1.0 / IMPORTANCE_RANGE, IMPORTANCE_RANGE)


def widened_max(lo: np.ndarray, hi: np.ndarray, fmt_name: str, step: TileStep, range_dtype: str,
                limits: tuple[float, float], chunk_importance: np.ndarray | None = None,
                pooled_size: float | None = None, median_size: float | None = None) -> np.ndarray:
    """The stored max of every chunk (chunks, C) under a tile step; `lo`, `hi` the chunk ranges as stored (in
    `range_dtype`). Never below `hi` (every value stays inside its range) nor above the plane's limit.
    `chunk_importance` (chunks,): scales each chunk's step when the step has an `importance` exponent.
    `pooled_size`: the step of every component (TileStep.pooled, pooled_step_size) instead of step_sizes'.
    `median_size`: the tile's median splat size (splat_sizes) for a size-relative step (TileStep.per_size)."""
    components = lo.shape[-1]
    step.check(fmt_name, components)
    fmt_levels = np.array(get_format(fmt_name).levels[:components], np.float64)
    lo64, hi64 = lo.astype(np.float64), hi.astype(np.float64)
    extent = hi64 - lo64
    size = step_sizes(extent, step, median_size) if pooled_size is None else np.full(components, pooled_size)
    if step.importance and chunk_importance is not None:
        size = size[None, :] * importance_factors(chunk_importance, step.importance)[:, None]
    steps = np.clip(np.divide(extent, size, out=np.zeros_like(extent), where=size > 0), 1.0, fmt_levels)
    wide = lo64 + extent * (fmt_levels / steps)
    if range_dtype == "<f2":

        stored = f16_ceil(wide.astype(np.float32)).astype(np.float64)
    else:
        stored = wide.astype(np.float32).astype(np.float64)
    # At the plane's limit (or f16's largest value) keep the tight range: a reader rejects ranges outside the limits.
    stored = np.where(np.isfinite(stored) & (stored <= limits[1]), np.maximum(stored, hi64), hi64)
    return stored.astype(range_dtype)


def zero_on_grid(lo: np.ndarray, wide: np.ndarray, hi: np.ndarray, fmt_name: str, range_dtype: str,
                 limits: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The stored (min, max) of every chunk (chunks, C) with 0 moved onto the quantisation grid (TileStep.zero):
    `lo`, `wide` the range after widened_max, `hi` the chunk's tight max. The step (max - min) / L is kept and the
    range shifted down by less than one step, for chunks whose values straddle 0 and whose values still fit below
    the shifted max; other chunks keep (lo, wide). The new ends are rounded outward to `range_dtype`, which moves
    the zero point by a few f16 ulps of the range, far below a step."""
    components = lo.shape[-1]
    fmt_levels = np.array(get_format(fmt_name).levels[:components], np.float64)
    lo64, wide64, hi64 = lo.astype(np.float64), wide.astype(np.float64), hi.astype(np.float64)
    step = (wide64 - lo64) / fmt_levels
    positive = step > 0
    k = np.ceil(np.divide(-lo64, step, out=np.zeros_like(step), where=positive))
    new_lo = -k * step
    new_hi = new_lo + fmt_levels * step
    if range_dtype == "<f2":
        new_lo = f16_floor(new_lo.astype(np.float32)).astype(np.float64)
        new_hi = f16_ceil(new_hi.astype(np.float32)).astype(np.float64)
    else:
        new_lo = new_lo.astype(np.float32).astype(np.float64)
        new_hi = new_hi.astype(np.float32).astype(np.float64)
    ok = (positive & (lo64 < 0) & (hi64 > 0) & (new_hi >= hi64) & np.isfinite(new_lo) & np.isfinite(new_hi)
          & (new_lo >= limits[0]) & (new_hi <= limits[1]))
    return np.where(ok, new_lo, lo64).astype(range_dtype), np.where(ok, new_hi, wide64).astype(range_dtype)


def round_towards_zero(t: np.ndarray, lo: np.ndarray, hi: np.ndarray, fmt_name: str, rounding: float) -> np.ndarray:
    """Normalised values t (chunks, 256, C) in [0, 1] of chunks with ranges lo, hi (chunks, C), requantised so that
    the code nearest 0 takes a value u codes away as sign(u) floor(|u| + rounding) codes from it
    (TileStep.rounding); chunks not straddling 0 keep plain rounding. Returns t on exact codes (code / L)."""
    components = t.shape[-1]
    levels = np.array(get_format(fmt_name).levels[:components], np.float64)
    lo64, hi64 = lo.astype(np.float64), hi.astype(np.float64)
    extent = hi64 - lo64
    straddles = (lo64 < 0) & (hi64 > 0)
    zero_code = np.rint(np.divide(-lo64, extent, out=np.zeros_like(extent), where=extent > 0) * levels)
    u = t.astype(np.float64) * levels - zero_code[:, None]
    towards = zero_code[:, None] + np.sign(u) * np.floor(np.abs(u) + rounding)
    code = np.where(straddles[:, None], towards, np.rint(t * levels))
    return (np.clip(code, 0, levels) / levels).astype(t.dtype)


# Opacities of 8-bit inputs (compressed.ply, .splat, SPZ) are k / 255; their sigmoid of a float32 logit comes back
# within about 2.4e-4 of a step of it (biker.compressed.ply).
OPACITY_GRID = 255
OPACITY_GRID_TOLERANCE = 1e-3


def on_grid(steps: np.ndarray, tolerance: float) -> bool:
    """Whether every value, counted in steps of some grid, is within `tolerance` of a whole step (and there are any):
    the mark of values an earlier quantiser wrote."""
    steps = np.asarray(steps, np.float64)
    return steps.size > 0 and bool(np.all(np.abs(steps - np.rint(steps)) <= tolerance))


def opacity_on_grid(opacity: np.ndarray) -> bool:
    """Whether every opacity is k / 255 (to float rounding): a quantised input's own grid."""
    return on_grid(np.asarray(opacity, np.float64) * OPACITY_GRID, OPACITY_GRID_TOLERANCE)


def keep_opacity_grid(lo: np.ndarray, hi: np.ndarray, fmt_name: str, component: int) -> bool:
    """For a colour plane whose opacities are on the 255-step grid (opacity_on_grid), set every chunk's opacity
    range to [0, 1] in place when the format's levels for it are a multiple of 255: each opacity then quantises to
    its own code exactly (k or 257 k), where a per-chunk range [k1 / 255, k2 / 255], rounded out to f16, puts a
    second grid over the first (medium on biker.compressed.ply: 71 -> 78 dB). 0 and 1 are exact in f16. Returns
    whether it did."""
    fmt = get_format(fmt_name)
    levels = fmt.levels[component] if component < len(fmt.levels) else 0
    if fmt.block > 1 or levels == 0 or levels % OPACITY_GRID:
        return False
    lo[:, component] = 0.0
    hi[:, component] = 1.0
    return True
