// Compute rasterizer, binning step 3: every depth-sorted visible splat writes one (tile id, record index) entry per
// tile it touches at its exclusive-scan offset, so entries are ordered by (depth, tile); a stable sort by tile id
// then leaves each tile's splats front to back. Entries past the capacity are dropped (bins.total tells).
layout(local_size_x = 256) in;

layout(std430, binding = 0) readonly buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) readonly buffer Order { uint order[]; };
#include "bin_common.glsl"
layout(std430, binding = 3) readonly buffer GroupSums { uint gsum[]; };
layout(std430, binding = 6) writeonly buffer TileKeys { uint tile_keys[]; };
layout(std430, binding = 7) writeonly buffer TileValues { uint tile_values[]; };

uniform uint u_capacity;

#include "scan_block.glsl"

void main() {
    uint n = count;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    uint vals[SCAN_ITEMS];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = g * SCAN_TILE + lid * SCAN_ITEMS + i;
        vals[i] = 0u;
        if (idx < n) {
            uvec2 lo, hi;
            tile_rect(order[idx], lo, hi);
            vals[i] = rect_tiles(lo, hi);
        }
    }
    uint tot;
    block_exclusive_scan(vals, tot);
    uint base = gsum[g];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = g * SCAN_TILE + lid * SCAN_ITEMS + i;
        if (idx >= n) break;
        uint r = order[idx];
        uvec2 lo, hi;
        tile_rect(r, lo, hi);
        uint o = base + vals[i];
        for (uint y = lo.y; y < hi.y; ++y) {
            for (uint x = lo.x; x < hi.x; ++x) {
                if (o < u_capacity) {
                    tile_keys[o] = y * u_grid.x + x;
                    tile_values[o] = r;
                }
                ++o;
            }
        }
    }
}
