"""Which tiles and SH bands a view wants: pure functions over the manifest's tile arrays (format_spec/client.md).

Per frame: `view_numbers` projects every tile (screen-space error, frustum test, projected radius); `select`
refines the tree from the root, widest on-screen splat spacing first, under a splat and a byte budget, with
hysteresis; `wanted_bands` gives SH bands to the tiles covering most of the view; `draw_set` turns what is
resident into a hole-free REPLACE cut (a tile stays drawn until every child in view can replace it); `prefetch`
names what the view will probably want next. No GL, no network, no clocks: the engine (engine.py) calls these
and acts on the answers.
"""
from __future__ import annotations

import functools
import heapq
import math
from dataclasses import dataclass, field

import numpy as np

from splatstream.camera import Camera
from splatstream.format.manifest import TileArrays

INF = float("inf")


@dataclass(frozen=True)
class SelectionOptions:
    max_sse: float = 1.5  # px: refine a tile while its screen-space error exceeds this (lod.md 3)
    max_splats: int | None = None  # the cut's splats at most (None: no limit)
    budget: float | None = None  # the cut's cost at most, in the units of the `cost` array (GPU bytes)
    hysteresis: float = 0.8  # a tile refined last frame stays refined until its sse drops below max_sse * this
    sh_degree: int = 3  # highest SH band wanted
    # SH bands by need: band b goes to the tiles of the cut that cover the largest share of the view per byte of the
    # band, until they cover band_area_share[b - 1] of the cut's projected area (the rest are too small on screen
    # for their view-dependent colour to matter). 1.0: every tile. max_sse 0 (full detail) takes every band.
    # Measured: bench/bench_stream.py, format_spec/client.md 4.
    band_area_share: tuple[float, float, float] = (0.97, 0.9, 0.8)
    prefetch_margin: float = 1.25  # prefetch tiles whose sse is above max_sse / this, and a frustum this much wider
    # Prefetch at most this share of the cut's cost: with the ancestors filled in coarse to fine (every third
    # level) the bytes fetched at convergence stay within 1.2x of the drawn tiles' (format_spec/client.md 1).
    prefetch_share: float = 0.04


@dataclass(frozen=True)
class TileView:
    """Per-tile numbers of one view (index = position in the manifest's tiles)."""

    sse: np.ndarray  # (T,) px, inf when the eye is inside the bounding sphere
    visible: np.ndarray  # (T,) bool: the 3-sigma box intersects the view frustum
    radius_px: np.ndarray  # (T,) projected radius of the bounding sphere, px (inf inside it)
    area_px: np.ndarray  # (T,) pixels of the image inside the projected sphere's bounding square (0 when culled)
    distance: np.ndarray  # (T,) distance from the eye to the sphere, world units (<= 0 inside)
    # (tile arrays, camera, its basis, widening) of the frustum widened by prefetch_margin: visible_wide tests it
    # when asked (only prefetch needs it, and the engine asks for prefetch only when nothing is missing)
    wide_frustum: tuple = field(repr=False, compare=False, default=())

    @functools.cached_property
    def visible_wide(self) -> np.ndarray:
        """(T,) bool: the box intersects a frustum widened by prefetch_margin."""
        a, cam, basis, widen = self.wide_frustum
        return boxes_in_frustum(a.box_min, a.box_max, frustum_planes(cam, widen, basis), a.box_corners)


@dataclass(frozen=True)
class Selection:
    cut: tuple[int, ...]  # tiles the view wants drawn: a REPLACE cut of the visible tree
    refined: frozenset[int]  # tiles whose (visible) children replace them
    priority: dict[int, float]  # cut tile -> fetch priority: minus the refinement key of its parent (root: inf)
    splats: int
    cost: float
    # A refinement the view wanted did not fit the splat or byte budget: the budget, not the error, ends the cut
    # (prefetch then leaves out the children of cut tiles: the budget would not let them in).
    budget_limited: bool = False


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _basis(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(eye, right, up, forward) of a camera, as Camera.basis computes them (without numpy's general cross)."""
    eye = np.asarray(cam.eye, np.float64)
    forward = np.asarray(cam.target, np.float64) - eye
    forward /= np.linalg.norm(forward)
    up = np.asarray(cam.up, np.float64)
    right = _cross(forward, up)
    n = np.linalg.norm(right)
    if n < 1e-9 * np.linalg.norm(up):
        right, true_up, forward = (np.asarray(v, np.float64) for v in cam.basis())
        return eye, right, true_up, forward
    right /= n
    return eye, right, _cross(right, forward), forward


def frustum_planes(cam: Camera, widen: float = 1.0, basis=None) -> np.ndarray:
    """(5, 4) inward planes (normal, d) of the view frustum without its far plane: n . p + d >= 0 inside."""
    eye, right, up, forward = basis if basis is not None else _basis(cam)
    tx, ty = cam.tan_half_fov_x * widen, cam.tan_half_fov_y * widen
    normals = np.empty((5, 3))
    normals[0] = forward
    for k, (axis, t) in enumerate(((right, tx), (-right, tx), (up, ty), (-up, ty)), start=1):
        n = forward * t - axis  # the plane through the eye containing the edge direction forward + t*axis
        normals[k] = n / np.linalg.norm(n)
    planes = np.empty((5, 4))
    planes[:, :3] = normals
    planes[:, 3] = -np.einsum("pk,k->p", normals, eye)
    planes[0, 3] -= cam.near
    return planes


def boxes_in_frustum(box_min: np.ndarray, box_max: np.ndarray, planes: np.ndarray,
                     corners: np.ndarray | None = None) -> np.ndarray:
    """(T,) True where an axis-aligned box is not entirely outside any plane (conservative). `corners`: the boxes
    as (T, 6) [max, min] (TileArrays.box_corners), when the caller has them."""
    n = planes[:, :3]
    if corners is None:
        corners = np.concatenate([box_max, box_min], axis=1)
    # The box corner farthest along each plane's normal ("positive vertex"), dotted with the normal: the max
    # corner's coordinates where the normal is positive, the min corner's where it is negative, in one product
    # (einsum, not @: see view_numbers).
    split = np.concatenate([np.maximum(n, 0.0), np.minimum(n, 0.0)], axis=1)
    return np.all(np.einsum("tk,pk->tp", corners, split) + planes[None, :, 3] >= 0, axis=1)


def view_numbers(a: TileArrays, cam: Camera, opts: SelectionOptions = SelectionOptions()) -> TileView:
    basis = _basis(cam)
    eye, right, up, forward = basis
    rel = a.sphere_center - eye
    centre_dist = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    distance = centre_dist - a.sphere_radius
    ahead = distance > 0  # the eye outside the bounding sphere
    focal = cam.height / (2.0 * cam.tan_half_fov_y)
    visible = boxes_in_frustum(a.box_min, a.box_max, frustum_planes(cam, 1.0, basis), a.box_corners)
    # The centres in the camera's frame (image x right, y down: camera.md), in one product. einsum, not @: a matrix
    # product goes to the BLAS library, whose worker threads (16 on the GPU machine) cost more than these few
    # thousand products.
    frame = np.einsum("ij,kj->ik", rel, np.stack([right, up, forward]))
    depth = frame[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        sse = np.where(ahead, a.geometric_error * focal / distance, INF)
        radius_px = np.where(ahead, a.sphere_radius * focal / np.maximum(centre_dist, 1e-12), INF)
        u = focal * frame[:, 0] / depth + cam.width / 2.0
        v = -focal * frame[:, 1] / depth + cam.height / 2.0
        r = np.where(ahead, radius_px, 0.0)
        w = np.clip(u + r, 0, cam.width) - np.clip(u - r, 0, cam.width)
        h = np.clip(v + r, 0, cam.height) - np.clip(v - r, 0, cam.height)
        area = np.where(depth > 0, np.nan_to_num(w * h), 0.0)
    area = np.where(ahead, area, float(cam.width * cam.height))  # the eye inside: everywhere
    area = np.where(visible, area, 0.0)
    return TileView(sse, visible, radius_px, area, distance, (a, cam, basis, opts.prefetch_margin))


def select(a: TileArrays, view: TileView, cost: np.ndarray, root: int, opts: SelectionOptions,
           previous_refined: frozenset[int] = frozenset(), reduction: float = 2.0) -> Selection:
    """The cut the view wants: REPLACE refinement from the root, widest on-screen splat spacing first.

    A visible tile whose sse exceeds the threshold is a candidate; candidates are refined in order of the spacing
    of their splats on screen (below; `reduction`: the scene's lod.reduction) while the cut stays within the splat
    and cost budgets; a refinement that does not fit is skipped. Children outside the frustum are dropped from the
    cut (they draw nothing)."""
    # Per-tile numbers over numpy first (visible children's cost and splats, priority): the greedy loop
    # below then does only heap work and list lookups (BENCHMARKS.md, "Figures behind library defaults"). The sums
    # are of whole numbers in float64, exact in any order, so the cut is the same as summing child by child.
    visible = view.visible
    child, has_kids, cost_l, splats_l = a.has_parent, a.has_children, cost.tolist(), a.splats_list
    n = len(a.parent)
    kid_cost = np.bincount(a.parent_of_child, weights=np.where(visible, cost, 0.0)[child], minlength=n)
    kid_splats = np.bincount(a.parent_of_child, weights=np.where(visible, a.splats_f64, 0.0)[child], minlength=n)
    threshold = np.full(n, float(opts.max_sse))
    if previous_refined:
        threshold[list(previous_refined)] *= opts.hysteresis
    candidate = (has_kids & visible & (view.sse > threshold)).tolist()
    # Order of refinement: the tile whose splats lie widest apart on screen first. A level holds `reduction` times
    # the splats of the one above over the same region, so on surfaces its splats are reduction^(1/2) closer
    # together; seen from distance d their spacing on screen goes as reduction^(-level/2) / d. Under a budget this
    # keeps the cut close to one level across the view, finer where the view is nearer (measured against error
    # removed per byte, sse x area / added cost, which refined the nearest tiles to their leaves first: a median
    # 1.0 dB better on the real scenes it was not chosen on; BENCHMARKS.md, "LOD against peers").
    with np.errstate(divide="ignore"):
        key = a.level * (0.5 * math.log2(max(reduction, 1.0 + 1e-9))) + np.log2(np.maximum(view.distance, 1e-30))
    prio = np.where(np.isfinite(view.sse), key, -INF).tolist()  # the eye inside a tile's sphere: refine it first
    kid_cost_l, kid_splats_l = kid_cost.tolist(), kid_splats.tolist()
    visible_l = visible.tolist()

    refined: set[int] = set()
    cut: set[int] = {root}
    priority: dict[int, float] = {root: INF}
    splats = int(splats_l[root])
    total = float(cost_l[root])
    heap: list[tuple[float, int]] = [(prio[root], root)] if candidate[root] else []
    limited = False
    while heap:
        neg_priority, i = heapq.heappop(heap)
        new_splats = splats - int(splats_l[i]) + int(kid_splats_l[i])
        new_total = total - cost_l[i] + kid_cost_l[i]
        # A refinement that does not fit is skipped, not the end: a smaller one further down the queue may fit, so
        # the budget is spent to within the smallest refinement's size.
        if opts.max_splats is not None and new_splats > opts.max_splats and new_splats > splats:
            limited = True
            continue
        if opts.budget is not None and new_total > opts.budget and new_total > total:
            limited = True
            continue
        cut.discard(i)
        refined.add(i)
        splats, total = new_splats, new_total
        for k in a.children[i]:
            if not visible_l[k]:
                continue
            cut.add(k)
            priority[k] = -neg_priority
            if candidate[k]:
                heapq.heappush(heap, (prio[k], k))
    distance = view.distance.tolist()
    cut_sorted = tuple(sorted(cut, key=lambda i: (-priority[i], distance[i])))
    return Selection(cut_sorted, frozenset(refined), {i: priority.get(i, 0.0) for i in cut_sorted}, splats, total,
                     limited)


def wanted_bands(a: TileArrays, view: TileView, tiles: tuple[int, ...] | list[int], opts: SelectionOptions,
                 scene_degree: int) -> dict[int, int]:
    """SH bands each tile wants: band b for the tiles that cover the first band_area_share[b - 1] of the cut's
    projected area, taken in order of area per byte of the band (a tile gets band b only with band b - 1)."""
    top = min(opts.sh_degree, scene_degree)
    out = dict.fromkeys(tiles, 0)
    if opts.max_sse <= 0:  # full detail: every band of every tile
        return dict.fromkeys(tiles, top)
    area = {i: float(view.area_px[i]) for i in tiles}
    total = sum(area.values())
    for b in range(1, top + 1):
        share = opts.band_area_share[b - 1]
        band_bytes = a.band_bytes[:, b - 1]
        order = sorted((i for i in tiles if out[i] == b - 1),
                       key=lambda i: (-area[i] / max(1.0, float(band_bytes[i])), i))
        covered = 0.0
        for i in order:
            if covered >= share * total and share < 1.0:
                break
            out[i] = b
            covered += area[i]
    return out


def draw_set(a: TileArrays, view: TileView, sel: Selection, resident: np.ndarray, root: int) -> list[int]:
    """The tiles to draw now: the wanted cut where resident, else what covers the same region without holes.

    A tile the selection refines is replaced by its visible children only when every one of them can be drawn
    (resident, or covered by its own resident descendants); otherwise the tile itself is drawn. A wanted tile
    that is not resident yet is covered by its resident descendants if they cover its view (they were wanted
    before the camera moved back), else by an ancestor. Never a tile together with a descendant."""

    def cover(i: int) -> list[int] | None:
        kids = [k for k in a.children[i] if view.visible[k]]
        if i in sel.refined:
            parts = _cover_all(kids)
            if parts is not None:
                return parts
        if resident[i]:
            return [i]
        if kids and i not in sel.refined:
            return _cover_all(kids)  # finer tiles still resident stand in for a coarser tile not yet loaded
        return None

    def _cover_all(kids: list[int]) -> list[int] | None:
        out: list[int] = []
        for k in kids:
            p = cover(k)
            if p is None:
                return None
            out += p
        return out

    return cover(root) or []


def prefetch(a: TileArrays, view: TileView, sel: Selection, opts: SelectionOptions,
             cost: np.ndarray | None = None) -> list[tuple[float, int]]:
    """Tiles the view will probably want next, best first: children of cut tiles close to the refinement
    threshold (the camera moving closer) and tiles just outside the frustum (the camera turning).

    Bounded by the budget: no children of cut tiles when the budget ended the cut (it would not let them in), and
    with `cost` (per tile, the units of sel.cost) the list stops at prefetch_share of the cut's cost."""
    out: list[tuple[float, int]] = []
    wide = view.visible_wide
    wide_l = wide.tolist()
    sse = view.sse
    if not sel.budget_limited and opts.max_sse > 0:
        for i in sel.cut:
            if a.children[i] and sse[i] > opts.max_sse / opts.prefetch_margin:
                score = float(sse[i]) / opts.max_sse
                out += [(score, k) for k in a.children[i] if wide_l[k]]
    # just outside the frustum, children of refined tiles (a cut tile is visible, so never one of these)
    parent = a.parent
    refined = np.zeros(len(parent) + 1, bool)  # index -1 (the root's parent) reads the extra False
    refined[list(sel.refined)] = True
    edge = np.flatnonzero(wide & ~view.visible & refined[parent])
    out += [(0.5, int(i)) for i in edge]
    out.sort(key=lambda x: -x[0])
    if cost is not None:
        allowance = opts.prefetch_share * sel.cost
        spent = np.cumsum([float(cost[i]) for _, i in out])
        out = out[:int(np.searchsorted(spent, allowance, side="right"))]
    return out
