"""Tile granularity against what a view costs to stream: bytes to converge, requests, time on a link.

For each leaf size (`encode --max-leaf-splats`), the scene is encoded once and the streaming client's own selection
(client_gl/stream/selection.py, no GPU needed) is asked what an overview and a close-up want at 1920x1080: the
payload bytes of the wanted cut with its bands plus the tiles shown on the way (every ancestor of a wanted tile
is fetched first: the root, then coarse levels, as the client draws them while refining), the number of requests,
and the time on a link of R Mbit/s with L ms latency and 6 requests in flight (bytes / rate + rounds of latency).

    python bench/bench_tile_size.py SCENE.ply --leaf-sizes 8192,16384,32768,65536 --json out.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from client_gl.stream.selection import SelectionOptions, select, view_numbers, wanted_bands  # noqa: E402
from splatstream.camera import Camera, standard_benchmark_view  # noqa: E402
from splatstream.encode import EncodeOptions, encode_gaussians  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def views(m, g) -> dict[str, Camera]:
    overview = standard_benchmark_view(g.positions)
    c = np.array(overview.target)
    eye = np.array(overview.eye)
    # close-up: a tenth of the way from the target toward the overview's eye, looking the same way
    close_eye = c + (eye - c) * 0.1
    close = Camera(tuple(close_eye), tuple(c), overview.up, overview.fov_y_deg, 1920, 1080, 0.001, 1e4)
    return {"overview": overview, "close-up": close}


def cost_of_view(m, cam: Camera, opts: SelectionOptions, link_mbps: float, latency_ms: float,
                 in_flight: int = 6) -> dict:
    a = m.arrays
    view = view_numbers(a, cam, opts)
    cost = np.array([t.chunks for t in m.tiles], np.float64)
    root = m.index_of[m.root]
    sel = select(a, view, cost, root, opts, reduction=m.lod.reduction)
    bands = wanted_bands(a, view, sel.cut, opts, m.sh_degree)
    tiles = set()
    for i in sel.cut:  # the cut and every ancestor (drawn while refining)
        k = i
        while k >= 0 and k not in tiles:
            tiles.add(k)
            k = int(a.parent[k])
    files: dict[str, int] = {}
    for i in tiles:
        t = m.tiles[i]
        files[t.groups["base"].file] = t.groups["base"].bytes
        for b in range(1, bands.get(i, 0) + 1):
            g = t.groups.get(f"sh{b}") or t.groups.get("sh1")
            files[g.file] = g.bytes
    if m.sh_codebook is not None:
        for b in range(1, max(bands.values(), default=0) + 1):
            p = m.sh_codebook.groups[f"sh{b}"]
            files[p.file] = p.bytes
    total = sum(files.values()) + m.bytes_on_disk - m.payload_bytes()  # + the manifest
    requests = len(files) + 1
    seconds = total * 8 / (link_mbps * 1e6) + math.ceil(requests / in_flight) * latency_ms / 1e3
    return {"bytes": int(total), "requests": requests, "tiles": len(tiles), "cut": len(sel.cut),
            "splats": int(sel.splats), "link_seconds": round(seconds, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--leaf-sizes", default="8192,16384,32768,65536")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--up", default="0,0,1", help="make_scene scenes are z-up")
    ap.add_argument("--link", default="20,40", help="Mbit/s,latency ms")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--workdir")
    args = ap.parse_args()
    mbps, lat = (float(v) for v in args.link.split(","))
    up = tuple(float(v) for v in args.up.split(","))
    results = []
    with tempfile.TemporaryDirectory(dir=args.workdir) as tmp:
        for leaf in [int(v) for v in args.leaf_sizes.split(",")]:
            g = read_gaussians(args.scene)
            t0 = time.perf_counter()
            m = encode_gaussians(g, os.path.join(tmp, f"s{leaf}"),
                                 EncodeOptions(preset=args.preset, max_leaf_splats=leaf, up=up))
            enc = time.perf_counter() - t0
            row = {"max_leaf_splats": leaf, "tiles": len(m.tiles), "levels": m.levels, "encode_s": round(enc, 1),
                   "bytes_on_disk": m.bytes_on_disk, "manifest_bytes": m.bytes_on_disk - m.payload_bytes()}
            for name, cam in views(m, g).items():
                row[name] = cost_of_view(m, cam, SelectionOptions(), mbps, lat)
            print(json.dumps(row), flush=True)
            results.append(row)
            del g
    out = {"scene": args.scene, "preset": args.preset, "link_mbps": mbps, "latency_ms": lat, "results": results}
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
