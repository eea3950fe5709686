//! Spherical-harmonic visibility volumes (Ritschel 2007): every SH voxel stores its visibility
//! V(x, w) projected on SH bands 0-1 (4 coefficients) or 0-3 (16), so the renderer lights the
//! volume by an environment with a dot product per sample.
//!
//! Exactly what is computed, so the GPU, the CPU reference and the clip-aware update agree:
//! - SH voxel I (dims = ceil(volume dims / downsample)) sits at full-resolution index point
//!   x = (I + 0.5) * dims_full / dims_sh, so it lines up with texture sampling.
//! - Pyramid: level 0 is the opacity of crossing one voxel, 1 - (1 - O)^(h0 / 1 mm), with h0 the
//!   geometric mean of the spacings; level l+1 cell = 1 - mean over the 12 face-adjacent pairs
//!   (a, b) of its 8 children of T_a * T_b (T = 1 - opacity; children outside the grid have T = 1).
//!   This is the paper's product minification: a ray through the coarse cell crosses two
//!   successive fine cells, and a box filter would let an opaque wall leak.
//! - March: from x along w, steps of h = h0 * 2^l at level l, `steps_per_level` steps per level
//!   before doubling, up to the top level, until t > `length_mm`; sample = trilinear opacity of
//!   level l at the step's end point (zero outside); transmittance *= 1 - sample; stop below
//!   1/1024. With `hierarchy` off every step is h0 on level 0 (the reference the approximation is
//!   measured against).
//! - Projection: V_k = (1/N) sum_i V(x, w_i) Y_k(w_i) over the N directions of the voxel's
//!   pattern (one of M jittered patterns, chosen by hashing the voxel index). |V_k| <= Y_0, so a
//!   coefficient is stored as snorm8 of V_k / Y_0: byte = round(clamp(V_k / Y_0, -1, 1) * 127),
//!   which keeps 0 and Y_0 (empty space) exact. Four coefficients per RGBA8_SNORM 3D texture.
//! - Directions w live in the volume's mm frame (along its i, j, k axes); the renderer projects
//!   the environment into that frame ([`crate::light`]).

use super::cao::Cao;
use super::voxel_box::VoxelBox;
use crate::gpu::{
    Buffer, ComputePipeline, Gpu, GpuError, GpuTimer, Image, ImageDesc, Reach, Result,
    MAX_FRAMES_IN_FLIGHT,
};
use crate::light::sh::eval;
use crate::volume::Volume;
use ash::vk;
use glam::DVec3;
use gpu_allocator::MemoryLocation;
use rayon::prelude::*;

pub use crate::light::sh::Y0;
use crate::rng::SplitMix64;
/// Marches stop once the transmittance falls below this.
pub use crate::shader_constants::SH_T_MIN as T_MIN;

/// How the SH visibility volume is computed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShParams {
    /// 4 (bands 0-1) or 16 (bands 0-3).
    pub coeffs: u32,
    /// Directions per voxel (N).
    pub directions: u32,
    /// Jittered direction patterns (M); each voxel uses one.
    pub patterns: u32,
    /// SH voxels are this many volume voxels along each axis (1:1, 1:2, 1:4, 1:8).
    pub downsample: u32,
    /// How far a visibility ray reaches (mm).
    pub length_mm: f32,
    /// March the expected-opacity pyramid with growing steps (else level 0 at the base step).
    pub hierarchy: bool,
    pub steps_per_level: u32,
    pub seed: u64,
}

impl Default for ShParams {
    fn default() -> Self {
        ShParams {
            coeffs: 16,
            directions: 128,
            patterns: 32,
            downsample: 4,
            length_mm: 60.0,
            hierarchy: true,
            steps_per_level: 4,
            seed: 1,
        }
    }
}

impl ShParams {
    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.coeffs != 4 && self.coeffs != 16 {
            return Err(format!(
                "SH coefficients must be 4 or 16, not {}",
                self.coeffs
            ));
        }
        if !(1..=4096).contains(&self.directions) {
            return Err(format!(
                "SH directions must be 1..4096, not {}",
                self.directions
            ));
        }
        if !(1..=256).contains(&self.patterns) {
            return Err(format!("SH patterns must be 1..256, not {}", self.patterns));
        }
        if !(1..=16).contains(&self.downsample) {
            return Err(format!(
                "SH downsampling must be 1..16, not {}",
                self.downsample
            ));
        }
        if !(self.length_mm > 0.0 && self.length_mm <= 2000.0) {
            return Err(format!(
                "SH ray length must be in (0, 2000] mm, not {}",
                self.length_mm
            ));
        }
        if !(1..=64).contains(&self.steps_per_level) {
            return Err(format!(
                "SH steps per level must be 1..64, not {}",
                self.steps_per_level
            ));
        }
        Ok(())
    }
    fn groups(&self) -> usize {
        self.coeffs as usize / 4
    }
}

/// The SH grid and pyramid geometry of one volume.
#[derive(Clone, Debug, PartialEq)]
pub struct ShGrid {
    pub full: [usize; 3],
    pub spacing: [f64; 3],
    pub dims: [usize; 3],
    /// h0: the base step and level-0 cell crossing (mm).
    pub h0: f64,
    /// Pyramid level dims, level 0 = full resolution.
    pub levels: Vec<[usize; 3]>,
    /// The highest level a march uses.
    pub top: usize,
}

impl ShGrid {
    pub fn new(full: [usize; 3], spacing: [f64; 3], p: &ShParams) -> ShGrid {
        let dims = full.map(|d| d.div_ceil(p.downsample as usize).max(1));
        let h0 = (spacing[0] * spacing[1] * spacing[2]).cbrt();
        // The lowest top level whose steps reach the ray length (S h0 (2^(L+1) - 1) >= length),
        // at most 7 and not beyond a 1-voxel level.
        let mut top = 0;
        if p.hierarchy {
            let reach = |l: usize| p.steps_per_level as f64 * h0 * ((2u64 << l) - 1) as f64;
            while top < 7 && reach(top) < p.length_mm as f64 && full.iter().any(|&d| d > 1 << top) {
                top += 1;
            }
        }
        let mut levels = vec![full];
        for _ in 0..top {
            let l = *levels.last().unwrap();
            levels.push(l.map(|d| d.div_ceil(2)));
        }
        ShGrid {
            full,
            spacing,
            dims,
            h0,
            levels,
            top,
        }
    }
    pub fn count(&self) -> usize {
        self.dims.iter().product()
    }
    /// Full-resolution voxels per SH voxel, per axis.
    pub fn scale(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| self.full[a] as f64 / self.dims[a] as f64)
    }
    fn offsets(&self) -> Vec<usize> {
        let mut off = vec![0];
        for l in &self.levels {
            off.push(off.last().unwrap() + l.iter().product::<usize>());
        }
        off
    }
    /// The SH box covering every SH voxel whose centre lies in a full-resolution voxel box.
    pub fn sh_box(&self, b: &VoxelBox) -> VoxelBox {
        let s = self.scale();
        VoxelBox {
            min: [0, 1, 2].map(|a| ((b.min[a] as f64 / s[a]).floor() as i32).max(0)),
            max: [0, 1, 2]
                .map(|a| ((b.max[a] as f64 / s[a]).ceil() as i32).min(self.dims[a] as i32)),
        }
    }
    /// The distance (mm) within which a change of the opacity can change an SH voxel's value:
    /// the ray length, the trilinear footprint of the top level's cells (1.5 cells per axis),
    /// and the anti-aliasing spread of a clipped voxel (a voxel diagonal), plus 1 %. Tested at
    /// the SH voxel's centre, where its rays start.
    pub fn radius_mm(&self, p: &ShParams) -> f64 {
        let s = self.spacing.iter().cloned().fold(0.0, f64::max);
        let diag = 3f64.sqrt() * s;
        (p.length_mm as f64 + 1.5 * diag * (1u64 << self.top) as f64 + diag) * 1.01
    }
}

/// M patterns of N unit directions (mm frame), pattern-major: the upper half of a spherical
/// Fibonacci set of N points with each direction jittered within its stratum (z in its band of
/// height 2/N, the azimuth by about one point spacing), then the antipodes of those points; each
/// pattern is rotated about z by a random angle.
pub fn patterns(p: &ShParams) -> Vec<DVec3> {
    let n = p.directions as usize;
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut rng = SplitMix64(p.seed);
    let mut out = Vec::with_capacity(n * p.patterns as usize);
    for _ in 0..p.patterns {
        let spin = rng.unit() * std::f64::consts::TAU;
        let start = out.len();
        for j in 0..n.div_ceil(2) {
            let z = 1.0 - 2.0 * (j as f64 + rng.unit()) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            // Azimuthal jitter of about one point spacing (sqrt(4 pi / N) on the sphere).
            let spread = ((4.0 * std::f64::consts::PI / n as f64).sqrt() / r.max(1e-3)).min(1.0);
            let phi = spin + golden * j as f64 + spread * (rng.unit() - 0.5);
            out.push(DVec3::new(r * phi.cos(), r * phi.sin(), z));
        }
        // The other half antipodal: the odd bands of a constant visibility cancel exactly.
        for j in 0..n / 2 {
            out.push(-out[start + j]);
        }
    }
    out
}

/// lowbias32 (Wellons): the pattern an SH voxel uses; shaders/sh.comp has its twin.
pub fn pattern_of(i: u32, patterns: u32) -> u32 {
    let mut x = i;
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x % patterns
}

/// The pyramid on the host (f64), level 0 first.
pub fn pyramid(opacity: &[f32], grid: &ShGrid) -> Vec<Vec<f64>> {
    let e = grid.h0;
    let mut levels = vec![opacity
        .iter()
        .map(|&o| {
            let o = o as f64;
            if o <= 0.0 {
                0.0
            } else if o >= 1.0 {
                1.0
            } else {
                1.0 - (1.0 - o).powf(e)
            }
        })
        .collect::<Vec<f64>>()];
    for l in 1..grid.levels.len() {
        let (src, sd, dd) = (&levels[l - 1], grid.levels[l - 1], grid.levels[l]);
        let mut dst = vec![0.0; dd.iter().product()];
        for (idx, out) in dst.iter_mut().enumerate() {
            let v = [idx % dd[0], (idx / dd[0]) % dd[1], idx / (dd[0] * dd[1])];
            let t = |c: usize| {
                let q = [0, 1, 2].map(|a| 2 * v[a] + ((c >> a) & 1));
                if (0..3).any(|a| q[a] >= sd[a]) {
                    1.0
                } else {
                    1.0 - src[q[0] + sd[0] * (q[1] + sd[1] * q[2])]
                }
            };
            let t: [f64; 8] = std::array::from_fn(t);
            let s = (t[0] * t[1] + t[2] * t[3] + t[4] * t[5] + t[6] * t[7])
                + (t[0] * t[2] + t[1] * t[3] + t[4] * t[6] + t[5] * t[7])
                + (t[0] * t[4] + t[1] * t[5] + t[2] * t[6] + t[3] * t[7]);
            *out = 1.0 - s / 12.0;
        }
        levels.push(dst);
    }
    levels
}

fn sample_level(pyr: &[Vec<f64>], grid: &ShGrid, level: usize, p: DVec3) -> f64 {
    let d = grid.levels[level];
    let c = p / (1u64 << level) as f64 - DVec3::splat(0.5);
    let fl = c.floor();
    let f = c - fl;
    let cell = |dx: i64, dy: i64, dz: i64| {
        let q = [fl.x as i64 + dx, fl.y as i64 + dy, fl.z as i64 + dz];
        if (0..3).any(|a| q[a] < 0 || q[a] >= d[a] as i64) {
            0.0
        } else {
            pyr[level][q[0] as usize + d[0] * (q[1] as usize + d[1] * q[2] as usize)]
        }
    };
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = lerp(cell(0, 0, 0), cell(1, 0, 0), f.x);
    let x10 = lerp(cell(0, 1, 0), cell(1, 1, 0), f.x);
    let x01 = lerp(cell(0, 0, 1), cell(1, 0, 1), f.x);
    let x11 = lerp(cell(0, 1, 1), cell(1, 1, 1), f.x);
    lerp(lerp(x00, x10, f.y), lerp(x01, x11, f.y), f.z)
}

/// Transmittance from full-resolution index point `x` along `dir` (index units per mm).
fn visibility(pyr: &[Vec<f64>], grid: &ShGrid, p: &ShParams, x: DVec3, dir: DVec3) -> f64 {
    let (mut h, mut level, mut n, mut t, mut trans) = (grid.h0, 0usize, 0u32, 0.0, 1.0);
    let pad = (1u64 << grid.top) as f64;
    let hi = DVec3::new(
        grid.full[0] as f64,
        grid.full[1] as f64,
        grid.full[2] as f64,
    ) + pad;
    for _ in 0..4096 {
        if p.hierarchy && n == p.steps_per_level && level < grid.top {
            level += 1;
            h *= 2.0;
            n = 0;
        }
        t += h;
        if t > p.length_mm as f64 {
            break;
        }
        n += 1;
        let q = x + t * dir;
        if q.cmplt(DVec3::splat(-pad)).any() || q.cmpgt(hi).any() {
            break;
        }
        trans *= 1.0 - sample_level(pyr, grid, level, q);
        if trans < T_MIN {
            break;
        }
    }
    trans
}

/// Per-direction index-space steps (per mm) of `dirs` for a volume's spacing.
fn index_dirs(dirs: &[DVec3], spacing: [f64; 3]) -> Vec<DVec3> {
    let s = DVec3::from(spacing);
    dirs.iter().map(|d| *d / s).collect()
}

/// CPU reference: the unquantised coefficients of every SH voxel of `opacity`.
pub fn cpu_reference(
    opacity: &[f32],
    full: [usize; 3],
    spacing: [f64; 3],
    p: &ShParams,
) -> Vec<[f64; 16]> {
    let grid = ShGrid::new(full, spacing, p);
    let pyr = pyramid(opacity, &grid);
    let dirs = patterns(p);
    let steps = index_dirs(&dirs, spacing);
    let basis: Vec<[f64; 16]> = dirs.iter().map(|d| eval(*d)).collect();
    let n = p.directions as usize;
    let s = grid.scale();
    let d = grid.dims;
    (0..grid.count())
        .into_par_iter()
        .map(|i| {
            let v = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
            let x = DVec3::new(
                (v[0] as f64 + 0.5) * s[0],
                (v[1] as f64 + 0.5) * s[1],
                (v[2] as f64 + 0.5) * s[2],
            );
            let first = pattern_of(i as u32, p.patterns) as usize * n;
            let mut acc = [0.0; 16];
            for k in first..first + n {
                let vis = visibility(&pyr, &grid, p, x, steps[k]);
                for (a, y) in acc.iter_mut().zip(&basis[k]).take(p.coeffs as usize) {
                    *a += vis * y;
                }
            }
            acc.map(|a| a / n as f64)
        })
        .collect()
}

/// snorm8 of V_k / Y_0 (see the module doc).
pub fn quantize(v: f64) -> i8 {
    ((v / Y0).clamp(-1.0, 1.0) * 127.0).round() as i8
}

pub fn dequantize(b: i8) -> f64 {
    (b as f64 / 127.0).max(-1.0) * Y0
}

/// Coefficient `k` of SH voxel `i` in a packed read-back ([`ShVolume::read_back`]).
pub fn packed_coeff(packed: &[u32], count: usize, i: usize, k: usize) -> f64 {
    let word = packed[(k / 4) * count + i];
    dequantize((word >> (8 * (k % 4))) as u8 as i8)
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PyramidPush {
    src_dims: [i32; 4],
    dst_dims: [i32; 4],
    exponent: f32,
    level0: u32,
    pad: [u32; 2],
    stride: [i32; 4],
}
crate::gpu::glsl_layout!(PyramidPush, 64,
    src_dims: 0, dst_dims: 16, exponent: 32, level0: 36, stride: 48);

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ShPush {
    dims: [i32; 4],
    box_min: [i32; 4],
    box_max: [i32; 4],
    scale: [f32; 4],
    march: [u32; 4],
    extent: [f32; 4],
}
crate::gpu::glsl_layout!(ShPush, 96,
    dims: 0, box_min: 16, box_max: 32, scale: 48, march: 64, extent: 80);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Pass {
    Compute = 0,
    ClipAware = 1,
    Restore = 2,
}

/// What a precompute took.
#[derive(Clone, Debug, Default)]
pub struct ShTiming {
    pub gpu_ms: f64,
    pub wall_ms: f64,
}

/// What one frame's SH update did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ShFrameMetrics {
    /// SH voxels the update pass visited (the tools' SH boxes).
    pub visited: u64,
    /// Whether the frame had any SH work (a tool now or in the frame before).
    pub updated: bool,
    /// The timer that measured it (one per frame in flight).
    timer: usize,
}

/// The SH visibility volume on the GPU: the precomputed V_PSH, this frame's V_SH (packed snorm8)
/// and the 3D textures every view samples.
pub struct ShVolume {
    gpu: Gpu,
    pyramid_pass: ComputePipeline,
    sh_pass: ComputePipeline,
    pub params: ShParams,
    pub grid: ShGrid,
    pyramid: Buffer,
    levels: Buffer,
    dirs: Buffer,
    basis: Buffer,
    pre: Buffer,
    cur: Buffer,
    /// RGBA8_SNORM 3D textures, coefficients 4g..4g+3 in texture g.
    pub images: Vec<Image>,
    prev_boxes: Vec<VoxelBox>,
    /// One per frame in flight; [`ShVolume::record_frame`] takes the next.
    timers: Vec<GpuTimer>,
    timer: usize,
}

impl ShVolume {
    /// Allocates the SH volume of `vol`'s geometry (nothing computed yet: all zero).
    pub fn new(gpu: &Gpu, vol: &Volume, params: ShParams) -> Result<ShVolume> {
        params.validate().map_err(GpuError::Other)?;
        let grid = ShGrid::new(vol.dims, vol.spacing, &params);
        let pyramid_pass = ComputePipeline::with_addresses(
            gpu,
            include_bytes!(concat!(env!("OUT_DIR"), "/sh_pyramid.comp.spv")),
            &[Reach::Address; 3],
            std::mem::size_of::<PyramidPush>() as u32,
            &[],
        )?;
        let sh_pass = ComputePipeline::with_addresses(
            gpu,
            include_bytes!(concat!(env!("OUT_DIR"), "/sh.comp.spv")),
            &[
                Reach::Address,
                Reach::Descriptor,
                Reach::Descriptor,
                Reach::Descriptor,
                Reach::Address,
                Reach::Address,
                Reach::Descriptor,
                Reach::Descriptor,
            ],
            std::mem::size_of::<ShPush>() as u32,
            &[],
        )?;
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER
            | vk::BufferUsageFlags::TRANSFER_SRC
            | vk::BufferUsageFlags::TRANSFER_DST;
        let offsets = grid.offsets();
        let pyramid = Buffer::new(
            gpu,
            (*offsets.last().unwrap() * 4) as u64,
            storage,
            MemoryLocation::GpuOnly,
            "sh-pyramid",
        )?;
        let level_info: Vec<[i32; 4]> = grid
            .levels
            .iter()
            .zip(&offsets)
            .map(|(d, o)| [d[0] as i32, d[1] as i32, d[2] as i32, *o as i32])
            .collect();
        let levels = Buffer::from_slice(gpu, &level_info, b_usage(), "sh-levels")?;
        let dirs_mm = patterns(&params);
        let dirs: Vec<[f32; 4]> = index_dirs(&dirs_mm, vol.spacing)
            .iter()
            .map(|d| [d.x as f32, d.y as f32, d.z as f32, 0.0])
            .collect();
        let dirs = Buffer::from_slice(gpu, &dirs, b_usage(), "sh-dirs")?;
        let basis: Vec<f32> = dirs_mm
            .iter()
            .flat_map(|d| eval(*d).map(|y| y as f32))
            .collect();
        let basis = Buffer::from_slice(gpu, &basis, b_usage(), "sh-basis")?;
        let bytes = (grid.count() * params.groups() * 4) as u64;
        let dev = |name| Buffer::new(gpu, bytes, storage, MemoryLocation::GpuOnly, name);
        let (pre, cur) = (dev("sh-pre")?, dev("sh-cur")?);
        let max = gpu.limits.max_image_dimension3_d as usize;
        if grid.dims.iter().any(|&d| d > max) {
            return Err(GpuError::Other(format!(
                "SH volume {:?} exceeds the device's 3D image limit of {max} per axis",
                grid.dims
            )));
        }
        let images = (0..params.groups())
            .map(|g| {
                Image::new(
                    gpu,
                    ImageDesc {
                        image_type: vk::ImageType::TYPE_3D,
                        view_type: vk::ImageViewType::TYPE_3D,
                        format: vk::Format::R8G8B8A8_SNORM,
                        extent: vk::Extent3D {
                            width: grid.dims[0] as u32,
                            height: grid.dims[1] as u32,
                            depth: grid.dims[2] as u32,
                        },
                        layers: 1,
                        usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                        aspect: vk::ImageAspectFlags::COLOR,
                    },
                    &format!("sh-{g}"),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let sh = ShVolume {
            gpu: gpu.clone(),
            pyramid_pass,
            sh_pass,
            params,
            grid,
            pyramid,
            levels,
            dirs,
            basis,
            pre,
            cur,
            images,
            prev_boxes: Vec::new(),
            timers: (0..MAX_FRAMES_IN_FLIGHT)
                .map(|_| GpuTimer::new(gpu, 8))
                .collect::<Result<_>>()?,
            timer: 0,
        };
        sh.gpu.submit_and_wait(|cmd| {
            for img in &sh.images {
                img.transition(
                    cmd,
                    vk::ImageLayout::UNDEFINED,
                    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                );
            }
        })?;
        Ok(sh)
    }

    /// Records the whole pyramid of `opacity` (O or O_c at full resolution), whose voxel v lies
    /// at `stride`\[0] + v.x + `stride`\[1] v.y + `stride`\[2] v.z; `stride`\[3] 1: f32, 0: 16-bit
    /// ([`Cao::clipped_stride`]).
    pub fn record_pyramid(&self, cmd: vk::CommandBuffer, opacity: &Buffer, stride: [i32; 4]) {
        let offsets = self.grid.offsets();
        let dims4 = |l: usize| {
            let d = self.grid.levels[l];
            [d[0] as i32, d[1] as i32, d[2] as i32, offsets[l] as i32]
        };
        for l in 0..self.grid.levels.len() {
            let push = PyramidPush {
                src_dims: dims4(l.saturating_sub(1)),
                dst_dims: dims4(l),
                exponent: self.grid.h0 as f32,
                level0: (l == 0) as u32,
                pad: [0; 2],
                stride,
            };
            self.pyramid_pass.bind(
                cmd,
                &[opacity, &self.pyramid, opacity],
                bytemuck::bytes_of(&push),
            );
            let d = self.grid.levels[l];
            self.pyramid_pass
                .dispatch(cmd, d.map(|n| n.div_ceil(4) as u32));
            self.gpu.barrier(cmd);
        }
    }

    fn record_pass(
        &self,
        cmd: vk::CommandBuffer,
        b: &VoxelBox,
        pass: Pass,
        clip: (&Buffer, &Buffer, u32),
        out: &Buffer,
    ) {
        let (g, p, s) = (&self.grid, &self.params, self.grid.scale());
        let push = ShPush {
            dims: [
                g.dims[0] as i32,
                g.dims[1] as i32,
                g.dims[2] as i32,
                p.groups() as i32,
            ],
            box_min: [b.min[0], b.min[1], b.min[2], clip.2 as i32],
            box_max: [b.max[0], b.max[1], b.max[2], pass as i32],
            scale: [s[0] as f32, s[1] as f32, s[2] as f32, g.h0 as f32],
            march: [
                p.directions,
                p.patterns,
                g.top as u32,
                if p.hierarchy { p.steps_per_level } else { 0 },
            ],
            extent: [
                g.full[0] as f32,
                g.full[1] as f32,
                g.full[2] as f32,
                p.length_mm,
            ],
        };
        let bufs = [
            &self.pyramid,
            &self.levels,
            &self.dirs,
            &self.basis,
            &self.pre,
            out,
            clip.0,
            clip.1,
        ];
        self.sh_pass.bind(cmd, &bufs, bytemuck::bytes_of(&push));
        self.sh_pass.dispatch(
            cmd,
            [0, 1, 2].map(|a| ((b.max[a] - b.min[a]).max(0) as u32).div_ceil(4)),
        );
    }

    /// Records a copy of this frame's V_SH into the textures.
    fn record_upload(&self, cmd: vk::CommandBuffer) {
        let n = self.grid.count() as u64 * 4;
        for (g, img) in self.images.iter().enumerate() {
            img.transition(
                cmd,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            );
            img.cmd_copy_from_offset(cmd, &self.cur, g as u64 * n);
            img.transition(
                cmd,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
        }
    }

    /// Opacity samples one SH slice costs (voxels x directions x about 24 samples a ray), the
    /// unit of [`crate::ao::progressive::slab_slices`] budgets.
    pub fn samples_per_slice(&self) -> f64 {
        let d = self.grid.dims;
        (d[0] * d[1]) as f64 * self.params.directions as f64 * 24.0
    }

    /// Records V_PSH of SH slices `z` into the precomputed buffer. [`ShVolume::record_pyramid`]
    /// of the unclipped opacity must have executed first; the textures keep their values until
    /// [`ShVolume::record_publish`].
    pub fn record_precompute_slab(&self, cmd: vk::CommandBuffer, z: std::ops::Range<usize>) {
        let d = self.grid.dims;
        let b = VoxelBox {
            min: [0, 0, z.start as i32],
            max: [d[0] as i32, d[1] as i32, z.end as i32],
        };
        // No tools: the clip bindings are unused stand-ins.
        let clip = (&self.levels, &self.levels, 0);
        self.record_pass(cmd, &b, Pass::Compute, clip, &self.pre);
    }

    /// Records making the precomputed V_PSH the current volume and the textures' content (no
    /// clip boxes to restore afterwards).
    pub fn record_publish(&mut self, cmd: vk::CommandBuffer) {
        self.gpu.barrier(cmd);
        let region = [vk::BufferCopy::default().size(self.pre.size)];
        // SAFETY: `cmd` is recording outside a render pass (this method's contract); `pre` and
        // `cur` are this volume's, the same size, made with TRANSFER_SRC and TRANSFER_DST.
        unsafe {
            self.gpu
                .device
                .cmd_copy_buffer(cmd, self.pre.raw, self.cur.raw, &region)
        };
        self.gpu.barrier(cmd);
        self.record_upload(cmd);
        self.prev_boxes.clear();
    }

    /// Computes V_PSH of the unclipped opacity O in z-slabs (progress in SH slices) and makes it
    /// the current volume.
    /// `opacity` as [`ShVolume::record_pyramid`] takes it.
    pub fn precompute(
        &mut self,
        (opacity, stride): (&Buffer, [i32; 4]),
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<ShTiming> {
        let t0 = std::time::Instant::now();
        let mut timing = ShTiming::default();
        let mut timer = GpuTimer::new(&self.gpu, 2)?;
        self.gpu
            .submit_and_wait(|cmd| self.record_pyramid(cmd, opacity, stride))?;
        let budget = if self.gpu.is_cpu() { 5e7 } else { 2e9 };
        let total = self.grid.dims[2];
        let mut slabs = crate::ao::progressive::SlabScheduler::with_budget(
            total,
            self.samples_per_slice(),
            budget,
        );
        progress(0, total);
        while let Some(z) = slabs.next_slab() {
            self.gpu.submit_and_wait(|cmd| {
                timer.begin(cmd);
                self.record_precompute_slab(cmd, z.clone());
                timer.mark(cmd, "sh");
            })?;
            timing.gpu_ms += timer.read()?.iter().map(|t| t.1).sum::<f64>();
            progress(z.end, total);
        }
        let gpu = self.gpu.clone();
        gpu.submit_and_wait(|cmd| self.record_publish(cmd))?;
        timing.wall_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(timing)
    }

    /// Records this frame's clip-aware SH update after CAO's clip pass (it reads O_c and the
    /// tools' SH dilation maps from `cao`): the previous frame's boxes get V_PSH back, the
    /// tools' SH boxes are recomputed where the SH dilation reaches and copied elsewhere, and
    /// the textures are refreshed. `naive` recomputes every SH voxel on the clipped volume (the
    /// reference the update must equal). Frames with no tool now or before cost nothing.
    pub fn record_frame(
        &mut self,
        cmd: vk::CommandBuffer,
        cao: &Cao,
        naive: bool,
    ) -> ShFrameMetrics {
        let count = cao.tool_count;
        let boxes: Vec<VoxelBox> = if count == 0 {
            Vec::new()
        } else if naive {
            vec![VoxelBox::whole(self.grid.dims)]
        } else {
            cao.sh_boxes
                .iter()
                .map(|b| self.grid.sh_box(b))
                .filter(|b| b.voxels() > 0)
                .collect()
        };
        let restore = std::mem::take(&mut self.prev_boxes);
        if boxes.is_empty() && restore.is_empty() {
            return ShFrameMetrics::default();
        }
        let (tools, maps, _) = cao.clip_buffers();
        self.timer = (self.timer + 1) % self.timers.len();
        self.timers[self.timer].begin(cmd);
        if !boxes.is_empty() {
            self.record_pyramid(cmd, cao.clipped(), cao.clipped_stride());
        }
        for b in &restore {
            self.record_pass(cmd, b, Pass::Restore, (tools, maps, 0), &self.cur);
        }
        self.gpu.barrier(cmd);
        let pass = if naive {
            Pass::Compute
        } else {
            Pass::ClipAware
        };
        for b in &boxes {
            self.record_pass(cmd, b, pass, (tools, maps, count), &self.cur);
        }
        self.gpu.barrier(cmd);
        self.record_upload(cmd);
        self.timers[self.timer].mark(cmd, "sh");
        let visited = boxes.iter().map(|b| b.voxels()).sum();
        self.prev_boxes = boxes;
        ShFrameMetrics {
            visited,
            updated: true,
            timer: self.timer,
        }
    }

    /// GPU milliseconds of a recorded frame's SH work, once it has executed.
    pub fn read_frame_ms(&self, m: &ShFrameMetrics) -> Result<f64> {
        if !m.updated {
            return Ok(0.0);
        }
        Ok(self.timers[m.timer].read()?.iter().map(|t| t.1).sum())
    }

    /// This frame's V_SH, packed: word g * count + i holds coefficients 4g..4g+3 of voxel i.
    pub fn read_back(&self) -> Result<Vec<u32>> {
        Ok(bytemuck::cast_slice(&self.cur.read_back()?).to_vec())
    }
}

fn b_usage() -> vk::BufferUsageFlags {
    vk::BufferUsageFlags::STORAGE_BUFFER
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_is_orthonormal_over_the_patterns() {
        // Any one jittered pattern integrates Y_j Y_k to delta_jk within Monte Carlo error.
        let p = ShParams {
            directions: 4096,
            patterns: 1,
            ..ShParams::default()
        };
        let dirs = patterns(&p);
        let mut gram = [[0.0; 16]; 16];
        for d in &dirs {
            assert!((d.length() - 1.0).abs() < 1e-12);
            let y = eval(*d);
            for (row, yj) in gram.iter_mut().zip(y) {
                for (g, yk) in row.iter_mut().zip(y) {
                    *g += yj * yk * 4.0 * std::f64::consts::PI / dirs.len() as f64;
                }
            }
        }
        for (j, row) in gram.iter().enumerate() {
            for (k, g) in row.iter().enumerate() {
                let want = if j == k { 1.0 } else { 0.0 };
                assert!((g - want).abs() < 0.01, "({j},{k}) = {g}");
            }
        }
    }

    #[test]
    fn product_minification_of_hand_made_blocks() {
        // One 2x2x2 block -> one cell: 1 - mean over the 12 successive pairs of T_a T_b.
        let p = ShParams {
            length_mm: 1000.0,
            ..ShParams::default()
        };
        let grid = ShGrid::new([2, 2, 2], [1.0; 3], &p);
        let top = |o: [f32; 8]| pyramid(&o, &grid)[1][0];
        // Empty and full blocks stay empty and full.
        assert_eq!(top([0.0; 8]), 0.0);
        assert_eq!(top([1.0; 8]), 1.0);
        // A wall of 4 opaque voxels (the z = 0 layer): every z pair is blocked, 2 of 4 x pairs
        // and 2 of 4 y pairs are free -> 1 - 4/12.
        let wall = [1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0];
        assert!((top(wall) - (1.0 - 4.0 / 12.0)).abs() < 1e-12);
        // The same 4 voxels as a checkerboard block every pair: opaque. A box filter gives 0.5
        // for both.
        let checker = [1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0];
        assert_eq!(top(checker), 1.0);
        // A single half-opaque voxel: 3 of its pairs carry T = 0.5 -> 1 - (9 + 1.5) / 12.
        let one = [0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert!((top(one) - (1.0 - 10.5 / 12.0)).abs() < 1e-12);
        // Odd dims: children outside the grid are empty.
        let grid3 = ShGrid::new([3, 1, 1], [1.0; 3], &p);
        let pyr = pyramid(&[1.0, 1.0, 1.0], &grid3);
        assert_eq!(grid3.levels[1], [2, 1, 1]);
        // Cell 1 has one opaque child and seven outside the grid: 3 of its 12 pairs include the
        // opaque child (T = 0), 9 pair empty cells.
        assert!((pyr[1][1] - (1.0 - 9.0 / 12.0)).abs() < 1e-12);
    }

    #[test]
    fn level_count_reaches_the_ray_length() {
        let p = ShParams::default();
        let g = ShGrid::new([256, 256, 108], [1.0; 3], &p);
        // 4 steps per level from 1 mm: 4 * (2^(L+1) - 1) >= 60 -> L = 3.
        assert_eq!(g.top, 3);
        assert_eq!(g.levels.len(), 4);
        assert_eq!(g.dims, [64, 64, 27]);
        let flat = ShGrid::new(
            [64; 3],
            [1.0; 3],
            &ShParams {
                hierarchy: false,
                ..p
            },
        );
        assert_eq!(flat.top, 0);
    }

    #[test]
    fn quantisation_keeps_zero_and_empty_space_exact() {
        assert_eq!(quantize(0.0), 0);
        assert_eq!(dequantize(quantize(0.0)), 0.0);
        assert_eq!(quantize(Y0), 127);
        assert_eq!(dequantize(127), Y0);
        for i in -100..=100 {
            let v = i as f64 / 100.0 * Y0;
            assert!((dequantize(quantize(v)) - v).abs() <= 0.5 * Y0 / 127.0 + 1e-12);
        }
    }
}
