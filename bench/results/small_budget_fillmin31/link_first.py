#!/usr/bin/env python3
"""The first picture and convergence over the reference access link (20 Mbit/s, 40 ms a request: server/throttle.py's
Link) with two settings of `view` (arms: `--fill-min-kb 64` and `--fill-min-kb 160`, or `--fill-gap 4` and `5`;
`in_flight=N` in an arm: N requests in flight over N connections, the client's defaults 6 and 8),
paired: for every run, budget and view the two arms stream back to back (their order alternating by run), the
lod_vs_peers cameras, --no-prefetch, no disk cache (issue 31, branch fillmin31: what a larger threshold costs the
first picture). One JSON line a stream on stdout.

    PYTHONPATH=. python bench/results/small_budget_fillmin31/link_first.py SERVE_ROOT SCENE LOD_VS_PEERS.json \
        0.06,0.25 RUNS "--fill-min-kb 64,--fill-min-kb 160" >> link/SCENE.jsonl
    python bench/results/small_budget_fillmin31/link_first.py --table link/

SERVE_ROOT holds the scene directories (copies: the server does not follow links out of its root).
"""
from __future__ import annotations

import collections
import glob
import json
import os
import statistics
import sys
import time
from dataclasses import replace


def measure(serve_root: str, scene: str, lvp: str, budgets: list[float], runs: int, arms: list[str]) -> None:
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
    from lod_vs_peers import view_argv

    from cli.commands import view as view_cmd
    from cli.commands.args import parse_size
    from cli.main import build_parser
    from client_gl.gpu.gl import wait_for_gpu
    from client_gl.offscreen import create_context
    from client_gl.stream.sources import open_source
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
                    for arm in (arms if r % 2 == 0 else arms[::-1]):
                        url = f"http://127.0.0.1:{server.port}/scenes/{scene}/"
                        # `in_flight=N`, an arm's token that no view option sets: N requests in flight and N
                        # connections (ViewOptions.max_in_flight, 6, and the HTTP source's connections, 8, by default)
                        in_flight = [int(t.split("=")[1]) for t in arm.split() if t.startswith("in_flight=")]
                        argv = view_argv(url, n, 384, cam.eye, cam.target, cam.up, cam.fov_y_deg) + \
                            ["--quiet", "--no-cache", "--no-prefetch",
                             *[t for t in arm.split() if not t.startswith("in_flight=")]]
                        args = build_parser().parse_args(argv)
                        options = view_cmd._options(args)
                        spec = url
                        if in_flight:
                            options = replace(options, max_in_flight=in_flight[0])
                            spec = open_source(url, connections=in_flight[0])
                        camera = view_cmd._fixed_camera(args, parse_size(args.size))
                        t0, c0 = time.perf_counter(), time.process_time()
                        session = StreamingSession.open(spec, ctx, options)
                        first_splats = None
                        try:
                            while True:
                                rec = session.frame(camera)
                                wait_for_gpu()
                                if first_splats is None and rec.drawn_splats:
                                    first_splats = rec.drawn_splats
                                if session.converged:
                                    break
                                if time.perf_counter() - t0 > 120:
                                    raise SystemExit("not converged after 120 s")
                                if not rec.uploaded_bytes:
                                    session.wait(0.005)
                            m = session.metrics
                            out = {"scene": scene, "budget": b, "view": v, "run": r, "arm": arm,
                                   "first_s": m.first_frame_s, "first_splats": first_splats,
                                   "first_bytes": m.bytes_first_frame,
                                   "converged_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                                   "downloaded": session.fetcher.stats().bytes_downloaded,
                                   "draw": sorted(int(t) for t in session.last.draw), "load": os.getloadavg()[0]}
                        finally:
                            session.close()
                        print(json.dumps(out), flush=True)
    finally:
        ctx.release()
        server.stop()


def table(folder: str) -> None:
    """Per scene and budget, each arm: the first picture's time (median, range), its splats, convergence's time,
    bytes; paired differences (the second arm less the first, same run, budget and view)."""
    print("| scene, budget | arm | first picture: median (range), splats drawn | converged: median (range) | "
          "downloaded B | paired, second - first: first picture later in, median; converged later in, median | "
          "same cut |")
    print("|---|---|---|---|---|---|---|")
    for path in sorted(glob.glob(os.path.join(folder, "*.jsonl"))):
        rows = [json.loads(x) for x in open(path)]
        scene = rows[0]["scene"]
        for b in sorted({x["budget"] for x in rows}):
            rs = [x for x in rows if x["budget"] == b]
            arm_names = list(dict.fromkeys(x["arm"] for x in rs))  # the first run's order: the command's
            cuts = collections.defaultdict(set)
            for x in rs:
                cuts[x["view"]].add(tuple(x["draw"]))
            by = {(x["arm"], x["run"], x["view"]): x for x in rs}
            first, second = arm_names[0], arm_names[-1]
            pairs = [(by[(first, r, v)], by[(second, r, v)]) for (k, r, v) in by
                     if k == first and (second, r, v) in by]
            df = [hi["first_s"] - lo["first_s"] for lo, hi in pairs]
            dc = [hi["converged_s"] - lo["converged_s"] for lo, hi in pairs]
            for i, arm in enumerate(arm_names):
                s = [x for x in rs if x["arm"] == arm]
                f = [x["first_s"] for x in s]
                c = [x["converged_s"] for x in s]
                paired = (f"{sum(x > 0 for x in df)} of {len(df)}, {statistics.median(df):+.3f} s; "
                          f"{sum(x > 0 for x in dc)} of {len(dc)}, {statistics.median(dc):+.3f} s") if i else ""
                print(f"| {scene} {b * 100:.0f} % | `{arm}` | {statistics.median(f):.3f} s "
                      f"({min(f):.3f}-{max(f):.3f}), {statistics.median(x['first_splats'] for x in s):,.0f} | "
                      f"{statistics.median(c):.3f} s ({min(c):.3f}-{max(c):.3f}) | "
                      f"{statistics.mean(x['downloaded'] for x in s):,.0f} | {paired} | "
                      f"{('yes' if all(len(v) == 1 for v in cuts.values()) else 'no') if i else ''} |")


if __name__ == "__main__":
    if sys.argv[1] == "--table":
        table(sys.argv[2])
    else:
        measure(sys.argv[1], sys.argv[2], sys.argv[3], [float(x) for x in sys.argv[4].split(",")], int(sys.argv[5]),
                sys.argv[6].split(","))
