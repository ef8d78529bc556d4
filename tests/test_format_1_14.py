"""The rotation format of format 1.14, cube8x4 (format.md 4.5): norm8x4's texels holding x, y, z of a cube-gauge
quaternion over [-tan(pi/8), tan(pi/8)] (A unused). Its quantiser's angle error bound against norm8x4's smallest
three, the version a scene using it is written as, readers that reject it where it does not belong, and medium-low's
measured choice between its half turns (norm8x4) and cube8x4 (encode/plan.plan_rotation_format). GPU decode against
numpy: test_gl_decode.py (every value format, cube8x4 included); the test vector `medium-low/` (1.14) and the old
scenes (1.2: `high/`, `medium/`, `low-norm565/`): test_spec_vectors.py."""
from __future__ import annotations

import logging
import math
import shutil
from dataclasses import replace

import msgpack
import numpy as np
import pytest
from conftest import read_manifest_dict, real, run_cli, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.encode.plan import plan_rotation_format, rotation_error_deg
from splatstream.errors import FormatError, UsageError
from splatstream.format.codec import decode_rotations, encode_rotations
from splatstream.format.manifest import writer_version
from splatstream.format.presets import resolve_formats, rotation_choices, rotation_gauge
from splatstream.format.texformats import CUBE_GAUGE_RANGE, get_format, pack_texels, unpack_texels
from splatstream.format.transport import FIELD_LAYOUTS
from splatstream.io import read_gaussians
from splatstream.rotation_canon import canonical_gauge
from splatstream.scene_decode import decode_scene

MEDIUM_LOW = resolve_formats("medium-low")


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle between unit quaternions, in degrees (q and -q the same rotation)."""
    return np.degrees(2 * np.arccos(np.clip(np.abs((a.astype(np.float64) * b).sum(axis=1)), 0.0, 1.0)))


def _round_trip(q: np.ndarray, fmt: str) -> np.ndarray:
    return decode_rotations(unpack_texels(fmt, pack_texels(fmt, encode_rotations(q, fmt))), fmt)


def _random_rotations(n: int, seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4)).astype(np.float32)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def cube_rotations() -> np.ndarray:
    """200,000 random rotations in the cube gauge (what the encoder stores in cube8x4), plus the gauge's corners."""
    q, _ = canonical_gauge(_random_rotations(200_000, 0), np.zeros((200_000, 3), np.float32), "cube")
    r = CUBE_GAUGE_RANGE
    corners = np.array([[1, sx * r, sy * r, sz * (1 - 2 * r)] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
                       + [[1, r, 0, 0], [1, 0, -r, 0], [1, 0, 0, r], [1, 0, 0, 0]], np.float32)
    corners /= np.linalg.norm(corners, axis=1, keepdims=True)
    return np.concatenate([q, corners])


def test_cube8x4_angle_error_bound(cube_rotations):
    """x, y, z on 8-bit grids over [-r, r] (r = tan(pi/8)): each off by at most half a step, r / 255, so
    |d xyz| <= sqrt(3) r / 255; w = sqrt(1 - |xyz|^2) moves by at most sqrt(3) r times that, so |d q| <=
    |d xyz| sqrt(1 + 3 r^2) and the angle is at most 4 asin(|d q| / 2): 0.40 degrees. norm8x4's smallest three (over
    [-1/sqrt(2), 1/sqrt(2)]) on the same random rotations, in the half turns medium-low stores them in, errs up to
    0.92 degrees, 0.34 on average (cube8x4 0.36 and 0.18)."""
    r = CUBE_GAUGE_RANGE
    bound = math.degrees(4 * math.asin(math.sqrt(3) * r / 255 * math.sqrt(1 + 3 * r * r) / 2))
    assert 0.39 < bound < 0.40
    err = _angle_deg(cube_rotations, _round_trip(cube_rotations, "cube8x4"))
    assert err.max() <= bound, (err.max(), bound)
    q = _random_rotations(200_000, 0)  # cube_rotations before the gauge
    half_turns, _ = canonical_gauge(q, np.zeros((len(q), 3), np.float32), "half-turns")
    old = _angle_deg(half_turns, _round_trip(half_turns, "norm8x4"))
    assert err.max() < 0.45 * old.max() and err.mean() < 0.6 * old.mean()
    # the format's formula: c = (2t - 1) r from R, G, B, w derived, normalised; A written 0
    texels = pack_texels("cube8x4", encode_rotations(cube_rotations, "cube8x4"))
    assert np.all(texels[:, 3] == 0)
    t = unpack_texels("cube8x4", texels)
    xyz = (2.0 * t[:, :3].astype(np.float64) - 1.0) * r
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(axis=1)))
    ref = np.concatenate([w[:, None], xyz], axis=1)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(decode_rotations(t, "cube8x4"), ref, atol=2e-7)


def test_cube8x4_is_norm8x4s_texels():
    fmt = get_format("cube8x4")
    assert fmt.texels == "norm8x4" and fmt.bits_per_texel == 32 and fmt.gl_internal == "RGBA8"
    assert FIELD_LAYOUTS["cube8x4"] == FIELD_LAYOUTS["norm8x4"]
    t = np.random.default_rng(1).random((1000, 4)).astype(np.float32)
    np.testing.assert_array_equal(pack_texels("cube8x4", t), pack_texels("norm8x4", t))


def test_writer_version_is_1_14_only_with_cube8x4():
    assert writer_version({**MEDIUM_LOW, "rotation": "cube8x4"}) == (1, 14)
    assert writer_version(MEDIUM_LOW) == (1, 2)


def test_cube8x4_takes_the_cube_gauge_and_only_the_rotation():
    assert rotation_gauge("medium-low", {**MEDIUM_LOW, "rotation": "cube8x4"}) == "cube"
    assert rotation_gauge("medium-low", MEDIUM_LOW) == "half-turns"
    with pytest.raises(UsageError, match="holds only rotation, not color"):
        resolve_formats("medium-low", {"color": "cube8x4"})


def test_the_measure_keeps_the_half_turns_for_rotations_on_their_grid():
    """A rotation already on norm8x4's smallest-three grid (a SOG file's) is kept by the half turns (its components
    in another order): its error there is float rounding, where cube8x4 moves it off; off any grid cube8x4 is the
    closer (about 0.18 against 0.34 degrees on random rotations)."""
    q = _random_rotations(20_000, 2)
    scales = np.zeros((len(q), 3), np.float32)
    cube = {**MEDIUM_LOW, "rotation": "cube8x4"}
    off_half, off_cube = (rotation_error_deg(q, scales, "medium-low", f).mean() for f in (MEDIUM_LOW, cube))
    assert 0.30 < off_half < 0.37 and 0.16 < off_cube < 0.20
    on_grid = _round_trip(q, "norm8x4")
    on_half, on_cube = (rotation_error_deg(on_grid, scales, "medium-low", f).mean() for f in (MEDIUM_LOW, cube))
    assert on_half < 0.01 and on_cube > 0.16
    opts = EncodeOptions(preset="medium-low")
    assert plan_rotation_format(opts, MEDIUM_LOW, q, scales)["rotation"] == "cube8x4"
    assert plan_rotation_format(opts, MEDIUM_LOW, on_grid, scales)["rotation"] == "norm8x4"
    # a rotation format given is kept, and presets with one rotation format measure nothing
    given = EncodeOptions(preset="medium-low", overrides={"rotation": "norm8x4"})
    assert rotation_choices("medium-low", {"rotation": "norm8x4"}) == ()
    assert plan_rotation_format(given, MEDIUM_LOW, q, scales)["rotation"] == "norm8x4"
    assert rotation_choices("medium") == () and rotation_choices("medium-low-9bit") == ()


@pytest.fixture(scope="module")
def medium_low_scene(tmp_path_factory):
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(700))
    out = tmp_path_factory.mktemp("cube8x4") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low", lod=False))
    return g, out, m


def test_a_medium_low_scene_off_the_grid_is_1_14_in_the_cube_gauge(medium_low_scene):
    g, out, m = medium_low_scene
    assert m.version == (1, 14) and m.formats["rotation"] == "cube8x4"
    assert msgpack.unpackb((out / "manifest.msgpack").read_bytes(), raw=False)["version"] == [1, 14]
    dec = decode_scene(out)
    assert np.all(dec.rotations[:, 0] >= 0.85)  # in the cube gauge: w >= 0.854 up to the grid
    # the rotations' error against the input's, the encoder's measure: cube8x4's (0.18 degrees on random ones)
    err = rotation_error_deg(g.rotations, g.log_scales, "medium-low", m.formats)
    assert err.max() < 0.40 and err.mean() < 0.25


def test_medium_low_on_a_grid_input_writes_norm8x4_and_version_1_2(medium_low_scene, tmp_path, caplog):
    """A scene whose rotations lie on norm8x4's smallest-three grid (as a SOG's do) keeps the half turns, and its
    file is what medium-low wrote before 1.14 (version 1.2, norm8x4 rotations)."""
    g, _, _ = medium_low_scene
    on_grid = replace(g, rotations=_round_trip(g.rotations, "norm8x4"))
    with caplog.at_level(logging.INFO, logger="splatstream.encode"):
        m = encode_gaussians(on_grid, tmp_path / "s", EncodeOptions(preset="medium-low", lod=False))
    assert m.version == (1, 2) and m.formats["rotation"] == "norm8x4"
    assert "medium-low rotations: norm8x4 (mean angle error norm8x4 0.0" in caplog.text
    forced = encode_gaussians(on_grid, tmp_path / "f", EncodeOptions(preset="medium-low", lod=False,
                                                                     overrides={"rotation": "norm8x4"}))
    assert forced.formats == m.formats
    assert np.array_equal(decode_scene(tmp_path / "s").rotations, decode_scene(tmp_path / "f").rotations)


def test_a_1_13_manifest_naming_cube8x4_is_rejected(medium_low_scene, tmp_path):
    _, out, _ = medium_low_scene
    d = read_manifest_dict(out)
    d["version"] = [1, 13]
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=r"formats\.rotation.*cube8x4 is a version 1\.14 texel format"):
        decode_scene(tmp_path / "s")
    r = run_cli("info", tmp_path / "s")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "version 1.14 texel format" in r.stderr


def test_cube8x4_for_another_attribute_is_rejected(medium_low_scene, tmp_path):
    _, out, _ = medium_low_scene
    d = read_manifest_dict(out)
    d["formats"]["scale"] = "cube8x4"
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=r"formats\.scale.*cube8x4 holds rotations in the cube gauge"):
        decode_scene(tmp_path / "s")


def test_info_calls_the_measured_rotation_the_presets_own(medium_low_scene):
    _, out, _ = medium_low_scene
    line = next(s for s in run_cli("info", out).stdout.splitlines() if s.startswith("preset"))
    assert "differs from it in" not in line


def _directory_digest(path) -> str:
    """One SHA-256 over every file's relative path and bytes, in path order."""
    import hashlib
    import os

    h = hashlib.sha256()
    for root, _, files in sorted(os.walk(path)):
        for name in sorted(files):
            full = os.path.join(root, name)
            h.update(os.path.relpath(full, path).encode() + b"\0")
            with open(full, "rb") as f:
                h.update(f.read())
    return h.hexdigest()


def test_every_engine_measures_the_same_choice(tmp_path):
    """The measure reads the scene sample's rotations (encode/sample.py), which a partitioned encode gathers from its
    passes over the rows exactly as the in-memory one takes them: both write cube8x4 for fruit_drops and the same
    files, byte for byte."""
    from splatstream.encode import encode_file
    from splatstream.store import load_manifest

    tree = {"max_leaf_splats": 300, "lod_merge": "grid"}
    encode_file(str(real("fruit_drops_sh3.ply")), str(tmp_path / "memory"), preset="medium-low", **tree)
    encode_file(str(real("fruit_drops_sh3.ply")), str(tmp_path / "parts"), preset="medium-low",
                memory_per_worker=1 << 20, **tree)
    assert load_manifest(tmp_path / "parts").formats["rotation"] == "cube8x4"
    assert _directory_digest(tmp_path / "parts") == _directory_digest(tmp_path / "memory")


# The other half-turn presets (issue 32, cube8x4all32): the rule written before the held-out runs admitted
# medium-low-12bit, -palette and low-plus (PSNR up on fruit_drops and guitar at +0.2-0.3 % bytes) and kept the half
# turns for the 9- and 10-bit ones, which lost 0.21-0.53 dB on fruit_drops with cube8x4 (BENCHMARKS.md, "The other
# half-turn presets measure cube8x4 too"); medium-low's per-splat SH variants measure since shvariants32.
MEASURING = ["medium-low-12bit", "medium-low-palette", "low-plus"]
HALF_TURNS_ONLY = ["medium-low-9bit", "low-plus-9bit", "low-plus-9bit-sh6", "low-plus-9bit-sh5", "low-plus-10bit-cb8"]


@pytest.mark.parametrize("preset", ["medium-low-sh16", "medium-low-sh8", *MEASURING])
def test_the_other_measuring_presets_make_medium_lows_choice(preset, medium_low_scene, tmp_path, caplog):
    """Every preset that measures its rotations besides medium-low measures the same candidates: off the grid
    (fruit_drops' PLY rotations) cube8x4 and version 1.14 in the cube gauge; on norm8x4's grid the half turns, written
    byte for byte as --rotation norm8x4 writes them; the rotation given is kept."""
    assert rotation_choices(preset) == rotation_choices("medium-low") == ("norm8x4", "cube8x4")
    assert rotation_choices(preset, {"rotation": "norm8x4"}) == ()
    formats = resolve_formats(preset)
    q = _random_rotations(20_000, 3)
    scales = np.zeros((len(q), 3), np.float32)
    assert plan_rotation_format(EncodeOptions(preset=preset), formats, q, scales)["rotation"] == "cube8x4"

    g, _, _ = medium_low_scene
    m = encode_gaussians(g, tmp_path / "off", EncodeOptions(preset=preset, lod=False))
    assert m.version == (1, 14) and m.formats["rotation"] == "cube8x4"
    if preset != "medium-low-palette":  # which falls back to -12bit's planes on a PLY, saying so
        assert m.formats == {**formats, "rotation": "cube8x4"}
    dec = decode_scene(tmp_path / "off")
    assert np.all(dec.rotations[:, 0] >= 0.85)  # the cube gauge
    err = rotation_error_deg(g.rotations, g.log_scales, preset, m.formats)
    assert err.max() < 0.40 and err.mean() < 0.25

    on_grid = replace(g, rotations=_round_trip(g.rotations, "norm8x4"))
    with caplog.at_level(logging.INFO, logger="splatstream.encode"):
        kept = encode_gaussians(on_grid, tmp_path / "on" / "s", EncodeOptions(preset=preset, lod=False))
    assert kept.formats["rotation"] == formats["rotation"] == "norm8x4" and kept.version < (1, 14)
    assert f"{preset} rotations: norm8x4 (mean angle error norm8x4 0.0" in caplog.text
    forced = encode_gaussians(on_grid, tmp_path / "f" / "s", EncodeOptions(preset=preset, lod=False,
                                                                           overrides={"rotation": "norm8x4"}))
    assert forced.formats == kept.formats  # and every file the same (the manifest names its directory: both "s")
    assert _directory_digest(tmp_path / "on") == _directory_digest(tmp_path / "f")
    # info calls the measured rotation the preset's own
    line = next(s for s in run_cli("info", tmp_path / "off").stdout.splitlines() if s.startswith("preset"))
    assert preset in line and "rotation=" not in line


@pytest.mark.parametrize("preset", MEASURING)
def test_a_sog_made_input_keeps_the_half_turns_bit_for_bit(preset, tmp_path):
    """A statue scan read from its SOG file (rotations on norm8x4's 8-bit smallest-three grid) measures ~0 degrees
    for the half turns: the preset writes norm8x4, the same files as with --rotation norm8x4 (what it wrote before
    cube8x4all32)."""
    g = read_gaussians(real("statues/massa.sog")).subset(np.arange(3000))
    m = encode_gaussians(g, tmp_path / "chosen" / "s", EncodeOptions(preset=preset, lod=False))
    encode_gaussians(g, tmp_path / "half" / "s", EncodeOptions(preset=preset, lod=False,
                                                               overrides={"rotation": "norm8x4"}))
    assert m.formats["rotation"] == "norm8x4" and m.version < (1, 14)
    assert _directory_digest(tmp_path / "chosen") == _directory_digest(tmp_path / "half")


@pytest.mark.parametrize("preset", HALF_TURNS_ONLY)
def test_the_9_and_10_bit_half_turn_presets_keep_norm8x4(preset):
    """They lost PSNR on fruit_drops with cube8x4 (cube8x4all32's rule): no measure, the half turns always."""
    assert rotation_choices(preset) == ()
    q = _random_rotations(2_000, 4)
    formats = resolve_formats(preset)
    assert plan_rotation_format(EncodeOptions(preset=preset), formats, q, np.zeros((len(q), 3), np.float32)) == formats
