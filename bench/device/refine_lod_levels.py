#!/usr/bin/env python3
"""Probe (issue 31, phase 1): refine the merged splats of each LOD level against renders of the full-detail scene.

The Hierarchical-3DGS idea with the originals as ground truth (no training images): for each scene, our default tree
is built in memory exactly as `splatstream encode` builds it (lod.build_tiles with the encoder's defaults: 16,384-splat
leaves, reduction 2, merge `auto`, the scene read as `splatstream convert` writes it for bench/lod_vs_peers.py);
the full-detail scene is rendered with gsplat from training cameras that are not the benchmark's 4 orbit views
(`training_cameras`: a jittered Fibonacci band of directions around the orbit centre, distances 0.6-1.6x the orbit
distance, the benchmark's fov); then each merged level d (the tiles at depth d that have children) is optimised
ALONE, drawn as its whole cut (every tile at depth d plus the leaves shallower than d; the leaves' originals fixed):

    A: opacity logits and SH0 (DC) colour;  B: A + log-scales;  C: B + positions and rotations

with Adam on the MSE of the clamped images (PSNR is the measure). Writes, per variant, the refined values as float16
DELTAS from the unrefined tree (per tile id, the shapes `Gaussians` uses) with the tree's digest, so that
bench/probe_lod_refine.py replays the real streaming cut with them (GL renderer, the benchmark's views).

Our renderer's conventions, matched in gsplat: the 0.3 px^2 low-pass (gsplat eps2d=0.3), the 0.99 opacity clamp
(gsplat clamps alpha at 0.999: the opacities are clamped to 0.99 before, the same within o (1 - exp(power)) for
o > 0.99), the 1/255 alpha cut (gsplat's), colour max(SH(dir) + 0.5, 0) with SH_C0 (gsplat's with sh_degree), black
background, pinhole K with the principal point at the image centre and pixel centres at +0.5 (camera.md), the
OpenCV world-to-camera matrix (Camera.world_to_camera_cv), splats with depth <= near culled (the view rule's near).
`--device cpu` uses `dense_render`, a small dense torch rasteriser of the same conventions (tests it against
splatstream.render_ref) for tiny checks here.

    python3 bench/device/refine_lod_levels.py --inputs .refine_in --out $OUT --variants A B C --budget-s 420
    python bench/device/refine_lod_levels.py --inputs /work/shared/data/real --scenes statue-massa --device cpu \
        --max-splats 3000 --size 48 --cameras 16 --iters 30 --out /tmp/refine_cpu
"""
from __future__ import annotations

import argparse
import hashlib
import io
import json
import math
import os
import sys
import tempfile
import time
import zipfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = os.path.dirname(HERE)
sys.path.insert(0, BENCH)

import lod_vs_peers as lvp  # noqa: E402  (bench/ is not a package)

from refine_gpu.levels import (  # noqa: E402  (the product's renderer and settings, phase 2)
    LR,
    OPACITY_MAX,
    Renderer,
    camera_tensors,
    dense_render,
    eval_sh_torch,
    fit_fields,
    gsplat_torch_rasterization,
    mean_mse,
    to_params,
)
from splatstream import lod, lod_refine  # noqa: E402
from splatstream.camera import Camera  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402
from splatstream.lod_refine import psnr_of  # noqa: E402

__all__ = ["LR", "OPACITY_MAX", "Renderer", "camera_tensors", "dense_render", "eval_sh_torch",
           "gsplat_torch_rasterization", "psnr_of", "to_params"]  # re-exported: the replay and tests use them here

# The encoder's defaults for a scene encoded in memory (EncodeOptions: max_leaf_splats, reduction,
# resolved_lod_merge(in_memory=True)); tests/test_bench_probe_lod_refine.py checks they still are. Not imported here:
# splatstream.encode imports zstandard, which the GPU machine's image lacks.
MAX_LEAF_SPLATS = 16384
REDUCTION = 2.0
LOD_MERGE = "auto"

VARIANTS = {"A": ("opacity_logits", "sh_dc"),
            "B": ("opacity_logits", "sh_dc", "log_scales"),
            "C": ("opacity_logits", "sh_dc", "log_scales", "positions", "rotations")}
FIELDS = ("opacity_logits", "sh_dc", "log_scales", "positions", "rotations")
PART_BYTES = 15 * 2**20  # files back from the device: at most 16 MiB each


def say(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --- scenes and trees (numpy only) -----------------------------------------------------------------------------

def load_scene(data_dir: str, name: str) -> Gaussians:
    """The scene as bench/lod_vs_peers.py reads it: `splatstream convert SRC full.ply`, then read_gaussians."""
    from splatstream.io import read_gaussians, write_gaussians

    g = read_gaussians(os.path.join(data_dir, lvp.SCENES[name].source))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "full.ply")
        write_gaussians(g, path)
        return read_gaussians(path)


def default_tree(g: Gaussians, max_leaf: int = MAX_LEAF_SPLATS) -> list[lod.Tile]:
    return lod.build_tiles(g, max_leaf, REDUCTION, merge=LOD_MERGE)


def tree_digest(tiles: list[lod.Tile], max_leaf: int = MAX_LEAF_SPLATS, max_splats: int | None = None) -> dict:
    """What must match between the device's tree and the replay's: the shape and every tile's splat count
    (`positions_sha` too when the arithmetic is bit-identical; a mismatch there alone is only reported)."""
    counts = [len(t.gaussians) for t in tiles]
    shape = json.dumps([[t.level, list(t.children), c] for t, c in zip(tiles, counts, strict=True)]).encode()
    pos = hashlib.sha256()
    for t in tiles:
        pos.update(np.ascontiguousarray(t.gaussians.positions, np.float32).tobytes())
    return {"max_leaf": max_leaf, "max_splats": max_splats, "tiles": len(tiles), "splats": counts,
            "shape_sha": hashlib.sha256(shape).hexdigest()[:16], "positions_sha": pos.hexdigest()[:16]}


def check_digest(ours: dict, theirs: dict) -> None:
    if ours["tiles"] != theirs["tiles"] or ours["splats"] != theirs["splats"] or ours["shape_sha"] != theirs[
            "shape_sha"]:
        raise SystemExit(f"tree digest mismatch: {ours['tiles']} tiles here, {theirs['tiles']} in the refined file "
                         f"(shape {ours['shape_sha']} / {theirs['shape_sha']})")
    if ours["positions_sha"] != theirs["positions_sha"]:
        print("note: same tree shape, merged positions not bit-identical (deltas still apply)", file=sys.stderr)


def level_cuts(tiles: list[lod.Tile]) -> dict[int, tuple[list[int], list[int]]]:
    """Per merged level d: (the tiles at depth d with children: trained; the leaves at depth <= d: fixed): the
    product's rule (splatstream.lod_refine.level_cuts), as this probe's dict."""
    return {c.level: (list(c.merged), list(c.fixed)) for c in lod_refine.level_cuts(tiles)}


def training_cameras(positions: np.ndarray, up, n: int, size: int, seed: int = 0) -> list[Camera]:
    """The product's camera rule (splatstream.lod_refine.refine_cameras; moved there from here, the same cameras):
    `n` jittered cameras around the benchmark's orbit centre, none one of its 4 orbit views."""
    return lod_refine.refine_cameras(positions, up, n, size, seed)


def replace_refined(tiles: list[lod.Tile], refined: dict[int, dict[str, np.ndarray]]) -> list[lod.Tile]:
    """A copy of `tiles` with each refined tile's splats carrying its deltas (float16 in the files) added."""
    import dataclasses

    out = list(tiles)
    for tid, deltas in refined.items():
        g = tiles[tid].gaussians
        vals = {f: getattr(g, f) for f in FIELDS}
        for f, dv in deltas.items():
            vals[f] = (vals[f].astype(np.float32) + dv.astype(np.float32)).astype(np.float32)
        q = vals["rotations"]
        vals["rotations"] = (q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        out[tid] = dataclasses.replace(tiles[tid], gaussians=Gaussians(vals["positions"], vals["rotations"],
                                                                       vals["log_scales"], vals["opacity_logits"],
                                                                       vals["sh_dc"], g.sh_rest))
    return out


def pack_scene(scene: str, digest: dict, refined: dict[int, dict[str, np.ndarray]], info: dict) -> dict[str, bytes]:
    """npz members (name -> .npy bytes) of one scene and variant: tile ids, offsets, float16 deltas per field."""
    ids = sorted(refined)
    members = {"tile_ids": np.asarray(ids, np.int32),
               "offsets": np.cumsum([0] + [len(next(iter(refined[i].values()))) for i in ids]).astype(np.int64),
               "digest": np.frombuffer(json.dumps(digest).encode(), np.uint8),
               "info": np.frombuffer(json.dumps(info).encode(), np.uint8)}
    fields = sorted({f for i in ids for f in refined[i]})
    for f in fields:
        members["d_" + f] = np.concatenate([refined[i][f] for i in ids]).astype(np.float16)
    out = {}
    for k, v in members.items():
        b = io.BytesIO()
        np.save(b, v)
        out[f"{scene}/{k}.npy"] = b.getvalue()
    return out


def write_parts(out_dir: str, variant: str, scenes: dict[str, dict[str, bytes]]) -> list[str]:
    """refine_<variant>_<k>.npz files (zip-deflated .npy members), each under PART_BYTES of members."""
    paths, part, size = [], {}, 0

    def flush():
        if not part:
            return
        path = os.path.join(out_dir, f"refine_{variant}_{len(paths)}.npz")
        with zipfile.ZipFile(path + ".part", "w", zipfile.ZIP_DEFLATED, compresslevel=6) as z:
            for k, v in part.items():
                z.writestr(k, v)
        os.replace(path + ".part", path)
        paths.append(path)

    for members in scenes.values():
        n = sum(len(v) for v in members.values())
        if part and size + n > PART_BYTES * 1.15:  # deflate takes ~15 % off float16 deltas
            flush()
            part, size = {}, 0
        part.update(members)
        size += n
    flush()
    return paths


def read_refined(paths: list[str], scene: str) -> tuple[dict, dict[int, dict[str, np.ndarray]], dict]:
    """(digest, {tile id: {field: float16 deltas}}, info) of `scene` from refine_<variant>_<k>.npz files."""
    for p in paths:
        with np.load(p) as z:
            if f"{scene}/tile_ids" not in z.files:
                continue
            ids = z[f"{scene}/tile_ids"]
            off = z[f"{scene}/offsets"]
            fields = [k.split("/d_", 1)[1] for k in z.files if k.startswith(f"{scene}/d_")]
            arrays = {f: z[f"{scene}/d_{f}"] for f in fields}
            refined = {int(t): {f: arrays[f][off[k]:off[k + 1]] for f in fields} for k, t in enumerate(ids)}
            digest = json.loads(z[f"{scene}/digest"].tobytes())
            info = json.loads(z[f"{scene}/info"].tobytes())
            return digest, refined, info
    raise KeyError(scene)


def drawn_tiles(results_dir: str | None, scene: str) -> set[int] | None:
    """Every tile id drawn at any budget from any view of a lod_vs_peers result (None: no result, keep all)."""
    path = results_dir and os.path.join(results_dir, f"{scene}.json")
    if not path or not os.path.exists(path):
        return None
    res = json.load(open(path))
    return {i for row in res["ours"] for ids in row["drawn_tile_ids_per_view"] for i in ids}


# --- torch: rendering (moved to the product: refine_gpu/levels.py) -------------------------------------------------

# --- torch: one scene -------------------------------------------------------------------------------------------



def refine_scene(name: str, g: Gaussians, tiles: list[lod.Tile], args, torch, budget_s: float) -> dict:
    """Per variant: ({tile id: {field: delta}}, per-level report). `budget_s` for the optimisation (GT excluded)."""
    from splatstream.orientation import detect_up

    dev = args.device
    up = detect_up(g).up
    cams = training_cameras(g.positions, up, args.cameras, args.size, seed=args.seed)
    bench = lvp.view_cameras(g.positions, up, 4, args.size)
    dist = math.dist(bench[0].eye, bench[0].target)
    render = Renderer(torch, dev, g.sh_degree)
    full = to_params(torch, g, dev)
    t0 = time.perf_counter()
    with torch.no_grad():
        gt = torch.cat([render(full, cams[i:i + args.batch]) for i in range(0, len(cams), args.batch)]).clamp(0, 1)
        gt_bench = render(full, bench).clamp(0, 1)
    if dev != "cpu":
        torch.cuda.synchronize()
    gt_s = time.perf_counter() - t0
    del full
    cuts = level_cuts(tiles)
    keep = drawn_tiles(args.drawn, name)
    report = {"scene": name, "splats": len(g), "sh_degree": g.sh_degree, "cameras": len(cams), "size": args.size,
              "gt_s": round(gt_s, 2), "levels": {}}
    results = {v: {} for v in args.variants}
    evals = cams[:args.eval_cameras]  # the training PSNR reported (and the keep rule): a fixed subset, for time
    levels = sum(1 for merged, _ in cuts.values() if keep is None or keep.intersection(merged))
    slot = budget_s / max(1, levels * len(args.variants))

    def mse_over(p, which: list[Camera], target) -> float:
        return mean_mse(torch, render, p, which, target, args.batch)

    for d, (merged_ids, fixed_ids) in cuts.items():
        if keep is not None and not keep.intersection(merged_ids):
            continue  # a level no budget's cut draws (the coarsest ones, under 1 % of the splats): not refined
        merged = Gaussians.concatenate([tiles[i].gaussians for i in merged_ids])
        fixed = Gaussians.concatenate([tiles[i].gaussians for i in fixed_ids]) if fixed_ids else None
        pm = to_params(torch, merged, dev)
        pf = to_params(torch, fixed, dev) if fixed is not None else None

        def cut(p, pf=pf):
            return p if pf is None else {k: torch.cat([pf[k], p[k]]) for k in p}

        before = mse_over(cut(pm), evals, gt[:len(evals)])
        before_bench = mse_over(cut(pm), bench, gt_bench)
        lv = {"merged_tiles": len(merged_ids), "merged_splats": len(merged), "fixed_splats": len(fixed or []),
              "train_psnr_before": round(psnr_of(before), 3), "bench_psnr_before": round(psnr_of(before_bench), 3)}
        for v in args.variants:
            t1 = time.perf_counter()
            trained = VARIANTS[v]
            p, it = fit_fields(torch, render, cut, pm, trained, cams, gt, dist, iterations=args.iters,
                               batch=args.batch, seed=args.seed + d, seconds=slot, min_iterations=args.min_iters)
            after = mse_over(cut(p), evals, gt[:len(evals)])
            after_bench = mse_over(cut(p), bench, gt_bench)
            lv[v] = {"iters": it, "seconds": round(time.perf_counter() - t1, 2),
                     "train_psnr_after": round(psnr_of(after), 3), "bench_psnr_after": round(psnr_of(after_bench), 3)}
            say(f"{name} level {d} ({len(merged):,} merged + {len(fixed or []):,} fixed) {v}: train "
                f"{psnr_of(before):.2f} -> {psnr_of(after):.2f} dB, bench views {psnr_of(before_bench):.2f} -> "
                f"{psnr_of(after_bench):.2f} dB, {it} it, {lv[v]['seconds']:.1f} s")
            if after >= before:  # worse on its own training views: keep the unrefined level
                lv[v]["kept"] = False
                continue
            lv[v]["kept"] = True
            off = 0
            for tid in merged_ids:
                n = len(tiles[tid].gaussians)
                if keep is None or tid in keep:
                    results[v][tid] = {k: (p[k][off:off + n] - pm[k][off:off + n]).cpu().numpy()
                                       for k in trained}
                off += n
        report["levels"][d] = lv
    return {"results": results, "report": report}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", required=True, help="a folder laid out as the shared data/real (the scene sources)")
    ap.add_argument("--scenes", nargs="+", default=None, help="default: every lod_vs_peers scene found in --inputs")
    ap.add_argument("--out", required=True)
    ap.add_argument("--variants", nargs="+", default=["A", "B", "C"], choices=sorted(VARIANTS))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--cameras", type=int, default=96)
    ap.add_argument("--size", type=int, default=384,
                    help="training views' size (the benchmark's: at 40 px, positions and rotations overfit its pixels)")
    ap.add_argument("--batch", type=int, default=8, help="views per step")
    ap.add_argument("--eval-cameras", type=int, default=32, help="training views the before/after PSNR is over")
    ap.add_argument("--iters", type=int, default=300, help="at most, per level and variant")
    ap.add_argument("--min-iters", type=int, default=30)
    ap.add_argument("--budget-s", type=float, default=420.0, help="wall clock for everything")
    ap.add_argument("--drawn", default=None, help="lod_vs_peers result dir: keep only the tiles its cuts drew")
    ap.add_argument("--max-splats", type=int, default=None, help="CPU tests: only the first N splats of a scene")
    ap.add_argument("--max-leaf", type=int, default=MAX_LEAF_SPLATS, help="CPU tests: smaller leaves")
    ap.add_argument("--workers", type=int, default=None, help="tree-building processes")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    start = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    names = args.scenes or [n for n, s in lvp.SCENES.items() if os.path.exists(os.path.join(args.inputs, s.source))]
    say(f"scenes: {' '.join(names)}")

    # the trees on the CPUs (a process per scene, the largest first) while the GPU renders and refines
    from concurrent.futures import ProcessPoolExecutor
    pool = ProcessPoolExecutor(max_workers=args.workers or min(len(names), os.cpu_count() or 1))
    futures = {n: pool.submit(_scene_and_tree, args.inputs, n, args.max_splats, args.max_leaf) for n in names}

    import torch
    if args.device != "cpu":
        from gsplat.cuda._backend import _C  # JIT-compiles gsplat's CUDA once, ~1 min, while the pool builds the trees
        if _C is None:  # no CUDA toolkit found: gsplat leaves it None, and every render would fail
            pool.shutdown(cancel_futures=True)
            raise SystemExit("gsplat's CUDA extension is not built (nvcc / CUDA_HOME not found)")
    say(f"torch {torch.__version__} on {args.device}, ready after {time.perf_counter() - start:.1f} s")
    packed = {v: {} for v in args.variants}
    reports = []
    for k, n in enumerate(names):
        try:
            g, tiles, digest, build_s = futures[n].result()
        except Exception as e:  # one unreadable scene does not cost the others' device time
            say(f"{n}: FAILED to load or build: {e!r}")
            continue
        left = args.budget_s - (time.perf_counter() - start) - 15.0  # writing the files
        share = max(5.0, left / (len(names) - k) * 0.85)  # the GT renders and the evaluation come out of the rest
        say(f"{n}: {len(g):,} splats, {digest['tiles']} tiles (built in {build_s:.1f} s), budget {share:.0f} s")
        try:
            r = refine_scene(n, g, tiles, args, torch, share)
        except Exception as e:
            say(f"{n}: FAILED to refine: {e!r}")
            if args.device != "cpu":
                torch.cuda.empty_cache()
            continue
        r["report"].update(digest={k2: digest[k2] for k2 in ("tiles", "shape_sha", "positions_sha")},
                           build_s=round(build_s, 1))
        reports.append(r["report"])
        for v in args.variants:
            packed[v][n] = pack_scene(n, digest, r["results"][v], {"variant": v, "fields": VARIANTS[v],
                                                                    "levels": r["report"]["levels"]})
        with open(os.path.join(args.out, "refine_report.json"), "w") as f:
            json.dump({"args": vars(args), "scenes": reports}, f, indent=1)
    pool.shutdown()
    sizes = {}
    for v in args.variants:
        for p in write_parts(args.out, v, packed[v]):
            sizes[os.path.basename(p)] = os.path.getsize(p)
    say("files: " + ", ".join(f"{k} {s / 2**20:.1f} MiB" for k, s in sizes.items())
        + f"; total {sum(sizes.values()) / 2**20:.1f} MiB; {time.perf_counter() - start:.0f} s")
    print_summary(reports, args.variants)
    return 0


def print_summary(reports: list[dict], variants: list[str]) -> None:
    print("scene level merged | train PSNR before -> " + " ".join(variants) + " | bench-view PSNR before -> "
          + " ".join(variants) + " | s")
    for r in reports:
        for d, lv in r["levels"].items():
            tr = " ".join(f"{lv[v]['train_psnr_after']:.2f}" for v in variants if v in lv)
            bv = " ".join(f"{lv[v]['bench_psnr_after']:.2f}" for v in variants if v in lv)
            secs = sum(lv[v]["seconds"] for v in variants if v in lv)
            print(f"{r['scene']} {d} {lv['merged_splats']} | {lv['train_psnr_before']:.2f} -> {tr} | "
                  f"{lv['bench_psnr_before']:.2f} -> {bv} | {secs:.1f}")


def _scene_and_tree(data_dir: str, name: str, max_splats: int | None, max_leaf: int):
    t = time.perf_counter()
    g = load_scene(data_dir, name)
    if max_splats:
        g = g.subset(np.arange(min(max_splats, len(g))))
    tiles = default_tree(g, max_leaf)
    return g, tiles, tree_digest(tiles, max_leaf, max_splats), time.perf_counter() - t


if __name__ == "__main__":
    sys.exit(main())
