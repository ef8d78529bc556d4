"""The README's picture of the viewer: `splatstream view SOURCE` in a window on a private Xvfb display, left to
stream until it converges, then the window grabbed as the X server shows it (overlay included).

    .venv/bin/python bench/viewer_screenshot.py ../shared/data/real/winter_fountain.splat \
        --size 1280x720 --out docs/images/viewer_winter_fountain.png

Needs Xvfb and xdotool (`.ci/run` installs both) and python-xlib (the `test` extra). Extra arguments after `--`
go to `splatstream view` (e.g. `-- --eye 1,2,3 --target 0,0,0`).
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np


def start_xvfb(width: int, height: int) -> tuple[subprocess.Popen, str]:
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", f"{width + 64}x{height + 64}x24",
                             "-nolisten", "tcp"], pass_fds=(w,), stderr=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL)
    os.close(w)
    number = b""
    while not number.endswith(b"\n"):
        chunk = os.read(r, 16)
        if not chunk:
            raise SystemExit("viewer_screenshot: Xvfb did not start")
        number += chunk
    os.close(r)
    return proc, f":{number.decode().strip()}"


def find_window(display: str, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        out = subprocess.run(["xdotool", "search", "--onlyvisible", "--name", "splatstream"],
                             env={**os.environ, "DISPLAY": display}, capture_output=True, text=True).stdout.split()
        if out:
            return out[0]
        time.sleep(0.2)
    raise SystemExit("viewer_screenshot: the viewer's window did not appear")


def grab(display: str, window: str) -> np.ndarray:
    from Xlib import X
    from Xlib import display as xdisplay

    d = xdisplay.Display(display)
    try:
        win = d.create_resource_object("window", int(window))
        geo = win.get_geometry()
        pos = win.translate_coords(d.screen().root, 0, 0)
        raw = d.screen().root.get_image(-pos.x, -pos.y, geo.width, geo.height, X.ZPixmap, 0xFFFFFFFF).data
        return np.frombuffer(raw, np.uint8).reshape(geo.height, geo.width, 4)[..., [2, 1, 0]].copy()
    finally:
        d.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--out", required=True)
    ap.add_argument("--settle-s", type=float, default=240.0, help="longest wait for the stream to converge")
    ap.add_argument("view_args", nargs="*", help="more `splatstream view` options (after --)")
    args = ap.parse_args()
    from PIL import Image

    w, h = (int(v) for v in args.size.split("x"))
    xvfb, display = start_xvfb(w, h)
    env = {**os.environ, "DISPLAY": display}
    with tempfile.TemporaryDirectory() as tmp:
        # --exit-when-converged with --screenshot writes the overlay-free picture when the stream converges; the
        # window is grabbed while that file appears (the overlay is drawn on every frame shown).
        shot = os.path.join(tmp, "clean.png")
        viewer = subprocess.Popen([sys.executable, "-m", "cli", "view", args.source, "--size",
                                   args.size, "--no-cache", "--screenshot", shot, *args.view_args], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            window = find_window(display, 120)
            deadline = time.monotonic() + args.settle_s
            while time.monotonic() < deadline and not os.path.exists(shot) and viewer.poll() is None:
                time.sleep(0.5)
            time.sleep(1.0)
            pixels = grab(display, window)
        finally:
            viewer.send_signal(signal.SIGTERM)
            try:
                out, err = viewer.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                viewer.kill()
                out, err = viewer.communicate()
            xvfb.send_signal(signal.SIGTERM)
            xvfb.wait(10)
        if not os.path.exists(shot):
            raise SystemExit(f"viewer_screenshot: the stream did not converge in {args.settle_s:.0f} s\n{err[-2000:]}")
    tmp_out = args.out + ".tmp.png"
    Image.fromarray(pixels).save(tmp_out)
    os.replace(tmp_out, args.out)
    print(f"wrote {args.out} ({pixels.shape[1]}x{pixels.shape[0]})")


if __name__ == "__main__":
    main()
