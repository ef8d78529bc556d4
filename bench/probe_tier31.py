"""The levels above the partitions of a partitioned `auto` encode, by upper domains (issue 31, branch tier31;
format_spec/lod.md 6, "Upper domains"): wall and CPU of the upper stages and of the whole encode, peak RSS, the
tree's digest.

    PYTHONPATH=. python bench/probe_tier31.py IN.ply OUT_DIR DOMAIN_SPLATS [--roots K] [--workers N]
        [--memory-mib M] [--json FILE]

DOMAIN_SPLATS forces the merge domains small (EncodeOptions.lod_merge_domain_splats: 32-128 partitions of a scene of
a few million splats); --roots is EncodeOptions.lod_upper_domain_roots (left out: the code's default; on a tree
before branch tier31 there is none, each upper level one task); --workers a local Dask cluster (else this process,
LocalEngine, whose CPU seconds are the encode's: the upper tasks one after another). Stage times from the progress
callback: from a stage's first report to the next stage's first report ("upper": every upper round, the passes over
the partitions' originals and the upper tiles' payloads included). Peak RSS: this process (ru_maxrss; with
--workers, the client only). In this process also each upper task's CPU seconds (process time: the tasks run one after
another): merge_level per level, their sum and their largest (the level's critical path where each task has a
worker); refine_upper's; the passes over the originals and the upper payloads added up (a task per partition or
tile, parallel before tier31 too); the rest of the upper stage is the client's own (folds, errors, bounds).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.encode import EncodeOptions, encode_file  # noqa: E402


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
    ap.add_argument("--roots", type=int)
    ap.add_argument("--workers", type=int)
    ap.add_argument("--memory-mib", type=int, default=1024)
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--json")
    a = ap.parse_args()
    kw: dict = {"lod_merge_domain_splats": a.domain}
    if a.roots is not None:
        if not hasattr(EncodeOptions, "lod_upper_domain_roots"):
            raise SystemExit("--roots: this tree has no upper domains (before branch tier31)")
        kw["lod_upper_domain_roots"] = a.roots
    stages: list[tuple[str, float, float]] = []  # (stage, wall, cpu) at each stage's first report

    def progress(stage: str, fraction: float) -> None:
        if not stages or stages[-1][0] != stage:
            stages.append((stage, time.perf_counter(), time.process_time()))

    tasks: list[dict] = []
    if a.workers is None:  # in this process: each upper merge task's CPU seconds (the tasks run one after another)
        from splatstream.encode import partitioned

        def timed(fn):
            def run(*args):
                c = time.process_time()  # the task's pool threads too (merge_level groups on the task's threads)
                out = fn(*args)
                # merge_level(scratch, shape, lvl, threads[, top, domain]); refine_upper(scratch, shape, level, top,
                # domain, ...) (before tier31: (scratch, shape, level, ...))
                tasks.append({"task": fn.__name__, "level": args[2], "top": args[4] if len(args) > 5 else 0,
                              "cpu_s": round(time.process_time() - c, 3)})
                return out
            return run

        for name in ("merge_level", "refine_upper", "partition_extremes", "partition_sums", "encode_saved_tile"):
            setattr(partitioned, name, timed(getattr(partitioned, name)))
    shutil.rmtree(a.out, ignore_errors=True)
    t0, c0 = time.perf_counter(), time.process_time()
    encode_file(a.input, a.out, preset=a.preset, progress=progress, workers=a.workers,
                memory_per_worker=a.memory_mib << 20, **kw)
    t1, c1 = time.perf_counter(), time.process_time()
    per_stage: dict[str, list[float]] = {}
    for (stage, w, c), nxt in zip(stages, [*stages[1:], ("end", t1, c1)], strict=True):
        acc = per_stage.setdefault(stage, [0.0, 0.0])
        acc[0] += nxt[1] - w
        acc[1] += nxt[2] - c
    out = {"input": a.input, "domain": a.domain, "roots": a.roots, "workers": a.workers, "memory_mib": a.memory_mib,
           "wall_s": round(t1 - t0, 2), "cpu_s": round(c1 - c0, 2),
           "stages": {k: {"wall_s": round(v[0], 2), "cpu_s": round(v[1], 2)} for k, v in per_stage.items()},
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
           "loadavg": os.getloadavg(), "digest": tree_digest(a.out)}
    if tasks:
        # per level: the tasks' CPU added up, and the largest (the level's critical path with a worker per task)
        levels: dict[int, list[float]] = {}
        for t in tasks:
            if t["task"] == "merge_level":
                levels.setdefault(t["level"], []).append(t["cpu_s"])
        out["merge_level"] = {lvl: {"tasks": len(v), "sum_cpu_s": round(sum(v), 3), "max_cpu_s": max(v)}
                              for lvl, v in sorted(levels.items())}
        out["merge_level_sum_cpu_s"] = round(sum(sum(v) for v in levels.values()), 3)
        out["merge_level_critical_cpu_s"] = round(sum(max(v) for v in levels.values()), 3)
        # the upper stage's other tasks (the passes over the originals, the payloads: a task per partition or tile)
        out["upper_tasks_cpu_s"] = {name: round(sum(t["cpu_s"] for t in tasks if t["task"] == name), 3)
                                    for name in ("partition_extremes", "partition_sums", "encode_saved_tile")}
        refine = [t["cpu_s"] for t in tasks if t["task"] == "refine_upper"]
        if refine:
            out["refine_upper_cpu_s"] = refine
    print(json.dumps(out))
    if a.json:
        with open(a.json, "a") as f:
            f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
