"""GPU residency of encoded splats: a fixed number of 256-splat slots in one texture atlas per plane.

Tiles JOIN with their base planes and LEAVE; SH bands are ADDED later and DROPPED again (the highest first), and a
per-frame DRAW SET hides resident tiles without touching their data (REPLACE refinement keeps a parent resident
but hidden until its children can take over). Nothing is reallocated after the pool is made: the slot count comes
from the caller (slots.slots_for_budget turns a GPU byte budget into one), a tile that does not fit raises.

Atlas layout: slot s is the 16x16 block at ((s % cols) * 16, (s // cols) * 16), (cols, rows) = atlas_grid(slots)
(at most 128 columns), the same block layout as a tile texture (format_spec/format.md 4.1). Global splat index =
s * 256 + j. A tile's chunk blocks are copied as the file stores them, still in their texel format.

Per slot, beside the atlases: a 64-word range record (RGBA32UI, 16 texels at ((s % cols) * 16, s // cols); word
offsets residency_layout.RANGE_WORDS, ranges as the file stores them) and a slot-state texel (RG8UI at
(s % cols, s // cols): drawn flag, SH bands resident). The shaders evaluate min(requested degree, resident bands)
per slot, so a tile without its higher bands renders exactly as at a lower SH degree.

SH codebook (format v1.1, format.md 4.7): the pool holds an `sh_index` atlas (index16, R16UI, one texel per splat:
its codebook entry) instead of the sh1..sh3 atlases; a tile's band 1 is its sh_index plane, bands 2..3 need no tile
data. The codebook itself: one array texture per band in its stored texel format and block layout (entry e at
chunk e >> 8, Morton j = e & 255) and a codebook range table (one 64-word record per codebook chunk, row = chunk,
band ranges at the RANGE_WORDS offsets). Its bands are uploaded in order with set_codebook_band; a codebook tile
renders min(requested degree, its resident bands, codebook bands uploaded).

format_spec/renderer.md 1 describes all of it.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from splatstream.errors import UsageError
from splatstream.format.codec import EncodedPlane, palette_as_ranged
from splatstream.format.texformats import PALETTE_FORMATS, get_format

from ..tiledata import HostMirror, TileData
from .gl import (
    BLOCK_BYTES,
    GL_RG8UI,
    GL_RGBA32UI,
    IMAGE_WORD_FORMATS,
    INTERNAL_FORMATS,
    RawTexture,
    StagingBuffer,
    has_gl,
)
from .residency_layout import (
    BASE_PLANE_NAMES,
    BLOCK,
    CHUNK,
    RANGE_RECORD_WORDS,
    RANGE_WORDS,
    SH_BAND_LAYERS,
    TEXTURE_UNITS,
    CodebookLayout,
    PoolLayout,
    atlas_grid,
)
from .slots import SlotAllocator, slots_for_budget
from .sort import compute_program

# How a new pool's atlases are made GPU-written before their first upload (ChunkPool._prime_atlases), and the default.
PRIMES = ("compute", "clear", "none")
DEFAULT_PRIME = "clear"


@dataclass
class _Resident:
    slots: np.ndarray  # slot of each chunk of the tile (int64)
    splats: int
    bands: int  # SH bands resident (0..sh_degree)
    drawn: bool


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
    """One layer's texture blob (uint8) of a decoded plane."""
    if not isinstance(plane.layers, (list, tuple)):
        raise UsageError(f"plane {plane.spec.name}: its layers must be decoded blobs (a list), not a lazy iterator")
    return np.frombuffer(plane.layers[layer], np.uint8)


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


def _put_ranges(records: np.ndarray, name: str, ranges: np.ndarray, dtype: str) -> None:
    """Write per-chunk ranges (chunks, 2, L, C) as `dtype` words at RANGE_WORDS[name] of (chunks, 64) records."""
    chunks = len(records)
    words = np.ascontiguousarray(np.asarray(ranges)[:chunks].astype(dtype)).reshape(chunks, -1).view(np.uint32)
    w = RANGE_WORDS[name]
    records[:, w:w + words.shape[1]] = words


class ChunkPool:
    """Atlases for `slots` 256-splat slots (rounded up to a whole atlas grid) of one scene's formats and SH bands.

    codebook: the scene's SH codebook shape for scenes encoded with one (its bands come with set_codebook_band).
    host_mirror: keep the CPU-sort path's per-splat centres, opacities and largest log scales (tiles must then
    carry TileData.mirror).
    prime: how the atlases are made GPU-written before their first upload (PRIMES, _prime_atlases).
    """

    def __init__(self, ctx, formats: Mapping[str, str], sh_degree: int, slots: int, *,
                 codebook: CodebookLayout | None = None, host_mirror: bool = True, prime: str = DEFAULT_PRIME):
        if prime not in PRIMES:
            raise UsageError(f"unknown atlas prime {prime!r} (choose one of {', '.join(PRIMES)})")
        self.ctx = ctx
        self.layout = PoolLayout(formats, int(sh_degree), codebook)
        cols, rows = atlas_grid(slots)
        max_size = int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 16384))
        if rows * BLOCK > max_size:
            raise UsageError(f"{cols * rows} slots need a {cols * BLOCK}x{rows * BLOCK} atlas; this GL allows "
                             f"{max_size} texels per side")
        self._cols, self._rows = cols, rows
        self._allocator = SlotAllocator(cols * rows)
        capacity = self._allocator.capacity
        width, height = cols * BLOCK, rows * BLOCK
        self._atlases: dict[str, RawTexture] = {}
        for plane in self.layout.planes:
            fmt = get_format(self.layout.plane_format(plane))
            self._atlases[plane] = RawTexture(INTERNAL_FORMATS[fmt.gl_internal], width, height,
                                              self.layout.plane_layers(plane))
        self._gpu_bytes: int | None = None
        self._staging = StagingBuffer(ctx)  # texel uploads go through it (the GPU copies, not the driver's CPU)
        self._prime_atlases(prime)
        self._ranges = RawTexture(GL_RGBA32UI, width, rows)
        self._state_texture = RawTexture(GL_RG8UI, cols, rows)
        self._records = np.zeros((capacity, RANGE_RECORD_WORDS), np.uint32)  # host copy of the range table
        self._state = np.zeros((capacity, 2), np.uint8)  # host copy of the slot states: (drawn, bands)
        self._state_dirty = True  # the texture's initial contents are undefined: upload zeros before the first draw
        self._slot_splats = np.zeros(capacity, np.int32)
        self._tiles: dict[int, _Resident] = {}
        self._draw_set: frozenset[int] | None = None
        self._draw_listed: tuple | None = None  # the ids of the last set_draw_set, as given
        self._drawn_ids: np.ndarray | None = None  # cache of drawn_ids()
        self._mirror: HostMirror | None = None
        if host_mirror:
            n = capacity * CHUNK
            self._mirror = HostMirror(np.zeros((n, 3), np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32))
        # SH codebook: every band's texture now (zeros decode to 0 until set_codebook_band fills them).
        self._codebook_textures: dict[int, RawTexture] = {}
        self._codebook_ranges: RawTexture | None = None
        self._codebook_records = np.zeros((0, RANGE_RECORD_WORDS), np.uint32)
        self._codebook_bands = 0
        cb = self.layout.codebook
        if cb is not None:
            internal = INTERNAL_FORMATS[get_format(cb.format).gl_internal]
            for band in range(1, self.layout.sh_degree + 1):
                tex = RawTexture(internal, *cb.size, SH_BAND_LAYERS[band])
                zeros = np.zeros(tex.nbytes // SH_BAND_LAYERS[band], np.uint8)
                for layer in range(SH_BAND_LAYERS[band]):
                    tex.write(zeros, 0, 0, tex.width, tex.height, layer)
                self._codebook_textures[band] = tex
            self._codebook_records = np.zeros((cb.chunks, RANGE_RECORD_WORDS), np.uint32)
            self._codebook_ranges = RawTexture(GL_RGBA32UI, BLOCK, cb.chunks)
            self._write_codebook_records()
        # The range table is not uploaded here: a frame scans slots below the allocator's high-water mark only, and
        # slots are handed out lowest first, so every one of those has been written by a join (or a leave). At a
        # 4 GB budget the upload of the whole table took most of the two seconds before a first frame (llvmpipe).

    def _prime_atlases(self, how: str) -> None:
        """The GPU writes one texel (0, 0 of layer 0) of every atlas that uploads go to through the staging buffer,
        before the first upload (prime_texels.comp says why: otherwise the first frame with splats moves whole atlases
        through host memory). how (PRIMES): "compute", a shader's imageStore (GL 4.3; a program to compile before
        the first frame: 37-80 ms on a cold NVIDIA driver, BENCHMARKS.md r24); "clear", glClearTexSubImage of that
        texel (GL 4.4 or ARB_clear_texture, no compile; the default: on the H200 the first uploads after it took
        0.1-0.2 ms with no page faults, as after the shader, bench/probe_gpu_alloc.py --primes, r26), the shader
        where the GL has neither; "none", nothing (the probe's baseline). The texel is slot 0's, which its first
        join overwrites."""
        if how == "none" or self.ctx.version_code < 430:
            return
        atlases = [tex for tex in self._atlases.values() if not tex.compressed]
        if how == "clear" and has_gl(self.ctx, 440, "GL_ARB_clear_texture"):
            for tex in atlases:
                tex.clear_texel()
            return
        for tex in atlases:
            fmt = IMAGE_WORD_FORMATS[tex.texel_bytes][0]
            prog = compute_program(self.ctx, "prime_texels.comp", f"#define TEXEL_FORMAT {fmt}\n")
            tex.bind_image_words(0)
            prog.run(1)
        self.ctx.memory_barrier()

    @classmethod
    def for_budget(cls, ctx, gpu_budget_bytes: int, formats: Mapping[str, str], sh_degree: int, *,
                   codebook: CodebookLayout | None = None, host_mirror: bool = True,
                   prime: str = DEFAULT_PRIME) -> ChunkPool:
        """The largest pool whose GPU bytes (gpu_bytes) stay within `gpu_budget_bytes`."""
        slots = slots_for_budget(gpu_budget_bytes, formats, sh_degree, codebook)
        return cls(ctx, formats, sh_degree, slots, codebook=codebook, host_mirror=host_mirror, prime=prime)

    # --- what the renderer reads ----------------------------------------------------------------------------
    @property
    def sh_degree(self) -> int:
        return self.layout.sh_degree

    @property
    def capacity_slots(self) -> int:
        """Slots (fixed when the pool is made)."""
        return self._allocator.capacity

    @property
    def splat_capacity(self) -> int:
        return self.capacity_slots * CHUNK

    @property
    def atlas_columns(self) -> int:
        """Slots per atlas row (the shaders' u_cols)."""
        return self._cols

    @property
    def scan_slots(self) -> int:
        """Highest used slot + 1: the slots a frame scans."""
        return self._allocator.high_water

    @property
    def free_slots(self) -> int:
        return self._allocator.free_count

    @property
    def used_slots(self) -> int:
        return self._allocator.used_count

    @property
    def codebook_bands(self) -> int:
        """SH codebook bands uploaded (1..n in order); 0 without a codebook."""
        return self._codebook_bands

    @property
    def host_mirror(self) -> HostMirror | None:
        """The CPU-sort path's values by global splat id (capacity * 256 rows), None when the pool keeps none."""
        return self._mirror

    def drop_host_mirror(self) -> None:
        """Keep no host mirror from now on (a renderer that drew its first frames with the CPU sort runs the GPU
        path: RenderOptions.cpu_first); tiles joining later need none, and what they bring is ignored."""
        self._mirror = None

    @property
    def resident_splats(self) -> int:
        return sum(t.splats for t in self._tiles.values())

    @property
    def drawn_splats(self) -> int:
        return sum(t.splats for t in self._tiles.values() if t.drawn)

    @property
    def tile_ids(self) -> tuple[int, ...]:
        return tuple(self._tiles)

    def __contains__(self, tile_id: int) -> bool:
        return tile_id in self._tiles

    def tile_bands(self, tile_id: int) -> int:
        """SH bands resident for a tile (0..sh_degree; a codebook tile joined with its index has them all)."""
        return self._resident(tile_id).bands

    def splat_ids(self, tile_id: int) -> np.ndarray:
        """Global splat ids (slot * 256 + j, uint32) of a resident tile's splats, in the tile's order."""
        res = self._resident(tile_id)
        j = np.arange(res.splats)
        return (res.slots[j // CHUNK] * CHUNK + j % CHUNK).astype(np.uint32)

    def drawn_ids(self) -> np.ndarray:
        """Global splat ids of every splat the draw set draws, ascending (uint32; cached until something changes)."""
        if self._drawn_ids is None:
            slots = np.flatnonzero((self._state[:, 0] != 0) & (self._slot_splats > 0))
            j = np.arange(CHUNK, dtype=np.uint32)
            inside = j[None, :] < self._slot_splats[slots][:, None]
            self._drawn_ids = (slots.astype(np.uint32)[:, None] * CHUNK + j[None, :])[inside]
        return self._drawn_ids

    # --- accounting -----------------------------------------------------------------------------------------
    def atlas_bytes(self, plane: str) -> int:
        return self._atlases[plane].nbytes

    @property
    def texel_bytes(self) -> int:
        return sum(t.nbytes for t in self._atlases.values())

    @property
    def range_bytes(self) -> int:
        return self._ranges.nbytes

    @property
    def state_bytes(self) -> int:
        return self._state_texture.nbytes

    @property
    def codebook_bytes(self) -> int:
        """The SH codebook's textures (bands and range table); 0 without a codebook."""
        if self._codebook_ranges is None:
            return 0
        return sum(t.nbytes for t in self._codebook_textures.values()) + self._codebook_ranges.nbytes

    @property
    def gpu_bytes(self) -> int:
        """Everything the pool allocated on the GPU (= layout.pool_bytes(capacity_slots); all of it is made with
        the pool, so the sum is taken once)."""
        if self._gpu_bytes is None:
            self._gpu_bytes = self.texel_bytes + self.range_bytes + self.state_bytes + self.codebook_bytes
        return self._gpu_bytes

    @property
    def resident_bytes(self) -> int:
        """The GPU bytes the resident splats use: their slots' share of the atlases, range table and slot states,
        and the SH codebook (held once for the scene). gpu_bytes is the whole pool, allocated up front."""
        per_slot = (self.texel_bytes + self.range_bytes + self.state_bytes) / max(1, self.capacity_slots)
        return int(round(self.used_slots * per_slot)) + self.codebook_bytes

    @property
    def bytes_per_splat(self) -> float:
        """GPU bytes per splat slot (atlases, range records, slot states, codebook), i.e. per splat of a full pool."""
        return self.gpu_bytes / self.splat_capacity

    # --- join / bands / leave -------------------------------------------------------------------------------
    def join(self, tile_id: int, tile: TileData) -> np.ndarray:
        """Upload a tile's base planes into the lowest free slots, and the SH bands it carries (sh1, sh2, .. in
        order; with a codebook its sh_index plane, which stands for every codebook band). Returns the slots
        (chunk c of the tile -> slots[c]). The tile is drawn if the current draw set includes it."""
        if tile_id in self._tiles:
            raise UsageError(f"tile {tile_id} is already resident")
        n = int(tile.splats)
        chunks = -(-n // CHUNK)
        if any(p.format in PALETTE_FORMATS for p in tile.planes.values()):  # held as ranged values (format.md 4.3.2)
            tile = replace(tile, planes={k: palette_as_ranged(p, n) for k, p in tile.planes.items()})
        bands = self._bands_carried(tile_id, tile)
        self._check_planes(tile_id, tile.planes, BASE_PLANE_NAMES, chunks)
        for band in range(1, bands + 1):
            self._check_planes(tile_id, tile.planes, self.layout.band_planes(band), chunks)
        if self._mirror is not None and tile.mirror is None:
            raise UsageError(f"tile {tile_id} has no host mirror, which this pool keeps for the CPU-sort path "
                             "(build the TileData with client_gl.tiledata.host_mirror)")
        slots = self._allocator.allocate(chunks)
        runs = _runs(slots, self._cols)
        for plane in BASE_PLANE_NAMES:
            self._upload_plane(plane, tile.planes[plane], chunks, runs)
        records = np.zeros((chunks, RANGE_RECORD_WORDS), np.uint32)
        _put_ranges(records, "position", tile.planes["position"].ranges, "<f4")
        _put_ranges(records, "scale", tile.planes["scale"].ranges, "<f2")
        _put_ranges(records, "color", tile.planes["color"].ranges, "<f2")
        counts = np.minimum(CHUNK, n - np.arange(chunks) * CHUNK)
        records[:, RANGE_WORDS["count"]] = counts
        records[:, RANGE_WORDS["tile"]] = np.uint32(tile_id & 0xFFFFFFFF)
        self._records[slots] = records
        self._slot_splats[slots] = counts
        if self._mirror is not None:
            ids = slots[np.arange(n) // CHUNK] * CHUNK + np.arange(n) % CHUNK
            self._mirror.positions[ids] = tile.mirror.positions
            self._mirror.opacity[ids] = tile.mirror.opacity
            self._mirror.max_log_scale[ids] = tile.mirror.max_log_scale
        res = _Resident(slots, n, 0, self._draw_set is None or tile_id in self._draw_set)
        self._tiles[tile_id] = res
        for band in range(1, bands + 1):
            self._put_band(res, band, tile.planes, runs)
        self._write_records(slots, runs)
        self._update_state(res)
        return slots

    def add_band(self, tile_id: int, band: int, planes: Mapping[str, EncodedPlane]) -> None:
        """Upload SH band `band` of a resident tile: the next band (bands join in order 1, 2, 3).

        planes: {"sh<band>": plane}; with an SH codebook {"sh_index": plane} for band 1 and {} for bands 2..3 (they
        come from the scene's codebook, set_codebook_band)."""
        res = self._resident(tile_id)
        if band != res.bands + 1:
            raise UsageError(f"tile {tile_id} has SH bands 1..{res.bands} resident: band {band} cannot join "
                             f"(bands join in order, the next is {res.bands + 1})")
        if band > self.sh_degree:
            raise UsageError(f"SH band {band}: this pool holds bands 1..{self.sh_degree}")
        expected = self.layout.band_planes(band)
        unexpected = set(planes) - set(expected)
        if unexpected:
            where = (f"band {band} of a codebook scene comes from the SH codebook (set_codebook_band)"
                     if self.layout.uses_codebook and band > 1 else f"band {band} takes {', '.join(expected)}")
            raise UsageError(f"tile {tile_id}: unexpected planes {', '.join(sorted(unexpected))}: {where}")
        self._check_planes(tile_id, planes, expected, len(res.slots))
        runs = _runs(res.slots, self._cols)
        self._put_band(res, band, planes, runs)
        if expected:
            self._write_records(res.slots, runs)
        self._update_state(res)

    def drop_band(self, tile_id: int) -> int:
        """Drop a tile's highest resident SH band (its texels stay, unused); returns the bands left."""
        res = self._resident(tile_id)
        if res.bands == 0:
            raise UsageError(f"tile {tile_id} has no SH band resident")
        res.bands -= 1
        self._update_state(res)
        return res.bands

    def leave(self, tile_id: int) -> None:
        """Remove a tile with all its bands; its slots are free again."""
        res = self._tiles.pop(tile_id, None)
        if res is None:
            raise UsageError(f"tile {tile_id} is not resident")
        self._records[res.slots] = 0
        self._write_records(res.slots, _runs(res.slots, self._cols))
        self._slot_splats[res.slots] = 0
        self._state[res.slots] = 0
        self._state_dirty = True
        self._drawn_ids = None
        self._allocator.free(res.slots)

    def clear(self) -> None:
        for tile_id in list(self._tiles):
            self.leave(tile_id)

    def set_draw_set(self, tile_ids: Iterable[int] | None) -> None:
        """Draw only these resident tiles (None: every resident tile); tiles not resident are ignored. The draw mask
        reaches the GPU at the next bind(), only when it changed."""
        # A frame loop passes the same ids frame after frame: compared as given first (a tuple of a few hundred ids
        # is a fraction of the set built from them, which a still view would otherwise pay every frame).
        listed = None if tile_ids is None else tuple(tile_ids)
        if listed == self._draw_listed:
            return
        new = None if listed is None else frozenset(int(t) for t in listed)
        self._draw_listed = listed
        if new == self._draw_set:
            return
        self._draw_set = new
        for tile_id, res in self._tiles.items():
            drawn = new is None or tile_id in new
            if drawn != res.drawn:
                res.drawn = drawn
                self._update_state(res)

    # --- SH codebook ------------------------------------------------------------------------------------------
    def set_codebook_band(self, band: int, plane: EncodedPlane) -> None:
        """Upload (or replace) band `band` of the SH codebook: its texels as stored and its per-chunk ranges. Bands
        come in order (1, then 2, then 3); a band not uploaded yet is not evaluated."""
        cb = self.layout.codebook
        if cb is None:
            raise UsageError("this pool was made without an SH codebook")
        if not 1 <= band <= self.sh_degree:
            raise UsageError(f"SH codebook band {band}: this pool holds bands 1..{self.sh_degree}")
        if band > self._codebook_bands + 1:
            raise UsageError(f"SH codebook band {band} before band {self._codebook_bands + 1} (bands come in order)")
        if plane.format != cb.format:
            raise UsageError(f"SH codebook band {band} is {plane.format}, this pool's codebook is {cb.format}")
        if (plane.width, plane.height) != cb.size:
            raise UsageError(f"SH codebook band {band} is {plane.width}x{plane.height} texels; a codebook of "
                             f"{cb.entries} entries is {cb.size[0]}x{cb.size[1]}")
        tex = self._codebook_textures[band]
        for layer in range(SH_BAND_LAYERS[band]):
            tex.write(layer_blob(plane, layer), 0, 0, tex.width, tex.height, layer)
        _put_ranges(self._codebook_records, f"sh{band}", plane.ranges, "<f2")
        self._write_codebook_records()
        self._codebook_bands = max(self._codebook_bands, band)

    # --- GL ---------------------------------------------------------------------------------------------------
    def bind(self) -> None:
        """Upload the slot states if they changed, bind every texture to its unit (residency_layout.TEXTURE_UNITS)."""
        if self._state_dirty:
            self._state_texture.write(self._state.reshape(self._rows, self._cols, 2), 0, 0, self._cols, self._rows)
            self._state_dirty = False
        for plane, tex in self._atlases.items():
            tex.bind(TEXTURE_UNITS[plane])
        self._ranges.bind(TEXTURE_UNITS["ranges"])
        self._state_texture.bind(TEXTURE_UNITS["slot_state"])
        for band, tex in self._codebook_textures.items():
            tex.bind(TEXTURE_UNITS[f"cb_sh{band}"])
        if self._codebook_ranges is not None:
            self._codebook_ranges.bind(TEXTURE_UNITS["cb_ranges"])

    def release(self) -> None:
        textures = [*self._atlases.values(), self._ranges, self._state_texture, *self._codebook_textures.values()]
        if self._codebook_ranges is not None:
            textures.append(self._codebook_ranges)
        for tex in textures:
            tex.release()
        self._staging.release()
        self._atlases.clear()
        self._codebook_textures.clear()
        self._codebook_ranges = None

    # --- internals --------------------------------------------------------------------------------------------
    def _resident(self, tile_id: int) -> _Resident:
        res = self._tiles.get(tile_id)
        if res is None:
            raise UsageError(f"tile {tile_id} is not resident")
        return res

    def _bands_carried(self, tile_id: int, tile: TileData) -> int:
        """SH bands a joining tile brings (validated against the pool's kind: with or without a codebook)."""
        names = set(tile.planes)
        bands = [b for b in SH_BAND_LAYERS if f"sh{b}" in names]
        if self.layout.uses_codebook:
            if bands:
                raise UsageError(f"tile {tile_id} has sh{bands[0]} planes: this pool holds scenes with an SH "
                                 "codebook (a tile brings its sh_index plane)")
            return self.sh_degree if "sh_index" in names else 0
        if "sh_index" in names:
            raise UsageError(f"tile {tile_id} has an sh_index plane: this pool holds scenes without an SH codebook")
        carried = 0
        while carried < self.sh_degree and f"sh{carried + 1}" in names:
            carried += 1
        if any(b > carried + 1 for b in bands if b <= self.sh_degree):
            raise UsageError(f"tile {tile_id} brings SH bands {bands} without band {carried + 1} (bands join in order)")
        return carried

    def _check_planes(self, tile_id: int, planes: Mapping[str, EncodedPlane], names, chunks: int) -> None:
        for name in names:
            plane = planes.get(name)
            if plane is None:
                raise UsageError(f"tile {tile_id} has no {name} plane")
            want = self.layout.plane_format(name)
            if plane.format != want:
                raise UsageError(f"tile {tile_id}: {name} is {plane.format}, this pool holds {want}")
            if plane.chunks < chunks:
                raise UsageError(f"tile {tile_id}: the {name} plane holds {plane.chunks} chunks, the tile has "
                                 f"{chunks}")

    def _put_band(self, res: _Resident, band: int, planes: Mapping[str, EncodedPlane], runs) -> None:
        """Texels (and, without a codebook, the ranges into the host records) of band `band`; bands = band."""
        chunks = len(res.slots)
        for name in self.layout.band_planes(band):
            self._upload_plane(name, planes[name], chunks, runs)
            if name != "sh_index":
                records = self._records[res.slots]
                _put_ranges(records, name, planes[name].ranges, "<f2")
                self._records[res.slots] = records
        res.bands = band

    def _update_state(self, res: _Resident) -> None:
        self._state[res.slots, 0] = 1 if res.drawn else 0
        self._state[res.slots, 1] = res.bands
        self._state_dirty = True
        self._drawn_ids = None

    def _upload_plane(self, name: str, plane: EncodedPlane, chunks: int, runs) -> None:
        tex = self._atlases[name]
        if not tex.compressed:
            self._upload_plane_direct(tex, plane, runs)
            return
        for layer in range(max(1, tex.layers)):
            blocks = _chunk_blocks(plane, layer, chunks)
            side = blocks.shape[1]
            for first, slot, length in runs:
                strip = blocks[first:first + length].transpose(1, 0, 2, 3).reshape(side, length * side, -1)
                tex.write(strip, (slot % self._cols) * BLOCK, (slot // self._cols) * BLOCK, length * BLOCK, BLOCK,
                          layer)

    def _upload_plane_direct(self, tex, plane: EncodedPlane, runs) -> None:
        """Uncompressed planes: each run of slots takes the matching blocks of the tile's texture as rectangles read
        in place (a tile's chunk c is the block at (c mod tw, c div tw) of its texture, format.md 4.1), so a 16,384-
        splat tile's plane goes up in one call per layer, with no copy on the CPU."""
        tw = plane.width // BLOCK
        for layer in range(max(1, tex.layers)):
            with self._staging.staged(layer_blob(plane, layer)):
                for first, slot, length in runs:
                    c, end = first, first + length
                    while c < end:  # split the run where it crosses a block row of the tile's texture
                        piece = min(end, (c // tw + 1) * tw) - c
                        dst = slot + (c - first)
                        tex.write_region(None, plane.width, (c % tw) * BLOCK, (c // tw) * BLOCK,
                                         (dst % self._cols) * BLOCK, (dst // self._cols) * BLOCK, piece * BLOCK,
                                         BLOCK, layer)
                        c += piece

    def _write_records(self, slots: np.ndarray, runs=None) -> None:
        """Upload the host range records of these slots (runs of consecutive slots in one atlas row at once)."""
        for _, slot, length in runs if runs is not None else _runs(slots, self._cols):
            texels = self._records[slot:slot + length].reshape(1, length * BLOCK, 4)
            self._ranges.write(texels, (slot % self._cols) * BLOCK, slot // self._cols, length * BLOCK, 1)

    def _write_codebook_records(self) -> None:
        chunks = len(self._codebook_records)
        self._codebook_ranges.write(self._codebook_records.reshape(chunks, BLOCK, 4), 0, 0, BLOCK, chunks)
