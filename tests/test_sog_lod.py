"""`splatstream export-sog-lod` (splatstream/writers/sog_lod.py, sog_export.py): our LOD tree as a PlayCanvas
streamed SOG, read back whole by our reader (readers/sog.read_streamed_sog) and by splat-transform."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, run_cli
from test_tool_roundtrip import run_tool, tool_gaussians

from splatstream.encode import encode_file
from splatstream.encode.local import encode_gaussians
from splatstream.format.layout import morton_order
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.readers.sog import read_streamed_sog
from splatstream.scene_decode import decode_scene
from splatstream.sog_export import export_streamed_sog
from splatstream.store import load_manifest
from splatstream.writers.sog_lod import TreeTile, streamed_sog

SOURCE = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """fruit_drops (4721 splats) encoded with 1024-splat leaves (7 levels), exported with small units."""
    work = tmp_path_factory.mktemp("sog_lod")
    encode_file(SOURCE, work / "scene", max_leaf_splats=1024)
    report = export_streamed_sog(work / "scene", work / "sog", unit_splats=2000)
    return work, report


def same_splats(a: Gaussians, b: Gaussians) -> float:
    """Largest position difference between two sets of the same size holding the same splats in any order: the
    Hausdorff distance of their centres (scenes hold coincident splats, so no one-to-one matching by position);
    the mean colour and opacity agree too."""
    assert len(a) == len(b)
    if not len(a):
        return 0.0
    pa, pb = a.positions.astype(np.float64), b.positions.astype(np.float64)
    assert np.allclose(a.sh_dc.mean(axis=0), b.sh_dc.mean(axis=0), atol=2e-3)
    assert abs(float(a.opacities.mean() - b.opacities.mean())) < 2e-3
    return max(_farthest_nearest(pa, pb), _farthest_nearest(pb, pa))


def _farthest_nearest(pa: np.ndarray, pb: np.ndarray, rows: int = 512) -> float:
    """max over pa of the distance to the nearest point of pb (numpy, in blocks of rows: scipy is not a test need)."""
    worst = 0.0
    for i in range(0, len(pa), rows):
        d2 = ((pa[i:i + rows, None, :] - pb[None, :, :]) ** 2).sum(axis=2)
        worst = max(worst, float(np.sqrt(d2.min(axis=1)).max()))
    return worst


def test_levels_are_our_depths(exported):
    work, report = exported
    manifest = load_manifest(work / "scene")
    depth = max(t.level for t in manifest.tiles)
    meta = json.loads((work / "sog" / "lod-meta.json").read_text())
    assert meta["version"] == 1 and meta["lodLevels"] == depth + 1 == report.levels == 7
    by_depth = [sum(t.splats for t in manifest.tiles if t.level == d) for d in range(depth + 1)]
    assert meta["counts"] == by_depth[::-1] and meta["counts"][0] == 4721 and meta["count"] == sum(by_depth)
    # Each unit serves one level, and the references of a unit tile it exactly, in order.
    sog = read_streamed_sog(work / "sog")
    leaves = sog.tree.leaves()
    assert len(leaves) == sum(1 for t in manifest.tiles if not t.children)
    ranges: dict[int, list[tuple[int, int, int]]] = {}
    for leaf in leaves:
        for level, (file, offset, count) in leaf.lods.items():
            ranges.setdefault(file, []).append((offset, count, level))
    for file, refs in ranges.items():
        assert len({level for _, _, level in refs}) == 1
        assert meta["filenames"][file].startswith(f"{refs[0][2]}_")
        ends = np.cumsum([0] + [c for _, c, _ in sorted(refs)])
        assert [o for o, _, _ in sorted(refs)] == ends[:-1].tolist()
        unit = json.loads((work / "sog" / meta["filenames"][file]).read_text())
        assert unit["count"] == ends[-1]
    # Every level holds exactly the splats of our tiles at that depth (within SOG's quantisation).
    for level in range(meta["lodLevels"]):
        ours = decode_scene(work / "scene", tiles=[t.id for t in manifest.tiles if t.level == depth - level])
        assert same_splats(sog.level(level), ours) < 1e-3, level


def test_bounds_hold_the_splats(exported):
    work, _ = exported
    sog = read_streamed_sog(work / "sog")
    for leaf in sog.tree.leaves():
        for g in sog.splats[id(leaf)].values():
            assert (g.positions >= leaf.bound_min - 1e-4).all() and (g.positions <= leaf.bound_max + 1e-4).all()
    assert (sog.tree.bound_min <= np.min([leaf.bound_min for leaf in sog.tree.leaves()], axis=0)).all()


def test_plain_read_is_the_finest_level(exported):
    work, _ = exported
    g = read_gaussians(work / "sog")
    ours = decode_scene(work / "scene")
    assert len(g) == 4721 and same_splats(g, ours) < 1e-3


def test_splat_transform_reads_every_level(exported):
    """The peer tool decodes each level of our streamed SOG (--select-lod) to the splats our reader gives."""
    work, _ = exported
    sog = read_streamed_sog(work / "sog")
    for level in range(sog.levels):
        out = work / f"tool_{level}.ply"
        run_tool(work / "sog" / "lod-meta.json", "-L", level, out)
        assert same_splats(tool_gaussians(out), sog.level(level)) < 1e-5, level


def test_cli_export_and_errors(exported, tmp_path):
    work, _ = exported
    cli = [sys.executable, "-m", "cli"]
    r = subprocess.run([*cli, "export-sog-lod", str(work / "scene"), str(tmp_path / "out"), "--sh-degree", "0"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "7 LOD levels" in r.stderr and "4,721 splats at level 0" in r.stderr
    units = [json.loads(p.read_text()) for p in (tmp_path / "out").glob("*/meta.json")]
    assert units and all("shN" not in u for u in units)
    for args, message in (([tmp_path / "missing", tmp_path / "o"], "missing"),
                          ([work / "scene", work / "scene"], "the output directory is the scene itself"),
                          # the option named (it said 'unit size 0', newuser61)
                          ([work / "scene", tmp_path / "o", "--unit-splats", "0"], "--unit-splats 0: expected")):
        r = subprocess.run([*cli, "export-sog-lod", *map(str, args)], capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_single_tile_scene(tmp_path):
    g = read_gaussians(SOURCE).subset(np.arange(300))
    encode_gaussians(g, tmp_path / "scene")
    export_streamed_sog(tmp_path / "scene", tmp_path / "sog")
    sog = read_streamed_sog(tmp_path / "sog")
    assert sog.levels == 1 and len(sog.tree.leaves()) == 1
    assert same_splats(sog.level(0), g.subset(morton_order(g.positions))) < 1e-3


def test_convert_reads_any_level(exported, tmp_path):
    work, _ = exported
    sog = read_streamed_sog(work / "sog")
    r = run_cli("convert", work / "sog", tmp_path / "l2.ply", "--lod-level", "2", "-q")
    assert r.returncode == 0, r.stderr
    assert same_splats(read_gaussians(tmp_path / "l2.ply"), sog.level(2)) < 1e-6
    for args, message in (([work / "sog", tmp_path / "x.ply", "--lod-level", "7"], "level 7 asked for"),
                          ([SOURCE, tmp_path / "y.ply", "--lod-level", "1"], "not a streamed SOG")):
        r = run_cli("convert", *args)
        assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr


def _splats(positions) -> Gaussians:
    p = np.asarray(positions, np.float32)
    n = len(p)
    return Gaussians(p, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), -4.0), np.zeros(n), np.zeros((n, 3)),
                     np.zeros((n, 0, 3)))


def test_mapping_routes_interior_splats_and_repeats_shallow_leaves():
    """Root (depth 0) over a leaf A at depth 1 (x < 0) and a chain B (depth 1) -> C (depth 2 leaf, x > 0)."""
    tiles = {
        0: TreeTile(0, 0, (1, 2), _splats([[-1.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])),
        1: TreeTile(1, 1, (), _splats([[-1.0, 0, 0], [-1.5, 0, 0]])),
        2: TreeTile(2, 1, (3,), _splats([[1.0, 0, 0], [1.5, 0, 0]])),
        3: TreeTile(3, 2, (), _splats([[1.0, 0, 0], [1.2, 0, 0], [1.4, 0, 0], [1.6, 0, 0]])),
    }
    out = streamed_sog(tiles, 0, unit_splats=100)
    meta = out.meta
    assert meta["lodLevels"] == 3 and meta["counts"] == [2 + 4, 2 + 2, 3]  # A repeated at level 0
    a, c = meta["tree"]["children"]  # B adds no node (one child)
    assert {k: v["count"] for k, v in a["lods"].items()} == {"0": 2, "1": 2, "2": 1}  # the root splat at x = -1
    assert {k: v["count"] for k, v in c["lods"].items()} == {"0": 4, "1": 2, "2": 2}
    assert meta["filenames"] == ["0_0/meta.json", "1_0/meta.json", "2_0/meta.json"]
    assert c["lods"]["0"]["offset"] == 2 and a["lods"]["0"]["offset"] == 0
    assert a["bound"]["max"][0] < 0 < c["bound"]["min"][0]
    assert meta["tree"]["bound"]["min"] == a["bound"]["min"] and meta["tree"]["bound"]["max"] == c["bound"]["max"]


def test_export_reports_progress_as_it_packs_units(exported, tmp_path):
    """The units' SOG encode is the slow part of an export (playbot: about 28 s): it is heard unit by unit, by
    the share of the splats packed, from 0 to exactly 1, never backwards, and inside each unit (its planes, then its
    SH palette: a 524,288-splat unit of a 2M-splat scene was 30-35 s of a bar standing still); the CLI shows it."""
    work, report = exported
    heard: list[tuple[str, float]] = []
    export_streamed_sog(work / "scene", tmp_path / "sog", unit_splats=2000,
                        progress=lambda stage, fraction: heard.append((stage, fraction)))
    encode = [f for stage, f in heard if stage == "encode"]
    assert encode[0] == 0.0 and encode[-1] == 1.0 and encode == sorted(encode)
    assert len(set(encode)) - 1 >= 2 * report.units  # the planes inside each unit, then the unit
    r = run_cli("export-sog-lod", work / "scene", tmp_path / "cli", "--unit-splats", "2000")
    assert r.returncode == 0, r.stderr
    steps = [line for line in r.stderr.splitlines() if line.startswith("export-sog-lod: encode ")]
    assert len(steps) >= 3 and steps[-1].startswith("export-sog-lod: encode 100% ("), r.stderr
