"""Whole encodes of one scene by several checkouts and LOD merges, paired and interleaved: CPU, wall, peak RSS.

    python bench/encode_bound31.py SCENE --presets medium,high --rounds 2 \
        --code old=/work/wt_old:splatstream.cli --code new=.:cli --variant old=old: --variant grid=new:grid \
        --variant auto=new:auto --json out.json [--workers 2]

Issue 31's bound ("encode time and peak memory within 1.5x of today's for every preset") is a ratio of whole
encodes against the encoder at the time the issue was filed, so each variant runs the CLI of its own checkout (its
directory is both the working directory and PYTHONPATH: `python -m` puts the working directory first on the path)
with `--lod-merge` where the variant names one. Every round runs every preset's variants back to back, the order
of the variants turned by one each round, so that a slow minute of a shared machine falls on all of them.

CPU = user + sys of the process tree. For an in-process encode that is the child's own rusage from wait4 (exact: the
in-memory encode's payload children, encode/forked.py, are reaped by it, so their rusage is in its own). With
--workers (a Dask cluster of processes, some not reaped by the encode's own process) the tree is also sampled with
psutil every 0.1 s, per process its last CPU times, and the larger of the two sums is recorded (the sampled one
misses at most each process's last 0.1 s). Peak RSS: the largest process's (wait4's ru_maxrss) and the sampled sum
over the tree. A preset a checkout does not have is run as that checkout's `--baseline-preset` (default medium) and
marked so.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import psutil


def _presets_of(code_dir: str) -> set[str]:
    listing = "from splatstream.format.presets import PRESETS; print(' '.join(PRESETS))"
    out = subprocess.run([sys.executable, "-c", listing], cwd=code_dir, env={**os.environ, "PYTHONPATH": code_dir},
                         capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def run_encode(argv: list[str], cwd: str, sample: bool) -> dict:
    """One encode: CPU s (user + sys), wall s, peak RSS MB of the largest process and of the tree's sum."""
    env = {**os.environ, "PYTHONPATH": cwd}
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    last_cpu: dict[int, float] = {}
    tree_rss_peak = 0
    root = psutil.Process(proc.pid)
    done = None
    while sample:
        # wait4 with WNOHANG, not Popen.poll: poll would reap the child and lose its rusage
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            done = (status, usage)
            break
        try:
            procs = [root] + root.children(recursive=True)
        except psutil.Error:
            break
        rss = 0
        for p in procs:
            try:
                c = p.cpu_times()
                last_cpu[p.pid] = c.user + c.system
                rss += p.memory_info().rss
            except psutil.Error:
                pass
        tree_rss_peak = max(tree_rss_peak, rss)
        time.sleep(0.1)
    status, usage = done if done else os.wait4(proc.pid, 0)[1:]
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    rc = os.waitstatus_to_exitcode(status)
    cpu = usage.ru_utime + usage.ru_stime
    return {"rc": rc, "cpu_s": round(max(cpu, sum(last_cpu.values())), 3), "cpu_wait4_s": round(cpu, 3),
            "cpu_sampled_s": round(sum(last_cpu.values()), 3), "wall_s": round(wall, 3),
            "rss_mb": round(usage.ru_maxrss / 1024, 1), "tree_rss_mb": round(tree_rss_peak / 2**20, 1),
            "stderr_tail": err[-400:] if rc else ""}


def print_table(rows: list[dict], base: str) -> None:
    """Per preset and variant: CPU s and peak RSS MB per round; the ratios to `base` of the same round (paired)."""
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    others = [v for v in variants if v != base]
    by = {(r["preset"], r["variant"], r["round"]): r for r in rows if r["rc"] == 0}
    head = ["preset"] + [f"{v}: CPU s, RSS MB" for v in variants]
    head += [f"{v} / {base}: CPU, RSS" for v in others]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    rounds = sorted({r["round"] for r in rows})
    for preset in dict.fromkeys(r["preset"] for r in rows):
        cells = [preset]
        ran = {r["ran_preset"] for r in rows if r["preset"] == preset and r["variant"] == base}
        if ran != {preset}:
            cells[0] += f" ({base}: {', '.join(sorted(ran))})"
        for v in variants:
            got = [by[(preset, v, k)] for k in rounds if (preset, v, k) in by]
            cells.append(" / ".join(f"{r['cpu_s']:.2f}" for r in got) + " s, "
                         + " / ".join(f"{r['rss_mb']:.0f}" for r in got))
        for v in others:
            cpu = [by[(preset, v, k)]["cpu_s"] / by[(preset, base, k)]["cpu_s"] for k in rounds
                   if (preset, v, k) in by and (preset, base, k) in by]
            rss = [by[(preset, v, k)]["rss_mb"] / by[(preset, base, k)]["rss_mb"] for k in rounds
                   if (preset, v, k) in by and (preset, base, k) in by]
            cells.append(" / ".join(f"{x:.2f}x" for x in cpu) + ", " + " / ".join(f"{x:.2f}x" for x in rss))
        print("| " + " | ".join(cells) + " |")
    loads = [r["load"] for r in rows]
    print(f"\nload average (1 min) at the runs: {min(loads):.1f}-{max(loads):.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?")
    ap.add_argument("--table", metavar="JSON", help="print the markdown table of a run's JSON (against BASE) and exit")
    ap.add_argument("--base", default="old", help="the variant --table's ratios are against")
    ap.add_argument("--presets", default="medium")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--code", action="append", default=[], help="NAME=DIR:MODULE (the CLI's module in DIR)")
    ap.add_argument("--variant", action="append", default=[], help="LABEL=CODE:MERGE (MERGE empty: no flag)")
    ap.add_argument("--baseline-preset", default="medium")
    ap.add_argument("--workers", default=None)
    ap.add_argument("--extra", default="", help="more encode arguments, space separated")
    ap.add_argument("--json")
    args = ap.parse_args()
    if args.table:
        with open(args.table) as f:
            print_table(json.load(f), args.base)
        return
    codes = {}
    for spec in args.code:
        name, rest = spec.split("=", 1)
        directory, module = rest.rsplit(":", 1)
        directory = os.path.abspath(directory)
        codes[name] = (directory, module, _presets_of(directory))
    variants = []
    for spec in args.variant:
        label, rest = spec.split("=", 1)
        code, merge = rest.split(":", 1)
        variants.append((label, code, merge))
    presets = args.presets.split(",")
    out_root = tempfile.mkdtemp(prefix="bound31_")
    rows = []
    try:
        for rnd in range(args.rounds):
            for preset in presets:
                turn = (rnd + presets.index(preset)) % len(variants)
                for label, code, merge in variants[turn:] + variants[:turn]:
                    directory, module, known = codes[code]
                    ran = preset if preset in known else args.baseline_preset
                    out = os.path.join(out_root, label)
                    argv = [sys.executable, "-m", module, "encode", os.path.abspath(args.scene), out, "-q",
                            "--preset", ran]
                    if merge:
                        argv += ["--lod-merge", merge]
                    if args.workers:
                        argv += ["--workers", args.workers]
                    argv += args.extra.split()
                    r = run_encode(argv, directory, sample=args.workers is not None)
                    r.update(round=rnd, preset=preset, ran_preset=ran, variant=label,
                             load=round(os.getloadavg()[0], 2))
                    rows.append(r)
                    print(json.dumps(r), flush=True)
                    shutil.rmtree(out, ignore_errors=True)
                    with open(args.json, "w") as f:
                        json.dump(rows, f, indent=1)
    finally:
        shutil.rmtree(out_root, ignore_errors=True)


if __name__ == "__main__":
    main()
