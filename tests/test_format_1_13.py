"""The rotation format of format 1.13, cube565 (format.md 4.5): norm565's texels holding x, y, z of a cube-gauge
quaternion over [-tan(pi/8), tan(pi/8)]. Its quantiser's angle error bound against norm565's, the version a scene
using it is written as, the encoder's gauge for it, and readers that reject it where it does not belong. GPU decode
against numpy: test_gl_decode.py (every value format); round trips of the presets that use it:
test_codec_roundtrip.py; old scenes (norm565 rotations, version 1.2): test_spec_vectors.py's `low-norm565`."""
from __future__ import annotations

import math
import shutil

import msgpack
import numpy as np
import pytest
from conftest import read_manifest_dict, real, run_cli, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError, UsageError
from splatstream.format.codec import decode_rotations, encode_rotations
from splatstream.format.manifest import writer_version
from splatstream.format.presets import resolve_formats, rotation_gauge
from splatstream.format.texformats import CUBE_GAUGE_RANGE, get_format, pack_texels, unpack_texels
from splatstream.format.transport import FIELD_LAYOUTS
from splatstream.io import read_gaussians
from splatstream.rotation_canon import canonical_gauge
from splatstream.scene_decode import decode_scene

LOW = {"position": "norm8x4", "rotation": "cube565", "scale": "norm8x4", "color": "norm8x4", "sh": "norm565"}


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle between unit quaternions, in degrees (q and -q the same rotation)."""
    return np.degrees(2 * np.arccos(np.clip(np.abs((a.astype(np.float64) * b).sum(axis=1)), 0.0, 1.0)))


def _round_trip(q: np.ndarray, fmt: str) -> np.ndarray:
    t = encode_rotations(q, fmt)
    return decode_rotations(unpack_texels(fmt, pack_texels(fmt, t[:, :3])), fmt)


@pytest.fixture(scope="module")
def cube_rotations() -> np.ndarray:
    """200,000 random rotations in the cube gauge (what the encoder stores in cube565), plus the gauge's corners."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(200_000, 4)).astype(np.float32)
    q, _ = canonical_gauge(q / np.linalg.norm(q, axis=1, keepdims=True), np.zeros((len(q), 3), np.float32), "cube")
    r = CUBE_GAUGE_RANGE
    # the gauge's region is |x|, |y|, |z| <= r w and |x| + |y| + |z| <= w: its corners (w smallest) are (1, r, r,
    # 1 - 2r) up to order and signs, normalised
    corners = np.array([[1, sx * r, sy * r, sz * (1 - 2 * r)] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
                       + [[1, r, 0, 0], [1, 0, -r, 0], [1, 0, 0, r], [1, 0, 0, 0]], np.float32)
    corners /= np.linalg.norm(corners, axis=1, keepdims=True)
    return np.concatenate([q, corners])


def test_cube_gauge_bounds_what_cube565_stores(cube_rotations):
    q = cube_rotations
    corner_w = 1 / math.sqrt(1 + 2 * CUBE_GAUGE_RANGE ** 2 + (1 - 2 * CUBE_GAUGE_RANGE) ** 2)
    assert abs(corner_w - 0.8536) < 1e-4
    assert np.all(q[:, 0] >= corner_w - 1e-6)
    assert np.all(np.abs(q[:, 1:]) <= CUBE_GAUGE_RANGE * q[:, :1] + 1e-6)


def test_cube565_angle_error_bound_per_bit_budget(cube_rotations):
    """x, y, z on 5/6/5-bit grids over [-r, r] (r = tan(pi/8)): each off by at most half a step, r / 31, r / 63,
    r / 31, so |d xyz| <= r sqrt(2 / 31^2 + 1 / 63^2); w = sqrt(1 - |xyz|^2) moves by at most |xyz| / w <= sqrt(3) r
    times that, so |d q| <= |d xyz| sqrt(1 + 3 r^2) and the angle is at most 4 asin(|d q| / 2): 2.9 degrees. norm565
    over [-1, 1] on the same rotations: 2.4x the step (r = 1)."""
    r = CUBE_GAUGE_RANGE
    dxyz = r * math.sqrt(2 / 31 ** 2 + 1 / 63 ** 2)
    bound = math.degrees(4 * math.asin(dxyz * math.sqrt(1 + 3 * r * r) / 2))
    assert 2.8 < bound < 2.95
    err = _angle_deg(cube_rotations, _round_trip(cube_rotations, "cube565"))
    assert err.max() <= bound, (err.max(), bound)
    old = _angle_deg(cube_rotations, _round_trip(cube_rotations, "norm565"))
    assert err.max() < 0.45 * old.max() and err.mean() < 0.45 * old.mean()  # 2.55 / 6.18, 1.29 / 3.08 degrees
    # the same texels as norm565, and the decode the format's formula: c = (2t - 1) r, w derived, normalised
    t = unpack_texels("cube565", pack_texels("cube565", encode_rotations(cube_rotations, "cube565")[:, :3]))
    xyz = (2.0 * t[:, :3].astype(np.float64) - 1.0) * r
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(axis=1)))
    ref = np.concatenate([w[:, None], xyz], axis=1)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(decode_rotations(t, "cube565"), ref, atol=2e-7)


def test_cube565_is_norm565s_texels():
    fmt = get_format("cube565")
    assert fmt.texels == "norm565" and fmt.bits_per_texel == 16 and fmt.levels == (31, 63, 31)
    assert FIELD_LAYOUTS["cube565"] == FIELD_LAYOUTS["norm565"]
    t = np.random.default_rng(1).random((1000, 3)).astype(np.float32)
    np.testing.assert_array_equal(pack_texels("cube565", t), pack_texels("norm565", t))


def test_writer_version_is_1_13_only_with_cube565():
    assert writer_version(LOW) == (1, 13)
    assert writer_version({**LOW, "rotation": "norm565"}) == (1, 2)


def test_the_encoder_stores_cube565_rotations_in_the_cube_gauge():
    assert rotation_gauge("low", resolve_formats("low")) == "cube"
    assert resolve_formats("low")["rotation"] == "cube565"
    # any preset given cube565 rotations stores the gauge the format needs
    assert rotation_gauge("medium", resolve_formats("medium", {"rotation": "cube565"})) == "cube"
    with pytest.raises(UsageError, match="holds only rotation, not scale"):
        resolve_formats("low", {"scale": "cube565"})


@pytest.fixture(scope="module")
def low_scene(tmp_path_factory):
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(700))
    out = tmp_path_factory.mktemp("cube565") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="low", lod=False))
    return g, out, m


def test_a_low_scene_is_1_13_and_keeps_every_covariance_within_the_rotation_error(low_scene):
    g, out, m = low_scene
    assert m.version == (1, 13) and m.formats["rotation"] == "cube565"
    assert msgpack.unpackb((out / "manifest.msgpack").read_bytes(), raw=False)["version"] == [1, 13]
    d = read_manifest_dict(out)  # its tiles as maps (conftest.tile_maps)
    section = next(s for s in d["tiles"][0]["groups"]["base"]["sections"] if s["name"] == "rotation")
    assert section["format"] == "cube565" and section["filter"] == "fields1"
    dec = decode_scene(out)
    assert np.all(dec.rotations[:, 0] >= 0.85)  # in the gauge: w >= 0.854 up to the grid


def test_a_1_12_manifest_naming_cube565_is_rejected(low_scene, tmp_path):
    _, out, _ = low_scene
    d = read_manifest_dict(out)
    d["version"] = [1, 12]
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=r"formats\.rotation.*cube565 is a version 1\.13 texel format"):
        decode_scene(tmp_path / "s")
    r = run_cli("info", tmp_path / "s")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "version 1.13 texel format" in r.stderr


def test_cube565_for_another_attribute_is_rejected(low_scene, tmp_path):
    _, out, _ = low_scene
    d = read_manifest_dict(out)
    d["formats"]["scale"] = "cube565"
    d["version"] = [1, 13]  # tile maps (conftest.tile_maps) in a 1.13 manifest
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=r"formats\.scale.*cube565 holds rotations in the cube gauge"):
        decode_scene(tmp_path / "s")
