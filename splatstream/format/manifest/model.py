"""The manifest's records (format.md 6): frozen dataclasses a validated manifest is made of, and their derived views.

Records are built by `validate.py` (from a map that passed every check) or by the encoder (from what it wrote);
code that holds one trusts it. `Manifest.to_dict()` gives back the spec's map (`wire.py` packs it).
"""
from __future__ import annotations

import functools
import operator
import weakref
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from itertools import chain, islice

import msgpack
import numpy as np

from ..names import payload_name, short_digest
from ..planes import MAX_SH_DEGREE, band_of, groups_for_degree
from ..texformats import FORMATS, blob_size
from .table import bounds_columns, compact_columns, relative_columns, tiles_body
from .versions import FORMAT_NAME, VERSION_1_9, VERSION_1_12, VERSION_1_15, VERSION_1_16
from .wire import pack_manifest

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
        return texels_size(self.format, self.width, self.height, self.layers) if self.kind == "texels" \
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
class PageRef:
    """A manifest page (format.md 6.1, version 1.5): a content-addressed file holding a subtree's next levels."""

    file: str
    sha256: str
    bytes: int

    def to_dict(self) -> dict:
        return {"file": self.file, "sha256": self.sha256, "bytes": self.bytes}


@dataclass(frozen=True)
class PagedInfo:
    """What a paged scene's root manifest says of the whole tree (format.md 6.1)."""

    tiles: int
    levels: int
    page_levels: int
    pages: int
    page_bytes: int

    def to_dict(self) -> dict:
        return {"tiles": self.tiles, "levels": self.levels, "page_levels": self.page_levels, "pages": self.pages,
                "page_bytes": self.page_bytes}


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
    page: PageRef | None = None  # the page holding this tile's children (a paged scene, format.md 6.1)

    @property
    def is_leaf(self) -> bool:
        return not self.children

    def to_dict(self) -> dict:
        d = {"id": self.id, "level": self.level, "children": list(self.children), "splats": self.splats,
             "chunks": self.chunks, "texture": list(self.texture), "box": self.box.to_dict(),
             "sphere": {"center": list(self.sphere_center), "radius": self.sphere_radius},
             "geometric_error": self.geometric_error,
             "groups": {name: p.to_dict() for name, p in self.groups.items()}}
        if self.page is not None:
            d["page"] = self.page.to_dict()
        return d


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
class LevelRefinement:
    """One merged level of a refined tree (version 1.11, format.md 6, lod.md 6): which refinement it kept (`kept`:
    a variant name such as `B` or `C`, or `none`: the level as built) and the validation PSNR in dB of each
    candidate (`none`, the level as built, and every variant tried), the measure it was kept by."""
    level: int
    kept: str
    validation_psnr: tuple[tuple[str, float], ...] = ()

    def to_dict(self) -> dict:
        return {"level": self.level, "kept": self.kept,
                "validation_psnr": {k: float(v) for k, v in self.validation_psnr}}


@dataclass(frozen=True)
class LodRefinement:
    """How the merged levels were refined after the tree was built (version 1.11, format.md 6, lod.md 6;
    informative): the method (`render-fit`), the fields each variant optimised, the image size and iterations, the
    training and validation camera sets (count and seed of the rule lod.md 6 names) and, per merged level, what was
    kept. Readers draw a scene alike with or without it."""
    method: str
    variants: tuple[tuple[str, tuple[str, ...]], ...]
    size_px: int
    iterations: int
    training_cameras: int
    training_seed: int
    validation_cameras: int
    validation_seed: int
    levels: tuple[LevelRefinement, ...]

    def to_dict(self) -> dict:
        return {"method": self.method, "variants": {k: list(v) for k, v in self.variants},
                "size_px": self.size_px, "iterations": self.iterations,
                "cameras": {"training": self.training_cameras, "training_seed": self.training_seed,
                            "validation": self.validation_cameras, "validation_seed": self.validation_seed},
                "levels": [lv.to_dict() for lv in self.levels]}


@dataclass(frozen=True)
class LodInfo:
    enabled: bool
    max_leaf_splats: int
    reduction: float
    refine: str = "replace"
    # How the encoder built the levels (version 1.9, format.md 6 and lod.md 6; informative): the merge that grouped
    # each level's splats (`grid`, `cost`, `auto`), and the screen-space errors in px at which step 5 matched
    # opacity and colour, (first merged level, levels above it): two numbers, the 1.9 key `viewing_scale_px`; or,
    # from 1.10, one per level from the first merged one, the last on every level above (`viewing_scale_levels_px`,
    # written where there are more than two). None: not recorded (before 1.9, or a tree the encoder did not build).
    merge: str | None = None
    viewing_scale_px: tuple[float, ...] | None = None
    # The optional refinement of the merged levels against renders of the full detail (version 1.11; `encode
    # --lod-refine`). None: not refined (or not recorded).
    refinement: LodRefinement | None = None

    @property
    def build_recorded(self) -> bool:
        return self.merge is not None or self.viewing_scale_px is not None

    def to_dict(self) -> dict:
        d = {"enabled": self.enabled, "max_leaf_splats": self.max_leaf_splats, "reduction": self.reduction,
             "refine": self.refine}
        if self.merge is not None:
            d["merge"] = self.merge
        if self.viewing_scale_px is not None:
            key = "viewing_scale_px" if len(self.viewing_scale_px) == 2 else "viewing_scale_levels_px"
            d[key] = [float(v) for v in self.viewing_scale_px]
        if self.refinement is not None:
            d["refinement"] = self.refinement.to_dict()
        return d

    @property
    def scales_need_1_10(self) -> bool:
        """The scales are more than two numbers: only `viewing_scale_levels_px` (1.10) says them."""
        return self.viewing_scale_px is not None and len(self.viewing_scale_px) > 2


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
        return _box_corners(self.box_max, self.box_min)

    @functools.cached_property
    def has_parent(self) -> np.ndarray:
        """(T,) bool: every tile but the root."""
        return self.parent >= 0

    @functools.cached_property
    def parent_of_child(self) -> np.ndarray:
        """The parent of every tile that has one (in tile order)."""
        return self.parent[self.has_parent]

    @functools.cached_property
    def child_count(self) -> np.ndarray:
        """(T,) int64: children of each tile (in these arrays)."""
        return np.bincount(self.parent_of_child, minlength=len(self.parent))

    @functools.cached_property
    def has_children(self) -> np.ndarray:
        """(T,) bool."""
        return self.child_count > 0

    @functools.cached_property
    def splats_list(self) -> list[int]:
        return self.splats.tolist()

    @functools.cached_property
    def splats_f64(self) -> np.ndarray:
        return _splats_f64(self.splats)


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
    # A paged scene's root manifest (format.md 6.1): `tiles` holds the top levels only. A manifest whose pages have
    # all been read (paging.resolve_pages) keeps it, with every tile in `tiles`.
    paged: PagedInfo | None = None
    # Scene palettes (format.md 4.3.2, version 1.7): per pal8x4 plane, its palettes as the manifest's bin holds them
    # (P x 256 little-endian f32); payloads without their own palette section index these.
    palettes: dict[str, bytes] | None = None

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

    @functools.cached_property
    def scene_palettes(self) -> dict[str, np.ndarray] | None:
        """The scene's palettes per plane as (P, 256) float32 arrays (read-only), or None (format.md 4.3.2): what
        a reader hands the payload decoder (format.decode.decode_payload's `palettes`)."""
        if not self.palettes:
            return None
        out = {}
        for name, raw in self.palettes.items():
            a = np.frombuffer(raw, "<f4").reshape(-1, 256)
            out[name] = a
        return out

    @property
    def uses_codebook(self) -> bool:
        return self.sh_codebook is not None

    @property
    def lod_tree_kept(self) -> bool:
        """Whether the LOD tree is one splatstream's encoder kept from its input (a streamed SOG's or a .rad's own
        LOD; format.md 6, "The tree's build record"): from 1.9 splatstream records how it built every tree it builds,
        so one of its scenes from 1.9 on with a tree and no record holds a tree it did not build. Before 1.9 the
        absence says nothing (False)."""
        return (self.lod.enabled and not self.lod.build_recorded and self.version >= VERSION_1_9
                and self.generator.startswith("splatstream "))

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
                file, size = entry_fields(t.groups, name, ("file", "bytes"))
                sizes[file] = size
        if self.sh_codebook is not None:
            for p in self.sh_codebook.groups.values():
                sizes[p.file] = p.bytes
        return sum(sizes.values())

    @functools.cached_property
    def arrays(self) -> TileArrays:
        return tile_arrays(self.tiles, self.index_of)

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
        if self.palettes:
            d["palettes"] = {name: bytes(raw) for name, raw in self.palettes.items()}
        d.update({
            "lod": self.lod.to_dict(), "root": self.root, **self.tiles_dict(),
            "gpu_bytes": self.gpu_bytes, "gpu_bytes_per_splat": self.gpu_bytes_per_splat,
            "leaf_bytes_on_disk": self.leaf_bytes_on_disk,
            "attributes": {a: s.to_dict() for a, s in self.attributes.items()},
            "encode_seconds": self.encode_seconds, "bytes_on_disk": self.bytes_on_disk,
        })
        if self.paged is not None:
            d["paged"] = self.paged.to_dict()
        return d

    def tiles_dict(self) -> dict:
        """The manifest's tiles as its version writes them: the compact tile table from 1.12 on, the tile table from
        1.8 on (format.md 6.2), else the array of tile maps."""
        return tiles_body(self.version, self.tiles, self.tile_groups())

    def compacted(self, short: bool = True, relative: bool = True, page_levels: int = 0) -> Manifest:
        """This manifest as 1.16 writes it (format.md 6.2, the compact tile table, short digests, boxes relative to
        the parent's): version at least 1.16, each tile's bounds as the values the table gives back (its box coded
        against its parent's decoded box, its sphere about the box's middle with the radius coded as steps of the
        half diagonal, its geometric error rounded up to f32: table.relative_columns), each tile payload named by
        the first 16 bytes of its SHA-256 (`data/<32 hex>.bin`: the encoder writes the files under that name at
        once, table.short_tile_names), so that what a reader gets back is this manifest; `bytes_on_disk` settled
        again. page_levels k > 0: the manifest will be paged k levels to a file (6.1), so the tiles of levels 0, k,
        2k, ... are the tables' anchors (their parents are in another file). relative False: as 1.15 wrote it (f32
        bounds rounded outward: table.compact_columns, each sphere about its box's middle); short False: as 1.12
        (the whole SHA-256, the spheres' own centres). An unchanged manifest where it is already compact. Tiles
        with a page (a paged manifest) cannot be shortened: compact before paging."""
        relative = relative and short
        if relative:
            box, sphere, error = (a.tolist() for a in relative_columns(self.tiles, page_levels)[:3])
        else:
            box, sphere, error = (a.tolist() for a in compact_columns(*bounds_columns(self.tiles),
                                                                       centre_from_box=short))
        tiles = tuple(replace(t, box=Box(tuple(b[:3]), tuple(b[3:])), sphere_center=tuple(s[:3]),
                              sphere_radius=s[3], geometric_error=e, **({"groups": _short_groups(t.groups)}
                                                                         if short else {}))
                      for t, b, s, e in zip(self.tiles, box, sphere, error, strict=True))
        least = VERSION_1_16 if relative else VERSION_1_15 if short else VERSION_1_12
        m = replace(self, version=max(self.version, least), tiles=tiles)
        return m.with_bytes_on_disk(m.payload_bytes())

    def with_bytes_on_disk(self, payload_bytes: int) -> Manifest:
        """This manifest with `bytes_on_disk` = payload bytes + its own packed size (which depends on the value)."""
        m = self
        for _ in range(3):  # the msgpack length of the number can change the length once; settled after two
            m = replace(m, bytes_on_disk=payload_bytes + len(pack_manifest(m)))
        return m




def _short_groups(groups: Mapping[str, PayloadEntry]) -> Mapping[str, PayloadEntry]:
    """A tile's payload entries named by short digests (format.md 6.2, 1.15); unchanged where they are already."""
    if all(len(e.sha256) != 64 for e in groups.values()):
        return groups
    out = {}
    for name, e in groups.items():
        h = short_digest(e.sha256)
        out[name] = replace(e, sha256=h, file=payload_name(h))
    return out


def tile_rows(tiles: Sequence[TileEntry]) -> dict[str, np.ndarray]:
    """The per-tile arrays of TileArrays but `parent` and `children`, over these tiles. A lazily checked tile's
    payload entries are unpacked to read their sizes: the streaming client takes a page's rows where it parses the
    page (a decode worker), so that adopting the page on the frame loop does not unpack them (grown_arrays' `rows`)."""
    n = len(tiles)
    table = _one_table(tiles)
    if table is not None:  # a tile table's tiles (1.8): their sizes as columns, no entry read
        base_bytes, band_bytes, gpu_bytes = table.tile_sizes(np.array([t.groups.row for t in tiles], np.int64))
    else:
        base_bytes, band_bytes, gpu_bytes = _group_sizes(tiles)
    return dict(
        ids=np.array([t.id for t in tiles], np.int64),
        level=np.array([t.level for t in tiles], np.int64),
        splats=np.array([t.splats for t in tiles], np.int64),
        box_min=np.array([t.box.min for t in tiles], np.float64).reshape(n, 3),
        box_max=np.array([t.box.max for t in tiles], np.float64).reshape(n, 3),
        sphere_center=np.array([t.sphere_center for t in tiles], np.float64).reshape(n, 3),
        sphere_radius=np.array([t.sphere_radius for t in tiles], np.float64),
        geometric_error=np.array([t.geometric_error for t in tiles], np.float64),
        base_bytes=base_bytes, band_bytes=band_bytes, gpu_bytes=gpu_bytes)


def _one_table(tiles: Sequence[TileEntry]) -> Table | None:
    """The tile table every one of these tiles' payload entries come from, or None."""
    first = tiles[0].groups if tiles else None
    if not isinstance(first, TablePayloads):
        return None
    table = first.table
    return table if all(type(t.groups) is TablePayloads and t.groups.table is table for t in tiles) else None


def _group_sizes(tiles: Sequence[TileEntry]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(base bytes, SH band bytes, GPU bytes) of each tile, from its payload entries."""
    n = len(tiles)
    band_bytes = np.zeros((n, MAX_SH_DEGREE), np.int64)
    base_bytes = np.zeros(n, np.int64)
    gpu_bytes = np.zeros(n, np.int64)
    for i, t in enumerate(tiles):
        for name in t.groups:
            gpu, size = entry_fields(t.groups, name, ("gpu_bytes", "bytes"))
            gpu_bytes[i] += gpu
            band = band_of(name)
            if band:
                band_bytes[i, band - 1] = size
            else:
                base_bytes[i] = size
    return base_bytes, band_bytes, gpu_bytes


def tile_arrays(tiles: Sequence[TileEntry], idx: Mapping[int, int]) -> TileArrays:
    """The tree of `tiles` as arrays (idx: tile id -> position in `tiles`)."""
    parent = np.full(len(tiles), -1, np.int64)
    children = []
    for i, t in enumerate(tiles):
        kids = tuple(idx[c] for c in t.children)
        children.append(kids)
        for k in kids:
            parent[k] = i
    return TileArrays(parent=parent, children=tuple(children), **tile_rows(tiles))


def grown_arrays(a: TileArrays, tiles: Sequence[TileEntry], idx: Mapping[int, int],
                 changed: Iterable[int], rows: Sequence[Mapping[str, np.ndarray]] | None = None,
                 capacity: int = 0) -> TileArrays:
    """`a` (the arrays of tiles[:len(a.ids)]) grown by the tiles after them, the tiles at positions `changed`
    (held before) with their children now as in `tiles`: the same arrays as tile_arrays(tiles, idx), in time of
    the new tiles (a paged tree grown by a page, client_gl/stream/pages.py), not of every tile held. `rows`: the
    new tiles' tile_rows, in parts in their order (each page's, taken where it was parsed), else taken here.
    `capacity`: rows of new storage at least (the tree's expected size: not doubled below it).

    The numeric arrays are views of storage with spare rows (_GrowingRows), written in place when the tree grows
    from its last grown arrays (copied into twice the rows when full: amortised), so a page costs its own rows,
    not a copy of every row held (BENCHMARKS.md, "Manifest pages"). Arrays `a` stay as they were. The children's
    tuples are a list the storage keeps, grown the same way and read through a ListPrefix (`a`'s keeps the tuples
    it read), copied only where the rows are."""
    start = len(a.ids)
    new = tiles[start:]
    changed = list(changed)
    made = [tuple(map(idx.__getitem__, tiles[i].children)) for i in changed]  # their positions, once each
    made += [tuple(map(idx.__getitem__, t.children)) for t in new]
    # each child's parent in array operations (a Python loop over the children took most of an adoption)
    lengths = np.fromiter(map(len, made), np.int64, len(made))
    kid = np.fromiter(chain.from_iterable(made), np.int64, int(lengths.sum()))
    parents = np.array([*changed, *range(start, len(tiles))], np.int64)
    of = np.repeat(parents, lengths)
    new_parent = np.full(len(new), -1, np.int64)
    in_new = kid >= start
    new_parent[kid[in_new] - start] = of[in_new]
    # held tiles given a parent (a tree grown other than by pages: not in place)
    old_parent = dict(zip(kid[~in_new].tolist(), of[~in_new].tolist(), strict=True))
    parts = [tile_rows(new)] if rows is None else list(rows)
    added = sum(len(p["ids"]) for p in parts)
    if added != len(new):
        raise ValueError(f"rows of {added} tiles for {len(new)} new tiles")
    store = a.__dict__.get("_growing")
    if store is None or store.n != start or old_parent:  # not the last grown arrays of their storage: a copy
        store = _GrowingRows(a, max(_FIRST_ROWS, 2 * len(tiles), capacity))
        if old_parent:
            store.buf["parent"][list(old_parent)] = list(old_parent.values())
    with_parent, at = [], 0
    for p in parts:
        with_parent.append({**p, "parent": new_parent[at:at + len(p["ids"])]})
        at += len(p["ids"])
    store.append(with_parent)
    n = store.n
    # the children: the storage's list, edited at the changed tiles (the tuples there before kept by the views
    # that hold them) and grown, read by the new arrays up to their length (ListPrefix): not a copy of every
    # tile's tuple an adoption (the list and the tuple made and the last freed were 0.08 ms median, 0.2 p99, at
    # 21,000 tiles: BENCHMARKS.md, "Manifest pages")
    shared = store.children
    if shared is None or len(shared) != start or not (isinstance(a.children, ListPrefix)
                                                      and a.children.items is shared):
        shared, store.child_views = list(a.children), []
        store.children = shared
    for i, kids in zip(changed, made[:len(changed)], strict=True):
        replace_kept(shared, store.child_views, i, kids)
    shared += made[len(changed):]
    children = kept_prefix(shared, store.child_views, n)
    out = TileArrays(children=children, **{name: store.buf[name][:n] for name in ("parent", *_ROW_NAMES)})
    for name in _DERIVED_ROWS:  # the derived arrays that only grow, kept as views too
        out.__dict__[name] = store.buf[name][:n]
    out.__dict__["_growing"] = store
    out.__dict__["_epoch"] = store.epoch  # its rows as they are until the storage's next take_in_place
    if not old_parent:  # the tiles given children by this growth, from `a`'s length: (start, parents, counts, kids),
        # each parent's children in the tree's order (the compiled selection's children's index grows by these:
        # client_gl/stream/selection_jit.py, _ChildIndex, instead of finding them again from the parents)
        some = lengths > 0
        out.__dict__["_children_grown"] = (start, parents[some], lengths[some], kid)
    return out


def kept_prefix(items: list, views: list[weakref.ref], n: int) -> ListPrefix:
    """A ListPrefix of items[:n], registered in `views` (the dead ones dropped) so that replace_kept keeps for it
    the items it read."""
    view = ListPrefix(items, n)
    views[:] = [r for r in views if r() is not None]
    views.append(weakref.ref(view))
    return view


def replace_kept(items: list, views: list[weakref.ref], at: int, value) -> None:
    """items[at] = value, the item there before kept by the live views (ListPrefix, weakly referenced) of `items`
    that hold that position, so that each still reads what it read when made."""
    old = items[at]
    for ref in views:
        view = ref()
        if view is not None and at < view._n:
            view._older.setdefault(at, old)
    items[at] = value


def indexable(items: Sequence) -> Sequence:
    """`items` to read by position at C speed: a ListPrefix's list where none of its items was replaced since it
    was made (read below its length only: the list may have grown past it), else `items` itself. A ListPrefix's
    own __getitem__ is Python's (0.2 us a read: the numpy selection's walks read a tile's children at each step)."""
    return items.items if type(items) is ListPrefix and not items._older else items


class ListPrefix(Sequence):
    """A tuple's worth of a list that grows at its end: `items` read up to `n` where they stand, and the items
    replaced there since the view was made (replace_kept) kept apart, so the view reads as it did when made. A
    paged tree's views (client_gl/stream/pages.py: `Manifest.tiles`, and their arrays' `children` here) are
    these, not tuples: a tuple of every tile held made a page, and the last one freed, touched every tile held
    (at 21,000 tiles, 0.14 ms median of an adoption and 0.4 p99 for the tiles, 0.07 and 0.2 for the children's
    tuples: BENCHMARKS.md, "Manifest pages"). Equal to the tuple of its items, pickled as one; slices are tuples."""

    __slots__ = ("items", "_n", "_older", "__weakref__")

    def __init__(self, items: list, n: int):
        self.items, self._n = items, n
        self._older: dict[int, object] = {}  # position -> the item there when the view was made

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            start, stop, step = i.indices(self._n)
            if step == 1 and not self._older:
                return tuple(self.items[start:stop])
            return tuple(map(self.__getitem__, range(start, stop, step)))
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError("position out of range")
        older = self._older
        return older[i] if i in older else self.items[i]

    def __iter__(self) -> Iterator:
        if not self._older:
            return islice(self.items, self._n)
        return map(self.__getitem__, range(self._n))

    def __eq__(self, other) -> bool:
        if isinstance(other, ListPrefix | tuple):
            return len(self) == len(other) and all(map(operator.eq, self, other))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]  (its list changes, as a list's)

    def __reduce__(self):
        return tuple, (tuple(self),)

    def __repr__(self) -> str:
        return f"ListPrefix({self._n} items)"


class _GrowingRows:
    """The numeric arrays of a TileArrays with spare rows after its `n` rows (grown_arrays). Rows below `n` are
    never written again, so every TileArrays viewing them stays as it was; the tree grows in place only from the
    arrays whose length is `n` (the last grown: the streaming client's frame loop grows one chain of views). The
    one exception, an eviction's take_in_place, counts itself in `epoch`."""

    def __init__(self, a: TileArrays, capacity: int):
        self.n = n = len(a.ids)
        self.epoch = 0  # rows moved in place (take_in_place) this many times: rows below n changed then
        self.buf: dict[str, np.ndarray] = {}
        # the children's tuples of the arrays grown in place (grown_arrays: their ListPrefix views), made there
        self.children: list | None = None
        self.child_views: list[weakref.ref] = []
        for name in ("parent", *_ROW_NAMES, *_DERIVED_ROWS):
            arr = getattr(a, name)
            self.buf[name] = np.empty((max(capacity, n), *arr.shape[1:]), arr.dtype)
            self.buf[name][:n] = arr

    @classmethod
    def taken(cls, a: TileArrays, keep: np.ndarray, moved: np.ndarray, capacity: int) -> _GrowingRows:
        """The rows of `a` at positions `keep` (new -> old) in new storage, where `moved` lists the new positions
        whose row is not the one already there (keep[i] == i elsewhere): a copy of the first rows and the moved
        rows written over them."""
        self = cls.__new__(cls)
        self.n = k = len(keep)
        self.epoch = 0
        self.buf = {}
        self.children, self.child_views = None, []
        src = keep[moved]
        for name in ("parent", *_ROW_NAMES, *_DERIVED_ROWS):
            arr = getattr(a, name)
            buf = self.buf[name] = np.empty((max(capacity, k), *arr.shape[1:]), arr.dtype)
            buf[:k] = arr[:k]
            buf[moved] = arr[src]
        return self

    def take_in_place(self, keep: np.ndarray, moved: np.ndarray, new_of: np.ndarray,
                      move_rows: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None = None) -> None:
        """The rows at positions `keep` (new -> old, the identity but at `moved`) in this storage: the moved rows
        written into their new positions and the rows after them given up (the arrays viewing the rows held
        before see the moved rows at those positions: PagedTree.evict's last view, not read after it). The
        parents, renumbered through `new_of`, in a new array: the arrays before keep theirs, which with their
        children is what the compiled selection's children's index grows by (selection_jit._ChildIndex).
        `move_rows(buf, moved, src)`: buf[moved] = buf[src] (the client's compiled kernel, which keeps the
        interpreter lock; None: numpy's, which lets it go for each array)."""
        src = keep[moved]
        k = len(keep)
        self.children, self.child_views = None, []  # the taken arrays' children are a tuple of their own
        for name, buf in self.buf.items():
            if name == "parent":
                parent = self.buf[name] = np.empty_like(buf)
                parent[:k] = new_of[buf[keep]]
            elif move_rows is not None:
                move_rows(buf, moved, src)
            else:
                buf[moved] = buf[src]
        self.n = k
        self.epoch += 1

    def append(self, parts: list[Mapping[str, np.ndarray]]) -> None:
        """Rows after the n held (each part: tile_rows' arrays and `parent`), the storage doubled when full."""
        n, add = self.n, sum(len(p["ids"]) for p in parts)
        capacity = len(self.buf["ids"])
        if n + add > capacity:
            grown = max(2 * capacity, n + add)
            for name, arr in self.buf.items():
                bigger = np.empty((grown, *arr.shape[1:]), arr.dtype)
                bigger[:n] = arr[:n]
                self.buf[name] = bigger
        buf = self.buf
        for p in parts:
            k = len(p["ids"])
            for name in ("parent", *_ROW_NAMES):
                buf[name][n:n + k] = p[name]
            buf["box_corners"][n:n + k] = _box_corners(p["box_max"], p["box_min"])
            buf["splats_f64"][n:n + k] = _splats_f64(p["splats"])
            n += k
        self.n = n


def _box_corners(box_max: np.ndarray, box_min: np.ndarray) -> np.ndarray:
    """TileArrays.box_corners of these rows (one formula for the cached array and the rows it grows by)."""
    return np.ascontiguousarray(np.concatenate([box_max, box_min], axis=1))


def _splats_f64(splats: np.ndarray) -> np.ndarray:
    return splats.astype(np.float64)


_ROW_NAMES = ("ids", "level", "splats", "box_min", "box_max", "sphere_center", "sphere_radius", "geometric_error",
              "base_bytes", "band_bytes", "gpu_bytes")
_FIRST_ROWS = 64  # rows of a new storage at least (twice the tiles held when it is made)
_DERIVED_ROWS = ("box_corners", "splats_f64")  # TileArrays' cached arrays that grow row by row with the tree


def taken_arrays(a: TileArrays, keep: np.ndarray, in_place: bool = False,
                 move_rows: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None = None,
                 compaction: tuple[np.ndarray, np.ndarray] | None = None) -> TileArrays:
    """`a` over the tiles at positions `keep` (new position -> old; every kept tile's parent kept, children dropped
    with their parent): the arrays of the tree left when a paged tree drops pages. `keep` in any order: a paged tree
    keeps its tiles where they are and moves the last ones into the holes (client_gl/stream/pages.py), so that
    only the tuples of the tiles moved and of the parents of a tile moved or dropped change; the others are
    carried over by one copy of the tuple of tuples, and the numeric rows by a copy of the first rows (renumbering
    every tile after the first position dropped took 4.8-8.8 ms of a frame's page eviction at 15,000-19,000 tiles
    held: BENCHMARKS.md, "Manifest pages"). Like grown_arrays' arrays, they are views of storage with spare rows
    (_GrowingRows), which the next page's tiles grow in place. `in_place`: where `a` is the last grown arrays of
    their storage, the moved rows are written into that storage's holes (a new storage's first write of every row
    was 1.1-1.4 ms of page faults at 17,000 tiles, the moved rows 0.1 ms), and `a` is not to be read after it
    (its rows at the holes are others'); else new storage, `a` as it was. `move_rows`: take_in_place's.
    `compaction`: (new_of, moved) where the caller has them (PagedTree.evict: the same map, not made again): the new
    position of each old one (-1: dropped; n + 1 entries, the last -1) and the new positions whose tile was
    elsewhere, ascending."""
    n, k = len(a.ids), len(keep)
    if compaction is not None:
        new_of, moved = compaction
    else:
        new_of = np.full(n + 1, -1, np.int64)  # index -1 (the root's parent) reads -1
        new_of[keep] = np.arange(k)
        moved = np.flatnonzero(keep != np.arange(k))  # new positions whose tile was elsewhere
    children = list(a.children[:k])
    if len(moved):
        # read through indexable: a ListPrefix's own __getitem__ is Python's, 0.1-0.2 ms a pass for the tiles moved
        deque(map(children.__setitem__, moved.tolist(), _taken(indexable(a.children), keep[moved].tolist())),
              maxlen=0)
    # the tiles whose children were renumbered or dropped: the parents of the tiles not where they were
    changed = np.flatnonzero(new_of[:n] != np.arange(n))
    redo = np.zeros(n + 1, bool)  # index -1 (the root's parent) ignored
    redo[a.parent[changed]] = True
    inner = np.flatnonzero(redo[keep])
    if len(inner):
        old = _taken(children, inner.tolist())
        n_kids = np.fromiter(map(len, old), np.int64, len(inner))
        flat = new_of[np.fromiter(chain.from_iterable(old), np.int64, int(n_kids.sum()))]
        kept = flat >= 0
        counts = np.add.reduceat(kept.astype(np.int64), np.cumsum(n_kids) - n_kids)
        kids, first_kid = flat[kept], np.cumsum(counts) - counts
        for c in np.unique(counts).tolist():  # the tuples of c children made by zip over c columns (in C)
            at = np.flatnonzero(counts == c)
            made = zip(*[kids[first_kid[at] + j].tolist() for j in range(c)], strict=True) if c else [()] * len(at)
            deque(map(children.__setitem__, inner[at].tolist(), made), maxlen=0)
    # the numeric rows into new storage with spare rows (the next page grows it in place): the rows up to k
    # copied as they are and the moved ones written over them (taking every row through `keep` took 1.1-2.0 ms
    # at 17,000 tiles held, a copy a tenth of it)
    store = a.__dict__.get("_growing")
    if in_place and store is not None and store.n == n:
        store.take_in_place(keep, moved, new_of, move_rows)
    else:
        store = _GrowingRows.taken(a, keep, moved, max(_FIRST_ROWS, 2 * k))
        parent = store.buf["parent"]
        parent[:k] = new_of[parent[:k]]
    out = TileArrays(children=tuple(children), **{name: store.buf[name][:k] for name in ("parent", *_ROW_NAMES)})
    for name in _DERIVED_ROWS:  # the derived arrays that only grow, kept as views too
        out.__dict__[name] = store.buf[name][:k]
    out.__dict__["_growing"] = store
    out.__dict__["_epoch"] = store.epoch
    return out


def _taken(items: Sequence, at: list[int]) -> list:
    """[items[i] for i in at], in C (operator.itemgetter: a third of a list comprehension's time)."""
    if len(at) > 1:
        return list(operator.itemgetter(*at)(items))
    return [items[i] for i in at]


def filter_element(name: str) -> int:
    if name == "none":
        return 1
    if name.startswith("shuffle") and name[7:].isdigit() and 1 < int(name[7:]) <= 16:
        return int(name[7:])
    raise ValueError(name)


def filter_for(element: int) -> str:
    return f"shuffle{element}" if element > 1 else "none"



@functools.lru_cache(maxsize=4096)  # a scene's thousands of sections repeat a few shapes
def texels_size(fmt: str, width: int, height: int, layers: int) -> int:
    """Bytes of `layers` layers of a width x height texture in texel format `fmt`, as the GPU holds them."""
    return blob_size(FORMATS[fmt], width, height, layers)


def entry_fields(groups: Mapping[str, PayloadEntry], name: str, fields: tuple[str, ...]) -> tuple:
    """Fields of one payload entry: from the raw map where it is checked lazily and they have the right types."""
    if isinstance(groups, (LazyPayloads, TablePayloads)):
        return groups.raw_fields(name, fields)
    entry = groups[name]
    return tuple(getattr(entry, f) for f in fields)


class LazyPayloads(Mapping):
    """A tile's payload entries (group name -> PayloadEntry), each checked by `check(raw_groups, name)` when first
    read (the validator's own function for one entry, so a bad one raises the FormatError an eager parse raises).

    The entries as stored are kept packed (msgpack bytes, unpacked when read): as parsed maps they were about 27
    objects and 7 KB a tile, which a paged scene's client holds for tens of thousands of tiles and the garbage
    collector walked in every full pass (BENCHMARKS.md, "Manifest pages"); packed, one bytes object of about 1 KB."""

    def __init__(self, raw: dict, names: tuple[str, ...], check: Callable[[dict, str], PayloadEntry]):
        self._packed: bytes = msgpack.packb(raw, use_bin_type=True)
        self._names, self._check = names, check
        self._checked: dict[str, PayloadEntry] = {}

    def _raw(self) -> dict:
        global _last_unpacked
        last = _last_unpacked
        if last[0] is self._packed:  # the fields of one tile's groups are read one group after another
            return last[1]
        raw = msgpack.unpackb(self._packed, raw=False, strict_map_key=False)
        _last_unpacked = (self._packed, raw)
        return raw

    def __getitem__(self, name: str) -> PayloadEntry:
        entry = self._checked.get(name)
        if entry is None:
            if name not in self._names:
                raise KeyError(name)
            entry = self._checked[name] = self._check(self._raw(), name)
        return entry

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def raw_fields(self, name: str, fields: tuple[str, ...]) -> tuple:
        """Fields of an entry as stored, where they are a non-negative integer or a payload file name; otherwise the
        entry is checked (and a bad one raises)."""
        raw = self._raw().get(name)
        if name in self._names and type(raw) is dict:
            values = tuple(raw.get(f) for f in fields)
            if all((type(v) is int and v >= 0) if f != "file" else type(v) is str
                   for f, v in zip(fields, values, strict=True)):
                return values
        entry = self[name]
        return tuple(getattr(entry, f) for f in fields)


# The last LazyPayloads unpacked (its packed bytes, the maps): reading several fields of one tile's groups unpacks
# them once. Replaced as a whole (one assignment), so threads reading different tiles at once stay correct.
_last_unpacked: tuple[bytes | None, dict] = (None, {})


class Table:
    """A validated tile table held by its tiles' payload entries: the sizes, the derived offsets and raw bytes, and
    per (group, layout, texture, chunks) the sections' fixed fields (their `Section`s at offset 0, from
    validate.py), so that an entry is built only when read."""

    __slots__ = ("groups", "sha", "bytes", "raw_bytes", "gpu_bytes", "sizes", "offsets", "first", "templates",
                 "kind", "_hex")

    def __init__(self, groups: tuple[str, ...], sha: np.ndarray, nbytes: np.ndarray, raw_bytes: np.ndarray,
                 gpu_bytes: np.ndarray, sizes: np.ndarray, offsets: np.ndarray, first: np.ndarray,
                 templates: list[tuple[Section, ...]], kind: np.ndarray):
        self.groups, self.sha, self.bytes, self.raw_bytes, self.gpu_bytes = groups, sha, nbytes, raw_bytes, gpu_bytes
        self.sizes, self.offsets, self.first, self.templates, self.kind = sizes, offsets, first, templates, kind
        self._hex: dict[int, str] = {}

    def sha_hex(self, p: int) -> str:
        h = self._hex.get(p)
        if h is None:
            h = self._hex[p] = bytes(self.sha[p]).hex()
        return h

    def entry(self, p: int) -> PayloadEntry:
        """Payload p (tile row x groups + group) as its record."""
        secs = []
        at = int(self.first[p])
        new = object.__new__
        for k, tpl in enumerate(self.templates[int(self.kind[p])]):
            s = new(Section)
            s.__dict__.update(tpl.__dict__)
            s.__dict__["offset"] = int(self.offsets[at + k])
            s.__dict__["size"] = int(self.sizes[at + k])
            secs.append(s)
        sha = self.sha_hex(p)
        return PayloadEntry(payload_name(sha), sha, int(self.bytes[p]), int(self.raw_bytes[p]),
                            int(self.gpu_bytes[p]), tuple(secs))

    def tile_sizes(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(base bytes, SH band bytes (n, 3), GPU bytes) of these tile rows: tile_rows' payload columns."""
        g = len(self.groups)
        nb = self.bytes.reshape(-1, g)[rows].astype(np.int64)
        gpu = self.gpu_bytes.reshape(-1, g)[rows].sum(axis=1)
        band = np.zeros((len(rows), MAX_SH_DEGREE), np.int64)
        base = np.zeros(len(rows), np.int64)
        for j, name in enumerate(self.groups):
            b = band_of(name)
            if b:
                band[:, b - 1] = nb[:, j]
            else:
                base = nb[:, j]
        return base, band, gpu


class TablePayloads(Mapping):
    """A tile's payload entries (group name -> PayloadEntry) from a checked tile table: each built when first read
    (the table's columns were checked whole when it was parsed)."""

    __slots__ = ("table", "row", "_built")

    def __init__(self, table: Table, row: int):
        self.table, self.row = table, row
        self._built: dict[str, PayloadEntry] = {}

    def __getitem__(self, name: str) -> PayloadEntry:
        entry = self._built.get(name)
        if entry is None:
            try:
                j = self.table.groups.index(name)
            except ValueError:
                raise KeyError(name) from None
            entry = self._built[name] = self.table.entry(self.row * len(self.table.groups) + j)
        return entry

    def __iter__(self) -> Iterator[str]:
        return iter(self.table.groups)

    def __len__(self) -> int:
        return len(self.table.groups)

    def raw_fields(self, name: str, fields: tuple[str, ...]) -> tuple:
        """Fields of an entry without building it (model.entry_fields)."""
        p = self.row * len(self.table.groups) + self.table.groups.index(name)
        t = self.table
        values = {"bytes": lambda: int(t.bytes[p]), "gpu_bytes": lambda: int(t.gpu_bytes[p]),
                  "raw_bytes": lambda: int(t.raw_bytes[p]), "sha256": lambda: t.sha_hex(p),
                  "file": lambda: payload_name(t.sha_hex(p))}
        return tuple(values[f]() for f in fields)

    def __reduce__(self):  # pickled as the plain entries (a tile sent to another process needs no table)
        return dict, ({name: self[name] for name in self},)



def scene_summary(m: Manifest) -> dict:
    """JSON-ready facts about a scene, as `splatstream info` and the server's /api/scenes give them."""
    return {
        "name": m.name,
        "splats": m.splats,
        "sh_degree": m.sh_degree,
        "preset": m.preset,
        # + 0.0 turns -0.0 into 0.0: a splat at x = -0.0 wrote '"min": [-0.0, ...]' into /api/scenes and info's JSON
        # (newuser63); the manifest keeps its bounds as stored
        "bounds": {k: [v + 0.0 for v in corner] for k, corner in m.bounds.to_dict().items()},
        "up": list(m.up),
        "bytes_on_disk": m.bytes_on_disk,
        "gpu_bytes": m.gpu_bytes,
        "gpu_bytes_per_splat": m.gpu_bytes_per_splat,
        "tiles": m.paged.tiles if m.paged is not None else len(m.tiles),
        "levels": m.paged.levels if m.paged is not None else m.levels,
        "sh_codebook_entries": m.sh_codebook.entries if m.sh_codebook else None,
        "version": list(m.version),
        **({"pages": m.paged.pages, "page_bytes": m.paged.page_bytes} if m.paged is not None else {}),
    }
