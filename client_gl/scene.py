"""Tiles for the pool, read from any scene store (a directory, or Gaussians encoded in memory by the encoder).

Both paths are the same: payload bytes -> splatstream.format.decode -> planes as stored (texels stay encoded).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from splatstream.decoder import read_codebook
from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.format.codec import EncodedPlane
from splatstream.format.decode import codebook_index, decode_payload, tile_groups_for
from splatstream.format.manifest import Manifest, TileEntry
from splatstream.gaussians import Gaussians
from splatstream.store import SceneStore, open_store, read_manifest

from .pool import TileData

DEFAULT_PRESET = "very-high"


@dataclass
class SceneTiles:
    formats: dict[str, str]
    sh_degree: int
    tiles: dict[int, TileData]
    manifest: Manifest
    # SH codebook scenes (format v1.1): the codebook's band planes "sh1".."sh{sh_degree}" as stored (K entries
    # each); the tiles then hold an `sh_index` plane instead of their SH bands. None without a codebook.
    codebook: dict[str, EncodedPlane] | None = None

    @property
    def splats(self) -> int:
        return sum(t.splats for t in self.tiles.values())


def load_tile(store: SceneStore, manifest: Manifest, tile: TileEntry, sh_degree: int) -> TileData:
    """A tile's planes from its payloads (verified, decompressed, unshuffled; texels stay encoded)."""
    planes: dict[str, EncodedPlane] = {}
    for group in tile_groups_for(manifest, sh_degree):
        entry = tile.groups[group]
        source = store.payload_source(entry)
        planes.update(decode_payload(store.read_payload(entry), entry, group, source, manifest.uses_codebook))
        if group == "sh1" and manifest.uses_codebook:  # an index >= K is an error for every reader (format.md 4.7)
            codebook_index(planes, tile.splats, manifest.sh_codebook.entries, source)
    return TileData(tile.splats, planes)


def tiles_from_scene(source: str | os.PathLike | SceneStore, sh_degree: int | None = None,
                     tile_ids: list[int] | None = None) -> SceneTiles:
    """The full-detail (leaf) tiles of a scene, or the listed tile ids."""
    store = open_store(source)
    manifest = read_manifest(store)
    degree = manifest.sh_degree if sh_degree is None else max(0, min(int(sh_degree), manifest.sh_degree))
    chosen = manifest.leaves if tile_ids is None else [manifest.tile(i) for i in tile_ids]
    codebook = read_codebook(store, manifest, degree) if degree >= 1 else None
    tiles = {t.id: load_tile(store, manifest, t, degree) for t in chosen}
    return SceneTiles(dict(manifest.formats), degree, tiles, manifest, codebook)



def tiles_from_gaussians(g: Gaussians, preset: str = DEFAULT_PRESET, sh_degree: int | None = None,
                         overrides: dict[str, str] | None = None,
                         sh_codebook: str | int | None = None) -> SceneTiles:
    """Gaussians encoded in memory by the encoder (one tile, as `encode --no-lod` writes it) at a preset.

    sh_codebook: "off", "auto" or an entry count for an SH codebook; None: the preset's choice (as `encode` does).
    """
    opts = EncodeOptions(preset=preset, overrides=dict(overrides or {}), sh_degree=sh_degree, lod=False,
                         sh_codebook=sh_codebook)
    return tiles_from_scene(encode_in_memory(g, opts))
