//! Local Ambient Occlusion (Hernell et al.) as DESIGN.md defines it, precomputed on the GPU.

use crate::gpu::{Buffer, ComputePipeline, Gpu, GpuTimer, Result};
use ash::vk;
use glam::DVec3;
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
        let pipeline =
            ComputePipeline::new(gpu, spv, &[b, b, b], std::mem::size_of::<Push>() as u32)?;
        Ok(LaoGpu {
            gpu: gpu.clone(),
            pipeline,
        })
    }

    /// Full LAO of the opacity volume (device buffer, x fastest) into a new device buffer.
    /// Works slab by slab so a large volume never stalls a GPU for long and progress can be
    /// reported through `progress(done_slices, total_slices)`.
    pub fn compute(
        &self,
        opacity: &Buffer,
        dims: [usize; 3],
        spacing: [f64; 3],
        params: &LaoParams,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(Buffer, LaoTiming)> {
        let n = dims[0] * dims[1] * dims[2];
        let out = Buffer::new(
            &self.gpu,
            (n * 4) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::TRANSFER_SRC
                | vk::BufferUsageFlags::TRANSFER_DST,
            gpu_allocator::MemoryLocation::GpuOnly,
            "lao",
        )?;
        let dirs: Vec<[f32; 4]> = index_steps(params, spacing)
            .iter()
            .map(|s| [s.x as f32, s.y as f32, s.z as f32, 0.0])
            .collect();
        let dir_buf = Buffer::from_slice(
            &self.gpu,
            &dirs,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "lao-dirs",
        )?;
        // About 2e8 samples a submission on a CPU device, 4e9 on a GPU.
        let budget = if self.gpu.is_cpu() { 2e8 } else { 4e9 };
        let per_slice = (dims[0] * dims[1]) as f64 * params.rays as f64 * params.steps as f64;
        let slab = ((budget / per_slice) as usize).clamp(4, dims[2].max(4)) / 4 * 4;
        let mut timer = GpuTimer::new(&self.gpu, 2)?;
        let mut timing = LaoTiming::default();
        let t0 = std::time::Instant::now();
        let mut z0 = 0;
        progress(0, dims[2]);
        while z0 < dims[2] {
            let z1 = (z0 + slab).min(dims[2]);
            let push = Push {
                dims: [dims[0] as i32, dims[1] as i32, dims[2] as i32, 0],
                rays: params.rays,
                steps: params.steps,
                exponent: params.step_mm,
                z0: z0 as u32,
                z1: z1 as u32,
            };
            self.gpu.submit_and_wait(|cmd| {
                timer.begin(cmd);
                self.pipeline
                    .bind(cmd, &[opacity, &dir_buf, &out], bytemuck::bytes_of(&push));
                self.pipeline.dispatch(
                    cmd,
                    [
                        dims[0].div_ceil(4) as u32,
                        dims[1].div_ceil(4) as u32,
                        (z1 - z0).div_ceil(4) as u32,
                    ],
                );
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
}
