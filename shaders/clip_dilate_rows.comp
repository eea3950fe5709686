#version 460
// Dilation map, first step (src/clip/gpu.rs): per clip-map row, the first and last texel that
// holds an interval (first > last: none). clip_dilate.comp visits only those columns: the others
// are empty and cannot move a hull, so skipping them changes no bit of the result.
layout(local_size_x = 64) in;

layout(std430, set = 0, binding = 0) readonly buffer Clip { vec4 clip[]; };
layout(std430, set = 0, binding = 1) writeonly buffer Rows { ivec2 rows[]; };

layout(push_constant) uniform Push {
    int res;
    int reach;
} pc;

void main() {
    int y = int(gl_GlobalInvocationID.x);
    if (y >= pc.res) return;
    int first = pc.res;
    int last = -1;
    for (int x = 0; x < pc.res; x++) {
        vec4 c = clip[y * pc.res + x];
        if (c.x <= c.y) {
            first = min(first, x);
            last = x;
        }
    }
    rows[y] = ivec2(first, last);
}
