"""Manifest pages (format.md 6.1, version 1.5): a large tree's root manifest holds its top levels, immutable pages
named by their SHA-256 the rest, each the next `page_levels` levels below one tile.

`split_pages` turns a whole manifest into the root manifest and its pages (the encoder); `read_page` checks a
page's bytes against the `page` entry naming it and parses its tiles (a reader, once per page, like a payload);
`resolve_pages` reads every page and gives back the whole tree as one Manifest (info, decode, export), checked
like an unpaged manifest.
"""
from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import msgpack

from ...errors import FormatError
from ..names import digest_hex, digest_matches, payload_name
from .model import Manifest, PagedInfo, PageRef, TileEntry
from .table import short_digests, tiles_body
from .validate import MAX_PAGE_BYTES, PAGE_FORMAT, check_whole_tree, page_tiles
from .versions import VERSION_1_5
from .wire import check_msgpack_bomb, pack_manifest


@dataclass(frozen=True)
class PagedScene:
    """A paged scene's files: the root manifest and each page's entry and bytes (deepest pages first)."""

    root: Manifest
    pages: tuple[tuple[PageRef, bytes], ...]


def pack_page(version: tuple[int, int], parent: int, tiles: list[TileEntry]) -> bytes:
    """A page's bytes (format.md 6.1): its tiles in id order, as a tile table from 1.8 on (6.2), a compact one from
    1.12 on."""
    ordered = sorted(tiles, key=lambda t: t.id)
    body = tiles_body(version, ordered, list(ordered[0].groups))
    return msgpack.packb({"format": PAGE_FORMAT, "version": list(version), "parent": parent, **body},
                         use_bin_type=True)


def page_heads(m: Manifest, page_levels: int) -> list[TileEntry]:
    """The tiles whose next `page_levels` levels of descendants make a page (format.md 6.1): those with children on
    the last level of the root manifest or of a page, deepest first (a page's name depends on the pages below it)."""
    k = page_levels
    return sorted((t for t in m.tiles if (t.level + 1) % k == 0 and t.children), key=lambda t: (-t.level, t.id))


def split_pages(m: Manifest, page_levels: int) -> PagedScene:
    """The root manifest (levels 0..k-1) and the pages of a whole, unpaged manifest. Deterministic: the same
    manifest gives the same bytes. A page's name depends on the pages below it, so the deepest are made first.
    From format 1.16 a page's top tiles are its table's anchors (f32 boxes, format.md 6.2), so the tree the pages
    give back is `m.compacted(page_levels=k)`: m itself where it was compacted so (store.write_scene_manifest)."""
    if page_levels < 1:
        raise ValueError(page_levels)
    k = page_levels
    by_id = {t.id: t for t in m.tiles}
    refs: dict[int, PageRef] = {}
    pages: list[tuple[PageRef, bytes]] = []

    def with_ref(t: TileEntry) -> TileEntry:
        ref = refs.get(t.id)
        return t if ref is None else replace(t, page=ref)

    def below(t: TileEntry) -> list[TileEntry]:
        """t's descendants of the next k levels."""
        out, frontier = [], [t]
        for _ in range(k):
            frontier = [by_id[c] for f in frontier for c in f.children]
            out += frontier
        return out

    # A page's version is its root manifest's (format.md 6.1): 1.5, or the scene's own where that is later (a
    # 1.6 or 1.7 scene's pages were written as 1.5 before, which every reader then refused).
    version = max(m.version, VERSION_1_5)
    for head in page_heads(m, k):
        raw = pack_page(version, head.id, [with_ref(t) for t in below(head)])
        sha = digest_hex(raw, short_digests(version))  # 16 bytes of it from 1.15 (format.md 6.2)
        if len(raw) > MAX_PAGE_BYTES:
            raise FormatError(m.name, "paged", f"a page of {len(raw)} bytes: more than {MAX_PAGE_BYTES}; fewer "
                              "levels to a page")
        ref = refs[head.id] = PageRef(payload_name(sha), sha, len(raw))
        pages.append((ref, raw))
    top = tuple(with_ref(t) for t in m.tiles if t.level < k)
    page_bytes = sum(ref.bytes for ref, _ in pages)
    root = replace(m, version=version, tiles=top,
                   paged=PagedInfo(len(m.tiles), m.levels, k, len(pages), page_bytes))
    payloads = m.payload_bytes()
    for _ in range(3):  # as Manifest.with_bytes_on_disk: the number's own length settles after two rounds
        root = replace(root, bytes_on_disk=payloads + page_bytes + len(pack_manifest(root)))
    return PagedScene(root, tuple(pages))


def read_page(raw: bytes, ref: PageRef, root: Manifest, parent: TileEntry, source: str,
              lazy_payloads: bool = False, hashed: bool = False) -> list[TileEntry]:
    """A page's tiles from its bytes, checked against the entry naming it (length and SHA-256, as a payload's)
    before anything in it is read. hashed: the caller holds the bytes as a VerifiedPayload of this entry
    (format/container.py, the streaming client: checked once where they entered), so they are not hashed again."""
    if len(raw) != ref.bytes:
        raise FormatError(source, None, f"{len(raw)} bytes, but the manifest names a page of {ref.bytes} bytes")
    actual = ref.sha256 if hashed else hashlib.sha256(raw).hexdigest()
    if not digest_matches(actual, ref.sha256):
        raise FormatError(source, None, f"checksum mismatch: the page is corrupt (its bytes hash to {actual}, the "
                          f"manifest names {ref.sha256})")
    check_msgpack_bomb(raw, source)
    try:
        d = msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise FormatError(source, None, f"not a msgpack page ({exc.__class__.__name__}: {exc})") from None
    return page_tiles(d, source, root, parent, lazy_payloads)


def resolve_pages(root: Manifest, read: Callable[[PageRef], bytes], source: str, root_bytes: int) -> Manifest:
    """The whole tree of a paged scene as one Manifest (its pages read through `read`, each checked), checked as
    an unpaged manifest is: one tree, the splat counts, the totals, bytes_on_disk. An unpaged manifest as is."""
    if root.paged is None:
        return root
    tiles = list(root.tiles)
    todo = [t for t in tiles if t.page is not None]
    files = root_bytes
    while todo:
        parent = todo.pop()
        ref = parent.page
        raw = read(ref)
        files += len(raw)
        got = read_page(raw, ref, root, parent, f"{source} page {ref.file}")
        tiles += got
        todo += [t for t in got if t.page is not None]
    tiles.sort(key=lambda t: t.id)
    whole = replace(root, tiles=tuple(tiles))
    if len(tiles) != root.paged.tiles:
        raise FormatError(source, "paged.tiles", f"{root.paged.tiles}, but the tree has {len(tiles)} tiles")
    check_whole_tree(whole, source, files)
    return whole
