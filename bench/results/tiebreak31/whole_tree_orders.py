#!/usr/bin/env python3
"""pagepair31's count (issue 31): tests/test_stream_engine.py's paged scene (fruit_drops, medium, max_leaf_splats
300, pages of 4 tiles and 2 levels) read whole, its pages added in N random orders, and selected from that test's
first view (the eye inside the scene, looking out) under its pool's byte budget (26 slots of 256 splats, 80 %):
the distinct cuts (tile ids) over the orders. Run from the repository root:

    PYTHONPATH=. python bench/results/tiebreak31/whole_tree_orders.py [N] [SEED]
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

    from client_gl.stream.pages import PagedTree
    from client_gl.stream.selection import SelectionOptions, select, view_numbers
    from splatstream.camera import Camera
    from splatstream.encode import EncodeOptions, encode_in_memory
    from splatstream.format.manifest import parse_manifest
    from splatstream.ply import read_gaussians_ply
    from splatstream.store import read_manifest

    n, seed = (int(argv[0]) if argv else 30), (int(argv[1]) if len(argv) > 1 else 1)
    store = encode_in_memory(read_gaussians_ply(real("fruit_drops_sh3.ply")),
                             EncodeOptions(preset="medium", max_leaf_splats=300, page_tiles=4, page_levels=2))
    whole = read_manifest(store)
    top = whole.tiles[0]
    c, r = np.array(top.sphere_center), top.sphere_radius
    d = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    cam = Camera(tuple(c + 0.3 * r * d), tuple(c + 2 * r * d), (0, 0, 1), 40.0, 320, 240, near=0.001 * r)
    opts = SelectionOptions(max_sse=1.0, budget=26 * 4096.0 * 0.8)
    rnd = random.Random(seed)

    def cut_of(m) -> frozenset[int]:
        cost = np.array([t.chunks for t in m.tiles], np.float64) * 4096.0
        sel = select(m.arrays, view_numbers(m.arrays, cam, opts), cost, m.index_of[m.root], opts,
                     reduction=m.lod.reduction)
        return frozenset(m.arrays.ids[list(sel.cut)].tolist())

    want = cut_of(whole)
    cuts = []
    for _ in range(n):
        tree = PagedTree(parse_manifest(store.read_manifest(), "root", lazy_payloads=True))
        while tree.pending:  # every page, in a random order (a page once its head is held)
            tile_id = rnd.choice(sorted(tree.pending))
            tree.add_page(tile_id, store.payloads[tree.entry(tile_id).file])
        assert len(tree.manifest.tiles) == len(whole.tiles)
        cuts.append(cut_of(tree.manifest))
    print(f"{n} random orders of every page (seed {seed}): {len(set(cuts))} distinct cuts, "
          f"{sum(cut != want for cut in cuts)} orders with a cut other than the whole tree's")


if __name__ == "__main__":
    main(sys.argv[1:])
