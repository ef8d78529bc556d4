"""Rounding to float16 in a chosen direction: chunk ranges are stored as float16 (format.md 4.3) and must still hold
the values they bound, so a minimum rounds down and a maximum up. Below both codec.py and steps.py, which use it."""
from __future__ import annotations

import numpy as np


def f16_floor(x: np.ndarray) -> np.ndarray:
    """Largest float16 <= x (so a stored minimum never exceeds the true one)."""
    h = x.astype(np.float16)
    over = h.astype(np.float32) > x
    h[over] = np.nextafter(h[over], np.float16(-np.inf))
    return h


def f16_ceil(x: np.ndarray) -> np.ndarray:
    h = x.astype(np.float16)
    under = h.astype(np.float32) < x
    h[under] = np.nextafter(h[under], np.float16(np.inf))
    return h
