#version 460
#extension GL_EXT_buffer_reference : require
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"
// SH visibility, step 1: the expected-opacity pyramid O_0..O_L (Ritschel 2007, src/ao/sh.rs).
// Level 0: the opacity of crossing one voxel, 1 - (1 - O)^(h0 / 1 mm). Level l+1: for each 2^3
// block of level l, the mean over its 12 pairs of face-adjacent (successive) voxels of the product
// of their transparencies - a ray crossing the coarse cell crosses two successive fine cells.
// Children outside the grid are empty (transparency 1), as O is zero outside.
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Opacity { uint16_t opacity[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Pyramid { float pyr[]; };
// O again where it is f32 (stride.w 1: the filters' density), bound to both.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer OpacityF { float opacity_f[]; };

layout(push_constant) uniform Push {
    Opacity opacity_buf;
    Pyramid pyr_buf;
    OpacityF opacity_f_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 src_dims;   // xyz: dims of level l (or of O), w: offset of level l in pyr
    ivec4 dst_dims;   // xyz: dims of the level written, w: its offset in pyr
    float exponent;   // level 0: h0 / 1 mm
    uint level0;      // 1: write level 0 from O
    ivec4 stride;     // level 0: voxel v of O lies at x + v.x + y v.y + z v.z (LAO's zero border);
                      // w: 1 = f32
} pc;
#define opacity pc.opacity_buf.opacity
#define pyr pc.pyr_buf.pyr
#define opacity_f pc.opacity_f_buf.opacity_f

float child_t(ivec3 q) {
    if (any(greaterThanEqual(q, pc.src_dims.xyz))) return 1.0;
    return 1.0 - pyr[pc.src_dims.w + q.x + pc.src_dims.x * (q.y + pc.src_dims.y * q.z)];
}

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID);
    if (any(greaterThanEqual(v, pc.dst_dims.xyz))) return;
    int dst = pc.dst_dims.w + v.x + pc.dst_dims.x * (v.y + pc.dst_dims.y * v.z);
    if (pc.level0 != 0u) {
        int c = pc.stride.x + v.x + pc.stride.y * v.y + pc.stride.z * v.z;
        float o = pc.stride.w != 0 ? opacity_f[c] : unorm16_value(uint(opacity[c]));
        pyr[dst] = o <= 0.0 ? 0.0 : (o >= 1.0 ? 1.0 : 1.0 - pow(1.0 - o, pc.exponent));
        return;
    }
    ivec3 b = 2 * v;
    float t[8];
    for (int c = 0; c < 8; c++) t[c] = child_t(b + ivec3(c & 1, (c >> 1) & 1, (c >> 2) & 1));
    float s = (t[0] * t[1] + t[2] * t[3] + t[4] * t[5] + t[6] * t[7])     // pairs along x
            + (t[0] * t[2] + t[1] * t[3] + t[4] * t[6] + t[5] * t[7])     // along y
            + (t[0] * t[4] + t[1] * t[5] + t[2] * t[6] + t[3] * t[7]);    // along z
    pyr[dst] = 1.0 - s / 12.0;
}
