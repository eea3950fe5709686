#version 460
// CAO per frame, step 0: voxels the previous frame's tools touched go back to the background state
// before this frame's tools are applied: unclipped (O_c = O, AO = V_PAO, category c), or with a
// probe active, clipped away (O_c = 0, AO = 1, category a).
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

layout(std430, binding = 0) readonly buffer Opacity { float opacity[]; };
layout(std430, binding = 1) writeonly buffer Clipped { float clipped[]; };
layout(std430, binding = 2) writeonly buffer Mask { uint mask[]; };
layout(std430, binding = 3) readonly buffer Pao { float pao[]; };
layout(std430, binding = 4) writeonly buffer Ao { float ao[]; };
// O_c again, inside the zero border the LAO kernel reads (src/ao/lao.rs LaoLayout).
layout(std430, binding = 5) writeonly buffer ClippedPadded { float clipped_padded[]; };

layout(push_constant) uniform Push {
    ivec4 dims;
    ivec4 box_min;   // w: 1 = clipped away
    ivec4 box_max;   // exclusive
    ivec4 stride;    // the padded grid's (origin, row, slice)
} pc;

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    bool away = pc.box_min.w != 0;
    float o = away ? 0.0 : opacity[i];
    clipped[i] = o;
    clipped_padded[pc.stride.x + v.x + pc.stride.y * v.y + pc.stride.z * v.z] = o;
    mask[i] = away ? 0u : 2u;
    ao[i] = away ? 1.0 : pao[i];
}
