//! Filtered AO on the GPU (shaders filter_box.comp, filter_ao.comp): three separable passes of
//! box statistics (x, y, z), then the estimator, over any set of voxel boxes. The statistics
//! are recomputed over each box grown by the farthest box centre, so a region's openness equals
//! the whole volume's bit for bit; that is what makes the filters a clip-aware AO method of CAO
//! (docs/design.md, "AO methods"). [`super::filtered::filtered_ao`] is the CPU reference.

use super::cao::Mode;
use super::filtered::FilterParams;
use super::method::MethodBuffers;
use super::voxel_box::{dispatch_box, BoxPush, VoxelBox};
use crate::gpu::{Buffer, ComputePipeline, Gpu, GpuTimer, Reach, Result, SlabBuffer};
use ash::vk;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct AoPush {
    dims: [i32; 4],
    box_min: [i32; 4],
    box_max: [i32; 4],
    hw: [i32; 4],
    spacing: [f32; 4],
}
crate::gpu::glsl_layout!(AoPush, 80, dims: 0, box_min: 16, box_max: 32, hw: 48, spacing: 64);

/// filter_ao.comp's modes: how a pass treats each voxel of its boxes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Pass {
    /// Every voxel computed, no mask (the precompute of the unclipped volume).
    All = 0,
    /// CAO's categories: a -> 1, c -> the precomputed openness, b -> recomputed.
    Contextual = 1,
    /// a -> 1, everything else recomputed (the naive baseline).
    Naive = 2,
}

/// The filters' pipelines and the two scratch volumes of box statistics (vec4 per voxel).
pub struct FilterGpu {
    gpu: Gpu,
    boxes: ComputePipeline,
    estimate: ComputePipeline,
    pass_a: SlabBuffer,
    pass_b: SlabBuffer,
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    pub params: FilterParams,
}

impl FilterGpu {
    pub fn new(
        gpu: &Gpu,
        dims: [usize; 3],
        spacing: [f64; 3],
        params: FilterParams,
    ) -> Result<FilterGpu> {
        let spv_box = include_bytes!(concat!(env!("OUT_DIR"), "/filter_box.comp.spv"));
        let spv_ao = include_bytes!(concat!(env!("OUT_DIR"), "/filter_ao.comp.spv"));
        // (mean, M2, min, max) per voxel, 16 bytes: split into slabs where one buffer is too small.
        let scratch = |name| SlabBuffer::new(gpu, dims, 16, name);
        Ok(FilterGpu {
            gpu: gpu.clone(),
            boxes: ComputePipeline::with_addresses(gpu, spv_box, &[Reach::Address; 3], 48)?,
            estimate: ComputePipeline::with_addresses(gpu, spv_ao, &[Reach::Address; 5], 80)?,
            pass_a: scratch("filter-stats-a")?,
            pass_b: scratch("filter-stats-b")?,
            dims,
            spacing,
            params,
        })
    }

    /// An independent copy (its own scratch volumes), for a second CAO state.
    pub fn duplicate(&self) -> Result<FilterGpu> {
        FilterGpu::new(&self.gpu, self.dims, self.spacing, self.params)
    }

    /// GPU memory the filters hold beyond the volumes every method has (the two stat volumes).
    pub fn resident_bytes(&self) -> u64 {
        self.pass_a.size() + self.pass_b.size()
    }

    /// `b` grown by `grow` voxels per axis, clamped into the grid.
    fn grown(&self, b: &VoxelBox, grow: [usize; 3]) -> VoxelBox {
        VoxelBox {
            min: [0, 1, 2].map(|a| (b.min[a] - grow[a] as i32).max(0)),
            max: [0, 1, 2].map(|a| (b.max[a] + grow[a] as i32).min(self.dims[a] as i32)),
        }
    }

    fn dims4(&self, w: i32) -> [i32; 4] {
        [
            self.dims[0] as i32,
            self.dims[1] as i32,
            self.dims[2] as i32,
            w,
        ]
    }

    /// Records the openness of the voxels of `boxes` from `bufs.density` into `bufs.out_a`,
    /// CAO's categories (`bufs.mask`, `bufs.pre_a`) as `mode` says
    /// ([`super::method::MethodGpu::record_update`]).
    pub fn record(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        at: &[i32],
        mode: Mode,
    ) {
        let pass = match mode {
            Mode::Contextual => Pass::Contextual,
            Mode::Naive => Pass::Naive,
        };
        self.dispatch(cmd, bufs, (boxes, at), pass);
    }

    /// Records the openness of every voxel of the unclipped `density` into `out` (V_PAO).
    pub fn record_precompute(&self, cmd: vk::CommandBuffer, density: &Buffer, out: &Buffer) {
        let bufs = MethodBuffers::precompute(density, self.dims, out);
        self.dispatch(cmd, &bufs, (&[VoxelBox::whole(self.dims)], &[0]), Pass::All);
    }

    fn dispatch(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        (boxes, at): (&[VoxelBox], &[i32]),
        mode: Pass,
    ) {
        let density = bufs.density;
        let h = self.params.half_widths(self.spacing);
        let o = self.params.max_offsets(self.spacing);
        // The statistics are needed at every centre a box's voxels can pick: the box grown by
        // the farthest offset. Pass x runs over that grown further by h in y and z, pass y by h
        // in z, so each pass reads only what the one before it wrote this frame.
        let stats: Vec<VoxelBox> = boxes.iter().map(|b| self.grown(b, o)).collect();
        let exact = self.params.estimator == super::filtered::Estimator::Exact;
        if !exact {
            // (axis, growth, source, target, voxels per member aggregate)
            let (a, b) = (&self.pass_a.table, &self.pass_b.table);
            let passes: [(usize, [usize; 3], &Buffer, &Buffer, usize); 3] = [
                (0, [0, h[1], h[2]], b, a, 1),
                (1, [0, 0, h[2]], a, b, 2 * h[0] + 1),
                (2, [0, 0, 0], b, a, (2 * h[0] + 1) * (2 * h[1] + 1)),
            ];
            for (axis, grow, src, dst, count) in passes {
                for s in &stats {
                    let r = self.grown(s, grow);
                    let push = BoxPush {
                        dims: self.dims4(axis as i32),
                        box_min: [r.min[0], r.min[1], r.min[2], h[axis] as i32],
                        box_max: [r.max[0], r.max[1], r.max[2], count as i32],
                    };
                    self.boxes
                        .bind(cmd, &[density, src, dst], bytemuck::bytes_of(&push));
                    dispatch_box(&self.boxes, cmd, &r);
                }
                self.gpu.barrier(cmd);
            }
        }
        let n: usize = h.iter().map(|x| 2 * x + 1).product();
        for (b, &at) in boxes.iter().zip(at) {
            let push = AoPush {
                dims: self.dims4(self.params.estimator.code() as i32),
                box_min: [b.min[0], b.min[1], b.min[2], mode as i32],
                box_max: [b.max[0], b.max[1], b.max[2], at],
                hw: [h[0] as i32, h[1] as i32, h[2] as i32, n as i32],
                spacing: [
                    self.spacing[0] as f32,
                    self.spacing[1] as f32,
                    self.spacing[2] as f32,
                    self.params.radius_mm as f32,
                ],
            };
            let bufs = [
                density,
                &self.pass_a.table,
                bufs.out_a,
                bufs.mask,
                bufs.pre_a,
            ];
            self.estimate.bind(cmd, &bufs, bytemuck::bytes_of(&push));
            dispatch_box(&self.estimate, cmd, b);
        }
        self.gpu.barrier(cmd);
    }

    /// The openness of the whole unclipped volume of `density` (one submission); returns it
    /// with its GPU ms.
    pub fn compute(&self, density: &Buffer) -> Result<(Buffer, f64)> {
        let out = super::stored::buffer(&self.gpu, self.dims, "filtered-ao")?;
        let mut timer = GpuTimer::new(&self.gpu, 2)?;
        self.gpu.submit_and_wait(|cmd| {
            timer.begin(cmd);
            self.record_precompute(cmd, density, &out);
            timer.mark(cmd, "filter");
        })?;
        let ms = timer.read()?.iter().map(|t| t.1).sum();
        Ok((out, ms))
    }
}
