"""Sorting splats back to front: a GPU radix sort in GL 4.3 compute shaders and a CPU fallback.

GPU: LSD radix sort of 32-bit keys with 32-bit values, 4 to 8 bits per pass (the renderer's depth sort: 6, four
passes over 24-bit keys; keys of fewer bits, fewer passes, always an even number),
each pass the steps of seed 002 / FidelityFX: count (per work-group digit histograms, digit-major table), reduce
(block sums of the table), scan (one work group scans the block sums), scan-add (block-local exclusive scan + block
offset) and scatter (a stable reorder: ranks from per-digit bit masks of each 256-key round; by default the work
group reorders its tile in shared memory first and writes each digit's run in one piece). By default the reduce
is folded into the count (atomic block sums) and the scan into the scan-add (each work group sums the block sums
before its own): three dispatches a pass instead of five. The element count is read on the GPU from the params
buffer; dispatch sizes come from an indirect buffer that `indirect_setup.comp` fills, so nothing is read back.
After the even number of passes the result is back in the input buffers.

CPU: numpy argsort of depths on a worker thread (for GL < 4.3 or software GL), uploaded as an index buffer.
"""
from __future__ import annotations

import concurrent.futures
import struct

import numpy as np

from . import shadergen
from .gl import work_buffer
from .shadergen import RADIX_BITS, SCAN_TILE, SORT_TILE

RADIX_CHOICES = (4, 5, 6, 7, 8)  # digit widths: 4 (16 buckets, 8 passes of 32-bit keys) to 8 (256 buckets, 4 passes)
GL_SHADER_STORAGE_BARRIER_BIT = 0x2000
GL_COMMAND_BARRIER_BIT = 0x40
# Between two dispatches of a chain: shader storage writes seen by the next dispatch's reads, indirect arguments.
CHAIN_BARRIER = GL_SHADER_STORAGE_BARRIER_BIT | GL_COMMAND_BARRIER_BIT


def compute_program(ctx, name: str, defines: str = "", radix_bits: int = RADIX_BITS):
    """A compute shader of client_gl/gpu/shaders without a decode header, compiled once per context and source.

    Several sorters use the same ones, so a program with uniforms shared this way has them set right before each
    dispatch (the sort passes' pass_index and pass_shift)."""
    cache = ctx.extra if isinstance(ctx.extra, dict) else {}
    ctx.extra = cache
    key = ("compute_program", name, defines, radix_bits)
    prog = cache.get(key)
    if prog is None:
        prog = cache[key] = ctx.compute_shader(compute_program_source(name, defines, radix_bits))
    return prog


def compute_program_source(name: str, defines: str = "", radix_bits: int = RADIX_BITS) -> str:
    """The source compute_program compiles: the shader's, `defines` after its version line."""
    src = shadergen.compute_source(name, radix_bits=radix_bits)
    first, rest = src.split("\n", 1)
    return f"{first}\n{defines}{rest}"


SHARED_PASS_DEFINES = ("uniform uint pass_index;\nuniform uint pass_shift;\n#define PASS pass_index\n"
                       "#define SHIFT pass_shift\n#define KEYS_IN 1\n#define VALUES_IN 2\n#define KEYS_OUT 3\n"
                       "#define VALUES_OUT 4\n")


def shared_pass_programs(radix_bits: int, fused: bool = True) -> list[tuple[str, str, int]]:
    """(name, defines, radix_bits) of compute_program for the pass programs every pass shares (per_pass=False)."""
    defines = SHARED_PASS_DEFINES + ("#define FUSED\n" if fused else "")
    return [(name, defines, radix_bits)
            for name in ("radix_count.comp", "radix_scanadd.comp", "radix_scatter_local.comp")]


def sort_programs(radix_bits: int, fused: bool = True, per_pass: bool = False) -> list[tuple[str, str, int]]:
    """(name, defines, radix_bits) of the compute_program calls a GpuRadixSort of these options makes (compiled
    ahead of its first sort by the renderer's deferred compiles; per_pass: its setup and scans only, the passes'
    programs depend on the key width and compile at first use)."""
    specs = [("indirect_setup.comp", "", radix_bits)]
    if not fused:
        specs += [("radix_reduce.comp", "", radix_bits), ("radix_scan.comp", "", radix_bits)]
    if not per_pass:
        specs += shared_pass_programs(radix_bits, fused)
    return specs


class GpuRadixSort:
    """Sorts (keys, values) uint32 buffer pairs of up to `capacity` elements in place (stable, ascending).

    radix_bits: digit width (4: 8 passes over 32-bit keys; 8: 4 passes). fused: three dispatches a pass (count with
    block sums by atomics, scan-add with its own block offset, scatter) instead of five (count, reduce, scan,
    scan-add, scatter). The scatter reorders its tile by digit in shared memory first and writes each digit's run in
    one piece (radix_scatter_local.comp), fewer and longer writes than each thread writing its key where it goes
    (measured and removed: BENCHMARKS.md, "Dense scenes, warm, wall clock"). Every pass runs the same three programs,
    the pass and its digit shift as uniforms and the buffer pairs bound in turn, so a session's first frame compiles
    three programs a sort instead of three a pass (the driver's compiles were 1.4 s of a cold first frame on the GPU
    machine, 18 of them the sorts' passes: BENCHMARKS.md, "Manifest pages"). per_pass: each pass its own programs
    (shift and buffer pair as constants: a pass binds nothing and sets no uniform). barrier_bits: glMemoryBarrier bits
    between dispatches."""

    def __init__(self, ctx, capacity: int, radix_bits: int = RADIX_BITS, fused: bool = True,
                 barrier_bits: int = CHAIN_BARRIER, per_pass: bool = False):
        if radix_bits not in RADIX_CHOICES:
            raise ValueError(f"radix sort digits of {radix_bits} bits: {RADIX_CHOICES}")
        self.ctx = ctx
        self.capacity = max(1, int(capacity))
        self.radix_bits = int(radix_bits)
        self.fused = bool(fused)
        self.barrier_bits = int(barrier_bits)
        self.per_pass = bool(per_pass)
        radix = 1 << self.radix_bits
        self.setup_shader = compute_program(ctx, "indirect_setup.comp", radix_bits=self.radix_bits)
        if not self.fused:
            self.reduce_shader = compute_program(ctx, "radix_reduce.comp", radix_bits=self.radix_bits)
            self.scan_shader = compute_program(ctx, "radix_scan.comp", radix_bits=self.radix_bits)
        self._pass_programs: dict[int, tuple] = {}
        groups = -(-self.capacity // SORT_TILE)
        table = groups * radix
        blocks = -(-table // SCAN_TILE)
        if not self.fused and blocks > SCAN_TILE:
            raise ValueError(f"{capacity} keys exceed the single-group scan of this radix sort")
        self.table = work_buffer(ctx, table * 4)
        # Block sums of the table; fused: one row per pass, all zero between sorts (each pass's scatter clears its
        # row after use).
        rows = self.passes(32) if self.fused else 1
        self.reduced = ctx.buffer(bytes(max(4, blocks * rows * 4)))
        self.keys_tmp = work_buffer(ctx, self.capacity * 4)
        self.values_tmp = work_buffer(ctx, self.capacity * 4)
        self.dispatch = ctx.buffer(reserve=32)
        self.draw = ctx.buffer(reserve=16)       # instanced: (4, n, 0, 0)
        self.draw_tri = ctx.buffer(reserve=16)   # non-instanced triangles: (6 n, 1, 0, 0)
        self.draw_points = ctx.buffer(reserve=16)  # points: (n, 1, 0, 0)
        self.batches = ctx.buffer(reserve=32 * shadergen.F2B_BATCHES)  # front-to-back batch commands
        self._params: object | None = None

    def _shift(self, p: int) -> int:
        # A pass past the key's 32 bits (the even count's padding with 5 or 7-bit digits) sorts by the top digit:
        # a stable sort by a digit that grows with the key leaves sorted keys as they are.
        return min(p * self.radix_bits, 32 - self.radix_bits)

    def _programs(self, p: int) -> tuple:
        """(count, scan-add, scatter) of pass p: digit shift p * radix_bits, buffer pair p % 2 -> the other (per
        pass: as constants; else as uniforms, set here, and the pairs bound by sort)."""
        if not self.per_pass:
            progs = self._pass_programs.get(-1)
            if progs is None:
                progs = self._pass_programs[-1] = tuple(
                    compute_program(self.ctx, name, defines, radix_bits)
                    for name, defines, radix_bits in shared_pass_programs(self.radix_bits, self.fused))
            for prog in progs:  # a uniform a program does not use is not there (scan-add: no shift; unfused: no pass)
                if "pass_index" in prog:
                    prog["pass_index"].value = p
                if "pass_shift" in prog:
                    prog["pass_shift"].value = self._shift(p)
            return progs
        progs = self._pass_programs.get(p)
        if progs is None:
            src, dst = ((1, 2), (3, 4)) if p % 2 == 0 else ((3, 4), (1, 2))
            shift = self._shift(p)
            defines = (f"#define PASS {p}u\n#define SHIFT {shift}u\n#define KEYS_IN {src[0]}\n"
                       f"#define VALUES_IN {src[1]}\n#define KEYS_OUT {dst[0]}\n#define VALUES_OUT {dst[1]}\n")
            if self.fused:
                defines += "#define FUSED\n"
            progs = self._pass_programs[p] = tuple(
                compute_program(self.ctx, name, defines, self.radix_bits)
                for name in ("radix_count.comp", "radix_scanadd.comp", "radix_scatter_local.comp"))
        return progs

    @property
    def dispatches_per_pass(self) -> int:
        return 3 if self.fused else 5

    @property
    def gpu_bytes(self) -> int:
        return sum(b.size for b in (self.table, self.reduced, self.keys_tmp, self.values_tmp, self.dispatch, self.draw,
                                     self.draw_tri, self.draw_points, self.batches))

    def release(self) -> None:
        for b in (self.table, self.reduced, self.keys_tmp, self.values_tmp, self.dispatch, self.draw, self.draw_tri,
                  self.draw_points, self.batches):
            b.release()

    def setup(self, params) -> None:
        """Fill the indirect dispatch and draw arguments from params.count (a GPU-side count)."""
        params.bind_to_storage_buffer(0)
        self.dispatch.bind_to_storage_buffer(3)
        self.draw.bind_to_storage_buffer(4)
        self.draw_tri.bind_to_storage_buffer(5)
        self.draw_points.bind_to_storage_buffer(6)
        self.batches.bind_to_storage_buffer(7)
        self.setup_shader.run(1)
        self.ctx.memory_barrier(self.barrier_bits)

    def passes(self, bits: int = 32) -> int:
        """Passes a sort of `bits`-bit keys runs: even, so that the result ends in the input buffers."""
        passes = -(-bits // self.radix_bits)
        return passes + passes % 2

    def sort(self, params, keys, values, bits: int = 32) -> None:
        """Sort the first params.count elements of keys/values (GL buffers) by the low `bits` key bits.

        `setup(params)` must have run since the count last changed.
        """
        barrier = self.ctx.memory_barrier
        bits_ = self.barrier_bits
        dispatch = self.dispatch
        params.bind_to_storage_buffer(0)
        keys.bind_to_storage_buffer(1)
        values.bind_to_storage_buffer(2)
        self.keys_tmp.bind_to_storage_buffer(3)
        self.values_tmp.bind_to_storage_buffer(4)
        self.table.bind_to_storage_buffer(5)
        self.reduced.bind_to_storage_buffer(6)
        pairs = ((keys, values), (self.keys_tmp, self.values_tmp))
        for p in range(self.passes(bits)):
            if not self.per_pass:  # this pass's pair in at 1-2, the other out at 3-4
                (k_in, v_in), (k_out, v_out) = pairs if p % 2 == 0 else pairs[::-1]
                k_in.bind_to_storage_buffer(1)
                v_in.bind_to_storage_buffer(2)
                k_out.bind_to_storage_buffer(3)
                v_out.bind_to_storage_buffer(4)
            count, scanadd, scatter = self._programs(p)
            count.run_indirect(dispatch, 0)
            barrier(bits_)
            if not self.fused:
                self.reduce_shader.run_indirect(dispatch, 16)
                barrier(bits_)
                self.scan_shader.run(1)
                barrier(bits_)
            scanadd.run_indirect(dispatch, 16)
            barrier(bits_)
            scatter.run_indirect(dispatch, 0)
            barrier(bits_)
        if not self.per_pass:  # the bindings as the per-pass programs leave them (what follows may read them)
            for unit, buf in enumerate((keys, values, self.keys_tmp, self.values_tmp), 1):
                buf.bind_to_storage_buffer(unit)

    def sort_arrays(self, keys: np.ndarray, values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Convenience for tests and benchmarks: upload, sort, read back. Returns (sorted keys, values)."""
        n = len(keys)
        if n > self.capacity:
            raise ValueError(f"{n} keys exceed the capacity {self.capacity}")
        if values is None:
            values = np.arange(n, dtype=np.uint32)
        k = self.ctx.buffer(np.ascontiguousarray(keys, np.uint32).tobytes() or b"\0" * 4)
        v = self.ctx.buffer(np.ascontiguousarray(values, np.uint32).tobytes() or b"\0" * 4)
        params = self.ctx.buffer(struct.pack("4I", n, 0, 0, 0))
        self.setup(params)
        self.sort(params, k, v)
        out_k = np.frombuffer(k.read(), np.uint32)[:n].copy()
        out_v = np.frombuffer(v.read(), np.uint32)[:n].copy()
        for b in (k, v, params):
            b.release()
        return out_k, out_v


def depth_order(depths: np.ndarray) -> np.ndarray:
    """Back-to-front order of splats with these view depths (stable: equal depths keep index order)."""
    return np.argsort(-depths, kind="stable")


class CpuSorter:
    """numpy argsort of view depths on a worker thread. `submit` returns a future of the visible ids, back to front."""

    def __init__(self):
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="splat-sort")

    def submit(self, fn, *args) -> concurrent.futures.Future:
        return self._pool.submit(fn, *args)

    def close(self) -> None:
        self._pool.shutdown(wait=False)
