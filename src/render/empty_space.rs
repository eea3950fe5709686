//! Exact empty-space skipping for the ray caster. The volume is cut into bricks of
//! [`RAY_BRICK`]^3 voxels; a brick is empty for a transfer function when every value any sample
//! inside it can take classifies as fully transparent: the values of its voxels and of an apron
//! of [`RAY_BRICK_APRON`] voxels around it (the footprint of trilinear and of tricubic B-spline
//! reconstruction, both convex combinations of voxels), looked up as the shader looks them up,
//! with a texel of margin. With pre-integration, every segment between two such values is
//! transparent too, so two samples in a row in an empty brick contribute nothing.
//!
//! raycast.frag then skips a sample (no clip test, no classification) when it and the sample
//! before lie in the same empty brick outside every tool's reach: the image is bit for bit the
//! one without skipping. Only the last skipped sample's value is read, for the next segment.

use crate::shader_constants::RAY_BRICK_SHIFT;

/// Edge of a ray-casting brick, in voxels.
pub const RAY_BRICK: usize = 1 << RAY_BRICK_SHIFT;
/// Voxels around a brick that a sample inside it can read: trilinear reads one, the tricubic
/// B-spline two; one more for rounding.
pub const RAY_BRICK_APRON: usize = 3;

/// Per brick, the least and greatest voxel value within the brick and its apron (NaN anywhere
/// makes the range infinite: such a brick is never empty).
#[derive(Clone, Debug, PartialEq)]
pub struct BrickRanges {
    /// Bricks along x, y, z.
    pub bricks: [usize; 3],
    /// (min, max) per brick, x fastest.
    pub ranges: Vec<(f32, f32)>,
}

/// The voxels [lo, hi) along an axis of `n` voxels that brick `b` and its apron cover.
fn apron(b: usize, n: usize) -> (usize, usize) {
    let lo = (b * RAY_BRICK).saturating_sub(RAY_BRICK_APRON);
    (lo, ((b + 1) * RAY_BRICK + RAY_BRICK_APRON).min(n))
}

impl BrickRanges {
    /// The ranges of `values` (x fastest) on a grid of `dims`.
    pub fn of(values: &[f32], dims: [usize; 3]) -> BrickRanges {
        Self::of_samples(dims, |i| values[i])
    }

    /// The ranges of the values `sample(i)` (voxel i, x fastest) on a grid of `dims`, reduced
    /// one axis at a time (the range over a box is the range over z of the ranges over y of the
    /// ranges over x). The first reduction reads the voxels themselves, a row of x per task on
    /// every core; the others work on arrays a brick's width smaller.
    pub fn of_samples(dims: [usize; 3], sample: impl Fn(usize) -> f32 + Sync) -> BrickRanges {
        use rayon::prelude::*;
        let nx = dims[0];
        let nbx = nx.div_ceil(RAY_BRICK);
        let mut cur = vec![(f32::INFINITY, f32::NEG_INFINITY); nbx * dims[1] * dims[2]];
        cur.par_chunks_mut(nbx.max(1))
            .enumerate()
            .for_each(|(row, out)| {
                for (b, o) in out.iter_mut().enumerate() {
                    let (lo, hi) = apron(b, nx);
                    *o = (lo..hi).fold(*o, |r, x| {
                        let v = sample(row * nx + x);
                        let (a, b) = if v.is_nan() {
                            (f32::NEG_INFINITY, f32::INFINITY)
                        } else {
                            (v, v)
                        };
                        (r.0.min(a), r.1.max(b))
                    });
                }
            });
        let mut shape = [nbx, dims[1], dims[2]];
        for axis in 1..3 {
            let n = shape[axis];
            let nb = n.div_ceil(RAY_BRICK);
            let mut next_shape = shape;
            next_shape[axis] = nb;
            let stride = |s: [usize; 3], a: usize| match a {
                0 => 1,
                1 => s[0],
                _ => s[0] * s[1],
            };
            let (src_stride, dst_stride) = (stride(shape, axis), stride(next_shape, axis));
            let mut next = vec![(f32::INFINITY, f32::NEG_INFINITY); next_shape.iter().product()];
            // Every line along `axis`: its start in the source and in the destination.
            let others: Vec<usize> = (0..3).filter(|&a| a != axis).collect();
            for j in 0..shape[others[1]] {
                for i in 0..shape[others[0]] {
                    let src0 = i * stride(shape, others[0]) + j * stride(shape, others[1]);
                    let dst0 =
                        i * stride(next_shape, others[0]) + j * stride(next_shape, others[1]);
                    for b in 0..nb {
                        let (lo, hi) = apron(b, n);
                        let r = (lo..hi).fold((f32::INFINITY, f32::NEG_INFINITY), |r, k| {
                            let v = cur[src0 + k * src_stride];
                            (r.0.min(v.0), r.1.max(v.1))
                        });
                        next[dst0 + b * dst_stride] = r;
                    }
                }
            }
            cur = next;
            shape = next_shape;
        }
        BrickRanges {
            bricks: shape,
            ranges: cur,
        }
    }

    /// 255 for each brick whose values all look up transparent in `table`, else 0.
    pub fn empty_flags(&self, table: &Transparency) -> Vec<u8> {
        self.ranges
            .iter()
            .map(|&(lo, hi)| if table.transparent(lo, hi) { 255 } else { 0 })
            .collect()
    }
}

/// Where a lookup table is fully transparent: the 1-D transfer function (point samples) or the
/// 2-D pre-integrated one (segments from a front to a back value), with the value-to-texture
/// map the shader uses (coordinate = value * scale + offset, over `n` texels per axis).
pub struct Transparency {
    n: usize,
    offset: f32,
    scale: f32,
    /// Texels with any opacity before each index (1-D), or in each leading square (2-D,
    /// (n + 1)^2 summed-area table).
    opaque_before: Vec<u32>,
    two_d: bool,
}

impl Transparency {
    /// `alpha[i]` of a table of `n` texels.
    pub fn lut(alpha: &[f32], (offset, scale): (f32, f32)) -> Transparency {
        let mut opaque_before = vec![0u32; alpha.len() + 1];
        for (i, a) in alpha.iter().enumerate() {
            opaque_before[i + 1] = opaque_before[i] + u32::from(*a != 0.0);
        }
        Transparency {
            n: alpha.len(),
            offset,
            scale,
            opaque_before,
            two_d: false,
        }
    }

    /// `alpha[y * n + x]` of an `n` x `n` table.
    pub fn preintegrated(alpha: &[f32], n: usize, (offset, scale): (f32, f32)) -> Transparency {
        let m = n + 1;
        let mut sat = vec![0u32; m * m];
        for y in 0..n {
            for x in 0..n {
                sat[(y + 1) * m + x + 1] =
                    u32::from(alpha[y * n + x] != 0.0) + sat[y * m + x + 1] + sat[(y + 1) * m + x]
                        - sat[y * m + x];
            }
        }
        Transparency {
            n,
            offset,
            scale,
            opaque_before: sat,
            two_d: true,
        }
    }

    /// The texels a linear lookup of any value in [lo, hi] can touch, with one of margin for
    /// rounding on the GPU.
    fn texels(&self, lo: f32, hi: f32) -> Option<(usize, usize)> {
        let u = |v: f32| (v * self.scale + self.offset) * self.n as f32 - 0.5;
        let (a, b) = (u(lo), u(hi));
        if !(a.is_finite() && b.is_finite()) {
            return None;
        }
        let last = self.n as f32 - 1.0;
        let first = (a.floor() - 1.0).clamp(0.0, last) as usize;
        let end = (b.floor() + 2.0).clamp(0.0, last) as usize;
        Some((first, end))
    }

    /// Whether every value in [lo, hi] (and, 2-D, every segment between two of them) looks up
    /// an opacity of exactly zero.
    pub fn transparent(&self, lo: f32, hi: f32) -> bool {
        let Some((a, b)) = self.texels(lo, hi) else {
            return false;
        };
        let o = &self.opaque_before;
        if self.two_d {
            let m = self.n + 1;
            let (a, b) = (a, b + 1);
            o[b * m + b] + o[a * m + a] == o[a * m + b] + o[b * m + a]
        } else {
            o[b + 1] == o[a]
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(values: &[f32], dims: [usize; 3]) -> BrickRanges {
        let bricks = dims.map(|d| d.div_ceil(RAY_BRICK));
        let mut ranges = Vec::new();
        for bz in 0..bricks[2] {
            for by in 0..bricks[1] {
                for bx in 0..bricks[0] {
                    let b = [bx, by, bz];
                    let span = |a: usize| {
                        (b[a] * RAY_BRICK).saturating_sub(RAY_BRICK_APRON)
                            ..((b[a] + 1) * RAY_BRICK + RAY_BRICK_APRON).min(dims[a])
                    };
                    let mut r = (f32::INFINITY, f32::NEG_INFINITY);
                    for z in span(2) {
                        for y in span(1) {
                            for x in span(0) {
                                let v = values[(z * dims[1] + y) * dims[0] + x];
                                r = if v.is_nan() {
                                    (f32::NEG_INFINITY, f32::INFINITY)
                                } else {
                                    (r.0.min(v), r.1.max(v))
                                };
                            }
                        }
                    }
                    ranges.push(r);
                }
            }
        }
        BrickRanges { bricks, ranges }
    }

    #[test]
    fn brick_ranges_equal_a_brute_force_scan_apron_and_nan_included() {
        let dims = [19, 11, 23];
        let mut rng = crate::rng::SplitMix64(7);
        let mut values: Vec<f32> = (0..dims.iter().product::<usize>())
            .map(|_| (rng.unit() * 100.0) as f32)
            .collect();
        values[5 * 19 * 11 + 3 * 19 + 17] = f32::NAN;
        assert_eq!(BrickRanges::of(&values, dims), brute(&values, dims));
    }

    #[test]
    fn transparency_follows_the_texels_a_lookup_can_touch() {
        // 16 texels over values 0..16 (texel i is centred on value i + 0.5): opaque at 8 only.
        let mut alpha = vec![0.0; 16];
        alpha[8] = 0.5;
        let t = Transparency::lut(&alpha, (0.0, 1.0 / 16.0));
        assert!(t.transparent(0.0, 5.0));
        // Within a texel and a margin of the opaque one: not transparent.
        assert!(!t.transparent(0.0, 6.7));
        assert!(!t.transparent(9.6, 9.9));
        assert!(t.transparent(11.0, 16.0));
        assert!(!t.transparent(f32::NEG_INFINITY, 1.0));
        // Pre-integrated: a square of the table; an opaque entry off the diagonal (a segment
        // from a low to a high value) counts only when both its values are in the range.
        let n = 16;
        let mut table = vec![0.0; n * n];
        table[12 * n + 2] = 0.1;
        let p = Transparency::preintegrated(&table, n, (0.0, 1.0 / 16.0));
        assert!(p.transparent(0.0, 8.0));
        assert!(p.transparent(5.0, 15.0));
        assert!(!p.transparent(0.0, 12.0));
        assert!(!p.transparent(1.0, 16.0));
    }
}
