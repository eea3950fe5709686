//! A volume too large for one buffer: split into slabs of whole z-slices, each its own buffer
//! within the device's largest allocation, reached from shaders through a small table of slab
//! addresses (shaders/include/slabs.glsl). A voxel's value lives at the same place in its slab
//! whatever the slab size, so a split volume computes bit for bit what one buffer would.

use super::{Buffer, Gpu, Result};
use ash::vk;
use gpu_allocator::MemoryLocation;

/// Forces a smaller largest buffer (KiB) for every slab-split volume: tests use it to split a
/// small volume into many slabs and compare with one buffer.
pub const MAX_BUFFER_ENV: &str = "CAO_XR_MAX_BUFFER_KB";

pub struct SlabBuffer {
    /// `[slices per slab, 0]`, then each slab's device address as two 32-bit words.
    pub table: Buffer,
    slabs: Vec<Buffer>,
    pub slices_per_slab: usize,
}

impl SlabBuffer {
    /// Room for `bytes_per_voxel` per voxel of `dims` in as few slabs as the largest buffer
    /// allows (one slice at least per slab).
    pub fn new(
        gpu: &Gpu,
        dims: [usize; 3],
        bytes_per_voxel: u64,
        name: &str,
    ) -> Result<SlabBuffer> {
        let slice = (dims[0] * dims[1]).max(1) as u64 * bytes_per_voxel;
        let depth = dims[2].max(1);
        let per_slab = (gpu.max_slab_bytes() / slice).clamp(1, depth as u64) as usize;
        let slabs = (0..depth.div_ceil(per_slab))
            .map(|s| {
                let slices = per_slab.min(depth - s * per_slab);
                Buffer::new(
                    gpu,
                    slices as u64 * slice,
                    vk::BufferUsageFlags::STORAGE_BUFFER,
                    MemoryLocation::GpuOnly,
                    &format!("{name}-slab{s}"),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let mut words = vec![per_slab as u32, 0];
        for b in &slabs {
            words.extend([b.address as u32, (b.address >> 32) as u32]);
        }
        let table = Buffer::from_slice(
            gpu,
            &words,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            &format!("{name}-table"),
        )?;
        Ok(SlabBuffer {
            table,
            slabs,
            slices_per_slab: per_slab,
        })
    }

    /// Bytes held by the slabs.
    pub fn size(&self) -> u64 {
        self.slabs.iter().map(|b| b.size).sum()
    }

    pub fn slab_count(&self) -> usize {
        self.slabs.len()
    }
}
