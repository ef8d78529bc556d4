"""Per-tile jobs: a tile in, its payloads (written through a SceneWriter) and its manifest entry out.

Pure apart from the writer: the same tile and context give the same bytes on any machine, in any order, so a
pool of threads or a cluster of workers can run them and the result does not depend on who ran what.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..format.codec import EncodedPlane, encode_index_plane, encode_plane, plane_values
from ..format.container import write_payload
from ..format.keyed import MORTON_FORMATS, morton_keys
from ..format.layout import CHUNK_SIZE, chunk_texel_index, morton_order, order_within_chunks, texture_size
from ..format.manifest import Box, PayloadEntry, SHCodebookEntry, TileEntry
from ..format.names import payload_name
from ..format.planes import BASE_PLANES, SH_INDEX_FORMAT, band_of, band_plane, chunks_for, groups_for_degree
from ..format.steps import TileStep, splat_sizes
from ..gaussians import Gaussians
from ..lod import Tile, extent_bounds
from ..rotation_canon import canonical_gauge
from ..store import SceneWriter
from ..vq import Codebook
from .codebook import assign_sh_codebook, codebook_planes, codebook_weights
from .plan import TileContext

LUMINANCE = np.array([0.299, 0.587, 0.114], np.float32)


def splat_order(g: Gaussians, chunk_order: str) -> np.ndarray:
    """Order of a tile's splats: 3D Morton, then optionally re-sorted inside each chunk; `input`: as they came
    (format.md 3)."""
    if chunk_order == "input":
        return np.arange(len(g.positions))
    order = morton_order(g.positions)
    if chunk_order == "luminance":
        order = order_within_chunks(order, g.base_colors @ LUMINANCE)
    return order


def keyed_order(g: Gaussians, order: np.ndarray, ctx: TileContext) -> np.ndarray:
    """`order` with each chunk's splats re-sorted by the Morton key of their quantised position codes (the codes the
    position plane stores: same chunks, same ranges, same codes, in another order), so that the `morton1` coding
    (format.md 5.4) stores a chunk as sorted keys. Only with the transport `keyed`, where the position format has
    one (MORTON_FORMATS) and the chunk order is `morton`; otherwise `order` as it is."""
    fmt = ctx.formats["position"]
    if fmt not in MORTON_FORMATS or ctx.chunk_order != "morton" or ctx.transport != "keyed" or len(order) < 2:
        return order
    spec = BASE_PLANES[0]
    step = ctx.steps.get("position")
    plane = encode_plane(plane_values(g, spec), spec, fmt, order, step=step, sizes=step_splat_sizes(g, step))
    n = len(order)
    chunks = chunks_for(n)
    texels = np.frombuffer(plane.layers[0], "<u2").reshape(-1, 4)[chunk_texel_index(chunks, plane.width)[:n]]
    key = morton_keys(texels).astype(np.int64)  # 48 bits
    chunk = np.arange(n) // CHUNK_SIZE
    within = np.lexsort((np.arange(n), key, chunk))  # by chunk, then key, ties in the given order
    return order[within]


def step_splat_sizes(g: Gaussians, step: TileStep | None) -> np.ndarray | None:
    """The splats' sizes a size-relative step needs (TileStep.per_size), else None."""
    return splat_sizes(g.log_scales, step.size_axis) if step is not None and step.per_size else None


def tile_order(g: Gaussians, ctx: TileContext) -> np.ndarray:
    """The order a tile's splats are stored in: splat_order, then keyed_order."""
    return keyed_order(g, splat_order(g, ctx.chunk_order), ctx)


def tile_group_names(ctx: TileContext) -> list[str]:
    return groups_for_degree(ctx.sh_degree, ctx.codebook is not None)


def write_planes(planes: list[EncodedPlane], chunks: int, ctx: TileContext, writer: SceneWriter,
                 short_name: bool = False) -> PayloadEntry:
    """One payload written through `writer` under its final name (`short_name`: its short digest's, a 1.15 scene's
    tile payload, table.short_tile_names; else its whole SHA-256's), and its entry as the manifest holds it before
    Manifest.compacted (the whole SHA-256 and its name: a 1.8 table packs it, for `bytes_on_disk`)."""
    with writer.payload_file() as (f, finish):
        entry = write_payload(planes, f, chunks, level=ctx.zstd_level, transport=ctx.transport,
                              block_slack=ctx.block_slack, min_match=ctx.zstd_min_match,
                              one_block_slack=ctx.one_block_slack)
        f.flush()
        # named once, as the published manifest will name it: an object store's rename would be a copy and a delete
        finish(replace(entry, file=payload_name(entry.sha256, short_name)) if short_name else entry)
    return entry


def group_planes_of(g: Gaussians, order: np.ndarray, group: str, ctx: TileContext) -> list[EncodedPlane]:
    """The planes of one payload group of a tile (lazy: layers are quantised as the writer asks for them)."""
    if ctx.codebook is not None and group == "sh1":
        return [encode_index_plane(assign_sh_codebook(ctx.codebook, g), order)]
    specs = BASE_PLANES if group == "base" else (band_plane(band_of(group)),)
    if group == "base" and ctx.rotation_gauge:
        # The same covariances with rotations near the identity, which code smaller (rotation_canon.py). Only the
        # rotation and scale planes read the swapped values; every other plane and the order are the tile's own.
        rotations, log_scales = canonical_gauge(g.rotations, g.log_scales, ctx.rotation_gauge)
        g = replace(g, rotations=rotations, log_scales=log_scales)
    planes = []
    for s in specs:
        step = ctx.steps.get(s.name, ctx.steps.get(s.attribute))
        # Importance-scaled steps (SH bands): each chunk's step by its splats' opacity x footprint (format.md 4.3.1).
        importance = codebook_weights(g) if step is not None and step.importance else None
        scene_palette = ctx.palettes.get(s.name) if ctx.palettes else None  # format.md 4.3.2, 1.7
        planes.append(encode_plane(plane_values(g, s), s, ctx.formats[s.attribute], order, lazy=True, step=step,
                                   importance=importance, scene_palette=scene_palette,
                                   sizes=step_splat_sizes(g, step)))
    return planes


def encode_group(g: Gaussians, order: np.ndarray, group: str, ctx: TileContext, writer: SceneWriter) -> PayloadEntry:
    return write_planes(group_planes_of(g, order, group, ctx), chunks_for(len(order)), ctx, writer, ctx.short_names)


def tile_entry(tile: Tile, groups: dict[str, PayloadEntry]) -> TileEntry:
    """A tile's manifest entry from the tile and its payloads (bounds computed here if the tree left them out)."""
    if tile.box_min is None:
        tile.box_min, tile.box_max, tile.sphere_center, tile.sphere_radius = extent_bounds(tile.gaussians)
    n = len(tile.gaussians)
    chunks = chunks_for(n)
    return TileEntry(
        id=int(tile.id), level=int(tile.level), children=tuple(int(c) for c in tile.children), splats=n,
        chunks=chunks, texture=texture_size(chunks),
        box=Box(tuple(float(v) for v in tile.box_min), tuple(float(v) for v in tile.box_max)),
        sphere_center=tuple(float(v) for v in tile.sphere_center), sphere_radius=float(tile.sphere_radius),
        geometric_error=float(tile.geometric_error), groups=groups)


def encode_tile(tile: Tile, ctx: TileContext, writer: SceneWriter) -> TileEntry:
    """Every payload of one tile, then its entry: the unit of work a distributed encoder hands a worker."""
    order = tile_order(tile.gaussians, ctx)
    groups = {group: encode_group(tile.gaussians, order, group, ctx, writer) for group in tile_group_names(ctx)}
    return tile_entry(tile, groups)


def encode_codebook(codebook: Codebook, ctx: TileContext, writer: SceneWriter) -> SHCodebookEntry:
    """The codebook's band payloads (one per band, so SH still loads band by band) and its manifest entry. Named by
    their whole SHA-256 in any version (format.md 6.2: short digests are the compact tile table's only)."""
    k = len(codebook.entries)
    fmt = ctx.formats["sh"]
    groups = {band: write_planes([plane], chunks_for(k), ctx, writer)
              for band, plane in codebook_planes(codebook, ctx.sh_degree, fmt, lazy=True).items()}
    return SHCodebookEntry(k, fmt, SH_INDEX_FORMAT, groups)
