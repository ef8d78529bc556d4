"""bench/probe_lod28_far.py (issue 31, the 2 + 8 px rule in frames without a budget): its cut is lod.md 3's
traversal, its far cameras are the orbit views moved back, and lod.OPACITY_MATCH_FAR_SSE_PX at 8 is the rule that
bench/probe_statue31.py's px=2/8 variant measured under a budget."""
from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import load_bench
from test_bench_probe_statue31 import P as STATUE31
from test_bench_probe_statue31 import same, scene

from splatstream import lod
from splatstream.camera import Camera


def load():
    return load_bench("probe_lod28_far")


P = load()


def test_the_library_rule_at_8_px_is_the_probes_2_8_variant(monkeypatch):
    g = scene()
    variant = STATUE31.build_variant(g, "px=2/8", max_leaf_splats=500, reduction=2.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 8.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)  # 8 px on every level above (growth since 2026-11-30)
    ours = lod.build_tiles(g, 500, 2.0, merge="auto")
    assert len(ours) == len(variant) > 7
    assert all(same(a, b) and a.geometric_error == b.geometric_error for a, b in zip(ours, variant, strict=True))


def test_threshold_cut_is_a_cut_refined_by_distance():
    tiles = lod.build_tiles(scene(), 500, 2.0, merge="grid")
    leaves = {t.id for t in tiles if not t.children}

    def covered_leaves(cut):
        out = []
        for i in cut:
            stack = [i]
            while stack:
                t = tiles[stack.pop()]
                if t.children:
                    stack.extend(t.children)
                else:
                    out.append(t.id)
        return out

    root = tiles[0]
    direction = np.array([1.0, 0.0, 0.0])
    counts = []
    for radii in (1.0, 3.0, 30.0, 3000.0):
        cut = P.threshold_cut(tiles, root.sphere_center + direction * radii * root.sphere_radius, 96, 50.0, 1.0)
        got = covered_leaves(cut)
        assert sorted(got) == sorted(leaves)  # every leaf under exactly one drawn tile
        counts.append(sum(len(tiles[i].gaussians) for i in cut))
        for i in cut:  # each drawn interior tile is within the threshold (lod.md 3)
            t = tiles[i]
            dist = float(np.linalg.norm(root.sphere_center + direction * radii * root.sphere_radius
                                        - t.sphere_center)) - t.sphere_radius
            if t.children:
                assert dist > 0 and t.geometric_error * 96 / (2 * math.tan(math.radians(25.0)) * dist) <= 1.0
    assert counts[0] == len(scene())  # the eye inside the root's sphere: full detail
    assert counts == sorted(counts, reverse=True) and counts[-1] == len(tiles[0].gaussians)


def test_far_cameras_move_the_eye_back_along_the_view_ray():
    cam = Camera((1.0, 2.0, 3.0), (0.0, 0.5, 1.0), (0.0, 0.0, 1.0), 50.0, 64, 64, 0.01, 1000.0)
    far = P.far_cameras([cam], 4.0)[0]
    np.testing.assert_allclose(np.subtract(far.eye, far.target), 4.0 * np.subtract(cam.eye, cam.target))
    assert far.target == cam.target and far.up == cam.up and far.fov_y_deg == cam.fov_y_deg
    assert (far.near, far.far) == P.lvp._near_far(far.eye, far.target)


def test_psnr_over_the_covered_pixels():
    ref = np.zeros((4, 4, 3), np.float32)
    img = ref.copy()
    ref[0, 0] = 0.5
    img[0, 0] = 0.4
    mask = P.covered(img, ref)
    assert mask.sum() == 1
    assert P.psnr(img, ref, mask) == pytest.approx(20.0)
    assert P.psnr(img, ref) == pytest.approx(20.0 + 10 * math.log10(16))
