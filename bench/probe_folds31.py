"""Where the upper stage of a partitioned `auto` encode spends its CPU (issue 31, branch folds31): every step of
partitioned._upper_tiles timed in this process (LocalEngine), the tasks and the client's own folds apart.

    PYTHONPATH=. python bench/probe_folds31.py IN.ply OUT_DIR DOMAIN_SPLATS [--memory-mib M] [--max-leaf N]
        [--workers N] [--label L] [--json FILE]

DOMAIN_SPLATS forces the merge domains small (EncodeOptions.lod_merge_domain_splats: 32-128 partitions of a scene of
a few million splats); --max-leaf is EncodeOptions.max_leaf_splats (smaller: more originals per partition root, as
at city scale, where a partition holds about 60 times its root's splats). CPU seconds per step: the thread's own
(time.thread_time) for the tasks LocalEngine runs on its pool threads, the process's for the heavy tasks it runs
alone (their own pools' threads included) and for the client's steps; "client other": the upper stage's CPU less
every task and every step timed on the client (its loops: the partitions' maps, the extremes' folds, the
bookkeeping); steps inside a task are listed apart ("in task") and are part of its CPU. Stage times
from the progress callback, as bench/probe_tier31.py; peak RSS this process's (ru_maxrss). --workers: a local Dask
cluster (the steps then run in the workers, untimed): the upper stage's maps, their tasks and the client's wall
waiting for each.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import sys
import threading
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.encode import encode_file, partitioned  # noqa: E402

# the upper stage's tasks: LocalEngine runs these on its pool threads (thread CPU) ...
POOLED = ("partition_extremes", "partition_sums", "encode_saved_tile")
# ... and these alone (process CPU: their own pools' threads included); merge_level: before folds31
HEAVY = ("upper_domain_step", "merge_level", "refine_upper")
# steps timed where they run: on the client (before folds31) or inside a task (upper_domain_step since)
STEPS = ("tile_error_first", "fold_leaf_sums", "finish_tile_appearance", "interior_bounds", "_save_tile", "encode_tile",
         "_merged_tiles", "_finish_tile")


def _array_bytes(x) -> int:
    """Bytes of the numpy arrays in a task's arguments (the folds a step is handed: made before it starts)."""
    import numpy as np

    if isinstance(x, np.ndarray):
        return x.nbytes
    if isinstance(x, (list, tuple)):
        return sum(_array_bytes(v) for v in x)
    if isinstance(x, dict):
        return sum(_array_bytes(v) for v in x.values())
    if hasattr(x, "__dataclass_fields__"):
        return sum(_array_bytes(getattr(x, f)) for f in x.__dataclass_fields__)
    return 0


def tree_digest(path: str) -> str:
    h = hashlib.sha256()
    for root, _, files in sorted(os.walk(path)):
        for f in sorted(files):
            p = os.path.join(root, f)
            h.update(os.path.relpath(p, path).encode())
            with open(p, "rb") as fh:
                h.update(fh.read())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input")
    ap.add_argument("out")
    ap.add_argument("domain", type=int)
    ap.add_argument("--memory-mib", type=int, default=1024)
    ap.add_argument("--workers", type=int)
    ap.add_argument("--trace", action="store_true", help="each heavy upper task's peak memory (tracemalloc)")
    ap.add_argument("--traffic", action="store_true",
                    help="the pickled bytes of each upper task's arguments and result (what Dask carries)")
    ap.add_argument("--max-leaf", type=int)
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--label", default="")
    ap.add_argument("--json")
    a = ap.parse_args()
    kw: dict = {"lod_merge_domain_splats": a.domain}
    if a.max_leaf:
        kw["max_leaf_splats"] = a.max_leaf
    stages: list[tuple[str, float, float]] = []
    steps: dict[str, list[float]] = {}
    lock = threading.Lock()
    in_upper = [False]

    def progress(stage: str, fraction: float) -> None:
        if not stages or stages[-1][0] != stage:
            stages.append((stage, time.perf_counter(), time.process_time()))
            in_upper[0] = stage == "upper"

    local = threading.local()  # inside a task: its steps are the task's, not the client's

    def timed(name: str, fn, clock, task: bool):
        def run(*args, **kwargs):
            depth = getattr(local, "depth", 0)
            local.depth = depth + 1
            c = clock()
            try:
                out = fn(*args, **kwargs)
            finally:
                local.depth = depth
            if not in_upper[0]:  # _save_tile and encode_tile also run in the partitions' tasks (tiles stage)
                return out
            key = f"task {name}" if task else f"{'in task' if depth else 'client'} {name}"
            with lock:
                acc = steps.setdefault(key, [0, 0.0])
                acc[0] += 1
                acc[1] += clock() - c
            return out
        return run

    traffic: dict[str, list[int]] = {}  # --traffic: per task, [calls, argument bytes, result bytes] (pickled)

    def carried(name: str, fn):
        def run(*args, **kwargs):
            import pickle

            out = fn(*args, **kwargs)
            if in_upper[0]:
                # the arguments but the payload writer and context (the same object every task: Dask sends them
                # once a task too, but they are not the upper stage's data)
                sent = [v for v in args if not callable(getattr(v, "write", None)) and
                        type(v).__name__ not in ("TileContext", "DirectoryPayloads", "MemoryWriter")]
                acc = traffic.setdefault(name, [0, 0, 0])
                acc[0] += 1
                acc[1] += len(pickle.dumps(sent, protocol=5))
                acc[2] += len(pickle.dumps(out, protocol=5))
            return out
        return run

    if a.traffic:
        for name in POOLED + HEAVY:
            if hasattr(partitioned, name):
                setattr(partitioned, name, carried(name, getattr(partitioned, name)))
    for name in POOLED if not a.workers else ():  # on Dask the tasks run in the workers (and must pickle)
        if hasattr(partitioned, name):
            setattr(partitioned, name, timed(name, getattr(partitioned, name), time.thread_time, True))
    peaks: dict[str, list[int]] = {}  # --trace: per heavy task, its arguments' arrays + tracemalloc's peak in it

    def traced(name: str, fn):
        def run(*args, **kwargs):
            import tracemalloc

            held = sum(_array_bytes(v) for v in args if isinstance(v, dict))  # the folds (not ctx's codebook)
            tracemalloc.start()
            try:
                return fn(*args, **kwargs)
            finally:
                peak = tracemalloc.get_traced_memory()[1]
                tracemalloc.stop()
                peaks.setdefault(name, []).append(held + peak)
        return run

    for name in HEAVY if not a.workers else ():
        if hasattr(partitioned, name):
            fn = getattr(partitioned, name)
            if a.trace:
                fn = traced(name, fn)
            setattr(partitioned, name, timed(name, fn, time.process_time, True))
    for name in STEPS if not a.workers else ():
        if hasattr(partitioned, name):
            setattr(partitioned, name, timed(name, getattr(partitioned, name), time.process_time, False))
    shutil.rmtree(a.out, ignore_errors=True)
    t0, c0 = time.perf_counter(), time.process_time()
    maps: list[dict] = []  # with --workers: each map of the upper stage, its tasks and its wall (the client waits)
    if a.workers:
        from splatstream.encode import distributed

        plain_map = distributed.DaskEngine.map

        def timed_map(self, fn, args, stage, *rest, **kwargs):
            w = time.perf_counter()
            out = plain_map(self, fn, args, stage, *rest, **kwargs)
            if stage in ("upper", "refine-upper"):
                maps.append({"task": fn.__name__, "tasks": len(args), "wall_s": round(time.perf_counter() - w, 3)})
            return out
        distributed.DaskEngine.map = timed_map
    encode_file(a.input, a.out, preset=a.preset, progress=progress, memory_per_worker=a.memory_mib << 20,
                workers=a.workers, **kw)
    t1, c1 = time.perf_counter(), time.process_time()
    per_stage: dict[str, list[float]] = {}
    for (stage, w, c), nxt in zip(stages, [*stages[1:], ("end", t1, c1)], strict=True):
        acc = per_stage.setdefault(stage, [0.0, 0.0])
        acc[0] += nxt[1] - w
        acc[1] += nxt[2] - c
    upper_cpu = per_stage.get("upper", [0.0, 0.0])[1]
    timed_cpu = sum(v[1] for k, v in steps.items() if not k.startswith("in task"))
    out = {"label": a.label, "input": a.input, "domain": a.domain, "max_leaf": a.max_leaf,
           "memory_mib": a.memory_mib, "wall_s": round(t1 - t0, 2), "cpu_s": round(c1 - c0, 2),
           "stages": {k: {"wall_s": round(v[0], 2), "cpu_s": round(v[1], 2)} for k, v in per_stage.items()},
           "steps": {k: {"calls": v[0], "cpu_s": round(v[1], 3)} for k, v in sorted(steps.items())},
           "client_other_cpu_s": round(upper_cpu - timed_cpu, 3), "workers": a.workers,
           "task_peak_mib": {k: round(max(v) / 2**20, 2) for k, v in peaks.items()},
           "traffic_mb": {k: {"tasks": v[0], "args": round(v[1] / 1e6, 2), "results": round(v[2] / 1e6, 2)}
                          for k, v in traffic.items()},
           "upper_maps": len(maps), "upper_map_walls": {
               name: {"maps": sum(1 for m in maps if m["task"] == name), "tasks": sum(m["tasks"] for m in maps
                                                                                     if m["task"] == name),
                      "wall_s": round(sum(m["wall_s"] for m in maps if m["task"] == name), 2)}
               for name in sorted({m["task"] for m in maps})},
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
           "loadavg": os.getloadavg(), "digest": tree_digest(a.out)}
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "a") as f:
            f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
