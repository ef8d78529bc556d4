// Compute rasterizer, binning step 1: per work group of SCAN_TILE depth-sorted visible splats, the number of
// (tile, splat) entries they emit (gsum[group]), and each splat's own count for bin_emit.
layout(local_size_x = 256) in;

layout(std430, binding = 0) readonly buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) readonly buffer Order { uint order[]; };  // record indices, front to back
#include "bin_common.glsl"
layout(std430, binding = 3) writeonly buffer GroupSums { uint gsum[]; };
layout(std430, binding = 5) writeonly buffer Counts { uint counts[]; };  // entries of each sorted splat, for bin_emit

shared uint s_sum;

void main() {
    uint n = count;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    if (lid == 0u) s_sum = 0u;
    barrier();
    uint sum = 0u;
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = g * SCAN_TILE + i * 256u + lid;
        if (idx < n) {
            uvec2 lo, hi;
            vec2 c;
            vec3 q;
            float op;
            tile_rect(order[idx], lo, hi, c, q, op);
            uint e = row_entries(lo, hi, c, q, op);
            counts[idx] = e;
            sum += e;
        }
    }
    atomicAdd(s_sum, sum);
    barrier();
    if (lid == 0u) gsum[g] = s_sum;
}
