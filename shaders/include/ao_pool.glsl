// V_AO in bricks (src/ao/pool.rs): per brick of 2^AO_BRICK_SHIFT voxels per axis (x fastest)
// its slot in the pool, or AO_NONE where the brick is not stored (every voxel's AO is 1); a
// table whose first word is AO_WHOLE stands for V_AO stored whole, x fastest (a precompute's
// V_PAO). A writer defines AO_TABLE_BINDING and AO_WORDS and stores through ao_store; the ray
// caster reads the table by address (ao_brick, ao_pool_index).
#ifndef CAO_XR_AO_POOL
#define CAO_XR_AO_POOL
#include "constants.glsl"

// Where voxel v lies in a pool whose table gives `slot` for its brick, or -1 where that brick
// is not stored.
int ao_pool_index(uint slot, ivec3 v) {
    if (slot == AO_NONE) return -1;
    ivec3 l = v & ((1 << AO_BRICK_SHIFT) - 1);
    return int(slot << (3 * AO_BRICK_SHIFT)) + l.x + ((l.y + (l.z << AO_BRICK_SHIFT)) << AO_BRICK_SHIFT);
}

// The table index of voxel v's brick.
int ao_brick(ivec3 v, ivec3 dims) {
    ivec3 n = (dims + (1 << AO_BRICK_SHIFT) - 1) >> AO_BRICK_SHIFT;
    ivec3 b = v >> AO_BRICK_SHIFT;
    return b.x + n.x * (b.y + n.y * b.z);
}

#ifdef AO_TABLE_BINDING
layout(std430, binding = AO_TABLE_BINDING) readonly buffer AoTable { uint ao_table[]; };

// Where voxel v (linear index i in a volume of `dims`) lies in V_AO, or -1 where it is not
// stored.
int ao_index(ivec3 v, int i, ivec3 dims) {
    uint first = ao_table[0];
    if (first == AO_WHOLE) return i;
    return ao_pool_index(ao_table[ao_brick(v, dims)], v);
}

// Stores `word` as voxel v's AO in AO_WORDS (V_AO's 16-bit words, as the including shader
// names them), where V_AO stores it.
void ao_store(ivec3 v, int i, ivec3 dims, uint word) {
    int at = ao_index(v, i, dims);
    if (at >= 0) AO_WORDS[at] = uint16_t(word);
}
#endif
#endif
