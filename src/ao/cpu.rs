//! CPU reference of LAO (docs/design.md), in f64, parallel over z-slices. The GPU kernel must agree
//! with it to 1e-4 per voxel; it is also what an outside checker would compute.

use super::lao::{index_steps, LaoParams};
use rayon::prelude::*;

/// Trilinear O at index-space point p (voxel centres at q + 0.5, zero outside the grid).
pub fn opacity_at(opacity: &[f32], dims: [usize; 3], p: [f64; 3]) -> f64 {
    let c = [p[0] - 0.5, p[1] - 0.5, p[2] - 0.5];
    let fl = c.map(f64::floor);
    let f = [c[0] - fl[0], c[1] - fl[1], c[2] - fl[2]];
    let q = fl.map(|x| x as i64);
    let at = |dx: i64, dy: i64, dz: i64| -> f64 {
        let (x, y, z) = (q[0] + dx, q[1] + dy, q[2] + dz);
        if x < 0
            || y < 0
            || z < 0
            || x >= dims[0] as i64
            || y >= dims[1] as i64
            || z >= dims[2] as i64
        {
            return 0.0;
        }
        opacity[x as usize + dims[0] * (y as usize + dims[1] * z as usize)] as f64
    };
    let lerp = |a: f64, b: f64, t: f64| a * (1.0 - t) + b * t;
    let x00 = lerp(at(0, 0, 0), at(1, 0, 0), f[0]);
    let x10 = lerp(at(0, 1, 0), at(1, 1, 0), f[0]);
    let x01 = lerp(at(0, 0, 1), at(1, 0, 1), f[0]);
    let x11 = lerp(at(0, 1, 1), at(1, 1, 1), f[0]);
    lerp(lerp(x00, x10, f[1]), lerp(x01, x11, f[1]), f[2])
}

/// LAO of voxel (i,j,k).
pub fn lao_voxel(
    opacity: &[f32],
    dims: [usize; 3],
    steps_idx: &[glam::DVec3],
    params: &LaoParams,
    v: [usize; 3],
) -> f64 {
    let x = glam::DVec3::new(v[0] as f64 + 0.5, v[1] as f64 + 0.5, v[2] as f64 + 0.5);
    let exponent = params.step_mm as f64;
    let mut total = 0.0;
    for s in steps_idx {
        let mut t = 1.0;
        let mut sum = 0.0;
        for m in 1..=params.steps {
            sum += t;
            if m == params.steps {
                break;
            }
            let p = x + *s * m as f64;
            let o = opacity_at(opacity, dims, p.to_array());
            t *= (1.0 - o).max(0.0).powf(exponent);
            if t == 0.0 {
                break;
            }
        }
        total += sum;
    }
    total / (steps_idx.len() as f64 * params.steps as f64)
}

/// Full LAO of an opacity volume.
pub fn lao(opacity: &[f32], dims: [usize; 3], spacing: [f64; 3], params: &LaoParams) -> Vec<f32> {
    let steps_idx = index_steps(params, spacing);
    let slice = dims[0] * dims[1];
    let mut out = vec![0f32; opacity.len()];
    out.par_chunks_mut(slice)
        .enumerate()
        .for_each(|(k, chunk)| {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    chunk[i + dims[0] * j] =
                        lao_voxel(opacity, dims, &steps_idx, params, [i, j, k]) as f32;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transparent_is_one_and_opaque_interior_is_one_over_m() {
        let dims = [12, 12, 12];
        let p = LaoParams {
            rays: 14,
            steps: 4,
            step_mm: 1.0,
        };
        let clear = vec![0.0; 12 * 12 * 12];
        assert!(lao(&clear, dims, [1.0; 3], &p).iter().all(|&a| a == 1.0));
        let solid = vec![1.0; 12 * 12 * 12];
        let a = lao(&solid, dims, [1.0; 3], &p);
        assert_eq!(a[6 + 12 * (6 + 12 * 6)], 0.25);
    }

    #[test]
    fn half_space_matches_hand_computation() {
        // Opaque (O=1) for slices z >= 4 of an 8^3 volume; K=6, M=3, D=1 mm = 1 voxel.
        // M=3 samples p1 and p2 only. Only the +z ray can reach the opaque half.
        let dims = [8, 8, 8];
        let mut o = vec![0.0; 512];
        for k in 4..8 {
            for j in 0..8 {
                for i in 0..8 {
                    o[i + 8 * (j + 8 * k)] = 1.0;
                }
            }
        }
        let p = LaoParams {
            rays: 6,
            steps: 3,
            step_mm: 1.0,
        };
        let s = index_steps(&p, [1.0; 3]);
        // Voxel (4,4,3): p1 is on slice 4's centre (opaque): A_+z = (1 + 0 + 0)/3.
        let a = lao_voxel(&o, dims, &s, &p, [4, 4, 3]);
        assert!((a - (5.0 + 1.0 / 3.0) / 6.0).abs() < 1e-12, "{a}");
        // Voxel (4,4,2): p1 on slice 3 (clear), p2 on slice 4: A_+z = (1 + 1 + 0)/3.
        let a = lao_voxel(&o, dims, &s, &p, [4, 4, 2]);
        assert!((a - (5.0 + 2.0 / 3.0) / 6.0).abs() < 1e-12, "{a}");
    }
}
