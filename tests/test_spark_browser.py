"""Our RAD export (`export-rad`) in Spark 2 (npm `@sparkjsdev/spark` with `three`, .ci/node) in headless Chromium
(Debian's `chromium`, software WebGL through SwiftShader), driven by playwright-core like the CesiumJS and
PlayCanvas tests (tests/cesium_page/drive.cjs).

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

import functools
import http.server
import json
import os
import re
import shutil
import threading
import urllib.parse
from pathlib import Path

import pytest
from conftest import ROOT, run_cli
from test_cesium_browser import compare
from test_playcanvas_browser import ARTIFACTS, MIN_IOU, MIN_PSNR_DB, SCENE, SIZE, camera, shoot
from test_playcanvas_browser import requirements as playcanvas_requirements

from splatstream.readers.rad import read_rad_tree

NODE_MODULES = ROOT / ".ci" / "node" / "node_modules"
SPARK = NODE_MODULES / "@sparkjsdev" / "spark"
THREE = NODE_MODULES / "three"
PAGE_DIR = ROOT / "tests" / "spark_page"


def requirements() -> None:
    # The PlayCanvas test's requirements (node, playwright-core, chromium, our GL), plus Spark and three.
    if not (SPARK / "dist" / "spark.module.js").is_file() or not (THREE / "build" / "three.module.js").is_file():
        pytest.skip("@sparkjsdev/spark / three not installed (.ci/run installs them into .ci/node)")
    playcanvas_requirements()


class _Handler(http.server.SimpleHTTPRequestHandler):
    """The page's files, three under /three/, Spark under /spark/, the exported file under /scene/; answers
    `Range: bytes=A-B` with 206 and those bytes (Spark's paged loader reads the .rad by ranges)."""

    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".mjs": "text/javascript",
                      ".js": "text/javascript", ".json": "application/json", ".rad": "application/octet-stream"}

    def __init__(self, *args, scene_dir: Path, **kwargs):
        self.scene_dir = scene_dir
        super().__init__(*args, **kwargs)

    def translate_path(self, path: str) -> str:
        path = urllib.parse.unquote(urllib.parse.urlsplit(path).path)
        base, rel = PAGE_DIR, path
        for prefix, root in (("/three/", THREE), ("/spark/", SPARK), ("/scene/", self.scene_dir)):
            if path.startswith(prefix):
                base, rel = root, path[len(prefix):]
        parts = [p for p in rel.split("/") if p not in ("", ".", "..")]
        return os.path.join(base, *parts)

    def do_GET(self) -> None:
        match = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        path = self.translate_path(self.path)
        if not match or not os.path.isfile(path):
            return super().do_GET()
        size = os.path.getsize(path)
        start = int(match[1])
        end = min(int(match[2]) if match[2] else size - 1, size - 1)
        if start > end:
            self.send_error(416)
            return
        self.server.ranges.append((os.path.basename(path), start, end))
        with open(path, "rb") as f:
            f.seek(start)
            body = f.read(end - start + 1)
        self.send_response(206)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    requirements()
    work = tmp_path_factory.mktemp("spark")
    r = run_cli("encode", SCENE, work / "scene", "--max-leaf-splats", "2000", "--quiet")
    assert r.returncode == 0, r.stderr
    (work / "rad").mkdir()
    for name, encoding in (("donut.rad", "exact"), ("donut_spark.rad", "spark")):
        r = run_cli("export-rad", work / "scene", work / "rad" / name, "--encoding", encoding, "--quiet")
        assert r.returncode == 0, r.stderr
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Handler, scene_dir=work / "rad"))
    httpd.ranges = []  # (file, first byte, last byte) of every range request, in order
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield work, f"http://127.0.0.1:{httpd.server_address[1]}", httpd.ranges
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.mark.parametrize("name", ["donut.rad", "donut_spark.rad"])
def test_spark_draws_our_rad_where_we_do(served, tmp_path, name):
    """Both encodings: ours (f32 / f16) and Spark's own 8-bit ones (our port of its encoders, drawn by Spark)."""
    work, base, ranges = served
    tree = read_rad_tree(work / "rad" / name)
    leaves = int((tree.child_count == 0).sum())
    query, ours = camera(work / "scene")
    ranges.clear()
    theirs_png, ours_png = tmp_path / f"spark-{name[:-4]}.png", tmp_path / "ours-donut-spark.png"
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': f'/scene/{name}', **query})}",
                   theirs_png)
    r = run_cli("render", work / "scene", "--out", ours_png, "--size", f"{SIZE[0]}x{SIZE[1]}", "--quiet", *ours)
    assert r.returncode == 0, r.stderr
    if ARTIFACTS:
        os.makedirs(ARTIFACTS, exist_ok=True)
        for p in (theirs_png, ours_png):
            shutil.copy(p, os.path.join(ARTIFACTS, p.name))
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
    query, _ = camera(work / "scene", 40.0)
    ranges.clear()
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': '/scene/donut.rad', **query})}",
                   tmp_path / "far.png")
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
