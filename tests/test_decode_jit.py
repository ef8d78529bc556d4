"""The compiled fields1 and unshuffle kernels (client_gl.stream.decode_jit, numba: the optional extra `fast`) give
the numpy path's bytes, bit for bit: on arbitrary well-formed contents of every format (random modes, slopes,
intercepts and plane bytes) against the literal reading of format.md 5.2 and against transport's numpy path, on
shuffled units of every element size, and on a real scene encoded with every preset through every decoder entry
point (one payload, a whole group at once). A malformed content is refused before the kernel sees it, with the
numpy path's message."""
from __future__ import annotations

import zlib

import numpy as np
import pytest
from conftest import real
from test_decode_batch import planes_bytes
from test_transport_decode import GEOMETRIES, random_content, random_modes, reference_unfilter

from splatstream.encode import EncodeOptions
from splatstream.encode.local import encode_in_memory
from splatstream.errors import FormatError
from splatstream.format import transport
from splatstream.format.decode import decode_payload, decode_payloads
from splatstream.format.presets import PRESETS
from splatstream.format.transport import FIELD_LAYOUTS, field_bits, unfilter_fields
from splatstream.io import read_gaussians
from splatstream.store import read_manifest

decode_jit = pytest.importorskip("client_gl.stream.decode_jit", reason="numba (the `fast` extra) is not installed")


@pytest.fixture
def numpy_path():
    """The numpy path during the test (whatever was installed before), restored after it."""
    previous = transport.use_fields_kernel(None), transport.use_unshuffle_kernel(None)
    yield
    transport.use_fields_kernel(previous[0])
    transport.use_unshuffle_kernel(previous[1])


def decode_both(content, fmt, width, height, layers):
    transport.use_fields_kernel(None)
    by_numpy = unfilter_fields(content, fmt, width, height, layers)
    transport.use_fields_kernel(decode_jit.fields1_kernel)
    try:
        by_kernel = unfilter_fields(content, fmt, width, height, layers)
    finally:
        transport.use_fields_kernel(None)
    return by_numpy, by_kernel


@pytest.mark.parametrize("fmt", sorted(FIELD_LAYOUTS))
@pytest.mark.parametrize("geometry", GEOMETRIES)
def test_kernel_matches_the_spec_and_the_numpy_path(numpy_path, fmt, geometry):
    width, height, layers = geometry
    rng = np.random.default_rng(zlib.crc32(f"jit {fmt} {geometry}".encode()))
    bits = field_bits(fmt)
    every_delta = [[(d, None) for _ in bits] for d in (False, True)]
    for trial in range(8):
        modes = every_delta if trial == 0 else [random_modes(rng, bits) for _ in range(layers)]
        modes = (modes * layers)[:layers]
        content = random_content(rng, fmt, width, height, layers, modes)
        for given in (content, np.frombuffer(content, np.uint8).copy()):  # read-only bytes, a writable buffer
            by_numpy, by_kernel = decode_both(given, fmt, width, height, layers)
            assert by_kernel.dtype == np.uint8
            assert by_kernel.tobytes() == by_numpy.tobytes(), (fmt, modes)
        assert by_kernel.tobytes() == reference_unfilter(content, fmt, width, height, layers), (fmt, modes)


def test_malformed_contents_are_refused_before_the_kernel(numpy_path):
    rng = np.random.default_rng(5)
    content = random_content(rng, "norm11", 16, 16, 1, [random_modes(rng, field_bits("norm11"))])
    for bad in (content[:-1], content + b"\0", b"\2" + content[1:], content[:3]):
        messages = []
        for kernel in (None, decode_jit.fields1_kernel):
            transport.use_fields_kernel(kernel)
            with pytest.raises(FormatError) as err:
                unfilter_fields(bad, "norm11", 16, 16, 1, "s")
            messages.append(str(err.value))
        transport.use_fields_kernel(None)
        assert messages[0] == messages[1]


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_decodes_with_the_kernel_as_with_numpy(numpy_path, fruit, preset):
    store = encode_in_memory(fruit, EncodeOptions(preset=preset, max_leaf_splats=512))
    m = read_manifest(store)
    by_group: dict[str, list] = {}
    for t in m.tiles:
        for group, entry in t.groups.items():
            by_group.setdefault(group, []).append((store.read_payload(entry), entry))

    def decode_all():
        out = []
        for group, items in by_group.items():
            out += [planes_bytes(decode_payload(d, e, group, "t", m.uses_codebook)) for d, e in items]
            out += [planes_bytes(p) for p in decode_payloads(items, group, ["t"] * len(items), m.uses_codebook)]
        return out

    by_numpy = decode_all()
    decode_jit.install()
    assert transport.fields_kernel() is not None
    assert decode_all() == by_numpy


@pytest.mark.parametrize("element", [2, 3, 4, 8])
def test_unshuffle_kernel_matches_numpy(numpy_path, element):
    rng = np.random.default_rng(element)
    units = [rng.integers(0, 256, element * count).astype(np.uint8) for count in (1, 5, 300, 512, 700, 4096)]
    by_numpy = [transport.unshuffle(u, element).tobytes() for u in units]
    many_numpy = [a.tobytes() for a in transport.unshuffle_many(units, element)]
    transport.use_unshuffle_kernel(decode_jit.unshuffle_kernel)
    try:
        assert [transport.unshuffle(u, element).tobytes() for u in units] == by_numpy
        assert [a.tobytes() for a in transport.unshuffle_many(units, element)] == many_numpy == by_numpy
        read_only = units[-1].copy()
        read_only.setflags(write=False)
        assert transport.unshuffle(read_only, element).tobytes() == by_numpy[-1]
    finally:
        transport.use_unshuffle_kernel(None)


def test_install_and_uninstall(numpy_path):
    decode_jit.install()
    assert transport.fields_kernel() is decode_jit.fields1_kernel
    assert transport.use_unshuffle_kernel(decode_jit.unshuffle_kernel) is decode_jit.unshuffle_kernel
    decode_jit.uninstall()
    assert transport.fields_kernel() is None
    assert transport.use_unshuffle_kernel(None) is None
