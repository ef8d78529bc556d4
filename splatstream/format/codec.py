"""Quantisation of splat attributes into texel planes and back (format_spec/format.md, "Planes").

Pure functions over numpy arrays. For every plane the encoder and the decoder here are exact inverses
up to the texel format's quantisation; the tests bound the round-trip error per preset and attribute.

Plane values are kept as (N, L, C) arrays: N splats, L layers (1, or the coefficients of an SH band),
C components. Ranged planes store t = (v - min) / (max - min) against per-chunk, per-layer, per-component
ranges; rotations are unit quaternions and need no range.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..gaussians import SH_BAND_COEFFS, Gaussians, logit, normalize_quaternions, sigmoid
from .f16 import f16_ceil, f16_floor
from .layout import CHUNK_SIZE, chunk_texel_index, texture_size
from .limits import plane_limits
from .planes import PALETTE_ENTRIES, PALETTE_GROUPS, SH_INDEX_FORMAT, SH_INDEX_PLANE, PlaneSpec, palette_count
from .steps import (
    TileStep,
    keep_opacity_grid,
    opacity_on_grid,
    pooled_step_size,
    round_towards_zero,
    widened_max,
    zero_on_grid,
)
from .texformats import (
    PALETTE_FORMATS,
    TEXEL_DTYPES,
    decode_image,
    encode_bc_image,
    get_format,
    pack_texels,
    unpack_texels,
)

SQRT2 = math.sqrt(2.0)
WHOLE_PLANE_GATHER_BYTES = 32 << 20
# Opacity is stored after the sigmoid; decoding takes the logit of a value clamped to this interval.
OPACITY_EPS = 1e-6


# ---------------------------------------------------------------------------------------------------------------
# Attribute values of a plane


OPACITY = 3  # the colour plane's opacity component (after SH0's R, G, B)


def plane_values(g: Gaussians, spec: PlaneSpec) -> np.ndarray:
    """(N, L, C) float32 values the plane stores (before normalisation)."""
    if spec.name == "position":
        return g.positions[:, None, :]
    if spec.name == "rotation":
        return g.rotations[:, None, :]
    if spec.name == "scale":
        return g.log_scales[:, None, :]
    if spec.name == "color":
        return np.concatenate([g.sh_dc, sigmoid(g.opacity_logits)[:, None]], axis=1)[:, None, :]
    return g.band(int(spec.name[2:]))


# ---------------------------------------------------------------------------------------------------------------
# Rotations


def rotation_mode(fmt_name: str) -> str:
    """How a texel format holds a quaternion: 'full' (w,x,y,z), 'smallest3' (3 comps + index), 'xyz' (w >= 0; over
    the format's rotation_range, format.md 4.5)."""
    fmt = get_format(fmt_name)
    if fmt.levels[0] == 0:
        return "full"
    if fmt.components == 4 and fmt.block == 1 and fmt.rotation_range == 1.0:
        return "smallest3"
    return "xyz"  # a format over a gauge's range (cube565) holds x, y, z whatever its texel


def encode_rotations(q: np.ndarray, fmt_name: str) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z) -> (N, 4) normalised texel values."""
    mode = rotation_mode(fmt_name)
    if mode == "full":
        return (q + 1.0) * 0.5
    if mode == "xyz":
        q = normalize_quaternions(q)  # w >= 0, so w is recovered from x, y, z
        t = np.zeros_like(q)
        span = get_format(fmt_name).rotation_range
        # over the format's range (format.md 4.5: cube565's [-tan(pi/8), tan(pi/8)], the cube gauge's); values out
        # of it are clamped by the texel quantiser (the encoder stores cube565 rotations in the gauge only)
        t[:, :3] = (q[:, 1:] + 1.0) * 0.5 if span == 1.0 else (q[:, 1:] / np.float32(span) + 1.0) * 0.5
        return t
    n = len(q)
    largest = np.argmax(np.abs(q), axis=1)
    sign = np.where(q[np.arange(n), largest] < 0, -1.0, 1.0).astype(np.float32)
    qs = q * sign[:, None]
    keep = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    small = np.take_along_axis(qs, keep, axis=1)
    t = np.empty((n, 4), np.float32)
    t[:, :3] = (small * SQRT2 + 1.0) * 0.5
    levels = get_format(fmt_name).levels[3]
    t[:, 3] = largest / levels
    return t


def decode_rotations(t: np.ndarray, fmt_name: str) -> np.ndarray:
    """(N, 4) normalised texel values -> (N, 4) unit quaternions (w, x, y, z) with w >= 0."""
    mode = rotation_mode(fmt_name)
    if mode == "full":
        return normalize_quaternions(t * 2.0 - 1.0)
    if mode == "xyz":
        span = get_format(fmt_name).rotation_range
        xyz = t[:, :3] * 2.0 - 1.0 if span == 1.0 else (t[:, :3] * 2.0 - 1.0) * np.float32(span)
        w = np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(axis=1)))
        return normalize_quaternions(np.concatenate([w[:, None], xyz], axis=1))
    n = len(t)
    levels = get_format(fmt_name).levels[3]
    largest = np.clip(np.rint(t[:, 3] * levels), 0, 3).astype(np.int64)
    small = (t[:, :3] * 2.0 - 1.0) / SQRT2
    big = np.sqrt(np.maximum(0.0, 1.0 - (small * small).sum(axis=1)))
    q = np.empty((n, 4), np.float32)
    keep = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    np.put_along_axis(q, keep, small.astype(np.float32), axis=1)
    q[np.arange(n), largest] = big
    return normalize_quaternions(q)


# ---------------------------------------------------------------------------------------------------------------
# Planes


@dataclass
class EncodedPlane:
    spec: PlaneSpec
    format: str
    width: int
    height: int
    layers: list[np.ndarray] | Iterator[np.ndarray]  # one uint8 texture blob per layer (see encode_plane's lazy)
    ranges: np.ndarray | None  # (chunks, 2, L, C) in range_dtype, [:, 0] = min, [:, 1] = max
    # A palette plane's palettes (format.md 4.3.2): (palette_count, 256) float32; its `ranges` are None.
    palette: np.ndarray | None = None
    # The palettes are the scene's (format.md 4.3.2, 1.7: in the manifest): its payload holds no palette section.
    scene_palette: bool = False

    @property
    def chunks(self) -> int:
        return (self.width // 16) * (self.height // 16)


def _pad_to_chunks(values: np.ndarray) -> np.ndarray:
    """Pad (N, ...) to a whole number of chunks by repeating the last row (keeps ranges and BC blocks tight)."""
    n = len(values)
    padded = -(-n // CHUNK_SIZE) * CHUNK_SIZE
    if padded == n:
        return values
    return np.concatenate([values, np.repeat(values[-1:], padded - n, axis=0)])


def chunk_ranges(values: np.ndarray, range_dtype: str,
                 limits: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk (min, max) over axis 0 of (N, ...) values, widened to what range_dtype can hold exactly.

    `limits`: the plane's value domain (format.md 4.8). Values the encoder made itself (SH codebook entries, merged
    LOD splats) are weighted means of values inside it, but float rounding can put them an ulp outside: 65504 +
    an ulp would round out to an infinite f16 range. The range is clamped to the domain (such values then decode
    to its edge)."""
    full = len(values) // CHUNK_SIZE * CHUNK_SIZE
    # Reduce along a contiguous axis of 256: numpy is several times faster there than over a middle axis. The axes
    # moved by transpose (np.moveaxis's checks cost more than the min and max of a small tile's layer).
    nd = values.ndim
    v = values[:full].transpose(*range(1, nd), 0).copy().reshape(*values.shape[1:], -1, CHUNK_SIZE)
    back = (nd - 1, *range(nd - 1))
    lo, hi = v.min(axis=-1).transpose(back), v.max(axis=-1).transpose(back)
    del v
    if full < len(values):
        lo = np.concatenate([lo, values[full:].min(axis=0, keepdims=True)])
        hi = np.concatenate([hi, values[full:].max(axis=0, keepdims=True)])
    if limits is not None:
        lo, hi = np.clip(lo, *limits), np.clip(hi, *limits)
    if range_dtype == "<f2":
        lo, hi = f16_floor(lo), f16_ceil(hi)
    else:
        lo, hi = lo.astype(np.float32), hi.astype(np.float32)
    return lo, hi


def _texture_blob(t: np.ndarray, fmt_name: str, chunks: int, width: int, height: int) -> np.ndarray:
    """(chunks * 256, C) normalised values in splat order -> texture blob in chunk-block layout."""
    fmt = get_format(fmt_name)
    dest = chunk_texel_index(chunks, width)
    if fmt.block == 1:
        texels = pack_texels(fmt_name, t)
        img = np.zeros((width * height,) + texels.shape[1:], texels.dtype)
        img[dest] = texels
        return img.reshape(-1).view(np.uint8)
    img = np.zeros((width * height, 4), np.uint8)
    img[dest, : t.shape[1]] = _quantize_u8(t)
    return encode_bc_image(fmt_name, img.reshape(height, width, 4))


def _quantize_u8(t: np.ndarray) -> np.ndarray:
    q = t * np.float32(255.0)
    q += np.float32(0.5)
    return q.astype(np.uint8)


def encode_plane(values: np.ndarray, spec: PlaneSpec, fmt_name: str, order: np.ndarray | None = None,
                 lazy: bool = False, step: TileStep | None = None,
                 importance: np.ndarray | None = None, scene_palette: np.ndarray | None = None,
                 sizes: np.ndarray | None = None) -> EncodedPlane:
    """Quantise (N, L, C) plane values into one texture blob per layer (+ per-chunk ranges).

    `step`: quantise a ranged plane on one step per component over the tile instead of per-chunk grids, by widening
    each chunk's stored max (steps.py, format.md 4.3.1).

    `importance` (N,): per-splat weights (in the input's order) for a step with an importance exponent: each chunk's
    step scales with its mean importance (steps.py, TileStep.importance).

    `order` (a permutation, the tile's Morton order) is applied before quantising. With
    `lazy`, `layers` is an iterator that encodes each layer when asked for it and `ranges` is filled in once it
    is exhausted, so a payload writer holds one layer at a time.

    `scene_palette`: a palette plane's scene palettes (encode_palette_plane's `scene`).

    `sizes` (N,): per-splat sizes (steps.splat_sizes) for a size-relative step (TileStep.per_size): its median over
    the tile sets the step.
    """
    get_format(fmt_name)
    if fmt_name in PALETTE_FORMATS:
        return encode_palette_plane(values, spec, fmt_name, order, scene_palette)
    n = len(values)
    chunks = max(1, -(-n // CHUNK_SIZE))
    width, height = texture_size(chunks)
    if n == 0:
        values, order = np.zeros((1, spec.layers, spec.components), np.float32), None
    plane = EncodedPlane(spec, fmt_name, width, height, [], None)
    chunk_importance = None
    if step is not None and step.importance and importance is not None and n > 0:
        w = np.asarray(importance, np.float64) if order is None else np.take(importance, order)
        w = np.concatenate([w, np.zeros(chunks * CHUNK_SIZE - n)])
        chunk_importance = w.reshape(chunks, CHUNK_SIZE).sum(axis=1) / np.minimum(
            CHUNK_SIZE, n - np.arange(chunks) * CHUNK_SIZE)

    # One gather of the whole plane is several times faster than one per layer (random access once), but
    # holds the plane twice; large planes are gathered layer by layer.
    if order is not None and values.nbytes <= WHOLE_PLANE_GATHER_BYTES:
        values, order = np.take(values, order, axis=0), None

    median_size = None
    if step is not None and step.per_size and sizes is not None and n > 0:
        median_size = float(np.median(sizes))
    pooled_size = None
    if step is not None and step.pooled and spec.range_dtype and n > 0:
        extents = []
        for layer in range(spec.layers):
            v = values[:, layer] if order is None else np.take(values[:, layer], order, axis=0)
            lo, hi = chunk_ranges(v, spec.range_dtype, plane_limits(spec.name))
            extents.append(hi.astype(np.float64) - lo.astype(np.float64))
        pooled_size = pooled_step_size(np.stack(extents), step)

    def layers():
        lows, highs = [], []
        for layer in range(spec.layers):
            v = values[:, layer] if order is None else np.take(values[:, layer], order, axis=0)
            if spec.range_dtype:
                lo, hi = chunk_ranges(v, spec.range_dtype, plane_limits(spec.name))
                if step is not None:
                    tight_hi = hi
                    hi = widened_max(lo, hi, fmt_name, step, spec.range_dtype, plane_limits(spec.name),
                                     chunk_importance, pooled_size, median_size)
                    if step.zero:
                        lo, hi = zero_on_grid(lo, hi, tight_hi, fmt_name, spec.range_dtype, plane_limits(spec.name))
                if spec.name == "color" and opacity_on_grid(v[:, OPACITY]):
                    keep_opacity_grid(lo, hi, fmt_name, OPACITY)
                lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
                extent = hi32 - lo32
                inv = np.divide(1.0, extent, out=np.zeros_like(extent), where=extent > 0)
                t = _pad_to_chunks(v).reshape(chunks, CHUNK_SIZE, spec.components) - lo32[:, None]
                t *= inv[:, None]
                np.clip(t, 0.0, 1.0, out=t)
                if step is not None and step.rounding != 0.5 and get_format(fmt_name).block == 1:
                    t = round_towards_zero(t, lo, hi, fmt_name, step.rounding)
                t = t.reshape(-1, spec.components)
                lows.append(lo)
                highs.append(hi)
            else:
                t = _pad_to_chunks(encode_rotations(v, fmt_name))
            del v
            blob = _texture_blob(t, fmt_name, chunks, width, height)
            del t
            if layer == spec.layers - 1 and spec.range_dtype:
                plane.ranges = np.stack([np.stack(lows, axis=1), np.stack(highs, axis=1)], axis=1).astype(
                    spec.range_dtype)
            yield blob

    plane.layers = layers() if lazy else list(layers())
    return plane


def fit_palette(values: np.ndarray) -> np.ndarray:
    """(PALETTE_ENTRIES,) float32 palette, ascending, for an array of values: the distinct values themselves when
    there are at most PALETTE_ENTRIES (every value is then an entry, exactly; entries past them repeat the last),
    else PALETTE_ENTRIES evenly spaced values from the least to the largest (a tile-wide 8-bit grid: the error is at
    most half its step, as a norm8x4 plane over one range; an LOD tile's merged values, which leave the input's
    palette, land here). Deterministic: a function of the values' set."""
    return PaletteValues.of(values).palette()


@dataclass(frozen=True)
class PaletteValues:
    """What a palette is fitted from (fit_palette), gathered part by part (the partitioned encoder's chunks of the
    input: encode/sample.py): the sorted distinct values while there are at most PALETTE_ENTRIES, else only the least
    and the largest (`many`), which is all the 256-step grid needs. Joining parts gives what the whole would."""

    values: np.ndarray  # float32, ascending
    many: bool = False

    @staticmethod
    def of(values: np.ndarray) -> PaletteValues:
        distinct = np.unique(np.asarray(values, np.float32))
        if distinct.size > PALETTE_ENTRIES:
            return PaletteValues(distinct[[0, -1]], True)
        return PaletteValues(distinct)

    @staticmethod
    def join(parts: list[PaletteValues]) -> PaletteValues:
        joined = PaletteValues.of(np.concatenate([p.values for p in parts]) if parts else np.zeros(0, np.float32))
        if any(p.many for p in parts) and not joined.many:
            return PaletteValues(joined.values[[0, -1]], True)
        return joined

    def palette(self) -> np.ndarray:
        """(PALETTE_ENTRIES,) float32, ascending: fit_palette's rule."""
        distinct = self.values
        if distinct.size == 0:
            return np.zeros(PALETTE_ENTRIES, np.float32)
        if not self.many:
            return np.concatenate([distinct, np.repeat(distinct[-1:], PALETTE_ENTRIES - distinct.size)])
        return _grid_palette(float(distinct[0]), float(distinct[-1]))


def palette_values(values: np.ndarray, spec: PlaneSpec) -> list[PaletteValues]:
    """The PaletteValues of each palette of a palette plane (PALETTE_GROUPS) from its (N, 1, C) values."""
    groups = PALETTE_GROUPS[spec.name]
    return [PaletteValues.of(values[:, 0, [k for k, g in enumerate(groups) if g == p]])
            for p in range(palette_count(spec))]


def scene_palettes(parts: dict[str, list[PaletteValues]]) -> dict[str, np.ndarray]:
    """The scene's palettes per plane, (palette_count, 256) float32 (format.md 4.3.2, 1.7), from its PaletteValues."""
    return {name: np.stack([p.palette() for p in groups]).astype(np.float32) for name, groups in parts.items()}


def merged_pairs(palette: np.ndarray) -> np.ndarray:
    """(256,) ascending palette with its distinct values merged pairwise (an encoder choice, presets.py
    PRESET_PALETTE_MERGE): the least and the largest distinct values stay, so every value stays inside the palette's
    span, and the ones between are merged two by two into their midpoint (256 distinct values -> 129; an odd count
    pairs the last with itself). Each value then takes its nearest entry: an error of at most half the gap of the
    pair it was merged in. Padded with the largest entry, as PaletteValues.palette pads."""
    d = np.unique(np.asarray(palette, np.float64))
    if len(d) <= 2:
        kept = d
    else:
        inner = d[1:-1]
        if len(inner) % 2:
            inner = np.append(inner, inner[-1])
        kept = np.concatenate([d[:1], (inner[0::2] + inner[1::2]) / 2, d[-1:]])
    return np.concatenate([kept, np.repeat(kept[-1:], PALETTE_ENTRIES - len(kept))]).astype(np.float32)


def _grid_palette(lo: float, hi: float) -> np.ndarray:
    grid = (lo + (hi - lo) * (np.arange(PALETTE_ENTRIES) / (PALETTE_ENTRIES - 1))).astype(np.float32)
    grid[0], grid[-1] = lo, hi
    return np.maximum.accumulate(grid)


def palette_indices(values: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """Index of the nearest palette entry of every value (the first of equal entries; exact where a value is one)."""
    p = palette.astype(np.float64)
    distinct = np.concatenate([[True], p[1:] != p[:-1]])
    first = np.flatnonzero(distinct)
    entries = p[first]
    v = np.asarray(values, np.float64)
    i = np.clip(np.searchsorted(entries, v), 1, max(1, len(entries) - 1)) if len(entries) > 1 else \
        np.zeros(v.shape, np.int64)
    if len(entries) > 1:
        i = np.where(np.abs(v - entries[i - 1]) <= np.abs(v - entries[i]), i - 1, i)
    return first[i]


def encode_palette_plane(values: np.ndarray, spec: PlaneSpec, fmt_name: str, order: np.ndarray | None = None,
                         scene: np.ndarray | None = None) -> EncodedPlane:
    """A palette plane (format.md 4.3.2): per palette of the plane (PALETTE_GROUPS: the components sharing it), the
    tile's values' palette (fit_palette: exact when they take at most 256 values), and every component's index into
    its palette as an 8-bit texel component in the chunk-block layout.

    `scene`: the scene's palettes of the plane ((palette_count, 256), format.md 4.3.2, 1.7). A palette group whose
    tile values all lie within its scene palette's least and largest entry is indexed into it (nearest entry); if
    every group is, the plane is marked `scene_palette` (its payload then holds no palette section), else the plane
    carries its own palettes: the scene's rows for the groups inside them, the tile's fit for the others."""
    if spec.name not in PALETTE_GROUPS or spec.layers != 1:
        raise ValueError(f"{fmt_name} holds palette indices of a scale or colour plane, not of {spec.name}")
    n = len(values)
    chunks = max(1, -(-n // CHUNK_SIZE))
    width, height = texture_size(chunks)
    v = values[:, 0] if order is None else np.take(values[:, 0], order, axis=0)
    if n == 0:
        v = np.zeros((1, spec.components), np.float32)
    groups = PALETTE_GROUPS[spec.name]
    palette = np.zeros((palette_count(spec), PALETTE_ENTRIES), np.float32)
    index = np.zeros((len(v), 4), np.float32)
    inside = True
    for p in range(len(palette)):
        comps = [k for k, g in enumerate(groups) if g == p]
        if scene is not None and within_palette(v[:, comps], scene[p]):
            palette[p] = scene[p]
        else:
            palette[p] = fit_palette(v[:, comps])
            inside = False
        index[:, comps] = palette_indices(v[:, comps], palette[p]).astype(np.float32) / np.float32(255.0)
    blob = _texture_blob(_pad_to_chunks(index), fmt_name, chunks, width, height)
    if scene is not None and inside:
        return EncodedPlane(spec, fmt_name, width, height, [blob], None, np.asarray(scene, np.float32), True)
    return EncodedPlane(spec, fmt_name, width, height, [blob], None, palette)


def within_palette(values: np.ndarray, palette: np.ndarray) -> bool:
    """Whether every value lies within the palette's least and largest entry (its nearest entry is then at most
    half the largest gap between neighbouring entries away)."""
    return not values.size or (float(values.min()) >= float(palette.min()) and
                               float(values.max()) <= float(palette.max()))


def decode_palette_indices(plane: EncodedPlane, n: int) -> np.ndarray:
    """(N, 4) int64 palette indices of a palette plane's first n splats (slot order)."""
    chunks = max(1, -(-n // CHUNK_SIZE))
    src = chunk_texel_index(chunks, plane.width)[:n]
    blob = plane.layers[0] if isinstance(plane.layers, list) else next(iter(plane.layers))
    return np.frombuffer(blob, np.uint8).reshape(-1, 4)[src].astype(np.int64)


def decode_palette_plane(plane: EncodedPlane, n: int) -> np.ndarray:
    """(N, 1, C) float32 values of a palette plane: each component's palette entry (every index 0..255 is valid)."""
    index = decode_palette_indices(plane, n)
    groups = PALETTE_GROUPS[plane.spec.name]
    out = np.empty((n, 1, len(groups)), np.float32)
    for k, p in enumerate(groups):
        out[:, 0, k] = plane.palette[p][index[:, k]]
    return out


# The texel format a GPU client holds a palette plane's values in (format.md 4.3.2, informative): 16-bit components
# over per-chunk f16 ranges, within 1/131070 of a chunk's extent of the palette's values. The GL client does not
# look palettes up in its shaders (yet): its pool transcodes on join (palette_as_ranged).
PALETTE_GPU_FORMAT = "norm16x4"


def gpu_format(fmt_name: str) -> str:
    """The texel format a GPU atlas holds a plane of `fmt_name` in (a palette plane's values: PALETTE_GPU_FORMAT)."""
    return PALETTE_GPU_FORMAT if fmt_name in PALETTE_FORMATS else fmt_name


def palette_as_ranged(plane: EncodedPlane, n: int) -> EncodedPlane:
    """A palette plane's first n values as a PALETTE_GPU_FORMAT plane with per-chunk ranges (the same chunks and
    texture); any other plane as it is."""
    if plane.format not in PALETTE_FORMATS:
        return plane
    return encode_plane(decode_palette_plane(plane, n), plane.spec, PALETTE_GPU_FORMAT)


def encode_index_plane(indices: np.ndarray, order: np.ndarray | None = None) -> EncodedPlane:
    """Per-splat codebook indices (N,) -> an index16 plane in the chunk-block layout (padding repeats the last)."""
    idx = np.asarray(indices, np.int64)
    if order is not None:
        idx = idx[order]
    if idx.size and (idx.min() < 0 or idx.max() > 65535):
        raise ValueError("codebook indices must be 0..65535")
    n = len(idx)
    chunks = max(1, -(-n // CHUNK_SIZE))
    width, height = texture_size(chunks)
    padded = _pad_to_chunks(idx) if n else np.zeros(CHUNK_SIZE, np.int64)
    img = np.zeros(width * height, "<u2")
    img[chunk_texel_index(chunks, width)] = padded.astype("<u2")
    return EncodedPlane(SH_INDEX_PLANE, SH_INDEX_FORMAT, width, height, [img.view(np.uint8)], None)


def decode_index_plane(plane: EncodedPlane, n: int) -> np.ndarray:
    """index16 plane -> (N,) int64 codebook indices."""
    chunks = max(1, -(-n // CHUNK_SIZE))
    src = chunk_texel_index(chunks, plane.width)[:n]
    blob = plane.layers[0] if isinstance(plane.layers, list) else next(iter(plane.layers))
    return np.frombuffer(blob, "<u2")[src].astype(np.int64)


def codebook_band_values(entries: np.ndarray, band: int) -> np.ndarray:
    """(K, L, 3) values of one band of a codebook whose rows are laid out as codebook_rows."""
    k = len(entries)
    rest = entries.reshape(k, -1, 3)
    first = sum(SH_BAND_COEFFS[b] for b in range(1, band))
    return rest[:, first:first + SH_BAND_COEFFS[band]]


def decode_plane(plane: EncodedPlane, n: int) -> np.ndarray:
    """Texture blob (+ ranges) back to (N, L, C) float32 plane values."""
    spec = plane.spec
    if plane.format in PALETTE_FORMATS:
        return decode_palette_plane(plane, n)
    fmt = get_format(plane.format)
    chunks = max(1, -(-n // CHUNK_SIZE))
    src = chunk_texel_index(chunks, plane.width)[:n]
    ts = []
    for blob in plane.layers:
        if fmt.block == 1:
            texels = np.frombuffer(blob, TEXEL_DTYPES[fmt.name])
            ts.append(unpack_texels(fmt.name, texels[src]))
        else:
            ts.append(decode_image(fmt.name, blob, plane.width, plane.height).reshape(-1, 4)[src])
    t = np.stack(ts, axis=1)  # (N, L, 4)
    if not spec.range_dtype:
        return decode_rotations(t[:, 0], plane.format)[:, None, :]
    chunk = np.arange(n) // CHUNK_SIZE
    lo = plane.ranges[:, 0].astype(np.float32)[chunk]
    hi = plane.ranges[:, 1].astype(np.float32)[chunk]
    return (lo + t[..., : spec.components] * (hi - lo)).astype(np.float32)


def assemble_gaussians(planes: dict[str, np.ndarray], sh_degree: int) -> Gaussians:
    """Gaussians from decoded plane values (missing SH bands above sh_degree are left out)."""
    color = planes["color"][:, 0]
    opacity = np.clip(color[:, OPACITY], OPACITY_EPS, 1.0 - OPACITY_EPS)
    n = len(color)
    rest = [planes[f"sh{b}"] for b in range(1, sh_degree + 1)]
    sh_rest = np.concatenate(rest, axis=1) if rest else np.zeros((n, 0, 3), np.float32)
    return Gaussians(
        positions=planes["position"][:, 0],
        rotations=planes["rotation"][:, 0],
        log_scales=planes["scale"][:, 0],
        opacity_logits=logit(opacity),
        sh_dc=color[:, :3],
        sh_rest=sh_rest,
    )
