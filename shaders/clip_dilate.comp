#version 460
// Dilation map (src/clip/gpu.rs; reference: `dilate` in src/clip/mod.rs): one thread per texel,
// in x, y the hull along Z of the spheres centred on the surface points of every texel within
// reach, i.e. the 2D Minkowski sum of the clip map with a sphere (paper, Sect. 3.4 step 3, Fig. 7). The
// sphere comes as a kernel over texel offsets built on the host (`DilationKernel`), shared with
// the CPU version, so both do the same float operations and agree bit for bit.
//
// Unlike the CPU loop this one has no branches (a SIMD-friendly form of the same sum): an empty
// texel (EMPTY_IN, EMPTY_OUT) and an offset outside the sphere (height EMPTY_OUT) give terms that
// cannot win the min / max (EMPTY_IN - h == EMPTY_IN, z + EMPTY_OUT == EMPTY_OUT, ...), and the
// columns visited per row are those of the sphere's disc (`widths`), outside which every height
// is EMPTY_OUT, and of the row's non-empty span (clip_dilate_rows.comp), outside which every
// texel is empty. In z, w: the contraction of the shape by the same sphere, for probe tools.
layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, set = 0, binding = 0) readonly buffer Clip { vec4 clip[]; };
// widths[|dj|] for |dj| in 0..=reach: the largest |di| inside the sphere (-1: none), then
// heights[|dj| * (reach + 1) + |di|]: the sphere's half-height at that offset.
layout(std430, set = 0, binding = 1) readonly buffer Kernel { uint kernel[]; };
layout(std430, set = 0, binding = 2) readonly buffer Rows { ivec2 rows[]; };
layout(std430, set = 0, binding = 3) writeonly buffer Dilated { vec4 dilated[]; };

layout(push_constant) uniform Push {
    int res;
    int reach;
} pc;

#include "constants.glsl"

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, ivec2(pc.res)))) return;
    int stride = pc.reach + 1;
    float lo = EMPTY_IN;
    float hi = EMPTY_OUT;
    // The contraction (src/clip/mod.rs `dilate`): max of in + h, min of out - h over the disc,
    // emptied by any empty or off-map texel in it; an empty texel gives in + h = EMPTY_IN.
    float c_lo = EMPTY_OUT;
    float c_hi = EMPTY_IN;
    bool contracted = true;
    for (int qj = p.y - pc.reach; qj <= p.y + pc.reach; qj++) {
        int dj = abs(qj - p.y);
        int width = int(kernel[dj]);
        if (width < 0) continue;
        // Texels beyond the row's non-empty span (or off the map) are empty: they empty the
        // contraction and cannot move the dilation's hull.
        if (qj < 0 || qj >= pc.res) {
            contracted = false;
            continue;
        }
        int row = stride + dj * stride;
        ivec2 span = rows[qj];
        if (p.x - width < span.x || p.x + width > span.y) contracted = false;
        int qi0 = max(p.x - width, span.x);
        int qi1 = min(p.x + width, span.y);
        for (int qi = qi0; qi <= qi1; qi++) {
            vec4 c = clip[qj * pc.res + qi];
            float h = uintBitsToFloat(kernel[row + abs(qi - p.x)]);
            float last_out = c.z <= c.w ? c.w : c.y;
            lo = min(lo, c.x - h);
            hi = max(hi, last_out + h);
            c_lo = max(c_lo, c.x + h);
            c_hi = min(c_hi, c.y - h);
        }
    }
    if (!contracted || c_lo > c_hi) {
        c_lo = EMPTY_IN;
        c_hi = EMPTY_OUT;
    }
    dilated[p.y * pc.res + p.x] = vec4(lo, hi, c_lo, c_hi);
}
