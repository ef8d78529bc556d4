"""The cost merge of the LOD tree (lod.LOD_MERGES "cost", format_spec/lod.md 6): one grouping per tree level with
the level's tiles as regions, so the splats each tile keeps are allocated by cost across the scene; the level's
total, the tree's shape, "no holes" and REPLACE stay as with the grid."""
from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import real

from splatstream import lod, lod_groups
from splatstream.encode import encode_file
from splatstream.errors import UsageError
from splatstream.gaussians import Gaussians
from splatstream.lod_groups import GroupRule
from splatstream.ply import read_gaussians_ply

MAX_LEAF = 2000


def cluster(n: int, centre, spread: float, seed: int, colour_spread: float) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = np.tile(np.array([1.0, 0, 0, 0], np.float32), (n, 1))
    return Gaussians((np.asarray(centre) + spread * rng.normal(size=(n, 3))).astype(np.float32), q,
                     np.full((n, 3), -3.0, np.float32), np.full(n, -2.0, np.float32),
                     (colour_spread * rng.normal(size=(n, 3))).astype(np.float32), np.zeros((n, 0, 3), np.float32))


def two_tiles() -> tuple[list[Gaussians], list[np.ndarray]]:
    """Tile 0: 400 splats of one colour packed far inside each other's footprints (cheap to merge); tile 1: 400
    splats of random colours a few footprints apart (costly)."""
    cheap = cluster(400, (0, 0, 0), 0.002, 1, 0.0)
    costly = cluster(400, (5, 0, 0), 0.5, 2, 2.0)
    return [cheap, costly], [lod.splat_mass(cheap), lod.splat_mass(costly)]


CAP4 = GroupRule(proj=1, max_group=4)  # groups of up to 4 from the start: the strongest allocation by cost


@pytest.mark.parametrize(("rule", "expected"), [(CAP4, [115, 285]), (lod.COST_RULE, [191, 209])])
def test_allocation_is_exact_by_cost_and_deterministic(rule, expected):
    members, masses = two_tiles()
    groups = lod.level_cost_groups(members, masses, [200, 200], cap=10_000, rule=rule)
    counts = [len(starts) for _, starts in groups]
    assert sum(counts) == 400  # the level's total is the sum of the tiles' targets, exactly
    # Allocated by cost: the cheap tile merges below its half (with CAP4 towards its cap of 4 per group: 100; greedy
    # matchings leave some groups of 2 and 3), the costly one keeps what the cheap one gave up. The default rule
    # pairs first, a near-perfect matching, so only what the pairs leave is allocated (BENCHMARKS.md).
    assert counts == expected
    for (order, starts), m in zip(groups, members, strict=True):  # each tile's groups partition its members
        assert np.array_equal(np.sort(order), np.arange(len(m)))
        assert starts[0] == 0 and np.all(np.diff(starts) > 0) and starts[-1] < len(m)
        assert np.diff(np.append(starts, len(m))).max() <= 4
    again = lod.level_cost_groups(members, masses, [200, 200], cap=10_000, rule=rule)
    for (o1, s1), (o2, s2) in zip(groups, again, strict=True):
        assert np.array_equal(o1, o2) and np.array_equal(s1, s2)


def test_allocation_respects_the_tile_cap_and_keeps_every_tile():
    members, masses = two_tiles()
    groups = lod.level_cost_groups(members, masses, [200, 200], cap=250, rule=CAP4)
    assert [len(s) for _, s in groups] == [115, 250]  # the costly tile capped: the grid at the cap
    one = [cluster(1, (9, 9, 9), 0.0, 3, 0.0)]
    groups = lod.level_cost_groups(members + one, masses + [lod.splat_mass(one[0])], [1, 1, 1], cap=10_000)
    assert [len(s) for _, s in groups] == [1, 1, 1]  # every tile keeps at least one splat


def test_groups_never_span_two_regions():
    members, masses = two_tiles()
    g = Gaussians.concatenate(members)
    alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    region = np.repeat([0, 1], 400)
    region[::7] = 2  # a third region interleaved with both
    ids = lod_groups.group_ids(g.positions, g.log_scales, g.rotations, alpha, 0.5 + g.sh_dc, np.concatenate(masses),
                               120, lod.COST_RULE, region=region)
    assert len(np.unique(ids)) == 120
    for gid in np.unique(ids):
        assert len(np.unique(region[ids == gid])) == 1
    with pytest.raises(ValueError):
        lod_groups.group_ids(g.positions, g.log_scales, g.rotations, alpha, 0.5 + g.sh_dc, np.concatenate(masses),
                             2, lod.COST_RULE, region=region)


@functools.cache
def fruit() -> Gaussians:
    return read_gaussians_ply(real("fruit_drops_sh3.ply"))


def test_cost_tree_has_no_holes_the_grid_shape_and_level_totals():
    g = fruit()
    grid = lod.build_tiles(g, max_leaf_splats=MAX_LEAF // 2, reduction=2.0)
    cost = lod.build_tiles(g, max_leaf_splats=MAX_LEAF // 2, reduction=2.0, merge="cost")
    assert [t.children for t in cost] == [t.children for t in grid]  # the same tiles, ids and REPLACE structure
    leaves = [t for t in cost if not t.children]
    assert sum(len(t.gaussians) for t in leaves) == len(g)  # leaves: an exact partition of the originals
    for t in cost:
        assert 1 <= len(t.gaussians) <= MAX_LEAF // 2
    shape = lod.TreeShape.of(len(g), MAX_LEAF // 2, 2.0)
    for level in range(max(t.level for t in cost)):  # each level's count: the sum of its tiles' targets, exactly
        level_tiles = [t for t in cost if t.level == level]
        members = [sum(len(cost[c].gaussians) for c in t.children) for t in level_tiles]
        assert sum(len(t.gaussians) for t in level_tiles) == sum(shape.target(m) for m in members)
    per_tile = [len(c.gaussians) != len(r.gaussians) for c, r in zip(cost, grid, strict=True) if c.children]
    assert any(per_tile)  # allocated across tiles, not halved per tile
    for t in cost:  # errors still monotone, boxes still cover the children (REPLACE draws never leave holes)
        for c in t.children:
            assert cost[c].geometric_error <= t.geometric_error
            assert np.all(t.box_min <= cost[c].box_min) and np.all(t.box_max >= cost[c].box_max)


def test_cost_tree_is_deterministic_with_any_threads():
    g = fruit()
    shape = lod.TreeShape.of(len(g), MAX_LEAF // 2, 2.0)
    one = lod.build_subtree(g, np.arange(len(g)), shape, threads=1, merge="cost")
    two = lod.build_subtree(g, np.arange(len(g)), shape, threads=2, merge="cost")
    for tid, t in one.tiles.items():
        u = two.tiles[tid]
        assert np.array_equal(t.gaussians.positions, u.gaussians.positions)
        assert np.array_equal(t.gaussians.opacity_logits, u.gaussians.opacity_logits)
        assert t.geometric_error == u.geometric_error


def test_unknown_merge_raises():
    with pytest.raises(ValueError):
        lod.build_tiles(fruit(), max_leaf_splats=MAX_LEAF, merge="nope")


def test_encode_with_the_cost_merge_in_memory_and_refused_by_partitions(tmp_path):
    path = str(real("fruit_drops_sh3.ply"))
    m = encode_file(path, tmp_path / "memory", lod_merge="cost", max_leaf_splats=1000, preset="low")
    grid = encode_file(path, tmp_path / "grid", max_leaf_splats=1000, preset="low")
    assert m.splats == grid.splats == 4721
    assert [t.children for t in m.tiles] == [t.children for t in grid.tiles]  # the same tree, other merges
    assert [t.splats for t in m.tiles] != [t.splats for t in grid.tiles]
    with pytest.raises(UsageError, match="--lod-merge cost groups each LOD level over the whole scene"):
        encode_file(path, tmp_path / "parts", lod_merge="cost", memory_per_worker=1 << 20, max_leaf_splats=1000)
    assert not (tmp_path / "parts").exists()
    with pytest.raises(UsageError, match="unknown LOD merge"):
        encode_file(path, tmp_path / "bad", lod_merge="nope")
