"""What `encode --target-size` / `--target-psnr` cost when they measure the presets with the LOD tree, against
without it (issue 32: the measure now encodes every preset as the encode writes it, LOD levels included).

    python bench/target_lod_cost.py SCENE.ply [--views 8] [--rounds 3] [--json OUT]

Runs `splatstream.evaluate.evaluate` on the scene, every preset, the reference renderer (what a machine without a GL
context uses), --views orbit views at 512x512, with lod=False (the measure before) and lod=True (after),
interleaved A/B over --rounds rounds. Times are CPU seconds of this process (time.process_time: other jobs on a
shared machine move wall time by 2-3x); median and minimum over the rounds. Also the per-preset bytes per splat both
ways and the preset each of a few --target-size values picks each way, with the bytes on disk it then writes.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from splatstream.errors import UsageError  # noqa: E402
from splatstream.evaluate import EvalOptions, evaluate, preset_for_target  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json")
    a = ap.parse_args()
    times: dict[bool, list[float]] = {False: [], True: []}
    rows: dict[bool, list[dict]] = {}
    for r in range(a.rounds):
        for lod in ((False, True) if r % 2 == 0 else (True, False)):
            t = time.process_time()
            rep = evaluate(a.scene, EvalOptions(views=a.views, lod=lod))
            times[lod].append(time.process_time() - t)
            rows[lod] = [row for row in rep["rows"] if row["kind"] == "preset"]
            print(f"round {r} lod={lod}: {times[lod][-1]:.1f} CPU s", file=sys.stderr)
    out = {"scene": os.path.basename(a.scene), "views": a.views, "rounds": a.rounds,
           "load_average": os.getloadavg(),
           "cpu_s": {("lod" if k else "no_lod"): {"median": statistics.median(v), "min": min(v), "all": v}
                     for k, v in times.items()},
           "presets": {row["label"]: {"no_lod": b["disk_bytes_per_splat"], "lod": row["disk_bytes_per_splat"],
                                      "leaf": row["leaf_bytes_on_disk"] / row["splats"]}
                       for row, b in zip(rows[True], rows[False], strict=True)}}
    picks = {}
    lod_size = {row["label"]: row["disk_bytes_per_splat"] for row in rows[True]}
    for target in sorted({round(v["no_lod"], 1) for v in out["presets"].values()}):
        pick = {}
        for lod in (False, True):
            try:
                pick["lod" if lod else "no_lod"] = preset_for_target(rows[lod], target_bytes=target)["label"]
            except UsageError:
                pick["lod" if lod else "no_lod"] = None
        pick["written_b_per_splat_if_no_lod_pick"] = lod_size.get(pick["no_lod"])
        picks[target] = pick
    out["picks"] = picks
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
