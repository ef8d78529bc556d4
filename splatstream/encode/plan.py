"""Plan: the scene-wide steps of an encode, done once before any tile is written.

Formats and SH degree from the options, the SH codebook, the up direction and the suggested camera (from the
deterministic samples of sample.py, the same a partitioned encode takes), the LOD tile tree (lod.py) and the
bounds. What comes out is everything a per-tile job needs
(`TileContext`) plus the tiles themselves; jobs.py encodes tiles, reduce.py builds the manifest.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputError, UsageError
from ..format.codec import chunk_ranges
from ..format.container import DEFAULT_ZSTD_LEVEL
from ..format.layout import CHUNK_SIZE, MAX_BLOCK_ROWS, MAX_BLOCKS_PER_ROW
from ..format.limits import describe_violations, domain_violations
from ..format.manifest import Box, CameraEntry
from ..format.presets import preset_steps, resolve_chunk_order, resolve_formats
from ..format.steps import TileStep, on_grid
from ..gaussians import Gaussians
from ..lod import Tile, build_tiles
from ..vq import Codebook
from .codebook import codebook_choice
from .options import EncodeOptions, Progress, no_progress
from .sample import SceneSample

log = logging.getLogger("splatstream.encode")


@dataclass(frozen=True)
class TileContext:
    """What a per-tile job needs besides its tile: small, picklable (a worker on another machine gets a copy)."""

    formats: dict[str, str]
    chunk_order: str
    sh_degree: int
    codebook: Codebook | None
    zstd_level: int = DEFAULT_ZSTD_LEVEL
    transport: str = "fields"  # format/transport.py TRANSPORTS
    # Tile-wide quantisation steps per attribute (format/steps.py): the preset's, for attributes it keeps the format of
    steps: dict[str, TileStep] = field(default_factory=dict)


@dataclass
class EncodePlan:
    context: TileContext
    tiles: list[Tile]  # breadth-first, root first; a single tile's bounds may still be None (jobs compute them)
    options: EncodeOptions
    name: str
    splats: int
    bounds: Box
    up: tuple[float, float, float]
    sample: SceneSample | None = None


def resolve_sh_degree(opts: EncodeOptions, g: Gaussians) -> int:
    return g.sh_degree if opts.sh_degree is None else min(opts.sh_degree, g.sh_degree)


def scene_name(opts: EncodeOptions, source_name: str | None, out_name: str | None) -> str:
    if opts.name:
        return opts.name
    if source_name:
        return os.path.splitext(os.path.basename(source_name))[0]
    return out_name or "scene"


def plan_tiles(g: Gaussians, opts: EncodeOptions, progress: Progress) -> list[Tile]:
    """The LOD tree, or one tile holding every splat (bounds left to the jobs) when LOD is off or not needed."""
    if opts.lod and len(g) > opts.max_leaf_splats:
        return build_tiles(g, max_leaf_splats=opts.max_leaf_splats, reduction=opts.reduction, progress=progress,
                           reorder_input=opts.reorder_input)
    limit = MAX_BLOCKS_PER_ROW * MAX_BLOCK_ROWS * CHUNK_SIZE
    if len(g) > limit:
        raise UsageError(f"{len(g)} splats do not fit one tile (at most {limit}); encode with LOD (drop --no-lod)")
    return [Tile(0, 0, [], g, 0.0, None, None, None, 0.0)]


# Within this many steps of a chunk's 8-bit grid (the SH0 of biker.compressed.ply: within 2.8e-5).
INPUT_GRID_TOLERANCE = 2e-3


def input_is_chunk_quantised(g: Gaussians) -> bool:
    """Whether the input is already cut into chunks of 256 with an 8-bit grid per chunk (compressed.ply): the SH0
    of every run of 256 splats, in input order, on 255 steps of its run's own range. Then a one-tile encode keeps
    that order (chunk order `input`, format.md 3), so its chunks are the input's and re-quantising them reproduces
    their grids: medium on biker.compressed.ply 77.4 -> 82.9 dB (the input's own re-encode by splat-transform:
    80.3 dB at 15 % more bytes). Continuous colours fail at once (each value is off a grid by chance), so the first
    run is tested alone before the whole scene."""
    if len(g.positions) < CHUNK_SIZE:  # a run's min and max are always on its grid: a few splats prove nothing
        return False
    return _on_chunk_grids(g.sh_dc[:CHUNK_SIZE]) and _on_chunk_grids(g.sh_dc)


def _on_chunk_grids(values: np.ndarray) -> bool:
    """Whether (N, C) values lie on 255 steps of their 256-splat chunk's range (codec.chunk_ranges), per component."""
    lo, hi = chunk_ranges(values, "<f4")
    chunk = np.arange(len(values)) // CHUNK_SIZE
    lo64 = lo.astype(np.float64)[chunk]
    extent = hi.astype(np.float64)[chunk] - lo64
    steps = np.divide(values - lo64, extent, out=np.zeros_like(lo64), where=extent > 0) * 255
    return on_grid(steps, INPUT_GRID_TOLERANCE)


def plan_encode(g: Gaussians, opts: EncodeOptions, progress: Progress = no_progress,
                source_name: str | None = None, out_name: str | None = None,
                tiles: list[Tile] | None = None) -> EncodePlan:
    """The plan of an encode of `g`. `tiles`: a tree built already (a foreign LOD tree: sog_import.py), breadth-
    first with bounds and errors, its leaves holding `g`; otherwise the LOD builder makes one."""
    formats = resolve_formats(opts.preset, opts.overrides)
    chunk_order = resolve_chunk_order(opts.chunk_order, formats)
    if len(g) == 0:
        raise InputError(source_name or "<gaussians>", None, "holds no splats (none, or none left after dropping "
                         "invalid ones); nothing to encode")
    # The encoder never writes what its readers refuse: values beyond the format's domain (format.md 4.8) would
    # make a range non-finite or decode to NaN. Files read through io.read_gaussians are screened already.
    violations = domain_violations(g)
    if violations:
        raise InputError(source_name or "<gaussians>", None, describe_violations(violations, len(g))[1])
    sh_degree = resolve_sh_degree(opts, g)
    if sh_degree != g.sh_degree:
        g = g.with_sh_degree(sh_degree)
    choice = codebook_choice(opts, sh_degree)
    sample = SceneSample.of(g, with_codebook=choice != "off")
    codebook = None
    if choice != "off":
        progress("codebook", 0.0)
        codebook = sample.codebook(choice)
        progress("codebook", 1.0)
        # The fitting rows are not needed again: below the sample size they are every splat's SH (180 MB at 1M
        # splats of SH3), which kept the codebook presets' LOD encode above 3x the input in peak memory.
        sample = replace(sample, codebook_rows=None, codebook_weights=None)
    bounds = Box(tuple(float(v) for v in g.positions.min(axis=0)), tuple(float(v) for v in g.positions.max(axis=0)))
    up = plan_up(opts, sample)
    progress("tiles", 0.0)
    if tiles is None:
        tiles = plan_tiles(g, opts, progress)
    elif sh_degree != g.sh_degree or any(t.gaussians.sh_degree != sh_degree for t in tiles):
        tiles = [replace(t, gaussians=t.gaussians.with_sh_degree(sh_degree)) for t in tiles]
    progress("tiles", 1.0)
    if opts.chunk_order == "auto" and chunk_order == "morton" and len(tiles) == 1 and input_is_chunk_quantised(g):
        chunk_order = "input"
    context = TileContext(formats, chunk_order, sh_degree, codebook, opts.resolved_zstd_level, opts.transport,
                          preset_steps(opts.preset, opts.overrides))
    return EncodePlan(context, tiles, opts, scene_name(opts, source_name, out_name), len(g), bounds, up, sample)


def plan_up(opts: EncodeOptions, sample: SceneSample) -> tuple[float, float, float]:
    if opts.up is not None:
        return tuple(float(v) for v in opts.up)
    choice = sample.up()
    log.info("up %s: %s (--up overrides it)", ",".join(f"{v:g}" for v in choice.up), choice.reason)
    return choice.up


def plan_camera(plan: EncodePlan) -> CameraEntry:
    """The suggested initial camera (format_spec/camera.md), from the scene sample."""
    return plan.sample.camera(plan.up)


def positions_box(positions: np.ndarray) -> Box:
    return Box(tuple(float(v) for v in positions.min(axis=0)), tuple(float(v) for v in positions.max(axis=0)))
