"""bench/probe_lod_refine.py and bench/device/refine_lod_levels.py (issue 31, merged levels refined against the
originals): the tree rule, the level cuts, the training cameras, and the refined file -> tree replacement, in numpy.
The torch parts (the refinement itself) run only where torch is installed (CI has none: a bench probe's GPU side)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import load_bench, lod_probe_scene

from splatstream.gaussians import Gaussians

P = load_bench("probe_lod_refine")
R = P.rl  # bench/device/refine_lod_levels.py, as the replay imports it


def scene(n: int = 3000, seed: int = 3) -> Gaussians:
    return lod_probe_scene(n, seed, random_sh=False)


def test_tree_rule_is_the_encoders_default():
    from splatstream.encode.options import EncodeOptions

    o = EncodeOptions()
    assert (R.MAX_LEAF_SPLATS, R.REDUCTION, R.LOD_MERGE) == (o.max_leaf_splats, o.reduction,
                                                            o.resolved_lod_merge(in_memory=True))


def leaves_under(tiles, tid: int) -> list[int]:
    t = tiles[tid]
    return [tid] if not t.children else [leaf for c in t.children for leaf in leaves_under(tiles, c)]


def test_level_cuts_cover_every_leaf_once():
    tiles = R.default_tree(scene(), 200)
    cuts = R.level_cuts(tiles)
    leaves = sorted(t.id for t in tiles if not t.children)
    assert sorted(cuts) == sorted({t.level for t in tiles if t.children})
    assert len(cuts) >= 3
    for d, (merged, fixed) in cuts.items():
        assert merged and all(tiles[i].level == d and tiles[i].children for i in merged)
        assert all(tiles[i].level <= d and not tiles[i].children for i in fixed)
        covered = [leaf for i in merged + fixed for leaf in leaves_under(tiles, i)]
        assert sorted(covered) == leaves  # each original exactly once: the level's whole picture


def test_training_cameras_are_not_the_benchmark_views():
    g = scene()
    up = (0.0, 0.0, 1.0)
    bench = P.lvp.view_cameras(g.positions, up, 4, 64)
    dist = math.dist(bench[0].eye, bench[0].target)
    cams = R.training_cameras(g.positions, up, 48, 64, seed=1)
    assert len(cams) == 48
    assert R.training_cameras(g.positions, up, 48, 64, seed=1) == cams  # deterministic
    d = np.array([math.dist(c.eye, c.target) for c in cams]) / dist
    assert d.min() >= 0.6 - 1e-9 and d.max() <= 1.6 + 1e-9 and d.max() / d.min() > 2.0  # spread over the range
    assert all(c.fov_y_deg == bench[0].fov_y_deg and (c.width, c.height) == (64, 64) for c in cams)
    centre = np.asarray(bench[0].target)
    assert max(np.linalg.norm(np.asarray(c.target) - centre) for c in cams) < 0.2 * dist
    elev = [math.degrees(math.asin((np.asarray(c.eye) - c.target)[2] / math.dist(c.eye, c.target))) for c in cams]
    assert -20.0 <= min(elev) < 0.0 < 60.0 < max(elev) <= 70.0
    assert min(math.dist(c.eye, b.eye) for c in cams for b in bench) > 1e-3 * dist


def test_refined_file_round_trip_into_the_tree(tmp_path):
    g = scene()
    tiles = R.default_tree(g, 200)
    digest = R.tree_digest(tiles, 200)
    merged = [t.id for t in tiles if t.children][:3]
    rng = np.random.default_rng(0)
    refined = {i: {"opacity_logits": rng.normal(0, 0.3, len(tiles[i].gaussians)).astype(np.float32),
                   "sh_dc": rng.normal(0, 0.1, (len(tiles[i].gaussians), 3)).astype(np.float32),
                   "rotations": rng.normal(0, 0.01, (len(tiles[i].gaussians), 4)).astype(np.float32)}
               for i in merged}
    members = R.pack_scene("s", digest, refined, {"variant": "C"})
    paths = R.write_parts(str(tmp_path), "C", {"s": members})
    assert [p.rsplit("/", 1)[1] for p in paths] == ["refine_C_0.npz"]
    theirs, back, info = R.read_refined(paths, "s")
    assert theirs == digest and info == {"variant": "C"} and sorted(back) == merged
    R.check_digest(R.tree_digest(R.default_tree(g, 200), 200), theirs)
    out = R.replace_refined(tiles, back)
    for t in tiles:
        if t.id not in refined:
            assert out[t.id] is t
            continue
        a, b = t.gaussians, out[t.id].gaussians
        want = a.opacity_logits + refined[t.id]["opacity_logits"].astype(np.float16).astype(np.float32)
        np.testing.assert_allclose(b.opacity_logits, want, rtol=0, atol=1e-6)
        np.testing.assert_allclose(b.sh_dc - a.sh_dc, refined[t.id]["sh_dc"], atol=1e-3)  # float16 deltas
        np.testing.assert_allclose(np.linalg.norm(b.rotations, axis=1), 1.0, atol=1e-6)
        assert np.array_equal(b.positions, a.positions) and np.array_equal(b.log_scales, a.log_scales)
        assert np.array_equal(b.sh_rest, a.sh_rest)
    with pytest.raises(SystemExit, match="digest mismatch"):
        R.check_digest(R.tree_digest(R.default_tree(scene(2900), 200), 200), theirs)


def test_dense_torch_render_matches_the_reference():
    torch = pytest.importorskip("torch")
    pytest.importorskip("gsplat")
    from splatstream.camera import Camera
    from splatstream.render_ref import render

    g = scene(400)
    g = Gaussians(g.positions, g.rotations, g.log_scales - 0.5, g.opacity_logits, g.sh_dc,
                  np.random.default_rng(1).normal(0, 0.2, (400, 3, 3)).astype(np.float32))
    cam = Camera((3.0, -2.0, 1.5), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 50.0, 40, 32, 0.01, 100.0)
    ref = np.clip(render(g, cam), 0, 1)
    for backend in ("dense", "gsplat-torch"):
        img = R.Renderer(torch, "cpu", 1, backend)(R.to_params(torch, g, "cpu"), [cam])[0].numpy()
        assert R.psnr_of(float(np.mean((np.clip(img, 0, 1) - ref) ** 2))) > 50.0, backend
