import numpy as np
import pytest

from splatstream.format import layout
from splatstream.format.texformats import (
    FORMATS,
    decode_image,
    encode_image,
    get_format,
    shuffle_bytes,
    unshuffle_bytes,
)

RNG = np.random.default_rng(1)


@pytest.mark.parametrize("name", [n for n, f in FORMATS.items() if f.block == 1])
def test_plain_formats_round_trip_within_half_a_step(name):
    fmt = get_format(name)
    t = RNG.random((32, 48, 4), dtype=np.float32)
    t[0, 0] = 0.0
    t[0, 1] = 1.0
    blob = encode_image(name, t)
    assert blob.size == 32 * 48 * fmt.bits_per_texel // 8
    back = decode_image(name, blob, 48, 32)
    for c in range(fmt.components):
        err = np.abs(back[..., c] - t[..., c]).max()
        assert err <= fmt.step(c) / 2 + 1e-7, (name, c, err)
    # end points are exact
    assert np.all(back[0, 0, : fmt.components] == 0.0)
    assert np.allclose(back[0, 1, : fmt.components], 1.0)


@pytest.mark.parametrize("name,rms_bound", [("bc7", 0.02), ("bc1", 0.05)])
def test_bc_formats_rms_error_on_smooth_data(name, rms_bound):
    pytest.importorskip("etcpak")
    y, x = np.mgrid[0:64, 0:64].astype(np.float32) / 63
    t = np.stack([x, y, (x + y) / 2, 1 - x], axis=-1)
    back = decode_image(name, encode_image(name, t), 64, 64)
    comps = get_format(name).components
    rms = np.sqrt(np.mean((back[..., :comps] - t[..., :comps]) ** 2))
    assert rms < rms_bound


def test_bc_channel_order_is_rgba():
    pytest.importorskip("etcpak")
    t = np.zeros((16, 16, 4), np.float32)
    t[..., 0] = 1.0
    t[..., 3] = 0.5
    back = decode_image("bc7", encode_image("bc7", t), 16, 16)
    assert back[..., 0].min() > 0.95 and back[..., 1].max() < 0.05 and back[..., 2].max() < 0.05
    assert abs(back[..., 3].mean() - 0.5) < 0.02


def test_known_bit_layouts():
    t = np.array([[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]]], np.float32)
    assert encode_image("norm11", t).view("<u4").tolist() == [2047, 1023 << 11, 2047 << 21]
    assert encode_image("norm10_2", t).view("<u4").tolist() == [1023, 1023 << 10, (1023 << 20) | (3 << 30)]
    assert encode_image("norm565", t).view("<u2").tolist() == [31, 63 << 5, 31 << 11]


def test_shuffle_round_trip():
    blob = RNG.integers(0, 255, 4096, dtype=np.uint8)
    for element in (1, 2, 4, 16):
        assert np.array_equal(unshuffle_bytes(shuffle_bytes(blob, element), element), blob)


def test_morton_2d_block_layout_matches_the_seed():
    # The seed's DecodeMorton2D_16x16: x = even bits, y = odd bits.
    x, y = layout.morton2d_decode_16(np.arange(256))
    assert (x[:4].tolist(), y[:4].tolist()) == ([0, 1, 0, 1], [0, 0, 1, 1])
    assert len(set(zip(x.tolist(), y.tolist(), strict=True))) == 256
    # 4x4 BC blocks hold 16 consecutive splats
    for start in range(0, 256, 16):
        assert len(set(zip((x[start:start + 16] // 4).tolist(), (y[start:start + 16] // 4).tolist(), strict=True))) == 1


def test_texture_layout_puts_chunk_c_in_block_c():
    w, h = layout.texture_size(300)
    assert (w, h) == (1600, 48)  # 100 blocks x 3 rows: no unused block
    xs, ys = layout.texel_coords(300 * 256, w)
    chunk = np.arange(300 * 256) // 256
    assert np.array_equal(xs // 16 + (ys // 16) * (w // 16), chunk)


def test_morton_3d_codes_interleave_xyz():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], np.float64)
    codes = layout.morton_codes(p, lo=np.zeros(3), hi=np.full(3, 2**21 - 1))
    assert codes.tolist() == [0, 1, 2, 4, 7]
