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
from .versions import VERSION_1_8, VERSION_1_12, VERSION_1_15, VERSION_1_16
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
# Version 1.16 (format.md 6.2, "Boxes relative to the parent's"): a compact table holds the box of each tile whose
# parent is a row of the same table as u8 steps of the parent's decoded box (`box8`), the others' as 1.15's f32 box
# (`anchor_box`), and every radius as u8 steps of its box's half diagonal (`radius8`; `radius_far` f32 for the few
# beyond 254/128 of it): 1.0-1.3 KB of box and 0.4-0.5 KB of radius were a fifth of a 1.15 table (issue 31, box16).
# A 1.15 reader finds `box` missing and rejects the table.
ANCHOR_BOX_KEY, BOX8_KEY, RADIUS8_KEY, RADIUS_FAR_KEY = "anchor_box", "box8", "radius8", "radius_far"
RELATIVE_KEYS = (ANCHOR_BOX_KEY, BOX8_KEY, RADIUS8_KEY, RADIUS_FAR_KEY)
_TILE_COLUMNS_RELATIVE = {k: v for k, v in _TILE_COLUMNS_SHORT.items() if k not in ("box", RADIUS_KEY)}
_KEYS_RELATIVE = ("count", *_TILE_COLUMNS_RELATIVE, *RELATIVE_KEYS, "child_ids", "groups", "layouts",
                  *_PAYLOAD_COLUMNS_SHORT, "sizes")
BOX_STEPS = 255  # a box8 step: 1/255 of the parent's decoded extent on that axis
RADIUS_STEPS = 128  # a radius8 step: 1/128 of the half diagonal; 255 says "in radius_far"
RADIUS_FAR = 255


def short_digests(version: tuple[int, int]) -> bool:
    """Whether a compact table (`tile_table_zstd`) of this version names its files by short digests (16 bytes of
    SHA-256: version 1.15). A 1.8 `tile_table` keeps the whole SHA-256 in any version."""
    return tuple(version) >= VERSION_1_15


def relative_boxes(version: tuple[int, int]) -> bool:
    """Whether a compact table of this version holds its boxes relative to their parents' and its radii as steps of
    the half diagonal (`anchor_box`, `box8`, `radius8`, `radius_far`: version 1.16, format.md 6.2)."""
    return tuple(version) >= VERSION_1_16


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
        return {TABLE_ZSTD_KEY: pack_compact_table(tiles, group_names, short_digests(version),
                                                   relative_boxes(version))}
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


def table_parents(ids: np.ndarray, children: np.ndarray, child_ids: np.ndarray) -> np.ndarray:
    """Each row's parent row in the same table (int64[T], -1 where its parent is not a row of it: the root of a root
    manifest, a page's top tiles). Children named by child_ids that are not rows (a tile with `page`) are skipped.
    Raises ValueError naming the row listed twice where one row is the child of two rows."""
    ids = np.asarray(ids, np.int64)
    n = len(ids)
    parent = np.full(n, -1, np.int64)
    child_ids = np.asarray(child_ids, np.int64)
    if not len(child_ids):
        return parent
    owner = np.repeat(np.arange(n), np.asarray(children, np.int64))
    order = np.argsort(ids, kind="stable")
    pos = np.minimum(np.searchsorted(ids[order], child_ids), n - 1)
    found = ids[order[pos]] == child_ids
    rows = order[pos[found]]
    twice = np.flatnonzero(np.bincount(rows, minlength=n) > 1)
    if len(twice):
        raise ValueError(int(twice[0]))
    parent[rows] = owner[found]
    return parent


def _steps(d: np.ndarray, q: np.ndarray) -> np.ndarray:
    """d * (q / 255) in f64 (format.md 6.2, 1.16: the order every reader computes a box8 step in)."""
    return d * (q.astype(np.float64) / BOX_STEPS)


def decode_child_boxes(pbox: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Child boxes (N x 6, f64) from their parents' decoded boxes (N x 6) and box8 steps (N x 6: three from each
    min up, three from each max down): min = pmin + (pmax - pmin) * (q / 255),
    max = pmax - (pmax - pmin) * (q' / 255)."""
    d = pbox[:, 3:] - pbox[:, :3]
    return np.concatenate([pbox[:, :3] + _steps(d, q[:, :3]), pbox[:, 3:] - _steps(d, q[:, 3:])], axis=1)


def half_diagonals(box: np.ndarray) -> np.ndarray:
    """0.5 * sqrt(dx*dx + dy*dy + dz*dz) of each box (f64, in that order; sqrt correctly rounded)."""
    e = box[:, 3:] - box[:, :3]
    return 0.5 * np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1] + e[:, 2] * e[:, 2])


def decode_radii(h: np.ndarray, q: np.ndarray, far: np.ndarray) -> np.ndarray:
    """Radii from half diagonals and radius8 steps: h * (q / 128), or (q = 255) the next radius_far value."""
    r = h * (q.astype(np.float64) / RADIUS_STEPS)
    r[q == RADIUS_FAR] = far.astype(np.float64)
    return r


def _levels_down(level: np.ndarray, parent: np.ndarray):
    """The child rows (parent >= 0) level by level, the shallowest first."""
    child = parent >= 0
    # bincount, not np.unique: numpy's first 1-D unique in a process imports numpy.ma (15 ms here, about 100 ms in a
    # fresh process on the GPU machine), which put a 1.16 manifest's first parse on the first frame's path
    for lev in np.flatnonzero(np.bincount(level[child])):
        yield np.flatnonzero(child & (level == lev))


def decode_relative(anchor_box: np.ndarray, box8: np.ndarray, parent: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Every row's decoded box (T x 6, f64) from a 1.16 table's `anchor_box` (the rows without a parent row, in row
    order) and `box8` (the others, in row order), parents decoded before children (by level: lod.md 1, a child is
    one level below its parent)."""
    n = len(parent)
    box = np.empty((n, 6), np.float64)
    anchors = parent < 0
    box[anchors] = anchor_box.astype(np.float64)
    q = np.empty((n, 6), np.uint8)
    q[~anchors] = box8
    for rows in _levels_down(level, parent):
        box[rows] = decode_child_boxes(box[parent[rows]], q[rows])
    return box


def _largest(ok, q0: np.ndarray, top: int = BOX_STEPS) -> np.ndarray:
    """The largest q in 0..top with ok(q) (ok monotone: true up to some q), starting from the estimate q0; 0 where
    none is."""
    q = np.clip(q0, 0, top).astype(np.int64)
    for _ in range(2 * top + 2):  # steps up where the next one still holds, down where this one does not
        up = (q < top) & ok(np.minimum(q + 1, top))
        down = (q > 0) & ~ok(q)
        if not (up.any() or down.any()):
            return q
        q = q + up - down
    raise AssertionError("a step search did not settle")


def encode_relative(box: np.ndarray, sphere: np.ndarray, parent: np.ndarray, level: np.ndarray):
    """A 1.16 table's bounds (format.md 6.2, "Boxes relative to the parent's"): tree boxes (T x 6) and spheres
    (T x 4), f64, with each row's parent row (-1: an anchor) and level. Each parent's box is first grown to hold its
    children's (bottom-up; a tree built by lod.md 2 needs none), the anchors' boxes rounded outward to f32, every
    other box coded as the largest steps of its parent's decoded box that still hold it (rounded outward), each
    sphere centred on the decoded box's middle with the smallest radius8 step that holds the tree's sphere (its
    radius grown by the centre's move), or radius_far (f32 rounded up) beyond 254/128 of the half diagonal.
    Returns (anchor_box f32[A x 6], box8 u8[(T-A) x 6], radius8 u8[T], radius_far f32[F], decoded box T x 6,
    decoded sphere T x 4, rows whose box was grown). Values already so come back unchanged."""
    box = np.array(box, np.float64)
    parent = np.asarray(parent, np.int64)
    level = np.asarray(level, np.int64)
    before = box.copy()
    for rows in reversed(list(_levels_down(level, parent))):
        np.minimum.at(box[:, :3], parent[rows], box[rows, :3])
        np.maximum.at(box[:, 3:], parent[rows], box[rows, 3:])
    grown = int((box != before).any(axis=1).sum())
    anchors = parent < 0
    dec = np.empty_like(box)
    anchor_box = np.concatenate([down_f32(box[anchors, :3]), up_f32(box[anchors, 3:])], axis=1).astype(np.float32)
    if not np.isfinite(anchor_box).all():
        raise ValueError("a tile's bounds are beyond float32's range: not a compact tile table")
    dec[anchors] = anchor_box.astype(np.float64)
    q = np.zeros((len(box), 6), np.int64)
    for rows in _levels_down(level, parent):
        p = dec[parent[rows]]
        lo, hi, d = p[:, :3], p[:, 3:], p[:, 3:] - p[:, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            est_min = np.where(d > 0, np.floor((box[rows, :3] - lo) / d * BOX_STEPS), 0)
            est_max = np.where(d > 0, np.floor((hi - box[rows, 3:]) / d * BOX_STEPS), 0)
        cmin, cmax = box[rows, :3], box[rows, 3:]
        qmin = _largest(lambda k, lo=lo, d=d, c=cmin: lo + _steps(d, k) <= c, est_min)
        qmax = _largest(lambda k, hi=hi, d=d, c=cmax: hi - _steps(d, k) >= c, est_max)
        q[rows] = np.concatenate([qmin, qmax], axis=1)
        dec[rows] = decode_child_boxes(p, q[rows])
        if (dec[rows, :3] > box[rows, :3]).any() or (dec[rows, 3:] < box[rows, 3:]).any():
            raise ValueError("a child's box is not inside its parent's decoded box")  # growth makes it so
    mid = box_centres(dec)
    moved = np.sqrt(((mid - sphere[:, :3]) ** 2).sum(axis=1))
    need = np.where(moved == 0.0, sphere[:, 3], np.nextafter(sphere[:, 3] + moved, np.inf))
    h = half_diagonals(dec)
    with np.errstate(divide="ignore", invalid="ignore"):
        est = np.where(h > 0, np.ceil(need / h * RADIUS_STEPS), np.where(need > 0, RADIUS_FAR, 0))
    qr = RADIUS_FAR - _largest(lambda k: h * ((RADIUS_FAR - k).astype(np.float64) / RADIUS_STEPS) >= need,
                               RADIUS_FAR - np.clip(est, 0, RADIUS_FAR), RADIUS_FAR)
    far = qr >= RADIUS_FAR
    qr = np.where(far, RADIUS_FAR, qr).astype(np.uint8)
    radius_far = up_f32(need[far]).astype(np.float32)
    radius = decode_radii(h, qr, radius_far)
    if not (np.isfinite(radius).all() and (radius >= need).all()):
        raise ValueError("a tile's sphere is beyond float32's range: not a compact tile table")
    dec_sphere = np.concatenate([mid, radius[:, None]], axis=1)
    return (anchor_box, q[~anchors].astype(np.uint8), qr, radius_far, dec, dec_sphere, grown)


def relative_columns(tiles: Sequence, page_levels: int = 0) -> tuple[np.ndarray, ...]:
    """A whole tree's bounds as a 1.16 writer holds them (encode_relative over every tile, each tile's parent the
    tile that lists it): decoded box (T x 6), decoded sphere (T x 4), geometric error rounded up to f32 (T), and
    the rows whose box was grown to hold its children's. page_levels k > 0: the tiles of levels 0, k, 2k, ... are
    anchors, as the root manifest's and pages' tables of a scene paged k levels to a file hold them (format.md
    6.1). Raises ValueError where a bound is beyond float32's range."""
    box, sphere, error = bounds_columns(tiles)
    ids = np.array([t.id for t in tiles], np.int64)
    level = np.array([t.level for t in tiles], np.int64)
    parent = table_parents(ids, [len(t.children) for t in tiles], [c for t in tiles for c in t.children])
    if page_levels:
        parent[level % page_levels == 0] = -1
    *_, dec_box, dec_sphere, grown = encode_relative(box, sphere, parent, level)
    error = up_f32(error)
    if not np.isfinite(error).all():
        raise ValueError("a tile's bounds are beyond float32's range: not a compact tile table")
    return dec_box, dec_sphere, error, grown


def pack_compact_table(tiles: Sequence, group_names: Sequence[str], short: bool = False,
                       relative: bool = False) -> bytes:
    """The `tile_table_zstd` bin of these tiles (format.md 6.2, version 1.12): the tile table with f32 bounds
    (rounded outward: compact_columns), msgpack-packed and zstd-compressed; short: its files named by 16-byte
    digests (1.15); relative (with short): boxes relative to their parents' and radii as steps (1.16,
    encode_relative). Raises ValueError where the table cannot be written (packable) or a bound is beyond
    float32's range."""
    d = pack_tile_table(tiles, group_names, compact=True, short=short, relative=relative and short)
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


def pack_tile_table(tiles: Sequence, group_names: Sequence[str], compact: bool = False, short: bool = False,
                    relative: bool = False) -> dict:
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
    bounds = None
    if compact and relative:  # 1.16: the writer's side of decode_relative
        ids = np.array([t.id for t in tiles], np.int64)
        parent = table_parents(ids, [len(t.children) for t in tiles], child_ids)
        anchor_box, box8, radius8, radius_far, *_ = encode_relative(
            box, sphere, parent, np.array([t.level for t in tiles], np.int64))
        bounds = {ANCHOR_BOX_KEY: _bin(anchor_box, "<f4"), BOX8_KEY: box8.tobytes(), RADIUS8_KEY: radius8.tobytes(),
                  RADIUS_FAR_KEY: _bin(radius_far, "<f4")}
        error = up_f32(error)
        if not np.isfinite(error).all():
            raise ValueError("a tile's bounds are beyond float32's range: not a compact tile table")
        float_type = "<f4"
    elif compact:
        float_type = "<f4"
        box, sphere, error = compact_columns(box, sphere, error, centre_from_box=short)
    if bounds is None:
        bounds = {"box": _bin(box, float_type),
                  **({RADIUS_KEY: _bin(sphere[:, 3], float_type)} if short else {"sphere": _bin(sphere, float_type)})}
    d = {
        "count": n,
        "id": _bin([t.id for t in tiles], "<u4"),
        "level": _bin([t.level for t in tiles], "u1"),
        "children": _bin([len(t.children) for t in tiles], "<u4"),
        "splats": _bin([t.splats for t in tiles], "<u4"),
        "texture": _bin([(t.texture[0] // BLOCK, t.texture[1] // BLOCK) for t in tiles], "<u2"),
        **bounds,
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


def _relative_bounds(d: dict, cols: dict, n: int, source: str) -> tuple[np.ndarray, np.ndarray]:
    """A 1.16 table's boxes and spheres (format.md 6.2, "Boxes relative to the parent's"), f64, from its
    `anchor_box`, `box8`, `radius8` and `radius_far` columns and its tree columns, or FormatError naming the
    column and row at fault."""
    level = cols["level"].astype(np.int64)
    try:
        parent = table_parents(cols["id"], cols["children"], cols["child_ids"])
    except ValueError as exc:
        _fail(source, "child_ids", f"expected each row the child of one row at most, got row {exc} twice")
    i = _first_row((parent >= 0) & (level != level[np.maximum(parent, 0)] + 1))
    if i is not None:
        _fail(source, f"level[{i}]", f"expected its parent's (row {parent[i]}) level + 1, "
              f"{level[parent[i]] + 1}, got {level[i]}")
    anchors = parent < 0
    a = int(anchors.sum())
    anchor_box = _array(d, ANCHOR_BOX_KEY, "<f4", 6, a, source).astype(np.float64)
    i = _first_row(~np.isfinite(anchor_box).all(axis=1) | (anchor_box[:, :3] > anchor_box[:, 3:]).any(axis=1))
    if i is not None:
        _fail(source, f"{ANCHOR_BOX_KEY}[{i}]", f"expected finite min <= max, got {anchor_box[i].tolist()}")
    box8 = _array(d, BOX8_KEY, "u1", 6, n - a, source)
    radius8 = _array(d, RADIUS8_KEY, "u1", 1, n, source)
    far = _array(d, RADIUS_FAR_KEY, "<f4", 1, int((radius8 == RADIUS_FAR).sum()), source)
    i = _first_row(~(np.isfinite(far) & (far >= 0)))
    if i is not None:
        _fail(source, f"{RADIUS_FAR_KEY}[{i}]", f"expected a finite radius >= 0, got {float(far[i])}")
    box = decode_relative(anchor_box, box8, parent, level)
    child = box[~anchors]
    i = _first_row((child[:, :3] > child[:, 3:]).any(axis=1))
    if i is not None:
        _fail(source, f"{BOX8_KEY}[{i}]", f"steps {box8[i].tolist()} make min {tuple(child[i, :3])} exceed max "
              f"{tuple(child[i, 3:])}")
    radius = decode_radii(half_diagonals(box), radius8, far)
    return box, np.concatenate([box_centres(box), radius[:, None]], axis=1)


def _first_row(mask: np.ndarray) -> int | None:
    return int(np.argmax(mask)) if mask.any() else None


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
                 compact: bool = False, short: bool = False, relative: bool = False) -> Columns:
    """The columns of a `tile_table` map (format.md 6.2), each a bin of the length its rows make, or FormatError
    naming the column (`tile_table.sizes: expected 96 bytes (24 x 1 <u4), got 95`); `groups` the scene's.
    compact: the map of a 1.12 `tile_table_zstd` (unpack_compact_table), whose bounds are f32 (given back as f64,
    exactly). short: a 1.15 table's, whose digests are the 16-byte `digest16` columns (Columns.sha256 holds them,
    n x groups x 16). relative: a 1.16 table's (with compact and short), whose boxes and radii are
    `anchor_box`, `box8`, `radius8` and `radius_far` (decoded here: _relative_bounds)."""
    relative = relative and compact and short
    if type(d) is not dict:
        raise FormatError(source, TABLE_KEY, f"expected a map, got {type(d).__name__}")
    keys, payload_columns = (_KEYS_SHORT, _PAYLOAD_COLUMNS_SHORT) if short else (_KEYS, _PAYLOAD_COLUMNS)
    if relative:
        keys = _KEYS_RELATIVE
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
    tile_columns = _TILE_COLUMNS_RELATIVE if relative else _TILE_COLUMNS_SHORT if short else _TILE_COLUMNS
    cols = {k: _array(d, k, "<f4" if compact and k in (*COMPACT_FLOAT_COLUMNS, RADIUS_KEY) else dt, w, n, source)
            for k, (dt, w) in tile_columns.items()}
    if short and not relative:  # 1.15: each sphere's centre is its box's middle (f64), its radius the column's
        box = cols["box"].astype(np.float64)
        cols["sphere"] = np.concatenate([box_centres(box), cols.pop(RADIUS_KEY).astype(np.float64)[:, None]], axis=1)
    if compact:
        cols.update({k: cols[k].astype(np.float64) for k in COMPACT_FLOAT_COLUMNS if k in cols})
    g = len(groups)
    cols.update({k: _array(d, k, dt, w * g, n, source) for k, (dt, w) in payload_columns.items()})
    width = SHORT_DIGEST_BYTES if short else 32
    cols["sha256"] = cols.pop(dkey).reshape(n, g, width)
    cols["layout"] = cols["layout"].reshape(n, g)
    cols["bytes"] = cols["bytes"].reshape(n, g)
    n_children = int(cols["children"].sum(dtype=np.int64))
    cols["child_ids"] = _array(d, "child_ids", "<u4", 1, n_children, source)
    if relative:
        cols["box"], cols["sphere"] = _relative_bounds(d, cols, n, source)
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
