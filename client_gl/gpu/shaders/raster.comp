// Compute rasterizer: one work group per tile (TILE_PX x TILE_PX pixels, 16), one thread per pixel. The
// tile's splats (front to back) are loaded in batches of BATCH (one per thread) into shared memory; per pixel, as the
// reference rasterizer (render_ref / forward.cu):
// power = -0.5 (a dx^2 + c dy^2) - b dx dy, skipped if > 0; alpha = min(0.99, opacity exp(power)), skipped if
// < 1/255; the pixel stops (this splat excluded) once T (1 - alpha) < 1e-4; C += rgb alpha T; T *= 1 - alpha.
// Output (C + T background, 1 - T), row 0 of the image at the bottom of the texture (GL convention).
// Most (pixel, splat) pairs have alpha < 1/255: power < -ln(255 opacity) (less a margin far above float rounding)
// rejects them before the exponential; the exact tests follow for the rest.
#define BATCH uint(TILE_PX * TILE_PX)
layout(local_size_x = TILE_PX, local_size_y = TILE_PX) in;

layout(std430, binding = 2) readonly buffer Records { uvec4 records[]; };
layout(std430, binding = 5) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 7) readonly buffer TileValues { uint tile_values[]; };
layout(OUT_FORMAT, binding = 0) uniform writeonly image2D u_out;

uniform uvec2 u_grid;
uniform uvec2 u_pixels;  // image width, height
uniform vec3 u_background;

// power = A dx^2 + B dx dy + C dy^2 with (A, B, C) = (-a / 2, -b, -c / 2) of the conic (a, b, c).
shared vec4 s_geo[BATCH];   // center.xy, A, B
shared vec4 s_geo2[BATCH];  // C, power below which alpha < 1/255 for sure, opacity
shared vec4 s_rgb[BATCH];
shared uint s_done;         // pixels done (outside the image, or stopped at T < 1e-4)
#ifdef WARP_CULL
// Blocks of 8x4 pixels (a warp of 32 threads each, TILE_PX 16): block b = bx + 2 by. s_bits[b * 8 + w], bit i: splat
// 32 w + i of the batch has its alpha >= 1/255 box over a pixel centre of block b. Each block walks its own bits, in
// order (front to back), and never evaluates splats that miss it; a block that most of the batch reaches walks the
// whole batch (the same splats in the same order: those that miss it fail the alpha test there).
shared uint s_bits[64];
#endif

// One splat j of the batch with its power at this pixel: the reference's tests, early stop, blending.
#define BLEND(power, h, j)                                                  \
    if (!(power > 0.0 || power < h.y)) {                                    \
        float alpha = min(0.99, h.z * exp(power));                          \
        if (alpha >= 1.0 / 255.0) {                                         \
            float test_t = T * (1.0 - alpha);                               \
            if (test_t < 1e-4) {                                            \
                done = true;                                                \
                atomicAdd(s_done, 1u);                                      \
                break;                                                      \
            }                                                               \
            C += s_rgb[j].rgb * (alpha * T);                                \
            T = test_t;                                                     \
        }                                                                   \
    }

void main() {
    uint lid = gl_LocalInvocationIndex;
#ifdef WARP_CULL
    uint blk = lid >> 5;
    uvec2 pix = gl_WorkGroupID.xy * 16u + uvec2((lid & 7u) | ((blk & 1u) << 3), ((lid >> 3) & 3u) | ((blk >> 1) << 2));
#else
    uvec2 pix = gl_GlobalInvocationID.xy;
#endif
    uint tile = gl_WorkGroupID.y * u_grid.x + gl_WorkGroupID.x;
    uvec2 range = ranges[tile];
    bool inside = all(lessThan(pix, u_pixels));
    vec2 p = vec2(pix) + 0.5;  // pixel centre, rows counted from the top
    bool done = !inside;
    float T = 1.0;
    vec3 C = vec3(0.0);
    if (lid == 0u) s_done = 0u;
    barrier();
    if (done) atomicAdd(s_done, 1u);
    for (uint base = range.x; base < range.y; base += BATCH) {
        barrier();
        if (s_done == BATCH) break;  // uniform: increments happen after the next barrier only
#ifdef WARP_CULL
        if (lid < 64u) s_bits[lid] = 0u;
        barrier();
#endif
        uint idx = base + lid;
        if (idx < range.y) {
            uint r = 3u * tile_values[idx];
            uvec4 a = records[r];
            vec3 q = uintBitsToFloat(records[r + 1u].xyz);
            float op = uintBitsToFloat(a.w);
            s_geo[lid] = vec4(uintBitsToFloat(a.xy), -0.5 * q.x, -q.y);
            s_geo2[lid] = vec4(-0.5 * q.z, -log(255.0 * op) - 1e-3, op, 0.0);
            s_rgb[lid] = vec4(uintBitsToFloat(records[r + 2u].xyz), 0.0);
#ifdef WARP_CULL
            float det = q.x * q.z - q.y * q.y;
            float k = sqrt(2.0 * log(max(op, 1.0 / 255.0) * 255.0));
            vec2 ext = k * sqrt(max(vec2(q.z, q.x) / det, vec2(0.0))) + 0.05;  // margin over float rounding
            vec2 o = vec2(gl_WorkGroupID.xy * 16u);
            vec2 lo = uintBitsToFloat(a.xy) - ext - o;
            vec2 hi = uintBitsToFloat(a.xy) + ext - o;
            for (uint b = 0u; b < 8u; ++b) {
                vec2 b0 = vec2(float((b & 1u) * 8u) + 0.5, float((b >> 1) * 4u) + 0.5);  // first pixel centre
                vec2 b1 = b0 + vec2(7.0, 3.0);                                           // last pixel centre
                if (all(greaterThanEqual(hi, b0)) && all(lessThanEqual(lo, b1))) {
                    atomicOr(s_bits[b * 8u + (lid >> 5)], 1u << (lid & 31u));
                }
            }
#endif
        }
        barrier();
        if (done) continue;
        uint m = min(BATCH, range.y - base);
#ifdef WARP_CULL
        // A block whose bits name most of the batch walks all of it in the unrolled loop below instead (large
        // splats: the bit walk costs more a splat than the loop, and skips little).
        uint hits = 0u;
        for (uint w = 0u; w < 8u; ++w) hits += uint(bitCount(s_bits[blk * 8u + w]));
        if (hits * 4u < m * 3u) {
            for (uint w = 0u; w < 8u && !done; ++w) {
                uint bits = s_bits[blk * 8u + w];
                while (bits != 0u) {
                    uint j0 = w * 32u + uint(findLSB(bits));
                    bits &= bits - 1u;
                    vec4 g0 = s_geo[j0];
                    vec4 h0 = s_geo2[j0];
                    vec2 d0 = g0.xy - p;
                    float power0 = g0.z * d0.x * d0.x + h0.x * d0.y * d0.y + g0.w * d0.x * d0.y;
                    if (bits != 0u) {  // two independent power evaluations per step
                        uint j1 = w * 32u + uint(findLSB(bits));
                        bits &= bits - 1u;
                        vec4 g1 = s_geo[j1];
                        vec4 h1 = s_geo2[j1];
                        vec2 d1 = g1.xy - p;
                        float power1 = g1.z * d1.x * d1.x + h1.x * d1.y * d1.y + g1.w * d1.x * d1.y;
                        BLEND(power0, h0, j0)
                        BLEND(power1, h1, j1)
                    } else {
                        BLEND(power0, h0, j0)
                    }
                }
            }
            continue;
        }
#endif
        // Four, then two independent power evaluations per step hide latency (the fastest of 1, 2 and 4:
        // BENCHMARKS.md, "Figures behind library defaults"); the last splats one by one.
        uint j = 0u;
        for (; j + 3u < m; j += 4u) {
            vec4 g0 = s_geo[j];
            vec4 h0 = s_geo2[j];
            vec4 g1 = s_geo[j + 1u];
            vec4 h1 = s_geo2[j + 1u];
            vec4 g2 = s_geo[j + 2u];
            vec4 h2 = s_geo2[j + 2u];
            vec4 g3 = s_geo[j + 3u];
            vec4 h3 = s_geo2[j + 3u];
            vec2 d0 = g0.xy - p;
            vec2 d1 = g1.xy - p;
            vec2 d2 = g2.xy - p;
            vec2 d3 = g3.xy - p;
            float power0 = g0.z * d0.x * d0.x + h0.x * d0.y * d0.y + g0.w * d0.x * d0.y;
            float power1 = g1.z * d1.x * d1.x + h1.x * d1.y * d1.y + g1.w * d1.x * d1.y;
            float power2 = g2.z * d2.x * d2.x + h2.x * d2.y * d2.y + g2.w * d2.x * d2.y;
            float power3 = g3.z * d3.x * d3.x + h3.x * d3.y * d3.y + g3.w * d3.x * d3.y;
            BLEND(power0, h0, j)
            BLEND(power1, h1, j + 1u)
            BLEND(power2, h2, j + 2u)
            BLEND(power3, h3, j + 3u)
        }
        if (done) continue;
        for (; j + 1u < m; j += 2u) {
            vec4 g0 = s_geo[j];
            vec4 h0 = s_geo2[j];
            vec4 g1 = s_geo[j + 1u];
            vec4 h1 = s_geo2[j + 1u];
            vec2 d0 = g0.xy - p;
            vec2 d1 = g1.xy - p;
            float power0 = g0.z * d0.x * d0.x + h0.x * d0.y * d0.y + g0.w * d0.x * d0.y;
            float power1 = g1.z * d1.x * d1.x + h1.x * d1.y * d1.y + g1.w * d1.x * d1.y;
            BLEND(power0, h0, j)
            BLEND(power1, h1, j + 1u)
        }
        if (done) continue;
        for (; j < m; ++j) {
            vec4 g = s_geo[j];
            vec4 h = s_geo2[j];
            vec2 d = g.xy - p;
            float power = g.z * d.x * d.x + h.x * d.y * d.y + g.w * d.x * d.y;
            BLEND(power, h, j)
        }
    }
    if (inside) {
        imageStore(u_out, ivec2(int(pix.x), int(u_pixels.y - 1u - pix.y)), vec4(C + T * u_background, 1.0 - T));
    }
}
