#version 460
#extension GL_EXT_buffer_reference : require
#extension GL_GOOGLE_include_directive : require
// Filtered AO (Ruiz et al.), the separable box statistics: one pass along one axis. Over the
// window [-h, h] along that axis it combines (mean, M2 = sum of squared deviations, min, max) of
// the members, each itself such an aggregate of `count` voxels (1 in pass x, which reads the
// density; the previous passes' box in y and z), with the pairwise update of Chan et al.: f32
// sums of d and d^2 would cancel catastrophically in m2 - mu^2 for nearly homogeneous boxes.
// Members outside the grid count as d = 0. Every output is combined in the same order whatever
// region is dispatched, so a region's values equal the whole volume's bit for bit. The
// statistics are held over a window of z-slices (src/ao/filter_gpu.rs), the density over
// O_c's window (src/ao/cao.rs).
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Density { float density[]; };
// The statistics are 16 bytes per voxel: split into slabs (slabs.glsl).
#include "slabs.glsl"
layout(buffer_reference, std430, buffer_reference_align = 16) buffer Stats { vec4 stats[]; };

layout(push_constant) uniform Push {
    Density density_buf;
    SlabTable src_buf;
    SlabTable dst_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;      // w: axis (0 = x, reading the density; 1 = y, 2 = z)
    ivec4 box_min;   // w: half-width h along the axis
    ivec4 box_max;   // exclusive; w: voxels per member (count)
    ivec4 window;    // x: where voxel 0 of the density lies; y: the first z-slice of the statistics
} pc;
#define density pc.density_buf.density

vec4 member(ivec3 p) {
    if (any(lessThan(p, ivec3(0))) || any(greaterThanEqual(p, pc.dims.xyz))) return vec4(0.0);
    int i = p.x + pc.dims.x * (p.y + pc.dims.y * p.z);
    if (pc.dims.w == 0) {
        float d = density[pc.window.x + i];
        return vec4(d, 0.0, d, d);
    }
    ivec2 at = slab_at(pc.src_buf, p - ivec3(0, 0, pc.window.y), pc.dims.xyz);
    return Stats(pc.src_buf.slab[at.x]).stats[at.y];
}

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    ivec3 step = ivec3(pc.dims.w == 0, pc.dims.w == 1, pc.dims.w == 2);
    int h = pc.box_min.w;
    float count = float(pc.box_max.w);
    vec4 acc = member(v - h * step);
    float na = count;
    for (int k = 1 - h; k <= h; k++) {
        vec4 m = member(v + k * step);
        float n = na + count;
        float delta = m.x - acc.x;
        acc.x += delta * (count / n);
        acc.y += m.y + delta * delta * (na * count / n);
        acc.zw = vec2(min(acc.z, m.z), max(acc.w, m.w));
        na = n;
    }
    ivec2 at = slab_at(pc.dst_buf, v - ivec3(0, 0, pc.window.y), pc.dims.xyz);
    Stats(pc.dst_buf.slab[at.x]).stats[at.y] = acc;
}
