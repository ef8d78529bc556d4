"""Probe (issue 31, phase 1): the real streaming cut with the merged levels refined on the GPU against renders of the
full-detail scene (bench/device/refine_lod_levels.py writes refine_<variant>_<k>.npz; BENCHMARKS.md, "Refining
the merged levels against the originals").

Replays THE REAL STREAMING CUT as bench/probe_lod_twoscale.py does: the tiles `splatstream view --headless
--max-splats N --no-prefetch` drew from each of the benchmark's 4 orbit views (`drawn_tile_ids_per_view` in a
bench/lod_vs_peers.py result JSON, today's default encode's cut) taken from our default tree built in memory
(refine_lod_levels.default_tree: 16,384-splat leaves, reduction 2, `auto`; its digest checked against the refined
file's, and the drawn splat counts against the JSON's), each drawn merged tile's splats carrying the refined deltas.
GL renderer at 384 px (client_gl, in-memory very-high upload), PSNR / SSIM against the cached full-detail render
(lod_vs_peers --cache-dir layout: CACHE/SCENE/full.ply, ref_<camera key>.npy; rendered and saved when missing), mean
of the 4 views. `today` (the unrefined tree replayed) must land within ~0.03 dB of the JSON's streamed PSNR; best
peer as bench/lod_vs_peers_compare.py.

    PYTHONPATH=. python bench/probe_lod_refine.py --refined RUN1_OUT RUN2_OUT --variants A B C \
        --results bench/results/lod_vs_peers_px28 --cache-dir /tmp/lvp50/cache --out /tmp/refine_replay.jsonl
    PYTHONPATH=. python bench/probe_lod_refine.py --results bench/results/lod_vs_peers_px28 --scenes statue-massa
        # no --refined: only the unrefined replay, against the JSON
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "device"))

import lod_vs_peers as lvp  # noqa: E402  (bench/ is not a package)
import refine_lod_levels as rl  # noqa: E402
from lod_vs_peers_compare import best_peer  # noqa: E402

from splatstream.camera import Camera  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402


def references(cache_dir: str, name: str, g: Gaussians, cams: list[Camera]) -> list[np.ndarray]:
    path = os.path.join(cache_dir, name, f"ref_{lvp.camera_key(cams)}.npy")
    if os.path.exists(path):
        return list(np.load(path))
    refs = lvp.render_views(g, cams)
    np.save(path, np.stack(refs))
    return refs


def cut_gaussians(tiles, ids: list[int]) -> Gaussians:
    return Gaussians.concatenate([tiles[i].gaussians for i in ids])


def replay_scene(name: str, args) -> list[dict]:
    from splatstream.io import read_gaussians

    res = json.load(open(os.path.join(args.results, f"{name}.json")))
    cams = [Camera.from_dict(c) for c in res["cameras"]]
    g = read_gaussians(os.path.join(args.cache_dir, name, "full.ply"))
    files = {}
    for v in args.variants:
        try:
            paths = sorted(p for d in args.refined for p in glob.glob(os.path.join(d, f"refine_{v}_*.npz")))
            files[v] = rl.read_refined(paths, name)
        except KeyError:
            print(f"{name}: no variant {v} in {args.refined}", file=sys.stderr)
    # a CPU test's file (refine_lod_levels --max-splats/--max-leaf): that small tree, whole levels only
    small = next((d for d, _, _ in files.values() if d.get("max_splats") or d.get("max_leaf") != rl.MAX_LEAF_SPLATS),
                 None)
    if small:
        g = g.subset(np.arange(min(small["max_splats"] or len(g), len(g))))
        refs = lvp.render_views(g, cams)  # not the cached full-detail render: another scene
        tiles = rl.default_tree(g, small["max_leaf"])
        digest = rl.tree_digest(tiles, small["max_leaf"], small["max_splats"])
        args.levels = True
    else:
        refs = references(args.cache_dir, name, g, cams)
        tiles = rl.default_tree(g)
        digest = rl.tree_digest(tiles)
    trees = {"today": tiles}
    for v, (theirs, refined, _) in files.items():
        rl.check_digest(digest, theirs)
        trees[v] = rl.replace_refined(tiles, refined)
    lines = []
    for row in [] if small else res["ours"]:
        ids_per_view = row["drawn_tile_ids_per_view"]
        drawn = [sum(len(tiles[i].gaussians) for i in ids) for ids in ids_per_view]
        assert drawn == row["splats_drawn_per_view"], (drawn, row["splats_drawn_per_view"])
        peer, who = best_peer(res, row["budget"])
        line = {"scene": name, "budget": row["budget"], "best_peer": peer, "best_peer_is": who,
                "streamed": row["psnr_mean"]}
        for label, tree in trees.items():
            imgs = [lvp.render_views(cut_gaussians(tree, ids), [c])[0] for ids, c in zip(ids_per_view, cams,
                                                                                         strict=True)]
            m = lvp.measure(imgs, refs)
            line[label] = m["psnr_mean"]
            line[label + "_ssim"] = m["ssim_mean"]
        lines.append(line)
        refined = "  ".join(f"{v} {line[v]:.2f} ({line[v] - peer:+.2f})" for v in trees if v != "today")
        print(f"{name:30s} {row['budget']:>7d}  best peer {peer:.2f} ({who})  streamed {row['psnr_mean']:.2f}  "
              f"today {line['today']:.2f} ({line['today'] - row['psnr_mean']:+.3f} vs streamed, "
              f"{line['today'] - peer:+.2f} vs peer)  {refined}", flush=True)
        if args.out:
            with open(args.out, "a") as f:
                print(json.dumps(line), file=f)
    if args.levels:  # each merged level's whole cut from the 4 views
        for d, (merged, fixed) in rl.level_cuts(tiles).items():
            ids = fixed + merged
            out = {"scene": name, "level": d, "splats": sum(len(tiles[i].gaussians) for i in ids)}
            for label, tree in trees.items():
                if label != "today" and not all(_refined(tree, tiles, i) for i in merged):
                    continue  # the file kept only the drawn tiles: this level is not whole
                out[label] = lvp.measure(lvp.render_views(cut_gaussians(tree, ids), cams), refs)["psnr_mean"]
            print(f"{name:30s} level {d}: {out}", flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    print(json.dumps(out), file=f)
    return lines


def _refined(tree, tiles, i: int) -> bool:
    return tree[i] is not tiles[i]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=os.path.join(HERE, "results", "lod_vs_peers_px28"))
    ap.add_argument("--cache-dir", default="/tmp/lvp50/cache")
    ap.add_argument("--refined", nargs="+", default=None,
                    help="the device runs' $OUT folders (refine_<variant>_<k>.npz; the runs' files share names)")
    ap.add_argument("--variants", nargs="*", default=["A", "B", "C"])
    ap.add_argument("--scenes", nargs="+", default=None, help="default: those with a JSON in --results")
    ap.add_argument("--levels", action="store_true", help="also each merged level's whole cut")
    ap.add_argument("--out", default=None, help="append one JSON line per result here")
    args = ap.parse_args()
    if not args.refined:
        args.variants = []
    names = args.scenes or [n for n in lvp.SCENES if os.path.exists(os.path.join(args.results, f"{n}.json"))]
    rows = [line for n in names for line in replay_scene(n, args)]
    for v in args.variants:
        got = [r for r in rows if v in r]
        if got:
            wins = sum(r[v] - r["best_peer"] >= 1.0 for r in got)
            today = sum(r["today"] - r["best_peer"] >= 1.0 for r in got)
            gain = np.median([r[v] - r["today"] for r in got])
            print(f"variant {v}: {wins}/{len(got)} points >= 1 dB over the best peer (today {today}); "
                  f"median gain over today {gain:+.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
