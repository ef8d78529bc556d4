"""GPU client for splatstream scenes (moderngl; headless through EGL).

Importing the package imports no GL: `client_gl.tiledata` (what decoding hands to the pool) and the streaming
engine (`client_gl.stream`) run without moderngl. The GL layer lives in `client_gl.gpu`: splat data stays on the GPU
in the encoded texel formats (gpu.pool: atlases of fixed slots, tiles join and leave, SH bands come later) and is
decoded in the shaders (gpu.shadergen); culling, depth keys and a radix sort run in compute shaders (gpu.sort), and
one draw blends the splats (gpu.renderer). `client_gl.scene` reads tiles from a scene store; `client_gl.offscreen`
renders images offscreen.
"""
