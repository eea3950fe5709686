//! Voxel boxes: the regions the AO passes run over (CAO's restore, clip and update boxes, a
//! method's region recompute, a slab of a precompute), their push constants and dispatch.

use crate::gpu::ComputePipeline;
use ash::vk;

/// A voxel box [min, max).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VoxelBox {
    pub min: [i32; 3],
    pub max: [i32; 3],
}

impl VoxelBox {
    /// Every voxel of a volume of `dims`.
    pub fn whole(dims: [usize; 3]) -> VoxelBox {
        VoxelBox {
            min: [0; 3],
            max: dims.map(|d| d as i32),
        }
    }

    pub fn voxels(&self) -> u64 {
        (0..3)
            .map(|a| (self.max[a] - self.min[a]).max(0) as u64)
            .product()
    }
    fn overlaps(&self, o: &VoxelBox) -> bool {
        (0..3).all(|a| self.min[a] < o.max[a] && o.min[a] < self.max[a])
    }
    fn union(&self, o: &VoxelBox) -> VoxelBox {
        VoxelBox {
            min: [0, 1, 2].map(|a| self.min[a].min(o.min[a])),
            max: [0, 1, 2].map(|a| self.max[a].max(o.max[a])),
        }
    }
}

/// Merges overlapping boxes so that no voxel is visited (or counted) twice.
pub fn merge_boxes(mut boxes: Vec<VoxelBox>) -> Vec<VoxelBox> {
    let mut merged = true;
    while merged {
        merged = false;
        'outer: for i in 0..boxes.len() {
            for j in i + 1..boxes.len() {
                if boxes[i].overlaps(&boxes[j]) {
                    boxes[i] = boxes[i].union(&boxes[j]);
                    boxes.swap_remove(j);
                    merged = true;
                    break 'outer;
                }
            }
        }
    }
    boxes
}

/// Dispatches a 4^3-workgroup compute pass over the voxels of `b`.
pub fn dispatch_box(pipe: &ComputePipeline, cmd: vk::CommandBuffer, b: &VoxelBox) {
    dispatch_box_in(pipe, cmd, b, [4; 3]);
}

/// Dispatches a compute pass of workgroup size `group` over the voxels of `b`.
pub fn dispatch_box_in(
    pipe: &ComputePipeline,
    cmd: vk::CommandBuffer,
    b: &VoxelBox,
    group: [u32; 3],
) {
    pipe.dispatch(
        cmd,
        [0, 1, 2].map(|a| ((b.max[a] - b.min[a]).max(0) as u32).div_ceil(group[a])),
    );
}

/// Push constants of the passes over a voxel box (the w components are each pass's own).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct BoxPush {
    pub dims: [i32; 4],
    pub box_min: [i32; 4],
    pub box_max: [i32; 4],
}
crate::gpu::glsl_layout!(BoxPush, 48, dims: 0, box_min: 16, box_max: 32);
