"""The frame loop's releases of the interpreter lock, counted, not sampled: bench_pages' engine path (a 250M-splat
paged tree by default) with every release the frame loop's thread makes inside the view (PartialView), the cut (the
compiled selection), the engine's `wanted` (view and cut included), the draw set and the whole update counted, and
with --lines, the line and C function that made each release in `wanted` and the draw set.

A release (PyEval_SaveThread: numpy's NPY_BEGIN_THREADS, a BLAS call, numba's nogil, ctypes' CDLL) is where a
decode or fetch thread can take the lock and keep it for up to the switch interval; whether it does is a race, so
the frame loop's waits (bench_pages' "waits") are a noisy sample of these. bench/gil_releases.c is compiled with cc
and preloaded (LD_PRELOAD: the interpreter must be linked against libpython, as this venv's is) to count them.

    PYTHONPATH=. python bench/bench_gil_releases.py [--splats 250e6] [--frames 100] [--lines]
            [--busy-threads 2 --busy-pattern 0.15,0.3]
"""
from __future__ import annotations

import argparse
import collections
import ctypes
import os
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SHIM = "libgilcount.so"


def _preloaded() -> str | None:
    return next((p for p in os.environ.get("LD_PRELOAD", "").split() if p.endswith(SHIM)), None)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--splats", default="250e6")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--lines", action="store_true", help="where each release is made (sys.settrace: slow)")
    ap.add_argument("--update-lines", action="store_true",
                    help="with --lines: where each release of the whole update is made, not only `wanted`'s")
    ap.add_argument("--busy-threads", type=int, default=0)
    ap.add_argument("--busy-pattern", default=None, metavar="HOLD,REST")
    ap.add_argument("--max-tree-tiles", type=int, default=None,
                    help="the engine's bound on the tiles held (bench_pages' option): pages dropped on the path")
    args = ap.parse_args()
    shim = _preloaded()
    if shim is None:  # build the shim and run again with it preloaded
        out = os.path.join(tempfile.mkdtemp(), SHIM)
        subprocess.run(["cc", "-O2", "-shared", "-fPIC", "-o", out, os.path.join(HERE, "gil_releases.c"), "-ldl"],
                       check=True)
        os.execve(sys.executable, [sys.executable, *sys.argv], {**os.environ, "LD_PRELOAD": out})
    lib = ctypes.PyDLL(shim)  # PyDLL: its calls keep the lock (a CDLL's would be counted)
    lib.gilcount_get.restype = ctypes.c_long

    sys.path.insert(0, HERE)
    import bench_pages

    from client_gl.stream import engine as engine_module
    from client_gl.stream.engine import COMPILED_SELECTION

    per_part: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    where: collections.Counter = collections.Counter()
    state: dict = {"loc": None, "n": 0}

    def flush(loc) -> None:  # the releases since the last event go to the line (and C call) that ran then
        n = lib.gilcount_get()
        if n != state["n"]:
            where[state["loc"]] += n - state["n"]
            state["n"] = n
        state["loc"] = loc

    numpy_dir = os.path.dirname(os.path.dirname(np.__file__))

    def tracer(frame, event, arg):
        if event == "line":
            name = ""
            while frame.f_back is not None and frame.f_code.co_filename.startswith(numpy_dir):
                name = f"{frame.f_code.co_name}/{name}"
                frame = frame.f_back
            flush((os.path.basename(frame.f_code.co_filename), frame.f_lineno, name))
        return tracer

    def profiler(frame, event, arg):
        name = getattr(arg, "__qualname__", str(arg)) if event == "c_call" else ""
        if event in ("c_call", "c_return", "c_exception"):
            # numpy's Python wrappers (np.concatenate's dispatcher, fromnumeric's) named by the line calling them
            while frame.f_back is not None and frame.f_code.co_filename.startswith(numpy_dir):
                name = f"{frame.f_code.co_name}/{name}"
                frame = frame.f_back
            flush((os.path.basename(frame.f_code.co_filename), frame.f_lineno, name))

    def counted(label, fn, lines=True):
        def wrapper(*a, **kw):
            n0 = lib.gilcount_get()
            tracing = args.lines and lines and sys.gettrace() is None  # not inside a traced part already
            if tracing:
                state["n"], state["loc"] = n0, (label, 0, "entry")
                sys.settrace(tracer)
                sys.setprofile(profiler)
            lib.gilcount_arm()
            try:
                return fn(*a, **kw)
            finally:
                lib.gilcount_disarm()
                if tracing:
                    sys.settrace(None)
                    sys.setprofile(None)
                    flush(None)
                per_part[label] += lib.gilcount_get() - n0
                calls[label] += 1
        return wrapper

    if COMPILED_SELECTION.wait() is None:
        raise SystemExit(f"the compiled selection is not available: {COMPILED_SELECTION.error!r}")
    # the whole update (its lines with --update-lines only: then `wanted`'s lines are counted in the update's list)
    # and the engine's `wanted` (view, cut, pages wanted, bands, keys) counted too
    engine_module.StreamEngine.update = counted("update", engine_module.StreamEngine.update, args.update_lines)
    engine_module.StreamEngine.wanted = counted("wanted", engine_module.StreamEngine.wanted)
    engine_module.PartialView = counted("view", engine_module.PartialView)
    COMPILED_SELECTION._fn = counted("cut", COMPILED_SELECTION._fn)
    COMPILED_SELECTION._draw = counted("draw set", COMPILED_SELECTION._draw)
    pattern = tuple(float(x) for x in args.busy_pattern.split(",")) if args.busy_pattern else None
    for n in [int(float(s)) for s in args.splats.split(",")]:
        per_part.clear(), calls.clear(), where.clear()
        bench_pages.engine_path(bench_pages.synthetic_tree(n, bench_pages.template(0)),
                                bench_pages.EncodeOptions.page_levels, args.frames, 3_000_000, 8, False,
                                busy_threads=args.busy_threads, busy_pattern=pattern,
                                max_tree_tiles=args.max_tree_tiles)
        for label in ("view", "cut", "wanted", "draw set", "update"):
            print(f"releases of the lock, {label}: {per_part[label]} in {calls[label]} calls "
                  f"({per_part[label] / max(calls[label], 1):.2f} a call)")
        for (file, line, c), k in where.most_common(40):
            print(f"  {k:6d}  {file}:{line} {c}")


if __name__ == "__main__":
    main()
