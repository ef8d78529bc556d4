// Radix sort pass PASS, step 4 (scan-add): exclusive scan of each block of the sum table plus the block's offset.
// The offset is reduced[block] (scanned by radix_scan.comp), or, FUSED, the sum of the block sums before this block
// (reduced[PASS * blocks + 0 .. block), added by radix_count.comp), summed here by each work group.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 5) buffer Table { uint table[]; };
layout(std430, binding = 6) readonly buffer Reduce { uint reduced[]; };

#include "scan_block.glsl"

#ifdef FUSED
shared uint s_part[256];
#endif

void main() {
    uint n = count;
    uint size = ((n + TILE - 1u) / TILE) * RADIX;
    uint lid = gl_LocalInvocationID.x;
    uint b = gl_WorkGroupID.x;
    uint start = b * SCAN_TILE;
    uint vals[SCAN_ITEMS];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = start + lid * SCAN_ITEMS + i;
        vals[i] = idx < size ? table[idx] : 0u;
    }
    uint total;
    block_exclusive_scan(vals, total);
#ifdef FUSED
    uint base = PASS * ((size + SCAN_TILE - 1u) / SCAN_TILE);
    uint part = 0u;
    for (uint i = lid; i < b; i += 256u) part += reduced[base + i];
    s_part[lid] = part;
    barrier();
    for (uint s = 128u; s > 0u; s >>= 1) {
        if (lid < s) s_part[lid] += s_part[lid + s];
        barrier();
    }
    uint offset = s_part[0];
#else
    uint offset = reduced[b];
#endif
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = start + lid * SCAN_ITEMS + i;
        if (idx < size) table[idx] = vals[i] + offset;
    }
}
