"""Per-payload against per-splat decode cost of a scene's LOD tree, one thread (issue 32, decode speed).

    python bench/decode_payload_fit.py SCENE.ply PRESET[,PRESET...]

Encodes SCENE in memory with the encoder's defaults (LOD tree), then times `format.decode.decode_payload` (checksum,
zstd, unfiltering) of every tile's base payload alone, the least CPU time (time.thread_time) of 7 tries each, and
fits time = fixed + per_splat x splats over the payloads (least squares). Prints the fit, the splats/s beyond the
fixed cost, and the share of the whole pass the fixed cost takes: where a tree of small tiles spends its decode.
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format.decode import decode_payload  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    g = read_gaussians(sys.argv[1])
    for preset in sys.argv[2].split(","):
        store = encode_in_memory(g, EncodeOptions(preset=preset))
        m = read_manifest(store)
        times, splats = [], []
        for t in m.tiles:
            data, entry = store.read_payload(t.groups["base"]), t.groups["base"]
            best = float("inf")
            for _ in range(7):
                start = time.thread_time()
                decode_payload(data, entry, "base", "bench", m.uses_codebook)
                best = min(best, time.thread_time() - start)
            times.append(best)
            splats.append(t.splats)
        ts, ns = np.array(times), np.array(splats, float)
        (fixed, per_splat), *_ = np.linalg.lstsq(np.stack([np.ones_like(ns), ns], 1), ts, rcond=None)
        print(f"{preset}: {len(ts)} payloads, splats min/median/max {ns.min():.0f}/{np.median(ns):.0f}/{ns.max():.0f};"
              f" {fixed * 1e6:.0f} us a payload + {per_splat * 1e9:.0f} ns a splat ({1 / per_splat / 1e6:.1f} M "
              f"splats/s beyond the fixed cost); whole pass {ns.sum() / ts.sum() / 1e6:.1f} M splats/s, fixed cost "
              f"{fixed * len(ts) / ts.sum():.0%} of it; load {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main()
