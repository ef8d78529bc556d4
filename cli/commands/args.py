"""Parsers for the option values the commands share (vectors, image sizes, the edits of convert and encode), with
the CLI's error messages."""
from __future__ import annotations

import argparse
import math
import re

from splatstream.edit import Box, Pipeline, Sphere, parse_filter, rotation, scaling, translation
from splatstream.errors import UsageError


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


def parse_size(text: str, smallest: int = 1, largest: int = 16384, what: str = "--size") -> tuple[int, int]:
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


# The edits of issue 36 (splatstream/edit.py), by splat-transform's long names, with the spellings beside
# them: (flags, metavar, what the value is, help).
EDIT_OPTIONS = [
    (("--translate",), "X,Y,Z", "translate", "move every splat by (X, Y, Z)"),
    (("--rotate",), "X,Y,Z", "rotate", "turn the scene by Euler angles in degrees (x first, then y, then z, about "
                                       "the origin), SH bands 1..3 turned with it"),
    (("--scale", "--scale-by"), "S", "scale", "scale the scene by S about the origin"),
    (("--filter-box", "--crop-box"), "X,Y,Z,X,Y,Z", "box", "keep the splats whose centre lies in the box "
                                                            "(min corner, max corner; faces included)"),
    (("--drop-box",), "X,Y,Z,X,Y,Z", "drop-box", "drop the splats whose centre lies in the box"),
    (("--filter-sphere", "--crop-sphere"), "X,Y,Z,R", "sphere", "keep the splats whose centre lies inside the "
                                                                 "sphere (centre, radius)"),
    (("--drop-sphere",), "X,Y,Z,R", "drop-sphere", "drop the splats whose centre lies inside the sphere"),
    (("--filter-value", "--filter"), "ATTR<OP>VALUE", "filter",
     "keep the splats whose attribute compares true: ATTR<OP>VALUE (OP one of < <= > >= == !=) or splat-transform's "
     "NAME,CMP,VALUE (CMP one of lt lte gt gte eq neq); ATTR one of x y z, opacity (0..1, after the sigmoid), "
     "scale_0..2 (after exp), f_dc_0..2 (colour 0..1), or opacity_raw, scale_N_raw, f_dc_N_raw as stored"),
]


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
        raise UsageError(f"{what}: expected {count} comma-separated numbers, got {text!r}")
    return values


def edits_from(args: argparse.Namespace) -> Pipeline:
    """The edit.Pipeline the options of add_edit_arguments ask for."""
    out = []
    for kind, flag, text in getattr(args, "edits", None) or []:
        if kind == "translate":
            out.append(translation(*_numbers(text, 3, flag)))
        elif kind == "rotate":
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
        else:
            out.append(parse_filter(text))
    return Pipeline(out)


def edit_report(path: str, read: int, counts: list[tuple[str, int]]) -> str:
    """--dry-run's lines: the splats read, then each step and the splats it keeps."""
    lines = [f"read {path}: {read} splats"]
    before = read
    for label, kept in counts:
        lines.append(f"  {label}: keeps {kept} of {before} ({before - kept} dropped)")
        before = kept
    if not counts:
        lines.append("  (no edits)")
    return "\n".join(lines)
