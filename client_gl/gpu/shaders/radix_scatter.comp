// Radix sort pass, step 5 (scatter): stable reorder of keys and values by one 4-bit digit.
// The tile is processed in rounds of 256 keys in index order; a key's rank among equal digits of its round comes
// from per-digit bit masks of the round (one bit per thread, popcounts of the lower threads), so the pass is stable.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) readonly buffer KeysIn { uint keys_in[]; };
layout(std430, binding = 2) readonly buffer ValuesIn { uint values_in[]; };
layout(std430, binding = 3) writeonly buffer KeysOut { uint keys_out[]; };
layout(std430, binding = 4) writeonly buffer ValuesOut { uint values_out[]; };
layout(std430, binding = 5) readonly buffer Table { uint table[]; };

uniform uint u_shift;

shared uint s_mask[RADIX * 8u];
shared uint s_offset[RADIX];

void main() {
    uint n = count;
    uint groups = (n + TILE - 1u) / TILE;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    uint word = lid >> 5;
    uint bit = 1u << (lid & 31u);
    if (lid < RADIX) s_offset[lid] = table[lid * groups + g];
    for (uint i = 0u; i < ITEMS; ++i) {
        if (lid < RADIX * 8u) s_mask[lid] = 0u;
        barrier();
        uint idx = g * TILE + i * 256u + lid;
        bool valid = idx < n;
        uint key = 0u;
        uint digit = 0u;
        if (valid) {
            key = keys_in[idx];
            digit = (key >> u_shift) & (RADIX - 1u);
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
        if (lid < RADIX) {
            uint total = 0u;
            for (uint w = 0u; w < 8u; ++w) total += bitCount(s_mask[lid * 8u + w]);
            s_offset[lid] += total;
        }
        barrier();
    }
}
