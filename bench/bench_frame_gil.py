"""Who runs Python while the frame loop works, without GL: the fly-through's engine side on the CPU.

The streaming engine as `view` runs it (the scene served on loopback by `splatstream serve`, the Fetcher with its
event loop thread, the decode threads, a paged tree's pages parsed on them) along bench_flythrough.py's camera path,
with a pool that only counts slots (bench_pages.py's) instead of the GPU. Each frame: `frame_started`, the engine's
update, `frame_submitted`, then --gpu-ms of sleep standing for the GPU's work (the loop's idle time, when the decode
threads and the fetch loop may run). Per frame: the update's wall and the frame thread's CPU (their difference is what
it waited: the interpreter lock, the fetcher's lock), and the CPU every other thread used during the update
(bench_flythrough.OtherThreadsCpu): CPU the gates (decode's `between`, Fetcher.yield_to) let through.

    PYTHONPATH=. python bench/bench_frame_gil.py --scene SCENE_DIR --ply SCENE.ply [--seconds 12] [--json out.json]
        [--no-decode-batch] [--decode-workers-moving N]     # the A/B of the engine's batch decode, fewer threads

Also: the decode jobs and the payloads in them, the decode threads' CPU in all, and the time from the path's end to
convergence (what fewer decode threads during motion cost).

CPU figures hold on a loaded machine better than wall times: the others' CPU during the update is work that ran
there, whatever else the machine did.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "bench"))

from bench_flythrough import OtherThreadsCpu, fly_path, thread_cpu_seconds  # noqa: E402
from bench_pages import _Slots  # noqa: E402
from bench_stream import serve_scene  # noqa: E402

from client_gl.stream.engine import DECODE_WAIT_S, StreamEngine, StreamOptions  # noqa: E402
from client_gl.stream.fetch import Fetcher  # noqa: E402
from client_gl.stream.selection import SelectionOptions  # noqa: E402
from client_gl.stream.sources import HttpSource  # noqa: E402
from client_gl.streaming import freeze_long_lived  # noqa: E402
from splatstream.camera_path import parse_camera_path  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--ply", required=True, help="the scene's source PLY (the camera path's standard view)")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--max-splats", type=int, default=3_000_000)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--gpu-ms", type=float, default=4.0, help="the loop's idle time a frame (the GPU's, standing in)")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--no-decode-batch", action="store_true", help="one decode job a payload (StreamOptions)")
    ap.add_argument("--decode-workers-moving", type=int, default=StreamOptions.decode_workers_moving,
                    help="decode threads while the camera moves (0: all)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    path = parse_camera_path(fly_path(args.ply, args.seconds))
    server, url = serve_scene(args.scene)
    fetcher = Fetcher(HttpSource(url)).start()
    try:
        engine = StreamEngine(fetcher, _Slots(), StreamOptions(SelectionOptions(max_splats=args.max_splats),
                                                               decode_batch=not args.no_decode_batch,
                                                               decode_workers_moving=args.decode_workers_moving))
        fetcher.yield_to(engine.loop_idle, DECODE_WAIT_S)
        freeze_long_lived()
        others = OtherThreadsCpu()
        rows = []
        start = time.perf_counter()
        while True:
            now = time.perf_counter() - start
            cam = path.camera(now, w, h)
            t_start = time.perf_counter()
            engine.frame_started()
            drain = (time.perf_counter() - t_start) * 1e3  # (a gate that drained background steps: 6b7d544)
            o0 = others.start()
            c0, t0 = time.thread_time(), time.perf_counter()
            update = engine.update(cam)
            engine.frame_submitted()
            wall, cpu = (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3
            rows.append({"wall_ms": wall, "cpu_ms": cpu, "others": others.since(o0), "drain_ms": drain,
                         "uploaded": update.uploaded_bytes})
            time.sleep(args.gpu_ms / 1e3)
            if (now > path.end and update.converged) or now > path.end + 60:
                converged_after_path_s = now - path.end
                break
        wall = np.array([r["wall_ms"] for r in rows])
        cpu = np.array([r["cpu_ms"] for r in rows])
        waited = wall - cpu
        by_thread: dict[str, float] = {}
        for r in rows:
            for k, v in r["others"].items():
                by_thread[k] = by_thread.get(k, 0.0) + v
        inside = np.array([sum(r["others"].values()) for r in rows])
        drains = np.array([r["drain_ms"] for r in rows])
        out = {"frames": len(rows), "gpu_ms": args.gpu_ms, "pages_read": engine.pages.pages_read if engine.pages
               else 0, "tiles_held": len(engine.manifest.tiles),
               "update_wall_ms": {"median": float(np.median(wall)), "p99": float(np.percentile(wall, 99)),
                                  "max": float(wall.max())},
               "update_cpu_ms": {"median": float(np.median(cpu)), "p99": float(np.percentile(cpu, 99))},
               "update_waited_ms": {"median": float(np.median(waited)), "p99": float(np.percentile(waited, 99)),
                                    "total": float(waited.sum())},
               "others_cpu_in_updates_ms": {"median": float(np.median(inside)),
                                            "p99": float(np.percentile(inside, 99)), "total": float(inside.sum())},
               "drain_ms": {"median": float(np.median(drains)), "p99": float(np.percentile(drains, 99)),
                            "max": float(drains.max()), "total": float(drains.sum()),
                            "frames_draining": int((drains > 0.05).sum())},
               "others_cpu_in_updates_by_thread_ms": {k: round(v, 1) for k, v in sorted(by_thread.items())},
               "bytes": fetcher.stats().bytes_downloaded,
               "decode_batch": not args.no_decode_batch, "decode_workers_moving": args.decode_workers_moving,
               "decode_jobs": engine.decode_jobs, "decode_job_payloads": engine.decode_job_payloads,
               "moving_frames": engine.moving_frames, "converged_after_path_s": converged_after_path_s,
               "decode_threads_cpu_s": {k: round(v, 3) for k, v in thread_cpu_seconds().items()
                                        if k.startswith("splat-decode")}}
        engine.close()
    finally:
        fetcher.close()
        server.terminate()
        server.wait(10)
    print(json.dumps(out, indent=1))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
