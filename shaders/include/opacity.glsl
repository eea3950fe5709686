// The opacity volume O of DESIGN.md, read from a storage buffer (x fastest) and interpolated in
// the shader, so the GPU matches the CPU reference instead of a sampler's fixed-point weights.
// Voxel q has its centre at index-space point q + 0.5; outside the grid O = 0 (zero padding).

float opacity_voxel(ivec3 q) {
    if (any(lessThan(q, ivec3(0))) || any(greaterThanEqual(q, pc.dims.xyz))) {
        return 0.0;
    }
    return opacity[q.x + pc.dims.x * (q.y + pc.dims.y * q.z)];
}

// Trilinear O at index-space point p.
float opacity_at(vec3 p) {
    vec3 c = p - 0.5;
    vec3 fl = floor(c);
    vec3 f = c - fl;
    ivec3 q = ivec3(fl);
    float c000 = opacity_voxel(q);
    float c100 = opacity_voxel(q + ivec3(1, 0, 0));
    float c010 = opacity_voxel(q + ivec3(0, 1, 0));
    float c110 = opacity_voxel(q + ivec3(1, 1, 0));
    float c001 = opacity_voxel(q + ivec3(0, 0, 1));
    float c101 = opacity_voxel(q + ivec3(1, 0, 1));
    float c011 = opacity_voxel(q + ivec3(0, 1, 1));
    float c111 = opacity_voxel(q + ivec3(1, 1, 1));
    float x00 = mix(c000, c100, f.x);
    float x10 = mix(c010, c110, f.x);
    float x01 = mix(c001, c101, f.x);
    float x11 = mix(c011, c111, f.x);
    return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
}
