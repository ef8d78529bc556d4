"""Probe: opacity matched at two viewing blurs, interpolated per tile by the screen-space error it is drawn at
(issue 31, "LOD at a budget"; BENCHMARKS.md, "Two viewing scales").

Would a merged splat carrying its opacity (and colour) matched at two viewing blurs, interpolated by the renderer
per drawn tile, beat the single 2-px match (lod.OPACITY_MATCH_SSE_PX, format_spec/lod.md 6 step 5)? Before any
format change, this replays THE REAL STREAMING CUT: the tiles `splatstream view --headless --max-splats N
--no-prefetch` drew from each of the benchmark's 4 orbit views (`drawn_tile_ids_per_view` in a
bench/lod_vs_peers.py result JSON) are taken from trees built by `lod.build_tiles` (the encoder's defaults:
16,384-splat leaves, reduction 2; the same tile ids, checked by the drawn splat counts) with step 5 at several
blurs. The trees differ only in opacity and base colour (the grid's groups, moment matching and errors do not
depend on step 5; checked). Each drawn tile's sse in that view (lod.md 3, the client's formula) picks the blend:

    f = clamp(log(sse / LO) / log(HI / LO), 0, 1),  alpha = (1 - f) alpha_LO + f alpha_HI

(colour: `c2` keeps the 2-px colour, `cLO` / `cHI` one end's, `ci` blends the two ends' like the opacity).
Rendered with the GL renderer at 384 px (in-memory very-high encode, no quantisation of ours to speak of), PSNR
against the cached full-detail render, mean of the 4 views. `2` (the shipped rule, replayed) is the baseline; the
replay differs from the streamed frame only by the default preset's quantisation.

    PYTHONPATH=. python bench/probe_lod_twoscale.py --results bench/results/lod_vs_peers_viewscale \
        --scenes statue-angel statue-massa --variants 2 4 i1-4c2 i1-4ci --out /tmp/twoscale.jsonl
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import lod_vs_peers as lvp  # noqa: E402  (bench/ is not a package)

from splatstream import lod  # noqa: E402
from splatstream.camera import Camera  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402


def build_at(g: Gaussians, px: float, max_leaf: int = 16384, reduction: float = 2.0) -> list[lod.Tile]:
    """The encoder's default tree (or `max_leaf`, `reduction`) with step 5 matched at `px` px of sse."""
    blur = lod.viewing_blur
    lod.viewing_blur = lambda e, p=float(px): lod.LOW_PASS_PX2 * (e / p) ** 2
    try:
        return lod.build_tiles(g, max_leaf, reduction)
    finally:
        lod.viewing_blur = blur


def tile_sse(t: lod.Tile, cam: Camera) -> float:
    """lod.md 3: error * height / (2 distance tan(fov_y / 2)), distance to the bounding sphere (inf inside)."""
    d = float(np.linalg.norm(np.asarray(t.sphere_center, float) - np.asarray(cam.eye, float))) - t.sphere_radius
    if d <= 0:
        return math.inf
    return t.geometric_error * cam.height / (2.0 * d * math.tan(math.radians(cam.fov_y_deg) / 2.0))


def parse(variant: str) -> tuple[float, float, str]:
    """'2' -> (2, 2, '2'); 'i1-4c2' -> (1, 4, '2'); 'i1-4ci' -> (1, 4, 'i'); 'i1-4c1' -> colour at 1 px;
    't1-8' -> (1, 8, 't'): the far match modelled per tile (tile_model), nothing per splat."""
    if variant.startswith("t"):
        lo, hi = (float(x) for x in variant[1:].split("-"))
        return lo, hi, "t"
    if not variant.startswith("i"):
        return float(variant), float(variant), variant
    pair, _, colour = variant[1:].partition("c")
    lo, hi = (float(x) for x in pair.split("-"))
    return lo, hi, colour or "i"


def blend(trees: dict[float, list[lod.Tile]], ids: list[int], cam: Camera, variant: str) -> Gaussians:
    lo, hi, colour = parse(variant)
    parts = []
    for tid in ids:
        a, b = trees[lo][tid].gaussians, trees[hi][tid].gaussians
        if lo == hi or not trees[lo][tid].children:  # leaves are the originals in every tree
            parts.append(a)
            continue
        s = tile_sse(trees[lo][tid], cam)
        f = 1.0 if not math.isfinite(s) else min(max(math.log(s / lo) / math.log(hi / lo), 0.0), 1.0)
        alpha = (1 - f) * a.opacities.astype(np.float64) + f * b.opacities.astype(np.float64)
        alpha = np.clip(alpha, 1e-7, 1 - 1e-7)
        if colour == "t":  # the far end from the near one by two per-tile numbers (a manifest's worth of bytes)
            ratio, shift = tile_model(a, b)
            alpha = np.clip(a.opacities.astype(np.float64) * (1 + f * (ratio - 1)), 1e-7, 1 - 1e-7)
            dc = a.sh_dc + f * shift
        elif colour == "i":
            dc = (1 - f) * a.sh_dc + f * b.sh_dc
        else:
            dc = trees[float(colour)][tid].gaussians.sh_dc
        m = Gaussians(a.positions, a.rotations, a.log_scales, np.log(alpha / (1 - alpha)).astype(np.float32),
                      dc.astype(np.float32), a.sh_rest)
        parts.append(m)
    return Gaussians.concatenate(parts)


def tile_model(near: Gaussians, far: Gaussians) -> tuple[float, np.ndarray]:
    """A tile's far match from its near one without per-splat data: one opacity ratio (sum of the far opacities
    over the near ones) and one base-colour shift (the opacity-weighted mean of far - near)."""
    an, af = near.opacities.astype(np.float64), far.opacities.astype(np.float64)
    ratio = float(af.sum() / max(an.sum(), 1e-12))
    shift = ((far.sh_dc - near.sh_dc).astype(np.float64) * af[:, None]).sum(0) / max(af.sum(), 1e-12)
    return ratio, shift


def one_px(scenes: list[str], variants: list[str], reduction: float, out: str | None, at_px: float = 1.0) -> None:
    """tests/test_lod.py's 1-px check with the blend: each level of a tree of 2,000-splat leaves drawn (96x96,
    reference rasteriser) from where its largest error is `at_px` px, every tile blended by its own sse there."""
    from splatstream.ply import read_gaussians_ply
    from splatstream.render_ref import render_with_alpha

    fov, size = 50.0, 96
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
    from conftest import real_path  # where the tests find them: bundled, aliased, or in the shared data

    for name in scenes:
        g = read_gaussians_ply(real_path(name))
        pxs = sorted({p for v in variants for p in parse(v)[:2]}
                     | {float(parse(v)[2]) for v in variants if parse(v)[2] not in "it"})
        trees = {p: build_at(g, p, 2000, reduction) for p in pxs}
        tiles = trees[pxs[0]]
        root = tiles[0]
        direction = np.array([1.0, -1.0, 0.6]) / np.linalg.norm([1.0, -1.0, 0.6])
        for level in range(max(t.level for t in tiles)):
            ids = [t.id for t in tiles if t.level == level]
            error = max(tiles[i].geometric_error for i in ids)
            distance = error * size / (2 * math.tan(math.radians(fov) / 2) * at_px)
            eye = root.sphere_center + direction * distance
            cam = Camera(eye=tuple(float(v) for v in eye), target=tuple(float(v) for v in root.sphere_center),
                         up=(0.0, 0.0, 1.0), fov_y_deg=fov, width=size, height=size,
                         near=min(0.2, distance / 20), far=1e9)
            full, _ = render_with_alpha(g, cam, 0)
            sse = [tile_sse(tiles[i], cam) for i in ids]
            line = {"scene": name, "reduction": reduction, "at_px": at_px, "level": level,
                    "splats": sum(len(tiles[i].gaussians) for i in ids),
                    "sse_px": [round(min(sse), 2), round(float(np.median(sse)), 2), round(max(sse), 2)]}
            for v in variants:
                img, _ = render_with_alpha(blend(trees, ids, cam, v), cam, 0)
                mse = float(np.mean((np.clip(img, 0, 1) - np.clip(full, 0, 1)) ** 2))
                line[v] = round(99.0 if mse == 0 else 10 * math.log10(1 / mse), 2)
            print(json.dumps(line), flush=True)
            if out:
                with open(out, "a") as f:
                    print(json.dumps(line), file=f)


def plane_bytes(scenes: list[str], results: str, cache_dir: str, lo: float, hi: float, out: str | None) -> None:
    """What a second `color` plane (RGB + opacity matched at `hi` px, the default preset's texel format and steps)
    adds to each merged tile's base payload (its `color` matched at `lo` px; zstd, the default transport), over the
    whole tree and at convergence (the drawn tiles and their ancestors: what `--no-prefetch` downloads) at each
    budget of `results`."""
    import dataclasses
    import io

    from splatstream.encode.jobs import group_planes_of, splat_order
    from splatstream.encode.options import EncodeOptions
    from splatstream.encode.plan import plan_encode
    from splatstream.format.codec import encode_plane, plane_values
    from splatstream.format.container import write_payload
    from splatstream.format.planes import BASE_PLANES, chunks_for
    from splatstream.io import read_gaussians

    spec = next(p for p in BASE_PLANES if p.name == "color")
    far = dataclasses.replace(spec, name="color_far")
    for name in scenes:
        res = json.load(open(os.path.join(results, f"{name}.json")))
        g = read_gaussians(os.path.join(cache_dir, name, "full.ply"))
        tiles = build_at(g, lo)
        far_tiles = build_at(g, hi)
        ctx = plan_encode(g, EncodeOptions(), tiles=tiles).context
        extra = {}
        base = {}
        for t in tiles:
            order = splat_order(t.gaussians, ctx.chunk_order)
            chunks = chunks_for(len(t.gaussians))
            size = write_payload(group_planes_of(t.gaussians, order, "base", ctx), io.BytesIO(), chunks,
                                 ctx.zstd_level, ctx.transport).bytes
            base[t.id] = size
            if t.children:
                planes = group_planes_of(t.gaussians, order, "base", ctx)
                planes.append(encode_plane(plane_values(far_tiles[t.id].gaussians, spec), far, ctx.formats["color"],
                                           order, lazy=True, step=ctx.steps.get("color")))
                extra[t.id] = write_payload(planes, io.BytesIO(), chunks, ctx.zstd_level, ctx.transport).bytes - size
        parent = {c: t.id for t in tiles for c in t.children}
        tree_splats = sum(len(t.gaussians) for t in tiles)
        merged_splats = sum(len(t.gaussians) for t in tiles if t.children)
        line = {"scene": name, "lo_px": lo, "hi_px": hi, "tree_splats": tree_splats, "merged_splats": merged_splats,
                "scene_bytes_2px": res["ours_encode"].get("bytes_on_disk"), "base_bytes": sum(base.values()),
                "extra_bytes": sum(extra.values()),
                "extra_per_merged_splat": round(sum(extra.values()) / max(merged_splats, 1), 3),
                "extra_per_tree_splat": round(sum(extra.values()) / tree_splats, 3), "budgets": []}
        for row in res["ours"]:
            add = []
            for ids in row["drawn_tile_ids_per_view"]:
                fetched = set()
                for i in ids:
                    while i is not None and i not in fetched:
                        fetched.add(i)
                        i = parent.get(i)
                add.append(sum(extra.get(i, 0) for i in fetched))
            line["budgets"].append({"budget": row["budget"], "downloaded_2px": row["bytes_downloaded_mean"],
                                    "extra_mean": round(float(np.mean(add)))})
        print(json.dumps(line), flush=True)
        if out:
            with open(out, "a") as f:
                print(json.dumps(line), file=f)


def main() -> None:
    from splatstream.io import read_gaussians

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", help="a bench/lod_vs_peers.py result directory (SCENE.json)")
    ap.add_argument("--one-px", type=float, default=None, metavar="REDUCTION",
                    help="instead: tests/test_lod.py's 1-px check of --scenes (tests/data/real) at this reduction")
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--variants", nargs="+", default=["2", "4", "i1-4c2", "i1-4ci"])
    ap.add_argument("--cache-dir", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "peers_cache"))
    ap.add_argument("--out", default=None, help="append one JSON line per result here")
    ap.add_argument("--at-px", type=float, default=1.0, help="with --one-px: draw each level at this sse")
    ap.add_argument("--bytes", type=float, nargs=2, default=None, metavar=("LO_PX", "HI_PX"),
                    help="instead: the bytes a second colour plane matched at HI_PX adds to LO_PX's (needs --results)")
    args = ap.parse_args()
    if args.bytes:
        plane_bytes(args.scenes, args.results, args.cache_dir, *args.bytes, args.out)
        return
    if args.one_px:
        one_px(args.scenes, args.variants, args.one_px, args.out, args.at_px)
        return
    for name in args.scenes:
        res = json.load(open(os.path.join(args.results, f"{name}.json")))
        cams = [Camera.from_dict(c) for c in res["cameras"]]
        refs = list(np.load(os.path.join(args.cache_dir, name, f"ref_{lvp.camera_key(cams)}.npy")))
        g = read_gaussians(os.path.join(args.cache_dir, name, "full.ply"))
        pxs = sorted({p for v in args.variants for p in parse(v)[:2]}
                     | {float(parse(v)[2]) for v in args.variants if parse(v)[2] not in "it"})
        t0 = time.process_time()
        trees = {p: build_at(g, p) for p in pxs}
        secs = time.process_time() - t0
        first = trees[pxs[0]]
        for p in pxs[1:]:  # step 5 changes nothing else
            for a, b in zip(first, trees[p], strict=True):
                assert a.geometric_error == b.geometric_error and np.array_equal(a.gaussians.positions,
                                                                                  b.gaussians.positions)
        for row in res["ours"]:
            ids_per_view = row["drawn_tile_ids_per_view"]
            drawn = [sum(len(first[i].gaussians) for i in ids) for ids in ids_per_view]
            assert drawn == row["splats_drawn_per_view"], (drawn, row["splats_drawn_per_view"])
            sse = [sorted(tile_sse(first[i], c) for i in ids if first[i].children)
                   for ids, c in zip(ids_per_view, cams, strict=True)]
            med = [float(np.median(s)) if s else 0.0 for s in sse]
            for variant in args.variants:
                imgs = [lvp.render_views(blend(trees, ids, c, variant), [c])[0]
                        for ids, c in zip(ids_per_view, cams, strict=True)]
                m = lvp.measure(imgs, refs)
                print(f"{name} {row['budget']} {variant}: {m['psnr_mean']:.3f} dB (streamed 2 px "
                      f"{row['psnr_mean']:.3f}); merged tiles drawn at median sse "
                      f"{', '.join(f'{x:.1f}' for x in med)} px", flush=True)
                if args.out:
                    with open(args.out, "a") as f:
                        print(json.dumps({"scene": name, "budget": row["budget"], "variant": variant,
                                          "psnr": m["psnr_mean"], "ssim": m["ssim_mean"],
                                          "psnr_per_view": m["psnr_per_view"], "streamed_2px": row["psnr_mean"],
                                          "median_sse_px": med, "build_cpu_s": round(secs, 1)}), file=f)


if __name__ == "__main__":
    main()
