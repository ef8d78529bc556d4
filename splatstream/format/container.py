"""Payload files (format_spec/format.md 5): one zstd frame per (tile, group) holding its planes.

A payload decompresses to the concatenation of its sections (texels of each plane, then its ranges),
each starting at a 16-byte aligned offset and stored through the filter its manifest entry names.
The manifest records, per section, where it starts and how to read it; per payload, the SHA-256 of the
file bytes (which is also the file name) so every fetch can be verified.

Writing streams (`write_payload`); reading works on bytes (`verify_payload`, `unpack_payload`): whatever brought
the bytes (a file, HTTP, memory) is the caller's business.
"""
from __future__ import annotations

import hashlib
import io
from typing import BinaryIO

import numpy as np
import zstandard

from ..errors import FormatError
from .codec import EncodedPlane
from .layout import ALIGN
from .limits import MAX_ABS_POSITION, MAX_LOG_SCALE, MIN_LOG_SCALE
from .manifest import PayloadEntry, Section, filter_for
from .names import payload_name, sha256_hex
from .planes import RANGE_DTYPE_NAMES, group_planes
from .texformats import TEXEL_DTYPES, blob_size, get_format, shuffle_bytes, unshuffle_bytes

WORKER_MODE_MAX_BYTES = 32 << 20


def write_payload(planes: list[EncodedPlane], out: BinaryIO, chunks: int, level: int = 3,
                  shuffle: bool = True) -> PayloadEntry:
    """Stream a payload into `out` (zstd, hashing as it goes) and return its manifest entry.

    The section table is laid out from the sizes alone; texels are then compressed one layer at a time as the
    planes produce them (planes from `encode_plane(..., lazy=True)`), so the encoder never holds a whole
    decompressed payload or its compressed copy in memory. `chunks` is the tile's chunk count (range shapes).
    """
    sections: list[Section] = []
    offset = 0

    def add(name: str, kind: str, size: int, element: int, **extra) -> None:
        nonlocal offset
        offset += (-offset) % ALIGN
        filt = filter_for(element) if shuffle else "none"
        sections.append(Section(name, kind, offset, int(size), filt, **extra))
        offset += size

    for p in planes:
        fmt = get_format(p.format)
        add(p.spec.name, "texels", blob_size(fmt, p.width, p.height, p.spec.layers), fmt.shuffle,
            format=p.format, width=p.width, height=p.height, layers=p.spec.layers)
        if p.spec.range_dtype:
            item = np.dtype(p.spec.range_dtype).itemsize
            shape = (chunks, 2, p.spec.layers, p.spec.components)
            add(p.spec.range_name, "range", int(np.prod(shape)) * item, item,
                dtype=RANGE_DTYPE_NAMES[p.spec.range_dtype], shape=shape)
    digest = hashlib.sha256()
    written = 0

    class _Sink:
        def write(self, data: bytes) -> int:
            nonlocal written
            digest.update(data)
            written += len(data)
            return out.write(data)

    position = 0
    # zstd's worker mode measured 1.5 % smaller payloads on 62,500-splat tiles than the single-threaded mode at
    # the same speed (its output does not depend on the worker count), but it buffers whole jobs: on a 112 MB
    # payload it lifted the encoder's peak memory from 2.3x to 3.1x the input. Large payloads stream single-threaded.
    threads = -1 if offset <= WORKER_MODE_MAX_BYTES else 0
    cctx = zstandard.ZstdCompressor(level=level, threads=threads, write_content_size=True)
    with cctx.stream_writer(_Sink(), size=offset, closefd=False) as stream:

        def emit(section: Section, units) -> None:
            nonlocal position
            stream.write(bytes(section.offset - position))
            position = section.offset
            size = 0
            for unit in units:
                stream.write((shuffle_bytes(unit, section.element) if section.element > 1 else unit).data)
                size += unit.size
            if size != section.size:
                raise AssertionError(f"section {section.name}: {size} bytes, laid out as {section.size}")
            position += size

        it = iter(sections)
        for p in planes:
            emit(next(it), p.layers)
            if p.spec.range_dtype:
                emit(next(it), [np.ascontiguousarray(p.ranges).reshape(-1).view(np.uint8)])
    sha = digest.hexdigest()
    return PayloadEntry(payload_name(sha), sha, written, int(position), sum(s.size for s in sections),
                        tuple(sections))


def pack_payload(planes: list[EncodedPlane], level: int = 3, shuffle: bool = True) -> tuple[bytes, PayloadEntry]:
    """In-memory payload: (file bytes, manifest entry)."""
    buf = io.BytesIO()
    chunks = len(planes[0].ranges) if planes[0].ranges is not None else planes[0].chunks
    entry = write_payload(planes, buf, chunks, level, shuffle)
    return buf.getvalue(), entry


def verify_payload(data: bytes | memoryview, entry: PayloadEntry, source: str) -> None:
    """Size and SHA-256 against the manifest: nothing unverified is ever decoded."""
    if len(data) != entry.bytes:
        raise FormatError(source, "bytes", f"payload is {len(data)} bytes, the manifest says {entry.bytes}")
    if sha256_hex(data) != entry.sha256:
        raise FormatError(source, "sha256", "checksum mismatch: the payload is corrupt or was replaced")


def unpack_payload(data: bytes | memoryview, entry: PayloadEntry, group: str, source: str,
                   codebook: bool = False) -> dict[str, EncodedPlane]:
    """Decompress verified payload bytes into planes (texels still encoded; ranges as stored).

    The entry comes from a validated manifest, so the section table is consistent with the planes of `group`;
    what is checked here is what only the bytes can tell. With `codebook`, a tile's sh1 group holds the SH index
    plane (format_spec/format.md 4.7)."""
    try:
        raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=entry.raw_bytes)
    except zstandard.ZstdError as exc:
        raise FormatError(source, None, f"not a valid zstd payload ({exc})") from None
    if len(raw) != entry.raw_bytes:
        raise FormatError(source, "raw_bytes", f"payload decompresses to {len(raw)} bytes, expected "
                          f"{entry.raw_bytes}")
    buf = np.frombuffer(raw, np.uint8)
    planes: dict[str, EncodedPlane] = {}
    for spec in group_planes(group, codebook):
        s = entry.section(spec.name)
        texels = buf[s.offset:s.offset + s.size]
        unit = s.size // spec.layers
        layers = [unshuffle_bytes(texels[i * unit:(i + 1) * unit], s.element) for i in range(spec.layers)]
        if s.format in FLOAT_TEXEL_FORMATS:
            _check_float_texels(layers, s, source)
        ranges = None
        if spec.range_dtype:
            r = entry.section(spec.range_name)
            data_r = unshuffle_bytes(buf[r.offset:r.offset + r.size], r.element)
            ranges = data_r.view(np.dtype(spec.range_dtype)).reshape(r.shape)
            _check_ranges(ranges, spec.name, r.name, source)
        planes[spec.name] = EncodedPlane(spec, s.format, s.width, s.height, layers, ranges)
    return planes


# Float texel formats store t as a float, which could hold anything; integer and BC formats cannot leave [0, 1].
FLOAT_TEXEL_FORMATS = ("f32x4", "f16x4")
# Where a plane's values may lie (format.md 4.8); the other ranged planes are bounded by their f16 storage.
RANGE_LIMITS = {"position": (-MAX_ABS_POSITION, MAX_ABS_POSITION), "scale": (MIN_LOG_SCALE, MAX_LOG_SCALE)}


def _check_float_texels(layers: list[np.ndarray], s: Section, source: str) -> None:
    """format.md 4.2: every texel of a float format holds t in [0, 1] (a hostile t would decode to inf or NaN)."""
    dtype = TEXEL_DTYPES[s.format].base
    for layer in layers:
        t = np.frombuffer(layer, dtype)
        if not ((t >= 0) & (t <= 1)).all():  # NaN compares False
            bad = t[~((t >= 0) & (t <= 1))]
            raise FormatError(source, f"section {s.name}", f"{bad.size} {s.format} texel values outside [0, 1] "
                              f"(first {float(bad[0])!r})")


def _check_ranges(ranges: np.ndarray, plane: str, name: str, source: str) -> None:
    """format.md 4.3 and 4.8: finite, min <= max, inside the plane's value domain. Then min + t (max - min) is
    finite for every t in [0, 1], in every decoder (numpy here, the GL client's shaders)."""
    lo, hi = ranges[:, 0].astype(np.float64), ranges[:, 1].astype(np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise FormatError(source, f"section {name}", "non-finite range values")
    if (lo > hi).any():
        chunk = int(np.argmax((lo > hi).reshape(len(lo), -1).any(axis=1)))
        raise FormatError(source, f"section {name}", f"chunk {chunk}: a range minimum exceeds its maximum")
    limit = RANGE_LIMITS.get(plane)
    if limit is not None and (lo.min() < limit[0] or hi.max() > limit[1]):
        raise FormatError(source, f"section {name}", f"range [{lo.min():g}, {hi.max():g}] leaves the {plane} "
                          f"domain [{limit[0]:g}, {limit[1]:g}] (format.md 4.8)")

