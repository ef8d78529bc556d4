"""PlayCanvas SOG version 2: one scene as meta.json plus lossless WebP planes (a "unit"), bundled into a `.sog`
zip or written as a directory (a unit of a streamed SOG, splatstream/writers/sog_lod.py).

The layout is the one splatstream/readers/sog.py reads and format_spec/foreign_formats.md describes; the
choices follow splat-transform's writer (src/lib/writers/write-sog.ts, 3.7):

* texels: width ceil(sqrt(n) / 4) * 4, height ceil(n / width / 4) * 4; splat i is texel i (row-major).
* positions: per axis v = sign(x) ln(1 + |x|), quantised to 16 bits over the unit's [min, max] of v.
* rotations: the three smallest of the unit (w, x, y, z) quaternion, sign-flipped so the largest is positive,
  times sqrt(2), mapped to bytes; alpha 252 + index of the largest.
* log scales and band-0 colours: one 256-entry codebook each, pooled over the three axes / channels (1D k-means
  here; splat-transform solves the same problem by dynamic programming on a histogram). sh0 alpha = opacity.
* SH bands 1..3: a palette of min(64, 2^floor(log2(n / 1024))) x 1024 entries (splat-transform's size) fitted by
  k-means (`vq.build_codebook`), its coefficient values in one more 256-entry codebook; labels 16-bit.

Everything is written rounded to nearest (splat-transform truncates the position and rotation bytes); the values
decode with the same formulas. Lossless WebP comes from Pillow with `exact` so colours under a zero alpha survive.
"""
from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..atomic import atomic_file
from ..errors import UsageError
from ..format.layout import morton_order
from ..gaussians import SH_REST_COEFFS, Gaussians, normalize_quaternions, sigmoid
from ..vq import build_codebook

SOG_VERSION = 2
CODEBOOK_ENTRIES = 256
LLOYD_ITERATIONS = 60
HISTOGRAM_BINS = 4096
# 1D k-means runs on a sorted sample: a million values fit the codebook as well as all of them (sub-1e-4 change
# in RMS on the 1M scene) and keep the sort short.
QUANTISE_SAMPLE = 1 << 20
# WebP's dimension limit: 16383 x 16383 texels.
MAX_TEXTURE_SIDE = 16383
# Lossless WebP effort (libwebp's method 0-6 and, for lossless, quality 0-100 as effort): method 2 at quality 50
# writes slightly fewer bytes than method 4 at quality 100 in up to a ninth of the CPU (BENCHMARKS.md, "WebP
# effort of the SOG writers").
WEBP_METHOD = 2
WEBP_QUALITY = 50
QUAT_ORDER = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))  # the stored components per largest index
PLANE_NAMES = ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp")
SHN_NAMES = ("shN_centroids.webp", "shN_labels.webp")
GENERATOR = "splatstream"


@dataclass(frozen=True)
class SogUnit:
    """One SOG scene: its meta.json object and its WebP files by name."""

    meta: dict
    files: dict[str, bytes]

    def meta_bytes(self) -> bytes:
        return json.dumps(self.meta, separators=(",", ":")).encode("utf-8")


def texture_size(count: int) -> tuple[int, int]:
    """(width, height) of the planes of `count` splats, as splat-transform lays them out (at least 4 x 4)."""
    width = max(4, math.ceil(math.sqrt(count) / 4) * 4)
    height = max(4, math.ceil(count / width / 4) * 4)
    return width, height


def palette_size(count: int) -> int:
    """splat-transform's SH palette size for `count` splats: min(64, 2^floor(log2(count / 1024))) x 1024."""
    if count <= 0:
        return 1
    return int(min(64.0, 2.0 ** math.floor(math.log2(count / 1024))) * 1024)


def quantise_1d(values: np.ndarray, k: int = CODEBOOK_ENTRIES, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(k sorted float32 centroids, uint8-or-wider label per value) by 1D Lloyd iterations from quantiles.

    Fewer distinct values than k: the codebook is those values (exact), padded with the last. Lloyd in 1D on
    sorted data is cheap: cell boundaries are midpoints, cell sums come from a prefix sum."""
    flat = np.asarray(values, np.float64).reshape(-1)
    if flat.size == 0:
        return np.zeros(k, np.float32), np.zeros(np.shape(values), np.int64)
    distinct = np.unique(flat) if flat.size <= 4 * QUANTISE_SAMPLE else None
    if distinct is not None and len(distinct) <= k:
        book = np.concatenate([distinct, np.full(k - len(distinct), distinct[-1])])
    else:
        data = flat
        if data.size > QUANTISE_SAMPLE:
            data = np.random.default_rng(seed).choice(data, QUANTISE_SAMPLE, replace=False)
        data = np.sort(data)
        # Lloyd on a histogram whose bins weigh count^0.5 (splat-transform's alpha = 0.5): plain least squares
        # leaves the sparse tails of log scales and colours to a handful of entries. Bin edges blend quantile and
        # even positions.
        ranks = np.linspace(0.0, 1.0, HISTOGRAM_BINS + 1)
        edges = np.unique(0.5 * np.quantile(data, ranks) + 0.5 * (data[0] + ranks * (data[-1] - data[0])))
        cuts = np.searchsorted(data, edges[1:-1])
        lo, hi = np.concatenate([[0], cuts]), np.concatenate([cuts, [len(data)]])
        prefix = np.concatenate([[0.0], np.cumsum(data)])
        filled = hi > lo
        counts = (hi - lo)[filled].astype(np.float64)
        points = (prefix[hi[filled]] - prefix[lo[filled]]) / counts
        weights = np.sqrt(counts)
        if len(points) <= k:
            book = np.concatenate([points, np.full(k - len(points), points[-1])])
        else:
            wsum = np.concatenate([[0.0], np.cumsum(weights)])
            wxsum = np.concatenate([[0.0], np.cumsum(weights * points)])
            book = np.quantile(points, (np.arange(k) + 0.5) / k)
            for _ in range(LLOYD_ITERATIONS):
                cut = np.searchsorted(points, (book[1:] + book[:-1]) / 2)
                a, b = np.concatenate([[0], cut]), np.concatenate([cut, [len(points)]])
                mass = wsum[b] - wsum[a]
                live = mass > 0
                updated = book.copy()
                updated[live] = (wxsum[b[live]] - wxsum[a[live]]) / mass[live]
                done = np.allclose(updated, book, rtol=0, atol=1e-9)
                book = np.sort(updated)
                if done:
                    break
    book32 = book.astype(np.float32)
    labels = np.searchsorted((book32[1:].astype(np.float64) + book32[:-1]) / 2, flat, side="right")
    return book32, labels.reshape(np.shape(values))


def _webp(texels: np.ndarray, width: int, height: int) -> bytes:
    """Lossless WebP of (n, 4) uint8 texels laid out row-major on width x height (the rest zero)."""
    from PIL import Image

    plane = np.zeros((width * height, 4), np.uint8)
    plane[:len(texels)] = texels
    out = io.BytesIO()
    Image.fromarray(plane.reshape(height, width, 4), "RGBA").save(out, format="WEBP", lossless=True, exact=True,
                                                                  quality=WEBP_QUALITY, method=WEBP_METHOD)
    return out.getvalue()


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _log_transform(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.log1p(np.abs(x))


def _means(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[float], list[float]]:
    logged = _log_transform(positions.astype(np.float64))
    mins = logged.min(axis=0) if len(logged) else np.zeros(3)
    maxs = logged.max(axis=0) if len(logged) else np.zeros(3)
    span = np.where(maxs > mins, maxs - mins, 1.0)
    q = np.clip(np.rint((logged - mins) / span * 65535.0), 0, 65535).astype(np.uint32)
    ones = np.full((len(q), 1), 255, np.uint8)
    low = np.concatenate([(q & 0xFF).astype(np.uint8), ones], axis=1)
    high = np.concatenate([(q >> 8).astype(np.uint8), ones], axis=1)
    return low, high, [float(v) for v in mins], [float(v) for v in maxs]


def _quats(rotations: np.ndarray) -> np.ndarray:
    q = normalize_quaternions(rotations).astype(np.float64)
    largest = np.argmax(np.abs(q), axis=1)
    q *= np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None] * math.sqrt(2.0)
    out = np.empty((len(q), 4), np.uint8)
    for index, others in enumerate(QUAT_ORDER):
        rows = largest == index
        out[rows, :3] = _u8(255.0 * (q[np.ix_(rows, others)] * 0.5 + 0.5))
        out[rows, 3] = 252 + index
    return out


def _shn(g: Gaussians, seed: int, progress: Callable[[float], None] | None = None) -> tuple[dict, dict[str, bytes],
                                                                                          np.ndarray]:
    """The SH palette section of meta.json, the centroids WebP, and the label texels (`progress`: the palette's fit,
    build_codebook's)."""
    k = SH_REST_COEFFS[g.sh_degree]
    rows = g.sh_rest.transpose(0, 2, 1).reshape(len(g), 3 * k)  # channel-major, as splat-transform clusters them
    size = palette_size(len(g))
    codebook = build_codebook(rows, size, seed=seed, progress=progress)
    labels = codebook.assign(rows)
    entries = codebook.entries.reshape(-1, 3, k)  # (palette, channel, coefficient)
    book, index = quantise_1d(entries, seed=seed)
    per_entry = np.concatenate([index.transpose(0, 2, 1).astype(np.uint8),  # (palette, coefficient, channel)
                                np.full((len(entries), k, 1), 255, np.uint8)], axis=2)
    rows_of_64 = math.ceil(len(entries) / 64)
    centroids = _webp(per_entry.reshape(-1, 4), 64 * k, rows_of_64)
    label_texels = np.zeros((len(g), 4), np.uint8)
    label_texels[:, 0] = labels & 0xFF
    label_texels[:, 1] = labels >> 8
    label_texels[:, 3] = 255
    meta = {"count": size, "bands": g.sh_degree, "codebook": [float(v) for v in book], "files": list(SHN_NAMES)}
    return meta, {SHN_NAMES[0]: centroids}, label_texels


# Shares of a unit's time: with SH bands their palette's fit is most of it (45 of 54 s of playbot's streamed SOG).
_SHARE_PLANES_WITH_SH = 0.15


def sog_unit(g: Gaussians, reorder: bool = True, seed: int = 0,
             progress: Callable[[float], None] | None = None) -> SogUnit:
    """The SOG files of `g`. `reorder`: store the splats in Morton order (what splat-transform does for a whole
    scene); False keeps the given order (a streamed SOG unit, whose row ranges are the tree's references).
    `progress` hears the share of the unit done (the planes, then the SH palette's fit), the files unchanged."""
    report = progress or (lambda fraction: None)
    planes_share = _SHARE_PLANES_WITH_SH if g.sh_degree > 0 and len(g) > 0 else 1.0
    n = len(g)
    width, height = texture_size(n)
    if width > MAX_TEXTURE_SIDE or height > MAX_TEXTURE_SIDE:
        raise UsageError(f"{n} splats do not fit one SOG (WebP planes are at most {MAX_TEXTURE_SIDE} texels a "
                         "side, about 268M splats); export a streamed SOG instead")
    if reorder and n > 1:
        g = g.subset(morton_order(g.positions))
    low, high, mins, maxs = _means(g.positions)
    scale_book, scale_index = quantise_1d(g.log_scales, seed=seed)
    color_book, color_index = quantise_1d(g.sh_dc, seed=seed)
    scale_texels = np.concatenate([scale_index.astype(np.uint8), np.full((n, 1), 255, np.uint8)], axis=1)
    alpha = _u8(sigmoid(g.opacity_logits.astype(np.float64)) * 255.0)
    color_texels = np.concatenate([color_index.astype(np.uint8), alpha[:, None]], axis=1)
    files = {
        "means_l.webp": _webp(low, width, height),
        "means_u.webp": _webp(high, width, height),
        "quats.webp": _webp(_quats(g.rotations), width, height),
        "scales.webp": _webp(scale_texels, width, height),
        "sh0.webp": _webp(color_texels, width, height),
    }
    report(planes_share)
    meta: dict = {
        "version": SOG_VERSION,
        "asset": {"generator": GENERATOR},
        "count": n,
        "means": {"mins": mins, "maxs": maxs, "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": [float(v) for v in scale_book], "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": [float(v) for v in color_book], "files": ["sh0.webp"]},
    }
    if g.sh_degree > 0 and n > 0:
        shn_meta, shn_files, label_texels = _shn(
            g, seed, lambda fraction: report(planes_share + (1.0 - planes_share) * fraction))
        files.update(shn_files)
        files[SHN_NAMES[1]] = _webp(label_texels, width, height)
        meta["shN"] = shn_meta
    report(1.0)
    return SogUnit(meta, files)


def sog_bytes(g: Gaussians, progress: Callable[[float], None] | None = None) -> bytes:
    """A bundled .sog: a zip of meta.json and the WebP planes, stored (WebP does not deflate further). `progress`
    hears the share done (sog_unit's)."""
    unit = sog_unit(g, progress=progress)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for name, data in unit.files.items():
            archive.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data)
        meta = zipfile.ZipInfo("meta.json", (1980, 1, 1, 0, 0, 0))
        archive.writestr(meta, unit.meta_bytes(), compress_type=zipfile.ZIP_DEFLATED)
    return out.getvalue()


def write_unit(unit: SogUnit, directory: str) -> None:
    """Write a unit's meta.json and WebP files into `directory` (which the caller writes atomically)."""
    os.makedirs(directory, exist_ok=True)
    for name, data in unit.files.items():
        with open(os.path.join(directory, name), "wb") as f:
            f.write(data)
    with open(os.path.join(directory, "meta.json"), "wb") as f:
        f.write(unit.meta_bytes())


def write_sog(g: Gaussians, path: str | os.PathLike, progress: Callable[[float], None] | None = None) -> None:
    """Write a bundled .sog atomically (temporary name, then rename). `progress` hears the share done: the planes,
    then the SH palette's fit, most of a scene with SH bands (5.6 s of playbot's write)."""
    try:
        data = sog_bytes(g, progress)
    except UsageError as exc:  # name the file being written
        raise UsageError(f"{os.fspath(path)}: {exc}") from None
    with atomic_file(path) as f:
        f.write(data)
