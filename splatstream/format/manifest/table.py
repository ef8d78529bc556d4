"""The tile table of format 1.8 (format.md 6.2): a manifest's (or a page's) tiles column-wise, as little-endian numpy
arrays in msgpack bins, with every payload's section table reduced to a scene-level list of section layouts and
each section's size.

Up to 1.7 a tile was a msgpack map whose payload entries repeated each section's name, kind, filter, format,
texture size, layers, dtype and shape, and the hex SHA-256 twice (`file` and `sha256`): about 0.9 KB a tile,
more than most coarse tiles' payloads a splat (BENCHMARKS.md, "Manifest pages"). Everything but the layout's names
and filters, the sizes, the SHA-256 and the file bytes follows from the manifest's `formats`, the tile's splats and
texture and the 16-byte alignment of sections (format.md 5), so the table holds only those; a reader derives the
rest and checks the columns with array operations, not a Python loop over tiles' maps.

`pack_tile_table` is the writer's side (from the frozen records); `read_columns` the reader's first step (types and
lengths of the columns, one message naming the column); validate.py checks the values and makes the records, whose
payload entries are model.TablePayloads: built from the columns when first read. (Nothing here imports the
records: model.py packs its tiles with this module.)
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import NoReturn

import msgpack
import numpy as np
import zstandard

from ...errors import FormatError
from ..layout import ALIGN, BLOCK
from ..names import SHORT_DIGEST_BYTES, payload_name
from ..planes import MAX_SH_DEGREE
from .versions import VERSION_1_8, VERSION_1_12, VERSION_1_15
from .wire import check_msgpack_bomb

TABLE_KEY = "tile_table"
# Version 1.12 (format.md 6.2, "The compact tile table"): the same table with its bounds as f32 rounded outward,
# packed with msgpack and compressed with zstd, as one bin under this key in place of `tile_table`. A budgeted view
# of a 45-100k-splat scene draws a few tens of KB of tiles: the 1.8 table's 35-41 KB was most of what it read
# (issue 31, BENCHMARKS.md "Manifest pages", branch manifest31).
TABLE_ZSTD_KEY = "tile_table_zstd"
COMPACT_FLOAT_COLUMNS = ("box", "sphere", "geometric_error")  # f32 in the compact table, f64 in the plain one
# zstd level of the compact table: written once, read before the first frame; 19 is 3-7 % smaller than 3 or 9 on
# the real scenes' tables (donut 11.4 KB against 12.0 at 9), for 8-19 ms of encode CPU (0.2 ms a KB of table)
COMPACT_TABLE_ZSTD_LEVEL = 19
# The largest compact table a reader inflates: a manifest's own limit (wire.MAX_MANIFEST_BYTES)
MAX_COMPACT_TABLE_BYTES = 64 << 20

# Column name -> (dtype, values per row); rows: "tile" (T), "payload" (T x groups), or a count of their own.
_TILE_COLUMNS = {"id": ("<u4", 1), "level": ("u1", 1), "children": ("<u4", 1), "splats": ("<u4", 1),
                 "texture": ("<u2", 2), "box": ("<f8", 6), "sphere": ("<f8", 4), "geometric_error": ("<f8", 1)}
_PAYLOAD_COLUMNS = {"layout": ("<u2", 1), "sha256": ("u1", 32), "bytes": ("<u4", 1)}
_KEYS = ("count", *_TILE_COLUMNS, "child_ids", "groups", "layouts", *_PAYLOAD_COLUMNS, "sizes")
_PAGE_KEYS = ("tile", "sha256", "bytes")
# Version 1.15 (format.md 6.2, "Short digests and radii"): a compact table names each payload and page by the first
# 16 bytes of its SHA-256, in this column (and `page`'s) in place of `sha256`: 32 B a payload that do not compress
# were about half a compact table (issue 31, branch digest31). A 1.12 to 1.14 reader finds a column missing and
# rejects the table.
SHORT_DIGEST_KEY = "digest16"
_PAYLOAD_COLUMNS_SHORT = {"layout": ("<u2", 1), SHORT_DIGEST_KEY: ("u1", SHORT_DIGEST_BYTES), "bytes": ("<u4", 1)}
# and each tile's bounding sphere as its `radius` alone (f32[T]), its centre the middle of the tile's f32 box (which
# the encoder's tree always made it: lod.md 2), 0.8-1.5 KB of a table less.
RADIUS_KEY = "radius"
_TILE_COLUMNS_SHORT = {(RADIUS_KEY if k == "sphere" else k): ((dt, 1) if k == "sphere" else (dt, w))
                       for k, (dt, w) in _TILE_COLUMNS.items()}
_KEYS_SHORT = ("count", *_TILE_COLUMNS_SHORT, "child_ids", "groups", "layouts", *_PAYLOAD_COLUMNS_SHORT, "sizes")
_PAGE_KEYS_SHORT = ("tile", SHORT_DIGEST_KEY, "bytes")


def short_digests(version: tuple[int, int]) -> bool:
    """Whether a compact table (`tile_table_zstd`) of this version names its files by short digests (16 bytes of
    SHA-256: version 1.15). A 1.8 `tile_table` keeps the whole SHA-256 in any version."""
    return tuple(version) >= VERSION_1_15


def short_tile_names(tree: bool, compact_table: bool, short: bool) -> bool:
    """Whether an encoder names a scene's tile payloads by short digests (`data/<32 hex>.bin`, format.md 6.2): a
    tree (more than one tile: a single tile's `tiles` map keeps the whole SHA-256) written as the compact table
    (`compact_table`) with short digests (`short`: 1.15). One rule for the payload jobs, which write each tile payload
    under that name at once (no rename: an object store's rename is a copy and a delete), and for
    store.write_scene_manifest, which refuses to publish a manifest that would name them otherwise."""
    return tree and compact_table and short


def digest_key(short: bool) -> str:
    """The column a table's digests are in: `digest16` (1.15), else `sha256`."""
    return SHORT_DIGEST_KEY if short else "sha256"
MAX_LAYOUTS = 1 << 16


def _fail(source: str, field: str, problem: str) -> NoReturn:
    raise FormatError(source, f"{TABLE_KEY}.{field}", problem)


def _bin(a: np.ndarray, dtype: str) -> bytes:
    return np.ascontiguousarray(a, dtype).tobytes()


def canonical_offsets(sizes: Sequence[int]) -> tuple[list[int], int]:
    """Each section's offset when sections follow each other in order, each at the next multiple of 16 (format.md
    5), and the payload's raw bytes (the end of its last section)."""
    offsets, end = [], 0
    for size in sizes:
        end += (-end) % ALIGN
        offsets.append(end)
        end += size
    return offsets, end


def packable(tiles: Sequence, short: bool = False) -> bool:
    """Whether every payload's sections lie as the table derives them: in order, each at the next multiple of 16
    (what the encoder writes, container.write_payload), the file named by its digest (short: 16 bytes of its
    SHA-256, 1.15; else all 32), sizes within the columns."""
    width = 2 * (SHORT_DIGEST_BYTES if short else 32)
    for t in tiles:
        if t.page is not None and len(t.page.sha256) != width:
            return False
        if t.splats >= 1 << 32 or t.texture[0] % BLOCK or t.texture[1] % BLOCK:
            return False
        for e in t.groups.values():
            offsets, end = canonical_offsets([s.size for s in e.sections])
            if offsets != [s.offset for s in e.sections] or end != e.raw_bytes or e.bytes >= 1 << 32 \
                    or e.file != payload_name(e.sha256) or len(e.sha256) != width:
                return False
    return True


def down_f32(x) -> np.ndarray:
    """Each value as the largest float32 at or below it (a box's min, rounded outward)."""
    x = np.asarray(x, np.float64)
    with np.errstate(over="ignore"):  # beyond float32's range: inf, which compact_columns refuses
        f = x.astype(np.float32)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float32(-np.inf)), f)


def up_f32(x) -> np.ndarray:
    """Each value as the smallest float32 at or above it (a box's max, a radius, a geometric error)."""
    x = np.asarray(x, np.float64)
    with np.errstate(over="ignore"):  # beyond float32's range: inf, which compact_columns refuses
        f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


def bounds_columns(tiles: Sequence) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tiles' bounds as float64 columns: box (T x 6: min then max), sphere (T x 4: centre then radius) and
    geometric error (T)."""
    n = len(tiles)
    box = np.array([(*t.box.min, *t.box.max) for t in tiles], np.float64).reshape(n, 6)
    sphere = np.array([(*t.sphere_center, t.sphere_radius) for t in tiles], np.float64).reshape(n, 4)
    return box, sphere, np.array([t.geometric_error for t in tiles], np.float64)


def tiles_body(version: tuple[int, int], tiles: Sequence, group_names: Sequence[str]) -> dict:
    """The key a manifest or page of this version holds its tiles under, and its value: the compact tile table from
    1.12 on, the tile table from 1.8 on (format.md 6.2), else the array of tile maps (6)."""
    if version >= VERSION_1_12:
        return {TABLE_ZSTD_KEY: pack_compact_table(tiles, group_names, short_digests(version))}
    if version >= VERSION_1_8:
        return {TABLE_KEY: pack_tile_table(tiles, group_names)}
    return {"tiles": [t.to_dict() for t in tiles]}


def box_centres(box: np.ndarray) -> np.ndarray:
    """The middle of each box (T x 6: min then max), in f64: a 1.15 compact table's sphere centres (format.md 6.2)."""
    box = np.asarray(box, np.float64)  # the sum of two float32 values, exact in f64
    return (box[:, :3] + box[:, 3:]) * 0.5


def compact_columns(box: np.ndarray, sphere: np.ndarray, error: np.ndarray,
                    centre_from_box: bool = False) -> tuple[np.ndarray, ...]:
    """Tiles' bounds (box T x 6, sphere T x 4, geometric error T; f64) as float32 values that still hold what the
    f64 ones did (format.md 6.2, the compact table): the box rounded outward, each centre to the nearest float32
    (centre_from_box, 1.15: to the middle of the rounded box, in f64) and its radius grown by the centre's move and
    rounded up, the geometric error rounded up, so culling and the screen-space error stay conservative. Values
    already so come back unchanged (compacting twice is compacting once). Raises ValueError where a bound is beyond
    float32's range."""
    box = np.concatenate([down_f32(box[:, :3]), up_f32(box[:, 3:])], axis=1)
    center = box_centres(box) if centre_from_box else sphere[:, :3].astype(np.float32)
    moved = np.sqrt(((center.astype(np.float64) - sphere[:, :3]) ** 2).sum(axis=1))
    radius = np.where(moved == 0.0, sphere[:, 3], np.nextafter(sphere[:, 3] + moved, np.inf))
    sphere = np.concatenate([center.astype(np.float64), up_f32(radius)[:, None]], axis=1)
    error = up_f32(error)
    if not (np.isfinite(box).all() and np.isfinite(sphere).all() and np.isfinite(error).all()):
        raise ValueError("a tile's bounds are beyond float32's range: not a compact tile table")
    return box, sphere, error


def pack_compact_table(tiles: Sequence, group_names: Sequence[str], short: bool = False) -> bytes:
    """The `tile_table_zstd` bin of these tiles (format.md 6.2, version 1.12): the tile table with f32 bounds
    (rounded outward: compact_columns), msgpack-packed and zstd-compressed; short: its files named by 16-byte
    digests (1.15). Raises ValueError where the table cannot be written (packable) or a bound is beyond float32's
    range."""
    d = pack_tile_table(tiles, group_names, compact=True, short=short)
    raw = msgpack.packb(d, use_bin_type=True)
    return zstandard.ZstdCompressor(level=COMPACT_TABLE_ZSTD_LEVEL, write_content_size=True).compress(raw)


def unpack_compact_table(v, source: str) -> dict:
    """The tile table map a `tile_table_zstd` bin holds (its f32 columns as they are; read_columns(compact=True)
    reads them), or FormatError naming the key: not a bin, not a zstd frame that states its size, larger than
    MAX_COMPACT_TABLE_BYTES, or not a msgpack map."""
    if type(v) is not bytes:
        raise FormatError(source, TABLE_ZSTD_KEY, f"expected a bin (a zstd frame), got {type(v).__name__}")
    try:
        size = zstandard.frame_content_size(v)
    except zstandard.ZstdError as exc:
        raise FormatError(source, TABLE_ZSTD_KEY, f"not a zstd frame ({exc})") from None
    if not 0 < size <= MAX_COMPACT_TABLE_BYTES:
        raise FormatError(source, TABLE_ZSTD_KEY, "expected a zstd frame stating its size, "
                          f"1..{MAX_COMPACT_TABLE_BYTES} bytes, got {'no size' if size < 0 else size}")
    try:
        raw = zstandard.ZstdDecompressor().decompress(v, max_output_size=size)
    except zstandard.ZstdError as exc:
        raise FormatError(source, TABLE_ZSTD_KEY, f"a damaged zstd frame ({exc})") from None
    if len(raw) != size:
        raise FormatError(source, TABLE_ZSTD_KEY, f"the frame states {size} bytes but holds {len(raw)}")
    check_msgpack_bomb(raw, f"{source} {TABLE_ZSTD_KEY}")
    try:
        return msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise FormatError(source, TABLE_ZSTD_KEY, f"not a msgpack map ({exc.__class__.__name__}: {exc})") from None


def pack_tile_table(tiles: Sequence, group_names: Sequence[str], compact: bool = False, short: bool = False) -> dict:
    """The `tile_table` map of these tiles (in their order): format.md 6.2. compact: the bounds as f32 rounded
    outward (the map a 1.12 `tile_table_zstd` holds); short: the digests as the 16-byte `digest16` columns (1.15;
    every entry's and page's digest must be short already: Manifest.compacted). Raises ValueError where a payload
    is not laid out as the table derives it (packable), or, compact, where a bound is beyond float32's range."""
    if not packable(tiles, short):
        raise ValueError("a payload's sections are not in order at 16-byte alignment, or a digest is not of the "
                         f"table's length ({'16' if short else '32'} bytes): not a tile table of this version")
    n, g = len(tiles), len(group_names)
    layouts: dict[tuple, int] = {}
    layout = np.zeros((n, g), np.uint16)
    sha = bytearray()
    nbytes = np.zeros((n, g), np.uint32)
    sizes: list[int] = []
    child_ids: list[int] = []
    pages: list[tuple[int, object]] = []
    for i, t in enumerate(tiles):
        child_ids += t.children
        if t.page is not None:
            pages.append((i, t.page))
        for j, name in enumerate(group_names):
            e = t.groups[name]
            key = tuple((s.name, s.filter) for s in e.sections)
            layout[i, j] = layouts.setdefault(key, len(layouts))
            sha += bytes.fromhex(e.sha256)
            nbytes[i, j] = e.bytes
            sizes += [s.size for s in e.sections]
    if len(layouts) > MAX_LAYOUTS:
        raise ValueError(f"{len(layouts)} section layouts: more than {MAX_LAYOUTS}")
    box, sphere, error = bounds_columns(tiles)
    float_type = "<f8"
    if compact:
        float_type = "<f4"
        box, sphere, error = compact_columns(box, sphere, error, centre_from_box=short)
    d = {
        "count": n,
        "id": _bin([t.id for t in tiles], "<u4"),
        "level": _bin([t.level for t in tiles], "u1"),
        "children": _bin([len(t.children) for t in tiles], "<u4"),
        "splats": _bin([t.splats for t in tiles], "<u4"),
        "texture": _bin([(t.texture[0] // BLOCK, t.texture[1] // BLOCK) for t in tiles], "<u2"),
        "box": _bin(box, float_type),
        **({RADIUS_KEY: _bin(sphere[:, 3], float_type)} if short else {"sphere": _bin(sphere, float_type)}),
        "geometric_error": _bin(error, float_type),
        "child_ids": _bin(child_ids, "<u4"),
        "groups": list(group_names),
        "layouts": [[list(s) for s in key] for key in layouts],
        "layout": layout.tobytes(),
        digest_key(short): bytes(sha),
        "bytes": nbytes.tobytes(),
        "sizes": _bin(sizes, "<u4"),
    }
    if pages:
        d["page"] = {"tile": _bin([i for i, _ in pages], "<u4"),
                     digest_key(short): b"".join(bytes.fromhex(r.sha256) for _, r in pages),
                     "bytes": _bin([r.bytes for _, r in pages], "<u4")}
    return d


class Columns:
    """A tile table's columns as arrays (types and lengths checked; values are validate.py's business)."""

    __slots__ = ("count", "id", "level", "children", "splats", "texture", "box", "sphere", "geometric_error",
                 "child_ids", "groups", "layouts", "layout", "sha256", "bytes", "sizes", "page_tile",
                 "page_sha256", "page_bytes")

    def __init__(self, **kw) -> None:
        for k, v in kw.items():
            setattr(self, k, v)


def _array(d: dict, key: str, dtype: str, width: int, rows: int, source: str, field: str | None = None) -> np.ndarray:
    raw = d[key]
    field = field or key
    if type(raw) is not bytes:
        _fail(source, field, f"expected a bin of {dtype} values, got {type(raw).__name__}")
    item = np.dtype(dtype).itemsize
    need = rows * width * item
    if len(raw) != need:
        _fail(source, field, f"expected {need} bytes ({rows} x {width} {dtype}), got {len(raw)}")
    a = np.frombuffer(raw, dtype)
    return a.reshape(rows, width) if width > 1 else a


def read_columns(d, source: str, strict: bool, max_tiles: int, paged: bool, group_names: tuple[str, ...],
                 compact: bool = False, short: bool = False) -> Columns:
    """The columns of a `tile_table` map (format.md 6.2), each a bin of the length its rows make, or FormatError
    naming the column (`tile_table.sizes: expected 96 bytes (24 x 1 <u4), got 95`); `groups` the scene's.
    compact: the map of a 1.12 `tile_table_zstd` (unpack_compact_table), whose bounds are f32 (given back as f64,
    exactly). short: a 1.15 table's, whose digests are the 16-byte `digest16` columns (Columns.sha256 holds them,
    n x groups x 16)."""
    if type(d) is not dict:
        raise FormatError(source, TABLE_KEY, f"expected a map, got {type(d).__name__}")
    keys, payload_columns = (_KEYS_SHORT, _PAYLOAD_COLUMNS_SHORT) if short else (_KEYS, _PAYLOAD_COLUMNS)
    dkey = digest_key(short)
    for k in keys:
        if k not in d:
            _fail(source, k, "missing")
    if strict:
        extra = sorted(str(k) for k in d if k not in keys and not (paged and k == "page"))
        if extra:
            raise FormatError(source, TABLE_KEY, f"unknown key{'s' if len(extra) > 1 else ''} "
                              f"{', '.join(map(repr, extra))}")
    n = d["count"]
    if type(n) is not int or not 1 <= n <= max_tiles:
        _fail(source, "count", f"expected an integer 1..{max_tiles}, got {n!r}")
    groups = d["groups"]
    if type(groups) is not list or not 1 <= len(groups) <= 1 + MAX_SH_DEGREE or not all(type(x) is str
                                                                                      for x in groups):
        _fail(source, "groups", f"expected a list of 1..{1 + MAX_SH_DEGREE} group names, got {groups!r:.80}")
    if tuple(groups) != tuple(group_names):
        _fail(source, "groups", f"expected {list(group_names)} (the scene's groups, in order), got {groups}")
    layouts = d["layouts"]
    if type(layouts) is not list or not 1 <= len(layouts) <= MAX_LAYOUTS:
        _fail(source, "layouts", f"expected a list of 1..{MAX_LAYOUTS} section layouts, got {type(layouts).__name__}")
    for i, lay in enumerate(layouts):
        if type(lay) is not list or not all(type(s) is list and len(s) == 2 and type(s[0]) is str and type(s[1])
                                            is str for s in lay):
            _fail(source, f"layouts[{i}]", f"expected a list of [section name, filter] pairs, got {lay!r:.80}")
    tile_columns = _TILE_COLUMNS_SHORT if short else _TILE_COLUMNS
    cols = {k: _array(d, k, "<f4" if compact and k in (*COMPACT_FLOAT_COLUMNS, RADIUS_KEY) else dt, w, n, source)
            for k, (dt, w) in tile_columns.items()}
    if short:  # 1.15: each sphere's centre is its box's middle (f64), its radius the column's
        box = cols["box"].astype(np.float64)
        cols["sphere"] = np.concatenate([box_centres(box), cols.pop(RADIUS_KEY).astype(np.float64)[:, None]], axis=1)
    if compact:
        cols.update({k: cols[k].astype(np.float64) for k in COMPACT_FLOAT_COLUMNS})
    g = len(groups)
    cols.update({k: _array(d, k, dt, w * g, n, source) for k, (dt, w) in payload_columns.items()})
    width = SHORT_DIGEST_BYTES if short else 32
    cols["sha256"] = cols.pop(dkey).reshape(n, g, width)
    cols["layout"] = cols["layout"].reshape(n, g)
    cols["bytes"] = cols["bytes"].reshape(n, g)
    n_children = int(cols["children"].sum(dtype=np.int64))
    cols["child_ids"] = _array(d, "child_ids", "<u4", 1, n_children, source)
    if int(cols["layout"].max()) >= len(layouts):
        i = int(np.argmax(cols["layout"].max(axis=1) >= len(layouts)))
        _fail(source, f"layout[{i}]", f"expected section layouts 0..{len(layouts) - 1}, got "
              f"{cols['layout'][i].tolist()}")
    per_layout = np.array([len(lay) for lay in layouts], np.int64)
    n_sections = int(per_layout[cols["layout"]].sum())
    cols["sizes"] = _array(d, "sizes", "<u4", 1, n_sections, source)
    page_tile = page_sha = page_bytes = None
    if paged and "page" in d:
        p = d["page"]
        page_keys = _PAGE_KEYS_SHORT if short else _PAGE_KEYS
        if type(p) is not dict or set(p) != set(page_keys):
            _fail(source, "page", f"expected a map of {', '.join(page_keys)}, got {p!r:.80}")
        pt = p["tile"]
        count = len(pt) // 4 if type(pt) is bytes else 0
        page_tile = _array(p, "tile", "<u4", 1, count, source, "page.tile")
        page_sha = _array(p, dkey, "u1", width, count, source, f"page.{dkey}")
        page_bytes = _array(p, "bytes", "<u4", 1, count, source, "page.bytes")
        if count and (int(page_tile.max()) >= n or np.any(np.diff(page_tile.astype(np.int64)) <= 0)):
            _fail(source, "page.tile", f"expected increasing tile positions below {n}")
    return Columns(count=n, groups=tuple(groups), layouts=layouts, page_tile=page_tile, page_sha256=page_sha,
                   page_bytes=page_bytes, **cols)
