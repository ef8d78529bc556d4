"""The optional refinement of the merged LOD levels (lod.md 6, `encode --lod-refine`, format 1.11 `lod.refinement`;
issue 31 phase 2): its numpy core (splatstream/lod_refine.py), the encoder's hook, the manifest record, the
validator, `info`, and the CLI's refusals. The optimiser (refine_gpu/, torch + gsplat) is replaced here by a numpy
refiner of the same interface: CI has no torch (tests/test_lod_refine_torch.py runs the real one where it is)."""
from __future__ import annotations

import copy
import json
import math

import msgpack
import numpy as np
import pytest
from conftest import real, run_cli

from splatstream.camera import scene_orbit_views
from splatstream.encode import EncodeOptions, encode_gaussians, encode_in_memory
from splatstream.errors import FormatError, InputError, UsageError
from splatstream.format.layout import morton_order
from splatstream.format.limits import MAX_LOG_SCALE, MIN_LOG_SCALE
from splatstream.format.manifest import LevelRefinement, LodRefinement, manifest_from_dict, parse_manifest
from splatstream.format.manifest.versions import VERSION_1_11
from splatstream.io import read_gaussians
from splatstream.lod import build_tiles, extent_bounds
from splatstream.lod_refine import (
    DISTANCE_RANGE,
    FAR_FILL,
    FAR_MAX_DISTANCE,
    FAR_MIN_PX,
    FAR_SSE_PX,
    UNREFINED,
    VARIANT_FIELDS,
    SharedRefineSettings,
    apply_refined,
    far_level_cameras,
    in_domain,
    kept_candidate,
    level_cuts,
    level_far_range,
    level_outcome,
    orbit_distance_and_focal,
    psnr_of,
    refine_cameras,
    split_merged,
    with_values,
)
from splatstream.scene_decode import decode_scene

# The 1.8 tile table (compact_table off), so the versions pinned here are the refinement record's (1.11); a compact
# table makes any tree 1.12 (format.md 6.2).
TREE = {"max_leaf_splats": 300, "compact_table": False}


@pytest.fixture(scope="module")
def scene():
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    return g.subset(morton_order(g.positions)[:2400])


def leaves_under(tiles, tid: int) -> list[int]:
    t = tiles[tid]
    return [tid] if not t.children else [leaf for c in t.children for leaf in leaves_under(tiles, c)]


def test_level_cuts_cover_every_leaf_once(scene):
    tiles = build_tiles(scene, 300, 2.0, merge="auto")
    cuts = level_cuts(tiles)
    assert [c.level for c in cuts] == sorted({t.level for t in tiles if t.children}) and cuts[0].level == 0
    assert len(cuts) >= 3
    leaves = sorted(t.id for t in tiles if not t.children)
    for cut in cuts:
        assert cut.merged and all(tiles[i].level == cut.level and tiles[i].children for i in cut.merged)
        assert all(tiles[i].level <= cut.level and not tiles[i].children for i in cut.fixed)
        covered = [leaf for i in cut.merged + cut.fixed for leaf in leaves_under(tiles, i)]
        assert sorted(covered) == leaves  # each original exactly once: the level's whole picture


def test_refine_cameras_are_a_rule_of_the_scene_and_not_the_orbit_views(scene):
    up = (0.0, 0.0, 1.0)
    orbit = scene_orbit_views(scene.positions, 4, 64, 64, up=up, elevation_deg=25.0)
    dist = math.dist(orbit[0].eye, orbit[0].target)
    cams = refine_cameras(scene.positions, up, 48, 64, seed=0)
    assert len(cams) == 48 and refine_cameras(scene.positions, up, 48, 64, seed=0) == cams  # deterministic
    d = np.array([math.dist(c.eye, c.target) for c in cams]) / dist
    assert d.min() >= DISTANCE_RANGE[0] - 1e-9 and d.max() <= DISTANCE_RANGE[1] + 1e-9 and d.max() / d.min() > 2.0
    assert all(c.fov_y_deg == orbit[0].fov_y_deg and (c.width, c.height) == (64, 64) for c in cams)
    centre = np.asarray(orbit[0].target)
    assert max(np.linalg.norm(np.asarray(c.target) - centre) for c in cams) < 0.2 * dist
    elev = [math.degrees(math.asin((np.asarray(c.eye) - c.target)[2] / math.dist(c.eye, c.target))) for c in cams]
    assert -20.0 <= min(elev) < 0.0 < 60.0 < max(elev) <= 70.0
    assert min(math.dist(c.eye, b.eye) for c in cams for b in orbit) > 1e-3 * dist  # never a benchmark view
    other = refine_cameras(scene.positions, up, 48, 64, seed=1)  # the validation set: another seed
    assert min(math.dist(a.eye, b.eye) for a in cams for b in other) > 1e-4 * dist
    # phase 1's training set (bench/device/refine_lod_levels.training_cameras, seed 0): the same cameras
    first = cams[0]
    assert first.near == min(0.01, 0.01 * math.dist(first.eye, first.target))


def test_far_cameras_sit_where_a_client_without_a_budget_draws_the_level(scene):
    up = (0.0, 0.0, 1.0)
    tiles = build_tiles(scene, 300, 2.0, merge="auto")
    cuts = level_cuts(tiles)
    orbit = scene_orbit_views(scene.positions, 1, 64, 64, up=up, elevation_deg=25.0)[0]
    dist, focal = orbit_distance_and_focal(scene.positions, up, 64)
    assert dist == pytest.approx(math.dist(orbit.eye, orbit.target))
    assert focal == pytest.approx(32.0 / math.tan(math.radians(orbit.fov_y_deg) / 2.0))
    ranges = [level_far_range(tiles, cut, dist, focal) for cut in cuts]
    assert ranges[0] is not None  # the root: drawn from its own distance on, up to FAR_ROOT_SPAN x that
    for cut, rng in zip(cuts, ranges, strict=True):
        err = float(np.median([tiles[i].geometric_error for i in cut.merged]))
        if rng is None:  # drawn without a budget only within the near cameras' distances
            assert err * focal / FAR_SSE_PX / dist * 1.01 >= DISTANCE_RANGE[1] or cut.level > 0
            continue
        lo, hi = rng
        assert DISTANCE_RANGE[1] <= lo < hi <= FAR_MAX_DISTANCE
        # at the range's near end the level's error projects to FAR_SSE_PX (or the near cameras' end is farther)
        assert err * focal / (lo * dist) == pytest.approx(FAR_SSE_PX) or lo == DISTANCE_RANGE[1]
    # coarser levels are drawn from farther
    lows = [r[0] for r in ranges if r is not None]
    assert lows == sorted(lows, reverse=True)
    rng = ranges[0]
    cams = far_level_cameras(scene.positions, up, 12, 64, 7, rng)
    assert cams == far_level_cameras(scene.positions, up, 12, 64, 7, rng)  # deterministic
    side = min(64, max(FAR_MIN_PX, math.ceil(FAR_FILL * 64 / rng[0])))
    d = np.array([math.dist(c.eye, c.target) for c in cams]) / dist
    assert d.min() >= rng[0] - 1e-9 and d.max() <= rng[1] + 1e-9
    for c in cams:
        assert (c.width, c.height) == (side, side)
        # a crop of a 64 px camera there: the same px per world unit
        assert c.height / (2 * math.tan(math.radians(c.fov_y_deg) / 2)) == pytest.approx(focal)
    # the directions are refine_cameras' rule (the same seed: the same directions, other distances)
    near = refine_cameras(scene.positions, up, 12, 64, seed=7)
    for a, b in zip(cams, near, strict=True):
        da = (np.asarray(a.eye) - a.target) / math.dist(a.eye, a.target)
        db = (np.asarray(b.eye) - b.target) / math.dist(b.eye, b.target)
        assert np.allclose(da, db) and np.allclose(a.target, b.target)


def moved(g, rng, grow: float = 0.4, shift: float = 0.05):
    """`g`'s splats shifted and grown, as a C refinement may leave them."""
    return with_values(g, {"positions": g.positions + rng.normal(0, shift, g.positions.shape),
                           "log_scales": g.log_scales + grow,
                           "opacity_logits": g.opacity_logits - 0.3,
                           "rotations": g.rotations + rng.normal(0, 0.05, g.rotations.shape)})


def test_applying_refined_values_recomputes_the_bounds_up_to_the_root(scene):
    tiles = build_tiles(scene, 300, 2.0, merge="auto")
    rng = np.random.default_rng(0)
    deepest = max(t.level for t in tiles if t.children)
    target = next(t.id for t in tiles if t.level == deepest and t.children)
    refined = {target: moved(tiles[target].gaussians, rng, grow=1.5)}
    out = apply_refined(tiles, refined)
    parent = {c: t.id for t in tiles for c in t.children}
    chain = [target]
    while chain[-1] in parent:
        chain.append(parent[chain[-1]])
    assert chain[-1] == 0
    for t, o in zip(tiles, out, strict=True):
        assert o.geometric_error == t.geometric_error and o.children == t.children  # errors as built
        if t.id not in chain:
            assert o is t  # untouched, leaves above all
            continue
        lo, hi, _, _ = extent_bounds(o.gaussians)
        assert np.all(o.box_min <= lo + 1e-6) and np.all(o.box_max >= hi - 1e-6)
        for k in o.children:
            assert np.all(o.box_min <= out[k].box_min + 1e-6) and np.all(o.box_max >= out[k].box_max - 1e-6)
            assert math.dist(o.sphere_center, out[k].sphere_center) + out[k].sphere_radius <= o.sphere_radius + 1e-5
    assert out[target].gaussians is refined[target]
    # the grown splats left the built box: the tile's and its ancestors' boxes grew with them
    assert np.any(out[target].box_max > tiles[target].box_max + 1e-4)
    assert np.any(out[0].box_max - out[0].box_min > tiles[0].box_max - tiles[0].box_min + 1e-4) or \
        np.all(out[0].box_max >= tiles[0].box_max)
    q = out[target].gaussians.rotations
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    assert np.array_equal(out[target].gaussians.sh_rest, tiles[target].gaussians.sh_rest)


def test_applying_refuses_leaves_other_counts_and_values_outside_the_domain(scene):
    tiles = build_tiles(scene, 300, 2.0, merge="auto")
    leaf = next(t for t in tiles if not t.children)
    with pytest.raises(InputError, match="leaves never change"):
        apply_refined(tiles, {leaf.id: leaf.gaussians})
    merged = next(t for t in tiles if t.children and len(t.gaussians) > 2)
    with pytest.raises(InputError, match="splats of SH degree"):
        apply_refined(tiles, {merged.id: merged.gaussians.subset(np.arange(2))})
    bad = with_values(merged.gaussians, {"log_scales": np.full_like(merged.gaussians.log_scales, np.nan)})
    with pytest.raises(InputError, match="log scale"):
        apply_refined(tiles, {merged.id: bad})


class NumpyRefiner:
    """The LodRefiner interface without torch: every merged tile of level `level` moved and grown (kept "C"),
    every other level kept as built ("none")."""

    def __init__(self, level: int = 1):
        self.level = level
        self.calls = []

    def __call__(self, g, tiles, up, progress):
        self.calls.append((len(g), len(tiles), up))
        rng = np.random.default_rng(1)
        refined = {t.id: moved(t.gaussians, rng) for t in tiles if t.children and t.level == self.level}
        levels = tuple(LevelRefinement(c.level, "C" if c.level == self.level else "none",
                                       (("none", 30.0), ("B", 31.5), ("C", 32.25)))
                       for c in level_cuts(tiles))
        return refined, LodRefinement("render-fit", tuple(VARIANT_FIELDS.items()), 384, 300, 96, 0, 32, 1, levels)


def test_a_refined_encode_records_it_and_keeps_the_full_detail_bit_for_bit(scene, tmp_path):
    plain = parse_manifest(encode_in_memory(scene, EncodeOptions(**TREE)).read_manifest())
    refiner = NumpyRefiner()
    out = tmp_path / "refined"
    m = encode_gaussians(scene, out, EncodeOptions(lod_refiner=refiner, **TREE))
    assert refiner.calls == [(len(scene), len(plain.tiles), plain.up)]
    assert plain.version < VERSION_1_11 and m.version == VERSION_1_11  # only the record needs 1.11
    back = parse_manifest((out / "manifest.msgpack").read_bytes())
    r = back.lod.refinement
    assert r is not None and r.to_dict() == m.lod.refinement.to_dict()
    assert [lv.kept for lv in r.levels][:3] == ["none", "C", "none"] and r.size_px == 384 and r.iterations == 300
    assert dict(r.levels[1].validation_psnr) == {"none": 30.0, "B": 31.5, "C": 32.25}
    assert back.lod.merge == plain.lod.merge == "auto" and back.lod.viewing_scale_px == plain.lod.viewing_scale_px
    for a, b in zip(plain.tiles, back.tiles, strict=True):
        assert (a.id, a.level, a.children, a.splats, a.geometric_error) == (b.id, b.level, b.children, b.splats,
                                                                            b.geometric_error)
        same = {g: e.sha256 for g, e in a.groups.items()} == {g: e.sha256 for g, e in b.groups.items()}
        if not a.children or a.level != 1:
            assert same  # leaves (the full detail) and the levels kept as built: bit for bit
        else:
            assert not same  # the refined level's payloads hold the refined values
        if a.level > 1:
            assert a.box == b.box and a.sphere_radius == b.sphere_radius  # below the refined level: as built
    # the full detail decodes to the same splats as the unrefined encode's
    full = decode_scene(out)
    ref = decode_scene(encode_gaussians(scene, tmp_path / "plain", EncodeOptions(**TREE)) and tmp_path / "plain")
    assert np.array_equal(full.positions, ref.positions) and np.array_equal(full.sh_dc, ref.sh_dc)
    d = msgpack.unpackb((out / "manifest.msgpack").read_bytes(), strict_map_key=False)
    assert d["version"] == [1, 11] and d["lod"]["refinement"]["cameras"] == {
        "training": 96, "training_seed": 0, "validation": 32, "validation_seed": 1}
    info = json.loads(run_cli("info", str(out), "--json").stdout)
    assert info["lod"]["refinement"]["levels"][1]["kept"] == "C"
    text = run_cli("info", str(out)).stdout
    assert "refined    render-fit at 384 px, 300 steps per variant" in text and "1: C" in text
    assert "refined" not in run_cli("info", str(tmp_path / "plain")).stdout


def test_a_tree_of_one_tile_is_not_refined_and_says_so(scene, caplog):
    """No merged level to refine (the scene under --max-leaf-splats): the refiner is not called, the manifest
    records no refinement, and a note says why rather than nothing."""
    refiner = NumpyRefiner()
    with caplog.at_level("INFO", logger="splatstream"):
        m = parse_manifest(encode_in_memory(scene, EncodeOptions(max_leaf_splats=len(scene) + 1,
                                                                 lod_refiner=refiner)).read_manifest())
    assert len(m.tiles) == 1 and m.lod.refinement is None and refiner.calls == []
    assert f"the tree is one tile ({len(scene):,} splats, under --max-leaf-splats), with no merged level; nothing " \
           "refined" in caplog.text


def test_the_partitioned_encoder_refuses_a_refiner_that_does_not_run_by_partitions(scene, tmp_path):
    from splatstream.encode.driver import encode_file
    from splatstream.io import write_gaussians

    src = tmp_path / "s.ply"
    write_gaussians(scene, src)
    # (refine_cpu's does: tests/test_partitioned_refine.py; this one says nothing of it, as refine_gpu's)
    with pytest.raises(UsageError, match="--lod-refine refines in-memory encodes only, not a partitioned one"):
        encode_file(src, tmp_path / "out", workers=1, lod_refiner=NumpyRefiner(), **TREE)
    with pytest.raises(UsageError, match="--no-lod"):
        encode_file(src, tmp_path / "out", lod=False, lod_refiner=NumpyRefiner())


def refined_dict(scene) -> dict:
    raw = encode_in_memory(scene, EncodeOptions(lod_refiner=NumpyRefiner(), **TREE)).read_manifest()
    return msgpack.unpackb(raw, strict_map_key=False)


def test_the_validator_checks_the_refinement_record(scene):
    d = refined_dict(scene)
    d.pop("checksum", None)
    assert manifest_from_dict(copy.deepcopy(d)).lod.refinement is not None
    for change, match in [
        (lambda r: r.update(method=""), "method"),
        (lambda r: r.update(variants={"B": []}), "variants"),
        (lambda r: r["levels"][0].update(kept="D"), "kept"),
        (lambda r: r["levels"][0].update(validation_psnr={"none": float("nan")}), "validation_psnr"),
        (lambda r: r["cameras"].pop("validation_seed"), "validation_seed"),
        (lambda r: r.update(size_px=0), "size_px"),
        (lambda r: r.update(extra=1), "unknown key"),
    ]:
        bad = copy.deepcopy(d)
        change(bad["lod"]["refinement"])
        with pytest.raises(FormatError, match=match):
            manifest_from_dict(bad)
    old = copy.deepcopy(d)
    old["version"] = [1, VERSION_1_11[1] - 1]  # a key of 1.11 in the version before: unknown there
    with pytest.raises(FormatError, match="unknown key.* 'refinement'"):
        manifest_from_dict(old)
    flat = copy.deepcopy(d)
    flat["lod"]["enabled"] = False
    with pytest.raises(FormatError, match="without an LOD tree"):
        manifest_from_dict(flat)


def test_the_refiners_share_the_choice_the_split_and_the_record(scene):
    """What refine_gpu and refine_cpu both use from the core: the kept candidate, a level's values split over its
    merged tiles, the domain clamp, the record's PSNR and the record itself."""
    # the lowest validation MSE wins; the level as built (named first) on a tie or against a fit that is not a number
    assert kept_candidate({UNREFINED: 0.02, "B": 0.01, "C": 0.015}) == "B"
    assert kept_candidate({UNREFINED: 0.01, "A": 0.01}) == UNREFINED
    assert kept_candidate({UNREFINED: 0.01, "A": math.nan}) == UNREFINED
    assert kept_candidate({UNREFINED: math.inf, "B": math.nan, "C": 0.5}) == "C"
    assert (psnr_of(0.01), psnr_of(0.0), psnr_of(math.inf), psnr_of(math.nan)) == (20.0, 99.0, -99.0, -99.0)
    tiles = build_tiles(scene, 300, 2.0, merge="auto")
    cut = level_cuts(tiles)[1]
    assert len(cut.merged) > 1
    n = sum(len(tiles[t].gaussians) for t in cut.merged)
    logits = np.arange(n, dtype=np.float64)
    dc = np.full((n, 3), 1e9)
    refined = split_merged(tiles, cut, {"opacity_logits": logits, "sh_dc": in_domain("sh_dc", dc)})
    assert sorted(refined) == sorted(cut.merged)
    off = 0
    for tid in cut.merged:
        old, new = tiles[tid].gaussians, refined[tid]
        assert np.array_equal(new.opacity_logits, logits[off:off + len(old)].astype(np.float32))
        assert np.array_equal(new.positions, old.positions) and np.array_equal(new.sh_rest, old.sh_rest)
        off += len(old)
    assert apply_refined(tiles, refined)  # the clamped colour is inside the format's domain
    assert np.array_equal(in_domain("log_scales", np.array([-1e3, 0.0, 1e3])), [MIN_LOG_SCALE, 0.0, MAX_LOG_SCALE])
    assert np.array_equal(in_domain("opacity_logits", np.array([-1e3, 1e3])), [-1e3, 1e3])  # any logit is valid
    logs: list[str] = []
    level, psnr = level_outcome(cut, {UNREFINED: 0.01, "A": 0.001}, "A", n, 1.25, logs.append)
    assert level == LevelRefinement(cut.level, "A", ((UNREFINED, 20.0), ("A", 30.0))) and psnr == {UNREFINED: 20.0,
                                                                                                 "A": 30.0}
    assert logs == [f"level {cut.level} ({n:,} merged splats): validation PSNR none 20.00, A 30.00 dB; kept A "
                    "(1.2 s)"]
    s = SharedRefineSettings(iterations=7, size=32, training_cameras=3, validation_cameras=2, training_seed=5,
                             validation_seed=6)
    train, valid = s.cameras(scene.positions, (0.0, 1.0, 0.0))
    assert train == refine_cameras(scene.positions, (0.0, 1.0, 0.0), 3, 32, 5)
    assert valid == refine_cameras(scene.positions, (0.0, 1.0, 0.0), 2, 32, 6)
    assert s.record(("B", "C"), [level]) == LodRefinement("render-fit", (("B", VARIANT_FIELDS["B"]),
                                                                          ("C", VARIANT_FIELDS["C"])),
                                                          32, 7, 3, 5, 2, 6, (level,))


def test_cli_refusals_come_before_the_scene_is_read(tmp_path):
    missing_input = str(tmp_path / "no-such-scene.ply")
    for extra, message in [(["--workers", "2"], "not with --workers or --scheduler"),
                           (["--no-lod"], "not with --no-lod"),
                           (["--lod-refine-iters", "0"], "--lod-refine-iters 0: expected at least 1 step"),
                           (["--lod-refine-size", "20000"], "--lod-refine-size 20000: expected 16 to 16384 px")]:
        r = run_cli("encode", missing_input, str(tmp_path / "out"), "--lod-refine", *extra)
        assert r.returncode == 2 and message in r.stderr and r.stderr.count("\n") == 1, r.stderr
    # the refinement's settings alone would be ignored: refused, naming the option they set
    for extra in (["--lod-refine-iters", "30"], ["--lod-refine-size", "64"]):
        r = run_cli("encode", missing_input, str(tmp_path / "out"), *extra)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert "give them with --lod-refine (gpu or cpu)" in r.stderr and "no-such-scene" not in r.stderr
    from refine_gpu.levels import missing

    lack = missing()
    if lack is None:
        pytest.skip("torch, gsplat and a CUDA device are all here: the missing-extra message cannot show")
    r = run_cli("encode", missing_input, str(tmp_path / "out"), "--lod-refine")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert f"--lod-refine needs torch, gsplat and a CUDA GPU: {lack}" in r.stderr
    assert "pip install 'splatstream[refine]'" in r.stderr and "no-such-scene" not in r.stderr
    assert not (tmp_path / "out").exists()
