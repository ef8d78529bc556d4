"""A/B of RenderOptions.warm_compile through the real session (bench_first_frame.py --frames-after N), alternating
runs with and without the warmer, each with a fresh Mesa shader-cache directory (cold), then again on that
directory (warm); or with the cache off. The frame loop's time in compile calls after the first frame is what the
warmer should take away (issue 38; BENCHMARKS.md, "Deferred compiles warmed off the frame loop").

    python bench/warm_compile_ab.py --scene S --rounds 5 [--cache off] -- --as-hardware --size 640x360 --gpu-mem-mb 64

On the GPU machine (NVIDIA) use --cache nvidia: a fresh __GL_SHADER_DISK_CACHE_PATH per cold run.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
KEYS = ("first_frame_s", "compile_ms", "compile_after_ms", "compile_after_max_ms", "frames_to_compute")


def run(scene: str, extra: list[str], env: dict, warm: bool, frames_after: int, out_json: str) -> dict:
    cmd = [sys.executable, os.path.join(HERE, "bench_first_frame.py"), "--scene", scene, "--frames-after",
           str(frames_after), "--json", out_json, *extra] + ([] if warm else ["--no-warm-compile"])
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    with open(out_json) as f:
        d = json.load(f)
    d["load"] = os.getloadavg()[0]
    return d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--frames-after", type=int, default=30)
    ap.add_argument("--cache", choices=("mesa", "off", "nvidia"), default="mesa")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("extra", nargs="*", help="bench_first_frame.py arguments (after --)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for warm in ((True, False) if r % 2 == 0 else (False, True)):
                cache = tempfile.mkdtemp(dir=tmp)
                env = dict(os.environ)
                if args.cache == "mesa":
                    env["MESA_SHADER_CACHE_DIR"] = cache
                    env.pop("MESA_SHADER_CACHE_DISABLE", None)
                elif args.cache == "nvidia":
                    env["__GL_SHADER_DISK_CACHE_PATH"] = cache
                    env["__GL_SHADER_DISK_CACHE_SKIP_CLEANUP"] = "1"
                else:
                    env["MESA_SHADER_CACHE_DISABLE"] = "true"
                    env["__GL_SHADER_DISK_CACHE"] = "0"
                passes = ("cold", "warm") if args.cache != "off" else ("cold",)
                for p in passes:
                    d = run(args.scene, args.extra, env, warm, args.frames_after, os.path.join(tmp, "ff.json"))
                    row = {"round": r, "warmer": warm, "cache": p, "load": d["load"],
                           "each_after_ms": d["compile_after_each_ms"], "warmer_ms": d["warmer_ms"],
                           "loop_compile_ms": d["loop_compile_ms"], "missed": d["warm_compile_missed"],
                           **{k: d[k] for k in KEYS}}
                    rows.append(row)
                    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()
                                      if k not in ("each_after_ms", "warmer_ms", "loop_compile_ms")}), flush=True)
    summary = {}
    for warm in (True, False):
        for p in ("cold", "warm"):
            sel = [row for row in rows if row["warmer"] == warm and row["cache"] == p]
            if not sel:
                continue
            summary[f"{'warmer' if warm else 'no warmer'}, {p}"] = {
                k: (round(statistics.median(row[k] for row in sel), 3), round(min(row[k] for row in sel), 3))
                for k in KEYS if all(row[k] is not None for row in sel)}
    print(json.dumps(summary, indent=1))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump({"rows": rows, "summary": summary, "median_min": True}, f, indent=1)


if __name__ == "__main__":
    main()
