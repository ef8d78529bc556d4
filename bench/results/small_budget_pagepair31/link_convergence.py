#!/usr/bin/env python3
"""Time to convergence over the reference access link (20 Mbit/s, 40 ms a request: server/throttle.py's Link), the
paged scenes at 2 and 25 %, the lod_vs_peers cameras, --no-prefetch, no disk cache: what the wait behind pages on
their way costs in latency (issue 31, pages landing a frame apart). One JSON line a view and run on stdout.

    PYTHONPATH=TREE python bench/results/small_budget_pagepair31/link_convergence.py SERVE_ROOT SCENE \
        LOD_VS_PEERS.json 0.02,0.25 RUNS >> SCENE_SIDE.jsonl
    python bench/results/small_budget_pagepair31/link_convergence.py --table link/   # the medians

SERVE_ROOT holds the scene directories (copies: the server does not follow links out of its root); TREE is the
code measured (this branch or its base), the bench importing its client.
"""
from __future__ import annotations

import collections
import glob
import json
import os
import statistics
import sys
import time


def measure(serve_root: str, scene: str, lvp: str, budgets: list[float], runs: int) -> None:
    tree = os.environ.get("PYTHONPATH", ".").split(os.pathsep)[0]
    sys.path.insert(0, os.path.join(tree, "bench"))
    from lod_vs_peers import view_argv

    from cli.commands import view as view_cmd
    from cli.commands.args import parse_size
    from cli.main import build_parser
    from client_gl.gpu.gl import wait_for_gpu
    from client_gl.offscreen import create_context
    from client_gl.streaming import StreamingSession
    from server.testing import ServerThread
    from server.throttle import MBIT, Link
    from splatstream.camera import Camera

    d = json.load(open(lvp))
    cams = [Camera.from_dict(c) for c in d["cameras"]]
    server = ServerThread(serve_root, throttle=Link(20 * MBIT, 0.040))
    ctx = create_context()
    try:
        for r in range(runs):
            for b in budgets:
                n = max(1, int(round(b * d["splats"])))
                for v, cam in enumerate(cams):
                    url = f"http://127.0.0.1:{server.port}/scenes/{scene}/"
                    argv = view_argv(url, n, 384, cam.eye, cam.target, cam.up, cam.fov_y_deg) + \
                        ["--quiet", "--no-cache", "--no-prefetch"]
                    args = build_parser().parse_args(argv)
                    options = view_cmd._options(args)
                    camera = view_cmd._fixed_camera(args, parse_size(args.size))
                    t0, c0 = time.perf_counter(), time.process_time()
                    session = StreamingSession.open(url, ctx, options)
                    frames = 0
                    try:
                        while True:
                            rec = session.frame(camera)
                            wait_for_gpu()
                            frames += 1
                            if session.converged:
                                break
                            if time.perf_counter() - t0 > 120:
                                raise SystemExit("not converged after 120 s")
                            if not rec.uploaded_bytes:
                                session.wait(0.005)
                        out = {"scene": scene, "budget": b, "view": v, "run": r,
                               "converged_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                               "frames": frames,
                               "pages": session.engine.pages.pages_read if session.engine.pages else 0,
                               "downloaded": session.fetcher.stats().bytes_downloaded,
                               "draw": sorted(int(t) for t in session.last.draw), "load": os.getloadavg()[0]}
                    finally:
                        session.close()
                    print(json.dumps(out), flush=True)
    finally:
        ctx.release()
        server.stop()


def table(folder: str) -> None:
    """Per scene and budget: convergence time's median and range, CPU, pages, bytes, before -> after, and whether
    every run of a view drew the same cut on both sides (SCENE_before.jsonl, SCENE_after.jsonl)."""
    for path in sorted(glob.glob(os.path.join(folder, "*_before.jsonl"))):
        scene = os.path.basename(path)[: -len("_before.jsonl")]
        sides = {s: [json.loads(x) for x in open(os.path.join(folder, f"{scene}_{s}.jsonl"))]
                 for s in ("before", "after")}
        for b in sorted({x["budget"] for x in sides["before"]}):
            cuts = collections.defaultdict(set)
            cells = []
            for rows in sides.values():
                rs = [x for x in rows if x["budget"] == b]
                for x in rs:
                    cuts[x["view"]].add(tuple(x["draw"]))
                t = [x["converged_s"] for x in rs]
                cells.append(f"{statistics.median(t):.2f} s ({min(t):.2f}-{max(t):.2f}), CPU "
                             f"{statistics.mean(x['cpu_s'] for x in rs):.2f} s, pages "
                             f"{statistics.mean(x['pages'] for x in rs):.2f}, "
                             f"{statistics.mean(x['downloaded'] for x in rs):,.0f} B, {len(rs)} streams")
            same = all(len(c) == 1 for c in cuts.values())
            print(f"| {scene} | {b * 100:.0f} % | {cells[0]} | {cells[1]} | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    if sys.argv[1] == "--table":
        table(sys.argv[2])
    else:
        measure(sys.argv[1], sys.argv[2], sys.argv[3], [float(x) for x in sys.argv[4].split(",")], int(sys.argv[5]))
