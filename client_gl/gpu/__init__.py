"""The GL layer of the client: residency (pool, slots, residency_layout), shaders (shadergen, shaders/), sorting
(sort), drawing (renderer, compute_raster) and the raw GL calls moderngl lacks (gl).

Importing this package imports no GL; `slots` and `residency_layout` are pure and need no context.
"""
