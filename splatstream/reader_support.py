"""What the readers of every splat format share, the PLY reader (ply.py) and readers/ alike: the memory budget and
the check of a declared splat count against it, reads of regular files only, and finite opacity logits from 8-bit
alpha. Below both ply.py and readers/, so neither imports the other for these."""
from __future__ import annotations

import os
import stat

import numpy as np

from .errors import InputError, UsageError

# What an invalid splat's error says to do. Every command that reads a splat file takes --drop-invalid (view, render
# and eval since newuser63's pass; before, they pointed at encode and convert, which alone took it).
DROP_INVALID_HINT = "--drop-invalid drops them (encode, convert, render, view, eval)"

# Opacity bytes of 0 and 255 have no finite logit; every 8-bit-alpha reader clamps the opacity to
# [OPACITY_EPS, 1 - OPACITY_EPS] first (the same clamp as splat-transform's .splat reader), so logits stay
# within +-13.8.
OPACITY_EPS = 1e-6


def opacity_logits_from_unit(alpha: np.ndarray) -> np.ndarray:
    """Logits of opacities in [0, 1], clamped away from 0 and 1 so they stay finite."""
    p = np.clip(alpha.astype(np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p / (1.0 - p)).astype(np.float32)


def read_regular_file(path: str, limit: int, label: str | None = None, field: str | None = None) -> bytes:
    """A regular file's bytes (at most `limit`). FIFOs, devices, sockets and directories are refused before any
    read could block or never end; errors name `label` (default: the file) and `field`."""
    where = label or path
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise InputError(where, field, f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(where, field, f"{path}: cannot read ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = "a directory" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO, device or socket)"
            raise InputError(where, field, f"{path} is {kind}")
        if st.st_size > limit:
            raise InputError(where, field, f"{path}: {st.st_size} bytes, more than the {limit} allowed (memory "
                             "budget)")
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read(limit + 1)
    finally:
        os.close(fd)


# Bytes of memory one decoded splat of SH degree d holds in the model (float32: 14 values plus the SH rest).
def model_bytes_per_splat(sh_degree: int) -> int:
    return 4 * (14 + 3 * (0, 3, 8, 15, 24)[min(max(sh_degree, 0), 4)])


def check_memory(path: str, field: str | None, splats: int, bytes_per_splat: int) -> None:
    """Refuse, before anything is allocated, a file whose declared splat count would need more memory to decode
    than the budget (a hostile or corrupt count must not take the machine down)."""
    need = splats * bytes_per_splat
    budget = memory_budget()
    if need > budget:
        raise InputError(path, field, f"{splats} splats need about {need / 2**20:.1f} MiB to decode, more than the "
                         f"memory budget of {budget / 2**20:.1f} MiB (half the machine's memory, or "
                         "SPLATSTREAM_MEMORY_BUDGET bytes)")


# Decoded data a reader may allocate for one file when the file's own size does not bound it (WebP planes, zstd
# frames and zip members can expand far beyond their compressed size): half the machine's memory, or
# SPLATSTREAM_MEMORY_BUDGET bytes.
def memory_budget() -> int:
    configured = os.environ.get("SPLATSTREAM_MEMORY_BUDGET")
    if configured:
        try:
            return int(configured)
        except ValueError:
            raise UsageError(f"SPLATSTREAM_MEMORY_BUDGET={configured!r}: expected a number of bytes") from None
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30
