"""The first frame's two compiles side by side (RenderOptions.warm_first, issue 31): a streaming session links the
pool's prime_texels program on a ShaderWarmer thread and the renderer's splat.vert program on its own context
through raw GL calls, before the pool, then makes both through moderngl (the driver cache's hits); the pool is primed
after the renderer, before its first upload. The programs linked ahead are the very sources moderngl compiles (the
cache is keyed by the text: moderngl strips a vertex and fragment program's sources), and the pictures are those of
a session without it. Real GL (EGL, llvmpipe here); no timings asserted."""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import real

from splatstream.camera import Camera
from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians
from splatstream.store import load_manifest

pytest.importorskip("moderngl")

W, H = 128, 96
ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ctx(gl_compute_context):
    return gl_compute_context


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("first_compiles") / "fruit"
    encode_gaussians(read_gaussians(real("fruit_drops_sh3.ply")), out,
                     EncodeOptions(preset="medium", max_leaf_splats=256))
    return out


class SynchronousWarmer:
    """warm_compile.ShaderWarmer, waited for when made: the thread's programs all linked whatever its timing."""

    def __new__(cls, programs):
        from client_gl.gpu.warm_compile import ShaderWarmer

        warmer = ShaderWarmer(programs)
        if warmer.thread is not None:
            warmer.thread.join()
        return warmer


def first_image(ctx, scene, render):
    """A session on `scene` drawn until its first frame with splats: (that image, the session's FirstFrameCompiles,
    whether its pool was primed when the session was built)."""
    from client_gl.streaming import StreamingSession, ViewOptions

    c = load_manifest(scene).camera
    cam = Camera(c.eye, c.target, c.up, c.fov_y, W, H)
    s = StreamingSession.open(str(scene), ctx, ViewOptions(gpu_mem_mb=32.0, cache=False, render=render))
    try:
        primed_when_built = s.pool.primed
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if s.frame(cam).drawn_splats:
                break
            s.wait(0.005)
        return s.read_image(), s.first_compiles, primed_when_built
    finally:
        s.close()


def test_the_session_links_both_first_frame_programs_ahead_and_draws_the_same(ctx, scene, monkeypatch):
    """The warmer links the pool's program and the main thread the renderer's, each the very source moderngl then
    compiles; the pool is primed by the time the session is built; the first frame equals, bit for bit, that of a
    session compiling both cold (warm_first=False), which starts no thread and links nothing ahead."""
    from client_gl.gpu import renderer as renderer_mod
    from client_gl.gpu.renderer import RenderOptions, program_stages
    from client_gl.gpu.warm_compile import GL_COMPUTE_SHADER

    monkeypatch.delenv("MESA_SHADER_CACHE_DISABLE", raising=False)  # shader_disk_cache_off would turn it off
    monkeypatch.delenv("__GL_SHADER_DISK_CACHE", raising=False)
    monkeypatch.setattr(ctx, "extra", {})  # no prime program cached by an earlier test on the shared context
    monkeypatch.setattr(renderer_mod, "ShaderWarmer", SynchronousWarmer)
    linked_here, compiled = [], []
    original_link = renderer_mod.link_here
    monkeypatch.setattr(renderer_mod, "link_here", lambda stages: (linked_here.append(stages),
                                                                   original_link(stages))[1])
    for name in ("program", "compute_shader"):
        original = getattr(type(ctx), name)

        def spy(self, *args, _original=original, _name=name, **kwargs):
            compiled.append((_name, args, kwargs))
            return _original(self, *args, **kwargs)
        monkeypatch.setattr(type(ctx), name, spy)

    want, cold, cold_primed = first_image(ctx, scene, RenderOptions(warm_first=False))
    assert not cold.active and cold.warmer is None and cold.seconds == {} and cold_primed
    assert linked_here == []
    compiled.clear()
    monkeypatch.setattr(ctx, "extra", {})
    got, first, primed = first_image(ctx, scene, RenderOptions())
    assert first.active and first.failed is None and primed
    warmer = first.warmer
    assert warmer is not None and warmer.failed is None and warmer.started
    # the renderer's program: linked here, then compiled by moderngl from the same text (stripped as moderngl does)
    programs = [(a, k) for name, a, k in compiled if name == "program"]
    assert len(programs) == 1 and len(linked_here) == 1
    args, kwargs = programs[0]
    assert program_stages("raster", (kwargs["vertex_shader"], kwargs["fragment_shader"])) == linked_here[0]
    assert linked_here[0][0][1] == kwargs["vertex_shader"].strip()
    # the pool's: linked on the thread, then compiled by moderngl from the same text
    computes = [a[0] for name, a, _ in compiled if name == "compute_shader"]
    assert computes and [((GL_COMPUTE_SHADER, src),) for src in computes] == warmer.programs
    assert all(warmer.done(p) for p in warmer.programs)
    assert set(first.seconds) >= {"here", "wait"} and any(k.startswith("prime ") for k in first.seconds)
    np.testing.assert_array_equal(got, want)


def test_a_failing_warmer_or_link_falls_back_to_the_cold_compiles(ctx, scene, monkeypatch):
    """No libEGL for the thread: it never starts, the pool's program is compiled cold when priming (not waited for);
    a raw link that raises: recorded, the renderer compiles as without it. The pictures are unchanged."""
    from client_gl.gpu import renderer as renderer_mod
    from client_gl.gpu import warm_compile
    from client_gl.gpu.renderer import RenderOptions

    monkeypatch.delenv("MESA_SHADER_CACHE_DISABLE", raising=False)
    monkeypatch.delenv("__GL_SHADER_DISK_CACHE", raising=False)
    want, _, _ = first_image(ctx, scene, RenderOptions(warm_first=False))
    monkeypatch.setattr(warm_compile, "_egl", lambda: None)
    monkeypatch.setattr(ctx, "extra", {})
    got, first, primed = first_image(ctx, scene, RenderOptions())
    assert first.warmer is not None and first.warmer.failed == "no libEGL" and not first.warmer.started
    assert "wait" not in first.seconds and primed and first.seconds["failed"] == "no libEGL"
    np.testing.assert_array_equal(got, want)

    def broken(stages):
        raise OSError("glCreateProgram: no such entry point")
    monkeypatch.setattr(renderer_mod, "link_here", broken)
    got, first, primed = first_image(ctx, scene, RenderOptions())
    assert first.failed == "OSError: glCreateProgram: no such entry point" and primed
    np.testing.assert_array_equal(got, want)


def test_nothing_ahead_where_the_disk_cache_is_off(ctx, scene, monkeypatch):
    """MESA_SHADER_CACHE_DISABLE or __GL_SHADER_DISK_CACHE=0: a program linked elsewhere is not carried over, so
    nothing is linked ahead and the pool is primed when made."""
    from client_gl.gpu.renderer import FirstFrameCompiles, RenderOptions, shader_disk_cache_off
    from client_gl.gpu.residency_layout import PoolLayout

    m = load_manifest(scene)
    layout = PoolLayout(m.formats, m.sh_degree, None)
    for name, value in (("MESA_SHADER_CACHE_DISABLE", "true"), ("__GL_SHADER_DISK_CACHE", "0")):
        with monkeypatch.context() as mp:
            mp.delenv("MESA_SHADER_CACHE_DISABLE", raising=False)
            mp.delenv("__GL_SHADER_DISK_CACHE", raising=False)
            assert not shader_disk_cache_off()
            mp.setenv(name, value)
            assert shader_disk_cache_off()
            first = FirstFrameCompiles(ctx, layout, True, RenderOptions())
            assert not first.active and first.warmer is None and first.linked_here_s is None


def test_the_pool_primes_before_its_first_upload(ctx):
    """ChunkPool(prime=False): not primed until prime_atlases or the first upload, which primes it first; once."""
    from client_gl.gpu.pool import ChunkPool, prime_program_specs
    from client_gl.scene import tiles_from_gaussians

    g = read_gaussians(real("fruit_drops_sh3.ply"))
    tiles = tiles_from_gaussians(g.subset(np.arange(600)))
    pool = ChunkPool(ctx, tiles.formats, tiles.sh_degree, tiles.slots, prime=False)
    try:
        assert not pool.primed and prime_program_specs(pool.layout)
        (_, tile), = tiles.tiles.items()
        pool.join(1, tile)
        assert pool.primed and pool.resident_splats == 600
        pool.prime_atlases()  # nothing more
        assert pool.primed
    finally:
        pool.release()


CACHE_PROBE = r"""
import json, sys
from client_gl.offscreen import create_context
from client_gl.gpu.renderer import program_stages
from client_gl.gpu.warm_compile import link_here
vert, frag, how = json.load(open(sys.argv[1]))
ctx = create_context()
if how == "moderngl":
    ctx.program(vertex_shader=vert, fragment_shader=frag).release()
elif how == "linked":
    link_here(program_stages("raster", (vert, frag)))
else:  # the sources as given, unstripped (what the warmer linked before it stripped them)
    link_here(((0x8B31, vert), (0x8B30, frag)))
ctx.release()
"""


def _cache_entries(directory: pathlib.Path) -> set[tuple[str, int]]:
    """The cache's files and sizes (a miss adds a file, or grows one where the cache is a single file; its LRU index
    is rewritten on every use, so it is left out)."""
    return {(str(p.relative_to(directory)), p.stat().st_size) for p in directory.rglob("*")
            if p.is_file() and p.name != "index"}


def _run_probe(tmp_path, cache, vert, frag, how) -> set[tuple[str, int]]:
    spec = tmp_path / "probe.json"
    spec.write_text(json.dumps([vert, frag, how]))
    env = dict(os.environ, MESA_SHADER_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    env.pop("MESA_SHADER_CACHE_DISABLE", None)
    subprocess.run([sys.executable, "-c", CACHE_PROBE, str(spec)], env=env, check=True, cwd=tmp_path, timeout=300)
    return _cache_entries(cache)


def test_a_pair_linked_ahead_is_the_one_moderngl_finds_in_the_cache(ctx, scene, tmp_path):
    """In Mesa's disk cache (a directory of its own per case, each step a process of its own): moderngl's compile
    of splat.vert's program adds no entry after program_stages' sources were linked raw (the cache's hit), where it
    adds entries after a link of the unstripped sources (a miss: the warmer's fetch draw before this fix)."""
    from client_gl.gpu import shadergen
    from client_gl.gpu.residency_layout import PoolLayout

    if "llvmpipe" not in ctx.info.get("GL_RENDERER", "").lower():
        pytest.skip("counts the entries of Mesa's disk cache")
    m = load_manifest(scene)
    vert, frag = shadergen.render_sources(shadergen.decode_header(PoolLayout(m.formats, m.sh_degree, None)), 430)
    assert vert != vert.strip()  # moderngl's strip changes the text
    for how, hit in (("linked", True), ("unstripped", False)):
        cache = tmp_path / how
        ahead = _run_probe(tmp_path, cache, vert, frag, how)
        if not ahead:
            pytest.skip("Mesa's disk cache wrote nothing here (switched off by its configuration)")
        after = _run_probe(tmp_path, cache, vert, frag, "moderngl")
        assert (after == ahead) == hit, (how, sorted(after - ahead))
