// Fragment shader of the GPU path's "fetch" draw modes: the vertex stage passes only the record index, the
// fragment reads the 48-byte record (cached: every fragment of a splat reads the same one).
#ifdef EARLY_TESTS
layout(early_fragment_tests) in;  // front-to-back draw: saturated pixels (depth 0) reject fragments before shading
#endif
layout(std430, binding = 0) readonly buffer Records { uvec4 records[]; };

flat in uint v_record;
uniform vec2 u_size;

out vec4 frag;

void main() {
    uint r = v_record * 3u;
    uvec4 a = records[r];
    uvec4 b = records[r + 1u];
    vec2 pix = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
    vec2 d = uintBitsToFloat(a.xy) - pix;
    vec3 conic = uintBitsToFloat(b.xyz);
    float power = -0.5 * (conic.x * d.x * d.x + conic.z * d.y * d.y) - conic.y * d.x * d.y;
    if (power > 0.0) discard;
    float alpha = min(0.99, uintBitsToFloat(a.w) * exp(power));
    if (alpha < 1.0 / 255.0) discard;
    vec3 rgb = uintBitsToFloat(records[r + 2u].xyz);
    frag = vec4(rgb * alpha, alpha);
}
