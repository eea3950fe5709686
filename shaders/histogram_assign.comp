#version 460
// The clustering's assignment: each local histogram, packed (the paper's packing matrix), goes
// to the nearest centroid in L2 (the first of equals), as histogram::nearest does on the CPU.
#extension GL_GOOGLE_include_directive : require
#include "constants.glsl"
layout(local_size_x = 64) in;

layout(std430, binding = 0) readonly buffer Rows { float rows[]; };
layout(std430, binding = 1) readonly buffer Packing { float packing[]; };
layout(std430, binding = 2) readonly buffer Centroids { float centroids[]; };
layout(std430, binding = 3) writeonly buffer Ids { uint ids[]; };

layout(push_constant) uniform Push {
    uvec4 job;  // x: rows, y: bins B, z: packed dimension P, w: clusters N
} pc;

void main() {
    uint r = gl_GlobalInvocationID.x;
    if (r >= pc.job.x) return;
    uint b = pc.job.y, p = pc.job.z;
    float packed[HIST_MAX_PACKED];
    for (uint d = 0u; d < p; d++) packed[d] = 0.0;
    for (uint k = 0u; k < b; k++) {
        float x = rows[r * b + k];
        for (uint d = 0u; d < p; d++) packed[d] += x * packing[k * p + d];
    }
    uint best = 0u;
    float best_d = 1.0 / 0.0;
    for (uint c = 0u; c < pc.job.w; c++) {
        float dist = 0.0;
        for (uint d = 0u; d < p; d++) {
            float t = centroids[c * p + d] - packed[d];
            dist += t * t;
        }
        if (dist < best_d) {
            best_d = dist;
            best = c;
        }
    }
    ids[r] = best;
}
