"""bench/rot_choice_dither.py and bench/rot_choice_probe.py (issue 32, cube9bit32): the re-drawn inputs (a dither far
below a pixel that moves every value between its grid points), the covariance measures of a decode against its
input whatever order the encoder stored the splats in, and the probe's attribute mixing."""
from __future__ import annotations

import numpy as np
from conftest import ROOT, load_bench

from splatstream.encode.local import encode_gaussians
from splatstream.encode.options import EncodeOptions
from splatstream.format.layout import morton_order
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene

D = load_bench("rot_choice_dither")
PR = load_bench("rot_choice_probe")
FRUIT = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"


def turn_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    dot = np.abs(np.sum(a.astype(np.float64) * b.astype(np.float64), axis=1))
    return np.degrees(2 * np.arccos(np.clip(dot, 0, 1)))


def test_seed_0_is_the_input_and_a_dither_stays_within_its_bounds():
    g = read_gaussians(FRUIT)
    assert D.dithered(g, 0, 0.02, 0.5) is g
    d = D.dithered(g, 3, 0.02, 0.5)
    moved = d.log_scales.astype(np.float64) - g.log_scales
    assert np.abs(moved).max() <= 0.02 + 1e-6 and np.abs(moved).mean() > 0.008  # U(-0.02, 0.02): mean |.| 0.01
    angle = turn_deg(d.rotations, g.rotations)
    assert angle.max() <= 0.5 + 0.01 and 0.2 < angle.mean() < 0.3  # U(0, 0.5) degrees
    assert np.array_equal(d.positions, g.positions) and np.array_equal(d.sh_rest, g.sh_rest)
    again = D.dithered(g, 3, 0.02, 0.5)
    assert np.array_equal(again.rotations, d.rotations)  # a seed is a draw that can be made again


def test_covariances_of_a_quarter_turn_swap_two_axes():
    q = np.array([[np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]])  # 90 degrees about z
    cov = D.covariances(q, np.log(np.array([[1.0, 2.0, 3.0]])))[0]
    assert np.allclose(cov, np.diag([4.0, 1.0, 9.0]))
    assert np.allclose(PR.covariances(q, np.log(np.array([[1.0, 2.0, 3.0]])))[0], cov)


def test_measures_match_the_decode_to_the_input_in_any_order(tmp_path):
    g = read_gaussians(FRUIT)
    zero = D.measures(g, g)  # the input's own order
    assert all(v == 0 for v in zero.values())
    assert D.measures(g, g.subset(morton_order(g.positions)))["cov_rel"] < 1e-6  # Morton order
    # a real decode in Morton order (fields) and in the keyed transport's order: the same scale plane (norm8x4 on
    # a 200-level tile step) and rotations, so nearly the same error; matched wrongly it would be far larger
    out = {}
    for preset in ("medium-low-9bit", "low-plus-10bit-cb8"):
        encode_gaussians(g, tmp_path / preset, EncodeOptions(preset=preset, lod=False, up=(0.0, -1.0, 0.0)))
        out[preset] = D.measures(g, decode_scene(tmp_path / preset))
    assert 0.01 < out["medium-low-9bit"]["cov_rel"] < 0.03
    assert abs(out["low-plus-10bit-cb8"]["cov_rel_opacity_area"]
               - out["medium-low-9bit"]["cov_rel_opacity_area"]) < 0.002


def test_the_probe_mixes_fields_whole_or_on_a_mask():
    g = read_gaussians(FRUIT)
    other = D.dithered(g, 1, 0.02, 0.5)
    whole = PR.mixed(g, other, ("log_scales",))
    assert np.array_equal(whole.log_scales, other.log_scales) and np.array_equal(whole.rotations, g.rotations)
    mask = np.zeros(len(g), bool)
    mask[:10] = True
    part = PR.mixed(g, other, ("rotations", "log_scales"), mask)
    assert np.array_equal(part.rotations[:10], other.rotations[:10])
    assert np.array_equal(part.rotations[10:], g.rotations[10:])
    assert np.array_equal(part.log_scales[10:], g.log_scales[10:])
