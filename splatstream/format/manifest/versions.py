"""Format versions: what this code reads, and what a writer writes a scene as (format.md, version history)."""
from __future__ import annotations

from collections.abc import Mapping

FORMAT_NAME = "splatstream"
FORMAT_VERSION = (1, 16)  # (major, minor) this code reads; what it writes: writer_version
# Version 1.2 added two things (format.md, version history): the manifest's last key `checksum`, the SHA-256 of the
# file with that value's 64 bytes read as ASCII '0' (format.md 6, "Checksum"), so a flipped byte in the manifest is
# caught like one in a payload; and the `fields1` transport coding of texels sections (format.md 5.2).
CHECKSUM_VERSION = (1, 2)
# Version 1.3 added the texel formats norm16x4 and norm9x3 (format.md 4.2). Like the 1.1 codebook it is written only
# by scenes that use them, so every other scene stays 1.2 and readers of 1.2 keep reading it.
VERSION_1_3 = (1, 3)
FORMATS_1_3 = ("norm16x4", "norm9x3")
# Version 1.4 added the chunk order `input` (format.md 3): a one-tile scene whose splats keep the order of an input
# that was already cut into quantised chunks of 256 (compressed.ply), so its chunks, and their grids, are the input's.
VERSION_1_4 = (1, 4)
CHUNK_ORDERS_1_4 = ("input",)
# Version 1.5 added manifest pages (format.md 6.1): written only by a paged scene (a tree too large for one manifest
# before the first frame), so every other scene keeps its version.
VERSION_1_5 = (1, 5)
# Version 1.6 added palette planes (format.md 4.3.2: the texel format pal8x4, 8-bit indices into the tile's 256-entry
# palettes of log scales, SH0 and opacity), written only by scenes that use them.
VERSION_1_6 = (1, 6)
FORMATS_1_6 = ("pal8x4",)
# Version 1.7 added scene palettes (format.md 4.3.2: the manifest key `palettes`, one set of palettes per pal8x4 plane
# for the whole scene, and pal8x4 payloads without their own palette section), written only by scenes that hold them.
VERSION_1_7 = (1, 7)
# Version 1.13 added the rotation format cube565 (format.md 4.5): norm565's texels holding x, y, z of a quaternion in
# the cube gauge (|x|, |y|, |z| <= tan(pi/8) w) over that range instead of [-1, 1], 2.4x finer (issue 32, rotrange32).
# Written only by scenes with such a plane; a 1.0-1.12 reader rejects the manifest naming the unknown texel format,
# so it fails cleanly and misreads nothing (a manifest key saying "ranged" would be ignored by them: wrong rotations).
VERSION_1_13 = (1, 13)
FORMATS_1_13 = ("cube565",)
# Version 1.14 added the rotation format cube8x4 (format.md 4.5): norm8x4's texels holding x, y, z of a cube-gauge
# quaternion over [-tan(pi/8), tan(pi/8)] (w derived), 1.7x finer than smallest three's 8 bits; medium-low's where the
# encoder measures it closer to the input's rotations than the half turns (issue 32, cube32). Written only by scenes
# with such a plane; a 1.0-1.13 reader rejects the manifest naming the unknown texel format, as for cube565.
VERSION_1_14 = (1, 14)
FORMATS_1_14 = ("cube8x4",)


def writer_version(formats: Mapping[str, str], codebook_format: str | None = None,
                   chunk_order: str = "morton") -> tuple[int, int]:
    """The version a writer writes a scene of these texel formats and chunk order as: 1.14 with a cube8x4 rotation
    plane, 1.13 with a cube565 one, 1.6 with a palette plane, 1.4 in the chunk order `input`, 1.3 with a norm16x4 or
    norm9x3 plane (or SH codebook), 1.2 otherwise (every scene carries the 1.2 manifest checksum)."""
    if set(formats.values()) & set(FORMATS_1_14):
        return VERSION_1_14
    if set(formats.values()) & set(FORMATS_1_13):
        return VERSION_1_13
    if set(formats.values()) & set(FORMATS_1_6):
        return VERSION_1_6
    if chunk_order in CHUNK_ORDERS_1_4:
        return VERSION_1_4
    used = set(formats.values()) | ({codebook_format} if codebook_format else set())
    return VERSION_1_3 if used & set(FORMATS_1_3) else CHECKSUM_VERSION
# Version 1.8 added the tile table (format.md 6.2): a manifest's or a page's tiles column-wise, payload entries as a
# scene-level list of section layouts plus each section's size and the raw SHA-256, about a fifth of the tile maps'
# bytes; written by every scene of more than one tile (an LOD tree), so one-tile scenes keep their version.
VERSION_1_8 = (1, 8)
# Version 1.9 added the LOD tree's build record (format.md 6, lod.md 6): the `lod` map's optional `merge` and
# `viewing_scale_px`, how the encoder grouped each level's splats and at which screen-space errors it matched opacity
# and colour; written by every scene whose tree splatstream built (an imported tree, and a one-tile scene, keep
# their version). A key added to a known version is damage to its readers (format.md 6, Versioning), so the record
# needs the new minor version; a 1.8 reader reads a 1.9 scene whole and ignores the two keys.
VERSION_1_9 = (1, 9)
# Version 1.10 added `lod.viewing_scale_levels_px` (format.md 6, lod.md 6 step 5): the viewing scale per level from the
# first merged one, the last on every level above, for a scale that grows with the level (which 1.9's two-number
# `viewing_scale_px` cannot say). Written instead of `viewing_scale_px` by such trees only: a 1.9 reader ignores the
# key (a newer minor version's) and says the scales are not recorded; a longer `viewing_scale_px` it would reject.
VERSION_1_10 = (1, 10)
# Version 1.11 added the refinement record (format.md 6, lod.md 6): the `lod` map's optional `refinement`, how the
# merged levels were refined against renders of the full detail after the tree was built (`encode --lod-refine`);
# written only by such scenes (every other scene keeps its version, byte for byte). A 1.8 to 1.10 reader reads a 1.11
# scene whole and ignores the key. (1.10 is branch farpx31's `lod.viewing_scale_levels_px`, merged into main while
# this branch was open: on this branch alone 1.10 adds nothing.)
VERSION_1_11 = (1, 11)
# Version 1.12 added the compact tile table (format.md 6.2): `tile_table_zstd`, the tile table with its bounds as f32
# rounded outward, msgpack-packed and zstd-compressed, in place of `tile_table`; written by every tree splatstream
# encodes (its pages too). A 45-100k-splat scene's manifest went from 35-41 KB to 12-13 KB, which at a 2 % budget was
# most of what a view read (issue 31). A 1.8 to 1.11 reader rejects it naming the missing `tiles` (it knows neither
# key of a newer minor version): it fails cleanly and misreads nothing.
VERSION_1_12 = (1, 12)
# Version 1.15 added short digests in the tile table (format.md 6.2, "Short digests"): a table names each payload and
# page by the first 16 bytes of its SHA-256 (the columns `digest16` and `page.digest16`, in place of the 32-byte
# `sha256` ones), its file `data/<32 hex>.bin`, and a reader checks the payload's SHA-256 against that prefix. 128 bits
# stay collision- and preimage-safe for content addressing; the 32-byte column was about half a compact table's bytes
# (issue 31, branch digest31). Written by every tree splatstream encodes with the compact table (its pages too); a
# 1.8 to 1.14 reader rejects it naming the missing column (`tile_table.sha256: missing`): it misreads nothing.
VERSION_1_15 = (1, 15)
# Version 1.16 added boxes relative to the parent's in the compact tile table (format.md 6.2, "Boxes relative to the
# parent's"): a tile whose parent is a row of the same table stores its box as u8 steps of the parent's decoded box
# (`box8`), the others (a root manifest's root, a page's top tiles) as f32 (`anchor_box`), and every sphere's radius
# as u8 steps of its box's half diagonal (`radius8`, `radius_far` beyond them). Written by every tree splatstream
# encodes with the compact table and short digests (issue 31, branch box16); a 1.15 reader rejects it naming the
# missing column (`tile_table.box: missing`), as a 1.12-1.14 one does: it misreads nothing.
VERSION_1_16 = (1, 16)
