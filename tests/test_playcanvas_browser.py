"""Our streamed-SOG export (`export-sog-lod`) in PlayCanvas's engine (npm `playcanvas`, .ci/node) in headless
Chromium (Debian's `chromium`, software WebGL through SwiftShader), driven by playwright-core like the CesiumJS test
(tests/test_cesium_browser.py; what the three share: tests/browser.py).

The page (tests/playcanvas_page/) and the exported scene are served by one loopback server here; every other
request is refused by the driver. The camera is the scene's suggested camera in the scene's own coordinates (a
streamed SOG keeps the PLY's axes, and the page puts the splats at the engine's origin untransformed), at which the
engine draws level 0 (the camera is nearer than its lodBaseDistance); the screenshot is compared with our
`render` of the same camera: the masks of drawn pixels (any channel above 16/255 on black) by intersection over
union, and the PSNR. From far away (the same view direction, 40x the distance) the engine must draw fewer splats
than level 0 holds: its LOD is in use.

Scene: the bundled donut (samples/donut.ply, so a fresh clone has it), 2,000-splat leaves.
"""
from __future__ import annotations

import json
import urllib.parse

import pytest
from browser import NODE_MODULES, compare, keep, render_ours, requirements, scene_camera, serve, shoot
from conftest import ROOT, run_cli

ENGINE = NODE_MODULES / "playcanvas" / "build"
PAGE_DIR = ROOT / "tests" / "playcanvas_page"
SCENE = ROOT / "samples" / "donut.ply"
SIZE = (320, 240)
MIN_IOU = 0.95
MIN_PSNR_DB = 25.0


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """The page's files, the engine's build under /playcanvas/ and the exported scene under /scene/."""
    requirements(ENGINE / "playcanvas.mjs", what="playcanvas")
    work = tmp_path_factory.mktemp("playcanvas")
    r = run_cli("encode", SCENE, work / "scene", "--max-leaf-splats", "2000", "--quiet")
    assert r.returncode == 0, r.stderr
    r = run_cli("export-sog-lod", work / "scene", work / "sog", "--quiet")
    assert r.returncode == 0, r.stderr
    with serve(PAGE_DIR, {"/playcanvas/": ENGINE, "/scene/": work / "sog"}) as (url, _):
        yield work, url


def test_playcanvas_draws_our_streamed_sog_where_we_do(served, tmp_path):
    work, base = served
    meta = json.loads((work / "sog" / "lod-meta.json").read_text())
    query, ours = scene_camera(work / "scene")
    theirs_png, ours_png = tmp_path / "playcanvas-donut.png", tmp_path / "ours-donut.png"
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': '/scene/lod-meta.json', **query})}",
                   theirs_png, SIZE)
    render_ours(work / "scene", ours_png, SIZE, ours)
    keep(theirs_png, ours_png)
    iou, psnr = compare(ours_png, theirs_png)
    result = report["result"]
    print(f"donut near: IoU {iou:.3f}, PSNR {psnr:.1f} dB, {result['splats']} splats drawn of {meta['counts']}, "
          f"units {result['units']}, {result['waitedMs']} ms, {report['gl']}")
    assert result["splats"] == meta["counts"][0]  # level 0: the scene's full detail, what we render
    assert iou >= MIN_IOU and psnr >= MIN_PSNR_DB, (iou, psnr)


def test_playcanvas_uses_the_lod_from_far(served, tmp_path):
    work, base = served
    meta = json.loads((work / "sog" / "lod-meta.json").read_text())
    query, _ = scene_camera(work / "scene", 40.0)
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': '/scene/lod-meta.json', **query})}",
                   tmp_path / "far.png", SIZE)
    result = report["result"]
    print(f"donut far: {result['splats']} splats drawn of {meta['counts']}, units {result['units']}")
    assert 0 < result["splats"] < meta["counts"][0]
    assert not any(u.startswith("0_") for u in result["units"])  # no level-0 unit was even fetched
