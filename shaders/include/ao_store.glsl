// V_AO and V_PAO: AO in [0, 1] as 16-bit unorm, 2 bytes a voxel (AO_UNORM_MAX, from
// src/shader_constants.rs). A computed value is rounded to nearest (`ao[i] =
// uint16_t(ao_word(a))`); a copy (restore, the outside of a tool's box) moves the stored word
// as it is, so CAO and its full recompute store the same bits. The ray caster reads them
// through an R16_UNORM image. (With 16-bit storage alone, 16-bit values exist only in buffers
// and in the conversion that stores them, hence words as uint here.)
#ifndef CAO_XR_AO_STORE
#define CAO_XR_AO_STORE
#extension GL_EXT_shader_16bit_storage : require
#include "constants.glsl"

uint ao_word(float a) {
    // precise: no fused multiply-add, so the rounding is the host's (`ao::stored::pack`).
    precise float q = clamp(a, 0.0, 1.0) * AO_UNORM_MAX + 0.5;
    return uint(q);
}

// The word of AO 1 (open): what a voxel no tool reaches, or an empty one, holds.
const uint AO_OPEN = uint(AO_UNORM_MAX);
#endif
