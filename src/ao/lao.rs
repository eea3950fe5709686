//! Local Ambient Occlusion (Hernell et al.) as docs/design.md defines it, precomputed on the GPU.

use crate::gpu::{Buffer, ComputePipeline, Gpu, GpuTimer, Result};
use ash::vk;
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
/// only zeros, so the kernel skips its eight loads and multiplies by nothing: values unchanged.
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

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Push {
    dims: [i32; 4],
    rays: u32,
    steps: u32,
    exponent: f32,
    z0: u32,
    z1: u32,
}
crate::gpu::glsl_layout!(Push, 36, dims: 0, rays: 16, steps: 20, exponent: 24, z0: 28, z1: 32);

/// Exact empty-space skipping data for one opacity volume and LAO setting.
pub struct SkipBuffers {
    pub clear: Buffer,
    pub bricks: Buffer,
}

/// The host side of [`SkipBuffers`]: pure host work, so it can run on a worker thread.
#[derive(Clone, Debug, PartialEq)]
pub struct SkipData {
    pub clear: Vec<u32>,
    pub bricks: Vec<u32>,
}

impl SkipData {
    pub fn new(
        opacity: &[f32],
        dims: [usize; 3],
        spacing: [f64; 3],
        params: &LaoParams,
    ) -> SkipData {
        SkipData {
            clear: clear_mask(opacity, dims, reach_voxels(params, spacing)),
            bricks: brick_occupancy(opacity, dims),
        }
    }
}

/// The LAO compute pipeline.
pub struct LaoGpu {
    gpu: Gpu,
    pipeline: ComputePipeline,
}

/// What a precompute took.
#[derive(Clone, Debug, Default)]
pub struct LaoTiming {
    /// Sum of the GPU timestamps of all slabs.
    pub gpu_ms: f64,
    pub wall_ms: f64,
    /// Opacity samples taken (upper bound: K*(M-1) per voxel, before early termination).
    pub samples: u64,
}

impl LaoGpu {
    pub fn new(gpu: &Gpu) -> Result<LaoGpu> {
        let spv = include_bytes!(concat!(env!("OUT_DIR"), "/lao.comp.spv"));
        let b = vk::DescriptorType::STORAGE_BUFFER;
        let pipeline = ComputePipeline::new(
            gpu,
            spv,
            &[b, b, b, b, b],
            std::mem::size_of::<Push>() as u32,
        )?;
        Ok(LaoGpu {
            gpu: gpu.clone(),
            pipeline,
        })
    }

    /// The [`clear_mask`] and [`brick_occupancy`] of a host opacity volume, uploaded for
    /// [`LaoGpu::compute`].
    pub fn skip_buffers(
        &self,
        opacity: &[f32],
        dims: [usize; 3],
        spacing: [f64; 3],
        params: &LaoParams,
    ) -> Result<SkipBuffers> {
        self.upload_skip(&SkipData::new(opacity, dims, spacing, params))
    }

    /// Stand-ins for the skipping data of a CAO state whose method is not LAO (the filters and
    /// the local histograms never read it); a switch to LAO brings real ones.
    pub fn skip_stand_in(&self) -> Result<SkipBuffers> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
        Ok(SkipBuffers {
            clear: Buffer::device_local(&self.gpu, &[0u32], usage, "lao-clear")?,
            bricks: Buffer::device_local(&self.gpu, &[0u32], usage, "lao-bricks")?,
        })
    }

    /// Uploads skipping data computed on the host (possibly on another thread).
    pub fn upload_skip(&self, data: &SkipData) -> Result<SkipBuffers> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
        Ok(SkipBuffers {
            clear: Buffer::device_local(&self.gpu, &data.clear, usage, "lao-clear")?,
            bricks: Buffer::device_local(&self.gpu, &data.bricks, usage, "lao-bricks")?,
        })
    }

    /// An uninitialised device buffer for one f32 per voxel, as [`LaoGpu::compute`] fills.
    pub fn output_buffer(&self, dims: [usize; 3]) -> Result<Buffer> {
        let n = dims[0] * dims[1] * dims[2];
        Buffer::new(
            &self.gpu,
            (n.max(1) * 4) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::TRANSFER_SRC
                | vk::BufferUsageFlags::TRANSFER_DST,
            gpu_allocator::MemoryLocation::GpuOnly,
            "lao",
        )
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

    /// Records the LAO of slices `z0..z1` of `opacity` into the same slices of `out`
    /// (`dirs` from [`LaoGpu::directions_buffer`]). Each voxel's value depends only on O, so
    /// any split into slabs gives the same volume bit for bit. Records no barrier: the caller
    /// orders `out` against its readers.
    #[allow(clippy::too_many_arguments)]
    pub fn record_slab(
        &self,
        cmd: vk::CommandBuffer,
        opacity: &Buffer,
        dirs: &Buffer,
        skip: &SkipBuffers,
        out: &Buffer,
        dims: [usize; 3],
        params: &LaoParams,
        z: std::ops::Range<usize>,
    ) {
        let push = Push {
            dims: [dims[0] as i32, dims[1] as i32, dims[2] as i32, 0],
            rays: params.rays,
            steps: params.steps,
            exponent: params.step_mm,
            z0: z.start as u32,
            z1: z.end as u32,
        };
        self.pipeline.bind(
            cmd,
            &[opacity, dirs, out, &skip.clear, &skip.bricks],
            bytemuck::bytes_of(&push),
        );
        self.pipeline.dispatch(
            cmd,
            [
                dims[0].div_ceil(4) as u32,
                dims[1].div_ceil(4) as u32,
                z.len().div_ceil(4) as u32,
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
                self.record_slab(cmd, opacity, &dir_buf, skip, &out, dims, params, z0..z1);
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
