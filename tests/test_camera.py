import json
import math
from pathlib import Path

import numpy as np
import pytest

from splatstream.camera import (
    Camera,
    framing_box,
    framing_view,
    look_at,
    orbit_views,
    scene_orbit_views,
    standard_benchmark_view,
    suggested_camera,
)

ROOT = Path(__file__).resolve().parents[1]


def test_view_matrix_is_look_at():
    cam = look_at((1.0, 2.0, 3.0), (4.0, 2.0, 3.0), up=(0, 0, 1))
    v = cam.view_matrix()
    np.testing.assert_allclose(v[:3, :3] @ v[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(v[:3, :3]) == pytest.approx(1.0)  # a rotation: no axis flips
    np.testing.assert_allclose(v @ [1, 2, 3, 1], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(v @ [4, 2, 3, 1], [0, 0, -3, 1], atol=1e-12)  # target straight ahead on -z
    np.testing.assert_allclose(v @ [1, 2, 4, 1], [0, 1, 0, 1], atol=1e-12)   # world up is camera up
    np.testing.assert_allclose(v @ [1, 1, 3, 1], [1, 0, 0, 1], atol=1e-12)   # looking along +x, -y is right
    cv = cam.world_to_camera_cv()
    np.testing.assert_allclose(cv @ [4, 2, 3, 1], [0, 0, 3, 1], atol=1e-12)
    np.testing.assert_allclose(cv @ [1, 2, 4, 1], [0, -1, 0, 1], atol=1e-12)


def test_intrinsics_and_pixel_convention():
    cam = look_at((0, 0, 0), (0, 0, -1), up=(0, 1, 0), fov_y_deg=60, width=200, height=100)
    fx, fy = cam.focal
    assert fy == pytest.approx(100 / (2 * math.tan(math.radians(30))))
    assert fx == fy
    uv, depth = cam.project(np.array([[0, 0, -1.0], [0, math.tan(math.radians(30)), -1.0]]))
    np.testing.assert_allclose(uv[0], [100, 50])        # image centre = corner between the four middle pixels
    np.testing.assert_allclose(uv[1], [100, 0], atol=1e-9)  # world up is row 0 (the top)
    assert depth[0] == pytest.approx(1.0)
    # the GL projection agrees with the pixel mapping
    clip = cam.view_projection() @ [0.3, -0.2, -2.0, 1.0]
    ndc = clip[:3] / clip[3]
    u = (ndc[0] + 1) / 2 * 200
    v = (1 - ndc[1]) / 2 * 100
    uv2, _ = cam.project(np.array([[0.3, -0.2, -2.0]]))
    np.testing.assert_allclose([u, v], uv2[0], atol=1e-9)
    assert -1 < ndc[2] < 1


def test_standard_benchmark_view_definition():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(10000, 3)) * [10, 5, 1] + [1, 2, 3]
    cam = standard_benchmark_view(p)
    c = np.median(p, axis=0)
    side = np.percentile(np.concatenate([np.abs(p[:, 0] - c[0]), np.abs(p[:, 1] - c[1])]), 95)
    np.testing.assert_allclose(cam.target, c)
    np.testing.assert_allclose(cam.eye, c + [-side, -side, 0.6 * side])
    assert cam.up == (0.0, 0.0, 1.0) and cam.fov_y_deg == 50.0
    assert (cam.width, cam.height) == (1920, 1080)


def test_suggested_camera_frames_robust_bounds():
    rng = np.random.default_rng(1)
    p = rng.uniform(-1, 1, size=(5000, 3))
    p[:10] = 1000.0  # outliers are ignored
    cam = suggested_camera(p, width=400, height=300)
    assert np.linalg.norm(cam.target) < 0.1
    uv, depth = cam.project(np.array([[x, y, z] for x in (-.9, .9) for y in (-.9, .9) for z in (-.9, .9)]))
    assert (depth > cam.near).all()
    assert (uv >= 0).all() and (uv[:, 0] <= 400).all() and (uv[:, 1] <= 300).all()
    d = np.subtract(cam.eye, cam.target)
    assert d[0] < 0 and d[1] < 0 and d[2] > 0
    flipped = suggested_camera(p, up=(0, -1, 0))
    assert flipped.up == (0.0, -1.0, 0.0)
    assert np.subtract(flipped.eye, flipped.target)[1] < 0  # above the scene along -y
    boxed = suggested_camera(bounds=((-1, -1, -1), (1, 1, 1)))
    np.testing.assert_allclose(boxed.target, [0, 0, 0])


def test_framing_leaves_one_percent_of_far_strays_out():
    """A scene with 1 % of opaque strays scattered far around it (issue 31: F on winter_fountain) is framed as it is
    without them: the same box, the same target and distance. Without the stray rule (the 99 % box alone) three of
    these five seeds moved the eye back 19-31 %."""
    direction = np.array([-1.0, -1.0, 0.6]) / np.linalg.norm([-1.0, -1.0, 0.6])
    for seed in range(5):
        rng = np.random.default_rng(seed)
        scene = rng.uniform([-1.0, -0.5, 0.0], [1.0, 0.5, 3.0], size=(100_000, 3))
        away = rng.normal(size=(1000, 3))
        strays = away / np.linalg.norm(away, axis=1, keepdims=True) * rng.uniform(20.0, 60.0, size=(1000, 1))
        clean = framing_box(scene, np.full(len(scene), 2.0))
        np.testing.assert_allclose(clean[0], [-1, -0.5, 0], atol=0.03)
        np.testing.assert_allclose(clean[1], [1, 0.5, 3], atol=0.03)
        for stray_logit in (2.0, -2.0):  # opaque strays, faint ones
            lo, hi = framing_box(np.concatenate([scene, strays]),
                                 np.concatenate([np.full(len(scene), 2.0), np.full(len(strays), stray_logit)]))
            np.testing.assert_allclose(lo, clean[0], atol=1e-3)
            np.testing.assert_allclose(hi, clean[1], atol=1e-3)
        target, dist = framing_view(lo, hi, direction, (0, 0, 1), 50.0, 16 / 9)
        clean_target, clean_dist = framing_view(*clean, direction, (0, 0, 1), 50.0, 16 / 9)
        assert dist == pytest.approx(clean_dist, rel=1e-3)
        assert np.linalg.norm(target - clean_target) < 1e-3 * clean_dist
    # a thin part within reach of the bulk is not a stray: a 2 % spike 1.5 units above a 3-unit scene is all
    # counted in the 99 % box (its top at the 99.5th percentile of every height, inside the spike)
    spike = np.column_stack([np.zeros(2000), np.zeros(2000), np.linspace(3.0, 4.5, 2000)])
    with_spike = np.concatenate([scene, spike])
    lo, hi = framing_box(with_spike)
    assert hi[2] == pytest.approx(np.percentile(with_spike[:, 2], 99.5)) and hi[2] > 4.0


def test_framing_view_is_the_suggested_cameras_view():
    """The F key and the suggested camera frame a box by one function: the same target and distance."""
    rng = np.random.default_rng(3)
    p = rng.normal(size=(20_000, 3)) * [2.0, 1.0, 0.5] + [5.0, -1.0, 2.0]
    logits = rng.normal(size=len(p))
    for up in ((0, 0, 1), (0, -1, 0)):
        cam = suggested_camera(p, up=up, width=800, height=600, opacity_logits=logits)
        direction = np.subtract(cam.eye, cam.target)
        dist = float(np.linalg.norm(direction))
        target, fitted = framing_view(*framing_box(p, logits), direction / dist, up, cam.fov_y_deg, 800 / 600)
        np.testing.assert_allclose(target, cam.target, atol=1e-9)
        assert fitted == pytest.approx(dist, rel=1e-9)
        # every corner of the box is in view, with the margin
        lo, hi = framing_box(p, logits)
        uv, depth = cam.project(np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                          for z in (lo[2], hi[2])]))
        assert (depth > cam.near).all() and (uv >= 0).all() and (uv[:, 0] <= 800).all() and (uv[:, 1] <= 600).all()


def test_orbit_views():
    cams = orbit_views((1, 2, 3), 5.0, 8, up=(0, 0, 1), elevation_deg=30, width=64, height=48)
    assert len(cams) == 8
    eyes = np.array([c.eye for c in cams])
    np.testing.assert_allclose(np.linalg.norm(eyes - [1, 2, 3], axis=1), 5.0)
    np.testing.assert_allclose(eyes[:, 2] - 3, 5.0 * math.sin(math.radians(30)))
    assert len({tuple(np.round(e, 6)) for e in eyes}) == 8
    np.testing.assert_allclose(eyes.mean(axis=0)[:2], [1, 2], atol=1e-9)
    views = scene_orbit_views(np.random.default_rng(2).normal(size=(100, 3)), 3)
    assert len(views) == 3


def test_camera_json_round_trip_and_validation():
    cam = look_at((1, 2, 3), (0, 0, 0), width=64, height=32, fov_y_deg=40)
    again = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert again == cam
    with pytest.raises(ValueError):
        look_at((0, 0, 0), (0, 0, 0))
    with pytest.raises(ValueError):
        look_at((0, 0, 1), (0, 0, 0), fov_y_deg=0)
    # up parallel to the view direction still gives a valid rotation
    v = look_at((0, 0, 5), (0, 0, 0), up=(0, 0, 1)).view_matrix()
    np.testing.assert_allclose(v[:3, :3] @ v[:3, :3].T, np.eye(3), atol=1e-12)


def test_splats_at_one_point_are_framed_by_their_size():
    """newuser63: a 1-splat scene (or every splat at one point) was framed as a unit box, so its splat (about 0.01
    across) was 16 px at 320x240. The box is now FRAME_POINT_SIGMAS (3) standard deviations of the largest splat's
    largest axis either side of the point, and the splat fills the view as a scene does."""
    from splatstream.camera import FRAME_POINT_SIGMAS
    from splatstream.encode.sample import SceneSample
    from splatstream.ply import read_gaussians_ply

    one = read_gaussians_ply(ROOT / "samples" / "donut.ply").subset(np.arange(1))
    sigma = math.exp(float(one.log_scales.max()))  # 0.00798
    lo, hi = framing_box(one.positions, one.opacity_logits, log_scales=one.log_scales)
    np.testing.assert_allclose(hi - lo, [2 * FRAME_POINT_SIGMAS * sigma] * 3, rtol=1e-12)
    np.testing.assert_allclose((lo + hi) / 2, one.positions[0], rtol=1e-12)
    # 20 splats at one point: the largest frames them
    many = one.subset(np.zeros(20, dtype=np.int64))
    bigger = many.log_scales.copy()
    bigger[7, 1] += 1.0
    lo, hi = framing_box(many.positions, log_scales=bigger)
    assert float(np.exp(bigger[7, 1])) > 1.9 * sigma
    np.testing.assert_allclose(hi - lo, [2 * FRAME_POINT_SIGMAS * float(np.exp(bigger[7, 1]))] * 3, rtol=1e-6)
    # the encoder's suggested camera (manifest camera): the splat's 3-sigma extent fills about the view's height
    entry = SceneSample.of(one, with_codebook=False).camera((0.0, -1.0, 0.0))
    cam = Camera(entry.eye, entry.target, entry.up, entry.fov_y, 320, 240)
    uv, _ = cam.project(one.positions.astype(np.float64) + np.array([[0.0, 3 * sigma, 0.0]]))
    centre, _ = cam.project(one.positions.astype(np.float64))
    assert 40 < abs(uv[0, 1] - centre[0, 1]) < 120, (uv, centre)  # was 16 px across in all
    assert math.dist(entry.eye, entry.target) < 0.2  # was 1.8 (a unit box)


@pytest.mark.parametrize("name", ["samples/donut.ply", "tests/data/real/fruit_drops_sh3.ply",
                                  "tests/data/real/lod_tile_sh3_zero_rest.ply"])
def test_scenes_with_an_extent_are_framed_as_before_with_their_scales(name):
    """The splats' scales change only a box without extent: the bundled samples' suggested cameras are the same
    bits with them as without."""
    from splatstream.io import read_gaussians

    g = read_gaussians(ROOT / name)
    for up in ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)):
        before = suggested_camera(g.positions, up=up, opacity_logits=g.opacity_logits)
        after = suggested_camera(g.positions, up=up, opacity_logits=g.opacity_logits, log_scales=g.log_scales)
        assert after == before
        assert framing_box(g.positions, log_scales=g.log_scales)[0].tolist() == framing_box(g.positions)[0].tolist()
