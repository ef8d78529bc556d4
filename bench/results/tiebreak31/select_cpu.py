#!/usr/bin/env python3
"""CPU time a call of the cut's functions (select_near_compiled, select_near) on fruit_drops' whole tree (medium,
max_leaf_splats 200), 8 views inside and outside the root's sphere, a 10x-root splat budget (issue 31, ties broken
by tile id: the cost of the tie-break). Run with the tree to measure first on PYTHONPATH:

    PYTHONPATH=TREE python bench/results/tiebreak31/select_cpu.py TREE
"""
from __future__ import annotations

import random
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> None:
    sys.path.insert(0, str(Path(argv[0]) / "tests"))
    import numpy as np
    from conftest import real

    from client_gl.stream.selection import PartialView, SelectionOptions, ViewBuffers, select_near
    from client_gl.stream.selection_jit import select_near_compiled
    from splatstream.camera import Camera
    from splatstream.encode import EncodeOptions, encode_in_memory
    from splatstream.ply import read_gaussians_ply
    from splatstream.store import read_manifest

    whole = read_manifest(encode_in_memory(read_gaussians_ply(real("fruit_drops_sh3.ply")),
                                           EncodeOptions(preset="medium", max_leaf_splats=200)))
    a, root = whole.arrays, whole.index_of[whole.root]
    cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
    top = whole.tiles[root]
    c, r = np.array(top.sphere_center), top.sphere_radius
    rnd = random.Random(3)
    cams = []
    for far in (0.05, 0.3, 0.5, 1.5, 3.0, 0.3, 0.5, 2.0):
        d = np.array([rnd.gauss(0, 1) for _ in range(3)])
        target = c + np.array([rnd.gauss(0, r) for _ in range(3)])
        cams.append(Camera(tuple(c + d / np.linalg.norm(d) * r * far), tuple(target), (0.0, 0.0, 1.0), 60.0, 320, 240,
                           near=0.001 * r))
    opts = SelectionOptions(max_sse=1.0, max_splats=10 * top.splats)
    buf = ViewBuffers()
    for fn, reps in ((select_near_compiled, 300), (select_near, 40)):
        for cam in cams:  # warm
            fn(a, PartialView(a, cam, opts, whole.lod.reduction, buf), cost, root, opts)
        t0 = time.process_time()
        for _ in range(reps):
            for cam in cams:
                fn(a, PartialView(a, cam, opts, whole.lod.reduction, buf), cost, root, opts)
        print(f"{fn.__name__}: {(time.process_time() - t0) / reps / len(cams) * 1e3:.4f} ms CPU a call")


if __name__ == "__main__":
    main(sys.argv[1:])
