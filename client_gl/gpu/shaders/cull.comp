// Frustum and opacity culling, projection and colour of every drawn resident splat (the slot-state draw mask skips
// the others); compacts the visible ones. One work group per chunk slot (256 splats). Visible splat number i
// (order of compaction) gets key = the depth's float bits mapped to u_key_max + 1 values, inverted (ascending key =
// back to front), value = i and a 48-byte
// record for the draw: (center.xy, ndc z, opacity), (conic.xyz, minor half-axis), (rgb, packHalf2x16(major
// half-axis vector)).
// The count goes to params.count (work-group aggregated atomics).
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint oversized; uint pad[2]; };
layout(std430, binding = 1) writeonly buffer Keys { uint keys[]; };
layout(std430, binding = 2) writeonly buffer Values { uint values[]; };
layout(std430, binding = 3) writeonly buffer Records { uvec4 records[]; };

uniform uint u_slots;       // slots to scan (highest used slot + 1)
uniform uint u_slot_base;   // first slot of this dispatch (dispatches are split to stay under the group limit)
uniform float u_max_point;  // largest point sprite (points draw mode): wider splats are counted in params.oversized
uniform uint u_key_xor;     // the key's bits (all ones): back to front (default); 0: front to back
// Depth keys of fewer than 32 bits (fewer radix passes): the float bits of the depth, less those of the near plane,
// shifted right so that the far plane's fit in the key (depth is in (near, far]: project_splat culls the rest).
uniform uvec2 u_key_range;  // (bits of near, right shift)
uniform uint u_key_max;     // largest key

shared uint s_local;
shared uint s_base;

void main() {
    uint slot = gl_WorkGroupID.x + u_slot_base;
    // A slot outside the draw set (or past the used ones) leaves at once, the whole group together (slot is the
    // same for all of it, so no barrier is skipped by part of the group): a pool that holds many more splats than
    // it draws scans them for a texel fetch each, not for barriers and an atomic.
    if (slot >= u_slots || !slot_drawn(slot)) return;
    uint j = gl_LocalInvocationID.x;
    if (j == 0u) s_local = 0u;
    barrier();
    bool visible = false;
    uint key = 0u;
    uint id = slot * 256u + j;
    ivec2 p = splat_texel(id);
    vec3 pos;
    vec4 col;
    vec2 center;
    vec3 cov;
    float depth;
    if (j < range_count(slot)) {
        col = decode_color(id, p);
        col.a = clamp(col.a, 0.0, 1.0);
        if (col.a >= ALPHA_MIN) {
            pos = decode_position(id, p);
            if (project_splat(pos, decode_rotation(p), decode_log_scale(id, p), center, cov, depth)) {
                // Axis-aligned box of the ellipse where alpha reaches 1/255 (the quad the vertex shader draws).
                vec2 ext = cutoff_sigmas(col.a) * sqrt(vec2(cov.x, cov.z));
                visible = all(greaterThan(center + ext, vec2(0.0))) && all(lessThan(center - ext, u_size));
                if (visible && 2.0 * max(ext.x, ext.y) + 1.0 > u_max_point) atomicAdd(oversized, 1u);
                key = min((floatBitsToUint(depth) - u_key_range.x) >> u_key_range.y, u_key_max) ^ u_key_xor;
            }
        }
    }
    uint local = 0u;
    if (visible) local = atomicAdd(s_local, 1u);
    barrier();
    if (j == 0u && s_local > 0u) s_base = atomicAdd(count, s_local);
    barrier();
    if (visible) {
        uint i = s_base + local;
        keys[i] = key;
        values[i] = i;
        vec3 conic;
        vec2 axis1;
        float minor;
        splat_quad(cov, col.a, conic, axis1, minor);
        vec3 rgb = max(eval_sh(id, p, normalize(pos - u_eye), u_sh_degree, col.rgb) + 0.5, vec3(0.0));
        float z = u_depth_ab.x + u_depth_ab.y / depth;
        records[3u * i] = uvec4(floatBitsToUint(center), floatBitsToUint(z), floatBitsToUint(col.a));
        records[3u * i + 1u] = uvec4(floatBitsToUint(conic), floatBitsToUint(minor));
        records[3u * i + 2u] = uvec4(floatBitsToUint(rgb), packHalf2x16(axis1));
    }
}
