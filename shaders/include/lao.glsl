// Local Ambient Occlusion of one voxel, exactly as docs/design.md defines it:
//   A_k = (1/M) sum_{m=1..M} prod_{i=1..m-1} (1 - a_i),  1 - a_i = (1 - O(p_i))^(D / 1 mm)
//   A   = (1/K) sum_k A_k
//
// Define before inclusion (after lao_sample.glsl): the buffer `opacity` (O with a zero border, src/ao/lao.rs LaoLayout),
// the buffer `samples` (LaoSample per ray k and step m, k-major), and push constants with
// `stride` (x: index of voxel (0,0,0), y: row, z: slice), rays, steps, exponent.
//
// Voxel centres sit at integer + 0.5, so sample m of ray k lies at the same integer offset and
// the same trilinear weights from every voxel: both come from the table, and the border is wide
// enough for every footprint to read zeros there (zero padding, exact, without a test). No other
// branch per sample: an empty footprint multiplies by exactly 1, and once the transmittance is 0
// it stays 0, so running every ray to its end changes no value.

float padded_opacity(int b, vec3 f) {
    int sy = pc.stride.y;
    int sz = pc.stride.z;
    return opacity_lerp(opacity_load(b), opacity_load(b + 1), opacity_load(b + sy), opacity_load(b + sy + 1),
                        opacity_load(b + sz), opacity_load(b + sz + 1), opacity_load(b + sz + sy),
                        opacity_load(b + sz + sy + 1), f);
}

// (1 - o)^D for D != 1 mm (o is in [0, 1], up to rounding).
float transmittance(float o) {
    return o >= 1.0 ? 0.0 : pow(max(1.0 - o, 0.0), pc.exponent);
}

// A(v) for the voxel at padded index `base`.
float lao_voxel(int base) {
    uint n = pc.steps - 1u;
    float total = 0.0;
    // One uniform branch per voxel, not per sample: D = 1 mm needs no pow.
    if (pc.exponent == 1.0) {
        for (uint k = 0u; k < pc.rays; k++) {
            float t = 1.0;
            float sum = 1.0;
            for (uint m = 0u; m < n; m++) {
                LaoSample s = samples[k * n + m];
                t *= max(1.0 - padded_opacity(base + s.offset, s.frac), 0.0);
                sum += t;
            }
            total += sum;
        }
    } else {
        for (uint k = 0u; k < pc.rays; k++) {
            float t = 1.0;
            float sum = 1.0;
            for (uint m = 0u; m < n; m++) {
                LaoSample s = samples[k * n + m];
                t *= transmittance(padded_opacity(base + s.offset, s.frac));
                sum += t;
            }
            total += sum;
        }
    }
    return total / float(pc.rays * pc.steps);
}

// The padded index of voxel v.
int lao_base(ivec3 v) {
    return pc.stride.x + v.x + pc.stride.y * v.y + pc.stride.z * v.z;
}
