"""Plan: the scene-wide steps of an encode, done once before any tile is written, the same for every engine.

`plan_formats` (texel formats and chunk order from the options) and `plan_scene` (the SH codebook, the up
direction and the ScenePlan the manifest is built from, out of the deterministic scene sample of sample.py) are
what the in-memory engine (`plan_encode`, below, with the LOD tile tree of lod.py) and the partitioned one
(partitioned.py, from the samples its passes over the rows gather) share; a per-tile job needs only the
`TileContext`; jobs.py encodes tiles, reduce.py builds the manifest from the ScenePlan and the tiles' entries.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputError, UsageError
from ..format.codec import PaletteValues, chunk_ranges, decode_rotations, encode_rotations, merged_pairs, scene_palettes
from ..format.container import DEFAULT_ZSTD_LEVEL
from ..format.layout import CHUNK_SIZE, MAX_BLOCK_ROWS, MAX_BLOCKS_PER_ROW
from ..format.limits import describe_violations, domain_violations
from ..format.manifest import Box, CameraEntry, LodRefinement, short_tile_names
from ..format.planes import BASE_PLANES
from ..format.presets import (
    PRESET_PALETTE_MERGE,
    compression_preset,
    palette_fallback,
    preset_block_slack,
    preset_one_block_slack,
    preset_zstd_min_match,
    resolve_chunk_order,
    resolve_formats,
    rotation_choices,
    rotation_gauge,
)
from ..format.steps import TileStep, on_grid
from ..format.texformats import PALETTE_FORMATS, pack_texels, unpack_texels
from ..gaussians import Gaussians
from ..lod import Tile, build_tiles, viewing_scales_px
from ..lod_refine import refine_tree
from ..rotation_canon import canonical_gauge
from ..store import is_url
from ..vq import Codebook
from .codebook import check_codebook_option, codebook_choice
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
    # The scene's palettes per pal8x4 plane, (P, 256) float32 (format.md 4.3.2, 1.7: written once, in the manifest)
    palettes: dict[str, np.ndarray] | None = None
    # How much larger a joined zstd block may code than its parts (container._block_ends; the preset's)
    block_slack: float = 0.0
    # zstd's shortest match, 0 for the level's own (container._compressor; the preset's)
    zstd_min_match: int = 0
    # How much larger a small payload may be stored as one zstd block (container.write_payload; the preset's)
    one_block_slack: float = 0.0
    # Store each splat's rotation and scales as the equivalent pair whose rotation is closest to the identity in
    # this group (rotation_canon.canonical_gauge: "cube" or "half-turns"; the preset's: presets.rotation_gauge)
    rotation_gauge: str | None = None
    # Name each tile payload by its short digest when it is written (data/<32 hex>.bin: a 1.15 scene, format.md 6.2;
    # table.short_tile_names): its final name at once, so no payload is renamed (an object store's copy and delete)
    short_names: bool = False


@dataclass(frozen=True)
class ScenePlan:
    """What the manifest says of the scene as a whole (reduce.build_manifest takes exactly this), decided before
    any tile is written."""

    context: TileContext
    preset: str
    name: str
    splats: int
    bounds: Box
    up: tuple[float, float, float]
    max_leaf_splats: int
    reduction: float
    # The merge the encoder builds an LOD tree with (lod.LOD_MERGES; the manifest's lod.merge, format 1.9), None
    # where the tree is not its own (an imported one: sog_import.py, EncodeOptions.imported_tree). A tree handed
    # in by a caller that built it with plan_tiles and these options (evaluate.py) is the encoder's own.
    lod_merge: str | None = None
    # Step 5's viewing scales (lod.md 6): px on the first merged level and above it (lod.viewing_scales_px()).
    viewing_scale_px: tuple[float, float] | None = None
    # The merged levels' refinement (EncodeOptions.lod_refiner, lod_refine.py; the manifest's lod.refinement, 1.11),
    # None where the tree was not refined.
    lod_refinement: LodRefinement | None = None
    # The suggested camera turned about up by this much (EncodeOptions.camera_azimuth_deg).
    camera_azimuth_deg: float = 0.0


@dataclass
class EncodePlan:
    """The in-memory engine's plan: the scene's, and its tiles with their splats."""

    scene: ScenePlan
    tiles: list[Tile]  # breadth-first, root first; a single tile's bounds may still be None (jobs compute them)
    sample: SceneSample

    @property
    def context(self) -> TileContext:
        return self.scene.context


def resolve_sh_degree(opts: EncodeOptions, g: Gaussians) -> int:
    return g.sh_degree if opts.sh_degree is None else min(opts.sh_degree, g.sh_degree)


# Inputs whose file name is the format's, not the scene's (a streamed SOG's index, an unbundled SOG's meta): such a
# scene is named after the directory that holds them (playbot/lod-meta.json is "playbot", not "lod-meta").
_FORMAT_FILE_NAMES = ("lod-meta.json", "meta.json")


def scene_name(opts: EncodeOptions, source_name: str | None, out_name: str | None) -> str:
    if opts.name:
        return opts.name
    if source_name:
        path = source_name if is_url(source_name) else os.path.abspath(source_name).replace(os.sep, "/")
        parent, _, base = path.rstrip("/").rpartition("/")
        if base.lower() in _FORMAT_FILE_NAMES:
            base = parent.rpartition("/")[2]
        else:
            base = os.path.splitext(base)[0]
        if base:
            return base
    return out_name or "scene"


def plan_tiles(g: Gaussians, opts: EncodeOptions, progress: Progress,
               on_level: Callable[[list[Tile]], None] | None = None) -> list[Tile]:
    """The LOD tree, or one tile holding every splat (bounds left to the jobs) when LOD is off or not needed.
    `on_level`: lod.build_subtree's (a tree's levels as they are final; not called for one tile)."""
    if opts.lod and len(g) > opts.max_leaf_splats:
        merge = opts.resolved_lod_merge(in_memory=True)
        log.info("LOD merge %s%s", merge, "" if opts.lod_merge is not None else " (the default in memory; "
                 "--lod-merge grid: a faster encode, 0.5-0.7x the CPU, and a blurrier picture at most splat budgets)")
        return build_tiles(g, max_leaf_splats=opts.max_leaf_splats, reduction=opts.reduction, progress=progress,
                           reorder_input=opts.reorder_input, merge=merge, on_level=on_level)
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


def plan_formats(opts: EncodeOptions) -> tuple[dict[str, str], str]:
    """Texel formats per attribute and the chunk order from the options (format/presets.py); a UsageError for an
    unknown preset or format, before anything is read."""
    formats = resolve_formats(opts.preset, opts.overrides)
    return formats, resolve_chunk_order(opts.chunk_order, formats)


def plan_scene(opts: EncodeOptions, formats: dict[str, str], chunk_order: str, sh_degree: int, sample: SceneSample,
               splats: int, bounds: Box, name: str, progress: Progress = no_progress, lod_merge: str | None = None,
               *, tree: bool) -> tuple[ScenePlan, SceneSample]:
    """The scene-wide decisions every engine takes from the scene sample: the SH codebook (fitted on the sample's
    rows, which are then dropped: below the sample size they are every splat's SH, 180 MB at 1M splats of SH3,
    which kept the codebook presets' LOD encode above 3x the input in peak memory) and the up direction. Returns
    the plan and the sample without its codebook rows (it still gives the camera). `lod_merge`: the merge the
    engine builds its LOD tree with (recorded in the manifest), None for a tree it did not build. `tree`: the scene
    will have more than one tile (its tile payloads then named by short digests where the options write 1.15)."""
    choice = codebook_choice(opts, sh_degree)
    codebook = None
    if choice != "off":
        progress("codebook", 0.0)
        codebook = sample.codebook(choice)
        progress("codebook", 1.0)
    sample = replace(sample, codebook_rows=None, codebook_weights=None)
    up = plan_up(opts, sample)
    formats, steps, palettes = plan_palettes(opts, formats, sample.palettes)
    formats = plan_rotation_format(opts, formats, sample.orient.rotations, sample.orient.log_scales)
    packing = compression_preset(opts.preset, sh_degree)  # a per-splat SH preset's base where no SH band is kept
    context = TileContext(formats, chunk_order, sh_degree, codebook, opts.zstd_level_for(sh_degree),
                          opts.resolved_transport, steps, palettes, preset_block_slack(packing),
                          preset_zstd_min_match(packing), preset_one_block_slack(packing),
                          rotation_gauge(opts.preset, formats),
                          short_tile_names(tree, opts.compact_table, opts.short_digests))
    return ScenePlan(context, opts.preset, name, splats, bounds, up, opts.max_leaf_splats, float(opts.reduction),
                     lod_merge, viewing_scales_px() if lod_merge is not None else None,
                     camera_azimuth_deg=opts.camera_azimuth_deg), sample


def plan_encode(g: Gaussians, opts: EncodeOptions, progress: Progress = no_progress,
                source_name: str | None = None, out_name: str | None = None, screened: bool = False,
                tiles: list[Tile] | None = None,
                on_level: Callable[[TileContext, list[Tile]], None] | None = None) -> EncodePlan:
    """The in-memory engine's plan. `screened`: `g` was read through io.read_gaussians, which refused (or
    dropped) values beyond the format's domain already, so the check is not repeated. `tiles`: a tree built
    already (a foreign LOD tree: sog_import.py, with `opts.imported_tree`; or plan_tiles' own under these options:
    evaluate.py), breadth-first with bounds and errors, its leaves holding `g`; otherwise the LOD builder makes one.
    `on_level(context, tiles)`: the tiles of each level of the tree it builds, as they are final (plan_tiles); not
    called where a refinement would replace them afterwards, nor for a tree handed in."""
    formats, chunk_order = plan_formats(opts)
    if len(g) == 0:
        raise InputError(source_name or "<gaussians>", None, "holds no splats (none, or none left after dropping "
                         "invalid ones); nothing to encode")
    # The encoder never writes what its readers refuse: values beyond the format's domain (format.md 4.8) would
    # make a range non-finite or decode to NaN.
    violations = [] if screened else domain_violations(g)
    if violations:
        raise InputError(source_name or "<gaussians>", None, describe_violations(violations, len(g))[1])
    check_codebook_option(opts, g.sh_degree, source_name)
    sh_degree = resolve_sh_degree(opts, g)
    if sh_degree != g.sh_degree:
        g = g.with_sh_degree(sh_degree)
    one_tile = not (opts.lod and len(g) > opts.max_leaf_splats)  # plan_tiles' choice, known before the tree
    # An input already cut into quantised chunks keeps its order in a single tile (input_is_chunk_quantised).
    if opts.chunk_order == "auto" and chunk_order == "morton" and one_tile and input_is_chunk_quantised(g):
        chunk_order = "input"
    sample = SceneSample.of(g, with_codebook=codebook_choice(opts, sh_degree) != "off",
                            palette_planes=palette_planes(formats))
    scene, sample = plan_scene(opts, formats, chunk_order, sh_degree, sample, len(g), positions_box(g.positions),
                               scene_name(opts, source_name, out_name), progress,
                               None if tiles is not None and opts.imported_tree else opts.resolved_lod_merge(True),
                               tree=len(tiles) > 1 if tiles is not None else not one_tile)
    progress("tiles", 0.0)
    own_tree = tiles is None
    if tiles is None:
        final = on_level is not None and opts.lod_refiner is None
        tiles = plan_tiles(g, opts, progress, (lambda level: on_level(scene.context, level)) if final else None)
    elif sh_degree != g.sh_degree or any(t.gaussians.sh_degree != sh_degree for t in tiles):
        tiles = [replace(t, gaussians=t.gaussians.with_sh_degree(sh_degree)) for t in tiles]
    progress("tiles", 1.0)
    if opts.lod_refiner is not None and own_tree and len(tiles) > 1:
        # lod.md 6's optional step: after the tree, before any payload is quantised; leaves stay the originals.
        tiles, record = refine_tree(g, tiles, scene.up, opts.lod_refiner, progress)
        scene = replace(scene, lod_refinement=record)
    elif opts.lod_refiner is not None and own_tree:
        # asked for, and nothing to do: said, not silent (the manifest then records no refinement)
        log.info("LOD refinement: the tree is one tile (%s splats, under --max-leaf-splats), with no merged level; "
                 "nothing refined", f"{len(g):,}")
    return EncodePlan(scene, tiles, sample)


def plan_palettes(opts: EncodeOptions, formats: dict[str, str], fitted: dict[str, list[PaletteValues]] | None
                  ) -> tuple[dict[str, str], dict[str, TileStep], dict[str, np.ndarray] | None]:
    """The formats, tile steps and scene palettes (format.md 4.3.2) of the encode: a palette attribute whose values
    do not fit its palettes (more than 256 distinct values in one: PaletteValues.many) falls back to its preset's
    fallback (presets.py PRESET_PALETTE_FALLBACK), logged in one line; the palettes the preset merges are merged
    pairwise (PRESET_PALETTE_MERGE, codec.merged_pairs). Decided from every splat's values (sample.py), so every
    engine decides alike."""
    fitted = fitted or {}
    attribute = {s.name: s.attribute for s in BASE_PLANES}
    unfit = {attribute[name] for name, groups in fitted.items() if any(p.many for p in groups)}
    formats, steps, fell = palette_fallback(opts.preset, opts.overrides, unfit, formats)
    if fell:
        log.info("%s: %s fell back to %s (values do not fit 256-entry palettes)", opts.preset, ", ".join(fell),
                 ", ".join(f"{a} {formats[a]}" for a in fell))
    kept = {name: groups for name, groups in fitted.items() if formats[attribute[name]] in PALETTE_FORMATS}
    if not kept:
        return formats, steps, None
    palettes = scene_palettes(kept)
    for name, indices in PRESET_PALETTE_MERGE.get(opts.preset, {}).items():
        if name in palettes and name not in (opts.overrides or {}):
            for i in indices:
                palettes[name][i] = merged_pairs(palettes[name][i])
    return formats, steps, palettes


def rotation_error_deg(rotations: np.ndarray, log_scales: np.ndarray, preset: str, formats: dict[str, str]
                       ) -> np.ndarray:
    """(N,) float64: each splat's rotation error in degrees as `preset` with these formats stores it: the angle of
    the rotation between the quaternion the encoder quantises (the input's in the preset's gauge, rotation_canon) and
    the one a reader decodes (codec's numpy reference through the texels). A gauge change is exact, so this is the
    angle by which the splat's axes turn."""
    q = np.asarray(rotations, np.float32)
    gauge = rotation_gauge(preset, formats)
    if gauge:
        q, _ = canonical_gauge(q, log_scales, gauge)
    fmt = formats["rotation"]
    stored = decode_rotations(unpack_texels(fmt, pack_texels(fmt, encode_rotations(q, fmt))), fmt)
    a, b = q.astype(np.float64), stored.astype(np.float64)
    # conj(a) * b, the turn from one to the other; its angle by atan2, which stays exact near 0 (arccos does not)
    w = np.sum(a * b, axis=1)
    v = a[:, :1] * b[:, 1:] - b[:, :1] * a[:, 1:] - np.cross(a[:, 1:], b[:, 1:])
    return np.degrees(2.0 * np.arctan2(np.linalg.norm(v, axis=1), np.abs(w)))


def plan_rotation_format(opts: EncodeOptions, formats: dict[str, str], rotations: np.ndarray,
                         log_scales: np.ndarray) -> dict[str, str]:
    """The formats with the rotation format the preset measures closest to the input (presets.rotation_choices):
    of its candidates, the one with the smallest mean rotation error (rotation_error_deg) over these rotations (the
    scene sample's, so every engine decides alike), the preset's own on a tie; logged in one line. Unchanged for a
    preset with one rotation format, or one given by the options."""
    choices = rotation_choices(opts.preset, opts.overrides)
    if len(choices) < 2 or formats["rotation"] != choices[0] or len(rotations) == 0:
        return formats
    errors = {fmt: float(np.mean(rotation_error_deg(rotations, log_scales, opts.preset, {**formats, "rotation": fmt})))
              for fmt in choices}
    best = min(choices, key=lambda fmt: errors[fmt])  # the first of equal errors: the preset's own
    log.info("%s rotations: %s (mean angle error %s over %s sampled splats)", opts.preset, best,
             ", ".join(f"{fmt} {errors[fmt]:.3f} deg" for fmt in choices), f"{len(rotations):,}")
    return {**formats, "rotation": best}


def palette_planes(formats: dict[str, str]) -> tuple[str, ...]:
    """The base planes stored as palette indices (format.md 4.3.2): their scene palettes are fitted in the plan."""
    return tuple(s.name for s in BASE_PLANES if formats.get(s.attribute) in PALETTE_FORMATS)


def plan_up(opts: EncodeOptions, sample: SceneSample) -> tuple[float, float, float]:
    if opts.up is not None:
        return tuple(float(v) for v in opts.up)
    choice = sample.up()
    log.info("up %s: %s (--up overrides it)", ",".join(f"{v:g}" for v in choice.up), choice.reason)
    return choice.up


def plan_camera(plan: EncodePlan) -> CameraEntry:
    """The suggested initial camera (format_spec/camera.md), from the scene sample."""
    return plan.sample.camera(plan.scene.up, plan.scene.camera_azimuth_deg)


def positions_box(positions: np.ndarray) -> Box:
    return Box(tuple(float(v) for v in positions.min(axis=0)), tuple(float(v) for v in positions.max(axis=0)))
