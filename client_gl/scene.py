"""Tiles for the pool, read from any scene store (a directory, or Gaussians encoded in memory by the encoder).

Both paths are the same: payload bytes -> splatstream.format.decode (verified, texels still encoded) -> TileData
(planes + the host mirror the CPU-sort path needs) -> ChunkPool.join / add_band.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np

from splatstream.camera import Camera
from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.format.codec import EncodedPlane
from splatstream.format.decode import codebook_index, decode_payload, tile_groups_for
from splatstream.format.manifest import Manifest, TileEntry
from splatstream.gaussians import Gaussians
from splatstream.scene_decode import read_codebook
from splatstream.store import SceneStore, open_store, read_manifest

from .gpu.residency_layout import CHUNK, CodebookLayout
from .stream.selection import SelectionOptions, select, view_numbers, wanted_bands
from .tiledata import TileData, host_mirror

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

    @property
    def slots(self) -> int:
        """Pool slots the tiles take (one per 256-splat chunk)."""
        return sum(-(-t.splats // CHUNK) for t in self.tiles.values())

    @property
    def codebook_layout(self) -> CodebookLayout | None:
        """The shape a pool needs for this scene's SH codebook (None: no codebook loaded)."""
        cb = self.manifest.sh_codebook
        if self.codebook is None or cb is None:
            return None
        return CodebookLayout(cb.format, cb.entries)


def _group_planes(store: SceneStore, manifest: Manifest, tile: TileEntry, group: str) -> dict[str, EncodedPlane]:
    entry = tile.groups[group]
    source = store.payload_source(entry)
    planes = decode_payload(store.read_payload(entry), entry, group, source, manifest.uses_codebook,
                            palettes=manifest.scene_palettes)
    if group == "sh1" and manifest.uses_codebook:  # an index >= K is an error for every reader (format.md 4.7)
        codebook_index(planes, tile.splats, manifest.sh_codebook.entries, source)
    return planes


def load_tile(store: SceneStore, manifest: Manifest, tile: TileEntry, sh_degree: int,
              with_mirror: bool = True) -> TileData:
    """A tile's planes from its payloads (base and the SH groups up to sh_degree) and, with_mirror, its host
    mirror."""
    planes: dict[str, EncodedPlane] = {}
    for group in tile_groups_for(manifest, sh_degree):
        planes.update(_group_planes(store, manifest, tile, group))
    return TileData(tile.splats, planes, host_mirror(planes, tile.splats) if with_mirror else None)


def load_band(store: SceneStore, manifest: Manifest, tile: TileEntry, band: int) -> dict[str, EncodedPlane]:
    """The planes ChunkPool.add_band takes for SH band `band` of a tile: its sh<band> payload, or with an SH
    codebook its index (band 1) and nothing for bands 2..3 (the codebook's)."""
    if manifest.uses_codebook and band > 1:
        return {}
    return _group_planes(store, manifest, tile, f"sh{band}")


def tiles_from_scene(source: str | os.PathLike | SceneStore, sh_degree: int | None = None,
                     tile_ids: list[int] | None = None, with_mirror: bool = True) -> SceneTiles:
    """The full-detail (leaf) tiles of a scene, or the listed tile ids."""
    store = open_store(source)
    manifest = read_manifest(store)
    degree = manifest.sh_degree if sh_degree is None else max(0, min(int(sh_degree), manifest.sh_degree))
    chosen = manifest.leaves if tile_ids is None else [manifest.tile(i) for i in tile_ids]
    codebook = read_codebook(store, manifest, degree) if degree >= 1 else None
    tiles = {t.id: load_tile(store, manifest, t, degree, with_mirror) for t in chosen}
    return SceneTiles(dict(manifest.formats), degree, tiles, manifest, codebook)


def tiles_from_gaussians(g: Gaussians, preset: str = DEFAULT_PRESET, sh_degree: int | None = None,
                         overrides: dict[str, str] | None = None,
                         sh_codebook: str | int | None = None, with_mirror: bool = True) -> SceneTiles:
    """Gaussians encoded in memory by the encoder (one tile, as `encode --no-lod` writes it) at a preset.

    sh_codebook: "off", "auto" or an entry count for an SH codebook; None: the preset's choice (as `encode` does).
    """
    opts = EncodeOptions(preset=preset, overrides=dict(overrides or {}), sh_degree=sh_degree, lod=False,
                         sh_codebook=sh_codebook)
    return tiles_from_scene(encode_in_memory(g, opts), with_mirror=with_mirror)



def tiles_for_view(source: str | os.PathLike | SceneStore, camera: Camera, options: SelectionOptions,
                   sh_degree: int | None = None, with_mirror: bool = True) -> SceneTiles:
    """The tiles and SH bands the streaming client wants for this view (client_gl/stream/selection.py, without a
    byte budget): what `render --max-sse` draws, so a converged stream can be compared with it."""
    store = open_store(source)
    manifest = read_manifest(store)
    degree = manifest.sh_degree if sh_degree is None else max(0, min(int(sh_degree), manifest.sh_degree))
    opts = replace(options, sh_degree=min(options.sh_degree, degree))
    a = manifest.arrays
    view = view_numbers(a, camera, opts)
    cost = np.array([t.chunks for t in manifest.tiles], np.float64)
    root = manifest.index_of[manifest.root]
    sel = select(a, view, cost, root, opts, reduction=manifest.lod.reduction)
    bands = wanted_bands(a, view, sel.cut, opts, manifest.sh_degree)
    top = max(bands.values(), default=0)
    codebook = read_codebook(store, manifest, top) if top >= 1 else None
    tiles = {}
    for i in sel.cut:
        tile = manifest.tiles[i]
        tiles[tile.id] = load_tile(store, manifest, tile, bands[i], with_mirror)
    return SceneTiles(dict(manifest.formats), top, tiles, manifest, codebook)
