"""The parts of bench/lod_vs_peers.py (issue 31) that need neither GL nor the peer tools: budgets, the decoding of
Spark's ExtSplats words and the per-view cut of a Spark LoD tree."""
from __future__ import annotations

import math
import pathlib

import numpy as np
from conftest import load_bench

from splatstream.camera import Camera


def load():
    return load_bench("lod_vs_peers")


L = load()


def encode_ext_rgb(rgb) -> int:
    """rust/spark-lib/src/splat_encode.rs encode_ext_rgb, ported."""
    m = max(abs(v) for v in rgb)
    base = int(round(min(max(math.floor(math.log2(m)) + 15.0, 0.0), 31.0))) if m > 0 else 0
    div = 2.0 ** (base - 15) / 255.0
    u = [min(max(round(abs(v) / div), 0), 255) for v in rgb]
    signs = sum(1 << k for k, v in enumerate(rgb) if v < 0)
    return u[0] | (u[1] << 8) | (u[2] << 16) | (((base << 3) | signs) << 24)


def test_budget_counts_fractions_and_counts():
    assert L.budget_counts(45624, [0.02, 0.06, 0.25, 0.5]) == [912, 2737, 11406, 22812]
    assert L.budget_counts(1000, [3000.0, 1.0]) == [3000, 1000]


def test_ext_rgb_decodes_spark_shared_exponent_words():
    vals = [(0.5, -0.25, 0.125), (-1.5, 0.0, 0.75), (0.01, 0.02, -0.03)]
    words = np.array([[encode_ext_rgb(v) for v in vals]], np.uint32)
    got = L._ext_rgb(words)[0]
    for v, g in zip(vals, got, strict=True):
        m = max(abs(x) for x in v)
        top = 2.0 ** math.floor(math.log2(m))  # the encoder keeps at most 2^floor(log2 max): Spark clips the rest
        want = [math.copysign(min(abs(x), top), x) for x in v]
        assert np.allclose(g, want, atol=top / 255 * 0.51)


def tree(n_leaves_per_child: int = 4) -> dict:
    """Root 0 -> children 1, 2 -> each n leaves; every node of size 1, spread along x."""
    kids = [1, 2]
    leaves = list(range(3, 3 + 2 * n_leaves_per_child))
    n = 3 + len(leaves)
    cc = np.zeros(n, np.int64)
    cs = np.zeros(n, np.int64)
    cc[0], cs[0] = 2, 1
    for k, c in enumerate(kids):
        cc[c], cs[c] = n_leaves_per_child, 3 + k * n_leaves_per_child
    centers = np.zeros((n, 3), np.float32)
    centers[:, 0] = np.linspace(-1, 1, n)
    return {"lod_center": centers, "size": np.ones(n, np.float32) * np.array([4.0, 2.0, 2.0] + [1.0] * len(leaves)),
            "child_count": cc, "child_start": cs}


def cam() -> Camera:
    return Camera((0.0, -10.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 50.0, 64, 64)


def test_spark_cut_stays_within_the_budget_and_covers_the_tree():
    t = tree()
    assert sorted(L.spark_cut(t, cam(), 1)) == [0]
    assert sorted(L.spark_cut(t, cam(), 2)) == [1, 2]
    five = L.spark_cut(t, cam(), 5)  # one child refined (2 - 1 + 4 = 5), the other kept
    assert len(five) == 5 and len(set(five) & {1, 2}) == 1
    assert sorted(L.spark_cut(t, cam(), 100)) == list(range(3, 11))


def test_spark_gaussians_inflate_and_clamp():
    n = 3
    t = {"positions": np.zeros((n, 3), np.float32), "quat_wxyz": np.tile([1.0, 0, 0, 0], (n, 1)),
         "ln_scales": np.zeros((n, 3), np.float32), "opacity": np.array([0.5, 1.0, 2.0], np.float32),
         "rgb": np.full((n, 3), 0.5, np.float32), "sh_rest": np.zeros((n, 0, 3), np.float32)}
    idx = np.arange(n)
    inflated = L.spark_gaussians(t, idx, "inflate")
    clamped = L.spark_gaussians(t, idx, "clamp")
    sig = 1 / (1 + np.exp(-inflated.opacity_logits))
    assert np.allclose(sig, [0.5, 1.0, 1.0], atol=1e-5)
    # a = 2 encodes 5: scales grow by exp((25 - 1) / e)^(1/3)
    assert np.allclose(inflated.log_scales[2], 24 / math.e / 3, atol=1e-5)
    assert np.allclose(inflated.log_scales[:2], 0) and np.allclose(clamped.log_scales, 0)
    assert np.allclose(clamped.sh_dc, 0)


def test_unique_budgets_measure_each_count_once():
    # 0.5 and 250000 of 500,000 splats name the same N: measured once (the chained peer level of N is not rebuilt
    # from itself), the first budget kept for its label
    budgets, counts = L.unique_budgets(500000, [0.02, 0.5, 250000.0, 125000.0, 0.25, 3000.0])
    assert counts == [10000, 250000, 125000, 3000]
    assert budgets == [0.02, 0.5, 125000.0, 3000.0]
    assert [L.budget_label(b, n) for b, n in zip(budgets, counts, strict=True)] == \
        ["10,000 (2 %)", "250,000 (50 %)", "125,000", "3,000"]


def test_cameras_an_ulp_apart_are_the_same_views():
    """cpurefine: statue-angel's stored peer rows were dropped by `--peers-from` because the orbit's eyes moved by an
    ulp (camera.look_at_near_far); such cameras are the same views, a real difference or a missing field is not."""
    stored = [{"eye": [0.35712093311489490, -2.5069121102696568, 1.0], "near": 0.1, "fov_y_deg": 50.0}]
    today = [{"eye": [0.35712093311489485, -2.506912110269657, 1.0], "near": 0.1, "fov_y_deg": 50.0}]
    assert stored != today
    assert L.same_cameras(stored, today)
    assert not L.same_cameras([{"eye": [0.0, 1.0]}], [{"eye": [0.0, 1.0 + 1e-9]}])
    assert not L.same_cameras([{"eye": [0.0, 1.0]}], [{"eye": [0.0, 1.0], "near": 0.1}])
    assert not L.same_cameras(stored, stored * 2)
    assert not L.same_cameras(None, today)


def test_held_out_scenes_are_named_only_and_read_as_the_user_would(tmp_path):
    """The held-out scenes (not in ../shared/data) run only when named; the SOG version 1 logo is its meta.json,
    whose input bytes count the WebP planes beside it (the fixture here: 300 splats of it)."""
    from splatstream.evaluate import path_size

    assert {n for n, s in L.SCENES.items() if s.outside} == {"playbot", "playcanvas-logo"}
    assert L.SCENES["playcanvas-logo"].source == "playcanvas-logo/meta.json"
    fixture = pathlib.Path(__file__).parent / "fixtures" / "foreign" / "logo_v1_sub300"
    assert path_size(str(fixture / "meta.json")) == sum(p.stat().st_size for p in fixture.iterdir()) > 5000
