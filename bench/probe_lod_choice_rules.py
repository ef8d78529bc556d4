"""Probe (issue 31): how `encode --lod-merge auto`'s per-tile choice between the cost merge's groups and the Morton
grid's (lod.level_auto_groups, the rule in the code: lod.AUTO_RULE's grouping, the choice by lod.auto_tile_choice on
every lod.AUTO_CHOICE_SAMPLE-th group at the first merged level only) would move under other judging rules, level by
level. Builds the tree as the encoder does (lod.build_subtree, 16,384-splat leaves, reduction 2) with
lod.level_auto_groups wrapped: each level grouped by lod.level_cost_groups at the code's rule (lod.AUTO_RULE,
imported, not copied), then on every tile the code judges (blur 0, the first merged level; every level with
--every-level, as `judge_every_level=True`) the choice taken under each rule below, the tree following `--follow`
(default `code`: the tree the encoder builds). It prints per judged level the share of tiles on which each rule
picks the grid and, for the rules measured on every group, the level's log10(sum cost error / sum grid error):

* `code`: the code's own choice, lod.auto_tile_choice at lod.AUTO_CHOICE_SAMPLE (grid share only: its errors are
  of the sampled groups);
* `cap1`: lod.choice_error on every group (merged opacity capped at 1, blur of the children's error);
* `cap4`: the same with 4x that blur's variance (the error 2x larger: about the tile's own error, at which the
  client draws it, or more);
* `uncap1`: the merged opacity not capped at 1 (stacked opaque members then cost what their shapes cost, not their
  summed opacity);
* `proxy`: the candidates' merged splats against the members drawn by lod_groups.proxy_views (alpha-composited).

    PYTHONPATH=. python bench/probe_lod_choice_rules.py shared/data/real/biker.compressed.ply [--follow cap1]
        [--every-level]
"""
import argparse
import time

import numpy as np

from splatstream import io as sio
from splatstream import lod
from splatstream.gaussians import SH_C0
from splatstream.lod_groups import _moments, covariances6, group_errors, proxy_views

# rule: (kind, blur scale); "code" is lod.auto_tile_choice itself
RULES = {"code": ("code", 1.0), "cap1": ("choice", 1.0), "cap4": ("choice", 4.0), "uncap1": ("uncap", 1.0),
         "proxy": ("proxy", 1.0)}
REC: list[dict | None] = []  # per level built, leaves first: None where no tile was judged
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


def uncapped_error(members, ids, blur):
    """lod.choice_error's measure without the cap of the merged opacity at 1."""
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-members.opacity_logits.astype(np.float64)))
    variances = np.exp(2.0 * members.log_scales.astype(np.float64)) + blur
    shown = alpha * lod._coverage_area(members.log_scales, blur)
    colours = 0.5 + SH_C0 * members.sh_dc.astype(np.float64)
    # Opacities and masses both divided by UNCAP, so the merged opacity (mass / area) never reaches the cap of 1;
    # every field then scales by 1 / UNCAP, the error by 1 / UNCAP^2, undone here.
    return float(group_errors(members.positions, 0.5 * np.log(variances), members.rotations, alpha / UNCAP, colours,
                              shown / UNCAP, ids, proj=True).sum()) * UNCAP * UNCAP


def make_recorder(follow: str, every_level: bool):
    """lod.level_auto_groups' stand-in: the code's grouping (its own defaults: lod.AUTO_RULE,
    lod.AUTO_CHOICE_SAMPLE), each judged tile's choice under every rule recorded, the tree following `follow`."""
    def level_auto_groups(members, masses, targets, cap, blurs, rule=lod.AUTO_RULE, pool=None,
                          sample=lod.AUTO_CHOICE_SAMPLE, judge_every_level=False):
        groups = lod.level_cost_groups(members, masses, targets, cap, rule, pool)
        rec = {name: [] for name in RULES}
        for t, (order, starts) in enumerate(groups):
            if not (every_level or judge_every_level or blurs[t] == 0.0):
                continue  # the code keeps the cost merge's groups here
            n, k = len(members[t]), len(starts)
            if n == 0 or k >= n:
                continue
            g_order, g_starts = lod._group_starts(members[t].positions, k)
            if len(g_starts) != k:
                continue
            cost_ids, grid_ids = lod._run_ids(order, starts, n), lod._run_ids(g_order, g_starts, n)
            cache: dict = {}
            for name, (kind, scale) in RULES.items():
                b = blurs[t] * scale
                if kind == "code":
                    _, grid = lod.auto_tile_choice(members[t], (order, starts), b, sample)
                    rec[name].append((1.0, 0.0) if grid else (0.0, 1.0))  # (cost, grid): only which is smaller
                elif kind == "choice":
                    prepared = lod.choice_members(members[t], b)
                    rec[name].append((lod.choice_error(members[t], cost_ids, b, prepared),
                                      lod.choice_error(members[t], grid_ids, b, prepared)))
                elif kind == "uncap":
                    rec[name].append((uncapped_error(members[t], cost_ids, b),
                                      uncapped_error(members[t], grid_ids, b)))
                else:
                    rec[name].append((proxy_error(members[t], cost_ids, b, cache),
                                      proxy_error(members[t], grid_ids, b, cache)))
            c, g = rec[follow][-1]
            if g < c:
                groups[t] = (g_order, g_starts)
        if any(rec.values()):
            REC.append({"level_tiles": len(members), "blur": float(np.median(blurs)), "rec": rec})
        else:
            REC.append(None)
        return groups, []
    return level_auto_groups


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("ply")
    ap.add_argument("--follow", default="code", choices=list(RULES))
    ap.add_argument("--every-level", action="store_true",
                    help="judge every level's tiles, not only the first merged level's (judge_every_level)")
    a = ap.parse_args()
    lod.level_auto_groups = make_recorder(a.follow, a.every_level)
    g = sio.read_gaussians(a.ply)
    shape = lod.TreeShape.of(len(g), 16384, 2.0)
    t0 = time.process_time()
    sub = lod.build_subtree(g, np.arange(len(g)), shape, 0, 0, merge="auto")
    print(f"# {a.ply}: {len(g)} splats, lod.AUTO_RULE {lod.AUTO_RULE}, sample {lod.AUTO_CHOICE_SAMPLE}, following "
          f"{a.follow}{', every level' if a.every_level else ''}, {time.process_time() - t0:.1f} CPU s")
    print("level judged/tiles blur_p50 | " + " | ".join(f"{n}: grid share, log10 sum cost/grid" for n in RULES))
    for i, r in enumerate(REC):
        lvl = shape.leaf_level - 1 - i
        if r is None:
            continue
        errs = [t.geometric_error for t in sub.tiles.values() if t.level == lvl]
        cells = []
        for name in RULES:
            e = np.array(r["rec"][name]).reshape(-1, 2)
            share = np.mean(e[:, 1] < e[:, 0]) if len(e) else float("nan")
            ratio = np.log10(e[:, 0].sum() / max(e[:, 1].sum(), 1e-300)) if len(e) else float("nan")
            cells.append(f"{share:.2f}" if name == "code" else f"{share:.2f} {ratio:+.3f}")
        print(f"L{lvl} {len(r['rec']['code'])}/{r['level_tiles']} {r['blur']:.2e} (own err p50 "
              f"{np.median(errs):.3g}) | " + " | ".join(cells))


if __name__ == "__main__":
    main()
