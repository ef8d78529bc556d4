"""The first frames' selection by part (issue 38, branch frame0): bench_pages' synthetic tree and street path, a
StreamEngine with the compiled selection, and each frame's thread CPU (ms) of the selection (PartialView +
select_near_compiled, as the GPU machine's `steps_ms` count it) and of its parts: the view buffers
(ViewBuffers.get), the children's index (selection_jit._ChildIndex.of) and the kernels. REPS engines one after the
other in one process (the first with the kernels' first calls), the engine's construction CPU, the digests of every
frame's cut and of the fetcher's requests.

    PYTHONPATH=. python bench/frame0_parts.py [SPLATS 250e6] [FRAMES 60] [REPS 3]
"""
from __future__ import annotations

import gc
import hashlib
import json
import sys
import time

import numpy as np

from bench import bench_pages as bp
from client_gl.stream import engine as engine_module
from client_gl.stream import selection, selection_jit
from client_gl.stream.engine import COMPILED_SELECTION, StreamOptions
from client_gl.stream.selection import SelectionOptions

acc: dict[str, float] = {}


def timed(owner, name: str, label: str) -> None:
    """owner.name replaced by a wrapper adding its thread CPU (ms) to acc[label]."""
    fn = getattr(owner, name)

    def wrapper(*args, **kw):
        c0 = time.thread_time()
        try:
            return fn(*args, **kw)
        finally:
            acc[label] = acc.get(label, 0.0) + (time.thread_time() - c0) * 1e3
    setattr(owner, name, wrapper)


def main() -> None:
    splats, frames, reps = (float(sys.argv[1]) if len(sys.argv) > 1 else 250e6,
                            int(sys.argv[2]) if len(sys.argv) > 2 else 60, int(sys.argv[3]) if len(sys.argv) > 3 else 3)
    if COMPILED_SELECTION.wait() is None:
        raise SystemExit(f"the compiled selection is not available: {COMPILED_SELECTION.error!r}")
    timed(selection.ViewBuffers, "get", "buffers")
    timed(selection_jit._index, "of", "index")
    for kernel in ("_seed", "_refine", "_cut"):
        timed(selection_jit, kernel, "kernels")
    whole = bp.synthetic_tree(int(splats), bp.template(0))
    paged = bp.split_pages(whole, bp.EncodeOptions.page_levels)
    files = {ref.file: raw for ref, raw in paged.pages}
    timed(engine_module, "PartialView", "view")
    timed(COMPILED_SELECTION, "_fn", "cut")
    gc.collect()
    gc.freeze()
    side = whole.bounds.max[0]
    for rep in range(reps):
        fetcher = bp._PathFetcher(paged.root, files, 8)
        c0 = time.thread_time()
        engine = bp._NoDecodeEngine(fetcher, bp._Slots(), StreamOptions(SelectionOptions(max_splats=3_000_000),
                                                                        upload_bytes_per_frame=1 << 40))
        init_ms = (time.thread_time() - c0) * 1e3
        engine.whole = whole
        _ = whole.tile_by_id
        rows, cuts = [], hashlib.sha256()
        for f in range(frames):
            cam = bp.street_camera(f, frames, side)
            for fut in list(engine._pages_arrived.values()):
                fut.result()
            acc.clear()
            u = engine.update(cam)
            rows.append({"selection": round(acc.get("view", 0.0) + acc.get("cut", 0.0), 3), "tiles":
                         len(engine.manifest.tiles), **{k: round(v, 3) for k, v in acc.items()}})
            cuts.update(np.array([int(engine.ids[i]) for i in u.selection.cut], np.int64).tobytes() + b"|")
        engine.close()
        sel = np.array([r["selection"] for r in rows])
        print(f"rep {rep}: engine made in {init_ms:.2f} ms CPU; selection CPU p99 {np.percentile(sel, 99):.3f}, median "
              f"{np.median(sel):.3f}, max {sel.max():.3f} ms; cut digest {cuts.hexdigest()[:16]}, requests "
              f"{fetcher.requests_digest()}")
        for f, r in enumerate(rows[:6]):
            print(f"  frame {f}: {json.dumps(r)}")
        print("JSON", rep, json.dumps(sel.tolist()), json.dumps([r.get("buffers", 0) for r in rows[:6]]),
              json.dumps([r.get("index", 0) for r in rows[:6]]))
        print("INIT", rep, round(init_ms, 3))


if __name__ == "__main__":
    main()
