"""Numpy decoder: scene directory (or single tiles and groups) back to float Gaussians."""
from __future__ import annotations

import os

import numpy as np

from .codec import EncodedPlane, assemble_gaussians, decode_index_plane, decode_plane
from .container import unpack_group, verify_payload
from .errors import FormatError
from .gaussians import Gaussians
from .manifest import load_manifest


def read_payload(scene_dir: str | os.PathLike, entry: dict) -> bytes:
    """Read a payload file and check it against its manifest entry."""
    rel = entry.get("file", "")
    if not isinstance(rel, str) or rel.startswith("/") or ".." in rel.split("/"):
        raise FormatError(os.path.join(scene_dir, "manifest.msgpack"), "file", f"unsafe payload path {rel!r}")
    path = os.path.join(os.fspath(scene_dir), rel)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise FormatError(path, None, "payload file named in the manifest is missing") from None
    verify_payload(data, entry, path)
    return data


def decode_group(data: bytes, entry: dict, group: str, splats: int, source: str = "payload") -> dict[str, np.ndarray]:
    """Decode one payload (verified bytes) into plane values {plane name: (N, L, C)}."""
    planes = unpack_group(data, entry, group, splats, source)
    return {name: decode_plane(p, splats) for name, p in planes.items()}


def codebook_info(manifest: dict, source: str = "manifest.msgpack") -> dict | None:
    """The manifest's SH codebook entry, validated (None when the scene has none)."""
    cb = manifest.get("sh_codebook")
    if cb is None:
        return None
    if not isinstance(cb, dict) or not isinstance(cb.get("entries"), int) or not 1 <= cb["entries"] <= 65536:
        raise FormatError(source, "sh_codebook.entries", "expected an integer 1..65536")
    if cb.get("index_format") != "index16":
        raise FormatError(source, "sh_codebook.index_format", f"expected 'index16', got {cb.get('index_format')!r}")
    groups = cb.get("groups")
    if not isinstance(groups, dict):
        raise FormatError(source, "sh_codebook.groups", "missing or not a map")
    for b in range(1, manifest["sh_degree"] + 1):
        if not isinstance(groups.get(f"sh{b}"), dict):
            raise FormatError(source, "sh_codebook.groups", f"no 'sh{b}' group for SH degree {manifest['sh_degree']}")
    return cb


def read_codebook(scene_dir: str | os.PathLike, manifest: dict, sh_degree: int) -> dict[str, EncodedPlane] | None:
    """The SH codebook's band planes sh1..sh{sh_degree} as stored (K entries each), or None without a codebook."""
    cb = codebook_info(manifest, os.path.join(os.fspath(scene_dir), "manifest.msgpack"))
    if cb is None:
        return None
    planes: dict[str, EncodedPlane] = {}
    for b in range(1, sh_degree + 1):
        entry = cb["groups"][f"sh{b}"]
        data = read_payload(scene_dir, entry)
        planes.update(unpack_group(data, entry, f"sh{b}", cb["entries"], os.path.join(scene_dir, entry["file"])))
    return planes


def decode_codebook(planes: dict[str, EncodedPlane], entries: int) -> dict[str, np.ndarray]:
    """Codebook band planes -> {"sh1": (K, 3, 3), ...} float32 values."""
    return {name: decode_plane(p, entries) for name, p in planes.items()}


def decode_tile(scene_dir: str | os.PathLike, tile: dict, sh_degree: int,
                codebook: dict[str, np.ndarray] | None = None) -> Gaussians:
    """Decode one tile; `codebook` (decode_codebook's values) is required for scenes with an SH codebook."""
    values: dict[str, np.ndarray] = {}
    groups = ["base"] + (["sh1"] if codebook is not None and sh_degree >= 1 else
                         [f"sh{b}" for b in range(1, sh_degree + 1)])
    manifest_path = os.path.join(scene_dir, "manifest.msgpack")
    for group in groups:
        entry = tile["groups"].get(group)
        if entry is None:
            raise FormatError(manifest_path, f"tile {tile['id']}.groups", f"no {group!r} group")
        data = read_payload(scene_dir, entry)
        source = os.path.join(scene_dir, entry["file"])
        if codebook is not None and group == "sh1":
            planes = unpack_group(data, entry, group, tile["splats"], source, codebook=True)
            index = decode_index_plane(planes["sh_index"], tile["splats"])
            k = len(next(iter(codebook.values())))
            if index.size and index.max() >= k:
                raise FormatError(source, "sh_index", f"codebook index {int(index.max())} out of range (the "
                                  f"codebook has {k} entries)")
            for b in range(1, sh_degree + 1):
                values[f"sh{b}"] = codebook[f"sh{b}"][index]
        else:
            values.update(decode_group(data, entry, group, tile["splats"], source))
    return assemble_gaussians(values, sh_degree)


def leaf_tiles(manifest: dict) -> list[dict]:
    return [t for t in manifest["tiles"] if not t.get("children")]


def decode_scene(scene_dir: str | os.PathLike, sh_degree: int | None = None, tiles: str | list[int] = "leaves",
                 manifest: dict | None = None) -> Gaussians:
    """Decode a scene: its full-detail leaves by default, or the listed tile ids."""
    manifest = manifest or load_manifest(scene_dir)
    degree = manifest["sh_degree"] if sh_degree is None else min(sh_degree, manifest["sh_degree"])
    if tiles == "leaves":
        chosen = leaf_tiles(manifest)
    else:
        by_id = {t["id"]: t for t in manifest["tiles"]}
        missing = [i for i in tiles if i not in by_id]
        if missing:
            raise FormatError(os.path.join(scene_dir, "manifest.msgpack"), "tiles", f"no tiles with ids {missing}")
        chosen = [by_id[i] for i in tiles]
    planes = read_codebook(scene_dir, manifest, degree) if degree >= 1 else None
    codebook = decode_codebook(planes, manifest["sh_codebook"]["entries"]) if planes is not None else None
    parts = [decode_tile(scene_dir, t, degree, codebook) for t in chosen]
    return Gaussians.concatenate(parts) if parts else Gaussians.empty(degree)
