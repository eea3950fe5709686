// Per-frame uniforms of the stereo ray caster (std140; mirrors render::FrameUniforms).
#include "constants.glsl"
layout(std140, set = 0, binding = 0) uniform Frame {
    mat4 inv_view_proj[2];   // clip -> world, per view
    mat4 view_proj[2];       // world -> clip, per view
    mat4 tex_from_world;     // world -> volume texture coordinates [0,1]^3
    vec4 extent_mm;          // xyz: volume extent in mm along i,j,k; w: step in mm
    vec4 value_map;          // lut coordinate = value * y + x; pre-integration table's: * w + z
    vec4 background;         // rgb background, a: the distance between the two eyes
    vec4 viewport;           // xy: width, height in pixels; z: number of clipping tools;
                             // w: the first eye's pixel width per unit of view depth
    vec4 phong;              // Blinn-Phong ka, kd, ks, shininess
    vec4 surface;            // x: least gradient (data units / mm) that lights a sample,
                             // y: cut layer in mm (0: cut faces lit by the data's gradient),
                             // z: share of the diffuse term the AO multiplies
    vec4 cut_tint;           // rgb: tint of cut faces, a: its weight (0: none)
    vec4 jitter;             // xy: left eye's blue-noise offset in pixels, zw: right eye's
    vec4 lighting;           // x: SH light weight (read with RAY_SH), y: SH coefficients, z: 1 = times AO,
                             // w: 1 / V_max of variance opacity modulation (RAY_VARIANCE)
    vec4 bleeding;           // x: bleeding weight W of the local-histogram method (0: off),
                             // y: its scattering weight (0: off), z: the phase function's g
    vec4 glow;               // rgb: the safety margins' glow colour, a: its emission per mm
    vec4 sh_light[16];       // rgb: Y_0 * L_k per colour channel (the environment in data space)
    ivec4 tool_reach[2 * MAX_TOOLS]; // per tool, index-space [min, max) holding all it hides
    vec4 structures[256];    // per structure id (0: unlabelled): rgb colour, a: opacity a_l
    uvec4 protect[2];        // bit id: the structure is protected from the carving tools
    vec4 light;              // w = 1: xyz towards a light fixed in the world, in the gradient's
                             // frame (along i, j, k, in mm, unit); w = 0: a headlight, xyz the
                             // head (midway between the eyes) in that frame (texture coords * mm)
    uvec4 ao_words;          // xy: V_AO's address (16-bit unorm words, x fastest), read with
                             // RAY_AO; zw: the bleeding colour E's (RGBA8 words),
                             // read with RAY_BLEEDING or RAY_SCATTERING
    // Per full-resolution box of the inset (read with RAY_INSET; a box absent has lo = hi):
    vec4 inset_lo[MAX_INSETS];     // xyz: the box in texture coordinates [lo, hi)
    vec4 inset_hi[MAX_INSETS];
    vec4 inset_scale[MAX_INSETS];  // xyz: its scalars' texture coordinates are t * scale + offset
    vec4 inset_offset[MAX_INSETS];
    uvec4 inset_words[MAX_INSETS]; // xy: its V_AO's address (16-bit unorm words, as ao_words);
                                   // zw: its bleeding colour E's (as ao_words.zw), 0 where none
    // With RAY_AO_BRICKS, the brick tables' addresses (src/ao/pool.rs): V_AO's, then each
    // box's, two to a uvec4 (xy, zw).
    uvec4 ao_tables[(MAX_INSETS + 2) / 2];
} frame;
