"""select_near compiled with numba (the `view` extra, or `fast` alone): the same cut as selection.select_near
and selection.select, bit for bit, in a fraction of the time (format_spec/client.md 1.2; BENCHMARKS.md, "Manifest
pages").

selection.select's greedy loop, run as it is written (a queue of candidates by refinement key, then tile id),
needs the numbers of the root and of the children of every tile it takes from the queue, nothing else. Here that
loop and the per-tile numbers (frustum test, sse, projected radius and area, distance: the same operations in the
same order as selection._numbers, so the same bits) are compiled kernels over the tree's arrays, and a tile's
numbers are computed when the loop first needs them: before it takes a tile whose children have none, the children
of every tile in its queue that lack them are computed in one pass. The one thing left to numpy is the refinement
key's log2: numpy's vectorised log2 and the C library's differ in the last bit for about 1 value in 2,000 (438 of
10^6 here), and the keys order the loop and are the cut's priorities, so a key's log2 is numpy's: one np.log2
over the new candidates of each pass (the kernels gather its argument and finish the keys, the same operations as
selection.refinement_keys). The loop pops (key, tile id) pairs, all distinct, so any correct queue pops them in the
order of select's heapq.

The kernels compile on first use or load from numba's cache (cache=True); `warm_up` calls each once on a tiny tree
with the argument types of a real call (the wrapper passes contiguous arrays of fixed dtypes), so that a frame never
compiles. The engine runs it on a worker thread and uses the numpy path until it is done (engine.CompiledSelection).
"""
from __future__ import annotations

import math
import weakref
from itertools import chain

import numpy as np
from numba import njit

from client_gl.stream.selection import (
    INF,
    PartialView,
    Selection,
    SelectionOptions,
    TileView,
    ViewBuffers,
    boxes_in_frustum,
    corner_weights,
    positions,
    select_near_heap,
    view_numbers,
)
from splatstream.camera import Camera
from splatstream.format.manifest import TileArrays, indexable

# error_model: x/0 gives inf or nan as numpy's does, never an exception. nogil=False: the kernels keep the interpreter
# lock. They run on the frame loop, which waits for their answer, so releasing it bought no parallelism; it handed the
# lock to the decode and fetch threads at every call (5-7 a frame), and the frame loop then waited for their Python to
# give it back (the draw set's wall median 0.43-0.79 ms on 0.13-0.15 of CPU beside busy threads, 0.08-0.12 holding it:
# BENCHMARKS.md, "Manifest pages").
_JIT = dict(cache=True, nogil=False, error_model="numpy")
# numpy's ufuncs and copies let the interpreter lock go over this many elements (NPY_BEGIN_THREADS_THRESHOLDED)
_KEEPS_LOCK = 500
# The kernels' `g`, the tree and camera (select_near_compiled builds it): positions in the tuple
_CAM, _CENTRE, _RADIUS, _ERR, _CORNERS, _PLANE_D, _SPLIT, _LO, _HI, _WAS_REFINED, _HIGH, _LOW = range(12)


@njit(inline="always")
def _clip(x, hi):
    """np.clip(x, 0, hi) of one float (NaN stays NaN, as numpy's)."""
    if x != x:
        return x
    if x < 0.0:
        return 0.0
    if x > hi:
        return hi
    return x


@njit(inline="always")
def _tile_numbers(i, g, known, sse, visible, radius_px, area_px, distance, cand):
    """selection._numbers of tile i, operation for operation (elementwise there, so the same bits), and whether it
    is a candidate (select's test: it has children, is visible, and its sse is above its threshold). The tree and
    camera `g` (select_near_compiled builds it) are read in place: unpacking the tuple here made numba count
    references to each of its arrays per tile, 190 ns a tile against 34."""
    rx = g[_CENTRE][i, 0] - g[_CAM][0]
    ry = g[_CENTRE][i, 1] - g[_CAM][1]
    rz = g[_CENTRE][i, 2] - g[_CAM][2]
    focal = g[_CAM][12]
    centre_dist = math.sqrt(rx * rx + ry * ry + rz * rz)
    dist = centre_dist - g[_RADIUS][i]
    ahead = dist > 0
    vis = True
    for p in range(g[_PLANE_D].shape[0]):
        s = g[_PLANE_D][p] + g[_CORNERS][i, 0] * g[_SPLIT][p, 0]
        for k in range(1, 6):
            s = s + g[_CORNERS][i, k] * g[_SPLIT][p, k]
        if not s >= 0:
            vis = False
    depth = rx * g[_CAM][9] + ry * g[_CAM][10] + rz * g[_CAM][11]
    if ahead:
        e = g[_ERR][i] * focal / dist
        rp = g[_RADIUS][i] * focal / (centre_dist if (centre_dist >= 1e-12 or centre_dist != centre_dist) else 1e-12)
        r = rp
    else:
        e = INF
        rp = INF
        r = 0.0
    u = focal * (rx * g[_CAM][3] + ry * g[_CAM][4] + rz * g[_CAM][5]) / depth + g[_CAM][15]
    v = -focal * (rx * g[_CAM][6] + ry * g[_CAM][7] + rz * g[_CAM][8]) / depth + g[_CAM][16]
    w = _clip(u + r, g[_CAM][13]) - _clip(u - r, g[_CAM][13])
    h = _clip(v + r, g[_CAM][14]) - _clip(v - r, g[_CAM][14])
    area = 0.0
    if depth > 0:
        area = w * h
        if area != area:  # np.nan_to_num
            area = 0.0
        elif area == INF:
            area = 1.7976931348623157e308
        elif area == -INF:
            area = -1.7976931348623157e308
    if not ahead:
        area = g[_CAM][17]  # the eye inside the sphere: the whole image
    if not vis:
        area = 0.0
    sse[i] = e
    visible[i] = vis
    radius_px[i] = rp
    area_px[i] = area
    distance[i] = dist
    known[i] = 1
    threshold = g[_LOW] if g[_WAS_REFINED][i] else g[_HIGH]
    cand[i] = 1 if (g[_HI][i] > g[_LO][i] and vis and e > threshold) else 0


@njit(inline="always")
def _log_arg(d):
    """np.maximum(d, 1e-30) of one float (NaN stays NaN): what refinement_keys takes the log2 of."""
    if d != d or d > 1e-30:
        return d
    return 1e-30


@njit(inline="always")
def _finish_keys(m, pending, lg, level, step, sse, prio):
    """refinement_keys of pending[:m], lg[:m] holding numpy's log2 of their _log_arg: level * step + log2, -inf
    where the sse is not finite (the same two operations on the same values as numpy's: the same bits)."""
    for j in range(m):
        c = pending[j]
        if math.isfinite(sse[c]):
            prio[c] = level[c] * step + lg[j]
        else:
            prio[c] = -INF


@njit(**_JIT)
def _seed(head, parents, more_parents, g, kids, known, sse, visible, radius_px, area_px, distance, cand, pending, lg,
          st):
    """The numbers of the tiles `head`, then of `parents` and `more_parents` and their children where they are
    candidates, each tile once: the new candidates into `pending` (their keys are numpy's), their count returned.
    (Two arrays of parents, the engine's last refined and cut tiles as they are: concatenating them let the lock go.)
    Only a candidate's children are ever needed (the loop pops candidates; the cut is the visible children of tiles
    it refined): the last frame's cut tiles that are not candidates now (about one in ten at 250M splats) have
    their children left out. st[4] counts the tiles whose numbers are computed."""
    first, last = g[_LO], g[_HI]
    m = 0
    looked = 0
    parents_from, more_from = head.shape[0], head.shape[0] + parents.shape[0]
    for t in range(more_from + more_parents.shape[0]):
        i = head[t] if t < parents_from else parents[t - parents_from] if t < more_from else more_parents[t - more_from]
        if not known[i]:
            _tile_numbers(i, g, known, sse, visible, radius_px, area_px, distance, cand)
            looked += 1
            if cand[i]:
                pending[m] = i
                lg[m] = _log_arg(distance[i])
                m += 1
        if t < parents_from or not cand[i]:
            continue
        for q in range(first[i], last[i]):
            c = kids[q]
            if known[c]:
                continue
            _tile_numbers(c, g, known, sse, visible, radius_px, area_px, distance, cand)
            looked += 1
            if cand[c]:
                pending[m] = c
                lg[m] = _log_arg(distance[c])
                m += 1
    st[4] += looked
    return m


@njit(inline="always")
def _less(ka, ta, kb, tb, ids):
    """Whether queued tile ta (key ka) comes out before tb: key, then tile id (client.md 1.2: not the position, which
    in a paged tree follows the order its pages arrived in)."""
    return ka < kb or (ka == kb and ids[ta] < ids[tb])


@njit(**_JIT)
def _refine(g, kids, splats_of, cost, prio, known, sse, visible, radius_px, area_px, distance, cand, heap_k, heap_t,
            st, total_a, refd, reflist, max_splats, budget, pending, lg, m_keys, level, step, root, ids):
    """select's greedy loop from where it stopped (st: queue size, splats, budget flag, refined count, tiles looked
    at, whether the root is still to be queued; total_a: the cost; ids: the tile ids, the order of equal keys),
    once the keys of the m_keys candidates pending[:m_keys] are finished (lg: numpy's log2 of their _log_arg).
    Returns 0 when the queue is empty, m > 0
    when it stopped to have the log2 of m new candidates taken (pending[:m], their _log_arg in lg[:m]; the queue's
    top is taken again then), -1 at a NaN key (select's heapq orders those its own way: the caller falls back to
    the numpy path). max_splats < 0, budget NaN: no limit."""
    _finish_keys(m_keys, pending, lg, level, step, sse, prio)
    if st[5]:  # the root, queued first when it is a candidate
        st[5] = 0
        if cand[root]:
            if prio[root] != prio[root]:
                return -1
            heap_k[0], heap_t[0], st[0] = prio[root], root, 1
    first, last = g[_LO], g[_HI]
    size, splats, limited, nref = st[0], st[1], st[2], st[3]
    total = total_a[0]
    status = 0
    while size > 0:
        i = heap_t[0]
        lacking = False
        for q in range(first[i], last[i]):
            if not known[kids[q]]:
                lacking = True
                break
        if lacking:  # the children of every queued tile lacking numbers, in one pass
            m = 0
            for h in range(size):
                t = heap_t[h]
                for q in range(first[t], last[t]):
                    c = kids[q]
                    if not known[c]:
                        _tile_numbers(c, g, known, sse, visible, radius_px, area_px, distance, cand)
                        st[4] += 1
                        if cand[c]:
                            pending[m] = c
                            lg[m] = _log_arg(distance[c])
                            m += 1
            if m:
                status = m
                break
        size -= 1  # pop: the last entry sifted down from the top
        if size > 0:
            lk, lt = heap_k[size], heap_t[size]
            h = 0
            while True:
                c = 2 * h + 1
                if c >= size:
                    break
                if c + 1 < size and _less(heap_k[c + 1], heap_t[c + 1], heap_k[c], heap_t[c], ids):
                    c += 1
                if _less(heap_k[c], heap_t[c], lk, lt, ids):
                    heap_k[h], heap_t[h] = heap_k[c], heap_t[c]
                    h = c
                else:
                    break
            heap_k[h], heap_t[h] = lk, lt
        kid_splats = 0
        kid_cost = 0.0  # whole numbers in float64: exact in any order, so select's bincount sums
        for q in range(first[i], last[i]):
            c = kids[q]
            if visible[c]:
                kid_splats += splats_of[c]
                kid_cost += cost[c]
        new_splats = splats - splats_of[i] + kid_splats
        new_total = total - cost[i] + kid_cost
        if max_splats >= 0 and new_splats > max_splats and new_splats > splats:
            limited = 1
            continue
        if budget == budget and new_total > budget and new_total > total:
            limited = 1
            continue
        refd[i] = 1
        reflist[nref] = i
        nref += 1
        splats, total = new_splats, new_total
        for q in range(first[i], last[i]):
            c = kids[q]
            if cand[c]:  # candidates are visible
                k = prio[c]
                if k != k:
                    status = -1
                    break
                h = size  # push: sifted up
                size += 1
                while h > 0:
                    p = (h - 1) // 2
                    if _less(k, c, heap_k[p], heap_t[p], ids):
                        heap_k[h], heap_t[h] = heap_k[p], heap_t[p]
                        h = p
                    else:
                        break
                heap_k[h], heap_t[h] = k, c
        if status < 0:
            break
    st[0], st[1], st[2], st[3] = size, splats, limited, nref
    total_a[0] = total
    return status


@njit(inline="always")
def _before(pa, da, ta, pb, db, tb, ids):
    """Whether cut tile a comes before b: np.lexsort((ids, distance, -priority))'s order (priority descending,
    then distance, then tile id; NaN after every number, as numpy sorts it)."""
    if pa != pb:
        if pa != pa:
            return False
        if pb != pb:
            return True
        return pa > pb
    if da != db:
        if da != da:
            return False
        if db != db:
            return True
        return da < db
    return ids[ta] < ids[tb]


@njit(**_JIT)
def _cut(first, last, kids, visible, distance, refd, reflist, nref, prio, root, out_t, out_p, tmp_t, tmp_p, ids):
    """The cut: the visible children of refined tiles that were not refined themselves (priority: minus the
    parent's key), and the root unless refined (inf), sorted in the fetch order (_before: priority descending,
    distance, tile id; all distinct, so any correct sort gives the lexsort's order). Returns its size."""
    m = 0
    for r in range(nref):
        i = reflist[r]
        for q in range(first[i], last[i]):
            c = kids[q]
            if visible[c] and not refd[c]:
                out_t[m] = c
                out_p[m] = -prio[i]
                m += 1
    if not refd[root]:
        out_t[m] = root
        out_p[m] = INF
        m += 1
    # a bottom-up merge sort, runs of `width` merged from (src) into (dst), then the roles swapped
    src_t, src_p, dst_t, dst_p = out_t, out_p, tmp_t, tmp_p
    swapped = False  # the sorted runs are in tmp_t, tmp_p
    width = 1
    while width < m:
        lo = 0
        while lo < m:
            mid = min(lo + width, m)
            hi = min(lo + 2 * width, m)
            a, b, k = lo, mid, lo
            while a < mid and b < hi:
                ta, tb = src_t[a], src_t[b]
                if _before(src_p[b], distance[tb], tb, src_p[a], distance[ta], ta, ids):
                    dst_t[k], dst_p[k] = tb, src_p[b]
                    b += 1
                else:
                    dst_t[k], dst_p[k] = ta, src_p[a]
                    a += 1
                k += 1
            while a < mid:
                dst_t[k], dst_p[k] = src_t[a], src_p[a]
                a += 1
                k += 1
            while b < hi:
                dst_t[k], dst_p[k] = src_t[b], src_p[b]
                b += 1
                k += 1
            lo = hi
        src_t, src_p, dst_t, dst_p = dst_t, dst_p, src_t, src_p
        swapped = not swapped
        width *= 2
    if swapped:
        out_t[:m] = src_t[:m]
        out_p[:m] = src_p[:m]
    return m


@njit(inline="always")
def _box_in(c, corners, plane_d, split):
    """Tile c's box against the planes (the same operations in the same order as boxes_in_frustum's: the same
    answer)."""
    for p in range(plane_d.shape[0]):
        s = plane_d[p] + corners[c, 0] * split[p, 0]
        for k in range(1, 6):
            s = s + corners[c, k] * split[p, k]
        if not s >= 0:
            return False
    return True


@njit(inline="always")
def _shown(c, all_known, known, visible, corners, plane_d, split):
    """PartialView.visible_at of tile c: its batch answer where its numbers are computed, else its box alone."""
    if all_known or known[c]:
        return visible[c]
    return _box_in(c, corners, plane_d, split)


# the draw set walk's frame states (selection.draw_set's cover(i), one stack frame a tile being covered)
_ENTER, _REFINED, _STAND_IN = 0, 1, 2


@njit(**_JIT)
def _draw_walk(root, lo, hi, kids, refd, resident, all_known, known, visible, corners, plane_d, split, out, stack,
               stand_ins):
    """selection.draw_set's recursive cover(root), as a loop over an explicit stack (a frame a tile: its state, the
    next child to look at, where its tiles start in `out`, whether a child was covered, whether one is being
    covered). A tile refined is replaced by its visible children when all of them are covered (none visible: by
    nothing), else drawn itself if resident; a tile not refined is drawn if resident, else stood in for by its
    visible children if it has some and all of them are covered (with `stand_ins`; without, not covered). A failed
    cover takes its tiles back out of `out`.
    Returns how many tiles `out` holds (0 when the root is not covered: draw_set's [])."""
    st_i, st_state, st_q, st_mark, st_any = stack[0], stack[1], stack[2], stack[3], stack[4]
    m = 0
    top = 1
    st_i[0], st_state[0] = root, _ENTER
    ok = False  # the answer of the last cover that returned
    waiting = False  # the top frame pushed a child, whose answer is `ok`
    while top > 0:
        f = top - 1
        i = st_i[f]
        state = st_state[f]
        if state == _ENTER:
            st_mark[f] = m
            st_q[f] = lo[i]
            st_any[f] = 0
            if refd[i]:
                st_state[f] = _REFINED
            elif resident[i]:
                out[m] = i
                m += 1
                ok = True
                top -= 1
                waiting = True
                continue
            elif stand_ins:
                st_state[f] = _STAND_IN
            else:  # not covered: the frame below takes the answer
                ok = False
                top -= 1
                waiting = True
                continue
            waiting = False
            continue
        if waiting and not ok:  # a visible child not covered: this try fails
            m = st_mark[f]
            if state == _REFINED and resident[i]:
                out[m] = i
                m += 1
                ok = True
            else:
                ok = False
            top -= 1
            continue  # `waiting` stays: the frame below takes this answer
        # the next visible child, covered in turn
        q = st_q[f]
        end = hi[i]
        while q < end and not _shown(kids[q], all_known, known, visible, corners, plane_d, split):
            q += 1
        if q < end:
            st_q[f] = q + 1
            st_any[f] = 1
            st_i[top], st_state[top] = kids[q], _ENTER
            top += 1
            waiting = False
            continue
        # every visible child covered: refined, the children replace it (even none); standing in, only if any
        ok = state == _REFINED or st_any[f] == 1
        if not ok:
            m = st_mark[f]
        top -= 1
        waiting = True
    return m if ok else 0


@njit(**_JIT)
def _draw_sums(resident, splats, drawn, sums):
    """sums[:] = (tiles resident, their splats, the drawn tiles' splats): whole numbers, so numpy's sums."""
    tiles = 0
    held = 0
    for i in range(resident.shape[0]):
        if resident[i]:
            tiles += 1
            held += splats[i]
    shown = 0
    for k in range(drawn.shape[0]):
        shown += splats[drawn[k]]
    sums[0], sums[1], sums[2] = tiles, held, shown


@njit(**_JIT)
def _take_blocks(keep, parent, lo, hi, kids):
    """_ChildIndex._take_numpy compiled (the same blocks): the blocks of the tiles indexed (`parent`: theirs) taken
    at the kept positions `keep` (new position -> old), in place: each moved tile's block carried to its new
    position, and the block of each kept parent of a tile moved or dropped renumbered, its dropped children taken
    out (the rest in their order, from the block's start). Blocks are disjoint, so taking them one at a time is
    numpy's taking them all at once."""
    n, k = parent.shape[0], keep.shape[0]
    new_of = np.full(n, -1, np.int64)
    for j in range(k):
        new_of[keep[j]] = j
    moved = 0
    for j in range(k):
        moved += keep[j] != j
    src_lo, src_hi = np.empty(moved, np.int64), np.empty(moved, np.int64)
    m = 0
    for j in range(k):  # gathered, then written (numpy's lo[moved] = lo[keep[moved]])
        if keep[j] != j:
            src_lo[m], src_hi[m] = lo[keep[j]], hi[keep[j]]
            m += 1
    m = 0
    for j in range(k):
        if keep[j] != j:
            lo[j], hi[j] = src_lo[m], src_hi[m]
            m += 1
    owner = np.zeros(n, np.uint8)  # the parents (old positions) of the tiles not where they were
    for i in range(n):
        if new_of[i] != i and parent[i] >= 0:
            owner[parent[i]] = 1
    for p in range(n):
        if not owner[p] or new_of[p] < 0:
            continue
        o = new_of[p]
        w = lo[o]
        for q in range(lo[o], hi[o]):
            v = new_of[kids[q]]
            if v >= 0:
                kids[w] = v
                w += 1
        hi[o] = w


@njit(**_JIT)
def _grow_blocks(lo, hi, kids, used, old, n, heads, counts, new_kids):
    """_ChildIndex._grow_numpy compiled (the same blocks): the rows old..n cleared, then the blocks of the new parents
    `heads` (their `counts` children, `new_kids` in order, appended after the `used` entries; kids has room). Returns
    the entries in use after, or -1 where a head had children before (the index is then made anew)."""
    for i in range(old, n):
        lo[i] = 0
        hi[i] = 0
    for j in range(heads.shape[0]):
        if hi[heads[j]] != lo[heads[j]]:
            return -1
    at = used
    for j in range(heads.shape[0]):
        lo[heads[j]] = at
        at += counts[j]
        hi[heads[j]] = at
    for q in range(new_kids.shape[0]):
        kids[used + q] = new_kids[q]
    return used + new_kids.shape[0]


class _ChildIndex:
    """Each tile's children as a block of one array, kids[lo[i]:hi[i]] (in the order of a.children), grown with the
    tree.

    A paged tree grows by appending a page's tiles to storage whose rows below the last length are never written
    again (manifest.grown_arrays): the children of the tiles held before are those they had, plus the new tiles
    whose parent they are. So an adoption appends the blocks of the parents of its new tiles (a tile gaining its
    page's children, and the new tiles' own) and leaves every other block in place: the time of the page's tiles,
    not of the tree held (made again from the parents after every adoption, 0.05 ms a frame on average at 250M
    splats: BENCHMARKS.md, "Manifest pages"). An eviction's kept rows (PagedTree.evict marks them with the arrays
    they were taken from and the positions kept) take the blocks through those positions, and the tree grown from
    them into new storage grows the index as above (_reach); any other tree (another scene) is indexed anew. The
    selection takes a tile's children in any order (its queue pops distinct (key, position) pairs); the
    draw set's walk takes them in draw_set's, the tree's."""

    compact_slack = 1024  # _take compacts where the entries in use exceed twice the tiles by more than this

    def __init__(self) -> None:
        self.held = lambda: None  # the TileArrays last indexed (weak)
        self.store = lambda: None  # their growing storage (weak), and how many of its rows are indexed
        self.n = 0
        self.epoch = 0  # the storage's epoch when indexed (its rows moved in place since: not reached from them)
        # the ids and parents of the tiles indexed (the arrays', not copies: rows below a length never change)
        self.ids, self.parent = np.zeros(0, np.int64), np.zeros(0, np.int64)
        self.lo, self.hi, self.kids = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
        self.used = 0  # entries of kids in use
        self.rebuilds = self.grown = self.taken = self.compacted = 0
        self.given = 0  # growths from grown_arrays' parents given children (_grow)

    def of(self, a: TileArrays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(a.parent)
        if self.held() is not a:
            taken = a.__dict__.get("_taken_from")  # an eviction's kept rows (client_gl/stream/pages.py)
            if taken is not None and self._reach(taken[0]):
                self._take(a, taken[1])
            elif not self._reach(a):
                self._rebuild(a, n)
            self.held = weakref.ref(a)
            store = a.__dict__.get("_growing")
            self.store = weakref.ref(store) if store is not None else (lambda: None)
            self.epoch = a.__dict__.get("_epoch", 0)
            self.n = n
            self.ids, self.parent = getattr(a, "ids", None), a.parent
        return self.lo[:n], self.hi[:n], self.kids[:self.used]

    def _reach(self, a: TileArrays) -> bool:
        """Bring the index to `a` without making it anew where `a` is the arrays indexed or grown from them: the same
        storage grown (its rows below the length indexed never change), or new storage whose first rows are the
        tiles indexed, the same ids under the same parents (the tree grown from an eviction's kept rows, copied into
        storage by the first page after it: made anew, that adoption's cut took 1.2-1.5 ms more; BENCHMARKS.md,
        "Manifest pages"). A tile's children are listed by its entry, so the same ids with the same parents are the
        same children in the same order. False: not reached (the index unchanged)."""
        if self.held() is a:
            return True
        n = len(a.parent)
        store = a.__dict__.get("_growing")
        if n < self.n or store is None:
            return False
        # An eviction moves rows within their storage (take_in_place, counted by its epoch) but leaves the
        # arrays before it their parents and children, all that growing reads: the same storage grows the index
        # from arrays of the epoch indexed. Other storage is compared by its ids and parents, which neither the
        # arrays indexed nor `a` may have had moved since they were made.
        epoch = a.__dict__.get("_epoch")
        if store is self.store():
            if epoch != self.epoch:
                return False
        else:
            indexed = self.store()
            if epoch != store.epoch or (indexed is not None and indexed.epoch != self.epoch) or \
                    self.ids is None or not (np.array_equal(a.ids[:self.n], self.ids) and
                                             np.array_equal(a.parent[:self.n], self.parent)):
                return False
        self._grow(a, n)
        self.held, self.store, self.n, self.epoch = weakref.ref(a), weakref.ref(store), n, epoch
        self.ids, self.parent = getattr(a, "ids", None), a.parent
        return True

    def _take(self, a: TileArrays, keep: np.ndarray) -> None:
        """The index of the arrays indexed taken at positions `keep` (an eviction's kept rows, new position -> old:
        the identity but for the tiles moved into holes; a kept tile's parent kept): each kept tile's block, its
        children kept, renumbered, in the same order (taken_arrays' children). In place, over the blocks that
        change only: the moved tiles' blocks carried to their new positions, and the blocks of the parents of a
        tile moved or dropped renumbered and cut within their room (the blocks of the tiles dropped left unused
        until the index is compacted, _take_compact, when they outnumber the tree). Taking every kept tile's
        block into new arrays took 0.33-0.55 ms of the eviction frame's cut at 15,000-19,000 tiles; made anew from
        the children's tuples, 1.2-1.5 ms (BENCHMARKS.md, "Manifest pages")."""
        n = self.n
        if self.parent is None or len(self.parent) != n or self.used > 2 * n + self.compact_slack:
            new_of = np.full(n, -1, np.int64)
            new_of[keep] = np.arange(len(keep))
            self._take_compact(keep, new_of)
            return
        # compiled: one pass over the tiles, keeping the interpreter lock (the numpy below, _take_numpy, took
        # 0.36-0.43 ms of the eviction frame's cut at 12,000 tiles on the 2-core VM, the most of what made those
        # frames the selection's slowest, and let the lock go at its fills, sorts and copies; BENCHMARKS.md, gil38c)
        _take_blocks(np.ascontiguousarray(keep, np.int64), np.ascontiguousarray(self.parent, np.int64), self.lo,
                     self.hi, self.kids)
        self.taken += 1

    def _take_numpy(self, keep: np.ndarray) -> None:
        """_take's blocks in numpy (not compacting): the reference _take_blocks is tested against."""
        k, n = len(keep), self.n
        new_of = np.full(n, -1, np.int64)
        new_of[keep] = np.arange(k)
        moved = np.flatnonzero(keep != np.arange(k))
        lo, hi = self.lo, self.hi
        lo[moved], hi[moved] = lo[keep[moved]], hi[keep[moved]]
        # the parents (the arrays indexed, whose parents an eviction does not move) of the tiles not where they were
        par = self.parent[np.flatnonzero(new_of != np.arange(n))]
        owners = new_of[np.unique(par[par >= 0])]
        owners = owners[owners >= 0]
        if len(owners):
            start = lo[owners]
            lens = hi[owners] - start
            first = np.cumsum(lens) - lens
            values = new_of[self.kids[np.repeat(start - first, lens) + np.arange(int(lens.sum()))]]
            kept = values >= 0
            owner = np.repeat(np.arange(len(owners)), lens)[kept]
            left = np.bincount(owner, minlength=len(owners))
            before = np.cumsum(left) - left
            self.kids[start[owner] + np.arange(len(owner)) - before[owner]] = values[kept]
            hi[owners] = start + left
        self.taken += 1

    def _take_compact(self, keep: np.ndarray, new_of: np.ndarray) -> None:
        """_take into new arrays, every kept tile's block in order (the unused room of dropped tiles given up)."""
        k = len(keep)
        starts, counts = self.lo[keep], self.hi[keep] - self.lo[keep]
        total = int(counts.sum())
        first = np.cumsum(counts) - counts  # each kept tile's children in the flat list of their old blocks
        at = np.repeat(starts - first, counts) + np.arange(total)
        flat = new_of[self.kids[at]]
        kept = flat >= 0
        owner = np.repeat(np.arange(k), counts)[kept]
        left = np.bincount(owner, minlength=k)
        cap = max(2 * k + 16, len(self.lo))
        lo, hi = np.zeros(cap, np.int64), np.zeros(cap, np.int64)
        np.cumsum(left, out=hi[:k])
        lo[:k] = hi[:k] - left
        self.used = int(hi[k - 1]) if k else 0
        kids = np.zeros(max(len(self.kids), self.used), np.int64)
        kids[:self.used] = flat[kept]
        self.lo, self.hi, self.kids = lo, hi, kids
        self.taken += 1
        self.compacted += 1

    def _rebuild(self, a: TileArrays, n: int) -> None:
        # the blocks from the tuple of children (their order: the draw set's walk visits them so), about 1.2 ms at
        # 21,600 tiles on the 2-core VM, once per tree neither grown nor taken from the last (another scene)
        counts = np.fromiter(map(len, a.children), np.int64, n)
        cap = 2 * n + 16  # room to grow by pages
        self.lo, self.hi, self.kids = (np.zeros(cap, np.int64) for _ in range(3))
        np.cumsum(counts, out=self.hi[:n])
        self.lo[:n] = self.hi[:n] - counts
        self.used = int(self.hi[n - 1]) if n else 0  # the children held (every tile with a parent)
        self.kids[:self.used] = np.fromiter(chain.from_iterable(a.children), np.int64, self.used)
        self.rebuilds += 1

    def _grow(self, a: TileArrays, n: int) -> None:
        old = self.n
        # room for the rows of the arrays' storage (made for the tree's expected size, PagedTree.rows_ahead: doubled
        # with the tree, the new arrays' page faults fell in one frame's cut)
        store = a.__dict__.get("_growing")
        room = len(store.buf["ids"]) if store is not None else 0
        if n > len(self.lo):
            cap = max(2 * n, 16, room)
            for name in ("lo", "hi"):
                grown = np.zeros(cap, np.int64)
                grown[:old] = getattr(self, name)[:old]
                setattr(self, name, grown)
        given = a.__dict__.get("_children_grown")  # grown_arrays' parents given children, from the length indexed
        if given is not None and given[0] == old:  # (the engine's arrays grow once a frame: 0.03-0.04 ms less)
            _, heads, counts, kids = given
            self.given += 1
            self._room_for(len(kids), room)
            # compiled: the blocks of the new parents written keeping the interpreter lock (the numpy below, about 10
            # calls, 0.03 ms median of an adopting frame's cut at 250M splats, let it go at fills and copies over 500
            # entries; BENCHMARKS.md, gil38c)
            used = _grow_blocks(self.lo, self.hi, self.kids, self.used, old, n, np.ascontiguousarray(heads, np.int64),
                                np.ascontiguousarray(counts, np.int64), np.ascontiguousarray(kids, np.int64))
            if used < 0:  # a tile held before with children before and now more (not a page's growth): anew
                self._rebuild(a, n)
            elif len(heads):
                self.used = used
                self.grown += 1
            return
        par = a.parent[old:n]
        at = np.flatnonzero(par >= 0)
        heads, counts = np.unique(par[at], return_counts=True)
        self._grow_numpy(a, old, n, heads, counts, None, room)

    def _room_for(self, more: int, room: int) -> None:
        """kids with room for `more` entries after those in use (doubled: amortised)."""
        if self.used + more > len(self.kids):
            grown = np.zeros(max(2 * (self.used + more), 16, room), np.int64)
            grown[:self.used] = self.kids[:self.used]
            self.kids = grown

    def _grow_numpy(self, a: TileArrays, old: int, n: int, heads: np.ndarray, counts: np.ndarray,
                    kids: np.ndarray | None, room: int) -> None:
        """The rows old..n cleared, then the blocks of the new parents `heads` (their children `kids`, else found
        from a.children), in numpy: the path without grown_arrays' parents, and the reference _grow_blocks is tested
        against."""
        self.lo[old:n] = 0
        self.hi[old:n] = 0
        if not heads.size:
            return
        starts = np.cumsum(counts) - counts
        had = self.hi[heads] - self.lo[heads]
        if had.any():  # a tile held before with children before and now more (not a page's growth): anew
            self._rebuild(a, n)
            return
        if kids is None:
            # each new parent's children in the tree's order (a.children: a page's tiles are new parents' children
            # only)
            of_tile = indexable(a.children).__getitem__
            kids = np.fromiter(chain.from_iterable(map(of_tile, heads.tolist())), np.int64, int(counts.sum()))
        self._room_for(len(kids), room)
        self.kids[self.used:self.used + len(kids)] = kids
        self.lo[heads] = self.used + starts
        self.hi[heads] = self.used + starts + counts
        self.used += len(kids)
        self.grown += 1


_index = _ChildIndex()


def _children(a: TileArrays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi, kids): tile i's children are kids[lo[i]:hi[i]] (_ChildIndex, kept from call to call)."""
    return _index.of(a)


def _f64(x) -> np.ndarray:
    return np.ascontiguousarray(x, np.float64)


def select_near_compiled(a: TileArrays, view: PartialView, cost: np.ndarray, root: int, opts: SelectionOptions,
                         previous_refined: frozenset[int] | np.ndarray = frozenset(), near=(),
                         near_parents=()) -> Selection:
    """selection.select_near's answer (the same Selection), compiled. `near`: tiles to compute the numbers of first,
    as select_near's; `near_parents`: tiles whose children to compute first (the engine gives the last frame's
    refined and cut tiles, a tuple of two arrays: both seeded as they are, not concatenated). Neither changes the
    answer, only how many passes it takes."""
    lo, hi, kids = _children(a)
    n = len(a.parent)
    # the per-tile scratch arrays: the view's buffers (kept from frame to frame by the engine), else new ones; cleared
    # by a kernel that keeps the interpreter lock from here on (the next view's too)
    buf = view.buffers if getattr(view, "buffers", None) is not None else ViewBuffers()
    buf.zero = _zero
    i64, f64, u8 = np.dtype(np.int64), np.dtype(np.float64), np.dtype(np.uint8)
    was = buf.get("was_refined", n, np.dtype(np.bool_), True)
    if len(previous_refined):
        was[positions(previous_refined)] = True
    cam, basis, planes = view.cam, view.basis, view.planes
    eye, right, up, forward = basis
    focal = cam.height / (2.0 * cam.tan_half_fov_y)
    camv = np.array([*eye, *right, *up, *forward, focal, cam.width, cam.height, cam.width / 2.0, cam.height / 2.0,
                     float(cam.width * cam.height)], np.float64)
    high = float(opts.max_sse)
    g = (camv, _f64(a.sphere_center), _f64(a.sphere_radius), _f64(a.geometric_error), _f64(a.box_corners),
         _f64(planes[:, 3]), _f64(view.split if hasattr(view, "split") else corner_weights(planes)), lo, hi, was, high,
         high * opts.hysteresis)
    known, sse, visible, radius_px, area_px, distance = (view.known, view.sse, view.visible, view.radius_px,
                                                         view.area_px, view.distance)
    cand = buf.get("cand", n, u8)  # written for every tile whose numbers are computed, read only for those
    prio = buf.get("prio", n, f64)
    pending = buf.get("pending", n, i64)
    direct = np.asarray(near, np.int64)
    # the root and `near` (small), then each group of parents as it is: concatenating and converting the last
    # frame's refined and cut tiles (over 500) let the interpreter lock go twice
    head = np.concatenate([np.array([root], np.int64), direct])
    if isinstance(near_parents, tuple) and len(near_parents) == 2 and all(
            isinstance(p, np.ndarray) for p in near_parents):
        parents, more_parents = (np.ascontiguousarray(p, np.int64) for p in near_parents)
    else:
        parents, more_parents = np.ascontiguousarray(near_parents, np.int64).reshape(-1), _NO_TILES
    level, step = np.ascontiguousarray(a.level, np.int64), float(view.level_step)
    lg = buf.get("log2", n, f64)  # the new candidates' _log_arg, then numpy's log2 of it (their keys' one term
    # numba's log2 would not give bit for bit)
    splats_of = np.ascontiguousarray(a.splats, np.int64)
    ids = np.ascontiguousarray(a.ids, np.int64)  # ties of key broken by tile id (client.md 1.2)
    # the loop's state: queue size, splats, budget flag, refined tiles, tiles looked at, the root still to be queued
    st = np.array([0, splats_of[root], 0, 0, 0, 1], np.int64)
    m = _seed(head, parents, more_parents, g, kids, known, sse, visible, radius_px, area_px, distance, cand, pending,
              lg, st)
    heap_k, heap_t = buf.get("heap_k", n, f64), buf.get("heap_t", n, i64)
    cost = _f64(cost)
    total = np.array([cost[root]], np.float64)
    refd, reflist = buf.get("refd", n, u8, True), buf.get("reflist", n, i64)
    max_splats = -1 if opts.max_splats is None else int(opts.max_splats)
    budget = math.nan if opts.budget is None else float(opts.budget)
    while True:
        # numpy's log2 (see the module's docstring) in pieces of 500 at most: a ufunc lets the interpreter lock go
        # over more (numpy's threshold; the first pass has about 1,400 at 250M splats). Elementwise: the same bits.
        for s in range(0, m, _KEEPS_LOCK):
            np.log2(lg[s:min(s + _KEEPS_LOCK, m)], out=lg[s:min(s + _KEEPS_LOCK, m)])
        m = _refine(g, kids, splats_of, cost, prio, known, sse, visible, radius_px, area_px, distance, cand, heap_k,
                    heap_t, st, total, refd, reflist, max_splats, budget, pending, lg, m, level, step, root, ids)
        if m <= 0:
            break
    view.looked_at += int(st[4])
    if m < 0:
        return select_near_heap(a, view, cost, root, opts, previous_refined, near)
    # arrays of its own (the scratch arrays are the next selection's): the engine takes them as they are
    nref = int(st[3])
    out_t, out_p = buf.get("out_t", n, i64), buf.get("out_p", n, f64)
    c = _cut(lo, hi, kids, visible, distance, refd, reflist, nref, prio, root, out_t, out_p,
             buf.get("sort_t", n, i64), buf.get("sort_p", n, f64), ids)
    return Selection.of_arrays(out_t[:c].copy(), out_p[:c].copy(), reflist[:nref].copy(), int(st[1]),
                               float(total[0]), bool(st[2]))


@njit(**_JIT)
def _zero(b):
    """b[:] = 0 while holding the interpreter lock (ndarray.fill lets it go over 500 elements): ViewBuffers.zero."""
    for i in range(b.shape[0]):
        b[i] = 0


@njit(**_JIT)
def _fill_ranks(parent, level, resident, cut, root, gap, step):
    """engine._coarse_to_fine's numpy climb, compiled (the same bases in the same order, the same flags): each cut
    tile's rank its position in the cut, every fill_step-th ancestor from fill_gap levels up of each cut tile not
    resident ranked by the first such cut tile, the root -1; the bases ranked, ordered by (level, rank) (no two
    alike: a tile's ancestors are on distinct levels), and the filling flags (ranked, not in the cut). In numpy
    these were about 13 releases of the interpreter lock a frame at 250M splats (arrays over the tree held)."""
    n = parent.shape[0]
    none = n + cut.shape[0]
    rank = np.full(n, none, np.int64)
    for j in range(cut.shape[0]):
        rank[cut[j]] = j
    for j in range(cut.shape[0]):
        at = cut[j]
        if resident[at]:
            continue
        d = 0
        while True:
            at = parent[at]
            d += 1
            if at < 0:
                break
            if d >= gap and (d - gap) % step == 0 and j < rank[at]:
                rank[at] = j
    rank[root] = -1
    m = 0
    for i in range(n):
        m += rank[i] < none
    named = np.empty(m, np.int64)
    order_key = np.empty(m, np.int64)
    filling = np.zeros(n, np.bool_)
    k = 0
    for i in range(n):
        if rank[i] < none:
            named[k] = i
            order_key[k] = level[i] * (none + 1) + rank[i] + 1
            filling[i] = True
            k += 1
    for j in range(cut.shape[0]):
        filling[cut[j]] = False
    return named[np.argsort(order_key)], filling


def coarse_to_fine_compiled(parent: np.ndarray, level: np.ndarray, resident: np.ndarray, cut: np.ndarray,
                            root: int, gap: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """(bases in the wish list's order, filling flags): engine._coarse_to_fine's numpy climb compiled, keeping the
    interpreter lock (tests/test_stream_engine.py checks it against the numpy path)."""
    return _fill_ranks(np.ascontiguousarray(parent, np.int64), np.ascontiguousarray(level, np.int64),
                       np.ascontiguousarray(resident, np.bool_), np.ascontiguousarray(cut, np.int64), int(root),
                       int(gap), int(step))


@njit(**_JIT)
def _boxes_at(idx, corners, plane_d, split):
    """boxes_in_frustum of the tiles at idx (_box_in's test, as the draw walk's _shown)."""
    out = np.empty(idx.shape[0], np.bool_)
    for j in range(idx.shape[0]):
        out[j] = _box_in(idx[j], corners, plane_d, split)
    return out


def boxes_at(corners: np.ndarray, idx: list[int], planes: np.ndarray) -> list[bool]:
    """selection.wide_visible's box test (boxes_in_frustum of corners[idx]: the same answer) keeping the interpreter
    lock: numpy's took the rows and tested them in a dozen calls over idx * 6 elements, each letting the lock go
    (the prefetch's, a frame that prefetches)."""
    if not idx:
        return []
    return _boxes_at(np.array(idx, np.int64), _f64(corners), _f64(planes[:, 3]), _f64(corner_weights(planes))).tolist()


@njit(**_JIT)
def _grown(state, n):
    """state's rows then zeros, n rows in all (engine._adopt's per-tile state grown by a page's tiles): np.concatenate
    and np.zeros over the tree held let the interpreter lock go, 7 times an adoption at 250M splats."""
    out = np.zeros(n, state.dtype)
    for i in range(state.shape[0]):
        out[i] = state[i]
    return out


@njit(**_JIT)
def _slot_cost(slots, slot_bytes):
    """slots.astype(np.float64) * slot_bytes (the same bits: the same conversion and product), keeping the lock."""
    out = np.empty(slots.shape[0], np.float64)
    for i in range(slots.shape[0]):
        out[i] = float(slots[i]) * slot_bytes
    return out


def grown(state: np.ndarray, n: int) -> np.ndarray:
    """A new array: `state` (bool or int64) then zeros, `n` rows, made keeping the interpreter lock."""
    return _grown(state, int(n))


def slot_cost(slots: np.ndarray, slot_bytes: float) -> np.ndarray:
    """slots (int64) * slot_bytes as float64, made keeping the interpreter lock."""
    return _slot_cost(slots, float(slot_bytes))


@njit(**_JIT)
def _move_rows(rows, moved, src):
    """rows[moved] = rows[src] over rows of words, the source rows read before any is written (numpy's order):
    straight where every target comes before every source (an eviction's holes and the tiles after the new end),
    else through a copy of the source rows."""
    m, w = moved.shape[0], rows.shape[1]
    apart = True
    if m:
        hi, lo = moved[0], src[0]
        for i in range(m):
            hi = max(hi, moved[i])
            lo = min(lo, src[i])
        apart = hi < lo
    if apart:
        for i in range(m):
            d, s = moved[i], src[i]
            for j in range(w):
                rows[d, j] = rows[s, j]
        return
    taken = np.empty((m, w), rows.dtype)
    for i in range(m):
        taken[i] = rows[src[i]]
    for i in range(m):
        rows[moved[i]] = taken[i]


def move_rows(buf: np.ndarray, moved: np.ndarray, src: np.ndarray) -> None:
    """buf[moved] = buf[src] (rows of any dtype and shape), keeping the interpreter lock: an eviction's moves of the
    tiles kept into the holes (PagedTree.evict's arrays, the engine's per-tile state), where numpy's fancy
    assignment let it go once for each of 18 arrays a pass (BENCHMARKS.md, "Manifest pages", evict38). The rows
    seen as 8-, 4- or 1-byte words: three kernel signatures for every dtype, so that no frame compiles one."""
    if not len(moved):
        return
    if not buf.flags.c_contiguous or buf.dtype.hasobject:
        buf[moved] = buf[src]
        return
    row = buf.itemsize * (buf.size // len(buf))
    word = np.uint64 if row % 8 == 0 else np.uint32 if row % 4 == 0 else np.uint8
    if moved.dtype != np.int64 or not moved.flags.c_contiguous:
        moved = np.ascontiguousarray(moved, np.int64)
    if src.dtype != np.int64 or not src.flags.c_contiguous:
        src = np.ascontiguousarray(src, np.int64)
    _move_rows(buf.view(word).reshape(len(buf), -1), moved, src)


_NO_TILES = np.zeros(0, np.int64)
_NO_PLANES = (np.zeros(1, np.uint8), np.zeros(0, np.float64), np.zeros((0, 6), np.float64), np.zeros((1, 6)))


def draw_set_compiled(a: TileArrays, view: PartialView | TileView, sel: Selection, resident: np.ndarray,
                      root: int, sums: np.ndarray | None = None, stand_ins: bool = True) -> np.ndarray:
    """selection.draw_set's tiles (the same, in the same order) as an array of positions, compiled: the Python walk
    was about 1 ms a frame at 250M splats (500 tiles, 700 one-tile box tests; BENCHMARKS.md, "Manifest pages").
    A PartialView's tiles without numbers are box-tested alone, as its visible_at does. `sums` (3 int64): set to
    the tiles resident, their splats and the drawn tiles' splats (what the engine reports a frame; numpy's
    boolean mask and sums over the tree held were 0.04 ms of it at 21,600 tiles)."""
    lo, hi, kids = _children(a)
    n = len(a.parent)
    # the refined tiles' flags: the view's buffers where it has them (cleared by _zero; np.zeros over the tree held
    # let the interpreter lock go, once a frame)
    buf = getattr(view, "buffers", None)
    refd = np.zeros(n, np.uint8) if buf is None else buf.get("draw_refd", n, np.dtype(np.uint8), True)
    refd[sel.refined_at] = 1
    known = getattr(view, "known", None)
    if known is None:  # a TileView: every tile's numbers are there
        all_known = True
        known, plane_d, split, corners = _NO_PLANES
    else:
        all_known = False
        plane_d, split, corners = _f64(view.planes[:, 3]), _f64(view.split), _f64(a.box_corners)
    out = np.empty(n, np.int64)
    m = _draw_walk(root, lo, hi, kids, refd, np.ascontiguousarray(resident, np.bool_), all_known, known,
                   np.ascontiguousarray(view.visible, np.bool_), corners, plane_d, split, out,
                   np.empty((5, n + 1), np.int64), stand_ins)
    drawn = out[:m]
    if sums is not None:
        _draw_sums(np.ascontiguousarray(resident, np.bool_), np.ascontiguousarray(a.splats, np.int64), drawn, sums)
    return drawn


def warm_up() -> None:
    """Compile (or load from the cache) every kernel with a real call's argument types, on a tree of three tiles."""
    parent = np.array([-1, 0, 0], np.int64)
    centre = np.array([[0.0, 0.0, 0.0], [-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    box_min, box_max = centre - 0.5, centre + 0.5
    a = _Tiny(parent, np.array([0, 1, 1], np.int64), np.array([100, 100, 100], np.int64), centre,
              np.array([0.9, 0.5, 0.5]), np.array([1.0, 0.0, 0.0]), np.concatenate([box_max, box_min], axis=1))
    cam = Camera((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 60.0, 64, 48, near=0.01)
    view = PartialView(a, cam, SelectionOptions())
    sel = select_near_compiled(a, view, np.array([1.0, 1.0, 1.0]), 0, SelectionOptions(max_splats=1000, budget=9.0),
                               frozenset({0}), [1], [0])
    assert sel.refined == frozenset({0}), sel
    resident = np.array([True, True, False])
    sums = np.zeros(3, np.int64)
    _zero(np.zeros(4, np.uint8))
    assert draw_set_compiled(a, view, sel, resident, 0, sums).tolist() == [0]  # child 2 not resident: the root drawn
    assert sums.tolist() == [2, 200, 100], sums
    assert draw_set_compiled(a, view_numbers(a, cam), sel, resident, 0).tolist() == [0]
    assert draw_set_compiled(a, view, sel, resident, 0, sums, False).tolist() == [0]
    base, filling = coarse_to_fine_compiled(parent, a.level, np.array([True, False, False]), np.array([1, 2]), 0, 1, 1)
    assert boxes_at(a.box_corners, [0, 2], view.planes) == boxes_in_frustum(None, None, view.planes,
                                                                           a.box_corners[[0, 2]]).tolist()
    assert grown(np.array([True]), 2).tolist() == [True, False] and grown(parent, 4).tolist() == [-1, 0, 0, 0]
    assert slot_cost(parent, 2.0).tolist() == [-2.0, 0.0, 0.0]
    for dtype in (np.float32, np.int16, np.uint8):  # 8-, 4- and 1-byte words; targets apart from sources or not
        rows = np.arange(6, dtype=dtype).reshape(3, 2)
        move_rows(rows, np.array([0], np.int64), np.array([2], np.int64))
        move_rows(rows, np.array([1, 2], np.int64), np.array([2, 1], np.int64))
        assert rows.tolist() == [[4, 5], [4, 5], [2, 3]], rows
    assert base.tolist() == [0, 1, 2] and filling.tolist() == [True, False, False], (base, filling)
    lo, hi, kids = np.array([0, 2, 2]), np.array([2, 2, 2]), np.array([1, 2])  # tile 1 dropped, 2 moved into its row
    _take_blocks(np.array([0, 2], np.int64), parent, lo, hi, kids)
    assert (lo[:2].tolist(), hi[:2].tolist(), kids[:1].tolist()) == ([0, 2], [1, 2], [1]), (lo, hi, kids)
    lo, hi, kids = np.array([0, 0, 9, 9]), np.array([1, 0, 9, 9]), np.array([1, 0, 0])  # tile 1 given children 2, 3
    assert _grow_blocks(lo, hi, kids, 1, 2, 4, np.array([1], np.int64), np.array([2], np.int64),
                        np.array([2, 3], np.int64)) == 3
    assert (lo.tolist(), hi.tolist(), kids.tolist()) == ([0, 1, 0, 0], [1, 3, 0, 0], [1, 2, 3]), (lo, hi, kids)


class _Tiny:
    """The few TileArrays fields the compiled selection, its draw set, PartialView and view_numbers read (warm_up's
    tree)."""

    def __init__(self, parent, level, splats, centre, radius, err, corners):
        self.parent, self.level, self.splats, self.sphere_center = parent, level, splats, centre
        self.ids = np.arange(len(parent), dtype=np.int64)
        self.children = tuple(tuple(np.flatnonzero(parent == i).tolist()) for i in range(len(parent)))
        self.sphere_radius, self.geometric_error, self.box_corners = radius, err, corners
