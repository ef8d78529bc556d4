"""A large group decoded in runs of container.RUN_RAW_BYTES decompressed bytes against one run a group (issue 32,
branch dec32): the `verified` pass of bench/decode_quiet.py (the streaming client's path, the numba kernels
installed) with each budget, in alternated order each round, on the same encodes.

    PYTHONPATH=. python bench/decode_runs_ab.py [--scenes guitar,winter_fountain,statue_massa] [--presets p,q]
        [--budgets 1048576,0] [--rounds 7] [--json PATH]

A budget of 0 is one run a group (the path before runs: the same code, every group under the budget). Each scene
is encoded with each preset in memory (LOD tree, the encoder's defaults; bench/decode_quiet.py's encode and Case),
the planes of every budget checked equal (texels, ranges, palettes), then thread CPU (time.thread_time) of a pass,
the least of 2 passes a round, the budgets alternated each round. Prints, per case, M splats/s of the least pass
and the median pass's ms per budget and the median of the per-round ratios to the first budget; one JSON object.
In one process the runs read faster than in a fresh one (very-high on this VM: 0.87-0.89 of one run's time here,
0.93-0.95 in A/B runs of main's tree and dec32's in fresh processes; BENCHMARKS.md, "Decode speed", dec32): a quick
look at budgets, not the change's measure.
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

import decode_quiet as dq  # noqa: E402

from client_gl.stream import decode_jit  # noqa: E402
from splatstream.format import container  # noqa: E402
from splatstream.format.decode import decode_payloads  # noqa: E402


def _planes(case: dq.Case) -> list[bytes]:
    """Every texel, range and palette byte of a `verified` pass."""
    got = []
    for group, items in case.verified.items():
        for planes in decode_payloads(items, group, ["bench"] * len(items), case.codebook, palettes=case.palettes):
            for name in sorted(planes):
                p = planes[name]
                got += [layer.tobytes() for layer in p.layers]
                got += [b"" if a is None else a.tobytes() for a in (p.ranges, p.palette)]
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="guitar,winter_fountain,statue_massa")
    ap.add_argument("--presets", default=",".join(dq.PRESETS))
    ap.add_argument("--budgets", default=f"{container.RUN_RAW_BYTES},0",
                    help="RUN_RAW_BYTES values (0: one run a group); ratios are to the first")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--json", help="also write the JSON here (default $OUT/decode_runs_ab.json when OUT is set)")
    args = ap.parse_args()
    budgets = [int(b) for b in args.budgets.split(",")]
    decode_jit.install()
    saved = container.RUN_RAW_BYTES
    results = {"bench": "bench/decode_runs_ab.py", "argv": sys.argv[1:], "load_start": os.getloadavg(),
               "budgets": budgets, "cases": []}
    for scene in args.scenes.split(","):
        for preset in args.presets.split(","):
            _, _, store, _ = dq.encode(scene, preset)
            if isinstance(store, str):
                print(f"{scene} {preset}: skipped ({store})", file=sys.stderr)
                continue
            case = dq.Case(store)
            reference = None
            for budget in budgets:
                container.RUN_RAW_BYTES = budget or 1 << 62
                got = _planes(case)
                if reference is not None and got != reference:
                    raise SystemExit(f"{scene} {preset}: a budget of {budget} decodes to other planes")
                reference = got
            times: dict[int, list[float]] = {b: [] for b in budgets}
            for r in range(args.rounds):
                for budget in budgets if r % 2 == 0 else budgets[::-1]:
                    container.RUN_RAW_BYTES = budget or 1 << 62
                    times[budget].append(min(case.run("verified"), case.run("verified")))
            container.RUN_RAW_BYTES = saved
            first = times[budgets[0]]
            row = {"scene": scene, "preset": preset, "splats": case.splats, "payloads": case.payloads,
                   "raw_mb": round(case.raw_bytes / 1e6, 3),
                   "m_splats_s": {b: round(case.splats / min(t) / 1e6, 2) for b, t in times.items()},
                   "median_ms": {b: round(statistics.median(t) * 1e3, 3) for b, t in times.items()},
                   "ratio_to_first": {b: round(statistics.median(x / y for x, y in zip(t, first, strict=True)), 3)
                                      for b, t in times.items()}}
            results["cases"].append(row)
            print(f"{scene} {preset}: M splats/s {row['m_splats_s']}, median ms {row['median_ms']}, "
                  f"ratio {row['ratio_to_first']}", file=sys.stderr, flush=True)
    results["load_end"] = os.getloadavg()
    results["date_utc"] = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())
    text = json.dumps(results, indent=1)
    print(text)
    path = args.json or (os.path.join(os.environ["OUT"], "decode_runs_ab.json") if os.environ.get("OUT") else None)
    if path:
        with open(path, "w") as f:
            f.write(text)


if __name__ == "__main__":
    main()
