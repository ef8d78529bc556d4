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
