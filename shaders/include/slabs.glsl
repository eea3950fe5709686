// A volume split into slabs of whole z-slices (src/gpu/slabs.rs): the table holds the slices per
// slab, then each slab's address. A voxel's index within its slab is its index within the
// volume less the slabs below it, so its value is the same whatever the slab size.
#extension GL_EXT_buffer_reference_uvec2 : require

layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer SlabTable {
    uint slices_per_slab;
    uint table_pad;
    uvec2 slab[];
};

// Which slab holds slice z, and the voxel's index within it.
ivec2 slab_at(SlabTable t, ivec3 p, ivec3 dims) {
    int slices = int(t.slices_per_slab);
    int s = p.z / slices;
    return ivec2(s, p.x + dims.x * (p.y + dims.y * (p.z - s * slices)));
}
