"""Scripted camera paths: keyframes (time, eye, target, up) read from JSON and sampled at any time.

    {"fov_y": 50, "keyframes": [{"time": 0, "eye": [0, -3, 1], "target": [0, 0, 0], "up": [0, 0, 1]},
                                {"time": 4, "eye": [3, 0, 1], "target": [0, 0, 0]}]}

Between keyframes the eye and the target move along Catmull-Rom splines (smooth through every keyframe; a path
of two keyframes is a straight line) and the up vector is interpolated linearly and renormalised; before the
first keyframe and after the last the camera holds still. `up` and `fov_y` may be given per keyframe or once for
the whole path; missing ones repeat the previous keyframe's.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass

import numpy as np

from .camera import DEFAULT_FOV_Y_DEG, Camera
from .errors import InputError

MAX_KEYFRAMES = 100_000


@dataclass(frozen=True)
class Keyframe:
    time: float
    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y: float


@dataclass(frozen=True)
class CameraPath:
    keyframes: tuple[Keyframe, ...]

    @property
    def duration(self) -> float:
        return self.keyframes[-1].time - self.keyframes[0].time

    @property
    def end(self) -> float:
        return self.keyframes[-1].time

    def camera(self, t: float, width: int, height: int, near: float | None = None, far: float = 1000.0) -> Camera:
        """The camera at time t (seconds on the path's clock)."""
        k = self.keyframes
        if t <= k[0].time or len(k) == 1:
            return _camera(k[0].eye, k[0].target, k[0].up, k[0].fov_y, width, height, near, far)
        if t >= k[-1].time:
            return _camera(k[-1].eye, k[-1].target, k[-1].up, k[-1].fov_y, width, height, near, far)
        i = int(np.searchsorted([f.time for f in k], t, side="right")) - 1
        a, b = k[i], k[i + 1]
        s = (t - a.time) / (b.time - a.time)
        p0, p3 = k[max(0, i - 1)], k[min(len(k) - 1, i + 2)]
        eye = _catmull_rom(p0.eye, a.eye, b.eye, p3.eye, s)
        target = _catmull_rom(p0.target, a.target, b.target, p3.target, s)
        up = (1 - s) * a.up + s * b.up
        if np.linalg.norm(up) < 1e-9:
            up = b.up
        return _camera(eye, target, up, (1 - s) * a.fov_y + s * b.fov_y, width, height, near, far)


def _catmull_rom(p0, p1, p2, p3, s: float) -> np.ndarray:
    s2, s3 = s * s, s * s * s
    return 0.5 * ((2 * p1) + (-p0 + p2) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s2 + (-p0 + 3 * p1 - 3 * p2 + p3) * s3)


def _camera(eye, target, up, fov_y, width, height, near, far) -> Camera:
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    dist = float(np.linalg.norm(target - eye)) or 1.0
    near = near if near is not None else min(0.01, 0.01 * dist)
    return Camera(tuple(eye), tuple(target), tuple(np.asarray(up, float)), fov_y, width, height, near,
                  max(far, 100.0 * dist))


def _vec(value, where: str, path: str) -> np.ndarray:
    if (not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 3
            or not all(isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) and math.isfinite(v)
                       for v in value)):
        raise InputError(path, where, f"expected three finite numbers, got {value!r}")
    return np.asarray(value, float)


def parse_camera_path(data, path: str = "camera path") -> CameraPath:
    """A CameraPath from the JSON value described in the module docstring; InputError names the field."""
    if isinstance(data, list):
        data = {"keyframes": data}
    if not isinstance(data, dict) or not isinstance(data.get("keyframes"), list) or not data["keyframes"]:
        raise InputError(path, "keyframes", "expected a non-empty list of {time, eye, target[, up][, fov_y]}")
    if len(data["keyframes"]) > MAX_KEYFRAMES:
        raise InputError(path, "keyframes", f"more than {MAX_KEYFRAMES} keyframes")
    up = data.get("up", (0.0, 0.0, 1.0))
    fov = data.get("fov_y", DEFAULT_FOV_Y_DEG)
    frames: list[Keyframe] = []
    for i, kf in enumerate(data["keyframes"]):
        where = f"keyframes[{i}]"
        if not isinstance(kf, dict):
            raise InputError(path, where, "expected an object")
        t = kf.get("time")
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
            raise InputError(path, f"{where}.time", f"expected a number of seconds, got {t!r}")
        if frames and t <= frames[-1].time:
            raise InputError(path, f"{where}.time", f"{t} is not after the previous keyframe's {frames[-1].time}")
        eye = _vec(kf.get("eye"), f"{where}.eye", path)
        target = _vec(kf.get("target"), f"{where}.target", path)
        if np.array_equal(eye, target):
            raise InputError(path, where, "eye and target coincide")
        up = _vec(kf.get("up", up), f"{where}.up", path)
        if not up.any():
            raise InputError(path, f"{where}.up", "zero-length up vector")
        fov = kf.get("fov_y", fov)
        if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0 < fov < 180:
            raise InputError(path, f"{where}.fov_y", f"expected degrees in (0, 180), got {fov!r}")
        frames.append(Keyframe(float(t), eye, target, up, float(fov)))
    return CameraPath(tuple(frames))


def load_camera_path(path: str | os.PathLike) -> CameraPath:
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        raise InputError(path, None, "no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, None, f"not a JSON camera path ({exc})") from None
    return parse_camera_path(data, path)
