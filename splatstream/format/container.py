"""Payload files (format_spec/format.md 5): one zstd frame per (tile, group) holding its planes.

A payload decompresses to the concatenation of its sections (texels of each plane, then its ranges),
each starting at a 16-byte aligned offset and stored through the filter its manifest entry names (the byte
shuffle, or for texels the `fields1` transport coding of transport.py).
The manifest records, per section, where it starts and how to read it; per payload, the SHA-256 of the
file bytes (which is also the file name) so every fetch can be verified.

Writing streams (`write_payload`); reading works on bytes (`verify_payload`, `unpack_payload`): whatever brought
the bytes (a file, HTTP, memory) is the caller's business. Bytes are verified once, where they enter: verify_payload
gives back a `VerifiedPayload`, which readers hand on and decoding takes without hashing again.
"""
from __future__ import annotations

import functools
import hashlib
import io
import itertools
import math
import operator
import threading
from collections.abc import Callable, Mapping
from typing import BinaryIO

import numpy as np
import zstandard

from ..errors import FormatError
from .codec import EncodedPlane
from .keyed import MORTON1, MORTON_FORMATS, morton_content, unfilter_morton
from .layout import ALIGN
from .limits import MAX_ABS_POSITION, MAX_ABS_SH, MAX_LOG_SCALE, MIN_LOG_SCALE
from .manifest import PayloadEntry, Section, filter_element
from .names import digest_matches, payload_name, sha256_hex
from .planes import RANGE_DTYPE_NAMES, group_planes, palette_shape
from .texformats import PALETTE_FORMATS, TEXEL_DTYPES
from .transport import (
    CHECK_FAILED_FLOATS,
    CHECK_FAILED_RANGES,
    CHECK_NONE,
    CHECK_RANGES,
    FIELD_LAYOUTS,
    FIELDS1,
    FIELDS1_HEADER_BYTES,
    FIELDS1_ROWS,
    FLOAT_CHECKS,
    batch_kernels,
    field_bits,
    fields_kernel,
    filter_texels,
    run_whole_at,
    shuffle,
    shuffle_filter,
    trial_size,
    unfilter_fields_at,
    unfilter_fields_many,
    unfilter_texels,
    unshuffle,
    unshuffle_at,
    unshuffle_many,
    whole_kernel,
)

WORKER_MODE_MAX_BYTES = 32 << 20
# Payloads of at most this many decompressed bytes choose where their zstd blocks end by trial (_block_ends); larger
# ones end a block after every part, but where their preset joins them anyway (below). Blocks grow to at most
# MERGED_BLOCK_MAX bytes (a trial compresses the block so far again with each part added: this bounds that work).
MERGE_MAX_RAW = 1 << 18
MERGED_BLOCK_MAX = 1 << 16
# A larger payload's blocks where its preset joins them anyway (write_payload's `one_block_slack`: very-high) grow to
# zstd's largest block, 128 KB: on playbot's LOD tree zstd read very-high's payloads in 0.75-0.77x the time of a block
# a part at 128 KB, 0.89x at 64 KB, for 1.08 % and 0.88 % more bytes (issue 32; BENCHMARKS.md, "Decode speed", vhdec5).
LARGE_MERGED_BLOCK_MAX = 1 << 17
# The trials' level whatever the payload's: about the same choices as at level 9, in a fifth of the time.
MERGE_TRIAL_LEVEL = 1
# zstd level of the encoder's payloads. With a zstd block per byte plane, level 1 is as small as level 3 or smaller
# (fields1 planes are near noise, where level 3's extra short matches cost more than they save) and compresses about
# twice as fast; higher levels gain a few per cent at many times the time, and on the SH planes they write more
# (their shorter matches cost more than the literals: BENCHMARKS.md, Encoder, "zstd level with the LOD tree";
# "Figures behind library defaults").
DEFAULT_ZSTD_LEVEL = 1


def write_payload(planes: list[EncodedPlane], out: BinaryIO, chunks: int, level: int = DEFAULT_ZSTD_LEVEL,
                  transport: str = "fields", block_slack: float = 0.0, min_match: int = 0,
                  one_block_slack: float = 0.0) -> PayloadEntry:
    """Write a payload into `out` (zstd, hashing as it goes) and return its manifest entry.

    Each plane's texels are taken one layer at a time as the plane produces them (planes from
    `encode_plane(..., lazy=True)`) and stored through the filter `transport` picks (format.md 5.2: `fields1` where
    it is smaller than the byte shuffle); their stored sizes lay out the section table, then the sections go through
    one zstd frame, a zstd block ending with a part of a section (a byte plane; a layer of BC blocks; a range) unless
    it and the next code smaller in one block (_block_ends): parts of different statistics get their own literal
    tables, smaller than one table across them (format.md 5.2; BENCHMARKS.md, "Figures behind library defaults"),
    and like parts of a small payload share one, which its decoder reads faster (issue 32). The payload's stored
    sections are held until then, never its texels as a whole.
    `chunks` is the tile's chunk count (range shapes); `block_slack`: _block_ends' (the preset's); `min_match`: zstd's
    shortest match where not 0 (0: the level's own; the preset's, presets.PRESET_ZSTD_MIN_MATCH); `one_block_slack`
    where not 0: a payload whose blocks _block_ends joins (at most MERGE_MAX_RAW) is also compressed as one block,
    and stored so where that frame takes at most 1 + one_block_slack times the bytes of the joined blocks' (the
    preset's, presets.PRESET_ONE_BLOCK_SLACK); such a preset's payloads above MERGE_MAX_RAW join their parts too
    (_block_ends with `block_slack`, blocks up to LARGE_MERGED_BLOCK_MAX), where other presets' end a block after every
    part.
    """
    sections: list[Section] = []
    contents: list[list] = []
    offset = 0

    def add(name: str, kind: str, filt: str, parts: list, **extra) -> None:
        nonlocal offset
        offset += (-offset) % ALIGN
        size = sum(memoryview(p).nbytes for p in parts)
        sections.append(Section(name, kind, offset, size, filt, **extra))
        contents.append(parts)
        offset += size

    for p in planes:
        layers = p.spec.layers
        if transport == "keyed" and p.format in MORTON_FORMATS and layers == 1:
            filt, parts = _keyed_or_fields(p, level)
        else:
            filt, parts = filter_texels(p.layers, p.format, p.width, p.height, layers, level, transport)
        add(p.spec.name, "texels", filt, parts, format=p.format, width=p.width, height=p.height, layers=layers)
        if p.palette is not None and p.scene_palette:  # the scene's palettes (format.md 4.3.2, 1.7): no section
            pass
        elif p.palette is not None:  # a palette plane (format.md 4.3.2): its palettes stand where its ranges would
            palette = np.ascontiguousarray(p.palette, "<f4")
            expected = palette_shape(p.spec)
            if palette.size != int(np.prod(expected)):
                raise AssertionError(f"{p.spec.palette_name}: palette of shape {palette.shape}, expected {expected}")
            element = 4 if transport != "none" else 1
            add(p.spec.palette_name, "range", shuffle_filter(element), [shuffle(palette.reshape(-1), element)],
                dtype="f32", shape=expected)
        elif p.spec.range_dtype:
            item = np.dtype(p.spec.range_dtype).itemsize
            ranges = np.ascontiguousarray(p.ranges, p.spec.range_dtype)
            expected = (chunks, 2, layers, p.spec.components)
            if ranges.shape != expected:
                raise AssertionError(f"{p.spec.range_name}: ranges of shape {ranges.shape}, expected {expected}")
            element = item if transport != "none" else 1
            add(p.spec.range_name, "range", shuffle_filter(element), [shuffle(ranges, element)],
                dtype=RANGE_DTYPE_NAMES[p.spec.range_dtype], shape=expected)
    digest = hashlib.sha256()
    written = 0

    class _Sink:
        def write(self, data: bytes) -> int:
            nonlocal written
            digest.update(data)
            written += len(data)
            return out.write(data)

    # the stored bytes as zstd gets them: each section's padding before its first part; a block ends after the parts
    # _block_ends names (every part where the payload is large)
    segments: list = []
    position = 0
    for section, parts in zip(sections, contents, strict=True):
        pad = section.offset - position
        for j, part in enumerate(parts or [b""]):
            segments.append((bytes(pad) if j == 0 and pad else None, part))
        position = section.offset + section.size
    # why large payloads join too where the preset trades bytes for fewer blocks: very-high's payloads of a few
    # thousand splats (playbot's LOD tree) kept a block a byte plane, and each block's tables were about a third of
    # zstd's read time (issue 32; BENCHMARKS.md, "Decode speed", vhdec5)
    ends = _block_ends(segments, offset, block_slack, join_large=one_block_slack > 0)
    # zstd's worker mode makes slightly smaller payloads than the single-threaded mode at the same speed (its output
    # does not depend on the worker count), but it buffers whole jobs, which lifts the encoder's peak memory on large
    # payloads (BENCHMARKS.md, "Figures behind library defaults"). Large payloads stream single-threaded.
    threads = -1 if offset <= WORKER_MODE_MAX_BYTES else 0
    if one_block_slack and offset <= MERGE_MAX_RAW and sum(ends) > 1:
        # why one block where it costs little: a zstd block's literal and sequence tables are read before its bytes,
        # a fixed cost that is most of what the lossless preset's blocks of a small payload cost its reader beyond
        # their bytes (issue 32; presets.PRESET_ONE_BLOCK_SLACK)
        joined, one = io.BytesIO(), io.BytesIO()
        _compress_segments(joined, segments, ends, _compressor(level, threads, offset, min_match), offset)
        _compress_segments(one, segments, [False] * (len(ends) - 1) + [True],
                           _compressor(level, threads, offset, min_match), offset)
        chosen = one if one.tell() <= joined.tell() * (1.0 + one_block_slack) else joined
        _Sink().write(chosen.getvalue())
    else:
        _compress_segments(_Sink(), segments, ends, _compressor(level, threads, offset, min_match), offset)
    sha = digest.hexdigest()
    return PayloadEntry(payload_name(sha), sha, written, int(position), sum(s.gpu_size for s in sections),
                        tuple(sections))


def _compress_segments(sink, segments: list, ends: list[bool], cctx: zstandard.ZstdCompressor, raw_bytes: int) -> None:
    """One zstd frame of `segments` ((padding or None, part), `raw_bytes` in all) into `sink`, a zstd block ending
    after each segment `ends` names."""
    with cctx.stream_writer(sink, size=raw_bytes, closefd=False) as stream:
        for (pad, part), end in zip(segments, ends, strict=True):
            if pad is not None:
                stream.write(pad)
            stream.write(part)
            if end:
                stream.flush(zstandard.FLUSH_BLOCK)


def _compressor(level: int, threads: int, raw_bytes: int, min_match: int) -> zstandard.ZstdCompressor:
    """A payload's compressor: zstd `level` (its parameters for a frame of `raw_bytes`), with its shortest match
    `min_match` where that is not 0. Why a longer shortest match: on the lossy presets' small LOD payloads the
    matches of 3-5 bytes a level finds cost more bytes than the literals they replace and give the reader more
    sequences to decode (issue 32; presets.PRESET_ZSTD_MIN_MATCH)."""
    if not min_match:
        return zstandard.ZstdCompressor(level=level, threads=threads, write_content_size=True)
    params = zstandard.ZstdCompressionParameters.from_level(level, source_size=raw_bytes, min_match=min_match,
                                                            threads=threads, write_content_size=1)
    return zstandard.ZstdCompressor(compression_params=params)


def _trial_bytes(data: bytes) -> int:
    """zstd's size of `data` alone at MERGE_TRIAL_LEVEL (a compressor kept per thread: not thread-safe)."""
    c = getattr(_local, "merge_trial", None)
    if c is None:
        c = _local.merge_trial = zstandard.ZstdCompressor(level=MERGE_TRIAL_LEVEL, write_content_size=False)
    return len(c.compress(data))


def _block_ends(segments: list[tuple[bytes | None, object]], raw_bytes: int, slack: float = 0.0,
                join_large: bool = False) -> list[bool]:
    """Whether a zstd block ends after each segment ((padding or None, part): a byte plane, a layer, a range) of a
    payload of `raw_bytes` decompressed bytes. Above MERGE_MAX_RAW after every part, unless `join_large`. Else a part
    joins the block before it where the two coded as one block take no more bytes than each alone (zstd at
    MERGE_TRIAL_LEVEL; with `slack`, no more than 1 + slack times as many), and the block stays under MERGED_BLOCK_MAX
    bytes (LARGE_MERGED_BLOCK_MAX above MERGE_MAX_RAW): planes of like statistics (the high bytes of a plane's fields,
    the noise of low bytes) then share one literal table, and those of unlike statistics keep their own (format.md
    5.2).

    Why: a block's fixed cost, its tables written and read, is most of what a small payload's many 1 KB byte planes
    pay zstd beyond their literals. On guitar's and winter_fountain's 221 LOD tiles (about 820 splats a payload)
    this makes 5-15 blocks of the 22-58 a payload had (medians), 0.5-2.2 % fewer bytes and up to 4.5 us less zstd
    time a payload decoded (median 2.8), for 3-10 % more encoding CPU (BENCHMARKS.md, "Decode speed"; issue 32). A
    slack trades bytes for zstd's read time: each block's literal table costs the reader more than its bytes
    (very-high's: presets.PRESET_BLOCK_SLACK)."""
    count = len(segments)
    if count < 2 or (raw_bytes > MERGE_MAX_RAW and not join_large):
        return [True] * count
    most = MERGED_BLOCK_MAX if raw_bytes <= MERGE_MAX_RAW else LARGE_MERGED_BLOCK_MAX
    ends = [False] * count
    ends[-1] = True

    def data(k: int) -> bytes:
        pad, part = segments[k]
        return (pad or b"") + bytes(memoryview(part).cast("B"))

    def trial(part: bytes) -> int:  # a part above `most` joins nothing, nor anything it: its size is never compared
        return _trial_bytes(part) if len(part) <= most else 0

    block = data(0)
    block_size = trial(block)
    for k in range(1, count):
        part = data(k)
        alone = trial(part)
        if len(block) + len(part) <= most:
            joined = block + part
            joined_size = _trial_bytes(joined)
            if joined_size <= (block_size + alone) * (1.0 + slack):
                block, block_size = joined, joined_size
                continue
        ends[k - 1] = True
        block, block_size = part, alone
    return ends


def _keyed_or_fields(p: EncodedPlane, level: int) -> tuple[str, list]:
    """A one-layer section of a MORTON_FORMATS format stored as `morton1` (format.md 5.4) or as filter_texels
    chooses, whichever compresses smaller (tried at the trial level of transport.py, on the whole layer)."""
    layer = np.ravel(next(iter(p.layers)) if not isinstance(p.layers, list) else p.layers[0]).view(np.uint8)
    filt, parts = filter_texels([layer], p.format, p.width, p.height, 1, level, "fields")
    keyed = morton_content(layer, p.width, p.height)
    if trial_size(keyed, level) < trial_size(parts, level):
        return MORTON1, keyed
    return filt, parts


def pack_payload(planes: list[EncodedPlane], level: int = DEFAULT_ZSTD_LEVEL,
                 transport: str = "fields") -> tuple[bytes, PayloadEntry]:
    """In-memory payload: (file bytes, manifest entry)."""
    buf = io.BytesIO()
    chunks = len(planes[0].ranges) if planes[0].ranges is not None else planes[0].chunks
    entry = write_payload(planes, buf, chunks, level, transport)
    return buf.getvalue(), entry


_MINT = object()  # only verify_payload holds it: a VerifiedPayload is never made from unchecked bytes


class VerifiedPayload:
    """Payload bytes whose size and SHA-256 matched a manifest entry, checked once where they entered (the network,
    the disk cache, a scene directory). Only `verify_payload` makes one; `decode_payload` takes it without hashing
    the bytes again (the bytes of `bytes`, immutable, cannot change after the check). Pickled to a decode process it
    arrives as it left."""

    __slots__ = ("data", "sha256")

    def __init__(self, data: bytes, sha256: str, mint: object = None):
        if mint is not _MINT:
            raise TypeError("a VerifiedPayload is made by verify_payload (the bytes must be hashed)")
        self.data, self.sha256 = data, sha256

    def __len__(self) -> int:
        return len(self.data)

    def __repr__(self) -> str:
        return f"VerifiedPayload({len(self.data)} bytes, sha256 {self.sha256[:12]}...)"

    def matches(self, entry: PayloadEntry) -> bool:
        """These bytes are the payload `entry` names (its size and digest: the SHA-256, or its 1.15 prefix)."""
        return self.sha256 == entry.sha256 and len(self.data) == entry.bytes


def verify_payload(data: bytes | memoryview, entry: PayloadEntry, source: str) -> VerifiedPayload:
    """Size and SHA-256 against the manifest: nothing unverified is ever decoded. The entry's digest is the whole
    SHA-256 or (a 1.15 tile table's, format.md 6.2) its first 16 bytes, which the bytes' SHA-256 must begin with.
    The bytes, as `bytes`, come back as a VerifiedPayload to hand on (a memoryview or bytearray is copied: a
    verified buffer must not change)."""
    if len(data) != entry.bytes:
        raise FormatError(source, "bytes", f"payload is {len(data)} bytes, the manifest says {entry.bytes}")
    if not digest_matches(sha256_hex(data), entry.sha256):
        raise FormatError(source, "sha256", "checksum mismatch: the payload is corrupt or was replaced")
    return VerifiedPayload(data if type(data) is bytes else bytes(data), entry.sha256, _MINT)


def verified_bytes(data: bytes | memoryview | VerifiedPayload, entry: PayloadEntry, source: str) -> bytes:
    """The bytes of a payload for `entry`: a VerifiedPayload of that entry as it is, anything else verified now."""
    if type(data) is VerifiedPayload and data.matches(entry):
        return data.data
    raw = data.data if type(data) is VerifiedPayload else data
    return verify_payload(raw, entry, source).data


_local = threading.local()


def _decompressor() -> zstandard.ZstdDecompressor:
    """This thread's zstd decompressor (a context is not thread-safe; reusing one saves its setup per payload)."""
    d = getattr(_local, "decompressor", None)
    if d is None:
        d = _local.decompressor = zstandard.ZstdDecompressor()
    return d


# Payloads that decompress to at most this many bytes go into a buffer kept per thread (see _decompress).
KEEP_RAW_BYTES = 1 << 24


def _decompress(data: bytes | memoryview, size: int, source: str) -> tuple[np.ndarray, bool]:
    """The payload's `size` decompressed bytes and whether they lie in this thread's reused buffer (else, above
    KEEP_RAW_BYTES, in a fresh array). FormatError unless `data` is one zstd frame of exactly `size` bytes.

    Why a kept buffer: a tile's payload decompresses to a few hundred KB, above glibc's mmap threshold, and a
    fresh buffer's page faults then cost a large share of zstd's time (issue 15; BENCHMARKS.md, "Figures behind
    library defaults"). The bytes are only valid until this thread's next call: unpack_payload copies what of them
    it returns as views."""
    buf, kept = _raw_buffer(size)
    _decompress_into(data, buf, source)
    return buf, kept


def _raw_buffer(size: int) -> tuple[np.ndarray, bool]:
    """`size` bytes to decompress into: this thread's kept buffer (grown in powers of two) where they fit in
    KEEP_RAW_BYTES, else a fresh array; and whether it is the kept one."""
    if size > KEEP_RAW_BYTES:
        return np.empty(size, np.uint8), False
    buf = getattr(_local, "raw", None)
    if buf is None or buf.size < size:
        buf = _local.raw = np.empty(min(KEEP_RAW_BYTES, 1 << max(16, (size - 1).bit_length())), np.uint8)
    return buf[:size], True


def _decompress_into(data: bytes | memoryview, buf: np.ndarray, source: str) -> None:
    """Decompress `data` into `buf` (uint8): FormatError unless it is one zstd frame of exactly buf.size bytes."""
    size = buf.size
    extra = b""
    try:
        with _decompressor().stream_reader(data) as reader:
            got = reader.readinto(buf)  # a payload's frame in one read as a rule: a slice only when it comes short
            while got < size:
                k = reader.readinto(buf[got:])
                if not k:
                    break
                got += k
            extra = reader.read(1)
    except zstandard.ZstdError as exc:
        raise FormatError(source, None, f"not a valid zstd payload ({exc})") from None
    if extra:  # a bomb is cut off here: nothing past size + 1 bytes is decompressed
        raise FormatError(source, "raw_bytes", f"payload decompresses to more than the {size} bytes expected")
    if got != size:
        raise FormatError(source, "raw_bytes", f"payload decompresses to {got} bytes, expected {size} (a short "
                          "or truncated zstd frame)")


_element = functools.lru_cache(maxsize=32)(filter_element)  # a filter name's parse, once (not once a section)


def unpack_payload(data: bytes | memoryview, entry: PayloadEntry, group: str, source: str,
                   codebook: bool = False, between: Callable[[], object] | None = None,
                   palettes: Mapping[str, np.ndarray] | None = None) -> dict[str, EncodedPlane]:
    """Decompress verified payload bytes into planes (texels still encoded; ranges as stored).

    The entry comes from a validated manifest, so the section table is consistent with the planes of `group`;
    what is checked here is what only the bytes can tell. With `codebook`, a tile's sh1 group holds the SH index
    plane (format_spec/format.md 4.7). `between` is called before each plane: a decode thread's point to wait
    while another thread needs the interpreter (the streaming client's frame loop). `palettes`: the scene's
    palettes (Manifest.scene_palettes, format.md 4.3.2), for a palette plane whose payload has no palette section."""
    buf, kept = _decompress(data, entry.raw_bytes, source)
    if whole_kernel() is not None:  # every payload goes through the whole kernel where there is one
        return _unpack_group(buf, [0], [buf.size], [entry.sections], group, codebook, [source], between, kept,
                             palettes)[0]
    # What a small payload's decode spends beyond its splats is per-call Python and numpy work (issue 32: on the LOD
    # tree's tiles of a few hundred splats it was half the time), so this loop does only what each plane needs: the
    # section table read once into a dict, not searched per section; a view of the kept buffer found by its base.
    owner = buf if buf.base is None else buf.base
    sections = {s.name: s for s in entry.sections}
    planes: dict[str, EncodedPlane] = {}
    for spec in group_planes(group, codebook):
        if between is not None:
            between()
        s = sections[spec.name]
        if s.filter == MORTON1:  # format.md 5.4 (the manifest checked its format, layers and size)
            layers = [unfilter_morton(buf[s.offset:s.offset + s.size], s.width, s.height)]
        else:
            layers = unfilter_texels(buf[s.offset:s.offset + s.size], s.filter, s.format, s.width, s.height,
                                     spec.layers, f"{source} section {s.name}")
        if s.format in FLOAT_TEXEL_FORMATS:
            _check_float_texels(layers, s, source)
        ranges = palette = None
        if s.format in PALETTE_FORMATS:
            palette = _palette_of(buf, sections, spec, palettes, source)
        elif spec.range_dtype:
            r = sections[spec.range_name]
            ranges = unshuffle(buf[r.offset:r.offset + r.size], _element(r.filter)).view(spec.range_dtype) \
                .reshape(r.shape)
            _check_ranges(ranges, spec.name, r.name, source)
        if kept:  # what is still a view of this thread's buffer is copied: the next payload overwrites it
            layers = [p.copy() if p.base is owner else p for p in layers]
            if ranges is not None and ranges.base is owner:
                ranges = ranges.copy()
            if palette is not None and np.may_share_memory(palette, buf):
                palette = palette.copy()
        planes[spec.name] = EncodedPlane(spec, s.format, s.width, s.height, layers, ranges, palette,
                                         palette is not None and spec.palette_name not in sections)
    return planes


def unpack_payloads(items: list[tuple[bytes | memoryview, PayloadEntry]], group: str, sources: list[str],
                    codebook: bool = False, between: Callable[[], object] | None = None,
                    palettes: Mapping[str, np.ndarray] | None = None) -> list[dict[str, EncodedPlane]]:
    """unpack_payload of several verified payloads of one group (the tiles of one request, a scene's tiles): the
    same planes, bit for bit, but each step taken for all of them in one go where it can be: fields1 sections of
    the same format and modes through one work array (transport.unfilter_fields_many), shuffled sections and
    ranges through one unshuffle, the ranges of a plane checked together.

    Why: a payload of the LOD tree's median tile (600 splats) spent more than half its decode in per-call
    overhead, a fixed cost per payload, section and numpy call (issue 32; BENCHMARKS.md, decode speed). A
    payload that does not decode raises FormatError naming its source, as unpack_payload does; nothing of the
    others is returned then."""
    if not items:
        return []
    in_one_call = whole_kernel() is not None
    if not in_one_call and not all(_batchable(entry) for _, entry in items):
        # palette planes (format.md 4.3.2), and keyed positions (5.4) without the whole kernel, are decoded one
        # payload at a time
        return [unpack_payload(data, entry, group, source, codebook, between, palettes)
                for (data, entry), source in zip(items, sources, strict=True)]
    sizes = [entry.raw_bytes for _, entry in items]
    total = sum(sizes)
    if in_one_call and total > RUN_RAW_BYTES and len(items) > 1:
        # a large group in runs of about RUN_RAW_BYTES decompressed bytes, each read and decoded while it is in cache
        out: list[dict[str, EncodedPlane]] = []
        first = run_bytes = 0
        for k, size in enumerate(sizes):
            if k > first and run_bytes + size > RUN_RAW_BYTES:
                out += _unpack_run(items[first:k], sizes[first:k], run_bytes, group, sources[first:k], codebook,
                                   between, palettes, in_one_call)
                first, run_bytes = k, 0
            run_bytes += size
        return out + _unpack_run(items[first:], sizes[first:], run_bytes, group, sources[first:], codebook, between,
                                 palettes, in_one_call)
    return _unpack_run(items, sizes, total, group, sources, codebook, between, palettes, in_one_call)


# The whole kernel's path decodes a group in runs of at most this many decompressed bytes (one payload at least):
# zstd writes a run into this thread's kept buffer and the kernel reads it back while it is still in cache, and the
# kernel's output is a block malloc hands back warm. A whole group at once (very-high's LOD tree: 9-14 MB) went out
# to memory and back twice: very-high's pass takes 5-7 % less time in runs, the lossy presets' (3-5 MB) the same
# (issue 32; BENCHMARKS.md, "Decode speed", dec32). About this VM's L2 of a core: 256 KB paid the per-run Python,
# 4 MB lost the cache. 2 MB rather than 1 since vhdec32b: on the GPU machine's host (r31's kind, where very-high sits
# at the 10 M splats/s line) very-high's pass 1.04-1.05x faster, medium 1.01-1.03x, high 1.00-1.01x; on this VM
# very-high 1.03-1.05x, high 1.03x, medium 0.99-1.03x (BENCHMARKS.md, "very-high's decode, stage by stage").
RUN_RAW_BYTES = 2 << 20


def _unpack_run(items: list[tuple[bytes | memoryview, PayloadEntry]], sizes: list[int], total: int, group: str,
                sources: list[str], codebook: bool, between: Callable[[], object] | None,
                palettes: Mapping[str, np.ndarray] | None, in_one_call: bool) -> list[dict[str, EncodedPlane]]:
    """unpack_payloads of `items` (their raw sizes `sizes`, `total` in all) in one go: one zstd read where it can
    (_decompress_group), then the whole kernel's one call (`in_one_call`) or the batch kernels / numpy a plane at a
    time."""
    whole, kept = _raw_buffer(total)
    owner = whole if whole.base is None else whole.base
    firsts = [0, *itertools.accumulate(sizes[:-1])]
    if not _decompress_group(items, sizes, whole):  # else a payload at a time, which names a bad one
        for (data, _), first, size, source in zip(items, firsts, sizes, sources, strict=True):
            _decompress_into(data, whole[first:first + size], source)
    if in_one_call:  # the whole group in one compiled call
        return _unpack_group(whole, firsts, sizes, [entry.sections for _, entry in items], group, codebook, sources,
                             between, kept, palettes)
    bufs = [whole[first:first + size] for first, size in zip(firsts, sizes, strict=True)]
    tables = [{s.name: s for s in entry.sections} for _, entry in items]
    out: list[dict[str, EncodedPlane]] = [{} for _ in items]
    batched = None not in batch_kernels()
    for spec in group_planes(group, codebook):
        if between is not None:
            between()
        secs = [t[spec.name] for t in tables]
        if batched:
            # compiled batch kernels: a plane's sections of all payloads in one call per format (issue 32)
            layers = _texels_at(whole, firsts, bufs, secs, spec, sources)
            ranges = _ranges_at(whole, firsts, bufs, tables, spec, sources)
            _finish(out, spec, secs, layers, ranges, kept, owner)
            continue
        where = [f"{source} section {spec.name}" for source in sources]
        layers: list = [None] * len(items)
        # fields1 sections in batches of one (format, layer count, header); shuffled ones of one element
        fields_batches: dict[tuple, list[int]] = {}
        shuffled: dict[int, list[int]] = {}
        batch_fields = fields_kernel() is None  # a compiled kernel takes a section a call at little cost
        for k, (s, buf) in enumerate(zip(secs, bufs, strict=True)):
            if batch_fields and s.filter == FIELDS1 and s.format in FIELD_LAYOUTS:
                head = bytes(buf[s.offset:s.offset + min(s.size, 1 + len(field_bits(s.format)) * spec.layers)])
                fields_batches.setdefault((s.format, head), []).append(k)
            elif s.filter not in ("none", FIELDS1) and s.format not in FLOAT_TEXEL_FORMATS:
                shuffled.setdefault(_element(s.filter), []).append(k)
            else:
                layers[k] = unfilter_texels(buf[s.offset:s.offset + s.size], s.filter, s.format, s.width, s.height,
                                            spec.layers, where[k])
        for (fmt, _), ks in fields_batches.items():
            got = unfilter_fields_many([bufs[k][secs[k].offset:secs[k].offset + secs[k].size] for k in ks], fmt,
                                       [(secs[k].width, secs[k].height) for k in ks], spec.layers,
                                       [where[k] for k in ks])
            for k, section_layers in zip(ks, got, strict=True):
                layers[k] = section_layers
        for element, ks in shuffled.items():
            units, index = [], []
            for k in ks:
                s = secs[k]
                stored = bufs[k][s.offset:s.offset + s.size]
                unit = stored.size // spec.layers
                units += [stored[i * unit:(i + 1) * unit] for i in range(spec.layers)]
                index.append(k)
            got = unshuffle_many(units, element)
            for j, k in enumerate(index):
                layers[k] = got[j * spec.layers:(j + 1) * spec.layers]
        for k, s in enumerate(secs):
            if s.format in FLOAT_TEXEL_FORMATS:
                _check_float_texels(layers[k], s, sources[k])
        ranges: list = [None] * len(items)
        if spec.range_dtype:
            rs = [t[spec.range_name] for t in tables]
            element = _element(rs[0].filter)
            if all(r.filter == rs[0].filter for r in rs):
                got = unshuffle_many([buf[r.offset:r.offset + r.size] for buf, r in zip(bufs, rs, strict=True)],
                                     element)
            else:
                got = [unshuffle(buf[r.offset:r.offset + r.size], r.element) for buf, r in zip(bufs, rs, strict=True)]
            ranges = _checked_ranges(got, rs, spec, sources)
        _finish(out, spec, secs, layers, ranges, kept, owner)
    return out


# Groups of at most this many compressed bytes are read by one zstd reader (_decompress_group): their frames are
# copied end to end for it, and a payload large enough to matter gains nothing (the reader's setup is 1.5-2.5 us)
GROUP_READ_MAX_BYTES = 1 << 22


def _decompress_group(items: list[tuple[bytes | memoryview, PayloadEntry]], sizes: list[int],
                      whole: np.ndarray) -> bool:
    """Decompress several payloads into `whole`, one after the other, by one zstd reader over their frames end to end;
    True only if that gave exactly what a payload at a time (_decompress_into) would: every payload's frame declares
    its manifest size (zstd refuses a frame that then decodes to another size), and the frames decode to exactly
    whole.size bytes with nothing after them. False (nothing raised; `whole` may hold anything): decompress them a
    payload at a time, which refuses a bad one naming it. So a payload with a frame or bytes after its frame, a frame
    without its size, a bomb, or any zstd error goes the way it went before (refused, naming it, or read alone).

    Why: python-zstandard's setup of a reader, its first read and the check for more is 1.5-2.5 us a payload, a tenth
    of a small payload's zstd (issue 32: the LOD tree's payloads of a few hundred splats); one reader for a group
    of them pays it once (measured 1.3-2 us a payload less, the frames' copy end to end included). Groups above
    GROUP_READ_MAX_BYTES compressed go a payload at a time: no copy of their frames."""
    joined = sum(len(data) for data, _ in items)
    if len(items) < 2 or joined > GROUP_READ_MAX_BYTES:
        return False
    try:
        for (data, _), size in zip(items, sizes, strict=True):
            if zstandard.frame_content_size(data) != size:
                return False
        total = whole.size
        frames = _frames_buffer(joined)
        at = 0
        for data, _ in items:  # a memoryview's slices: about 0.6 us a frame, where numpy's concatenate took 0.9
            end = at + len(data)
            frames[at:end] = data
            at = end
        with _decompressor().stream_reader(frames[:joined], read_across_frames=True) as reader:
            got = reader.readinto(whole)
            while got < total:
                k = reader.readinto(whole[got:])
                if not k:
                    break
                got += k
            return got == total and not reader.read(1)
    except zstandard.ZstdError:
        return False


def _frames_buffer(size: int) -> memoryview:
    """A memoryview of this thread's kept buffer for a group's frames end to end (_decompress_group), at least `size`
    bytes (grown in powers of two, at most GROUP_READ_MAX_BYTES). Why kept: the frames joined into fresh bytes (a
    run's 0.4-0.7 MB) faulted their pages in again each run in a process whose malloc handed back new pages, about
    2,000 of a 12.5 ms pass's 5,300 faults on very-high's LOD tree on this VM (issue 32; BENCHMARKS.md, "Decode
    speed", vhdecode32)."""
    view = getattr(_local, "frames", None)
    if view is None or len(view) < size:
        view = _local.frames = memoryview(np.empty(1 << max(16, (size - 1).bit_length()), np.uint8)).cast("B")
    return view


def _batchable(entry: PayloadEntry) -> bool:
    """Without the whole kernel, the payload's planes can go through unpack_payloads' batches: no keyed positions, no
    palette planes (format.md 5.4, 4.3.2), which are decoded a plane at a time, one payload at a time. With the whole
    kernel every payload goes through _unpack_group, which decodes each morton1 section alone beside the kernel's call
    and reads each palette plane's palettes as unpack_payload does.

    Why those go whole too: a group of them decoded a payload at a time cost 1.5-2x as much a payload as one of the
    same size without them (medium-low-palette on guitar and winter_fountain, 221 payloads: 159 and 153 us against
    72-92 us; issue 32)."""
    return not any(sec.filter == MORTON1 or sec.format in PALETTE_FORMATS for sec in entry.sections)


def _unpack_group(whole: np.ndarray, firsts: list[int], sizes: list[int], sections: list[tuple[Section, ...]],
                  group: str, codebook: bool, sources: list[str], between: Callable[[], object] | None, kept: bool,
                  palettes: Mapping[str, np.ndarray] | None) -> list[dict[str, EncodedPlane]]:
    """Every plane of the payloads lying in `whole` (payload k from firsts[k], sizes[k] bytes; sections[k] its
    entry's sections) by one call of the whole kernel (transport.run_whole_at): every well-formed fields1 section,
    every shuffled or stored texel section and every range section of them all, into one fresh array. One pass of
    Python over the planes of the payloads plans the call, and one after it takes the views and checks them:

    * a fields1 section that is not well-formed (or of a format without a fields1 layout) is decoded alone in the
      planning pass by unfilter_texels, which raises FormatError naming its payload and section; a morton1 section
      is decoded alone after the call (unfilter_morton: format.md 5.4, the manifest checked its geometry);
    * a float plane's texels (format.md 4.2: t in [0, 1]) are checked at once for the whole group (_floats_ok); where
      that fails, or the plane's payloads differ in format, each payload's by _check_float_texels, which names a bad
      one;
    * a plane's ranges of every payload at once (_whole_ranges: a payload's own check only to name a bad one), a
      palette plane's palettes a payload at a time (_whole_palettes; `palettes`: the scene's, format.md 4.3.2); a
      plane with palettes in some payloads only (two scenes' payloads in one group) each payload's palettes or ranges
      alone (_mixed_plane), as unpack_payload reads them.

    Same bytes, bit for bit, as unpack_payload's numpy path. Why one call: a decode thread holds the interpreter lock
    for the Python around each compiled call and takes it back after each one; the streaming client's frame thread
    waits for it (issue 38's fly-through p99), and on the LOD tree's small payloads (a few hundred splats) that Python
    is the largest part of a payload's decode beside zstd (issue 32). So each section's row, and where its texels will
    lie in the kernel's output, are worked out in the one walk that finds it, and the views taken after the call from
    those offsets. (This folds decpy2's two planners, the fast one and the one that kept the refusals: issue 32.)"""
    specs = group_planes(group, codebook)
    # Each payload's bytes and sections by name, made only where a rare path needs them (a section decoded alone, a
    # palette or mixed plane): a dict and a slice a payload were about 1 us of its Python (vhdec33)
    bufs: list[np.ndarray] = [whole[first:first + size] for first, size in zip(firsts, sizes, strict=True)] \
        if len(firsts) == 1 else _LazyBufs(whole, firsts, sizes)
    tables = _LazyTables(sections)
    view = whole.data  # the headers' bytes through a memoryview (a third of a numpy slice's cost)
    header_of, rows_of, elements, float_checks = FIELDS1_HEADER_BYTES, FIELDS1_ROWS, _ELEMENTS, FLOAT_CHECKS
    owner = whole if whole.base is None else whole.base
    flat: list[int] = []  # run_whole_at's 3 ints a fields1 section
    unit_rows: list[int] = []  # and its 5 a shuffled unit
    span_rows: list[int] = []  # and its 4 a plane's ranges checked in the kernel
    index: dict[tuple, int] = {}  # (format, layers, header, width, height) -> its index in the tables' key
    out_bytes = 0
    plan = []  # per plane: (spec, per payload (section, where its texels start in out or -1: decoded alone, bytes,
    #            the layers' starts or None: the layers one after the other; or its layers decoded alone), where each
    #            payload's ranges start or _PALETTES or None, (float format, span, gaps) or None, floats a payload,
    #            palettes in some payloads only)
    for spec in specs:
        count, name = spec.layers, spec.name
        texels: list[tuple] = []
        add = texels.append
        float_format = None
        floats_each = False  # the plane's float texels checked a payload at a time (two formats, or decoded alone)
        plane_first = -1
        palette_plane = None  # whether the plane's payloads have palettes in place of ranges
        mixed = False  # palettes in some payloads only (payloads of two scenes): each read alone, as unpack_payload
        pads: list[tuple[int, int]] = []  # alignment gaps between the plane's texels (where, bytes)
        secs = _named(sections, name)
        s = secs[0]
        fmt, filt = s.format, s.filter
        uniform = True  # every payload's section of one format and filter: what each needs decided once (below)
        for s in secs:
            if s.format != fmt or s.filter != filt:
                uniform = False
                break
        per_layer = header_of.get(fmt) if filt == FIELDS1 else None
        planned = False  # by one of the two loops for a uniform plane
        views = True  # every payload's texels a stretch of out (none decoded alone, no layers apart)
        if uniform and per_layer is not None and fmt not in PALETTE_FORMATS:
            # the common case, a fields1 plane of one format (issue 32, vhdec33: the Python around the kernel, 10-13
            # us a payload, was the largest part of a pass but zstd): each section a header read, a cached row and
            # its run_whole_at row; what unpack_payload's checks need decided once for the plane
            palette_plane = False
            is_float = fmt in FLOAT_TEXEL_FORMATS
            if is_float:
                float_format = fmt
            head = 1 + per_layer * count
            for k, (s, first) in enumerate(zip(secs, firsts, strict=True)):
                at = first + s.offset
                key = (fmt, count, view[at:at + head].tobytes(), s.width, s.height)
                row = rows_of[key]
                if row is None or s.size != row[0]:  # not well-formed: decoded alone, which refuses it naming it
                    add((s, -1, 0, _texels_alone(bufs[k], s, count, sources[k], kept, owner)))
                    floats_each = floats_each or is_float
                    views = False
                    continue
                nbytes = row[4]
                pad = -out_bytes % 16
                if pad:
                    if plane_first >= 0:
                        pads.append((out_bytes, pad))
                    out_bytes += pad
                u = index.get(key)
                if u is None:
                    u = index[key] = len(index)
                flat += (at, out_bytes, u)
                add((s, out_bytes, nbytes, None))
                if plane_first < 0:
                    plane_first = out_bytes
                out_bytes += nbytes
            planned = True
        elif uniform and count == 1 and filt not in (FIELDS1, MORTON1) and fmt not in PALETTE_FORMATS:
            # a shuffled (or stored) plane of one format and one layer: a unit a payload (as below)
            palette_plane = False
            if fmt in FLOAT_TEXEL_FORMATS:
                float_format = fmt
            element = elements.get(filt) or _element(filt)
            check = float_checks.get(fmt, CHECK_NONE)
            for s, first in zip(secs, firsts, strict=True):
                unit = s.size
                e = 1 if element <= 1 or unit % element else element
                if e in (2, 4, 8):  # aligned for views of its elements
                    pad = -out_bytes % e
                    if pad:
                        if plane_first >= 0:
                            pads.append((out_bytes, pad))
                        out_bytes += pad
                unit_rows += (first + s.offset, unit // e, e, out_bytes, check)
                if plane_first < 0:
                    plane_first = out_bytes
                add((s, out_bytes, unit, None))
                out_bytes += unit
            planned = True
        for s, first in () if planned else zip(secs, firsts, strict=True):  # each payload adds one entry to texels
            fmt, filt = s.format, s.filter
            is_palette = fmt in PALETTE_FORMATS
            if palette_plane is None:
                palette_plane = is_palette
            elif is_palette is not palette_plane:
                mixed = True
            if fmt in FLOAT_TEXEL_FORMATS:
                if float_format is None:
                    float_format = fmt
                elif fmt != float_format:
                    floats_each = True
            if filt == FIELDS1:
                per_layer = header_of.get(fmt)
                row = None
                if per_layer is not None:
                    at = first + s.offset
                    key = (fmt, count, view[at:at + 1 + per_layer * count].tobytes(), s.width, s.height)
                    row = rows_of[key]
                if row is None or s.size != row[0]:  # not well-formed: decoded alone, which refuses it naming it
                    k = len(texels)  # this payload's index
                    add((s, -1, 0, _texels_alone(bufs[k], s, count, sources[k], kept, owner)))
                    floats_each = floats_each or fmt in FLOAT_TEXEL_FORMATS
                    views = False
                    continue
                nbytes = row[4]
                pad = -out_bytes % 16
                if pad and plane_first >= 0:
                    pads.append((out_bytes, pad))
                out_bytes += pad
                u = index.get(key)
                if u is None:
                    u = index[key] = len(index)
                flat += (at, out_bytes, u)
                add((s, out_bytes, nbytes, None))
                if plane_first < 0:
                    plane_first = out_bytes
                out_bytes += nbytes
            elif filt == MORTON1:  # decoded alone after the call (format.md 5.4; the manifest checked its geometry)
                add((s, -1, 0, None))
                views = False
            else:  # shuffled (float formats too: checked by the kernel, CHECK_F32/F16), a unit a layer; "none" a unit
                # of 1-byte elements, which the kernel copies
                element = elements.get(filt) or _element(filt)
                check = float_checks.get(fmt, CHECK_NONE)
                unit = s.size // count
                if element <= 1 or unit % element:
                    element = 1
                at = first + s.offset
                starts = None if count == 1 else []
                for i in range(count):
                    if element in (2, 4, 8):  # aligned for views of its elements
                        pad = -out_bytes % element
                        if pad and plane_first >= 0:
                            pads.append((out_bytes, pad))
                        out_bytes += pad
                    if plane_first < 0:
                        plane_first = out_bytes
                    unit_rows += (at + i * unit, unit // element, element, out_bytes, check)
                    if starts is not None:
                        starts.append(out_bytes)
                    else:
                        add((s, out_bytes, unit, None))
                    out_bytes += unit
                if starts is not None:
                    add((s, starts[0], unit, starts))
                    views = False
        float_span = None
        ranges_checked = False  # the plane's ranges all checked by the kernel (a span of span_rows)
        if float_format is not None and not floats_each and plane_first >= 0:
            float_span = (float_format, plane_first, out_bytes, pads)
        else:
            floats_each = float_format is not None
        range_at = None
        range_sections: list[Section] = []  # the plane's range sections (not mixed: one a payload)
        range_shape = None  # their shape less the first axis where every one has it and they lie in a row, else None
        if palette_plane and not mixed:
            range_at = _PALETTES
        elif spec.range_dtype or mixed:  # a plane's ranges in a row, each aligned to its element: checked at once
            range_at = []
            range_name = spec.range_name
            in_row = True
            range_dtype = spec.range_dtype
            range_check = CHECK_NONE if mixed else (_RANGE_CHECKS.get((name, range_dtype))
                                                    or _RANGE_CHECKS.get(("", range_dtype), CHECK_NONE))
            if mixed:
                for k, first in enumerate(firsts):
                    if secs[k].format in PALETTE_FORMATS or not spec.range_dtype:
                        range_at.append(-1)  # its palettes (or no ranges): _mixed_plane
                        continue
                    r = tables[k][range_name]
                    size, filt = r.size, r.filter
                    element = elements.get(filt) or _element(filt)
                    if element <= 1 or size % element:
                        element = 1
                    if element in (2, 4, 8):
                        pad = -out_bytes % element
                        if pad and range_sections:
                            in_row = False
                        out_bytes += pad
                    if range_sections:
                        if r.shape[1:] != range_shape:
                            in_row = False
                    else:
                        range_shape = r.shape[1:]
                    range_sections.append(r)
                    unit_rows += (first + r.offset, size // element, element, out_bytes, CHECK_NONE)
                    range_at.append(out_bytes)
                    out_bytes += size
            else:  # a range section a payload, as above, with the first one's filter and shape looked at once
                range_sections = _named(sections, range_name)
                r = range_sections[0]
                filt0, shape0 = r.filter, r.shape
                range_shape = shape0[1:]
                element0 = elements.get(filt0) or _element(filt0)
                for r, first in zip(range_sections, firsts, strict=True):
                    size, filt = r.size, r.filter
                    element = element0 if filt == filt0 else elements.get(filt) or _element(filt)
                    if element <= 1 or size % element:
                        element = 1
                    if element in (2, 4, 8):
                        pad = -out_bytes % element
                        if pad:
                            if range_at:
                                in_row = False
                            out_bytes += pad
                    if r.shape is not shape0 and r.shape[1:] != range_shape:
                        in_row = False
                    unit_rows += (first + r.offset, size // element, element, out_bytes, CHECK_NONE)
                    range_at.append(out_bytes)
                    out_bytes += size
            if not in_row:
                range_shape = None
            elif range_check != CHECK_NONE and range_sections:
                # the plane's ranges in a row, of one shape: checked by the kernel as one span (its status says
                # whether all passed) in chunks of `half` minimums then `half` maximums, as _ranges_ok pairs them;
                # else _whole_ranges checks them after the call
                half = math.prod(range_shape) // 2
                if half and not math.prod(range_shape) % 2:
                    span_rows += (range_at[0], out_bytes - range_at[0], half, range_check)
                    ranges_checked = True
        plan.append((spec, texels, range_at, range_sections, range_shape, float_span, floats_each, mixed,
                     ranges_checked, views))
    if between is not None:
        between()
    out, status = run_whole_at(whole, flat, tuple(index), unit_rows, out_bytes, span_rows, _CHECK_BOUNDS)
    floats_passed = not status & CHECK_FAILED_FLOATS  # every float texel the kernel wrote in [0, 1]
    ranges_passed = not status & CHECK_FAILED_RANGES  # every range it checked finite, ordered, in its domain
    result: list[dict[str, EncodedPlane]] = [{} for _ in firsts]
    for (spec, texels, range_at, range_sections, range_shape, float_span, floats_each, mixed,
         ranges_checked, views) in plan:
        if between is not None:
            between()
        count, name = spec.layers, spec.name
        plane_palettes = None
        if mixed:
            checked, plane_palettes = _mixed_plane(out, range_at, bufs, tables, spec, palettes, sources, kept)
        elif range_at is _PALETTES:
            plane_palettes = _whole_palettes(bufs, tables, spec, palettes, sources, kept)
            checked = [None] * len(texels)
        elif range_at is None:
            checked = [None] * len(texels)
        else:
            checked = _whole_ranges(out, range_at, range_sections, range_shape, spec, sources,
                                    ranges_checked and ranges_passed)
        if float_span is not None and not (floats_passed and _whole_floats(*float_span)) \
                and not _floats_ok(out, *float_span):
            floats_each = True  # some payload's texels leave [0, 1] (or the stretch is not whole floats): named below
        if views and count == 1 and plane_palettes is None and not floats_each:
            # the common case: each payload's one layer a view of out, its ranges checked above (vhdec33)
            for planes, (s, first, size, _), plane_ranges in zip(result, texels, checked, strict=True):
                planes[name] = EncodedPlane(spec, s.format, s.width, s.height, [out[first:first + size]],
                                            plane_ranges)
            continue
        for k, (planes, (s, first, size, starts), plane_ranges) in enumerate(zip(result, texels, checked,
                                                                                  strict=True)):
            if first < 0:
                if starts is not None:  # decoded alone in the planning pass
                    layers = starts
                else:  # morton1: a fresh array, not a view of the kept buffer
                    layers = [unfilter_morton(bufs[k][s.offset:s.offset + s.size], s.width, s.height)]
            elif starts is not None:
                layers = [out[a:a + size] for a in starts]
            elif count == 1:
                layers = [out[first:first + size]]
            else:
                step = size // count
                layers = [out[first + i * step:first + (i + 1) * step] for i in range(count)]
            if floats_each and s.format in FLOAT_TEXEL_FORMATS:
                _check_float_texels(layers, s, sources[k])
            if plane_palettes is None or plane_palettes[k] is None:
                planes[name] = EncodedPlane(spec, s.format, s.width, s.height, layers, plane_ranges)
            else:
                palette, scene = plane_palettes[k]
                planes[name] = EncodedPlane(spec, s.format, s.width, s.height, layers, None, palette, scene)
    return result


_PALETTES: list[int] = []  # _unpack_group's mark of a palette plane in place of its ranges' offsets


_SHAPE = operator.attrgetter("shape")


def _named(sections: list[tuple[Section, ...]], name: str) -> list[Section]:
    """Each payload's section `name` (a validated entry has it): read at its place in the first payload's table where
    every payload's table has it there (a group's payloads list their sections in one order), else found by name."""
    i = next((j for j, s in enumerate(sections[0]) if s.name == name), 0)
    try:
        got = [ss[i] for ss in sections]
    except IndexError:
        got = None
    if got is not None:
        for s in got:
            if s.name != name:
                got = None
                break
    if got is None:
        got = [_section_named(ss, name) for ss in sections]
    return got


def _section_named(sections: tuple[Section, ...], name: str) -> Section:
    for s in sections:
        if s.name == name:
            return s
    raise KeyError(name)


class _LazyTables:
    """_unpack_group's payloads' sections by name (a dict a payload), each made when first read."""

    __slots__ = ("sections", "made")

    def __init__(self, sections: list[tuple[Section, ...]]):
        self.sections, self.made = sections, {}

    def __getitem__(self, k: int) -> dict[str, Section]:
        t = self.made.get(k)
        if t is None:
            t = self.made[k] = {s.name: s for s in self.sections[k]}
        return t

    def __len__(self) -> int:
        return len(self.sections)

    def __iter__(self):
        return (self[k] for k in range(len(self.sections)))


class _LazyBufs:
    """_unpack_group's payloads' bytes (payload k: whole[firsts[k]:firsts[k] + sizes[k]]), each sliced when read."""

    __slots__ = ("whole", "firsts", "sizes")

    def __init__(self, whole: np.ndarray, firsts: list[int], sizes: list[int]):
        self.whole, self.firsts, self.sizes = whole, firsts, sizes

    def __getitem__(self, k: int) -> np.ndarray:
        first = self.firsts[k]
        return self.whole[first:first + self.sizes[k]]

    def __len__(self) -> int:
        return len(self.firsts)

    def __iter__(self):
        return (self[k] for k in range(len(self.firsts)))


def _mixed_plane(out: np.ndarray, range_at: list[int], bufs: list[np.ndarray], tables: list[dict], spec,
                 palettes: Mapping[str, np.ndarray] | None, sources: list[str],
                 kept: bool) -> tuple[list, list]:
    """A plane with palettes (format.md 4.3.2) in some of the group's payloads only (a group of payloads of two
    scenes): each payload's ranges (from range_at[k] in the whole kernel's `out`; -1: none) or its palettes and
    whether they are the scene's, read and checked as unpack_payload reads them, a payload at a time."""
    checked: list = []
    got: list = []
    for buf, t, at, source in zip(bufs, tables, range_at, sources, strict=True):
        if t[spec.name].format in PALETTE_FORMATS:
            palette = _palette_of(buf, t, spec, palettes, source)
            if kept and np.may_share_memory(palette, buf):
                palette = palette.copy()
            got.append((palette, spec.palette_name not in t))
            checked.append(None)
            continue
        got.append(None)
        ranges = None
        if at >= 0:
            r = t[spec.range_name]
            ranges = out[at:at + r.size].view(spec.range_dtype).reshape(r.shape)
            _check_ranges(ranges, spec.name, r.name, source)
        checked.append(ranges)
    return checked, got


def _whole_floats(fmt: str, lo: int, hi: int, pads: list[tuple[int, int]]) -> bool:
    """Whether a float plane's stretch out[lo:hi] is whole floats of `fmt`: where the whole kernel's checks of every
    texel in it passed (transport.CHECK_F32, CHECK_F16), _floats_ok would pass it too."""
    return not (hi - lo) % FLOAT_TEXEL_BITS[fmt][1].itemsize


def _floats_ok(out: np.ndarray, fmt: str, lo: int, hi: int, pads: list[tuple[int, int]]) -> bool:
    """Every texel of a float plane (format.md 4.2: t in [0, 1]) in out[lo:hi] (the plane's texels of every payload,
    one after the other, the alignment gaps `pads` between them zeroed first: 0 passes) in the bits of `fmt`'s floats,
    as _check_float_texels tests them; False also where the stretch is not whole floats."""
    _, bits, one, negative_zero = FLOAT_TEXEL_BITS[fmt]
    if hi <= lo:
        return True
    for at, size in pads:
        out[at:at + size] = 0
    if (hi - lo) % bits.itemsize:
        return False
    u = np.frombuffer(out[lo:hi], bits)
    return not (u.max() > one and not ((u <= one) | (u == negative_zero)).all())


# The elements of the shuffle filters a writer uses (format.md 5.1), without _element's cached call
_ELEMENTS = {f"shuffle{element}": element for element in range(2, 17)} | {"none": 1}


def _texels_alone(buf: np.ndarray, s: Section, count: int, source: str, kept: bool,
                  owner: np.ndarray) -> list[np.ndarray]:
    """A texel section the whole kernel does not take (a fields1 section that is not well-formed, or of a format
    without a fields1 layout) decoded alone by unfilter_texels, which raises FormatError naming `source` and the
    section where it cannot be decoded; what is still a view of this thread's kept buffer copied (the next payload
    overwrites it)."""
    layers = unfilter_texels(buf[s.offset:s.offset + s.size], s.filter, s.format, s.width, s.height, count,
                             f"{source} section {s.name}")
    return [p.copy() if p.base is owner else p for p in layers] if kept else layers


def _whole_palettes(bufs: list[np.ndarray], tables: list[dict], spec, palettes: Mapping[str, np.ndarray] | None,
                    sources: list[str], kept: bool) -> list[tuple[np.ndarray, bool]]:
    """Each payload's palettes of a palette plane and whether they are the scene's (format.md 4.3.2), read and
    checked as unpack_payload reads them (a palette section copied out of this thread's kept buffer)."""
    out = []
    name = spec.palette_name
    for buf, t, source in zip(bufs, tables, sources, strict=True):
        palette = _palette_of(buf, t, spec, palettes, source)
        if kept and np.may_share_memory(palette, buf):
            palette = palette.copy()
        out.append((palette, name not in t))
    return out


def _whole_ranges(out: np.ndarray, range_at: list[int], rs: list[Section], shape: tuple | None, spec,
                  sources: list[str], passed: bool = False) -> list[np.ndarray]:
    """Each payload's ranges of one plane from the whole kernel's `out` (payload k's range section rs[k], its bytes
    from range_at[k]), checked: all at once where they lie in a row with one shape less the first axis (`shape`, else
    None; _unpack_group's planner found that in its walk over them, which saves this a second one: issue 32), as
    slices of one view, a payload's own check only to name a bad one (_checked_ranges). `passed`: the whole kernel
    checked them all and every one passed (transport.CHECK_RANGES): the views alone."""
    first = range_at[0]
    if len(rs) == 1:  # one payload: its own check
        r = rs[0]
        one = out[first:first + r.size].view(spec.range_dtype).reshape(r.shape)
        if not passed:
            _check_ranges(one, spec.name, r.name, sources[0])
        return [one]
    if shape is not None:
        last = rs[-1]
        together = out[first:range_at[-1] + last.size].view(spec.range_dtype).reshape(-1, *shape)
        if passed or _ranges_ok(together, spec.name):
            if len(set(map(_SHAPE, rs))) == 1:  # each payload's ranges of one shape: views by a reshape (vhdec33)
                return list(together.reshape(len(rs), *rs[0].shape))
            views, chunk = [], 0
            for r in rs:
                rows = r.shape[0]
                views.append(together[chunk:chunk + rows])
                chunk += rows
            return views
    got = [out[at:at + r.size] for at, r in zip(range_at, rs, strict=True)]
    if passed:
        return [g.view(spec.range_dtype).reshape(r.shape) for g, r in zip(got, rs, strict=True)]
    return _checked_ranges(got, rs, spec, sources)


def _finish(out: list[dict], spec, secs: list[Section], layers: list, ranges: list, kept: bool,
            owner: np.ndarray) -> None:
    """Each payload's plane `spec` into `out`, copying what is still a view of this thread's kept buffer (the next
    payload overwrites it)."""
    for k, s in enumerate(secs):
        lay, rng = layers[k], ranges[k]
        if kept:
            lay = [p.copy() if p.base is owner else p for p in lay]
            if rng is not None and rng.base is owner:
                rng = rng.copy()
        out[k][spec.name] = EncodedPlane(spec, s.format, s.width, s.height, lay, rng)


def _texels_at(whole: np.ndarray, firsts: list[int], bufs: list[np.ndarray], secs: list[Section], spec,
               sources: list[str]) -> list:
    """Each payload's texel layers of one plane by the batch kernels (transport.use_batch_kernels): its fields1
    sections in one call per format, its shuffled ones in one call per element size, the sections lying in `whole`
    (the group's decompressed payloads, payload k from firsts[k]). A section the batch refuses (not well-formed), and
    any other filter, goes through unfilter_texels, which decodes it alone or raises FormatError naming it."""
    layers: list = [None] * len(secs)
    fields: dict[str, list[int]] = {}
    shuffled: dict[int, list[int]] = {}
    for k, s in enumerate(secs):
        if s.filter == FIELDS1 and s.format in FIELD_LAYOUTS:
            fields.setdefault(s.format, []).append(k)
        elif s.filter not in ("none", FIELDS1) and s.format not in FLOAT_TEXEL_FORMATS:
            shuffled.setdefault(_element(s.filter), []).append(k)
    count = spec.layers
    for fmt, ks in fields.items():
        got = unfilter_fields_at(whole, fmt, count, [(firsts[k] + secs[k].offset, secs[k].size, secs[k].width,
                                                      secs[k].height) for k in ks])
        if got is None:  # the batch kernel handed back since `batched` was read (decode_jit.warm_up): each below
            continue
        for k, texels in zip(ks, got, strict=True):
            if texels is not None:
                unit = texels.size // count
                layers[k] = [texels[i * unit:(i + 1) * unit] for i in range(count)]
    for element, ks in shuffled.items():
        units = []
        for k in ks:
            s = secs[k]
            unit = s.size // count
            units += [(firsts[k] + s.offset + i * unit, unit) for i in range(count)]
        got = unshuffle_at(whole, units, element)
        if got is not None:
            for j, k in enumerate(ks):
                layers[k] = got[j * count:(j + 1) * count]
    for k, s in enumerate(secs):
        if layers[k] is None:
            layers[k] = unfilter_texels(bufs[k][s.offset:s.offset + s.size], s.filter, s.format, s.width, s.height,
                                        count, f"{sources[k]} section {s.name}")
        if s.format in FLOAT_TEXEL_FORMATS:
            _check_float_texels(layers[k], s, sources[k])
    return layers


def _ranges_at(whole: np.ndarray, firsts: list[int], bufs: list[np.ndarray], tables: list[dict], spec,
               sources: list[str]) -> list:
    """Each payload's ranges of one plane (None where it has none), unshuffled by one batch kernel call where the
    range sections share a filter, and checked all at once (a payload's own check only to name a bad one)."""
    if not spec.range_dtype:
        return [None] * len(tables)
    rs = [t[spec.range_name] for t in tables]
    got = None
    if all(r.filter == rs[0].filter for r in rs):
        got = unshuffle_at(whole, [(first + r.offset, r.size) for first, r in zip(firsts, rs, strict=True)],
                           _element(rs[0].filter))
    if got is None:
        got = [unshuffle(buf[r.offset:r.offset + r.size], _element(r.filter)) for buf, r in zip(bufs, rs, strict=True)]
    return _checked_ranges(got, rs, spec, sources)


def _checked_ranges(got: list[np.ndarray], rs: list[Section], spec, sources: list[str]) -> list[np.ndarray]:
    """Each payload's ranges of one plane from its unshuffled range bytes `got`, checked in one go where they lie one
    after the other in one array (found from their base); a payload's own check only to say which one failed."""
    ranges = [g.view(spec.range_dtype).reshape(r.shape) for g, r in zip(got, rs, strict=True)]
    shapes = {r.shape[1:] for r in ranges}
    together = None
    base = got[0].base
    if len(ranges) > 1 and base is not None and all(g.base is base for g in got) \
            and base.nbytes == sum(g.nbytes for g in got):
        together = base.reshape(-1).view(np.uint8)
    if len(shapes) == 1 and together is not None:
        whole_r = together.view(spec.range_dtype).reshape(-1, *shapes.pop())
        if _ranges_ok(whole_r, spec.name):
            return ranges
    for k, r in enumerate(ranges):
        _check_ranges(r, spec.name, rs[k].name, sources[k])
    return ranges


# Float texel formats store t as a float, which could hold anything; integer and BC formats cannot leave [0, 1].
FLOAT_TEXEL_FORMATS = ("f32x4", "f16x4")


def _float_bits(fmt: str) -> tuple[np.dtype, np.dtype, int, int]:
    """A float texel format's float type, the unsigned type of its width, and the bit patterns of 1.0 and -0.0.
    A float in [0, 1] is a bit pattern in [0, that of 1.0] or -0.0 (IEEE 754 orders non-negative floats like their
    bits; NaN, inf and negatives lie above): comparing the bits as unsigned integers is several times faster than
    float comparisons, for float16 above all (decode speed, issue 15)."""
    float_type = TEXEL_DTYPES[fmt].base.newbyteorder("<")
    bits = np.dtype(f"<u{float_type.itemsize}")
    return float_type, bits, int(np.array(1.0, float_type).view(bits)), int(np.array(-0.0, float_type).view(bits))


FLOAT_TEXEL_BITS = {fmt: _float_bits(fmt) for fmt in FLOAT_TEXEL_FORMATS}
# Where a plane's values may lie (format.md 4.8); the other ranged planes are bounded by their f16 storage.
RANGE_LIMITS = {"position": (-MAX_ABS_POSITION, MAX_ABS_POSITION), "scale": (MIN_LOG_SCALE, MAX_LOG_SCALE)}
_NO_LIMIT = (-np.inf, np.inf)
_LIMITS32 = {plane: (float(np.float32(lo)), float(np.float32(hi))) for plane, (lo, hi) in RANGE_LIMITS.items()}
# The whole kernel's range checks (transport.CHECK_RANGES): a (plane, range dtype)'s code ("": a plane without
# limits), and each code's (low, high, bytes a value) as _ranges_ok compares them with the ranges kernel (_LIMITS32)
_RANGE_BOUNDS = [("", _NO_LIMIT)] + list(_LIMITS32.items())
_RANGE_CHECKS = {(plane, dtype): CHECK_RANGES + i * len(_RANGE_BOUNDS) + j
                 for i, dtype in enumerate(("<f4", "<f2")) for j, (plane, _) in enumerate(_RANGE_BOUNDS)}
_CHECK_BOUNDS = np.array([(0.0, 0.0, 0.0)] * CHECK_RANGES
                         + [(lo, hi, np.dtype(dtype).itemsize)
                            for dtype in ("<f4", "<f2") for _, (lo, hi) in _RANGE_BOUNDS], np.float64)
SMALL_RANGES = 256  # values of a range section checked in Python (_ranges_ok)


def _check_float_texels(layers: list[np.ndarray], s: Section, source: str) -> None:
    """format.md 4.2: every texel of a float format holds t in [0, 1] (a hostile t would decode to inf or NaN)."""
    float_type, bits, one, negative_zero = FLOAT_TEXEL_BITS[s.format]
    for layer in layers:
        u = np.frombuffer(layer, bits)
        if u.size == 0 or u.max() <= one:
            continue
        inside = (u <= one) | (u == negative_zero)
        if not inside.all():
            bad = np.frombuffer(layer, float_type)[~inside]
            raise FormatError(source, f"section {s.name}", f"{bad.size} {s.format} texel values outside [0, 1] "
                              f"(first {float(bad[0])!r})")


_ranges_kernel = None  # see use_ranges_kernel


def use_ranges_kernel(kernel) -> object:
    """Check ranges (_ranges_ok) with a compiled kernel (None: Python's floats and numpy's reductions, its
    reference); returns the one it replaces. Called as kernel(pairs, low, high) -> bool with `pairs` the ranges as
    float32 of shape (chunks, 2, values a chunk's minimum or maximum), C-ordered, and the plane's limits as float32
    values in Python floats (_LIMITS32): True only if every value is finite, every minimum at most its maximum, and
    all of them inside [low, high].

    Why: those checks, three range planes a payload, were 5-6 us a call in Python (a job of the engine's few small
    payloads checks each plane once; a payload alone once a plane), the largest single piece of a small payload's
    Python around the whole kernel (issue 32; BENCHMARKS.md, "Decode speed"). The core never imports numba: the
    streaming client hands the kernel in (client_gl/stream/decode_jit.py)."""
    global _ranges_kernel
    previous, _ranges_kernel = _ranges_kernel, kernel
    return previous


def _ranges_ok(ranges: np.ndarray, plane: str) -> bool:
    """_check_ranges' every check at once, in three reductions (those checks took 12 us a range section, a tenth of
    a small tile's decode: issue 32): a NaN fails every comparison, an infinite least minimum or greatest maximum
    fails the domain test, and +inf in a minimum or -inf in a maximum makes some max - min -inf."""
    if not ranges.size:
        return False
    r = ranges.astype(np.float32, copy=False)  # exact for f16, whose arithmetic numpy runs several times slower
    kernel = _ranges_kernel
    if kernel is not None and r.flags.c_contiguous:  # the compiled check (use_ranges_kernel); else the paths below
        low, high = _LIMITS32.get(plane, _NO_LIMIT)
        return bool(kernel(r.reshape(len(r), 2, -1), low, high))
    limit = RANGE_LIMITS.get(plane, _NO_LIMIT)
    if r.size <= SMALL_RANGES:
        # a tile's few chunks: Python's builtins over the floats beat the reductions' numpy calls (12 us a range
        # section, a tenth of a small payload's decode one at a time); the limits as float32, as numpy compares.
        # The sum of them all is finite only if every one is (a NaN or an infinity makes it NaN or infinite, and
        # float32 values cannot overflow a double's sum); then min, max and min <= max decide as above.
        pairs = r.reshape(len(r), 2, -1)
        lo, hi = pairs[:, 0].ravel().tolist(), pairs[:, 1].ravel().tolist()
        low, high = _LIMITS32.get(plane, _NO_LIMIT)
        return bool(math.isfinite(sum(lo) + sum(hi)) and low <= min(lo) and max(hi) <= high
                    and all(map(operator.le, lo, hi)))
    lo, hi = r[:, 0], r[:, 1]
    low, high = lo.min(), hi.max()
    # max - min only once no minimum is -inf and no maximum +inf (nor NaN): it then makes no inf - inf
    return bool(limit[0] <= low and high <= limit[1] and -np.inf < low and high < np.inf and (hi - lo).min() >= 0)


def _palette_of(buf: np.ndarray, sections: dict, spec, palettes: Mapping[str, np.ndarray] | None,
                source: str) -> np.ndarray:
    """A palette plane's palettes (format.md 4.3.2): its payload's `<plane>.palette` section when it has one, else
    the scene's (1.7: the manifest's `palettes`, checked when the manifest was)."""
    r = sections.get(spec.palette_name)
    if r is None:
        if palettes is None or spec.name not in palettes:
            raise FormatError(source, f"section {spec.palette_name}", "missing, and the scene has no palettes of "
                              f"{spec.name} (format.md 4.3.2)")
        return palettes[spec.name]
    palette = unshuffle(buf[r.offset:r.offset + r.size], r.element).view("<f4").reshape(r.shape[0], -1)
    _check_palette(palette, spec.name, r.name, source)
    return palette


def _check_palette(palette: np.ndarray, plane: str, name: str, source: str) -> None:
    """format.md 4.3.2 and 4.8: every palette entry finite and inside the plane's value domain (any index 0..255
    then decodes to a value a scene may hold)."""
    if not np.isfinite(palette).all():
        raise FormatError(source, f"section {name}", "non-finite palette values")
    lo, hi = RANGE_LIMITS.get(plane, (-MAX_ABS_SH, MAX_ABS_SH))
    if float(palette.min()) < lo or float(palette.max()) > hi:
        raise FormatError(source, f"section {name}", f"palette [{palette.min():g}, {palette.max():g}] leaves the "
                          f"{plane} domain [{lo:g}, {hi:g}] (format.md 4.8)")


def _check_ranges(ranges: np.ndarray, plane: str, name: str, source: str) -> None:
    """format.md 4.3 and 4.8: finite, min <= max, inside the plane's value domain. Then min + t (max - min) is
    finite for every t in [0, 1], in every decoder (numpy here, the GL client's shaders)."""
    if _ranges_ok(ranges, plane):
        return
    r = ranges.astype(np.float32, copy=False)
    lo, hi = r[:, 0], r[:, 1]
    limit = RANGE_LIMITS.get(plane, _NO_LIMIT)
    if not np.isfinite(r).all():
        raise FormatError(source, f"section {name}", "non-finite range values")
    if (lo > hi).any():
        chunk = int(np.argmax((lo > hi).reshape(len(lo), -1).any(axis=1)))
        raise FormatError(source, f"section {name}", f"chunk {chunk}: a range minimum exceeds its maximum")
    if limit is not _NO_LIMIT and (float(lo.min()) < limit[0] or float(hi.max()) > limit[1]):
        raise FormatError(source, f"section {name}", f"range [{lo.min():g}, {hi.max():g}] leaves the {plane} "
                          f"domain [{limit[0]:g}, {limit[1]:g}] (format.md 4.8)")

