// The local histograms' two hemispheres (docs/design.md, "Local-histogram AO"): the scalar per
// voxel, whether to split, whether the scalars are integers (then o . Δ is exact in int),
// 1 / (2 s) per axis and, in w, the square of the flat threshold in scalar units per mm
// (src/ao/histogram_gpu.rs writes it). The including shader defines SPLIT_BINDING.
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Scalars { float s[]; };
layout(std430, binding = SPLIT_BINDING) readonly buffer Split {
    Scalars scalars;
    uint split_on;
    uint integer_scalars;
    vec4 half_inv_spacing;
};

// Δ(v): the scalar's central differences, neighbours clamped into the grid.
vec3 split_delta(ivec3 v, ivec3 dims) {
    int row = dims.x, slice = dims.x * dims.y;
    ivec3 hi = min(v + 1, dims - 1), lo = max(v - 1, ivec3(0));
    return vec3(scalars.s[hi.x + row * v.y + slice * v.z] - scalars.s[lo.x + row * v.y + slice * v.z],
                scalars.s[v.x + row * hi.y + slice * v.z] - scalars.s[v.x + row * lo.y + slice * v.z],
                scalars.s[v.x + row * v.y + slice * hi.z] - scalars.s[v.x + row * v.y + slice * lo.z]);
}

// Whether v's neighbourhood splits (the gradient is steep enough), and its Δ.
bool split_at(ivec3 v, ivec3 dims, out vec3 d) {
    d = vec3(0.0);
    if (split_on == 0u) return false;
    d = split_delta(v, dims);
    vec3 g = d * half_inv_spacing.xyz;
    return dot(g, g) >= half_inv_spacing.w;
}

// Whether member offset o lies in the back hemisphere H_b (o . Δ > 0) of a split voxel.
bool in_back(ivec3 o, vec3 d) {
    if (integer_scalars != 0u) {
        ivec3 di = ivec3(d);
        return o.x * di.x + o.y * di.y + o.z * di.z > 0;
    }
    return dot(vec3(o), d) > 0.0;
}
