#version 460
#extension GL_EXT_buffer_reference : require
// SH visibility, step 2: per SH voxel, visibility in N jittered directions (absorption-only marches
// through the pyramid with growing steps, or through level 0 only), projected on SH bands 0-1 or
// 0-3 and packed as snorm8 (coefficient / Y_0). Modes: 0 computes every voxel of the box; 1 (the
// clip-aware update) computes the voxels within the tools' SH dilation and copies the precomputed
// value elsewhere; 2 copies the precomputed value (restore). See src/ao/sh.rs.
#extension GL_GOOGLE_include_directive : require
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Pyramid { float pyr[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Pre { uint pre[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer Out { uint sh_out[]; };
layout(std430, binding = 1) readonly buffer Levels { ivec4 levels[]; };   // xyz dims, w offset
layout(std430, binding = 2) readonly buffer Dirs { vec4 dirs[]; };        // index units per mm
layout(std430, binding = 3) readonly buffer Basis { float basis[]; };     // Y_k of each direction

layout(push_constant) uniform Push {
    Pyramid pyr_buf;
    Pre pre_buf;
    Out sh_out_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;       // xyz: SH volume dims, w: coefficient groups (1 or 4)
    ivec4 box_min;    // w: number of tools
    ivec4 box_max;    // exclusive; w: mode
    vec4 scale;       // xyz: full-resolution voxels per SH voxel, w: h0 (mm)
    uvec4 march;      // x: N directions, y: patterns, z: top level, w: steps per level (0: flat)
    vec4 extent;      // xyz: full-resolution dims, w: ray length (mm)
} pc;
#define pyr pc.pyr_buf.pyr
#define pre pc.pre_buf.pre
#define sh_out pc.sh_out_buf.sh_out

#define CLIP_SET 0
#define CLIP_TOOLS_BINDING 6
#define CLIP_MAPS_BINDING 7
#define CLIP_TOOL_COUNT pc.box_min.w
#include "clip.glsl"

#include "constants.glsl"

float cell(int level, ivec3 q) {
    ivec4 l = levels[level];
    if (any(lessThan(q, ivec3(0))) || any(greaterThanEqual(q, l.xyz))) return 0.0;
    return pyr[l.w + q.x + l.x * (q.y + l.y * q.z)];
}

// Trilinear opacity of `level` at full-resolution index point p (cell centres at (I + 0.5) 2^l).
float sample_level(int level, vec3 p) {
    vec3 c = p / float(1 << level) - 0.5;
    vec3 fl = floor(c);
    vec3 f = c - fl;
    ivec3 q = ivec3(fl);
    float x00 = mix(cell(level, q), cell(level, q + ivec3(1, 0, 0)), f.x);
    float x10 = mix(cell(level, q + ivec3(0, 1, 0)), cell(level, q + ivec3(1, 1, 0)), f.x);
    float x01 = mix(cell(level, q + ivec3(0, 0, 1)), cell(level, q + ivec3(1, 0, 1)), f.x);
    float x11 = mix(cell(level, q + ivec3(0, 1, 1)), cell(level, q + ivec3(1, 1, 1)), f.x);
    return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
}

// Transmittance from x along a direction (index units per mm) up to the ray length.
float visibility(vec3 x, vec3 dir) {
    float h = pc.scale.w;
    int level = 0;
    uint n = 0u;
    float t = 0.0;
    float trans = 1.0;
    for (int i = 0; i < 4096; i++) {
        if (pc.march.w > 0u && n == pc.march.w && level < int(pc.march.z)) {
            level++;
            h *= 2.0;
            n = 0u;
        }
        t += h;
        if (t > pc.extent.w) break;
        n++;
        vec3 p = x + t * dir;
        // Once beyond the grid by more than a top-level cell, every later sample reads zeros.
        float pad = float(1 << int(pc.march.z));
        if (any(lessThan(p, vec3(-pad))) || any(greaterThan(p, pc.extent.xyz + pad))) break;
        trans *= 1.0 - sample_level(level, p);
        if (trans < SH_T_MIN) break;
    }
    return trans;
}

uint pattern_of(uint i) {
    // lowbias32 (Wellons): a well-mixed, cheap integer hash; src/ao/sh.rs has its twin.
    i ^= i >> 16; i *= 0x7feb352du; i ^= i >> 15; i *= 0x846ca68bu; i ^= i >> 16;
    return i % pc.march.y;
}

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int n = pc.dims.x * pc.dims.y * pc.dims.z;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    int groups = pc.dims.w;
    vec3 x = (vec3(v) + 0.5) * pc.scale.xyz;
    int mode = pc.box_max.w;
    if (mode == 2 || (mode == 1 && !sh_affected_index(x))) {
        for (int g = 0; g < groups; g++) sh_out[g * n + i] = pre[g * n + i];
        return;
    }
    float acc[16];
    for (int k = 0; k < 16; k++) acc[k] = 0.0;
    uint count = pc.march.x;
    uint first = pattern_of(uint(i)) * count;
    for (uint d = first; d < first + count; d++) {
        float vis = visibility(x, dirs[d].xyz);
        if (vis == 0.0) continue;
        for (int k = 0; k < 4 * groups; k++) acc[k] += vis * basis[d * 16u + uint(k)];
    }
    float norm = 1.0 / (float(count) * Y0);
    for (int g = 0; g < groups; g++) {
        vec4 c = vec4(acc[4 * g], acc[4 * g + 1], acc[4 * g + 2], acc[4 * g + 3]) * norm;
        sh_out[g * n + i] = packSnorm4x8(c);
    }
}
