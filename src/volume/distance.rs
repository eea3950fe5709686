//! Exact Euclidean distances in mm to a labelled structure, for safety margins: the distance
//! transform of Felzenszwalb and Huttenlocher (lower envelopes of parabolas, one axis after the
//! other), weighted by the spacing so that anisotropic voxels give physical distances.
//!
//! dist_l(v) is the distance from voxel v's centre to the nearest voxel centre labelled l (0 on
//! the structure). A [`MarginField`] holds it only in the structure's box grown by its margin:
//! beyond, every voxel is at least the margin away, which is all a margin check asks.

use rayon::prelude::*;

/// Squared distances, in mm², from each voxel centre of `dims` to the nearest voxel where
/// `inside` is true (infinite when there is none), `spacing` mm apart.
pub fn squared_distances(inside: &[bool], dims: [usize; 3], spacing: [f64; 3]) -> Vec<f32> {
    let [nx, ny, nz] = dims;
    let mut d: Vec<f32> = inside
        .iter()
        .map(|&b| if b { 0.0 } else { f32::INFINITY })
        .collect();
    if d.is_empty() {
        return d;
    }
    // x: rows are contiguous
    d.par_chunks_mut(nx).for_each(|row| {
        let line = envelope(row, spacing[0]);
        row.copy_from_slice(&line);
    });
    // y: within each z-slice, the columns of stride nx
    d.par_chunks_mut(nx * ny).for_each(|slice| {
        let mut col = vec![0.0f32; ny];
        for i in 0..nx {
            for (j, c) in col.iter_mut().enumerate() {
                *c = slice[i + nx * j];
            }
            for (j, v) in envelope(&col, spacing[1]).into_iter().enumerate() {
                slice[i + nx * j] = v;
            }
        }
    });
    // z: each (i, j) column into a scratch volume laid out column by column, then back
    let mut cols = vec![0.0f32; d.len()];
    cols.par_chunks_mut(nz).enumerate().for_each(|(c, out)| {
        let line: Vec<f32> = (0..nz).map(|k| d[c + nx * ny * k]).collect();
        out.copy_from_slice(&envelope(&line, spacing[2]));
    });
    d.par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slice)| {
            for (c, v) in slice.iter_mut().enumerate() {
                *v = cols[c * nz + k];
            }
        });
    d
}

/// One axis of the transform: out(x) = min_q s²(x − q)² + f(q), the lower envelope of the
/// parabolas rooted at the finite f(q).
fn envelope(f: &[f32], s: f64) -> Vec<f32> {
    let s2 = s * s;
    let n = f.len();
    // roots of the parabolas on the envelope, and where each takes over
    let mut v: Vec<usize> = Vec::with_capacity(n);
    let mut z: Vec<f64> = Vec::with_capacity(n + 1);
    let h = |q: usize| f[q] as f64 + s2 * (q * q) as f64;
    for q in (0..n).filter(|&q| f[q].is_finite()) {
        loop {
            match v.last() {
                None => {
                    v.push(q);
                    z.push(f64::NEG_INFINITY);
                    break;
                }
                Some(&p) => {
                    // where parabola q meets parabola p
                    let x = (h(q) - h(p)) / (2.0 * s2 * (q - p) as f64);
                    if x <= *z.last().expect("one per root") {
                        v.pop();
                        z.pop();
                    } else {
                        v.push(q);
                        z.push(x);
                        break;
                    }
                }
            }
        }
    }
    if v.is_empty() {
        return vec![f32::INFINITY; n];
    }
    let mut out = vec![0.0f32; n];
    let mut k = 0;
    for (x, o) in out.iter_mut().enumerate() {
        while k + 1 < v.len() && z[k + 1] < x as f64 {
            k += 1;
        }
        let q = v[k];
        let dx = x as f64 - q as f64;
        *o = (s2 * dx * dx + f[q] as f64) as f32;
    }
    out
}

/// dist_l in mm within structure l's box grown by its margin (a few voxels more), for the
/// per-frame margin check.
#[derive(Clone, Debug, PartialEq)]
pub struct MarginField {
    /// Index of the structure in its label map.
    pub structure: usize,
    pub margin_mm: f32,
    /// The box within the volume's grid: its lowest voxel and its size.
    pub min: [usize; 3],
    pub dims: [usize; 3],
    /// Distances in mm, x fastest.
    pub dist: Vec<f32>,
}

impl MarginField {
    /// The field of the voxels whose `ids` equal `id` in a volume of `dims` and `spacing`;
    /// None when no voxel has it.
    pub fn new(
        ids: &[u8],
        id: u8,
        dims: [usize; 3],
        spacing: [f64; 3],
        structure: usize,
        margin_mm: f32,
    ) -> Option<MarginField> {
        let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
        for (n, _) in ids.iter().enumerate().filter(|(_, &v)| v == id) {
            let p = [
                n % dims[0],
                (n / dims[0]) % dims[1],
                n / (dims[0] * dims[1]),
            ];
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        if lo[0] == usize::MAX {
            return None;
        }
        // one voxel past the margin, so that every voxel within it is in the box
        let grow = |a: usize| (margin_mm as f64 / spacing[a]).ceil() as usize + 1;
        let min = [0, 1, 2].map(|a| lo[a].saturating_sub(grow(a)));
        let max = [0, 1, 2].map(|a| (hi[a] + grow(a)).min(dims[a] - 1));
        let bd = [0, 1, 2].map(|a| max[a] - min[a] + 1);
        let mut inside = vec![false; bd[0] * bd[1] * bd[2]];
        for (n, b) in inside.iter_mut().enumerate() {
            let p = [n % bd[0], (n / bd[0]) % bd[1], n / (bd[0] * bd[1])];
            let v = min[0] + p[0] + dims[0] * (min[1] + p[1] + dims[1] * (min[2] + p[2]));
            *b = ids[v] == id;
        }
        let dist = squared_distances(&inside, bd, spacing)
            .into_iter()
            .map(f32::sqrt)
            .collect();
        Some(MarginField {
            structure,
            margin_mm,
            min,
            dims: bd,
            dist,
        })
    }

    /// dist_l at voxel `v` of the volume's grid: infinite outside the box (more than the margin).
    pub fn at(&self, v: [usize; 3]) -> f32 {
        let p = [0, 1, 2].map(|a| v[a].wrapping_sub(self.min[a]));
        if (0..3).any(|a| p[a] >= self.dims[a]) {
            return f32::INFINITY;
        }
        self.dist[p[0] + self.dims[0] * (p[1] + self.dims[1] * p[2])]
    }
}

/// The volumetric glow of the safety margins (Ropinski et al., Sect. 4.4), one byte per voxel:
/// around each structure l with a margin m_l, 1 − dist_l / m_l where 0 < dist_l < m_l (fading
/// from the structure's surface to the margin's edge), 0 on the structure and beyond; the
/// largest over the structures.
pub fn glow(fields: &[MarginField], dims: [usize; 3]) -> Vec<u8> {
    glow_in(fields, [0; 3], dims)
}

/// [`glow`] over the box of `size` voxels from voxel `lo` of the fields' grid (x fastest).
pub fn glow_in(fields: &[MarginField], lo: [usize; 3], size: [usize; 3]) -> Vec<u8> {
    let mut glow = vec![0u8; size[0] * size[1] * size[2]];
    for f in fields {
        // The field's box within this one.
        let a = [0, 1, 2].map(|x| f.min[x].max(lo[x]));
        let b = [0, 1, 2].map(|x| (f.min[x] + f.dims[x]).min(lo[x] + size[x]));
        for k in a[2]..b[2] {
            for j in a[1]..b[1] {
                for i in a[0]..b[0] {
                    let d = f.at([i, j, k]);
                    if d > 0.0 && d < f.margin_mm {
                        let v = i - lo[0] + size[0] * (j - lo[1] + size[1] * (k - lo[2]));
                        let g = ((1.0 - d / f.margin_mm) * 255.0).round() as u8;
                        glow[v] = glow[v].max(g);
                    }
                }
            }
        }
    }
    glow
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The direct definition: the nearest inside voxel centre, every pair tried.
    fn brute(inside: &[bool], d: [usize; 3], s: [f64; 3]) -> Vec<f32> {
        let at = |n: usize| [n % d[0], (n / d[0]) % d[1], n / (d[0] * d[1])];
        (0..inside.len())
            .map(|n| {
                let p = at(n);
                (0..inside.len())
                    .filter(|&m| inside[m])
                    .map(|m| {
                        let q = at(m);
                        (0..3)
                            .map(|a| ((p[a] as f64 - q[a] as f64) * s[a]).powi(2))
                            .sum::<f64>()
                    })
                    .fold(f64::INFINITY, f64::min)
                    .sqrt() as f32
            })
            .collect()
    }

    #[test]
    fn distances_equal_the_brute_force_nearest_centre_with_anisotropic_spacing() {
        let d = [13, 9, 7];
        let s = [0.7, 1.3, 2.5];
        // a few scattered voxels and a small blob, from a fixed pseudo-random sequence
        let mut x = 12345u32;
        let inside: Vec<bool> = (0..d[0] * d[1] * d[2])
            .map(|n| {
                x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
                (x >> 16) % 97 == 0 || n == 500 || n == 501 || n == 513
            })
            .collect();
        let got: Vec<f32> = squared_distances(&inside, d, s)
            .into_iter()
            .map(f32::sqrt)
            .collect();
        let want = brute(&inside, d, s);
        for (n, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!((g - w).abs() <= 1e-4 * w.max(1.0), "voxel {n}: {g} vs {w}");
        }
        assert!(want.iter().any(|&w| w > 5.0), "the test reaches far voxels");
        // nothing inside: infinitely far
        let none = squared_distances(&[false; 8], [2, 2, 2], s);
        assert!(none.iter().all(|v| v.is_infinite()));
    }

    #[test]
    fn a_margin_field_equals_the_whole_volume_transform_within_its_margin() {
        let d = [20, 16, 10];
        let s = [0.8, 0.8, 2.0];
        let mut ids = vec![0u8; d[0] * d[1] * d[2]];
        for (n, v) in ids.iter_mut().enumerate() {
            let p = [n % d[0], (n / d[0]) % d[1], n / (d[0] * d[1])];
            if (8..11).contains(&p[0]) && (6..8).contains(&p[1]) && (4..6).contains(&p[2]) {
                *v = 3;
            } else if p[0] < 2 {
                *v = 1;
            }
        }
        let f = MarginField::new(&ids, 3, d, s, 2, 3.0).unwrap();
        let inside: Vec<bool> = ids.iter().map(|&v| v == 3).collect();
        let whole = brute(&inside, d, s);
        for (n, &want) in whole.iter().enumerate() {
            let p = [n % d[0], (n / d[0]) % d[1], n / (d[0] * d[1])];
            let got = f.at(p);
            if want <= 3.0 {
                assert!((got - want).abs() < 1e-4, "{p:?}: {got} vs {want}");
            } else {
                assert!(got > 3.0, "{p:?}: {got} within the margin, but {want} away");
            }
        }
        assert!(MarginField::new(&ids, 7, d, s, 0, 3.0).is_none());
        // The glow fades from the structure's surface to the margin's edge.
        let g = glow(std::slice::from_ref(&f), d);
        for (n, &v) in g.iter().enumerate() {
            let w = whole[n];
            let want = if w > 0.0 && w < 3.0 {
                ((1.0 - w / 3.0) * 255.0).round() as u8
            } else {
                0
            };
            assert!(
                v.abs_diff(want) <= 1,
                "voxel {n} at {w} mm: glow {v}, not {want}"
            );
        }
        assert!(g.iter().any(|&v| v > 100), "the glow is lit somewhere");
        // A box of it: the same bytes.
        let (lo, size) = ([2, 1, 3], [5, 6, 4]);
        let part = glow_in(std::slice::from_ref(&f), lo, size);
        for k in 0..size[2] {
            for j in 0..size[1] {
                for i in 0..size[0] {
                    let w = lo[0] + i + d[0] * (lo[1] + j + d[1] * (lo[2] + k));
                    assert_eq!(
                        part[i + size[0] * (j + size[1] * k)],
                        g[w],
                        "({i}, {j}, {k})"
                    );
                }
            }
        }
    }
}
