"""Payload bytes per zstd level with the LOD tree, payload by payload and section by section (why a higher level
wrote more bytes than level 1 or 3 on flowers with the tree: BENCHMARKS.md, Encoder, "zstd level with the LOD tree").

    PYTHONPATH=. python bench/probe_zstd_levels.py SCENE [--preset medium] [--levels 1,3,9,16,19] [--json OUT.json]

Encodes SCENE once with the encoder's defaults (the LOD tree) at the first level, and hands every payload's planes,
exactly as the encoder writes them, to `container.write_payload` at each level, in one process: the same planes,
the same transport, the level alone changes. Per level: the payload bytes (the manifest aside), how many sections
took another filter than at the first level, and each plane compressed alone (a zstd block per part, as the writer
codes it) with the filter that level's trial chose and with the other filter, so a section's bytes can be told
from the filter's choice. `--single-thread` adds the levels' payloads written without zstd's worker mode.
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import json
import os
import sys
import tempfile
import time
from collections import defaultdict

import numpy as np
import zstandard

from splatstream.encode import encode_file, jobs
from splatstream.format import container
from splatstream.format.transport import (
    FIELD_LAYOUTS,
    _zstd_size,
    assemble,
    code_layer,
    filter_texels,
    shuffle_element,
    shuffle_planes,
)


def blocked_size(parts: list, params: zstandard.ZstdCompressionParameters) -> int:
    """transport._zstd_size with explicit zstd parameters: a block per part, the source size pledged."""
    c = zstandard.ZstdCompressor(compression_params=params).compressobj(
        size=sum(memoryview(x).nbytes for x in parts))
    size = 0
    for x in parts:
        size += len(c.compress(x)) + len(c.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK))
    return size + len(c.flush())


def plane_sizes(p, level: int, transport: str, min_match: int) -> dict:
    """One plane's texels alone at `level`: the filter the writer picks, its bytes, the other filter's, and the
    chosen filter's parts with zstd's shortest match raised to `min_match` bytes (0: not measured)."""
    layers = p.layers
    filt, parts = filter_texels(layers, p.format, p.width, p.height, len(layers), level, transport)
    raw = sum(memoryview(x).nbytes for x in parts)
    out = {"filter": filt, "bytes": _zstd_size(parts, level), "raw": raw}
    if min_match:
        params = zstandard.ZstdCompressionParameters.from_level(level, source_size=raw)
        params = zstandard.ZstdCompressionParameters.from_level(level, source_size=raw,
                                                                 min_match=max(min_match, params.min_match))
        out["min_match"] = blocked_size(parts, params)
    element = shuffle_element(p.format)
    out["shuffle"] = _zstd_size([x for layer in layers for x in shuffle_planes(layer, element)], level)
    if p.format in FIELD_LAYOUTS:
        out["fields1"] = _zstd_size(assemble([code_layer(np.ravel(layer).view(np.uint8), p.format, p.width,
                                                         p.height) for layer in layers]), level)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--levels", default="1,3,9,16,19")
    ap.add_argument("--single-thread", action="store_true")
    ap.add_argument("--min-match", type=int, default=0, metavar="N",
                    help="also each plane alone with zstd's shortest match at least N bytes (zstd's own for the level "
                         "and size where longer)")
    ap.add_argument("--json")
    a = ap.parse_args()
    levels = [int(x) for x in a.levels.split(",")]
    rows: list[dict] = []
    real = jobs.write_payload

    def probe(planes, f, chunks, level=1, transport="fields"):
        planes = [dataclasses.replace(p, layers=[np.ravel(x).view(np.uint8).copy() for x in p.layers])
                  for p in planes]
        row = {"group": "+".join(p.spec.name for p in planes), "texels": sum(p.width * p.height for p in planes[:1]),
               "levels": {}}
        for lv in levels:
            variants = [("", None)] + ([("st", 0)] if a.single_thread else [])
            for tag, worker_max in variants:
                saved = container.WORKER_MODE_MAX_BYTES
                if worker_max is not None:
                    container.WORKER_MODE_MAX_BYTES = worker_max
                try:
                    t0 = time.perf_counter()
                    e = real(planes, io.BytesIO(), chunks, lv, transport)
                    seconds = time.perf_counter() - t0
                finally:
                    container.WORKER_MODE_MAX_BYTES = saved
                cell = {"bytes": e.bytes, "raw": e.raw_bytes, "seconds": seconds,
                        "filters": [s.filter for s in e.sections]}
                if not tag:
                    cell["planes"] = {p.spec.name: plane_sizes(p, lv, transport, a.min_match) for p in planes}
                row["levels"][f"{lv}{tag}"] = cell
        rows.append(row)
        return real(planes, f, chunks, level, transport)

    jobs.write_payload = probe
    with tempfile.TemporaryDirectory(prefix="zlevels-") as tmp:
        t0 = time.perf_counter()
        m = encode_file(a.scene, os.path.join(tmp, "s"), preset=a.preset, zstd_level=levels[0])
        wall = time.perf_counter() - t0
    jobs.write_payload = real
    keys = list(rows[0]["levels"])
    print(f"{os.path.basename(a.scene)}: {m.splats:,} splats, {len(m.tiles)} tiles, {len(rows)} payloads, preset "
          f"{a.preset} ({wall:.0f} s for the probe)")
    print("| level | payload bytes | write s | sections with another filter than level "
          f"{levels[0]} | payloads larger than at level {levels[0]} |")
    print("|---|---:|---:|---:|---:|")
    base = str(levels[0])
    for k in keys:
        total = sum(r["levels"][k]["bytes"] for r in rows)
        secs = sum(r["levels"][k]["seconds"] for r in rows)
        flips = sum(x != y for r in rows
                    for x, y in zip(r["levels"][k]["filters"], r["levels"][base]["filters"], strict=True))
        larger = sum(r["levels"][k]["bytes"] > r["levels"][base]["bytes"] for r in rows)
        print(f"| {k} | {total:,} | {secs:.1f} | {flips} | {larger} |")
    # per plane: bytes alone with the chosen filter, and with shuffle / fields1 forced
    per = defaultdict(lambda: defaultdict(lambda: defaultdict(int)))
    for r in rows:
        for k in levels:
            for name, s in r["levels"][str(k)]["planes"].items():
                d = per[name][k]
                d["bytes"] += s["bytes"]
                d["shuffle"] += s["shuffle"]
                d["fields1"] += s.get("fields1", s["shuffle"])
                d["min_match"] += s.get("min_match", 0)
                d["fields1_sections"] += s["filter"] == "fields1"
                d["sections"] += 1
    mm = f" / chosen filter, shortest match {a.min_match}" if a.min_match else ""
    print("\nEach plane alone (every payload's section summed): chosen filter / shuffle forced / fields1 forced"
          f"{mm}, and how many sections chose fields1")
    print("| plane | " + " | ".join(f"level {k}" for k in levels) + " |")
    print("|---|" + "---|" * len(levels))
    for name, by in per.items():
        print(f"| {name} | " + " | ".join(
            f"{by[k]['bytes']:,} / {by[k]['shuffle']:,} / {by[k]['fields1']:,}"
            + (f" / {by[k]['min_match']:,}" if a.min_match else "")
            + f" ({by[k]['fields1_sections']} of {by[k]['sections']})" for k in levels) + " |")
    if a.min_match:
        print("| all planes | " + " | ".join(
            f"{sum(by[k]['bytes'] for by in per.values()):,} / - / - / "
            f"{sum(by[k]['min_match'] for by in per.values()):,}" for k in levels) + " |")
    # by payload size
    print(f"\nBy payload size at level {levels[0]} (bytes per level)")
    bins = [0, 4096, 16384, 65536, 262144, 1 << 40]
    print("| payload bytes | payloads | " + " | ".join(f"level {k}" for k in keys) + " |")
    print("|---|---:|" + "---:|" * len(keys))
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        sel = [r for r in rows if lo <= r["levels"][base]["bytes"] < hi]
        if sel:
            print(f"| {lo:,}-{hi:,} | {len(sel)} | " + " | ".join(
                f"{sum(r['levels'][k]['bytes'] for r in sel):,}" for k in keys) + " |")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"scene": a.scene, "preset": a.preset, "splats": m.splats, "tiles": len(m.tiles),
                       "rows": rows}, f)
            f.write("\n")


if __name__ == "__main__":
    sys.exit(main())
