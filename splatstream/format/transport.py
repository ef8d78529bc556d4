"""Transport coding of texels sections (format_spec/format.md 5.2): the `fields1` section filter.

What a payload stores and sends may differ from the texel bytes the GPU holds, as long as decoding gives back those
bytes exactly. `fields1` splits every texel into its fields (norm11 -> 11, 10 and 11-bit integers, norm565 ->
5/6/5, f16x4 -> four 16-bit words, ...), lays each field out in **slot order** (16x16 blocks in row-major block
order, Morton order inside a block: the splat order of format.md 4.1) and predicts it: optionally from another
field of the same texel through a per-block linear model (colour R and B from G, SH coefficient R and B from G: the
channels of one value are strongly correlated, while per-chunk normalisation leaves little between chunks), then
optionally from the previous slot (delta: Morton-ordered splats are near neighbours). Residuals modulo 2^bits are
zigzag-mapped and stored as byte planes; the payload's one zstd frame does the entropy coding.

The encoder (`filter_texels`) decides per section, on a band of its first layer coded both ways, whether `fields1`
or the byte shuffle of format.md 5.1 is smaller; rotations and scales usually keep the shuffle, BC blocks always do.
Decoding (`unfilter_fields`) is numpy-vectorised: running sums, shifts and one gather per layer back to texture
order, in work arrays kept per thread.

Pure functions; every malformed content raises FormatError, and no decode allocates more than the section's texel
size (plus its small per-block parameters).
"""
from __future__ import annotations

import functools
import sys
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import zstandard

from ..errors import FormatError
from .layout import BLOCK
from .texformats import FORMATS

FIELDS1 = "fields1"
BLOCK_TEXELS = BLOCK * BLOCK
FIELDS_VERSION = 1
SLOPE_SHIFT = 6  # per-block slopes are in units of 1/64
SLOPE_MIN, SLOPE_MAX = -128, 127
INTERCEPT_MIN, INTERCEPT_MAX = -32768, 32767
MODE_DELTA = 0x01
MODE_RESERVED = 0x0E
# Encoder: modes are chosen on about this many slots (whole blocks spread over the layer; 16,384 chose the same
# modes as 65,536 on the 1M scene's medium planes, at a third of the time), and fields1 is tried against the byte
# shuffle on a band of the first layer (BAND_SLOTS, whole block rows).
SAMPLE_SLOTS = 1 << 14
BAND_SLOTS = 1 << 17
# Transport choices of the encoder: "fields" (fields1 where it is smaller, format 1.2), "keyed" (as "fields", and
# norm16x4 positions re-sorted inside chunks and stored as morton1 where smaller: format 1.6, format/keyed.py),
# "shuffle" (format 1.0/1.1 filters only, for old readers), "none" (stored as the GPU holds them).
TRANSPORTS = ("fields", "keyed", "shuffle", "none")

# Field layout of each texel format fields1 applies to: (word dtype, words per texel, [(shift, bits)] low bits first).
FIELD_LAYOUTS: dict[str, tuple[str, int, tuple[tuple[int, int], ...]]] = {
    "f32x4": ("<u4", 4, ((0, 32),)),
    "f16x4": ("<u2", 4, ((0, 16),)),
    "norm10_2": ("<u4", 1, ((0, 10), (10, 10), (20, 10), (30, 2))),
    "norm11": ("<u4", 1, ((0, 11), (11, 10), (21, 11))),
    # bits 27-31 of a norm9x3 texel are zero (format.md 4.2): no field holds them, so they decode as zero
    "norm9x3": ("<u4", 1, ((0, 9), (9, 9), (18, 9))),
    "norm8x4": ("<u1", 4, ((0, 8),)),
    "norm16x4": ("<u2", 4, ((0, 16),)),
    "norm565": ("<u2", 1, ((0, 5), (5, 6), (11, 5))),
    "index16": ("<u2", 1, ((0, 16),)),
    "pal8x4": ("<u1", 4, ((0, 8),)),
}
# A format that shares another's texels (texformats.TexelFormat.same_texels_as: cube565) shares its fields too.
FIELD_LAYOUTS.update({name: FIELD_LAYOUTS[f.texels] for name, f in FORMATS.items() if f.same_texels_as})
# Unsigned type that holds one whole texel, for moving texels as single elements.
_TEXEL_UINT = {4: np.dtype("<u4"), 8: np.dtype("<u8"), 2: np.dtype("<u2")}


@functools.lru_cache(maxsize=16)
def field_bits(fmt: str) -> tuple[int, ...]:
    """Bit width of each field of one texel, in field order (format.md 5.2)."""
    _, words, layout = FIELD_LAYOUTS[fmt]
    return tuple(bits for _, bits in layout) * words


@functools.lru_cache(maxsize=16)
def unused_bits(fmt: str) -> int:
    """Mask of the word bits no field covers (bits 27-31 of norm9x3; 0 for every other format): they MUST be zero
    in a texel, since fields1 restores them as zero."""
    dtype, _, layout = FIELD_LAYOUTS[fmt]
    covered = 0
    for shift, bits in layout:
        covered |= ((1 << bits) - 1) << shift
    return ((1 << (np.dtype(dtype).itemsize * 8)) - 1) & ~covered


@functools.lru_cache(maxsize=32)
def slot_to_texel(width: int, height: int) -> np.ndarray:
    """Texel index (y * width + x) of every slot: blocks in row-major block order, Morton order inside a block."""
    j = np.arange(BLOCK_TEXELS, dtype=np.intp)
    bx = (j & 1) | ((j >> 1) & 2) | ((j >> 2) & 4) | ((j >> 3) & 8)
    by = ((j >> 1) & 1) | ((j >> 2) & 2) | ((j >> 3) & 4) | ((j >> 4) & 8)
    cols, rows = width // BLOCK, height // BLOCK
    b = np.arange(cols * rows, dtype=np.intp)
    x0, y0 = (b % cols) * BLOCK, (b // cols) * BLOCK
    index = ((y0[:, None] + by[None, :]) * width + x0[:, None] + bx[None, :]).reshape(-1)
    index.setflags(write=False)
    return index


def content_bounds(fmt: str, width: int, height: int, layers: int) -> tuple[int, int]:
    """Smallest and largest `fields1` content of a section (no field predicted / every field that may be)."""
    bits = field_bits(fmt)
    n = width * height
    planes = n * layers * sum((b + 7) // 8 for b in bits)
    predictable = sum(b <= 16 for b in bits)
    predicted = predictable - 1 if predictable > 1 else 0  # at least one anchor
    smallest = 1 + len(bits) * layers + planes
    return smallest, smallest + 3 * (n // BLOCK_TEXELS) * predicted * layers


def _check_geometry(fmt: str, width: int, height: int, layers: int, source: str) -> None:
    if fmt not in FIELD_LAYOUTS:
        raise FormatError(source, "filter", f"fields1 does not apply to texel format {fmt!r}")
    if not (type(width) is int and type(height) is int and type(layers) is int and 0 < width <= 2048
            and 0 < height <= 16384 and 0 < layers <= 64 and width % BLOCK == 0 and height % BLOCK == 0):
        raise FormatError(source, "texture", f"{width}x{height}x{layers} is not a texture of 16x16 blocks "
                          "(width <= 2048, height <= 16384, 1..64 layers)")


# ---------------------------------------------------------------------------------------------------------------
# Field split and join (one layer)


def split_layer(layer: np.ndarray, fmt: str, width: int, height: int) -> list[np.ndarray]:
    """One layer's texel bytes -> one array per field in slot order (uint8 for 8-bit fields, uint16 up to 16 bits,
    uint32 for 32-bit ones)."""
    dtype, words, layout = FIELD_LAYOUTS[fmt]
    word_dtype = np.dtype(dtype)
    index = slot_to_texel(width, height)
    texel_bytes = word_dtype.itemsize * words
    unused = unused_bits(fmt)
    if unused and (np.asarray(layer).view(word_dtype) & word_dtype.type(unused)).any():
        # a writer's bug: fields1 would drop these bits, and the decoded texels would differ from the GPU bytes
        raise ValueError(f"{fmt} texels with bits outside their fields set (mask {unused:#x}): they must be zero")
    if texel_bytes in _TEXEL_UINT:
        slots = np.asarray(layer).view(_TEXEL_UINT[texel_bytes])[index].view(word_dtype).reshape(-1, words)
    else:  # f32x4: 16 bytes a texel
        slots = np.asarray(layer).view(word_dtype).reshape(-1, words)[index]
    out = []
    for w in range(words):
        column = slots[:, w]
        for shift, bits in layout:
            if bits == word_dtype.itemsize * 8:
                out.append(np.ascontiguousarray(column))
            else:
                t = _field_dtype(bits)
                out.append(((column >> word_dtype.type(shift)) & word_dtype.type((1 << bits) - 1)).astype(t))
    return out


def join_layer(fields: list[np.ndarray], fmt: str, width: int, height: int,
               out: np.ndarray | None = None) -> np.ndarray:
    """Inverse of split_layer: field arrays in slot order (any unsigned type; only the field's bits are used when
    the format packs several fields in a word) -> the layer's texel bytes in texture order, written into `out`
    (uint8, the layer's size) when given."""
    dtype, words, layout = FIELD_LAYOUTS[fmt]
    word_dtype = np.dtype(dtype)
    n = width * height
    index = slot_to_texel(width, height)
    texel_bytes = word_dtype.itemsize * words
    if out is None:
        out = np.empty(n * texel_bytes, np.uint8)
    if len(layout) == 1:
        # one field per word: interleave the words of a texel in slot order, then one scatter of whole texels
        if words == 1:
            slots = fields[0].astype(word_dtype, copy=False)
        else:
            slots = np.empty((n, words), word_dtype)
            for k, f in enumerate(fields):
                slots[:, k] = f
        if texel_bytes in _TEXEL_UINT:
            out.view(_TEXEL_UINT[texel_bytes])[index] = slots.reshape(-1).view(_TEXEL_UINT[texel_bytes])
        else:
            out.view(word_dtype).reshape(n, words)[index] = slots
        return out
    acc = fields[0].astype(np.uint32)  # a copy: it is written to below
    for f, (shift, _) in zip(fields[1:], layout[1:], strict=True):
        acc |= f.astype(np.uint32, copy=False) << np.uint32(shift)
    out.view(word_dtype)[index] = acc
    return out


# ---------------------------------------------------------------------------------------------------------------
# Prediction


def _field_dtype(bits: int) -> type:
    """Unsigned type a field's residuals are computed in (wrap-around arithmetic modulo its size, then masked)."""
    return np.uint8 if bits <= 8 else np.uint16 if bits <= 16 else np.uint32


def _zigzag(u: np.ndarray, bits: int) -> np.ndarray:
    """Residual modulo 2^bits (two's complement in `bits` bits) -> zigzag code 2v (v >= 0) or -2v - 1 (v < 0)."""
    t = u.dtype.type
    mask = t((1 << bits) - 1)
    return ((u << t(1)) ^ np.negative(u >> t(bits - 1))) & mask


def _cross_prediction(ref: np.ndarray, slope: np.ndarray, intercept: np.ndarray) -> np.ndarray:
    """Per-block linear prediction floor((slope * ref + 64 * intercept + 32) / 64), as int32 (slot order); `ref`
    holds values below 2^16 (any integer type). Slopes and intercepts of shape (..., blocks) predict as many
    references at once (choose_modes' pairs), each row of the result one of them."""
    if ref.dtype != np.int32:
        ref = ref.view(np.int32) if ref.dtype == np.uint32 else ref.astype(np.int32)
    r = np.multiply(ref.reshape(*slope.shape, BLOCK_TEXELS), slope.astype(np.int32)[..., None])
    r += ((intercept.astype(np.int32) << SLOPE_SHIFT) + (1 << (SLOPE_SHIFT - 1)))[..., None]
    r >>= SLOPE_SHIFT
    return r.reshape(*slope.shape[:-1], -1)


def _block_stats(x: np.ndarray, t: type) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A field's blocks in the fit's float type, their sums and their sums of squares (float64)."""
    b = x.reshape(-1, BLOCK_TEXELS).astype(t)
    return b, b.sum(axis=1, dtype=np.float64), np.einsum("ij,ij->i", b, b).astype(np.float64)


def _fit_type(bits: int) -> type:
    return np.float32 if bits <= 8 else np.float64


def _fit_cross(values: np.ndarray, ref: np.ndarray, bits: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Per-block least-squares slope (1/64 units) and intercept of values against ref. The block sums are exact
    (so the fit is the same on every machine): in float32 for fields of up to 8 bits (256 products below 2^16 sum
    below 2^24), else in float64."""
    t = _fit_type(bits)
    v = values.reshape(-1, BLOCK_TEXELS).astype(t)
    return _fit_from_stats(v, v.sum(axis=1, dtype=np.float64), _block_stats(ref, t))


def _fit_from_stats(v: np.ndarray, sv: np.ndarray, ref_stats: tuple[np.ndarray, np.ndarray, np.ndarray]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """_fit_cross from the values' blocks and sums and the reference's _block_stats (choose_modes computes each
    field's once for all its pairs: the same operations on the same arrays, so the same fit)."""
    r, sr, rr = ref_stats
    return _fit_from_sums(np.einsum("ij,ij->i", r, v).astype(np.float64), sv, sr, rr)


def _fit_from_sums(dot: np.ndarray, sv: np.ndarray, sr: np.ndarray, rr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The slope and intercept of each block (any leading shape) from its sums: of reference times values, of the
    values, of the reference and of the reference's squares."""
    cov = dot * BLOCK_TEXELS - sr * sv
    var = rr * BLOCK_TEXELS - sr * sr
    slope = np.divide(cov, var, out=np.zeros_like(var), where=var > 0)
    slope = np.clip(np.rint(slope * (1 << SLOPE_SHIFT)), SLOPE_MIN, SLOPE_MAX)
    intercept = np.rint((sv - slope / (1 << SLOPE_SHIFT) * sr) / BLOCK_TEXELS)
    return slope.astype(np.int8), np.clip(intercept, INTERCEPT_MIN, INTERCEPT_MAX).astype("<i2")


@functools.lru_cache(maxsize=64)
def _fit_plan(bits: tuple[int, ...], pairs: tuple[tuple[int, int], ...]) -> tuple[tuple, ...]:
    """_fit_stacked's work for one (bits, pairs), worked out once: per fit type (float32 or float64), the pairs it
    fits, the fields they use (None: all, in order) and each pair's field and reference among them."""
    plan = []
    for t in (np.float32, np.float64):
        rows = [p for p, (i, r) in enumerate(pairs) if _fit_type(max(bits[i], bits[r])) is t]
        if not rows:
            continue
        used = sorted({k for p in rows for k in pairs[p]})
        at = {k: n for n, k in enumerate(used)}
        ii = np.array([at[pairs[p][0]] for p in rows], np.intp)
        ri = np.array([at[pairs[p][1]] for p in rows], np.intp)
        plan.append((t, np.array(rows, np.intp), None if used == list(range(len(bits))) else np.array(used, np.intp),
                     len(used), ii, ri))
    return tuple(plan)


def _fit_stacked(stacked: np.ndarray, bits: tuple[int, ...], pairs: tuple[tuple[int, int], ...]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """_fit_cross(fields[i], fields[r], max(bits[i], bits[r])) of every pair (i, r) at once, the fields as one
    (fields, slots) array of any integer type that holds them, as (pairs, blocks) slopes and intercepts
    (choose_modes' up to 12 pairs per layer on ~6 blocks: numpy's per-call overhead). The same results: every block
    sum is an exact integer in its float type (_fit_cross), so summing several fields' blocks in one call gives the
    same sums, and the rest is the same elementwise arithmetic."""
    sv, sr, rr, dot = (np.empty((len(pairs), stacked.shape[1] // BLOCK_TEXELS)) for _ in range(4))
    for t, rows, used, count, ii, ri in _fit_plan(bits, pairs):
        blk = (stacked if used is None else stacked[used]).reshape(count, -1, BLOCK_TEXELS).astype(t)
        sums = blk.sum(axis=2, dtype=np.float64)
        dots = np.einsum("mbk,nbk->mnb", blk, blk).astype(np.float64)
        sv[rows], sr[rows], rr[rows], dot[rows] = sums[ii], sums[ri], dots[ri, ri], dots[ri, ii]
    return _fit_from_sums(dot, sv, sr, rr)


def _residual(values: np.ndarray, bits: int, delta: bool, pred: np.ndarray | None) -> np.ndarray:
    """Stored code of every slot: (values - pred) modulo 2^bits, delta to the previous slot if asked; fields of more
    than 8 bits as zigzag codes (so small residuals of either sign have a zero high byte)."""
    t = _field_dtype(bits)
    x = values.astype(t)  # a copy
    if pred is not None:
        x -= pred.astype(t)
    if delta:
        x[1:] -= x[:-1].copy()
    if bits not in (8, 16, 32):
        x &= t((1 << bits) - 1)
    return x if bits <= 8 else _zigzag(x, bits)


def _planes(z: np.ndarray, bits: int) -> list[np.ndarray]:
    """Codes -> contiguous byte planes, low byte first."""
    nbytes = (bits + 7) // 8
    if nbytes == 1:
        return [z.astype(np.uint8, copy=False)]
    b = z.view(np.uint8).reshape(-1, z.dtype.itemsize)
    return [np.ascontiguousarray(b[:, i]) for i in range(nbytes)]


def _plane_cost(z: np.ndarray, bits: int) -> float:
    """Order-0 entropy of the byte planes in bytes (what zstd's Huffman stage roughly reaches)."""
    total = 0.0
    nbytes = (bits + 7) // 8
    b = z.view(np.uint8).reshape(-1, z.dtype.itemsize)
    n = len(b)  # every plane's count sum (not summed per plane: choose_modes calls this ~30 times per layer)
    for k in range(nbytes):
        counts = np.bincount(b[:, k], minlength=256)
        counts = counts[counts > 0]
        total += float((counts * np.log2(n / counts)).sum()) / 8
    return total


def _block_costs(blocks: list[tuple[np.ndarray, int]]) -> list[list[float]]:
    """_plane_cost of every row of several (codes (rows, slots), bits) blocks, rows of one block of one code type
    and all of one length: one bincount and one log2 for all their byte planes, each block's planes taken from it
    in one strided pass (no per-row views or list of planes). Byte-identical to _plane_cost row by row, in
    order: the same counts, each plane's terms the same elementwise operations, each plane's sum numpy's sum over a
    contiguous array of the same values in the same order, a row's planes added low byte first."""
    n = blocks[0][0].shape[1]
    nbytes = [(b + 7) // 8 for _, b in blocks]
    count = sum(len(z) * k for (z, _), k in zip(blocks, nbytes, strict=True))
    # bin = plane * 256 + byte; in uint16 where that fits (64 planes at most a layer today): bincount's own cast of
    # it is cheaper than writing intp here
    index_type = np.uint16 if 256 * count <= 1 << 16 else np.intp
    idx = np.empty((count, n), index_type)
    start = 0
    for (z, _), k in zip(blocks, nbytes, strict=True):
        rows = len(z)
        planes = z.view(np.uint8).reshape(rows, n, z.dtype.itemsize)[:, :, :k].transpose(0, 2, 1)
        offsets = (np.arange(start, start + rows * k, dtype=np.intp) * 256).astype(index_type).reshape(rows, k, 1)
        np.add(planes, offsets, out=idx[start:start + rows * k].reshape(rows, k, n))
        start += rows * k
    counts = np.bincount(idx.reshape(-1), minlength=256 * count).reshape(count, 256)
    seen = counts > 0
    c = counts[seen]  # row after row: each plane's nonzero counts in _plane_cost's order
    terms = c * np.log2(n / c)
    ends = np.cumsum(seen.sum(axis=1)).tolist()
    add = np.add.reduce  # what ndarray.sum calls, without its Python wrapper (~40 planes a layer)
    out, plane, begin = [], 0, 0
    for (z, _), k in zip(blocks, nbytes, strict=True):
        costs = []
        for _ in range(len(z)):
            total = 0.0
            for _ in range(k):
                end = ends[plane]
                total += float(add(terms[begin:end])) / 8
                begin, plane = end, plane + 1
            costs.append(total)
        out.append(costs)
    return out


def _sample_blocks(blocks: int) -> np.ndarray | None:
    """Blocks the encoder measures modes on: all of them (None), or an even spread of about SAMPLE_SLOTS slots."""
    want = max(1, SAMPLE_SLOTS // BLOCK_TEXELS)
    if blocks <= want:
        return None
    return np.linspace(0, blocks - 1, want).astype(np.intp)


Modes = list[tuple[bool, int | None]]  # per field: (delta, reference field or None)


@functools.lru_cache(maxsize=64)
def _row_masks(dtype: str, bits: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """_residual_rows' per-row field masks and zigzag shifts (bits - 1), as (rows, 1) arrays of the code type."""
    t = np.dtype(dtype).type
    mask = np.array([(1 << b) - 1 for b in bits], np.uint64).astype(t)[:, None]
    top = np.array([b - 1 for b in bits], np.uint64).astype(t)[:, None]
    for m in (mask, top):
        m.setflags(write=False)
    return mask, top


def _residual_rows(values: np.ndarray, bits: tuple[int, ...], pred: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """_residual without and with delta of several fields of one code type at once: `values` (rows, slots) in
    _field_dtype of every row's `bits`, `pred` (rows, slots) int32 or None; (plain, delta) codes as (rows, slots)
    arrays, the prediction subtracted once for both. Row for row the same elementwise integer operations as
    _residual (masking with a field's whole width, as the one-row form skips, changes nothing), so the same codes:
    choose_modes pays numpy's per-call overhead once per code type of a layer instead of once per residual (~12 a
    layer on a few blocks)."""
    t = values.dtype.type
    mask, top = _row_masks(values.dtype.str, bits)
    x = values.copy()
    if pred is not None:
        x -= pred.astype(t)
    d = x.copy()
    d[:, 1:] -= x[:, :-1]
    x &= mask
    d &= mask
    if values.dtype.itemsize == 1:  # fields of up to 8 bits: no zigzag
        return x, d
    return ((x << t(1)) ^ np.negative(x >> top)) & mask, ((d << t(1)) ^ np.negative(d >> top)) & mask


class _LayerTrials:
    """What choose_modes computed on a sample that is the whole layer: every field's codes alone (without and with
    delta) and against every reference it tried (the block parameters and both codes). code_layer takes the chosen
    ones from here instead of fitting and coding the chosen modes again: the same fits (_fit_stacked equals
    _fit_cross pair by pair), the same predictions and residuals (_residual_rows equals _residual), so the same
    planes."""

    def __init__(self) -> None:
        self.alone: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.cross: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]] = {}

    def code(self, i: int, delta: bool, ref: int | None) -> tuple[np.ndarray, list[np.ndarray]]:
        """Field i's codes under (delta, ref) and its block parameters (slope, intercept; none without ref)."""
        if ref is None:
            return self.alone[i][int(delta)], []
        slope, intercept, codes = self.cross[(i, ref)]
        return codes[int(delta)], [slope, intercept]


@dataclass(frozen=True)
class _CodeGroup:
    """Candidates of one kind (fields alone, or pairs) whose codes share a type: coded together."""

    dtype: np.dtype
    pairs: bool
    keys: tuple[int, ...]  # field indices (alone) or pair indices
    fields: np.ndarray  # (rows,) index of each row's field among the fields of `dtype` (pairs only)
    refs: np.ndarray  # (rows,) each row's reference field (pairs only)
    bits: tuple[int, ...]  # each row's field bits
    width: int  # the widest of them: (width + 7) // 8 byte planes measured per code


@functools.lru_cache(maxsize=64)
def _trial_plan(bits: tuple[int, ...]) -> tuple[tuple[tuple[int, int], ...], tuple[_CodeGroup, ...],
                                                 dict[np.dtype, tuple[int, ...]]]:
    """choose_modes' work for one field layout, worked out once: the pairs tried, the code groups (by code type,
    narrowest first; fields alone, then pairs) and the fields of each code type."""
    nf = len(bits)
    pairs = tuple((i, r) for i in range(nf) for r in range(nf) if i != r and bits[i] <= 16 and bits[r] <= 16)
    of_type: dict[np.dtype, tuple[int, ...]] = {}
    for i in range(nf):
        t = np.dtype(_field_dtype(bits[i]))
        of_type[t] = of_type.get(t, ()) + (i,)
    groups = []
    for t in sorted(of_type, key=lambda t: t.itemsize):
        members = of_type[t]
        groups.append(_CodeGroup(t, False, members, np.arange(len(members)), np.empty(0, np.intp),
                                 tuple(bits[i] for i in members), max(bits[i] for i in members)))
        ps = [p for p, (i, _) in enumerate(pairs) if i in members]
        if ps:
            groups.append(_CodeGroup(t, True, tuple(ps), np.array([members.index(pairs[p][0]) for p in ps], np.intp),
                                     np.array([pairs[p][1] for p in ps], np.intp),
                                     tuple(bits[pairs[p][0]] for p in ps), max(bits[pairs[p][0]] for p in ps)))
    return pairs, tuple(groups), of_type


def _choose(fields: list[np.ndarray], bits: tuple[int, ...]) -> tuple[Modes, _LayerTrials | None]:
    """choose_modes, and its trials where its sample is the whole layer (else None).

    Every candidate's codes (each field alone, each field against each other field) without and with delta come
    from one _residual_rows per code group, their entropies from one _block_costs; the fits from one _fit_stacked."""
    nf, bits = len(fields), tuple(bits)
    blocks = len(fields[0]) // BLOCK_TEXELS
    pick = _sample_blocks(blocks)
    sample = fields if pick is None else [f.reshape(blocks, BLOCK_TEXELS)[pick].reshape(-1) for f in fields]
    pairs, groups, of_type = _trial_plan(bits)
    # each field in its code type (split_layer's already; a caller's wider array is cut as _residual cuts it)
    by_type = {t: np.stack([sample[i] for i in members]).astype(t, copy=False) for t, members in of_type.items()}
    slopes = intercepts = refs = None
    if pairs:
        refs = np.stack(sample).astype(np.int32)  # the fields as _cross_prediction takes its references
        slopes, intercepts = _fit_stacked(refs, bits, pairs)
    coded, code_blocks = [], []
    for g in groups:
        values = by_type[g.dtype]
        pred = None
        if g.pairs:
            values = values[g.fields]
            keys = list(g.keys)
            pred = _cross_prediction(refs[g.refs], slopes[keys], intercepts[keys])
        x, d = _residual_rows(values, g.bits, pred)
        coded.append((x, d))
        code_blocks += [(x, g.width), (d, g.width)]
    costs = _block_costs(code_blocks)
    param_cost = 3.0 * len(sample[0]) // BLOCK_TEXELS  # i8 slope + i16 intercept per block, before zstd
    alone: list[tuple[float, bool]] = [(0.0, False)] * nf
    cross: dict[tuple[int, int], tuple[float, bool]] = {}
    for k, g in enumerate(groups):
        plain_costs, delta_costs = costs[2 * k], costs[2 * k + 1]
        for row, key in enumerate(g.keys):
            plain, delta = plain_costs[row], delta_costs[row]
            if g.pairs:
                plain, delta = plain + param_cost, delta + param_cost
            best = (plain, False) if plain <= delta else (delta, True)  # min over {False, True}: ties keep False
            if g.pairs:
                cross[pairs[key]] = best
            else:
                alone[key] = best
    modes = _best_anchors(nf, alone, cross)
    if pick is not None:
        return modes, None
    trials = _LayerTrials()
    for g, (x, d) in zip(groups, coded, strict=True):
        for row, key in enumerate(g.keys):
            if g.pairs:
                trials.cross[pairs[key]] = (slopes[key], intercepts[key], (x[row], d[row]))
            else:
                trials.alone[key] = (x[row], d[row])
    return modes, trials


def _best_anchors(nf: int, alone: list[tuple[float, bool]], cross: dict[tuple[int, int], tuple[float, bool]]
                  ) -> Modes:
    """The modes of the cheapest set of anchors: every set tried in increasing mask order (the first of equal
    totals kept), each other field taking its cheapest option in the order alone, then its anchors by increasing
    index (the first of equal costs kept), a set's total summed in field order."""
    best_total, best = float("inf"), None
    for mask in range(1, 1 << nf):
        total, modes = 0.0, []
        for i in range(nf):
            cost, d = alone[i]
            r = None
            if not mask >> i & 1:
                for a in range(nf):
                    if mask >> a & 1 and (i, a) in cross:
                        c, dc = cross[(i, a)]
                        if c < cost:
                            cost, d, r = c, dc, a
            total += cost
            modes.append((d, r))
        if total < best_total:
            best_total, best = total, modes
    return best


def choose_modes(fields: list[np.ndarray], bits: tuple[int, ...]) -> Modes:
    """Per field (delta, reference field or None), chosen on a sample of blocks by the byte-plane entropy.

    Fields with a reference are predicted from an **anchor** (a field without one) of the same texel. Every set of
    anchors is tried (4 fields at most: 15 sets), each other field taking its best anchor or none.
    """
    return _choose(fields, bits)[0]


# ---------------------------------------------------------------------------------------------------------------
# Encoder


@dataclass
class CodedLayer:
    """One layer of a fields1 content: mode bytes, per-block parameters of its predicted fields, byte planes."""

    modes: Modes
    params: list[np.ndarray] = field(default_factory=list)
    planes: list[np.ndarray] = field(default_factory=list)

    def mode_bytes(self) -> bytes:
        return bytes((MODE_DELTA if d else 0) | ((0 if r is None else r + 1) << 4) for d, r in self.modes)


def code_layer(layer: np.ndarray, fmt: str, width: int, height: int, modes: Modes | None = None) -> CodedLayer:
    """One layer's texel bytes -> its part of the fields1 content (modes chosen on a sample unless given)."""
    bits = field_bits(fmt)
    fields = split_layer(layer, fmt, width, height)
    trials = None
    if modes is None:
        modes, trials = _choose(fields, bits)
    coded = CodedLayer(modes)
    for i, (delta, ref) in enumerate(coded.modes):
        if trials is not None:  # chosen on the whole layer: its codes and fits are at hand
            z, params = trials.code(i, delta, ref)
            coded.params += params
            coded.planes += _planes(z, bits[i]) if bits[i] > 8 else [z.copy()]  # a copy: not a view of every trial
            continue
        pred = None
        if ref is not None:
            slope, intercept = _fit_cross(fields[i], fields[ref], max(bits[i], bits[ref]))
            coded.params += [slope, intercept]
            pred = _cross_prediction(fields[ref], slope, intercept)
        coded.planes += _planes(_residual(fields[i], bits[i], delta, pred), bits[i])
    return coded


def assemble(layers: list[CodedLayer]) -> list[bytes | np.ndarray]:
    """The fields1 content of a section as parts to write in order: the version, modes and parameters as one part,
    then every byte plane (the payload writer ends a zstd block after each part, or after a run of like parts of a
    small payload: container._block_ends)."""
    head = bytes([FIELDS_VERSION]) + b"".join(c.mode_bytes() for c in layers) + \
        b"".join(p.tobytes() for c in layers for p in c.params)
    return [head] + [p for c in layers for p in c.planes]


def fields_content(data: np.ndarray | bytes, fmt: str, width: int, height: int, layers: int,
                   modes: list[Modes] | None = None) -> tuple[bytes, list[Modes]]:
    """The fields1 content of a whole texels section (GPU bytes, layer after layer) and the modes used (chosen per
    layer unless given): the normative encoder of format.md 5.2, for tests and test vectors."""
    data = np.frombuffer(data, np.uint8) if isinstance(data, bytes | bytearray) else np.ravel(data).view(np.uint8)
    unit = data.size // layers
    coded = [code_layer(data[k * unit:(k + 1) * unit], fmt, width, height, None if modes is None else modes[k])
             for k in range(layers)]
    return b"".join(bytes(p) for p in assemble(coded)), [c.modes for c in coded]


def shuffle_element(fmt: str) -> int:
    """Byte-shuffle element of a texel format (format.md 5.1): 1 for BC blocks (no shuffle)."""
    return max(1, FORMATS[fmt].shuffle)


def shuffle_filter(element: int) -> str:
    return f"shuffle{element}" if element > 1 else "none"


def shuffle_planes(data: np.ndarray, element: int) -> list[np.ndarray]:
    """Byte shuffle of one unit (format.md 5.1) as its byte planes: all first bytes of every element, then all
    second bytes, ... (one part, the unit itself, when there is nothing to shuffle)."""
    data = np.ravel(data).view(np.uint8)
    if element <= 1 or data.size % element:
        return [data]
    if element in (2, 4):
        words = data.view(f"<u{element}")
        return [(words >> (8 * k)).astype(np.uint8) for k in range(element)]
    return list(np.ascontiguousarray(data.reshape(-1, element).T))


def shuffle(data: np.ndarray, element: int) -> np.ndarray:
    """Byte shuffle of one unit (format.md 5.1) as one array."""
    planes = shuffle_planes(data, element)
    return planes[0] if len(planes) == 1 else np.concatenate(planes)


def _band(layer: np.ndarray, fmt: str, width: int, height: int) -> tuple[np.ndarray, int]:
    """The middle band of whole block rows of a layer holding about BAND_SLOTS slots, and its height."""
    block_rows = height // BLOCK
    rows = max(1, min(block_rows, -(-BAND_SLOTS // (width * BLOCK))))
    if rows == block_rows:
        return layer, height
    start = (block_rows - rows) // 2 * BLOCK
    row_bytes = width * FORMATS[fmt].bits_per_texel // 8
    return layer[start * row_bytes:(start + rows * BLOCK) * row_bytes], rows * BLOCK


# The fields1-or-shuffle trial compresses at this level at most: at the payload's level 16 (btultra) the trials cost
# as much as the payloads themselves (issue 32).
TRIAL_LEVEL_MAX = 9
_trial = threading.local()


def _trial_compressor(level: int) -> zstandard.ZstdCompressor:
    """One compressor per thread and level for the trial sizes: a fresh one per trial allocated zstd's tables each
    time (at level 16, btultra, that was most of low-plus-9bit's encode time with the LOD tree: issue 32)."""
    cache = getattr(_trial, "by_level", None)
    if cache is None:
        cache = _trial.by_level = {}
    if level not in cache:
        cache[level] = zstandard.ZstdCompressor(level=level)
    return cache[level]


def _zstd_size(parts: list, level: int) -> int:
    """Compressed size of parts coded as the payload writer codes a large payload (a zstd block ending with each
    part; a small payload's writer may join like parts' blocks, container._block_ends, which the trial leaves out:
    it compares two codings of one section, not how blocks end). The source size is pledged, so zstd sizes its
    tables to the trial, not to its largest window."""
    c = _trial_compressor(level).compressobj(size=sum(p.nbytes if isinstance(p, np.ndarray) else len(p) for p in parts))
    size = 0
    for p in parts:
        size += len(c.compress(p)) + len(c.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK))
    return size + len(c.flush())


def trial_size(parts: list, level: int) -> int:
    """Compressed size of `parts` as the encoder's transport trials measure it (zstd at `level`, at most
    TRIAL_LEVEL_MAX, a block per part)."""
    return _zstd_size(parts, min(level, TRIAL_LEVEL_MAX))


def filter_texels(layers: Iterable[np.ndarray], fmt: str, width: int, height: int, count: int, level: int = 1,
                  transport: str = "fields") -> tuple[str, list[bytes | np.ndarray]]:
    """A texels section's stored form: (filter name, parts to write in order), layers taken one at a time as the
    iterable yields them (each is dropped once coded).

    With transport "fields" the first layer decides: a band of it (about BAND_SLOTS slots, all of a small layer)
    is coded with fields1 and with the byte shuffle, both compressed with zstd at `level`, and the smaller
    wins for every layer of the section (SH coefficients of one band behave alike). The band's modes serve
    the whole first layer; the other layers choose their own."""
    element = shuffle_element(fmt)
    it = iter(layers)
    if transport == "none":
        return "none", [np.ravel(layer).view(np.uint8) for layer in it]
    if transport == "shuffle" or fmt not in FIELD_LAYOUTS:
        return shuffle_filter(element), [p for layer in it for p in shuffle_planes(layer, element)]
    if transport not in ("fields", "keyed"):
        raise ValueError(f"unknown transport {transport!r} (expected one of {', '.join(TRANSPORTS)})")
    first = np.ravel(next(it)).view(np.uint8)
    band, band_height = _band(first, fmt, width, height)
    trial = code_layer(band, fmt, width, band_height)
    shuffled = shuffle_planes(band, element)
    trial_level = min(level, TRIAL_LEVEL_MAX)
    if _zstd_size(assemble([trial]), trial_level) >= _zstd_size(shuffled, trial_level):
        if band_height != height:
            shuffled = shuffle_planes(first, element)
        return shuffle_filter(element), shuffled + [p for layer in it for p in shuffle_planes(layer, element)]
    coded = [trial if band_height == height else code_layer(first, fmt, width, height, trial.modes)]
    del first, band, shuffled
    coded += [code_layer(np.ravel(layer).view(np.uint8), fmt, width, height) for layer in it]
    if len(coded) != count:
        raise ValueError(f"{len(coded)} layers, expected {count}")
    return FIELDS1, assemble(coded)


# ---------------------------------------------------------------------------------------------------------------
# Decoder


# Up to this size, a shuffled unit is undone by numpy's transposing copy, faster than the general path for small units
# (BENCHMARKS.md, "Figures behind library defaults").
SMALL_UNSHUFFLE_BYTES = 2048


def unshuffle(buf: np.ndarray, element: int) -> np.ndarray:
    """Inverse byte shuffle (format.md 5.1) of one unit, as bytes (a view of `buf` when there is nothing to do)."""
    if element <= 1 or buf.size % element:
        return buf
    kernel = _unshuffle_kernel  # read once: another thread may hand it back meanwhile (decode_jit.warm_up)
    if kernel is not None and buf.size > SMALL_UNSHUFFLE_BYTES:
        out = np.empty(buf.size, np.uint8)
        kernel(buf, element, out)
        return out
    if buf.size <= SMALL_UNSHUFFLE_BYTES:  # ranges: one transposing copy beats the shifts' several numpy calls
        return np.ascontiguousarray(buf.reshape(element, -1).T).reshape(-1)
    if element in (2, 4):
        v = buf.reshape(element, -1)
        word = np.uint16 if element == 2 else np.uint32
        z = v[element - 1].astype(word)
        for k in range(element - 2, -1, -1):
            z <<= word(8)
            z |= v[k]
        return z.view(np.uint8)
    return np.ascontiguousarray(buf.reshape(element, -1).T).reshape(-1)


@functools.lru_cache(maxsize=32)
def texel_to_slot(width: int, height: int) -> np.ndarray:
    """Slot of every texel (the inverse of slot_to_texel): a gather with it (np.take, mode "clip": no index
    checks, and every index is in range) puts slot-order texels in texture order about 1.5x faster than a scatter."""
    index = slot_to_texel(width, height)
    inverse = np.empty_like(index)
    inverse[index] = np.arange(index.size, dtype=np.intp)
    inverse.setflags(write=False)
    return inverse


@dataclass(frozen=True)
class _Layout:
    """What unfilter_fields needs of a (format, width, height), worked out once: per-call Python work is a good
    part of a small tile's decode time."""

    bits: tuple[int, ...]
    nbytes: tuple[int, ...]  # byte planes per field
    runs: tuple[tuple[int, int, int, int], ...]  # (first field, end field, first byte, bytes a plane) of equal nbytes
    masks: np.ndarray  # (fields,) uint32: each field's bits
    word: np.dtype  # the texel's word
    words: int  # words a texel (one field each) or 1 (fields packed in one word)
    shifts: np.ndarray  # (fields, 1) uint32: bit offset of each field in its word (packed formats)
    texel_bytes: int
    texel: np.dtype  # the texel as one element: uint16/32/64, or V16 for f32x4
    inverse: np.ndarray  # texel_to_slot
    plane_bytes: int  # byte planes a slot (the sum of nbytes)


@functools.lru_cache(maxsize=64, typed=True)
def _layout(fmt: str, width: int, height: int) -> _Layout:
    bits = field_bits(fmt)
    nbytes = tuple((b + 7) // 8 for b in bits)
    runs, start, byte = [], 0, 0
    for i in range(1, len(bits) + 1):
        if i == len(bits) or nbytes[i] != nbytes[start]:
            runs.append((start, i, byte, nbytes[start]))
            byte += (i - start) * nbytes[start] * width * height
            start = i
    dtype, words, layout = FIELD_LAYOUTS[fmt]
    texel_bytes = FORMATS[fmt].bits_per_texel // 8
    masks = np.array([(1 << b) - 1 for b in bits], np.uint64).astype(np.uint32)
    shifts = np.array([shift for shift, _ in layout], np.uint32)[:, None]
    for a in (masks, shifts):
        a.setflags(write=False)
    return _Layout(bits, nbytes, tuple(runs), masks, np.dtype(dtype), words, shifts, texel_bytes,
                   _TEXEL_UINT.get(texel_bytes, np.dtype("V16")), texel_to_slot(width, height), sum(nbytes))


@functools.lru_cache(maxsize=4096)
def _decode_plan(fmt: str, width: int, height: int, layers: int, head: bytes) -> tuple:
    """Checks the header of a fields1 content (the version byte and the modes) once per distinct header; returns
    (expected content size, number of predicted fields, the _layer_plan of every layer), or an error message."""
    bits = field_bits(fmt)
    nf = len(bits)
    if head[0] != FIELDS_VERSION:
        return f"content has no version-{FIELDS_VERSION} header (version {head[0]})"
    modes = head[1:]
    if any(m & MODE_RESERVED for m in modes):
        return "reserved mode bits set"
    refs = tuple((m >> 4) - 1 for m in modes)
    for layer in range(layers):
        lr = refs[layer * nf:(layer + 1) * nf]
        for i, r in enumerate(lr):
            if r >= 0 and (r >= nf or r == i or lr[r] >= 0 or bits[i] > 16 or bits[r] > 16):
                return f"layer {layer} field {i}: reference field {r} is not an anchor field of the same texel"
    n = width * height
    crossed = sum(r >= 0 for r in refs)
    size = 1 + nf * layers + 3 * (n // BLOCK_TEXELS) * crossed + n * layers * sum((b + 7) // 8 for b in bits)
    deltas = tuple(bool(m & MODE_DELTA) for m in modes)
    plans = tuple(_layer_plan(fmt, refs[k * nf:(k + 1) * nf], deltas[k * nf:(k + 1) * nf],
                              sum(r >= 0 for r in refs[:k * nf])) for k in range(layers))
    return size, crossed, plans


def _layer_plan(fmt: str, refs: tuple[int, ...], deltas: tuple[bool, ...], first_param: int) -> tuple:
    """The steps of decoding one layer of a fields1 content with these modes: (delta rows, rows masked before the
    cross predictions, cross groups, rows masked after them), rows of the (fields, slots) work array as one slice
    where they are consecutive (one numpy call for them all). A cross group is (reference field, predicted rows as
    a slice, index of their first parameter set in the content, count): all predicted fields of a layer in one
    group when they share their reference and are evenly spaced (colour R and B from G), else one group each.

    A field is cut to its bits only where that changes the texel: where its uint32 value may exceed the field (a
    running sum, a negative residual modulo 2^32, a stored byte wider than the field) and it is the reference of a
    prediction (the spec predicts from the field's value) or bits above the field would reach the texel word
    (packed formats: the next field; norm9x3: the unused bits 27-31). Word-per-field formats (norm8x4, norm16x4,
    f16x4) need no cut: the copy into their words drops the high bits."""
    bits = field_bits(fmt)
    nf = len(bits)
    dtype, _, layout = FIELD_LAYOUTS[fmt]
    word_bits = np.dtype(dtype).itemsize * 8
    room = [word_bits - shift for shift, _ in layout] * (nf // len(layout))  # field bits that reach the word
    anchors = {r for r in refs if r >= 0}
    # a value may exceed its field after a running sum, as a zigzag residual (negative ones are near 2^32), or
    # when its stored byte has more bits than the field (norm565, the 2-bit field of norm10_2)
    wide = [i for i in range(nf) if bits[i] < 32 and (deltas[i] or bits[i] != 8)]
    pre_mask = [i for i in wide if i in anchors or (refs[i] < 0 and bits[i] < room[i])]
    crossed = [(i, r) for i, r in enumerate(refs) if r >= 0]
    rows = [i for i, _ in crossed]
    step = rows[1] - rows[0] if len(rows) > 1 else 1
    if crossed and len(anchors) == 1 and rows == list(range(rows[0], rows[-1] + 1, step)):
        groups = ((crossed[0][1], slice(rows[0], rows[-1] + 1, step), first_param, len(rows)),)
    else:
        groups = tuple((r, slice(i, i + 1), first_param + k, 1) for k, (i, r) in enumerate(crossed))
    post_mask = tuple(slice(i, i + 1) for i in rows if bits[i] < room[i])
    return _rows([i for i in range(nf) if deltas[i]]), _rows(pre_mask), groups, post_mask


def _rows(rows: list[int]) -> tuple[slice, ...]:
    """Rows as one slice when they are consecutive, else one slice a row."""
    if rows and rows == list(range(rows[0], rows[-1] + 1)):
        return (slice(rows[0], rows[-1] + 1),)
    return tuple(slice(i, i + 1) for i in rows)


_work = threading.local()
# Work buffers up to this size are kept per thread between calls (a decode thread's sections are alike in size).
KEEP_WORK_BYTES = 1 << 24


class _Work:
    """This thread's work arrays for one (format, slots), views of one buffer (contents undefined): z and spare
    (fields, slots) uint32, z as int32, two (fields, slots) uint8, each run's rows of them, and for word-per-field
    formats the texels in slot order (in spare) with a view of each word's column."""

    __slots__ = ("z", "spare", "signed", "runs", "columns", "texels")

    def __init__(self, buf: np.ndarray, lay: _Layout, n: int) -> None:
        nf = len(lay.bits)
        m = nf * n
        self.z = buf[:4 * m].view(np.uint32).reshape(nf, n)
        self.spare = buf[4 * m:8 * m].view(np.uint32).reshape(nf, n)
        self.signed = self.z.view(np.int32)
        t, u = buf[8 * m:9 * m].reshape(nf, n), buf[9 * m:10 * m].reshape(nf, n)
        self.runs = tuple((start, (end - first) * nb * n, end - first, nb, self.z[first:end], self.spare[first:end],
                           t[first:end], u[first:end]) for first, end, start, nb in lay.runs)
        slots = self.spare.reshape(-1)[:n * lay.texel_bytes // 4]
        if lay.words > 1:
            columns = slots.view(lay.word).reshape(n, lay.words)
            self.columns = tuple((columns[:, k], self.z[k]) for k in range(lay.words))
        else:
            self.columns = ()
        self.texels = slots.view(lay.texel)


def _work_for(fmt: str, lay: _Layout, n: int) -> _Work:
    """This thread's _Work for (fmt, n), reused from call to call.

    Why: the arrays of a tile's section are 40-160 KB, around glibc's mmap threshold, so fresh ones often come as
    new pages, and on this VM every first touch of a page is a fault of several microseconds: profiling the
    decode of biker's tiles put two thirds of the unfilter time in page faults (issue 15); and building the views
    once saves a good part of a small section's per-call work. Buffers larger than KEEP_WORK_BYTES (no-LOD tiles
    of millions of splats) are allocated per call and not kept."""
    cache = getattr(_work, "views", None)
    if cache is not None:
        work = cache.get((fmt, n))
        if work is not None:
            return work
    size = 10 * len(lay.bits) * n
    buf = getattr(_work, "buffer", None)
    if buf is not None and buf.size >= size:
        work = _Work(buf, lay, n)
    elif size > KEEP_WORK_BYTES:
        return _Work(np.empty(size, np.uint8), lay, n)
    else:
        buf = _work.buffer = np.empty(min(KEEP_WORK_BYTES, 1 << max(16, (size - 1).bit_length())), np.uint8)
        _work.views = cache = {}  # views of the old buffer go with it
        work = _Work(buf, lay, n)
    if cache is None:
        _work.views = cache = {}
    if len(cache) >= 64:
        cache.clear()
    cache[(fmt, n)] = work
    return work


_U8_ONE, _U32_SEVEN = np.uint8(1), np.uint32(7)


def _join_zigzag16(planes: np.ndarray, z: np.ndarray, spare: np.ndarray, t: np.ndarray, u: np.ndarray) -> None:
    """(fields, 2, slots) byte planes of 16-bit zigzag codes (low byte first) -> z, their residuals modulo 2^32.

    The code is c = 256 hi + lo and the residual (c >> 1) ^ -(c & 1) = (hi << 7) ^ t, where t, the int8
    (lo >> 1) ^ -(lo & 1), sign-extends to the all-ones mask for odd codes: four byte-sized passes and three
    uint32 passes instead of seven, and no mixed-type ufunc (numpy runs those several times slower)."""
    lo, hi = planes[:, 0], planes[:, 1]
    np.bitwise_and(lo, _U8_ONE, out=t)
    np.negative(t, out=t)
    np.right_shift(lo, _U8_ONE, out=u)
    t ^= u
    np.copyto(spare.view(np.int32), t.view(np.int8))  # sign extension
    np.copyto(z, hi)
    z <<= _U32_SEVEN
    z ^= spare


def _join_zigzag(planes: np.ndarray, z: np.ndarray, spare: np.ndarray) -> None:
    """(fields, nbytes, slots) byte planes of zigzag codes -> z, their residuals modulo 2^32 (the general case)."""
    nbytes = planes.shape[1]
    np.copyto(z, planes[:, nbytes - 1])
    for k in range(nbytes - 2, -1, -1):
        z <<= np.uint32(8)
        np.copyto(spare, planes[:, k])
        z |= spare
    np.bitwise_and(z, np.uint32(1), out=spare)
    z >>= np.uint32(1)
    np.negative(spare, out=spare)
    z ^= spare



def _fields1_header(raw: np.ndarray, fmt: str, width: int, height: int, layers: int, source: str):
    """A fields1 content's field layout, decode plan and header size from its header (FormatError naming `source`
    if short or invalid)."""
    lay = _layout(fmt, width, height)
    header_bytes = 1 + len(lay.bits) * layers
    if raw.size < header_bytes:
        raise FormatError(source, "fields1", f"{raw.size}-byte content is shorter than its header")
    plan = _decode_plan(fmt, width, height, layers, raw[:header_bytes].tobytes())
    if isinstance(plan, str):
        raise FormatError(source, "fields1", plan)
    return lay, plan, header_bytes

# ---------------------------------------------------------------------------------------------------------------
# A compiled fields1 decoder, handed in by a shell


_fields_kernel = None  # see use_fields_kernel


def use_fields_kernel(kernel) -> object:
    """Decode fields1 contents with `kernel` from now on (None: the numpy path again); returns the one it replaces.

    The core never imports numba (ARCHITECTURE.md): the streaming client's `client_gl.stream.decode_jit` compiles
    the kernel (the optional extra `fast`) and hands it in here. It must give the numpy path's bytes, bit for bit
    (tests/test_decode_jit.py holds both to the literal reading of format.md 5.2): the numpy path takes a dozen to
    two dozen numpy calls a layer, each a pass over the work array, and on the LOD tree's small tiles it was most
    of a payload's decode (issue 32). The header, the geometry and the content's size are checked here first,
    whichever decodes, so the kernel only ever sees a well-formed content; it is called as
    kernel(raw, planes_at, params_at, n, layers, words, fields, modes, slot_to_texel, work, out) with the tables of
    _kernel_args, `work` (fields, slots) int64 scratch and `out` the texels' words (native byte order)."""
    global _fields_kernel
    previous, _fields_kernel = _fields_kernel, kernel
    return previous


_unshuffle_kernel = None  # see use_unshuffle_kernel


def use_unshuffle_kernel(kernel) -> object:
    """Undo the byte shuffle of units above SMALL_UNSHUFFLE_BYTES with `kernel(unit, element, out)` (None: numpy
    again); returns the one it replaces. Handed in like use_fields_kernel's, for the same reason: numpy's shifts
    and casts are four to eight calls a unit, most of a small shuffled section's time."""
    global _unshuffle_kernel
    previous, _unshuffle_kernel = _unshuffle_kernel, kernel
    return previous


def fields_kernel() -> object:
    """The kernel use_fields_kernel handed in, or None (the numpy path)."""
    return _fields_kernel


@functools.lru_cache(maxsize=4096)
def _kernel_args(fmt: str, layers: int, head: bytes) -> tuple:
    """The per-format and per-header tables the kernel takes (int64, read-only): words a texel; per field (rows)
    its byte planes, its first plane's index in a layer, its mask, its word and its shift in the word; per field of
    every layer (rows) its delta flag, its reference field (-1: none) and its parameter set's index."""
    bits = field_bits(fmt)
    nf = len(bits)
    dtype, words, layout = FIELD_LAYOUTS[fmt]
    nbytes = [(b + 7) // 8 for b in bits]
    plane_index = [sum(nbytes[:f]) for f in range(nf)]
    masks = [(1 << b) - 1 for b in bits]
    word_of = [f // len(layout) for f in range(nf)]
    shifts = [layout[f % len(layout)][0] for f in range(nf)]
    modes = head[1:1 + nf * layers]
    refs = [(m >> 4) - 1 for m in modes]
    deltas = [m & MODE_DELTA for m in modes]
    param_index, k = [], 0
    for r in refs:
        param_index.append(k if r >= 0 else -1)
        k += r >= 0
    fields = np.array([nbytes, plane_index, masks, word_of, shifts], np.int64)
    table = np.array([deltas, refs, param_index], np.int64)
    for a in (fields, table):
        a.setflags(write=False)
    return words, fields, table, np.dtype(dtype).newbyteorder("=")


@functools.lru_cache(maxsize=4096, typed=True)
def _kernel_plan(fmt: str, width: int, height: int, layers: int, head: bytes) -> tuple | None:
    """What a kernel call needs for contents of this geometry and header, checked once (None: not a well-formed
    geometry or header, which the numpy path then refuses with its message): (content size, where the parameters
    and the byte planes start, slots, words, the two tables, the word dtype, slot_to_texel, fields, texel bytes)."""
    try:
        _check_geometry(fmt, width, height, layers, "")
    except FormatError:
        return None
    lay = _layout(fmt, width, height)
    header_bytes = 1 + len(lay.bits) * layers
    if len(head) != header_bytes:
        return None
    plan = _decode_plan(fmt, width, height, layers, head)
    if isinstance(plan, str):
        return None
    expected, crossed, _ = plan
    n = width * height
    words, fields, modes, word = _kernel_args(fmt, layers, head)
    return (expected, header_bytes, header_bytes + 3 * (n // BLOCK_TEXELS) * crossed, n, words, fields, modes, word,
            slot_to_texel(width, height), len(lay.bits), n * lay.texel_bytes * layers)


def _kernel_unfilter(kernel, raw: np.ndarray, fmt: str, width: int, height: int, layers: int) -> np.ndarray | None:
    """unfilter_fields' bytes by the handed-in `kernel` (as its caller read it); None where the content is not
    well-formed (the numpy path then raises its FormatError). The checks and the kernel's arguments come from one
    cached lookup per geometry and header: a section's Python around the kernel was as long as the kernel on small
    tiles."""
    nf = len(FIELD_LAYOUTS[fmt][2]) * FIELD_LAYOUTS[fmt][1] if fmt in FIELD_LAYOUTS else 0
    if not nf or type(layers) is not int or layers < 1:
        return None
    plan = _kernel_plan(fmt, width, height, layers, raw[:1 + nf * layers].tobytes())
    if plan is None or raw.size != plan[0]:
        return None
    _, params_at, planes_at, n, words, fields, modes, word, order, nf, out_bytes = plan
    out = np.empty(out_bytes, np.uint8)
    work = _scratch("kernel", 8 * nf * n).view(np.int64).reshape(nf, n)
    kernel(raw, planes_at, params_at, n, layers, words, fields, modes, order, work, out.view(word))
    return out


def unfilter_fields(raw: np.ndarray | bytes, fmt: str, width: int, height: int, layers: int,
                    source: str = "section") -> np.ndarray:
    """Inverse of fields_content: a section's stored bytes -> its GPU bytes (uint8, layer after layer), bit-exact;
    FormatError for anything that is not a well-formed fields1 content of exactly its size (format.md 5.2).

    All fields of a layer are decoded together in one (fields, slots) uint32 work array, so a layer costs a dozen
    numpy calls whatever its field count (on the 10-16k-splat tiles a client streams, per-call overhead is much of
    the time), every step in place in this thread's work arrays (no page faults of fresh arrays). Arithmetic
    modulo 2^32, then cut to each field's bits, equals the spec's arithmetic modulo 2^|T|; the running sums run on
    an int32 view, which numpy accumulates about 3x faster than uint32 (the same bits: both wrap modulo 2^32)."""
    raw = np.frombuffer(raw, np.uint8) if isinstance(raw, bytes | bytearray | memoryview) else raw
    kernel = _fields_kernel  # read once: another thread may hand it back meanwhile (decode_jit.warm_up)
    if kernel is not None:
        out = _kernel_unfilter(kernel, raw, fmt, width, height, layers)
        if out is not None:
            return out
    _check_geometry(fmt, width, height, layers, source)
    lay, plan, header_bytes = _fields1_header(raw, fmt, width, height, layers, source)
    n = width * height
    blocks = n // BLOCK_TEXELS
    expected, crossed, layer_plans = plan
    if raw.size != expected:
        raise FormatError(source, "fields1", f"content of {raw.size} bytes, expected {expected} for its modes")
    pos = header_bytes + 3 * blocks * crossed
    if crossed:
        # per predicted field and block: slope, and 64 * intercept + 32 (the prediction's rounding), as int32
        params = raw[header_bytes:pos].reshape(crossed, 3 * blocks)
        slopes = params[:, :blocks].view(np.int8).astype(np.int32)[:, :, None]
        biases = params[:, blocks:].view("<i2").astype(np.int32)
        biases <<= SLOPE_SHIFT
        biases += 1 << (SLOPE_SHIFT - 1)
        biases = biases[:, :, None]
    layer_bytes = n * lay.texel_bytes
    out = np.empty(layer_bytes * layers, np.uint8)
    work = _work_for(fmt, lay, n)
    z, spare, signed = work.z, work.spare, work.signed
    for layer, (delta_rows, pre_mask, cross_groups, post_mask) in enumerate(layer_plans):
        for start, size, fields, nb, z_rows, spare_rows, t_rows, u_rows in work.runs:
            planes = raw[pos + start:pos + start + size].reshape(fields, nb, n)
            if nb == 1:  # fields of up to 8 bits: no zigzag
                np.copyto(z_rows, planes[:, 0])
            elif nb == 2:
                _join_zigzag16(planes, z_rows, spare_rows, t_rows, u_rows)
            else:
                _join_zigzag(planes, z_rows, spare_rows)
        pos += n * lay.plane_bytes
        for rows in delta_rows:
            np.add.accumulate(signed[rows], axis=1, out=signed[rows])
        for rows in pre_mask:
            z[rows] &= lay.masks[rows, None]
        for ref, rows, first, count in cross_groups:
            # z[rows] += floor((slope * z[ref] + 64 * intercept + 32) / 64) per block, as _cross_prediction
            prediction = spare[:count].view(np.int32).reshape(count, blocks, BLOCK_TEXELS)
            np.multiply(signed[ref].reshape(blocks, BLOCK_TEXELS), slopes[first:first + count], out=prediction)
            prediction += biases[first:first + count]
            prediction >>= SLOPE_SHIFT
            z[rows] += spare[:count]
        for rows in post_mask:
            z[rows] &= lay.masks[rows, None]
        if lay.words > 1:  # norm8x4, norm16x4, f16x4, f32x4: one field a word, interleaved by a column copy a word
            for column, row in work.columns:
                column[...] = row
            texels = work.texels
        else:  # fields packed in one word
            if len(lay.bits) > 1:
                z <<= lay.shifts
                np.bitwise_or.reduce(z, axis=0, out=spare[0])
            else:
                spare[0] = z[0]
            texels = spare[0] if lay.word.itemsize == 4 else spare[0].astype(lay.word)
        texels.take(lay.inverse, out=out[layer * layer_bytes:(layer + 1) * layer_bytes].view(lay.texel), mode="clip")
    return out


def unfilter_texels(stored: np.ndarray, filter_name: str, fmt: str, width: int, height: int, layers: int,
                    source: str) -> list[np.ndarray]:
    """A texels section's stored bytes -> its GPU bytes, one uint8 array per layer. The filter name was checked
    against the format by the manifest; the stored size of shuffled sections too."""
    if filter_name == FIELDS1:
        texels = unfilter_fields(stored, fmt, width, height, layers, source)
    else:
        texels = stored
    unit = texels.size // layers
    parts = [texels[k * unit:(k + 1) * unit] for k in range(layers)]
    if filter_name in (FIELDS1, "none"):
        return parts
    element = int(filter_name[7:])
    return [unshuffle(p, element) for p in parts]


# ---------------------------------------------------------------------------------------------------------------
# Several sections at once


def unfilter_fields_many(raws: list[np.ndarray], fmt: str, dims: list[tuple[int, int]], layers: int,
                         sources: list[str]) -> list[list[np.ndarray]]:
    """unfilter_fields of several sections of one texel format, layer count and fields1 header (the same modes),
    of several payloads, as each section's layers: the same bytes, but their fields decoded together in one
    (fields, slots of them all) work array, so that the dozen numpy calls of a layer are made once for them all,
    not once a section.

    Why: on the LOD tree's small tiles (a few hundred splats) a section's decode is mostly the per-call overhead
    of those numpy calls (issue 32). What is left per section is building views of its byte planes and
    parameters: they are copied into the work array by one concatenation, and one gather over the slots of all
    sections puts every texel in its section's texture order. Each section is checked as unfilter_fields checks it
    (FormatError naming its source); the running sums restart at each section (the sum carried over from the
    sections before is subtracted, modulo 2^32 like the sums)."""
    if len(raws) == 1 or _fields_kernel is not None:  # the kernel's per-call cost is small: one call a section
        return [_layers_of(unfilter_fields(raw, fmt, w, h, layers, source), layers)
                for raw, (w, h), source in zip(raws, dims, sources, strict=True)]
    lay0 = None
    members = []  # (raw, n, layout, first byte plane position)
    plan0 = None
    for raw, (width, height), source in zip(raws, dims, sources, strict=True):
        _check_geometry(fmt, width, height, layers, source)
        lay, plan, header_bytes = _fields1_header(raw, fmt, width, height, layers, source)
        if raw.size != plan[0]:
            raise FormatError(source, "fields1", f"content of {raw.size} bytes, expected {plan[0]} for its modes")
        head = raw[:header_bytes].tobytes()
        if plan0 is None:
            plan0, lay0, head0 = plan, lay, head
        elif head != head0:
            raise ValueError("unfilter_fields_many takes sections of the same modes")
        members.append((raw, width * height, lay, header_bytes))
    _, crossed, layer_plans = plan0
    lay = lay0
    nf = len(lay.bits)
    counts = [n for _, n, _, _ in members]
    total = sum(counts)
    starts = np.cumsum([0] + counts)
    buf = _scratch("work", 10 * nf * total)
    z = buf[:4 * nf * total].view(np.uint32).reshape(nf, total)
    spare = buf[4 * nf * total:8 * nf * total].view(np.uint32).reshape(nf, total)
    signed = z.view(np.int32)
    t_all = buf[8 * nf * total:9 * nf * total].reshape(nf, total)
    u_all = buf[9 * nf * total:].reshape(nf, total)
    staging = _scratch("staging", nf * 4 * total)
    staging = {nb: staging[:nf * nb * total].reshape(nf, nb, total) for _, _, _, nb in lay.runs}
    blocks = total // BLOCK_TEXELS
    pos = [h for _, _, _, h in members]
    if crossed:
        slope_parts, bias_parts = [], []
        for k, (raw, n, _, h) in enumerate(members):
            b = n // BLOCK_TEXELS
            params = raw[h:h + 3 * b * crossed].reshape(crossed, 3 * b)
            slope_parts.append(params[:, :b].view(np.int8))
            bias_parts.append(params[:, b:].view("<i2"))
            pos[k] += 3 * b * crossed
        slopes = np.concatenate(slope_parts, axis=1)
        biases = np.concatenate(bias_parts, axis=1)
        slopes = slopes.astype(np.int32)[:, :, None]
        biases = biases.astype(np.int32)
        biases <<= SLOPE_SHIFT
        biases += 1 << (SLOPE_SHIFT - 1)
        biases = biases[:, :, None]
    texel_bytes = lay.texel_bytes
    # every section's texels in texture order: a gather over the slots of them all, each section's texel-to-slot
    # map moved to where its slots start
    inverse = np.concatenate([m[2].inverse for m in members])
    inverse += np.repeat(starts[:-1], counts)
    out = np.empty((layers, total * texel_bytes), np.uint8)
    ends = starts[1:-1] - 1  # last slot of every section but the last
    slots = spare.reshape(-1)[:total * texel_bytes // 4]
    columns = slots.view(lay.word).reshape(total, lay.words) if lay.words > 1 else None
    texels_all = slots.view(lay.texel)
    for layer, (delta_rows, pre_mask, cross_groups, post_mask) in enumerate(layer_plans):
        for run, (first, end, _, nb) in enumerate(lay.runs):
            fields = end - first
            stage = staging[nb][:fields]
            parts = []
            for k, (raw, n, member_lay, _) in enumerate(members):
                at = pos[k] + member_lay.runs[run][2]
                parts.append(raw[at:at + fields * nb * n].reshape(fields, nb, n))
            np.concatenate(parts, axis=2, out=stage)
            z_rows, spare_rows = z[first:end], spare[first:end]
            if nb == 1:
                np.copyto(z_rows, stage[:, 0])
            elif nb == 2:
                _join_zigzag16(stage, z_rows, spare_rows, t_all[first:end], u_all[first:end])
            else:
                _join_zigzag(stage, z_rows, spare_rows)
        for k, (_, n, _, _) in enumerate(members):
            pos[k] += n * lay.plane_bytes
        for rows in delta_rows:
            s = signed[rows]
            np.add.accumulate(s, axis=1, out=s)
            if len(ends):
                carried = s[:, ends]  # each section's running sum, carried into the next ones
                carried = np.repeat(carried, np.diff(starts[1:]), axis=1)
                s[:, starts[1]:] -= carried
        for rows in pre_mask:
            z[rows] &= lay.masks[rows, None]
        for ref, rows, first_param, count in cross_groups:
            prediction = spare[:count].view(np.int32).reshape(count, blocks, BLOCK_TEXELS)
            np.multiply(signed[ref].reshape(blocks, BLOCK_TEXELS), slopes[first_param:first_param + count],
                        out=prediction)
            prediction += biases[first_param:first_param + count]
            prediction >>= SLOPE_SHIFT
            z[rows] += spare[:count]
        for rows in post_mask:
            z[rows] &= lay.masks[rows, None]
        if lay.words > 1:
            for w in range(lay.words):
                columns[:, w] = z[w]
            texels = texels_all
        else:
            if nf > 1:
                z <<= lay.shifts
                np.bitwise_or.reduce(z, axis=0, out=spare[0])
            else:
                spare[0] = z[0]
            texels = spare[0] if lay.word.itemsize == 4 else spare[0].astype(lay.word)
        texels.take(inverse, out=out[layer].view(lay.texel), mode="clip")
    return [[out[layer, starts[k] * texel_bytes:starts[k + 1] * texel_bytes] for layer in range(layers)]
            for k in range(len(members))]


def _layers_of(texels: np.ndarray, layers: int) -> list[np.ndarray]:
    unit = texels.size // layers
    return [texels[k * unit:(k + 1) * unit] for k in range(layers)]


_scratch_local = threading.local()


def _scratch(name: str, size: int) -> np.ndarray:
    """`size` bytes of this thread's scratch buffer `name` (contents undefined), kept between calls up to
    KEEP_WORK_BYTES for the reason _work_for gives (fresh arrays of this size fault their pages in)."""
    kept = getattr(_scratch_local, "buffers", None)
    if kept is None:
        kept = _scratch_local.buffers = {}
    buf = kept.get(name)
    if buf is None or buf.size < size:
        if size > KEEP_WORK_BYTES:
            return np.empty(size, np.uint8)
        buf = kept[name] = np.empty(min(KEEP_WORK_BYTES, 1 << max(16, (size - 1).bit_length())), np.uint8)
    return buf[:size]


_slabs = threading.local()
# The whole kernel's outputs kept per thread for reuse (texel_slab), up to this many bytes in all; sizes rounded up to
# SLAB_STEP so that a run's slab fits the next pass's run of about its size.
KEEP_SLAB_BYTES = 1 << 25
KEEP_SLABS = 32  # and at most this many (each call looks at every one)
SLAB_STEP = 1 << 16
SLAB_MIN_BYTES = 1 << 17  # smaller outputs a fresh array as before (glibc's default mmap threshold: its heap's)


def _free_slab_refs() -> int:
    """A slab's reference count, as _slab_free reads it, when only its list holds it (the interpreter's own count of
    an argument and a subscript's result differ between Python versions: measured, not assumed)."""
    probe = [np.empty(0)]
    return sys.getrefcount(probe[0])


_FREE_SLAB_REFS = _free_slab_refs()


def _slab_free(slabs: list[np.ndarray], i: int) -> bool:
    """Whether slabs[i] is held by its list alone: no array viewing it is left (a view's base is the slab itself:
    numpy points a view of a view at the array that owns the memory), so its bytes may be written again."""
    return sys.getrefcount(slabs[i]) <= _FREE_SLAB_REFS


def texel_slab(size: int) -> np.ndarray:
    """`size` bytes for the whole kernel's texels (contents undefined): a view of the smallest of this thread's kept
    slabs that fits it (at most twice its size) and that no plane views any more, else of a new slab kept while this
    thread's slabs are at most KEEP_SLABS and take at most KEEP_SLAB_BYTES (slabs nothing views are let go, oldest
    first, to make room), else a fresh array, as before; below SLAB_MIN_BYTES a fresh array. Planes returned earlier
    keep their slab, and their bytes, for as long as they are held: a slab is handed out again only once nothing
    views it.

    Why: a group's texels were a fresh array a run (about 1 MB; very-high's pass on the LOD tree 14 MB), and whether
    malloc hands back pages already mapped or new ones that fault in on the kernel's first write depends on what the
    process freed before (glibc's mmap threshold and heap trimming): on this VM a `verified` pass of very-high's LOD
    tree took 12.5 ms in a process whose runs faulted (about 3,000 faults a pass, zstd's joined frames included)
    and 8.3 in one whose runs did not, with the same code (issue 32: r23's host read very-high at 9.8-10.0 M
    splats/s; BENCHMARKS.md, "Decode speed", vhdecode32). Kept slabs make that the same in every process."""
    if size < SLAB_MIN_BYTES:
        return np.empty(size, np.uint8)
    slabs = getattr(_slabs, "kept", None)
    if slabs is None:
        slabs = _slabs.kept = []
    best = -1
    fit = 2 * size + SLAB_STEP  # the most a slab may hold for this size
    free, refs = _FREE_SLAB_REFS, sys.getrefcount
    for i in range(len(slabs)):
        have = slabs[i].size
        if size <= have < fit and refs(slabs[i]) <= free:  # _slab_free, inline (a run's call, a dozen slabs)
            best, fit = i, have
    if best >= 0:
        return slabs[best][:size]
    want = max(SLAB_STEP, size + -size % SLAB_STEP)
    held = sum(s.size for s in slabs)
    i = 0
    while (held + want > KEEP_SLAB_BYTES or len(slabs) >= KEEP_SLABS) and i < len(slabs):
        if _slab_free(slabs, i):  # room: let go of slabs nothing views, oldest first
            held -= slabs[i].size
            del slabs[i]
        else:
            i += 1
    if held + want > KEEP_SLAB_BYTES or len(slabs) >= KEEP_SLABS:
        return np.empty(size, np.uint8)
    slabs.append(np.empty(want, np.uint8))
    return slabs[-1][:size]


def unshuffle_many(units: list[np.ndarray], element: int) -> list[np.ndarray]:
    """unshuffle of several units of one element size, the same bytes in fresh arrays (views of one array), in a
    few numpy calls for them all plus one copy a unit (small units' per-call overhead: issue 32)."""
    if element <= 1 or any(u.size % element for u in units):
        return [unshuffle(u, element) for u in units]
    sizes = [u.size // element for u in units]
    total = sum(sizes)
    out = []
    kernel = _unshuffle_kernel  # read once, as unshuffle's
    if kernel is not None:  # one call a unit into one array
        dst = np.empty(total * element, np.uint8)
        at = 0
        for u, m in zip(units, sizes, strict=True):
            part = dst[at:at + m * element]
            kernel(u, element, part)
            out.append(part)
            at += m * element
        return out
    if element in (2, 4) and total * element > SMALL_UNSHUFFLE_BYTES:
        stage = _scratch("unshuffle", total * element).reshape(element, total)
        at = 0
        for u, m in zip(units, sizes, strict=True):
            stage[:, at:at + m] = u.reshape(element, m)
            at += m
        word = np.uint16 if element == 2 else np.uint32
        z = stage[element - 1].astype(word)
        for k in range(element - 2, -1, -1):
            z <<= word(8)
            z |= stage[k]
        at = 0
        for m in sizes:
            out.append(z[at:at + m].view(np.uint8))
            at += m
        return out
    dst = np.empty((total, element), np.uint8)
    at = 0
    for u, m in zip(units, sizes, strict=True):
        dst[at:at + m] = u.reshape(element, m).T
        out.append(dst[at:at + m].reshape(-1))
        at += m
    return out


# ---------------------------------------------------------------------------------------------------------------
# Compiled batch kernels: one call for many sections (handed in by a shell, like the kernels above)


_batch_kernels: tuple = (None, None)  # see use_batch_kernels


def use_batch_kernels(fields_many, unshuffle_many) -> tuple:
    """Decode many fields1 sections, and undo the byte shuffle of many units, of one decompressed buffer in one call
    each (None, None: not batched); returns the pair it replaces. Called as fields_many(raw, table, words, fields,
    modes, orders, work, out): per section (a row of `table`: where its byte planes and its parameters start in
    `raw`, its slots, where its slot_to_texel starts in `orders`, where its texels start in `out` and how many words
    they are, its row of `modes`) what use_fields_kernel's kernel is called with; and unshuffle_many(raw, table,
    element, out): per unit (a row: where it starts in `raw`, its element count) its bytes unshuffled one unit after
    the other into `out`.

    Why: with the kernels a small tile's section decodes in a few microseconds, and what was left of a payload's
    decode in a whole group was the Python and the dispatch around each kernel call (about 60 us a payload on a
    quiet core: issue 32, BENCHMARKS.md "Decode speed"). A batch pays them once a plane."""
    global _batch_kernels
    previous, _batch_kernels = _batch_kernels, (fields_many, unshuffle_many)
    return previous


def batch_kernels() -> tuple:
    """The pair use_batch_kernels handed in, or (None, None)."""
    return _batch_kernels


def unfilter_fields_at(raw: np.ndarray, fmt: str, layers: int,
                       sections: list[tuple[int, int, int, int]]) -> list[np.ndarray | None] | None:
    """unfilter_fields of several fields1 sections of one texel format and layer count lying in `raw` (one
    decompressed buffer), given as (offset, size, width, height), by one call of the batch kernel: each section's
    texels (views of one array), None for a section that is not well-formed (its caller decodes it with
    unfilter_fields, which raises FormatError naming it). None when there is no batch kernel. Each section is checked
    as _kernel_unfilter checks it, from the same cached lookup per (geometry, header)."""
    kernel = _batch_kernels[0]
    if kernel is None or fmt not in FIELD_LAYOUTS or type(layers) is not int or layers < 1:
        return None
    header = 1 + len(FIELD_LAYOUTS[fmt][2]) * FIELD_LAYOUTS[fmt][1] * layers
    got: list = [None] * len(sections)
    rows, take = [], []
    orders: dict[tuple[int, int], int] = {}
    order_parts: list[np.ndarray] = []
    modes: dict[bytes, int] = {}
    mode_parts: list[np.ndarray] = []
    out_words = most = order_words = 0
    plan = None
    for k, (at, size, width, height) in enumerate(sections):
        head = raw[at:at + header].tobytes()
        plan = _kernel_plan(fmt, width, height, layers, head)
        if plan is None or size != plan[0]:
            continue
        _, params_at, planes_at, n, words, fields, table, word, order, _, out_bytes = plan
        o = orders.get((width, height))
        if o is None:
            o = orders[width, height] = order_words
            order_parts.append(order)
            order_words += n
        m = modes.get(head)
        if m is None:
            m = modes[head] = len(mode_parts)
            mode_parts.append(table)
        length = out_bytes // word.itemsize
        rows.append((at + planes_at, at + params_at, n, o, out_words, length, m))
        take.append(k)
        out_words += length
        most = max(most, n)
    if not rows:
        return got
    _, _, _, _, words, fields, _, word, _, nf, _ = plan
    out = np.empty(out_words * word.itemsize, np.uint8)
    work = _scratch("kernel", 8 * nf * most).view(np.int64).reshape(nf, most)
    # `orders` always a fresh (writable) array, like `modes`: one argument type per word type, so the compiled
    # specialisations warm_up loads are the ones every call takes
    kernel(raw, np.array(rows, np.int64), words, fields, np.stack(mode_parts), np.concatenate(order_parts), work,
           out.view(word))
    size = word.itemsize
    for k, (_, _, _, _, first, length, _) in zip(take, rows, strict=True):
        got[k] = out[first * size:(first + length) * size]
    return got


def unshuffle_at(raw: np.ndarray, units: list[tuple[int, int]], element: int) -> list[np.ndarray] | None:
    """unshuffle of several units lying in `raw`, given as (offset, size), by one call of the batch kernel: their
    bytes as views of one array, one unit after the other (None when there is no batch kernel, or a unit's size is
    not a multiple of `element`: unshuffle then handles each)."""
    kernel = _batch_kernels[1]
    if kernel is None or element <= 1 or any(size % element for _, size in units):
        return None
    out = np.empty(sum(size for _, size in units), np.uint8)
    kernel(raw, np.array([(at, size // element) for at, size in units], np.int64).reshape(-1, 2), element, out)
    views, first = [], 0
    for _, size in units:
        views.append(out[first:first + size])
        first += size
    return views


# ---------------------------------------------------------------------------------------------------------------
# A whole payload (or a whole group's payloads) in one compiled call (handed in by a shell, like the kernels above)


_whole_kernel = None  # see use_whole_kernel
# the last whole kernel handed in: run_whole's call, planned by a caller that saw one, runs on it even where another
# thread handed it back meanwhile (decode_jit.warm_up hands each kernel in for its calls and back)
_whole_kernel_planned = None


def use_whole_kernel(kernel) -> object:
    """Decode every fields1 section, of any format, and undo the byte shuffle of every unit of one decompressed
    buffer in one call (None: not so); returns the one it replaces. Called as kernel(raw, rows, fields, modes, orders,
    work, out8, out16, out32, outf32, units, spans, bounds) -> status: per fields1 section a row of `rows` (where its
    byte planes and its parameters start in `raw`, its slots, where its slot_to_texel starts in `orders`, where its
    texels start and how many words they are in the out view of its word size, where its columns of `fields` start
    and how many, where its columns of `modes` start and how many, words a texel, bytes a word, the check of its
    texels), which is use_fields_kernel's call for it; per unit a row of `units` (where it starts in `raw`, its
    element count, its element size, where its bytes go in out8, the check of its values); per span of ranges to
    check a row of `spans`. out8, out16, out32 and outf32 are views of one buffer; the checks, `spans` and `bounds`
    are run_whole's (CHECK_*); the status: the CHECK_FAILED_* bits of the checks that failed.

    Why: a decode thread holds the interpreter lock for the Python between its compiled calls and must take it back
    after each one (issue 38: the frame thread waits for it; issue 32: that Python is most of a small payload's
    decode). With this kernel a payload's, or a group's, decode is two calls that release the lock (zstd, then this),
    with one stretch of Python before and one after (unfilter_whole)."""
    global _whole_kernel, _whole_kernel_planned
    previous, _whole_kernel = _whole_kernel, kernel
    if kernel is not None:
        _whole_kernel_planned = kernel
    return previous


def whole_kernel() -> object:
    """The kernel use_whole_kernel handed in, or None."""
    return _whole_kernel


@functools.lru_cache(maxsize=1024)
def _whole_tables(keys: tuple) -> tuple:
    """The whole kernel's `fields`, `modes` and `orders` for sections of these (format, layers, header, width,
    height), each table once, and per section (its first column of fields, of modes, how many of modes, where its
    slot_to_texel starts in orders, its texels' check: FLOAT_CHECKS), as a tuple of tuples and as an int64 array of 5
    columns. Cached: a scene's
    payloads repeat a few combinations of formats, modes and geometries, and concatenating the tables was a fifth of
    a small payload's Python around the kernel. The arrays are writable and C-ordered (the one argument type
    decode_jit.warm_up compiles) and never written."""
    field_parts, mode_parts, order_parts, columns = [], [], [], []
    fields_at: dict[str, int] = {}
    modes_at: dict[tuple, int] = {}
    orders_at: dict[tuple[int, int], int] = {}
    field_cols = mode_cols = order_words = 0
    for fmt, layers, head, width, height in keys:
        _, fields, table, _ = _kernel_args(fmt, layers, head)
        f = fields_at.get(fmt)
        if f is None:
            f = fields_at[fmt] = field_cols
            field_parts.append(fields)
            field_cols += fields.shape[1]
        m = modes_at.get((fmt, layers, head))
        if m is None:
            m = modes_at[fmt, layers, head] = mode_cols
            mode_parts.append(table)
            mode_cols += table.shape[1]
        o = orders_at.get((width, height))
        if o is None:
            o = orders_at[width, height] = order_words
            order_parts.append(slot_to_texel(width, height))
            order_words += width * height
        columns.append((f, m, table.shape[1], o, FLOAT_CHECKS.get(fmt, CHECK_NONE)))
    return (np.concatenate(field_parts, axis=1) if field_parts else np.zeros((5, 0), np.int64),
            np.concatenate(mode_parts, axis=1) if mode_parts else np.zeros((3, 0), np.int64),
            np.concatenate(order_parts) if order_parts else np.zeros(0, np.int64), tuple(columns),
            np.array(columns, np.int64).reshape(-1, 5))


class _Fields1Rows(dict):
    """FIELDS1_ROWS' kind: a dict that fills in a missing key's row (__missing__) and empties itself at
    _WHOLE_ROWS_MAX keys (a scene repeats a few combinations; a hostile stream of headers cannot grow it)."""

    def __missing__(self, key: tuple) -> tuple | None:
        fmt, layers, head, width, height = key
        plan = _kernel_plan(fmt, width, height, layers, head)
        row = None
        if plan is not None:
            expected, params_at, planes_at, n, words, _, _, word, _, nf, nbytes = plan
            row = (expected, planes_at, params_at, n, nbytes, nf, words, word.itemsize)
        if len(self) >= _WHOLE_ROWS_MAX:
            self.clear()
        self[key] = row
        return row


# A fields1 section's row for the whole kernel by its (format, layers, header, width, height): (content size, where
# its byte planes start, where its parameters start, slots, texel bytes, fields, words a texel, bytes a word) from
# _kernel_plan, None where it is not well-formed (its decoder, unfilter_fields, then refuses it naming it). Looked up
# as FIELDS1_ROWS[key], which plans a key not seen before. Its readers: unfilter_whole, and container's planner of a
# group's planes, which plans the whole kernel's call itself. Why one subscript: a small payload's sections repeat a
# few combinations, and an lru_cache call with five arguments and a second lookup for the tables' index cost about a
# microsecond a section more (issue 32).
FIELDS1_ROWS: dict[tuple, tuple | None] = _Fields1Rows()
_WHOLE_ROWS_MAX = 4096


def unfilter_whole(raw: np.ndarray, sections: list[tuple[str, int, int, int, int, int]],
                   units: list[tuple[int, int, int]]) -> tuple[np.ndarray, list, list[int]] | None:
    """unfilter_fields of every fields1 section in `sections` ((format, layers, offset, size, width, height), lying in
    `raw`, one decompressed buffer) and unshuffle of every unit in `units` ((offset, size, element)) by one call of
    the whole kernel (use_whole_kernel): (out, where each section's texels lie in out as (offset, size), or None for a
    section that is not well-formed, which its caller decodes with unfilter_fields to raise FormatError naming it;
    where each unit's bytes lie in out). Sections' texels start at 16-byte offsets; the units follow in the order given,
    each at an offset aligned to its element (2, 4 or 8 bytes), so that units of one element size given in a row (a
    plane's ranges) lie in a row.
    None when there is no whole kernel. Each section is checked as _kernel_unfilter checks it, from the same cached
    lookup per (geometry, header); a unit whose size is not a multiple of its element is copied as it is, as unshuffle
    returns it."""
    kernel = _whole_kernel
    if kernel is None:
        return None
    # A group of small payloads has hundreds of sections, so the Python per section is kept to a cached lookup and
    # one flat row (issue 32: it was 11 us a payload): the row's table columns are filled in by numpy afterwards,
    # from each distinct combination's (a scene repeats a few), not per section.
    got: list = []
    flat: list[int] = []  # per section: 9 ints (_WHOLE_COLUMNS' first nine), the combination's index last but five
    index: dict[tuple, int] = {}  # (format, layers, header, width, height) -> its index in the tables' key
    out_bytes = most_n = most_f = 0
    header_of = FIELDS1_HEADER_BYTES
    rows_of = FIELDS1_ROWS
    view = raw.data  # the header bytes through a memoryview: a third of a numpy slice's cost
    for fmt, layers, at, size, width, height in sections:
        per_layer = header_of.get(fmt)
        if per_layer is None or type(layers) is not int or layers < 1:
            got.append(None)
            continue
        key = (fmt, layers, view[at:at + 1 + per_layer * layers].tobytes(), width, height)
        row = rows_of[key]
        if row is None or size != row[0]:
            got.append(None)
            continue
        _, planes_at, params_at, n, nbytes, nf, words, size_of = row
        out_bytes += -out_bytes % 16
        u = index.get(key)
        if u is None:
            u = index[key] = len(index)
        flat += (at + planes_at, at + params_at, n, out_bytes // size_of, nbytes // size_of, nf, words, size_of, u)
        got.append((out_bytes, nbytes))
        out_bytes += nbytes
        if n > most_n:
            most_n = n
        if nf > most_f:
            most_f = nf
    out_bytes += -out_bytes % 16
    unit_rows: list[int] = []
    unit_at = []
    for at, size, element in units:
        if element <= 1 or size % element:
            element = 1
        if element in (2, 4, 8):  # aligned for views of its elements (a plane's ranges still lie in a row)
            out_bytes += -out_bytes % element
        unit_rows += (at, size // element, element, out_bytes, CHECK_NONE)
        unit_at.append(out_bytes)
        out_bytes += size
    out, _ = run_whole(raw, flat, tuple(index), unit_rows, out_bytes, most_n, most_f)  # its callers check the values
    return out, got, unit_at


def run_whole(raw: np.ndarray, flat: list[int], keys: tuple, unit_rows: list[int], out_bytes: int, most_n: int,
              most_f: int, span_rows: list[int] | None = None, bounds: np.ndarray | None = None
              ) -> tuple[np.ndarray, int]:
    """The whole kernel's call (use_whole_kernel) over `raw` for sections and units already planned: `flat` 9 ints a
    fields1 section (where its byte planes start, where its parameters start, slots, where its texels start in the
    out view of its word size, how many words, fields, words a texel, bytes a word, the index of its key in `keys`),
    `keys` the distinct (format, layers, header, width, height) of them, `unit_rows` 5 ints a unit (where it starts,
    its element count, its element size, where its bytes go in out, the check of its values: CHECK_NONE, CHECK_F32
    or CHECK_F16), `span_rows` 4 ints a span of ranges to check after the units (where it starts in out, its bytes,
    the values of a chunk's minimum, its CHECK_RANGES code), `bounds` a range check's (low, high, bytes a value: 4
    float32, 2 float16) by its code (float64, (codes, 3); None: no range checks); returns (`out`, out_bytes rounded up
    to 16, which the kernel wrote, and the kernel's status: the CHECK_FAILED_* bits of the checks that failed, 0 when
    every one passed).
    `most_n` and `most_f`: the most slots and fields of a section (the work array's shape).
    Its callers: unfilter_whole, and container._unpack_group, which plans a group's call with its planes'."""
    fields, modes, orders, columns, column_array = _whole_tables(keys)
    # columns per combination: (first column of fields, of modes, how many of modes, where its orders start, its
    # texels' check), as a tuple and as an array (cached with the tables: not converted again a call)
    if len(flat) > 9 * _FEW_ROWS:  # a group's hundreds of sections: by numpy, a fixed cost of a few calls
        part = np.fromiter(flat, np.int64, len(flat)).reshape(-1, 9)  # fromiter: a fifth less than np.array here
        rows = np.concatenate([part, column_array[part[:, 8]]], axis=1)[:, _WHOLE_COLUMNS]
    else:  # a payload's few: a loop costs less than those calls
        row_list: list[int] = []
        for i in range(0, len(flat), 9):
            planes_at, params_at, n, first, length, nf, words, size_of, u = flat[i:i + 9]
            f, m, nm, o, check = columns[u]
            row_list += (planes_at, params_at, n, o, first, length, f, nf, m, nm, words, size_of, check)
        rows = np.array(row_list, np.int64).reshape(-1, 13)
    return _call_whole(raw, rows, fields, modes, orders, most_f, most_n, out_bytes, unit_rows, span_rows, bounds)


def run_whole_at(raw: np.ndarray, flat: list[int], keys: tuple, unit_rows: list[int], out_bytes: int,
                 span_rows: list[int] | None = None, bounds: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """run_whole for fields1 sections given as 3 ints each in `flat`: where its content starts in `raw`, where its
    texels start in out (bytes, a multiple of its word size), the index of its key in `keys` (whose FIELDS1_ROWS row,
    well-formed, gives the rest of its row: numpy takes it from each distinct key's, not the caller a section; the
    work array's shape from them too). The other arguments and what it returns: run_whole's.

    Why: container's planner of a group's call wrote 9 ints a section, 6 of them its key's (issue 32, vhdec33: the
    Python around the kernel, 10-13 us a small payload, was the largest part of a pass but zstd)."""
    fields, modes, orders, _, _ = _whole_tables(keys)
    template, most_n, most_f = _whole_key_rows(keys)
    part = np.array(flat, np.int64).reshape(-1, 3)
    rows = template[part[:, 2]]  # each section's key's row, less where the section lies (a copy: filled in below)
    rows[:, 0] += part[:, 0]
    rows[:, 1] += part[:, 0]
    rows[:, 4] = part[:, 1] // rows[:, 11]
    return _call_whole(raw, rows, fields, modes, orders, most_f, most_n, out_bytes, unit_rows, span_rows, bounds)


def _call_whole(raw: np.ndarray, rows: np.ndarray, fields: np.ndarray, modes: np.ndarray, orders: np.ndarray,
                most_f: int, most_n: int, out_bytes: int, unit_rows: list[int], span_rows: list[int] | None,
                bounds: np.ndarray | None) -> tuple[np.ndarray, int]:
    """The whole kernel's call for run_whole and run_whole_at, once their rows are built: the texel slab, the
    scratch, the unit and span rows as arrays. Returns (out, status) as they do."""
    out = texel_slab(out_bytes + -out_bytes % 16)
    work = _scratch("kernel", 8 * most_f * most_n).view(np.int64).reshape(most_f, most_n)
    kernel = _whole_kernel or _whole_kernel_planned
    status = kernel(raw, rows, fields, modes, orders, work, out, out.view(np.uint16), out.view(np.uint32),
                    out.view(np.float32), np.array(unit_rows, np.int64).reshape(-1, 5),
                    np.array(span_rows or (), np.int64).reshape(-1, 4), _NO_BOUNDS if bounds is None else bounds)
    return out, int(status)


@functools.lru_cache(maxsize=1024)
def _whole_key_rows(keys: tuple) -> tuple[np.ndarray, int, int]:
    """Each key's whole kernel row (run_whole's 13 columns) for a section at 0 in raw and in out, from FIELDS1_ROWS
    and _whole_tables' columns, as an int64 array (len(keys), 13); and the most slots and fields of them (run_whole's
    most_n, most_f)."""
    rows = [FIELDS1_ROWS[key] for key in keys]
    columns = _whole_tables(keys)[3]
    table = np.array([(planes_at, params_at, n, o, 0, nbytes // size_of, f, nf, m, nm, words, size_of, check)
                      for (_, planes_at, params_at, n, nbytes, nf, words, size_of), (f, m, nm, o, check)
                      in zip(rows, columns, strict=True)], np.int64).reshape(-1, 13)
    return table, max((r[3] for r in rows), default=0), max((r[5] for r in rows), default=0)


# The whole kernel's row of a section from unfilter_whole's 9 flat ints and its combination's 5 columns: (planes at,
# parameters at, slots, orders at, out at, out words, fields at, fields, modes at, modes, words a texel, word bytes,
# its texels' check)
_WHOLE_COLUMNS = np.array([0, 1, 2, 12, 3, 4, 9, 5, 10, 11, 6, 7, 13])

# The whole kernel's checks of the values it writes (a row's, a unit's or a span's CHECK_ code), which its caller
# would otherwise make with numpy after the call (issue 32: a float plane's max and a range plane's check, one call a
# plane a run, were about 1 ms of very-high's 13 ms pass on the LOD tree): CHECK_NONE none; CHECK_F32 / CHECK_F16
# float texels (format.md 4.2: t in [0, 1]: each word's bits at most those of 1.0, or -0.0's); a span's code from
# CHECK_RANGES on ranges (format.md 4.3, 4.8: a plane's range sections in a row, one span a plane, in chunks of `k`
# minimums then `k` maximums: every value finite, each minimum at most its maximum, all inside bounds[code][:2];
# float32 or float16 values by bounds[code][2], their bytes). A check that fails sets its CHECK_FAILED_ bit in the
# kernel's status, and the caller then checks as it does without the kernel, which names the payload and section;
# so the kernel's checks are a fast yes, never the refusal itself. Values the kernel cannot check as asked (not whole
# values, not aligned to them, not whole chunks, none) fail their check.
CHECK_NONE, CHECK_F32, CHECK_F16 = 0, 1, 2
CHECK_RANGES = 3  # range checks: codes from here, one per (low, high) of the caller's bounds
CHECK_FAILED_FLOATS, CHECK_FAILED_RANGES = 1, 2
FLOAT_CHECKS = {"f32x4": CHECK_F32, "f16x4": CHECK_F16}
_NO_BOUNDS = np.zeros((CHECK_RANGES, 3), np.float64)
_FEW_ROWS = 24  # sections up to which unfilter_whole builds the rows in Python
# A fields1 format's header bytes per layer (its modes), without the first byte
FIELDS1_HEADER_BYTES = {fmt: len(layout[2]) * layout[1] for fmt, layout in FIELD_LAYOUTS.items()}
