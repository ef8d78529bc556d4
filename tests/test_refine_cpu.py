"""The CPU refinement of the merged LOD levels (refine_cpu/, `encode --lod-refine cpu`, lod.md 6): its numba
rasteriser against the numpy reference (render_ref), its gradients against finite differences, and the refiner on a
small real scene."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from conftest import real

pytest.importorskip("numba")

from refine_cpu import raster  # noqa: E402
from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings  # noqa: E402
from splatstream import render_ref  # noqa: E402
from splatstream.camera import Camera, scene_orbit_views  # noqa: E402
from splatstream.format.layout import morton_order  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.lod import build_tiles  # noqa: E402
from splatstream.lod_refine import VARIANT_FIELDS, level_cuts, refine_cameras  # noqa: E402
from splatstream.sh import eval_sh, view_directions  # noqa: E402


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))  # 4,721 splats, SH3


@pytest.fixture(scope="module")
def part(fruit):
    return fruit.subset(morton_order(fruit.positions)[:1500])


def psnr(a, b) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * np.log10(1 / mse) if mse > 0 else np.inf


def test_forward_matches_the_numpy_reference(fruit):
    for cam in scene_orbit_views(fruit.positions, 3, 80, 64, elevation_deg=25.0):
        ref = render_ref.render(fruit, cam)
        mine = raster.render(fruit, cam)
        assert mine.shape == ref.shape == (64, 80, 3) and ref.max() > 0.2
        assert psnr(mine, ref) > 60.0


def numpy_projection(g, cam, sh_degree=None):
    """raster.project's arrays by the numpy path it replaced: render_ref.preprocess, tile_lists, eval_sh."""
    p = render_ref.preprocess(g, cam, sh_degree)
    ids, offsets = render_ref.tile_lists(p, -(-cam.width // render_ref.TILE), -(-cam.height // render_ref.TILE))
    base = eval_sh(np.zeros((len(p.index), 3)), g.sh_rest[p.index],
                   view_directions(g.positions[p.index], np.asarray(cam.eye)), sh_degree, clamp=False)
    return {"index": p.index, "xy": p.xy, "conic": p.conic, "base": base, "tile_ids": ids, "tile_offsets": offsets}


def test_the_compiled_projection_is_the_numpy_paths_bit_for_bit(fruit):
    # every array equal, not close: a last bit moved in a full-detail render or a pair's weight would move the
    # refined scene's bytes. The refiner's own cameras, one inside the scene (splats behind it culled), another size,
    # and a lowered SH degree.
    cams = refine_cameras(fruit.positions, (0.0, 1.0, 0.0), 4, 96, seed=3)
    centre = np.median(fruit.positions, axis=0).astype(np.float64)
    inside = Camera(tuple(centre), tuple(centre + [1.0, 0.0, 0.0]), (0.0, 1.0, 0.0), 60.0, 80, 48, 0.01, 100.0)
    for cam, degree in [*((c, None) for c in cams), (inside, None), (cams[0], 1)]:
        mine = raster.project(fruit, cam, degree)
        ref = numpy_projection(fruit, cam, degree)
        assert 0 < len(ref["index"]) < (len(fruit) // 2 + 1 if cam is inside else len(fruit) + 1)
        for name, want in ref.items():
            got = getattr(mine, name)
            assert got.dtype == want.dtype and got.shape == want.shape, name
            assert np.array_equal(got.view(np.uint8), np.ascontiguousarray(want).view(np.uint8)), name
        assert np.array_equal(raster.render(fruit, cam, degree), raster.render_projection(
            raster.Projection(**ref, width=cam.width, height=cam.height),
            fruit.opacities.astype(np.float64)[ref["index"]], raster.colours_of(mine, fruit.sh_dc)))


def test_the_tile_binning_is_the_same_in_any_number_of_runs():
    # raster._bin_tiles fills each tile from consecutive runs of the depth order in parallel (one run per thread at
    # 65,536 projected splats and more): the same lists as one run and as render_ref.tile_lists' stable argsort
    rng = np.random.default_rng(7)
    grid_x, grid_y, n = 7, 5, 3000
    lo = np.stack([rng.integers(0, grid_x, n), rng.integers(0, grid_y, n)], axis=1)
    hi = lo + rng.integers(0, 3, (n, 2))  # some rectangles empty, some past the grid (the kernel clips them first)
    hi = np.minimum(hi, [grid_x, grid_y])
    rect = np.concatenate([lo, hi], axis=1).astype(np.int64)
    order = rng.permutation(n)[: n - 100]
    p = render_ref.Projected(index=order, xy=None, depth=None, conic=None, opacity=None, radius=None,
                             rect_min=rect[order, :2], rect_max=rect[order, 2:], color=None)
    want_ids, want_offsets = render_ref.tile_lists(p, grid_x, grid_y)
    for chunks in (1, 2, 3, 8, 64):
        ids, offsets = raster._bin_tiles(order, rect, grid_x, grid_x * grid_y, chunks)
        assert np.array_equal(offsets, want_offsets) and np.array_equal(ids, want_ids), chunks


def brute_force_walk(proj, opacity, colour):
    """raster's render and pairs of one camera by the walk it had before its row lists: every splat of the pixel's
    tile, in depth order, through the kernels' own tests (plain Python floats: IEEE doubles, as the kernels')."""
    width, height = proj.width, proj.height
    grid_x = -(-width // render_ref.TILE)
    img = np.zeros((height, width, 3))
    pairs = []
    for y in range(height):
        for x in range(width):
            t = (y // render_ref.TILE) * grid_x + x // render_ref.TILE
            ids = proj.tile_ids[proj.tile_offsets[t]:proj.tile_offsets[t + 1]]
            trans, rgb, done = 1.0, [0.0, 0.0, 0.0], False
            pix, trans_store = [], 1.0
            for i in ids:
                dx, dy = float(proj.xy[i, 0]) - x, float(proj.xy[i, 1]) - y
                a, b, c = (float(v) for v in proj.conic[i])
                power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
                if power > 0.0 or power < raster.POWER_SKIP:
                    continue
                g = math.exp(power)
                alpha = min(render_ref.ALPHA_MAX, float(opacity[i]) * g)
                if g >= render_ref.ALPHA_MIN and trans_store >= raster.T_STORE:
                    pix.append((int(i), np.float32(g)))
                    if alpha >= render_ref.ALPHA_MIN:
                        trans_store *= 1.0 - alpha
                if done or alpha < render_ref.ALPHA_MIN:
                    continue
                tn = trans * (1.0 - alpha)
                if tn < render_ref.T_MIN:
                    done = True
                    continue
                for ch in range(3):
                    rgb[ch] += alpha * trans * float(colour[i, ch])
                trans = tn
            img[y, x] = rgb
            pairs.append(pix)
    return img.astype(np.float32), pairs


def test_the_row_lists_skip_only_what_the_walk_skipped(part):
    # the tile walk lists each pixel row's reachable splats first (raster._row_candidates): the same picture and the
    # same pairs, bit for bit, as walking every splat of the tile; here with splats of every size (a close camera)
    cams = [*scene_orbit_views(part.positions, 1, 40, 24, elevation_deg=25.0),
            *refine_cameras(part.positions, (0.0, 1.0, 0.0), 1, 24, seed=5)]
    for cam in cams:
        proj = raster.project(part, cam)
        opacity = part.opacities.astype(np.float64)[proj.index]
        colour = raster.colours_of(proj, part.sh_dc)
        want_img, want_pairs = brute_force_walk(proj, opacity, colour)
        assert np.array_equal(raster.render_projection(proj, opacity, colour).view(np.uint32), want_img.view(np.uint32))
        pl = raster.pair_lists(part, [cam])
        assert len(pl.g) == sum(len(p) for p in want_pairs) > 1000
        got = [list(zip(pl.proj[s:e].tolist(), pl.g[s:e], strict=True))
               for s, e in zip(pl.pixel_offsets[:-1], pl.pixel_offsets[1:], strict=True)]
        assert got == want_pairs


def test_pair_lists_draw_the_same_picture(part):
    cams = scene_orbit_views(part.positions, 2, 48, 48, elevation_deg=25.0)
    pl = raster.pair_lists(part, cams)
    assert pl.cameras == 2 and len(pl.pixel_offsets) == 2 * 48 * 48 + 1 and len(pl.g) == pl.pixel_offsets[-1]
    assert pl.g.min() >= render_ref.ALPHA_MIN and pl.g.max() <= 1.0
    target = np.clip(np.stack([render_ref.render(part, c) for c in cams]), 0, 1)
    loss, _, _ = raster.loss_and_grad(pl, part.opacities.astype(np.float64),
                                      raster.SH_C0 * part.sh_dc.astype(np.float64), target, grad=False)
    assert loss < 1e-10  # the pairs' forward is the reference's picture


def test_pair_lists_of_several_cameras_are_each_cameras_lists_in_turn(part):
    # pair_lists grows its arrays by each camera's pairs (one walk a camera): the same arrays as the cameras' own
    # lists, concatenated
    cams = scene_orbit_views(part.positions, 3, 40, 32, elevation_deg=25.0)
    whole = raster.pair_lists(part, cams)
    ones = [raster.pair_lists(part, [c]) for c in cams]
    hw = 40 * 32
    proj_off, pair_off = 0, 0
    for c, one in enumerate(ones):
        assert np.array_equal(whole.pixel_offsets[c * hw:(c + 1) * hw + 1], one.pixel_offsets + pair_off)
        s, e = pair_off, pair_off + len(one.g)
        assert np.array_equal(whole.proj[s:e], one.proj + proj_off) and np.array_equal(whole.g[s:e], one.g)
        pair_off, proj_off = e, proj_off + len(one.splat)
    assert len(whole.g) == pair_off and len(whole.splat) == proj_off > 0
    assert np.array_equal(whole.splat, np.concatenate([o.splat for o in ones]))
    assert np.array_equal(whole.base, np.concatenate([o.base for o in ones]))


def test_pair_lists_whose_walk_buffer_is_too_small_walk_the_missed_tiles_again(part, monkeypatch):
    # a camera's tiles reserve runs of one walk buffer; the tiles that do not fit are walked again once it has room.
    # Room for 0 pairs a pixel: no tile fits; for the fewest a pixel that hold the largest tile's pairs (and not a
    # camera's): the first tiles to finish fit and the others not, whatever the order; the default: all fit. The same
    # arrays, on any number of threads.
    side = 96
    cams = scene_orbit_views(part.positions, 2, side, side, elevation_deg=25.0)
    want = raster.pair_lists(part, cams)
    hw, tiles = side * side, side // render_ref.TILE
    counts = np.diff(want.pixel_offsets).reshape(2, tiles, render_ref.TILE, tiles, render_ref.TILE)
    partial = -(-counts.sum(axis=(2, 4)).max() // hw)
    assert (counts.sum(axis=(1, 2, 3, 4)) > partial * hw).all()
    assert (counts.sum(axis=(1, 2, 3, 4)) <= raster.WALK_ROOM_PAIRS * hw).all()  # the default: one walk, no tile missed
    runs = [(room, 0) for room in (0, partial)]
    runs.append((raster.WALK_ROOM_PAIRS, 1))  # and on one thread (the tiles reserve their runs in another order)
    before = raster.numba.get_num_threads()
    try:
        for room, threads in runs:
            monkeypatch.setattr(raster, "WALK_ROOM_PAIRS", room)
            raster.numba.set_num_threads(threads or before)
            got = raster.pair_lists(part, cams)
            for name in ("pixel_offsets", "proj", "g", "splat", "base", "projected"):
                assert np.array_equal(getattr(got, name), getattr(want, name)), (room, threads, name)
    finally:
        raster.numba.set_num_threads(before)


def test_gradients_match_finite_differences(part):
    cams = scene_orbit_views(part.positions, 2, 48, 48, elevation_deg=25.0)
    pl = raster.pair_lists(part, cams)
    op = part.opacities.astype(np.float64)
    dc = raster.SH_C0 * part.sh_dc.astype(np.float64)
    rng = np.random.default_rng(0)
    clean = np.stack([raster.render(part, c) for c in cams])
    target = np.clip(clean * 0.8 + 0.1 + rng.normal(0, 0.05, clean.shape), 0, 1).astype(np.float32)
    _, g_op, g_dc = raster.loss_and_grad(pl, op, dc, target)
    assert np.abs(g_op).max() > 0 and np.abs(g_dc).max() > 0
    h = 1e-6

    def loss(o, d) -> float:
        return raster.loss_and_grad(pl, o, d, target, grad=False)[0]

    for i in np.argsort(-np.abs(g_op))[:15]:  # the splats that matter most
        up, down = op.copy(), op.copy()
        up[i] += h
        down[i] -= h
        assert (loss(up, dc) - loss(down, dc)) / (2 * h) == pytest.approx(g_op[i], rel=1e-4, abs=1e-12)
    for i in np.argsort(-np.abs(g_dc).max(axis=1))[:10]:
        for ch in range(3):
            up, down = dc.copy(), dc.copy()
            up[i, ch] += h
            down[i, ch] -= h
            fd = (loss(op, up) - loss(op, down)) / (2 * h)
            assert fd == pytest.approx(g_dc[i, ch], abs=1e-4 * np.abs(g_dc[i]).max() + 1e-12)


def reference_loss_and_grad(pl, opacity, dc, target, f=np.float64, divide=False):
    """raster.loss_and_grad in plain Python, as its kernel computes it but for the per-camera table (refinefast31):
    each pair's splat, opacity, fixed colour part and DC term read where they lie, the gradient rows
    (raster.GRADIENT_ROWS, cameras round-robin) summed in order. Scalars of type `f`: float64 is the kernel's
    operations, so its bits; np.longdouble (x87's 64-bit mantissa here) the same sums with 11 more bits, the yardstick
    of test_the_stored_transmittance_gives_gradients_closer_than_the_division_chain. The backward pass reads each
    pair's transmittance as the forward met it (refinewall31); `divide`: as the kernel did before, T_j = T_{j+1} /
    (1 - a_j) from the pixel's last T."""
    n, nt, hw = len(opacity), raster.GRADIENT_ROWS, pl.width * pl.height
    tgt = np.asarray(target, np.float32).reshape(pl.cameras, -1, 3)
    scale = f(2.0) / f(tgt.size)
    g_op, g_dc = np.zeros((nt, n), f), np.zeros((nt, n, 3), f)
    losses = np.zeros(pl.cameras, f)
    for c in range(pl.cameras):
        t = c % nt
        for q in range(hw):
            s, e = pl.pixel_offsets[c * hw + q], pl.pixel_offsets[c * hw + q + 1]
            trans, rgb, met = f(1.0), [f(0.0)] * 3, []
            for k in range(s, e):
                b = pl.proj[k]
                i = pl.splat[b]
                alpha = min(f(raster.ALPHA_MAX), f(opacity[i]) * f(pl.g[k]))
                if alpha < raster.ALPHA_MIN:
                    continue
                tn = trans * (f(1.0) - alpha)
                if tn < raster.T_MIN:
                    break
                w = alpha * trans
                col = [max(f(pl.base[b, ch]) + f(dc[i, ch]), f(0.0)) for ch in range(3)]
                rgb = [rgb[ch] + w * col[ch] for ch in range(3)]
                met.append((alpha, k, i, col, trans))
                trans = tn
            d = [min(rgb[ch], f(1.0)) - f(tgt[c, q, ch]) for ch in range(3)]
            losses[c] += d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            err = [scale * d[ch] if rgb[ch] < 1.0 else f(0.0) for ch in range(3)]
            if err == [0.0, 0.0, 0.0]:
                continue
            behind, tj = [f(0.0)] * 3, trans
            for a, k, i, col, t_in_front in reversed(met):
                tj = tj / (f(1.0) - a) if divide else t_in_front
                w = a * tj
                for ch in range(3):
                    if col[ch] > 0.0:
                        g_dc[t, i, ch] += err[ch] * w
                inv = f(1.0) / (f(1.0) - a)
                da = (err[0] * (col[0] * tj - behind[0] * inv) + err[1] * (col[1] * tj - behind[1] * inv)
                      + err[2] * (col[2] * tj - behind[2] * inv))
                if a < raster.ALPHA_MAX:
                    g_op[t, i] += da * f(pl.g[k])
                behind = [behind[ch] + col[ch] * w for ch in range(3)]
    return float(losses.sum()) / tgt.size, g_op.sum(0), g_dc.sum(0)


def _clamping_case(part):
    """Cameras, pair lists, opacities, DC colours and targets where colours clamp at 0, alphas at 0.99 and pairs fall
    under the alpha cut."""
    cams = refine_cameras(part.positions, (0.0, 1.0, 0.0), 3, 20, seed=7)
    pl = raster.pair_lists(part, cams)
    rng = np.random.default_rng(1)
    op = np.clip(part.opacities.astype(np.float64) * rng.uniform(0.5, 1.6, len(part)), 0.0, 0.999)
    dc = raster.SH_C0 * part.sh_dc.astype(np.float64) + rng.normal(0.0, 0.3, (len(part), 3))
    clean = np.stack([raster.render(part, c) for c in cams])
    target = np.clip(clean * 0.9 + rng.normal(0, 0.05, clean.shape), 0, 1).astype(np.float32)
    return pl, op, dc, target


def test_the_compiled_loss_and_gradients_are_the_references_bit_for_bit(part):
    # the kernel reads each camera's table of projected splats (opacity, clamped colour), computed once a step, and
    # blends a pair under the alpha cut as alpha 0 without a branch: neither may move a bit of the loss or of any
    # gradient (the refined scene's bytes depend on them). Colours clamped at 0 and alphas at 0.99 both occur.
    pl, op, dc, target = _clamping_case(part)
    assert len(pl.g) > 2000 and pl.max_projected == np.diff(pl.projected).max() > 0
    assert (op[pl.splat[pl.proj]] * pl.g > raster.ALPHA_MAX).any() and (pl.base + dc[pl.splat] < 0).any()
    assert (op[pl.splat[pl.proj]] * pl.g < raster.ALPHA_MIN).any()
    loss, g_op, g_dc = raster.loss_and_grad(pl, op, dc, target)
    want_loss, want_op, want_dc = reference_loss_and_grad(pl, op, dc, target)
    assert np.abs(g_op).max() > 0 and np.abs(g_dc).max() > 0
    assert loss == want_loss
    assert np.array_equal(g_op.view(np.uint64), want_op.view(np.uint64))
    assert np.array_equal(g_dc.view(np.uint64), want_dc.view(np.uint64))
    assert raster.loss_and_grad(pl, op, dc, target, grad=False)[0] == want_loss


def test_the_stored_transmittance_gives_gradients_closer_than_the_division_chain(part):
    # refinewall31 changed the backward pass's bits (the forward's stored T_j for T_{j+1} / (1 - a_j)): the new bits
    # must be at least as good. Yardstick: the same sums in long double (11 more mantissa bits, the stored T); the
    # kernel's gradients are nearer it than the division chain's, whose rounding grows by 1 / (1 - a) a pair.
    pl, op, dc, target = _clamping_case(part)
    _, g_op, g_dc = raster.loss_and_grad(pl, op, dc, target)
    _, div_op, div_dc = reference_loss_and_grad(pl, op, dc, target, divide=True)
    _, ref_op, ref_dc = reference_loss_and_grad(pl, op, dc, target, f=np.longdouble)
    if np.finfo(np.longdouble).nmant <= 52:
        pytest.skip("long double is float64 on this platform: no yardstick")
    for new, old, ref in ((g_op, div_op, ref_op), (g_dc, div_dc, ref_dc)):
        new_err = np.abs(new - ref.astype(np.float64)).max()
        old_err = np.abs(old - ref.astype(np.float64)).max()
        assert old_err > 0 and new_err <= old_err, (new_err, old_err)
        assert np.abs(new - ref.astype(np.float64)).sum() < np.abs(old - ref.astype(np.float64)).sum()


def test_a_batched_step_fits_its_own_cameras_and_the_learning_rate_falls_to_its_final_share(part):
    # refinecheap31: step t fits batch (t - 1) % batches (camera k in batch k % batches), the learning rates falling
    # linearly to lr_final x themselves at the last step
    from refine_cpu.levels import fit_opacity_dc

    cams = scene_orbit_views(part.positions, 4, 32, 32, elevation_deg=25.0)
    target = np.clip(np.stack([render_ref.render(part, c) for c in cams]), 0, 1)
    first = len(part) // 2  # the second half fitted, the first fixed
    # the full detail's own opacities against a darker target, so that the fit moves
    darker = target * 0.8
    one = [(raster.pair_lists(part, cams), darker, 1.0)]
    halves = [(raster.pair_lists(part, cams[b::2]), np.ascontiguousarray(darker[b::2]), 1.0) for b in (0, 1)]
    s = CpuRefineSettings(iterations=1)
    full = fit_opacity_dc(one, part, first, s)
    # one step of two batches: the first batch's cameras alone
    batched = fit_opacity_dc(halves, part, first, CpuRefineSettings(iterations=1, batches=2), [0, 1])
    alone = fit_opacity_dc(halves[:1], part, first, s)
    assert all(np.array_equal(a, b) for a, b in zip(batched, alone, strict=True))
    assert not np.array_equal(batched[1], full[1])
    # a second step at lr_final = 0 moves nothing: the first step's values
    still = fit_opacity_dc(one, part, first, CpuRefineSettings(iterations=2, lr_final=0.0))
    assert all(np.array_equal(a, b) for a, b in zip(still, full, strict=True))
    # and at lr_final = 1 (constant) it does
    moved = fit_opacity_dc(one, part, first, CpuRefineSettings(iterations=2, lr_final=1.0))
    assert not np.array_equal(moved[1], full[1])
    # the fit lowers the loss
    dc = raster.SH_C0 * part.sh_dc.astype(np.float64)
    op = part.opacities.astype(np.float64)
    before = raster.loss_and_grad(one[0][0], op, dc, darker, grad=False)[0]
    op_fit, dc_fit = op.copy(), dc.copy()
    op_fit[first:] = 1 / (1 + np.exp(-moved[0].astype(np.float64)))
    dc_fit[first:] = raster.SH_C0 * moved[1].astype(np.float64)
    assert raster.loss_and_grad(one[0][0], op_fit, dc_fit, darker, grad=False)[0] < before


def test_the_refiner_fits_the_merged_levels_and_keeps_only_what_validates(part):
    tiles = build_tiles(part, 256, 2.0, merge="auto")
    cuts = level_cuts(tiles)
    logs: list[str] = []
    seen: list[tuple[str, float]] = []
    refiner = CpuLevelRefiner(CpuRefineSettings(iterations=25, size=48, training_cameras=8, validation_cameras=4,
                                           far_training_cameras=4, far_validation_cameras=2, log=logs.append))
    refined, record = refiner(part, tiles, (0.0, 1.0, 0.0), lambda phase, f: seen.append((phase, f)))
    # the coarsest level is also fitted and judged from where a client without a budget draws it (far31)
    root = refiner.report[0]
    assert root["far_cameras"] == 6 and root["far_range"][0] > 1.6 and 8 <= root["far_px"] < 48
    assert all(len(r["validation_psnr_near_far"]["A"]) == (2 if r["far_cameras"] else 1) for r in refiner.report)
    assert record.variants == (("A", VARIANT_FIELDS["A"]),) == (("A", ("opacity_logits", "sh_dc")),)
    assert (record.size_px, record.iterations, record.training_cameras, record.validation_cameras) == (48, 25, 8, 4)
    assert [lv.level for lv in record.levels] == [c.level for c in cuts] and len(logs) == len(cuts) + 1
    assert seen[0] == ("refine", 0.0) and seen[-1] == ("refine", 1.0)
    assert all(a[1] <= b[1] for a, b in zip(seen, seen[1:], strict=False))
    kept_a = [lv for lv in record.levels if lv.kept == "A"]
    assert kept_a  # the fit beats the level as built on validation views, where it is kept
    for lv, cut in zip(record.levels, cuts, strict=True):
        psnr_of = dict(lv.validation_psnr)
        assert set(psnr_of) == {"none", "A"}
        assert (lv.kept == "A") == (psnr_of["A"] > psnr_of["none"])
        for tid in cut.merged:
            assert (tid in refined) == (lv.kept == "A")
    for tid, g in refined.items():
        old = tiles[tid].gaussians
        assert tiles[tid].children and len(g) == len(old)
        # the geometry and the view-dependent bands never change; opacity and DC colour do
        for f in ("positions", "rotations", "log_scales", "sh_rest"):
            assert np.array_equal(getattr(g, f), getattr(old, f))
        assert not np.array_equal(g.opacity_logits, old.opacity_logits)
        assert not np.array_equal(g.sh_dc, old.sh_dc)


# --- the CLI: encode --lod-refine cpu ------------------------------------------------------------------------------

TREE_ARGS = ("--max-leaf-splats", "256", "--no-compact-table")


def cut_ids(manifest, level: int) -> list[int]:
    """The tiles a client draws with the tree cut at `level`: its merged tiles and the shallower leaves."""
    return [t.id for t in manifest.tiles if (t.level == level and t.children) or (t.level <= level and not t.children)]


def test_cli_refines_on_the_cpu_records_it_and_keeps_the_leaves(fruit, tmp_path):
    from conftest import run_cli

    from splatstream.scene_decode import decode_scene
    from splatstream.store import open_store, read_manifest

    src = real("fruit_drops_sh3.ply")
    plain, refined = tmp_path / "plain", tmp_path / "refined"
    assert run_cli("encode", src, plain, *TREE_ARGS, "-q").returncode == 0
    r = run_cli("encode", src, refined, *TREE_ARGS, "--lod-refine", "cpu", "--lod-refine-iters", "30",
                "--lod-refine-size", "64")
    assert r.returncode == 0, r.stderr
    assert "lod-refine: full-detail renders" in r.stderr and "lod-refine: level 0 (" in r.stderr  # progress shown
    lines = r.stderr.splitlines()
    last_level = max(i for i, line in enumerate(lines) if line.startswith("lod-refine: level "))
    assert [i for i, line in enumerate(lines) if line.startswith("encode: refine 100%")] > [last_level], r.stderr
    mp, mr = read_manifest(open_store(plain)), read_manifest(open_store(refined))
    rec = mr.lod.refinement
    assert mp.lod.refinement is None and rec is not None
    assert rec.variants == (("A", ("opacity_logits", "sh_dc")),) and (rec.size_px, rec.iterations) == (64, 30)
    assert [lv.level for lv in rec.levels] == sorted({t.level for t in mr.tiles if t.children})
    info = json.loads(run_cli("info", refined, "--json").stdout)
    assert info["lod"]["refinement"]["variants"] == {"A": ["opacity_logits", "sh_dc"]}
    text = run_cli("info", refined).stdout
    assert "render-fit at 64 px, 30 steps per variant (A = opacity_logits+sh_dc)" in text
    for a, b in zip(mp.tiles, mr.tiles, strict=True):
        if not a.children:  # the full detail: byte for byte
            assert {g: e.sha256 for g, e in a.groups.items()} == {g: e.sha256 for g, e in b.groups.items()}
    # The coarsest levels against the full detail on views of their own (the benchmark's orbit, not the training
    # or validation cameras): closer where the fit was kept.
    views = scene_orbit_views(fruit.positions, 4, 96, 96, elevation_deg=25.0)
    full = [render_ref.render(fruit, v) for v in views]
    kept = {lv.level: lv.kept for lv in rec.levels}
    assert kept[0] == "A" and kept[1] == "A"
    for level in (0, 1):
        before = decode_scene(plain, tiles=cut_ids(mp, level))
        after = decode_scene(refined, tiles=cut_ids(mr, level))
        gain = np.mean([psnr(render_ref.render(after, v), f) - psnr(render_ref.render(before, v), f)
                        for v, f in zip(views, full, strict=True)])
        assert gain > 0.3, (level, gain)


def test_cli_refusals_of_the_cpu_refinement(tmp_path):
    import subprocess
    import sys

    from conftest import run_cli

    missing_input = str(tmp_path / "no-such-scene.ply")
    out = str(tmp_path / "out")
    # (--workers, --scheduler: refined by partitions since branch partrefine31, tests/test_partitioned_refine.py)
    for extra, message in [(["--no-lod"], "not with --no-lod"),
                           (["--target-size", "20"], "not with --target-psnr / --target-size"),
                           (["--lod-refine-size", "8"], "--lod-refine-size 8: expected 16 to 16384 px")]:
        r = run_cli("encode", missing_input, out, *extra, "--lod-refine", "cpu")
        assert r.returncode == 2 and message in r.stderr and r.stderr.count("\n") == 1, r.stderr
    r = run_cli("encode", missing_input, out, "--lod-refine", "tpu")
    assert r.returncode == 2 and "'tpu' is neither gpu nor cpu" in r.stderr
    # the output directory after the option is taken as its value (argparse): the message says how to write it
    r = run_cli("encode", missing_input, "--lod-refine", out)
    assert r.returncode == 2 and "is neither gpu nor cpu" in r.stderr and "--lod-refine=gpu" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()
    # numba absent (its import blocked in that process): one line naming the extra, before the scene is read
    block = "import sys; sys.modules['numba'] = None; from cli.main import main; sys.exit(main())"
    r = subprocess.run([sys.executable, "-c", block, "encode", missing_input, out, "--lod-refine", "cpu"],
                       capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "--lod-refine cpu needs numba" in r.stderr and "pip install 'splatstream[fast]'" in r.stderr
    assert "no-such-scene" not in r.stderr and not (tmp_path / "out").exists()


def test_the_refiner_runs_numbas_workqueue_layer_unless_one_is_named():
    """OpenMP's threads spin between the refiner's parallel loops (BENCHMARKS.md, "Both refiners on the GPU
    machine"): the refiner asks for workqueue, and a layer the user names is kept."""
    import subprocess
    import sys

    code = ("import numpy as np, numba\n"
            "from refine_cpu import raster\n"
            "@numba.njit(parallel=True)\n"
            "def f(a):\n"
            "    s = 0.0\n"
            "    for i in numba.prange(a.size):\n"
            "        s += a[i]\n"
            "    return s\n"
            "f(np.ones(8))\n"
            "print(numba.threading_layer())\n")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "workqueue", out.stderr
    # a layer the user names is the one numba runs (omp: the layer numba picks by itself where tbb is absent)
    named = subprocess.run([sys.executable, "-c", code], env={**env, "NUMBA_THREADING_LAYER": "omp"},
                           capture_output=True, text=True)
    assert named.returncode == 0 and named.stdout.strip() == "omp", named.stderr


def test_concurrent_fits_share_this_machines_cores():
    # a local cluster's partitions fit at once (cores / fits threads each; 16 workers on 4 partitions: 4, not 1), the
    # upper levels' single fit every core; an existing cluster's refiner keeps numba's default
    import os

    from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings

    cores = os.cpu_count() or 1
    shared = CpuLevelRefiner(CpuRefineSettings(share_cores=True))
    assert shared.for_concurrent_fits(4).settings.threads == max(1, cores // 4)
    assert shared.for_concurrent_fits(1).settings.threads == cores
    assert shared.for_concurrent_fits(10 * cores).settings.threads == 1
    assert shared.for_concurrent_fits(4).settings.iterations == shared.settings.iterations
    own = CpuLevelRefiner(CpuRefineSettings())
    assert own.for_concurrent_fits(4) is own and own.settings.threads == 0
