// Radix sort pass PASS, step 5 (scatter): stable reorder of keys and values by the digit at SHIFT, from the buffer
// pair KEYS_IN / VALUES_IN into KEYS_OUT / VALUES_OUT (bindings 1-2 and 3-4, alternating with the pass).
// The tile is processed in rounds of 256 keys in index order; a key's rank among equal digits of its round comes
// from per-digit bit masks of the round (one bit per thread, popcounts of the lower threads), so the pass is stable.
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

shared uint s_mask[RADIX * 8u];
shared uint s_offset[RADIX];

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
    for (uint d = lid; d < RADIX; d += 256u) s_offset[d] = table[d * groups + g];
    for (uint i = 0u; i < ITEMS; ++i) {
        for (uint m = lid; m < RADIX * 8u; m += 256u) s_mask[m] = 0u;
        barrier();
        uint idx = g * TILE + i * 256u + lid;
        bool valid = idx < n;
        uint key = 0u;
        uint digit = 0u;
        if (valid) {
            key = keys_in[idx];
            digit = (key >> SHIFT) & (RADIX - 1u);
            atomicOr(s_mask[digit * 8u + word], bit);
        }
        barrier();
        if (valid) {
            uint rank = bitCount(s_mask[digit * 8u + word] & (bit - 1u));
            for (uint w = 0u; w < word; ++w) rank += bitCount(s_mask[digit * 8u + w]);
            uint dest = s_offset[digit] + rank;
            keys_out[dest] = key;
            values_out[dest] = values_in[idx];
        }
        barrier();
        for (uint d = lid; d < RADIX; d += 256u) {
            uint total = 0u;
            for (uint w = 0u; w < 8u; ++w) total += bitCount(s_mask[d * 8u + w]);
            s_offset[d] += total;
        }
        barrier();
    }
}
