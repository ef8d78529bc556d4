// Tile binning of the compute rasterizer: the TILE_PX x TILE_PX-pixel tiles (16) a projected splat touches.
// Records are cull.comp's 48-byte records: (center.xy, ndc z, opacity), (conic.xyz, minor), (rgb, axis).
layout(std430, binding = 2) readonly buffer Records { uvec4 records[]; };

uniform uvec2 u_grid;  // tiles in x and y

// Tiles [lo, hi) overlapped by the axis-aligned box of the ellipse where alpha reaches 1/255
// (k = sqrt(2 ln(255 opacity)) sigmas; the covariance is the inverse of the conic). Empty when degenerate.
// c, q, op: the splat's centre (pixels), conic (a, b, c) and opacity, for row_spans.
void tile_rect(uint r, out uvec2 lo, out uvec2 hi, out vec2 c, out vec3 q, out float op) {
    uvec4 a = records[3u * r];
    q = uintBitsToFloat(records[3u * r + 1u].xyz);
    c = uintBitsToFloat(a.xy);
    op = uintBitsToFloat(a.w);
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

// A splat's ellipse Q(d) <= L for row_tiles: Q(d) = a dx^2 + 2 b dx dy + c dy^2 (q = (a, b, c)), L = 2 (ln(255
// opacity) + 0.01) (the alpha >= 1/255 level plus a margin far above float rounding: a splat this keeps and the
// raster rejects costs time, never a pixel); det = ac - b^2, ey its half height,
// s = sqrt(L / (det c)).
struct RowSplat { vec2 c; vec3 q; float L; float det; float ey; float s; };

RowSplat row_splat(vec2 c, vec3 q, float op) {
    RowSplat e;
    e.c = c;
    e.q = q;
    precise float L = 2.0 * (log(max(op, 1.0 / 255.0) * 255.0) + 0.01);
    precise float det = q.x * q.z - q.y * q.y;
    precise float ey = sqrt(L * q.x / det);
    precise float s = sqrt(L / (det * q.z));
    e.L = L;
    e.det = det;
    e.ey = ey;
    e.s = s;
    return e;
}

// Tiles [x.x, x.y) of tile row ty (within the box [lo, hi)) whose rectangle of pixel centres the ellipse reaches:
// its slice over the row's band of pixel-centre rows is convex, so the tiles it reaches are those whose pixel-centre
// columns meet its x extent, the smallest left and largest right boundary over the band. The left boundary, convex
// in dy, is smallest at the band's point nearest dy = b s (the ellipse's leftmost point), the right one largest
// nearest dy = -b s. Count and emit evaluate it with this same code; 0.001 px of margin on either side.
uvec2 row_tiles(uint ty, uvec2 lo, uvec2 hi, RowSplat e) {
    precise float y0 = float(ty * uint(TILE_PX)) + 0.5 - e.c.y;
    precise float d0 = max(y0, -e.ey), d1 = min(y0 + float(TILE_PX - 1), e.ey);
    if (!(d0 <= d1)) return uvec2(lo.x);
    precise float dl = clamp(e.q.y * e.s, d0, d1), dr = clamp(-e.q.y * e.s, d0, d1);
    precise float xl = e.c.x + (-e.q.y * dl - sqrt(max(e.q.x * e.L - e.det * dl * dl, 0.0))) / e.q.x - 1e-3;
    precise float xr = e.c.x + (-e.q.y * dr + sqrt(max(e.q.x * e.L - e.det * dr * dr, 0.0))) / e.q.x + 1e-3;
    float t = float(TILE_PX);
    float f0 = max(ceil((xl - (t - 0.5)) / t), float(lo.x));
    float f1 = min(floor((xr - 0.5) / t) + 1.0, float(hi.x));
    if (!(f0 < f1)) return uvec2(lo.x);
    return uvec2(uint(f0), uint(f1));
}

// Whether a splat's entries are its rows' tiles (boxes at most ROW_BINS_ROWS tiles high and 127 wide, whose rows
// bin_emit keeps in shared memory: four bounds of 8 bits in a word whose top bit, clear below 128, tells them from a
// whole box) or its whole box (taller ones: a thread a splat over many rows would keep its warp waiting, as the
// per-entry walk of an earlier version did; wider ones, seen only on images over 2,048 pixels wide).
#define ROW_BINS_ROWS 2u
bool row_binned(uvec2 lo, uvec2 hi) { return hi.y - lo.y <= ROW_BINS_ROWS && hi.x - lo.x <= 127u; }

// A row-binned splat's tile spans [x0, x1): its first row's in .xy, its second row's in .zw (empty: lo.x, lo.x).
// bin_count counts them and bin_emit keeps them: one code, so both agree.
uvec4 row_spans(uvec2 lo, uvec2 hi, vec2 c, vec3 q, float op) {
    if (hi.y - lo.y == 1u && hi.x - lo.x == 1u) return uvec4(lo.x, hi.x, lo.x, lo.x);  // one tile: the box is exact
    uvec4 s = uvec4(lo.x);
    if (hi.y == lo.y) return s;
    RowSplat e = row_splat(c, q, op);
    s.xy = row_tiles(lo.y, lo, hi, e);
    if (hi.y - lo.y == 2u) s.zw = row_tiles(lo.y + 1u, lo, hi, e);
    return s;
}

uint row_entries(uvec2 lo, uvec2 hi, vec2 c, vec3 q, float op) {
    if (!row_binned(lo, hi)) return rect_tiles(lo, hi);
    uvec4 s = row_spans(lo, hi, c, q, op);
    return (s.y - s.x) + (s.w - s.z);
}
