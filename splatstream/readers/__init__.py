"""Readers (and the .splat writer) for splat formats other than the standard 3DGS PLY.

Each reader validates a file before trusting it: sizes against the file length, counts capped by the file
size before anything is allocated, reserved fields and versions, and decompressed sizes capped by what the
declared count implies. Every problem is an InputError naming the file, the field and what was expected.
Field mappings and what each format loses are documented in format_spec/foreign_formats.md.
"""
from __future__ import annotations

import os

import numpy as np

# Opacity bytes of 0 and 255 have no finite logit; every 8-bit-alpha reader clamps the opacity to
# [OPACITY_EPS, 1 - OPACITY_EPS] first (the same clamp as splat-transform's .splat reader), so logits stay
# within +-13.8.
OPACITY_EPS = 1e-6


def opacity_logits_from_unit(alpha: np.ndarray) -> np.ndarray:
    """Logits of opacities in [0, 1], clamped away from 0 and 1 so they stay finite."""
    p = np.clip(alpha.astype(np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p / (1.0 - p)).astype(np.float32)


# Decoded data a reader may allocate for one file when the file's own size does not bound it (WebP planes, zstd
# frames and zip members can expand far beyond their compressed size): half the machine's memory, or
# SPLATSTREAM_MEMORY_BUDGET bytes.
def memory_budget() -> int:
    configured = os.environ.get("SPLATSTREAM_MEMORY_BUDGET")
    if configured:
        return int(configured)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30
