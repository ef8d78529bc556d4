"""Payload files (format_spec/format.md, "Payloads"): one zstd frame per (tile, group) holding its planes.

A payload decompresses to the concatenation of its sections (texels of each plane, then its ranges),
each starting at a 16-byte aligned offset and stored through the filter its manifest entry names.
The manifest records, per section, where it starts and how to read it; per payload, the SHA-256 of the
file bytes (which is also the file name) so every fetch can be verified.
"""
from __future__ import annotations

import hashlib
import io
from typing import BinaryIO

import numpy as np
import zstandard

from .codec import EncodedPlane, PlaneSpec, group_planes
from .errors import FormatError
from .manifest import sha256_hex
from .texformats import blob_size, get_format, shuffle_bytes, unshuffle_bytes

ALIGN = 16
WORKER_MODE_MAX_BYTES = 32 << 20
# A payload may not claim to decompress to more than this (guards readers against decompression bombs).
MAX_PAYLOAD_RAW_BYTES = 2 << 30


def _filter_for(element: int) -> str:
    return f"shuffle{element}" if element > 1 else "none"


def _element_of(filter_name: str) -> int:
    if filter_name == "none":
        return 1
    if filter_name.startswith("shuffle") and filter_name[7:].isdigit():
        return int(filter_name[7:])
    raise ValueError(filter_name)


def write_group(planes: list[EncodedPlane], out: BinaryIO, chunks: int, level: int = 3, shuffle: bool = True) -> dict:
    """Stream a payload into `out` (zstd, hashing as it goes). Returns the manifest group entry without 'file'.

    The section table is laid out from the sizes alone; texels are then compressed one layer at a time as the
    planes produce them (planes from `encode_plane(..., lazy=True)`), so the encoder never holds a whole
    decompressed payload or its compressed copy in memory. `chunks` is the tile's chunk count (range shapes).
    """
    sections = []
    offset = 0

    def add(name: str, size: int, element: int, extra: dict) -> None:
        nonlocal offset
        offset += (-offset) % ALIGN
        filt = _filter_for(element) if shuffle else "none"
        sections.append({"name": name, "offset": offset, "size": int(size), "filter": filt, **extra})
        offset += size

    for p in planes:
        fmt = get_format(p.format)
        add(p.spec.name, blob_size(fmt, p.width, p.height, p.spec.layers), fmt.shuffle,
            {"kind": "texels", "format": p.format, "width": p.width, "height": p.height, "layers": p.spec.layers})
        if p.spec.range_dtype:
            item = np.dtype(p.spec.range_dtype).itemsize
            shape = [chunks, 2, p.spec.layers, p.spec.components]
            add(p.spec.name + ".range", int(np.prod(shape)) * item, item,
                {"kind": "range", "dtype": "f32" if item == 4 else "f16", "shape": shape})
    digest = hashlib.sha256()
    written = 0

    class _Sink:
        def write(self, data: bytes) -> int:
            nonlocal written
            digest.update(data)
            written += len(data)
            return out.write(data)

    position = 0
    gpu_bytes = 0
    # zstd's worker mode measured 1.5 % smaller payloads on 62,500-splat tiles than the single-threaded mode at
    # the same speed (its output does not depend on the worker count), but it buffers whole jobs: on a 112 MB
    # payload it lifted the encoder's peak memory from 2.3x to 3.1x the input. Large payloads stream single-threaded.
    threads = -1 if offset <= WORKER_MODE_MAX_BYTES else 0
    cctx = zstandard.ZstdCompressor(level=level, threads=threads, write_content_size=True)
    with cctx.stream_writer(_Sink(), size=offset, closefd=False) as stream:

        def emit(section: dict, units) -> None:
            nonlocal position, gpu_bytes
            stream.write(bytes(section["offset"] - position))
            position = section["offset"]
            size = 0
            for unit in units:
                element = _element_of(section["filter"])
                stream.write((shuffle_bytes(unit, element) if element > 1 else unit).data)
                size += unit.size
            if size != section["size"]:
                raise AssertionError(f"section {section['name']}: {size} bytes, laid out as {section['size']}")
            position += size
            gpu_bytes += size

        it = iter(sections)
        for p in planes:
            emit(next(it), p.layers)
            if p.spec.range_dtype:
                emit(next(it), [np.ascontiguousarray(p.ranges).reshape(-1).view(np.uint8)])
    return {"sha256": digest.hexdigest(), "bytes": written, "raw_bytes": int(position), "gpu_bytes": int(gpu_bytes),
            "sections": sections}


def pack_group(planes: list[EncodedPlane], level: int = 3, shuffle: bool = True) -> tuple[bytes, dict]:
    """In-memory payload: (file bytes, manifest group entry without 'file')."""
    buf = io.BytesIO()
    chunks = len(planes[0].ranges) if planes[0].ranges is not None else planes[0].chunks
    entry = write_group(planes, buf, chunks, level, shuffle)
    return buf.getvalue(), entry


def verify_payload(data: bytes, entry: dict, source: str) -> None:
    if len(data) != entry["bytes"]:
        raise FormatError(source, "bytes", f"payload is {len(data)} bytes, the manifest says {entry['bytes']}")
    if sha256_hex(data) != entry["sha256"]:
        raise FormatError(source, "sha256", "checksum mismatch: the payload is corrupt or was replaced")


def unpack_group(data: bytes, entry: dict, group: str, splats: int, source: str,
                 codebook: bool = False) -> dict[str, EncodedPlane]:
    """Decompress and parse a payload into planes, checking every size against the manifest.

    With `codebook`, a tile's sh1 group holds the SH index plane (format_spec/format.md 4.7)."""
    raw_size = entry.get("raw_bytes")
    if not isinstance(raw_size, int) or not 0 <= raw_size <= MAX_PAYLOAD_RAW_BYTES:
        raise FormatError(source, "raw_bytes", f"expected an integer 0..{MAX_PAYLOAD_RAW_BYTES}, got {raw_size!r}")
    try:
        raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=raw_size)
    except zstandard.ZstdError as exc:
        raise FormatError(source, None, f"not a valid zstd payload ({exc})") from None
    if len(raw) != raw_size:
        raise FormatError(source, "raw_bytes", f"payload decompresses to {len(raw)} bytes, expected {raw_size}")
    buf = np.frombuffer(raw, np.uint8)
    sections = {s["name"]: s for s in entry["sections"]}
    planes: dict[str, EncodedPlane] = {}
    for spec in group_planes(group, codebook):
        planes[spec.name] = _read_plane(buf, sections, spec, splats, source)
    return planes


def _section(buf: np.ndarray, sections: dict, name: str, source: str) -> tuple[dict, np.ndarray, int]:
    s = sections.get(name)
    if s is None:
        raise FormatError(source, f"section {name}", "missing from the manifest entry")
    off, size = s.get("offset"), s.get("size")
    if not (isinstance(off, int) and isinstance(size, int) and 0 <= off and off + size <= buf.size):
        raise FormatError(source, f"section {name}", f"offset {off!r} + size {size!r} outside the {buf.size}-byte "
                          "payload")
    try:
        element = _element_of(s.get("filter", "none"))
    except ValueError:
        raise FormatError(source, f"section {name}.filter", f"unknown filter {s.get('filter')!r} "
                          "(expected none or shuffleN)") from None
    return s, buf[off:off + size], element


def _read_plane(buf: np.ndarray, sections: dict, spec: PlaneSpec, splats: int, source: str) -> EncodedPlane:
    s, texels, element = _section(buf, sections, spec.name, source)
    try:
        fmt = get_format(s.get("format"))
    except Exception:
        raise FormatError(source, f"section {spec.name}.format", f"unknown texel format {s.get('format')!r}") from None
    width, height, layers = s.get("width"), s.get("height"), s.get("layers")
    chunks = max(1, -(-splats // 256))
    if not (isinstance(width, int) and isinstance(height, int) and width % 16 == 0 and height % 16 == 0
            and width > 0 and height > 0 and (width // 16) * (height // 16) >= chunks):
        raise FormatError(source, f"section {spec.name}", f"texture {width}x{height} cannot hold {chunks} chunks")
    if layers != spec.layers or texels.size != blob_size(fmt, width, height, layers):
        raise FormatError(source, f"section {spec.name}", f"{texels.size} bytes for {layers} layers of {width}x"
                          f"{height} {fmt.name}, expected {spec.layers} layers")
    layer_size = texels.size // spec.layers
    layers = [unshuffle_bytes(texels[i * layer_size:(i + 1) * layer_size], element) for i in range(spec.layers)]
    ranges = None
    if spec.range_dtype:
        r, data, element = _section(buf, sections, spec.name + ".range", source)
        data = unshuffle_bytes(data, element)
        dtype = np.dtype("<f4" if r.get("dtype") == "f32" else "<f2")
        shape = (chunks, 2, spec.layers, spec.components)
        if list(r.get("shape", [])) != list(shape) or data.size != int(np.prod(shape)) * dtype.itemsize:
            raise FormatError(source, f"section {spec.name}.range", f"shape {r.get('shape')!r}, expected {list(shape)}")
        ranges = data.view(dtype).reshape(shape)
        if not np.isfinite(ranges).all():
            raise FormatError(source, f"section {spec.name}.range", "non-finite range values")
    return EncodedPlane(spec, fmt.name, width, height, layers, ranges)
