"""Niantic SPZ writer: version 3 (one gzip stream) and version 4 (plaintext header, one zstd frame per array).

The quantisation is that of the reference packer (nianticlabs/spz `packGaussians` with default `PackOptions`):
24-bit fixed-point positions with 12 fractional bits, 8-bit log scales `(s + 10) * 16`, 8-bit sigmoid alpha,
8-bit colour `f_dc * 0.15 * 255 + 127.5`, smallest-three rotations (2-bit index, 3 x (sign + 9 bits)), and SH as
`round(x * 128) + 128` snapped to buckets of 8 (band 1, 5 bits) or 16 (bands 2-3, 4 bits). Arithmetic is done in
float32 with round-half-away-from-zero like the C++ code, so our bytes equal the reference's for the same input.
Compression: gzip at zlib's default level with memLevel 9 (v3), zstd level 12 per stream (v4), as the reference.

Axes: our RDF model is turned to SPZ's RUB on the way in (see splatstream/axes.py).
"""
from __future__ import annotations

import os
import struct
import warnings
import zlib

import numpy as np

from ..atomic import atomic_file
from ..axes import RDF_TO_RUB, turn
from ..errors import UsageError
from ..gaussians import Gaussians

MAGIC = b"NGSP"
LEGACY_HEADER = struct.Struct("<4sIIBBBB")
V4_HEADER = struct.Struct("<4sIIBBBBI12s")
TOC_ENTRY = struct.Struct("<QQ")
DEFAULT_FRACTIONAL_BITS = 12
COLOR_SCALE = np.float32(0.15)
SH1_BITS = 5  # PackOptions defaults
SH_REST_BITS = 4
ZSTD_LEVEL = 12
GZIP_LEVEL = 6  # Z_DEFAULT_COMPRESSION
GZIP_MEM_LEVEL = 9
SUPPORTED_VERSIONS = (3, 4)


def _round_half_away(x: np.ndarray) -> np.ndarray:
    """std::round: halves go away from zero (numpy's rint goes to even)."""
    return np.sign(x) * np.floor(np.abs(x) + np.float32(0.5))


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round_half_away(x.astype(np.float32)), 0, 255).astype(np.uint8)


def fractional_bits_for(positions: np.ndarray, preferred: int = DEFAULT_FRACTIONAL_BITS) -> int:
    """The reference always uses 12 fractional bits and silently wraps coordinates beyond +-2048; we keep 12
    where it fits and otherwise use the largest number of bits that holds every coordinate in 24 signed bits
    (any fractionalBits decodes in every reader)."""
    extent = float(np.abs(positions).max()) if len(positions) else 0.0
    bits = preferred
    while bits > 0 and extent * (1 << bits) + 0.5 >= (1 << 23) - 1:
        bits -= 1
    if extent * (1 << bits) + 0.5 >= (1 << 23) - 1:
        raise UsageError(f"SPZ cannot hold coordinates as large as {extent:g} (24-bit fixed point: at most "
                         f"{(1 << 23) - 1} units)")
    return bits


def _pack_positions(p: np.ndarray, fractional_bits: int) -> bytes:
    fixed = _round_half_away(p.astype(np.float32) * np.float32(1 << fractional_bits)).astype(np.int64)
    fixed &= 0xFFFFFF
    out = np.empty((len(p), 3, 3), np.uint8)
    out[..., 0] = fixed & 0xFF
    out[..., 1] = (fixed >> 8) & 0xFF
    out[..., 2] = (fixed >> 16) & 0xFF
    return out.tobytes()


def _pack_rotations(wxyz: np.ndarray) -> bytes:
    """Smallest three, as packQuaternionSmallestThree: (x, y, z, w) normalised, index of the largest |component|
    (first wins ties) in bits 31-30, then every other component in x, y, z, w order, each as sign (relative to
    the largest's sign) and a 9-bit magnitude |c| / sqrt(1/2) * 511 + 0.5 truncated; the first lands highest."""
    q = wxyz[:, [1, 2, 3, 0]].astype(np.float32)
    norm = np.sqrt((q * q).sum(axis=1, dtype=np.float32))
    q = q / np.where(norm > 0, norm, np.float32(1))[:, None]
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    sqrt1_2 = np.float32(0.7071067811865476)
    for i in range(4):
        other = largest != i
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = (np.float32(511.0) * (np.abs(q[:, i]) / sqrt1_2) + np.float32(0.5)).astype(np.uint32)
        comp = np.where(other, (comp << np.uint32(10)) | (negbit << np.uint32(9)) | mag, comp)
    return comp.astype("<u4").tobytes()


def _quantize_sh(x: np.ndarray, bucket: int) -> np.ndarray:
    q = (_round_half_away(x.astype(np.float32) * np.float32(128.0)) + 128).astype(np.int64)
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def pack_streams(g: Gaussians, fractional_bits: int) -> dict[str, bytes]:
    """The six attribute arrays of `g` (already in SPZ's axes), in the reference packer's byte layout."""
    with np.errstate(over="ignore"):  # exp overflows to inf for logits below -88: alpha is then exactly 0
        alpha = np.float32(1) / (np.float32(1) + np.exp(-g.opacity_logits.astype(np.float32)))
    sh = g.sh_rest
    packed_sh = np.empty(sh.shape, np.uint8)
    packed_sh[:, :3] = _quantize_sh(sh[:, :3], 1 << (8 - SH1_BITS))
    packed_sh[:, 3:] = _quantize_sh(sh[:, 3:], 1 << (8 - SH_REST_BITS))
    return {
        "positions": _pack_positions(g.positions, fractional_bits),
        "alphas": _to_u8(alpha * np.float32(255.0)).tobytes(),
        "colors": _to_u8(g.sh_dc * (COLOR_SCALE * np.float32(255.0)) + np.float32(127.5)).tobytes(),
        "scales": _to_u8((g.log_scales + np.float32(10.0)) * np.float32(16.0)).tobytes(),
        "rotations": _pack_rotations(g.rotations),
        "sh": packed_sh.tobytes(),
    }


def spz_bytes(g: Gaussians, version: int = 4, axes: tuple[float, float, float] = RDF_TO_RUB) -> bytes:
    """An SPZ file (version 3 or 4) holding `g`.

    `axes` turns our RDF attributes into the stored ones; the default stores SPZ's own RUB, so every SPZ
    reader (ours, Niantic's, splat-transform's) gets the original coordinates back. (1, 1, 1) stores the
    attributes as they are (for containers that define their own axes).
    """
    if version not in SUPPORTED_VERSIONS:
        raise UsageError(f"SPZ version {version} cannot be written (expected one of {SUPPORTED_VERSIONS})")
    if len(g) >= 1 << 32:
        raise UsageError(f"SPZ holds at most {(1 << 32) - 1} splats, not {len(g)}")
    stored = turn(g, axes) if tuple(axes) != (1.0, 1.0, 1.0) else g
    bits = fractional_bits_for(stored.positions)
    if bits != DEFAULT_FRACTIONAL_BITS:
        warnings.warn(f"SPZ: coordinates up to {float(np.abs(stored.positions).max()):g} need more than 12 integer "
                      f"bits; writing {bits} fractional bits (a {2.0 ** -bits:g} grid)", stacklevel=2)
    streams = pack_streams(stored, bits)
    order = ("positions", "alphas", "colors", "scales", "rotations", "sh")
    if version == 3:
        header = LEGACY_HEADER.pack(MAGIC, 3, len(g), g.sh_degree, bits, 0, 0)
        compressor = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, 16 + zlib.MAX_WBITS, GZIP_MEM_LEVEL)
        body = compressor.compress(header + b"".join(streams[name] for name in order))
        return body + compressor.flush()
    import zstandard

    compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    # Empty arrays (no SH at degree 0, everything for 0 splats) get no stream, as the reference writes it.
    frames = [(compressor.compress(streams[name]), len(streams[name])) for name in order if streams[name]]
    header = V4_HEADER.pack(MAGIC, 4, len(g), g.sh_degree, bits, 0, len(frames), V4_HEADER.size, bytes(12))
    toc = b"".join(TOC_ENTRY.pack(len(frame), size) for frame, size in frames)
    return header + toc + b"".join(frame for frame, _ in frames)


def write_spz(g: Gaussians, path: str | os.PathLike, version: int = 4) -> None:
    """Write an SPZ file atomically (temporary name, then rename)."""
    try:
        data = spz_bytes(g, version)
    except UsageError as exc:  # name the file being written
        raise UsageError(f"{os.fspath(path)}: {exc}") from None
    with atomic_file(path) as f:
        f.write(data)
