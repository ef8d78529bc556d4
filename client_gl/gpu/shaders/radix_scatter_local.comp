// Radix sort pass PASS, step 5 (scatter), reordering the tile locally first: the work group ranks its tile's keys
// by the digit at SHIFT (stable: the tile's digit counts, read off the scanned table, give each digit's run, and
// per-digit bit masks of each 256-key round give a key's rank among equal digits of its round), places them in that
// order in shared memory, and then writes them out in it: consecutive threads write consecutive addresses of one
// digit's run, where threads writing each key straight to its place would write up to RADIX runs per round (wide
// digits then scatter single words; measured slower, BENCHMARKS.md).
// Keys first, then values through the same shared array (a tile's keys and values would not fit 32 KB together).
// FUSED: work group 0 zeroes this pass's block sums again (reduced is all zero between sorts).
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = KEYS_IN) readonly buffer KeysIn { uint keys_in[]; };
layout(std430, binding = VALUES_IN) readonly buffer ValuesIn { uint values_in[]; };
layout(std430, binding = KEYS_OUT) writeonly buffer KeysOut { uint keys_out[]; };
layout(std430, binding = VALUES_OUT) writeonly buffer ValuesOut { uint values_out[]; };
layout(std430, binding = 5) readonly buffer Table { uint table[]; };
#ifdef FUSED
layout(std430, binding = 6) writeonly buffer Reduce { uint reduced[]; };
#endif

shared uint s_tile[TILE];     // the tile in digit order: keys, then values
shared uint s_mask[RADIX * 8u];
shared uint s_start[RADIX];   // the digit's run in the reordered tile: first position
shared uint s_run[RADIX];     // the digit's keys placed by the rounds before
shared uint s_dest[RADIX];    // output position of the digit's run, less s_start (mod 2^32)

void main() {
    uint n = count;
    uint groups = (n + TILE - 1u) / TILE;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    uint word = lid >> 5;
    uint bit = 1u << (lid & 31u);
#ifdef FUSED
    if (g == 0u) {
        uint blocks = (groups * RADIX + SCAN_TILE - 1u) / SCAN_TILE;
        for (uint i = lid; i < blocks; i += 256u) reduced[PASS * blocks + i] = 0u;
    }
#endif
    uint start = g * TILE;
    uint tile_n = min(TILE, n - start);
    for (uint m = lid; m < RADIX * 8u; m += 256u) s_mask[m] = 0u;
    uint keys[ITEMS];
    for (uint i = 0u; i < ITEMS; ++i) {
        uint idx = i * 256u + lid;
        keys[i] = idx < tile_n ? keys_in[start + idx] : 0u;
    }
    // The tile's count of the digit: the scanned table is one exclusive scan in digit-major order, so it is the
    // distance to the next entry (the last entry's: to n). Then an exclusive scan over the digits (Hillis-Steele over
    // the first RADIX threads; RADIX <= 256).
    uint own = 0u;
    uint dest0 = 0u;
    if (lid < RADIX) {
        uint t = lid * groups + g;
        dest0 = table[t];
        own = (t + 1u < groups * RADIX ? table[t + 1u] : n) - dest0;
        s_start[lid] = own;
    }
    barrier();
    for (uint off = 1u; off < RADIX; off <<= 1) {
        uint add = (lid < RADIX && lid >= off) ? s_start[lid - off] : 0u;
        barrier();
        if (lid < RADIX) s_start[lid] += add;
        barrier();
    }
    if (lid < RADIX) {
        uint first = s_start[lid] - own;
        s_start[lid] = first;
        s_dest[lid] = dest0 - first;
        s_run[lid] = 0u;
    }
    barrier();
    uint pos[ITEMS];
    for (uint i = 0u; i < ITEMS; ++i) {
        uint idx = i * 256u + lid;
        bool valid = idx < tile_n;
        uint digit = (keys[i] >> SHIFT) & (RADIX - 1u);
        if (valid) atomicOr(s_mask[digit * 8u + word], bit);
        barrier();
        // The key's rank among its digit's keys of the round, and their number; the digit's last key of the round
        // advances the digit's run and every key clears its own mask word, so a round costs the same at any RADIX.
        uint rank = 0u;
        uint total = 0u;
        pos[i] = 0u;
        if (valid) {
            for (uint w = 0u; w < 8u; ++w) {
                uint m = s_mask[digit * 8u + w];
                if (w < word) rank += bitCount(m);
                if (w == word) rank += bitCount(m & (bit - 1u));
                total += bitCount(m);
            }
            pos[i] = s_start[digit] + s_run[digit] + rank;
        }
        barrier();
        if (valid) {
            s_mask[digit * 8u + word] = 0u;
            if (rank + 1u == total) s_run[digit] += total;
        }
        barrier();
    }
    for (uint i = 0u; i < ITEMS; ++i) {
        if (i * 256u + lid < tile_n) s_tile[pos[i]] = keys[i];
    }
    barrier();
    uint dest[ITEMS];
    for (uint i = 0u; i < ITEMS; ++i) {
        uint j = i * 256u + lid;
        dest[i] = 0u;
        if (j < tile_n) {
            uint key = s_tile[j];
            dest[i] = s_dest[(key >> SHIFT) & (RADIX - 1u)] + j;
            keys_out[dest[i]] = key;
        }
    }
    barrier();
    for (uint i = 0u; i < ITEMS; ++i) {
        uint idx = i * 256u + lid;
        if (idx < tile_n) s_tile[pos[i]] = values_in[start + idx];
    }
    barrier();
    for (uint i = 0u; i < ITEMS; ++i) {
        if (i * 256u + lid < tile_n) values_out[dest[i]] = s_tile[i * 256u + lid];
    }
}
