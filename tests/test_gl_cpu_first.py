"""CPU-sorted first frames (RenderOptions.cpu_first, issue 38): a GPU-path renderer on a pool with a host mirror
draws its first frames with the CPU sort (two programs compiled before the first frame: the pool's and splat.vert's),
compiles the GPU path's programs after the first frame with splats and switches to it for good; the pictures on
both sides of the switch are those of renderers that took one path from the start. llvmpipe stands in for a
hardware GL (SOFTWARE_RENDERERS emptied: the auto choices of the GPU machine)."""
from __future__ import annotations

import ctypes
import threading
import time

import numpy as np
import pytest
from conftest import close_camera, real

from splatstream.camera import Camera
from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians
from splatstream.metrics import psnr
from splatstream.store import load_manifest

pytest.importorskip("moderngl")

W, H = 128, 96


@pytest.fixture(scope="module")
def ctx(gl_compute_context):
    return gl_compute_context


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))


class SynchronousWarmer:
    """warm_compile.ShaderWarmer, waited for when made."""

    def __new__(cls, programs):
        from client_gl.gpu.warm_compile import ShaderWarmer

        warmer = ShaderWarmer(programs)
        if warmer.thread is not None:
            warmer.thread.join()
        return warmer


@pytest.fixture
def as_hardware(ctx, monkeypatch):
    """The auto choices of a hardware GL, programs counted as compiled, deferred compiles one a frame."""
    from client_gl.gpu import renderer as renderer_mod

    monkeypatch.setattr(renderer_mod, "SOFTWARE_RENDERERS", ())
    monkeypatch.setattr(renderer_mod, "DEFERRED_COMPILE_BUDGET_S", 0.0)
    # the warmer's programs all linked before the first frame (RenderOptions.warm_compile): the frames' compiles in
    # the order and number they have without it, whatever the thread's timing
    monkeypatch.setattr(renderer_mod, "ShaderWarmer", SynchronousWarmer)
    # an empty program cache: an earlier test module on the session's context may have compiled the sort's programs
    monkeypatch.setattr(ctx, "extra", {})
    compiled: list[str] = []
    for name in ("compute_shader", "program"):
        original = getattr(type(ctx), name)

        def counting(self, *args, _original=original, _name=name, **kwargs):
            compiled.append(_name)
            return _original(self, *args, **kwargs)
        monkeypatch.setattr(type(ctx), name, counting)
    return compiled


def test_first_frames_cpu_sorted_then_the_gpu_path(ctx, fruit, as_hardware, monkeypatch):
    """1 program before the first frame instead of 6 (the pool's prime is a clear: nothing compiled); the GPU path's
    6 compile one a frame (a zero budget) after the first frame with splats, the frame after the last switches to
    the GPU path (fetch, nothing compiled in it), then the compute draw's 9 as before; the CPU-sorted picture is
    the GPU path's up to the raster's rounding and the final one equals that of a renderer that compiled everything
    up front."""
    from client_gl.gpu import renderer as renderer_mod
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    compiled = as_hardware
    monkeypatch.setattr(renderer_mod, "MIN_WORK_SPLATS", 1)  # work buffers for what is drawn (a reservation shows)
    scene = tiles_from_gaussians(fruit)  # with the host mirror, as a streaming session's tiles while it is kept
    cam = close_camera(fruit, W, H)

    def fresh(options):
        for key in [k for k in ctx.extra if k[0] == "compute_program"]:  # the shared sort programs compile again
            del ctx.extra[key]
        compiled.clear()
        pool = ChunkPool(ctx, scene.formats, scene.sh_degree, 4 * scene.slots)  # room for reserve_work below
        for tile_id, tile in scene.tiles.items():
            pool.join(tile_id, tile)
        return SplatRenderer(ctx, pool, options), pool

    up_front, pool_a = fresh(RenderOptions(cpu_first=False, defer_compute=False))
    up_front.render(cam)
    assert up_front.sort_mode == "gpu" and up_front.draw_mode == "compute" and len(compiled) == 15
    want = up_front.read_image()
    fetch, pool_f = fresh(RenderOptions(sort="gpu", draw="fetch"))
    fetch.render(cam)
    want_fetch = fetch.read_image()

    r, pool = fresh(RenderOptions())
    assert r.sort_mode == "cpu" and r.cpu_first_pending and compiled == ["program"]
    reserved = 3 * len(fruit)  # a session's splat budget (more than twice the drawn splats): made at the switch
    assert reserved < pool.splat_capacity
    r.reserve_work(reserved)
    stats = r.render(cam)
    assert stats.sort == "cpu" and stats.visible > 1000 and len(compiled) == 1
    first = r.read_image()
    # The CPU sort's frame against the GPU path's of the same splats (fetch: the same back-to-front blending; on
    # llvmpipe bit for bit, splat.vert and cull.comp projecting alike; the bound leaves a hardware GL its rounding)
    # and against the compute draw's (80 dB here).
    assert np.abs(first - want_fetch).max() <= 1e-3
    assert psnr(first[..., :3], want[..., :3]) >= 60.0
    paths = []
    for _ in range(16):
        r.render(cam)
        paths.append((r.sort_mode, r.draw_mode, len(compiled)))
    # 6 frames compile the cull, the sort's setup and 3 pass programs, the fetch draw's; the 7th switches.
    assert paths[:6] == [("cpu", "fetch", 1 + i) for i in range(1, 7)]
    assert paths[6] == ("gpu", "fetch", 7) and not r.cpu_first_pending and r._cpu_program is None
    assert r._work_splats == reserved and r.work_bytes > 0
    assert paths[7:] == [("gpu", "fetch", 7 + i) for i in range(1, 9)] + [("gpu", "compute", 16)]
    assert np.abs(r.read_image() - want).max() <= 1e-4  # the compute draw's own frame-to-frame noise
    r.render(cam)  # warm: nothing compiles, the picture stays
    assert len(compiled) == 16 and np.abs(r.read_image() - want).max() <= 1e-4
    for rr, p in ((up_front, pool_a), (fetch, pool_f), (r, pool)):
        rr.release()
        p.release()


def test_a_frame_of_many_splats_switches_at_once(ctx, fruit, as_hardware, monkeypatch):
    """More drawn splats than CPU_FIRST_MAX_SPLATS: that frame compiles the GPU path's programs and draws with it,
    the first frame too."""
    from client_gl.gpu import renderer as renderer_mod
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    compiled = as_hardware
    scene = tiles_from_gaussians(fruit)
    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, scene.slots)
    for tile_id, tile in scene.tiles.items():
        pool.join(tile_id, tile)
    r = SplatRenderer(ctx, pool, RenderOptions())
    cam = close_camera(fruit, W, H)
    monkeypatch.setattr(renderer_mod, "CPU_FIRST_MAX_SPLATS", 100)
    compiled.clear()
    assert r.render(cam, draw_set=[]).sort == "cpu" and r.cpu_first_pending and not compiled  # nothing drawn
    assert pool.drawn_splats == 0
    stats = r.render(cam)
    assert stats.sort == "gpu" and r.draw_mode == "fetch" and not r.cpu_first_pending and len(compiled) == 6
    assert r.read_visible_count() > 1000
    r.release()
    pool.release()


def test_cpu_first_needs_the_auto_choices_and_a_host_mirror(ctx, fruit, as_hardware):
    """An explicit sort or draw, a pool without a host mirror (HeadlessRenderer on the GPU path) or cpu_first=False:
    the GPU path from the first frame."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer, draws_cpu_first
    from client_gl.offscreen import HeadlessRenderer
    from client_gl.scene import tiles_from_gaussians

    assert draws_cpu_first(ctx, RenderOptions())
    for options in (RenderOptions(sort="gpu"), RenderOptions(draw="fetch"), RenderOptions(cpu_first=False),
                    RenderOptions(depth_test=False)):
        assert not draws_cpu_first(ctx, options)
    scene = tiles_from_gaussians(fruit, with_mirror=False)
    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, scene.slots, host_mirror=False)
    r = SplatRenderer(ctx, pool, RenderOptions())
    assert r.sort_mode == "gpu" and not r.cpu_first_pending
    r.release()
    pool.release()
    h = HeadlessRenderer(ctx=ctx)
    h.load_gaussians(fruit)
    assert h.sort_mode == "gpu" and h.pool.host_mirror is None
    h.render(close_camera(fruit, W, H))
    assert h.renderer.sort_mode == "gpu" and h.renderer.draw_mode == "compute"
    h.unload()


def test_streaming_session_drops_the_host_mirror_at_the_switch(ctx, fruit, as_hardware, tmp_path):
    """A streamed scene: the first frame with splats is CPU-sorted with a host mirror in the pool and the decode
    workers; from the switch on neither keeps one, and the converged picture equals a session's on the GPU path
    from its first frame."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.streaming import StreamingSession, ViewOptions

    encode_gaussians(fruit, tmp_path / "fruit", EncodeOptions(preset="medium", max_leaf_splats=256))
    c = load_manifest(tmp_path / "fruit").camera
    cam = Camera(c.eye, c.target, c.up, c.fov_y, W, H)
    images = []
    for cpu_first in (True, False):
        view = ViewOptions(gpu_mem_mb=32.0, cache=False, render=RenderOptions(cpu_first=cpu_first))
        s = StreamingSession.open(str(tmp_path / "fruit"), ctx, view)
        try:
            assert s.with_mirror == cpu_first and (s.pool.host_mirror is not None) == cpu_first
            first_sort = None
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                rec = s.frame(cam)
                if first_sort is None and rec.drawn_splats:
                    first_sort = s.last_stats.sort
                if s.converged and s.renderer.draw_mode == "compute":
                    break
                s.wait(0.005)
            assert s.converged and s.renderer.draw_mode == "compute"
            assert first_sort == ("cpu" if cpu_first else "gpu")
            assert s.pool.host_mirror is None and not s.engine.with_mirror and not s.with_mirror
            s.frame(cam)
            images.append(s.read_image())
        finally:
            s.close()
    assert np.abs(images[0] - images[1]).max() <= 1e-4


def test_a_pool_without_its_host_mirror_takes_tiles_with_or_without_one(ctx, fruit):
    """ChunkPool.drop_host_mirror: a tile without a mirror is refused before it and taken after it, and one that
    still brings a mirror (decoded before the switch) is taken too."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.scene import tiles_from_gaussians
    from splatstream.errors import UsageError

    with_mirror = tiles_from_gaussians(fruit.subset(np.arange(600)))
    without = tiles_from_gaussians(fruit.subset(np.arange(600, 1200)), with_mirror=False)
    pool = ChunkPool(ctx, with_mirror.formats, with_mirror.sh_degree, with_mirror.slots + without.slots)
    (_, a), = with_mirror.tiles.items()
    (_, b), = without.tiles.items()
    with pytest.raises(UsageError, match="host mirror"):
        pool.join(1, b)
    pool.drop_host_mirror()
    assert pool.host_mirror is None
    pool.join(1, b)
    pool.join(2, a)
    assert pool.resident_splats == 1200
    pool.release()


def test_warm_compile_waits_for_the_warmer_and_draws_the_same_frames(ctx, fruit, as_hardware, monkeypatch):
    """RenderOptions.warm_compile: the 15 programs the frames compile after the first one (the GPU path's 6, the
    compute draw's 9) are linked first on the warmer's thread and context; a frame compiles none that the warmer has
    not linked (until WARM_COMPILE_WAIT_S), and the frames, path by path, equal those of a renderer without the
    warmer (the same sources compiled by the frame loop): the CPU-sorted ones bit for bit, the GPU path's within its
    own frame-to-frame noise."""
    from client_gl.gpu import renderer as renderer_mod
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer, program_stages
    from client_gl.scene import tiles_from_gaussians

    compiled = as_hardware
    scene = tiles_from_gaussians(fruit)
    cam = close_camera(fruit, W, H)

    def frames(options, n, gate=None):
        for key in [k for k in ctx.extra if k[0] == "compute_program"]:
            del ctx.extra[key]
        compiled.clear()
        pool = ChunkPool(ctx, scene.formats, scene.sh_degree, scene.slots)
        for tile_id, tile in scene.tiles.items():
            pool.join(tile_id, tile)
        r = SplatRenderer(ctx, pool, options)
        out = []
        for i in range(n):
            if gate is not None and i == gate[0]:
                gate[1](r)
            r.render(cam)
            out.append(((r.sort_mode, r.draw_mode, len(compiled)), r.read_image()))
        return r, pool, out

    cold, pool_c, want = frames(RenderOptions(warm_compile=False), 18)
    assert cold._warmer is None
    warm, pool_w, got = frames(RenderOptions(), 18)
    assert warm._warmer is not None and warm._warmer.failed is None
    assert set(warm.warm_compile_seconds) == {"cull", "fetch", "indirect_setup.comp", "radix_count.comp",
                                              "radix_scanadd.comp", "radix_scatter_local.comp", "count_shader",
                                              "scan_shader", "emit_shader", "ranges_shader", "raster_shader"}
    assert len(warm._warmer.programs) == 15  # the depth and tile sorts' programs differ in their digit width
    assert [p for p, _ in got] == [p for p, _ in want] and want[-1][0] == ("gpu", "compute", 16)
    for (path, a), (_, b) in zip(want, got, strict=True):
        if path[0] == "cpu":
            assert np.array_equal(a, b), path
        else:  # the GPU path's own noise: cull's atomic compaction orders depth-key ties by thread timing (two
            # renderers without the warmer differed by 1.2e-5 in 31 values of their switch frame here)
            assert np.abs(a - b).max() <= 1e-4, path
    for r, p in ((cold, pool_c), (warm, pool_w)):
        r.release()
        p.release()

    # A warmer that has linked nothing yet: the frames after the first compile nothing and draw with the CPU sort,
    # until it has (or WARM_COMPILE_WAIT_S passed).
    monkeypatch.setattr(renderer_mod, "ShaderWarmer", WaitingWarmer)
    # not started beside the first frame (its context's making delayed the first frame's GL calls): at the second
    r, pool, _ = frames(RenderOptions(), 1)
    assert r._warmer is None and r._warm_later
    r.render(cam)
    assert isinstance(r._warmer, WaitingWarmer) and not r._warm_later
    r.release()
    pool.release()
    r, pool, seen = frames(RenderOptions(), 5, gate=(3, lambda r: r._warmer.ready.add(
        program_stages("cull", r._gpu_pending[0][1]))))
    assert [p for p, _ in seen] == [("cpu", "fetch", 1)] * 3 + [("cpu", "fetch", 2), ("cpu", "fetch", 2)]
    assert set(r.compile_seconds) == {"cull"}
    monkeypatch.setattr(renderer_mod, "WARM_COMPILE_WAIT_S", 0.0)
    r.render(cam)  # waited long enough: compiled by the frame loop
    assert len(compiled) == 3 and not r.warm_compile_missed
    r.release()
    pool.release()

    # The frame loop's compiles as slow as the warmer's (no cache hit): after two, no more waiting for it.
    monkeypatch.setattr(renderer_mod, "WARM_COMPILE_WAIT_S", 3600.0)
    monkeypatch.setattr(renderer_mod, "WARM_MISS_MIN_S", 0.0)

    def all_ready(warmer):  # as the warmer starts (the second frame)
        warmer.ready.update(warmer.programs)
        warmer.seconds.update(dict.fromkeys(warmer.programs[:2], 1e-9))
    monkeypatch.setattr(WaitingWarmer, "on_start", staticmethod(all_ready))
    r, pool, seen = frames(RenderOptions(), 4)
    assert r.warm_compile_missed and r._warmer.stopped
    r._warmer.ready.clear()  # the warmer has linked nothing more: compiled regardless, one a frame
    r.render(cam)
    assert [p for p, _ in seen][1:] == [("cpu", "fetch", 2), ("cpu", "fetch", 3), ("cpu", "fetch", 4)]
    assert len(compiled) == 5
    r.release()
    pool.release()


class WaitingWarmer:
    """A stand-in for warm_compile.ShaderWarmer whose programs are linked when a test says so (`ready`)."""

    on_start = None  # a test's hook, called with the warmer as the renderer makes it

    def __init__(self, programs):
        self.programs, self.seconds, self.failed, self.thread = list(programs), {}, None, None
        self.ready: set = set()
        self.stopped = False
        self.finished = False
        if self.on_start is not None:
            self.on_start(self)

    def done(self, stages):
        return stages in self.ready

    def stop(self, wait=True):
        self.stopped = True


def test_the_warmer_compiles_on_its_own_context(ctx):
    """ShaderWarmer on the test's EGL context: every program linked on its thread (one that does not compile too:
    the frame loop reports it), the interpreter lock free meanwhile, its context gone after."""
    from client_gl.gpu import warm_compile
    from client_gl.gpu.compute_raster import raster_sources
    from client_gl.gpu.warm_compile import GL_COMPUTE_SHADER, ShaderWarmer

    programs = [((GL_COMPUTE_SHADER, src),) for src in raster_sources("f4").values()]
    programs.append(((GL_COMPUTE_SHADER, "#version 430\nnot glsl"),))
    warmer = ShaderWarmer(programs)
    while not warmer.finished:
        pass  # the main thread runs beside the compiles (how many steps it gets is the scheduler's, not asserted)
    assert warmer.failed is None and all(warmer.done(p) for p in programs) and len(warmer.seconds) == 6
    # the compiles leave the interpreter lock free: the GL entry points are ctypes foreign functions that drop it
    # (CFUNCTYPE), not PYFUNCTYPE ones that keep it
    gl_calls = warm_compile._gl_functions()
    assert gl_calls and all(not type(f)._flags_ & ctypes._FUNCFLAG_PYTHONAPI for f in gl_calls.values())
    program = ctx.compute_shader(programs[0][0][1])  # this thread's context is still current and works
    program.release()
    elsewhere = []  # on a thread without a current GL context: nothing started, the frames compile as before
    thread = threading.Thread(target=lambda: elsewhere.append(ShaderWarmer(programs)))
    thread.start()
    thread.join()
    assert elsewhere[0].failed == "no current GL context" and elsewhere[0].finished and not elsewhere[0].done(
        programs[0])
