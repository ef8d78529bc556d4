"""The tile table (format_spec/format.md 6.2, version 1.8): an LOD tree's tiles column-wise, read back into the same
records as the tile maps of 1.0-1.7, and rejected field by field when damaged."""
import copy
import hashlib
import pickle
from dataclasses import replace

import msgpack
import numpy as np
import pytest
from conftest import real

from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.errors import FormatError
from splatstream.format.manifest import (
    pack_manifest,
    pack_manifest_dict,
    parse_manifest,
    resolve_pages,
    split_pages,
    tile_rows,
)
from splatstream.format.manifest.versions import FORMAT_VERSION, VERSION_1_7, VERSION_1_8, VERSION_1_10
from splatstream.ply import read_gaussians_ply
from splatstream.store import MemoryStore, read_manifest


@pytest.fixture(scope="module")
def scene():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    # the 1.8 table (the 1.12 compact one, its f32 bounds zstd-compressed: test_manifest_compact.py)
    store = encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=300, compact_table=False))
    return store.read_manifest(), read_manifest(store)


def _old(m):
    """The same tree as a 1.7 writer writes it (tile maps)."""
    m = replace(m, version=VERSION_1_7, lod=replace(m.lod, merge=None, viewing_scale_px=None))  # no 1.9 record
    return m.with_bytes_on_disk(m.payload_bytes())


def test_an_lod_tree_is_written_as_a_tile_table_and_reads_back_as_the_tile_maps(scene):
    raw, m = scene
    d = msgpack.unpackb(raw, strict_map_key=False)
    assert d["version"] == [1, 10] and "tile_table" in d and "tiles" not in d  # 1.10: the scales per level
    old = parse_manifest(pack_manifest(_old(m)))
    for lazy in (False, True):
        back = parse_manifest(raw, lazy_payloads=lazy)
        assert len(back.tiles) == len(old.tiles) > 1
        for a, b in zip(back.tiles, old.tiles, strict=True):
            assert a.to_dict() == b.to_dict()
            assert dict(a.groups) == dict(b.groups)
        for name, arr in tile_rows(back.tiles).items():  # the columns' sizes, without reading an entry
            assert np.array_equal(arr, tile_rows(old.tiles)[name]), name
    assert back.gpu_bytes == old.gpu_bytes and back.payload_bytes() == old.payload_bytes()
    # a fifth of the bytes: the tiles cost 1.0-1.7 about 1 KB each
    assert len(raw) * 3 < len(pack_manifest(_old(m)))


def test_a_tile_is_pickled_with_plain_entries(scene):
    raw, _ = scene
    t = parse_manifest(raw).tiles[1]
    back = pickle.loads(pickle.dumps(t))
    assert type(back.groups) is dict and back == t and back.groups["base"] == t.groups["base"]


def test_a_one_tile_scene_keeps_its_version():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    m = read_manifest(encode_in_memory(g, EncodeOptions(preset="medium", lod=False)))
    assert len(m.tiles) == 1 and m.version < VERSION_1_8 and "tiles" in m.to_dict()


def test_a_paged_tree_writes_its_pages_as_tile_tables(scene):
    _, m = scene
    paged = split_pages(m, 2)
    assert paged.root.version == VERSION_1_10
    for _, data in paged.pages:
        d = msgpack.unpackb(data, strict_map_key=False)
        assert "tile_table" in d and "tiles" not in d
    raw = pack_manifest(paged.root)
    store = MemoryStore(raw, {ref.file: data for ref, data in paged.pages}, "paged")
    back = resolve_pages(parse_manifest(raw, lazy_payloads=True), store.read_payload, "paged", len(raw))
    assert [replace(t, page=None).to_dict() for t in back.tiles] == [t.to_dict() for t in m.tiles]


def _col(d, key, dtype):
    return np.frombuffer(d["tile_table"][key], dtype).copy()


def _set(d, key, a):
    d["tile_table"][key] = np.ascontiguousarray(a).tobytes()


def _edit_col(key, dtype, fn):
    def edit(d):
        a = _col(d, key, dtype)
        fn(a)
        _set(d, key, a)
    return edit


def _range_section_size(d, delta):
    """Change the size of tile 1's first range section (a range's size is exact)."""
    t = d["tile_table"]
    layouts = t["layouts"]
    layout = np.frombuffer(t["layout"], "<u2").reshape(t["count"], -1)
    counts = np.array([len(lay) for lay in layouts])[layout.reshape(-1)]
    g = layout.shape[1]
    first = int(counts[:g].sum())  # tile 1, group base
    k = next(k for k, (name, _) in enumerate(layouts[layout[1, 0]]) if name.endswith(".range"))
    sizes = _col(d, "sizes", "<u4")
    sizes[first + k] += delta
    _set(d, "sizes", sizes)
    return k


@pytest.mark.parametrize("edit, problem", [
    (lambda d: d["tile_table"].update(sizes=d["tile_table"]["sizes"][:-1]), r"tile_table\.sizes: expected \d+ bytes"),
    (lambda d: d["tile_table"].pop("bytes"), r"tile_table\.bytes: missing"),
    (lambda d: d["tile_table"].update(extra=1), r"tile_table: unknown key 'extra'"),
    (lambda d: d["tile_table"].update(groups=["base"]), r"tile_table\.groups: expected \['base', 'sh1'"),
    (lambda d: d["tile_table"].update(count=0), r"tile_table\.count: expected an integer 1\.\."),
    (lambda d: d["tile_table"].update(box=3), r"tile_table\.box: expected a bin"),
    (_edit_col("splats", "<u4", lambda a: a.__setitem__(0, 0)), r"tile_table\.splats\[0\]: expected an integer 1"),
    (_edit_col("id", "<u4", lambda a: a.__setitem__(2, a[1])), r"tile_table\.id\[2\]: tile id \d+ appears twice"),
    (_edit_col("texture", "<u2", lambda a: a.__setitem__(0, 0)), r"tile_table\.texture\[0\]: 0x\d+ blocks"),
    (_edit_col("box", "<f8", lambda a: a.__setitem__(6, a[9] + 1)), r"tile_table\.box\[1\]: min .* exceeds max"),
    (_edit_col("sphere", "<f8", lambda a: a.__setitem__(3, np.nan)), r"tile_table\.sphere\[0\]: expected finite"),
    (_edit_col("geometric_error", "<f8", lambda a: a.__setitem__(1, -1)), r"tile_table\.geometric_error\[1\]"),
    (_edit_col("layout", "<u2", lambda a: a.__setitem__(0, 999)), r"tile_table\.layout\[0\]: expected section "
     r"layouts 0\.\."),
    (_edit_col("bytes", "<u4", lambda a: a.__setitem__(0, 2**32 - 1)), r"tile_table\[0\]\.groups\.base\.bytes: "
     r"expected an integer"),
    (lambda d: d["tile_table"]["layouts"][0].__setitem__(0, ["pos", "none"]), r"tile_table\[\d+\]\.groups\.\w+\."
     r"sections\[0\]\.name: unexpected section 'pos'"),
    (lambda d: d["tile_table"]["layouts"][0].__setitem__(0, [d["tile_table"]["layouts"][0][0][0], "zip"]),
     r"tile_table\[\d+\]\.groups\.\w+\.sections\[0\]\.filter: unknown filter 'zip'"),
    (lambda d: d["tile_table"]["layouts"][0].pop(), r"tile_table\.sizes: expected \d+ bytes"),
    (lambda d: d["tile_table"]["layouts"].__setitem__(0, 5), r"tile_table\.layouts\[0\]: expected a list"),
    (lambda d: _range_section_size(d, 4), r"tile_table\[1\]\.groups\.base\.sections\[\d\]\.size: \d+ bytes for a "
     r"f(16|32) range"),
])
def test_a_damaged_table_is_refused_naming_the_field(scene, edit, problem):
    raw, _ = scene
    d = msgpack.unpackb(raw, strict_map_key=False)
    edit(d)
    with pytest.raises(FormatError, match=problem) as err:
        parse_manifest(pack_manifest_dict(d))
    assert "\n" not in str(err.value)
    with pytest.raises(FormatError, match=problem):  # the streaming client's parse checks the table as a whole
        parse_manifest(pack_manifest_dict(d), lazy_payloads=True)


def test_versions_and_the_table(scene):
    raw, _ = scene
    d = msgpack.unpackb(raw, strict_map_key=False)
    older = copy.deepcopy(d)
    older["version"] = [1, 7]  # a 1.7 manifest has tile maps: its reader names the missing key
    with pytest.raises(FormatError, match=r"tiles: missing"):
        parse_manifest(pack_manifest_dict(older))
    newer = copy.deepcopy(d)
    # A newer minor version's key in the table is ignored (format.md 6, Versioning).
    newer["version"] = [1, FORMAT_VERSION[1] + 1]
    newer["tile_table"]["later"] = b"x"
    assert len(parse_manifest(pack_manifest_dict(newer)).tiles) == d["tile_table"]["count"]


def test_the_page_column_names_the_pages(scene):
    _, m = scene
    paged = split_pages(m, 2)
    ref, data = paged.pages[-1]
    assert hashlib.sha256(data).hexdigest() == ref.sha256
    root = parse_manifest(pack_manifest(paged.root))
    assert {t.page.sha256 for t in root.tiles if t.page} <= {r.sha256 for r, _ in paged.pages}
