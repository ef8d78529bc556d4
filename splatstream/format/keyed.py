"""The `morton1` coding of position texels sections (format_spec/format.md 5.4, version 1.6).

A splat's order inside a chunk is free (format.md 3), so a set of 256 points costs less than a sequence of them:
the encoder (transport `keyed`) sorts each chunk by the 3D Morton key of its quantised position codes
(jobs.keyed_order), and this
coding stores, in slot order, the difference of consecutive keys (modulo 2^48) as six byte planes, low byte first,
then the texels' fourth 16-bit component as two byte planes. Sorted keys inside a chunk differ by about the volume
per point, where fields1's per-axis differences each carry the spacing between neighbours: on the statue scans at
about 11-bit positions, 2.8 against 3.1 B/splat (BENCHMARKS.md, issue 32). The stored content is exactly as large
as the texels (8 bytes a texel); zstd does the entropy coding.

Only `norm16x4` sections of one layer use it. Pure numpy; a compiled decoder of the same bytes may be handed in
(`use_morton_kernel`: the streaming client's, client_gl/stream/decode_jit.py).
"""
from __future__ import annotations

import numpy as np

from .transport import slot_to_texel

MORTON1 = "morton1"
MORTON_FORMATS = ("norm16x4",)
KEY_BITS = 48
KEY_BYTES = KEY_BITS // 8
_KEY_MASK = np.uint64((1 << KEY_BITS) - 1)
_SPREAD = ((16, 0x0000FF0000FF), (8, 0x00F00F00F00F), (4, 0x0C30C30C30C3), (2, 0x249249249249))
_COMPACT = ((2, 0x0C30C30C30C3), (4, 0x00F00F00F00F), (8, 0x0000FF0000FF), (16, 0x00000000FFFF))


def spread_bits(v: np.ndarray) -> np.ndarray:
    """16-bit integers -> uint64 with bit i moved to bit 3i."""
    v = v.astype(np.uint64) & np.uint64(0xFFFF)
    for shift, mask in _SPREAD:
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def compact_bits(v: np.ndarray) -> np.ndarray:
    """spread_bits' inverse on the bits 0, 3, 6, ... of v (uint64) -> uint64 holding 16 bits."""
    v = v & np.uint64(0x249249249249)
    for shift, mask in _COMPACT:
        v = (v | (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def _piece_tables() -> np.ndarray:
    """(3, 65536) uint64: for the 16-bit piece p of a key (bits 16p..16p+15), its bits moved to x, y, z as three
    16-bit lanes of a uint64 (x in bits 0-15, y 16-31, z 32-47): a decode by three table look-ups."""
    v = np.arange(1 << 16, dtype=np.uint64)
    tables = np.zeros((3, 1 << 16), np.uint64)
    for p in range(3):
        for j in range(16):
            b = 16 * p + j
            lane_bit = np.uint64(16 * (b % 3) + b // 3)
            tables[p] |= ((v >> np.uint64(j)) & np.uint64(1)) << lane_bit
    return tables


_PIECES = _piece_tables()


def morton_keys(codes: np.ndarray) -> np.ndarray:
    """(N, >=3) 16-bit integer codes -> (N,) uint64 keys: bit 3i of x, 3i + 1 of y, 3i + 2 of z."""
    return spread_bits(codes[:, 0]) | (spread_bits(codes[:, 1]) << np.uint64(1)) | \
        (spread_bits(codes[:, 2]) << np.uint64(2))


def _slot_words(layer: np.ndarray, width: int, height: int) -> np.ndarray:
    """(slots, 4) uint16 components of a norm16x4 layer (GPU bytes) in slot order."""
    words = np.frombuffer(np.ascontiguousarray(layer), "<u2").reshape(-1, 4)
    return words[slot_to_texel(width, height)]


def morton_content(layer: np.ndarray, width: int, height: int) -> list[np.ndarray]:
    """One norm16x4 layer's texel bytes -> the morton1 content's parts: 6 key-difference planes, 2 planes of the
    fourth component (format.md 5.4)."""
    words = _slot_words(np.ravel(layer).view(np.uint8), width, height)
    key = morton_keys(words)
    delta = key.copy()
    delta[1:] -= key[:-1]
    delta &= _KEY_MASK
    b = delta.view(np.uint8).reshape(-1, 8)
    w = np.ascontiguousarray(words[:, 3]).astype("<u2").view(np.uint8).reshape(-1, 2)
    return [np.ascontiguousarray(b[:, i]) for i in range(KEY_BYTES)] + [np.ascontiguousarray(w[:, i])
                                                                         for i in range(2)]


_morton_kernel = None  # see use_morton_kernel


def use_morton_kernel(kernel) -> object:
    """Decode morton1 contents with `kernel` (None: numpy's path); returns the one it replaces. Called as
    kernel(stored, slots, slot_to_texel, out): `stored` the content's 8 x slots bytes (uint8), `out` the layer as
    `slots` uint64 texels, each slot's texel written at out[slot_to_texel[slot]].

    Why: numpy's path is about fifteen whole-array calls a section, about 35 us of a 512-slot tile's position plane,
    half a small payload's decode besides zstd (issue 32: medium-low-palette on guitar); one pass does it in a few."""
    global _morton_kernel
    previous, _morton_kernel = _morton_kernel, kernel
    return previous


def unfilter_morton(stored: np.ndarray, width: int, height: int) -> np.ndarray:
    """A morton1 content (exactly 8 bytes a texel, checked by the manifest) -> the layer's GPU bytes."""
    slots = width * height
    kernel = _morton_kernel
    if kernel is not None:
        out = np.empty(slots, "<u8")
        kernel(np.frombuffer(stored, np.uint8), slots, slot_to_texel(width, height), out)
        return out.view(np.uint8)
    planes = np.frombuffer(stored, np.uint8).reshape(KEY_BYTES + 2, slots)
    delta = planes[0].astype(np.uint64)
    for b in range(1, KEY_BYTES):
        delta |= planes[b].astype(np.uint64) << np.uint64(8 * b)
    key = np.cumsum(delta, dtype=np.uint64, out=delta)  # modulo 2^64; only bits 0-47 are read
    pieces = key.view("<u2").reshape(-1, 4)
    lanes = _PIECES[0][pieces[:, 0]]
    lanes |= _PIECES[1][pieces[:, 1]]
    lanes |= _PIECES[2][pieces[:, 2]]
    fourth = planes[KEY_BYTES].astype(np.uint64) | (planes[KEY_BYTES + 1].astype(np.uint64) << np.uint64(8))
    if fourth.any():  # a position plane's fourth component is 0 (format.md 4.4): usually nothing to add
        lanes |= fourth << np.uint64(48)
    out = np.empty(slots, "<u8")
    out[slot_to_texel(width, height)] = lanes  # one 8-byte texel per slot
    return out.view(np.uint8)
