"""The scene manifest (format_spec/format.md 6), typed: parsed and validated once, then trusted.

`parse_manifest(bytes)` turns a msgpack manifest into a frozen `Manifest` (tiles as `TileEntry`, payloads as
`PayloadEntry` with their `Section`s) or raises FormatError naming the field (`tiles[3].groups.base.bytes`) and
what was expected. Everything a reader later relies on is checked here: types, ranges, the tile tree (one root,
every tile reachable once, levels), splat and chunk counts, texture sizes, and every payload's section table
against the planes its group must hold. `Manifest.to_dict()` gives back the spec's map (the encoder writes it).
"""
from __future__ import annotations

import contextlib
import functools
import gc
import hashlib
import math
import operator
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace

import msgpack
import numpy as np

from ..errors import FormatError
from .layout import ALIGN, BLOCK, CHUNK_SIZE
from .names import MANIFEST_NAME, SHA256_HEX_RE, payload_name
from .planes import (
    MAX_SH_DEGREE,
    RANGE_DTYPE_NAMES,
    SH_INDEX_FORMAT,
    band_of,
    band_plane,
    chunks_for,
    group_planes,
    groups_for_degree,
)
from .texformats import FORMATS, VALUE_FORMATS, blob_size
from .transport import FIELD_LAYOUTS, FIELDS1, content_bounds

FORMAT_NAME = "splatstream"
FORMAT_VERSION = (1, 4)  # (major, minor) this code reads; what it writes: writer_version
# Version 1.2 added two things (format.md, version history): the manifest's last key `checksum`, the SHA-256 of the
# file with that value's 64 bytes read as ASCII '0' (format.md 6, "Checksum"), so a flipped byte in the manifest is
# caught like one in a payload; and the `fields1` transport coding of texels sections (format.md 5.2).
CHECKSUM_VERSION = (1, 2)
# Version 1.3 added the texel formats norm16x4 and norm9x3 (format.md 4.2). Like the 1.1 codebook it is written only
# by scenes that use them, so every other scene stays 1.2 and readers of 1.2 keep reading it.
VERSION_1_3 = (1, 3)
FORMATS_1_3 = ("norm16x4", "norm9x3")
# Version 1.4 added the chunk order `input` (format.md 3): a one-tile scene whose splats keep the order of an input
# that was already cut into quantised chunks of 256 (compressed.ply), so its chunks, and their grids, are the input's.
VERSION_1_4 = (1, 4)
CHUNK_ORDERS_1_4 = ("input",)
CHECKSUM_KEY = "checksum"
CHECKSUM_PLACEHOLDER = b"0" * 64
MAX_MANIFEST_BYTES = 64 << 20
# A payload may not claim to decompress to more than this (guards readers against decompression bombs).
MAX_PAYLOAD_RAW_BYTES = 2 << 30
MAX_WASTED_BLOCKS = 128  # max_blocks: a row of the widest texture (2048 texels)
MAX_TILES = 1 << 20
CHUNK_ORDER_NAMES = ("morton", "luminance", "input")
FILTERS_DOC = "none, shuffleN or, for texels, fields1"

Vec3 = tuple[float, float, float]


# --------------------------------------------------------------------------------------------------------------
# Entries


@dataclass(frozen=True)
class Section:
    """One section of a decompressed payload (format.md 5): a plane's texels or its per-chunk ranges."""

    name: str
    kind: str  # "texels" or "range"
    offset: int
    size: int
    filter: str  # "none", "shuffleN" or (texels) "fields1"
    format: str = ""  # texels: texel format
    width: int = 0
    height: int = 0
    layers: int = 0
    dtype: str = ""  # range: "f32" or "f16"
    shape: tuple[int, ...] = ()

    @property
    def element(self) -> int:
        """Byte-shuffle element size of the filter (1: none)."""
        return filter_element(self.filter)

    @property
    def gpu_size(self) -> int:
        """Bytes the section decodes to: its texels (whatever the filter stores), or its ranges."""
        return _texels_size(self.format, self.width, self.height, self.layers) if self.kind == "texels" \
            else self.size

    def to_dict(self) -> dict:
        d = {"name": self.name, "offset": self.offset, "size": self.size, "filter": self.filter, "kind": self.kind}
        if self.kind == "texels":
            d.update(format=self.format, width=self.width, height=self.height, layers=self.layers)
        else:
            d.update(dtype=self.dtype, shape=list(self.shape))
        return d


@dataclass(frozen=True)
class PayloadEntry:
    """A payload file (a tile's group, or a band of the SH codebook): where it is and how to read it."""

    file: str
    sha256: str
    bytes: int
    raw_bytes: int
    gpu_bytes: int
    sections: tuple[Section, ...]

    def section(self, name: str) -> Section:
        for s in self.sections:
            if s.name == name:
                return s
        raise KeyError(name)

    def to_dict(self) -> dict:
        return {"file": self.file, "sha256": self.sha256, "bytes": self.bytes, "raw_bytes": self.raw_bytes,
                "gpu_bytes": self.gpu_bytes, "sections": [s.to_dict() for s in self.sections]}


@dataclass(frozen=True)
class Box:
    min: Vec3
    max: Vec3

    def to_dict(self) -> dict:
        return {"min": list(self.min), "max": list(self.max)}


@dataclass(frozen=True)
class TileEntry:
    """One tile of the LOD tree (format_spec/lod.md 1)."""

    id: int
    level: int
    children: tuple[int, ...]
    splats: int
    chunks: int
    texture: tuple[int, int]
    box: Box
    sphere_center: Vec3
    sphere_radius: float
    geometric_error: float
    groups: dict[str, PayloadEntry]  # read-only by convention (frozen dataclasses cannot freeze a dict)

    @property
    def is_leaf(self) -> bool:
        return not self.children

    def to_dict(self) -> dict:
        return {"id": self.id, "level": self.level, "children": list(self.children), "splats": self.splats,
                "chunks": self.chunks, "texture": list(self.texture), "box": self.box.to_dict(),
                "sphere": {"center": list(self.sphere_center), "radius": self.sphere_radius},
                "geometric_error": self.geometric_error,
                "groups": {name: p.to_dict() for name, p in self.groups.items()}}


@dataclass(frozen=True)
class SHCodebookEntry:
    """The scene-wide SH codebook (format.md 4.7)."""

    entries: int
    format: str
    index_format: str
    groups: dict[str, PayloadEntry]

    def to_dict(self) -> dict:
        return {"entries": self.entries, "format": self.format, "index_format": self.index_format,
                "groups": {name: p.to_dict() for name, p in self.groups.items()}}


@dataclass(frozen=True)
class CameraEntry:
    eye: Vec3
    target: Vec3
    up: Vec3
    fov_y: float

    def to_dict(self) -> dict:
        return {"eye": list(self.eye), "target": list(self.target), "up": list(self.up), "fov_y": self.fov_y}


@dataclass(frozen=True)
class LodInfo:
    enabled: bool
    max_leaf_splats: int
    reduction: float
    refine: str = "replace"

    def to_dict(self) -> dict:
        return {"enabled": self.enabled, "max_leaf_splats": self.max_leaf_splats, "reduction": self.reduction,
                "refine": self.refine}


@dataclass(frozen=True)
class AttributeSize:
    format: str
    gpu_bytes: int
    disk_bytes: int

    def to_dict(self) -> dict:
        return {"format": self.format, "gpu_bytes": self.gpu_bytes, "disk_bytes": self.disk_bytes}


@dataclass(frozen=True)
class TileArrays:
    """The tile tree as arrays (index = position in `Manifest.tiles`), for selection and culling over numpy."""

    ids: np.ndarray             # (T,) int64
    parent: np.ndarray          # (T,) int64 index of the parent, -1 for the root
    level: np.ndarray           # (T,) int64
    splats: np.ndarray          # (T,) int64
    box_min: np.ndarray         # (T, 3) float64
    box_max: np.ndarray         # (T, 3) float64
    sphere_center: np.ndarray   # (T, 3) float64
    sphere_radius: np.ndarray   # (T,) float64
    geometric_error: np.ndarray  # (T,) float64
    children: tuple[tuple[int, ...], ...]  # indices of each tile's children
    base_bytes: np.ndarray      # (T,) int64 bytes of the base payload
    band_bytes: np.ndarray      # (T, 3) int64 bytes of the tile's sh1..sh3 payloads (0: none)
    gpu_bytes: np.ndarray       # (T,) int64 GPU bytes of every group of the tile

    # Derived once, for the per-frame selection (client_gl/stream/selection.py): a frozen dataclass keeps a
    # cached_property in its __dict__.
    @functools.cached_property
    def box_corners(self) -> np.ndarray:
        """(T, 6) every box as [max, min]: the frustum test's positive vertex in one product."""
        return np.ascontiguousarray(np.concatenate([self.box_max, self.box_min], axis=1))

    @functools.cached_property
    def has_parent(self) -> np.ndarray:
        """(T,) bool: every tile but the root."""
        return self.parent >= 0

    @functools.cached_property
    def parent_of_child(self) -> np.ndarray:
        """The parent of every tile that has one (in tile order)."""
        return self.parent[self.has_parent]

    @functools.cached_property
    def has_children(self) -> np.ndarray:
        """(T,) bool."""
        return np.bincount(self.parent_of_child, minlength=len(self.parent)) > 0

    @functools.cached_property
    def splats_list(self) -> list[int]:
        return self.splats.tolist()

    @functools.cached_property
    def splats_f64(self) -> np.ndarray:
        return self.splats.astype(np.float64)


@dataclass(frozen=True)
class Manifest:
    version: tuple[int, int]
    generator: str
    name: str
    splats: int
    leaf_splats: int
    sh_degree: int
    preset: str
    formats: dict[str, str]
    chunk_size: int
    chunk_order: str
    bounds: Box
    extent_bounds: Box
    up: Vec3
    camera: CameraEntry
    sh_codebook: SHCodebookEntry | None
    lod: LodInfo
    root: int
    tiles: tuple[TileEntry, ...]
    gpu_bytes: int
    gpu_bytes_per_splat: float
    leaf_bytes_on_disk: int
    attributes: dict[str, AttributeSize]
    encode_seconds: float
    bytes_on_disk: int = 0
    format: str = field(default=FORMAT_NAME)

    # --- derived views (cached: a Manifest never changes) ------------------------------------------------------
    @functools.cached_property
    def tile_by_id(self) -> dict[int, TileEntry]:
        return {t.id: t for t in self.tiles}

    @functools.cached_property
    def index_of(self) -> dict[int, int]:
        """Tile id -> position in `tiles`."""
        return {t.id: i for i, t in enumerate(self.tiles)}

    @property
    def leaves(self) -> list[TileEntry]:
        return [t for t in self.tiles if t.is_leaf]

    @property
    def uses_codebook(self) -> bool:
        return self.sh_codebook is not None

    @property
    def levels(self) -> int:
        return 1 + max((t.level for t in self.tiles), default=0)

    def tile(self, tile_id: int) -> TileEntry:
        return self.tile_by_id[tile_id]

    def tile_groups(self) -> list[str]:
        return groups_for_degree(self.sh_degree, self.uses_codebook)

    def payloads(self) -> Iterator[tuple[TileEntry | None, str, PayloadEntry]]:
        """(tile, group name, payload) for every payload the manifest names (tile None: the SH codebook's)."""
        for tile in self.tiles:
            for name, p in tile.groups.items():
                yield tile, name, p
        if self.sh_codebook is not None:
            for name, p in self.sh_codebook.groups.items():
                yield None, name, p

    def payload_bytes(self) -> int:
        """Bytes of every distinct payload file (content-addressed: equal payloads are one file). Lazily checked
        entries are read as stored (they are checked when read for anything else)."""
        sizes = {}
        for t in self.tiles:
            for name in t.groups:
                file, size = _entry_fields(t.groups, name, ("file", "bytes"))
                sizes[file] = size
        if self.sh_codebook is not None:
            for p in self.sh_codebook.groups.values():
                sizes[p.file] = p.bytes
        return sum(sizes.values())

    @functools.cached_property
    def arrays(self) -> TileArrays:
        tiles = self.tiles
        n = len(tiles)
        idx = self.index_of
        parent = np.full(n, -1, np.int64)
        children = []
        for i, t in enumerate(tiles):
            kids = tuple(idx[c] for c in t.children)
            children.append(kids)
            for k in kids:
                parent[k] = i
        band_bytes = np.zeros((n, MAX_SH_DEGREE), np.int64)
        base_bytes = np.zeros(n, np.int64)
        gpu_bytes = np.zeros(n, np.int64)
        for i, t in enumerate(tiles):
            for name in t.groups:
                gpu, size = _entry_fields(t.groups, name, ("gpu_bytes", "bytes"))
                gpu_bytes[i] += gpu
                band = band_of(name)
                if band:
                    band_bytes[i, band - 1] = size
                else:
                    base_bytes[i] = size
        return TileArrays(
            ids=np.array([t.id for t in tiles], np.int64), parent=parent,
            level=np.array([t.level for t in tiles], np.int64),
            splats=np.array([t.splats for t in tiles], np.int64),
            box_min=np.array([t.box.min for t in tiles], np.float64).reshape(n, 3),
            box_max=np.array([t.box.max for t in tiles], np.float64).reshape(n, 3),
            sphere_center=np.array([t.sphere_center for t in tiles], np.float64).reshape(n, 3),
            sphere_radius=np.array([t.sphere_radius for t in tiles], np.float64),
            geometric_error=np.array([t.geometric_error for t in tiles], np.float64),
            children=tuple(children),
            base_bytes=base_bytes, band_bytes=band_bytes, gpu_bytes=gpu_bytes)

    def to_dict(self) -> dict:
        """The manifest map of format.md 6, keys in the order the encoder has always written them."""
        d = {
            "format": self.format, "version": list(self.version), "generator": self.generator, "name": self.name,
            "splats": self.splats, "leaf_splats": self.leaf_splats, "sh_degree": self.sh_degree,
            "preset": self.preset, "formats": dict(self.formats), "chunk_size": self.chunk_size,
            "chunk_order": self.chunk_order, "bounds": self.bounds.to_dict(),
            "extent_bounds": self.extent_bounds.to_dict(), "up": list(self.up), "camera": self.camera.to_dict(),
        }
        if self.sh_codebook is not None:
            d["sh_codebook"] = self.sh_codebook.to_dict()
        d.update({
            "lod": self.lod.to_dict(), "root": self.root, "tiles": [t.to_dict() for t in self.tiles],
            "gpu_bytes": self.gpu_bytes, "gpu_bytes_per_splat": self.gpu_bytes_per_splat,
            "leaf_bytes_on_disk": self.leaf_bytes_on_disk,
            "attributes": {a: s.to_dict() for a, s in self.attributes.items()},
            "encode_seconds": self.encode_seconds, "bytes_on_disk": self.bytes_on_disk,
        })
        return d

    def with_bytes_on_disk(self, payload_bytes: int) -> Manifest:
        """This manifest with `bytes_on_disk` = payload bytes + its own packed size (which depends on the value)."""
        m = self
        for _ in range(3):  # the msgpack length of the number can change the length once; settled after two
            m = replace(m, bytes_on_disk=payload_bytes + len(pack_manifest(m)))
        return m


def pack_manifest(m: Manifest) -> bytes:
    """The manifest file's bytes (with its checksum from version 1.2 on)."""
    return pack_manifest_dict(m.to_dict())


def pack_manifest_dict(d: dict) -> bytes:
    """A manifest map as the file of its version: from 1.2 on `checksum` is moved to the end and computed (the
    map is packed with 64 ASCII '0' as its value, hashed, and the digest patched in); before 1.2 it is left out."""
    d = {k: v for k, v in d.items() if k != CHECKSUM_KEY}
    version = d.get("version")
    two_ints = isinstance(version, (list, tuple)) and len(version) == 2 and all(
        isinstance(v, int) and not isinstance(v, bool) for v in version)
    if not (two_ints and tuple(version) >= CHECKSUM_VERSION):
        return msgpack.packb(d, use_bin_type=True)
    d[CHECKSUM_KEY] = CHECKSUM_PLACEHOLDER.decode()
    packed = msgpack.packb(d, use_bin_type=True)
    assert packed.endswith(CHECKSUM_PLACEHOLDER)  # a 64-character str is the last thing in the map
    return packed[:-64] + manifest_checksum(packed).encode()


def manifest_checksum(raw: bytes) -> str:
    """SHA-256 (hex) of manifest bytes whose last 64 bytes are the checksum value, read as 64 ASCII '0'."""
    return hashlib.sha256(raw[:-64] + CHECKSUM_PLACEHOLDER).hexdigest()


def _verify_checksum(raw: bytes, d: dict, source: str) -> None:
    """format.md 6, Checksum: a 1.2+ manifest's last key is `checksum`, its value the file's last 64 bytes."""
    keys = list(d)
    if CHECKSUM_KEY not in d:
        raise FormatError(source, CHECKSUM_KEY, f"missing (a version {d['version'][0]}.{d['version'][1]} manifest "
                          "ends with its checksum)")
    value = d[CHECKSUM_KEY]
    if not isinstance(value, str) or not SHA256_HEX_RE.match(value):
        raise FormatError(source, CHECKSUM_KEY, f"expected 64 lowercase hex digits, got {value!r}")
    if keys[-1] != CHECKSUM_KEY or raw[-64:] != value.encode():
        raise FormatError(source, CHECKSUM_KEY, "not the manifest's last key and value")
    actual = manifest_checksum(raw)
    if actual != value:
        raise FormatError(source, CHECKSUM_KEY, f"checksum mismatch: the manifest is corrupt (it records {value}, "
                          f"its bytes hash to {actual})")


def filter_element(name: str) -> int:
    if name == "none":
        return 1
    if name.startswith("shuffle") and name[7:].isdigit() and 1 < int(name[7:]) <= 16:
        return int(name[7:])
    raise ValueError(name)


def filter_for(element: int) -> str:
    return f"shuffle{element}" if element > 1 else "none"


# --------------------------------------------------------------------------------------------------------------
# Parsing and validation


class _Map:
    """A msgpack map being read: typed getters that raise FormatError naming `path.key`; unknown keys checked."""

    def __init__(self, source: str, path: str, value, strict: bool):
        if not isinstance(value, dict):
            raise FormatError(source, path or None, f"expected a map, got {type(value).__name__}")
        self.source, self.path, self.d, self.strict = source, path, value, strict
        self.used: set[str] = set()

    def where(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str | None, problem: str):
        raise FormatError(self.source, self.where(key) if key else (self.path or None), problem)

    def raw(self, key: str, optional: bool = False):
        self.used.add(key)
        if key not in self.d:
            if optional:
                return None
            self.fail(key, "missing")
        return self.d[key]

    def int(self, key: str, lo: int = 0, hi: int = 2**62) -> int:
        v = self.raw(key)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            self.fail(key, f"expected an integer {lo}..{hi}, got {v!r}")
        return v

    def float(self, key: str, lo: float = -math.inf, hi: float = math.inf) -> float:
        v = self.raw(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
            self.fail(key, f"expected a finite number in [{lo}, {hi}], got {v!r}")
        return float(v)

    def str(self, key: str, choices: tuple[str, ...] | None = None) -> str:
        v = self.raw(key)
        if not isinstance(v, str) or (choices is not None and v not in choices):
            want = f"one of {', '.join(choices)}" if choices else "a string"
            self.fail(key, f"expected {want}, got {v!r}")
        return v

    def bool(self, key: str) -> bool:
        v = self.raw(key)
        if not isinstance(v, bool):
            self.fail(key, f"expected true or false, got {v!r}")
        return v

    def vec(self, key: str, n: int = 3) -> tuple[float, ...]:
        v = self.raw(key)
        if (not isinstance(v, (list, tuple)) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            self.fail(key, f"expected {n} finite numbers, got {v!r}")
        return tuple(float(x) for x in v)

    def ints(self, key: str, n: int | None = None, lo: int = 0, hi: int = 2**62) -> tuple[int, ...]:
        v = self.raw(key)
        if (not isinstance(v, (list, tuple)) or (n is not None and len(v) != n)
                or not all(isinstance(x, int) and not isinstance(x, bool) and lo <= x <= hi for x in v)):
            count = f"{n} " if n is not None else ""
            self.fail(key, f"expected a list of {count}integers {lo}..{hi}, got {v!r}")
        return tuple(v)

    def map(self, key: str) -> _Map:
        return _Map(self.source, self.where(key), self.raw(key), self.strict)

    def list(self, key: str, limit: int = MAX_TILES) -> list:
        v = self.raw(key)
        if not isinstance(v, (list, tuple)) or len(v) > limit:
            self.fail(key, f"expected a list of at most {limit} items, got {type(v).__name__}")
        return list(v)

    def done(self) -> None:
        """Unknown keys are errors in a manifest of a version this reader knows (format.md 6, Versioning)."""
        if self.strict:
            extra = sorted(str(k) for k in self.d if k not in self.used)
            if extra:
                self.fail(None, f"unknown key{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra))}")


def _box(m: _Map, key: str) -> Box:
    b = m.map(key)
    lo, hi = b.vec("min"), b.vec("max")
    if any(a > c for a, c in zip(lo, hi, strict=True)):
        b.fail(None, f"min {lo} exceeds max {hi}")
    b.done()
    return Box(lo, hi)


_PAYLOAD_KEYS = frozenset({"file", "sha256", "bytes", "raw_bytes", "gpu_bytes", "sections"})
_TEXELS_KEYS = frozenset({"name", "kind", "offset", "size", "filter", "format", "width", "height", "layers"})
_RANGE_KEYS = frozenset({"name", "kind", "offset", "size", "filter", "dtype", "shape"})
_FILTERS = frozenset(["none"] + [f"shuffle{n}" for n in range(2, 17)])


def _is_int(v) -> bool:
    return type(v) is int  # not bool, not float


def _payload_fast(v, expect: list[tuple[str, dict]], chunks: int, strict: bool) -> PayloadEntry | None:
    """The same checks as _payload with plain dict operations (a 6M-splat scene's manifest has thousands of
    sections: this is most of the time a client waits for it); None when anything is off, and _payload then says
    what, naming the field."""
    if type(v) is not dict or not (v.keys() == _PAYLOAD_KEYS if strict else v.keys() >= _PAYLOAD_KEYS):
        return None
    sha, file, raw, size, gpu, items = (v["sha256"], v["file"], v["raw_bytes"], v["bytes"], v["gpu_bytes"],
                                        v["sections"])
    if not (type(sha) is str and SHA256_HEX_RE.match(sha) and file == payload_name(sha) and _is_int(raw)
            and 0 <= raw <= MAX_PAYLOAD_RAW_BYTES and _is_int(size) and 0 <= size <= raw + raw // 128 + 1024
            and _is_int(gpu) and 0 <= gpu <= MAX_PAYLOAD_RAW_BYTES and type(items) is list
            and len(items) == len(expect)):
        return None
    expected = dict(expect)
    sections = []
    gpu_total = 0
    for item in items:
        if type(item) is not dict:
            return None
        want = expected.pop(item.get("name"), None)
        if want is None or item.get("kind") != want["kind"]:
            return None
        kind = want["kind"]
        if not (item.keys() == (_TEXELS_KEYS if kind == "texels" else _RANGE_KEYS) or not strict and
                item.keys() >= (_TEXELS_KEYS if kind == "texels" else _RANGE_KEYS)):
            return None
        offset, length, filt = item["offset"], item["size"], item["filter"]
        if not (_is_int(offset) and _is_int(length) and 0 <= offset and offset % ALIGN == 0 and 0 <= length
                and offset + length <= raw and (filt in _FILTERS or filt == FIELDS1 and kind == "texels")):
            return None
        if kind == "texels":
            fmt, width, height, layers = item["format"], item["width"], item["height"], item["layers"]
            if not (fmt == want["format"] and _is_int(width) and _is_int(height) and _is_int(layers)
                    and BLOCK <= width <= 1 << 16 and BLOCK <= height <= 1 << 16 and width % BLOCK == 0
                    and height % BLOCK == 0 and chunks <= (width // BLOCK) * (height // BLOCK) <= max_blocks(chunks)
                    and layers == want["layers"] and _stored_size_problem(fmt, width, height, layers, filt, length)
                    is None):
                return None
            sections.append(_section(item["name"], kind, offset, length, filt, fmt, width, height, layers, "", ()))
            gpu_total += _texels_size(fmt, width, height, layers)
        else:
            dtype, shape = item["dtype"], item["shape"]
            if not (dtype == want["dtype"] and type(shape) is list and shape == list(want["shape"])):
                return None
            n = 4 if dtype == "f32" else 2
            for k in shape:
                n *= k
            if length != n:
                return None
            sections.append(_section(item["name"], kind, offset, length, filt, "", 0, 0, 0, dtype, tuple(shape)))
            gpu_total += length
    if expected:
        return None
    end = 0
    for sec in sorted(sections, key=_offset):
        if sec.offset < end:  # overlaps the one before
            return None
        end = sec.offset + sec.size
    if raw != end or gpu != gpu_total:
        return None
    return PayloadEntry(file, sha, size, raw, gpu, tuple(sections))


_offset = operator.attrgetter("offset")
_new = object.__new__


def _section(name: str, kind: str, offset: int, size: int, filt: str, fmt: str, width: int, height: int, layers: int,
             dtype: str, shape: tuple) -> Section:
    """A Section from fields already checked, without the frozen dataclass's __init__ (eleven object.__setattr__
    calls: 2 us, a third of the time to parse a 6M-splat scene's manifest)."""
    sec = _new(Section)
    sec.__dict__.update(name=name, kind=kind, offset=offset, size=size, filter=filt, format=fmt, width=width,
                        height=height, layers=layers, dtype=dtype, shape=shape)
    return sec


@functools.lru_cache(maxsize=1024)
def max_blocks(chunks: int) -> int:
    """The most 16x16 blocks a texture of `chunks` chunks may have (format.md 4.1): twice the chunks and one row of
    the widest texture. The encoder's textures waste less than a row; a larger one declares texels nothing fills
    (a 1-splat tile claiming 8192x8192, a gigabyte to decompress and upload)."""
    return 2 * chunks + MAX_WASTED_BLOCKS


def _texels_size(fmt: str, width: int, height: int, layers: int) -> int:
    return blob_size(FORMATS[fmt], width, height, layers)


@functools.lru_cache(maxsize=4096)  # a large scene's thousands of sections repeat a few shapes
def _stored_size_problem(fmt: str, width: int, height: int, layers: int, filt: str, length: int) -> str | None:
    """What is wrong with a texels section's stored size, or None: the texture's bytes for none/shuffleN, a size
    within what the fields1 layout allows (format.md 5.2; the exact size depends on modes only the bytes hold)."""
    if filt != FIELDS1:
        need = blob_size(FORMATS[fmt], width, height, layers)
        return None if length == need else f"{length} bytes for {layers} layers of {width}x{height} {fmt}, " \
            f"expected {need}"
    if fmt not in FIELD_LAYOUTS:
        return f"fields1 does not apply to texel format {fmt}"
    lo, hi = content_bounds(fmt, width, height, layers)
    return None if lo <= length <= hi else f"{length} bytes of fields1 content for {layers} layers of " \
        f"{width}x{height} {fmt}, expected {lo}..{hi}"


def _payload(m: _Map, key: str, expect: list[tuple[str, dict]], chunks: int) -> PayloadEntry:
    """Parse a payload entry; `expect` is [(section name, {kind, format, layers, dtype, shape, ...})]."""
    m.used.add(key)
    fast = _payload_fast(m.d.get(key), expect, chunks, m.strict)
    if fast is not None:
        return fast
    p = m.map(key)
    sha = p.str("sha256")
    if not SHA256_HEX_RE.match(sha):
        p.fail("sha256", f"expected 64 lowercase hex digits, got {sha!r}")
    file = p.str("file")
    if file != payload_name(sha):
        p.fail("file", f"expected {payload_name(sha)!r} (the payload's name is its SHA-256), got {file!r}")
    raw_bytes = p.int("raw_bytes", 0, MAX_PAYLOAD_RAW_BYTES)
    # zstd never expands data by more than a small bound; a larger claim is a lie a client must not allocate for.
    size = p.int("bytes", 0, raw_bytes + raw_bytes // 128 + 1024)
    gpu_bytes = p.int("gpu_bytes", 0, MAX_PAYLOAD_RAW_BYTES)
    items = p.list("sections", 64)
    expected = dict(expect)
    sections = []
    for i, item in enumerate(items):
        s = _Map(p.source, f"{p.path}.sections[{i}]", item, p.strict)
        name = s.str("name")
        want = expected.pop(name, None)
        if want is None:
            s.fail("name", f"unexpected section {name!r} (this payload holds {', '.join(n for n, _ in expect)})")
        kind = s.str("kind", ("texels", "range"))
        if kind != want["kind"]:
            s.fail("kind", f"expected {want['kind']!r}, got {kind!r}")
        offset = s.int("offset", 0, raw_bytes)
        length = s.int("size", 0, raw_bytes)
        if offset % ALIGN:
            s.fail("offset", f"{offset} is not a multiple of {ALIGN}")
        if offset + length > raw_bytes:
            s.fail("size", f"offset {offset} + size {length} lies outside the {raw_bytes}-byte payload")
        filt = s.str("filter")
        try:
            filter_element(filt)
        except ValueError:
            if filt != FIELDS1 or kind != "texels":
                s.fail("filter", f"unknown filter {filt!r} (expected {FILTERS_DOC})")
        if kind == "texels":
            fmt = s.str("format", tuple(FORMATS))
            if fmt != want["format"]:
                s.fail("format", f"expected {want['format']!r} (the manifest's format for this plane), got {fmt!r}")
            width, height = s.int("width", BLOCK, 1 << 16), s.int("height", BLOCK, 1 << 16)
            if width % BLOCK or height % BLOCK or (width // BLOCK) * (height // BLOCK) < chunks:
                s.fail(None, f"texture {width}x{height} cannot hold {chunks} chunks of {BLOCK}x{BLOCK} texels")
            if (width // BLOCK) * (height // BLOCK) > max_blocks(chunks):
                s.fail(None, f"texture {width}x{height} has {(width // BLOCK) * (height // BLOCK)} blocks of "
                       f"{BLOCK}x{BLOCK} texels for {chunks} chunks (at most {max_blocks(chunks)}: format.md 4.1)")
            layers = s.int("layers", 1, 64)
            if layers != want["layers"]:
                s.fail("layers", f"expected {want['layers']}, got {layers}")
            problem = _stored_size_problem(fmt, width, height, layers, filt, length)
            if problem is not None:
                s.fail("filter" if problem.startswith("fields1") else "size", problem)
            sections.append(Section(name, kind, offset, length, filt, format=fmt, width=width, height=height,
                                    layers=layers))
        else:
            dtype = s.str("dtype", ("f32", "f16"))
            if dtype != want["dtype"]:
                s.fail("dtype", f"expected {want['dtype']!r}, got {dtype!r}")
            shape = s.ints("shape", 4, 0, 1 << 24)
            if list(shape) != list(want["shape"]):
                s.fail("shape", f"expected {list(want['shape'])}, got {list(shape)}")
            need = int(np.prod(shape)) * (4 if dtype == "f32" else 2)
            if length != need:
                s.fail("size", f"{length} bytes for a {dtype} range of shape {list(shape)}, expected {need}")
            sections.append(Section(name, kind, offset, length, filt, dtype=dtype, shape=tuple(shape)))
        s.done()
    if expected:
        p.fail("sections", f"missing section{'s' if len(expected) > 1 else ''} {', '.join(map(repr, expected))}")
    ordered = sorted(sections, key=lambda s: s.offset)
    for a, b in zip(ordered, ordered[1:], strict=False):
        if a.offset + a.size > b.offset:
            p.fail("sections", f"sections {a.name!r} and {b.name!r} overlap")
    end = max((s.offset + s.size for s in sections), default=0)
    if raw_bytes != end:
        p.fail("raw_bytes", f"{raw_bytes}, but the sections end at byte {end}")
    if gpu_bytes != sum(s.gpu_size for s in sections):
        p.fail("gpu_bytes", f"{gpu_bytes}, but the sections decode to {sum(s.gpu_size for s in sections)} bytes")
    p.done()
    return PayloadEntry(file, sha, size, raw_bytes, gpu_bytes, tuple(sections))


def expected_sections(group: str, codebook: bool, formats: dict[str, str], chunks: int,
                      codebook_format: str | None = None) -> list[tuple[str, dict]]:
    """The sections a payload group must hold: [(name, properties)] (format.md 4.4, 4.7, 5).

    `group` is a tile group (`codebook`: the scene has an SH codebook), or `cb:sh<b>` for a codebook band."""
    return _expected_sections(group, codebook, tuple(sorted(formats.items())), chunks, codebook_format)


@functools.lru_cache(maxsize=1024)  # the same few groups and chunk counts for every tile of a scene
def _expected_sections(group: str, codebook: bool, format_items: tuple, chunks: int,
                       codebook_format: str | None) -> list[tuple[str, dict]]:
    formats = dict(format_items)
    if group.startswith("cb:"):
        specs = (band_plane(int(group[5:])),)
    else:
        specs = group_planes(group, codebook)
    out = []
    for spec in specs:
        if spec.name == "sh_index":
            fmt = SH_INDEX_FORMAT
        elif group.startswith("cb:"):
            fmt = codebook_format
        else:
            fmt = formats[spec.attribute]
        out.append((spec.name, {"kind": "texels", "format": fmt, "layers": spec.layers}))
        if spec.range_dtype:
            out.append((spec.range_name, {"kind": "range", "dtype": RANGE_DTYPE_NAMES[spec.range_dtype],
                                          "shape": [chunks, 2, spec.layers, spec.components]}))
    return out


def parse_manifest(raw: bytes, source: str = MANIFEST_NAME, lazy_payloads: bool = False) -> Manifest:
    """Parse and validate manifest file bytes; from version 1.2 on the checksum is verified first.

    lazy_payloads (the streaming client): each tile's payload entries are checked when first read (a FormatError
    naming the field then), not here; everything else, totals included, is checked now. They are most of the parse
    of a large scene's manifest (a 6M-splat scene's: 2,732 entries, 27,000 sections), which a client waits for
    before its first frame and then reads a few at a time."""
    with _collector_paused():
        return _parse_manifest(raw, source, lazy_payloads)


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


def _object_bytes_bound() -> np.ndarray:
    """Per msgpack lead byte: about the bytes of Python objects the value it starts becomes (with its pointer in
    its container). A map or array of one byte is a 64-byte object; a small int, nil or a bool only a pointer."""
    cost = np.full(256, 8, np.int64)
    cost[0x80:0xA0] = cost[0xDC:0xE0] = 80      # fixmap, fixarray, array16/32, map16/32
    cost[0xA0:0xC0] = cost[0xD9:0xDC] = 64      # strings
    cost[0xC4:0xC7] = 64                        # bin
    cost[0xCA:0xCC] = 32                        # floats
    cost[0xCC:0xD4] = 40                        # ints beyond the cached small ones
    return cost


_OBJECT_BYTES = _object_bytes_bound()
# The Python objects a manifest may unpack into, estimated from its bytes before anything is built (real manifests
# estimate 17 bytes per byte and make a third of that: one of 44 MB passes; a 64 MiB array of empty maps, 4.9 GB
# unpacked, does not).
MAX_MANIFEST_OBJECT_BYTES = 768 << 20


def check_msgpack_bomb(raw: bytes, source: str) -> None:
    """Refuse manifest bytes that would unpack into more objects than MAX_MANIFEST_OBJECT_BYTES (counting every
    byte as the lead byte of a value bounds what any parse builds), or whose top level is not a map."""
    if not raw or not (0x80 <= raw[0] <= 0x8F or raw[0] in (0xDE, 0xDF)):
        raise FormatError(source, None, "not a msgpack manifest (expected a map at the top)")
    counts = np.zeros(256, np.int64)
    view = np.frombuffer(raw, np.uint8)
    for start in range(0, len(view), 1 << 22):  # bincount widens to int64: 8 bytes per byte, so in 4 MiB pieces
        counts += np.bincount(view[start:start + (1 << 22)], minlength=256)
    estimate = int(counts @ _OBJECT_BYTES)
    if estimate > MAX_MANIFEST_OBJECT_BYTES:
        containers = int(counts[0x80:0xA0].sum() + counts[0xDC:0xE0].sum())
        raise FormatError(source, None, f"{len(raw)} bytes that would unpack into about {estimate >> 20} MiB of "
                          f"objects (up to {containers} maps and arrays; at most {MAX_MANIFEST_OBJECT_BYTES >> 20} "
                          "MiB): not a manifest")


def _parse_manifest(raw: bytes, source: str, lazy_payloads: bool) -> Manifest:
    check_msgpack_bomb(raw, source)
    try:
        d = msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise FormatError(source, None, f"not a msgpack manifest ({exc.__class__.__name__}: {exc})") from None
    version = _check_format_and_version(d, source)
    if version >= CHECKSUM_VERSION:
        _verify_checksum(raw, d, source)
    manifest = manifest_from_dict(d, source, lazy_payloads)
    if CHECKSUM_VERSION <= version <= FORMAT_VERSION:
        files = manifest.payload_bytes()
        if manifest.bytes_on_disk != files + len(raw):
            _check_all_entries(manifest.tiles)
            raise FormatError(source, "bytes_on_disk", f"{manifest.bytes_on_disk}, but the payload files and the "
                              f"manifest are {files + len(raw)} bytes")
    return manifest


def _check_all_entries(tiles) -> None:
    """Read every payload entry of these tiles: a lazily checked one that is wrong raises its own FormatError."""
    for t in tiles:
        for name in t.groups:
            t.groups[name]


def _entry_fields(groups: Mapping[str, PayloadEntry], name: str, fields: tuple[str, ...]) -> tuple:
    """Fields of one payload entry: from the raw map where it is checked lazily and they have the right types."""
    if isinstance(groups, LazyPayloads):
        return groups.raw_fields(name, fields)
    entry = groups[name]
    return tuple(getattr(entry, f) for f in fields)


class LazyPayloads(Mapping):
    """A tile's payload entries (group name -> PayloadEntry), each checked when first read, as manifest_from_dict
    checks them (parse_manifest(..., lazy_payloads=True)); a bad one raises the same FormatError, naming the field."""

    def __init__(self, raw: dict, names: tuple[str, ...], codebook: bool, formats: dict[str, str], chunks: int,
                 strict: bool, texture: tuple[int, int], source: str, path: str):
        self._raw, self._names, self._codebook, self._formats = raw, names, codebook, formats
        self._chunks, self._strict, self._texture, self._source, self._path = chunks, strict, texture, source, path
        self._checked: dict[str, PayloadEntry] = {}

    def __getitem__(self, name: str) -> PayloadEntry:
        entry = self._checked.get(name)
        if entry is None:
            if name not in self._names:
                raise KeyError(name)
            entry = self._checked[name] = _checked_group(self._raw, name, self._codebook, self._formats,
                                                         self._chunks, self._strict, self._texture, self._source,
                                                         self._path)
        return entry

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def raw_fields(self, name: str, fields: tuple[str, ...]) -> tuple:
        """Fields of an entry as stored, where they are a non-negative integer or a payload file name; otherwise the
        entry is checked (and a bad one raises)."""
        raw = self._raw.get(name)
        if name in self._names and type(raw) is dict:
            values = tuple(raw.get(f) for f in fields)
            if all((_is_int(v) and v >= 0) if f != "file" else type(v) is str for f, v in zip(fields, values,
                                                                                               strict=True)):
                return values
        entry = self[name]
        return tuple(getattr(entry, f) for f in fields)


def _fast_group(raw_groups: dict, name: str, codebook: bool, formats: dict[str, str], chunks: int, strict: bool,
                texture: tuple[int, int]) -> PayloadEntry | None:
    """_payload_fast of one tile group, with its texels the tile's texture size; None when anything is off."""
    entry = _payload_fast(raw_groups.get(name), expected_sections(name, codebook, formats, chunks), chunks, strict)
    if entry is None or any(sec.kind == "texels" and (sec.width, sec.height) != texture for sec in entry.sections):
        return None
    return entry


def _checked_group(raw_groups: dict, name: str, codebook: bool, formats: dict[str, str], chunks: int, strict: bool,
                   texture: tuple[int, int], source: str, path: str) -> PayloadEntry:
    """One tile group's payload entry, checked as manifest_from_dict checks it (the fast path, then the one that
    names what is wrong)."""
    entry = _fast_group(raw_groups, name, codebook, formats, chunks, strict, texture)
    if entry is not None:
        return entry
    gm = _Map(source, path, raw_groups, strict)
    entry = _payload(gm, name, expected_sections(name, codebook, formats, chunks), chunks)
    for sec in entry.sections:
        if sec.kind == "texels" and (sec.width, sec.height) != texture:
            gm.fail(f"{name}.sections", f"{sec.name} is {sec.width}x{sec.height}, the tile's texture "
                    f"{texture[0]}x{texture[1]}")
    return entry


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


def writer_version(formats: Mapping[str, str], codebook_format: str | None = None,
                   chunk_order: str = "morton") -> tuple[int, int]:
    """The version a writer writes a scene of these texel formats and chunk order as: 1.4 in the chunk order
    `input`, 1.3 with a norm16x4 or norm9x3 plane (or SH codebook), 1.2 otherwise (every scene carries the 1.2
    manifest checksum)."""
    if chunk_order in CHUNK_ORDERS_1_4:
        return VERSION_1_4
    used = set(formats.values()) | ({codebook_format} if codebook_format else set())
    return VERSION_1_3 if used & set(FORMATS_1_3) else CHECKSUM_VERSION


def manifest_from_dict(d, source: str = MANIFEST_NAME, lazy_payloads: bool = False) -> Manifest:
    """Validate a manifest map (format.md 6) into a Manifest; FormatError names the first field that is wrong.
    (The checksum, a property of the file's bytes, is verified by parse_manifest.)"""
    version = _check_format_and_version(d, source)
    # Keys are added only in new minor versions: in a version this reader knows, an unknown key is damage.
    strict = version[1] <= FORMAT_VERSION[1]
    m = _Map(source, "", d, strict)
    m.raw("format")
    m.raw("version")
    if version >= CHECKSUM_VERSION:
        m.raw(CHECKSUM_KEY, optional=True)
    splats = m.int("splats", 1)
    sh_degree = m.int("sh_degree", 0, MAX_SH_DEGREE)
    fm = m.map("formats")
    formats = {a: fm.str(a, VALUE_FORMATS) for a in ("position", "rotation", "scale", "color", "sh")}
    fm.done()
    for a, f in formats.items():
        if f in FORMATS_1_3 and version < VERSION_1_3:
            fm.fail(a, f"{f} is a version 1.3 texel format; the manifest is version {version[0]}.{version[1]}")
    if FORMATS[formats["color"]].components < 4:
        fm.fail("color", f"{formats['color']} has 3 components; color needs 4")
    chunk_size = m.int("chunk_size", CHUNK_SIZE, CHUNK_SIZE)
    chunk_order = m.str("chunk_order", CHUNK_ORDER_NAMES)
    if chunk_order in CHUNK_ORDERS_1_4 and version < VERSION_1_4:
        m.fail("chunk_order", f"{chunk_order} is a version 1.4 chunk order; the manifest is version "
               f"{version[0]}.{version[1]}")
    codebook = None
    if m.raw("sh_codebook", optional=True) is not None:
        c = m.map("sh_codebook")
        entries = c.int("entries", 1, 65536)
        cb_format = c.str("format", VALUE_FORMATS)
        if cb_format in FORMATS_1_3 and version < VERSION_1_3:
            c.fail("format", f"{cb_format} is a version 1.3 texel format; the manifest is version "
                   f"{version[0]}.{version[1]}")
        index_format = c.str("index_format", (SH_INDEX_FORMAT,))
        g = c.map("groups")
        cb_chunks = chunks_for(entries)
        cb_groups = {}
        for b in range(1, sh_degree + 1):
            cb_groups[f"sh{b}"] = _payload(g, f"sh{b}", expected_sections(f"cb:sh{b}", True, formats, cb_chunks,
                                                                          cb_format), cb_chunks)
        g.done()
        c.done()
        codebook = SHCodebookEntry(entries, cb_format, index_format, cb_groups)
    group_names = groups_for_degree(sh_degree, codebook is not None)
    tiles = []
    ids: set[int] = set()
    for i, item in enumerate(m.list("tiles")):
        fast = _tile_fast(item, group_names, codebook is not None, formats, strict,
                          (source, f"tiles[{i}].groups") if lazy_payloads else None)
        if fast is not None and fast.id not in ids:
            ids.add(fast.id)
            tiles.append(fast)
            continue
        t = _Map(source, f"tiles[{i}]", item, strict)
        tid = t.int("id", 0, 2**31 - 1)
        if tid in ids:
            t.fail("id", f"tile id {tid} appears twice")
        ids.add(tid)
        n = t.int("splats", 1, 1 << 31)
        chunks = t.int("chunks", 1, 1 << 24)
        if chunks != chunks_for(n):
            t.fail("chunks", f"{chunks}, but {n} splats make {chunks_for(n)} chunks")
        texture = t.ints("texture", 2, BLOCK, 1 << 16)
        if texture[0] % BLOCK or texture[1] % BLOCK or (texture[0] // BLOCK) * (texture[1] // BLOCK) < chunks:
            t.fail("texture", f"{texture[0]}x{texture[1]} cannot hold {chunks} chunks")
        sphere = t.map("sphere")
        center, radius = sphere.vec("center"), sphere.float("radius", 0.0)
        sphere.done()
        gm = t.map("groups")
        groups = {}
        for name in group_names:
            groups[name] = _checked_group(gm.d, name, codebook is not None, formats, chunks, strict,
                                          (texture[0], texture[1]), source, gm.path)
            gm.used.add(name)
        gm.done()
        tiles.append(TileEntry(tid, t.int("level", 0, 64), t.ints("children", None, 0, 2**31 - 1), n, chunks,
                               (texture[0], texture[1]), _box(t, "box"), center, radius,
                               t.float("geometric_error", 0.0), groups))
        t.done()
    if not tiles:
        m.fail("tiles", "no tiles: a scene has at least its root tile")
    root = m.int("root", 0, 2**31 - 1)
    _check_tree(source, tiles, root)
    leaf_splats = m.int("leaf_splats", 1)
    leaf_sum = sum(t.splats for t in tiles if t.is_leaf)
    if leaf_splats != leaf_sum or splats != leaf_sum:
        m.fail("splats", f"splats {splats} and leaf_splats {leaf_splats} must both equal the leaf tiles' "
               f"{leaf_sum} splats")
    cam = m.map("camera")
    camera = CameraEntry(cam.vec("eye"), cam.vec("target"), cam.vec("up"), cam.float("fov_y", 1e-3, 179.0))
    if camera.eye == camera.target:
        cam.fail("eye", "the camera's eye and target coincide")
    if not any(camera.up):
        cam.fail("up", "zero-length up vector")
    cam.done()
    up = m.vec("up")
    if not any(up):
        m.fail("up", "zero-length up vector")
    lod = m.map("lod")
    lod_info = LodInfo(lod.bool("enabled"), lod.int("max_leaf_splats", 1), lod.float("reduction", 1.0),
                       lod.str("refine", ("replace",)))
    lod.done()
    am = m.map("attributes")
    attributes = {}
    for a in [k for k in ("position", "rotation", "scale", "color", "sh") if k in am.d]:
        s = am.map(a)
        attributes[a] = AttributeSize(s.str("format", VALUE_FORMATS), s.int("gpu_bytes"), s.int("disk_bytes"))
        s.done()
    am.done()
    manifest = Manifest(
        version=(version[0], version[1]), generator=m.str("generator"), name=m.str("name"), splats=splats,
        leaf_splats=leaf_splats, sh_degree=sh_degree, preset=m.str("preset"), formats=formats,
        chunk_size=chunk_size, chunk_order=chunk_order, bounds=_box(m, "bounds"),
        extent_bounds=_box(m, "extent_bounds"), up=up, camera=camera, sh_codebook=codebook, lod=lod_info,
        root=root, tiles=tuple(tiles), gpu_bytes=m.int("gpu_bytes"),
        gpu_bytes_per_splat=m.float("gpu_bytes_per_splat", 0.0), leaf_bytes_on_disk=m.int("leaf_bytes_on_disk"),
        attributes=attributes, encode_seconds=m.float("encode_seconds", 0.0),
        bytes_on_disk=m.int("bytes_on_disk"))
    m.done()
    if not strict:  # a newer minor version may add payloads these totals count; only its own keys are checked
        return manifest
    # Totals a reader can recompute must agree (a resealed but edited manifest, or a writer's bug).
    leaf_sizes = [_entry_fields(t.groups, name, ("gpu_bytes", "bytes")) for t in manifest.leaves for name in t.groups]
    if codebook is not None:
        leaf_sizes += [(p.gpu_bytes, p.bytes) for p in codebook.groups.values()]
    gpu = sum(g for g, _ in leaf_sizes)
    disk = sum(b for _, b in leaf_sizes)
    if manifest.gpu_bytes != gpu or manifest.leaf_bytes_on_disk != disk:
        _check_all_entries(manifest.leaves)  # a lazily checked entry at fault is named, not only the total
    if manifest.gpu_bytes != gpu:
        m.fail("gpu_bytes", f"{manifest.gpu_bytes}, but the leaf tiles' and codebook's sections hold {gpu} bytes")
    if manifest.leaf_bytes_on_disk != disk:
        m.fail("leaf_bytes_on_disk", f"{manifest.leaf_bytes_on_disk}, but the leaf tiles' and codebook's payloads "
               f"are {disk} bytes")
    return manifest


_TILE_KEYS = frozenset({"id", "level", "children", "splats", "chunks", "texture", "box", "sphere", "geometric_error",
                        "groups"})


def _finite3(v) -> bool:
    return (type(v) is list and len(v) == 3 and all(type(x) in (float, int) for x in v)
            and all(math.isfinite(x) for x in v))


def _tile_fast(v, group_names, codebook: bool, formats: dict[str, str], strict: bool,
               lazy: tuple[str, str] | None = None) -> TileEntry | None:
    """The checks of manifest_from_dict's tile loop with plain dict operations (a 6M-splat scene has thousands of
    tiles: with _payload_fast, the manifest of the 6M scene parses in a third of the time); None when anything is
    off, and the loop's _Map checks then say what, naming the field."""
    if type(v) is not dict or not (v.keys() == _TILE_KEYS if strict else v.keys() >= _TILE_KEYS):
        return None
    tid, level, children, n, chunks, texture = (v["id"], v["level"], v["children"], v["splats"], v["chunks"],
                                                v["texture"])
    if not (_is_int(tid) and 0 <= tid < 2**31 and _is_int(level) and 0 <= level <= 64 and _is_int(n)
            and 1 <= n <= 1 << 31 and _is_int(chunks) and chunks == chunks_for(n) and type(children) is list
            and all(_is_int(c) and 0 <= c < 2**31 for c in children) and type(texture) is list and len(texture) == 2
            and all(_is_int(x) and BLOCK <= x <= 1 << 16 and x % BLOCK == 0 for x in texture)
            and (texture[0] // BLOCK) * (texture[1] // BLOCK) >= chunks):
        return None
    box, sphere, error, groups = v["box"], v["sphere"], v["geometric_error"], v["groups"]
    if not (type(box) is dict and box.keys() == {"min", "max"} and _finite3(box["min"]) and _finite3(box["max"])
            and all(a <= b for a, b in zip(box["min"], box["max"], strict=True)) and type(sphere) is dict
            and sphere.keys() == {"center", "radius"} and _finite3(sphere["center"])
            and type(sphere["radius"]) in (float, int) and math.isfinite(sphere["radius"]) and sphere["radius"] >= 0
            and type(error) in (float, int) and math.isfinite(error) and error >= 0 and type(groups) is dict
            and (groups.keys() == set(group_names) if strict else groups.keys() >= set(group_names))):
        return None
    size = (texture[0], texture[1])
    if lazy is not None:  # (source, path): the entries are checked when read (LazyPayloads)
        entries = LazyPayloads(groups, tuple(group_names), codebook, formats, chunks, strict, size, *lazy)
    else:
        entries = {}
        for name in group_names:
            entry = _fast_group(groups, name, codebook, formats, chunks, strict, size)
            if entry is None:
                return None
            entries[name] = entry
    return TileEntry(tid, level, tuple(children), n, chunks, size,
                     Box(tuple(float(x) for x in box["min"]), tuple(float(x) for x in box["max"])),
                     tuple(float(x) for x in sphere["center"]), float(sphere["radius"]), float(error), entries)


def _check_tree(source: str, tiles: list[TileEntry], root: int) -> None:
    """One root at level 0; every other tile is the child of exactly one tile, one level below it."""
    by_id = {t.id: t for t in tiles}
    if root not in by_id:
        raise FormatError(source, "root", f"no tile with id {root}")
    parent: dict[int, int] = {}
    for i, t in enumerate(tiles):
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


def scene_summary(m: Manifest) -> dict:
    """JSON-ready facts about a scene, as `splatstream info` and the server's /api/scenes give them."""
    return {
        "name": m.name,
        "splats": m.splats,
        "sh_degree": m.sh_degree,
        "preset": m.preset,
        "bounds": m.bounds.to_dict(),
        "up": list(m.up),
        "bytes_on_disk": m.bytes_on_disk,
        "gpu_bytes": m.gpu_bytes,
        "gpu_bytes_per_splat": m.gpu_bytes_per_splat,
        "tiles": len(m.tiles),
        "levels": m.levels,
        "sh_codebook_entries": m.sh_codebook.entries if m.sh_codebook else None,
        "version": list(m.version),
    }
