"""The manifest's one validator: a map (format.md 6) into frozen records, or a FormatError naming the first field
that is wrong (`tiles[3].groups.base.bytes`) and what was expected.

Everything a reader later relies on is checked here: types, ranges, the tile tree (one root, every tile reachable
once, levels), splat and chunk counts, texture sizes, and every payload's section table against the planes its
group must hold. Each field is checked once, by plain dict operations, and a message is built only when a check
fails: the same functions serve the eager parse and the lazily checked payload entries (`lazy_payloads`), so
both name a damaged field with the same message.

Messages (format_spec/format.md 6, "Validation"): `<file>: <field path>: <problem>`; a key that is absent is
"missing", a key a known version does not define is "unknown key 'k'", a value of the wrong type or range is
"expected <what>, got <value>".
"""
from __future__ import annotations

import contextlib
import functools
import gc
import math
import operator
from typing import NoReturn

import numpy as np

from ...errors import FormatError
from ..keyed import MORTON1, MORTON_FORMATS
from ..layout import ALIGN, BLOCK, CHUNK_SIZE
from ..limits import MAX_ABS_SH, MAX_LOG_SCALE, MIN_LOG_SCALE
from ..names import MANIFEST_NAME, SHA256_HEX_RE, SHORT_DIGEST_BYTES, payload_name
from ..planes import (
    MAX_SH_DEGREE,
    PALETTE_ATTRIBUTES,
    RANGE_DTYPE_NAMES,
    SH_INDEX_FORMAT,
    band_plane,
    chunks_for,
    group_planes,
    groups_for_degree,
    palette_shape,
)
from ..texformats import FORMATS, PALETTE_FORMATS, ROTATION_ONLY_FORMATS, VALUE_FORMATS
from ..transport import FIELD_LAYOUTS, FIELDS1, content_bounds
from .model import (
    AttributeSize,
    Box,
    CameraEntry,
    LazyPayloads,
    LevelRefinement,
    LodInfo,
    LodRefinement,
    Manifest,
    PagedInfo,
    PageRef,
    PayloadEntry,
    Section,
    SHCodebookEntry,
    Table,
    TablePayloads,
    TileEntry,
    entry_fields,
    filter_element,
    texels_size,
)
from .table import (
    TABLE_KEY,
    TABLE_ZSTD_KEY,
    canonical_offsets,
    read_columns,
    relative_boxes,
    short_digests,
    unpack_compact_table,
)
from .versions import (
    CHECKSUM_VERSION,
    CHUNK_ORDERS_1_4,
    FORMAT_NAME,
    FORMAT_VERSION,
    FORMATS_1_3,
    FORMATS_1_6,
    FORMATS_1_13,
    FORMATS_1_14,
    VERSION_1_3,
    VERSION_1_4,
    VERSION_1_5,
    VERSION_1_6,
    VERSION_1_7,
    VERSION_1_8,
    VERSION_1_9,
    VERSION_1_10,
    VERSION_1_11,
    VERSION_1_12,
    VERSION_1_13,
    VERSION_1_14,
)
from .wire import CHECKSUM_KEY, unpack_manifest, verify_checksum

# A payload may not claim to decompress to more than this (guards readers against decompression bombs).
MAX_PAYLOAD_RAW_BYTES = 2 << 30
MAX_WASTED_BLOCKS = 128  # max_blocks: a row of the widest texture (2048 texels)
MAX_TILES = 1 << 20
MAX_PAGE_BYTES = 64 << 20  # a page is a manifest's top levels' size (format.md 6.1): far below a manifest's limit
PAGE_FORMAT = "splatstream-page"
MAX_SECTIONS = 64
CHUNK_ORDER_NAMES = ("morton", "luminance", "input")
FILTERS_DOC = "none, shuffleN or, for texels, fields1 or morton1"
ATTRIBUTES = ("position", "rotation", "scale", "color", "sh")

# Keys of each map, in the order they are read (a missing one is named in this order).
_TOP_KEYS = ("format", "version", "splats", "sh_degree", "formats", "chunk_size", "chunk_order", "tiles", "root",
             "leaf_splats", "camera", "up", "lod", "attributes", "generator", "name", "preset", "bounds",
             "extent_bounds", "gpu_bytes", "gpu_bytes_per_splat", "leaf_bytes_on_disk", "encode_seconds",
             "bytes_on_disk")
_TOP_KEYS_TABLE = tuple(TABLE_KEY if k == "tiles" else k for k in _TOP_KEYS)  # 1.8: the tile table (6.2)
_TOP_KEYS_COMPACT = tuple(TABLE_ZSTD_KEY if k == "tiles" else k for k in _TOP_KEYS)  # 1.12: the compact table
_TILE_KEYS = ("id", "splats", "chunks", "texture", "sphere", "groups", "level", "children", "box", "geometric_error")
_PAYLOAD_KEYS = ("sha256", "file", "raw_bytes", "bytes", "gpu_bytes", "sections")
_SECTION_KEYS = ("name", "kind", "offset", "size", "filter")
_KIND_KEYS = {"texels": _SECTION_KEYS + ("format", "width", "height", "layers"),
              "range": _SECTION_KEYS + ("dtype", "shape")}
_KEY_SETS: dict[tuple[str, ...], frozenset[str]] = {}  # each tuple of keys as a set (made once, when first used)
_PAYLOAD_SET = frozenset(_PAYLOAD_KEYS)
_KIND_SETS = {kind: frozenset(keys) for kind, keys in _KIND_KEYS.items()}
_FILTER_ELEMENTS = {"none": 1, **{f"shuffle{n}": n for n in range(2, 17)}}
_INF = math.inf
_NUMBER = (float, int)  # msgpack's numbers (a bool is neither type)
_isfinite = math.isfinite


# --------------------------------------------------------------------------------------------------------------
# Field checks: each returns the value or raises FormatError(source, "path.key", problem)


def _where(path: str, key: str | None) -> str | None:
    if key is None:
        return path or None
    return f"{path}.{key}" if path else key


def _fail(source: str, path: str, key: str | None, problem: str) -> NoReturn:
    raise FormatError(source, _where(path, key), problem)


def _key_set(keys: tuple[str, ...]) -> frozenset[str]:
    key_set = _KEY_SETS.get(keys)
    if key_set is None:
        key_set = _KEY_SETS[keys] = frozenset(keys)
    return key_set


def _keys(d, keys: tuple[str, ...], source: str, path: str, strict: bool, optional: tuple[str, ...] = ()) -> dict:
    """`d` is a map holding `keys` (and, in a version this reader knows, nothing but them and `optional`: format.md
    6, Versioning). Returns `d`."""
    if type(d) is not dict:
        raise FormatError(source, path or None, f"expected a map, got {type(d).__name__}")
    if d.keys() == _key_set(keys):
        return d
    for k in keys:
        if k not in d:
            _fail(source, path, k, "missing")
    if strict:
        extra = sorted(str(k) for k in d if k not in keys and k not in optional)
        if extra:
            _fail(source, path, None, f"unknown key{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra))}")
    return d


def _int(d: dict, key: str, source: str, path: str, lo: int = 0, hi: int = 2**62) -> int:
    v = d[key]
    if type(v) is not int or not lo <= v <= hi:
        _fail(source, path, key, f"expected an integer {lo}..{hi}, got {v!r}")
    return v


def _float(d: dict, key: str, source: str, path: str, lo: float = -_INF, hi: float = _INF) -> float:
    v = d[key]
    if type(v) not in (float, int) or not math.isfinite(v) or not lo <= v <= hi:
        _fail(source, path, key, f"expected a finite number in [{lo}, {hi}], got {v!r}")
    return float(v)


def _str(d: dict, key: str, source: str, path: str, choices: tuple[str, ...] | None = None) -> str:
    v = d[key]
    if type(v) is not str or (choices is not None and v not in choices):
        want = f"one of {', '.join(choices)}" if choices else "a string"
        _fail(source, path, key, f"expected {want}, got {v!r}")
    return v


def _bool(d: dict, key: str, source: str, path: str) -> bool:
    v = d[key]
    if type(v) is not bool:
        _fail(source, path, key, f"expected true or false, got {v!r}")
    return v


def _vec(d: dict, key: str, source: str, path: str) -> tuple[float, float, float]:
    v = d[key]
    if type(v) in (list, tuple) and len(v) == 3:
        x, y, z = v
        if type(x) in _NUMBER and type(y) in _NUMBER and type(z) in _NUMBER and _isfinite(x) and _isfinite(y) \
                and _isfinite(z):
            return (float(x), float(y), float(z))
    _fail(source, path, key, f"expected 3 finite numbers, got {v!r}")


def _ints(d: dict, key: str, source: str, path: str, n: int | None, lo: int, hi: int) -> tuple[int, ...]:
    v = d[key]
    if type(v) not in (list, tuple) or (n is not None and len(v) != n) or not all(type(x) is int and lo <= x <= hi
                                                                                  for x in v):
        count = f"{n} " if n is not None else ""
        _fail(source, path, key, f"expected a list of {count}integers {lo}..{hi}, got {v!r}")
    return tuple(v)


def _list(d: dict, key: str, source: str, path: str, limit: int) -> list:
    v = d[key]
    if type(v) not in (list, tuple) or len(v) > limit:
        _fail(source, path, key, f"expected a list of at most {limit} items, got {type(v).__name__}")
    return v


def _box(d: dict, key: str, source: str, path: str, strict: bool) -> Box:
    where = _where(path, key)
    b = _keys(d[key], ("min", "max"), source, where, strict)
    lo, hi = _vec(b, "min", source, where), _vec(b, "max", source, where)
    if lo[0] > hi[0] or lo[1] > hi[1] or lo[2] > hi[2]:
        _fail(source, where, None, f"min {lo} exceeds max {hi}")
    return Box(lo, hi)


# --------------------------------------------------------------------------------------------------------------
# Payload entries and their sections (format.md 5)


@functools.lru_cache(maxsize=1024)
def max_blocks(chunks: int) -> int:
    """The most 16x16 blocks a texture of `chunks` chunks may have (format.md 4.1): twice the chunks and one row of
    the widest texture. The encoder's textures waste less than a row; a larger one declares texels nothing fills
    (a 1-splat tile claiming 8192x8192, a gigabyte to decompress and upload)."""
    return 2 * chunks + MAX_WASTED_BLOCKS


@functools.lru_cache(maxsize=4096)  # a large scene's thousands of sections repeat a few shapes
def _stored_size_rule(fmt: str, width: int, height: int, layers: int, filt: str) -> tuple[int, int, int, str | None]:
    """(smallest and largest stored size, GPU bytes, what is wrong with the filter or None) of a texels section: the
    texture's bytes for none/shuffleN, a size within what the fields1 layout allows (format.md 5.2; the exact size
    depends on modes only the bytes hold)."""
    gpu = texels_size(fmt, width, height, layers)
    if filt == MORTON1:  # format.md 5.4: exactly the texels' size
        if fmt not in MORTON_FORMATS or layers != 1:
            return gpu, gpu, gpu, f"morton1 applies to one layer of {', '.join(MORTON_FORMATS)} only, not {layers} " \
                f"of {fmt}"
        return gpu, gpu, gpu, None
    if filt != FIELDS1:
        return gpu, gpu, gpu, None
    if fmt not in FIELD_LAYOUTS:
        return 0, 0, gpu, f"fields1 does not apply to texel format {fmt}"
    lo, hi = content_bounds(fmt, width, height, layers)
    return lo, hi, gpu, None


def _odd_shuffle(filt: str) -> bool:
    """A shuffle filter spelled other than shuffle2..shuffle16 that filter_element still reads (`shuffle04`)."""
    try:
        filter_element(filt)
    except ValueError:
        return False
    return True


# Sections are made without the frozen dataclass's __init__ (its eleven object.__setattr__ calls were a third of the
# time to parse a large scene's manifest): object.__new__, then the checked fields into its __dict__.
_new = object.__new__


def _bad_int(source: str, path: str, key: str, v, lo: int, hi: int) -> NoReturn:
    _fail(source, path, key, f"expected an integer {lo}..{hi}, got {v!r}")


def _spath(at: tuple[str, int]) -> str:
    return f"{at[0]}.sections[{at[1]}]"


def _texels(s: dict, want: dict, chunks: int, filt: str, length: int, source: str, at: tuple[str, int]) -> tuple:
    """(format, width, height, layers, GPU bytes) of a texels section."""
    fmt, width, height, layers = s["format"], s["width"], s["height"], s["layers"]
    if fmt != want["format"]:
        _str(s, "format", source, _spath(at), tuple(FORMATS))
        _fail(source, _spath(at), "format", f"expected {want['format']!r} (the manifest's format for this plane), "
              f"got {fmt!r}")
    if type(width) is not int or not BLOCK <= width <= 1 << 16:
        _bad_int(source, _spath(at), "width", width, BLOCK, 1 << 16)
    if type(height) is not int or not BLOCK <= height <= 1 << 16:
        _bad_int(source, _spath(at), "height", height, BLOCK, 1 << 16)
    blocks = (width // BLOCK) * (height // BLOCK)
    if width % BLOCK or height % BLOCK or blocks < chunks:
        _fail(source, _spath(at), None, f"texture {width}x{height} cannot hold {chunks} chunks of {BLOCK}x{BLOCK} "
              "texels")
    if blocks > max_blocks(chunks):
        _fail(source, _spath(at), None, f"texture {width}x{height} has {blocks} blocks of {BLOCK}x{BLOCK} texels "
              f"for {chunks} chunks (at most {max_blocks(chunks)}: format.md 4.1)")
    if type(layers) is not int or not 1 <= layers <= 64:
        _bad_int(source, _spath(at), "layers", layers, 1, 64)
    if layers != want["layers"]:
        _fail(source, _spath(at), "layers", f"expected {want['layers']}, got {layers}")
    lo, hi, gpu, problem = _stored_size_rule(fmt, width, height, layers, filt)
    if problem is not None:
        _fail(source, _spath(at), "filter", problem)
    if not lo <= length <= hi:
        _fail(source, _spath(at), "size", f"{length} bytes for {layers} layers of {width}x{height} {fmt}, expected "
              f"{lo}" if filt != FIELDS1 else f"{length} bytes of fields1 content for {layers} layers of "
              f"{width}x{height} {fmt}, expected {lo}..{hi}")
    return fmt, width, height, layers, gpu


def _range(s: dict, want: dict, length: int, source: str, at: tuple[str, int]) -> tuple:
    """(dtype, shape) of a range section."""
    dtype, shape = s["dtype"], s["shape"]
    if dtype != want["dtype"]:
        _str(s, "dtype", source, _spath(at), ("f32", "f16"))
        _fail(source, _spath(at), "dtype", f"expected {want['dtype']!r}, got {dtype!r}")
    # Equal to the expected shape (integers in range) and made of ints, not bools (True == 1): nothing else to check.
    if type(shape) is not list or shape != want["shape"] or not (type(shape[0]) is type(shape[1]) is type(shape[2])
                                                                 is type(shape[3]) is int):
        shape = _ints(s, "shape", source, _spath(at), 4, 0, 1 << 24)
        if list(shape) != want["shape"]:
            _fail(source, _spath(at), "shape", f"expected {list(want['shape'])}, got {list(shape)}")
    need = (4 if dtype == "f32" else 2) * shape[0] * shape[1] * shape[2] * shape[3]
    if length != need:
        _fail(source, _spath(at), "size", f"{length} bytes for a {dtype} range of shape {list(shape)}, expected {need}")
    return dtype, tuple(shape)


def _name_or_kind_problem(s: dict, want: dict | None, expect: list, source: str, at: tuple[str, int]) -> NoReturn:
    """The section's name is not one its group holds, or its kind is not the one that name has."""
    if want is None:
        name = _str(_keys(s, ("name",), source, _spath(at), False), "name", source, _spath(at))
        _fail(source, _spath(at), "name", f"unexpected section {name!r} (this payload holds "
              f"{', '.join(n for n, _ in expect)})")
    _keys(s, _SECTION_KEYS[:2], source, _spath(at), False)
    _str(s, "kind", source, _spath(at), ("texels", "range"))
    _fail(source, _spath(at), "kind", f"expected {want['kind']!r}, got {s['kind']!r}")


def _section(s, i: int, expected: dict, expect: list, raw_bytes: int, chunks: int, strict: bool, source: str,
             ppath: str) -> tuple[Section, int]:
    """Section i of a payload entry at `ppath` and the bytes it decodes to; `expected` (name -> properties) loses
    the section's name."""
    at = (ppath, i)  # the section's path, made into a string only for a message
    if type(s) is not dict:
        raise FormatError(source, _spath(at), f"expected a map, got {type(s).__name__}")
    name = s.get("name")
    want = expected.pop(name, None) if type(name) is str else None
    if want is None or s.get("kind") != want["kind"]:
        _name_or_kind_problem(s, want, expect, source, at)
    kind = want["kind"]
    if s.keys() != _KIND_SETS[kind]:
        _keys(s, _KIND_KEYS[kind], source, _spath(at), strict)
    offset, length, filt = s["offset"], s["size"], s["filter"]
    if type(offset) is not int or not 0 <= offset <= raw_bytes:
        _bad_int(source, _spath(at), "offset", offset, 0, raw_bytes)
    if type(length) is not int or not 0 <= length <= raw_bytes:
        _bad_int(source, _spath(at), "size", length, 0, raw_bytes)
    if offset % ALIGN:
        _fail(source, _spath(at), "offset", f"{offset} is not a multiple of {ALIGN}")
    if offset + length > raw_bytes:
        _fail(source, _spath(at), "size", f"offset {offset} + size {length} lies outside the {raw_bytes}-byte "
              "payload")
    if type(filt) is not str:
        _str(s, "filter", source, _spath(at))
    texel_filter = filt in (FIELDS1, MORTON1) and kind == "texels"
    if filt not in _FILTER_ELEMENTS and not texel_filter and not _odd_shuffle(filt):
        _fail(source, _spath(at), "filter", f"unknown filter {filt!r} (expected {FILTERS_DOC})")
    sec = _new(Section)
    if kind == "texels":
        fmt, width, height, layers, gpu = _texels(s, want, chunks, filt, length, source, at)
        sec.__dict__.update(name=name, kind=kind, offset=offset, size=length, filter=filt, format=fmt, width=width,
                            height=height, layers=layers, dtype="", shape=())
        return sec, gpu
    dtype, shape = _range(s, want, length, source, at)
    sec.__dict__.update(name=name, kind=kind, offset=offset, size=length, filter=filt, format="", width=0, height=0,
                        layers=0, dtype=dtype, shape=shape)
    return sec, length


_offset = operator.attrgetter("offset")


def _payload(v, expect: list[tuple[str, dict]], chunks: int, strict: bool, source: str, path: str,
             derived_gpu: bool = False, short: bool = False) -> PayloadEntry:
    """A payload entry at `path`; `expect` is [(section name, {kind, format, layers, dtype, shape})]. derived_gpu:
    the entry's `gpu_bytes` is what its sections decode to (a tile table's, format.md 6.2), not a stated value.
    short: its digest is a 1.15 table's, the first 16 bytes of the SHA-256 (32 hex digits)."""
    if type(v) is not dict or v.keys() != _PAYLOAD_SET:
        _keys(v, _PAYLOAD_KEYS, source, path, strict)
    sha, file, raw_bytes, size, gpu_bytes, items = (v["sha256"], v["file"], v["raw_bytes"], v["bytes"],
                                                    v["gpu_bytes"], v["sections"])
    if short:
        if type(sha) is not str or len(sha) != 2 * SHORT_DIGEST_BYTES:
            _fail(source, path, "sha256", f"expected {2 * SHORT_DIGEST_BYTES} lowercase hex digits (a short digest), "
                  f"got {sha!r}")
    elif type(sha) is not str or not SHA256_HEX_RE.match(sha):
        _str(v, "sha256", source, path)
        _fail(source, path, "sha256", f"expected 64 lowercase hex digits, got {sha!r}")
    if file != payload_name(sha):
        _str(v, "file", source, path)
        _fail(source, path, "file", f"expected {payload_name(sha)!r} (the payload's name is its SHA-256), got "
              f"{file!r}")
    if type(raw_bytes) is not int or not 0 <= raw_bytes <= MAX_PAYLOAD_RAW_BYTES:
        _bad_int(source, path, "raw_bytes", raw_bytes, 0, MAX_PAYLOAD_RAW_BYTES)
    # zstd never expands data by more than a small bound; a larger claim is a lie a client must not allocate for.
    if type(size) is not int or not 0 <= size <= raw_bytes + raw_bytes // 128 + 1024:
        _bad_int(source, path, "bytes", size, 0, raw_bytes + raw_bytes // 128 + 1024)
    if type(gpu_bytes) is not int or not 0 <= gpu_bytes <= MAX_PAYLOAD_RAW_BYTES:
        _bad_int(source, path, "gpu_bytes", gpu_bytes, 0, MAX_PAYLOAD_RAW_BYTES)
    if type(items) is not list or len(items) > MAX_SECTIONS:
        _list(v, "sections", source, path, MAX_SECTIONS)
    expected = dict(expect)
    sections = []
    gpu = 0
    for i, s in enumerate(items):
        sec, decoded = _section(s, i, expected, expect, raw_bytes, chunks, strict, source, path)
        sections.append(sec)
        gpu += decoded
    if expected and any(not w.get("optional") for w in expected.values()):
        # a palette section where the scene's palettes hold may be left out (format.md 4.3.2, 1.7)
        expected = [n for n, w in expected.items() if not w.get("optional")]
        _fail(source, path, "sections", f"missing section{'s' if len(expected) > 1 else ''} "
              f"{', '.join(map(repr, expected))}")
    ordered = sorted(sections, key=_offset)
    for a, b in zip(ordered, ordered[1:], strict=False):
        if a.offset + a.size > b.offset:
            _fail(source, path, "sections", f"sections {a.name!r} and {b.name!r} overlap")
    end = ordered[-1].offset + ordered[-1].size if ordered else 0
    if raw_bytes != end:
        _fail(source, path, "raw_bytes", f"{raw_bytes}, but the sections end at byte {end}")
    if derived_gpu:
        gpu_bytes = gpu
    if gpu_bytes != gpu:
        _fail(source, path, "gpu_bytes", f"{gpu_bytes}, but the sections decode to {gpu} bytes")
    return PayloadEntry(file, sha, size, raw_bytes, gpu_bytes, tuple(sections))


def expected_sections(group: str, codebook: bool, formats: dict[str, str], chunks: int,
                      codebook_format: str | None = None,
                      scene_palettes: tuple[str, ...] = ()) -> list[tuple[str, dict]]:
    """The sections a payload group must hold: [(name, properties)] (format.md 4.4, 4.7, 5); a section a payload
    may leave out has `optional` (the palette section of a plane whose palettes the manifest holds: 4.3.2).

    `group` is a tile group (`codebook`: the scene has an SH codebook), or `cb:sh<b>` for a codebook band."""
    return _expected_sections(group, codebook, tuple(sorted(formats.items())), chunks, codebook_format,
                              tuple(sorted(scene_palettes)))


@functools.lru_cache(maxsize=1024)  # the same few groups and chunk counts for every tile of a scene
def _expected_sections(group: str, codebook: bool, format_items: tuple, chunks: int,
                       codebook_format: str | None, scene_palettes: tuple[str, ...] = ()) -> list[tuple[str, dict]]:
    formats = dict(format_items)
    specs = (band_plane(int(group[5:])),) if group.startswith("cb:") else group_planes(group, codebook)
    out = []
    for spec in specs:
        if spec.name == "sh_index":
            fmt = SH_INDEX_FORMAT
        elif group.startswith("cb:"):
            fmt = codebook_format
        else:
            fmt = formats[spec.attribute]
        out.append((spec.name, {"kind": "texels", "format": fmt, "layers": spec.layers}))
        if fmt in PALETTE_FORMATS:  # format.md 4.3.2: the palettes stand where the ranges would
            want = {"kind": "range", "dtype": "f32", "shape": list(palette_shape(spec))}
            if spec.name in scene_palettes:  # 1.7: the scene's palettes stand for a section left out
                want["optional"] = True
            out.append((spec.palette_name, want))
        elif spec.range_dtype:
            out.append((spec.range_name, {"kind": "range", "dtype": RANGE_DTYPE_NAMES[spec.range_dtype],
                                          "shape": [chunks, 2, spec.layers, spec.components]}))
    return out


# --------------------------------------------------------------------------------------------------------------
# Tiles


class _Scene:
    """What every tile of one manifest is checked against."""

    __slots__ = ("source", "strict", "formats", "format_items", "codebook", "group_names", "lazy", "expect",
                 "tile_optional", "scene_palettes", "short_digests", "relative_boxes")

    def __init__(self, source: str, strict: bool, formats: dict[str, str], sh_degree: int, codebook: bool,
                 lazy: bool, version: tuple[int, int] = FORMAT_VERSION, scene_palettes: tuple[str, ...] = ()):
        self.source, self.strict, self.formats, self.codebook, self.lazy = source, strict, formats, codebook, lazy
        self.scene_palettes = tuple(sorted(scene_palettes))
        self.tile_optional = ("page",) if version >= VERSION_1_5 else ()
        self.short_digests = short_digests(version)  # a compact table's digests: 16 bytes from 1.15 (format.md 6.2)
        self.relative_boxes = relative_boxes(version)  # its boxes relative to the parent's from 1.16 (format.md 6.2)
        self.group_names = tuple(groups_for_degree(sh_degree, codebook))
        self.format_items = tuple(sorted(formats.items()))
        self.expect: dict[tuple[str, int], list] = {}  # (group, chunks) -> expected_sections: a few per scene


def _tile_group(scene: _Scene, raw_groups: dict, chunks: int, texture: tuple[int, int], path: str,
               name: str) -> PayloadEntry:
    """One tile group's payload entry, its texels the tile's texture size (an eager parse and LazyPayloads both
    check an entry with this function)."""
    expect = scene.expect.get((name, chunks))
    if expect is None:
        expect = scene.expect[name, chunks] = _expected_sections(name, scene.codebook, scene.format_items, chunks,
                                                                 None, scene.scene_palettes)
    entry = _payload(raw_groups[name], expect, chunks, scene.strict, scene.source, f"{path}.{name}")
    for sec in entry.sections:
        if sec.kind == "texels" and (sec.width, sec.height) != texture:
            _fail(scene.source, path, f"{name}.sections", f"{sec.name} is {sec.width}x{sec.height}, the tile's "
                  f"texture {texture[0]}x{texture[1]}")
    return entry


def _lazy_group(scene: _Scene, chunks: int, texture: tuple[int, int], path: str, raw_groups: dict,
                name: str) -> PayloadEntry:
    """_tile_group, as LazyPayloads calls it (with the tile's groups unpacked again)."""
    return _tile_group(scene, raw_groups, chunks, texture, path, name)


def _tile(v, i: int, scene: _Scene, group_names: tuple[str, ...]) -> TileEntry:
    source, strict = scene.source, scene.strict
    path = f"tiles[{i}]"
    t = _keys(v, _TILE_KEYS, source, path, strict, scene.tile_optional)
    tid, n, chunks, level = t["id"], t["splats"], t["chunks"], t["level"]
    if type(tid) is not int or not 0 <= tid <= 2**31 - 1:
        _bad_int(source, path, "id", tid, 0, 2**31 - 1)
    if type(n) is not int or not 1 <= n <= 1 << 31:
        _bad_int(source, path, "splats", n, 1, 1 << 31)
    if type(chunks) is not int or not 1 <= chunks <= 1 << 24:
        _bad_int(source, path, "chunks", chunks, 1, 1 << 24)
    if chunks != chunks_for(n):
        _fail(source, path, "chunks", f"{chunks}, but {n} splats make {chunks_for(n)} chunks")
    texture = _ints(t, "texture", source, path, 2, BLOCK, 1 << 16)
    if texture[0] % BLOCK or texture[1] % BLOCK or (texture[0] // BLOCK) * (texture[1] // BLOCK) < chunks:
        _fail(source, path, "texture", f"{texture[0]}x{texture[1]} cannot hold {chunks} chunks")
    sphere = _keys(t["sphere"], ("center", "radius"), source, f"{path}.sphere", strict)
    center = _vec(sphere, "center", source, f"{path}.sphere")
    radius = _float(sphere, "radius", source, f"{path}.sphere", 0.0)
    gpath = f"{path}.groups"
    raw_groups = t["groups"]
    if type(raw_groups) is not dict:
        raise FormatError(source, gpath, f"expected a map, got {type(raw_groups).__name__}")
    names = _key_set(group_names)
    if scene.lazy and (raw_groups.keys() == names or not strict and raw_groups.keys() >= names):
        groups = LazyPayloads(raw_groups, group_names, functools.partial(_lazy_group, scene, chunks, texture, gpath))
    else:  # in order, so that a missing group is named where its turn comes (as a scene of another degree has it)
        groups = {}
        for name in group_names:
            if name not in raw_groups:
                _fail(source, gpath, name, "missing")
            groups[name] = _tile_group(scene, raw_groups, chunks, texture, gpath, name)
        _keys(raw_groups, group_names, source, gpath, strict)
    if type(level) is not int or not 0 <= level <= 64:
        _bad_int(source, path, "level", level, 0, 64)
    page = _page_ref(t["page"], source, f"{path}.page", strict) if scene.tile_optional and "page" in t else None
    return TileEntry(tid, level, _ints(t, "children", source, path, None, 0, 2**31 - 1),
                     n, chunks, texture, _box(t, "box", source, path, strict), center, radius,
                     _float(t, "geometric_error", source, path, 0.0), groups, page)


def _page_ref(v, source: str, path: str, strict: bool) -> PageRef:
    """A tile's `page` (format.md 6.1): named like a payload, by its SHA-256."""
    p = _keys(v, ("file", "sha256", "bytes"), source, path, strict)
    sha = _str(p, "sha256", source, path)
    if not SHA256_HEX_RE.match(sha):
        _fail(source, path, "sha256", f"expected 64 lowercase hex digits, got {sha!r}")
    if p["file"] != payload_name(sha):
        _fail(source, path, "file", f"expected {payload_name(sha)!r} (the page's own sha256), got {p['file']!r}")
    return PageRef(p["file"], sha, _int(p, "bytes", source, path, 1, MAX_PAGE_BYTES))


def _paged(d: dict, source: str, strict: bool) -> PagedInfo:
    g = _keys(d["paged"], ("tiles", "levels", "page_levels", "pages", "page_bytes"), source, "paged", strict)
    return PagedInfo(_int(g, "tiles", source, "paged", 1, MAX_TILES), _int(g, "levels", source, "paged", 1, 65),
                     _int(g, "page_levels", source, "paged", 1, 64), _int(g, "pages", source, "paged", 1, MAX_TILES),
                     _int(g, "page_bytes", source, "paged", 1))


def _tiles(items: list, scene: _Scene) -> list[TileEntry]:
    group_names = scene.group_names
    tiles = []
    ids: set[int] = set()
    for i, item in enumerate(items):
        tile = _tile(item, i, scene, group_names)
        if tile.id in ids:
            _fail(scene.source, f"tiles[{i}]", "id", f"tile id {tile.id} appears twice")
        ids.add(tile.id)
        tiles.append(tile)
    return tiles


def _table_fail(source: str, column: str, row: int, problem: str) -> NoReturn:
    raise FormatError(source, f"{TABLE_KEY}.{column}[{row}]", problem)


def _first(mask: np.ndarray) -> int | None:
    """The first row where `mask` holds (any axis beyond the first folded), or None."""
    if mask.ndim > 1:
        mask = mask.reshape(len(mask), -1).any(axis=1)
    return int(np.argmax(mask)) if mask.any() else None


def _table_tile_checks(c, source: str) -> np.ndarray:
    """format.md 6, Validation, per tile, over the columns (a message naming the first row at fault); the chunks."""
    for column, bad, problem in (
            ("id", c.id > 2**31 - 1, "expected an integer 0..2147483647"),
            ("level", c.level > 64, "expected an integer 0..64"),
            ("splats", (c.splats < 1) | (c.splats > 1 << 31), f"expected an integer 1..{1 << 31}")):
        i = _first(bad)
        if i is not None:
            _table_fail(source, column, i, f"{problem}, got {int(getattr(c, column)[i])}")
    ids = c.id.astype(np.int64)
    order = np.argsort(ids, kind="stable")
    dup = np.flatnonzero(ids[order][1:] == ids[order][:-1])
    if len(dup):
        i = int(order[dup[0] + 1])
        _table_fail(source, "id", i, f"tile id {ids[i]} appears twice")
    chunks = np.maximum(1, (c.splats.astype(np.int64) + CHUNK_SIZE - 1) // CHUNK_SIZE)
    blocks = c.texture.astype(np.int64)
    i = _first((blocks == 0).any(axis=1) | (blocks[:, 0] * blocks[:, 1] < chunks))
    if i is not None:
        _table_fail(source, "texture", i, f"{blocks[i, 0]}x{blocks[i, 1]} blocks of {BLOCK}x{BLOCK} texels cannot "
                    f"hold {chunks[i]} chunks")
    i = _first(blocks[:, 0] * blocks[:, 1] > 2 * chunks + MAX_WASTED_BLOCKS)
    if i is not None:
        _table_fail(source, "texture", i, f"{blocks[i, 0] * blocks[i, 1]} blocks for {chunks[i]} chunks (at most "
                    f"{max_blocks(int(chunks[i]))}: format.md 4.1)")
    for column in ("box", "sphere", "geometric_error"):
        i = _first(~np.isfinite(getattr(c, column)))
        if i is not None:
            _table_fail(source, column, i, f"expected finite numbers, got {getattr(c, column)[i].tolist()}")
    i = _first(c.box[:, :3] > c.box[:, 3:])
    if i is not None:
        _table_fail(source, "box", i, f"min {tuple(c.box[i, :3])} exceeds max {tuple(c.box[i, 3:])}")
    for column, values in (("sphere", c.sphere[:, 3]), ("geometric_error", c.geometric_error)):
        i = _first(values < 0)
        if i is not None:
            _table_fail(source, column, i, f"expected a radius or error >= 0, got {float(values[i])}")
    return chunks


def n_payloads(c) -> int:
    """A tile table's payloads: its tiles x groups."""
    return c.count * len(c.groups)


def _table_payload_map(c, p: int, raw_bytes: int, first: int, scene: _Scene, chunks: int,
                       texture: tuple[int, int]) -> tuple[dict, list]:
    """Payload p of a tile table as the payload map of format.md 5 (each section's fixed fields as its plane must
    have them, offsets derived), to be checked by _payload: one function names a damaged entry in both forms."""
    g = len(c.groups)
    name = c.groups[p % g]
    expect = _expected_sections(name, scene.codebook, scene.format_items, chunks, None, scene.scene_palettes)
    want = dict(expect)
    sha = bytes(c.sha256.reshape(n_payloads(c), -1)[p]).hex()
    layout = c.layouts[int(c.layout.reshape(-1)[p])]
    sizes = [int(size) for size in c.sizes[first:first + len(layout)]]
    sections = []
    for (sname, filt), size, offset in zip(layout, sizes, canonical_offsets(sizes)[0], strict=True):
        s = {"name": sname, "offset": offset, "size": size, "filter": filt}
        w = want.get(sname)
        if w is None:
            s["kind"] = "texels"
        elif w["kind"] == "texels":
            s.update(kind="texels", format=w["format"], width=texture[0], height=texture[1], layers=w["layers"])
        else:
            s.update(kind="range", dtype=w["dtype"], shape=list(w["shape"]))
        sections.append(s)
    return {"sha256": sha, "file": payload_name(sha), "raw_bytes": raw_bytes, "bytes": int(c.bytes.reshape(-1)[p]),
            "gpu_bytes": 0, "sections": sections}, expect


# A payload kind of a tile table (the scene's formats, group, layout, chunks, texture) once checked whole: its
# sections at offset 0 and size 0, each section's smallest and largest size, its GPU bytes. Kept across parses (a
# streaming client parses hundreds of pages of one scene, whose tiles repeat a few kinds), bounded.
_KINDS: dict[tuple, tuple[tuple[Section, ...], np.ndarray, np.ndarray, int]] = {}
_MAX_KINDS = 4096


def _kind(entry: PayloadEntry) -> tuple[tuple[Section, ...], np.ndarray, np.ndarray, int]:
    """A checked entry as its kind's template, size bounds and GPU bytes."""
    lo, hi, template = [], [], []
    for s in entry.sections:
        if s.kind == "texels":
            a, b, _, _ = _stored_size_rule(s.format, s.width, s.height, s.layers, s.filter)
        else:
            a = b = s.size
        lo.append(a)
        hi.append(b)
        sec = _new(Section)
        sec.__dict__.update(s.__dict__)
        sec.__dict__.update(offset=0, size=0)
        template.append(sec)
    return tuple(template), np.array(lo, np.int64), np.array(hi, np.int64), entry.gpu_bytes


def _tiles_key(d: dict, version: tuple[int, int]) -> str:
    """The key a manifest's or page's tiles are under: `tile_table_zstd` (1.12), `tile_table` (1.8) or `tiles`."""
    if version >= VERSION_1_12 and TABLE_ZSTD_KEY in d:
        return TABLE_ZSTD_KEY
    return TABLE_KEY if version >= VERSION_1_8 and TABLE_KEY in d else "tiles"


def _any_tiles(d: dict, key: str, scene: _Scene) -> list[TileEntry]:
    """The tiles under `key` (_tiles_key), checked."""
    if key == "tiles":
        return _tiles(_list(d, "tiles", scene.source, "", MAX_TILES), scene)
    return _table_tiles(d[key], scene, compact=key == TABLE_ZSTD_KEY)


def _table_tiles(v, scene: _Scene, compact: bool = False) -> list[TileEntry]:
    """A tile table (format.md 6.2, version 1.8) into its tiles, every field checked over the columns; a payload
    entry at fault is named by the same line as a tile map's (`tile_table[3].groups.base.sections[2].size`).
    compact: `v` is a 1.12 `tile_table_zstd` bin (inflated here; its columns named as a tile table's)."""
    source, strict = scene.source, scene.strict
    if compact:
        v = unpack_compact_table(v, source)
    short = compact and scene.short_digests  # 1.15's digests are the compact table's (format.md 6.2)
    c = read_columns(v, source, strict, MAX_TILES, bool(scene.tile_optional), scene.group_names, compact, short,
                     compact and scene.relative_boxes)
    n, g = c.count, len(c.groups)
    chunks = _table_tile_checks(c, source)
    texture = c.texture.astype(np.int64) * BLOCK
    # Sections: each payload's run of `sizes`, offsets at the next multiple of 16 (format.md 6.2).
    layout = c.layout.reshape(-1).astype(np.int64)
    per_layout = np.array([len(lay) for lay in c.layouts], np.int64)
    counts = per_layout[layout]
    first = np.zeros(n * g, np.int64)
    np.cumsum(counts[:-1], out=first[1:])
    sizes = c.sizes.astype(np.int64)
    aligned = np.concatenate([[0], np.cumsum((sizes + (ALIGN - 1)) // ALIGN * ALIGN)])
    payload_of = np.repeat(np.arange(n * g), counts)
    offsets = aligned[:-1] - aligned[first[payload_of]]
    last = first + counts - 1
    raw_bytes = np.where(counts > 0, offsets[np.maximum(last, 0)] + sizes[np.maximum(last, 0)] if len(sizes)
                         else 0, 0)
    nbytes = c.bytes.reshape(-1).astype(np.int64)
    tile_of = np.arange(n * g) // g

    def check(p: int) -> PayloadEntry:
        i = int(tile_of[p])
        tex = (int(texture[i, 0]), int(texture[i, 1]))
        d, expect = _table_payload_map(c, p, int(raw_bytes[p]), int(first[p]), scene, int(chunks[i]), tex)
        return _payload(d, expect, int(chunks[i]), strict, source, f"{TABLE_KEY}[{i}].groups.{c.groups[p % g]}",
                        derived_gpu=True, short=short)

    bad = _first((raw_bytes > MAX_PAYLOAD_RAW_BYTES) | (nbytes > raw_bytes + raw_bytes // 128 + 1024))
    if bad is not None:
        check(bad)
    # Per kind of payload (group, layout, chunks, texture): one entry checked whole, the others' sizes against it.
    kinds = np.stack([np.arange(n * g) % g, layout, chunks[tile_of], texture[tile_of, 0], texture[tile_of, 1]], 1)
    _, rep, kind = np.unique(kinds, axis=0, return_index=True, return_inverse=True)
    kind = kind.reshape(-1)
    templates, gpu_of_kind = [], np.zeros(len(rep), np.int64)
    scene_key = (scene.format_items, scene.codebook, scene.scene_palettes, strict)
    for k, (p, row) in enumerate(zip(rep.tolist(), kinds[rep].tolist(), strict=True)):
        key = (scene_key, c.groups[row[0]], tuple(map(tuple, c.layouts[row[1]])), *row[2:])
        known = _KINDS.get(key)
        if known is None:
            known = _kind(check(p))
            if len(_KINDS) >= _MAX_KINDS:
                _KINDS.clear()
            _KINDS[key] = known
        template, lo, hi, gpu = known
        members = np.flatnonzero(kind == k)
        got = sizes[first[members][:, None] + np.arange(len(template))]
        i = _first((got < lo) | (got > hi))
        if i is not None:
            check(int(members[i]))
        templates.append(template)
        gpu_of_kind[k] = gpu
    table = Table(c.groups, c.sha256.reshape(n_payloads(c), -1), nbytes, raw_bytes, gpu_of_kind[kind], sizes,
                  offsets, first, templates, kind)
    pages = {}
    if c.page_tile is not None:
        for row, sha, size in zip(c.page_tile.tolist(), c.page_sha256, c.page_bytes.tolist(), strict=True):
            h = bytes(sha).hex()
            if not 1 <= size <= MAX_PAGE_BYTES:
                _table_fail(source, "page.bytes", row, f"expected an integer 1..{MAX_PAGE_BYTES}, got {size}")
            pages[row] = PageRef(payload_name(h), h, size)
    ends = np.cumsum(c.children.astype(np.int64)).tolist()
    child_ids = c.child_ids.tolist()
    ids, levels, splats = c.id.tolist(), c.level.tolist(), c.splats.tolist()
    tex, box, sphere, gerr, chunk_l = texture.tolist(), c.box.tolist(), c.sphere.tolist(), \
        c.geometric_error.tolist(), chunks.tolist()
    tiles = []
    start = 0
    for i in range(n):
        b, s = box[i], sphere[i]
        bx = _new(Box)
        bx.__dict__.update(min=(b[0], b[1], b[2]), max=(b[3], b[4], b[5]))
        tile = _new(TileEntry)
        tile.__dict__.update(id=ids[i], level=levels[i], children=tuple(child_ids[start:ends[i]]), splats=splats[i],
                             chunks=chunk_l[i], texture=(tex[i][0], tex[i][1]), box=bx,
                             sphere_center=(s[0], s[1], s[2]), sphere_radius=s[3], geometric_error=gerr[i],
                             groups=TablePayloads(table, i), page=pages.get(i))
        start = ends[i]
        tiles.append(tile)
    return tiles


def _check_tree(source: str, tiles: list[TileEntry], root: int, page_levels: int = 0) -> None:
    """One root at level 0; every other tile is the child of exactly one tile, one level below it. page_levels k > 0
    (a paged root manifest, format.md 6.1): tiles at levels below k, and the children of a tile with `page` are in
    that page instead."""
    by_id = {t.id: t for t in tiles}
    if root not in by_id:
        raise FormatError(source, "root", f"no tile with id {root}")
    parent: dict[int, int] = {}
    for i, t in enumerate(tiles):
        if page_levels:
            _check_page_rule(source, f"tiles[{i}]", t, page_levels)
            if t.page is not None:
                continue
        for c in t.children:
            if c not in by_id:
                raise FormatError(source, f"tiles[{i}].children", f"no tile with id {c}")
            if c in parent or c == root:
                raise FormatError(source, f"tiles[{i}].children", f"tile {c} has more than one parent")
            parent[c] = t.id
            if by_id[c].level != t.level + 1:
                raise FormatError(source, f"tiles[{i}].children", f"tile {c} is at level {by_id[c].level}, "
                                  f"expected {t.level + 1} (one below its parent)")
    if by_id[root].level != 0:
        raise FormatError(source, "root", f"the root tile is at level {by_id[root].level}, expected 0")
    orphans = [t.id for t in tiles if t.id != root and t.id not in parent]
    if orphans:
        raise FormatError(source, "tiles", f"tiles {orphans[:8]} are not reachable from the root {root}")


def _check_page_rule(source: str, path: str, t: TileEntry, page_levels: int) -> None:
    """format.md 6.1: a tile has `page` exactly when it has children and is at a file's deepest level."""
    deepest = (t.level + 1) % page_levels == 0
    if t.page is None and deepest and t.children:
        _fail(source, path, "page", f"missing (a tile at level {t.level} with children names the page holding them, "
              f"{page_levels} levels to a page)")
    if t.page is not None and not (deepest and t.children):
        _fail(source, path, "page", f"a tile at level {t.level} with {len(t.children)} children has no page "
              f"({page_levels} levels to a page)")


# --------------------------------------------------------------------------------------------------------------
# The manifest


def _check_format_and_version(d, source: str) -> tuple[int, int]:
    if not isinstance(d, dict) or d.get("format") != FORMAT_NAME:
        raise FormatError(source, "format", f"expected {FORMAT_NAME!r}; this is not a splatstream manifest")
    version = d.get("version")
    if not (isinstance(version, (list, tuple)) and len(version) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in version)):
        raise FormatError(source, "version", f"expected [major, minor], got {version!r}")
    if version[0] != FORMAT_VERSION[0]:
        raise FormatError(source, "version", f"format version {version[0]}.{version[1]} is not supported by this "
                          f"reader (it reads major version {FORMAT_VERSION[0]}); upgrade splatstream")
    return version[0], version[1]


def _newer_than(version: tuple[int, int], what: str, since: tuple[int, int]) -> str:
    return f"{what} is a version {since[0]}.{since[1]} {'chunk order' if since == VERSION_1_4 else 'texel format'}; " \
        f"the manifest is version {version[0]}.{version[1]}"


def _formats(d: dict, version: tuple[int, int], source: str, strict: bool) -> dict[str, str]:
    fm = _keys(d["formats"], ATTRIBUTES, source, "formats", strict)
    formats = {a: _str(fm, a, source, "formats", VALUE_FORMATS) for a in ATTRIBUTES}
    for a, f in formats.items():
        if f in FORMATS_1_3 and version < VERSION_1_3:
            _fail(source, "formats", a, _newer_than(version, f, VERSION_1_3))
        if f in FORMATS_1_6 and version < VERSION_1_6:
            _fail(source, "formats", a, _newer_than(version, f, VERSION_1_6))
        if f in FORMATS_1_13 and version < VERSION_1_13:
            _fail(source, "formats", a, _newer_than(version, f, VERSION_1_13))
        if f in FORMATS_1_14 and version < VERSION_1_14:
            _fail(source, "formats", a, _newer_than(version, f, VERSION_1_14))
        if f in ROTATION_ONLY_FORMATS and a != "rotation":
            _fail(source, "formats", a, f"{f} holds rotations in the cube gauge (format.md 4.5) only")
        if f in PALETTE_FORMATS and a not in PALETTE_ATTRIBUTES:
            _fail(source, "formats", a, f"{f} holds palette indices of {' or '.join(PALETTE_ATTRIBUTES)} only")
    if FORMATS[formats["color"]].components < 4:
        _fail(source, "formats", "color", f"{formats['color']} has 3 components; color needs 4")
    return formats


def _codebook(d: dict, version: tuple[int, int], formats: dict[str, str], sh_degree: int, source: str,
              strict: bool) -> SHCodebookEntry | None:
    if d.get("sh_codebook") is None:
        return None
    c = _keys(d["sh_codebook"], ("entries", "format", "index_format", "groups"), source, "sh_codebook", strict)
    entries = _int(c, "entries", source, "sh_codebook", 1, 65536)
    cb_format = _str(c, "format", source, "sh_codebook",
                     tuple(f for f in VALUE_FORMATS if f not in PALETTE_FORMATS + ROTATION_ONLY_FORMATS))
    if cb_format in FORMATS_1_3 and version < VERSION_1_3:
        _fail(source, "sh_codebook", "format", _newer_than(version, cb_format, VERSION_1_3))
    index_format = _str(c, "index_format", source, "sh_codebook", (SH_INDEX_FORMAT,))
    bands = tuple(f"sh{b}" for b in range(1, sh_degree + 1))
    g = _keys(c["groups"], bands, source, "sh_codebook.groups", strict)
    chunks = chunks_for(entries)
    groups = {b: _payload(g[b], expected_sections(f"cb:{b}", True, formats, chunks, cb_format), chunks, strict,
                          source, f"sh_codebook.groups.{b}") for b in bands}
    return SHCodebookEntry(entries, cb_format, index_format, groups)


def _palettes(d: dict, formats: dict[str, str], source: str) -> dict[str, bytes]:
    """The scene palettes (format.md 4.3.2, 1.7): per pal8x4 plane a bin of P x 256 little-endian f32, every entry
    finite and inside the plane's value domain (4.8), so any index decodes to a value a scene may hold."""
    p = d["palettes"]
    if type(p) is not dict or not p:
        raise FormatError(source, "palettes", f"expected a map of plane names to palettes, got {p!r:.60}")
    out = {}
    for name, raw in p.items():
        spec = next((s for s in group_planes("base", False) if s.name == name), None)
        if spec is None or formats.get(spec.attribute) not in PALETTE_FORMATS:
            _fail(source, "palettes", str(name), f"names no {'/'.join(PALETTE_FORMATS)} plane of this scene")
        need = 4 * int(np.prod(palette_shape(spec)))
        if type(raw) is not bytes or len(raw) != need:
            _fail(source, "palettes", name, f"expected a bin of {need} bytes ({palette_shape(spec)[0]} x 256 f32), "
                  f"got {type(raw).__name__} of {len(raw) if isinstance(raw, (bytes, str)) else '?'}")
        values = np.frombuffer(raw, "<f4")
        if not np.isfinite(values).all():
            _fail(source, "palettes", name, "non-finite palette values")
        lo, hi = (MIN_LOG_SCALE, MAX_LOG_SCALE) if name == "scale" else (-MAX_ABS_SH, MAX_ABS_SH)
        if float(values.min()) < lo or float(values.max()) > hi:
            _fail(source, "palettes", name, f"palette [{values.min():g}, {values.max():g}] leaves the {name} domain "
                  f"[{lo:g}, {hi:g}] (format.md 4.8)")
        out[name] = raw
    return out


def _camera(d: dict, source: str, strict: bool) -> CameraEntry:
    cam = _keys(d["camera"], ("eye", "target", "up", "fov_y"), source, "camera", strict)
    camera = CameraEntry(_vec(cam, "eye", source, "camera"), _vec(cam, "target", source, "camera"),
                         _vec(cam, "up", source, "camera"), _float(cam, "fov_y", source, "camera", 1e-3, 179.0))
    if camera.eye == camera.target:
        _fail(source, "camera", "eye", "the camera's eye and target coincide")
    if not any(camera.up):
        _fail(source, "camera", "up", "zero-length up vector")
    return camera


_LOD_KEYS = ("enabled", "max_leaf_splats", "reduction", "refine")
# Version 1.9: how the encoder built the tree (format.md 6, lod.md 6), each optional (absent: not recorded).
_LOD_BUILD_KEYS = ("merge", "viewing_scale_px")
# Version 1.10: the viewing scale per level (format.md 6), instead of viewing_scale_px.
_LOD_LEVELS_KEY = "viewing_scale_levels_px"


def _lod(d: dict, source: str, strict: bool, version: tuple[int, int]) -> LodInfo:
    build = _LOD_BUILD_KEYS if version >= VERSION_1_9 else ()
    if version >= VERSION_1_10:
        build = (*build, _LOD_LEVELS_KEY)
    if version >= VERSION_1_11:
        build = (*build, "refinement")
    lod = _keys(d["lod"], _LOD_KEYS, source, "lod", strict, build)
    info = LodInfo(_bool(lod, "enabled", source, "lod"), _int(lod, "max_leaf_splats", source, "lod", 1),
                   _float(lod, "reduction", source, "lod", 1.0), _str(lod, "refine", source, "lod", ("replace",)))
    if not build or not (lod.keys() & set(build)):
        return info
    refinement = None
    if "refinement" in build and "refinement" in lod:  # present means a map: a nil is damage, not "not refined"
        if not info.enabled:
            _fail(source, "lod", "refinement", "a refinement record in a scene without an LOD tree (lod.enabled is "
                  "false)")
        refinement = _lod_refinement(lod["refinement"], source, strict)
    merge = lod.get("merge")
    if merge is not None and (type(merge) is not str or not merge):
        # Informative and open: a later encoder may name a merge this reader does not know (format.md 6).
        _fail(source, "lod", "merge", f"expected a merge name (a non-empty string), got {merge!r}")
    scales = lod.get("viewing_scale_px")
    if scales is not None:
        if not (type(scales) in (list, tuple) and len(scales) == 2 and all(type(v) in _NUMBER and _isfinite(v)
                                                                           and v > 0 for v in scales)):
            _fail(source, "lod", "viewing_scale_px", f"expected 2 finite numbers > 0 (px on the first merged level, "
                  f"px above it), got {scales!r}")
        scales = (float(scales[0]), float(scales[1]))
    levels = lod.get(_LOD_LEVELS_KEY) if _LOD_LEVELS_KEY in build else None
    if levels is not None:
        if scales is not None:
            _fail(source, "lod", _LOD_LEVELS_KEY, "both viewing_scale_px and viewing_scale_levels_px (one record)")
        if not (type(levels) in (list, tuple) and len(levels) >= 2 and all(type(v) in _NUMBER and _isfinite(v)
                                                                            and v > 0 for v in levels)):
            _fail(source, "lod", _LOD_LEVELS_KEY, f"expected 2 or more finite numbers > 0 (px per level from the "
                  f"first merged one, the last on every level above), got {levels!r}")
        scales = tuple(float(v) for v in levels)
    if not info.enabled:
        named = [k for k in (*_LOD_BUILD_KEYS, _LOD_LEVELS_KEY) if lod.get(k) is not None]  # the key that is there
        _fail(source, "lod", named[0] if named else "viewing_scale_px",
              "a build record in a scene without an LOD tree (lod.enabled is false)")
    return LodInfo(info.enabled, info.max_leaf_splats, info.reduction, info.refine, merge, scales, refinement)


_REFINEMENT_KEYS = ("method", "variants", "size_px", "iterations", "cameras", "levels")
_REFINEMENT_CAMERA_KEYS = ("training", "training_seed", "validation", "validation_seed")


def _name(v, source: str, path: str, key: str) -> str:
    if type(v) is not str or not v:
        _fail(source, path, key, f"expected a non-empty string, got {v!r}")
    return v


def _lod_refinement(r, source: str, strict: bool) -> LodRefinement:
    """Version 1.11's `lod.refinement` (format.md 6; informative, but well formed where present)."""
    path = "lod.refinement"
    r = _keys(r, _REFINEMENT_KEYS, source, path, strict)
    method = _name(r["method"], source, path, "method")
    variants = r["variants"]
    if type(variants) is not dict or not all(
            type(k) is str and k and type(v) is list and v and all(type(f) is str and f for f in v)
            for k, v in variants.items()):
        _fail(source, path, "variants", f"expected a map of variant name to a list of field names, got {variants!r}")
    cams = _keys(r["cameras"], _REFINEMENT_CAMERA_KEYS, source, f"{path}.cameras", strict)
    levels = r["levels"]
    if type(levels) is not list:
        _fail(source, path, "levels", f"expected a list, got {type(levels).__name__}")
    out = []
    for i, lv in enumerate(levels):
        where = f"{path}.levels[{i}]"
        lv = _keys(lv, ("level", "kept", "validation_psnr"), source, where, strict)
        kept = _name(lv["kept"], source, where, "kept")
        if kept != "none" and kept not in variants:
            _fail(source, where, "kept", f"expected none or one of the variants ({', '.join(variants)}), got {kept!r}")
        psnr = lv["validation_psnr"]
        if type(psnr) is not dict or not all(type(k) is str and type(v) in _NUMBER and _isfinite(v)
                                             for k, v in psnr.items()):
            _fail(source, where, "validation_psnr", f"expected a map of candidate to a finite number, got {psnr!r}")
        out.append(LevelRefinement(_int(lv, "level", source, where), kept,
                                   tuple((k, float(v)) for k, v in psnr.items())))
    return LodRefinement(method, tuple((k, tuple(v)) for k, v in variants.items()),
                         _int(r, "size_px", source, path, 1), _int(r, "iterations", source, path),
                         _int(cams, "training", source, f"{path}.cameras", 1),
                         _int(cams, "training_seed", source, f"{path}.cameras"),
                         _int(cams, "validation", source, f"{path}.cameras", 1),
                         _int(cams, "validation_seed", source, f"{path}.cameras"), tuple(out))


def _check_refined_levels(r: LodRefinement, tiles: list[TileEntry], paged: PagedInfo | None, source: str) -> None:
    """Each `lod.refinement.levels[i].level` is a merged level of this tree (a depth above its deepest level: 0 to
    levels - 2, the levels counted by `paged.levels` in a paged root manifest, which holds only the top ones), in
    ascending order without repeats, as the encoder writes them (lod_refine.level_cuts)."""
    depth = paged.levels if paged is not None else 1 + max(t.level for t in tiles)
    previous = -1
    for i, lv in enumerate(r.levels):
        if not previous < lv.level <= depth - 2:
            _fail(source, f"lod.refinement.levels[{i}]", "level", f"expected a merged level of this {depth}-level "
                  f"tree, {previous + 1}..{depth - 2} (ascending, each once), got {lv.level}")
        previous = lv.level


def _attributes(d: dict, source: str, strict: bool) -> dict[str, AttributeSize]:
    am = _keys(d["attributes"], (), source, "attributes", strict, ATTRIBUTES)
    attributes = {}
    for a in [k for k in ATTRIBUTES if k in am]:
        path = f"attributes.{a}"
        s = _keys(am[a], ("format", "gpu_bytes", "disk_bytes"), source, path, strict)
        attributes[a] = AttributeSize(_str(s, "format", source, path, VALUE_FORMATS),
                                      _int(s, "gpu_bytes", source, path), _int(s, "disk_bytes", source, path))
    return attributes


def _check_splats(d: dict, tiles: list[TileEntry], splats: int, source: str) -> int:
    leaf_splats = _int(d, "leaf_splats", source, "", 1)
    leaf_sum = sum(t.splats for t in tiles if t.is_leaf)
    if leaf_splats != leaf_sum or splats != leaf_sum:
        _fail(source, "", "splats", f"splats {splats} and leaf_splats {leaf_splats} must both equal the leaf tiles' "
              f"{leaf_sum} splats")
    return leaf_splats


def _check_totals(manifest: Manifest, source: str) -> None:
    """Totals a reader can recompute must agree (a resealed but edited manifest, or a writer's bug)."""
    leaf_sizes = [entry_fields(t.groups, name, ("gpu_bytes", "bytes")) for t in manifest.leaves for name in t.groups]
    if manifest.sh_codebook is not None:
        leaf_sizes += [(p.gpu_bytes, p.bytes) for p in manifest.sh_codebook.groups.values()]
    gpu = sum(g for g, _ in leaf_sizes)
    disk = sum(b for _, b in leaf_sizes)
    if manifest.gpu_bytes != gpu or manifest.leaf_bytes_on_disk != disk:
        check_all_entries(manifest.leaves)  # a lazily checked entry at fault is named, not only the total
    if manifest.gpu_bytes != gpu:
        _fail(source, "", "gpu_bytes", f"{manifest.gpu_bytes}, but the leaf tiles' and codebook's sections hold "
              f"{gpu} bytes")
    if manifest.leaf_bytes_on_disk != disk:
        _fail(source, "", "leaf_bytes_on_disk", f"{manifest.leaf_bytes_on_disk}, but the leaf tiles' and codebook's "
              f"payloads are {disk} bytes")


def manifest_from_dict(d, source: str = MANIFEST_NAME, lazy_payloads: bool = False) -> Manifest:
    """Validate a manifest map (format.md 6) into a Manifest; FormatError names the first field that is wrong.
    (The checksum, a property of the file's bytes, is verified by parse_manifest.)

    lazy_payloads: each tile's payload entries are checked when first read (by the same function), not here."""
    version = _check_format_and_version(d, source)
    # Keys are added only in new minor versions: in a version this reader knows, an unknown key is damage.
    strict = version[1] <= FORMAT_VERSION[1]
    optional = ("sh_codebook", CHECKSUM_KEY) if version >= CHECKSUM_VERSION else ("sh_codebook",)
    if version >= VERSION_1_5:
        optional += ("paged",)
    if version >= VERSION_1_7:
        optional += ("palettes",)
    tiles_key = _tiles_key(d, version)
    _keys(d, {TABLE_ZSTD_KEY: _TOP_KEYS_COMPACT, TABLE_KEY: _TOP_KEYS_TABLE}.get(tiles_key, _TOP_KEYS), source, "",
          strict, optional)
    splats = _int(d, "splats", source, "", 1)
    sh_degree = _int(d, "sh_degree", source, "", 0, MAX_SH_DEGREE)
    formats = _formats(d, version, source, strict)
    chunk_size = _int(d, "chunk_size", source, "", CHUNK_SIZE, CHUNK_SIZE)
    chunk_order = _str(d, "chunk_order", source, "", CHUNK_ORDER_NAMES)
    if chunk_order in CHUNK_ORDERS_1_4 and version < VERSION_1_4:
        _fail(source, "", "chunk_order", _newer_than(version, chunk_order, VERSION_1_4))
    codebook = _codebook(d, version, formats, sh_degree, source, strict)
    palettes = _palettes(d, formats, source) if version >= VERSION_1_7 and "palettes" in d else None
    scene = _Scene(source, strict, formats, sh_degree, codebook is not None, lazy_payloads, version,
                   tuple(palettes or ()))
    tiles = _any_tiles(d, tiles_key, scene)
    if not tiles:
        _fail(source, "", "tiles", "no tiles: a scene has at least its root tile")
    root = _int(d, "root", source, "", 0, 2**31 - 1)
    paged = _paged(d, source, strict) if version >= VERSION_1_5 and "paged" in d else None
    _check_tree(source, tiles, root, paged.page_levels if paged else 0)
    if paged is None:
        leaf_splats = _check_splats(d, tiles, splats, source)
    else:  # the leaves are in the pages: checked when they are all read (paging.resolve_pages)
        leaf_splats = _int(d, "leaf_splats", source, "", 1)
        if any(t.level >= paged.page_levels for t in tiles):
            _fail(source, "", "tiles", f"a paged root manifest holds levels 0 to {paged.page_levels - 1} only")
    camera = _camera(d, source, strict)
    up = _vec(d, "up", source, "")
    if not any(up):
        _fail(source, "", "up", "zero-length up vector")
    manifest = Manifest(
        version=version, generator=_str(d, "generator", source, ""), name=_str(d, "name", source, ""),
        splats=splats, leaf_splats=leaf_splats, sh_degree=sh_degree, preset=_str(d, "preset", source, ""),
        formats=formats, chunk_size=chunk_size, chunk_order=chunk_order,
        bounds=_box(d, "bounds", source, "", strict), extent_bounds=_box(d, "extent_bounds", source, "", strict),
        up=up, camera=camera, sh_codebook=codebook, lod=_lod(d, source, strict, version), root=root, tiles=tuple(tiles),
        gpu_bytes=_int(d, "gpu_bytes", source, ""),
        gpu_bytes_per_splat=_float(d, "gpu_bytes_per_splat", source, "", 0.0),
        leaf_bytes_on_disk=_int(d, "leaf_bytes_on_disk", source, ""), attributes=_attributes(d, source, strict),
        encode_seconds=_float(d, "encode_seconds", source, "", 0.0), bytes_on_disk=_int(d, "bytes_on_disk", source, ""),
        paged=paged, palettes=palettes)
    if manifest.lod.refinement is not None:
        _check_refined_levels(manifest.lod.refinement, tiles, paged, source)
    if strict and paged is None:  # a newer minor version may add payloads these totals count; only its own keys
        _check_totals(manifest, source)
    return manifest


def check_whole_tree(manifest: Manifest, source: str, files_bytes: int) -> None:
    """The checks of a manifest over a paged scene's whole tree, once every page is read (format.md 6.1): one tree,
    the splat counts, the totals and `bytes_on_disk` (`files_bytes`: the root manifest's and the pages' bytes)."""
    _check_tree(source, list(manifest.tiles), manifest.root)
    _check_splats({"leaf_splats": manifest.leaf_splats}, list(manifest.tiles), manifest.splats, source)
    _check_totals(manifest, source)
    files = manifest.payload_bytes()
    if manifest.bytes_on_disk != files + files_bytes:
        check_all_entries(manifest.tiles)
        raise FormatError(source, "bytes_on_disk", f"{manifest.bytes_on_disk}, but the payload files, the manifest "
                          f"and its pages are {files + files_bytes} bytes")


def page_tiles(d, source: str, root: Manifest, parent: TileEntry, lazy_payloads: bool = False) -> list[TileEntry]:
    """A manifest page's map (format.md 6.1; its bytes already checked against `parent.page`) into its tiles:
    each checked like a manifest's, and together exactly `parent`'s descendants of the page's levels."""
    assert root.paged is not None and parent.page is not None
    if type(d) is not dict or d.get("format") != PAGE_FORMAT:
        raise FormatError(source, "format", f"expected {PAGE_FORMAT!r}; this is not a splatstream manifest page")
    if d.get("version") != list(root.version):
        raise FormatError(source, "version", f"expected {list(root.version)} (the manifest's), got "
                          f"{d.get('version')!r}")
    strict = root.version[1] <= FORMAT_VERSION[1]
    tiles_key = _tiles_key(d, root.version)
    _keys(d, ("format", "version", "parent", tiles_key), source, "", strict)
    if _int(d, "parent", source, "", 0, 2**31 - 1) != parent.id:
        _fail(source, "", "parent", f"expected {parent.id} (the tile naming this page), got {d['parent']}")
    scene = _Scene(source, strict, root.formats, root.sh_degree, root.sh_codebook is not None, lazy_payloads,
                   root.version, tuple(root.palettes or ()))
    tiles = _any_tiles(d, tiles_key, scene)
    k = root.paged.page_levels
    by_id = {t.id: t for t in tiles}
    position = {t.id: i for i, t in enumerate(tiles)}
    reached, todo = 0, [parent]
    while todo:
        t = todo.pop()
        if t is not parent:
            if not parent.level < t.level <= parent.level + k:
                _fail(source, "", "tiles", f"tile {t.id} is at level {t.level}, outside the page's levels "
                      f"{parent.level + 1}..{parent.level + k}")
            _check_page_rule(source, f"tiles[{position[t.id]}]", t, k)
            reached += 1
            if t.page is not None:
                continue
        for c in t.children:
            child = by_id.get(c)
            if child is None:
                _fail(source, "", "tiles", f"tile {c}, a child of tile {t.id}, is not in the page")
            if child.level != t.level + 1:
                _fail(source, "", "tiles", f"tile {c} is at level {child.level}, expected {t.level + 1} "
                      "(one below its parent)")
            todo.append(child)
    if reached != len(tiles):
        _fail(source, "", "tiles", f"{len(tiles) - reached} tiles are not descendants of tile {parent.id}")
    return tiles


def check_all_entries(tiles) -> None:
    """Read every payload entry of these tiles: a lazily checked one that is wrong raises its own FormatError."""
    for t in tiles:
        for name in t.groups:
            t.groups[name]


def parse_manifest(raw: bytes, source: str = MANIFEST_NAME, lazy_payloads: bool = False) -> Manifest:
    """Parse and validate manifest file bytes; from version 1.2 on the checksum is verified first.

    lazy_payloads (the streaming client): each tile's payload entries are checked when first read (a FormatError
    naming the field then), not here; everything else, totals included, is checked now. They are most of the parse
    of a large scene's manifest (thousands of entries, tens of thousands of sections), which a client waits for
    before its first frame and then reads a few at a time."""
    with _collector_paused():
        # A function of its own, so that the unpacked map is freed before the collector runs again (the eager
        # parse keeps nothing of it: the collector's first pass would walk its hundreds of thousands of objects).
        return _parse(raw, source, lazy_payloads)


def _parse(raw: bytes, source: str, lazy_payloads: bool) -> Manifest:
    d = unpack_manifest(raw, source)
    version = _check_format_and_version(d, source)
    if version >= CHECKSUM_VERSION:
        verify_checksum(raw, d, source)
    manifest = manifest_from_dict(d, source, lazy_payloads)
    if CHECKSUM_VERSION <= version <= FORMAT_VERSION and manifest.paged is None:
        files = manifest.payload_bytes()
        if manifest.bytes_on_disk != files + len(raw):
            check_all_entries(manifest.tiles)
            raise FormatError(source, "bytes_on_disk", f"{manifest.bytes_on_disk}, but the payload files and the "
                              f"manifest are {files + len(raw)} bytes")
    return manifest


@contextlib.contextmanager
def _collector_paused():
    """The garbage collector off while a manifest's tens of thousands of objects are made (they hold no cycles; its
    passes over them were a tenth of the parse), back as it was after."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()
