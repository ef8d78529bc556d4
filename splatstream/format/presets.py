"""Presets (format_spec/format.md 7): the texel format of each attribute, and how a preset is overridden.

A reader never needs a preset: it follows the manifest's `formats`. Encoder, evaluation and the in-memory client
path resolve a preset name here, so they agree on what a preset means.
"""
from __future__ import annotations

from ..errors import UsageError
from .planes import PALETTE_ATTRIBUTES
from .steps import TileStep
from .texformats import FORMATS, PALETTE_FORMATS, ROTATION_ONLY_FORMATS, VALUE_FORMATS, get_format

ATTRIBUTES = ("position", "rotation", "scale", "color", "sh")

# Texel format per attribute, from the largest files to the smallest. The seed's table (Very High .. Very Low) is
# the baseline these must beat; the three presets between medium and low fill the hole where SPZ and SOG sit (issue
# 15; BENCHMARKS.md, "Size against quality"). Sizes below are disk bytes per splat with the fields1 transport
# coding, PSNR the mean over 8 views (fruit_drops: real SH3, 4.7k splats; make_scene 1M).
PRESETS: dict[str, dict[str, str]] = {
    "very-high": {"position": "f32x4", "rotation": "f32x4", "scale": "f32x4", "color": "f32x4", "sh": "f32x4"},
    "high": {"position": "f16x4", "rotation": "norm10_2", "scale": "norm11", "color": "f16x4", "sh": "norm11"},
    # high with its 11-bit SH on importance-scaled tile steps of 255 levels (medium-high's are 63; issue 32, hole32):
    # on flowers and playbot (SH2) medium-high -> high was one 1.42-1.44x step in bytes with nothing between. SH
    # alone makes the difference (flowers: 15.4 -> 29.1 B/splat of SH, every other plane the same), so the step's G
    # alone fills it: chosen on flowers (G = 127: 35.76 B, 61.72 dB; 255: 38.70 B, 61.98 dB, against the geometric
    # middle 39.22 B), checked on playbot, fruit_drops and lod_tile (BENCHMARKS.md, "The hole between medium-high
    # and high"). On SH0 scenes its files are high's.
    "high-sh255": {"position": "f16x4", "rotation": "norm10_2", "scale": "norm11", "color": "f16x4", "sh": "norm11"},
    # high's positions, rotations, scales and colour with 11-bit SH on importance-scaled tile steps (issue 32): on
    # the real SH2 scene flowers (542k splats) between medium and high, where compressed.ply sits.
    "medium-high": {"position": "f16x4", "rotation": "norm10_2", "scale": "norm11", "color": "f16x4", "sh": "norm11"},
    # medium with about 12-bit positions: 16-bit texels on one step per tile (PRESET_STEPS), as medium-low-12bit's
    # (issue 32). On the statue scans (SOG inputs) medium's norm11 positions carry most of its error (statue-massa:
    # 63.0 dB, 72.4 with lossless positions) and land on compressed.ply's PSNR to a few hundredths of a dB; one
    # 12-bit tile step gains 3.6-5.8 dB there for 0.07-0.27 B/splat more (BENCHMARKS.md, "medium-12bit"). Not for
    # compressed.ply inputs: medium keeps their chunk grids and stays the better preset there. Its scales stay on
    # per-chunk grids (it was measured before medium's scale step, PRESET_STEPS, and keeps its own settings).
    "medium-12bit": {"position": "norm16x4", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4",
                     "sh": "norm565"},
    "medium": {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"},
    # medium-low's positions, rotations, scales and colour with per-splat SH bands (no codebook) on importance-scaled
    # tile steps of 16 and 8 levels (issue 32): on real SH with many distinct rows (flowers: 262k of 542k) the
    # codebook loses 15 dB against medium's bands; these fill the curve between medium-low and medium.
    "medium-low-sh16": {"position": "norm11", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                        "sh": "norm565"},
    "medium-low-sh8": {"position": "norm11", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                       "sh": "norm565"},
    # low-plus-9bit's positions, rotations, scales and colour (and their tile steps, zstd level 16) with per-splat
    # SH bands on importance-scaled steps of 6 levels (issue 32): on flowers (SH2) 18.46 B/splat at 45.2 dB, 0.94 of
    # SPZ's bytes at +0.9 dB, between medium-low (15.4 B, 42.5 dB) and medium-low-sh8 (21.5 B, 48.5 dB).
    "low-plus-9bit-sh6": {"position": "norm9x3", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                          "sh": "norm565"},
    # low-plus-9bit-sh6 with one step per SH band, 0 on the grid and a flatter importance scaling (issue 32): on
    # flowers 17.55 B/splat at 44.7 dB, 0.89 of SPZ's bytes at +0.5 dB (sh6: 18.46 B at 45.2, 0.94).
    "low-plus-9bit-sh5": {"position": "norm9x3", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                          "sh": "norm565"},
    # low-plus-9bit's rotations, scales and colour (and their tile steps, zstd level 16) with about 10-bit positions
    # (16-bit texels on one tile step of 1023 levels, the keyed transport) and the SH codebook at about one entry per
    # 8 splats, up to 65,536 (vq.py "large"; issue 32). Made for flowers (SH2, 542k splats, 262k distinct SH rows),
    # where SOG's 64k palette (4.4 B/splat of SH) beats every codebook of 16k entries or fewer (BENCHMARKS.md, "A 64k
    # SH codebook on flowers"). The keyed transport's 0.36 B/splat on flowers went into positions (760 -> 1023
    # levels): 15.79 -> 15.57 B/splat, 44.96 -> 45.06 dB (BENCHMARKS.md, "SOG's point on playbot").
    "low-plus-10bit-cb8": {"position": "norm16x4", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                           "sh": "norm565"},
    # medium's positions, 8-bit smallest-three rotations, 8-bit scales and the SH codebook at its finer size: on
    # the 1M scene within 1.2 dB of medium at 40 % of its bytes; on fruit_drops 46.6 dB at 15.3 B. Its rotations are
    # measured per scene since format 1.14 (PRESET_ROTATION_CHOICES): these half turns, or cube8x4 where closer.
    "medium-low": {"position": "norm11", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                   "sh": "norm565"},
    # medium-low with 9-bit positions (norm9x3, format 1.3) and zstd level 16: between low-plus and medium-low on
    # every benchmark scene, 0.7-0.9 B/splat under medium-low for 3.5-7.5 dB less (fruit_drops: 14.5 B, 47.7 dB, no
    # loss: its SH codebook's error dominates); on the biker scene 11.39 B at 60.6 dB, 0.898 of SOG's bytes at +1.1 dB.
    # Its scales and opacity on low-plus-9bit's tile steps (PRESET_STEPS; issue 32, chosen on guitar, where SOG was
    # met at 0.92 only; now 0.898 at +0.48 dB): on the 13 other real scenes 0.14-0.55 B/splat fewer for 0.0-0.8 dB
    # less (lod_tile 1.1 dB), losing no peer point met before (BENCHMARKS.md, "Size against quality").
    "medium-low-9bit": {"position": "norm9x3", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                        "sh": "norm565"},
    # medium-low-9bit's other planes with 16-bit positions on one step per tile (PRESET_STEPS): about 12-bit
    # positions where they spread like the median chunk, and scales and opacity on steps coarser than 8 bits. Made
    # for the donut scene, where SOG's 16-bit positions sat above every preset (bench/results/donut_summary.md).
    "medium-low-12bit": {"position": "norm16x4", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                         "sh": "norm565"},
    # medium-low-12bit for inputs whose scales and colour are palettes already (SOG files, issue 32): scales and
    # colour as indices into the scene's palettes (pal8x4, format.md 4.3.2), the SH0 R, G, B palette merged pairwise
    # (PRESET_PALETTE_MERGE: 256 -> 129 values), positions on a step from the splats' size (the tile's median splat
    # size / 120, PRESET_STEPS) and the keyed transport. On the seven statue scans (SOG inputs) it met SOG's point on
    # every one held out (BENCHMARKS.md, "A position step from the splats' size"). Where a plane's values do not fit
    # its palettes (more than 256 distinct values: not a SOG input) that plane is medium-low-12bit's, and positions
    # take medium-low-12bit's step too (PRESET_PALETTE_FALLBACK).
    "medium-low-palette": {"position": "norm16x4", "rotation": "norm8x4", "scale": "pal8x4", "color": "pal8x4",
                           "sh": "norm565"},
    # low-plus with 9-bit positions on one step per tile (PRESET_STEPS), and scales and opacity on coarser steps:
    # on fruit_drops, lod_tile, donut and the 1M scene fewer bytes and more PSNR than low-plus (1M: 12.55 B at 57.1 dB
    # against 13.42 B at 54.2; 0.88 of SOG's bytes at +3.8 dB there); on biker 0.6 B less for 0.6 dB less.
    "low-plus-9bit": {"position": "norm9x3", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                      "sh": "norm565"},
    # low with 8-bit smallest-three rotations: +4.4 dB on fruit_drops, +2.8 dB on the 1M scene for 1.2-1.3 B.
    "low-plus": {"position": "norm8x4", "rotation": "norm8x4", "scale": "norm8x4", "color": "norm8x4",
                 "sh": "norm565"},
    # low keeps SH1..SH3 in a scene-wide codebook (PRESET_SH_CODEBOOK; sh is the codebook's format). Its colour was
    # BC7 until format 1.2: norm8x4 colour gains 1.3-5.4 dB on real scenes (fruit_drops 36.1 -> 37.9 dB, the 1M
    # scene 45.2 -> 50.0) and, coded with fields1, costs about 1 B/splat more (fruit_drops 11.2 -> 11.7 B).
    # Rotations stay 16-bit (3 x 5/6/5 bits, w from the rest) to keep real SH3 scenes under 12 B/splat; since
    # format 1.13 cube565, the cube gauge's x, y, z over its range [-tan(pi/8), tan(pi/8)] (2.4x finer; rotrange32).
    "low": {"position": "norm8x4", "rotation": "cube565", "scale": "norm8x4", "color": "norm8x4", "sh": "norm565"},
    # very-low's positions, rotations, scales and SH codebook with norm8x4 colour (low's) on one tile step of 127
    # levels for R, G, B (55 for opacity; PRESET_STEPS), instead of BC7 (issue 32, step32): very-low -> low was one
    # 1.29-1.30x step in bytes on flowers and playbot (1.31-1.39x on the SH0 scenes). Per plane (flowers, B/splat)
    # the two differ in colour (BC7 0.82, norm8x4 2.92) and scales (norm565 1.59, norm8x4 2.89), and the colour buys
    # the PSNR: very-low with norm8x4 colour 11.63 B at 37.68 dB, with norm8x4 scales 10.70 B at 35.15 (very-low
    # 9.70 B at 35.06, low 12.63 B at 37.83). G chosen on flowers (63: 10.79 B, 37.64 dB; 95: 11.00, 37.66; 127:
    # 11.16, 37.67; 255: 11.53, 37.68; the geometric middle 11.07 B), checked on playbot, fruit_drops, lod_tile and
    # the eleven SH0 scenes (BENCHMARKS.md, "The hole between very-low and low").
    "very-low-rgb127": {"position": "norm8x4", "rotation": "cube565", "scale": "norm565", "color": "norm8x4",
                        "sh": "norm565"},
    # Not the seed's very-low (BC7 for position, rotation and scale): BC7 scales ruined the picture. Packed 16-bit
    # scales and rotations do far better at fewer bytes, and the codebook keeps all three SH bands for less
    # (BENCHMARKS.md, "Figures behind library defaults").
    "very-low": {"position": "norm8x4", "rotation": "cube565", "scale": "norm565", "color": "bc7", "sh": "norm565"},
}
# Presets whose SH bands go through a scene-wide codebook (vq.py: "auto" about one entry per 64 splats, "fine" one
# per 16, at least 256, at most 16,384 below 1M splats, "large" one per 8, 256..65,536).
PRESET_SH_CODEBOOK: dict[str, str] = {"low-plus-10bit-cb8": "large",
                                      "medium-low": "fine", "medium-low-12bit": "fine", "medium-low-palette": "fine",
                                      "medium-low-9bit": "fine",
                                      "low-plus-9bit": "auto", "low-plus": "auto", "low": "auto",
                                      "very-low-rgb127": "auto", "very-low": "auto"}
# Tile-wide quantisation steps (format/steps.py, format.md 4.3.1): levels of the tile's median chunk per component,
# the first `shared` components on one step. Per-chunk grids give a chunk of widely spread values a coarse step and a
# tight chunk a fine one; one step per tile spends the bits where values spread. On donut one step for positions
# (over the three axes), log scales (over the three axes) and SH0 R, G, B each gained 0.2-0.3 dB against per-axis
# steps, and the three together about 0.3 B/splat against per-chunk grids at the same PSNR.
# SH bands on importance-scaled steps (issue 32; format.md 4.3.1): each band's step is its tile's median chunk extent /
# G, scaled per chunk by (median importance / the chunk's) ** 0.5, importance = opacity x footprint (the codebook's
# weight). On flowers (SH2) the SH-only PSNR against bytes of the SH planes: G = 8: 48.8 dB at 8.2 B/splat, 16: 54.8
# at 10.0, norm565 without steps 61.9 at 12.6, norm11 at G = 63: 67.1 at 15.4, 127: 73.1 at 18.3 (bench/results/
# sh_coding_probe.md); at equal bytes the importance scaling gains about 0.8 dB over a plain tile step.
SH_IMPORTANCE = 0.5


def sh_steps(levels: float) -> dict[str, TileStep]:
    """The same importance-scaled step for SH bands 1..3."""
    return {f"sh{b}": TileStep((levels,) * 3, shared=1, importance=SH_IMPORTANCE) for b in (1, 2, 3)}


# low-plus-9bit-sh5's SH bands: one step per band plane (the median chunk extent over its coefficients and R, G, B /
# G), 0 on every chunk's grid, and importance exponent 0.4 (format.md 4.3.1). On flowers (4 views at 384 px,
# bench/sh_coding_probe.py) against per-coefficient steps at G = 5, exponent 0.5 (17.91 B, 43.92 dB): 0 on the grid
# 17.82 B, 44.20 dB; and one step per band 17.76 B, 44.37 dB; exponent 0.4 17.66 B, 44.61 dB; 0.3 17.55 B, 44.74 dB.
# The exponent was chosen on flowers and checked on fruit_drops (SH3, held out): 0.5 / 0.4 / 0.3 / 0.2 gave 21.36 /
# 21.17 / 21.07 / 20.89 B at 48.28 / 48.24 / 48.10 / 46.20 dB there, so 0.3 and not lower.
SH5_IMPORTANCE = 0.3


def sh_pooled_steps(levels: float, importance: float) -> dict[str, TileStep]:
    """One importance-scaled, zero-anchored step per SH band plane (TileStep.pooled, .zero)."""
    return {f"sh{b}": TileStep((levels,) * 3, shared=1, importance=importance, zero=True, pooled=True)
            for b in (1, 2, 3)}


PRESET_STEPS: dict[str, dict[str, TileStep]] = {
    # medium's log scales on one step per tile over the three axes, 1023 levels of the median chunk (issue 32, chosen
    # on guitar, whose compressed.ply point medium missed at 0.908): guitar 14.61 B/splat at 83.63 dB, 0.897 of
    # compressed.ply's bytes at +0.45 dB; held out on biker (the other compressed.ply input) 0.856 at +0.22 dB, and on
    # the 12 other real scenes 0.16-0.42 B/splat fewer for 0.01-0.23 dB (BENCHMARKS.md, "Guitar's near misses").
    "medium": {"scale": TileStep((1023.0,) * 3, shared=3)},
    "high-sh255": sh_steps(255.0),
    "medium-high": sh_steps(63.0),
    "medium-12bit": {"position": TileStep((4095.0,) * 3, shared=3)},
    "medium-low-sh16": sh_steps(16.0),
    "medium-low-sh8": sh_steps(8.0),
    "medium-low-12bit": {"position": TileStep((4095.0,) * 3, shared=3), "scale": TileStep((180.0,) * 3, shared=3),
                         "color": TileStep((255.0, 255.0, 255.0, 55.0), shared=3)},
    # the median chunk gets 120 x its extent / the tile's median splat size levels, at most 4095 (TileStep.per_size):
    # every K from 96 to 144 met SOG's point on all seven statues held out, K = 120 worst +1.01 dB at 0.892 of its
    # bytes (BENCHMARKS.md, "A position step from the splats' size").
    "medium-low-palette": {"position": TileStep((4095.0,) * 3, shared=3, per_size=120.0)},
    "medium-low-9bit": {"scale": TileStep((200.0,) * 3, shared=3),
                        "color": TileStep((255.0, 255.0, 255.0, 55.0), shared=3)},
    "low-plus-9bit": {"position": TileStep((400.0,) * 3, shared=3), "scale": TileStep((200.0,) * 3, shared=3),
                      "color": TileStep((255.0, 255.0, 255.0, 55.0), shared=3)},
    "low-plus-9bit-sh6": {"position": TileStep((400.0,) * 3, shared=3), "scale": TileStep((200.0,) * 3, shared=3),
                          "color": TileStep((255.0, 255.0, 255.0, 55.0), shared=3), **sh_steps(6.0)},
    "low-plus-9bit-sh5": {"position": TileStep((400.0,) * 3, shared=3), "scale": TileStep((200.0,) * 3, shared=3),
                          "color": TileStep((255.0, 255.0, 255.0, 55.0), shared=3),
                          **sh_pooled_steps(5.0, SH5_IMPORTANCE)},
    "low-plus-10bit-cb8": {"position": TileStep((1023.0,) * 3, shared=3), "scale": TileStep((200.0,) * 3, shared=3),
                           "color": TileStep((255.0, 255.0, 255.0, 55.0), shared=3)},
    "very-low-rgb127": {"color": TileStep((127.0, 127.0, 127.0, 55.0), shared=3)},
}
# zstd level per preset where it is not the encoder's default (DEFAULT_ZSTD_LEVEL, 1; `--zstd-level` overrides
# both): a higher level where its small gain puts a preset under 0.90 of SOG's bytes on a real scene, for a little
# more encode time; low-plus and low gained nothing, and medium keeps level 1 for its encode speed
# (bench/results/pos9_levels_*; BENCHMARKS.md, "Figures behind library defaults"). very-high takes level 12 for its
# decode: its float byte planes at level 12 are 1.2-1.6 % smaller and zstd reads them 8-15 % faster than at level 1,
# where levels 16 and 19 read as slowly as level 1 (issue 32; BENCHMARKS.md, "Decode speed", vhdec).
# high, medium-low-sh8 and medium-low-sh16 take level 12 with a shortest match of 6 (PRESET_ZSTD_MIN_MATCH) for
# their decode: 0.4-4 % fewer bytes than level 1 on the real scenes and, with their parts joined within 2 %, zstd reads
# them 10-20 % faster (issue 32; BENCHMARKS.md, "Decode speed", lossydec). medium-high took high's settings two rounds
# later (tidy32): on SH0 scenes its planes are high's, and at level 1 its files were 0.4 % larger than high's there.
# high-sh255 (hole32) takes them from the start, for the same reason. On a scene without SH bands a per-splat SH preset
# takes its base's level, shortest match and slacks (PRESET_SH_BASE, compression_preset).
PRESET_ZSTD_LEVEL: dict[str, int] = {"very-high": 12, "medium-low": 9, "medium-low-12bit": 16, "medium-low-palette": 16,
                                     "medium-low-9bit": 16,
                                     "low-plus-9bit": 16, "low-plus-9bit-sh6": 16,
                                     "low-plus-9bit-sh5": 16, "low-plus-10bit-cb8": 16,
                                     "high": 12, "high-sh255": 12, "medium-high": 12, "medium-low-sh8": 12,
                                     "medium-low-sh16": 12}
# zstd's shortest match per preset where not its level's own (3 at level 16, 4-5 at 12 on payloads this small; 0:
# the level's). On the lossy presets' small LOD payloads the short matches cost more bytes than the literals they
# replace, and each is a sequence more to decode: at level 16 a shortest match of 6 stores 0.05-1.6 % fewer bytes on
# every real scene measured and zstd reads them 5-12 % faster; the bytes it saves pay for joining more parts into a
# block (PRESET_BLOCK_SLACK), which reads faster again (issue 32; BENCHMARKS.md, "Decode speed", lossydec).
# `--zstd-level` leaves it (and the slack) in place: they are the preset's, as its planes are.
# medium-low-9bit and low-plus-10bit-cb8 (level 16) took the same the round after (eval32), with a 1 % slack: on all 14
# real scenes 0.06-1.3 % fewer bytes, zstd 0.75-0.94 and the whole `verified` pass 0.86-0.97 of the time (a 2 % slack
# grew them by up to 1.1 %: BENCHMARKS.md, "Decode speed", eval32).
_LOSSY_MIN_MATCH = ("high", "high-sh255", "medium-high", "medium-low-sh8", "medium-low-sh16", "medium-low-12bit",
                    "medium-low-palette", "medium-low-9bit", "low-plus-9bit", "low-plus-9bit-sh6", "low-plus-9bit-sh5",
                    "low-plus-10bit-cb8")
PRESET_ZSTD_MIN_MATCH: dict[str, int] = dict.fromkeys(_LOSSY_MIN_MATCH, 6)
# How much larger (a fraction) a small payload's zstd block may code, at the trial level, than its parts alone and
# still be one block (container._block_ends), per preset where not 0. very-high's float byte planes cut into blocks
# of a few KB, each with its tables, made zstd read them at about 1.1 GB/s: joined within 3 %, zstd reads them in
# 0.4-0.5 of the time, with level 12 in 0.9-1.7 % more bytes than level 1 without a slack (issue 32: decode speed;
# BENCHMARKS.md, "Decode speed", vhdec).
# The lossy presets of PRESET_ZSTD_MIN_MATCH join within 1 % (level 16) or 2 % (level 12): what their shortest match
# saved, less than it, so that their payloads still take fewer bytes than before on every real scene measured.
PRESET_BLOCK_SLACK: dict[str, float] = {"very-high": 0.035, "high": 0.02, "high-sh255": 0.02, "medium-high": 0.02,
                                        "medium-low-sh8": 0.02, "medium-low-sh16": 0.02, "medium-low-12bit": 0.01,
                                        "medium-low-palette": 0.01,
                                        "medium-low-9bit": 0.01, "low-plus-9bit": 0.01, "low-plus-9bit-sh6": 0.01,
                                        "low-plus-9bit-sh5": 0.01, "low-plus-10bit-cb8": 0.01}
# How much larger a small payload's zstd frame may be as one block than with the blocks PRESET_BLOCK_SLACK joins, and
# still be stored as one block (container.write_payload), per preset where not 0. very-high: with its parts joined
# within 3.5 % and a payload as one block where that costs at most 1 % more, zstd reads guitar's and
# winter_fountain's LOD trees in 0.75-0.85 of the time of a 3 % slack alone, for 0.4-0.9 % more bytes (issue 32;
# BENCHMARKS.md, "Decode speed", vhdec2).
PRESET_ONE_BLOCK_SLACK: dict[str, float] = {"very-high": 0.01}
DEFAULT_PRESET = "medium"
# What each preset is for, in the words the CLI (`encode --help`, `info`) shows: disk bytes per splat (full detail,
# manifest included, no LOD) and mean PSNR over the 14 real-scene eval reports (bench/results/eval_real; SH3 is
# fruit_drops, SH2 flowers, SH0 the twelve others, lod_tile's all-zero SH3 bands counted as SH0). `python
# bench/preset_summary_ranges.py` prints the reports' ranges; tests/test_bench_preset_summary_ranges.py holds every
# "N B/splat at SHk" figure here to them (within 3 %).
PRESET_SUMMARY: dict[str, str] = {
    "very-high": "32-bit floats, near-lossless (renders identical to the input's, values within 2^-24 of their "
                 "chunk's range: not a bit-exact copy); about 179 B/splat at SH3, 40.7-43.3 at SH0",
    "high": "16-bit positions and colour; about 70.4 B/splat at SH3, 46.4 at SH2, 16.3-17.9 at SH0; 61-77 dB",
    "high-sh255": "high with 11-bit SH on importance-scaled steps of 255 levels (about 8 bits where it matters), "
                  "between medium-high and high; about 38.4 B/splat at SH2 (flowers, 62 dB), 55.5 at SH3 "
                  "(fruit_drops, 63.6 dB); high's files at SH0",
    "medium-high": "high with 11-bit SH on importance-scaled steps (about 6 bits where it matters); about 32.7 "
                   "B/splat at SH2 (flowers, 61 dB), 44.9 at SH3 (fruit_drops, 63 dB); high's files at SH0",
    "medium-12bit": "medium with about 12-bit positions (16-bit texels on one step per tile); about 13.7-15.2 "
                    "B/splat at SH0 (statue scans 63.7-68.1 dB, 3.7-5.9 dB over medium), 27.5 at SH2, 36.9 at SH3",
    "medium": "the default: 11-bit positions, 8-bit colour, 16-bit SH, scales on a tile step; about 36.6 B/splat "
              "at SH3, 27.1 at SH2, 13.2-14.8 at SH0; 56-84 dB",
    "medium-low-sh16": "medium-low with per-splat SH bands (no codebook) on importance-scaled steps of about 4 bits; "
                       "about 23.1 B/splat at SH2 (flowers, 53.1 dB), 29 at SH3, 12.1-13.1 at SH0",
    "medium-low-sh8": "medium-low with per-splat SH bands on importance-scaled steps of about 3 bits; about 21 "
                      "B/splat at SH2 (flowers, 48.1 dB), 26 at SH3, 12.1-13.1 at SH0",
    "medium-low": "medium's positions, 8-bit rotations (half turns, or cube8x4 where that measures closer to the "
                  "input) and scales, SH codebook (about 1 entry per 16 splats); about 15.1 B/splat at SH3, 15.2 at "
                  "SH2, 12.2-13.1 at SH0; 42-74 dB",
    "medium-low-12bit": "medium-low with about 12-bit positions (16-bit texels on one step per tile), coarser "
                        "scales and opacity, zstd level 16; about 14.3 B/splat at SH3, 15 at SH2, 11.9-12.7 at "
                        "SH0; 42-70 dB",
    "medium-low-palette": "medium-low-12bit for SOG inputs: scale and colour palettes (SH0's merged pairwise), "
                          "positions on a step of the splat size / 120, keyed transport; medium-low-12bit's planes "
                          "where the values do not fit a palette; statue scans (SOG, SH0) 11-11.3 B/splat, "
                          "60-66 dB; other inputs as medium-low-12bit (0-0.7 B/splat fewer: keyed)",
    "medium-low-9bit": "medium-low with 9-bit positions, scales and opacity on tile steps, zstd level 16; about "
                       "13.6 B/splat at SH3, 14.1 at SH2, 11.2-11.9 at SH0; 42-62 dB",
    "low-plus-9bit": "low-plus with 9-bit positions on one step per tile, coarser scales and opacity, zstd level "
                     "16; about 12 B/splat at SH3, 13.4 at SH2, 10.6-11.4 at SH0; 41-61 dB",
    "low-plus-9bit-sh6": "low-plus-9bit with per-splat SH bands (no codebook) on importance-scaled steps of about "
                         "2.5 bits; about 18.2 B/splat at SH2 (flowers, 44.7 dB), 22 at SH3, 10.6-11.4 at SH0",
    "low-plus-9bit-sh5": "low-plus-9bit-sh6 with one SH step per band, 0 on its grid and a flatter importance "
                         "scaling, about 2.3 bits; about 17.3 B/splat at SH2 (flowers, 44.2 dB), 20.4 at SH3, "
                         "10.6-11.4 at SH0",
    "low-plus-10bit-cb8": "low-plus-9bit with 10-bit positions (keyed transport) and a larger SH codebook (about "
                          "1 entry per 8 splats, up to 65,536); about 15.3 B/splat at SH2 (flowers, 45.1 dB), 14.5 "
                          "at SH3 (fruit_drops, 48.8 dB)",
    "low-plus": "8-bit positions, rotations (half turns, or cube8x4 where that measures closer to the input), "
                "scales and colour, SH codebook (1 per 64); about 12.7 B/splat at SH3, 13.7 at SH2, 11-11.9 at SH0; "
                "40-60 dB",
    "low": "low-plus with 16-bit rotations (cube565); about 11.7 B/splat at SH3, 12.6 at SH2, 10.1-10.9 at SH0; "
           "40-57 dB",
    "very-low-rgb127": "very-low with 8-bit colour (low's norm8x4, not BC7) on a tile step of 127 levels, "
                       "between very-low and low; about 10.0 B/splat at SH3, 11.1 at SH2, 8.8-9.2 at SH0; 38-56 dB",
    "very-low": "16-bit scales and rotations (cube565), BC7 colour, SH codebook; about 9.4 B/splat at SH3, 9.7 at "
                "SH2, 7.7-8.0 at SH0; 33-48 dB",
}
CHUNK_ORDERS = ("auto", "morton", "luminance")


def resolve_formats(preset: str, overrides: dict[str, str] | None = None) -> dict[str, str]:
    """Texel format per attribute of a preset with per-attribute overrides, checked."""
    if preset not in PRESETS:
        raise UsageError(f"unknown preset {preset!r} (choose one of {', '.join(PRESETS)})")
    formats = dict(PRESETS[preset])
    for attr, fmt in (overrides or {}).items():
        if attr not in ATTRIBUTES:
            raise UsageError(f"unknown attribute {attr!r} in a format override (expected one of "
                             f"{', '.join(ATTRIBUTES)})")
        get_format(fmt)
        if fmt not in VALUE_FORMATS:
            raise UsageError(f"{fmt} holds codebook indices, not attribute values (choose one of "
                             f"{', '.join(VALUE_FORMATS)})")
        if attr == "color" and FORMATS[fmt].components < 4:
            raise UsageError(f"color holds SH0 and opacity and needs a 4-component format; {fmt} has 3 "
                             f"(use one of {', '.join(n for n, f in FORMATS.items() if f.components == 4)})")
        if fmt in PALETTE_FORMATS and attr not in PALETTE_ATTRIBUTES:
            raise UsageError(f"{fmt} (palette indices, format.md 4.3.2) holds only {' and '.join(PALETTE_ATTRIBUTES)}, "
                             f"not {attr}")
        if fmt in ROTATION_ONLY_FORMATS and attr != "rotation":
            raise UsageError(f"{fmt} (quaternions in the cube gauge, format.md 4.5) holds only rotation, not {attr}")
        formats[attr] = fmt
    return formats


def preset_steps(preset: str, overrides: dict[str, str] | None = None) -> dict[str, TileStep]:
    """The preset's tile steps, for the attributes whose format `overrides` leaves as the preset's."""
    formats = PRESETS.get(preset, {})
    return {key: step for key, step in PRESET_STEPS.get(preset, {}).items()
            if (overrides or {}).get(step_attribute(key), formats[step_attribute(key)]) == formats[step_attribute(key)]}


def step_attribute(key: str) -> str:
    """The attribute whose format a PRESET_STEPS key follows: the key itself, or `sh` for a band plane `sh1`..`sh3`
    (SH bands may each have their own step)."""
    return "sh" if key in ("sh1", "sh2", "sh3") else key


# The transport a preset's payloads are written with when none is given (format/transport.py TRANSPORTS); "fields"
# for every preset not named here. `keyed` (morton1 positions, format.md 5.4) measured 0.3 B/splat smaller on the
# statue scans and about 10 % slower to decode (BENCHMARKS.md, issue 32); medium-low-palette uses it, and
# low-plus-10bit-cb8 (0.32-0.36 B/splat on flowers and playbot, spent on its positions' 1023 levels).
PRESET_TRANSPORT: dict[str, str] = {"medium-low-palette": "keyed", "low-plus-10bit-cb8": "keyed"}


# Presets that store attributes as palette indices (pal8x4, format.md 4.3.2) only where the scene's values fit the
# palettes (at most 256 distinct values in each: exact), with the preset they fall back to: an attribute whose
# values do not fit takes the fallback preset's format and tile step, and positions then take its position step too
# (the size-relative step was chosen on palette inputs; on donut, not one, it loses SOG's point). encode/plan.py
# plan_palettes.
PRESET_PALETTE_FALLBACK: dict[str, str] = {"medium-low-palette": "medium-low-12bit"}
# Scene palettes a preset merges pairwise before any tile is encoded (codec.merged_pairs: the least and largest
# distinct values kept, the ones between merged two by two into their midpoint, 256 -> 129): plane -> palette
# indices (color 0: SH0 R, G, B; 1: opacity; scale 0). An encoder choice: the file stores the merged palette as any.
# On the statue scans SH0's merged palette cost about 0.3 dB for about 0.35 B/splat (BENCHMARKS.md, "A position step
# from the splats' size").
PRESET_PALETTE_MERGE: dict[str, dict[str, tuple[int, ...]]] = {"medium-low-palette": {"color": (0,)}}


def palette_fallback(preset: str, overrides: dict[str, str] | None, unfit: set[str],
                     formats: dict[str, str] | None = None) -> tuple[dict[str, str], dict[str, TileStep], list[str]]:
    """The formats and tile steps of `preset` (with `overrides`; `formats`: resolve_formats' already) once the
    palette attributes in `unfit` (their values exceed a palette) fall back (PRESET_PALETTE_FALLBACK); also the
    attributes that fell back. A preset without a fallback, or nothing unfit, keeps its own."""
    formats = dict(formats) if formats is not None else resolve_formats(preset, overrides)
    steps = preset_steps(preset, overrides)
    fallback = PRESET_PALETTE_FALLBACK.get(preset)
    fell = [a for a in ATTRIBUTES if a in unfit and a not in (overrides or {}) and formats[a] in PALETTE_FORMATS]
    if fallback is None or not fell:
        return formats, steps, []
    other = preset_steps(fallback)
    for attr in fell:
        formats[attr] = PRESETS[fallback][attr]
        steps.pop(attr, None)
        if attr in other:
            steps[attr] = other[attr]
    if "position" in steps and "position" not in (overrides or {}):
        steps.pop("position")
        if "position" in other and formats["position"] == PRESETS[fallback]["position"]:
            steps["position"] = other["position"]
    return formats, steps, fell


def preset_transport(preset: str, default: str) -> str:
    """The transport an encode of `preset` uses when none is given (`default`: the encoder's)."""
    return PRESET_TRANSPORT.get(preset, default)


# The per-splat SH presets and their bases: the same planes but the SH bands'. On a scene without SH bands (SH degree
# 0 as read, or kept by --sh-degree 0) a variant writes its base's planes, and it takes its base's zstd settings too
# (level, shortest match, block slacks: compression_preset), so it writes its base's bytes, as the README's preset
# table says ("= medium-low (no SH bands)"): medium-low-sh16 and -sh8 took level 12 with a shortest match of 6 where
# medium-low takes level 9, 0.4 % more bytes on SH0 scenes (newuser63). A scene with SH bands is untouched.
PRESET_SH_BASE: dict[str, str] = {"high-sh255": "high", "medium-high": "high", "medium-low-sh16": "medium-low",
                                  "medium-low-sh8": "medium-low", "low-plus-9bit-sh6": "low-plus-9bit",
                                  "low-plus-9bit-sh5": "low-plus-9bit"}


def compression_preset(preset: str, sh_degree: int) -> str:
    """The preset whose zstd settings (level, shortest match, block slacks) an encode of `preset` keeping
    `sh_degree` SH bands takes: its base (PRESET_SH_BASE) where it keeps none, else itself."""
    return PRESET_SH_BASE.get(preset, preset) if sh_degree == 0 else preset


def preset_zstd_level(preset: str, default: int) -> int:
    """The zstd level an encode of `preset` uses when none is given (`default`: the encoder's)."""
    return PRESET_ZSTD_LEVEL.get(preset, default)


def preset_zstd_min_match(preset: str) -> int:
    """zstd's shortest match for the preset's payloads (PRESET_ZSTD_MIN_MATCH), 0 for its level's own."""
    return PRESET_ZSTD_MIN_MATCH.get(preset, 0)


def preset_block_slack(preset: str) -> float:
    """How much larger a joined zstd block of `preset`'s small payloads may code (container._block_ends)."""
    return PRESET_BLOCK_SLACK.get(preset, 0.0)


# Presets whose encoder stores each splat's rotation as the one of its equivalent (rotation, scales) pairs closest to
# the identity (rotation_canon.canonical_gauge; format.md 4.5): the same covariances, a decoder sees nothing new
# (issue 32, rot32; BENCHMARKS.md, "Rotations in a canonical gauge"). "cube" (of all 24, the scales permuted) for the
# xyz rotations (norm565), whose w, derived from x, y, z, was coarse where it is small: there it is at least 0.85,
# +0.15 to +3.8 dB with 1-4 % fewer bytes on 13 of 14 scenes measured (fruit -0.17 dB); "half-turns" (of 1, i, j, k:
# the same components in another order, the scales kept, so the same picture) for every smallest-three preset
# (norm10_2, norm8x4), whose largest-component index is then constant: medium and medium-low in rot32, the others in
# evalrefresh32 (bench/rot_halfturn_bytes.py on all 16 real scenes: fewer bytes on 15 of 16 for the norm10_2
# presets, at most +0.18 % on guitar, a compressed PLY; on all 16 for the norm8x4 ones; BENCHMARKS.md, "Half turns
# for every smallest-three preset"). The cube's mixing of components moves a rotation off another tool's 8- or 10-bit
# grid (a SOG's, a compressed PLY's), which cost smallest-three presets up to 2.2 dB there. Only where the rotation
# is quantised (a float rotation is stored as given); palette scales could take the cube too: one palette holds the
# three axes (PALETTE_GROUPS).
# Since format 1.13 (rotrange32) the cube presets store their rotations as cube565, the gauge's x, y, z over its range
# [-tan(pi/8), tan(pi/8)] instead of [-1, 1] (2.4x finer; format.md 4.5): at eval's 8 views of 512 px, chosen on
# fruit_drops, guitar and statue-massa (low +5.1 to +5.7 dB, very-low-rgb127 +2.1 to +4.4, very-low +1.1 to +2.1, for
# 2.2-6.4 % more bytes) and held out on the 13 other real scenes (BENCHMARKS.md, "Rotations over the gauge's range").
PRESET_ROTATION_GAUGE: dict[str, str] = {
    "low": "cube", "very-low-rgb127": "cube", "very-low": "cube",
    **dict.fromkeys(("high", "high-sh255", "medium-high", "medium-12bit", "medium", "medium-low-sh16", "medium-low-sh8",
                     "low-plus-9bit-sh6", "low-plus-9bit-sh5", "low-plus-10bit-cb8", "medium-low", "medium-low-9bit",
                     "medium-low-12bit", "medium-low-palette", "low-plus-9bit", "low-plus"), "half-turns")}


# Presets whose encoder measures more than one rotation format on the scene and keeps the one closest to the input
# (encode/plan.plan_rotation_format: the mean angle between each splat's rotation and its stored one, over the scene
# sample's rotations; the first, the preset's own in PRESETS, on a tie), unless the rotation format is given. For
# medium-low (issue 32, cube32): its half turns (norm8x4, smallest three) keep a rotation that lies on an 8-bit
# smallest-three grid (a SOG file's) exactly, where the cube in cube8x4 (format 1.14: the gauge's x, y, z over its
# range, 1.7x finer) moves it off (-0.48 dB on the statues); off any such grid (PLY, .splat, a compressed PLY's 10
# bits) cube8x4 is the closer, +0.2 to +2.9 dB (bench/rot_range_probe.py, rotrange32). The measure decides where the
# input lies without a test for grids: chosen on fruit_drops and guitar, held out on the 14 other real scenes
# (BENCHMARKS.md, "medium-low's rotations over the cube gauge's range").
# medium-low-sh16 and medium-low-sh8 (issue 32, shvariants32) are medium-low's planes with per-splat SH bands, so
# their rotations are the same question and take the same measure.
# Of the other half-turn norm8x4 presets (issue 32, cube8x4all32), which store the same rotations in the same
# texels beside other positions, scales and SH (so the measure, reading only the rotations, chooses for them what it
# chooses for medium-low), a rule written before the held-out rows were read admitted those whose PSNR rose on both
# choice scenes (fruit_drops, guitar) at most 3 % more bytes, keeping their ladder places: medium-low-12bit (+0.26 /
# +1.49 dB), medium-low-palette (the same) and low-plus (+0.62 / +0.18 dB), each at +0.2-0.3 % bytes. The 9- and
# 10-bit ones (medium-low-9bit, low-plus-9bit, -sh6, -sh5, low-plus-10bit-cb8) lost 0.21-0.53 dB on fruit_drops
# with cube8x4 (though its covariances were closer there too) and keep the half turns (BENCHMARKS.md, "The other
# half-turn presets measure cube8x4 too").
PRESET_ROTATION_CHOICES: dict[str, tuple[str, ...]] = dict.fromkeys(
    ("medium-low", "medium-low-sh16", "medium-low-sh8", "medium-low-12bit", "medium-low-palette", "low-plus"),
    ("norm8x4", "cube8x4"))


def rotation_choices(preset: str, overrides: dict[str, str] | None = None) -> tuple[str, ...]:
    """The rotation formats the encoder measures for `preset` (PRESET_ROTATION_CHOICES), the preset's own first;
    none where the rotation format is given (`--rotation`) or the preset has one only."""
    if overrides and "rotation" in overrides:
        return ()
    return PRESET_ROTATION_CHOICES.get(preset, ())


def rotation_gauge(preset: str, formats: dict[str, str]) -> str | None:
    """The canonical gauge `preset`'s encoder picks with these formats (PRESET_ROTATION_GAUGE), None for none: none
    for float rotations (stored as given)."""
    fmt = get_format(formats["rotation"])
    if fmt.levels[0] == 0:
        return None
    if fmt.rotation_range != 1.0:  # the format holds only the gauge's range (cube565, cube8x4, format.md 4.5)
        return "cube"
    return PRESET_ROTATION_GAUGE.get(preset)


def preset_one_block_slack(preset: str) -> float:
    """How much larger `preset`'s small payloads may be stored as one zstd block (container.write_payload)."""
    return PRESET_ONE_BLOCK_SLACK.get(preset, 0.0)


def resolve_chunk_order(chunk_order: str, formats: dict[str, str]) -> str:
    """In-chunk order: luminance groups similar colours into the same 4x4 BC block (on fruit_drops, BC7 colour
    went from 34.1 to 41.1 dB PSNR), but BC-compressed positions need spatially coherent blocks instead."""
    if chunk_order not in CHUNK_ORDERS:
        raise UsageError(f"unknown chunk order {chunk_order!r} (expected one of {', '.join(CHUNK_ORDERS)})")
    if chunk_order != "auto":
        return chunk_order
    bc = {a for a, f in formats.items() if get_format(f).block > 1}
    return "luminance" if bc & {"color", "sh"} and not bc & {"position", "rotation", "scale"} else "morton"
