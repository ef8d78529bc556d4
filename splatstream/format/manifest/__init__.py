"""The scene manifest (format_spec/format.md 6), typed: parsed and validated once, then trusted.

`parse_manifest(bytes)` turns a msgpack manifest into a frozen `Manifest` (tiles as `TileEntry`, payloads as
`PayloadEntry` with their `Section`s) or raises FormatError naming the field (`tiles[3].groups.base.bytes`) and
what was expected. `Manifest.to_dict()` gives back the spec's map (the encoder writes it with `pack_manifest`).

    model.py     the frozen records and their derived views (TileArrays)
    wire.py      the file's bytes: msgpack, the checksum, the msgpack-bomb guard
    validate.py  the one validator (eager, or each tile's payload entries when first read)
    versions.py  what this code reads and what a writer writes
    paging.py    manifest pages (version 1.5): a large tree split into a root manifest and pages, and read back
"""
from .model import (
    AttributeSize,
    Box,
    CameraEntry,
    LazyPayloads,
    LevelRefinement,
    ListPrefix,
    LodInfo,
    LodRefinement,
    Manifest,
    PagedInfo,
    PageRef,
    PayloadEntry,
    Section,
    SHCodebookEntry,
    TileArrays,
    TileEntry,
    Vec3,
    filter_element,
    filter_for,
    grown_arrays,
    indexable,
    kept_prefix,
    replace_kept,
    scene_summary,
    taken_arrays,
    tile_arrays,
    tile_rows,
)
from .paging import PagedScene, pack_page, page_heads, read_page, resolve_pages, split_pages
from .table import short_tile_names
from .validate import (
    CHUNK_ORDER_NAMES,
    FILTERS_DOC,
    MAX_PAGE_BYTES,
    MAX_PAYLOAD_RAW_BYTES,
    MAX_TILES,
    MAX_WASTED_BLOCKS,
    PAGE_FORMAT,
    expected_sections,
    manifest_from_dict,
    max_blocks,
    parse_manifest,
)
from .versions import (
    CHECKSUM_VERSION,
    CHUNK_ORDERS_1_4,
    FORMAT_NAME,
    FORMAT_VERSION,
    FORMATS_1_3,
    VERSION_1_3,
    VERSION_1_4,
    VERSION_1_5,
    writer_version,
)
from .wire import (
    CHECKSUM_KEY,
    CHECKSUM_PLACEHOLDER,
    MAX_MANIFEST_BYTES,
    MAX_MANIFEST_OBJECT_BYTES,
    check_msgpack_bomb,
    manifest_checksum,
    pack_manifest,
    pack_manifest_dict,
)

__all__ = [
    "PagedInfo", "PageRef", "PagedScene", "pack_page", "page_heads", "read_page", "resolve_pages", "split_pages",
    "MAX_PAGE_BYTES", "PAGE_FORMAT", "VERSION_1_5",
    "AttributeSize", "Box", "CameraEntry", "LazyPayloads", "LevelRefinement", "LodInfo", "LodRefinement", "Manifest",
    "PayloadEntry", "Section",
    "SHCodebookEntry", "TileArrays", "TileEntry", "Vec3", "scene_summary", "grown_arrays", "taken_arrays",
    "tile_arrays", "tile_rows", "ListPrefix", "kept_prefix", "replace_kept", "indexable",
    "CHUNK_ORDER_NAMES", "FILTERS_DOC", "MAX_PAYLOAD_RAW_BYTES", "MAX_TILES", "MAX_WASTED_BLOCKS",
    "expected_sections", "filter_element", "filter_for", "manifest_from_dict", "max_blocks", "parse_manifest",
    "CHECKSUM_VERSION", "CHUNK_ORDERS_1_4", "FORMAT_NAME", "FORMAT_VERSION", "FORMATS_1_3", "VERSION_1_3",
    "VERSION_1_4", "writer_version",
    "CHECKSUM_KEY", "CHECKSUM_PLACEHOLDER", "MAX_MANIFEST_BYTES", "MAX_MANIFEST_OBJECT_BYTES", "check_msgpack_bomb",
    "manifest_checksum", "pack_manifest", "pack_manifest_dict",
    "short_tile_names",
]
