"""The GPU pool's pure parts (no GL): the slot allocator, slots for a GPU byte budget, the residency layout's byte
counts, the host mirror; and that they import without moderngl."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, real

from client_gl.gpu.residency_layout import CodebookLayout, PoolLayout, atlas_grid
from client_gl.gpu.slots import SlotAllocator, slots_for_budget
from client_gl.tiledata import TileData, host_mirror
from splatstream.errors import UsageError
from splatstream.format.presets import PRESETS

VERY_HIGH = PRESETS["very-high"]
MEDIUM = PRESETS["medium"]


def test_allocation_takes_the_lowest_free_slots():
    a = SlotAllocator(10)
    assert (a.capacity, a.free_count, a.used_count, a.high_water) == (10, 10, 0, 0)
    np.testing.assert_array_equal(a.allocate(3), [0, 1, 2])
    np.testing.assert_array_equal(a.allocate(4), [3, 4, 5, 6])
    a.free([1, 4])
    assert (a.free_count, a.used_count, a.high_water) == (5, 5, 7)
    np.testing.assert_array_equal(a.allocate(3), [1, 4, 7])  # holes first, then above the high-water mark
    assert a.high_water == 8 and a.is_used(7) and not a.is_used(8)
    assert a.allocate(0).size == 0 and a.free_count == 2
    a.free(np.arange(8))
    assert a.free_count == 10 and a.high_water == 0


def test_full_and_bad_frees_raise_and_change_nothing():
    a = SlotAllocator(4)
    a.allocate(3)
    with pytest.raises(UsageError, match="2 slots needed, 1 of 4 are free"):
        a.allocate(2)
    assert a.free_count == 1 and a.high_water == 3
    with pytest.raises(UsageError, match="slot 3 is not allocated"):
        a.free([0, 3])
    with pytest.raises(UsageError, match="slot 1 is not allocated"):
        a.free([1, 1])
    with pytest.raises(UsageError, match="out of range"):
        a.free([4])
    with pytest.raises(UsageError, match="out of range"):
        a.free([-1])
    assert a.free_count == 1 and a.used_count == 3  # nothing freed by the failed calls
    a.free([0, 1, 2])
    assert a.free_count == 4 and a.high_water == 0
    with pytest.raises(UsageError):
        SlotAllocator(0)
    with pytest.raises(UsageError):
        a.allocate(-1)


def test_slot_bytes_of_the_presets():
    # very-high: 4 base planes + 15 SH layers of f32x4, 16 B a texel, 256 texels a slot; range record 256 B;
    # slot state 2 B.
    assert PoolLayout(VERY_HIGH, 3).slot_bytes() == 19 * 16 * 256 + 256 + 2
    assert PoolLayout(VERY_HIGH, 0).slot_bytes() == 4 * 16 * 256 + 256 + 2
    # medium: norm11 position and scale (4 B), norm10_2 rotation (4 B), norm8x4 color (4 B), norm565 SH (2 B)
    assert PoolLayout(MEDIUM, 3).slot_bytes() == (4 * 4 + 15 * 2) * 256 + 256 + 2
    # with a codebook: one index16 texel a splat instead of the SH layers, the codebook a fixed cost
    cb = CodebookLayout("norm565", 300)  # 2 chunks: a 32x16 texture per band
    assert cb.size == (32, 16) and cb.chunks == 2
    layout = PoolLayout(MEDIUM, 3, cb)
    assert layout.planes == ("position", "rotation", "scale", "color", "sh_index")
    assert layout.slot_bytes() == (4 * 4 + 2) * 256 + 256 + 2
    assert layout.fixed_bytes() == 32 * 16 * 2 * 15 + 2 * 256
    assert PoolLayout(MEDIUM, 0, cb).codebook is None  # no SH bands: nothing to look up
    assert atlas_grid(1) == (1, 1) and atlas_grid(128) == (128, 1) and atlas_grid(129) == (65, 2)
    assert atlas_grid(200) == (100, 2) and atlas_grid(257) == (86, 3) and atlas_grid(128 * 1024) == (128, 1024)
    assert layout.pool_bytes(200) == layout.fixed_bytes() + 200 * layout.slot_bytes()  # two rows of 100
    assert layout.pool_bytes(201) == layout.fixed_bytes() + 202 * layout.slot_bytes()  # two rows of 101


def test_atlas_grid_is_the_fewest_rows_and_columns():
    for slots in range(1, 128 * 1024 + 1, 7):
        cols, rows = atlas_grid(slots)
        assert cols <= 128 and rows == -(-slots // 128)  # rows as wide as a texture allows
        assert slots <= cols * rows < slots + rows  # at most rows - 1 slots beyond those asked for
        assert atlas_grid(cols * rows) == (cols, rows)  # a pool of the grid's capacity has that grid


def test_layout_rejects_what_it_cannot_hold():
    with pytest.raises(UsageError, match="lack sh"):
        PoolLayout({k: v for k, v in MEDIUM.items() if k != "sh"}, 1)
    assert PoolLayout({k: v for k, v in MEDIUM.items() if k != "sh"}, 0).planes[-1] == "color"
    with pytest.raises(UsageError, match="SH degree 4"):
        PoolLayout(MEDIUM, 4)
    with pytest.raises(UsageError, match="unknown texel format"):
        PoolLayout(dict(MEDIUM, sh="f8"), 3)
    with pytest.raises(UsageError, match="65536"):
        CodebookLayout("norm565", 70000)


@pytest.mark.parametrize("codebook", [None, CodebookLayout("f32x4", 4096)])
def test_slots_for_budget_fill_the_budget(codebook):
    layout = PoolLayout(VERY_HIGH, 3, codebook)
    per_slot, fixed = layout.slot_bytes(), layout.fixed_bytes()
    assert slots_for_budget(fixed + 10 * per_slot, VERY_HIGH, 3, codebook) == 10
    assert slots_for_budget(fixed + 10 * per_slot - 1, VERY_HIGH, 3, codebook) == 9
    # above one atlas row: a grid of fewer columns, not whole rows of 128 (which held 128 of these 200: 64 %)
    assert slots_for_budget(fixed + 200 * per_slot, VERY_HIGH, 3, codebook) == 200
    assert slots_for_budget(fixed + 201 * per_slot, VERY_HIGH, 3, codebook) == 200  # 2 x 101 would pass it
    assert slots_for_budget(fixed + 257 * per_slot, VERY_HIGH, 3, codebook) == 256  # 3 x 86 would pass it
    rng = np.random.default_rng(0)
    for budget in rng.integers(fixed + per_slot, fixed + 5000 * per_slot, 200):
        slots = slots_for_budget(int(budget), VERY_HIGH, 3, codebook)
        assert layout.pool_bytes(slots) <= budget  # never above the budget
        cols, rows = atlas_grid(slots)
        assert cols * rows == slots  # the pool allocates exactly these slots
        held = (int(budget) - fixed) // per_slot
        assert held - slots < -(-held // 128)  # within a slot a row of what the budget holds
    with pytest.raises(UsageError, match="holds no slot"):
        slots_for_budget(fixed + per_slot - 1, VERY_HIGH, 3, codebook)
    assert slots_for_budget(1 << 50, VERY_HIGH, 3, codebook) == 128 * 1024  # one atlas of 16384 texels at most


def test_host_mirror_and_tile_data():
    from client_gl.scene import tiles_from_gaussians
    from splatstream.format.codec import decode_plane
    from splatstream.io import read_gaussians

    g = read_gaussians(real("fruit_drops_sh3.ply")).subset(np.arange(700))
    scene = tiles_from_gaussians(g, "medium", sh_codebook="off")
    tile = scene.tiles[0]
    planes = tile.planes
    m = host_mirror(planes, 700)
    assert len(m) == 700
    np.testing.assert_array_equal(m.positions, decode_plane(planes["position"], 700)[:, 0])
    np.testing.assert_array_equal(m.opacity, np.clip(decode_plane(planes["color"], 700)[:, 0, 3], 0, 1))
    np.testing.assert_array_equal(m.max_log_scale, decode_plane(planes["scale"], 700)[:, 0].max(axis=1))
    np.testing.assert_array_equal(tile.mirror.positions, m.positions)  # what scene.py hands to the pool
    assert tiles_from_gaussians(g, "medium", with_mirror=False).tiles[0].mirror is None
    with pytest.raises(UsageError, match="missing color, scale"):
        host_mirror({"position": planes["position"]}, 700)
    with pytest.raises(UsageError, match="host mirror of 700 splats for a tile of 600"):
        TileData(600, planes, m)


def test_pure_modules_import_without_moderngl():
    """The streaming engine and the decode workers use these without a GL (moderngl blocked here)."""
    code = ("import sys; sys.modules['moderngl'] = None\n"
            "import client_gl, client_gl.tiledata, client_gl.gpu, client_gl.gpu.slots, client_gl.gpu.residency_layout\n"
            "import client_gl.gpu.shadergen, client_gl.scene\n"
            "assert 'moderngl' not in [m for m in sys.modules if sys.modules[m] is not None]\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_high_water_cached_matches_a_scan():
    """high_water is cached (read every frame): after any sequence of allocations and frees it equals a scan."""
    rng = np.random.default_rng(0)
    a = SlotAllocator(300)
    held = []
    for _ in range(1500):
        if held and rng.random() < 0.5:
            a.free(held.pop(int(rng.integers(len(held)))))
        else:
            n = int(rng.integers(0, 12))
            if n <= a.free_count:
                held.append(a.allocate(n))
        used = np.flatnonzero([a.is_used(s) for s in range(a.capacity)])
        assert a.high_water == (int(used[-1]) + 1 if used.size else 0)
