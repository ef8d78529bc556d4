"""What an encode is asked to do (the CLI's options, as one value every stage of the encoder reads)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from ..format.container import DEFAULT_ZSTD_LEVEL
from ..format.presets import DEFAULT_PRESET, compression_preset, preset_transport, preset_zstd_level
from ..lod_refine import LodRefiner

# progress(stage, fraction in [0, 1]); stages: codebook, tiles, encode
Progress = Callable[[str, float], None]


def no_progress(stage: str, fraction: float) -> None:
    return None


# The LOD merge of an encode that names none: "auto" on either engine. In memory (BENCHMARKS.md, "LOD against peers",
# the per-tile choice: a median 0.36 dB above the best peer at 2-50 % budgets, the grid 0.43 dB below); by
# partitions, auto inside each partition (its merge domain, partitioned.merge_domain_level) and over the whole
# level above them: -0.25 to +0.09 dB from the in-memory auto on biker and flowers in 4 and 16 partitions, above the
# grid at 7 of 8 points (BENCHMARKS.md, "The auto merge in partitioned encodes"; the grid until branch partauto31).
IN_MEMORY_LOD_MERGE = "auto"
PARTITIONED_LOD_MERGE = "auto"


def default_lod_merge(in_memory: bool) -> str:
    """The LOD merge used when the options name none: IN_MEMORY_LOD_MERGE or PARTITIONED_LOD_MERGE."""
    return IN_MEMORY_LOD_MERGE if in_memory else PARTITIONED_LOD_MERGE


@dataclass
class EncodeOptions:
    preset: str = DEFAULT_PRESET
    overrides: dict[str, str] = field(default_factory=dict)
    sh_degree: int | None = None  # drop bands above this
    zstd_level: int | None = None  # None: the preset's (format/presets.py PRESET_ZSTD_LEVEL), else DEFAULT_ZSTD_LEVEL
    # How payload sections are stored (format/transport.py): "fields" (the fields1 filter where it is smaller than
    # the byte shuffle; format 1.2), "keyed" (and morton1 positions, format 1.6), "shuffle" (what 1.0/1.1 readers
    # read), "none". None: the preset's (format/presets.py PRESET_TRANSPORT), else "fields".
    transport: str | None = None
    lod: bool = True
    # Leaf tile size: measured against bytes to converge and requests on a 20 Mbit/s + 40 ms link (BENCHMARKS.md,
    # "Tile size"): 16,384 converged an overview 12 % and a close-up 26 % sooner than 65,536, with a 192 KB manifest
    # at 1M splats (4,096 halves the tiles' bytes no further and doubles the manifest and the requests).
    max_leaf_splats: int = 16384
    # Splats between LOD levels: 2x steps spend a splat budget in small steps and measured sharper at equal splat
    # counts than 4x steps (BENCHMARKS.md, "LOD merges").
    reduction: float = 2.0
    # How each level's splats are grouped for merging (lod.LOD_MERGES, format_spec/lod.md 6): "grid" (a Morton grid
    # per tile, every tile halved), "cost" (groups by merge cost over the whole level, the count each tile keeps
    # decided across the scene) or "auto" (the cost merge's counts, and per tile the cost merge's groups or the
    # grid's, whichever is closer to the tile's members); cost in-process encodes only, auto in partitioned ones
    # inside each partition (lod_merge_domain_splats). None (the default): "auto" (default_lod_merge).
    # auto's budgeted picture is a median 0.3 dB above the best peer's where the grid's is 0.4 dB below, for
    # 1.4-1.9x the grid's encode CPU (BENCHMARKS.md, "LOD against peers", the default merge; autofast4).
    lod_merge: str | None = None
    # A partitioned encode's "auto" merge groups each level inside subtrees of at most this many original splats
    # (its merge domains: the partitions, partitioned.merge_domain_level), the levels above them by upper domains
    # (lod_upper_domain_roots, below); a function of the scene's splat count, so the output is the same on any
    # engine and worker count.
    # 2^20: 16 partitions of a 16M-splat scene (16 workers busy); 2^21 left half of them idle (BENCHMARKS.md, "The
    # auto merge in partitioned encodes", 16M on 16 cores), and domains 8-64x smaller measured as close to in memory.
    lod_merge_domain_splats: int = 1 << 20
    # Above the merge domains, the partitions' roots are grouped into upper domains (partitioned.upper_domain_levels):
    # the subtrees of the shallowest tile level whose tiles hold at most this many roots, each level of them grouped
    # over its own tiles in a task of its own, tier after tier up to the root (one task a level was serial: 35 s of a
    # 249 s encode of 60M splats, growing with the partitions; with it 26.9 s of 216.6 s on the same 16 cores, the
    # per-level folds still serial; BENCHMARKS.md, "Upper domains"). A function of the
    # tree's shape, so the output is the same on any engine and worker count. 8: at 60M (64 partitions) the lowest
    # upper levels in 8 parallel tasks of at most 8 roots (128k members at 16,384 splats a leaf).
    lod_upper_domain_roots: int = 8
    # Manifest pages (format.md 6.1): a tree of more than `page_tiles` tiles (0: never) is written as a root
    # manifest of its top `page_levels` levels and pages of the next `page_levels` levels below each of its
    # deepest tiles. Both measured against manifest bytes before the first frame and page fetches (BENCHMARKS.md,
    # "Manifest pages"): scenes up to a few million splats keep one manifest, as before.
    # The LOD tree handed to the encoder (`tiles=`) is an imported one (sog_import.py: a streamed SOG's or RAD's
    # levels), not one lod.py built: the manifest then does not record a merge or viewing scales (format.md 6).
    imported_tree: bool = False
    # The optional refinement of the merged levels against renders of the full detail (lod_refine.py, lod.md 6;
    # `encode --lod-refine`): a callable the shell hands in (refine_gpu.levels, torch + gsplat on a CUDA GPU), run on
    # the in-memory engine's own tree after it is built and before any payload is quantised. None: not refined.
    lod_refiner: LodRefiner | None = None
    page_tiles: int = 1024
    page_levels: int = 6
    # A tree's tiles as the compact tile table (format.md 6.2, version 1.12: bounds as f32 rounded outward, the table
    # zstd-compressed): a third of the 1.8 table's bytes on the real scenes, which a small budget reads before any
    # tile (issue 31; BENCHMARKS.md, "Manifest pages"). False: the 1.8 table and the version the scene needs.
    compact_table: bool = True
    # The compact table's files named by the first 16 bytes of their SHA-256 (format.md 6.2, version 1.15: 16 B a
    # payload in the table instead of 32, which do not compress: 5.5-6.8 KB of a 45-150k-splat scene's 11.8-13.5 KB
    # manifest; issue 31, branch digest31). False: the whole SHA-256, version 1.12.
    short_digests: bool = True
    # With short digests, each box as u8 steps of its parent's and each radius as u8 steps of its box's half diagonal
    # (format.md 6.2, version 1.16; issue 31, branch box16). False: the f32 boxes and radii, version 1.15.
    relative_boxes: bool = True
    name: str | None = None
    up: tuple[float, float, float] | None = None
    # The suggested camera (the manifest's `camera`) turned by this many degrees about up (camera.turn_about_up;
    # `encode --camera-azimuth`): no rule from the splats alone tells a scene's front (camera.md), the user can.
    camera_azimuth_deg: float = 0.0
    chunk_order: str = "auto"  # "morton", "luminance", or "auto" (luminance when only colour/SH are BC-compressed)
    # SH codebook: None = the preset's choice, "off", "auto" or an entry count (format_spec/format.md 4.7).
    sh_codebook: str | int | None = None
    # Let the LOD builder permute the input's arrays in place instead of copying the scene (saves one copy of
    # the whole scene). Only for callers that own the Gaussians and do not need their order afterwards.
    reorder_input: bool = False

    def resolved_lod_merge(self, in_memory: bool = True) -> str:
        """The LOD merge an encode uses: the option, else the default of its engine (default_lod_merge)."""
        return self.lod_merge if self.lod_merge is not None else default_lod_merge(in_memory)

    @property
    def resolved_transport(self) -> str:
        """The transport the payloads are written with: the option, else the preset's, else "fields"."""
        return self.transport if self.transport is not None else preset_transport(self.preset, "fields")

    @property
    def resolved_zstd_level(self) -> int:
        """The zstd level the payloads are written with: the option, else the preset's, else the default (of a
        scene with SH bands: zstd_level_for gives a scene's)."""
        return self.zstd_level_for(1)

    def zstd_level_for(self, sh_degree: int) -> int:
        """The zstd level the payloads of a scene keeping `sh_degree` SH bands are written with: the option, else
        the preset's (its base's where no band is kept: presets.compression_preset), else the default."""
        if self.zstd_level is not None:
            return self.zstd_level
        return preset_zstd_level(compression_preset(self.preset, sh_degree), DEFAULT_ZSTD_LEVEL)

