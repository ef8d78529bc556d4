"""The texel formats of format 1.3, norm16x4 and norm9x3 (format.md 4.2): bit layouts, norm9x3's five zero bits that
no fields1 field holds, the version a scene using them is written as, scenes that decode within one step, and
readers that reject them in a manifest of an older version. Round-trip error bounds of every attribute:
test_codec_roundtrip.py; GPU decode against numpy: test_gl_decode.py and test_gl_codebook.py; fields1 vectors:
test_transport.py."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import read_manifest_dict, real, run_cli, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError
from splatstream.format.manifest import writer_version
from splatstream.format.texformats import encode_image, get_format, pack_texels, unpack_texels
from splatstream.format.transport import FIELD_LAYOUTS, fields_content, filter_texels, unfilter_fields, unused_bits
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene

FORMATS_1_3 = {"norm16x4": 65535, "norm9x3": 511}  # format -> levels (a step is 1 / levels of the chunk's range)


def test_bit_layout_is_four_little_endian_u16():
    t = np.array([[[1.0, 0.0, 0.5, 1 / 65535], [0.25, 0.75, 2.0, -1.0]]], np.float32)
    words = encode_image("norm16x4", t).view("<u2").tolist()
    assert words == [65535, 0, 32768, 1, 16384, 49151, 65535, 0]  # round to nearest; outside [0, 1] clamped
    assert encode_image("norm16x4", t)[:2].tolist() == [0xFF, 0xFF]
    back = unpack_texels("norm16x4", pack_texels("norm16x4", t.reshape(-1, 4)))
    assert back[0].tolist() == [1.0, 0.0, np.float32(32768 / 65535), np.float32(1 / 65535)]
    fmt = get_format("norm16x4")
    assert (fmt.bits_per_texel, fmt.gl_internal, fmt.shuffle, fmt.step(0)) == (64, "RGBA16", 2, 1 / 65535)


def test_bit_layout_is_three_9_bit_fields_in_a_little_endian_u32():
    t = np.array([[[1.0, 0.0, 0.5, 0.7], [1 / 511, 2.0, -1.0, 1.0], [0.25, 0.75, 1.0, 0.0]]], np.float32)
    words = encode_image("norm9x3", t).view("<u4").tolist()
    # round to nearest (0.5 * 511 + 0.5 = 256; 0.25 -> 128, 0.75 -> 383.75 -> 383); outside [0, 1] clamped; no 4th
    assert words == [511 | (0 << 9) | (256 << 18), 1 | (511 << 9) | (0 << 18), 128 | (383 << 9) | (511 << 18)]
    assert encode_image("norm9x3", t)[:4].tolist() == [0xFF, 0x01, 0x00, 0x04]  # R = 511 spills into byte 1 bit 0
    assert max(w >> 27 for w in words) == 0
    back = unpack_texels("norm9x3", pack_texels("norm9x3", t.reshape(-1, 4)))
    assert back[0].tolist() == [1.0, 0.0, np.float32(256 / 511), 0.0]
    assert back[1].tolist() == [np.float32(1 / 511), 1.0, 0.0, 0.0]
    fmt = get_format("norm9x3")
    assert (fmt.bits_per_texel, fmt.components, fmt.gl_internal, fmt.shuffle) == (32, 3, "R32UI", 4)
    assert [fmt.step(c) for c in range(3)] == [1 / 511] * 3
    assert FIELD_LAYOUTS["norm9x3"] == ("<u4", 1, ((0, 9), (9, 9), (18, 9))) and unused_bits("norm9x3") == 0xF8000000


def test_unused_bits_are_ignored_by_the_decoder_and_refused_by_fields1():
    words = np.array([511 | (3 << 9) | (7 << 18)] * 256, "<u4")
    dirty = words | np.uint32(0xF8000000)
    np.testing.assert_array_equal(unpack_texels("norm9x3", dirty), unpack_texels("norm9x3", words))
    with pytest.raises(ValueError, match="norm9x3 texels with bits outside their fields"):
        filter_texels([dirty.view(np.uint8)], "norm9x3", 16, 16, 1)
    content, _ = fields_content(words.view(np.uint8), "norm9x3", 16, 16, 1)
    assert unfilter_fields(content, "norm9x3", 16, 16, 1).tobytes() == words.tobytes()  # bits 27-31 back as 0


@pytest.mark.parametrize("fmt", FORMATS_1_3)
def test_writer_version_is_1_3_only_where_a_1_3_format_is_used(fmt):
    medium_low = {"position": "norm11", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                  "sh": "norm565"}
    assert writer_version(medium_low) == (1, 2)
    assert writer_version({**medium_low, "position": fmt}) == (1, 3)
    assert writer_version({**medium_low, "scale": fmt}) == (1, 3)
    assert writer_version(medium_low, fmt) == (1, 3)  # the SH codebook's entries
    assert writer_version(medium_low, "norm565") == (1, 2)


@pytest.fixture(scope="module", params=list(FORMATS_1_3))
def scene_1_3(request, tmp_path_factory):
    """(format, input, scene directory, manifest): medium-low with positions in a 1.3 format."""
    fmt = request.param
    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(700))
    out = tmp_path_factory.mktemp(fmt) / "s"
    # the rotation format given: medium-low would measure fruit_drops' rotations closer in cube8x4 (1.14, cube32)
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low", overrides={"position": fmt, "rotation": "norm8x4"},
                                               lod=False))
    return fmt, g, out, m


def test_scene_with_1_3_positions_is_1_3_and_decodes_within_one_step(scene_1_3):
    fmt, g, out, m = scene_1_3
    assert m.version == (1, 3) and m.formats["position"] == fmt
    d = read_manifest_dict(out)
    assert d["version"] == [1, 3]
    section = next(s for s in d["tiles"][0]["groups"]["base"]["sections"] if s["name"] == "position")
    assert section["format"] == fmt and section["filter"] == "fields1"
    dec = decode_scene(out)
    # every decoded position within one step of the scene's extent (a chunk's range is inside it), plus f32 rounding,
    # of the input position it came from (nearest input point: the encoder reorders splats)
    lo, hi = g.positions.min(axis=0), g.positions.max(axis=0)
    dist = np.abs(dec.positions[:, None, :] - g.positions[None, :, :])
    nearest = dist.max(axis=2).argmin(axis=1)
    err = np.abs(dec.positions - g.positions[nearest]).max(axis=0)
    assert np.all(err <= (hi - lo) / FORMATS_1_3[fmt] + 1e-6 * np.abs(g.positions).max()), err
    if fmt == "norm9x3":
        assert np.all(err > 0)  # a 9-bit grid: not lossless


def test_a_1_2_manifest_naming_a_1_3_format_is_rejected(scene_1_3, tmp_path):
    fmt, _, out, _ = scene_1_3
    d = read_manifest_dict(out)
    d["version"] = [1, 2]
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=rf"formats\.position.*{fmt} is a version 1\.3 texel format"):
        decode_scene(tmp_path / "s")
    r = run_cli("info", tmp_path / "s")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "version 1.3 texel format" in r.stderr
