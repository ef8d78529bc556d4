"""The typed manifest: every field checked once, with an error naming it; the tree and section tables cross-checked.

Each case damages one field of a real encoded scene (the `low` test vector: a codebook scene) and expects a
FormatError naming that field, from the parser and through the CLI (exit 2, one line, no traceback).
"""
import copy
import pathlib
import shutil

import msgpack
import pytest
from conftest import read_manifest_dict, run_cli, write_manifest_dict

from splatstream.errors import FormatError
from splatstream.format.manifest import manifest_from_dict, pack_manifest, parse_manifest

VECTORS = pathlib.Path(__file__).resolve().parents[1] / "format_spec" / "vectors"


# The manifests damaged below: the `low` vector as written before format 1.13 (version 1.2, norm565 rotations), so a
# test that sets an older version (1.0, 1.1) still names only formats of that version.
OLD_LOW = VECTORS / "low-norm565"


@pytest.fixture(scope="module")
def raw():
    return read_manifest_dict(OLD_LOW)


def _set(d, path, value):
    *head, last = path
    for k in head:
        d = d[k]
    if value is _DELETE:
        del d[last]
    else:
        d[last] = value


_DELETE = object()
BASE = ["tiles", 0, "groups", "base"]
SEC = BASE + ["sections"]

# (path, new value, text the error must contain)
CASES = [
    (["splats"], 0, "splats"),
    (["splats"], 259, "splats"),
    (["splats"], "260", "splats"),
    (["leaf_splats"], 261, "splats"),
    (["sh_degree"], 4, "sh_degree"),
    (["chunk_size"], 128, "chunk_size"),
    (["chunk_order"], "random", "chunk_order"),
    (["formats", "position"], "norm9", "formats.position"),
    (["formats", "color"], "norm11", "formats.color"),
    (["formats", "scale"], _DELETE, "formats.scale"),
    (["bounds", "min"], [0.0, 0.0], "bounds.min"),
    (["bounds", "max"], [float("nan"), 0.0, 0.0], "bounds.max"),
    (["up"], [0.0, 0.0, 0.0], "up"),
    (["camera", "fov_y"], 0, "camera.fov_y"),
    (["camera", "eye"], None, "camera.eye"),
    (["lod", "refine"], "add", "lod.refine"),
    (["root"], 5, "root"),
    (["tiles"], [], "tiles"),
    (["tiles"], [1, 2, 3], "tiles[0]"),
    (["tiles", 0, "chunks"], 3, "tiles[0].chunks"),
    (["tiles", 0, "texture"], [16, 16], "tiles[0]"),
    (["tiles", 0, "level"], 1, "root"),
    (["tiles", 0, "children"], [0], "tiles[0].children"),
    (["tiles", 0, "children"], [7], "tiles[0].children"),
    (["tiles", 0, "geometric_error"], -1.0, "geometric_error"),
    (["tiles", 0, "sphere", "radius"], float("inf"), "sphere.radius"),
    (["tiles", 0, "groups", "sh2"], {}, "unknown key 'sh2'"),
    (["tiles", 0, "groups", "sh1"], _DELETE, "groups.sh1"),
    (BASE + ["bytes"], "2683", "groups.base.bytes"),
    (BASE + ["bytes"], 1 << 40, "groups.base.bytes"),
    (BASE + ["raw_bytes"], 5745, "groups.base"),
    (BASE + ["raw_bytes"], 1 << 40, "groups.base.raw_bytes"),
    (BASE + ["gpu_bytes"], 1, "groups.base.gpu_bytes"),
    (BASE + ["sha256"], "ab" * 31, "groups.base.sha256"),
    (BASE + ["file"], "../../etc/passwd", "groups.base.file"),
    (BASE + ["sections"], 5, "groups.base.sections"),
    (SEC + [0, "filter"], "shuffle0", "sections[0].filter"),
    (SEC + [0, "offset"], 4, "sections[0].offset"),
    (SEC + [1, "offset"], 2032, "overlap"),
    (SEC + [0, "size"], 1024, "sections[0].size"),
    (SEC + [0, "format"], "norm565", "sections[0].format"),
    (SEC + [0, "width"], 48, "sections[0]"),
    (SEC + [1, "shape"], [2, 2, 1, 4], "sections[1].shape"),
    (SEC + [1, "dtype"], "f16", "sections[1].dtype"),
    (SEC + [2, "name"], "rotations", "sections[2].name"),
    (["sh_codebook", "entries"], 0, "sh_codebook.entries"),
    (["sh_codebook", "index_format"], "index8", "sh_codebook.index_format"),
    (["sh_codebook", "groups", "sh3"], _DELETE, "sh_codebook.groups.sh3"),
    (["attributes", "position", "gpu_bytes"], -1, "attributes.position.gpu_bytes"),
    (["bytes_on_disk"], "many", "bytes_on_disk"),
    (["version"], [1], "version"),
    (["format"], "splatstreams", "format"),
]


@pytest.mark.parametrize("path,value,field", CASES, ids=[".".join(map(str, c[0])) + f"={c[1]!r}"[:40] for c in CASES])
def test_damaged_field_is_named(raw, path, value, field):
    d = copy.deepcopy(raw)
    _set(d, path, value)
    with pytest.raises(FormatError) as err:
        manifest_from_dict(d, "m")
    assert field in str(err.value), str(err.value)


def test_renamed_key_is_damage_in_a_known_version(raw):
    d = copy.deepcopy(raw)
    d["tiles"][0]["groups"]["base"]["sections"][0]["fil4er"] = d["tiles"][0]["groups"]["base"]["sections"][0].pop(
        "filter")
    with pytest.raises(FormatError, match="sections\\[0\\].filter: missing"):
        manifest_from_dict(d, "m")


def test_manifest_round_trips_to_the_same_bytes():
    for preset in ("high", "medium", "low", "very-low"):
        data = (VECTORS / preset / "manifest.msgpack").read_bytes()
        m = parse_manifest(data)
        assert pack_manifest(m) == data, preset


def test_arrays_view_of_the_tree(tmp_path):
    from conftest import real

    from splatstream.encode import EncodeOptions, encode_gaussians
    from splatstream.ply import read_gaussians_ply

    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium", max_leaf_splats=1024))
    a = m.arrays
    assert len(m.tiles) > 4 and a.parent[m.index_of[m.root]] == -1
    for i, t in enumerate(m.tiles):
        assert tuple(m.tiles[k].id for k in a.children[i]) == t.children
        assert a.base_bytes[i] == t.groups["base"].bytes and a.splats[i] == t.splats
        if t.children:  # children's bounds lie inside their parent's (format_spec/lod.md 2)
            for k in a.children[i]:
                assert (a.box_min[k] >= a.box_min[i] - 1e-9).all() and (a.box_max[k] <= a.box_max[i] + 1e-9).all()
    assert int(a.splats[[m.index_of[t.id] for t in m.leaves]].sum()) == m.splats == len(g)


@pytest.mark.parametrize("command", ["info", "decode", "render"])
def test_cli_names_the_field_without_traceback(tmp_path, raw, command):
    shutil.copytree(OLD_LOW, tmp_path / "s")
    d = copy.deepcopy(raw)
    d["tiles"][0]["groups"]["base"]["sections"][3]["offset"] = 3124
    write_manifest_dict(tmp_path / "s", d)
    args = {"info": [], "decode": [tmp_path / "o.ply"], "render": ["--out", tmp_path / "o.png"]}[command]
    r = run_cli(command, tmp_path / "s", *args)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "sections[3].offset" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o.ply").exists() and not (tmp_path / "o.png").exists()


def test_garbage_manifests(tmp_path):
    for data in (b"", b"\x00" * 100, msgpack.packb([1, 2, 3]), msgpack.packb({"format": "splatstream"}),
                 b"\xc1" * 10):
        with pytest.raises(FormatError):
            parse_manifest(data, "m")


def _payload_case(tmp_path, mutate):
    """A copy of the medium vector whose base payload of tile 0 is replaced by mutate(entry) bytes (the manifest
    updated to name them, so only the payload's own content is wrong)."""
    import hashlib

    shutil.copytree(VECTORS / "medium", tmp_path / "s")
    d = read_manifest_dict(tmp_path / "s")
    base = d["tiles"][0]["groups"]["base"]
    old = tmp_path / "s" / base["file"]
    data = mutate(base, old.read_bytes())
    sha = hashlib.sha256(data).hexdigest()
    (tmp_path / "s" / "data" / f"{sha}.bin").write_bytes(data)
    base.update(file=f"data/{sha}.bin", sha256=sha, bytes=len(data))
    write_manifest_dict(tmp_path / "s", d, settle=True)
    return tmp_path / "s"


def test_payload_content_is_checked(tmp_path):
    import zstandard

    from splatstream.scene_decode import decode_scene

    # not zstd at all
    scene = _payload_case(tmp_path / "a", lambda e, b: b"\x00" * 64)
    with pytest.raises(FormatError, match="not a valid zstd payload"):
        decode_scene(scene)
    # a frame that decompresses to fewer bytes than raw_bytes
    scene = _payload_case(tmp_path / "b", lambda e, b: zstandard.ZstdCompressor().compress(b"\x00" * 100))
    with pytest.raises(FormatError, match="decompresses to 100 bytes"):
        decode_scene(scene)
    # a bomb: a small frame that expands far past raw_bytes is cut off at raw_bytes + 1 and refused
    bomb = zstandard.ZstdCompressor(level=19).compress(b"\x00" * (64 << 20))
    assert len(bomb) < 10_000
    scene = _payload_case(tmp_path / "c", lambda e, b: bomb)
    with pytest.raises(FormatError, match="zstd|decompresses"):
        decode_scene(scene)


def test_non_regular_payload_is_refused_without_blocking(tmp_path):
    import os

    from splatstream.scene_decode import decode_scene

    shutil.copytree(VECTORS / "medium", tmp_path / "s")
    d = read_manifest_dict(tmp_path / "s")
    path = tmp_path / "s" / d["tiles"][0]["groups"]["base"]["file"]
    path.unlink()
    os.mkfifo(path)  # a read would block forever
    with pytest.raises(FormatError, match="not a regular file"):
        decode_scene(tmp_path / "s")
    r = run_cli("render", tmp_path / "s", "--out", tmp_path / "o.png")
    assert r.returncode == 2 and "not a regular file" in r.stderr and "Traceback" not in r.stderr


# --------------------------------------------------------------------------------------------------------------
# The manifest's own checksum (format 1.2, format.md 6 "Checksum"; issue 19 finding 8)


def test_checksum_is_the_sha256_of_the_file_with_its_value_zeroed():
    import hashlib

    for preset, version in (("high", [1, 2]), ("low", [1, 13]), ("low-norm565", [1, 2])):
        data = (VECTORS / preset / "manifest.msgpack").read_bytes()
        d = msgpack.unpackb(data, raw=False)
        assert list(d)[-1] == "checksum" and d["version"] == version
        assert data.endswith(d["checksum"].encode()) and len(d["checksum"]) == 64
        assert hashlib.sha256(data[:-64] + b"0" * 64).hexdigest() == d["checksum"]


def test_every_flipped_bit_of_a_manifest_is_detected():
    """Each byte of the manifest with one bit flipped: never accepted (the checksum or the parser says so)."""
    data = (VECTORS / "medium" / "manifest.msgpack").read_bytes()
    outcomes: dict[str, int] = {}
    for i in range(len(data)):
        corrupt = bytearray(data)
        corrupt[i] ^= 1 << (i % 8)
        with pytest.raises(FormatError) as err:
            parse_manifest(bytes(corrupt), "m")
        kind = "checksum" if "checksum" in str(err.value) else "other"
        outcomes[kind] = outcomes.get(kind, 0) + 1
    # The rest break the msgpack structure, the format or version key first (each still a FormatError).
    assert outcomes["checksum"] > 0.7 * len(data), outcomes


@pytest.mark.parametrize("command", ["info", "decode", "render"])
def test_cli_reports_a_corrupt_manifest(tmp_path, command):
    """The campaign's `fil4er`, `shuffle0` and offset-by-4 edits, made in the bytes (no reseal): the checksum
    names the file (before 1.2 only the schema could catch them, and only some)."""
    shutil.copytree(VECTORS / "medium", tmp_path / "s")
    path = tmp_path / "s" / "manifest.msgpack"
    data = path.read_bytes()
    path.write_bytes(data.replace(b"shuffle4", b"shuffle2", 1))
    args = {"info": [], "decode": [tmp_path / "o.ply"], "render": ["--out", tmp_path / "o.png"]}[command]
    r = run_cli(command, tmp_path / "s", *args)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"{path}: checksum: checksum mismatch" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_checksum_must_be_present_last_and_well_formed(tmp_path, raw):
    base = msgpack.packb(raw, use_bin_type=True)
    assert parse_manifest(base, "m").version == (1, 2)
    d = copy.deepcopy(raw)
    del d["checksum"]
    with pytest.raises(FormatError, match="checksum: missing"):
        parse_manifest(msgpack.packb(d, use_bin_type=True), "m")
    d = copy.deepcopy(raw)
    d = {"checksum": d.pop("checksum"), **d}  # first instead of last
    with pytest.raises(FormatError, match="checksum: not the manifest's last key"):
        parse_manifest(msgpack.packb(d, use_bin_type=True), "m")
    d = copy.deepcopy(raw)
    d["checksum"] = d["checksum"].upper()
    with pytest.raises(FormatError, match="checksum: expected 64 lowercase hex digits"):
        parse_manifest(msgpack.packb(d, use_bin_type=True), "m")
    with pytest.raises(FormatError, match="not a msgpack manifest"):  # bytes after the map
        parse_manifest(base + b"\x00", "m")


def test_older_manifests_without_checksum_still_read(tmp_path, raw):
    """1.0 and 1.1 manifests have no checksum and still read; in them a `checksum` key is an unknown key."""
    from splatstream.scene_decode import decode_scene

    shutil.copytree(OLD_LOW, tmp_path / "s")
    d = copy.deepcopy(raw)
    del d["checksum"]
    d["version"] = [1, 1]
    (tmp_path / "s" / "manifest.msgpack").write_bytes(msgpack.packb(d, use_bin_type=True))
    assert len(decode_scene(tmp_path / "s")) == 260
    d["checksum"] = raw["checksum"]
    (tmp_path / "s" / "manifest.msgpack").write_bytes(msgpack.packb(d, use_bin_type=True))
    with pytest.raises(FormatError, match="unknown key 'checksum'"):
        decode_scene(tmp_path / "s")
    shutil.copytree(VECTORS / "medium", tmp_path / "m")
    d = read_manifest_dict(tmp_path / "m")
    d["version"] = [1, 0]
    write_manifest_dict(tmp_path / "m", d)  # written as a 1.0 file: no checksum
    assert "checksum" not in read_manifest_dict(tmp_path / "m") and len(decode_scene(tmp_path / "m")) == 260


def test_totals_are_cross_checked(tmp_path, raw):
    """gpu_bytes and leaf_bytes_on_disk are recomputed from the entries, bytes_on_disk from the files (1.2)."""
    for key, delta in (("gpu_bytes", 16), ("leaf_bytes_on_disk", -1)):
        d = copy.deepcopy(raw)
        d[key] += delta
        with pytest.raises(FormatError, match=f"^m: {key}: "):
            manifest_from_dict(d, "m")
    d = copy.deepcopy(raw)
    d["bytes_on_disk"] += 1
    from splatstream.format.manifest import pack_manifest_dict

    with pytest.raises(FormatError, match="bytes_on_disk: .* but the payload files and the manifest are"):
        parse_manifest(pack_manifest_dict(d), "m")


TILE_CASES = [c for c in CASES if c[0][:2] == ["tiles", 0] and "groups" in c[0]]


@pytest.mark.parametrize("path,value,field", TILE_CASES,
                         ids=[".".join(map(str, c[0])) + f"={c[1]!r}"[:40] for c in TILE_CASES])
def test_lazily_checked_payload_entries_name_the_same_field(raw, path, value, field):
    """parse_manifest(lazy_payloads=True), the streaming client's: a damaged payload entry raises the FormatError the
    eager parse raises, at the parse (where the damage reaches the totals) or when the entry is first read."""
    assert len(TILE_CASES) >= 10
    d = copy.deepcopy(raw)
    _set(d, path, value)
    with pytest.raises(FormatError) as eager:
        manifest_from_dict(d, "m")
    try:
        m = manifest_from_dict(d, "m", lazy_payloads=True)
        tile = next(t for t in m.tiles if t.id == d["tiles"][0]["id"])
        for name in tile.groups:
            tile.groups[name]
    except FormatError as exc:
        lazy = str(exc)
    else:
        pytest.fail("the damaged entry was never refused")
    assert lazy == str(eager.value)


def test_lazy_parse_reads_the_same_manifest():
    """The lazily checked manifest has the same entries, totals and per-tile arrays as the eager one."""
    data = (VECTORS / "low" / "manifest.msgpack").read_bytes()
    eager, lazy = parse_manifest(data), parse_manifest(data, lazy_payloads=True)
    assert [dict(t.groups) for t in lazy.tiles] == [dict(t.groups) for t in eager.tiles]
    assert lazy.payload_bytes() == eager.payload_bytes()
    for f in ("base_bytes", "band_bytes", "gpu_bytes", "splats", "parent"):
        assert (getattr(lazy.arrays, f) == getattr(eager.arrays, f)).all(), f
