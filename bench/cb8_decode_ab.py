"""Decode CPU time of low-plus-10bit-cb8's payloads before (760-level positions, fields transport) and now (1023
levels, keyed), LOD tree on, one thread, every payload of every tile, interleaved rounds (BENCHMARKS.md, "SOG's point
on playbot").

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 python bench/cb8_decode_ab.py SCENE.ply [ROUNDS]
"""
from __future__ import annotations

import sys
import tempfile
import time

import numpy as np

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.format import presets as P
from splatstream.format.decode import decode_payload
from splatstream.format.presets import TileStep
from splatstream.io import read_gaussians
from splatstream.store import DirectoryStore, load_manifest

NOW = "low-plus-10bit-cb8"
BEFORE = "cb8-before"


def main(path: str, rounds: int) -> None:
    g = read_gaussians(path)
    P.PRESETS[BEFORE] = dict(P.PRESETS[NOW])
    P.PRESET_STEPS[BEFORE] = {**P.PRESET_STEPS[NOW], "position": TileStep((760.0,) * 3, shared=3)}
    for table in (P.PRESET_SH_CODEBOOK, P.PRESET_ZSTD_LEVEL, P.PRESET_ZSTD_MIN_MATCH, P.PRESET_BLOCK_SLACK):
        if NOW in table:
            table[BEFORE] = table[NOW]
    items = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in (BEFORE, NOW):
            m = encode_gaussians(g, f"{tmp}/{name}", EncodeOptions(preset=name, lod=True))
            store = DirectoryStore(f"{tmp}/{name}")
            man = load_manifest(store)
            items[name] = [(store.read_payload(e), e, group, man.uses_codebook)
                           for t in man.tiles for group, e in t.groups.items()]
            print(f"{name}: {m.bytes_on_disk / len(g):.3f} B/splat with LOD, transport "
                  f"{P.PRESET_TRANSPORT.get(name, 'fields')}", flush=True)
    seconds: dict[str, list[float]] = {k: [] for k in items}
    for r in range(rounds):
        for name in (list(items) if r % 2 == 0 else list(items)[::-1]):
            t = time.thread_time()
            for data, entry, group, codebook in items[name]:
                decode_payload(data, entry, group, "ab", codebook=codebook)
            seconds[name].append(time.thread_time() - t)
    for name, v in seconds.items():
        print(f"{name}: decode CPU s {[round(x, 3) for x in v]}, median {float(np.median(v)):.3f}")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 5)
