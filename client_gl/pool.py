"""GPU residency of encoded splats: a pool of 256-splat chunk slots in one texture atlas per plane.

Tiles JOIN and LEAVE: a tile's chunk blocks (16x16 texels, exactly as the file stores them, still in their texel
format) are copied into free slots of the atlases, and its per-chunk ranges into the slot's row of the range table;
leaving frees the slots (their splat count becomes 0, so culling skips them). One draw covers every resident chunk.

Atlas layout: slot s is the 16x16 block at ((s % cols) * 16, (s // cols) * 16), cols = atlas width / 16, the same
block layout as a tile texture (format_spec/format.md 4.1). Global splat index = s * 256 + j.

Range table: an RGBA32UI texture with 16 texels (64 words) per slot at ((s % cols) * 16, s // cols); word offsets
are RANGE_WORDS (f32 position ranges, f16 pairs for the others, as the file stores them).

SH codebook (format v1.1, format_spec/format.md): the pool holds an `sh_index` atlas (index16, R16UI, one texel
per splat: its codebook entry) instead of the sh1..sh3 atlases, and the codebook: one array texture per band in
the codebook's stored texel format and block layout (entry e at chunk e >> 8, Morton j = e & 255), and a codebook
range table, an RGBA32UI texture of one 64-word record (16 texels) per codebook chunk, row c = chunk c, with the
band ranges at the same RANGE_WORDS offsets as the pool's range table. Uploaded once per pool; bands can be set
later (progressive SH); a band not set yet decodes to 0 (its ranges are zero).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from splatstream.errors import UsageError
from splatstream.format.codec import EncodedPlane
from splatstream.format.planes import SH_INDEX_FORMAT
from splatstream.format.texformats import get_format
from splatstream.gaussians import SH_BAND_COEFFS

from .gl import BLOCK_BYTES, GL_RGBA32UI, INTERNAL_FORMATS, RawTexture

CHUNK = 256
BLOCK = 16
MAX_COLS = 128
SH_BAND_LAYERS = dict(SH_BAND_COEFFS)
# Word offsets inside a slot's 64-word range record.
RANGE_WORDS = {"position": 0, "count": 6, "tile": 7, "scale": 8, "color": 11, "sh1": 15, "sh2": 24, "sh3": 39}
RANGE_RECORD_WORDS = 64
PLANE_ATTRIBUTE = {"position": "position", "rotation": "rotation", "scale": "scale", "color": "color",
                   "sh1": "sh", "sh2": "sh", "sh3": "sh", "sh_index": "sh"}


@dataclass
class TileData:
    """One tile's planes as the file stores them (EncodedPlane per plane name) and its splat count."""

    splats: int
    planes: dict[str, EncodedPlane]


@dataclass
class _Resident:
    slots: np.ndarray
    splats: int


@dataclass
class HostMirror:
    """What the CPU sort path needs per splat slot: decoded centres, opacity, largest log scale."""

    positions: np.ndarray
    opacity: np.ndarray
    max_log_scale: np.ndarray
    counts: np.ndarray = field(default=None)  # splats per slot


def _runs(slots: np.ndarray, cols: int) -> list[tuple[int, int, int]]:
    """(first index into slots, first slot, length) of runs of consecutive slots within one atlas row."""
    runs = []
    i = 0
    while i < len(slots):
        j = i + 1
        while j < len(slots) and slots[j] == slots[j - 1] + 1 and slots[j] % cols != 0:
            j += 1
        runs.append((i, int(slots[i]), j - i))
        i = j
    return runs


def layer_blob(plane: EncodedPlane, layer: int) -> np.ndarray:
    """One layer's texture blob (uint8) of an encoded plane."""
    layers = getattr(plane, "layers", None)
    if isinstance(layers, (list, tuple)):
        return np.frombuffer(layers[layer], np.uint8)
    if layers is not None:  # a lazy iterator: materialise once
        plane.layers = [np.asarray(b) for b in layers]
        return np.frombuffer(plane.layers[layer], np.uint8)
    texels = plane.texels  # single-blob form (layers concatenated)
    size = texels.size // plane.spec.layers
    return texels[layer * size:(layer + 1) * size]


def _chunk_blocks(plane: EncodedPlane, layer: int, chunks: int) -> np.ndarray:
    """(chunks, rows, cols, bytes) blocks of one layer: 16x16 texels, or 4x4 BC blocks for block formats."""
    fmt = get_format(plane.format)
    blob = layer_blob(plane, layer)
    if fmt.block > 1:
        unit, side = BLOCK_BYTES[INTERNAL_FORMATS[fmt.gl_internal]], BLOCK // 4
        h, w = plane.height // 4, plane.width // 4
    else:
        unit, side = fmt.bits_per_texel // 8, BLOCK
        h, w = plane.height, plane.width
    img = blob.reshape(h // side, side, w // side, side, unit)
    return img.transpose(0, 2, 1, 3, 4).reshape(-1, side, side, unit)[:chunks]


class ChunkPool:
    """Atlases for `capacity` splats in fixed texel formats (one per plane) with `sh_degree` bands resident."""

    def __init__(self, ctx, formats: dict[str, str], sh_degree: int, capacity: int, keep_host_mirror: bool = True,
                 growable: bool = True, codebook: dict[str, EncodedPlane] | None = None):
        """`codebook`: the SH codebook's band planes ("sh1".."shD", as splatstream.decoder.read_codebook returns
        them) for scenes encoded with one; tiles then bring an `sh_index` plane instead of their SH bands. Bands
        may be missing and set later with set_codebook_band (they decode to 0 until then)."""
        self.ctx = ctx
        self.formats = dict(formats)
        self.sh_degree = int(sh_degree)
        self.growable = growable
        self.codebook_format: str | None = None  # texel format of the codebook bands; None: no codebook
        self.codebook_textures: dict[str, RawTexture] = {}
        self.codebook_ranges: RawTexture | None = None
        if codebook and self.sh_degree >= 1:
            self._init_codebook(codebook)
        if self.codebook_format is not None:
            self.planes = ["position", "rotation", "scale", "color", "sh_index"]
        else:
            self.planes = ["position", "rotation", "scale", "color"] + [f"sh{b}" for b in range(1, self.sh_degree + 1)]
        self.textures: dict[str, RawTexture] = {}
        self.slots = 0
        self._allocate(max(1, -(-int(capacity) // CHUNK)))
        self._free = list(range(self.slots))  # kept sorted: allocation takes the lowest slots
        self.tiles: dict[int, _Resident] = {}
        self.mirror: HostMirror | None = None
        if keep_host_mirror:
            n = self.slots * CHUNK
            self.mirror = HostMirror(np.zeros((n, 3), np.float32), np.zeros(n, np.float32),
                                     np.zeros(n, np.float32), self.counts)

    def _allocate(self, slots: int) -> None:
        """(Re)create the atlases and the range table for `slots` slots, copying the used blocks of the old ones."""
        cols = min(MAX_COLS, slots)
        rows = -(-slots // cols)
        width, height = cols * BLOCK, rows * BLOCK
        max_size = self.ctx.info.get("GL_MAX_TEXTURE_SIZE", 16384)
        if height > max_size:
            raise UsageError(f"{slots * CHUNK} splats need a {width}x{height} atlas; this GL allows "
                             f"{max_size} texels per side")
        old = (self.textures, getattr(self, "ranges", None), self.slots, getattr(self, "cols", 1))
        textures = {}
        for plane in self.planes:
            fmt = get_format(self.plane_format(plane))
            layers = SH_BAND_LAYERS[int(plane[2:])] if plane[2:].isdigit() else 0
            textures[plane] = RawTexture(INTERNAL_FORMATS[fmt.gl_internal], width, height, layers)
        ranges = RawTexture(GL_RGBA32UI, width, rows)
        old_textures, old_ranges, old_slots, old_cols = old
        if old_ranges is not None:
            # Slot numbers (and so splat ids) stay; only their block positions change when the row width does.
            used = [int(s) for s in np.nonzero(self.counts)[0]]
            if old_cols == cols and used:  # same row width: the blocks keep their positions, copy whole rows
                last_row = used[-1] // cols + 1
                for plane, tex in old_textures.items():
                    tex.copy_to(textures[plane], 0, 0, 0, 0, cols * BLOCK, last_row * BLOCK)
                old_ranges.copy_to(ranges, 0, 0, 0, 0, cols * BLOCK, last_row)
                used = []
            for s in used:
                sx, sy, dx, dy = s % old_cols, s // old_cols, s % cols, s // cols
                for plane, tex in old_textures.items():
                    tex.copy_to(textures[plane], sx * BLOCK, sy * BLOCK, dx * BLOCK, dy * BLOCK, BLOCK, BLOCK)
                old_ranges.copy_to(ranges, sx * BLOCK, sy, dx * BLOCK, dy, BLOCK, 1)
            for tex in old_textures.values():
                tex.release()
            old_ranges.release()
        self.textures, self.ranges = textures, ranges
        self.slots, self.cols, self.rows, self.width, self.height = slots, cols, rows, width, height
        counts = np.zeros(slots, np.uint32)
        if old_ranges is not None:
            counts[:old_slots] = self.counts
        self.counts = counts
        if getattr(self, "mirror", None) is not None:
            n = slots * CHUNK
            m = self.mirror
            grow = n - len(m.opacity)
            self.mirror = HostMirror(np.concatenate([m.positions, np.zeros((grow, 3), np.float32)]),
                                     np.concatenate([m.opacity, np.zeros(grow, np.float32)]),
                                     np.concatenate([m.max_log_scale, np.zeros(grow, np.float32)]), counts)

    def plane_format(self, plane: str) -> str:
        """Texel format of a plane's atlas."""
        if plane == "sh_index":
            return SH_INDEX_FORMAT
        return self.formats[PLANE_ATTRIBUTE[plane]]

    # --- SH codebook ------------------------------------------------------------------------------------------
    @property
    def uses_codebook(self) -> bool:
        return self.codebook_format is not None

    def _init_codebook(self, codebook: dict[str, EncodedPlane]) -> None:
        bands = {}
        for name, plane in codebook.items():
            band = int(name[2:]) if name.startswith("sh") and name[2:].isdigit() else 0
            if not 1 <= band <= 3:
                raise UsageError(f"SH codebook plane {name!r}: expected sh1..sh3")
            if band <= self.sh_degree:
                bands[band] = plane
        if not bands:
            return
        first = bands[min(bands)]
        self.codebook_format = first.format
        self._cb_size = (int(first.width), int(first.height))
        self._cb_chunks = max(1, (first.width // BLOCK) * (first.height // BLOCK))
        internal = INTERNAL_FORMATS[get_format(self.codebook_format).gl_internal]
        for b in range(1, self.sh_degree + 1):  # every resident band's texture now: progressive bands fill them
            tex = RawTexture(internal, *self._cb_size, SH_BAND_LAYERS[b])
            self.codebook_textures[f"sh{b}"] = tex
            zeros = np.zeros(tex.nbytes // SH_BAND_LAYERS[b], np.uint8)
            for layer in range(SH_BAND_LAYERS[b]):
                tex.write(zeros, 0, 0, tex.width, tex.height, layer)
        self._cb_records = np.zeros((self._cb_chunks, RANGE_RECORD_WORDS), np.uint32)
        self.codebook_ranges = RawTexture(GL_RGBA32UI, BLOCK, self._cb_chunks)
        self.codebook_ranges.write(self._cb_records.reshape(self._cb_chunks, BLOCK, 4), 0, 0, BLOCK, self._cb_chunks)
        for b, plane in sorted(bands.items()):
            self.set_codebook_band(b, plane)

    def set_codebook_band(self, band: int, plane: EncodedPlane) -> None:
        """Upload (or replace) one band of the SH codebook: its texels as stored and its per-chunk ranges."""
        if not self.uses_codebook:
            raise UsageError("this pool was made without an SH codebook")
        if not 1 <= band <= self.sh_degree:
            raise UsageError(f"SH codebook band {band}: this pool holds bands 1..{self.sh_degree}")
        if plane.format != self.codebook_format:
            raise UsageError(f"SH codebook band {band} is {plane.format}, this pool's codebook is "
                             f"{self.codebook_format}")
        if (plane.width, plane.height) != self._cb_size:
            raise UsageError(f"SH codebook band {band} is {plane.width}x{plane.height} texels, the codebook's other "
                             f"bands {self._cb_size[0]}x{self._cb_size[1]}")
        tex = self.codebook_textures[f"sh{band}"]
        for layer in range(SH_BAND_LAYERS[band]):
            tex.write(layer_blob(plane, layer), 0, 0, tex.width, tex.height, layer)
        ranges = np.ascontiguousarray(np.asarray(plane.ranges).astype("<f2"))
        chunks = len(ranges)
        words = ranges.reshape(chunks, -1).view(np.uint32)
        w = RANGE_WORDS[f"sh{band}"]
        self._cb_records[:chunks, w:w + words.shape[1]] = words
        self.codebook_ranges.write(self._cb_records.reshape(self._cb_chunks, BLOCK, 4), 0, 0, BLOCK, self._cb_chunks)

    def grow(self, capacity: int) -> None:
        """Make room for `capacity` splats (GL 4.3: atlases are copied on the GPU; slot numbers are kept)."""
        slots = -(-int(capacity) // CHUNK)
        if slots <= self.slots:
            return
        if self.ctx.version_code < 430:
            raise UsageError(f"the chunk pool is full ({self.slots * CHUNK} splats) and growing it needs GL 4.3")
        old = self.slots
        self._allocate(slots)
        self._free = sorted(self._free + list(range(old, slots)))

    # --- accounting -----------------------------------------------------------------------------------------
    @property
    def texel_bytes(self) -> int:
        return sum(t.nbytes for t in self.textures.values())

    @property
    def range_bytes(self) -> int:
        return self.ranges.nbytes

    @property
    def codebook_bytes(self) -> int:
        """The SH codebook's textures (bands and range table); 0 without a codebook."""
        if self.codebook_ranges is None:
            return 0
        return sum(t.nbytes for t in self.codebook_textures.values()) + self.codebook_ranges.nbytes

    @property
    def gpu_bytes(self) -> int:
        return self.texel_bytes + self.range_bytes + self.codebook_bytes

    @property
    def bytes_per_splat(self) -> float:
        """GPU bytes per splat slot (atlases + range table + codebook), i.e. per splat of a full pool."""
        return self.gpu_bytes / (self.slots * CHUNK)

    @property
    def resident_splats(self) -> int:
        return sum(t.splats for t in self.tiles.values())

    @property
    def used_slots(self) -> int:
        """Highest used slot + 1 (culling scans this many)."""
        used = np.nonzero(self.counts)[0]
        return int(used[-1]) + 1 if used.size else 0

    # --- join / leave ---------------------------------------------------------------------------------------
    def join(self, tile_id: int, tile: TileData) -> np.ndarray:
        """Upload a tile's chunks into free slots; returns the slots (chunk c of the tile -> slots[c])."""
        if tile_id in self.tiles:
            raise UsageError(f"tile {tile_id} is already resident")
        n = int(tile.splats)
        chunks = -(-n // CHUNK)
        if chunks > len(self._free):
            if not self.growable:
                raise UsageError(f"tile {tile_id} needs {chunks} chunk slots, {len(self._free)} of {self.slots} "
                                 "are free")
            self.grow(max(2 * self.slots, self.slots + chunks - len(self._free)) * CHUNK)
        for plane in self.planes:
            p = tile.planes.get(plane)
            if p is None:
                if plane == "sh_index" or (plane.startswith("sh") and "sh_index" in tile.planes):
                    mode = "with" if plane == "sh_index" else "without"
                    raise UsageError(f"tile {tile_id} has no {plane} plane: this pool holds scenes {mode} an SH "
                                     "codebook")
                raise UsageError(f"tile {tile_id} has no {plane} plane")
            want = self.plane_format(plane)
            if p.format != want:
                raise UsageError(f"tile {tile_id}: {plane} is {p.format}, this pool holds {want}")
        slots = np.array(self._free[:chunks], np.int64)
        del self._free[:chunks]
        runs = _runs(slots, self.cols)
        for plane in self.planes:
            self._upload_plane(self.textures[plane], tile.planes[plane], chunks, runs)
        self._upload_ranges(tile_id, tile, n, chunks, slots, runs)
        self.counts[slots] = np.minimum(CHUNK, n - np.arange(chunks) * CHUNK).astype(np.uint32)
        if self.mirror is not None:
            self._fill_mirror(tile, n, slots)
        self.tiles[tile_id] = _Resident(slots, n)
        return slots

    def leave(self, tile_id: int) -> None:
        res = self.tiles.pop(tile_id, None)
        if res is None:
            raise UsageError(f"tile {tile_id} is not resident")
        zeros = np.zeros((1, BLOCK * 4), np.uint32)
        for s in res.slots:
            self.ranges.write(zeros, int(s % self.cols) * BLOCK, int(s // self.cols), BLOCK, 1)
        self.counts[res.slots] = 0
        self._free = sorted(self._free + [int(s) for s in res.slots])

    def clear(self) -> None:
        for tile_id in list(self.tiles):
            self.leave(tile_id)

    # --- uploads ----------------------------------------------------------------------------------------------
    def _upload_plane(self, tex: RawTexture, plane: EncodedPlane, chunks: int, runs) -> None:
        layers = max(1, tex.layers)
        for layer in range(layers):
            blocks = _chunk_blocks(plane, layer, chunks)
            side = blocks.shape[1]
            for first, slot, length in runs:
                strip = blocks[first:first + length].transpose(1, 0, 2, 3).reshape(side, length * side, -1)
                tex.write(strip, (slot % self.cols) * BLOCK, (slot // self.cols) * BLOCK, length * BLOCK, BLOCK, layer)

    def _upload_ranges(self, tile_id: int, tile: TileData, n: int, chunks: int, slots: np.ndarray, runs) -> None:
        rec = np.zeros((chunks, RANGE_RECORD_WORDS), np.uint32)
        w = RANGE_WORDS

        def put(name: str, ranges: np.ndarray, dtype: str) -> None:
            words = np.ascontiguousarray(ranges.astype(dtype)).reshape(chunks, -1).view(np.uint32)
            rec[:, w[name]:w[name] + words.shape[1]] = words

        put("position", tile.planes["position"].ranges, "<f4")
        put("scale", tile.planes["scale"].ranges, "<f2")
        put("color", tile.planes["color"].ranges, "<f2")
        if not self.uses_codebook:  # codebook scenes: the SH ranges are the codebook's (codebook_ranges)
            for b in range(1, self.sh_degree + 1):
                put(f"sh{b}", tile.planes[f"sh{b}"].ranges, "<f2")
        rec[:, w["count"]] = np.minimum(CHUNK, n - np.arange(chunks) * CHUNK)
        rec[:, w["tile"]] = np.uint32(tile_id & 0xFFFFFFFF)
        texels = rec.reshape(chunks, BLOCK, 4)
        for first, slot, length in runs:
            self.ranges.write(texels[first:first + length].reshape(1, length * BLOCK, 4),
                              (slot % self.cols) * BLOCK, slot // self.cols, length * BLOCK, 1)

    def _fill_mirror(self, tile: TileData, n: int, slots: np.ndarray) -> None:
        from splatstream.format.codec import decode_plane

        idx = (slots[np.arange(n) // CHUNK] * CHUNK + np.arange(n) % CHUNK)
        self.mirror.positions[idx] = decode_plane(tile.planes["position"], n)[:, 0]
        self.mirror.opacity[idx] = np.clip(decode_plane(tile.planes["color"], n)[:, 0, 3], 0.0, 1.0)
        self.mirror.max_log_scale[idx] = decode_plane(tile.planes["scale"], n)[:, 0].max(axis=1)

    def bind(self) -> None:
        from .shadergen import TEXTURE_UNITS

        for plane, tex in self.textures.items():
            tex.bind(TEXTURE_UNITS[plane])
        self.ranges.bind(TEXTURE_UNITS["ranges"])
        for name, tex in self.codebook_textures.items():
            tex.bind(TEXTURE_UNITS["cb_" + name])
        if self.codebook_ranges is not None:
            self.codebook_ranges.bind(TEXTURE_UNITS["cb_ranges"])

    def release(self) -> None:
        for tex in self.textures.values():
            tex.release()
        self.ranges.release()
        self.textures.clear()
        for tex in self.codebook_textures.values():
            tex.release()
        self.codebook_textures.clear()
        if self.codebook_ranges is not None:
            self.codebook_ranges.release()
            self.codebook_ranges = None


