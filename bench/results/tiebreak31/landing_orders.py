#!/usr/bin/env python3
"""Distinct converged cuts of one view over random orders of page arrival (issue 31, ties broken by tile id):
fruit_drops (medium, max_leaf_splats 200) split into pages of 2 levels, views with the eye inside the root's sphere
(refinement keys tied at -inf) or outside it (no ties), budgets in splats or bytes; each view streamed R times with
the engine's page loop without the network (tests/test_stream_page_budget.py's _land_in_random_order: a random part
of the pages on their way landing each frame). Counts, per side of the root's sphere, the views whose R cuts (tile
ids, as a set) are not all one, the distinct cuts in all, and the views whose cut differs from the whole tree's.
Run from the repository root:

    PYTHONPATH=. python bench/results/tiebreak31/landing_orders.py SEED [VIEWS] [R]
"""
from __future__ import annotations

import random
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "tests"))


def main(argv: list[str]) -> None:
    import numpy as np
    from conftest import real
    from test_stream_page_budget import _cut_ids, _land_in_random_order

    from client_gl.stream.selection import SelectionOptions
    from splatstream.camera import Camera
    from splatstream.encode import EncodeOptions, encode_in_memory
    from splatstream.format.manifest import split_pages
    from splatstream.ply import read_gaussians_ply
    from splatstream.store import read_manifest

    seed = int(argv[0])
    n_views, repeats = (int(argv[1]) if len(argv) > 1 else 10), (int(argv[2]) if len(argv) > 2 else 10)
    whole = read_manifest(encode_in_memory(read_gaussians_ply(real("fruit_drops_sh3.ply")),
                                           EncodeOptions(preset="medium", max_leaf_splats=200)))
    paged = split_pages(whole, 2)
    files = {ref.file: raw for ref, raw in paged.pages}
    whole_cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
    root = whole.tiles[whole.index_of[whole.root]]
    c, r = np.array(root.sphere_center), root.sphere_radius
    rnd = random.Random(seed)
    for side, far in (("inside", (0.05, 0.3, 0.5)), ("outside", (1.5, 3.0))):
        split = cuts = off = 0
        for v in range(n_views):
            d = np.array([rnd.gauss(0, 1) for _ in range(3)])
            eye = c + d / np.linalg.norm(d) * r * rnd.choice(far)
            cam = Camera(tuple(eye), tuple(c + np.array([rnd.gauss(0, r) for _ in range(3)])), (0.0, 0.0, 1.0),
                         rnd.choice([40.0, 60.0, 90.0]), 320, 240, near=0.001 * r)
            by_bytes = v % 3 == 2
            budget = rnd.choice([3, 5, 10, 20]) * root.splats
            opts = SelectionOptions(max_sse=1.0, max_splats=None if by_bytes else budget,
                                    budget=budget / whole.chunk_size * 4096.0 * 1.5 if by_bytes else None)
            want = frozenset(_cut_ids(whole, cam, opts, whole_cost)[0])
            seen = set()
            for _ in range(repeats):
                tree = _land_in_random_order(paged.root, files, cam, opts, random.Random(rnd.random()))
                m = tree.manifest
                cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
                seen.add(frozenset(_cut_ids(m, cam, opts, cost)[0]))
            split += len(seen) > 1
            cuts += len(seen)
            off += seen != {want}
        print(f"seed {seed}, eye {side} the root's sphere, {n_views} views x {repeats} orders: {split} views with "
              f"more than one cut, {cuts} distinct cuts in all, {off} views with a cut other than the whole tree's")


if __name__ == "__main__":
    main(sys.argv[1:])
