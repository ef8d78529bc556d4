"""Export a splatstream scene's LOD tree as Spark 2's `.rad` (one file: header, LoD tree, 64K-splat paging chunks),
for Spark's paged loader (format_spec/foreign_formats.md, "Our RAD export").

The mapping from our tree is `splatstream.writers.rad` (pure); this module decodes the scene's tiles and writes
the file atomically.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

from .atomic import atomic_file, check_output
from .errors import UsageError
from .format.decode import decode_planes
from .scene_decode import decode_tile, read_codebook
from .store import SceneStore, open_store, read_manifest
from .writers.rad import CHUNK_SPLATS, ENCODINGS, TreeTile, rad_bytes, rad_tree


@dataclass(frozen=True)
class RadExportReport:
    tiles: int
    levels: int  # depths of the splat tree (our levels, plus the merged root splat when our root has several)
    chunks: int
    splats: int  # every splat written (all levels)
    leaf_splats: int  # splats without children (the full detail)
    bytes: int


def export_rad(scene: str | os.PathLike | SceneStore, out: str | os.PathLike, sh_degree: int | None = None,
               progress: Callable[[str, float], None] | None = None, encoding: str = "exact") -> RadExportReport:
    """Write the .rad of `scene` to `out` (replaced atomically). `encoding`: "exact" (our decoded values, f32 and
    f16) or "spark" (Spark's own 8-bit defaults: smaller, quantised again)."""
    if encoding not in ENCODINGS:
        raise UsageError(f"RAD encoding {encoding!r}: expected one of {', '.join(ENCODINGS)}")
    store = open_store(scene)
    manifest = read_manifest(store)
    out = os.fspath(out)
    check_output(out)
    degree = manifest.sh_degree if sh_degree is None else max(0, min(sh_degree, manifest.sh_degree))
    planes = read_codebook(store, manifest, degree) if degree >= 1 else None
    codebook = decode_planes(planes, manifest.sh_codebook.entries) if planes is not None else None
    report = progress or (lambda stage, fraction: None)
    tiles: dict[int, TreeTile] = {}
    for done, tile in enumerate(manifest.tiles):
        tiles[tile.id] = TreeTile(tile.id, tile.level, tuple(tile.children),
                                  decode_tile(store, manifest, tile, degree, codebook))
        report("decode", (done + 1) / len(manifest.tiles))
    report("encode", 0.0)
    try:
        tree = rad_tree(tiles, manifest.root)
    except ValueError as e:
        raise UsageError(f"{os.fspath(scene) if not isinstance(scene, SceneStore) else 'scene'}: {e}") from None
    data = rad_bytes(tree, degree, encoding)
    report("encode", 1.0)
    with atomic_file(out) as f:
        f.write(data)
    os.chmod(out, 0o644)
    n = len(tree.splats)
    return RadExportReport(tiles=len(manifest.tiles), levels=tree.levels(), chunks=-(-n // CHUNK_SPLATS),
                           splats=n, leaf_splats=int((tree.child_count == 0).sum()), bytes=len(data))


__all__ = ["RadExportReport", "export_rad"]
