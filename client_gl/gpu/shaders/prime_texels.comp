// One texel written by the GPU into a fresh atlas before any upload: on the NVIDIA driver, the first upload from a
// pixel-unpack buffer into a texture that no shader had written moved the whole texture through host memory
// (bench/probe_gpu_alloc.py; BENCHMARKS.md, "Figures behind library defaults"); after a shader's write, those uploads cost nothing extra.
// TEXEL_FORMAT: an unsigned image format of the texture's texel size (image units match formats by size).
layout(local_size_x = 1) in;

layout(TEXEL_FORMAT, binding = 0) writeonly uniform uimage2D u_texels;

void main() {
    imageStore(u_texels, ivec2(0), uvec4(0u));
}
