#version 460
#extension GL_EXT_buffer_reference : require
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"
// Filtered AO (Ruiz et al.), the openness of every voxel of a box, exactly as docs/design.md
// defines it: the tangent box's centre from the density gradient, then the cdf (t^beta), gauss
// (Winitzki's erf) or penner estimator from that box's statistics (filter_box.comp), or the
// exact fraction of members no denser than the voxel. As an AO method of CAO it writes, per
// category, a (clipped) -> 1, c (unaffected) -> the precomputed openness, b -> recomputed.
// The statistics are held over a window of z-slices (src/ao/filter_gpu.rs), the density over
// O_c's window (src/ao/cao.rs).
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Density { float density[]; };
// The statistics (filter_box.comp), split into slabs.
#include "slabs.glsl"
layout(buffer_reference, std430, buffer_reference_align = 16) readonly buffer Stats { vec4 stats[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer Ao { uint16_t ao[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Mask { uint mask[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Pre { uint16_t pre[]; };

layout(push_constant) uniform Push {
    Density density_buf;
    SlabTable stats_buf;
    Ao ao_buf;
    Mask mask_buf;
    Pre pre_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;      // w: where voxel 0 of the density lies
    // w: mode (0: every voxel, no mask; 1: CAO by category; 2: naive, a -> 1)
    //    + 4 x estimator (0 cdf, 1 gauss, 2 penner, 3 exact)
    ivec4 box_min;
    ivec4 box_max;   // exclusive; w: where the box's V_PAO starts in `pre` (staged boxes)
    ivec4 hw;        // xyz: half-widths h_a; w: the first z-slice of the statistics
    vec4 spacing;    // xyz: mm per voxel; w: R in mm
} pc;
#define density pc.density_buf.density
#define ao pc.ao_buf.ao
#define mask pc.mask_buf.mask
#include "mask.glsl"
#define pre pc.pre_buf.pre
#include "staged.glsl"
#define AO_WORDS ao
#define AO_TABLE_BINDING 5
#include "ao_pool.glsl"

float d_at(ivec3 p) {
    if (any(lessThan(p, ivec3(0))) || any(greaterThanEqual(p, pc.dims.xyz))) return 0.0;
    return density[pc.dims.w + p.x + pc.dims.x * (p.y + pc.dims.y * p.z)];
}

// Rounds half away from zero, as docs/design.md's centre does.
float round_away(float x) {
    return sign(x) * floor(abs(x) + 0.5);
}

float erf_winitzki(float x) {
    const float a = 0.147;
    float x2 = x * x;
    return sign(x) * sqrt(1.0 - exp(-x2 * (4.0 / 3.14159265358979 + a * x2) / (1.0 + a * x2)));
}

float openness(ivec3 v, float dv) {
    vec3 g = vec3(d_at(v + ivec3(1, 0, 0)) - d_at(v - ivec3(1, 0, 0)),
                  d_at(v + ivec3(0, 1, 0)) - d_at(v - ivec3(0, 1, 0)),
                  d_at(v + ivec3(0, 0, 1)) - d_at(v - ivec3(0, 0, 1))) / (2.0 * pc.spacing.xyz);
    ivec3 c = v;
    float len = length(g);
    if (len > 0.0) {
        vec3 off = vec3(round_away(-pc.spacing.w * g.x / len / pc.spacing.x),
                        round_away(-pc.spacing.w * g.y / len / pc.spacing.y),
                        round_away(-pc.spacing.w * g.z / len / pc.spacing.z));
        c = clamp(v + ivec3(off), ivec3(0), pc.dims.xyz - 1);
    }
    int estimator = pc.box_min.w / 4;
    ivec3 w = 2 * pc.hw.xyz + 1;
    float n = float(w.x * w.y * w.z);
    if (estimator == 3) {
        uint below = 0u;
        for (int z = c.z - pc.hw.z; z <= c.z + pc.hw.z; z++)
            for (int y = c.y - pc.hw.y; y <= c.y + pc.hw.y; y++)
                for (int x = c.x - pc.hw.x; x <= c.x + pc.hw.x; x++)
                    below += uint(d_at(ivec3(x, y, z)) <= dv);
        return float(below) / n;
    }
    ivec2 at = slab_at(pc.stats_buf, c - ivec3(0, 0, pc.hw.w), pc.dims.xyz);
    vec4 s = Stats(pc.stats_buf.slab[at.x]).stats[at.y];
    float lo = s.z, hi = s.w;
    // (mean, M2) from filter_box.comp; a box of one value has that mean and no variance exactly.
    float mu = lo == hi ? lo : s.x;
    float var = lo == hi ? 0.0 : max(s.y / n, 0.0);
    if (estimator == 0) {
        if (dv >= hi) return 1.0;
        if (dv <= lo) return 0.0;
        if (mu >= hi) return 0.0;
        float beta = (mu - lo) / (hi - mu);
        if (beta <= 0.0) return 1.0;
        return pow((dv - lo) / (hi - lo), beta);
    }
    if (var <= 1e-12) return dv >= mu ? 1.0 : 0.0;
    if (estimator == 1) return 0.5 * (1.0 + erf_winitzki((dv - mu) / sqrt(2.0 * var)));
    if (dv <= mu) return 0.0;
    float e = (dv - mu) * (dv - mu);
    return e / (var + e);
}

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    int mode = pc.box_min.w % 4;
    uint category = mode == 0 ? 1u : mask_get(i);
    if (category == 0u) {
        ao_store(v, i, pc.dims.xyz, AO_OPEN);
    } else if (category == 2u && mode == 1) {
        ao_store(v, i, pc.dims.xyz, uint(pre[staged_index(v)]));
    } else {
        ao_store(v, i, pc.dims.xyz, unorm16_word(openness(v, d_at(v))));
    }
}
