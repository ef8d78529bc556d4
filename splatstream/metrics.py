"""Image quality metrics: PSNR and SSIM.

Images are float arrays (H, W) or (H, W, C) with values meant in [0, 1]; both metrics clamp to [0, 1] first
(what a display shows, and what an 8-bit screenshot holds), unless `clamp=False`.

SSIM follows Wang, Bovik, Sheikh, Simoncelli 2004 and their reference MATLAB code: an 11x11 Gaussian window with
sigma 1.5 (normalised to sum 1), K1 = 0.01, K2 = 0.03, dynamic range L = 1, statistics only where the window fits
inside the image ("valid" filtering, no padding), no downsampling. Colour images: SSIM is computed per channel
(R, G, B separately) and the per-channel means are averaged.
"""
from __future__ import annotations

import math

import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _prepare(a: np.ndarray, b: np.ndarray, clamp: bool) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if a.ndim not in (2, 3):
        raise ValueError(f"expected (H, W) or (H, W, C) images, got shape {a.shape}")
    if clamp:
        a = np.clip(a, 0.0, 1.0)
        b = np.clip(b, 0.0, 1.0)
    return a, b


def mse(a: np.ndarray, b: np.ndarray, clamp: bool = True) -> float:
    a, b = _prepare(a, b, clamp)
    return float(np.mean((a - b) ** 2))


def psnr_from_mse(m: float, data_range: float = 1.0) -> float:
    return math.inf if m == 0 else 10.0 * math.log10(data_range * data_range / m)


def psnr(a: np.ndarray, b: np.ndarray, data_range: float = 1.0, clamp: bool = True) -> float:
    """10 log10(range^2 / MSE), MSE over all pixels and channels; inf for identical images."""
    return psnr_from_mse(mse(a, b, clamp), data_range)


def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    w = np.exp(-(x * x) / (2.0 * sigma * sigma))
    return w / w.sum()


def _filter_valid(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation of (H, W, ...) with the outer product w w^T."""
    n = len(w)
    h = x.shape[0] - n + 1
    wd = x.shape[1] - n + 1
    rows = sum(w[k] * x[k:k + h] for k in range(n))
    return sum(w[k] * rows[:, k:k + wd] for k in range(n))


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = 1.0, clamp: bool = True) -> np.ndarray:
    """SSIM index map ((H-10), (W-10)[, C]) of two images."""
    a, b = _prepare(a, b, clamp)
    if a.shape[0] < SSIM_WINDOW or a.shape[1] < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {a.shape[1]}x{a.shape[0]}")
    w = gaussian_window_1d()
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    mu_a = _filter_valid(a, w)
    mu_b = _filter_valid(b, w)
    aa = _filter_valid(a * a, w) - mu_a * mu_a
    bb = _filter_valid(b * b, w) - mu_b * mu_b
    ab = _filter_valid(a * b, w) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * ab + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (aa + bb + c2))


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0, clamp: bool = True) -> float:
    """Mean SSIM; for colour images the mean over channels of each channel's mean SSIM."""
    m = ssim_map(a, b, data_range, clamp)
    return float(m.mean())
