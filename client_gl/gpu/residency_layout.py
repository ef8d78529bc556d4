"""How splats are laid out on the GPU: the constants the pool (client_gl.gpu.pool), the shader generator
(client_gl.gpu.shadergen) and the slot budget (client_gl.gpu.slots) share. Pure: no GL.

format_spec/renderer.md 1 describes the layout: slots of 256 splats (one 16x16 block of every atlas), a 64-word
range record per slot (word offsets RANGE_WORDS), a slot-state texel per slot (drawn flag, resident SH bands), and
for SH codebook scenes the codebook textures.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from splatstream.errors import UsageError
from splatstream.format.codec import gpu_format
from splatstream.format.layout import BLOCK, CHUNK_SIZE, MAX_BLOCK_ROWS, MAX_BLOCKS_PER_ROW, texture_size
from splatstream.format.planes import BASE_PLANES, MAX_SH_DEGREE, SH_INDEX_FORMAT, SH_INDEX_PLANE, band_plane
from splatstream.format.texformats import blob_size, get_format
from splatstream.gaussians import SH_BAND_COEFFS

CHUNK = CHUNK_SIZE  # splats per slot
MAX_COLS = MAX_BLOCKS_PER_ROW  # slots per atlas row at most (atlas width 2048 texels)
MAX_ROWS = MAX_BLOCK_ROWS  # atlas rows at most (16384 texels, the GL 4.3 minimum of GL_MAX_TEXTURE_SIZE)
SH_BAND_LAYERS: dict[int, int] = dict(SH_BAND_COEFFS)  # texture-array layers of each SH band's atlas

# Word offsets inside a slot's 64-word range record (RGBA32UI, 16 texels a slot). Words 60-63 are free.
RANGE_WORDS = {"position": 0, "count": 6, "tile": 7, "scale": 8, "color": 11, "sh1": 15, "sh2": 24, "sh3": 39}
RANGE_RECORD_WORDS = 64
RANGE_RECORD_BYTES = RANGE_RECORD_WORDS * 4
# Slot state: one RG8UI texel per slot at (slot % cols, slot // cols): r = drawn (the draw mask), g = the SH bands
# resident for the slot's tile (0..3).
SLOT_STATE_BYTES = 2

# Texture unit of each plane's atlas, the range table and the slot state; with an SH codebook the sh_index atlas,
# the codebook bands and the codebook's range table (unit 8 is left to the front-to-back draw's saturation pass).
TEXTURE_UNITS = {"position": 0, "rotation": 1, "scale": 2, "color": 3, "sh1": 4, "sh2": 5, "sh3": 6, "ranges": 7,
                 "sh_index": 9, "cb_sh1": 10, "cb_sh2": 11, "cb_sh3": 12, "cb_ranges": 13, "slot_state": 14}

BASE_PLANE_NAMES = tuple(p.name for p in BASE_PLANES)
_PLANE_SPECS = {p.name: p for p in (*BASE_PLANES, SH_INDEX_PLANE, *(band_plane(b) for b in SH_BAND_LAYERS))}


@dataclass(frozen=True)
class CodebookLayout:
    """Shape of a scene's SH codebook (format.md 4.7): its texel format and entry count K. The band textures are
    laid out as the file stores them (texture_size of ceil(K / 256) chunks)."""

    format: str
    entries: int

    def __post_init__(self) -> None:
        get_format(self.format)
        if not 1 <= self.entries <= 65536:
            raise UsageError(f"SH codebook of {self.entries} entries: expected 1..65536")

    @property
    def chunks(self) -> int:
        return max(1, -(-self.entries // CHUNK))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in texels of each band's texture."""
        return texture_size(self.chunks)


@dataclass(frozen=True)
class PoolLayout:
    """What a pool holds: texel formats by attribute, SH bands (0..3) and the SH codebook's shape (None: none).

    The generated shaders depend on exactly this (shadergen.decode_header)."""

    formats: Mapping[str, str]  # attribute -> texel format ("position", "rotation", "scale", "color", "sh")
    sh_degree: int
    codebook: CodebookLayout | None = None
    planes: tuple[str, ...] = field(init=False)  # atlases: base planes, then sh_index or sh1..sh{sh_degree}

    def __post_init__(self) -> None:
        if not 0 <= self.sh_degree <= MAX_SH_DEGREE:
            raise UsageError(f"SH degree {self.sh_degree}: expected 0..{MAX_SH_DEGREE}")
        if self.codebook is not None and self.sh_degree == 0:
            object.__setattr__(self, "codebook", None)  # no SH bands: nothing to look up
        attributes = {"position", "rotation", "scale", "color"} | ({"sh"} if self.sh_degree else set())
        missing = attributes - set(self.formats)
        if missing:
            raise UsageError(f"pool formats lack {', '.join(sorted(missing))}")
        for attribute in attributes:
            get_format(self.formats[attribute])
        # Palette planes are held as ranged 16-bit values (codec.palette_as_ranged, done by the pool on join).
        object.__setattr__(self, "formats", {a: gpu_format(f) for a, f in self.formats.items()})
        if self.codebook is not None:
            planes = BASE_PLANE_NAMES + ("sh_index",)
        else:
            planes = BASE_PLANE_NAMES + tuple(f"sh{b}" for b in range(1, self.sh_degree + 1))
        object.__setattr__(self, "planes", planes)

    @property
    def uses_codebook(self) -> bool:
        return self.codebook is not None

    @property
    def codebook_format(self) -> str | None:
        return None if self.codebook is None else self.codebook.format

    def plane_format(self, plane: str) -> str:
        """Texel format of a plane's atlas."""
        if plane == "sh_index":
            return SH_INDEX_FORMAT
        return self.formats[_PLANE_SPECS[plane].attribute]

    def plane_layers(self, plane: str) -> int:
        """Texture-array layers of a plane's atlas (0: a plain 2D texture)."""
        return SH_BAND_LAYERS[int(plane[2:])] if plane in ("sh1", "sh2", "sh3") else 0

    def band_planes(self, band: int) -> tuple[str, ...]:
        """Atlas planes a tile brings for SH band `band`: sh<band>; with a codebook only band 1 (sh_index)."""
        if self.codebook is not None:
            return ("sh_index",) if band == 1 else ()
        return (f"sh{band}",)

    # --- GPU bytes (exact: what the pool allocates) -------------------------------------------------------------
    def slot_bytes(self) -> int:
        """GPU bytes per slot: one 16x16 block of every atlas (all layers), its range record and its state."""
        texels = sum(blob_size(get_format(self.plane_format(p)), BLOCK, BLOCK, max(1, self.plane_layers(p)))
                     for p in self.planes)
        return texels + RANGE_RECORD_BYTES + SLOT_STATE_BYTES

    def fixed_bytes(self) -> int:
        """GPU bytes that do not depend on the slot count: the SH codebook's band textures and range table."""
        if self.codebook is None:
            return 0
        width, height = self.codebook.size
        fmt = get_format(self.codebook.format)
        bands = sum(blob_size(fmt, width, height, SH_BAND_LAYERS[b]) for b in range(1, self.sh_degree + 1))
        return bands + self.codebook.chunks * RANGE_RECORD_BYTES

    def pool_bytes(self, slots: int) -> int:
        """GPU bytes of a pool of `slots` slots (a whole number of atlas rows: see atlas_grid)."""
        cols, rows = atlas_grid(slots)
        return self.fixed_bytes() + cols * rows * self.slot_bytes()


def atlas_grid(slots: int) -> tuple[int, int]:
    """(cols, rows) of slots of an atlas holding at least `slots` slots: the fewest rows of at most MAX_COLS slots
    (rows = ceil(slots / MAX_COLS)), and the fewest columns for them (cols = ceil(slots / rows)).

    A pool's capacity is cols * rows, at most rows - 1 slots above `slots`: the slots of a partly used last row are
    allocated anyway, so they are usable. Rows of MAX_COLS each would round a budget of 1.9 rows down to one
    (58 % of a 0.9 MiB budget on guitar: BENCHMARKS.md, "GPU memory budget filled"). The grid of cols * rows is
    (cols, rows) again (cols * rows > MAX_COLS * (rows - 1), as slots is)."""
    slots = max(1, int(slots))
    rows = -(-slots // MAX_COLS)
    return -(-slots // rows), rows
