"""Vector quantisation of SH coefficient rows into a codebook (format_spec/format.md, "SH codebook").

A two-level k-means tree: `top` coarse centroids, each owning a contiguous run of codebook entries fitted to the
rows nearest to it. Assignment walks the same tree (nearest top centroid, then nearest entry among its children),
which costs N x (top + children) distances instead of N x K: about a second for a million 45-value rows against
16,384 entries on two cores, where a flat search takes minutes. When the rows hold no more distinct values than
the codebook has entries, the codebook is those values and the assignment is exact.

Pure numpy; deterministic for a given seed.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .errors import UsageError

MAX_ENTRIES = 65536  # the per-splat index is 16 bits
MIN_AUTO_ENTRIES = 64
# "auto" sizes the codebook to about one entry per this many splats: on fruit_drops (4.7k splats) and the 1M
# scene this kept the codebook near 0.7 B/splat on disk, where index bits and codebook bytes balance.
AUTO_SPLATS_PER_ENTRY = 64
ITERATIONS = 8
SAMPLE_PER_CENTROID = 64
MIN_SAMPLE = 4096
ASSIGN_BLOCK = 32768
DISTANCE_BLOCK_BYTES = 16 << 20
# Below this many row-entry distance pairs a flat k-means (one entry per top cell) is cheap and fits better:
# on fruit_drops at 64 entries, RMSE 0.0340 flat against 0.0355 for the tree.
FLAT_LIMIT = 1 << 27


# "fine" sizes the codebook to about one entry per 16 splats, at least 256 (a small scene keeps its SH detail for
# little more size), but no more than 16,384 or auto's size, whichever is larger: the fit's time grows with the
# entries (BENCHMARKS.md, "Figures behind library defaults").
FINE_SPLATS_PER_ENTRY = 16
MIN_FINE_ENTRIES = 256
FINE_CAP = 16384
# "large" sizes the codebook to about one entry per 8 splats, at least 256, up to the 16-bit index's 65,536: on
# flowers (SH2, 542k splats, 262k distinct SH rows) 65,536 entries where "fine" stops at 16,384; at a 64k codebook
# the SH bands cost 3.5 B/splat there (SOG's palette: 4.4) and the preset gains 3.3 dB over its 8k one
# (BENCHMARKS.md, "A 64k SH codebook on flowers").
LARGE_SPLATS_PER_ENTRY = 8
# Above FINE_CAP entries a row searches the entries of its two nearest top cells, in the fit (one Lloyd round after
# the tree's) and in every assignment: on flowers at 65,536 entries the weighted RMS SH error of the fit went 0.01799
# -> 0.01760 (one cell -> two, and the round), for about twice the assignment time.
LARGE_PROBES = 2
# The large codebooks' cells are fitted in this many Lloyd rounds (8 elsewhere), seeded from dot products: on flowers
# the fit's CPU time went 9.35 -> 4.31 s for a weighted RMS error of 0.017618 against 0.017604 (-0.02 dB on its
# renders; BENCHMARKS.md, "The large codebook's encode time").
LARGE_ITERATIONS = 5


def _power_of_two_near(x: float) -> int:
    return 2 ** int(round(np.log2(max(1.0, x))))


def auto_entries(splats: int) -> int:
    """Codebook size for `splats` rows: a power of two near splats / 64, in 64..65536."""
    if splats <= 0:
        return MIN_AUTO_ENTRIES
    k = _power_of_two_near(splats / AUTO_SPLATS_PER_ENTRY)
    return int(min(MAX_ENTRIES, max(MIN_AUTO_ENTRIES, k)))


def fine_entries(splats: int) -> int:
    """The larger codebook of `--sh-codebook fine`: a power of two near splats / 16, at least 256, at most 16,384
    or auto_entries(splats), whichever is larger."""
    k = max(MIN_FINE_ENTRIES, _power_of_two_near(max(1, splats) / FINE_SPLATS_PER_ENTRY))
    return int(min(k, max(FINE_CAP, auto_entries(splats)), MAX_ENTRIES))


def large_entries(splats: int) -> int:
    """The codebook of `--sh-codebook large`: a power of two near splats / 8, at least 256, at most 65,536."""
    k = _power_of_two_near(max(1, splats) / LARGE_SPLATS_PER_ENTRY)
    return int(min(max(MIN_FINE_ENTRIES, k), MAX_ENTRIES))


def parse_entries(value: str | int, splats: int) -> int:
    """'auto', 'fine', 'large' or an entry count -> the entry count (0 = no codebook, 'off')."""
    if value in ("off", 0, "0", None):
        return 0
    if value == "auto":
        return auto_entries(splats)
    if value == "fine":
        return fine_entries(splats)
    if value == "large":
        return large_entries(splats)
    try:
        k = int(value)
    except (TypeError, ValueError):
        raise UsageError(f"SH codebook size {value!r}: expected off, auto, fine, large or an entry count "
                         f"1..{MAX_ENTRIES}") from None
    if not 1 <= k <= MAX_ENTRIES:
        raise UsageError(f"SH codebook size {k}: expected 1..{MAX_ENTRIES} entries (the index is 16 bits)")
    return k


@dataclass
class Codebook:
    entries: np.ndarray      # (K, D) float32, in stored order: entry i is what a splat with index i gets
    top: np.ndarray          # (T, D) float32 coarse centroids
    starts: np.ndarray       # (T + 1,) tree positions starts[t]..starts[t + 1] are the entries of top centroid t
    tree: np.ndarray | None = None  # (K,) stored index of each tree position (None: the same order)
    probes: int = 1          # rows search the entries of their `probes` nearest top centroids
    _prep: _Prepared | None = field(default=None, init=False, repr=False, compare=False)

    def __getstate__(self) -> dict:
        # Without what assignments prepared (about twice the entries' bytes): a process it is sent to makes its own.
        return {**self.__dict__, "_prep": None}

    def ordered_by_use(self, counts: np.ndarray) -> Codebook:
        """The same codebook with entries renumbered by falling use count (ties keep their order): frequent entries
        get small indices, so the per-splat index plane has mostly-zero high bytes (-7 % on the index plane of a
        1M scene with distinct SH rows). Assignment still walks the tree."""
        order = np.argsort(-np.asarray(counts), kind="stable")
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order))
        tree = rank if self.tree is None else rank[self.tree]
        return Codebook(self.entries[order], self.top, self.starts, tree, self.probes)

    def assign(self, rows: np.ndarray) -> np.ndarray:
        """Index of the (tree-)nearest entry of every row, (N,) int64. Rows equal to an entry get that entry
        (looked up by value: a million rows in about a second where the search would take many)."""
        rows = np.ascontiguousarray(rows, np.float32)
        labels = np.full(len(rows), -1, np.int64)
        if len(self.entries) > 1:
            hit = self._lookup(rows, labels)
            if hit.all():
                return labels
            missing = np.flatnonzero(~hit)
            labels[missing] = self._search(rows[missing])
            return labels
        return self._search(rows)

    def _prepared(self) -> _Prepared:
        """What every assignment reuses, made on the first one: the entries' row hashes in sorted order and each
        top cell's entries with their squared norms. Made again per call, the sort of the 65,536 entries' keys and
        the per-cell gathers took most of the `large` codebook's assignment time over the LOD tiles (BENCHMARKS.md,
        "The large codebook's encode time")."""
        if self._prep is None:
            entries = np.ascontiguousarray(self.entries, np.float32)
            hashes = _row_hashes(entries)
            by_hash = np.argsort(hashes, kind="stable")
            sorted_hashes = hashes[by_hash]
            # Distinct entries with one hash (never seen): the exact keys instead, as before the hashes.
            same = np.flatnonzero(sorted_hashes[1:] == sorted_hashes[:-1])
            exact = bool(len(same)) and not np.array_equal(entries[by_hash[same]].view(np.uint32),
                                                           entries[by_hash[same + 1]].view(np.uint32))
            cells = []
            for t in range(len(self.top)):
                s, e = int(self.starts[t]), int(self.starts[t + 1])
                ids = np.arange(s, e) if self.tree is None else self.tree[s:e]
                ent = np.ascontiguousarray(entries[ids])
                cells.append((ids, ent, np.einsum("ij,ij->i", ent, ent)))
            self._prep = _Prepared(by_hash, sorted_hashes, exact, cells,
                                   np.einsum("ij,ij->i", self.top, self.top))
        return self._prep

    def _lookup(self, rows: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Set labels of the rows bit-for-bit equal to an entry (the first such entry); returns which rows were."""
        prep = self._prepared()
        if prep.exact_keys:
            keys = _row_keys(np.ascontiguousarray(self.entries, np.float32))
            by_key = np.argsort(keys, kind="stable")
            sorted_keys = keys[by_key]
            row_keys = _row_keys(rows)
            pos = np.minimum(np.searchsorted(sorted_keys, row_keys), len(sorted_keys) - 1)
            hit = sorted_keys[pos] == row_keys
            labels[hit] = by_key[pos[hit]]
            return hit
        row_hashes = _row_hashes(rows)
        pos = np.minimum(np.searchsorted(prep.sorted_hashes, row_hashes), len(prep.sorted_hashes) - 1)
        hit = prep.sorted_hashes[pos] == row_hashes
        cand = np.flatnonzero(hit)
        ids = prep.by_hash[pos[cand]]
        equal = (rows[cand].view(np.uint32) == self.entries[ids].view(np.uint32)).all(axis=1)
        hit[cand[~equal]] = False
        labels[cand[equal]] = ids[equal]
        return hit

    def _search(self, rows: np.ndarray) -> np.ndarray:
        if self.probes > 1 and len(self.top) > 1:
            return self._search_probes(rows)
        prep = self._prepared()
        parent = _nearest(rows, self.top)
        labels = np.empty(len(rows), np.int64)
        for t, members in enumerate(_members(parent, len(self.top))):
            if len(members) == 0:
                continue
            ids, ent, ee = prep.cells[t]
            labels[members] = ids[_nearest(rows[members], ent, ee)]
        return labels

    def _search_probes(self, rows: np.ndarray) -> np.ndarray:
        """The nearest entry among the children of each row's `probes` nearest top centroids (ties: the nearer
        top centroid's entry)."""
        prep = self._prepared()
        probes = min(self.probes, len(self.top))
        near = _nearest_cells(rows, self.top, prep.top_norms, probes)
        labels = np.zeros(len(rows), np.int64)
        best = np.full(len(rows), np.inf, np.float32)
        rr = np.einsum("ij,ij->i", rows, rows)
        for p in range(probes):
            for t, members in enumerate(_members(near[:, p], len(self.top))):
                if len(members) == 0:
                    continue
                ids, ent, ee = prep.cells[t]
                d = rows[members] @ ent.T
                d *= -2.0
                d += ee[None, :]
                j = np.argmin(d, axis=1)
                dist = d[np.arange(len(members)), j] + rr[members]
                better = dist < best[members]
                best[members[better]] = dist[better]
                labels[members[better]] = ids[j[better]]
        return labels


@dataclass
class _Prepared:
    by_hash: np.ndarray        # entry indices in order of their row hash
    sorted_hashes: np.ndarray  # those hashes
    exact_keys: bool           # two distinct entries share a hash: look rows up by their exact keys
    cells: list[tuple[np.ndarray, np.ndarray, np.ndarray]]  # per top cell: entry ids, entry rows, squared norms
    top_norms: np.ndarray


def _nearest_cells(rows: np.ndarray, top: np.ndarray, tt: np.ndarray, probes: int) -> np.ndarray:
    """(N, probes) the `probes` nearest top centroids of every row, nearest first (ties: the lower index)."""
    near = np.empty((len(rows), probes), np.int64)
    for i in range(0, len(rows), ASSIGN_BLOCK):
        d = rows[i:i + ASSIGN_BLOCK] @ top.T
        d *= -2.0
        d += tt[None, :]
        at = np.arange(len(d))
        for p in range(probes):  # argmin, then masked: cheaper than argpartition over 256 cells
            near[i:i + len(d), p] = j = np.argmin(d, axis=1)
            d[at, j] = np.inf
    return near


def _members(labels: np.ndarray, k: int) -> list[np.ndarray]:
    """For each label 0..k-1, the ascending indices of the rows that carry it (one sort, not k scans)."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(k + 1))
    return [order[bounds[t]:bounds[t + 1]] for t in range(k)]


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index of the first occurrence of each distinct row, index into those of every row), through a 64-bit hash
    of each row: a sort of N hashes instead of N rows (np.unique on whole rows held another copy of them, which
    put the encoder's peak above 3x the input). Hash collisions are checked for and fall back to exact rows."""
    _, first, inverse = np.unique(_row_hashes(rows), return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    for i in range(0, len(rows), ASSIGN_BLOCK):
        if not np.array_equal(rows[first[inverse[i:i + ASSIGN_BLOCK]]], rows[i:i + ASSIGN_BLOCK]):
            _, first, inverse = np.unique(_row_keys(rows), return_index=True, return_inverse=True)
            return first, inverse.reshape(-1)
    return first, inverse


def _row_hashes(rows: np.ndarray) -> np.ndarray:
    """A 64-bit FNV-1a hash of each float32 row's bits."""
    words = rows.view(np.uint32)
    h = np.full(len(rows), 0xCBF29CE484222325, np.uint64)
    prime = np.uint64(0x100000001B3)
    for j in range(words.shape[1]):
        h ^= words[:, j]
        h *= prime
    return h


def _row_keys(rows: np.ndarray) -> np.ndarray:
    """Each float32 row as one opaque (void) value, for exact lookups."""
    return rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).reshape(-1)


def _nearest(rows: np.ndarray, centroids: np.ndarray, cc: np.ndarray | None = None) -> np.ndarray:
    """Index of the nearest centroid (squared Euclidean) of every row, computed in blocks (cc: the centroids'
    squared norms, where known)."""
    if len(centroids) == 1:
        return np.zeros(len(rows), np.int64)
    if cc is None:
        cc = np.einsum("ij,ij->i", centroids, centroids)
    out = np.empty(len(rows), np.int64)
    # Blocks of rows sized so the (rows x centroids) distance block stays small: a fixed 32,768 rows against
    # 4,517 entries took 1.8 GB of temporaries per thread (the encoder's peak at 1M splats, preset low).
    step = max(256, min(ASSIGN_BLOCK, DISTANCE_BLOCK_BYTES // (4 * len(centroids))))
    for i in range(0, len(rows), step):
        d = rows[i:i + step] @ centroids.T
        d *= -2.0
        d += cc[None, :]
        out[i:i + step] = np.argmin(d, axis=1)
    return out


def kmeans(rows: np.ndarray, k: int, rng: np.random.Generator, weights: np.ndarray | None = None,
           iterations: int = ITERATIONS, product_seeding: bool = False) -> np.ndarray:
    """k centroids of (weighted) rows by Lloyd's algorithm from a k-means++-style seeding on a sample.
    product_seeding: the seeding's distances from dot products in one matrix product per batch of new centroids,
    as the Lloyd rounds take them (cheaper; slightly other values, so another seeding)."""
    n = len(rows)
    if n <= k:
        return rows.copy()
    sample = max(SAMPLE_PER_CENTROID * k, MIN_SAMPLE)
    if n > sample:
        if weights is None:
            pick = np.sort(rng.choice(n, sample, replace=False))
        else:
            # Importance sampling (with replacement) by sqrt(weight), carrying sqrt(weight) as the weight: the
            # weighted means stay unbiased, and neither the many light rows nor a few heavy ones are lost.
            root = np.sqrt(np.asarray(weights, np.float64))
            pick = np.sort(rng.choice(n, sample, replace=True, p=root / root.sum()))
            weights = root[pick]
        rows = rows[pick]
        n = sample
    w = np.ones(n, np.float32) if weights is None else np.asarray(weights, np.float32)
    # Seeding: farthest-point flavoured (probability ~ weight x squared distance), over a few candidates at once.
    centroids = np.empty((k, rows.shape[1]), np.float32)
    first = rng.choice(n, p=w / w.sum())
    centroids[0] = rows[first]
    d2 = ((rows - centroids[0]) ** 2).sum(axis=1)
    rr = None
    filled = 1
    while filled < k:
        p = w * d2
        total = p.sum()
        take = min(k - filled, max(1, k // 16))
        idx = rng.choice(n, take, replace=False, p=p / total) if total > 0 and np.count_nonzero(p) >= take \
            else rng.choice(n, take, replace=False)
        centroids[filled:filled + take] = rows[idx]
        if product_seeding:
            new = centroids[filled:filled + take]
            nn = np.einsum("ij,ij->i", new, new)
            if rr is None:
                rr = np.einsum("ij,ij->i", rows, rows)
            for i in range(0, n, ASSIGN_BLOCK):
                d = rows[i:i + ASSIGN_BLOCK] @ new.T
                d *= -2.0
                d += nn[None, :]
                d += rr[i:i + ASSIGN_BLOCK, None]
                np.minimum(d2[i:i + ASSIGN_BLOCK], np.maximum(d.min(axis=1), 0.0), out=d2[i:i + ASSIGN_BLOCK])
        else:
            for c in centroids[filled:filled + take]:
                np.minimum(d2, ((rows - c) ** 2).sum(axis=1), out=d2)
        filled += take
    for _ in range(iterations):
        labels = _nearest(rows, centroids)
        sums = np.zeros_like(centroids)
        np.add.at(sums, labels, rows * w[:, None])
        mass = np.bincount(labels, weights=w, minlength=k).astype(np.float32)
        live = mass > 0
        centroids[live] = sums[live] / mass[live, None]
        if not live.all():  # re-seed empty cells at the rows worst served
            err = ((rows - centroids[labels]) ** 2).sum(axis=1) * w
            centroids[~live] = rows[np.argsort(-err)[: int((~live).sum())]]
    return centroids


def probes_for(entries: int) -> int:
    """Top cells a row searches in the encoder's codebooks: 2 above FINE_CAP entries (the "large" codebook), else 1."""
    return LARGE_PROBES if entries > FINE_CAP else 1


def build_codebook(rows: np.ndarray, entries: int, weights: np.ndarray | None = None, seed: int = 0,
                   probes: int = 1, progress: Callable[[float], None] | None = None) -> Codebook:
    """Fit a codebook of at most `entries` rows to (N, D) rows (weights: importance of each row, e.g. opacity).
    Rows with at most `entries` distinct values get those values as the codebook, bit for bit (flat or tree).
    probes > 1 (a tree codebook only): after the tree's fit, one Lloyd round over every distinct row assigned among
    the entries of its `probes` nearest top cells, and later assignments search those cells too. `progress` hears
    the share of the fit done (a tree codebook: after its top cells, then by the rows of each cell fitted), the
    result unchanged."""
    rows = np.ascontiguousarray(rows, np.float32)
    if rows.ndim != 2 or len(rows) == 0:
        raise ValueError("build_codebook needs a non-empty (N, D) array")
    if not 1 <= entries <= MAX_ENTRIES:
        raise ValueError(f"entries must be 1..{MAX_ENTRIES}")
    rng = np.random.default_rng(seed)
    first, inverse = _unique_rows(rows)
    if len(first) == len(rows):  # all distinct (real scenes): no copy, each row its own weight
        uniq = rows
        uw = np.ones(len(rows), np.float32) if weights is None else np.asarray(weights, np.float64).astype(np.float32)
    else:
        uniq = rows[first]
        uw = np.bincount(inverse, weights=None if weights is None else np.asarray(weights, np.float64),
                         minlength=len(uniq)).astype(np.float32)
    if weights is not None:
        uw = np.maximum(uw, 1e-12)
    if len(uniq) * entries <= FLAT_LIMIT:  # (a palette that fits is kept exactly: kmeans returns its rows)
        flat = kmeans(uniq, min(entries, len(uniq)), rng, uw, iterations=2 * ITERATIONS).astype(np.float32)
        return Codebook(flat, flat, np.arange(len(flat) + 1, dtype=np.int64))
    top_k = int(min(len(uniq), max(1, round(np.sqrt(entries)))))
    # The large codebooks' cells (probes > 1) are fitted cheaper (LARGE_ITERATIONS): their extra round below stands
    # in for the Lloyd rounds left out.
    child_fit = {"iterations": LARGE_ITERATIONS, "product_seeding": True} if probes > 1 else {}
    top = kmeans(uniq, top_k, rng, uw)
    parent = _nearest(uniq, top)
    if len(uniq) <= entries:
        return _palette_codebook(uniq, top, parent, probes)
    # Entries per top cell in proportion to its weighted spread (mass x mean squared distance), at least one,
    # never more than the distinct rows it holds.
    spread = np.zeros(top_k, np.float64)
    np.add.at(spread, parent, uw * ((uniq - top[parent]) ** 2).sum(axis=1))
    counts = np.bincount(parent, minlength=top_k)
    share = _apportion(spread + 1e-12 * counts, counts, entries)
    blocks, starts = [], [0]
    # (the top fit is about a tenth of the time; the cells' fits, by their rows, the rest: a SOG unit's SH palette
    # of 524,288 splats is tens of seconds on a busy 2-core machine, a terminal's bar standing still without this)
    report = progress or (lambda fraction: None)
    report(0.1)
    fitted = 0
    for t, members in enumerate(_members(parent, top_k)):
        k = int(share[t])
        if k == 0 or len(members) == 0:
            block = top[t:t + 1] if len(members) == 0 else uniq[members[:1]]
        else:
            block = kmeans(uniq[members], k, rng, uw[members], **child_fit)
        blocks.append(block.astype(np.float32))
        starts.append(starts[-1] + len(block))
        fitted += len(members)
        report(0.1 + 0.9 * fitted / len(uniq))
    codebook = Codebook(np.concatenate(blocks), top.astype(np.float32), np.array(starts, np.int64), probes=probes)
    if probes > 1:
        # Rows near a top cell's border are fitted to the entries of one cell: one Lloyd round with the search
        # over the nearest cells moves the entries to the rows that will take them (an entry no row takes stays).
        labels = codebook._search_probes(uniq)
        sums = np.zeros(codebook.entries.shape, np.float64)
        np.add.at(sums, labels, uniq * uw[:, None])
        mass = np.bincount(labels, weights=uw, minlength=len(codebook.entries))
        live = mass > 0
        codebook.entries[live] = (sums[live] / mass[live, None]).astype(np.float32)
        codebook._prep = None  # its entries moved
    return codebook


def _palette_codebook(uniq: np.ndarray, top: np.ndarray, parent: np.ndarray, probes: int) -> Codebook:
    """The codebook of rows that hold no more distinct values than it has entries (an input that is itself a
    palette, e.g. a SOG's SH): the distinct rows themselves, bit for bit, grouped by their top cell so the tree
    still serves rows that are not among them (LOD tiles' merged splats). The fit of the cells (and the large
    codebooks' extra Lloyd round, which averages in float) left playbot's 65,536 rows within 1e-7 of an entry but
    only 22 % of them bit-exact, so assignments fell back from the exact lookup to the search."""
    held = np.bincount(parent, minlength=len(top)) > 0
    if not held.all():  # a top cell nearest to none of the rows would have no entries to search: dropped
        top = top[held]
        parent = (np.cumsum(held) - 1)[parent]
    order = np.argsort(parent, kind="stable")
    starts = np.searchsorted(parent[order], np.arange(len(top) + 1))
    return Codebook(np.ascontiguousarray(uniq[order], np.float32), top.astype(np.float32), starts.astype(np.int64),
                    probes=probes)


def _apportion(score: np.ndarray, cap: np.ndarray, total: int) -> np.ndarray:
    """Integers >= 1 (where cap >= 1) summing to at most `total`, roughly proportional to score, each <= cap."""
    share = np.minimum(cap, 1).astype(np.int64)
    budget = total - int(share.sum())
    room = cap - share
    while budget > 0 and room.sum() > 0:
        want = score * (room > 0)
        if want.sum() <= 0:
            want = (room > 0).astype(np.float64)
        extra = np.minimum(room, np.floor(want / want.sum() * budget).astype(np.int64))
        if extra.sum() == 0:  # hand out the remainder one by one to the largest scores with room
            for i in np.argsort(-want)[:budget]:
                if room[i] > 0:
                    extra[i] = 1
        share += extra
        room -= extra
        budget = total - int(share.sum())
    return share
