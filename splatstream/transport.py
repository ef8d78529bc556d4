"""Transport coding of payload sections, separate from the GPU layout (prototype; format_spec/transport_draft.md).

What a payload stores and sends may differ from the texel bytes the GPU holds, as long as decoding gives back those
bytes exactly. A texels section is coded one of two ways:

* ``shuffle-zstd``: today's filter (byte shuffle by the format's element, one unit per layer) and one zstd frame.
* ``fields-zstd``: every texel is split into its fields (norm11 -> 11, 10 and 11-bit integers, norm565 -> 5/6/5,
  f16x4 -> four 16-bit words, ...), each field is laid out in **slot order** (16x16 blocks in row-major block
  order, Morton order inside a block: the splat order of format.md 4.1) and predicted: optionally from another
  field of the same texel through a per-block linear model (colour R and B from G, SH coefficient R and B from G:
  the channels of one value are strongly correlated, while per-chunk normalisation leaves little between chunks),
  then optionally from the previous slot (delta). Residuals modulo 2^bits are zigzag-mapped and stored as byte
  planes, and all of it goes through one zstd frame.

The encoder measures both and keeps the smaller. Decoding is numpy-vectorised (cumulative sums, shifts, one
gather per layer back to texture order) and runs well above 10 M splats/s on one core for the base planes
(bench/transport/bench_decode.py). Range sections and BC blocks use ``shuffle-zstd`` (element 1 for BC).

Pure functions; every malformed stream raises FormatError, and no decode allocates more than the section's size
(plus the small per-block parameters) allows.
"""
from __future__ import annotations

import functools

import numpy as np
import zstandard

from .errors import FormatError
from .texformats import FORMATS, blob_size, shuffle_bytes, unshuffle_bytes

BLOCK = 16
BLOCK_TEXELS = BLOCK * BLOCK
FIELDS_VERSION = 1
SLOPE_SHIFT = 6  # per-block slopes are in units of 1/64
SLOPE_MIN, SLOPE_MAX = -128, 127
INTERCEPT_MIN, INTERCEPT_MAX = -32768, 32767
MODE_DELTA = 0x01
MODE_RESERVED = 0x0E
# Encoder: fields are measured on about this many slots (whole blocks, spread over the section) to pick modes.
SAMPLE_SLOTS = 1 << 16
CODINGS = ("shuffle-zstd", "fields-zstd")

# Field layout of each splittable texel format: (texel word dtype, [(shift, bits)] low bits first).
FIELD_LAYOUTS: dict[str, tuple[str, tuple[tuple[int, int], ...]]] = {
    "f32x4": ("<u4", ((0, 32),)),  # one field per f32 word (4 words per texel, see _fields_per_texel)
    "f16x4": ("<u2", ((0, 16),)),
    "norm10_2": ("<u4", ((0, 10), (10, 10), (20, 10), (30, 2))),
    "norm11": ("<u4", ((0, 11), (11, 10), (21, 11))),
    "norm8x4": ("<u1", ((0, 8),)),
    "norm565": ("<u2", ((0, 5), (5, 6), (11, 5))),
    "index16": ("<u2", ((0, 16),)),
}
# Formats whose texel is several words of one field each (f32x4 = 4 x u32, f16x4 = 4 x u16, norm8x4 = 4 x u8).
WORDS_PER_TEXEL = {"f32x4": 4, "f16x4": 4, "norm8x4": 4}


def _fields(fmt: str) -> list[int]:
    """Bit width of each field of one texel, in field order."""
    _, layout = FIELD_LAYOUTS[fmt]
    return [bits for _, bits in layout] * WORDS_PER_TEXEL.get(fmt, 1)


@functools.lru_cache(maxsize=32)
def slot_to_texel(width: int, height: int) -> np.ndarray:
    """Texel index (y * width + x) of every slot: blocks in row-major block order, Morton order inside a block."""
    j = np.arange(BLOCK_TEXELS, dtype=np.int64)
    bx = (j & 1) | ((j >> 1) & 2) | ((j >> 2) & 4) | ((j >> 3) & 8)
    by = ((j >> 1) & 1) | ((j >> 2) & 2) | ((j >> 3) & 4) | ((j >> 4) & 8)
    cols, rows = width // BLOCK, height // BLOCK
    b = np.arange(cols * rows, dtype=np.int64)
    x0, y0 = (b % cols) * BLOCK, (b // cols) * BLOCK
    index = ((y0[:, None] + by[None, :]) * width + x0[:, None] + bx[None, :]).reshape(-1)
    index.setflags(write=False)
    return index


def _check_geometry(fmt: str, width: int, height: int, layers: int, source: str) -> None:
    if fmt not in FORMATS:
        raise FormatError(source, "format", f"unknown texel format {fmt!r}")
    if not (isinstance(width, int) and isinstance(height, int) and isinstance(layers, int) and width > 0
            and height > 0 and layers > 0 and width % BLOCK == 0 and height % BLOCK == 0
            and width <= 2048 and height <= 16384 and layers <= 64):
        raise FormatError(source, "texture", f"{width}x{height}x{layers} is not a texture of 16x16 blocks "
                          "(width <= 2048, height <= 16384, 1..64 layers)")


# ---------------------------------------------------------------------------------------------------------------
# Field split and join (one layer)


def split_layer(layer: np.ndarray, fmt: str, width: int, height: int) -> list[np.ndarray]:
    """One layer's texel bytes -> one array per field, values in slot order (uint16, or uint32 for 32-bit)."""
    dtype, layout = FIELD_LAYOUTS[fmt]
    words = WORDS_PER_TEXEL.get(fmt, 1)
    word = layer.view(dtype).reshape(width * height, words)[slot_to_texel(width, height)]
    out = []
    for w in range(words):
        column = word[:, w]
        for shift, bits in layout:
            if bits == 32:
                out.append(np.ascontiguousarray(column, np.uint32))
            else:
                out.append(((column >> shift) & ((1 << bits) - 1)).astype(np.uint16))
    return out


def join_layer(fields: list[np.ndarray], fmt: str, width: int, height: int) -> np.ndarray:
    """Inverse of split_layer: field arrays in slot order -> the layer's texel bytes (texture order)."""
    dtype, layout = FIELD_LAYOUTS[fmt]
    words = WORDS_PER_TEXEL.get(fmt, 1)
    n = width * height
    index = slot_to_texel(width, height)
    word_dtype = np.dtype(dtype)
    if len(layout) == 1:
        # one field per word: interleave the words of a texel in slot order, then one scatter of whole texels
        slots = np.empty((n, words), word_dtype)
        for k, f in enumerate(fields):
            slots[:, k] = f
        out = np.empty((n, words), word_dtype)
        if words * word_dtype.itemsize in (4, 8):
            row = np.dtype(f"<u{words * word_dtype.itemsize}")
            out.view(row).reshape(n)[index] = slots.view(row).reshape(n)
        else:
            out[index] = slots
        return out.reshape(-1).view(np.uint8)
    acc = fields[0].astype(word_dtype)  # a copy: it is written to below
    for field, (shift, _) in zip(fields[1:], layout[1:], strict=True):
        acc |= field.astype(word_dtype, copy=False) << word_dtype.type(shift)
    out = np.empty(n, word_dtype)
    out[index] = acc
    return out.view(np.uint8)


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


def _unzigzag(z: np.ndarray) -> np.ndarray:
    """Zigzag codes -> residuals modulo the dtype's size (the caller masks to the field's bits)."""
    t = z.dtype.type
    return (z >> t(1)) ^ np.negative(z & t(1))  # np.negative of an unsigned array wraps, and is faster than 0 - x


def _cross_prediction(ref: np.ndarray, slope: np.ndarray, intercept: np.ndarray) -> np.ndarray:
    """Per-block linear prediction floor((slope * ref + 64 * intercept + 32) / 64), as int32 (slot order)."""
    r = ref.astype(np.int32).reshape(len(slope), BLOCK_TEXELS)
    p = r * slope.astype(np.int32)[:, None]
    p += (intercept.astype(np.int32) << SLOPE_SHIFT)[:, None] + (1 << (SLOPE_SHIFT - 1))
    p >>= SLOPE_SHIFT
    return p.reshape(-1)


def _fit_cross(values: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-block least-squares slope (1/64 units) and intercept of values against ref (sums in exact integers)."""
    v = values.astype(np.int64).reshape(-1, BLOCK_TEXELS)
    r = ref.astype(np.int64).reshape(-1, BLOCK_TEXELS)
    sv, sr = v.sum(axis=1), r.sum(axis=1)
    cov = (r * v).sum(axis=1) * BLOCK_TEXELS - sr * sv
    var = (r * r).sum(axis=1) * BLOCK_TEXELS - sr * sr
    slope = np.divide(cov.astype(np.float64), var, out=np.zeros(len(var)), where=var > 0)
    slope = np.clip(np.rint(slope * (1 << SLOPE_SHIFT)), SLOPE_MIN, SLOPE_MAX)
    intercept = np.rint((sv - slope / (1 << SLOPE_SHIFT) * sr) / BLOCK_TEXELS)
    return slope.astype(np.int8), np.clip(intercept, INTERCEPT_MIN, INTERCEPT_MAX).astype("<i2")


def _residual(values: np.ndarray, bits: int, delta: bool, pred: np.ndarray | None) -> np.ndarray:
    """Stored code of every slot: (values - pred) modulo 2^bits, delta to the previous slot if asked; fields of more
    than 8 bits as zigzag codes (so small residuals of either sign have a zero high byte)."""
    t = _field_dtype(bits)
    x = values.astype(t)
    if pred is not None:
        x -= pred.astype(t)
    if delta:
        x[1:] -= x[:-1].copy()
    x &= t((1 << bits) - 1)
    return x if bits <= 8 else _zigzag(x, bits)


def _planes(z: np.ndarray, bits: int) -> list[np.ndarray]:
    """Codes -> byte planes, low byte first."""
    nbytes = (bits + 7) // 8
    if nbytes == 1:
        return [z.astype(np.uint8, copy=False)]
    b = z.view(np.uint8).reshape(-1, z.dtype.itemsize)
    return [b[:, i] for i in range(nbytes)]


def _plane_cost(z: np.ndarray, bits: int) -> float:
    """Order-0 entropy of the byte planes in bytes (what zstd's Huffman stage roughly reaches)."""
    total = 0.0
    for plane in _planes(z, bits):
        counts = np.bincount(plane, minlength=256)
        counts = counts[counts > 0]
        total += float((counts * np.log2(counts.sum() / counts)).sum()) / 8
    return total


def _sample_blocks(blocks: int) -> np.ndarray:
    """Blocks the encoder measures modes on: all of them, or an even spread of about SAMPLE_SLOTS slots."""
    want = max(1, SAMPLE_SLOTS // BLOCK_TEXELS)
    if blocks <= want:
        return np.arange(blocks)
    return np.linspace(0, blocks - 1, want).astype(np.int64)


def choose_modes(fields: list[np.ndarray], bits: list[int]) -> list[tuple[bool, int | None]]:
    """Per field (delta, reference field or None), chosen on a sample of blocks by the byte-plane entropy.

    Fields with a reference are predicted from an **anchor** (a field without one) of the same texel. Every set of
    anchors is tried (4 fields at most: 15 sets), each other field taking its best anchor or none.
    """
    nf = len(fields)
    blocks = len(fields[0]) // BLOCK_TEXELS
    pick = _sample_blocks(blocks)
    sample = [f.reshape(blocks, BLOCK_TEXELS)[pick].reshape(-1) for f in fields]
    alone = []
    for f, b in zip(sample, bits, strict=True):
        costs = {d: _plane_cost(_residual(f, b, d, None), b) for d in (False, True)}
        d = min(costs, key=costs.get)
        alone.append((costs[d], d))
    cross: dict[tuple[int, int], tuple[float, bool]] = {}
    param_cost = 3.0 * len(pick)  # i8 slope + i16 intercept per block, before zstd
    for i in range(nf):
        for r in range(nf):
            if i == r or bits[i] > 16 or bits[r] > 16:
                continue
            slope, intercept = _fit_cross(sample[i], sample[r])
            pred = _cross_prediction(sample[r], slope, intercept)
            costs = {d: _plane_cost(_residual(sample[i], bits[i], d, pred), bits[i]) + param_cost
                     for d in (False, True)}
            d = min(costs, key=costs.get)
            cross[(i, r)] = (costs[d], d)
    best_total, best = float("inf"), None
    for mask in range(1, 1 << nf):
        anchors = [i for i in range(nf) if mask >> i & 1]
        total, modes = 0.0, []
        for i in range(nf):
            options = [(alone[i][0], alone[i][1], None)]
            if i not in anchors:
                options += [(cross[(i, r)][0], cross[(i, r)][1], r) for r in anchors if (i, r) in cross]
            cost, d, r = min(options, key=lambda o: o[0])
            total += cost
            modes.append((d, r))
        if total < best_total:
            best_total, best = total, modes
    return best


# ---------------------------------------------------------------------------------------------------------------
# Section streams


def _shuffle_element(fmt: str | None, element: int | None) -> int:
    if element is not None:
        return element
    return max(1, FORMATS[fmt].shuffle) if fmt is not None else 1


def encode_shuffle_zstd(data: np.ndarray, element: int, units: int = 1, level: int = 3) -> bytes:
    """Byte shuffle of each of `units` equal parts, then one zstd frame (today's payload filter, per section)."""
    data = np.ascontiguousarray(data, np.uint8).reshape(-1)
    unit = data.size // units if units else data.size
    parts = [shuffle_bytes(data[i * unit:(i + 1) * unit], element) for i in range(units)]
    raw = np.concatenate(parts) if len(parts) > 1 else parts[0]
    return zstandard.ZstdCompressor(level=level, write_content_size=True).compress(raw.tobytes())


def encode_fields_zstd(data: np.ndarray, fmt: str, width: int, height: int, layers: int, level: int = 3,
                       modes: list[list[tuple[bool, int | None]]] | None = None) -> bytes:
    """The fields-zstd stream of a texels section (modes chosen per layer unless given)."""
    return _encode_fields(data, fmt, width, height, layers, level, modes)[0]


def _encode_fields(data: np.ndarray, fmt: str, width: int, height: int, layers: int, level: int,
                   modes: list[list[tuple[bool, int | None]]] | None) -> tuple[bytes, list]:
    raw, chosen = fields_content(data, fmt, width, height, layers, modes)
    return zstandard.ZstdCompressor(level=level, write_content_size=True).compress(raw), chosen


def fields_content(data: np.ndarray, fmt: str, width: int, height: int, layers: int,
                   modes: list[list[tuple[bool, int | None]]] | None = None) -> tuple[bytes, list]:
    """The `fields1` filter: a texels section's GPU bytes -> its stored bytes (header, per-block parameters, byte
    planes of the residuals; format_spec/transport_draft.md), and the modes used (chosen per layer unless given)."""
    data = np.ascontiguousarray(data, np.uint8).reshape(-1)
    unit = data.size // layers
    bits = _fields(fmt)
    header = [FIELDS_VERSION]
    chosen = []
    params: list[bytes] = []
    planes: list[np.ndarray] = []
    for layer in range(layers):
        fields = split_layer(data[layer * unit:(layer + 1) * unit], fmt, width, height)
        layer_modes = modes[layer] if modes is not None else choose_modes(fields, bits)
        chosen.append(layer_modes)
        for i, (delta, ref) in enumerate(layer_modes):
            header.append((MODE_DELTA if delta else 0) | ((0 if ref is None else ref + 1) << 4))
            pred = None
            if ref is not None:
                slope, intercept = _fit_cross(fields[i], fields[ref])
                params += [slope.tobytes(), intercept.tobytes()]
                pred = _cross_prediction(fields[ref], slope, intercept)
            planes += _planes(_residual(fields[i], bits[i], delta, pred), bits[i])
    return bytes(header) + b"".join(params) + b"".join(p.tobytes() for p in planes), chosen


def encode_section(texel_bytes: bytes | np.ndarray, texel_format: str, width: int, height: int, layers: int,
                   level: int = 3, codings: tuple[str, ...] = CODINGS) -> tuple[bytes, dict]:
    """Code one texels section; returns (stored bytes, coding descriptor for the manifest's section entry).

    Tries each coding in `codings` that applies to the format and keeps the smallest."""
    data = np.frombuffer(texel_bytes, np.uint8) if isinstance(texel_bytes, bytes | bytearray | memoryview) \
        else np.ascontiguousarray(texel_bytes, np.uint8).reshape(-1)
    _check_geometry(texel_format, width, height, layers, "encode_section")
    expected = blob_size(FORMATS[texel_format], width, height, layers)
    if data.size != expected:
        raise ValueError(f"{data.size} texel bytes for {layers} layers of {width}x{height} {texel_format}, "
                         f"expected {expected}")
    element = _shuffle_element(texel_format, None)
    if "fields-zstd" not in codings or texel_format not in FIELD_LAYOUTS:
        return encode_shuffle_zstd(data, element, layers, level), {"coding": "shuffle-zstd", "element": element}
    if "shuffle-zstd" not in codings:
        return _encode_fields(data, texel_format, width, height, layers, level, None)[0], {"coding": "fields-zstd"}
    # Decide on a band of whole block rows (about 2 x SAMPLE_SLOTS slots, all of a small section) with both
    # codings; the band's field modes are reused for the whole section, so a large section costs one more zstd
    # pass over an eighth of its bytes instead of a second pass over all of them.
    band, band_height = _band(data, texel_format, width, height, layers)
    fields, modes = _encode_fields(band, texel_format, width, band_height, layers, level, None)
    shuffled = encode_shuffle_zstd(band, element, layers, level)
    if band_height == height:
        return (fields, {"coding": "fields-zstd"}) if len(fields) < len(shuffled) else \
            (shuffled, {"coding": "shuffle-zstd", "element": element})
    if len(fields) < len(shuffled):
        return _encode_fields(data, texel_format, width, height, layers, level, modes)[0], {"coding": "fields-zstd"}
    return encode_shuffle_zstd(data, element, layers, level), {"coding": "shuffle-zstd", "element": element}


def filter_section(texel_bytes: bytes | np.ndarray, texel_format: str, width: int, height: int, layers: int,
                   level: int = 3) -> tuple[bytes, str]:
    """Section filter for a payload that stays one zstd frame (the integration format.md 5 would take): the
    section's stored bytes and its `filter` value, `fields1` or today's `shuffleN` / `none`, whichever
    encode_section finds smaller."""
    data = np.frombuffer(texel_bytes, np.uint8) if isinstance(texel_bytes, bytes | bytearray | memoryview) \
        else np.ascontiguousarray(texel_bytes, np.uint8).reshape(-1)
    _, descriptor = encode_section(data, texel_format, width, height, layers, level)
    if descriptor["coding"] == "fields-zstd":
        return fields_content(data, texel_format, width, height, layers)[0], "fields1"
    element = descriptor["element"]
    unit = data.size // layers
    parts = [shuffle_bytes(data[i * unit:(i + 1) * unit], element) for i in range(layers)]
    return np.concatenate(parts).tobytes(), (f"shuffle{element}" if element > 1 else "none")


def unfilter_section(stored: bytes | np.ndarray, filter_name: str, texel_format: str, width: int, height: int,
                     layers: int, source: str = "section") -> np.ndarray:
    """Inverse of filter_section (stored bytes of a decompressed payload -> GPU bytes)."""
    buf = np.frombuffer(stored, np.uint8) if isinstance(stored, bytes | bytearray | memoryview) else stored
    if filter_name == "fields1":
        return unfilter_fields(buf, texel_format, width, height, layers, source)
    if filter_name == "none" or (filter_name.startswith("shuffle") and filter_name[7:].isdigit()):
        element = 1 if filter_name == "none" else int(filter_name[7:])
        _check_geometry(texel_format, width, height, layers, source)
        if buf.size != blob_size(FORMATS[texel_format], width, height, layers):
            raise FormatError(source, "size", f"{buf.size} bytes for {layers} layers of {width}x{height} "
                              f"{texel_format}")
        unit = buf.size // layers
        return np.concatenate([_unshuffle(buf[i * unit:(i + 1) * unit], element) for i in range(layers)])
    raise FormatError(source, "filter", f"unknown filter {filter_name!r} (expected none, shuffleN or fields1)")


def _band(data: np.ndarray, fmt: str, width: int, height: int, layers: int) -> tuple[np.ndarray, int]:
    """The middle band of whole block rows holding about 2 x SAMPLE_SLOTS slots of every layer, and its height."""
    block_rows = height // BLOCK
    rows = max(1, min(block_rows, -(-SAMPLE_SLOTS * 2 // (width * BLOCK))))
    if rows == block_rows:
        return data, height
    start = (block_rows - rows) // 2 * BLOCK
    row_bytes = width * FORMATS[fmt].bits_per_texel // 8
    unit = data.size // layers
    parts = [data[layer * unit + start * row_bytes:layer * unit + (start + rows * BLOCK) * row_bytes]
             for layer in range(layers)]
    return np.concatenate(parts), rows * BLOCK


def encode_range_section(range_bytes: bytes | np.ndarray, element: int, level: int = 3) -> tuple[bytes, dict]:
    """Code a range section (f32 or f16 per-chunk ranges): byte shuffle by the element, zstd."""
    data = np.frombuffer(range_bytes, np.uint8) if isinstance(range_bytes, bytes | bytearray | memoryview) \
        else np.ascontiguousarray(range_bytes, np.uint8).reshape(-1)
    return encode_shuffle_zstd(data, element, 1, level), {"coding": "shuffle-zstd", "element": element}


def _join_planes(planes: np.ndarray, element: int, word: type | None = None) -> np.ndarray:
    """`element` byte planes (low byte first) -> (n,) words (of `element` bytes unless `word` is given); shifts and
    ors are several times faster than numpy's strided transpose copy."""
    v = planes.reshape(element, -1)
    if word is None:
        word = np.uint16 if element == 2 else np.uint32 if element == 4 else np.uint64
    z = v[element - 1].astype(word)
    for k in range(element - 2, -1, -1):
        z <<= word(8)
        z |= v[k]
    return z


def _unshuffle(buf: np.ndarray, element: int) -> np.ndarray:
    """Inverse byte shuffle (format.md 5) of one unit, as bytes."""
    if element <= 1 or buf.size % element:
        return buf
    if element in (2, 4, 8):
        return _join_planes(buf, element).view(np.uint8)
    return unshuffle_bytes(buf, element)


def _decompress(data: bytes, limit: int, source: str) -> bytes:
    try:
        params = zstandard.get_frame_parameters(data)
    except zstandard.ZstdError as exc:
        raise FormatError(source, "coding", f"not a zstd frame ({exc})") from None
    if params.content_size in (zstandard.CONTENTSIZE_UNKNOWN, zstandard.CONTENTSIZE_ERROR) \
            or params.content_size > limit:
        raise FormatError(source, "coding", f"zstd frame declares {params.content_size} bytes, at most {limit} "
                          "expected")
    try:
        raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=limit)
    except zstandard.ZstdError as exc:
        raise FormatError(source, "coding", f"corrupt zstd frame ({exc})") from None
    return raw


def decode_section(data: bytes, descriptor: dict, texel_format: str | None, width: int = 0, height: int = 0,
                   layers: int = 1, size: int | None = None, source: str = "section") -> np.ndarray:
    """Stored bytes + coding descriptor -> the section's GPU bytes (uint8 array), bit-exact.

    Texels sections give `texel_format`, `width`, `height`, `layers`; range sections give `texel_format=None` and
    their byte `size`. Raises FormatError for any stream that does not decode to exactly that many bytes."""
    if not isinstance(descriptor, dict):
        raise FormatError(source, "coding", f"expected a map, got {descriptor!r}")
    coding = descriptor.get("coding")
    if texel_format is not None:
        _check_geometry(texel_format, width, height, layers, source)
        size = blob_size(FORMATS[texel_format], width, height, layers)
    if not isinstance(size, int) or size < 0:
        raise FormatError(source, "size", f"expected a byte count, got {size!r}")
    if coding == "shuffle-zstd":
        element = descriptor.get("element")
        if not isinstance(element, int) or not 1 <= element <= 16:
            raise FormatError(source, "coding.element", f"expected 1..16, got {element!r}")
        raw = _decompress(data, size, source)
        if len(raw) != size:
            raise FormatError(source, "coding", f"decodes to {len(raw)} bytes, expected {size}")
        buf = np.frombuffer(raw, np.uint8)
        units = layers if texel_format is not None else 1
        unit = size // units
        if units == 1:
            return _unshuffle(buf, element)
        return np.concatenate([_unshuffle(buf[i * unit:(i + 1) * unit], element) for i in range(units)])
    if coding == "fields-zstd":
        if texel_format not in FIELD_LAYOUTS:
            raise FormatError(source, "coding", f"fields-zstd does not apply to texel format {texel_format!r}")
        return _decode_fields(data, texel_format, width, height, layers, source)
    raise FormatError(source, "coding", f"unknown coding {coding!r} (expected one of {', '.join(CODINGS)})")


def fields_content_limit(fmt: str, width: int, height: int, layers: int) -> int:
    """Largest `fields1` content a texels section can have (every non-anchor field predicted)."""
    bits = _fields(fmt)
    n = width * height
    return 1 + len(bits) * layers + n * sum((b + 7) // 8 for b in bits) * layers \
        + 3 * (n // BLOCK_TEXELS) * len(bits) * layers


def _decode_fields(data: bytes, fmt: str, width: int, height: int, layers: int, source: str) -> np.ndarray:
    raw = _decompress(data, fields_content_limit(fmt, width, height, layers), source)
    return unfilter_fields(np.frombuffer(raw, np.uint8), fmt, width, height, layers, source)


def unfilter_fields(raw: np.ndarray, fmt: str, width: int, height: int, layers: int,
                    source: str = "section") -> np.ndarray:
    """Inverse of fields_content: a section's stored bytes -> its GPU bytes (uint8), bit-exact; FormatError for
    anything that is not a well-formed `fields1` content of exactly its size."""
    if fmt not in FIELD_LAYOUTS:
        raise FormatError(source, "filter", f"fields1 does not apply to texel format {fmt!r}")
    _check_geometry(fmt, width, height, layers, source)
    raw = np.frombuffer(raw, np.uint8) if isinstance(raw, bytes | bytearray | memoryview) else raw
    bits = _fields(fmt)
    nf = len(bits)
    n = width * height
    blocks = n // BLOCK_TEXELS
    plane_bytes = n * sum((b + 7) // 8 for b in bits) * layers
    header_bytes = 1 + nf * layers
    if raw.size < header_bytes or raw[0] != FIELDS_VERSION:
        raise FormatError(source, "coding", f"fields-zstd stream of {raw.size} bytes has no version-"
                          f"{FIELDS_VERSION} header")
    # the header as Python ints: numpy scalar access costs more than the arithmetic on a small section
    flat = raw[1:header_bytes].tolist()
    modes = [flat[layer * nf:(layer + 1) * nf] for layer in range(layers)]
    refs = [[(m >> 4) - 1 for m in layer_modes] for layer_modes in modes]
    if any(m & MODE_RESERVED for m in flat):
        raise FormatError(source, "coding", "reserved mode bits set")
    for layer in range(layers):
        for i in range(nf):
            r = refs[layer][i]
            if r >= 0 and (r >= nf or r == i or refs[layer][r] >= 0 or bits[i] > 16 or bits[r] > 16):
                raise FormatError(source, "coding", f"layer {layer} field {i}: reference field {r} is not an anchor "
                                  "field of the same texel")
    crossed = sum(r >= 0 for layer_refs in refs for r in layer_refs)
    expected = header_bytes + 3 * blocks * crossed + plane_bytes
    if raw.size != expected:
        raise FormatError(source, "coding", f"fields-zstd stream holds {raw.size} bytes, expected {expected}")
    pos = header_bytes
    params = {}
    for layer in range(layers):
        for i in range(nf):
            if refs[layer][i] >= 0:
                slope = raw[pos:pos + blocks].view(np.int8)
                intercept = raw[pos + blocks:pos + 3 * blocks].view("<i2")
                params[(layer, i)] = (slope, intercept)
                pos += 3 * blocks
    out = np.empty(n * FORMATS[fmt].bits_per_texel // 8 * layers, np.uint8)
    unit = out.size // layers
    for layer in range(layers):
        codes = []
        for i in range(nf):
            nbytes = (bits[i] + 7) // 8
            planes = raw[pos:pos + n * nbytes]
            pos += n * nbytes
            # byte planes -> one code per slot (low byte first)
            codes.append(planes if nbytes == 1 else _join_planes(planes, nbytes, np.uint32))
        fields: list[np.ndarray | None] = [None] * nf
        for i in sorted(range(nf), key=lambda k: refs[layer][k] >= 0):  # anchors first
            # Fields of up to 16 bits are reconstructed in uint32 (the result modulo 2^32 masked to the field's
            # bits equals the arithmetic modulo 2^|T| of the spec): numpy's running sum and arithmetic are several
            # times faster on 32-bit words than on 8- or 16-bit ones.
            x = codes[i] if bits[i] <= 8 else _unzigzag(codes[i])
            if modes[layer][i] & MODE_DELTA:
                x = np.cumsum(x, dtype=np.uint32)
            r = refs[layer][i]
            if r < 0 and x.dtype == np.uint8:
                fields[i] = x  # a plain 8-bit field is its byte plane
                continue
            x = x.astype(np.uint32, copy=False)
            if r >= 0:
                slope, intercept = params[(layer, i)]
                x += _cross_prediction(fields[r], slope, intercept).view(np.uint32)
            if bits[i] < 32:
                x &= np.uint32((1 << bits[i]) - 1)
            fields[i] = x
        out[layer * unit:(layer + 1) * unit] = join_layer(fields, fmt, width, height)
    return out
