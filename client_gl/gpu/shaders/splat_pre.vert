// GPU-sort path: the cull pass already projected each visible splat into a 48-byte record; this shader only
// expands record order[i] into a quad. DRAW_TRIANGLES: one non-instanced draw of 6 vertices per splat
// (i = gl_VertexID / 6); otherwise an instanced 4-vertex strip per splat (i = gl_InstanceID).
layout(std430, binding = 0) readonly buffer Records { uvec4 records[]; };
layout(std430, binding = 1) readonly buffer Order { uint order[]; };

flat out vec4 v_color;
flat out vec3 v_conic;
flat out vec2 v_center;

#include "quad.glsl"

void main() {
#ifdef DRAW_TRIANGLES
    uint i = uint(gl_VertexID) / 6u;
    uint v = uint(gl_VertexID) % 6u;
    uint c = v < 3u ? v : v - 2u;  // (0, 1, 2), (1, 2, 3)
#else
    uint i = uint(gl_InstanceID);
    uint c = uint(gl_VertexID);
#endif
    uint r = order[i] * 3u;
    uvec4 a = records[r];
    uvec4 b = records[r + 1u];
    uvec4 d = records[r + 2u];
    vec2 center = uintBitsToFloat(a.xy);
    v_center = center;
    v_color = vec4(uintBitsToFloat(d.xyz), uintBitsToFloat(a.w));
    v_conic = uintBitsToFloat(b.xyz);
    gl_Position = quad_corner(c, center, unpackHalf2x16(d.w), uintBitsToFloat(b.w), uintBitsToFloat(a.z));
}
