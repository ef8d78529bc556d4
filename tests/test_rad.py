"""`splatstream export-rad` (splatstream/writers/rad.py, rad_export.py): our LOD tree as Spark 2's .rad, read back
by our reader (readers/rad.py) as a splat tree, as its finest level (`convert`) and as a tree of ours
(rad_import.py, what `view` streams). Spark itself draws it in tests/test_spark_browser.py."""
from __future__ import annotations

import json
import struct
import subprocess
import sys

import numpy as np
import pytest
from browser import compare
from conftest import ROOT, run_cli
from test_sog_lod import _splats, same_splats

from client_gl.stream.sources import StoreSource, open_source
from splatstream.encode import encode_file
from splatstream.errors import InputError
from splatstream.gaussians import covariances
from splatstream.io import read_gaussians
from splatstream.rad_export import export_rad
from splatstream.rad_import import encode_rad
from splatstream.readers.rad import read_rad_tree
from splatstream.scene_decode import decode_scene
from splatstream.store import load_manifest
from splatstream.writers.rad import (
    CHUNK_SPLATS,
    RAD_CHUNK_MAGIC,
    RAD_MAGIC,
    RadTree,
    TreeTile,
    merge_splats,
    nearest,
    nearest_brute,
    rad_bytes,
    rad_tree,
)

SOURCE = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """fruit_drops (4721 splats) encoded with 1024-splat leaves (7 levels), exported as .rad. The grid merge named:
    the counts below are its tree's (the default, auto, shares each level's splats out by cost, and its grouping may
    still change)."""
    work = tmp_path_factory.mktemp("rad")
    encode_file(SOURCE, work / "scene", max_leaf_splats=1024, lod_merge="grid")
    report = export_rad(work / "scene", work / "scene.rad")
    return work, report


def our_cut(scene, manifest, depth: int):
    """Our REPLACE cut at `depth`: the tiles at that depth and the leaves above it."""
    ids = [t.id for t in manifest.tiles if t.level == depth or (t.level < depth and not t.children)]
    return decode_scene(scene, tiles=ids, manifest=manifest)


def test_header_chunks_and_tree(exported):
    work, report = exported
    data = (work / "scene.rad").read_bytes()
    magic, length = struct.unpack_from("<II", data)
    meta = json.loads(data[8:8 + length])
    assert magic == RAD_MAGIC and meta["version"] == 1 and meta["type"] == "gsplat" and meta["lodTree"] is True
    assert meta["count"] == report.splats == 1 + 9376 and meta["maxSh"] == 3 and meta["chunkSize"] == CHUNK_SPLATS
    start = 8 + ((length + 7) & ~7)
    assert len(meta["chunks"]) == 1 and meta["chunks"][0]["offset"] == 0
    assert start + meta["allChunkBytes"] == len(data) == report.bytes
    assert struct.unpack_from("<I", data, start)[0] == RAD_CHUNK_MAGIC
    tree = read_rad_tree(work / "scene.rad")
    # Breadth-first: each splat's children are one run right after the children of the splats before it.
    count, first = tree.child_count.astype(np.int64), tree.child_start.astype(np.int64)
    runs = first[count > 0]
    assert runs[0] == 1 and (np.diff(runs) == count[count > 0][:-1]).all()
    assert count.sum() == len(tree.splats) - 1 and report.leaf_splats == int((count == 0).sum()) == 4721
    assert report.levels == tree.levels() == 8 and report.tiles == 39


def test_every_level_is_our_cut(exported):
    """RAD's cut at depth d + 1 (d + 1 below its merged root) is our cut at depth d, splat for splat."""
    work, _ = exported
    manifest = load_manifest(work / "scene")
    tree = read_rad_tree(work / "scene.rad")
    root = tree.splats.subset(np.array([0]))
    top = decode_scene(work / "scene", tiles=[manifest.root], manifest=manifest)
    # The root splat is the opacity-weighted mean of our root tile.
    w = top.opacities / top.opacities.sum()
    assert np.allclose(root.positions[0], w @ top.positions, atol=1e-4)
    for depth in range(max(t.level for t in manifest.tiles) + 1):
        rows = tree.cut(depth + 1)
        assert same_splats(tree.splats.subset(rows), our_cut(work / "scene", manifest, depth)) < 1e-5, depth
    # No interior splat of ours is left without children (it would be drawn at every distance by Spark).
    assert ((tree.child_count == 0) == (tree.depth == tree.levels() - 1)).all()


def test_round_trip_into_our_tree_keeps_every_level(exported):
    """ours -> RAD -> ours (rad_import, what `view` streams): every cut of the new tree is the original's."""
    work, _ = exported
    manifest = load_manifest(work / "scene")
    store = encode_rad(work / "scene.rad")
    back = load_manifest(store)
    depth = max(t.level for t in manifest.tiles)
    assert max(t.level for t in back.tiles) == depth
    for d in range(depth + 1):
        assert same_splats(our_cut(store, back, d), our_cut(work / "scene", manifest, d)) < 2e-3, d


def test_convert_reads_the_finest_level(exported, tmp_path):
    work, _ = exported
    r = run_cli("convert", work / "scene.rad", tmp_path / "out.ply", "-q")
    assert r.returncode == 0, r.stderr
    g = read_gaussians(tmp_path / "out.ply")
    ours = decode_scene(work / "scene")
    assert len(g) == 4721 and same_splats(g, ours) < 1e-5
    assert np.abs(np.sort(g.sh_rest.ravel()) - np.sort(ours.sh_rest.ravel())).max() < 2e-3  # f16 SH


def test_cli_export_and_errors(exported, tmp_path):
    work, _ = exported
    cli = [sys.executable, "-m", "cli"]
    r = subprocess.run([*cli, "export-rad", str(work / "scene"), str(tmp_path / "o.rad"), "--sh-degree", "0"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "8 tree levels" in r.stderr and "4,721 splats of full detail" in r.stderr
    assert read_rad_tree(tmp_path / "o.rad").splats.sh_degree == 0
    for args, message in (([tmp_path / "missing", tmp_path / "o.rad"], "missing"),
                          ([work / "scene", tmp_path / "nodir" / "o.rad"], "does not exist"),
                          ([work / "scene", tmp_path], "is a directory")):
        r = subprocess.run([*cli, "export-rad", *map(str, args)], capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr
    bad = tmp_path / "bad.rad"
    data = bytearray((work / "scene.rad").read_bytes())
    length = struct.unpack_from("<I", data, 4)[0]
    struct.pack_into("<I", data, 8 + ((length + 7) & ~7), 0)  # the chunk's magic
    bad.write_bytes(bytes(data))
    r = run_cli("convert", bad, tmp_path / "x.ply")
    assert r.returncode == 2 and "chunk 0" in r.stderr and "RADC" in r.stderr, r.stderr


def test_mapping_gives_every_parent_a_child():
    """Root tile of 2 splats over a leaf tile of 3 splats all nearest to the first: the second steals one."""
    tiles = {0: TreeTile(0, 0, (1,), _splats([[0.0, 0, 0], [3.0, 0, 0]])),
             1: TreeTile(1, 1, (), _splats([[0.0, 0, 0], [0.1, 0, 0], [1.2, 0, 0]]))}
    tree = rad_tree(tiles, 0)
    assert tree.child_count.tolist() == [2, 2, 1, 0, 0, 0] and tree.child_start.tolist() == [1, 3, 5, 0, 0, 0]
    assert tree.depth.tolist() == [0, 1, 1, 2, 2, 2]
    assert tree.splats.positions[5, 0] == pytest.approx(1.2)  # the second parent's child: the nearest it could take
    assert tree.splats.positions[0, 0] == pytest.approx(1.5)  # merged root: the mean


def test_a_parent_whose_16_nearest_children_are_only_children_still_gets_one():
    """20 parents on a line, each with one child beside it, a 21st parent past their end and 3 more children far
    on the other side (nearest the first parent): the 21st parent's 16 nearest children are all only children, so
    it stayed childless and Spark drew it at full detail (61 such splats in playbot's kept tree, issue 31)."""
    line = [[float(i), 0, 0] for i in range(20)]
    tiles = {0: TreeTile(0, 0, (1,), _splats(line + [[25.0, 0, 0]])),
             1: TreeTile(1, 1, (), _splats([[i + 0.01, 0, 0] for i in range(20)] + [[-10.0, 0, 0]] * 3))}
    tree = rad_tree(tiles, 0)
    parents = np.flatnonzero(tree.depth == 1)
    assert (tree.child_count[parents] >= 1).all() and tree.child_count[parents].sum() == 23
    assert ((tree.child_count == 0) == (tree.depth == tree.levels() - 1)).all()  # leaves only at full detail
    last = parents[-1]
    taken = tree.splats.positions[tree.child_start[last], 0]
    assert taken == pytest.approx(0.01)  # the nearest child whose parent (the first, with 4) keeps others


def test_several_chunks(tmp_path):
    """70,000 leaves under two parents: two chunks, read back in place."""
    n = 70000
    g = _splats(np.column_stack([np.arange(n + 3, dtype=np.float32), np.zeros(n + 3), np.zeros(n + 3)]))
    count = np.zeros(n + 3, np.uint16)
    start = np.zeros(n + 3, np.uint32)
    count[:3] = [2, 35000, 35000]
    start[:3] = [1, 3, 35003]
    depth = np.concatenate([[0, 1, 1], np.full(n, 2)])
    data = rad_bytes(RadTree(g, count, start, depth), 0)
    (tmp_path / "big.rad").write_bytes(data)
    back = read_rad_tree(tmp_path / "big.rad")
    assert len(back.splats) == n + 3 and (back.depth == depth).all() and (back.child_start == start).all()
    assert np.array_equal(back.splats.positions, g.positions)
    assert len(json.loads(data[8:8 + struct.unpack_from("<I", data, 4)[0]])["chunks"]) == 2


def test_spark_encoding_reads_back_within_its_steps(exported, tmp_path):
    """`--encoding spark` (Spark's 8-bit defaults, drawn by Spark in tests/test_spark_browser.py) read back by our
    decoders of the same encodings: within each encoding's step of the exact file."""
    work, _ = exported
    r = run_cli("export-rad", work / "scene", tmp_path / "s.rad", "--encoding", "spark", "-q")
    assert r.returncode == 0, r.stderr
    exact, spark = read_rad_tree(work / "scene.rad"), read_rad_tree(tmp_path / "s.rad")
    assert (tmp_path / "s.rad").stat().st_size < 0.5 * (work / "scene.rad").stat().st_size
    data = (tmp_path / "s.rad").read_bytes()
    enc = json.loads(data[8:8 + struct.unpack_from("<I", data, 4)[0]])["splatEncoding"]
    a, b = exact.splats, spark.splats
    assert np.array_equal(a.positions, b.positions)  # f32_lebytes: lossless
    assert (exact.child_start == spark.child_start).all() and (exact.child_count == spark.child_count).all()
    assert np.abs(a.opacities - b.opacities).max() <= 1.0 / 255 + 1e-3  # r8 over [0, 2]: half a step
    step = (enc["lnScaleMax"] - enc["lnScaleMin"]) / 254
    assert np.abs(a.log_scales - b.log_scales).max() <= step / 2 + 1e-3
    # oct88r8: an 8-bit axis and angle; every rotation within a few degrees.
    dot = np.abs((a.rotations.astype(np.float64) * b.rotations).sum(axis=1))
    assert np.degrees(2 * np.arccos(np.minimum(dot, 1))).max() < 3.0
    # Colours are clamped to Spark's 1st-99th percentile range (its writer's choice), then r8: inside the range
    # within half a step.
    rgb_a, rgb_b = a.base_colors.astype(np.float64), b.base_colors.astype(np.float64)
    inside = (rgb_a >= enc["rgbMin"]) & (rgb_a <= enc["rgbMax"])
    assert np.abs(rgb_a - rgb_b)[inside].max() <= (enc["rgbMax"] - enc["rgbMin"]) / 255 / 2 + 2e-3
    assert inside.mean() > 0.97
    assert np.abs(a.sh_rest - b.sh_rest).max() <= max(enc["sh1Max"], enc["sh2Max"], enc["sh3Max"]) / 127 / 2 + 2e-3


def _with_header(data: bytes, **changes) -> bytes:
    """`data` (a .rad) with its header JSON changed, the chunks moved to stay 8-aligned after it."""
    length = struct.unpack_from("<I", data, 4)[0]
    meta = json.loads(data[8:8 + length])
    meta.update(changes)
    text = json.dumps(meta).encode()
    return struct.pack("<II", RAD_MAGIC, len(text)) + text + bytes(-len(text) % 8) + data[8 + ((length + 7) & ~7):]


def test_bad_headers_are_one_line_errors(exported, tmp_path, monkeypatch):
    work, _ = exported
    data = (work / "scene.rad").read_bytes()
    for changes, message in (({"count": 10 ** 12}, "memory budget"), ({"count": "many"}, "header count"),
                             ({"version": 2}, "expected version 1"), ({"maxSh": 7}, "expected 0 to 3")):
        (tmp_path / "bad.rad").write_bytes(_with_header(data, **changes))
        with pytest.raises(InputError, match=message):
            read_rad_tree(tmp_path / "bad.rad")
    (tmp_path / "ok.rad").write_bytes(_with_header(data))
    assert len(read_rad_tree(tmp_path / "ok.rad").splats) == 9377
    monkeypatch.setenv("SPLATSTREAM_MEMORY_BUDGET", "1000")
    with pytest.raises(InputError, match="memory budget"):
        read_rad_tree(work / "scene.rad")


def test_view_headless_streams_our_rad_coarse_to_fine(exported, tmp_path, gl_context):
    """`view FILE.rad`: its tree converted into ours streams coarse to fine, ending at the full detail, drawn as
    our render of the original scene draws it."""
    work, _ = exported
    r = run_cli("view", work / "scene.rad", "--headless", "--size", "96x64", "--screenshot", tmp_path / "v.png",
                "--record", tmp_path / "m.json", "--no-cache", "--max-sse", "0", "-q")
    assert r.returncode == 0, r.stderr
    drawn = [f["drawn_splats"] for f in json.loads((tmp_path / "m.json").read_text())["frames"]]
    first = next(d for d in drawn if d > 0)
    assert first < drawn[-1] == 4721 and drawn == sorted(drawn)
    r = run_cli("render", work / "scene", "--size", "96x64", "--out", tmp_path / "r.png", "-q")
    assert r.returncode == 0, r.stderr
    iou, psnr = compare(tmp_path / "r.png", tmp_path / "v.png")
    assert iou > 0.99 and psnr > 40, (iou, psnr)


def test_merged_root_matches_the_moments():
    """merge_splats: one splat's covariance is the opacity-weighted covariance of the parts plus their spread."""
    rng = np.random.default_rng(3)
    n = 50
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = _splats(rng.normal(size=(n, 3)))
    g = type(g)(g.positions, q.astype(np.float32), rng.uniform(-3, -1, (n, 3)).astype(np.float32),
                rng.normal(size=n).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32), g.sh_rest)
    m = merge_splats(g)
    w = g.opacities.astype(np.float64) / g.opacities.sum()
    mean = w @ g.positions
    d = g.positions - mean
    want = np.einsum("n,nij->ij", w, covariances(g) + d[:, :, None] * d[:, None, :])
    assert np.allclose(m.positions[0], mean, atol=1e-5)
    assert np.allclose(covariances(m)[0], want, rtol=1e-4, atol=1e-6)
    assert np.allclose(m.sh_dc[0], w @ g.sh_dc, atol=1e-5) and m.opacities[0] == pytest.approx(g.opacities.max())


def test_open_source_takes_a_rad_as_its_tree(exported):
    """What `view` does with a .rad (GL-free): its tree converted into ours in memory, not its finest level."""
    work, _ = exported
    src = open_source(work / "scene.rad")
    assert isinstance(src, StoreSource)
    manifest = load_manifest(src.store)
    assert manifest.splats == 4721 and max(t.level for t in manifest.tiles) == 6


def test_a_binary_tree_with_shallow_leaves_becomes_ours(tmp_path):
    """A tree shaped like Spark's own (a single root, two children per splat, some leaves high up), not ours:
    our tree's cut at depth j is its cut at depth k + j, k the shallowest depth whose cut holds 16 splats."""
    rng = np.random.default_rng(5)
    count, depth = [], []
    frontier = [0]
    n = 1
    level = 0
    while frontier and level < 9:
        nxt = []
        for _ in frontier:
            leaf = level >= 3 and rng.random() < 0.15
            count.append(0 if leaf else 2)
            depth.append(level)
            if not leaf:
                nxt += [n, n + 1]
                n += 2
        frontier, level = nxt, level + 1
    count += [0] * len(frontier)
    depth += [level] * len(frontier)
    count = np.array(count, np.uint16)
    start = np.where(count > 0, 1 + np.concatenate([[0], np.cumsum(count)[:-1]]), 0).astype(np.uint32)
    total = len(count)
    g = _splats(rng.normal(size=(total, 3)))
    tree = RadTree(g, count, start, np.array(depth))
    (tmp_path / "bin.rad").write_bytes(rad_bytes(tree, 0))
    back = read_rad_tree(tmp_path / "bin.rad")
    assert (back.depth == tree.depth).all()
    store = encode_rad(tmp_path / "bin.rad")
    manifest = load_manifest(store)
    k = next(d for d in range(tree.levels()) if len(tree.cut(d)) >= 16)
    assert 0 < k and max(t.level for t in manifest.tiles) == tree.levels() - 1 - k
    for j in range(tree.levels() - k):
        # Within the encode preset's position quantisation (the scene spans about 6 units).
        assert same_splats(our_cut(store, manifest, j), tree.splats.subset(tree.cut(k + j))) < 5e-3, j


@pytest.mark.parametrize("n, m, k", [(6000, 3000, 1), (2500, 4000, 16), (9000, 800, 1), (4000, 4000, 3)])
def test_nearest_spatial_blocks_equal_every_pair(n, m, k):
    """export-rad's parent search over spatial blocks finds the same nearest centres as the search over every pair,
    on clustered points of three scales with exact coincidences (ties break by index)."""
    rng = np.random.default_rng(n + m + k)
    centres = rng.normal(size=(m, 3)) * rng.choice([0.01, 1.0, 30.0], size=(m, 1)) + rng.normal(size=(m, 1)) * 5
    points = rng.normal(size=(n, 3)) * rng.choice([0.01, 1.0, 30.0], size=(n, 1)) + rng.normal(size=(n, 1)) * 5
    points[:50] = centres[:50]
    centres[60:70] = centres[50:60]  # duplicate centres: the lower index wins
    fast, brute = nearest(points, centres, k), nearest_brute(points, centres, k)
    assert fast.shape == brute.shape == ((n,) if k == 1 else (n, k))
    if k == 1:
        assert np.array_equal(fast, brute)
    else:
        def dist(idx):
            return ((points[:, None, :] - centres[idx]) ** 2).sum(axis=2)
        assert np.allclose(dist(fast), dist(brute), rtol=1e-12, atol=1e-12)
        assert (np.diff(dist(fast), axis=1) >= -1e-12).all()


def test_export_reports_the_tree_and_the_chunks(exported, tmp_path):
    """The nearest-parent searches (most of an export's time: playbot 31 of 34 s of CPU) are heard as stage
    "tree", by the share of the splats below the root placed, then the chunks as "encode": each from 0 to exactly
    1, never backwards."""
    work, _ = exported
    heard: list[tuple[str, float]] = []
    export_rad(work / "scene", tmp_path / "p.rad", progress=lambda stage, fraction: heard.append((stage, fraction)))
    stages = [stage for stage, _ in heard if stage != "decode"]
    assert stages == sorted(stages, key=["tree", "encode"].index)
    for name in ("tree", "encode"):
        fractions = [f for stage, f in heard if stage == name]
        assert fractions[0] == 0.0 and fractions[-1] == 1.0 and fractions == sorted(fractions), name
    assert len([f for stage, f in heard if stage == "tree"]) > 3  # more than the start and the end
    assert (tmp_path / "p.rad").read_bytes() == (work / "scene.rad").read_bytes()


def test_a_truncated_file_says_so(exported, tmp_path):
    """A .rad cut short inside a chunk's property: the property, the bytes it needs and the file's end (it said
    'expected raw DEFLATE data (Error -5 ...: incomplete or truncated stream)')."""
    work, _ = exported
    data = (work / "scene.rad").read_bytes()
    (tmp_path / "cut.rad").write_bytes(data[:len(data) - 1000])
    with pytest.raises(InputError, match=r"chunk \d+ \w+: needs bytes [\d,]+\.\.[\d,]+, past the end of its file "
                                         rf"\({len(data) - 1000:,} bytes\): truncated\?"):
        read_rad_tree(tmp_path / "cut.rad")


@pytest.mark.parametrize("keep", [6, 100])
def test_a_file_cut_in_its_header_says_so(exported, tmp_path, keep):
    """A .rad cut inside its JSON header (a download stopped early): the bytes the header needs and the file's end
    (it said 'header: expected JSON (Expecting property name enclosed in double quotes: line 7 column 3 ...)')."""
    work, _ = exported
    (tmp_path / "cut.rad").write_bytes((work / "scene.rad").read_bytes()[:keep])
    with pytest.raises(InputError, match=r"header: needs .*the file has 6: truncated\?" if keep == 6 else
                       r"header: needs bytes 8\.\.[\d,]+, past the end of its file \(100 bytes\): truncated\?"):
        read_rad_tree(tmp_path / "cut.rad")
