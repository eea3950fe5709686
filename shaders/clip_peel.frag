#version 460
// Clip-camera depth peels (src/clip/gpu.rs). Every crossing of a texel's ray with the surface is
// one fragment, keyed by (depth, triangle). Front peel k keeps the crossing with the smallest key
// beyond layer k-1's: the fragment shader discards keys up to the previous layer's, and the depth
// test (LESS, depth cleared to 1) keeps the smallest depth of the rest, the first drawn (smallest
// triangle) among equal depths, as Vulkan tests depth in primitive order. So no crossing is lost
// or counted twice, even where two share a depth (the two sheets at a silhouette fold). Culling
// is off: the winding does not matter. The farthest pass keeps the largest depth (GREATER).
// Layers store (local z, triangle) in RGBA32F (z exactly; triangles up to 2^24 exactly).
layout(set = 0, binding = 1, rgba32f) readonly uniform image2D previous;

layout(push_constant) uniform Push {
    vec2 shift;
    float inv_extent;
    float z_lo;
    float z_scale;
    uint mode;
} pc;

layout(location = 0) in float local_z;
layout(location = 1) flat in uint triangle;
layout(location = 0) out vec4 out_key;

void main() {
    // The depth is a monotonic map of z, recomputed the same way for the previous layer's z.
    float depth = (local_z - pc.z_lo) * pc.z_scale;
    float id = float(triangle);
    if (pc.mode == 0u) {
        vec2 prev = imageLoad(previous, ivec2(gl_FragCoord.xy)).xy;
        float prev_depth = (prev.x - pc.z_lo) * pc.z_scale;
        if (depth < prev_depth || (depth == prev_depth && id <= prev.y)) discard;
    }
    out_key = vec4(local_z, id, 0.0, 0.0);
    gl_FragDepth = depth;
}
