"""container._unpack_group's planner (issue 32, vhdec33): the fast paths for a plane of one format and filter, the
section lookup by place (_named) and transport.run_whole_at's 3-int rows decode what a payload at a time decodes, bit
for bit, also where a group's payloads list their sections in another order or differ in format."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import real

from splatstream.encode import EncodeOptions
from splatstream.encode.local import encode_in_memory
from splatstream.format import container
from splatstream.io import read_gaussians
from splatstream.store import read_manifest

decode_jit = pytest.importorskip("client_gl.stream.decode_jit", reason="numba (the `fast` extra) is not installed")


@pytest.fixture
def installed():
    decode_jit.install()
    yield
    decode_jit.uninstall()


def _items(preset: str, scene: str = "lod_tile_sh3_zero_rest.ply"):
    store = encode_in_memory(read_gaussians(real(scene)), EncodeOptions(preset=preset))
    m = read_manifest(store)
    return [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles], m


def _bytes(planes: dict) -> list[bytes]:
    out = []
    for name in sorted(planes):
        p = planes[name]
        out += [name.encode(), p.format.encode(), bytes(p.width), bytes(p.height)]
        out += [np.asarray(layer).tobytes() for layer in p.layers]
        out += [b"" if p.ranges is None else np.asarray(p.ranges).tobytes()]
    return out


def _alone(items, m) -> list[list[bytes]]:
    return [_bytes(container.unpack_payload(data, entry, "base", "t", m.uses_codebook, palettes=m.scene_palettes))
            for data, entry in items]


@pytest.mark.parametrize("presets", [("very-high",), ("medium",), ("very-high", "medium")])
def test_group_decodes_as_each_payload_alone(installed, presets):
    items, m = [], None
    for preset in presets:  # two presets: a plane of two formats in one group (the general path)
        got, m = _items(preset)
        items += got
    many = container.unpack_payloads(items, "base", ["t"] * len(items), m.uses_codebook, palettes=m.scene_palettes)
    assert [_bytes(p) for p in many] == _alone(items, m)


def test_sections_in_another_order_are_found_by_name(installed):
    items, m = _items("high")
    reordered = []
    for k, (data, entry) in enumerate(items):
        if k % 2:  # every other payload lists its sections backwards: _named finds them by name
            entry = dataclasses.replace(entry, sections=tuple(reversed(entry.sections)))
        reordered.append((data, entry))
    many = container.unpack_payloads(reordered, "base", ["t"] * len(items), m.uses_codebook)
    assert [_bytes(p) for p in many] == _alone(items, m)


def test_named_reads_by_place_and_by_name():
    a = container.Section("x", "texels", 0, 1, "none")
    b = container.Section("y", "range", 16, 1, "none")
    assert container._named([(a, b), (a, b)], "y") == [b, b]
    assert container._named([(a, b), (b, a)], "y") == [b, b]
    assert container._named([(a, b), (b,)], "y") == [b, b]
    with pytest.raises(KeyError):
        container._named([(a, b), (a,)], "y")


@pytest.fixture(scope="module")
def very_high_items():
    return _items("very-high")


@pytest.fixture(scope="module")
def medium_items():
    return _items("medium")


@pytest.mark.parametrize("which", ["very_high_items", "medium_items"])
def test_compiled_planner_decodes_as_the_python_loops(installed, monkeypatch, request, which):
    # decjit: a run's planes keyed and rowed by decode_jit's plan kernels, the same bytes as the loops they replace
    items, m = request.getfixturevalue(which)
    items = items * -(-container.PLAN_MIN_PAYLOADS // len(items))  # a run the planner takes (the scene: one tile)
    monkeypatch.setattr(container, "RUN_RAW_BYTES", 1 << 30)  # in one run
    used = []
    fields1, units = container._plan_fields1, container._plan_units

    def counted(plan):
        def wrapped(*args):
            got = plan(*args)
            used.append(got is not None)
            return got
        return wrapped

    monkeypatch.setattr(container, "_plan_fields1", counted(fields1))
    monkeypatch.setattr(container, "_plan_units", counted(units))
    sources = [f"p{k}" for k in range(len(items))]
    many = container.unpack_payloads(items, "base", sources, m.uses_codebook, palettes=m.scene_palettes)
    assert any(used)
    previous = container.use_plan_kernels(None, None, None)
    try:
        used.clear()
        loops = container.unpack_payloads(items, "base", sources, m.uses_codebook, palettes=m.scene_palettes)
        assert not any(used)
    finally:
        container.use_plan_kernels(*previous)
    assert [_bytes(p) for p in many] == [_bytes(p) for p in loops] == _alone(items, m)


def test_a_bad_section_in_a_planned_run_is_refused_naming_it(installed, monkeypatch, very_high_items):
    # a fields1 section whose size is not its header's: the compiled planner gives the plane back to the loop, which
    # decodes it alone and refuses it naming its payload, as without the kernels
    items, m = very_high_items
    items = items * -(-container.PLAN_MIN_PAYLOADS // len(items))
    monkeypatch.setattr(container, "RUN_RAW_BYTES", 1 << 30)
    k = 3
    data, entry = items[k]
    s = next(s for s in entry.sections if s.filter == "fields1")
    bad = tuple(dataclasses.replace(x, size=x.size - 1) if x is s else x for x in entry.sections)
    items = [*items[:k], (data, dataclasses.replace(entry, sections=bad)), *items[k + 1:]]
    sources = [f"p{j}" for j in range(len(items))]
    messages = []
    for kernels in (True, False):
        previous = container.use_plan_kernels(None, None, None) if not kernels else None
        try:
            with pytest.raises(container.FormatError) as got:
                container.unpack_payloads(items, "base", sources, m.uses_codebook, palettes=m.scene_palettes)
            messages.append(str(got.value))
        finally:
            if previous is not None:
                container.use_plan_kernels(*previous)
    assert messages[0] == messages[1]
    assert f"p{k}" in messages[0]


def test_plan_kernels_key_row_and_give_back():
    raw = np.zeros(64, np.uint8)
    raw[0:5] = raw[16:21] = [1, 2, 3, 4, 5]
    raw[32:37] = [1, 2, 3, 4, 6]
    # offsets, sizes, widths, heights: sections 0 and 1 share a key (header and geometry), 2 differs in its header,
    # 3 in its width
    cols = np.array([[0, 16, 32, 0], [10, 10, 12, 10], [16, 16, 16, 32], [16, 16, 16, 16]], np.int64)
    firsts = np.zeros(4, np.int64)
    ats, ids, reps = np.empty(4, np.int64), np.empty(4, np.int64), np.empty(4, np.int64)
    assert decode_jit.fields1_keys_kernel(raw, cols, firsts, 5, ats, ids, reps) == 3
    assert ids.tolist() == [0, 0, 1, 2] and reps[:3].tolist() == [0, 2, 3] and ats.tolist() == [0, 16, 32, 0]
    far = cols.copy()
    far[0, 3] = 60  # its header past the buffer: planned in Python
    assert decode_jit.fields1_keys_kernel(raw, far, firsts, 5, ats, ids, reps) == -1
    assert decode_jit.fields1_keys_kernel(raw, cols, np.array([0, 0, 0, 60]), 5, ats, ids, reps) == -1
    part = np.empty((4, 3), np.int64)
    expected, nbytes, keys = np.array([10, 12, 10]), np.array([20, 16, 8]), np.array([5, 6, 7])
    assert decode_jit.fields1_rows_kernel(np.array([0, 0, 1, 2]), np.array([0, 16, 32, 0]), cols, expected, nbytes,
                                          keys, 3, part) == 104
    assert part.tolist() == [[0, 16, 5], [16, 48, 5], [32, 80, 6], [0, 96, 7]]  # at 16-byte offsets from 3
    assert decode_jit.fields1_rows_kernel(np.array([0, 0, 1, 2]), np.array([0, 16, 32, 0]), cols,
                                          np.array([10, 11, 10]), nbytes, keys, 3, part) == -1  # a size not its key's
    units = np.array([[0, 8, 20], [8, 12, 4]], np.int64)  # offsets, sizes
    rows = np.empty((3, 5), np.int64)
    assert decode_jit.units_rows_kernel(units, np.array([100, 200, 300]), 4, 1, 2, rows) == 28
    assert rows.tolist() == [[100, 2, 4, 4, 1], [208, 3, 4, 12, 1], [320, 1, 4, 24, 1]]  # the first aligned to 4
    assert decode_jit.units_rows_kernel(units, np.zeros(3, np.int64), 1, 0, 3, rows) == 27  # stored: bytes, no gaps
    assert rows[:, 1].tolist() == [8, 12, 4] and rows[:, 3].tolist() == [3, 11, 23]
    assert decode_jit.units_rows_kernel(units, np.zeros(3, np.int64), 8, 0, 0, rows) == -1  # 12 bytes: a gap
    assert decode_jit.units_rows_kernel(units, np.zeros(3, np.int64), 16, 0, 0, rows) == -1  # copied whole
