"""Texel formats: how normalised values t in [0, 1] become texture bytes, and back (format_spec/format.md).

This module is the one source of truth for texel bit layouts. The numpy decoders here are the reference
the GLSL decoders in client_gl are tested against.

Every encoder takes an image of normalised values, shape (H, W, 4) float32 in [0, 1] (unused channels
may be anything), and returns the texture blob as the GPU takes it (row 0 first; BC formats in 4x4
blocks, row-major block order). Every decoder returns (H, W, 4) float32.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import UsageError


@dataclass(frozen=True)
class TexelFormat:
    name: str
    bits_per_texel: int
    components: int          # meaningful components (3 or 4)
    levels: tuple[int, ...]  # quantisation levels - 1 per component (0 = float format)
    gl_internal: str         # GL internal format the client creates the texture with
    block: int = 1           # 4 for BC formats (dimensions must be multiples of 4)
    shuffle: int = 0         # byte-shuffle element size applied before zstd (0 = none)

    @property
    def bytes_per_texel(self) -> float:
        return self.bits_per_texel / 8

    def step(self, component: int) -> float:
        """Quantisation step in t units (for float formats: the spacing near t = 1)."""
        if self.name == "f32x4":
            return 2.0 ** -24
        if self.name == "f16x4":
            return 2.0 ** -11
        if self.block > 1:
            return 1.0 / 255
        return 1.0 / self.levels[component]


FORMATS: dict[str, TexelFormat] = {f.name: f for f in (
    TexelFormat("f32x4", 128, 4, (0, 0, 0, 0), "RGBA32F", shuffle=4),
    TexelFormat("f16x4", 64, 4, (0, 0, 0, 0), "RGBA16F", shuffle=2),
    TexelFormat("norm10_2", 32, 4, (1023, 1023, 1023, 3), "RGB10_A2", shuffle=4),
    TexelFormat("norm11", 32, 3, (2047, 1023, 2047), "R32UI", shuffle=4),
    TexelFormat("norm8x4", 32, 4, (255, 255, 255, 255), "RGBA8", shuffle=4),
    TexelFormat("norm565", 16, 3, (31, 63, 31), "R16UI", shuffle=2),
    TexelFormat("bc7", 8, 4, (255, 255, 255, 255), "COMPRESSED_RGBA_BPTC_UNORM", block=4),
    TexelFormat("bc1", 4, 3, (31, 63, 31), "COMPRESSED_RGB_S3TC_DXT1", block=4),
)}


def get_format(name: str) -> TexelFormat:
    try:
        return FORMATS[name]
    except KeyError:
        raise UsageError(f"unknown texel format {name!r} (known: {', '.join(FORMATS)})") from None


def blob_size(fmt: TexelFormat, width: int, height: int, layers: int = 1) -> int:
    return width * height * fmt.bits_per_texel // 8 * layers


def _q(t: np.ndarray, levels: int) -> np.ndarray:
    return np.rint(np.clip(t, 0.0, 1.0) * levels).astype(np.uint32)


def _bc_module():
    try:
        import etcpak
        import texture2ddecoder
    except ImportError:
        raise UsageError("BC1/BC7 texel formats need the 'bc' extra: pip install 'splatstream[bc]' "
                         "(etcpak and texture2ddecoder)") from None
    return etcpak, texture2ddecoder


def encode_image(fmt_name: str, t: np.ndarray) -> np.ndarray:
    """Encode (H, W, 4) normalised values into the texture blob (uint8 array)."""
    fmt = get_format(fmt_name)
    h, w = t.shape[:2]
    if fmt.name == "f32x4":
        return np.ascontiguousarray(t, dtype="<f4").reshape(-1).view(np.uint8)
    if fmt.name == "f16x4":
        return np.ascontiguousarray(np.clip(t, 0.0, 1.0), dtype="<f2").reshape(-1).view(np.uint8)
    if fmt.name == "norm10_2":
        word = _q(t[..., 0], 1023) | (_q(t[..., 1], 1023) << 10) | (_q(t[..., 2], 1023) << 20) | (_q(t[..., 3], 3) << 30)
        return word.astype("<u4").reshape(-1).view(np.uint8)
    if fmt.name == "norm11":
        word = _q(t[..., 0], 2047) | (_q(t[..., 1], 1023) << 11) | (_q(t[..., 2], 2047) << 21)
        return word.astype("<u4").reshape(-1).view(np.uint8)
    if fmt.name == "norm8x4":
        return _q(t, 255).astype(np.uint8).reshape(-1)
    if fmt.name == "norm565":
        word = _q(t[..., 0], 31) | (_q(t[..., 1], 63) << 5) | (_q(t[..., 2], 31) << 11)
        return word.astype("<u2").reshape(-1).view(np.uint8)
    etcpak, _ = _bc_module()
    if h % 4 or w % 4:
        raise ValueError(f"{fmt.name}: image {w}x{h} is not a multiple of 4x4 blocks")
    rgba = _q(t, 255).astype(np.uint8)
    if fmt.name == "bc1":
        rgba[..., 3] = 255
        return np.frombuffer(etcpak.compress_bc1(np.ascontiguousarray(rgba).tobytes(), w, h), np.uint8)
    return np.frombuffer(etcpak.compress_bc7(np.ascontiguousarray(rgba).tobytes(), w, h), np.uint8)


def decode_image(fmt_name: str, blob: np.ndarray | bytes, width: int, height: int) -> np.ndarray:
    """Decode a texture blob back into (H, W, 4) float32 normalised values."""
    fmt = get_format(fmt_name)
    raw = np.frombuffer(blob, np.uint8)
    expected = blob_size(fmt, width, height)
    if raw.size != expected:
        raise ValueError(f"{fmt.name}: blob of {raw.size} bytes for {width}x{height} texels, expected {expected}")
    out = np.zeros((height, width, 4), np.float32)
    if fmt.name == "f32x4":
        return raw.view("<f4").reshape(height, width, 4).astype(np.float32)
    if fmt.name == "f16x4":
        return raw.view("<f2").reshape(height, width, 4).astype(np.float32)
    if fmt.name == "norm10_2":
        word = raw.view("<u4").reshape(height, width)
        out[..., 0] = (word & 1023) / 1023.0
        out[..., 1] = ((word >> 10) & 1023) / 1023.0
        out[..., 2] = ((word >> 20) & 1023) / 1023.0
        out[..., 3] = (word >> 30) / 3.0
        return out
    if fmt.name == "norm11":
        word = raw.view("<u4").reshape(height, width)
        out[..., 0] = (word & 2047) / 2047.0
        out[..., 1] = ((word >> 11) & 1023) / 1023.0
        out[..., 2] = (word >> 21) / 2047.0
        return out
    if fmt.name == "norm8x4":
        return raw.reshape(height, width, 4) / np.float32(255.0)
    if fmt.name == "norm565":
        word = raw.view("<u2").reshape(height, width).astype(np.uint32)
        out[..., 0] = (word & 31) / 31.0
        out[..., 1] = ((word >> 5) & 63) / 63.0
        out[..., 2] = (word >> 11) / 31.0
        return out
    _, t2d = _bc_module()
    decode = t2d.decode_bc1 if fmt.name == "bc1" else t2d.decode_bc7
    bgra = np.frombuffer(decode(raw.tobytes(), width, height), np.uint8).reshape(height, width, 4)
    out[..., :] = bgra[..., [2, 1, 0, 3]] / np.float32(255.0)
    return out


def shuffle_bytes(blob: np.ndarray, element: int) -> np.ndarray:
    """Byte-shuffle filter: all first bytes of each element, then all second bytes, ... (zstd likes it)."""
    if element <= 1 or blob.size % element:
        return blob
    return np.ascontiguousarray(blob.reshape(-1, element).T).reshape(-1)


def unshuffle_bytes(blob: np.ndarray, element: int) -> np.ndarray:
    if element <= 1 or blob.size % element:
        return blob
    return np.ascontiguousarray(blob.reshape(element, -1).T).reshape(-1)
