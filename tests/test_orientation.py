"""Scenes open upright and framed: the up direction per input and the suggested camera (issue: first run)."""
import numpy as np
import pytest
from conftest import real, run_cli, with_shared

from splatstream.camera import suggested_camera
from splatstream.io import read_gaussians
from splatstream.orientation import Y_DOWN_UP, Z_UP, detect_up, view_side
from splatstream.store import load_manifest

# Looked at (BENCHMARKS.md, "Upright on open"): the y-down captures and the z-up synthetic scenes.
EXPECTED_UP = {
    "fruit_drops_sh3.ply": Y_DOWN_UP,
    "donut_sh0_no_normals.ply": Z_UP,
    "lod_tile_sh3_zero_rest.ply": Z_UP,
    "winter_fountain.splat": Y_DOWN_UP,
    "guitar.compressed.ply": Y_DOWN_UP,
    "biker.compressed.ply": Y_DOWN_UP,
}


@pytest.mark.parametrize("name", with_shared(list(EXPECTED_UP)))
def test_up_is_detected_and_the_suggested_view_frames_the_scene(name):
    g = read_gaussians(real(name))
    up = detect_up(g).up
    assert up == EXPECTED_UP[name]
    cam = suggested_camera(g.positions, up=up, side=view_side(g, up))
    right, true_up, forward = cam.basis()
    assert float(true_up @ np.array(up)) > 0.9  # upright: the image's up is the scene's up
    uv, depth = cam.project(g.positions)
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert inside.mean() > 0.9, inside.mean()  # the bulk of the splats in frame
    # and not a close-up of a part: the splats span a good part of the image
    span = np.percentile(uv[inside], 95, axis=0) - np.percentile(uv[inside], 5, axis=0)
    assert max(span[0] / cam.width, span[1] / cam.height) > 0.3


def test_up_is_stored_reported_and_overridable(tmp_path):
    r = run_cli("encode", real("fruit_drops_sh3.ply"), tmp_path / "a")
    assert r.returncode == 0 and "up 0,-1,0" in r.stderr
    assert load_manifest(tmp_path / "a").up == (0.0, -1.0, 0.0)
    r = run_cli("encode", real("fruit_drops_sh3.ply"), tmp_path / "b", "--up", "0,0,1", "-q")
    assert r.returncode == 0
    m = load_manifest(tmp_path / "b")
    assert m.up == (0.0, 0.0, 1.0) and m.camera.up == (0.0, 0.0, 1.0)
    import json

    info = json.loads(run_cli("info", tmp_path / "a", "--json").stdout)
    assert info["up"] == [0.0, -1.0, 0.0]
