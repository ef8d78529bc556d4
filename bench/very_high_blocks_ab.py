"""very-high's encoder choices for decode speed (issue 32, branch vhdec): the encoder as it was (zstd level 1, no
block slack) against the preset's (presets.PRESET_ZSTD_LEVEL, PRESET_BLOCK_SLACK), on the bundled real scenes.

    PYTHONPATH=. python bench/very_high_blocks_ab.py [--scenes a,b] [--rounds 9]

Each scene is encoded both ways in memory (LOD tree, the encoder's defaults), the decoded texels checked equal, then
thread CPU (time.thread_time) of a `zstd` pass (every payload into the decoder's kept buffer) and a `verified` pass
(the streaming client's path, the numba kernels installed) of each, in alternated order each round
(bench/decode_quiet.py's Case). Prints bytes, encode CPU, least and median pass, the median of the per-round ratios.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import decode_quiet as dq  # noqa: E402

from client_gl.stream import decode_jit  # noqa: E402
from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format import presets  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def encode_both(scene: str) -> tuple[dict, dict]:
    """(Case by variant, encode CPU s by variant): "before" level 1 without a slack, "after" the preset's."""
    g = read_gaussians(os.path.join(dq.ROOT, dq.SCENES[scene]))
    slack = presets.PRESET_BLOCK_SLACK.get("very-high", 0.0)
    cases, cpu = {}, {}
    for name, level, block_slack in (("before", 1, 0.0), ("after", None, slack)):
        presets.PRESET_BLOCK_SLACK["very-high"] = block_slack
        t = time.process_time()
        cases[name] = dq.Case(encode_in_memory(g, EncodeOptions(preset="very-high", zstd_level=level)))
        cpu[name] = time.process_time() - t
    presets.PRESET_BLOCK_SLACK["very-high"] = slack
    return cases, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="winter_fountain,guitar,statue_massa,fruit_drops_sh3,lod_tile_sh3_zero_rest")
    ap.add_argument("--rounds", type=int, default=9)
    args = ap.parse_args()
    decode_jit.install()
    print("load", os.getloadavg(), flush=True)
    for scene in args.scenes.split(","):
        cases, cpu = encode_both(scene)
        digests = {k: hashlib.sha256(b"".join(c.texels())).hexdigest() for k, c in cases.items()}
        if digests["before"] != digests["after"]:
            raise SystemExit(f"{scene}: the decoded texels differ")
        times: dict = {k: {"zstd": [], "verified": []} for k in cases}
        for r in range(args.rounds):
            for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
                for v in ("zstd", "verified"):
                    times[k][v].append(cases[k].run(v))
        a, b = cases["before"], cases["after"]
        row = [scene, f"splats {a.splats} payloads {a.payloads}",
               f"encode CPU s {cpu['before']:.1f} -> {cpu['after']:.1f}",
               f"bytes {a.bytes} -> {b.bytes} ({b.bytes / a.bytes:.4f})"]
        for v in ("zstd", "verified"):
            x, y = times["before"][v], times["after"][v]
            ratio = statistics.median(q / p for p, q in zip(x, y, strict=True))
            row.append(f"{v} ms least {min(x) * 1e3:.2f} -> {min(y) * 1e3:.2f}, median {statistics.median(x) * 1e3:.2f}"
                       f" -> {statistics.median(y) * 1e3:.2f}, ratio {ratio:.3f}")
        best = [a.splats / min(times[k]["verified"]) / 1e6 for k in ("before", "after")]
        med = [a.splats / statistics.median(times[k]["verified"]) / 1e6 for k in ("before", "after")]
        row.append(f"M splats/s best {best[0]:.2f} -> {best[1]:.2f}, median {med[0]:.2f} -> {med[1]:.2f}")
        print(" | ".join(row), flush=True)
    print("load", os.getloadavg(), flush=True)


if __name__ == "__main__":
    main()
