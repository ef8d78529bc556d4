"""Tiles for the pool: from an encoded scene directory (payloads as stored) or from Gaussians encoded in memory."""
from __future__ import annotations

import os
from dataclasses import dataclass

from splatstream.codec import BASE_PLANES, band_plane, encode_plane, groups_for_degree, plane_values
from splatstream.container import unpack_group
from splatstream.decoder import leaf_tiles, read_payload
from splatstream.encoder import resolve_formats
from splatstream.gaussians import Gaussians
from splatstream.layout import morton_order
from splatstream.manifest import load_manifest

from .pool import TileData

DEFAULT_PRESET = "very-high"


@dataclass
class SceneTiles:
    formats: dict[str, str]
    sh_degree: int
    tiles: dict[int, TileData]
    manifest: dict | None = None

    @property
    def splats(self) -> int:
        return sum(t.splats for t in self.tiles.values())


def tiles_from_gaussians(g: Gaussians, preset: str = DEFAULT_PRESET, sh_degree: int | None = None,
                         overrides: dict[str, str] | None = None) -> SceneTiles:
    """Encode Gaussians in memory into one tile (Morton order, as the encoder writes it) at a preset."""
    formats = resolve_formats(preset, overrides or {})
    degree = g.sh_degree if sh_degree is None else min(int(sh_degree), g.sh_degree)
    order = morton_order(g.positions)
    specs = list(BASE_PLANES) + [band_plane(b) for b in range(1, degree + 1)]
    planes = {}
    for s in specs:
        try:
            planes[s.name] = encode_plane(plane_values(g, s), s, formats[s.attribute], order=order)
        except TypeError:  # codec without the `order` argument
            planes[s.name] = encode_plane(plane_values(g, s)[order], s, formats[s.attribute])
    return SceneTiles(formats, degree, {0: TileData(len(g), planes)})


def load_tile(scene_dir: str | os.PathLike, tile: dict, sh_degree: int) -> TileData:
    """A tile's planes from its payloads (verified, decompressed, unshuffled; texels stay encoded)."""
    planes = {}
    for group in groups_for_degree(sh_degree):
        entry = tile["groups"][group]
        data = read_payload(scene_dir, entry)
        planes.update(unpack_group(data, entry, group, tile["splats"], os.path.join(scene_dir, entry["file"])))
    return TileData(int(tile["splats"]), planes)


def tiles_from_scene(scene_dir: str | os.PathLike, sh_degree: int | None = None,
                     tile_ids: list[int] | None = None) -> SceneTiles:
    """The full-detail (leaf) tiles of an encoded scene, or the listed tile ids."""
    manifest = load_manifest(scene_dir)
    degree = manifest["sh_degree"] if sh_degree is None else min(int(sh_degree), manifest["sh_degree"])
    if tile_ids is None:
        chosen = leaf_tiles(manifest)
    else:
        by_id = {t["id"]: t for t in manifest["tiles"]}
        chosen = [by_id[i] for i in tile_ids]
    tiles = {int(t["id"]): load_tile(scene_dir, t, degree) for t in chosen}
    return SceneTiles(dict(manifest["formats"]), degree, tiles, manifest)
