"""Probe (issue 31, refine31 phase 1): whole merged levels refined by bench/device/refine_lod_levels.py, drawn from
cameras OUTSIDE its training band (elevations -20..70 deg, 0.6-1.6x the orbit distance): from below (-50 deg), the
top (85 deg), close (0.35x) and far (3x), 4 azimuths each (45 deg off the benchmark's), GL renderer at the
benchmark's 384 px, PSNR against the full-detail render from the same cameras. Only levels whose every merged tile
the phase-1 files refined (they keep the tiles the benchmark's cuts drew) are drawn.

    PYTHONPATH=. python bench/probe_lod_refine_offband.py statue-st-peter RUN1_OUT RUN2_OUT   # JSON lines
"""
from __future__ import annotations

import glob
import json
import math
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "device"))

import lod_vs_peers as lvp  # noqa: E402  (bench/ is not a package)
import refine_lod_levels as rl  # noqa: E402

from splatstream.camera import Camera  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def orbit_family(bench: Camera, elevation_deg: float, distance_scale: float, n: int = 4,
                 azimuth0_deg: float = 45.0) -> list[Camera]:
    """`n` cameras around the benchmark camera's target at that elevation about its up and that multiple of its
    distance."""
    centre = np.asarray(bench.target, float)
    offset = np.asarray(bench.eye, float) - centre
    up = np.asarray(bench.up, float)
    up /= np.linalg.norm(up)
    flat = offset - up * (offset @ up)
    a = flat / np.linalg.norm(flat)
    b = np.cross(up, a)
    dist = float(np.linalg.norm(offset)) * distance_scale
    el = math.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = math.radians(azimuth0_deg + 360.0 * i / n)
        d = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up
        eye = centre + dist * d
        cams.append(Camera(tuple(eye), tuple(centre), tuple(up), bench.fov_y_deg, bench.width, bench.height,
                           *lvp._near_far(eye, centre)))
    return cams


def main(name: str, run_dirs: list[str], cache_dir: str = "/tmp/lvp50/cache") -> None:
    res = json.load(open(os.path.join(HERE, "results", "lod_vs_peers_px28", f"{name}.json")))
    bench = [Camera.from_dict(c) for c in res["cameras"]]
    g = read_gaussians(os.path.join(cache_dir, name, "full.ply"))
    tiles = rl.default_tree(g)
    digest = rl.tree_digest(tiles)
    trees = {"today": tiles}
    for v in ("B", "C"):
        paths = sorted(p for d in run_dirs for p in glob.glob(os.path.join(d, f"refine_{v}_*.npz")))
        theirs, refined, _ = rl.read_refined(paths, name)
        rl.check_digest(digest, theirs)
        trees[v] = rl.replace_refined(tiles, refined)
    cuts = rl.level_cuts(tiles)
    whole = [d for d, (merged, _) in cuts.items() if all(trees["B"][i] is not tiles[i] for i in merged)]
    families = {"bench(25deg,1x)": bench, "below(-50deg,1x)": orbit_family(bench[0], -50, 1.0),
                "top(85deg,1x)": orbit_family(bench[0], 85, 1.0),
                "close(25deg,0.35x)": orbit_family(bench[0], 25, 0.35),
                "far(25deg,3x)": orbit_family(bench[0], 25, 3.0)}
    for family, cams in families.items():
        refs = lvp.render_views(g, cams)
        for d in whole:
            merged, fixed = cuts[d]
            ids = fixed + merged
            row = {"scene": name, "family": family, "level": d,
                   "splats": sum(len(tiles[i].gaussians) for i in ids)}
            for label, tree in trees.items():
                imgs = lvp.render_views(Gaussians.concatenate([tree[i].gaussians for i in ids]), cams)
                row[label] = round(lvp.measure(imgs, refs)["psnr_mean"], 2)
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
