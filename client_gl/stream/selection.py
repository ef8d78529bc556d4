"""Which tiles and SH bands a view wants: pure functions over the manifest's tile arrays (format_spec/client.md).

Per frame: `view_numbers` projects every tile (screen-space error, frustum test, projected radius); `select`
refines the tree from the root, widest on-screen splat spacing first, under a splat and a byte budget, with
hysteresis. Those two are the reference; the engine runs `select_near` over a `PartialView`: the same cut from the
numbers of the tiles the refinement reaches only (its cost follows the cut, not the tree held), select's heap loop
replayed as one scan in key order (`select_near_heap` keeps the heap loop). `wanted_bands`
gives SH bands to the tiles covering most of the view; `draw_set` turns what is resident into a hole-free REPLACE
cut (a tile stays drawn until every child in view can replace it); `prefetch` names what the view will probably
want next. No GL, no network, no clocks: the engine (engine.py) calls these and acts on the answers.
"""
from __future__ import annotations

import heapq
import math
from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import accumulate, chain

import numpy as np

from splatstream.camera import Camera
from splatstream.format.manifest import TileArrays, indexable

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
    # (tile arrays, camera, its basis, widening) of the frustum widened by prefetch_margin: wide_visible tests it
    # (only prefetch needs it, and the engine asks for prefetch only when nothing is missing)
    wide_frustum: tuple = field(repr=False, compare=False, default=())

    def ensure(self, idx) -> None:
        """Every tile's numbers are here already (PartialView computes them when asked)."""

    def visible_at(self, i: int) -> bool:
        return bool(self.visible[i])


class Selection:
    """A view's cut: the tiles to draw (a REPLACE cut of the visible tree, in fetch order), the tiles refined above
    it, each cut tile's fetch priority (minus the refinement key of its parent; the root's inf), its splats and cost,
    and whether a budget ended it (a refinement the view wanted did not fit the splat or byte budget: prefetch then
    leaves out the children of cut tiles, the budget would not let them in).

    Held as numpy arrays (`cut_at`, `priority_at`, `refined_at`: positions) where the selection made arrays (the
    compiled selection and select_near), as Python collections where it made those (select, select_near_heap); each
    form is made from the other when first asked for. The engine takes the arrays: building the tuple, frozenset
    and dict of a 250M-splat cut every frame cost 0.15 ms that it turned back into arrays (BENCHMARKS.md, "Manifest
    pages")."""

    def __init__(self, cut, refined, priority: dict[int, float], splats: int, cost: float,
                 budget_limited: bool = False):
        self._cut: tuple[int, ...] | None = tuple(cut)
        self._refined: frozenset[int] | None = frozenset(refined)
        self._priority: dict[int, float] | None = priority
        self._cut_at = self._priority_at = self._refined_at = None
        self.splats, self.cost, self.budget_limited = splats, cost, budget_limited

    @classmethod
    def of_arrays(cls, cut_at: np.ndarray, priority_at: np.ndarray, refined_at: np.ndarray, splats: int,
                  cost: float, budget_limited: bool = False) -> Selection:
        """A selection from arrays it owns (not views of scratch arrays a later selection writes): the cut's
        positions in order, their priorities, the refined positions (any order)."""
        sel = cls.__new__(cls)
        sel._cut = sel._refined = sel._priority = None
        sel._cut_at, sel._priority_at = np.asarray(cut_at, np.intp), np.asarray(priority_at, np.float64)
        sel._refined_at = np.asarray(refined_at, np.intp)
        sel.splats, sel.cost, sel.budget_limited = splats, cost, budget_limited
        return sel

    @property
    def cut(self) -> tuple[int, ...]:
        """The cut's positions, in fetch order."""
        if self._cut is None:
            self._cut = tuple(self._cut_at.tolist())
        return self._cut

    @property
    def refined(self) -> frozenset[int]:
        """Positions of the tiles whose (visible) children replace them."""
        if self._refined is None:
            self._refined = frozenset(self._refined_at.tolist())
        return self._refined

    @property
    def priority(self) -> dict[int, float]:
        """Cut position -> fetch priority."""
        if self._priority is None:
            self._priority = dict(zip(self.cut, self.priority_at.tolist(), strict=True))
        return self._priority

    @property
    def cut_at(self) -> np.ndarray:
        """The cut's positions in order, as an array (read only: shared)."""
        if self._cut_at is None:
            self._cut_at = np.array(self._cut, np.intp)
        return self._cut_at

    @property
    def priority_at(self) -> np.ndarray:
        """The cut's priorities, in the cut's order."""
        if self._priority_at is None:
            self._priority_at = np.array([self._priority.get(i, 0.0) for i in self._cut], np.float64)
        return self._priority_at

    @property
    def refined_at(self) -> np.ndarray:
        """The refined positions, as an array (in no particular order)."""
        if self._refined_at is None:
            self._refined_at = np.fromiter(self._refined, np.intp, len(self._refined))
        return self._refined_at

    def _fields(self) -> tuple:
        return self.cut, self.refined, self.priority, self.splats, self.cost, self.budget_limited

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Selection) and self._fields() == other._fields()

    __hash__ = None  # type: ignore[assignment]  # mutable caches, dict inside: not hashable (as before)

    def __repr__(self) -> str:
        return (f"Selection(cut={self.cut!r}, refined={self.refined!r}, priority={self.priority!r}, "
                f"splats={self.splats!r}, cost={self.cost!r}, budget_limited={self.budget_limited!r})")


def positions(tiles) -> np.ndarray:
    """Tile positions as an intp array: an array as it is, any other collection (a frozenset, a list) converted."""
    if isinstance(tiles, np.ndarray):
        return tiles.astype(np.intp, copy=False)
    return np.fromiter(tiles, np.intp, len(tiles))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _norm(v: np.ndarray) -> float:
    """The length of a 3-vector in Python floats (x*x + y*y + z*z, in that order), the one norm of every path (the
    numpy reference's view_numbers, PartialView, the compiled selection's basis and planes). Not numpy's v.dot(v):
    its BLAS dot lets the interpreter lock go whatever the size, 7 times a view, each a chance for a decode thread to
    take the lock from the frame loop (BENCHMARKS.md, "Manifest pages"); it also rounds differently (an FMA), in the
    last bit for about 1 vector in 10."""
    x, y, z = v.tolist()
    return math.sqrt(x * x + y * y + z * z)


def _basis(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(eye, right, up, forward) of a camera, as Camera.basis computes them (without numpy's general cross)."""
    eye = np.asarray(cam.eye, np.float64)
    forward = np.asarray(cam.target, np.float64) - eye
    forward /= _norm(forward)
    up = np.asarray(cam.up, np.float64)
    right = _cross(forward, up)
    n = _norm(right)
    if n < 1e-9 * _norm(up):
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
        normals[k] = n / _norm(n)
    planes = np.empty((5, 4))
    planes[:, :3] = normals
    planes[:, 3] = -np.einsum("pk,k->p", normals, eye)
    planes[0, 3] -= cam.near
    return planes


def boxes_in_frustum(box_min: np.ndarray | None, box_max: np.ndarray | None, planes: np.ndarray,
                     corners: np.ndarray | None = None) -> np.ndarray:
    """(T,) True where an axis-aligned box is not entirely outside any plane (conservative). `corners`: the boxes
    as (T, 6) [max, min] (TileArrays.box_corners), when the caller has them."""
    if corners is None:
        corners = np.concatenate([box_max, box_min], axis=1)
    # The box corner farthest along each plane's normal ("positive vertex"), dotted with the normal: the max
    # corner's coordinates where the normal is positive, the min corner's where it is negative. Written out term by
    # term (not einsum or @): each row's result is then the same bits whether every tile is tested or a few
    # (PartialView tests the tiles near the cut only, and its cut must be the whole tree's).
    split = corner_weights(planes)
    terms = corners[:, None, :] * split[None, :, :]  # (T, planes, 6)
    s = planes[None, :, 3] + terms[:, :, 0]
    for k in range(1, 6):
        s = s + terms[:, :, k]
    inside = np.all(s >= 0, axis=1)
    return inside


def corner_weights(planes: np.ndarray) -> np.ndarray:
    """(planes, 6): each plane's normal split for the [max, min] box corners (the positive vertex's weights)."""
    n = planes[:, :3]
    return np.concatenate([np.maximum(n, 0.0), np.minimum(n, 0.0)], axis=1)


def refinement_level_step(reduction: float) -> float:
    """The refinement key's step per tree level (see refinement_keys): log2 of reduction^(1/2)."""
    return 0.5 * math.log2(max(reduction, 1.0 + 1e-9))


def refinement_keys(level: np.ndarray, distance: np.ndarray, sse: np.ndarray, level_step: float) -> np.ndarray:
    """select's refinement key of these tiles (smallest refined first): level * level_step + log2(distance), and
    -inf where the sse is not finite (the eye inside a tile's sphere: refine it first). One formula for select,
    select_near and the compiled selection, which must order the loop and give the priorities bit for bit alike."""
    # no errstate: log2 of a value at least 1e-30 (or NaN) warns of nothing, and the context costs as much as the rest
    key = level * level_step + np.log2(np.maximum(distance, 1e-30))
    return np.where(np.isfinite(sse), key, -INF)


def _dot3(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(T,) rows of v (T, 3) dotted with w (3,), term by term (the same bits over any subset of rows)."""
    return v[:, 0] * w[0] + v[:, 1] * w[1] + v[:, 2] * w[2]


def _numbers(a: TileArrays, cam: Camera, basis, planes: np.ndarray, idx) -> tuple[np.ndarray, ...]:
    """(sse, visible, radius_px, area_px, distance) of the tiles at positions idx (None: every tile). Elementwise
    only: a tile's numbers do not depend on which other tiles are computed with it."""
    eye, right, up, forward = basis
    if idx is None:
        center, radius, err, corners = a.sphere_center, a.sphere_radius, a.geometric_error, a.box_corners
    else:
        center, radius, err, corners = (a.sphere_center[idx], a.sphere_radius[idx], a.geometric_error[idx],
                                        a.box_corners[idx])
    rel = center - eye
    centre_dist = np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] + rel[:, 2] * rel[:, 2])
    distance = centre_dist - radius
    ahead = distance > 0  # the eye outside the bounding sphere
    focal = cam.height / (2.0 * cam.tan_half_fov_y)
    visible = boxes_in_frustum(None, None, planes, corners)
    depth = _dot3(rel, forward)  # the centres in the camera's frame (image x right, y down: camera.md)
    with np.errstate(divide="ignore", invalid="ignore"):
        sse = np.where(ahead, err * focal / distance, INF)
        radius_px = np.where(ahead, radius * focal / np.maximum(centre_dist, 1e-12), INF)
        u = focal * _dot3(rel, right) / depth + cam.width / 2.0
        v = -focal * _dot3(rel, up) / depth + cam.height / 2.0
        r = np.where(ahead, radius_px, 0.0)
        w = np.clip(u + r, 0, cam.width) - np.clip(u - r, 0, cam.width)
        h = np.clip(v + r, 0, cam.height) - np.clip(v - r, 0, cam.height)
        area = np.where(depth > 0, np.nan_to_num(w * h), 0.0)
    area = np.where(ahead, area, float(cam.width * cam.height))  # the eye inside: everywhere
    area = np.where(visible, area, 0.0)
    return sse, visible, radius_px, area, distance


def wide_visible(view, idx: list[int], boxes: Callable | None = None) -> list[bool]:
    """Whether the boxes of the tiles at positions idx intersect the view's frustum widened by prefetch_margin.
    `boxes(corners, idx, planes)`: the same test another way (selection_jit.boxes_at: the same answer, keeping
    the interpreter lock)."""
    if not idx:
        return []
    a, cam, basis, widen = view.wide_frustum
    planes = frustum_planes(cam, widen, basis)
    if boxes is not None:
        return boxes(a.box_corners, idx, planes)
    return boxes_in_frustum(None, None, planes, a.box_corners[idx]).tolist()


def view_numbers(a: TileArrays, cam: Camera, opts: SelectionOptions = SelectionOptions()) -> TileView:
    """Every tile's numbers (the reference: the engine computes those near the cut only, PartialView)."""
    basis = _basis(cam)
    sse, visible, radius_px, area, distance = _numbers(a, cam, basis, frustum_planes(cam, 1.0, basis), None)
    return TileView(sse, visible, radius_px, area, distance, (a, cam, basis, opts.prefetch_margin))


# The per-tile arrays a frame's selection takes from its ViewBuffers, by name: PartialView's numbers, the compiled
# selection's scratch (selection_jit.select_near_compiled) and its draw set's flags (draw_set_compiled).
# ViewBuffers.prepare makes them all at once, before the first frame (the names and dtypes those take them with).
SELECTION_BUFFERS: tuple[tuple[str, np.dtype], ...] = tuple(
    (name, np.dtype(kind)) for names, kind in (
        (("sse", "radius_px", "distance", "area_px", "prio", "log2", "heap_k", "out_p", "sort_p"), np.float64),
        (("pending", "heap_t", "reflist", "out_t", "sort_t"), np.int64),
        (("known", "cand", "refd", "draw_refd"), np.uint8),
        (("visible", "was_refined"), np.bool_)) for name in names)


class ViewBuffers:
    """Per-tile arrays kept from one view to the next: a PartialView (and the compiled selection, selection_jit)
    takes its arrays here instead of allocating a dozen arrays over the tree held every frame (about 0.17 ms a frame
    at 21,000 tiles on the 2-core VM, a fifth of the compiled selection's CPU: BENCHMARKS.md, "Manifest pages").
    The arrays of the last view taken are overwritten by the next: the holder (the engine) uses a view only until it
    selects again."""

    def __init__(self, ahead: int = 0) -> None:
        """`ahead`: elements to make each array with at least (a paged tree's expected size, PagedTree.rows_ahead:
        np.zeros, memory touched as the tree grows into it; doubled at 7,384 and 14,652 tiles, the new arrays' page
        faults were 0.4-0.5 ms of that frame's view and cut at 250M splats: BENCHMARKS.md, "Manifest pages")."""
        self._arrays: dict[str, np.ndarray] = {}
        self.ahead = ahead
        # What clears an array asked for with `zero`: None, ndarray.fill; the compiled selection sets a kernel that
        # keeps the interpreter lock (numpy's fill lets it go above 500 elements, 5 times a selection: each a chance
        # for a decode thread to take it from the frame loop; BENCHMARKS.md, "Manifest pages"). Called with the
        # array's bytes (a uint8 view).
        self.zero: Callable[[np.ndarray], None] | None = None

    def prepare(self, n: int, layout: tuple[tuple[str, np.dtype], ...] = SELECTION_BUFFERS) -> None:
        """Make the arrays of `layout` not made yet, as `get` would first make them for n elements (np.zeros of
        max(n, ahead)): the engine's set-up, so that the first frame's selection does not (its 20 np.zeros over the
        expected tree were 0.23-0.27 ms of frame 0's 0.6-0.8 ms of selection CPU at 250M splats on the 2-core VM;
        frame 0 of every fly-through on the GPU machine selected in 1.2-1.6 ms against a p99 of 0.6-0.9:
        BENCHMARKS.md, "Manifest pages", frame0). Zeros: what a cleared `get` returns, so a first `get` is the same
        either way."""
        for name, dtype in layout:
            if name not in self._arrays:
                # np.zeros as `get`: their memory written as the tree grows into it (writing it all here, 1.2 ms more
                # of set-up and the memory of the bound, gained nothing measurable in the next frames: frame0)
                self._arrays[name] = np.zeros(max(n, self.ahead), dtype)

    def get(self, name: str, n: int, dtype, zero: bool = False) -> np.ndarray:
        """An array of n elements of this dtype named `name`: zeros with `zero`, else what the last view left."""
        a = self._arrays.get(name)
        if a is None or len(a) < n or a.dtype != dtype:
            # grown ahead: trees grow by pages
            a = np.zeros(max(n, 2 * len(a) if a is not None else n, self.ahead), dtype)
            self._arrays[name] = a
            return a[:n]
        out = a[:n]
        if zero:
            if self.zero is None:
                out.fill(0)
            else:
                self.zero(out.view(np.uint8))
        return out


class PartialView:
    """A view's numbers for the tiles asked for only (`ensure`), where TileView has every tile's: the same arrays
    over every position, valid where computed. `select_near` asks for the tiles it reaches, so a frame looks at
    the cut, its children and the tiles refined above it, not the whole tree held (client.md 1.1). A tile's
    numbers are the same bits as view_numbers' (elementwise arithmetic), so the cut is the same."""

    def __init__(self, a: TileArrays, cam: Camera, opts: SelectionOptions = SelectionOptions(),
                 reduction: float = 2.0, buffers: ViewBuffers | None = None):
        """`buffers`: where to take the per-tile arrays from (ViewBuffers: the last view taken from them is
        overwritten); None: new arrays."""
        self.arrays, self.cam = a, cam
        # the camera's basis and frustum planes, public: the compiled selection reads them (selection_jit)
        self.basis = _basis(cam)
        self.planes = frustum_planes(cam, 1.0, self.basis)
        self.wide_frustum = (a, cam, self.basis, opts.prefetch_margin)
        self.level_step = refinement_level_step(reduction)
        n = len(a.parent)
        self.buffers = buffers
        if buffers is None:
            self.sse, self.radius_px, self.distance = np.empty(n), np.empty(n), np.empty(n)
            self.visible, self.area_px = np.zeros(n, bool), np.zeros(n)
            self.known = np.zeros(n, np.uint8)  # 1: computed
        else:
            f64 = np.dtype(np.float64)
            self.sse, self.radius_px = buffers.get("sse", n, f64), buffers.get("radius_px", n, f64)
            self.distance = buffers.get("distance", n, f64)
            self.visible = buffers.get("visible", n, np.dtype(bool), True)
            self.area_px = buffers.get("area_px", n, f64, True)
            self.known = buffers.get("known", n, np.dtype(np.uint8), True)
        self.looked_at = 0  # tiles whose numbers were computed
        # the planes' normals split for the box corners (boxes_in_frustum's; the compiled selection takes them too)
        self.split = corner_weights(self.planes)
        self._one: list | None = None  # the box test of one tile in Python floats (visible_at), made when needed
        self._visible_of: dict[int, bool] = {}

    def ensure(self, idx) -> None:
        """Compute the numbers of the tiles at these positions (each named once) that have none yet, in one batch."""
        at = np.asarray(idx, np.intp)
        if not at.size:
            return
        at = at[self.known[at] == 0]  # the callers name each tile once
        if not at.size:
            return
        sse, visible, radius_px, area, distance = _numbers(self.arrays, self.cam, self.basis, self.planes, at)
        self.sse[at], self.visible[at], self.radius_px[at], self.area_px[at], self.distance[at] = \
            sse, visible, radius_px, area, distance
        self.known[at] = 1
        self.looked_at += len(at)

    def visible_at(self, i: int) -> bool:
        """Whether tile i's box intersects the frustum (computed alone when its numbers are not: the draw set walks
        below cut tiles not resident yet, one tile at a time)."""
        if self.known[i]:
            return bool(self.visible[i])
        v = self._visible_of.get(i)
        if v is None:
            if self._one is None:  # the same operations in the same order as boxes_in_frustum's: the same answer
                self._one = list(zip(self.planes[:, 3].tolist(), self.split.tolist(), strict=True))
            c = self.arrays.box_corners[i].tolist()
            v = True
            for d, w in self._one:
                s = d + c[0] * w[0]
                for k in range(1, 6):
                    s = s + c[k] * w[k]
                if not s >= 0:
                    v = False
                    break
            self._visible_of[i] = v
        return v


def select(a: TileArrays, view: TileView, cost: np.ndarray, root: int, opts: SelectionOptions,
           previous_refined: frozenset[int] | np.ndarray = frozenset(), reduction: float = 2.0) -> Selection:
    """The cut the view wants: REPLACE refinement from the root, widest on-screen splat spacing first.

    A visible tile whose sse exceeds the threshold is a candidate; candidates are refined in order of the spacing
    of their splats on screen (below; `reduction`: the scene's lod.reduction) while the cut stays within the splat
    and cost budgets; a refinement that does not fit is skipped. Children outside the frustum are dropped from the
    cut (they draw nothing)."""
    # Per-tile numbers over numpy first (visible children's cost and splats, priority): the greedy loop
    # below then does only heap work and list lookups (BENCHMARKS.md, "Figures behind library defaults"). The sums
    # are of whole numbers in float64, exact in any order, so the cut is the same as summing child by child.
    visible, children = view.visible, indexable(a.children)
    child, has_kids, cost_l, splats_l = a.has_parent, a.has_children, cost.tolist(), a.splats_list
    n = len(a.parent)
    kid_cost = np.bincount(a.parent_of_child, weights=np.where(visible, cost, 0.0)[child], minlength=n)
    kid_splats = np.bincount(a.parent_of_child, weights=np.where(visible, a.splats_f64, 0.0)[child], minlength=n)
    threshold = np.full(n, float(opts.max_sse))
    if len(previous_refined):
        threshold[positions(previous_refined)] *= opts.hysteresis
    candidate = (has_kids & visible & (view.sse > threshold)).tolist()
    # Order of refinement: the tile whose splats lie widest apart on screen first. A level holds `reduction` times
    # the splats of the one above over the same region, so on surfaces its splats are reduction^(1/2) closer
    # together; seen from distance d their spacing on screen goes as reduction^(-level/2) / d. Under a budget this
    # keeps the cut close to one level across the view, finer where the view is nearer (measured against error
    # removed per byte, sse x area / added cost, which refined the nearest tiles to their leaves first: a median
    # 1.0 dB better on the real scenes it was not chosen on; BENCHMARKS.md, "LOD against peers").
    prio = refinement_keys(a.level, view.distance, view.sse, refinement_level_step(reduction)).tolist()
    kid_cost_l, kid_splats_l = kid_cost.tolist(), kid_splats.tolist()
    visible_l = visible.tolist()
    # ties of key by tile id (client.md 1.2), not by position: a paged tree's rows follow the order its pages
    # arrived in, the ids are the manifest's, the same for every client and every order of arrival
    ids = a.ids.tolist()

    refined: set[int] = set()
    cut: set[int] = {root}
    priority: dict[int, float] = {root: INF}
    splats = int(splats_l[root])
    total = float(cost_l[root])
    heap: list[tuple[float, int, int]] = [(prio[root], ids[root], root)] if candidate[root] else []
    limited = False
    while heap:
        neg_priority, _, i = heapq.heappop(heap)
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
        for k in children[i]:
            if not visible_l[k]:
                continue
            cut.add(k)
            priority[k] = -neg_priority
            if candidate[k]:
                heapq.heappush(heap, (prio[k], ids[k], k))
    distance = view.distance.tolist()
    # ties (equal priority and distance) by tile id: the order then depends neither on the set's history nor on the
    # rows a paged tree gave its tiles
    cut_sorted = tuple(sorted(cut, key=lambda i: (-priority[i], distance[i], ids[i])))
    return Selection(cut_sorted, frozenset(refined), {i: priority.get(i, 0.0) for i in cut_sorted}, splats, total,
                     limited)


def select_near(a: TileArrays, view: PartialView, cost: np.ndarray, root: int, opts: SelectionOptions,
                previous_refined: frozenset[int] | np.ndarray = frozenset(), near=()) -> Selection:
    """select's cut (the same tiles, order, priorities, splats, cost and budget flag) from the tiles near the last
    frame's cut, as one ordered scan instead of a heap of every reached tile (client.md 1.2).

    select's heap hands out the tiles it reaches in the order of their refinement keys (key, then tile id, as the
    heap compares them) wherever a candidate's key is above its parent's: a tile enters the heap when its parent is
    refined, and the parent's key is smaller. So the loop here is a scan over the set's candidates sorted once by
    key (numpy), deciding each whose parent was refined (reached) with select's budget test; no heap pushes, no walk
    over children. The few candidates whose key is below their parent's (a child's sphere reaching nearer the eye
    than its parent's; the tiles with the eye inside their spheres, ordered by tile id) enter a small heap when
    their parent is refined, as they would enter select's, and that heap is emptied before the scan goes on (its
    tiles are smaller than every tile the scan has left, so select pops them first); their candidate children below
    the scan's position join that heap, the others wait for the scan. The set starts as the root and `near` (the
    engine gives the children of the last frame's cut and refined tiles: the last frame's frontier); when a tile to
    decide lacks children in it, the children of every candidate lacking them join it and the scan goes on where it
    was (the tiles joining sort after it, or hang below tiles not refined). The cut and its priorities follow from
    the refined tiles, in numpy. select_near_heap is the same loop as select's (kept as a second reference)."""
    s = _NearSet(a, view, cost, opts, previous_refined)
    s.add(_first(root, near, s.local))
    # the children of the candidates lacking them, before the first scan: the scan would stop at the first it
    # reaches and add them all (a camera moving on refines below the last cut), and go on with a second sort
    s.add_children_of_candidates()
    children, index = indexable(a.children), s.index
    max_splats, budget = opts.max_splats, opts.budget
    refd = bytearray()
    j0 = index[root]
    splats, total = int(s.splats[j0]), float(s.cost[j0])
    limited = False
    low: list[tuple[float, int, int]] = []  # (key, tile id, index in the set): tiles popped before the scan goes on
    at = (-INF, -1)  # (key, tile id) of the last tile the scan decided
    last = None  # its index in the set
    while True:
        n = len(s.tiles)
        refd += bytes(n - len(refd))
        tiles, prio, cand, parent, tid = s.tiles_a, s.prio_a, s.cand_a, s.parent_a, s.ids_a
        pj = np.where(parent >= 0, s.local[np.maximum(parent, 0)], -1)
        cj = np.flatnonzero(cand)
        if np.isnan(prio[cj]).any():  # no order to scan in (select's heap compares NaN keys its own way)
            return select_near_heap(a, view, cost, root, opts, previous_refined, near)
        order = cj[np.lexsort((tid[cj], prio[cj]))].tolist()  # ties of key by tile id (client.md 1.2)
        # candidates below their candidate parent in the heap's order: they skip the scan's turn
        pc = pj[cj]
        ok = pc >= 0
        ok[ok] = cand[pc[ok]]
        cw, pw = cj[ok], pc[ok]
        below = (prio[cw] < prio[pw]) | ((prio[cw] == prio[pw]) & (tid[cw] < tid[pw]))
        early: dict[int, list[int]] = {}
        for c, p in zip(cw[below].tolist(), pw[below].tolist(), strict=True):
            early.setdefault(p, []).append(c)
        pj_l, need_l = pj.tolist(), (s.kids_in != s.kids_all).tolist()
        sp, co, pr, tl, il = s.splats, s.cost, s.prio, s.tiles, s.ids
        ksp, kco = s.kid_splats.tolist(), s.kid_cost.tolist()
        cand_l = s.candidate
        start = order.index(last) + 1 if last is not None else 0

        lists = (need_l, sp, ksp, co, kco, refd, tl, il, cand_l, pr, children, index)
        stopped, splats, total, limited = _drain(low, at, lists, splats, total, limited, opts)
        if not stopped:
            for j in order[start:] if start else order:
                if j != j0:
                    p = pj_l[j]
                    if p < 0 or not refd[p]:
                        continue  # not reached: its parent was not refined
                if need_l[j]:
                    stopped = True
                    break
                new_splats = splats - sp[j] + int(ksp[j])
                new_total = total - co[j] + kco[j]
                at, last = (pr[j], il[j]), j
                if max_splats is not None and new_splats > max_splats and new_splats > splats:
                    limited = True
                    continue
                if budget is not None and new_total > budget and new_total > total:
                    limited = True
                    continue
                refd[j] = 1
                splats, total = new_splats, new_total
                if j in early:
                    for c in early[j]:
                        heapq.heappush(low, (pr[c], il[c], c))
                    stopped, splats, total, limited = _drain(low, at, lists, splats, total, limited, opts)
                    if stopped:
                        break
        if not stopped:
            break
        s.add_children_of_candidates()
    # the cut: the root unless refined, and the visible children of refined tiles that were not refined themselves;
    # a cut tile's priority is minus its parent's key (the root's inf)
    refined_m = np.frombuffer(bytes(refd), np.uint8).astype(bool)
    vis = np.array(s.visible, bool)
    parent_refined = np.zeros(n, bool)
    has_p = pj >= 0
    parent_refined[has_p] = refined_m[pj[has_p]]
    cj = np.flatnonzero(parent_refined & vis & ~refined_m)
    pri = -prio[pj[cj]]
    if not refd[j0]:
        cj = np.append(cj, j0)
        pri = np.append(pri, INF)
    ct = tiles[cj]
    rank = np.lexsort((tid[cj], view.distance[ct], -pri))
    return Selection.of_arrays(ct[rank], pri[rank], tiles[refined_m], splats, total, limited)


def _first(root: int, near, scratch: np.ndarray) -> np.ndarray:
    """The root and `near`, each once (`scratch`: a position array of -1, left so)."""
    at = np.concatenate([[root], np.asarray(near, np.intp)]).astype(np.intp)
    k = np.arange(len(at))
    scratch[at] = k
    at = at[scratch[at] == k]  # the last of each
    scratch[at] = -1
    return at


def _drain(low: list, at: tuple[float, int], lists: tuple, splats: int, total: float, limited: bool,
           opts: SelectionOptions) -> tuple[bool, int, float, bool]:
    """select_near's small heap popped empty, as select pops those tiles before the scan's next one: (stopped at a
    tile whose children are not all in the set, splats, total, budget flag)."""
    need_l, sp, ksp, co, kco, refd, tl, il, cand_l, pr, children, index = lists
    max_splats, budget = opts.max_splats, opts.budget
    while low:
        c = low[0][2]
        if need_l[c]:
            return True, splats, total, limited
        heapq.heappop(low)
        new_splats = splats - sp[c] + int(ksp[c])
        new_total = total - co[c] + kco[c]
        if max_splats is not None and new_splats > max_splats and new_splats > splats:
            limited = True
            continue
        if budget is not None and new_total > budget and new_total > total:
            limited = True
            continue
        refd[c] = 1
        splats, total = new_splats, new_total
        for k in children[tl[c]]:  # its candidate children below the scan's position join the heap
            jk = index[k]
            if cand_l[jk] and (pr[jk], il[jk]) < at:
                heapq.heappush(low, (pr[jk], il[jk], jk))
    return False, splats, total, limited


def select_near_heap(a: TileArrays, view: PartialView, cost: np.ndarray, root: int, opts: SelectionOptions,
                     previous_refined: frozenset[int] | np.ndarray = frozenset(), near=()) -> Selection:
    """select's cut (the same tiles, order, priorities, splats, cost and budget flag), looking only at the tiles it
    reaches.

    select's greedy loop needs the numbers of the root and of the children of every tile it pops (their sums decide
    whether a refinement fits; the visible ones join the cut and the queue), nothing else. Here its per-tile numpy
    runs over a set of tiles only: the root and `near` (the engine gives the children of the last frame's cut and
    refined tiles: a moving camera's cut is mostly there). When the loop pops a tile whose children are not all in
    the set, the children of every candidate lacking them join it (their numbers in one batch, the sums taken
    again over the set) and the loop goes on: it makes exactly select's moves whatever `near` is, and only the work
    depends on it. The refinement key is the view's (PartialView takes the scene's lod.reduction)."""
    s = _NearSet(a, view, cost, opts, previous_refined)
    s.add(_first(root, near, s.local))
    children, index = indexable(a.children), s.index
    refined: set[int] = set()
    cut: set[int] = {root}
    priority: dict[int, float] = {root: INF}
    j = index[root]
    splats = int(s.splats[j])
    total = float(s.cost[j])
    heap: list[tuple[float, int, int]] = [(s.prio[j], s.ids[j], root)] if s.candidate[j] else []
    limited = False
    while heap:
        neg_priority, _, i = heapq.heappop(heap)
        j = index[i]
        if s.kids_in[j] != s.kids_all[j]:
            s.add_children_of_candidates()
        new_splats = splats - int(s.splats[j]) + int(s.kid_splats[j])
        new_total = total - s.cost[j] + float(s.kid_cost[j])
        if opts.max_splats is not None and new_splats > opts.max_splats and new_splats > splats:
            limited = True
            continue
        if opts.budget is not None and new_total > opts.budget and new_total > total:
            limited = True
            continue
        cut.discard(i)
        refined.add(i)
        splats, total = new_splats, new_total
        visible_l, candidate, prio = s.visible, s.candidate, s.prio
        for k in children[i]:
            jk = index[k]
            if not visible_l[jk]:
                continue
            cut.add(k)
            priority[k] = -neg_priority
            if candidate[jk]:
                heapq.heappush(heap, (prio[jk], s.ids[jk], k))
    distance, ids = view.distance, s.ids
    cut_sorted = tuple(sorted(cut, key=lambda i: (-priority[i], float(distance[i]), ids[index[i]])))
    return Selection(cut_sorted, frozenset(refined), {i: priority.get(i, 0.0) for i in cut_sorted}, splats, total,
                     limited)


class _NearSet:
    """The tiles select_near runs over, with select's per-tile values of each (lists, by index in `tiles`)."""

    def __init__(self, a: TileArrays, view: PartialView, cost: np.ndarray, opts: SelectionOptions,
                 previous_refined: frozenset[int]):
        self.a, self.view, self.cost_a, self.previous = a, view, cost, previous_refined
        self.high = float(opts.max_sse)
        self.low = self.high * opts.hysteresis  # select's threshold of a tile refined last frame (float64, as numpy)
        self.tiles: list[int] = []
        self.ids: list[int] = []  # their tile ids (the tie-break of equal keys: client.md 1.2)
        self.index: dict[int, int] = {}
        self.local = np.full(len(a.parent), -1, np.intp)  # position -> index in `tiles`
        self.visible: list[bool] = []
        self.candidate: list[bool] = []
        self.prio: list[float] = []
        self.cost: list[float] = []
        self.splats: list[int] = []
        self.kid_cost, self.kid_splats = np.zeros(0), np.zeros(0)
        self.kids_in, self.kids_all = np.zeros(0, np.int64), np.zeros(0, np.int64)
        self.orphans: dict[int, int] = {}  # tile -> its parent, not in the set
        if len(previous_refined):
            self.was_refined = np.zeros(len(a.parent), bool)
            self.was_refined[positions(previous_refined)] = True
        # the same as arrays (select_near's scan sorts and tests them in numpy)
        self.tiles_a, self.prio_a, self.ids_a = np.zeros(0, np.intp), np.zeros(0), np.zeros(0, np.int64)
        self.cand_a, self.parent_a = np.zeros(0, bool), np.zeros(0, np.intp)

    def add(self, at: np.ndarray) -> None:
        """Add tiles (positions, each once, none in the set yet): their numbers, then every tile's sums over its
        visible children."""
        a, view = self.a, self.view
        view.ensure(at)
        new = at.tolist()
        start = len(self.tiles)
        self.local[at] = np.arange(start, start + len(new))
        self.index.update(zip(new, range(start, start + len(new)), strict=True))
        self.tiles += new
        ids = a.ids[at]
        self.ids += ids.tolist()
        self.ids_a = np.concatenate([self.ids_a, ids])
        vis, sse = view.visible[at], view.sse[at]
        threshold = np.full(len(new), self.high)
        if len(self.previous):
            threshold[self.was_refined[at]] = self.low
        cand = a.has_children[at] & vis & (sse > threshold)
        self.candidate += cand.tolist()
        prio = refinement_keys(a.level[at], view.distance[at], sse, view.level_step)
        self.prio += prio.tolist()
        self.tiles_a = np.concatenate([self.tiles_a, at])
        self.prio_a = np.concatenate([self.prio_a, prio])
        self.cand_a = np.concatenate([self.cand_a, cand])
        self.parent_a = np.concatenate([self.parent_a, a.parent[at]])
        self.visible += vis.tolist()
        self.cost += self.cost_a[at].tolist()
        self.splats += a.splats[at].tolist()
        # Sums over each tile's visible children in the set, and how many of its children are in it: the new tiles'
        # shares added to their parents. Whole numbers in float64: exact in any order, so the sums are select's.
        grow = np.zeros(len(new))
        self.kid_cost = np.concatenate([self.kid_cost, grow])
        self.kid_splats = np.concatenate([self.kid_splats, grow])
        self.kids_in = np.concatenate([self.kids_in, np.zeros(len(new), np.int64)])
        self.kids_all = np.concatenate([self.kids_all, a.child_count[at]])
        parent = a.parent[at]
        up = np.where(parent >= 0, self.local[parent], -1)
        has_up = up >= 0
        for j in np.flatnonzero(~has_up & (parent >= 0)).tolist():
            self.orphans[new[j]] = int(parent[j])  # a tile whose parent is not in the set (yet)
        up = up[has_up]
        np.add.at(self.kid_cost, up, np.where(vis, self.cost_a[at], 0.0)[has_up])
        np.add.at(self.kid_splats, up, np.where(vis, a.splats_f64[at], 0.0)[has_up])
        np.add.at(self.kids_in, up, 1)
        if self.orphans:  # tiles of the set whose parent joins it now (a `near` that is not closed upwards)
            index = self.index
            old = [(index[o], index[p]) for o, p in self.orphans.items() if p in index]
            if old:
                for o in [o for o, p in self.orphans.items() if p in index]:
                    del self.orphans[o]
                kid, up = (np.array(v, np.intp) for v in zip(*old, strict=True))
                shown = self.view.visible[np.array(self.tiles, np.intp)[kid]]
                np.add.at(self.kid_cost, up, np.where(shown, np.array(self.cost)[kid], 0.0))
                np.add.at(self.kid_splats, up, np.where(shown, np.array(self.splats, np.float64)[kid], 0.0))
                np.add.at(self.kids_in, up, 1)

    def add_children_of_candidates(self) -> None:
        """Add the children of every candidate whose children are not all in the set (the loop may pop any)."""
        lacking = self.tiles_a[self.cand_a & (self.kids_in != self.kids_all)].tolist()
        if not lacking:
            return
        kids = np.fromiter(chain.from_iterable(map(indexable(self.a.children).__getitem__, lacking)), np.intp)
        self.add(kids[self.local[kids] < 0])  # each child once: its parent is one tile


def wanted_bands(a: TileArrays, view: TileView, tiles: tuple[int, ...] | list[int], opts: SelectionOptions,
                 scene_degree: int) -> dict[int, int]:
    """SH bands each tile wants: band b for the tiles that cover the first band_area_share[b - 1] of the cut's
    projected area, taken in order of area per byte of the band (a tile gets band b only with band b - 1)."""
    top = min(opts.sh_degree, scene_degree)
    out = dict.fromkeys(tiles, 0)
    if opts.max_sse <= 0:  # full detail: every band of every tile
        return dict.fromkeys(tiles, top)
    if top <= 0:
        return out
    at = np.asarray(tiles, np.intp)
    area = dict(zip(tiles, view.area_px[at].tolist(), strict=True))
    # ties of area per byte by tile id (client.md 1.2's tie rule), not by position: a paged tree's positions follow
    # the order its pages arrived in
    tile_id = dict(zip(tiles, a.ids[at].tolist(), strict=True))
    total = sum(area.values())
    for b in range(1, top + 1):
        share = opts.band_area_share[b - 1]
        band_bytes = a.band_bytes[:, b - 1]
        order = sorted((i for i in tiles if out[i] == b - 1),
                       key=lambda i: (-area[i] / max(1.0, float(band_bytes[i])), tile_id[i]))
        covered = 0.0
        for i in order:
            if covered >= share * total and share < 1.0:
                break
            out[i] = b
            covered += area[i]
    return out



def wanted_bands_at(a: TileArrays, view: TileView, cut_at: np.ndarray, opts: SelectionOptions,
                    scene_degree: int) -> np.ndarray:
    """wanted_bands' answer as an array over the cut's positions `cut_at` (each once), in their order: the same
    bands, from numpy sorts and sums (the same operations on the same values: the order's keys divided as Python
    divides, the areas summed in the cut's order and covered in the band's order, one addition at a time)."""
    top = min(opts.sh_degree, scene_degree)
    at = np.asarray(cut_at, np.intp)
    if opts.max_sse <= 0:  # full detail: every band of every tile
        return np.full(len(at), top, np.int64)
    # not np.zeros: numpy's calloc over 1 KB lets the interpreter lock go (once a frame on the frame loop); a fill
    # keeps it up to 500 elements
    out = np.full(len(at), 0, np.int64)
    if top <= 0 or not len(at):
        return out
    area = view.area_px[at]
    total = sum(area.tolist())  # Python's sum, in the cut's order, as wanted_bands
    for b in range(1, top + 1):
        share = opts.band_area_share[b - 1]
        idx = np.flatnonzero(out == b - 1)
        if not idx.size:
            break
        key = -area[idx] / np.maximum(1.0, a.band_bytes[at[idx], b - 1].astype(np.float64))
        order = idx[np.lexsort((a.ids[at[idx]], key))]  # ties by tile id, as wanted_bands'
        if share < 1.0:  # the first tile reached with the covered area at or above the share stops the band
            covered = np.cumsum(area[order])  # one addition at a time, in order: the loop's running sum
            before = np.concatenate([[0.0], covered[:-1]])
            stop = np.flatnonzero(before >= share * total)
            order = order[:stop[0]] if stop.size else order
        out[order] = b
    return out


def draw_set(a: TileArrays, view: TileView, sel: Selection, resident: np.ndarray, root: int,
             stand_ins: bool = True) -> list[int]:
    """The tiles to draw now: the wanted cut where resident, else what covers the same region without holes.

    A tile the selection refines is replaced by its visible children only when every one of them can be drawn
    (resident, or covered by its own resident descendants); otherwise the tile itself is drawn. A wanted tile
    that is not resident yet is covered by its resident descendants if they cover its view (they were wanted
    before the camera moved back), else by an ancestor. Never a tile together with a descendant.

    `stand_ins=False`: a wanted tile not resident is covered by an ancestor only (descendants standing in hold
    more splats than the cut: the engine asks for this set when the other one is over the splat budget)."""

    visible_at, children = view.visible_at, indexable(a.children)  # a PartialView tests the tiles the walk reaches only
    refined = sel.refined  # once: the walk asks for each tile it reaches

    def shown(i: int) -> list[int]:
        return [k for k in children[i] if visible_at(k)]

    def cover(i: int) -> list[int] | None:
        if i in refined:
            parts = _cover_all(shown(i))
            if parts is not None:
                return parts
        if resident[i]:
            return [i]
        if stand_ins and i not in refined:
            kids = shown(i)
            if kids:
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
             cost: np.ndarray | None = None, boxes: Callable | None = None) -> list[tuple[float, int]]:
    """Tiles the view will probably want next, best first: children of cut tiles close to the refinement
    threshold (the camera moving closer) and tiles just outside the frustum (the camera turning).

    Bounded by the budget: no children of cut tiles when the budget ended the cut (it would not let them in), and
    with `cost` (per tile, the units of sel.cost) the list stops at prefetch_share of the cut's cost. `boxes`: the
    widened frustum's box test (wide_visible's)."""
    out: list[tuple[float, int]] = []
    sse, children = view.sse, indexable(a.children)
    near_cut = []
    if not sel.budget_limited and opts.max_sse > 0:
        near_cut = [i for i in sel.cut if children[i] and sse[i] > opts.max_sse / opts.prefetch_margin]
    # just outside the frustum, children of refined tiles (a cut tile is visible, so never one of these), in tile
    # id order (client.md 1.2's tie rule; the scores below tie at 0.5): a paged tree's positions follow the order its
    # pages arrived in, the ids do not. The children of the cut tiles above come in the cut's order (its ties by id)
    # and each tile's children in the manifest's order, neither of them the positions'
    edge = [k for r in sel.refined for k in children[r]]
    edge = [k for _, k in sorted(zip(a.ids[np.asarray(edge, np.intp)].tolist(), edge, strict=True))]
    view.ensure(edge)
    look = edge + [k for i in near_cut for k in children[i]]
    wide = dict(zip(look, wide_visible(view, look, boxes), strict=True))
    for i in near_cut:
        score = float(sse[i]) / opts.max_sse
        out += [(score, k) for k in children[i] if wide[k]]
    visible = view.visible
    out += [(0.5, k) for k in edge if wide[k] and not visible[k]]
    out.sort(key=lambda x: -x[0])  # stable: equal scores keep the order above
    if cost is not None:
        allowance = opts.prefetch_share * sel.cost
        # Python's running sum and bisect (np.cumsum's sums in its order, searchsorted's side="right"): numpy's let
        # the interpreter lock go over 500 tiles
        spent = list(accumulate(cost[[i for _, i in out]].tolist()))
        out = out[:bisect_right(spent, allowance)]
    return out


# The least the children of a page head hold, as a share of `lod.reduction` times its splats, for the page rule
# below (`pages_the_budget_can_use`). Not a rule of the format (lod.md 1: a reader must not rely on the tree's
# shape): on the 13 real trees of BENCHMARKS.md (default encode, its merge "auto") a tile's children hold 0.87 to
# 1.27 times reduction x its splats (0.93 on donut and biker, where this share was chosen, 0.87 on playbot and
# statue-trumpet, held out); 0.75 keeps a margin under every one of them. A tree below it would only have a page
# left unread that the budget could have used (its head drawn instead of its children).
PAGE_CHILDREN_SHARE = 0.75


@dataclass(frozen=True)
class _RefinementTurns:
    """The turns at which select decides a selection's refinements, and what each adds, for pages_the_budget_can_use
    and cut_a_page_may_undo (client.md 1.11)."""
    refined: np.ndarray  # positions of the refined tiles (sel.refined_at)
    slot: np.ndarray  # position -> index in `refined`, -1 where not refined; its last entry: no parent
    parent_slot: np.ndarray  # per refinement: its parent's index in `refined` (-1: the root)
    levels: np.ndarray  # per refinement: its tile's level
    by_level: list[int]  # the levels of `levels`, parents' before children's
    turn: np.ndarray  # per refinement: its key, or its parent's turn where that is later
    child_splats: np.ndarray  # per refinement: its visible children's (cut or refined tiles') splats
    child_cost: np.ndarray  # and their cost
    head_key: np.ndarray  # per head: its own refinement key
    parent_turn: np.ndarray  # per head: its parent's turn (-inf for the root)


def _refinement_turns(a: TileArrays, view, cost: np.ndarray, sel: Selection, heads: np.ndarray,
                      reduction: float) -> _RefinementTurns:
    cut, refined = sel.cut_at, np.asarray(sel.refined_at, np.intp)
    step = refinement_level_step(reduction)
    # each refined tile's key, or its parent's turn where that is later (select's queue hands out a child whose key
    # is below its parent's right after the parent)
    slot = np.full(len(a.parent) + 1, -1, np.intp)
    slot[refined] = np.arange(len(refined))
    parent_slot = slot[a.parent[refined]]
    turn = refinement_keys(a.level[refined], view.distance[refined], view.sse[refined], step)
    levels = a.level[refined]
    by_level = np.unique(levels).tolist()
    for lv in by_level:  # parents before children
        at = np.flatnonzero((levels == lv) & (parent_slot >= 0))
        turn[at] = np.maximum(turn[at], turn[parent_slot[at]])
    members = np.concatenate([cut, refined])
    members = members[a.parent[members] >= 0]
    owner = slot[a.parent[members]]
    head_key = refinement_keys(a.level[heads], view.distance[heads], view.sse[heads], step)
    head_parent = slot[a.parent[heads]]  # a cut tile's parent is refined; the root has none
    parent_turn = np.full(len(heads), -INF)
    parent_turn[head_parent >= 0] = turn[head_parent[head_parent >= 0]]
    return _RefinementTurns(refined, slot, parent_slot, levels, by_level, turn,
                            np.bincount(owner, a.splats_f64[members], len(refined)),
                            np.bincount(owner, cost[members], len(refined)), head_key, parent_turn)


def pages_the_budget_can_use(a: TileArrays, view, cost: np.ndarray, root: int, sel: Selection, heads: np.ndarray,
                             opts: SelectionOptions, reduction: float, chunk_splats: int, chunk_bytes: float,
                             children_share: float = PAGE_CHILDREN_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """(wanted, waiting), each (len(heads),) bool: whether the budget could let the children of a page head in
    (client.md 1.11), its page wanted now or waiting for earlier heads' pages (below). `heads` are
    cut tiles whose page is not read and that the selection would refine (visible, sse above max_sse), leaves of
    the tree held. A head's refinement would be decided at its turn in the selection's order (select's queue: the
    refinement keys, a tile whose key is not above its parent's right after the parent), against the cut's splats
    and cost at that moment: the root's plus every refinement decided before it (refined tiles' visible children
    less themselves). Its page is wanted unless even the least its children could add would not fit: where the
    head's box lies inside every frustum plane (then so do its children's: lod.md 2, every child visible), that is
    `children_share * reduction` times its splats (and those splats' chunks' bytes) less its own; where its box
    crosses a plane its children may all be outside (the refinement could shrink the cut), and its page is wanted.
    So where the budget lets a page's children in, the page is wanted: the cut that converges is the one it is when
    every page is read (the selection's history to that head is the same either way). Of the heads that pass, in
    the order of their turns, each sets aside its children's likely addition (reduction times its splats, where
    all are visible) for the heads after it, so that pages wanted only if earlier heads' children do not fit wait
    for those heads' pages (a frame later): such a head is `waiting` (it stands for its children as a head whose
    page loads does; where the earlier heads' children fit it becomes a cut tile again). Without a budget: every
    page wanted (the engine asks only while the camera rests). `view`: the frame's TileView or PartialView (the
    numbers of the cut and refined tiles computed); `chunk_splats`, `chunk_bytes`: the pool's slot (`cost` counts
    whole slots)."""
    heads = np.asarray(heads, np.intp)
    if not len(heads) or (opts.max_splats is None and opts.budget is None):
        return np.ones(len(heads), bool), np.zeros(len(heads), bool)
    splats = a.splats_f64
    t = _refinement_turns(a, view, cost, sel, heads, reduction)
    refined, turn, head_key, parent_turn = t.refined, t.turn, t.head_key, t.parent_turn
    add_splats = t.child_splats - splats[refined]
    add_cost = t.child_cost - cost[refined]
    order = np.lexsort((a.ids[refined], turn))  # ties of key by tile id, as the selection's (client.md 1.2)
    turns = turn[order]
    before_splats = np.concatenate([[0.0], np.cumsum(add_splats[order])])
    before_cost = np.concatenate([[0.0], np.cumsum(add_cost[order])])
    # the refinements decided before each head (ties of key: the later side, where the head follows its parent;
    # the earlier, where its own key orders it)
    follows = head_key <= parent_turn
    head_turn = np.maximum(head_key, parent_turn)
    n_before = np.where(follows, np.searchsorted(turns, head_turn, "right"), np.searchsorted(turns, head_turn, "left"))
    at_splats = splats[root] + before_splats[n_before]
    at_cost = cost[root] + before_cost[n_before]
    # the least the refinement could add, where every child is visible
    least_children = np.ceil(children_share * reduction * splats[heads])
    add_splats_least = least_children - splats[heads]
    add_cost_least = np.ceil(least_children / chunk_splats) * chunk_bytes - cost[heads]
    planes = frustum_planes(view.wide_frustum[1], 1.0, view.wide_frustum[2])
    inside = boxes_inside_frustum(a.box_corners[heads], planes)
    add_splats_least = np.where(inside, add_splats_least, -splats[heads])  # all children may be outside
    add_cost_least = np.where(inside, add_cost_least, -cost[heads])
    # In the order of the heads' turns, each wanted page's likely addition (its children at reduction times its
    # splats, where all are visible; nothing set aside for a head crossing the frustum) is set aside for the heads
    # after it: a page the budget could use only if an earlier head's children do not come in waits for that page
    # (a frame later; where the earlier head's children fit, it is not read at all). Once no page is wanted
    # nothing is set aside, so the test that decides convergence is the one above.
    likely = np.ceil(reduction * splats[heads])
    set_splats = np.where(inside, np.maximum(likely - splats[heads], 0.0), 0.0).tolist()
    set_cost = np.where(inside, np.maximum(np.ceil(likely / chunk_splats) * chunk_bytes - cost[heads], 0.0),
                        0.0).tolist()
    max_splats = INF if opts.max_splats is None else float(opts.max_splats)
    budget = INF if opts.budget is None else float(opts.budget)
    fits = ((add_splats_least <= 0) | (at_splats + add_splats_least <= max_splats)) & \
        ((add_cost_least <= 0) | (at_cost + add_cost_least <= budget))
    wanted = np.zeros(len(heads), bool)
    held_splats = held_cost = 0.0
    s_at, c_at = at_splats.tolist(), at_cost.tolist()
    s_add, c_add = add_splats_least.tolist(), add_cost_least.tolist()
    for j in np.flatnonzero(fits)[np.lexsort((a.ids[heads[fits]], head_turn[fits]))].tolist():
        if (s_add[j] <= 0 or s_at[j] + held_splats + s_add[j] <= max_splats) and \
                (c_add[j] <= 0 or c_at[j] + held_cost + c_add[j] <= budget):
            wanted[j] = True
            held_splats += set_splats[j]
            held_cost += set_cost[j]
    return wanted, fits & ~wanted


def cut_a_page_may_undo(a: TileArrays, view, cost: np.ndarray, root: int, sel: Selection, heads: np.ndarray,
                        opts: SelectionOptions, reduction: float) -> np.ndarray:
    """(len(sel.cut_at),) bool: the cut tiles whose place in the cut a page still to come could undo (client.md
    1.11), not fetched while the pages of `heads` (the heads whose pages are wanted or wait) load. A page brings its
    head's subtree, which the selection refines at the head's turn and below it for as long as the budget lets it
    (not only the children: pages_the_budget_can_use's least); every refinement decided after the earliest such
    head's turn (select's order: pages_the_budget_can_use's turns) then sees less budget left, and one that no
    longer fits is refused, and the tiles it brought leave the cut (a payload fetched for them was given up: donut
    `--page-levels 5` at 50 %, 158 KB a view against 355 KB drawn). So where a budget can bind (`--max-splats`, or
    the byte budget limited this selection), a cut tile below a refinement that adds splats or bytes and is
    decided after that turn is held back; the refinements before it are the same whatever the pages bring
    (pages_the_budget_can_use's "why the same cut"), and so are the cut tiles below them only. Decides when
    payloads are fetched, never the cut."""
    cut = sel.cut_at
    out = np.zeros(len(cut), bool)
    heads = np.asarray(heads, np.intp)
    if not len(heads) or not len(sel.refined_at) or (opts.max_splats is None and not sel.budget_limited):
        return out
    t = _refinement_turns(a, view, cost, sel, heads, reduction)
    refined, parent_slot = t.refined, t.parent_slot
    adds = (t.child_splats > a.splats_f64[refined]) | (t.child_cost > cost[refined])
    # the earliest head's turn (a tie goes to the refinement, as a head that follows its parent would)
    first = float(np.maximum(t.head_key, t.parent_turn).min())
    undone = (t.turn > first) & adds
    for lv in t.by_level:  # below an undone refinement everything may leave the cut too
        at = np.flatnonzero((t.levels == lv) & (parent_slot >= 0))
        undone[at] |= undone[parent_slot[at]]
    up = t.slot[a.parent[cut]]
    has = up >= 0
    out[has] = undone[up[has]]
    return out


def boxes_inside_frustum(corners: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(T,) True where an axis-aligned box ((T, 6) [max, min] corners) lies inside every plane: its corner least
    along each plane's normal (the "negative vertex") is inside, so every box within it is visible."""
    n = planes[:, :3]
    split = np.concatenate([np.minimum(n, 0.0), np.maximum(n, 0.0)], axis=1)  # [max, min] weights, negative vertex
    s = planes[None, :, 3] + np.einsum("tk,pk->tp", corners, split)
    return np.all(s >= 0, axis=1)
