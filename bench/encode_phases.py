"""Where one in-process encode's CPU and peak memory go: CPU per phase, and what runs at the peak RSS.

    PYTHONPATH=. python bench/encode_phases.py SCENE OUT_DIR [--preset medium] [--lod-merge grid|auto|cost]
        [--threads | --timeline]

Runs `encode_file` once in this process with every thread pool (the LOD tree's, the payloads') replaced by an inline
executor, so that every job runs on the calling thread and the process CPU of each wrapped function is its own
(inclusive: the grouping's row includes its k-NN, costs and matching). Without pools a phase's CPU is the work
itself, not the interpreter-lock hand-offs of two threads (BENCHMARKS.md, "Where the grid encode's CPU goes");
`--threads` keeps the pools as shipped. Either way the payloads stay in this process (no forked children);
`--timeline` runs the encode exactly as shipped, children included. A thread samples the RSS every 3 ms and records,
at its largest, the wrapped phases running and the main thread's innermost lines. Prints one JSON object: CPU s per
wrapped function, the whole encode's CPU and wall, the peak RSS and where it was reached.
"""
from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import resource
import shutil
import sys
import threading
import time
from concurrent.futures import Future

import splatstream.encode.driver as driver
import splatstream.encode.local as local
import splatstream.encode.plan as plan
import splatstream.io as splat_io
import splatstream.lod as lod
import splatstream.lod_groups as lod_groups
from splatstream.format import codec, container, transport


class InlineExecutor:
    """A ThreadPoolExecutor stand-in that runs every job at once on the calling thread."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def submit(self, fn, *args, **kwargs) -> Future:
        done: Future = Future()
        done.set_result(fn(*args, **kwargs))
        return done

    def map(self, fn, *iterables):
        return [fn(*args) for args in zip(*iterables, strict=False)]

    def shutdown(self, *args, **kwargs) -> None:
        pass

    def __enter__(self) -> InlineExecutor:
        return self

    def __exit__(self, *exc) -> None:
        pass


# (module, function) pairs timed; a name imported by another module is wrapped where it is called from.
WRAPPED = (
    (splat_io, "read_gaussians"), (plan, "build_tiles"), (lod, "_kd_leaves"), (lod, "_leaf_orders"),
    (lod, "level_auto_groups"), (lod, "level_cost_groups"), (lod, "auto_tile_choice"), (lod, "group_ids_of"),
    (lod, "merge_groups"), (lod, "merge_gaussians"), (lod, "finish_tile"), (lod, "extent_bounds"),
    (lod_groups, "neighbour_keys"), (lod_groups, "edge_costs_at"), (lod_groups, "_greedy_pairs"),
    (lod_groups, "_cheapest_share"), (lod_groups, "_merge_pairs"), (lod_groups, "_drop"),
    (lod_groups, "covariances6"), (lod_groups, "_sorted_unique"), (lod_groups, "_morton_finish"),
    (local, "encode_group"), (container, "filter_texels"), (transport, "code_layer"), (transport, "_choose"),
    (transport, "split_layer"), (transport, "_zstd_size"), (container, "_block_ends"),
    (container, "_compress_segments"), (codec, "chunk_ranges"), (codec, "_texture_blob"),
)
# The payload stage's rows (encfast31): `_choose` is choose_modes' work (code_layer calls it, choose_modes wraps it;
# before encfast31 this row was `choose_modes`); `filter_texels` holds code_layer and the layers' quantisation (the
# plane's lazy layers are made as it asks for them), `_zstd_size` the fields1-or-shuffle trials; `_block_ends` and
# `_compress_segments` are write_payload's block trials and its compression.


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--lod-merge", default=None)
    ap.add_argument("--threads", action="store_true", help="keep the thread pools as shipped")
    ap.add_argument("--timeline", action="store_true",
                    help="pools as shipped, no wrappers: per progress stage its wall span and the process CPU in it "
                         "(CPU / wall near 1: one core busy, near 2: two), as a user's encode runs")
    args = ap.parse_args()
    if args.timeline:
        return timeline(args)
    # The payloads in this process (no forked children, encode/forked.py): a child's CPU is not this process's, so
    # the wrappers would miss it
    local.payload_processes = lambda writer, cores=None: 0
    if not args.threads:
        lod.ThreadPoolExecutor = InlineExecutor
        local.ThreadPoolExecutor = InlineExecutor
    cpu: dict[str, float] = collections.defaultdict(float)
    running: list[str] = []
    peak = [0, ""]
    main_thread = threading.get_ident()
    page = os.sysconf("SC_PAGE_SIZE")

    def sample() -> None:
        while True:
            with open("/proc/self/statm") as statm:
                rss = int(statm.read().split()[1]) * page
            if rss > peak[0]:
                frame, lines = sys._current_frames().get(main_thread), []
                while frame is not None and len(lines) < 4:
                    lines.append(f"{os.path.basename(frame.f_code.co_filename)}:{frame.f_lineno}")
                    frame = frame.f_back
                peak[0], peak[1] = rss, "/".join(running) + " @ " + " < ".join(lines)
            time.sleep(0.003)

    def wrap(module, name: str) -> None:
        fn = getattr(module, name)

        @functools.wraps(fn)
        def timed(*a, **k):
            t0 = time.process_time()
            running.append(name)
            try:
                return fn(*a, **k)
            finally:
                running.pop()
                cpu[name] += time.process_time() - t0

        setattr(module, name, timed)

    for module, name in WRAPPED:
        wrap(module, name)
    threading.Thread(target=sample, daemon=True).start()
    shutil.rmtree(args.out, ignore_errors=True)
    options = {} if args.lod_merge is None else {"lod_merge": args.lod_merge}
    t0, w0 = time.process_time(), time.perf_counter()
    driver.encode_file(args.scene, args.out, preset=args.preset, **options)
    total, wall = time.process_time() - t0, time.perf_counter() - w0
    print(json.dumps({"cpu_s": round(total, 3), "wall_s": round(wall, 3), "load": os.getloadavg()[0],
                      "peak_rss_mb": round(peak[0] / 2**20, 1), "peak_at": peak[1],
                      "maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                      **{name: round(s, 3) for name, s in cpu.items()}}, indent=1))


def timeline(args) -> None:
    """The encode as shipped (pools, processes), its progress stages stamped: wall and process CPU (this process
    and its reaped children) at each stage's first and last report."""
    spans: dict[str, list[float]] = {}

    def cpu_now() -> float:
        own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime

    t0, c0 = time.perf_counter(), cpu_now()

    def progress(stage: str, fraction: float) -> None:
        now, cpu_s = time.perf_counter() - t0, cpu_now() - c0
        if stage not in spans:
            spans[stage] = [now, cpu_s, now, cpu_s]
        spans[stage][2:] = [now, cpu_s]

    shutil.rmtree(args.out, ignore_errors=True)
    options = {} if args.lod_merge is None else {"lod_merge": args.lod_merge}
    driver.encode_file(args.scene, args.out, preset=args.preset, progress=progress, **options)
    wall, total = time.perf_counter() - t0, cpu_now() - c0
    rows = [{"stage": k, "wall_from": round(v[0], 2), "wall_to": round(v[2], 2), "cpu_s": round(v[3] - v[1], 2),
             "cores": round((v[3] - v[1]) / max(v[2] - v[0], 1e-9), 2)} for k, v in spans.items()]
    print(json.dumps({"wall_s": round(wall, 2), "cpu_s": round(total, 2), "load": os.getloadavg()[0],
                      "maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                      "children_maxrss_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1),
                      "stages": rows}, indent=1))


if __name__ == "__main__":
    main()
