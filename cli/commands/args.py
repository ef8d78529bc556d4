"""Parsers for the option values the commands share (vectors, image sizes), with the CLI's error messages."""
from __future__ import annotations

import math

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
    import re

    match = re.fullmatch(r"\s*([0-9.]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", text or "")
    unit = match.group(2).lower() if match else ""
    try:
        value = float(match.group(1)) * _UNITS[unit] if match else math.nan
    except (KeyError, ValueError):
        value = math.nan
    if not math.isfinite(value) or value < (1 << 20):
        raise UsageError(f"{what}: expected a size of at least 1MiB like 4GB or 512MiB, got {text!r}")
    return int(value)
