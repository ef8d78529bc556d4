"""Probe (issue 31, branch lodmix): what the groups of each tree level look like under a merge (`grid`, `cost`,
`auto`), to see why the cost merge loses on some scenes. Builds the tree as the encoder does (lod.build_subtree,
16,384-splat leaves, reduction 2, one thread so the merges come level by level, tile by tile) and prints per tile
level: group sizes (share of groups of 1, 2, 3, 4, more members), the share of members left single, the share each
tile keeps (5th/50th/95th percentile over the level's tiles), the spread of a group (mass-weighted mean squared
distance of the members to the merged centre over their mean variance), the colour variance inside a group
(mass-weighted, base colour), the growth of the largest axis (merged over the members' mass-weighted mean) and the
merged opacity (mass / area, before the viewing-scale step). Numbers in BENCHMARKS.md ("per-tile choice").

    PYTHONPATH=. python bench/probe_lod_group_stats.py bench/peers_cache/flowers/full.ply cost

With `choice` instead of a merge: the first merged level only, grouped as `auto` does (lod.level_auto_groups: the
cost merge's groups, the grid at the same count per tile), and per tile log10 of the cost merge's choice_error over
the grid's (no blur: the children are leaves), with the level's sum.
"""
import sys
import time

import numpy as np

from splatstream import io as sio
from splatstream import lod
from splatstream.gaussians import SH_C0

REC: list[dict] = []
_merge_groups = lod.merge_groups


def recording_merge(g, mass, order, starts):
    """lod.merge_groups, recording what its groups look like."""
    out = _merge_groups(g, mass, order, starts)
    merged, merged_mass, assign = out
    k = len(starts)
    count = np.bincount(assign, minlength=k)
    w = mass + 1e-300
    f = w / np.bincount(assign, weights=w, minlength=k)[assign]
    p = g.positions.astype(np.float64)
    d2 = ((p - merged.positions.astype(np.float64)[assign]) ** 2).sum(1)
    var = np.exp(2 * g.log_scales.astype(np.float64)).mean(1)
    spread = (np.bincount(assign, weights=f * d2, minlength=k)
              / np.maximum(np.bincount(assign, weights=f * var, minlength=k), 1e-300))
    col = 0.5 + SH_C0 * g.sh_dc.astype(np.float64)
    mean_col = np.stack([np.bincount(assign, weights=f * col[:, c], minlength=k) for c in range(3)], 1)
    cvar = np.bincount(assign, weights=f * ((col - mean_col[assign]) ** 2).sum(1), minlength=k)
    largest = np.bincount(assign, weights=f * np.exp(g.log_scales.astype(np.float64)).max(1), minlength=k)
    growth = np.exp(merged.log_scales.astype(np.float64)).max(1) / np.maximum(largest, 1e-300)
    alpha = 1 / (1 + np.exp(-merged.opacity_logits.astype(np.float64)))
    multi = count > 1
    REC.append({"n": len(g), "k": k, "count": count, "spread": spread[multi], "cvar": cvar[multi],
                "growth": growth[multi], "alpha": alpha[multi]})
    return out


def q(a: np.ndarray, fmt: str) -> str:
    return f"{np.median(a):{fmt}}/{np.percentile(a, 90):{fmt}}"


def main(path: str, merge: str) -> None:
    lod.merge_groups = recording_merge
    g = sio.read_gaussians(path)
    shape = lod.TreeShape.of(len(g), 16384, 2.0)
    t0 = time.process_time()
    lod.build_subtree(g, np.arange(len(g)), shape, 0, 0, threads=1, merge=merge)
    print(f"# {path} {merge}: {len(g)} splats, {time.process_time() - t0:.1f} CPU s, {shape.leaf_level} levels")
    print("level tiles members groups | groups of 1/2/3/4/more | members single | kept per tile p5/p50/p95 "
          "| spread p50/p90 | colour var p50/p90 | growth p50/p90 | merged alpha p50")
    at = 0
    for lvl in range(shape.leaf_level - 1, -1, -1):
        span = 2 ** (shape.kd_depths[lvl] - shape.kd_depths[0])
        recs = REC[at:at + span]
        at += span
        n, k = sum(r["n"] for r in recs), sum(r["k"] for r in recs)
        count = np.concatenate([r["count"] for r in recs])
        kept = np.array([r["k"] / max(r["n"], 1) for r in recs])
        cat = {key: np.concatenate([r[key] for r in recs]) for key in ("spread", "cvar", "growth", "alpha")}
        sizes = [np.mean(count == s) for s in (1, 2, 3, 4)] + [np.mean(count > 4)]
        print(f"L{lvl} {span} {n} {k} | " + "/".join(f"{h:.2f}" for h in sizes)
              + f" | {np.sum(count == 1) / n:.2f} | " + "/".join(f"{np.percentile(kept, x):.2f}" for x in (5, 50, 95))
              + f" | {q(cat['spread'], '.2f')} | {q(cat['cvar'], '.4f')} | {q(cat['growth'], '.2f')}"
              + f" | {np.median(cat['alpha']):.2f}")


def first_level_choice(path: str) -> None:
    g = sio.read_gaussians(path)
    shape = lod.TreeShape.of(len(g), 16384, 2.0)
    leaves = lod._kd_leaves(g.positions, np.arange(len(g)), shape.depth - shape.kd_depths[0], lambda *a: None)
    span = 2 ** shape.kd_depths[shape.leaf_level - 1]
    per = len(leaves) // span
    sets = [lod._permute(g, np.concatenate(leaves[j * per:(j + 1) * per])) for j in range(span)]
    masses = [lod.splat_mass(m) for m in sets]
    groups = lod.level_cost_groups(sets, masses, [shape.target(len(m)) for m in sets], shape.max_leaf_splats)
    cost, grid = [], []
    for m, (order, starts) in zip(sets, groups, strict=True):
        g_order, g_starts = lod._group_starts(m.positions, len(starts))
        if len(g_starts) != len(starts):
            continue
        cost.append(lod.choice_error(m, lod._run_ids(order, starts, len(m)), 0.0))
        grid.append(lod.choice_error(m, lod._run_ids(g_order, g_starts, len(m)), 0.0))
    r = np.log10(np.array(cost) / np.array(grid))
    print(f"{path}: log10(cost / grid) per tile p10/p50/p90 "
          + "/".join(f"{np.percentile(r, x):+.2f}" for x in (10, 50, 90))
          + f", level sum {np.log10(sum(cost) / sum(grid)):+.3f}, grid chosen on {np.mean(r > 0):.2f} of the tiles")


if __name__ == "__main__":
    if sys.argv[2] == "choice":
        first_level_choice(sys.argv[1])
    else:
        main(sys.argv[1], sys.argv[2])
