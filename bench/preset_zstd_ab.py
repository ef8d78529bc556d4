"""The presets' zstd choices for decode speed (issue 32, branches vhdec and lossydec): each preset's encoder as it
was (its zstd level, the level's shortest match, blocks joined only where no bytes grow) against the preset's now
(presets.PRESET_ZSTD_LEVEL, PRESET_ZSTD_MIN_MATCH, PRESET_BLOCK_SLACK), on the bundled real scenes.

    PYTHONPATH=. python bench/preset_zstd_ab.py [--scenes a,b,name=path] [--presets p,q] [--rounds 7]
    PYTHONPATH=. python bench/preset_zstd_ab.py --presets very-high --rounds 9      # vhdec's measurement
    PYTHONPATH=. python bench/preset_zstd_ab.py --presets medium-low-9bit --after 16:6:0.01   # a candidate
    PYTHONPATH=. python bench/preset_zstd_ab.py --presets very-high --before 12:0:0.03 --rounds 9   # vhdec2's

`--after LEVEL:MIN_MATCH:SLACK[:ONE_BLOCK_SLACK]` measures a candidate instead of the preset's settings now (the
"after" side), for settings not yet in presets.py (issue 32, eval32: the two level-16 presets lossydec left);
`--before` the same for the "before" side instead of BEFORE (vhdec2: very-high's one-block slack against vhdec's
settings, `12:0:0.03`). ONE_BLOCK_SLACK is presets.PRESET_ONE_BLOCK_SLACK's (0 where left out).

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

# (zstd level, shortest match (0: the level's), block slack) of each preset before its branch (no one-block slack):
# very-high before vhdec (main at e8b6c09), the others before lossydec (main at c8fa564)
BEFORE = {"very-high": (1, 0, 0.0), "high": (1, 0, 0.0), "medium-low-sh8": (1, 0, 0.0), "medium-low-sh16": (1, 0, 0.0),
          "medium-low-12bit": (16, 0, 0.0), "medium-low-palette": (16, 0, 0.0), "low-plus-9bit": (16, 0, 0.0),
          "low-plus-9bit-sh6": (16, 0, 0.0), "low-plus-9bit-sh5": (16, 0, 0.0),
          # before eval32 (main at 957988b): the two level-16 presets lossydec left on the level's own settings
          "low-plus-10bit-cb8": (16, 0, 0.0), "medium-low-9bit": (16, 0, 0.0),
          # before tidy32 (main at 5579774): medium-high on the encoder's default level without a slack
          "medium-high": (1, 0, 0.0)}
TABLES = (presets.PRESET_ZSTD_LEVEL, presets.PRESET_ZSTD_MIN_MATCH, presets.PRESET_BLOCK_SLACK,
          presets.PRESET_ONE_BLOCK_SLACK)


def parse_settings(text: str) -> tuple[int, int, float, float]:
    """`LEVEL:MIN_MATCH:SLACK[:ONE_BLOCK_SLACK]` (e.g. 16:6:0.01) as (zstd level, shortest match (0: the level's),
    block slack, one-block slack (0 where left out))."""
    level, min_match, slack, *one = text.split(":")
    return int(level), int(min_match), float(slack), float(one[0]) if one else 0.0


def encode_both(g, preset: str, after: tuple[int, int, float, float] | None = None,
                before: tuple[int, int, float, float] | None = None) -> tuple[dict, dict]:
    """(Case by variant, encode CPU s by variant): "before" the settings of BEFORE (or `before`), "after" the
    preset's now, or `after` (level, shortest match, slack, one-block slack) where given."""
    now = [dict(t) for t in TABLES]
    cases, cpu = {}, {}
    for name in ("before", "after"):
        settings = (before or (*BEFORE[preset], 0.0)) if name == "before" else after
        if settings is not None:
            for table, value in zip(TABLES, settings, strict=True):
                table.pop(preset, None)
                if value:
                    table[preset] = value
        t = time.process_time()
        cases[name] = dq.Case(encode_in_memory(g, EncodeOptions(preset=preset)))
        cpu[name] = time.process_time() - t
        for table, saved in zip(TABLES, now, strict=True):
            table.clear()
            table.update(saved)
    return cases, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="winter_fountain,guitar,statue_massa,fruit_drops_sh3,lod_tile_sh3_zero_rest")
    ap.add_argument("--presets", default=",".join(p for p in BEFORE if p != "very-high"))
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--after", type=parse_settings, default=None, metavar="LEVEL:MIN_MATCH:SLACK[:ONE_BLOCK_SLACK]",
                    help="a candidate's zstd settings instead of the preset's now (e.g. 16:6:0.01)")
    ap.add_argument("--before", type=parse_settings, default=None, metavar="LEVEL:MIN_MATCH:SLACK[:ONE_BLOCK_SLACK]",
                    help="the settings to measure against instead of BEFORE's (e.g. 12:0:0.03)")
    args = ap.parse_args()
    decode_jit.install()
    print("load", os.getloadavg(), flush=True)
    for scene, g in dq.scene_gaussians(args.scenes):
        for preset in args.presets.split(","):
            cases, cpu = encode_both(g, preset, args.after, args.before)
            digests = {k: hashlib.sha256(b"".join(c.texels())).hexdigest() for k, c in cases.items()}
            if digests["before"] != digests["after"]:
                raise SystemExit(f"{scene} {preset}: the decoded texels differ")
            times: dict = {k: {"zstd": [], "verified": []} for k in cases}
            for r in range(args.rounds):
                for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
                    for v in ("zstd", "verified"):
                        times[k][v].append(cases[k].run(v))
            a, b = cases["before"], cases["after"]
            row = [scene, preset, f"splats {a.splats} payloads {a.payloads}",
                   f"encode CPU s {cpu['before']:.1f} -> {cpu['after']:.1f}",
                   f"bytes {a.bytes} -> {b.bytes} ({b.bytes / a.bytes - 1:+.2%})"]
            for v in ("zstd", "verified"):
                x, y = times["before"][v], times["after"][v]
                ratio = statistics.median(q / p for p, q in zip(x, y, strict=True))
                row.append(f"{v} ms least {min(x) * 1e3:.2f} -> {min(y) * 1e3:.2f}, median "
                           f"{statistics.median(x) * 1e3:.2f} -> {statistics.median(y) * 1e3:.2f}, ratio {ratio:.3f}")
            best = [a.splats / min(times[k]["verified"]) / 1e6 for k in ("before", "after")]
            med = [a.splats / statistics.median(times[k]["verified"]) / 1e6 for k in ("before", "after")]
            row.append(f"M splats/s best {best[0]:.2f} -> {best[1]:.2f}, median {med[0]:.2f} -> {med[1]:.2f}")
            print(" | ".join(row), flush=True)
    print("load", os.getloadavg(), flush=True)


if __name__ == "__main__":
    main()
