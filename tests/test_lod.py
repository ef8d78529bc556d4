"""LOD tile tree (splatstream/lod.py): partition, structure, bounds, errors, merge validity, and what a coarse cut
looks like from the distance at which a client would draw it (format_spec/lod.md)."""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from conftest import REAL_PLYS, real

from splatstream import lod
from splatstream.gaussians import SH_C0, Gaussians, covariances
from splatstream.ply import read_gaussians_ply

MAX_LEAF = 2000


@functools.cache
def scene(name: str) -> Gaussians:
    return read_gaussians_ply(real(name))


@functools.cache
def tree(name: str, reduction: float = 4.0) -> list[lod.Tile]:
    return lod.build_tiles(scene(name), max_leaf_splats=MAX_LEAF, reduction=reduction)


def rows(g: Gaussians) -> np.ndarray:
    """All attributes of every splat as one float32 row, rows sorted: equal sets of splats give equal arrays."""
    table = np.concatenate([g.positions, g.rotations, g.log_scales, g.opacity_logits[:, None], g.sh_dc,
                            g.sh_rest.reshape(len(g), -1)], axis=1)
    return table[np.lexsort(table.T[::-1])]


def random_gaussians(n: int, seed: int = 0, sh_degree: int = 1) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    k = (0, 3, 8, 15)[sh_degree]
    return Gaussians(rng.normal(size=(n, 3)), q, rng.normal(-3, 0.5, size=(n, 3)), rng.normal(0, 2, size=n),
                     rng.normal(size=(n, 3)), rng.normal(0, 0.1, size=(n, k, 3)))


# ---------------------------------------------------------------------------------------------- structure


@pytest.mark.parametrize("name", REAL_PLYS)
def test_every_splat_lands_in_exactly_one_leaf(name):
    g, tiles = scene(name), tree(name)
    leaves = [t for t in tiles if not t.children]
    assert len(leaves) > 1
    assert sum(len(t.gaussians) for t in leaves) == len(g)
    assert all(len(t.gaussians) <= MAX_LEAF for t in leaves)
    np.testing.assert_array_equal(rows(Gaussians.concatenate([t.gaussians for t in leaves])), rows(g))


@pytest.mark.parametrize("name", REAL_PLYS)
def test_tree_shape_ids_levels_and_counts(name):
    tiles = tree(name)
    assert [t.id for t in tiles] == list(range(len(tiles)))
    assert tiles[0].level == 0 and tiles[0].children
    parents = {}
    for t in tiles:
        for c in t.children:
            assert c > t.id and c not in parents
            parents[c] = t.id
            assert tiles[c].level == t.level + 1
    assert sorted(parents) == list(range(1, len(tiles)))  # a tree: every tile but the root has one parent
    assert [t.level for t in tiles] == sorted(t.level for t in tiles)  # breadth-first
    for t in tiles:
        if t.children:
            below = sum(len(tiles[c].gaussians) for c in t.children)
            assert len(t.gaussians) == min(MAX_LEAF, math.ceil(below / 4.0))


@pytest.mark.parametrize("reduction", [2.0, 4.0])
def test_reduction_sets_per_level_counts_and_a_small_root(reduction):
    g = scene("donut_sh0_no_normals.ply")
    tiles = tree("donut_sh0_no_normals.ply", reduction)
    levels = max(t.level for t in tiles) + 1
    assert levels >= 3
    per_level = [sum(len(t.gaussians) for t in tiles if t.level == level) for level in range(levels)]
    for upper, lower in zip(per_level[1:-1], per_level[2:], strict=True):
        assert upper == pytest.approx(lower / reduction, rel=0.02)
    # the root about 0.25 % of the scene (lod.ROOT_FRACTION, at least ROOT_MIN_SPLATS): any budget of a few percent
    # can be spent from it
    assert len(tiles[0].gaussians) <= max(lod.ROOT_MIN_SPLATS, lod.ROOT_FRACTION * len(g))


def test_shape_small_tiles_on_top_chains_below():
    # 542k splats at leaves of 16,384: 64 leaves; the top levels split into many small tiles, the levels just above
    # the leaves are chains (one child, the same region) whose tiles grow by the reduction.
    shape = lod.TreeShape.of(542_104, 16384, 2.0)
    assert shape.kd_depths[0] == 0 and shape.kd_depths[-1] == shape.depth == 6
    assert list(shape.kd_depths) == sorted(shape.kd_depths)
    assert shape.kd_depths.count(6) >= 3  # chains above the leaves
    assert 542_104 / 2 ** (len(shape.kd_depths) - 1) <= lod.ROOT_MAX_SPLATS
    for level in range(len(shape.kd_depths) - 1):
        assert shape.fan(level) == 2 ** (shape.kd_depths[level + 1] - shape.kd_depths[level])
    assert lod.TreeShape.of(1000, 1000, 2.0).tiles == 1


@pytest.mark.parametrize("n,max_leaf,reduction", [(2001, 2000, 4.0), (5000, 300, 3.0), (5000, 300, 2.0),
                                                  (45_000, 16384, 1.75)])
def test_odd_sizes_and_reductions(n, max_leaf, reduction):
    g = random_gaussians(n, seed=n)
    tiles = lod.build_tiles(g, max_leaf_splats=max_leaf, reduction=reduction)
    leaves = [t for t in tiles if not t.children]
    np.testing.assert_array_equal(rows(Gaussians.concatenate([t.gaussians for t in leaves])), rows(g))
    assert all(len(t.gaussians) <= max_leaf for t in tiles)
    assert len({t.level for t in leaves}) == 1
    for t in tiles:
        if t.children:
            below = sum(len(tiles[c].gaussians) for c in t.children)
            assert len(t.gaussians) == min(max_leaf, math.ceil(below / reduction))
            assert len(t.children) in (1, 2, 4, 8, 16, 32, 64) or t.id == 0


@pytest.mark.parametrize("n", [300, 3000])
def test_reorder_input_gives_the_same_tree_without_a_copy(n):
    g = random_gaussians(n, seed=7, sh_degree=3)
    before = rows(g)
    copied = lod.build_tiles(g, max_leaf_splats=400)
    np.testing.assert_array_equal(rows(g), before)  # the default leaves the input alone
    in_place = lod.build_tiles(g, max_leaf_splats=400, reorder_input=True)
    np.testing.assert_array_equal(rows(g), before)  # same splats, new order
    assert len(copied) == len(in_place)
    for a, b in zip(copied, in_place, strict=True):
        for f in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
            np.testing.assert_array_equal(getattr(a.gaussians, f), getattr(b.gaussians, f))
        assert a.geometric_error == b.geometric_error
    leaves = [t for t in in_place if not t.children]
    assert all(np.shares_memory(t.gaussians.sh_rest, g.sh_rest) for t in leaves)


def test_error_sees_a_merged_blob_among_untouched_outliers():
    # 995 isolated splats on a lattice stay single, a dense blob of 3000 merges into a handful: over 99 % of the
    # merged splats are untouched copies, so a percentile over merged splats would say 0. The error must not.
    blob = random_gaussians(3000, seed=11)
    blob.positions = blob.positions * 0.01 + 50.0
    lonely = random_gaussians(995, seed=13)
    lattice = np.stack(np.meshgrid(*[np.arange(10)] * 3, indexing="ij"), -1).reshape(-1, 3)[:995]
    lonely.positions = (lattice * 100.0).astype(np.float32)
    lonely.log_scales[:] = -6.0
    tiles = lod.build_tiles(Gaussians.concatenate([blob, lonely]), max_leaf_splats=1000)
    root = tiles[0]
    assert len(root.gaussians) < 1000 and root.children
    assert root.geometric_error > 0.0


def test_empty_scene_is_an_empty_leaf():
    tiles = lod.build_tiles(Gaussians.empty(3))
    assert len(tiles) == 1 and len(tiles[0].gaussians) == 0 and tiles[0].children == []


def test_progress_reports_fractions_up_to_one():
    calls = []
    lod.build_tiles(random_gaussians(3000), max_leaf_splats=200, progress=lambda s, f: calls.append((s, f)))
    assert calls and all(0.0 <= f <= 1.0 for _, f in calls)
    assert calls[-1] == ("lod-merge", 1.0)


def test_bad_parameters_raise():
    with pytest.raises(ValueError):
        lod.build_tiles(random_gaussians(10), max_leaf_splats=0)
    with pytest.raises(ValueError):
        lod.build_tiles(random_gaussians(10), reduction=1.0)


# ---------------------------------------------------------------------------------------------- bounds, errors


@pytest.mark.parametrize("name", REAL_PLYS)
def test_boxes_and_spheres_cover_three_sigma_extents(name):
    tiles = tree(name)
    for t in tiles:
        g = t.gaussians
        p = g.positions.astype(np.float64)
        half = 3.0 * np.sqrt(np.diagonal(covariances(g), axis1=1, axis2=2))
        eps = 1e-6 * (1 + np.abs(p).max())
        assert np.all(p - half >= t.box_min - eps) and np.all(p + half <= t.box_max + eps)
        reach = 3.0 * np.exp(g.log_scales.max(axis=1).astype(np.float64))
        assert np.all(np.linalg.norm(p - t.sphere_center, axis=1) + reach <= t.sphere_radius + eps)
        for c in t.children:  # a parent's volume encloses its children's
            k = tiles[c]
            assert np.all(k.box_min >= t.box_min - eps) and np.all(k.box_max <= t.box_max + eps)
            assert np.linalg.norm(k.sphere_center - t.sphere_center) + k.sphere_radius <= t.sphere_radius + eps


@pytest.mark.parametrize("name", REAL_PLYS)
def test_geometric_error_zero_at_leaves_and_monotone(name):
    tiles = tree(name)
    for t in tiles:
        if not t.children:
            assert t.geometric_error == 0.0
        else:
            assert t.geometric_error > 0.0
            assert all(t.geometric_error >= tiles[c].geometric_error for c in t.children)
    # Errors are world units on the scene's scale: positive and well below the scene's size at the root.
    assert tiles[0].geometric_error < 2 * tiles[0].sphere_radius


@pytest.mark.parametrize("name", REAL_PLYS)
def test_merged_splats_are_valid(name):
    g = scene(name)
    for t in tree(name):
        m = t.gaussians
        assert m.sh_rest.shape[1:] == g.sh_rest.shape[1:]
        for arr in (m.positions, m.rotations, m.log_scales, m.opacity_logits, m.sh_dc, m.sh_rest):
            assert np.all(np.isfinite(arr))
        np.testing.assert_allclose(np.linalg.norm(m.rotations, axis=1), 1.0, atol=1e-5)
        assert np.all(m.rotations[:, 0] >= 0)
        assert np.all(m.opacities <= 1.0)


# ---------------------------------------------------------------------------------------------- merge maths


def test_moment_matching_of_two_splats():
    s = 0.1
    g = Gaussians(np.array([[-0.3, 0, 0], [0.3, 0, 0]]), np.array([[1, 0, 0, 0], [1, 0, 0, 0]]),
                  np.full((2, 3), math.log(s)), np.zeros(2), np.array([[1.0, 0, 0], [0, 1.0, 0]]),
                  np.zeros((2, 3, 3)))
    mass = lod.splat_mass(g)
    merged, merged_mass, assign = lod.merge_gaussians(g, mass, 1)
    assert len(merged) == 1 and list(assign) == [0, 0]
    np.testing.assert_allclose(merged.positions[0], 0.0, atol=1e-7)
    np.testing.assert_allclose(covariances(merged)[0], np.diag([s * s + 0.09, s * s, s * s]), rtol=1e-5)
    np.testing.assert_allclose(merged.sh_dc[0], [0.5, 0.5, 0.0], atol=1e-6)
    assert merged_mass[0] == pytest.approx(mass.sum())
    # Mass (opacity x mean cross-section) is preserved while the opacity stays below the ceiling.
    area = lambda ls: np.exp(ls[:, 0] + ls[:, 1]) + np.exp(ls[:, 1] + ls[:, 2]) + np.exp(ls[:, 0] + ls[:, 2])  # noqa: E731
    assert float(merged.opacities[0] * area(merged.log_scales)[0]) == pytest.approx(mass.sum(), rel=1e-5)


def test_opacity_and_colour_matched_at_the_two_pixel_viewing_scale():
    # lod.md 6 step 5: b = 0.3 p^2 with p = error / 2 px (nearer than the 1 px of a view without a budget).
    assert lod.OPACITY_MATCH_SSE_PX == 2.0
    assert lod.viewing_blur(0.8) == pytest.approx(0.3 * 0.4 ** 2, rel=1e-12)
    s, blur = 0.1, lod.viewing_blur(0.8)
    g = Gaussians(np.array([[-0.3, 0, 0], [0.3, 0, 0]]), np.array([[1, 0, 0, 0], [1, 0, 0, 0]]),
                  np.full((2, 3), math.log(s)), np.zeros(2), np.array([[1.0, 0, 0], [0, 1.0, 0]]),
                  np.zeros((2, 3, 3)))
    merged, _, assign = lod.merge_gaussians(g, lod.splat_mass(g), 1)
    moments = merged.positions.copy(), covariances(merged).copy()
    terms = lod.appearance_terms(g.opacity_logits, g.log_scales, g.sh_dc, blur)
    lod.finish_appearance(merged, np.array([2]), lod.fold_leaf_sums([lod.leaf_sums(assign, terms, 1)], 1), blur)
    # Each member covers 0.5 * 3 (s^2 + b) after the blur; the merged splat (variances 0.09 + s^2, s^2, s^2)
    # covers the same in all: alpha = 2 * 1.5 (s^2 + b) / (2 sqrt((0.1 + b)(s^2 + b)) + (s^2 + b)).
    member = 0.5 * 3 * (s * s + blur)
    own = 2 * math.sqrt((0.09 + s * s + blur) * (s * s + blur)) + (s * s + blur)
    assert float(merged.opacities[0]) == pytest.approx(2 * member / own, rel=1e-5)
    # 0.715 (at the earlier 1 px: 0.881, more opaque than the pair looks from nearer; without a blur: 0.410)
    assert float(merged.opacities[0]) == pytest.approx(0.7152, abs=1e-4)
    np.testing.assert_allclose(merged.sh_dc[0], [0.5, 0.5, 0.0], atol=1e-6)  # equal members: the plain mean
    # Moment matching is untouched: the step sets opacity and base colour only.
    np.testing.assert_array_equal(merged.positions, moments[0])
    np.testing.assert_array_equal(covariances(merged), moments[1])


def test_far_viewing_scale_is_8_px_above_the_first_merged_level(monkeypatch):
    # lod.md 6 step 5: the first merged level (children are originals: child error 0) at 2 px, the level above it
    # at 8 px (+0.74 dB median under a splat budget; BENCHMARKS.md, "The default viewing scale: 2 + 8 px"). The
    # rule before it (every level at 2 px) stays reachable by setting lod.OPACITY_MATCH_FAR_SSE_PX (and growth 1).
    assert lod.OPACITY_MATCH_SSE_PX == 2.0 and lod.OPACITY_MATCH_FAR_SSE_PX == 8.0
    assert lod.viewing_scale_px(0.0) == 2.0 and lod.viewing_scale_px(0.3) == 8.0
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 2.0)
    assert lod.viewing_scale_px(0.0) == 2.0 and lod.viewing_scale_px(0.3) == 2.0
    assert lod.tile_viewing_blur(0.8, 0.3) == lod.viewing_blur(0.8)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 8.0)
    assert lod.tile_viewing_blur(0.8, 0.0) == lod.viewing_blur(0.8)
    assert lod.tile_viewing_blur(0.8, 0.3) == pytest.approx(0.3 * 0.1 ** 2, rel=1e-12)


def test_far_viewing_scale_changes_only_the_levels_above_the_first_merged_one(monkeypatch):
    # The grid merge: groups that do not depend on opacities, so every level's geometry stays the same. (8 px on
    # every level above, growth 1: the rule of 2026-11-29 this measured.)
    g = scene("lod_tile_sh3_zero_rest.ply")
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 2.0)
    two = lod.build_tiles(g, max_leaf_splats=1000, reduction=2.0, merge="grid")
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_SSE_PX", 8.0)
    eight = lod.build_tiles(g, max_leaf_splats=1000, reduction=2.0, merge="grid")
    first = max(t.level for t in two) - 1
    ceiling = {}
    for level in range(first + 1):
        a = [t.gaussians for t in two if t.level == level]
        b = [t.gaussians for t in eight if t.level == level]
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x.positions, y.positions)
            np.testing.assert_array_equal(x.log_scales, y.log_scales)
        oa = np.concatenate([x.opacities for x in a])
        ob = np.concatenate([y.opacities for y in b])
        if level == first:  # matched at 2 px either way: the same bits
            np.testing.assert_array_equal(oa, ob)
            np.testing.assert_array_equal(np.concatenate([x.sh_dc for x in a]), np.concatenate([y.sh_dc for y in b]))
        else:  # the smaller blur of 8 px: fewer merged splats at the 0.99 ceiling, lower opacities
            assert ob.mean() < oa.mean(), level
            ceiling[level] = ((oa >= 0.985).mean(), (ob >= 0.985).mean())
    # Measured: 96 % -> 95 % at the root, 56 % -> 28 % and 30 % -> 16 % on the two levels just above the first
    # merged one.
    assert ceiling[first - 2] == pytest.approx((0.555, 0.284), abs=0.01)
    assert ceiling[first - 1] == pytest.approx((0.303, 0.155), abs=0.01)


def test_the_far_scale_grows_with_the_level(monkeypatch):
    # lod.OPACITY_MATCH_FAR_GROWTH (issue 31, farpx31, the default since 2026-11-30): the level k above the first
    # merged one at 8 x 1.5^(k - 1) px, at most 16 (+0.24 / +0.19 dB median at 2 / 6 % budgets over 8 px on every
    # level above; BENCHMARKS.md, "A viewing scale growing with the level"). The record lists px per level up to the
    # first at the cap (format 1.10); without a cap no list says it (None: not recorded).
    assert lod.OPACITY_MATCH_FAR_GROWTH == 1.5 and lod.OPACITY_MATCH_FAR_CAP_SSE_PX == 16.0
    assert [lod.viewing_scale_px(0.3, k) for k in (1, 2, 3, 4, 9)] == [8.0, 12.0, 16.0, 16.0, 16.0]
    assert lod.viewing_scale_px(0.0, 3) == 2.0  # the first merged level (child error 0) keeps its 2 px
    assert lod.viewing_scales_px() == (2.0, 8.0, 12.0, 16.0)
    assert lod.tile_viewing_blur(0.8, 0.3, 2) == pytest.approx(0.3 * (0.8 / 12.0) ** 2, rel=1e-12)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_CAP_SSE_PX", 32.0)
    assert [lod.viewing_scale_px(0.3, k) for k in (1, 2, 3, 4, 5, 6)] == [8.0, 12.0, 18.0, 27.0, 32.0, 32.0]
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_CAP_SSE_PX", math.inf)
    assert lod.viewing_scales_px() is None
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_CAP_SSE_PX", 6.0)  # a cap under the start: one scale again
    assert lod.viewing_scale_px(0.3, 4) == 6.0 and lod.viewing_scales_px() == (2.0, 6.0)
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)  # growth 1: 8 px on every level above
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_CAP_SSE_PX", math.inf)
    assert [lod.viewing_scale_px(0.3, k) for k in (1, 2, 5, 9)] == [8.0] * 4 and lod.viewing_scales_px() == (2.0, 8.0)


def test_a_growing_far_scale_changes_the_levels_two_and_more_above_the_first_merged_one(monkeypatch):
    # The grid merge (groups that do not read opacities): levels k = 0 (the first merged) and 1 keep their bits,
    # k >= 2 are matched at 12, 16 px instead of 8: a smaller blur, lower opacities on average.
    g = scene("lod_tile_sh3_zero_rest.ply")
    grow = lod.build_tiles(g, max_leaf_splats=1000, reduction=2.0, merge="grid")
    monkeypatch.setattr(lod, "OPACITY_MATCH_FAR_GROWTH", 1.0)
    eight = lod.build_tiles(g, max_leaf_splats=1000, reduction=2.0, merge="grid")
    first = max(t.level for t in eight) - 1
    assert first >= 3
    for level in range(first + 1):
        a = np.concatenate([t.gaussians.opacities for t in eight if t.level == level])
        b = np.concatenate([t.gaussians.opacities for t in grow if t.level == level])
        if level >= first - 1:
            np.testing.assert_array_equal(a, b)
        else:
            assert b.mean() < a.mean(), level


def test_merging_preserves_mass_and_first_moment_and_keeps_singletons():
    g = random_gaussians(5000, seed=3, sh_degree=2)
    mass = lod.splat_mass(g)
    merged, merged_mass, assign = lod.merge_gaussians(g, mass, 1250)
    assert len(merged) == 1250
    assert merged_mass.sum() == pytest.approx(mass.sum())
    np.testing.assert_allclose((merged.positions * merged_mass[:, None]).sum(0),
                               (g.positions.astype(np.float64) * mass[:, None]).sum(0), atol=1e-3 * mass.sum())
    # Every merged splat's members are its own: the assignment is onto and mass-consistent.
    np.testing.assert_allclose(np.bincount(assign, weights=mass, minlength=1250), merged_mass, rtol=1e-9)
    single = np.bincount(assign, minlength=1250) == 1
    src = np.flatnonzero(single[assign])
    np.testing.assert_array_equal(merged.opacity_logits[assign[src]], g.opacity_logits[src])
    np.testing.assert_allclose(covariances(merged.subset(assign[src])), covariances(g.subset(src)), atol=1e-6)


def test_quaternions_from_matrices_round_trip():
    g = random_gaussians(2000, seed=5)
    from splatstream.gaussians import rotation_matrices

    q = lod._matrices_to_quaternions(rotation_matrices(g.rotations))
    np.testing.assert_allclose(q, g.rotations, atol=1e-5)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("columns", [None, 3, 45])
def test_group_sums_are_reduceats_bits(dtype, columns):
    # group_sums replaces np.add.reduceat in merge_groups: the same bits, or the tree's bytes would change. Values
    # over 16 decades (every rounding order shows), signed zeros, a NaN; groups of 1-20 rows (past GROUP_SUM_ROWS,
    # where reduceat itself takes over), and all-(-0.0) groups (reduceat keeps -0.0).
    rng = np.random.default_rng(11)
    n = 3000
    shape = (n,) if columns is None else (n, columns)
    a = (rng.standard_normal(shape) * 10.0 ** rng.integers(-8, 8, shape)).astype(dtype)
    zeros = rng.random(shape) < 0.2
    a[zeros] = np.where(rng.random(int(zeros.sum())) < 0.5, -0.0, 0.0)
    a[:3] = -0.0
    a[7] = np.nan
    sizes = np.concatenate([[3], rng.integers(1, 21, n)])
    starts = np.concatenate([[0], np.cumsum(sizes)])
    starts = starts[starts < n]
    got, want = lod.group_sums(a, starts), np.add.reduceat(a, starts, axis=0)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes()
    assert np.signbit(got[0]).all()


def test_quaternions_are_the_stacked_candidates_bits():
    # _matrices_to_quaternions computes each row's picked candidate only: the same bits as all four stacked and
    # the pick taken (the form before, 4a1caf1), on eigh's bases as merge_groups makes them.
    from splatstream.gaussians import normalize_quaternions

    rng = np.random.default_rng(13)
    m = rng.standard_normal((5000, 3, 3))
    _, r = np.linalg.eigh(m + np.transpose(m, (0, 2, 1)))
    r[:, :, 0] *= lod._orientation(r)[:, None]
    r[:4] = np.eye(3)
    m00, m01, m02 = r[:, 0, 0], r[:, 0, 1], r[:, 0, 2]
    m10, m11, m12 = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    m20, m21, m22 = r[:, 2, 0], r[:, 2, 1], r[:, 2, 2]
    cands = np.stack([
        np.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], 1),
        np.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], 1),
        np.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], 1),
        np.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], 1),
    ], 1)
    pick = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], 1), axis=1)
    assert len(np.unique(pick)) == 4
    q = cands[np.arange(len(r)), pick]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert lod._matrices_to_quaternions(r).tobytes() == normalize_quaternions(q).tobytes()


def test_orientation_is_the_determinants_sign():
    rng = np.random.default_rng(12)
    m = rng.standard_normal((4000, 3, 3))
    _, evecs = np.linalg.eigh(m + np.transpose(m, (0, 2, 1)))
    evecs[:5] = np.eye(3)
    evecs[5:10] = -np.eye(3)
    want = np.sign(np.linalg.det(evecs))
    assert (want == 1).any() and (want == -1).any()
    np.testing.assert_array_equal(lod._orientation(evecs), want)


# ---------------------------------------------------------------------------------------------- looks


def _private_render(g: Gaussians, eye, target, up, fov_y_deg: float, size: int, near: float):
    """Front-to-back EWA splatting (DC colour, 0.3 px^2 low-pass, alpha <= 0.99, black background)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    w = np.stack([right, down, fwd])  # world -> camera (x right, y down, z forward)
    t = (g.positions.astype(float) - eye) @ w.T
    keep = t[:, 2] > near
    t, cov = t[keep], w @ covariances(g.subset(np.flatnonzero(keep))) @ w.T
    f = size / (2 * math.tan(math.radians(fov_y_deg) / 2))
    z = t[:, 2]
    j = np.zeros((len(t), 2, 3))
    j[:, 0, 0] = j[:, 1, 1] = f / z
    j[:, 0, 2] = -f * t[:, 0] / z**2
    j[:, 1, 2] = -f * t[:, 1] / z**2
    c2 = j @ cov @ np.transpose(j, (0, 2, 1)) + 0.3 * np.eye(2)
    det = c2[:, 0, 0] * c2[:, 1, 1] - c2[:, 0, 1] ** 2
    conic = np.stack([c2[:, 1, 1], -c2[:, 0, 1], c2[:, 0, 0]], 1) / det[:, None]
    uv = f * t[:, :2] / z[:, None] + size / 2
    colour = np.maximum(0.5 + SH_C0 * g.sh_dc[keep].astype(float), 0)
    opacity = g.opacities[keep].astype(float)
    radius = 3 * np.sqrt(np.maximum(c2[:, 0, 0], c2[:, 1, 1]))
    by_depth = np.argsort(z, kind="stable")
    img, trans = np.zeros((size, size, 3)), np.ones((size, size))
    block = 16  # composite per 16x16 pixel block, over the splats whose 3-sigma box touches it
    for y0 in range(0, size, block):
        for x0 in range(0, size, block):
            ys, xs = np.mgrid[y0:min(y0 + block, size), x0:min(x0 + block, size)] + 0.5
            pix = np.stack([xs.ravel(), ys.ravel()], 1)
            u, v, r = uv[by_depth, 0], uv[by_depth, 1], radius[by_depth]
            touch = by_depth[(u + r > x0) & (u - r < x0 + block) & (v + r > y0) & (v - r < y0 + block)]
            col, tr = np.zeros((len(pix), 3)), np.ones(len(pix))
            for b in range(0, len(touch), 256):
                sl = touch[b:b + 256]
                d = pix[:, None, :] - uv[sl][None]
                power = (-0.5 * (conic[sl, 0] * d[..., 0] ** 2 + conic[sl, 2] * d[..., 1] ** 2)
                         - conic[sl, 1] * d[..., 0] * d[..., 1])
                alpha = np.minimum(0.99, opacity[sl] * np.exp(np.minimum(power, 0)))
                alpha[alpha < 1 / 255] = 0
                before = np.cumprod(np.concatenate([np.ones((len(pix), 1)), 1 - alpha[:, :-1]], 1), axis=1)
                before *= tr[:, None]
                col += (before * alpha) @ colour[sl]
                tr = before[:, -1] * (1 - alpha[:, -1])
            img[y0:y0 + block, x0:x0 + block] = col.reshape(ys.shape + (3,))
            trans[y0:y0 + block, x0:x0 + block] = tr.reshape(ys.shape)
    return img, 1 - trans


def _renderer():
    """The project's reference rasteriser when it is there, else the private splatter above."""
    try:
        from splatstream.camera import Camera
        from splatstream.render_ref import render_with_alpha
    except ImportError:
        return lambda g, eye, target, up, fov, size, near: _private_render(g, eye, target, up, fov, size, near)

    def render(g, eye, target, up, fov, size, near):
        cam = Camera(eye=tuple(eye), target=tuple(target), up=tuple(up), fov_y_deg=fov, width=size, height=size,
                     near=near, far=1e9)
        return render_with_alpha(g, cam, 0)

    return render


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 99.0 if mse == 0 else 10 * math.log10(1 / mse)


FOV_Y = 50.0
SIZE = 96


def level_views(name: str):
    """Per level: the cut's render and the full render from where the level's screen-space error is 1 px."""
    g, tiles = scene(name), tree(name)
    render = _renderer()
    root = tiles[0]
    direction = np.array([1.0, -1.0, 0.6]) / np.linalg.norm([1.0, -1.0, 0.6])
    for level in range(max(t.level for t in tiles)):
        cut = [t for t in tiles if t.level == level]
        error = max(t.geometric_error for t in cut)
        # 3D Tiles: sse = error * height / (2 distance tan(fov/2)) = 1 px
        distance = error * SIZE / (2 * math.tan(math.radians(FOV_Y) / 2) * 1.0)
        eye = root.sphere_center + direction * distance
        args = (eye, root.sphere_center, np.array([0.0, 0.0, 1.0]), FOV_Y, SIZE, min(0.2, distance / 20))
        coarse = Gaussians.concatenate([t.gaussians for t in cut])
        yield level, len(coarse), render(g, *args), render(coarse, *args)


@pytest.mark.parametrize("name", REAL_PLYS)
def test_each_level_looks_like_the_full_scene_at_one_pixel_error(name):
    for level, n, (full, full_cov), (coarse, coarse_cov) in level_views(name):
        # Measured (96x96, reference rasteriser): 33.3-49.6 dB over the image on these scenes (opacity and colour
        # matched at 2 px, lod.OPACITY_MATCH_SSE_PX; at 1 px 33.3-50.1 dB; at 4 px the two finest merged levels of
        # lod_tile's 2x tree lost 2.7-3.2 dB: BENCHMARKS.md, "LOD against peers", the viewing scale). With the levels
        # above the first merged one at 8 px (lod.OPACITY_MATCH_FAR_SSE_PX, the default since 2026-11-29, for views
        # under a splat budget): 33.3-49.6 dB; at 8, 12, 16 px by level (OPACITY_MATCH_FAR_GROWTH, since 2026-11-30):
        # 33.2-49.6 dB (the donut's 45-splat root 33.24).
        assert psnr(full, coarse) > 33.0, (level, psnr(full, coarse))
        # Nearly the same coverage (measured ratio 0.70-1.00 for levels of 100 splats or more: small roots lose
        # most at their rims, since merged scales are no longer grown for coverage, which blurred every budgeted
        # view; lod.finish_appearance). The 45-74-splat roots of these small scenes: 0.51-0.84.
        assert (0.68 if n >= 100 else 0.45) < coarse_cov.sum() / full_cov.sum() < 1.10, level
        # Mean colour where covered: measured within 15 % with every level at 2 px, except fruit_drops' 74-splat
        # root (a 44-pixel footprint whose soft rim covers less): 34 % brighter (32 % matched at 1 px). With the
        # levels above the first merged one at 8 px (the default) they are matched for a view that draws them
        # larger, and seen at 1 px they are brighter: measured up to 18 % (the donut's 2,880-splat level; lod_tile
        # 10 % darker), fruit_drops' root 40 % (lod.md 3 states this trade). At 8, 12, 16 px by level: up to 21 %
        # (the donut's 180-splat level; lod_tile's 220-splat level 13 % darker), fruit_drops' root 42 %.
        np.testing.assert_allclose(coarse.sum((0, 1)) / coarse_cov.sum(), full.sum((0, 1)) / full_cov.sum(),
                                   rtol=0.43 if n < 100 else 0.23, err_msg=str(level))
        halo = (coarse_cov > 0.05) & (full_cov < 0.01)
        hole = (full_cov > 0.5) & (coarse_cov < 0.25)
        # Measured: up to 12 halo or hole pixels on the rims of roots 32-75 pixels wide.
        assert halo.sum() + hole.sum() <= (0.20 if n >= 100 else 0.40) * (full_cov > 0.01).sum() + 2, level


def test_private_splatter_agrees_with_reference_rasteriser():
    pytest.importorskip("splatstream.render_ref")
    g = scene("fruit_drops_sh3.ply")
    c = g.positions.mean(0)
    eye = c + np.array([0.8, -0.8, 0.5])
    args = (eye, c, np.array([0.0, 0.0, 1.0]), FOV_Y, 64, 0.01)
    ref, ref_cov = _renderer()(g, *args)
    own, own_cov = _private_render(g, *args)
    assert psnr(ref, own) > 30.0
