// Radix sort pass PASS, step 1 (count): per work group histogram of the RADIX_BITS-bit digit at SHIFT over its tile
// of keys. The sum table is digit-major (table[digit * groups + group]) so one exclusive scan gives scatter offsets.
// Passes alternate between the two buffer pairs: even passes read bindings 1-2, odd passes 3-4 (KEYS_IN).
// FUSED: the work group also adds its counts to the block sums of the table (reduced[PASS * blocks + block], zero
// before the pass), so no separate reduce step runs.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = KEYS_IN) readonly buffer KeysIn { uint keys_in[]; };
layout(std430, binding = 5) writeonly buffer Table { uint table[]; };
#ifdef FUSED
layout(std430, binding = 6) buffer Reduce { uint reduced[]; };
#endif

shared uint s_hist[RADIX];

void main() {
    uint n = count;
    uint groups = (n + TILE - 1u) / TILE;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    for (uint d = lid; d < RADIX; d += 256u) s_hist[d] = 0u;
    barrier();
    uint start = g * TILE;
    for (uint i = 0u; i < ITEMS; ++i) {
        uint idx = start + i * 256u + lid;
        if (idx < n) atomicAdd(s_hist[(keys_in[idx] >> SHIFT) & (RADIX - 1u)], 1u);
    }
    barrier();
#ifdef FUSED
    uint base = PASS * ((groups * RADIX + SCAN_TILE - 1u) / SCAN_TILE);
#endif
    for (uint d = lid; d < RADIX; d += 256u) {
        uint c = s_hist[d];
        uint t = d * groups + g;
        table[t] = c;
#ifdef FUSED
        if (c != 0u) atomicAdd(reduced[base + t / SCAN_TILE], c);
#endif
    }
}
