"""Tiles for the pool: from an encoded scene directory (payloads as stored) or from Gaussians encoded in memory."""
from __future__ import annotations

import os
from dataclasses import dataclass

from splatstream.codec import BASE_PLANES, EncodedPlane, band_plane, encode_plane, groups_for_degree, plane_values
from splatstream.container import unpack_group
from splatstream.decoder import leaf_tiles, read_codebook, read_payload
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
    # SH codebook scenes (format v1.1): the codebook's band planes "sh1".."sh{sh_degree}" as stored (K entries
    # each); the tiles then hold an `sh_index` plane instead of their SH bands. None without a codebook.
    codebook: dict[str, EncodedPlane] | None = None

    @property
    def splats(self) -> int:
        return sum(t.splats for t in self.tiles.values())


def tiles_from_gaussians(g: Gaussians, preset: str = DEFAULT_PRESET, sh_degree: int | None = None,
                         overrides: dict[str, str] | None = None,
                         sh_codebook: str | int | None = None) -> SceneTiles:
    """Encode Gaussians in memory into one tile (Morton order, as the encoder writes it) at a preset.

    sh_codebook: "off", "auto" or an entry count for an SH codebook (format v1.1) as the encoder builds it; None:
    the preset's choice (splatstream.encoder.PRESET_SH_CODEBOOK, as `encode` does).
    """
    formats = resolve_formats(preset, overrides or {})
    degree = g.sh_degree if sh_degree is None else min(int(sh_degree), g.sh_degree)
    order = morton_order(g.positions)
    codebook = _codebook_planes(g, preset, degree, formats["sh"], sh_codebook, order)
    specs = list(BASE_PLANES)
    if codebook is None:
        specs += [band_plane(b) for b in range(1, degree + 1)]
    planes = {}
    for s in specs:
        try:
            planes[s.name] = encode_plane(plane_values(g, s), s, formats[s.attribute], order=order)
        except TypeError:  # codec without the `order` argument
            planes[s.name] = encode_plane(plane_values(g, s)[order], s, formats[s.attribute])
    if codebook is not None:
        planes["sh_index"] = codebook.pop("sh_index")
    return SceneTiles(formats, degree, {0: TileData(len(g), planes)}, codebook=codebook)


def _codebook_planes(g: Gaussians, preset: str, degree: int, fmt: str, choice: str | int | None,
                     order) -> dict[str, EncodedPlane] | None:
    """Codebook band planes sh1..sh{degree} and the splats' index plane ("sh_index"), or None (no codebook)."""
    from splatstream.codec import encode_index_plane
    from splatstream.encoder import assign_sh_codebook, codebook_planes, fit_sh_codebook

    book = fit_sh_codebook(g, preset, choice, degree)  # exactly as the encoder fits it
    if book is None:
        return None
    out = codebook_planes(book, degree, fmt)
    out["sh_index"] = encode_index_plane(assign_sh_codebook(book, g.with_sh_degree(degree)), order)
    return out


def load_tile(scene_dir: str | os.PathLike, tile: dict, sh_degree: int, codebook: bool = False) -> TileData:
    """A tile's planes from its payloads (verified, decompressed, unshuffled; texels stay encoded).

    codebook: the scene has an SH codebook (manifest "sh_codebook"): the tile's sh1 payload is its sh_index plane.
    """
    planes = {}
    for group in groups_for_degree(sh_degree, codebook):
        entry = tile["groups"][group]
        data = read_payload(scene_dir, entry)
        source = os.path.join(scene_dir, entry["file"])
        planes.update(unpack_group(data, entry, group, tile["splats"], source, codebook=codebook))
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
    codebook = read_codebook(scene_dir, manifest, degree) if degree >= 1 else None
    cb = codebook is not None
    tiles = {int(t["id"]): load_tile(scene_dir, t, degree, cb) for t in chosen}
    return SceneTiles(dict(manifest["formats"]), degree, tiles, manifest, codebook)
