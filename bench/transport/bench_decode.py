"""Decode speed of base payloads back to GPU texels, one thread: today's payloads against transport-coded ones.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python bench/transport/bench_decode.py SCENE.ply \
        [--presets medium,low,high] [--leaf 65536] [--no-lod] [--runs 5] [--json OUT]

Encodes the scene (LOD tiles of at most --leaf splats, or one tile), then times decoding the base payload of every
leaf tile: today = container.unpack_group (zstd + unshuffle of every section, no float conversion); transport = the
payload as the proposed integration stores it (one zstd frame, sections through transport.filter_section, ranges
shuffled) decompressed and every section unfiltered with transport.unfilter_section. Times are CPU seconds of
the one thread (time.thread_time: the machine is shared, wall time moved by 2-3x), median of --runs runs over all
tiles; both paths are checked to give identical bytes. Prints M splats/s and the machine's load average.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np
import zstandard

from splatstream.container import unpack_group
from splatstream.encoder import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians
from splatstream.manifest import load_manifest
from splatstream.texformats import unshuffle_bytes
from splatstream.transport import filter_section, unfilter_section

ALIGN = 16


def transport_payload(data: bytes, entry: dict) -> tuple[bytes, list[dict]]:
    """Re-code a payload file the proposed way; returns (file bytes, section table with stored offsets/sizes)."""
    raw = np.frombuffer(zstandard.ZstdDecompressor().decompress(data), np.uint8)
    parts, table, offset = [], [], 0
    for s in entry["sections"]:
        element = 1 if s["filter"] == "none" else int(s["filter"][7:])
        buf = raw[s["offset"]:s["offset"] + s["size"]]
        if s["kind"] == "texels":
            unit = buf.size // s["layers"]
            gpu = np.concatenate([unshuffle_bytes(buf[i * unit:(i + 1) * unit], element) for i in range(s["layers"])])
            stored, name = filter_section(gpu, s["format"], s["width"], s["height"], s["layers"])
        else:
            stored, name = buf.tobytes(), s["filter"]
        pad = -offset % ALIGN
        parts.append(bytes(pad) + stored)
        offset += pad
        table.append({**s, "offset": offset, "size": len(stored), "filter": name})
        offset += len(stored)
    cobj = zstandard.ZstdCompressor(level=3, write_content_size=True).compressobj(size=offset)
    out = []
    for p in parts:
        out += [cobj.compress(p), cobj.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK)]
    out.append(cobj.flush())
    return b"".join(out), table


def decode_transport(data: bytes, table: list[dict], raw_size: int) -> list[np.ndarray]:
    raw = np.frombuffer(zstandard.ZstdDecompressor().decompress(data, max_output_size=raw_size), np.uint8)
    out = []
    for s in table:
        stored = raw[s["offset"]:s["offset"] + s["size"]]
        if s["kind"] == "texels":
            out.append(unfilter_section(stored, s["filter"], s["format"], s["width"], s["height"], s["layers"]))
        else:
            element = 1 if s["filter"] == "none" else int(s["filter"][7:])
            out.append(unshuffle_bytes(stored, element))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--presets", default="medium,low,high")
    ap.add_argument("--leaf", type=int, default=65536)
    ap.add_argument("--no-lod", action="store_true")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json")
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    results = []
    for preset in args.presets.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "scene")
            encode_gaussians(g, out, EncodeOptions(preset=preset, lod=not args.no_lod, max_leaf_splats=args.leaf))
            m = load_manifest(out)
            tiles = []
            for t in m["tiles"]:
                if t.get("children"):
                    continue
                e = t["groups"]["base"]
                data = open(os.path.join(out, e["file"]), "rb").read()
                coded, table = transport_payload(data, e)
                raw_size = sum(s["size"] for s in table) + ALIGN * len(table)
                tiles.append((t["splats"], data, e, coded, table, raw_size))
        splats = sum(t[0] for t in tiles)
        for n, data, e, coded, table, raw_size in tiles:  # identical GPU bytes, or the timing means nothing
            today = unpack_group(data, e, "base", n, "bench")
            new = decode_transport(coded, table, raw_size)
            planes = [p for name in ("position", "rotation", "scale", "color") for p in today[name].layers]
            texels = [x for x, s in zip(new, table, strict=True) if s["kind"] == "texels"]
            assert all(np.array_equal(np.concatenate([np.asarray(a).reshape(-1)]), b) for a, b in zip(planes, texels,
                                                                                                      strict=True))

        def run_today(tiles=tiles):
            for n, data, e, *_ in tiles:
                unpack_group(data, e, "base", n, "bench")

        def run_new(tiles=tiles):
            for _, _, _, coded, table, raw_size in tiles:
                decode_transport(coded, table, raw_size)

        timings = {}
        for name, fn in (("today", run_today), ("transport", run_new)):
            fn()
            ts = []
            for _ in range(args.runs):
                t0 = time.thread_time()
                fn()
                ts.append(time.thread_time() - t0)
            timings[name] = float(np.median(ts))
        r = {"preset": preset, "tiles": len(tiles), "splats": splats,
             "base_bytes_today": sum(len(t[1]) for t in tiles), "base_bytes_transport": sum(len(t[3]) for t in tiles),
             "today_msplats_s": splats / timings["today"] / 1e6,
             "transport_msplats_s": splats / timings["transport"] / 1e6, "load_average": os.getloadavg()[0]}
        results.append(r)
        print(f"{preset}: {len(tiles)} tiles, {splats} splats; base {r['base_bytes_today'] / splats:.2f} -> "
              f"{r['base_bytes_transport'] / splats:.2f} B/splat; decode today {r['today_msplats_s']:.1f}, transport "
              f"{r['transport_msplats_s']:.1f} M splats/s (load average {r['load_average']:.1f})", flush=True)
    if args.json:
        json.dump(results, open(args.json, "w"), indent=1)


if __name__ == "__main__":
    main()
