// Radix sort pass, step 4 (scan-add): exclusive scan of each block of the sum table plus the block's offset.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 5) buffer Table { uint table[]; };
layout(std430, binding = 6) readonly buffer Reduce { uint reduced[]; };

#include "scan_block.glsl"

void main() {
    uint n = count;
    uint size = ((n + TILE - 1u) / TILE) * RADIX;
    uint lid = gl_LocalInvocationID.x;
    uint start = gl_WorkGroupID.x * SCAN_TILE;
    uint vals[SCAN_ITEMS];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = start + lid * SCAN_ITEMS + i;
        vals[i] = idx < size ? table[idx] : 0u;
    }
    uint total;
    block_exclusive_scan(vals, total);
    uint offset = reduced[gl_WorkGroupID.x];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = start + lid * SCAN_ITEMS + i;
        if (idx < size) table[idx] = vals[i] + offset;
    }
}
