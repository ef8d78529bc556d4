"""The morton1 coding of norm16x4 position sections (format.md 5.4, version 1.6): exact round trip of any texels,
the encoder's in-chunk key order, its choice against fields1, the version it writes, and the manifest's checks."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import read_manifest_dict, real, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError
from splatstream.format.decode import decode_payload
from splatstream.format.keyed import KEY_BYTES, compact_bits, morton_content, morton_keys, spread_bits, unfilter_morton
from splatstream.format.layout import CHUNK_SIZE, chunk_texel_index
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene
from splatstream.store import open_store


def test_keys_interleave_x_y_z_from_bit_0():
    codes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 0], [0xFFFF, 0xFFFF, 0xFFFF]])
    assert morton_keys(codes).tolist() == [1, 2, 4, 9, (1 << 48) - 1]
    v = np.random.default_rng(0).integers(0, 1 << 16, 1000)
    np.testing.assert_array_equal(compact_bits(spread_bits(v)), v)


@pytest.mark.parametrize("high", [1 << 16, 40])
def test_any_texels_round_trip_exactly(high):
    rng = np.random.default_rng(high)
    width, height = 48, 32
    words = rng.integers(0, high, (width * height, 4)).astype("<u2")  # the fourth component too
    layer = words.reshape(-1).view(np.uint8)
    parts = morton_content(layer, width, height)
    assert len(parts) == KEY_BYTES + 2 and all(p.size == width * height for p in parts)
    stored = np.concatenate(parts)
    assert stored.size == layer.size  # exactly the texels' size
    np.testing.assert_array_equal(unfilter_morton(stored, width, height), layer)


@pytest.fixture(scope="module")
def keyed_scene(tmp_path_factory):
    g = read_gaussians(real("statues/massa.sog")).subset(np.arange(6000))
    out = tmp_path_factory.mktemp("keyed") / "s"
    m = encode_gaussians(g, out, EncodeOptions(preset="medium-low-12bit", lod=False, transport="keyed"))
    plain = tmp_path_factory.mktemp("plain") / "s"
    encode_gaussians(g, plain, EncodeOptions(preset="medium-low-12bit", lod=False))
    return g, out, m, plain


def test_the_keyed_transport_stores_sorted_keys_as_morton1_and_writes_1_6(keyed_scene):
    g, out, m, plain = keyed_scene
    sections = {s.name: s for s in m.tiles[0].groups["base"].sections}
    assert sections["position"].filter == "morton1" and m.version == (1, 6)
    d, p = decode_scene(out), decode_scene(plain)
    # the same splats (the order inside chunks differs): sort both by position and compare every attribute
    a, b = np.lexsort(d.positions.T), np.lexsort(p.positions.T)
    for name in ("positions", "rotations", "log_scales", "sh_dc", "opacity_logits"):
        np.testing.assert_array_equal(getattr(d, name)[a], getattr(p, name)[b])
    # every chunk's splats in key order of their stored codes
    store = open_store(out)
    entry = m.tiles[0].groups["base"]
    plane = decode_payload(store.read_payload(entry), entry, "base", "s")["position"]
    n = m.tiles[0].splats
    codes = np.frombuffer(plane.layers[0], "<u2").reshape(-1, 4)[chunk_texel_index(-(-n // 256), plane.width)[:n]]
    keys = morton_keys(codes).astype(np.int64)
    full = n // CHUNK_SIZE * CHUNK_SIZE
    assert np.all(np.diff(keys[:full].reshape(-1, CHUNK_SIZE), axis=1) >= 0)
    plain_m = read_manifest_dict(plain)
    assert plain_m["version"] == [1, 3]  # the default transport (fields) keeps norm16x4 scenes as they were
    assert all(s["filter"] != "morton1" for s in plain_m["tiles"][0]["groups"]["base"]["sections"])
    assert m.attributes["position"].disk_bytes < 0.97 * plain_m["attributes"]["position"]["disk_bytes"]


def test_morton1_applies_to_one_norm16x4_layer_only(keyed_scene, tmp_path):
    _, out, _, _ = keyed_scene
    d = read_manifest_dict(out)
    sections = d["tiles"][0]["groups"]["base"]["sections"]
    rot = next(s for s in sections if s["name"] == "rotation")
    rot["filter"] = "morton1"
    shutil.copytree(out, tmp_path / "s")
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match="morton1 applies to one layer of norm16x4 only"):
        decode_scene(tmp_path / "s")


def test_a_paged_keyed_scene_writes_its_pages_at_its_own_version(tmp_path):
    """format.md 6.1: a page's version is its root manifest's; a 1.6 scene's pages were written as 1.5 (and every
    reader refused them) before the pages took the scene's version."""
    g = read_gaussians(real("statues/massa.sog")).subset(np.arange(3000))
    m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium-low-12bit", transport="keyed",
                                                          max_leaf_splats=400, page_tiles=4, page_levels=1))
    assert m.paged is not None and m.version == (1, 16)  # 1.6 morton1, 1.10 the lod record, 1.16 compact tables
    d = decode_scene(tmp_path / "s")
    assert len(d) == len(g)
