// Compute rasterizer, binning step 3: every depth-sorted visible splat writes one (tile id, record index) entry per
// tile it touches at its exclusive-scan offset, so entries are ordered by (depth, tile); a stable sort by tile id
// then leaves each tile's splats front to back. Entries past the capacity are dropped (bins.total tells).
// TIGHT_BINS: only the tiles of the box that tile_hit keeps (bin_count.comp counts them with the same code).
// EMIT_RECTS: the tile boxes of the first pass are kept (packed 16-bit corners) instead of read and computed again.
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
#ifdef EMIT_RECTS
    uvec2 rects[SCAN_ITEMS];  // (lo.x | lo.y << 16, hi.x | hi.y << 16)
#endif
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = g * SCAN_TILE + lid * SCAN_ITEMS + i;
        vals[i] = 0u;
#ifdef EMIT_RECTS
        rects[i] = uvec2(0u);
#endif
        if (idx < n) {
            uvec2 lo, hi;
            vec2 c;
            vec3 q;
            float op;
            tile_rect(order[idx], lo, hi, c, q, op);
#ifdef TIGHT_BINS
            vals[i] = splat_entries(lo, hi, c, q, op);
#else
            vals[i] = rect_tiles(lo, hi);
#endif
#ifdef EMIT_RECTS
            rects[i] = uvec2(lo.x | (lo.y << 16), hi.x | (hi.y << 16));
#endif
        }
    }
#ifdef TIGHT_BINS
    uint counts[SCAN_ITEMS];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) counts[i] = vals[i];
#endif
    uint tot;
    block_exclusive_scan(vals, tot);
    uint base = gsum[g];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = g * SCAN_TILE + lid * SCAN_ITEMS + i;
        if (idx >= n) break;
        uint r = order[idx];
        uvec2 lo, hi;
        vec2 c;
        vec3 q;
        float op;
#ifdef EMIT_RECTS
        lo = uvec2(rects[i].x & 0xFFFFu, rects[i].x >> 16);
        hi = uvec2(rects[i].y & 0xFFFFu, rects[i].y >> 16);
#ifdef TIGHT_BINS
        tile_rect(r, lo, hi, c, q, op);
#endif
#else
        tile_rect(r, lo, hi, c, q, op);
#endif
        uint o = base + vals[i];
#ifdef TIGHT_BINS
        uint end = o + counts[i];  // never past this splat's own entries, whatever the second evaluation says
#endif
        for (uint y = lo.y; y < hi.y; ++y) {
            for (uint x = lo.x; x < hi.x; ++x) {
#ifdef TIGHT_BINS
                if (!tile_hit(uvec2(x, y), c, q, op) || o >= end) continue;
#endif
                if (o < u_capacity) {
                    tile_keys[o] = y * u_grid.x + x;
                    tile_values[o] = r;
                }
                ++o;
            }
        }
    }
}
