// CAO's voxel categories (0 = a: clipped away, 1 = b: AO affected by the cut, 2 = c: unaffected),
// one byte per voxel, four to a word (src/ao/cao.rs): a quarter of a word per voxel.
// Define before inclusion: `mask` (the words), and MASK_WRITE in the passes that set them.

uint mask_get(int i) {
    return (mask[i >> 2] >> (8u * uint(i & 3))) & 0xffu;
}

#ifdef MASK_WRITE
// Neighbouring voxels share a word and may be written at once: the byte is cleared and set
// atomically, each voxel's by the one invocation that owns it.
void mask_set(int i, uint category) {
    uint shift = 8u * uint(i & 3);
    atomicAnd(mask[i >> 2], ~(0xffu << shift));
    atomicOr(mask[i >> 2], category << shift);
}
#endif
