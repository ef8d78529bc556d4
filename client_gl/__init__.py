"""GPU renderer for splatstream scenes (moderngl; headless through EGL).

Splat data stays on the GPU in the encoded texel formats (client_gl.pool) and is decoded in the shaders
(client_gl.shadergen); culling, depth keys and a radix sort run in compute shaders (client_gl.sort), and one
instanced draw blends the splats back to front (client_gl.renderer). client_gl.headless renders images offscreen.
"""
