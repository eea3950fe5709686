//! Volumetric ambient occlusion by separable filtering (Ruiz, Szirmay-Kalos et al.), exactly as
//! docs/design.md ("Filtered AO") defines it: the openness of a voxel is estimated from the
//! statistics (mean, second moment, minimum, maximum) of the density d over a box tangent to the
//! surface, on the side the gradient points into. This file holds the parameters and the CPU
//! reference (f64, brute force over each box); [`FilterGpu`](super::filter_gpu::FilterGpu) is the
//! separable GPU version tested against it.

use rayon::prelude::*;

/// How the openness is estimated from the box statistics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Estimator {
    /// The CDF reconstructed as t^beta from the minimum, maximum and mean.
    Cdf,
    /// A Gaussian CDF of mean and variance (Winitzki's erf).
    Gauss,
    /// Penner's one-tailed Chebyshev bound on the occluders.
    Penner,
    /// The brute-force fraction of box members no denser than the voxel: the definition the
    /// estimators approximate (slow; for tests and the benchmark's error column).
    Exact,
}

impl Estimator {
    pub const ALL: [Estimator; 4] = [
        Estimator::Cdf,
        Estimator::Gauss,
        Estimator::Penner,
        Estimator::Exact,
    ];

    /// The name in `--ao filter-NAME` and in the sidecar's `estimator`.
    pub fn name(self) -> &'static str {
        match self {
            Estimator::Cdf => "cdf",
            Estimator::Gauss => "gauss",
            Estimator::Penner => "penner",
            Estimator::Exact => "exact",
        }
    }

    /// The number the shader switches on.
    pub fn code(self) -> u32 {
        match self {
            Estimator::Cdf => 0,
            Estimator::Gauss => 1,
            Estimator::Penner => 2,
            Estimator::Exact => 3,
        }
    }
}

/// What is filtered.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FilterInput {
    /// The clipped opacity O_c of LAO (same TF, same clip coverage): a TF change is a refilter.
    Opacity,
    /// The normalised scalar (value - v_min) / (v_max - v_min) times the clip coverage.
    Scalar,
}

impl FilterInput {
    pub fn name(self) -> &'static str {
        match self {
            FilterInput::Opacity => "opacity",
            FilterInput::Scalar => "scalar",
        }
    }
}

/// The filtered AO's parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FilterParams {
    /// R: the tangent box's half-size and its centre's distance from the voxel, in mm.
    pub radius_mm: f64,
    pub estimator: Estimator,
    pub input: FilterInput,
}

impl Default for FilterParams {
    /// 6 mm: on the CT head (about 1 mm voxels) a box of 13 x 13 x 9 voxels, between the
    /// paper's 5 and 10 voxels; it darkens the orbits, the nasal cavity and the gaps between the
    /// teeth without greying whole faces of the skull.
    fn default() -> Self {
        FilterParams {
            radius_mm: 6.0,
            estimator: Estimator::Gauss,
            input: FilterInput::Opacity,
        }
    }
}

impl FilterParams {
    pub fn validate(&self) -> Result<(), String> {
        if !(self.radius_mm.is_finite() && self.radius_mm > 0.0 && self.radius_mm <= 200.0) {
            return Err(format!(
                "--filter-radius-mm must be in (0, 200] mm, got {}",
                self.radius_mm
            ));
        }
        Ok(())
    }

    /// h_a = max(1, round(R / s_a)) voxels per axis.
    pub fn half_widths(&self, spacing: [f64; 3]) -> [usize; 3] {
        spacing.map(|s| ((self.radius_mm / s).round() as usize).max(1))
    }

    /// The farthest the box centre moves from the voxel, per axis: round(R / s_a) voxels.
    pub fn max_offsets(&self, spacing: [f64; 3]) -> [usize; 3] {
        spacing.map(|s| (self.radius_mm / s).round() as usize)
    }

    /// The reach in mm: beyond it a change of d cannot change a voxel's openness. The centre
    /// moves by round(-R n_a / s_a) voxels per axis, at most R + half a voxel diagonal in all
    /// (clamping only shortens it), and a box member lies within the box's half-diagonal of the
    /// centre; the gradient stencil (one voxel) lies inside the box, as h_a >= 1.
    pub fn reach_mm(&self, spacing: [f64; 3]) -> f64 {
        let h = self.half_widths(spacing);
        let norm = |f: &dyn Fn(usize) -> f64| (0..3).map(|a| f(a).powi(2)).sum::<f64>().sqrt();
        self.radius_mm + 0.5 * norm(&|a| spacing[a]) + norm(&|a| h[a] as f64 * spacing[a])
    }
}

/// Winitzki's approximation of erf (a = 0.147), as docs/design.md writes it.
pub fn erf_winitzki(x: f64) -> f64 {
    const A: f64 = 0.147;
    let x2 = x * x;
    let inner = -x2 * (4.0 / std::f64::consts::PI + A * x2) / (1.0 + A * x2);
    x.signum() * (1.0 - inner.exp()).sqrt()
}

/// The statistics of d over one box (out-of-grid members counted with d = 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxStats {
    pub mean: f64,
    pub m2: f64,
    pub min: f64,
    pub max: f64,
}

impl BoxStats {
    pub fn variance(&self) -> f64 {
        (self.m2 - self.mean * self.mean).max(0.0)
    }
}

/// Openness of a voxel of density `dv` from its box statistics, for the three estimators.
pub fn estimate(estimator: Estimator, dv: f64, s: &BoxStats) -> f64 {
    let var = s.variance();
    match estimator {
        Estimator::Cdf => {
            if dv >= s.max {
                1.0
            } else if dv <= s.min {
                0.0
            } else {
                let t = (dv - s.min) / (s.max - s.min);
                if s.mean >= s.max {
                    return 0.0;
                }
                let beta = (s.mean - s.min) / (s.max - s.mean);
                if beta <= 0.0 {
                    1.0
                } else {
                    t.powf(beta)
                }
            }
        }
        Estimator::Gauss => {
            if var <= 1e-12 {
                (dv >= s.mean) as u8 as f64
            } else {
                0.5 * (1.0 + erf_winitzki((dv - s.mean) / (2.0 * var).sqrt()))
            }
        }
        Estimator::Penner => {
            if var <= 1e-12 {
                (dv >= s.mean) as u8 as f64
            } else if dv <= s.mean {
                0.0
            } else {
                let e = (dv - s.mean).powi(2);
                e / (var + e)
            }
        }
        Estimator::Exact => unreachable!("the exact openness counts the box, see filtered_ao"),
    }
}

/// A density volume on the grid, zero outside.
struct Grid<'a> {
    d: &'a [f32],
    dims: [usize; 3],
}

impl Grid<'_> {
    fn at(&self, p: [i64; 3]) -> f64 {
        let inside = (0..3).all(|a| p[a] >= 0 && (p[a] as usize) < self.dims[a]);
        if !inside {
            return 0.0;
        }
        let [x, y, z] = p.map(|c| c as usize);
        self.d[x + self.dims[0] * (y + self.dims[1] * z)] as f64
    }

    /// Every member of the box of half-widths `h` around `c`, in a fixed order.
    fn members(&self, c: [i64; 3], h: [usize; 3]) -> impl Iterator<Item = f64> + '_ {
        let h = h.map(|x| x as i64);
        (-h[2]..=h[2]).flat_map(move |k| {
            (-h[1]..=h[1]).flat_map(move |j| {
                (-h[0]..=h[0]).map(move |i| self.at([c[0] + i, c[1] + j, c[2] + k]))
            })
        })
    }
}

/// The tangent box's centre for voxel `v`: v + round(-R n_a / s_a) per axis (half away from
/// zero), clamped into the grid, with n the unit gradient (central differences, zero padding);
/// v itself where the gradient vanishes.
pub fn box_centre(
    d: &[f32],
    dims: [usize; 3],
    spacing: [f64; 3],
    radius_mm: f64,
    v: [usize; 3],
) -> [i64; 3] {
    let g = Grid { d, dims };
    let vi = v.map(|c| c as i64);
    let grad: [f64; 3] = std::array::from_fn(|a| {
        let (mut lo, mut hi) = (vi, vi);
        lo[a] -= 1;
        hi[a] += 1;
        (g.at(hi) - g.at(lo)) / (2.0 * spacing[a])
    });
    let len = grad.iter().map(|x| x * x).sum::<f64>().sqrt();
    if len <= 0.0 {
        return vi;
    }
    std::array::from_fn(|a| {
        let off = (-radius_mm * grad[a] / len / spacing[a]).round() as i64;
        (vi[a] + off).clamp(0, dims[a] as i64 - 1)
    })
}

/// Brute-force statistics of d over the box of half-widths `h` around `c`.
pub fn box_stats(d: &[f32], dims: [usize; 3], c: [i64; 3], h: [usize; 3]) -> BoxStats {
    let g = Grid { d, dims };
    let n = h.iter().map(|x| 2 * x + 1).product::<usize>() as f64;
    let (mut sum, mut sum2, mut min, mut max) = (0.0, 0.0, f64::INFINITY, f64::NEG_INFINITY);
    for x in g.members(c, h) {
        sum += x;
        sum2 += x * x;
        min = min.min(x);
        max = max.max(x);
    }
    if min == max {
        // A box of one value has exactly that mean and no variance; summing would round them,
        // and a voxel of the same density must compare equal to its box.
        return BoxStats {
            mean: min,
            m2: min * min,
            min,
            max,
        };
    }
    BoxStats {
        mean: sum / n,
        m2: sum2 / n,
        min,
        max,
    }
}

/// The CPU reference: the filtered openness of every voxel of the density `d` (x fastest).
pub fn filtered_ao(d: &[f32], dims: [usize; 3], spacing: [f64; 3], p: &FilterParams) -> Vec<f32> {
    let h = p.half_widths(spacing);
    let n = h.iter().map(|x| 2 * x + 1).product::<usize>() as f64;
    let g = Grid { d, dims };
    (0..dims[0] * dims[1] * dims[2])
        .into_par_iter()
        .map(|i| {
            let v = [
                i % dims[0],
                (i / dims[0]) % dims[1],
                i / (dims[0] * dims[1]),
            ];
            let c = box_centre(d, dims, spacing, p.radius_mm, v);
            let dv = d[i] as f64;
            let a = match p.estimator {
                Estimator::Exact => g.members(c, h).filter(|&x| x <= dv).count() as f64 / n,
                e => estimate(e, dv, &box_stats(d, dims, c, h)),
            };
            a as f32
        })
        .collect()
}

/// The density that is filtered, for the unclipped volume: O itself (`opacity`), or the
/// normalised scalar.
pub fn density(input: FilterInput, opacity: &[f32], vol: &crate::volume::Volume) -> Vec<f32> {
    match input {
        FilterInput::Opacity => opacity.to_vec(),
        FilterInput::Scalar => {
            let (lo, hi) = vol.value_range();
            let span = (hi - lo) as f64;
            (0..vol.voxel_count())
                .into_par_iter()
                .map(|i| {
                    if span > 0.0 {
                        ((vol.voxels.get(i) - lo) as f64 / span) as f32
                    } else {
                        0.0
                    }
                })
                .collect()
        }
    }
}

/// Variance opacity modulation (docs/design.md): the ray caster multiplies each sample's
/// opacity by min(var_s(p) / max, 1), so homogeneous tissue fades and boundaries stay.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VarianceModulation {
    /// The centred box's half-widths come from this radius, as the filters' do.
    pub radius_mm: f64,
    /// V_max, in the data's units squared (HU^2 for CT).
    pub max: f64,
}

/// var_s(v): the variance of the data values over the centred box B(v) of half-widths
/// max(1, round(R / s_a)), out-of-grid members taking v_min; in data units squared. Separable
/// sums in f64 (the values are shifted by v_min, so outside members add nothing). A crop's
/// v_min is the whole's ([`crate::volume::Volume::whole_range`]), so each of its voxels whose
/// box lies in it has the whole's var_s, bit for bit (the same sums in the same order).
pub fn variance_volume(vol: &crate::volume::Volume, radius_mm: f64) -> Vec<f32> {
    let lo = vol.value_range().0;
    let h = FilterParams {
        radius_mm,
        ..Default::default()
    }
    .half_widths(vol.spacing);
    let dims = vol.dims;
    let mut sums: Vec<[f64; 2]> = (0..vol.voxel_count())
        .into_par_iter()
        .map(|i| {
            let x = (vol.voxels.get(i) - lo) as f64;
            [x, x * x]
        })
        .collect();
    let stride = [1, dims[0], dims[0] * dims[1]];
    for axis in 0..3 {
        let src = sums;
        sums = (0..src.len())
            .into_par_iter()
            .map(|i| {
                let c = [
                    i % dims[0],
                    (i / dims[0]) % dims[1],
                    i / (dims[0] * dims[1]),
                ][axis] as i64;
                let mut acc = [0.0; 2];
                for k in -(h[axis] as i64)..=h[axis] as i64 {
                    let q = c + k;
                    if q >= 0 && (q as usize) < dims[axis] {
                        let s = src[(i as i64 + k * stride[axis] as i64) as usize];
                        acc[0] += s[0];
                        acc[1] += s[1];
                    }
                }
                acc
            })
            .collect();
    }
    let n = h.iter().map(|x| 2 * x + 1).product::<usize>() as f64;
    sums.into_par_iter()
        .map(|[s, s2]| {
            let mu = s / n;
            (s2 / n - mu * mu).max(0.0) as f32
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const DIMS: [usize; 3] = [12, 12, 12];

    fn params(estimator: Estimator) -> FilterParams {
        FilterParams {
            radius_mm: 2.0,
            estimator,
            input: FilterInput::Opacity,
        }
    }

    fn volume(f: impl Fn(usize, usize, usize) -> f32) -> Vec<f32> {
        let mut d = Vec::new();
        for z in 0..DIMS[2] {
            for y in 0..DIMS[1] {
                for x in 0..DIMS[0] {
                    d.push(f(x, y, z));
                }
            }
        }
        d
    }

    fn at(a: &[f32], [x, y, z]: [usize; 3]) -> f32 {
        a[x + DIMS[0] * (y + DIMS[1] * z)]
    }

    #[test]
    fn an_empty_volume_is_open_for_every_estimator() {
        let d = vec![0.0; DIMS.iter().product()];
        for e in Estimator::ALL {
            let a = filtered_ao(&d, DIMS, [1.0; 3], &params(e));
            assert!(a.iter().all(|&x| x == 1.0), "{e:?}");
        }
    }

    #[test]
    fn the_surface_of_a_half_space_is_open_for_exact_and_cdf() {
        // Solid for z >= 6: the surface voxels z = 6 look up, into the empty side.
        let d = volume(|_, _, z| if z >= 6 { 1.0 } else { 0.0 });
        for e in [Estimator::Exact, Estimator::Cdf] {
            let a = filtered_ao(&d, DIMS, [1.0; 3], &params(e));
            assert_eq!(at(&a, [6, 6, 6]), 1.0, "{e:?}");
        }
        // The box of the surface voxel sits on the empty side, 2 voxels up.
        assert_eq!(box_centre(&d, DIMS, [1.0; 3], 2.0, [6, 6, 6]), [6, 6, 4]);
    }

    #[test]
    fn the_bottom_of_a_slot_is_darker_than_a_flat_surface() {
        // Solid (1) for z >= 6, with a slot 2 voxels wide (x = 5, 6) and 3 deep (z = 6..8) cut
        // into it; the surface voxels looked at, flat (z = 6) and the slot's bottom (z = 9), are
        // half dense, as a smooth surface's are.
        let d = volume(|x, _, z| {
            let slot = (5..=6).contains(&x);
            match z {
                0..6 => 0.0,
                6..9 if slot => 0.0,
                6 => 0.5,
                9 if slot => 0.5,
                _ => 1.0,
            }
        });
        for e in Estimator::ALL {
            let a = filtered_ao(&d, DIMS, [1.0; 3], &params(e));
            let (flat, bottom) = (at(&a, [1, 6, 6]), at(&a, [5, 6, 9]));
            assert!(bottom < flat, "{e:?}: slot bottom {bottom}, flat {flat}");
        }
    }

    #[test]
    fn box_statistics_count_out_of_grid_members_as_zero() {
        let d = vec![1.0; DIMS.iter().product()];
        let s = box_stats(&d, DIMS, [0, 0, 0], [1, 1, 1]);
        // 8 of the 27 members lie inside the grid.
        assert!((s.mean - 8.0 / 27.0).abs() < 1e-12);
        assert!((s.m2 - 8.0 / 27.0).abs() < 1e-12);
        assert_eq!((s.min, s.max), (0.0, 1.0));
    }

    #[test]
    fn winitzki_erf_is_close_to_erf() {
        // erf(0.5) = 0.5204998778, erf(1) = 0.8427007929, erf(2) = 0.9953222650
        for (x, e) in [
            (0.5, 0.520_499_877_8),
            (1.0, 0.842_700_792_9),
            (2.0, 0.995_322_265),
        ] {
            assert!((erf_winitzki(x) - e).abs() < 2e-4, "{x}");
            assert!((erf_winitzki(-x) + e).abs() < 2e-4, "{x}");
        }
        assert_eq!(erf_winitzki(0.0), 0.0);
    }

    #[test]
    fn estimators_follow_the_definition_in_their_singular_cases() {
        let flat = BoxStats {
            mean: 0.5,
            m2: 0.25,
            min: 0.5,
            max: 0.5,
        };
        assert_eq!(estimate(Estimator::Gauss, 0.5, &flat), 1.0);
        assert_eq!(estimate(Estimator::Gauss, 0.4, &flat), 0.0);
        assert_eq!(estimate(Estimator::Penner, 0.5, &flat), 1.0);
        assert_eq!(estimate(Estimator::Cdf, 0.5, &flat), 1.0);
        let s = BoxStats {
            mean: 0.25,
            m2: 0.25,
            min: 0.0,
            max: 1.0,
        };
        // cdf: t^beta with beta = 0.25 / 0.75
        let want = 0.5f64.powf(1.0 / 3.0);
        assert!((estimate(Estimator::Cdf, 0.5, &s) - want).abs() < 1e-12);
        // penner: (dv - mu)^2 / (var + (dv - mu)^2), var = 0.25 - 0.0625
        let want = 0.0625 / (0.1875 + 0.0625);
        assert!((estimate(Estimator::Penner, 0.5, &s) - want).abs() < 1e-12);
        assert_eq!(estimate(Estimator::Penner, 0.2, &s), 0.0);
    }

    #[test]
    fn the_variance_volume_matches_brute_force_and_fades_homogeneous_tissue() {
        use crate::volume::{Modality, Volume, Voxels};
        let n = 10;
        // Two half-spaces of 100 and about 300 (data units), the low one with a bright voxel.
        let mut v: Vec<f32> = (0..n * n * n)
            .map(|i| {
                if i % n < 5 {
                    100.0
                } else {
                    300.0 + (i * 7 % 13) as f32 * 0.37
                }
            })
            .collect();
        v[2 + n * (3 + n * 4)] = 1000.0;
        let vol = Volume {
            whole_range: None,
            name: "halves".into(),
            dims: [n; 3],
            spacing: [1.0, 1.0, 2.0],
            directions: glam::DMat3::IDENTITY,
            origin: glam::DVec3::ZERO,
            modality: Modality::Unknown,
            voxels: Voxels::F32(v.clone()),
            labels: None,
        };
        let var = variance_volume(&vol, 1.0);
        // Brute force over the centred box, out-of-grid members at v_min = 100.
        let h = [1i64, 1, 1];
        for (i, got) in var.iter().enumerate() {
            let p = [(i % n) as i64, ((i / n) % n) as i64, (i / (n * n)) as i64];
            let mut xs = Vec::new();
            for k in -h[2]..=h[2] {
                for j in -h[1]..=h[1] {
                    for l in -h[0]..=h[0] {
                        let q = [p[0] + l, p[1] + j, p[2] + k];
                        let inside = q.iter().all(|&c| c >= 0 && c < n as i64);
                        let idx = (q[0] + n as i64 * (q[1] + n as i64 * q[2])) as usize;
                        xs.push(if inside { v[idx] as f64 } else { 100.0 });
                    }
                }
            }
            let mu = xs.iter().sum::<f64>() / xs.len() as f64;
            let want = xs.iter().map(|x| (x - mu).powi(2)).sum::<f64>() / xs.len() as f64;
            assert!(
                (*got as f64 - want).abs() <= 1e-3 * want.max(1.0),
                "{i}: {got} vs {want}"
            );
        }
        // Inside the homogeneous low half, away from the bright voxel and the boundary: 0.
        assert_eq!(var[1 + n * (8 + n * 8)], 0.0);
        // At the boundary between the halves: large.
        assert!(var[5 + n * (5 + n * 5)] > 1000.0);
        // A crop of the high half at the volume's far x face, whose own least value is 300: its
        // out-of-grid members take the whole's v_min (100) as the whole's do, so each voxel
        // whose box lies in the crop or beyond the volume has the whole's bits.
        let (lo, size) = ([5, 2, 3], [5, 8, 5]);
        let part = vol.crop(lo, size);
        assert_ne!(part.own_value_range().0, vol.value_range().0);
        let var_part = variance_volume(&part, 1.0);
        let (mut compared, mut at_face) = (0, 0);
        for k in 1..size[2] - 1 {
            for j in 1..size[1] - 1 {
                for i in 1..size[0] {
                    let whole = var[vol.index(lo[0] + i, lo[1] + j, lo[2] + k)];
                    let got = var_part[part.index(i, j, k)];
                    assert_eq!(got.to_bits(), whole.to_bits(), "({i}, {j}, {k})");
                    compared += 1;
                    at_face += (i == size[0] - 1) as usize;
                }
            }
        }
        assert!(compared > 50 && at_face > 10);
    }

    #[test]
    fn the_reach_covers_the_farthest_box_member() {
        for (radius_mm, s) in [
            (5.0, [1.0, 1.0, 2.5]),
            (6.0, [0.957, 0.957, 1.5]),
            (3.0, [2.0; 3]),
        ] {
            let p = FilterParams {
                radius_mm,
                ..Default::default()
            };
            let h = p.half_widths(s);
            let reach = p.reach_mm(s);
            // Every gradient direction (a Fibonacci sphere): the box centre's offset, then the
            // farthest corner of the box from the voxel.
            for j in 0..2000 {
                let z = 1.0 - (2 * j + 1) as f64 / 2000.0;
                let (r, phi) = (
                    (1.0 - z * z).sqrt(),
                    j as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt()),
                );
                let n = [r * phi.cos(), r * phi.sin(), z];
                let far = (0..3)
                    .map(|a| {
                        let off = (-radius_mm * n[a] / s[a]).round().abs();
                        ((off + h[a] as f64) * s[a]).powi(2)
                    })
                    .sum::<f64>()
                    .sqrt();
                assert!(
                    far <= reach + 1e-9,
                    "R {radius_mm} {s:?} n {n:?}: {far} > {reach}"
                );
            }
        }
    }
}
