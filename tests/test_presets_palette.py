"""medium-low-palette (issue 32): scene palettes with SH0's merged pairwise, a position step from the splats' size,
and medium-low-12bit's planes and position step where a plane's values do not fit a palette."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from conftest import real

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.evaluate import preset_for_target
from splatstream.format.codec import merged_pairs
from splatstream.format.planes import PALETTE_ENTRIES
from splatstream.format.presets import (
    PRESET_PALETTE_FALLBACK,
    PRESET_STEPS,
    PRESET_TRANSPORT,
    PRESETS,
    palette_fallback,
    preset_steps,
)
from splatstream.format.steps import splat_sizes
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene

PRESET = "medium-low-palette"


def test_merged_pairs_keeps_the_ends_and_halves_the_inner_values_within_half_a_pair():
    rng = np.random.default_rng(3)
    pal = np.sort(rng.normal(size=PALETTE_ENTRIES)).astype(np.float32)
    merged = merged_pairs(pal)
    assert merged.shape == (PALETTE_ENTRIES,) and merged.dtype == np.float32
    distinct = np.unique(merged)
    assert len(distinct) == 129  # 2 ends + 254 / 2
    assert distinct[0] == pal[0] and distinct[-1] == pal[-1]
    assert np.all(merged[129:] == pal[-1])  # padded with the largest, as a palette is
    # every input value's nearest merged entry is within half the gap of the pair it was merged in
    inner = pal[1:-1].astype(np.float64)
    half_pair = np.repeat((inner[1::2] - inner[0::2]) / 2, 2)
    nearest = np.abs(pal[1:-1, None].astype(np.float64) - distinct[None, :].astype(np.float64)).min(axis=1)
    assert np.all(nearest <= half_pair + 1e-6) and nearest.max() > 0
    np.testing.assert_array_equal(merged[1:3], ((inner[[0, 2]] + inner[[1, 3]]) / 2).astype(np.float32))
    # an odd count of inner values pairs the last with itself; two or fewer distinct values stay as they are
    odd = merged_pairs(np.array([0, 1, 2, 3, 4] + [4] * 251, np.float32))
    np.testing.assert_array_equal(np.unique(odd), [0, 1.5, 3, 4])
    np.testing.assert_array_equal(np.unique(merged_pairs(np.array([1, 2] + [2] * 254, np.float32))), [1, 2])


def test_the_preset_falls_back_to_medium_low_12bit_per_plane_and_then_its_position_step():
    assert PRESETS[PRESET]["scale"] == PRESETS[PRESET]["color"] == "pal8x4" and PRESET_TRANSPORT[PRESET] == "keyed"
    own = PRESET_STEPS[PRESET]["position"]
    assert own.per_size == 120.0
    formats, steps, fell = palette_fallback(PRESET, None, set())
    assert fell == [] and formats == PRESETS[PRESET] and steps == {"position": own}
    other = preset_steps(PRESET_PALETTE_FALLBACK[PRESET])
    formats, steps, fell = palette_fallback(PRESET, None, {"scale"})
    assert fell == ["scale"] and formats["scale"] == "norm8x4" and formats["color"] == "pal8x4"
    assert steps == {"position": other["position"], "scale": other["scale"]}
    formats, steps, fell = palette_fallback(PRESET, None, {"scale", "color"})
    assert fell == ["scale", "color"] and formats == PRESETS["medium-low-12bit"] and steps == other
    # an attribute the options override never falls back; another preset never does
    formats, steps, fell = palette_fallback(PRESET, {"scale": "pal8x4"}, {"scale"})
    assert fell == [] and formats["scale"] == "pal8x4" and steps == {"position": own}
    assert palette_fallback("medium-low-12bit", {"scale": "pal8x4"}, {"scale"})[2] == []


@pytest.fixture(scope="module")
def sog(tmp_path_factory):
    """The first 3000 splats of a statue scan (a SOG file: 256 log scales, 256 SH0 values, 201 opacities)."""
    g = read_gaussians(real("statues/massa.sog")).subset(np.arange(3000))
    out = tmp_path_factory.mktemp("palpreset") / "s"
    return g, out, encode_gaussians(g, out, EncodeOptions(preset=PRESET, lod=False))


def test_a_sog_input_keeps_its_palettes_with_sh0_merged_and_decodes_within_bounds(sog):
    """The dequantizer's error bound: scales and opacity exact, SH0 within half its merged pair's gap, positions
    within half of the tile's median splat size / 120 (the size-relative step, or a finer one where 4095 levels of
    the median chunk are finer)."""
    g, out, m = sog
    assert m.formats["scale"] == m.formats["color"] == "pal8x4" and m.formats["position"] == "norm16x4"
    pal = m.scene_palettes
    dc = np.unique(g.sh_dc).astype(np.float64)
    assert len(dc) > 200 and len(np.unique(pal["color"][0])) == (len(dc) - 2 + 1) // 2 + 2
    np.testing.assert_array_equal(np.unique(pal["scale"][0]), np.unique(g.log_scales))  # not merged
    d = decode_scene(out)
    np.testing.assert_array_equal(np.sort(d.log_scales.ravel()), np.sort(g.log_scales.ravel()))
    np.testing.assert_allclose(np.sort(d.opacities), np.sort(g.opacities), atol=2e-7)
    inner = dc[1:-1]
    half_gap = np.max(np.diff(inner)) / 2
    assert np.abs(np.sort(d.sh_dc.ravel()) - np.sort(g.sh_dc.ravel())).max() <= half_gap + 1e-6
    got = np.unique(d.sh_dc).astype(np.float32)
    assert set(got.tolist()) <= set(np.unique(pal["color"][0]).tolist())
    step = float(np.median(splat_sizes(g.log_scales))) / 120.0
    # splats are reordered: each decoded position lies within half a step of an input position (max norm)
    near = np.array([np.abs(g.positions - p).max(axis=1).min() for p in d.positions.astype(np.float64)])
    assert near.max() <= step / 2 * (1 + 1e-3) + 1e-6 and near.max() > step / 8


def test_a_non_sog_input_falls_back_to_medium_low_12bit_planes_and_says_so(tmp_path, caplog):
    """A .splat file: 8-bit colour and opacity fit the palettes, its float scales do not: scales and positions are
    written as medium-low-12bit (with the same transport) writes them, exactly, and one log line says so."""
    g = read_gaussians(real("winter_fountain_first3000.splat"))
    with caplog.at_level(logging.INFO, logger="splatstream.encode"):
        m = encode_gaussians(g, tmp_path / "p", EncodeOptions(preset=PRESET, lod=False))
    lines = [r.getMessage() for r in caplog.records if "fell back" in r.getMessage()]
    assert lines == [f"{PRESET}: scale fell back to scale norm8x4 (values do not fit 256-entry palettes)"]
    assert m.formats["scale"] == "norm8x4" and m.formats["color"] == "pal8x4"
    encode_gaussians(g, tmp_path / "r", EncodeOptions(preset="medium-low-12bit", lod=False, transport="keyed"))
    d, r = decode_scene(tmp_path / "p"), decode_scene(tmp_path / "r")
    np.testing.assert_array_equal(d.positions, r.positions)
    np.testing.assert_array_equal(d.log_scales, r.log_scales)


def test_target_psnr_and_size_choose_among_rows_that_include_the_preset():
    rows = [{"label": PRESET, "kind": "preset", "disk_bytes_per_splat": 11.0, "psnr_mean": 65.0},
            {"label": "medium-low-12bit", "kind": "preset", "disk_bytes_per_splat": 12.0, "psnr_mean": 64.0},
            {"label": "medium", "kind": "preset", "disk_bytes_per_splat": 14.0, "psnr_mean": 66.0}]
    assert preset_for_target(rows, target_psnr=64.5)["label"] == PRESET
    assert preset_for_target(rows, target_bytes=11.5)["label"] == PRESET
