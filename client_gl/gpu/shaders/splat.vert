// CPU-sort path (GL >= 4.1): one instance per visible splat (a_id = global splat index slot * 256 + j, back to
// front), 4 vertices per quad; decodes, projects (EWA) and evaluates SH per vertex.
layout(location = 0) in uint a_id;

flat out vec4 v_color;      // rgb (clamped at 0), opacity
flat out vec3 v_conic;      // inverse 2D covariance (a, b, c)
flat out vec2 v_center;     // image coordinates of the projected mean

void main() {
    uint id = a_id;
    ivec2 p = splat_texel(id);
    vec3 pos = decode_position(id, p);
    vec4 col = decode_color(id, p);
    float opacity = clamp(col.a, 0.0, 1.0);
    vec2 center;
    vec3 cov;
    float depth;
    bool ok = opacity >= ALPHA_MIN && project_splat(pos, decode_rotation(p), decode_log_scale(id, p), center, cov, depth);
    if (!ok) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the clip volume: the quad is dropped
        v_color = vec4(0.0);
        v_conic = vec3(0.0);
        v_center = vec2(0.0);
        return;
    }
    vec2 axis1;
    float minor;
    splat_quad(cov, opacity, v_conic, axis1, minor);
    gl_Position = quad_corner(uint(gl_VertexID), center, axis1, minor, u_depth_ab.x + u_depth_ab.y / depth);
    vec3 rgb = eval_sh(id, p, normalize(pos - u_eye), u_sh_degree, col.rgb);
    v_color = vec4(max(rgb + 0.5, vec3(0.0)), opacity);
    v_center = center;
}
