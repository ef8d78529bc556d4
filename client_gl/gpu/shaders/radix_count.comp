// Radix sort pass, step 1 (count): per work group histogram of one 4-bit digit over its tile of keys.
// The sum table is digit-major (table[digit * groups + group]) so one exclusive scan gives scatter offsets.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) readonly buffer KeysIn { uint keys_in[]; };
layout(std430, binding = 5) writeonly buffer Table { uint table[]; };

uniform uint u_shift;

shared uint s_hist[RADIX];

void main() {
    uint n = count;
    uint groups = (n + TILE - 1u) / TILE;
    uint lid = gl_LocalInvocationID.x;
    uint g = gl_WorkGroupID.x;
    if (lid < RADIX) s_hist[lid] = 0u;
    barrier();
    uint start = g * TILE;
    for (uint i = 0u; i < ITEMS; ++i) {
        uint idx = start + i * 256u + lid;
        if (idx < n) atomicAdd(s_hist[(keys_in[idx] >> u_shift) & (RADIX - 1u)], 1u);
    }
    barrier();
    if (lid < RADIX) table[lid * groups + g] = s_hist[lid];
}
