"""A paged scene's tree as the client holds it (format.md 6.1, client.md 1.11): the root manifest's tiles and those
of the pages read so far, grown in place when a page arrives.

Pure (no GL, no I/O): the engine asks which pages the cut reaches (`wanted_pages`), hands the fetcher their
entries (verified there like payloads), and gives each page's verified bytes to `add_page`. Tiles keep their
position once held, so everything the engine keeps per tile position (residency, bands, last drawn) stays valid:
a page's tiles are appended. A tile whose page is not read yet has no children in the view `manifest`: the
selection treats it as a leaf, which it may draw (REPLACE: it stands for its whole subtree, lod.md 5). `evict`
drops pages again (the engine decides which); the tiles kept stay where they are but for the last ones, moved into
the holes (the tiles left dense, the pass's Python over the tiles dropped and moved), and the engine takes its
per-tile state through the positions it returns.
"""
from __future__ import annotations

import functools
import operator
import weakref
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from itertools import repeat

import numpy as np

from splatstream.format.container import VerifiedPayload, verified_bytes
from splatstream.format.manifest import (
    ListPrefix,
    Manifest,
    PageRef,
    TileEntry,
    grown_arrays,
    kept_prefix,
    read_page,
    replace_kept,
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
    # the tiles as the tree holds them (_as_held: those with a page below as leaves), made there too: a copy of
    # each such tile (half a page's tiles, 3 us each) was 0.2 ms of a page's adoption on the frame loop
    held: list[TileEntry] | None = None


@dataclass(frozen=True)
class HeldPages:
    """The pages held as arrays over the tiles' positions (`PagedTree.held`): what is below each page's head (its
    descendants through every page held: `PagedTree.below`) found by grouping, not by walking the tree. The pages
    are in the order of their heads' positions, in no order of the tree (an eviction moves tiles into the holes
    left, so a tile can come before its page's head): pages nest by `up` and `depth` only."""

    heads: np.ndarray  # positions of the tiles whose page is held, ascending
    ids: np.ndarray  # their tile ids
    owner: np.ndarray  # per position held: the index (in heads) of the page the tile came in; -1: the root manifest's
    up: np.ndarray  # per head: the index of the page its head came in; -1: a tile of the root manifest
    depth: np.ndarray  # per head: pages above it (0: its head is a tile of the root manifest)

    @functools.cached_property
    def tiles_below(self) -> np.ndarray:
        """Per head, how many tiles are held below it (kept with the HeldPages, which the tree keeps until it
        changes)."""
        return self.below(np.ones(len(self.owner), np.int64), np.add, 0)

    @functools.cached_property
    def _owner_row(self) -> np.ndarray:
        """owner + 1 per position held: np.bincount's bins (0: the root manifest's tiles, given up)."""
        return self.owner + 1

    @functools.cached_property
    def _owned(self) -> tuple[np.ndarray, np.ndarray]:
        """The positions held that came in a page, and their pages (ufunc.at's indices)."""
        at = np.flatnonzero(self.owner >= 0)
        return at, self.owner[at]

    def below(self, values: np.ndarray, ufunc: np.ufunc, initial) -> np.ndarray:
        """Per head, `ufunc` (np.add, np.maximum, ...) reduced over `values` (one per position held) of the tiles
        below it, from `initial` (what a page with no tile below it reads). Sums of integers by np.bincount (exact
        below 2**53; np.add.at over the tiles held was most of the eviction's choice: BENCHMARKS.md, "Manifest
        pages", evict38)."""
        m = len(self.heads)
        if ufunc is np.add and values.dtype.kind in "bi" and values.dtype.itemsize <= 8:
            sums = np.bincount(self._owner_row, values, minlength=m + 1)[1:]
            out = sums.astype(values.dtype) if sums.dtype != values.dtype else sums
            if initial:
                out += initial
        else:
            out = np.full(m, initial, values.dtype)
            at, owner = self._owned
            ufunc.at(out, owner, values[at])
        for d in range(int(self.depth.max(initial=0)), 0, -1):  # the deepest pages first, into the page above them
            at = np.flatnonzero(self.depth == d)
            ufunc.at(out, self.up[at], out[at])
        return out


class PagedTree:
    """The tiles of a paged scene held so far; `manifest` is their view (the root manifest with these tiles)."""

    def __init__(self, root: Manifest, source: str = "scene", rows_ahead: int = 0):
        """`rows_ahead`: the tiles the tree is expected to hold at most (the engine's bound and its margin): its
        arrays' storage is made that large at first (np.empty: memory touched as rows are written), where doubling
        it as the tree grew copied every row held into new memory in one adoption (0.95 ms at 7,384 tiles, 1.83 ms
        at 14,652, at 250M splats: BENCHMARKS.md, "Manifest pages"); beyond it, doubled as before."""
        self.root = root
        self.source = source
        self.rows_ahead = rows_ahead
        self.pending: dict[int, PageRef] = {t.id: t.page for t in root.tiles if t.page is not None}
        self._full: dict[int, TileEntry] = {t.id: t for t in root.tiles}  # held tiles, children as stored
        self._tiles: list[TileEntry] = [replace(t, children=()) if t.page is not None else t for t in root.tiles]
        self._position = {t.id: i for i, t in enumerate(self._tiles)}
        # per position held: the position of the head of the page the tile came in (-1: the root manifest's), and
        # its id; rows with spare room after the n held (appended to as pages arrive), what `held` groups by
        self._head_at = np.full(max(64, 2 * len(self._tiles), rows_ahead), -1, np.int64)
        self._ids = np.zeros(len(self._head_at), np.int64)
        self._ids[:len(self._tiles)] = [t.id for t in self._tiles]
        self.pages_read = 0
        self.page_bytes = 0
        self.evicted = 0  # pages dropped again (evict)
        self.dropped_ids: list[int] = []  # the ids of the tiles the last eviction dropped
        self.compaction: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # the last eviction's (evict)
        self._read: set[int] = set()  # tiles whose page is held
        self._held: HeldPages | None = None  # held(), until the tree changes
        self._by_id = {t.id: t for t in self._tiles}  # held tiles as the view has them
        self._view_of: Manifest | None = None  # the view, made again when asked for after a change
        self._changed: set[int] = set()  # positions held in the last view whose children have changed since
        self._rows: list[dict] | None = []  # the rows of the tiles added since the last view (None: take them)
        self._views: list[weakref.ref] = []  # the views' tiles reading self._tiles (ListPrefix: older tiles kept there)
        self._manifest = self._view_of = replace(self.root, tiles=self._tiles_view())

    @property
    def manifest(self) -> Manifest:
        """The tiles held as a manifest. Its arrays, positions and tiles by id are carried over from the last view
        and grown by the tiles added since (tiles keep their positions): a page costs the time of its own tiles,
        not of every tile held (rebuilding them over 21,000 tiles held took 170 ms a page at 250M splats: issue
        38, BENCHMARKS.md "Manifest pages")."""
        if self._view_of is None:
            last = self._manifest
            m = replace(self.root, tiles=self._tiles_view())
            # cached_property values, as Manifest would compute them: the tree's own maps, not copies (the newest
            # view looks tiles up at a dict's speed; _detach gives it its own lookups before the maps change)
            m.__dict__["index_of"] = self._position
            m.__dict__["tile_by_id"] = self._by_id
            if "arrays" in last.__dict__:
                m.__dict__["arrays"] = grown_arrays(last.arrays, m.tiles, m.index_of, self._changed, self._rows,
                                                    self.rows_ahead)
            self._changed, self._rows = set(), []
            self._manifest = self._view_of = m
        return self._view_of

    def _tiles_view(self) -> ListPrefix:
        """The tiles held now as a view's `tiles` (ListPrefix): the tree's list up to its length, not a tuple of
        every tile (a tuple a page, and the last one's freed, touched every tile held: 0.14 ms median of a page's
        adoption, 0.4 p99, at 21,000 tiles; BENCHMARKS.md, "Manifest pages")."""
        return kept_prefix(self._tiles, self._views, len(self._tiles))

    def _replace_tile(self, at: int, tile: TileEntry) -> None:
        """self._tiles[at] = tile, the tile there before kept by the views that hold that position."""
        replace_kept(self._tiles, self._views, at, tile)

    def _detach(self) -> None:
        """Before the tree's maps grow: the last view, which shares them, keeps lookups of its own tiles only
        (positions never change between evictions, so its positions are the maps' below its length; its tiles by
        id are its own tuple's). O(1), where copying both maps took 0.1-0.35 ms a page at 21,000 tiles held."""
        v = self._manifest
        if v.__dict__.get("index_of") is self._position:
            index = _HeldIndex(self._position, len(v.tiles))
            v.__dict__["index_of"], v.__dict__["tile_by_id"] = index, _HeldById(v.tiles, index)

    def entry(self, tile_id: int) -> PageRef:
        """The entry of the page below a tile whose page is not read yet (what the fetcher fetches and checks)."""
        return self.pending[tile_id]

    def wanted_pages(self, cut: tuple[int, ...] | list[int], sse: np.ndarray, visible: np.ndarray,
                     max_sse: float) -> list[Key]:
        """Fetch keys of the pages the cut reaches, in the cut's order: cut tiles (positions) whose page is not
        read and that the selection would refine if their children were known (visible, sse above max_sse)."""
        return [(t, PAGE_GROUP) for t in self.manifest.arrays.ids[self.heads_to_refine(cut, sse, visible, max_sse)]
                .tolist()]

    def heads_to_refine(self, cut: tuple[int, ...] | list[int] | np.ndarray, sse: np.ndarray, visible: np.ndarray,
                        max_sse: float) -> np.ndarray:
        """The positions of wanted_pages' tiles, in the cut's order (the engine keeps those whose children the
        budget could let in: selection.pages_the_budget_can_use)."""
        at = np.asarray(cut, np.intp)
        if not self.pending or not at.size:
            return at[:0]
        pending = self.pending
        # the tests in numpy over the cut (a Python test a tile read three numpy scalars: 0.1 ms a frame at 250M)
        refine = at[visible[at] & (sse[at] > max_sse)]
        ids = self.manifest.arrays.ids[refine].tolist()
        return refine[np.fromiter((t in pending for t in ids), bool, len(ids))]

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
        return ParsedPage(tiles, tile_rows(tiles), _as_held(tiles))

    def insert(self, tile_id: int, page: ParsedPage | list[TileEntry]) -> None:
        """Add a page's tiles (what `read` gave; a plain list of tiles has its rows taken with the view); the view
        grows when next asked for (`manifest`: once for the pages a frame adds). A page already added changes
        nothing."""
        ref = self.pending.pop(tile_id, None)
        if ref is None:
            return
        if isinstance(page, ParsedPage):
            tiles, held = page.tiles, page.held
            if self._rows is not None:
                self._rows.append(page.rows)
        else:
            tiles, held, self._rows = page, None, None
        if held is None:
            held = _as_held(tiles)
        self._detach()
        self._held = None
        at = self._position[tile_id]
        self._replace_tile(at, self._full[tile_id])  # its children are known now
        self._by_id[tile_id] = self._full[tile_id]
        if at < len(self._manifest.tiles):
            self._changed.add(at)
        n, add = len(self._tiles), len(tiles)
        if n + add > len(self._head_at):  # doubled when full: a page costs its own rows (amortised)
            grown = max(2 * len(self._head_at), n + add)
            self._head_at = np.concatenate([self._head_at[:n], np.full(grown - n, -1, np.int64)])
            self._ids = np.concatenate([self._ids[:n], np.zeros(grown - n, np.int64)])
        ids = [t.id for t in tiles]
        self._head_at[n:n + add] = at
        self._ids[n:n + add] = ids
        self._full.update(zip(ids, tiles, strict=True))
        self._position.update(zip(ids, range(n, n + add), strict=True))
        self.pending.update((t.id, t.page) for t in tiles if t.page is not None)
        self._tiles += held
        self._by_id.update(zip(ids, held, strict=True))
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

    def heads_unused(self, used: np.ndarray) -> np.ndarray:
        """Positions of the heads of the pages held none of whose own tiles (those the page brought, not those of
        the pages held below it) is marked in `used` (a bool per position held), ascending: every page none of whose
        tiles below is used is among them (its own tiles are some of those below it, and it has one at least), so
        an empty answer says that no page can be dropped. Two gathers over the tiles held, without grouping them by
        page (`held`, 0.2-0.3 ms at 16,000 tiles, made again after every page added): the engine's eviction pass
        asks it first (BENCHMARKS.md, "Manifest pages")."""
        n = len(self._tiles)
        head_at = self._head_at[:n]
        owned = head_at >= 0  # (-1: a tile of the root manifest)
        has_tiles = np.zeros(n, bool)
        has_tiles[head_at[owned]] = True
        has_used = np.zeros(n, bool)
        has_used[head_at[owned & used[:n]]] = True
        return np.flatnonzero(has_tiles & ~has_used)

    def held(self) -> HeldPages:
        """The pages held as arrays (HeldPages): their heads, and which page each tile held came in. Kept until the
        tree changes (the engine's choice of pages to drop, then `evict`, ask for it in one frame: 0.2-0.3 ms each
        at 16,000 tiles)."""
        if self._held is not None:
            return self._held
        n = len(self._tiles)
        position = self._position
        heads = np.sort(np.fromiter(map(position.__getitem__, self._read), np.int64, len(self._read)))
        head_at = self._head_at[:n]
        slot = np.full(n, -1, np.int64)  # each head's index in heads, by its position (a gather, not a search)
        slot[heads] = np.arange(len(heads))
        owner = slot[head_at]  # (head_at -1, the root manifest's tiles, reads the last row: set below)
        owner[head_at < 0] = -1
        up = owner[heads]
        depth = np.zeros(len(heads), np.int64)
        above = up.copy()
        while (above >= 0).any():  # a few rounds: pages nest as deep as the tree's levels over a page's levels
            depth += above >= 0
            above = np.where(above >= 0, up[above], -1)
        self._held = HeldPages(heads, self._ids[heads], owner, up, depth)
        return self._held

    def evict(self, heads: list[int],
              move_rows: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None = None) -> np.ndarray:
        """Drop the pages below these tiles (and every page held below them): the tiles become leaves again, their
        pages wanted again when a cut reaches them. Returns the old position of each tile kept, by its new position
        (the engine's per-tile state is taken through it): the tiles kept keep their positions, but for those after
        the new end, moved into the holes (the lowest hole first, in order). A head not held, or below a head
        dropped before it in `heads`, changes nothing. In array operations over the tiles held and Python over the
        tiles dropped and moved (a walk of the tree for each head, and Python over every tile held, took 73-107 ms
        of a frame at 250M splats: issue 38, BENCHMARKS.md "Manifest pages"). `move_rows(buf, moved, src)`:
        buf[moved] = buf[src] (the client's compiled kernel, which keeps the interpreter lock; None: numpy's).
        After it, `compaction` is (new_of, holes, moved): the new position of each old one (-1: dropped; one entry
        more, -1), the new positions whose tile was elsewhere (ascending) and the old positions of those tiles, the
        one map the engine takes its per-tile state through."""
        # the view before the eviction: its arrays' rows are taken, moved within their storage; it and the views
        # before it share the maps edited below, and are not read after the eviction (the engine drops them)
        last = self.manifest
        held = self.held()
        n = len(self._tiles)
        # in Python lists (a page's index by its head's position): a searchsorted and numpy scalars a head were a
        # release of the interpreter lock each and microseconds of Python (evict38)
        slot_of = dict(zip(held.heads.tolist(), range(len(held.heads)), strict=True))
        up = held.up.tolist()
        dropped_at = [False] * len(up)  # pages dropped, the heads given first
        for h in heads:
            if h not in self._read:
                continue
            j = slot_of[self._position[h]]
            above = j
            while above >= 0 and not dropped_at[above]:  # below a page dropped before it: gone already
                above = up[above]
            if above >= 0:
                continue
            dropped_at[j] = True
            self._read.discard(h)
            self.pending[h] = self._full[h].page
            self.evicted += 1
        dropped = np.array(dropped_at, bool)
        if not dropped.any():
            self.dropped_ids = []
            none = np.zeros(0, np.int64)
            self.compaction = (np.append(np.arange(n, dtype=np.int64), -1), none, none)
            return np.arange(n, dtype=np.int64)
        self._held = None
        cut = dropped.copy()  # the pages dropped and every page below them
        for d in range(1, int(held.depth.max(initial=0)) + 1):
            at = np.flatnonzero(held.depth == d)
            cut[at] |= cut[held.up[at]]
        gone = np.append(cut, False)[held.owner]  # (owner -1, the root manifest's tiles, reads the False)
        self.dropped_ids = gone_ids = self._ids[np.flatnonzero(gone)].tolist()
        # the tiles of the pages dropped, forgotten in C loops (map over the ids: a Python loop a tile was 0.1-0.2
        # ms of a pass dropping 1,000 tiles)
        self._read.difference_update(gone_ids)
        deque(map(self.pending.pop, gone_ids, repeat(None)), maxlen=0)
        deque(map(self._full.__delitem__, gone_ids), maxlen=0)
        deque(map(self._by_id.__delitem__, gone_ids), maxlen=0)
        # a list of its own from here (one copy at C speed): the views before the eviction keep theirs
        tiles = self._tiles = list(self._tiles)
        self._views = []
        for j in np.flatnonzero(dropped & ~gone[held.heads]).tolist():  # a head dropped (a leaf again), unless
            h = int(held.ids[j])  # below a page dropped after it
            tiles[held.heads[j]] = self._by_id[h] = replace(self._full[h], children=())
        # The kept tiles stay where they are and the last ones fill the holes (each moved tile into the lowest
        # hole, in order): the positions, tiles and tuples of children change for the tiles moved and dropped
        # only, where renumbering every tile after the first hole in order took 7-12 ms of the frame at 16,000
        # tiles (BENCHMARKS.md, "Manifest pages").
        k = n - int(gone.sum())
        holes = np.flatnonzero(gone[:k])
        moved = np.flatnonzero(~gone[k:]) + k
        keep = np.arange(k)
        keep[holes] = moved
        deque(map(tiles.__setitem__, holes.tolist(), _taken(tiles, moved.tolist())), maxlen=0)
        del tiles[k:]
        new_of = np.full(n + 1, -1, np.int64)  # index -1 (the root manifest's tiles' head) reads -1
        new_of[keep] = np.arange(k)
        self.compaction = (new_of, holes, moved)
        # the rows moved in their storage (rows from n on are written before they are read: insert), where new
        # arrays took every row through `keep` (two gathers, two concatenations over the tiles held)
        move = move_rows if move_rows is not None else _move_rows
        move(self._head_at, holes, moved)
        move(self._ids, holes, moved)
        self._head_at[:k] = new_of[self._head_at[:k]]
        # edited in place (made anew, 1.0-1.3 ms at 19,000 tiles; a copy of a dict with holes 0.3-1.0 ms): the
        # views before the eviction, which share it, are not read after it (their arrays' rows are moved too)
        position = self._position
        deque(map(position.__delitem__, gone_ids), maxlen=0)
        position.update(zip(self._ids[holes].tolist(), holes.tolist(), strict=True))
        m = replace(self.root, tiles=self._tiles_view())
        m.__dict__["index_of"], m.__dict__["tile_by_id"] = self._position, self._by_id
        if "arrays" in last.__dict__:  # the kept rows taken, not rebuilt from the tiles
            # the moved rows written into the holes of the last view's storage (the last view is not read after
            # the eviction: the engine drops everything made from it)
            m.__dict__["arrays"] = arrays = taken_arrays(last.arrays, keep, in_place=True, move_rows=move_rows,
                                                         compaction=(new_of, holes))
            # where they came from, for the compiled selection's children's index (selection_jit._ChildIndex: taken
            # through `keep` instead of made again from the tuples); one link only, the last arrays' own dropped
            arrays.__dict__["_taken_from"] = (last.arrays, keep)
            last.arrays.__dict__.pop("_taken_from", None)
        self._changed, self._rows = set(), []
        self._manifest = self._view_of = m
        return keep

    def add_page(self, tile_id: int, data: VerifiedPayload | bytes) -> Manifest:
        """read, then insert (in one thread)."""
        if tile_id not in self.pending:
            return self.manifest
        self.insert(tile_id, self.read(tile_id, data))
        return self.manifest


def _as_held(tiles: list[TileEntry]) -> list[TileEntry]:
    """A page's tiles as the tree holds them: a tile with a page below it is a leaf until that page is read."""
    if all(t.page is None for t in tiles):
        return tiles
    return [replace(t, children=()) if t.page is not None else t for t in tiles]


def _move_rows(buf: np.ndarray, moved: np.ndarray, src: np.ndarray) -> None:
    """buf[moved] = buf[src] (the numpy path of evict's `move_rows`)."""
    buf[moved] = buf[src]


def _taken(items: list, at: list[int]) -> list:
    """[items[i] for i in at], in C (operator.itemgetter: a third of a list comprehension's time)."""
    return list(operator.itemgetter(*at)(items)) if len(at) > 1 else [items[i] for i in at]


class _HeldIndex(Mapping):
    """Tile id -> position of a view that is no longer the newest (PagedTree._detach): the tree's map, which only
    grows until the next eviction (which makes new maps), read below the view's length."""

    def __init__(self, position: dict[int, int], n: int):
        self._position, self._n = position, n

    def __getitem__(self, tile_id: int) -> int:
        i = self._position[tile_id]
        if i >= self._n:
            raise KeyError(tile_id)
        return i

    def __iter__(self):
        return (t for t, i in self._position.items() if i < self._n)

    def __len__(self) -> int:
        return self._n


class _HeldById(Mapping):
    """Tile id -> tile of a view that is no longer the newest: its own tiles, through its positions."""

    def __init__(self, tiles: tuple[TileEntry, ...], index: _HeldIndex):
        self._tiles, self._index = tiles, index

    def __getitem__(self, tile_id: int) -> TileEntry:
        return self._tiles[self._index[tile_id]]

    def __iter__(self):
        return iter(self._index)

    def __len__(self) -> int:
        return len(self._tiles)
