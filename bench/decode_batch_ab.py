"""Decoding a group's payloads together against one at a time, passes interleaved in one process (issue 32).

    python bench/decode_batch_ab.py SCENE.ply PRESET[,PRESET...] [--rounds 7] [--reference CHECKOUT] [--json OUT]

Encodes SCENE in memory with the encoder's defaults (the LOD tree), then times, in turn within each round, one pass
over every tile's base payload with `format.decode.decode_payload` one at a time, and with `decode_payloads` 16 at a
time and all at once (the whole group); with --reference, first a pass of CHECKOUT's `decode_payload` (its
splatstream package copied to a temporary directory under another name: another commit's decoder on the same
bytes). CPU time of this thread (time.thread_time); M splats/s of the median and of the best pass; and the calls into
C a pass makes (sys.setprofile's c_call events, per payload): each is a point where a decode thread may hand the
interpreter lock to the frame loop or wait for it (the engine's batch decode, issue 38). Interleaving
puts a shared machine's load on every variant alike (timing one after the other moved figures by 30 % there).
Every variant's planes are checked equal to decode_payload's first.
"""
from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import shutil
import statistics
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format.decode import decode_payload, decode_payloads  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402


def planes_bytes(planes: dict) -> list[bytes]:
    return [np.asarray(a).tobytes() for p in planes.values() for a in [*p.layers, p.ranges] if a is not None]


def one_at_a_time(items: list, codebook: bool, decode) -> list:
    return [decode(d, e, "base", "bench", codebook) for d, e in items]


def together(items: list, codebook: bool, n: int) -> list:
    out = []
    for i in range(0, len(items), n):
        out += decode_payloads(items[i:i + n], "base", ["bench"] * len(items[i:i + n]), codebook)
    return out


def c_calls(run) -> int:
    """Calls into C (numpy, zstd, builtins) of one run."""
    count = [0]

    def profile(frame, event, arg):
        if event == "c_call":
            count[0] += 1
    sys.setprofile(profile)
    try:
        run()
    finally:
        sys.setprofile(None)
    return count[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("presets")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--reference", help="a checkout whose decode_payload is timed too")
    ap.add_argument("--json")
    args = ap.parse_args()
    reference = None
    if args.reference:
        where = tempfile.mkdtemp()
        shutil.copytree(os.path.join(args.reference, "splatstream"), os.path.join(where, "splatstream_reference"),
                        ignore=shutil.ignore_patterns("__pycache__"))
        sys.path.insert(0, where)
        reference = importlib.import_module("splatstream_reference.format.decode").decode_payload
    g = read_gaussians(args.scene)
    rows = []
    for preset in args.presets.split(","):
        store = encode_in_memory(g, EncodeOptions(preset=preset))
        m = read_manifest(store)
        items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles]
        splats = sum(t.splats for t in m.tiles)
        cb = m.uses_codebook

        variants = {"one_at_a_time": functools.partial(one_at_a_time, items, cb, decode_payload),
                    "16_at_a_time": functools.partial(together, items, cb, 16),
                    "all_at_once": functools.partial(together, items, cb, len(items))}
        if reference is not None:
            variants = {"reference_one_at_a_time": functools.partial(one_at_a_time, items, cb, reference), **variants}
        expected = [planes_bytes(p) for p in one_at_a_time(items, cb, decode_payload)]
        for name, run in variants.items():
            if [planes_bytes(p) for p in run()] != expected:
                raise SystemExit(f"{preset}: {name} decodes to other planes than decode_payload")
        calls = {name: c_calls(run) for name, run in variants.items()}
        times: dict[str, list[float]] = {name: [] for name in variants}
        loads = []
        for _ in range(args.rounds):
            for name, run in variants.items():
                start = time.thread_time()
                run()
                times[name].append(time.thread_time() - start)
            loads.append(os.getloadavg()[0])
        row = {"scene": os.path.basename(args.scene), "preset": preset, "payloads": len(items), "splats": splats,
               "load_average": [min(loads), max(loads)]}
        for name, ts in times.items():
            row[name] = {"msplats_s": splats / statistics.median(ts) / 1e6, "best_pass": splats / min(ts) / 1e6,
                         "c_calls_per_payload": calls[name] / len(items)}
        rows.append(row)
        print(f"{preset:>18}: " + "  ".join(f"{name} {row[name]['msplats_s']:.1f} ({row[name]['best_pass']:.1f}), "
                                          f"{row[name]['c_calls_per_payload']:.0f} C calls a payload"
                                          for name in variants) + f"; load {min(loads):.1f}-{max(loads):.1f}",
              flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
