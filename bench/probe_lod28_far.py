#!/usr/bin/env python3
"""The whole frame a view WITHOUT a splat budget draws, before and after the 2 + 8 px viewing-scale rule (issue 31).

lod.OPACITY_MATCH_FAR_SSE_PX sets the scale at which the levels above the first merged one match opacity and base
colour (format_spec/lod.md 6, step 5); 2.0 is the old rule (2 px everywhere), 8.0 the 2 + 8 px rule. Two parts:

* `onem`: lod.md 3's measurement: make_scene 1M (seed 0; /work/shared/tools/make_scene.py), trees built in memory
  with lod.build_tiles (default: max_leaf_splats 65536 and reduction 4 as lod.md quotes, and the encoder's 16384 /
  2), the cut chosen by lod.md 3's traversal (refine while sse > threshold, 1 px) from 1.5, 3 and 6 root-sphere
  radii, drawn with our GL renderer (client_gl.offscreen.render_image, very-high) at 128x128 against the full
  scene from the same camera, once per rule.

      PYTHONPATH=. .venv/bin/python bench/probe_lod28_far.py onem --out /tmp/lod28/onem.json

* `scenes`: real scenes encoded twice (--before: the old rule, --after: 2 + 8 px; e.g. lod_vs_peers' scene
  directories of both rules), streamed as `splatstream view SCENE --headless --max-splats N --no-prefetch` with N
  ten times the scene's splats (no budget binds: the default --max-sse threshold decides the cut) from
  lod_vs_peers' orbit cameras moved back along their view ray by --factors, against the full-detail render from
  the same camera (GL, very-high). PSNR over the whole image and over the pixels either image covers (> 1/255).

      PYTHONPATH=. .venv/bin/python bench/probe_lod28_far.py scenes --scenes donut,guitar \\
          --before /tmp/lvp50/ours --after /tmp/st31/ours28 --cache-dir /tmp/lvp50/cache --out /tmp/lod28/far.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import lod_vs_peers as lvp  # noqa: E402

MAKE_SCENE = "/work/shared/tools/make_scene.py"


def psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    a, b = np.clip(img.astype(np.float64), 0, 1), np.clip(ref.astype(np.float64), 0, 1)
    d = (a - b) ** 2
    mse = float(d[mask].mean()) if mask is not None else float(d.mean())
    return 99.0 if mse == 0 else 10 * math.log10(1 / mse)


def covered(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return (img.max(-1) > 1 / 255) | (ref.max(-1) > 1 / 255)


# --- onem ------------------------------------------------------------------------------------------------------------

def threshold_cut(tiles, eye: np.ndarray, height: int, fov_y_deg: float, threshold: float) -> list[int]:
    """lod.md 3's traversal: from the root, refine while sse > threshold (eye inside the sphere: refine)."""
    k = height / (2 * math.tan(math.radians(fov_y_deg) / 2))
    out, stack = [], [0]
    while stack:
        t = tiles[stack.pop()]
        dist = float(np.linalg.norm(eye - t.sphere_center)) - t.sphere_radius
        sse = math.inf if dist <= 0 else t.geometric_error * k / dist
        if t.children and sse > threshold:
            stack.extend(t.children)
        else:
            out.append(t.id)
    return out


def run_onem(args) -> dict:
    from client_gl.offscreen import render_image
    from splatstream import lod
    from splatstream.camera import Camera
    from splatstream.gaussians import Gaussians
    from splatstream.io import read_gaussians
    from splatstream.orientation import detect_up

    path = os.path.join(args.workdir, "make_scene_1m_seed0.ply")
    if not os.path.exists(path):
        subprocess.run([sys.executable, MAKE_SCENE, "--splats", "1000000", "--seed", "0", "--out", path], check=True,
                       stdout=subprocess.DEVNULL)
    g = read_gaussians(path)
    up = np.asarray(detect_up(g).up, float)
    rows = []
    for leaf, reduction in args.shapes:
        for far_px in args.far_px:
            lod.OPACITY_MATCH_FAR_SSE_PX = far_px
            t0 = time.process_time()
            tiles = lod.build_tiles(g, leaf, reduction, merge="auto")
            cpu = time.process_time() - t0
            root = tiles[0]
            side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
            direction = side / np.linalg.norm(side) + 0.45 * up
            direction /= np.linalg.norm(direction)
            for radii in args.radii:
                eye = root.sphere_center + direction * radii * root.sphere_radius
                dist = radii * root.sphere_radius
                cam = Camera(tuple(map(float, eye)), tuple(map(float, root.sphere_center)), tuple(map(float, up)),
                             args.fov, args.size, args.size, 0.01 * dist, 100 * dist)
                cut = threshold_cut(tiles, eye, args.size, args.fov, args.threshold)
                coarse = Gaussians.concatenate([tiles[i].gaussians for i in cut])
                ref = np.asarray(render_image(g, cam), np.float32)
                img = np.asarray(render_image(coarse, cam), np.float32)
                m = covered(img, ref)
                shown = float((img.max(-1) > 1 / 255).sum()) / max(1, int((ref.max(-1) > 1 / 255).sum()))
                row = {"max_leaf_splats": leaf, "reduction": reduction, "far_px": far_px, "radii": radii,
                       "cut_tiles": len(cut), "cut_splats": len(coarse),
                       "levels": sorted({tiles[i].level for i in cut}),
                       "psnr": round(psnr(img, ref), 2), "psnr_covered": round(psnr(img, ref, m), 2),
                       "coverage": round(shown, 3),
                       "build_cpu_s": round(cpu, 1)}
                lvp.say(json.dumps(row))
                rows.append(row)
    lod.OPACITY_MATCH_FAR_SSE_PX = 2.0
    return {"part": "onem", "size": args.size, "fov_y_deg": args.fov, "threshold_px": args.threshold, "rows": rows}


# --- scenes ----------------------------------------------------------------------------------------------------------

def far_cameras(cameras, factor: float):
    from splatstream.camera import Camera

    out = []
    for c in cameras:
        eye = np.asarray(c.target) + factor * (np.asarray(c.eye) - np.asarray(c.target))
        eye_t = tuple(map(float, eye))
        out.append(Camera(eye_t, c.target, c.up, c.fov_y_deg, c.width, c.height, *lvp._near_far(eye_t, c.target)))
    return out


def run_scenes(args) -> dict:
    from splatstream.io import read_gaussians
    from splatstream.orientation import detect_up

    rows = []
    for name in args.scenes:
        full = os.path.join(args.cache_dir, name, "full.ply")
        g = read_gaussians(full)
        n = len(g)
        base = lvp.view_cameras(g.positions, detect_up(g).up, args.views, args.size)
        for factor in args.factors:
            cams = far_cameras(base, factor)
            ref_path = os.path.join(args.workdir, f"{name}_ref_{lvp.camera_key(cams)}.npy")
            if os.path.exists(ref_path):
                refs = list(np.load(ref_path))
            else:
                refs = lvp.render_views(g, cams)
                np.save(ref_path, np.stack(refs))
            row = {"scene": name, "splats": n, "factor": factor}
            for side, root in (("before", args.before), ("after", args.after)):
                with tempfile.TemporaryDirectory(dir=args.workdir) as wd:
                    views = lvp.our_views(os.path.join(root, name), 10 * n, cams, args.size, wd)
                ps = [psnr(v["image"], r) for v, r in zip(views, refs, strict=True)]
                pc = [psnr(v["image"], r, covered(v["image"], r)) for v, r in zip(views, refs, strict=True)]
                row[side] = {"psnr": round(lvp.mean_psnr(ps), 2), "psnr_views": [round(p, 2) for p in ps],
                             "psnr_covered": round(lvp.mean_psnr(pc), 2),
                             "drawn_splats": [v["drawn_splats"] for v in views],
                             "drawn_tiles": [v["drawn_tiles"] for v in views]}
            row["after_minus_before"] = round(row["after"]["psnr"] - row["before"]["psnr"], 2)
            row["after_minus_before_covered"] = round(row["after"]["psnr_covered"] - row["before"]["psnr_covered"], 2)
            lvp.say(json.dumps({k: v for k, v in row.items()}))
            rows.append(row)
    return {"part": "scenes", "size": args.size, "views": args.views, "max_splats": "10 x scene splats",
            "max_sse": "view default", "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("part", choices=["onem", "scenes"])
    ap.add_argument("--out", required=True)
    ap.add_argument("--workdir", default="/tmp/lod28")
    ap.add_argument("--size", type=int, default=None, help="pixels (onem 128, scenes 384)")
    ap.add_argument("--fov", type=float, default=50.0)
    ap.add_argument("--threshold", type=float, default=1.0)
    ap.add_argument("--radii", default="1.5,3,6")
    ap.add_argument("--shapes", default="65536/4,16384/2", help="max_leaf_splats/reduction,...")
    ap.add_argument("--far-px", default="2,8")
    ap.add_argument("--scenes", default="donut,guitar,biker,statue-st-peter,statue-angel-with-candlestick")
    ap.add_argument("--factors", default="1,2,4,8")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--before", default="/tmp/lvp50/ours")
    ap.add_argument("--after", default="/tmp/st31/ours28")
    ap.add_argument("--cache-dir", default="/tmp/lvp50/cache")
    args = ap.parse_args(argv)
    os.makedirs(args.workdir, exist_ok=True)
    args.radii = [float(x) for x in args.radii.split(",")]
    args.shapes = [(int(a), float(b)) for a, b in (s.split("/") for s in args.shapes.split(","))]
    args.far_px = [float(x) for x in args.far_px.split(",")]
    args.scenes = args.scenes.split(",")
    args.factors = [float(x) for x in args.factors.split(",")]
    if args.size is None:
        args.size = 128 if args.part == "onem" else 384
    result = run_onem(args) if args.part == "onem" else run_scenes(args)
    result["load_average"] = os.getloadavg()
    json.dump(result, open(args.out, "w"), indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
