"""What the browser tests share (tests/test_cesium_browser.py, test_playcanvas_browser.py, test_spark_browser.py):
a peer engine's page in headless Chromium (Debian's `chromium`, software WebGL through SwiftShader) driven by
playwright-core (tests/cesium_page/drive.cjs), the page's files served from loopback, and its screenshot compared
with our own render of the same camera.

* `requirements` skips a test (with the reason) where node, the npm packages (.ci/run installs them into
  .ci/node), Chromium or our headless GL are missing.
* `serve` is a loopback HTTP server of a page directory and of folders under URL prefixes (an engine's build, the
  exported scene); with `ranges`, it answers `Range: bytes=A-B` with 206 and records each range asked for (Spark's
  paged loader reads a .rad by ranges; Python's SimpleHTTPRequestHandler does not answer them).
* `shoot` runs the driver: the page at a URL, its screenshot, and its `window.splatResult` with the console log;
  every request not to loopback is refused by the driver, and a refused request fails the shot.
* `compare`: the masks of drawn pixels (any channel above 16/255 on the black background) by intersection over
  union, and the PSNR of the two images.
"""
from __future__ import annotations

import contextlib
import functools
import http.server
import json
import os
import re
import shutil
import subprocess
import threading
import urllib.parse
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, run_cli

from splatstream.store import load_manifest

NODE_MODULES = ROOT / ".ci" / "node" / "node_modules"
DRIVER = ROOT / "tests" / "cesium_page" / "drive.cjs"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
MASK_LEVEL = 16  # of 255: a drawn pixel
ARTIFACTS = os.environ.get("SPLATSTREAM_TEST_ARTIFACTS")  # keep the screenshots there (README's images)


def requirements(*files: Path, what: str) -> None:
    """Skip unless node, playwright-core, these installed files (`what` names their packages), Chromium and our
    headless GL (EGL, for our render) are all here."""
    if shutil.which("node") is None:
        pytest.skip("node not installed")
    if not all(Path(f).exists() for f in files) or not (NODE_MODULES / "playwright-core").is_dir():
        pytest.skip(f"{what} / playwright-core not installed (.ci/run installs them into .ci/node)")
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} not installed (.ci/run: apt-get install chromium)")
    from client_gl.offscreen import GLUnavailableError, shared_context

    try:
        shared_context()
    except GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")


class _Handler(http.server.SimpleHTTPRequestHandler):
    """The page directory's files, and each folder of `routes` under its URL prefix ("/cesium/": a build)."""

    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".wasm": "application/wasm",
                      ".mjs": "text/javascript", ".js": "text/javascript", ".json": "application/json",
                      ".webp": "image/webp", ".rad": "application/octet-stream"}

    def __init__(self, *args, page_dir: Path, routes: dict[str, Path], ranges: list | None, **kwargs):
        self.page_dir, self.routes, self.ranges = page_dir, routes, ranges
        super().__init__(*args, **kwargs)

    def translate_path(self, path: str) -> str:
        path = urllib.parse.unquote(urllib.parse.urlsplit(path).path)
        base, rel = self.page_dir, path
        for prefix, root in self.routes.items():
            if path.startswith(prefix):
                base, rel = root, path[len(prefix):]
        parts = [p for p in rel.split("/") if p not in ("", ".", "..")]
        return os.path.join(base, *parts)

    def do_GET(self) -> None:
        match = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        path = self.translate_path(self.path)
        if self.ranges is None or not match or not os.path.isfile(path):
            return super().do_GET()
        size = os.path.getsize(path)
        start = int(match[1])
        end = min(int(match[2]) if match[2] else size - 1, size - 1)
        if start > end:
            self.send_error(416)
            return
        self.ranges.append((os.path.basename(path), start, end))
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


@contextlib.contextmanager
def serve(page_dir: Path, routes: dict[str, Path], ranges: bool = False) -> Iterator[tuple[str, list]]:
    """A loopback server of `page_dir` and `routes` (URL prefix -> folder); yields its base URL and the list of
    (file name, first byte, last byte) of every range request answered (empty without `ranges`)."""
    asked: list[tuple[str, int, int]] = []
    handler = functools.partial(_Handler, page_dir=page_dir, routes=routes, ranges=asked if ranges else None)
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", asked
    finally:
        httpd.shutdown()
        httpd.server_close()


def shoot(url: str, out: Path, size: tuple[int, int], timeout: float = 1800) -> dict:
    """The page at `url` in headless Chromium: its screenshot written to `out`, its report returned (`result`:
    the page's window.splatResult, `gl`: the WebGL renderer, `logs`: console lines and refused requests)."""
    r = subprocess.run(["node", str(DRIVER), url, str(out), f"{size[0]}x{size[1]}", CHROMIUM], capture_output=True,
                       text=True, timeout=timeout, stdin=subprocess.DEVNULL,
                       env={**os.environ, "NODE_PATH": str(NODE_MODULES)})
    lines = [line for line in r.stdout.splitlines() if line.startswith("{")]
    assert lines, f"driver said nothing: {r.stdout[-2000:]} {r.stderr[-2000:]}"
    report = json.loads(lines[-1])
    assert r.returncode == 0 and report["result"]["status"] == "ok", json.dumps(report)[:4000]
    assert not any(line.startswith("refused") for line in report["logs"]), report["logs"]  # nothing from outside
    return report


def compare(ours_png: Path, theirs_png: Path) -> tuple[float, float]:
    """Drawn-pixel IoU and PSNR (dB) of two screenshots of one size."""
    from PIL import Image

    a = np.asarray(Image.open(ours_png).convert("RGB"), np.float64)
    b = np.asarray(Image.open(theirs_png).convert("RGB"), np.float64)
    assert a.shape == b.shape
    ma, mb = a.max(axis=2) > MASK_LEVEL, b.max(axis=2) > MASK_LEVEL
    iou = float((ma & mb).sum() / max((ma | mb).sum(), 1))
    mse = float(((a - b) ** 2).mean())
    return iou, 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def coverage(png: Path) -> float:
    """The share of drawn pixels."""
    from PIL import Image

    return float((np.asarray(Image.open(png).convert("L")) > MASK_LEVEL).mean())


def vector_text(v) -> str:
    return ",".join(repr(float(x)) for x in v)


def scene_camera(scene: Path, distance_scale: float = 1.0) -> tuple[dict, list[str]]:
    """The scene's suggested camera in its own coordinates, `distance_scale` times as far from its target: the
    page's query (eye, target, up, fovy, near) and the same camera as `splatstream render` options."""
    cam = load_manifest(scene).camera
    eye, target = np.asarray(cam.eye, np.float64), np.asarray(cam.target, np.float64)
    eye = target + (eye - target) * distance_scale
    query = {"eye": vector_text(eye), "target": vector_text(target), "up": vector_text(cam.up), "fovy": cam.fov_y,
             "near": 0.01 * float(np.linalg.norm(target - eye))}
    # (--opt=value: a vector may start with a minus sign)
    ours = [f"--eye={vector_text(eye)}", f"--target={vector_text(target)}", f"--up={vector_text(cam.up)}",
            f"--fov-y={cam.fov_y}"]
    return query, ours


def render_ours(scene: Path, out: Path, size: tuple[int, int], camera_args: list[str], *extra: str) -> None:
    """`splatstream render` of the scene from that camera (a process of its own, as a user runs it)."""
    r = run_cli("render", scene, "--out", out, "--size", f"{size[0]}x{size[1]}", "--quiet", *camera_args, *extra)
    assert r.returncode == 0, r.stderr


def keep(*pngs: Path) -> None:
    """Copy the screenshots to SPLATSTREAM_TEST_ARTIFACTS, where that is set."""
    if ARTIFACTS:
        os.makedirs(ARTIFACTS, exist_ok=True)
        for p in pngs:
            shutil.copy(p, os.path.join(ARTIFACTS, p.name))
