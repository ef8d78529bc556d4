"""Export a splatstream scene's LOD tree as a PlayCanvas streamed SOG (`lod-meta.json` + SOG units), for
PlayCanvas's engine and SuperSplat (format_spec/foreign_formats.md, "Our streamed SOG export").

The mapping from our tree is `splatstream.writers.sog_lod` (pure); this module decodes the scene's tiles and
writes the output directory atomically (built under a hidden temporary name, swapped into place).
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

from .atomic import atomic_directory, check_output
from .errors import UsageError
from .scene_decode import decode_tree_tiles
from .store import SceneStore, open_store, read_manifest
from .writers.sog_lod import LOD_META_NAME, UNIT_SPLATS, streamed_sog, write_streamed_sog


@dataclass(frozen=True)
class SogExportReport:
    tiles: int
    levels: int
    units: int
    splats: int  # splats written over every level
    leaf_splats: int  # level 0 (the scene's full detail)
    bytes: int  # everything written


def export_streamed_sog(scene: str | os.PathLike | SceneStore, out_dir: str | os.PathLike,
                        sh_degree: int | None = None, unit_splats: int = UNIT_SPLATS,
                        progress: Callable[[str, float], None] | None = None) -> SogExportReport:
    """Write the streamed SOG of `scene` into `out_dir` (replaced atomically)."""
    store = open_store(scene)
    manifest = read_manifest(store)
    out = os.fspath(out_dir)
    if isinstance(scene, (str, os.PathLike)) and os.path.exists(out) and \
            os.path.realpath(out) == os.path.realpath(os.fspath(scene)):
        raise UsageError(f"{out}: the output directory is the scene itself")
    if unit_splats < 1:
        raise UsageError(f"unit size {unit_splats}: expected at least 1 splat")
    check_output(out, directory=True, holds=LOD_META_NAME)
    report = progress or (lambda stage, fraction: None)
    degree, tiles = decode_tree_tiles(store, manifest, sh_degree, report)
    sog = streamed_sog(tiles, manifest.root, unit_splats, lambda fraction: report("encode", fraction))
    with atomic_directory(out, holds=LOD_META_NAME) as tmp:
        write_streamed_sog(sog, tmp)
        for base, dirs, files in os.walk(tmp):
            for d in dirs:
                os.chmod(os.path.join(base, d), 0o755)
            for f in files:
                os.chmod(os.path.join(base, f), 0o644)
        written = sum(os.path.getsize(os.path.join(base, f)) for base, _, files in os.walk(tmp) for f in files)
    meta = sog.meta
    return SogExportReport(tiles=len(manifest.tiles), levels=meta["lodLevels"], units=len(sog.units),
                           splats=meta["count"], leaf_splats=meta["counts"][0], bytes=written)


__all__ = ["LOD_META_NAME", "SogExportReport", "export_streamed_sog"]
