// Compute rasterizer, binning step 1: per work group of SCAN_TILE depth-sorted visible splats, the number of
// (tile, splat) entries they emit (gsum[group]).
layout(local_size_x = 256) in;

layout(std430, binding = 0) readonly buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) readonly buffer Order { uint order[]; };  // record indices, front to back
#include "bin_common.glsl"
layout(std430, binding = 3) writeonly buffer GroupSums { uint gsum[]; };
#ifdef ROW_BINS
layout(std430, binding = 5) writeonly buffer Counts { uint counts[]; };  // entries of each sorted splat, for bin_emit
#endif

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
#if defined(TIGHT_BINS) || defined(ROW_BINS)
            vec2 c;
            vec3 q;
            float op;
            tile_rect(order[idx], lo, hi, c, q, op);
#ifdef ROW_BINS
            uint e = row_entries(lo, hi, c, q, op);
            counts[idx] = e;
            sum += e;
#else
            sum += splat_entries(lo, hi, c, q, op);
#endif
#else
            tile_rect(order[idx], lo, hi);
            sum += rect_tiles(lo, hi);
#endif
        }
    }
    atomicAdd(s_sum, sum);
    barrier();
    if (lid == 0u) gsum[g] = s_sum;
}
