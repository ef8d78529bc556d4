"""The few raw OpenGL calls moderngl does not offer: textures in the packed and block-compressed texel formats.

moderngl cannot create RGB10_A2 textures from packed words or upload BC blocks (`ctx.texture()` rejects raw
compressed data), so the plane atlases are plain GL texture names driven through ctypes. Function pointers come
from eglGetProcAddress (EGL 1.5 returns core functions too) or, failing that, from the process's libGL/libOpenGL.
Everything here acts on the context current on the calling thread (the one moderngl made current).
"""
from __future__ import annotations

import ctypes
import ctypes.util
from contextlib import contextmanager
from functools import lru_cache

import moderngl
import numpy as np

GL_TEXTURE_2D = 0x0DE1
GL_TEXTURE_2D_ARRAY = 0x8C1A
GL_TEXTURE0 = 0x84C0
GL_TEXTURE_MAG_FILTER = 0x2800
GL_TEXTURE_MIN_FILTER = 0x2801
GL_TEXTURE_BASE_LEVEL = 0x813C
GL_TEXTURE_MAX_LEVEL = 0x813D
GL_NEAREST = 0x2600
GL_UNPACK_ALIGNMENT = 0x0CF5
GL_UNPACK_ROW_LENGTH = 0x0CF2
GL_UNPACK_SKIP_ROWS = 0x0CF3
GL_UNPACK_SKIP_PIXELS = 0x0CF4
GL_PIXEL_UNPACK_BUFFER = 0x88EC
GL_COPY_WRITE_BUFFER = 0x8F37
GL_WRITE_ONLY = 0x88B9
GL_MAJOR_VERSION = 0x821B
GL_MINOR_VERSION = 0x821C
GL_MAP_READ_BIT = 0x0001
GL_DYNAMIC_STORAGE_BIT = 0x0100
GL_SYNC_GPU_COMMANDS_COMPLETE = 0x9117
GL_TIMEOUT_IGNORED = 0xFFFFFFFFFFFFFFFF
GL_NO_ERROR = 0

GL_RGBA = 0x1908
GL_RED_INTEGER = 0x8D94
GL_RG_INTEGER = 0x8228
GL_RGBA_INTEGER = 0x8D99
GL_FLOAT = 0x1406
GL_HALF_FLOAT = 0x140B
GL_UNSIGNED_BYTE = 0x1401
GL_UNSIGNED_SHORT = 0x1403
GL_UNSIGNED_INT = 0x1405
GL_UNSIGNED_INT_2_10_10_10_REV = 0x8368

GL_RGBA32F = 0x8814
GL_RGBA16F = 0x881A
GL_RGBA16 = 0x805B
GL_RGB10_A2 = 0x8059
GL_R32UI = 0x8236
GL_R16UI = 0x8234
GL_RG8UI = 0x8238
GL_RGBA8 = 0x8058
GL_RGBA32UI = 0x8D70
GL_COMPRESSED_RGBA_BPTC_UNORM = 0x8E8C
GL_COMPRESSED_RGB_S3TC_DXT1_EXT = 0x83F0

GL_RG32UI = 0x823C
# Unsigned image formats by texel size in bytes: (GLSL layout name, GL internal format).
IMAGE_WORD_FORMATS = {2: ("r16ui", GL_R16UI), 4: ("r32ui", GL_R32UI), 8: ("rg32ui", GL_RG32UI),
                      16: ("rgba32ui", GL_RGBA32UI)}

# GL internal-format names as texformats.TexelFormat.gl_internal spells them.
INTERNAL_FORMATS = {
    "RGBA32F": GL_RGBA32F, "RGBA16F": GL_RGBA16F, "RGBA16": GL_RGBA16, "RGB10_A2": GL_RGB10_A2, "R32UI": GL_R32UI,
    "RGBA8": GL_RGBA8, "R16UI": GL_R16UI, "RGBA32UI": GL_RGBA32UI, "RG8UI": GL_RG8UI,
    "COMPRESSED_RGBA_BPTC_UNORM": GL_COMPRESSED_RGBA_BPTC_UNORM,
    "COMPRESSED_RGB_S3TC_DXT1": GL_COMPRESSED_RGB_S3TC_DXT1_EXT,
}
# (pixel format, pixel type, bytes per texel) for uncompressed uploads.
PIXEL_TRANSFER = {
    GL_RGBA32F: (GL_RGBA, GL_FLOAT, 16), GL_RGBA16F: (GL_RGBA, GL_HALF_FLOAT, 8),
    GL_RGBA16: (GL_RGBA, GL_UNSIGNED_SHORT, 8),
    GL_RGB10_A2: (GL_RGBA, GL_UNSIGNED_INT_2_10_10_10_REV, 4), GL_R32UI: (GL_RED_INTEGER, GL_UNSIGNED_INT, 4),
    GL_RGBA8: (GL_RGBA, GL_UNSIGNED_BYTE, 4), GL_R16UI: (GL_RED_INTEGER, GL_UNSIGNED_SHORT, 2),
    GL_RGBA32UI: (GL_RGBA_INTEGER, GL_UNSIGNED_INT, 16), GL_RG8UI: (GL_RG_INTEGER, GL_UNSIGNED_BYTE, 2),
}
# Bytes per 4x4 block of the compressed formats.
BLOCK_BYTES = {GL_COMPRESSED_RGBA_BPTC_UNORM: 16, GL_COMPRESSED_RGB_S3TC_DXT1_EXT: 8}

_u = ctypes.c_uint
_i = ctypes.c_int
_p = ctypes.c_void_p
_SIGNATURES = {
    "glGetError": (_u, ()),
    "glGenTextures": (None, (_i, ctypes.POINTER(_u))),
    "glDeleteTextures": (None, (_i, ctypes.POINTER(_u))),
    "glBindTexture": (None, (_u, _u)),
    "glActiveTexture": (None, (_u,)),
    "glTexParameteri": (None, (_u, _u, _i)),
    "glPixelStorei": (None, (_u, _i)),
    "glBindBuffer": (None, (_u, _u)),
    "glTexImage2D": (None, (_u, _i, _i, _i, _i, _i, _u, _u, _p)),
    "glTexImage3D": (None, (_u, _i, _i, _i, _i, _i, _i, _u, _u, _p)),
    "glTexSubImage2D": (None, (_u, _i, _i, _i, _i, _i, _u, _u, _p)),
    "glTexSubImage3D": (None, (_u, _i, _i, _i, _i, _i, _i, _i, _u, _u, _p)),
    "glCompressedTexImage2D": (None, (_u, _i, _u, _i, _i, _i, _i, _p)),
    "glCompressedTexImage3D": (None, (_u, _i, _u, _i, _i, _i, _i, _i, _p)),
    "glCompressedTexSubImage2D": (None, (_u, _i, _i, _i, _i, _i, _u, _i, _p)),
    "glCompressedTexSubImage3D": (None, (_u, _i, _i, _i, _i, _i, _i, _i, _u, _i, _p)),
    "glTextureBarrier": (None, ()),
    "glTextureBarrierNV": (None, ()),
    "glFlush": (None, ()),
    "glGetIntegerv": (None, (_u, _p)),
    "glBindImageTexture": (None, (_u, _u, _i, ctypes.c_ubyte, _i, _u, _u)),
    "glTexStorage2D": (None, (_u, _i, _u, _i, _i)),
    "glTexStorage3D": (None, (_u, _i, _u, _i, _i, _i)),
    "glGenBuffers": (None, (_i, _p)),
    "glDeleteBuffers": (None, (_i, _p)),
    "glBufferStorage": (None, (_u, ctypes.c_ssize_t, _p, _u)),
    "glClearTexSubImage": (None, (_u, _i, _i, _i, _i, _i, _i, _i, _u, _u, _p)),
    "glFenceSync": (_p, (_u, _u)),
    "glWaitSync": (None, (_p, _u, ctypes.c_uint64)),
    "glDeleteSync": (None, (_p,)),
}


class GLError(RuntimeError):
    pass


# PYFUNCTYPE keeps the GIL through the call. CFUNCTYPE would release it, and the frame loop then waits for it again
# behind the fetch and decode threads (up to a switch interval per call), which made frames that uploaded tiles
# slow (BENCHMARKS.md, "Streaming client"). bench_flythrough --gl-release-gil sets CFUNCTYPE for the A/B before any
# entry point is resolved.
FUNCTION_TYPE = ctypes.PYFUNCTYPE


@lru_cache(maxsize=1)
def _loaders():
    loaders = []
    for name in ("libEGL.so.1", "libEGL.so", ctypes.util.find_library("EGL")):
        if not name:
            continue
        try:
            egl = ctypes.CDLL(name)
        except OSError:
            continue
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        loaders.append(lambda fn, egl=egl: egl.eglGetProcAddress(fn.encode()))
        break
    for name in ("libOpenGL.so.0", "libGL.so.1", ctypes.util.find_library("GL"), ctypes.util.find_library("OpenGL")):
        if not name:
            continue
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue

        def dlsym(fn, lib=lib):
            try:
                return ctypes.cast(getattr(lib, fn), ctypes.c_void_p).value
            except AttributeError:
                return None
        loaders.append(dlsym)
    return loaders


class _GL:
    """Lazily resolved GL entry points."""

    def __getattr__(self, name: str):
        restype, argtypes = _SIGNATURES[name]
        fn = FUNCTION_TYPE(restype, *argtypes)(gl_function_address(name))
        setattr(self, name, fn)
        return fn


def gl_function_address(name: str) -> int:
    """The address of GL entry point `name` (EGL's eglGetProcAddress, else libOpenGL/libGL's symbol); GLError when
    no loader has it. warm_compile.py calls through it with CFUNCTYPE, for its own context's calls."""
    for load in _loaders():
        addr = load(name)
        if addr:
            return addr
    raise GLError(f"OpenGL function {name} not found")


gl = _GL()


def check(what: str) -> None:
    err = gl.glGetError()
    if err != GL_NO_ERROR:
        raise GLError(f"{what}: GL error 0x{err:04x}")


def texture_barrier() -> bool:
    """glTextureBarrier (GL 4.5 / ARB_texture_barrier) or glTextureBarrierNV; False when neither exists."""
    for name in ("glTextureBarrier", "glTextureBarrierNV"):
        try:
            getattr(gl, name)()
            return True
        except GLError:
            continue
    return False


def flush() -> None:
    """glFlush: hand the commands issued so far to the GPU now (moderngl offers finish() only)."""
    gl.glFlush()


@lru_cache(maxsize=1)
def _finish_releasing_gil():
    return ctypes.CFUNCTYPE(None)(gl_function_address("glFinish"))


def wait_for_gpu() -> None:
    """glFinish with the interpreter lock released (moderngl's finish() keeps it): the frame loop's wait for the
    GPU is when the fetch and decode threads run their Python, instead of in the frame loop's next CPU work (where
    each of them takes up to a switch interval, 5 ms, from it)."""
    _finish_releasing_gil()()


GL_COLOR = 0x1800
GL_DEPTH = 0x1801


@lru_cache(maxsize=1)
def _framebuffer_clears_releasing_gil():
    clear = ctypes.CFUNCTYPE(None, _u, _u, _i, ctypes.POINTER(ctypes.c_float))(
        gl_function_address("glClearNamedFramebufferfv"))
    return clear, ctypes.CFUNCTYPE(None)(gl_function_address("glFlush"))


def clear_framebuffer_releasing_gil(glo: int, color: tuple[float, float, float, float], depth: float) -> None:
    """Clear colour attachment 0 and the depth of framebuffer `glo` (glClearNamedFramebufferfv, GL 4.5: no binding
    changes, so moderngl's idea of the bound framebuffer stays true) and flush, with the interpreter lock released
    through each call: a cold driver's first clear is tens of milliseconds of its CPU time (BENCHMARKS.md, r25), which
    the fetcher's thread can spend parsing the manifest meanwhile. The scissor test and the write masks apply as to
    any clear."""
    clear, flush_ = _framebuffer_clears_releasing_gil()
    clear(glo, GL_COLOR, 0, (ctypes.c_float * 4)(*color))
    clear(glo, GL_DEPTH, 0, (ctypes.c_float * 1)(depth))
    flush_()
    check(f"clearing framebuffer {glo}")


def fence() -> int:
    """A fence after the commands issued so far in the current context, flushed to the GPU (a GLsync handle; sync
    objects are shared by contexts that share objects)."""
    sync = gl.glFenceSync(GL_SYNC_GPU_COMMANDS_COMPLETE, 0)
    gl.glFlush()
    return sync


def gpu_wait(sync: int | None) -> None:
    """The current context's next commands wait for `sync` on the GPU (the CPU goes on); the fence is deleted."""
    if sync:
        gl.glWaitSync(sync, 0, GL_TIMEOUT_IGNORED)
        gl.glDeleteSync(sync)


def delete_fence(sync: int | None) -> None:
    if sync:
        gl.glDeleteSync(sync)


def _ptr(data: np.ndarray | None):
    return None if data is None else data.ctypes.data_as(ctypes.c_void_p)


def gl_version() -> int:
    """The current context's OpenGL version as 10 * major + minor (43 for 4.3)."""
    major, minor = ctypes.c_int(0), ctypes.c_int(0)
    gl.glGetIntegerv(GL_MAJOR_VERSION, ctypes.byref(major))
    gl.glGetIntegerv(GL_MINOR_VERSION, ctypes.byref(minor))
    return 10 * major.value + minor.value


def has_gl(ctx, version_code: int, extension: str) -> bool:
    """Whether the context offers a feature that became core in `version_code` (e.g. 440) through its version or
    its ARB extension. The NVIDIA driver makes the 4.3 context asked for (moderngl's require=430: "4.3.0 NVIDIA
    580.159.04", version_code 430) and offers the later features as extensions, so a version check alone took
    the slower fallback there (r27: the atlases' prime compiled its shader, 46 ms of a cold first frame)."""
    return ctx.version_code >= version_code or extension in ctx.extensions


class WorkBuffer(moderngl.Buffer):
    """A moderngl Buffer over immutable storage (glBufferStorage) that it owns: moderngl's own buffers are mutable
    (glBufferData), and the NVIDIA driver allocated those at their first use, inside the frame loop
    (bench/probe_gpu_alloc.py; BENCHMARKS.md, "Figures behind library defaults"); immutable storage is allocated
    when it is created."""

    def release(self) -> None:
        glo = getattr(self, "_owned_glo", 0)
        if glo:
            self._owned_glo = 0
            name = _u(glo)
            gl.glDeleteBuffers(1, ctypes.byref(name))
        super().release()


def work_buffer(ctx, size: int) -> moderngl.Buffer:
    """A GPU buffer of `size` bytes (contents undefined) that shaders fill: written by write() and read back by
    read() like any moderngl Buffer. Immutable storage where the GL has it (4.4 or ARB_buffer_storage: the NVIDIA
    driver's 4.3 context has the extension), else ctx.buffer(reserve=size)."""
    size = max(4, int(size))
    if not has_gl(ctx, 440, "GL_ARB_buffer_storage") or size >= 1 << 32:  # external_buffer: a 32-bit size
        return ctx.buffer(reserve=size)
    name = _u(0)
    gl.glGenBuffers(1, ctypes.byref(name))
    gl.glBindBuffer(GL_COPY_WRITE_BUFFER, name.value)
    gl.glBufferStorage(GL_COPY_WRITE_BUFFER, size, None, GL_DYNAMIC_STORAGE_BIT | GL_MAP_READ_BIT)
    gl.glBindBuffer(GL_COPY_WRITE_BUFFER, 0)
    check(f"allocating a {size}-byte buffer")
    buf = ctx.external_buffer(name.value, size)
    buf.__class__ = WorkBuffer
    buf._owned_glo = name.value
    return buf


class StagingBuffer:
    """A pixel-unpack buffer that texture uploads read from. From client memory the NVIDIA driver copied on the
    calling thread in every glTexSubImage (BENCHMARKS.md, "Figures behind library defaults"); from a buffer the
    GPU copies, and the CPU's part is one memcpy per image into the buffer. The buffer is orphaned before each
    image, so a write never waits for the copies of the one before."""

    def __init__(self, ctx, size: int = 4 << 20):
        self.ctx = ctx
        self.buffer = ctx.buffer(reserve=max(1, int(size)), dynamic=True)

    @contextmanager
    def staged(self, image: np.ndarray):
        """Within the block, the pixel-unpack buffer holds `image` (bytes from offset 0) and is bound."""
        data = np.ascontiguousarray(image).reshape(-1).view(np.uint8)
        if data.nbytes > self.buffer.size:
            self.buffer.release()
            self.buffer = self.ctx.buffer(reserve=data.nbytes, dynamic=True)
        else:
            self.buffer.orphan()
        self.buffer.write(data)
        gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, self.buffer.glo)
        try:
            yield
        finally:
            gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)

    def release(self) -> None:
        self.buffer.release()


class RawTexture:
    """A 2D texture or 2D texture array (layers > 0) with a fixed internal format and no mipmaps."""

    def __init__(self, internal: int, width: int, height: int, layers: int = 0):
        self.internal, self.width, self.height, self.layers = internal, width, height, layers
        self.target = GL_TEXTURE_2D_ARRAY if layers else GL_TEXTURE_2D
        self.compressed = internal in BLOCK_BYTES
        name = _u(0)
        gl.glGetError()  # clear stale errors left by others
        gl.glGenTextures(1, ctypes.byref(name))
        self.glo = name.value
        gl.glBindTexture(self.target, self.glo)
        for pname, value in ((GL_TEXTURE_MIN_FILTER, GL_NEAREST), (GL_TEXTURE_MAG_FILTER, GL_NEAREST),
                             (GL_TEXTURE_BASE_LEVEL, 0), (GL_TEXTURE_MAX_LEVEL, 0)):
            gl.glTexParameteri(self.target, pname, value)
        gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)
        gl.glPixelStorei(GL_UNPACK_ALIGNMENT, 1)
        gl.glPixelStorei(GL_UNPACK_ROW_LENGTH, 0)
        depth = max(1, layers)
        if gl_version() >= 42:
            # Immutable storage, contents undefined (the pool writes every slot it draws). Compressed textures had
            # been created from a host array of zeros, which the NVIDIA driver read only at the first upload into the
            # texture, a page fault per 4 KB of the whole pool in the first frame with splats
            # (bench/probe_gpu_alloc.py; BENCHMARKS.md, "Figures behind library defaults").
            if layers:
                gl.glTexStorage3D(self.target, 1, internal, width, height, layers)
            else:
                gl.glTexStorage2D(self.target, 1, internal, width, height)
        elif self.compressed:  # GL 4.1 (the raster path): no glTexStorage
            size = (width // 4) * (height // 4) * BLOCK_BYTES[internal] * depth
            zeros = np.zeros(size, np.uint8)
            if layers:
                gl.glCompressedTexImage3D(self.target, 0, internal, width, height, layers, 0, size, _ptr(zeros))
            else:
                gl.glCompressedTexImage2D(self.target, 0, internal, width, height, 0, size, _ptr(zeros))
        else:
            fmt, typ, _ = PIXEL_TRANSFER[internal]
            if layers:
                gl.glTexImage3D(self.target, 0, internal, width, height, layers, 0, fmt, typ, None)
            else:
                gl.glTexImage2D(self.target, 0, internal, width, height, 0, fmt, typ, None)
        check(f"creating a {width}x{height}x{depth} texture of format 0x{internal:04x}")

    @property
    def nbytes(self) -> int:
        depth = max(1, self.layers)
        if self.compressed:
            return (self.width // 4) * (self.height // 4) * BLOCK_BYTES[self.internal] * depth
        return self.width * self.height * PIXEL_TRANSFER[self.internal][2] * depth

    def write(self, data: np.ndarray, x: int, y: int, w: int, h: int, layer: int = 0) -> None:
        """Upload a w x h region at (x, y): texels row-major (row y first), or BC blocks in row-major block order."""
        data = np.ascontiguousarray(data)
        stale = gl.glGetError()
        if stale != GL_NO_ERROR:
            raise GLError(f"GL error 0x{stale:04x} pending before a texture upload")
        gl.glBindTexture(self.target, self.glo)
        gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)
        gl.glPixelStorei(GL_UNPACK_ALIGNMENT, 1)
        gl.glPixelStorei(GL_UNPACK_ROW_LENGTH, 0)
        if self.compressed:
            if self.layers:
                gl.glCompressedTexSubImage3D(self.target, 0, x, y, layer, w, h, 1, self.internal, data.nbytes,
                                             _ptr(data))
            else:
                gl.glCompressedTexSubImage2D(self.target, 0, x, y, w, h, self.internal, data.nbytes, _ptr(data))
        else:
            fmt, typ, _ = PIXEL_TRANSFER[self.internal]
            if self.layers:
                gl.glTexSubImage3D(self.target, 0, x, y, layer, w, h, 1, fmt, typ, _ptr(data))
            else:
                gl.glTexSubImage2D(self.target, 0, x, y, w, h, fmt, typ, _ptr(data))
        check(f"uploading a {w}x{h} region at ({x}, {y}) layer {layer}")

    def write_region(self, image: np.ndarray | None, image_width: int, src_x: int, src_y: int, x: int, y: int,
                     w: int, h: int, layer: int = 0) -> None:
        """Upload the w x h region at (src_x, src_y) of a contiguous image `image_width` texels wide (uncompressed
        formats) to (x, y): GL reads the rows in place (UNPACK_ROW_LENGTH / SKIP_*), nothing is copied here.
        image None: the image is the one staged in the bound pixel-unpack buffer (StagingBuffer.staged)."""
        if self.compressed:
            raise GLError("write_region: compressed textures take whole blocks through write()")
        if image is not None and not image.flags.c_contiguous:
            raise GLError("write_region needs a contiguous image")
        stale = gl.glGetError()
        if stale != GL_NO_ERROR:
            raise GLError(f"GL error 0x{stale:04x} pending before a texture upload")
        gl.glBindTexture(self.target, self.glo)
        if image is not None:
            gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)
        gl.glPixelStorei(GL_UNPACK_ALIGNMENT, 1)
        gl.glPixelStorei(GL_UNPACK_ROW_LENGTH, image_width)
        gl.glPixelStorei(GL_UNPACK_SKIP_PIXELS, src_x)
        gl.glPixelStorei(GL_UNPACK_SKIP_ROWS, src_y)
        fmt, typ, _ = PIXEL_TRANSFER[self.internal]
        try:
            if self.layers:
                gl.glTexSubImage3D(self.target, 0, x, y, layer, w, h, 1, fmt, typ, _ptr(image))
            else:
                gl.glTexSubImage2D(self.target, 0, x, y, w, h, fmt, typ, _ptr(image))
        finally:
            gl.glPixelStorei(GL_UNPACK_ROW_LENGTH, 0)
            gl.glPixelStorei(GL_UNPACK_SKIP_PIXELS, 0)
            gl.glPixelStorei(GL_UNPACK_SKIP_ROWS, 0)
        check(f"uploading a {w}x{h} region at ({x}, {y}) layer {layer} from ({src_x}, {src_y})")

    @property
    def texel_bytes(self) -> int:
        return PIXEL_TRANSFER[self.internal][2]

    def clear_texel(self, x: int = 0, y: int = 0, layer: int = 0) -> None:
        """Set one texel to zero on the GPU (glClearTexSubImage, GL 4.4; uncompressed formats): the pool's prime
        without a shader (ChunkPool's prime="clear")."""
        fmt, typ, _ = PIXEL_TRANSFER[self.internal]
        gl.glClearTexSubImage(self.glo, 0, x, y, layer, 1, 1, 1, fmt, typ, None)
        check(f"clearing texel ({x}, {y}) layer {layer}")

    def bind_image_words(self, unit: int, layer: int = 0) -> str:
        """Bind one layer of this (uncompressed) texture to image unit `unit` for writing, in the unsigned image
        format of its texel size (GL matches image formats to textures by size); returns that format's GLSL name."""
        glsl, internal = IMAGE_WORD_FORMATS[self.texel_bytes]
        gl.glBindImageTexture(unit, self.glo, 0, 0, layer, GL_WRITE_ONLY, internal)
        return glsl

    def bind(self, unit: int) -> None:
        gl.glActiveTexture(GL_TEXTURE0 + unit)
        gl.glBindTexture(self.target, self.glo)

    def release(self) -> None:
        if self.glo:
            name = _u(self.glo)
            gl.glDeleteTextures(1, ctypes.byref(name))
            self.glo = 0
