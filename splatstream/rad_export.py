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
from .scene_decode import decode_tree_tiles
from .store import SceneStore, open_store, read_manifest
from .writers.rad import CHUNK_SPLATS, ENCODINGS, rad_bytes, rad_tree


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
    report = progress or (lambda stage, fraction: None)
    degree, tiles = decode_tree_tiles(store, manifest, sh_degree, report)
    try:
        tree = rad_tree(tiles, manifest.root, lambda fraction: report("tree", fraction))
    except ValueError as e:
        raise UsageError(f"{os.fspath(scene) if not isinstance(scene, SceneStore) else 'scene'}: {e}") from None
    data = rad_bytes(tree, degree, encoding, lambda fraction: report("encode", fraction))
    with atomic_file(out) as f:
        f.write(data)
    os.chmod(out, 0o644)
    n = len(tree.splats)
    return RadExportReport(tiles=len(manifest.tiles), levels=tree.levels(), chunks=-(-n // CHUNK_SPLATS),
                           splats=n, leaf_splats=int((tree.child_count == 0).sum()), bytes=len(data))


__all__ = ["RadExportReport", "export_rad"]
