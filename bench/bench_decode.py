"""Decode speed of payloads to GPU texels, one thread: what the streaming client's decode workers do per payload.

    python bench/bench_decode.py SCENE.ply [--presets medium,low,high] [--leaf 16384] [--no-lod] [--runs 5]
        [--groups base] [--transport fields,shuffle] [--batch N] [--overrides scale=pal8x4,...] [--json OUT]

Encodes the scene in memory (LOD tiles of at most --leaf splats, the encoder's default, or one tile with --no-lod),
then times `format.decode.decode_payload` (size and SHA-256 check, zstd, unfiltering every section into the texel
bytes the GPU takes and the ranges) over every tile's payloads of the listed groups, and the same without the
checksum (`container.unpack_payload`). Times are CPU seconds of this one thread (time.thread_time: other jobs on a
shared machine move wall time by 2-3x), the median of --runs passes over all tiles, and the best pass (other jobs
on the other core still move the median by up to 1.5x: they share caches and, on a VM, the physical core);
splats/s counts each tile's splats once per group. Every transport gives the same texels (checked).
With --batch N the payloads of a group are decoded N at a time, in tile order, by `format.decode.decode_payloads`
(and `container.unpack_payloads` without the checksum): the same texels (checked), each numpy step taken once for
the N payloads (issue 32).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format.container import unpack_payload, unpack_payloads  # noqa: E402
from splatstream.format.decode import decode_payload, decode_payloads  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402


def time_decode(jobs: list, runs: int, verify: bool, codebook: bool, batch: int = 0,
                palettes: dict | None = None) -> tuple[float, float]:
    """Median and least CPU seconds of one pass over every (bytes, entry, group) job (the least is what the code
    does when no other job on a shared machine slows this core: the steadier figure of the two there); with
    `batch`, the jobs of a group N at a time."""
    times = []
    batches = _batches(jobs, batch)
    for _ in range(runs):
        start = time.thread_time()
        if batches is None:
            for data, entry, group in jobs:
                if verify:
                    decode_payload(data, entry, group, "bench", codebook, palettes=palettes)
                else:
                    unpack_payload(data, entry, group, "bench", codebook, palettes=palettes)
        else:
            for group, items, sources in batches:
                if verify:
                    decode_payloads(items, group, sources, codebook, palettes=palettes)
                else:
                    unpack_payloads(items, group, sources, codebook, palettes=palettes)
        times.append(time.thread_time() - start)
    return statistics.median(times), min(times)


def _batches(jobs: list, batch: int) -> list | None:
    """(group, [(bytes, entry)], sources) of at most `batch` jobs of one group each, in job order; None for 0."""
    if batch <= 0:
        return None
    by_group: dict[str, list] = {}
    for data, entry, group in jobs:
        by_group.setdefault(group, []).append((data, entry))
    return [(group, items[i:i + batch], ["bench"] * len(items[i:i + batch]))
            for group, items in by_group.items() for i in range(0, len(items), batch)]


def texels(jobs: list, codebook: bool, batch: int = 0, palettes: dict | None = None) -> list[bytes]:
    out = []
    batches = _batches(jobs, batch)
    if batches is None:
        decoded = [unpack_payload(data, entry, group, "bench", codebook, palettes=palettes)
                   for data, entry, group in jobs]
    else:
        by_key = {}
        for group, items, sources in batches:
            for (_, entry), planes in zip(items, unpack_payloads(items, group, sources, codebook, palettes=palettes),
                                          strict=True):
                by_key[id(entry), group] = planes
        decoded = [by_key[id(entry), group] for _, entry, group in jobs]
    for planes in decoded:
        for p in planes.values():
            out += [np.asarray(layer).tobytes() for layer in p.layers]
            if p.ranges is not None:
                out.append(p.ranges.tobytes())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--presets", default="medium,low,high")
    ap.add_argument("--leaf", type=int, default=16384)
    ap.add_argument("--no-lod", action="store_true")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--groups", default="base", help="payload groups timed (base, sh1, ...; comma-separated)")
    ap.add_argument("--transport", default="fields,shuffle")
    ap.add_argument("--batch", type=int, default=0, help="payloads of a group decoded together (0: one at a time)")
    ap.add_argument("--overrides", default="", help="texel formats per attribute, e.g. scale=pal8x4,color=pal8x4")
    ap.add_argument("--json")
    args = ap.parse_args()
    overrides = dict(kv.split("=", 1) for kv in args.overrides.split(",") if kv)
    g = read_gaussians(args.scene)
    groups = args.groups.split(",")
    results = []
    for preset in args.presets.split(","):
        reference = None
        for transport in args.transport.split(","):
            store = encode_in_memory(g, EncodeOptions(preset=preset, overrides=overrides, lod=not args.no_lod,
                                                      max_leaf_splats=args.leaf, transport=transport))
            m = read_manifest(store)
            jobs = [(store.read_payload(t.groups[gr]), t.groups[gr], gr) for t in m.tiles for gr in groups
                    if gr in t.groups]
            splats = sum(t.splats for t in m.tiles for gr in groups if gr in t.groups)
            pal = m.scene_palettes  # format.md 4.3.2: the scene's palettes, for palette planes
            got = texels(jobs, m.uses_codebook, palettes=pal)
            if reference is None:
                reference = got
            elif got != reference:
                raise SystemExit(f"{preset}: {transport} decodes to other texels than {args.transport.split(',')[0]}")
            if args.batch and texels(jobs, m.uses_codebook, args.batch, pal) != got:
                raise SystemExit(f"{preset}: decoded {args.batch} at a time, other texels than one at a time")
            with_check, best = time_decode(jobs, args.runs, True, m.uses_codebook, args.batch, pal)
            without, _ = time_decode(jobs, args.runs, False, m.uses_codebook, args.batch, pal)
            row = {
                "scene": os.path.basename(args.scene), "preset": preset, "overrides": overrides,
                "transport": transport,
                "groups": groups, "batch": args.batch, "tiles": len(m.tiles), "payloads": len(jobs), "splats": splats,
                "median_tile_splats": int(statistics.median(t.splats for t in m.tiles)),
                "payload_bytes": sum(len(d) for d, _, _ in jobs),
                "bytes_per_splat": sum(len(d) for d, _, _ in jobs) / splats,
                "msplats_s": splats / with_check / 1e6, "msplats_s_no_checksum": splats / without / 1e6,
                "msplats_s_best_pass": splats / best / 1e6,
                "load_average": os.getloadavg()[0],
            }
            results.append(row)
            print(f"{row['scene']} {preset:>10} {transport:>8} {','.join(groups)}: {len(jobs)} payloads"
                  f"{f' ({args.batch} at a time)' if args.batch else ''}, "
                  f"{row['bytes_per_splat']:.2f} B/splat, {row['msplats_s']:.1f} M splats/s "
                  f"({row['msplats_s_no_checksum']:.1f} without the checksum; best pass "
                  f"{row['msplats_s_best_pass']:.1f}), load {row['load_average']:.1f}",
                  flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
