//! How values in [0, 1] are stored on the GPU: as 16-bit unorm, 2 bytes a voxel (docs/design.md,
//! "Stored sizes"). AO (V_AO, V_PAO), the opacity O and O_c, and the filters' density are. The
//! shaders read and store through `shaders/include/unorm16.glsl`; the host uploads through
//! [`upload`] and reads through [`read`].

use crate::gpu::{Buffer, Gpu, Result};
use crate::shader_constants::UNORM16_MAX;
use ash::vk;

/// Bytes per voxel of V_AO and V_PAO.
pub const BYTES_PER_VOXEL: u64 = 2;

/// The largest difference between a value in [0, 1] and its stored value (half a step).
pub const ROUNDING: f32 = 0.5 / UNORM16_MAX;

/// The stored word of AO value `a`: round(clamp(a) · 65535), as `unorm16` in the shaders.
pub fn pack(a: f32) -> u16 {
    (a.clamp(0.0, 1.0) * UNORM16_MAX + 0.5) as u16
}

/// The AO value of stored word `q`: q / 65535 (what the ray caster reads, `unorm16_value`).
pub fn unpack(q: u16) -> f32 {
    q as f32 / UNORM16_MAX
}

/// `values` as they would be stored (for CPU references and exports).
pub fn quantised(values: &[f32]) -> Vec<f32> {
    values.iter().map(|&a| unpack(pack(a))).collect()
}

/// The stored words of `values`.
pub fn words(values: &[f32]) -> Vec<u16> {
    use rayon::prelude::*;
    values.par_iter().map(|&a| pack(a)).collect()
}

/// `values` stored on the GPU (device-local, `usage` and a transfer destination).
pub fn upload(
    gpu: &Gpu,
    values: &[f32],
    usage: vk::BufferUsageFlags,
    name: &str,
) -> Result<Buffer> {
    Buffer::device_local(gpu, &words(values), usage, name)
}

/// The size of an AO volume of `voxels` voxels (no padding: [`read`] of the whole buffer is
/// the volume).
pub fn bytes(voxels: u64) -> u64 {
    voxels.max(1) * BYTES_PER_VOXEL
}

/// An uninitialised AO volume of `dims` on the GPU.
pub fn buffer(gpu: &Gpu, dims: [usize; 3], name: &str) -> Result<Buffer> {
    Buffer::new(
        gpu,
        bytes((dims[0] * dims[1] * dims[2]) as u64),
        vk::BufferUsageFlags::STORAGE_BUFFER
            | vk::BufferUsageFlags::TRANSFER_SRC
            | vk::BufferUsageFlags::TRANSFER_DST,
        gpu_allocator::MemoryLocation::GpuOnly,
        name,
    )
}

/// A stored volume of `voxels` voxels read back to the host, as values in [0, 1].
pub fn read(buf: &Buffer, voxels: usize) -> Result<Vec<f32>> {
    let bytes = buf.read_back()?;
    Ok(
        bytemuck::cast_slice::<u8, u16>(&bytes[..voxels * BYTES_PER_VOXEL as usize])
            .iter()
            .map(|&q| unpack(q))
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packing_rounds_to_nearest_and_round_trips_every_word() {
        assert_eq!(pack(0.0), 0);
        assert_eq!(pack(1.0), 65535);
        assert_eq!(pack(-0.5), 0);
        assert_eq!(pack(2.0), 65535);
        for q in [0u16, 1, 2, 32767, 32768, 65534, 65535] {
            assert_eq!(pack(unpack(q)), q);
        }
        for a in [0.1f32, 0.25, 0.3333, 0.5, 0.9999] {
            assert!((unpack(pack(a)) - a).abs() <= ROUNDING + 1e-7, "{a}");
        }
    }
}
