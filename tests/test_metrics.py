import math

import numpy as np
import pytest

from splatstream.metrics import gaussian_window_1d, psnr, ssim, ssim_map


def test_psnr_of_known_noise():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.2, 0.8, size=(64, 64, 3))
    b = a + rng.choice([-0.01, 0.01], size=a.shape)  # every error exactly +-0.01: MSE = 1e-4
    assert psnr(a, b) == pytest.approx(40.0, abs=1e-9)
    assert psnr(a, a) == math.inf
    assert psnr(np.zeros((4, 4)), np.full((4, 4), 0.5)) == pytest.approx(10 * math.log10(4))
    # values outside [0, 1] are clamped: 1.5 shows as 1.0
    assert psnr(np.full((4, 4), 1.5), np.ones((4, 4))) == math.inf


def test_ssim_identical_and_shifted():
    rng = np.random.default_rng(1)
    img = rng.uniform(size=(48, 40, 3))
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    shifted = np.roll(img, 1, axis=1)
    s = ssim(img, shifted)
    assert s < 0.2  # white noise shifted by a pixel is uncorrelated
    smooth = np.cumsum(np.cumsum(rng.normal(size=(48, 40)), 0), 1)
    smooth = (smooth - smooth.min()) / np.ptp(smooth)
    s2 = ssim(smooth, np.roll(smooth, 1, axis=1))
    assert 0.5 < s2 < 1.0
    with pytest.raises(ValueError):
        ssim(img, img[:, :-1])


def test_ssim_constant_images_known_value():
    # constant images: sigma = 0 everywhere, so SSIM = (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1)
    c1 = 0.01 ** 2
    expected = (2 * 0.3 * 0.5 + c1) / (0.3 ** 2 + 0.5 ** 2 + c1)
    assert ssim(np.full((20, 20), 0.3), np.full((20, 20), 0.5)) == pytest.approx(expected, rel=1e-12)


def test_ssim_matches_direct_window_sums():
    """Independent computation: every 11x11 window summed explicitly with the 2D Gaussian weights."""
    rng = np.random.default_rng(2)
    a = rng.uniform(size=(16, 14))
    b = np.clip(a + rng.normal(scale=0.1, size=a.shape), 0, 1)
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5 ** 2))
    w2 = np.outer(g, g)
    w2 /= w2.sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    vals = []
    for i in range(16 - 10):
        for j in range(14 - 10):
            pa, pb = a[i:i + 11, j:j + 11], b[i:i + 11, j:j + 11]
            ma, mb = (w2 * pa).sum(), (w2 * pb).sum()
            va = (w2 * (pa - ma) ** 2).sum()
            vb = (w2 * (pb - mb) ** 2).sum()
            cov = (w2 * (pa - ma) * (pb - mb)).sum()
            vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma * ma + mb * mb + c1) * (va + vb + c2)))
    m = ssim_map(a, b)
    assert m.shape == (6, 4)
    np.testing.assert_allclose(m.ravel(), vals, rtol=1e-10)
    assert ssim(a, b) == pytest.approx(np.mean(vals), rel=1e-12)
    # colour: the mean of the per-channel SSIMs
    rgb_a = np.stack([a, a[::-1], a[:, ::-1]], axis=2)
    rgb_b = np.stack([b, b[::-1], b[:, ::-1]], axis=2)
    per = [ssim(rgb_a[..., k], rgb_b[..., k]) for k in range(3)]
    assert ssim(rgb_a, rgb_b) == pytest.approx(np.mean(per), rel=1e-12)


def test_gaussian_window():
    w = gaussian_window_1d()
    assert len(w) == 11 and w.sum() == pytest.approx(1.0)
    assert w[5] == w.max() and w[0] == pytest.approx(w[10])
