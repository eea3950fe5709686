#version 460
// The LAO kernel before issue 18 (per-sample brick and border tests, pow per sample), kept only
// so that `cao-xr bench lao --kernel both` measures the current one against it in one run.
#extension GL_GOOGLE_include_directive : require

layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

layout(std430, binding = 0) readonly buffer Opacity { float opacity[]; };
layout(std430, binding = 1) readonly buffer Dirs { vec4 dirs[]; };
layout(std430, binding = 2) writeonly buffer Ao { float ao[]; };
// Bit v set: no voxel within reach of v's rays (plus the trilinear footprint) has O > 0, so every
// transmittance is 1 and A(v) = KM / KM = 1 exactly.
layout(std430, binding = 3) readonly buffer Clear { uint clear_bits[]; };
layout(std430, binding = 4) readonly buffer Bricks { uint brick_occupied[]; };

layout(push_constant) uniform Push {
    ivec4 dims;
    uint rays;
    uint steps;
    float exponent;
    uint z0;
    uint z1;
} pc;

#include "opacity.glsl"
#include "lao_old.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + ivec3(0, 0, int(pc.z0));
    if (any(greaterThanEqual(v, pc.dims.xyz)) || v.z >= int(pc.z1)) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    bool clear = ((clear_bits[i >> 5] >> (i & 31)) & 1u) != 0u;
    ao[i] = clear ? 1.0 : lao_voxel(v);
}
