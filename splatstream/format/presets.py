"""Presets (format_spec/format.md 7): the texel format of each attribute, and how a preset is overridden.

A reader never needs a preset: it follows the manifest's `formats`. Encoder, evaluation and the in-memory client
path resolve a preset name here, so they agree on what a preset means.
"""
from __future__ import annotations

from ..errors import UsageError
from .texformats import FORMATS, VALUE_FORMATS, get_format

ATTRIBUTES = ("position", "rotation", "scale", "color", "sh")

# Texel format per attribute. The seed's table (Very High .. Very Low) is the baseline these must beat.
PRESETS: dict[str, dict[str, str]] = {
    "very-high": {"position": "f32x4", "rotation": "f32x4", "scale": "f32x4", "color": "f32x4", "sh": "f32x4"},
    "high": {"position": "f16x4", "rotation": "norm10_2", "scale": "norm11", "color": "f16x4", "sh": "norm11"},
    "medium": {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"},
    # low and very-low keep SH1..SH3 in a scene-wide codebook (PRESET_SH_CODEBOOK; sh is the codebook's format).
    # On fruit_drops low went from 35.2 dB at 19.4 B/splat (BC1 SH, norm11/norm10_2/norm565 for position,
    # rotation, scale) to 35.9 dB at 11.2 B/splat (manifest included): the codebook frees 6 B/splat, part of which
    # buys 8-bit scales (+1.7 dB on fruit); 8-bit positions cost under 0.1 dB there. 8-bit smallest-three
    # rotations would add 2.3 dB on fruit (0.75 on the 1M scene) for 1.2 B/splat more, past 12 B/splat on fruit.
    "low": {"position": "norm8x4", "rotation": "norm565", "scale": "norm8x4", "color": "bc7", "sh": "norm565"},
    # The seed's very-low (BC7 for position, rotation and scale) measured 18 dB on fruit_drops: BC7 scales are
    # the worst of it. Packed 16-bit scales and rotations gave 31 dB at fewer bytes (SH1 in BC1); the codebook
    # keeps all three bands for less.
    "very-low": {"position": "norm8x4", "rotation": "norm565", "scale": "norm565", "color": "bc7", "sh": "norm565"},
}
# Presets whose SH bands go through a scene-wide codebook ("auto": sized from the splat count; see vq.py).
PRESET_SH_CODEBOOK: dict[str, str] = {"low": "auto", "very-low": "auto"}
DEFAULT_PRESET = "medium"
CHUNK_ORDERS = ("auto", "morton", "luminance")


def resolve_formats(preset: str, overrides: dict[str, str] | None = None) -> dict[str, str]:
    """Texel format per attribute of a preset with per-attribute overrides, checked."""
    if preset not in PRESETS:
        raise UsageError(f"unknown preset {preset!r} (choose one of {', '.join(PRESETS)})")
    formats = dict(PRESETS[preset])
    for attr, fmt in (overrides or {}).items():
        if attr not in ATTRIBUTES:
            raise UsageError(f"unknown attribute {attr!r} in a format override (expected one of "
                             f"{', '.join(ATTRIBUTES)})")
        get_format(fmt)
        if fmt not in VALUE_FORMATS:
            raise UsageError(f"{fmt} holds codebook indices, not attribute values (choose one of "
                             f"{', '.join(VALUE_FORMATS)})")
        if attr == "color" and FORMATS[fmt].components < 4:
            raise UsageError(f"color holds SH0 and opacity and needs a 4-component format; {fmt} has 3 "
                             f"(use one of {', '.join(n for n, f in FORMATS.items() if f.components == 4)})")
        formats[attr] = fmt
    return formats


def resolve_chunk_order(chunk_order: str, formats: dict[str, str]) -> str:
    """In-chunk order: luminance groups similar colours into the same 4x4 BC block (on fruit_drops, BC7 colour
    went from 34.1 to 41.1 dB PSNR), but BC-compressed positions need spatially coherent blocks instead."""
    if chunk_order not in CHUNK_ORDERS:
        raise UsageError(f"unknown chunk order {chunk_order!r} (expected one of {', '.join(CHUNK_ORDERS)})")
    if chunk_order != "auto":
        return chunk_order
    bc = {a for a, f in formats.items() if get_format(f).block > 1}
    return "luminance" if bc & {"color", "sh"} and not bc & {"position", "rotation", "scale"} else "morton"
