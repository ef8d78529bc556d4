"""Format 1.15 (format_spec/format.md 6.2, "Short digests"): a compact tile table names each payload and page by the
first 16 bytes of its SHA-256 (`digest16`, files `data/<32 hex>.bin`) and holds each tile's sphere as its `radius`
about the box's middle. A 1.15 scene reads end to end; a 1.12 scene (whole SHA-256) still reads; a damaged payload
is refused in one line naming its file; an older reader refuses a 1.15 table naming a missing column. The encoder
writes each payload under its final name at once (an object store sees no copy and no delete), and refuses two
payloads of one short name."""
import hashlib

import msgpack
import numpy as np
import pytest
import zstandard
from conftest import real, run_cli

from splatstream.encode import EncodeOptions, encode_in_memory, encode_to
from splatstream.errors import FormatError
from splatstream.format.container import verify_payload
from splatstream.format.manifest import pack_manifest, pack_manifest_dict, parse_manifest, resolve_pages, split_pages
from splatstream.format.manifest.versions import VERSION_1_12, VERSION_1_15, VERSION_1_16
from splatstream.format.names import digest_matches, is_payload_path, payload_name
from splatstream.ply import read_gaussians_ply
from splatstream.scene_decode import decode_scene
from splatstream.store import FsspecStore, FsspecWriter, MemoryStore, MemoryWriter, read_manifest, write_scene_manifest


@pytest.fixture(scope="module")
def scenes(fruit):
    """The same tree as 1.15 (relative_boxes off: 1.16 is test_relative_boxes.py's) and as 1.12 (short_digests
    off): (store, manifest)."""
    g = fruit
    out = {}
    for short in (True, False):
        store = encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=300, short_digests=short,
                                                  relative_boxes=False))
        out[short] = (store, read_manifest(store))
    return out


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians_ply(real("fruit_drops_sh3.ply"))


def _table(raw: bytes) -> dict:
    d = msgpack.unpackb(raw, strict_map_key=False)
    return msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)


def test_a_1_15_scene_names_payloads_by_16_bytes_and_decodes_as_the_1_12_one(scenes):
    (store, m), (old_store, old) = scenes[True], scenes[False]
    assert m.version == VERSION_1_15 and old.version == VERSION_1_12
    t, t_old = _table(store.read_manifest()), _table(old_store.read_manifest())
    assert "digest16" in t and "sha256" not in t and "radius" in t and "sphere" not in t
    assert len(t["digest16"]) * 2 == len(t_old["sha256"]) and len(t["radius"]) * 4 == len(t_old["sphere"])
    for a, b in zip(m.tiles, old.tiles, strict=True):
        for name, e in a.groups.items():
            data = store.read_payload(e)
            assert len(e.sha256) == 32 and e.file == payload_name(e.sha256) == f"data/{e.sha256}.bin"
            assert is_payload_path(e.file) and hashlib.sha256(data).hexdigest().startswith(e.sha256)
            assert b.groups[name].sha256[:32] == e.sha256 and data == old_store.read_payload(b.groups[name])
        # the sphere: the box's middle (its radius holding the tree's f64 sphere: test_manifest_compact.py)
        assert a.box == b.box and a.geometric_error == b.geometric_error
        assert a.sphere_center == tuple((x + y) / 2 for x, y in zip(a.box.min, a.box.max, strict=True))
        assert abs(a.sphere_radius - b.sphere_radius) <= 1e-6 * b.sphere_radius
    assert len(store.read_manifest()) < len(old_store.read_manifest()) * 0.8
    new, before = decode_scene(store), decode_scene(old_store)
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(new, field), getattr(before, field)), field


def test_a_paged_1_15_scene_names_its_pages_by_16_bytes(scenes):
    _, m = scenes[True]
    paged = split_pages(m, 2)
    assert paged.root.version == VERSION_1_15
    for ref, raw in paged.pages:
        assert ref.file == f"data/{ref.sha256}.bin" and hashlib.sha256(raw).hexdigest()[:32] == ref.sha256
        assert "digest16" in msgpack.unpackb(raw, strict_map_key=False) or "tile_table_zstd" in msgpack.unpackb(raw)
    raw = pack_manifest(paged.root)
    files = {ref.file: data for ref, data in paged.pages}
    back = resolve_pages(parse_manifest(raw), MemoryStore(raw, files, "p").read_payload, "p", len(raw))
    assert len(back.tiles) == len(m.tiles)
    ref, data = paged.pages[0]
    files[ref.file] = data[:-1] + bytes([data[-1] ^ 1])
    with pytest.raises(FormatError, match=rf"page {ref.file}: checksum mismatch: the page is corrupt"):
        resolve_pages(parse_manifest(raw), MemoryStore(raw, files, "p").read_payload, "p", len(raw))


def test_a_payload_is_verified_against_its_digest(scenes):
    store, m = scenes[True]
    e = m.tiles[0].groups["base"]
    data = store.read_payload(e)
    assert verify_payload(data, e, "x").data == data
    with pytest.raises(FormatError, match="x: sha256: checksum mismatch"):
        verify_payload(data[:-1] + bytes([data[-1] ^ 1]), e, "x")
    full = hashlib.sha256(data).hexdigest()
    assert digest_matches(full, full) and digest_matches(full, full[:32])
    assert not digest_matches(full, full[:31]) and not digest_matches(full, full[:40]) and not digest_matches(full, "")


def test_a_damaged_payload_is_refused_in_one_line_naming_the_file(tmp_path):
    scene = tmp_path / "s"
    r = run_cli("encode", real("fruit_drops_sh3.ply"), scene, "--max-leaf-splats", "2000", "-q")
    assert r.returncode == 0, r.stderr
    m = parse_manifest((scene / "manifest.msgpack").read_bytes())
    assert m.version == VERSION_1_16
    e = m.tiles[-1].groups["base"]
    path = scene / e.file
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x40
    path.write_bytes(bytes(data))
    r = run_cli("decode", scene, tmp_path / "out.ply")
    assert r.returncode != 0
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and e.file in lines[0] and "checksum mismatch" in lines[0], r.stderr


def test_older_readers_and_damaged_tables_are_refused_naming_a_key(scenes):
    store, _ = scenes[True]
    raw = store.read_manifest()

    def edited(version=None, table_edit=None):
        d = msgpack.unpackb(raw, strict_map_key=False)
        if version is not None:
            d["version"] = version
        if table_edit is not None:
            t = _table(raw)
            table_edit(t)
            d["tile_table_zstd"] = zstandard.ZstdCompressor().compress(msgpack.packb(t, use_bin_type=True))
        return pack_manifest_dict(d)

    # what a 1.12-1.14 reader says of a 1.15 scene (its sphere and digest columns are under keys it does not know)
    with pytest.raises(FormatError, match=r"manifest.msgpack: tile_table.sphere: missing"):
        parse_manifest(edited(version=[1, 14]))
    with pytest.raises(FormatError, match=r"tile_table.digest16: missing"):
        parse_manifest(edited(table_edit=lambda t: t.update(sha256=t.pop("digest16") * 2)))
    with pytest.raises(FormatError, match=r"tile_table.radius: missing"):
        parse_manifest(edited(table_edit=lambda t: t.pop("radius")))
    with pytest.raises(FormatError, match=r"tile_table.digest16: expected \d+ bytes"):
        parse_manifest(edited(table_edit=lambda t: t.update(digest16=t["digest16"][:-1])))
    with pytest.raises(FormatError, match=r"tile_table: unknown key 'sphere'"):
        parse_manifest(edited(table_edit=lambda t: t.update(sphere=b"")))


def test_server_routes_and_the_client_cache_take_both_lengths(tmp_path, scenes):
    from client_gl.stream.cache import DiskCache
    from server.paths import PathRejected, parse_scene_path, parse_scene_path_general

    short, full = "ab" * 16, "cd" * 32
    for h in (short, full):
        raw = f"/scenes/s/data/{h}.bin"
        sp = parse_scene_path(raw)
        assert sp == parse_scene_path_general(raw) and sp.kind == "payload" and sp.sha256 == h
    for bad in ("ab" * 20, "ab" * 16 + "a", "AB" * 16):
        for parse in (parse_scene_path, parse_scene_path_general):
            with pytest.raises(PathRejected):
                parse(f"/scenes/s/data/{bad}.bin")
    store, m = scenes[True]
    e = m.tiles[0].groups["base"]
    cache = DiskCache(tmp_path / "cache")
    assert cache.put(e, store.read_payload(e))
    assert cache.get(e).data == store.read_payload(e)
    assert DiskCache(tmp_path / "cache").contains(e.sha256)  # a fresh index finds the 32-hex name


@pytest.mark.parametrize("short", [True, False])
def test_an_object_store_gets_each_payload_once_under_its_final_name(fruit, short, monkeypatch):
    """No rename: every object is one PUT under the name the manifest gives it (1.15: the tile payloads' 32 hex; the
    codebook's and 1.12's 64), and nothing is copied or deleted (an object store's rename is both)."""
    fsspec = pytest.importorskip("fsspec")
    from fsspec.implementations.memory import MemoryFileSystem

    puts: list[str] = []
    other: list[str] = []
    pipe = MemoryFileSystem.pipe_file
    monkeypatch.setattr(MemoryFileSystem, "pipe_file", lambda fs, path, *a, **k: (puts.append(path),
                                                                                   pipe(fs, path, *a, **k))[1])
    for name in ("cp_file", "copy", "mv", "rm_file", "rm", "_rm"):
        monkeypatch.setattr(MemoryFileSystem, name, lambda fs, *a, _n=name, **k: other.append(_n), raising=False)
    url = f"memory://digests/{short}"
    opts = EncodeOptions(preset="medium", max_leaf_splats=300, short_digests=short, sh_codebook=64)
    m = encode_to(fruit, FsspecWriter(url), opts)
    assert other == []
    assert len(puts) == len(set(puts))  # each object once
    root = fsspec.core.url_to_fs(url)[1].rstrip("/")
    named = {p.file for _, _, p in m.payloads()}
    assert {p[len(root) + 1:] for p in puts} == named | {"manifest.msgpack"}
    assert m.version == (VERSION_1_16 if short else VERSION_1_12) and m.sh_codebook is not None
    for tile, _, p in m.payloads():
        assert len(p.sha256) == (32 if short and tile is not None else 64) and p.file == payload_name(p.sha256)
    back = read_manifest(FsspecStore(url))
    assert back.tiles == m.tiles


def test_two_payloads_of_one_short_digest_refuse_the_scene(fruit, monkeypatch):
    """A 128-bit prefix collision (never seen; made here by a short digest of one hex digit) refuses the scene in one
    line naming the file and the field, and publishes nothing."""
    import splatstream.format.manifest.model as model
    import splatstream.format.names as names

    short = lambda h: h[:1] + "0" * 31  # noqa: E731  (16 names for the fruit's 63 x 2 payloads: they collide)
    monkeypatch.setattr(names, "short_digest", short)
    monkeypatch.setattr(model, "short_digest", short)
    writer = MemoryWriter("fruit")
    with pytest.raises(FormatError, match=r"^fruit: tile_table: two payloads whose SHA-256 share their first 16 "
                       r"bytes \(data/[0-9a-f]0{31}\.bin\): .*--no-short-digests\)$"):
        encode_to(fruit, writer, EncodeOptions(preset="medium", max_leaf_splats=300, name="fruit"))
    assert writer.manifest is None


def test_the_manifest_must_name_the_payloads_as_they_were_written(scenes):
    """write_scene_manifest renames nothing: options that would name the tile payloads otherwise than the jobs wrote
    them are refused before anything is published."""
    _, m = scenes[False]
    writer = MemoryWriter("s")
    with pytest.raises(ValueError, match="written under whole digests' names, the manifest would name them by short"):
        write_scene_manifest(writer, m, 0, 0, compact_table=True, short_digests=True, short_names=False)
    with pytest.raises(ValueError, match="written under short digests' names, the manifest would name them by whole"):
        write_scene_manifest(writer, m, 0, 0, compact_table=False, short_digests=True, short_names=True)
    assert writer.manifest is None


def test_an_encode_to_a_local_url_makes_its_directories(tmp_path):
    """local:// (fsspec's real directories: a parent is not made by writing its file, as an object store's key is)
    gives the same scene as a plain directory, read back through the URL."""
    pytest.importorskip("fsspec")
    src = real("fruit_drops_sh3.ply")
    url = f"local://{tmp_path}/as_url/scene"
    for out in (url, tmp_path / "as_dir"):
        r = run_cli("encode", src, out, "-q", "--max-leaf-splats", "300")
        assert r.returncode == 0, r.stderr
    a = read_manifest(FsspecStore(url))
    b = read_manifest(FsspecStore(f"local://{tmp_path}/as_dir"))
    assert a.tiles == b.tiles and len(a.tiles) > 1
    manifest = "manifest.msgpack"
    assert (tmp_path / "as_url/scene" / manifest).read_bytes() == (tmp_path / "as_dir" / manifest).read_bytes()
