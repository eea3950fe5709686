#version 460
// Clip-camera depth peels (src/clip/gpu.rs): the clip camera is orthographic over tool-local
// x, y in [-extent, extent] and looks along local +Z. The mesh comes as a flat triangle list
// (three vec4 corners per triangle, pulled by gl_VertexIndex); local z travels to the fragment
// stage unchanged so the peels store the surface's depth in tool units.
layout(std430, set = 0, binding = 0) readonly buffer Corners { vec4 corners[]; };

layout(push_constant) uniform Push {
    vec2 shift;         // the sample offset in local units: pixel centres are the sample points
    float inv_extent;   // local x, y -> NDC
    float z_lo;         // depth = (z - z_lo) * z_scale, inside (0, 1) for the whole mesh
    float z_scale;
    uint mode;          // 0: front peel, 1: farthest crossing
} pc;

// Every front peel must rasterise the same fragments with the same interpolated z, bit for bit: a
// peel skips the fragments up to the previous layer's by comparing against its stored z. They all
// run one pipeline on the same data, which gives that; `invariant` says so for z (gl_Position is
// left undecorated: SPIR-V allows no Invariant on gl_PerVertex members).
layout(location = 0) invariant out float local_z;
// The triangle, to order crossings of equal depth (a fold at a silhouette).
layout(location = 1) flat out uint triangle;

void main() {
    // Every triangle is rasterised with the same winding on screen (corners 1 and 2 swapped
    // where it would be clockwise). Vulkan only asks that of two triangles on either side of an
    // edge exactly one covers a sample on it; a rasteriser may decide by the edge's direction as
    // wound, and the front and back sheets folding over at a silhouette are wound oppositely on
    // screen, so a sample on the fold edge could get one crossing. With one winding, both sheets
    // decide alike: a grazing ray gets an even number of crossings, never one that pairs with a
    // surface across a hole. (lavapipe normalises the winding itself; this does not rely on it.)
    int tri = gl_VertexIndex / 3;
    int k = gl_VertexIndex - 3 * tri;
    vec2 a = corners[3 * tri].xy;
    vec2 b = corners[3 * tri + 1].xy;
    vec2 c = corners[3 * tri + 2].xy;
    if ((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y) < 0.0 && k != 0) k = 3 - k;
    vec3 v = corners[3 * tri + k].xyz;
    local_z = v.z;
    triangle = uint(tri);
    gl_Position = vec4((v.xy - pc.shift) * pc.inv_extent, (v.z - pc.z_lo) * pc.z_scale, 1.0);
}
