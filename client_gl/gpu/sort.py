"""Sorting splats back to front: a GPU radix sort in GL 4.3 compute shaders and a CPU fallback.

GPU: LSD radix sort of 32-bit keys with 32-bit values, 4 bits per pass (8 passes), each pass the five steps of seed
002 / FidelityFX: count (per work-group digit histograms, digit-major table), reduce (block sums of the table),
scan (one work group scans the block sums), scan-add (block-local exclusive scan + block offset) and scatter (a
stable reorder: ranks from per-digit bit masks of each 256-key round). The element count is read on the GPU from
the params buffer; dispatch sizes come from an indirect buffer that `indirect_setup.comp` fills, so nothing is read
back. After the even number of passes the result is back in the input buffers.

CPU: numpy argsort of depths on a worker thread (for GL < 4.3 or software GL), uploaded as an index buffer.
"""
from __future__ import annotations

import concurrent.futures
import struct

import numpy as np

from . import shadergen
from .shadergen import RADIX_BITS, SCAN_TILE, SORT_TILE

PASSES = 32 // RADIX_BITS


class GpuRadixSort:
    """Sorts (keys, values) uint32 buffer pairs of up to `capacity` elements in place (stable, ascending)."""

    def __init__(self, ctx, capacity: int):
        self.ctx = ctx
        self.capacity = max(1, int(capacity))
        self.count_shader = ctx.compute_shader(shadergen.compute_source("radix_count.comp"))
        self.reduce_shader = ctx.compute_shader(shadergen.compute_source("radix_reduce.comp"))
        self.scan_shader = ctx.compute_shader(shadergen.compute_source("radix_scan.comp"))
        self.scanadd_shader = ctx.compute_shader(shadergen.compute_source("radix_scanadd.comp"))
        self.scatter_shader = ctx.compute_shader(shadergen.compute_source("radix_scatter.comp"))
        self.setup_shader = ctx.compute_shader(shadergen.compute_source("indirect_setup.comp"))
        self.table = self.reduced = self.keys_tmp = self.values_tmp = None
        self.resize(self.capacity)
        self.dispatch = ctx.buffer(reserve=32)
        self.draw = ctx.buffer(reserve=16)       # instanced: (4, n, 0, 0)
        self.draw_tri = ctx.buffer(reserve=16)   # non-instanced triangles: (6 n, 1, 0, 0)
        self.draw_points = ctx.buffer(reserve=16)  # points: (n, 1, 0, 0)
        self.batches = ctx.buffer(reserve=32 * shadergen.F2B_BATCHES)  # front-to-back batch commands
        self._params: object | None = None

    def resize(self, capacity: int) -> None:
        """Scratch buffers for up to `capacity` keys. The programs stay: compiling the six of them again took about
        200 ms a growth on the GPU machine, a frame the fly-through saw as a stall."""
        capacity = max(1, int(capacity))
        groups = -(-capacity // SORT_TILE)
        table = groups * (1 << RADIX_BITS)
        if -(-table // SCAN_TILE) > SCAN_TILE:
            raise ValueError(f"{capacity} keys exceed the single-group scan of this radix sort")
        for b in (self.table, self.reduced, self.keys_tmp, self.values_tmp):
            if b is not None:
                b.release()
        self.capacity = capacity
        self.table = self.ctx.buffer(reserve=max(4, table * 4))
        self.reduced = self.ctx.buffer(reserve=max(4, -(-table // SCAN_TILE) * 4))
        self.keys_tmp = self.ctx.buffer(reserve=capacity * 4)
        self.values_tmp = self.ctx.buffer(reserve=capacity * 4)

    @property
    def gpu_bytes(self) -> int:
        return sum(b.size for b in (self.table, self.reduced, self.keys_tmp, self.values_tmp, self.dispatch, self.draw,
                                     self.draw_tri, self.draw_points, self.batches))

    def release(self) -> None:
        for b in (self.table, self.reduced, self.keys_tmp, self.values_tmp, self.dispatch, self.draw, self.draw_tri,
                  self.draw_points, self.batches, self.count_shader, self.reduce_shader, self.scan_shader,
                  self.scanadd_shader, self.scatter_shader, self.setup_shader):
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
        self.ctx.memory_barrier()

    def sort(self, params, keys, values, bits: int = 32) -> None:
        """Sort the first params.count elements of keys/values (GL buffers) by the low `bits` key bits.

        `setup(params)` must have run since the count last changed.
        """
        ctx = self.ctx
        passes = -(-bits // RADIX_BITS)
        passes += passes % 2  # even: the result ends in the input buffers
        src = (keys, values)
        dst = (self.keys_tmp, self.values_tmp)
        params.bind_to_storage_buffer(0)
        self.table.bind_to_storage_buffer(5)
        self.reduced.bind_to_storage_buffer(6)
        for p in range(passes):
            shift = p * RADIX_BITS
            src[0].bind_to_storage_buffer(1)
            src[1].bind_to_storage_buffer(2)
            self.count_shader["u_shift"] = shift
            self.count_shader.run_indirect(self.dispatch, 0)
            ctx.memory_barrier()
            self.reduce_shader.run_indirect(self.dispatch, 16)
            ctx.memory_barrier()
            self.scan_shader.run(1)
            ctx.memory_barrier()
            self.scanadd_shader.run_indirect(self.dispatch, 16)
            ctx.memory_barrier()
            dst[0].bind_to_storage_buffer(3)
            dst[1].bind_to_storage_buffer(4)
            self.scatter_shader["u_shift"] = shift
            self.scatter_shader.run_indirect(self.dispatch, 0)
            ctx.memory_barrier()
            src, dst = dst, src

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
