"""Decoding what came over the wire or off the disk: payload bytes -> planes for the GPU or values for numpy.

Every reader (the numpy decoder, the renderer's scene loader, the streaming client's decode workers) goes through
these functions, so checksums, sizes and codebook indices are checked in one place:

    planes = decode_payload(data, tile.groups["base"], "base", source)    # verified once, texels still encoded
    values = decode_planes(planes, tile.splats)                           # {"position": (N, 1, 3), ...} float32
    g = tile_gaussians(values, sh_degree)                                 # a Gaussians for numpy work
"""
from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from ..errors import FormatError
from ..gaussians import Gaussians
from .codec import EncodedPlane, assemble_gaussians, decode_index_plane, decode_plane
from .container import VerifiedPayload, unpack_payload, unpack_payloads, verified_bytes
from .manifest import Manifest, PayloadEntry, TileEntry
from .planes import band_of


def decode_payload(data: bytes | memoryview | VerifiedPayload, entry: PayloadEntry, group: str, source: str,
                   codebook: bool = False, between: Callable[[], object] | None = None,
                   palettes: Mapping[str, np.ndarray] | None = None) -> dict[str, EncodedPlane]:
    """Unpack a payload into planes (texels as stored): a VerifiedPayload of this entry as it is, other bytes
    verified against the entry first (size and SHA-256).

    `codebook`: the scene has an SH codebook, so a tile's `sh1` group is its `sh_index` plane. `between`: called
    between steps (after the checksum, before each plane; see unpack_payload). `palettes`: the scene's palettes
    (Manifest.scene_palettes, format.md 4.3.2), needed by a palette plane whose payload has no palette section."""
    raw = verified_bytes(data, entry, source)
    if between is not None:
        between()
    return unpack_payload(raw, entry, group, source, codebook, between, palettes)


def decode_planes(planes: dict[str, EncodedPlane], splats: int) -> dict[str, np.ndarray]:
    """Decoded (N, L, C) float32 values of each plane (index planes excluded)."""
    return {name: decode_plane(p, splats) for name, p in planes.items() if name != "sh_index"}


def check_codebook_indices(index: np.ndarray, entries: int, source: str) -> None:
    """format.md 4.7: a reader MUST reject a codebook index >= K."""
    if index.size and int(index.max()) >= entries:
        raise FormatError(source, "sh_index", f"codebook index {int(index.max())} out of range (the codebook has "
                          f"{entries} entries)")


def codebook_index(planes: dict[str, EncodedPlane], splats: int, entries: int, source: str) -> np.ndarray:
    """A tile's per-splat SH codebook entries from its `sh1` planes, checked against the codebook size."""
    index = decode_index_plane(planes["sh_index"], splats)
    check_codebook_indices(index, entries, source)
    return index


def expand_codebook(index: np.ndarray, codebook_values: dict[str, np.ndarray], sh_degree: int) -> dict:
    """SH band values of every splat from its codebook entry: {"sh1": (N, 3, 3), ...} up to sh_degree."""
    return {f"sh{b}": codebook_values[f"sh{b}"][index] for b in range(1, sh_degree + 1)}


def tile_gaussians(values: dict[str, np.ndarray], sh_degree: int) -> Gaussians:
    """Gaussians from decoded plane values (base planes and SH bands up to sh_degree)."""
    return assemble_gaussians(values, sh_degree)


def tile_groups_for(manifest: Manifest, sh_degree: int) -> list[str]:
    """The groups of each tile a reader fetches for `sh_degree` (<= the scene's)."""
    return [g for g in manifest.tile_groups() if band_of(g) <= sh_degree]


def decode_tile_bytes(tile: TileEntry, payloads: dict[str, bytes | VerifiedPayload], sh_degree: int, source: str,
                      codebook_values: dict[str, np.ndarray] | None = None, entries: int = 0,
                      palettes: Mapping[str, np.ndarray] | None = None) -> Gaussians:
    """One tile's Gaussians from its payload bytes by group (`base`, then `sh1`.. as needed for sh_degree);
    `palettes`: the scene's (decode_payload)."""
    values: dict[str, np.ndarray] = {}
    for group, data in payloads.items():
        entry = tile.groups[group]
        where = f"{source}/{entry.file}"
        planes = decode_payload(data, entry, group, where, codebook=codebook_values is not None, palettes=palettes)
        if codebook_values is not None and group == "sh1":
            values.update(expand_codebook(codebook_index(planes, tile.splats, entries, where), codebook_values,
                                          sh_degree))
        else:
            values.update(decode_planes(planes, tile.splats))
    return tile_gaussians(values, sh_degree)


def decode_payloads(items: list[tuple[bytes | memoryview | VerifiedPayload, PayloadEntry]], group: str,
                    sources: list[str], codebook: bool = False, between: Callable[[], object] | None = None,
                    palettes: Mapping[str, np.ndarray] | None = None) -> list[dict[str, EncodedPlane]]:
    """decode_payload of several payloads of one group (the tiles of one request, a scene's tiles), each verified as
    decode_payload verifies it: the same planes, bit for bit, decoded together (container.unpack_payloads), so the
    fixed cost of a payload's numpy calls is paid once for them all (issue 32)."""
    raws = [(verified_bytes(data, entry, source), entry) for (data, entry), source in zip(items, sources, strict=True)]
    if between is not None:
        between()
    return unpack_payloads(raws, group, sources, codebook, between, palettes)
