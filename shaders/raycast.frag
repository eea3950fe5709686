#version 460
// Stereo ray caster: front-to-back compositing through the volume with early termination.
// Shading (docs/design.md, "Shading"): Blinn-Phong from the data's gradient with a headlight at
// the head (or a light fixed in the world), the AO multiplying the ambient term and a share of the
// diffuse one,
//   C = C_tf * (ka * AO + kd * (1 - s + s * AO) * |n.l|) + ks * (n.h)^p  (+ w * E_sh),
// where E_sh = sum_k V_k L_k is the environment light seen through the SH visibility volume
// (Ritschel), and with the local-histogram method C_tf bleeds towards the neighbourhood's colour
// E, which the Henyey-Greenstein phase function also scatters towards the eye. Where a tool
// cut the volume, the tool's surface normal lights a thin layer (the cut face).
// Segments are pre-integrated over (front, back) scalar pairs; the start is jittered by blue
// noise. Opacity is corrected per mm; depth is written where the ray enters visible material, so
// later geometry (tools, hands) is depth-correct.
#extension GL_GOOGLE_include_directive : require
// [[unroll]] on the fixed-length loops of the features that are on: lavapipe (gallivm) ends
// every loop of an invocation after 65,535 iterations in all (docs/design.md).
#extension GL_EXT_control_flow_attributes : require
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_buffer_reference_uvec2 : require
#include "frame.glsl"
#include "unorm16.glsl"
#include "ao_pool.glsl"
// The scalars as stored (src/render/mod.rs scalar_storage: integers as unorm texels); value_map
// and the gradient threshold surface.x are in those units.
layout(set = 0, binding = 1) uniform sampler3D scalars;
// V_AO itself, by address (no copy into an image, no size limit): the method's 16-bit words.
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer AoWords { uint16_t ao_words[]; };
// V_AO's brick table (src/ao/pool.rs, ao_pool.glsl), with RAY_AO_BRICKS.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer AoTableRef { uint t[]; };
// The local-histogram method's bleeding colour E (rgb), RGBA8 words by address; read when
// bleeding.x = W > 0 or bleeding.y > 0.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer BleedingWords { uint e_words[]; };
layout(set = 0, binding = 3) uniform sampler1D tf_lut;
// SH visibility, coefficients 4g..4g+3 in texture g, snorm8 of V_k / Y_0 (src/ao/sh.rs).
layout(set = 0, binding = 6) uniform sampler3D sh0;
layout(set = 0, binding = 7) uniform sampler3D sh1;
layout(set = 0, binding = 8) uniform sampler3D sh2;
layout(set = 0, binding = 9) uniform sampler3D sh3;
// var_s of variance opacity modulation (data units squared), when VARIANCE; the inset's boxes'
// at full resolution (flag INSET).
layout(set = 0, binding = 10) uniform sampler3D variance;
layout(set = 0, binding = 23) uniform sampler3D inset_variance_0;
layout(set = 0, binding = 27) uniform sampler3D inset_variance_1;
layout(set = 0, binding = 31) uniform sampler3D inset_variance_2;
// Pre-integrated TF: premultiplied colour and opacity of a step from front to back value.
layout(set = 0, binding = 12) uniform sampler2D preint;
// Blue-noise thresholds in (0, 1), tiled over the screen (src/render/blue_noise.rs).
layout(set = 0, binding = 13) uniform sampler2D blue_noise;
// Per brick of 2^RAY_BRICK_SHIFT voxels: 1 where every value a sample can read classifies as
// transparent (src/render/empty_space.rs).
layout(set = 0, binding = 14) uniform sampler3D empty_bricks;
// Where in a pre-integrated step its light comes from: 0 at the front sample, 1 at the back.
layout(set = 0, binding = 15) uniform sampler2D preint_at;
// The structure id of every voxel (R8 unorm: id / 255; src/volume/labels.rs), when LABELS.
layout(set = 0, binding = 16) uniform sampler3D structure_ids;
// The safety margins' glow intensity (R8 unorm; src/render/mod.rs margin_glow), when GLOW.
layout(set = 0, binding = 17) uniform sampler3D glow;
// Per box of the inset (the volume is shown downsampled around them, each box finer; flag
// RAY_INSET): its scalars, its structure ids (as structure_ids, when LABELS) and its glow from
// the full-resolution margins (when GLOW). A box is chosen per sample, so each box's images
// have their own bindings (src/render/mod.rs INSET_BINDINGS), picked by a branch: an array
// indexed by a lane's box reads one lane's box for all (no non-uniform indexing).
layout(set = 0, binding = 21) uniform sampler3D inset_scalars_0;
layout(set = 0, binding = 25) uniform sampler3D inset_scalars_1;
layout(set = 0, binding = 22) uniform sampler3D inset_structure_ids_0;
layout(set = 0, binding = 26) uniform sampler3D inset_structure_ids_1;
layout(set = 0, binding = 24) uniform sampler3D inset_glow_0;
layout(set = 0, binding = 28) uniform sampler3D inset_glow_1;
layout(set = 0, binding = 29) uniform sampler3D inset_scalars_2;
layout(set = 0, binding = 30) uniform sampler3D inset_structure_ids_2;
layout(set = 0, binding = 32) uniform sampler3D inset_glow_2;
#if MAX_INSETS != 3
#error "the inset_* functions pick one of three boxes"
#endif

#define CLIP_SET 0
#define CLIP_TOOLS_BINDING 4
#define CLIP_MAPS_BINDING 5
#define CLIP_TOOL_COUNT frame.viewport.z
#include "clip.glsl"
// Per brick of the empty-space grid, four to a word (src/clip/bricks.rs): CLIP_BRICK_OPEN where
// no tool hides any sample, 1 + t where tool t is every sample's first hider, CLIP_BRICK_CUT
// where the samples test the maps. Read when CLIPPING and CLIP_BRICKS.
layout(std430, set = 0, binding = 20) readonly buffer ClipBricks {
    uint clip_bricks[];
};

// Which eye (layer of the stereo target) this draw renders, and its pass (src/render/mod.rs
// Foveation): 0, every pixel cast; 1, the coarse pass of a foveated eye, each pixel standing for
// a block of `scale` x `scale` pixels of the eye, whose ray it casts through the block's centre;
// 2, the full pass of a foveated eye: pixels within `radius` (pixels) of `centre` (the gaze or
// the lens centre, src/render/mod.rs fovea_centre) cast as in pass 0, the others take the
// coarse pass's colour and depth, interpolated. `record`: the address of the first eye's
// record, which its casting pass (0, or 1 where foveated) writes (RAY_RECORD) and the second
// eye's reads (RAY_REPROJECT).
layout(push_constant) uniform Eye {
    uint index; uint pass; float scale; float radius; uvec2 record; vec2 centre;
} eye;
// The first eye's record, per pixel of its casting pass (rows of record_size().x): its colour (RGBA8) and the view
// depths (its clip w) where the ray's opacity reached DEPTH_ALPHA and REPROJECT_BACK_ALPHA (0:
// never, or the ray did not end opaque).
layout(buffer_reference, std430, buffer_reference_align = 16) buffer EyeRecord { uvec4 texels[]; };
// The coarse pass's colour and depth, layer = eye; read in pass 2 (else stand-ins, unread).
layout(set = 0, binding = 18) uniform sampler2DArray coarse_color;
layout(set = 0, binding = 19) uniform sampler2DArray coarse_depth;

layout(location = 0) out vec4 out_color;

// Bisections that place a cut face within 1/64 of a step.
const int CUT_BISECTIONS = 6;
const float DEPTH_ALPHA = 0.05;

// Bisections that place an isosurface within 1/256 of a step.
const int ISO_BISECTIONS = 8;

// The features this pipeline is specialised for (RAY_* in src/shader_constants.rs; src/render/mod.rs
// Renderer::pipeline): the code of a feature that is off is not compiled in, which on lavapipe
// is the only way not to pay for it (gallivm runs both sides of every branch).
layout(constant_id = 0) const uint FLAGS = 0u;

bool flag(uint f) { return (FLAGS & f) != 0u; }

// Cubic B-spline of the scalars through eight trilinear fetches (Sigg and Hadwiger, GPU Gems 2
// ch. 20): smooth reconstruction for small volumes and close-ups.
float scalar_tricubic(sampler3D level, vec3 t) {
    vec3 size = vec3(textureSize(level, 0));
    vec3 x = t * size - 0.5;
    vec3 i = floor(x);
    vec3 f = x - i;
    vec3 f2 = f * f;
    vec3 f3 = f2 * f;
    vec3 w0 = (1.0 - 3.0 * f + 3.0 * f2 - f3) / 6.0;
    vec3 w1 = (4.0 - 6.0 * f2 + 3.0 * f3) / 6.0;
    vec3 w2 = (1.0 + 3.0 * f + 3.0 * f2 - 3.0 * f3) / 6.0;
    vec3 w3 = f3 / 6.0;
    vec3 g0 = w0 + w1;
    vec3 g1 = w2 + w3;
    vec3 h0 = (i - 0.5 + w1 / g0) / size;
    vec3 h1 = (i + 1.5 + w3 / g1) / size;
    float r = 0.0;
    [[unroll]] for (int k = 0; k < 8; k++) {
        vec3 h = vec3((k & 1) != 0 ? h1.x : h0.x, (k & 2) != 0 ? h1.y : h0.y, (k & 4) != 0 ? h1.z : h0.z);
        vec3 g = vec3((k & 1) != 0 ? g1.x : g0.x, (k & 2) != 0 ? g1.y : g0.y, (k & 4) != 0 ? g1.z : g0.z);
        r += g.x * g.y * g.z * texture(level, h).r;
    }
    return r;
}

float level_scalar(sampler3D level, vec3 t) {
    return flag(RAY_TRICUBIC) ? scalar_tricubic(level, t) : texture(level, t).r;
}

// The box texture point t lies in (frame.inset_lo/hi; the first where boxes overlap, and the
// finest come first: each holds its level's whole AO there), or -1. In a box the scalars and
// V_AO are its own: the volume at full resolution (or, in a middle level's box, at half),
// cropped with a margin of the AO's reach so that its AO there is that level's whole volume's
// (docs/design.md, "The inset").
int inset_at(vec3 t) {
    if (!flag(RAY_INSET)) return -1;
    [[unroll]] for (int s = 0; s < MAX_INSETS; s++) {
        if (all(greaterThanEqual(t, frame.inset_lo[s].xyz)) && all(lessThan(t, frame.inset_hi[s].xyz))) {
            return s;
        }
    }
    return -1;
}

bool in_inset(vec3 t) {
    return inset_at(t) >= 0;
}

// Box s's texture coordinates of texture point t.
vec3 inset_tex(int s, vec3 t) {
    return t * frame.inset_scale[s].xyz + frame.inset_offset[s].xyz;
}

// Box s's voxels per axis.
ivec3 inset_size(int s) {
    return s == 0 ? textureSize(inset_scalars_0, 0)
         : s == 1 ? textureSize(inset_scalars_1, 0)
                  : textureSize(inset_scalars_2, 0);
}

// Box s's glow and var_s at texture point t (of the shown volume).
float inset_glow_at(int s, vec3 t) {
    return s == 0 ? texture(inset_glow_0, inset_tex(0, t)).r
         : s == 1 ? texture(inset_glow_1, inset_tex(1, t)).r
                  : texture(inset_glow_2, inset_tex(2, t)).r;
}

float inset_variance_at(int s, vec3 t) {
    return s == 0 ? texture(inset_variance_0, inset_tex(0, t)).r
         : s == 1 ? texture(inset_variance_1, inset_tex(1, t)).r
                  : texture(inset_variance_2, inset_tex(2, t)).r;
}

float scalar_at(vec3 t) {
    int s = inset_at(t);
    if (s == 0) return level_scalar(inset_scalars_0, inset_tex(0, t));
    if (s == 1) return level_scalar(inset_scalars_1, inset_tex(1, t));
    if (s == 2) return level_scalar(inset_scalars_2, inset_tex(2, t));
    return level_scalar(scalars, t);
}

// The method's volumes the ray caster reads where they lie (V_AO, E: no image, no copy, no size
// limit but the buffer's), trilinear between voxel centres and clamped to the edge as a linear
// sampler reads an image: the eight corners around texture coordinates t, as the first
// voxel's index v (i in 3D), the offsets d (0 on an axis where v is the last voxel) and the
// weights f.
struct Corners { uint v; uvec3 d; vec3 f; ivec3 i; };

Corners corners_at(ivec3 n, vec3 t) {
    vec3 x = clamp(t * vec3(n) - 0.5, vec3(0.0), vec3(n - 1));
    ivec3 i = min(ivec3(x), n - 1);
    Corners c;
    c.f = x - vec3(i);
    c.d = uvec3(i.x + 1 < n.x ? 1u : 0u, i.y + 1 < n.y ? uint(n.x) : 0u,
                i.z + 1 < n.z ? uint(n.x * n.y) : 0u);
    c.v = uint(i.x) + uint(n.x) * (uint(i.y) + uint(n.y) * uint(i.z));
    c.i = i;
    return c;
}

// Voxel v's AO from V_AO's words `b` stored in bricks through `table`, or `whole` (a volume of
// n voxels).
float brick_word(AoWords b, AoTableRef table, bool whole, ivec3 n, ivec3 v) {
    uint slot = table.t[ao_brick(v, n)];
    bool none = !whole && slot == AO_NONE;
    int at = whole ? v.x + n.x * (v.y + n.y * v.z) : ao_pool_index(none ? 0u : slot, v);
    uint w = uint(b.ao_words[at]);
    return unorm16_value(none ? AO_OPEN : w);
}

#define TRILINEAR(c, read) \
    mix(mix(mix(read(c.v), read(c.v + c.d.x), c.f.x), \
            mix(read(c.v + c.d.y), read(c.v + c.d.x + c.d.y), c.f.x), c.f.y), \
        mix(mix(read(c.v + c.d.z), read(c.v + c.d.x + c.d.z), c.f.x), \
            mix(read(c.v + c.d.y + c.d.z), read(c.v + c.d.x + c.d.y + c.d.z), c.f.x), c.f.y), \
        c.f.z)

// V_AO at texture coordinates t (the inset's within it).
float ambient_at(vec3 t) {
    int s = inset_at(t);
    uvec2 words = s >= 0 ? frame.inset_words[s].xy : frame.ao_words.xy;
    AoWords b = AoWords(words);
    ivec3 n = s >= 0 ? inset_size(s) : textureSize(scalars, 0);
    Corners c = corners_at(n, s >= 0 ? inset_tex(s, t) : t);
    if ((FLAGS & RAY_AO_BRICKS) != 0u) {
        // Stored in bricks (src/ao/pool.rs): each corner's word through its brick's slot, 1
        // where the brick is not stored. A V_AO stored whole has no table (address 0): its
        // own words stand in for one (read in range, unused).
        uvec4 tables = frame.ao_tables[(s + 1) >> 1];
        uvec2 t = ((s + 1) & 1) == 0 ? tables.xy : tables.zw;
        bool whole = all(equal(t, uvec2(0)));
        AoTableRef table = AoTableRef(whole ? words : t);
        ivec3 v0 = c.i, v1 = min(c.i + 1, n - 1);
#define AO_BRICK_READ(k) brick_word(b, table, whole, n, ivec3((k & 1) != 0 ? v1.x : v0.x, \
                                                       (k & 2) != 0 ? v1.y : v0.y, \
                                                       (k & 4) != 0 ? v1.z : v0.z))
        return mix(mix(mix(AO_BRICK_READ(0), AO_BRICK_READ(1), c.f.x),
                       mix(AO_BRICK_READ(2), AO_BRICK_READ(3), c.f.x), c.f.y),
                   mix(mix(AO_BRICK_READ(4), AO_BRICK_READ(5), c.f.x),
                       mix(AO_BRICK_READ(6), AO_BRICK_READ(7), c.f.x), c.f.y),
                   c.f.z);
#undef AO_BRICK_READ
    }
#define AO_READ(i) unorm16_value(uint(b.ao_words[i]))
    return TRILINEAR(c, AO_READ);
#undef AO_READ
}

// The bleeding colour E at texture coordinates t (the inset's within it, where it has one: its
// local histograms at full resolution).
vec3 bleeding_at(vec3 t) {
    int s = inset_at(t);
    bool fine = s >= 0 && any(notEqual(frame.inset_words[s].zw, uvec2(0)));
    BleedingWords b = BleedingWords(fine ? frame.inset_words[s].zw : frame.ao_words.zw);
    Corners c = fine ? corners_at(inset_size(s), inset_tex(s, t))
                     : corners_at(textureSize(scalars, 0), t);
#define E_READ(i) unpackUnorm4x8(b.e_words[i]).rgb
    return TRILINEAR(c, E_READ);
#undef E_READ
}

// Whether some tool reaches index-space point v (it may hide it: no skipping there).
bool in_tool_reach(vec3 v) {
    for (int k = 0; k < min(int(CLIP_TOOL_COUNT), MAX_TOOLS); k++) {
        if (all(greaterThanEqual(v, vec3(frame.tool_reach[2 * k].xyz)))
            && all(lessThan(v, vec3(frame.tool_reach[2 * k + 1].xyz)))) return true;
    }
    return false;
}

// Where the ray v(t) = ov + t dv (index space; inv = 1 / dv) first enters box [lo, hi) at or
// after t (no bound where it does not).
float box_entry(vec3 lo, vec3 hi, vec3 ov, vec3 inv, float t) {
    vec3 t0 = (lo - ov) * inv;
    vec3 t1 = (hi - ov) * inv;
    float enter = max(max(min(t0.x, t1.x), min(t0.y, t1.y)), min(t0.z, t1.z));
    float leave = min(min(max(t0.x, t1.x), max(t0.y, t1.y)), max(t0.z, t1.z));
    return enter <= leave && leave >= t ? max(enter, t) : 3.0e38;
}

// Where the ray v(t) = ov + t dv (index space) leaves brick b (an edge brick extends past the
// grid, as the clamped lookup does) or, with `reach`, first enters a tool's reach, whichever
// comes first.
float run_end(vec3 ov, vec3 dv, float t, ivec3 b, ivec3 last_brick, bool reach) {
    vec3 lo = vec3(b << RAY_BRICK_SHIFT);
    vec3 hi = vec3((b + 1) << RAY_BRICK_SHIFT);
    float end = 3.0e38;
    [[unroll]] for (int a = 0; a < 3; a++) {
        if (dv[a] > 0.0 && b[a] < last_brick[a]) end = min(end, (hi[a] - ov[a]) / dv[a]);
        if (dv[a] < 0.0 && b[a] > 0) end = min(end, (lo[a] - ov[a]) / dv[a]);
    }
    vec3 inv = 1.0 / dv;
    for (int k = 0; k < (reach ? min(int(CLIP_TOOL_COUNT), MAX_TOOLS) : 0); k++) {
        end = min(end, box_entry(vec3(frame.tool_reach[2 * k].xyz), vec3(frame.tool_reach[2 * k + 1].xyz), ov, inv, t));
    }
    // The inset's bricks are the coarse volume's: nothing is skipped inside it.
    if (flag(RAY_INSET)) {
        vec3 dims = vec3(textureSize(scalars, 0));
        [[unroll]] for (int s = 0; s < MAX_INSETS; s++) {
            if (frame.inset_lo[s].x < frame.inset_hi[s].x) {
                end = min(end, box_entry(frame.inset_lo[s].xyz * dims, frame.inset_hi[s].xyz * dims, ov, inv, t));
            }
        }
    }
    return end;
}

// The structure id of texel q of an id volume of n texels (clamped to its edge).
uint structure_texel(sampler3D ids, ivec3 q, ivec3 n) {
    return uint(texelFetch(ids, clamp(q, ivec3(0), n - 1), 0).r * 255.0 + 0.5);
}

// The structure id of texel q of box s's ids, or of the shown volume's with s = -1 (n texels).
uint box_structure_texel(int s, ivec3 q, ivec3 n) {
    if (s == 0) return structure_texel(inset_structure_ids_0, q, n);
    if (s == 1) return structure_texel(inset_structure_ids_1, q, n);
    if (s == 2) return structure_texel(inset_structure_ids_2, q, n);
    return structure_texel(structure_ids, q, n);
}

// The texels per axis of box s's ids, or of the shown volume's with s = -1.
ivec3 box_structure_size(int s) {
    if (s == 0) return textureSize(inset_structure_ids_0, 0);
    if (s == 1) return textureSize(inset_structure_ids_1, 0);
    if (s == 2) return textureSize(inset_structure_ids_2, 0);
    return textureSize(structure_ids, 0);
}

// The structure id of the voxel nearest texture point t (the inset's within it).
uint structure_at(vec3 t) {
    int s = inset_at(t);
    vec3 u = s >= 0 ? inset_tex(s, t) : t;
    ivec3 n = box_structure_size(s);
    ivec3 q = ivec3(floor(u * vec3(n)));
    return box_structure_texel(s, q, n);
}

// Whether the carving tools leave the sample at texture point t standing: its nearest voxel's
// structure is protected (the rule clip_mask.comp applies per voxel).
bool spared_at(vec3 t) {
    if (!flag(RAY_LABELS)) return false;
    uint id = structure_at(t);
    return ((frame.protect[id >> 7][(id >> 5) & 3u] >> (id & 31u)) & 1u) != 0u;
}

// The first tool that hides world point w (texture point p, index-space point v = p * dims: the
// ray caster's shadow test), or -1; the same rule as clip_test_index for a spared point (its
// structure protected). A carving tool hides nothing outside its reach box (frame.tool_reach,
// conservative: the box CAO's update covers, which skipping relies on too), so there neither its
// map nor the point's structure is read; a probe hides all outside it and is always tested.
int hiding_tool(vec3 w, vec3 p, vec3 v) {
    for (uint t = 0u; t < uint(CLIP_TOOL_COUNT); t++) {
        bool probe = tools[t].map.w > 0.5;
        if (!probe && (any(lessThan(v, vec3(frame.tool_reach[2 * t].xyz)))
                       || any(greaterThanEqual(v, vec3(frame.tool_reach[2 * t + 1].xyz))))) {
            continue;
        }
        bool inside = tool_inside(t, (tools[t].local_from_world * vec4(w, 1.0)).xyz);
        if (probe ? !inside : inside && !spared_at(p)) return int(t);
    }
    return -1;
}

// The clip state of brick b of a grid of n bricks (see ClipBricks).
uint clip_brick(ivec3 b, ivec3 n) {
    uint i = uint(b.x + n.x * (b.y + n.y * b.z));
    return (clip_bricks[i >> 2] >> ((i & 3u) * 8u)) & 0xffu;
}

// The structures around texture point t (the inset's within it), interpolated per structure
// rather than by id, so that boundaries are as smooth as the data's: the trilinear weight of
// the unlabelled voxels among the eight nearest, the sum of weight x a_l over the labelled
// ones, and of weight x a_l x c_l.
void structures_at(vec3 t, out float unlabelled, out float shown, out vec3 colour) {
    int s = inset_at(t);
    vec3 u = s >= 0 ? inset_tex(s, t) : t;
    ivec3 n = box_structure_size(s);
    vec3 c = u * vec3(n) - 0.5;
    ivec3 q = ivec3(floor(c));
    vec3 f = c - floor(c);
    unlabelled = 0.0;
    shown = 0.0;
    colour = vec3(0.0);
    [[unroll]] for (int k = 0; k < 8; k++) {
        ivec3 o = ivec3(k & 1, (k >> 1) & 1, k >> 2);
        vec3 w3 = mix(1.0 - f, f, vec3(o));
        float w = w3.x * w3.y * w3.z;
        uint id = box_structure_texel(s, q + o, n);
        if (id == 0u) {
            unlabelled += w;
        } else {
            vec4 s = frame.structures[id];
            shown += w * s.a;
            colour += w * s.a * s.rgb;
        }
    }
}

vec4 classify_value(float s) {
    return texture(tf_lut, s * frame.value_map.y + frame.value_map.x);
}

// Gradient of the scalar field in mm (central differences, one texel apart).
vec3 level_gradient_mm(sampler3D level, vec3 t, vec3 extent_mm) {
    vec3 texel = 1.0 / vec3(textureSize(level, 0));
    vec3 mm = extent_mm * texel;
    float gx = level_scalar(level, t + vec3(texel.x, 0, 0)) - level_scalar(level, t - vec3(texel.x, 0, 0));
    float gy = level_scalar(level, t + vec3(0, texel.y, 0)) - level_scalar(level, t - vec3(0, texel.y, 0));
    float gz = level_scalar(level, t + vec3(0, 0, texel.z)) - level_scalar(level, t - vec3(0, 0, texel.z));
    return vec3(gx, gy, gz) / (2.0 * mm);
}

// In the inset, its own texels (its margin holds the neighbours).
vec3 gradient_mm(vec3 t) {
    int s = inset_at(t);
    if (s < 0) return level_gradient_mm(scalars, t, frame.extent_mm.xyz);
    vec3 mm = frame.extent_mm.xyz / frame.inset_scale[s].xyz;
    return s == 0 ? level_gradient_mm(inset_scalars_0, inset_tex(0, t), mm)
         : s == 1 ? level_gradient_mm(inset_scalars_1, inset_tex(1, t), mm)
                  : level_gradient_mm(inset_scalars_2, inset_tex(2, t), mm);
}

vec3 sh_dot(vec4 v, int first) {
    return v.x * frame.sh_light[first].rgb + v.y * frame.sh_light[first + 1].rgb
         + v.z * frame.sh_light[first + 2].rgb + v.w * frame.sh_light[first + 3].rgb;
}

// The environment light reaching point t through the volume (Y_0 is folded into sh_light).
vec3 sh_emission(vec3 t) {
    vec3 e = sh_dot(texture(sh0, t), 0);
    if (frame.lighting.y > 4.5) {
        e += sh_dot(texture(sh1, t), 4) + sh_dot(texture(sh2, t), 8) + sh_dot(texture(sh3, t), 12);
    }
    return max(e, vec3(0.0));
}

// The start offset in [0,1): the blue-noise tile, at a fixed offset per eye, so each eye's
// pattern is the same every frame and the two eyes' patterns differ.
float pixel_jitter(vec2 p, uint eye_index) {
    if (!flag(RAY_JITTER)) return 0.0;
    ivec2 size = textureSize(blue_noise, 0);
    vec2 off = eye_index == 0u ? frame.jitter.xy : frame.jitter.zw;
    ivec2 q = (ivec2(p) + ivec2(off)) % size;
    return texelFetch(blue_noise, q, 0).r;
}

// The surface depth of texel q of tool t's clip map nearest to z, or EMPTY_IN where the texel
// is empty or outside the map; `which` picks the same peel boundary at the neighbours.
float map_depth(ClipTool tool, ivec2 q, int which) {
    int res = int(tool.map.z);
    if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, ivec2(res)))) return EMPTY_IN;
    vec4 c = clip_maps[tool.offsets.x + uint(q.y * res + q.x)];
    vec2 iv = which < 2 ? c.xy : c.zw;
    if (iv.x > iv.y) return EMPTY_IN;
    return (which & 1) == 0 ? iv.x : iv.y;
}

// The normal of tool t's surface at tool-local point q, from the clip map's depth differences
// (any shape, meshes included).
vec3 map_normal(ClipTool tool, vec3 q) {
    ivec2 px = ivec2(floor((q.xy + tool.map.x) * tool.map.y));
    int which = 0;
    float best = 1e38;
    [[unroll]] for (int k = 0; k < 4; k++) {
        float z = map_depth(tool, px, k);
        if (z != EMPTY_IN && abs(z - q.z) < best) { best = abs(z - q.z); which = k; }
    }
    float texel = 1.0 / tool.map.y;
    vec2 dh = vec2(0.0);
    [[unroll]] for (int a = 0; a < 2; a++) {
        ivec2 e = a == 0 ? ivec2(1, 0) : ivec2(0, 1);
        float h0 = map_depth(tool, px, which);
        float hp = map_depth(tool, px + e, which);
        float hm = map_depth(tool, px - e, which);
        if (hp != EMPTY_IN && hm != EMPTY_IN) dh[a] = (hp - hm) / (2.0 * texel);
        else if (hp != EMPTY_IN && h0 != EMPTY_IN) dh[a] = (hp - h0) / texel;
        else if (hm != EMPTY_IN && h0 != EMPTY_IN) dh[a] = (h0 - hm) / texel;
    }
    return vec3(-dh, 1.0);
}

// The exact normal of a built-in shape (src/clip/mesh.rs: unit sphere, box [-1,1]^3, cylinder
// of radius 1 and height 2 along z, torus of radii 1 and TORUS_MINOR around z) at local point q
// near its surface: the face nearest to q. (A clip map's depth differences break up where the
// surface turns away from its camera, the silhouette, which speckled sphere cuts' rims.)
vec3 shape_normal(uint shape, vec3 q) {
    if (shape == SHAPE_SPHERE) return q;
    if (shape == SHAPE_BOX) {
        vec3 a = abs(q);
        if (a.x >= a.y && a.x >= a.z) return vec3(sign(q.x), 0.0, 0.0);
        if (a.y >= a.z) return vec3(0.0, sign(q.y), 0.0);
        return vec3(0.0, 0.0, sign(q.z));
    }
    float r = length(q.xy);
    if (shape == SHAPE_CYLINDER) {
        return abs(r - 1.0) < abs(abs(q.z) - 1.0) ? vec3(q.xy, 0.0) : vec3(0.0, 0.0, sign(q.z));
    }
    // The torus: away from the nearest point of its core circle.
    return r > 0.0 ? q - vec3(q.xy / r, 0.0) : vec3(0.0, 0.0, sign(q.z));
}

// The normal of tool t's surface near world point w (just outside what it hides), in the
// volume's mm frame: exact for the built-in shapes, from the clip map for meshes.
vec3 cut_normal_mm(uint t, vec3 w) {
    ClipTool tool = tools[t];
    vec3 local = (tool.local_from_world * vec4(w, 1.0)).xyz;
    vec3 n_local = tool.offsets.w == SHAPE_MESH ? vec3(0.0) : shape_normal(tool.offsets.w, local);
    if (dot(n_local, n_local) < 1e-12) n_local = map_normal(tool, local);
    // Normals go back through the transpose; index space to mm divides by the spacing.
    vec3 n_index = transpose(mat3(tool.local_from_index)) * n_local;
    vec3 spacing = frame.extent_mm.xyz / vec3(textureSize(scalars, 0));
    return n_index / spacing;
}

// The ray of eye v through pixel p: its points on the near and far planes in the world (a_w,
// b_w) and in texture space (o + t d, t in [0, 1] from near to far), and where it enters and
// leaves the volume (tn < tf where it meets it).
struct Ray { vec3 a_w; vec3 b_w; vec3 o; vec3 d; float tn; float tf; };

Ray eye_ray(uint v, vec2 pixel) {
    Ray r;
    vec2 ndc = pixel / frame.viewport.xy * 2.0 - 1.0;
    vec4 near_w = frame.inv_view_proj[v] * vec4(ndc, 0.0, 1.0);
    vec4 far_w = frame.inv_view_proj[v] * vec4(ndc, 1.0, 1.0);
    r.a_w = near_w.xyz / near_w.w;
    r.b_w = far_w.xyz / far_w.w;
    r.o = (frame.tex_from_world * vec4(r.a_w, 1.0)).xyz;
    r.d = (frame.tex_from_world * vec4(r.b_w, 1.0)).xyz - r.o;
    vec3 inv = 1.0 / r.d;
    vec3 t0 = (vec3(0.0) - r.o) * inv;
    vec3 t1 = (vec3(1.0) - r.o) * inv;
    r.tn = max(max(min(t0.x, t1.x), min(t0.y, t1.y)), max(min(t0.z, t1.z), 0.0));
    r.tf = min(min(max(t0.x, t1.x), max(t0.y, t1.y)), min(max(t0.z, t1.z), 1.0));
    return r;
}

// The record is on this pass's grid: the eye's pixels (pass 0), or a foveated eye's coarse
// pixels, one per block of eye.scale x eye.scale (pass 1), which also cast through their
// centres; its texel coordinates are the eye's pixel coordinates over eye.scale.
ivec2 record_size() {
    return ivec2(ceil(frame.viewport.xy / eye.scale));
}

// The first eye's record texel coordinates (as its gl_FragCoord) of point c in its clip space.
vec2 first_eye_pixel(vec4 c) {
    return (c.xy / c.w * 0.5 + 0.5) * frame.viewport.xy / eye.scale;
}

uvec4 first_eye_texel(ivec2 q) {
    return EyeRecord(eye.record).texels[q.y * record_size().x + q.x];
}

// A record texel the first eye did not cast (a coarse pixel inside the full-rate centre): what
// it saw there is unknown, and the second eye casts wherever its walk meets one.
const float RECORD_UNKNOWN = -1.0;

// The first eye's surface at its pixel coordinates p: the view depth and colour of the four
// texels around p, bilinear, where all four show one opaque surface: each ray ended opaque and
// reached REPROJECT_BACK_ALPHA so close behind where it reached 5 % that the eyes' parallax
// over that depth (the baseline frame.background.w over the depth) stays within
// REPROJECT_PARALLAX pixel footprints (frame.viewport.w per unit of depth); their depths lie
// within REPROJECT_SLOPE footprints of each other, and their colours within
// REPROJECT_CONTRAST. False where they do not.
bool first_eye_surface(vec2 p, out float w, out vec4 colour) {
    vec2 x = p - 0.5;
    ivec2 q = ivec2(floor(x));
    vec2 f = x - vec2(q);
    w = 0.0;
    colour = vec4(0.0);
    if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q + 1, record_size()))) {
        return false;
    }
    // The first eye's pixel footprint per unit of depth, on the record's grid.
    float footprint = frame.viewport.w * eye.scale;
    float lo = 3.0e38;
    float hi = 0.0;
    vec3 c_lo = vec3(1.0);
    vec3 c_hi = vec3(0.0);
    [[unroll]] for (int k = 0; k < 4; k++) {
        ivec2 o = ivec2(k & 1, k >> 1);
        uvec4 r = first_eye_texel(q + o);
        float front = uintBitsToFloat(r.y);
        float back = uintBitsToFloat(r.z);
        if (front <= 0.0 || back <= 0.0
            || (back - front) * frame.background.w > REPROJECT_PARALLAX * footprint * front * front) {
            return false;
        }
        vec2 w2 = mix(1.0 - f, f, vec2(o));
        w += w2.x * w2.y * front;
        vec4 ck = unpackUnorm4x8(r.x);
        colour += w2.x * w2.y * ck;
        c_lo = min(c_lo, ck.rgb);
        c_hi = max(c_hi, ck.rgb);
        lo = min(lo, front);
        hi = max(hi, front);
    }
    return hi - lo <= REPROJECT_SLOPE * footprint * hi
        && all(lessThanEqual(c_hi - c_lo, vec3(REPROJECT_CONTRAST)));
}

// Bisections that place the second eye's ray on the first eye's surface within 1/64 of a pixel.
const int REPROJECT_BISECTIONS = 6;

// RAY_REPROJECT: this pixel of the second eye (ray r) from the first eye's record, where the first
// thing its ray meets is a surface the first eye saw opaque. Walking the ray from where it
// enters the volume, in steps of at most one first-eye pixel, each point lies in front of what
// the first eye saw there (which saw through it: it is empty) until one lies behind; between
// the two, the ray crosses the first eye's surface (bisected on its interpolated depth), and
// that crossing must lie on one surface (first_eye_surface) within a ray step. Where the walk
// meets no surface and every first-eye ray it passed saw nothing at all (alpha 0: all of
// their space is empty), the ray sees nothing either: background. False where any of this
// fails, the entry lies behind a surface already, or the walk leaves the first eye's image:
// the pixel casts its own ray.
bool reprojected(Ray r) {
    if (r.tn >= r.tf) return false;
    vec3 xa = mix(r.a_w, r.b_w, r.tn);
    vec3 xb = mix(r.a_w, r.b_w, r.tf);
    vec4 ca = frame.view_proj[0] * vec4(xa, 1.0);
    vec4 cb = frame.view_proj[0] * vec4(xb, 1.0);
    if (ca.w <= 0.0 || cb.w <= 0.0) return false;
    int n = int(ceil(length(first_eye_pixel(cb) - first_eye_pixel(ca)))) + 1;
    if (n > REPROJECT_MAX_MARCH) return false;
    ivec2 size = record_size();
    float s_front = 0.0;
    float s_behind = -1.0;
    // Whether every first-eye ray the walk passed saw nothing at all.
    bool clear = true;
    for (int i = 0; i <= n; i++) {
        float s = float(i) / float(n);
        vec4 c = mix(ca, cb, s);
        ivec2 q = ivec2(floor(first_eye_pixel(c)));
        if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) return false;
        uvec4 texel = first_eye_texel(q);
        float front = uintBitsToFloat(texel.y);
        if (front == RECORD_UNKNOWN) return false;
        clear = clear && (texel.x >> 24) == 0u;
        if (front > 0.0 && c.w >= front) {
            s_behind = s;
            break;
        }
        s_front = s;
    }
    if (s_behind < 0.0 && clear) {
        out_color = vec4(frame.background.rgb, 0.0);
        gl_FragDepth = 1.0;
        return true;
    }
    if (s_behind <= 0.0) return false;
    float w;
    vec4 colour;
    for (int k = 0; k < REPROJECT_BISECTIONS; k++) {
        float s = 0.5 * (s_front + s_behind);
        vec4 c = mix(ca, cb, s);
        if (!first_eye_surface(first_eye_pixel(c), w, colour)) return false;
        if (c.w >= w) s_behind = s; else s_front = s;
    }
    float s = 0.5 * (s_front + s_behind);
    vec4 c = mix(ca, cb, s);
    // One ray step, in world units.
    float step_w = frame.extent_mm.w / length(r.d * frame.extent_mm.xyz) * length(r.b_w - r.a_w);
    if (!first_eye_surface(first_eye_pixel(c), w, colour) || abs(c.w - w) > step_w) {
        return false;
    }
    vec4 c1 = frame.view_proj[1] * vec4(mix(xa, xb, s), 1.0);
    out_color = colour;
    gl_FragDepth = clamp(c1.z / c1.w, 0.0, 1.0);
    return true;
}

void main() {
    uint v = eye.index;
    // The pixel of the eye's image this ray goes through.
    vec2 pixel = eye.pass == 1u ? gl_FragCoord.xy * eye.scale : gl_FragCoord.xy;
    if (eye.pass != 0u) {
        float r = length(pixel - eye.centre);
        if (eye.pass == 2u && r > eye.radius) {
            vec2 texel = pixel / eye.scale / vec2(textureSize(coarse_color, 0).xy);
            vec3 uvw = vec3(texel, float(v));
            out_color = textureLod(coarse_color, uvw, 0.0);
            gl_FragDepth = textureLod(coarse_depth, uvw, 0.0).r;
            return;
        }
        // A coarse pixel that no interpolated pixel reads (it and its neighbours lie well
        // within the centre) casts nothing.
        if (eye.pass == 1u && r + 2.0 * eye.scale < eye.radius) {
            out_color = vec4(0.0);
            gl_FragDepth = 1.0;
            if (flag(RAY_RECORD)) {
                ivec2 q = ivec2(gl_FragCoord.xy);
                EyeRecord(eye.record).texels[q.y * record_size().x + q.x] =
                    uvec4(0u, floatBitsToUint(RECORD_UNKNOWN), 0u, 0u);
            }
            return;
        }
    }
    Ray ray = eye_ray(v, pixel);
    if (flag(RAY_REPROJECT) && reprojected(ray)) return;
    vec3 a_w = ray.a_w;
    vec3 b_w = ray.b_w;
    vec3 o = ray.o;
    vec3 d = ray.d;
    float tn = ray.tn;
    float tf = ray.tf;

    vec3 color = vec3(0.0);
    float alpha = 0.0;
    float depth = 1.0;
    // The view depths where the opacity reached DEPTH_ALPHA and REPROJECT_BACK_ALPHA (RAY_RECORD).
    float w_front = 0.0;
    float w_back = 0.0;
    if (tn < tf) {
        float step_mm = frame.extent_mm.w;
        vec3 d_mm = d * frame.extent_mm.xyz;
        float len_mm = length(d_mm);
        float dt = step_mm / len_mm;
        // The view direction v (towards the eye); the light l: the headlight at the head
        // (frame.light.xyz, midway between the eyes; l = h, per sample, so that both eyes see
        // a point lit alike) or one fixed in the world, with Blinn's half vector h.
        vec3 view = -d_mm / len_mm;
        bool headlight = frame.light.w < 0.5;
        vec3 half_vector = headlight ? view : normalize(frame.light.xyz + view);
        float hg = frame.bleeding.z;
        float t = tn + dt * pixel_jitter(pixel, v);
        bool clipping = flag(RAY_CLIPPING);
        // The previous sample's value (pre-integration), or none after a gap in the material.
        float s_prev = 0.0;
        bool have_prev = false;
        // The cut face: where the ray leaves a tool that hid the samples before.
        int prev_tool = -1;
        float cut_t = -1.0;
        vec3 cut_n = vec3(0.0);
        // Empty-space skipping and the clip test per brick: the brick the last sample was
        // in, whether it is empty, its clip state (see ClipBricks; CUT: test every sample),
        // and whether that sample could have been skipped (an empty brick no tool cuts).
        bool skipping = flag(RAY_SKIP_EMPTY);
        bool clip_bricks = clipping && flag(RAY_CLIP_BRICKS);
        vec3 dims = vec3(textureSize(scalars, 0));
        ivec3 last_brick = ((ivec3(dims) + (1 << RAY_BRICK_SHIFT) - 1) >> RAY_BRICK_SHIFT) - 1;
        ivec3 brick = ivec3(-1);
        bool brick_empty = false;
        uint clip_state = CLIP_BRICK_CUT;
        bool prev_skippable = false;
        // The samples lie on the lattice t = t0 + k dt (computed, not accumulated, so that a
        // jump over k lands exactly where stepping would have); a cut-face bisection restarts
        // it at the cut. No fixed sample cap: the loop is bounded by twice the ray's sample
        // count (each bisection steps back by less than a step, at most every other sample).
        float t0 = t;
        int k = 0;
        int max_iterations = 2 * int(ceil((tf - t) / dt)) + 4;
        for (int it = 0; it < max_iterations; it++, k++) {
            t = t0 + float(k) * dt;
            if (t >= tf) break;
            vec3 p = o + t * d;
            vec3 vi = p * dims;
            if (skipping || clip_bricks) {
                ivec3 b = clamp(ivec3(floor(vi)) >> RAY_BRICK_SHIFT, ivec3(0), last_brick);
                if (b != brick) {
                    brick_empty = skipping && texelFetch(empty_bricks, b, 0).r > 0.5;
                    if (clip_bricks) clip_state = clip_brick(b, last_brick + 1);
                    prev_skippable = false;
                    brick = b;
                }
            }
            // In the inset every sample is tested with its own clip maps (the bricks' states
            // are the shown volume's, from its maps).
            uint sample_clip = in_inset(p) ? CLIP_BRICK_CUT : clip_state;
            // A brick one tool hides whole, where no structure can be spared and no glow
            // shines: every sample is hidden by that tool, as the test would find one by one.
            // Jump to two steps before the brick's end, as below; the last two are taken here
            // one by one.
            if (clip_bricks && sample_clip != CLIP_BRICK_OPEN && sample_clip != CLIP_BRICK_CUT
                && !flag(RAY_LABELS) && !flag(RAY_GLOW)) {
                float t_out = min(tf, run_end(o * dims, d * dims, t, brick, last_brick, false));
                int n = int(floor((t_out - t) / dt)) - 2;
                if (n > 0) k += n;
                prev_tool = int(sample_clip) - 1;
                have_prev = false;
                prev_skippable = false;
                continue;
            }
            if (skipping) {
                vec3 v = vi;
                bool here = brick_empty
                    && (clip_bricks ? clip_state == CLIP_BRICK_OPEN : !in_tool_reach(v))
                    && !in_inset(p);
                if (here && prev_skippable) {
                    // This sample and the one before read only values (and, pre-integrated,
                    // the segment between them) that classify as transparent, and no tool hides
                    // it: it adds exactly nothing, and so does every next sample in this brick
                    // out of the tools' reach. Jump over those that lie two steps or more inside
                    // both (the lattice makes the jump land on a sample; the margin keeps
                    // rounding from ever skipping one the per-sample test would keep); the
                    // rest are tested one by one. Only the last skipped value matters, to the
                    // next segment.
                    float t_out = min(tf, run_end(o * dims, d * dims, t, brick, last_brick,
                                                  !clip_bricks));
                    int n = int(floor((t_out - t) / dt)) - 2;
                    if (n > 0) {
                        k += n;
                        t = t0 + float(k) * dt;
                        p = o + t * d;
                    }
                    vec3 vn = (o + (t0 + float(k + 1) * dt) * d) * dims;
                    ivec3 bn = clamp(ivec3(floor(vn)) >> RAY_BRICK_SHIFT, ivec3(0), last_brick);
                    if (bn != brick || (!clip_bricks && in_tool_reach(vn)) || in_inset(vn / dims)) {
                        s_prev = scalar_at(p);
                        have_prev = true;
                    }
                    continue;
                }
                prev_skippable = here;
            }
            // The safety margins' volumetric glow (Ropinski et al., Sect. 4.4): emission only,
            // through what lies in front, and also where a tool cut the tissue away.
            if (flag(RAY_GLOW)) {
                int s = inset_at(p);
                float g = s >= 0 ? inset_glow_at(s, p) : texture(glow, p).r;
                color += (1.0 - alpha) * frame.glow.rgb * (g * frame.glow.a * step_mm);
            }
            // Shadow-test clipping: the same maps the AO update used.
            if (clipping) {
                vec3 w = a_w + t * (b_w - a_w);
                // A brick no tool cuts needs no test; in one a tool hides whole, that tool is
                // the first hider unless a protected structure is spared.
                int hider = sample_clip == CLIP_BRICK_OPEN ? -1
                          : sample_clip == CLIP_BRICK_CUT || flag(RAY_LABELS) ? hiding_tool(w, p, vi)
                          : int(sample_clip) - 1;
                if (hider >= 0) {
                    prev_tool = hider;
                    have_prev = false;
                    prev_skippable = false;
                    continue;
                }
                if (prev_tool >= 0) {
                    // The cut lies between the last hidden sample and this one: find it, and
                    // step on from there, so a cut face sits where the tool is rather than
                    // where the jittered samples happen to fall.
                    float lo = t - dt;
                    for (int n = 0; n < CUT_BISECTIONS; n++) {
                        float mid = 0.5 * (lo + t);
                        vec3 pm = o + mid * d;
                        if (hiding_tool(a_w + mid * (b_w - a_w), pm, pm * dims) >= 0) lo = mid; else t = mid;
                    }
                    p = o + t * d;
                    w = a_w + t * (b_w - a_w);
                    t0 = t;
                    k = 0;
                    // The sample moved back, maybe out of its brick.
                    brick = ivec3(-1);
                    if (frame.surface.y > 0.0) {
                        cut_t = t;
                        cut_n = cut_normal_mm(uint(prev_tool), w);
                    }
                }
                prev_tool = -1;
            }
            float s = scalar_at(p);
            vec4 c = classify_value(s);
            float a;
            vec3 premult;
            bool pre_mid = flag(RAY_PREINTEGRATED) && have_prev;
            vec2 pre_uv = vec2(0.0);
            if (flag(RAY_ISO)) {
                // The first-hit isosurface (frame.surface.w, in texel units): below it nothing
                // is seen; the first sample at or past it ends the ray, moved back onto the
                // surface by bisection on the scalar between it and the sample before (at the
                // ray's entry or a cut face there is no sample before: the surface is there),
                // and shaded opaque in the TF's colour at the isovalue.
                float iso = frame.surface.w;
                if (s < iso) {
                    have_prev = true;
                    continue;
                }
                if (have_prev) {
                    float lo = t - dt;
                    for (int n = 0; n < ISO_BISECTIONS; n++) {
                        float mid = 0.5 * (lo + t);
                        if (scalar_at(o + mid * d) >= iso) t = mid; else lo = mid;
                    }
                    p = o + t * d;
                }
                a = 1.0;
                premult = classify_value(iso).rgb;
            } else if (flag(RAY_PREINTEGRATED)) {
                float sf = have_prev ? s_prev : s;
                pre_uv = vec2(sf, s) * frame.value_map.w + frame.value_map.z;
                vec4 pre = texture(preint, pre_uv);
                a = pre.a;
                premult = pre.rgb;
            } else {
                a = c.a > 0.0 ? 1.0 - pow(1.0 - min(c.a, 0.9999), step_mm) : 0.0;
                premult = c.rgb * a;
            }
            s_prev = s;
            have_prev = true;
            // Structures: their opacity a_l scales the TF's, their colour replaces its colour.
            if (flag(RAY_LABELS)) {
                float unlabelled, shown;
                vec3 colour;
                structures_at(p, unlabelled, shown, colour);
                premult = premult * unlabelled + a * colour;
                a *= unlabelled + shown;
            }
            // Variance opacity modulation: homogeneous tissue fades, boundaries stay.
            if (flag(RAY_VARIANCE)) {
                int s = inset_at(p);
                float var_s = s >= 0 ? inset_variance_at(s, p) : texture(variance, p).r;
                float m = min(var_s * frame.lighting.w, 1.0);
                a *= m;
                premult *= m;
            }
            if (a > 0.0) {
                // A pre-integrated step is shaded where its light comes from (its extinction's
                // mean position), not at the back sample.
                vec3 q = pre_mid ? o + (t - (1.0 - texture(preint_at, pre_uv).r) * dt) * d : p;
                float occl = flag(RAY_AO) ? ambient_at(q) : 1.0;
                vec3 e = flag(RAY_BLEEDING) || flag(RAY_SCATTERING) ? bleeding_at(q) : vec3(0.0);
                // Colour bleeding (Ropinski et al.): towards the neighbourhood's colour E, the
                // more the neighbourhood occludes (O_env = 1 - A).
                if (flag(RAY_BLEEDING)) {
                    premult = mix(premult, e * a, frame.bleeding.x * (1.0 - occl));
                }
                // The normal: the tool's within the cut layer, else the data's gradient, which
                // lights only where it is steep enough to mean a surface.
                vec3 n = vec3(0.0);
                float lit = 0.0;
                bool on_cut = cut_t >= 0.0 && (t - cut_t) * len_mm <= frame.surface.y;
                if (on_cut) {
                    n = cut_n;
                    lit = 1.0;
                    if (frame.cut_tint.a > 0.0) {
                        premult = mix(premult, frame.cut_tint.rgb * a, frame.cut_tint.a);
                    }
                } else if (flag(RAY_LIT)) {
                    n = gradient_mm(q);
                    float g = length(n);
                    float gmin = frame.surface.x;
                    lit = gmin > 0.0 ? smoothstep(gmin, 2.0 * gmin, g) : float(g > 0.0);
                }
                vec3 light = headlight ? normalize(frame.light.xyz - q * frame.extent_mm.xyz)
                                       : frame.light.xyz;
                float ndl = 0.0;
                float ndh = 0.0;
                if (lit > 0.0) {
                    // Two-sided: a surface is lit from whichever side the eye sees it.
                    ndl = abs(dot(normalize(n), light));
                    ndh = headlight ? ndl : abs(dot(normalize(n), half_vector));
                }
                float ao_diffuse = 1.0 - frame.surface.z + frame.surface.z * occl;
                vec3 shade = vec3(frame.phong.x * occl + lit * frame.phong.y * ao_diffuse * ndl);
                if (flag(RAY_SH)) {
                    float ao_factor = frame.lighting.z > 0.5 ? occl : 1.0;
                    shade += frame.lighting.x * ao_factor * sh_emission(q);
                }
                float spec = lit * frame.phong.z * pow(ndh, frame.phong.w);
                // Scattering (Ropinski et al. Sect. 3.3): ambient light (ka) of the environment's
                // colour E, which is both hemispheres' where the data is flat and the front
                // one's at a border, scattered towards the eye.
                vec3 scattered = vec3(0.0);
                if (flag(RAY_SCATTERING)) {
                    // The Henyey-Greenstein phase between the light's travel (-l) and the way
                    // to the eye (v), times 4 pi (1 where g = 0).
                    float phase = (1.0 - hg * hg) / pow(1.0 + hg * hg + 2.0 * hg * dot(light, view), 1.5);
                    scattered = frame.phong.x * frame.bleeding.y * phase * e;
                }
                color += (1.0 - alpha) * (premult * shade + a * (spec + scattered));
                float alpha_before = alpha;
                alpha += (1.0 - alpha) * a;
                if (depth == 1.0 && alpha >= DEPTH_ALPHA) {
                    vec4 clip = frame.view_proj[v] * vec4(a_w + t * (b_w - a_w), 1.0);
                    depth = clamp(clip.z / clip.w, 0.0, 1.0);
                }
                if (flag(RAY_RECORD)) {
                    // The view depths where the opacity reached DEPTH_ALPHA and
                    // REPROJECT_BACK_ALPHA, placed within the step (linearly), free of the
                    // jittered lattice.
                    [[unroll]] for (int k = 0; k < 2; k++) {
                        float level = k == 0 ? DEPTH_ALPHA : REPROJECT_BACK_ALPHA;
                        if (alpha_before < level && alpha >= level) {
                            float f = clamp((level - alpha_before) / (alpha - alpha_before), 0.0, 1.0);
                            float tc = t - (1.0 - f) * dt;
                            float w = (frame.view_proj[v] * vec4(a_w + tc * (b_w - a_w), 1.0)).w;
                            if (k == 0) w_front = w; else w_back = w;
                        }
                    }
                }
                if (alpha >= OPAQUE_ALPHA || flag(RAY_ISO)) break;
            }
        }
    }
    out_color = vec4(color + (1.0 - alpha) * frame.background.rgb, alpha);
    gl_FragDepth = depth;
    if (flag(RAY_RECORD)) {
        // Only a ray that ended opaque shows a surface.
        if (alpha < OPAQUE_ALPHA && !flag(RAY_ISO)) w_back = 0.0;
        ivec2 q = ivec2(gl_FragCoord.xy);
        EyeRecord(eye.record).texels[q.y * record_size().x + q.x] =
            uvec4(packUnorm4x8(out_color), floatBitsToUint(w_front), floatBitsToUint(w_back), 0u);
    }
}
