"""Probe (issue 31, branch lodauto): how `encode --lod-merge auto`'s per-tile choice between the cost merge's groups
and the Morton grid's (lod.level_auto_groups) moves under other judging rules, level by level, before any
streaming-cut run. Builds the tree as the encoder does (lod.build_subtree, 16,384-splat leaves, reduction 2), the
tree following `--follow` (the rule whose choices are kept), and prints per tile level the share of tiles on which
the grid would be chosen, and the level's log10(sum cost error / sum grid error), under each rule:

* `cap1`: lod.choice_error as of lodmix (merged opacity capped at 1, blur of the children's error at 2 px);
* `cap4`: the same with 4x that blur's variance (the error 2x larger: about the tile's own error, at which the
  client draws it, or more);
* `uncap1`: the merged opacity not capped at 1 (stacked opaque members then cost what their shapes cost, not their
  summed opacity);
* `proxy`: the candidates' merged splats against the members drawn by lod_groups.proxy_views (alpha-composited).

    PYTHONPATH=. python bench/probe_lod_choice_rules.py bench/peers_cache/flowers/full.ply --follow uncap1
"""
import argparse
import time

import numpy as np

from splatstream import io as sio
from splatstream import lod
from splatstream.gaussians import SH_C0
from splatstream.lod_groups import _moments, covariances6, group_errors, proxy_views

RULES = {"cap1": (True, 1.0), "cap4": (True, 4.0), "uncap1": (False, 1.0), "proxy": (None, 1.0)}
REC: list[dict] = []
UNCAP = 1e6


def proxy_error(members, ids, blur, ref_cache):
    """Squared error of the candidate's merged splats against the members, both drawn by lod_groups.proxy_views
    (6 axis views, alpha-composited, 2 sqrt(groups) px across within 64..128: each merged splat about 2 px)."""
    p = members.positions.astype(np.float64)
    cov = covariances6(members.rotations, members.log_scales)
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-members.opacity_logits.astype(np.float64)))
    col = 0.5 + SH_C0 * members.sh_dc.astype(np.float64)
    groups = int(ids.max()) + 1
    size = int(min(128, max(64, 2 * np.sqrt(groups))))
    box = (p.min(axis=0), p.max(axis=0))
    if "ref" not in ref_cache:
        ref_cache["ref"] = proxy_views(p, cov, alpha, col, box, size)
    w = alpha * lod._coverage_area(members.log_scales, blur) + 1e-30
    mu, cm, am, cl = _moments(p, cov, alpha, col, w, ids, groups)
    return float(np.mean((proxy_views(mu, cm, am, cl, box, size) - ref_cache["ref"]) ** 2))


def error(members, ids, blur, cap):
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-members.opacity_logits.astype(np.float64)))
    variances = np.exp(2.0 * members.log_scales.astype(np.float64)) + blur
    shown = alpha * lod._coverage_area(members.log_scales, blur)
    colours = 0.5 + SH_C0 * members.sh_dc.astype(np.float64)
    # Uncapped: opacities and masses both divided by UNCAP, so the merged opacity (mass / area) never reaches the
    # cap of 1; every field then scales by 1 / UNCAP, the error by 1 / UNCAP^2, undone here.
    k = 1.0 if cap else UNCAP
    return float(group_errors(members.positions, 0.5 * np.log(variances), members.rotations, alpha / k, colours,
                              shown / k, ids, proj=True).sum()) * k * k


def make_recorder(follow: str):
    def level_auto_groups(members, masses, targets, cap, blurs, rule=lod.COST_RULE):
        groups = lod.level_cost_groups(members, masses, targets, cap, rule)
        rec = {name: [] for name in RULES}
        for t, (order, starts) in enumerate(groups):
            n, k = len(members[t]), len(starts)
            if n == 0 or k >= n:
                continue
            g_order, g_starts = lod._group_starts(members[t].positions, k)
            if len(g_starts) != k:
                continue
            cost_ids, grid_ids = lod._run_ids(order, starts, n), lod._run_ids(g_order, g_starts, n)
            cache: dict = {}
            for name, (capped, scale) in RULES.items():
                b = blurs[t] * scale
                if capped is None:
                    rec[name].append((proxy_error(members[t], cost_ids, b, cache),
                                      proxy_error(members[t], grid_ids, b, cache)))
                    continue
                rec[name].append((error(members[t], cost_ids, b, capped), error(members[t], grid_ids, b, capped)))
            c, g = rec[follow][-1]
            if g < c:
                groups[t] = (g_order, g_starts)
        REC.append({"tiles": len(members), "blur": float(np.median(blurs)), "rec": rec})
        return groups, []
    return level_auto_groups


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("ply")
    ap.add_argument("--follow", default="cap1", choices=list(RULES))
    a = ap.parse_args()
    lod.level_auto_groups = make_recorder(a.follow)
    g = sio.read_gaussians(a.ply)
    shape = lod.TreeShape.of(len(g), 16384, 2.0)
    t0 = time.process_time()
    sub = lod.build_subtree(g, np.arange(len(g)), shape, 0, 0, merge="auto")
    print(f"# {a.ply}: {len(g)} splats, following {a.follow}, {time.process_time() - t0:.1f} CPU s")
    print("level tiles blur_p50 | " + " | ".join(f"{n}: grid share, log10 sum cost/grid" for n in RULES))
    for i, r in enumerate(REC):
        lvl = shape.leaf_level - 1 - i
        errs = [t.geometric_error for t in sub.tiles.values() if t.level == lvl]
        cells = []
        for name in RULES:
            e = np.array(r["rec"][name]).reshape(-1, 2)
            share = np.mean(e[:, 1] < e[:, 0]) if len(e) else float("nan")
            ratio = np.log10(e[:, 0].sum() / max(e[:, 1].sum(), 1e-300)) if len(e) else float("nan")
            cells.append(f"{share:.2f} {ratio:+.3f}")
        print(f"L{lvl} {r['tiles']} {r['blur']:.2e} (own err p50 {np.median(errs):.3g}) | " + " | ".join(cells))


if __name__ == "__main__":
    main()
