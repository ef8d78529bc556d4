"""Pinhole cameras shared by the reference rasterizer, the GL client and the evaluation.

Conventions (normative text in format_spec/camera.md):

* World space is the file's space as stored, right-handed, no axis flips.
* The camera looks from `eye` towards `target`; `up` picks the roll (it need not be orthogonal to the view direction).
* `view_matrix()` is the OpenGL look-at matrix (camera space: x right, y up, looking down -z);
  `world_to_camera_cv()` is the same rotation in the reference 3DGS / COLMAP convention (x right, y down, z forward).
* Image row 0 is at the top; pixel (col, row) has its centre at continuous image coordinate (col + 0.5, row + 0.5).
* Square pixels: fy = height / (2 tan(fov_y / 2)), fx = fy; principal point at the image centre (width/2, height/2).
* Splats with view depth <= `near` are culled (the reference CUDA rasterizer uses 0.2).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

Vec3 = tuple[float, float, float]

DEFAULT_UP: Vec3 = (0.0, 0.0, 1.0)
DEFAULT_FOV_Y_DEG = 50.0
REFERENCE_NEAR = 0.2


def _vec3(v: Sequence[float] | np.ndarray, name: str) -> Vec3:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"camera {name}: expected 3 finite numbers, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError("zero-length vector")
    return v / n


@dataclass
class Camera:
    """A pinhole camera. All fields are plain Python numbers so the camera serialises to JSON as is."""

    eye: Vec3
    target: Vec3
    up: Vec3 = DEFAULT_UP
    fov_y_deg: float = DEFAULT_FOV_Y_DEG
    width: int = 512
    height: int = 512
    near: float = REFERENCE_NEAR
    far: float = 1000.0
    extra: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.eye = _vec3(self.eye, "eye")
        self.target = _vec3(self.target, "target")
        self.up = _vec3(self.up, "up")
        self.fov_y_deg = float(self.fov_y_deg)
        self.width = int(self.width)
        self.height = int(self.height)
        self.near = float(self.near)
        self.far = float(self.far)
        if self.eye == self.target:
            raise ValueError("camera eye and target coincide")
        if not 0.0 < self.fov_y_deg < 180.0:
            raise ValueError(f"camera fov_y_deg must lie in (0, 180), got {self.fov_y_deg}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not 0.0 < self.near < self.far:
            raise ValueError(f"camera needs 0 < near < far, got near={self.near} far={self.far}")
        if np.linalg.norm(self.up) == 0:
            raise ValueError("camera up vector is zero")

    # --- intrinsics -------------------------------------------------------------------------------------------
    @property
    def aspect(self) -> float:
        return self.width / self.height

    @property
    def tan_half_fov_y(self) -> float:
        return math.tan(math.radians(self.fov_y_deg) / 2.0)

    @property
    def tan_half_fov_x(self) -> float:
        return self.tan_half_fov_y * self.aspect

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.tan_half_fov_x))

    @property
    def focal(self) -> tuple[float, float]:
        """(fx, fy) in pixels; square pixels."""
        fy = self.height / (2.0 * self.tan_half_fov_y)
        return fy, fy

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy) in continuous image coordinates (pixel centres at +0.5)."""
        return self.width / 2.0, self.height / 2.0

    def intrinsics(self) -> np.ndarray:
        """3x3 K with image coordinates u right, v down (pixel centres at +0.5)."""
        fx, fy = self.focal
        cx, cy = self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    # --- extrinsics -------------------------------------------------------------------------------------------
    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World-space unit (right, true_up, forward) of the camera."""
        eye = np.array(self.eye)
        forward = _normalize(np.array(self.target) - eye)
        up = _normalize(np.array(self.up))
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:  # up parallel to the view direction: pick any perpendicular roll
            alt = np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            right = np.cross(forward, alt)
        right = _normalize(right)
        true_up = np.cross(right, forward)
        return right, true_up, forward

    @property
    def position(self) -> np.ndarray:
        return np.array(self.eye)

    def view_matrix(self) -> np.ndarray:
        """4x4 OpenGL look-at (world -> camera, camera looks down -z, y up), float64, row-major (M @ p)."""
        right, true_up, forward = self.basis()
        eye = np.array(self.eye)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, true_up, -forward
        m[:3, 3] = -m[:3, :3] @ eye
        return m

    def world_to_camera_cv(self) -> np.ndarray:
        """4x4 world -> camera in the reference 3DGS (COLMAP) convention: x right, y down, z forward."""
        right, true_up, forward = self.basis()
        eye = np.array(self.eye)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, -true_up, forward
        m[:3, 3] = -m[:3, :3] @ eye
        return m

    def projection_matrix(self) -> np.ndarray:
        """4x4 OpenGL perspective (clip z in [-w, w]) matching `focal` and `principal_point`."""
        f = 1.0 / self.tan_half_fov_y
        n, fa = self.near, self.far
        p = np.zeros((4, 4))
        p[0, 0] = f / self.aspect
        p[1, 1] = f
        p[2, 2] = (fa + n) / (n - fa)
        p[2, 3] = 2.0 * fa * n / (n - fa)
        p[3, 2] = -1.0
        return p

    def view_projection(self) -> np.ndarray:
        return self.projection_matrix() @ self.view_matrix()

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> (continuous image coordinates (N, 2), view depth (N,)).

        Pixel (col, row) covers [col, col+1) x [row, row+1); depth is the distance along the view axis.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        m = self.world_to_camera_cv()
        t = p @ m[:3, :3].T + m[:3, 3]
        fx, fy = self.focal
        cx, cy = self.principal_point
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([fx * t[:, 0] / t[:, 2] + cx, fy * t[:, 1] / t[:, 2] + cy], axis=1)
        return uv, t[:, 2]

    # --- (de)serialisation ------------------------------------------------------------------------------------
    def with_size(self, width: int, height: int) -> Camera:
        return Camera(self.eye, self.target, self.up, self.fov_y_deg, width, height, self.near, self.far)

    def to_dict(self) -> dict:
        return {"eye": list(self.eye), "target": list(self.target), "up": list(self.up),
                "fov_y_deg": self.fov_y_deg, "width": self.width, "height": self.height,
                "near": self.near, "far": self.far}

    @staticmethod
    def from_dict(d: dict) -> Camera:
        fov = d.get("fov_y_deg", d.get("fov_y", DEFAULT_FOV_Y_DEG))
        return Camera(d["eye"], d["target"], d.get("up", DEFAULT_UP), fov, d.get("width", 512),
                      d.get("height", 512), d.get("near", REFERENCE_NEAR), d.get("far", 1000.0))


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = DEFAULT_UP,
            fov_y_deg: float = DEFAULT_FOV_Y_DEG, width: int = 512, height: int = 512,
            near: float = REFERENCE_NEAR, far: float = 1000.0) -> Camera:
    """A camera at `eye` looking at `target`."""
    return Camera(tuple(eye), tuple(target), tuple(up), fov_y_deg, width, height, near, far)


def _positions(positions: np.ndarray) -> np.ndarray:
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"expected a non-empty (N, 3) array of positions, got shape {p.shape}")
    finite = np.all(np.isfinite(p), axis=1)
    if not finite.all():
        p = p[finite]
        if len(p) == 0:
            raise ValueError("no finite positions")
    return p


def _sample(p: np.ndarray, limit: int = 2_000_000) -> np.ndarray:
    """A deterministic subsample for percentile statistics on very large scenes."""
    if len(p) <= limit:
        return p
    return p[:: int(math.ceil(len(p) / limit))]


def standard_benchmark_view(positions: np.ndarray, width: int = 1920, height: int = 1080) -> Camera:
    """The standard benchmark view of /work/shared/data/README.md for make_scene.py scenes.

    target c = per-axis median of positions; side = 95th percentile of |x - c.x| and |y - c.y| taken together;
    eye = c + (-side, -side, 0.6 side); up = +z; vertical FOV 50 degrees.
    """
    p = _positions(positions)
    c = np.median(p, axis=0)
    d = np.concatenate([np.abs(p[:, 0] - c[0]), np.abs(p[:, 1] - c[1])])
    side = float(np.percentile(d, 95))
    if side == 0:
        side = 1.0
    eye = c + np.array([-side, -side, 0.6 * side])
    far = max(1000.0, 10.0 * side)
    return Camera(tuple(eye), tuple(c), DEFAULT_UP, DEFAULT_FOV_Y_DEG, width, height, REFERENCE_NEAR, far)


def robust_bounds(positions: np.ndarray, percentile: float = 95.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(median, lo, hi): per-axis median and the central `percentile` % box of the positions."""
    p = _sample(_positions(positions))
    tail = (100.0 - percentile) / 2.0
    lo, med, hi = np.percentile(p, [tail, 50.0, 100.0 - tail], axis=0)
    return med, lo, hi


def _diagonal(up: np.ndarray, side: float = 0.0) -> np.ndarray:
    """Unit direction from the target towards the eye of the default view.

    Scenes with up along y (the 3DGS / COLMAP axes) are seen along their z axis, as a capture sees them, raised 20
    degrees towards up: from the `side` (+1: +z, -1: -z; 0: -z for y down, +z for y up). Otherwise (-1, -1, 0.6)
    in a frame whose third axis is `up`."""
    up = _normalize(up)
    if abs(up[1]) > 0.9:
        el = math.radians(20.0)
        behind = side if side else (-1.0 if up[1] < 0 else 1.0)
        return _normalize(np.array([0.0, 0.0, behind * math.cos(el)]) + math.sin(el) * up)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = _normalize(helper - up * (helper @ up))
    b = np.cross(up, a)
    return _normalize(-a - b + 0.6 * up)


def fit_distance(radius: float, camera_fov_y_deg: float, aspect: float) -> float:
    """Distance at which a sphere of `radius` fits in the narrower field of view."""
    half = math.radians(camera_fov_y_deg) / 2.0
    half_x = math.atan(math.tan(half) * aspect)
    return radius / math.sin(min(half, half_x))


# The default view frames the central FRAME_PERCENTILE % box of the splats that are not nearly transparent (at
# least FRAME_MIN_OPACITY): thin parts that hold few splats (a guitar's head, a statue's) are inside it, stray
# floaters are not. The whole box is kept in view, with FRAME_MARGIN of the half-width spare, for any window from
# 4:3 to wider (the manifest's camera is drawn at the window's aspect).
FRAME_PERCENTILE = 99.0
FRAME_MIN_OPACITY = 0.3
FRAME_MARGIN = 0.08
FRAME_NARROWEST_ASPECT = 4.0 / 3.0
# Far strays are left out before the percentile box is taken: splats farther than FRAME_STRAY_REACH times the
# largest side of the central 95 % box beyond that box on some axis. A 99 % box alone let 1 % of opaque strays
# scattered around a scene pull it out several times over (0.5 % a side is within reach of their count); thin
# parts of the scene lie within the reach. Chosen on winter_fountain and guitar (BENCHMARKS.md, "The F key frames
# the scene").
FRAME_STRAY_REACH = 1.0
# A box without extent (one splat, or every splat at one point) is framed by the splats' own size: a cube of
# FRAME_POINT_SIGMAS standard deviations of the largest splat's largest axis either side of the point (its 3-sigma
# extent, as a renderer draws it). The unit box framed before made a 1-splat scene's splat (0.01 across) 16 px
# at 320x240 (newuser63).
FRAME_POINT_SIGMAS = 3.0


def framing_box(positions: np.ndarray, opacity_logits: np.ndarray | None = None,
                percentile: float = FRAME_PERCENTILE, log_scales: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): the central `percentile` % box of the positions of splats at least FRAME_MIN_OPACITY opaque (all
    of them where fewer than a tenth are), far strays left out first (FRAME_STRAY_REACH). Where that box has no
    extent (every splat at one point), the cube of FRAME_POINT_SIGMAS times the largest of `log_scales`' standard
    deviations either side of it (as given: a box of no extent without them; framing_view then frames a unit box)."""
    lo, hi = _percentile_box(positions, opacity_logits, percentile)
    if not np.linalg.norm(hi - lo) > 0 and log_scales is not None:
        scales = np.asarray(log_scales, dtype=np.float64)
        scales = scales[np.isfinite(scales)]
        if scales.size:
            half = FRAME_POINT_SIGMAS * math.exp(float(scales.max()))
            if half > 0 and math.isfinite(half):
                centre = (lo + hi) / 2.0
                lo, hi = centre - half, centre + half
    return lo, hi


def _percentile_box(positions: np.ndarray, opacity_logits: np.ndarray | None,
                    percentile: float) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(positions, dtype=np.float64)
    ok = np.isfinite(p).all(axis=1)
    if opacity_logits is not None:
        logits = np.asarray(opacity_logits, dtype=np.float64)
        opaque = ok & (logits >= math.log(FRAME_MIN_OPACITY / (1.0 - FRAME_MIN_OPACITY)))
        if opaque.sum() >= max(16, 0.1 * ok.sum()):
            ok = opaque
    p = _sample(_positions(p[ok]))
    core_lo, core_hi = np.percentile(p, [2.5, 97.5], axis=0)
    reach = FRAME_STRAY_REACH * float((core_hi - core_lo).max())
    near = np.all((p >= core_lo - reach) & (p <= core_hi + reach), axis=1)
    if near.sum() >= 16:
        p = p[near]
    tail = (100.0 - percentile) / 2.0
    lo, hi = np.percentile(p, [tail, 100.0 - tail], axis=0)
    return lo, hi


def fit_box_distance(lo: np.ndarray, hi: np.ndarray, target: np.ndarray, direction: np.ndarray, up: np.ndarray,
                     fov_y_deg: float, aspect: float, margin: float = FRAME_MARGIN) -> float:
    """The smallest distance from `target` along `direction` (towards the eye) at which every corner of the box
    [lo, hi] is inside the view (`margin`: the share of each half-width kept free)."""
    forward = -_normalize(direction)
    right = np.cross(forward, _normalize(up))
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right = _normalize(right)
    true_up = np.cross(right, forward)
    ty = math.tan(math.radians(fov_y_deg) / 2.0) * (1.0 - margin)
    tx = math.tan(math.radians(fov_y_deg) / 2.0) * aspect * (1.0 - margin)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rel = corners - np.asarray(target, dtype=np.float64)
    along = rel @ forward  # depth of the corner beyond the target
    need = np.maximum(np.abs(rel @ right) / tx, np.abs(rel @ true_up) / ty) - along
    size = float(np.linalg.norm(hi - lo))
    return float(max(need.max(), (-along).max() + 0.05 * size, 1e-6))


def framing_view(lo: np.ndarray, hi: np.ndarray, direction: np.ndarray, up: Sequence[float], fov_y_deg: float,
                 aspect: float) -> tuple[np.ndarray, float]:
    """(target, distance): the view of the box [lo, hi] (framing_box) from `direction` (target towards the eye):
    its centre looked at from the smallest distance that keeps the whole box in view (fit_box_distance) at `aspect`
    or 4:3, whichever is narrower. The suggested camera and the viewer's F key both frame a scene with it."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    target = (lo + hi) / 2.0
    if not np.linalg.norm(hi - lo) > 0:
        lo, hi = target - 0.5, target + 0.5
    dist = fit_box_distance(lo, hi, target, np.asarray(direction, dtype=np.float64),
                            np.asarray(up, dtype=np.float64), fov_y_deg, min(aspect, FRAME_NARROWEST_ASPECT))
    return target, dist


def suggested_camera(positions: np.ndarray | None = None, up: Sequence[float] = DEFAULT_UP, width: int = 1280,
                     height: int = 720, fov_y_deg: float = DEFAULT_FOV_Y_DEG,
                     bounds: tuple[Sequence[float], Sequence[float]] | None = None,
                     center: Sequence[float] | None = None, percentile: float = FRAME_PERCENTILE,
                     side: float = 0.0, opacity_logits: np.ndarray | None = None,
                     log_scales: np.ndarray | None = None) -> Camera:
    """Default camera for a scene: looks at the centre of its box along a diagonal, the whole box in view.

    Give `positions` (N, 3) (with `opacity_logits`, nearly transparent splats are left out, and with `log_scales`
    splats all at one point are framed by their size: framing_box), or
    `bounds=(lo, hi)` (and optionally `center`, the point looked at). The box is kept in view (fit_box_distance)
    for the given aspect or 4:3, whichever is narrower. `up` defaults to +z; the view direction is _diagonal's
    (from the front for 3DGS-convention scenes, else a diagonal).
    """
    if positions is not None:
        lo, hi = framing_box(positions, opacity_logits, percentile, log_scales)
    elif bounds is not None:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    else:
        raise ValueError("suggested_camera needs positions or bounds")
    med = (lo + hi) / 2.0 if center is None else np.asarray(center, dtype=np.float64)
    radius = float(np.linalg.norm(np.maximum(hi - med, med - lo)))
    if not radius > 0:
        radius = 1.0
        lo, hi = med - 0.5, med + 0.5
    direction = _diagonal(np.asarray(up, dtype=np.float64), side)
    if center is None:
        med, dist = framing_view(lo, hi, direction, up, fov_y_deg, width / height)
    else:
        aspect = min(width / height, FRAME_NARROWEST_ASPECT)
        dist = fit_box_distance(lo, hi, med, direction, np.asarray(up, dtype=np.float64), fov_y_deg, aspect)
    eye = med + direction * dist
    near = min(REFERENCE_NEAR, 0.01 * dist)
    far = max(1000.0, 10.0 * (dist + radius))
    return Camera(tuple(eye), tuple(med), tuple(up), fov_y_deg, width, height, near, far)


# `encode --camera-azimuth` / `view --camera-azimuth`: turns beyond a whole turn either way are refused (a typo, not
# a wish); any angle within is taken as given.
MAX_AZIMUTH_DEG = 360.0


def check_azimuth(degrees: float) -> float:
    """`degrees` as a float when it is a finite number within +-MAX_AZIMUTH_DEG, else a ValueError saying so."""
    value = float(degrees)
    if not (math.isfinite(value) and abs(value) <= MAX_AZIMUTH_DEG):
        raise ValueError(f"expected degrees from -{MAX_AZIMUTH_DEG:g} to {MAX_AZIMUTH_DEG:g}, got {degrees!r}")
    return value


def turn_about_up(eye: Sequence[float], target: Sequence[float], up: Sequence[float], degrees: float) -> Vec3:
    """The eye turned by `degrees` of azimuth about the line through `target` along `up` (right-handed:
    counter-clockwise seen from above, +up towards the viewer); distance to the target and elevation unchanged.
    180 degrees looks at the other side of the target (camera.md, "Standard views"). The target and up stay."""
    axis = _normalize(np.asarray(up, dtype=np.float64))
    t = np.asarray(target, dtype=np.float64)
    v = np.asarray(eye, dtype=np.float64) - t
    a = math.radians(float(degrees))
    c, s = math.cos(a), math.sin(a)
    turned = v * c + np.cross(axis, v) * s + axis * float(axis @ v) * (1.0 - c)  # Rodrigues' rotation
    return _vec3(t + turned, "eye")


def look_at_near_far(eye: Sequence[float], target: Sequence[float]) -> tuple[float, float]:
    """The near and far planes of a camera placed by its eye and target (`view --eye/--target`, a headless view's
    scene camera, the LOD refinement's cameras): 1 % of the distance, at most 0.01; 100x it, at least 1000."""
    dist = math.dist(eye, target)
    return min(0.01, 0.01 * dist), max(1000.0, 100.0 * dist)


def orbit_views(center: Sequence[float], radius: float, n: int, up: Sequence[float] = DEFAULT_UP,
                elevation_deg: float = 25.0, fov_y_deg: float = DEFAULT_FOV_Y_DEG, width: int = 512,
                height: int = 512, near: float | None = None, far: float | None = None,
                start_deg: float = 225.0) -> list[Camera]:
    """`n` cameras evenly spaced on a circle around `center` (about the `up` axis), all looking at `center`.

    `radius` is the distance from the centre; `elevation_deg` lifts the eyes above the plane normal to `up`.
    The first eye sits at azimuth `start_deg` (225 degrees: the (-1, -1) diagonal, as suggested_camera).
    """
    if n < 1:
        raise ValueError(f"orbit_views needs n >= 1, got {n}")
    if not radius > 0:
        raise ValueError(f"orbit_views needs a positive radius, got {radius}")
    c = np.asarray(center, dtype=np.float64)
    u = _normalize(np.asarray(up, dtype=np.float64))
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = _normalize(helper - u * (helper @ u))
    b = np.cross(u, a)
    el = math.radians(elevation_deg)
    near = min(REFERENCE_NEAR, 0.01 * radius) if near is None else near
    far = max(1000.0, 10.0 * radius) if far is None else far
    cams = []
    for i in range(n):
        az = math.radians(start_deg) + 2.0 * math.pi * i / n
        d = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * u
        cams.append(Camera(tuple(c + radius * d), tuple(c), tuple(u), fov_y_deg, width, height, near, far))
    return cams


def scene_orbit_views(positions: np.ndarray, n: int, width: int = 512, height: int = 512,
                      up: Sequence[float] = DEFAULT_UP, elevation_deg: float = 25.0,
                      fov_y_deg: float = DEFAULT_FOV_Y_DEG, percentile: float = 95.0,
                      distance_scale: float = 1.0) -> list[Camera]:
    """Evaluation views for a scene: `orbit_views` around the median, at the distance that fits the robust bounds."""
    return bounds_orbit_views(*robust_bounds(positions, percentile), n, width, height, up, elevation_deg, fov_y_deg,
                              distance_scale)


def bounds_orbit_views(med: np.ndarray, lo: np.ndarray, hi: np.ndarray, n: int, width: int = 512, height: int = 512,
                       up: Sequence[float] = DEFAULT_UP, elevation_deg: float = 25.0,
                       fov_y_deg: float = DEFAULT_FOV_Y_DEG, distance_scale: float = 1.0) -> list[Camera]:
    """scene_orbit_views from the scene's robust bounds (robust_bounds: median, lo, hi) already taken: the same
    cameras, where the positions are not at hand (a partitioned encode's task holds a part of the scene)."""
    radius = float(np.linalg.norm(np.maximum(hi - med, med - lo))) or 1.0
    dist = fit_distance(radius, fov_y_deg, width / height) * distance_scale
    return orbit_views(med, dist, n, up, elevation_deg, fov_y_deg, width, height)
