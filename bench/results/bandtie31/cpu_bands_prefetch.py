#!/usr/bin/env python3
"""CPU a call of wanted_bands_at and prefetch (the frame path's) on fruit_drops' whole tree (medium,
max_leaf_splats 200), 8 views from 1.2 root radii looking at its centre, 300 rounds (bandtie31: their ties by tile
id). Run from the root of the tree to measure (this branch, or its base unpacked with git archive):

    PYTHONPATH=. python bench/results/bandtie31/cpu_bands_prefetch.py
"""
from __future__ import annotations

import random
import sys
import time
from pathlib import Path


def main() -> None:
    sys.path.insert(0, str(Path.cwd() / "tests"))
    import numpy as np
    from conftest import real

    from client_gl.stream.selection import SelectionOptions, prefetch, select, view_numbers, wanted_bands_at
    from splatstream.camera import Camera
    from splatstream.encode import EncodeOptions, encode_in_memory
    from splatstream.ply import read_gaussians_ply
    from splatstream.store import read_manifest

    m = read_manifest(encode_in_memory(read_gaussians_ply(real("fruit_drops_sh3.ply")),
                                       EncodeOptions(preset="medium", max_leaf_splats=200)))
    a = m.arrays
    cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
    root = m.tiles[m.index_of[m.root]]
    c, r = np.array(root.sphere_center), root.sphere_radius
    rnd = random.Random(3)
    opts = SelectionOptions(max_sse=1.0, prefetch_share=100.0)
    cases = []
    for _ in range(8):
        d = np.array([rnd.gauss(0, 1) for _ in range(3)])
        cam = Camera(tuple(c + d / np.linalg.norm(d) * r * 1.2), tuple(c), (0.0, 0.0, 1.0), 60.0, 640, 360,
                     near=0.001 * r)
        view = view_numbers(a, cam, opts)
        cases.append((view, select(a, view, cost, m.index_of[m.root], opts, reduction=m.lod.reduction)))
    calls = (("bands", lambda v, s: wanted_bands_at(a, v, s.cut_at, opts, 3)),
             ("prefetch", lambda v, s: prefetch(a, v, s, opts, cost)))
    for name, call in calls:
        t, n = time.process_time(), 0
        for _ in range(300):
            for view, sel in cases:
                call(view, sel)
                n += 1
        print(name, f"{(time.process_time() - t) / n * 1e6:.1f} us CPU a call", "cut",
              np.mean([len(s.cut) for _, s in cases]), "prefetched",
              np.mean([len(prefetch(a, v, s, opts, cost)) for v, s in cases]))


if __name__ == "__main__":
    main()
