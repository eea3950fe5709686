//! Real spherical harmonics, bands 0..3 (16 coefficients), in the usual graphics convention:
//! coefficient index k = l*(l+1)+m, z the polar axis, orthonormal over the sphere (integral of
//! Y_k * Y_k' over the sphere = delta(k, k')), the constants of Sloan's "Stupid Spherical
//! Harmonics (SH) Tricks" but every sign positive (no Condon-Shortley phase, as in Ramamoorthi and
//! Hanrahan), e.g. Y_1,-1 = +0.4886 y. The visibility volume (`crate::ao::sh`) and the light
//! both use it: V_k and L_k must share it, since the signs of the odd-m coefficients would
//! otherwise flip.
//!
//! # Conventions shared by the visibility volume and the light
//!
//! Visibility: V_k = (1/N) sum_i V(w_i) Y_k(w_i) over N uniform directions (Ritschel's eq. 1), an
//! estimate of (1/4pi) * integral of V * Y_k. Light: L_k = integral of L(w) * Y_k(w) dw per colour
//! channel. Then the emission of a voxel of albedo rho is
//!
//! E = rho * sum_k V_k L_k = rho * (1/4pi) * integral of V(w) L(w) dw,
//!
//! the mean visible radiance (exact for band-limited V or L). An empty volume (V = 1, so
//! V_k = Y_0 delta_k0) under a constant environment L = c gives L_0 = c * 4pi * Y_0 and
//! E = rho * Y_0 * c * 4pi * Y_0 = rho * c exactly, since Y_0^2 = 1/(4pi).
//!
//! The volume stores each V_k as snorm8 of V_k / Y_0 (see `crate::ao::sh::quantize`): by
//! Cauchy-Schwarz |V_k| <= (1/4pi) * sqrt(4pi) = Y_0, so that range is the whole of it.

use glam::{DVec3, Vec3};

/// Number of coefficients of bands 0..3.
pub const COEFFS_MAX: usize = 16;

pub use crate::shader_constants::Y0;

// Normalisation constants (Sloan's appendix), named after the GLSL twin.
const C1: f64 = 0.488_602_511_902_919_9; // sqrt(3 / 4pi)
const C2A: f64 = 1.092_548_430_592_079_2; // sqrt(15 / 4pi)
const C2B: f64 = 0.315_391_565_252_520_05; // sqrt(5 / 16pi)
const C2C: f64 = 0.546_274_215_296_039_6; // sqrt(15 / 16pi)
const C3A: f64 = 0.590_043_589_926_643_5; // sqrt(35 / 32pi)
const C3B: f64 = 2.890_611_442_640_554; // sqrt(105 / 4pi)
const C3C: f64 = 0.457_045_799_464_465_8; // sqrt(21 / 32pi)
const C3D: f64 = 0.373_176_332_590_115_4; // sqrt(7 / 16pi)
const C3E: f64 = 1.445_305_721_320_277; // sqrt(105 / 16pi)

/// The 16 basis functions at the unit vector `d` = (x, y, z).
pub fn eval(d: DVec3) -> [f64; COEFFS_MAX] {
    let (x, y, z) = (d.x, d.y, d.z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    [
        Y0,
        C1 * y,
        C1 * z,
        C1 * x,
        C2A * x * y,
        C2A * y * z,
        C2B * (3.0 * z2 - 1.0),
        C2A * x * z,
        C2C * (x2 - y2),
        C3A * y * (3.0 * x2 - y2),
        C3B * x * y * z,
        C3C * y * (5.0 * z2 - 1.0),
        C3D * z * (5.0 * z2 - 3.0),
        C3C * x * (5.0 * z2 - 1.0),
        C3E * z * (x2 - y2),
        C3A * x * (x2 - 3.0 * y2),
    ]
}

/// [`eval`] in single precision (what the shader computes).
pub fn eval_f32(d: Vec3) -> [f32; COEFFS_MAX] {
    eval(d.as_dvec3()).map(|v| v as f32)
}

/// Band l of coefficient index k (k = l*(l+1)+m).
pub fn band(k: usize) -> usize {
    match k {
        0 => 0,
        1..=3 => 1,
        4..=8 => 2,
        _ => 3,
    }
}

/// A deterministic product quadrature over the sphere: Gauss-Legendre nodes in z = cos(theta)
/// times `n_phi` equally spaced longitudes (offset by half a step). Returns (unit direction,
/// solid angle) pairs whose weights sum to 4pi. It integrates every polynomial of degree
/// <= min(2 n_z - 1, n_phi - 1) in (x, y, z) exactly, so band-limited integrands (such as
/// products of rotated SH of bands <= 3) come out exact.
pub fn sphere_quadrature(n_z: usize, n_phi: usize) -> Vec<(DVec3, f64)> {
    let (nodes, weights) = gauss_legendre(n_z);
    let dphi = std::f64::consts::TAU / n_phi as f64;
    let mut out = Vec::with_capacity(n_z * n_phi);
    for (&z, &w) in nodes.iter().zip(&weights) {
        let r = (1.0 - z * z).max(0.0).sqrt();
        for j in 0..n_phi {
            let phi = (j as f64 + 0.5) * dphi;
            out.push((DVec3::new(r * phi.cos(), r * phi.sin(), z), w * dphi));
        }
    }
    out
}

/// Gauss-Legendre nodes and weights on [-1, 1] (Newton on P_n from Chebyshev guesses).
fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut nodes = vec![0.0; n];
    let mut weights = vec![0.0; n];
    for i in 0..n.div_ceil(2) {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // Recurrence for P_n(x) and its derivative.
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
            let dx = p1 / dp;
            x -= dx;
            if dx.abs() < 1e-15 {
                break;
            }
        }
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        nodes[i] = x;
        nodes[n - 1 - i] = -x;
        weights[i] = w;
        weights[n - 1 - i] = w;
    }
    (nodes, weights)
}

/// Numerical projection: integral over the sphere of f(w) * Y_k(w) dw, with about `samples`
/// quadrature points (an even number of latitudes, so a kink at z = 0 falls between nodes of
/// each half and converges fast).
pub fn project_fn(f: impl Fn(DVec3) -> f64, samples: usize) -> [f64; COEFFS_MAX] {
    let n_z = ((samples as f64 / 2.0).sqrt() as usize).max(2);
    let n_z = n_z + n_z % 2;
    let n_phi = (samples / n_z).max(8);
    // Two Gauss-Legendre halves, one on each hemisphere, each exact for polynomials there.
    let (nodes, weights) = gauss_legendre(n_z / 2);
    let dphi = std::f64::consts::TAU / n_phi as f64;
    let mut acc = [0.0; COEFFS_MAX];
    for half in [-1.0, 1.0] {
        for (&t, &w) in nodes.iter().zip(&weights) {
            // Map [-1, 1] onto [0, 1] or [-1, 0].
            let z = half * 0.5 * (t + 1.0);
            let r = (1.0 - z * z).max(0.0).sqrt();
            for j in 0..n_phi {
                let phi = (j as f64 + 0.5) * dphi;
                let d = DVec3::new(r * phi.cos(), r * phi.sin(), z);
                let fw = f(d) * 0.5 * w * dphi;
                for (a, y) in acc.iter_mut().zip(eval(d)) {
                    *a += fw * y;
                }
            }
        }
    }
    acc
}

/// Zonal coefficients (m = 0 terms, per band) of (1/4pi) * integral over {w.z > 0} of Y_l0(w):
/// (1/4pi) * 2pi * integral_0^1 Y_l0(z) dz. Band 2 vanishes (integral of 3z^2 - 1 over [0, 1]).
const HALF_SPACE_ZONAL: [f64; 4] = [Y0 / 2.0, C1 / 4.0, 0.0, -C3D / 8.0];

/// Visibility coefficients V_k = (1/4pi) * integral over {w . n > 0} of Y_k(w) dw: visibility 1
/// in the open half space around `n`, 0 in the other (an infinite opaque wall). Closed form: the
/// zonal coefficients for n = z rotated to n, V_lm = sqrt(4pi / (2l+1)) * zonal_l * Y_lm(n).
pub fn half_space_visibility(n: DVec3) -> [f64; COEFFS_MAX] {
    let y = eval(n.normalize());
    let mut out = [0.0; COEFFS_MAX];
    for (k, o) in out.iter_mut().enumerate() {
        let l = band(k);
        let rot = (4.0 * std::f64::consts::PI / (2 * l + 1) as f64).sqrt();
        *o = rot * HALF_SPACE_ZONAL[l] * y[k];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::test_rng::Rng;
    use std::f64::consts::PI;

    #[test]
    fn constants_match_their_formulas() {
        let c = |num: f64, den: f64| (num / (den * PI)).sqrt();
        let want = [
            (Y0, c(1.0, 4.0)),
            (C1, c(3.0, 4.0)),
            (C2A, c(15.0, 4.0)),
            (C2B, c(5.0, 16.0)),
            (C2C, c(15.0, 16.0)),
            (C3A, c(35.0, 32.0)),
            (C3B, c(105.0, 4.0)),
            (C3C, c(21.0, 32.0)),
            (C3D, c(7.0, 16.0)),
            (C3E, c(105.0, 16.0)),
        ];
        for (i, (got, w)) in want.iter().enumerate() {
            assert!((got - w).abs() < 1e-15, "constant {i}: {got} vs {w}");
        }
    }

    #[test]
    fn basis_is_orthonormal() {
        // Degree <= 6 integrands: 4 x 8 nodes integrate them exactly.
        let q = sphere_quadrature(4, 8);
        let total: f64 = q.iter().map(|(_, w)| w).sum();
        assert!((total - 4.0 * PI).abs() < 1e-12);
        let mut gram = [[0.0; COEFFS_MAX]; COEFFS_MAX];
        for (d, w) in &q {
            assert!((d.length() - 1.0).abs() < 1e-12);
            let y = eval(*d);
            for i in 0..COEFFS_MAX {
                for j in 0..COEFFS_MAX {
                    gram[i][j] += w * y[i] * y[j];
                }
            }
        }
        for (i, row) in gram.iter().enumerate() {
            for (j, g) in row.iter().enumerate() {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((g - want).abs() < 1e-12, "<Y{i}, Y{j}> = {g}");
            }
        }
    }

    #[test]
    fn known_values_fix_the_sign_convention() {
        // The table at +x, +y, +z: no Condon-Shortley phase, so x, y, z give positive l = 1 terms.
        let x = eval(DVec3::X);
        assert!((x[3] - C1).abs() < 1e-15 && x[1] == 0.0 && x[2] == 0.0);
        assert!((x[8] - C2C).abs() < 1e-15 && (x[6] + C2B).abs() < 1e-15);
        assert!((x[15] - C3A).abs() < 1e-15 && (x[13] + C3C).abs() < 1e-15);
        let y = eval(DVec3::Y);
        assert!((y[1] - C1).abs() < 1e-15 && (y[9] + C3A).abs() < 1e-15);
        let z = eval(DVec3::Z);
        assert!((z[2] - C1).abs() < 1e-15 && (z[6] - 2.0 * C2B).abs() < 1e-15);
        assert!((z[12] - 2.0 * C3D).abs() < 1e-15);
        // Addition theorem: sum over m of Y_lm(a) Y_lm(a) = (2l+1)/4pi for any unit a.
        let mut rng = Rng::new(3);
        for _ in 0..20 {
            let y = eval(rng.unit());
            for l in 0..4 {
                let s: f64 = (l * l..(l + 1) * (l + 1)).map(|k| y[k] * y[k]).sum();
                assert!((s - (2 * l + 1) as f64 / (4.0 * PI)).abs() < 1e-12);
            }
        }
        let f = eval_f32(Vec3::new(0.6, 0.0, 0.8));
        let d = eval(DVec3::new(0.6, 0.0, 0.8));
        for k in 0..COEFFS_MAX {
            assert!((f[k] as f64 - d[k]).abs() < 1e-6);
        }
    }

    #[test]
    fn projection_of_one_is_band_zero() {
        let p = project_fn(|_| 1.0, 8192);
        assert!((p[0] - (4.0 * PI).sqrt()).abs() < 1e-10, "{}", p[0]);
        for (k, v) in p.iter().enumerate().skip(1) {
            assert!(v.abs() < 1e-10, "coefficient {k} = {v}");
        }
    }

    #[test]
    fn projection_of_clamped_cosine_matches_zonal_coefficients() {
        let p = project_fn(|d| d.z.max(0.0), 8192);
        let want = [
            (0, PI.sqrt() / 2.0),
            (2, (PI / 3.0).sqrt()),
            (6, (5.0 * PI).sqrt() / 8.0),
            (12, 0.0),
        ];
        for (k, v) in want {
            assert!((p[k] - v).abs() < 1e-9, "coefficient {k}: {} vs {v}", p[k]);
        }
        for k in [1, 3, 4, 5, 7, 8, 9, 10, 11, 13, 14, 15] {
            assert!(p[k].abs() < 1e-9, "non-zonal coefficient {k} = {}", p[k]);
        }
    }

    #[test]
    fn half_space_visibility_matches_numerical_projection() {
        let mut rng = Rng::new(7);
        let mut normals = vec![DVec3::Z, DVec3::X, -DVec3::Y];
        normals.extend((0..5).map(|_| rng.unit()));
        for n in normals {
            let got = half_space_visibility(n);
            // The wall's edge is oblique to the grid for a general n: converge by brute force.
            let num = project_fn(|w| if w.dot(n) > 0.0 { 1.0 } else { 0.0 }, 400_000);
            for k in 0..COEFFS_MAX {
                let want = num[k] / (4.0 * PI);
                assert!(
                    (got[k] - want).abs() < 2e-4,
                    "n = {n}, k = {k}: closed form {} vs numerical {want}",
                    got[k]
                );
            }
            assert!(
                (got[0] - Y0 / 2.0).abs() < 1e-15,
                "half the sphere is visible"
            );
        }
        // The zonal case exactly: only m = 0, and V_l0 as derived.
        let z = half_space_visibility(DVec3::Z);
        assert!((z[2] - C1 / 4.0).abs() < 1e-15 && z[6].abs() < 1e-15);
        assert!((z[12] + C3D / 8.0).abs() < 1e-15);
    }

    #[test]
    fn visibility_coefficients_respect_the_bound() {
        // Random visibility functions: a few random opaque caps, plus a random smooth
        // semi-transparent attenuation. The bound |V_k| <= Y_0 (and V_0 in [0, Y_0]) must hold.
        let mut rng = Rng::new(23);
        let q = sphere_quadrature(24, 48);
        let mut closest = 0.0f64;
        for _ in 0..200 {
            let caps: Vec<(DVec3, f64)> = (0..1 + rng.next_u64() % 6)
                .map(|_| (rng.unit(), 2.0 * rng.f64() - 1.0))
                .collect();
            let a = rng.unit();
            let s = rng.f64();
            let vis = |w: DVec3| -> f64 {
                if caps.iter().any(|(c, t)| w.dot(*c) > *t) {
                    0.0
                } else {
                    1.0 - s * (0.5 + 0.5 * w.dot(a))
                }
            };
            let mut v = [0.0; COEFFS_MAX];
            for (d, w) in &q {
                let vw = vis(*d) * w / (4.0 * PI);
                for (acc, y) in v.iter_mut().zip(eval(*d)) {
                    *acc += vw * y;
                }
            }
            assert!(v[0] >= 0.0 && v[0] <= Y0 + 1e-12);
            for (k, c) in v.iter().enumerate() {
                assert!(c.abs() <= Y0 + 1e-9, "k = {k}: {c}");
                closest = closest.max(c.abs() / Y0);
            }
        }
        // Visibility 1 everywhere reaches the bound exactly for k = 0.
        let full = project_fn(|_| 1.0, 4096)[0] / (4.0 * PI);
        assert!((full - Y0).abs() < 1e-12);
        assert!(
            closest > 0.5,
            "the random functions span the range: {closest}"
        );
    }
}
