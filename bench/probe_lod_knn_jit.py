"""Probe (issue 31, branch lodfast2): the cost merge's k-NN graph (lod_groups.neighbour_keys) compiled with numba, as
a kernel a shell could hand the core (the core never imports numba: pyproject.toml's first contract), against
numpy's path: the same keys bit for bit, the CPU it saves, and what loading numba costs an encode process.

    PYTHONPATH=. python bench/probe_lod_knn_jit.py SCENE [--repeat R] [--aot]

Builds the LOD tree of SCENE as `encode --lod-merge auto` does (lod.build_tiles, merge="auto"), recording the
positions of every call of neighbour_keys (one per tree level), then per level: numpy's keys and the kernel's,
equal or not, and the least CPU seconds of each over R runs. Before anything else it measures, in this process,
`import numba` and the kernel's first call (compiled once, then loaded from numba's cache: cache=True; run the
probe twice to see the cached load) as CPU seconds and the growth of VmRSS / RssAnon / RssFile. With `--aot`, the
same kernel compiled ahead of time (numba.pycc, deprecated by numba but still shipped: a plain extension module
that needs neither numba nor LLVM at run time) into a temporary directory, then imported and run in a fresh
process, whose import time, memory and keys are printed the same way.

The kernel: per point its candidates at ranks +-1 .. +-w in each shifted Morton order, itself and repeats dropped,
squared distances summed as numpy sums them (dx dx + dy dy + dz dz, left to right; no fused multiply-add: numba
contracts nothing without fastmath), and the k smallest by (distance, id) kept: numpy's choice (the candidates
sorted by id, a partition and a tie count per row), without the sort. Result: BENCHMARKS.md, "The encode time of
`auto`: compiled grouping kernels".
"""
from __future__ import annotations

import argparse
import time

T0 = time.process_time()
import numba  # noqa: E402  (timed: the import is part of what a compiled kernel costs)

T_IMPORT = time.process_time() - T0
import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from splatstream import lod, lod_groups  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402

_JIT = dict(cache=True, nogil=True, boundscheck=False)


@njit(**_JIT)
def neighbour_keys(px, py, pz, orders, ranks, k, w):
    """Keys i * n + j (i < j) of every point's k nearest candidates, repeats allowed (an edge found from both
    ends comes twice), as lod_groups._neighbour_blocks(ordered=False) chooses them."""
    n = px.shape[0]
    shifts = orders.shape[0]
    m = 2 * w * shifts
    cand = np.empty(m, np.int64)
    best_d = np.empty(k, np.float64)
    best_j = np.empty(k, np.int64)
    out = np.empty(n * k, np.int64)
    cnt = 0
    for r in range(n):
        c = 0
        for s in range(shifts):
            rk = ranks[s, r]
            for t in range(1, w + 1):
                a = rk + t
                if a > n - 1:
                    a = n - 1
                cand[c] = orders[s, a]
                b = rk - t
                if b < 0:
                    b = 0
                cand[c + 1] = orders[s, b]
                c += 2
        got = 0
        xr, yr, zr = px[r], py[r], pz[r]
        for x in range(m):
            j = cand[x]
            if j == r:
                continue
            dx = px[j] - xr
            dy = py[j] - yr
            dz = pz[j] - zr
            d = dx * dx + dy * dy + dz * dz
            if not (d < np.inf):  # NaN or infinite: never a neighbour
                continue
            if got == k and (d > best_d[k - 1] or (d == best_d[k - 1] and j > best_j[k - 1])):
                continue
            seen = False  # a candidate met again (in another order, or twice at the ends of one)
            for y in range(got):
                if best_j[y] == j:
                    seen = True
                    break
            if seen:
                continue
            y = got - 1 if got < k else k - 2  # the last kept row moves down or falls off
            while y >= 0 and (best_d[y] > d or (best_d[y] == d and best_j[y] > j)):
                best_d[y + 1] = best_d[y]
                best_j[y + 1] = best_j[y]
                y -= 1
            best_d[y + 1] = d
            best_j[y + 1] = j
            if got < k:
                got += 1
        for x in range(got):
            j = best_j[x]
            out[cnt] = r * n + j if r < j else j * n + r
            cnt += 1
    return out[:cnt]


def keys_by_kernel(p: np.ndarray, k: int = 8, shifts: int = 3) -> np.ndarray:
    """neighbour_keys(p, k, shifts) with the kernel: the same orders (lod_groups._shifted_orders), then the kernel's
    keys sorted and made distinct as numpy's path does."""
    if len(p) < 2:
        return np.zeros(0, np.int64)
    orders, ranks, k, w = lod_groups._shifted_orders(p, k, shifts)
    every = neighbour_keys(*(np.ascontiguousarray(p[:, a], dtype=np.float64) for a in range(3)), orders, ranks, k, w)
    every.sort()
    return every[np.concatenate([[True], every[1:] != every[:-1]])]


def _status() -> dict:
    with open("/proc/self/status") as f:
        d = dict(line.split(":", 1) for line in f)
    return {key: int(d[key].split()[0]) / 1024 for key in ("VmRSS", "RssAnon", "RssFile")}


_AOT_RUN = """
import sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
from splatstream import lod_groups
from splatstream.io import read_gaussians
def _status():  # as the probe's (whose module imports numba: not here)
    with open("/proc/self/status") as f:
        d = dict(line.split(":", 1) for line in f)
    return {key: int(d[key].split()[0]) / 1024 for key in ("VmRSS", "RssAnon", "RssFile")}
before, t0 = _status(), time.process_time()
import lodknn_aot
took, after = time.process_time() - t0, _status()
print(f"aot: import {took:.3f} CPU s, " + ", ".join(f"{k} +{after[k] - before[k]:.0f} MB" for k in before))
g = read_gaussians(sys.argv[2])
p = g.positions.astype(np.float64)
p -= p.mean(axis=0)
t0 = time.process_time()
a = lod_groups.neighbour_keys(p, 8)
t_np, t0 = time.process_time() - t0, time.process_time()
orders, ranks, k, w = lod_groups._shifted_orders(p, 8, 3)
every = lodknn_aot.neighbour_keys(*(np.ascontiguousarray(p[:, i]) for i in range(3)), orders, ranks, k, w)
every.sort()
b = every[np.concatenate([[True], every[1:] != every[:-1]])]
print(f"aot: the scene's splats ({len(p):,}), keys equal: {np.array_equal(a, b)}; numpy {t_np:.3f} CPU s, "
      f"aot {time.process_time() - t0:.3f} CPU s")
"""


def _aot(scene: str) -> None:
    """Build the kernel ahead of time (numba.pycc) and measure it in a fresh process (_AOT_RUN)."""
    import subprocess  # only for --aot
    import sys
    import tempfile

    from numba.pycc import CC

    with tempfile.TemporaryDirectory() as out:
        cc = CC("lodknn_aot")
        cc.output_dir = out
        cc.export("neighbour_keys", "i8[:](f8[::1], f8[::1], f8[::1], i4[:, ::1], i8[:, ::1], i8, i8)")(
            neighbour_keys.py_func)
        t0 = time.process_time()
        cc.compile()
        print(f"aot: compiled in {time.process_time() - t0:.2f} CPU s (this process; the C compiler's not counted)")
        subprocess.run([sys.executable, "-c", _AOT_RUN, out, scene], check=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--aot", action="store_true", help="also the kernel compiled ahead of time (numba.pycc)")
    args = ap.parse_args()
    before = _status()
    t0 = time.process_time()
    keys_by_kernel(np.random.default_rng(0).normal(size=(64, 3)))
    first = time.process_time() - t0
    after = _status()
    print(f"import numba {T_IMPORT:.2f} CPU s; kernel's first call (compile or cached load) {first:.2f} CPU s; "
          + ", ".join(f"{key} +{after[key] - before[key]:.0f} MB" for key in before)
          + " over the import; the process now " + ", ".join(f"{key} {v:.0f} MB" for key, v in after.items()))
    if args.aot:
        _aot(args.scene)
    g = read_gaussians(args.scene)
    inputs = []
    original = lod_groups.neighbour_keys

    def record(p, *rest, **kw):
        inputs.append(p.copy())
        return original(p, *rest, **kw)

    lod_groups.neighbour_keys = record
    try:
        lod.build_tiles(g, merge="auto")
    finally:
        lod_groups.neighbour_keys = original
    total_np = total_jit = 0.0
    for level, p in enumerate(inputs):
        best_np = best_jit = float("inf")
        for _ in range(args.repeat):
            t0 = time.process_time()
            a = original(p, 8)
            best_np = min(best_np, time.process_time() - t0)
            t0 = time.process_time()
            b = keys_by_kernel(p, 8)
            best_jit = min(best_jit, time.process_time() - t0)
        total_np += best_np
        total_jit += best_jit
        print(f"level {level} (first merged = 0): {len(p):,} splats, {len(a):,} edges, keys equal: "
              f"{np.array_equal(a, b)}; numpy {best_np:.3f} CPU s, kernel {best_jit:.3f} CPU s")
    print(f"all levels: numpy {total_np:.2f} CPU s, kernel {total_jit:.2f} CPU s (numba {numba.__version__})")


if __name__ == "__main__":
    main()
