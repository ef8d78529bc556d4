"""Parsers for the option values the commands share (vectors, image sizes, the edits of convert and encode), with
the CLI's error messages."""
from __future__ import annotations

import argparse
import math
import os
import re

from splatstream.camera import MAX_AZIMUTH_DEG, check_azimuth
from splatstream.edit import (
    Box,
    DensityFilter,
    Pipeline,
    Sphere,
    parse_filter,
    rotation,
    rotation_quaternion,
    scaling,
    translation,
)
from splatstream.errors import UsageError
from splatstream.progress import count

from .edit_flags import EDIT_OPTIONS

# --drop-invalid, in every command that reads a splat file (encode, convert, render, view, eval): one meaning, one
# help. render, view and eval refused NaN rows pointing at encode and convert for it (newuser63); each reads its
# splat file with read_gaussians, so dropping the rows there costs nothing more than in encode.
DROP_INVALID_HELP = ("drop the splats a scene cannot hold (NaN, inf, a zero-length quaternion, values beyond "
                     "format.md 4.8's limits; a warning says how many) instead of refusing the input")


def check_directory_output(output_dir: str, command: str, index: str, file_suffixes: tuple[str, ...] = ()) -> None:
    """A directory output (export-sog-lod's streamed SOG, export-3dtiles's tileset) named as the file an engine is
    given (`sog/garden/lod-meta.json`, `tiles/garden/tileset.json`) or as a one-file format (`garden.sog`) was
    written as a directory of that name: a lod-meta.json directory holding lod-meta.json (newuser64)."""
    name = os.path.basename(os.path.normpath(output_dir))
    parent = os.path.dirname(os.path.normpath(output_dir)) or "."
    if name == index:
        raise UsageError(f"{output_dir}: {command} writes a directory with {index} inside it; give the directory "
                         f"({parent}), and {output_dir} is the file an engine loads")
    for suffix in file_suffixes:
        if name.lower().endswith(suffix):
            raise UsageError(f"{output_dir}: {command} writes a directory ({index} and its files), not a {suffix} "
                             f"file; `splatstream decode SCENE {output_dir}` writes one {suffix} file of the full "
                             "detail")


def parse_vector(text: str, what: str, nonzero: bool = False) -> tuple[float, float, float]:
    """'X,Y,Z' -> three finite floats (not all zero when `nonzero`); `what` names the option in errors."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values) or (nonzero and not any(values)):
        kind = "a non-zero vector" if nonzero else "three comma-separated numbers"
        raise UsageError(f"{what}: expected {kind} like 0,0,1, got {text!r}")
    return values  # type: ignore[return-value]


def check_look(eye, target, fov_y: float | None) -> None:
    """A camera the user's --eye, --target and --fov-y can make: one line naming the options where it cannot (the
    Camera's own message, 'camera eye and target coincide', named neither)."""
    if tuple(map(float, eye)) == tuple(map(float, target)):
        point = ",".join(f"{float(v):g}" for v in eye)
        raise UsageError(f"--eye and --target: the camera's eye and target are the same point ({point}); give "
                         "a target the camera looks at from the eye")
    if fov_y is not None and not 0 < fov_y < 180:
        raise UsageError(f"--fov-y {fov_y:g}: expected degrees in (0, 180)")


def parse_azimuth(text: str | None, what: str = "--camera-azimuth") -> float:
    """--camera-azimuth DEG: degrees (camera.check_azimuth's range); 0 where not given."""
    if text is None:
        return 0.0
    try:
        return check_azimuth(float(text))
    except ValueError:
        raise UsageError(f"{what} {text}: expected degrees from -{MAX_AZIMUTH_DEG:g} to {MAX_AZIMUTH_DEG:g} (180: "
                         "the other side)") from None


def check_sort_draw(sort: str, draw: str) -> None:
    """--draw names a GPU-path rasterizer: with --sort cpu it was ignored (a raster draw) or refused in a line naming
    neither option (compute)."""
    if sort == "cpu" and draw != "auto":
        raise UsageError(f"--draw {draw} and --sort cpu: --draw picks the GPU sort path's rasterizer, and the CPU "
                         "sort draws its own; give one of them")


# The largest side of a picture the commands render (render, view --size; encode --lod-refine-size).
MAX_RENDER_SIDE = 16384


def parse_size(text: str, smallest: int = 1, largest: int = MAX_RENDER_SIDE, what: str = "--size") -> tuple[int, int]:
    """'WxH' -> (width, height), each within [smallest, largest]."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"{what}: expected WIDTHxHEIGHT like 1280x720, got {text!r}") from None
    if not (smallest <= w <= largest and smallest <= h <= largest):
        raise UsageError(f"{what}: {w}x{h} is out of range ({smallest}..{largest} per side)")
    return w, h


_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "kib": 1024, "m": 1e6, "mb": 1e6, "mib": 1 << 20,
          "g": 1e9, "gb": 1e9, "gib": 1 << 30, "t": 1e12, "tb": 1e12, "tib": 1 << 40}


def parse_bytes(text: str, what: str) -> int:
    """'4GB', '512MiB', '2e9' -> bytes (at least 1 MiB)."""
    match = re.fullmatch(r"\s*([0-9.]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", text or "")
    unit = match.group(2).lower() if match else ""
    try:
        value = float(match.group(1)) * _UNITS[unit] if match else math.nan
    except (KeyError, ValueError):
        value = math.nan
    if not math.isfinite(value) or value < (1 << 20):
        raise UsageError(f"{what}: expected a size of at least 1MiB like 4GB or 512MiB, got {text!r}")
    return int(value)


class _EditAction(argparse.Action):
    """Appends (kind, text) to `edits`, so the edits keep their command-line order across options."""

    def __init__(self, *args, kind: str = "", **kwargs):
        self.kind = kind
        super().__init__(*args, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        edits = list(getattr(namespace, "edits", None) or [])
        edits.append((self.kind, option_string, values))
        namespace.edits = edits


def add_edit_arguments(p: argparse.ArgumentParser, taken: tuple[str, ...] = ()) -> None:
    """The edit options; `taken`: flags the command uses for something else (encode's --scale is the scale
    attribute's texel format), left to it: their edit keeps its other spelling."""
    group = p.add_argument_group(
        "editing the splats (in the order given)",
        "Operations with the names and meaning of PlayCanvas splat-transform's: coordinates are in its frame, a "
        "3DGS PLY's turned 180 degrees about z (x and y negated). --dry-run prints how many splats each step "
        "keeps and writes nothing.")
    for flags, metavar, kind, help_text in EDIT_OPTIONS:
        free = [f for f in flags if f not in taken]
        group.add_argument(*free, metavar=metavar, dest="edits", action=_EditAction, kind=kind, help=help_text)
    group.add_argument("--dry-run", action="store_true", help="print the edit steps and the splats each keeps; "
                                                              "write nothing")


def _numbers(text: str, count: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        expected = "a finite number" if count == 1 else f"{count} comma-separated numbers"
        raise UsageError(f"{what}: expected {expected}, got {text!r}")
    return values


def edits_from(args: argparse.Namespace) -> Pipeline:
    """The edit.Pipeline the options of add_edit_arguments ask for."""
    out = []
    for kind, flag, text in getattr(args, "edits", None) or []:
        if kind == "translate":
            out.append(translation(*_numbers(text, 3, flag)))
        elif kind == "rotate":
            if text.count(",") == 3:
                out.append(rotation_quaternion(*_numbers(text, 4, flag)))
            else:
                out.append(rotation(*_numbers(text, 3, flag)))
        elif kind == "scale":
            s = _numbers(text, 1, flag)[0]
            if s <= 0:
                raise UsageError(f"{flag}: expected a factor above 0, got {text!r}")
            out.append(scaling(s))
        elif kind in ("box", "drop-box"):
            v = _numbers(text, 6, flag)
            if any(a > b for a, b in zip(v[:3], v[3:], strict=True)):
                raise UsageError(f"{flag}: the min corner {v[:3]} exceeds the max corner {v[3:]} on some axis")
            out.append(Box(v[:3], v[3:], keep_inside=kind == "box"))
        elif kind in ("sphere", "drop-sphere"):
            v = _numbers(text, 4, flag)
            if v[3] <= 0:
                raise UsageError(f"{flag}: expected a radius above 0, got {v[3]:g}")
            out.append(Sphere(v[:3], v[3], keep_inside=kind == "sphere"))
        elif kind == "density":
            size, count = _numbers(text, 2, flag)
            if count != int(count):
                raise UsageError(f"{flag}: expected a whole minimum count, got {count:g}")
            out.append(DensityFilter(size, int(count)))
        else:
            out.append(parse_filter(text))
    return Pipeline(out)


def edit_report(path: str, read: int, counts: list[tuple[str, int]]) -> str:
    """--dry-run's lines: the splats read, then each step and the splats it keeps."""
    lines = [f"read {path}: {count(read, 'splat')}"]
    before = read
    for label, kept in counts:
        lines.append(f"  {label}: keeps {kept:,} of {before:,} ({before - kept:,} dropped)")
        before = kept
    if not counts:
        lines.append("  (no edits)")
    return "\n".join(lines)
