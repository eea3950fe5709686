// The LAO kernel before issue 18 (lao_old.comp, for the benchmark only).
// Local Ambient Occlusion of one voxel, exactly as docs/design.md defines it:
//   A_k = (1/M) sum_{m=1..M} prod_{i=1..m-1} (1 - a_i),  1 - a_i = (1 - O(p_i))^(D / 1 mm)
//   A   = (1/K) sum_k A_k
// dirs[k].xyz is the step D*d_k expressed in index units (mm step / spacing).
// Stopping once the transmittance is exactly 0 leaves every value unchanged.

float transmittance(float o) {
    if (o <= 0.0) return 1.0;
    if (o >= 1.0) return 0.0;
    return pow(1.0 - o, pc.exponent);
}

// Bricks of 2^BRICK_SHIFT voxels per axis (constants.glsl); brick_occupied[b] = 0 means the brick
// and one voxel beyond its upper faces hold only O = 0, so a sample whose footprint starts there
// has O = 0 and transmittance 1.
#include "constants.glsl"

bool footprint_empty(vec3 p, ivec3 bricks) {
    ivec3 q = ivec3(floor(p - 0.5));
    if (any(lessThan(q, ivec3(0))) || any(greaterThanEqual(q, pc.dims.xyz))) return false;
    ivec3 b = q >> BRICK_SHIFT;
    return brick_occupied[b.x + bricks.x * (b.y + bricks.y * b.z)] == 0u;
}

float lao_voxel(ivec3 v) {
    vec3 x = vec3(v) + 0.5;
    float total = 0.0;
    ivec3 bricks = (pc.dims.xyz + (1 << BRICK_SHIFT) - 1) >> BRICK_SHIFT;
    for (uint k = 0u; k < pc.rays; k++) {
        vec3 s = dirs[k].xyz;
        float t = 1.0;
        float sum = 0.0;
        for (uint m = 1u; m <= pc.steps; m++) {
            sum += t;
            if (m == pc.steps) break;
            vec3 p = x + float(m) * s;
            if (footprint_empty(p, bricks)) continue;
            t *= transmittance(opacity_at(p));
            if (t == 0.0) break;
        }
        total += sum;
    }
    return total / float(pc.rays * pc.steps);
}
