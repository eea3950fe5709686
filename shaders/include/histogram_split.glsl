// The local histograms' two hemispheres (docs/design.md, "Local-histogram AO"): the scalar per
// voxel's address, whether to split, whether the scalars are integers, 1 / (2 s) per axis and,
// in w, the square of the flat threshold in scalar units per mm (src/ao/histogram_gpu.rs
// writes it). Integer scalars are 16-bit words, the value less the data's least (every integer
// type cao-xr reads spans at most 65536 values): their differences, and so Δ, are those of the
// values exactly, and o . Δ is exact in int; other scalars are f32. The including shader
// defines SPLIT_BINDING.
#extension GL_EXT_buffer_reference_uvec2 : require
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Scalars { float s[]; };
layout(buffer_reference, std430, buffer_reference_align = 2) readonly buffer ScalarWords { uint16_t w[]; };
layout(std430, binding = SPLIT_BINDING) readonly buffer Split {
    uvec2 scalars_address;
    uint split_on;
    uint integer_scalars;
    vec4 half_inv_spacing;
};

float scalar_at(int i) {
    if (integer_scalars != 0u) return float(uint(ScalarWords(scalars_address).w[i]));
    return Scalars(scalars_address).s[i];
}

// Δ(v): the scalar's central differences, neighbours clamped into the grid.
vec3 split_delta(ivec3 v, ivec3 dims) {
    int row = dims.x, slice = dims.x * dims.y;
    ivec3 hi = min(v + 1, dims - 1), lo = max(v - 1, ivec3(0));
    return vec3(scalar_at(hi.x + row * v.y + slice * v.z) - scalar_at(lo.x + row * v.y + slice * v.z),
                scalar_at(v.x + row * hi.y + slice * v.z) - scalar_at(v.x + row * lo.y + slice * v.z),
                scalar_at(v.x + row * v.y + slice * hi.z) - scalar_at(v.x + row * v.y + slice * lo.z));
}

// Whether the scalars are integers, read once in split_at: read in in_back it would be read
// again for every member (the rows a shader writes could alias it), lane by lane on a CPU.
bool split_integer = false;

// Whether v's neighbourhood splits (the gradient is steep enough), and its Δ.
bool split_at(ivec3 v, ivec3 dims, out vec3 d) {
    d = vec3(0.0);
    split_integer = integer_scalars != 0u;
    if (split_on == 0u) return false;
    d = split_delta(v, dims);
    vec3 g = d * half_inv_spacing.xyz;
    return dot(g, g) >= half_inv_spacing.w;
}

// Whether member offset o lies in the back hemisphere H_b (o . Δ > 0) of a split voxel.
bool in_back(ivec3 o, vec3 d) {
    if (split_integer) {
        ivec3 di = ivec3(d);
        return o.x * di.x + o.y * di.y + o.z * di.z > 0;
    }
    return dot(vec3(o), d) > 0.0;
}
