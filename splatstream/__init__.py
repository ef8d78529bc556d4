"""splatstream: compact, streamable 3D Gaussian Splatting scenes."""
__version__ = "0.1.0"
