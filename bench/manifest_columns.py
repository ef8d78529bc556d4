#!/usr/bin/env python3
"""Where a scene's manifest bytes go (issue 31, branch digest31): the root manifest's size, the compact tile table's
bin, the keys outside it, and each column's share of the table as zstd compresses it (the table packed again at the
writer's level without that column: its marginal bytes; the parts do not add up to the whole exactly), for scenes
given as BEFORE:AFTER directory pairs (the same input encoded by two writers, e.g. 1.12 and 1.15), and the bounds
columns' joint share (`bounds_marginal`: box and radius, or 1.16's anchor_box, box8, radius8 and radius_far).

    PYTHONPATH=. python bench/manifest_columns.py /tmp/before/donut:/tmp/after/donut ... [--out OUT.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import msgpack
import zstandard

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from splatstream.format.manifest import parse_manifest  # noqa: E402
from splatstream.format.manifest.table import COMPACT_TABLE_ZSTD_LEVEL, TABLE_ZSTD_KEY  # noqa: E402

BOUNDS_KEYS = ("box", "sphere", "radius", "anchor_box", "box8", "radius8", "radius_far")


def _z(d: dict) -> int:
    raw = msgpack.packb(d, use_bin_type=True)
    return len(zstandard.ZstdCompressor(level=COMPACT_TABLE_ZSTD_LEVEL, write_content_size=True).compress(raw))


def columns(scene_dir: str) -> dict:
    raw = open(os.path.join(scene_dir, "manifest.msgpack"), "rb").read()
    m = parse_manifest(raw)  # checked: a manifest this reader reads
    d = msgpack.unpackb(raw, strict_map_key=False)
    out = {"version": list(m.version), "tiles": len(m.tiles), "manifest": len(raw)}
    if TABLE_ZSTD_KEY not in d:
        return out
    table_bin = d[TABLE_ZSTD_KEY]
    t = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(table_bin), strict_map_key=False)
    out["table"] = len(table_bin)
    out["outside_table"] = len(raw) - len(table_bin)
    out["payloads"] = t["count"] * len(t["groups"])
    whole = _z(t)
    out["table_repacked"] = whole
    marginal = {}
    for k in t:
        if k == "count":
            continue
        rest = {a: b for a, b in t.items() if a != k}
        marginal[k] = whole - _z(rest)
    out["column_marginal"] = marginal
    # the bounds together (box and sphere or radius; 1.16's anchor_box, box8, radius8, radius_far): their joint
    # marginal bytes, the table packed without all of them (box16)
    bounds = [k for k in t if k in BOUNDS_KEYS]
    out["bounds_keys"] = bounds
    out["bounds_marginal"] = whole - _z({a: b for a, b in t.items() if a not in BOUNDS_KEYS})
    out["column_raw"] = {k: len(v) for k, v in t.items() if isinstance(v, bytes)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", nargs="+", help="BEFORE_DIR:AFTER_DIR")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    for pair in args.pairs:
        before, after = pair.split(":")
        b, a = columns(before), columns(after)
        name = os.path.basename(after.rstrip("/"))
        rows.append({"scene": name, "before": b, "after": a})
        dig = {k: v for k, v in a.get("column_marginal", {}).items() if k in ("digest16", "sha256")}
        print(f"{name}: {b['manifest']:,} B ({'.'.join(map(str, b['version']))}) -> {a['manifest']:,} B "
              f"({'.'.join(map(str, a['version']))}), {a['tiles']} tiles, {a.get('payloads', 0)} payloads; "
              f"digests {b.get('column_marginal', {}).get('sha256', 0):,} -> {sum(dig.values()):,} B; bounds "
              f"{b.get('bounds_marginal', 0):,} -> {a.get('bounds_marginal', 0):,} B; after: "
              + ", ".join(f"{k} {v:,}" for k, v in sorted(a.get("column_marginal", {}).items(),
                                                          key=lambda kv: -kv[1])[:8]))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
