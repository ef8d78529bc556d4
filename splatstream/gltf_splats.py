"""The names of the KHR_gaussian_splatting glTF extension that the glTF reader (readers/gltf.py) and the GLB writer
(writers/glb.py) share, so that neither imports the other (format_spec/foreign_formats.md)."""
from __future__ import annotations

from .gaussians import SH_BAND_COEFFS

EXTENSION = "KHR_gaussian_splatting"
SPZ_EXTENSION = "KHR_gaussian_splatting_compression_spz_2"
PREFIX = "KHR_gaussian_splatting:"


def sh_attribute_names(degree: int) -> list[str]:
    """KHR_gaussian_splatting SH attribute names of bands 1..degree, in the order of our sh_rest rows."""
    return [f"{PREFIX}SH_DEGREE_{band}_COEF_{n}" for band in range(1, degree + 1)
            for n in range(SH_BAND_COEFFS[band])]
