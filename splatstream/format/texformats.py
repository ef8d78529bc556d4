"""Texel formats: how normalised values t in [0, 1] become texture bytes, and back (format_spec/format.md).

This module is the one source of truth for texel bit layouts. The numpy decoders here are the reference
the GLSL decoders in client_gl are tested against.

Every encoder takes an image of normalised values, shape (H, W, 4) float32 in [0, 1] (unused channels
may be anything), and returns the texture blob as the GPU takes it (row 0 first; BC formats in 4x4
blocks, row-major block order). Every decoder returns (H, W, 4) float32.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import UsageError

# The largest |x|, |y|, |z| of a unit quaternion in the cube gauge (rotation_canon: of the 24 rotations of a cube
# applied to a splat's axes, the one closest to the identity has |x|, |y|, |z| <= tan(pi/8) w and w >= 0.854).
CUBE_GAUGE_RANGE = math.tan(math.pi / 8)


@dataclass(frozen=True)
class TexelFormat:
    name: str
    bits_per_texel: int
    components: int          # meaningful components (3 or 4)
    levels: tuple[int, ...]  # quantisation levels - 1 per component (0 = float format)
    gl_internal: str         # GL internal format the client creates the texture with
    block: int = 1           # 4 for BC formats (dimensions must be multiples of 4)
    shuffle: int = 0         # byte-shuffle element size applied before zstd (0 = none)
    # Another format whose texel layout (bits, fields1 fields, GL texture) this one shares: a rotation format that
    # differs only in what its values mean (format.md 4.5). "" for a layout of its own.
    same_texels_as: str = ""
    # xyz rotations (format.md 4.5): the components stored, c = (2t - 1) * rotation_range; 1 for [-1, 1].
    rotation_range: float = 1.0

    @property
    def texels(self) -> str:
        """The name of this format's texel layout (its own, or the format it shares its texels with)."""
        return self.same_texels_as or self.name

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
    # Format 1.3: three 9-bit unorm components in a u32 (bits 27-31 zero), the position grid between norm8x4 and
    # norm10_2 (issue 15: on biker a 9-bit grid fits under 0.90 of SOG's bytes at its PSNR).
    TexelFormat("norm9x3", 32, 3, (511, 511, 511), "R32UI", shuffle=4),
    # Format 1.3: 16-bit unorm components, the per-chunk-ranged position format between norm11 and f16x4 (issue 15).
    TexelFormat("norm16x4", 64, 4, (65535, 65535, 65535, 65535), "RGBA16", shuffle=2),
    TexelFormat("norm565", 16, 3, (31, 63, 31), "R16UI", shuffle=2),
    # Format 1.13, rotation only (format.md 4.5): norm565's texels holding x, y, z of a cube-gauge quaternion over
    # [-tan(pi/8), tan(pi/8)], 2.4x finer than norm565's [-1, 1] (issue 32, rotrange32).
    TexelFormat("cube565", 16, 3, (31, 63, 31), "R16UI", shuffle=2, same_texels_as="norm565",
                rotation_range=CUBE_GAUGE_RANGE),
    # Format 1.14, rotation only (format.md 4.5): norm8x4's texels holding x, y, z of a cube-gauge quaternion over
    # [-tan(pi/8), tan(pi/8)] in R, G, B (A written 0, not read), 1.7x finer than smallest three's 8-bit
    # [-0.707, 0.707]; medium-low's where it measures closer to the input than the half turns (issue 32, cube32).
    TexelFormat("cube8x4", 32, 4, (255, 255, 255, 255), "RGBA8", shuffle=4, same_texels_as="norm8x4",
                rotation_range=CUBE_GAUGE_RANGE),
    TexelFormat("bc7", 8, 4, (255, 255, 255, 255), "COMPRESSED_RGBA_BPTC_UNORM", block=4),
    TexelFormat("bc1", 4, 3, (31, 63, 31), "COMPRESSED_RGB_S3TC_DXT1", block=4),
    # Not a value format: a codebook entry index (0..65535) per texel, for the SH codebook's per-splat index.
    TexelFormat("index16", 16, 1, (65535,), "R16UI", shuffle=2),
    # Format 1.6: a palette plane (format.md 4.3.2): four 8-bit indices into the tile's 256-entry palettes of the
    # plane's values, for the log scales and the colour plane (issue 32: SOG inputs hold 256 distinct values).
    TexelFormat("pal8x4", 32, 4, (255, 255, 255, 255), "RGBA8", shuffle=4),
)}
# Texel formats whose texels are palette indices, not normalised values (format.md 4.3.2).
PALETTE_FORMATS = ("pal8x4",)
# Formats an attribute can be quantised to (index16 only holds codebook indices).
VALUE_FORMATS = tuple(name for name in FORMATS if name != "index16")
# Texel formats only the rotation plane may name: their values are quaternion components over a gauge's range.
ROTATION_ONLY_FORMATS = tuple(name for name, f in FORMATS.items() if f.rotation_range != 1.0)


def get_format(name: str) -> TexelFormat:
    try:
        return FORMATS[name]
    except KeyError:
        raise UsageError(f"unknown texel format {name!r} (known: {', '.join(FORMATS)})") from None


def blob_size(fmt: TexelFormat, width: int, height: int, layers: int = 1) -> int:
    return width * height * fmt.bits_per_texel // 8 * layers


def _q(t: np.ndarray, levels: int) -> np.ndarray:
    """Round t in [0, 1] to the nearest of levels + 1 steps (values outside are clamped)."""
    q = t * np.float32(levels)
    q += np.float32(0.5)
    np.clip(q, 0.0, levels, out=q)
    return q.astype(np.uint32)


def _bc_module():
    try:
        import etcpak
        import texture2ddecoder
    except ImportError:
        raise UsageError("BC1/BC7 texel formats need the 'bc' extra: pip install 'splatstream[bc]' "
                         "(etcpak and texture2ddecoder)") from None
    return etcpak, texture2ddecoder


TEXEL_DTYPES = {
    "f32x4": np.dtype(("<f4", 4)), "f16x4": np.dtype(("<f2", 4)), "norm10_2": np.dtype("<u4"),
    "norm11": np.dtype("<u4"), "norm9x3": np.dtype("<u4"), "norm8x4": np.dtype((np.uint8, 4)),
    "norm565": np.dtype("<u2"), "norm16x4": np.dtype(("<u2", 4)), "index16": np.dtype("<u2"),
    "pal8x4": np.dtype((np.uint8, 4)),
}
TEXEL_DTYPES.update({name: TEXEL_DTYPES[f.texels] for name, f in FORMATS.items() if f.same_texels_as})


def pack_texels(fmt_name: str, t: np.ndarray) -> np.ndarray:
    """(M, C) normalised values (C = 3 or 4; a missing 4th channel is 0) -> (M,) texels (non-BC formats)."""
    fmt = get_format(fmt_name)
    if t.shape[1] < 4 and (fmt.components == 4 or fmt.levels[0] == 0):
        t = np.concatenate([t, np.zeros((len(t), 4 - t.shape[1]), np.float32)], axis=1)
    layout = fmt.texels
    if layout == "f32x4":
        return np.ascontiguousarray(t, dtype="<f4")
    if layout == "f16x4":
        return np.clip(t, 0.0, 1.0).astype("<f2")
    if layout == "norm10_2":
        return (_q(t[:, 0], 1023) | (_q(t[:, 1], 1023) << 10) | (_q(t[:, 2], 1023) << 20)
                | (_q(t[:, 3], 3) << 30)).astype("<u4")
    if layout == "norm11":
        return (_q(t[:, 0], 2047) | (_q(t[:, 1], 1023) << 11) | (_q(t[:, 2], 2047) << 21)).astype("<u4")
    if layout == "norm9x3":
        return (_q(t[:, 0], 511) | (_q(t[:, 1], 511) << 9) | (_q(t[:, 2], 511) << 18)).astype("<u4")
    if layout in ("norm8x4", "pal8x4"):
        return _q(t, 255).astype(np.uint8)
    if layout == "norm16x4":
        return _q(t, 65535).astype("<u2")
    if layout == "norm565":
        return (_q(t[:, 0], 31) | (_q(t[:, 1], 63) << 5) | (_q(t[:, 2], 31) << 11)).astype("<u2")
    if layout == "index16":
        return _q(t[:, 0], 65535).astype("<u2")
    raise ValueError(f"{fmt.name} is a block format: use encode_image")


def unpack_texels(fmt_name: str, texels: np.ndarray) -> np.ndarray:
    """(M,) texels (as pack_texels returns them, or raw bytes) -> (M, 4) float32 normalised values."""
    fmt = get_format(fmt_name)
    layout = fmt.texels
    if layout in ("f32x4", "f16x4", "norm8x4", "norm16x4", "pal8x4"):
        raw = np.frombuffer(np.ascontiguousarray(texels), TEXEL_DTYPES[layout].base).reshape(-1, 4)
        if layout in ("norm8x4", "pal8x4"):
            return raw / np.float32(255.0)
        if layout == "norm16x4":
            return raw / np.float32(65535.0)
        return raw.astype(np.float32)
    word = np.frombuffer(np.ascontiguousarray(texels), TEXEL_DTYPES[layout]).astype(np.uint32)
    out = np.zeros((word.size, 4), np.float32)
    if layout == "norm10_2":
        out[:, 0] = (word & 1023) / 1023.0
        out[:, 1] = ((word >> 10) & 1023) / 1023.0
        out[:, 2] = ((word >> 20) & 1023) / 1023.0
        out[:, 3] = (word >> 30) / 3.0
    elif layout == "norm11":
        out[:, 0] = (word & 2047) / 2047.0
        out[:, 1] = ((word >> 11) & 1023) / 1023.0
        out[:, 2] = (word >> 21) / 2047.0
    elif layout == "norm9x3":  # bits 27-31 are zero in a valid texel and ignored here, as in the shader
        out[:, 0] = (word & 511) / 511.0
        out[:, 1] = ((word >> 9) & 511) / 511.0
        out[:, 2] = ((word >> 18) & 511) / 511.0
    elif layout == "norm565":
        out[:, 0] = (word & 31) / 31.0
        out[:, 1] = ((word >> 5) & 63) / 63.0
        out[:, 2] = (word >> 11) / 31.0
    elif layout == "index16":
        out[:, 0] = word / 65535.0
    else:
        raise ValueError(f"{fmt.name} is a block format: use decode_image")
    return out


def encode_image(fmt_name: str, t: np.ndarray) -> np.ndarray:
    """Encode (H, W, 4) normalised values into the texture blob (uint8 array)."""
    fmt = get_format(fmt_name)
    h, w = t.shape[:2]
    if fmt.block == 1:
        return pack_texels(fmt.name, t.reshape(-1, 4)).reshape(-1).view(np.uint8)
    return encode_bc_image(fmt.name, _q(t, 255).astype(np.uint8))


def encode_bc_image(fmt_name: str, rgba: np.ndarray) -> np.ndarray:
    """(H, W, 4) uint8 image -> BC1/BC7 blocks, row-major block order."""
    etcpak, _ = _bc_module()
    h, w = rgba.shape[:2]
    if h % 4 or w % 4:
        raise ValueError(f"{fmt_name}: image {w}x{h} is not a multiple of 4x4 blocks")
    if fmt_name == "bc1":
        rgba = rgba.copy()
        rgba[..., 3] = 255
        return np.frombuffer(etcpak.compress_bc1(np.ascontiguousarray(rgba).tobytes(), w, h), np.uint8)
    return np.frombuffer(etcpak.compress_bc7(np.ascontiguousarray(rgba).tobytes(), w, h, _bc7_params(etcpak)), np.uint8)


def _bc7_params(etcpak):
    # Texels are data, not pictures: linear (not perceptual) channel weights, and alpha (opacity, or the
    # fourth value) weighted double because a wrong opacity shows more than a wrong colour. Uber level 2: the best
    # quality for its encode time on the real scenes (format_spec/format.md, "BC7").
    params = etcpak.BC7CompressBlockParams()
    params.init_linear_weights()
    params.m_weights = [1, 1, 1, 2]
    params.m_uber_level = 2
    return params


def decode_image(fmt_name: str, blob: np.ndarray | bytes, width: int, height: int) -> np.ndarray:
    """Decode a texture blob back into (H, W, 4) float32 normalised values."""
    fmt = get_format(fmt_name)
    raw = np.frombuffer(blob, np.uint8)
    expected = blob_size(fmt, width, height)
    if raw.size != expected:
        raise ValueError(f"{fmt.name}: blob of {raw.size} bytes for {width}x{height} texels, expected {expected}")
    if fmt.block == 1:
        return unpack_texels(fmt.name, raw).reshape(height, width, 4)
    _, t2d = _bc_module()
    decode = t2d.decode_bc1 if fmt.name == "bc1" else t2d.decode_bc7
    bgra = np.frombuffer(decode(raw.tobytes(), width, height), np.uint8).reshape(height, width, 4)
    return bgra[..., [2, 1, 0, 3]] / np.float32(255.0)


def shuffle_bytes(blob: np.ndarray, element: int) -> np.ndarray:
    """Byte-shuffle filter: all first bytes of each element, then all second bytes, ... (zstd likes it)."""
    if element <= 1 or blob.size % element:
        return blob
    return np.ascontiguousarray(blob.reshape(-1, element).T).reshape(-1)


def unshuffle_bytes(blob: np.ndarray, element: int) -> np.ndarray:
    if element <= 1 or blob.size % element:
        return blob
    return np.ascontiguousarray(blob.reshape(element, -1).T).reshape(-1)
