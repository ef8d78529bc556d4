"""The LOD tree's build record (format.md 6, "The tree's build record", version 1.9; issue 31): the manifest's
`lod.merge` and `lod.viewing_scale_px`, written by every tree the encoder builds, absent ("not recorded") in older
scenes and imported trees, checked by the validator and shown by `info`; from 1.10 the scales per level
(`lod.viewing_scale_levels_px`) of a scale that grows with the level, the default since 2026-11-30 (farpx31)."""
from __future__ import annotations

import copy
import importlib.util
import json
import pathlib

import msgpack
import numpy as np
import pytest
from conftest import real, run_cli

from splatstream import lod
from splatstream.encode import EncodeOptions, encode_gaussians, encode_in_memory
from splatstream.encode.local import LocalEngine
from splatstream.encode.partitioned import ArrayRows, encode_partitioned
from splatstream.encode.plan import plan_tiles
from splatstream.encode.scratch import Scratch
from splatstream.errors import FormatError
from splatstream.format import presets
from splatstream.format.layout import morton_order
from splatstream.format.manifest import manifest_from_dict, pack_manifest, parse_manifest, split_pages
from splatstream.format.manifest.versions import FORMAT_VERSION, VERSION_1_8, VERSION_1_9, VERSION_1_10
from splatstream.io import read_gaussians
from splatstream.store import MemoryWriter, load_manifest

VECTORS = pathlib.Path(__file__).resolve().parents[1] / "format_spec" / "vectors"
# The 1.8 tile table (compact_table off): these tests pin the versions the records need (1.9, 1.10); a compact
# table makes any tree 1.12 (format.md 6.2, test_manifest_compact.py).
TREE = {"max_leaf_splats": 300, "compact_table": False}


@pytest.fixture(scope="module")
def scene():
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    return g.subset(morton_order(g.positions)[:2400])


@pytest.fixture(scope="module")
def auto_raw(scene) -> bytes:
    """The manifest bytes of the default in-process encode (the merge left to the engine: auto)."""
    return encode_in_memory(scene, EncodeOptions(**TREE)).read_manifest()


def test_an_in_process_encode_records_auto_and_the_viewing_scales(auto_raw):
    m = parse_manifest(auto_raw)
    # 2 px on the first merged level, then 8, 12 and 16 px on every level above (lod.md 6 step 5): a 1.10 record.
    assert len(m.tiles) > 3 and m.version == VERSION_1_10
    assert m.lod.merge == "auto" and m.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0)
    d = msgpack.unpackb(auto_raw, strict_map_key=False)
    assert d["lod"] == {"enabled": True, "max_leaf_splats": 300, "reduction": 2.0, "refine": "replace",
                        "merge": "auto", "viewing_scale_levels_px": [2.0, 8.0, 12.0, 16.0]}


def test_a_named_merge_is_recorded_and_the_constants_are_read_at_the_encode(scene, monkeypatch):
    m = parse_manifest(encode_in_memory(scene, EncodeOptions(lod_merge="grid", **TREE)).read_manifest())
    assert m.lod.merge == "grid" and m.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0)
    # The record is what the encode used: the module constants as they are at the encode (a bench changes them).
    monkeypatch.setattr(lod, "OPACITY_MATCH_SSE_PX", 1.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 4.0)
    m = parse_manifest(encode_in_memory(scene, EncodeOptions(lod_merge="cost", **TREE)).read_manifest())
    assert m.lod.merge == "cost" and m.lod.viewing_scale_px == (1.0, 4.0, 6.0, 9.0, 13.5, 16.0)
    # One scale above the first merged level (growth 1, the rule before 2026-11-30): the 1.9 record.
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)
    m = parse_manifest(encode_in_memory(scene, EncodeOptions(lod_merge="cost", **TREE)).read_manifest())
    assert m.lod.viewing_scale_px == (1.0, 4.0) and m.version == VERSION_1_9
    # A growth without a cap: no finite list says it, so nothing is recorded (the merge still is).
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.5)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_CAP_SSE_PX", float("inf"))
    m = parse_manifest(encode_in_memory(scene, EncodeOptions(lod_merge="cost", **TREE)).read_manifest())
    assert m.lod.merge == "cost" and m.lod.viewing_scale_px is None and m.version == VERSION_1_9


def test_a_partitioned_encode_records_the_grid_as_the_in_process_grid_does(scene, tmp_path):
    """A partitioned grid encode's manifest is the in-process grid encode's, byte for byte, record included; a
    partitioned auto encode (its default since branch partauto31) records auto."""
    raws = {}
    for merge in ("grid", "auto"):
        writer = MemoryWriter("s")
        space = Scratch.create(str(tmp_path))
        opts = EncodeOptions(lod_merge=merge, lod_merge_domain_splats=len(scene) // 4, **TREE)
        encode_partitioned(ArrayRows(scene), writer, opts, LocalEngine(8 << 20), space, source_name="s")
        space.remove()
        raws[merge] = writer.store().manifest_bytes
    m = parse_manifest(raws["grid"])
    assert m.lod.merge == "grid" and m.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0) and m.version == VERSION_1_10
    assert raws["grid"] == encode_in_memory(scene, EncodeOptions(lod_merge="grid", **TREE), name="s").manifest_bytes
    m = parse_manifest(raws["auto"])
    assert m.lod.merge == "auto" and m.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0)


def test_one_tile_and_imported_trees_record_nothing_and_keep_their_version(scene):
    one = parse_manifest(encode_in_memory(scene.subset(np.arange(200)), EncodeOptions(**TREE)).read_manifest())
    assert len(one.tiles) == 1 and not one.lod.enabled and one.version < VERSION_1_8
    assert one.lod.merge is None and one.lod.viewing_scale_px is None
    assert "merge" not in msgpack.unpackb(pack_manifest(one), strict_map_key=False)["lod"]
    # A tree the caller built with plan_tiles under the same options (evaluate.py builds it once for every preset)
    # is the encoder's own: the same manifest as an encode building it.
    opts = EncodeOptions(lod_merge="grid", **TREE)
    tiles = plan_tiles(scene, opts, lambda *a: None)
    assert encode_in_memory(scene, opts, tiles=tiles).read_manifest() == \
        encode_in_memory(scene, opts).read_manifest()
    # An imported tree (sog_import.py: a streamed SOG's levels) was not built by it: nothing recorded, 1.8.
    imported = EncodeOptions(imported_tree=True, **TREE)
    given = parse_manifest(encode_in_memory(scene, imported, tiles=tiles).read_manifest())
    assert len(given.tiles) > 3 and given.version == VERSION_1_8 and not given.lod.build_recorded


def test_pages_keep_the_record_and_the_version(auto_raw):
    paged = split_pages(parse_manifest(auto_raw), 1)
    root = parse_manifest(pack_manifest(paged.root))
    assert root.lod.merge == "auto" and root.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0)
    assert root.version == VERSION_1_10
    assert all(msgpack.unpackb(raw, strict_map_key=False)["version"] == [1, 10] for _, raw in paged.pages)


def test_a_scene_before_1_9_reads_and_info_says_not_recorded():
    """The `table` vector (1.8, written before the record): it reads, and `info` says the build is not recorded."""
    scene = VECTORS / "table"
    m = load_manifest(scene)
    assert m.version == VERSION_1_8 and m.lod.enabled and m.lod.merge is None and m.lod.viewing_scale_px is None
    info = json.loads(run_cli("info", scene, "--json").stdout)
    assert info["lod"] == {"enabled": True, "kept_from_input": False, "max_leaf_splats": 64, "reduction": 2.0,
                           "refine": "replace", "merge": None, "viewing_scale_px": None, "refinement": None}
    text = run_cli("info", scene).stdout
    assert "LOD tree   merge and viewing scales not recorded" in text


def test_info_shows_the_record(scene, tmp_path):
    encode_gaussians(scene, tmp_path / "s", EncodeOptions(lod_merge="grid", **TREE))
    info = json.loads(run_cli("info", tmp_path / "s", "--json").stdout)
    assert info["version"] == [1, 10] and info["lod"]["merge"] == "grid"
    assert info["lod"]["viewing_scale_px"] == [2, 8, 12, 16]
    text = run_cli("info", tmp_path / "s").stdout
    assert "LOD tree   merge grid, opacity/colour matched at 2 px (first merged level), 8 / 12 / 16 px (the levels " \
           "above, the last on every higher one)" in text


def test_info_shows_a_two_number_record(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)  # 8 px on every level above: the 1.9 record
    encode_gaussians(scene, tmp_path / "s", EncodeOptions(lod_merge="grid", **TREE))
    info = json.loads(run_cli("info", tmp_path / "s", "--json").stdout)
    assert info["version"] == [1, 9] and info["lod"]["viewing_scale_px"] == [2, 8]
    text = run_cli("info", tmp_path / "s").stdout
    assert "LOD tree   merge grid, opacity/colour matched at 2 px (first merged level), 8 px (above)" in text


def test_the_table_vector_is_a_2_px_tree_that_today_s_encoder_records(tmp_path, monkeypatch):
    """format.md 8: the `table` vector (1.8) was written before the 2 + 8 px rule, so it is a 2-px tree that cannot
    say so. Its input and options encoded today with the far scale at 2 px give the same payload files and tiles,
    and the record says [2, 2] (version 1.9; pages differ in their version and the names of the pages below them);
    at today's scales (8, 12, 16 px) the levels above the first merged one differ. It was also written before
    `medium` stored its rotations in the half-turn gauge (rot32, format.md 4.5), so the gauge is off here."""
    monkeypatch.delitem(presets.PRESET_ROTATION_GAUGE, "medium")
    spec = importlib.util.spec_from_file_location("make_vectors", VECTORS / "make_vectors.py")
    make_vectors = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_vectors)
    source = read_gaussians(make_vectors.SOURCE)
    g = source.subset(morton_order(source.positions)[:make_vectors.PAGED_SPLATS])
    opts = EncodeOptions(preset="medium", name="vector-table", zstd_level=3, compact_table=False, **make_vectors.PAGED)
    old = load_manifest(VECTORS / "table")
    old_files = {p.file for _, _, p in old.payloads()}
    encode_gaussians(g, tmp_path / "today", opts)
    today = load_manifest(tmp_path / "today")
    assert today.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0) and today.lod.merge == "grid"
    assert len(old_files - {p.file for _, _, p in today.payloads()}) == 9  # the coarse levels' payloads (of 82)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 2.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)
    encode_gaussians(g, tmp_path / "t", opts)
    new = load_manifest(tmp_path / "t")
    assert new.version == VERSION_1_9 and new.lod.merge == "grid" and new.lod.viewing_scale_px == (2.0, 2.0)
    assert old_files == {p.file for _, _, p in new.payloads()} and len(old_files) == 82
    for f in old_files:
        assert (VECTORS / "table" / f).read_bytes() == (tmp_path / "t" / f).read_bytes()
    def tiles(m):  # the page names differ (a page's bytes hold its version), the tiles do not
        return [{k: v for k, v in t.to_dict().items() if k != "page"} for t in m.tiles]

    assert tiles(old) == tiles(new)
    assert [t.page is None for t in old.tiles] == [t.page is None for t in new.tiles]


@pytest.fixture(scope="module")
def record_dict(auto_raw) -> dict:
    return msgpack.unpackb(auto_raw, strict_map_key=False)


@pytest.mark.parametrize("key, value, message", [
    ("merge", "", "lod.merge: expected a merge name"),
    ("merge", 3, "lod.merge: expected a merge name"),
    ("viewing_scale_px", [2.0], "lod.viewing_scale_px: expected 2 finite numbers > 0"),
    ("viewing_scale_px", [0.0, 8.0], "lod.viewing_scale_px: expected 2 finite numbers > 0"),
    ("viewing_scale_px", [2.0, float("nan")], "lod.viewing_scale_px: expected 2 finite numbers > 0"),
    ("viewing_scale_px", "2+8", "lod.viewing_scale_px: expected 2 finite numbers > 0"),
    ("viewing_scale_levels_px", [2.0], "lod.viewing_scale_levels_px: expected 2 or more finite numbers > 0"),
    ("viewing_scale_levels_px", [2.0, 8.0, -1.0], "lod.viewing_scale_levels_px: expected 2 or more finite"),
    ("viewing_scale_levels_px", "2,8,12", "lod.viewing_scale_levels_px: expected 2 or more finite"),
])
def test_the_validator_rejects_a_bad_record(record_dict, key, value, message):
    d = copy.deepcopy(record_dict)
    d["lod"].pop("viewing_scale_levels_px")  # one record at a time
    d["lod"][key] = value
    with pytest.raises(FormatError, match=message):
        manifest_from_dict(d)


def test_the_validator_accepts_what_the_spec_allows_and_rejects_the_rest(record_dict):
    d = copy.deepcopy(record_dict)
    d["lod"]["merge"] = "a-later-merge"  # informative and open: a name this reader does not know is shown as it is
    del d["lod"]["viewing_scale_levels_px"]  # each key optional: absent is "not recorded"
    m = manifest_from_dict(d)
    assert m.lod.merge == "a-later-merge" and m.lod.viewing_scale_px is None
    del d["lod"]["merge"]
    assert not manifest_from_dict(d).lod.build_recorded
    # Before 1.9 the keys are unknown: damage in a version this reader knows (format.md 6, Versioning).
    d = copy.deepcopy(record_dict)
    d["version"] = [1, 8]
    with pytest.raises(FormatError, match="lod: unknown keys 'merge', 'viewing_scale_levels_px'"):
        manifest_from_dict(d)
    # The per-level scales are a 1.10 key: in a 1.9 scene, damage; with the two-number key, one record too many.
    d = copy.deepcopy(record_dict)
    d["version"] = [1, 9]
    with pytest.raises(FormatError, match="lod: unknown key 'viewing_scale_levels_px'"):
        manifest_from_dict(d)
    d = copy.deepcopy(record_dict)
    d["lod"]["viewing_scale_px"] = [2.0, 8.0]
    with pytest.raises(FormatError, match="lod.viewing_scale_levels_px: both viewing_scale_px and"):
        manifest_from_dict(d)
    # A two-number list in the 1.10 key reads as the 1.9 record does.
    d = copy.deepcopy(record_dict)
    d["lod"]["viewing_scale_levels_px"] = [2.0, 8.0]
    assert manifest_from_dict(d).lod.viewing_scale_px == (2.0, 8.0)
    # A record in a scene without a tree.
    d = copy.deepcopy(record_dict)
    d["lod"]["enabled"] = False
    with pytest.raises(FormatError, match="lod.merge: a build record in a scene without an LOD tree"):
        manifest_from_dict(d)
    # A newer minor version may add lod keys: ignored.
    d = copy.deepcopy(record_dict)
    d["version"] = [1, FORMAT_VERSION[1] + 1]  # (1.11 is known now: lod.refinement)
    d["lod"]["later"] = 1
    assert manifest_from_dict(d).lod.merge == "auto"
