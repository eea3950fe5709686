// The opacity volume O of docs/design.md, read from a storage buffer (x fastest, 16-bit unorm
// words: unorm16.glsl) and interpolated in the shader, so the GPU matches the CPU reference
// instead of a sampler's fixed-point weights. Voxel q has its centre at index-space point q + 0.5;
// outside the grid O = 0 (zero padding).

float opacity_load(int i) {
    return unorm16_value(uint(opacity[i]));
}

float opacity_voxel(ivec3 q) {
    if (any(lessThan(q, ivec3(0))) || any(greaterThanEqual(q, pc.dims.xyz))) {
        return 0.0;
    }
    return opacity_load(q.x + pc.dims.x * (q.y + pc.dims.y * q.z));
}

float opacity_lerp(float c000, float c100, float c010, float c110,
                   float c001, float c101, float c011, float c111, vec3 f) {
    float x00 = mix(c000, c100, f.x);
    float x10 = mix(c010, c110, f.x);
    float x01 = mix(c001, c101, f.x);
    float x11 = mix(c011, c111, f.x);
    return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
}

// Trilinear O at index-space point p. The footprint is bounds-checked once: inside the grid the
// eight voxels are read directly, at the border each read is checked (zero padding).
float opacity_at(vec3 p) {
    vec3 c = p - 0.5;
    vec3 fl = floor(c);
    vec3 f = c - fl;
    ivec3 q = ivec3(fl);
    if (all(greaterThanEqual(q, ivec3(0))) && all(lessThan(q + 1, pc.dims.xyz))) {
        int sy = pc.dims.x;
        int sz = pc.dims.x * pc.dims.y;
        int b = q.x + sy * q.y + sz * q.z;
        return opacity_lerp(opacity_load(b), opacity_load(b + 1), opacity_load(b + sy), opacity_load(b + sy + 1),
                            opacity_load(b + sz), opacity_load(b + sz + 1), opacity_load(b + sz + sy),
                            opacity_load(b + sz + sy + 1), f);
    }
    return opacity_lerp(opacity_voxel(q), opacity_voxel(q + ivec3(1, 0, 0)),
                        opacity_voxel(q + ivec3(0, 1, 0)), opacity_voxel(q + ivec3(1, 1, 0)),
                        opacity_voxel(q + ivec3(0, 0, 1)), opacity_voxel(q + ivec3(1, 0, 1)),
                        opacity_voxel(q + ivec3(0, 1, 1)), opacity_voxel(q + ivec3(1, 1, 1)), f);
}
