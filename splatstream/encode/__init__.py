"""The encoder: Gaussians -> a scene (manifest + content-addressed payloads), in three steps.

plan.py (scene-wide: formats, SH codebook, LOD tree, camera) -> jobs.py (per tile: payloads and a tile entry,
pure) -> reduce.py (the manifest from the entries). local.py runs them on this machine's threads.
"""
from .local import encode_file, encode_gaussians, encode_in_memory, encode_to
from .options import EncodeOptions

__all__ = ["EncodeOptions", "encode_file", "encode_gaussians", "encode_in_memory", "encode_to"]
