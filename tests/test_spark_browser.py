"""Our RAD export (`export-rad`) in Spark 2 (npm `@sparkjsdev/spark` with `three`, .ci/node) in headless Chromium
(Debian's `chromium`, software WebGL through SwiftShader), driven by playwright-core like the CesiumJS and
PlayCanvas tests (what the three share: tests/browser.py).

The page (tests/spark_page/) loads the .rad with Spark's paged loader (`SplatMesh({paged: true})`): the header
first, then each 64K-splat chunk by an HTTP range request once Spark's LoD traversal needs it; so the server here
answers Range requests (Python's SimpleHTTPRequestHandler does not). Every other request is refused by the
driver. The camera is the scene's suggested camera in the scene's own coordinates (the .rad keeps the PLY's axes
and the page adds the mesh untransformed); the screenshot is compared with our `render` of the same camera (drawn
pixels' IoU and PSNR, as the PlayCanvas test does). From far away (same direction, 40x the distance) Spark must
draw fewer splats than the scene's full detail: its LoD traversal stops above the leaves.

Scene: the bundled donut (samples/donut.ply, so a fresh clone has it), 2,000-splat leaves.
"""
from __future__ import annotations

import json
import urllib.parse
from pathlib import Path

import pytest
from browser import NODE_MODULES, compare, keep, render_ours, requirements, scene_camera, serve, shoot
from conftest import ROOT, run_cli
from test_playcanvas_browser import MIN_IOU, MIN_PSNR_DB, SCENE, SIZE

from splatstream.readers.rad import read_rad_tree

SPARK = NODE_MODULES / "@sparkjsdev" / "spark"
THREE = NODE_MODULES / "three"
PAGE_DIR = ROOT / "tests" / "spark_page"


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """The page's files, three under /three/, Spark under /spark/, the exported files under /scene/, answering
    range requests (Spark's paged loader reads the .rad by ranges)."""
    requirements(SPARK / "dist" / "spark.module.js", THREE / "build" / "three.module.js",
                 what="@sparkjsdev/spark / three")
    work = tmp_path_factory.mktemp("spark")
    r = run_cli("encode", SCENE, work / "scene", "--max-leaf-splats", "2000", "--quiet")
    assert r.returncode == 0, r.stderr
    (work / "rad").mkdir()
    for name, encoding in (("donut.rad", "exact"), ("donut_spark.rad", "spark")):
        r = run_cli("export-rad", work / "scene", work / "rad" / name, "--encoding", encoding, "--quiet")
        assert r.returncode == 0, r.stderr
    with serve(PAGE_DIR, {"/three/": THREE, "/spark/": SPARK, "/scene/": work / "rad"}, ranges=True) as (url, ranges):
        yield work, url, ranges


@pytest.mark.parametrize("name", ["donut.rad", "donut_spark.rad"])
def test_spark_draws_our_rad_where_we_do(served, tmp_path, name):
    """Both encodings: ours (f32 / f16) and Spark's own 8-bit ones (our port of its encoders, drawn by Spark)."""
    work, base, ranges = served
    tree = read_rad_tree(work / "rad" / name)
    leaves = int((tree.child_count == 0).sum())
    query, ours = scene_camera(work / "scene")
    ranges.clear()
    theirs_png, ours_png = tmp_path / f"spark-{name[:-4]}.png", tmp_path / "ours-donut-spark.png"
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': f'/scene/{name}', **query})}",
                   theirs_png, SIZE)
    render_ours(work / "scene", ours_png, SIZE, ours)
    keep(theirs_png, ours_png)
    iou, psnr = compare(ours_png, theirs_png)
    result = report["result"]
    print(f"{name} near: IoU {iou:.3f}, PSNR {psnr:.1f} dB, {result['splats']} splats drawn of {leaves} leaves "
          f"({len(tree.splats)} in the tree), {result['fetches']} fetches, {result['waitedMs']} ms, {report['gl']}")
    assert iou >= MIN_IOU and psnr >= MIN_PSNR_DB, (iou, psnr)
    # Paged: the header, then both chunks (the donut's 91,263 splats fill two), each by a range request.
    assert chunks_fetched(work / "rad" / name, ranges) == [0, 1], ranges


def test_spark_uses_the_lod_from_far(served, tmp_path):
    work, base, ranges = served
    tree = read_rad_tree(work / "rad" / "donut.rad")
    leaves = int((tree.child_count == 0).sum())
    query, _ = scene_camera(work / "scene", 40.0)
    ranges.clear()
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': '/scene/donut.rad', **query})}",
                   tmp_path / "far.png", SIZE)
    result = report["result"]
    print(f"donut far: {result['splats']} splats drawn of {leaves} leaves")
    assert 0 < result["splats"] < leaves
    # The second chunk (finest splats only) is never fetched.
    assert chunks_fetched(work / "rad" / "donut.rad", ranges) == [0], ranges


def chunks_fetched(rad: Path, ranges: list[tuple[str, int, int]]) -> list[int]:
    """Indices of the chunks of `rad` whose first byte a range request asked for."""
    data = rad.read_bytes()
    length = int.from_bytes(data[4:8], "little")
    meta = json.loads(data[8:8 + length])
    start = 8 + ((length + 7) & ~7)
    firsts = {start + c["offset"]: i for i, c in enumerate(meta["chunks"])}
    return sorted({firsts[a] for name, a, _ in ranges if name == rad.name and a in firsts})
