#!/usr/bin/env python3
"""Copies of encoded scenes with their manifest rewritten as format 1.12's compact tile table (format.md 6.2), the
same payloads (`data/` linked), for an A/B of what a view reads with the old manifest and the compact one (issue 31,
BENCHMARKS.md "Format 1.12: the compact tile table"); and, with --pages, what a cut would read of the compact
manifest paged k levels to a file (format.md 6.1), estimated from the cuts a lod_vs_peers JSON recorded.

    PYTHONPATH=. python bench/compact_manifest_ab.py copy SRC_DIR DST_DIR SCENE [SCENE ...]
    PYTHONPATH=. python bench/compact_manifest_ab.py pages SCENE_DIR LOD_VS_PEERS.json --levels 2,3,4,5

`pages` counts the root manifest, the pages that hold the drawn tiles and their ancestors (the least a cut reads)
and, as the most, also the page below every drawn tile that heads one (the client asks for a cut tile's page when
its screen-space error is above max_sse, client.md 1.11: at a small budget most are); the payload bytes read are
the JSON's own, less its whole manifest.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from splatstream.format.manifest import pack_manifest, parse_manifest, read_page, split_pages  # noqa: E402


def copy_compact(src_root: str, dst_root: str, names: list[str]) -> None:
    for name in names:
        src, dst = os.path.join(src_root, name), os.path.join(dst_root, name)
        os.makedirs(dst, exist_ok=True)
        raw = open(os.path.join(src, "manifest.msgpack"), "rb").read()
        m = parse_manifest(raw)
        compact = m.compacted(short=False)  # 1.12: the payloads keep their names (data/ is linked)
        new = pack_manifest(compact)
        assert parse_manifest(new) == compact  # what a reader gets back is what was written
        with open(os.path.join(dst, "manifest.msgpack"), "wb") as f:
            f.write(new)
        if not os.path.exists(os.path.join(dst, "data")):
            os.symlink(os.path.join(os.path.abspath(src), "data"), os.path.join(dst, "data"))
        print(f"{name}: {len(raw):,} -> {len(new):,} B, version {m.version} -> {compact.version}")


def page_estimate(scene_dir: str, bench_json: str, levels: list[int]) -> None:
    raw = open(os.path.join(scene_dir, "manifest.msgpack"), "rb").read()
    m = parse_manifest(raw).compacted(short=False)
    by_id = {t.id: t for t in m.tiles}
    parent = {c: t.id for t in m.tiles for c in t.children}
    d = json.load(open(bench_json))
    whole = len(pack_manifest(m))
    print(f"{d['scene']}: compact manifest {whole:,} B, {len(m.tiles)} tiles")
    for k in levels:
        paged = split_pages(m, k)
        root = len(pack_manifest(paged.root))
        raws = {ref.sha256: data for ref, data in paged.pages}
        page_bytes: dict[int, int] = {}  # head tile id -> its page's bytes
        todo = [t for t in paged.root.tiles if t.page]
        while todo:
            head = todo.pop()
            page_bytes[head.id] = head.page.bytes
            todo += [t for t in read_page(raws[head.page.sha256], head.page, paged.root, head, "page") if t.page]

        def head_of(tile_id: int, k: int = k) -> int | None:
            """The tile whose page holds this tile (None: the root manifest's)."""
            level = by_id[tile_id].level
            if level < k:
                return None
            a = tile_id
            while by_id[a].level > level // k * k - 1:
                a = parent[a]
            return a

        cells = []
        for budget, ours in zip(d["budget_splats"], d["ours"], strict=False):
            least, most = [], []
            for ids in ours["drawn_tile_ids_per_view"]:
                need: set[int] = set()
                for tile_id in ids:
                    a = head_of(tile_id)
                    while a is not None:
                        need.add(a)
                        a = head_of(a)
                below = {t for t in ids if t in page_bytes} - need
                least.append(root + sum(page_bytes[h] for h in need))
                most.append(least[-1] + sum(page_bytes[h] for h in below))
            drawn = ours["drawn_tile_bytes_mean"]
            payloads = ours["bytes_downloaded_mean"] - len(raw)
            lo, hi = statistics.mean(least), statistics.mean(most)
            cells.append(f"{budget:,}: {(payloads + lo) / drawn:.2f}-{(payloads + hi) / drawn:.2f} "
                         f"(whole {(payloads + whole) / drawn:.2f})")
        print(f"  k={k}: root {root:,} B, {len(paged.pages)} pages ({sum(page_bytes.values()):,} B) | "
              + " | ".join(cells))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("copy")
    c.add_argument("src")
    c.add_argument("dst")
    c.add_argument("scenes", nargs="+")
    p = sub.add_parser("pages")
    p.add_argument("scene_dir")
    p.add_argument("bench_json")
    p.add_argument("--levels", default="2,3,4,5")
    args = ap.parse_args(argv)
    if args.cmd == "copy":
        copy_compact(args.src, args.dst, args.scenes)
    else:
        page_estimate(args.scene_dir, args.bench_json, [int(x) for x in args.levels.split(",")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
