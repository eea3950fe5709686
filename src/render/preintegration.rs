//! Pre-integrated transfer functions (Engel, Kraus and Ertl 2001): the colour and opacity of a
//! whole ray step whose scalar runs linearly from a front to a back value, looked up in a 2-D
//! table instead of classifying one point per step. Sharp TFs and thin layers that a point
//! sample steps over still contribute, so the picture does not band.
//!
//! With the TF's opacity alpha(s) per mm read as an extinction tau(s) = -ln(1 - alpha(s)) per
//! mm, a step of D mm from s_f to s_b has (colour inside the step not self-attenuated)
//!   tau_bar = (1 / (s_b - s_f)) * integral_{s_f}^{s_b} tau(s) ds,
//!   alpha   = 1 - exp(-D tau_bar),
//!   C       = alpha * (integral c tau ds) / (integral tau ds)   (premultiplied),
//! computed from prefix integrals, so a table costs O(n + SIZE^2). Where s_f = s_b this is the
//! point sample 1 - (1 - alpha(s))^D with colour c(s) exactly.

/// Texels per side of the table (front value along x, back value along y).
pub const SIZE: usize = 256;

/// The ray caster's clamp of a sample's opacity per mm (an opacity of 1 has no extinction).
const MAX_ALPHA: f64 = 0.9999;

/// Trapezoids of the integral of a step's transmittance ([`tables`]): a position within 1/128
/// of a step.
const POSITION_STEPS: usize = 64;

/// The table for a TF lookup table `lut` (RGBA, A = opacity per mm, spread evenly over the value
/// range) and a step of `step_mm`: `size * size` entries (premultiplied RGB, opacity), entry
/// (f, b) at index b * size + f for front value f / (size - 1) and back value b / (size - 1) of
/// the range.
pub fn table(lut: &[[f32; 4]], step_mm: f32, size: usize) -> Vec<[f32; 4]> {
    tables(lut, step_mm, size).0
}

/// [`table`], and beside it, per entry, where in the step its light comes from: the mean
/// position of what the step adds to the ray, its extinction attenuated by the step's own
/// opacity in front of it, from 0 at the front sample to 1 at the back (0.5 where the step adds
/// nothing). With T(x) the transmittance from the front to x, that density is -T'(x) / alpha,
/// so the mean is (integral_0^1 T dx - T(1)) / (1 - T(1)); T comes from the prefix integral of
/// the extinction, exact at every point, and the integral takes `POSITION_STEPS` trapezoids.
/// The ray caster shades the step there (gradient, AO, SH): at the surface a sharp TF puts
/// inside the step, rather than at its middle.
pub fn tables(lut: &[[f32; 4]], step_mm: f32, size: usize) -> (Vec<[f32; 4]>, Vec<f32>) {
    let n = lut.len();
    if n == 0 || size < 2 {
        return (vec![[0.0; 4]; size * size], vec![0.5; size * size]);
    }
    let tau = |c: &[f32; 4]| -(1.0 - (c[3] as f64).clamp(0.0, MAX_ALPHA)).ln();
    // Integrands at the LUT's entries: tau and tau * rgb.
    let f: Vec<[f64; 4]> = lut
        .iter()
        .map(|c| {
            let t = tau(c);
            [t, t * c[0] as f64, t * c[1] as f64, t * c[2] as f64]
        })
        .collect();
    // Prefix integrals by the trapezoid rule (the integrand is linear between entries, as the
    // ray caster's linear LUT filtering makes it).
    let mut prefix = vec![[0.0f64; 4]; n];
    for i in 1..n {
        for k in 0..4 {
            prefix[i][k] = prefix[i - 1][k] + 0.5 * (f[i - 1][k] + f[i][k]);
        }
    }
    // Integrand and integral at a continuous LUT position x in [0, n - 1].
    let at = |x: f64| -> ([f64; 4], [f64; 4]) {
        let i = (x.floor() as usize).min(n.saturating_sub(2));
        let j = (i + 1).min(n - 1);
        let w = x - i as f64;
        let d = |k: usize| f[j][k] - f[i][k];
        let value = std::array::from_fn(|k| f[i][k] + w * d(k));
        // The integral from entry i to x of the linear integrand.
        let integral = std::array::from_fn(|k| prefix[i][k] + w * (f[i][k] + 0.5 * w * d(k)));
        (value, integral)
    };
    let step = step_mm as f64;
    let scale = (n - 1) as f64 / (size - 1) as f64;
    let mut out = Vec::with_capacity(size * size);
    let mut where_ = Vec::with_capacity(size * size);
    for b in 0..size {
        let xb = b as f64 * scale;
        let (_, ib) = at(xb);
        for fr in 0..size {
            let xf = fr as f64 * scale;
            let (vf, i_f) = at(xf);
            // Mean integrands over the step: the point value where front = back.
            let mean: [f64; 4] = if fr == b {
                vf
            } else {
                let width = (b as f64 - fr as f64) * scale;
                std::array::from_fn(|k| (ib[k] - i_f[k]) / width)
            };
            let alpha = 1.0 - (-step * mean[0]).exp();
            let rgb = |k: usize| {
                if mean[0] > 0.0 {
                    (mean[k] / mean[0] * alpha) as f32
                } else {
                    0.0
                }
            };
            out.push([rgb(1), rgb(2), rgb(3), alpha as f32]);
            let x = if fr != b && alpha > 1e-6 {
                // T at a fraction u of the step, from the extinction integral up to there.
                let width = xb - xf;
                let trans = |u: f64| {
                    let (_, iu) = at(xf + u * width);
                    (-step * (iu[0] - i_f[0]) / width).exp()
                };
                let m = POSITION_STEPS;
                let t: Vec<f64> = (0..=m).map(|k| trans(k as f64 / m as f64)).collect();
                let area = (0..m).map(|k| 0.5 * (t[k] + t[k + 1])).sum::<f64>() / m as f64;
                ((area - t[m]) / (1.0 - t[m])).clamp(0.0, 1.0)
            } else {
                0.5
            };
            where_.push(x as f32);
        }
    }
    (out, where_)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp_lut(n: usize, alpha: impl Fn(f64) -> f64, rgb: [f32; 3]) -> Vec<[f32; 4]> {
        (0..n)
            .map(|i| {
                let u = i as f64 / (n - 1) as f64;
                [rgb[0], rgb[1], rgb[2], alpha(u) as f32]
            })
            .collect()
    }

    /// On the diagonal the table is the ray caster's point sample.
    #[test]
    fn equal_front_and_back_give_the_point_sample() {
        let lut = ramp_lut(4096, |u| 0.8 * u, [0.9, 0.5, 0.2]);
        let t = table(&lut, 0.5, SIZE);
        for k in [0, 17, 128, 255] {
            let u = k as f64 / (SIZE - 1) as f64;
            let want = 1.0 - (1.0 - 0.8 * u).powf(0.5);
            let e = t[k * SIZE + k];
            assert!((e[3] as f64 - want).abs() < 1e-5, "{k}: {} vs {want}", e[3]);
            assert!((e[0] as f64 - 0.9 * want).abs() < 1e-5);
            assert!((e[2] as f64 - 0.2 * want).abs() < 1e-5);
        }
    }

    /// A thin opaque spike between front and back values is not stepped over: the step's
    /// opacity is that of the spike's integral, whichever way the step crosses it.
    #[test]
    fn a_thin_layer_between_the_samples_still_counts() {
        let n = 4096;
        // Extinction 5 per mm on a band 1/200 of the range wide, zero elsewhere.
        let lut: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                let u = i as f64 / (n - 1) as f64;
                let a = if (0.5..0.505).contains(&u) {
                    1.0 - (-5.0f64).exp()
                } else {
                    0.0
                };
                [1.0, 1.0, 1.0, a as f32]
            })
            .collect();
        let t = table(&lut, 1.0, SIZE);
        let (f, b) = (64, 192); // values 0.25 and 0.75: the band is a hundredth of the way
        let want = 1.0 - (-5.0 * 0.005 / 0.5f64).exp();
        for e in [t[b * SIZE + f], t[f * SIZE + b]] {
            assert!((e[3] as f64 - want).abs() < 2e-3, "{} vs {want}", e[3]);
        }
        // Point samples at either end see nothing.
        assert_eq!(t[f * SIZE + f][3], 0.0);
        assert_eq!(t[b * SIZE + b][3], 0.0);
    }

    /// Against brute force on a real preset: the step split into 2000 point samples along the
    /// linear scalar ramp (the LUT linearly interpolated, as the GPU samples it).
    #[test]
    fn agrees_with_fine_point_sampling_on_a_real_tf() {
        let tf = crate::volume::transfer::TransferFunction::preset("ct-bone").unwrap();
        let n = 4096;
        let lut = tf.lut((-1024.0, 3071.0), n);
        let step = 1.5f32;
        let t = table(&lut, step, SIZE);
        let sample = |x: f64| {
            let i = (x.floor() as usize).min(n - 2);
            let w = x - i as f64;
            std::array::from_fn::<f64, 4, _>(|k| {
                lut[i][k] as f64 * (1.0 - w) + lut[i + 1][k] as f64 * w
            })
        };
        let mut rng = crate::rng::SplitMix64(3);
        for _ in 0..200 {
            let (f, b) = (
                (rng.unit() * SIZE as f64) as usize,
                (rng.unit() * SIZE as f64) as usize,
            );
            let scale = (n - 1) as f64 / (SIZE - 1) as f64;
            let (xf, xb) = (f as f64 * scale, b as f64 * scale);
            let m = 2000;
            let mut trans = 1.0;
            for i in 0..m {
                let c = sample(xf + (xb - xf) * (i as f64 + 0.5) / m as f64);
                trans *= (1.0 - c[3].min(MAX_ALPHA)).powf(step as f64 / m as f64);
            }
            let got = t[b * SIZE + f][3] as f64;
            assert!(
                (got - (1.0 - trans)).abs() < 1e-3,
                "({f}, {b}): {got} vs {}",
                1.0 - trans
            );
        }
    }

    /// The light of a step comes from where its extinction is: a thin band a fifth of the way
    /// from the front value to the back one is shaded a fifth of the way into the step, from
    /// either side; a uniform or empty step at its middle.
    #[test]
    fn the_shading_position_follows_the_extinction() {
        let n = 4096;
        let band = |lo: f64| -> Vec<[f32; 4]> {
            (0..n)
                .map(|i| {
                    let u = i as f64 / (n - 1) as f64;
                    let a = if (lo..lo + 0.004).contains(&u) {
                        0.9
                    } else {
                        0.0
                    };
                    [1.0, 1.0, 1.0, a as f32]
                })
                .collect()
        };
        let (_, at) = tables(&band(0.6), 1.0, SIZE);
        let (lo, hi) = (128, 255); // values ~0.5 and 1.0
        let u = |k: usize| k as f64 / (SIZE - 1) as f64;
        let want = (0.602 - u(lo)) / (u(hi) - u(lo));
        let got = at[hi * SIZE + lo] as f64;
        assert!((got - want).abs() < 0.01, "{got} vs {want}");
        let back = at[lo * SIZE + hi] as f64;
        assert!(
            (back - (1.0 - want)).abs() < 0.01,
            "{back} vs {}",
            1.0 - want
        );
        // Empty, and uniform (front = back): the middle.
        assert_eq!(at[10 * SIZE + 20], 0.5);
        assert_eq!(at[lo * SIZE + lo], 0.5);
        // The tables agree with `table`.
        assert_eq!(
            tables(&band(0.6), 1.0, SIZE).0,
            table(&band(0.6), 1.0, SIZE)
        );
        // A long step into opaque tissue (entered 30 % of the way in) gets its light from just
        // behind the entry, as the tissue hides the rest: 0.3 + 1 / (D tau) = 0.38, not the
        // middle of the opaque part (0.65).
        let solid: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                let a = if i as f64 / (n - 1) as f64 >= 0.65 {
                    0.95
                } else {
                    0.0
                };
                [1.0, 1.0, 1.0, a]
            })
            .collect();
        let (_, at) = tables(&solid, 4.0, SIZE);
        let x = at[hi * SIZE + lo] as f64;
        let want = (0.65 - u(lo)) / (u(hi) - u(lo)) + 1.0 / (4.0 * -(0.05f64).ln());
        assert!((x - want).abs() < 0.02, "{x} vs {want}");
    }

    /// Colour is the extinction-weighted mean: where only one colour is opaque, the step takes
    /// that colour.
    #[test]
    fn colour_follows_the_extinction() {
        let n = 1024;
        let lut: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                if i < n / 2 {
                    [1.0, 0.0, 0.0, 0.0]
                } else {
                    [0.0, 0.0, 1.0, 0.5]
                }
            })
            .collect();
        let t = table(&lut, 1.0, SIZE);
        let e = t[(SIZE - 1) * SIZE];
        assert!(
            e[3] > 0.0 && e[0] < 0.01 * e[3] && (e[2] - e[3]).abs() < 1e-4,
            "{e:?}"
        );
    }
}
