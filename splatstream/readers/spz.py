"""Niantic SPZ, versions 2, 3 and 4 (as written by nianticlabs/spz, also inside splat-transform).

Versions 2 and 3: the whole file is one gzip stream holding a 16-byte header (magic 'NGSP', version,
numPoints, shDegree, fractionalBits, flags, reserved) followed by the attribute arrays positions, alphas,
colours, scales, rotations, SH (each for all points). Version 4: a plaintext 32-byte header (adds
numStreams and tocByteOffset, 12 reserved bytes), optional extension records up to tocByteOffset, a table
of contents of (compressedSize, uncompressedSize) u64 pairs, then one zstd frame per attribute array.

SPZ stores RUB axes (x right, y up, z back); 3DGS PLYs use RDF (y down, z forward). Like splat-transform's
reader we convert to RDF, so a PLY -> SPZ -> Gaussians round trip keeps the original coordinates.
"""
from __future__ import annotations

import os
import struct
import warnings
import zlib

import numpy as np

from ..errors import InputError
from ..gaussians import SH_REST_COEFFS, Gaussians, normalize_quaternions
from ..reader_support import check_memory, model_bytes_per_splat, opacity_logits_from_unit

MAGIC = b"NGSP"
LEGACY_HEADER = struct.Struct("<4sIIBBBB")  # magic, version, numPoints, shDegree, fractionalBits, flags, reserved
V4_HEADER = struct.Struct("<4sIIBBBBI12s")  # ... flags, numStreams, tocByteOffset, reserved[12]
TOC_ENTRY = struct.Struct("<QQ")
FLAG_ANTIALIASED = 0x1
FLAG_HAS_EXTENSIONS = 0x2
STREAMS = ("positions", "alphas", "colors", "scales", "rotations", "sh")
SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15, 4: 24}  # SH coefficients per channel (beyond DC) for each degree
COLOR_SCALE = 0.15  # SPZ stores colour bytes as f_dc * 0.15 * 255 + 127.5
# Deflate cannot expand more than 1032:1 and zstd goes further only on data without entropy, but real attribute
# streams are never near that: SPZ files of the real scenes (v3 and v4, SH degree 0 to 3, one with every SH
# coefficient zero) hold 1.4 to 4.0 bytes of attributes per compressed byte. A header declaring more than 64 per
# byte (plus 64 KiB for tiny files) describes a decompression bomb or a corrupt count, and is refused before
# anything is allocated, as is one whose decoded splats would not fit the memory budget.
MAX_EXPANSION = 64
EXPANSION_SLACK = 64 << 10
# RUB -> RDF is a 180 degree rotation about x: y and z flip, so do the quaternion's y and z, and each SH
# basis function changes sign with its parity in (y, z). Per coefficient for degrees 1..4 (the order of the
# reference code's flipSh for this conversion).
_SH_FLIP = np.array([-1, -1, 1,
                     -1, 1, 1, -1, 1,
                     -1, 1, -1, -1, 1, -1, 1,
                     -1, 1, -1, 1, 1, -1, 1, -1, 1], np.float32)


def _point_sizes(version: int, sh_degree: int) -> dict[str, int]:
    return {"positions": 9, "alphas": 1, "colors": 3, "scales": 3,
            "rotations": 4 if version >= 3 else 3, "sh": SH_DIM[sh_degree] * 3}


def _check_header(path: str, version: int, n: int, sh_degree: int, fractional_bits: int, flags: int) -> None:
    if version == 1:
        raise InputError(path, "header version", "SPZ version 1 (float16 positions, never released) is not "
                         "supported (expected 2, 3 or 4)")
    if version not in (2, 3, 4):
        raise InputError(path, "header version", f"SPZ version {version} is not supported (expected 2, 3 or 4)")
    if sh_degree not in SH_DIM:
        raise InputError(path, "header shDegree", f"{sh_degree} (expected 0..4)")
    if fractional_bits > 23:
        raise InputError(path, "header fractionalBits", f"{fractional_bits} (expected 0..23 for 24-bit positions)")
    if flags & ~(FLAG_ANTIALIASED | FLAG_HAS_EXTENSIONS):
        raise InputError(path, "header flags", f"0x{flags:02x} has unknown bits set (expected only 0x1 antialiased "
                         "and 0x2 extensions)")


def _check_count(path: str, n: int, needed: int, compressed: int, sh_degree: int) -> None:
    if needed > MAX_EXPANSION * compressed + EXPANSION_SLACK:
        raise InputError(path, "header numPoints", f"{n} points need {needed} bytes of attributes, but no real SPZ "
                         f"file compresses its attributes more than {MAX_EXPANSION}:1 and this one has {compressed} "
                         "compressed bytes (a decompression bomb, or a corrupt header)")
    # The attribute bytes, the model, and the float temporaries of decoding (the peak holds about three models).
    check_memory(path, "header numPoints", n, needed // max(n, 1) + 3 * model_bytes_per_splat(sh_degree))


def _gunzip_bounded(path: str, data: bytes, limit: int) -> bytes:
    """Decompress a gzip stream, refusing to produce more than `limit` bytes (decompression bomb guard)."""
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        out = d.decompress(data, limit + 1)
    except zlib.error as exc:
        raise InputError(path, "gzip stream", f"corrupt ({exc})") from None
    if len(out) > limit:
        raise InputError(path, "gzip stream", f"decompresses to more than the {limit} bytes the header declares")
    if not d.eof:
        raise InputError(path, "gzip stream", f"truncated: stream ends after {len(out)} of {limit} "
                         "decompressed bytes")
    if d.unused_data:
        what = "a second gzip member" if d.unused_data[:2] == b"\x1f\x8b" else "trailing bytes"
        raise InputError(path, "gzip stream", f"{len(d.unused_data)} bytes follow the end of the SPZ gzip stream "
                         f"({what}; an SPZ v2/v3 file is exactly one gzip member)")
    return out


def _read_legacy(path: str, data: bytes) -> tuple[dict, dict[str, bytes]]:
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        head = d.decompress(data, LEGACY_HEADER.size)
    except zlib.error as exc:
        raise InputError(path, "gzip stream", f"corrupt ({exc})") from None
    if len(head) < LEGACY_HEADER.size:
        raise InputError(path, "header", f"gzip stream holds only {len(head)} bytes (expected a 16-byte SPZ header)")
    magic, version, n, sh_degree, fractional_bits, flags, reserved = LEGACY_HEADER.unpack(head)
    if magic != MAGIC:
        raise InputError(path, "header magic", f"{magic!r}: a gzip file, but not SPZ (expected 'NGSP')")
    _check_header(path, version, n, sh_degree, fractional_bits, flags)
    if version == 4:
        raise InputError(path, "header version", "version 4 inside a gzip stream (v4 files start with a plaintext "
                         "'NGSP' header)")
    if reserved:
        raise InputError(path, "header reserved byte", f"{reserved} (expected 0)")
    if flags & FLAG_HAS_EXTENSIONS:
        raise InputError(path, "header flags", "extension records in a version 2/3 file are not supported")
    sizes = _point_sizes(version, sh_degree)
    needed = n * sum(sizes.values())
    _check_count(path, n, needed, len(data), sh_degree)
    body = _gunzip_bounded(path, data, LEGACY_HEADER.size + needed)
    if len(body) != LEGACY_HEADER.size + needed:
        raise InputError(path, "gzip stream", f"decompresses to {len(body)} bytes; {n} points of version {version} "
                         f"with SH degree {sh_degree} need exactly {LEGACY_HEADER.size + needed} "
                         "(the data is truncated or the header is wrong)")
    streams: dict[str, bytes] = {}
    offset = LEGACY_HEADER.size
    for name in STREAMS:
        size = n * sizes[name]
        streams[name] = body[offset:offset + size]
        offset += size
    return {"version": version, "n": n, "sh_degree": sh_degree, "fractional_bits": fractional_bits,
            "flags": flags}, streams


def _read_v4(path: str, data: bytes) -> tuple[dict, dict[str, bytes]]:
    import zstandard

    if len(data) < V4_HEADER.size:
        raise InputError(path, "header", f"file is {len(data)} bytes (an SPZ v4 header alone is 32)")
    magic, version, n, sh_degree, fractional_bits, flags, num_streams, toc_offset, reserved = \
        V4_HEADER.unpack_from(data)
    _check_header(path, version, n, sh_degree, fractional_bits, flags)
    if version != 4:
        raise InputError(path, "header version", f"plaintext 'NGSP' header with version {version} (versions 2 and "
                         "3 are gzip-wrapped; a plaintext header must be version 4)")
    if any(reserved):
        raise InputError(path, "header reserved", f"bytes {reserved.hex()} (expected 12 zero bytes)")
    sizes = _point_sizes(version, sh_degree)
    # The reference writer gives an array of zero bytes no stream (SH at degree 0; everything for 0 points), so
    # the count follows from the header; all six (empty ones with compressedSize 0 or an empty frame) are also
    # accepted.
    present = [name for name in STREAMS if n * sizes[name]]
    if num_streams == len(present):
        names = present
    elif num_streams == len(STREAMS):
        names = list(STREAMS)
    else:
        raise InputError(path, "header numStreams", f"{num_streams}, but {n} points with SH degree {sh_degree} have "
                         f"{len(present)} non-empty arrays ({', '.join(present) or 'none'}; expected {len(present)} "
                         f"or {len(STREAMS)})")
    toc_end = toc_offset + num_streams * TOC_ENTRY.size
    if toc_offset < V4_HEADER.size or toc_end > len(data):
        raise InputError(path, "header tocByteOffset", f"{toc_offset}: the table of contents must start at or "
                         f"after byte 32 and end within the file ({len(data)} bytes)")
    if toc_offset != V4_HEADER.size and not flags & FLAG_HAS_EXTENSIONS:
        raise InputError(path, "header tocByteOffset", f"{toc_offset} but the extensions flag is not set "
                         "(expected 32)")
    _skip_extensions(path, data[V4_HEADER.size:toc_offset])
    streams: dict[str, bytes] = {name: b"" for name in STREAMS}
    offset = toc_end
    toc = [TOC_ENTRY.unpack_from(data, toc_offset + i * TOC_ENTRY.size) for i in range(num_streams)]
    total_compressed = sum(c for c, _ in toc)
    if toc_end + total_compressed != len(data):
        raise InputError(path, "table of contents", f"streams total {total_compressed} compressed bytes, but "
                         f"{len(data) - toc_end} bytes follow the table (truncated or corrupt)")
    _check_count(path, n, n * sum(sizes.values()), total_compressed, sh_degree)
    decompressor = zstandard.ZstdDecompressor()
    for name, (compressed, uncompressed) in zip(names, toc, strict=True):
        expected = n * sizes[name]
        if uncompressed != expected:
            raise InputError(path, f"table of contents, {name} stream", f"uncompressedSize {uncompressed}; {n} points "
                             f"need {expected}")
        frame = data[offset:offset + compressed]
        offset += compressed
        if expected == 0 and compressed == 0:
            streams[name] = b""
            continue
        try:
            # The frame's own content size must agree with the table before anything is allocated from it;
            # max_output_size bounds frames that do not declare one.
            declared = zstandard.frame_content_size(frame)
            if declared not in (expected, zstandard.CONTENTSIZE_UNKNOWN):
                raise InputError(path, f"{name} stream", f"zstd frame declares {declared} bytes (expected {expected})")
            out = decompressor.decompress(frame, max_output_size=expected)
        except zstandard.ZstdError as exc:
            raise InputError(path, f"{name} stream", f"corrupt zstd frame ({exc})") from None
        if len(out) != expected:
            raise InputError(path, f"{name} stream", f"decompresses to {len(out)} bytes (expected {expected})")
        streams[name] = out
    return {"version": version, "n": n, "sh_degree": sh_degree, "fractional_bits": fractional_bits,
            "flags": flags}, streams


def _skip_extensions(path: str, zone: bytes) -> None:
    """Walk the (type u32, byteLength u32, payload) extension records; unknown ones are skipped by length."""
    offset = 0
    while offset < len(zone):
        if len(zone) - offset < 8:
            raise InputError(path, "extension records", f"{len(zone) - offset} stray bytes before the table of "
                             "contents (expected 8-byte record headers)")
        ext_type, length = struct.unpack_from("<II", zone, offset)
        if offset + 8 + length > len(zone):
            raise InputError(path, f"extension record 0x{ext_type:08x}", f"byteLength {length} runs past the table "
                             "of contents")
        offset += 8 + length


def _decode(path: str, info: dict, streams: dict[str, bytes]) -> Gaussians:
    n, version, sh_degree = info["n"], info["version"], info["sh_degree"]
    pos_bytes = np.frombuffer(streams["positions"], np.uint8).reshape(n, 3, 3).astype(np.int32)
    fixed = pos_bytes[..., 0] | (pos_bytes[..., 1] << 8) | (pos_bytes[..., 2] << 16)
    fixed = (fixed ^ 0x800000) - 0x800000  # sign-extend 24 bits
    positions = fixed.astype(np.float32) * np.float32(1.0 / (1 << info["fractional_bits"]))
    alphas = np.frombuffer(streams["alphas"], np.uint8).astype(np.float32) / np.float32(255.0)
    colors = np.frombuffer(streams["colors"], np.uint8).reshape(n, 3).astype(np.float32)
    sh_dc = (colors / np.float32(255.0) - np.float32(0.5)) / np.float32(COLOR_SCALE)
    log_scales = np.frombuffer(streams["scales"], np.uint8).reshape(n, 3).astype(np.float32) / 16.0 - 10.0
    if version >= 3:
        xyzw = _unpack_smallest_three(np.frombuffer(streams["rotations"], "<u4"))
    else:
        xyz = np.frombuffer(streams["rotations"], np.uint8).reshape(n, 3).astype(np.float32) / np.float32(127.5) - 1
        w = np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(axis=1)))
        xyzw = np.concatenate([xyz, w[:, None]], axis=1)
    dim = SH_DIM[sh_degree]
    sh = (np.frombuffer(streams["sh"], np.uint8).reshape(n, dim, 3).astype(np.float32) - 128.0) / 128.0
    # RUB -> RDF.
    positions *= np.array([1, -1, -1], np.float32)
    xyzw[:, 1:3] *= -1
    sh *= _SH_FLIP[:dim, None]
    if sh_degree > 3:
        warnings.warn(f"{path}: SH degree 4 is not supported; band 4 dropped", stacklevel=3)
        sh = sh[:, :SH_REST_COEFFS[3]]
    if info["flags"] & FLAG_ANTIALIASED:
        warnings.warn(f"{path}: trained with antialiasing (mip-splatting); the flag is not kept", stacklevel=3)
    return Gaussians(
        positions=positions,
        rotations=normalize_quaternions(xyzw[:, [3, 0, 1, 2]]),
        log_scales=log_scales,
        opacity_logits=opacity_logits_from_unit(alphas),
        sh_dc=sh_dc,
        sh_rest=sh,
    )


def _unpack_smallest_three(words: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w from SPZ v3 words: 2-bit index of the largest component, then for each other
    component from the last to the first a sign bit and a 9-bit magnitude scaled by 1/sqrt(2)."""
    words = words.astype(np.uint32)
    largest = (words >> 30).astype(np.intp)
    out = np.empty((len(words), 4), np.float32)
    sqrt1_2 = np.float32(0.7071067811865476)
    for index in range(4):
        rows = np.nonzero(largest == index)[0]
        comp = words[rows]
        sum_squares = np.zeros(len(rows), np.float32)
        for c in (3, 2, 1, 0):
            if c == index:
                continue
            magnitude = (comp & 511).astype(np.float32)
            negative = ((comp >> 9) & 1).astype(bool)
            comp = comp >> 10
            value = sqrt1_2 * magnitude / np.float32(511.0)
            value[negative] *= -1
            out[rows, c] = value
            sum_squares += value * value
        out[rows, index] = np.sqrt(np.maximum(0.0, 1.0 - sum_squares))
    return out


def read_spz(path: str | os.PathLike, drop_invalid: bool = False) -> Gaussians:
    """Decode SPZ v2, v3 or v4 into RDF axes. Every byte pattern decodes to finite values, so there are no
    invalid splats to drop (`drop_invalid` is accepted for a uniform signature)."""
    path = os.fspath(path)
    with open(path, "rb") as f:
        data = f.read()
    return decode_spz(path, data)


def decode_spz(path: str, data: bytes) -> Gaussians:
    """Decode SPZ bytes (a file, or a glTF buffer view); `path` names the source in error messages."""
    if data[:4] == MAGIC:
        info, streams = _read_v4(path, data)
    elif data[:2] == b"\x1f\x8b":
        info, streams = _read_legacy(path, data)
    else:
        raise InputError(path, "header", "not an SPZ file (expected 'NGSP' or a gzip stream)")
    return _decode(path, info, streams)
