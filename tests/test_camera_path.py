"""Scripted camera paths: keyframes from JSON, smooth and exact at the keyframes, clear errors."""
import json

import numpy as np
import pytest

from splatstream.camera_path import load_camera_path, parse_camera_path
from splatstream.errors import InputError

PATH = {"fov_y": 40, "up": [0, 0, 1], "keyframes": [
    {"time": 0, "eye": [0, -4, 1], "target": [0, 0, 0]},
    {"time": 2, "eye": [4, 0, 1], "target": [0, 0, 0]},
    {"time": 4, "eye": [0, 4, 2], "target": [0, 0, 0.5], "fov_y": 60},
]}


def test_keyframes_are_hit_and_motion_is_smooth():
    p = parse_camera_path(PATH)
    assert p.duration == 4
    for kf in PATH["keyframes"]:
        cam = p.camera(kf["time"], 64, 48)
        assert np.allclose(cam.eye, kf["eye"]) and np.allclose(cam.target, kf["target"])
    assert p.camera(-1, 64, 48).eye == p.camera(0, 64, 48).eye and p.camera(9, 64, 48).fov_y_deg == 60
    assert p.camera(3, 64, 48).fov_y_deg == pytest.approx(50)
    eyes = np.array([p.camera(t, 64, 48).eye for t in np.linspace(0, 4, 401)])
    step = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    assert step.max() < 3 * np.median(step)  # no jumps
    turn = np.diff(eyes, 2, axis=0)
    assert np.linalg.norm(turn, axis=1).max() < 0.01  # C1 through the middle keyframe


def test_bad_paths_name_the_field(tmp_path):
    bad = [({"keyframes": []}, "keyframes"),
           ({"keyframes": [{"time": 0, "eye": [0, 0], "target": [0, 0, 0]}]}, "keyframes[0].eye"),
           ({"keyframes": [{"time": 1, "eye": [0, 1, 0], "target": [0, 0, 0]},
                           {"time": 1, "eye": [0, 2, 0], "target": [0, 0, 0]}]}, "keyframes[1].time"),
           ({"keyframes": [{"time": 0, "eye": [1, 1, 1], "target": [1, 1, 1]}]}, "coincide"),
           ({"keyframes": [{"time": 0, "eye": [0, 1, 0], "target": [0, 0, 0], "fov_y": 180}]}, "fov_y")]
    for data, field in bad:
        with pytest.raises(InputError, match=field.replace("[", "\\[").replace("]", "\\]")):
            parse_camera_path(data)
    (tmp_path / "p.json").write_text("{not json")
    with pytest.raises(InputError, match="not a JSON camera path"):
        load_camera_path(tmp_path / "p.json")
    (tmp_path / "q.json").write_text(json.dumps(PATH))
    assert load_camera_path(tmp_path / "q.json").end == 4
