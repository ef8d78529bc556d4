// Tile binning of the compute rasterizer: the TILE_PX x TILE_PX-pixel tiles (16 by default) a projected splat touches.
// Records are cull.comp's 48-byte records: (center.xy, ndc z, opacity), (conic.xyz, minor), (rgb, axis).
layout(std430, binding = 2) readonly buffer Records { uvec4 records[]; };

uniform uvec2 u_grid;  // tiles in x and y

// Tiles [lo, hi) overlapped by the axis-aligned box of the ellipse where alpha reaches 1/255
// (k = sqrt(2 ln(255 opacity)) sigmas; the covariance is the inverse of the conic). Empty when degenerate.
void tile_rect(uint r, out uvec2 lo, out uvec2 hi) {
    uvec4 a = records[3u * r];
    vec3 q = uintBitsToFloat(records[3u * r + 1u].xyz);
    vec2 c = uintBitsToFloat(a.xy);
    float op = uintBitsToFloat(a.w);
    float det = q.x * q.z - q.y * q.y;
    float k = sqrt(2.0 * log(max(op, 1.0 / 255.0) * 255.0));
    vec2 ext = k * sqrt(max(vec2(q.z, q.x) / det, vec2(0.0)));
    vec2 l = (c - ext) / float(TILE_PX);
    vec2 h = (c + ext) / float(TILE_PX);
    lo = uvec2(0u);
    hi = uvec2(0u);
    if (!(det > 0.0) || any(isnan(l)) || any(isnan(h)) || any(isinf(l)) || any(isinf(h))) return;
    vec2 g = vec2(u_grid);
    lo = uvec2(clamp(floor(l), vec2(0.0), g));
    hi = max(uvec2(clamp(floor(h) + 1.0, vec2(0.0), g)), lo);
}

uint rect_tiles(uvec2 lo, uvec2 hi) { return (hi.x - lo.x) * (hi.y - lo.y); }
