"""Shader programs compiled ahead on a thread of their own, so that the frame loop's compile of each is a driver
shader-cache hit (RenderOptions.warm_compile; issue 38, BENCHMARKS.md "Deferred compiles warmed off the frame loop").

The renderer compiles the GPU path's programs after its first frame (CPU-first frames, deferred compute draw
programs), one or a few a frame. moderngl keeps the interpreter lock through a compile, so on a cold driver each of
those frames stalls for the compile (55-258 ms each on the GPU machine). Here a daemon thread makes an EGL context
of its own on the display of the caller's (current) EGL context (on EGL's default display where the caller's context
is another API's, a GLFW window's GLX one), not sharing its objects, and compiles and links the
same GLSL sources through raw GL calls made with ctypes.CFUNCTYPE, which release the interpreter lock: the frame loop
runs beside it. The driver keeps what it compiled in its shader cache (Mesa: its disk cache; NVIDIA: its in-process
and disk caches), and the renderer compiles a program through moderngl only once this thread has linked it, so its
own compile finds it there. Nothing compiled here is used: the programs are deleted, the thread's context destroyed.

Nothing here is needed for correctness: without libEGL or a current GL context, or when anything fails, `failed` is
set and the renderer compiles as without it.
"""
from __future__ import annotations

import ctypes
import threading
import time
from collections.abc import Iterable
from functools import lru_cache

from .gl import gl_function_address

GL_COMPUTE_SHADER = 0x91B9
GL_VERTEX_SHADER = 0x8B31
GL_FRAGMENT_SHADER = 0x8B30
GL_COMPILE_STATUS = 0x8B81
GL_LINK_STATUS = 0x8B82

EGL_NONE = 0x3038
EGL_SURFACE_TYPE = 0x3033
EGL_PBUFFER_BIT = 0x0001
EGL_RENDERABLE_TYPE = 0x3040
EGL_OPENGL_BIT = 0x0008
EGL_OPENGL_API = 0x30A2
EGL_CONTEXT_MAJOR_VERSION = 0x3098
EGL_CONTEXT_MINOR_VERSION = 0x30FB
EGL_CONTEXT_OPENGL_PROFILE_MASK = 0x30FD
EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT = 0x0001

# A program's stages: ((GL shader type, source), ...), compute or vertex + fragment.
Stages = tuple[tuple[int, str], ...]

_u, _i, _p = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
# CFUNCTYPE: the interpreter lock is released through each call (the point of this thread).
_GL_SIGNATURES = {
    "glCreateShader": (_u, (_u,)),
    "glShaderSource": (None, (_u, _i, ctypes.POINTER(ctypes.c_char_p), ctypes.POINTER(_i))),
    "glCompileShader": (None, (_u,)),
    "glGetShaderiv": (None, (_u, _u, ctypes.POINTER(_i))),
    "glCreateProgram": (_u, ()),
    "glAttachShader": (None, (_u, _u)),
    "glLinkProgram": (None, (_u,)),
    "glGetProgramiv": (None, (_u, _u, ctypes.POINTER(_i))),
    "glDeleteShader": (None, (_u,)),
    "glDeleteProgram": (None, (_u,)),
    "glGetIntegerv": (None, (_u, _p)),
}
GL_MAJOR_VERSION = 0x821B
GL_MINOR_VERSION = 0x821C


@lru_cache(maxsize=1)
def _egl():
    """libEGL with the prototypes used here, or None (the GL functions come from gl.py's loaders)."""
    for name in ("libEGL.so.1", "libEGL.so"):
        try:
            egl = ctypes.CDLL(name)
        except OSError:
            continue
        for fn, res, args in (
                ("eglGetCurrentDisplay", _p, ()), ("eglGetCurrentContext", _p, ()),
                ("eglChooseConfig", _u, (_p, ctypes.POINTER(_i), ctypes.POINTER(_p), _i, ctypes.POINTER(_i))),
                ("eglBindAPI", _u, (_u,)), ("eglCreateContext", _p, (_p, _p, _p, ctypes.POINTER(_i))),
                ("eglMakeCurrent", _u, (_p, _p, _p, _p)), ("eglDestroyContext", _u, (_p, _p)),
                ("eglReleaseThread", _u, ()), ("eglGetError", _i, ()), ("eglGetDisplay", _p, (_p,)),
                ("eglInitialize", _u, (_p, _p, _p))):
            f = getattr(egl, fn)
            f.restype, f.argtypes = res, args
        return egl
    return None


@lru_cache(maxsize=1)
def _gl_functions():
    # gl.py's loaders (libEGL, libGL), resolved once and shared with it.
    return {name: ctypes.CFUNCTYPE(res, *args)(gl_function_address(name))
            for name, (res, args) in _GL_SIGNATURES.items()}


def _attribs(*values: int):
    return (_i * (len(values) + 1))(*values, EGL_NONE)


class ShaderWarmer:
    """Compiles and links `programs` (Stages, in order) on a thread with an EGL context of its own. Made on the thread
    whose GL context is current (the renderer's); `done(stages)` says whether that program was linked there (or
    failed to: the frame loop then compiles it and raises moderngl's error), `failed` whether the thread gave up."""

    def __init__(self, programs: Iterable[Stages]):
        self.programs: list[Stages] = list(dict.fromkeys(programs))
        self._done: set[Stages] = set()
        self.seconds: dict[Stages, float] = {}  # each program's compile + link on the thread (wall clock)
        self.failed: str | None = None
        self._lock = threading.Lock()
        self._stop = False
        self.thread: threading.Thread | None = None
        egl = _egl()
        if egl is None:
            self.failed = "no libEGL"
            return
        # The context's version as the renderer's has it (the driver's cache keys may include it).
        major, minor = ctypes.c_int(0), ctypes.c_int(0)
        try:
            gl = _gl_functions()
            gl["glGetIntegerv"](GL_MAJOR_VERSION, ctypes.byref(major))
            gl["glGetIntegerv"](GL_MINOR_VERSION, ctypes.byref(minor))
        except Exception as exc:  # noqa: BLE001 - an entry point missing: the frame loop compiles as before
            self.failed = f"{type(exc).__name__}: {exc}"
            return
        if major.value < 4:  # no GL context current here (glvnd's calls without one do nothing)
            self.failed = "no current GL context"
            return
        # The caller's EGL display, or where its context is another API's (a GLFW window's GLX context) EGL's
        # default display, initialised on the thread: the driver and its cache are the same (a miss shows in the
        # renderer, which then stops waiting).
        display = egl.eglGetCurrentDisplay() if egl.eglGetCurrentContext() else None
        self.thread = threading.Thread(target=self._run, args=(egl, display, major.value, minor.value, gl),
                                       name="splatstream-shader-warmer", daemon=True)
        self.thread.start()

    def done(self, stages: Stages) -> bool:
        with self._lock:
            return stages in self._done

    @property
    def finished(self) -> bool:
        """The thread is over (all compiled, stopped or failed)."""
        return self.thread is None or not self.thread.is_alive()

    def stop(self, wait: bool = True) -> None:
        """No more programs after the one being compiled (the renderer is released); wait: join the thread."""
        self._stop = True
        if wait and self.thread is not None:
            self.thread.join()

    def _run(self, egl, display, major: int, minor: int, gl) -> None:
        context = None
        try:
            if display is None:
                display = egl.eglGetDisplay(None)
                if not display or not egl.eglInitialize(display, None, None):
                    display = None
                    raise RuntimeError(f"no current EGL context, and EGL's default display failed "
                                       f"(0x{egl.eglGetError():x})")
            config, count = _p(), _i(0)
            if not egl.eglChooseConfig(display, _attribs(EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_RENDERABLE_TYPE,
                                                         EGL_OPENGL_BIT), ctypes.byref(config), 1,
                                       ctypes.byref(count)) or count.value < 1:
                raise RuntimeError(f"eglChooseConfig failed (0x{egl.eglGetError():x})")
            if not egl.eglBindAPI(EGL_OPENGL_API):
                raise RuntimeError(f"eglBindAPI failed (0x{egl.eglGetError():x})")
            context = egl.eglCreateContext(display, config, None, _attribs(
                EGL_CONTEXT_MAJOR_VERSION, major, EGL_CONTEXT_MINOR_VERSION, minor,
                EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT))
            if not context:
                raise RuntimeError(f"eglCreateContext failed (0x{egl.eglGetError():x})")
            if not egl.eglMakeCurrent(display, None, None, context):
                raise RuntimeError(f"eglMakeCurrent failed (0x{egl.eglGetError():x})")
            for stages in self.programs:
                if self._stop:
                    break
                t0 = time.perf_counter()
                _compile_and_link(gl, stages)
                with self._lock:
                    self.seconds[stages] = time.perf_counter() - t0
                    self._done.add(stages)
        except Exception as exc:  # noqa: BLE001 - an optimisation only: the frame loop compiles as before
            self.failed = f"{type(exc).__name__}: {exc}"
        finally:
            if context and display:
                egl.eglMakeCurrent(display, None, None, None)
                egl.eglDestroyContext(display, context)
            if egl is not None:
                egl.eglReleaseThread()


def _compile_and_link(gl, stages: Stages) -> None:
    """Compile and link one program in the current context and delete it (its status is not checked: a program that
    does not compile fails again in the frame loop, with moderngl's message)."""
    status = _i(0)
    shaders = []
    program = gl["glCreateProgram"]()
    try:
        for kind, source in stages:
            shader = gl["glCreateShader"](kind)
            shaders.append(shader)
            text = ctypes.c_char_p(source.encode())
            gl["glShaderSource"](shader, 1, ctypes.byref(text), None)
            gl["glCompileShader"](shader)
            gl["glGetShaderiv"](shader, GL_COMPILE_STATUS, ctypes.byref(status))
            gl["glAttachShader"](program, shader)
        gl["glLinkProgram"](program)
        gl["glGetProgramiv"](program, GL_LINK_STATUS, ctypes.byref(status))  # waits for the link
    finally:
        for shader in shaders:
            gl["glDeleteShader"](shader)
        gl["glDeleteProgram"](program)
