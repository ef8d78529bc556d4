"""Writers for foreign splat formats (SPZ, glTF/GLB with KHR_gaussian_splatting).

The .ply and .splat writers live beside their readers (splatstream/ply.py, splatstream/readers/splat.py).
Each writer here has a pure function Gaussians -> bytes (usable per tile by other exporters) and a
`write_*` wrapper that writes a file atomically. Layouts: format_spec/foreign_formats.md.
"""
