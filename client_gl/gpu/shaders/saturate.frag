// Saturation pass of the front-to-back draw: pixels whose transmittance fell below T_MIN get the nearest depth, so
// the splats of later batches are rejected there by the early depth test (the reference's early stop).
uniform sampler2D u_accum;   // the colour target drawn so far (alpha = 1 - T)

const float T_MIN = 1e-4;

void main() {
    float a = texelFetch(u_accum, ivec2(gl_FragCoord.xy), 0).a;
    if (1.0 - a >= T_MIN) discard;
    gl_FragDepth = 0.0;
}
