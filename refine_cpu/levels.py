"""The merged LOD levels refined on the CPU (lod.md 6, the optional step; `encode --lod-refine cpu`; issue 31):
variant A, each merged splat's opacity logit and DC colour fitted with the geometry fixed.

Each merged level is refined ALONE, drawn as its whole cut (lod_refine.level_cuts: its merged tiles and the
shallower leaves, the originals fixed), by Adam on the MSE of the clamped images against renders of the full detail
(refine_cpu.raster, our renderer's conventions) from lod_refine.refine_cameras' training cameras. With the geometry
fixed, each camera's per-pixel (splat, gaussian weight) pairs are built once per level and every step is a sparse
forward and backward pass over them (raster.loss_and_grad), each step over one batch of the training cameras in turn
(since refinecheap31: 2 batches, the learning rates falling linearly). The fit, and the level as built, are then
judged on VALIDATION cameras (the same rule, another seed and count), and the fit is kept only where it beats the
level as built. Each level's loss and validation error also count, weighted 0.1, small FAR cameras where a client
without a budget draws that level (lod_refine.level_far_range, far_level_cameras; branch far31), so the coarse
levels seen from far away keep what the near cameras alone traded away. Phase 1 (BENCHMARKS.md, "Refining the merged
levels against the originals", variant A on gsplat) measured this variant +1.02 dB or more above the best peer at
all 48 points.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numba
import numpy as np

from splatstream import lod_refine
from splatstream.cores import available_cores
from splatstream.format.manifest import LevelRefinement, LodRefinement
from splatstream.gaussians import Gaussians, covariances
from splatstream.lod import Tile, split_axis
from splatstream.lod_refine import (
    CPU_BATCHES,
    CPU_FAR_TRAINING_CAMERAS,
    CPU_FAR_TRAINING_SEED,
    CPU_FAR_VALIDATION_CAMERAS,
    CPU_FAR_VALIDATION_SEED,
    CPU_FAR_WEIGHT,
    CPU_ITERATIONS,
    CPU_LR_FINAL,
    CPU_LR_OPACITY_LOGIT,
    CPU_LR_SH_DC,
    CPU_SIZE_PX,
    CPU_TRAINING_CAMERAS,
    CPU_TRAINING_SEED,
    CPU_VALIDATION_CAMERAS,
    CPU_VALIDATION_SEED,
    UNREFINED,
    in_domain,
    kept_candidate,
    level_cuts,
    level_outcome,
    split_merged,
)

from . import raster

# CpuLevelRefiner.peak_bytes: pairs a pixel of the training cameras (raster keeps a pixel's pairs while T > 1e-6;
# measured 21 on biker's whole scene at 256 px, 25 and 41 on fruit_drops at 128 and 32 px), and copies of a
# full-detail splat's values held at the peak (fitted to fruit_drops at 32 px, where the splats dominate, on its
# first, compiling fit: 30.4 MiB, 14.4 once compiled; on the safe side).
PAIRS_PER_PIXEL = 32
# The scene's own pairs a pixel, where the caller gives a sample of its splats (CpuLevelRefiner.with_scene_pairs,
# estimate_pairs; issue 31, branch memmodel31): the estimate, of the full detail, times this margin, chosen on donut
# copies (bench/tile_scene.py) from 2^13 to 2^18 splats (BENCHMARKS.md, "The refiner's memory from the scene's own
# pairs a pixel"). The fit holds the largest MERGED level's pairs, measured 0.38-0.67x the full detail's estimate
# there (and 0.43-0.52x on the held-out real scenes); their peaks needed at most 0.59x it in the pair term (RSS of one
# run of 2^13 splats; 0.51 in the other), so 0.8 leaves 1.2x over the largest level's pairs and 1.36x over the
# peaks' need. At most PAIRS_SAMPLE of its splats (every k-th), on the fit's near training cameras, in tiles of
# PAIRS_TILE px.
PAIRS_MARGIN = 0.8
PAIRS_SAMPLE = 16384
PAIRS_TILE = 16
PAIRS_GRID = 4  # the depth map's cells (px): a splat's box is widened to them
SPLAT_COPIES = 14
# and what the first fit of a process adds whatever its size: numba's cached kernels loaded and its threads started
# (45 MiB measured over a fit of 3,000 splats at 8 px; bench/refiner_memory.py at 64 px measured 80 MiB above the tree
# where the rest of the model gave 61)
KERNELS_BYTES = 48 << 20
VARIANT = "A"  # the one variant fitted here (lod_refine.VARIANT_FIELDS): opacity and DC colour, the geometry fixed


@dataclass
class CpuRefineSettings(lod_refine.SharedRefineSettings):
    """The CPU fit's settings (BENCHMARKS.md, "Refining the merged levels on the CPU"): 256 px renders, 32 training
    and 8 validation cameras, Adam at these learning rates, 30 steps each over one of 2 batches of the training
    cameras, the rates falling linearly to 0.1x; per level 8 + 4 far cameras whose error counts 0.1 (BENCHMARKS.md,
    "The CPU refinement's far cameras"; the steps, batches, rates and counts since refinecheap31: "The CPU refinement
    at 0.4x its CPU")."""
    iterations: int = CPU_ITERATIONS
    size: int = CPU_SIZE_PX
    training_cameras: int = CPU_TRAINING_CAMERAS
    validation_cameras: int = CPU_VALIDATION_CAMERAS
    training_seed: int = CPU_TRAINING_SEED
    validation_seed: int = CPU_VALIDATION_SEED
    lr_opacity_logit: float = CPU_LR_OPACITY_LOGIT
    lr_sh_dc: float = CPU_LR_SH_DC
    # the learning rates' multiplier at the last step, linear from 1 at the first (1: constant)
    lr_final: float = CPU_LR_FINAL
    # the training cameras (near and far) in this many batches, camera k in batch k % batches; step t fits batch
    # (t - 1) % batches (1: every step every camera, full batch)
    batches: int = CPU_BATCHES
    # each level's far cameras (lod_refine.far_level_cameras; 0: none, the fit of the near cameras alone)
    far_training_cameras: int = CPU_FAR_TRAINING_CAMERAS
    far_validation_cameras: int = CPU_FAR_VALIDATION_CAMERAS
    far_training_seed: int = CPU_FAR_TRAINING_SEED
    far_validation_seed: int = CPU_FAR_VALIDATION_SEED
    far_weight: float = CPU_FAR_WEIGHT  # the far cameras' mean error x this, beside the near cameras' (x 1)
    # numba threads of one fit; 0: numba's default (every core). With `share_cores` (a local cluster: its workers
    # share this machine) CpuLevelRefiner.for_concurrent_fits sets it to the cores / the fits that run at once.
    threads: int = 0
    share_cores: bool = False
    # the pairs a pixel peak_bytes counts; None: PAIRS_PER_PIXEL (no sample of the scene given); with_scene_pairs
    # sets the scene's own (its estimate times PAIRS_MARGIN). The fit never reads it: the bytes do not depend on it.
    pairs_per_pixel: float | None = None

    def far_cameras(self, positions: np.ndarray | lod_refine.CameraFrame, up, tiles: list[Tile],
                    cuts: list[lod_refine.LevelCut]) -> list[tuple[list, list, tuple[float, float] | None]]:
        """Per level of `cuts`, its far (training, validation) cameras and their distances (x the orbit distance);
        none where the level has no far range (lod_refine.level_far_range) or the counts are 0."""
        if self.far_training_cameras <= 0:
            return [([], [], None) for _ in cuts]
        dist, focal = lod_refine.orbit_distance_and_focal(positions, up, self.size)
        out = []
        for cut in cuts:
            rng = lod_refine.level_far_range(tiles, cut, dist, focal)
            if rng is None:
                out.append(([], [], None))
                continue
            out.append((lod_refine.far_level_cameras(positions, up, self.far_training_cameras, self.size,
                                                     self.far_training_seed + cut.level, rng),
                        lod_refine.far_level_cameras(positions, up, self.far_validation_cameras, self.size,
                                                     self.far_validation_seed + cut.level, rng), rng))
        return out


class CpuLevelRefiner:
    """lod_refine.LodRefiner on the CPU: (splats, tree, up, progress) -> ({tile id: refined splats}, record).
    Picklable (its settings' log included, by Dask's cloudpickle), so it runs in a partitioned encode's tasks."""

    name = "--lod-refine cpu"
    # the pairs a pixel peak_bytes counts without the scene's (partitioned.py: also the most it counts for the levels
    # above the merge domains, fitted over merged roots the scene's sample does not hold)
    default_pairs_per_pixel = PAIRS_PER_PIXEL
    # a partitioned encode refines its merge domains with it, each in its own task (lod.md 6, "The refinement by
    # partitions"): its fit's bytes do not depend on the threads it runs on (raster.GRADIENT_ROWS)
    runs_by_partitions = True

    def __init__(self, settings: CpuRefineSettings | None = None):
        self.settings = settings or CpuRefineSettings()
        self.report: list[dict] = []  # per level: splats, pairs, validation PSNR per candidate, kept, seconds

    def for_concurrent_fits(self, fits: int) -> CpuLevelRefiner:
        """This refiner for `fits` fits at once on this machine (settings.share_cores): cores / fits numba threads
        each, so that 16 workers fitting 4 partitions give each fit 4 threads, not 1, and an upper tier of one domain
        every core; without share_cores (an existing cluster's machines) itself."""
        if not self.settings.share_cores:
            return self
        return CpuLevelRefiner(replace(self.settings, threads=max(1, available_cores() // max(1, fits))))

    def with_scene_pairs(self, sample: Gaussians, splats: int, placed_by: np.ndarray | lod_refine.CameraFrame, up,
                         cell_depth: int = 0) -> CpuLevelRefiner:
        """This refiner with the pairs a pixel of peak_bytes estimated from the scene: `sample` some of its
        `splats` splats (every k-th: estimate_pairs keeps at most PAIRS_SAMPLE of them), seen from the fit's near
        training cameras (placed by `placed_by`, as __call__'s), times PAIRS_MARGIN. `cell_depth` > 0: a fit over one
        kd subtree of that depth (a partitioned encode's merge domain, or an upper domain, seen from the whole
        scene's cameras: its splats alone, where they fall in the images), the most of the sample's kd cells."""
        return self.with_pairs_per_pixel(self.scene_pairs(sample, splats, placed_by, up, (cell_depth,))[cell_depth])

    def scene_pairs(self, sample: Gaussians, splats: int, placed_by: np.ndarray | lod_refine.CameraFrame, up,
                    cell_depths: tuple[int, ...]) -> dict[int, float]:
        """with_scene_pairs' pairs a pixel (PAIRS_MARGIN included) for each of `cell_depths`, at one pass."""
        train, _ = self.settings.cameras(placed_by, up)
        return {d: PAIRS_MARGIN * v for d, v in estimate_pairs(sample, splats, train, cell_depths).items()}

    def with_pairs_per_pixel(self, pairs: float | None) -> CpuLevelRefiner:
        """This refiner with peak_bytes counting `pairs` a pixel (0: a lower bound of the fit, the pairs left out;
        None: PAIRS_PER_PIXEL)."""
        return CpuLevelRefiner(replace(self.settings, pairs_per_pixel=pairs))

    def peak_bytes(self, splats: int, splat_bytes: int) -> int:
        """The fit's own peak over a tree of `splats` full-detail splats of `splat_bytes` bytes each, beyond the
        tree (a model, for the memory a refined partition task needs; partitioned.py): numba's kernels
        (KERNELS_BYTES), the clamped targets (float32 RGB, every near and far camera at the full size), the training
        set's pair lists (raster.PairLists: a pixel offset and PAIRS_PER_PIXEL pairs of 8 bytes a pixel, or
        settings.pairs_per_pixel where set, the scene's own: with_scene_pairs; a far camera at its largest crop),
        and a full-detail splat's share: each training camera's projected splat (16 bytes), the fit kernel's
        per-camera tables (one a gradient row) and SPLAT_COPIES copies of its values (the level cuts'
        concatenations, the fit's and the tree's copies). With the scene's pairs: BENCHMARKS.md, "The refiner's
        memory from the scene's own pairs a pixel" (1.4-2.6x the peaks from 2^13 to 2^18 splats, where the splats'
        share is the most of the rest). Before it, measured (bench/refiner_memory.py; BENCHMARKS.md, "The fit's
        kernel, and the refiner's memory measured again"): the peak RSS above the tree, the first fit of each
        process (numba's cached kernels loaded), 220 / 273 / 381 / 561 MiB on biker (SH0) slices of 2^14 / 2^15 /
        2^16 / 2^17 splats, this model 821 / 851 / 911 / 1,031 MiB (1.8-3.7x); 438 and 495 MiB (two runs) on a
        2^18-splat slice of flowers (SH2), the model 1,607 MiB; 80 MiB at 64 px on 2^13 splats of donut copies
        (bench/tile_scene.py), the model 109; tracemalloc's peak (numpy's arrays: the model less KERNELS_BYTES) 14.4
        / 128.9 MiB on fruit_drops (SH3, 4,721 splats) at 32 / 128 px once compiled (30.4 at 32 px compiling), 31.6
        / 206 MiB; 990 / 1,741 MiB on 2^20 / 2^21 splats of donut copies (SH0, the GPU machine's 16 threads), the
        model 2,711 / 4,631 (2.7x; a near pixel held 10.7 / 18 pairs, under the 32 assumed); 5,231 MiB for a
        2^20-splat SH3 domain at the defaults. The model figures above are before raster.GRADIENT_ROWS went 8 -> 16
        and the gradient rows were counted (refinewall31): 768 B a splat more since."""
        s = self.settings
        pixels = s.size * s.size
        near_and_far = s.training_cameras + s.validation_cameras + s.far_training_cameras + s.far_validation_cameras
        training = s.training_cameras + s.far_training_cameras
        # a far camera is a crop of side at most FAR_FILL x size / the nearest far distance (lod_refine's
        # far_level_cameras; its range starts at DISTANCE_RANGE[1] or beyond): its pair lists at that side, not the
        # full size (its targets stay counted at the full size: every level's are held through the fit)
        far_side = min(s.size, max(lod_refine.FAR_MIN_PX,
                                   math.ceil(lod_refine.FAR_FILL * s.size / lod_refine.DISTANCE_RANGE[1])))
        training_pixels = s.training_cameras * pixels + s.far_training_cameras * far_side * far_side
        # raster.loss_and_grad's per-camera tables (raster.PACKED_COLUMNS float64 a projected splat), one a gradient
        # row at most, each at most every splat, and the gradient rows (raster.GRADIENT_COLUMNS float64 a splat a row;
        # SPLAT_COPIES' fit held 8 rows of them, so counting all 16 is on the safe side by 8)
        tables = raster.GRADIENT_ROWS * (raster.PACKED_COLUMNS + raster.GRADIENT_COLUMNS) * 8
        pairs = PAIRS_PER_PIXEL if s.pairs_per_pixel is None else s.pairs_per_pixel
        # a step over one of several batches reads its targets (every batches-th camera's, a strided view) through a
        # contiguous copy (raster.loss_and_grad), held for the step
        batch = 0 if s.batches <= 1 else 12 * (pixels * -(-s.training_cameras // s.batches)
                                               + far_side * far_side * -(-s.far_training_cameras // s.batches))
        return int(KERNELS_BYTES + 12 * pixels * near_and_far + batch + (8 + 8 * pairs) * training_pixels
                   + (16 * training + tables + SPLAT_COPIES * splat_bytes) * splats)

    def __call__(self, g: Gaussians, tiles: list[Tile], up, progress, frame: lod_refine.CameraFrame | None = None
                 ) -> tuple[dict[int, Gaussians], LodRefinement]:
        s = self.settings
        degree = g.sh_degree
        # the cameras: placed by the whole scene's frame (a partitioned encode's merge domain: lod_refine.CameraFrame),
        # else by `g`'s own positions (the whole scene in memory)
        placed_by = frame if frame is not None else g.positions
        train, valid = s.cameras(placed_by, up)
        cuts = level_cuts(tiles)
        # progress: the full-detail renders count as one level's worth, each level one
        steps = len(cuts) + 1
        progress("refine", 0.0)
        t0 = time.perf_counter()
        if s.threads:
            # a partition task beside others on one machine: its share of the cores, not all of them each (the bytes
            # do not depend on it: the gradient sums in fixed rows)
            numba.set_num_threads(max(1, min(s.threads, numba.config.NUMBA_NUM_THREADS)))
        cov3d = covariances(g)  # the full detail's covariances, once for all 48 cameras
        far = s.far_cameras(placed_by, up, tiles, cuts)
        n_far = sum(len(a) + len(b) for a, b, _ in far)
        n_renders = len(train) + len(valid) + n_far
        done = [0]

        def render(c, cov: np.ndarray) -> np.ndarray:
            # the full-detail renders move the bar too (15 s of a silent first step on lod_tile: newuser58)
            img = raster.render(g, c, degree, cov)
            done[0] += 1
            progress("refine", min(done[0] / n_renders, 0.99) / steps)
            return img

        gt = np.clip(np.stack([render(c, cov3d) for c in train]), 0.0, 1.0)
        gt_valid = np.clip(np.stack([render(c, cov3d) for c in valid]), 0.0, 1.0)
        far_gt = [tuple(np.clip(np.stack([render(c, cov3d) for c in cams]), 0.0, 1.0)
                        if cams else None for cams in (train_far, valid_far)) for train_far, valid_far, _ in far]
        del cov3d
        s.log(f"full-detail renders: {len(train) + len(valid)} at {s.size} px, {n_far} far "
              f"({time.perf_counter() - t0:.1f} s)")
        progress("refine", 1 / steps)
        refined: dict[int, Gaussians] = {}
        levels: list[LevelRefinement] = []
        self.report = []
        for k, cut in enumerate(cuts):
            t1 = time.perf_counter()
            merged = Gaussians.concatenate([tiles[i].gaussians for i in cut.merged])
            parts = [tiles[i].gaussians for i in cut.fixed] + [merged]
            whole = Gaussians.concatenate(parts)
            first = len(whole) - len(merged)  # the merged splats come last
            (far_train, far_valid, far_range), (far_gt_train, far_gt_valid) = far[k], far_gt[k]
            sets, batch_of = [], []
            batches = max(1, s.batches)
            for b in range(batches):
                for cams, targets, weight in ((train, gt, 1.0), (far_train, far_gt_train, s.far_weight)):
                    if cams[b::batches]:
                        sets.append((raster.pair_lists(whole, cams[b::batches], degree), targets[b::batches], weight))
                        batch_of.append(b)
            # the fit's last step is not the level's end (its validation follows): below k + 2, so that the last
            # level's "100%" comes after its line, not a minute before it (newuser57, donut: 58 s)
            logits, dc = fit_opacity_dc(sets, whole, first, s, batch_of, lambda it, k=k: progress(
                "refine", (k + 1 + min(it / s.iterations, 0.99)) / steps))
            # the validation pairs only once the training pairs are gone: the peak holds one set, not both
            train_pairs, train_bytes = sum(len(pl.g) for pl, _, _ in sets), sum(pl.nbytes for pl, _, _ in sets)
            del sets
            vsets = [(raster.pair_lists(whole, valid, degree), gt_valid, 1.0)]
            if far_valid:
                vsets.append((raster.pair_lists(whole, far_valid, degree), far_gt_valid, s.far_weight))
            op_all = whole.opacities.astype(np.float64)
            dc_all = raster.SH_C0 * whole.sh_dc.astype(np.float64)
            op_fit, dc_fit = op_all.copy(), dc_all.copy()
            op_fit[first:] = _sigmoid(logits)
            dc_fit[first:] = raster.SH_C0 * dc
            # the near and the far cameras' mean errors weighted as in the fit: their weighted mean is the level's
            weights = [w for _, _, w in vsets]
            before_parts = [raster.loss_and_grad(pl, op_all, dc_all, t, grad=False)[0] for pl, t, _ in vsets]
            after_parts = [raster.loss_and_grad(pl, op_fit, dc_fit, t, grad=False)[0] for pl, t, _ in vsets]
            before = float(np.average(before_parts, weights=weights))
            after = float(np.average(after_parts, weights=weights))
            scores = {UNREFINED: before, VARIANT: after}
            kept = kept_candidate(scores)
            if kept == VARIANT:
                refined.update(split_merged(tiles, cut, {"opacity_logits": logits, "sh_dc": dc}))
            secs = time.perf_counter() - t1
            level, psnr = level_outcome(cut, scores, kept, len(merged), secs, s.log)
            levels.append(level)
            self.report.append({"level": cut.level, "merged_splats": len(merged), "splats": len(whole),
                                "pairs": train_pairs + sum(len(pl.g) for pl, _, _ in vsets),
                                "training_pairs": train_pairs, "training_pair_bytes": train_bytes,
                                "pair_bytes": train_bytes + sum(pl.nbytes for pl, _, _ in vsets),
                                "validation_psnr": psnr,
                                "validation_psnr_near_far": {
                                    c: [round(lod_refine.psnr_of(e), 3) for e in parts]
                                    for c, parts in ((UNREFINED, before_parts), (VARIANT, after_parts))},
                                "far_cameras": len(far_train) + len(far_valid),
                                "far_px": far_train[0].width if far_train else 0,
                                "far_range": [round(x, 2) for x in far_range] if far_range else None,
                                "kept": kept, "iterations": s.iterations, "seconds": round(secs, 2)})
            progress("refine", (k + 2) / steps)
            del vsets
        return refined, s.record((VARIANT,), levels)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    # float64 throughout the fit (gaussians.sigmoid rounds to float32, the stored opacity's precision)
    return 1.0 / (1.0 + np.exp(-x))


def fit_opacity_dc(sets: list[tuple[raster.PairLists, np.ndarray, float]], whole: Gaussians, first: int,
                   s: CpuRefineSettings, batch_of: list[int] | None = None,
                   on_step: Callable[[int], None] = lambda it: None) -> tuple[np.ndarray, np.ndarray]:
    """Adam on the opacity logits and DC colour of splats `first`: of `whole` (the rest fixed) against each set's
    target (its cameras' full-detail renders, clamped; a set: cameras of one size, the near ones and a level's far
    ones), the loss the sum of the sets' mean errors times their weights. `batch_of[i]`: set i's batch; step t uses
    the sets of batch (t - 1) % s.batches (None: every set every step, full batch). The learning rates fall linearly
    from themselves at the first step to s.lr_final x themselves at the last. `on_step(steps done)` after
    each step (the encode's progress: a large level's fit takes minutes). Returns the fitted logits and sh_dc
    (float32; sh_dc within the format's limits), after `s.iterations` steps."""
    logits = whole.opacity_logits[first:].astype(np.float64).copy()
    sh_dc = whole.sh_dc[first:].astype(np.float64).copy()
    op_all = whole.opacities.astype(np.float64)
    dc_all = raster.SH_C0 * whole.sh_dc.astype(np.float64)
    params = [logits, sh_dc]
    lrs = [s.lr_opacity_logit, s.lr_sh_dc]
    m1 = [np.zeros_like(p) for p in params]
    m2 = [np.zeros_like(p) for p in params]
    b1, b2, eps = 0.9, 0.999, 1e-15
    for it in range(1, s.iterations + 1):
        decay = 1.0 - (1.0 - s.lr_final) * (it - 1) / max(1, s.iterations - 1)
        sig = _sigmoid(logits)
        op_all[first:] = sig
        dc_all[first:] = raster.SH_C0 * sh_dc
        g_op, g_dc = 0.0, 0.0
        batch = (it - 1) % max(1, s.batches)
        for i, (pl, target, weight) in enumerate(sets):
            if batch_of is not None and batch_of[i] != batch:
                continue
            _, g_o, g_d = raster.loss_and_grad(pl, op_all, dc_all, target)
            g_op, g_dc = g_op + weight * g_o, g_dc + weight * g_d
        grads = [g_op[first:] * sig * (1.0 - sig), g_dc[first:] * raster.SH_C0]
        for p, gr, a, b, lr in zip(params, grads, m1, m2, lrs, strict=True):
            a *= b1
            a += (1 - b1) * gr
            b *= b2
            b += (1 - b2) * gr * gr
            p -= decay * lr * (a / (1 - b1 ** it)) / (np.sqrt(b / (1 - b2 ** it)) + eps)
        on_step(it)
    return logits.astype(np.float32), in_domain("sh_dc", sh_dc).astype(np.float32)


def _sample_rows(splats: int, keep: int) -> np.ndarray:
    """Every k-th of `splats` rows, at most `keep` of them (the first and the last included): a fixed choice."""
    return np.linspace(0, splats - 1, keep).astype(np.int64) if splats > keep else np.arange(splats)


def kd_cells(positions: np.ndarray, depth: int) -> list[np.ndarray]:
    """The rows of `positions` in 2^depth cells, split as the tile tree splits (lod.split_axis: the longest side of
    the cell's centre box; at the median, ties by row): the sample's own approximation of a partitioned encode's
    kd subtrees at that depth (their splits are exact over the whole scene: partitioned._top_splits)."""
    cells = [np.arange(len(positions))]
    for _ in range(depth):
        nxt = []
        for rows in cells:
            if len(rows) < 2:
                nxt += [rows, rows[:0]]
                continue
            p = positions[rows]
            axis = split_axis(p.min(axis=0), p.max(axis=0))
            order = rows[np.argsort(p[:, axis], kind="stable")]
            nxt += [np.sort(order[:len(order) // 2]), np.sort(order[len(order) // 2:])]
        cells = nxt
    return cells


def estimate_pairs(sample: Gaussians, splats: int, cams: list, cell_depths: tuple[int, ...] = (0,)
                   ) -> dict[int, float]:
    """The pairs a pixel of `cams` (raster.PairLists: every (pixel, splat) with g >= 1/255 until T < T_STORE) that a
    fit over one kd cell of each depth of `cell_depths` (kd_cells; depth 0: the whole scene) can make, the most over
    that depth's cells, for a scene of `splats` splats of which `sample` is an even share (every k-th), estimated
    without any pair list.

    Each sampled splat's footprint (the ellipse where g >= 1/255: 2 pi ln 255 / sqrt(det conic) px, by
    raster.project's conventions, the low-pass included) times splats / the sample, spread evenly over its box (in
    cells of PAIRS_GRID px, the box widened to them) and summed per cell of the scene into a depth map averaged per
    tile of PAIRS_TILE px (D, a pixel's pairs without occlusion); a pixel's pairs capped where T falls under T_STORE:
    at most K = (ln(1 / T_STORE) + ln(1 / (1 - ALPHA_MAX))) / tau, tau the footprint-weighted mean of -ln(1 - alpha)
    over the cell's pairs (g is log-uniform over a Gaussian's footprint; alpha = min(0.99, opacity g), 0 under
    1/255: Wald's bound on the pairs until the optical depth passes ln(1 / T_STORE)). Per tile min(D, K), summed over
    the tiles and the cameras, over their pixels. Spreading a splat over its box and a tile evens D out, which only
    raises the sum of min(D, K) (it is concave): on the safe side. A cell's fit sees only its own splats, so its D is
    its own, where they fall in the images. At least 64 sampled splats a cell where the sample has them.
    Deterministic: the same sample, cameras and depths give the same numbers."""
    out = {d: 0.0 for d in cell_depths}
    if len(sample) == 0 or not cams:
        return out
    rows = _sample_rows(len(sample), max(PAIRS_SAMPLE, 64 << max(cell_depths)))
    g = sample if len(rows) == len(sample) else sample.subset(rows)
    share = splats / len(g)
    cov3d = covariances(g)
    opacity = g.opacities.astype(np.float64)
    cut = math.log(1.0 / raster.ALPHA_MIN)  # ln 255: the footprint's edge, g = exp(-u) for u in [0, cut]
    u = (np.arange(32) + 0.5) / 32 * cut
    alpha = np.minimum(raster.ALPHA_MAX, opacity[:, None] * np.exp(-u)[None, :])
    tau = np.where(alpha >= raster.ALPHA_MIN, -np.log1p(-alpha), 0.0).mean(axis=1)  # per splat, over its pairs
    stop = math.log(1.0 / raster.T_STORE) + math.log(1.0 / (1.0 - raster.ALPHA_MAX))
    labels = {}
    for depth in cell_depths:
        lab = np.zeros(len(g), np.int64)
        for k, cell in enumerate(kd_cells(g.positions, depth)):
            lab[cell] = k
        labels[depth] = (lab, 1 << depth)
    per = PAIRS_TILE // PAIRS_GRID  # grid cells a tile side
    totals = {d: np.zeros(n) for d, (_, n) in labels.items()}
    pixels = 0
    for cam in cams:
        w, h = cam.width, cam.height
        pixels += w * h
        p = raster.project(g, cam, 0, cov3d)
        if len(p.index) == 0:
            continue
        a, b, c = p.conic[:, 0], p.conic[:, 1], p.conic[:, 2]
        det = np.maximum(a * c - b * b, 1e-300)
        area = 2.0 * math.pi * cut / np.sqrt(det)  # px where g >= 1/255
        rx, ry = np.sqrt(2.0 * cut * c / det), np.sqrt(2.0 * cut * a / det)  # the ellipse's half extents
        gw, gh = -(-w // PAIRS_TILE) * per, -(-h // PAIRS_TILE) * per  # the grid, whole tiles
        # the box in grid cells, widened to whole cells, and the part of it inside the image's
        x0 = np.floor((p.xy[:, 0] - rx) / PAIRS_GRID)
        x1 = np.floor((p.xy[:, 0] + rx) / PAIRS_GRID) + 1
        y0 = np.floor((p.xy[:, 1] - ry) / PAIRS_GRID)
        y1 = np.floor((p.xy[:, 1] + ry) / PAIRS_GRID) + 1
        density = share * area / ((x1 - x0) * (y1 - y0))  # a grid cell's pairs from this splat
        cx0, cx1 = np.clip(x0, 0, gw), np.clip(x1, 0, gw)
        cy0, cy1 = np.clip(y0, 0, gh), np.clip(y1, 0, gh)
        inside = (cx1 > cx0) & (cy1 > cy0)
        if not inside.any():
            continue
        ix0, ix1, iy0, iy1 = (v[inside].astype(np.int64) for v in (cx0, cx1, cy0, cy1))
        d = density[inside]
        weight = d * (iy1 - iy0) * (ix1 - ix0)  # each splat's pairs inside the image
        splat = p.index[inside]
        for depth, (lab, n) in labels.items():
            cell = lab[splat]
            diff = np.zeros((n, gh + 1, gw + 1))
            np.add.at(diff, (cell, iy0, ix0), d)
            np.add.at(diff, (cell, iy0, ix1), -d)
            np.add.at(diff, (cell, iy1, ix0), -d)
            np.add.at(diff, (cell, iy1, ix1), d)
            grid = diff.cumsum(axis=1).cumsum(axis=2)[:, :gh, :gw]
            tile = grid.reshape(n, gh // per, per, gw // per, per).sum(axis=(2, 4)) / (PAIRS_TILE * PAIRS_TILE)
            tw = np.bincount(cell, weight, n)
            mean_tau = np.bincount(cell, weight * tau[splat], n) / np.maximum(tw, 1e-300)
            cap = np.where(mean_tau > 0, stop / np.maximum(mean_tau, 1e-300), np.inf)
            # the tiles' pixels inside the image (the last row and column of tiles may hang over its edge)
            tx = np.minimum(PAIRS_TILE, w - PAIRS_TILE * np.arange(gw // per))
            ty = np.minimum(PAIRS_TILE, h - PAIRS_TILE * np.arange(gh // per))
            inside_px = ty[:, None] * tx[None, :]
            totals[depth] += np.sum(inside_px[None] * np.minimum(tile, cap[:, None, None]), axis=(1, 2))
    return {d: float(t.max()) / pixels for d, t in totals.items()}
