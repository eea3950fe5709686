//! Procedural CT phantoms in Hounsfield units: a head, and a chest of any grid ([`chest`]).
//!
//! Everything is defined analytically in millimetres (patient LPS space centred in a 220 mm
//! cube: x = patient left, y = posterior, z = superior), so every resolution shows the same
//! anatomy; edges are anti-aliased over one voxel. No noise: the result is deterministic.
//!
//! Index axes follow the declared identity `directions`: +i = patient left, +j = posterior,
//! +k = superior. So the face and the teeth sit at small j, the teeth at small k.

use super::{Modality, Volume, Voxels};
use glam::{DMat3, DVec3};

/// Edge length of the cube the phantom fills (mm).
const FOV_MM: f32 = 220.0;

const AIR: f32 = -1000.0;
const SKIN: f32 = 40.0;
const FAT: f32 = -100.0;
const CORTICAL: f32 = 1500.0;
const DIPLOE: f32 = 1000.0;
const SKULL_BASE: f32 = 1100.0;
const BRAIN: f32 = 35.0;
const SOFT_TISSUE: f32 = 45.0;
const ORBIT_FAT: f32 = -80.0;
const EYE: f32 = 15.0;
const CSF: f32 = 5.0;
const ENAMEL: f32 = 2800.0;

/// Skin thickness and the depth of the outer bone surface below the skin surface (mm).
const SKIN_MM: f32 = 3.0;
const BONE_DEPTH_MM: f32 = 7.0;
/// Thickness of each cortical table of the cranial vault (mm).
const TABLE_MM: f32 = 1.8;

/// An axis-aligned ellipsoid.
#[derive(Clone, Copy)]
struct Ellipsoid {
    c: [f32; 3],
    r: [f32; 3],
}

impl Ellipsoid {
    const fn new(c: [f32; 3], r: [f32; 3]) -> Self {
        Self { c, r }
    }

    /// Approximate signed distance (mm, negative inside); exact on the surface, good near it.
    #[inline]
    fn sdf(&self, p: [f32; 3]) -> f32 {
        let q = [p[0] - self.c[0], p[1] - self.c[1], p[2] - self.c[2]];
        let a = [q[0] / self.r[0], q[1] / self.r[1], q[2] / self.r[2]];
        let b = [a[0] / self.r[0], a[1] / self.r[1], a[2] / self.r[2]];
        let k0 = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        let k1 = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
        if k1 < 1e-12 {
            return -self.r[0].min(self.r[1]).min(self.r[2]);
        }
        k0 * (k0 - 1.0) / k1
    }
}

/// Polynomial smooth minimum (blend width `k` mm).
#[inline]
fn smin(a: f32, b: f32, k: f32) -> f32 {
    let h = (k - (a - b).abs()).max(0.0) / k;
    a.min(b) - h * h * k * 0.25
}

#[inline]
fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Outer surface of the skull: the cranium blended with the face/jaw.
const CRANIUM: Ellipsoid = Ellipsoid::new([0.0, 8.0, 22.0], [74.0, 90.0, 78.0]);
const JAW: Ellipsoid = Ellipsoid::new([0.0, -22.0, -40.0], [54.0, 56.0, 58.0]);
const NOSE: Ellipsoid = Ellipsoid::new([0.0, -78.0, -12.0], [11.0, 16.0, 24.0]);

/// Which surface a cavity must stay inside of.
#[derive(Clone, Copy, PartialEq)]
enum Inside {
    /// Below the skin (depth > SKIN_MM under the head surface).
    Skin,
    /// Below the outer bone surface.
    Bone,
    /// Anywhere (the blob lies inside the brain by construction).
    Any,
}

#[derive(Clone, Copy)]
struct Blob {
    e: Ellipsoid,
    value: f32,
    inside: Inside,
}

const fn blob(c: [f32; 3], r: [f32; 3], value: f32, inside: Inside) -> Blob {
    Blob {
        e: Ellipsoid::new(c, r),
        value,
        inside,
    }
}

/// Cavities painted over the layered head, in order.
const CAVITIES: [Blob; 15] = [
    // orbits (fat) with the eyeballs
    blob(
        [-32.0, -50.0, 4.0],
        [16.0, 20.0, 15.0],
        ORBIT_FAT,
        Inside::Skin,
    ),
    blob(
        [32.0, -50.0, 4.0],
        [16.0, 20.0, 15.0],
        ORBIT_FAT,
        Inside::Skin,
    ),
    blob([-32.0, -54.0, 4.0], [11.5, 11.5, 11.5], EYE, Inside::Skin),
    blob([32.0, -54.0, 4.0], [11.5, 11.5, 11.5], EYE, Inside::Skin),
    // maxillary, frontal, sphenoid sinuses and the nasal cavity
    blob([-24.0, -42.0, -32.0], [13.0, 15.0, 15.0], AIR, Inside::Bone),
    blob([24.0, -42.0, -32.0], [13.0, 15.0, 15.0], AIR, Inside::Bone),
    blob([0.0, -70.0, 30.0], [13.0, 6.0, 9.0], AIR, Inside::Bone),
    blob([0.0, -20.0, -22.0], [10.0, 10.0, 9.0], AIR, Inside::Bone),
    blob([0.0, -58.0, -22.0], [7.0, 18.0, 14.0], AIR, Inside::Bone),
    // lateral, third and fourth ventricles
    blob([-11.0, 8.0, 32.0], [6.0, 30.0, 11.0], CSF, Inside::Any),
    blob([11.0, 8.0, 32.0], [6.0, 30.0, 11.0], CSF, Inside::Any),
    blob([0.0, 10.0, 14.0], [2.5, 12.0, 8.0], CSF, Inside::Any),
    blob([0.0, 45.0, -15.0], [5.0, 4.0, 6.0], CSF, Inside::Any),
    // a few more: the frontal horns dip forward and down
    blob([-10.0, -14.0, 24.0], [5.0, 9.0, 7.0], CSF, Inside::Any),
    blob([10.0, -14.0, 24.0], [5.0, 9.0, 7.0], CSF, Inside::Any),
];

/// Number of teeth on the dental arc.
const TEETH: usize = 14;

/// The upper dental arc: `TEETH` blobs on a 160-degree arc inside the jaw's bone ring, front
/// teeth most anterior.
fn teeth() -> [Blob; TEETH] {
    let mut out = [blob([0.0; 3], [1.0; 3], ENAMEL, Inside::Any); TEETH];
    for (m, t) in out.iter_mut().enumerate() {
        let theta = (-80.0 + 160.0 * m as f32 / (TEETH - 1) as f32).to_radians();
        let (s, c) = theta.sin_cos();
        t.e = Ellipsoid::new([36.0 * s, -22.0 - 36.0 * c, -58.0], [3.6, 4.0, 6.0]);
    }
    out
}

/// Skull base: a bony plate sloping down towards the back (anterior fossa high, posterior
/// fossa low), z-position for a given y.
#[inline]
fn skull_base_z(y: f32) -> f32 {
    -22.0 - 0.3 * y
}

/// A procedural CT head in Hounsfield units (int16), `n`^3 voxels of 220/`n` mm.
/// Deterministic; identity directions (+i left, +j posterior, +k superior); name "phantom-n".
pub fn head(n: usize) -> Volume {
    let n = n.max(1);
    let s = FOV_MM / n as f32;
    // Partial-volume width: a fixed 3.5 mm blur like a scanner's (at least one voxel); sharper
    // edges leave voxel terraces that show as contour rings under gradient shading.
    let w = s.max(3.5);
    let half = FOV_MM * 0.5;
    // coverage of "inside" for signed distance d
    let cov = |d: f32| (0.5 - d / w).clamp(0.0, 1.0);
    let mix = |v: f32, value: f32, c: f32| v + (value - v) * c;

    let coord = |i: usize| (i as f32 + 0.5) * s - half;
    let teeth = teeth();
    let all: Vec<Blob> = CAVITIES
        .iter()
        .copied()
        .chain(teeth.iter().copied())
        .collect();
    // Blobs whose extent (plus the anti-aliasing margin) reaches coordinate `t` on axis `a`.
    let near = |b: &Blob, a: usize, t: f32| (t - b.e.c[a]).abs() <= b.e.r[a] + w;

    let mut data = vec![AIR as i16; n * n * n];
    let mut active_k: Vec<Blob> = Vec::with_capacity(all.len());
    let mut active_jk: Vec<Blob> = Vec::with_capacity(all.len());
    for k in 0..n {
        let z = coord(k);
        active_k.clear();
        active_k.extend(all.iter().filter(|b| near(b, 2, z)));
        // Thinner bone in the face and jaw than in the cranial vault.
        let face_w = smoothstep(-5.0, -35.0, z);
        let bone_t = 6.5 - 3.5 * face_w;
        let diploe_w = 1.0 - face_w;
        for j in 0..n {
            let y = coord(j);
            active_jk.clear();
            active_jk.extend(active_k.iter().filter(|b| near(b, 1, y)));
            let zb = skull_base_z(y);
            let row = &mut data[n * (j + n * k)..n * (j + n * k) + n];
            for (i, out) in row.iter_mut().enumerate() {
                let x = coord(i);
                let p = [x, y, z];
                let skull_d = smin(CRANIUM.sdf(p), JAW.sdf(p), 20.0);
                let head_d = smin(skull_d, NOSE.sdf(p), 8.0);
                if head_d > w {
                    continue; // air
                }
                let depth_bone = skull_d + BONE_DEPTH_MM; // < 0 below the outer bone surface
                let mut v = AIR;
                v = mix(v, SKIN, cov(head_d));
                v = mix(v, FAT, cov(head_d + SKIN_MM));
                v = mix(v, CORTICAL, cov(depth_bone));
                v = mix(v, DIPLOE, cov(depth_bone + TABLE_MM) * diploe_w);
                v = mix(v, CORTICAL, cov(depth_bone + bone_t - TABLE_MM) * diploe_w);
                // Inside the skull: brain above the skull base, soft tissue below it.
                let inner = cov(depth_bone + bone_t);
                if inner > 0.0 {
                    let below = cov(z - zb);
                    let tissue = BRAIN + (SOFT_TISSUE - BRAIN) * below;
                    v = mix(v, tissue, inner);
                    // skull base plate behind the orbits, with a foramen magnum
                    if y > -55.0 {
                        let plate = (z - zb).abs() - 2.5;
                        let foramen = 16.0 - (x * x + (y - 25.0) * (y - 25.0)).sqrt();
                        v = mix(v, SKULL_BASE, cov(plate.max(foramen)) * inner);
                    }
                }
                for b in active_jk.iter() {
                    if (x - b.e.c[0]).abs() > b.e.r[0] + w {
                        continue;
                    }
                    let mut c = cov(b.e.sdf(p));
                    if c <= 0.0 {
                        continue;
                    }
                    c *= match b.inside {
                        Inside::Skin => cov(head_d + SKIN_MM),
                        Inside::Bone => cov(depth_bone),
                        Inside::Any => 1.0,
                    };
                    v = mix(v, b.value, c);
                }
                *out = v.round() as i16;
            }
        }
    }

    Volume {
        whole_range: None,
        name: format!("phantom-{n}"),
        dims: [n, n, n],
        spacing: [FOV_MM as f64 / n as f64; 3],
        directions: DMat3::IDENTITY,
        origin: DVec3::splat(-110.0 + 110.0 / n as f64),
        modality: Modality::Ct,
        voxels: Voxels::I16(data),
        labels: None,
    }
}

/// A procedural chest CT in Hounsfield units (int16) of any grid: `dims` voxels of `spacing` mm
/// (as a scanner writes them, e.g. 512 x 512 x 133 at 0.7 x 0.7 x 2.5 mm), for benchmarks at
/// clinical sizes. An elliptical body (soft tissue, a fat layer) in air, two lungs, a
/// contrast-filled heart and aorta, a spine, and ribs every 30 mm of z around the body wall.
/// The anatomy is in mm about the grid's centre, so every grid of the same extent shows the
/// same chest; edges are anti-aliased over one voxel. Rows in parallel; deterministic.
pub fn chest(dims: [usize; 3], spacing: [f64; 3]) -> Volume {
    use rayon::prelude::*;
    let [nx, ny, nz] = dims.map(|n| n.max(1));
    let s = spacing.map(|v| v as f32);
    let ext = [nx as f32 * s[0], ny as f32 * s[1], nz as f32 * s[2]];
    // The body fills 80 % of the field's width and 60 % of its depth.
    let body = [0.4 * ext[0], 0.3 * ext[1]];
    let w = s[0].max(s[1]);
    let cov = |d: f32| (0.5 - d / w).clamp(0.0, 1.0);
    let mix = |v: f32, value: f32, c: f32| v + (value - v) * c;
    // Signed distance (mm, approximate) to an ellipse of semi-axes r centred at c.
    let ellipse = |x: f32, y: f32, c: [f32; 2], r: [f32; 2]| {
        let q = ((x - c[0]) / r[0]).hypot((y - c[1]) / r[1]);
        (q - 1.0) * r[0].min(r[1])
    };
    let mut data = vec![AIR as i16; nx * ny * nz];
    data.par_chunks_mut(nx).enumerate().for_each(|(row, out)| {
        let (j, k) = (row % ny, row / ny);
        let y = (j as f32 + 0.5) * s[1] - 0.5 * ext[1];
        let z = (k as f32 + 0.5) * s[2] - 0.5 * ext[2];
        // A rib where z is within 5 mm of a multiple of 30 mm (a rib's height), else gap.
        let rib = cov((z.rem_euclid(30.0) - 15.0).abs() - 10.0);
        for (i, o) in out.iter_mut().enumerate() {
            let x = (i as f32 + 0.5) * s[0] - 0.5 * ext[0];
            let outer = ellipse(x, y, [0.0, 0.0], body);
            let mut v = mix(AIR, FAT, cov(outer));
            v = mix(v, SOFT_TISSUE, cov(outer + 12.0));
            // ribs: a bone ring 12-22 mm inside the skin
            let ring = (outer + 17.0).abs() - 5.0;
            v = mix(v, DIPLOE, cov(ring) * rib);
            for side in [-1.0f32, 1.0] {
                let lung = ellipse(
                    x,
                    y,
                    [side * 0.45 * body[0], -0.1 * body[1]],
                    [0.38 * body[0], 0.7 * body[1]],
                );
                v = mix(v, -850.0, cov(lung));
            }
            // heart (contrast) left-anterior, aorta behind it, spine at the back
            v = mix(
                v,
                250.0,
                cov(ellipse(
                    x,
                    y,
                    [0.12 * body[0], -0.3 * body[1]],
                    [0.25 * body[0], 0.35 * body[1]],
                )),
            );
            v = mix(
                v,
                300.0,
                cov(ellipse(
                    x,
                    y,
                    [-0.05 * body[0], 0.45 * body[1]],
                    [12.0, 12.0],
                )),
            );
            v = mix(
                v,
                CORTICAL,
                cov(ellipse(x, y, [0.0, 0.75 * body[1]], [18.0, 16.0])),
            );
            v = mix(
                v,
                DIPLOE,
                cov(ellipse(x, y, [0.0, 0.75 * body[1]], [14.0, 12.0])),
            );
            *o = v.round() as i16;
        }
    });
    Volume {
        whole_range: None,
        name: format!("chest-{nx}x{ny}x{nz}"),
        dims: [nx, ny, nz],
        spacing,
        directions: DMat3::IDENTITY,
        origin: DVec3::new(
            -0.5 * (ext[0] - s[0]) as f64,
            -0.5 * (ext[1] - s[1]) as f64,
            -0.5 * (ext[2] - s[2]) as f64,
        ),
        modality: Modality::Ct,
        voxels: Voxels::I16(data),
        labels: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(v: &Volume) -> &[i16] {
        match &v.voxels {
            Voxels::I16(d) => d,
            _ => panic!("phantom must be int16"),
        }
    }

    fn fraction(v: &Volume, f: impl Fn(i16) -> bool) -> f64 {
        let d = values(v);
        d.iter().filter(|&&x| f(x)).count() as f64 / d.len() as f64
    }

    #[test]
    fn the_chest_has_air_lungs_soft_tissue_and_bone_in_ct_proportions() {
        let v = chest([96, 96, 24], [3.5, 3.5, 12.5]);
        assert_eq!((v.dims, v.name.as_str()), ([96, 96, 24], "chest-96x96x24"));
        let air = fraction(&v, |x| x < -950);
        let lung = fraction(&v, |x| (-900..-700).contains(&x));
        let soft = fraction(&v, |x| (-150..150).contains(&x));
        let bone = fraction(&v, |x| x > 600);
        assert!((0.3..0.7).contains(&air), "air {air}");
        assert!((0.05..0.3).contains(&lung), "lung {lung}");
        assert!((0.05..0.4).contains(&soft), "soft tissue {soft}");
        assert!((0.005..0.1).contains(&bone), "bone {bone}");
        // the same chest on a finer grid of the same extent
        let fine = chest([192, 192, 48], [1.75, 1.75, 6.25]);
        let lung_fine = fraction(&fine, |x| (-900..-700).contains(&x));
        assert!((lung - lung_fine).abs() < 0.02, "{lung} vs {lung_fine}");
    }

    #[test]
    fn deterministic() {
        let a = head(24);
        let b = head(24);
        assert_eq!(a.voxels, b.voxels);
        assert_eq!(a.name, "phantom-24");
        assert_eq!(a.dims, [24, 24, 24]);
        assert_eq!(a.modality, Modality::Ct);
        assert_eq!(a.directions, DMat3::IDENTITY);
        assert!((a.spacing[0] - 220.0 / 24.0).abs() < 1e-12);
        assert_eq!(a.spacing[0], a.spacing[2]);
    }

    #[test]
    fn anatomy() {
        let n = 64;
        let v = head(n);
        let d = values(&v);
        let (lo, hi) = v.value_range();
        assert_eq!(lo, -1000.0);
        assert!((2000.0..=3000.0).contains(&hi), "max {hi}");
        assert!(fraction(&v, |x| x == -1000) > 0.3, "air");
        assert!(fraction(&v, |x| x > 700) > 0.01, "bone");
        assert!(fraction(&v, |x| (0..=80).contains(&x)) > 0.1, "soft tissue");
        assert!(fraction(&v, |x| (-150..=-50).contains(&x)) > 0.005, "fat");

        // Teeth: everything above 2000 HU is low (small k) and anterior (small j).
        let (mut count, mut tj, mut tk) = (0usize, 0.0, 0.0);
        let (mut hj, mut hn) = (0.0, 0.0);
        let (mut kmin, mut kmax, mut imin, mut imax) = (n, 0, n, 0);
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    let x = d[v.index(i, j, k)];
                    if x > 2000 {
                        assert!(k < n * 2 / 5 && j < n * 2 / 5, "dense voxel at {i} {j} {k}");
                        count += 1;
                        tj += j as f64;
                        tk += k as f64;
                    }
                    if x > -500 {
                        hj += j as f64;
                        hn += 1.0;
                        kmin = kmin.min(k);
                        kmax = kmax.max(k);
                        imin = imin.min(i);
                        imax = imax.max(i);
                    }
                }
            }
        }
        assert!(count > 20, "teeth voxels: {count}");
        let (tj, tk, hj) = (tj / count as f64, tk / count as f64, hj / hn);
        assert!(tj < hj - 10.0, "teeth j {tj} vs head j {hj}");
        assert!(tk < n as f64 * 0.3, "teeth k {tk}");
        // Taller (~200 mm) than wide (~150 mm).
        let s = v.spacing[0];
        let height = (kmax - kmin + 1) as f64 * s;
        let width = (imax - imin + 1) as f64 * s;
        assert!((185.0..=215.0).contains(&height), "height {height}");
        assert!((135.0..=165.0).contains(&width), "width {width}");
        // Symmetric left/right.
        for k in (0..n).step_by(7) {
            for j in 0..n {
                for i in 0..n / 2 {
                    assert_eq!(d[v.index(i, j, k)], d[v.index(n - 1 - i, j, k)]);
                }
            }
        }
    }

    #[test]
    fn resolution_independent() {
        let a = head(32);
        let b = head(64);
        let fa = fraction(&a, |x| x > 700);
        let fb = fraction(&b, |x| x > 700);
        assert!(
            (fa - fb).abs() / fb < 0.05,
            "bone fraction 32^3 {fa} vs 64^3 {fb}"
        );
        let ha = fraction(&a, |x| x > -500);
        let hb = fraction(&b, |x| x > -500);
        assert!(
            (ha - hb).abs() / hb < 0.03,
            "head fraction 32^3 {ha} vs 64^3 {hb}"
        );
    }
}
