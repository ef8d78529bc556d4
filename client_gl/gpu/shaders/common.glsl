// Shared by the cull compute shader, the splat vertex shader and the decode test shader.
// Generated definitions (texel decoders, range offsets, SH constants) are prepended by client_gl/shadergen.py.

#include "quad.glsl"

uniform mat4 u_view;        // world -> camera in the reference 3DGS convention (x right, y down, z forward)
uniform vec2 u_focal;       // (fx, fy) in pixels
uniform vec2 u_principal;   // (cx, cy): image coordinates of the optical axis (pixel centres at +0.5)
uniform vec2 u_tan_fov;     // (tan(fov_x / 2), tan(fov_y / 2))
uniform float u_near;       // splats with view depth <= near are culled (reference: 0.2)
uniform float u_far;
uniform vec3 u_eye;         // camera position (SH view directions)
uniform int u_sh_degree;    // bands requested (eval_sh lowers it to each slot's resident bands)
uniform vec2 u_depth_ab;    // NDC depth = a + b / view depth (OpenGL perspective with near/far)

const float ALPHA_MIN = 1.0 / 255.0;

// Rotation matrix of a unit quaternion stored as (w, x, y, z) in (.x, .y, .z, .w); same as gaussians.rotation_matrices.
mat3 quat_to_mat(vec4 q) {
    float w = q.x, x = q.y, y = q.z, z = q.w;
    // GLSL constructors fill columns: build the rows and transpose.
    return transpose(mat3(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)));
}

// EWA projection as the reference rasterizer does it (computeCov2D): Jacobian at the mean with t.x/t.z and t.y/t.z
// clamped to 1.3 tan(fov/2), 0.3 pixel^2 low-pass on the diagonal. Returns false when the splat is culled
// (behind the near plane, degenerate). cov2 = (a, b, c) of [[a, b], [b, c]] in pixels^2.
bool project_splat(vec3 pos, vec4 q, vec3 log_scale, out vec2 center, out vec3 cov2, out float depth) {
    vec3 t = (u_view * vec4(pos, 1.0)).xyz;
    depth = t.z;
    center = vec2(0.0);
    cov2 = vec3(0.0);
    if (!(t.z > u_near) || t.z > u_far) return false;
    center = u_focal * t.xy / t.z + u_principal;
    vec2 lim = 1.3 * u_tan_fov;
    vec2 txy = clamp(t.xy / t.z, -lim, lim) * t.z;
    float iz = 1.0 / t.z;
    mat3 J = transpose(mat3(
        u_focal.x * iz, 0.0, -u_focal.x * txy.x * iz * iz,
        0.0, u_focal.y * iz, -u_focal.y * txy.y * iz * iz,
        0.0, 0.0, 0.0));
    mat3 W = mat3(u_view);
    mat3 M = quat_to_mat(q) * mat3(exp(log_scale.x), 0.0, 0.0, 0.0, exp(log_scale.y), 0.0, 0.0, 0.0, exp(log_scale.z));
    mat3 T = J * W * M;
    mat3 C = T * transpose(T);
    cov2 = vec3(C[0][0] + 0.3, C[1][0], C[1][1] + 0.3);
    float det = cov2.x * cov2.z - cov2.y * cov2.y;
    return det > 0.0;
}

// Half extent (in sigmas) of the ellipse where opacity * exp(-d^2 / 2) falls to 1/255.
float cutoff_sigmas(float opacity) {
    return sqrt(2.0 * log(max(opacity, ALPHA_MIN) * 255.0));
}

// Screen-space quad of a projected splat: conic (inverse covariance) for the fragment shader, and the ellipse's
// semi-axes where alpha reaches 1/255: axis1 (major, a vector) and the minor half-length (along axis1 rotated +90).
void splat_quad(vec3 cov, float opacity, out vec3 conic, out vec2 axis1, out float minor) {
    float det = cov.x * cov.z - cov.y * cov.y;
    conic = vec3(cov.z, -cov.y, cov.x) / det;
    float mid = 0.5 * (cov.x + cov.z);
    float disc = sqrt(max(0.0, 0.25 * (cov.x - cov.z) * (cov.x - cov.z) + cov.y * cov.y));
    float l1 = mid + disc;
    float l2 = max(mid - disc, 0.0);
    vec2 e1 = abs(cov.y) > 1e-12 ? normalize(vec2(cov.y, l1 - cov.x)) : (cov.x >= cov.z ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    float k = cutoff_sigmas(opacity);
    axis1 = e1 * (k * sqrt(l1));
    minor = k * sqrt(l2);
}
