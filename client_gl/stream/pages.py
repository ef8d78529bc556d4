"""A paged scene's tree as the client holds it (format.md 6.1, client.md 1.11): the root manifest's tiles and those
of the pages read so far, grown in place when a page arrives.

Pure (no GL, no I/O): the engine asks which pages the cut reaches (`wanted_pages`), hands the fetcher their
entries (verified there like payloads), and gives each page's verified bytes to `add_page`. Tiles keep their
position once held, so everything the engine keeps per tile position (residency, bands, last drawn) stays valid:
a page's tiles are appended. A tile whose page is not read yet has no children in the view `manifest`: the
selection treats it as a leaf, which it may draw (REPLACE: it stands for its whole subtree, lod.md 5). `evict`
drops pages again (the engine decides which); the tiles kept are then renumbered in order, and the engine takes its
per-tile state through the positions it returns.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from splatstream.format.container import VerifiedPayload, verified_bytes
from splatstream.format.manifest import (
    Manifest,
    PageRef,
    TileEntry,
    grown_arrays,
    read_page,
    taken_arrays,
    tile_rows,
)

Key = tuple[int, str]
PAGE_GROUP = "page"  # the group of a page's fetch key (tile id, "page"): the page below that tile


@dataclass(frozen=True)
class ParsedPage:
    """A page's tiles as `PagedTree.read` parsed them, and their rows of the tree's arrays (tile_rows), taken there
    too: reading a tile's payload sizes unpacks its entries, which on the frame loop was most of a page's adoption
    (BENCHMARKS.md, "Manifest pages")."""

    tiles: list[TileEntry]
    rows: dict[str, np.ndarray]


class PagedTree:
    """The tiles of a paged scene held so far; `manifest` is their view (the root manifest with these tiles)."""

    def __init__(self, root: Manifest, source: str = "scene"):
        self.root = root
        self.source = source
        self.pending: dict[int, PageRef] = {t.id: t.page for t in root.tiles if t.page is not None}
        self._full: dict[int, TileEntry] = {t.id: t for t in root.tiles}  # held tiles, children as stored
        self._tiles: list[TileEntry] = [replace(t, children=()) if t.page is not None else t for t in root.tiles]
        self._position = {t.id: i for i, t in enumerate(self._tiles)}
        self.pages_read = 0
        self.page_bytes = 0
        self.evicted = 0  # pages dropped again (evict)
        self._read: set[int] = set()  # tiles whose page is held
        self._by_id = {t.id: t for t in self._tiles}  # held tiles as the view has them
        self._view_of: Manifest | None = None  # the view, made again when asked for after a change
        self._changed: set[int] = set()  # positions held in the last view whose children have changed since
        self._rows: list[dict] | None = []  # the rows of the tiles added since the last view (None: take them)
        self._manifest = self._view_of = replace(self.root, tiles=tuple(self._tiles))

    @property
    def manifest(self) -> Manifest:
        """The tiles held as a manifest. Its arrays, positions and tiles by id are carried over from the last view
        and grown by the tiles added since (tiles keep their positions): a page costs the time of its own tiles,
        not of every tile held (rebuilding them over 21,000 tiles held took 170 ms a page at 250M splats: issue
        38, BENCHMARKS.md "Manifest pages")."""
        if self._view_of is None:
            last = self._manifest
            m = replace(self.root, tiles=tuple(self._tiles))
            m.__dict__["index_of"] = dict(self._position)  # cached_property values, as Manifest would compute them
            m.__dict__["tile_by_id"] = dict(self._by_id)
            if "arrays" in last.__dict__:
                m.__dict__["arrays"] = grown_arrays(last.arrays, m.tiles, m.index_of, self._changed, self._rows)
            self._changed, self._rows = set(), []
            self._manifest = self._view_of = m
        return self._view_of

    def entry(self, tile_id: int) -> PageRef:
        """The entry of the page below a tile whose page is not read yet (what the fetcher fetches and checks)."""
        return self.pending[tile_id]

    def wanted_pages(self, cut: tuple[int, ...] | list[int], sse: np.ndarray, visible: np.ndarray,
                     max_sse: float) -> list[Key]:
        """Fetch keys of the pages the cut reaches, in the cut's order: cut tiles (positions) whose page is not
        read and that the selection would refine if their children were known (visible, sse above max_sse)."""
        if not self.pending:
            return []
        at = np.asarray(cut, np.intp)
        pending = self.pending
        # the tests in numpy over the cut (a Python test a tile read three numpy scalars: 0.1 ms a frame at 250M)
        refine = at[visible[at] & (sse[at] > max_sse)]
        return [(t, PAGE_GROUP) for t in self.manifest.arrays.ids[refine].tolist() if t in pending]

    def read(self, tile_id: int, data: VerifiedPayload | bytes,
             between: Callable[[], object] | None = None) -> ParsedPage:
        """A page's tiles, parsed and checked, and their rows (any thread: it changes nothing here). Its bytes are
        checked once, like a payload's: a VerifiedPayload of its entry (the fetcher's) as it is, anything else
        hashed now. `between`: called before the parse and before the rows (the engine's decode workers wait there
        for the frame loop's idle time, as between a payload's decode steps: both are Python that would take the
        interpreter lock from the frame loop)."""
        ref = self.pending[tile_id]
        source = f"{self.source} page {ref.file}"
        raw = verified_bytes(data, ref, source)
        if between is not None:
            between()
        tiles = read_page(raw, ref, self.root, self._full[tile_id], source, lazy_payloads=True, hashed=True)
        if between is not None:
            between()
        return ParsedPage(tiles, tile_rows(tiles))

    def insert(self, tile_id: int, page: ParsedPage | list[TileEntry]) -> None:
        """Add a page's tiles (what `read` gave; a plain list of tiles has its rows taken with the view); the view
        grows when next asked for (`manifest`: once for the pages a frame adds). A page already added changes
        nothing."""
        ref = self.pending.pop(tile_id, None)
        if ref is None:
            return
        if isinstance(page, ParsedPage):
            tiles = page.tiles
            if self._rows is not None:
                self._rows.append(page.rows)
        else:
            tiles, self._rows = page, None
        at = self._position[tile_id]
        self._tiles[at] = self._by_id[tile_id] = self._full[tile_id]  # its children are known now
        if at < len(self._manifest.tiles):
            self._changed.add(at)
        for t in tiles:
            self._full[t.id] = t
            self._position[t.id] = len(self._tiles)
            if t.page is not None:
                self.pending[t.id] = t.page
                t = replace(t, children=())
            self._tiles.append(t)
            self._by_id[t.id] = t
        self._read.add(tile_id)
        self.pages_read += 1
        self.page_bytes += ref.bytes
        self._view_of = None

    def held_pages(self) -> list[int]:
        """Tiles whose page is held (each the head of a subtree a page brought)."""
        return sorted(self._read)

    def below(self, tile_id: int) -> list[int]:
        """Positions of the tiles held below a tile (its descendants, through every page held)."""
        out, todo = [], [tile_id]
        while todo:
            t = self._full[todo.pop()]
            if t.page is not None and t.id not in self._read:
                continue
            for c in t.children:
                out.append(self._position[c])
                todo.append(c)
        return out

    def evict(self, heads: list[int]) -> np.ndarray:
        """Drop the pages below these tiles (and every page held below them): the tiles become leaves again, their
        pages wanted again when a cut reaches them. Returns the old positions of the tiles kept, in order (the
        engine's per-tile state is taken through it)."""
        last = self.manifest  # the view before the eviction: its arrays' rows are taken
        gone: set[int] = set()
        for h in heads:
            if h not in self._read or self._position[h] in gone:
                continue
            below = self.below(h)
            gone.update(below)
            for i in below:
                t = self._tiles[i]
                self._read.discard(t.id)
                self.pending.pop(t.id, None)
            self._read.discard(h)
            self.pending[h] = self._full[h].page
            self._tiles[self._position[h]] = self._by_id[h] = replace(self._full[h], children=())
            self.evicted += 1
        keep = np.array([i for i in range(len(self._tiles)) if i not in gone], np.int64)
        for i in gone:
            t = self._tiles[i]
            del self._full[t.id]
            del self._position[t.id]
            del self._by_id[t.id]
        self._tiles = [self._tiles[i] for i in keep]
        self._position = {t.id: i for i, t in enumerate(self._tiles)}
        m = replace(self.root, tiles=tuple(self._tiles))
        m.__dict__["index_of"] = dict(self._position)
        m.__dict__["tile_by_id"] = dict(self._by_id)
        if "arrays" in last.__dict__:  # the kept rows taken, not rebuilt from the tiles
            m.__dict__["arrays"] = taken_arrays(last.arrays, keep)
        self._changed, self._rows = set(), []
        self._manifest = self._view_of = m
        return keep

    def add_page(self, tile_id: int, data: VerifiedPayload | bytes) -> Manifest:
        """read, then insert (in one thread)."""
        if tile_id not in self.pending:
            return self.manifest
        self.insert(tile_id, self.read(tile_id, data))
        return self.manifest
