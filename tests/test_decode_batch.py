"""Several payloads decoded together (format.decode.decode_payloads, container.unpack_payloads,
transport.unfilter_fields_many, transport.unshuffle_many) give what decoding them one at a time gives, bit for bit:
on a real scene encoded with every preset (the LOD tree's tiles of every size, fields1 sections of many modes,
shuffled and BC sections, SH groups, the codebook's index planes), on arbitrary fields1 contents, and a payload
that does not decode is named. Also the ranges' one-pass check (container._ranges_ok) against the checks it
stands for."""
from __future__ import annotations

import zlib

import numpy as np
import pytest
import zstandard
from conftest import payloads_by_group, real, zstd_block_count
from test_transport_decode import random_content, random_modes

from splatstream.encode import EncodeOptions
from splatstream.encode.local import encode_in_memory
from splatstream.errors import FormatError
from splatstream.format import container
from splatstream.format.decode import decode_payload, decode_payloads
from splatstream.format.presets import PRESET_BLOCK_SLACK, PRESET_ONE_BLOCK_SLACK, PRESETS
from splatstream.format.transport import (
    FIELD_LAYOUTS,
    field_bits,
    unfilter_fields,
    unfilter_fields_many,
    unshuffle,
    unshuffle_many,
)
from splatstream.io import read_gaussians
from splatstream.store import read_manifest


def planes_bytes(planes: dict) -> list:
    out = []
    for name, p in planes.items():
        out.append((name, p.spec.name, p.format, p.width, p.height))
        out += [(np.asarray(a).dtype.str, np.asarray(a).shape, np.asarray(a).tobytes()) for a in p.layers]
        if p.ranges is not None:
            out.append((p.ranges.dtype.str, p.ranges.shape, p.ranges.tobytes()))
    return out


@pytest.fixture(scope="module")
def fruit():
    return read_gaussians(real("fruit_drops_sh3.ply"))


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_decodes_together_as_one_at_a_time(fruit, preset):
    store = encode_in_memory(fruit, EncodeOptions(preset=preset, max_leaf_splats=512))
    m = read_manifest(store)
    by_group = payloads_by_group(store, m)
    assert len(by_group["base"]) >= 8
    for group, items in by_group.items():
        alone = [planes_bytes(decode_payload(d, e, group, "t", m.uses_codebook)) for d, e in items]
        sources = [f"t{k}" for k in range(len(items))]
        for size in (len(items), 3):
            together = []
            for i in range(0, len(items), size):
                together += [planes_bytes(p) for p in decode_payloads(items[i:i + size], group, sources[i:i + size],
                                                                      m.uses_codebook)]
            assert together == alone, (preset, group, size)


def test_decoded_together_survive_the_next_batch():
    """The batch's payloads are decompressed into this thread's kept buffer: nothing returned may be a view of it."""
    rng = np.random.default_rng(5)
    from splatstream.gaussians import Gaussians
    n = 3000
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = Gaussians(rng.normal(size=(n, 3)), q, rng.normal(-3, 0.5, size=(n, 3)), rng.normal(0, 2, size=n),
                  rng.normal(size=(n, 3)), rng.normal(0, 0.1, size=(n, 3, 3)))
    for transport_name in ("none", "fields"):
        store = encode_in_memory(g, EncodeOptions(preset="very-low", max_leaf_splats=512, transport=transport_name,
                                                  sh_codebook="off"))
        m = read_manifest(store)
        items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles]
        first = decode_payloads(items, "base", ["t"] * len(items))
        kept = [planes_bytes(p) for p in first]
        decode_payloads(items[::-1], "base", ["t"] * len(items))
        assert [planes_bytes(p) for p in first] == kept


@pytest.mark.parametrize("fmt", sorted(FIELD_LAYOUTS))
def test_fields_many_matches_one_at_a_time_on_arbitrary_contents(fmt):
    rng = np.random.default_rng(zlib.crc32(f"many {fmt}".encode()))
    bits = field_bits(fmt)
    for layers in (1, 2):
        modes = [random_modes(rng, bits) for _ in range(layers)]
        dims = [(16, 16), (48, 32), (16, 48), (32, 16)]
        raws = [np.frombuffer(random_content(rng, fmt, w, h, layers, modes), np.uint8) for w, h in dims]
        got = unfilter_fields_many(raws, fmt, dims, layers, ["s"] * len(raws))
        for raw, (w, h), texels in zip(raws, dims, got, strict=True):
            assert len(texels) == layers
            assert b"".join(t.tobytes() for t in texels) == unfilter_fields(raw, fmt, w, h, layers).tobytes(), \
                (fmt, modes)


def test_fields_many_names_the_section_that_does_not_decode():
    rng = np.random.default_rng(11)
    modes = [random_modes(rng, field_bits("norm11"))]
    raws = [np.frombuffer(random_content(rng, "norm11", 16, 16, 1, modes), np.uint8) for _ in range(3)]
    raws[1] = raws[1][:-1]
    with pytest.raises(FormatError, match="second"):
        unfilter_fields_many(raws, "norm11", [(16, 16)] * 3, 1, ["first", "second", "third"])


@pytest.mark.parametrize("element", [2, 4, 8])
def test_unshuffle_many_matches_unshuffle(element):
    rng = np.random.default_rng(element)
    for sizes in ([8, 64, 4096], [16, 24]):
        units = [rng.integers(0, 256, s * element, dtype=np.uint8) for s in sizes]
        got = unshuffle_many(units, element)
        assert [g.tobytes() for g in got] == [unshuffle(u, element).tobytes() for u in units]


def _damaged(data: bytes, entry, name: str, value: float):
    """The payload with the first minimum of range section `name` replaced (zstd again; the entry's checksum no
    longer matches, so it goes to unpack_payloads, which takes verified bytes)."""
    raw = bytearray(zstandard.ZstdDecompressor().decompress(data))
    s = entry.section(name)
    stored = np.frombuffer(bytes(raw[s.offset:s.offset + s.size]), np.uint8)
    ranges = unshuffle(stored, s.element).view({"f32": "<f4", "f16": "<f2"}[s.dtype]).copy()
    with np.errstate(over="ignore"):  # 1e30 into an f16 range is meant to become inf: the damage under test
        ranges[0] = value
    from splatstream.format.transport import shuffle
    raw[s.offset:s.offset + s.size] = shuffle(ranges.view(np.uint8), s.element).tobytes()
    return zstandard.ZstdCompressor().compress(bytes(raw))


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e30])
def test_a_bad_range_in_a_batch_names_its_payload(fruit, value):
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    data, entry = items[2]
    items[2] = (_damaged(data, entry, "position.range", value), entry)
    with pytest.raises(FormatError, match="payload2"):
        container.unpack_payloads(items, "base", [f"payload{k}" for k in range(4)])


def _reference_ok(ranges: np.ndarray, plane: str) -> bool:
    r = ranges.astype(np.float32)
    lo, hi = r[:, 0], r[:, 1]
    if not np.isfinite(r).all() or (lo > hi).any():
        return False
    limit = container.RANGE_LIMITS.get(plane)
    return limit is None or (float(lo.min()) >= limit[0] and float(hi.max()) <= limit[1])


@pytest.mark.parametrize("small", [container.SMALL_RANGES, 0])  # small sections in Python, and numpy's reductions
@pytest.mark.parametrize("dtype", ["<f4", "<f2"])
def test_one_pass_range_check_agrees_with_the_checks(dtype, small, monkeypatch):
    monkeypatch.setattr(container, "SMALL_RANGES", small)
    monkeypatch.setattr(container, "_ranges_kernel", None)  # these paths, not the compiled check a test installed
    rng = np.random.default_rng(1)
    specials = [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e6, -1e6, 65504.0, 3e38, -3e38, 1e18, -1e18, 2e18, -80.0, 40.0,
                -80.5, 40.5]
    for plane in ("position", "scale", "color"):
        for _ in range(400):
            r = rng.normal(0, 3, size=(3, 2, 1, 3))
            r[:, 1] = r[:, 0] + np.abs(rng.normal(0, 1, size=(3, 1, 3)))
            for _ in range(rng.integers(0, 3)):
                r[tuple(rng.integers(0, s) for s in r.shape)] = specials[rng.integers(len(specials))]
            with np.errstate(over="ignore", invalid="ignore"):
                ranges = r.astype(dtype)
            expected = _reference_ok(ranges, plane)
            assert container._ranges_ok(ranges, plane) == expected, (plane, ranges)
            if expected:
                container._check_ranges(ranges, plane, "r", "s")
            else:
                with pytest.raises(FormatError):
                    container._check_ranges(ranges, plane, "r", "s")


def test_keyed_positions_decode_together_as_one_at_a_time(fruit):
    """Payloads with sections decode_payloads does not batch (keyed positions, format.md 5.4) are decoded one at a
    time by it: the same planes."""
    store = encode_in_memory(fruit, EncodeOptions(preset="medium-12bit", max_leaf_splats=512, transport="keyed"))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles]
    assert any(s.filter == "morton1" for _, e in items for s in e.sections)
    alone = [planes_bytes(decode_payload(d, e, "base", "t")) for d, e in items]
    assert [planes_bytes(p) for p in decode_payloads(items, "base", ["t"] * len(items))] == alone


def test_block_ends_join_like_parts_of_small_payloads_only():
    rng = np.random.default_rng(5)
    noise = [rng.integers(0, 256, 1024, dtype=np.uint8) for _ in range(3)]  # like parts: one table serves them
    skewed = [np.minimum(rng.geometric(0.3, 1024), 255).astype(np.uint8) for _ in range(2)]
    segments = [(None, p) for p in noise + skewed] + [(bytes(16), np.zeros(1024, np.uint8))]
    ends = container._block_ends(segments, 6 * 1024 + 16)
    assert ends[-1] and sum(ends) < len(segments)  # some parts share a block
    assert ends[2]  # the noise and the skewed bytes have unlike statistics: a block ends between them
    assert container._block_ends(segments, container.MERGE_MAX_RAW + 1) == [True] * len(segments)
    assert container._block_ends(segments[:1], 1024) == [True]
    # a large payload of a preset that joins anyway (very-high: write_payload's one_block_slack) joins as a small one
    assert container._block_ends(segments, container.MERGE_MAX_RAW + 1, join_large=True) == ends


def test_large_payloads_join_blocks_up_to_zstds_largest_block():
    # container._block_ends with join_large: blocks of like parts grow to LARGE_MERGED_BLOCK_MAX (zstd's 128 KB)
    # above MERGE_MAX_RAW, to MERGED_BLOCK_MAX below it
    rng = np.random.default_rng(6)
    part = 8 * 1024
    segments = [(None, rng.integers(0, 256, part, dtype=np.uint8)) for _ in range(40)]  # 320 KB of like noise
    raw = 40 * part
    assert raw > container.MERGE_MAX_RAW and container.LARGE_MERGED_BLOCK_MAX == zstandard.BLOCKSIZE_MAX
    ends = container._block_ends(segments, raw, 0.035, join_large=True)
    assert ends[-1] and sum(ends) == -(-raw // container.LARGE_MERGED_BLOCK_MAX)  # 128 KB blocks: 16 parts each
    assert [k for k, e in enumerate(ends) if e][:2] == [15, 31]
    small = container._block_ends(segments[:24], 24 * part, 0.035)  # 192 KB: a small payload, 64 KB blocks
    assert sum(small) == 3


def test_small_payloads_have_fewer_blocks_and_bytes_and_the_same_raw_bytes(fruit, monkeypatch):
    # container._block_ends: where blocks end changes no decompressed byte (format.md 5.2); the encoder joins like
    # parts of a small payload into one block, fewer bytes than a block a part
    def encode():
        store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
        m = read_manifest(store)
        return [(store.read_payload(e), e) for t in m.tiles for e in t.groups.values()]

    joined = encode()
    monkeypatch.setattr(container, "MERGE_MAX_RAW", 0)
    apart = encode()
    assert len(joined) == len(apart) > 10
    d = zstandard.ZstdDecompressor()
    for (a, ea), (b, eb) in zip(joined, apart, strict=True):
        assert d.decompress(a) == d.decompress(b) and ea.sections == eb.sections and ea.raw_bytes == eb.raw_bytes
        assert zstd_block_count(a) > 0 and zstd_block_count(b) > 0  # each one well-formed frame, as parsed
    blocks_joined = sum(zstd_block_count(a) for a, _ in joined)
    blocks_apart = sum(zstd_block_count(b) for b, _ in apart)
    assert 0 < blocks_joined < 0.7 * blocks_apart
    assert sum(len(a) for a, _ in joined) < 0.995 * sum(len(b) for b, _ in apart)



def test_block_ends_with_slack_join_more_parts():
    # a slack (presets.PRESET_BLOCK_SLACK) joins a part where the joined block codes up to 1 + slack times the parts'
    # bytes: fewer blocks, never more, and none joined across MERGE_MAX_RAW
    rng = np.random.default_rng(5)
    parts = [rng.integers(0, 256, 1024, dtype=np.uint8) for _ in range(3)]
    parts += [np.minimum(rng.geometric(p, 1024), 255).astype(np.uint8) for p in (0.3, 0.05, 0.5, 0.02)]
    segments = [(None, p) for p in parts]
    raw = 7 * 1024
    ends = {slack: container._block_ends(segments, raw, slack) for slack in (0.0, 0.03, 0.5)}
    assert sum(ends[0.5]) < sum(ends[0.03]) <= sum(ends[0.0]) and sum(ends[0.5]) == 1
    assert all(e[-1] for e in ends.values())
    assert container._block_ends(segments, container.MERGE_MAX_RAW + 1, 0.5) == [True] * len(segments)


def test_a_shortest_match_changes_the_frame_not_its_bytes_decompressed():
    # container._compressor (presets.PRESET_ZSTD_MIN_MATCH): 0 is the level's own parameters, the frame the plain
    # compressor writes; a shortest match of 6 leaves out the shorter matches (3-5 byte repeats here), the content
    # size still in the frame header (format.md 5.1), the same bytes decompressed
    rng = np.random.default_rng(7)
    words = rng.integers(0, 256, (64, 4), dtype=np.uint8)
    data = words[rng.integers(0, 64, 4096)].tobytes()  # 4-byte words from a small set: short matches only
    size = len(data)

    def frame(min_match: int) -> bytes:
        return container._compressor(16, 0, size, min_match).compress(data)

    assert frame(0) == zstandard.ZstdCompressor(level=16, write_content_size=True).compress(data)
    longer = frame(6)
    assert longer != frame(0) and zstandard.frame_content_size(longer) == size
    assert zstandard.ZstdDecompressor().decompress(longer) == data


def test_very_high_joins_blocks_with_its_slack_the_same_bytes_decompressed(fruit, monkeypatch):
    # very-high's slack (presets.PRESET_BLOCK_SLACK; issue 32: each zstd block's tables cost its reader more than
    # their bytes) changes where blocks end and nothing decompressed (format.md 5.2): fewer blocks, within 2 % of
    # the bytes
    def encode():
        store = encode_in_memory(fruit, EncodeOptions(preset="very-high", max_leaf_splats=512))
        m = read_manifest(store)
        return [(store.read_payload(e), e) for t in m.tiles for e in t.groups.values()]

    assert PRESET_BLOCK_SLACK["very-high"] > 0
    monkeypatch.delitem(PRESET_ONE_BLOCK_SLACK, "very-high")  # the slack alone (the one-block rule: the test after)
    joined = encode()
    monkeypatch.setitem(PRESET_BLOCK_SLACK, "very-high", 0.0)
    apart = encode()
    assert len(joined) == len(apart) > 10
    d = zstandard.ZstdDecompressor()
    for (a, ea), (b, eb) in zip(joined, apart, strict=True):
        assert d.decompress(a) == d.decompress(b) and ea.sections == eb.sections
    blocks_joined = sum(zstd_block_count(a) for a, _ in joined)
    blocks_apart = sum(zstd_block_count(b) for b, _ in apart)
    assert 0 < blocks_joined < 0.8 * blocks_apart
    assert sum(len(a) for a, _ in joined) < 1.02 * sum(len(b) for b, _ in apart)  # (the trials' level is 1, the
    # payload's 12: joined blocks may even code smaller)

def test_very_high_stores_a_small_payload_as_one_block_within_its_one_block_slack(fruit, monkeypatch):
    # very-high's one-block slack (presets.PRESET_ONE_BLOCK_SLACK; issue 32: a block's tables cost zstd's reader more
    # than their bytes): a payload of at most MERGE_MAX_RAW is stored as one zstd block where that frame takes at most
    # 1 + slack times the bytes of its joined blocks' (container.write_payload), else as those blocks; nothing
    # decompressed changes (format.md 5.2)
    def encode():
        store = encode_in_memory(fruit, EncodeOptions(preset="very-high", max_leaf_splats=512))
        m = read_manifest(store)
        return [(store.read_payload(e), e) for t in m.tiles for e in t.groups.values()]

    slack = PRESET_ONE_BLOCK_SLACK["very-high"]
    assert 0 < slack <= 0.01
    one = encode()
    monkeypatch.delitem(PRESET_ONE_BLOCK_SLACK, "very-high")
    joined = encode()
    assert len(one) == len(joined) > 10
    d = zstandard.ZstdDecompressor()
    singles = 0
    for (a, ea), (b, eb) in zip(one, joined, strict=True):
        assert d.decompress(a) == d.decompress(b) and ea.sections == eb.sections
        assert len(a) <= (1 + slack) * len(b)
        if a != b:  # stored as one block: a data block and the frame's empty last one (FLUSH_BLOCK, then the end)
            assert ea.raw_bytes <= container.MERGE_MAX_RAW and zstd_block_count(b) > 2
            assert zstd_block_count(a) <= 1 + -(-ea.raw_bytes // zstandard.BLOCKSIZE_MAX)
            singles += 1
    assert singles >= 1  # (fruit_drops' SH3 tiles of 512 splats: most of their payloads cost more as one block)
    assert sum(zstd_block_count(a) for a, _ in one) < sum(zstd_block_count(b) for b, _ in joined)
    monkeypatch.setitem(PRESET_ONE_BLOCK_SLACK, "very-high", 1.0)  # any cost: every small payload is one block
    for data, entry in encode():
        if entry.raw_bytes <= container.MERGE_MAX_RAW:
            assert zstd_block_count(data) <= 1 + -(-entry.raw_bytes // zstandard.BLOCKSIZE_MAX)


def test_very_high_joins_the_blocks_of_large_payloads_too(monkeypatch):
    # very-high (its one-block slack, presets.PRESET_ONE_BLOCK_SLACK) joins the parts of payloads above MERGE_MAX_RAW
    # as of small ones (issue 32: a block a byte plane made a third of zstd's read time block tables on playbot's LOD
    # tree); nothing decompressed changes (format.md 5.2): fewer blocks, within 2 % of the bytes
    g = read_gaussians(real("fruit_drops_sh3.ply"))

    def encode():
        store = encode_in_memory(g, EncodeOptions(preset="very-high"))
        m = read_manifest(store)
        return [(store.read_payload(e), e) for t in m.tiles for e in t.groups.values()]

    joined = encode()
    monkeypatch.setattr(container, "LARGE_MERGED_BLOCK_MAX", 0)  # a block a part above MERGE_MAX_RAW, as before
    apart = encode()
    assert len(joined) == len(apart)
    large = [k for k, (_, e) in enumerate(joined) if e.raw_bytes > container.MERGE_MAX_RAW]
    assert len(large) >= 2
    d = zstandard.ZstdDecompressor()
    for k, ((a, ea), (b, eb)) in enumerate(zip(joined, apart, strict=True)):
        assert d.decompress(a) == d.decompress(b) and ea.sections == eb.sections and ea.raw_bytes == eb.raw_bytes
        assert k in large or a == b  # a small payload's blocks as before
    joined = [joined[k] for k in large]
    apart = [apart[k] for k in large]
    blocks_joined = sum(zstd_block_count(a) for a, _ in joined)
    blocks_apart = sum(zstd_block_count(b) for b, _ in apart)
    assert 0 < blocks_joined < 0.8 * blocks_apart
    assert sum(len(a) for a, _ in joined) < 1.02 * sum(len(b) for b, _ in apart)


def _group_reads(monkeypatch) -> list[bool]:
    """Whether each container._decompress_group call decompressed its group (True) or left it to a payload at a
    time (False)."""
    calls: list[bool] = []
    group_read = container._decompress_group

    def spy(*args):
        got = group_read(*args)
        calls.append(got)
        return got
    monkeypatch.setattr(container, "_decompress_group", spy)
    return calls


@pytest.mark.parametrize("odd", ["none", "frame after", "bytes after", "no size", "size differs", "short"])
def test_a_group_decompressed_by_one_reader_as_a_payload_at_a_time(fruit, monkeypatch, odd):
    # container._decompress_group reads a group's frames end to end with one zstd reader; a payload that would not
    # read the same that way (a frame or bytes after its frame, a frame without its size, another size than the
    # manifest's, a cut frame) sends the group to a payload at a time: the same planes, or the error a payload alone
    # gets, naming the payload
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    sources = [f"payload{k}" for k in range(4)]
    expected = [planes_bytes(container.unpack_payload(d, e, "base", s)) for (d, e), s in zip(items, sources,
                                                                                               strict=True)]
    data, entry = items[2]
    raw = zstandard.ZstdDecompressor().decompress(data)
    damaged = {
        "none": data,
        "frame after": data + zstandard.ZstdCompressor().compress(b"more bytes"),
        "bytes after": data + b"\0\1\2",
        "no size": zstandard.ZstdCompressor(write_content_size=False).compress(raw),
        "size differs": zstandard.ZstdCompressor().compress(raw + b"\0" * 16),
        "short": data[:-7],
    }[odd]
    items[2] = (damaged, entry)
    reads = _group_reads(monkeypatch)
    if odd in ("none", "no size"):
        assert [planes_bytes(p) for p in container.unpack_payloads(items, "base", sources)] == expected
    else:
        with pytest.raises(FormatError, match="payload2") as alone:
            container.unpack_payload(damaged, entry, "base", "payload2")
        with pytest.raises(FormatError, match="payload2") as together:
            container.unpack_payloads(items, "base", sources)
        assert str(together.value) == str(alone.value)
    assert reads == [odd == "none"]


def test_a_large_group_is_decompressed_a_payload_at_a_time(fruit, monkeypatch):
    # above GROUP_READ_MAX_BYTES compressed a group's frames are not copied end to end for one reader
    store = encode_in_memory(fruit, EncodeOptions(preset="medium", max_leaf_splats=512))
    m = read_manifest(store)
    items = [(store.read_payload(t.groups["base"]), t.groups["base"]) for t in m.tiles][:4]
    sources = [f"payload{k}" for k in range(4)]
    together = [planes_bytes(p) for p in container.unpack_payloads(items, "base", sources)]
    monkeypatch.setattr(container, "GROUP_READ_MAX_BYTES", sum(len(d) for d, _ in items) - 1)
    reads = _group_reads(monkeypatch)
    assert [planes_bytes(p) for p in container.unpack_payloads(items, "base", sources)] == together
    assert reads == [False]


def test_whole_ranges_checks_ranges_in_a_row_at_once_or_each_apart_and_names_a_bad_one():
    """container._whole_ranges, the whole kernel's range check: ranges the planner found in one row of one shape
    (`shape`) come back as views of one checked array, ranges apart (shape None) each checked alone; the values are
    the bytes at range_at either way, and a bad payload is named (issue 32: the planner's one walk over them)."""
    from splatstream.format.manifest import Section
    from splatstream.format.planes import group_planes

    spec = next(s for s in group_planes("base") if s.name == "scale")
    ranges = [np.array([[[[-1.0, 0.0, 0.5]], [[0.0, 1.0, 2.0]]]], np.float16),
              np.array([[[[-2.0, -1.0, 0.0]], [[2.0, 3.0, 4.0]]], [[[0.0, 0.0, 0.0]], [[0.5, 0.5, 0.5]]]], np.float16)]
    rs = [Section("scale.range", "range", 0, r.nbytes, "shuffle2", dtype="f16", shape=r.shape) for r in ranges]
    for gap in (0, 4):  # in a row, or 4 bytes apart
        out = np.zeros(64, np.uint8)
        range_at = [8, 8 + ranges[0].nbytes + gap]
        for at, r in zip(range_at, ranges, strict=True):
            out[at:at + r.nbytes] = r.view(np.uint8).reshape(-1)
        shape = ranges[0].shape[1:] if gap == 0 else None
        got = container._whole_ranges(out, range_at, rs, shape, spec, ["payload1", "payload2"])
        assert [g.shape for g in got] == [(1, 2, 1, 3), (2, 2, 1, 3)]
        assert all(np.array_equal(g, r) for g, r in zip(got, ranges, strict=True))
        assert all(np.shares_memory(g, out) for g in got)
        bad = out.copy()
        bad[range_at[1]:range_at[1] + 2] = np.array([np.nan], np.float16).view(np.uint8)
        with pytest.raises(FormatError, match="payload2"):
            container._whole_ranges(bad, range_at, rs, shape, spec, ["payload1", "payload2"])
