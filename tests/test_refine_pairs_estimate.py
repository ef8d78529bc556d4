"""The CPU refiner's memory model from the scene's own pairs a pixel (issue 31, branch memmodel31;
refine_cpu.levels.estimate_pairs, CpuLevelRefiner.scene_pairs): estimated from a sample of the splats before any
pair list, it stays above the pairs the fit's own pair lists count (deterministic counts, not RSS), for the whole
scene and for each kd cell fitted alone from the whole scene's cameras (a partitioned encode's merge domains), and
the model with it stays above the arrays it counts."""
from __future__ import annotations

from dataclasses import replace

import pytest
from conftest import real

from splatstream.encode.partitioned import routed_row_bytes
from splatstream.io import read_gaussians
from splatstream.lod import build_tiles
from splatstream.lod_refine import CameraFrame, refine_tree

pytest.importorskip("numba")

from refine_cpu import levels, raster  # noqa: E402
from refine_cpu.levels import KERNELS_BYTES, CpuLevelRefiner, CpuRefineSettings, kd_cells  # noqa: E402

UP = (0.0, 0.0, 1.0)
SIZE = 32  # fruit_drops whole in 32 px: 58 pairs a pixel, above the constant 32 the model assumed before


@pytest.fixture(scope="module")
def scene():
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    refiner = CpuLevelRefiner(CpuRefineSettings(size=SIZE))
    frame = CameraFrame.of(g.positions)
    train, _ = refiner.settings.cameras(frame, UP)
    return g, refiner, frame, train


def counted_pairs_per_pixel(g, cams) -> float:
    return len(raster.pair_lists(g, cams, 0).g) / (len(cams) * cams[0].width * cams[0].height)


def fitted(g, refiner: CpuLevelRefiner, frame: CameraFrame, leaf: int) -> tuple[float, int]:
    """One fit of `g`'s tree (1 step) in `frame`: its largest level's training pairs over the training pixels the
    model counts (near at the size, far at their crop), and the largest level's training pair lists' bytes."""
    fit = CpuLevelRefiner(replace(refiner.settings, iterations=1))
    refine_tree(g, build_tiles(g, leaf, 2.0, merge="auto"), UP, fit, lambda stage, f: None, frame=frame)
    s = fit.settings
    far_px = max(r["far_px"] for r in fit.report)
    pixels = s.training_cameras * SIZE * SIZE + s.far_training_cameras * far_px * far_px
    return (max(r["training_pairs"] for r in fit.report) / pixels,
            max(r["training_pair_bytes"] for r in fit.report))


def test_the_estimate_is_above_the_fit_s_counted_pairs_for_the_scene_and_each_kd_cell(scene):
    """The whole scene (depth 0) and its 8 kd cells of depth 3 each fitted alone in the whole scene's frame, as a
    partitioned encode's domains are: the estimate (PAIRS_MARGIN included) above the pairs the fit's largest level
    holds (the refiner's own pair lists, counted), and not far above them (within 3x: the model is meant to come
    near the measure). Deterministic: the same sample and cameras give the same numbers."""
    g, refiner, frame, train = scene
    est = refiner.scene_pairs(g, len(g), frame, UP, (0, 3))
    whole, _ = fitted(g, refiner, frame, 300)
    cells = [fitted(g.subset(rows), refiner, frame, 150)[0] for rows in kd_cells(g.positions, 3)]
    assert whole <= est[0] <= 3 * whole, (whole, est)
    assert max(cells) <= est[3] <= 3 * max(cells), (cells, est)
    assert est[3] < est[0] / 4  # a cell alone makes far fewer pairs than the whole scene
    # the full detail's own pairs: above the constant the model assumed before (32) at this size
    assert counted_pairs_per_pixel(g, train) > levels.PAIRS_PER_PIXEL
    assert refiner.scene_pairs(g, len(g), frame, UP, (0, 3)) == est


def test_a_sample_of_the_scene_gives_nearly_the_same_estimate(scene, monkeypatch):
    """Every k-th splat stands for the rest (x splats / sample): a quarter of the splats estimates within 25 % of
    the whole sample's."""
    g, refiner, frame, train = scene
    full = refiner.scene_pairs(g, len(g), frame, UP, (0,))[0]
    monkeypatch.setattr(levels, "PAIRS_SAMPLE", len(g) // 4)
    part = refiner.scene_pairs(g, len(g), frame, UP, (0,))[0]
    assert part != full and abs(part / full - 1) < 0.25, (part, full)


def test_the_model_with_the_scene_pairs_is_above_the_arrays_it_counts(scene):
    """peak_bytes with the scene's pairs a pixel (numba's kernels aside) holds the fit's largest training pair lists
    (near and far, as the fit built them) and every camera's target; without the pairs (the lower bound a
    partitioned encode checks before its route pass) it is lower."""
    g, refiner, frame, train = scene
    fit = refiner.with_scene_pairs(g, len(g), frame, UP)
    s = fit.settings
    row = routed_row_bytes(g.sh_degree)
    _, pair_bytes = fitted(g, refiner, frame, 300)
    targets = 12 * SIZE * SIZE * (s.training_cameras + s.validation_cameras + s.far_training_cameras
                                  + s.far_validation_cameras)
    assert pair_bytes + targets <= fit.peak_bytes(len(g), row) - KERNELS_BYTES
    assert refiner.with_pairs_per_pixel(0.0).peak_bytes(len(g), row) < fit.peak_bytes(len(g), row)
