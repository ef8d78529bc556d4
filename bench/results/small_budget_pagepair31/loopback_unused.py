#!/usr/bin/env python3
"""Pages read and not used over loopback (issue 31, pages landing a frame apart): the scene and view of
tests/test_stream_page_budget.py (fruit_drops, max_leaf_splats 300, pages of 2 levels), streamed N times at each
budget over `splatstream serve`'s app on 127.0.0.1, counting in each run the page files read that hold no drawn
tile nor an ancestor of one. Run from the repository root:

    PYTHONPATH=. python bench/results/small_budget_pagepair31/loopback_unused.py N 600,2000 [pf] [--enc DIR]
"""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "tests"))


def main(argv: list[str]) -> None:
    from conftest import real
    from test_stream_engine import orbit
    from test_stream_page_budget import _pages_used
    from test_stream_pages import _stream

    from client_gl.stream.engine import StreamOptions
    from client_gl.stream.selection import SelectionOptions
    from server.testing import ServerThread
    from splatstream.encode import encode_file
    from splatstream.store import load_manifest

    enc = Path(argv[argv.index("--enc") + 1]) if "--enc" in argv else Path(tempfile.gettempdir()) / "pagepair31_enc"
    n, budgets, prefetch = int(argv[0]), [int(b) for b in argv[1].split(",")], "pf" in argv[2:]
    if not (enc / "paged" / "manifest.msgpack").exists():
        ply = real("fruit_drops_sh3.ply")
        encode_file(ply, enc / "paged", max_leaf_splats=300, page_tiles=4, page_levels=2)
        encode_file(ply, enc / "whole", max_leaf_splats=300)
    server = ServerThread(enc)
    cam = orbit(load_manifest(enc / "whole"), 2.5, 0.3)
    try:
        for budget in budgets:
            sel = SelectionOptions(max_sse=1.0, max_splats=budget)
            unused, read, cuts = [], [], set()
            for _ in range(n):
                u, m, _, pages = _stream(server, "paged", cam, StreamOptions(sel, prefetch=prefetch))
                unused.append(len(set(pages) - _pages_used(m, u.draw)))
                read.append(len(pages))
                cuts.add(tuple(sorted(u.draw)))
            print(f"{budget} splats{' (prefetch)' if prefetch else ''}: {n} runs, runs with pages not used "
                  f"{sum(x > 0 for x in unused)} (unused {unused}), pages read {sorted(set(read))}, distinct cuts "
                  f"{len(cuts)}; load average {os.getloadavg()[0]:.1f}", flush=True)
    finally:
        server.stop()


if __name__ == "__main__":
    main(sys.argv[1:])
