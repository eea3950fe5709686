#version 460
#extension GL_EXT_buffer_reference : require
// CAO per frame, step 1: shadow-test clipping of every voxel of a box with 9 samples (centre and
// corners), 32 more where they disagree. Writes the anti-aliased opacity O_c, the category mask
// (0 = a: clipped away, 1 = b: AO affected by the cut, 2 = c: unaffected) and category counts.
#extension GL_GOOGLE_include_directive : require
#include "unorm16.glsl"
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;

// The volume-sized buffers by address, in binding order (src/gpu/resources.rs
// ComputePipeline::with_addresses): no maxStorageBufferRange limits a volume.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer Opacity { uint16_t opacity[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) writeonly buffer Clipped { uint16_t clipped[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Mask { uint mask[]; };
// The structure of every voxel (src/volume/labels.rs: one byte each, 0 unlabelled), and the
// 256-bit set of protected structures, read where dims.w says some structure is protected.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Labels { uint label_words[]; };
layout(std430, binding = 7) readonly buffer Protect { uint protect_bits[8]; };
layout(std430, binding = 5) buffer Counts { uint counts[]; };
// O and O_c in their two formats (src/ao/cao.rs Cao::clipped_stride): stride.w 1, f32 (the
// filters' density), else 16-bit unorm (unorm16.glsl); the same buffers are bound to both.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer OpacityF { float opacity_f[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer ClippedF { float clipped_f[]; };

layout(push_constant) uniform Push {
    Opacity opacity_buf;
    Clipped clipped_buf;
    Mask mask_buf;
    Labels label_words_buf;
    OpacityF opacity_f_buf;
    ClippedF clipped_f_buf;
    ivec4 dims;      // w: 1 = some structure is protected
    ivec4 box_min;   // w: tool count
    ivec4 box_max;   // exclusive; w: where the box's O starts in the frame's O, in voxels
    ivec4 stride;    // where voxel v of O_c lies: x + v.x + y v.y + z v.z (LAO's zero border);
                     // w: 1 = f32
} pc;
#define opacity pc.opacity_buf.opacity
#define clipped pc.clipped_buf.clipped
#define mask pc.mask_buf.mask
#define MASK_WRITE
#include "mask.glsl"
#define label_words pc.label_words_buf.label_words
#define opacity_f pc.opacity_f_buf.opacity_f
#define clipped_f pc.clipped_f_buf.clipped_f

#define CLIP_SET 0
#define CLIP_TOOLS_BINDING 3
#define CLIP_MAPS_BINDING 4
#define CLIP_TOOL_COUNT pc.box_min.w
#include "clip.glsl"

// 32 fixed anti-aliasing offsets in the voxel's [-1,1]^3 neighbourhood (a scrambled 3D Halton set).
const vec3 AA[32] = vec3[32](
    vec3(-0.875, -0.333, -0.600), vec3(0.125, 0.333, -0.200), vec3(-0.375, -0.778, 0.200),
    vec3(0.625, -0.111, 0.600), vec3(-0.625, 0.556, -0.920), vec3(0.375, -0.556, -0.520),
    vec3(-0.125, 0.111, -0.120), vec3(0.875, 0.778, 0.280), vec3(-0.938, -0.926, 0.680),
    vec3(0.063, -0.259, -0.840), vec3(-0.438, 0.407, -0.440), vec3(0.563, -0.704, -0.040),
    vec3(-0.688, -0.037, 0.360), vec3(0.313, 0.630, 0.760), vec3(-0.188, -0.481, -0.680),
    vec3(0.813, 0.185, -0.280), vec3(-0.813, 0.852, 0.120), vec3(0.188, -0.852, 0.520),
    vec3(-0.313, -0.185, 0.920), vec3(0.688, 0.481, -0.968), vec3(-0.563, -0.630, -0.568),
    vec3(0.438, 0.037, -0.168), vec3(-0.063, 0.704, 0.232), vec3(0.938, -0.407, 0.632),
    vec3(-0.969, 0.259, -0.888), vec3(0.031, 0.926, -0.488), vec3(-0.469, -0.975, -0.088),
    vec3(0.531, -0.309, 0.312), vec3(-0.719, 0.358, 0.712), vec3(0.281, -0.642, -0.728),
    vec3(-0.219, 0.025, -0.328), vec3(0.781, 0.691, 0.072));

// Whether voxel i belongs to a protected structure: the carving tools leave it standing.
bool spared(int i) {
    if (pc.dims.w == 0) return false;
    uint id = (label_words[i >> 2] >> (8 * (i & 3))) & 0xffu;
    return ((protect_bits[id >> 5] >> (id & 31u)) & 1u) != 0u;
}

#include "staged.glsl"

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID) + pc.box_min.xyz;
    if (any(greaterThanEqual(v, pc.box_max.xyz))) return;
    int i = v.x + pc.dims.x * (v.y + pc.dims.y * v.z);
    bool spare = spared(i);
    vec3 c = vec3(v) + 0.5;
    uint visible = 0u;
    uint affected = 0u;
    for (int s = 0; s < 9; s++) {
        vec3 off = s == 0 ? vec3(0.0) : vec3(((s - 1) & 1) != 0 ? 0.5 : -0.5,
                                             ((s - 1) & 2) != 0 ? 0.5 : -0.5,
                                             ((s - 1) & 4) != 0 ? 0.5 : -0.5);
        uint r = clip_test_index(c + off, spare);
        visible += r & 1u;
        affected += (r >> 1) & 1u;
    }
    bool f32 = pc.stride.w != 0;
    int oi = staged_index(v);
    float o = f32 ? opacity_f[oi] : unorm16_value(uint(opacity[oi]));
    bool whole = visible == 9u;
    float oc = whole ? o : 0.0;
    if (visible != 0u && !whole) {
        for (int s = 0; s < 32; s++) {
            uint r = clip_test_index(c + AA[s], spare);
            visible += r & 1u;
            affected += (r >> 1) & 1u;
        }
        oc = o * (float(visible) / 41.0);
    }
    int at = pc.stride.x + v.x + pc.stride.y * v.y + pc.stride.z * v.z;
    if (f32) {
        clipped_f[at] = oc;
    } else {
        // Unclipped, O's own word; else O times the coverage, rounded.
        clipped[at] = whole ? opacity[oi] : uint16_t(unorm16_word(oc));
    }
    uint category = affected == 0u ? 2u : (visible > 0u ? 1u : 0u);
    mask_set(i, category);
    atomicAdd(counts[category], 1u);
}
