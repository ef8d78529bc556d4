"""bench/probe_lod_twoscale.py (issue 31, two viewing scales): its variants, the sse it blends by and the blend
itself, without GL."""
from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import load_bench

from splatstream.camera import Camera
from splatstream.gaussians import Gaussians


def load():
    return load_bench("probe_lod_twoscale")


P = load()


def scene(n: int = 3000, seed: int = 3) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), q.astype(np.float32),
                     rng.normal(-3.5, 0.4, size=(n, 3)).astype(np.float32),
                     rng.normal(0, 1.5, size=n).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32),
                     np.zeros((n, 0, 3), np.float32))


def camera(distance: float) -> Camera:
    return Camera(eye=(0.0, 0.0, distance), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_y_deg=50.0,
                  width=96, height=96, near=0.01, far=1e6)


def test_variants():
    assert P.parse("2") == (2.0, 2.0, "2")
    assert P.parse("i1-8ci") == (1.0, 8.0, "i")
    assert P.parse("i1-4c2") == (1.0, 4.0, "2")
    assert P.parse("t1-8") == (1.0, 8.0, "t")


def test_the_per_tile_model_is_exact_for_a_uniform_change():
    near = scene(300)
    far = Gaussians(near.positions, near.rotations, near.log_scales,
                    np.log(0.5 * near.opacities / (1 - 0.5 * near.opacities)).astype(np.float32),
                    near.sh_dc + np.float32(0.25), near.sh_rest)
    ratio, shift = P.tile_model(near, far)
    assert ratio == pytest.approx(0.5, rel=1e-5)
    np.testing.assert_allclose(shift, [0.25, 0.25, 0.25], rtol=1e-5)


def test_tile_sse_is_the_3d_tiles_formula():
    trees = P.build_at(scene(), 2.0, 500, 2.0)
    t = trees[1]
    cam = camera(40.0)
    d = float(np.linalg.norm(np.asarray(t.sphere_center) - np.array(cam.eye))) - t.sphere_radius
    assert P.tile_sse(t, cam) == pytest.approx(t.geometric_error * 96 / (2 * d * math.tan(math.radians(25.0))))
    inside = Camera(eye=tuple(float(v) for v in t.sphere_center), target=(0.0, 0.0, 1e3), up=(0.0, 1.0, 0.0),
                    fov_y_deg=50.0, width=96, height=96, near=0.01, far=1e6)
    assert P.tile_sse(t, inside) == math.inf  # the eye inside the sphere: refine, i.e. the far end


@pytest.fixture(scope="module")
def trees():
    g = scene()
    return {p: P.build_at(g, p, 500, 2.0) for p in (1.0, 2.0, 8.0)}


def test_the_trees_differ_only_in_opacity_and_colour(trees):
    for a, b in zip(trees[1.0], trees[8.0], strict=True):
        assert a.geometric_error == b.geometric_error
        np.testing.assert_array_equal(a.gaussians.positions, b.gaussians.positions)
        np.testing.assert_array_equal(a.gaussians.log_scales, b.gaussians.log_scales)
    merged = [t.id for t in trees[1.0] if t.children]
    assert any(not np.array_equal(trees[1.0][i].gaussians.opacity_logits, trees[8.0][i].gaussians.opacity_logits)
               for i in merged)


def test_blend_clamps_to_the_near_and_far_matches_and_leaves_leaves_alone(trees):
    merged = [t.id for t in trees[1.0] if t.children]
    leaf = next(t.id for t in trees[1.0] if not t.children)
    ids = [merged[0], leaf]
    n0 = len(trees[1.0][merged[0]].gaussians)
    c, r = trees[1.0][merged[0]].sphere_center, trees[1.0][merged[0]].sphere_radius
    near_cam = camera(1e5)
    far_cam = Camera(eye=(float(c[0]), float(c[1]), float(c[2]) + 0.5 * r), target=tuple(float(v) for v in c),
                     up=(0.0, 1.0, 0.0), fov_y_deg=50.0, width=96, height=96, near=0.01, far=1e6)  # inside: inf
    assert P.tile_sse(trees[1.0][merged[0]], near_cam) < 1.0  # far away: sse under the pair's near end
    for cam, p in ((near_cam, 1.0), (far_cam, 8.0)):
        out = P.blend(trees, ids, cam, "i1-8ci")
        ref = trees[p][merged[0]].gaussians
        np.testing.assert_allclose(out.opacities[:n0], ref.opacities, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(out.sh_dc[:n0], ref.sh_dc, rtol=1e-6)
        np.testing.assert_array_equal(out.positions[n0:], trees[1.0][leaf].gaussians.positions)
        np.testing.assert_array_equal(out.opacity_logits[n0:], trees[1.0][leaf].gaussians.opacity_logits)
    # In between: each opacity between its two ends, the colour too; 'c2' keeps the 2-px colour.
    t = trees[1.0][merged[0]]
    d = t.geometric_error * 96 / (2 * 3.0 * math.tan(math.radians(25.0)))  # where the tile's sse is 3 px
    eye_z = float(t.sphere_center[2]) + t.sphere_radius + d
    cam = Camera(eye=(float(t.sphere_center[0]), float(t.sphere_center[1]), eye_z),
                 target=tuple(float(v) for v in t.sphere_center), up=(0.0, 1.0, 0.0), fov_y_deg=50.0, width=96,
                 height=96, near=0.01, far=1e6)
    assert P.tile_sse(t, cam) == pytest.approx(3.0)
    f = math.log(3.0) / math.log(8.0)
    a, b = trees[1.0][t.id].gaussians.opacities, trees[8.0][t.id].gaussians.opacities
    out = P.blend(trees, [t.id], cam, "i1-8ci")
    np.testing.assert_allclose(out.opacities, np.clip((1 - f) * a + f * b, 1e-7, 1 - 1e-7), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(P.blend(trees, [t.id], cam, "i1-8c2").sh_dc, trees[2.0][t.id].gaussians.sh_dc)
