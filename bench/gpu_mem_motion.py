"""The engine flown across a scene at several shares of the pool for the cut (StreamOptions.target_fraction): per
camera step, whether it converged within 200 frames, the drawn splats, the evictions (BENCHMARKS.md, "GPU memory
budget filled"). The fly, fetcher and pool of tests/test_stream_engine.py's test_budget_holds_and_eviction_follows_
the_camera, with pools of 1/DIV of the full detail's slots.

    PYTHONPATH=. SCENE=guitar.compressed.ply LEAF=16384 DIVS=1.6,4,8 STEPS=12 TFS=0.8,0.85,0.9 \
        python bench/gpu_mem_motion.py
"""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
from conftest import real  # noqa: E402
from test_stream_engine import CountingPool, StepFetcher  # noqa: E402

from client_gl.stream.engine import StreamEngine, StreamOptions  # noqa: E402
from client_gl.stream.selection import SelectionOptions  # noqa: E402
from splatstream.camera import Camera  # noqa: E402
from splatstream.encode import EncodeOptions, encode_in_memory  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402


def main() -> None:
    name = os.environ.get("SCENE", "fruit_drops_sh3.ply")
    store = encode_in_memory(read_gaussians(real(name)),
                             EncodeOptions(preset="medium", max_leaf_splats=int(os.environ.get("LEAF", "256"))))
    m = read_manifest(store)
    leaf_chunks = sum(t.chunks for t in m.leaves)
    steps = int(os.environ.get("STEPS", "24"))
    lo, hi = np.array(m.bounds.min), np.array(m.bounds.max)
    for div in [float(x) for x in os.environ.get("DIVS", "1.5,3,6").split(",")]:
        for share in [float(x) for x in os.environ.get("TFS", "0.8,0.9,0.95").split(",")]:
            pool = CountingPool(int(leaf_chunks / div))
            engine = StreamEngine(StepFetcher(store, per_frame=4), pool,
                                  StreamOptions(SelectionOptions(max_sse=0.5), target_fraction=share))
            frames_to_converge, drawn, empty, stuck, cut_drawn = [], [], 0, 0, 0
            for step in range(steps):
                eye = lo + (hi - lo) * np.array([step / (steps - 1), 0.5, 0.5]) - np.array([0, (hi - lo)[1] * 0.8, 0])
                cam = Camera(tuple(eye), tuple(eye + np.array([0, 1.0, 0])), (0, 0, 1), 40.0, 320, 240, near=1e-3)
                frames = 0
                while frames < 200:
                    frames += 1
                    u = engine.update(cam)
                    engine.wait(float(os.environ.get("WAIT_S", "0.01")))
                    empty += bool(step and not u.draw)
                    if u.converged:
                        break
                if u.converged:
                    frames_to_converge.append(frames)
                stuck += not u.converged
                cut_drawn += sorted(u.draw) == sorted(int(m.arrays.ids[i]) for i in u.selection.cut)
                drawn.append(sum(m.tile(t).splats for t in u.draw))
            print(f"1/{div:g} of full detail ({pool.capacity_slots} slots), cut share {share}: "
                  f"frames to converge median {np.median(frames_to_converge or [0]):.0f} "
                  f"max {max(frames_to_converge or [0])}, not converged {stuck}/{steps}, "
                  f"cut drawn {cut_drawn}/{steps}, "
                  f"empty frames {empty}, drawn splats mean {np.mean(drawn):.0f}, evictions {engine.evictions}",
                  flush=True)
            engine.close()


if __name__ == "__main__":
    main()
