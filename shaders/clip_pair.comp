#version 460
// Clip map from the depth peels (src/clip/gpu.rs): pairs the crossings of every texel into the
// clip intervals (in0, out0, in1, out1) with the rule of `intervals` in src/clip/mod.rs. Layers:
// 0 the "nothing before" layer the first peel compares with, 1..4 the front peels (nearest
// first; an empty layer holds EMPTY_IN and so do all after it), 5 the farthest crossing; z in x.
layout(local_size_x = 8, local_size_y = 8) in;

layout(set = 0, binding = 0, rgba32f) readonly uniform image2DArray peels;
layout(std430, set = 0, binding = 1) writeonly buffer Clip { vec4 clip[]; };

layout(push_constant) uniform Push { int res; } pc;

#include "constants.glsl"

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, ivec2(pc.res)))) return;
    float z[4];
    int n = 0;
    for (int k = 0; k < 4; k++) {
        z[k] = imageLoad(peels, ivec3(p, k + 1)).x;
        if (z[k] < EMPTY_IN) n = k + 1;
    }
    // The peels are in depth order; crossings closer than the depth's precision may be out of z
    // order by a rounding error. Sort them, so that no interval is inside out.
    for (int i = 1; i < n; i++) {
        for (int j = i; j > 0 && z[j - 1] > z[j]; j--) {
            float t = z[j];
            z[j] = z[j - 1];
            z[j - 1] = t;
        }
    }
    float last = imageLoad(peels, ivec3(p, 5)).x;
    vec4 c = vec4(EMPTY_IN, EMPTY_OUT, EMPTY_IN, EMPTY_OUT);
    // One crossing, or the third of three, is a grazing ray's: dropped.
    if (n >= 2) c.xy = vec2(z[0], z[1]);
    // Four or more: everything from the third crossing to the farthest is hulled.
    if (n >= 4) c.zw = vec2(z[2], max(z[3], last));
    clip[p.y * pc.res + p.x] = c;
}
