"""splatstream.lod_groups: merge groups chosen by cost, and the hybrid that picks a grouping by a rendered proxy."""
from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import real

from splatstream import lod, lod_groups
from splatstream.gaussians import SH_C0, Gaussians
from splatstream.ply import read_gaussians_ply


@functools.cache
def fruit() -> Gaussians:
    return read_gaussians_ply(real("fruit_drops_sh3.ply"))


def arrays(g: Gaussians) -> tuple:
    alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    return (g.positions, g.log_scales, g.rotations, alpha, 0.5 + SH_C0 * g.sh_dc.astype(np.float64),
            lod.splat_mass(g))


def random_arrays(n: int, seed: int = 0) -> tuple:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), q.astype(np.float32),
                  rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32), rng.normal(0, 2, size=n).astype(np.float32),
                  rng.normal(size=(n, 3)).astype(np.float32), np.zeros((n, 0, 3), np.float32))
    return arrays(g)


def check_partition(ids: np.ndarray, n: int, target: int) -> None:
    assert ids.shape == (n,) and ids.dtype == np.int64
    assert ids.min() == 0 and ids.max() == target - 1
    assert len(np.unique(ids)) == target  # every id used: exactly `target` groups, every splat in one


@pytest.mark.parametrize("rule", [lod_groups.DEFAULT_RULE, *lod_groups.HYBRID_RULES, lod.AUTO_RULE])
@pytest.mark.parametrize("target", [1, 7, 500, 1999])
def test_cost_groups_are_an_exact_deterministic_partition(rule, target):
    a = random_arrays(2000)
    ids = lod_groups.group_ids(*a, target, rule)
    check_partition(ids, 2000, target)
    assert np.array_equal(ids, lod_groups.group_ids(*a, target, rule))
    if rule.max_group and rule.max_group < 2000 // target:  # below the cap's reach the Morton finish merges more
        return
    if rule.max_group:
        assert np.bincount(ids).max() <= max(rule.max_group, 4 * -(-2000 // target))


def test_at_or_above_the_count_every_splat_is_its_own_group():
    a = random_arrays(50)
    assert np.array_equal(lod_groups.group_ids(*a, 50), np.arange(50))
    assert np.array_equal(lod_groups.group_ids(*a, 80), np.arange(50))
    assert np.array_equal(lod_groups.hybrid_group_ids(*a, 50)[0], np.arange(50))


def test_coincident_splats_still_reach_the_count():
    """No edge is left between clusters at one point: the Morton finish makes up the count."""
    pos, *rest = random_arrays(300)
    pos = np.zeros_like(pos)
    ids = lod_groups.group_ids(pos, *rest, 10)
    check_partition(ids, 300, 10)


def test_hybrid_on_a_real_scene_is_exact_and_deterministic():
    g = fruit()
    a = arrays(g)
    ids, pick = lod_groups.hybrid_group_ids(*a, 1180)
    check_partition(ids, len(g), 1180)
    assert 0 <= pick <= len(lod_groups.HYBRID_RULES)
    again, pick2 = lod_groups.hybrid_group_ids(*a, 1180)
    assert np.array_equal(ids, again) and pick == pick2
    # The groups merge with the tree's own merge into exactly that many splats.
    merged, mass, assign = lod.merge_groups(g, lod.splat_mass(g), *lod_groups.group_runs(ids))
    assert len(merged) == 1180 and np.array_equal(np.unique(assign), np.arange(1180))
    assert np.isclose(mass.sum(), lod.splat_mass(g).sum())


def test_cost_groups_beat_the_grid_on_fruit_drops_by_their_own_measure():
    """The projected field-L2 the rule minimises: its groups' total error is below the Morton grid's at the same
    count (real values, not a timing)."""
    g = fruit()
    a = arrays(g)
    cost_ids = lod_groups.group_ids(*a, 1180, lod_groups.HYBRID_RULES[0])
    order, starts = lod_groups.grid_group_starts(g.positions, 1180)
    grid_ids = np.empty(len(g), np.int64)
    grid_ids[order] = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(g))))
    e_cost = lod_groups.group_errors(*a, cost_ids).sum()
    e_grid = lod_groups.group_errors(*a, grid_ids).sum()
    assert e_cost < 0.5 * e_grid


def test_group_errors_are_zero_for_single_splats_and_for_a_splat_split_in_two():
    a = random_arrays(20)
    assert np.allclose(lod_groups.group_errors(*a, np.arange(20)), 0.0, atol=1e-12)
    # Two identical splats at one place merge into one at the same place: the sum field is 2 a c G, the merge
    # (mass 2 m, same area, opacity capped at 1) is min(1, 2 a) c G; with a = 0.25 exactly 0.
    pos = np.zeros((2, 3))
    ls = np.full((2, 3), -2.0)
    rot = np.tile([1.0, 0, 0, 0], (2, 1))
    alpha = np.full(2, 0.25)
    col = np.full((2, 3), 0.5)
    mass = alpha * lod._coverage_area(ls)
    assert lod_groups.group_errors(pos, ls, rot, alpha, col, mass, np.zeros(2, np.int64))[0] < 1e-12


def test_proxy_draws_one_opaque_splat_where_it_is():
    """A splat of opacity 0.99 and colour (1, 0.5, 0) at the box centre: every view shows that colour times its
    Gaussian footprint (with the rasteriser's low-pass) at the pixels around the centre, black elsewhere."""
    pos = np.zeros((1, 3))
    cov = lod_groups.covariances6(np.array([[1.0, 0, 0, 0]]), np.full((1, 3), np.log(0.05)))
    img = lod_groups.proxy_views(pos, cov, np.array([0.99]), np.array([[1.0, 0.5, 0.0]]),
                                 (np.full(3, -1.0), np.full(3, 1.0)), 32)
    assert img.shape == (6, 32, 32, 3)
    for v in img:
        centre = v[15:17, 15:17].reshape(-1, 3)
        # pixel centres 0.5 px off on both axes; variance (0.05 / (2 / 32))^2 + 0.3 px^2 = 0.94
        peak = 0.99 * np.exp(-0.5 * 0.5 / 0.94)
        assert np.allclose(centre.max(axis=0), [peak, 0.5 * peak, 0.0], atol=1e-6)
        assert v[0, 0].max() == 0.0 and v.max() <= 0.99 + 1e-9
    # A second, nearer splat of another colour in front hides it in the view from that side only.
    pos2 = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    img2 = lod_groups.proxy_views(pos2, np.repeat(cov, 2, 0), np.array([0.99, 0.99]),
                                  np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), (np.full(3, -1.0), np.full(3, 1.0)),
                                  32)
    front, back = img2[0, 15:17, 15:17].reshape(-1, 3).max(0), img2[1, 15:17, 15:17].reshape(-1, 3).max(0)
    peak = 0.99 * np.exp(-0.5 * 0.5 / 0.94)
    # looking along -x the splat at x = 0.5 is in front: its blue over the red behind, seen through 1 - its alpha
    assert np.allclose(front, [(1 - peak) * peak, 0.0, peak], atol=1e-6)
    assert np.allclose(back, [peak, 0.0, (1 - peak) * peak], atol=1e-6)


def test_a_tail_round_takes_every_merge_left():
    """GroupRule.tail (the auto merge's rule): once the merges still needed are at most that share of the clusters,
    one round takes them all instead of halving them round after round; the early rounds are unchanged."""
    a = random_arrays(4000, seed=3)
    rounds = {}
    original = lod_groups._greedy_pairs
    for tail in (0.0, 0.05):
        quotas = []

        def counted(count, i, j, cost, quota, passes=12, _q=quotas):
            _q.append(quota)
            return original(count, i, j, cost, quota, passes)

        lod_groups._greedy_pairs = counted
        try:
            ids = lod_groups.group_ids(*a, 2000, lod_groups.GroupRule(proj=1, first_cap=2, max_group=4, tail=tail))
        finally:
            lod_groups._greedy_pairs = original
        check_partition(ids, 4000, 2000)
        rounds[tail] = quotas
    assert rounds[0.05][0] == rounds[0.0][0] == 1000  # the first round: half of the 2000 merges, as before
    assert len(rounds[0.05]) < len(rounds[0.0])
    # a tail round's quota is every merge left, at most 5 % of the clusters then
    assert any(q <= 0.05 * 4000 and q not in rounds[0.0] for q in rounds[0.05])


def test_closed_form_eigenvalues_and_area_match_numpy():
    """_eig6 (the closed form the grouping takes every merged splat's area from, in place since autofast5) against
    numpy's eigvalsh on random covariances, flat and needle-like ones and a sphere (a repeated eigenvalue)."""
    rng = np.random.default_rng(3)
    m = rng.normal(size=(500, 3, 3)) * np.exp(rng.uniform(-4, 2, size=(500, 1, 3)))
    c = np.concatenate([m @ np.transpose(m, (0, 2, 1)), np.eye(3)[None] * 2.5])
    six = np.stack([c[:, a, b] for a, b in lod_groups._SYM6], 1)
    want = np.linalg.eigvalsh(c)[:, ::-1]
    got = lod_groups._eig6(six)
    assert np.allclose(got, np.maximum(want, 1e-300), rtol=1e-6, atol=1e-9 * want[:, :1])
    assert np.allclose(got[-1], [2.5, 2.5, 2.5])
    s = np.sqrt(np.maximum(want, 0.0))
    area = s[:, 0] * s[:, 1] + s[:, 1] * s[:, 2] + s[:, 0] * s[:, 2]
    assert np.allclose(lod_groups._area6(six), area, rtol=1e-5, atol=1e-9 * want[:, 0])
    assert lod_groups._area6(six)[-1] == pytest.approx(3 * 2.5)


def test_parked_rows_join_maps_drops_and_folds():
    """group_ids_of's parked rows (enc31c): chunks parked in two rounds' cluster ids are mapped through the later
    rounds' remaps, rows inside one cluster dropped, repeated ordered pairs folded (multiplicities summed), and
    appended to the live rows with no cost (NaN)."""
    parked = lod_groups._ParkedRows()
    parked.step(np.array([0, 1, 2], np.int32))  # no chunk yet: not kept
    # round 0's ids (5 clusters): rows (0, 1) x2, (3, 4), (2, 0)
    parked.add(np.array([0, 3, 2], np.int32), np.array([1, 4, 0], np.int32), np.array([2, 1, 1], np.int32))
    parked.step(np.array([0, 1, 1, 2, 3], np.int32))  # round 1 merges clusters 1 and 2: 5 -> 4
    # round 1's ids: (1, 0) once more (the same ordered pair as round 0's (2, 0)), and (2, 3)
    parked.add(np.array([1, 2], np.int32), np.array([0, 3], np.int32), np.array([1, 4], np.int32))
    parked.step(np.array([0, 1, 2, 2], np.int32))  # round 2 merges clusters 2 and 3: 4 -> 3
    ei, ej = np.array([0], np.int32), np.array([2], np.int32)
    mult, cost = np.array([1], np.int32), np.array([0.5])
    ei, ej, mult, cost = parked.join(ei, ej, mult, cost, 3)
    # round 0 (3, 4) and round 1 (2, 3) now lie inside cluster 2: dropped; (0, 1) x2 and the two (1, 0) folded
    assert ei.tolist() == [0, 0, 1]
    assert ej.tolist() == [2, 1, 0]
    assert mult.tolist() == [1, 2, 2]
    assert mult.dtype == np.int32
    assert cost[0] == 0.5 and np.isnan(cost[1:]).all()
    assert not parked.chunks and not parked.remaps


def test_row_dots_are_einsums_bits():
    """row_dots replaces np.einsum("ij,ij->i") in the edge costs and group_errors: the same bits (groups hang on
    them) on every pair of rows drawn from special values, and on random rows of many magnitudes."""
    import itertools

    values = np.array([0.0, -0.0, 1.0, -1.0, 3.0, 5e-324, -1e-310, 1e308, -1e308, np.inf, -np.inf, np.nan])
    rows = np.array(list(itertools.product(values, repeat=3)))
    a, b = np.repeat(rows, len(rows), axis=0), np.tile(rows, (len(rows), 1))
    rng = np.random.default_rng(3)
    scale = 10.0 ** rng.integers(-150, 150, size=(200_000, 1))
    r = rng.normal(size=(200_000, 3)) * scale
    s = rng.normal(size=(200_000, 3)) * scale[::-1]
    for x, y in ((a, b), (r, s), (r, r), (np.take(r, rng.permutation(len(r)), axis=0), s)):
        with np.errstate(over="ignore", invalid="ignore"):
            want = np.einsum("ij,ij->i", x, y)
        got = lod_groups.row_dots(x, y)
        both_nan = np.isnan(want) & np.isnan(got)
        assert np.array_equal(want.view(np.int64)[~both_nan], got.view(np.int64)[~both_nan])
        assert np.array_equal(np.isnan(want), np.isnan(got))


def test_covariances_from_columns_are_the_strided_bits():
    """covariances6 (and lod.merge_groups) take R S as nine contiguous columns (gaussians.scaled_rotation_columns):
    the same bits as the products over rotation_matrices(q) * exp(s)[:, None, :]'s (N, 3, 3) strides, on random
    and unnormalised quaternions, log scales of many magnitudes, signed zeros and non-finite entries."""
    from splatstream.gaussians import rotation_matrices, scaled_rotation_columns

    rng = np.random.default_rng(5)
    n = 50_000
    q = (rng.normal(size=(n, 4)) * 10.0 ** rng.integers(-20, 20, size=(n, 1))).astype(np.float32)
    s = (rng.normal(size=(n, 3)) * 30).astype(np.float32)
    q[:8] = [[0, 0, 0, 0], [-0.0, 0, -0.0, 1], [np.inf, 0, 0, 1], [np.nan, 1, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0],
             [0.5, -0.5, 0.5, -0.5], [1e-30, 1e30, 0, 0]]
    s[:4] = [[-np.inf, 0, 1], [800, -800, 0], [np.nan, 0, 0], [-0.0, 0.0, -1e-40]]
    with np.errstate(all="ignore"):
        m = rotation_matrices(q) * np.exp(s.astype(np.float64))[:, None, :]
        cols = scaled_rotation_columns(q, s)
        want = np.empty((n, 6))
        for k, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
            want[:, k] = m[:, a, 0] * m[:, b, 0] + m[:, a, 1] * m[:, b, 1] + m[:, a, 2] * m[:, b, 2]
        got = lod_groups.covariances6(q, s)
    for k in range(9):
        assert np.array_equal(cols[k].view(np.int64), m[:, k // 3, k % 3].view(np.int64))
    assert np.array_equal(want.view(np.int64), got.view(np.int64))
