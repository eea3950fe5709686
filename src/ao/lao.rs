//! Local Ambient Occlusion (Hernell et al.) as docs/design.md defines it, precomputed on the GPU.

use super::cao::Mode;
use super::method::MethodBuffers;
use super::voxel_box::{dispatch_box_in, VoxelBox};
use crate::gpu::{Buffer, ComputePipeline, Gpu, GpuTimer, Reach, Result};
use ash::vk;
use bytemuck::Zeroable;
use glam::DVec3;
use rayon::prelude::*;
use serde::Serialize;

/// K rays of M steps of D mm.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct LaoParams {
    pub rays: u32,
    pub steps: u32,
    pub step_mm: f32,
}

impl Default for LaoParams {
    fn default() -> Self {
        LaoParams {
            rays: 26,
            steps: 12,
            step_mm: 1.0,
        }
    }
}

impl LaoParams {
    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.rays == 0 || self.rays > 1024 {
            return Err(format!("--rays must be 1..=1024, got {}", self.rays));
        }
        if self.steps == 0 || self.steps > 4096 {
            return Err(format!("--steps must be 1..=4096, got {}", self.steps));
        }
        if !(self.step_mm.is_finite() && self.step_mm > 0.0) {
            return Err(format!("--step-mm must be positive, got {}", self.step_mm));
        }
        Ok(())
    }

    /// Ray length M*D in mm: how far a voxel's AO can see.
    pub fn ray_length_mm(&self) -> f64 {
        self.steps as f64 * self.step_mm as f64
    }
}

/// The K unit directions (in mm space): 6 axes, 14 = axes + cube corners, 26 = all neighbour
/// offsets, any other K a spherical Fibonacci set.
pub fn directions(k: u32) -> Vec<DVec3> {
    let neighbours = |keep: &dyn Fn(i32) -> bool| -> Vec<DVec3> {
        let mut v = Vec::new();
        for z in -1..=1 {
            for y in -1..=1 {
                for x in -1..=1 {
                    let n = x * x + y * y + z * z;
                    if n > 0 && keep(n) {
                        v.push(DVec3::new(x as f64, y as f64, z as f64).normalize());
                    }
                }
            }
        }
        v
    };
    match k {
        6 => neighbours(&|n| n == 1),
        14 => neighbours(&|n| n == 1 || n == 3),
        26 => neighbours(&|_| true),
        _ => {
            let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
            (0..k)
                .map(|j| {
                    let z = 1.0 - (2.0 * j as f64 + 1.0) / k as f64;
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    let phi = j as f64 * golden;
                    DVec3::new(r * phi.cos(), r * phi.sin(), z)
                })
                .collect()
        }
    }
}

/// Each direction's step D*d_k in index units (mm / spacing), as the shader and CPU use it.
pub fn index_steps(params: &LaoParams, spacing: [f64; 3]) -> Vec<DVec3> {
    let s = DVec3::from(spacing);
    directions(params.rays)
        .into_iter()
        .map(|d| d * params.step_mm as f64 / s)
        .collect()
}

/// Per-axis half-width, in voxels, of the box a voxel's rays can reach: (M-1) steps of D mm plus
/// the one-voxel trilinear footprint.
pub fn reach_voxels(params: &LaoParams, spacing: [f64; 3]) -> [usize; 3] {
    let len = params.steps.saturating_sub(1) as f64 * params.step_mm as f64;
    spacing.map(|s| (len / s).ceil() as usize + 1)
}

/// Marks voxels whose reach box (half-widths `h`) holds no voxel with O > 0, one bit per voxel
/// (x fastest, 32 per word). Their LAO is exactly 1, so the kernel can skip them unchanged.
pub fn clear_mask(opacity: &[f32], dims: [usize; 3], h: [usize; 3]) -> Vec<u32> {
    let occupied: Vec<u8> = opacity.par_iter().map(|&o| (o > 0.0) as u8).collect();
    let strides = [1, dims[0], dims[0] * dims[1]];
    // Separable box dilation: OR over [-h, h] along each axis in turn.
    let dilated = (0..3).fold(occupied, |src, axis| {
        let mut out = vec![0u8; src.len()];
        out.par_chunks_mut(dims[0])
            .enumerate()
            .for_each(|(row, line)| {
                let (j, k) = (row % dims[1], row / dims[1]);
                for (i, o) in line.iter_mut().enumerate() {
                    let pos = [i, j, k][axis];
                    let lo = pos.saturating_sub(h[axis]);
                    let hi = (pos + h[axis]).min(dims[axis] - 1);
                    let base = i + dims[0] * (j + dims[1] * k) - pos * strides[axis];
                    *o = (lo..=hi).any(|p| src[base + p * strides[axis]] != 0) as u8;
                }
            });
        out
    });
    dilated
        .par_chunks(32)
        .map(|c| {
            c.iter()
                .enumerate()
                .fold(0u32, |w, (b, &d)| w | (((d == 0) as u32) << b))
        })
        .collect()
}

pub use crate::shader_constants::BRICK;

/// One word per BRICK^3 brick (x fastest): 1 when any voxel in the brick or one voxel beyond its
/// upper faces has O > 0. A sample whose trilinear footprint starts in an unoccupied brick reads
/// only zeros, so the old kernel (lao_old.comp) skips its eight loads: values unchanged.
pub fn brick_occupancy(opacity: &[f32], dims: [usize; 3]) -> Vec<u32> {
    let bd = dims.map(|d| d.div_ceil(BRICK));
    (0..bd[0] * bd[1] * bd[2])
        .into_par_iter()
        .map(|b| {
            let c = [b % bd[0], (b / bd[0]) % bd[1], b / (bd[0] * bd[1])];
            let lo = c.map(|x| x * BRICK);
            let hi = [0, 1, 2].map(|a| (lo[a] + BRICK).min(dims[a] - 1));
            for k in lo[2]..=hi[2] {
                for j in lo[1]..=hi[1] {
                    let row = dims[0] * (j + dims[1] * k);
                    if opacity[row + lo[0]..=row + hi[0]].iter().any(|&o| o > 0.0) {
                        return 1;
                    }
                }
            }
            0
        })
        .collect()
}

/// Which LAO kernel runs: `New` (the default) or the kernel before issue 18, kept so that
/// `cao-xr bench lao` can measure both in one run. Both compute the same A(v) to within float
/// rounding.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LaoKernel {
    Old,
    #[default]
    New,
}

/// One entry of the kernel's sample table (shaders/include/lao_sample.glsl): sample m of ray k.
/// Voxel centres sit at integer + 0.5, so the sample's footprint starts at the same integer
/// offset from every voxel, with the same trilinear weights.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct LaoSample {
    pub frac: [f32; 3],
    /// Index of the footprint's lower corner relative to the voxel's, in the padded grid.
    pub offset: i32,
}
crate::gpu::glsl_layout!(LaoSample, 16, frac: 0, offset: 12);

/// The grid the kernel reads: O with a zero border wide enough for every sample's footprint, so
/// that zero padding needs no test per sample, and the sample table for that grid.
#[derive(Clone, Debug, PartialEq)]
pub struct LaoLayout {
    pub dims: [usize; 3],
    /// Zero voxels before and after the volume on each axis.
    pub pad: [usize; 3],
    /// K * (M - 1) entries, ray-major.
    pub samples: Vec<LaoSample>,
}

impl LaoLayout {
    pub fn new(params: &LaoParams, spacing: [f64; 3], dims: [usize; 3]) -> LaoLayout {
        let mut cells = Vec::new();
        let mut pad = [0usize; 3];
        for s in index_steps(params, spacing) {
            for m in 1..params.steps {
                // Sample point - 0.5 = v + m*s: its floor is v + floor(m*s).
                let c = s * m as f64;
                let d = c.floor();
                let f = c - d;
                let d = [d.x as i64, d.y as i64, d.z as i64];
                for a in 0..3 {
                    // The footprint spans d..=d+1 beyond the voxel on this axis.
                    pad[a] = pad[a].max((-d[a]).max(d[a] + 1).max(0) as usize);
                }
                cells.push((d, [f.x as f32, f.y as f32, f.z as f32]));
            }
        }
        let p = [0, 1, 2].map(|a| (dims[a] + 2 * pad[a]) as i64);
        let samples = cells
            .into_iter()
            .map(|(d, frac)| LaoSample {
                frac,
                offset: (d[0] + p[0] * (d[1] + p[1] * d[2])) as i32,
            })
            .collect();
        LaoLayout { dims, pad, samples }
    }

    /// Dimensions of the padded grid.
    pub fn padded_dims(&self) -> [usize; 3] {
        [0, 1, 2].map(|a| self.dims[a] + 2 * self.pad[a])
    }

    pub fn padded_len(&self) -> usize {
        self.padded_dims().iter().product()
    }

    /// (index of voxel (0,0,0), row stride, slice stride, 0) in the padded grid, as the shaders
    /// take them.
    pub fn stride(&self) -> [i32; 4] {
        let p = self.padded_dims();
        let (sy, sz) = (p[0], p[0] * p[1]);
        [
            (self.pad[0] + sy * self.pad[1] + sz * self.pad[2]) as i32,
            sy as i32,
            sz as i32,
            0,
        ]
    }

    /// The strides of a grid without a border, in [`LaoLayout::stride`]'s form.
    pub fn unpadded_stride(dims: [usize; 3]) -> [i32; 4] {
        [0, dims[0] as i32, (dims[0] * dims[1]) as i32, 0]
    }

    /// `opacity` (x fastest) inside its zero border.
    pub fn padded<T: Copy + Default + Send + Sync>(&self, opacity: &[T]) -> Vec<T> {
        let (d, p) = (self.dims, self.padded_dims());
        let mut out = vec![T::default(); self.padded_len()];
        out.par_chunks_mut(p[0] * p[1])
            .enumerate()
            .skip(self.pad[2])
            .take(d[2])
            .for_each(|(pk, slice)| {
                let k = pk - self.pad[2];
                for j in 0..d[1] {
                    let dst = (j + self.pad[1]) * p[0] + self.pad[0];
                    let src = d[0] * (j + d[1] * k);
                    slice[dst..dst + d[0]].copy_from_slice(&opacity[src..src + d[0]]);
                }
            });
        out
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Push {
    dims: [i32; 4],
    stride: [i32; 4],
    rays: u32,
    steps: u32,
    exponent: f32,
    z0: u32,
    z1: u32,
}
crate::gpu::glsl_layout!(Push, 52,
    dims: 0, stride: 16, rays: 32, steps: 36, exponent: 40, z0: 44, z1: 48);

pub use crate::shader_constants::LAO_GROUP;

/// lao_old.comp's push constants.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct OldPush {
    dims: [i32; 4],
    rays: u32,
    steps: u32,
    exponent: f32,
    z0: u32,
    z1: u32,
}
crate::gpu::glsl_layout!(OldPush, 36, dims: 0, rays: 16, steps: 20, exponent: 24, z0: 28, z1: 32);

/// What the kernel needs of one opacity volume and LAO setting besides O itself: exact
/// empty-space skipping data, O inside its zero border and the sample table ([`LaoLayout`]).
pub struct SkipBuffers {
    pub clear: Buffer,
    /// Only the old kernel reads the bricks.
    pub bricks: Buffer,
    pub padded: Buffer,
    pub samples: Buffer,
    /// [`LaoLayout::stride`] of `padded`.
    pub stride: [i32; 4],
}

/// What [`LaoGpu::record_slab`] reads: the old kernel the opacity O and the K ray steps
/// (`dirs`, from [`LaoGpu::directions_buffer`]), the new one O and its table from `skip`.
#[derive(Clone, Copy)]
pub struct SlabInput<'a> {
    pub opacity: &'a Buffer,
    pub dirs: &'a Buffer,
    pub skip: &'a SkipBuffers,
}

impl SkipBuffers {
    /// What the CAO update keeps of a precompute's skipping data: the clear bits and the sample
    /// table. The padded O (4 bytes per voxel and its border) and the bricks, read only by the
    /// precompute kernels, become 4-byte stand-ins, and their memory is free. Call it once no
    /// submitted work reads them.
    pub fn for_update(self, gpu: &Gpu) -> Result<SkipBuffers> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
        drop((self.padded, self.bricks));
        Ok(SkipBuffers {
            bricks: Buffer::device_local(gpu, &[0u32], usage, "lao-bricks")?,
            padded: Buffer::device_local(gpu, &[0u32], usage, "lao-padded")?,
            clear: self.clear,
            samples: self.samples,
            stride: self.stride,
        })
    }
}

/// The host side of [`SkipBuffers`]: pure host work, so it can run on a worker thread.
#[derive(Clone, Debug, PartialEq)]
pub struct SkipData {
    pub clear: Vec<u32>,
    pub bricks: Vec<u32>,
    /// O inside its zero border, stored ([`super::stored`]).
    pub padded: Vec<u16>,
    pub samples: Vec<LaoSample>,
    pub stride: [i32; 4],
}

impl SkipData {
    pub fn new(
        opacity: &[f32],
        dims: [usize; 3],
        spacing: [f64; 3],
        params: &LaoParams,
    ) -> SkipData {
        let layout = LaoLayout::new(params, spacing, dims);
        SkipData {
            clear: clear_mask(opacity, dims, reach_voxels(params, spacing)),
            bricks: brick_occupancy(opacity, dims),
            padded: layout.padded(&super::stored::words(opacity)),
            stride: layout.stride(),
            samples: layout.samples,
        }
    }
}

/// The LAO compute pipelines.
pub struct LaoGpu {
    gpu: Gpu,
    pipeline: ComputePipeline,
    old: ComputePipeline,
    /// Which kernel [`LaoGpu::record_slab`] and [`LaoGpu::compute`] run.
    pub kernel: LaoKernel,
}

/// What a precompute took.
#[derive(Clone, Debug, Default)]
pub struct LaoTiming {
    /// Sum of the GPU timestamps of all slabs.
    pub gpu_ms: f64,
    pub wall_ms: f64,
    /// Nominal opacity samples: K*(M-1) per voxel (voxels of the clear mask take none).
    pub samples: u64,
}

impl LaoGpu {
    pub fn new(gpu: &Gpu) -> Result<LaoGpu> {
        let spv = include_bytes!(concat!(env!("OUT_DIR"), "/lao.comp.spv"));
        let pipeline = ComputePipeline::with_addresses(
            gpu,
            spv,
            &[
                Reach::Address,
                Reach::Descriptor,
                Reach::Address,
                Reach::Address,
            ],
            std::mem::size_of::<Push>() as u32,
            &[],
        )?;
        let old = ComputePipeline::with_addresses(
            gpu,
            include_bytes!(concat!(env!("OUT_DIR"), "/lao_old.comp.spv")),
            &[
                Reach::Address,
                Reach::Descriptor,
                Reach::Address,
                Reach::Address,
                Reach::Descriptor,
            ],
            std::mem::size_of::<OldPush>() as u32,
            &[],
        )?;
        Ok(LaoGpu {
            gpu: gpu.clone(),
            pipeline,
            old,
            kernel: LaoKernel::New,
        })
    }

    /// The [`SkipData`] of a host opacity volume, uploaded for [`LaoGpu::compute`].
    pub fn skip_buffers(
        &self,
        opacity: &[f32],
        dims: [usize; 3],
        spacing: [f64; 3],
        params: &LaoParams,
    ) -> Result<SkipBuffers> {
        self.upload_skip(&SkipData::new(opacity, dims, spacing, params))
    }

    /// Uploads skipping data computed on the host (possibly on another thread).
    pub fn upload_skip(&self, data: &SkipData) -> Result<SkipBuffers> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
        // A table needs one entry even when M = 1 leaves no samples.
        let samples: &[LaoSample] = if data.samples.is_empty() {
            &[LaoSample::zeroed()]
        } else {
            &data.samples
        };
        Ok(SkipBuffers {
            clear: Buffer::device_local(&self.gpu, &data.clear, usage, "lao-clear")?,
            bricks: Buffer::device_local(&self.gpu, &data.bricks, usage, "lao-bricks")?,
            padded: Buffer::device_local(&self.gpu, &data.padded, usage, "lao-padded")?,
            samples: Buffer::device_local(&self.gpu, samples, usage, "lao-samples")?,
            stride: data.stride,
        })
    }

    /// An uninitialised AO volume ([`super::stored`]), as [`LaoGpu::compute`] fills.
    pub fn output_buffer(&self, dims: [usize; 3]) -> Result<Buffer> {
        super::stored::buffer(&self.gpu, dims, "lao")
    }

    /// The K ray steps in index units, as the kernel reads them.
    pub fn directions_buffer(&self, params: &LaoParams, spacing: [f64; 3]) -> Result<Buffer> {
        let dirs: Vec<[f32; 4]> = index_steps(params, spacing)
            .iter()
            .map(|s| [s.x as f32, s.y as f32, s.z as f32, 0.0])
            .collect();
        Buffer::from_slice(
            &self.gpu,
            &dirs,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "lao-dirs",
        )
    }

    /// Records the LAO of slices `z0..z1` of `input.opacity` into the same slices of `out`
    /// (see [`SlabInput`]). Each voxel's value depends only on O, so any split into slabs gives
    /// the same volume bit for bit. Records no barrier: the caller orders `out` against its
    /// readers.
    pub fn record_slab(
        &self,
        cmd: vk::CommandBuffer,
        input: &SlabInput,
        out: &Buffer,
        dims: [usize; 3],
        params: &LaoParams,
        z: std::ops::Range<usize>,
    ) {
        let SlabInput {
            opacity,
            dirs,
            skip,
        } = *input;
        let dims4 = [dims[0] as i32, dims[1] as i32, dims[2] as i32, 0];
        let pipeline = match self.kernel {
            LaoKernel::New => {
                let push = Push {
                    dims: dims4,
                    stride: skip.stride,
                    rays: params.rays,
                    steps: params.steps,
                    exponent: params.step_mm,
                    z0: z.start as u32,
                    z1: z.end as u32,
                };
                let bufs = [&skip.padded, &skip.samples, out, &skip.clear];
                self.pipeline.bind(cmd, &bufs, bytemuck::bytes_of(&push));
                &self.pipeline
            }
            LaoKernel::Old => {
                let push = OldPush {
                    dims: dims4,
                    rays: params.rays,
                    steps: params.steps,
                    exponent: params.step_mm,
                    z0: z.start as u32,
                    z1: z.end as u32,
                };
                let bufs = [opacity, dirs, out, &skip.clear, &skip.bricks];
                self.old.bind(cmd, &bufs, bytemuck::bytes_of(&push));
                &self.old
            }
        };
        let group = match self.kernel {
            LaoKernel::New => LAO_GROUP,
            LaoKernel::Old => [4; 3],
        };
        pipeline.dispatch(
            cmd,
            [
                (dims[0] as u32).div_ceil(group[0]),
                (dims[1] as u32).div_ceil(group[1]),
                (z.len() as u32).div_ceil(group[2]),
            ],
        );
    }

    /// Opacity samples one z-slice costs at most (K*M per voxel), for sizing slabs.
    pub fn samples_per_slice(dims: [usize; 3], params: &LaoParams) -> f64 {
        (dims[0] * dims[1]) as f64 * params.rays as f64 * params.steps as f64
    }

    /// Full LAO of the opacity volume (device buffer, x fastest) into a new device buffer;
    /// `skip` is its [`LaoGpu::skip_buffers`].
    /// Works slab by slab so a large volume never stalls a GPU for long and progress can be
    /// reported through `progress(done_slices, total_slices)`.
    pub fn compute(
        &self,
        opacity: &Buffer,
        skip: &SkipBuffers,
        dims: [usize; 3],
        spacing: [f64; 3],
        params: &LaoParams,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(Buffer, LaoTiming)> {
        let n = dims[0] * dims[1] * dims[2];
        let out = self.output_buffer(dims)?;
        let dir_buf = self.directions_buffer(params, spacing)?;
        // About 2e8 samples a submission on a CPU device, 4e9 on a GPU.
        let budget = if self.gpu.is_cpu() { 2e8 } else { 4e9 };
        let per_slice = Self::samples_per_slice(dims, params);
        let slab = ((budget / per_slice) as usize).clamp(4, dims[2].max(4)) / 4 * 4;
        let mut timer = GpuTimer::new(&self.gpu, 2)?;
        let mut timing = LaoTiming::default();
        let t0 = std::time::Instant::now();
        let mut z0 = 0;
        progress(0, dims[2]);
        while z0 < dims[2] {
            let z1 = (z0 + slab).min(dims[2]);
            self.gpu.submit_and_wait(|cmd| {
                timer.begin(cmd);
                let input = SlabInput {
                    opacity,
                    dirs: &dir_buf,
                    skip,
                };
                self.record_slab(cmd, &input, &out, dims, params, z0..z1);
                timer.mark(cmd, "lao");
            })?;
            timing.gpu_ms += timer.read()?.iter().map(|t| t.1).sum::<f64>();
            z0 = z1;
            progress(z0, dims[2]);
        }
        timing.wall_ms = t0.elapsed().as_secs_f64() * 1e3;
        timing.samples = n as u64 * params.rays as u64 * params.steps.saturating_sub(1) as u64;
        Ok((out, timing))
    }
}

/// Push constants of cao_update.comp: the padded grid, the LAO parameters and a box.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct UpdatePush {
    dims: [i32; 4],
    stride: [i32; 4],
    rays: u32,
    steps: u32,
    exponent: f32,
    naive: u32,
    box_min: [i32; 4],
    box_max: [i32; 4],
}
crate::gpu::glsl_layout!(UpdatePush, 80,
    dims: 0, stride: 16, rays: 32, steps: 36, exponent: 40, naive: 44, box_min: 48, box_max: 64);

/// LAO as CAO's method ([`super::method::MethodGpu::Lao`]): its parameters, its region
/// recompute (cao_update.comp) and what that kernel reads besides O_c: the skipping data of O
/// and the padded grid O_c lies in ([`LaoLayout`]).
pub struct LaoMethod {
    gpu: Gpu,
    update: ComputePipeline,
    pub params: LaoParams,
    /// The skipping data of O (the whole precompute's set until [`LaoMethod::for_update`]).
    pub skip: SkipBuffers,
    pub dims: [usize; 3],
    /// [`LaoLayout::stride`], [`LaoLayout::padded_len`] and [`LaoLayout::pad`] of the padded
    /// grid.
    stride: [i32; 4],
    padded_len: usize,
    pad: [usize; 3],
}

impl LaoMethod {
    /// LAO with `params` over a volume of `dims` voxels of `spacing` (named `name` in errors),
    /// `skip` the skipping data of its O: an error when they were made for another grid.
    pub fn new(
        gpu: &Gpu,
        (name, dims, spacing): (&str, [usize; 3], [f64; 3]),
        params: LaoParams,
        skip: SkipBuffers,
    ) -> Result<LaoMethod> {
        let layout = LaoLayout::new(&params, spacing, dims);
        let stride = layout.stride();
        if skip.stride != stride {
            return Err(crate::gpu::GpuError::Other(format!(
                "{name}: LAO skipping data for a padded grid of strides {:?}, the CAO state uses {stride:?}",
                skip.stride
            )));
        }
        let update = update_pipeline(gpu)?;
        Ok(LaoMethod {
            gpu: gpu.clone(),
            update,
            params,
            skip,
            dims,
            stride,
            padded_len: layout.padded_len(),
            pad: layout.pad,
        })
    }

    /// What the per-frame update keeps ([`SkipBuffers::for_update`]).
    pub fn for_update(self) -> Result<LaoMethod> {
        let skip = self.skip.for_update(&self.gpu)?;
        Ok(LaoMethod { skip, ..self })
    }

    /// An independent copy (skipping data of its own), for a second CAO state.
    pub fn duplicate(&self) -> Result<LaoMethod> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
        let skip = SkipBuffers {
            clear: self.skip.clear.duplicate(usage, "lao-clear")?,
            bricks: self.skip.bricks.duplicate(usage, "lao-bricks")?,
            padded: self.skip.padded.duplicate(usage, "lao-padded")?,
            samples: self.skip.samples.duplicate(usage, "lao-samples")?,
            stride: self.skip.stride,
        };
        Ok(LaoMethod {
            gpu: self.gpu.clone(),
            update: update_pipeline(&self.gpu)?,
            skip,
            ..*self
        })
    }

    /// The farthest sample in mm, (M - 1) D: the method's reach.
    pub fn reach_mm(&self) -> f64 {
        self.params.steps.saturating_sub(1) as f64 * self.params.step_mm as f64
    }

    /// Where voxel v of O_c lies, inside the zero border the kernel reads (its 4th component 0).
    pub fn stride(&self) -> [i32; 4] {
        self.stride
    }

    /// Voxels of the padded grid O_c lies in.
    pub fn padded_len(&self) -> usize {
        self.padded_len
    }

    /// The padded grid's zero border on each axis.
    pub fn pad(&self) -> [usize; 3] {
        self.pad
    }

    /// GPU memory the method holds beyond the volumes every method has (the skipping data the
    /// update reads, and the bricks).
    pub fn resident_bytes(&self) -> u64 {
        self.skip.clear.size + self.skip.bricks.size
    }

    /// Records the LAO of the voxels of `boxes` from O_c (`bufs.density`, in the padded grid or
    /// the z-slices of it that CAO holds: `bufs.density_stride`) into `bufs.out_a`, CAO's categories as `mode` says. Records no barrier.
    pub fn record(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        at: &[i32],
        mode: Mode,
    ) {
        let d = self.dims;
        for (b, &at) in boxes.iter().zip(at) {
            let push = UpdatePush {
                dims: [d[0] as i32, d[1] as i32, d[2] as i32, 0],
                stride: bufs.density_stride,
                rays: self.params.rays,
                steps: self.params.steps,
                exponent: self.params.step_mm,
                naive: (mode == Mode::Naive) as u32,
                box_min: [b.min[0], b.min[1], b.min[2], 0],
                box_max: [b.max[0], b.max[1], b.max[2], at],
            };
            let bufs = [
                bufs.density,
                &self.skip.samples,
                bufs.out_a,
                &self.skip.clear,
                bufs.mask,
                bufs.pre_a,
                bufs.ao_table,
            ];
            self.update.bind(cmd, &bufs, bytemuck::bytes_of(&push));
            dispatch_box_in(&self.update, cmd, b, LAO_GROUP);
        }
    }
}

/// cao_update.comp: LAO of the voxels of a box from O_c, by CAO's categories.
fn update_pipeline(gpu: &Gpu) -> Result<ComputePipeline> {
    ComputePipeline::with_addresses(
        gpu,
        include_bytes!(concat!(env!("OUT_DIR"), "/cao_update.comp.spv")),
        &[
            Reach::Address,
            Reach::Descriptor,
            Reach::Address,
            Reach::Address,
            Reach::Address,
            Reach::Address,
            Reach::Descriptor,
        ],
        std::mem::size_of::<UpdatePush>() as u32,
        &[],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn direction_sets_are_unit_and_sized() {
        for k in [6, 14, 26, 54, 7, 100] {
            let d = directions(k);
            assert_eq!(d.len(), k as usize);
            for v in &d {
                assert!((v.length() - 1.0).abs() < 1e-12);
            }
            // Balanced sets: the mean direction is (close to) zero.
            let mean = d.iter().copied().sum::<DVec3>() / k as f64;
            assert!(mean.length() < 0.1, "K={k} mean {mean}");
        }
        assert!(directions(14)
            .iter()
            .any(|v| (v.x - 1.0 / 3f64.sqrt()).abs() < 1e-12));
    }

    #[test]
    fn the_padded_layout_reads_what_the_definition_reads() {
        // Anisotropic spacing, D != 1, voxels at every border: each sample the table describes,
        // read from the padded grid as the shader reads it, is the reference's trilinear O at
        // that sample (zero padding included), and every read stays inside the padded grid.
        // Also whole-voxel steps (K = 6, D = 1 mm = the spacing), whose footprints end one
        // voxel farther out.
        let dims = [7, 5, 6];
        for (rays, steps, step_mm, spacing) in
            [(26, 9, 1.7, [0.8, 1.3, 2.1]), (6, 4, 1.0, [1.0; 3])]
        {
            let params = LaoParams {
                rays,
                steps,
                step_mm,
            };
            check_layout(dims, &params, spacing);
        }
    }

    fn check_layout(dims: [usize; 3], params: &LaoParams, spacing: [f64; 3]) {
        let n = dims[0] * dims[1] * dims[2];
        let params = *params;
        let o: Vec<f32> = (0..n).map(|i| ((i * 37) % 11) as f32 / 10.0).collect();
        let l = LaoLayout::new(&params, spacing, dims);
        let padded = l.padded(&o);
        assert_eq!(padded.len(), l.padded_len());
        let [origin, sy, sz, _] = l.stride().map(|x| x as i64);
        let steps = index_steps(&params, spacing);
        let m1 = params.steps as usize - 1;
        assert_eq!(l.samples.len(), steps.len() * m1);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let base = origin + i as i64 + sy * j as i64 + sz * k as i64;
                    assert_eq!(padded[base as usize], o[i + dims[0] * (j + dims[1] * k)]);
                    for (r, s) in steps.iter().enumerate() {
                        for m in 1..=m1 {
                            let e = l.samples[r * m1 + m - 1];
                            let b = base + e.offset as i64;
                            let at = |d: i64| padded[(b + d) as usize] as f64;
                            let f = e.frac.map(|x| x as f64);
                            let lerp = |a: f64, b: f64, t: f64| a * (1.0 - t) + b * t;
                            let x0 = lerp(at(0), at(1), f[0]);
                            let x1 = lerp(at(sy), at(sy + 1), f[0]);
                            let x2 = lerp(at(sz), at(sz + 1), f[0]);
                            let x3 = lerp(at(sz + sy), at(sz + sy + 1), f[0]);
                            let got = lerp(lerp(x0, x1, f[1]), lerp(x2, x3, f[1]), f[2]);
                            let p = DVec3::new(i as f64, j as f64, k as f64) + 0.5 + *s * m as f64;
                            let want = super::super::cpu::opacity_at(&o, dims, p.to_array());
                            assert!(
                                (got - want).abs() < 1e-6,
                                "voxel {i},{j},{k} ray {r} step {m}: {got} vs {want}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn skip_structures_match_brute_force() {
        let dims = [13, 9, 11];
        let n = dims[0] * dims[1] * dims[2];
        // A few occupied voxels, including at the borders.
        let mut o = vec![0.0f32; n];
        for &(i, j, k) in &[(0, 0, 0), (6, 4, 5), (12, 8, 10), (3, 8, 2)] {
            o[i + dims[0] * (j + dims[1] * k)] = 0.5;
        }
        let at = |i: usize, j: usize, k: usize| o[i + dims[0] * (j + dims[1] * k)] > 0.0;
        let h = [2, 1, 3];
        let mask = clear_mask(&o, dims, h);
        let bricks = brick_occupancy(&o, dims);
        let bd = dims.map(|d| d.div_ceil(BRICK));
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let idx = i + dims[0] * (j + dims[1] * k);
                    let mut near = false;
                    for z in k.saturating_sub(h[2])..=(k + h[2]).min(dims[2] - 1) {
                        for y in j.saturating_sub(h[1])..=(j + h[1]).min(dims[1] - 1) {
                            for x in i.saturating_sub(h[0])..=(i + h[0]).min(dims[0] - 1) {
                                near |= at(x, y, z);
                            }
                        }
                    }
                    assert_eq!(
                        (mask[idx / 32] >> (idx % 32)) & 1 == 1,
                        !near,
                        "voxel {i},{j},{k}"
                    );
                    // A voxel's brick, and the brick of the voxel one step below on each axis,
                    // must be marked occupied when the voxel is.
                    if at(i, j, k) {
                        for (di, dj, dk) in [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1)]
                        {
                            let (x, y, z) = (
                                i.saturating_sub(di),
                                j.saturating_sub(dj),
                                k.saturating_sub(dk),
                            );
                            let b = x / BRICK + bd[0] * (y / BRICK + bd[1] * (z / BRICK));
                            assert_eq!(bricks[b], 1, "brick of {x},{y},{z}");
                        }
                    }
                }
            }
        }
        assert!(bricks.contains(&0) && mask.iter().any(|&w| w != 0));
    }
}
