"""The interactive viewer in a real window on a virtual display (Xvfb): real X input events (xdotool) drive the
camera, the screenshot key saves the frame without the overlay, and the frame matches the headless render of the
same camera. Skipped where Xvfb or xdotool are missing (.ci/run installs both)."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, xvfb_display

pytestmark = pytest.mark.skipif(not (shutil.which("Xvfb") and shutil.which("xdotool")),
                                reason="needs Xvfb and xdotool (apt-get install xvfb xdotool)")
SIZE = (720, 420)


@pytest.fixture(scope="module")
def display():
    with xvfb_display("1024x768x24") as name:
        yield name


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("served")
    r = subprocess.run([sys.executable, "-m", "cli", "encode", str(ROOT / "samples" / "donut.ply"),
                        str(root / "donut"), "--max-leaf-splats", "8000", "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    proc = subprocess.Popen([sys.executable, "-m", "cli", "serve", str(root), "--port", "0",
                             "--no-access-log"], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    line = proc.stderr.readline()
    url = line.split("at ", 1)[1].split(" ", 1)[0].rstrip("/") + "/scenes/donut"
    yield url
    proc.send_signal(signal.SIGTERM)
    proc.wait(10)


def xdo(display: str, *args: str) -> str:
    return subprocess.run(["xdotool", *args], env={**os.environ, "DISPLAY": display}, capture_output=True,
                          text=True, timeout=20).stdout


def wait_for_window(display: str, timeout: float = 60.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ids = xdo(display, "search", "--onlyvisible", "--name", "splatstream").split()
        if ids:
            return ids[0]
        time.sleep(0.2)
    raise AssertionError("the viewer's window did not appear")


def grab(display: str, window: str) -> np.ndarray:
    """The window's pixels as the X server shows them (overlay included)."""
    from Xlib import X
    from Xlib import display as xdisplay

    d = xdisplay.Display(display)
    try:
        win = d.create_resource_object("window", int(window))
        geo = win.get_geometry()
        root = d.screen().root
        pos = win.translate_coords(root, 0, 0)  # the window's origin in root coordinates (negated)
        x, y = -pos.x, -pos.y
        raw = root.get_image(x, y, geo.width, geo.height, X.ZPixmap, 0xFFFFFFFF).data
        img = np.frombuffer(raw, np.uint8).reshape(geo.height, geo.width, 4)[..., [2, 1, 0]]
        return img.astype(np.float32) / 255.0
    finally:
        d.close()


def psnr(a, b) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def test_window_input_screenshot_and_overlay(display, served, tmp_path):
    from PIL import Image

    env = {**os.environ, "DISPLAY": display, "SPLATSTREAM_CACHE_DIR": str(tmp_path / "cache")}
    viewer = subprocess.Popen([sys.executable, "-m", "cli", "view", served, "--size",
                               f"{SIZE[0]}x{SIZE[1]}", "--gpu-mem-mb", "64", "--no-vsync",
                               "--record", str(tmp_path / "record.json")], env=env, cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        window = wait_for_window(display)
        xdo(display, "windowfocus", "--sync", window)
        time.sleep(3.0)  # the scene streams in
        # A user's orbit: drag with the left button across the image (outside the overlay), then the screenshot key.
        xdo(display, "mousemove", "--window", window, "560", "300", "mousedown", "1")
        for x in range(560, 620, 6):
            xdo(display, "mousemove", "--window", window, str(x), "305")
        xdo(display, "mouseup", "1")
        time.sleep(3.0)  # the camera settles (smoothing) and the new view converges
        xdo(display, "windowfocus", "--sync", window)
        xdo(display, "key", "p")
        deadline = time.monotonic() + 20
        shots = []
        while time.monotonic() < deadline and not shots:
            shots = sorted(tmp_path.glob("splatstream-*.png"))
            time.sleep(0.2)
        assert shots, "no screenshot was written"
        time.sleep(0.5)
        window_pixels = grab(display, window)
        assert window_pixels.shape[0] >= SIZE[1] and window_pixels.shape[1] >= SIZE[0], window_pixels.shape
        xdo(display, "key", "Escape")
        out, err = viewer.communicate(timeout=30)
    finally:
        if viewer.poll() is None:
            viewer.kill()
            viewer.communicate()
    assert viewer.returncode == 0, err
    assert "Traceback" not in err
    assert f"saved {shots[0]}" in out
    record = json.loads((tmp_path / "record.json").read_text())
    assert record["window_backend"] == "glfw"  # not pyglet's fallback
    assert record["gl_version"] >= 430  # compute shaders in the window
    assert record["sort"] == "cpu"  # as choose_sort picks on a software GL (llvmpipe); the GPU sort on a real GPU
    shot = np.asarray(Image.open(shots[0]), np.float32) / 255.0
    assert shot.shape == (SIZE[1], SIZE[0], 3)
    cam = json.loads(Path(str(shots[0]) + ".camera.json").read_text())
    # the drag moved the camera away from the scene's suggested one (an orbit: same target, same distance)
    import urllib.request

    from splatstream.format.manifest import parse_manifest

    with urllib.request.urlopen(served + "/manifest.msgpack", timeout=10) as resp:
        home = parse_manifest(resp.read()).camera
    moved = np.linalg.norm(np.subtract(cam["eye"], home.eye))
    dist = np.linalg.norm(np.subtract(home.eye, home.target))
    assert moved > 0.05 * dist
    assert np.linalg.norm(np.subtract(cam["eye"], cam["target"])) == pytest.approx(dist, rel=0.02)
    # the same camera headless: the screenshot holds the same picture
    ref = tmp_path / "headless.png"
    r = subprocess.run([sys.executable, "-m", "cli", "view", served, "--headless", "--size",
                        f"{SIZE[0]}x{SIZE[1]}", "--gpu-mem-mb", "64", "--eye=" + ",".join(map(str, cam["eye"])),
                        "--target=" + ",".join(map(str, cam["target"])), "--up=" + ",".join(map(str, cam["up"])),
                        "--fov-y", str(cam["fov_y_deg"]), "--screenshot", str(ref), "-q"],
                       capture_output=True, text=True, env={**os.environ, "SPLATSTREAM_CACHE_DIR": str(tmp_path)})
    assert r.returncode == 0, r.stderr
    headless = np.asarray(Image.open(ref), np.float32) / 255.0
    assert psnr(shot, headless) >= 40
    # the overlay was in the window (top left), not in the screenshot; elsewhere the window shows the screenshot
    h, w = shot.shape[:2]
    win = window_pixels[:h, :w]
    overlay = np.abs(win[10:60, 10:200] - shot[10:60, 10:200]).mean()
    assert overlay > 0.05, overlay
    assert psnr(win[:, 440:], shot[:, 440:]) >= 40  # right of the overlay panel


def test_window_exit_when_converged_with_screenshot_alone(display, served, tmp_path):
    """The README's `view URL --screenshot shot.png --exit-when-converged` in a window, with no other option
    (`--measure-frames` at its default 0): the screenshot is written and the viewer exits 0 without an error."""
    from PIL import Image

    env = {**os.environ, "DISPLAY": display, "SPLATSTREAM_CACHE_DIR": str(tmp_path / "cache")}
    r = subprocess.run([sys.executable, "-m", "cli", "view", served, "--screenshot", "shot.png",
                        "--exit-when-converged"], env=env, cwd=tmp_path, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "internal error" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    shot = np.asarray(Image.open(tmp_path / "shot.png"), np.float32) / 255.0
    assert shot.ndim == 3 and shot.shape[2] == 3
    assert shot.std() > 0.02  # the scene is in the picture, not an empty background
