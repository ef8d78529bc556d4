"""The GPU pool as the streaming client drives it: tiles join with their base and gain SH bands later (with and
without an SH codebook), the per-frame draw set hides tiles, and GPU bytes stay within the budget the pool was made
for. Renders are compared with the same tiles loaded whole, on both sort paths."""
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

K = 300  # SH codebook entries
W, H = 128, 96
BASE = ("position", "rotation", "scale", "color")


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))


@pytest.fixture(scope="module")
def scenes(fruit):
    """Per kind (SH bands as planes, or an SH codebook) the two leaf tiles of fruit_drops (2360 and 2361 splats,
    10 slots each), sharing the scene's formats and codebook: (scene, tile a, tile b)."""
    from client_gl.scene import tiles_from_scene
    from splatstream.encode import EncodeOptions, encode_in_memory

    out = {}
    for kind, codebook in (("bands", "off"), ("codebook", K)):
        opts = EncodeOptions(preset="medium", sh_codebook=codebook, lod=True, max_leaf_splats=2500)
        scene = tiles_from_scene(encode_in_memory(fruit, opts))
        assert (scene.codebook is not None) == (kind == "codebook") and len(scene.tiles) == 2
        a, b = scene.tiles.values()
        out[kind] = (scene, a, b)
    return out


@pytest.fixture(scope="module")
def sorts(gl_context):
    """Render paths: the CPU sort, the GPU sort with the raster draw "auto" picks (fetch on llvmpipe), the compute
    rasterizer."""
    return ("cpu", "gpu", "compute") if gl_context.version_code >= 430 else ("cpu",)


def _options(sort: str):
    from client_gl.gpu.renderer import RenderOptions

    return RenderOptions(draw="compute") if sort == "compute" else RenderOptions(sort=sort)


def _pool(ctx, scene, slots: int, codebook_bands: int | None = None):
    from client_gl.gpu.pool import ChunkPool

    pool = ChunkPool(ctx, scene.formats, scene.sh_degree, slots, codebook=scene.codebook_layout)
    for band in range(1, (3 if codebook_bands is None else codebook_bands) + 1) if scene.codebook else ():
        pool.set_codebook_band(band, scene.codebook[f"sh{band}"])
    return pool


def _base(tile):
    from client_gl.tiledata import TileData

    return TileData(tile.splats, {name: tile.planes[name] for name in BASE}, tile.mirror)


def _slots(tile) -> int:
    return -(-tile.splats // 256)


def _band(scene, tile, band: int) -> dict:
    """What add_band takes for band `band` (scene.load_band reads the same from a store)."""
    if scene.codebook is not None:
        return {"sh_index": tile.planes["sh_index"]} if band == 1 else {}
    return {f"sh{band}": tile.planes[f"sh{band}"]}


def _same(img, ref, sort: str, what) -> None:
    """The CPU path draws in a deterministic order: bit-identical. The GPU paths compact visible splats with
    atomics, so splats at exactly equal depths may swap: >= 60 dB (measured on llvmpipe: bit-identical too)."""
    if sort == "cpu":
        np.testing.assert_array_equal(img, ref, err_msg=str(what))
    else:
        assert psnr(img, ref) >= 60.0, (what, psnr(img, ref))


@pytest.mark.parametrize("kind", ["bands", "codebook"])
def test_bands_join_later(gl_context, scenes, sorts, fruit, kind):
    """A tile joins with its base only and gains SH bands 1, 2, 3 later: with bands 0..k resident the render equals
    the whole tile's render at SH degree k, with all of them the whole tile's; dropping bands goes back."""
    from client_gl.gpu.renderer import SplatRenderer

    scene, tile, _ = scenes[kind]
    cam = suggested_camera(tile.mirror.positions, width=W, height=H)
    whole = _pool(gl_context, scene, _slots(tile))
    whole.join(7, tile)
    assert whole.tile_bands(7) == 3
    later = _pool(gl_context, scene, _slots(tile))
    for sort in sorts:
        r_whole = SplatRenderer(gl_context, whole, _options(sort))
        r_later = SplatRenderer(gl_context, later, _options(sort))
        refs = []
        for degree in range(4):
            r_whole.render(cam, sh_degree=degree)
            refs.append(r_whole.read_image())
        assert all(psnr(refs[d], refs[d + 1]) < 50 for d in range(3))  # every band changes the picture
        later.join(7, _base(tile))
        assert later.tile_bands(7) == 0
        for band in range(1, 4):
            r_later.render(cam)  # the pool's SH degree (3) requested, bands 0..band-1 resident
            _same(r_later.read_image(), refs[band - 1], sort, (kind, "bands", band - 1))
            later.add_band(7, band, _band(scene, tile, band))
            assert later.tile_bands(7) == band
        r_later.render(cam)
        _same(r_later.read_image(), refs[3], sort, (kind, "all bands"))
        r_later.render(cam, sh_degree=1)  # a lower request still wins
        _same(r_later.read_image(), refs[1], sort, (kind, "requested 1"))
        assert later.drop_band(7) == 2  # the highest band goes first
        r_later.render(cam)
        _same(r_later.read_image(), refs[2], sort, (kind, "dropped to 2"))
        later.leave(7)  # a tile leaves with all its bands
        assert 7 not in later and later.free_slots == later.capacity_slots
        r_later.release()
        r_whole.release()
    whole.release()
    later.release()


def _reference_values(scene, tile, degree: int):
    """Decoded values of a tile with SH bands above `degree` zero (not resident: not evaluated)."""
    from splatstream.format.codec import assemble_gaussians, decode_index_plane, decode_plane

    v = {name: decode_plane(tile.planes[name], tile.splats) for name in BASE}
    for band in (1, 2, 3):
        if scene.codebook is not None:
            idx = decode_index_plane(tile.planes["sh_index"], tile.splats)
            v[f"sh{band}"] = decode_plane(scene.codebook[f"sh{band}"], K)[idx]
        else:
            v[f"sh{band}"] = decode_plane(tile.planes[f"sh{band}"], tile.splats)
        if band > degree:
            v[f"sh{band}"] = np.zeros_like(v[f"sh{band}"])
    return assemble_gaussians(v, 3)


@pytest.mark.parametrize("kind", ["bands", "codebook"])
def test_tiles_at_different_bands(gl_context, scenes, sorts, fruit, kind):
    """The band count is per slot: a tile at SH degree 3 beside one at degree 1 (whose bands 2 and 3 were uploaded
    and dropped again, so their data is still in its slots) renders like the reference of that mix."""
    from client_gl.gpu.renderer import SplatRenderer
    from splatstream.gaussians import Gaussians

    cam = suggested_camera(fruit.positions, width=W, height=H)
    scene, a, b = scenes[kind]
    mix = Gaussians.concatenate([_reference_values(scene, a, 3), _reference_values(scene, b, 1)])
    wrong = Gaussians.concatenate([_reference_values(scene, a, 3), _reference_values(scene, b, 3)])
    ref, ref_wrong = render_ref.render(mix, cam), render_ref.render(wrong, cam)
    assert psnr(ref, ref_wrong) < 50  # the test can tell them apart
    pool = _pool(gl_context, scene, _slots(a) + _slots(b))
    pool.join(1, a)
    pool.join(2, _base(b))
    for band in (1, 2, 3):
        pool.add_band(2, band, _band(scene, b, band))
    pool.drop_band(2)
    pool.drop_band(2)
    assert (pool.tile_bands(1), pool.tile_bands(2)) == (3, 1)
    for sort in sorts:
        r = SplatRenderer(gl_context, pool, _options(sort))
        r.render(cam)
        assert psnr(r.read_image()[..., :3], ref) >= 70.0, (kind, sort, psnr(r.read_image()[..., :3], ref))
        r.release()
    pool.release()


def test_codebook_bands_arrive_in_order(gl_context, scenes, sorts, fruit):
    """With an SH codebook a tile renders at most the bands the codebook has uploaded: with band 1 only a whole tile
    renders as at SH degree 1, then 2."""
    from client_gl.gpu.renderer import SplatRenderer

    scene, a, _ = scenes["codebook"]
    cam = suggested_camera(fruit.positions, width=W, height=H)
    full = _pool(gl_context, scene, _slots(a))
    full.join(1, a)
    empty = _pool(gl_context, scene, 1, codebook_bands=0)
    with pytest.raises(UsageError, match="band 3 before band 1"):
        empty.set_codebook_band(3, scene.codebook["sh3"])
    empty.release()
    for sort in sorts:
        partial = _pool(gl_context, scene, _slots(a), codebook_bands=1)
        partial.join(1, a)
        assert partial.codebook_bands == 1 and partial.tile_bands(1) == 3
        r_full = SplatRenderer(gl_context, full, _options(sort))
        r_partial = SplatRenderer(gl_context, partial, _options(sort))
        r_full.render(cam, sh_degree=1)
        r_partial.render(cam)
        _same(r_partial.read_image(), r_full.read_image(), sort, "codebook band 1 only")
        partial.set_codebook_band(2, scene.codebook["sh2"])
        r_full.render(cam, sh_degree=2)
        r_partial.render(cam)
        _same(r_partial.read_image(), r_full.read_image(), sort, "codebook bands 1..2")
        r_full.release()
        r_partial.release()
        partial.release()
    full.release()


def test_draw_set_hides_tiles(gl_context, scenes, sorts, fruit):
    """Hiding a tile with the draw set renders exactly as if it were not resident; a tile joining while the draw
    set leaves it out stays hidden; None draws everything again."""
    from client_gl.gpu.renderer import SplatRenderer

    scene, a, b = scenes["bands"]
    cam = suggested_camera(fruit.positions, width=W, height=H)
    for sort in sorts:
        pool = _pool(gl_context, scene, _slots(a) + _slots(b))
        r = SplatRenderer(gl_context, pool, _options(sort))
        pool.join(1, a)
        pool.join(2, b)
        r.render(cam)
        both = r.read_image()
        visible = {}
        for draw_set in ({2}, {1}, set()):
            r.render(cam, draw_set=draw_set)
            visible[frozenset(draw_set)] = r.read_visible_count() if sort != "cpu" else None
            assert pool.drawn_splats == sum(t.splats for i, t in ((1, a), (2, b)) if i in draw_set)
        r.render(cam, draw_set={2, 99})  # ids that are not resident are ignored
        hidden = r.read_image()
        assert psnr(hidden, both) < 40  # tile 1 is gone from the picture
        r.render(cam, draw_set=set())
        assert np.array_equal(r.read_image(), np.zeros_like(both))  # nothing drawn: background, alpha 0
        r.render(cam, draw_set=None)
        _same(r.read_image(), both, sort, "all again")
        pool.set_draw_set({2})
        pool.leave(1)
        r.render(cam, draw_set={2})
        _same(r.read_image(), hidden, sort, "hidden == not resident")
        r.render(cam)
        _same(r.read_image(), hidden, sort, "draw set None after the leave")
        pool.set_draw_set({2})
        pool.join(3, a)  # not in the draw set: joins hidden
        r.render(cam, draw_set={2})
        _same(r.read_image(), hidden, sort, "joined hidden")
        r.render(cam, draw_set={2, 3})
        _same(r.read_image(), both, sort, "shown")
        if sort != "cpu":
            assert visible[frozenset()] == 0 and visible[frozenset({1})] > 0 and visible[frozenset({2})] > 0
            assert r.read_visible_count() == visible[frozenset({1})] + visible[frozenset({2})]
        r.release()
        pool.release()


@pytest.mark.parametrize("kind", ["bands", "codebook"])
def test_pool_within_its_gpu_budget(gl_context, scenes, kind):
    """A pool made for a GPU byte budget never allocates more, however tiles and bands come and go; a tile that
    does not fit raises and changes nothing."""
    from client_gl.gpu.pool import ChunkPool
    from client_gl.gpu.residency_layout import PoolLayout

    scene, a, b = scenes[kind]
    layout = PoolLayout(scene.formats, scene.sh_degree, scene.codebook_layout)
    per_slot, fixed = layout.slot_bytes(), layout.fixed_bytes()
    budget = fixed + (_slots(a) + 3) * per_slot + per_slot // 2  # room for tile a and 3 slots more
    pool = ChunkPool.for_budget(gl_context, budget, scene.formats, scene.sh_degree, codebook=scene.codebook_layout)
    for band in range(1, 4) if scene.codebook else ():
        pool.set_codebook_band(band, scene.codebook[f"sh{band}"])
    assert pool.capacity_slots == _slots(a) + 3
    assert budget - per_slot < pool.gpu_bytes <= budget
    bytes_made = pool.gpu_bytes
    pool.join(1, _base(a))
    with pytest.raises(UsageError, match="10 slots needed, 3 of 13 are free"):
        pool.join(2, b)
    assert pool.tile_ids == (1,) and pool.free_slots == 3
    for band in (1, 2, 3):
        pool.add_band(1, band, _band(scene, a, band))
    pool.set_draw_set(set())
    pool.drop_band(1)
    pool.leave(1)
    pool.join(2, _base(b))
    assert pool.gpu_bytes == bytes_made <= budget
    pool.release()


@pytest.mark.parametrize("kind", ["bands", "codebook"])
def test_band_and_join_errors(gl_context, scenes, kind):
    from client_gl.gpu.pool import ChunkPool

    scene, tile, _ = scenes[kind]
    pool = _pool(gl_context, scene, _slots(tile))
    pool.join(1, _base(tile))
    with pytest.raises(UsageError, match="bands join in order, the next is 1"):
        pool.add_band(1, 2, _band(scene, tile, 2))
    with pytest.raises(UsageError, match="no SH band resident"):
        pool.drop_band(1)
    with pytest.raises(UsageError, match="not resident"):
        pool.add_band(5, 1, _band(scene, tile, 1))
    with pytest.raises(UsageError, match="already resident"):
        pool.join(1, tile)
    pool.add_band(1, 1, _band(scene, tile, 1))
    if kind == "codebook":
        with pytest.raises(UsageError, match="comes from the SH codebook"):
            pool.add_band(1, 2, {"sh2": scene.codebook["sh2"]})
    else:
        with pytest.raises(UsageError, match="has no sh2 plane"):
            pool.add_band(1, 2, {})
        other = ChunkPool(gl_context, dict(scene.formats, sh="f32x4"), 3, _slots(tile))
        try:
            other.join(1, _base(tile))
            other.add_band(1, 1, {"sh1": _band_as(tile, 1)})
            with pytest.raises(UsageError, match="sh2 is norm565, this pool holds f32x4"):
                other.add_band(1, 2, _band(scene, tile, 2))
            assert other.tile_bands(1) == 1
        finally:
            other.release()
    pool.add_band(1, 2, _band(scene, tile, 2))
    pool.add_band(1, 3, _band(scene, tile, 3))
    with pytest.raises(UsageError, match="band 4"):
        pool.add_band(1, 4, {})
    assert pool.tile_bands(1) == 3
    pool.release()


def _band_as(tile, band: int):
    """Band `band` of a tile re-encoded as f32x4 (for a pool of other formats)."""
    from splatstream.format.codec import decode_plane, encode_plane
    from splatstream.format.planes import band_plane

    values = decode_plane(tile.planes[f"sh{band}"], tile.splats)
    return encode_plane(values, band_plane(band), "f32x4")


def test_work_buffers_grow_with_what_is_drawn(gl_context, scenes, sorts, fruit, monkeypatch):
    """The renderer's per-frame work buffers follow the slots the pool holds, not its capacity (a large pool made
    for a GPU budget does not make gigabytes of scratch), and a frame after they grew draws what a renderer made
    for the whole set draws."""
    from client_gl.gpu import renderer as renderer_module
    from client_gl.gpu.renderer import SplatRenderer

    monkeypatch.setattr(renderer_module, "MIN_WORK_SPLATS", 256)
    scene, a, b = scenes["bands"]
    cam = suggested_camera(fruit.positions, width=W, height=H)
    for sort in [s for s in sorts if s != "cpu"]:
        pool = _pool(gl_context, scene, 4096)  # about a million splats of capacity
        grown = SplatRenderer(gl_context, pool, _options(sort))
        small = grown.work_bytes
        pool.join(1, a)
        grown.render(cam)
        after_a = grown.work_bytes
        pool.join(2, b)
        grown.render(cam)
        # (made for the pool's capacity of 1M splats they would take about 130 MB)
        assert small < after_a < grown.work_bytes < 4 << 20, (sort, small, after_a, grown.work_bytes)
        whole = SplatRenderer(gl_context, pool, _options(sort))  # made with both tiles resident
        whole.render(cam)
        _same(grown.read_image(), whole.read_image(), sort, "grown work buffers")
        assert grown.read_visible_count() == whole.read_visible_count() > 0
        grown.release()
        whole.release()
        pool.release()


def test_work_buffers_reserved_for_a_budget_do_not_grow(gl_context, scenes, sorts, fruit, monkeypatch):
    """reserve_work (a streaming session's splat budget, before its first frame): the work buffers are made for the
    budget at once, no frame up to it grows them, and the pictures are those of buffers grown frame by frame."""
    from client_gl.gpu import renderer as renderer_module
    from client_gl.gpu.renderer import SplatRenderer

    monkeypatch.setattr(renderer_module, "MIN_WORK_SPLATS", 256)
    scene, a, b = scenes["bands"]
    cam = suggested_camera(fruit.positions, width=W, height=H)
    for sort in [s for s in sorts if s != "cpu"]:
        pool = _pool(gl_context, scene, 4096)
        reserved = SplatRenderer(gl_context, pool, _options(sort))
        grown = SplatRenderer(gl_context, pool, _options(sort))
        reserved.reserve_work(a.splats + b.splats)
        assert reserved._work_splats == a.splats + b.splats
        entries = reserved.craster.entry_capacity if reserved.craster is not None else None
        allocations = []
        allocate = reserved._allocate_work
        monkeypatch.setattr(reserved, "_allocate_work",
                            lambda n, log=allocations, allocate=allocate: (log.append(n), allocate(n)))
        for tile_id, tile in ((1, a), (2, b)):
            pool.join(tile_id, tile)
            reserved.render(cam)
            grown.render(cam)
            _same(reserved.read_image(), grown.read_image(), sort, f"reserved work buffers, {tile_id} tiles")
        assert allocations == [] and reserved._work_splats == a.splats + b.splats
        assert (reserved.craster.entry_capacity if reserved.craster is not None else None) == entries
        assert grown._work_splats > reserved._work_splats  # doubled ahead of what it drew
        reserved.reserve_work(10)  # never shrinks
        assert reserved._work_splats == a.splats + b.splats
        for r in (reserved, grown):
            r.release()
        pool.release()


def test_work_buffers_and_primed_atlases(gl_context):
    """Work buffers on immutable storage (gl.work_buffer) write, read back and bind like moderngl's, and release
    once; a new pool's uncompressed atlases get one texel from a shader (prime_texels.comp) and still upload and
    read what a tile puts there (the pool tests above draw through them)."""
    from client_gl.gpu.gl import WorkBuffer, gl_version, work_buffer
    from client_gl.gpu.pool import ChunkPool

    ctx = gl_context
    buf = work_buffer(ctx, 1 << 20)
    if gl_version() >= 44:
        assert isinstance(buf, WorkBuffer)
    buf.write(b"splatstream", offset=4096)
    assert buf.read(11, offset=4096) == b"splatstream" and buf.size == 1 << 20
    buf.bind_to_storage_buffer(0)
    buf.release()
    buf.release()  # a second release is a no-op, as moderngl's
    formats = {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"}
    pool = ChunkPool.for_budget(ctx, 16 << 20, formats, 0, host_mirror=False)
    try:
        assert pool.gpu_bytes <= 16 << 20
    finally:
        pool.release()


def test_two_output_targets(gl_context, scenes, fruit):
    """next_output_target: frames go to the other of two framebuffers (a window shows one while the next is drawn);
    each holds the frame drawn into it and read_image reads the last one drawn."""
    from client_gl.offscreen import HeadlessRenderer, RenderOptions

    r = HeadlessRenderer(RenderOptions(), ctx=gl_context)
    r.load_gaussians(fruit)
    cam = suggested_camera(fruit.positions, width=96, height=64)
    try:
        first = r.render(cam)
        fbo0 = r.renderer.framebuffer(96, 64)
        img0 = r.renderer.read_image()
        r.renderer.next_output_target()
        blue = r.render(cam, background=(0.0, 0.0, 1.0))  # a different picture into the second target
        fbo1 = r.renderer.framebuffer(96, 64)
        assert fbo0.glo != fbo1.glo
        assert not np.array_equal(first, blue)
        r.renderer.next_output_target()
        assert r.renderer.framebuffer(96, 64).glo == fbo0.glo
        np.testing.assert_array_equal(r.renderer.read_image(), img0)  # the first target kept its frame
    finally:
        r.renderer.output_target = 0
        r.unload()
