//! Filtered AO on the GPU (shaders filter_box.comp, filter_ao.comp): three separable passes of
//! box statistics (x, y, z), then the estimator, over any set of voxel boxes. The statistics
//! are recomputed over each box grown by the farthest box centre, so a region's openness equals
//! the whole volume's bit for bit; that is what makes the filters a clip-aware AO method of CAO
//! (docs/design.md, "AO methods"). [`super::filtered::filtered_ao`] is the CPU reference.
//!
//! The statistics are scratch: on a volume of more than [`STATS_CHUNK_BYTES`] of them, the GPU
//! holds them only over a window of z-slices, and every pass runs in chunks of slices, each
//! with the margin of slices its statistics read on either side. A voxel's statistics are the
//! same whichever region they are computed over, so a chunked pass equals a whole one bit for
//! bit.

use super::cao::Mode;
use super::filtered::FilterParams;
use super::method::MethodBuffers;
use super::voxel_box::{dispatch_box, VoxelBox};
use crate::gpu::{Buffer, ComputePipeline, Gpu, GpuTimer, Reach, Result, SlabBuffer};
use ash::vk;

/// Box statistics computed at once, at least (beyond the margins a chunk needs): on larger
/// volumes the GPU holds them over a window of z-slices only. A chunk recomputes its margins,
/// so a tool's update should fit one: 32 slices of 512 x 512, the 40 mm sphere of `bench
/// scale` and its reach on a chest CT.
pub const STATS_CHUNK_BYTES: u64 = 128 << 20;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct StatsPush {
    dims: [i32; 4],
    box_min: [i32; 4],
    box_max: [i32; 4],
    window: [i32; 4],
}
crate::gpu::glsl_layout!(StatsPush, 64, dims: 0, box_min: 16, box_max: 32, window: 48);

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

/// The z-slices the statistics of the slices being computed read on either side: the box
/// centre's offset and the box's half-width. It is also how far the region recompute reads the
/// density beyond its boxes (the gradient's one voxel lies inside, as h >= 1).
fn margin(params: &FilterParams, spacing: [f64; 3]) -> usize {
    params.half_widths(spacing)[2] + params.max_offsets(spacing)[2]
}

/// The z-slices whose AO one chunk computes (`forced`, or at least [`STATS_CHUNK_BYTES`] of
/// statistics, eight margins and 16 slices, fewer where a GPU budget leaves `budget_left`
/// bytes: a smaller chunk costs time, not exactness), and the z-slices the statistics hold: the chunk
/// and its margins, or the whole volume where that is less. The exact estimator reads no
/// statistics: one chunk, one slice held.
pub fn stats_window(
    dims: [usize; 3],
    spacing: [f64; 3],
    params: &FilterParams,
    (forced, budget_left): (Option<usize>, Option<u64>),
) -> (usize, usize) {
    if params.estimator == super::filtered::Estimator::Exact {
        return (dims[2].max(1), 1);
    }
    let slice = (dims[0] * dims[1]).max(1) as u64 * 16;
    let margin = margin(params, spacing);
    let chunk = forced.unwrap_or_else(|| {
        let most = ((STATS_CHUNK_BYTES / slice) as usize)
            .max(8 * margin)
            .max(16);
        // Under a GPU budget both windows take at most a quarter of what it leaves.
        let within = budget_left.map_or(most, |left| {
            ((left / 8 / slice) as usize)
                .saturating_sub(2 * margin)
                .max(1)
        });
        most.min(within)
    });
    (chunk, (chunk + 2 * margin).min(dims[2].max(1)))
}

/// The filters' pipelines and the two scratch volumes of box statistics (vec4 per voxel).
pub struct FilterGpu {
    gpu: Gpu,
    boxes: ComputePipeline,
    estimate: ComputePipeline,
    pass_a: SlabBuffer,
    pass_b: SlabBuffer,
    /// Z-slices whose AO one chunk computes, and the z-slices the statistics hold: the chunk and
    /// the margin its statistics read on either side, or the whole volume.
    chunk: usize,
    window: usize,
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    pub params: FilterParams,
    /// The one-word brick table its precompute writes V_PAO whole through.
    whole: Buffer,
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
        // (mean, M2, min, max) per voxel, 16 bytes, over a window of slices (the module's doc),
        // split into slabs where one buffer is too small.
        let (chunk, window) = stats_window(
            dims,
            spacing,
            &params,
            (gpu.forced_scratch_slices(), gpu.budget_left()),
        );
        let scratch = |name| SlabBuffer::new(gpu, [dims[0], dims[1], window], 16, name);
        Ok(FilterGpu {
            gpu: gpu.clone(),
            boxes: ComputePipeline::with_addresses(gpu, spv_box, &[Reach::Address; 3], 64, &[])?,
            estimate: ComputePipeline::with_addresses(
                gpu,
                spv_ao,
                &[[Reach::Address; 5].as_slice(), &[Reach::Descriptor]].concat(),
                80,
                &[],
            )?,
            pass_a: scratch("filter-stats-a")?,
            pass_b: scratch("filter-stats-b")?,
            chunk,
            window,
            dims,
            spacing,
            params,
            whole: super::pool::whole_table(gpu)?,
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

    /// How many z-slices either side of a voxel its recompute reads the density.
    pub fn reach_slices(&self) -> usize {
        margin(&self.params, self.spacing)
    }

    /// The z-slices the statistics hold (all of the volume's, or a window of them).
    pub fn stats_slices(&self) -> usize {
        self.window
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
        let bufs = MethodBuffers::precompute(density, self.dims, (out, &self.whole));
        self.dispatch(cmd, &bufs, (&[VoxelBox::whole(self.dims)], &[0]), Pass::All);
    }

    fn dispatch(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        (boxes, at): (&[VoxelBox], &[i32]),
        mode: Pass,
    ) {
        let exact = self.params.estimator == super::filtered::Estimator::Exact;
        // Whole statistics (or none, for the exact estimator): one chunk of every slice.
        let whole = exact || self.window == self.dims[2];
        let chunk = if whole {
            self.dims[2].max(1)
        } else {
            self.chunk
        };
        let margin = self.reach_slices();
        let mut z = boxes.iter().filter(|b| b.voxels() > 0);
        let Some(first) = z.next() else {
            self.gpu.barrier(cmd);
            return;
        };
        let (lo, hi) = z.fold((first.min[2], first.max[2]), |(lo, hi), b| {
            (lo.min(b.min[2]), hi.max(b.max[2]))
        });
        for c0 in (lo..hi).step_by(chunk) {
            let c1 = (c0 + chunk as i32).min(hi);
            // The boxes' slices in [c0, c1), each box's staged V_PAO moved on by the slices cut.
            let (part, part_at): (Vec<VoxelBox>, Vec<i32>) = boxes
                .iter()
                .zip(at)
                .filter(|(b, _)| b.min[2] < c1 && c0 < b.max[2] && b.voxels() > 0)
                .map(|(b, &at)| {
                    let mut p = *b;
                    p.min[2] = b.min[2].max(c0);
                    p.max[2] = b.max[2].min(c1);
                    let row = (b.max[0] - b.min[0]) * (b.max[1] - b.min[1]);
                    (p, at + row * (p.min[2] - b.min[2]))
                })
                .unzip();
            // The window from the chunk less its margin, kept inside the volume: it holds every
            // slice the chunk's statistics are computed over and read.
            let base = if whole {
                0
            } else {
                (c0 as usize)
                    .saturating_sub(margin)
                    .min(self.dims[2] - self.window)
            };
            self.dispatch_chunk(cmd, bufs, (&part, &part_at), mode, base as i32);
        }
    }

    /// The passes over `boxes`, whose statistics lie in the window from z-slice `base`.
    fn dispatch_chunk(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        (boxes, at): (&[VoxelBox], &[i32]),
        mode: Pass,
        base: i32,
    ) {
        let density = bufs.density;
        // Where voxel v of the density lies: v's index in the volume plus this (a window of
        // O_c, src/ao/cao.rs).
        let offset = bufs.density_stride[0];
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
                    let push = StatsPush {
                        dims: self.dims4(axis as i32),
                        box_min: [r.min[0], r.min[1], r.min[2], h[axis] as i32],
                        box_max: [r.max[0], r.max[1], r.max[2], count as i32],
                        window: [offset, base, 0, 0],
                    };
                    self.boxes
                        .bind(cmd, &[density, src, dst], bytemuck::bytes_of(&push));
                    dispatch_box(&self.boxes, cmd, &r);
                }
                self.gpu.barrier(cmd);
            }
        }
        let estimator = self.params.estimator.code() as i32;
        for (b, &at) in boxes.iter().zip(at) {
            let push = AoPush {
                dims: self.dims4(offset),
                box_min: [b.min[0], b.min[1], b.min[2], mode as i32 + 4 * estimator],
                box_max: [b.max[0], b.max[1], b.max[2], at],
                hw: [h[0] as i32, h[1] as i32, h[2] as i32, base],
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
                bufs.ao_table,
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
