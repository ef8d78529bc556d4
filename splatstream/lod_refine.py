"""The optional refinement of the merged LOD levels against renders of the full-detail scene (lod.md 6, the optional
step; `encode --lod-refine`; issue 31): the numpy parts.

The optimiser itself (torch + gsplat on a CUDA GPU in `refine_gpu/`, or numba on the CPU in `refine_cpu/`) lives
outside the core and is handed to the encoder as a callable (`LodRefiner`, EncodeOptions.lod_refiner), as the
streaming client's compiled kernels are: the core never imports torch, gsplat or numba. What the core owns is
everything the refinement's result depends on besides the optimiser: which splats each level's picture is made of
(`level_cuts`), the cameras it is trained and judged on (`refine_cameras`, a rule of the scene alone), which
candidate a level keeps (`kept_candidate`), what the manifest records (`SharedRefineSettings.record`, `level_outcome`),
and how refined values enter the tree (`split_merged`, `refine_tree`: checked, applied to the merged tiles only,
bounds recomputed; geometric errors stay the unrefined tree's). Both optimisers use these, so the GPU's and the
CPU's refinements differ only in how they fit.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from .camera import Camera, bounds_orbit_views, look_at_near_far, robust_bounds
from .errors import InputError
from .format.limits import (
    MAX_ABS_POSITION,
    MAX_ABS_SH,
    MAX_LOG_SCALE,
    MIN_LOG_SCALE,
    describe_violations,
    domain_violations,
)
from .format.manifest import LevelRefinement, LodRefinement
from .gaussians import Gaussians
from .lod import Tile, interior_bounds

# The method name the manifest records (lod.refinement.method): the merged splats' values fitted by gradient
# descent to renders of the full-detail scene (lod.md 6).
REFINE_METHOD = "render-fit"
# What each variant optimises (phase 1, BENCHMARKS.md "Refining the merged levels against the originals": B won at
# the first merged level on several scenes, C at the coarser ones; A, opacity and DC colour alone, never won there,
# but was already +1.02 dB or more above the best peer at all 48 points). The GPU refiner tries B and C; A, the
# geometry fixed, is the CPU refiner's (refine_cpu/). Higher SH bands are kept as merged: no variant changes sh_rest.
VARIANT_FIELDS: dict[str, tuple[str, ...]] = {
    "A": ("opacity_logits", "sh_dc"),
    "B": ("opacity_logits", "sh_dc", "log_scales"),
    "C": ("opacity_logits", "sh_dc", "log_scales", "positions", "rotations"),
}
UNREFINED = "none"
# The camera rule's defaults (phase 1's training set; the validation set is the same rule, another seed and count).
TRAINING_CAMERAS = 96
TRAINING_SEED = 0
VALIDATION_CAMERAS = 32
VALIDATION_SEED = 1
# Each refiner's defaults live here, where the CLI's help and defaults read them without importing a shell (torch,
# numba). The GPU refiner's (refine_gpu/, phase 1's, BENCHMARKS.md "Refining the merged levels against the
# originals"): Adam steps per level and variant, render size; its cameras are the rule's defaults above.
GPU_ITERATIONS = 300
GPU_SIZE_PX = 384
# The CPU refiner's (refine_cpu/, BENCHMARKS.md "Refining the merged levels on the CPU"): Adam steps per level,
# render size, camera counts and seeds; since refinecheap31 (BENCHMARKS.md, "The CPU refinement at 0.4x its CPU") 30
# steps, each over one of 2 batches of the training cameras, at 4x the learning rates falling linearly to 0.1x, and
# half the validation and far cameras (60 full-batch steps at 0.1 / 0.02, 16 validation, 16 + 8 far before).
CPU_ITERATIONS = 30
CPU_SIZE_PX = 256
CPU_TRAINING_CAMERAS = 32
CPU_VALIDATION_CAMERAS = 8
CPU_TRAINING_SEED = 1000
CPU_VALIDATION_SEED = 1001
CPU_BATCHES = 2  # step t fits training camera k where k % CPU_BATCHES == (t - 1) % CPU_BATCHES
CPU_LR_OPACITY_LOGIT = 0.4
CPU_LR_SH_DC = 0.08
CPU_LR_FINAL = 0.1  # the learning rates' multiplier at the last step, linear from 1 at the first
# and its far cameras per level (lod_refine.far_level_cameras; the seeds + the level)
CPU_FAR_TRAINING_CAMERAS = 8
CPU_FAR_VALIDATION_CAMERAS = 4
CPU_FAR_TRAINING_SEED = 2000
CPU_FAR_VALIDATION_SEED = 3000
CPU_FAR_WEIGHT = 0.1  # the far cameras' mean squared error x this in the loss, the near cameras' x 1
DISTANCE_RANGE = (0.6, 1.6)  # x the orbit distance of scene_orbit_views
ELEVATION_DEG = (-20.0, 70.0)  # about up; the benchmark's orbit views sit at 25 deg
# The far cameras of a level (far_level_cameras; issue 31, branch far31): the distances at which a client without a
# budget draws the level, by the client's default screen-space error threshold (client_gl SelectionOptions.max_sse,
# lod.md 3): a tile is drawn, not refined, while geometric_error x focal / distance <= this many px.
FAR_SSE_PX = 1.5
FAR_MAX_DISTANCE = 64.0  # x the orbit distance: the farthest far camera (the scene a few px across beyond that)
FAR_ROOT_SPAN = 4.0  # the root is drawn at every distance past its own: its far cameras span this factor from there
FAR_MIN_PX = 8  # the smallest far camera's side (px)
FAR_FILL = 1.25  # a far camera's side: this x the px the scene's fitted extent spans at its nearest distance

# The optimiser's side (refine_gpu, refine_cpu): (full-detail splats, the tree, up, progress) -> ({merged tile id:
# its refined splats}, the record). A refiner whose attribute `runs_by_partitions` is true also refines partitioned
# encodes (encode/partitioned.py: each merge domain in its own task, on any engine, so it must pickle), and is then
# called with the keyword `frame=` (a CameraFrame: the whole scene's, which places its cameras); `name`, where
# it has one, is how messages name it; `for_concurrent_fits(n)`, where it has one, gives the refiner to run when n
# fits run at once (a share of the machine's cores each; partitioned.py asks it before the partitions and the upper
# levels); `peak_bytes(splats)`, where it has one, the memory its fit of a tree of that many full-detail splats takes
# beyond the tree (partitioned.py counts it in what a refined partition task needs of --memory-per-worker), and
# `scene_pairs(sample, splats, frame, up, kd depths)` with `with_pairs_per_pixel(p)`, where it has them, let that
# model count the scene's own pairs a pixel (the CPU refiner's; partitioned._check_scene_pairs).
LodRefiner = Callable[[Gaussians, list[Tile], tuple[float, float, float], Callable[[str, float], None]],
                      tuple[dict[int, Gaussians], LodRefinement]]


@dataclass(frozen=True)
class CameraFrame:
    """What places the camera rule (refine_cameras, far_level_cameras): the robust bounds (camera.robust_bounds: the
    per-axis median and the central 95 % box) of the scene's splat centres. A partitioned encode's merge domain is
    fitted from the WHOLE scene's frame, taken from the scene's sample of centres (encode/sample.py: every centre up
    to 2,000,000, so the in-memory encode's own), not from its own splats: the domain is seen from where the scene is
    (BENCHMARKS.md, "Closing the partitioned refinement's gap")."""
    median: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @staticmethod
    def of(positions: np.ndarray) -> CameraFrame:
        return CameraFrame(*robust_bounds(positions))


def _frame(where: np.ndarray | CameraFrame) -> CameraFrame:
    return where if isinstance(where, CameraFrame) else CameraFrame.of(where)


def _orbit(where: np.ndarray | CameraFrame, up, size: int) -> Camera:
    """The orbit view the camera rule is placed by (camera.scene_orbit_views' first, 25 deg up, of the frame)."""
    f = _frame(where)
    return bounds_orbit_views(f.median, f.lo, f.hi, 1, size, size, up=up, elevation_deg=25.0)[0]


@dataclass(frozen=True)
class LevelCut:
    """One merged level's whole picture: the merged tiles at depth `level` (refined) and the leaves at depths
    <= `level` (the originals, drawn with them and fixed), as a client draws the tree cut at that depth."""
    level: int
    merged: tuple[int, ...]
    fixed: tuple[int, ...]


def level_cuts(tiles: list[Tile]) -> list[LevelCut]:
    """Every merged level of the tree, the coarsest (the root's) first."""
    return [LevelCut(d, tuple(t.id for t in tiles if t.level == d and t.children),
                     tuple(t.id for t in tiles if t.level <= d and not t.children))
            for d in sorted({t.level for t in tiles if t.children})]


def refine_cameras(positions: np.ndarray | CameraFrame, up, n: int, size: int, seed: int = TRAINING_SEED
                   ) -> list[Camera]:
    """`n` square cameras of `size` px looking at the scene's orbit centre (scene_orbit_views: the robust median,
    the distance that fits the robust bounds, its fov and `up`; of the positions, or of their CameraFrame) from a
    jittered Fibonacci band of directions (elevations ELEVATION_DEG about `up`), at distances log-uniform over
    DISTANCE_RANGE x the orbit distance, each target jittered by 3 % of that distance. A rule of the scene alone: no
    benchmark's views (theirs sit exactly on the 25 deg orbit), and a seed gives another set (the validation
    cameras)."""
    return _band_cameras(positions, up, n, size, seed, DISTANCE_RANGE, size)


def orbit_distance_and_focal(positions: np.ndarray | CameraFrame, up, size: int) -> tuple[float, float]:
    """The orbit distance of refine_cameras' rule (world units) and the focal length (px) of its `size` px cameras."""
    orbit = _orbit(positions, up, size)
    return math.dist(orbit.eye, orbit.target), size / (2.0 * math.tan(math.radians(orbit.fov_y_deg) / 2.0))


def level_far_range(tiles: list[Tile], cut: LevelCut, dist: float, focal: float) -> tuple[float, float] | None:
    """The distances (x the orbit distance `dist`) past refine_cameras' DISTANCE_RANGE at which a client without a
    budget draws level `cut.level` through `size` px cameras of focal length `focal`: its merged tiles' (median)
    geometric error projects to at most FAR_SSE_PX there, and the level above's (median) to more (the root: up to
    FAR_ROOT_SPAN x its own distance); capped at FAR_MAX_DISTANCE. None where that range lies within DISTANCE_RANGE
    (a fine level: drawn without a budget only from near, where refine_cameras already sits)."""
    err = float(np.median([tiles[i].geometric_error for i in cut.merged]))
    lo = err * focal / FAR_SSE_PX / dist
    above = [t.geometric_error for t in tiles if t.level == cut.level - 1 and t.children]
    hi = float(np.median(above)) * focal / FAR_SSE_PX / dist if above else FAR_ROOT_SPAN * lo
    lo, hi = max(lo, DISTANCE_RANGE[1]), min(hi, FAR_MAX_DISTANCE)
    return (lo, hi) if hi > lo * 1.01 else None


def far_level_cameras(positions: np.ndarray | CameraFrame, up, n: int, size: int, seed: int,
                      far_range: tuple[float, float]) -> list[Camera]:
    """`n` cameras of refine_cameras' rule (directions, jitter) at distances log-uniform over `far_range` x the orbit
    distance (level_far_range), each the centre crop of a `size` px camera there: the same px per world unit (a
    splat as many px across as the client draws it at that distance) in a square of side FAR_FILL x the scene's
    fitted extent at the nearest of them (at least FAR_MIN_PX), so the scene fills about as much of each as of a
    near camera and each camera's pixels count alike in the fit's mean."""
    side = min(size, max(FAR_MIN_PX, math.ceil(FAR_FILL * size / far_range[0])))
    return _band_cameras(positions, up, n, size, seed, far_range, side)


def _band_cameras(positions: np.ndarray | CameraFrame, up, n: int, size: int, seed: int,
                  distance_range: tuple[float, float], side: int) -> list[Camera]:
    """refine_cameras' rule at `distance_range` x the orbit distance, each camera the centre `side` px crop of a
    `size` px one (side == size: the whole camera)."""
    orbit = _orbit(positions, up, size)
    centre = np.asarray(orbit.target, np.float64)
    dist = math.dist(orbit.eye, orbit.target)
    fov = orbit.fov_y_deg if side == size else \
        math.degrees(2.0 * math.atan(math.tan(math.radians(orbit.fov_y_deg) / 2.0) * side / size))
    u = np.asarray(orbit.up, np.float64)
    u = u / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = helper - u * (helper @ u)
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    rng = np.random.default_rng(seed)
    lo, hi = (math.sin(math.radians(e)) for e in ELEVATION_DEG)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cams = []
    for i in range(n):
        s = lo + (hi - lo) * (i + rng.uniform(0.2, 0.8)) / n  # sin(elevation), jittered within its stratum
        az = golden * i + rng.uniform(-0.3, 0.3)
        c = math.sqrt(max(0.0, 1.0 - s * s))
        d = c * (math.cos(az) * a + math.sin(az) * b) + s * u
        r = dist * math.exp(rng.uniform(math.log(distance_range[0]), math.log(distance_range[1])))
        target = centre + rng.normal(0.0, 0.03 * dist, 3)
        eye = target + r * d
        cams.append(Camera(tuple(eye), tuple(target), tuple(u), fov, side, side, *look_at_near_far(eye, target)))
    return cams


def with_values(g: Gaussians, values: dict[str, np.ndarray]) -> Gaussians:
    """`g` with some of its fields replaced (float32; rotations normalised: the optimiser's are not unit)."""
    f = {k: np.ascontiguousarray(values.get(k, getattr(g, k)), np.float32)
         for k in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc")}
    if "rotations" in values:
        q = f["rotations"]
        f["rotations"] = (q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)).astype(np.float32)
    return Gaussians(f["positions"], f["rotations"], f["log_scales"], f["opacity_logits"], f["sh_dc"], g.sh_rest)


@dataclass
class SharedRefineSettings:
    """What every refiner is set by and the manifest's record names (lod.refinement): the square render size, the
    optimiser's steps per level (and variant), the training and validation cameras (count and seed of
    `refine_cameras`' rule), and where the refiner's progress lines go. Each refiner's settings extend these with
    its own defaults (refine_gpu.levels.RefineSettings, refine_cpu.levels.CpuRefineSettings)."""
    iterations: int
    size: int
    training_cameras: int
    validation_cameras: int
    training_seed: int
    validation_seed: int
    log: Callable[[str], None] = field(default=lambda msg: None, repr=False)

    def cameras(self, positions: np.ndarray | CameraFrame, up) -> tuple[list[Camera], list[Camera]]:
        """The training and the validation cameras of a scene (`refine_cameras`: one rule, two seeds)."""
        return (refine_cameras(positions, up, self.training_cameras, self.size, self.training_seed),
                refine_cameras(positions, up, self.validation_cameras, self.size, self.validation_seed))

    def record(self, variants: tuple[str, ...], levels: list[LevelRefinement]) -> LodRefinement:
        """The manifest's record of a refinement by these settings that tried `variants` (VARIANT_FIELDS' names)."""
        return LodRefinement(REFINE_METHOD, tuple((v, VARIANT_FIELDS[v]) for v in variants), self.size,
                             self.iterations, self.training_cameras, self.training_seed, self.validation_cameras,
                             self.validation_seed, tuple(levels))


def psnr_of(mse: float) -> float:
    """A validation MSE as the record's PSNR: finite where the MSE is 0 (99 dB) or not finite (-99 dB), as the
    manifest's numbers must be (metrics.psnr_from_mse says inf)."""
    return 99.0 if mse <= 0 else 10.0 * math.log10(1.0 / mse) if math.isfinite(mse) else -99.0


def kept_candidate(validation_mse: dict[str, float]) -> str:
    """The candidate (UNREFINED or a variant) with the lowest validation MSE; `validation_mse` names UNREFINED first,
    so that a tie, or a fit whose error is not a number, keeps the level as built."""
    return min(validation_mse, key=lambda c: validation_mse[c])


def level_outcome(cut: LevelCut, validation_mse: dict[str, float], kept: str, merged_splats: int,
                  seconds: float, log: Callable[[str], None]) -> tuple[LevelRefinement, dict[str, float]]:
    """One level's entry of the record (the candidates' validation PSNR, rounded to 3 decimals, and what was kept),
    its line in the log, and the PSNR per candidate (for the refiner's report)."""
    psnr = {c: round(psnr_of(e), 3) for c, e in validation_mse.items()}
    log(f"level {cut.level} ({merged_splats:,} merged splats): validation PSNR "
        + ", ".join(f"{c} {v:.2f}" for c, v in psnr.items()) + f" dB; kept {kept} ({seconds:.1f} s)")
    return LevelRefinement(cut.level, kept, tuple(psnr.items())), psnr


def split_merged(tiles: list[Tile], cut: LevelCut, values: dict[str, np.ndarray]) -> dict[int, Gaussians]:
    """A level's fitted values (fields over its merged splats, concatenated in `cut.merged`'s order) as each merged
    tile's refined splats (`with_values`), the input of `apply_refined`."""
    refined: dict[int, Gaussians] = {}
    off = 0
    for tid in cut.merged:
        n = len(tiles[tid].gaussians)
        refined[tid] = with_values(tiles[tid].gaussians, {f: v[off:off + n] for f, v in values.items()})
        off += n
    return refined


def in_domain(field_name: str, v: np.ndarray) -> np.ndarray:
    """A fitted field within the format's limits (format.md 4.8), which an optimiser step may in principle cross:
    clamped, not refused (apply_refined refuses what is still outside)."""
    if field_name == "log_scales":
        return np.clip(v, MIN_LOG_SCALE, MAX_LOG_SCALE)
    if field_name == "sh_dc":
        return np.clip(v, -MAX_ABS_SH, MAX_ABS_SH)
    if field_name == "positions":
        return np.clip(v, -MAX_ABS_POSITION, MAX_ABS_POSITION)
    return v


def apply_refined(tiles: list[Tile], refined: dict[int, Gaussians]) -> list[Tile]:
    """A copy of the tree with the merged tiles of `refined` holding their refined splats, and the bounds (box and
    sphere, lod.interior_bounds: the splats' 3-sigma extents and the children's volumes) of those tiles and of their
    ancestors recomputed, deepest first, so a parent still covers its children. Geometric errors stay as built.
    Refused (InputError): a leaf (the originals never change), an unknown tile, another splat count or SH degree,
    values outside the format's domain."""
    parent = {c: t.id for t in tiles for c in t.children}
    out = list(tiles)
    dirty: set[int] = set()
    for tid, g in refined.items():
        if not 0 <= tid < len(tiles) or not tiles[tid].children:
            raise InputError("<lod refinement>", f"tile {tid}", "not a merged tile of this tree (leaves never change)")
        old = tiles[tid].gaussians
        if len(g) != len(old) or g.sh_degree != old.sh_degree:
            raise InputError("<lod refinement>", f"tile {tid}", f"{len(g)} splats of SH degree {g.sh_degree} for "
                             f"{len(old)} of SH degree {old.sh_degree}")
        bad = domain_violations(g)
        if bad:
            raise InputError("<lod refinement>", f"tile {tid}", describe_violations(bad, len(g))[1])
        out[tid] = replace(out[tid], gaussians=g)
        t = tid
        while t is not None and t not in dirty:
            dirty.add(t)
            t = parent.get(t)
    for tid in sorted(dirty, reverse=True):  # children's ids are above their parent's: deepest first
        t = out[tid]
        lo, hi, c, r = interior_bounds(t.gaussians, [out[k] for k in t.children])
        out[tid] = replace(t, box_min=lo, box_max=hi, sphere_center=c, sphere_radius=r)
    return out


def refine_tree(g: Gaussians, tiles: list[Tile], up, refiner: LodRefiner,
                progress: Callable[[str, float], None], frame: CameraFrame | None = None
                ) -> tuple[list[Tile], LodRefinement]:
    """The tree with its merged levels refined by `refiner` (the optimiser's side), and the record the manifest
    keeps. `frame`: where the cameras are placed from (None: `g`'s own positions, the whole scene in memory)."""
    up = tuple(float(v) for v in up)
    refined, record = refiner(g, tiles, up, progress) if frame is None else \
        refiner(g, tiles, up, progress, frame=frame)
    return apply_refined(tiles, refined), record


# ---------------------------------------------------------------------------------------------- by partitions


def refine_subtree(g: Gaussians, tiles: dict[int, Tile], up, refiner: LodRefiner,
                   progress: Callable[[str, float], None], frame: CameraFrame | None = None
                   ) -> tuple[dict[int, Tile], LodRefinement]:
    """refine_tree over one subtree of a larger tree (a partitioned encode's merge domain, or the tiles above the
    partitions with the partitions' roots as its leaves): `tiles` by global id, `g` the splats its leaves hold (the
    "full detail" its levels are fitted to), `frame` the whole scene's CameraFrame (its cameras: the subtree alone in
    the frame of the whole scene, as the client sees it; None: around `g`). The subtree is numbered 0.. in the order
    of its global ids (a parent's id is below its children's in both) for the refiner, and its refined tiles come
    back by global id; the record names the global depths."""
    ids = sorted(tiles)
    local = {tid: i for i, tid in enumerate(ids)}
    renumbered = [replace(tiles[tid], id=i, children=[local[c] for c in tiles[tid].children])
                  for i, tid in enumerate(ids)]
    refined, record = refine_tree(g, renumbered, up, refiner, progress, frame)
    return {tid: replace(t, id=tid, children=list(tiles[tid].children)) for tid, t in zip(ids, refined, strict=True)}, \
        record


def domains_record(domains: list[LodRefinement], above: LodRefinement | None) -> LodRefinement:
    """The manifest's one record (lod.md 6, "The refinement by partitions") of a partitioned encode's refinements:
    the levels above the partitions as `above` fitted them (None: not refined, none listed), and each level inside
    the merge domains once, from every domain's own fit and choice: kept the variant where any domain kept it (else
    none), each candidate's validation PSNR that of the domains' mean validation MSE, the level as written (each
    domain's kept candidate) recorded under the variant. Settings (size, steps, cameras) are the domains'."""
    first = domains[0] if domains else above
    assert first is not None, "no refinement to record"
    by_level: dict[int, list[LevelRefinement]] = {}
    for r in domains:
        for lv in r.levels:
            by_level.setdefault(lv.level, []).append(lv)
    variants = [v for v, _ in first.variants]
    levels = list(above.levels) if above is not None else []
    for level in sorted(by_level):
        entries = by_level[level]
        kept = next((v for v in variants if any(e.kept == v for e in entries)), UNREFINED)
        mse = {c: float(np.mean([10.0 ** (-dict(e.validation_psnr)[c] / 10.0) for e in entries]))
               for c in dict(entries[0].validation_psnr)}
        if kept != UNREFINED:  # the level as written: each domain's kept candidate
            mse[kept] = float(np.mean([10.0 ** (-dict(e.validation_psnr)[e.kept] / 10.0) for e in entries]))
        levels.append(LevelRefinement(level, kept, tuple((c, round(psnr_of(e), 3)) for c, e in mse.items())))
    return replace(first, levels=tuple(levels))
