"""Slot allocation for the GPU pool, and how many slots a GPU byte budget holds. Pure: no GL.

A slot holds one 256-splat chunk of a tile (one 16x16 block of every atlas). A pool's slot count is fixed when it is
made, from the caller's budget: nothing is reallocated while frames are drawn; a tile that does not fit raises.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from splatstream.errors import UsageError

from .residency_layout import MAX_COLS, MAX_ROWS, CodebookLayout, PoolLayout, atlas_grid


class SlotAllocator:
    """`capacity` slots; allocation takes the lowest free slots (a tile's chunks tend to land in consecutive slots,
    uploaded as one run each, and the highest used slot, which bounds the per-frame cull, stays low)."""

    def __init__(self, capacity: int):
        capacity = int(capacity)
        if capacity < 1:
            raise UsageError(f"a slot allocator needs at least one slot, got {capacity}")
        self._used = np.zeros(capacity, bool)
        self._free_count = capacity
        self._high_water: int | None = 0  # cached: read every frame; None after a free (recomputed on demand)

    @property
    def capacity(self) -> int:
        return len(self._used)

    @property
    def free_count(self) -> int:
        return self._free_count

    @property
    def used_count(self) -> int:
        return self.capacity - self._free_count

    @property
    def high_water(self) -> int:
        """Highest used slot + 1 (0 when none is used): the slots a frame has to scan."""
        if self._high_water is None:  # a scan of every slot (30 us at 23k slots): only after slots were freed
            used = np.flatnonzero(self._used)
            self._high_water = int(used[-1]) + 1 if used.size else 0
        return self._high_water

    def is_used(self, slot: int) -> bool:
        return bool(self._used[slot])

    def allocate(self, count: int) -> np.ndarray:
        """The `count` lowest free slots (int64, ascending), now used. UsageError when fewer are free."""
        count = int(count)
        if count < 0:
            raise UsageError(f"cannot allocate {count} slots")
        if count > self._free_count:
            raise UsageError(f"{count} slots needed, {self._free_count} of {self.capacity} are free (the pool's "
                             "capacity is fixed when it is made: free slots first, or make it larger)")
        slots = np.flatnonzero(~self._used)[:count].astype(np.int64)
        self._used[slots] = True
        self._free_count -= count
        if count and self._high_water is not None:
            self._high_water = max(self._high_water, int(slots[-1]) + 1)
        return slots

    def free(self, slots) -> None:
        """Give slots back. UsageError for a slot out of range or not allocated (nothing is freed then)."""
        slots = np.asarray(slots, np.int64).reshape(-1)
        if slots.size == 0:
            return
        outside = slots[(slots < 0) | (slots >= self.capacity)]
        if outside.size:
            raise UsageError(f"slot {int(outside[0])} is out of range (capacity {self.capacity})")
        unique, counts = np.unique(slots, return_counts=True)
        bad = unique[(counts > 1) | ~self._used[unique]]
        if bad.size:
            raise UsageError(f"slot {int(bad[0])} is not allocated (freed twice?)")
        self._used[slots] = False
        self._free_count += len(slots)
        self._high_water = None


def slots_for_budget(gpu_budget_bytes: int, formats: Mapping[str, str], sh_degree: int,
                     codebook: CodebookLayout | None = None, max_slots: int = MAX_COLS * MAX_ROWS) -> int:
    """How many slots a pool may have so that its GPU bytes (atlases of every plane and SH band, range records,
    slot states, plus the SH codebook's textures as a fixed cost) stay within `gpu_budget_bytes`.

    The result is a whole atlas grid (atlas_grid's cols * rows, within rows - 1 slots of what the budget holds), so
    the pool allocates exactly that many slots. UsageError when the budget does not hold a single slot."""
    layout = PoolLayout(formats, sh_degree, codebook)
    per_slot, fixed = layout.slot_bytes(), layout.fixed_bytes()
    slots = (int(gpu_budget_bytes) - fixed) // per_slot
    if slots < 1:
        raise UsageError(f"a GPU budget of {int(gpu_budget_bytes)} bytes holds no slot: one slot of these formats "
                         f"takes {per_slot} bytes" + (f" beside the SH codebook's {fixed}" if fixed else ""))
    most = min(slots, int(max_slots))
    # the largest grid within `most`: atlas_grid(n) holds n to n + rows - 1 slots, so at most rows steps down
    for n in range(most, 0, -1):
        cols, rows = atlas_grid(n)
        if cols * rows <= most:
            return cols * rows
    raise AssertionError("atlas_grid(1) is one slot")  # not reached
