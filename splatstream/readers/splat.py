"""antimatter15 `.splat`: headerless 32-byte records (no magic, no count, no SH bands).

Record layout (little-endian): position f32 x3, LINEAR scale f32 x3, RGBA u8 x4 (RGB = 0.5 + SH_C0 * f_dc
clamped to [0, 1] times 255, A = sigmoid(opacity) times 255), rotation u8 x4 = (w, x, y, z) * 128 + 128.
"""
from __future__ import annotations

import os
import warnings

import numpy as np

from ..atomic import atomic_file
from ..errors import InputError
from ..gaussians import SH_C0, Gaussians, normalize_quaternions, sigmoid
from ..progress import some_of
from ..reader_support import DROP_INVALID_HINT, check_memory, model_bytes_per_splat, opacity_logits_from_unit

SPLAT_RECORD = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)),
                         ("rotation", "u1", (4,))])
assert SPLAT_RECORD.itemsize == 32
# Beyond these magnitudes a float is not a coordinate or a scale of any real scene: it is what other bytes
# read as float32 look like. Used to tell a .splat file from a misnamed one.
PLAUSIBLE_POSITION = 1e7
PLAUSIBLE_SCALE = 1e7
# Scales that underflowed to 0 when the writer took exp() of a very negative log scale get this log scale
# instead of -inf (the splat is invisible either way).
MIN_LOG_SCALE = float(np.log(np.float32(1e-30)))


def read_splat(path: str | os.PathLike, drop_invalid: bool = False) -> Gaussians:
    path = os.fspath(path)
    size = os.path.getsize(path)
    if size == 0:
        raise InputError(path, None, "file is empty (expected 32-byte .splat records)")
    if size % SPLAT_RECORD.itemsize:
        raise InputError(path, "file length", f"{size} bytes is not a multiple of 32 (a .splat file is a sequence of "
                         f"32-byte records; {size % 32} bytes left over: truncated or not a .splat file)")
    check_memory(path, None, size // SPLAT_RECORD.itemsize, SPLAT_RECORD.itemsize + 3 * model_bytes_per_splat(0))
    records = np.fromfile(path, SPLAT_RECORD)
    n = len(records)
    positions = records["position"]
    scales = records["scale"]
    with np.errstate(invalid="ignore"):
        bad_position = ~(np.abs(positions) < PLAUSIBLE_POSITION).all(axis=1)  # NaN compares False
        # A scale of 0 on one axis is a flat splat (a writer's exp() underflowed); 0 on all three is no splat at
        # all, and what a zero-filled file or padding reads as.
        bad_scale = ~((scales >= 0) & (scales < PLAUSIBLE_SCALE)).all(axis=1) | (scales == 0).all(axis=1)
    zero_rotation = (records["rotation"] == 128).all(axis=1)
    bad = bad_position | bad_scale | zero_rotation
    if bad.any():
        counts = (f"{int(bad_position.sum())} with a non-finite or implausible position (|x| >= 1e7), "
                  f"{int(bad_scale.sum())} with a non-finite, negative, implausible (>= 1e7) or all-zero scale, "
                  f"{int(zero_rotation.sum())} with a zero-length quaternion (all four bytes 128)")
        if bad.sum() * 2 > n:
            raise InputError(path, "records", f"{some_of(int(bad.sum()), n, 'records', ('is', 'are'))} implausible "
                             f"({counts}): this does not look like a .splat file")
        msg = f"{some_of(int(bad.sum()), n, 'splats', ('is', 'are'))} invalid ({counts})"
        if not drop_invalid:
            raise InputError(path, "records", f"{msg}; {DROP_INVALID_HINT}")
        warnings.warn(f"{path}: {msg}; dropped", stacklevel=2)
        records = records[~bad]
        positions, scales = records["position"], records["scale"]
    rgba = records["rgba"].astype(np.float32) / 255.0
    rotations = (records["rotation"].astype(np.float32) - 128.0) / 128.0
    with np.errstate(divide="ignore"):
        log_scales = np.maximum(np.log(scales), MIN_LOG_SCALE)
    m = len(records)
    return Gaussians(
        positions=positions,
        rotations=normalize_quaternions(rotations),
        log_scales=log_scales,
        opacity_logits=opacity_logits_from_unit(rgba[:, 3]),
        sh_dc=(rgba[:, :3] - 0.5) / SH_C0,
        sh_rest=np.zeros((m, 0, 3), np.float32),
    )


def splat_records(g: Gaussians) -> np.ndarray:
    """The 32-byte .splat records of `g`, in the order of `g` (SH bands above 0 are dropped)."""
    out = np.empty(len(g), SPLAT_RECORD)
    out["position"] = g.positions
    out["scale"] = np.exp(g.log_scales)
    rgb = np.clip(np.rint(g.base_colors * 255.0), 0, 255)
    alpha = np.clip(np.rint(sigmoid(g.opacity_logits) * 255.0), 0, 255)
    out["rgba"] = np.concatenate([rgb, alpha[:, None]], axis=1).astype(np.uint8)
    out["rotation"] = np.clip(np.rint(g.rotations * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return out


def write_splat(g: Gaussians, path: str | os.PathLike) -> None:
    """Write an antimatter15 .splat file (atomically). Lossy: no SH bands, 8-bit colour, opacity, rotation."""
    records = splat_records(g)
    # The format has no header: readers (ours included) tell a .splat file from other bytes by plausible values,
    # so records beyond those bounds would make the file unreadable. Refuse rather than write it.
    with np.errstate(invalid="ignore"):
        implausible = ~(np.abs(records["position"]) < PLAUSIBLE_POSITION).all(axis=1) | \
            ~(records["scale"] < PLAUSIBLE_SCALE).all(axis=1) | (records["scale"] == 0).all(axis=1)
    if implausible.any():
        raise InputError(path, None, f"{some_of(int(implausible.sum()), len(g), 'splats', ('has', 'have'))} a "
                         "position beyond +-1e7 or a scale of 1e7 or more (or none at all), which .splat readers take "
                         "for garbage (the format has no header); write .ply, .spz or .glb instead")
    with atomic_file(path) as f:
        records.tofile(f)
