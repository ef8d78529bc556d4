"""The first frame's start-up work taken off its serial path (issue 31): the pool's atlases primed without a shader
(RenderOptions.atlas_prime="clear": glClearTexSubImage of one texel instead of prime_texels.comp's compile), and the
headless session's framebuffer made and cleared while the manifest is fetched (RenderOptions.early_target). Neither
may change what the uploads leave in the atlases or what is drawn: checked here on llvmpipe against the compute prime
and the framebuffer made by the first frame (main's behaviour), pixel for pixel. Whether the NVIDIA driver treats a
cleared atlas as GPU-written is a GPU machine's measurement (bench/probe_gpu_alloc.py --primes), not a test."""
from __future__ import annotations

import ctypes
import time

import numpy as np
import pytest
from conftest import real

from splatstream.io import read_gaussians

pytest.importorskip("moderngl")

W, H = 128, 96
BASE = ("position", "rotation", "scale", "color")
GL_TEXTURE_2D_ARRAY = 0x8C1A


@pytest.fixture(scope="module")
def ctx(gl_context):
    if gl_context.version_code < 440:
        pytest.skip("glClearTexSubImage needs GL 4.4")
    return gl_context


@pytest.fixture
def as_hardware(monkeypatch):
    """llvmpipe counted as a hardware GL: the early target is made only there (streaming.early_target)."""
    from client_gl.gpu import renderer

    monkeypatch.setattr(renderer, "SOFTWARE_RENDERERS", ())


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))


@pytest.fixture(scope="module")
def tiles(fruit):
    """fruit_drops' two leaf tiles (2360 and 2361 splats), medium preset (uncompressed planes, SH bands 1-3)."""
    from client_gl.scene import tiles_from_scene
    from splatstream.encode import EncodeOptions, encode_in_memory

    scene = tiles_from_scene(encode_in_memory(fruit, EncodeOptions(preset="medium", lod=True, max_leaf_splats=2500)))
    assert len(scene.tiles) == 2 and scene.codebook is None
    return scene


@pytest.fixture(scope="module")
def scene_dir(fruit, tmp_path_factory):
    """fruit_drops cut into small LOD tiles, as a local scene directory a session streams from."""
    from splatstream.encode import EncodeOptions, encode_gaussians

    out = tmp_path_factory.mktemp("ff31") / "fruit"
    encode_gaussians(fruit, out, EncodeOptions(preset="medium", max_leaf_splats=256))
    return out


def read_atlas(tex) -> np.ndarray:
    """Every texel of a RawTexture read back ((layers,) height, width, bytes per texel), glGetTexImage."""
    from client_gl.gpu.gl import PIXEL_TRANSFER, gl, gl_function_address

    get = ctypes.PYFUNCTYPE(None, ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p)(
        gl_function_address("glGetTexImage"))
    fmt, typ, size = PIXEL_TRANSFER[tex.internal]
    shape = ((tex.layers,) if tex.layers else ()) + (tex.height, tex.width, size)
    out = np.zeros(shape, np.uint8)
    gl.glBindTexture(tex.target, tex.glo)
    get(tex.target, 0, fmt, typ, out.ctypes.data_as(ctypes.c_void_p))
    return out


def test_primes_leave_what_the_uploads_put(ctx, tiles):
    """Each prime (pool.PRIMES) writes texel (0, 0) of layer 0 of every uncompressed atlas as zero (compute and
    clear; none writes nothing), and after two tiles join and a band is added, the atlases hold exactly the tiles'
    blocks at their slots, whichever prime made the pool."""
    from client_gl.gpu.pool import PRIMES, ChunkPool, _chunk_blocks
    from client_gl.gpu.residency_layout import BLOCK
    from client_gl.tiledata import TileData

    a, b = tiles.tiles.values()
    slots = 2 * -(-max(a.splats, b.splats) // 256)
    for prime in PRIMES:
        pool = ChunkPool(ctx, tiles.formats, tiles.sh_degree, slots, codebook=None, host_mirror=False, prime=prime)
        try:
            uncompressed = {name: tex for name, tex in pool._atlases.items() if not tex.compressed}
            assert uncompressed  # the medium preset's planes
            if prime != "none":
                for name, tex in uncompressed.items():
                    first = read_atlas(tex)
                    texel = first[0, 0, 0] if tex.layers else first[0, 0]
                    assert not texel.any(), (prime, name)
            got = {}
            for tile_id, tile in tiles.tiles.items():
                base = TileData(tile.splats, {n: tile.planes[n] for n in BASE}, None)
                got[tile_id] = pool.join(tile_id, base)
            pool.add_band(next(iter(tiles.tiles)), 1, {"sh1": a.planes["sh1"]})
            cols = pool.atlas_columns
            for name, tex in uncompressed.items():
                atlas = read_atlas(tex)
                for tile_id, tile in tiles.tiles.items():
                    if name not in BASE and (name != "sh1" or tile is not a):
                        continue  # a band not uploaded: undefined texels
                    plane = tile.planes[name]
                    chunks = len(got[tile_id])
                    for layer in range(max(1, tex.layers)):
                        want = _chunk_blocks(plane, layer, chunks)
                        img = atlas[layer] if tex.layers else atlas
                        for c, slot in enumerate(got[tile_id]):
                            x, y = (slot % cols) * BLOCK, (slot // cols) * BLOCK
                            np.testing.assert_array_equal(img[y:y + BLOCK, x:x + BLOCK], want[c],
                                                          err_msg=f"{prime} {name} slot {slot} layer {layer}")
        finally:
            pool.release()


def test_unknown_prime_is_refused(ctx, tiles):
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions
    from splatstream.errors import UsageError

    with pytest.raises(UsageError, match="atlas prime 'shader'"):
        ChunkPool(ctx, tiles.formats, tiles.sh_degree, 4, prime="shader")
    with pytest.raises(UsageError, match="atlas prime 'shader'"):
        RenderOptions(atlas_prime="shader")


def test_prepare_target_is_the_first_frames_framebuffer_cleared(ctx):
    """prepare_target makes the framebuffer a renderer's frame of that size draws into (the context's cached one)
    and clears it (colour 0, alpha 0) without leaving another framebuffer bound in moderngl's view."""
    from client_gl.gpu.renderer import output_framebuffer, prepare_target

    size = (W + 3, H + 5)  # a size no other test's framebuffer has
    fbo = output_framebuffer(ctx, *size)
    fbo.clear(1.0, 0.5, 0.25, 1.0)  # something to clear
    bound = ctx.fbo
    prepare_target(ctx, *size)
    assert ctx.fbo is bound
    assert output_framebuffer(ctx, *size) is fbo
    img = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32)
    assert not img.any()


def _stream(ctx, source, render, size=(W, H), timeout_s=60.0):
    """A session opened as `view --headless` opens it (the output size given), run until converged: (the converged
    picture (H, W, 3) float32, the session's metrics, whether the first frame's framebuffer existed before it)."""
    from client_gl.gpu.renderer import output_framebuffer
    from client_gl.streaming import StreamingSession, ViewOptions
    from client_gl.view_headless import start_camera

    if isinstance(ctx.extra, dict):  # this size's framebuffer made by this session, not by an earlier one
        ctx.extra.pop(("splat_fbo", *size, render.color_dtype, 0), None)
    session = StreamingSession.open(str(source), ctx, ViewOptions(gpu_mem_mb=32.0, cache=False, render=render),
                                    target_size=size)
    try:
        made_before = ("splat_fbo", *size, render.color_dtype, 0) in (ctx.extra or {})
        cam = start_camera(session.manifest, None, size)
        deadline = time.monotonic() + timeout_s
        while not session.converged and time.monotonic() < deadline:
            rec = session.frame(cam)
            if not rec.uploaded_bytes:
                session.wait(0.005)
        assert session.converged
        fbo = output_framebuffer(ctx, *size, render.color_dtype)
        assert session.renderer._fbo is fbo
        return session.read_image(), session.metrics, made_before
    finally:
        session.close()


@pytest.mark.parametrize("sort", ["cpu", "gpu"])
def test_the_picture_is_mains_with_the_early_target_and_the_clear_prime(ctx, scene_dir, sort, as_hardware):
    """A headless session converges to the same picture (but for the last bits of a few blends, which equal sort
    keys take in the tiles' landing order), with the framebuffer made and cleared
    while the manifest is fetched and with the atlases primed by a clear, each alone and both, as with neither
    (main's behaviour: the compute prime, the framebuffer made by the first frame); the CPU sort path and the GPU
    path's fetch draw (llvmpipe's auto choice is the CPU sort)."""
    from client_gl.gpu.renderer import RenderOptions

    if sort == "gpu" and ctx.version_code < 430:
        pytest.skip("no GL 4.3 compute shaders")
    images = {}
    for early in (False, True):
        for prime in ("compute", "clear"):
            image, metrics, made_before = _stream(ctx, scene_dir, RenderOptions(sort=sort, atlas_prime=prime,
                                                                                early_target=early))
            assert made_before == early
            assert metrics.first_frame_s is not None
            images[(early, prime)] = image
    main = images[(False, "compute")]
    assert main.max() > 0.1  # the scene is drawn
    for key, image in images.items():
        # Either sort takes splats of equal depth keys in slot order, and slots follow the order the tiles landed
        # in (the fetch threads'): a few pixels' blends then differ in the last bits (12 pixels by up to 2.4e-5 seen,
        # the same between any two runs alike, whatever the switches): no test may hang on that order.
        np.testing.assert_allclose(image, main, rtol=0, atol=2e-4, err_msg=str(key))
        assert np.mean(image != main) < 0.01, key


def test_view_headless_gives_the_session_its_output_size(ctx, scene_dir, monkeypatch, tmp_path):
    """`view --headless` (run_headless) opens its session with its output size, so that on a hardware GL the
    framebuffer is made and cleared before the manifest is waited for (once, at that size); with early_target off,
    and on a software GL (llvmpipe as it is), it is not."""
    from client_gl import streaming
    from client_gl.gpu import renderer
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.streaming import ViewOptions
    from client_gl.view_headless import HeadlessRun, run_headless

    calls = []
    real_prepare = streaming.prepare_target
    real_manifest = streaming.Fetcher.manifest

    def prepare(*args, **kwargs):
        calls.append(("prepare", args[1:]))
        return real_prepare(*args, **kwargs)

    def manifest(self, *args, **kwargs):
        calls.append(("manifest",))
        return real_manifest(self, *args, **kwargs)

    monkeypatch.setattr(streaming, "prepare_target", prepare)
    monkeypatch.setattr(streaming.Fetcher, "manifest", manifest)
    software = renderer.SOFTWARE_RENDERERS
    for early, hardware in ((True, True), (False, True), (True, False)):
        calls.clear()
        monkeypatch.setattr(renderer, "SOFTWARE_RENDERERS", () if hardware else software)
        opts = ViewOptions(gpu_mem_mb=32.0, cache=False, render=RenderOptions(sort="cpu", early_target=early))
        code, report = run_headless(HeadlessRun(str(scene_dir), opts, (W, H), timeout_s=60, quiet=True,
                                                screenshot=str(tmp_path / f"{early}{hardware}.png")), ctx)
        assert code == 0 and report["first_frame_s"] is not None
        made = early and (hardware or not renderer.is_software(ctx))
        want = [("prepare", (W, H, "f4")), ("manifest",)] if made else [("manifest",)]
        assert calls[:len(want)] == want and ("prepare", (W, H, "f4")) not in calls[len(want):]


def test_prepared_source_closes_its_fetcher_when_the_early_work_fails(scene_dir, monkeypatch):
    """PreparedSource.open's while_fetching raising: the fetcher is closed and the error goes to the caller."""
    from client_gl import streaming
    from client_gl.streaming import PreparedSource, ViewOptions

    closed = []
    real_close = streaming.Fetcher.close

    def close(self, *args, **kwargs):
        closed.append(self)
        return real_close(self, *args, **kwargs)

    def fail():
        raise RuntimeError("no framebuffer")

    monkeypatch.setattr(streaming.Fetcher, "close", close)
    with pytest.raises(RuntimeError, match="no framebuffer"):
        PreparedSource.open(str(scene_dir), ViewOptions(cache=False), while_fetching=fail)
    assert len(closed) == 1 and closed[0]._closed


def test_the_primes_probe_runs_every_variant(ctx):
    """bench/probe_gpu_alloc.py --primes (the GPU machine's measurement of the clear prime) runs every variant on a
    fresh pool, and after each the first uploads land (its import had broken unnoticed: a renamed helper)."""
    from conftest import load_bench

    probe = load_bench("probe_gpu_alloc")
    rows = probe.prime_steps(ctx, 8, list(probe.PRIME_VARIANTS), 1)
    runs = [r for r in rows if "round" in r]
    assert [r["variant"] for r in runs] == list(probe.PRIME_VARIANTS)
    for r in runs:
        assert set(r["atlases"]) >= {"position", "scale", "color"}  # the uncompressed ones (SH0: no sh atlas)
        assert all(a["first_upload_ms"] >= 0 for a in r["atlases"].values())


def test_the_ab_pairs_each_variant_with_the_first_of_its_round():
    """first_frame_variants_ab.summarize: medians and minima a variant and pass, and each run's difference from the
    first variant's run of the same round and pass."""
    from conftest import load_bench

    ab = load_bench("first_frame_variants_ab")
    rows = [{"round": r, "variant": v, "cache": p, **{k: None for k in ab.KEYS},
             "first_frame_s": t + (0.1 if p == "cold" else 0.0)}
            for r, (a, b) in enumerate([(0.30, 0.20), (0.34, 0.22), (0.28, 0.25)])
            for v, t in (("main", a), ("new", b)) for p in ("cold", "warm")]
    s = ab.summarize(rows, ["main", "new"])
    assert s["main, cold"]["first_frame_s"] == (0.4, 0.38)
    assert s["new, warm"]["first_frame_s"] == (0.22, 0.2)
    paired = s["new, cold"]["first_frame_s minus main's, paired: median, each"]
    assert paired[0] == -0.1 and paired[1] == [-0.1, -0.12, -0.03]


def test_later_gl_features_found_by_extension_in_a_4_3_context(ctx):
    """The NVIDIA driver makes the 4.3 context moderngl asks for ("4.3.0 NVIDIA 580.159.04") and offers 4.4/4.5
    features as extensions: the clear prime, the early target's lock-free clear and immutable work buffers must be
    found there by extension (r27: the prime compiled its shader, 46 ms of a cold first frame)."""
    from types import SimpleNamespace

    from client_gl.gpu.gl import has_gl

    nvidia_43 = SimpleNamespace(version_code=430, extensions={"GL_ARB_clear_texture", "GL_ARB_buffer_storage",
                                                              "GL_ARB_direct_state_access"})
    assert has_gl(nvidia_43, 440, "GL_ARB_clear_texture") and has_gl(nvidia_43, 450, "GL_ARB_direct_state_access")
    assert not has_gl(SimpleNamespace(version_code=430, extensions=set()), 440, "GL_ARB_clear_texture")
    assert has_gl(SimpleNamespace(version_code=450, extensions=set()), 440, "GL_ARB_clear_texture")
    # this context (llvmpipe 4.5) offers them both ways
    assert has_gl(ctx, 440, "GL_ARB_clear_texture") and "GL_ARB_clear_texture" in ctx.extensions
