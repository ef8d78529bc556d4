"""Reduce: the manifest from the plan and every tile's entry (what the jobs returned, in any order)."""
from __future__ import annotations

import numpy as np

from .. import __version__
from ..format.keyed import MORTON1
from ..format.layout import CHUNK_SIZE
from ..format.manifest import (
    AttributeSize,
    CameraEntry,
    LodInfo,
    Manifest,
    PayloadEntry,
    SHCodebookEntry,
    TileEntry,
    writer_version,
)
from ..format.manifest.versions import VERSION_1_6, VERSION_1_7, VERSION_1_8, VERSION_1_9, VERSION_1_10, VERSION_1_11
from ..format.planes import BASE_PLANE_NAMES
from ..format.presets import ATTRIBUTES
from .plan import ScenePlan


def section_attribute(section_name: str) -> str:
    """The preset attribute a section's bytes count towards (`position.range` -> position, `sh2` -> sh)."""
    return "sh" if section_name.startswith("sh") else section_name.split(".")[0]


class _Sizes:
    """GPU and disk bytes of the full-detail scene per attribute: leaf tiles and the SH codebook."""

    def __init__(self) -> None:
        self.gpu = dict.fromkeys(ATTRIBUTES, 0)
        self.disk = dict.fromkeys(ATTRIBUTES, 0.0)
        self.leaf_gpu = 0
        self.leaf_disk = 0

    def add(self, entry: PayloadEntry, attributes: tuple[str, ...]) -> None:
        # GPU bytes exactly per section; a payload's file bytes shared out by the sections' raw sizes.
        for sec in entry.sections:
            attr = section_attribute(sec.name)
            if attr in attributes:
                self.gpu[attr] += sec.gpu_size
                self.disk[attr] += entry.bytes * sec.size / max(1, entry.raw_bytes)
        self.leaf_gpu += entry.gpu_bytes
        self.leaf_disk += entry.bytes


def _version(ctx, codebook: SHCodebookEntry | None, tiles: list[TileEntry], lod: LodInfo) -> tuple[int, int]:
    """The formats' and chunk order's version (writer_version), 1.6 where a section is stored as morton1 (format.md
    5.4: the encoder chooses it per section, so only the entries tell); 1.9 where the manifest records how the LOD
    tree was built."""
    version = writer_version(ctx.formats, codebook.format if codebook is not None else None, ctx.chunk_order)
    keyed = any(s.filter == MORTON1 for t in tiles for e in t.groups.values() for s in e.sections)
    if ctx.palettes:  # scene palettes in the manifest (format.md 4.3.2)
        version = max(version, VERSION_1_7)
    elif keyed:
        version = max(version, VERSION_1_6)
    # An LOD tree's tiles as the tile table (format.md 6.2, 1.8): a fifth of the tile maps' bytes. A one-tile scene's
    # map is under a kilobyte, and its version stays the one its formats need.
    if len(tiles) > 1:
        version = max(version, VERSION_1_8)
    # The tree's build record (format.md 6, lod.md 6: lod.merge, lod.viewing_scale_px) is a 1.9 key; scales per
    # level (a scale growing with the level: lod.viewing_scale_levels_px) a 1.10 one.
    if lod.scales_need_1_10:
        version = max(version, VERSION_1_10)
    elif lod.build_recorded:
        version = max(version, VERSION_1_9)
    # The refinement record (encode --lod-refine: lod.refinement) is a 1.11 key; every other scene keeps its version.
    return max(version, VERSION_1_11) if lod.refinement is not None else version


def lod_info(scene: ScenePlan, tiles: int) -> LodInfo:
    """The manifest's `lod` map: a tree's build recorded where the encoder built it (scene.lod_merge); a one-tile
    scene has no merged level, so nothing to record."""
    tree = tiles > 1
    built = tree and scene.lod_merge is not None
    return LodInfo(tree, scene.max_leaf_splats, scene.reduction, "replace",
                   scene.lod_merge if built else None, scene.viewing_scale_px if built else None,
                   scene.lod_refinement if tree else None)


def build_manifest(scene: ScenePlan, camera: CameraEntry, tiles: list[TileEntry],
                   codebook: SHCodebookEntry | None) -> Manifest:
    """`tiles` in the plan's tile order (the per-attribute sums add up in that order); bytes_on_disk settled.

    Deterministic: the same plan and entries give the same bytes (`encode_seconds` is written as 0, format.md 6),
    so encodes of the same input with the same options, on one machine or many, give identical manifests."""
    ctx = scene.context
    sizes = _Sizes()
    if codebook is not None:
        for entry in codebook.groups.values():
            sizes.add(entry, ("sh",))
    for tile in tiles:
        if tile.is_leaf:
            for group, entry in tile.groups.items():
                sizes.add(entry, BASE_PLANE_NAMES if group == "base" else ("sh",))
    ordered = tuple(sorted(tiles, key=lambda t: t.id))
    root = ordered[0]
    lod = lod_info(scene, len(ordered))
    m = Manifest(
        # 1.2 (the manifest checksum), fields1 or not; 1.3 where a plane is norm16x4 or norm9x3 (format.md 9)
        version=_version(ctx, codebook, tiles, lod),
        generator=f"splatstream {__version__}",
        name=scene.name,
        splats=scene.splats,
        leaf_splats=sum(t.splats for t in ordered if t.is_leaf),
        sh_degree=ctx.sh_degree,
        preset=scene.preset,
        formats=dict(ctx.formats),
        chunk_size=CHUNK_SIZE,
        chunk_order=ctx.chunk_order,
        bounds=scene.bounds,
        extent_bounds=root.box,
        up=scene.up,
        camera=camera,
        sh_codebook=codebook,
        lod=lod,
        root=root.id,
        tiles=ordered,
        gpu_bytes=int(sizes.leaf_gpu),
        gpu_bytes_per_splat=sizes.leaf_gpu / scene.splats,
        leaf_bytes_on_disk=int(sizes.leaf_disk),
        attributes={a: AttributeSize(ctx.formats[a], int(sizes.gpu[a]), int(sizes.disk[a]))
                    for a in ATTRIBUTES if a != "sh" or ctx.sh_degree > 0},
        encode_seconds=0.0,
        palettes={name: np.ascontiguousarray(p, "<f4").tobytes() for name, p in ctx.palettes.items()}
        if ctx.palettes else None,
    )
    return m.with_bytes_on_disk(m.payload_bytes())
