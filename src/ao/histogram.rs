//! Local-histogram AO with colour bleeding (Ropinski et al.), exactly as docs/design.md
//! ("Local-histogram AO") defines it. Every voxel's neighbourhood S_r is summarised, once and
//! independently of the transfer function, as a histogram of its bins weighted by 1/d^2; the
//! histograms are clustered (LBG on packed histograms, L2), so that per TF each cluster's
//! occlusion O_env and bleeding colour E is one dot product with the TF's per-bin opacity and
//! colour. This file holds the parameters, the definition's CPU reference (f64), the packing,
//! the LBG training, the per-TF table and the on-disk cache; [`super::histogram_gpu`] runs the
//! heavy parts (the histograms, the assignment, the direct sums of the clip update).

use crate::rng::SplitMix64;
use crate::volume::labels::LabelMap;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

pub use crate::shader_constants::{
    HIST_BRICK_SHIFT, HIST_MAX_BINS, HIST_MAX_PACKED, SAME_AS_FRONT,
};

/// The local-histogram AO's parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HistParams {
    /// r: the neighbourhood's radius in mm.
    pub radius_mm: f64,
    /// B: histogram bins over the data's value range.
    pub bins: usize,
    /// N: clusters (0: the direct, unclustered definition).
    pub clusters: usize,
    /// Two hemispheres split by the gradient (the front's sums), not one sphere.
    pub hemispheres: bool,
}

impl Default for HistParams {
    /// r = 12 mm (the paper's head used 12 to 24 voxels of about 1 mm); 64 bins (64 HU each on
    /// CT, which keeps air, fat, soft tissue and bone apart); the paper's 2048 clusters; its two
    /// hemispheres.
    fn default() -> Self {
        HistParams {
            radius_mm: 12.0,
            bins: 64,
            clusters: 2048,
            hemispheres: true,
        }
    }
}

impl HistParams {
    pub fn validate(&self) -> Result<(), String> {
        if !(self.radius_mm.is_finite() && self.radius_mm > 0.0 && self.radius_mm <= 64.0) {
            return Err(format!(
                "--hist-radius-mm must be in (0, 64] mm, got {}",
                self.radius_mm
            ));
        }
        if !(2..=HIST_MAX_BINS as usize).contains(&self.bins) {
            return Err(format!(
                "--hist-bins must be in 2..={HIST_MAX_BINS}, got {}",
                self.bins
            ));
        }
        if self.clusters > MAX_CLUSTERS {
            return Err(format!(
                "--clusters must be at most {MAX_CLUSTERS} (0: the direct sums), got {}",
                self.clusters
            ));
        }
        Ok(())
    }
}

/// The packed dimension the clustering compares histograms of `shades` entries in
/// ([`Shades`]): a quarter of them (the paper packs 256 bins into 64), at least 8 (or all) and
/// at most [`HIST_MAX_PACKED`].
pub fn packed_dims(shades: usize) -> usize {
    (shades / 4).clamp(shades.min(8), HIST_MAX_PACKED as usize)
}

/// Most clusters `--clusters` takes (cluster ids are stored as u16 in the cache).
pub const MAX_CLUSTERS: usize = 16384;

/// bin(u) = min(B-1, floor(B (value_u - v_min) / (v_max - v_min))), in f64, over the range the
/// volume is classified over (a crop's is the whole's); 0 for a constant volume.
pub fn bins(vol: &Volume, b: usize) -> Vec<u32> {
    let (lo, hi) = vol.value_range();
    let span = hi as f64 - lo as f64;
    (0..vol.voxel_count())
        .into_par_iter()
        .map(|i| {
            if span > 0.0 {
                let t = b as f64 * (vol.voxels.get(i) as f64 - lo as f64) / span;
                (t.floor().max(0.0) as usize).min(b - 1) as u32
            } else {
                0
            }
        })
        .collect()
}

/// Per bin k: the TF's colour (rgb) and opacity (a, per mm as in the TF file) at the bin's
/// centre value v_min + (k + 1/2) (v_max - v_min) / B.
pub fn bin_table(tf: &TransferFunction, range: (f32, f32), b: usize) -> Vec<[f32; 4]> {
    let span = range.1 as f64 - range.0 as f64;
    (0..b)
        .map(|k| {
            let v = range.0 as f64 + (k as f64 + 0.5) * span / b as f64;
            tf.eval(v as f32, range)
        })
        .collect()
}

/// The histograms' entries with the structures folded in (docs/design.md, "Local-histogram
/// AO", labels): an unlabelled voxel's shade is its bin k (0..B); a labelled voxel's is the pair
/// (its structure id, k), numbered after the B bins in (id, k) order over the pairs the volume
/// holds. Under a TF and the structures as shown, each shade has one colour and one opacity, so
/// the local histograms, their clusters, the TF table and the direct sums all follow the
/// structures as they follow the bins. Without labels the shades are the bins.
#[derive(Clone, Debug, PartialEq)]
pub struct Shades {
    /// Each voxel's shade.
    pub ids: Vec<u32>,
    /// Each shade's (structure id, bin); the first B are (0, k).
    pub pairs: Vec<(u8, u32)>,
}

impl Shades {
    pub fn new(bins: Vec<u32>, b: usize, labels: Option<&LabelMap>) -> Shades {
        let mut pairs: Vec<(u8, u32)> = (0..b as u32).map(|k| (0, k)).collect();
        let Some(l) = labels else {
            return Shades { ids: bins, pairs };
        };
        // index[id * B + k]: the shade of the pair (id, k) where the volume holds it.
        let mut index = vec![u32::MAX; 256 * b];
        for (&k, &id) in bins.iter().zip(&l.ids) {
            if id > 0 {
                index[id as usize * b + k as usize] = 0;
            }
        }
        for (j, slot) in index.iter_mut().enumerate().filter(|(_, s)| **s == 0) {
            *slot = pairs.len() as u32;
            pairs.push(((j / b) as u8, (j % b) as u32));
        }
        let ids = bins
            .par_iter()
            .zip(&l.ids)
            .map(|(&k, &id)| {
                if id == 0 {
                    k
                } else {
                    index[id as usize * b + k as usize]
                }
            })
            .collect();
        Shades { ids, pairs }
    }

    pub fn count(&self) -> usize {
        self.pairs.len()
    }

    /// Per shade, its colour and opacity: bin k's TF colour and opacity (`bins`, from
    /// [`bin_table`]) for an unlabelled shade; for (id, k) the structure's colour and α_k times
    /// its opacity a_l as `shown` (by structure index, 0 hidden; empty: the label map's own).
    pub fn table(
        &self,
        bins: &[[f32; 4]],
        labels: Option<&LabelMap>,
        shown: &[f32],
    ) -> Vec<[f32; 4]> {
        self.pairs
            .iter()
            .map(|&(id, k)| {
                let t = bins[k as usize];
                match (id as usize, labels) {
                    (0, _) | (_, None) => t,
                    (id, Some(l)) => {
                        let s = &l.structures[id - 1];
                        let a = shown.get(id - 1).copied().unwrap_or(s.opacity);
                        let [r, g, b] = s.colour;
                        [r, g, b, t[3] * a]
                    }
                }
            })
            .collect()
    }

    /// q of the unclipped volume: each voxel's shade opacity (`table` from [`Shades::table`]),
    /// the histogram method's O of docs/design.md.
    pub fn q(&self, table: &[[f32; 4]]) -> Vec<f32> {
        self.ids.par_iter().map(|&s| table[s as usize][3]).collect()
    }
}

/// S_r with its weights: every integer offset o != 0 with |o * s| <= r (mm), in z, y, x order,
/// w(o) = (s_min / |o * s|)^2, and W = the sum of w.
#[derive(Clone, Debug)]
pub struct Neighbourhood {
    pub offsets: Vec<[i32; 3]>,
    pub weights: Vec<f64>,
    pub total: f64,
}

impl Neighbourhood {
    pub fn new(radius_mm: f64, spacing: [f64; 3]) -> Neighbourhood {
        let s_min = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
        let h = spacing.map(|s| (radius_mm / s).floor() as i32);
        let (mut offsets, mut weights) = (Vec::new(), Vec::new());
        for z in -h[2]..=h[2] {
            for y in -h[1]..=h[1] {
                for x in -h[0]..=h[0] {
                    let d2 = [x, y, z]
                        .iter()
                        .zip(spacing)
                        .map(|(&o, s)| (o as f64 * s).powi(2))
                        .sum::<f64>();
                    if d2 > 0.0 && d2 <= radius_mm * radius_mm {
                        offsets.push([x, y, z]);
                        weights.push(s_min * s_min / d2);
                    }
                }
            }
        }
        let total = weights.iter().sum();
        Neighbourhood {
            offsets,
            weights,
            total,
        }
    }

    /// The farthest member, in mm (the method's reach).
    pub fn reach_mm(&self, spacing: [f64; 3]) -> f64 {
        self.offsets
            .iter()
            .map(|o| {
                (0..3)
                    .map(|a| (o[a] as f64 * spacing[a]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(0.0, f64::max)
    }

    /// The GPU's table: offset xyz and the normalised weight w / W, as vec4.
    pub fn gpu_table(&self) -> Vec<[f32; 4]> {
        self.offsets
            .iter()
            .zip(&self.weights)
            .map(|(o, w)| {
                [
                    o[0] as f32,
                    o[1] as f32,
                    o[2] as f32,
                    (w / self.total) as f32,
                ]
            })
            .collect()
    }
}

/// What the direct definition needs of `vol` under `tf` with B = `b` bins and the structures as
/// shown by `structures` (empty: the label map's own): q of the unclipped volume, each voxel's
/// shade and the shade table ([`Shades`]).
#[allow(clippy::type_complexity)]
pub fn direct_inputs(
    vol: &Volume,
    tf: &TransferFunction,
    b: usize,
    structures: &[f32],
) -> (Vec<f32>, Vec<u32>, Vec<[f32; 4]>) {
    let labels = vol.labels.as_deref();
    let shades = Shades::new(bins(vol, b), b, labels);
    let table = shades.table(&bin_table(tf, vol.value_range(), b), labels, structures);
    (shades.q(&table), shades.ids, table)
}

/// The hemispheres' split of every voxel (docs/design.md, "Local-histogram AO", two
/// hemispheres): Δ(v), the scalar's central differences with the neighbours clamped into the
/// grid, or None where the gradient Δ_i / (2 s_i) is shorter than the ray caster's lighting
/// threshold ([`super::MIN_GRADIENT`] of the value range per mm): a flat voxel keeps S_r.
pub fn splits(vol: &Volume) -> Vec<Option<[f64; 3]>> {
    let (lo, hi) = vol.value_range();
    let gmin = super::MIN_GRADIENT as f64 * (hi as f64 - lo as f64);
    let d = vol.dims;
    (0..vol.voxel_count())
        .into_par_iter()
        .map(|i| {
            let v = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
            let stride = [1, d[0], d[0] * d[1]];
            let delta: [f64; 3] = std::array::from_fn(|a| {
                let up = if v[a] + 1 < d[a] { i + stride[a] } else { i };
                let down = if v[a] > 0 { i - stride[a] } else { i };
                vol.voxels.get(up) as f64 - vol.voxels.get(down) as f64
            });
            let g2: f64 = (0..3)
                .map(|a| (delta[a] / (2.0 * vol.spacing[a])).powi(2))
                .sum();
            (g2 >= gmin * gmin).then_some(delta)
        })
        .collect()
}

/// The direct definition on q (clip coverage already applied): openness A = 1 - O_env and the
/// bleeding colour E (0 where no neighbour is opaque), in f64, voxel by voxel. A member's colour
/// is `table[shades[j]]` ([`Shades`]; without labels the bins and [`bin_table`]). With `splits`
/// ([`splits`]; empty: one sphere) the sums run over each voxel's front hemisphere H_f.
pub fn direct_reference(
    dims: [usize; 3],
    q: &[f32],
    shades: &[u32],
    table: &[[f32; 4]],
    nb: &Neighbourhood,
    splits: &[Option<[f64; 3]>],
) -> (Vec<f32>, Vec<[f32; 3]>) {
    let n = dims[0] * dims[1] * dims[2];
    (0..n)
        .into_par_iter()
        .map(|i| {
            let split = splits.get(i).copied().flatten();
            direct_at(dims, q, shades, table, nb, split, i)
        })
        .unzip()
}

/// [`direct_reference`] of one voxel.
pub fn direct_at(
    dims: [usize; 3],
    q: &[f32],
    shades: &[u32],
    table: &[[f32; 4]],
    nb: &Neighbourhood,
    split: Option<[f64; 3]>,
    i: usize,
) -> (f32, [f32; 3]) {
    let v = [
        (i % dims[0]) as i32,
        ((i / dims[0]) % dims[1]) as i32,
        (i / (dims[0] * dims[1])) as i32,
    ];
    let (mut occ, mut rgb) = (0.0f64, [0.0f64; 3]);
    // W of what the sums run over: S_r's, or H_f's (out-of-grid members included).
    let mut total = if split.is_some() { 0.0 } else { nb.total };
    for (o, w) in nb.offsets.iter().zip(&nb.weights) {
        if let Some(d) = split {
            // H_f: (u - v) . Δ <= 0, down the gradient, away from the higher values.
            if (0..3).map(|a| o[a] as f64 * d[a]).sum::<f64>() > 0.0 {
                continue;
            }
            total += w;
        }
        let u = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
        if (0..3).any(|a| u[a] < 0 || u[a] >= dims[a] as i32) {
            continue;
        }
        let j = u[0] as usize + dims[0] * (u[1] as usize + dims[1] * u[2] as usize);
        let wq = w * q[j] as f64;
        occ += wq;
        let c = &table[shades[j] as usize];
        for ch in 0..3 {
            rgb[ch] += wq * c[ch] as f64;
        }
    }
    let e = if occ > 0.0 {
        rgb.map(|c| (c / occ) as f32)
    } else {
        [0.0; 3]
    };
    let o_env = if total > 0.0 { occ / total } else { 0.0 };
    ((1.0 - o_env) as f32, e)
}

/// The local histogram LH(v) of the unclipped volume: per bin (or shade, [`Shades`]), the sum
/// of w over the in-grid members of S_r in that bin, over W (f64; the reference the GPU's
/// histograms are tested against).
pub fn local_histogram(
    dims: [usize; 3],
    bins: &[u32],
    b: usize,
    nb: &Neighbourhood,
    voxel: usize,
) -> Vec<f64> {
    let v = [
        (voxel % dims[0]) as i32,
        ((voxel / dims[0]) % dims[1]) as i32,
        (voxel / (dims[0] * dims[1])) as i32,
    ];
    let mut h = vec![0.0; b];
    for (o, w) in nb.offsets.iter().zip(&nb.weights) {
        let u = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
        if (0..3).any(|a| u[a] < 0 || u[a] >= dims[a] as i32) {
            continue;
        }
        let j = u[0] as usize + dims[0] * (u[1] as usize + dims[1] * u[2] as usize);
        h[bins[j] as usize] += w / nb.total;
    }
    h
}

/// The hemispheres' split as histogram_local.comp computes it, in f32: the scalars (integer
/// data as their values, whose differences are those of the 16-bit words the shader reads),
/// whether they are integers, 1 / (2 s) per axis, and the square of the flat threshold.
pub struct SplitF32<'a> {
    pub values: &'a [f32],
    pub integer: bool,
    pub half_inv_spacing: [f32; 3],
    pub flat2: f32,
}

impl SplitF32<'_> {
    /// 1 / (2 s) per axis and the square of the flat threshold ([`super::MIN_GRADIENT`] of the
    /// value range per mm), as the shaders read them.
    pub fn parameters(spacing: [f64; 3], range: (f32, f32)) -> ([f32; 3], f32) {
        let gmin = super::MIN_GRADIENT as f64 * (range.1 as f64 - range.0 as f64);
        (spacing.map(|s| (0.5 / s) as f32), (gmin * gmin) as f32)
    }

    /// Δ(v), the central differences with the neighbours clamped into the grid, where the
    /// gradient is steep enough to split.
    fn at(&self, dims: [usize; 3], i: usize, v: [usize; 3]) -> Option<[f32; 3]> {
        let stride = [1, dims[0], dims[0] * dims[1]];
        let d: [f32; 3] = std::array::from_fn(|a| {
            let up = if v[a] + 1 < dims[a] { i + stride[a] } else { i };
            let down = if v[a] > 0 { i - stride[a] } else { i };
            self.values[up] - self.values[down]
        });
        let g: [f32; 3] = std::array::from_fn(|a| d[a] * self.half_inv_spacing[a]);
        (g[0] * g[0] + g[1] * g[1] + g[2] * g[2] >= self.flat2).then_some(d)
    }
}

/// histogram_local.comp on the host's cores, bit for bit: the rows of `out.len() / (rows per
/// voxel x shades)` voxels, the r-th being `voxel(r)`, laid out as the shader writes them (H_f's
/// then H_b's with `split`, a flat voxel's second row marked by -1). The same f32 sums in the
/// order of S_r (`table`: [`Neighbourhood::gpu_table`]), so the same bits: a CPU renderer runs
/// the shader's scattered reads and adds lane by lane, and the host's own code is several times
/// faster there (docs/benchmarks.md).
pub fn local_rows_f32(
    dims: [usize; 3],
    (shades, count): (&[u32], usize),
    table: &[[f32; 4]],
    split: Option<&SplitF32>,
    voxel: impl Fn(usize) -> usize + Sync,
    out: &mut [f32],
) {
    // S_r in runs of consecutive x (it is ordered by z, y, x): a run's members are read from
    // consecutive voxels, and those in the grid are a sub-range of it.
    struct Run {
        first: usize,
        len: usize,
        o: [i32; 3],
    }
    let mut runs: Vec<Run> = Vec::new();
    for (m, t) in table.iter().enumerate() {
        let o = [t[0] as i32, t[1] as i32, t[2] as i32];
        match runs.last_mut() {
            Some(r) if r.o[1..] == o[1..] && r.o[0] + r.len as i32 == o[0] => r.len += 1,
            _ => runs.push(Run {
                first: m,
                len: 1,
                o,
            }),
        }
    }
    let weights: Vec<f32> = table.iter().map(|t| t[3]).collect();
    let d32 = dims.map(|d| d as i32);
    let hemis = 1 + split.is_some() as usize;
    out.par_chunks_mut(hemis * count).enumerate().for_each_init(
        || vec![0.0f32; 2 * count],
        |h, (r, rows)| {
            let i = voxel(r);
            let v = [
                i % dims[0],
                (i / dims[0]) % dims[1],
                i / (dims[0] * dims[1]),
            ]
            .map(|x| x as i32);
            let d = split.and_then(|s| s.at(dims, i, v.map(|x| x as usize)));
            let integer = split.is_some_and(|s| s.integer);
            h.fill(0.0);
            // The entry last added to, held in a register until another is (the same
            // additions in the same order: a uniform neighbourhood's members would
            // otherwise each wait for the previous one's store).
            let (mut slot, mut held) = (0usize, h[0]);
            let mut add = |h: &mut [f32], k: usize, w: f32| {
                if k != slot {
                    h[slot] = held;
                    (slot, held) = (k, h[k]);
                }
                held += w;
            };
            let (mut total_f, mut total_b) = (0.0f32, 0.0f32);
            for run in &runs {
                let (y, z, x) = (v[1] + run.o[1], v[2] + run.o[2], v[0] + run.o[0]);
                // The run's members in the grid: lo..hi.
                let (lo, hi) = if (0..d32[1]).contains(&y) && (0..d32[2]).contains(&z) {
                    let lo = (-x).clamp(0, run.len as i32) as usize;
                    (lo, (d32[0] - x).clamp(lo as i32, run.len as i32) as usize)
                } else {
                    (0, 0)
                };
                // The run's member j is voxel at + j (read only for j in lo..hi).
                let at = (x + d32[0] * (y + d32[1] * z)) as isize;
                let read = |j: usize| (at + j as isize) as usize;
                let w = &weights[run.first..run.first + run.len];
                let Some(d) = d else {
                    if lo < hi {
                        let members = &shades[read(lo)..read(hi)];
                        for (&k, &w) in members.iter().zip(&w[lo..hi]) {
                            add(h, k as usize, w);
                        }
                    }
                    continue;
                };
                for (j, &w) in w.iter().enumerate() {
                    let o = [run.o[0] + j as i32, run.o[1], run.o[2]];
                    let back = if integer {
                        o[0] * d[0] as i32 + o[1] * d[1] as i32 + o[2] * d[2] as i32 > 0
                    } else {
                        o[0] as f32 * d[0] + o[1] as f32 * d[1] + o[2] as f32 * d[2] > 0.0
                    };
                    if back {
                        total_b += w;
                    } else {
                        total_f += w;
                    }
                    if (lo..hi).contains(&j) {
                        add(
                            h,
                            if back { count } else { 0 } + shades[read(j)] as usize,
                            w,
                        );
                    }
                }
            }
            h[slot] = held;
            let (front, back) = rows.split_at_mut(count);
            if d.is_some() {
                let scale = |t: f32| if t > 0.0 { 1.0 / t } else { 0.0 };
                let (sf, sb) = (scale(total_f), scale(total_b));
                for k in 0..count {
                    front[k] = h[k] * sf;
                    back[k] = h[count + k] * sb;
                }
            } else {
                front.copy_from_slice(&h[..count]);
                if let Some((first, rest)) = back.split_first_mut() {
                    *first = -1.0;
                    rest.fill(0.0);
                }
            }
        },
    );
}

/// The bricks (2^[`HIST_BRICK_SHIFT`] voxels per axis, x fastest, one bit each) none of whose
/// voxels has a voxel with q > 0 within `reach` voxels per axis (the box around S_r). Every w q
/// of such a voxel is 0, so its direct sums are A = 1 and E = 0 under any clip (clipping only
/// lowers q): histogram_sums.comp skips their member loop, the same bits.
pub fn clear_bricks(dims: [usize; 3], q: &[f32], reach: [usize; 3]) -> Vec<u32> {
    debug_assert_eq!(q.len(), dims.iter().product::<usize>());
    let side = 1usize << HIST_BRICK_SHIFT;
    let bd = dims.map(|d| d.div_ceil(side));
    // The voxels along axis a that brick c's voxels reach, inclusive.
    let within = move |a: usize, c: usize| {
        let lo = (c * side).saturating_sub(reach[a]);
        lo..=((c + 1) * side - 1 + reach[a]).min(dims[a] - 1)
    };
    // Separably, one axis at a time: whether any opaque voxel lies within reach of the brick
    // along x (per brick column of each row), then y (per slice), then z.
    let along_x: Vec<bool> = q
        .par_chunks(dims[0])
        .flat_map_iter(|row| {
            let mut before = vec![0u32; row.len() + 1];
            for (x, &v) in row.iter().enumerate() {
                before[x + 1] = before[x] + (v > 0.0) as u32;
            }
            (0..bd[0]).map(move |bx| {
                let r = within(0, bx);
                before[r.end() + 1] > before[*r.start()]
            })
        })
        .collect();
    let along_y: Vec<bool> = along_x
        .par_chunks(bd[0] * dims[1])
        .flat_map_iter(|slice| {
            (0..bd[1]).flat_map(move |by| {
                (0..bd[0]).map(move |bx| within(1, by).any(|y| slice[bx + bd[0] * y]))
            })
        })
        .collect();
    let plane = bd[0] * bd[1];
    let clear: Vec<bool> = (0..plane * bd[2])
        .into_par_iter()
        .map(|b| !within(2, b / plane).any(|z| along_y[b % plane + plane * z]))
        .collect();
    let mut bits = vec![0u32; clear_brick_words(dims)];
    for (b, _) in clear.iter().enumerate().filter(|(_, &c)| c) {
        bits[b / 32] |= 1 << (b % 32);
    }
    bits
}

/// The u32 words [`clear_bricks`] gives for a volume of `dims` (at least one).
pub fn clear_brick_words(dims: [usize; 3]) -> usize {
    let bricks: usize = dims
        .iter()
        .map(|d| d.div_ceil(1 << HIST_BRICK_SHIFT))
        .product();
    bricks.div_ceil(32).max(1)
}

/// The paper's histogram packing: starting from the volume's normalised histogram, the smallest
/// bin is split repeatedly and its content given in equal halves to its two neighbours (all of
/// it to the one neighbour at an end) until `packed` bins remain. `matrix[k * packed + p]` is
/// the share of original bin k in packed bin p, so packed = LH . matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct Packing {
    pub bins: usize,
    pub packed: usize,
    pub matrix: Vec<f32>,
}

impl Packing {
    pub fn new(bin_ids: &[u32], b: usize, packed: usize) -> Packing {
        let mut h = vec![0.0f64; b];
        for &k in bin_ids {
            h[k as usize] += 1.0;
        }
        // Each current bin: its global mass and its shares of the original bins (sparse: with
        // labels there can be thousands of shades).
        let mut cols: Vec<(f64, BTreeMap<usize, f64>)> =
            (0..b).map(|k| (h[k], BTreeMap::from([(k, 1.0)]))).collect();
        while cols.len() > packed.max(1) {
            let j = (0..cols.len())
                .min_by(|&x, &y| cols[x].0.total_cmp(&cols[y].0))
                .expect("non-empty");
            let (mass, share) = cols.remove(j);
            // Neighbours of the removed bin, in the shortened list.
            let left = j.checked_sub(1);
            let right = (j < cols.len()).then_some(j);
            let parts: Vec<usize> = left.into_iter().chain(right).collect();
            let f = 1.0 / parts.len() as f64;
            for p in parts {
                cols[p].0 += f * mass;
                for (&k, s) in &share {
                    *cols[p].1.entry(k).or_insert(0.0) += f * s;
                }
            }
        }
        let packed = cols.len();
        let mut matrix = vec![0.0f32; b * packed];
        for (p, (_, share)) in cols.iter().enumerate() {
            for (&k, &x) in share {
                matrix[k * packed + p] = x as f32;
            }
        }
        Packing {
            bins: b,
            packed,
            matrix,
        }
    }

    pub fn pack(&self, lh: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0f32; self.packed];
        // Skipping the zeros changes no sum (histogram_assign.comp does the same).
        for (k, &x) in lh.iter().enumerate().filter(|(_, x)| **x != 0.0) {
            for (p, o) in out.iter_mut().enumerate() {
                *o += x * self.matrix[k * self.packed + p];
            }
        }
        out
    }
}

/// Squared L2 distance, summed in the same order as histogram_assign.comp.
fn dist2(a: &[f32], b: &[f32]) -> f32 {
    let mut s = 0.0;
    for (x, y) in a.iter().zip(b) {
        s += (x - y) * (x - y);
    }
    s
}

/// The nearest centroid (the first of equals), and its squared distance.
pub fn nearest(centroids: &[f32], dim: usize, p: &[f32]) -> (u32, f32) {
    let mut best = (0u32, f32::INFINITY);
    for (c, cen) in centroids.chunks_exact(dim).enumerate() {
        let d = dist2(cen, p);
        if d < best.1 {
            best = (c as u32, d);
        }
    }
    best
}

/// Lloyd iterations of each LBG stage, and of the last.
const LBG_ITERATIONS: usize = 4;
const LBG_FINAL_ITERATIONS: usize = 8;

/// LBG (Linde, Buzo, Gray) on `samples` (rows of `dim`): start from the mean, split every
/// centroid in two (times 1 +- 1e-3) and run Lloyd's iterations, until `n` centroids; a cluster
/// left empty takes the sample farthest from its centroid. Deterministic.
pub fn lbg(samples: &[f32], dim: usize, n: usize) -> Vec<f32> {
    let count = samples.len() / dim;
    let n = n.max(1);
    let mut centroids = vec![0.0f32; dim];
    for s in samples.chunks_exact(dim) {
        for (c, x) in centroids.iter_mut().zip(s) {
            *c += x / count.max(1) as f32;
        }
    }
    let mut k = 1;
    while k < n {
        // Split the most populated clusters first when not all of them can split.
        let splits = (n - k).min(k);
        let assign = assign_all(samples, dim, &centroids);
        let mut pop = vec![0usize; k];
        for &(c, _) in &assign {
            pop[c as usize] += 1;
        }
        let mut order: Vec<usize> = (0..k).collect();
        order.sort_by_key(|&c| std::cmp::Reverse(pop[c]));
        for &c in &order[..splits] {
            let base: Vec<f32> = centroids[c * dim..(c + 1) * dim].to_vec();
            for (d, x) in base.iter().enumerate() {
                centroids[c * dim + d] = x * (1.0 + 1e-3);
            }
            centroids.extend(base.iter().map(|x| x * (1.0 - 1e-3) + 1e-6));
        }
        k += splits;
        let iterations = if k == n {
            LBG_FINAL_ITERATIONS
        } else {
            LBG_ITERATIONS
        };
        for _ in 0..iterations {
            if !lloyd(samples, dim, &mut centroids) {
                break;
            }
        }
    }
    centroids
}

/// Groups of centroids for the two-level assignment: `centres` (G x dim), and group g's
/// members (centroid indices, ascending) `members[first[g]..first[g + 1]]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Groups {
    pub centres: Vec<f32>,
    pub first: Vec<u32>,
    pub members: Vec<u32>,
}

/// How many groups the assignment searches (histogram_assign.comp's GROUPS_SEARCHED).
pub const GROUPS_SEARCHED: usize = 3;

impl Groups {
    /// About sqrt(2 N) groups from k-means (Lloyd) on the centroids themselves, started from
    /// evenly spaced centroids; each centroid belongs to its nearest centre.
    pub fn new(centroids: &[f32], dim: usize) -> Groups {
        let n = centroids.len() / dim;
        let g = ((2.0 * n as f64).sqrt().ceil() as usize).clamp(1, n.max(1));
        let mut centres: Vec<f32> = (0..g)
            .flat_map(|i| centroids[(i * n / g) * dim..(i * n / g + 1) * dim].to_vec())
            .collect();
        for _ in 0..10 {
            if !lloyd(centroids, dim, &mut centres) {
                break;
            }
        }
        let owner: Vec<u32> = assign_all(centroids, dim, &centres)
            .iter()
            .map(|a| a.0)
            .collect();
        let mut first = vec![0u32; g + 1];
        for &o in &owner {
            first[o as usize + 1] += 1;
        }
        for i in 0..g {
            first[i + 1] += first[i];
        }
        let mut fill = first.clone();
        let mut members = vec![0u32; n];
        for (c, &o) in owner.iter().enumerate() {
            members[fill[o as usize] as usize] = c as u32;
            fill[o as usize] += 1;
        }
        Groups {
            centres,
            first,
            members,
        }
    }

    /// The assignment histogram_assign.comp makes: the nearest centroid among the members of
    /// the [`GROUPS_SEARCHED`] groups whose centres are nearest.
    pub fn assign(&self, centroids: &[f32], dim: usize, p: &[f32]) -> u32 {
        let mut groups: Vec<(f32, usize)> = self
            .centres
            .chunks_exact(dim)
            .enumerate()
            .map(|(g, c)| (dist2(c, p), g))
            .collect();
        groups.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut best = (f32::INFINITY, 0u32);
        for &(_, g) in groups.iter().take(GROUPS_SEARCHED) {
            for &c in &self.members[self.first[g] as usize..self.first[g + 1] as usize] {
                let d = dist2(&centroids[c as usize * dim..(c as usize + 1) * dim], p);
                if d < best.0 || (d == best.0 && c < best.1) {
                    best = (d, c);
                }
            }
        }
        best.1
    }
}

/// The assignment of whole batches on the host's cores, histogram_assign.comp's twin bit for
/// bit ([`Groups::assign`] after [`Packing::pack`], a flat voxel's second row
/// [`SAME_AS_FRONT`]): each row's squared distances to the group centres and then to the
/// searched groups' members are summed in the same element order, but for many centres at once
/// from tables stored element by element, which the compiler vectorises.
pub struct HostAssign<'a> {
    groups: &'a Groups,
    packing: &'a Packing,
    /// The group centres, element-major: `centres[e * G + g]`.
    centres: Vec<f32>,
    /// Each group's members' centroids, element-major within the group: member j of group g,
    /// element e at `members[first[g] * dim + e * len_g + j]`.
    members: Vec<f32>,
}

/// The squared distances of `p` to the `n` points of `table` (element-major: element e of point
/// i at `table[e * n + i]`) into `out`, each summed over the elements in order.
fn distances(table: &[f32], n: usize, p: &[f32], out: &mut [f32]) {
    let out = &mut out[..n];
    out.fill(0.0);
    for (e, &x) in p.iter().enumerate() {
        for (o, &c) in out.iter_mut().zip(&table[e * n..(e + 1) * n]) {
            let t = c - x;
            *o += t * t;
        }
    }
}

impl<'a> HostAssign<'a> {
    pub fn new(groups: &'a Groups, packing: &'a Packing, centroids: &[f32]) -> HostAssign<'a> {
        let dim = packing.packed;
        let g = groups.first.len() - 1;
        let centres = (0..dim)
            .flat_map(|e| (0..g).map(move |i| groups.centres[i * dim + e]))
            .collect();
        let mut members = vec![0.0f32; groups.members.len() * dim];
        for i in 0..g {
            let (first, last) = (groups.first[i] as usize, groups.first[i + 1] as usize);
            let block = &mut members[first * dim..last * dim];
            for (j, &c) in groups.members[first..last].iter().enumerate() {
                for e in 0..dim {
                    block[e * (last - first) + j] = centroids[c as usize * dim + e];
                }
            }
        }
        HostAssign {
            groups,
            packing,
            centres,
            members,
        }
    }

    /// The cluster of each row of `rows` (the shades' sums, [`Packing::bins`] each).
    pub fn assign(&self, rows: &[f32]) -> Vec<u32> {
        let (b, dim) = (self.packing.bins, self.packing.packed);
        let (groups, first) = (self.groups.first.len() - 1, &self.groups.first);
        let most = (0..groups)
            .map(|g| (first[g + 1] - first[g]) as usize)
            .max()
            .unwrap_or(0);
        rows.par_chunks_exact(b)
            .map_init(
                || (vec![0.0f32; dim], vec![0.0f32; groups.max(most)]),
                |(p, d), lh| {
                    if lh[0] < 0.0 {
                        return SAME_AS_FRONT;
                    }
                    p.fill(0.0);
                    for (k, &x) in lh.iter().enumerate().filter(|(_, x)| **x != 0.0) {
                        let m = &self.packing.matrix[k * dim..(k + 1) * dim];
                        for (o, &w) in p.iter_mut().zip(m) {
                            *o += x * w;
                        }
                    }
                    // The nearest groups, as the shader inserts them (the first of equals).
                    distances(&self.centres, groups, p, d);
                    let mut near = [(f32::INFINITY, usize::MAX); GROUPS_SEARCHED];
                    for (g, &dg) in d[..groups].iter().enumerate() {
                        if dg < near[GROUPS_SEARCHED - 1].0 {
                            let mut i = GROUPS_SEARCHED - 1;
                            while i > 0 && dg < near[i - 1].0 {
                                near[i] = near[i - 1];
                                i -= 1;
                            }
                            near[i] = (dg, g);
                        }
                    }
                    let mut best = (f32::INFINITY, 0u32);
                    for &(_, g) in near.iter().filter(|n| n.1 != usize::MAX) {
                        let (f, l) = (first[g] as usize, first[g + 1] as usize);
                        distances(&self.members[f * dim..l * dim], l - f, p, d);
                        for (&c, &dc) in self.groups.members[f..l].iter().zip(&d[..l - f]) {
                            if dc < best.0 || (dc == best.0 && c < best.1) {
                                best = (dc, c);
                            }
                        }
                    }
                    best.1
                },
            )
            .collect()
    }
}

/// Each sample's [`nearest`] centroid and its squared distance.
fn assign_all(samples: &[f32], dim: usize, centroids: &[f32]) -> Vec<(u32, f32)> {
    let k = centroids.len() / dim;
    // Element-major, so that `distances` sums many centroids at once (dist2's sums).
    let table: Vec<f32> = (0..dim)
        .flat_map(|e| (0..k).map(move |c| centroids[c * dim + e]))
        .collect();
    samples
        .par_chunks_exact(dim)
        .map_init(
            || vec![0.0f32; k],
            |d, s| {
                distances(&table, k, s, d);
                let mut best = (0u32, f32::INFINITY);
                for (c, &dc) in d.iter().enumerate() {
                    if dc < best.1 {
                        best = (c as u32, dc);
                    }
                }
                best
            },
        )
        .collect()
}

/// One Lloyd iteration; returns whether any assignment changed the centroids.
fn lloyd(samples: &[f32], dim: usize, centroids: &mut [f32]) -> bool {
    let k = centroids.len() / dim;
    let assign = assign_all(samples, dim, centroids);
    let mut sums = vec![0.0f64; k * dim];
    let mut pop = vec![0usize; k];
    for (s, &(c, _)) in samples.chunks_exact(dim).zip(&assign) {
        pop[c as usize] += 1;
        for (d, x) in s.iter().enumerate() {
            sums[c as usize * dim + d] += *x as f64;
        }
    }
    // Empty clusters take the samples farthest from their centroids.
    let mut far: Vec<usize> = (0..assign.len()).collect();
    far.sort_by(|&a, &b| assign[b].1.total_cmp(&assign[a].1).then(a.cmp(&b)));
    let mut far = far.into_iter();
    let mut changed = false;
    for c in 0..k {
        let new: Vec<f32> = if pop[c] > 0 {
            (0..dim)
                .map(|d| (sums[c * dim + d] / pop[c] as f64) as f32)
                .collect()
        } else {
            match far.next() {
                Some(s) => samples[s * dim..(s + 1) * dim].to_vec(),
                None => continue,
            }
        };
        if new[..] != centroids[c * dim..(c + 1) * dim] {
            changed = true;
            centroids[c * dim..(c + 1) * dim].copy_from_slice(&new);
        }
    }
    changed
}

/// The training sample: up to `count` voxel indices, deterministic. Half are drawn from
/// surface-like voxels (a 6-neighbour in another bin, the paper's |grad| > eps), the rest
/// from all voxels, so the homogeneous air and tissue do not take every cluster.
pub fn training_sample(dims: [usize; 3], bins: &[u32], count: usize) -> Vec<u32> {
    let n = bins.len();
    if n <= count {
        return (0..n as u32).collect();
    }
    let surface: Vec<u32> = (0..n)
        .into_par_iter()
        .filter(|&i| {
            let v = [
                i % dims[0],
                (i / dims[0]) % dims[1],
                i / (dims[0] * dims[1]),
            ];
            let stride = [1, dims[0], dims[0] * dims[1]];
            (0..3).any(|a| {
                (v[a] > 0 && bins[i - stride[a]] != bins[i])
                    || (v[a] + 1 < dims[a] && bins[i + stride[a]] != bins[i])
            })
        })
        .map(|i| i as u32)
        .collect();
    let mut rng = SplitMix64(0x4c48_5f73_616d_706c);
    let mut pick = |from: &dyn Fn(&mut SplitMix64) -> u32, k: usize, out: &mut Vec<u32>| {
        for _ in 0..k {
            out.push(from(&mut rng));
        }
    };
    let mut out = Vec::with_capacity(count);
    let from_surface = if surface.is_empty() { 0 } else { count / 2 };
    pick(
        &|r: &mut SplitMix64| surface[(r.next_u64() % surface.len() as u64) as usize],
        from_surface,
        &mut out,
    );
    pick(
        &|r: &mut SplitMix64| (r.next_u64() % n as u64) as u32,
        count - from_surface,
        &mut out,
    );
    out.sort_unstable();
    out
}

/// The clustering of one volume: each voxel's cluster (two with the hemispheres, H_f's first)
/// and each cluster's representative, the mean of its members' full histograms (N x shades,
/// row-major; [`Shades`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Clusters {
    /// The histograms' length: the number of shades.
    pub bins: usize,
    pub ids: Vec<u32>,
    pub reps: Vec<f32>,
}

impl Clusters {
    pub fn count(&self) -> usize {
        self.reps.len() / self.bins.max(1)
    }

    /// Per cluster, for the TF of `table` ([`Shades::table`]): rgb = E = sum LH a rgb / sum LH a
    /// (0 where nothing is opaque), a = the openness 1 - O_env = 1 - sum LH a.
    pub fn tf_table(&self, table: &[[f32; 4]]) -> Vec<[f32; 4]> {
        self.reps
            .chunks_exact(self.bins)
            .map(|lh| {
                let (mut occ, mut rgb) = (0.0f64, [0.0f64; 3]);
                for (x, t) in lh.iter().zip(table) {
                    let wa = *x as f64 * t[3] as f64;
                    occ += wa;
                    for c in 0..3 {
                        rgb[c] += wa * t[c] as f64;
                    }
                }
                let e = if occ > 0.0 {
                    rgb.map(|c| (c / occ) as f32)
                } else {
                    [0.0; 3]
                };
                [e[0], e[1], e[2], (1.0 - occ) as f32]
            })
            .collect()
    }
}

/// A 64-bit FNV-1a hash, for the cache key.
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0100_0000_01b3);
        }
    }
}

/// Bumped whenever the clustering would give other ids or representatives.
const CACHE_VERSION: u32 = 2;
const CACHE_MAGIC: &[u8; 8] = b"CAOXRLH\x01";

/// What a clustering depends on: the volume's shades and geometry, and the parameters.
pub fn cache_key(
    dims: [usize; 3],
    spacing: [f64; 3],
    shades: &Shades,
    p: &HistParams,
    scalars: Option<&[f32]>,
) -> u64 {
    let mut h = Fnv::new();
    h.bytes(&CACHE_VERSION.to_le_bytes());
    for d in dims {
        h.bytes(&(d as u64).to_le_bytes());
    }
    for s in spacing {
        h.bytes(&s.to_le_bytes());
    }
    h.bytes(&p.radius_mm.to_le_bytes());
    h.bytes(&(p.bins as u64).to_le_bytes());
    h.bytes(&(p.clusters as u64).to_le_bytes());
    h.bytes(&[p.hemispheres as u8]);
    h.bytes(bytemuck::cast_slice(&shades.ids));
    // The hemispheres' split follows the scalars themselves, not only their bins.
    if let Some(s) = scalars {
        h.bytes(bytemuck::cast_slice(s));
    }
    for &(id, k) in &shades.pairs {
        h.bytes(&[id]);
        h.bytes(&k.to_le_bytes());
    }
    h.0
}

/// The default cache folder: `histograms/` in the data cache of [`crate::volume::ct_head`].
pub fn default_cache_dir() -> PathBuf {
    crate::volume::ct_head::cache_dir().join("histograms")
}

pub fn cache_path(dir: &Path, key: u64) -> PathBuf {
    dir.join(format!("{key:016x}.lh"))
}

/// Reads a cached clustering of histograms of `bins` entries (the shades); None (so it is
/// rebuilt) when the file is missing, is for other data, or is truncated or corrupt in any way.
pub fn load_cache(
    path: &Path,
    key: u64,
    voxels: usize,
    bins: usize,
    p: &HistParams,
) -> Option<Clusters> {
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .ok()?
        .read_to_end(&mut bytes)
        .ok()?;
    let want = 8 + 8 + 12 + voxels * 2 + p.clusters * bins * 4 + 4;
    if bytes.len() != want || &bytes[..8] != CACHE_MAGIC {
        return None;
    }
    let (body, crc) = bytes.split_at(want - 4);
    let mut c = flate2::Crc::new();
    c.update(body);
    if c.sum().to_le_bytes() != crc[..] {
        return None;
    }
    let u64_at = |o: usize| u64::from_le_bytes(body[o..o + 8].try_into().unwrap());
    let u32_at = |o: usize| u32::from_le_bytes(body[o..o + 4].try_into().unwrap()) as usize;
    if u64_at(8) != key || u32_at(16) != voxels || u32_at(20) != bins || u32_at(24) != p.clusters {
        return None;
    }
    let ids_at = 28;
    let reps_at = ids_at + voxels * 2;
    let ids: Vec<u32> = body[ids_at..reps_at]
        .chunks_exact(2)
        .map(|b| u16::from_le_bytes([b[0], b[1]]) as u32)
        .collect();
    if ids.iter().any(|&i| i as usize >= p.clusters) {
        return None;
    }
    let reps = body[reps_at..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    Some(Clusters { bins, ids, reps })
}

/// Writes the cache beside its final name, then renames it, so a crash leaves no partial file
/// under the name [`load_cache`] reads.
pub fn save_cache(path: &Path, key: u64, c: &Clusters) -> std::io::Result<()> {
    let mut body = Vec::with_capacity(28 + c.ids.len() * 2 + c.reps.len() * 4 + 4);
    body.extend_from_slice(CACHE_MAGIC);
    body.extend_from_slice(&key.to_le_bytes());
    for x in [c.ids.len(), c.bins, c.count()] {
        body.extend_from_slice(&(x as u32).to_le_bytes());
    }
    for &id in &c.ids {
        body.extend_from_slice(&(id as u16).to_le_bytes());
    }
    for &r in &c.reps {
        body.extend_from_slice(&r.to_le_bytes());
    }
    let mut crc = flate2::Crc::new();
    crc.update(&body);
    body.extend_from_slice(&crc.sum().to_le_bytes());
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = path.with_extension(format!("lh.tmp{}-{n}", std::process::id()));
    let result = std::fs::File::create(&tmp)
        .and_then(|mut f| f.write_all(&body).and_then(|_| f.sync_all()))
        .and_then(|_| std::fs::rename(&tmp, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_neighbourhood_is_the_ball_without_its_centre_weighted_by_inverse_square_distance() {
        let nb = Neighbourhood::new(2.0, [1.0, 1.0, 2.0]);
        assert!(!nb.offsets.contains(&[0, 0, 0]));
        assert!(nb.offsets.contains(&[2, 0, 0]) && nb.offsets.contains(&[0, 0, 1]));
        assert!(!nb.offsets.contains(&[2, 0, 1]) && !nb.offsets.contains(&[0, 0, 2]));
        let w = |o: [i32; 3]| nb.weights[nb.offsets.iter().position(|x| *x == o).unwrap()];
        assert_eq!(w([1, 0, 0]), 1.0);
        assert_eq!(w([2, 0, 0]), 0.25);
        assert_eq!(w([0, 0, 1]), 0.25);
        assert!((nb.total - nb.weights.iter().sum::<f64>()).abs() < 1e-12);
        assert_eq!(nb.reach_mm([1.0, 1.0, 2.0]), 2.0);
    }

    #[test]
    fn packing_merges_the_smallest_bins_into_their_neighbours_and_keeps_mass() {
        // Global histogram: bin 1 is the rarest, then bin 3.
        let ids = [0, 0, 0, 1, 2, 2, 2, 2, 3, 3, 4, 4, 4];
        let p = Packing::new(&ids, 5, 3);
        assert_eq!(p.packed, 3);
        // Bin 1 went half to 0 and half to 2; then bin 3 (mass 2) half to 2 and half to 4.
        let lh = [0.0, 1.0, 0.0, 0.0, 0.0];
        assert_eq!(p.pack(&lh), [0.5, 0.5, 0.0]);
        let lh = [0.0, 0.0, 0.0, 1.0, 0.0];
        assert_eq!(p.pack(&lh), [0.0, 0.5, 0.5]);
        // Every original bin's shares add up to 1.
        for k in 0..5 {
            let s: f32 = p.matrix[k * 3..k * 3 + 3].iter().sum();
            assert!((s - 1.0).abs() < 1e-6, "bin {k}: {s}");
        }
        // Nothing to pack: the identity.
        let id = Packing::new(&ids, 5, 8);
        assert_eq!(id.packed, 5);
        assert_eq!(
            id.pack(&[0.1, 0.2, 0.3, 0.4, 0.5]),
            [0.1, 0.2, 0.3, 0.4, 0.5]
        );
    }

    /// A 12^3 volume of 1 mm voxels, `material(z)` giving each slice's value (0 or 1000, u16),
    /// with q = 1 where it is 1000: the hemispheres' openness (H_f) and the sphere's at (6, 6, z).
    fn hemisphere_case(material: impl Fn(usize) -> bool, z: usize) -> (f32, f32) {
        use crate::volume::{Modality, Voxels};
        let d = [12usize; 3];
        let on = |i: usize| material(i / (d[0] * d[1]));
        let n = d[0] * d[1] * d[2];
        let vol = Volume {
            whole_range: None,
            name: "hemispheres".into(),
            dims: d,
            spacing: [1.0; 3],
            directions: glam::DMat3::IDENTITY,
            origin: glam::DVec3::ZERO,
            modality: Modality::Unknown,
            voxels: Voxels::U16((0..n).map(|i| if on(i) { 1000 } else { 0 }).collect()),
            labels: None,
        };
        let q: Vec<f32> = (0..n).map(|i| on(i) as u8 as f32).collect();
        let (shades, table) = (vec![0; n], [[1.0; 4]]);
        let nb = Neighbourhood::new(3.0, vol.spacing);
        let splits = splits(&vol);
        let i = 6 + d[0] * (6 + d[1] * z);
        let front = direct_at(d, &q, &shades, &table, &nb, splits[i], i).0;
        let sphere = direct_at(d, &q, &shades, &table, &nb, None, i).0;
        (front, sphere)
    }

    #[test]
    fn the_front_hemisphere_faces_away_from_the_material() {
        // A half-space of material from z = 6: just outside it, H_f holds none of it (open),
        // though half the sphere is material; on its surface H_f holds the surface's own plane.
        let (front, sphere) = hemisphere_case(|z| z >= 6, 5);
        assert_eq!(front, 1.0);
        assert!(sphere < 0.75, "sphere {sphere}");
        let (front, sphere) = hemisphere_case(|z| z >= 6, 6);
        assert!(
            front > sphere && front < 1.0,
            "front {front}, sphere {sphere}"
        );
        // A plate one voxel thick at z = 6: open on both sides; inside it the gradient is zero
        // (flat), so the sphere is kept.
        for z in [5, 7] {
            let (front, sphere) = hemisphere_case(|z| z == 6, z);
            assert_eq!(front, 1.0, "z {z}");
            assert!(sphere < 1.0);
        }
        let (front, sphere) = hemisphere_case(|z| z == 6, 6);
        assert_eq!(front, sphere);
        assert!(front < 1.0);
        // A homogeneous block: no split anywhere.
        let (front, sphere) = hemisphere_case(|_| true, 6);
        assert_eq!(front, sphere);
    }

    #[test]
    fn a_labelled_voxel_s_shade_is_its_structure_and_bin_and_takes_the_structure_s_look() {
        use crate::volume::labels::{LabelMap, Structure};
        let structure = |colour, opacity| Structure {
            value: 1,
            name: "s".into(),
            colour,
            opacity,
            protected: false,
            margin_mm: None,
            voxels: 0,
        };
        let labels = LabelMap {
            source: "test".into(),
            ids: vec![0, 2, 2, 1, 0, 2],
            structures: vec![
                structure([0.0, 1.0, 0.0], 0.5),
                structure([0.0, 0.0, 1.0], 1.0),
            ],
        };
        let bins = vec![1, 1, 2, 1, 2, 1];
        let s = Shades::new(bins.clone(), 3, Some(&labels));
        // The three bins, then the pairs the volume holds in (id, bin) order.
        assert_eq!(s.pairs, [(0, 0), (0, 1), (0, 2), (1, 1), (2, 1), (2, 2)]);
        assert_eq!(s.ids, [1, 4, 5, 3, 2, 4]);
        let tf = [
            [1.0, 0.0, 0.0, 0.1],
            [1.0, 0.0, 0.0, 0.2],
            [1.0, 0.0, 0.0, 0.4],
        ];
        let t = s.table(&tf, Some(&labels), &[]);
        assert_eq!(t[..3], tf);
        assert_eq!(t[3], [0.0, 1.0, 0.0, 0.2 * 0.5]);
        assert_eq!(t[5], [0.0, 0.0, 1.0, 0.4]);
        // Hidden: the structure's shades are transparent, the rest as before.
        let hidden = s.table(&tf, Some(&labels), &[1.0, 0.0]);
        assert_eq!(s.q(&hidden), [0.2, 0.0, 0.0, 0.2, 0.4, 0.0]);
        // Without labels the shades are the bins.
        let plain = Shades::new(bins.clone(), 3, None);
        assert_eq!((plain.count(), plain.ids), (3, bins));
    }

    #[test]
    fn lbg_finds_well_separated_clusters_and_gives_n_centroids() {
        // Four tight groups in 2-D.
        let centres = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]];
        let mut rng = SplitMix64(3);
        let mut samples = Vec::new();
        for i in 0..400 {
            let c = centres[i % 4];
            samples.push(c[0] + 0.01 * rng.range(-1.0, 1.0) as f32);
            samples.push(c[1] + 0.01 * rng.range(-1.0, 1.0) as f32);
        }
        let cen = lbg(&samples, 2, 4);
        assert_eq!(cen.len(), 8);
        for c in centres {
            let (_, d) = nearest(&cen, 2, &[c[0], c[1]]);
            assert!(d < 1e-3, "no centroid near {c:?}: {cen:?}");
        }
        // More clusters than distinct samples: still n centroids, deterministic.
        let same = vec![0.5f32; 20];
        let a = lbg(&same, 2, 7);
        assert_eq!(a.len(), 14);
        assert_eq!(a, lbg(&same, 2, 7));
    }

    #[test]
    fn the_two_level_assignment_mostly_finds_the_nearest_centroid() {
        let mut rng = SplitMix64(5);
        let dim = 4;
        let samples: Vec<f32> = (0..4000 * dim).map(|_| rng.unit() as f32).collect();
        let cen = lbg(&samples, dim, 256);
        let groups = Groups::new(&cen, dim);
        assert_eq!(groups.members.len(), 256);
        assert_eq!(*groups.first.last().unwrap(), 256);
        let mut seen = groups.members.clone();
        seen.sort();
        assert!(
            seen.iter().enumerate().all(|(i, &c)| c == i as u32),
            "each centroid once"
        );
        let same = samples
            .chunks_exact(dim)
            .filter(|s| groups.assign(&cen, dim, s) == nearest(&cen, dim, s).0)
            .count();
        assert!(same as f64 >= 0.95 * 4000.0, "{same} of 4000 exact");
    }

    #[test]
    fn a_clear_brick_is_one_no_voxel_of_which_reaches_an_opaque_one() {
        // Three grids (edge bricks partial), sparse opaque voxels, per-axis reaches; checked
        // against every voxel's box of reach, brute force, and the bits beyond the bricks 0.
        for (dims, reach, every) in [
            ([19, 13, 11], [3, 2, 1], 1303),
            ([40, 9, 17], [9, 0, 4], 331),
            ([30, 30, 30], [2, 2, 2], 2003),
        ] {
            let n = dims[0] * dims[1] * dims[2];
            let q: Vec<f32> = (0..n)
                .map(|i| if (i * 7919) % every == 3 { 0.5 } else { 0.0 })
                .collect();
            let bits = clear_bricks(dims, &q, reach);
            let side = 1usize << HIST_BRICK_SHIFT;
            let bd = dims.map(|d| d.div_ceil(side));
            let bricks = bd[0] * bd[1] * bd[2];
            let (mut clear, mut occupied) = (0, 0);
            for b in 0..bricks {
                let c = [b % bd[0], (b / bd[0]) % bd[1], b / (bd[0] * bd[1])];
                let reaches = (0..n).filter(|&j| q[j] > 0.0).any(|j| {
                    let u = [
                        j % dims[0],
                        (j / dims[0]) % dims[1],
                        j / (dims[0] * dims[1]),
                    ];
                    (0..3).all(|a| {
                        let (lo, hi) = (c[a] * side, ((c[a] + 1) * side).min(dims[a]) - 1);
                        u[a] + reach[a] >= lo && u[a] <= hi + reach[a]
                    })
                });
                let bit = bits[b / 32] >> (b % 32) & 1 == 1;
                assert_eq!(bit, !reaches, "{dims:?} brick {c:?}");
                (clear, occupied) = (clear + bit as usize, occupied + !bit as usize);
            }
            assert!(bricks % 32 == 0 || bits[bricks / 32] >> (bricks % 32) == 0);
            assert!(clear > 0, "{dims:?}: no brick clear");
            assert!(occupied > 0, "{dims:?}: every brick clear");
        }
    }

    #[test]
    fn the_tf_table_is_the_dot_product_with_the_bins_opacity_and_colour() {
        let c = Clusters {
            bins: 2,
            ids: vec![0, 1],
            reps: vec![0.5, 0.25, 0.0, 0.0],
        };
        let table = [[1.0, 0.0, 0.0, 0.4], [0.0, 1.0, 0.0, 0.8]];
        let t = c.tf_table(&table);
        // O_env = 0.5 * 0.4 + 0.25 * 0.8 = 0.4; E = (0.2 red + 0.2 green) / 0.4.
        assert!((t[0][3] - 0.6).abs() < 1e-6);
        assert!((t[0][0] - 0.5).abs() < 1e-6 && (t[0][1] - 0.5).abs() < 1e-6);
        assert_eq!(t[1], [0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn the_cache_round_trips_and_a_damaged_or_foreign_file_is_not_trusted() {
        let p = HistParams {
            radius_mm: 3.0,
            bins: 4,
            clusters: 3,
            ..Default::default()
        };
        let c = Clusters {
            bins: 4,
            ids: vec![0, 2, 1, 1, 0],
            reps: (0..12).map(|x| x as f32 / 12.0).collect(),
        };
        let dir = std::env::temp_dir().join(format!("cao-lh-cache-{}", std::process::id()));
        let path = cache_path(&dir, 42);
        save_cache(&path, 42, &c).unwrap();
        assert_eq!(load_cache(&path, 42, 5, 4, &p), Some(c.clone()));
        assert_eq!(load_cache(&path, 43, 5, 4, &p), None, "another key");
        assert_eq!(load_cache(&path, 42, 6, 4, &p), None, "another volume");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 7]).unwrap();
        assert_eq!(load_cache(&path, 42, 5, 4, &p), None, "truncated");
        let mut flipped = bytes.clone();
        flipped[40] ^= 1;
        std::fs::write(&path, &flipped).unwrap();
        assert_eq!(load_cache(&path, 42, 5, 4, &p), None, "corrupt");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
