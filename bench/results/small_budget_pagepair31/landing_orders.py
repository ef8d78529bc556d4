#!/usr/bin/env python3
"""The engine's page loop without the network, pages landing in random orders (issue 31, pages landing a frame
apart): fruit_drops (medium, max_leaf_splats 200) split into pages of K levels, random views and budgets (the
views of tests/test_stream_page_budget.py), each streamed once with every wanted page landing at once each frame
and R times with a random part of the pages on their way landing each frame; with the rule told of the pages on
their way (the wait) and without (before). Counts the pages read, those not used (head not refined at
convergence) and the runs that read a page the all-at-once loop does not. Run from the repository root:

    PYTHONPATH=. python bench/results/small_budget_pagepair31/landing_orders.py K SEED [VIEWS] [R]
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
    from test_stream_page_budget import _camera_at, _cut_ids, _land_in_any_order

    from client_gl.stream.selection import SelectionOptions
    from splatstream.encode import EncodeOptions, encode_in_memory
    from splatstream.format.manifest import split_pages
    from splatstream.ply import read_gaussians_ply
    from splatstream.store import read_manifest

    levels, seed = int(argv[0]), int(argv[1])
    n_views, repeats = (int(argv[2]) if len(argv) > 2 else 30), (int(argv[3]) if len(argv) > 3 else 5)
    whole = read_manifest(encode_in_memory(read_gaussians_ply(real("fruit_drops_sh3.ply")),
                                           EncodeOptions(preset="medium", max_leaf_splats=200)))
    paged = split_pages(whole, levels)
    files = {ref.file: raw for ref, raw in paged.pages}
    chunk = whole.chunk_size
    whole_cost = np.array([t.chunks for t in whole.tiles], np.float64) * 4096.0
    rnd = random.Random(seed)
    # [pages read, not used, runs reading a page the all-at-once loop does not] per rule; the all-at-once loop's
    totals = {"before": [0, 0, 0], "after": [0, 0, 0]}
    at_once_total = [0, 0]
    for _ in range(n_views):
        cam = _camera_at(whole, rnd, rnd.choice([1.5, 3.0, 8.0]))
        budget = rnd.choice([2, 3, 5, 10, 20, 40]) * whole.tiles[whole.index_of[whole.root]].splats
        by_bytes = rnd.random() < 0.3
        opts = SelectionOptions(max_sse=1.0, max_splats=None if by_bytes else budget,
                                budget=budget / chunk * 4096.0 * 1.5 if by_bytes else None)
        want = _cut_ids(whole, cam, opts, whole_cost)[0]
        cut, at_once, refined = _land_in_any_order(paged.root, files, cam, opts, None)
        assert cut == want
        at_once_total[0] += repeats * len(at_once)
        at_once_total[1] += repeats * len(set(at_once) - refined)
        for side in ("before", "after"):
            for _ in range(repeats):
                cut, read, refined = _land_in_any_order(paged.root, files, cam, opts, random.Random(rnd.random()),
                                                        side == "after")
                assert cut == want  # the same cut either way
                t = totals[side]
                t[0] += len(read)
                t[1] += len(set(read) - refined)
                t[2] += not set(read) <= set(at_once)
    runs = n_views * repeats
    print(f"pages of {levels} levels, seed {seed}, {n_views} views x {repeats} orders: all at once {at_once_total[0]} "
          f"read, {at_once_total[1]} not used; before {totals['before'][0]} read, {totals['before'][1]} not used, "
          f"{totals['before'][2]} of {runs} runs read a page the all-at-once loop does not; after "
          f"{totals['after'][0]} read, {totals['after'][1]} not used, {totals['after'][2]} of {runs} runs")


if __name__ == "__main__":
    main(sys.argv[1:])
