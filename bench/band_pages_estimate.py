#!/usr/bin/env python3
"""What a budgeted view would read of a manifest split into level bands (issue 31; a layout format 1.12 does not
have: format.md 6.1 pages one head tile's subtree each), estimated from the cuts a lod_vs_peers run recorded.

A band layout: the root manifest holds the tree's levels 0..a (its scene keys and those tiles' rows, as a compact
table), and each further band of levels (a+1..b, b+1..c, ...) is ONE page holding those levels of the whole tree,
read once any drawn tile lies in it (a client that asks for a page only when its budget could take the refinement
below: the floor of what such a layout reads, not what today's client reads of format 6.1's pages). Each part's
bytes are measured: the compact table of its tiles packed as the encoder packs a page (format.md 6.2), plus the
root's keys; the payload bytes are the run's own downloads less its whole manifest.

    PYTHONPATH=. python bench/band_pages_estimate.py SCENE_DIR LOD_VS_PEERS.json --bands 4,5 --bands 3,5,7
    PYTHONPATH=. python bench/band_pages_estimate.py SCENE_DIR LOD_VS_PEERS.json --rule 0.02,2   # from the shape
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

import msgpack

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from splatstream.format.manifest import parse_manifest  # noqa: E402
from splatstream.format.manifest.paging import pack_page  # noqa: E402


def shape_bands(m, share: float, step: int) -> list[int]:
    """Band edges from the tree's shape: the root manifest to the shallowest level holding at least `share` of
    the scene's splats, then a band every `step` levels (the last band to the leaves)."""
    per_level = [0] * m.levels
    for t in m.tiles:
        per_level[t.level] += t.splats
    first = next((lv for lv, n in enumerate(per_level) if n >= share * m.splats), m.levels - 1)
    return list(range(first, m.levels - 1, step))


def estimate(scene_dir: str, bench_json: str, bands: list[list[int]],
             rules: list[tuple[float, int]] = ()) -> list[dict]:
    raw = open(os.path.join(scene_dir, "manifest.msgpack"), "rb").read()
    m = parse_manifest(raw)
    if m.paged is not None:
        raise SystemExit(f"{scene_dir}: paged already; give an unpaged encode")
    bands = list(bands) + [shape_bands(m, share, step) for share, step in rules]
    keys = len(raw) - len(msgpack.unpackb(raw, raw=False)["tile_table_zstd"])
    by_id = {t.id: t for t in m.tiles}
    d = json.load(open(bench_json))
    out = []
    for cuts in bands:  # the last level of the root manifest, then of each band page but the last (to the leaves)
        edges = [-1, *cuts, m.levels - 1]
        part_of_level = {}
        sizes = []
        for i in range(len(edges) - 1):
            tiles = [t for t in m.tiles if edges[i] < t.level <= edges[i + 1]]
            for lv in range(edges[i] + 1, edges[i + 1] + 1):
                part_of_level[lv] = i
            body = len(pack_page(m.version, m.root, tiles))
            sizes.append(body + (keys + 40 * (len(edges) - 2) if i == 0 else 0))  # the root: a page entry a band
        cells = []
        for ours in d["ours"]:
            reads = []
            for ids in ours["drawn_tile_ids_per_view"]:
                parts = {0} | {part_of_level[by_id[int(t)].level] for t in ids}
                reads.append(sum(sizes[p] for p in parts))
            payloads = ours["bytes_downloaded_mean"] - len(raw)
            drawn = ours["drawn_tile_bytes_mean"]
            cells.append({"budget": ours["budget"], "manifest_read": statistics.mean(reads),
                          "ratio": (payloads + statistics.mean(reads)) / drawn,
                          "ratio_whole": ours["bytes_downloaded_mean"] / drawn})
        out.append({"bands": cuts, "sizes": sizes, "cells": cells})
        print(f"{d['scene']} root to level {cuts[0]}, bands to {cuts[1:] + [m.levels - 1]}: parts "
              f"{', '.join(f'{s:,}' for s in sizes)} B (whole {len(raw):,}) | "
              + " | ".join(f"{c['budget']:,}: {c['ratio']:.2f} (whole {c['ratio_whole']:.2f})" for c in cells))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir")
    ap.add_argument("bench_json")
    ap.add_argument("--rule", action="append", default=[],
                    help="SHARE,STEP: bands from the tree's shape (shape_bands), e.g. 0.02,2 (repeatable)")
    ap.add_argument("--bands", action="append", default=[],
                    help="comma list: the root manifest's last level, then each band page's last level but the "
                         "deepest's (repeat for more layouts)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rules = [(float(r.split(",")[0]), int(r.split(",")[1])) for r in args.rule]
    res = estimate(args.scene_dir, args.bench_json, [[int(x) for x in b.split(",")] for b in args.bands], rules)
    if args.out:
        json.dump(res, open(args.out, "w"), indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
