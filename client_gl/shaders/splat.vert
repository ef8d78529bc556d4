// One instance per visible splat (a_id = global splat index slot * 256 + j, back to front); 4 vertices per quad.
layout(location = 0) in uint a_id;

uniform vec3 u_eye;
uniform int u_sh_degree;
uniform vec2 u_depth_ab;    // NDC depth = a + b / view depth (OpenGL perspective with near/far)

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
    float det = cov.x * cov.z - cov.y * cov.y;
    v_conic = vec3(cov.z, -cov.y, cov.x) / det;
    // Eigen decomposition of the 2x2 covariance: the quad follows the ellipse axes.
    float mid = 0.5 * (cov.x + cov.z);
    float disc = sqrt(max(0.0, 0.25 * (cov.x - cov.z) * (cov.x - cov.z) + cov.y * cov.y));
    float l1 = mid + disc;
    float l2 = max(mid - disc, 0.0);
    vec2 e1 = abs(cov.y) > 1e-12 ? normalize(vec2(cov.y, l1 - cov.x)) : (cov.x >= cov.z ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    vec2 e2 = vec2(-e1.y, e1.x);
    float k = cutoff_sigmas(opacity);
    vec2 corner = vec2((gl_VertexID & 1) != 0 ? 1.0 : -1.0, (gl_VertexID & 2) != 0 ? 1.0 : -1.0);
    vec2 pix = center + corner.x * (k * sqrt(l1)) * e1 + corner.y * (k * sqrt(l2)) * e2;
    vec2 ndc = vec2(pix.x / u_size.x * 2.0 - 1.0, 1.0 - pix.y / u_size.y * 2.0);
    gl_Position = vec4(ndc, u_depth_ab.x + u_depth_ab.y / depth, 1.0);
    vec3 dir = normalize(pos - u_eye);
    vec3 rgb = eval_sh(id, p, dir, u_sh_degree, col.rgb);
    v_color = vec4(max(rgb + 0.5, vec3(0.0)), opacity);
    v_center = center;
}
