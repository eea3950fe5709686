//! Buffers, images and compute pipelines. Each owns its memory and frees it on drop.

use super::{Gpu, GpuError, Result};
use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

pub struct Buffer {
    gpu: Gpu,
    pub raw: vk::Buffer,
    pub size: u64,
    /// Its device address, for the compute passes that reach storage buffers by address
    /// ([`ComputePipeline::with_addresses`]); 0 for a buffer that is not a storage buffer.
    pub address: vk::DeviceAddress,
    alloc: Option<Allocation>,
    /// Its share of [`super::Core::memory_in_use`].
    held: u64,
}

/// The most bytes an upload or a read-back stages at once: a whole volume's staging copy would
/// add a few bytes per voxel to the GPU's peak.
pub const STAGING_CHUNK: u64 = 8 << 20;

impl Buffer {
    pub fn new(
        gpu: &Gpu,
        size: u64,
        usage: vk::BufferUsageFlags,
        location: MemoryLocation,
        name: &str,
    ) -> Result<Buffer> {
        // Every storage buffer can be reached by address: that is how the volume passes read
        // buffers past `maxStorageBufferRange`, which limits a descriptor, not a buffer.
        // And read back (the CAO state keeps O on the host, read back from whichever pass
        // made it).
        let by_address = usage.contains(vk::BufferUsageFlags::STORAGE_BUFFER);
        let usage = if by_address {
            usage | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS | vk::BufferUsageFlags::TRANSFER_SRC
        } else {
            usage
        };
        // SAFETY: `raw` is created here and destroyed on each early return before anything else
        // sees it; `alloc` was made for `raw`'s own requirements, so binding it at its offset is
        // valid; from the bind on, `buffer` owns both and its Drop frees them once. The allocator
        // is behind its mutex.
        unsafe {
            let raw = gpu.device.create_buffer(
                &vk::BufferCreateInfo::default()
                    .size(size.max(4))
                    .usage(usage)
                    .sharing_mode(vk::SharingMode::EXCLUSIVE),
                None,
            )?;
            let requirements = gpu.device.get_buffer_memory_requirements(raw);
            let held = match gpu.reserve(name, requirements.size) {
                Ok(id) => id,
                Err(e) => {
                    gpu.device.destroy_buffer(raw, None);
                    return Err(e);
                }
            };
            let alloc = gpu
                .allocator
                .lock()
                .unwrap()
                .allocate(&AllocationCreateDesc {
                    name,
                    requirements,
                    location,
                    linear: true,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                });
            let alloc = match alloc {
                Ok(a) => a,
                Err(e) => {
                    gpu.release(held);
                    gpu.device.destroy_buffer(raw, None);
                    return Err(gpu.allocation_failed(name, requirements.size, e));
                }
            };
            let (memory, offset) = (alloc.memory(), alloc.offset());
            // Owned from here on: if binding fails, Drop frees the memory and the handle.
            let mut buffer = Buffer {
                gpu: gpu.clone(),
                raw,
                size,
                address: 0,
                alloc: Some(alloc),
                held,
            };
            gpu.device.bind_buffer_memory(raw, memory, offset)?;
            if by_address {
                buffer.address = gpu
                    .device
                    .get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(raw));
            }
            Ok(buffer)
        }
    }

    /// A host-visible buffer holding `data`.
    pub fn from_slice<T: bytemuck::Pod>(
        gpu: &Gpu,
        data: &[T],
        usage: vk::BufferUsageFlags,
        name: &str,
    ) -> Result<Buffer> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let mut b = Buffer::new(
            gpu,
            bytes.len() as u64,
            usage,
            MemoryLocation::CpuToGpu,
            name,
        )?;
        b.write(0, bytes)?;
        Ok(b)
    }

    /// A device-local buffer filled with `data` through a staging copy.
    pub fn device_local<T: bytemuck::Pod>(
        gpu: &Gpu,
        data: &[T],
        usage: vk::BufferUsageFlags,
        name: &str,
    ) -> Result<Buffer> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let b = Buffer::new(
            gpu,
            bytes.len() as u64,
            // Copyable both ways, so it can be read back or duplicated.
            usage | vk::BufferUsageFlags::TRANSFER_DST | vk::BufferUsageFlags::TRANSFER_SRC,
            MemoryLocation::GpuOnly,
            name,
        )?;
        // Buffer::new rounds a size up to 4 bytes: so does the staging and the copy.
        let mut padded = bytes.to_vec();
        let bytes = if bytes.len() < 4 {
            padded.resize(4, 0);
            &padded[..]
        } else {
            bytes
        };
        let mut staging = Buffer::new(
            gpu,
            (bytes.len() as u64).min(STAGING_CHUNK),
            vk::BufferUsageFlags::TRANSFER_SRC,
            MemoryLocation::CpuToGpu,
            "staging",
        )?;
        for (k, chunk) in bytes.chunks(STAGING_CHUNK as usize).enumerate() {
            staging.write(0, chunk)?;
            // SAFETY: `cmd` is recording (submit_and_wait); `staging` (TRANSFER_SRC) holds the
            // chunk from 0 and `b` (TRANSFER_DST) the whole of `bytes`, so the region lies in
            // both; both outlive the waited submission.
            gpu.submit_and_wait(|cmd| unsafe {
                let region = [vk::BufferCopy::default()
                    .dst_offset(k as u64 * STAGING_CHUNK)
                    .size(chunk.len() as u64)];
                gpu.device.cmd_copy_buffer(cmd, staging.raw, b.raw, &region);
            })?;
        }
        Ok(b)
    }

    /// A device-local copy of this buffer (same size and usage).
    pub fn duplicate(&self, usage: vk::BufferUsageFlags, name: &str) -> Result<Buffer> {
        let b = Buffer::new(
            &self.gpu,
            self.size,
            usage | vk::BufferUsageFlags::TRANSFER_DST,
            MemoryLocation::GpuOnly,
            name,
        )?;
        // SAFETY: `cmd` is recording; `b` (TRANSFER_DST) was created with `self.size.max(4)` bytes
        // like `self`, both outlive the waited submission; `self` must have been made with
        // TRANSFER_SRC, which its owners do (Buffer does not record its usage).
        self.gpu.submit_and_wait(|cmd| unsafe {
            let region = [vk::BufferCopy::default().size(self.size.max(4))];
            self.gpu
                .device
                .cmd_copy_buffer(cmd, self.raw, b.raw, &region);
        })?;
        Ok(b)
    }

    /// Writes `bytes` at `offset` of a host-visible buffer; past its end is an error, not a panic.
    pub fn write(&mut self, offset: usize, bytes: &[u8]) -> Result<()> {
        let size = self.size as usize;
        let slice = self
            .alloc
            .as_mut()
            .and_then(|a| a.mapped_slice_mut())
            .ok_or_else(|| GpuError::Other("buffer is not host visible".into()))?;
        let end = offset
            .checked_add(bytes.len())
            .filter(|&e| e <= size.min(slice.len()))
            .ok_or_else(|| {
                GpuError::Other(format!(
                    "writing {} bytes at offset {offset} overruns a buffer of {size} bytes",
                    bytes.len()
                ))
            })?;
        slice[offset..end].copy_from_slice(bytes);
        Ok(())
    }

    /// The mapped bytes of a host-visible buffer.
    pub fn mapped(&self) -> Result<&[u8]> {
        self.alloc
            .as_ref()
            .and_then(|a| a.mapped_slice())
            .map(|s| &s[..self.size as usize])
            .ok_or_else(|| GpuError::Other("buffer is not host visible".into()))
    }

    /// Copies the whole buffer back to the host (through a staging buffer).
    pub fn read_back(&self) -> Result<Vec<u8>> {
        let size = self.size.max(4);
        let staging = Buffer::new(
            &self.gpu,
            size.min(STAGING_CHUNK),
            vk::BufferUsageFlags::TRANSFER_DST,
            MemoryLocation::GpuToCpu,
            "readback",
        )?;
        let mut out = Vec::with_capacity(size as usize);
        for at in (0..size).step_by(STAGING_CHUNK as usize) {
            let len = (size - at).min(STAGING_CHUNK);
            // SAFETY: `cmd` is recording; the region lies in `self` (`at + len <= size`, which
            // Buffer::new rounded up to 4) and in `staging` (at least `len` bytes from 0); both
            // outlive the waited submission; `self` must have been made with TRANSFER_SRC, which
            // its owners do (Buffer does not record its usage).
            self.gpu.submit_and_wait(|cmd| unsafe {
                let region = [vk::BufferCopy::default().src_offset(at).size(len)];
                self.gpu
                    .device
                    .cmd_copy_buffer(cmd, self.raw, staging.raw, &region);
            })?;
            out.extend_from_slice(&staging.mapped()?[..len as usize]);
        }
        out.truncate(self.size as usize);
        Ok(out)
    }

    pub fn descriptor(&self) -> vk::DescriptorBufferInfo {
        vk::DescriptorBufferInfo::default()
            .buffer(self.raw)
            .offset(0)
            .range(vk::WHOLE_SIZE)
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        // SAFETY: the allocation and handle are this buffer's own, freed once (`take`); Buffer does
        // not wait, so its owner drops it only once no submitted work uses it (the frame loop
        // retires a frame before what it reads goes; one-shot passes wait in submit_and_wait).
        unsafe {
            if let Some(a) = self.alloc.take() {
                let _ = self.gpu.allocator.lock().unwrap().free(a);
            }
            self.gpu.release(self.held);
            self.gpu.device.destroy_buffer(self.raw, None);
        }
    }
}

#[derive(Clone, Debug)]
pub struct ImageDesc {
    pub image_type: vk::ImageType,
    pub view_type: vk::ImageViewType,
    pub format: vk::Format,
    pub extent: vk::Extent3D,
    pub layers: u32,
    pub usage: vk::ImageUsageFlags,
    pub aspect: vk::ImageAspectFlags,
}

pub struct Image {
    gpu: Gpu,
    pub raw: vk::Image,
    pub view: vk::ImageView,
    /// One 2D view per array layer (for rendering into a single layer), when layers > 1.
    pub layer_views: Vec<vk::ImageView>,
    pub desc: ImageDesc,
    alloc: Option<Allocation>,
    /// Its share of [`super::Core::memory_in_use`].
    held: u64,
}

impl Image {
    pub fn new(gpu: &Gpu, desc: ImageDesc, name: &str) -> Result<Image> {
        // SAFETY: as in Buffer::new: `raw` is destroyed on every early return before anything else
        // sees it, `alloc` was made for its requirements, and from the bind on `image` owns memory,
        // image and views (its Drop destroys what exists; a null view is a no-op). Every view names
        // `raw` with a range inside `desc`.
        unsafe {
            let raw = gpu.device.create_image(
                &vk::ImageCreateInfo::default()
                    .image_type(desc.image_type)
                    .format(desc.format)
                    .extent(desc.extent)
                    .mip_levels(1)
                    .array_layers(desc.layers)
                    .samples(vk::SampleCountFlags::TYPE_1)
                    .tiling(vk::ImageTiling::OPTIMAL)
                    .usage(desc.usage)
                    .sharing_mode(vk::SharingMode::EXCLUSIVE)
                    .initial_layout(vk::ImageLayout::UNDEFINED),
                None,
            )?;
            let requirements = gpu.device.get_image_memory_requirements(raw);
            let held = match gpu.reserve(name, requirements.size) {
                Ok(id) => id,
                Err(e) => {
                    gpu.device.destroy_image(raw, None);
                    return Err(e);
                }
            };
            let alloc = match gpu
                .allocator
                .lock()
                .unwrap()
                .allocate(&AllocationCreateDesc {
                    name,
                    requirements,
                    location: MemoryLocation::GpuOnly,
                    linear: false,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                }) {
                Ok(a) => a,
                Err(e) => {
                    gpu.release(held);
                    gpu.device.destroy_image(raw, None);
                    return Err(gpu.allocation_failed(name, requirements.size, e));
                }
            };
            let (memory, offset) = (alloc.memory(), alloc.offset());
            // Owned from here on: if binding or a view fails, Drop frees what exists (destroying
            // a null view is a no-op in Vulkan).
            let mut image = Image {
                gpu: gpu.clone(),
                raw,
                view: vk::ImageView::null(),
                layer_views: Vec::new(),
                desc: desc.clone(),
                alloc: Some(alloc),
                held,
            };
            gpu.device.bind_image_memory(raw, memory, offset)?;
            image.view = gpu.device.create_image_view(
                &vk::ImageViewCreateInfo::default()
                    .image(raw)
                    .view_type(desc.view_type)
                    .format(desc.format)
                    .subresource_range(Self::range_of(&desc)),
                None,
            )?;
            if desc.layers > 1 {
                for layer in 0..desc.layers {
                    let range = Self::range_of(&desc).base_array_layer(layer).layer_count(1);
                    image.layer_views.push(
                        gpu.device.create_image_view(
                            &vk::ImageViewCreateInfo::default()
                                .image(raw)
                                .view_type(vk::ImageViewType::TYPE_2D)
                                .format(desc.format)
                                .subresource_range(range),
                            None,
                        )?,
                    );
                }
            }
            Ok(image)
        }
    }

    fn range_of(desc: &ImageDesc) -> vk::ImageSubresourceRange {
        vk::ImageSubresourceRange::default()
            .aspect_mask(desc.aspect)
            .base_mip_level(0)
            .level_count(1)
            .base_array_layer(0)
            .layer_count(desc.layers)
    }

    pub fn subresource_range(&self) -> vk::ImageSubresourceRange {
        Self::range_of(&self.desc)
    }

    /// A layout transition of the whole image that also orders all earlier memory writes.
    pub fn transition(&self, cmd: vk::CommandBuffer, from: vk::ImageLayout, to: vk::ImageLayout) {
        cmd_image_barrier(
            &self.gpu.device,
            cmd,
            self.raw,
            self.subresource_range(),
            from,
            to,
        );
    }

    fn layers_all(&self) -> vk::ImageSubresourceLayers {
        vk::ImageSubresourceLayers::default()
            .aspect_mask(self.desc.aspect)
            .mip_level(0)
            .base_array_layer(0)
            .layer_count(self.desc.layers)
    }

    /// Records a copy of a tightly packed buffer into the whole image (layout TRANSFER_DST).
    pub fn cmd_copy_from(&self, cmd: vk::CommandBuffer, src: &Buffer) {
        self.cmd_copy_from_offset(cmd, src, 0)
    }

    /// [`Image::cmd_copy_from`] starting `offset` bytes into `src`.
    pub fn cmd_copy_from_offset(&self, cmd: vk::CommandBuffer, src: &Buffer, offset: u64) {
        self.cmd_copy_slices_from(cmd, src, offset, 0..self.desc.extent.depth);
    }

    /// Records a copy of z-slices `z` of the image (layout TRANSFER_DST_OPTIMAL) from `src`,
    /// where they lie tightly packed from `offset` on (the callers size it so).
    fn cmd_copy_slices_from(
        &self,
        cmd: vk::CommandBuffer,
        src: &Buffer,
        offset: u64,
        z: std::ops::Range<u32>,
    ) {
        let e = self.desc.extent;
        let region = [vk::BufferImageCopy::default()
            .buffer_offset(offset)
            .image_subresource(self.layers_all())
            .image_offset(vk::Offset3D {
                x: 0,
                y: 0,
                z: z.start as i32,
            })
            .image_extent(vk::Extent3D {
                depth: z.end - z.start,
                ..e
            })];
        // SAFETY: `cmd` is recording with the image in TRANSFER_DST_OPTIMAL (this method's
        // contract); `src` holds the slices, tightly packed, from `offset` on (the callers
        // size it so).
        unsafe {
            self.gpu.device.cmd_copy_buffer_to_image(
                cmd,
                src.raw,
                self.raw,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                &region,
            );
        }
    }

    /// Records a copy of the whole image (layout TRANSFER_SRC) into a tightly packed buffer.
    pub fn cmd_copy_to(&self, cmd: vk::CommandBuffer, dst: &Buffer) {
        let region = [vk::BufferImageCopy::default()
            .image_subresource(self.layers_all())
            .image_extent(self.desc.extent)];
        // SAFETY: `cmd` is recording with the image in TRANSFER_SRC_OPTIMAL (this method's
        // contract); `dst` has room for the whole image tightly packed (the callers size it so).
        unsafe {
            self.gpu.device.cmd_copy_image_to_buffer(
                cmd,
                self.raw,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                dst.raw,
                &region,
            );
        }
    }

    /// Uploads tightly packed texels and leaves the image in `final_layout`, staging at most
    /// `STAGING_CHUNK` bytes (or one z-slice) at a time.
    pub fn upload(&self, bytes: &[u8], final_layout: vk::ImageLayout) -> Result<()> {
        let e = self.desc.extent;
        let texels = [e.width, e.height, e.depth, self.desc.layers]
            .iter()
            .map(|&n| n as usize)
            .product::<usize>();
        if texels == 0 || bytes.is_empty() || bytes.len() % texels != 0 {
            return Err(GpuError::Other(format!(
                "{} bytes do not fill a {}x{}x{} image of {} layer(s) with whole texels",
                bytes.len(),
                e.width,
                e.height,
                e.depth,
                self.desc.layers
            )));
        }
        // Every side is at least 1 and the bytes whole texels (above): a slice is not empty.
        let slice = bytes.len() / e.depth as usize;
        let slices = (STAGING_CHUNK as usize / slice).clamp(1, e.depth as usize);
        let mut staging = Buffer::new(
            &self.gpu,
            (slice * slices) as u64,
            vk::BufferUsageFlags::TRANSFER_SRC,
            MemoryLocation::CpuToGpu,
            "staging",
        )?;
        let last = e.depth.div_ceil(slices as u32);
        for (k, chunk) in bytes.chunks(slice * slices).enumerate() {
            staging.write(0, chunk)?;
            let z0 = (k * slices) as u32;
            let z = z0..z0 + (chunk.len() / slice) as u32;
            self.gpu.submit_and_wait(|cmd| {
                if k == 0 {
                    self.transition(
                        cmd,
                        vk::ImageLayout::UNDEFINED,
                        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    );
                }
                // The image is in TRANSFER_DST_OPTIMAL (made so in the first chunk's
                // submission); `staging` holds the chunk's slices tightly packed from 0.
                self.cmd_copy_slices_from(cmd, &staging, 0, z);
                if k as u32 + 1 == last {
                    self.transition(cmd, vk::ImageLayout::TRANSFER_DST_OPTIMAL, final_layout);
                }
            })?;
        }
        Ok(())
    }
}

impl Drop for Image {
    fn drop(&mut self) {
        // SAFETY: views, allocation and image are this image's own, each destroyed once, the
        // views before their image; Image does not wait, so its owner drops it only once no
        // submitted work uses it (as for Buffer).
        unsafe {
            self.gpu.device.destroy_image_view(self.view, None);
            for v in self.layer_views.drain(..) {
                self.gpu.device.destroy_image_view(v, None);
            }
            if let Some(a) = self.alloc.take() {
                let _ = self.gpu.allocator.lock().unwrap().free(a);
            }
            self.gpu.release(self.held);
            self.gpu.device.destroy_image(self.raw, None);
        }
    }
}

/// A linear blit of the colour layers `layers` (first, count) of `src` (TRANSFER_SRC_OPTIMAL,
/// `src_size` pixels) onto the rectangle `dst_rect` (corners) of the same number of layers of
/// `dst` (TRANSFER_DST_OPTIMAL): both eyes into a headset's array image, or one eye into a window.
pub fn cmd_blit_color(
    device: &ash::Device,
    cmd: vk::CommandBuffer,
    src: vk::Image,
    (first, count): (u32, u32),
    src_size: (u32, u32),
    dst: vk::Image,
    dst_rect: [(i32, i32); 2],
) {
    let layers = |base| {
        vk::ImageSubresourceLayers::default()
            .aspect_mask(vk::ImageAspectFlags::COLOR)
            .base_array_layer(base)
            .layer_count(count)
    };
    let corner = |(x, y): (i32, i32), z| vk::Offset3D { x, y, z };
    let region = [vk::ImageBlit::default()
        .src_subresource(layers(first))
        .src_offsets([
            vk::Offset3D::default(),
            corner((src_size.0 as i32, src_size.1 as i32), 1),
        ])
        .dst_subresource(layers(0))
        .dst_offsets([corner(dst_rect[0], 0), corner(dst_rect[1], 1)])];
    // SAFETY: `cmd` is recording on `device`, `src` and `dst` are live images of it in the
    // TRANSFER_SRC / TRANSFER_DST layouts with the layers and rectangles named (this function's
    // contract).
    unsafe {
        device.cmd_blit_image(
            cmd,
            src,
            vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
            dst,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            &region,
            vk::Filter::LINEAR,
        );
    }
}

/// A layout transition of `range` of any image (also swapchain images, which no [`Image`] owns)
/// that orders all earlier memory writes before all later accesses.
pub fn cmd_image_barrier(
    device: &ash::Device,
    cmd: vk::CommandBuffer,
    image: vk::Image,
    range: vk::ImageSubresourceRange,
    from: vk::ImageLayout,
    to: vk::ImageLayout,
) {
    let b = [vk::ImageMemoryBarrier2::default()
        .src_stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
        .src_access_mask(vk::AccessFlags2::MEMORY_WRITE)
        .dst_stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
        .dst_access_mask(vk::AccessFlags2::MEMORY_READ | vk::AccessFlags2::MEMORY_WRITE)
        .old_layout(from)
        .new_layout(to)
        .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .image(image)
        .subresource_range(range)];
    // SAFETY: `cmd` is recording on `device`; `image` is a live image of it, `range` lies inside it
    // and `from` is its layout there (or UNDEFINED) (this function's contract).
    unsafe {
        device.cmd_pipeline_barrier2(
            cmd,
            &vk::DependencyInfo::default().image_memory_barriers(&b),
        )
    };
}

/// A compute pipeline whose descriptors are pushed (VK_KHR_push_descriptor), one set, with an
/// optional push-constant block. A pass over whole volumes reaches its volume-sized buffers by
/// device address instead, at the start of the push constants
/// ([`ComputePipeline::with_addresses`]): `maxStorageBufferRange` limits a descriptor (128 MiB
/// on lavapipe, less than one f32 copy of a routine chest CT), not an address.
pub struct ComputePipeline {
    gpu: Gpu,
    pub pipeline: vk::Pipeline,
    pub layout: vk::PipelineLayout,
    pub set_layout: vk::DescriptorSetLayout,
    /// Per buffer, in binding order: whether it is reached by address (else by descriptor).
    reach: Vec<Reach>,
    /// The push constants' size in the layout: the addresses' and the pass's own block.
    push_bytes: u32,
}

/// How a compute pass reaches one of its storage buffers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reach {
    /// A pushed descriptor at its binding: small tables.
    Descriptor,
    /// Its device address in the push constants: the volume-sized buffers.
    Address,
}

/// Bytes that `n` buffer addresses take at the start of a pass's push constants: 8 each, rounded
/// up to 16 so that the pass's own block starts aligned (a shader with an odd count declares a
/// `uvec2` pad after its references).
pub fn address_bytes(n: usize) -> u32 {
    (8 * n as u32).next_multiple_of(16)
}

/// Map entries of `n` u32 specialization constants, constant_id 0.. in order.
pub fn specialization_entries(n: usize) -> Vec<vk::SpecializationMapEntry> {
    (0..n as u32)
        .map(|i| {
            vk::SpecializationMapEntry::default()
                .constant_id(i)
                .offset(4 * i)
                .size(4)
        })
        .collect()
}

/// Creates a shader module from SPIR-V bytes (as built by build.rs).
pub fn shader_module(gpu: &Gpu, spv: &[u8]) -> Result<vk::ShaderModule> {
    let words = ash::util::read_spv(&mut std::io::Cursor::new(spv))
        .map_err(|e| GpuError::Other(format!("bad SPIR-V: {e}")))?;
    // SAFETY: `words` is SPIR-V that read_spv checked and aligned (glslc's output, from build.rs);
    // the info borrows it only for the call.
    Ok(unsafe {
        gpu.device
            .create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None)?
    })
}

/// A push-descriptor set layout with one descriptor per binding, in order.
pub fn push_set_layout(
    gpu: &Gpu,
    bindings: &[vk::DescriptorType],
    stages: vk::ShaderStageFlags,
) -> Result<vk::DescriptorSetLayout> {
    let bindings: Vec<_> = bindings.iter().map(|&t| Some(t)).collect();
    sparse_set_layout(gpu, &bindings, stages)
}

/// [`push_set_layout`] with no descriptor at the bindings that are None.
pub fn sparse_set_layout(
    gpu: &Gpu,
    bindings: &[Option<vk::DescriptorType>],
    stages: vk::ShaderStageFlags,
) -> Result<vk::DescriptorSetLayout> {
    let b: Vec<_> = bindings
        .iter()
        .enumerate()
        .filter_map(|(i, t)| {
            t.map(|t| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(i as u32)
                    .descriptor_type(t)
                    .descriptor_count(1)
                    .stage_flags(stages)
            })
        })
        .collect();
    // SAFETY: the info borrows `b`, which outlives the call; VK_KHR_push_descriptor, which
    // PUSH_DESCRIPTOR_KHR needs, is enabled on every device (Gpu::create).
    Ok(unsafe {
        gpu.device.create_descriptor_set_layout(
            &vk::DescriptorSetLayoutCreateInfo::default()
                .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
                .bindings(&b),
            None,
        )?
    })
}

impl ComputePipeline {
    /// A pass over volumes: its storage buffers (bindings 0..n) reached as `reach` says, the
    /// addresses first in the push constants (see [`address_bytes`]), then its own
    /// `push_constant_bytes`; the shader's specialization constants, constant_id 0.. (u32
    /// each): a loop bounded by one is unrolled, and an array it sizes can be held in registers
    /// (on a CPU renderer an array in memory is read and written lane by lane).
    pub fn with_addresses(
        gpu: &Gpu,
        spv: &[u8],
        reach: &[Reach],
        push_constant_bytes: u32,
        constants: &[u32],
    ) -> Result<ComputePipeline> {
        let addresses = reach.iter().filter(|&&r| r == Reach::Address).count();
        let bytes = address_bytes(addresses) + push_constant_bytes;
        let limit = gpu.limits.max_push_constants_size;
        if bytes > limit {
            return Err(GpuError::Other(format!(
                "a compute pass needs {bytes} bytes of push constants ({addresses} buffer \
                 addresses and its own {push_constant_bytes}); the device allows {limit}"
            )));
        }
        let descriptors: Vec<Option<vk::DescriptorType>> = reach
            .iter()
            .map(|r| (*r == Reach::Descriptor).then_some(vk::DescriptorType::STORAGE_BUFFER))
            .collect();
        ComputePipeline::build(gpu, spv, &descriptors, bytes, reach.to_vec(), constants)
    }

    pub fn new(
        gpu: &Gpu,
        spv: &[u8],
        bindings: &[vk::DescriptorType],
        push_constant_bytes: u32,
    ) -> Result<ComputePipeline> {
        let reach = vec![Reach::Descriptor; bindings.len()];
        let bindings: Vec<_> = bindings.iter().map(|&t| Some(t)).collect();
        ComputePipeline::build(gpu, spv, &bindings, push_constant_bytes, reach, &[])
    }

    /// The pipeline with a descriptor at each binding that has a type (the others are absent),
    /// its buffers bound as `reach` says.
    fn build(
        gpu: &Gpu,
        spv: &[u8],
        bindings: &[Option<vk::DescriptorType>],
        push_constant_bytes: u32,
        reach: Vec<Reach>,
        constants: &[u32],
    ) -> Result<ComputePipeline> {
        // SAFETY: each create call borrows locals that outlive it; the module is destroyed only
        // once the pipeline was created from it (allowed); on success the returned pipeline owns
        // the layouts and pipeline and its Drop destroys them.
        unsafe {
            let set_layout = sparse_set_layout(gpu, bindings, vk::ShaderStageFlags::COMPUTE)?;
            let ranges = [vk::PushConstantRange::default()
                .stage_flags(vk::ShaderStageFlags::COMPUTE)
                .size(push_constant_bytes)];
            let set_layouts = [set_layout];
            let mut li = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
            if push_constant_bytes > 0 {
                li = li.push_constant_ranges(&ranges);
            }
            let layout = gpu.device.create_pipeline_layout(&li, None)?;
            let module = shader_module(gpu, spv)?;
            let entries = specialization_entries(constants.len());
            let specialization = vk::SpecializationInfo::default()
                .map_entries(&entries)
                .data(bytemuck::cast_slice(constants));
            let stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .module(module)
                .name(c"main")
                .specialization_info(&specialization);
            let info = [vk::ComputePipelineCreateInfo::default()
                .stage(stage)
                .layout(layout)];
            let res = gpu
                .device
                .create_compute_pipelines(vk::PipelineCache::null(), &info, None);
            gpu.device.destroy_shader_module(module, None);
            let pipeline = res.map_err(|(_, e)| e)?[0];
            Ok(ComputePipeline {
                gpu: gpu.clone(),
                pipeline,
                layout,
                set_layout,
                reach,
                push_bytes: push_constant_bytes,
            })
        }
    }

    /// Binds the pipeline, pushes the storage buffers (bindings 0..n: descriptors, and the
    /// addresses before `push`) and the push constants.
    pub fn bind(&self, cmd: vk::CommandBuffer, buffers: &[&Buffer], push: &[u8]) {
        assert_eq!(
            buffers.len(),
            self.reach.len(),
            "a compute pass bound with the wrong buffer count"
        );
        let by = |r: Reach| {
            buffers
                .iter()
                .zip(&self.reach)
                .enumerate()
                .filter(move |(_, (_, &x))| x == r)
        };
        let mut bytes: Vec<u8> = by(Reach::Address)
            .flat_map(|(_, (b, _))| b.address.to_le_bytes())
            .collect();
        bytes.resize(address_bytes(bytes.len() / 8) as usize, 0);
        bytes.extend_from_slice(push);
        // A block of another size than the layout's leaves the shader reading stale words.
        assert_eq!(
            bytes.len(),
            self.push_bytes as usize,
            "a compute pass bound with push constants of the wrong size"
        );
        let infos: Vec<(u32, [vk::DescriptorBufferInfo; 1])> = by(Reach::Descriptor)
            .map(|(i, (b, _))| (i as u32, [b.descriptor()]))
            .collect();
        let writes: Vec<_> = infos
            .iter()
            .map(|(i, info)| {
                vk::WriteDescriptorSet::default()
                    .dst_binding(*i)
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .buffer_info(info)
            })
            .collect();
        // SAFETY: `cmd` is recording (the caller's contract); `writes` give a storage buffer at
        // exactly the Descriptor bindings of the set layout, live buffers the caller keeps until
        // the work finished; the push bytes start at 0: the addresses, then `push`, which the
        // callers give the size of the pass's own block that the layout's range was built with.
        unsafe {
            let d = &self.gpu.device;
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, self.pipeline);
            if !writes.is_empty() {
                self.gpu.push_descriptor.cmd_push_descriptor_set(
                    cmd,
                    vk::PipelineBindPoint::COMPUTE,
                    self.layout,
                    0,
                    &writes,
                );
            }
            if !bytes.is_empty() {
                d.cmd_push_constants(cmd, self.layout, vk::ShaderStageFlags::COMPUTE, 0, &bytes);
            }
        }
    }

    pub fn dispatch(&self, cmd: vk::CommandBuffer, groups: [u32; 3]) {
        // SAFETY: `cmd` is recording with this pipeline bound by `bind` (the caller's contract).
        unsafe {
            self.gpu
                .device
                .cmd_dispatch(cmd, groups[0], groups[1], groups[2])
        }
    }
}

impl Drop for ComputePipeline {
    fn drop(&mut self) {
        // SAFETY: the handles are this pipeline's own, destroyed once; its owners drop it only
        // after the work recorded with it finished (FrameLoop::drop flushes first, one-shot passes
        // wait in submit_and_wait).
        unsafe {
            self.gpu.device.destroy_pipeline(self.pipeline, None);
            self.gpu.device.destroy_pipeline_layout(self.layout, None);
            self.gpu
                .device
                .destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}
