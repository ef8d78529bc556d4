"""Planes and payload groups (format_spec/format.md 4.4, 4.7 and 5): which planes a payload holds.

A plane is one quantity of every splat stored as a texture (its texels) plus, for ranged planes, per-chunk
ranges. A tile has the group `base` (position, rotation, scale, color) and one group per SH band; with an SH
codebook its only SH group is `sh1`, holding each splat's codebook index.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..gaussians import SH_BAND_COEFFS
from .layout import CHUNK_SIZE

MAX_SH_DEGREE = 3


@dataclass(frozen=True)
class PlaneSpec:
    name: str
    attribute: str       # preset attribute whose texel format this plane uses
    components: int
    layers: int
    range_dtype: str     # "" (not ranged), "<f4" or "<f2"

    @property
    def range_name(self) -> str:
        return self.name + ".range"

    @property
    def palette_name(self) -> str:
        return self.name + ".palette"


BASE_PLANES = (
    PlaneSpec("position", "position", 3, 1, "<f4"),
    PlaneSpec("rotation", "rotation", 4, 1, ""),
    PlaneSpec("scale", "scale", 3, 1, "<f2"),
    PlaneSpec("color", "color", 4, 1, "<f2"),
)
BASE_PLANE_NAMES = tuple(p.name for p in BASE_PLANES)

# With an SH codebook, a tile's sh1 payload holds this plane: each splat's codebook entry (texel format index16).
SH_INDEX_PLANE = PlaneSpec("sh_index", "sh", 1, 1, "")
SH_INDEX_FORMAT = "index16"

# Palette planes (format.md 4.3.2, format 1.6): the attributes a palette texel format (pal8x4) may hold, and per
# plane which palette each component indexes. The three log scales share one palette, as SH0's R, G and B do (a
# SOG file's scale and colour codebooks are shared so); opacity has its own. A palette has PALETTE_ENTRIES values.
PALETTE_ATTRIBUTES = ("scale", "color")
PALETTE_GROUPS = {"scale": (0, 0, 0), "color": (0, 0, 0, 1)}
PALETTE_ENTRIES = 256


def palette_count(spec: PlaneSpec) -> int:
    """Palettes of a palette plane (its `<name>.palette` section holds this many rows of PALETTE_ENTRIES)."""
    return max(PALETTE_GROUPS[spec.name]) + 1
RANGE_DTYPE_NAMES = {"<f4": "f32", "<f2": "f16"}


def band_plane(band: int) -> PlaneSpec:
    return PlaneSpec(f"sh{band}", "sh", 3, SH_BAND_COEFFS[band], "<f2")


def band_of(group: str) -> int:
    """SH band of a group name `sh<b>` (0 for `base`)."""
    return int(group[2:]) if group.startswith("sh") and group[2:].isdigit() else 0


def group_planes(group: str, codebook: bool = False) -> tuple[PlaneSpec, ...]:
    """Planes of a tile payload group; with an SH codebook the tile's sh1 group holds the index plane."""
    if group == "base":
        return BASE_PLANES
    band = band_of(group)
    if not 1 <= band <= MAX_SH_DEGREE:
        raise ValueError(f"no payload group {group!r}")
    if codebook:
        if band != 1:
            raise ValueError(f"with an SH codebook a tile has no {group!r} group")
        return (SH_INDEX_PLANE,)
    return (band_plane(band),)


def groups_for_degree(sh_degree: int, codebook: bool = False) -> list[str]:
    """Payload groups of a tile: base, then one per SH band (only sh1, the index, with a codebook)."""
    if codebook:
        return ["base"] + (["sh1"] if sh_degree >= 1 else [])
    return ["base"] + [f"sh{b}" for b in range(1, sh_degree + 1)]


def chunks_for(splats: int) -> int:
    """Chunks of CHUNK_SIZE holding `splats` splats (a tile of 0 splats still has one block)."""
    return max(1, -(-int(splats) // CHUNK_SIZE))


def palette_shape(spec: PlaneSpec) -> tuple[int, int, int, int]:
    """Shape of a palette plane's `<name>.palette` section (format.md 4.3.2): (palettes, 1, 1, 256) float32."""
    return (palette_count(spec), 1, 1, PALETTE_ENTRIES)
