"""Decode speed of several presets measured interleaved (issue 32): one process, one thread, the passes of the
presets alternating, so the load of a shared machine falls on all of them alike (bench_decode.py times one preset
after the other, and on 2 shared cores its numbers moved by 15-20 % between runs).

    python bench/decode_ab.py SCENE.ply PRESET ... [--runs 5]

Encodes the scene in memory with the LOD tree (the encoder's default), then times format.decode.decode_payload
(checksum, zstd, unfiltering) over every payload of every tile, CPU time of this thread; prints M splats/s per
payload group (each tile's splats counted once per group), median and best pass.

With `--encode-times` it also prints each preset's encode CPU time (time.process_time around the in-memory encode
with the LOD tree: every thread of this process, the PLY read left out) and its ratio to `medium`'s, which is then
encoded first and once more at the end (the median of those runs is the reference); issue 32 asks every preset
within 2x of medium's.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.errors import UsageError  # noqa: E402
from splatstream.format.decode import decode_payload  # noqa: E402
from splatstream.format.manifest import parse_manifest  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("presets", nargs="+")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--encode-times", action="store_true")
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    sets, enc = {}, {}
    order = list(args.presets)
    if args.encode_times:
        order = ["medium", *[p for p in order if p != "medium"], "medium"]
    for p in order:
        t = time.process_time()
        try:
            store = encode_in_memory(g, EncodeOptions(preset=p))
        except UsageError as e:  # e.g. very-low's BC7 colour without the 'bc' extra
            print(f"skipped {p}: {e}", flush=True)
            continue
        enc.setdefault(p, []).append(time.process_time() - t)
        print(f"encoded {p}: {enc[p][-1]:.2f} CPU s", flush=True)
        if p in sets:
            continue
        m = parse_manifest(store.read_manifest())
        jobs = [(store.read_payload(e), e, grp) for t in m.tiles for grp, e in t.groups.items()]
        # the scene's palettes (format.md 4.3.2): medium-low-palette's planes without their own palette section
        sets[p] = (jobs, m.uses_codebook, sum(t.splats * len(t.groups) for t in m.tiles), m.scene_palettes)
    times: dict[str, list[float]] = {p: [] for p in sets}
    for _ in range(args.runs):
        for p, (jobs, codebook, _, palettes) in sets.items():
            t = time.thread_time()
            for data, entry, group in jobs:
                decode_payload(data, entry, group, p, codebook=codebook, palettes=palettes)
            times[p].append(time.thread_time() - t)
    for p, ts in times.items():
        n = sets[p][2]
        print(f"{p:>20}: {n / statistics.median(ts) / 1e6:6.2f} M splats/s (best {n / min(ts) / 1e6:6.2f})")
    if args.encode_times:
        m = statistics.median(enc["medium"])
        print(f"\nencode CPU s, LOD tree (medium: median of {', '.join(f'{x:.2f}' for x in enc['medium'])})")
        for p, ts in enc.items():
            print(f"{p:>20}: {statistics.median(ts):6.2f} CPU s, {statistics.median(ts) / m:4.2f}x medium")


if __name__ == "__main__":
    main()
