// Compute rasterizer, binning step 3: every depth-sorted visible splat writes one (tile id, record index) entry per
// tile it touches at its exclusive-scan offset, so entries are ordered by (depth, tile); a stable sort by tile id
// then leaves each tile's splats front to back. Entries past the capacity are dropped (bins.total tells).
// After the block's scan the work group writes its entries together, thread t the entries t, t + 256, ... of the
// group's run (each finds its splat by a binary search of the offsets in shared memory): every thread writes as
// many entries, and neighbouring threads neighbouring words, where one thread a splat would leave a warp waiting on
// its largest splat's tiles. A splat whose box is at most two tiles high (bin_common.glsl's row_binned) has, row by
// row, the tiles row_tiles keeps (those whose pixel centres its alpha >= 1/255 ellipse reaches, found per row in
// closed form); a taller one its whole box. Why these and not the alternatives measured: BENCHMARKS.md (issue 20).
layout(local_size_x = 256) in;

layout(std430, binding = 0) readonly buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) readonly buffer Order { uint order[]; };
#include "bin_common.glsl"
layout(std430, binding = 3) readonly buffer GroupSums { uint gsum[]; };
layout(std430, binding = 6) writeonly buffer TileKeys { uint tile_keys[]; };
layout(std430, binding = 7) writeonly buffer TileValues { uint tile_values[]; };
layout(std430, binding = 5) readonly buffer Counts { uint counts[]; };  // bin_count's entries of each sorted splat

uniform uint u_capacity;

#include "scan_block.glsl"

shared uint s_off[SCAN_TILE];  // exclusive entry offset of each splat of the group, in depth order
shared uint s_lo[SCAN_TILE];   // its tile box's first tile, x | y << 16
shared uint s_w[SCAN_TILE];    // its packed row spans, or (a taller box) its width | 1 << 31

void main() {
    uint n = count;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    uint vals[SCAN_ITEMS];
    uvec2 los[SCAN_ITEMS];  // (first tile x | y << 16, row spans or box width)
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = g * SCAN_TILE + lid * SCAN_ITEMS + i;
        vals[i] = 0u;
        los[i] = uvec2(0u);
        // bin_count's counts (what its group sums add up); a row-binned splat's rows kept as (lo.x | lo.y << 16,
        // first row's [x0, x1) | second row's << 16, 8 bits each from lo.x); a taller box as
        // (lo.x | lo.y << 16, width | 1 << 31).
        if (idx < n) {
            vals[i] = counts[idx];
            uvec2 lo, hi;
            vec2 c;
            vec3 q;
            float op;
            tile_rect(order[idx], lo, hi, c, q, op);
            los[i] = uvec2(lo.x | (lo.y << 16), (hi.x - lo.x) | 0x80000000u);
            if (row_binned(lo, hi)) {
                uvec4 r = row_spans(lo, hi, c, q, op) - lo.x;
                los[i].y = r.x | (r.y << 8) | (r.z << 16) | (r.w << 24);
            }
        }
    }
    uint tot;
    block_exclusive_scan(vals, tot);
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint k = lid * SCAN_ITEMS + i;
        s_off[k] = vals[i];
        s_lo[k] = los[i].x;
        s_w[k] = los[i].y;
    }
    barrier();
    uint base = gsum[g];
    for (uint o = lid; o < tot; o += 256u) {
        uint a = 0u, b = SCAN_TILE;  // the last splat whose offset is at most o (it has entries: the next starts later)
        while (a < b) {
            uint m = (a + b) >> 1;
            if (s_off[m] <= o) a = m + 1u; else b = m;
        }
        uint k = a - 1u;
        uint t = o - s_off[k];
        uint r = order[g * SCAN_TILE + k];
        uint lo0 = s_lo[k];
        uint rows = s_w[k];
        uint x, y;
        if ((rows & 0x80000000u) != 0u) {  // a taller box: all of it
            uint w = rows & 0x7FFFFFFFu;
            x = (lo0 & 0xFFFFu) + t % w;
            y = (lo0 >> 16) + t / w;
        } else {
            uint w0 = ((rows >> 8) & 0xFFu) - (rows & 0xFFu);
            if (t < w0) {
                x = (lo0 & 0xFFFFu) + (rows & 0xFFu) + t;
                y = lo0 >> 16;
            } else {
                x = (lo0 & 0xFFFFu) + ((rows >> 16) & 0xFFu) + t - w0;
                y = (lo0 >> 16) + 1u;
            }
        }
        if (base + o < u_capacity) {
            tile_keys[base + o] = y * u_grid.x + x;
            tile_values[base + o] = r;
        }
    }
}
