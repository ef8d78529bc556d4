"""A whole encoded scene (a directory or any SceneStore) back to float Gaussians: `splatstream decode`, `eval`,
the 3D Tiles export.

A thin shell over a store: bytes come from the store, and turning one payload's bytes into planes and values is
splatstream.format.decode's job (the one place every reader goes through), not this module's.
"""
from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from .errors import FormatError
from .format.codec import EncodedPlane
from .format.decode import decode_payload, decode_planes, decode_tile_bytes, tile_groups_for
from .format.manifest import Manifest, TileEntry
from .gaussians import Gaussians
from .sh import warn_sh_degree_above
from .store import SceneStore, open_store, read_manifest
from .writers.sog_lod import TreeTile


def read_codebook(store: SceneStore, manifest: Manifest, sh_degree: int) -> dict[str, EncodedPlane] | None:
    """The SH codebook's band planes sh1..sh{sh_degree} as stored (K entries each), or None without a codebook."""
    cb = manifest.sh_codebook
    if cb is None:
        return None
    planes: dict[str, EncodedPlane] = {}
    for b in range(1, sh_degree + 1):
        entry = cb.groups[f"sh{b}"]
        planes.update(decode_payload(store.read_payload(entry), entry, f"sh{b}", store.payload_source(entry)))
    return planes


def decode_tile(store: SceneStore, manifest: Manifest, tile: TileEntry, sh_degree: int,
                codebook_values: dict[str, np.ndarray] | None = None) -> Gaussians:
    """One tile's Gaussians; `codebook_values` (decoded codebook bands) is required for codebook scenes."""
    payloads = {g: store.read_payload(tile.groups[g]) for g in tile_groups_for(manifest, sh_degree)}
    entries = manifest.sh_codebook.entries if manifest.sh_codebook else 0
    return decode_tile_bytes(tile, payloads, sh_degree, store.location, codebook_values, entries,
                             manifest.scene_palettes)


def decode_scene(scene: str | os.PathLike | SceneStore, sh_degree: int | None = None,
                 tiles: str | list[int] = "leaves", manifest: Manifest | None = None) -> Gaussians:
    """Decode a scene: its full-detail leaves by default, or the listed tile ids."""
    store = open_store(scene)
    manifest = manifest or read_manifest(store)
    degree = manifest.sh_degree if sh_degree is None else max(0, min(sh_degree, manifest.sh_degree))
    if tiles == "leaves":
        chosen = manifest.leaves
    else:
        missing = [i for i in tiles if i not in manifest.tile_by_id]
        if missing:
            raise FormatError(store.location, "tiles", f"no tiles with ids {missing}")
        chosen = [manifest.tile(i) for i in tiles]
    planes = read_codebook(store, manifest, degree) if degree >= 1 else None
    codebook = decode_planes(planes, manifest.sh_codebook.entries) if planes is not None else None
    parts = [decode_tile(store, manifest, t, degree, codebook) for t in chosen]
    return Gaussians.concatenate(parts) if parts else Gaussians.empty(degree)


def decode_tree_tiles(store: SceneStore, manifest: Manifest, sh_degree: int | None,
                      progress: Callable[[str, float], None]) -> tuple[int, dict[int, TreeTile]]:
    """Every tile of a scene decoded whole, with its depth and children, for the exports of our tree into foreign
    LOD formats (sog_export, rad_export): the SH degree kept (at most the scene's; None: the scene's) and the tiles
    by id. Reports ("decode", fraction done); warns where more SH bands are asked for than the scene has."""
    warn_sh_degree_above(sh_degree, manifest.sh_degree, store.location)
    degree = manifest.sh_degree if sh_degree is None else max(0, min(sh_degree, manifest.sh_degree))
    planes = read_codebook(store, manifest, degree) if degree >= 1 else None
    codebook = decode_planes(planes, manifest.sh_codebook.entries) if planes is not None else None
    tiles: dict[int, TreeTile] = {}
    for done, tile in enumerate(manifest.tiles):
        tiles[tile.id] = TreeTile(tile.id, tile.level, tuple(tile.children),
                                  decode_tile(store, manifest, tile, degree, codebook))
        progress("decode", (done + 1) / len(manifest.tiles))
    return degree, tiles
