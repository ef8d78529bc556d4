"""Where a manifest's bytes go (issues 32 and 38): per top-level key, per tile key, per payload-entry key and per
section, msgpack-packed alone, for encoded scenes (a paged scene's root manifest and pages together), as written
and as the other table form (format.md 6: the tile map array of 1.0-1.7, the column table of 1.8).

    PYTHONPATH=. python bench/manifest_bytes.py SCENE [SCENE ...] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from collections import defaultdict
from dataclasses import replace

import msgpack

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.format.manifest import pack_manifest, split_pages  # noqa: E402
from splatstream.format.manifest.versions import VERSION_1_7, VERSION_1_8  # noqa: E402
from splatstream.format.names import MANIFEST_NAME  # noqa: E402
from splatstream.store import open_store, read_manifest  # noqa: E402


def _size(v) -> int:
    return len(msgpack.packb(v, use_bin_type=True))


def breakdown(m) -> dict:
    """Bytes of the 1.7 form by key (each value packed alone, its key's bytes counted with it)."""
    d = replace(m, version=VERSION_1_7, paged=None).to_dict()
    top = {k: _size(k) + _size(v) for k, v in d.items()}
    tile_keys, entry_keys, sections = defaultdict(int), defaultdict(int), defaultdict(int)
    for t in d["tiles"]:
        for k, v in t.items():
            tile_keys[k] += _size(k) + _size(v)
        for g in t["groups"].values():
            for k, v in g.items():
                entry_keys[k] += _size(k) + _size(v)
            for s in g["sections"]:
                sections[s["name"]] += _size(s)
    n = len(d["tiles"])
    per = {k: round(v / n, 1) for k, v in sorted(tile_keys.items(), key=lambda kv: -kv[1])}
    return {"tiles": n, "top_key_bytes": dict(sorted(top.items(), key=lambda kv: -kv[1])),
            "tile_key_bytes_per_tile": per,
            "entry_key_bytes_per_tile": {k: round(v / n, 1) for k, v in sorted(entry_keys.items(),
                                                                          key=lambda kv: -kv[1])},
            "section_bytes_per_tile": {k: round(v / n, 1) for k, v in sorted(sections.items(),
                                                                           key=lambda kv: -kv[1])}}


def files_bytes(m, version, page_levels: int | None) -> dict:
    """The manifest files' bytes when the whole tree `m` is written as `version` (paged with page_levels k)."""
    w = replace(m, version=version, paged=None)
    if page_levels:
        p = split_pages(w, page_levels)
        pages = [len(raw) for _, raw in p.pages]
        root = len(pack_manifest(p.root))
        return {"root": root, "pages": len(pages), "page_bytes": sum(pages), "total": root + sum(pages),
                "page_bytes_mean": round(sum(pages) / max(1, len(pages)), 1)}
    root = len(pack_manifest(w))
    return {"root": root, "total": root}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--json")
    args = ap.parse_args()
    out = {}
    for scene in args.scenes:
        m = read_manifest(open_store(scene))
        k = m.paged.page_levels if m.paged is not None else None
        whole = replace(m, paged=None)
        row = {"version": list(m.version), "splats": m.splats, "tiles": len(m.tiles),
               "manifest_file": os.path.getsize(os.path.join(scene, MANIFEST_NAME)),
               "as_1_7": files_bytes(whole, VERSION_1_7, k), "as_1_8": files_bytes(whole, VERSION_1_8, k),
               "breakdown_1_7": breakdown(whole)}
        for v in ("as_1_7", "as_1_8"):
            row[v]["bytes_per_tile"] = round(row[v]["total"] / len(m.tiles), 1)
            row[v]["bytes_per_splat"] = round(row[v]["total"] / m.splats, 3)
        out[scene] = row
        print(scene, json.dumps({k: row[k] for k in ("version", "tiles", "as_1_7", "as_1_8")}))
        print("  per tile (1.7):", row["breakdown_1_7"]["tile_key_bytes_per_tile"])
        print("  per tile entries (1.7):", row["breakdown_1_7"]["entry_key_bytes_per_tile"])
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
