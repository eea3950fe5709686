// Real spherical harmonics, bands 0..3, the GLSL twin of src/light/sh.rs (k = l*(l+1)+m, z the
// polar axis, orthonormal over the sphere, Sloan's constants with every sign positive: no
// Condon-Shortley phase, the same basis as src/ao/sh.rs).
// A unit test in sh.rs reads this file and checks every SH_C* constant against the Rust ones,
// so keep the `const float NAME = VALUE;` lines one per line.
//
// Emission of a voxel of albedo rho: E = rho * sum_k V_k L_k, V_k the dequantised visibility
// coefficients, L_k the light's coefficients in the data frame (see src/light/mod.rs).

const float SH_C0 = 0.28209479177387814;  // 1 / sqrt(4pi) = Y_0
const float SH_C1 = 0.4886025119029199;   // sqrt(3 / 4pi)
const float SH_C2A = 1.0925484305920792;  // sqrt(15 / 4pi)
const float SH_C2B = 0.31539156525252005; // sqrt(5 / 16pi)
const float SH_C2C = 0.5462742152960396;  // sqrt(15 / 16pi)
const float SH_C3A = 0.5900435899266435;  // sqrt(35 / 32pi)
const float SH_C3B = 2.890611442640554;   // sqrt(105 / 4pi)
const float SH_C3C = 0.4570457994644658;  // sqrt(21 / 32pi)
const float SH_C3D = 0.3731763325901154;  // sqrt(7 / 16pi)
const float SH_C3E = 1.445305721320277;   // sqrt(105 / 16pi)

// The 16 basis functions at the unit vector d.
void sh_eval(vec3 d, out float y[16]) {
    float x = d.x, yy = d.y, z = d.z;
    float x2 = x * x, y2 = yy * yy, z2 = z * z;
    y[0] = SH_C0;
    y[1] = SH_C1 * yy;
    y[2] = SH_C1 * z;
    y[3] = SH_C1 * x;
    y[4] = SH_C2A * x * yy;
    y[5] = SH_C2A * yy * z;
    y[6] = SH_C2B * (3.0 * z2 - 1.0);
    y[7] = SH_C2A * x * z;
    y[8] = SH_C2C * (x2 - y2);
    y[9] = SH_C3A * yy * (3.0 * x2 - y2);
    y[10] = SH_C3B * x * yy * z;
    y[11] = SH_C3C * yy * (5.0 * z2 - 1.0);
    y[12] = SH_C3D * z * (5.0 * z2 - 3.0);
    y[13] = SH_C3C * x * (5.0 * z2 - 1.0);
    y[14] = SH_C3E * z * (x2 - y2);
    y[15] = SH_C3A * x * (x2 - 3.0 * y2);
}

// 8-bit visibility coefficient k of value v (sh.rs, "quantisation"): u = V_0 / Y_0 for k = 0,
// 0.5 + V_k / (2 Y_0) for k >= 1, clamped; byte = floor(255 u + 0.5) (ties up on every GPU,
// unlike round(); pack the bytes yourself rather than relying on a UNORM store's rounding).
uint sh_quantize(int k, float v) {
    float u = k == 0 ? v / SH_C0 : 0.5 + v / (2.0 * SH_C0);
    return uint(floor(clamp(u, 0.0, 1.0) * 255.0 + 0.5));
}

// 8-bit visibility coefficients (sh.rs, "quantisation"): value = scale * unorm + bias, with
// unorm = byte / 255 (what an R8/RGBA8 UNORM texture or unpackUnorm4x8 returns).
// k = 0: V_0 = Y_0 * unorm; k >= 1: V_k = 2 Y_0 * unorm - Y_0.
float sh_dequant(int k, float unorm) {
    return k == 0 ? SH_C0 * unorm : 2.0 * SH_C0 * unorm - SH_C0;
}
