"""Our streamed-SOG export (`export-sog-lod`) in PlayCanvas's engine (npm `playcanvas`, .ci/node) in headless
Chromium (Debian's `chromium`, software WebGL through SwiftShader), driven by playwright-core like the CesiumJS test
(tests/test_cesium_browser.py, whose driver tests/cesium_page/drive.cjs this reuses).

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

import functools
import http.server
import json
import os
import shutil
import subprocess
import threading
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, run_cli
from test_cesium_browser import CHROMIUM, compare

from splatstream.store import load_manifest

NODE_MODULES = ROOT / ".ci" / "node" / "node_modules"
ENGINE = NODE_MODULES / "playcanvas" / "build"
PAGE_DIR = ROOT / "tests" / "playcanvas_page"
DRIVER = ROOT / "tests" / "cesium_page" / "drive.cjs"
SCENE = ROOT / "samples" / "donut.ply"
SIZE = (320, 240)
MIN_IOU = 0.95
MIN_PSNR_DB = 25.0
ARTIFACTS = os.environ.get("SPLATSTREAM_TEST_ARTIFACTS")  # keep the screenshots there (README's image)


def requirements() -> None:
    if shutil.which("node") is None:
        pytest.skip("node not installed")
    if not (ENGINE / "playcanvas.mjs").is_file() or not (NODE_MODULES / "playwright-core").is_dir():
        pytest.skip("playcanvas / playwright-core not installed (.ci/run installs them into .ci/node)")
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} not installed (.ci/run: apt-get install chromium)")
    from client_gl.offscreen import GLUnavailableError, shared_context

    try:
        shared_context()  # our render needs headless GL (EGL)
    except GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")


class _Handler(http.server.SimpleHTTPRequestHandler):
    """The page's files, the engine's build under /playcanvas/ and the exported scene under /scene/."""

    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".mjs": "text/javascript",
                      ".js": "text/javascript", ".json": "application/json", ".webp": "image/webp"}

    def __init__(self, *args, scene_dir: Path, **kwargs):
        self.scene_dir = scene_dir
        super().__init__(*args, **kwargs)

    def translate_path(self, path: str) -> str:
        path = urllib.parse.unquote(urllib.parse.urlsplit(path).path)
        base, rel = PAGE_DIR, path
        for prefix, root in (("/playcanvas/", ENGINE), ("/scene/", self.scene_dir)):
            if path.startswith(prefix):
                base, rel = root, path[len(prefix):]
        parts = [p for p in rel.split("/") if p not in ("", ".", "..")]
        return os.path.join(base, *parts)

    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    requirements()
    work = tmp_path_factory.mktemp("playcanvas")
    r = run_cli("encode", SCENE, work / "scene", "--max-leaf-splats", "2000", "--quiet")
    assert r.returncode == 0, r.stderr
    r = run_cli("export-sog-lod", work / "scene", work / "sog", "--quiet")
    assert r.returncode == 0, r.stderr
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Handler, scene_dir=work / "sog"))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield work, f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


def shoot(url: str, out: Path) -> dict:
    r = subprocess.run(["node", str(DRIVER), url, str(out), f"{SIZE[0]}x{SIZE[1]}", CHROMIUM], capture_output=True,
                       text=True, timeout=500, stdin=subprocess.DEVNULL, env={**os.environ,
                                                                              "NODE_PATH": str(NODE_MODULES)})
    lines = [line for line in r.stdout.splitlines() if line.startswith("{")]
    assert lines, f"driver said nothing: {r.stdout[-2000:]} {r.stderr[-2000:]}"
    report = json.loads(lines[-1])
    assert r.returncode == 0 and report["result"]["status"] == "ok", json.dumps(report)[:4000]
    assert not any(line.startswith("refused") for line in report["logs"]), report["logs"]
    return report


def camera(scene: Path, distance_scale: float = 1.0) -> tuple[dict, list[str]]:
    cam = load_manifest(scene).camera
    eye, target = np.asarray(cam.eye, np.float64), np.asarray(cam.target, np.float64)
    eye = target + (eye - target) * distance_scale

    def text(v) -> str:
        return ",".join(repr(float(x)) for x in v)

    query = {"eye": text(eye), "target": text(target), "up": text(cam.up), "fovy": cam.fov_y,
             "near": 0.01 * float(np.linalg.norm(target - eye))}
    ours = [f"--eye={text(eye)}", f"--target={text(target)}", f"--up={text(cam.up)}", f"--fov-y={cam.fov_y}"]
    return query, ours


def test_playcanvas_draws_our_streamed_sog_where_we_do(served, tmp_path):
    work, base = served
    meta = json.loads((work / "sog" / "lod-meta.json").read_text())
    query, ours = camera(work / "scene")
    theirs_png, ours_png = tmp_path / "playcanvas-donut.png", tmp_path / "ours-donut.png"
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': '/scene/lod-meta.json', **query})}",
                   theirs_png)
    r = run_cli("render", work / "scene", "--out", ours_png, "--size", f"{SIZE[0]}x{SIZE[1]}", "--quiet", *ours)
    assert r.returncode == 0, r.stderr
    if ARTIFACTS:
        os.makedirs(ARTIFACTS, exist_ok=True)
        for p in (theirs_png, ours_png):
            shutil.copy(p, os.path.join(ARTIFACTS, p.name))
    iou, psnr = compare(ours_png, theirs_png)
    result = report["result"]
    print(f"donut near: IoU {iou:.3f}, PSNR {psnr:.1f} dB, {result['splats']} splats drawn of {meta['counts']}, "
          f"units {result['units']}, {result['waitedMs']} ms, {report['gl']}")
    assert result["splats"] == meta["counts"][0]  # level 0: the scene's full detail, what we render
    assert iou >= MIN_IOU and psnr >= MIN_PSNR_DB, (iou, psnr)


def test_playcanvas_uses_the_lod_from_far(served, tmp_path):
    work, base = served
    meta = json.loads((work / "sog" / "lod-meta.json").read_text())
    query, _ = camera(work / "scene", 40.0)
    report = shoot(f"{base}/index.html?{urllib.parse.urlencode({'scene': '/scene/lod-meta.json', **query})}",
                   tmp_path / "far.png")
    result = report["result"]
    print(f"donut far: {result['splats']} splats drawn of {meta['counts']}, units {result['units']}")
    assert 0 < result["splats"] < meta["counts"][0]
    assert not any(u.startswith("0_") for u in result["units"])  # no level-0 unit was even fetched
