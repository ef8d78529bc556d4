"""The compute-shader tile rasterizer (draw mode "compute") against the numpy reference (render_ref) and a numpy
model of its binning (tile rectangles, (depth, tile) order, tile ranges)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import REAL_PLYS, close_camera, real, run_cli

from splatstream import render_ref
from splatstream.camera import look_at, suggested_camera
from splatstream.errors import UsageError
from splatstream.io import read_gaussians
from splatstream.metrics import psnr

pytest.importorskip("moderngl")

W, H = 128, 96


@pytest.fixture(scope="module")
def ctx(gl_compute_context):
    return gl_compute_context


@pytest.fixture(scope="module")
def renderer(ctx):
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer

    r = HeadlessRenderer(RenderOptions(draw="compute"), ctx=ctx)  # sort "auto": the compute draw forces the GPU sort
    yield r
    r.unload()


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))


@pytest.mark.parametrize("name", REAL_PLYS)
def test_real_scene_matches_reference(renderer, name):
    g = read_gaussians(real(name))
    cam = suggested_camera(g.positions, width=W, height=H)
    ref, coverage = render_ref.render_with_alpha(g, cam)
    renderer.load_gaussians(g)
    img = renderer.render(cam)
    assert renderer.sort_mode == "gpu" and renderer.renderer.draw_mode == "compute"
    assert img.shape == (H, W, 3) and img.dtype == np.float32
    assert ref.mean() > 0.02  # the view shows the scene
    assert psnr(img, ref) >= 40.0
    alpha = renderer.renderer.read_image()[..., 3]  # 1 - T
    assert np.abs(alpha - coverage).mean() < 2e-3
    entries, needed = renderer.renderer.read_bin_counts()
    assert entries == needed > 0


def test_close_view_partial_tiles_background_sh_degree(renderer, fruit):
    # 120 x 90: the last tile column and row are partly outside the image.
    cam = close_camera(fruit, 120, 90)
    renderer.load_gaussians(fruit)
    for degree, bg in ((0, (0.2, 0.4, 0.9)), (1, (0.0, 0.0, 0.0)), (3, (1.0, 1.0, 1.0))):
        ref = render_ref.render(fruit, cam, sh_degree=degree, background=bg)
        img = renderer.render(cam, sh_degree=degree, background=bg)
        assert img.shape == (90, 120, 3)
        assert psnr(img, ref) >= 40.0, degree


def test_binning_matches_numpy(ctx, fruit):
    """Entries = for each visible splat front to back, the tiles of its alpha >= 1/255 box where that box is more
    than two tiles high, a subset of it otherwise (row bins: test_row_bins_keep_every_reached_tile); stable by
    tile."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer

    cam = close_camera(fruit, 120, 90)
    renderer = HeadlessRenderer(RenderOptions(draw="compute"), ctx=ctx)
    renderer.load_gaussians(fruit)
    renderer.render(cam)
    rend = renderer.renderer
    cr = rend.craster
    n = rend.read_visible_count()
    entries, needed = rend.read_bin_counts()
    assert n > 0 and entries == needed
    gx, gy = cr.grid
    assert (gx, gy) == (8, 6)
    rec = np.frombuffer(rend.records.read(n * 48), np.float32).reshape(n, 12)
    # The depth sort's key buffer, spent by then, holds bin_count's entries of each sorted splat (row bins' scratch).
    splat_entries = np.frombuffer(rend.keys.read(n * 4), np.uint32)
    order = np.frombuffer(rend.values.read(n * 4), np.uint32)
    z = rec[order, 2].astype(np.float64)
    assert np.all(np.diff(z) >= -1e-4 * np.abs(z[1:]))  # front to back, up to the 24-bit depth keys' resolution
    keys = np.frombuffer(cr.tile_keys.read(entries * 4), np.uint32)
    vals = np.frombuffer(cr.tile_values.read(entries * 4), np.uint32)
    ranges = np.frombuffer(cr.ranges.read(gx * gy * 8), np.uint32).reshape(-1, 2)

    # numpy model of bin_common.glsl (float64; the GPU's float32 may differ where a box edge meets a tile edge)
    c = rec[:, 0:2].astype(np.float64)
    op = rec[:, 3].astype(np.float64)
    a, b, cc = (rec[:, 4 + i].astype(np.float64) for i in range(3))
    det = a * cc - b * b
    k = np.sqrt(2 * np.log(np.maximum(op, 1 / 255) * 255))
    ext = k[:, None] * np.sqrt(np.stack([cc / det, a / det], axis=1))
    lo_f, hi_f = (c - ext) / 16, (c + ext) / 16
    grid = np.array([gx, gy])
    lo = np.clip(np.floor(lo_f), 0, grid).astype(np.int64)
    hi = np.maximum(np.clip(np.floor(hi_f) + 1, 0, grid).astype(np.int64), lo)
    near_edge = np.any((np.abs(lo_f - np.round(lo_f)) < 1e-4) | (np.abs(hi_f - np.round(hi_f)) < 1e-4), axis=1)

    # The GPU's rectangle of each record, from its entries.
    tx, ty = keys % gx, keys // gx
    got = {}
    for r_, x, y in zip(vals.tolist(), tx.tolist(), ty.tolist(), strict=True):
        got.setdefault(r_, []).append((x, y))
    row_binned = (hi[:, 1] - lo[:, 1] <= 2) & (hi[:, 0] - lo[:, 0] <= 127)  # bin_common.glsl's row_binned
    checked = whole = 0
    for r_ in range(n):
        want = {(x, y) for y in range(lo[r_, 1], hi[r_, 1]) for x in range(lo[r_, 0], hi[r_, 0])}
        have = got.get(r_, [])
        assert len(have) == len(set(have))
        if near_edge[r_]:
            continue
        if row_binned[r_]:
            assert set(have) <= want, r_
        else:
            assert set(have) == want, r_
            whole += 1
        checked += 1
    assert checked > 0.95 * n and whole > 0
    assert np.array_equal(splat_entries, [len(got.get(int(r_), [])) for r_ in order])

    # Stable by tile: keys ascending, and within a tile the splats in depth order.
    assert np.all(np.diff(keys.astype(np.int64)) >= 0)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    same_tile = keys[1:] == keys[:-1]
    assert np.all(rank[vals[1:]][same_tile] > rank[vals[:-1]][same_tile])
    # Tile ranges by boundary detection.
    starts = np.searchsorted(keys, np.arange(gx * gy), side="left")
    ends = np.searchsorted(keys, np.arange(gx * gy), side="right")
    nonempty = ends > starts
    assert np.array_equal(ranges[nonempty, 0], starts[nonempty])
    assert np.array_equal(ranges[nonempty, 1], ends[nonempty])
    assert np.all(ranges[~nonempty] == 0)
    renderer.unload()


def test_nothing_visible_and_empty_scene(renderer, fruit):
    base = suggested_camera(fruit.positions, width=W, height=H)
    eye = np.array(base.eye)
    away = eye + (eye - np.array(base.target))  # looking away from the scene
    cam = look_at(eye, away, fov_y_deg=40, width=W, height=H)
    renderer.load_gaussians(fruit)
    bg = (0.25, 0.5, 0.75)
    assert np.allclose(render_ref.render(fruit, cam, background=bg), bg)
    renderer.render(base)  # a frame with content first: nothing of it may remain
    img = renderer.render(cam, background=bg)
    assert renderer.renderer.read_visible_count() == 0
    assert renderer.renderer.read_bin_counts() == (0, 0)
    assert np.allclose(img, bg)
    assert np.allclose(renderer.renderer.read_image()[..., 3], 0.0)
    # A scene whose splats are all transparent (culled at opacity < 1/255).
    g = fruit.subset(np.arange(64))
    g.opacity_logits[:] = -8.0  # opacity 3.4e-4
    renderer.load_gaussians(g)
    img = renderer.render(base, background=bg)
    assert renderer.renderer.read_visible_count() == 0
    assert np.allclose(img, bg)


def test_entry_buffer_grows(renderer, fruit):
    cam = close_camera(fruit, 120, 90)
    ref = render_ref.render(fruit, cam)
    renderer.load_gaussians(fruit)
    rend = renderer.renderer
    cr = rend.craster
    cr.resize(cr.visible_capacity, 64)
    rend.check_bins_after(0)  # no automatic check: see the overflow
    renderer.render_frame(cam)
    entries, needed = rend.read_bin_counts()
    assert entries == 64 and needed > 64  # overflow: entries past the capacity dropped
    img = renderer.render(cam)  # HeadlessRenderer.render checks, grows and renders again
    assert cr.entry_capacity >= needed
    assert rend.read_bin_counts() == (needed, needed)
    assert psnr(img, ref) >= 40.0
    # The renderer's own check in the first frames after an allocation.
    cr.resize(cr.visible_capacity, 64)
    rend.check_bins_after(1)
    renderer.render_frame(cam)
    assert cr.entry_capacity >= needed
    assert psnr(rend.read_image()[..., :3], ref) >= 40.0
    # A frame loop's check reads an earlier frame's count (no wait) and grows at 85 % of the capacity, ahead of
    # an overflow: the count copied every COUNT_EVERY binnings, read two binnings after its copy.
    cr.resize(cr.visible_capacity, needed + needed // 10)  # 91 % full: no overflow, but over the 85 % mark
    rend.check_bins_after(0)
    cr._frames = 0
    renderer.render_frame(cam)
    assert not rend.check_bins() and cr.entry_capacity == needed + needed // 10  # one frame binned: nothing known
    renderer.render_frame(cam)
    assert not rend.check_bins()  # grew ahead; the frame had not overflowed: no second draw
    assert cr.entry_capacity >= needed + needed // 2
    renderer.render_frame(cam)
    assert not rend.check_bins()  # not a frame that reads the count
    cr.resize(cr.visible_capacity, 64)
    cr._frames = 0
    renderer.render_frame(cam)
    renderer.render_frame(cam)
    assert rend.check_bins()  # the counted frame overflowed: grown, draw again
    renderer.render_frame(cam)
    assert cr.entry_capacity >= needed and psnr(rend.read_image()[..., :3], ref) >= 40.0


def test_variants_and_modes(ctx, fruit):
    from client_gl.gpu.renderer import RenderOptions, is_software
    from client_gl.offscreen import HeadlessRenderer

    cam = close_camera(fruit, 120, 90)
    ref = render_ref.render(fruit, cam)
    variants = [dict(), dict(warp_cull=False)]
    for variant in variants:
        r = HeadlessRenderer(RenderOptions(draw="compute", color_dtype="f2", **variant), ctx=ctx)
        r.load_gaussians(fruit)
        assert psnr(r.render(cam), ref) >= 40.0, variant
        assert r.renderer.craster.tile_px == 16 and r.renderer.craster.warp_cull == variant.get("warp_cull", True)
        r.unload()
    # auto keeps the raster draws on a software GL; the compute draw needs the GPU sort
    r = HeadlessRenderer(RenderOptions(sort="gpu"), ctx=ctx)
    r.load_gaussians(fruit)
    r.render(cam)
    assert r.renderer.draw_mode == ("fetch" if is_software(ctx) else "compute")
    r.unload()
    with pytest.raises(UsageError, match="GPU sort"):
        HeadlessRenderer(RenderOptions(sort="cpu", draw="compute"), ctx=ctx)
    with pytest.raises(UsageError, match="raster-draw options"):
        RenderOptions(draw="compute", front_to_back=True)
    with pytest.raises(UsageError, match="options of the compute draw"):
        RenderOptions(draw="fetch", warp_cull=False)
    with pytest.raises(UsageError, match="unknown draw mode"):
        RenderOptions(draw="compute+t8")


def test_cli_draw_compute(ctx, tmp_path):
    out = tmp_path / "c.png"
    r = run_cli("render", real("fruit_drops_sh3.ply"), "--size", "64x48", "--draw", "compute", "--out", out)
    assert r.returncode == 0, r.stderr
    assert "draw compute" in r.stderr


def test_empty_pool(ctx, fruit):
    """No resident splats at all (a pool before any tile joined, or after all left)."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    scene = tiles_from_gaussians(fruit.subset(np.arange(300)))
    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, 2)
    r = SplatRenderer(ctx, pool, RenderOptions(sort="gpu", draw="compute"))
    cam = suggested_camera(fruit.positions, width=40, height=30)
    bg = (0.1, 0.2, 0.3)
    r.render(cam, background=bg)
    assert np.allclose(r.read_image()[..., :3], bg)
    for tile_id, tile in scene.tiles.items():  # join, render, leave: nothing of the splats may remain
        pool.join(tile_id, tile)
    r.render(cam, background=bg)
    assert r.read_visible_count() > 0
    for tile_id in scene.tiles:
        pool.leave(tile_id)
    r.render(cam, background=bg)
    assert r.read_visible_count() == 0 and r.read_bin_counts() == (0, 0)
    assert np.allclose(r.read_image()[..., :3], bg)
    r.release()
    pool.release()


def test_work_buffers_fixed_while_tiles_come_and_go(ctx, fruit):
    """The renderer sizes its work buffers once, for the pool's capacity: tiles joining and leaving reallocate
    nothing, and the image matches the reference of what is resident."""
    from client_gl.gpu.compute_raster import default_entries
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    small = tiles_from_gaussians(fruit.subset(np.arange(200)))
    g = fruit.subset(np.arange(200, len(fruit)))
    big = tiles_from_gaussians(g)
    pool = ChunkPool(ctx, small.formats, small.sh_degree, big.slots)
    r = SplatRenderer(ctx, pool, RenderOptions(sort="gpu", draw="compute"))
    buffers = (r.keys.glo, r.values.glo, r.records.glo, r.craster.gsum.glo, r.craster.tile_keys.glo)
    assert r.craster.visible_capacity == pool.splat_capacity == big.slots * 256
    assert r.craster.entry_capacity == default_entries(pool.splat_capacity)
    cam = suggested_camera(fruit.positions, width=W, height=H)
    for tile_id, tile in small.tiles.items():
        pool.join(tile_id, tile)
    r.render(cam)
    for tile_id in small.tiles:
        pool.leave(tile_id)
    for tile_id, tile in big.tiles.items():
        pool.join(tile_id + 1000, tile)
    assert pool.free_slots == 0
    r.render(cam)
    assert (r.keys.glo, r.values.glo, r.records.glo, r.craster.gsum.glo, r.craster.tile_keys.glo) == buffers
    entries, needed = r.read_bin_counts()
    assert entries == needed > 0
    assert psnr(r.read_image()[..., :3], render_ref.render(g, cam)) >= 40.0
    r.release()
    pool.release()


DENSE_VARIANTS = [dict(tile_radix_bits=8), dict(tile_radix_bits=4), dict(radix_bits=6, tile_radix_bits=5),
                  dict(radix_bits=4), dict(radix_bits=8, tile_radix_bits=8), dict(warp_cull=False)]


@pytest.mark.parametrize("variant", DENSE_VARIANTS, ids=lambda v: "+".join(f"{k}={v[k]}" for k in v))
def test_dense_variants_match_default(ctx, fruit, variant):
    """The measurement variants for dense scenes change how a frame is binned, sorted or submitted, never a pixel:
    the same image as the default, bit for bit, and the reference's. With 32-bit depth keys: the default's 24 bits
    tie splats of nearly equal depth, which the cull's compaction (atomics) then orders differently from run to run."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer

    cam = close_camera(fruit, 120, 90)
    images, bins = [], []
    base = RenderOptions(draw="compute", depth_bits=32)
    for options in (base, replace(base, **variant)):
        r = HeadlessRenderer(options, ctx=ctx)
        r.load_gaussians(fruit)
        images.append(r.render(cam))
        bins.append(r.renderer.read_bin_counts())
        r.unload()
    assert np.array_equal(images[0], images[1])
    assert psnr(images[1], render_ref.render(fruit, cam)) >= 40.0
    default_entries_, variant_entries = bins[0][0], bins[1][0]
    assert bins[1][0] == bins[1][1]
    assert variant_entries == default_entries_


@pytest.mark.parametrize("bits, min_db", [(32, 120.0), (16, 70.0)])
def test_depth_keys_of_fewer_bits(ctx, fruit, bits, min_db):
    """Depth keys of 24 bits (the default) or 16 (depth_key_range between the near and far planes) sort as the
    32-bit float bits do but for depths closer than their resolution: 24 bits change no pixel by more than float
    rounding (136 dB against 32 bits on this close view), 16 bits by 75 dB; both keep the reference's 40 dB."""
    from client_gl.gpu.renderer import RenderOptions, depth_key_range
    from client_gl.offscreen import HeadlessRenderer

    cam = close_camera(fruit, 120, 90)
    lo, shift, top = depth_key_range(cam.near, cam.far, bits)
    assert top == (1 << bits) - 1 and (int(np.float32(cam.far).view(np.uint32)) - lo) >> shift <= top
    assert shift == 0 or (int(np.float32(cam.far).view(np.uint32)) - lo) >> (shift - 1) > top  # the smallest shift
    images = []
    for options in (RenderOptions(draw="compute"), RenderOptions(draw="compute", depth_bits=bits)):
        r = HeadlessRenderer(options, ctx=ctx)
        r.load_gaussians(fruit)
        images.append(r.render(cam))
        r.unload()
    assert psnr(images[1], images[0]) >= min_db
    assert psnr(images[1], render_ref.render(fruit, cam)) >= 40.0


def test_row_bins_keep_every_reached_tile(ctx, fruit):
    """Row bins: each splat's entries are the tiles of its box where its alpha reaches 1/255 at a pixel centre
    (numpy, float64), in (tile, depth) order, no tile twice; tiles that the ellipse misses even between the pixel
    centres (the shaders bound the rectangle of pixel centres, not the centres one by one) are not entries, except
    for splats whose box is more than two tiles high (their whole box)."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer

    cam = close_camera(fruit, 120, 90)
    r = HeadlessRenderer(RenderOptions(draw="compute"), ctx=ctx)
    r.load_gaussians(fruit)
    r.render(cam)
    rend = r.renderer
    cr = rend.craster
    n = rend.read_visible_count()
    entries, needed = rend.read_bin_counts()
    gx, gy = cr.grid
    rec = np.frombuffer(rend.records.read(n * 48), np.float32).reshape(n, 12).astype(np.float64)
    order = np.frombuffer(rend.values.read(n * 4), np.uint32)
    keys = np.frombuffer(cr.tile_keys.read(entries * 4), np.uint32)
    vals = np.frombuffer(cr.tile_values.read(entries * 4), np.uint32)
    r.unload()
    assert entries == needed > 0
    assert np.all(np.diff(keys.astype(np.int64)) >= 0)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    same_tile = keys[1:] == keys[:-1]
    assert np.all(rank[vals[1:]][same_tile] > rank[vals[:-1]][same_tile])
    got = set(zip(vals.tolist(), keys.tolist(), strict=True))
    assert len(got) == entries

    c, op = rec[:, 0:2], rec[:, 3]
    a, b, cc = rec[:, 4], rec[:, 5], rec[:, 6]
    valid = a * cc - b * b > 0
    lim = np.log(np.maximum(op, 1 / 255) * 255)  # alpha >= 1/255 where power >= -lim, power = -Q / 2

    def q(dx, dy):
        return a * dx * dx + 2 * b * dx * dy + cc * dy * dy

    # only boxes surely at most two tiles high (a margin over float32) are row-binned
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.sqrt(2 * lim)
        det = a * cc - b * b
        ey, ex = k * np.sqrt(a / det) * 1.001 + 1e-3, k * np.sqrt(cc / det) * 1.001 + 1e-3
    rows = np.floor((c[:, 1] + ey) / 16) - np.floor((c[:, 1] - ey) / 16) + 1
    cols = np.floor((c[:, 0] + ex) / 16) - np.floor((c[:, 0] - ex) / 16) + 1
    row_binned = (rows <= 2) & (cols <= 127)
    assert row_binned.sum() > 0.5 * valid.sum()
    offs = np.arange(16) + 0.5
    reached = 0
    for t in range(gx * gy):
        x0, y0 = (t % gx) * 16 + 0.5, (t // gx) * 16 + 0.5
        # at the pixel centres
        dx = (x0 - 0.5 + offs)[None, None, :] - c[:, 0, None, None]
        dy = (y0 - 0.5 + offs)[None, :, None] - c[:, 1, None, None]
        power = -0.5 * (a[:, None, None] * dx * dx + cc[:, None, None] * dy * dy) - b[:, None, None] * dx * dy
        best = power.reshape(n, -1).max(axis=1) + lim
        # over the rectangle of the pixel centres (0 inside; else the clamped minima along the four edges)
        lo_x, lo_y, hi_x, hi_y = x0 - c[:, 0], y0 - c[:, 1], x0 + 15 - c[:, 0], y0 + 15 - c[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            qmin = np.minimum.reduce([
                q(lo_x, np.clip(-b * lo_x / cc, lo_y, hi_y)), q(hi_x, np.clip(-b * hi_x / cc, lo_y, hi_y)),
                q(np.clip(-b * lo_y / a, lo_x, hi_x), lo_y), q(np.clip(-b * hi_y / a, lo_x, hi_x), hi_y)])
        inside = (lo_x <= 0) & (hi_x >= 0) & (lo_y <= 0) & (hi_y >= 0)
        qmin[inside] = 0.0
        have = np.array([(i, t) in got for i in range(n)])
        must = valid & (best >= 1e-3)  # reached at a pixel centre: an entry
        must_not = valid & row_binned & (0.5 * qmin > lim + 0.05)  # missed by the whole rectangle
        assert np.all(have[must]), t
        assert not np.any(have[must_not]), t
        reached += int(must.sum())
    assert reached > 0.7 * entries


def test_wide_flat_splat_keeps_its_tiles(ctx):
    """A splat two tiles high and 128 or more wide (a thin streak across a 4096-pixel image): row bins pack its rows'
    bounds in 7 bits each, so a wider one keeps its whole box; its entries and the image are the reference's."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer
    from splatstream.gaussians import Gaussians

    g = Gaussians(positions=np.zeros((1, 3)), rotations=np.array([[1.0, 0.0, 0.0, 0.0]]),
                  log_scales=np.log([[40.0, 0.05, 0.05]]), opacity_logits=np.array([4.0]),
                  sh_dc=np.array([[1.0, 0.5, -0.5]]), sh_rest=np.zeros((1, 0, 3)))
    cam = look_at((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov_y_deg=60, width=4096, height=64)
    r = HeadlessRenderer(RenderOptions(draw="compute"), ctx=ctx)
    r.load_gaussians(g)
    img = r.render(cam)
    entries, needed = r.renderer.read_bin_counts()
    r.unload()
    ref = render_ref.render(g, cam)
    lit = ref.max(axis=2) > 0.05
    assert lit.any(axis=0).sum() > 1900 and entries == needed  # its box: 181 tiles wide, rows 1 and 2
    assert psnr(img, ref) >= 40.0


@pytest.mark.parametrize("view", ["close", "far"])
def test_warp_cull_walks_and_loops_alike(ctx, fruit, view):
    """The per-block splat lists (warp_cull, the default) give the plain loop's image bit for bit, on a close view
    (large splats: most blocks walk their whole batch) and a far one (small splats: blocks walk their own bits)."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer

    base = suggested_camera(fruit.positions, width=W, height=H)
    far = look_at(np.array(base.target) + 2.5 * (np.array(base.eye) - np.array(base.target)), base.target,
                  fov_y_deg=50, width=160, height=128)
    cam = close_camera(fruit, 120, 90) if view == "close" else far
    images = []
    for warp_cull in (True, False):
        r = HeadlessRenderer(RenderOptions(draw="compute", depth_bits=32, warp_cull=warp_cull), ctx=ctx)
        r.load_gaussians(fruit)
        images.append(r.render(cam))
        r.unload()
    assert np.array_equal(images[0], images[1])
    assert images[0].std() > 0.02  # the view holds the scene, not only background


def test_auto_draw_defers_compute_programs(ctx, fruit, monkeypatch):
    """draw="auto" on a hardware GL (issue 38): the first frame draws "fetch" with 7 programs compiled (the pool's,
    cull, the depth sort's 4, the fetch draw's) instead of 16 (and the compute draw's 9); those 9 compile one a
    frame (a zero budget) after the first frame with splats, then the draw switches to "compute" and its picture
    equals that of a renderer that compiled them all up front."""
    from client_gl.gpu import renderer as renderer_mod
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.renderer import RenderOptions, SplatRenderer
    from client_gl.scene import tiles_from_gaussians

    compiled = []
    for name in ("compute_shader", "program"):
        original = getattr(type(ctx), name)

        def counting(self, *args, _original=original, **kwargs):
            compiled.append(1)
            return _original(self, *args, **kwargs)
        monkeypatch.setattr(type(ctx), name, counting)
    monkeypatch.setattr(renderer_mod, "DEFERRED_COMPILE_BUDGET_S", 0.0)
    monkeypatch.setattr(ctx, "extra", dict(ctx.extra or {}))
    scene = tiles_from_gaussians(fruit)
    cam = close_camera(fruit, W, H)

    def fresh_renderer(options):
        for key in [k for k in ctx.extra if k[0] == "compute_program"]:  # the shared sort programs compile again
            del ctx.extra[key]
        compiled.clear()
        pool = ChunkPool(ctx, scene.formats, scene.sh_degree, scene.slots)
        for tile_id, tile in scene.tiles.items():
            pool.join(tile_id, tile)
        r = SplatRenderer(ctx, pool, options)
        r._software = False  # the auto choices of a hardware GL on llvmpipe too
        return r, pool

    up_front, pool_a = fresh_renderer(RenderOptions(sort="gpu", defer_compute=False))
    up_front.render(cam)
    assert up_front.draw_mode == "compute" and len(compiled) == 15
    want = up_front.read_image()
    deferred, pool_b = fresh_renderer(RenderOptions(sort="gpu"))
    deferred.render(cam)
    assert deferred.draw_mode == "fetch" and deferred.craster is None and len(compiled) == 6
    first = deferred.read_image()
    assert psnr(first[..., :3], want[..., :3]) >= 40.0  # the same splats blended back to front, raster draw
    modes = []
    for _ in range(9):
        deferred.render(cam)
        modes.append(deferred.draw_mode)
    assert modes == ["fetch"] * 8 + ["compute"] and len(compiled) == 15
    # Equal up to the compute draw's own frame-to-frame noise: cull's atomic compaction orders depth-key ties by
    # thread timing (an up-front renderer's frames differed from its first by up to 1.1e-5 here).
    assert np.abs(deferred.read_image() - want).max() <= 1e-4
    deferred.render(cam)  # warm: nothing compiles, the picture stays
    assert deferred.draw_mode == "compute" and len(compiled) == 15
    assert np.abs(deferred.read_image() - want).max() <= 1e-4
    for r, pool in ((up_front, pool_a), (deferred, pool_b)):
        r.release()
        pool.release()
