// Turns the visible count into dispatch sizes for the radix sort and the instanced draw's arguments,
// so the CPU never reads the count back.
layout(local_size_x = 1) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 3) writeonly buffer Dispatch { uint dispatch[8]; };   // (sort groups, 1, 1), (scan groups, 1, 1)
layout(std430, binding = 4) writeonly buffer Draw { uint draw[4]; };          // instanced: 4 vertices, n instances
layout(std430, binding = 5) writeonly buffer DrawTri { uint draw_tri[4]; };   // triangles: 6 n vertices, 1 instance
layout(std430, binding = 6) writeonly buffer DrawPts { uint draw_pts[4]; };   // points: n vertices, 1 instance
// Front-to-back draws in BATCHES batches: per batch an instanced-quad command (4, size, 0, first) and a points
// command (size, 1, first, 0).
layout(std430, binding = 7) writeonly buffer Batches { uint batches[BATCHES * 8u]; };

void main() {
    uint n = count;
    uint groups = (n + TILE - 1u) / TILE;
    uint table = groups * RADIX;
    dispatch[0] = groups; dispatch[1] = 1u; dispatch[2] = 1u;
    dispatch[4] = (table + SCAN_TILE - 1u) / SCAN_TILE; dispatch[5] = 1u; dispatch[6] = 1u;
    draw[0] = 4u; draw[1] = n; draw[2] = 0u; draw[3] = 0u;
    draw_tri[0] = 6u * n; draw_tri[1] = 1u; draw_tri[2] = 0u; draw_tri[3] = 0u;
    draw_pts[0] = n; draw_pts[1] = 1u; draw_pts[2] = 0u; draw_pts[3] = 0u;
    uint size = (n + BATCHES - 1u) / BATCHES;
    for (uint b = 0u; b < BATCHES; ++b) {
        uint first = min(n, b * size);
        uint count = min(size, n - first);
        batches[8u * b + 0u] = 4u; batches[8u * b + 1u] = count; batches[8u * b + 2u] = 0u; batches[8u * b + 3u] = first;
        batches[8u * b + 4u] = count; batches[8u * b + 5u] = 1u; batches[8u * b + 6u] = first; batches[8u * b + 7u] = 0u;
    }
}
