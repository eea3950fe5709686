#version 460
#extension GL_EXT_buffer_reference : require
// Local-histogram AO (Ropinski et al.) for every voxel of a box, as docs/design.md defines it:
// the direct sums over S_r of w q (openness A = 1 - sum w q / W) and of w q rgb (the bleeding
// colour E = sum w q rgb / sum w q), q = the clip coverage times the bin's opacity; or the
// clustered values of the voxel's cluster. As an AO method of CAO it writes, per category,
// a (clipped) -> A = 1 and no colour, c (unaffected) -> the precomputed values, b -> the sums.
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Q { uint16_t q[]; };
// Each voxel's shade, and with clusters its (front) cluster: 16-bit words.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Bins { uint16_t bins[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Mask { uint mask[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer PreA { uint16_t pre_a[]; };
// E of the unclipped volume, held without clusters (with them it is the voxel's cluster's).
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer PreE { uint pre_e[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer OutA { uint16_t out_a[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer OutE { uint out_e[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Ids { uint16_t ids[]; };
// The shade table: per shade (a bin with the structure folded in: src/ao/histogram.rs Shades),
// rgb and the opacity a (unused here: q already holds it).
layout(std430, binding = 2) readonly buffer BinTable { vec4 bin_table[]; };
// S_r: offset xyz, and the weight w / W.
layout(std430, binding = 3) readonly buffer Neighbours { vec4 neighbours[]; };
// Per cluster, for the current TF: rgb = E, a = A.
layout(std430, binding = 10) readonly buffer Clusters { vec4 clusters[]; };
#define SPLIT_BINDING 11
#include "histogram_split.glsl"
// One bit per brick of 2^HIST_BRICK_SHIFT voxels: no voxel within S_r's reach (a box) of any of
// its voxels has q > 0 under this TF (src/ao/histogram.rs clear_bricks; clipping only lowers q).
layout(std430, binding = 12) readonly buffer ClearBricks { uint clear_bricks[]; };

layout(push_constant) uniform Push {
    Q q_buf;
    Bins bins_buf;
    Mask mask_buf;
    PreA pre_a_buf;
    PreE pre_e_buf;
    OutA out_a_buf;
    OutE out_e_buf;
    Ids ids_buf;
    ivec4 dims;     // w: number of neighbours
    ivec4 box_min;  // w: mode (0: direct sums, no mask; 1: CAO by category; 2: naive, a -> 1;
                    //          3: restore the precomputed values; 4: the clustered values;
                    //          5: the precomputed E alone)
                    //    + 8 where the precomputed values are the clusters'
    ivec4 box_max;  // exclusive; w: where the box's V_PAO starts in pre_a (staged boxes)
    ivec4 reach;    // xyz: S_r's largest offset per axis; w: where voxel 0 of q lies in the
                    // buffer (the z-slices CAO holds: src/ao/cao.rs Cao::clipped_stride)
} pc;
#define q pc.q_buf.q
#define bins pc.bins_buf.bins
#define mask pc.mask_buf.mask
#include "mask.glsl"
#define pre_a pc.pre_a_buf.pre_a
#include "staged.glsl"
#define pre_e pc.pre_e_buf.pre_e
#define out_a pc.out_a_buf.out_a
#define out_e pc.out_e_buf.out_e
#define ids pc.ids_buf.ids
#define AO_WORDS out_a
#define AO_TABLE_BINDING 13
#include "ao_pool.glsl"

void direct(ivec3 v, out float a, out vec3 e) {
    float occ = 0.0;
    vec3 rgb = vec3(0.0);
    // The front hemisphere H_f, members with o . Δ <= 0, where the gradient is steep enough;
    // total: its share of W (out-of-grid members included).
    vec3 d;
    bool split = split_at(v, pc.dims.xyz, d);
    float total = 0.0;
    // Away from the border every member is in the grid: no test per member. The sum runs in
    // the same order either way, so a region's values equal the whole volume's bit for bit.
    bool inside = all(greaterThanEqual(v, pc.reach.xyz)) && all(lessThan(v + pc.reach.xyz, pc.dims.xyz));
    int row = pc.dims.x, slice = pc.dims.x * pc.dims.y;
    int i0 = v.x + row * v.y + slice * v.z;
    // In a clear brick every w q is 0: the loop would leave occ = 0 and rgb = 0 (A = 1, E = 0),
    // so it does not run.
    ivec3 bricks = (pc.dims.xyz + (1 << HIST_BRICK_SHIFT) - 1) >> HIST_BRICK_SHIFT;
    ivec3 b = v >> HIST_BRICK_SHIFT;
    int bi = b.x + bricks.x * (b.y + bricks.y * b.z);
    bool clear = (clear_bricks[bi >> 5] & (1u << (bi & 31))) != 0u;
    int members = clear ? 0 : pc.dims.w;
    for (int n = 0; n < members; n++) {
        vec4 nb = neighbours[n];
        ivec3 o = ivec3(nb.xyz);
        if (split) {
            if (in_back(o, d)) continue;
            total += nb.w;
        }
        if (!inside) {
            ivec3 u = v + o;
            if (any(lessThan(u, ivec3(0))) || any(greaterThanEqual(u, pc.dims.xyz))) continue;
        }
        int j = i0 + o.x + row * o.y + slice * o.z;
        float wq = nb.w * unorm16_value(uint(q[j + pc.reach.w]));
        occ += wq;
        // A transparent member adds nothing (0 to each sum): its shade is not read, which on a
        // CPU renderer spares its lane two reads.
        if (wq > 0.0) rgb += wq * bin_table[uint(bins[j])].rgb;
    }
    a = 1.0 - (split ? (total > 0.0 ? occ / total : 0.0) : occ);
    e = occ > 0.0 ? rgb / occ : vec3(0.0);
}

// The precomputed E: the voxel's (front) cluster's, as the clustered precompute's word, or the
// direct sums' held in pre_e.
uint precomputed_e(int i, bool clustered) {
    return clustered ? packUnorm4x8(vec4(clusters[uint(ids[i])].rgb, 1.0)) : pre_e[i];
}

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    int mode = pc.box_min.w % 8;
    bool clustered = pc.box_min.w >= 8;
    if (mode == 4) {
        // V_PAO from the front hemisphere's cluster, with hemispheres (its E is the cluster's,
        // read where it is restored).
        ao_store(v, i, pc.dims.xyz, unorm16_word(clusters[uint(ids[i])].a));
        return;
    }
    if (mode == 5) {
        out_e[i] = precomputed_e(i, clustered);
        return;
    }
    uint category = mode == 0 ? 1u : mask_get(i);
    if (mode == 3 || (mode == 1 && category == 2u)) {
        ao_store(v, i, pc.dims.xyz, uint(pre_a[staged_index(v)]));
        out_e[i] = precomputed_e(i, clustered);
    } else if (category == 0u) {
        ao_store(v, i, pc.dims.xyz, AO_OPEN);
        out_e[i] = packUnorm4x8(vec4(0.0, 0.0, 0.0, 1.0));
    } else {
        float a;
        vec3 e;
        direct(v, a, e);
        ao_store(v, i, pc.dims.xyz, unorm16_word(a));
        out_e[i] = packUnorm4x8(vec4(e, 1.0));
    }
}
