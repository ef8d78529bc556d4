"""Decode speed of several presets measured interleaved (issue 32): one process, one thread, the passes of the
presets alternating, so the load of a shared machine falls on all of them alike (bench_decode.py times one preset
after the other, and on 2 shared cores its numbers moved by 15-20 % between runs).

    python bench/decode_ab.py SCENE.ply PRESET ... [--runs 5]

Encodes the scene in memory with the LOD tree (the encoder's default), then times format.decode.decode_payload
(checksum, zstd, unfiltering) over every payload of every tile, CPU time of this thread; prints M splats/s per
payload group (each tile's splats counted once per group), median and best pass.
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
from splatstream.format.decode import decode_payload  # noqa: E402
from splatstream.format.manifest import parse_manifest  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("presets", nargs="+")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    sets = {}
    for p in args.presets:
        store = encode_in_memory(g, EncodeOptions(preset=p))
        m = parse_manifest(store.read_manifest())
        jobs = [(store.read_payload(e), e, grp) for t in m.tiles for grp, e in t.groups.items()]
        sets[p] = (jobs, m.uses_codebook, sum(t.splats * len(t.groups) for t in m.tiles))
    times: dict[str, list[float]] = {p: [] for p in sets}
    for _ in range(args.runs):
        for p, (jobs, codebook, _) in sets.items():
            t = time.thread_time()
            for data, entry, group in jobs:
                decode_payload(data, entry, group, p, codebook=codebook)
            times[p].append(time.thread_time() - t)
    for p, ts in times.items():
        n = sets[p][2]
        print(f"{p:>20}: {n / statistics.median(ts) / 1e6:6.2f} M splats/s (best {n / min(ts) / 1e6:6.2f})")


if __name__ == "__main__":
    main()
