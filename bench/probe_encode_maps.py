"""Where a partitioned encode's time goes between the engine's task rounds and the client (issue 16): encodes
INPUT with `encode_file(..., workers=N)` and prints every round of tasks the engine ran (function, tasks, start,
seconds), the client's time between rounds summed per following round, and the time after the last round
(manifest, scratch removal, cluster shutdown).

    python bench/probe_encode_maps.py /tmp/bs/scene_60000000.ply --workers 16 --memory-per-worker 3GB [--json OUT]
"""
from __future__ import annotations

import argparse
import collections
import json
import shutil
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input")
    ap.add_argument("--workers", type=int, required=True)
    ap.add_argument("--memory-per-worker", default="3GB")
    ap.add_argument("--json")
    args = ap.parse_args()
    from cli.commands.args import parse_bytes
    from splatstream.encode import distributed, encode_file

    rounds: list[tuple[str, int, float, float]] = []
    original = distributed.DaskEngine.map

    def timed(self, fn, tasks, stage, progress, heavy=False, task_progress=False):
        t = time.perf_counter()
        try:
            return original(self, fn, tasks, stage, progress, heavy, task_progress)
        finally:
            rounds.append((fn.__name__, len(tasks), t, time.perf_counter() - t))

    distributed.DaskEngine.map = timed
    out = tempfile.mkdtemp(prefix="probe-maps-")
    t0 = time.perf_counter()
    try:
        encode_file(args.input, f"{out}/scene", workers=args.workers,
                    memory_per_worker=parse_bytes(args.memory_per_worker, "--memory-per-worker"))
    finally:
        total = time.perf_counter() - t0
        shutil.rmtree(out, ignore_errors=True)
    per = collections.defaultdict(lambda: {"rounds": 0, "tasks": 0, "seconds": 0.0, "client_before_s": 0.0})
    last = t0
    for name, n, start, seconds in rounds:
        p = per[name]
        p["rounds"] += 1
        p["tasks"] += n
        p["seconds"] += seconds
        p["client_before_s"] += start - last
        last = start + seconds
    report = {"workers": args.workers, "total_s": round(total, 2), "after_last_round_s": round(t0 + total - last, 2),
              "per_function": {k: {kk: round(vv, 2) for kk, vv in v.items()} for k, v in per.items()},
              "rounds": [(name, n, round(start - t0, 2), round(seconds, 2)) for name, n, start, seconds in rounds]}
    for k, v in report["per_function"].items():
        print(f"{k:22s} rounds {v['rounds']:3.0f} tasks {v['tasks']:5.0f} in rounds {v['seconds']:7.2f} s, "
              f"client before them {v['client_before_s']:6.2f} s")
    print(f"total {report['total_s']} s, after the last round {report['after_last_round_s']} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
