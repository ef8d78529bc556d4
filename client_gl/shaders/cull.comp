// Frustum and opacity culling plus view-depth sort keys for every resident splat; compacts the visible ones.
// One work group per chunk slot (256 splats). Visible splats get key = ~floatBitsToUint(depth) (ascending key =
// back to front) and value = global splat index. The count goes to params.count (work-group aggregated atomics).
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Params { uint count; uint pad[3]; };
layout(std430, binding = 1) writeonly buffer Keys { uint keys[]; };
layout(std430, binding = 2) writeonly buffer Values { uint values[]; };

uniform uint u_slots;       // slots to scan (highest used slot + 1)
uniform uint u_slot_base;   // first slot of this dispatch (dispatches are split to stay under the group limit)

shared uint s_local;
shared uint s_base;

void main() {
    uint slot = gl_WorkGroupID.x + u_slot_base;
    uint j = gl_LocalInvocationID.x;
    if (j == 0u) s_local = 0u;
    barrier();
    bool visible = false;
    uint key = 0u;
    uint id = slot * 256u + j;
    if (slot < u_slots && j < range_count(slot)) {
        ivec2 p = splat_texel(id);
        float opacity = clamp(decode_color(id, p).a, 0.0, 1.0);
        if (opacity >= ALPHA_MIN) {
            vec2 center;
            vec3 cov;
            float depth;
            if (project_splat(decode_position(id, p), decode_rotation(p), decode_log_scale(id, p), center, cov, depth)) {
                // Axis-aligned box of the ellipse where alpha reaches 1/255 (the quad the vertex shader draws).
                vec2 ext = cutoff_sigmas(opacity) * sqrt(vec2(cov.x, cov.z));
                visible = all(greaterThan(center + ext, vec2(0.0))) && all(lessThan(center - ext, u_size));
                key = 0xFFFFFFFFu - floatBitsToUint(depth);
            }
        }
    }
    uint local = 0u;
    if (visible) local = atomicAdd(s_local, 1u);
    barrier();
    if (j == 0u) s_base = atomicAdd(count, s_local);
    barrier();
    if (visible) {
        keys[s_base + local] = key;
        values[s_base + local] = id;
    }
}
