"""Probe: merge groups chosen by cost, whole-scene levels (issue 31; BENCHMARKS.md, "LOD groups by cost").

Each level is built from the one before it (a 2x-ish chain as the tree builds it: 50, 25, 12.5, 6, 3, 2 % of the
scene), merged by the tree's own merge (lod.merge_groups: mass weights carried from the originals, moment
matching, opacity = mass / area), over the whole scene (no tiles). The levels of 50, 25, 6 and 2 % (the counts of
bench/lod_vs_peers.py) are drawn by the GL renderer from its 4 orbit views at 384 px and compared with the
full-detail render: PSNR of the mean MSE over the views. splat-transform's levels of the same counts (its
--decimate-adaptive, chained the same way) are read from bench/lod_vs_peers.py's cache, never re-run here.

    python bench/probe_lod_groups.py statue-angel donut fruit_drops flowers-crop guitar --rule grid --rule hybrid \
        --rule cost:proj=1,max_group=4 --rule cost:proj=1,first_cap=2,max_group=4 [--json results.jsonl]

Rules: `grid` (lod._group_starts, the product's Morton grid), `cost[:k=v,...]` (splatstream.lod_groups.group_ids
with the GroupRule fields given), `hybrid[:SIZE]` (lod_groups.hybrid_group_ids, its proxy at SIZE px; `hybrid0` is
the same), `mix:F:RULE` (RULE for levels of at least F, the grid below). Scenes: the names of bench/lod_vs_peers.py
(its cache must hold full.ply), and `fruit_drops`, `flowers-crop` (the splats within the 25 % quantile of the
per-axis distance from the median).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from lod_vs_peers import budget_counts, camera_key, render_views, view_cameras  # noqa: E402

from splatstream import lod, lod_groups  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.metrics import psnr_from_mse  # noqa: E402
from splatstream.orientation import detect_up  # noqa: E402

HERE = Path(__file__).parent
CACHE = HERE / "peers_cache"
DATA = Path(os.environ.get("SPLATSTREAM_REAL", HERE.parent.parent / "shared" / "data" / "real"))
CHAIN = [0.5, 0.25, 0.125, 0.06, 0.03, 0.02]
MEASURED = [0.5, 0.25, 0.06, 0.02]
C0 = 0.28209479177387814
CHOICES: list[int] = []  # the hybrid's choice per level (0, 1: its cost rules, 2: the grid)


def load_scene(name: str) -> tuple[Gaussians, str | None]:
    """The scene's splats and its bench/lod_vs_peers.py cache directory (None: no peer levels)."""
    if name == "fruit_drops":
        return read_gaussians(str(DATA / "fruit_drops_sh3.ply")), None
    if name.startswith("flowers-crop"):
        g = read_gaussians(str(CACHE / "flowers" / "full.ply"))
        d = np.abs(g.positions - np.median(g.positions, axis=0))
        cheb = d.max(axis=1)
        return g.subset(np.flatnonzero(cheb <= np.quantile(cheb, 0.25))), None
    return read_gaussians(str(CACHE / name / "full.ply")), str(CACHE / name)


def group_with(rule: str, g: Gaussians, mass: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    if rule == "grid":
        return lod._group_starts(g.positions, target)
    name, _, params = rule.partition(":")
    if name in ("hybrid", "hybrid0"):  # hybrid[:SIZE]: lod_groups.hybrid_group_ids, the proxy at SIZE px (0: its
        # default); hybrid0 is the same (the name of an earlier run's rule)
        with np.errstate(over="ignore"):
            alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
        ids, pick = lod_groups.hybrid_group_ids(g.positions, g.log_scales, g.rotations, alpha,
                                                0.5 + C0 * g.sh_dc.astype(np.float64), mass, target,
                                                size=int(params or 0))
        CHOICES.append(pick)
        assert len(np.unique(ids)) == target, (len(np.unique(ids)), target)
        return lod_groups.group_runs(ids)
    assert name == "cost", rule
    kw = {}
    for item in filter(None, params.split(",")):
        k, v = item.split("=")
        kw[k] = type(getattr(lod_groups.DEFAULT_RULE, k))(float(v))
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    ids = lod_groups.group_ids(g.positions, g.log_scales, g.rotations, alpha, 0.5 + C0 * g.sh_dc.astype(np.float64),
                               mass, target, dataclasses.replace(lod_groups.DEFAULT_RULE, **kw))
    assert len(np.unique(ids)) == target, (len(np.unique(ids)), target)
    return lod_groups.group_runs(ids)


def psnr(s: Gaussians, cams, refs) -> float:
    imgs = render_views(s, cams)
    mse = np.mean([np.mean((np.clip(a, 0, 1) - np.clip(r, 0, 1)) ** 2) for a, r in zip(imgs, refs, strict=True)])
    return psnr_from_mse(float(mse))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--rule", action="append", default=[])
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--json", help="append one JSON line per scene and rule here")
    args = ap.parse_args()
    for name in args.scenes:
        g, sdir = load_scene(name)
        n = len(g)
        cams = view_cameras(g.positions, detect_up(g).up, 4, args.size)
        key = camera_key(cams)
        ref_path = os.path.join(sdir, f"ref_{key}.npy") if sdir else f"/tmp/probe_lod_groups_{name}_{key}.npy"
        if os.path.exists(ref_path):
            refs = list(np.load(ref_path))
        else:
            refs = render_views(g, cams)
            np.save(ref_path, np.stack(refs))
        counts = dict(zip(CHAIN, budget_counts(n, CHAIN), strict=True))
        peer = {}
        if sdir:
            for f in MEASURED:
                m = os.path.join(sdir, f"st-adaptive_{counts[f]}.ply.metrics_{key}.json")
                if os.path.exists(m):
                    peer[counts[f]] = json.load(open(m))["psnr_mean"]
        print(f"{name}: {n:,} splats; levels {[counts[f] for f in MEASURED]}; splat-transform "
              f"{[peer.get(counts[f]) for f in MEASURED]}", flush=True)
        for rule in args.rule or ["grid"]:
            cur, mass = g, lod.splat_mass(g)
            row, secs = {}, 0.0
            CHOICES.clear()
            for f in CHAIN:
                t = time.perf_counter()
                level_rule = rule
                if rule.startswith("mix"):  # mix:F:COST_RULE: the cost rule for levels of at least F, the grid below
                    _, frac, level_rule = rule.split(":", 2)
                    level_rule = level_rule if f >= float(frac) else "grid"
                order, starts = group_with(level_rule, cur, mass, counts[f])
                cur, mass, _ = lod.merge_groups(cur, mass, order, starts)
                secs += time.perf_counter() - t
                if f in MEASURED:
                    row[counts[f]] = round(psnr(cur, cams, refs), 2)
            picks = f" chose {CHOICES}" if CHOICES else ""
            print(f"  {rule:40s} " + " / ".join(f"{v:.2f}" for v in row.values()) + f"   ({secs:.1f} s grouping)"
                  + picks, flush=True)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps({"scene": name, "splats": n, "rule": rule, "psnr": row, "peer": peer,
                                         "seconds": round(secs, 2), "choices": CHOICES}) + "\n")


if __name__ == "__main__":
    main()
