#version 460
// CAO per frame, step 2: the AO of every voxel of a box from its category: a (clipped) -> 1,
// c (unaffected) -> the precomputed V_PAO, b -> LAO recomputed on the clipped opacity O_c.
// With `naive` set, c voxels are recomputed too (the full-LAO baseline).
#extension GL_GOOGLE_include_directive : require

#include "constants.glsl"
#include "lao_sample.glsl"

layout(local_size_x = LAO_GROUP_X, local_size_y = LAO_GROUP_Y, local_size_z = LAO_GROUP_Z) in;

// O_c with its zero border (src/ao/lao.rs LaoLayout), as clip_mask.comp writes it.
layout(std430, binding = 0) readonly buffer Opacity { float opacity[]; };
layout(std430, binding = 1) readonly buffer Samples { LaoSample samples[]; };
layout(std430, binding = 2) writeonly buffer Ao { float ao[]; };
layout(std430, binding = 3) readonly buffer Clear { uint clear_bits[]; };
layout(std430, binding = 4) readonly buffer Mask { uint mask[]; };
layout(std430, binding = 5) readonly buffer Pao { float pao[]; };

layout(push_constant) uniform Push {
    ivec4 dims;
    ivec4 stride;
    uint rays;
    uint steps;
    float exponent;
    uint naive;
    ivec4 box_min;
    ivec4 box_max;   // exclusive
} pc;

#include "opacity.glsl"
#include "lao.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    uint category = mask[i];
    if (category == 0u) {
        ao[i] = 1.0;
    } else if (category == 2u && pc.naive == 0u) {
        ao[i] = pao[i];
    } else {
        // The clear mask comes from the unclipped O; clipping only lowers opacity, so it stays
        // exact for O_c.
        bool clear = ((clear_bits[i >> 5] >> (i & 31)) & 1u) != 0u;
        ao[i] = clear ? 1.0 : lao_voxel(lao_base(v));
    }
}
