"""A streamed SOG's whole LOD tree as ours (splatstream/sog_import.py): ours -> streamed SOG -> ours keeps the
splats of every level, and `view --headless` streams a streamed SOG (splat-transform's, from ../shared, and our
own export) coarse to fine."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import ROOT, real, run_cli, with_shared
from PIL import Image
from test_sog_lod import same_splats

from splatstream.encode import EncodeOptions, encode_file
from splatstream.gaussians import Gaussians
from splatstream.readers.sog import read_streamed_sog
from splatstream.scene_decode import decode_scene
from splatstream.sog_export import export_streamed_sog
from splatstream.sog_import import encode_streamed_sog, tree_tiles
from splatstream.store import load_manifest, read_manifest

SOURCE = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"
FLOWERS_CASES = with_shared(["flowers_lod/lod-meta.json"])  # not bundled (22 MB): shared-only cases


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    work = tmp_path_factory.mktemp("sog_import")
    encode_file(SOURCE, work / "scene", max_leaf_splats=1024)
    export_streamed_sog(work / "scene", work / "sog", unit_splats=2000)
    return work


def test_round_trip_keeps_every_level(exported):
    """ours -> streamed SOG -> ours: at every depth the same splats (within SOG's quantisation: float32 formats
    on the way back, so only SOG's rounding shows), the same depth, errors non-increasing, leaves exact."""
    ours = load_manifest(exported / "scene")
    store = encode_streamed_sog(exported / "sog", EncodeOptions(preset="very-high"))
    back = read_manifest(store)
    depth = max(t.level for t in ours.tiles)
    assert max(t.level for t in back.tiles) == depth and back.splats == ours.splats == 4721
    for d in range(depth + 1):
        a = decode_scene(exported / "scene", tiles=[t.id for t in ours.tiles if t.level == d])
        b = decode_scene(store, tiles=[t.id for t in back.tiles if t.level == d], manifest=back)
        assert same_splats(a, b) < 1e-3, d
    for t in back.tiles:
        assert all(back.tile(c).geometric_error <= t.geometric_error for c in t.children)
        assert (t.geometric_error == 0) == (not t.children)
    assert back.lod.enabled and back.tile(back.root).geometric_error > 0


def test_view_headless_streams_our_export_coarse_to_fine(exported, tmp_path, gl_context):
    r = run_cli("view", exported / "sog", "--headless", "--size", "96x64", "--screenshot", tmp_path / "v.png",
                "--record", tmp_path / "m.json", "--no-cache", "-q")
    assert r.returncode == 0, r.stderr
    drawn = [f["drawn_splats"] for f in json.loads((tmp_path / "m.json").read_text())["frames"]]
    first = next(d for d in drawn if d > 0)
    assert first < drawn[-1] and drawn == sorted(drawn)  # coarse first, then finer, never back


@pytest.mark.parametrize("name", FLOWERS_CASES or ["flowers_lod/lod-meta.json"])
def test_splat_transform_streamed_sog_becomes_our_tree(name):
    """flowers_lod (written by splat-transform: 4 levels, 16 leaves): our depth d holds their level 3 - d."""
    FLOWERS_LOD = real(name).parent
    sog = read_streamed_sog(FLOWERS_LOD)
    meta = json.loads((FLOWERS_LOD / "lod-meta.json").read_text())
    tiles = tree_tiles(sog)
    per_depth = [sum(len(t.gaussians) for t in tiles if t.level == d) for d in range(sog.levels)]
    counts = [sum(ref["count"] for leaf in _leaves(meta["tree"]) for k, ref in leaf["lods"].items() if int(k) == lv)
              for lv in range(meta["lodLevels"])]
    assert sog.levels == 4 and per_depth == counts[::-1] and per_depth[-1] == len(sog.level(0))
    for d in range(sog.levels):  # their splats, level for level (not only as many): the same rows in any order
        ours = Gaussians.concatenate([t.gaussians for t in tiles if t.level == d])
        assert np.array_equal(_rows(ours), _rows(sog.level(sog.levels - 1 - d))), d
    assert tiles[0].id == 0 and all(c > t.id for t in tiles for c in t.children)
    for t in tiles:  # bounds hold the splats and the children's bounds
        assert (t.gaussians.positions >= t.box_min - 1e-6).all() and (t.gaussians.positions <= t.box_max + 1e-6).all()
        for c in t.children:
            assert (tiles[c].box_min >= t.box_min - 1e-9).all() and (tiles[c].box_max <= t.box_max + 1e-9).all()
            assert tiles[c].geometric_error <= t.geometric_error


def _rows(g: Gaussians) -> np.ndarray:
    """Every splat's attributes as one row, rows sorted: equal for the same splats in any order."""
    rows = np.column_stack([g.positions, g.rotations, g.log_scales, g.opacity_logits, g.sh_dc,
                            g.sh_rest.reshape(len(g), -1)])
    return rows[np.lexsort(rows.T[::-1])]


def _leaves(node: dict) -> list[dict]:
    return [node] if "lods" in node else [leaf for c in node.get("children", []) for leaf in _leaves(c)]


@pytest.mark.parametrize("name", FLOWERS_CASES or ["flowers_lod/lod-meta.json"])
def test_view_headless_streams_flowers_lod(name, tmp_path, gl_context):
    FLOWERS_LOD = real(name).parent
    r = run_cli("view", FLOWERS_LOD, "--headless", "--size", "96x64", "--screenshot", tmp_path / "v.png",
                "--record", tmp_path / "m.json", "--no-cache", "-q")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "m.json").read_text())
    drawn = [f["drawn_splats"] for f in report["frames"]]
    first = next(d for d in drawn if d > 0)
    assert report["converged_s"] is not None
    assert first < drawn[-1] and drawn == sorted(drawn)
    assert np.asarray(Image.open(tmp_path / "v.png")).std() > 1  # the scene is in the picture


def test_encode_keeps_their_tree(exported, tmp_path):
    """`encode lod-meta.json OUT` writes their tree level for level (what `view` streams, now on disk); with
    --rebuild-lod, our own tree from their finest level."""
    ours = load_manifest(exported / "scene")
    r = run_cli("encode", exported / "sog" / "lod-meta.json", tmp_path / "kept", "--preset", "very-high", "-q")
    assert r.returncode == 0, r.stderr
    kept = load_manifest(tmp_path / "kept")
    depth = max(t.level for t in ours.tiles)
    assert max(t.level for t in kept.tiles) == depth and kept.splats == ours.splats
    for d in range(depth + 1):
        a = decode_scene(exported / "scene", tiles=[t.id for t in ours.tiles if t.level == d])
        b = decode_scene(tmp_path / "kept", tiles=[t.id for t in kept.tiles if t.level == d])
        assert same_splats(a, b) < 1e-3, d
    r = run_cli("encode", exported / "sog", tmp_path / "rebuilt", "--rebuild-lod", "--max-leaf-splats", "4096",
                "-q")
    assert r.returncode == 0, r.stderr
    rebuilt = load_manifest(tmp_path / "rebuilt")
    assert rebuilt.splats == 4721 and rebuilt.lod.max_leaf_splats == 4096 != kept.lod.max_leaf_splats
    assert sum(not t.children for t in rebuilt.tiles) < sum(not t.children for t in kept.tiles)
    # Their kept tree says nothing of how it was built; ours, rebuilt, records its merge and viewing scales (1.9).
    # Both are written with the compact tile table (1.16, format.md 6.2), which says nothing of how a tree was built.
    assert not kept.lod.build_recorded and kept.version == (1, 16)
    assert rebuilt.lod.merge == "auto" and rebuilt.lod.viewing_scale_px == (2.0, 8.0, 12.0, 16.0)
    assert rebuilt.version == (1, 16)
    r = run_cli("encode", exported / "sog", tmp_path / "x", "--workers", "2", "-q")
    assert r.returncode == 2 and "--rebuild-lod" in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("name", FLOWERS_CASES or ["flowers_lod/lod-meta.json"])
def test_encode_keeps_splat_transforms_tree_and_view_streams_it(name, tmp_path, gl_context):
    """flowers_lod encoded: our depth d on disk holds their level 3 - d, and `view` of the scene directory
    streams it coarse to fine."""
    sog = read_streamed_sog(real(name).parent)
    r = run_cli("encode", real(name), tmp_path / "scene", "-q")
    assert r.returncode == 0, r.stderr
    m = load_manifest(tmp_path / "scene")
    assert max(t.level for t in m.tiles) == sog.levels - 1
    for d in range(sog.levels):
        tiles = [t.id for t in m.tiles if t.level == d]
        assert sum(m.tile(t).splats for t in tiles) == len(sog.level(sog.levels - 1 - d)), d
    top = decode_scene(tmp_path / "scene", tiles=[m.root])
    assert same_splats(top, sog.level(sog.levels - 1)) < 0.05  # their coarsest level, at the preset's quantisation
    r = run_cli("view", tmp_path / "scene", "--headless", "--size", "96x64", "--screenshot", tmp_path / "v.png",
                "--record", tmp_path / "m.json", "--no-cache", "-q")
    assert r.returncode == 0, r.stderr
    drawn = [f["drawn_splats"] for f in json.loads((tmp_path / "m.json").read_text())["frames"]]
    first = next(d for d in drawn if d > 0)
    assert first < drawn[-1] and drawn == sorted(drawn)
    # `render --max-sse K` draws the kept tree's cut: every leaf while K is below its finest interior tiles' errors
    # on screen (1.5-11 px at 64 rows from the suggested camera: 17-128 px at 720), coarser above, the root alone
    # past the root's 75 px; its last line names the cut's tiles and levels (newuser62 read the same count at
    # every small K as the option ignored).
    counts, lines = [], []
    for k in (1, 4, 16, 100):
        r = run_cli("render", tmp_path / "scene", "--max-sse", str(k), "--size", "96x64", "--out", tmp_path / "r.png")
        assert r.returncode == 0, r.stderr
        last = r.stderr.splitlines()[-1]
        lines.append(last)
        counts.append(int(last.split(" splats")[0].rsplit(" ", 1)[1].replace(",", "")))
        assert f"(--max-sse {k}: " in last and f"of {len(m.tiles)} tiles" in last, last
    assert counts[0] == m.splats and "level 3 of 0-3; every tile drawn is a leaf: full detail" in lines[0], lines[0]
    assert counts == sorted(counts, reverse=True) and counts[1] < counts[0] and counts[2] < counts[1], counts
    assert counts[-1] == m.tile(m.root).splats and f"1 of {len(m.tiles)} tiles, level 0 of 0-3)" in last, last


if not FLOWERS_CASES:  # without the shared data these cases are not collected (conftest.NOT_BUNDLED), not skipped
    del test_splat_transform_streamed_sog_becomes_our_tree, test_view_headless_streams_flowers_lod
    del test_encode_keeps_splat_transforms_tree_and_view_streams_it


def test_tree_progress_is_heard_tile_by_tile(exported, tmp_path, gl_context):
    """Measuring a kept tree's errors is the slow part before the first tile (playbot: about 10 s): tree_tiles
    reports stage "tree" by tile, 0 to exactly 1, and `view --headless` shows it as `encode` shows its stages."""
    sog = read_streamed_sog(exported / "sog")
    heard: list[tuple[str, float]] = []
    tiles = tree_tiles(sog, lambda stage, fraction: heard.append((stage, fraction)))
    fractions = [f for stage, f in heard if stage == "tree"]
    assert len(heard) == len(fractions) == len(tiles) + 1
    assert fractions[0] == 0.0 and fractions[-1] == 1.0 and fractions == sorted(fractions)
    r = run_cli("view", exported / "sog", "--headless", "--size", "96x64", "--no-cache")
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    for stage in ("read", "tree", "tiles", "encode"):
        assert any(line.startswith(f"view: {stage} 100% (") for line in lines), (stage, r.stderr)


def test_a_missing_unit_is_named_as_lod_meta_json_names_it(exported, tmp_path):
    """A unit directory gone from a streamed SOG: the error is lod-meta.json's entry that names it (it said 'SOG
    meta.json: names ...', which read as the unit's own meta.json naming something), exit 2, no output."""
    damaged = tmp_path / "sog"
    shutil.copytree(exported / "sog", damaged)
    meta = json.loads((damaged / "lod-meta.json").read_text())
    gone = meta["filenames"][1]
    shutil.rmtree(damaged / gone.split("/")[0])
    r = run_cli("encode", damaged, tmp_path / "out", "-q")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip() == (f"splatstream encode: error: {damaged}: lod-meta.json filenames[1]: names '{gone}', "
                                f"which does not exist in {damaged}"), r.stderr
    assert not (tmp_path / "out").exists()
