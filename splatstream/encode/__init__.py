"""The encoder: Gaussians -> a scene (manifest + content-addressed payloads), in three steps.

plan.py (scene-wide: formats, SH codebook, LOD tree, camera) -> jobs.py (per tile: payloads and a tile entry,
pure) -> reduce.py (the manifest from the entries). driver.py opens the input and picks the engine: local.py in
memory on this machine's threads, or partitioned.py by partitions (in this process or on Dask, distributed.py).
"""
from .driver import encode_file
from .local import encode_gaussians, encode_in_memory, encode_to
from .options import EncodeOptions

__all__ = ["EncodeOptions", "encode_file", "encode_gaussians", "encode_in_memory", "encode_to"]
