#version 460
// Full LAO precompute over a slab of z-slices [z0, z1) of the volume.
#extension GL_GOOGLE_include_directive : require


#include "constants.glsl"
#include "lao_sample.glsl"

layout(local_size_x = LAO_GROUP_X, local_size_y = LAO_GROUP_Y, local_size_z = LAO_GROUP_Z) in;

// O with its zero border (src/ao/lao.rs LaoLayout).
layout(std430, binding = 0) readonly buffer Opacity { float opacity[]; };
layout(std430, binding = 1) readonly buffer Samples { LaoSample samples[]; };
layout(std430, binding = 2) writeonly buffer Ao { float ao[]; };
// Bit v set: no voxel within reach of v's rays (plus the trilinear footprint) has O > 0, so every
// transmittance is 1 and A(v) = KM / KM = 1 exactly.
layout(std430, binding = 3) readonly buffer Clear { uint clear_bits[]; };

layout(push_constant) uniform Push {
    ivec4 dims;
    ivec4 stride;
    uint rays;
    uint steps;
    float exponent;
    uint z0;
    uint z1;
} pc;

#include "opacity.glsl"
#include "lao.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + ivec3(0, 0, int(pc.z0));
    if (any(greaterThanEqual(v, pc.dims.xyz)) || v.z >= int(pc.z1)) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    bool clear = ((clear_bits[i >> 5] >> (i & 31)) & 1u) != 0u;
    ao[i] = clear ? 1.0 : lao_voxel(lao_base(v));
}
