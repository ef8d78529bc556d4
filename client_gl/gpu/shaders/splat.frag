flat in vec4 v_color;
flat in vec3 v_conic;
flat in vec2 v_center;

uniform vec2 u_size;

out vec4 frag;

void main() {
    // Image coordinates of this pixel's centre (row 0 at the top; GL windows count rows from the bottom).
    vec2 pix = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
    vec2 d = v_center - pix;
    float power = -0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) - v_conic.y * d.x * d.y;
    if (power > 0.0) discard;
    float alpha = min(0.99, v_color.a * exp(power));
    if (alpha < 1.0 / 255.0) discard;
    frag = vec4(v_color.rgb * alpha, alpha);  // premultiplied; blended with (ONE, ONE_MINUS_SRC_ALPHA)
}
