"""Shader texel decoding (client_gl.gpu.shadergen) against the numpy decoders (splatstream.format)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import real

from splatstream.format.codec import decode_plane
from splatstream.format.layout import chunk_texel_index
from splatstream.format.texformats import (
    FORMATS,
    PALETTE_FORMATS,
    TEXEL_DTYPES,
    VALUE_FORMATS,
    decode_image,
    unpack_texels,
)
from splatstream.io import read_gaussians

pytest.importorskip("moderngl")

N = 700  # 3 chunks, the last one partial


@pytest.fixture(scope="module")
def gaussians():
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    return g.subset(np.arange(N))


def _numpy_t(plane, n: int) -> np.ndarray:
    """Normalised texel values (n, 4) of layer 0 as texformats decodes them, in splat order."""
    from client_gl.gpu.pool import layer_blob

    blob = layer_blob(plane, 0)
    src = chunk_texel_index(-(-n // 256), plane.width)[:n]
    if FORMATS[plane.format].block == 1:
        return unpack_texels(plane.format, np.frombuffer(blob, TEXEL_DTYPES[plane.format])[src])
    return decode_image(plane.format, blob, plane.width, plane.height).reshape(-1, 4)[src]


@pytest.mark.parametrize("fmt", [f for f in VALUE_FORMATS if f not in PALETTE_FORMATS])
def test_shader_decode_equals_numpy(gl_compute_context, gaussians, fmt):
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    ctx = gl_compute_context
    if FORMATS[fmt].block > 1:
        pytest.importorskip("etcpak")
        pytest.importorskip("texture2ddecoder")
    rotation = fmt
    fmt = FORMATS[fmt].texels  # a rotation-only format (cube565, cube8x4, format.md 4.5) for the rotation, its
    color = fmt if FORMATS[fmt].components == 4 else "f16x4"  # texels elsewhere
    overrides = {"position": fmt, "rotation": rotation, "scale": fmt, "color": color, "sh": fmt}
    scene = tiles_from_gaussians(gaussians, "very-high", overrides=overrides)
    tile = scene.tiles[0]
    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, 8)
    np.testing.assert_array_equal(pool.join(5, tile), [0, 1, 2])
    pool.leave(5)
    np.testing.assert_array_equal(pool.join(6, tile), [0, 1, 2])  # same slots again, written twice
    renderer = SplatRenderer(ctx, pool, RenderOptions(sort="cpu"))
    out = renderer.decode_debug(pool.splat_ids(6))
    renderer.release()
    pool.release()

    planes = tile.planes
    ref = {name: decode_plane(p, N)[:, :, :] for name, p in planes.items()}
    block = FORMATS[fmt].block > 1
    # Raw normalised texels: the numpy decode to 1 ulp (BC: hardware and numpy BC decoders may differ by one step).
    for k, (name, f) in enumerate((("position", fmt), ("rotation", rotation), ("scale", fmt), ("color", color))):
        t_gpu = out[:, 59 + 4 * k: 63 + 4 * k]
        t_np = _numpy_t(planes[name], N)
        comps = FORMATS[f].components
        if FORMATS[f].block > 1:
            assert np.abs(t_gpu[:, :comps] - t_np[:, :comps]).max() <= 1.0 / 255 + 1e-6, name
        else:  # GL's unorm conversion (c / (2^b - 1)) need not round exactly as numpy's float64 division: 1 ulp
            np.testing.assert_array_max_ulp(t_gpu[:, :comps], t_np[:, :comps].astype(np.float32), maxulp=1)
    # Decoded attribute values: the numpy arithmetic up to float rounding (plus one BC step of the range).
    def extent(name: str) -> float:  # largest per-chunk range: one BC step of t moves a value by extent / 255
        r = planes[name].ranges.astype(np.float32)
        return float((r[:, 1] - r[:, 0]).max())

    def close(gpu, cpu, what, scale=1.0):
        tol = 2e-6 * max(1.0, float(np.abs(cpu).max())) + (scale / 255 if block else 0.0)
        assert np.abs(gpu - cpu).max() <= tol, (what, np.abs(gpu - cpu).max(), tol)

    close(out[:, 0:3], ref["position"][:, 0], "position", extent("position"))
    q_gpu, q_np = out[:, 3:7], ref["rotation"][:, 0]
    dots = np.abs(np.sum(q_gpu * q_np, axis=1))
    assert dots.min() >= 1 - (2e-2 if block else 1e-6), "rotation"
    if not block:
        np.testing.assert_allclose(q_gpu, q_np, atol=2e-6)
    close(out[:, 7:10], ref["scale"][:, 0], "scale", extent("scale"))
    close(out[:, 10:14], ref["color"][:, 0], "color", extent("color"))
    rest = out[:, 14:59].reshape(N, 15, 3)
    np_rest = np.concatenate([ref[f"sh{b}"] for b in (1, 2, 3)], axis=1)
    close(rest, np_rest, "sh", max(extent(f"sh{b}") for b in (1, 2, 3)))


def test_palette_planes_decode_on_the_gpu_as_numpy_does(gl_compute_context, gaussians):
    """pal8x4 scale and colour (format.md 4.3.2), their palettes the scene's (in the manifest): the pool holds them
    as 16-bit ranged values (palette_as_ranged); the shaders' values are the numpy palette decode within half a
    16-bit step of each chunk's range."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    ctx = gl_compute_context
    scene = tiles_from_gaussians(gaussians, "medium", overrides={"scale": "pal8x4", "color": "pal8x4"})
    tile = scene.tiles[0]
    assert tile.planes["scale"].format == "pal8x4"
    # the encoder stores the palettes once, in the manifest (format.md 4.3.2, 1.7): the decode took them from there
    assert tile.planes["scale"].scene_palette and tile.planes["color"].scene_palette
    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, 8)
    pool.join(3, tile)
    renderer = SplatRenderer(ctx, pool, RenderOptions(sort="cpu"))
    out = renderer.decode_debug(pool.splat_ids(3))
    renderer.release()
    pool.release()
    for name, cols in (("scale", slice(7, 10)), ("color", slice(10, 14))):
        ref = decode_plane(tile.planes[name], N)[:, 0]
        extent = float(np.ptp(ref, axis=0).max())
        err = np.abs(out[:, cols] - ref).max()
        assert err <= extent / 65535 + 2e-6 * max(1.0, float(np.abs(ref).max())), (name, err)


def test_shader_decode_equals_numpy_on_tile_steps(gl_compute_context, gaussians):
    """medium-low-12bit (format.md 4.3.1): widened ranges decode in the shader as numpy decodes them."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    scene = tiles_from_gaussians(gaussians, "medium-low-12bit", sh_codebook="off")
    tile = scene.tiles[0]
    planes = tile.planes
    r = planes["position"].ranges.astype(np.float64)
    assert np.all(r[:, 1] - r[:, 0] > 0)
    t_position = _numpy_t(planes["position"], N)[:, :3]
    assert 0 < np.median(t_position) < 0.05  # codes on the tile's step (about 4095 of the 65535 levels), not all
    pool = ChunkPool(gl_compute_context, scene.formats, scene.sh_degree, 8)
    pool.join(5, tile)
    renderer = SplatRenderer(gl_compute_context, pool, RenderOptions(sort="cpu"))
    out = renderer.decode_debug(pool.splat_ids(5))
    renderer.release()
    pool.release()
    for k, name in enumerate(("position", "rotation", "scale", "color")):
        t_np = _numpy_t(planes[name], N).astype(np.float32)
        np.testing.assert_array_max_ulp(out[:, 59 + 4 * k: 63 + 4 * k][:, :3], t_np[:, :3], maxulp=1)
    for name, cols in (("position", slice(0, 3)), ("scale", slice(7, 10)), ("color", slice(10, 14))):
        cpu = decode_plane(planes[name], N)[:, 0]
        assert np.abs(out[:, cols] - cpu).max() <= 2e-6 * max(1.0, float(np.abs(cpu).max())), name


def test_shader_decode_equals_numpy_on_zero_anchored_sh_steps(gl_compute_context, gaussians):
    """low-plus-9bit-sh5 (issue 32, format.md 4.3.1): SH band ranges moved so that 0 is on each chunk's grid (and
    one step per band) decode in the shader as numpy decodes them."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    scene = tiles_from_gaussians(gaussians, "low-plus-9bit-sh5")
    tile = scene.tiles[0]
    planes = tile.planes
    pool = ChunkPool(gl_compute_context, scene.formats, scene.sh_degree, 8)
    pool.join(5, tile)
    renderer = SplatRenderer(gl_compute_context, pool, RenderOptions(sort="cpu"))
    out = renderer.decode_debug(pool.splat_ids(5))
    renderer.release()
    pool.release()
    cpu = np.concatenate([decode_plane(planes[f"sh{b}"], N) for b in (1, 2, 3)], axis=1)
    assert np.sum(np.abs(cpu) < 1e-4) > 0.1 * cpu.size  # many coefficients decode to about 0: the zero code
    gpu = out[:, 14:59].reshape(N, 15, 3)
    assert np.abs(gpu - cpu).max() <= 2e-6 * max(1.0, float(np.abs(cpu).max()))
