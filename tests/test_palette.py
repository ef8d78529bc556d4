"""Palette planes (format 1.6, format.md 4.3.2): the pal8x4 texel format's palettes (exact on at most 256 distinct
values, else a tile-wide 8-bit grid within half its step), scenes written as 1.6 that decode exactly on a SOG input,
the palette section's checks, and the GL client's 16-bit transcode against the numpy decode (test_gl_decode.py:
the shaders on it)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import read_manifest_dict, real, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError, UsageError
from splatstream.format.codec import (
    PALETTE_GPU_FORMAT,
    decode_palette_indices,
    decode_plane,
    encode_plane,
    fit_palette,
    palette_as_ranged,
)
from splatstream.format.container import pack_payload, unpack_payload
from splatstream.format.manifest import writer_version
from splatstream.format.planes import BASE_PLANES, PALETTE_ENTRIES
from splatstream.format.presets import resolve_formats
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene

SCALE, COLOR = BASE_PLANES[2], BASE_PLANES[3]


def test_fit_palette_is_the_distinct_values_when_there_are_at_most_256():
    rng = np.random.default_rng(1)
    values = rng.normal(size=256).astype(np.float32)
    palette = fit_palette(rng.choice(values, 5000))
    assert palette.dtype == np.float32 and palette.shape == (PALETTE_ENTRIES,)
    assert set(palette.tolist()) == set(np.unique(rng.choice(values, 5000)).tolist()) or \
        set(palette.tolist()) <= set(values.tolist())
    few = fit_palette(np.array([3.0, -1.0, 3.0, 0.5], np.float32))
    assert few[:3].tolist() == [-1.0, 0.5, 3.0] and np.all(few[3:] == 3.0)  # entries past them repeat the last


def test_more_than_256_values_get_a_tile_wide_8_bit_grid_within_half_a_step():
    rng = np.random.default_rng(2)
    values = (rng.normal(size=(4000, 1, 3)) * 2 - 3).astype(np.float32)
    plane = encode_plane(values, SCALE, "pal8x4")
    back = decode_plane(plane, len(values))
    step = float(np.ptp(values)) / 255
    assert np.abs(back - values).max() <= step / 2 * (1 + 1e-5)
    assert plane.palette[0, 0] == values.min() and plane.palette[0, -1] == values.max()


def test_palette_planes_round_trip_exactly_on_256_values_through_a_payload():
    rng = np.random.default_rng(3)
    n = 700  # 3 chunks, the last partial
    pal = rng.normal(size=256).astype(np.float32)
    scale = pal[rng.integers(0, 256, (n, 1, 3))] - 4
    color = pal[rng.integers(0, 256, (n, 1, 4))]
    color[:, 0, 3] = rng.integers(0, 201, n) / np.float32(255.0)  # opacity: its own palette, k / 255 as in SOG
    q = rng.normal(size=(n, 1, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=2, keepdims=True)
    order = rng.permutation(n)
    planes = [encode_plane(rng.normal(size=(n, 1, 3)).astype(np.float32), BASE_PLANES[0], "f32x4", order),
              encode_plane(q, BASE_PLANES[1], "f32x4", order),
              encode_plane(scale, SCALE, "pal8x4", order), encode_plane(color, COLOR, "pal8x4", order)]
    assert planes[2].ranges is None and planes[2].palette.shape == (1, PALETTE_ENTRIES)
    assert planes[3].palette.shape == (2, PALETTE_ENTRIES)
    data, entry = pack_payload(planes, level=3)
    sections = {s.name: s for s in entry.sections}
    assert "scale.range" not in sections and "color.range" not in sections
    assert (sections["color.palette"].kind, sections["color.palette"].dtype, sections["color.palette"].shape) == \
        ("range", "f32", (2, 1, 1, 256))
    back = unpack_payload(data, entry, "base", "x")
    np.testing.assert_array_equal(decode_plane(back["scale"], n), scale[order])
    np.testing.assert_array_equal(decode_plane(back["color"], n), color[order])
    idx = decode_palette_indices(back["scale"], n)
    assert idx.max() < 256 and np.array_equal(back["scale"].palette[0][idx[:, :3]], scale[order][:, 0])


def test_palettes_hold_scale_and_colour_only():
    assert resolve_formats("medium-low", {"scale": "pal8x4", "color": "pal8x4"})["scale"] == "pal8x4"
    for attr in ("position", "rotation", "sh"):
        with pytest.raises(UsageError, match="palette indices"):
            resolve_formats("medium-low", {attr: "pal8x4"})
    base = resolve_formats("medium-low-12bit")
    assert writer_version(base) == (1, 3) and writer_version({**base, "scale": "pal8x4"}) == (1, 6)


@pytest.fixture(scope="module")
def sog_scene(tmp_path_factory):
    """A statue scan (a SOG file: 256 log scales, 256 SH0 values, 201 opacities) at medium-low-12bit with palettes."""
    g = read_gaussians(real("statues/massa.sog"))
    g = g.subset(np.arange(3000))
    out = tmp_path_factory.mktemp("pal") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit",
                                               overrides={"scale": "pal8x4", "color": "pal8x4"}, lod=False))
    return g, out, m


def test_a_sog_input_decodes_exactly_from_a_1_6_scene(sog_scene):
    g, out, m = sog_scene
    assert m.version == (1, 6) and m.formats["scale"] == m.formats["color"] == "pal8x4"
    assert len(np.unique(g.log_scales)) <= 256 and len(np.unique(g.sh_dc)) <= 256
    d = decode_scene(out)
    # the encoder reorders splats: compare the values as multisets (exact; opacity through sigmoid and logit)
    np.testing.assert_array_equal(np.sort(d.log_scales.ravel()), np.sort(g.log_scales.ravel()))
    np.testing.assert_array_equal(np.sort(d.sh_dc.ravel()), np.sort(g.sh_dc.ravel()))
    np.testing.assert_allclose(np.sort(d.opacities), np.sort(g.opacities), atol=2e-7)


def test_a_1_5_manifest_naming_pal8x4_is_rejected(sog_scene, tmp_path):
    _, out, _ = sog_scene
    d = read_manifest_dict(out)
    d["version"] = [1, 5]
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match=r"formats\.scale.*pal8x4 is a version 1\.6 texel format"):
        decode_scene(tmp_path / "s")


def test_a_non_finite_or_out_of_domain_palette_is_rejected():
    from splatstream.format.container import _check_palette

    _check_palette(np.zeros((1, 256), np.float32), "scale", "scale.palette", "x")
    with pytest.raises(FormatError, match="non-finite palette"):
        _check_palette(np.full((1, 256), np.nan, np.float32), "scale", "scale.palette", "x")
    with pytest.raises(FormatError, match="leaves the scale domain"):
        _check_palette(np.full((1, 256), 50.0, np.float32), "scale", "scale.palette", "x")


def test_the_gpu_transcode_is_within_half_a_16_bit_step_of_the_palette_values():
    rng = np.random.default_rng(4)
    n = 700
    pal = np.sort(rng.normal(size=256)).astype(np.float32) * 3 - 4
    values = pal[rng.integers(0, 256, (n, 1, 3))]
    plane = encode_plane(values, SCALE, "pal8x4")
    ranged = palette_as_ranged(plane, n)
    assert ranged.format == PALETTE_GPU_FORMAT and ranged.ranges.dtype == np.float16
    assert (ranged.width, ranged.height) == (plane.width, plane.height)
    r = ranged.ranges.astype(np.float64)
    extent = (r[:, 1] - r[:, 0]).max()
    assert np.abs(decode_plane(ranged, n) - decode_plane(plane, n)).max() <= extent / 65535 / 2 + 1e-6
    assert palette_as_ranged(ranged, n) is ranged  # any other plane as it is
