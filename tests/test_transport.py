"""The `fields1` transport coding of texels sections (splatstream/format/transport.py, format_spec/format.md 5.2):
every section decodes back to exactly the GPU bytes, scenes decode to the same splats whatever the transport, and
malformed contents, section tables and payloads fail with a FormatError."""
from __future__ import annotations

import json
import os
import zlib

import numpy as np
import pytest
import zstandard
from conftest import real_path

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError
from splatstream.format.manifest import manifest_from_dict
from splatstream.format.texformats import FORMATS, blob_size, shuffle_bytes
from splatstream.format.transport import (
    BLOCK_TEXELS,
    FIELD_LAYOUTS,
    FIELDS1,
    FIELDS_VERSION,
    _block_costs,
    _block_stats,
    _cross_prediction,
    _fit_cross,
    _fit_from_stats,
    _fit_stacked,
    _fit_type,
    _plane_cost,
    _residual,
    _residual_rows,
    choose_modes,
    content_bounds,
    fields_content,
    filter_texels,
    join_layer,
    shuffle,
    slot_to_texel,
    split_layer,
    unfilter_fields,
    unfilter_texels,
    unshuffle,
    unused_bits,
)
from splatstream.io import read_gaussians
from splatstream.scene_decode import decode_scene
from splatstream.store import load_manifest

FRUIT = real_path("fruit_drops_sh3.ply")  # bundled (tests/data/real), so always here
VECTORS = os.path.join(os.path.dirname(__file__), "..", "format_spec", "vectors", "transport")
GEOMETRIES = [(16, 16, 1), (48, 32, 3), (64, 16, 7)]


def layers_of(data: np.ndarray, layers: int) -> list[np.ndarray]:
    unit = data.size // layers
    return [data[k * unit:(k + 1) * unit] for k in range(layers)]


def stored_bytes(parts) -> np.ndarray:
    return np.frombuffer(b"".join(bytes(memoryview(p)) for p in parts), np.uint8)


def roundtrip(data: np.ndarray, fmt: str, w: int, h: int, layers: int, transport: str = "fields") -> tuple[str, int]:
    """filter_texels then unfilter_texels: the same bytes back; returns (filter, stored size)."""
    filt, parts = filter_texels(layers_of(data, layers), fmt, w, h, layers, transport=transport)
    stored = stored_bytes(parts)
    back = unfilter_texels(stored, filt, fmt, w, h, layers, "test")
    assert len(back) == layers
    np.testing.assert_array_equal(np.concatenate(back), data)
    return filt, stored.size


def fields_roundtrip(data: np.ndarray, fmt: str, w: int, h: int, layers: int, modes=None) -> bytes:
    content, _ = fields_content(data, fmt, w, h, layers, modes)
    lo, hi = content_bounds(fmt, w, h, layers)
    assert lo <= len(content) <= hi
    np.testing.assert_array_equal(unfilter_fields(content, fmt, w, h, layers), data)
    return content


def valid_texels(data: np.ndarray, fmt: str) -> np.ndarray:
    """`data` with the bits no field holds cleared (bits 27-31 of norm9x3 MUST be 0, format.md 4.2)."""
    if fmt in FIELD_LAYOUTS and unused_bits(fmt):
        dtype = FIELD_LAYOUTS[fmt][0]
        data = (data.view(dtype) & np.dtype(dtype).type(~unused_bits(fmt) & 0xFFFFFFFF)).view(np.uint8)
    return data


def zstd_size(data) -> int:
    return len(zstandard.ZstdCompressor(level=3).compress(bytes(data)))


@pytest.mark.parametrize("fmt", sorted(FORMATS))
@pytest.mark.parametrize("geometry", GEOMETRIES)
def test_random_texels_round_trip_exactly_with_every_transport(fmt, geometry):
    w, h, layers = geometry
    rng = np.random.default_rng(zlib.crc32(f"{fmt} {geometry}".encode()))
    data = valid_texels(rng.integers(0, 256, blob_size(FORMATS[fmt], w, h, layers), dtype=np.uint8), fmt)
    element = max(1, FORMATS[fmt].shuffle)
    assert roundtrip(data, fmt, w, h, layers, "shuffle") == (f"shuffle{element}" if element > 1 else "none",
                                                              data.size)
    assert roundtrip(data, fmt, w, h, layers, "none") == ("none", data.size)
    filt, _ = roundtrip(data, fmt, w, h, layers)
    if fmt in FIELD_LAYOUTS:
        fields_roundtrip(data, fmt, w, h, layers)  # forced, whatever the encoder would pick for noise
    else:
        assert filt == "none"  # BC blocks are never split into fields


@pytest.mark.parametrize("fmt", sorted(FIELD_LAYOUTS))
def test_extreme_values_round_trip(fmt):
    """All-zero, all-ones and alternating extremes: residuals wrap around modulo 2^bits in both directions, with
    every combination of delta and reference the format allows."""
    w, h = 32, 32
    size = blob_size(FORMATS[fmt], w, h)
    nf = len(fields_content(np.zeros(size, np.uint8), fmt, w, h, 1)[1][0])
    for data in (np.zeros(size, np.uint8), np.full(size, 255, np.uint8),
                 np.tile(np.array([0, 0, 0, 0, 255, 255, 255, 255], np.uint8), size // 8)):
        data = valid_texels(data, fmt)
        fields_roundtrip(data, fmt, w, h, 1)
        for delta in (False, True):
            modes = [(delta, None)] + [(not delta, 0 if fmt != "f32x4" else None)] * (nf - 1)
            fields_roundtrip(data, fmt, w, h, 1, [modes])


def test_split_and_join_are_inverse_and_follow_the_slot_order():
    w, h = 32, 16
    rng = np.random.default_rng(1)
    words = rng.integers(0, 2**32, w * h, dtype=np.uint32)
    fields = split_layer(words.view(np.uint8), "norm11", w, h)
    assert [f.dtype for f in fields] == [np.uint16] * 3
    order = slot_to_texel(w, h)
    # slot 0 is texel (0, 0); slot 1 is (1, 0); slot 2 is (0, 1); slot 256 starts the second block at x = 16
    assert order[:4].tolist() == [0, 1, w, w + 1] and order[BLOCK_TEXELS] == 16
    np.testing.assert_array_equal(fields[0], words[order] & 2047)
    np.testing.assert_array_equal(fields[1], (words[order] >> 11) & 1023)
    np.testing.assert_array_equal(fields[2], words[order] >> 21)
    np.testing.assert_array_equal(join_layer(fields, "norm11", w, h), words.view(np.uint8))
    rgba = rng.integers(0, 256, (w * h, 4), dtype=np.uint8)
    fields = split_layer(rgba.reshape(-1), "norm8x4", w, h)
    assert [f.dtype for f in fields] == [np.uint8] * 4
    np.testing.assert_array_equal(fields[2], rgba[order, 2])
    np.testing.assert_array_equal(join_layer(fields, "norm8x4", w, h), rgba.reshape(-1))


def test_shuffle_matches_the_reference_byte_shuffle():
    rng = np.random.default_rng(9)
    for element in (1, 2, 4, 3):
        data = rng.integers(0, 256, 96 * 4, dtype=np.uint8)
        np.testing.assert_array_equal(shuffle(data, element), shuffle_bytes(data, element))
        np.testing.assert_array_equal(unshuffle(shuffle(data, element), element), data)


def _correlated_rgb565(w: int, h: int, layers: int, seed: int) -> np.ndarray:
    """norm565 layers whose R and B follow G (as SH channels of one coefficient do) and whose G is a random walk
    along the slot order (neighbouring splats are similar)."""
    rng = np.random.default_rng(seed)
    n = w * h
    out = []
    for _ in range(layers):
        g = np.cumsum(rng.integers(-2, 3, n)) % 64
        r = np.clip(g // 2 + rng.integers(-1, 2, n), 0, 31)
        b = np.clip(31 - g // 2 + rng.integers(-1, 2, n), 0, 31)
        texels = np.empty(n, "<u2")
        texels[slot_to_texel(w, h)] = (r | (g << 5) | (b << 11)).astype("<u2")
        out.append(texels)
    return np.concatenate(out).view(np.uint8)


def test_fields_coding_wins_on_correlated_channels_and_stays_exact():
    w, h, layers = 128, 64, 3
    data = _correlated_rgb565(w, h, layers, seed=2)
    filt, _ = roundtrip(data, "norm565", w, h, layers)
    assert filt == FIELDS1
    content, modes = fields_content(data, "norm565", w, h, layers)
    shuffled = np.concatenate([shuffle(x, 2) for x in layers_of(data, layers)])
    # G steps by -2..2 along the slots (2.3 bits), R and B are G/2 (or 31 - G/2) plus 1.6 bits of noise (about 2
    # bits each after rounding): 6.3 bits of entropy a texel against 16 stored; zstd reaches about 8.3 bits here
    # (measured 25,553 bytes for 49,152; byte shuffle 44,165)
    assert zstd_size(content) < 0.55 * data.size, (zstd_size(content), zstd_size(shuffled), data.size)
    assert zstd_size(content) < 0.65 * zstd_size(shuffled)
    assert content[0] == FIELDS_VERSION
    mode_bytes = np.frombuffer(content[1:1 + 3 * layers], np.uint8).reshape(layers, 3)
    # in every layer some field is predicted from another one (reference in the high nibble)
    assert ((mode_bytes >> 4) > 0).any(axis=1).all()
    assert all(any(r is not None for _, r in layer) for layer in modes)


def test_encoder_keeps_the_shuffle_where_fields_do_not_pay():
    """Random bytes: fields1 adds its header and gains nothing, so the byte shuffle is kept."""
    data = np.random.default_rng(3).integers(0, 256, blob_size(FORMATS["norm11"], 64, 64), dtype=np.uint8)
    assert roundtrip(data, "norm11", 64, 64, 1) == ("shuffle4", data.size)


def test_slopes_and_intercepts_that_clip_still_round_trip():
    """Per-block fits clamp to int8 slopes and int16 intercepts; the residual absorbs the rest exactly."""
    w, h = 32, 32
    n = w * h
    g = np.arange(n, dtype=np.int64) % 64
    r = (g * 31) % 32  # slope far outside what an int8 / 64 can say
    data = (r | (g << 5) | (((63 - g) // 2) << 11)).astype("<u2").view(np.uint8)
    fields_roundtrip(data, "norm565", w, h, 1, [[(False, 1), (False, None), (True, 1)]])
    words = np.zeros(n, "<u4")
    words |= (np.arange(n) * 7 % 2048).astype("<u4")
    words |= ((np.arange(n) * 13 % 1024).astype("<u4")) << 11
    words |= ((2047 - np.arange(n) % 2048).astype("<u4")) << 21
    fields_roundtrip(words.view(np.uint8), "norm11", w, h, 1, [[(False, 2), (True, 2), (False, None)]])


def test_encoding_is_deterministic():
    data = _correlated_rgb565(64, 32, 2, seed=3)
    assert fields_content(data, "norm565", 64, 32, 2) == fields_content(data.copy(), "norm565", 64, 32, 2)



# choose_modes of the test below, computed by the code before its pairs shared their work (the same modes since).
CHOOSE_MODES_PINNED = {5: [(False, 2), (False, None), (False, None)], 8: [(True, None), (False, None), (False, 0)],
                       10: [(False, None), (False, None), (False, 0)], 16: [(True, None), (False, None), (False, 0)]}


@pytest.mark.parametrize("bits", [5, 8, 10, 16])
def test_choose_modes_shared_work_gives_the_one_pair_results(bits):
    """choose_modes computes a field's block sums once for all its pairs and a residual without and with delta in
    one pass (issue 31's encode time): the same arrays as _residual and _fit_cross give one pair at a time."""
    rng = np.random.default_rng(bits)
    n = 6 * BLOCK_TEXELS
    dt = np.uint8 if bits <= 8 else np.uint16
    base = rng.integers(0, 1 << bits, n)
    values = ((base + rng.integers(0, 9, n)) % (1 << bits)).astype(dt)
    ref = ((3 * base // 2 + rng.integers(0, 5, n)) % (1 << bits)).astype(dt)
    t = _fit_type(bits)
    v = values.reshape(-1, BLOCK_TEXELS).astype(t)
    slope, intercept = _fit_from_stats(v, v.sum(axis=1, dtype=np.float64), _block_stats(ref, t))
    one_slope, one_intercept = _fit_cross(values, ref, bits)
    assert np.array_equal(slope, one_slope) and np.array_equal(intercept, one_intercept)
    assert np.any(slope != 0)
    for pred in (None, _cross_prediction(ref, slope, intercept), _cross_prediction(ref.astype(np.int32), slope,
                                                                                     intercept)):
        plain, delta = (z[0] for z in _residual_rows(values[None], (bits,), None if pred is None else
                                                     pred.astype(np.int32)[None]))
        assert np.array_equal(plain, _residual(values, bits, False, pred))
        assert np.array_equal(delta, _residual(values, bits, True, pred))
    fields = [values, ref, (values // 2).astype(dt)]
    assert choose_modes(fields, (bits,) * 3) == CHOOSE_MODES_PINNED[bits]



@pytest.mark.parametrize("bits", [(5, 6, 5), (8, 8, 8, 8), (11, 10, 11), (10, 10, 10, 2), (16, 16, 16, 16)])
def test_fit_stacked_equals_fit_cross_pair_by_pair(bits):
    """_fit_stacked (choose_modes' fits of every pair at once) gives _fit_cross's slopes and intercepts exactly."""
    rng = np.random.default_rng(sum(bits))
    n = 7 * BLOCK_TEXELS
    base = rng.integers(0, 1 << min(bits), n)
    fields = [((base * (k + 1) + rng.integers(0, 1 << (b // 2), n)) % (1 << b)).astype(np.uint8 if b <= 8 else
                                                                                      np.uint16)
              for k, b in enumerate(bits)]
    pairs = [(i, r) for i in range(len(bits)) for r in range(len(bits)) if i != r]
    slopes, intercepts = _fit_stacked(np.stack(fields), bits, tuple(pairs))
    assert slopes.shape == (len(pairs), 7) and np.any(slopes != 0)
    for p, (i, r) in enumerate(pairs):
        slope, intercept = _fit_cross(fields[i], fields[r], max(bits[i], bits[r]))
        assert np.array_equal(slopes[p], slope) and np.array_equal(intercepts[p], intercept)
        assert slopes[p].dtype == slope.dtype and intercepts[p].dtype == intercept.dtype


def test_block_costs_batch_equals_one_at_a_time():
    """_block_costs (choose_modes' one batch of entropies per layer) gives _plane_cost's floats exactly, for 8, 16
    and 32-bit codes, planes with one value, all 256 values and the skewed counts of real residuals."""
    rng = np.random.default_rng(31)
    n = 6 * BLOCK_TEXELS
    codes = [rng.integers(0, 256, n).astype(np.uint8), np.zeros(n, np.uint8),
             rng.geometric(0.3, n).astype(np.uint16), (rng.integers(0, 1 << 20, n) * 3).astype(np.uint32),
             rng.integers(0, 1 << 10, n).astype(np.uint16)]
    bits = [8, 5, 16, 32, 11]
    batch = [c for (c,) in _block_costs([(z[None], b) for z, b in zip(codes, bits, strict=True)])]
    assert batch == [_plane_cost(z, b) for z, b in zip(codes, bits, strict=True)]
    assert batch[1] == 0.0 and abs(batch[0] - n) < 0.05 * n  # one value: 0 bits; uniform bytes: ~8 bits a slot


# --- whole scenes -------------------------------------------------------------------------------------------------

needs_fruit = pytest.mark.skipif(FRUIT is None, reason="fruit_drops_sh3.ply: neither bundled in tests/data/real "
                                 "nor in $SPLATSTREAM_SHARED/data/real")


@needs_fruit
@pytest.mark.parametrize("preset", ["very-high", "high", "medium", "low"])
def test_scenes_decode_to_the_same_splats_with_either_transport(tmp_path, preset):
    if preset == "low":
        pytest.importorskip("etcpak")
    g = read_gaussians(FRUIT)
    sizes, decoded, manifests = {}, {}, {}
    for transport in ("shuffle", "fields"):
        out = tmp_path / transport
        encode_gaussians(g, out, EncodeOptions(preset=preset, lod=False, transport=transport))
        manifests[transport] = m = load_manifest(out)
        sizes[transport] = m.bytes_on_disk
        decoded[transport] = decode_scene(out)
    old, new = manifests["shuffle"], manifests["fields"]
    filters = {s.filter for _, _, p in new.payloads() for s in p.sections}
    # 1.2, or 1.13 for low's cube565 rotations (format.md 4.5): the version its formats need, either transport
    assert FIELDS1 in filters and new.version == old.version == ((1, 13) if preset == "low" else (1, 2))
    assert FIELDS1 not in {s.filter for _, _, p in old.payloads() for s in p.sections}
    # the manifest checksum: every scene is at least 1.2, fields1 or not
    # the GPU side is untouched: same texel sizes per payload, same decoded splats bit for bit
    assert new.gpu_bytes == old.gpu_bytes
    assert [p.gpu_bytes for _, _, p in new.payloads()] == [p.gpu_bytes for _, _, p in old.payloads()]
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(decoded["fields"], name), getattr(decoded["shuffle"], name))
    # measured on fruit_drops (B/splat, shuffle -> fields): medium 42.2 -> 37.1, high 78.9 -> 73.1, very-high
    # 208.5 -> 181.0, low 10.79 -> 10.54
    limit = {"medium": 0.9, "high": 0.95, "very-high": 0.9, "low": 0.99}[preset]
    assert sizes["fields"] < limit * sizes["shuffle"], sizes


# --- hostile input ------------------------------------------------------------------------------------------------

def _valid_content(layers=2):
    data = _correlated_rgb565(32, 16, layers, seed=5)
    content, _ = fields_content(data, "norm565", 32, 16, layers)
    return bytearray(content), ("norm565", 32, 16, layers)


@pytest.mark.parametrize("cut", [0, 1, 5, 17, -1])
def test_truncated_contents_raise_format_error(cut):
    content, geometry = _valid_content()
    with pytest.raises(FormatError):
        unfilter_fields(bytes(content[:cut] if cut >= 0 else content[:-1]), *geometry)


def test_garbage_and_malformed_contents_raise_format_error():
    content, geometry = _valid_content()
    rng = np.random.default_rng(6)
    for data in (b"", b"\x00" * 64, rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(), bytes(content) + b"\0"):
        with pytest.raises(FormatError):
            unfilter_fields(data, *geometry)
    for patch in ({0: FIELDS_VERSION + 1}, {1: 0x02}, {1: 0x10}, {2: 0x30}, {1: 0x20, 2: 0x10}, {1: 0x40}):
        bad = bytearray(content)
        for k, v in patch.items():
            bad[k] = v
        with pytest.raises(FormatError):  # wrong version, reserved bits, self / chained / missing references
            unfilter_fields(bytes(bad), *geometry)
    with pytest.raises(FormatError, match="does not apply"):
        unfilter_fields(bytes(content), "bc7", 32, 16, 2)
    for geometry in (("norm565", 30, 16, 2), ("norm565", 32, 0, 2), ("norm565", 32, 16, 0), ("norm565", 4096, 16, 1)):
        with pytest.raises(FormatError):
            unfilter_fields(bytes(content), *geometry)


def test_fields1_vectors_decode_exactly():
    """format_spec/vectors/transport: stored fields1 contents and the texel bytes they decode to (every mode)."""
    index = json.load(open(os.path.join(VECTORS, "vectors.json")))
    assert set(index) == {"norm11", "norm10_2", "norm565", "norm8x4", "f16x4", "index16", "norm16x4", "norm9x3"}
    modes_seen = set()
    for fmt, v in index.items():
        stored = open(os.path.join(VECTORS, f"{fmt}.fields1.bin"), "rb").read()
        texels = open(os.path.join(VECTORS, f"{fmt}.texels.bin"), "rb").read()
        assert len(stored) == v["stored_bytes"] and len(texels) == v["texel_bytes"]
        decoded = unfilter_fields(stored, fmt, v["width"], v["height"], v["layers"], f"{fmt}.fields1.bin")
        assert decoded.tobytes() == texels, fmt
        modes = [[(m["delta"], m["ref"]) for m in layer] for layer in v["modes"]]
        # the encoder gives the same content for the recorded modes
        assert fields_content(np.frombuffer(texels, np.uint8), fmt, v["width"], v["height"], v["layers"],
                              modes)[0] == stored, fmt
        modes_seen |= {(m["delta"], m["ref"] is not None) for layer in v["modes"] for m in layer}
    assert modes_seen == {(False, False), (True, False), (False, True), (True, True)}


def _fields1_scene(tmp_path):
    from conftest import read_manifest_dict

    g = read_gaussians(FRUIT).subset(slice(0, 700))
    encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium", lod=False, sh_degree=1))
    return read_manifest_dict(tmp_path / "s")


@needs_fruit
def test_section_tables_with_bad_fields1_entries_are_rejected(tmp_path):
    d = _fields1_scene(tmp_path)
    base = d["tiles"][0]["groups"]["base"]
    position = next(s for s in base["sections"] if s["name"] == "position")
    assert position["filter"] == FIELDS1
    manifest_from_dict(d)  # valid as written

    def rejected(mutate, match):
        bad = json.loads(json.dumps(d))
        sec = next(s for s in bad["tiles"][0]["groups"]["base"]["sections"] if s["name"] == mutate[0])
        sec[mutate[1]] = mutate[2]
        with pytest.raises(FormatError, match=match):
            manifest_from_dict(bad)

    rejected(("position.range", "filter", FIELDS1), "position.range.*filter|unknown filter")
    lo, hi = content_bounds("norm11", position["width"], position["height"], 1)
    rejected(("position", "size", lo - 16), "expected")
    rejected(("position", "size", hi + 16), "size|expected")
    rejected(("rotation", "filter", "fields2"), "unknown filter 'fields2'")
    # gpu_bytes counts the texels a section decodes to, not its stored bytes
    bad = json.loads(json.dumps(d))
    bad["tiles"][0]["groups"]["base"]["gpu_bytes"] = sum(s["size"] for s in base["sections"])
    with pytest.raises(FormatError, match="gpu_bytes"):
        manifest_from_dict(bad)


@needs_fruit
def test_damaged_fields1_sections_in_a_payload_raise_format_error(tmp_path):
    """A payload whose checksum matches but whose fields1 content is wrong (a writer's bug, or a forged scene)."""
    from splatstream.format.decode import decode_payload
    from splatstream.format.names import sha256_hex

    d = _fields1_scene(tmp_path)
    m = manifest_from_dict(d)
    entry = m.tiles[0].groups["base"]
    sec = entry.section("position")
    data = (tmp_path / "s" / entry.file).read_bytes()
    raw = bytearray(zstandard.ZstdDecompressor().decompress(data))
    for patch in ({sec.offset: 9}, {sec.offset + 1: 0x0E}):  # version, reserved mode bits
        bad = bytearray(raw)
        for k, v in patch.items():
            bad[k] = v
        forged = zstandard.ZstdCompressor(write_content_size=True).compress(bytes(bad))
        sha = sha256_hex(forged)
        from dataclasses import replace

        forged_entry = replace(entry, sha256=sha, file=f"data/{sha}.bin", bytes=len(forged))
        with pytest.raises(FormatError, match="section position"):
            decode_payload(forged, forged_entry, "base", "forged")


def test_texel_slabs_are_handed_out_again_only_once_nothing_views_them(monkeypatch):
    # transport.texel_slab (the whole kernel's output): a slab comes back for the next call of about its size once no
    # array views it, never while one does (planes held from an earlier decode keep their bytes); at most
    # KEEP_SLAB_BYTES are kept per thread, beyond it a fresh array; each thread has its own slabs
    import threading

    from splatstream.format import transport
    monkeypatch.setattr(transport._slabs, "kept", [], raising=False)
    a = transport.texel_slab(300_000)
    a[:] = 7
    layer = a[1000:2000]  # a plane's view, as the planes returned hold
    del a
    b = transport.texel_slab(300_000)
    assert not np.shares_memory(b, layer) and (layer == 7).all()
    del layer
    c = transport.texel_slab(290_000)  # the first slab again (the smallest free one that fits), not a third
    assert len(transport._slabs.kept) == 2 and np.shares_memory(c, transport._slabs.kept[0])
    del b, c
    small = transport.texel_slab(1000)  # below SLAB_MIN_BYTES: a fresh array, no slab
    assert small.size == 1000 and len(transport._slabs.kept) == 2
    del small
    unit = transport.SLAB_MIN_BYTES
    assert unit % transport.SLAB_STEP == 0
    monkeypatch.setattr(transport, "KEEP_SLAB_BYTES", 4 * unit)
    transport._slabs.kept = []
    held = [transport.texel_slab(unit) for _ in range(6)]  # four kept, then fresh arrays: every one its own bytes
    assert [s.size for s in transport._slabs.kept] == [unit] * 4 and all(h.size == unit for h in held)
    assert sum(any(np.shares_memory(h, s) for s in transport._slabs.kept) for h in held) == 4
    assert not any(np.shares_memory(x, y) for i, x in enumerate(held) for y in held[i + 1:])
    last = held[3]
    del held
    large = transport.texel_slab(3 * unit)  # slabs nothing views let go, oldest first, to make room for a larger one
    assert [s.size for s in transport._slabs.kept] == [unit, 3 * unit]
    assert np.shares_memory(last, transport._slabs.kept[0]) and np.shares_memory(large, transport._slabs.kept[1])
    monkeypatch.setattr(transport, "KEEP_SLAB_BYTES", 1 << 30)
    monkeypatch.setattr(transport, "KEEP_SLABS", 3)
    more = [transport.texel_slab(2 * unit) for _ in range(3)]  # at most KEEP_SLABS slabs, whatever their bytes
    assert len(transport._slabs.kept) == 3 and sum(any(np.shares_memory(m, s) for s in transport._slabs.kept)
                                                   for m in more) == 1
    other: list = []
    thread = threading.Thread(target=lambda: other.append((transport.texel_slab(unit), transport._slabs.kept)))
    thread.start()
    thread.join()
    assert other[0][1] is not transport._slabs.kept and np.shares_memory(other[0][0], other[0][1][0])
