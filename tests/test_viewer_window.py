"""The interactive viewer in a real window on a virtual display (Xvfb): real X input events (xdotool) drive the
camera, the screenshot key saves the frame without the overlay, and the frame matches the headless render of the
same camera. Skipped where Xvfb or xdotool are missing (.ci/run installs both)."""
import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, xvfb_display

pytestmark = pytest.mark.skipif(not (shutil.which("Xvfb") and shutil.which("xdotool")),
                                reason="needs Xvfb and xdotool (apt-get install xvfb xdotool)")
SIZE = (720, 420)
# Each wait below is for something the viewer does (a window, a line it prints); this bound only stops a hang (the
# steps take seconds, tens of seconds on a loaded machine), with a message saying what never came.
HANG_S = 300.0


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


class ViewerOutput:
    """The viewer's stdout and stderr (one pipe, so in the order printed), read line by line on a thread: the test
    waits for the lines the viewer prints when something happens ("view: converged", "saved ..."), not for a time."""

    def __init__(self, stream):
        self.lines: list[str] = []
        self.closed = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in stream:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def text(self) -> str:
        with self._cond:
            return "\n".join(self.lines)

    def wait_for(self, prefix: str, after: int, what: str) -> int:
        """The index of the first line after line `after` (-1: from the start) that starts with `prefix`."""
        deadline = time.monotonic() + HANG_S
        with self._cond:
            start = after + 1
            while True:
                for i in range(start, len(self.lines)):
                    if self.lines[i].startswith(prefix):
                        return i
                start = len(self.lines)
                if self.closed:
                    raise AssertionError(f"the viewer exited before {what}; its output:\n" + "\n".join(self.lines))
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"no {what} after {HANG_S:g} s (a hang?); the viewer's output:\n"
                                         + "\n".join(self.lines))
                self._cond.wait(left)

    def join(self) -> None:
        self._thread.join(HANG_S)


def wait_for_window(display: str, viewer: subprocess.Popen, output: ViewerOutput) -> str:
    """The viewer's window once it is mapped (xdotool's --sync search returns when it is)."""
    search = subprocess.Popen(["xdotool", "search", "--sync", "--onlyvisible", "--name", "splatstream"],
                              env={**os.environ, "DISPLAY": display}, stdout=subprocess.PIPE, text=True)
    deadline = time.monotonic() + HANG_S
    try:
        while True:
            try:
                return search.communicate(timeout=1.0)[0].split()[0]
            except subprocess.TimeoutExpired:
                if viewer.poll() is not None or time.monotonic() > deadline:  # the search alone would wait forever
                    raise AssertionError(f"the viewer's window did not appear (viewer exit code {viewer.poll()}); "
                                         f"its output:\n{output.text()}") from None
    finally:
        if search.poll() is None:
            search.kill()
            search.communicate()


@contextlib.contextmanager
def open_viewer(display: str, source: str, tmp_path: Path, *extra: str):
    """`view SOURCE` in a window of SIZE on the display (its own disk cache under tmp_path), yielded as (viewer, its
    output, the window's id) once the window is mapped; killed on the way out if a test left it running."""
    env = {**os.environ, "DISPLAY": display, "SPLATSTREAM_CACHE_DIR": str(tmp_path / "cache")}
    viewer = subprocess.Popen([sys.executable, "-m", "cli", "view", source, "--size", f"{SIZE[0]}x{SIZE[1]}",
                               "--no-vsync", *extra], env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    output = ViewerOutput(viewer.stdout)
    try:
        yield viewer, output, wait_for_window(display, viewer, output)
    finally:
        if viewer.poll() is None:
            viewer.kill()
            viewer.wait()


def quit_viewer(display: str, viewer: subprocess.Popen, output: ViewerOutput) -> None:
    """Esc, as a user quits, and the viewer's exit and output awaited."""
    xdo(display, "key", "Escape")
    viewer.wait(HANG_S)
    output.join()


def screenshot_at_rest(display: str, window: str, output: ViewerOutput, seen: int, what: str) -> tuple[Path, int]:
    """P until the screenshot's line says the view was at rest ("converged"), waiting for the next "view:
    converged" between tries: (the screenshot's path, the index of its line)."""
    for _ in range(5):
        xdo(display, "windowfocus", "--sync", window)
        xdo(display, "key", "p")
        seen = output.wait_for("saved ", seen, "line for the screenshot (P)")
        if "; converged; " in output.lines[seen]:
            return Path(output.lines[seen][len("saved "):].split(" (", 1)[0]), seen
        seen = output.wait_for("view: converged", seen, what)
    raise AssertionError(f"no screenshot of the view at rest:\n{output.text()}")


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

    with open_viewer(display, served, tmp_path, "--gpu-mem-mb", "64", "--record",
                     str(tmp_path / "record.json")) as (viewer, output, window):
        xdo(display, "windowfocus", "--sync", window)
        # The viewer prints "view: converged" each time the view comes to rest (every wanted tile resident, nothing
        # in flight, the camera still): here, the scene has streamed in.
        seen = output.wait_for("view: converged", -1, "converged view of the scene")
        # A user's orbit: drag with the left button across the image (outside the overlay), then the screenshot key.
        xdo(display, "mousemove", "--window", window, "560", "300", "mousedown", "1")
        for x in range(560, 620, 6):
            xdo(display, "mousemove", "--window", window, str(x), "305")
        xdo(display, "mouseup", "1")
        # X delivers the key after the drag, so the screenshot's line comes after the orbit was applied; it says
        # whether the view was at rest ("converged") or not.
        shot, seen = screenshot_at_rest(display, window, output, seen, "converged view after the orbit")
        assert shot.parent == tmp_path and shot.name.startswith("splatstream-"), output.lines[seen]
        window_pixels = grab(display, window)  # the window shows the same view at rest (and the overlay)
        assert window_pixels.shape[0] >= SIZE[1] and window_pixels.shape[1] >= SIZE[0], window_pixels.shape
        quit_viewer(display, viewer, output)
    out = output.text()
    assert viewer.returncode == 0, out
    assert "Traceback" not in out
    record = json.loads((tmp_path / "record.json").read_text())
    assert record["window_backend"] == "glfw"  # not pyglet's fallback
    assert record["gl_version"] >= 430  # compute shaders in the window
    assert record["sort"] == "cpu"  # as choose_sort picks on a software GL (llvmpipe); the GPU sort on a real GPU
    assert record["draw"] == "raster"  # what the overlay says (draw_path_line); it said "fetch", the GPU path's draw
    cam = json.loads(Path(str(shot) + ".camera.json").read_text())
    shot = np.asarray(Image.open(shot), np.float32) / 255.0
    assert shot.shape == (SIZE[1], SIZE[0], 3)
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


def test_window_says_which_payload_keeps_failing(display, tmp_path):
    """A served scene whose payloads the server does not have (stopped, or a file gone: 404): the window showed
    only 'OFFLINE' or nothing and printed nothing, so it looked stuck. It now names the payload's URL and why on
    stderr once it has failed twice in a row (as --headless does), and keeps retrying."""
    from splatstream.store import load_manifest

    root = tmp_path / "root"
    r = subprocess.run([sys.executable, "-m", "cli", "encode", str(ROOT / "samples" / "donut.ply"),
                        str(root / "donut"), "--max-leaf-splats", "8000", "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    m = load_manifest(root / "donut")
    keep = {e.file for e in (m.tile(m.root).groups[g] for g in m.tile(m.root).groups)}
    removed = [p for p in (root / "donut" / "data").iterdir() if f"data/{p.name}" not in keep]
    assert removed  # every tile but the root: its picture comes, the finer tiles answer 404
    for p in removed:
        p.unlink()
    server = subprocess.Popen([sys.executable, "-m", "cli", "serve", str(root), "--port", "0", "--no-access-log"],
                              stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        url = server.stderr.readline().split("at ", 1)[1].split(" ", 1)[0].rstrip("/") + "/scenes/donut"
        with open_viewer(display, url, tmp_path) as (viewer, output, window):
            said = output.wait_for(f"view: {url}/data/", -1, "line naming the failing payload")
            line = output.lines[said]
            assert "not on the server (404" in line and line.endswith("; retrying"), line
            assert viewer.poll() is None  # still open, retrying
            xdo(display, "windowfocus", "--sync", window)
            quit_viewer(display, viewer, output)
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(10)
    out = output.text()
    assert viewer.returncode == 0, out
    assert "Traceback" not in out
    assert len([ln for ln in output.lines if ln.startswith(f"view: {url}/data/")]) == 1, out  # once, not a frame


def test_overlay_gpu_line_says_the_budget_as_given():
    # `view --gpu-mem-mb 0.5` in a window: 'GPU 0.5 MiB resident of 0 MiB budget' (the budget rounded to MiB), read
    # as over budget; the headless summary says 'budget 0.5 MiB' since newuser58
    from client_gl.window import gpu_line

    assert gpu_line(524_288, int(0.5 * 2**20)) == "GPU     0.5 MiB resident of 0.5 MiB budget"
    assert gpu_line(16_866_200, 1024 * 2**20) == "GPU     16.1 MiB resident of 1024 MiB budget"


def test_window_controls_list_fits_a_short_window(display, served, tmp_path):
    """H in a window shorter than the controls list below the stats (a 960x600 window cut off its last lines, Esc
    among them): the list is placed from the window's bottom up, so all of it shows."""
    def frame_after(keys: list[str], seen: int) -> tuple[np.ndarray, int]:
        """The window's pixels once `keys` and a screenshot key have been handled: events are handled in order,
        between frames, so each 'saved' line comes a frame or more after the keys before it."""
        xdo(display, "key", *keys, "p")
        seen = output.wait_for("saved ", seen, "line for the screenshot (P)")
        return grab(display, window), seen

    with open_viewer(display, served, tmp_path, "--gpu-mem-mb", "64") as (viewer, output, window):
        seen = output.wait_for("view: converged", -1, "converged view of the scene")
        xdo(display, "windowfocus", "--sync", window)
        without, seen = frame_after([], seen)
        shown, seen = frame_after(["h"], seen)
        # The list is 16 lines (about 290 px) high. Placed at y = 330 as before, only its top rows are in a 420 px
        # window, and the band 130-300 px right of the stats panel (x 400-520) shows the scene unchanged; placed
        # from the bottom up, the list covers it. An auto-sized ImGui window shows a frame or two after it opens.
        for _ in range(10):
            if np.abs(shown[130:300, 400:520] - without[130:300, 400:520]).mean() > 0.02:
                break
            shown, seen = frame_after([], seen)
        quit_viewer(display, viewer, output)
    assert viewer.returncode == 0, output.text()
    band = np.abs(shown[130:300, 400:520] - without[130:300, 400:520]).mean()
    assert band > 0.02, band
    # its last line (Esc) is inside the window: the list's bottom edge is above the window's
    rows = np.abs(shown[:, 20:200] - without[:, 20:200]).mean(axis=(1, 2))
    assert rows[-8:].max() < rows[SIZE[1] - 60:SIZE[1] - 20].max(), rows[-60:]


def test_window_f_frames_the_box_the_suggested_camera_frames(display, served, tmp_path):
    """F in a window (issue 31): the view frames the box of the root tile's splats (camera.framing_box, the suggested
    camera's rule) from the current direction, not the bounding sphere of every splat. Pressed at the suggested
    camera, it comes back to about that camera (the root tile's box is the coarse stand-in for the scene's)."""
    import urllib.request

    from splatstream.format.manifest import parse_manifest

    with urllib.request.urlopen(served + "/manifest.msgpack", timeout=10) as resp:
        m = parse_manifest(resp.read())
    home, root = m.camera, m.tile(m.root)
    with open_viewer(display, served, tmp_path, "--gpu-mem-mb", "64") as (viewer, output, window):
        seen = output.wait_for("view: converged", -1, "converged view of the scene")
        xdo(display, "windowfocus", "--sync", window)
        xdo(display, "key", "f")
        # the camera glides to the framed view: a screenshot once it is at rest there
        seen = output.wait_for("view: converged", seen, "converged view after F")
        shot, seen = screenshot_at_rest(display, window, output, seen, "converged view after F")
        quit_viewer(display, viewer, output)
    assert viewer.returncode == 0, output.text()
    cam = json.loads(Path(str(shot) + ".camera.json").read_text())
    home_dist = float(np.linalg.norm(np.subtract(home.eye, home.target)))
    dist = float(np.linalg.norm(np.subtract(cam["eye"], cam["target"])))
    # the same direction, about the suggested camera's distance and target (the donut's root box: 0.88 of the
    # full detail's diagonal, BENCHMARKS.md "The F key frames the scene")
    view = np.subtract(cam["target"], cam["eye"]) / dist
    home_view = np.subtract(home.target, home.eye) / home_dist
    assert float(view @ home_view) > 0.999
    assert 0.8 * home_dist < dist < 1.05 * home_dist, (dist, home_dist)
    assert np.linalg.norm(np.subtract(cam["target"], home.target)) < 0.05 * home_dist
    # the bounding sphere's framing (before issue 31) stood much farther back
    half = math.radians(home.fov_y) / 2.0
    half = min(half, math.atan(math.tan(half) * SIZE[0] / SIZE[1]))
    assert dist < 0.7 * root.sphere_radius / math.sin(half)


def test_window_t_and_arrows_turn_about_the_target(display, served, tmp_path):
    """The suggested camera's side (issues 31 and 32): `view --camera-azimuth 90` opens at the scene's camera turned
    90 degrees about up, T turns to the other side of the target (+180), the left arrow 45 degrees more, the right
    arrow back: each camera is the scene's turned by camera.turn_about_up (same target, distance and elevation),
    and R returns to the turned home."""
    import urllib.request

    from splatstream.camera import turn_about_up
    from splatstream.format.manifest import parse_manifest

    with urllib.request.urlopen(served + "/manifest.msgpack", timeout=10) as resp:
        home = parse_manifest(resp.read()).camera
    cams = []
    with open_viewer(display, served, tmp_path, "--gpu-mem-mb", "64", "--camera-azimuth", "90") as (viewer, output,
                                                                                                   window):
        seen = output.wait_for("view: converged", -1, "converged view of the scene")
        for keys in ([], ["t"], ["Left"], ["Right", "Right"], ["r"]):
            xdo(display, "windowfocus", "--sync", window)
            if keys:
                xdo(display, "key", *keys)
            shot, seen = screenshot_at_rest(display, window, output, seen, f"converged view after {keys}")
            cams.append(json.loads(Path(str(shot) + ".camera.json").read_text()))
        quit_viewer(display, viewer, output)
    assert viewer.returncode == 0, output.text()
    dist = float(np.linalg.norm(np.subtract(home.eye, home.target)))
    for cam, degrees in zip(cams, (90.0, 270.0, 315.0, 225.0, 90.0), strict=True):
        want = turn_about_up(home.eye, home.target, home.up, degrees)
        assert np.linalg.norm(np.subtract(cam["eye"], want)) < 1e-4 * dist, (degrees, cam["eye"], want)
        assert np.linalg.norm(np.subtract(cam["target"], home.target)) < 1e-4 * dist
