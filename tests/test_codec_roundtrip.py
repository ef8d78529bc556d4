"""Round trip of every preset and attribute on the real scenes: error within one quantisation step per chunk
(BC formats: bounded RMS error), and SH bands that decode on their own."""
from dataclasses import replace

import numpy as np
import pytest
from conftest import REAL_PLYS, group_planes_of, real

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.encode.jobs import splat_order, tile_order
from splatstream.encode.plan import plan_encode
from splatstream.format.codec import decode_plane, plane_values, rotation_mode
from splatstream.format.decode import decode_planes
from splatstream.format.layout import CHUNK_SIZE, morton_order
from splatstream.format.planes import band_plane, group_planes, groups_for_degree
from splatstream.format.presets import PRESETS, preset_transport, resolve_chunk_order
from splatstream.format.texformats import get_format
from splatstream.ply import read_gaussians_ply
from splatstream.rotation_canon import canonical_gauge
from splatstream.scene_decode import decode_scene
from splatstream.store import load_manifest

# RMS error bounds for block-compressed planes, in normalised units (t; quaternion components for rotations).
# Measured on the three real scenes (worst: 0.093 t, 0.29 for BC7 rotations) plus a margin.
BC_RMS_BOUND = {"bc7": 0.12, "bc1": 0.12, "rotation": 0.35}


@pytest.fixture(scope="module", params=REAL_PLYS)
def scene(request):
    g = read_gaussians_ply(real(request.param))
    return request.param, g.subset(morton_order(g.positions))


# Every preset, and every attribute in the 16-bit unorm format (format 1.3; `medium` has no SH codebook, so the SH
# bands are norm16x4 planes too, and its rotation is the smallest-three of 4.5 with L_A = 65535).
ALL_NORM16 = dict.fromkeys(("position", "rotation", "scale", "color", "sh"), "norm16x4")
# 9-bit grids (format 1.3) for every three-component attribute (rotation: the xyz mode of 4.5); colour needs four
ALL_NORM9 = {**dict.fromkeys(("position", "rotation", "scale", "sh"), "norm9x3"), "color": "norm8x4"}
ROUND_TRIP_CASES = [pytest.param(p, {}, id=p) for p in PRESETS] + [
    pytest.param("medium", ALL_NORM16, id="norm16x4"), pytest.param("medium", ALL_NORM9, id="norm9x3")]


@pytest.mark.parametrize("preset,overrides", ROUND_TRIP_CASES)
def test_every_attribute_round_trips_within_one_step(scene, preset, overrides, tmp_path):
    name, g = scene
    if any(get_format(f).block > 1 for f in {**PRESETS[preset], **overrides}.values()):
        pytest.importorskip("etcpak")
    opts = EncodeOptions(preset=preset, overrides=overrides, lod=False)
    m = encode_gaussians(g, tmp_path / "s", opts)
    # 1.3 where a texel format of 1.3 is used (norm16x4, or norm9x3: the override or medium-low-9bit's positions)
    if "cube8x4" in m.formats.values():  # the measured choice of ranged rotations (format 1.14, 4.5; the latest
        assert m.version == (1, 14)          # version a scene needs is its own: keyed medium-low-palette too)
    elif preset_transport(preset, "fields") == "keyed":  # morton1 sections (1.6), scene palettes (1.7)
        assert m.version == ((1, 7) if m.palettes else (1, 6))
    elif "cube565" in m.formats.values():  # the cube gauge's ranged rotations (format 1.13, 4.5)
        assert m.version == (1, 13)
    else:
        assert m.version == ((1, 3) if {"norm16x4", "norm9x3"} & set(m.formats.values()) else (1, 2))
    assert all(m.formats[a] == f for a, f in overrides.items())
    context = plan_encode(g, opts).context
    g = g.subset(tile_order(g, context))  # the order the encoder stored
    if context.rotation_gauge:  # the equivalent rotations and scales it stored (tests/test_rotation_canon.py)
        rotations, log_scales = canonical_gauge(g.rotations, g.log_scales, context.rotation_gauge)
        g = replace(g, rotations=rotations, log_scales=log_scales)
    tile = m.tiles[0]
    n = len(g)
    assert tile.splats == n and m.splats == n
    chunk = np.arange(n) // CHUNK_SIZE
    assert m.sh_degree == g.sh_degree
    codebook = m.uses_codebook  # its planes and indices: tests/test_sh_codebook.py
    for group in groups_for_degree(m.sh_degree, codebook):
        planes = group_planes_of(tmp_path / "s", m, tile, group)
        for spec in group_planes(group, codebook):
            if spec.name == "sh_index":
                continue
            plane = planes[spec.name]
            fmt = get_format(plane.format)
            orig = plane_values(g, spec)
            dec = decode_plane(plane, n)
            assert dec.shape == orig.shape
            if not spec.range_dtype:  # rotation: compare up to the sign of the quaternion
                err = np.minimum(np.abs(dec[:, 0] - orig[:, 0]).max(1), np.abs(dec[:, 0] + orig[:, 0]).max(1))
                mode = rotation_mode(plane.format)
                if fmt.block > 1:
                    rms = float(np.sqrt(np.mean(err ** 2)))
                    assert rms < BC_RMS_BOUND["rotation"], (name, preset, spec.name, rms)
                elif mode == "full":
                    assert err.max() <= 2 * fmt.step(0) + 1e-6
                elif mode == "xyz":  # stored x, y, z within one step (of 2 r units); w is derived, bounded in RMS
                    q = orig[:, 0] * np.where(orig[:, 0, :1] < 0, -1, 1)
                    xyz_err = np.abs(dec[:, 0, 1:] - q[:, 1:]).max(1)
                    steps = np.array([fmt.step(c) for c in range(3)]) * fmt.rotation_range
                    assert np.all(xyz_err <= 2 * steps.max() + 1e-6), (name, preset, xyz_err.max())
                    assert np.sqrt(np.mean(err ** 2)) < 0.08, (name, preset, spec.name)  # measured 0.059
                else:  # smallest three: stored components within one step, the derived one within a few
                    assert err.max() <= 3 * np.sqrt(2) * fmt.step(0), (name, preset, err.max())
                continue
            lo = plane.ranges[:, 0].astype(np.float32)[chunk]
            hi = plane.ranges[:, 1].astype(np.float32)[chunk]
            assert np.all(lo <= orig + 1e-7) and np.all(orig <= hi + 1e-7), "ranges must contain the values"
            extent = hi - lo
            for c in range(spec.components):
                e = np.abs(dec[..., c] - orig[..., c])
                if fmt.block > 1:
                    t_err = np.divide(e, extent[..., c], out=np.zeros_like(e), where=extent[..., c] > 0)
                    rms = float(np.sqrt(np.mean(t_err ** 2)))
                    assert rms < BC_RMS_BOUND[fmt.name], (name, preset, spec.name, c, rms)
                else:
                    bound = fmt.step(c) * extent[..., c] + 1e-6 * np.maximum(np.abs(lo[..., c]), np.abs(hi[..., c]))
                    assert np.all(e <= bound + 1e-9), (name, preset, spec.name, c, float((e - bound).max()))


def test_sh_bands_decode_independently(tmp_path):
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    g = g.subset(morton_order(g.positions))
    encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="high", lod=False))
    m = load_manifest(tmp_path / "s")
    tile = m.tiles[0]
    for band in (3, 1, 2):  # any order, each on its own
        values = decode_planes(group_planes_of(tmp_path / "s", m, tile, f"sh{band}"), len(g))
        assert list(values) == [f"sh{band}"]
        assert np.abs(values[f"sh{band}"] - g.band(band)).max() < 2e-3 * max(1.0, np.abs(g.band(band)).max())
    base = decode_scene(tmp_path / "s", sh_degree=0)
    assert base.sh_degree == 0 and len(base) == len(g)
    assert band_plane(2).layers == 5


def test_decode_scene_matches_input_order_and_values(tmp_path):
    g = read_gaussians_ply(real("donut_sh0_no_normals.ply"))
    encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="very-high", lod=False))  # one tile: Morton order
    d = decode_scene(tmp_path / "s")
    ordered = g.subset(morton_order(g.positions))
    assert np.allclose(d.positions, ordered.positions, atol=1e-6)
    assert np.allclose(d.opacities, ordered.opacities, atol=1e-6)
    assert d.sh_degree == 0


def test_luminance_chunk_order_keeps_chunk_membership():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    morton = splat_order(g, "morton")
    lum = splat_order(g, "luminance")
    assert resolve_chunk_order("auto", PRESETS["low"]) == "morton"  # norm8x4 colour since format 1.2
    assert resolve_chunk_order("auto", PRESETS["very-low"]) == "luminance"
    assert resolve_chunk_order("auto", {**PRESETS["low"], "color": "bc7"}) == "luminance"
    assert resolve_chunk_order("auto", {**PRESETS["low"], "color": "bc7", "position": "bc7"}) == "morton"
    assert resolve_chunk_order("auto", PRESETS["medium"]) == "morton"
    for c in range(0, len(g), CHUNK_SIZE):
        assert set(morton[c:c + CHUNK_SIZE].tolist()) == set(lum[c:c + CHUNK_SIZE].tolist())
        y = g.base_colors[lum[c:c + CHUNK_SIZE]] @ np.array([0.299, 0.587, 0.114], np.float32)
        assert np.all(np.diff(y) >= 0)
