"""The compact tile table (format_spec/format.md 6.2, version 1.12): a tree's tile table with f32 bounds rounded
outward, msgpack-packed and zstd-compressed under `tile_table_zstd`; read back into the same records, conservative
against the f64 bounds it was made from, and rejected in one line when damaged."""
import msgpack
import numpy as np
import pytest
import zstandard
from conftest import real, run_cli

from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.errors import FormatError
from splatstream.format.manifest import pack_manifest, pack_manifest_dict, parse_manifest, resolve_pages, split_pages
from splatstream.format.manifest.table import compact_columns, down_f32, up_f32
from splatstream.format.manifest.versions import VERSION_1_10, VERSION_1_12, VERSION_1_15, VERSION_1_16
from splatstream.ply import read_gaussians_ply
from splatstream.store import MemoryStore, read_manifest


@pytest.fixture(scope="module")
def scenes():
    """The same tree written compact with f32 boxes (1.15: relative_boxes off; 1.16's u8 boxes are
    test_relative_boxes.py's) and as the 1.8 table."""
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    out = {}
    for compact in (True, False):
        store = encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=300, compact_table=compact,
                                                  relative_boxes=False))
        out[compact] = (store.read_manifest(), read_manifest(store))
    return out


def test_a_tree_is_written_compact_and_reads_back_conservative(scenes):
    raw, m = scenes[True]
    plain_raw, plain = scenes[False]
    d = msgpack.unpackb(raw, strict_map_key=False)
    assert d["version"] == [1, 15] and "tile_table_zstd" in d and "tile_table" not in d and "tiles" not in d
    assert plain.version == VERSION_1_10 and m.version == VERSION_1_15
    back = parse_manifest(raw)
    assert back == m  # the encoder's manifest is what a reader gets: its bounds are the table's f32 values
    assert len(m.tiles) == len(plain.tiles) > 1
    for a, b in zip(m.tiles, plain.tiles, strict=True):
        assert a.children == b.children and a.splats == b.splats
        # the same payloads, named by the first 16 bytes of their SHA-256 (1.15, format.md 6.2)
        for name in b.groups:
            x, y = a.groups[name], b.groups[name]
            assert x.sha256 == y.sha256[:32] and x.file == f"data/{y.sha256[:32]}.bin"
            assert (x.bytes, x.raw_bytes, x.gpu_bytes, x.sections) == (y.bytes, y.raw_bytes, y.gpu_bytes, y.sections)
        # outward: the f32 box holds the f64 one, the sphere the f64 sphere, the error is no smaller
        assert all(x <= y and float(np.float32(x)) == x for x, y in zip(a.box.min, b.box.min, strict=True))
        assert all(x >= y and float(np.float32(x)) == x for x, y in zip(a.box.max, b.box.max, strict=True))
        moved = float(np.linalg.norm(np.subtract(a.sphere_center, b.sphere_center)))
        assert a.sphere_radius >= b.sphere_radius + moved and a.geometric_error >= b.geometric_error
        # by at most a few float32 steps
        assert a.geometric_error <= b.geometric_error * (1 + 2 ** -22)
    assert m.payload_bytes() == plain.payload_bytes() and m.gpu_bytes == plain.gpu_bytes
    assert m.bytes_on_disk == m.payload_bytes() + len(raw)
    # 7,717 B against 21,930 on this 63-tile SH3 tree (four payloads a tile: their 16-byte digests do not compress;
    # 11,747 B with 32-byte ones, 1.12)
    assert len(raw) * 5 < len(plain_raw) * 2


def test_compacting_is_idempotent_and_rounds_outward():
    rng = np.random.default_rng(3)
    box = np.sort(rng.normal(0, 50, (200, 2, 3)), axis=1).reshape(200, 6)
    sphere = np.concatenate([rng.normal(0, 50, (200, 3)), rng.uniform(0, 10, (200, 1))], axis=1)
    error = rng.uniform(0, 1, 200)
    b, s, e = compact_columns(box, sphere, error)
    assert (b[:, :3] <= box[:, :3]).all() and (b[:, 3:] >= box[:, 3:]).all() and (e >= error).all()
    assert (s[:, 3] >= sphere[:, 3] + np.linalg.norm(s[:, :3] - sphere[:, :3], axis=1)).all()
    for a in (b, s, e):
        assert np.array_equal(a.astype(np.float32).astype(np.float64), a)
    again = compact_columns(b, s, e)
    assert all(np.array_equal(x, y) for x, y in zip(again, (b, s, e), strict=True))
    assert float(down_f32([1.0])[0]) == 1.0 and float(up_f32([0.1])[0]) > 0.1 > float(down_f32([0.1])[0])
    with pytest.raises(ValueError, match="beyond float32's range"):
        compact_columns(box * 1e37, sphere, error)


def test_a_paged_compact_tree_writes_compact_pages(scenes):
    _, m = scenes[True]
    paged = split_pages(m, 2)
    assert paged.root.version == VERSION_1_15
    assert all(len(ref.sha256) == 32 and ref.file == f"data/{ref.sha256}.bin" for ref, _ in paged.pages)
    for _, data in paged.pages:
        d = msgpack.unpackb(data, strict_map_key=False)
        assert "tile_table_zstd" in d and "tile_table" not in d
    raw = pack_manifest(paged.root)
    store = MemoryStore(raw, {ref.file: data for ref, data in paged.pages}, "paged")
    back = resolve_pages(parse_manifest(raw, lazy_payloads=True), store.read_payload, "paged", len(raw))
    assert [t.to_dict() for t in back.tiles if t.page is None] == [t.to_dict() for t in m.tiles if
                                                                   t.id not in {u.id for u in back.tiles if u.page}]


def _damaged(raw, edit):
    d = msgpack.unpackb(raw, strict_map_key=False)
    edit(d)
    return pack_manifest_dict(d)


def _table_edit(fn):
    """An edit of the table inside the zstd frame, packed again."""
    def edit(d):
        t = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)
        fn(t)
        d["tile_table_zstd"] = zstandard.ZstdCompressor().compress(msgpack.packb(t, use_bin_type=True))
    return edit


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(tile_table_zstd={}), "manifest.msgpack: tile_table_zstd: expected a bin (a zstd frame), "
     "got dict"),
    (lambda d: d.update(tile_table_zstd=b"not zstd"), "manifest.msgpack: tile_table_zstd: not a zstd frame"),
    (lambda d: d.update(tile_table_zstd=zstandard.ZstdCompressor(write_content_size=False).compress(b"\x80")),
     "manifest.msgpack: tile_table_zstd: expected a zstd frame stating its size, 1..67108864 bytes, got no size"),
    (lambda d: d.update(tile_table_zstd=zstandard.ZstdCompressor().compress(b"\x92\x01\x02")),
     "manifest.msgpack tile_table_zstd: not a msgpack manifest (expected a map at the top)"),
    (_table_edit(lambda t: t.update(box=np.frombuffer(t["box"], "<f4").astype("<f8").tobytes())),
     "manifest.msgpack: tile_table.box: expected {} bytes ({} x 6 <f4), got {}"),
    (_table_edit(lambda t: t.update(extra=1)), "manifest.msgpack: tile_table: unknown key 'extra'"),
    (lambda d: d.update(tile_table=d["tile_table_zstd"]), "manifest.msgpack: unknown key 'tile_table'"),
])
def test_a_damaged_compact_table_is_rejected_in_one_line(scenes, edit, message):
    raw, m = scenes[True]
    n = len(m.tiles)
    with pytest.raises(FormatError) as e:
        parse_manifest(_damaged(raw, edit))
    assert str(e.value).startswith(message.format(n * 24, n, n * 48)), str(e.value)


def test_a_compact_table_in_an_older_version_is_an_unknown_key(scenes):
    """format.md 6, Versioning: a 1.11 manifest (a version this reader knows) holding `tile_table_zstd` is damage:
    rejected naming the missing tiles, as a 1.11 reader rejects a 1.12 scene."""
    raw, _ = scenes[True]
    with pytest.raises(FormatError, match=r"tiles: missing"):
        parse_manifest(_damaged(raw, lambda d: d.update(version=[1, 11])))


def test_encode_writes_the_compact_table_unless_told_not_to(tmp_path):
    """`encode` writes a tree as 1.16 (the compact table, short digests, relative boxes); `--no-relative-boxes` as
    1.15, `--no-short-digests` as 1.12, `--no-compact-table` as the 1.8 table, the same payloads (the 1.15 and 1.16
    scenes' named by their digests' prefixes)."""
    for name, extra in (("compact", []), ("plain", ["--no-compact-table"]), ("long", ["--no-short-digests"]),
                        ("f32", ["--no-relative-boxes"])):
        r = run_cli("encode", real("fruit_drops_sh3.ply"), tmp_path / name, "--max-leaf-splats", "2000", "-q", *extra)
        assert r.returncode == 0, r.stderr
    compact, plain, long = ((tmp_path / n / "manifest.msgpack").read_bytes() for n in ("compact", "plain", "long"))
    assert "tile_table_zstd" in msgpack.unpackb(compact, strict_map_key=False)
    assert "tile_table" in msgpack.unpackb(plain, strict_map_key=False)
    assert parse_manifest(compact).version == VERSION_1_16 and parse_manifest(plain).version == VERSION_1_10
    assert parse_manifest(long).version == VERSION_1_12
    f32 = (tmp_path / "f32" / "manifest.msgpack").read_bytes()
    assert parse_manifest(f32).version == VERSION_1_15 and len(compact) < len(f32)
    names = {n: sorted(p.name for p in (tmp_path / n / "data").iterdir()) for n in ("compact", "plain", "long",
                                                                                    "f32")}
    assert names["f32"] == names["compact"]
    assert names["plain"] == names["long"] and all(len(n) == 64 + 4 for n in names["plain"])
    assert names["compact"] == sorted(n[:32] + ".bin" for n in names["plain"])
