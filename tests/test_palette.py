"""Palette planes (format 1.6, format.md 4.3.2): the pal8x4 texel format's palettes (exact on at most 256 distinct
values, else a tile-wide 8-bit grid within half its step), scene palettes in the manifest (1.7) and per-tile
palettes (1.6) that decode exactly on a SOG input, LOD tiles indexed into the scene's palettes within half their
largest gap, the palette checks, and the GL client's 16-bit transcode against the numpy decode (test_gl_decode.py:
the shaders on it)."""
from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest
from conftest import read_manifest_dict, real, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.encode import plan as encode_plan
from splatstream.errors import FormatError, UsageError
from splatstream.format import keyed, transport
from splatstream.format.codec import (
    PALETTE_GPU_FORMAT,
    PaletteValues,
    decode_palette_indices,
    decode_plane,
    encode_plane,
    fit_palette,
    palette_as_ranged,
    plane_values,
)
from splatstream.format.container import pack_payload, unpack_payload
from splatstream.format.decode import decode_payload, decode_payloads
from splatstream.format.manifest import pack_manifest, writer_version
from splatstream.format.names import MANIFEST_NAME
from splatstream.format.planes import BASE_PLANES, PALETTE_ENTRIES
from splatstream.format.presets import resolve_formats
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene
from splatstream.store import DirectoryStore, load_manifest

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


PAL = {"scale": "pal8x4", "color": "pal8x4"}


def _sog_input():
    """The first 3000 splats of a statue scan (a SOG file: 256 log scales, 256 SH0 values, 201 opacities)."""
    return read_gaussians(real("statues/massa.sog")).subset(np.arange(3000))


@pytest.fixture(scope="module")
def sog_scene(tmp_path_factory):
    """The SOG input at medium-low-12bit with palettes, one tile (the encoder's scene palettes: 1.7)."""
    g = _sog_input()
    out = tmp_path_factory.mktemp("pal") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit", overrides=PAL, lod=False))
    return g, out, m


@pytest.fixture(scope="module")
def sog_lod_scene(tmp_path_factory):
    """The SOG input with palettes in an LOD tree (leaves of at most 400 splats): scene palettes (1.7)."""
    g = _sog_input()
    out = tmp_path_factory.mktemp("pal") / "lod"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit", overrides=PAL, max_leaf_splats=400,
                                               transport="keyed"))
    return g, out, m


@pytest.fixture(scope="module")
def tile_palette_scene(tmp_path_factory):
    """The same LOD encode with per-tile palettes (format 1.6, as the encoder wrote it before scene palettes)."""
    g = _sog_input()
    out = tmp_path_factory.mktemp("pal") / "tiles"
    fit = encode_plan.scene_palettes
    encode_plan.scene_palettes = lambda parts: None
    try:
        m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit", overrides=PAL, max_leaf_splats=400,
                                                   transport="keyed", short_digests=False))
    finally:
        encode_plan.scene_palettes = fit
    # its manifest as a 1.6 writer wrote it (tile maps; today's encoder writes an LOD tree's as 1.8 tile tables)
    m = replace(m, version=(1, 6), lod=replace(m.lod, merge=None, viewing_scale_px=None))
    m = m.with_bytes_on_disk(m.payload_bytes())
    (out / MANIFEST_NAME).write_bytes(pack_manifest(m))
    return g, out, load_manifest(out)


def _assert_exact(g, d):
    # the encoder reorders splats: compare the values as multisets (exact; opacity through sigmoid and logit)
    np.testing.assert_array_equal(np.sort(d.log_scales.ravel()), np.sort(g.log_scales.ravel()))
    np.testing.assert_array_equal(np.sort(d.sh_dc.ravel()), np.sort(g.sh_dc.ravel()))
    np.testing.assert_allclose(np.sort(d.opacities), np.sort(g.opacities), atol=2e-7)


def _palette_sections(m, leaves_only=False) -> int:
    return sum(s.name.endswith(".palette") for t in m.tiles if t.is_leaf or not leaves_only
               for e in t.groups.values() for s in e.sections)


def test_a_sog_input_decodes_exactly_from_a_scene_with_scene_palettes(sog_scene):
    g, out, m = sog_scene
    assert m.version == (1, 7) and m.formats["scale"] == m.formats["color"] == "pal8x4"
    assert len(np.unique(g.log_scales)) <= 256 and len(np.unique(g.sh_dc)) <= 256
    assert sorted(m.palettes) == ["color", "scale"] and len(m.palettes["scale"]) == 1024
    assert len(m.palettes["color"]) == 2048
    assert _palette_sections(m) == 0  # stored once, in the manifest
    # the scene's palettes are the input's distinct values (entries past them repeat the last)
    pal = m.scene_palettes
    distinct = np.unique(g.log_scales)
    np.testing.assert_array_equal(pal["scale"][0, :len(distinct)], distinct)
    assert np.all(pal["scale"][0, len(distinct):] == distinct[-1])
    _assert_exact(g, decode_scene(out))


def test_lod_leaves_decode_exactly_and_payloads_carry_no_palettes(sog_lod_scene):
    g, out, m = sog_lod_scene
    assert m.version == (1, 16) and len(m.tiles) > 3 and m.palettes  # 1.7 palettes, 1.10 lod, 1.16 compact table
    assert _palette_sections(m, leaves_only=True) == 0
    _assert_exact(g, decode_scene(out))


def test_lod_tiles_inside_the_scene_palettes_are_within_half_their_largest_gap(sog_lod_scene):
    """An interior tile's merged values leave the input's palette: indexed into the scene's (no section of its own)
    when they lie within it, within half the largest gap between neighbouring entries; outside, the tile keeps its
    own palette section (1.6's rule for that payload)."""
    g, out, m = sog_lod_scene
    tiles = encode_plan.plan_encode(g, EncodeOptions(preset="medium-low-12bit", overrides=PAL, max_leaf_splats=400,
                                                     transport="keyed")).tiles
    pal = m.scene_palettes["scale"][0].astype(np.float64)
    half_gap = np.diff(pal).max() / 2
    checked = 0
    for tile, entry in zip(sorted(tiles, key=lambda t: t.id), m.tiles, strict=True):
        values = plane_values(tile.gaussians, SCALE)
        inside = values.min() >= pal.min() and values.max() <= pal.max()
        own = any(s.name == "scale.palette" for s in entry.groups["base"].sections)
        assert own == (not inside)
        if inside and not entry.is_leaf:
            d = decode_scene(out, tiles=[entry.id])
            # the decoded values as a multiset, each within half the largest gap of one of the tile's values
            got, want = np.sort(d.log_scales.ravel()), np.sort(values.ravel())
            assert np.abs(got - want).max() <= half_gap + 1e-6
            checked += 1
    assert checked >= 1


def test_a_paged_scene_keeps_its_palettes_in_the_root_manifest(tmp_path):
    """format.md 6.1: the pages' tiles index the root manifest's palettes."""
    g = _sog_input()
    out = tmp_path / "paged"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit", overrides=PAL, max_leaf_splats=400,
                                               page_tiles=4, page_levels=1))
    assert m.paged is not None and m.version == (1, 16) and m.palettes
    _assert_exact(g, decode_scene(out))


def test_a_1_6_scene_with_per_tile_palettes_still_reads_exactly(tile_palette_scene, sog_lod_scene):
    g, out, m = tile_palette_scene
    assert m.version == (1, 6) and m.palettes is None
    assert _palette_sections(m) == 2 * len(m.tiles)
    _assert_exact(g, decode_scene(out))
    # scene palettes make the tree smaller: the same splats, the palettes stored once
    assert sog_lod_scene[2].bytes_on_disk < m.bytes_on_disk


def test_palette_values_joined_part_by_part_fit_the_palette_of_the_whole():
    """encode/sample.py: the partitioned encoder gathers the values chunk by chunk."""
    rng = np.random.default_rng(5)
    few = rng.normal(size=200).astype(np.float32)[rng.integers(0, 200, 3000)]
    many = rng.normal(size=3000).astype(np.float32)
    for values in (few, many):
        parts = [PaletteValues.of(p) for p in np.array_split(values, 7)]
        np.testing.assert_array_equal(PaletteValues.join(parts).palette(), fit_palette(values))
    # parts of at most 256 each that together hold more
    a, b = np.arange(200, dtype=np.float32), np.arange(200, 400, dtype=np.float32)
    np.testing.assert_array_equal(PaletteValues.join([PaletteValues.of(a), PaletteValues.of(b)]).palette(),
                                  fit_palette(np.concatenate([a, b])))


def test_a_partitioned_encode_fits_the_same_scene_palettes(tmp_path):
    """The partitioned encoder (chunks of the input, encode/sample.py's palette values) writes the bytes of the
    single-process encode, scene palettes included."""
    from splatstream.encode import encode_in_memory
    from splatstream.encode.local import LocalEngine
    from splatstream.encode.partitioned import ArrayRows, encode_partitioned
    from splatstream.encode.scratch import Scratch
    from splatstream.store import MemoryWriter

    g = _sog_input()
    # the grid named: the same bytes in memory and by partitions for any partitioning (auto: by merge domains)
    opts = EncodeOptions(preset="medium-low-12bit", overrides=PAL, max_leaf_splats=400, lod_merge="grid")
    ref = encode_in_memory(g, opts, name="s")
    writer = MemoryWriter("s")
    space = Scratch.create(str(tmp_path))
    m = encode_partitioned(ArrayRows(g), writer, opts, LocalEngine(200_000), space, source_name="s")
    space.remove()
    got = writer.store()
    assert m.palettes and got.manifest_bytes == ref.manifest_bytes and got.payloads == ref.payloads


def test_scene_palettes_are_checked_with_the_manifest(sog_scene, tmp_path):
    _, out, _ = sog_scene
    cases = [
        (lambda d: d["palettes"].__setitem__("scale", d["palettes"]["scale"][:-4]), r"palettes\.scale.*bin of 1024"),
        (lambda d: d["palettes"].__setitem__("scale", np.full(256, np.nan, "<f4").tobytes()), "non-finite"),
        (lambda d: d["palettes"].__setitem__("scale", np.full(256, 50.0, "<f4").tobytes()), "leaves the scale"),
        (lambda d: d["palettes"].__setitem__("position", bytes(1024)), r"palettes\.position.*names no"),
        (lambda d: d["palettes"].pop("scale"), r"missing section 'scale\.palette'"),
        (lambda d: d.__setitem__("version", [1, 6]), "unknown key 'palettes'"),
    ]
    for i, (damage, message) in enumerate(cases):
        d = read_manifest_dict(out)
        damage(d)
        shutil.copytree(out, tmp_path / f"s{i}")
        write_manifest_dict(tmp_path / f"s{i}", d)
        with pytest.raises(FormatError, match=message):
            decode_scene(tmp_path / f"s{i}")


def test_a_1_5_manifest_naming_pal8x4_is_rejected(sog_scene, tmp_path):
    _, out, _ = sog_scene
    d = read_manifest_dict(out)
    d["version"] = [1, 5]
    d.pop("palettes")  # a 1.7 key: a 1.5 manifest fails on it first
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


@pytest.mark.parametrize("scene", ["sog_lod_scene", "tile_palette_scene"])
def test_palette_and_keyed_payloads_decode_alike_with_the_compiled_kernels(scene, request):
    # with the whole kernel a group of palette planes and morton1 positions goes through one call
    # (container._unpack_group), as every other group does: the same planes, bit for bit, as the numpy path's
    decode_jit = pytest.importorskip("client_gl.stream.decode_jit", reason="numba (the `fast` extra)")
    _, out, m = request.getfixturevalue(scene)
    store = DirectoryStore(out)
    groups: dict[str, list] = {}
    for t in m.tiles:
        for group, entry in t.groups.items():
            groups.setdefault(group, []).append((store.read_payload(entry), entry))
    filters = {s.filter for items in groups.values() for _, e in items for s in e.sections}
    formats = {s.format for items in groups.values() for _, e in items for s in e.sections}
    assert keyed.MORTON1 in filters and "pal8x4" in formats

    def planes(decoded):
        got = []
        for name, p in decoded.items():
            got.append((name, p.format, p.width, p.height, p.scene_palette))
            got += [np.asarray(a).tobytes() for a in p.layers]
            got += [None if a is None else (a.dtype.str, a.shape, a.tobytes()) for a in (p.ranges, p.palette)]
        return got

    def decode_all():
        got = []
        for group, items in groups.items():
            got += [planes(decode_payload(d, e, group, "t", palettes=m.scene_palettes)) for d, e in items]
            got += [planes(p) for p in decode_payloads(items, group, ["t"] * len(items), palettes=m.scene_palettes)]
        return got

    saved = (transport.use_fields_kernel(None), transport.use_unshuffle_kernel(None),
             transport.use_batch_kernels(None, None), transport.use_whole_kernel(None), keyed.use_morton_kernel(None))
    try:
        by_numpy = decode_all()
        decode_jit.install()
        assert decode_all() == by_numpy
    finally:
        transport.use_fields_kernel(saved[0])
        transport.use_unshuffle_kernel(saved[1])
        transport.use_batch_kernels(*saved[2])
        transport.use_whole_kernel(saved[3])
        keyed.use_morton_kernel(saved[4])
