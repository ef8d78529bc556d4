"""Manifest pages (format_spec/format.md 6.1, version 1.5): a large tree written as a root manifest and
content-addressed pages, read back whole by the stores (info, decode, export) and checked by the one validator."""
import copy
import hashlib
import os
from dataclasses import replace

import msgpack
import pytest
from conftest import real, run_cli

from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.errors import FormatError
from splatstream.format.manifest import (
    PAGE_FORMAT,
    VERSION_1_5,
    pack_manifest,
    pack_manifest_dict,
    parse_manifest,
    resolve_pages,
    split_pages,
)
from splatstream.format.manifest.versions import VERSION_1_7
from splatstream.format.names import payload_name
from splatstream.ply import read_gaussians_ply
from splatstream.store import MemoryStore, load_manifest, read_manifest


@pytest.fixture(scope="module")
def whole():
    """The tree as a 1.5-1.7 writer wrote it (tile maps: the pages here edit them), which readers still read; the
    encoder's own 1.8 tile table (format.md 6.2) is tests/test_manifest_table.py's."""
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    m = read_manifest(encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=300, short_digests=False)))
    m = replace(m, version=VERSION_1_7, lod=replace(m.lod, merge=None, viewing_scale_px=None))  # no 1.9 record
    return m.with_bytes_on_disk(m.payload_bytes())


def _store(paged) -> MemoryStore:
    files = {ref.file: raw for ref, raw in paged.pages}
    return MemoryStore(pack_manifest(paged.root), files, "paged")


@pytest.mark.parametrize("k", [1, 2, 3])
def test_split_then_resolve_gives_the_whole_tree(whole, k):
    paged = split_pages(whole, k)
    root = paged.root
    assert root.version == max(whole.version, VERSION_1_5) and root.paged.page_levels == k
    assert {t.level for t in root.tiles} == set(range(min(k, whole.levels)))
    assert [t.id for t in root.tiles] == list(range(len(root.tiles)))  # lod.md 1: tiles[i].id == i
    assert root.paged.tiles == len(whole.tiles) and root.paged.pages == len(paged.pages)
    raw = pack_manifest(root)
    assert parse_manifest(raw).to_dict() == root.to_dict()
    # every page is named by its content, and the root counts them in bytes_on_disk
    for ref, data in paged.pages:
        assert ref.file == payload_name(hashlib.sha256(data).hexdigest()) and ref.bytes == len(data)
        assert msgpack.unpackb(data)["format"] == PAGE_FORMAT
    store = _store(paged)
    back = resolve_pages(parse_manifest(raw), store.read_payload, "paged", len(raw))
    assert [t.id for t in back.tiles] == [t.id for t in whole.tiles]
    for a, b in zip(back.tiles, whole.tiles, strict=True):
        assert a.children == b.children and a.groups == b.groups and a.splats == b.splats
    assert back.bytes_on_disk == whole.payload_bytes() + len(raw) + root.paged.page_bytes
    assert split_pages(whole, k).pages == paged.pages  # deterministic


def test_an_unpaged_manifest_is_written_as_before(whole):
    """Below the threshold nothing changes: the same bytes (tests/test_encode_bytes.py pins them too)."""
    assert whole.paged is None and "paged" not in whole.to_dict()
    assert all("page" not in t.to_dict() for t in whole.tiles)


def test_damaged_pages_are_refused_naming_the_page(whole):
    paged = split_pages(whole, 2)
    raw = pack_manifest(paged.root)
    files = {ref.file: data for ref, data in paged.pages}
    ref, data = paged.pages[-1]  # the top page (made last)

    def resolve(files):
        return resolve_pages(parse_manifest(raw), lambda r: files[r.file], "paged", len(raw))

    flipped = dict(files)
    flipped[ref.file] = data[:-1] + bytes([data[-1] ^ 1])
    with pytest.raises(FormatError, match=f"page {ref.file}.*checksum mismatch"):
        resolve(flipped)
    short = dict(files)
    short[ref.file] = data[:-1]
    with pytest.raises(FormatError, match="bytes, but the manifest names a page of"):
        resolve(short)


def _repage(whole, edit) -> tuple[bytes, dict]:
    """A paged scene whose top page is edited (its map) and renamed by its new content, the root resealed."""
    paged = split_pages(whole, 2)
    files = {ref.file: data for ref, data in paged.pages}
    top_ref, top = paged.pages[-1]
    d = msgpack.unpackb(top, strict_map_key=False)
    edit(d)
    data = msgpack.packb(d, use_bin_type=True)
    sha = hashlib.sha256(data).hexdigest()
    files[payload_name(sha)] = data
    root = copy.deepcopy(paged.root.to_dict())
    for t in root["tiles"]:
        if t.get("page", {}).get("sha256") == top_ref.sha256:
            t["page"] = {"file": payload_name(sha), "sha256": sha, "bytes": len(data)}
    return pack_manifest_dict(root), files


@pytest.mark.parametrize("edit, problem", [
    (lambda d: d.update(parent=d["parent"] + 1), "parent: expected"),
    (lambda d: d.update(format="x"), "not a splatstream manifest page"),
    (lambda d: d["tiles"].pop(), "is not in the page"),
    (lambda d: d["tiles"][0].update(splats=0), r"tiles\[0\]\.splats: expected"),
    (lambda d: d["tiles"][-1].pop("page", None) if any("page" in t for t in d["tiles"])
     else d["tiles"][-1].update(page={"file": payload_name("0" * 64), "sha256": "0" * 64, "bytes": 1}), "page"),
])
def test_a_page_is_checked_like_a_manifest(whole, edit, problem):
    raw, files = _repage(whole, edit)
    with pytest.raises(FormatError, match=problem):
        resolve_pages(parse_manifest(raw), lambda r: files[r.file], "paged", len(raw))


def test_the_root_manifest_is_checked_alone(whole):
    root = split_pages(whole, 2).root.to_dict()
    deep = copy.deepcopy(root)
    next(t for t in deep["tiles"] if "page" in t).pop("page")
    with pytest.raises(FormatError, match=r"tiles\[\d+\]\.page: missing"):
        parse_manifest(pack_manifest_dict(deep))
    bad = copy.deepcopy(root)
    paged_tile = next(t for t in bad["tiles"] if "page" in t)
    paged_tile["page"]["file"] = "data/x.bin"
    with pytest.raises(FormatError, match=r"page: file: expected|page\.file|page: file"):
        parse_manifest(pack_manifest_dict(bad))


def test_a_1_4_reader_refuses_a_paged_scene_at_the_tree_check(whole):
    """format.md 6.1: an older reader ignores `paged` and `page` (keys of a newer minor version) and then finds a
    child it cannot read: it fails naming it, and misreads nothing."""
    root = split_pages(whole, 2).root.to_dict()
    for t in root["tiles"]:
        t.pop("page", None)
    root.pop("paged")
    with pytest.raises(FormatError, match=r"tiles\[\d+\]\.children: no tile with id"):
        parse_manifest(pack_manifest_dict(root))


def test_encode_writes_pages_over_the_threshold_and_the_cli_reads_them(tmp_path):
    out = tmp_path / "scene"
    r = run_cli("encode", str(real("fruit_drops_sh3.ply")), str(out), "--max-leaf-splats", "300", "--page-tiles",
                "4", "--page-levels", "2", "--quiet")
    assert r.returncode == 0, r.stderr
    root = parse_manifest((out / "manifest.msgpack").read_bytes())
    assert root.paged is not None and root.paged.pages > 1
    assert sum(os.path.getsize(out / ref) for ref in {t.page.file for t in root.tiles if t.page}) > 0
    whole = load_manifest(out)
    assert len(whole.tiles) == root.paged.tiles
    assert whole.bytes_on_disk == sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    r = run_cli("info", str(out), "--json")
    assert r.returncode == 0 and '"pages": ' in r.stdout
    r = run_cli("decode", str(out), str(tmp_path / "back.ply"))
    assert r.returncode == 0, r.stderr
    unpaged = tmp_path / "unpaged"
    assert run_cli("encode", str(real("fruit_drops_sh3.ply")), str(unpaged), "--max-leaf-splats", "300",
                   "--quiet").returncode == 0
    assert run_cli("decode", str(unpaged), str(tmp_path / "b2.ply")).returncode == 0
    assert (tmp_path / "back.ply").read_bytes() == (tmp_path / "b2.ply").read_bytes()
    # the payloads are the same files: only the manifest is split
    assert {p.name for p in (unpaged / "data").iterdir()} < {p.name for p in (out / "data").iterdir()}


def test_export_3dtiles_of_a_paged_scene_is_the_unpaged_scenes(tmp_path):
    """The exporter reads every page (load_manifest): with --external-tilesets never, the same tileset as the
    scene's unpaged encode; by default the same content, the tree cut into external tilesets at the pages
    (tests/test_tiles3d.py checks that tree tile for tile). Encoded as 1.15 (f32 boxes): from 1.16 a page's top
    tiles are its table's anchors (f32 boxes) where the unpaged table codes them against their parents, so the two
    encodes' bounding volumes differ there by their rounding (both hold the tree's; format.md 6.2); their tiles'
    content is the same (below)."""
    ply = str(real("fruit_drops_sh3.ply"))
    for name, extra in (("paged", ["--page-tiles", "4", "--page-levels", "2"]), ("whole", []),
                        ("paged16", ["--page-tiles", "4", "--page-levels", "2"]), ("whole16", [])):
        f32 = [] if name.endswith("16") else ["--no-relative-boxes"]
        assert run_cli("encode", ply, str(tmp_path / name), "--max-leaf-splats", "300", "--quiet",
                       *extra, *f32).returncode == 0
        r = run_cli("export-3dtiles", str(tmp_path / name), str(tmp_path / f"{name}.tiles"))
        assert r.returncode == 0, r.stderr
    r = run_cli("export-3dtiles", str(tmp_path / "paged"), str(tmp_path / "paged.single"), "--external-tilesets",
                "never")
    assert r.returncode == 0, r.stderr
    a, b, external = tmp_path / "paged.single", tmp_path / "whole.tiles", tmp_path / "paged.tiles"
    assert (a / "tileset.json").read_bytes() == (b / "tileset.json").read_bytes()
    assert sorted(p.name for p in (a / "tiles").iterdir()) == sorted(p.name for p in (b / "tiles").iterdir())
    assert not list((b / "tiles").glob("*.json"))  # an unpaged scene: one tileset.json, as before
    assert len(list((external / "tiles").glob("*.json"))) == load_manifest(tmp_path / "paged").paged.pages
    assert sorted(p.name for p in (external / "tiles").glob("*.glb")) == sorted(p.name for p in (b / "tiles").iterdir())
    # 1.16: the same tiles, payloads and content; the bounds each hold the unpaged tree's f64 ones
    paged16, whole16 = load_manifest(tmp_path / "paged16"), load_manifest(tmp_path / "whole16")
    assert paged16.version == whole16.version == (1, 16)
    for x, y in zip(paged16.tiles, whole16.tiles, strict=True):
        assert (x.id, x.children, x.splats, x.groups) == (y.id, y.children, y.splats, y.groups)
