"""The per-frame pipeline: cull + depth keys (compute), radix sort (compute), one instanced draw (indirect).

GPU path (GL >= 4.3 with compute shaders, a hardware GL):
  1. cull.comp, one work group per used chunk slot: skip slots outside the frame's draw set (the pool's draw mask),
     decode the splat from the atlases, drop it when behind the near plane, with opacity < 1/255, or when its
     alpha >= 1/255 ellipse misses the image; survivors are compacted with work-group aggregated atomics into
     (key = ~bits(depth), value = i) plus a 48-byte projected record (EWA covariance, conic, quad axes, SH colour),
     so the raster stage only expands quads.
  2. indirect_setup.comp turns the count into sort dispatch sizes and the draw's arguments.
  3. GpuRadixSort sorts only the visible keys (8 passes of count/reduce/scan/scan-add/scatter).
  4. One indirect draw (quads or point sprites, see DRAW_MODES) back to front, premultiplied colour blended with
     (ONE, ONE_MINUS_SRC_ALPHA), depth-tested against the framebuffer's depth without writing it;
     or, draw mode "compute" (the default of "auto" on a hardware GL when the target is cleared), keys front to back
     and the compute-shader tile rasterizer of client_gl/gpu/compute_raster.py (binning, tile sort, per-tile
     blending with the reference's early stop, imageStore into the colour target; no depth test, the target is
     overwritten).
CPU path (GL < 4.3, software GL, or sort="cpu"; and the GPU path's first frames while its programs compile,
RenderOptions.cpu_first): cull and depth sort in numpy on a worker thread over the pool's drawn splats and host
mirror, index buffer upload, one instanced draw whose vertex shader decodes, projects and evaluates SH (splat.vert,
GL 4.1).
The renderer reads only the pool's public API; format_spec/renderer.md describes both paths and what they measured.
"""
from __future__ import annotations

import functools
import math
import struct
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import moderngl
import numpy as np

from splatstream.camera import Camera
from splatstream.errors import UsageError

from . import shadergen
from .compute_raster import ComputeRaster, default_entries, raster_sources
from .gl import clear_framebuffer_releasing_gil, has_gl, texture_barrier, work_buffer
from .gl import flush as gl_flush
from .pool import DEFAULT_PRIME, PRIMES, ChunkPool
from .residency_layout import TEXTURE_UNITS
from .sort import (
    CHAIN_BARRIER,
    RADIX_CHOICES,
    CpuSorter,
    GpuRadixSort,
    compute_program,
    compute_program_source,
    depth_order,
    sort_programs,
)
from .uniforms import ProgramUniforms
from .warm_compile import GL_COMPUTE_SHADER, GL_FRAGMENT_SHADER, GL_VERTEX_SHADER, ShaderWarmer, Stages

SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swiftshader", "software rasterizer")
MAX_GROUPS_PER_DISPATCH = 65535
SORT_MODES = ("auto", "cpu", "gpu")
DRAW_MODES = ("instanced", "triangles", "fetch", "points")
# "auto" among the raster draws (a software GL, render(clear=False); otherwise auto is "compute", see AUTO_COMPUTE):
# point sprites (one primitive per splat: with many splats the raster path is bound by its primitive rate) when at
# least AUTO_POINTS_MIN_SPLATS are drawn and point sprites are at least as wide as the image; otherwise fetch quads
# (tighter, fewer fragments, which is what bounds fewer splats). Figures: BENCHMARKS.md, "GPU renderer".
# "compute": the compute-shader tile rasterizer (client_gl/gpu/compute_raster.py), no raster hardware.
DRAW_CHOICES = ("auto",) + DRAW_MODES + ("compute",)
COLOR_DTYPES = ("f1", "f2", "f4")  # RGBA8, RGBA16F, RGBA32F colour target
AUTO_POINTS_MIN_SPLATS = 2_000_000
RECORD_BYTES = 48  # per visible splat, written by cull.comp
# "auto" on the GPU path of a hardware GL: the compute rasterizer (several times faster than the raster draws, which
# are primitive-bound; BENCHMARKS.md, "GPU renderer") unless render(clear=False) draws over opaque geometry (depth
# test).
AUTO_COMPUTE = True
MIN_WORK_SPLATS = 1 << 20  # work buffers are made for at least this many splats (about 130 MB with the draw's)
BIN_CHECK_FRAMES = 2  # compute draw: frames after an allocation whose entry count is read back (overflow -> grow)
TIMER_QUERIES = 5  # GL_TIME_ELAPSED queries a frame uses at most (the compute draw's five stages)
ALL_BARRIER_BITS = 0xFFFFFFFF
ZERO_PARAMS = bytes(16)  # params: visible count, oversized count, padding
# "auto" draws choosing "compute" with RenderOptions.defer_compute: after the first frame that drew splats, each frame
# compiles the compute draw's programs until this much time went to them (at least one a frame), before it is drawn.
DEFERRED_COMPILE_BUDGET_S = 0.008
# RenderOptions.cpu_first: a frame that draws more splats than this while GPU path programs are still to compile
# compiles the rest at once and switches (the numpy cull and sort of 65536 splats took 14-17 ms of CPU time on the
# shared 2-core VM, 3815 splats, a 250M scene's root, 0.4-0.5 ms: BENCHMARKS.md, "CPU-sorted first frames").
CPU_FIRST_MAX_SPLATS = 65536
# RenderOptions.warm_compile: a deferred program the warmer thread has not linked yet is compiled by the frame loop
# once the frames have waited this long for it (a warmer slowed down by other work cannot hold the GPU path back).
WARM_COMPILE_WAIT_S = 1.0
# The frames stop waiting for the warmer after two programs whose frame-loop compile took WARM_MISS_RATIO or more of
# the warmer's time for it (at least WARM_MISS_MIN_S there): the driver's cache did not carry them over (Mesa's with
# its disk cache off: BENCHMARKS.md, "Deferred compiles warmed off the frame loop").
WARM_MISS_RATIO = 0.5
WARM_MISS_MIN_S = 0.010


def has_compute(ctx) -> bool:
    return ctx.version_code >= 430


def is_software(ctx) -> bool:
    name = str(ctx.info.get("GL_RENDERER", "")).lower()
    return any(s in name for s in SOFTWARE_RENDERERS)


def choose_sort(ctx, mode: str = "auto") -> str:
    """'gpu' or 'cpu' for a context: auto picks the CPU sort without compute shaders or on a software GL."""
    if mode not in SORT_MODES:
        raise UsageError(f"unknown sort mode {mode!r} (choose one of {', '.join(SORT_MODES)})")
    if mode == "gpu":
        if not has_compute(ctx):
            raise UsageError(f"--sort gpu needs OpenGL 4.3 compute shaders; this context is {ctx.version_code}")
        return "gpu"
    if mode == "cpu":
        return "cpu"
    return "gpu" if has_compute(ctx) and not is_software(ctx) else "cpu"


@dataclass(frozen=True)
class RenderOptions:
    """How a SplatRenderer draws, fixed for its lifetime. Product options: sort, draw, color_dtype, depth_test. The
    others' defaults are the product's, and their other values measurement options that bench/bench_render.py
    spells as draw-mode suffixes ("fetch+f2b", "compute+nowc"). One measured and left off goes with its code; these
    stay: the plain raster loop, the per-block lists' oracle in the tests (warp_cull=False), the sort and depth-key
    widths kept as options after their measurement (radix_bits, tile_radix_bits, depth_bits: BENCHMARKS.md), and
    switches whose result BENCHMARKS.md does not hold (front_to_back: format_spec/renderer.md 5; blend, fused_sort,
    full_barriers, sort_pass_programs)."""

    sort: str = "auto"  # auto | cpu | gpu (choose_sort)
    draw: str = "auto"  # auto | instanced | triangles | fetch | points | compute (GPU path)
    color_dtype: str = "f4"  # colour target: f1 (RGBA8), f2 (RGBA16F), f4 (RGBA32F)
    # Raster draws of the GPU path:
    front_to_back: bool = False  # experimental: batches front to back with saturation passes (fetch, points)
    depth_test: bool = True  # test splats against the framebuffer's depth (opaque geometry drawn first)
    blend: bool = True  # False: blending off (measurement)
    # Compute draw (client_gl/gpu/compute_raster.py):
    # Per 8x4-pixel block splat lists: each warp walks only the splats of the batch whose alpha >= 1/255 box reaches
    # its block, or the whole batch when most do, so a warp skips splats that cannot reach its pixels (figures:
    # BENCHMARKS.md, "Per-block splat lists in the raster"). False: the plain loop, the same image bit for bit (the
    # tests' oracle).
    warp_cull: bool = True
    # GPU sort (client_gl/gpu/sort.py), all GPU-path draws:
    # Digit width of the depth sort (RADIX_CHOICES: 4 to 8). 6: four passes over the 24-bit depth keys; with the local
    # scatter it beat 4-bit digits with the global scatter, and 5 or 8 bits were slower (BENCHMARKS.md, "Dense
    # scenes, warm, wall clock").
    radix_bits: int = 6
    fused_sort: bool = True  # 3 dispatches a sort pass (False: the 5 of count, reduce, scan, scan-add, scatter)
    # Each sort pass its own programs (shift and buffers as constants) instead of one set for every pass (shift as a
    # uniform): 18 programs to compile before a first frame instead of 6 (GpuRadixSort). Kept until the GPU
    # machine's frame times of both are in BENCHMARKS.md ("Manifest pages").
    sort_pass_programs: bool = False
    full_barriers: bool = False  # compute draw: glMemoryBarrier(ALL) between dispatches (default: the bits needed)
    # Digit width of the tile sort (None: radix_bits). 7: two passes over 1080p's 13-bit tile ids where 4-bit digits
    # take four (5 and 8 bits slower; BENCHMARKS.md, "Dense scenes, warm, wall clock").
    tile_radix_bits: int | None = 7
    # Bits of the depth keys (all GPU-sort draws): the depth's float bits between the near and far planes mapped to
    # 2**depth_bits values (depth_key_range); fewer bits, fewer radix passes (32: 8 passes of 4 bits, 24: 6, 16: 4).
    # 24 bits change no pixel by more than float rounding on llvmpipe (tests); 16 bits move pixels visibly (splats
    # close in depth swap), so they stay an option (figures: BENCHMARKS.md, "Dense scenes, warm, wall clock").
    depth_bits: int = 24
    # draw="auto" where it chooses the compute draw: the first frames draw with "fetch" (6 programs: cull, the depth
    # sort's 4, the draw's; the same splats blended back to front) while the compute draw's 9 other programs (binning,
    # tile ranges, raster, the tile sort's 4) compile, spread over the frames after the first one with splats
    # (DEFERRED_COMPILE_BUDGET_S a frame); once all are compiled every frame draws "compute", as without deferral.
    # A cold driver cache compiled all 15 inside a streamed first frame (issue 38; BENCHMARKS.md, "Deferred compute
    # draw programs"). False: all compiled before the first compute frame (HeadlessRenderer: every image it reads back
    # is a finished one).
    defer_compute: bool = True
    # sort="auto" and draw="auto" resolving to the GPU path, on a pool that keeps a host mirror (the streaming
    # session's): the first frames draw with the CPU sort (1 program: splat.vert's; the numpy depth sort of the few
    # thousand splats a first view draws takes well under a millisecond) while the GPU path's 6 (cull, the depth
    # sort's setup and 3 pass programs, the fetch draw's) compile after the first frame with splats,
    # DEFERRED_COMPILE_BUDGET_S a frame (at least one); the frame after the last one switches to the GPU path for
    # good (then defer_compute goes on with the compute draw's), a frame of more than CPU_FIRST_MAX_SPLATS at once.
    # A cold driver cache compiled 7 programs, 277 of a 360 ms first frame (issue 38; BENCHMARKS.md, "CPU-sorted
    # first frames"). False: the GPU path's programs before the first frame.
    cpu_first: bool = True
    # The programs that cpu_first and defer_compute compile after the first frame are compiled ahead on a thread with
    # an EGL context of its own (client_gl/gpu/warm_compile.py; its GL calls release the interpreter lock, moderngl's
    # do not), and a frame compiles one only once that thread has linked it (or after WARM_COMPILE_WAIT_S of waiting
    # for it): the frame's compile is then the driver shader cache's hit instead of a cold compile on the frame loop
    # (issue 38; BENCHMARKS.md, "Deferred compiles warmed off the frame loop"). False: the frames compile them cold.
    warm_compile: bool = True
    # How the pool made for this renderer primes its atlases (pool.PRIMES, ChunkPool._prime_atlases): "clear",
    # glClearTexSubImage of one texel with nothing compiled (GL 4.4; the compute prime below 4.4), or "compute", a
    # one-texel shader whose compile was 37-80 ms of a cold NVIDIA driver's first frame (BENCHMARKS.md, r24). On the
    # H200 (r26) the first pixel-unpack uploads after either took 0.1-0.2 ms with no page faults, against 122-138 ms
    # and 131,072 faults unprimed: the driver treats a cleared atlas as GPU-written (issue 31; BENCHMARKS.md, "The
    # first frame's prime and framebuffer off the serial path").
    atlas_prime: str = DEFAULT_PRIME
    # A session that knows its output size before the manifest (`view --headless`, StreamingSession.open with
    # target_size) on a hardware GL makes the first frame's framebuffer and clears it while the manifest is fetched
    # (prepare_target), not in the first frame: a cold driver's first clear took 57 ms there (r24). The picture is
    # the same (the first frame clears or overwrites its target). False: made by the first frame, as the window's.
    early_target: bool = True

    def __post_init__(self) -> None:
        if self.sort not in SORT_MODES:
            raise UsageError(f"unknown sort mode {self.sort!r} (choose one of {', '.join(SORT_MODES)})")
        if self.draw not in DRAW_CHOICES:
            raise UsageError(f"unknown draw mode {self.draw!r} (choose one of {', '.join(DRAW_CHOICES)})")
        if self.color_dtype not in COLOR_DTYPES:
            raise UsageError(f"unknown colour type {self.color_dtype!r} (choose one of {', '.join(COLOR_DTYPES)})")
        if self.radix_bits not in RADIX_CHOICES:
            raise UsageError(f"radix sort digits of {self.radix_bits} bits: choose one of {RADIX_CHOICES}")
        if self.tile_radix_bits is not None and self.tile_radix_bits not in RADIX_CHOICES:
            raise UsageError(f"tile sort digits of {self.tile_radix_bits} bits: choose one of {RADIX_CHOICES}")
        if self.depth_bits not in DEPTH_BITS_CHOICES:
            raise UsageError(f"depth keys of {self.depth_bits} bits: choose one of {DEPTH_BITS_CHOICES}")
        if self.draw != "compute" and not self.compute_defaults:
            raise UsageError("warp_cull, full_barriers and tile_radix_bits are options of the compute draw mode")
        if self.draw == "compute" and not self.raster_defaults:
            raise UsageError("the compute draw mode takes no raster-draw options (front_to_back, depth_test, blend)")
        if self.front_to_back and (self.sort == "cpu" or self.draw not in ("auto", "fetch", "points")):
            raise UsageError("the front-to-back draw needs the GPU sort and the fetch or points draw mode")
        if self.atlas_prime not in PRIMES:
            raise UsageError(f"unknown atlas prime {self.atlas_prime!r} (choose one of {', '.join(PRIMES)})")

    @property
    def raster_defaults(self) -> bool:
        return self.depth_test and self.blend and not self.front_to_back

    @property
    def compute_defaults(self) -> bool:
        return self.warp_cull and not self.full_barriers and self.tile_radix_bits == 7


def resolve_sort(ctx, options: RenderOptions) -> str:
    """The sort path a renderer with these options takes on this context ('gpu' or 'cpu')."""
    if options.draw == "compute":
        if options.sort == "auto" and has_compute(ctx):
            return "gpu"  # the compute rasterizer needs the GPU path, also on a software GL
        if options.sort != "gpu":
            raise UsageError("the compute draw mode needs OpenGL 4.3 compute shaders and the GPU sort")
    elif options.draw != "auto" and options.sort != "cpu":
        # A raster draw named is a GPU-path draw: under sort "auto" a software GL took the CPU sort, which draws its
        # own raster, and `--draw points` was ignored without a word (newuser61).
        if not has_compute(ctx):
            raise UsageError(f"the {options.draw} draw mode is the GPU path's, which needs OpenGL 4.3 compute shaders; "
                             "this GL has none (leave the draw mode at auto)")
        return "gpu"
    sort = choose_sort(ctx, options.sort)
    if options.front_to_back and sort != "gpu":
        raise UsageError("the front-to-back draw needs the GPU sort")
    return sort


def draws_cpu_first(ctx, options: RenderOptions) -> bool:
    """Whether a renderer with these options on this context draws its first frames with the CPU sort (given a pool
    with a host mirror: RenderOptions.cpu_first)."""
    return (options.cpu_first and options.sort == "auto" and options.draw == "auto" and options.raster_defaults
            and resolve_sort(ctx, options) == "gpu")


@dataclass
class FrameStats:
    sort: str
    visible: int | None = None          # known on the CPU path, or after read_visible_count()
    cull_ms: float | None = None        # GPU time (timer queries) when timing was requested
    sort_ms: float | None = None
    draw_ms: float | None = None
    bin_ms: float | None = None         # compute draw mode: tile binning (count, scan, emit)
    tile_sort_ms: float | None = None   # compute draw mode: sort of the entries by tile, tile ranges
    cpu_ms: dict[str, float] = field(default_factory=dict)

    @property
    def total_ms(self) -> float | None:
        if self.cull_ms is None:
            return None
        return self.cull_ms + self.sort_ms + self.draw_ms + (self.bin_ms or 0.0) + (self.tile_sort_ms or 0.0)


def _set(prog, name: str, value) -> None:
    """Set a uniform if the program uses it (unused uniforms are optimised away)."""
    try:
        member = prog[name]
    except KeyError:
        return
    if isinstance(value, np.ndarray):
        member.write(value.astype("f4").tobytes())
    elif isinstance(value, bytes):
        member.write(value)
    else:
        member.value = value


DEPTH_BITS_CHOICES = (16, 20, 24, 32)


@functools.lru_cache(maxsize=64)  # once per camera's planes, not every frame
def depth_key_range(near: float, far: float, bits: int) -> tuple[int, int, int]:
    """(bits of near, right shift, largest key) of cull.comp's depth keys: depths in (near, far] as float32 bits less
    those of near, shifted right until far's fit in `bits` bits. Order-preserving (positive floats' bits grow with
    them); depths whose bits differ only in the bits shifted out tie (the stable sort keeps compaction order)."""
    lo = int(np.float32(near).view(np.uint32))
    hi = int(np.float32(far).view(np.uint32))
    shift = max(0, (hi - lo).bit_length() - bits)
    return lo, shift, (1 << bits) - 1


def camera_uniforms(cam: Camera) -> dict:
    """Uniform values of the projection shared by the cull and vertex shaders (camera.py conventions)."""
    view = cam.world_to_camera_cv()
    n, f = cam.near, cam.far
    return {
        # GLSL matrices are column-major: write the transpose so that the shader's u_view equals `view`.
        "u_view": np.ascontiguousarray(view.T),
        "u_focal": tuple(float(v) for v in cam.focal),
        "u_principal": tuple(float(v) for v in cam.principal_point),
        "u_tan_fov": (cam.tan_half_fov_x, cam.tan_half_fov_y),
        "u_size": (float(cam.width), float(cam.height)),
        "u_near": n,
        "u_far": f,
        "u_eye": tuple(float(v) for v in cam.eye),
        "u_depth_ab": ((f + n) / (f - n), -2.0 * f * n / (f - n)),
    }


@functools.lru_cache(maxsize=128)  # asked every frame while a program waits for the warmer
def program_stages(key: str | None, src) -> Stages:
    """The (GL shader type, source) stages of a program as SplatRenderer._compile_some compiles it (key None: a
    compute_program spec; a str: a compute shader; a pair: vertex and fragment), for the warmer."""
    if key is None:
        return ((GL_COMPUTE_SHADER, compute_program_source(*src)),)
    if isinstance(src, str):
        return ((GL_COMPUTE_SHADER, src),)
    vert, frag = src
    # moderngl's Context.program strips both sources (compute_shader does not): the driver's cache is keyed by the
    # text, so the warmer's unstripped copy missed (the fetch draw's program "not helped" on llvmpipe and NVIDIA:
    # BENCHMARKS.md, "The first frame's two compiles side by side").
    return ((GL_VERTEX_SHADER, vert.strip()), (GL_FRAGMENT_SHADER, frag.strip()))


def _cached_compute_program(ctx, spec) -> bool:
    """Whether compute_program(ctx, *spec) finds its program in the context's cache (compiles nothing)."""
    return isinstance(ctx.extra, dict) and ("compute_program", *spec) in ctx.extra


def output_framebuffer(ctx, width: int, height: int, color_dtype: str = "f4", output_target: int = 0):
    """The offscreen target (colour + depth) of this size, colour type and output target, made once and kept in
    ctx.extra for the context's lifetime (SplatRenderer.framebuffer): moderngl re-binds the last framebuffer after
    creating another one, so releasing a bound one leaves a dangling binding (GL_INVALID_OPERATION)."""
    cache = ctx.extra if isinstance(ctx.extra, dict) else {}
    ctx.extra = cache
    key = ("splat_fbo", width, height, color_dtype, output_target)
    fbo = cache.get(key)
    if fbo is None:
        color = ctx.texture((width, height), 4, dtype=color_dtype)
        depth = ctx.depth_renderbuffer((width, height))
        fbo = cache[key] = ctx.framebuffer([color], depth)
    return fbo


def prepare_target(ctx, width: int, height: int, color_dtype: str = "f4") -> None:
    """The framebuffer a renderer's first frame of this size draws into (output target 0), made now and cleared
    once (RenderOptions.early_target): a cold driver's first clear is its start-up work, tens of milliseconds of CPU
    (BENCHMARKS.md r24/r25), done here while the manifest is fetched instead of inside the first frame. The clear
    releases the interpreter lock where the GL has glClearNamedFramebufferfv (4.5 or ARB_direct_state_access), so
    the fetcher's thread parses meanwhile; moderngl's clear otherwise. The first frame clears (or, drawing
    "compute", overwrites) the target again: its picture does not depend on this."""
    fbo = output_framebuffer(ctx, width, height, color_dtype)
    if has_gl(ctx, 450, "GL_ARB_direct_state_access"):
        clear_framebuffer_releasing_gil(fbo.glo, (0.0, 0.0, 0.0, 0.0), 1.0)
    else:
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)


def program_name(key: str | None, src) -> str:
    """A deferred program's name for benchmark timelines: its key, or a compute_program spec's shader file."""
    return key if key is not None else src[0]


class SplatRenderer:
    """Draws the splats of a ChunkPool (those of the frame's draw set) from a camera into an offscreen framebuffer.

    The pool's slot count is fixed, so every per-frame buffer is allocated here, once."""

    def __init__(self, ctx, pool: ChunkPool, options: RenderOptions | None = None):
        self.ctx = ctx
        self.pool = pool
        self.options = options or RenderOptions()
        self.sort_mode = resolve_sort(ctx, self.options)
        self._software = is_software(ctx)
        self.header = shadergen.decode_header(pool.layout)
        self.max_point = float(ctx.info.get("GL_POINT_SIZE_RANGE", (1.0, 1.0))[1])
        self._fbo = None
        self.output_target = 0  # which of two offscreen targets frames go to (next_output_target)
        self._fbo_size: tuple[int, int] | None = None
        self._background = (0.0, 0.0, 0.0)
        self._camera_key: tuple | None = None  # camera_values() cache
        self._camera_values: dict = {}
        self._queries = [ctx.query(time=True) for _ in range(TIMER_QUERIES)]
        self._debug = None  # decode_debug's program, compiled on first use (a test hook)
        self._work_bytes_key: tuple | None = None
        self._work_bytes = 0
        self._work_splats = 0
        # CPU path
        self._cpu_sorter: CpuSorter | None = None
        self._cpu_program = None
        self._index_buffer = None
        self._vao_cpu = None
        # GPU path
        self.cull = None
        self.params = self.keys = self.values = self.records = self._zero_params = None
        self.sorter: GpuRadixSort | None = None
        self.craster: ComputeRaster | None = None
        self._bin_checks = 0
        self._deferred: list[tuple[str, object]] | None = None  # compute draw programs still to compile (defer_compute)
        self._deferred_programs: dict[str, object] = {}  # ComputeRaster's own, compiled ahead
        self._drew_splats = False  # a frame drew splats (deferred compiles wait for it)
        self._programs: dict[str, tuple] = {}
        self._saturate = self._saturate_vao = self._batch_cmd = None
        self.draw_mode = "fetch" if self.options.draw == "auto" else self.options.draw
        self.program_gpu = self.vao_gpu = None
        # CPU-first (RenderOptions.cpu_first): the GPU path's programs still to compile, (what, source) in order;
        # None once the GPU path runs (or when the renderer never draws with the CPU sort first).
        self._gpu_pending: list[tuple[str | None, object]] | None = None
        self._gpu_compiled: dict[str, object] = {}  # of those, the cull's and the fetch draw's, compiled ahead
        self._reserved_splats = 0  # reserve_work's splats while the CPU sort draws (applied at the switch)
        self._warmer: ShaderWarmer | None = None  # RenderOptions.warm_compile
        self._warm_later = False  # a warmer to start at the next frame after one with splats
        self._warm_wait_since: float | None = None  # when frames began waiting for the warmer's next program
        self._warm_misses = 0
        self.warm_compile_missed = False  # the frames' compiles were not the warmer's cache hits: no more waiting
        self.compile_seconds: dict[str, float] = {}  # the frame loop's compile of each deferred program (program_name)
        if self.sort_mode == "gpu" and pool.host_mirror is not None and draws_cpu_first(ctx, self.options):
            self.sort_mode = "cpu"
            self._gpu_pending = self._gpu_path_sources()
        if self.sort_mode == "gpu":
            self._start_gpu_path()
        else:
            if pool.host_mirror is None:
                raise UsageError("the CPU sort path needs a pool with a host mirror of the splat centres")
            vert, frag = shadergen.render_sources(self.header, 430 if has_compute(ctx) else 410)
            self._cpu_program = ctx.program(vertex_shader=vert, fragment_shader=frag)
            self._bind_samplers(self._cpu_program)
            self._cpu_sorter = CpuSorter()
        if self.options.warm_compile:
            later = list(self._gpu_pending or [])
            if self._defers_compute():
                later += self._deferred_sources()
            later = [(key, src) for key, src in later if key is not None or not _cached_compute_program(ctx, src)]
            if later:
                self._warm_names = {program_stages(key, src): program_name(key, src) for key, src in later}
                # Started after the first frame, not beside it: on the H200 its EGL context's making while the first
                # frame drew took a GL buffer allocation from 0.04 to 24 ms and that frame from 0.070 to 0.135 s
                # warm (BENCHMARKS.md, "Deferred compiles warmed off the frame loop"); no compile waits for it sooner.
                self._warm_later = True

    def _start_gpu_path(self) -> None:
        """The GPU path's programs (those compiled ahead by the CPU-first frames taken from there) and buffers."""
        ctx = self.ctx
        self.cull = self._gpu_compiled.pop("cull", None)
        if self.cull is None:
            self.cull = ctx.compute_shader(shadergen.compute_source("cull.comp", self.header))
        self._bind_samplers(self.cull)
        self._cull_uniforms = ProgramUniforms(self.cull)
        self.params = ctx.buffer(reserve=16)
        self._zero_params = ctx.buffer(ZERO_PARAMS)
        if self._reserved_splats:  # reserved while the CPU-first frames drew
            self.reserve_work(self._reserved_splats)
        self._ensure_work(max(1, self.pool.drawn_splats))
        if self.options.front_to_back:
            vert, frag = shadergen.saturate_sources()
            self._saturate = ctx.program(vertex_shader=vert, fragment_shader=frag)
            self._saturate_vao = ctx.vertex_array(self._saturate, [])
            self._batch_cmd = ctx.buffer(reserve=16)
        self._select_program(self.draw_mode)

    def _gpu_path_sources(self) -> list[tuple[str | None, object]]:
        """What the GPU path compiles before its first frame: the cull, the depth sort's programs (compute_program
        specs, cached in the context where its GpuRadixSort finds them) and the draw's (fetch, as "auto" starts)."""
        opts = self.options
        sources: list[tuple[str | None, object]] = [("cull", shadergen.compute_source("cull.comp", self.header))]
        sources += [(None, spec) for spec in sort_programs(opts.radix_bits, opts.fused_sort, opts.sort_pass_programs)]
        sources.append((self.draw_mode, shadergen.projected_render_sources(self.draw_mode, opts.front_to_back)))
        return sources

    def _advance_cpu_first(self) -> bool:
        """A CPU-first frame: after the first frame with splats, compile GPU path programs for
        DEFERRED_COMPILE_BUDGET_S at most (at least one); the frame after the last one switches to the GPU path
        (so no frame both compiles for the budget and makes the switch), or this one, having compiled them all,
        when it draws more than CPU_FIRST_MAX_SPLATS. True: this frame switched."""
        pending = self._gpu_pending
        if not pending:
            self._switch_to_gpu()
            return True
        budget = DEFERRED_COMPILE_BUDGET_S
        if self.pool.drawn_splats > CPU_FIRST_MAX_SPLATS:  # too many for the CPU sort: the GPU path now
            budget = math.inf
        elif not self._drew_splats:
            return False
        self._compile_some(pending, self._gpu_compiled, budget)
        if budget == math.inf:
            self._switch_to_gpu()
            return True
        return False

    def _switch_to_gpu(self) -> None:
        """From the CPU sort to the GPU path for good: the CPU path's program, buffers and worker go (the pool's
        host mirror is the caller's: nothing here reads it any more)."""
        self._gpu_pending = None
        self._cpu_sorter.close()
        for obj in (self._vao_cpu, self._index_buffer, self._cpu_program):
            if obj is not None:
                obj.release()
        self._cpu_sorter = self._vao_cpu = self._index_buffer = self._cpu_program = None
        self.sort_mode = "gpu"
        self._start_gpu_path()

    @property
    def draw_path(self) -> str:
        """How frames are drawn now, as the window's overlay and every `--record` say it: the GPU path's draw mode
        (fetch, compute, points, instanced, triangles), or "raster" on the CPU sort path (section 4 of
        renderer.md: instanced quads of splat.vert). `draw_mode` alone kept "fetch", the GPU path's first draw,
        while the CPU sort drew (a window's record said "fetch" where its overlay said "raster")."""
        return self.draw_mode if self.sort_mode == "gpu" else "raster"

    @property
    def cpu_first_pending(self) -> bool:
        """True while the CPU-first frames draw (RenderOptions.cpu_first): the pool's host mirror is still read."""
        return self._gpu_pending is not None

    def _ensure_work(self, splats: int) -> None:
        """Per-frame work buffers (keys, values, records, the depth sort's scratch, the compute draw's entries) for
        `splats` drawn splats (the cull pass writes the visible ones of the drawn tiles, compacted). They grow with
        what is drawn (to twice that, never beyond the pool's capacity), not with the pool's capacity: a 1 GiB pool
        holds 23M splats, whose work buffers (2.9 GB) took most of the time to a streamed first frame, for a view
        that draws a few hundred thousand. Their contents live one frame, so growing copies nothing; each growth
        costs an allocation of tens of milliseconds (BENCHMARKS.md, "Streaming client"), hence the doubling."""
        if splats <= self._work_splats:
            return
        capacity = self.pool.splat_capacity
        self._allocate_work(min(capacity, max(2 * splats, 2 * self._work_splats, MIN_WORK_SPLATS)))

    def reserve_work(self, splats: int) -> None:
        """Work buffers for `splats` drawn splats now (a streaming session's splat budget, before its first frame),
        so that no frame of a flight pays a growth: on the GPU machine the two growths of a 3M-splat budget's
        flight were its 35-42 ms render frames (BENCHMARKS.md, "Manifest pages"). Their allocation is immutable
        storage (gl.WorkBuffer), made when created, not at first use. Drawing more later still doubles them."""
        if self.sort_mode != "gpu":
            if self._gpu_pending is not None:  # made at the switch to the GPU path
                self._reserved_splats = max(self._reserved_splats, int(splats))
            return
        n = min(self.pool.splat_capacity, max(int(splats), MIN_WORK_SPLATS))
        if n > self._work_splats:
            self._allocate_work(n)

    def _allocate_work(self, n: int) -> None:
        for b in (self.keys, self.values, self.records):
            if b is not None:
                b.release()
        if self.sorter is not None:
            self.sorter.release()
        ctx = self.ctx
        self.sorter = GpuRadixSort(ctx, n, self.options.radix_bits, self.options.fused_sort,
                                   per_pass=self.options.sort_pass_programs)
        self.sorter.barrier_bits = self._chain_barrier(self.draw_mode)
        self.keys = work_buffer(ctx, n * 4)
        self.values = work_buffer(ctx, n * 4)
        self.records = work_buffer(ctx, n * RECORD_BYTES)
        self._work_splats = n
        if self.craster is not None:
            self.craster.resize(n, max(self.craster.entry_capacity, default_entries(n)))
            self._bin_checks = BIN_CHECK_FRAMES
        if self.options.front_to_back:  # their vertex arrays read `values`: made again with it
            for _prog, vao in self._programs.values():
                vao.release()
            self._programs = {mode: (prog, self._vertex_array(mode, prog))
                              for mode, (prog, _) in self._programs.items()}
            if self.draw_mode in self._programs:
                self.program_gpu, self.vao_gpu = self._programs[self.draw_mode]

    def _vertex_array(self, mode: str, prog):
        """A raster draw's vertex array: front to back, the sorted order (`values`) as an instanced attribute."""
        if self.options.front_to_back and mode != "points":
            return self.ctx.vertex_array(prog, [(self.values, "1u /i", "a_order")])
        return self.ctx.vertex_array(prog, [])

    def _chain_barrier(self, mode: str) -> int:
        """glMemoryBarrier bits between the dispatches of a frame: the compute draw's chain needs shader storage and
        indirect commands only; the raster draws (vertex attributes, indirect draws) keep all bits."""
        return CHAIN_BARRIER if mode == "compute" and not self.options.full_barriers else ALL_BARRIER_BITS

    def _select_program(self, mode: str) -> None:
        opts = self.options
        if self.sorter is not None:
            self.sorter.barrier_bits = self._chain_barrier(mode)
        if mode == "compute":
            if self.craster is None:
                self.craster = ComputeRaster(self.ctx, opts.color_dtype, self._work_splats,
                                             warp_cull=opts.warp_cull,
                                             radix_bits=opts.tile_radix_bits or opts.radix_bits,
                                             fused_sort=opts.fused_sort, barrier_bits=self._chain_barrier("compute"),
                                             sort_pass_programs=opts.sort_pass_programs,
                                             programs=self._deferred_programs)
                self._deferred_programs = {}
                self._bin_checks = BIN_CHECK_FRAMES
            self.draw_mode = mode
            self.program_gpu = self.vao_gpu = None
            return
        if mode not in self._programs:
            prog = self._gpu_compiled.pop(mode, None)
            if prog is None:
                vert, frag = shadergen.projected_render_sources(mode, opts.front_to_back)
                prog = self.ctx.program(vertex_shader=vert, fragment_shader=frag)
            self._programs[mode] = (prog, self._vertex_array(mode, prog))
        self.draw_mode = mode
        self.program_gpu, self.vao_gpu = self._programs[mode]

    def _draw_front_to_back(self, cam: Camera, guard: int) -> None:
        """Batches front to back; between them a saturation pass writes depth 0 where T < 1e-4 (early stop)."""
        ctx = self.ctx
        fbo = self._fbo
        color = fbo.color_attachments[0]
        points = self.draw_mode == "points"
        batches = shadergen.F2B_BATCHES
        for b in range(batches):
            ctx.copy_buffer(self._batch_cmd, self.sorter.batches, size=16, read_offset=32 * b + (16 if points else 0))
            if points:
                ctx.enable(moderngl.PROGRAM_POINT_SIZE)
                ctx.viewport = (-guard, -guard, cam.width + 2 * guard, cam.height + 2 * guard)
                self.vao_gpu.render_indirect(self._batch_cmd, mode=moderngl.POINTS, count=1)
                ctx.viewport = (0, 0, cam.width, cam.height)
            else:
                self.vao_gpu.render_indirect(self._batch_cmd, mode=moderngl.TRIANGLE_STRIP, count=1)
            if b == batches - 1:
                break
            # Saturation pass: colour writes off, depth written (0) where the accumulated alpha saturated.
            if not texture_barrier():
                raise UsageError("the front-to-back draw needs glTextureBarrier (GL 4.5 or NV_texture_barrier)")
            fbo.color_mask = (False, False, False, False)
            fbo.depth_mask = True
            fbo.use()
            ctx.disable(moderngl.BLEND)
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.depth_func = "1"  # always
            color.use(8)
            _set(self._saturate, "u_accum", 8)
            self._saturate_vao.render(mode=moderngl.TRIANGLES, vertices=3)
            fbo.color_mask = (True, True, True, True)
            fbo.depth_mask = False
            fbo.use()
            self._draw_state()
            self.records.bind_to_storage_buffer(0)
            self.values.bind_to_storage_buffer(1)

    def read_oversized_count(self) -> int:
        """Visible splats of the last GPU frame wider than the largest point sprite (clamped in the points mode)."""
        return struct.unpack("4I", self.params.read(16))[1]

    def _bind_samplers(self, prog) -> None:
        for plane, unit in TEXTURE_UNITS.items():
            _set(prog, "u_" + plane, unit)
        _set(prog, "u_cols", self.pool.atlas_columns)

    # --- memory --------------------------------------------------------------------------------------------
    @property
    def work_bytes(self) -> int:
        """GPU bytes of per-frame work buffers (keys, values, sort scratch), beside the pool's splat data (summed
        again only when a buffer may have changed: a frame loop asks every frame)."""
        cr = self.craster
        key = (self._work_splats if self.sort_mode == "gpu" else 0, id(cr), cr.entry_capacity if cr else 0,
               cr.grid if cr else None, self._index_buffer.size if self._index_buffer is not None else 0)
        if key != self._work_bytes_key:
            self._work_bytes_key, self._work_bytes = key, self._sum_work_bytes()
        return self._work_bytes

    def _sum_work_bytes(self) -> int:
        if self.sort_mode == "gpu":
            extra = self.craster.gpu_bytes if self.craster is not None else 0
            return (self.keys.size + self.values.size + self.records.size + self.params.size + self.sorter.gpu_bytes
                    + extra)
        return self._index_buffer.size if self._index_buffer is not None else 0

    # --- framebuffer ---------------------------------------------------------------------------------------
    def framebuffer(self, width: int, height: int):
        """The offscreen target (colour + depth) for this size, shared by all renderers of the context and kept for
        its lifetime (output_framebuffer; prepare_target makes the first one ahead)."""
        self._fbo = output_framebuffer(self.ctx, width, height, self.options.color_dtype, self.output_target)
        self._fbo_size = (width, height)
        return self._fbo

    def next_output_target(self) -> None:
        """Draw the next frames into the other of two offscreen targets: a window shows a frame while the next one
        is drawn (render_thread.py)."""
        self.output_target ^= 1

    def read_image(self) -> np.ndarray:
        """(H, W, 4) float32 of the last frame, row 0 at the top (premultiplied RGB over the background, alpha)."""
        if self._fbo is None:
            raise UsageError("no frame rendered yet")
        w, h = self._fbo_size
        raw = self._fbo.read(components=4, dtype="f4")
        img = np.frombuffer(raw, np.float32).reshape(h, w, 4)[::-1].copy()
        if self.options.front_to_back:
            img[..., :3] += (1.0 - img[..., 3:4]) * np.asarray(self._background, np.float32)
        return img

    # --- frame ---------------------------------------------------------------------------------------------
    def render(self, cam: Camera, *, sh_degree: int | None = None, background=(0.0, 0.0, 0.0), clear: bool = True,
               timing: bool = False, draw_set: Iterable[int] | None = None) -> FrameStats:
        """One frame. sh_degree: bands to evaluate (None: the pool's; each tile evaluates at most its resident
        bands). draw_set: the resident tile ids to draw (None: all); the pool uploads its draw mask only when
        the set changed. clear=False draws over what the framebuffer holds (opaque geometry, depth tested)."""
        self.pool.set_draw_set(draw_set)
        degree = self.pool.sh_degree if sh_degree is None else max(0, min(int(sh_degree), self.pool.sh_degree))
        fbo = self.framebuffer(cam.width, cam.height)
        uniforms = self.camera_values(cam)
        self._background = (float(background[0]), float(background[1]), float(background[2]))
        switched = False
        if self._warm_later and self._drew_splats:  # the frames from here on compile what it will have linked
            self._warm_later = False
            self._warmer = ShaderWarmer(self._warm_names)
        if self._gpu_pending is not None:
            switched = self._advance_cpu_first()
        if self.sort_mode == "gpu":
            self._choose_draw(cam, clear, compile_deferred=not switched)
        self._drew_splats = self._drew_splats or self.pool.drawn_splats > 0
        if self.draw_mode == "compute" and self.sort_mode == "gpu":
            # The tile rasterizer writes every pixel (colour over the background, alpha) and ignores depth: no clear.
            return self._render_compute(cam, uniforms, degree, timing)
        if clear:
            fbo.depth_mask = True
            fbo.use()
            if self.options.front_to_back:  # accumulates C and 1 - T from zero; the background is added on read-back
                fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            else:
                fbo.clear(float(background[0]), float(background[1]), float(background[2]), 0.0, depth=1.0)
        fbo.depth_mask = False
        fbo.use()
        if self.sort_mode == "gpu":
            return self._render_gpu(cam, uniforms, degree, timing)
        uniforms = dict(uniforms, u_sh_degree=degree, u_cb_bands=self.pool.codebook_bands)
        return self._render_cpu(cam, uniforms, timing)

    def camera_values(self, cam: Camera) -> dict:
        """camera_uniforms(cam) with u_view as float32 bytes, computed again only when the camera changed."""
        key = (cam.eye, cam.target, cam.up, cam.fov_y_deg, cam.width, cam.height, cam.near, cam.far)
        if key != self._camera_key:
            values = camera_uniforms(cam)
            values["u_view"] = values["u_view"].astype("f4").tobytes()
            self._camera_key, self._camera_values = key, values
        return self._camera_values

    def _draw_state(self) -> None:
        ctx = self.ctx
        ctx.disable(moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND | moderngl.DEPTH_TEST)
        if not self.options.depth_test:
            ctx.disable(moderngl.DEPTH_TEST)
        if not self.options.blend:
            ctx.disable(moderngl.BLEND)
        if self.options.front_to_back:  # "under": C += (1 - A) alpha c, A += (1 - A) alpha
            ctx.blend_func = moderngl.ONE_MINUS_DST_ALPHA, moderngl.ONE
        else:
            ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        ctx.blend_equation = moderngl.FUNC_ADD
        ctx.depth_func = "<"

    def _start_cull(self, uniforms: dict, degree: int, max_point: float, key_xor: int) -> int:
        """Uniforms of the cull pass (written when they changed), pool and buffers bound; returns the slots to scan."""
        slots = self.pool.scan_slots
        self._ensure_work(self.pool.drawn_splats)  # cull keeps drawn splats only, compacted
        # Zeroed by a GPU copy, in the command stream: a glBufferSubData from here, while frames still queued read and
        # count into `params`, stalled the NVIDIA driver for several frames' time when frames were issued back to back
        # (no wait between them) and drew some of them nearly empty; the copy neither stalls nor races (BENCHMARKS.md,
        # "Figures behind library defaults").
        self.ctx.copy_buffer(self.params, self._zero_params, len(ZERO_PARAMS))
        u = self._cull_uniforms
        for name, value in uniforms.items():
            u.set(name, value)
        u.set("u_sh_degree", degree)
        u.set("u_cb_bands", self.pool.codebook_bands)
        u.set("u_max_point", max_point)
        u.set("u_slots", slots)
        bits = self.options.depth_bits
        lo, shift, top = depth_key_range(uniforms["u_near"], uniforms["u_far"], bits)
        u.set("u_key_range", (lo, shift))
        u.set("u_key_max", top)
        u.set("u_key_xor", key_xor & top)
        self.pool.bind()
        self.params.bind_to_storage_buffer(0)
        self.keys.bind_to_storage_buffer(1)
        self.values.bind_to_storage_buffer(2)
        self.records.bind_to_storage_buffer(3)
        return slots

    def _cull(self, slots: int) -> None:
        u = self._cull_uniforms
        for base in range(0, slots, MAX_GROUPS_PER_DISPATCH):
            u.set("u_slot_base", base)
            self.cull.run(min(MAX_GROUPS_PER_DISPATCH, slots - base))
        self.ctx.memory_barrier(self.sorter.barrier_bits)
        self.sorter.setup(self.params)

    def _choose_draw(self, cam: Camera, clear: bool, compile_deferred: bool = True) -> None:
        """The draw mode of this frame ("auto": see DRAW_CHOICES). compile_deferred=False: no deferred compile in
        this frame (the one that switched from the CPU-first frames)."""
        if self.options.draw != "auto":
            return
        # The compute rasterizer overwrites the target and ignores its depth: raster draws over opaque geometry.
        if AUTO_COMPUTE and clear and self.options.raster_defaults and not self._software:
            mode = "compute"
        else:
            wide = self.max_point >= max(cam.width, cam.height)
            points = wide and self.pool.drawn_splats >= AUTO_POINTS_MIN_SPLATS
            mode = "points" if points else "fetch"
        if mode == "compute" and self.craster is None and self.options.defer_compute:
            mode = self._compile_deferred(compile_deferred)
        if mode != self.draw_mode or (mode == "compute" and self.craster is None):
            self._select_program(mode)

    def _compile_deferred(self, compile_now: bool = True) -> str:
        """The draw mode of a frame that chose "compute" before its programs are compiled: "fetch" while some are
        not (compiling them, after the first frame with splats, for DEFERRED_COMPILE_BUDGET_S at most, at least
        one), then "compute"."""
        if self._deferred is None:
            self._deferred = self._deferred_sources()
        if self._drew_splats and compile_now:
            self._compile_some(self._deferred, self._deferred_programs, DEFERRED_COMPILE_BUDGET_S)
        return "fetch" if self._deferred else "compute"

    def _deferred_sources(self) -> list[tuple[str | None, object]]:
        """The compute draw's programs that defer_compute compiles after the first frame, (key, source) in order."""
        opts = self.options
        bits = opts.tile_radix_bits or opts.radix_bits
        deferred: list[tuple[str | None, object]] = list(raster_sources(opts.color_dtype, opts.warp_cull, bits).items())
        # The tile sort's programs, cached in the context (compute_program) where its GpuRadixSort finds them.
        deferred += [(None, spec) for spec in sort_programs(bits, opts.fused_sort, opts.sort_pass_programs)]
        return deferred

    def _defers_compute(self) -> bool:
        """Whether this renderer's frames will compile the compute draw's programs after its first frame (the
        GPU path's "auto" choosing "compute" with defer_compute; a frame with clear=False would not)."""
        opts = self.options
        return (opts.draw == "auto" and opts.defer_compute and AUTO_COMPUTE and opts.raster_defaults
                and not self._software and (self.sort_mode == "gpu" or self._gpu_pending is not None))

    def _compile_some(self, pending: list[tuple[str | None, object]], into: dict[str, object],
                      budget_s: float) -> None:
        """Compile pending (key, source) programs in order until budget_s went to them (at least one): key None, a
        compute_program spec (cached in the context); a str source, a compute shader; a (vertex, fragment) pair, a
        program; each kept in `into` under its key. With a warmer (RenderOptions.warm_compile) and a finite budget,
        a program waits until the warmer linked it (then this compile is the driver cache's hit) or the frames waited
        WARM_COMPILE_WAIT_S for it: this frame may compile none."""
        t0 = time.perf_counter()
        while pending:
            key, src = pending[0]
            stages = program_stages(key, src)
            if not self._warmed(key, src, stages, budget_s):
                break
            pending.pop(0)
            t = time.perf_counter()
            if key is None:
                compute_program(self.ctx, *src)
            elif isinstance(src, str):
                into[key] = self.ctx.compute_shader(src)
            else:
                vert, frag = src
                into[key] = self.ctx.program(vertex_shader=vert, fragment_shader=frag)
            now = time.perf_counter()
            self.compile_seconds[program_name(key, src)] = now - t
            self._check_warm_hit(stages, now - t)
            if now - t0 >= budget_s:
                break

    def _check_warm_hit(self, stages: Stages, loop_s: float) -> None:
        """After the frame loop compiled a program the warmer had linked: when that compile took about as long as the
        warmer's (WARM_MISS_RATIO of it, a program that took the warmer WARM_MISS_MIN_S or more), twice, the driver's
        cache is not shared between the contexts (or is off), and the frames stop waiting for the warmer."""
        warmer = self._warmer
        warm_s = warmer.seconds.get(stages) if warmer is not None and not self.warm_compile_missed else None
        if warm_s is None or warm_s < WARM_MISS_MIN_S or loop_s < WARM_MISS_RATIO * warm_s:
            return
        self._warm_misses += 1
        if self._warm_misses >= 2:
            self.warm_compile_missed = True
            warmer.stop(wait=False)

    def _warmed(self, key: str | None, src, stages: Stages, budget_s: float) -> bool:
        """Whether the frame loop compiles this program now: no warmer, the warmer linked it, is over (done, failed,
        stopped after misses) or was waited for WARM_COMPILE_WAIT_S, the frame compiles everything at once (an
        infinite budget), or it is a compute_program the context holds already (nothing to compile)."""
        warmer = self._warmer
        if (warmer is None or budget_s == math.inf or self.warm_compile_missed or warmer.done(stages)
                or warmer.finished or (key is None and _cached_compute_program(self.ctx, src))):
            self._warm_wait_since = None
            return True
        now = time.perf_counter()
        if self._warm_wait_since is None:
            self._warm_wait_since = now
        if now - self._warm_wait_since >= WARM_COMPILE_WAIT_S:
            self._warm_wait_since = None
            return True
        return False

    @property
    def warm_compile_seconds(self) -> dict[str, float]:
        """The warmer's compile + link time of each program it did (seconds on its thread, by program_name: for
        benchmarks), and "failed" 1.0 if it gave up."""
        warmer = self._warmer
        if warmer is None:
            return {}
        out = {self._warm_names[stages]: t for stages, t in warmer.seconds.items()}
        if warmer.failed:
            out["failed"] = 1.0
        return out

    def _render_gpu(self, cam: Camera, uniforms: dict, degree: int, timing: bool) -> FrameStats:
        """The raster draws of the GPU path (cull, sort, one indirect draw)."""
        ctx = self.ctx
        stats = FrameStats("gpu")
        _set(self.program_gpu, "u_size", uniforms["u_size"])
        guard = float(int(self.max_point) // 2 + 1)
        _set(self.program_gpu, "u_max_point", self.max_point)
        _set(self.program_gpu, "u_guard", guard)
        key_xor = 0 if self.options.front_to_back else 0xFFFFFFFF
        slots = self._start_cull(uniforms, degree, self.max_point if self.draw_mode == "points" else 1e30, key_xor)

        def sort():
            self.sorter.sort(self.params, self.keys, self.values, self.options.depth_bits)

        def draw():
            self._draw_state()
            self.records.bind_to_storage_buffer(0)
            self.values.bind_to_storage_buffer(1)
            if self.options.front_to_back:
                self._draw_front_to_back(cam, int(guard))
            elif self.draw_mode == "triangles":
                self.vao_gpu.render_indirect(self.sorter.draw_tri, mode=moderngl.TRIANGLES, count=1)
            elif self.draw_mode == "points":
                ctx.enable(moderngl.PROGRAM_POINT_SIZE)
                g = int(guard)
                ctx.viewport = (-g, -g, cam.width + 2 * g, cam.height + 2 * g)  # guard band (splat_fetch.vert)
                self.vao_gpu.render_indirect(self.sorter.draw_points, mode=moderngl.POINTS, count=1)
                ctx.viewport = (0, 0, cam.width, cam.height)
            else:
                self.vao_gpu.render_indirect(self.sorter.draw, mode=moderngl.TRIANGLE_STRIP, count=1)

        steps = (lambda: self._cull(slots), sort, draw)
        if timing:
            for q, step in zip(self._queries, steps, strict=False):
                with q:
                    step()
            stats.cull_ms, stats.sort_ms, stats.draw_ms = (q.elapsed / 1e6 for q in self._queries[:3])
        else:
            for step in steps:
                step()
        return stats

    def _render_compute(self, cam: Camera, uniforms: dict, degree: int, timing: bool) -> FrameStats:
        """Cull + keys (front to back), depth sort, tile binning, tile sort, tile raster (compute_raster.py)."""
        stats = FrameStats("gpu")
        cr = self.craster
        w, h = cam.width, cam.height
        color = self._fbo.color_attachments[0]
        slots = self._start_cull(uniforms, degree, 1e30, 0)  # ascending key = front to back
        if timing:
            steps = (
                lambda: self._cull(slots),
                lambda: self.sorter.sort(self.params, self.keys, self.values, self.options.depth_bits),
                lambda: cr.bin(self.params, self.values, self.records, self.sorter.dispatch, w, h, self.keys),
                cr.sort,
                lambda: cr.raster(self.records, color, w, h, self._background),
            )
            for q, step in zip(self._queries, steps, strict=True):
                with q:
                    step()
            stats.cull_ms, stats.sort_ms, stats.bin_ms, stats.tile_sort_ms, stats.draw_ms = (
                q.elapsed / 1e6 for q in self._queries)
        else:
            # A glFlush after every stage but the last: the GPU starts on the frame while the CPU still issues the
            # rest of it (the wall clock a frame gains: BENCHMARKS.md, issue 20).
            self._cull(slots)
            gl_flush()
            self.sorter.sort(self.params, self.keys, self.values, self.options.depth_bits)
            gl_flush()
            cr.bin(self.params, self.values, self.records, self.sorter.dispatch, w, h, self.keys)
            gl_flush()
            cr.sort()
            gl_flush()
            cr.raster(self.records, color, w, h, self._background)
        if self._bin_checks > 0:  # the first frames after an allocation check the entry buffer's capacity
            self._bin_checks -= 1
            if cr.grow_if_needed():
                return self._render_compute(cam, uniforms, degree, timing)
        return stats

    def check_bins(self, exact: bool = False) -> bool:
        """Compute draw, once a frame: grow the entry buffer ahead of need from an earlier frame's count, without
        waiting for this frame's (a read-back of it would stall every frame until the GPU is done: no overlap of
        one frame's GPU work with the next one's CPU work). exact: this frame's count (waits; before a read-back of
        the image). True: a frame overflowed, render this one again."""
        if self.draw_mode != "compute":
            return False
        return self.craster.grow_if_needed() if exact else self.craster.grow_ahead()

    def check_bins_after(self, frames: int) -> None:
        """Compute draw: read the entry count back after each of the next `frames` frames (overflow -> grow)."""
        self._bin_checks = int(frames)

    def read_bin_counts(self) -> tuple[int, int]:
        """Compute draw: (entries sorted, entries needed) of the last frame (a read-back: tests, benchmarks)."""
        return self.craster.read_bins()

    def read_visible_count(self) -> int:
        """The GPU path's visible-splat count of the last frame (a readback: for tests and benchmarks only)."""
        return struct.unpack("I", self.params.read(4))[0]

    # --- CPU path ------------------------------------------------------------------------------------------
    def cpu_visible_order(self, cam: Camera, ids: np.ndarray | None = None) -> np.ndarray:
        """Visible splat ids back to front (conservative cull; the vertex shader drops the rest exactly).

        ids: the candidates (default: every splat the draw set draws, pool.drawn_ids())."""
        ids = self.pool.drawn_ids() if ids is None else ids
        m = self.pool.host_mirror
        view = cam.world_to_camera_cv()
        pos = m.positions[ids]
        t = pos @ view[:3, :3].T.astype(np.float32) + view[:3, 3].astype(np.float32)
        z = t[:, 2]
        op = m.opacity[ids]
        keep = (z > cam.near) & (z < cam.far) & (op >= 1.0 / 255.0)
        fx, fy = cam.focal
        cx, cy = cam.principal_point
        lim = 1.3 * np.array([cam.tan_half_fov_x, cam.tan_half_fov_y])
        jnorm = math.sqrt(1.0 + lim[0] ** 2 + lim[1] ** 2)  # bound on |J| / (f / z) with the reference's clamp
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            k = np.sqrt(2.0 * np.log(np.maximum(op, 1.0 / 255.0) * 255.0))
            r = k * (fy * np.exp(m.max_log_scale[ids]) / z * jnorm + math.sqrt(0.3)) + 1.0
            u = fx * t[:, 0] / z + cx
            v = fy * t[:, 1] / z + cy
            keep &= (u + r > 0) & (u - r < cam.width) & (v + r > 0) & (v - r < cam.height)
        vis = ids[keep]
        return vis[depth_order(z[keep])]

    def _render_cpu(self, cam: Camera, uniforms: dict, timing: bool) -> FrameStats:
        ctx = self.ctx
        stats = FrameStats("cpu")
        t0 = time.perf_counter()
        # The drawn ids are taken here, on the render thread: the pool is not shared with the worker.
        order = self._cpu_sorter.submit(self.cpu_visible_order, cam, self.pool.drawn_ids()).result()
        t1 = time.perf_counter()
        n = len(order)
        stats.visible = n
        if n:
            data = order.astype(np.uint32).tobytes()
            if self._index_buffer is None or self._index_buffer.size < len(data):
                if self._vao_cpu is not None:
                    self._vao_cpu.release()
                    self._index_buffer.release()
                self._index_buffer = ctx.buffer(reserve=max(len(data), 1 << 16), dynamic=True)
                self._vao_cpu = ctx.vertex_array(self._cpu_program, [(self._index_buffer, "1u /i", "a_id")])
            self._index_buffer.write(data)
            for name, value in uniforms.items():
                _set(self._cpu_program, name, value)
            self._draw_state()
            self.pool.bind()
            if timing:
                q = self._queries[0]
                with q:
                    self._vao_cpu.render(mode=moderngl.TRIANGLE_STRIP, vertices=4, instances=n)
                stats.draw_ms = q.elapsed / 1e6
            else:
                self._vao_cpu.render(mode=moderngl.TRIANGLE_STRIP, vertices=4, instances=n)
        stats.cpu_ms = {"cull_sort": (t1 - t0) * 1e3, "upload_draw": (time.perf_counter() - t1) * 1e3}
        return stats

    # --- test hook -----------------------------------------------------------------------------------------
    def decode_debug(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids), DEBUG_STRIDE) float32 decoded by the shaders' decoders (decode_debug.comp)."""
        ctx = self.ctx
        if self._debug is None:
            self._debug = ctx.compute_shader(shadergen.compute_source("decode_debug.comp", self.header))
            self._bind_samplers(self._debug)
        n = len(ids)
        ids_buf = ctx.buffer(np.ascontiguousarray(ids, np.uint32).tobytes() or b"\0" * 4)
        out = ctx.buffer(reserve=max(4, n * shadergen.DEBUG_STRIDE * 4))
        ids_buf.bind_to_storage_buffer(1)
        out.bind_to_storage_buffer(2)
        self.pool.bind()
        _set(self._debug, "u_n", n)
        self._debug.run(max(1, -(-n // 64)))
        ctx.memory_barrier()
        res = np.frombuffer(out.read(), np.float32)[:n * shadergen.DEBUG_STRIDE].reshape(n, shadergen.DEBUG_STRIDE)
        ids_buf.release()
        out.release()
        return res.copy()

    def release(self) -> None:
        if self._warmer is not None:  # its context is on this one's display: done with it before this one goes
            self._warmer.stop()
            self._warmer = None
        if self._cpu_sorter is not None:
            self._cpu_sorter.close()
        for b in (self._index_buffer, self.params, self._zero_params, self.keys, self.values, self.records,
                  self._batch_cmd):
            if b is not None:
                b.release()
        if self.sorter is not None:
            self.sorter.release()
        if self.craster is not None:
            self.craster.release()
        for prog in self._gpu_compiled.values():  # compiled ahead by CPU-first frames, not taken yet
            prog.release()
        self._gpu_compiled.clear()
