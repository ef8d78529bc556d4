// GPU path, "fetch" draw modes: quads (instanced strips) or point sprites (POINTS) that pass only the record index
// to the fragment shader (which reads the record). Point sprites cover the ellipse's bounding square, at most
// u_max_point pixels wide. GL drops a point whose centre is outside the clip volume, so the points mode draws with
// a viewport enlarged by a guard band of u_guard pixels on every side (max point size / 2): every point whose
// square reaches the image has its centre inside. Fragments outside the framebuffer are never generated.
layout(std430, binding = 0) readonly buffer Records { uvec4 records[]; };
layout(std430, binding = 1) readonly buffer Order { uint order[]; };

uniform float u_max_point;
uniform float u_guard;

flat out uint v_record;

#include "quad.glsl"

#ifdef ORDER_ATTRIBUTE
layout(location = 0) in uint a_order;  // per instance: honours the base instance of batched indirect draws
#endif

void main() {
#ifdef ORDER_ATTRIBUTE
    uint rec = a_order;
#else
    uint rec = order[uint(gl_InstanceID) + uint(gl_VertexID) * POINTS_STRIDE];
#endif
    v_record = rec;
    uint r = rec * 3u;
    uvec4 a = records[r];
    uvec4 d = records[r + 2u];
    vec2 center = uintBitsToFloat(a.xy);
    vec2 axis1 = unpackHalf2x16(d.w);
    float minor = uintBitsToFloat(records[r + 1u].w);
#ifdef DRAW_POINTS
    float len1 = max(length(axis1), 1e-12);
    vec2 e2 = vec2(-axis1.y, axis1.x) / len1;
    vec2 ext = sqrt(axis1 * axis1 + (minor * e2) * (minor * e2));  // half extents of the ellipse's bounding box
    gl_PointSize = min(2.0 * max(ext.x, ext.y) + 1.0, u_max_point);
    vec2 full = u_size + 2.0 * u_guard;
    gl_Position = vec4((center.x + u_guard) / full.x * 2.0 - 1.0, 1.0 - (center.y + u_guard) / full.y * 2.0,
                       uintBitsToFloat(a.z), 1.0);
#else
    gl_Position = quad_corner(uint(gl_VertexID), center, axis1, minor, uintBitsToFloat(a.z));
#endif
}
