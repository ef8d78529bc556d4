"""Tile steps (format.md 4.3.1, format/steps.py): a ranged plane quantised on one step per tile by widening chunk
ranges; the preset medium-low-12bit that uses them. The shader decode of such a scene: test_gl_decode.py."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import real, run_cli

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.encode.jobs import splat_order
from splatstream.errors import UsageError
from splatstream.format.codec import decode_plane, encode_plane
from splatstream.format.layout import CHUNK_SIZE, chunk_texel_index
from splatstream.format.planes import BASE_PLANES, band_plane
from splatstream.format.presets import PRESET_SH_CODEBOOK, PRESET_STEPS, PRESETS, preset_steps, step_attribute
from splatstream.format.steps import (
    TileStep,
    round_towards_zero,
    shared_levels,
    splat_sizes,
    step_sizes,
    widened_max,
    zero_on_grid,
)
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene

POSITION, SCALE = BASE_PLANES[0], BASE_PLANES[2]


def test_widened_max_gives_every_chunk_the_median_chunks_step():
    lo = np.zeros((4, 3), np.float32)
    hi = np.array([[1, 0.5, 0], [2, 1, 1], [4, 0, 0], [1000, 1, 1]], np.float32)
    step = TileStep((100.0,) * 3, shared=3)
    # largest extents 1, 2, 4, 1000: median 3, so one step of 0.03 on every axis
    np.testing.assert_allclose(step_sizes(hi.astype(np.float64), step), [0.03] * 3)
    wide = widened_max(lo, hi, "norm8x4", step, "<f4", (-1e18, 1e18))
    # n = e / 0.03 steps (at least 1, at most 255): max = e * 255 / n = 255 * 0.03 = 7.65, except where e / 0.03 > 255
    # (the 1000 chunk keeps its tight range, 255 steps of 1000/255) or e = 0 (max = min = 0: one step, nothing widened)
    np.testing.assert_allclose(wide, [[7.65, 7.65, 0], [7.65, 7.65, 7.65], [7.65, 0, 0], [1000, 7.65, 7.65]],
                               rtol=1e-6)
    assert np.all(wide >= hi) and wide.dtype == np.float32
    per_axis = widened_max(lo, hi, "norm8x4", TileStep((100.0, 100.0, 100.0), shared=1), "<f4", (-1e18, 1e18))
    # per axis: median extents 3, 0.75, 0.5 over 100 levels; chunk 1 (extents 2, 1, 1) gets 255 of those steps
    np.testing.assert_allclose(per_axis[1], [255 * 0.03, 255 * 0.0075, 255 * 0.005], rtol=1e-6)


def test_f16_ranges_round_up_and_stay_inside_the_limits():
    lo = np.array([[-5.0, 30.0, 39.0]], np.float16)
    hi = np.array([[-4.9, 31.0, 39.9]], np.float16)
    wide = widened_max(lo, hi, "norm8x4", TileStep((10.0,) * 3, shared=3), "<f2", (-80.0, 40.0))
    assert wide.dtype == np.float16
    # one chunk whose largest extent is 1: one step of 0.1 on all three, so max = lo + 255 * 0.1 where e / 0.1 >= 1
    assert float(wide[0, 0]) == 20.5  # e = 0.1016 (f16 -4.9 rounds to -4.898): one step, max = lo + 255 e / 1.016
    # 30 + 25.5 and 39 + 25.5 are above the log-scale limit 40: kept tight
    assert wide[0, 1:].tolist() == hi[0, 1:].tolist()
    with pytest.raises(UsageError, match="integer texel format"):
        widened_max(lo, hi, "f16x4", TileStep((10.0,) * 3, shared=3), "<f2", (-80.0, 40.0))
    with pytest.raises(UsageError, match="tile step levels"):
        widened_max(lo, hi, "norm8x4", TileStep((10.0,) * 2, shared=2), "<f2", (-80.0, 40.0))


@pytest.mark.parametrize("fmt", ["norm16x4", "norm8x4"])
def test_plane_on_a_tile_step_decodes_within_half_a_step_and_stores_small_codes(fmt):
    rng = np.random.default_rng(3)
    spread = np.repeat([0.5, 1.0, 2.0, 3.0, 4000.0], CHUNK_SIZE)[:, None]
    values = (rng.random((len(spread), 1, 3)) * spread[:, None]).astype(np.float32) + 10.0
    levels = 200.0
    plane = encode_plane(values, POSITION, fmt, step=TileStep((levels,) * 3, shared=3))
    chunk_lo = values.reshape(5, CHUNK_SIZE, 3).min(axis=1)
    extent = values.reshape(5, CHUNK_SIZE, 3).max(axis=1) - chunk_lo
    size = np.median(extent.max(axis=1)) / levels  # about 2 / 200
    back = decode_plane(plane, len(values))
    err = np.abs(back - values)[:, 0].reshape(5, CHUNK_SIZE, 3).max(axis=1)
    L = 65535 if fmt == "norm16x4" else 255
    # every chunk at the tile's step (the widest one at its format's finest, e / L), plus f32 rounding of the range
    bound = np.maximum(size, extent / L) / 2 * (1 + 1e-3) + 1e-5
    assert np.all(err <= bound), (err, bound)
    assert err[:4].max() > size / 4  # a real grid of that step, not the format's finer one
    texel_of_splat = chunk_texel_index(5, plane.width)
    words = np.frombuffer(plane.layers[0], "<u2" if fmt == "norm16x4" else np.uint8).reshape(-1, 4)[texel_of_splat]
    assert words[:, :3].max() <= L
    tight = encode_plane(values, POSITION, fmt)
    assert np.frombuffer(tight.layers[0], words.dtype).max() == L  # per-chunk grids use every level
    assert words[: 4 * CHUNK_SIZE, :3].max() <= np.ceil(4 / size) + 1  # the tile step's codes: about e / size


def test_a_size_relative_step_is_the_median_splat_size_over_k_and_decodes_within_half_of_it():
    """TileStep.per_size (issue 32): the shared step is the tile's median splat size (largest axis) / K, so the
    median chunk gets K x its extent / that size levels, clamped to [size_levels_min, levels[0]]; splats twice as
    large give a step twice as coarse; without sizes the step is levels[0]'s."""
    log_scales = np.log(np.array([[0.01, 0.02, 0.04], [0.05, 0.01, 0.01], [0.03, 0.03, 0.03]]))
    np.testing.assert_allclose(splat_sizes(log_scales), [0.04, 0.05, 0.03])
    step = TileStep((4095.0,) * 3, shared=3, per_size=80.0, size_levels_min=100.0)
    assert shared_levels(2.0, step, 0.04) == 80.0 * 2.0 / 0.04  # 4000
    assert shared_levels(2.0, step, 0.01) == 4095.0 and shared_levels(2.0, step, 10.0) == 100.0  # clamped
    assert shared_levels(2.0, step, None) == 4095.0 and shared_levels(2.0, TileStep((9.0,) * 3, shared=3), 1.0) == 9.0
    extent = np.array([[1.0, 0.5, 0.2], [2.0, 1.0, 1.0], [3.0, 0.1, 0.1]])
    np.testing.assert_allclose(step_sizes(extent, step, 0.04), [0.04 / 80] * 3)  # median largest extent 2
    rng = np.random.default_rng(5)
    values = (rng.random((4 * CHUNK_SIZE, 1, 3)) * [[[1.0, 1.5, 2.0]]]).astype(np.float32)
    sizes = np.exp(rng.normal(np.log(0.05), 0.5, len(values)))  # about 3,200 and 1,600 levels
    errs = {}
    for scale in (1.0, 2.0):
        s = float(np.median(sizes * scale)) / 80.0
        plane = encode_plane(values, POSITION, "norm16x4", step=step, sizes=sizes * scale)
        err = np.abs(decode_plane(plane, len(values)) - values).max()
        assert err <= s / 2 * (1 + 1e-3) + 1e-6 and err > s / 4, (scale, err, s)
        errs[scale] = err
    assert 1.6 < errs[2.0] / errs[1.0] < 2.4
    # no sizes given: the step of levels[0] (4095 levels of the median chunk), finer here
    plane = encode_plane(values, POSITION, "norm16x4", step=step)
    assert np.abs(decode_plane(plane, len(values)) - values).max() < errs[1.0]


def test_preset_steps_follow_the_preset_and_are_dropped_with_an_override():
    assert PRESETS["medium-low-12bit"]["position"] == "norm16x4"
    assert set(preset_steps("medium-low-12bit")) == {"position", "scale", "color"}
    assert preset_steps("medium-low-12bit", {"position": "norm11"}).keys() == {"scale", "color"}
    assert preset_steps("medium-low-12bit", {"position": "norm16x4"}).keys() == {"position", "scale", "color"}
    assert preset_steps("medium") == {"scale": TileStep((1023.0,) * 3, shared=3)}
    assert preset_steps("medium", {"scale": "norm565"}) == {}
    assert PRESET_STEPS["medium-low-12bit"]["color"].levels == (255.0, 255.0, 255.0, 55.0)
    # every preset with tile steps puts them on integer formats of the planes they name
    for preset, steps in PRESET_STEPS.items():
        for attr, step in steps.items():
            step.check(PRESETS[preset][step_attribute(attr)], 4 if attr == "color" else 3)
    assert PRESETS["low-plus-9bit"]["position"] == "norm9x3" and PRESET_STEPS["low-plus-9bit"]["position"].shared == 3


def test_low_plus_9bit_scene_is_1_3_with_a_codebook_and_its_positions_on_the_step(tmp_path):
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(1800))
    m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="low-plus-9bit", lod=False))
    assert m.version == (1, 3) and m.formats["position"] == "norm9x3" and m.uses_codebook
    dec = decode_scene(tmp_path / "s")
    dist = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2)
    err = dist.min(axis=1).max()
    assert 0 < err <= float((g.positions.max(axis=0) - g.positions.min(axis=0)).max()) / 400


@pytest.fixture(scope="module")
def scene_12bit(tmp_path_factory):
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(1800))
    out = tmp_path_factory.mktemp("ml12") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit", lod=False))
    return g, out, m


def test_preset_scene_decodes_on_its_steps(scene_12bit):
    g, out, m = scene_12bit
    # 1.3 for its norm16x4 positions; 1.14 since cube8x4all32, as its rotations measure closer in cube8x4 here
    # (a PLY's; presets.PRESET_ROTATION_CHOICES)
    assert m.version == (1, 14) and m.formats["rotation"] == "cube8x4"
    assert m.formats["position"] == "norm16x4" and m.preset == "medium-low-12bit"
    dec = decode_scene(out)
    dist = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2)
    nearest = dist.argmin(axis=1)
    err = np.abs(dec.positions - g.positions[nearest]).max()
    lo, hi = g.positions.min(axis=0), g.positions.max(axis=0)
    # a chunk of 256 of 1800 splats spans less than the scene: the step (median chunk / 4095) is under the scene's
    # extent / 4095, and no worse than 1/8 of norm9x3's grid over the scene
    assert 0 < err <= float((hi - lo).max()) / 4095
    # scales on the 180-level step of the median chunk: within a step of the input, and on a grid coarser than 8 bits
    # (each splat's three scales sorted: the cube gauge permutes a splat's axes, format.md 4.5)
    err_scale = np.abs(np.sort(dec.log_scales, axis=1) - np.sort(g.log_scales[nearest], axis=1)).max()
    assert 0 < err_scale <= float(g.log_scales.max() - g.log_scales.min()) / 180
    r = run_cli("info", out)
    assert r.returncode == 0 and "medium-low-12bit" in r.stdout


def test_medium_12bit_is_medium_with_positions_on_one_12_bit_tile_step(tmp_path):
    """medium-12bit (issue 32): medium's rotations, scales, colour and SH with medium-low-12bit's positions (norm16x4
    on one step per tile, the median chunk's extent / 4095): a position error within that step (norm11's per-chunk
    grid of the same scene is coarser: 2047 / 1023 levels over each chunk's own extent), nothing else changed."""
    assert PRESETS["medium-12bit"] == {**PRESETS["medium"], "position": "norm16x4"}
    assert preset_steps("medium-12bit") == {"position": TileStep((4095.0,) * 3, shared=3)}
    assert "medium-12bit" not in PRESET_SH_CODEBOOK and "medium" not in PRESET_SH_CODEBOOK
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(1800))
    errs, formats = {}, {}
    for preset in ("medium-12bit", "medium"):
        m = encode_gaussians(g, tmp_path / preset, EncodeOptions(preset=preset, lod=False))
        dec = decode_scene(tmp_path / preset)
        dist = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2)
        errs[preset] = np.abs(dec.positions - g.positions[dist.argmin(axis=1)]).max()
        formats[preset] = {a: f for a, f in m.formats.items() if a != "position"}
        if preset == "medium-12bit":
            assert m.version == (1, 3) and m.formats["position"] == "norm16x4" and m.preset == "medium-12bit"
    assert formats["medium-12bit"] == formats["medium"]
    lo, hi = g.positions.min(axis=0), g.positions.max(axis=0)
    assert 0 < errs["medium-12bit"] <= float((hi - lo).max()) / 4095
    assert errs["medium-12bit"] < errs["medium"] / 2, errs  # measured 3.2e-5 against 9.5e-5 (1,800 splats)


COLOR = BASE_PLANES[3]


@pytest.mark.parametrize("fmt, exact", [("norm8x4", True), ("norm16x4", True), ("f16x4", False), ("bc7", False)])
def test_opacities_on_the_8_bit_grid_keep_it(fmt, exact):
    """An input's 8-bit opacities (k / 255, through a float32 logit and back as the readers give them) quantise to
    their own codes: chunk ranges [0, 1] for opacity, so they decode to k / 255 where per-chunk ranges put a second
    grid over the first; other opacities keep their tight ranges."""
    from splatstream.format.steps import keep_opacity_grid, opacity_on_grid

    if fmt == "bc7":
        pytest.importorskip("etcpak")
    rng = np.random.default_rng(7)
    n = 3 * CHUNK_SIZE + 40
    k = rng.integers(1, 256, n)
    logits = np.log(k / 255 / (1 - k / 255 + 1e-12)).astype(np.float32)
    opacity = (1 / (1 + np.exp(-logits.astype(np.float64)))).astype(np.float32)
    assert opacity_on_grid(opacity) and not opacity_on_grid(opacity + np.float32(4e-4))
    assert not opacity_on_grid(rng.random(n))
    values = np.concatenate([rng.normal(0, 1, (n, 3)).astype(np.float32), opacity[:, None]], axis=1)[:, None, :]
    plane = encode_plane(values, COLOR, fmt)
    back = decode_plane(plane, n)[:, 0, 3]
    ranges = plane.ranges[:, :, 0, 3].astype(np.float32)
    if exact:
        assert np.all(ranges[:, 0] == 0) and np.all(ranges[:, 1] == 1)
        assert np.abs(back * 255 - k).max() < 1e-3
    else:
        assert not np.all(ranges[:, 0] == 0)
    per_chunk = encode_plane(values * np.float32([1, 1, 1, 0.999]), COLOR, fmt)  # off the grid: tight ranges
    assert float(per_chunk.ranges[:, 0, 0, 3].astype(np.float32).min()) > 0
    lo, hi = np.zeros((2, 4), np.float16), np.ones((2, 4), np.float16)
    assert keep_opacity_grid(lo, hi, "norm565", 3) is False  # no opacity component


def test_importance_scales_each_chunks_step_and_stays_within_half_a_step():
    """Issue 32: SH bands on importance-scaled steps: a chunk of w times the median importance gets a step
    (1 / w) ** exponent times the tile's (clamped to 64x either way); the decode error stays within half of it."""
    from splatstream.format.planes import band_plane
    from splatstream.format.steps import IMPORTANCE_RANGE, importance_factors

    # median of the positive importances: 1
    np.testing.assert_allclose(importance_factors(np.array([1.0, 4.0, 0.25, 1.0, 1e9, 0.0, 1.0]), 0.5),
                               [1.0, 0.5, 2.0, 1.0, 1 / IMPORTANCE_RANGE, IMPORTANCE_RANGE, 1.0])
    np.testing.assert_allclose(importance_factors(np.array([1.0, 4.0]), 0.0), [1.0, 1.0])
    rng = np.random.default_rng(5)
    chunks = 5
    n = chunks * CHUNK_SIZE - 17  # a partial last chunk
    values = rng.normal(0, 0.2, (n, 3, 3)).astype(np.float32)
    importance = np.repeat([1.0, 1.0, 16.0, 1 / 16, 1.0], CHUNK_SIZE)[:n]
    step = TileStep((8.0,) * 3, shared=1, importance=0.5)
    plane = encode_plane(values, band_plane(1), "norm565", step=step, importance=importance)
    plain = encode_plane(values, band_plane(1), "norm565", step=TileStep((8.0,) * 3, shared=1))
    back, back_plain = decode_plane(plane, n), decode_plane(plain, n)
    pad = np.concatenate([np.abs(back - values), np.zeros((chunks * CHUNK_SIZE - n, 3, 3))])
    err = pad.reshape(chunks, CHUNK_SIZE, 3, 3).max(axis=(1, 3))  # (chunks, coefficients)
    pad = np.concatenate([np.abs(back_plain - values), np.zeros((chunks * CHUNK_SIZE - n, 3, 3))])
    err_plain = pad.reshape(chunks, CHUNK_SIZE, 3, 3).max(axis=(1, 3))
    extent = np.ptp(np.concatenate([values, np.zeros((chunks * CHUNK_SIZE - n, 3, 3))]).reshape(
        chunks, CHUNK_SIZE, 3, 3), axis=1).max(axis=2)
    size = np.median(extent, axis=0) / 8  # the tile's step per coefficient (components share none here)
    factor = np.array([1.0, 1.0, 0.25, 4.0, 1.0])[:, None]
    levels = np.array([31.0, 63.0, 31.0]).min()
    bound = np.maximum(size * factor, extent / levels) / 2 * 1.01 + 1e-3  # + f16 rounding of the range
    assert np.all(err <= bound), (err, bound)
    assert err[2].max() < err_plain[2].max() / 2  # the important chunk: a finer grid
    assert err[3].max() > err_plain[3].max() * 2  # the unimportant one: a coarser grid


def test_sh_bands_take_their_own_steps_and_the_decode_follows_the_ranges(tmp_path, monkeypatch):
    """A preset step keyed by band plane (sh1, sh2, ...) applies to that band only; readers need nothing new."""
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    monkeypatch.setitem(PRESETS, "t-sh", {**PRESETS["medium"]})
    monkeypatch.setitem(PRESET_STEPS, "t-sh", {"sh2": TileStep((2.0,) * 3, importance=0.5)})
    assert preset_steps("t-sh") == {"sh2": TileStep((2.0,) * 3, importance=0.5)}
    assert preset_steps("t-sh", {"sh": "norm11"}) == {}  # an SH format override drops band steps
    encode_gaussians(g, tmp_path / "a", EncodeOptions(preset="t-sh", lod=False))
    encode_gaussians(g, tmp_path / "b", EncodeOptions(preset="medium", lod=False))
    a, b = decode_scene(tmp_path / "a"), decode_scene(tmp_path / "b")
    np.testing.assert_array_equal(a.sh_rest[:, :3], b.sh_rest[:, :3])  # band 1: medium's grid
    np.testing.assert_array_equal(a.sh_rest[:, 8:], b.sh_rest[:, 8:])  # band 3 too
    assert np.abs(a.sh_rest[:, 3:8] - b.sh_rest[:, 3:8]).max() > 0.01  # band 2: the coarse step


def test_sh_step_presets_keep_sh_per_splat_on_importance_scaled_band_steps(tmp_path):
    """medium-high, medium-low-sh16, medium-low-sh8 (issue 32): no codebook, one importance-scaled step per SH band
    (format 1.2's; the two medium-low variants' fruit_drops scenes are 1.14 for the cube8x4 rotations they measure
    closer, shvariants32); a coarser G gives fewer SH bytes and a larger (but bounded) SH error."""
    from splatstream.encode.jobs import splat_order
    from splatstream.format.presets import PRESET_SH_CODEBOOK, SH_IMPORTANCE

    for preset, levels in (("high-sh255", 255.0), ("medium-high", 63.0), ("medium-low-sh16", 16.0),
                           ("medium-low-sh8", 8.0)):
        assert preset not in PRESET_SH_CODEBOOK
        assert preset_steps(preset) == {f"sh{b}": TileStep((levels,) * 3, importance=SH_IMPORTANCE) for b in (1, 2, 3)}
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    sizes, errors = {}, {}
    for preset in ("medium-low-sh16", "medium-low-sh8"):
        m = encode_gaussians(g, tmp_path / preset, EncodeOptions(preset=preset, lod=False))
        assert m.version == (1, 14) and m.formats["rotation"] == "cube8x4" and m.sh_codebook is None
        sizes[preset] = m.attributes["sh"].disk_bytes
        d = decode_scene(tmp_path / preset)
        stored = g.subset(splat_order(g, m.chunk_order))  # one tile: the order the encoder stored
        errors[preset] = float(np.sqrt(np.mean((d.sh_rest - stored.sh_rest) ** 2)))
    assert sizes["medium-low-sh8"] < sizes["medium-low-sh16"]
    assert errors["medium-low-sh16"] < errors["medium-low-sh8"] < 0.05, errors  # measured 0.0075, 0.0149


def test_high_sh255_lies_between_medium_high_and_high_in_sh_bytes_and_sh_error(tmp_path):
    """high-sh255 (issue 32, hole32): high's planes and zstd settings, its SH on steps of 255 levels, between
    medium-high (63) and high (no step) in SH bytes and SH error; every other plane is stored as high's."""
    from splatstream.format.presets import preset_block_slack, preset_zstd_level, preset_zstd_min_match

    assert PRESETS["high-sh255"] == PRESETS["medium-high"] == PRESETS["high"]
    for setting in (preset_zstd_level, preset_zstd_min_match, preset_block_slack):
        args = (0,) if setting is preset_zstd_level else ()
        assert setting("high-sh255", *args) == setting("high", *args) == setting("medium-high", *args)
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    sizes, errors, others = {}, {}, {}
    for preset in ("medium-high", "high-sh255", "high"):
        m = encode_gaussians(g, tmp_path / preset, EncodeOptions(preset=preset, lod=False))
        assert m.version == (1, 2) and m.sh_codebook is None
        sizes[preset] = m.attributes["sh"].disk_bytes
        others[preset] = {a: m.attributes[a].disk_bytes for a in ("position", "rotation", "scale", "color")}
        d = decode_scene(tmp_path / preset)
        stored = g.subset(splat_order(g, m.chunk_order))
        errors[preset] = float(np.sqrt(np.mean((d.sh_rest - stored.sh_rest) ** 2)))
    assert others["medium-high"] == others["high-sh255"] == others["high"]
    # measured: SH 125,665 / 175,739 / 246,019 bytes at RMS 0.00188 / 0.00047 / 0.00007 (the steps: 4x finer, 4x less)
    assert sizes["medium-high"] < sizes["high-sh255"] < sizes["high"], sizes
    assert 1.2 < sizes["high-sh255"] / sizes["medium-high"] < 1.6 and 1.2 < sizes["high"] / sizes["high-sh255"] < 1.6
    assert errors["high"] < errors["high-sh255"] < errors["medium-high"] / 3 < 0.001, errors


def test_zero_on_the_grid_decodes_small_coefficients_to_zero_within_half_a_step():
    """Issue 32: SH bands with TileStep.zero: each chunk's range moves down by less than one step so that 0 is a
    grid point; the step is kept, every value stays inside its range and decodes within half a step, and values
    near 0 decode to (almost) 0 where an anchored-at-min grid puts them up to half a step away."""
    lo = np.array([[-0.25, 0.5, -1.0]], np.float32)
    hi = np.array([[0.5, 1.0, -0.5]], np.float32)
    wide = np.array([[1.0, 1.5, 30.0]], np.float32)  # steps (wide - lo) / (31, 63, 31)
    new_lo, new_hi = zero_on_grid(lo, wide, hi, "norm565", "<f4", (-65504.0, 65504.0))
    step = 1.25 / 31
    # component 0 straddles 0: min = -ceil(0.25 / step) steps = -7 steps, max = min + 31 steps (>= 0.5)
    np.testing.assert_allclose([new_lo[0, 0], new_hi[0, 0]], [-7 * step, 24 * step], rtol=1e-6)
    # component 1 (all positive) and 2 (all negative) keep their ranges
    assert new_lo[0, 1:].tolist() == lo[0, 1:].tolist() and new_hi[0, 1:].tolist() == wide[0, 1:].tolist()
    # a chunk using every level (no room below its max) keeps its range
    full_lo, full_hi = zero_on_grid(lo[:, :1], np.float32([[0.5]]), np.float32([[0.5]]), "norm565", "<f4",
                                    (-65504.0, 65504.0))
    assert full_lo[0, 0] == np.float32(-0.25) and full_hi[0, 0] == np.float32(0.5)

    rng = np.random.default_rng(11)
    n = 40 * CHUNK_SIZE
    values = (rng.laplace(0, 0.03, (n, 3, 3)) * (rng.random((n, 1, 1)) < 0.7)).astype(np.float32)
    anchored = encode_plane(values, band_plane(1), "norm565", step=TileStep((6.0,) * 3, shared=1))
    zeroed = encode_plane(values, band_plane(1), "norm565", step=TileStep((6.0,) * 3, shared=1, zero=True))
    back_a, back_z = decode_plane(anchored, n), decode_plane(zeroed, n)
    ranges = zeroed.ranges.astype(np.float32)  # (chunks, 2, layers, components)
    step_z = (ranges[:, 1] - ranges[:, 0]) / np.float32([31, 63, 31])
    err_z = np.abs(back_z - values).reshape(40, CHUNK_SIZE, 3, 3).max(axis=1)
    assert np.all(err_z <= step_z / 2 * 1.01 + 1e-6)
    zero = values == 0
    assert np.abs(back_z[zero]).max() < 1e-3 * np.abs(values).max()
    assert np.abs(back_a[zero]).mean() > 0.003  # anchored at the minimum: zeros land between codes
    rms_a, rms_z = np.sqrt(np.mean((back_a - values) ** 2)), np.sqrt(np.mean((back_z - values) ** 2))
    assert rms_z < 0.85 * rms_a, (rms_z, rms_a)


def test_rounding_towards_zero_bounds_the_error_and_shrinks_the_codes():
    """TileStep.rounding below 0.5 (a dead zone): a value u steps from the zero code takes sign(u) floor(|u| + r)
    steps, so the error stays within (1 - r) of a step, and codes move towards the zero code (fewer distinct)."""
    t = np.array([[[0.5 + 0.6 / 31, 0.0, 1.0], [0.5 - 1.55 / 31, 0.5, 0.0]]])  # one chunk, two values
    lo = np.array([[-1.0, 0.5, -2.0]])
    hi = np.array([[1.0, 1.0, -1.0]])
    out = round_towards_zero(t, lo, hi, "norm565", 0.3)
    # component 0 straddles 0: the zero code is rint(0.5 * 31) = 16 (value 0.032, within half a step of 0):
    # u = 15.5 + 0.6 - 16 = 0.1 -> 0 steps; u = 15.5 - 1.55 - 16 = -2.05 -> -2 steps
    np.testing.assert_allclose(out[0, :, 0] * 31, [16, 14])
    # components 1 and 2 do not straddle 0: plain rounding
    np.testing.assert_allclose(out[0, :, 1] * 63, [0, np.rint(0.5 * 63)])
    np.testing.assert_allclose(out[0, :, 2] * 31, [31, 0])

    rng = np.random.default_rng(12)
    n = 40 * CHUNK_SIZE
    values = rng.laplace(0, 0.03, (n, 3, 3)).astype(np.float32)
    plain = encode_plane(values, band_plane(1), "norm565", step=TileStep((6.0,) * 3, shared=1, zero=True))
    dead = encode_plane(values, band_plane(1), "norm565",
                        step=TileStep((6.0,) * 3, shared=1, zero=True, rounding=0.3))
    assert plain.ranges.tobytes() == dead.ranges.tobytes()  # only the codes change
    back_p, back_d = decode_plane(plain, n), decode_plane(dead, n)
    ranges = dead.ranges.astype(np.float32)
    step = (ranges[:, 1] - ranges[:, 0]) / np.float32([31, 63, 31])
    err = np.abs(back_d - values).reshape(40, CHUNK_SIZE, 3, 3).max(axis=1)
    assert np.all(err <= step * 0.7 * 1.01 + 1e-6)
    near_zero = np.abs(back_p) < 1e-3 * np.abs(values).max()
    assert (np.abs(back_d) < 1e-3 * np.abs(values).max()).sum() > 1.2 * near_zero.sum()


def test_low_plus_9bit_sh5_codes_sh_on_one_zero_anchored_step_per_band(tmp_path):
    """low-plus-9bit-sh5 (issue 32): low-plus-9bit's base with per-splat SH on one importance-scaled step per band
    plane, 0 on every chunk's grid: fewer SH bytes than low-plus-9bit-sh6 on fruit_drops at a bounded error, and
    small coefficients decode to about 0."""
    steps = preset_steps("low-plus-9bit-sh5")
    assert "low-plus-9bit-sh5" not in PRESET_SH_CODEBOOK
    assert all(steps[f"sh{b}"] == TileStep((5.0,) * 3, importance=0.3, zero=True, pooled=True) for b in (1, 2, 3))
    assert {k: steps[k] for k in ("position", "scale", "color")} == {
        k: PRESET_STEPS["low-plus-9bit"][k] for k in ("position", "scale", "color")}
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    sizes, errors = {}, {}
    for preset in ("low-plus-9bit-sh6", "low-plus-9bit-sh5"):
        m = encode_gaussians(g, tmp_path / preset, EncodeOptions(preset=preset, lod=False))
        assert m.version == (1, 3) and m.sh_codebook is None
        sizes[preset] = m.attributes["sh"].disk_bytes
        d = decode_scene(tmp_path / preset)
        stored = g.subset(splat_order(g, m.chunk_order))
        errors[preset] = float(np.sqrt(np.mean((d.sh_rest - stored.sh_rest) ** 2)))
        if preset == "low-plus-9bit-sh5":
            assert np.abs(d.sh_rest[stored.sh_rest == 0]).max(initial=0.0) < 1e-3
    assert sizes["low-plus-9bit-sh5"] < 0.9 * sizes["low-plus-9bit-sh6"], sizes  # measured 46,953 and 54,256 B
    assert max(errors.values()) < 0.03, errors  # SH RMS error, measured 0.0198 (sh6) and 0.0203 (sh5)


def test_medium_low_9bit_has_low_plus_9bits_scale_and_opacity_steps_and_per_chunk_positions(tmp_path):
    """medium-low-9bit (issue 32, chosen on guitar): low-plus-9bit's scale and colour steps, its own per-chunk norm9x3
    positions and fine codebook; the decoded log scales within the 200-level step of the median chunk, opacities
    within the 55-level one, positions on each chunk's 511-level grid."""
    steps = preset_steps("medium-low-9bit")
    assert steps == {k: PRESET_STEPS["low-plus-9bit"][k] for k in ("scale", "color")}
    assert PRESETS["medium-low-9bit"]["position"] == "norm9x3" and PRESET_SH_CODEBOOK["medium-low-9bit"] == "fine"
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(1800))
    m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium-low-9bit", lod=False))
    assert m.version == (1, 3) and m.formats["position"] == "norm9x3" and m.uses_codebook
    dec = decode_scene(tmp_path / "s")
    dist = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2)
    nearest = dist.argmin(axis=1)
    extent = float((g.positions.max(axis=0) - g.positions.min(axis=0)).max())
    assert 0 < np.abs(dec.positions - g.positions[nearest]).max() <= extent / 511
    # scales and opacity: on 9-bit positions a decoded splat's nearest input may be another one, so they are checked
    # on the same preset with exact positions (the override drops only the position format; the steps stay)
    encode_gaussians(g, tmp_path / "p", EncodeOptions(preset="medium-low-9bit", lod=False,
                                                      overrides={"position": "f32x4"}))
    dec = decode_scene(tmp_path / "p")
    nearest = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2).argmin(axis=1)
    assert np.abs(dec.positions - g.positions[nearest]).max() <= extent * 1e-6  # f32x4: t in the chunk's range
    # (each splat's three scales sorted: the cube gauge permutes a splat's axes, format.md 4.5)
    err_scale = np.abs(np.sort(dec.log_scales, axis=1) - np.sort(g.log_scales[nearest], axis=1)).max()
    assert 0 < err_scale <= float(g.log_scales.max() - g.log_scales.min()) / 200
    err_opacity = np.abs(dec.opacities - g.opacities[nearest]).max()
    assert 0 < err_opacity <= float(g.opacities.max() - g.opacities.min()) / 55


def test_medium_scales_lie_on_one_1023_level_tile_step(tmp_path, monkeypatch):
    """medium (issue 32, chosen on guitar): log scales on one step per tile over the three axes (the median
    chunk's extent / 1023), everything else per chunk: scale error within that step, more on average than on the
    per-chunk grids of before (11/10/11 bits), for fewer bytes; the scene stays 1.2. Scales are compared on encodes
    with exact positions (the override drops only the position format), so that each decoded splat is matched to
    its own input splat."""
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(1800))
    m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium", lod=False))
    assert m.version == (1, 2) and m.formats == PRESETS["medium"]

    def scale_error(out, **kw):
        encode_gaussians(g, out, EncodeOptions(preset="medium", lod=False, overrides={"position": "f32x4"}, **kw))
        dec = decode_scene(out)
        nearest = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2).argmin(axis=1)
        return np.abs(dec.log_scales - g.log_scales[nearest])

    err = scale_error(tmp_path / "p")
    assert 0 < err.max() <= float(g.log_scales.max() - g.log_scales.min()) / 1023
    monkeypatch.setitem(PRESET_STEPS, "medium", {})  # medium before issue 32: scales on per-chunk grids
    per_chunk = encode_gaussians(g, tmp_path / "c", EncodeOptions(preset="medium", lod=False))
    assert per_chunk.formats == m.formats and m.bytes_on_disk < per_chunk.bytes_on_disk
    assert scale_error(tmp_path / "pc").mean() < err.mean()  # x and z had 2047 levels of their own chunk


def test_very_low_rgb127_is_very_low_with_8_bit_colour_on_a_127_level_step_between_very_low_and_low(tmp_path):
    """very-low-rgb127 (issue 32, step32): very-low's positions, rotations, scales and SH codebook with low's norm8x4
    colour (not BC7) on one tile step of 127 levels for R, G, B and 55 for opacity. The scene is 1.13 like
    very-low's (cube565 rotations; 1.2 before them), its bytes lie between very-low's and low's, and so does its
    colour error: SH0 within the 127-level step of the median chunk, opacity within the 55-level one. Colour is
    compared on encodes with exact positions (the override drops only the position format), so that each decoded
    splat is matched to its own input splat."""
    assert PRESETS["very-low-rgb127"] == {**PRESETS["very-low"], "color": PRESETS["low"]["color"]}
    assert PRESET_SH_CODEBOOK["very-low-rgb127"] == PRESET_SH_CODEBOOK["very-low"] == "auto"
    assert preset_steps("very-low-rgb127") == {"color": TileStep((127.0, 127.0, 127.0, 55.0), shared=3)}
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(1800))
    sizes, errors = {}, {}
    for preset in ("very-low", "very-low-rgb127", "low"):
        m = encode_gaussians(g, tmp_path / preset, EncodeOptions(preset=preset, lod=False))
        assert m.version == (1, 13) and m.uses_codebook  # 1.13: cube565 rotations (format.md 4.5), else 1.2
        sizes[preset] = m.bytes_on_disk
        encode_gaussians(g, tmp_path / f"{preset}-p", EncodeOptions(preset=preset, lod=False,
                                                                    overrides={"position": "f32x4"}))
        dec = decode_scene(tmp_path / f"{preset}-p")
        nearest = np.abs(dec.positions[:, None, :] - g.positions[None, :, :]).max(axis=2).argmin(axis=1)
        errors[preset] = np.abs(dec.sh_dc - g.sh_dc[nearest]), np.abs(dec.opacities - g.opacities[nearest])
    # measured: 21,115 / 22,172 / 25,126 bytes; SH0 RMS error 0.0672 / 0.0074 / 0.0037 (BC7 / the step / 8 bits per
    # chunk); the largest SH0 and opacity errors 0.0127 and 0.0089 against the bounds 0.0321 and 0.0180
    assert sizes["very-low"] < sizes["very-low-rgb127"] < sizes["low"], sizes
    rms = {p: float(np.sqrt(np.mean(e[0] ** 2))) for p, e in errors.items()}
    assert rms["low"] < rms["very-low-rgb127"] < rms["very-low"], rms
    sh_dc, opacity = errors["very-low-rgb127"]
    assert 0 < sh_dc.max() <= float((g.sh_dc.max(axis=0) - g.sh_dc.min(axis=0)).max()) / 127
    assert 0 < opacity.max() <= float(g.opacities.max() - g.opacities.min()) / 55


def test_a_size_relative_step_may_take_the_middle_axis_as_the_splat_size():
    """TileStep.size_axis (issue 32, logo32's probe): 1 takes the middle axis of exp(log scale) as the size, so a
    thin strand (one long axis) gets the step of its width; 0 the smallest, 2 (the default) the largest."""
    log_scales = np.log(np.array([[0.01, 0.02, 0.04], [0.05, 0.01, 0.01], [0.03, 0.002, 0.03]]))
    np.testing.assert_allclose(splat_sizes(log_scales, 1), [0.02, 0.01, 0.03])
    np.testing.assert_allclose(splat_sizes(log_scales, 0), [0.01, 0.01, 0.002])
    np.testing.assert_allclose(splat_sizes(log_scales, 2), splat_sizes(log_scales))
    with pytest.raises(UsageError):
        TileStep((4095.0,) * 3, shared=3, per_size=40.0, size_axis=3).check("norm16x4", 3)
    step = TileStep((65535.0,) * 3, shared=3, per_size=40.0, size_levels_min=4095.0, size_axis=1)
    rng = np.random.default_rng(7)
    values = (rng.random((4 * CHUNK_SIZE, 1, 3)) * [[[1.0, 1.5, 2.0]]]).astype(np.float32)
    widths = np.full(len(values), 2e-5)  # 40 x 2 / 2e-5 = 4M levels: clamped to 65535
    plane = encode_plane(values, POSITION, "norm16x4", step=step, sizes=widths)
    err = np.abs(decode_plane(plane, len(values)) - values).max()
    assert err <= 2.0 / 65535 / 2 * 1.01, err
    coarse = encode_plane(values, POSITION, "norm16x4", step=step, sizes=np.full(len(values), 1.0))  # 80: 4095
    err = np.abs(decode_plane(coarse, len(values)) - values).max()
    assert 2.0 / 4095 / 4 < err <= 2.0 / 4095 / 2 * 1.01, err
