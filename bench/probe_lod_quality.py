"""Probe: why is our LOD level worse than splat-transform's at the same splat count? (issue 31, "LOD at a budget")

For each scene of bench/peers_cache (full.ply, splat-transform's adaptive levels st-adaptive_N.ply, the cached
full-detail renders of bench/lod_vs_peers.py: the same 4 orbit views at 384 px, the same cameras), builds our
tree (`lod.build_tiles`, the encoder's defaults: 16,384-splat leaves, reduction 2) with each variant and draws
ONE WHOLE LEVEL (every tile of that level) of about 50 % and 25 % of the scene with the GL renderer, next to
splat-transform's level of the same count:

* `grid` / `cost`: the merge (`--lod-merge`), with the product's step 5 (format_spec/lod.md 6: opacity and base
  colour matched at the viewing blur `b = 0.3 p^2`, p a pixel where the tile's error spans
  lod.OPACITY_MATCH_SSE_PX);
* `@PX`: step 5 matched at PX px instead (`@1`: the rule before 2026-11-28; `@0`: no blur: mass-conserving
  opacity and mass-weighted colour of the originals, which is splat-transform's own rule up to its opacity cap of
  1 and its ellipsoid-area weights);

Also prints, per view, the screen-space error (px) at which the tiles of that level are seen from the orbit views
(projected error = error / pixel size at the tile's sphere distance), which is the scale the blur is about.
`--sizes 384 96`: the same views drawn at fewer pixels too (the same cameras, so the level is seen at a quarter of
the screen-space error: near the 1 px it is drawn at without a budget), against full detail at that size.

    PYTHONPATH=. python bench/probe_lod_quality.py --scenes statue-angel statue-massa \
        --variants grid@1 grid@2 grid@4 grid@0 cost@1 cost@4 --fractions 0.5 0.25 0.06 0.02 --sizes 384 96
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
from splatstream.gaussians import Gaussians  # noqa: E402


def level_sse(tiles: list[lod.Tile], level: int, cameras) -> list[float]:
    """Median over the level's tiles of error / pixel size at the tile's sphere distance, per camera (px)."""
    out = []
    for cam in cameras:
        eye = np.asarray(cam.eye, np.float64)
        px_per_unit = cam.height / (2.0 * math.tan(math.radians(cam.fov_y_deg) / 2.0))
        s = []
        for t in tiles:
            if t.level != level or not len(t.gaussians):
                continue
            d = max(float(np.linalg.norm(np.asarray(t.sphere_center) - eye)) - t.sphere_radius, 1e-6)
            s.append(t.geometric_error * px_per_unit / d)
        out.append(float(np.median(s)))
    return out


def build(g: Gaussians, variant: str) -> list[lod.Tile]:
    merge, _, px = variant.partition("@")
    blur = lod.viewing_blur
    if px:  # matched at PX pixels of screen-space error; 0: no blur at all
        lod.viewing_blur = (lambda e, p=float(px): lod.LOW_PASS_PX2 * (e / p) ** 2) if float(px) else (lambda e: 0.0)
    try:
        return lod.build_tiles(g, 16384, 2.0, merge=merge)
    finally:
        lod.viewing_blur = blur


def main() -> None:
    from splatstream.io import read_gaussians
    from splatstream.orientation import detect_up

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["statue-angel", "statue-massa"])
    ap.add_argument("--variants", nargs="+", default=["grid", "grid@0"])
    ap.add_argument("--fractions", nargs="+", type=float, default=[0.5, 0.25])
    ap.add_argument("--cache-dir", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "peers_cache"))
    ap.add_argument("--sizes", nargs="+", type=int, default=[384])
    ap.add_argument("--out", default=None, help="append one JSON line per result here")
    args = ap.parse_args()
    for name in args.scenes:
        sdir = os.path.join(args.cache_dir, name)
        g = read_gaussians(os.path.join(sdir, "full.ply"))
        n = len(g)
        up = detect_up(g).up
        views = {}
        for size in args.sizes:
            cams = lvp.view_cameras(g.positions, up, 4, size)
            ref_path = os.path.join(sdir, f"ref_{lvp.camera_key(cams)}.npy")
            views[size] = (cams, list(np.load(ref_path)) if os.path.exists(ref_path) else lvp.render_views(g, cams))
        for f in args.fractions:
            count = max(1, int(round(f * n)))
            path = os.path.join(sdir, f"st-adaptive_{count}.ply")
            if not os.path.exists(path):
                continue
            st = read_gaussians(path)
            for size, (cams, refs) in views.items():
                m = lvp.measure(lvp.render_views(st, cams), refs)
                print(f"{name} st-adaptive {count} at {size} px: {m['psnr_mean']:.2f} dB", flush=True)
                if args.out:
                    print(json.dumps({"scene": name, "variant": "st-adaptive", "fraction": f, "splats": count,
                                      "size": size, "psnr": m["psnr_mean"]}), file=open(args.out, "a"))
        for variant in args.variants:
            t0 = time.process_time()
            tiles = build(g, variant)
            secs = time.process_time() - t0
            levels: dict[int, int] = {}
            for t in tiles:
                levels[t.level] = levels.get(t.level, 0) + len(t.gaussians)
            for f in args.fractions:
                level = min(levels, key=lambda lv: abs(levels[lv] - f * n))
                s = Gaussians.concatenate([t.gaussians for t in tiles if t.level == level])
                for size, (cams, refs) in views.items():
                    m = lvp.measure(lvp.render_views(s, cams), refs)
                    sse = level_sse(tiles, level, cams)
                    print(f"{name} {variant} level {level} ({len(s)} splats, {f:.0%}) at {size} px: "
                          f"{m['psnr_mean']:.2f} dB; drawn at sse {', '.join(f'{x:.1f}' for x in sse)} px; "
                          f"build {secs:.1f} s CPU", flush=True)
                    if args.out:
                        print(json.dumps({"scene": name, "variant": variant, "fraction": f, "level": level,
                                          "splats": len(s), "size": size, "psnr": m["psnr_mean"], "sse_px": sse,
                                          "build_cpu_s": round(secs, 2)}), file=open(args.out, "a"))


if __name__ == "__main__":
    main()
