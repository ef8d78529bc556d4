"""`splatstream view SOURCE --headless`: stream a scene without a window, for scripts, tests and benchmarks.

The same StreamingSession as the window, on a headless EGL context, driven by a fixed camera or a camera path on
the wall clock. It stops when the view has converged (and the path has ended), or at the timeout; on the way it
writes PNG frames, a final screenshot and the metrics JSON (client_gl/streaming.py: FrameRecord, StreamMetrics).
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, replace

import numpy as np
from PIL import Image

from splatstream.atomic import atomic_file
from splatstream.camera import Camera, look_at_near_far, turn_about_up
from splatstream.camera_path import CameraPath
from splatstream.progress import ProgressPrinter, bar_drawn, end_open_line
from splatstream.sh import warn_sh_degree_above

from .gpu.gl import wait_for_gpu
from .streaming import StreamingSession, ViewOptions, freeze_long_lived

EXIT_OK = 0
EXIT_NOT_CONVERGED = 1


@dataclass
class HeadlessRun:
    source: str
    options: ViewOptions
    size: tuple[int, int]
    camera: Camera | None = None  # None: the scene's suggested camera (at `size`)
    path: CameraPath | None = None
    until_converged: bool = True
    timeout_s: float = 120.0
    record: str | None = None
    screenshot: str | None = None
    frames_dir: str | None = None
    frame_every: int = 10
    sh_degree: int | None = None
    quiet: bool = False
    measure_frames: int = 0  # once converged, time this many frames (glFinish each) into the report
    camera_azimuth_deg: float = 0.0  # the scene's camera turned about up (view --camera-azimuth)
    up: tuple[float, float, float] | None = None  # view --up (None: the scene's)
    fov_y: float | None = None  # view --fov-y (None: the camera's)


def start_camera(manifest, fixed: Camera | None, size: tuple[int, int], azimuth_deg: float = 0.0,
                 up: tuple[float, float, float] | None = None, fov_y: float | None = None) -> Camera:
    """The camera a view starts from: `fixed` (view --eye/--target; its up the scene's unless --up was given), else
    the manifest's camera at `size`, turned by `azimuth_deg` about its up (camera.turn_about_up), with --up and
    --fov-y where given. --eye/--target took +z as up where --up was not given (a 3DGS capture, y down, drew rolled)
    and --up or --fov-y without them were ignored (newuser61)."""
    c = manifest.camera
    if fixed is not None:
        return fixed if up is not None else replace(fixed, up=tuple(c.up))
    eye = turn_about_up(c.eye, c.target, c.up, azimuth_deg) if azimuth_deg else c.eye
    return Camera(eye, c.target, up or c.up, fov_y or c.fov_y, size[0], size[1], *look_at_near_far(eye, c.target))


def write_png(path: str, image) -> None:
    rgb8 = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_file(path) as f:
        Image.fromarray(rgb8, "RGB").save(f, format="PNG")


# Failed attempts in a row at one payload before the view says so (one failure is a blip the retry hides).
RETRIES_BEFORE_A_WARNING = 2


def new_version_line(session: StreamingSession) -> str:
    """Said when a session has continued with a new version of its scene (re-encoded on the server while streamed:
    http.md 10). The view rebuilt its pool and fetched again with nothing said: the picture went coarse, or
    changed, for no reason a user could read."""
    m = session.manifest
    return (f"view: {session.source.location}: the scene was re-encoded on the server; continuing with its new version "
            f"({m.splats:,} splats, preset {m.preset})")


def _status_line(rec, downloaded: int) -> str:
    """The progress line of one frame record (FrameRecord)."""
    return (f"view: {rec.t:6.2f}s  {downloaded / 1e6:8.2f} MB  {rec.drawn_splats:>10,} drawn  "
            f"{rec.resident_tiles:>4} tile{'' if rec.resident_tiles == 1 else 's'}  "
            f"{rec.in_flight:>3} in flight  "
            f"{'converged' if rec.converged else 'streaming'}")


def _measure_frames(session: StreamingSession, ctx, cam: Camera, sh_degree: int | None,
                    frames: int) -> tuple[list[float], float | None]:
    """`frames` frames timed one by one (GPU work included: glFinish after each), then as many back to back, as a
    running viewer draws them (the GPU's work of one frame overlaps the CPU's of the next): (ms per frame, mean ms
    back to back, None when no frame was asked for)."""
    measured = []
    for _ in range(frames):
        t = time.perf_counter()
        session.frame(cam, sh_degree=sh_degree)
        ctx.finish()
        measured.append((time.perf_counter() - t) * 1e3)
    if not measured:
        return measured, None
    t = time.perf_counter()
    for _ in range(frames):
        session.frame(cam, sh_degree=sh_degree)
    ctx.finish()
    return measured, (time.perf_counter() - t) * 1e3 / frames


def run_headless(run: HeadlessRun, ctx) -> tuple[int, dict]:
    """Stream until done; (exit code, metrics JSON)."""
    def say(msg: str) -> None:
        if not run.quiet:
            end_open_line()  # below a terminal's status line, not glued onto it
            print(msg, file=sys.stderr, flush=True)

    tty = sys.stderr.isatty() and not run.quiet

    # Reading and encoding a file or a foreign tree before the first frame (playbot's streamed SOG: 10-20 s) shows
    # its stages as `encode` does: a line per stage and 25 % step with the time taken, a bar on a terminal.
    encode_progress = ProgressPrinter("view", enabled=not run.quiet)

    # The timeout counts from here: the manifest's request (however slowly it arrives) is inside it.
    # A request that takes half the timeout (a server dripping bytes) fails and is named before the timeout ends.
    options = replace(run.options, manifest_timeout_s=min(run.options.manifest_timeout_s, run.timeout_s),
                      request_deadline_s=min(run.options.request_deadline_s, max(5.0, run.timeout_s / 2)))
    # The output size is known now: the first frame's framebuffer is made and cleared while the manifest is fetched
    # (RenderOptions.early_target), not inside the first frame.
    session = StreamingSession.open(run.source, ctx, options, progress=encode_progress, target_size=run.size)
    freeze_long_lived()
    warn_sh_degree_above(run.sh_degree, session.manifest.sh_degree, run.source)
    try:
        w, h = run.size
        fixed = start_camera(session.manifest, run.camera, run.size, run.camera_azimuth_deg, run.up, run.fov_y)
        start = time.perf_counter()
        frame = 0
        last_line = 0.0
        warned = False
        versions = session.manifest_changes
        code = EXIT_OK
        while True:
            now = time.perf_counter() - start
            cam = run.path.camera(now, w, h) if run.path is not None else fixed
            rec = session.frame(cam, sh_degree=run.sh_degree)
            wait_for_gpu()  # as a display's swap would: the decoders run meanwhile, not in the next frame's work
            frame += 1
            if run.frames_dir and frame % max(1, run.frame_every) == 0:
                write_png(os.path.join(run.frames_dir, f"frame_{frame:06d}.png"), session.read_image())
            path_done = run.path is None or now >= run.path.end
            done = path_done and (session.converged or not run.until_converged)
            if time.perf_counter() - last_line > 0.25 or done:
                last_line = time.perf_counter()
                line = _status_line(rec, session.fetcher.stats().bytes_downloaded)
                if tty:
                    sys.stderr.write("\r" + line + ("\n" if done else ""))
                    sys.stderr.flush()
                    bar_drawn(sys.stderr, ended=done)  # a failure's line then starts a line of its own
                elif done or frame % 20 == 1:
                    say(line)
            if session.manifest_changes != versions:
                versions = session.manifest_changes
                if tty:
                    sys.stderr.write("\n")
                    bar_drawn(sys.stderr, ended=True)
                say(new_version_line(session))
            failing = None if warned or done else session.fetcher.failing()
            if failing and failing[0][2] >= RETRIES_BEFORE_A_WARNING:
                # A payload the server keeps refusing (a scene missing a file: 404) was named only at --timeout,
                # after two minutes of 'streaming' lines: said once, as soon as it has failed twice in a row.
                warned = True
                if tty:
                    sys.stderr.write("\n")
                say(f"view: {failing[0][1]}; retrying until --timeout {run.timeout_s:g} s")
            if done:
                if session.engine.failed:  # converged without payloads that do not decode: not the scene's picture
                    say(f"view: {session.problem()}")
                    code = EXIT_NOT_CONVERGED
                break
            if time.perf_counter() - session.metrics.start > run.timeout_s:
                problem = session.problem()
                say(f"view: not converged after {run.timeout_s:g} s: {problem}" if problem else
                    f"view: not converged after {run.timeout_s:g} s (timeout)")
                code = EXIT_NOT_CONVERGED
                break
            if not rec.uploaded_bytes:
                session.wait(0.005)  # nothing arrived: wait for a decode instead of spinning
        measured, back_to_back = _measure_frames(session, ctx, cam, run.sh_degree,
                                                 run.measure_frames if code == EXIT_OK else 0)
        if run.screenshot:
            write_png(run.screenshot, session.read_image())
            say(f"view: wrote {run.screenshot}")
        report = session.metrics.to_json(session.fetcher.stats())
        if measured:
            report["measured_frames_ms"] = measured
            report["measured_frame_ms_median"] = sorted(measured)[len(measured) // 2]
            report["measured_back_to_back_ms"] = back_to_back
        report.update({"source": run.source, "frames_rendered": frame, "size": [w, h],
                       "camera_path": run.path is not None, "gl_renderer": ctx.info.get("GL_RENDERER", "?"),
                       "sort": session.renderer.sort_mode, "draw": session.renderer.draw_path})
        if run.record:
            with atomic_file(run.record) as f:
                f.write(json.dumps(report, indent=1).encode())
        return code, report
    finally:
        session.close()
