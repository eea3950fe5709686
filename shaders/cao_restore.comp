#version 460
#extension GL_EXT_buffer_reference : require
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"
// CAO per frame, step 0: voxels the previous frame's tools touched go back to the background state
// before this frame's tools are applied: unclipped (O_c = O, AO = V_PAO, category c), or with a
// probe active, clipped away (O_c = 0, AO = 1, category a). Where CAO holds only the slices of O_c
// a frame's LAO update reads, filled anew each frame, O_c is not written here.
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Opacity { uint16_t opacity[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer Clipped { uint16_t clipped[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Mask { uint mask[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Pao { uint16_t pao[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer Ao { uint16_t ao[]; };
// O and O_c in their two formats (src/ao/cao.rs Cao::clipped_stride): stride.w 1, f32 (the
// filters' density), else 16-bit unorm (unorm16.glsl); the same buffers are bound to both.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer OpacityF { float opacity_f[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer ClippedF { float clipped_f[]; };

layout(push_constant) uniform Push {
    Opacity opacity_buf;
    Clipped clipped_buf;
    Mask mask_buf;
    Pao pao_buf;
    Ao ao_buf;
    OpacityF opacity_f_buf;
    ClippedF clipped_f_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;
    ivec4 box_min;   // w: bit 0 = clipped away, bit 1 = leave O_c alone
    ivec4 box_max;   // exclusive; w: where the box's O and V_PAO start in the frame's staged
                     // boxes, in voxels
    ivec4 stride;    // where voxel v of O_c lies: x + v.x + y v.y + z v.z (LAO's zero border);
                     // w: 1 = f32
} pc;
#define opacity pc.opacity_buf.opacity
#define clipped pc.clipped_buf.clipped
#define mask pc.mask_buf.mask
#define MASK_WRITE
#include "mask.glsl"
#define pao pc.pao_buf.pao
#define ao pc.ao_buf.ao
#define opacity_f pc.opacity_f_buf.opacity_f
#define clipped_f pc.clipped_f_buf.clipped_f

#include "staged.glsl"
#define AO_WORDS ao
#define AO_TABLE_BINDING 7
#include "ao_pool.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    bool away = (pc.box_min.w & 1) != 0;
    int c = pc.stride.x + v.x + pc.stride.y * v.y + pc.stride.z * v.z;
    int o = staged_index(v);
    if ((pc.box_min.w & 2) != 0) {
        // O_c is the frame's window (src/ao/cao.rs Cao::windowed).
    } else if (pc.stride.w != 0) {
        clipped_f[c] = away ? 0.0 : opacity_f[o];
    } else {
        clipped[c] = away ? uint16_t(0) : opacity[o];
    }
    mask_set(i, away ? 0u : 2u);
    ao_store(v, i, pc.dims.xyz, away ? AO_OPEN : uint(pao[o]));
}
