#version 460
// CAO per frame, step 0: voxels the previous frame's tools touched go back to the unclipped state
// (O_c = O, AO = V_PAO, category c) before this frame's tools are applied.
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

layout(std430, binding = 0) readonly buffer Opacity { float opacity[]; };
layout(std430, binding = 1) writeonly buffer Clipped { float clipped[]; };
layout(std430, binding = 2) writeonly buffer Mask { uint mask[]; };
layout(std430, binding = 3) readonly buffer Pao { float pao[]; };
layout(std430, binding = 4) writeonly buffer Ao { float ao[]; };

layout(push_constant) uniform Push {
    ivec4 dims;
    ivec4 box_min;
    ivec4 box_max;   // exclusive
} pc;

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    clipped[i] = opacity[i];
    mask[i] = 2u;
    ao[i] = pao[i];
}
