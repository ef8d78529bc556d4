// Compute rasterizer: one work group per 16x16 tile, one thread per pixel. The tile's splats (front to back) are
// loaded in batches of 256 into shared memory; per pixel, as the reference rasterizer (render_ref / forward.cu):
// power = -0.5 (a dx^2 + c dy^2) - b dx dy, skipped if > 0; alpha = min(0.99, opacity exp(power)), skipped if
// < 1/255; the pixel stops (this splat excluded) once T (1 - alpha) < 1e-4; C += rgb alpha T; T *= 1 - alpha.
// Output (C + T background, 1 - T), row 0 of the image at the bottom of the texture (GL convention).
layout(local_size_x = 16, local_size_y = 16) in;

layout(std430, binding = 2) readonly buffer Records { uvec4 records[]; };
layout(std430, binding = 5) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 7) readonly buffer TileValues { uint tile_values[]; };
layout(OUT_FORMAT, binding = 0) uniform writeonly image2D u_out;

uniform uvec2 u_grid;
uniform uvec2 u_pixels;  // image width, height
uniform vec3 u_background;

shared vec4 s_xyo[256];    // center.xy, opacity
shared vec4 s_conic[256];  // conic a, b, c
shared vec4 s_rgb[256];
shared uint s_done;

void main() {
    uint lid = gl_LocalInvocationIndex;
    uvec2 pix = gl_GlobalInvocationID.xy;
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
    for (uint base = range.x; base < range.y; base += 256u) {
        barrier();
        if (s_done == 256u) break;  // uniform: increments happen after the next barrier only
        uint idx = base + lid;
        if (idx < range.y) {
            uint r = 3u * tile_values[idx];
            uvec4 a = records[r];
            s_xyo[lid] = vec4(uintBitsToFloat(a.xy), uintBitsToFloat(a.w), 0.0);
            s_conic[lid] = vec4(uintBitsToFloat(records[r + 1u].xyz), 0.0);
            s_rgb[lid] = vec4(uintBitsToFloat(records[r + 2u].xyz), 0.0);
        }
        barrier();
        if (!done) {
            uint m = min(256u, range.y - base);
            for (uint j = 0u; j < m; ++j) {
                vec4 xyo = s_xyo[j];
                vec3 q = s_conic[j].xyz;
                vec2 d = xyo.xy - p;
                float power = -0.5 * (q.x * d.x * d.x + q.z * d.y * d.y) - q.y * d.x * d.y;
                if (power > 0.0) continue;
                float alpha = min(0.99, xyo.z * exp(power));
                if (alpha < 1.0 / 255.0) continue;
                float test_t = T * (1.0 - alpha);
                if (test_t < 1e-4) {
                    done = true;
                    atomicAdd(s_done, 1u);
                    break;
                }
                C += s_rgb[j].rgb * (alpha * T);
                T = test_t;
            }
        }
    }
    if (inside) {
        imageStore(u_out, ivec2(int(pix.x), int(u_pixels.y - 1u - pix.y)), vec4(C + T * u_background, 1.0 - T));
    }
}
