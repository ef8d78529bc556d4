"""Pages a budget cannot use are not wanted (issue 31, client.md 1.11): the pure rule
(`selection.pages_the_budget_can_use`) against a hand-built tree, where the whole tree's selection says which heads
the budget refines; and a paged scene streamed over real sockets from `splatstream serve`'s app on loopback, under
a small budget, reading no page none of whose tiles is drawn, to the unpaged scene's cut."""
from __future__ import annotations

import random
from dataclasses import replace

import numpy as np
import pytest
from conftest import real
from test_stream_engine import orbit
from test_stream_pages import _stream
from test_stream_select_near import PATHS, check_same
from test_stream_select_near import whole as whole  # noqa: F401 (the fixture)

from client_gl.stream.engine import StreamOptions
from client_gl.stream.pages import PagedTree
from client_gl.stream.selection import (
    SelectionOptions,
    boxes_in_frustum,
    boxes_inside_frustum,
    frustum_planes,
    pages_the_budget_can_use,
    prefetch,
    select,
    view_numbers,
    wanted_bands,
    wanted_bands_at,
)
from server.testing import ServerThread
from splatstream.camera import Camera
from splatstream.encode import encode_file
from splatstream.format.manifest import TileArrays, split_pages
from splatstream.store import load_manifest

REDUCTION = 2.0
CHUNK = 256


def _tree(parent: list[int], splats: list[int], centre: list[tuple[float, float, float]], half: list[float],
          error: list[float]) -> TileArrays:
    """A tile tree by hand: each tile a cube of half-size `half` around `centre` (children inside their parent)."""
    n = len(parent)
    c = np.array(centre, float)
    h = np.array(half, float)[:, None]
    children = tuple(tuple(k for k in range(n) if parent[k] == i) for i in range(n))
    chunks = -(-np.array(splats) // CHUNK)
    level = [0] * n
    for i in range(n):  # parents come before their children
        level[i] = 0 if parent[i] < 0 else level[parent[i]] + 1
    return TileArrays(
        ids=np.arange(n, dtype=np.int64), parent=np.array(parent, np.int64),
        level=np.array(level, np.int64),
        splats=np.array(splats, np.int64), box_min=c - h, box_max=c + h, sphere_center=c,
        sphere_radius=np.sqrt(3.0) * h[:, 0], geometric_error=np.array(error, float), children=children,
        base_bytes=chunks * 100, band_bytes=np.zeros((n, 3), np.int64), gpu_bytes=chunks * 1000)


# A row of tiles along x in front of the camera: the root (0), two heads (1 near, 2 far: their pages below), and
# each head's two children (3, 4 under 1; 5, 6 under 2), reduction 2: children hold twice their parent's splats.
PARENT = [-1, 0, 0, 1, 1, 2, 2]
SPLATS = [100, 100, 100, 100, 100, 100, 100]
CENTRE = [(0, 0, 0), (-1, 0, 0), (1, 0, 0), (-1.5, 0, 0), (-0.5, 0, 0), (0.5, 0, 0), (1.5, 0, 0)]
HALF = [2.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5]
ERROR = [1.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0]


def _views(cam: Camera):
    whole = _tree(PARENT, SPLATS, CENTRE, HALF, ERROR)
    held = _tree(PARENT[:3], SPLATS[:3], CENTRE[:3], HALF[:3], ERROR[:3])  # the root manifest: heads unread
    return whole, held, view_numbers(whole, cam), view_numbers(held, cam)


def _rule(held, view, opts, cost):
    sel = select(held, view, cost, 0, opts, reduction=REDUCTION)
    heads = np.array([i for i in sel.cut if view.sse[i] > opts.max_sse and view.visible[i]], np.intp)
    now, later = pages_the_budget_can_use(held, view, cost, 0, sel, heads, opts, REDUCTION, CHUNK, 1000.0)
    assert not (now & later).any()
    return sel, heads, now


# the camera on the row's near side, looking along it: head 1 is nearer (refined first), head 2 farther
CAM = Camera(eye=(-12.0, 0.0, 0.5), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=640, height=480)


@pytest.mark.parametrize("budget, wanted", [
    (200, [False, False]),  # the cut (both heads) is the budget: no head's children fit, no page wanted
    (249, [False, False]),  # 49 splats left: the least the children add (0.75 x 2 x 100 - 100 = 50) does not fit
    (250, [True, False]),   # 50 left: head 1's may fit at its turn; head 2's only if head 1's do not: its page
                            # waits (set aside for head 1: its children's likely 200 splats less its 100)
    (300, [True, False]),   # head 1's children fit (the whole tree's cut refines it), head 2's would not after
    (350, [True, True]),    # head 2's may fit after head 1's likely 100 (the whole tree's cut: 400, it does not)
    (None, [True, True]),   # no splat budget (the byte budget is large): every page, as before
])
def test_a_page_is_wanted_where_the_budget_could_let_its_children_in(budget, wanted):
    whole, held, full_view, view = _views(CAM)
    assert view.distance[1] < view.distance[2] and bool(view.visible[1:3].all())
    cost = held.gpu_bytes.astype(float)
    opts = SelectionOptions(max_sse=0.1, max_splats=budget, budget=1e9)
    sel, heads, mask = _rule(held, view, opts, cost)
    assert heads.tolist() == [1, 2] and mask.tolist() == wanted
    # the whole tree's selection refines a head only where its page is wanted (the same cut either way)
    refined = select(whole, full_view, whole.gpu_bytes.astype(float), 0, opts, reduction=REDUCTION).refined
    assert all(m for h, m in zip(heads.tolist(), mask.tolist(), strict=True) if h in refined)
    if budget in (300, 350):
        assert refined == {0, 1}  # at 350 head 2's page is wanted and not used: the rule is conservative


def test_the_byte_budget_bounds_pages_as_the_splat_budget_does():
    held = _tree(PARENT[:3], [1000] * 3, CENTRE[:3], HALF[:3], ERROR[:3])  # 4 chunks of 1,000 B a tile
    view = view_numbers(held, CAM)
    cost = held.gpu_bytes.astype(float)
    # the least the children add: 0.75 x 2 x 1,000 splats in 6 chunks, 2,000 B more than the head's 4; set aside
    # for a head whose page is wanted: 2 x 1,000 splats in 8 chunks, 4,000 B more
    for budget, wanted in ((8000.0, [False, False]), (9999.0, [False, False]), (10000.0, [True, False]),
                           (13999.0, [True, False]), (14000.0, [True, True])):
        opts = SelectionOptions(max_sse=0.1, budget=budget)
        _, heads, mask = _rule(held, view, cost=cost, opts=opts)
        assert mask.tolist() == wanted, budget


def test_a_head_crossing_the_frustum_always_wants_its_page():
    """Where a head's box crosses a frustum plane its children may all lie outside (the refinement could shrink
    the cut): its page is wanted whatever the budget left."""
    cam = Camera(eye=(-1.0, -12.0, 0.5), target=(-1.0, 0.0, 0.0), fov_y_deg=6.0, width=640, height=480)
    _, held, _, view = _views(cam)
    planes = frustum_planes(cam)
    inside = boxes_inside_frustum(held.box_corners, planes)
    assert bool(view.visible[1]) and not inside[1]  # head 1 crosses the frustum's edge
    assert boxes_in_frustum(None, None, planes, held.box_corners).tolist() == view.visible.tolist()
    opts = SelectionOptions(max_sse=0.1, max_splats=200, budget=1e9)
    _, heads, mask = _rule(held, view, opts, held.gpu_bytes.astype(float))
    assert 1 in heads.tolist()
    assert dict(zip(heads.tolist(), mask.tolist(), strict=True))[1]


def test_a_head_that_follows_its_parent_takes_its_parents_turn():
    """A tile whose key is not above its parent's (spheres that do not nest) is decided right after its parent:
    the refinements decided before it are those before its parent (and the parent's own)."""
    # head 2 nearer the eye than its parent's key allows: its key falls below the root's
    centre = [(0, 0, 0), (1.5, 0, 0), (-1.9, 0, 0)]
    half = [2.0, 0.5, 0.1]
    held = _tree(PARENT[:3], SPLATS[:3], centre, half, ERROR[:3])
    cam = Camera(eye=(-6.0, 0.0, 0.2), target=(0.0, 0.0, 0.0), fov_y_deg=60.0, width=640, height=480)
    view = view_numbers(held, cam)
    opts = SelectionOptions(max_sse=0.01, max_splats=249, budget=1e9)
    _, heads, mask = _rule(held, view, opts, held.gpu_bytes.astype(float))
    assert sorted(heads.tolist()) == [1, 2]
    assert not mask.any()  # 200 of 249 used either way: 49 left, the least is 50
    opts = SelectionOptions(max_sse=0.01, max_splats=250, budget=1e9)
    _, heads, mask = _rule(held, view, opts, held.gpu_bytes.astype(float))
    # head 2 (its key below the root's) is decided right after the root, before head 1: its page is the one
    assert dict(zip(heads.tolist(), mask.tolist(), strict=True)) == {1: False, 2: True}
    opts = SelectionOptions(max_sse=0.01, max_splats=350, budget=1e9)
    _, heads, mask = _rule(held, view, opts, held.gpu_bytes.astype(float))
    assert mask.all()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("page-budget")
    ply = real("fruit_drops_sh3.ply")
    encode_file(ply, root / "paged", max_leaf_splats=300, page_tiles=4, page_levels=2)
    encode_file(ply, root / "whole", max_leaf_splats=300)
    s = ServerThread(root)
    yield root, s
    s.stop()


def _pages_used(m, draw) -> set[str]:
    """The page files that hold a drawn tile or an ancestor of one (the pages the cut went through)."""
    parent = {c: t.id for t in m.tiles for c in t.children}
    by_id = {t.id: t for t in m.tiles}
    used: set[str] = set()
    for t in draw:
        a = parent.get(t)
        while a is not None:
            if by_id[a].page is not None:
                used.add(by_id[a].page.file)
            a = parent.get(a)
    return used


@pytest.mark.parametrize("budget", [600, 2000])
def test_a_paged_scene_under_a_small_budget_reads_the_pages_it_draws_from(served, budget):
    root, server = served
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    sel = SelectionOptions(max_sse=1.0, max_splats=budget)
    u, m, _, pages = _stream(server, "paged", cam, StreamOptions(sel, prefetch=False))
    # Every page read holds a drawn tile or one above it, but for pages asked for while the pages above them load
    # (what is set aside for a head wanted is its children's likely splats, not the refinements below them that its
    # page lets in; where the first two pages land a frame apart, the first's heads see the budget the second will
    # take): 0 in most runs, 2 in about 1 run of 3 at both budgets (of 2-4 pages read at 600 splats, 10-12 at 2,000)
    assert len(set(pages) - _pages_used(m, u.draw)) <= 2
    uw, _, _, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False))
    assert sorted(u.draw) == sorted(uw.draw)  # the unpaged scene's cut
    # as before (every page of a cut tile the view would refine): the same cut, more pages
    u0, m0, _, pages0 = _stream(server, "paged", cam, StreamOptions(sel, prefetch=False, pages_by_budget=False))
    assert sorted(u0.draw) == sorted(u.draw)
    if budget == 600:  # the rule refuses pages here: 10 read without it, 8 of them unused
        assert len(pages) <= 4 and len(set(pages0) - _pages_used(m0, u0.draw)) >= 6
    # with prefetch (bounded by the budget too): the same pages, the same cut
    up, _, _, pagesp = _stream(server, "paged", cam, StreamOptions(sel))
    assert sorted(up.draw) == sorted(u.draw)
    assert len(set(pagesp) - _pages_used(m, up.draw)) <= 2


def test_without_a_budget_every_page_the_view_refines_is_read(served):
    root, server = served
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    sel = SelectionOptions(max_sse=1.0)
    u, _, _, pages = _stream(server, "paged", cam, StreamOptions(sel, prefetch=False))
    u0, _, _, pages0 = _stream(server, "paged", cam, StreamOptions(sel, prefetch=False, pages_by_budget=False))
    assert sorted(u.draw) == sorted(u0.draw) and sorted(pages) == sorted(pages0)


def _cut_ids(m, cam, opts, cost) -> tuple[set[int], object, np.ndarray]:
    a = m.arrays
    view = view_numbers(a, cam, opts)
    sel = select(a, view, cost, m.index_of[m.root], opts, reduction=m.lod.reduction)
    return set(a.ids[list(sel.cut)].tolist()), sel, view


def _camera_at(m, rnd: random.Random, far: float) -> Camera:
    """A random view from `far` times the root's sphere radius from its centre."""
    root = m.tiles[m.index_of[m.root]]
    c, r = np.array(root.sphere_center), root.sphere_radius
    d = np.array([rnd.gauss(0, 1) for _ in range(3)])
    target = c + np.array([rnd.gauss(0, 0.3 * r) for _ in range(3)])
    size = rnd.choice([(320, 240), (640, 360), (1920, 1080)])
    return Camera(tuple(c + d / np.linalg.norm(d) * r * far), tuple(target), (0.0, 0.0, 1.0),
                  rnd.choice([30.0, 60.0, 90.0]), *size, near=0.01 * r)


def _closer(m, cam: Camera) -> Camera:
    """The same view from nearer the root's sphere (still outside it)."""
    root = m.tiles[m.index_of[m.root]]
    c, r = np.array(root.sphere_center), root.sphere_radius
    eye = np.array(cam.eye)
    d = eye - c
    eye = c + d / np.linalg.norm(d) * r * 1.05
    return Camera(tuple(eye), cam.target, cam.up, cam.fov_y_deg, cam.width, cam.height, near=cam.near)


def test_reading_the_pages_the_rule_wants_converges_to_the_whole_trees_cut(whole):
    """The engine's loop without the network, on a paged tree (fruit_drops, pages of 2 levels): read the pages the
    rule wants, select again, until none is wanted; the cut is then the whole tree's, at random views and budgets,
    and again after the camera moves (closer, or anywhere): a page needed later still comes. Fewer pages are read
    than by wanting the page of every head the view would refine."""
    # format 1.16: the tree as it is held when paged 2 levels to a file (each page's top tiles are its table's f32
    # anchors, format.md 6.2), which is what the pages give back
    whole = whole.compacted(page_levels=2)
    paged = split_pages(whole, 2)
    files = {ref.file: raw for ref, raw in paged.pages}
    rnd = random.Random(31)
    chunk = whole.chunk_size
    read_rule = read_all = 0
    for _ in range(40):
        # eyes outside the root's sphere (so outside every tile's: lod.md 2): no two refinement keys tie at -inf,
        # where the queue's order among them, by position, differs between trees read in different orders
        far = rnd.choice([1.5, 3.0, 8.0])
        cams = [_camera_at(whole, rnd, far), None, _camera_at(whole, rnd, 1.1)]
        cams[1] = _closer(whole, cams[0])
        splats = whole.tiles[whole.index_of[whole.root]].splats
        budget = rnd.choice([2, 3, 5, 10, 20, 40]) * splats
        by_bytes = rnd.random() < 0.3
        for by_rule in (True, False):
            tree = PagedTree(paged.root)
            for cam in cams:
                for _ in range(50):
                    m = tree.manifest
                    cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
                    opts = SelectionOptions(max_sse=1.0, max_splats=None if by_bytes else budget,
                                            budget=budget / chunk * 4096.0 * 1.5 if by_bytes else None)
                    _, sel, view = _cut_ids(m, cam, opts, cost)
                    heads = tree.heads_to_refine(sel.cut, view.sse, view.visible, opts.max_sse)
                    if by_rule:
                        now, _ = pages_the_budget_can_use(m.arrays, view, cost, m.index_of[m.root], sel, heads,
                                                          opts, m.lod.reduction, chunk, 4096.0)
                        heads = heads[now]
                    if not len(heads):
                        break
                    for tile_id in m.arrays.ids[heads].tolist():
                        tree.add_page(tile_id, files[tree.entry(tile_id).file])
                        read_rule += by_rule
                        read_all += not by_rule
                else:
                    raise AssertionError("pages wanted after 50 rounds")
                whole_cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
                got, want = _cut_ids(tree.manifest, cam, opts, cost)[0], _cut_ids(whole, cam, opts, whole_cost)[0]
                assert got == want, (by_rule, cams.index(cam), budget, by_bytes)
    assert read_rule < read_all, (read_rule, read_all)


def _land_in_random_order(root_manifest, files, cam: Camera, opts: SelectionOptions, rnd: random.Random) -> PagedTree:
    """The engine's page loop without the network (pagepair31's landing_orders.py), the pages landing when they will:
    each frame selects over the tree held and asks for the pages the rule wants (those on their way that it no longer
    wants are cancelled), and a random part of the pages on their way lands. The tree held once no page is wanted:
    its rows in the order its pages arrived in."""
    tree = PagedTree(root_manifest)
    on_way: list[int] = []
    for _ in range(200):
        m = tree.manifest
        cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
        _, sel, view = _cut_ids(m, cam, opts, cost)
        heads = tree.heads_to_refine(sel.cut, view.sse, view.visible, opts.max_sse)
        now, _ = pages_the_budget_can_use(m.arrays, view, cost, m.index_of[m.root], sel, heads, opts,
                                          m.lod.reduction, m.chunk_size, 4096.0)
        wanted = m.arrays.ids[heads[now]].tolist()
        on_way = [t for t in on_way if t in wanted] + [t for t in wanted if t not in on_way]
        if not on_way:
            return tree
        land = [t for t in on_way if rnd.random() < 0.5] or [rnd.choice(on_way)]
        for tile_id in land:
            tree.add_page(tile_id, files[tree.entry(tile_id).file])
        on_way = [t for t in on_way if t not in land]
    raise AssertionError("pages wanted after 200 frames")


def _bands_and_prefetch(m, view, sel, opts: SelectionOptions, cost: np.ndarray) -> tuple[list, list]:
    """By tile id: the SH bands the cut wants (wanted_bands, and wanted_bands_at, the engine's, which must agree),
    under the view's areas and under areas that tie every cut tile's area per byte of band 1 (as the eye inside
    tiles of one size would: which tiles get band 1 under a share below 1 is then the tie rule alone); and the
    prefetch list, with the engine's allowance and with one that lets every tile in."""
    a, ids = m.arrays, m.arrays.ids
    tied = replace(view, area_px=np.maximum(1.0, a.band_bytes[:, 0].astype(np.float64)) * 3.0)
    bands = []
    for v in (view, tied):
        for o in (opts, replace(opts, band_area_share=(0.5, 0.3, 0.1))):
            by_dict = wanted_bands(a, v, sel.cut, o, m.sh_degree)
            at = wanted_bands_at(a, v, sel.cut_at, o, m.sh_degree).tolist()
            assert at == [by_dict[i] for i in sel.cut]
            bands.append(sorted((int(ids[i]), b) for i, b in zip(sel.cut, at, strict=True)))
    fetched = [[(score, int(ids[i])) for score, i in prefetch(a, view, sel, o, cost)]
               for o in (opts, replace(opts, prefetch_share=100.0))]
    return bands, fetched


@pytest.mark.parametrize("path", PATHS)
def test_a_view_inside_tiles_converges_to_one_cut_whatever_order_the_pages_land_in(whole, path):
    """Issue 31 (client.md 1.2's tie-break): with the eye inside tiles' spheres many refinement keys tie (-inf), and
    equal keys are taken in the order of the tiles' ids, not of their rows in the tree held (which follow the order
    the pages arrived in). So a view converges to one cut, the whole tree's (the same tiles in the same order, the
    same refined tiles and priorities), whatever order its pages land in; and on each tree held the scan and the
    compiled selection are select's (test_stream_select_near.check_same). Before, the rows broke the ties: the same
    views gave several cuts."""
    whole = whole.compacted(page_levels=2)  # 1.16: as held when paged (the pages' top tiles f32 anchors)
    paged = split_pages(whole, 2)
    files = {ref.file: raw for ref, raw in paged.pages}
    whole_cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
    root = whole.tiles[whole.index_of[whole.root]]
    c, r = np.array(root.sphere_center), root.sphere_radius
    rnd = random.Random(31)
    tied = prefetched = 0
    for v in range(6):
        d = np.array([rnd.gauss(0, 1) for _ in range(3)])
        eye = c + d / np.linalg.norm(d) * r * rnd.choice([0.05, 0.3, 0.5])  # inside the root's sphere
        cam = Camera(tuple(eye), tuple(c + np.array([rnd.gauss(0, r) for _ in range(3)])), (0.0, 0.0, 1.0),
                     rnd.choice([40.0, 60.0, 90.0]), 320, 240, near=0.001 * r)
        by_bytes = v % 3 == 2
        budget = rnd.choice([3, 5, 10, 20]) * root.splats
        opts = SelectionOptions(max_sse=1.0, max_splats=None if by_bytes else budget,
                                budget=budget / whole.chunk_size * 4096.0 * 1.5 if by_bytes else None)
        # under the budget, and without one (more refined tiles, so more tiles just outside the frustum to prefetch,
        # tied at score 0.5)
        for o in (opts, SelectionOptions(max_sse=1.0)):
            want_sel, want_view = _cut_ids(whole, cam, o, whole_cost)[1:]
            ids = whole.arrays.ids
            want = ([int(ids[i]) for i in want_sel.cut], sorted(ids[list(want_sel.refined)].tolist()),
                    [want_sel.priority[i] for i in want_sel.cut])
            if o is opts:  # the eye inside refined tiles' spheres: their sse infinite, their keys -inf, tied
                tied += int(np.isinf(want_view.sse[list(want_sel.refined)]).sum() > 1)
            want_bands, (_, want_prefetch) = _bands_and_prefetch(whole, want_view, want_sel, o, whole_cost)
            first_prefetch = None
            for _ in range(4):
                tree = _land_in_random_order(paged.root, files, cam, o, random.Random(rnd.random()))
                m = tree.manifest
                cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
                sel, view = _cut_ids(m, cam, o, cost)[1:]
                a_ids = m.arrays.ids
                got = ([int(a_ids[i]) for i in sel.cut], sorted(a_ids[list(sel.refined)].tolist()),
                       [sel.priority[i] for i in sel.cut])
                assert got == want, v
                # issue 31's other orders (bandtie31): the SH bands each cut tile wants and the prefetch list, ties by
                # tile id too: the bands the whole tree's; the prefetch list one whatever the order, and with every
                # tile let in the whole tree's less the tiles not held (children of cut tiles whose pages are not read)
                bands, fetched = _bands_and_prefetch(m, view, sel, o, cost)
                assert bands == want_bands, v
                first_prefetch = fetched if first_prefetch is None else first_prefetch
                assert fetched == first_prefetch, v
                assert fetched[1] == [(score, t) for score, t in want_prefetch if t in m.index_of], v
                prefetched += len(fetched[1])
                check_same(m, cam, o, frozenset(), (), np.ones(len(m.tiles), bool), rnd, path)
    assert tied >= 3, tied  # the views do tie keys (several refined tiles with the eye inside them)
    assert prefetched >= 4, prefetched  # and some prefetch (tiles tied at score 0.5, just outside the frustum)
