"""bench/probe_statue31.py (issue 31, the statue diagnosis): its variants change what they say and nothing else,
and the lod module is left as it was."""
from __future__ import annotations

import numpy as np
from conftest import load_bench

from splatstream import lod
from splatstream.gaussians import Gaussians


def load():
    return load_bench("probe_statue31")


P = load()


def scene(n: int = 4000, seed: int = 5) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), q.astype(np.float32),
                     rng.normal(-3.5, 0.4, size=(n, 3)).astype(np.float32),
                     rng.normal(0, 1.5, size=n).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32),
                     np.zeros((n, 0, 3), np.float32))


def build(variant: str) -> list[lod.Tile]:
    return P.build_variant(scene(), variant, max_leaf_splats=500, reduction=2.0)


def first_merged(tiles: list[lod.Tile]) -> int:
    return max(t.level for t in tiles) - 1


def same(a: lod.Tile, b: lod.Tile, fields=("positions", "rotations", "log_scales", "opacity_logits", "sh_dc")) -> bool:
    return all(np.array_equal(getattr(a.gaussians, f), getattr(b.gaussians, f)) for f in fields)


def test_the_encoders_scale_is_the_base_tree_and_the_module_is_restored():
    before = (lod.finish_tile, lod.level_auto_groups, lod.appearance_terms, lod.finish_appearance)
    # The encoder's rule since 2026-11-30: 2 px on the first merged level, 8, 12, 16 px above it (lod.md 6 step 5).
    base, grown = build("base"), build("grow=8/1.5/16")
    assert after_restored(before)
    assert len(base) == len(grown) > 7 and all(same(a, b) for a, b in zip(base, grown, strict=True))
    assert [a.geometric_error for a in base] == [b.geometric_error for b in grown]
    # The rule of 2026-11-29 (8 px on every level above): px=2/8 and grow=8/1/inf are the same tree.
    two_eight, flat = build("px=2/8"), build("grow=8/1/inf")
    assert all(same(a, b) and a.geometric_error == b.geometric_error for a, b in zip(two_eight, flat, strict=True))


def after_restored(before) -> bool:
    return (lod.finish_tile, lod.level_auto_groups, lod.appearance_terms, lod.finish_appearance) == before


def test_scale_above_the_first_merged_level_changes_only_appearance_above_it():
    base, far = build("px=2/2"), build("px=2/8")  # before 2026-11-29 (every level at 2 px), 2026-11-29s
    first = first_merged(base)
    changed = 0
    for a, b in zip(base, far, strict=True):
        # The leaves and the first merged level are untouched; above it the opacities and colours differ, and so
        # may the groups (the cost grouping reads the children's opacities and colours).
        if a.level >= first:
            assert same(a, b) and a.geometric_error == b.geometric_error
        elif a.children:
            changed += not same(a, b, ("opacity_logits",))
    assert changed > 0
    # A smaller blur counts fewer sub-pixel members' dilated areas: merged splats are no more opaque on average.
    above = [t for t in base if t.children and t.level < first]
    assert np.mean([np.mean(b.gaussians.opacities) for b in far if b.children and b.level < first]) <= \
        np.mean([np.mean(a.gaussians.opacities) for a in above])


def test_rule_above_the_first_merged_level_keeps_the_first_merged_level():
    base, alt = build("base"), build("above:first_share=0.5")
    first = first_merged(base)
    assert all(same(a, b) for a, b in zip(base, alt, strict=True) if a.level >= first)
    assert any(not same(a, b) for a, b in zip(base, alt, strict=True) if a.level < first)


def test_optical_depth_opacity_of_two_members():
    # Two members of opacity 0.5 with the merged splat's area: summed coverage 1.0 (clamped to 0.99), optical depth
    # 2 log 2, so 1 - exp(-2 log 2) = 0.75.
    logits = np.zeros(2, np.float32)
    log_scales = np.full((2, 3), -2.0, np.float32)
    terms = P._optical_terms(logits, log_scales, np.zeros((2, 3), np.float32), 0.0)
    merged = Gaussians(np.zeros((1, 3), np.float32), np.array([[1, 0, 0, 0]], np.float32),
                       np.full((1, 3), -2.0, np.float32), np.zeros(1, np.float32), np.zeros((1, 3), np.float32),
                       np.zeros((1, 0, 3), np.float32))
    P._optical_finish(merged, np.array([2]), terms.sum(axis=1, keepdims=True), 0.0)
    assert abs(float(merged.opacities[0]) - 0.75) < 1e-6


def test_opacity_and_colour_scales_apart():
    # px=A/B is px=A/B/B; px=A/B/C with B != C matches opacity and colour apart, and the first merged level keeps A.
    base, far, same_two = build("base"), build("px=2/8"), build("px=2/8/8")
    assert all(same(a, b) for a, b in zip(far, same_two, strict=True))
    split = build("px=2/8/2")
    first = first_merged(base)
    assert all(same(a, b) for a, b in zip(base, split, strict=True) if a.level >= first)
    above = [(a, b, c) for a, b, c in zip(base, far, split, strict=True) if a.children and a.level < first]
    assert any(not same(b, c, ("sh_dc",)) for _, b, c in above)
    assert any(not same(a, c, ("opacity_logits",)) for a, _, c in above)


def test_grow_is_the_library_rule_and_the_constants_are_restored():
    # grow=A/G/CAP sets lod.OPACITY_MATCH_FAR_SSE_PX, _GROWTH and _CAP_SSE_PX for the build (issue 31, farpx31);
    # grow=8/1/inf is the rule of 2026-11-29, the px=2/8 tree.
    before = (lod.OPACITY_MATCH_FAR_SSE_PX, lod.OPACITY_MATCH_FAR_GROWTH, lod.OPACITY_MATCH_FAR_CAP_SSE_PX)
    base, same_rule, grow = build("px=2/8"), build("grow=8/1/inf"), build("grow=8/2/16")
    assert (lod.OPACITY_MATCH_FAR_SSE_PX, lod.OPACITY_MATCH_FAR_GROWTH, lod.OPACITY_MATCH_FAR_CAP_SSE_PX) == before
    assert all(same(a, b) and a.geometric_error == b.geometric_error for a, b in zip(base, same_rule, strict=True))
    first = first_merged(base)
    # k = 0 and 1 (8 px either way) keep their bits; k = 2 (16 px) and above differ.
    assert all(same(a, b) for a, b in zip(base, grow, strict=True) if a.level >= first - 1)
    assert any(not same(a, b) for a, b in zip(base, grow, strict=True) if a.level < first - 1)
    assert P.grow_px(1, 8, 1.5, 32) == 8 and P.grow_px(3, 8, 1.5, 32) == 18 and P.grow_px(5, 8, 1.5, 32) == 32


def test_opmax_lifts_the_ceiling_up_to_the_cap_and_nothing_else():
    before = (lod.finish_tile, lod.level_auto_groups, lod.appearance_terms, lod.finish_appearance)
    alpha = np.array([0.01, 0.5, 0.98, 1.0, 1.7, 8.0])
    assert np.allclose(P.over_opacity(P.over_logits(alpha)), alpha, atol=2e-6)
    logits = np.array([-20.0, -1.0, 0.0, 4.6, 13.8], np.float32)  # every logit an input can carry: the sigmoid
    assert np.array_equal(P.over_opacity(logits), 1.0 / (1.0 + np.exp(-logits)))
    base, lifted = build("base"), build("opmax=2")
    assert after_restored(before)
    first = first_merged(base)
    assert all(same(a, b) for a, b in zip(base, lifted, strict=True) if a.level > first)  # the leaves
    over = np.concatenate([P.over_opacity(t.gaussians.opacity_logits) for t in lifted if t.children])
    at_ceiling = np.concatenate([t.gaussians.opacities for t in base if t.children]) >= lod.MAX_MERGED_OPACITY - 1e-6
    assert at_ceiling.mean() > 0.2 and (over > 1.0).mean() > 0.2  # the 0.99 ceiling is gone ...
    assert over.max() <= 2.0 + 1e-5  # ... up to the cap
    # The first merged level: the same groups, so the same splats but for the opacities above 0.99.
    for a, b in zip(base, lifted, strict=True):
        if a.level == first and a.children:
            assert same(a, b, ("positions", "rotations", "log_scales", "sh_dc"))
            pa, pb = a.gaussians.opacities, P.over_opacity(b.gaussians.opacity_logits)
            below = pa < lod.MAX_MERGED_OPACITY - 1e-6  # below the ceiling: the same match
            assert np.allclose(pa[below], pb[below], atol=1e-5) and np.all(pb[~below] >= pa[~below] - 1e-5)
