// Where voxel v's O and V_PAO lie in the frame's staged boxes (src/ao/cao.rs Cao::stage): the
// host keeps both and stages only the boxes a frame's restore, clip and update passes cover,
// each x fastest, the box's first voxel at pc.box_max.w. Define before inclusion: the push
// block `pc` with box_min and box_max.

int staged_index(ivec3 v) {
    ivec3 r = v - pc.box_min.xyz;
    ivec3 n = pc.box_max.xyz - pc.box_min.xyz;
    return pc.box_max.w + r.x + n.x * (r.y + n.y * r.z);
}
