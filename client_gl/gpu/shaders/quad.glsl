// Image-space quad corners -> clip space (image row 0 at the top, pixel centres at +0.5).
uniform vec2 u_size;        // image (width, height) in pixels

// Clip-space position of quad corner c (0..3: (-1,-1), (1,-1), (-1,1), (1,1)) of a splat centred at `center`
// (image coordinates) with semi-axes axis1 and minor (along axis1 rotated by +90 degrees); NDC depth z.
vec4 quad_corner(uint c, vec2 center, vec2 axis1, float minor, float z) {
    vec2 corner = vec2((c & 1u) != 0u ? 1.0 : -1.0, (c & 2u) != 0u ? 1.0 : -1.0);
    float len1 = length(axis1);
    vec2 axis2 = len1 > 0.0 ? vec2(-axis1.y, axis1.x) * (minor / len1) : vec2(0.0, minor);
    vec2 pix = center + corner.x * axis1 + corner.y * axis2;
    return vec4(pix.x / u_size.x * 2.0 - 1.0, 1.0 - pix.y / u_size.y * 2.0, z, 1.0);
}
