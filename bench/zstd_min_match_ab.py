"""A preset's zstd shortest match on every payload against only on the payloads whose blocks are joined (issue 32,
the round after eval32, branch zmatch: measured, not kept).

    PYTHONPATH=. python bench/zstd_min_match_ab.py [--scenes a,b,name=path] [--presets p,q] [--lod both|yes|no]
        [--rounds 0]

Each scene is encoded in memory twice per preset ("every": the shortest match on every payload, as before;
"joined": on payloads of at most MERGE_MAX_RAW decompressed bytes, whose blocks _block_ends may join, the level's own
above: container._compressor wrapped here, no library change), with and/or without the
LOD tree (the eval counts the full-detail payloads of a no-LOD encode); the decoded texels are checked equal. Prints
bytes of the small payloads (which must be the same) and of the large ones. `--rounds N` also times N alternated
`zstd` passes (thread CPU; bench/decode_quiet.py's Case) of each: least, median, median of the per-round ratios.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import decode_quiet as dq  # noqa: E402

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format import container, presets  # noqa: E402

VARIANTS = ("every", "joined")
_COMPRESSOR = container._compressor


def _joined_only(level: int, threads: int, raw_bytes: int, min_match: int):
    """container._compressor with the shortest match only where the payload's blocks may be joined."""
    return _COMPRESSOR(level, threads, raw_bytes, min_match if raw_bytes <= container.MERGE_MAX_RAW else 0)


def split_bytes(case: dq.Case) -> tuple[int, int, int]:
    """(bytes of payloads of at most MERGE_MAX_RAW raw bytes, bytes of the larger ones, count of the larger)."""
    items = [(len(d), e.raw_bytes) for v in case.groups.values() for d, e in v]
    small = sum(n for n, raw in items if raw <= container.MERGE_MAX_RAW)
    large = [n for n, raw in items if raw > container.MERGE_MAX_RAW]
    return small, sum(large), len(large)


def encode_both(g, preset: str, lod: bool) -> dict:
    cases = {}
    try:
        for name in VARIANTS:
            container._compressor = _joined_only if name == "joined" else _COMPRESSOR
            cases[name] = dq.Case(encode_in_memory(g, EncodeOptions(preset=preset, lod=lod)))
    finally:
        container._compressor = _COMPRESSOR
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="winter_fountain,guitar,statue_massa,fruit_drops_sh3,lod_tile_sh3_zero_rest")
    ap.add_argument("--presets", default=",".join(presets.PRESET_ZSTD_MIN_MATCH))
    ap.add_argument("--lod", choices=("both", "yes", "no"), default="both")
    ap.add_argument("--rounds", type=int, default=0)
    args = ap.parse_args()
    print("load", os.getloadavg(), flush=True)
    lods = {"both": (True, False), "yes": (True,), "no": (False,)}[args.lod]
    for scene, g in dq.scene_gaussians(args.scenes):
        for preset in args.presets.split(","):
            for lod in lods:
                cases = encode_both(g, preset, lod)
                digests = {k: hashlib.sha256(b"".join(c.texels())).hexdigest() for k, c in cases.items()}
                if digests["every"] != digests["joined"]:
                    raise SystemExit(f"{scene} {preset}: the decoded texels differ")
                (s0, l0, n), (s1, l1, _) = split_bytes(cases["every"]), split_bytes(cases["joined"])
                a, b = cases["every"].bytes, cases["joined"].bytes
                row = [scene, preset, "LOD" if lod else "no LOD", f"small {s0} -> {s1}" + (" same" if s0 == s1
                       else " DIFFER"), f"large ({n}) {l0} -> {l1}" + (f" ({l1 / l0 - 1:+.3%})" if l0 else ""),
                       f"all {a} -> {b} ({b / a - 1:+.3%})"]
                if args.rounds:
                    times: dict = {k: [] for k in cases}
                    for r in range(args.rounds):
                        for k in (("every", "joined") if r % 2 == 0 else ("joined", "every")):
                            times[k].append(cases[k].run("zstd"))
                    x, y = times["every"], times["joined"]
                    ratio = statistics.median(q / p for p, q in zip(x, y, strict=True))
                    med = [statistics.median(t) * 1e3 for t in (x, y)]
                    row.append(f"zstd ms least {min(x) * 1e3:.2f} -> {min(y) * 1e3:.2f}, median "
                               f"{med[0]:.2f} -> {med[1]:.2f}, ratio {ratio:.3f}")
                print(" | ".join(row), flush=True)
    print("load", os.getloadavg(), flush=True)


if __name__ == "__main__":
    main()
