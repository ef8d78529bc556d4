"""The fields1 decoder (transport.unfilter_fields) against a plain reference decoder written from format.md 5.2.

The decoder takes shortcuts for speed (int32 running sums, zigzag codes decoded from the byte planes, masks only
where a field's high bits reach the texel, work arrays kept per thread, a gather into texture order); these tests
hold it to the spec's arithmetic on arbitrary well-formed contents (random codes, modes, slopes and intercepts,
not only what the encoder writes), across threads and across work-buffer sizes."""
from __future__ import annotations

import threading
import zlib

import numpy as np
import pytest

from splatstream.format import transport
from splatstream.format.transport import (
    BLOCK_TEXELS,
    FIELD_LAYOUTS,
    FIELDS_VERSION,
    MODE_DELTA,
    field_bits,
    unfilter_fields,
)

GEOMETRIES = [(16, 16, 1), (48, 32, 3), (32, 64, 2)]


def reference_slot_order(width: int, height: int) -> np.ndarray:
    """Texel index of every slot, computed slot by slot: 16x16 blocks in row-major order, Morton order inside."""
    cols = width // 16
    order = []
    for s in range(width * height):
        b, j = divmod(s, BLOCK_TEXELS)
        bx = sum(((j >> (2 * k)) & 1) << k for k in range(4))
        by = sum(((j >> (2 * k + 1)) & 1) << k for k in range(4))
        order.append(((b // cols) * 16 + by) * width + (b % cols) * 16 + bx)
    return np.array(order)


def reference_unfilter(content: bytes, fmt: str, width: int, height: int, layers: int) -> bytes:
    """format.md 5.2 read literally: every field as int64 arithmetic, reduced modulo 2^bits."""
    bits = field_bits(fmt)
    nf, n = len(bits), width * height
    blocks = n // BLOCK_TEXELS
    raw = np.frombuffer(content, np.uint8)
    assert raw[0] == FIELDS_VERSION
    modes = raw[1:1 + nf * layers].tolist()
    pos = 1 + nf * layers
    params = {}
    for k, m in enumerate(modes):
        if m >> 4:
            slope = raw[pos:pos + blocks].view(np.int8).astype(np.int64)
            intercept = raw[pos + blocks:pos + 3 * blocks].view("<i2").astype(np.int64)
            params[k] = (np.repeat(slope, BLOCK_TEXELS), np.repeat(intercept, BLOCK_TEXELS))
            pos += 3 * blocks
    dtype, words, layout = FIELD_LAYOUTS[fmt]
    word_bytes = np.dtype(dtype).itemsize
    order = reference_slot_order(width, height)
    out = []
    for layer in range(layers):
        codes = []
        for b in bits:
            nb = (b + 7) // 8
            code = np.zeros(n, np.int64)
            for byte in range(nb):
                code |= raw[pos + byte * n:pos + (byte + 1) * n].astype(np.int64) << (8 * byte)
            pos += nb * n
            codes.append(code)
        values = [None] * nf
        lm = modes[layer * nf:(layer + 1) * nf]
        for i in sorted(range(nf), key=lambda i: (lm[i] >> 4) != 0):  # anchors first
            r = codes[i] if bits[i] <= 8 else (codes[i] >> 1) ^ -(codes[i] & 1)
            if lm[i] & MODE_DELTA:
                r = np.cumsum(r)
            if lm[i] >> 4:
                slope, intercept = params[layer * nf + i]
                ref = values[(lm[i] >> 4) - 1]
                r = r + (slope * ref + 64 * intercept + 32) // 64
            values[i] = r % (1 << bits[i])
        texels = np.zeros((n, words), np.int64)
        for w in range(words):
            for f, (shift, _) in enumerate(layout):
                texels[:, w] |= values[w * len(layout) + f] << shift
        in_texture_order = np.zeros_like(texels)
        in_texture_order[order] = texels
        out.append(in_texture_order.astype(np.uint64).astype(f"<u{word_bytes}").tobytes())
    return b"".join(out)


def random_modes(rng: np.random.Generator, bits: tuple[int, ...]) -> list[tuple[bool, int | None]]:
    """Modes the format allows: some anchors, other fields of up to 16 bits predicted from one of them or not."""
    nf = len(bits)
    anchors = [i for i in range(nf) if rng.random() < 0.5 or bits[i] > 16] or [0]
    modes = []
    for i in range(nf):
        options = [r for r in anchors if r != i and bits[i] <= 16 and bits[r] <= 16]
        ref = int(rng.choice(options)) if i not in anchors and options and rng.random() < 0.7 else None
        modes.append((bool(rng.random() < 0.6), ref))
    return modes


def random_content(rng: np.random.Generator, fmt: str, width: int, height: int, layers: int,
                   modes: list[list[tuple[bool, int | None]]]) -> bytes:
    """A well-formed fields1 content with these modes and random slopes, intercepts and plane bytes."""
    bits = field_bits(fmt)
    n = width * height
    head = bytes([FIELDS_VERSION]) + bytes((MODE_DELTA if d else 0) | ((0 if r is None else r + 1) << 4)
                                            for layer in modes for d, r in layer)
    params = b"".join(rng.integers(-128, 128, n // BLOCK_TEXELS).astype(np.int8).tobytes()
                      + rng.integers(-32768, 32768, n // BLOCK_TEXELS).astype("<i2").tobytes()
                      for layer in modes for _, r in layer if r is not None)
    planes = b""
    for _layer in modes:
        for b in bits:
            for _ in range((b + 7) // 8):
                # small codes (smooth fields) as well as any byte: either must decode as the spec says
                top = 256 if rng.random() < 0.5 else 4
                planes += rng.integers(0, top, n).astype(np.uint8).tobytes()
    return head + params + planes


@pytest.mark.parametrize("fmt", sorted(FIELD_LAYOUTS))
@pytest.mark.parametrize("geometry", GEOMETRIES)
def test_decoder_matches_the_spec_on_arbitrary_contents(fmt, geometry):
    width, height, layers = geometry
    rng = np.random.default_rng(zlib.crc32(f"decode {fmt} {geometry}".encode()))
    bits = field_bits(fmt)
    every_delta = [[(d, None) for _ in bits] for d in (False, True)]
    for trial in range(8):
        modes = every_delta if trial == 0 else [random_modes(rng, bits) for _ in range(layers)]
        modes = (modes * layers)[:layers]
        content = random_content(rng, fmt, width, height, layers, modes)
        decoded = unfilter_fields(content, fmt, width, height, layers)
        assert decoded.dtype == np.uint8
        assert decoded.tobytes() == reference_unfilter(content, fmt, width, height, layers), (fmt, modes)


def test_threads_and_work_buffer_sizes_do_not_mix_sections(monkeypatch):
    """Work arrays are per thread and reused: sections of several formats and sizes decoded at once on four
    threads, and with work buffers too large to keep (allocated per call), give what one thread gives."""
    rng = np.random.default_rng(7)
    cases = []
    for fmt, (w, h, layers) in [("norm16x4", (48, 32, 1)), ("norm8x4", (16, 16, 2)), ("norm11", (32, 64, 1)),
                                ("f16x4", (64, 16, 3)), ("norm10_2", (16, 48, 1))]:
        modes = [random_modes(rng, field_bits(fmt)) for _ in range(layers)]
        content = random_content(rng, fmt, w, h, layers, modes)
        cases.append((content, fmt, w, h, layers, reference_unfilter(content, fmt, w, h, layers)))
    failures = []

    def work(seed: int) -> None:
        order = np.random.default_rng(seed).permutation(len(cases) * 6) % len(cases)
        for k in order:
            content, fmt, w, h, layers, expected = cases[k]
            if unfilter_fields(content, fmt, w, h, layers).tobytes() != expected:
                failures.append((seed, fmt))

    threads = [threading.Thread(target=work, args=(seed,)) for seed in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert failures == []
    monkeypatch.setattr(transport, "KEEP_WORK_BYTES", 4096)  # every case above now takes a fresh buffer
    monkeypatch.setattr(transport, "_work", threading.local())
    work(99)
    assert failures == []


@pytest.mark.parametrize("transport_name", ["none", "fields"])
def test_decoded_planes_do_not_share_the_reused_payload_buffer(transport_name):
    """unpack_payload decompresses into a buffer kept per thread: whatever it returns (texels of "none" sections,
    ranges, fields1 texels) must survive the next payloads decoded on the thread, and equal a decode in another
    thread."""
    from splatstream.encode import EncodeOptions
    from splatstream.encode.local import encode_in_memory
    from splatstream.format.decode import decode_payload
    from splatstream.gaussians import Gaussians
    from splatstream.store import read_manifest

    rng = np.random.default_rng(3)
    n = 3000
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = Gaussians(rng.normal(size=(n, 3)), q, rng.normal(-3, 0.5, size=(n, 3)), rng.normal(0, 2, size=n),
                  rng.normal(size=(n, 3)), rng.normal(0, 0.1, size=(n, 3, 3)))
    store = encode_in_memory(g, EncodeOptions(preset="very-low", max_leaf_splats=512, transport=transport_name,
                                              sh_codebook="off"))
    m = read_manifest(store)
    jobs = [(store.read_payload(t.groups[gr]), t.groups[gr], gr) for t in m.tiles for gr in t.groups]
    assert len(jobs) > 4

    def snapshot(planes: dict) -> list[bytes]:
        return [np.asarray(a).tobytes() for p in planes.values() for a in [*p.layers, p.ranges] if a is not None]

    first = [decode_payload(d, e, gr, "test", m.uses_codebook) for d, e, gr in jobs]  # all kept, one thread
    elsewhere: list = []
    t = threading.Thread(target=lambda: elsewhere.extend(
        snapshot(decode_payload(d, e, gr, "test", m.uses_codebook)) for d, e, gr in jobs))
    t.start()
    t.join()
    assert [snapshot(p) for p in first] == elsewhere
    if transport_name == "none":
        assert any(s.filter == "none" for _, e, _ in jobs for s in e.sections if s.kind == "texels")
