"""Probe (issue 31, distill31): is the GPU refinement's gain on the merged levels SYSTEMATIC enough for a CPU rule?

For each scene, our default tree is built in memory (bench/device/refine_lod_levels.default_tree: the encoder's
defaults, `auto` merge), and the product's refined encode of the same scene (`splatstream encode full.ply OUT
--lod-refine`, /tmp/refined/SCENE) is read back: the refinement changes only the merged splats' values, so both trees
have the same tiles (ids, levels, children, splat counts: checked). The encoder stores a tile's splats in its own
order (morton chunks, luminance inside a chunk), so each refined splat is paired with a built splat of the same tile:
the nearest in position (in units of the built splat's largest scale), sorted log-scales, rotation and the untouched
higher SH bands among the +-WINDOW neighbours in a common morton order; only pairs claimed once are kept (their share
is printed: 88-94 %; leaves pair 100 %). Deltas refined - built (the refined side
through the medium preset's quantisation) of: mean log-scale and each sorted axis, opacity (logit and value; the
refined opacity clamped at 0.99 as every renderer here clamps it), DC colour and its luminance, and the position shift
in built-scale units; features: the level from the leaves (1 = first merged level), built opacity at the 0.99
ceiling or not, and the splat's geometric-mean scale in pixels of its tile's viewing scale (lod.viewing_scale_px:
2/8/12/16 px by level).

Then the real streaming cut is replayed (bench/probe_lod_refine.py's way: the tiles lod_vs_peers drew per view, GL
renderer, 384 px, 4 views, against the cached full-detail renders) for
    today:      the default tree;
    refined:    its merged tiles replaced by the refined encode's decoded tiles (quantised; the leaves unquantised);
    systematic: the default tree with, per merged splat, the MEAN delta of its cell (level x ceiling x size bin)
                fitted on the OTHER scenes (leave one scene out; each training scene's cell mean weighted equally)
                of the log-scale of each sorted axis (smallest, middle, largest), opacity logit and DC colour.

    PYTHONPATH=. python bench/probe_lod_distill.py --out D/deltas.jsonl        # the deltas (cached: /tmp/distill31)
    PYTHONPATH=. python bench/probe_lod_distill.py --replay --out D/replay.jsonl   # the 12 scenes' LOSO replay
    PYTHONPATH=. python bench/probe_lod_distill.py --appearance-only --replay donut statue-massa statue-angel guitar \
        --out D/appearance.jsonl    # the refined per-splat appearance on the built positions and rotations
    PYTHONPATH=. python bench/probe_lod_distill.py --summary D/replay.jsonl D/appearance.jsonl
(--results: today's default cut, bench/results/lod_vs_peers_farpx31_g15c16, whose drawn splat counts the tree built
here matches; D = bench/results/lod_distill31.)
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "device"))

import lod_vs_peers as lvp  # noqa: E402  (bench/ is not a package)
import probe_lod_refine as plr  # noqa: E402
import refine_lod_levels as rl  # noqa: E402
from lod_vs_peers_compare import best_peer  # noqa: E402

from splatstream import lod  # noqa: E402
from splatstream.camera import Camera  # noqa: E402
from splatstream.format.layout import morton_codes  # noqa: E402
from splatstream.gaussians import SH_C0, Gaussians  # noqa: E402

WINDOW = 384  # morton ranks searched either side (chunks of 256 are luminance-ordered inside)
CEIL = 0.99
SIZE_EDGES = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])  # log2(scale / viewing pixel) bin edges
MAX_HEIGHT = 5  # levels from the leaves pooled above this
LUMA = np.array([0.299, 0.587, 0.114])
MIN_CELL = 50  # splats a training scene needs in a cell to count


def heights(tiles: list[lod.Tile]) -> list[int]:
    """0 for leaves, else 1 + the largest of the children's (1 = first merged level)."""
    h = [0] * len(tiles)
    for t in reversed(tiles):  # children ids > parent id
        h[t.id] = 1 + max(h[c] for c in t.children) if t.children else 0
    return h


def viewing_pixel(tile: lod.Tile, height: int) -> float:
    """World size of one pixel where the tile is matched (lod.tile_viewing_blur's scale)."""
    px = lod.viewing_scale_px(0.0 if height == 1 else 1.0, max(height - 1, 1))
    return max(tile.geometric_error, 1e-12) / px


def features(g: Gaussians, tile: lod.Tile, height: int) -> dict[str, np.ndarray]:
    size = np.log2(np.exp(g.log_scales.astype(np.float64).mean(axis=1)) / viewing_pixel(tile, height))
    return {"height": np.full(len(g), min(height, MAX_HEIGHT), np.int8),
            "ceil": (g.opacities >= CEIL - 1e-4).astype(np.int8),
            "size": size.astype(np.float32),
            "size_bin": np.searchsorted(SIZE_EDGES, size).astype(np.int8)}


def cell_of(f: dict[str, np.ndarray]) -> np.ndarray:
    return (f["height"].astype(np.int32) * 2 + f["ceil"]) * (len(SIZE_EDGES) + 1) + f["size_bin"]


def pair(built: Gaussians, refined: Gaussians) -> np.ndarray:
    """For each refined splat, the index of its built splat (-1: not claimed once)."""
    n = len(built)
    lo = np.minimum(built.positions.min(0), refined.positions.min(0))
    hi = np.maximum(built.positions.max(0), refined.positions.max(0))
    ob = np.argsort(morton_codes(built.positions, lo, hi), kind="stable")
    orr = np.argsort(morton_codes(refined.positions, lo, hi), kind="stable")
    s = np.exp(built.log_scales.astype(np.float64).max(1))[ob]
    pb = built.positions[ob].astype(np.float64)
    pr = refined.positions[orr].astype(np.float64)
    lb = np.sort(built.log_scales[ob].astype(np.float64), 1)
    lr = np.sort(refined.log_scales[orr].astype(np.float64), 1)
    qb = built.rotations[ob].astype(np.float64)
    qr = refined.rotations[orr].astype(np.float64)
    qb /= np.linalg.norm(qb, axis=1, keepdims=True)
    qr /= np.linalg.norm(qr, axis=1, keepdims=True)
    rb = built.sh_rest.reshape(n, -1)[ob].astype(np.float64) if built.sh_rest.size else None
    rr = refined.sh_rest.reshape(n, -1)[orr].astype(np.float64) if refined.sh_rest.size else None
    best = np.empty(n, np.int64)
    offs = np.arange(-WINDOW, WINDOW + 1)
    for a in range(0, n, 256):
        i = np.arange(a, min(a + 256, n))
        cand = np.clip(i[:, None] + offs[None, :], 0, n - 1)
        d = (((pb[cand] - pr[i, None, :]) ** 2).sum(-1)) / (s[cand] ** 2)
        d = d + ((lb[cand] - lr[i, None, :]) ** 2).sum(-1) / 0.25
        d = d + (1.0 - np.abs((qb[cand] * qr[i, None, :]).sum(-1))) / 0.02
        if rb is not None:
            d = d + ((rb[cand] - rr[i, None, :]) ** 2).sum(-1) / 0.01
        best[i] = cand[np.arange(len(i)), d.argmin(1)]
    out = np.full(n, -1, np.int64)
    claims = np.bincount(best, minlength=n)
    once = claims[best] == 1
    out[orr[once]] = ob[best[once]]
    return out


def scene_deltas(name: str, cache_dir: str, refined_dir: str) -> tuple[dict, list[lod.Tile], dict[int, Gaussians]]:
    from splatstream.io import read_gaussians
    from splatstream.scene_decode import decode_tile
    from splatstream.store import open_store, read_manifest

    g = read_gaussians(os.path.join(cache_dir, name, "full.ply"))
    tiles = rl.default_tree(g)
    store = open_store(os.path.join(refined_dir, name))
    m = read_manifest(store)
    same = len(m.tiles) == len(tiles) and all(
        a.id == b.id and a.level == b.level and tuple(a.children) == tuple(b.children) and a.splats == len(b.gaussians)
        for a, b in zip(m.tiles, tiles, strict=True))
    if not same:
        raise SystemExit(f"{name}: the refined encode's tree is not the default tree built here")
    h = heights(tiles)
    rows: dict[str, list[np.ndarray]] = {}
    refined_tiles: dict[int, Gaussians] = {}
    paired = total = 0
    for t in tiles:
        if not t.children:
            continue
        b = t.gaussians
        r = decode_tile(store, m, m.tile(t.id), m.sh_degree).with_sh_degree(b.sh_degree)
        refined_tiles[t.id] = r
        p = pair(b, r)
        ok = p >= 0
        paired += int(ok.sum())
        total += len(b)
        bi = p[ok]
        bb, rr = b.subset(bi), r.subset(np.flatnonzero(ok))
        f = features(bb, t, h[t.id])
        ob = np.clip(bb.opacities.astype(np.float64), 1e-6, CEIL)
        orf = np.clip(rr.opacities.astype(np.float64), 1e-6, CEIL)
        ls_b = np.sort(bb.log_scales.astype(np.float64), 1)
        ls_r = np.sort(rr.log_scales.astype(np.float64), 1)
        d = {"d_ls_mean": (rr.log_scales.astype(np.float64).mean(1) - bb.log_scales.astype(np.float64).mean(1)),
             "d_ls_min": ls_r[:, 0] - ls_b[:, 0], "d_ls_max": ls_r[:, 2] - ls_b[:, 2],
             "d_logit": np.log(orf / (1 - orf)) - np.log(ob / (1 - ob)), "d_opacity": orf - ob,
             "d_dc": (rr.sh_dc - bb.sh_dc).astype(np.float64),
             "d_luma": SH_C0 * (rr.sh_dc - bb.sh_dc).astype(np.float64) @ LUMA,
             "d_pos": np.linalg.norm(rr.positions - bb.positions, axis=1) / np.exp(bb.log_scales.mean(1))}
        for k, v in {**f, **d}.items():
            rows.setdefault(k, []).append(np.asarray(v))
    out = {k: np.concatenate(v) for k, v in rows.items()}
    out["paired_share"] = np.array(paired / max(total, 1))
    return out, tiles, refined_tiles


def refined_tree(name: str, cache_dir: str, refined_dir: str) -> tuple[list[lod.Tile], list[lod.Tile]]:
    """The default tree, and a copy with the merged tiles the refined encode's decoded ones."""
    from splatstream.io import read_gaussians
    from splatstream.scene_decode import decode_tile
    from splatstream.store import open_store, read_manifest

    tiles = rl.default_tree(read_gaussians(os.path.join(cache_dir, name, "full.ply")))
    store = open_store(os.path.join(refined_dir, name))
    m = read_manifest(store)
    assert [t.splats for t in m.tiles] == [len(t.gaussians) for t in tiles]
    refined = [dataclasses.replace(t, gaussians=decode_tile(store, m, m.tile(t.id), m.sh_degree).with_sh_degree(
        t.gaussians.sh_degree)) if t.children else t for t in tiles]
    return tiles, refined


def appearance_only(tiles: list[lod.Tile], refined: list[lod.Tile]) -> list[lod.Tile]:
    """The default tree with each PAIRED merged splat's log-scales, opacity and DC colour the refined ones (positions,
    rotations and the unpaired splats as built): how much of the gain is per-splat appearance, not the moves."""
    out = list(tiles)
    for t in tiles:
        if not t.children:
            continue
        b, r = t.gaussians, refined[t.id].gaussians
        p = pair(b, r)
        ok = np.flatnonzero(p >= 0)
        ls, op, dc = b.log_scales.copy(), b.opacity_logits.copy(), b.sh_dc.copy()
        ls[p[ok]], op[p[ok]], dc[p[ok]] = r.log_scales[ok], r.opacity_logits[ok], r.sh_dc[ok]
        out[t.id] = dataclasses.replace(t, gaussians=Gaussians(b.positions, b.rotations, ls, op, dc, b.sh_rest))
    return out


def fit_cells(scenes: dict[str, dict]) -> dict[int, np.ndarray]:
    """Per cell: the mean over training scenes (each with >= MIN_CELL splats there) of the scene's cell mean of
    (d_ls of the smallest, middle and largest axis, d_logit, d_dc x3)."""
    per: dict[int, list[np.ndarray]] = {}
    for d in scenes.values():
        cells = cell_of(d)
        mid = 3 * d["d_ls_mean"] - d["d_ls_min"] - d["d_ls_max"]  # the mean is order-free: the sorted sum
        vals = np.column_stack([d["d_ls_min"], mid, d["d_ls_max"], d["d_logit"], d["d_dc"]])
        for c in np.unique(cells):
            sel = cells == c
            if sel.sum() >= MIN_CELL:
                per.setdefault(int(c), []).append(vals[sel].mean(0))
    return {c: np.mean(v, 0) for c, v in per.items() if len(v) >= 2}


def apply_cells(tiles: list[lod.Tile], model: dict[int, np.ndarray], parts: tuple[str, ...] = ("scale", "opacity",
                                                                                              "colour")
                ) -> list[lod.Tile]:
    h = heights(tiles)
    out = list(tiles)
    for t in tiles:
        if not t.children:
            continue
        g = t.gaussians
        cells = cell_of(features(g, t, h[t.id]))
        corr = np.array([model.get(int(c), np.zeros(7)) for c in range(cells.max() + 1)])[cells]
        corr[:, 0:3] *= "scale" in parts
        corr[:, 3] *= "opacity" in parts
        corr[:, 4:7] *= "colour" in parts
        op = np.clip(g.opacities.astype(np.float64), 1e-6, CEIL)
        logit = np.log(op / (1 - op)) + corr[:, 3]
        ls = g.log_scales.astype(np.float64).copy()
        axes = np.argsort(ls, axis=1, kind="stable")  # smallest, middle, largest axis of each splat
        np.put_along_axis(ls, axes, np.take_along_axis(ls, axes, 1) + corr[:, 0:3], 1)
        ng = Gaussians(g.positions, g.rotations, ls.astype(np.float32),
                       logit.astype(np.float32), (g.sh_dc + corr[:, 4:7]).astype(np.float32), g.sh_rest)
        out[t.id] = dataclasses.replace(t, gaussians=ng)
    return out


def summarize(name: str, d: dict) -> list[dict]:
    lines = []
    for hgt in np.unique(d["height"]):
        for ceil in (0, 1):
            sel = (d["height"] == hgt) & (d["ceil"] == ceil)
            if sel.sum() < MIN_CELL:
                continue
            row = {"scene": name, "height": int(hgt), "ceil": ceil, "n": int(sel.sum()),
                   "size_med": float(np.median(d["size"][sel]))}
            for k in ("d_ls_mean", "d_ls_min", "d_ls_max", "d_logit", "d_opacity", "d_luma", "d_pos"):
                row[k] = float(np.mean(d[k][sel]))
                row[k + "_med"] = float(np.median(d[k][sel]))
            row["d_dc"] = [float(x) for x in d["d_dc"][sel].mean(0)]
            lines.append(row)
    return lines


def table(deltas: dict[str, dict]) -> str:
    """Markdown: per level from the leaves x ceiling, the mean over scenes of each scene's mean delta, the scenes
    agreeing in sign with it (of those with >= MIN_CELL splats there), and the across-scene spread (std)."""
    keys = ("d_ls_mean", "d_ls_min", "d_ls_max", "d_logit", "d_opacity", "d_luma", "d_pos")
    out = ["| level | ceiling | scenes | splats | size (log2 px) | " + " | ".join(keys) + " |",
           "|---|---|---|---|---|" + "---|" * len(keys)]
    for hgt in range(1, MAX_HEIGHT + 1):
        for ceil in (0, 1):
            per = {}
            n = 0
            for d in deltas.values():
                sel = (d["height"] == hgt) & (d["ceil"] == ceil)
                if sel.sum() >= MIN_CELL:
                    n += int(sel.sum())
                    for k in (*keys, "size"):
                        per.setdefault(k, []).append(float(np.mean(d[k][sel])))
            if not per:
                continue
            cells = []
            for k in keys:
                v = np.array(per[k])
                m = v.mean()
                cells.append(f"{m:+.3f} ({int((np.sign(v) == np.sign(m)).sum())}/{len(v)}, sd {v.std():.3f})")
            out.append(f"| {hgt} | {'yes' if ceil else 'no'} | {len(per['size'])} | {n:,} | "
                       f"{np.mean(per['size']):+.2f} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def replay(name: str, results: str, cache_dir: str, trees: dict[str, list[lod.Tile]]) -> list[dict]:
    from splatstream.io import read_gaussians

    res = json.load(open(os.path.join(results, f"{name}.json")))
    cams = [Camera.from_dict(c) for c in res["cameras"]]
    refs = plr.references(cache_dir, name, read_gaussians(os.path.join(cache_dir, name, "full.ply")), cams)
    lines = []
    for row in res["ours"]:
        ids_per_view = row["drawn_tile_ids_per_view"]
        drawn = [sum(len(trees["today"][i].gaussians) for i in ids) for ids in ids_per_view]
        assert drawn == row["splats_drawn_per_view"], (drawn, row["splats_drawn_per_view"])
        peer, who = best_peer(res, row["budget"])
        line = {"scene": name, "budget": row["budget"], "best_peer": peer, "best_peer_is": who,
                "streamed": row["psnr_mean"]}
        for label, tree in trees.items():
            imgs = [lvp.render_views(plr.cut_gaussians(tree, ids), [c])[0]
                    for ids, c in zip(ids_per_view, cams, strict=True)]
            line[label] = lvp.measure(imgs, refs)["psnr_mean"]
        print(f"{name:30s} {row['budget']:>7d} peer {peer:.2f} streamed {row['psnr_mean']:.2f} " +
              " ".join(f"{k} {line[k]:.2f} ({line[k] - peer:+.2f})" for k in trees), flush=True)
        lines.append(line)
    return lines


def summary(replay_path: str, appearance_path: str | None) -> str:
    """Markdown: each replayed point's dB against today, then per tree the counts (up, down by more than 0.1 dB,
    >= 1 dB over the best peer) and its median share of the refined gain."""
    def lines(path):
        return [r for r in map(json.loads, open(path)) if r.get("kind") == "replay"]

    rows = lines(replay_path)
    app = {(r["scene"], r["budget"]): r for r in (lines(appearance_path) if appearance_path else [])}
    out = ["| scene | budget | best peer | today | refined | systematic (LOSO) | scales only | opacity + colour only "
           "| refined appearance on built positions |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    seen: dict[str, int] = {}
    for r in rows:
        k = seen[r["scene"]] = seen.get(r["scene"], -1) + 1
        t, a = r["today"], app.get((r["scene"], r["budget"]))
        moved = f"{a['refined_appearance'] - t:+.2f}" if a else ""
        out.append(f"| {r['scene']} | {r['budget']:,} ({('2', '6', '25', '50')[k]} %) | {r['best_peer']:.2f} | "
                   f"{t:.2f} | {r['refined'] - t:+.2f} | {r['systematic'] - t:+.2f} | {r['sys_scale'] - t:+.2f} | "
                   f"{r['sys_opacity_colour'] - t:+.2f} | {moved} |")
    for v in ("refined", "systematic", "sys_scale", "sys_opacity_colour"):
        d = np.array([r[v] - r["today"] for r in rows])
        share = np.median([(r[v] - r["today"]) / (r["refined"] - r["today"]) for r in rows])
        out.append(f"{v}: {len(d)} points, median {np.median(d):+.2f} dB (min {d.min():+.2f}, max {d.max():+.2f}), "
                   f"up {int((d > 0).sum())}, down by > 0.1 dB {int((d < -0.1).sum())}, >= 1 dB over the best peer "
                   f"{sum(r[v] - r['best_peer'] >= 1 for r in rows)} (today "
                   f"{sum(r['today'] - r['best_peer'] >= 1 for r in rows)}); median share of the refined gain "
                   f"{share:+.1%}")
    if app:
        s = [(a["refined_appearance"] - a["today"]) / (a["refined"] - a["today"]) for a in app.values()]
        out.append(f"refined appearance on built positions: {len(s)} points, median share of the refined gain "
                   f"{np.median(s):.1%} ({min(s):.1%} to {max(s):.1%})")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=os.path.join(HERE, "results", "lod_vs_peers_farpx31_g15c16"))
    ap.add_argument("--cache-dir", default="/tmp/lvp50/cache")
    ap.add_argument("--refined", default="/tmp/refined")
    ap.add_argument("--work", default="/tmp/distill31", help="per-scene deltas cached here (deltas_SCENE.npz)")
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--replay", nargs="*", default=None, help="scenes to replay (default: none; bare: all)")
    ap.add_argument("--appearance-only", action="store_true",
                    help="replay today, refined and the refined appearance on the built positions/rotations only")
    ap.add_argument("--out", default=None, help="append JSON lines (deltas tables, replays) here")
    ap.add_argument("--summary", nargs="+", metavar="JSONL", default=None,
                    help="only print the table of a replay's --out (and an --appearance-only run's --out)")
    args = ap.parse_args()
    if args.summary:
        print(summary(args.summary[0], args.summary[1] if len(args.summary) > 1 else None))
        return 0
    os.makedirs(args.work, exist_ok=True)
    names = args.scenes or [n for n in lvp.SCENES if os.path.isdir(os.path.join(args.refined, n))]
    deltas: dict[str, dict] = {}
    for n in names:
        path = os.path.join(args.work, f"deltas_{n}.npz")
        if os.path.exists(path):
            deltas[n] = dict(np.load(path))
            continue
        d, _, _ = scene_deltas(n, args.cache_dir, args.refined)
        np.savez(path, **d)
        deltas[n] = d
        print(f"{n}: {len(d['d_logit'])} paired merged splats ({float(d['paired_share']):.1%})", flush=True)
        for row in summarize(n, d):
            print(json.dumps(row), flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    print(json.dumps({"kind": "deltas", **row}), file=f)
    print(table(deltas), flush=True)
    todo = names if args.replay == [] else (args.replay or [])
    for n in todo:
        model = fit_cells({k: v for k, v in deltas.items() if k != n})
        tiles, refined = refined_tree(n, args.cache_dir, args.refined)
        trees = {"today": tiles, "refined": refined, "systematic": apply_cells(tiles, model),
                 "sys_scale": apply_cells(tiles, model, ("scale",)),
                 "sys_opacity_colour": apply_cells(tiles, model, ("opacity", "colour"))}
        if args.appearance_only:
            trees = {"today": tiles, "refined": refined, "refined_appearance": appearance_only(tiles, refined)}
        for line in replay(n, args.results, args.cache_dir, trees):
            if args.out:
                with open(args.out, "a") as f:
                    print(json.dumps({"kind": "replay", **line}), file=f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
