// CAO's voxel categories (0 = a: clipped away, 1 = b: AO affected by the cut, 2 = c: unaffected),
// two bits per voxel, sixteen to a word (src/ao/cao.rs MASK_BITS).
// Define before inclusion: `mask` (the words), and MASK_WRITE in the passes that set them.

uint mask_get(int i) {
    return (mask[i >> 4] >> (2u * uint(i & 15))) & 3u;
}

#ifdef MASK_WRITE
// Neighbouring voxels share a word and may be written at once: the two bits are cleared and
// set atomically, each voxel's by the one invocation that owns it.
void mask_set(int i, uint category) {
    uint shift = 2u * uint(i & 15);
    atomicAnd(mask[i >> 4], ~(3u << shift));
    atomicOr(mask[i >> 4], category << shift);
}
#endif
