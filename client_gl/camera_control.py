"""Interactive cameras for the viewer: orbit and fly, as SuperSplat and the SIBR viewer drive them. Pure numpy.

Orbit: left drag orbits around the target, right or middle drag pans, the wheel zooms toward the point under the
cursor. Fly: WASD moves, Q/E down/up, shift runs, left drag looks around. Both modes respond to WASD/QE (in orbit
mode they move the target along). Motion is frame-rate independent: inputs set where the camera should go, and
`update(dt)` moves it there with an exponential approach (the same feel at 30 and 240 fps).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from splatstream.camera import Camera, framing_view, turn_about_up

ORBIT_DEG_PER_PX = 0.3
LOOK_DEG_PER_PX = 0.15
# The arrow keys' turn about the target: 8 presses go round, 4 to the other side (a scene's front is found in a few).
TURN_STEP_DEG = 45.0
ZOOM_PER_NOTCH = 0.85  # distance factor per wheel notch (toward the cursor)
SMOOTHING_PER_S = 18.0  # the camera covers 1 - exp(-18 dt) of the way each frame: 90 % in about 0.13 s
MIN_PITCH_COS = 0.999  # keep the view off the up axis (no flip at the poles)


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


@dataclass
class CameraState:
    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y: float

    def copy(self) -> CameraState:
        return CameraState(self.eye.copy(), self.target.copy(), self.up.copy(), self.fov_y)


@dataclass
class CameraController:
    home: CameraState  # R returns here (the scene's suggested camera)
    scene_center: np.ndarray  # the scene's bounding sphere (every splat, strays included): the fly speed, near/far
    scene_radius: float
    mode: str = "orbit"  # or "fly"
    speed: float = 0.0  # fly speed, world units per second (0: from the scene size)
    # F frames this box (camera.framing_box of the root tile's splats, set once they are decoded), as the suggested
    # camera frames the scene; the bounding sphere until then.
    frame_box: tuple[np.ndarray, np.ndarray] | None = None
    goal: CameraState = field(init=False)
    now: CameraState = field(init=False)

    def __post_init__(self) -> None:
        self.goal = self.home.copy()
        self.now = self.home.copy()
        if not self.speed:
            self.speed = max(1e-6, 0.5 * self.scene_radius)

    # --- geometry -------------------------------------------------------------------------------------------
    def _basis(self, s: CameraState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        forward = _unit(s.target - s.eye)
        right = _unit(np.cross(forward, s.up))
        if not right.any():
            right = _unit(np.cross(forward, np.array([1.0, 0.0, 0.0])))
        true_up = np.cross(right, forward)
        return right, true_up, forward

    def camera(self, width: int, height: int) -> Camera:
        s = self.now
        dist = float(np.linalg.norm(s.target - s.eye)) or 1.0
        near = max(1e-4, min(0.01, 0.002 * dist, 0.001 * self.scene_radius))
        far = max(1000.0, 100.0 * (dist + self.scene_radius))
        return Camera(tuple(s.eye), tuple(s.target), tuple(s.up), s.fov_y, width, height, near, far)

    # --- inputs ---------------------------------------------------------------------------------------------
    def set_mode(self, mode: str) -> None:
        self.mode = mode

    def orbit(self, dx_px: float, dy_px: float) -> None:
        """Left drag: turn the eye around the target (yaw about up, pitch about the camera's right)."""
        g = self.goal
        offset = g.eye - g.target
        up = _unit(g.up)
        yaw = math.radians(-dx_px * ORBIT_DEG_PER_PX)
        offset = _rotate(offset, up, yaw)
        right = _unit(np.cross(up, offset))
        pitch = math.radians(-dy_px * ORBIT_DEG_PER_PX)
        turned = _rotate(offset, right, pitch)
        if abs(float(_unit(turned) @ up)) < MIN_PITCH_COS:
            offset = turned
        g.eye = g.target + offset

    def look(self, dx_px: float, dy_px: float) -> None:
        """Fly mode's left drag: turn the view direction about the eye."""
        g = self.goal
        ahead = g.target - g.eye
        up = _unit(g.up)
        ahead = _rotate(ahead, up, math.radians(-dx_px * LOOK_DEG_PER_PX))
        right = _unit(np.cross(ahead, up))
        turned = _rotate(ahead, right, math.radians(-dy_px * LOOK_DEG_PER_PX))
        if abs(float(_unit(turned) @ up)) < MIN_PITCH_COS:
            ahead = turned
        g.target = g.eye + ahead

    def pan(self, dx_px: float, dy_px: float, height_px: int) -> None:
        """Right or middle drag: move eye and target in the view plane, the point under the cursor following it."""
        g = self.goal
        right, true_up, _ = self._basis(g)
        dist = float(np.linalg.norm(g.target - g.eye))
        world_per_px = 2.0 * dist * math.tan(math.radians(g.fov_y) / 2.0) / max(1, height_px)
        shift = (-dx_px * right + dy_px * true_up) * world_per_px
        g.eye = g.eye + shift
        g.target = g.target + shift

    def zoom(self, notches: float, cursor: tuple[float, float] | None = None,
             size: tuple[int, int] | None = None) -> None:
        """Wheel: move toward (or away from) the target, and toward the point under the cursor."""
        g = self.goal
        factor = ZOOM_PER_NOTCH ** notches
        offset = g.eye - g.target
        new_eye = g.target + offset * factor
        if cursor is not None and size is not None:
            # Shift the pivot toward the cursor's ray at the target's depth, as much as the eye moved in.
            right, true_up, forward = self._basis(g)
            dist = float(np.linalg.norm(offset))
            t = math.tan(math.radians(g.fov_y) / 2.0)
            x = (2.0 * cursor[0] / size[0] - 1.0) * t * size[0] / size[1]
            y = (1.0 - 2.0 * cursor[1] / size[1]) * t
            point = g.target + (x * right + y * true_up) * dist
            shift = (point - g.target) * (1.0 - factor)
            new_eye, g.target = new_eye + shift, g.target + shift
        g.eye = new_eye

    def move(self, forward: float, right: float, up: float, dt: float, run: bool = False) -> None:
        """WASD/QE held for dt seconds: move eye and target together (fly), or target and eye (orbit)."""
        g = self.goal
        r, _, f = self._basis(g)
        step = self.speed * dt * (4.0 if run else 1.0)
        shift = (forward * f + right * r + up * _unit(g.up)) * step
        g.eye = g.eye + shift
        g.target = g.target + shift

    def turn(self, degrees: float) -> None:
        """T (180 degrees: the other side of the target) and the arrow keys (TURN_STEP_DEG): the eye turned about
        the line through the target along up, same distance and elevation (camera.turn_about_up, the rule of
        `--camera-azimuth`). At once, not glided: the glide goes straight from eye to eye, through the target for a
        half turn."""
        for s in (self.goal, self.now):
            s.eye = np.array(turn_about_up(s.eye, s.target, self.goal.up, degrees))

    def reset(self) -> None:
        """R: back to the scene's suggested camera."""
        self.goal = self.home.copy()

    def frame_scene(self, aspect: float) -> None:
        """F: look at the scene from the current direction, fitting it in view: its framing box (frame_box, the
        suggested camera's rule: camera.framing_view) where known, else its bounding sphere."""
        g = self.goal
        _, _, forward = self._basis(g)
        if self.frame_box is not None:
            g.target, dist = framing_view(*self.frame_box, -forward, g.up, g.fov_y, aspect)
            g.eye = g.target - forward * dist
            return
        half = math.radians(g.fov_y) / 2.0
        half = min(half, math.atan(math.tan(half) * aspect))
        dist = self.scene_radius / math.sin(half)
        g.target = self.scene_center.copy()
        g.eye = g.target - forward * dist

    # --- time -----------------------------------------------------------------------------------------------
    def update(self, dt: float) -> bool:
        """Move the camera toward where the inputs want it; True while it is still moving."""
        k = 1.0 - math.exp(-SMOOTHING_PER_S * max(0.0, dt))
        n, g = self.now, self.goal
        n.eye = n.eye + (g.eye - n.eye) * k
        n.target = n.target + (g.target - n.target) * k
        n.up = _unit(n.up + (g.up - n.up) * k)
        n.fov_y = n.fov_y + (g.fov_y - n.fov_y) * k
        scale = max(1e-9, float(np.linalg.norm(g.target - g.eye)))
        moving = float(np.linalg.norm(g.eye - n.eye) + np.linalg.norm(g.target - n.target)) > 1e-5 * scale
        if not moving:
            self.now = g.copy()
        return moving

    def jump(self) -> None:
        """Go to the goal at once (scripts, --camera-path)."""
        self.now = self.goal.copy()


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation of v about a unit axis."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * float(axis @ v) * (1.0 - c)


def state_from_camera(cam: Camera) -> CameraState:
    return CameraState(np.array(cam.eye, float), np.array(cam.target, float), np.array(cam.up, float), cam.fov_y_deg)
