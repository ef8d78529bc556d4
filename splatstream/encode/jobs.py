"""Per-tile jobs: a tile in, its payloads (written through a SceneWriter) and its manifest entry out.

Pure apart from the writer: the same tile and context give the same bytes on any machine, in any order, so a
pool of threads or a cluster of workers can run them and the result does not depend on who ran what.
"""
from __future__ import annotations

import numpy as np

from ..format.codec import EncodedPlane, encode_index_plane, encode_plane, plane_values
from ..format.container import write_payload
from ..format.layout import morton_order, order_within_chunks, texture_size
from ..format.manifest import Box, PayloadEntry, SHCodebookEntry, TileEntry
from ..format.planes import BASE_PLANES, SH_INDEX_FORMAT, band_of, band_plane, chunks_for, groups_for_degree
from ..gaussians import Gaussians
from ..lod import Tile, extent_bounds
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


def tile_group_names(ctx: TileContext) -> list[str]:
    return groups_for_degree(ctx.sh_degree, ctx.codebook is not None)


def write_planes(planes: list[EncodedPlane], chunks: int, ctx: TileContext, writer: SceneWriter) -> PayloadEntry:
    with writer.payload_file() as (f, finish):
        entry = write_payload(planes, f, chunks, level=ctx.zstd_level, transport=ctx.transport)
        f.flush()
        finish(entry)
    return entry


def group_planes_of(g: Gaussians, order: np.ndarray, group: str, ctx: TileContext) -> list[EncodedPlane]:
    """The planes of one payload group of a tile (lazy: layers are quantised as the writer asks for them)."""
    if ctx.codebook is not None and group == "sh1":
        return [encode_index_plane(assign_sh_codebook(ctx.codebook, g), order)]
    specs = BASE_PLANES if group == "base" else (band_plane(band_of(group)),)
    planes = []
    for s in specs:
        step = ctx.steps.get(s.name, ctx.steps.get(s.attribute))
        # Importance-scaled steps (SH bands): each chunk's step by its splats' opacity x footprint (format.md 4.3.1).
        importance = codebook_weights(g) if step is not None and step.importance else None
        planes.append(encode_plane(plane_values(g, s), s, ctx.formats[s.attribute], order, lazy=True, step=step,
                                   importance=importance))
    return planes


def encode_group(g: Gaussians, order: np.ndarray, group: str, ctx: TileContext, writer: SceneWriter) -> PayloadEntry:
    return write_planes(group_planes_of(g, order, group, ctx), chunks_for(len(order)), ctx, writer)


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
    order = splat_order(tile.gaussians, ctx.chunk_order)
    groups = {group: encode_group(tile.gaussians, order, group, ctx, writer) for group in tile_group_names(ctx)}
    return tile_entry(tile, groups)


def encode_codebook(codebook: Codebook, ctx: TileContext, writer: SceneWriter) -> SHCodebookEntry:
    """The codebook's band payloads (one per band, so SH still loads band by band) and its manifest entry."""
    k = len(codebook.entries)
    fmt = ctx.formats["sh"]
    groups = {band: write_planes([plane], chunks_for(k), ctx, writer)
              for band, plane in codebook_planes(codebook, ctx.sh_degree, fmt, lazy=True).items()}
    return SHCodebookEntry(k, fmt, SH_INDEX_FORMAT, groups)
