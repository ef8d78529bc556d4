"""Edits of a capture before it ships (issue 36): translate, rotate, scale, crop to a box or a sphere, filter by an
attribute's value. Pure functions over Gaussians, run in the order given; the CLI only parses them.

Names and semantics are PlayCanvas splat-transform's (its README, version 3): a user moving from it finds the same
results. Like it, every coordinate a user gives (a translation, Euler angles, a box, a sphere, a filter on x, y or
z) is in PlayCanvas's engine frame, which is a 3DGS PLY's frame turned 180 degrees about z (x and y negated; our
Gaussians keep the PLY's axes, axes.py). Transforms compose before they are applied, as splat-transform composes
them, and each edit is a function of one splat at a time with a fixed order of float operations: the same splat
gives the same bytes whether the scene is edited whole or by row ranges (the partitioned encoder edits each chunk
of rows it reads).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import UsageError
from .gaussians import SH_BAND_COEFFS, SH_BAND_START, Gaussians
from .sh import SH_C0, sh_basis

# splat-transform's engine frame from ours and back (a 180-degree turn about z: its own inverse).
ENGINE_SIGNS = np.array([-1.0, -1.0, 1.0])


# ---------------------------------------------------------------------------------------------- rotations


def quaternion_from_euler(x: float, y: float, z: float) -> np.ndarray:
    """(w, x, y, z) of PlayCanvas's Quat.setFromEulerAngles (degrees; the x turn first, then y, then z)."""
    ex, ey, ez = (math.radians(v) * 0.5 for v in (x, y, z))
    sx, cx, sy, cy, sz, cz = math.sin(ex), math.cos(ex), math.sin(ey), math.cos(ey), math.sin(ez), math.cos(ez)
    return np.array([cx * cy * cz + sx * sy * sz, sx * cy * cz - cx * sy * sz, cx * sy * cz + sx * cy * sz,
                     cx * cy * sz - sx * sy * cz])


def quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a * b (Hamilton) of (w, x, y, z) quaternions; `b` may be (N, 4). Float64, a fixed order per element."""
    aw, ax, ay, az = (float(v) for v in a)
    bw, bx, by, bz = (b[..., i].astype(np.float64) for i in range(4))
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by + ay * bw + az * bx - ax * bz, aw * bz + az * bw + ax * by - ay * bx], axis=-1)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# Directions the SH rotation is fitted on: many more than the 7 coefficients of band 3, spread over the sphere
# (a Fibonacci lattice), so the least-squares fit is exact to float64 rounding.
_FIT_DIRECTIONS = 64


def _fit_directions() -> np.ndarray:
    i = np.arange(_FIT_DIRECTIONS) + 0.5
    z = 1 - 2 * i / _FIT_DIRECTIONS
    phi = math.pi * (1 + math.sqrt(5)) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sh_rotation(matrix: np.ndarray, band: int) -> np.ndarray:
    """(2 band + 1)^2 matrix M taking a band's coefficients c (3DGS basis, sh.sh_basis) to those of the scene turned
    by `matrix`: the colour the turned splat shows towards R d is the colour it showed towards d, so
    sum M c . Y(d) = sum c . Y(R^T d) for every direction d. Each band of real SH is closed under rotation, so M is
    that identity solved on directions enough to fix it."""
    d = _fit_directions()
    lo, n = 1 + SH_BAND_START[band], SH_BAND_COEFFS[band]
    here = sh_basis(d, 3)[:, lo:lo + n]
    before = sh_basis(d @ matrix, 3)[:, lo:lo + n]  # rows: (R^T d)^T = d^T R
    m, *_ = np.linalg.lstsq(here, before, rcond=None)  # here @ m = before: Y(d) m c = Y(R^T d) c
    return m


# ---------------------------------------------------------------------------------------------- edits


@dataclass(frozen=True)
class Transform:
    """p -> R (s p) + t in our frame (one composed step of --translate, --rotate, --scale)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)  # (w, x, y, z)
    scale: float = 1.0
    label: str = ""

    def then(self, other: Transform) -> Transform:
        """`other` applied after this one."""
        r2 = np.array(other.rotation)
        t = quaternion_matrix(r2) @ (other.scale * np.array(self.translation)) + np.array(other.translation)
        q = quaternion_product(r2, np.array(self.rotation)[None])[0]
        return Transform(tuple(float(v) for v in t), tuple(float(v) for v in q), self.scale * other.scale,
                         " ".join(v for v in (self.label, other.label) if v))

    def apply(self, g: Gaussians) -> Gaussians:
        q = np.array(self.rotation)
        m = quaternion_matrix(q)
        s, t = float(self.scale), self.translation
        p = g.positions.astype(np.float64) * s
        positions = np.stack([m[i, 0] * p[:, 0] + m[i, 1] * p[:, 1] + m[i, 2] * p[:, 2] + t[i] for i in range(3)],
                             axis=1)
        # splat-transform's test: a turn within 1e-6 of none leaves rotations and SH bands as they are
        turned = abs(abs(q[0]) - 1) >= 1e-6
        rotations = quaternion_product(q, g.rotations) if turned else g.rotations
        log_scales = g.log_scales.astype(np.float64) + math.log(s) if s != 1 else g.log_scales
        sh_rest = g.sh_rest
        if turned and g.sh_degree:
            sh_rest = np.empty_like(g.sh_rest)
            for band in range(1, g.sh_degree + 1):
                rot = sh_rotation(m, band)
                lo, n = SH_BAND_START[band], SH_BAND_COEFFS[band]
                c = g.sh_rest[:, lo:lo + n].astype(np.float64)
                for i in range(n):  # term by term: the same splat gives the same bytes in any batch
                    acc = rot[i, 0] * c[:, 0]
                    for j in range(1, n):
                        acc = acc + rot[i, j] * c[:, j]
                    sh_rest[:, lo + i] = acc
        return Gaussians(positions, rotations, log_scales, g.opacity_logits, g.sh_dc, sh_rest)


def translation(x: float, y: float, z: float) -> Transform:
    """splat-transform --translate x,y,z (engine frame)."""
    t = tuple(float(v) for v in ENGINE_SIGNS * (x, y, z))
    return Transform(translation=t, label=f"translate {x:g},{y:g},{z:g}")  # type: ignore[arg-type]


def rotation(x: float, y: float, z: float) -> Transform:
    """splat-transform --rotate x,y,z: Euler degrees in the engine frame (PlayCanvas's order)."""
    q = quaternion_from_euler(x, y, z)
    # the engine frame's turn D (180 degrees about z) conjugates it: D R D is (w, -x, -y, z)
    ours = (float(q[0]), float(-q[1]), float(-q[2]), float(q[3]))
    return Transform(rotation=ours, label=f"rotate {x:g},{y:g},{z:g}")


def rotation_quaternion(x: float, y: float, z: float, w: float) -> Transform:
    """--rotate x,y,z,w: a turn given as a quaternion in the order PlayCanvas's Quat and glTF write it (x, y, z, w;
    not a PLY's rot_0..3, which is w first), in the engine frame like the Euler angles; normalised here."""
    q = np.array([w, x, y, z], np.float64)
    n = float(np.linalg.norm(q))
    if not (math.isfinite(n) and n > 0):
        raise UsageError(f"--rotate {x:g},{y:g},{z:g},{w:g}: a quaternion of length 0 is no rotation")
    q = q / n
    ours = (float(q[0]), float(-q[1]), float(-q[2]), float(q[3]))  # D q D, as rotation() turns Euler angles
    return Transform(rotation=ours, label=f"rotate {x:g},{y:g},{z:g},{w:g}")


def scaling(s: float) -> Transform:
    """splat-transform --scale s (uniform, about the origin)."""
    if not (math.isfinite(s) and s > 0):
        raise UsageError(f"--scale {s:g}: expected a factor above 0")
    return Transform(scale=float(s), label=f"scale {s:g}")


@dataclass(frozen=True)
class Box:
    """splat-transform --filter-box: keep the splats whose centre lies in the box, faces included (engine frame);
    `keep_inside` False drops them instead."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    keep_inside: bool = True

    @property
    def label(self) -> str:
        what = "filter-box" if self.keep_inside else "drop-box"
        return f"{what} {','.join(f'{v:g}' for v in (*self.lo, *self.hi))}"

    def keep(self, g: Gaussians) -> np.ndarray:
        p = g.positions.astype(np.float64) * ENGINE_SIGNS
        inside = np.all((p >= np.array(self.lo)) & (p <= np.array(self.hi)), axis=1)
        return inside if self.keep_inside else ~inside


@dataclass(frozen=True)
class Sphere:
    """splat-transform --filter-sphere: keep the splats whose centre lies strictly inside the sphere (engine
    frame); `keep_inside` False drops them instead."""

    center: tuple[float, float, float]
    radius: float
    keep_inside: bool = True

    @property
    def label(self) -> str:
        what = "filter-sphere" if self.keep_inside else "drop-sphere"
        return f"{what} {','.join(f'{v:g}' for v in (*self.center, self.radius))}"

    def keep(self, g: Gaussians) -> np.ndarray:
        d = g.positions.astype(np.float64) * ENGINE_SIGNS - np.array(self.center)
        inside = d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2 < float(self.radius) ** 2
        return inside if self.keep_inside else ~inside


COMPARATORS = {"lt": np.less, "lte": np.less_equal, "gt": np.greater, "gte": np.greater_equal, "eq": np.equal,
               "neq": np.not_equal}
SYMBOLS = {"<": "lt", "<=": "lte", ">": "gt", ">=": "gte", "==": "eq", "=": "eq", "!=": "neq"}
# An attribute by its PLY name: the column it reads and, for the values users know (opacity after the sigmoid,
# scale after exp, colour 0..1), the map from such a value to the stored one (increasing, so comparisons hold).
_COLUMNS = {"x": ("positions", 0), "y": ("positions", 1), "z": ("positions", 2),
            "scale_0": ("log_scales", 0), "scale_1": ("log_scales", 1), "scale_2": ("log_scales", 2),
            "opacity": ("opacity_logits", None),
            "f_dc_0": ("sh_dc", 0), "f_dc_1": ("sh_dc", 1), "f_dc_2": ("sh_dc", 2)}
FILTER_ATTRIBUTES = (*_COLUMNS, *(f"{n}_raw" for n in _COLUMNS if n not in ("x", "y", "z")))


def _stored(name: str, value: float) -> float:
    """A value as users know it (linear opacity, linear scale, colour 0..1) as stored; increasing, so a comparison
    of stored values gives the comparison of known ones."""
    if name == "opacity":
        return math.log(value / (1 - value))
    if name.startswith("scale_"):
        return math.log(value)
    if name.startswith("f_dc_"):
        return (value - 0.5) / SH_C0
    return value


@dataclass(frozen=True)
class ValueFilter:
    """splat-transform --filter-value name,cmp,value: keep the splats whose attribute compares true. opacity,
    scale_* and f_dc_* are compared as users know them (linear opacity 0..1, linear scale, colour 0..1), with _raw
    as stored; x, y, z in the engine frame."""

    name: str
    comparator: str
    value: float

    def __post_init__(self) -> None:
        if self.name not in FILTER_ATTRIBUTES:
            raise UsageError(f"filter {self.name!r}: unknown attribute (expected one of "
                             f"{', '.join(FILTER_ATTRIBUTES)})")
        if self.comparator not in COMPARATORS:
            raise UsageError(f"filter {self.name}: unknown comparison {self.comparator!r} (expected one of "
                             f"{', '.join(COMPARATORS)})")
        if self.name == "opacity" and not 0 < self.value < 1:
            raise UsageError(f"filter opacity: {self.value:g} is not between 0 and 1 (exclusive)")
        if self.name.startswith("scale_") and not self.name.endswith("_raw") and not self.value > 0:
            raise UsageError(f"filter {self.name}: {self.value:g} is not above 0 (a linear scale)")

    @property
    def label(self) -> str:
        return f"filter-value {self.name},{self.comparator},{self.value:g}"

    def keep(self, g: Gaussians) -> np.ndarray:
        name = self.name.removesuffix("_raw")
        column, index = _COLUMNS[name]
        values = getattr(g, column).astype(np.float64)
        values = values if index is None else values[:, index]
        if column == "positions":
            values = values * ENGINE_SIGNS[index]
        threshold = float(self.value) if self.name.endswith("_raw") else _stored(name, float(self.value))
        return COMPARATORS[self.comparator](values, np.float64(threshold))


# Cells along one axis the density filter numbers at most: its cell keys (three axes' ranks) then fit an int64.
_MAX_AXIS_CELLS = 1 << 21


@dataclass(frozen=True)
class DensityFilter:
    """Floater removal (--filter-density SIZE,MIN): keep the splats whose grid cell (cubes of side SIZE, in scene
    units) and its 26 neighbours hold at least MIN splat centres together; a floater is a splat alone in empty
    space. Unlike the other edits this is a function of the whole scene, not of one splat: it runs on the splats
    in memory, and the partitioned encoder refuses it (Pipeline.per_splat). Exact integer counts: the result does
    not depend on the splats' order."""

    size: float
    min_count: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.size) and self.size > 0):
            raise UsageError(f"--filter-density: cell size {self.size:g} is not above 0")
        if self.min_count < 1:
            raise UsageError(f"--filter-density: minimum count {self.min_count} is not at least 1")

    @property
    def label(self) -> str:
        return f"filter-density {self.size:g},{self.min_count}"

    def neighbour_counts(self, g: Gaussians) -> np.ndarray:
        """Per splat, the splat centres in its cell and the 26 around it (itself included)."""
        if not len(g):
            return np.zeros(0, np.int64)
        cells = np.floor(g.positions.astype(np.float64) / self.size).astype(np.int64)
        # Each axis's occupied cells ranked, with a gap kept wherever two are not adjacent, so that +-1 in rank is
        # +-1 in space and a cell key is three small ranks whatever the scene's extent (floaters far out included).
        ranks = np.empty_like(cells)
        for a in range(3):
            values, inverse = np.unique(cells[:, a], return_inverse=True)
            steps = np.minimum(np.diff(values), 2)  # adjacent: 1; farther apart: 2 (never neighbours)
            dense = np.concatenate([[1], 1 + np.cumsum(steps)])  # from 1: rank - 1 exists for every cell
            if dense[-1] + 2 > _MAX_AXIS_CELLS:
                raise UsageError(f"--filter-density: cell size {self.size:g} makes more than {_MAX_AXIS_CELLS} "
                                 "cells along one axis of the scene; give a larger size")
            ranks[:, a] = dense[inverse]
        span = _MAX_AXIS_CELLS
        keys = ranks[:, 0] + span * (ranks[:, 1] + span * ranks[:, 2])
        unique, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        total = np.zeros(len(unique), np.int64)
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    other = unique + dx + span * (dy + span * dz)
                    at = np.minimum(np.searchsorted(unique, other), len(unique) - 1)
                    total += np.where(unique[at] == other, counts[at], 0)
        return total[inverse.ravel()]

    def keep(self, g: Gaussians) -> np.ndarray:
        return self.neighbour_counts(g) >= self.min_count


Edit = Transform | Box | Sphere | ValueFilter | DensityFilter


def parse_filter(text: str) -> ValueFilter:
    """'opacity>0.1', 'scale_0<=0.05', 'x!=0' (--filter) or 'opacity,gt,0.1' (--filter-value)."""
    if text.count(",") == 2:
        name, comparator, value = (v.strip() for v in text.split(","))
    else:
        for symbol in ("<=", ">=", "!=", "==", "<", ">", "="):
            if symbol in text:
                name, value = (v.strip() for v in text.split(symbol, 1))
                comparator = SYMBOLS[symbol]
                break
        else:
            raise UsageError(f"filter {text!r}: expected ATTR<OP>VALUE like opacity>0.1 (OP one of < <= > >= == !=) "
                             "or NAME,CMP,VALUE like opacity,gt,0.1")
    try:
        number = float(value)
    except ValueError:
        raise UsageError(f"filter {text!r}: {value!r} is not a number") from None
    if not math.isfinite(number):
        raise UsageError(f"filter {text!r}: {value!r} is not a finite number")
    return ValueFilter(name, comparator, number)


@dataclass
class Pipeline:
    """Edits in command-line order; consecutive transforms composed into one step (as splat-transform does)."""

    edits: list[Edit] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.edits)

    @property
    def steps(self) -> list[Edit]:
        out: list[Edit] = []
        for e in self.edits:
            if isinstance(e, Transform) and out and isinstance(out[-1], Transform):
                out[-1] = out[-1].then(e)
            else:
                out.append(e)
        return out

    @property
    def per_splat(self) -> bool:
        """Whether every edit is a function of one splat (so chunks may be edited apart: the partitioned encoder,
        a dry run by row ranges)."""
        return not any(isinstance(e, DensityFilter) for e in self.edits)

    @property
    def transforms(self) -> bool:
        return any(isinstance(e, Transform) for e in self.edits)

    def run(self, g: Gaussians) -> tuple[Gaussians, list[tuple[str, int]]]:
        """The edited splats and, per step, its label and the splats it kept."""
        counts = []
        for step in self.steps:
            if isinstance(step, Transform):
                g = step.apply(g)
            else:
                g = g.subset(step.keep(g))
            counts.append((step.label, len(g)))
        return g, counts

    def apply(self, g: Gaussians) -> Gaussians:
        return self.run(g)[0] if self.edits else g
