#version 460
// The clustering's assignment: each local histogram, packed (the paper's packing matrix), goes
// to its nearest centroid in L2 among the members of the GROUPS_SEARCHED groups of centroids
// whose centres are nearest (a two-level search: about 13 times fewer distances than all N at
// N = 2048, 64 groups; histogram::assign_two_level is the CPU twin).
#extension GL_GOOGLE_include_directive : require
#include "constants.glsl"
layout(local_size_x = 64) in;

layout(std430, binding = 0) readonly buffer Rows { float rows[]; };
// The packing matrix, the centroids and the group centres in vec4s, each row zero-padded to
// P4 of them (a zero adds nothing to a distance): a CPU renderer reads a vec4 lane by lane in
// one go, not four.
layout(std430, binding = 1) readonly buffer Packing { vec4 packing[]; };
layout(std430, binding = 2) readonly buffer Centroids { vec4 centroids[]; };
layout(std430, binding = 3) writeonly buffer Ids { uint ids[]; };
layout(std430, binding = 4) readonly buffer GroupCentres { vec4 group_centres[]; };
// Group g's members are members[first[g] .. first[g + 1]].
layout(std430, binding = 5) readonly buffer GroupFirst { uint first[]; };
layout(std430, binding = 6) readonly buffer GroupMembers { uint members[]; };

layout(push_constant) uniform Push {
    uvec4 job;  // x: rows, y: shades, z: groups G, w: clusters N
} pc;

const uint GROUPS_SEARCHED = 3u;

// The packed dimension in vec4s, a specialization constant (src/ao/histogram_gpu.rs): the
// packed histogram is then held in registers and the distance loops unrolled. The two
// distances read their tables in loops of their own: a select between two tables reads both on
// a CPU renderer.
layout(constant_id = 0) const uint P4 = HIST_MAX_PACKED / 4u;
vec4 packed[P4];

// The squared distance, its terms added in the order of the dimensions.
float add_squares(float d, vec4 t) {
    d += t.x * t.x;
    d += t.y * t.y;
    d += t.z * t.z;
    return d + t.w * t.w;
}

float dist_group(uint c) {
    float d = 0.0;
    for (uint k = 0u; k < P4; k++) d = add_squares(d, group_centres[c * P4 + k] - packed[k]);
    return d;
}

float dist_centroid(uint c) {
    float d = 0.0;
    for (uint k = 0u; k < P4; k++) d = add_squares(d, centroids[c * P4 + k] - packed[k]);
    return d;
}

void main() {
    uint r = gl_GlobalInvocationID.x;
    if (r >= pc.job.x) return;
    uint b = pc.job.y;
    // A flat voxel's second row (marked negative by histogram_local.comp) is its first: the
    // host takes the first row's cluster.
    if (rows[r * b] < 0.0) {
        ids[r] = SAME_AS_FRONT;
        return;
    }
    for (uint d = 0u; d < P4; d++) packed[d] = vec4(0.0);
    for (uint k = 0u; k < b; k++) {
        float x = rows[r * b + k];
        // A neighbourhood holds few of the shades: skipping the zeros changes no sum.
        if (x == 0.0) continue;
        for (uint d = 0u; d < P4; d++) packed[d] += x * packing[k * P4 + d];
    }
    // The nearest groups (first of equals), kept sorted.
    uint near_g[GROUPS_SEARCHED];
    float near_d[GROUPS_SEARCHED];
    for (uint i = 0u; i < GROUPS_SEARCHED; i++) {
        near_g[i] = 0xffffffffu;
        near_d[i] = 1.0 / 0.0;
    }
    for (uint g = 0u; g < pc.job.z; g++) {
        float d = dist_group(g);
        if (d < near_d[GROUPS_SEARCHED - 1u]) {
            uint i = GROUPS_SEARCHED - 1u;
            while (i > 0u && d < near_d[i - 1u]) {
                near_d[i] = near_d[i - 1u];
                near_g[i] = near_g[i - 1u];
                i--;
            }
            near_d[i] = d;
            near_g[i] = g;
        }
    }
    uint best = 0u;
    float best_d = 1.0 / 0.0;
    for (uint i = 0u; i < GROUPS_SEARCHED; i++) {
        uint g = near_g[i];
        if (g == 0xffffffffu) continue;
        for (uint m = first[g]; m < first[g + 1u]; m++) {
            uint c = members[m];
            float d = dist_centroid(c);
            if (d < best_d || (d == best_d && c < best)) {
                best_d = d;
                best = c;
            }
        }
    }
    ids[r] = best;
}
