// Test hook: decodes the listed splats with the same generated decoders the renderer uses and writes
// DEBUG_STRIDE floats per splat: position 3, rotation 4 (w, x, y, z), log scale 3, SH0 3 + opacity 1,
// SH rest 15 x 3 (coefficient-major), then the raw normalised texels t of position, rotation, scale, color (4 each).
layout(local_size_x = 64) in;

layout(std430, binding = 1) readonly buffer Ids { uint ids[]; };
layout(std430, binding = 2) writeonly buffer Out { float outv[]; };

uniform uint u_n;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= u_n) return;
    uint id = ids[i];
    ivec2 p = splat_texel(id);
    uint o = i * DEBUG_STRIDE;
    vec3 pos = decode_position(id, p);
    vec4 q = decode_rotation(p);
    vec3 ls = decode_log_scale(id, p);
    vec4 col = decode_color(id, p);
    for (uint k = 0u; k < 3u; ++k) outv[o + k] = pos[k];
    for (uint k = 0u; k < 4u; ++k) outv[o + 3u + k] = q[k];
    for (uint k = 0u; k < 3u; ++k) outv[o + 7u + k] = ls[k];
    for (uint k = 0u; k < 4u; ++k) outv[o + 10u + k] = col[k];
    for (uint k = 14u; k < 59u; ++k) outv[o + k] = 0.0;
#if SH_DEGREE >= 1
    for (int l = 0; l < 3; ++l) { vec3 c = decode_sh1(id, p, l); for (uint k = 0u; k < 3u; ++k) outv[o + 14u + uint(l) * 3u + k] = c[k]; }
#endif
#if SH_DEGREE >= 2
    for (int l = 0; l < 5; ++l) { vec3 c = decode_sh2(id, p, l); for (uint k = 0u; k < 3u; ++k) outv[o + 23u + uint(l) * 3u + k] = c[k]; }
#endif
#if SH_DEGREE >= 3
    for (int l = 0; l < 7; ++l) { vec3 c = decode_sh3(id, p, l); for (uint k = 0u; k < 3u; ++k) outv[o + 38u + uint(l) * 3u + k] = c[k]; }
#endif
    vec4 t0 = t_position(p), t1 = t_rotation(p), t2 = t_scale(p), t3 = t_color(p);
    for (uint k = 0u; k < 4u; ++k) {
        outv[o + 59u + k] = t0[k];
        outv[o + 63u + k] = t1[k];
        outv[o + 67u + k] = t2[k];
        outv[o + 71u + k] = t3[k];
    }
}
