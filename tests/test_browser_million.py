"""A million-splat scene, exported to streamed SOG (`export-sog-lod`) and to RAD (`export-rad`), drawn by PlayCanvas's
engine and by Spark in headless Chromium (software WebGL) with their own LOD and budgets: from the scene's camera
and from 40x as far, where each must draw fewer splats (PlayCanvas: no level-0 unit fetched; Spark: fewer chunks
fetched). The donut's tests (test_playcanvas_browser.py, test_spark_browser.py) check the same at full detail.

The scene is made at test time, deterministically: tests/tools/make_scene.py (the shared data's generator, run over
the bundled scenes) with `--splats 1000000 --seed 0 --sh-degree 0` (copies of the four real scenes over a ground,
z up; SH degree 0 keeps the browsers' software WebGL and our llvmpipe render quick), encoded once per session
(module fixture, in pytest's tmp) with 2,000-splat leaves, then exported once each (RAD with `--encoding spark`,
Spark's own 8-bit encodings). Pages, server and comparison: tests/browser.py, at a 160x120 canvas.

Not met yet (issue 35's "matching our render"): each engine's picture of this scene against our render of the
same camera (drawn-pixel IoU >= 0.95, PSNR >= 25 dB, as the donut meets) is reported as an expected failure with
its numbers. At this canvas most splats are sub-pixel, where the engines draw unlike 3DGS by default: PlayCanvas
culls splats under 2 px across (minPixelSize) and Spark compensates opacity for its low-pass (for antialiased
training); the pages set both to 3DGS's way here (PLAYCANVAS_QUERY, SPARK_QUERY), which lifts PlayCanvas from IoU
0.65 / 18.7 dB to 0.71 / 20.2 dB and Spark from 0.74 / 19.2 dB to 0.85 / 21.7 dB. The rest is not the LOD
(PlayCanvas at full detail, all 1M splats, matches no better: 0.72 / 20.4 dB) and not our render (it equals our
numpy reference rasteriser on the same splats, 72.6 dB); a single copy of the donut as make_scene places it
(45,624 splats) matches at IoU 0.95, 23.8 dB in PlayCanvas, its thin sprinkles drawn thinner. BENCHMARKS.md, "1M
scene in PlayCanvas and Spark".
"""
from __future__ import annotations

import json
import time
import urllib.parse

import pytest
from browser import NODE_MODULES, compare, keep, render_ours, requirements, scene_camera, serve, shoot
from conftest import ROOT, run_cli
from test_spark_browser import chunks_fetched
from test_upright import make_scene

from splatstream.readers.rad import read_rad_tree

PLAYCANVAS = NODE_MODULES / "playcanvas" / "build"
SPARK = NODE_MODULES / "@sparkjsdev" / "spark"
THREE = NODE_MODULES / "three"
SPLATS = 1_000_000
SIZE = (160, 120)
MIN_IOU = 0.95
MIN_PSNR_DB = 25.0
FAR = 40.0  # times the suggested camera's distance
# Standard 3DGS drawing in each engine (see the pages): PlayCanvas culls splats under 2 px across by default, and
# Spark's default low-pass compensates opacity (for antialiased training); at this canvas most splats are sub-pixel.
PLAYCANVAS_QUERY = {"minpx": 0}
SPARK_QUERY = {"preblur": 0.3, "blur": 0}
# Leaves of 2,000 splats, as the donut's tests: export-rad's nearest-parent search costs a tile's splats times its
# parent's, which with the default 16,384-splat leaves took 320 s here for this scene (BENCHMARKS.md).
LEAF_SPLATS = 2000


@pytest.fixture(scope="module")
def million(tmp_path_factory):
    requirements(PLAYCANVAS / "playcanvas.mjs", SPARK / "dist" / "spark.module.js", THREE / "build" / "three.module.js",
                 what="playcanvas / @sparkjsdev/spark / three")
    work = tmp_path_factory.mktemp("million")
    steps = {}
    t = time.perf_counter()
    ply = make_scene(work, SPLATS, "--seed", "0", "--sh-degree", "0")
    steps["make_scene"] = time.perf_counter() - t
    for name, args in (("encode", ["encode", ply, work / "scene", "--max-leaf-splats", str(LEAF_SPLATS)]),
                       ("export-sog-lod", ["export-sog-lod", work / "scene", work / "sog"]),
                       ("export-rad", ["export-rad", work / "scene", work / "rad" / "million.rad", "--encoding",
                                       "spark"])):
        if name == "export-rad":
            (work / "rad").mkdir()
        t = time.perf_counter()
        r = run_cli(*args, "--quiet")
        assert r.returncode == 0, r.stderr
        steps[name] = time.perf_counter() - t
    ply.unlink()
    t = time.perf_counter()
    query, ours = scene_camera(work / "scene")
    render_ours(work / "scene", work / "ours.png", SIZE, ours)
    steps["render (ours)"] = time.perf_counter() - t
    print("million: " + ", ".join(f"{k} {v:.1f} s" for k, v in steps.items()))
    return work, query


def matches_or_known_gap(engine: str, iou: float, psnr: float) -> None:
    """The donut's thresholds; below them, an expected failure with the numbers (see the module's docstring)."""
    if iou < MIN_IOU or psnr < MIN_PSNR_DB:
        pytest.xfail(f"{engine} draws the 1M scene unlike our render: IoU {iou:.3f}, PSNR {psnr:.1f} dB "
                     f"(need {MIN_IOU}, {MIN_PSNR_DB} dB; BENCHMARKS.md, '1M scene in PlayCanvas and Spark')")


def test_playcanvas_streams_the_million_with_its_lod(million, tmp_path):
    work, query = million
    query = {**query, **PLAYCANVAS_QUERY}
    meta = json.loads((work / "sog" / "lod-meta.json").read_text())
    assert meta["counts"][0] == SPLATS
    with serve(ROOT / "tests" / "playcanvas_page", {"/playcanvas/": PLAYCANVAS, "/scene/": work / "sog"}) as (url, _):
        t = time.perf_counter()
        near = tmp_path / "playcanvas-million.png"
        report = shoot(f"{url}/index.html?{urllib.parse.urlencode({'scene': '/scene/lod-meta.json', **query})}",
                       near, SIZE)
        near_s = time.perf_counter() - t
        far_query = {**scene_camera(work / "scene", FAR)[0], **PLAYCANVAS_QUERY}
        t = time.perf_counter()
        far = shoot(f"{url}/index.html?{urllib.parse.urlencode({'scene': '/scene/lod-meta.json', **far_query})}",
                    tmp_path / "far.png", SIZE)
        far_s = time.perf_counter() - t
    keep(near, work / "ours.png")
    iou, psnr = compare(work / "ours.png", near)
    result, far_result = report["result"], far["result"]
    print(f"million in PlayCanvas: near IoU {iou:.3f}, PSNR {psnr:.1f} dB, {result['splats']} splats drawn of "
          f"{meta['counts']}, units {result['units']}, {near_s:.1f} s; far {far_result['splats']} splats, units "
          f"{far_result['units']}, {far_s:.1f} s; {report['gl']}")
    assert 0 < result["splats"] <= SPLATS and iou > 0.5  # the scene is drawn where ours is
    assert 0 < far_result["splats"] < result["splats"]
    assert not any(u.startswith("0_") for u in far_result["units"])  # no level-0 unit was even fetched
    matches_or_known_gap("PlayCanvas", iou, psnr)


def test_spark_streams_the_million_with_its_lod(million, tmp_path):
    work, query = million
    query = {**query, **SPARK_QUERY}
    rad = work / "rad" / "million.rad"
    tree = read_rad_tree(rad)
    leaves = int((tree.child_count == 0).sum())
    assert leaves == SPLATS
    routes = {"/three/": THREE, "/spark/": SPARK, "/scene/": work / "rad"}
    with serve(ROOT / "tests" / "spark_page", routes, ranges=True) as (url, ranges):
        t = time.perf_counter()
        near = tmp_path / "spark-million.png"
        report = shoot(f"{url}/index.html?{urllib.parse.urlencode({'scene': '/scene/million.rad', **query})}",
                       near, SIZE)
        near_s = time.perf_counter() - t
        near_chunks = chunks_fetched(rad, ranges)
        ranges.clear()
        far_query = {**scene_camera(work / "scene", FAR)[0], **SPARK_QUERY}
        t = time.perf_counter()
        far = shoot(f"{url}/index.html?{urllib.parse.urlencode({'scene': '/scene/million.rad', **far_query})}",
                    tmp_path / "far.png", SIZE)
        far_s = time.perf_counter() - t
        far_chunks = chunks_fetched(rad, ranges)
    keep(near, work / "ours.png")
    iou, psnr = compare(work / "ours.png", near)
    result, far_result = report["result"], far["result"]
    data = rad.read_bytes()
    chunks = len(json.loads(data[8:8 + int.from_bytes(data[4:8], "little")])["chunks"])
    print(f"million in Spark: near IoU {iou:.3f}, PSNR {psnr:.1f} dB, {result['splats']} splats drawn of {leaves} "
          f"leaves ({len(tree.splats)} in the tree), chunks {near_chunks} of {chunks}, {near_s:.1f} s; far "
          f"{far_result['splats']} splats, chunks {far_chunks}, {far_s:.1f} s")
    assert 0 < result["splats"] < leaves and iou > 0.5  # the scene is drawn where ours is, by Spark's LoD cut
    assert 0 < far_result["splats"] < result["splats"]
    assert 0 in far_chunks and len(far_chunks) < len(near_chunks) <= chunks
    matches_or_known_gap("Spark", iou, psnr)
