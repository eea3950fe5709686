#version 460
#extension GL_EXT_buffer_reference : require
// CAO per frame, step 2: the AO of every voxel of a box from its category: a (clipped) -> 1,
// c (unaffected) -> the precomputed V_PAO (staged with the box), b -> LAO recomputed on the clipped opacity O_c.
// With `naive` set, c voxels are recomputed too (the full-LAO baseline).
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"

#include "constants.glsl"
#include "lao_sample.glsl"

layout(local_size_x = LAO_GROUP_X, local_size_y = LAO_GROUP_Y, local_size_z = LAO_GROUP_Z) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
// O_c with its zero border (src/ao/lao.rs LaoLayout), as clip_mask.comp writes it.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Opacity { uint16_t opacity[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer Ao { uint16_t ao[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Clear { uint clear_bits[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Mask { uint mask[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Pao { uint16_t pao[]; };
layout(std430, binding = 1) readonly buffer Samples { LaoSample samples[]; };

layout(push_constant) uniform Push {
    Opacity opacity_buf;
    Ao ao_buf;
    Clear clear_bits_buf;
    Mask mask_buf;
    Pao pao_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;
    ivec4 stride;
    uint rays;
    uint steps;
    float exponent;
    uint naive;
    ivec4 box_min;
    ivec4 box_max;   // exclusive; w: where the box's V_PAO starts in the staged boxes
} pc;
#define opacity pc.opacity_buf.opacity
#define ao pc.ao_buf.ao
#define clear_bits pc.clear_bits_buf.clear_bits
#define mask pc.mask_buf.mask
#include "mask.glsl"
#define pao pc.pao_buf.pao

#include "opacity.glsl"
#include "lao.glsl"
#include "staged.glsl"
#define AO_WORDS ao
#define AO_TABLE_BINDING 6
#include "ao_pool.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    uint category = mask_get(i);
    if (category == 0u) {
        ao_store(v, i, pc.dims.xyz, AO_OPEN);
    } else if (category == 2u && pc.naive == 0u) {
        ao_store(v, i, pc.dims.xyz, uint(pao[staged_index(v)]));
    } else {
        // The clear mask comes from the unclipped O; clipping only lowers opacity, so it stays
        // exact for O_c.
        bool clear = ((clear_bits[i >> 5] >> (i & 31)) & 1u) != 0u;
        ao_store(v, i, pc.dims.xyz, clear ? AO_OPEN : unorm16_word(lao_voxel(lao_base(v))));
    }
}
