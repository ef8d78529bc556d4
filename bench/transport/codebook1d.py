"""1-D codebooks for scales and colours (SOG-style), against per-chunk norm8x4, on the error and entropy side.

Lossy, so an operating point rather than transport: this only estimates whether it could pay. For each scene:
log scales (3 per splat) and SH0 colour (3 per splat) quantised (a) as the encoder does today, norm8x4 against
per-chunk ranges (Morton order), and (b) by one 256-entry 1-D k-means codebook over all values of the attribute;
RMSE in value units and the order-0 entropy of the 8-bit symbols (per-chunk: after the transport's delta / none,
whichever is smaller; codebook indices: as they are, plus the 256-entry table).

    python bench/transport/codebook1d.py SCENE ...
"""
from __future__ import annotations

import sys

import numpy as np

from splatstream.format.layout import CHUNK_SIZE, morton_order
from splatstream.io import read_gaussians


def entropy_bytes(sym: np.ndarray) -> float:
    counts = np.bincount(sym.reshape(-1))
    counts = counts[counts > 0]
    return float((counts * np.log2(counts.sum() / counts)).sum() / 8)


def per_chunk_8bit(v: np.ndarray) -> tuple[float, float]:
    n = len(v) // CHUNK_SIZE * CHUNK_SIZE
    c = v[:n].reshape(-1, CHUNK_SIZE, v.shape[1])
    lo, hi = c.min(axis=1, keepdims=True), c.max(axis=1, keepdims=True)
    ext = np.where(hi > lo, hi - lo, 1)
    q = np.rint((c - lo) / ext * 255).astype(np.int64)
    err = lo + q / 255 * ext - c
    sym = q.reshape(-1, v.shape[1])
    plain = sum(entropy_bytes(sym[:, k]) for k in range(v.shape[1]))
    delta = sum(entropy_bytes(np.diff(sym[:, k], prepend=0) & 255) for k in range(v.shape[1]))
    return float(np.sqrt((err ** 2).mean())), min(plain, delta) / n


def codebook_8bit(v: np.ndarray, iterations: int = 12) -> tuple[float, float]:
    flat = np.sort(v.reshape(-1).astype(np.float64))
    centres = flat[np.linspace(0, len(flat) - 1, 256).astype(np.int64)].copy()  # quantile seeding
    for _ in range(iterations):  # 1-D Lloyd on the sorted values: boundaries are midpoints
        edges = (centres[1:] + centres[:-1]) / 2
        idx = np.searchsorted(edges, flat)
        sums = np.bincount(idx, weights=flat, minlength=256)
        counts = np.bincount(idx, minlength=256)
        live = counts > 0
        centres[live] = sums[live] / counts[live]
        centres.sort()
    edges = (centres[1:] + centres[:-1]) / 2
    idx = np.searchsorted(edges, v.reshape(-1))
    err = centres[idx] - v.reshape(-1)
    return float(np.sqrt((err ** 2).mean())), (entropy_bytes(idx) + 256 * 2) / len(v)


def main() -> None:
    for path in sys.argv[1:]:
        g = read_gaussians(path)
        order = morton_order(g.positions)
        for name, values in (("log scale", g.log_scales[order]), ("SH0 colour", g.sh_dc[order])):
            a = per_chunk_8bit(values)
            b = codebook_8bit(values)
            print(f"{path.split('/')[-1]:28s} {name:10s}: per-chunk norm8 RMSE {a[0]:.4f}, {a[1]:.2f} B/splat; "
                  f"1-D codebook RMSE {b[0]:.4f}, {b[1]:.2f} B/splat")


if __name__ == "__main__":
    main()
