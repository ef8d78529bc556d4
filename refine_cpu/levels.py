"""The merged LOD levels refined on the CPU (lod.md 6, the optional step; `encode --lod-refine cpu`; issue 31):
variant A, each merged splat's opacity logit and DC colour fitted with the geometry fixed.

Each merged level is refined ALONE, drawn as its whole cut (lod_refine.level_cuts: its merged tiles and the
shallower leaves, the originals fixed), by full-batch Adam on the MSE of the clamped images against renders of the
full detail (refine_cpu.raster, our renderer's conventions) from lod_refine.refine_cameras' training cameras. With
the geometry fixed, each camera's per-pixel (splat, gaussian weight) pairs are built once per level and every step
is a sparse forward and backward pass over them (raster.loss_and_grad). The fit, and the level as built, are then
judged on VALIDATION cameras (the same rule, another seed and count), and the fit is kept only where it beats the
level as built. Each level's loss and validation error also count, weighted 0.1, small FAR cameras where a client
without a budget draws that level (lod_refine.level_far_range, far_level_cameras; branch far31), so the coarse
levels seen from far away keep what the near cameras alone traded away. Phase 1 (BENCHMARKS.md, "Refining the
merged levels against the originals", variant A on gsplat) measured this variant +1.02 dB or more above the best
peer at all 48 points.
"""
from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numba
import numpy as np

from splatstream import lod_refine
from splatstream.format.manifest import LevelRefinement, LodRefinement
from splatstream.gaussians import Gaussians, covariances
from splatstream.lod import Tile
from splatstream.lod_refine import (
    CPU_FAR_TRAINING_CAMERAS,
    CPU_FAR_TRAINING_SEED,
    CPU_FAR_VALIDATION_CAMERAS,
    CPU_FAR_VALIDATION_SEED,
    CPU_FAR_WEIGHT,
    CPU_ITERATIONS,
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
SPLAT_COPIES = 14
# and what the first fit of a process adds whatever its size: numba's cached kernels loaded and its threads started
# (45 MiB measured over a fit of 3,000 splats at 8 px; bench/refiner_memory.py at 64 px measured 80 MiB above the tree
# where the rest of the model gave 61)
KERNELS_BYTES = 48 << 20
VARIANT = "A"  # the one variant fitted here (lod_refine.VARIANT_FIELDS): opacity and DC colour, the geometry fixed


@dataclass
class CpuRefineSettings(lod_refine.SharedRefineSettings):
    """The CPU fit's settings (BENCHMARKS.md, "Refining the merged levels on the CPU"): 256 px renders, 32 training
    and 16 validation cameras, full-batch Adam at these learning rates; per level 16 + 8 far cameras whose error
    counts 0.1 (BENCHMARKS.md, "The CPU refinement's far cameras")."""
    iterations: int = CPU_ITERATIONS
    size: int = CPU_SIZE_PX
    training_cameras: int = CPU_TRAINING_CAMERAS
    validation_cameras: int = CPU_VALIDATION_CAMERAS
    training_seed: int = CPU_TRAINING_SEED
    validation_seed: int = CPU_VALIDATION_SEED
    lr_opacity_logit: float = 0.1
    lr_sh_dc: float = 0.02
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
        return CpuLevelRefiner(replace(self.settings, threads=max(1, (os.cpu_count() or 1) // max(1, fits))))

    def peak_bytes(self, splats: int, splat_bytes: int) -> int:
        """The fit's own peak over a tree of `splats` full-detail splats of `splat_bytes` bytes each, beyond the tree
        (a model, for the memory a refined partition task needs; partitioned.py): numba's kernels (KERNELS_BYTES),
        the clamped targets (float32 RGB, every near and far camera at the full size), the training set's pair lists
        (raster.PairLists: a pixel offset and PAIRS_PER_PIXEL pairs of 8 bytes a pixel, a far camera at its largest
        crop), and a full-detail splat's share: each training camera's projected splat (16 bytes), the fit kernel's
        per-camera tables and gradient rows and SPLAT_COPIES copies of its values (the level cuts'
        concatenations, the fit's and the tree's copies). Measured (bench/refiner_memory.py; BENCHMARKS.md, "The
        fit's kernel, and the refiner's memory measured again"): the peak RSS above the tree, the first fit of each
        process (numba's cached kernels loaded), 220 / 273 / 381 / 561 MiB on biker (SH0) slices of 2^14 / 2^15 /
        2^16 / 2^17 splats, this model 821 / 851 / 911 / 1,031 MiB (1.8-3.7x); 438 and 495 MiB (two runs) on a
        2^18-splat slice of flowers (SH2), the model 1,607 MiB; 80 MiB at 64 px on 2^13 splats of donut copies
        (bench/tile_scene.py), the model 109; tracemalloc's peak (numpy's arrays: the model less KERNELS_BYTES)
        14.4 / 128.9 MiB on fruit_drops (SH3, 4,721 splats) at 32 / 128 px once compiled (30.4 at 32 px compiling),
        31.6 / 206 MiB; 990 / 1,741 MiB on 2^20 / 2^21 splats of donut copies (SH0, the GPU machine's 16 threads),
        the model 2,711 / 4,631 (2.7x; a near pixel held 10.7 / 18 pairs, under the 32 assumed); 5,231 MiB for a
        2^20-splat SH3 domain at the defaults. The model figures above are before raster.GRADIENT_ROWS went 8 -> 16
        and the gradient rows were counted (refinewall31): 768 B a splat more since (833 / 1,127 MiB at 2^14 / 2^17,
        3,479 / 6,167 at 2^20 / 2^21 SH0, 5,999 at 2^20 SH3)."""
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
        return int(KERNELS_BYTES + 12 * pixels * near_and_far + (8 + 8 * PAIRS_PER_PIXEL) * training_pixels
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
            sets = [(raster.pair_lists(whole, train, degree), gt, 1.0)]
            if far_train:
                sets.append((raster.pair_lists(whole, far_train, degree), far_gt_train, s.far_weight))
            # the fit's last step is not the level's end (its validation follows): below k + 2, so that the last
            # level's "100%" comes after its line, not a minute before it (newuser57, donut: 58 s)
            logits, dc = fit_opacity_dc(sets, whole, first, s, lambda it, k=k: progress(
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
                   s: CpuRefineSettings, on_step: Callable[[int], None] = lambda it: None,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Full-batch Adam on the opacity logits and DC colour of splats `first`: of `whole` (the rest fixed) against
    each set's target (its cameras' full-detail renders, clamped; a set: cameras of one size, the near ones and a
    level's far ones), the loss the sum of the sets' mean errors times their weights; `on_step(steps done)` after
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
        sig = _sigmoid(logits)
        op_all[first:] = sig
        dc_all[first:] = raster.SH_C0 * sh_dc
        g_op, g_dc = 0.0, 0.0
        for pl, target, weight in sets:
            _, g_o, g_d = raster.loss_and_grad(pl, op_all, dc_all, target)
            g_op, g_dc = g_op + weight * g_o, g_dc + weight * g_d
        grads = [g_op[first:] * sig * (1.0 - sig), g_dc[first:] * raster.SH_C0]
        for p, gr, a, b, lr in zip(params, grads, m1, m2, lrs, strict=True):
            a *= b1
            a += (1 - b1) * gr
            b *= b2
            b += (1 - b2) * gr * gr
            p -= lr * (a / (1 - b1 ** it)) / (np.sqrt(b / (1 - b2 ** it)) + eps)
        on_step(it)
    return logits.astype(np.float32), in_domain("sh_dc", sh_dc).astype(np.float32)
