"""GL client with SH codebook scenes (format v1.1): loading, GPU residency (index atlas + codebook textures),
the generated SH decoders against the numpy decoder, renders against the reference renderer, GPU byte accounting."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import real

from splatstream import render_ref
from splatstream.camera import suggested_camera
from splatstream.errors import UsageError
from splatstream.io import read_gaussians
from splatstream.metrics import psnr

pytest.importorskip("moderngl")

N = 3000  # 12 chunks, the last one partial
K = 300   # codebook entries: 2 codebook chunks, the second partial
W, H = 128, 96


@pytest.fixture(scope="module")
def gaussians():
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    return g.subset(np.arange(N))


@pytest.fixture(scope="module")
def encoded(tmp_path_factory, gaussians):
    """Scene directories: {(preset, sh texel format or None, entries): path}, encoded on demand."""
    from splatstream.encode import EncodeOptions, encode_gaussians

    cache = {}

    def get(preset: str = "very-high", sh: str | None = None, entries: int | str = K):
        key = (preset, sh, entries)
        if key not in cache:
            out = tmp_path_factory.mktemp("cb")
            opts = EncodeOptions(preset=preset, overrides={"sh": sh} if sh else {}, sh_codebook=entries)
            encode_gaussians(gaussians, out, opts)
            cache[key] = out
        return cache[key]

    return get


def _pool_ids(pool, scene) -> np.ndarray:
    """Global splat ids of the scene's tiles in the order decode_scene concatenates them (leaf order)."""
    return np.concatenate([pool.splat_ids(tile_id) for tile_id in scene.tiles])


def _codebook_pool(ctx, scene, slots: int, bands: int | None = None, host_mirror: bool = True):
    """A pool for a codebook scene with its first `bands` codebook bands uploaded (None: all loaded)."""
    from client_gl.gpu.pool import ChunkPool

    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, slots, codebook=scene.codebook_layout,
                     host_mirror=host_mirror)
    for band in range(1, (len(scene.codebook) if bands is None else bands) + 1):
        pool.set_codebook_band(band, scene.codebook[f"sh{band}"])
    return pool


def test_scene_loads_index_plane_and_codebook(encoded):
    from client_gl.scene import tiles_from_scene
    from splatstream.format.codec import decode_index_plane, decode_plane
    from splatstream.scene_decode import decode_scene

    path = encoded()
    scene = tiles_from_scene(path)
    assert scene.sh_degree == 3 and scene.codebook is not None
    assert sorted(scene.codebook) == ["sh1", "sh2", "sh3"]
    for tile in scene.tiles.values():
        assert "sh_index" in tile.planes and not {"sh1", "sh2", "sh3"} & set(tile.planes)
        assert tile.planes["sh_index"].format == "index16"
    # The stored planes reproduce the numpy decode: codebook band b at each splat's index.
    tile = next(iter(scene.tiles.values()))
    idx = decode_index_plane(tile.planes["sh_index"], tile.splats)
    assert idx.min() >= 0 and idx.max() < K
    g = decode_scene(path)
    rest = np.concatenate([decode_plane(scene.codebook[f"sh{b}"], K)[idx] for b in (1, 2, 3)], axis=1)
    np.testing.assert_array_equal(rest, g.sh_rest[:tile.splats])
    # Fewer bands: only those codebook bands are read.
    low = tiles_from_scene(path, sh_degree=1)
    assert sorted(low.codebook) == ["sh1"] and "sh_index" in next(iter(low.tiles.values())).planes
    none = tiles_from_scene(path, sh_degree=0)
    assert none.codebook is None and set(next(iter(none.tiles.values())).planes) == {
        "position", "rotation", "scale", "color"}


@pytest.mark.parametrize("sh_fmt", ["f32x4", "f16x4", "norm16x4", "norm11", "norm9x3", "norm565", "norm8x4", "norm10_2",
                                    "bc1", "bc7"])
def test_shader_decode_equals_numpy(gl_compute_context, encoded, sh_fmt):
    ctx = gl_compute_context
    block = sh_fmt.startswith("bc")
    if block:
        pytest.importorskip("etcpak")
        pytest.importorskip("texture2ddecoder")
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_scene
    from splatstream.scene_decode import decode_scene

    path = encoded(sh=sh_fmt)
    scene = tiles_from_scene(path)
    assert scene.codebook["sh1"].format == sh_fmt
    pool = _codebook_pool(ctx, scene, 16)
    assert pool.layout.uses_codebook and pool.layout.planes == ("position", "rotation", "scale", "color", "sh_index")
    first = next(iter(scene.tiles))
    pool.join(first + 100, scene.tiles[first])  # written twice into the same slots
    pool.leave(first + 100)
    for tile_id, tile in scene.tiles.items():
        pool.join(tile_id, tile)
    renderer = SplatRenderer(ctx, pool, RenderOptions(sort="cpu"))
    try:
        out = renderer.decode_debug(_pool_ids(pool, scene))
    finally:
        renderer.release()
        pool.release()
    g = decode_scene(path)
    n = len(g)
    assert out.shape[0] == n
    rest = out[:, 14:59].reshape(n, 15, 3)
    tol = 2e-6 * max(1.0, float(np.abs(g.sh_rest).max()))
    if block:  # hardware and numpy BC decoders may differ by one step: extent / 255 of the codebook chunk's range
        extent = max(float((p.ranges[:, 1].astype(np.float32) - p.ranges[:, 0]).max()) for p in scene.codebook.values())
        tol += extent / 255
    assert np.abs(rest - g.sh_rest).max() <= tol, np.abs(rest - g.sh_rest).max()
    np.testing.assert_allclose(out[:, 0:3], g.positions, atol=2e-6 * max(1.0, float(np.abs(g.positions).max())))
    np.testing.assert_allclose(out[:, 10:13], g.sh_dc, atol=2e-6)


def test_progressive_codebook_bands(gl_compute_context, encoded):
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_scene
    from splatstream.scene_decode import decode_scene

    ctx = gl_compute_context
    path = encoded()
    scene = tiles_from_scene(path)
    pool = _codebook_pool(ctx, scene, scene.slots, bands=1)
    for tile_id, tile in scene.tiles.items():
        pool.join(tile_id, tile)
    assert pool.codebook_bands == 1
    full = pool.codebook_bytes
    renderer = SplatRenderer(ctx, pool, RenderOptions(sort="cpu"))
    try:
        ids = _pool_ids(pool, scene)
        g = decode_scene(path)
        out = renderer.decode_debug(ids)[:, 14:59].reshape(len(ids), 15, 3)
        np.testing.assert_allclose(out[:, :3], g.sh_rest[:, :3], atol=2e-6)
        assert not out[:, 3:].any()  # bands not uploaded yet decode to 0
        pool.set_codebook_band(2, scene.codebook["sh2"])
        pool.set_codebook_band(3, scene.codebook["sh3"])
        assert pool.codebook_bands == 3
        out = renderer.decode_debug(ids)[:, 14:59].reshape(len(ids), 15, 3)
        np.testing.assert_allclose(out, g.sh_rest, atol=2e-6)
        assert pool.codebook_bytes == full  # every band's texture was allocated up front
    finally:
        renderer.release()
        pool.release()


def test_gpu_bytes_count_the_codebook(gl_context, encoded):
    from client_gl.gpu.pool import ChunkPool
    from client_gl.scene import tiles_from_scene

    ctx = gl_context
    path = encoded()
    scene = tiles_from_scene(path)
    slots = scene.slots
    pool = _codebook_pool(ctx, scene, slots)
    plain = ChunkPool(ctx, scene.formats, scene.sh_degree, slots)
    try:
        cb = scene.codebook["sh1"]
        assert cb.format == "f32x4"
        texels = cb.width * cb.height
        expected = texels * 16 * (3 + 5 + 7) + cb.chunks * 16 * 16  # bands + one 64-word range record per chunk
        assert pool.codebook_bytes == expected
        assert pool.gpu_bytes == pool.texel_bytes + pool.range_bytes + pool.state_bytes + pool.codebook_bytes
        assert pool.gpu_bytes == pool.layout.pool_bytes(slots)
        assert pool.atlas_bytes("sh_index") == slots * 256 * 2  # R16UI, one texel per splat
        # Instead of 15 f32x4 texels a splat: one 16-bit index + the shared codebook.
        assert pool.gpu_bytes == plain.gpu_bytes - slots * 256 * (15 * 16 - 2) + expected
        assert pool.bytes_per_splat < plain.bytes_per_splat
        for tile_id, tile in scene.tiles.items():  # joining tiles allocates nothing
            pool.join(tile_id, tile)
        assert pool.gpu_bytes == pool.layout.pool_bytes(slots) and pool.free_slots == 0
    finally:
        pool.release()
        plain.release()


def test_codebook_tiles_need_a_codebook_pool(gl_context, encoded):
    from client_gl.gpu.pool import ChunkPool
    from client_gl.scene import tiles_from_gaussians, tiles_from_scene
    from splatstream.errors import UsageError

    ctx = gl_context
    scene = tiles_from_scene(encoded())
    tile = next(iter(scene.tiles.values()))
    plain = ChunkPool(ctx, scene.formats, 3, scene.slots)
    with_cb = _codebook_pool(ctx, scene, scene.slots)
    try:
        with pytest.raises(UsageError, match="without an SH codebook"):
            plain.join(1, tile)
        other = tiles_from_gaussians(read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(300)))
        with pytest.raises(UsageError, match="with an SH codebook"):
            with_cb.join(2, other.tiles[0])
        with pytest.raises(UsageError, match="without an SH codebook"):
            plain.set_codebook_band(1, scene.codebook["sh1"])
        assert plain.tile_ids == () and with_cb.tile_ids == ()
    finally:
        plain.release()
        with_cb.release()


RENDER_MODES = ["cpu", "gpu-fetch", "gpu-instanced", "gpu-compute"]


@pytest.mark.parametrize("preset", ["low", "very-high"])
def test_render_matches_reference(gl_context, encoded, preset):
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer
    from splatstream.scene_decode import decode_scene

    ctx = gl_context
    path = encoded(preset=preset, entries=64 if preset == "very-high" else "auto")
    g = decode_scene(path)
    cam = suggested_camera(g.positions, width=W, height=H)
    refs = {d: render_ref.render(g, cam, sh_degree=d) for d in (1, 3)}
    assert refs[3].mean() > 0.02  # the view shows the scene
    assert psnr(refs[1], refs[3]) < 60  # the higher bands change the image: the codebook is exercised
    for mode in RENDER_MODES:
        sort, _, draw = mode.partition("-")
        if sort == "gpu" and ctx.version_code < 430:
            continue
        r = HeadlessRenderer(RenderOptions(sort=sort, draw=draw or "auto"), ctx=ctx)
        try:
            r.load_scene(path)
            assert r.pool.layout.uses_codebook and r.pool.codebook_bands == 3
            for degree, ref in refs.items():
                img = r.render(cam, sh_degree=degree)
                assert psnr(img, ref) >= 40.0, (mode, degree, psnr(img, ref))
        finally:
            r.unload()


def test_render_image_of_a_codebook_scene(encoded):
    """What splatstream.evaluate does with the GL renderer: render_image(scene_dir, camera)."""
    from client_gl import offscreen
    from splatstream.scene_decode import decode_scene

    try:
        offscreen.get_renderer()
    except offscreen.GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")
    path = encoded(preset="low", entries="auto")
    g = decode_scene(path)
    cam = suggested_camera(g.positions, width=W, height=H)
    img = offscreen.render_image(path, cam)
    assert psnr(img, render_ref.render(g, cam)) >= 40.0


def test_in_memory_codebook_tiles(gl_context, gaussians):
    """tiles_from_gaussians builds the codebook as the encoder does; GL renders it like the numpy decode."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer
    from client_gl.scene import tiles_from_gaussians
    from splatstream.format.codec import assemble_gaussians, decode_index_plane, decode_plane
    from splatstream.format.planes import BASE_PLANES

    scene = tiles_from_gaussians(gaussians, "medium", sh_codebook=K)
    tile = scene.tiles[0]
    assert sorted(scene.codebook) == ["sh1", "sh2", "sh3"] and "sh_index" in tile.planes
    assert scene.codebook["sh1"].format == scene.formats["sh"]
    assert tiles_from_gaussians(gaussians, "medium", sh_codebook="off").codebook is None
    # a codebook asked for by name where --sh-degree 0 keeps no band for it is refused (newuser62), not dropped
    with pytest.raises(UsageError, match="--sh-degree 0 drops every SH band"):
        tiles_from_gaussians(gaussians, "medium", sh_degree=0, sh_codebook=K)
    assert tiles_from_gaussians(gaussians, "medium", sh_degree=0, sh_codebook="off").codebook is None
    n = tile.splats
    idx = decode_index_plane(tile.planes["sh_index"], n)
    values = {s.name: decode_plane(tile.planes[s.name], n) for s in BASE_PLANES}
    values.update({f"sh{b}": decode_plane(scene.codebook[f"sh{b}"], K)[idx] for b in (1, 2, 3)})
    g = assemble_gaussians(values, 3)
    cam = suggested_camera(g.positions, width=W, height=H)
    ref = render_ref.render(g, cam)
    r = HeadlessRenderer(RenderOptions(sort="cpu"), ctx=gl_context)
    try:
        r.load_tiles(scene)
        assert r.pool.layout.uses_codebook
        assert psnr(r.render(cam), ref) >= 40.0
    finally:
        r.unload()


def test_lod_scene_tiles_share_the_codebook(gl_context, tmp_path, gaussians):
    """Several tiles (LOD leaves and interior tiles) index one codebook; leaves decode as decode_scene does."""
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_scene

    ctx = gl_context
    from splatstream.encode import EncodeOptions, encode_gaussians
    from splatstream.scene_decode import decode_scene
    from splatstream.store import load_manifest

    encode_gaussians(gaussians, tmp_path, EncodeOptions(preset="medium", sh_codebook=128, lod=True,
                                                        max_leaf_splats=1000))
    manifest = load_manifest(tmp_path)
    assert len(manifest.tiles) > 2
    leaves = tiles_from_scene(tmp_path)
    assert len(leaves.tiles) > 1
    everything = tiles_from_scene(tmp_path, tile_ids=[t.id for t in manifest.tiles])
    pool = _codebook_pool(ctx, everything, everything.slots)
    for tile_id, tile in everything.tiles.items():
        pool.join(tile_id, tile)
    for tile_id in everything.tiles:
        if tile_id not in leaves.tiles:
            pool.leave(tile_id)
    g = decode_scene(tmp_path)
    cam = suggested_camera(g.positions, width=W, height=H)
    renderer = SplatRenderer(ctx, pool, RenderOptions(sort="cpu"))
    try:
        if ctx.version_code >= 430:
            out = renderer.decode_debug(_pool_ids(pool, leaves))
            np.testing.assert_allclose(out[:, 14:59].reshape(len(g), 15, 3), g.sh_rest, atol=2e-6)
        renderer.render(cam)
        img = renderer.read_image()[..., :3]
    finally:
        renderer.release()
        pool.release()
    assert psnr(img, render_ref.render(g, cam)) >= 40.0
