// Where voxel v's O lies in the frame's staged O (src/ao/cao.rs Cao::stage_opacity): the host
// keeps O and stages only the boxes a frame's restore and clip passes cover, each x fastest,
// the box's first voxel at pc.box_max.w. Define before inclusion: the push block `pc` with
// box_min and box_max.

int box_opacity_index(ivec3 v) {
    ivec3 r = v - pc.box_min.xyz;
    ivec3 n = pc.box_max.xyz - pc.box_min.xyz;
    return pc.box_max.w + r.x + n.x * (r.y + n.y * r.z);
}
