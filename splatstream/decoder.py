"""Numpy decoder: scene directory (or single tiles and groups) back to float Gaussians."""
from __future__ import annotations

import os

import numpy as np

from .codec import assemble_gaussians, decode_plane
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


def decode_tile(scene_dir: str | os.PathLike, tile: dict, sh_degree: int) -> Gaussians:
    values: dict[str, np.ndarray] = {}
    for group in ["base"] + [f"sh{b}" for b in range(1, sh_degree + 1)]:
        entry = tile["groups"].get(group)
        if entry is None:
            raise FormatError(os.path.join(scene_dir, "manifest.msgpack"), f"tile {tile['id']}.groups",
                              f"no {group!r} group")
        data = read_payload(scene_dir, entry)
        values.update(decode_group(data, entry, group, tile["splats"], os.path.join(scene_dir, entry["file"])))
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
    parts = [decode_tile(scene_dir, t, degree) for t in chosen]
    return Gaussians.concatenate(parts) if parts else Gaussians.empty(degree)
