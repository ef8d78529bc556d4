"""Each merged level of a few encodes of one scene drawn as its whole cut (its merged tiles and the shallower leaves,
as a client draws the tree cut there) against the full detail, from the benchmark's 4 views and from the same views
moved back 4x and 16x (where only coarse levels are drawn): the levels above the partitions of a refined
partitioned encode judged on their own (BENCHMARKS.md, "Refining the merged levels by partitions"; issue 31, branch
partrefine31). Prints one JSON line per (encode, level): the mean PSNR per distance.

    PYTHONPATH=. python bench/partrefine31_levels.py FULL.ply LOD_VS_PEERS.json LEVELS NAME=SCENE_DIR ...

LEVELS: the merged levels to judge, e.g. 0,1,2. The renders are refine_cpu.raster's (render_ref's picture, compiled),
384 px, clamped to [0, 1].
"""
import json
import sys

import numpy as np

from refine_cpu import raster
from splatstream.camera import Camera
from splatstream.gaussians import covariances
from splatstream.io import read_gaussians
from splatstream.metrics import psnr
from splatstream.scene_decode import decode_scene
from splatstream.store import open_store, read_manifest

BACK = (1.0, 4.0, 16.0)


def views(path: str) -> dict[float, list[Camera]]:
    cams = json.load(open(path))["cameras"]
    out = {}
    for k in BACK:
        out[k] = []
        for c in cams:
            eye, target = np.array(c["eye"]), np.array(c["target"])
            eye = target + k * (eye - target)
            out[k].append(Camera(tuple(eye), tuple(c["target"]), tuple(c["up"]), c["fov_y_deg"], c["width"],
                                 c["height"], c["near"], c["far"] * k))
    return out


def main() -> None:
    full_path, json_path, levels = sys.argv[1:4]
    encodes = dict(a.split("=", 1) for a in sys.argv[4:])
    full = read_gaussians(full_path)
    cams = views(json_path)
    cov = covariances(full)
    ref = {k: [np.clip(raster.render(full, c, None, cov), 0, 1) for c in cs] for k, cs in cams.items()}
    for name, path in encodes.items():
        m = read_manifest(open_store(path))
        for level in (int(x) for x in levels.split(",")):
            ids = [t.id for t in m.tiles if (t.level == level and t.children) or (t.level <= level and not t.children)]
            g = decode_scene(path, tiles=ids, manifest=m)
            row = {"encode": name, "level": level, "splats": len(g)}
            for k, cs in cams.items():
                row[f"psnr_{k:g}x"] = round(float(np.mean([psnr(np.clip(raster.render(g, c), 0, 1), r)
                                                           for c, r in zip(cs, ref[k], strict=True)])), 3)
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
