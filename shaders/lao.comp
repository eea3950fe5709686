#version 460
#extension GL_EXT_buffer_reference : require
// Full LAO precompute over a slab of z-slices [z0, z1) of the volume.
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"

#include "constants.glsl"
#include "lao_sample.glsl"

layout(local_size_x = LAO_GROUP_X, local_size_y = LAO_GROUP_Y, local_size_z = LAO_GROUP_Z) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
// O with its zero border (src/ao/lao.rs LaoLayout).
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Opacity { uint16_t opacity[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer Ao { uint16_t ao[]; };
// Bit v set: no voxel within reach of v's rays (plus the trilinear footprint) has O > 0, so every
// transmittance is 1 and A(v) = KM / KM = 1 exactly.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Clear { uint clear_bits[]; };
layout(std430, binding = 1) readonly buffer Samples { LaoSample samples[]; };

layout(push_constant) uniform Push {
    Opacity opacity_buf;
    Ao ao_buf;
    Clear clear_bits_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;
    ivec4 stride;
    uint rays;
    uint steps;
    float exponent;
    uint z0;
    uint z1;
} pc;
#define opacity pc.opacity_buf.opacity
#define ao pc.ao_buf.ao
#define clear_bits pc.clear_bits_buf.clear_bits

#include "opacity.glsl"
#include "lao.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + ivec3(0, 0, int(pc.z0));
    if (any(greaterThanEqual(v, pc.dims.xyz)) || v.z >= int(pc.z1)) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    bool clear = ((clear_bits[i >> 5] >> (i & 31)) & 1u) != 0u;
    ao[i] = uint16_t(clear ? AO_OPEN : unorm16_word(lao_voxel(lao_base(v))));
}
