"""Format 1.16 (format_spec/format.md 6.2, "Boxes relative to the parent's"): a compact table holds the box of each
tile whose parent is a row of the same table as u8 steps of the parent's decoded box (`box8`), the others' (the
root; a page's top tiles) as f32 rounded outward (`anchor_box`), and each sphere's radius as u8 steps of its box's
half diagonal (`radius8`; `radius_far`, f32, beyond 254/128 of it). What the encoder holds is what a reader gets,
bit for bit; the decoded bounds hold the tree's f64 ones; a paged scene's pages decode against their own anchors;
damaged columns and older readers are refused in one line naming the column."""
import msgpack
import numpy as np
import pytest
import zstandard
from conftest import real

from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.errors import FormatError
from splatstream.format.manifest import pack_manifest, pack_manifest_dict, parse_manifest, resolve_pages, split_pages
from splatstream.format.manifest.table import (
    RADIUS_FAR,
    decode_child_boxes,
    decode_radii,
    encode_relative,
    half_diagonals,
    up_f32,
)
from splatstream.format.manifest.versions import VERSION_1_15, VERSION_1_16
from splatstream.ply import read_gaussians_ply
from splatstream.store import MemoryStore, read_manifest


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians_ply(real("fruit_drops_sh3.ply"))


@pytest.fixture(scope="module")
def scenes(fruit):
    """The same tree as 1.16 (the default), as 1.15 (relative_boxes off) and as the 1.8 table (its f64 bounds):
    (manifest bytes, manifest)."""
    out = {}
    for key, opts in (("1.16", {}), ("1.15", {"relative_boxes": False}), ("f64", {"compact_table": False})):
        store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=300, **opts))
        out[key] = (store.read_manifest(), read_manifest(store))
    return out


def _table(raw: bytes) -> dict:
    d = msgpack.unpackb(raw, strict_map_key=False)
    return msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)


def _holds(a, b) -> None:
    """a's bounds (decoded) hold b's (the tree's f64 ones): box outward, sphere about a's box middle holding b's
    sphere, geometric error no smaller."""
    assert all(x <= y for x, y in zip(a.box.min, b.box.min, strict=True))
    assert all(x >= y for x, y in zip(a.box.max, b.box.max, strict=True))
    moved = float(np.linalg.norm(np.subtract(a.sphere_center, b.sphere_center)))
    assert a.sphere_radius >= b.sphere_radius + moved and a.geometric_error >= b.geometric_error


def test_a_1_16_table_reads_back_bit_for_bit_and_holds_the_tree(scenes):
    raw, m = scenes["1.16"]
    raw15, m15 = scenes["1.15"]
    _, plain = scenes["f64"]
    assert m.version == VERSION_1_16 and m15.version == VERSION_1_15
    t = _table(raw)
    n = len(m.tiles)
    assert {"anchor_box", "box8", "radius8", "radius_far"} <= t.keys() and not {"box", "radius", "sphere"} & t.keys()
    assert len(t["anchor_box"]) == 24 and len(t["box8"]) == 6 * (n - 1) and len(t["radius8"]) == n
    assert len(t["radius_far"]) == 4 * t["radius8"].count(RADIUS_FAR)
    assert parse_manifest(raw) == m  # the encoder holds what a reader gets, bit for bit
    assert m.compacted() == m  # compacting twice is compacting once
    for a, b, c in zip(m.tiles, plain.tiles, m15.tiles, strict=True):
        assert a.children == b.children and a.groups == c.groups
        _holds(a, b)
        assert a.sphere_center == tuple((x + y) * 0.5 for x, y in zip(a.box.min, a.box.max, strict=True))
        assert a.geometric_error == c.geometric_error
        # each side within one step of the parent's extent (at most 1/255 of the root's box on the root's children)
    root = m.tiles[m.root]
    assert root.box == m15.tiles[m15.root].box  # the anchor: 1.15's f32 box
    assert len(raw) < len(raw15) - 250


def test_the_codec_rounds_outward_grows_parents_and_takes_far_radii():
    """encode_relative over a random three-level tree whose children stick out of their parents (grown bottom-up
    first), with degenerate (flat) boxes and radii beyond 254/128 of the half diagonal."""
    rng = np.random.default_rng(7)
    parent = np.array([-1, 0, 0, 1, 1, 2, 2, 2])
    level = np.array([0, 1, 1, 2, 2, 2, 2, 2])
    lo = rng.normal(0, 10, (8, 3))
    box = np.concatenate([lo, lo + rng.uniform(0, 5, (8, 3))], axis=1)
    box[5, [2, 5]] = 1.5  # a flat box
    sphere = np.concatenate([(box[:, :3] + box[:, 3:]) / 2 + rng.normal(0, 0.01, (8, 3)),
                             half_diagonals(box)[:, None] * rng.uniform(0.5, 1.3, (8, 1))], axis=1)
    sphere[4, 3] = 3 * half_diagonals(box[4:5])[0] + 1  # beyond 254/128 h: radius_far
    anchor_box, box8, radius8, far, dec, dec_sphere, grown = encode_relative(box, sphere, parent, level)
    assert grown >= 1 and anchor_box.shape == (1, 6) and box8.shape == (7, 6) and radius8[4] == RADIUS_FAR
    assert len(far) == int((radius8 == RADIUS_FAR).sum()) and float(far[0]) == float(up_f32([dec_sphere[4, 3]])[0])
    assert (dec[:, :3] <= box[:, :3]).all() and (dec[:, 3:] >= box[:, 3:]).all()
    for child in range(1, 8):  # a child inside its parent's decoded box, as the reader decodes it
        p = parent[child]
        assert (dec[child, :3] >= dec[p, :3]).all() and (dec[child, 3:] <= dec[p, 3:]).all()
        assert np.array_equal(decode_child_boxes(dec[p:p + 1], box8[child - 1:child].astype(np.int64)),
                              dec[child:child + 1])
    mid = (dec[:, :3] + dec[:, 3:]) * 0.5
    assert np.array_equal(dec_sphere[:, :3], mid)
    need = sphere[:, 3] + np.linalg.norm(mid - sphere[:, :3], axis=1)
    assert (dec_sphere[:, 3] >= need).all()
    assert np.array_equal(decode_radii(half_diagonals(dec), radius8, far), dec_sphere[:, 3])
    # the smallest step: one less would not hold the sphere
    q = radius8.astype(np.int64)
    near = (q > 0) & (q < RADIUS_FAR)
    assert (half_diagonals(dec)[near] * ((q[near] - 1) / 128) < need[near]).all()
    again = encode_relative(dec, dec_sphere, parent, level)
    assert again[6] == 0 and all(np.array_equal(x, y) for x, y in zip(again[:6], (anchor_box, box8, radius8, far,
                                                                                   dec, dec_sphere), strict=True))


def test_a_paged_1_16_scene_codes_each_pages_top_tiles_as_anchors(fruit):
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=300, page_tiles=4, page_levels=2))
    whole = read_manifest(store)  # every page read and checked
    assert whole.version == VERSION_1_16 and whole.paged is not None and whole.paged.pages > 1
    _, plain = (None, read_manifest(encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=300,
                                                                           compact_table=False))))
    for a, b in zip(whole.tiles, plain.tiles, strict=True):
        _holds(a, b)
    by_id = {t.id: t for t in whole.tiles}
    for t in whole.tiles:
        if t.page is None:
            continue
        d = msgpack.unpackb(store.read_payload(t.page), strict_map_key=False)
        table = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)
        tops = np.frombuffer(table["anchor_box"], "<f4").reshape(-1, 6)
        assert len(tops) == len(t.children)  # the page's top tiles: the children of the tile naming it
        for row, c in zip(tops.tolist(), sorted(t.children), strict=True):
            assert tuple(row[:3]) == by_id[c].box.min and tuple(row[3:]) == by_id[c].box.max
    # the encoder's manifest, compacted for these pages, is what the pages give back: split again, the same bytes
    held = whole.compacted(page_levels=2)
    assert held.tiles == whole.tiles
    paged = split_pages(held, 2)
    raw = pack_manifest(paged.root)
    back = resolve_pages(parse_manifest(raw), MemoryStore(raw, dict((r.file, b) for r, b in paged.pages),
                                                          "p").read_payload, "p", len(raw))
    assert back.tiles == whole.tiles


def _edited(raw, version=None, table_edit=None):
    d = msgpack.unpackb(raw, strict_map_key=False)
    if version is not None:
        d["version"] = version
    if table_edit is not None:
        t = _table(raw)
        table_edit(t)
        d["tile_table_zstd"] = zstandard.ZstdCompressor().compress(msgpack.packb(t, use_bin_type=True))
    return pack_manifest_dict(d)


def _set_byte(key, i, value):
    def edit(t):
        b = bytearray(t[key])
        b[i] = value
        t[key] = bytes(b)
    return edit


def _anchor(values):
    return lambda t: t.update(anchor_box=np.array(values, "<f4").tobytes())


@pytest.mark.parametrize("version, edit, message", [
    ([1, 15], None, r"manifest.msgpack: tile_table.box: missing"),  # a 1.15 reader
    ([1, 14], None, r"manifest.msgpack: tile_table.box: missing"),  # a 1.12-1.14 reader
    (None, lambda t: t.pop("box8"), r"tile_table.box8: missing"),
    (None, lambda t: t.update(box8=t["box8"][:-1]), r"tile_table.box8: expected (\d+) bytes \(\d+ x 6 u1\), got"),
    (None, lambda t: t.update(anchor_box=t["anchor_box"] * 2), r"tile_table.anchor_box: expected 24 bytes \(1 x 6 "
     r"<f4\), got 48"),
    (None, lambda t: t.update(radius8=t["radius8"][1:]), r"tile_table.radius8: expected \d+ bytes"),
    (None, lambda t: t.update(radius_far=t["radius_far"] + b"\0\0\0\0"), r"tile_table.radius_far: expected \d+ "
     r"bytes"),
    (None, _set_byte("radius8", 0, RADIUS_FAR), r"tile_table.radius_far: expected \d+ bytes"),
    (None, lambda t: (_set_byte("box8", 0, 200)(t), _set_byte("box8", 3, 200)(t)),
     r"tile_table.box8\[0\]: steps \[200, \d+, \d+, 200, \d+, \d+\] make min .* exceed max"),
    (None, _anchor([1, 0, 0, 0, 1, 1]), r"tile_table.anchor_box\[0\]: expected finite min <= max, got \[1.0, 0.0"),
    (None, _anchor([np.nan, 0, 0, 1, 1, 1]), r"tile_table.anchor_box\[0\]: expected finite min <= max, got \[nan"),
    (None, lambda t: t.update(box=b""), r"tile_table: unknown key 'box'"),
])
def test_damaged_1_16_tables_and_older_readers_are_refused_naming_the_column(scenes, version, edit, message):
    raw, _ = scenes["1.16"]
    with pytest.raises(FormatError, match=message):
        parse_manifest(_edited(raw, version, edit))


def test_a_negative_far_radius_is_refused(scenes):
    raw, _ = scenes["1.16"]

    def edit(t):
        _set_byte("radius8", 0, RADIUS_FAR)(t)
        far = np.frombuffer(t["radius_far"], "<f4")
        t["radius_far"] = np.concatenate([[-1.0], far]).astype("<f4").tobytes()
    with pytest.raises(FormatError, match=r"tile_table.radius_far\[0\]: expected a finite radius >= 0, got -1.0"):
        parse_manifest(_edited(raw, None, edit))


def test_a_1_16_parse_keeps_numpy_ma_off_the_first_frames_path(scenes, tmp_path):
    """The first parse of a 1.16 table in a process (the first frame's manifest step) imports nothing beyond what a
    1.15 parse does: numpy's first 1-D np.unique imports numpy.ma, which on the GPU machine added about 70 ms to a
    fresh client's first frame (BENCHMARKS.md, r34)."""
    import subprocess
    import sys

    from conftest import ROOT

    for key in ("1.16", "1.15"):
        path = tmp_path / f"{key}.msgpack"
        path.write_bytes(scenes[key][0])
        code = ("import sys; from splatstream.format.manifest import parse_manifest; "
                f"parse_manifest(open({str(path)!r}, 'rb').read(), 'x', lazy_payloads=True); "
                "print('numpy.ma' in sys.modules)")
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
        assert out.stdout.strip() == "False", (key, out.stdout, out.stderr)
