"""Issue 32: `bench/eval_probe.py` with coarser scene palettes: adjacent distinct entries merged pairwise.

    MERGE=color:0[,scale:0] python bench/palette_merge_probe.py SCENE [eval options] -- CONFIG [CONFIG ...]

As bench/eval_probe.py, except that the encoder's scene palettes (format.md 4.3.2, 1.7; `encode/plan.py`'s
`scene_palettes`) named in MERGE (plane:palette, e.g. `color:0` the SH0 R, G, B palette, `color:1` opacity,
`scale:0` the log scales) are made coarser before any tile is encoded: the least and the largest distinct value
stay (so every value stays within the palette's span and indexes into it), and the distinct values between them
are merged two by two into their midpoint (256 distinct values -> 129). Every value then takes the nearest entry:
the payload's indices use about one bit less of entropy, at an error of at most half the gap of a merged pair.
Encoder policy only, nothing new to read; the rule is codec.merged_pairs, which the preset medium-low-palette
applies to SH0's palette (presets.py PRESET_PALETTE_MERGE). Used for the statue scans against SOG (BENCHMARKS.md,
"A position step from the splats' size"), with the size-relative position step (`pos_k=`, TileStep.per_size).
"""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

import eval_probe  # noqa: E402

from splatstream.encode import plan  # noqa: E402
from splatstream.format.codec import merged_pairs, scene_palettes  # noqa: E402


def coarser(which: list[tuple[str, int]]):
    def fit(parts):
        palettes = scene_palettes(parts)
        for name, i in which:
            if name in palettes:
                palettes[name][i] = merged_pairs(palettes[name][i])
        return palettes
    return fit


if __name__ == "__main__":
    spec = [item.split(":") for item in os.environ.get("MERGE", "").split(",") if item]
    plan.scene_palettes = coarser([(name, int(i)) for name, i in spec])
    sys.exit(eval_probe.run(sys.argv[1:]))
