"""SH codebook (format 1.1): the vector quantiser, its planes in the payloads, decoding, LOD and bad input."""
import numpy as np
import pytest
from conftest import group_planes_of, read_manifest_dict, real, run_cli, write_manifest_dict

from splatstream import vq
from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.encode.codebook import codebook_rows, codebook_weights, order_by_use
from splatstream.encode.jobs import splat_order
from splatstream.errors import FormatError, UsageError
from splatstream.format.codec import codebook_band_values, decode_index_plane, decode_plane, encode_index_plane
from splatstream.format.layout import morton_order
from splatstream.format.planes import SH_INDEX_PLANE
from splatstream.format.texformats import get_format
from splatstream.ply import read_gaussians_ply
from splatstream.scene_decode import decode_scene, read_codebook
from splatstream.store import DirectoryStore, load_manifest
from splatstream.vq import (
    MAX_ENTRIES,
    Codebook,
    auto_entries,
    build_codebook,
    fine_entries,
    large_entries,
    parse_entries,
)


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians_ply(real("fruit_drops_sh3.ply"))


def test_auto_size_and_parsing():
    assert auto_entries(4721) == 64 and auto_entries(1_000_000) == 16384 and auto_entries(6_000_000) == 65536
    assert auto_entries(10) == 64
    assert parse_entries("off", 10) == 0 and parse_entries("auto", 1_000_000) == 16384
    assert parse_entries("300", 1) == 300
    # fine: a power of two near N / 16, at least 256, capped at 16,384 (or auto's size where that is larger).
    assert fine_entries(4721) == 256 and fine_entries(10) == 256 and fine_entries(14_051) == 1024
    assert fine_entries(1_000_000) == 16384 and fine_entries(6_000_000) == 65536
    assert parse_entries("fine", 152_746) == 8192
    # large: a power of two near N / 8, 256..65,536 (flowers, 542,104 splats: the 16-bit index's whole range).
    assert large_entries(542_104) == 65536 and large_entries(4721) == 512 and large_entries(14_051) == 2048
    assert large_entries(10) == 256 and large_entries(6_000_000) == 65536
    assert parse_entries("large", 152_746) == 16384
    for bad in ("0x10", "-1", str(MAX_ENTRIES + 1), "many"):
        with pytest.raises(UsageError):
            parse_entries(bad, 1000)


def test_codebook_is_exact_when_rows_repeat():
    rng = np.random.default_rng(1)
    distinct = rng.normal(size=(300, 45)).astype(np.float32)
    rows = distinct[rng.integers(0, 300, 20000)]
    cb = build_codebook(rows, 512)
    assert len(cb.entries) == 300
    np.testing.assert_array_equal(cb.entries[cb.assign(rows)], rows)


@pytest.mark.parametrize("probes", [1, 2])
def test_tree_codebook_of_a_palette_is_the_palette_bit_for_bit(monkeypatch, probes):
    """Rows holding no more distinct values than the entries (a SOG input's SH palette) get those rows as the
    codebook on the tree path too (before: a fit per cell, and with probes=2 a Lloyd round whose float means left
    most entries an ulp off); rows not in it (LOD tiles' merged splats) still get a tree-nearest entry."""
    monkeypatch.setattr(vq, "FLAT_LIMIT", 0)  # the tree at a test's size
    rng = np.random.default_rng(7)
    palette = rng.choice(np.linspace(-0.5, 0.5, 256).astype(np.float32), size=(3000, 24))
    rows = palette[rng.integers(0, 3000, 20000)]
    weights = rng.random(20000)
    cb = build_codebook(rows, 4096, weights=weights, probes=probes)
    assert len(cb.top) > 1 and cb.probes == probes and cb.starts[-1] == len(cb.entries)
    assert len(cb.entries) == len(np.unique(rows, axis=0)) <= 4096
    labels = cb.assign(rows)
    np.testing.assert_array_equal(cb.entries[labels], rows)  # every row exact
    assert len(np.unique(labels)) == len(cb.entries)  # every entry a row of the palette, none twice
    # The tree holds every row in the cell of its nearest top centroid: the search (rows not in the palette, e.g.
    # LOD tiles' merged splats, take it) finds a palette row itself too.
    np.testing.assert_array_equal(cb.entries[cb._search(rows[:2000])], rows[:2000])
    merged = (rows[:500] + rows[500:1000]) / 2
    near = cb.assign(merged)
    assert near.min() >= 0 and near.max() < len(cb.entries)


def test_tree_codebook_beats_uniform_noise_floor_and_assigns_consistently():
    rng = np.random.default_rng(2)
    centres = rng.normal(size=(2000, 45)).astype(np.float32)
    rows = centres[rng.integers(0, 2000, 60000)] + 0.05 * rng.normal(size=(60000, 45)).astype(np.float32)
    cb = build_codebook(rows, 4096)  # 60,000 x 4096 pairs: the two-level tree
    assert len(cb.top) < len(cb.entries) <= 4096
    labels = cb.assign(rows)
    assert labels.min() >= 0 and labels.max() < len(cb.entries)
    rmse = float(np.sqrt(np.mean((rows - cb.entries[labels]) ** 2)))
    assert rmse < 0.06, rmse  # the noise is 0.05 RMS; the centres are 1.0 RMS apart
    np.testing.assert_array_equal(cb.assign(rows[:1000]), labels[:1000])


def test_weights_pull_entries_towards_important_rows():
    rows = np.concatenate([np.zeros((1000, 3)), np.ones((10, 3))]).astype(np.float32)
    rows[:, 0] += np.linspace(0, 0.1, 1010, dtype=np.float32)  # keep rows distinct
    light = build_codebook(rows, 1)
    heavy = build_codebook(rows, 1, weights=np.r_[np.ones(1000), np.full(10, 1e5)])
    assert light.entries[0, 1] < 0.1 and heavy.entries[0, 1] > 0.9


def test_index_plane_round_trips():
    idx = np.random.default_rng(3).integers(0, 65536, 700)
    plane = encode_index_plane(idx)
    assert plane.format == "index16" and plane.spec is SH_INDEX_PLANE and get_format("index16").bits_per_texel == 16
    np.testing.assert_array_equal(decode_index_plane(plane, 700), idx)
    order = np.random.default_rng(4).permutation(700)
    np.testing.assert_array_equal(decode_index_plane(encode_index_plane(idx, order), 700), idx[order])
    with pytest.raises(ValueError):
        encode_index_plane(np.array([65536]))


def test_encoded_codebook_round_trips_within_one_step(fruit, tmp_path):
    m = encode_gaussians(fruit, tmp_path / "s", EncodeOptions(preset="low", lod=False))
    cb = m.sh_codebook
    assert m.version == (1, 13) and cb.entries == 64 and cb.index_format == "index16"  # 1.13: low's cube565
    assert cb.format == m.formats["sh"] == "norm565"
    assert set(cb.groups) == {"sh1", "sh2", "sh3"} and set(m.tiles[0].groups) == {"base", "sh1"}
    # The codebook the encoder fitted (deterministic for the same input), entries numbered by falling use.
    fitted = order_by_use(build_codebook(codebook_rows(fruit), 64, weights=codebook_weights(fruit)),
                          codebook_rows(fruit))
    planes = read_codebook(DirectoryStore(tmp_path / "s"), m, 3)
    fmt = get_format("norm565")
    for band in (1, 2, 3):
        plane = planes[f"sh{band}"]
        want = codebook_band_values(fitted.entries, band)
        got = decode_plane(plane, 64)
        chunk = np.arange(64) // 256
        extent = (plane.ranges[:, 1].astype(np.float32) - plane.ranges[:, 0].astype(np.float32))[chunk]
        for c in range(3):
            assert np.all(np.abs(got[..., c] - want[..., c]) <= fmt.step(c) * extent[..., c] + 1e-6)
    # Each splat points at its nearest entry (64 entries: a flat codebook, so exactly nearest).
    g = fruit.subset(splat_order(fruit, m.chunk_order))
    tile = m.tiles[0]
    index_plane = group_planes_of(tmp_path / "s", m, tile, "sh1")
    index = decode_index_plane(index_plane["sh_index"], len(g))
    rows = codebook_rows(g)
    d = ((rows[:, None, :] - fitted.entries[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(index, d.argmin(1))
    uses = np.bincount(index, minlength=64)
    assert (np.diff(uses) <= 0).all() and uses[0] > uses[-1]
    # The decoder puts the entries back per splat, band by band; lower degrees need fewer payloads.
    dec = decode_scene(tmp_path / "s")
    assert dec.sh_degree == 3
    full = np.concatenate([decode_plane(planes[f"sh{b}"], 64) for b in (1, 2, 3)], axis=1)
    np.testing.assert_array_equal(dec.sh_rest, full[index])
    assert decode_scene(tmp_path / "s", sh_degree=1).sh_rest.shape == (len(g), 3, 3)
    assert decode_scene(tmp_path / "s", sh_degree=0).sh_degree == 0
    # Payloads: every codebook group is listed, and the bytes are counted.
    listed = [name for tile_, name, _ in m.payloads() if tile_ is None]
    assert listed == ["sh1", "sh2", "sh3"]
    cb_disk = sum(g_.bytes for g_ in cb.groups.values())
    assert m.leaf_bytes_on_disk == cb_disk + sum(g_.bytes for g_ in tile.groups.values())
    assert m.attributes["sh"].gpu_bytes == sum(g_.gpu_bytes for g_ in cb.groups.values()) + \
        tile.groups["sh1"].gpu_bytes


def test_codebook_rms_error_is_bounded(fruit, tmp_path):
    """Weighted RMS SH error of the 64-entry codebook on fruit_drops: measured 0.046, bounded at 0.06."""
    encode_gaussians(fruit, tmp_path / "s", EncodeOptions(preset="low", lod=False))
    dec = decode_scene(tmp_path / "s")
    g = fruit.subset(splat_order(fruit, load_manifest(tmp_path / "s").chunk_order))
    w = codebook_weights(g)
    err = ((dec.sh_rest - g.sh_rest) ** 2).sum(axis=(1, 2))
    assert float(np.sqrt((w * err).sum() / w.sum() / 45)) < 0.06


def test_lod_tiles_share_one_codebook(fruit, tmp_path):
    m = encode_gaussians(fruit, tmp_path / "s", EncodeOptions(preset="very-low", max_leaf_splats=1024))
    assert m.lod.enabled and len(m.tiles) > 4 and m.sh_degree == 3
    for tile in m.tiles:
        assert set(tile.groups) == {"base", "sh1"}
    every = decode_scene(tmp_path / "s", tiles=[t.id for t in m.tiles])
    assert every.sh_rest.shape[1:] == (15, 3) and np.isfinite(every.sh_rest).all()
    leaves = decode_scene(tmp_path / "s")
    assert len(leaves) == len(fruit)


def test_every_scene_is_version_1_2(fruit, tmp_path):
    # Before 1.2 a scene without a codebook was written as 1.0 (1.1 with one); every scene a writer makes now has a
    # manifest checksum, so it is 1.2 (format.md 6), with fields1 sections or (--transport shuffle) without.
    few = fruit.subset(morton_order(fruit.positions)[:600])
    m = encode_gaussians(few, tmp_path / "s", EncodeOptions(preset="medium"))
    assert m.version == (1, 2) and m.sh_codebook is None
    m = encode_gaussians(few, tmp_path / "s", EncodeOptions(preset="low", transport="shuffle"))
    assert m.version == (1, 13) and m.sh_codebook is not None  # 1.13: low's cube565 rotations (format.md 4.5)
    assert {s.filter for _, _, p in m.payloads() for s in p.sections} <= {"none", "shuffle2", "shuffle4"}
    m = encode_gaussians(fruit.subset(np.arange(600)), tmp_path / "t", EncodeOptions(preset="medium", sh_codebook=32))
    assert m.sh_codebook.entries == 32 and m.formats["sh"] == "norm565"


def test_bad_codebook_input_gives_clear_errors(fruit, tmp_path):
    encode_gaussians(fruit.subset(np.arange(300)), tmp_path / "s", EncodeOptions(preset="low", lod=False))
    m = read_manifest_dict(tmp_path / "s")
    m["sh_codebook"]["entries"] = 2  # indices now point past the end
    write_manifest_dict(tmp_path / "s", m)
    with pytest.raises(FormatError, match="codebook"):
        decode_scene(tmp_path / "s")
    del m["sh_codebook"]["groups"]["sh2"]
    write_manifest_dict(tmp_path / "s", m)
    with pytest.raises(FormatError, match="sh_codebook.groups"):
        decode_scene(tmp_path / "s")


def test_cli_codebook_option(tmp_path):
    out = tmp_path / "o"
    r = run_cli("encode", str(real("fruit_drops_sh3.ply")), str(out), "--preset", "medium", "--sh-codebook", "128",
                "-q")
    assert r.returncode == 0, r.stderr
    assert load_manifest(out).sh_codebook.entries == 128
    r = run_cli("encode", str(real("fruit_drops_sh3.ply")), str(tmp_path / "x"), "--sh-codebook", "70000")
    assert r.returncode == 2 and "65536" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x").exists()


def test_codebook_option_refused_where_no_sh_band_is_kept(tmp_path):
    """--sh-codebook on an SH0 input (or with --sh-degree 0) was taken without a word and the scene written without a
    codebook (newuser62): refused in one line naming the option, the input and its SH degree, nothing written. `off`
    is still taken, and the presets whose own codebook is on keep encoding SH0 inputs."""
    donut = str(real("donut_sh0_no_normals.ply"))
    r = run_cli("encode", donut, str(tmp_path / "x"), "--sh-codebook", "fine", "--no-lod", "-q")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "--sh-codebook fine" in r.stderr and donut in r.stderr
    assert "SH degree 0" in r.stderr and not (tmp_path / "x").exists()
    # a partitioned encode refuses it too, before its scan
    r = run_cli("encode", donut, str(tmp_path / "x"), "--sh-codebook", "64", "--memory-per-worker", "2MB", "-q")
    assert r.returncode == 2 and "--sh-codebook 64" in r.stderr and not (tmp_path / "x").exists(), r.stderr
    fruit_path = str(real("fruit_drops_sh3.ply"))
    r = run_cli("encode", fruit_path, str(tmp_path / "x"), "--sh-codebook", "auto", "--sh-degree", "0", "-q")
    assert r.returncode == 2 and "--sh-degree 0" in r.stderr and "SH degree 3" in r.stderr, r.stderr
    assert not (tmp_path / "x").exists()
    r = run_cli("encode", donut, str(tmp_path / "off"), "--sh-codebook", "off", "--no-lod", "-q")
    assert r.returncode == 0, r.stderr
    for preset in ("medium-low", "low", "low-plus-10bit-cb8"):  # codebooks of their own: still encode SH0 inputs
        r = run_cli("encode", donut, str(tmp_path / preset), "--preset", preset, "--no-lod", "-q")
        assert r.returncode == 0, r.stderr
        m = load_manifest(tmp_path / preset)
        assert m.sh_degree == 0 and m.sh_codebook is None
    with pytest.raises(UsageError, match="--sh-codebook 32"):
        encode_gaussians(read_gaussians_ply(donut), tmp_path / "y", EncodeOptions(sh_codebook=32, lod=False))


def test_renumbering_by_use_keeps_every_assignment(monkeypatch):
    """ordered_by_use permutes the entries; every row still gets the same entry (now under its new number), through
    the value lookup and through the tree search alike."""
    import splatstream.vq as vq

    rng = np.random.default_rng(11)
    rows = np.concatenate([rng.normal(size=(3000, 9)), rng.normal(size=(200, 9)) * 0.1 + 2]).astype(np.float32)
    for entries, flat_limit in ((32, vq.FLAT_LIMIT), (256, 0)):  # a flat codebook, then a two-level tree
        monkeypatch.setattr(vq, "FLAT_LIMIT", flat_limit)
        cb = build_codebook(rows, entries)
        assert (len(cb.top) == len(cb.entries)) == (flat_limit > 0)
        labels = cb.assign(rows)
        counts = np.bincount(labels, minlength=len(cb.entries))
        sorted_cb = cb.ordered_by_use(counts)
        new = sorted_cb.assign(rows)
        np.testing.assert_array_equal(sorted_cb.entries[new], cb.entries[labels])
        uses = np.bincount(new, minlength=len(cb.entries))
        assert (np.diff(uses) <= 0).all()
        np.testing.assert_array_equal(sorted_cb.assign(cb.entries), np.argsort(-counts, kind="stable").argsort())


def test_low_plus_10bit_cb8_has_the_large_codebook(fruit, tmp_path):
    """low-plus-10bit-cb8 (issue 32): low-plus-9bit's rotations, scales, colour, their steps and zstd level, 16-bit
    positions on one 1023-level tile step (keyed transport), and the codebook sized "large" (one entry per 8 splats:
    512 on fruit_drops' 4,721 splats, against low-plus-9bit's 64): a lower weighted SH error than low-plus-9bit's."""
    from splatstream.format.presets import PRESET_STEPS, PRESET_TRANSPORT, PRESET_ZSTD_LEVEL, PRESETS, TileStep

    assert PRESETS["low-plus-10bit-cb8"] == {**PRESETS["low-plus-9bit"], "position": "norm16x4"}
    assert PRESET_STEPS["low-plus-10bit-cb8"] == {**PRESET_STEPS["low-plus-9bit"],
                                                  "position": TileStep((1023.0,) * 3, shared=3)}
    assert PRESET_TRANSPORT["low-plus-10bit-cb8"] == "keyed"
    assert PRESET_ZSTD_LEVEL["low-plus-10bit-cb8"] == PRESET_ZSTD_LEVEL["low-plus-9bit"] == 16
    errors = {}
    for preset in ("low-plus-9bit", "low-plus-10bit-cb8"):
        # fields transport: the keyed one re-sorts splats inside chunks, and the decode is compared in splat order
        m = encode_gaussians(fruit, tmp_path / preset, EncodeOptions(preset=preset, lod=False, transport="fields"))
        assert m.sh_codebook.entries == {"low-plus-9bit": 64, "low-plus-10bit-cb8": 512}[preset]
        dec = decode_scene(tmp_path / preset)
        g = fruit.subset(splat_order(fruit, m.chunk_order))
        w = codebook_weights(g)
        err = ((dec.sh_rest - g.sh_rest) ** 2).sum(axis=(1, 2))
        errors[preset] = float(np.sqrt((w * err).sum() / w.sum() / 45))
    # measured 0.0189 (64 entries) and 0.0076 (512 entries)
    assert errors["low-plus-10bit-cb8"] < 0.5 * errors["low-plus-9bit"] and errors["low-plus-10bit-cb8"] < 0.012, \
        errors


def test_two_probe_search_finds_entries_the_tree_misses(monkeypatch):
    """A tree codebook with probes=2 (the "large" codebooks, vq.probes_for): every row gets the nearest entry among
    the children of its two nearest top cells, never farther than the one-cell search's; the fit's extra Lloyd
    round lowers the error on the rows it was fitted to."""
    monkeypatch.setattr(vq, "FLAT_LIMIT", 0)  # the tree at a test's size
    rng = np.random.default_rng(5)
    centres = rng.normal(0, 1, (60, 9)).astype(np.float32)
    rows = (centres[rng.integers(0, 60, 6000)] + rng.normal(0, 0.35, (6000, 9))).astype(np.float32)
    one = build_codebook(rows, 256, seed=3)
    two = build_codebook(rows, 256, seed=3, probes=2)
    assert len(one.top) > 1 and two.probes == 2 and vq.probes_for(65536) == 2 and vq.probes_for(16384) == 1
    np.testing.assert_array_equal(one.top, two.top)  # the same tree; only the entries moved
    lab = two.assign(rows)
    d_all = ((rows[:, None, :] - two.entries[None]) ** 2).sum(-1)
    near_top = np.argsort(((rows[:, None, :] - two.top[None]) ** 2).sum(-1), axis=1)[:, :2]
    cell_of = np.repeat(np.arange(len(two.top)), np.diff(two.starts))
    allowed = (cell_of[None, :] == near_top[:, :1]) | (cell_of[None, :] == near_top[:, 1:2])
    want = np.where(allowed, d_all, np.inf).min(axis=1)
    got = d_all[np.arange(len(rows)), lab]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    tree_only = Codebook(two.entries, two.top, two.starts)
    assert np.all(got <= d_all[np.arange(len(rows)), tree_only.assign(rows)] + 1e-5)
    err = {k: float(np.mean(((rows - c.entries[c.assign(rows)]) ** 2).sum(-1)))
           for k, c in (("one", one), ("two", two))}
    assert err["two"] < 0.99 * err["one"], err


def test_assignment_reuses_its_prepared_entries_without_changing_a_label(monkeypatch):
    """assign() keeps the entries' sorted row hashes and each top cell's entries from its first call (the LOD
    tiles make hundreds of small calls against one codebook): labels are those of a fresh codebook whatever the
    calls' sizes; a row bit-for-bit equal to an entry gets the first such entry (-0.0 is not 0.0); when two
    distinct entries share a hash the exact keys are used instead, with the same labels."""
    monkeypatch.setattr(vq, "FLAT_LIMIT", 0)
    rng = np.random.default_rng(8)
    centres = rng.normal(0, 1, (40, 6)).astype(np.float32)
    rows = (centres[rng.integers(0, 40, 4000)] + rng.normal(0, 0.3, (4000, 6))).astype(np.float32)
    for probes in (1, 2):
        cb = order_by_use(build_codebook(rows, 256, seed=1, probes=probes), rows)
        entries = cb.entries.copy()
        entries[7] = entries[3]  # a duplicate entry: rows equal to it take the first, 3
        zero = np.zeros((1, 6), np.float32)
        entries[9] = zero
        cb = Codebook(entries, cb.top, cb.starts, cb.tree, probes)
        queries = np.concatenate([rows[:1500], entries[::5], entries[[7, 9]], -zero, zero]).astype(np.float32)
        whole = Codebook(entries, cb.top, cb.starts, cb.tree, probes).assign(queries)
        pieces = np.concatenate([cb.assign(queries[i:i + 97]) for i in range(0, len(queries), 97)])
        np.testing.assert_array_equal(pieces, whole)
        assert whole[-4] == 3 and whole[-3] == whole[-1] == 9
        first = {e.tobytes(): i for i, e in reversed(list(enumerate(entries)))}
        exact = [i for i, q in enumerate(queries) if q.tobytes() in first]
        assert [whole[i] for i in exact] == [first[queries[i].tobytes()] for i in exact]
        # Every other row: no entry of the probed cells is nearer than the one it got.
        queries, whole = np.delete(queries, exact, axis=0), np.delete(whole, exact)
        d = ((queries[:, None, :] - entries[None]) ** 2).sum(-1)
        near_top = np.argsort(((queries[:, None, :] - cb.top[None]) ** 2).sum(-1), axis=1)[:, :probes]
        cell_of = np.empty(len(entries), np.int64)
        cell_of[cb.tree if cb.tree is not None else np.arange(len(entries))] = \
            np.repeat(np.arange(len(cb.top)), np.diff(cb.starts))
        allowed = (cell_of[None, :, None] == near_top[:, None, :]).any(axis=2)
        np.testing.assert_allclose(d[np.arange(len(queries)), whole], np.where(allowed, d, np.inf).min(axis=1),
                                   rtol=1e-4, atol=1e-5)
        monkeypatch.setattr(vq, "_row_hashes", lambda r: np.zeros(len(r), np.uint64))  # every hash collides
        colliding = Codebook(entries, cb.top, cb.starts, cb.tree, probes)
        np.testing.assert_array_equal(colliding.assign(queries), whole)
        np.testing.assert_array_equal(colliding.assign(entries[[7, 9]]), [3, 9])
        assert colliding._prepared().exact_keys
        monkeypatch.undo()
        monkeypatch.setattr(vq, "FLAT_LIMIT", 0)


def test_large_codebook_fit_is_deterministic_and_as_close_as_the_full_fit(monkeypatch):
    """The cells of a large codebook (probes > 1) are fitted in vq.LARGE_ITERATIONS Lloyd rounds from a seeding by
    dot products: the same codebook on every run, and an error within 2 % of the full fit's (8 rounds, seeding by
    differences; on flowers 0.017618 against 0.017604)."""
    monkeypatch.setattr(vq, "FLAT_LIMIT", 0)
    rng = np.random.default_rng(21)
    centres = rng.normal(0, 1, (80, 12)).astype(np.float32)
    rows = (centres[rng.integers(0, 80, 8000)] + rng.normal(0, 0.3, (8000, 12))).astype(np.float32)
    w = rng.random(8000) + 0.1
    a = build_codebook(rows, 1024, weights=w, seed=2, probes=2)
    b = build_codebook(rows, 1024, weights=w, seed=2, probes=2)
    np.testing.assert_array_equal(a.entries, b.entries)
    np.testing.assert_array_equal(a.assign(rows), b.assign(rows))
    monkeypatch.setattr(vq, "LARGE_ITERATIONS", vq.ITERATIONS)
    real_kmeans = vq.kmeans
    monkeypatch.setattr(vq, "kmeans", lambda *args, product_seeding=False, **kw: real_kmeans(*args, **kw))
    full = build_codebook(rows, 1024, weights=w, seed=2, probes=2)
    err = {k: float(np.sqrt((w * ((rows - c.entries[c.assign(rows)]) ** 2).sum(-1)).sum() / w.sum()))
           for k, c in (("fast", a), ("full", full))}
    assert not np.array_equal(a.entries, full.entries)
    assert err["fast"] < 1.02 * err["full"], err


def test_a_pickled_codebook_leaves_its_prepared_arrays_behind():
    """A codebook sent to another process (the partitioned encoder's workers) is pickled without the arrays its
    assignments prepared; the copy prepares its own and assigns the same."""
    import pickle

    rng = np.random.default_rng(4)
    rows = rng.normal(size=(3000, 9)).astype(np.float32)
    cb = build_codebook(rows, 64)
    labels = cb.assign(rows)
    assert cb._prep is not None
    copy = pickle.loads(pickle.dumps(cb))
    assert copy._prep is None
    np.testing.assert_array_equal(copy.assign(rows), labels)
    assert len(pickle.dumps(cb)) < 1.2 * len(pickle.dumps(Codebook(cb.entries, cb.top, cb.starts, cb.tree)))
