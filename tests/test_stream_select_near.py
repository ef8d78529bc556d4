"""The selection near the cut (select_near over a PartialView, what the engine runs each frame: the greedy loop as
one scan in key order) against the whole-tree reference (select over view_numbers) and the heap loop over the same
tiles (select_near_heap): the same cut, refined set, priorities, splats, cost and budget
flag, the same draw set and prefetch, on many random views, budgets and trees, paged ones with pages arriving and
being dropped, whatever tiles it is told to look at first. Each test runs twice: the numpy path, and the compiled one
(selection_jit.select_near_compiled, the optional `fast` extra: skipped where numba is not installed), which must
give the same Selection and the same bits of every number it computed."""
import gc
import math
import random
import sys
import weakref
from concurrent.futures import Future
from dataclasses import replace

import numpy as np
import pytest
from conftest import ROOT, real
from test_stream_engine import CountingPool, PagedFetcher, orbit

from client_gl.stream.engine import COMPILED_SELECTION, StreamEngine, StreamOptions
from client_gl.stream.pages import PagedTree
from client_gl.stream.selection import (
    SELECTION_BUFFERS,
    PartialView,
    Selection,
    SelectionOptions,
    ViewBuffers,
    boxes_in_frustum,
    draw_set,
    prefetch,
    select,
    select_near,
    select_near_heap,
    view_numbers,
    wanted_bands,
    wanted_bands_at,
)
from splatstream.camera import Camera
from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.format.manifest import parse_manifest, split_pages
from splatstream.ply import read_gaussians_ply
from splatstream.store import read_manifest

try:
    from client_gl.stream import selection_jit
    from client_gl.stream.selection_jit import _children, draw_set_compiled, select_near_compiled
except ImportError:  # numba is an optional extra (`fast`): the compiled half of each test is skipped without it
    select_near_compiled = _children = selection_jit = draw_set_compiled = None

NEEDS_NUMBA = pytest.mark.skipif(select_near_compiled is None,
                                 reason="the compiled selection needs the package numba (extra `fast`)")
PATHS = ["numpy", pytest.param("compiled", marks=NEEDS_NUMBA)]


@pytest.fixture(scope="module")
def whole():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    m = read_manifest(encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=200)))
    assert m.levels >= 5
    return m


# one set of view arrays for every check, as the engine keeps one from frame to frame: each view finds what the last
# left there (other trees, other sizes)
BUFFERS = ViewBuffers()


def test_view_buffers_are_kept_grown_and_zeroed_where_asked():
    b = ViewBuffers()
    x = b.get("x", 5, np.dtype(np.float64), True)
    assert x.tolist() == [0.0] * 5
    x[:] = 7.0
    again = b.get("x", 3, np.dtype(np.float64))
    assert again.tolist() == [7.0] * 3 and np.shares_memory(again, x)  # the same array, not zeroed
    assert b.get("x", 4, np.dtype(np.float64), True).tolist() == [0.0] * 4
    grown = b.get("x", 6, np.dtype(np.float64))  # more than held: a new array, grown ahead, zeros
    assert grown.tolist() == [0.0] * 6 and not np.shares_memory(grown, x)
    assert len(b.get("x", 10, np.dtype(np.float64))) == 10 and np.shares_memory(b.get("x", 10, np.dtype(np.float64)),
                                                                                 grown)
    assert b.get("x", 2, np.dtype(np.uint8)).dtype == np.uint8  # another dtype: another array
    # made for `ahead` elements at first (a paged tree's expected size): the same array up to it, then doubled
    b = ViewBuffers(ahead=100)
    first = b.get("y", 5, np.dtype(np.int64), True)
    assert first.tolist() == [0] * 5
    first[:] = 3
    kept = b.get("y", 100, np.dtype(np.int64))
    assert np.shares_memory(kept, first) and kept[:5].tolist() == [3] * 5
    assert b.get("y", 50, np.dtype(np.int64), True).tolist() == [0] * 50
    more = b.get("y", 101, np.dtype(np.int64))
    assert not np.shares_memory(more, first) and more.tolist() == [0] * 101
    assert len(b._arrays["y"]) == 200


def test_prepared_view_buffers_are_what_get_would_first_make():
    """ViewBuffers.prepare (the engine's set-up) makes each array of the layout as a first `get` would: zeros of
    max(n, ahead) elements, that `get` then returns (the same memory) up to that size; an array already made is
    kept."""
    b = ViewBuffers(ahead=100)
    kept = b.get("sse", 3, np.dtype(np.float64), True)
    kept[:] = 2.0
    b.prepare(40)
    assert {name for name, _ in SELECTION_BUFFERS} <= b._arrays.keys()
    assert np.shares_memory(b.get("sse", 3, np.dtype(np.float64)), kept)  # made before: kept, not zeroed
    assert b.get("sse", 3, np.dtype(np.float64)).tolist() == [2.0] * 3
    for name, dtype in SELECTION_BUFFERS:
        if name == "sse":
            continue
        made = b._arrays[name]
        assert made.dtype == dtype and len(made) == 100 and not made.any()
        assert np.shares_memory(b.get(name, 100, dtype, True), made)
    small = ViewBuffers()
    small.prepare(40)
    assert all(len(a) == 40 for a in small._arrays.values())


@NEEDS_NUMBA
def test_a_selection_over_prepared_buffers_makes_no_array_there(whole):
    """Every array a PartialView, the compiled selection and its draw set take from their ViewBuffers is one
    `prepare` made (SELECTION_BUFFERS names them all): the first frame's selection allocates none of them, and
    selects as over new buffers."""
    a, root = whole.arrays, whole.index_of[whole.root]
    cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
    cam, opts = random_camera(whole, random.Random(11)), SelectionOptions(max_splats=200_000)
    b = ViewBuffers()
    b.prepare(len(a.parent))
    made = dict(b._arrays)
    view = PartialView(a, cam, opts, whole.lod.reduction, b)
    got = select_near_compiled(a, view, cost, root, opts)
    draw_set_compiled(a, view, got, np.ones(len(a.parent), bool), root)
    assert b._arrays.keys() == made.keys() and all(b._arrays[k] is made[k] for k in made)
    assert got == select_near_compiled(a, PartialView(a, cam, opts, whole.lod.reduction, ViewBuffers()), cost, root,
                                       opts)


def test_view_buffers_zero_with_the_kernel_they_are_given():
    """ViewBuffers.zero (the compiled selection's kernel, which keeps the interpreter lock) clears the array's bytes
    where ndarray.fill would: the same zeros, whatever the dtype."""
    b = ViewBuffers()
    cleared = []
    b.zero = lambda raw: (cleared.append((raw.dtype, len(raw))), raw.fill(0))
    x = b.get("x", 5, np.dtype(np.float64), True)  # a new array: zeros already, nothing to clear
    x[:] = 7.0
    assert b.get("x", 4, np.dtype(np.float64), True).tolist() == [0.0] * 4 and x[4] == 7.0
    assert cleared == [(np.dtype(np.uint8), 32)]  # the four float64's bytes
    if selection_jit is not None:
        b.zero = selection_jit._zero
        for dtype, garbage in ((np.float64, -1.5), (np.bool_, True), (np.uint8, 9), (np.int64, -3)):
            y = b.get(f"y{dtype.__name__}", 1000, np.dtype(dtype), True)
            y[:] = garbage
            again = b.get(f"y{dtype.__name__}", 999, np.dtype(dtype), True)
            assert np.shares_memory(again, y) and not again.any() and y[999] == garbage


@NEEDS_NUMBA
def test_the_compiled_selection_clears_its_buffers_with_its_kernel(whole):
    """select_near_compiled sets its view's ViewBuffers.zero to its kernel: the next view's arrays are cleared by it
    (the same zeros: a tile's numbers are computed again, none left from the last view)."""
    a, root = whole.arrays, whole.index_of[whole.root]
    cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
    rnd = random.Random(5)
    b = ViewBuffers()
    assert b.zero is None
    for _ in range(3):
        cam, opts = random_camera(whole, rnd), SelectionOptions(max_splats=200_000)
        part = PartialView(a, cam, opts, whole.lod.reduction, b)
        assert not part.known.any() and not part.visible.any() and not part.area_px.any()
        got = select_near_compiled(a, part, cost, root, opts)
        assert b.zero is selection_jit._zero
        assert got == select(a, view_numbers(a, cam, opts), cost, root, opts, frozenset(), whole.lod.reduction)


def random_camera(m, rnd: random.Random) -> Camera:
    root = m.tiles[m.index_of[m.root]]
    c, r = np.array(root.sphere_center), root.sphere_radius
    d = np.array([rnd.gauss(0, 1) for _ in range(3)])
    eye = c + d / np.linalg.norm(d) * r * rnd.choice([0.05, 0.3, 0.7, 1.0, 1.5, 3.0, 8.0])
    target = c + np.array([rnd.gauss(0, 0.5 * r) for _ in range(3)])
    size = rnd.choice([(320, 240), (640, 360), (1920, 1080)])
    return Camera(tuple(eye), tuple(target), (0.0, 0.0, 1.0), rnd.choice([30.0, 60.0, 90.0]), *size,
                  near=0.01 * r)


def random_options(m, rnd: random.Random, cost) -> SelectionOptions:
    splats = m.tiles[m.index_of[m.root]].splats
    return SelectionOptions(max_sse=rnd.choice([0.0, 0.5, 1.5, 4.0, 20.0]),
                            max_splats=rnd.choice([None, splats, 2 * splats, 5 * splats, 40 * splats]),
                            budget=rnd.choice([None, float(cost.sum()) * rnd.choice([0.01, 0.1, 0.5])]),
                            hysteresis=rnd.choice([0.8, 0.5, 1.0]))


def check_same(m, cam, opts, previous, near, resident, rnd, path="numpy", near_parents=()):
    """select_near (told to look at `near` first) against select, and draw_set and prefetch with either view; with
    path "compiled", select_near_compiled (also told to look at the children of `near_parents` first)."""
    a = m.arrays
    root = m.index_of[m.root]
    cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
    full = view_numbers(a, cam, opts)
    want = select(a, full, cost, root, opts, previous, m.lod.reduction)
    part = PartialView(a, cam, opts, m.lod.reduction, BUFFERS)  # arrays the last check's view left (the engine's)
    # the engine hands the last refined tiles over as an array (Selection.refined_at), the references a frozenset
    previous_at = np.array(sorted(previous), np.intp)
    if path == "compiled":
        got = select_near_compiled(a, part, cost, root, opts, previous_at, near, near_parents)
        assert got == select_near(a, PartialView(a, cam, opts, m.lod.reduction), cost, root, opts, previous, near)
        # the children's index (grown with a paged tree, else made anew) is the tree's
        lo, hi, kids = _children(a)
        assert [tuple(kids[lo[i]:hi[i]].tolist()) for i in range(len(m.tiles))] == list(a.children)
    else:
        got = select_near(a, part, cost, root, opts, previous_at, near)
        # the heap loop over the same set (select_near_heap), the scan's second reference
        assert select_near_heap(a, PartialView(a, cam, opts, m.lod.reduction), cost, root, opts, previous,
                                near) == got
    assert got.cut == want.cut  # the same tiles in the same order
    assert got.refined == want.refined and got.priority == want.priority
    # the arrays the engine takes are the same selection
    assert got.cut_at.tolist() == list(want.cut) and sorted(got.refined_at.tolist()) == sorted(want.refined)
    assert got.priority_at.tolist() == [want.priority[i] for i in want.cut]
    assert want.cut_at.tolist() == list(want.cut) and sorted(want.refined_at.tolist()) == sorted(want.refined)
    # the SH bands from arrays (the engine's) are wanted_bands' (share 1.0 and below, full detail)
    for o in (opts, SelectionOptions(band_area_share=(1.0, 0.5, 0.0)), SelectionOptions(max_sse=0.0)):
        bands = wanted_bands(a, full, want.cut, o, m.sh_degree)
        assert wanted_bands_at(a, part, got.cut_at, o, m.sh_degree).tolist() == [bands[i] for i in want.cut]
    assert (got.splats, got.cost, got.budget_limited) == (want.splats, want.cost, want.budget_limited)
    known = np.frombuffer(bytes(part.known), np.uint8).astype(bool)
    for name in ("sse", "visible", "radius_px", "area_px", "distance"):  # the same bits where computed
        assert np.array_equal(getattr(part, name)[known], getattr(full, name)[known]), name
    # one tile's box test alone (what the draw set's walk below the cut uses) is the batch's
    some = rnd.sample(range(len(m.tiles)), min(40, len(m.tiles)))
    assert all(part.visible_at(i) == bool(full.visible[i]) for i in some)
    drawn = draw_set(a, part, got, resident, root)
    assert drawn == draw_set(a, full, want, resident, root)
    if draw_set_compiled is not None:  # the compiled draw set: the same tiles in the same order, either view
        assert draw_set_compiled(a, part, got, resident, root).tolist() == drawn
        assert draw_set_compiled(a, full, want, resident, root).tolist() == drawn
    prefetched = prefetch(a, part, got, opts, cost)
    assert prefetched == prefetch(a, full, want, opts, cost)
    if selection_jit is not None:  # the widened frustum's box test compiled: the same tiles
        assert prefetch(a, part, got, opts, cost, selection_jit.boxes_at) == prefetched
        look = random.Random(7).sample(range(len(m.tiles)), min(300, len(m.tiles)))
        assert selection_jit.boxes_at(a.box_corners, look, part.planes) == \
            boxes_in_frustum(None, None, part.planes, a.box_corners[look]).tolist()
    return got, int(known.sum())


@pytest.mark.parametrize("path", PATHS)
def test_select_near_is_the_whole_tree_selection(whole, path):
    m = whole
    rnd, other = random.Random(1), random.Random(2)
    cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
    n = len(m.tiles)
    previous, last = frozenset(), ()
    looked = []
    for step in range(150):
        cam, opts = random_camera(m, rnd), random_options(m, rnd, cost)
        near_kind = step % 3
        near = ([k for i in set(previous) | set(last) for k in m.arrays.children[i]] if near_kind == 0 else
                rnd.sample(range(n), rnd.randrange(n)) if near_kind == 1 else [])
        resident = np.array([rnd.random() < rnd.choice([0.0, 0.3, 0.9]) for _ in range(n)], bool)
        # the compiled path is also told to look below some tiles first (its own random stream: the same views)
        # (step % 4 == 2: as the engine gives them, the last refined and cut tiles as a tuple of two arrays, each
        # seeded as it is)
        parents = (sorted(set(previous) | set(last)) if step % 4 == 0 else
                   other.sample(range(n), other.randrange(n)) if step % 4 == 1 else
                   (np.array(sorted(previous), np.intp), np.array(last, np.intp)) if step % 4 == 2 else [])
        sel, k = check_same(m, cam, opts, previous if rnd.random() < 0.7 else frozenset(
            rnd.sample(range(n), rnd.randrange(n // 4))), near, resident, rnd, path, parents)
        previous, last = sel.refined, sel.cut
        looked.append(k)
    assert min(looked) < n  # some views look at part of the tree only


@pytest.mark.parametrize("path", PATHS)
def test_select_near_when_keys_fall_below_the_parents(whole, path):
    """Spheres that do not nest (a child's reaching nearer the eye than its parent's, as on flat city tiles): select's
    heap then pops such a child right after its parent, out of key order; select_near's scan takes it through its
    small heap at the same turn. Shrunk and shifted spheres make many such children; the cut is still select's."""
    rnd = random.Random(3)
    tiles = []
    for t in whole.tiles:
        shift = np.array([rnd.gauss(0, 0.1 * t.sphere_radius) for _ in range(3)])
        tiles.append(replace(t, sphere_center=tuple(np.array(t.sphere_center) + shift),
                             sphere_radius=t.sphere_radius * rnd.uniform(0.2, 1.0)))
    m = replace(whole, tiles=tuple(tiles))
    a = m.arrays
    cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
    previous, last = frozenset(), ()
    out_of_order = 0
    step_key = 0.5 * math.log2(max(m.lod.reduction, 1.0 + 1e-9))
    for step in range(120):
        cam, opts = random_camera(m, rnd), random_options(m, rnd, cost)
        near = [k for i in set(previous) | set(last) for k in a.children[i]] if step % 2 else []
        resident = np.array([rnd.random() < 0.5 for _ in m.tiles], bool)
        sel, _ = check_same(m, cam, opts, previous, near, resident, rnd, path,
                            sorted(previous | set(last)) if step % 4 == 1 else [])
        full = view_numbers(a, cam, opts)
        with np.errstate(divide="ignore"):
            key = a.level * step_key + np.log2(np.maximum(full.distance, 1e-30))
        key = np.where(np.isfinite(full.sse), key, -np.inf)
        out_of_order += sum(1 for i in sel.refined if i != m.index_of[m.root] and key[i] < key[a.parent[i]])
        previous, last = sel.refined, sel.cut
    assert out_of_order > 20  # refinements out of key order: the scan's small heap made them


@pytest.mark.parametrize("path", PATHS)
def test_select_near_on_a_paged_tree_with_pages_arriving_and_dropped(whole, path, monkeypatch):
    if path == "compiled":  # the children's index compacted at some evictions too (_take_compact)
        monkeypatch.setattr(selection_jit._ChildIndex, "compact_slack", 0)
        compacted = selection_jit._index.compacted
    paged = split_pages(whole, 2)
    assert len(paged.pages) >= 5
    files = {ref.file: raw for ref, raw in paged.pages}
    rnd = random.Random(7)
    tree = PagedTree(paged.root)
    if path == "compiled":
        made, taken = selection_jit._index.rebuilds, selection_jit._index.taken
    previous: frozenset[int] = frozenset()
    last: set[int] = set()
    reads = evictions = 0
    for _ in range(200):
        m = tree.manifest
        cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
        cam, opts = random_camera(m, rnd), random_options(m, rnd, cost)
        children = m.arrays.children
        near = [k for i in previous | last for k in children[i]]
        resident = np.array([rnd.random() < 0.5 for _ in m.tiles], bool)
        sel, _ = check_same(m, cam, opts, previous, near, resident, rnd, path, sorted(previous | last))
        previous, last = sel.refined, set(sel.cut)
        # pages arriving: some the cut reaches, some anywhere; some dropped again
        full = view_numbers(m.arrays, cam, opts)
        wanted = tree.wanted_pages(sel.cut, full.sse, full.visible, opts.max_sse)
        pending = list(tree.pending)
        for tile_id in [k[0] for k in wanted[:3]] + rnd.sample(pending, min(len(pending), rnd.randrange(3))):
            if tile_id in tree.pending:
                tree.add_page(tile_id, files[tree.entry(tile_id).file])
                reads += 1
        held = tree.held_pages()
        if held and rnd.random() < 0.3:
            before = len(tree.manifest.tiles)
            keep = tree.evict(rnd.sample(held, rnd.randrange(1, min(3, len(held)) + 1)))
            evictions += 1
            new_of = np.full(before, -1, np.int64)  # the engine's remapping of its per-tile state
            new_of[keep] = np.arange(len(keep))
            previous = frozenset(int(new_of[i]) for i in previous if new_of[i] >= 0)
            last = {int(new_of[i]) for i in last if new_of[i] >= 0}
    assert reads > 10 and evictions > 10 and tree.evicted > 0
    if path == "compiled":  # the children's index was grown with the tree (and checked against it), not only made anew
        assert selection_jit._index.grown > 10
        assert selection_jit._index.given > 5  # from grown_arrays' parents given children (checked the same)
        # and taken through the kept rows at evictions, then grown from them in new storage: made anew only for the
        # first tree (the root manifest, then the first page's storage)
        taken, made = selection_jit._index.taken - taken, selection_jit._index.rebuilds - made
        print(f"children's index: {taken} taken, {made} made anew, {evictions} evictions")
        assert taken > 5 and made <= 2, (taken, made, evictions)
        compacted = selection_jit._index.compacted - compacted
        assert 0 < compacted < taken, (compacted, taken)  # blocks taken in place, and compacted


@NEEDS_NUMBA
def test_the_childrens_index_is_taken_by_its_kernel_as_by_numpy():
    """_take_blocks (an eviction's kept rows, compiled) against _ChildIndex._take_numpy on random trees and drops:
    the same blocks, and each kept tile's children those of the tree taken (renumbered, in the tree's order)."""
    rnd = random.Random(38)
    checked = moved_total = 0
    for _ in range(60):
        n = rnd.randrange(2, 400)
        parent = np.array([-1] + [rnd.randrange(0, i) for i in range(1, n)], np.int64)
        children = [[] for _ in range(n)]
        for i in range(1, n):
            children[parent[i]].append(i)
        # drop a few subtrees (a kept tile's parent is kept), the last kept tiles moved into the holes
        gone = np.zeros(n, bool)
        for head in rnd.sample(range(1, n), min(n - 1, rnd.randrange(1, 4))):
            stack = [head]
            while stack:
                t = stack.pop()
                gone[t] = True
                stack += children[t]
        kept = np.flatnonzero(~gone)
        k = len(kept)
        keep = np.arange(k)
        holes = [j for j in range(k) if gone[j]]
        keep[holes] = kept[kept >= k]
        moved_total += len(holes)
        index = selection_jit._ChildIndex()
        tiny = type("T", (), {})()
        tiny.children = tuple(tuple(c) for c in children)
        index._rebuild(tiny, n)
        index.n, index.parent = n, parent
        reference = selection_jit._ChildIndex()
        reference.__dict__.update({k_: (v.copy() if isinstance(v, np.ndarray) else v)
                                   for k_, v in index.__dict__.items()})
        reference._take_numpy(keep)
        index._take(tiny, keep)
        assert index.taken == 1 and index.compacted == 0
        assert index.lo[:k].tolist() == reference.lo[:k].tolist() and index.hi[:k].tolist() == reference.hi[:k].tolist()
        new_of = np.full(n, -1, np.int64)
        new_of[keep] = np.arange(k)
        for j in range(k):
            got = index.kids[index.lo[j]:index.hi[j]].tolist()
            assert got == reference.kids[reference.lo[j]:reference.hi[j]].tolist()
            assert got == [int(new_of[c]) for c in children[keep[j]] if new_of[c] >= 0]
            checked += 1
    assert checked > 3000 and moved_total > 20, (checked, moved_total)


@NEEDS_NUMBA
def test_the_childrens_index_grows_by_its_kernel_as_by_numpy(whole):
    """_ChildIndex._grow from grown_arrays' parents (the kernel _grow_blocks) against _grow_numpy given the same
    parents, page after page of a paged tree: the same blocks, entries in use and flags."""
    paged = split_pages(whole, 2)
    files = {ref.file: raw for ref, raw in paged.pages}
    rnd = random.Random(38)
    tree = PagedTree(paged.root)
    index = selection_jit._ChildIndex()
    index.of(tree.manifest.arrays)
    steps = 0
    while tree.pending:
        for tile_id in rnd.sample(sorted(tree.pending), min(len(tree.pending), rnd.randrange(1, 4))):
            tree.add_page(tile_id, files[tree.entry(tile_id).file])
        a = tree.manifest.arrays
        given = a.__dict__.get("_children_grown")
        reference = selection_jit._ChildIndex()
        reference.__dict__.update({k: (v.copy() if isinstance(v, np.ndarray) else v)
                                   for k, v in index.__dict__.items()})
        old, given_before = index.n, index.given
        lo, hi, kids = index.of(a)
        if given is None or given[0] != old:
            continue
        assert index.given == given_before + 1
        for name in ("lo", "hi"):  # as _grow gives both paths: the rows held, room after them (not yet cleared)
            grown = np.full(len(getattr(index, name)), -1, np.int64)
            grown[:old] = getattr(reference, name)[:old]
            setattr(reference, name, grown)
        reference._grow_numpy(a, old, len(a.parent), *given[1:], 0)
        n = len(a.parent)
        assert lo.tolist() == reference.lo[:n].tolist() and hi.tolist() == reference.hi[:n].tolist()
        assert kids.tolist() == reference.kids[:reference.used].tolist() and index.used == reference.used
        assert (index.grown, index.rebuilds) == (reference.grown, reference.rebuilds)
        assert [kids[lo[i]:hi[i]].tolist() for i in range(n)] == [list(c) for c in a.children]
        steps += 1
    assert steps >= 4, steps


@NEEDS_NUMBA
def test_compiled_draw_set_is_draw_sets(whole):
    """selection_jit.draw_set_compiled against draw_set (the numpy reference) on trees whose children are listed in
    shuffled order (the walk's order is the tree's, not the positions'), with refined sets from selections and at
    random (refined tiles that are not candidates, whose children are not visible, below tiles not refined), every
    kind of residency, and both views: a PartialView whose numbers are known for some tiles only (the others
    box-tested alone) and the whole TileView. The same tiles in the same order, every time."""
    rnd = random.Random(11)
    a0 = whole.arrays
    kinds = {"refined and replaced": 0, "refined, drawn itself": 0, "stood in for": 0, "empty": 0}
    for trial in range(6):
        tiles = list(whole.tiles)
        if trial:  # the children of every tile in another order
            tiles = [replace(t, children=tuple(rnd.sample(t.children, len(t.children)))) for t in tiles]
        m = replace(whole, tiles=tuple(tiles))
        a = m.arrays
        root = m.index_of[m.root]
        n = len(m.tiles)
        assert trial == 0 or any(a.children[i] != a0.children[i] for i in range(n))
        lo, hi, kids = _children(a)
        assert [tuple(kids[lo[i]:hi[i]].tolist()) for i in range(n)] == list(a.children)
        cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
        for _ in range(40):
            cam, opts = random_camera(m, rnd), random_options(m, rnd, cost)
            full = view_numbers(a, cam, opts)
            part = PartialView(a, cam, opts, m.lod.reduction, BUFFERS)
            part.ensure(rnd.sample(range(n), rnd.randrange(n + 1)))
            if rnd.random() < 0.5:
                sel = select(a, full, cost, root, opts, frozenset(), m.lod.reduction)
            else:  # any refined set: the walk must follow draw_set's rules wherever they lead
                refined = np.array(rnd.sample(range(n), rnd.randrange(n // 2 + 1)), np.intp)
                sel = Selection.of_arrays(np.zeros(0, np.intp), np.zeros(0), refined, 0, 0.0)
            share = rnd.choice([0.0, 0.1, 0.5, 0.9, 1.0])
            resident = np.array([rnd.random() < share for _ in range(n)], bool)
            for view in (part, full):
                want = draw_set(a, view, sel, resident, root)
                sums = np.full(3, -1, np.int64)
                got = draw_set_compiled(a, view, sel, resident, root, sums)
                assert got.dtype == np.int64 and got.tolist() == want
                # the engine's residency sums, from the same call
                assert sums.tolist() == [int(resident.sum()), int(a.splats[resident].sum()), int(a.splats[want].sum())]
                # without stand-ins (the engine's set over a splat budget): ancestors only, the same way
                held = draw_set(a, view, sel, resident, root, stand_ins=False)
                assert draw_set_compiled(a, view, sel, resident, root, None, False).tolist() == held
                assert int(a.splats[held].sum()) <= int(a.splats[want].sum()) or not held
                top_refined = root in sel.refined
                if not want:
                    kinds["empty"] += 1
                elif top_refined:
                    kinds["refined, drawn itself" if want == [root] else "refined and replaced"] += 1
                elif not resident[root]:
                    kinds["stood in for"] += 1  # the root not loaded: its descendants drawn in its place
    assert all(kinds.values()), kinds


@NEEDS_NUMBA
def test_compiled_selection_falls_back_on_nan_keys(whole):
    """Keys that are NaN (here: a NaN reduction makes every key NaN) have no order in the compiled queue: it hands
    the frame to the numpy path, whose heapq compares them its own way, and the answer is select_near's."""
    m, rnd = whole, random.Random(5)
    a, root = m.arrays, m.index_of[m.root]
    cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
    refined = 0
    for _ in range(10):
        cam, opts = random_camera(m, rnd), random_options(m, rnd, cost)
        got = select_near_compiled(a, PartialView(a, cam, opts, math.nan), cost, root, opts)
        want = select_near(a, PartialView(a, cam, opts, math.nan), cost, root, opts)
        assert (got.cut, got.refined, got.splats, got.cost, got.budget_limited) == \
            (want.cut, want.refined, want.splats, want.cost, want.budget_limited)
        assert list(got.priority) == list(want.priority)  # NaN priorities: equal as arrays, not as floats
        assert np.array_equal(list(got.priority.values()), list(want.priority.values()), equal_nan=True)
        refined += len(got.refined)
    assert refined  # the queue ran (with NaN keys)


def test_dropped_pages_are_freed_when_the_tree_was_frozen(whole):
    """The engine freezes the collector's objects after adding pages (StreamOptions.freeze_pages): a dropped
    page's tiles must still be freed, by reference counting alone (they hold no reference cycles)."""
    paged = split_pages(whole, 2)
    files = {ref.file: raw for ref, raw in paged.pages}
    tree = PagedTree(paged.root)
    head = next(iter(tree.pending))
    tree.add_page(head, files[tree.entry(head).file])
    _ = tree.manifest.arrays
    below = tree.below(head)
    assert below
    refs = [weakref.ref(tree.manifest.tiles[i]) for i in below]
    # their payload entries: a 1.8 tile's are a row of its page's tile table (TablePayloads and Table take no weak
    # references): held here only, checked below to be held by nothing else
    held = list({id(x): x for i in below for g in (tree.manifest.tiles[i].groups,)
                 for x in (g, getattr(g, "table", None)) if x is not None}.values())
    gc.freeze()
    try:
        tree.evict([head])
        _ = tree.manifest.arrays
        assert all(r() is None for r in refs)
        for h in held:  # the list, the loop's name, the call's argument and the held payload maps of the table
            assert sys.getrefcount(h) == 3 + sum(getattr(x, "table", None) is h for x in held)
    finally:
        gc.unfreeze()


class Inline:
    """An executor that runs what it is given at once."""

    def submit(self, fn, *args):
        future = Future()
        try:
            future.set_result(fn(*args))
        except Exception as exc:  # as an executor hands it over
            future.set_exception(exc)
        return future

    def shutdown(self, **_) -> None:
        return None


@pytest.fixture(scope="module")
def paged_store():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    return encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=300, page_tiles=4, page_levels=2))


def test_the_engine_selects_near_the_cut_as_over_every_tile(paged_store):
    """The engine with the selection near the cut from the first tile (select_near_from 0) and over every tile held
    (never near), and near the cut compiled where numba is installed: the same selections, draw sets and fetches
    frame by frame, with pages read and dropped."""
    whole = read_manifest(paged_store)
    root_tiles = len(parse_manifest(paged_store.read_manifest(), "root").tiles)
    opts = StreamOptions(SelectionOptions(max_sse=1.0, band_area_share=(0.95, 0.8, 0.6)),
                         max_tree_tiles=root_tiles + 4)
    top = whole.tiles[0]
    c, r = np.array(top.sphere_center), top.sphere_radius

    def outward(angle):  # from inside the scene, looking out at one side of it (test_stream_engine's views)
        d = np.array([np.cos(angle), np.sin(angle), 0.0])
        return Camera(tuple(c + 0.3 * r * d), tuple(c + 2 * r * d), (0, 0, 1), 40.0, 320, 240, near=0.001 * r)

    cams = [orbit(whole, 2.5, 0.3), outward(0.3), outward(0.3 + np.pi), orbit(whole, 0.8, 1.5), outward(0.3),
            orbit(whole, 0.6, 3.0), outward(2.0), orbit(whole, 3.0, 2.0)]
    runs = []
    ways = [(0, False, None), (1 << 30, False, None)]
    if select_near_compiled is not None:  # and compiled, ready from the first frame (else the numpy path's frames)
        assert COMPILED_SELECTION.wait() is not None, COMPILED_SELECTION.error
        ways += [(0, True, None), (0, True, 1e-4)]  # and with a short switch interval while it selects
    process_interval = sys.getswitchinterval()
    intervals_seen: list[float] = []
    for near_from, compiled, interval in ways:
        if compiled:  # the interval the compiled selection runs under
            fn = COMPILED_SELECTION._fn

            def seen(*args, _fn=fn, **kw):
                intervals_seen.append(sys.getswitchinterval())
                return _fn(*args, **kw)
            COMPILED_SELECTION._fn = seen
        fetcher = PagedFetcher(paged_store)
        engine = StreamEngine(fetcher, CountingPool(26), replace(opts, select_near_from=near_from,
                                                                 compiled_selection=compiled,
                                                                 select_switch_interval=interval))
        engine._pool.shutdown()
        engine._pool = Inline()  # decodes and page parses done when asked for: the frames do not depend on timing
        frames = []
        for cam in cams:
            for _ in range(25):
                u = engine.update(cam)
                frames.append((u.draw, u.selection.cut, u.selection.refined, u.converged))
        runs.append((frames, fetcher.fetched, engine.pages.pages_read, engine.pages.evicted))
        engine.close()
        if compiled:
            COMPILED_SELECTION._fn = fn
            expected = process_interval if interval is None else interval
            assert intervals_seen and all(abs(x - expected) < 1e-9 for x in intervals_seen), intervals_seen
            intervals_seen.clear()
        assert sys.getswitchinterval() == process_interval  # restored after every selection
    assert all(run == runs[0] for run in runs[1:])
    assert runs[0][2] > 3 and runs[0][3] > 0  # pages read and dropped on the way


@NEEDS_NUMBA
def test_moved_rows_are_numpys():
    """selection_jit.move_rows (an eviction's moves into the holes, keeping the interpreter lock) against numpy's
    buf[moved] = buf[src]: every dtype and row shape of the tree's arrays and the engine's state, sources read
    before any row is written (targets among the sources too), a view that is not contiguous."""
    rnd = np.random.default_rng(7)
    for n in (1, 9, 2_000):
        bufs = [rnd.random(n) < 0.5, rnd.integers(-9, 1 << 40, n), rnd.random((n, 3)).astype(np.float32),
                rnd.random((n, 6)), rnd.integers(0, 255, (n, 2), dtype=np.uint8), rnd.integers(0, 9, n, np.int32),
                rnd.random((n, 4))[:, 1]]
        for m in (0, 1, n // 3):
            moved = np.sort(rnd.choice(n, m, replace=False))
            src = rnd.choice(n, m, replace=False)  # overlapping the targets: numpy's order
            for buf in bufs:
                want = buf.copy()
                want[moved] = want[src]
                got = buf.copy() if buf.flags.c_contiguous else buf
                selection_jit.move_rows(got, moved, src)
                assert got.dtype == want.dtype and np.array_equal(got, want)


@NEEDS_NUMBA
def test_an_eviction_with_the_compiled_moves_is_numpys(paged_store):
    """PagedTree.evict with selection_jit.move_rows (the engine's, once the kernels are loaded) against its numpy
    moves: the same random trees give the same tiles, arrays, positions and compaction map."""
    from test_stream_engine import _random_tree, _same_arrays
    for seed in range(6):
        trees = []
        for move in (None, selection_jit.move_rows):
            rnd = random.Random(seed)
            tree = _random_tree(paged_store, rnd, rnd.randrange(8, 30))
            held = tree.held_pages()
            keep = tree.evict(rnd.sample(held, min(3, len(held))), move) if held else None
            trees.append((tree, keep))
        (a, keep_a), (b, keep_b) = trees
        assert [t.id for t in a.manifest.tiles] == [t.id for t in b.manifest.tiles]
        _same_arrays(a.manifest.arrays, b.manifest.arrays)
        assert a.manifest.index_of == b.manifest.index_of
        if keep_a is not None:
            assert np.array_equal(keep_a, keep_b)
            assert all(np.array_equal(x, y) for x, y in zip(a.compaction, b.compaction, strict=True))
            n = len(a.manifest.tiles)
            assert np.array_equal(a._head_at[:n], b._head_at[:n]) and np.array_equal(a._ids[:n], b._ids[:n])


@NEEDS_NUMBA
def test_the_engines_grown_state_is_numpys():
    """selection_jit.grown and slot_cost (engine._adopt's per-tile state grown by a page, keeping the interpreter
    lock) against np.concatenate with zeros and astype * slot bytes: the same dtypes and values, new arrays."""
    rnd = np.random.default_rng(3)
    for n in (0, 1, 700, 20_000):
        for state in (rnd.random(n) < 0.5, rnd.integers(-5, 1 << 40, n, dtype=np.int64)):
            for grow in (0, 1, 613):
                out = selection_jit.grown(state, n + grow)
                want = np.concatenate([state, np.zeros(grow, state.dtype)])
                assert out.dtype == want.dtype and np.array_equal(out, want) and not np.shares_memory(out, state)
        slots = rnd.integers(0, 1 << 20, n, dtype=np.int64)
        for slot_bytes in (256 * 62.0, 1234.5):
            cost = selection_jit.slot_cost(slots, slot_bytes)
            assert cost.dtype == np.float64
            assert cost.tobytes() == (slots.astype(np.float64) * float(slot_bytes)).tobytes()


def test_the_engine_makes_its_view_buffers_before_its_first_frame(paged_store):
    """An engine that selects compiled makes its view's arrays when made (ViewBuffers.prepare, for the tree it
    expects: PagedTree.rows_ahead), not in its first frame's selection; one that does not, none."""
    for compiled in (True, False):
        engine = StreamEngine(PagedFetcher(paged_store), CountingPool(26), StreamOptions(compiled_selection=compiled))
        held = engine._view_buffers._arrays
        if compiled:
            assert held.keys() == {name for name, _ in SELECTION_BUFFERS}
            assert all(len(x) == max(len(engine.resident), engine.pages.rows_ahead) for x in held.values())
            assert engine.pages.rows_ahead > len(engine.resident)
        else:
            assert not held
        engine.close()


def test_the_warm_up_child_leaves_when_its_parent_is_killed(tmp_path):
    """The kernels' warm-up child (engine._WARM_UP) of a viewer killed while it compiles (SIGKILL: no clean-up runs)
    exits instead of compiling on as an orphan. A parent process starts it as CompiledSelection does and is killed at
    once, with numba's cache empty; the child must be gone (or a zombie) within a generous bound, not finish its
    compile first."""
    import os
    import signal
    import subprocess
    import time

    from client_gl.stream import engine

    parent_code = ("import os, subprocess, sys, time\n"
                   f"child = subprocess.Popen([sys.executable, '-c', {engine._WARM_UP!r}, str(os.getpid())])\n"
                   "print(child.pid, flush=True)\n"
                   "time.sleep(600)\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))  # an empty cache: killed while it compiles, the case seen
    parent = subprocess.Popen([sys.executable, "-c", parent_code], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                              env=env)
    child = int(parent.stdout.readline())
    parent.send_signal(signal.SIGKILL)
    parent.wait()

    def alive(pid: int) -> bool:
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False

    for _ in range(600):  # a liveness bound (60 s), not a timing claim: the watch polls every 0.25 s
        if not alive(child):
            break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        raise AssertionError("the warm-up child outlived its killed parent by 60 s")
