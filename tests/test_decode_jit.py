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
from conftest import payloads_by_group, real
from test_decode_batch import _damaged, planes_bytes
from test_palette import PAL
from test_transport_decode import GEOMETRIES, random_content, random_modes, reference_unfilter

from splatstream.encode import EncodeOptions
from splatstream.encode.local import encode_in_memory
from splatstream.errors import FormatError
from splatstream.format import container, keyed, transport
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
    batch = transport.use_batch_kernels(None, None)
    whole = transport.use_whole_kernel(None)
    morton = keyed.use_morton_kernel(None)
    ranges = container.use_ranges_kernel(None)
    yield
    transport.use_fields_kernel(previous[0])
    transport.use_unshuffle_kernel(previous[1])
    transport.use_batch_kernels(*batch)
    transport.use_whole_kernel(whole)
    keyed.use_morton_kernel(morton)
    container.use_ranges_kernel(ranges)


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
    by_group = payloads_by_group(store, m)

    def decode_all():
        out = []
        for group, items in by_group.items():
            out += [planes_bytes(decode_payload(d, e, group, "t", m.uses_codebook)) for d, e in items]
            out += [planes_bytes(p) for p in decode_payloads(items, group, ["t"] * len(items), m.uses_codebook)]
        return out

    by_numpy = decode_all()
    decode_jit.install()
    assert transport.fields_kernel() is not None and transport.whole_kernel() is not None
    assert decode_all() == by_numpy  # a payload, a group, in one call each (the whole kernel)
    transport.use_whole_kernel(None)
    assert decode_all() == by_numpy  # a plane at a time (the batch kernels), a section at a time


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


@pytest.mark.parametrize("geometry", [(16, 16), (32, 16), (48, 32), (64, 64)])
def test_morton_kernel_matches_the_numpy_path(numpy_path, geometry):
    # arbitrary contents (any key differences, sums past 2^48 and 2^64, any fourth component) and real ones
    width, height = geometry
    rng = np.random.default_rng(width * height)
    texels = rng.integers(0, 1 << 16, (width * height, 4), dtype=np.uint16).view(np.uint8).ravel()
    contents = [rng.integers(0, 256, 8 * width * height, dtype=np.uint8),
                np.full(8 * width * height, 255, np.uint8),
                np.concatenate(keyed.morton_content(texels, width, height))]
    by_numpy = [keyed.unfilter_morton(c, width, height).tobytes() for c in contents]
    assert by_numpy[2] == texels.tobytes()
    keyed.use_morton_kernel(decode_jit.morton_kernel)
    for content, expected in zip(contents, by_numpy, strict=True):
        assert keyed.unfilter_morton(content, width, height).tobytes() == expected  # a writable buffer's view
        assert keyed.unfilter_morton(content.tobytes(), width, height).tobytes() == expected  # read-only bytes


def test_morton_kernel_byte_table_splits_every_key_byte():
    # each of a key's six bytes, every value, through the kernel's table: x, y and z as keyed.compact_bits reads them
    table = decode_jit._SPREAD
    v = np.arange(256, dtype=np.uint64)
    for b in range(6):
        r, q = divmod(8 * b, 3)[::-1]
        key = v << np.uint64(8 * b)
        expected = (keyed.compact_bits(key) | (keyed.compact_bits(key >> np.uint64(1)) << np.uint64(16))
                    | (keyed.compact_bits(key >> np.uint64(2)) << np.uint64(32)))
        assert np.array_equal(table[r] << np.uint64(q), expected), b


def test_install_and_uninstall(numpy_path):
    decode_jit.install()
    assert keyed.use_morton_kernel(decode_jit.morton_kernel) is decode_jit.morton_kernel
    assert transport.fields_kernel() is decode_jit.fields1_kernel
    assert transport.use_unshuffle_kernel(decode_jit.unshuffle_kernel) is decode_jit.unshuffle_kernel
    assert transport.batch_kernels() == (decode_jit.fields1_many_kernel, decode_jit.unshuffle_many_kernel)
    assert transport.whole_kernel() is decode_jit.whole_kernel
    decode_jit.uninstall()
    assert keyed.use_morton_kernel(None) is None
    assert transport.fields_kernel() is None
    assert transport.use_unshuffle_kernel(None) is None
    assert transport.batch_kernels() == (None, None)
    assert transport.whole_kernel() is None


@pytest.mark.parametrize("fmt", sorted(FIELD_LAYOUTS))
def test_batch_kernel_matches_the_numpy_path_section_by_section(numpy_path, fmt):
    """Sections of several geometries and modes in one buffer, one call: each section's texels are the numpy
    path's; a malformed one among them comes back None (its caller decodes it alone, which raises) and the
    others are still right."""
    rng = np.random.default_rng(zlib.crc32(f"batch {fmt}".encode()))
    bits = field_bits(fmt)
    for layers in (1, 2):
        dims = [(16, 16), (48, 32), (16, 16), (16, 48), (32, 16)]
        contents = [random_content(rng, fmt, w, h, layers, [random_modes(rng, bits) for _ in range(layers)])
                    for w, h in dims]
        contents[2] = contents[2][:-1]  # short by a byte
        raw, sections, at = bytearray(b"\x55" * 7), [], 7  # an odd start: offsets are absolute in the buffer
        for content, (w, h) in zip(contents, dims, strict=True):
            sections.append((at, len(content), w, h))
            raw += content + b"\xaa" * 5
            at += len(content) + 5
        buf = np.frombuffer(bytes(raw), np.uint8).copy()
        assert transport.unfilter_fields_at(buf, fmt, layers, sections) is None  # no batch kernel: not batched
        expected = [None if k == 2 else unfilter_fields(c, fmt, w, h, layers).tobytes()
                    for k, (c, (w, h)) in enumerate(zip(contents, dims, strict=True))]
        transport.use_batch_kernels(decode_jit.fields1_many_kernel, decode_jit.unshuffle_many_kernel)
        got = transport.unfilter_fields_at(buf, fmt, layers, sections)
        transport.use_batch_kernels(None, None)
        assert [None if g is None else g.tobytes() for g in got] == expected, fmt


@pytest.mark.parametrize("element", [2, 3, 4, 8])
def test_batch_unshuffle_matches_numpy(numpy_path, element):
    rng = np.random.default_rng(element + 100)
    counts = (1, 5, 300, 512, 700)
    buf = rng.integers(0, 256, 3 + element * sum(counts) + 9).astype(np.uint8)
    units, at = [], 3
    for count in counts:
        units.append((at, element * count))
        at += element * count
    expected = [transport.unshuffle(buf[a:a + size], element).tobytes() for a, size in units]
    transport.use_batch_kernels(decode_jit.fields1_many_kernel, decode_jit.unshuffle_many_kernel)
    got = transport.unshuffle_at(buf, units, element)
    ragged = transport.unshuffle_at(buf, [(0, element + 1)], element)  # not whole elements: not batched
    transport.use_batch_kernels(None, None)
    assert [g.tobytes() for g in got] == expected
    assert ragged is None or element == 1


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e30])
def test_a_bad_range_in_a_batch_names_its_payload_with_the_kernels(numpy_path, fruit, value):
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    data, entry = items[2]
    items[2] = (_damaged(data, entry, "position.range", value), entry)
    decode_jit.install()
    with pytest.raises(FormatError, match="payload2"):
        container.unpack_payloads(items, "base", [f"payload{k}" for k in range(4)])


@pytest.mark.parametrize("few_rows", [0, 1000])
def test_whole_kernel_matches_the_numpy_path(numpy_path, monkeypatch, few_rows):
    """Sections of every format, geometry, layer count and modes and units of every element size (some not whole
    elements) in one buffer, one call: each section's texels and each unit's bytes are the numpy path's, at the
    offsets unfilter_whole says (texels at 16-byte offsets, each unit aligned to its element, units of one element
    size given in a row lying in a row); malformed sections among them come back None and the others are still
    right. The kernel's rows built either way (by numpy for a group's many sections, in Python for a few)."""
    monkeypatch.setattr(transport, "_FEW_ROWS", few_rows)
    rng = np.random.default_rng(zlib.crc32(b"whole"))
    raw, sections, expected, at = bytearray(b"\x55" * 7), [], [], 7  # an odd start: offsets are absolute
    for k, fmt in enumerate(sorted(FIELD_LAYOUTS) * 2):
        bits = field_bits(fmt)
        layers = 1 + k % 2
        w, h = [(16, 16), (48, 32), (16, 48), (32, 16)][k % 4]
        content = random_content(rng, fmt, w, h, layers, [random_modes(rng, bits) for _ in range(layers)])
        if k in (3, 12):
            content = content[:-1]  # short by a byte
            expected.append(None)
        elif k == 7:
            content = bytes([99]) + content[1:]  # not fields1's version
            expected.append(None)
        else:
            expected.append(unfilter_fields(content, fmt, w, h, layers).tobytes())
        sections.append((fmt, layers, at, len(content), w, h))
        raw += content + b"\xaa" * (k % 5)
        at += len(content) + k % 5
    units, unit_bytes = [], []
    for element, count in [(4, 37), (4, 2), (2, 300), (2, 5), (3, 7), (8, 33), (1, 9), (4, 0), (2, 0)] + [(4, 1)]:
        size = element * count + (1 if element == 8 else 0)  # 8-byte units not whole elements: copied as they are
        unit = rng.integers(0, 256, size).astype(np.uint8)
        units.append((at, size, element))
        unit_bytes.append(transport.unshuffle(unit, element).tobytes())
        raw += unit.tobytes()
        at += size
    buf = np.frombuffer(bytes(raw), np.uint8).copy()
    assert transport.unfilter_whole(buf, sections, units) is None  # no whole kernel: not so
    transport.FIELDS1_ROWS.clear()
    transport.use_whole_kernel(decode_jit.whole_kernel)
    try:
        out, got, unit_at = transport.unfilter_whole(buf, sections, units)
        # the same call again takes every section's row from FIELDS1_ROWS (the malformed ones' None too): same bytes
        again, got_again, unit_at_again = transport.unfilter_whole(buf, sections, units)
    finally:
        transport.use_whole_kernel(None)
    assert [None if g is None else out[g[0]:g[0] + g[1]].tobytes() for g in got] == expected
    assert got_again == got and unit_at_again == unit_at
    assert [None if g is None else again[g[0]:g[0] + g[1]].tobytes() for g in got] == expected
    # k 7's None (not fields1's version); 3 and 12, short by a byte, have rows their sizes do not match
    assert sum(row is None for row in transport.FIELDS1_ROWS.values()) == 1
    assert all(g is None or g[0] % 16 == 0 for g in got)
    assert [out[a:a + u[1]].tobytes() for a, u in zip(unit_at, units, strict=True)] == unit_bytes
    assert unit_at[1] == unit_at[0] + units[0][1] and unit_at[3] == unit_at[2] + units[2][1]
    assert all(a % u[2] == 0 for a, u in zip(unit_at, units, strict=True) if u[2] in (2, 4) and u[1] % u[2] == 0)


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e30])
def test_a_bad_range_in_one_payload_is_refused_by_the_whole_kernel(numpy_path, fruit, value):
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    entry = m.tiles[0].groups["base"]
    data = _damaged(store.read_payload(entry), entry, "scale.range", value)
    with pytest.raises(FormatError, match="scale.range") as by_numpy:
        container.unpack_payload(data, entry, "base", "payload0")
    decode_jit.install()
    with pytest.raises(FormatError, match="scale.range") as by_kernel:
        container.unpack_payload(data, entry, "base", "payload0")
    assert str(by_kernel.value) == str(by_numpy.value)


def _float_damaged(data: bytes, entry, name: str, value: float) -> bytes:
    """The payload with its section `name` (an f32x4 section stored shuffled) holding `value` in its first texel."""
    import zstandard
    raw = bytearray(zstandard.ZstdDecompressor().decompress(data))
    s = entry.section(name)
    texels = transport.unshuffle(np.frombuffer(bytes(raw[s.offset:s.offset + s.size]), np.uint8), 4).view("<f4").copy()
    texels[0] = value
    raw[s.offset:s.offset + s.size] = transport.shuffle(texels.view(np.uint8), 4).tobytes()
    return zstandard.ZstdCompressor().compress(bytes(raw))


@pytest.mark.parametrize("value", [np.nan, 1.5, -0.5, -0.0])
@pytest.mark.parametrize("transport_name", ["shuffle", "fields"])
def test_float_texels_of_a_group_are_checked_at_once_and_a_bad_one_named(numpy_path, fruit, value, transport_name):
    # _unpack_group checks a float plane's texels of the whole group in one go (container._floats_ok) and
    # each payload alone only where that fails: a bad texel is still refused naming its payload, -0.0 accepted
    store = encode_in_memory(fruit, EncodeOptions(preset="very-high", max_leaf_splats=512, transport=transport_name))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    sources = [f"payload{k}" for k in range(4)]
    by_numpy = [planes_bytes(p) for p in container.unpack_payloads(items, "base", sources)]
    decode_jit.install()
    assert [planes_bytes(p) for p in container.unpack_payloads(items, "base", sources)] == by_numpy
    shuffled = [s.name for s in items[2][1].sections if s.kind == "texels" and s.filter == "shuffle4"]
    assert shuffled  # very-high's rotation keeps the shuffle with either transport
    data, entry = items[2]
    items[2] = (_float_damaged(data, entry, shuffled[0], value), entry)
    if value == 0.0:
        container.unpack_payloads(items, "base", sources)
    else:
        with pytest.raises(FormatError, match=f"payload2.*section {shuffled[0]}.*outside"):
            container.unpack_payloads(items, "base", sources)


@pytest.mark.parametrize("dtype", ["<f4", "<f2"])
def test_the_ranges_kernel_answers_as_the_python_and_numpy_checks(numpy_path, dtype, monkeypatch):
    """decode_jit.ranges_kernel (container.use_ranges_kernel) against _ranges_ok's Python-float and numpy paths, its
    reference, on hostile ranges: NaN, infinities, values at and beyond each plane's domain, minimum above maximum;
    C-ordered, read-only and strided arrays (the last go to the reference paths)."""
    decode_jit.warm_up()
    rng = np.random.default_rng(7)
    specials = [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e6, -1e6, 65504.0, 3e38, -3e38, 1e18, -1e18, 2e18, -80.0, 40.0,
                -80.5, 40.5]
    answers = {True: 0, False: 0}
    for plane in ("position", "scale", "color", "opacity", "sh1"):
        for _ in range(300):
            chunks = int(rng.integers(1, 6))
            r = rng.normal(0, 3, size=(chunks, 2, 1, 3))
            r[:, 1] = r[:, 0] + np.abs(rng.normal(0, 1, size=(chunks, 1, 3)))
            for _ in range(rng.integers(0, 3)):
                r[tuple(rng.integers(0, k) for k in r.shape)] = specials[rng.integers(len(specials))]
            with np.errstate(over="ignore", invalid="ignore"):
                ranges = r.astype(dtype)
            read_only = ranges.copy()
            read_only.setflags(write=False)
            strided = np.repeat(ranges, 2, axis=0)[::2]
            for small in (container.SMALL_RANGES, 0):  # Python's floats, numpy's reductions
                monkeypatch.setattr(container, "SMALL_RANGES", small)
                container.use_ranges_kernel(None)
                expected = container._ranges_ok(ranges, plane)
                container.use_ranges_kernel(decode_jit.ranges_kernel)
                for x in (ranges, read_only, strided):
                    assert container._ranges_ok(x, plane) == expected, (plane, x)
            answers[expected] += 1
            if expected:
                container._check_ranges(ranges, plane, "r", "s")
            else:
                with pytest.raises(FormatError):
                    container._check_ranges(ranges, plane, "r", "s")
    assert answers[True] > 100 and answers[False] > 100  # both answers well covered


def _alone_calls(monkeypatch) -> list[str]:
    """The texel sections _unpack_group left out of the whole kernel's call and decoded alone (_texels_alone: not
    well-formed fields1), by name."""
    calls: list[str] = []
    alone = container._texels_alone

    def spy(buf, s, *args):
        calls.append(s.name)
        return alone(buf, s, *args)
    monkeypatch.setattr(container, "_texels_alone", spy)
    return calls


def _planes_of_groups(by_group: dict, m, alone: int = 0) -> list:
    """Every group of `by_group` through unpack_payloads (and its first `alone` payloads through unpack_payload):
    each payload's plane bytes and palettes, to compare paths by."""
    out = []
    for group, items in by_group.items():
        sources = [f"payload{k}" for k in range(len(items))]
        planes = container.unpack_payloads(items, group, sources, m.uses_codebook, palettes=m.scene_palettes)
        planes += [container.unpack_payload(d, e, group, "one", m.uses_codebook, palettes=m.scene_palettes)
                   for d, e in items[:alone]]
        out += [(planes_bytes(p), [None if q.palette is None else (q.palette.tobytes(), q.scene_palette)
                                   for q in p.values()]) for p in planes]
    return out


@pytest.mark.parametrize("preset", ["medium", "high", "very-low", "medium-low-palette", "low-plus-10bit-cb8"])
def test_a_group_planned_in_one_pass_decodes_as_the_numpy_path(numpy_path, monkeypatch, fruit, preset):
    # container._unpack_group takes a group of the usual kind in its one call (fields1, shuffled, stored as is
    # (very-low's bc7 colour), morton1 positions and palette planes (medium-low-palette), f16x4 planes (high), SH
    # groups and codebook indices (cb8)): the same planes, palettes included, as the numpy path's, a group and a
    # payload alone
    store = encode_in_memory(fruit, EncodeOptions(preset=preset, max_leaf_splats=512))
    m = read_manifest(store)
    by_group = payloads_by_group(store, m)

    def decode_all() -> list:
        return _planes_of_groups(by_group, m, alone=2)

    by_numpy = decode_all()
    decode_jit.install()
    calls = _alone_calls(monkeypatch)
    assert decode_all() == by_numpy
    assert calls == []  # no section of any payload left out of the kernel's call


@pytest.mark.parametrize("preset", ["medium", "medium-low-palette", "very-high", "low-plus-10bit-cb8"])
def test_a_large_group_decodes_in_runs_as_the_numpy_path(numpy_path, monkeypatch, fruit, preset):
    # above RUN_RAW_BYTES decompressed, unpack_payloads takes a group with the whole kernel in runs (each decompressed
    # into this thread's kept buffer, which the next run overwrites): every plane, palettes included, as the numpy
    # path's, whatever the runs; a payload that does not decode is named as before
    store = encode_in_memory(fruit, EncodeOptions(preset=preset, max_leaf_splats=512))
    m = read_manifest(store)
    by_group = payloads_by_group(store, m)

    def decode_all() -> list:
        return _planes_of_groups(by_group, m)

    by_numpy = decode_all()
    decode_jit.install()
    runs = []
    unpack_run = container._unpack_run

    def spy(items, *args):
        runs.append(len(items))
        return unpack_run(items, *args)
    monkeypatch.setattr(container, "_unpack_run", spy)
    largest = max(e.raw_bytes for items in by_group.values() for _, e in items)
    for budget in (1, largest, 3 * largest, 1 << 40):  # a payload a run, a few, the whole group
        monkeypatch.setattr(container, "RUN_RAW_BYTES", budget)
        runs.clear()
        assert decode_all() == by_numpy, budget
        assert sum(runs) == sum(len(items) for items in by_group.values())
        if budget == 1:
            assert set(runs) == {1}
        elif budget == 1 << 40:
            assert len(runs) == len(by_group)
        else:
            assert len(by_group) < len(runs) < sum(runs)
    items = by_group["base"]
    data, entry = items[-2]
    items[-2] = (data[:-5], entry)  # a cut frame in the last run: named, as a payload alone is
    monkeypatch.setattr(container, "RUN_RAW_BYTES", largest)
    with pytest.raises(FormatError, match=f"payload{len(items) - 2}"):
        container.unpack_payloads(items, "base", [f"payload{k}" for k in range(len(items))], m.uses_codebook,
                                  palettes=m.scene_palettes)


@pytest.mark.parametrize("damage", ["version", "short"])
def test_a_malformed_section_in_a_planned_group_is_refused_naming_its_payload(numpy_path, monkeypatch, fruit, damage):
    # a fields1 section that is not well-formed is decoded alone in _unpack_group's planning pass, which refuses it
    # as the numpy path does: the same message, naming the payload and the section
    import zstandard
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    data, entry = items[2]
    s = next(s for s in entry.sections if s.filter == "fields1")
    raw = bytearray(zstandard.ZstdDecompressor().decompress(data))
    if damage == "version":
        raw[s.offset] = 2  # a fields1 version this reader does not know
    else:
        raw[s.offset + 1:s.offset + 1 + len(field_bits(s.format))] = bytes([0x0E] * len(field_bits(s.format)))
    items[2] = (zstandard.ZstdCompressor().compress(bytes(raw)), entry)
    sources = [f"payload{k}" for k in range(4)]
    with pytest.raises(FormatError) as by_numpy:
        container.unpack_payloads(items, "base", sources)
    decode_jit.install()
    calls = _alone_calls(monkeypatch)
    with pytest.raises(FormatError) as by_kernel:
        container.unpack_payloads(items, "base", sources)
    assert calls == [s.name]
    assert str(by_kernel.value) == str(by_numpy.value)
    assert "payload2" in str(by_kernel.value) and s.name in str(by_kernel.value)


@pytest.mark.parametrize("presets", [("medium", "medium+pal"), ("medium+pal", "high"), ("high", "very-high")])
def test_a_group_of_two_scenes_payloads_decodes_as_the_numpy_path(numpy_path, monkeypatch, fruit, presets):
    # a group whose payloads store a plane in two formats (payloads of two scenes: palettes in some payloads only,
    # f16x4 beside f32x4) goes through _unpack_group's one call too: each payload's palettes or ranges read alone
    # (_mixed_plane), the float texels of two formats checked a payload at a time; the same planes as the numpy path
    stores = [encode_in_memory(fruit, EncodeOptions(preset=p.removesuffix("+pal"), max_leaf_splats=512,
                                                    overrides=PAL if p.endswith("+pal") else {}))
              for p in presets]
    manifests = [read_manifest(store) for store in stores]
    per_store = [[(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:3]
                 for store, m in zip(stores, manifests, strict=True)]
    items = [item for pair in zip(*per_store, strict=True) for item in pair]  # the two scenes' payloads alternate
    palettes = {}
    for m in manifests:
        palettes.update(m.scene_palettes or {})
    sources = [f"payload{k}" for k in range(len(items))]

    def decode_all() -> list:
        planes = container.unpack_payloads(items, "base", sources, palettes=palettes or None)
        return [(planes_bytes(p), [None if q.palette is None else (q.palette.tobytes(), q.scene_palette)
                                   for q in p.values()], [None if q.ranges is None else q.ranges.tobytes()
                                                          for q in p.values()]) for p in planes]

    by_numpy = decode_all()
    decode_jit.install()
    calls = _alone_calls(monkeypatch)
    assert decode_all() == by_numpy
    assert calls == []
    if presets[1] == "very-high":  # a bad f32x4 texel in a payload of the second scene: refused naming it
        data, entry = items[3]
        shuffled = [s.name for s in entry.sections if s.format == "f32x4" and s.filter == "shuffle4"]
        assert shuffled  # very-high's rotation keeps the shuffle
        items[3] = (_float_damaged(data, entry, shuffled[0], 1.5), entry)
        with pytest.raises(FormatError, match=f"payload3.*section {shuffled[0]}.*outside"):
            container.unpack_payloads(items, "base", sources)


def test_half_value_reads_every_float16_as_numpy_does():
    # the whole kernel's float16 range check reads a half's bits itself (numba has no float16 arithmetic)
    bits = np.arange(1 << 16, dtype=np.uint16)
    expected = bits.view(np.float16).astype(np.float64)
    got = np.array([decode_jit.half_value(b) for b in bits])
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    assert np.array_equal(got[~np.isnan(got)], expected[~np.isnan(expected)])


def _ranges_answer(values: np.ndarray, plane: str) -> bool:
    """_ranges_ok's answer by its Python and numpy paths and by the ranges kernel, which must agree."""
    answers = set()
    for kernel in (None, decode_jit.ranges_kernel):
        previous = container.use_ranges_kernel(kernel)
        try:
            answers.add(container._ranges_ok(values, plane))
        finally:
            container.use_ranges_kernel(previous)
    assert len(answers) == 1
    return answers.pop()


@pytest.mark.parametrize("dtype", ["<f4", "<f2"])
@pytest.mark.parametrize("plane", ["position", "scale", "color"])
def test_the_whole_kernels_range_checks_answer_as_ranges_ok(numpy_path, dtype, plane):
    """A span of ranges checked by the whole kernel (transport.CHECK_RANGES, container's codes and bounds) fails its
    check exactly where container._ranges_ok refuses the same values: finite, ordered, inside the plane's domain;
    NaN, infinities, -0.0, float16 subnormals and values at and past the domain's ends among them."""
    rng = np.random.default_rng(zlib.crc32(f"ranges {dtype} {plane}".encode()))
    low, high = container._LIMITS32.get(plane, (-6e4, 6e4))
    specials = [np.nan, np.inf, -np.inf, -0.0, 0.0, 6e-8, low, high, np.nextafter(np.float32(high), np.inf),
                2 * low, 1e30, -1e30]
    code = container._RANGE_CHECKS.get((plane, dtype)) or container._RANGE_CHECKS["", dtype]
    answers = []
    for case in range(60):
        chunks, k = 1 + case % 3, [3, 4, 1][case % 3]
        lo = rng.uniform(-3, 3, (chunks, k))
        values = np.stack([lo, lo + rng.uniform(0, 2, (chunks, k))], axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            values = values.astype(dtype)
            if case % 4:  # a damage at a random place (the fourth case of each four left whole)
                values.reshape(-1)[rng.integers(values.size)] = specials[rng.integers(len(specials))]
            if case % 7 == 5:  # a minimum above its maximum
                values[0, 0, 0], values[0, 1, 0] = values[0, 1, 0] + 1, values[0, 0, 0]
        raw = np.zeros(16 + values.nbytes, np.uint8)
        raw[16:] = values.view(np.uint8).ravel()
        transport.use_whole_kernel(decode_jit.whole_kernel)
        try:
            out, status = transport.run_whole(raw, [], (), [16, values.nbytes, 1, 0, transport.CHECK_NONE],
                                              values.nbytes, 0, 0, [0, values.nbytes, k, code],
                                              container._CHECK_BOUNDS)
        finally:
            transport.use_whole_kernel(None)
        assert out[:values.nbytes].tobytes() == values.tobytes()
        expected = _ranges_answer(values, plane)
        assert (status == 0) == expected, (case, values)
        answers.append(expected)
    assert any(answers) and not all(answers)  # both answers met


@pytest.mark.parametrize("fmt", ["f32x4", "f16x4"])
def test_the_whole_kernels_float_checks_answer_as_check_float_texels(numpy_path, monkeypatch, fmt):
    """A float format's texels, from fields1 rows and from shuffled units, fail the whole kernel's check
    (transport.CHECK_F32, CHECK_F16) exactly where container._check_float_texels refuses them: t in [0, 1] or -0.0."""
    float_type, bits, one, negative_zero = container.FLOAT_TEXEL_BITS[fmt]
    rng = np.random.default_rng(zlib.crc32(fmt.encode()))
    statuses: list[int] = []
    real_run_whole = transport.run_whole

    def run_whole(*args):
        out, status = real_run_whole(*args)
        statuses.append(status)
        return out, status

    monkeypatch.setattr(transport, "run_whole", run_whole)

    def refused(texels: np.ndarray) -> bool:
        section = container.Section(name="t", kind="texels", format=fmt, filter="none", offset=0, size=texels.size)
        try:
            container._check_float_texels([texels], section, "s")
        except FormatError:
            return True
        return False

    answers = []
    for case in range(24):
        w, h = 16, 16 * (1 + case % 2)
        if case % 3 == 0:  # fields1: random planes (floats of every kind) or zero planes (0.0 throughout)
            modes = [random_modes(rng, field_bits(fmt))]
            content = random_content(rng, fmt, w, h, 1, modes)
            if case % 2:
                head = 1 + len(field_bits(fmt))
                content = content[:head] + bytes(len(content) - head)
            raw = np.frombuffer(bytes(16) + content, np.uint8).copy()
            transport.use_whole_kernel(decode_jit.whole_kernel)
            try:
                out, got, _ = transport.unfilter_whole(raw, [(fmt, 1, 16, len(content), w, h)], [])
            finally:
                transport.use_whole_kernel(None)
            texels = out[got[0][0]:got[0][0] + got[0][1]]
            assert texels.tobytes() == unfilter_fields(content, fmt, w, h, 1).tobytes()
        else:  # a shuffled unit: floats in [0, 1], one damaged in most cases
            values = rng.uniform(0, 1, w * h * 4).astype(float_type)
            if case % 3 == 1:
                values[rng.integers(values.size)] = [np.nan, np.inf, -1.0, 1.0001, -0.0, 1.0, 2.0][case % 7]
            element = values.itemsize
            unit = transport.shuffle(values.view(np.uint8), element)
            raw = np.concatenate([np.zeros(16, np.uint8), unit])
            check = transport.FLOAT_CHECKS[fmt]
            transport.use_whole_kernel(decode_jit.whole_kernel)
            try:
                out, status = real_run_whole(raw, [], (), [16, values.size, element, 0, check], values.nbytes, 0, 0)
            finally:
                transport.use_whole_kernel(None)
            statuses.append(status)
            texels = out[:values.nbytes]
            assert texels.tobytes() == values.tobytes()
        status = statuses.pop()
        assert status in (0, transport.CHECK_FAILED_FLOATS)
        assert (status != 0) == refused(texels), case
        answers.append(status)
    assert any(answers) and not all(answers)


@pytest.mark.parametrize("preset", ["medium", "very-high"])
@pytest.mark.parametrize("name", ["position.range", "scale.range", "color.range"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -1e30, 1e30])
def test_a_bad_range_in_a_group_is_refused_as_by_the_numpy_path(numpy_path, fruit, preset, name, value):
    """A damaged range (float32 or float16) in one payload of a group: the whole kernel's status sends the group to
    the checks the numpy path makes, which refuse it with the same one-line message naming the payload and section."""
    store = encode_in_memory(fruit, EncodeOptions(preset=preset, max_leaf_splats=512))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    data, entry = items[2]
    items[2] = (_damaged(data, entry, name, value), entry)
    sources = [f"payload{k}" for k in range(4)]
    with pytest.raises(FormatError, match=f"payload2.*{name}") as by_numpy:
        container.unpack_payloads(items, "base", sources)
    decode_jit.install()
    with pytest.raises(FormatError, match=f"payload2.*{name}") as by_kernel:
        container.unpack_payloads(items, "base", sources)
    assert str(by_kernel.value) == str(by_numpy.value)
    assert "\n" not in str(by_kernel.value)


@pytest.mark.parametrize("path", ["fields", "batch", "whole"])
def test_a_kernel_handed_back_during_a_call_does_not_break_it(numpy_path, fruit, monkeypatch, path):
    """decode_jit.warm_up hands each kernel in for its own calls and back (None) while the decode threads of the
    process may be decoding (install warms up first, so the first frame's decode keeps the numpy path until the
    kernels are loaded). A decode that read a kernel and then called the module's, handed back meanwhile, failed with
    "'NoneType' object is not callable" and its view never converged (pagebudget31). Here each kernel is handed back
    between a call's check and its use: the call decodes the same bytes as the numpy path."""
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    by_group = payloads_by_group(store, m)

    def decode_all():
        out = []
        for group, items in by_group.items():
            if path == "fields":
                out += [planes_bytes(decode_payload(d, e, group, "t", m.uses_codebook)) for d, e in items]
            else:
                out += [planes_bytes(p) for p in decode_payloads(items, group, ["t"] * len(items), m.uses_codebook)]
        return out

    by_numpy = decode_all()
    decode_jit.install()
    if path == "fields":  # the fields kernel alone, handed back after unfilter_fields read it
        transport.use_batch_kernels(None, None)
        transport.use_whole_kernel(None)
        module, name, hand_back = transport, "_kernel_plan", lambda: transport.use_fields_kernel(None)
    elif path == "batch":  # the batch kernels, handed back after the group's decode chose them
        transport.use_whole_kernel(None)
        module, name, hand_back = container, "_texels_at", lambda: transport.use_batch_kernels(None, None)
    else:  # the whole kernel, handed back after the group's decode planned its call
        module, name, hand_back = transport, "_whole_tables", lambda: transport.use_whole_kernel(None)
    real_step = getattr(module, name)

    def step(*args, **kwargs):
        hand_back()
        return real_step(*args, **kwargs)
    monkeypatch.setattr(module, name, step)
    assert decode_all() == by_numpy


@pytest.fixture(scope="module")
def winter_fountain_very_high():
    """winter_fountain (a bundled real scene, SH0) encoded with very-high and the encoder's defaults (the LOD tree
    bench/decode_quiet.py reads: 221 payloads of a few hundred splats, every texel plane f32x4)."""
    store = encode_in_memory(read_gaussians(real("winter_fountain.splat")), EncodeOptions(preset="very-high"))
    m = read_manifest(store)
    return m, payloads_by_group(store, m)


def test_very_high_decodes_with_the_kernels_as_the_numpy_path(numpy_path, winter_fountain_very_high):
    # f32x4's own path in fields1_kernel (_f32x4_layer: uint32 residuals, the running sums taken as the texels are
    # written) on a real scene's very-high payloads, every delta mode the encoder chose among them: the numpy path's
    # bytes, bit for bit, a whole group at once (the whole kernel, in runs), each payload alone, and a section at a
    # time (the fields kernel without the whole one)
    m, by_group = winter_fountain_very_high
    fields1 = [s for items in by_group.values() for _, e in items for s in e.sections if s.filter == "fields1"]
    assert fields1 and {s.format for s in fields1} == {"f32x4"}
    by_numpy = _planes_of_groups(by_group, m, alone=3)
    decode_jit.install()
    assert _planes_of_groups(by_group, m, alone=3) == by_numpy
    transport.use_whole_kernel(None)
    transport.use_batch_kernels(None, None)
    assert _planes_of_groups(by_group, m, alone=3) == by_numpy


def test_planes_kept_from_an_earlier_decode_keep_their_bytes(numpy_path, winter_fountain_very_high, fruit):
    # the whole kernel writes into this thread's kept slabs (transport.texel_slab): planes still held from an earlier
    # decode keep their bytes while other groups are decoded into slabs again and again, and a slab is written again
    # only once nothing views it
    m, by_group = winter_fountain_very_high
    decode_jit.install()
    items = by_group["base"]
    kept = container.unpack_payloads(items[:40], "base", ["kept"] * 40)
    expected = [planes_bytes(p) for p in kept]
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    others = payloads_by_group(store, read_manifest(store))
    for _ in range(3):
        container.unpack_payloads(items, "base", ["all"] * len(items))
        for group, its in others.items():
            container.unpack_payloads(its, group, ["fruit"] * len(its))
    assert [planes_bytes(p) for p in kept] == expected
    slabs = transport._slabs.kept
    held = [i for i in range(len(slabs)) if not transport._slab_free(slabs, i)]
    assert held  # the kept planes' slab, not handed out again
    views = [a for p in kept for q in p.values() for a in q.layers]
    assert all(any(np.shares_memory(v, slabs[i]) for i in held) for v in views)
    del kept, views
    assert all(transport._slab_free(slabs, i) for i in range(len(slabs)))


@pytest.mark.parametrize("texel_bytes", [2, 4, 8, 16])
@pytest.mark.parametrize("geometry", [(16, 16), (48, 32), (32, 64), (992, 16), (16, 48)])
def test_pair_stores_put_each_texel_where_slot_to_texel_says(texel_bytes, geometry):
    # fields1_kernel packs a layer in slot order and stores it two texels at a time (_store_pairs: slots 2k and
    # 2k + 1 side by side in a row, each block laid out as the first): every texel at slot_to_texel's place, as a
    # texel at a time puts it, on one block, several in a row, in a column and both
    width, height = geometry
    n = width * height
    order = transport.slot_to_texel(width, height)
    rng = np.random.default_rng(texel_bytes * 7919 + n)
    packed = rng.integers(0, 256, n * texel_bytes).astype(np.uint8)
    expected = np.zeros((n, texel_bytes), np.uint8)
    expected[order] = packed.reshape(n, texel_bytes)
    got = np.zeros(n * texel_bytes, np.uint8)
    decode_jit._store_pairs(packed, got, order, texel_bytes)
    assert got.tobytes() == expected.tobytes()


@pytest.mark.parametrize("preset", ["medium", "medium-low", "low-plus-9bit", "low", "very-low", "medium-12bit"])
def test_lossy_presets_on_wide_tiles_decode_with_the_kernels_as_the_numpy_path(numpy_path, fruit, preset):
    # the packed texel paths stored two at a time (norm565 SH bands, norm11 / norm9x3 positions, norm10_2
    # rotations, norm8x4 colour, index16 codebook indices) on the encoder's default tiles (fruit_drops_sh3 in one
    # tile: textures of many blocks in a row) and on small ones: the numpy path's bytes, bit for bit, a group in one
    # call (the whole kernel), a plane of a group a call (the batch kernels) and a section a call
    widest = []
    for options in (EncodeOptions(preset=preset), EncodeOptions(preset=preset, max_leaf_splats=512)):
        store = encode_in_memory(fruit, options)
        m = read_manifest(store)
        by_group = payloads_by_group(store, m)
        widths = {s.width for items in by_group.values() for _, e in items for s in e.sections if s.width}
        transport.use_fields_kernel(None)
        transport.use_batch_kernels(None, None)
        transport.use_whole_kernel(None)
        by_numpy = _planes_of_groups(by_group, m, alone=1)
        decode_jit.install()
        assert _planes_of_groups(by_group, m, alone=1) == by_numpy, (preset, widths)
        transport.use_whole_kernel(None)
        assert _planes_of_groups(by_group, m, alone=1) == by_numpy, (preset, widths)
        transport.use_batch_kernels(None, None)
        assert _planes_of_groups(by_group, m, alone=1) == by_numpy, (preset, widths)
        widest.append(max(widths))
    assert widest[0] > 16  # the default tile: blocks side by side
