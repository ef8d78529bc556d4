"""`splatstream view SOURCE`: the interactive viewer. A window (moderngl-window, GLFW backend), the same
StreamingSession as `view --headless`, orbit and fly cameras (camera_control.py) and a Dear ImGui overlay.

The window opens at once; the source is opened and the manifest fetched on a worker thread (a splat file is
encoded there), so the window keeps drawing (a progress line) until the scene can stream. Splats are drawn into
the renderer's own framebuffer at the window's framebuffer size (HiDPI: physical pixels), copied to the window,
and the overlay is drawn over the copy only: a screenshot (P) is the renderer's framebuffer, full resolution,
without the overlay. The session and its frames live on a render thread with a GL context of its own
(render_thread.py): the window shows frame N while frame N+1 is drawn.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from splatstream.atomic import atomic_file
from splatstream.camera import Camera
from splatstream.camera_path import CameraPath
from splatstream.errors import SplatstreamError, UsageError
from splatstream.progress import mib
from splatstream.sh import warn_sh_degree_above

from .camera_control import TURN_STEP_DEG, CameraController, state_from_camera
from .gpu.gl import fence, gpu_wait
from .render_thread import WAIT_S, Frame, RenderThread
from .streaming import PreparedSource, StreamingSession, ViewOptions, freeze_long_lived
from .view_headless import RETRIES_BEFORE_A_WARNING, new_version_line, start_camera, write_png

EXIT_OK = 0
EXIT_NOT_CONVERGED = 1
LEVEL_COLOURS = [(1.0, 0.35, 0.3), (1.0, 0.75, 0.2), (0.5, 0.9, 0.3), (0.3, 0.8, 1.0), (0.6, 0.5, 1.0),
                 (1.0, 0.5, 0.9), (0.9, 0.9, 0.9)]
CONTROLS = [
    ("left drag", "orbit (fly mode: look around)"),
    ("right / middle drag", "pan"),
    ("wheel", "zoom toward the cursor"),
    ("W A S D", "move forward / left / back / right"),
    ("Q / E", "move down / up"),
    ("shift", "move faster"),
    ("C", "switch orbit / fly camera"),
    ("R", "reset to the scene's camera"),
    ("F", "frame the scene (stray splats left out)"),
    ("T", "turn to the other side of the target"),
    ("left / right arrow", f"turn {TURN_STEP_DEG:g} degrees about the target"),
    ("B", "show tile bounds, coloured by LOD level"),
    ("space", "pause / resume streaming"),
    ("P", "save a screenshot (PNG, full resolution, no overlay)"),
    ("O", "show / hide the overlay"),
    ("H or ?", "show / hide these controls"),
    ("Esc", "quit"),
]


def gpu_line(resident_bytes: int, budget_bytes: int) -> str:
    """The overlay's GPU memory line. The budget as given, as the headless summary writes it: `--gpu-mem-mb 0.5`
    showed 'GPU 0.5 MiB resident of 0 MiB budget', read as over budget."""
    return f"GPU     {resident_bytes / 2**20:.1f} MiB resident of {mib(budget_bytes)} MiB budget"


def draw_path_line(renderer) -> str:
    """The overlay's draw path ("CPU sort, raster draw"): the renderer's sort_mode and draw_path, the two words
    `--record` writes as `sort` and `draw` (a window's record said "fetch" where this line said "raster")."""
    return f"{renderer.sort_mode.upper()} sort, {renderer.draw_path} draw"


_BLIT_VS = """#version 410
out vec2 uv;
void main() {
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    uv = p;
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""
_BLIT_FS = """#version 410
uniform sampler2D u_image;
in vec2 uv;
out vec4 colour;
void main() { colour = vec4(clamp(texture(u_image, uv).rgb, 0.0, 1.0), 1.0); }
"""
_LINES_VS = """#version 410
uniform mat4 u_mvp;
in vec3 in_pos;
in vec3 in_colour;
out vec3 colour;
void main() { colour = in_colour; gl_Position = u_mvp * vec4(in_pos, 1.0); }
"""
_LINES_FS = """#version 410
in vec3 colour;
out vec4 frag;
void main() { frag = vec4(colour, 1.0); }
"""
_BOX_EDGES = [(0, 1), (1, 3), (3, 2), (2, 0), (4, 5), (5, 7), (7, 6), (6, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


@dataclass
class WindowRun:
    source: str
    options: ViewOptions
    size: tuple[int, int]
    camera: Camera | None = None
    path: CameraPath | None = None
    screenshot: str | None = None
    exit_when_converged: bool = False
    vsync: bool = True
    timeout_s: float = 120.0
    quiet: bool = False
    sh_degree: int | None = None
    record: str | None = None  # metrics JSON at exit (as view --headless writes it)
    overlay: bool = True  # the overlay shown on open (O toggles it)
    measure_frames: int = 0  # with exit_when_converged: time this many more frames (swap and glFinish) first
    camera_azimuth_deg: float = 0.0  # the scene's camera turned about up (view --camera-azimuth); R returns there
    up: tuple[float, float, float] | None = None  # view --up (None: the scene's)
    fov_y: float | None = None  # view --fov-y (None: the camera's)


def open_window(size: tuple[int, int], vsync: bool, title: str):
    """A GLFW window with an OpenGL >= 4.1 core context, or a UsageError saying what is missing."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and sys.platform.startswith("linux"):
        raise UsageError("cannot open a window: no display (DISPLAY is not set); use --headless, or run under a "
                         "virtual display (xvfb-run)")
    try:
        import moderngl_window as mglw
        from moderngl_window.conf import settings
    except ImportError as exc:
        raise UsageError(f"the viewer needs moderngl-window ({exc.name}): pip install 'splatstream[view]'") from None
    # The key is "class" (a Python keyword, hence no dict(...) here): moderngl-window falls back to pyglet without it.
    settings.WINDOW.update({"class": "moderngl_window.context.glfw.Window", "size": size, "title": title,
                            "vsync": vsync, "resizable": True, "aspect_ratio": None, "samples": 0})
    # Ask for 4.3 first: a driver may hand out exactly the version asked for, and below 4.3 there are no compute
    # shaders, so the frame would take the CPU sort, far too slow for a window (BENCHMARKS.md, "Figures behind
    # library defaults").
    # 4.1 is the floor (macOS).
    error: Exception | None = None
    for version in ((4, 3), (4, 1)):
        settings.WINDOW["gl_version"] = version
        try:
            return mglw.create_window_from_settings()
        except Exception as exc:  # GLFW and the GL loader raise plain exceptions with their own message
            error = exc
    raise UsageError(f"cannot open a window with OpenGL 4.1 ({error.__class__.__name__}: {error}); use "
                     "--headless") from None


class Viewer:
    def __init__(self, run: WindowRun):
        self.run = run
        self.wnd = open_window(run.size, run.vsync, f"splatstream - {os.path.basename(run.source.rstrip('/'))}")
        self.ctx = self.wnd.ctx
        from imgui_bundle import imgui
        from moderngl_window.integrations.imgui_bundle import ModernglWindowRenderer

        self.imgui = imgui
        imgui.create_context()
        imgui.get_io().set_ini_filename("")  # no imgui.ini in the user's directory
        self.gui = ModernglWindowRenderer(self.wnd)
        self.blit = self.ctx.program(vertex_shader=_BLIT_VS, fragment_shader=_BLIT_FS)
        self.blit_vao = self.ctx.vertex_array(self.blit, [])
        # How the renderer's image reaches the window: "draw" (a full-window triangle sampling it, any size) or
        # "copy" (glBlitFramebuffer, same size only); a bench hook for the window-against-headless measurement.
        self.present = os.environ.get("SPLATSTREAM_WINDOW_PRESENT", "draw")
        # Frames drawn on a render thread in a context of its own (render_thread.py says why); "0": in the window's
        # context on this thread, as before (also the fallback where no second context opens).
        self.threaded = os.environ.get("SPLATSTREAM_WINDOW_THREAD", "1") != "0"
        self.render: RenderThread | None = None
        self._shown: Frame | None = None  # threaded: the frame the window shows (drawn from an earlier camera)
        self._released: int | None = None  # threaded: fence after the window's last read of a frame
        self._pending = False  # threaded: a camera was handed to the render thread
        self._textures: dict = {}  # threaded: the render thread's targets as textures of this context
        self.lines = self.ctx.program(vertex_shader=_LINES_VS, fragment_shader=_LINES_FS)
        self.line_vbo = None
        self.line_vao = None
        self.session: StreamingSession | None = None
        self.prepared: PreparedSource | None = None
        self.load_error: str | None = None
        self.load_exception: BaseException | None = None
        self.load_stage = "opening"
        self.controller: CameraController | None = None
        self.keys_down: set[int] = set()
        self.show_help = False
        self.show_overlay = run.overlay
        self.show_bounds = False
        self.fps = 0.0
        self.frame_ms = 0.0
        self.rate = 0.0
        self._rate_window: list[tuple[float, int]] = []
        self.messages: list[str] = []
        self._versions = 0  # the session's manifest_changes said so far
        self.problem: str | None = None  # a payload failing RETRIES_BEFORE_A_WARNING times in a row, while it does
        self.screenshots: list[str] = []
        self.exit_code = EXIT_OK
        self._settled = False  # the view was at rest at the last frame (settled())
        self._say = (lambda msg: None) if run.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.start = time.perf_counter()
        self.ui_sse = run.options.max_sse
        self.ui_budget = run.options.gpu_mem_mb
        self.ui_degree = run.options.sh_degree
        self._wire_events()
        self._loader = threading.Thread(target=self._prepare, name="splat-open", daemon=True)
        self._loader.start()

    # --- loading (worker thread) --------------------------------------------------------------------------------
    def _prepare(self) -> None:
        def progress(stage: str, fraction: float) -> None:
            self.load_stage = f"{stage} {fraction * 100:.0f}%"

        try:
            self.load_stage = "fetching the manifest"
            self.prepared = PreparedSource.open(self.run.source, self.run.options, progress)
        except Exception as exc:  # shown in the window and raised again on exit (the CLI prints one line)
            self.load_error = str(exc) if isinstance(exc, SplatstreamError) else f"{exc.__class__.__name__}: {exc}"
            self.load_exception = exc

    def _start_session(self) -> None:
        """The session: on a render thread (it opens there; draw_frame picks it up when ready), or here."""
        m = self.prepared.manifest
        warn_sh_degree_above(self.run.sh_degree, m.sh_degree, self.run.source)  # (the overlay shows it too)
        if self.threaded and self.ctx.version_code >= 430:
            prepared, options = self.prepared, self.run.options
            try:
                self.render = RenderThread(self.wnd._window, self.wnd.gl_version,
                                           lambda ctx: StreamingSession(prepared, ctx, options))
                self.render.start()
            except RuntimeError as exc:
                self.render = None
                self.messages.append(f"drawing in the window's context ({exc})")
        if self.render is None:
            self.session = StreamingSession(self.prepared, self.ctx, self.run.options)
            freeze_long_lived()
        w, h = self.wnd.buffer_size
        r = self.run
        home = state_from_camera(start_camera(m, r.camera, (w, h), r.camera_azimuth_deg, r.up, r.fov_y))
        root = m.tile(m.root)
        self.controller = CameraController(home, np.array(root.sphere_center), float(root.sphere_radius))

    def _render_thread_ready(self) -> None:
        """Threaded: the session once the render thread has opened it (or its error, as a load error)."""
        r = self.render
        if self.session is not None or r is None or not r.ready.is_set():
            return
        if r.error is not None:
            exc = r.error
            self.load_error = str(exc) if isinstance(exc, SplatstreamError) else f"{exc.__class__.__name__}: {exc}"
            self.load_exception = exc
            return
        self.session = r.session
        freeze_long_lived()

    # --- events (the path every user input takes) ----------------------------------------------------------------
    def _wire_events(self) -> None:
        w = self.wnd
        w.key_event_func = self.on_key
        w.mouse_drag_event_func = self.on_drag
        w.mouse_scroll_event_func = self.on_scroll
        w.mouse_press_event_func = self.gui.mouse_press_event
        w.mouse_release_event_func = self.gui.mouse_release_event
        w.mouse_position_event_func = self.on_mouse_move
        w.resize_func = self.gui.resize
        w.unicode_char_entered_func = self.on_char

    def _gui_wants_mouse(self) -> bool:
        return bool(self.show_overlay and self.imgui.get_io().want_capture_mouse)

    def on_mouse_move(self, x, y, dx, dy) -> None:
        self.gui.mouse_position_event(x, y, dx, dy)
        self._cursor = (x, y)

    def on_drag(self, x, y, dx, dy) -> None:
        self.gui.mouse_drag_event(x, y, dx, dy)
        self._cursor = (x, y)
        if self.controller is None or self._gui_wants_mouse():
            return
        states = self.wnd.mouse_states
        ratio = self.wnd.pixel_ratio
        if states.left:
            if self.controller.mode == "fly":
                self.controller.look(dx, dy)
            else:
                self.controller.orbit(dx, dy)
        elif states.right or states.middle:
            self.controller.pan(dx * ratio, dy * ratio, self.wnd.buffer_size[1])

    def on_scroll(self, x_offset, y_offset) -> None:
        self.gui.mouse_scroll_event(x_offset, y_offset)
        if self.controller is None or self._gui_wants_mouse():
            return
        self.controller.zoom(y_offset, getattr(self, "_cursor", None), self.wnd.size)

    def on_char(self, char) -> None:
        self.gui.unicode_char_entered(char)
        if char == "?":
            self.show_help = not self.show_help

    def on_key(self, key, action, modifiers) -> None:
        self.gui.key_event(key, action, modifiers)
        keys = self.wnd.keys
        if action == keys.ACTION_PRESS:
            self.keys_down.add(key)
        elif action == keys.ACTION_RELEASE:
            self.keys_down.discard(key)
            return
        else:
            return
        if self.show_overlay and self.imgui.get_io().want_capture_keyboard:
            return
        if key == keys.ESCAPE:
            self.wnd.close()
        elif key == keys.H:
            self.show_help = not self.show_help
        elif key == keys.O:
            self.show_overlay = not self.show_overlay
        elif key == keys.B:
            self.show_bounds = not self.show_bounds
        elif key == keys.P:
            self.screenshot()
        elif self.controller is not None:
            if key == keys.C:
                self.controller.set_mode("fly" if self.controller.mode == "orbit" else "orbit")
            elif key == keys.R:
                self.controller.reset()
            elif key == keys.F:
                if self.controller.frame_box is None and self.session is not None:
                    self.controller.frame_box = self.session.engine.frame_box  # once the root's base has decoded
                w, h = self.wnd.buffer_size
                self.controller.frame_scene(w / max(1, h))
            elif key == keys.T:
                self.controller.turn(180.0)
            elif key in (keys.LEFT, keys.RIGHT):  # as a drag that way turns the scene (orbit: right is negative)
                self.controller.turn(TURN_STEP_DEG if key == keys.LEFT else -TURN_STEP_DEG)
            elif key == keys.SPACE and self.session is not None:
                self.session.paused = not self.session.paused

    def _held_motion(self, dt: float) -> None:
        k = self.wnd.keys
        down = self.keys_down
        forward = (k.W in down) - (k.S in down)
        right = (k.D in down) - (k.A in down)
        up = (k.E in down) - (k.Q in down)
        if forward or right or up:
            run = bool(self.wnd.modifiers.shift)
            self.controller.move(forward, right, up, dt, run)

    # --- frame ----------------------------------------------------------------------------------------------------
    def camera(self) -> Camera:
        w, h = self.wnd.buffer_size
        if self.run.path is not None:
            return self.run.path.camera(time.perf_counter() - self.path_start, w, h)
        return self.controller.camera(w, h)

    def draw_frame(self, dt: float) -> None:
        ctx = self.ctx
        if self.controller is None and self.prepared is not None:
            self._start_session()
            self.path_start = time.perf_counter()
        self._render_thread_ready()
        self.wnd.use()
        if self.session is None:  # otherwise the blit below covers every pixel: one pass over the window's pixels less
            ctx.clear(0.0, 0.0, 0.0, 1.0)
        if self.session is not None:
            self._held_motion(dt)
            self.controller.update(dt)
            cam = self.camera()
            if self.render is not None:
                self._threaded_frame(cam)
            else:
                self.last_camera = cam
                t0 = time.perf_counter()
                self.session.frame(cam, sh_degree=self.run.sh_degree)
                self.frame_ms = (time.perf_counter() - t0) * 1e3
                fbo = self.session.renderer.framebuffer(cam.width, cam.height)
                self._show_texture(fbo.color_attachments[0], cam, fbo)
        if self.show_overlay:
            self._overlay()

    def _threaded_frame(self, cam: Camera) -> None:
        """Show the frame the render thread drew from the camera before (waiting for it up to WAIT_S), and hand it
        this frame's camera: it draws while this thread shows and swaps."""
        if self.render.error is not None:  # the render thread stopped on an error: it ends the viewer, as here
            raise self.render.error
        frame = self.render.take(WAIT_S if self._shown is not None or self._pending else 0.0)
        self.render.submit(cam, self.run.sh_degree, self._released)
        self._released = None
        self._pending = True
        if frame is not None:
            gpu_wait(frame.sync)
            self._shown = frame
            self.last_camera = frame.camera
            self.frame_ms = frame.frame_ms
        if self._shown is None:
            self.ctx.clear(0.0, 0.0, 0.0, 1.0)
            return
        f = self._shown
        key = (f.texture, f.size, f.dtype)
        tex = self._textures.get(key)
        if tex is None:
            tex = self._textures[key] = self.ctx.external_texture(f.texture, f.size, 4, 0, f.dtype)
        self._show_texture(tex, f.camera)
        self._released = fence()

    def _show_texture(self, tex, cam: Camera, fbo=None) -> None:
        """A frame's image into the window (and the tile bounds over it). fbo: its framebuffer in this context,
        which the "copy" present mode blits from."""
        ctx = self.ctx
        self.wnd.use()
        ctx.viewport = (0, 0, *self.wnd.buffer_size)
        if fbo is not None and self.present == "copy" and tuple(self.wnd.buffer_size) == (cam.width, cam.height):
            ctx.copy_framebuffer(ctx.screen, fbo)
        else:
            ctx.disable(ctx.DEPTH_TEST | ctx.BLEND)
            tex.use(0)
            self.blit["u_image"].value = 0
            self.blit_vao.render(vertices=3)
        if self.show_bounds:
            self._draw_bounds(cam)

    def _draw_bounds(self, cam: Camera) -> None:
        s = self.session
        m = s.engine.manifest  # the tiles held (a paged scene's grow as pages arrive)
        a = m.arrays
        drawn = s.last.draw if s.last is not None else []
        verts = []
        for tile_id in drawn:
            i = m.index_of[tile_id]
            lo, hi = a.box_min[i], a.box_max[i]
            corners = [np.array([(lo, hi)[b & 1][0], (lo, hi)[(b >> 1) & 1][1], (lo, hi)[(b >> 2) & 1][2]])
                       for b in range(8)]
            colour = LEVEL_COLOURS[min(int(a.level[i]), len(LEVEL_COLOURS) - 1)]
            for p, q in _BOX_EDGES:
                verts += [*corners[p], *colour, *corners[q], *colour]
        if not verts:
            return
        data = np.asarray(verts, np.float32).tobytes()
        if self.line_vbo is None or self.line_vbo.size < len(data):
            if self.line_vbo is not None:
                self.line_vao.release()
                self.line_vbo.release()
            self.line_vbo = self.ctx.buffer(reserve=max(len(data), 1 << 16), dynamic=True)
            self.line_vao = self.ctx.vertex_array(self.lines, [(self.line_vbo, "3f 3f", "in_pos", "in_colour")])
        self.line_vbo.write(data)
        mvp = cam.projection_matrix() @ cam.view_matrix()
        self.lines["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32).tobytes())
        self.line_vao.render(self.ctx.LINES, vertices=len(data) // 24)

    def _overlay(self) -> None:
        imgui = self.imgui
        imgui.new_frame()
        imgui.set_next_window_pos((10, 10), imgui.Cond_.first_use_ever)
        imgui.begin("splatstream", None, imgui.WindowFlags_.always_auto_resize)
        if self.session is None:
            imgui.text(f"{self.run.source}")
            imgui.text(self.load_error or f"loading: {self.load_stage}")
        else:
            self._stats(imgui)
            self._controls(imgui)
        for line in self.messages[-3:]:
            imgui.text_wrapped(line)
        imgui.text("H: controls")
        imgui.end()
        if self.show_help:
            # Below the stats where the whole list fits; in a shorter window (960x600 cut off its last lines, Esc
            # among them) from the window's bottom up, over the stats if need be. Placed each time it is shown.
            height = (len(CONTROLS) + 2) * imgui.get_text_line_height_with_spacing() + 16
            if 330 + height <= imgui.get_io().display_size.y:
                imgui.set_next_window_pos((10, 330), imgui.Cond_.appearing)
            else:
                imgui.set_next_window_pos((10, imgui.get_io().display_size.y - 10), imgui.Cond_.appearing, (0, 1))
            imgui.begin("controls", None, imgui.WindowFlags_.always_auto_resize)
            for key, what in CONTROLS:
                imgui.text(f"{key:<20} {what}")
            imgui.end()
        imgui.render()
        self.gui.render(imgui.get_draw_data())

    def _stats(self, imgui) -> None:
        s = self.session
        u = s.last
        stats = s.fetcher.stats()
        now = time.perf_counter()
        self._rate_window.append((now, stats.bytes_downloaded))
        while len(self._rate_window) > 2 and now - self._rate_window[0][0] > 1.0:
            self._rate_window.pop(0)
        (t0, b0), (t1, b1) = self._rate_window[0], self._rate_window[-1]
        self.rate = (b1 - b0) / max(1e-6, t1 - t0)
        path = draw_path_line(s.renderer)
        imgui.text(f"{self.fps:6.1f} fps   frame {self.frame_ms:6.2f} ms (CPU)")
        imgui.text(f"splats  {u.drawn_splats if u else 0:,} drawn / {u.resident_splats if u else 0:,} resident")
        imgui.text(f"tiles   {u.resident_tiles if u else 0} resident / {u.in_flight if u else 0} in flight"
                   f"{'  (paused)' if s.paused else ''}{'  converged' if s.converged else ''}")
        if stats.manifest_source == "local":  # a scene directory or a splat file: read, not downloaded
            imgui.text(f"read    {stats.bytes_downloaded / 1e6:.1f} MB, {self.rate / 1e6:.1f} MB/s")
        else:
            imgui.text(f"network {stats.bytes_downloaded / 1e6:.1f} MB, {self.rate * 8 / 1e6:.1f} Mbit/s"
                       f"{'  OFFLINE' if stats.offline else ''}")
        imgui.text(gpu_line(s.pool.resident_bytes, s.budget))
        degree = min(s.options.sh_degree, s.manifest.sh_degree)
        imgui.text(f"SH      degree {degree} (scene {s.manifest.sh_degree})   {path}")
        imgui.text(f"camera  {self.controller.mode} (C switches)")
        if self.problem is not None:
            imgui.text_colored((1.0, 0.55, 0.4, 1.0), "retrying:")
            imgui.same_line()
            imgui.text_wrapped(self.problem)

    def _controls(self, imgui) -> None:
        s = self.session
        changed, self.ui_sse = imgui.slider_float("max SSE px", self.ui_sse, 0.0, 16.0, "%.2f")
        if changed:
            self._reconfigure(max_sse=self.ui_sse)
        _, self.ui_budget = imgui.input_float("GPU MiB", self.ui_budget, 64.0, 256.0, "%.4g")
        if imgui.is_item_deactivated_after_edit():
            if self.ui_budget > 1:
                self._reconfigure(gpu_mem_mb=float(self.ui_budget))
            else:  # was ignored while the field kept showing it, as if in force: say so and show the budget held
                self.messages.append(f"GPU MiB {self.ui_budget:.4g} not taken: 1 or more here "
                                     f"(--gpu-mem-mb takes less)")
                self.ui_budget = s.budget / 2**20
        self.ui_degree = min(self.ui_degree, s.manifest.sh_degree)  # the slider shows what the scene can have
        changed, self.ui_degree = imgui.slider_int("SH degree", self.ui_degree, 0, s.manifest.sh_degree)
        if changed:
            self.run = replace(self.run, sh_degree=self.ui_degree)
            self._reconfigure(sh_degree=self.ui_degree)
        _, self.show_bounds = imgui.checkbox("tile bounds (by level)", self.show_bounds)
        _, s.paused = imgui.checkbox("pause streaming", s.paused)

    def _reconfigure(self, **changes) -> None:
        """Session options changed from the overlay: on the thread that owns the session's GL objects."""
        def apply(s: StreamingSession) -> None:
            s.reconfigure(replace(s.options, **changes))
        if self.render is not None:
            self.render.call(apply)
        else:
            apply(self.session)

    # --- output ---------------------------------------------------------------------------------------------------
    def screenshot(self, path: str | None = None) -> str | None:
        """P: the renderer's framebuffer (full resolution, no overlay) as a PNG; prints the path, whether the view
        was at rest (settled(): "converged"; else "streaming" or "camera moving") and the camera."""
        if self.session is None:
            return None
        moving = self.controller is not None and (self.controller.update(0.0) or not self._camera_shown())
        state = "converged" if self.settled() else "camera moving" if moving else "streaming"
        path = path or self.run.screenshot or os.path.abspath(time.strftime("splatstream-%Y%m%d-%H%M%S.png"))
        if os.path.exists(path) and not self.run.screenshot:
            path = path[:-4] + f"-{len(self.screenshots)}.png"
        if self.render is not None:  # the image is the render thread's: read there, in its context
            image, cam = self.render.call(lambda s: (s.read_image(), s.drawn_camera)).result(timeout=60)
        else:
            image, cam = self.session.read_image(), self.last_camera
        write_png(path, image)
        with open(path + ".camera.json", "w") as f:
            json.dump(cam.to_dict(), f)
        def vec(v) -> str:
            return ",".join(f"{x:.6g}" for x in v)

        # --opt=value: a vector starting with a minus sign would read as an option
        message = (f"saved {path} ({cam.width}x{cam.height}; {state}; camera: --eye={vec(cam.eye)} "
                   f"--target={vec(cam.target)} --up={vec(cam.up)} --fov-y={cam.fov_y_deg:.6g})")
        print(message, flush=True)
        self.messages.append(f"saved {os.path.basename(path)}")
        self.screenshots.append(path)
        return path

    def loop(self) -> int:
        last = time.perf_counter()
        fps_frames, fps_start = 0, last
        while not self.wnd.is_closing:
            now = time.perf_counter()
            dt, last = now - last, now
            self.draw_frame(dt)
            self.wnd.swap_buffers()
            fps_frames += 1
            if now - fps_start >= 0.5:
                self.fps, fps_frames, fps_start = fps_frames / (now - fps_start), 0, now
            if self.load_error is not None and self.run.exit_when_converged:
                break
            self._watch_failures()
            settled = self.settled()
            if settled and not self._settled:
                # One line each time the view comes to rest: scripts and the window test wait for it, not a clock.
                self._say(f"view: converged ({self.session.last.resident_tiles} tiles resident; camera still)")
            self._settled = settled
            if (self.run.screenshot and not self.run.exit_when_converged and not self.screenshots
                    and self.session is not None and self.session.converged):
                self.screenshot(self.run.screenshot)  # a window that stays open: written when the view converges
            if self.run.exit_when_converged and self.session is not None:
                if settled:
                    if self.run.screenshot:
                        self.screenshot(self.run.screenshot)
                    self._measure()
                    break
                if now - self.start > self.run.timeout_s:
                    problem = self.session.problem()
                    print(f"view: not converged after {self.run.timeout_s:g} s: {problem}" if problem else
                          f"view: not converged after {self.run.timeout_s:g} s (timeout)", file=sys.stderr)
                    self.exit_code = EXIT_NOT_CONVERGED
                    break
            if self.session is None and self.load_error is None:
                time.sleep(0.005)
        return self.exit_code

    def _watch_failures(self) -> None:
        """A payload that keeps failing (the server stopped or gone, a file missing: 404) showed only as OFFLINE
        in the overlay, or not at all, and nothing was printed: the window looked stuck while streaming. As
        --headless does, it is said on stderr once it has failed RETRIES_BEFORE_A_WARNING times in a row (its URL
        and why), shown in the overlay while it lasts, and the recovery is said too."""
        if self.session is None:
            return
        if self.session.manifest_changes != self._versions:  # re-encoded on the server, continued with (http.md 10)
            self._versions = self.session.manifest_changes
            line = new_version_line(self.session)
            self._say(line)
            self.messages.append(line[len("view: "):])
        failing = self.session.fetcher.failing()
        if failing and failing[0][2] >= RETRIES_BEFORE_A_WARNING:
            if self.problem is None:
                self._say(f"view: {failing[0][1]}; retrying")
            more = len(failing) - 1
            self.problem = failing[0][1] + (f" ({more} more payloads failing)" if more else "")
        elif not failing and self.problem is not None:
            self.problem = None
            self._say("view: payloads arrive again; streaming")

    def settled(self) -> bool:
        """The view at rest: every tile it wants resident, nothing in flight (the last frame's `converged`), the
        camera still (no smoothing left) and the camera path, if any, at its end."""
        if self.session is None or not self.session.converged:
            return False
        if self.run.path is not None and time.perf_counter() - self.path_start < self.run.path.end:
            return False
        return not self.controller.update(0.0) and self._camera_shown() if self.controller else True

    def _camera_shown(self) -> bool:
        """The frame shown was drawn from the controller's camera (or a camera path drives the view). A key that
        moves the camera at once (T, the arrows) leaves it still, with the frame before on screen: 'converged'
        was said of that frame (the window test's screenshot after T held the camera before it)."""
        shown = getattr(self, "last_camera", None)
        if self.run.path is not None or self.controller is None:
            return True
        if shown is None:
            return False
        now = self.controller.now
        scale = max(1e-9, float(np.linalg.norm(now.target - now.eye)))
        return bool(np.abs(np.subtract(shown.eye, now.eye)).max() <= 1e-9 * scale
                    and np.abs(np.subtract(shown.target, now.target)).max() <= 1e-9 * scale)

    def _measure(self) -> None:
        """Time converged frames through the window path (draw, copy, overlay, swap), two ways: one at a time
        (glFinish after each; apart, the share before the swap: on a virtual display the swap is the X server's
        copy, not our work), and back to back as a running viewer draws them (vsync off, glFinish after the last:
        the frame time a user sees, where the GPU's work of one frame overlaps the CPU's of the next). Nothing is
        timed (and the record carries no timing) when `--measure-frames` is 0, its default."""
        if self.run.measure_frames <= 0:
            return
        times: list[float] = []
        drawn: list[float] = []
        for _ in range(self.run.measure_frames):
            t = time.perf_counter()
            self.draw_frame(0.0)
            self.ctx.finish()
            drawn.append((time.perf_counter() - t) * 1e3)
            self.wnd.swap_buffers()
            self.ctx.finish()
            times.append((time.perf_counter() - t) * 1e3)
        self.measured = times
        self.measured_draw = drawn
        n = self.run.measure_frames
        split: dict[str, list[float]] = {"draw_ms": [], "swap_ms": [], "render_cpu_ms": []}
        t = time.perf_counter()
        for _ in range(n):
            t0 = time.perf_counter()
            self.draw_frame(0.0)
            t1 = time.perf_counter()
            self.wnd.swap_buffers()
            split["draw_ms"].append((t1 - t0) * 1e3)  # threaded: mostly the wait for the render thread's frame
            split["swap_ms"].append((time.perf_counter() - t1) * 1e3)
            split["render_cpu_ms"].append(self.frame_ms)
        self.ctx.finish()
        self.measured_back_to_back = (time.perf_counter() - t) * 1e3 / n
        self.measured_back_to_back_split = {k: sorted(v)[len(v) // 2] for k, v in split.items()}

    def write_record(self) -> None:
        if not self.run.record or self.session is None:
            return
        report = self.session.metrics.to_json(self.session.fetcher.stats())
        report.update({"source": self.run.source, "window": True, "window_backend": self.wnd.name,
                       "size": list(self.wnd.buffer_size),
                       "gl_renderer": self.ctx.info.get("GL_RENDERER", "?"), "gl_version": self.ctx.version_code,
                       "sort": self.session.renderer.sort_mode, "draw": self.session.renderer.draw_path,
                       "overlay": self.show_overlay})
        if getattr(self, "measured", None):
            report["measured_frames_ms"] = self.measured
            report["measured_frame_ms_median"] = sorted(self.measured)[len(self.measured) // 2]
            report["measured_draw_ms_median"] = sorted(self.measured_draw)[len(self.measured_draw) // 2]
            report["measured_back_to_back_ms"] = self.measured_back_to_back
            report["measured_back_to_back_split_median"] = self.measured_back_to_back_split
            report["present"] = self.present
        with atomic_file(self.run.record) as f:
            f.write(json.dumps(report, indent=1).encode())

    def close(self) -> None:
        self.write_record()
        if self.render is not None:
            self.render.close()  # closes the session in its context
        elif self.session is not None:
            self.session.close()
        if self.session is None and self.prepared is not None:
            self.prepared.fetcher.close()  # no session took it over (none opened, or the render thread's failed)
        self.wnd.destroy()


def run_window(run: WindowRun) -> int:
    viewer = Viewer(run)
    try:
        code = viewer.loop()
    except KeyboardInterrupt:
        code = 130
    finally:
        viewer.close()
    if viewer.load_exception is not None and viewer.run.exit_when_converged:
        raise viewer.load_exception
    return code
