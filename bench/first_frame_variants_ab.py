"""Paired A/B of bench_first_frame.py option sets (variants) through the real session: each round runs every
variant, in an order rotated by one each round, each run cold on a fresh shader-cache directory (Mesa's or NVIDIA's
disk cache) and then once more on that directory warm; the summary gives each variant's median and minimum and its
median difference from the first variant's run of the same round (issue 31: the first frame's prime and early
framebuffer, BENCHMARKS.md "The first frame's prime and framebuffer off the serial path").

    python bench/first_frame_variants_ab.py --scene S --rounds 4 --cache mesa \\
        --variant main="--atlas-prime compute --no-early-target" --variant new="--atlas-prime clear" \\
        -- --as-hardware --size 640x360 --gpu-mem-mb 64

On the GPU machine use --cache nvidia (a fresh __GL_SHADER_DISK_CACHE_PATH per cold run): bench/device/
first_frame_prime_ab.sh. Without --variant: main's behaviour, the new default and each switch alone.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
KEYS = ("first_frame_s", "manifest_s", "pool_s", "built_s", "compile_ms", "early_target_ms", "prime_ms",
        "first_clear_ms", "first_join_ms", "context_ms")
DEFAULT_VARIANTS = {
    "main": "--atlas-prime compute --no-early-target",  # main's behaviour before issue 31's ff31
    "both": "--atlas-prime clear",  # the early target (default on) and the clear prime
    "early": "--atlas-prime compute",  # the early target alone
    "clear": "--atlas-prime clear --no-early-target",  # the clear prime alone
}


def run(scene: str, args: list[str], env: dict, out_json: str) -> dict:
    cmd = [sys.executable, os.path.join(HERE, "bench_first_frame.py"), "--scene", scene, "--json", out_json, *args]
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    with open(out_json) as f:
        d = json.load(f)
    d["load"] = os.getloadavg()[0]
    return d


def cache_env(kind: str, directory: str) -> dict:
    env = dict(os.environ)
    if kind == "mesa":
        env["MESA_SHADER_CACHE_DIR"] = directory
        env.pop("MESA_SHADER_CACHE_DISABLE", None)
    elif kind == "nvidia":
        env["__GL_SHADER_DISK_CACHE_PATH"] = directory
        env["__GL_SHADER_DISK_CACHE_SKIP_CLEANUP"] = "1"
    else:
        env["MESA_SHADER_CACHE_DISABLE"] = "true"
        env["__GL_SHADER_DISK_CACHE"] = "0"
    return env


def summarize(rows: list[dict], names: list[str]) -> dict:
    """Per variant and pass: (median, min) of each key; and the median of its per-round difference from the first
    variant's run (paired: the same round, the same pass)."""
    summary = {}
    base = names[0]
    for name in names:
        for p in ("cold", "warm"):
            sel = [r for r in rows if r["variant"] == name and r["cache"] == p]
            if not sel:
                continue
            entry = {k: (round(statistics.median(r[k] for r in sel), 4), round(min(r[k] for r in sel), 4))
                     for k in KEYS if all(r.get(k) is not None for r in sel)}
            if name != base:
                diffs = []
                for r in sel:
                    other = [b for b in rows if b["variant"] == base and b["cache"] == p and b["round"] == r["round"]]
                    if other:
                        diffs.append(r["first_frame_s"] - other[0]["first_frame_s"])
                if diffs:
                    entry[f"first_frame_s minus {base}'s, paired: median, each"] = (
                        round(statistics.median(diffs), 4), [round(d, 4) for d in diffs])
            summary[f"{name}, {p}"] = entry
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--cache", choices=("mesa", "off", "nvidia"), default="mesa")
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME=bench_first_frame.py options (repeatable; the first is the one the others are paired "
                         "against; default: " + ", ".join(f"{k}={v!r}" for k, v in DEFAULT_VARIANTS.items()) + ")")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("extra", nargs="*", help="bench_first_frame.py options of every run (after --)")
    args = ap.parse_args()
    variants = dict(v.split("=", 1) for v in args.variant) if args.variant else dict(DEFAULT_VARIANTS)
    names = list(variants)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            shift = r % len(names)
            for name in names[shift:] + names[:shift]:
                env = cache_env(args.cache, tempfile.mkdtemp(dir=tmp))
                for p in (("cold", "warm") if args.cache != "off" else ("cold",)):
                    d = run(args.scene, shlex.split(variants[name]) + args.extra, env, os.path.join(tmp, "ff.json"))
                    row = {"round": r, "variant": name, "cache": p, "load": round(d["load"], 2),
                           "programs_compiled": d.get("programs_compiled"),
                           **{k: d.get(k) for k in KEYS}}
                    rows.append(row)
                    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}),
                          flush=True)
    summary = summarize(rows, names)
    print(json.dumps(summary, indent=1))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump({"variants": variants, "extra": args.extra, "cache": args.cache, "rows": rows,
                       "summary": summary, "median_min": True}, f, indent=1)


if __name__ == "__main__":
    main()
