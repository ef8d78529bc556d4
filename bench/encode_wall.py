"""Whole CLI encodes as a user runs them: wall clock, CPU and memory of the process tree, one JSON line per run.

    python bench/encode_wall.py --label new --code DIR:MODULE [--cores 0,1] --json OUT.json -- SCENE --preset medium

Runs `python -m MODULE encode SCENE TMP_OUT -q ARGS...` from DIR (DIR first on the path, as encode_bound31.py runs a
checkout), pinned to `--cores` (os.sched_setaffinity in the child before exec: taskset's effect; the encoder sees
the cores it may use, not the host's). Records wall s, CPU s (user + sys of the encode and every child it reaped:
wait4's rusage), ru_maxrss MB (the largest single process), and the peak over time of the tree's summed PSS MB
(/proc/PID/smaps_rollup every 50 ms: pages shared by a forked child and its parent counted once, split between
them) and of its summed RSS (shared pages counted in each). The output directory's sha256 digest (every file, by
relative path) shows the bytes are the same across checkouts. Appends the row to --json (a list).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time


def _children(pid: int) -> list[int]:
    out = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                out += [int(x) for x in f.read().split()]
    except OSError:
        pass
    return out


def _tree(pid: int) -> list[int]:
    seen, todo = [], [pid]
    while todo:
        p = todo.pop()
        seen.append(p)
        todo += _children(p)
    return seen


def _rollup(pid: int) -> tuple[int, int]:
    """(PSS, RSS) in kB of one process, (0, 0) once it is gone."""
    pss = rss = 0
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    pss = int(line.split()[1])
                elif line.startswith("Rss:"):
                    rss = int(line.split()[1])
    except OSError:
        pass
    return pss, rss


def digest(directory: str) -> str:
    h = hashlib.sha256()
    for root, _, files in sorted(os.walk(directory)):
        for name in sorted(files):
            path = os.path.join(root, name)
            h.update(os.path.relpath(path, directory).encode() + b"\0")
            with open(path, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
    return h.hexdigest()[:16]


def run(code_dir: str, module: str, scene: str, args: list[str], cores: set[int] | None) -> dict:
    out_root = tempfile.mkdtemp(prefix="encode_wall_")
    out = os.path.join(out_root, "scene")
    argv = [sys.executable, "-m", module, "encode", os.path.abspath(scene), out, "-q", *args]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([code_dir] + [p for p in os.environ.get("PYTHONPATH", "")
                                                                     .split(os.pathsep) if p])}
    peak = {"pss": 0, "rss": 0}
    stop = threading.Event()
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=code_dir, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=(lambda: os.sched_setaffinity(0, cores)) if cores else None)

    def sample() -> None:
        while not stop.is_set():
            pss = rss = 0
            for p in _tree(proc.pid):
                a, b = _rollup(p)
                pss, rss = pss + a, rss + b
            peak["pss"], peak["rss"] = max(peak["pss"], pss), max(peak["rss"], rss)
            stop.wait(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    stop.set()
    sampler.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    row = {"rc": proc.returncode, "wall_s": round(wall, 3), "cpu_s": round(usage.ru_utime + usage.ru_stime, 3),
           "user_s": round(usage.ru_utime, 3), "sys_s": round(usage.ru_stime, 3),
           "maxrss_mb": round(usage.ru_maxrss / 1024, 1), "tree_pss_peak_mb": round(peak["pss"] / 1024, 1),
           "tree_rss_peak_mb": round(peak["rss"] / 1024, 1), "digest": digest(out) if proc.returncode == 0 else None,
           "stderr_tail": err[-600:] if proc.returncode else ""}
    shutil.rmtree(out_root, ignore_errors=True)
    return row


def cpu_list(text: str) -> set[int]:
    """A CPU list as taskset takes it: "0,1", "0-7", "0-3,8-11"."""
    cores: set[int] = set()
    for part in text.split(","):
        first, _, last = part.partition("-")
        cores.update(range(int(first), int(last or first) + 1))
    return cores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--code", required=True, help="DIR:MODULE, the checkout and its CLI module")
    ap.add_argument("--cores", default=None, help="CPU list, e.g. 0,1 or 0-7 (default: as this process)")
    ap.add_argument("--json", required=True)
    ap.add_argument("--tag", default="", help="free text kept in the row (the round, the scene's name)")
    ap.add_argument("scene")
    ap.add_argument("args", nargs=argparse.REMAINDER, help="encode arguments after the scene")
    a = ap.parse_args()
    code_dir, module = a.code.rsplit(":", 1)
    cores = cpu_list(a.cores) if a.cores else None
    row = {"label": a.label, "tag": a.tag, "scene": os.path.basename(a.scene), "args": " ".join(a.args),
           "cores": a.cores or "all", "load": round(os.getloadavg()[0], 2),
           **run(os.path.abspath(code_dir), module, a.scene, [x for x in a.args if x != "--"], cores)}
    rows = []
    if os.path.exists(a.json):
        with open(a.json) as f:
            rows = json.load(f)
    rows.append(row)
    with open(a.json, "w") as f:
        json.dump(rows, f, indent=1)
    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
