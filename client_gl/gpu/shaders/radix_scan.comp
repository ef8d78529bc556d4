// Radix sort pass, step 3 (scan): one work group turns the block sums into exclusive block offsets.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 6) buffer Reduce { uint reduced[]; };

#include "scan_block.glsl"

void main() {
    uint n = count;
    uint size = ((((n + TILE - 1u) / TILE) * RADIX) + SCAN_TILE - 1u) / SCAN_TILE;
    uint lid = gl_LocalInvocationID.x;
    uint vals[SCAN_ITEMS];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = lid * SCAN_ITEMS + i;
        vals[i] = idx < size ? reduced[idx] : 0u;
    }
    uint total;
    block_exclusive_scan(vals, total);
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = lid * SCAN_ITEMS + i;
        if (idx < size) reduced[idx] = vals[i];
    }
}
