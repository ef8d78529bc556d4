// Compute rasterizer, binning step 2 (one work group): exclusive scan of the group sums in place (entry offset of
// each group), the entry total (bins.total; bins.entries = min(total, capacity): what the tile sort sorts; total >
// capacity is an overflow the host checks between frames), zeroed tile ranges, and the tile sort's indirect
// dispatch sizes (as indirect_setup.comp writes them, for the tile sort's digit width RADIX).
layout(local_size_x = 256) in;

layout(std430, binding = 0) readonly buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) writeonly buffer SortDispatch { uint sort_dispatch[8]; };
layout(std430, binding = 3) buffer GroupSums { uint gsum[]; };
layout(std430, binding = 4) buffer Bins { uint entries; uint total; uint pad2[2]; };
layout(std430, binding = 5) writeonly buffer Ranges { uvec2 ranges[]; };

uniform uint u_capacity;
uniform uint u_tiles;

#include "scan_block.glsl"

void main() {
    uint lid = gl_LocalInvocationID.x;
    uint groups = (count + SCAN_TILE - 1u) / SCAN_TILE;
    uint carry = 0u;
    for (uint base = 0u; base < groups; base += SCAN_TILE) {
        uint vals[SCAN_ITEMS];
        for (uint i = 0u; i < SCAN_ITEMS; ++i) {
            uint k = base + lid * SCAN_ITEMS + i;
            vals[i] = k < groups ? gsum[k] : 0u;
        }
        uint tot;
        block_exclusive_scan(vals, tot);
        for (uint i = 0u; i < SCAN_ITEMS; ++i) {
            uint k = base + lid * SCAN_ITEMS + i;
            if (k < groups) gsum[k] = vals[i] + carry;
        }
        carry += tot;
    }
    for (uint t = lid; t < u_tiles; t += 256u) ranges[t] = uvec2(0u);
    if (lid == 0u) {
        uint m = min(carry, u_capacity);
        total = carry;
        entries = m;
        uint groups = (m + TILE - 1u) / TILE;
        sort_dispatch[0] = groups; sort_dispatch[1] = 1u; sort_dispatch[2] = 1u;
        sort_dispatch[4] = (groups * RADIX + SCAN_TILE - 1u) / SCAN_TILE; sort_dispatch[5] = 1u; sort_dispatch[6] = 1u;
    }
}
