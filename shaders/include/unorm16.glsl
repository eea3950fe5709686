// Values in [0, 1] as 16-bit unorm words, 2 bytes a voxel (UNORM16_MAX, from
// src/shader_constants.rs; the host's side is src/ao/stored.rs): AO (V_AO, V_PAO), the opacity O
// and O_c, and the filters' density. A computed value is rounded to nearest (`x[i] =
// uint16_t(unorm16_word(a))`); a copy (restore, an unclipped voxel, the outside of a tool's box)
// moves the stored word as it is, so CAO and its full recompute store the same bits. The ray
// caster reads V_AO's words by address and filters them itself. (With 16-bit storage alone, 16-bit values exist
// only in buffers and in the conversion that stores them, hence words as uint here.)
#ifndef CAO_XR_UNORM16
#define CAO_XR_UNORM16
#extension GL_EXT_shader_16bit_storage : require
#include "constants.glsl"

uint unorm16_word(float a) {
    // precise: no fused multiply-add, so the rounding is the host's (`ao::stored::pack`).
    precise float q = clamp(a, 0.0, 1.0) * UNORM16_MAX + 0.5;
    return uint(q);
}

// The value of a stored word, as the host's `ao::stored::unpack`.
float unorm16_value(uint w) {
    return float(w) / UNORM16_MAX;
}

// The word of AO 1 (open): what a voxel no tool reaches, or an empty one, holds.
const uint AO_OPEN = uint(UNORM16_MAX);
#endif
