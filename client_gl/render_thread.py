"""The viewer's render thread: a GL context of its own that shares objects with the window's, the streaming session,
and finished frames handed to the window with a fence.

Why: a window's swap can take as long as a frame. On the GPU machine's virtual display (Xvfb with the NVIDIA GLX
library) it copies every frame to the X server on the CPU and waits for all the work queued in its context, so in
one context the frame and the swap add up. In two contexts on two threads, the window shows and swaps frame N while
this thread draws frame N+1, so they overlap (bench/probe_window_overlap.py; figures in BENCHMARKS.md, "Streaming
client").

The window's thread (main) calls submit(camera) once per frame, take() for the frame drawn from the camera before,
waits for it on the GPU (gpu.gl.gpu_wait: glWaitSync, the CPU does not wait), draws it, swaps, and hands a fence back
with the next submit so that this thread draws into that frame's target only after the window has read it. The
session lives on this thread: anything that changes it goes through call(fn), run here before the next frame.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

from splatstream.camera import Camera

from .gpu.gl import delete_fence, fence, gpu_wait

WAIT_S = 0.05  # longest wait for a camera or a frame before looking at stop requests and pending calls again


@dataclass
class Frame:
    texture: int  # GL name of the colour texture the frame was drawn into (shared with the window's context)
    size: tuple[int, int]
    dtype: str  # the texture's moderngl dtype ("f2", "f4", "f1")
    camera: Camera
    sync: int  # fence after the frame's commands
    frame_ms: float  # CPU time of session.frame


class RenderThread:
    """Draws the session's frames in a context of its own (see the module doc). Made on the window's thread."""

    def __init__(self, window_handle, gl_version: tuple[int, int], open_session: Callable):
        import glfw

        self._glfw = glfw
        glfw.window_hint(glfw.VISIBLE, glfw.FALSE)
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, gl_version[0])
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, gl_version[1])
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        self._hidden = glfw.create_window(16, 16, "splatstream render", None, window_handle)
        glfw.window_hint(glfw.VISIBLE, glfw.TRUE)
        if not self._hidden:
            raise RuntimeError("no second OpenGL context sharing the window's")
        self._open_session = open_session
        self._cond = threading.Condition()
        self._camera: tuple[Camera, int | None] | None = None  # the next frame's camera and SH degree
        self._released: int | None = None  # the window's fence: it has read the frame before the last one
        self._frames: list[Frame] = []  # drawn, not taken yet (at most one: the targets are two)
        self._calls: list[tuple[Callable, Future]] = []
        self._stop = False
        self.session = None
        self.error: BaseException | None = None
        self.ready = threading.Event()  # the session is open (or opening it failed: error)
        self._thread = threading.Thread(target=self._run, name="splat-render", daemon=True)

    def start(self) -> None:
        self._thread.start()

    # --- the window's thread ---------------------------------------------------------------------------------------
    def submit(self, camera: Camera, sh_degree: int | None, released: int | None) -> None:
        """The camera of the next frame; `released`: a fence after the window's last read of a frame's texture."""
        with self._cond:
            self._camera = (camera, sh_degree)
            if released is not None:
                delete_fence(self._released)  # superseded: the new one comes after it
                self._released = released
            self._cond.notify_all()

    def take(self, timeout_s: float = WAIT_S) -> Frame | None:
        """The oldest drawn frame not taken yet, waiting up to timeout_s for one."""
        with self._cond:
            if not self._frames:
                self._cond.wait_for(lambda: self._frames or self._stop or self.error is not None, timeout_s)
            if not self._frames:
                return None
            frame = self._frames.pop(0)
            self._cond.notify_all()
            return frame

    def call(self, fn: Callable) -> Future:
        """fn(session) on the render thread, before its next frame."""
        future: Future = Future()
        with self._cond:
            self._calls.append((fn, future))
            self._cond.notify_all()
        return future

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the thread (it closes the session in its context) and destroy the hidden window."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        if self._hidden:
            self._glfw.destroy_window(self._hidden)
            self._hidden = None

    # --- the render thread -----------------------------------------------------------------------------------------
    def _run(self) -> None:
        glfw = self._glfw
        glfw.make_context_current(self._hidden)
        try:
            import moderngl

            ctx = moderngl.create_context()
            self.session = self._open_session(ctx)
        except BaseException as exc:  # noqa: BLE001 (handed to the window's thread, which reports it)
            self.error = exc
            self.ready.set()
            with self._cond:
                self._cond.notify_all()
            glfw.make_context_current(None)
            return
        self.ready.set()
        try:
            self._loop()
        except BaseException as exc:  # noqa: BLE001
            self.error = exc
            with self._cond:
                self._cond.notify_all()
        finally:
            self._fail_calls()
            try:
                self.session.close()
            finally:
                glfw.make_context_current(None)

    def _loop(self) -> None:
        session = self.session
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stop or self._calls or (self._camera is not None
                                                                             and not self._frames), WAIT_S)
                if self._stop:
                    return
                calls, self._calls = self._calls, []
                job = self._camera if not self._frames else None
                released = None
                if job is not None:  # the window's release fence goes with the frame that needs it
                    self._camera = None
                    released, self._released = self._released, None
            for fn, future in calls:
                try:
                    future.set_result(fn(session))
                except Exception as exc:  # noqa: BLE001 (the caller's future carries it)
                    future.set_exception(exc)
            if job is None:
                continue
            camera, sh_degree = job
            gpu_wait(released)  # the window has read the target this frame is about to overwrite
            session.renderer.next_output_target()
            frame = session.frame(camera, sh_degree=sh_degree)
            fbo = session.renderer.framebuffer(camera.width, camera.height)
            texture = fbo.color_attachments[0]
            drawn = Frame(texture.glo, (camera.width, camera.height), texture.dtype, camera, fence(),
                          frame.frame_ms)
            with self._cond:
                self._frames.append(drawn)
                self._cond.notify_all()

    def _fail_calls(self) -> None:
        with self._cond:
            calls, self._calls = self._calls, []
        for _, future in calls:
            future.set_exception(RuntimeError("the render thread stopped"))
