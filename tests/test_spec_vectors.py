"""The committed test vectors in format_spec/vectors decode to their expected values."""
import hashlib
import importlib.util
import json
import pathlib
from dataclasses import replace

import msgpack
import numpy as np
import pytest
import zstandard

from splatstream.format.manifest import FORMAT_VERSION, parse_manifest
from splatstream.scene_decode import decode_scene
from splatstream.store import load_manifest

VECTORS = pathlib.Path(__file__).resolve().parents[1] / "format_spec" / "vectors"


# Each vector's version: 1.2 (the manifest carries its checksum), 1.13 where the rotations are cube565 (format.md
# 4.5, since rotrange32), 1.14 where they are cube8x4 (medium-low on fruit_drops' splats, off any 8-bit grid, since
# cube32). `low-norm565` is `low` as written before 1.13 (norm565 rotations in the cube gauge, 1.2): a reader still
# decodes such a scene exactly as it did.
PRESET_VECTORS = {"high": (1, 2), "medium": (1, 2), "medium-low": (1, 14), "low": (1, 13), "very-low": (1, 13),
                  "low-norm565": (1, 2)}
# The rotation format each vector holds (format.md 4.5).
VECTOR_ROTATIONS = {"high": "norm10_2", "medium": "norm10_2", "medium-low": "cube8x4", "low": "cube565",
                    "very-low": "cube565", "low-norm565": "norm565"}


@pytest.mark.parametrize("name", sorted(PRESET_VECTORS))
def test_vector_decodes_to_expected_values(name):
    preset = name.removesuffix("-norm565")
    if preset in ("low", "very-low"):
        pytest.importorskip("texture2ddecoder")
    scene = VECTORS / name
    expected = json.loads((scene / "expected.json").read_text())
    m = load_manifest(scene)
    codebook = preset in ("medium-low", "low", "very-low")  # SH codebook (format 1.1 and later)
    assert m.version == PRESET_VECTORS[name] and m.uses_codebook == codebook
    assert m.formats["rotation"] == VECTOR_ROTATIONS[name]
    assert m.preset == preset and m.splats == expected["splats"] == 260
    g = decode_scene(scene)
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        got = getattr(g, field)
        want = np.array(expected[field], np.float32)
        assert got.shape == want.shape, field
        assert np.array_equal(got, want), (preset, field, float(np.abs(got - want).max()))


def make_vectors():
    """format_spec/vectors/make_vectors.py (not a package: loaded from its file), the vectors' generator."""
    spec = importlib.util.spec_from_file_location("make_vectors", VECTORS / "make_vectors.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("preset", ["high", "medium", "medium-low", "low", "very-low"])
def test_vector_is_what_the_preset_writes_today(preset, tmp_path):
    """An old vector still decodes to its values (above), but it may no longer show what its preset writes:
    medium's did not have its scales on a tile step (issue 32) for a while. The scene is encoded again by
    make_vectors' own function, and every payload's decompressed bytes (the quantised planes, their filters and
    layout: what a preset decides) and the manifest's preset-level fields must be the vector's. The compressed bytes
    are not compared: another zstd build may compress the same planes differently."""
    fresh = tmp_path / preset
    make_vectors().encode_vector(preset, fresh)
    new, old = load_manifest(fresh), load_manifest(VECTORS / preset)
    regenerate = f"regenerate it: PYTHONPATH=. python format_spec/vectors/make_vectors.py {preset}"
    for field in ("version", "preset", "formats", "sh_degree", "splats", "chunk_size", "chunk_order", "bounds"):
        assert getattr(new, field) == getattr(old, field), f"{preset}: manifest field {field} differs; {regenerate}"
    assert (new.sh_codebook is None) == (old.sh_codebook is None), regenerate
    payloads = {(tile.id if tile else None, group): p for tile, group, p in old.payloads()}
    assert len(payloads) == len(list(new.payloads())), regenerate
    unzip = zstandard.ZstdDecompressor()
    for tile, group, p in new.payloads():
        was = payloads[(tile.id if tile else None, group)]
        assert p.sections == was.sections, f"{preset}: {group}'s section table differs; {regenerate}"
        raw = unzip.decompress((fresh / p.file).read_bytes())
        assert raw == unzip.decompress((VECTORS / preset / was.file).read_bytes()), \
            f"{preset}: {group}'s planes differ from the vector's; {regenerate}"


def test_vectors_verify_their_checksums(tmp_path):
    import shutil

    from splatstream.errors import FormatError

    shutil.copytree(VECTORS / "medium", tmp_path / "s")
    payload = next((tmp_path / "s" / "data").iterdir())
    data = bytearray(payload.read_bytes())
    data[len(data) // 2] ^= 0xFF
    payload.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="checksum mismatch"):
        decode_scene(tmp_path / "s")


def test_newer_major_version_is_rejected(tmp_path):
    import shutil

    from conftest import read_manifest_dict, write_manifest_dict

    from splatstream.errors import FormatError

    shutil.copytree(VECTORS / "high", tmp_path / "s")
    m = read_manifest_dict(tmp_path / "s")
    m["version"] = [2, 0]
    write_manifest_dict(tmp_path / "s", m)
    with pytest.raises(FormatError, match="version 2.0 is not supported"):
        load_manifest(tmp_path / "s")
    # A newer minor version may add keys: this reader ignores them. In a version it knows, they are damage.
    m["version"] = [1, FORMAT_VERSION[1] + 1]
    m["a_future_key"] = {"x": 1}
    write_manifest_dict(tmp_path / "s", m)
    assert len(decode_scene(tmp_path / "s")) == 260
    m["version"] = [1, 0]
    write_manifest_dict(tmp_path / "s", m)
    with pytest.raises(FormatError, match="unknown key 'a_future_key'"):
        load_manifest(tmp_path / "s")


def test_paged_vector_reads_its_pages_and_decodes_to_expected_values():
    """format.md 6.1 and 8: the paged vector's root manifest names only the top of the tree; with every page read
    (each named by the SHA-256 of its bytes) it is the whole tree and decodes exactly."""
    scene = VECTORS / "paged"
    root = parse_manifest((scene / "manifest.msgpack").read_bytes())
    assert root.version == (1, 5) and root.paged.page_levels == 1 and [t.id for t in root.tiles] == [root.root]
    m = load_manifest(scene)
    assert len(m.tiles) == root.paged.tiles == 41 and m.levels == root.paged.levels
    pages = {p.name for p in (scene / "data").iterdir()} - {p.file.split("/")[1] for _, _, p in m.payloads()}
    assert len(pages) == root.paged.pages == 25
    for name in pages:
        assert hashlib.sha256((scene / "data" / name).read_bytes()).hexdigest() + ".bin" == name
    expected = json.loads((scene / "expected.json").read_text())
    g = decode_scene(scene)
    assert len(g) == expected["splats"] == m.splats == 600
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(g, field), np.array(expected[field], np.float32)), field


def test_table_vector_reads_its_tile_tables_and_decodes_to_expected_values():
    """format.md 6.2 and 8: the `table` vector is `paged`'s input and options written as 1.8 (2026-11-29): its
    root manifest and pages hold tile tables, and with every page read it decodes exactly."""
    scene = VECTORS / "table"
    raw = (scene / "manifest.msgpack").read_bytes()
    assert "tile_table" in msgpack.unpackb(raw, strict_map_key=False)
    root = parse_manifest(raw)
    assert root.version == (1, 8) and root.paged.page_levels == 1 and [t.id for t in root.tiles] == [root.root]
    m = load_manifest(scene)
    assert len(m.tiles) == root.paged.tiles and m.levels == root.paged.levels
    expected = json.loads((scene / "expected.json").read_text())
    g = decode_scene(scene)
    assert len(g) == expected["splats"] == m.splats == 600
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(g, field), np.array(expected[field], np.float32)), field


COMPACT_VECTORS = {"compact": [1, 12], "digest16": [1, 15], "relbox16": [1, 16]}


@pytest.mark.parametrize("name", sorted(COMPACT_VECTORS))
def test_compact_vector_holds_compact_tables_and_decodes_to_expected_values(name):
    """format.md 6.2 and 8: the `compact` vector (1.12) is `levels`'s tree paged two levels to a file; its root
    manifest and every page hold `tile_table_zstd` (a zstd frame of the table with f32 bounds), and with every page
    read it is `levels`'s tree: the same payloads, each tile's bounds `levels`'s rounded outward to float32.
    `digest16` (1.15) is the same with its payloads and pages named by the first 16 bytes of their SHA-256 and its
    spheres as radii about the boxes' middles. `relbox16` (1.16) is `digest16` with its boxes as u8 steps of their
    parents' (`box8`; the root's and each page's top tiles' f32, `anchor_box`) and its radii as u8 steps of the half
    diagonal (`radius8`): `levels`'s bounds held, the root's box `digest16`'s."""
    scene = VECTORS / name
    version = COMPACT_VECTORS[name]
    short = version >= [1, 15]
    relative = version >= [1, 16]
    raw = (scene / "manifest.msgpack").read_bytes()
    d = msgpack.unpackb(raw, strict_map_key=False)
    assert "tile_table_zstd" in d and "tile_table" not in d and d["version"] == version
    table = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)
    if relative:  # the root the one anchor of the root manifest, its 8 children steps of its box
        assert len(table["anchor_box"]) == 6 * 4 and len(table["box8"]) == (table["count"] - 1) * 6
        assert len(table["radius8"]) == table["count"] and "box" not in table
    else:
        assert len(table["box"]) == table["count"] * 6 * 4  # f32
    digests = table["digest16" if short else "sha256"]
    assert ("sha256" in table) != short and len(digests) == table["count"] * 2 * (16 if short else 32)
    root = parse_manifest(raw)
    assert root.paged.page_levels == 2 and {t.level for t in root.tiles} == {0, 1}
    m = load_manifest(scene)
    plain = load_manifest(VECTORS / "levels")
    assert len(m.tiles) == len(plain.tiles) == root.paged.tiles == 41
    payloads = {p.file for _, _, p in m.payloads()}
    pages = {p.name for p in (scene / "data").iterdir()} - {f.split("/")[1] for f in payloads}
    assert len(pages) == root.paged.pages > 1
    for name in pages:
        page = msgpack.unpackb((scene / "data" / name).read_bytes(), strict_map_key=False)
        assert "tile_table_zstd" in page and page["version"] == version
        data = (scene / "data" / name).read_bytes()
        assert hashlib.sha256(data).hexdigest().startswith(name.removesuffix(".bin"))
        assert len(name) == (32 if short else 64) + 4
    for a, b in zip(m.tiles, plain.tiles, strict=True):
        assert {k: e.sha256 for k, e in a.groups.items()} == {k: e.sha256[:32] if short else e.sha256
                                                              for k, e in b.groups.items()}
        if not relative:
            assert all(float(np.float32(v)) == v for v in (*a.box.min, *a.box.max, a.sphere_radius))
        if short:  # 1.15: the sphere's centre is the f32 box's middle (its `radius` column alone is stored)
            assert a.sphere_center == tuple((x + y) / 2 for x, y in zip(a.box.min, a.box.max, strict=True))
            moved = float(np.linalg.norm(np.subtract(a.sphere_center, b.sphere_center)))
            assert a.sphere_radius >= b.sphere_radius + moved
        else:
            assert all(float(np.float32(v)) == v for v in a.sphere_center)
        assert all(x <= y for x, y in zip(a.box.min, b.box.min, strict=True))
        assert all(x >= y for x, y in zip(a.box.max, b.box.max, strict=True))
        assert a.sphere_radius >= b.sphere_radius and a.geometric_error >= b.geometric_error
    if relative:  # the anchors (the root; each page's top tiles) as digest16's f32 boxes
        f32 = {t.id: t.box for t in load_manifest(VECTORS / "digest16").tiles}
        assert all(t.box == f32[t.id] for t in m.tiles if t.level % 2 == 0)
        assert sum(t.box != f32[t.id] for t in m.tiles) > 0
    expected = json.loads((scene / "expected.json").read_text())
    g = decode_scene(scene)
    assert len(g) == expected["splats"] == m.splats == 600
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(g, field), np.array(expected[field], np.float32)), field


@pytest.mark.parametrize("name", sorted(COMPACT_VECTORS))
def test_compact_vector_is_what_the_encoder_writes_today(tmp_path, name):
    """Encoded again by make_vectors: the same version, the same tiles (bounds included) and the same payloads'
    decompressed bytes (zstd's own bytes may differ between zstd versions: those are not pinned)."""
    fresh = tmp_path / name
    make_vectors().encode_compact_vector(fresh, name=name)
    regenerate = f"regenerate it: PYTHONPATH=. python format_spec/vectors/make_vectors.py {name}"
    new, old = load_manifest(fresh), load_manifest(VECTORS / name)
    assert (new.version, new.lod, new.paged) == (old.version, old.lod, old.paged), regenerate
    unnamed = [[replace(t, page=None).to_dict() for t in m.tiles] for m in (new, old)]  # a page's name is its hash
    assert unnamed[0] == unnamed[1], regenerate


# The committed vectors' zstd blocks (format.md 5.2, 8): written by the encoder that lets like parts of a small
# payload share a block (container._block_ends), where a block per part had made 125 / 81 / 62 / 56 / 1214; medium's
# and very-low's rewritten with their rotations in a canonical gauge (issue 32, rot32: 49 and 12 blocks before), high's
# with its rotations in the half turns (evalrefresh32: 38 before); low's and very-low's with cube565 rotations (format
# 1.13, rotrange32: 14 and 16 before; the old low kept as low-norm565); medium-low's written with cube8x4 rotations
# (format 1.14, cube32).
VECTOR_BLOCKS = {"high": 27, "medium": 51, "medium-low": 45, "low": 12, "very-low": 13, "low-norm565": 14,
                 "table": 165}
# Those with a payload of fewer blocks than sections: a block there holds the end of one section and the start of
# the next (in high's and medium's the shared blocks are within sections; very-low's, rewritten in rot32, ended a
# block with every section, and rewritten in rotrange32 has the case again; low, low-norm565 and table keep it).
ACROSS_SECTIONS = {"medium-low", "low", "very-low", "low-norm565", "table"}


@pytest.mark.parametrize("name", sorted(VECTOR_BLOCKS))
def test_vector_payloads_share_zstd_blocks_as_the_encoder_writes_them(name):
    """Readers are tested on what writers emit: the vectors' payloads hold zstd blocks that span several parts (byte
    planes, layers, ranges), in some vectors parts of two sections, and decode exactly (the tests above)."""
    from conftest import zstd_block_count  # the frame's block count, as the encoder's block test reads it

    scene = VECTORS / name
    payloads = [p for _, _, p in load_manifest(scene).payloads()]
    blocks = [zstd_block_count((scene / p.file).read_bytes()) for p in payloads]
    assert all(b > 0 for b in blocks)  # each payload one well-formed frame
    assert sum(blocks) == VECTOR_BLOCKS[name]
    assert any(b < len(p.sections) for b, p in zip(blocks, payloads, strict=True)) == (name in ACROSS_SECTIONS)


# The LOD record vectors (format.md 6 and 8): `paged`'s 600 splats and tree in one manifest, 1.10 and 1.11.
RECORD_LOD = {"enabled": True, "max_leaf_splats": 64, "reduction": 2.0, "refine": "replace", "merge": "grid",
              "viewing_scale_levels_px": [2.0, 8.0, 12.0, 16.0]}
REFINEMENT = {"method": "render-fit",
              "variants": {"B": ["opacity_logits", "sh_dc", "log_scales"],
                           "C": ["opacity_logits", "sh_dc", "log_scales", "positions", "rotations"]},
              "size_px": 384, "iterations": 300,
              "cameras": {"training": 96, "training_seed": 0, "validation": 32, "validation_seed": 1},
              "levels": [{"level": d, "kept": "B" if d == 2 else "none",
                          "validation_psnr": {"none": 30.0, "B": 31.5, "C": 31.25}} for d in (0, 1, 2)]}


def raw_manifest(name: str) -> dict:
    return msgpack.unpackb((VECTORS / name / "manifest.msgpack").read_bytes(), strict_map_key=False)


@pytest.mark.parametrize("name", ["levels", "refined"])
def test_record_vectors_hold_their_lod_records_and_decode_to_expected_values(name):
    """format.md 6: `levels` (1.10) records the viewing scale per level, `refined` (1.11) also the refinement, each
    key exactly as the manifest holds it; both decode exactly, and the refinement left the leaves as they were."""
    d = raw_manifest(name)
    want = dict(RECORD_LOD, refinement=REFINEMENT) if name == "refined" else RECORD_LOD
    assert d["version"] == ([1, 11] if name == "refined" else [1, 10]) and d["lod"] == want
    m = load_manifest(VECTORS / name)
    assert len(m.tiles) == 41 and m.levels == 4 and m.paged is None
    assert m.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0) and m.lod.merge == "grid"
    assert (m.lod.refinement.to_dict() if m.lod.refinement else None) == (REFINEMENT if name == "refined" else None)
    expected = json.loads((VECTORS / name / "expected.json").read_text())
    g = decode_scene(VECTORS / name)
    assert len(g) == expected["splats"] == m.splats == 600
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(g, field), np.array(expected[field], np.float32)), field
    if name == "refined":
        plain = load_manifest(VECTORS / "levels")
        for a, b in zip(plain.tiles, m.tiles, strict=True):
            same = {k: e.sha256 for k, e in a.groups.items()} == {k: e.sha256 for k, e in b.groups.items()}
            assert same == (not a.children or a.level != 2), a.id  # only the level that kept B was rewritten


@pytest.mark.parametrize("name", ["levels", "refined"])
def test_record_vector_is_what_the_encoder_writes_today(name, tmp_path):
    """As the presets' vectors: encoded again by make_vectors, the manifest's version and `lod` map and every
    payload's decompressed bytes are the vector's."""
    fresh = tmp_path / name
    make_vectors().encode_record_vector(name, fresh)
    regenerate = f"regenerate it: PYTHONPATH=. python format_spec/vectors/make_vectors.py {name}"
    new, old = load_manifest(fresh), load_manifest(VECTORS / name)
    assert (new.version, new.lod) == (old.version, old.lod), regenerate
    unzip = zstandard.ZstdDecompressor()
    payloads = {(t.id, group): p for t, group, p in old.payloads()}
    for t, group, p in new.payloads():
        raw = unzip.decompress((fresh / p.file).read_bytes())
        assert raw == unzip.decompress((VECTORS / name / payloads[(t.id, group)].file).read_bytes()), regenerate


REFINEMENT_REJECTED = [
    (lambda r: r.update(size_px="384"), "lod.refinement.size_px: expected an integer 1..4611686018427387904, "
                                         "got '384'"),
    (lambda r: r["levels"][2].update(kept="D"), "lod.refinement.levels[2].kept: expected none or one of the "
                                                 "variants (B, C), got 'D'"),
    (lambda r: r["levels"][2].update(level=3), "lod.refinement.levels[2].level: expected a merged level of this "
                                                "4-level tree, 2..2 (ascending, each once), got 3"),
    (lambda r: r["levels"][1].update(level=0), "lod.refinement.levels[1].level: expected a merged level of this "
                                                "4-level tree, 1..2 (ascending, each once), got 0"),
    (lambda r: r.update(variants={"B": "opacity_logits"}), "lod.refinement.variants: expected a map of variant name "
                                                            "to a list of field names, got {'B': 'opacity_logits'}"),
    (lambda r: r["cameras"].pop("validation_seed"), "lod.refinement.cameras.validation_seed: missing"),
]


@pytest.mark.parametrize("change, message", REFINEMENT_REJECTED)
def test_a_damaged_refinement_record_is_rejected_in_one_line(change, message):
    """format.md 6, Validation: `refined`'s manifest with one thing wrong in its record (its checksum left out, as
    manifest_from_dict checks the map) is rejected naming the field and what was expected."""
    from splatstream.errors import FormatError
    from splatstream.format.manifest import manifest_from_dict

    d = raw_manifest("refined")
    d.pop("checksum")
    change(d["lod"]["refinement"])
    with pytest.raises(FormatError) as e:
        manifest_from_dict(d)
    assert str(e.value) == f"manifest.msgpack: {message}"


def test_a_nil_refinement_or_levels_without_a_tree_is_rejected():
    from splatstream.errors import FormatError
    from splatstream.format.manifest import manifest_from_dict

    d = raw_manifest("refined")
    d.pop("checksum")
    d["lod"]["refinement"] = None  # present is a map: nil is damage, not "not refined"
    with pytest.raises(FormatError) as e:
        manifest_from_dict(d)
    assert str(e.value) == "manifest.msgpack: lod.refinement: expected a map, got NoneType"
    d = raw_manifest("levels")
    d.pop("checksum")
    d["lod"].pop("merge")
    d["lod"]["enabled"] = False
    with pytest.raises(FormatError) as e:  # the key that is there is named
        manifest_from_dict(d)
    assert str(e.value) == ("manifest.msgpack: lod.viewing_scale_levels_px: a build record in a scene without an LOD "
                            "tree (lod.enabled is false)")
