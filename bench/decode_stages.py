"""Where a `verified` decode pass goes, stage by stage, on the client's path with the whole kernel (issue 32, vhdec32b:
very-high at 9.2-10.1 M splats/s on r31's host, every lossy preset 10.6-13.9).

    python bench/decode_stages.py [--scenes guitar,winter_fountain] [--presets very-high,medium,high] [--runs 20]

bench/decode_quiet.py's `verified` pass (its Case: every payload of every tile, a group at a time through
format.decode.decode_payloads from the fetcher's VerifiedPayloads, the `fast` extra's numba kernels as
decode_jit.install() installs them) with the thread's CPU time (time.thread_time) split at the calls of
format.container's group path, which this script wraps (the wrappers' own cost, about 0.1 us a call, lands in the
stage that calls them):

* `zstd`: container._decompress_group and _decompress_into (a run's frames into the kept buffer);
* `plan`: container._unpack_group up to its call of run_whole_at (run_whole before vhdec33; the Python walk over
  every section of every payload of a run that plans the kernel's rows);
* `call`: transport.run_whole_at (run_whole) less the kernel (the rows' arrays, the texel slab, the call's arguments);
* `kernel`: decode_jit.whole_kernel itself (fields1 sections, shuffled units, float and range checks);
* `views`: _unpack_group after run_whole_at (the views of each payload's planes, EncodedPlane, the ranges' views);
* `rest`: the pass less all of those (decode_payloads' and unpack_payloads' Python, verified_bytes, the runs' loop).

Medians over --runs passes (each stage's own median; `pass` the passes' median), in ms and as M splats/s of the
pass. --run-bytes A,B,...: the pass with each size of the whole kernel's runs (container.RUN_RAW_BYTES), alternating
in every round (a core with a larger L2 may take larger runs). One JSON object on stdout (and in --json).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import decode_quiet  # noqa: E402  (bench/: its Case, encode and kernels)

from splatstream.format import container, transport  # noqa: E402

STAGES = ("zstd", "plan", "call", "kernel", "views", "rest")


class Stages:
    """Wraps container's group path and the whole kernel, adding each stage's thread CPU time to `spent`."""

    def __init__(self, kernel) -> None:
        self.spent = dict.fromkeys(STAGES, 0.0)
        self.group_start = self.call_end = 0.0
        clock, spent = time.thread_time, self.spent
        # the call container's group path makes: run_whole_at since vhdec33 (3 ints a section), run_whole before
        self._call = "run_whole_at" if hasattr(container, "run_whole_at") else "run_whole"
        run_whole, unpack_group = getattr(container, self._call), container._unpack_group
        decompress_group, decompress_into = container._decompress_group, container._decompress_into

        def timed_kernel(*args):
            t = clock()
            status = kernel(*args)
            spent["kernel"] += clock() - t
            return status

        def timed_run_whole(*args, **kwargs):
            t = clock()
            spent["plan"] += t - self.group_start
            before = spent["kernel"]
            got = run_whole(*args, **kwargs)
            self.call_end = clock()
            spent["call"] += self.call_end - t - (spent["kernel"] - before)
            return got

        def timed_unpack_group(*args, **kwargs):
            self.group_start = clock()
            got = unpack_group(*args, **kwargs)
            spent["views"] += clock() - self.call_end
            return got

        def timed(function):
            def call(*args):
                t = clock()
                got = function(*args)
                spent["zstd"] += clock() - t
                return got
            return call

        self._previous = (transport.use_whole_kernel(timed_kernel), run_whole, unpack_group, decompress_group,
                          decompress_into)
        setattr(container, self._call, timed_run_whole)
        container._unpack_group = timed_unpack_group
        container._decompress_group = timed(decompress_group)
        container._decompress_into = timed(decompress_into)

    def close(self) -> None:
        """Put back what __init__ wrapped (the whole kernel handed in before, container's own functions)."""
        kernel, run_whole, container._unpack_group, container._decompress_group, \
            container._decompress_into = self._previous
        setattr(container, self._call, run_whole)
        transport.use_whole_kernel(kernel)

    def reset(self) -> None:
        for k in self.spent:
            self.spent[k] = 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="guitar,winter_fountain")
    ap.add_argument("--presets", default="very-high,medium,high")
    ap.add_argument("--runs", type=int, default=20, help="timed passes of each case (after one untimed pass)")
    ap.add_argument("--run-bytes", default=str(container.RUN_RAW_BYTES),
                    help="comma-separated values of container.RUN_RAW_BYTES (the whole kernel's runs of decompressed "
                    "bytes), each timed in turn in every round, alternating (default: the library's)")
    ap.add_argument("--json", help="also write the JSON here")
    args = ap.parse_args()
    run_bytes = [int(v) for v in args.run_bytes.split(",")]
    kernels, why = decode_quiet._numba_kernel()
    if kernels is None:
        raise SystemExit(f"the numba kernels (the `fast` extra) are needed: {why}")
    decode_quiet._use(kernels)
    stages = Stages(transport.whole_kernel())
    scenes = dict(s.split("=", 1) if "=" in s else (s, decode_quiet.SCENES[s]) for s in args.scenes.split(","))
    rows = []
    for scene, path in scenes.items():
        for preset in args.presets.split(","):
            _, _, store, _ = decode_quiet.encode(scene, preset, path)
            if isinstance(store, str):
                print(f"{scene} {preset}: skipped: {store}", file=sys.stderr)
                continue
            case = decode_quiet.Case(store)
            case.run("verified")  # warm-up: allocations, caches
            passes = {b: [] for b in run_bytes}
            by_stage = {b: {k: [] for k in STAGES} for b in run_bytes}
            for _ in range(args.runs):
                for b in run_bytes:  # each run size once a round: any load falls on them alike
                    container.RUN_RAW_BYTES = b
                    stages.reset()
                    took = case.run("verified")
                    passes[b].append(took)
                    for k in STAGES[:-1]:
                        by_stage[b][k].append(stages.spent[k])
                    by_stage[b]["rest"].append(took - sum(stages.spent[k] for k in STAGES[:-1]))
            for b in run_bytes:
                ms = {k: round(statistics.median(v) * 1e3, 3) for k, v in by_stage[b].items()}
                row = {"scene": scene, "preset": preset, "run_raw_bytes": b, "splats": case.splats,
                       "payloads": case.payloads, "pass_ms": round(statistics.median(passes[b]) * 1e3, 3),
                       "m_splats_s": round(case.splats / statistics.median(passes[b]) / 1e6, 2), "stages_ms": ms}
                rows.append(row)
                print(f"{scene:>16} {preset:>12} runs of {b:>8} B: pass {row['pass_ms']:7.3f} ms "
                      f"({row['m_splats_s']:5.2f} M splats/s) " + " ".join(f"{k} {v:.3f}" for k, v in ms.items()),
                      file=sys.stderr, flush=True)
            container.RUN_RAW_BYTES = run_bytes[0]
    report = {"bench": "bench/decode_stages.py", "argv": sys.argv[1:],
              "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "cpu": decode_quiet._cpu_name(),
              "load_average_end": os.getloadavg(), "runs": args.runs, "cases": rows}
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
