"""The compiled selection's view and cut alone, replayed: bench_pages.py's --engine path (the synthetic city, its
street-level camera path, pages and payloads arriving a few a frame) is flown once while every selection's inputs
are kept (the tree held, the camera, the options, the last frame's refined and cut tiles); then each selection is
run again ROUNDS times, in path order, timing `PartialView` (the view's numbers) and `select_near_compiled` (the
cut): what bench_flythrough.py counts as `select_ms`. Thread CPU, the least of the rounds per selection, then the
median, p99 and max over the path: on a shared VM the engine path's per-frame figures move 20-60 % run to run, the
least of a few replays of the same call much less. The children's index is brought up to each tree before its
call, untimed (an adoption's share of it is in the engine path's figures). A digest of every selection (cut,
priorities, refined tiles, splats, cost, budget flag) says whether two versions of the code select the same.

    PYTHONPATH=. python bench/bench_selection_replay.py [--splats 250e6] [--frames 300] [--rounds 5]
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_pages as bp  # noqa: E402 (bench/ is on the path: scripts run from it)

from client_gl.stream import engine as engine_module  # noqa: E402
from client_gl.stream import selection_jit  # noqa: E402
from client_gl.stream.engine import COMPILED_SELECTION, StreamOptions  # noqa: E402
from client_gl.stream.selection import PartialView, SelectionOptions, ViewBuffers  # noqa: E402


def captured_selections(splats: int, frames: int, per_frame: int, max_splats: int, k: int) -> list[dict]:
    """Every compiled selection of the engine path: its view's and its cut's arguments."""
    whole = bp.synthetic_tree(splats, bp.template(0))
    paged = bp.split_pages(whole, k)
    files = {ref.file: raw for ref, raw in paged.pages}
    engine = bp._NoDecodeEngine(bp._PathFetcher(paged.root, files, per_frame), bp._Slots(),
                                StreamOptions(SelectionOptions(max_splats=max_splats), upload_bytes_per_frame=1 << 40))
    if COMPILED_SELECTION.wait() is None:
        raise SystemExit(f"the compiled selection is not available: {COMPILED_SELECTION.error!r}")
    engine.whole = whole
    side = whole.bounds.max[0]
    calls: list[dict] = []
    select_fn, view_cls = COMPILED_SELECTION._fn, engine_module.PartialView

    def view_kept(a, cam, opts, reduction, buffers=None):
        calls.append({"a": a, "cam": cam, "opts": opts, "reduction": reduction})
        return view_cls(a, cam, opts, reduction, buffers)

    def select_kept(a, view, cost, root, sel_opts, refined, near_parents=()):
        # the engine's near parents: its last refined and cut tiles, a tuple of two arrays (kept as it gives them)
        kept = tuple(map(np.array, near_parents)) if isinstance(near_parents, tuple) else np.array(near_parents)
        calls[-1].update(cost=cost.copy(), root=root, sel_opts=sel_opts, refined=np.array(refined),
                         near_parents=kept)
        return select_fn(a, view, cost, root, sel_opts, refined, near_parents=near_parents)
    engine_module.PartialView, COMPILED_SELECTION._fn = view_kept, select_kept
    try:
        for f in range(frames):  # bench_pages.engine_path's camera path
            cam = bp.street_camera(f, frames, side)
            for fut in list(engine._pages_arrived.values()):
                fut.result()
            engine.update(cam)
    finally:
        engine_module.PartialView, COMPILED_SELECTION._fn = view_cls, select_fn
        engine.close()
    return [c for c in calls if "cost" in c]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", default="250e6")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--per-frame", type=int, default=8)
    ap.add_argument("--max-splats", type=int, default=3_000_000)
    args = ap.parse_args()
    for n in [int(float(s)) for s in args.splats.split(",")]:
        calls = captured_selections(n, args.frames, args.per_frame, args.max_splats, bp.EncodeOptions.page_levels)
        buffers = ViewBuffers()  # one set, as the engine keeps
        view_ms = np.full((args.rounds, len(calls)), np.inf)
        cut_ms = np.full((args.rounds, len(calls)), np.inf)
        digest = hashlib.sha256()
        for r in range(args.rounds):
            for k, c in enumerate(calls):
                selection_jit._children(c["a"])
                t0 = time.thread_time()
                view = PartialView(c["a"], c["cam"], c["opts"], c["reduction"], buffers)
                t1 = time.thread_time()
                sel = selection_jit.select_near_compiled(c["a"], view, c["cost"], c["root"], c["sel_opts"],
                                                         c["refined"], near_parents=c["near_parents"])
                t2 = time.thread_time()
                view_ms[r, k], cut_ms[r, k] = (t1 - t0) * 1e3, (t2 - t1) * 1e3
                if r == 0:
                    digest.update(sel.cut_at.tobytes() + sel.priority_at.tobytes() +
                                  np.sort(sel.refined_at).tobytes() +
                                  repr((sel.splats, sel.cost, sel.budget_limited)).encode())
        v, c = view_ms.min(axis=0), cut_ms.min(axis=0)

        def fig(x: np.ndarray) -> str:
            return f"{np.median(x):.3f} / {np.percentile(x, 99):.3f} / {x.max():.3f}"
        print(f"{n / 1e6:.0f}M: {len(calls)} selections replayed, the least of {args.rounds} rounds each, median / "
              f"p99 / max ms of thread CPU: view {fig(v)}; cut {fig(c)}; view + cut {fig(v + c)}; load average "
              f"{os.getloadavg()[0]:.2f}; selections sha256 {digest.hexdigest()[:16]}")


if __name__ == "__main__":
    main()
