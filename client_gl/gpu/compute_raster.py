"""Compute-shader tile rasterizer (draw mode "compute"), in the style of gsplat / the reference CUDA rasterizer.

Runs after the renderer's cull pass (48-byte projected records, keys = depth bits, front to back) and its depth
radix sort (values = record indices, front to back):

  1. bin_count.comp: per work group of SCAN_TILE sorted splats, the number of (tile, splat) entries (16x16-pixel
     tiles overlapped by the alpha >= 1/255 box of each splat);
  2. bin_scan.comp (one work group): exclusive scan of the group sums, the entry total (`bins`), zeroed tile ranges;
  3. bin_emit.comp: block-local exclusive scans + group offsets; each splat writes (tile id, record index) entries
     in (depth, tile) order;
  4. a stable radix sort of the entries by tile id only (ceil(log2(tiles)) bits: 4 passes of 4 bits at 1080p), so
     each tile's run stays front to back;
  5. tile_ranges.comp: [start, end) per tile by boundary detection;
  6. raster.comp: one work group per tile, one thread per pixel, batches of 256 splats in shared memory, the
     reference's blending and early stop (T < 1e-4), imageStore into the colour texture.

Dispatch sizes come from indirect buffers filled on the GPU (no read-back in the frame; bin_scan.comp writes the tile
sort's). Uniforms are written only when they change (ProgramUniforms). The entry buffer has a
fixed capacity; entries beyond it are dropped and `bins.total` records the need: `read_bins()` / `grow_if_needed()`
check it between frames (the renderer does after the first frames and on request, HeadlessRenderer after every
image it reads back) and re-allocate.
"""
from __future__ import annotations

import struct

from . import shadergen
from .gl import work_buffer
from .shadergen import RADIX_BITS, SCAN_TILE, SORT_TILE
from .sort import CHAIN_BARRIER, GpuRadixSort
from .uniforms import ProgramUniforms

# Tile size in pixels: 16x16 (a work group of 256 threads, eight warps of 8x4 pixels for the per-block lists);
# 8x8 tiles doubled the entries and made the frame slower (BENCHMARKS.md, "Per-block splat lists in the raster").
TILE_PX = 16
MIN_ENTRIES = 1 << 16
COUNT_EVERY = 4  # binnings between two copies of the entry count for the frame loop's overflow check
ENTRIES_PER_SPLAT = 4  # initial entry capacity per splat of the pool's capacity
IMAGE_FORMATS = {"f4": "rgba32f", "f2": "rgba16f", "f1": "rgba8"}

assert SCAN_TILE == SORT_TILE, "bin_count/bin_emit run on the depth sort's dispatch sizes"


def default_entries(visible_capacity: int) -> int:
    """Initial entry capacity for a pool of this many splats (grown on overflow)."""
    return max(MIN_ENTRIES, ENTRIES_PER_SPLAT * int(visible_capacity))


def _source(name: str, defines: str = "", radix_bits: int = RADIX_BITS) -> str:
    src = shadergen.compute_source(name, radix_bits=radix_bits)
    first, rest = src.split("\n", 1)
    return f"{first}\n{defines}{rest}"


def raster_sources(color_dtype: str, warp_cull: bool = True, radix_bits: int = RADIX_BITS) -> dict[str, str]:
    """Compute shader sources of a ComputeRaster's own programs, by attribute, in the order it compiles them."""
    tile = f"#define TILE_PX {TILE_PX}\n"
    defines = f"{tile}#define OUT_FORMAT {IMAGE_FORMATS[color_dtype]}\n" + ("#define WARP_CULL\n" if warp_cull else "")
    return {"count_shader": _source("bin_count.comp", tile), "scan_shader": _source("bin_scan.comp", tile, radix_bits),
            "emit_shader": _source("bin_emit.comp", tile), "ranges_shader": _source("tile_ranges.comp", tile),
            "raster_shader": _source("raster.comp", defines)}


class ComputeRaster:
    """GPU buffers and programs of the tile rasterizer for one renderer."""

    def __init__(self, ctx, color_dtype: str, visible_capacity: int, entry_capacity: int | None = None,
                 warp_cull: bool = True, radix_bits: int = RADIX_BITS,
                 fused_sort: bool = True, barrier_bits: int = CHAIN_BARRIER, sort_pass_programs: bool = False,
                 programs: dict | None = None):
        """programs: some of raster_sources' programs, compiled already (the renderer's deferred compiles)."""
        self.ctx = ctx
        self.color_dtype = color_dtype
        self.tile_px = TILE_PX
        self.radix_bits = radix_bits
        self.fused_sort = fused_sort
        self.barrier_bits = barrier_bits
        self.sort_pass_programs = sort_pass_programs
        self.warp_cull = bool(warp_cull)
        # Binning (bin_count, bin_emit): row bins with the work group's balanced emit, whose count and emit share
        # bin_common.glsl's code so that both agree on every splat's entries.
        sources = raster_sources(color_dtype, self.warp_cull, radix_bits)
        programs = programs or {}
        compiled = {attr: programs[attr] if attr in programs else ctx.compute_shader(src)
                    for attr, src in sources.items()}
        self.count_shader = compiled["count_shader"]
        self.scan_shader = compiled["scan_shader"]
        self.emit_shader = compiled["emit_shader"]
        self.ranges_shader = compiled["ranges_shader"]
        self.raster_shader = compiled["raster_shader"]
        self._u_count, self._u_scan, self._u_emit, self._u_raster = (
            ProgramUniforms(p) for p in (self.count_shader, self.scan_shader, self.emit_shader, self.raster_shader))
        self.bins = ctx.buffer(reserve=16)
        # (entries sorted, entries needed), copied from `bins` every COUNT_EVERY binnings: the frame loop's overflow
        # check reads it two binnings later, when the GPU is done with it, instead of stalling on this frame's
        # (the copy costs the driver CPU time, hence not every frame; BENCHMARKS.md, "Figures behind library
        # defaults")
        self._counts = ctx.buffer(reserve=8)
        self._frames = 0
        self.gsum = None
        self.ranges = None
        self.tile_sorter = None
        self.tile_keys = None
        self.tile_values = None
        self.tiles = 0
        self.grid = (0, 0)
        self.visible_capacity = 0
        self.entry_capacity = 0
        self.resize(visible_capacity, entry_capacity or default_entries(visible_capacity))

    # --- buffers ---------------------------------------------------------------------------------------------
    def resize(self, visible_capacity: int, entry_capacity: int | None = None) -> None:
        """Group-sum buffer for `visible_capacity` splats; entry buffers (and their sorter) for `entry_capacity`."""
        visible_capacity = max(1, int(visible_capacity))
        if visible_capacity != self.visible_capacity:
            if self.gsum is not None:
                self.gsum.release()
            self.gsum = work_buffer(self.ctx, 4 * max(1, -(-visible_capacity // SCAN_TILE)))
            self.visible_capacity = visible_capacity
        if entry_capacity is not None and int(entry_capacity) != self.entry_capacity:
            for b in (self.tile_keys, self.tile_values):
                if b is not None:
                    b.release()
            if self.tile_sorter is not None:
                self.tile_sorter.release()
            self.entry_capacity = int(entry_capacity)
            self.tile_sorter = GpuRadixSort(self.ctx, self.entry_capacity, self.radix_bits, self.fused_sort,
                                            self.barrier_bits, per_pass=self.sort_pass_programs)
            self.tile_keys = work_buffer(self.ctx, 4 * self.entry_capacity)
            self.tile_values = work_buffer(self.ctx, 4 * self.entry_capacity)

    def _grid_for(self, width: int, height: int) -> None:
        grid = (-(-width // self.tile_px), -(-height // self.tile_px))
        if grid != self.grid:
            if self.ranges is not None:
                self.ranges.release()
            self.grid = grid
            self.tiles = grid[0] * grid[1]
            self.ranges = work_buffer(self.ctx, 8 * self.tiles)

    @property
    def gpu_bytes(self) -> int:
        bufs = (self.bins, self.gsum, self.ranges, self.tile_keys, self.tile_values)
        return sum(b.size for b in bufs if b is not None) + self.tile_sorter.gpu_bytes

    def release(self) -> None:
        for b in (self._counts, self.bins, self.gsum, self.ranges, self.tile_keys, self.tile_values):
            if b is not None:
                b.release()
        self.tile_sorter.release()

    # --- overflow ----------------------------------------------------------------------------------------------
    def read_bins(self) -> tuple[int, int]:
        """(entries sorted, entries needed) of the last frame: a read-back, for between frames."""
        entries, total = struct.unpack("2I", self.bins.read(8))
        return entries, total

    def grow_if_needed(self) -> bool:
        """Re-allocate the entry buffers when the last frame needed more entries than they hold (True: re-render)."""
        _, total = self.read_bins()
        if total <= self.entry_capacity:
            return False
        self.resize(self.visible_capacity, max(2 * self.entry_capacity, total + total // 4))
        return True

    def grow_ahead(self) -> bool:
        """The check a frame loop makes every frame without waiting for the GPU: every COUNT_EVERY frames, the
        entry count copied two binnings ago (finished by now), grown at 85 % of the capacity so that a frame seldom
        overflows. True when that frame overflowed (the last one probably did too: draw it again)."""
        if self._frames % COUNT_EVERY != 2 % COUNT_EVERY or self._frames < 2:
            return False
        _, total = struct.unpack("2I", self._counts.read(8))
        old = self.entry_capacity
        if total <= old * 0.85:
            return False
        self.resize(self.visible_capacity, max(2 * old, total + total // 2))
        return total > old

    # --- frame -----------------------------------------------------------------------------------------------
    def bin(self, params, order, records, dispatch, width: int, height: int, scratch) -> None:
        """Steps 1-3: entries of the `params.count` splats of `order` (depth-sorted record indices).

        `dispatch` is the depth sort's indirect buffer (offset 0: ceil(count / SCAN_TILE) groups). bin_scan.comp
        also writes the tile sort's dispatch sizes. scratch: a buffer of a word per splat (the count pass leaves each
        splat's entry count there for the emit; the depth sort's keys, spent by now).
        """
        barrier = self.ctx.memory_barrier
        bits = self.barrier_bits
        self._grid_for(width, height)
        params.bind_to_storage_buffer(0)
        order.bind_to_storage_buffer(1)
        records.bind_to_storage_buffer(2)
        self.gsum.bind_to_storage_buffer(3)
        self.bins.bind_to_storage_buffer(4)
        self.ranges.bind_to_storage_buffer(5)
        self.tile_keys.bind_to_storage_buffer(6)
        self.tile_values.bind_to_storage_buffer(7)
        self._u_count.set("u_grid", self.grid)
        self._u_emit.set("u_grid", self.grid)
        self._u_scan.set("u_capacity", self.entry_capacity)
        self._u_scan.set("u_tiles", self.tiles)
        self._u_emit.set("u_capacity", self.entry_capacity)
        scratch.bind_to_storage_buffer(5)
        self.count_shader.run_indirect(dispatch, 0)
        barrier(bits)
        self.tile_sorter.dispatch.bind_to_storage_buffer(1)
        self.ranges.bind_to_storage_buffer(5)
        self.scan_shader.run(1)
        barrier(bits)
        order.bind_to_storage_buffer(1)
        scratch.bind_to_storage_buffer(5)
        self.emit_shader.run_indirect(dispatch, 0)
        barrier(bits)
        if self._frames % COUNT_EVERY == 0:
            self.ctx.copy_buffer(self._counts, self.bins, 8)
        self._frames += 1

    @property
    def tile_bits(self) -> int:
        return max(1, (self.tiles - 1).bit_length())

    def sort(self) -> None:
        """Steps 4-5: stable sort of the entries by tile id, tile ranges."""
        self.tile_sorter.sort(self.bins, self.tile_keys, self.tile_values, bits=self.tile_bits)
        self.bins.bind_to_storage_buffer(4)
        self.ranges.bind_to_storage_buffer(5)
        self.tile_keys.bind_to_storage_buffer(6)
        self.ranges_shader.run_indirect(self.tile_sorter.dispatch, 0)
        self.ctx.memory_barrier(self.barrier_bits)

    def raster(self, records, texture, width: int, height: int, background) -> None:
        """Step 6 into `texture` (the colour attachment, bound as image unit 0)."""
        records.bind_to_storage_buffer(2)
        self.ranges.bind_to_storage_buffer(5)
        self.tile_values.bind_to_storage_buffer(7)
        texture.bind_to_image(0, read=False, write=True)
        u = self._u_raster
        u.set("u_grid", self.grid)
        u.set("u_pixels", (width, height))
        u.set("u_background", background)
        self.raster_shader.run(self.grid[0], self.grid[1])
        self.ctx.memory_barrier()  # all bits: the image is read back, sampled or blitted next
