// Radix sort pass, step 2 (reduce): sum of each SCAN_TILE block of the sum table.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 5) readonly buffer Table { uint table[]; };
layout(std430, binding = 6) writeonly buffer Reduce { uint reduced[]; };

shared uint s_sum[256];

void main() {
    uint n = count;
    uint size = ((n + TILE - 1u) / TILE) * RADIX;
    uint lid = gl_LocalInvocationID.x;
    uint start = gl_WorkGroupID.x * SCAN_TILE;
    uint sum = 0u;
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint idx = start + i * 256u + lid;
        if (idx < size) sum += table[idx];
    }
    s_sum[lid] = sum;
    barrier();
    for (uint s = 128u; s > 0u; s >>= 1) {
        if (lid < s) s_sum[lid] += s_sum[lid + s];
        barrier();
    }
    if (lid == 0u) reduced[gl_WorkGroupID.x] = s_sum[0];
}
