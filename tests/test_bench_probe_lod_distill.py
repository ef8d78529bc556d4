"""bench/probe_lod_distill.py (issue 31, distill31): the pairing of a re-ordered, slightly moved tile back to its
built splats, the levels from the leaves, and the cell correction applied to each splat's sorted axes."""
from __future__ import annotations

import numpy as np
from conftest import load_bench, lod_probe_scene

from splatstream.gaussians import Gaussians

P = load_bench("probe_lod_distill")


def scene(n: int = 3000, seed: int = 5) -> Gaussians:
    return lod_probe_scene(n, seed, random_sh=True)


def test_pairing_recovers_a_shuffled_moved_tile():
    b = scene()
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(b))
    r = b.subset(perm)
    r.positions = r.positions + 0.1 * np.exp(r.log_scales.mean(1, keepdims=True)) * rng.normal(size=(len(b), 3))
    r.log_scales = r.log_scales - 0.05
    p = P.pair(b, r)
    ok = p >= 0
    assert ok.mean() > 0.99
    assert np.array_equal(p[ok], perm[ok])  # every pair kept is the right one


def test_heights_count_levels_from_the_leaves():
    tiles = P.rl.default_tree(scene(6000), max_leaf=500)
    h = P.heights(tiles)
    assert all(h[t.id] == 0 for t in tiles if not t.children)
    assert all(h[t.id] == 1 + max(h[c] for c in t.children) for t in tiles if t.children)
    assert h[0] == max(h) >= 3


def test_cell_correction_goes_to_the_sorted_axes():
    tiles = P.rl.default_tree(scene(6000), max_leaf=500)
    cells = set()
    for t in tiles:
        if t.children:
            cells |= {int(c) for c in P.cell_of(P.features(t.gaussians, t, P.heights(tiles)[t.id]))}
    model = {c: np.array([-0.2, 0.0, 0.1, 0.5, 0.0, 0.0, 0.0]) for c in cells}
    out = P.apply_cells(tiles, model)
    t = next(t for t in tiles if t.children)
    before, after = np.sort(t.gaussians.log_scales, 1), np.sort(out[t.id].gaussians.log_scales, 1)
    d = after - before
    np.testing.assert_allclose(d[:, 0], -0.2, atol=1e-5)  # the smallest axis shrinks, the largest grows
    np.testing.assert_allclose(d[:, 2], 0.1, atol=1e-5)
    op = np.clip(t.gaussians.opacities.astype(np.float64), 1e-6, P.CEIL)
    np.testing.assert_allclose(out[t.id].gaussians.opacity_logits, np.log(op / (1 - op)) + 0.5, atol=1e-4)
    leaf = next(t for t in tiles if not t.children)
    assert out[leaf.id] is leaf  # leaves untouched
    assert P.apply_cells(tiles, model, ("opacity",))[t.id].gaussians.log_scales.tolist() == \
        t.gaussians.log_scales.tolist()
