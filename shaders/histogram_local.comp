#version 460
#extension GL_EXT_buffer_reference : require
// Local histograms of the unclipped volume (Ropinski et al., eq. 2), one row per voxel:
// LH_k(v) = sum of w / W over the in-grid members of S_r whose shade (bin, with the structure
// folded in: src/ao/histogram.rs Shades) is k. The voxels are a range (base + row) or a list
// (the clustering's training sample). A row has one entry per shade, however many there are:
// the sums go straight into it, in the order of S_r. With the two hemispheres a voxel has two
// rows, H_f's then H_b's, each over its own W_h (docs/design.md); a flat voxel's are both S_r's.
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_16bit_storage : require
#include "constants.glsl"
layout(local_size_x = 64) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
// Each voxel's shade, a 16-bit word.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Bins { uint16_t bins[]; };
layout(std430, binding = 1) readonly buffer Neighbours { vec4 neighbours[]; };
layout(std430, binding = 2) readonly buffer List { uint list[]; };
layout(std430, binding = 3) buffer Rows { float rows[]; };
#define SPLIT_BINDING 4
#include "histogram_split.glsl"

layout(push_constant) uniform Push {
    Bins bins_buf;
    uvec2 addresses_pad;   // the block below starts 16-aligned
    ivec4 dims;   // w: number of neighbours
    uvec4 job;    // x: rows, y: shades, z: first voxel of a range (with a list: its first entry), w: 1 = voxels from the list
} pc;
#define bins pc.bins_buf.bins

// The shades, a specialization constant (src/ao/histogram_gpu.rs): up to PRIVATE_SHADES a
// voxel's sums are added in an array of its own and written once (on lavapipe 1.4x faster
// than adding into the rows, each access of which a CPU renderer makes lane by lane behind a
// bounds test); 0 past that: added in the rows.
layout(constant_id = 0) const uint S = 0u;
float h[2u * S + 1u];

void main() {
    uint r = gl_GlobalInvocationID.x;
    if (r >= pc.job.x) return;
    uint i = pc.job.w == 1u ? list[pc.job.z + r] : pc.job.z + r;
    ivec3 v = ivec3(int(i) % pc.dims.x, (int(i) / pc.dims.x) % pc.dims.y,
                    int(i) / (pc.dims.x * pc.dims.y));
    uint shades = pc.job.y;
    uint base = (split_on != 0u ? 2u * r : r) * shades;
    vec3 d;
    bool split = split_at(v, pc.dims.xyz, d);
    uint back = base + shades;
    if (S > 0u) {
        for (uint k = 0u; k < 2u * S; k++) h[k] = 0.0;
    } else {
        for (uint k = 0u; k < (split ? 2u : 1u) * shades; k++) rows[base + k] = 0.0;
    }
    // One loop for every voxel, at the border or not, split or not: a CPU renderer runs every
    // branch of a workgroup whichever its lanes take, so separate loops would each cost the
    // whole. The members are added in the order of S_r either way.
    float total_f = 0.0, total_b = 0.0;
    int row = pc.dims.x, slice = pc.dims.x * pc.dims.y;
    int i0 = v.x + row * v.y + slice * v.z;
    for (int n = 0; n < pc.dims.w; n++) {
        vec4 nb = neighbours[n];
        ivec3 o = ivec3(nb.xyz);
        bool b = split && in_back(o, d);
        // Adding 0 changes neither total.
        total_b += b ? nb.w : 0.0;
        total_f += b ? 0.0 : nb.w;
        ivec3 u = v + o;
        if (all(greaterThanEqual(u, ivec3(0))) && all(lessThan(u, pc.dims.xyz))) {
            uint k = uint(bins[i0 + o.x + row * o.y + slice * o.z]);
            if (S > 0u) h[(b ? S : 0u) + k] += nb.w;
            else rows[(b ? back : base) + k] += nb.w;
        }
    }
    if (split) {
        float sf = total_f > 0.0 ? 1.0 / total_f : 0.0, sb = total_b > 0.0 ? 1.0 / total_b : 0.0;
        for (uint k = 0u; k < shades; k++) {
            rows[base + k] = (S > 0u ? h[k] : rows[base + k]) * sf;
            rows[back + k] = (S > 0u ? h[S + k] : rows[back + k]) * sb;
        }
        return;
    }
    if (S > 0u)
        for (uint k = 0u; k < shades; k++) rows[base + k] = h[k];
    if (split_on != 0u) {
        // A flat voxel's H_b is its H_f: its second row is only marked (its first entry
        // negative), and the clustering takes the first row for it (src/ao/histogram_gpu.rs).
        rows[back] = -1.0;
        for (uint k = 1u; k < shades; k++) rows[back + k] = 0.0;
    }
}
