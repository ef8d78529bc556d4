// Compute rasterizer: [start, end) of each tile's run in the tile-sorted entries (boundary detection).
layout(local_size_x = 256) in;

layout(std430, binding = 4) readonly buffer Bins { uint entries; uint total; uint pad2[2]; };
layout(std430, binding = 5) buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 6) readonly buffer TileKeys { uint tile_keys[]; };

void main() {
    uint m = entries;
    for (uint i = 0u; i < ITEMS; ++i) {
        uint idx = gl_WorkGroupID.x * TILE + i * 256u + gl_LocalInvocationID.x;
        if (idx >= m) return;
        uint t = tile_keys[idx];
        if (idx == 0u || tile_keys[idx - 1u] != t) ranges[t].x = idx;
        if (idx + 1u == m || tile_keys[idx + 1u] != t) ranges[t].y = idx + 1u;
    }
}
