"""The texel format norm16x4 (format 1.3, format.md 4.2): bit layout, the version a scene using it is written as,
and readers that reject it in a manifest of an older version. Round-trip error bounds: test_codec_roundtrip.py
(case norm16x4); GPU decode against numpy: test_gl_decode.py; fields1 vectors: test_transport.py."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import read_manifest_dict, real, run_cli, write_manifest_dict

from splatstream.decoder import decode_scene
from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError
from splatstream.format.manifest import writer_version
from splatstream.format.texformats import encode_image, get_format, pack_texels, unpack_texels
from splatstream.io import read_gaussians


def test_bit_layout_is_four_little_endian_u16():
    t = np.array([[[1.0, 0.0, 0.5, 1 / 65535], [0.25, 0.75, 2.0, -1.0]]], np.float32)
    words = encode_image("norm16x4", t).view("<u2").tolist()
    assert words == [65535, 0, 32768, 1, 16384, 49151, 65535, 0]  # round to nearest; outside [0, 1] clamped
    assert encode_image("norm16x4", t)[:2].tolist() == [0xFF, 0xFF]
    back = unpack_texels("norm16x4", pack_texels("norm16x4", t.reshape(-1, 4)))
    assert back[0].tolist() == [1.0, 0.0, np.float32(32768 / 65535), np.float32(1 / 65535)]
    fmt = get_format("norm16x4")
    assert (fmt.bits_per_texel, fmt.gl_internal, fmt.shuffle, fmt.step(0)) == (64, "RGBA16", 2, 1 / 65535)


def test_writer_version_is_1_3_only_where_norm16x4_is_used():
    medium = {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"}
    assert writer_version(medium) == (1, 2)
    assert writer_version({**medium, "position": "norm16x4"}) == (1, 3)
    assert writer_version(medium, "norm16x4") == (1, 3)  # the SH codebook's entries
    assert writer_version(medium, "norm565") == (1, 2)


@pytest.fixture(scope="module")
def norm16_scene(tmp_path_factory):
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(700))
    out = tmp_path_factory.mktemp("n16") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low", overrides={"position": "norm16x4"}, lod=False))
    return out, m


def test_scene_with_norm16x4_positions_is_1_3_and_decodes(norm16_scene):
    out, m = norm16_scene
    assert m.version == (1, 3) and m.formats["position"] == "norm16x4"
    d = read_manifest_dict(out)
    assert d["version"] == [1, 3]
    section = next(s for s in d["tiles"][0]["groups"]["base"]["sections"] if s["name"] == "position")
    assert section["format"] == "norm16x4" and section["filter"] == "fields1"
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(700))
    dec = decode_scene(out)
    # every position within one 1/65535 step of its chunk's range (plus f32 rounding) of an input position
    lo, hi = g.positions.min(axis=0), g.positions.max(axis=0)
    err = np.abs(np.sort(dec.positions, axis=0) - np.sort(g.positions, axis=0)).max(axis=0)
    assert np.all(err <= (hi - lo) / 65535 + 1e-6 * np.abs(g.positions).max()), err


def test_a_1_2_manifest_naming_norm16x4_is_rejected(norm16_scene, tmp_path):
    out, _ = norm16_scene
    d = read_manifest_dict(out)
    d["version"] = [1, 2]
    import shutil

    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=r"formats\.position.*norm16x4 is a version 1\.3 texel format"):
        decode_scene(tmp_path / "s")
    r = run_cli("info", tmp_path / "s")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "version 1.3 texel format" in r.stderr
