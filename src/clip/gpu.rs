//! Clip maps on the GPU: the clip camera's depth peels rendered with the rasterisation pipeline,
//! and the dilation maps by a compute shader (the paper's Sect. 3.4, steps 1-3). The result is
//! the same [`ClipMap`] the CPU reference ([`ClipMap::build`]) gives, read back to the host (the
//! maps are small: res^2 * 32 bytes) so CAO uploads them as before.
//!
//! Per shape, one submission:
//! 1. Front peels (shaders/clip_peel.{vert,frag}): an orthographic camera over local x, y in
//!    [-extent, extent] looking along local +Z, culling off (winding does not matter), one pass
//!    per peel, one sample per texel at the CPU's sample point ([`SAMPLE_OFFSET`]: the projection
//!    is shifted so that pixel centres land there). Each crossing is a fragment keyed by (depth,
//!    triangle); peel k holds the smallest key beyond peel k-1's: the fragment shader discards
//!    keys up to the previous layer's, the depth test (LESS, cleared to 1 each pass) keeps the
//!    nearest of the rest. Keying by triangle too keeps two crossings of equal depth (the two
//!    sheets at a silhouette fold) apart, as the CPU counts them. Four peels: two intervals.
//! 2. The farthest crossing (same shaders, depth test GREATER, depth cleared to 0): where a ray
//!    crosses the surface more than four times, the second interval hulls everything from the
//!    third crossing to this one, as the CPU version does. (No fifth to eighth peel: the CPU keeps
//!    two intervals too, and the hull needs only the last crossing.)
//! 3. shaders/clip_pair.comp pairs the crossings into the clip map with the CPU's rule
//!    ([`super::intervals`]): one crossing, or the odd third of three, is a grazing ray's and is
//!    dropped; five or more keep their last in the hull. CPU and GPU agree on every count.
//! 4. shaders/clip_dilate_rows.comp and clip_dilate.comp: the dilation map from the clip map,
//!    with the CPU reference's sphere kernel ([`DilationKernel`]), so the same clip map gives the
//!    same dilation, bit for bit.
//!
//! What still differs from the CPU reference: the rasteriser snaps vertices to its sub-pixel grid
//! (limits.subPixelPrecisionBits, 8 on common devices: 1/256 texel) before deciding coverage and
//! interpolates z with its own barycentrics, and its fill rule for samples exactly on an edge is
//! its own. So a texel whose sample point lies within about 1/256 texel of a silhouette may be
//! covered on one side only, and z differs by up to the triangle's slope times 1/512 texel (half
//! a snap step): most near a silhouette, where the surface is steep. On lavapipe, built-in shapes
//! at 64^2 and 128^2: no texel (sphere, cube, cylinder, torus) or one (the torus on its side) of
//! several thousand covered differs in its interval count, and depths differ by at most 6.7e-5
//! tool units (at the sphere's rim at 128^2), 5e-6 on the other shapes. Crossings closer together
//! than the depth's precision (about 1e-7 of the mesh's z range) are ordered by triangle rather
//! than by z, then sorted.

use super::{z_range, ClipMap, DilationKernel, TriMesh, EMPTY_IN, EMPTY_OUT, SAMPLE_OFFSET};
use crate::gpu::{pipeline, push_set_layout, Buffer, ComputePipeline, Gpu, GpuError};
use crate::gpu::{Image, ImageDesc};
use ash::vk;
use gpu_allocator::MemoryLocation;

/// Front peels per texel: two depth intervals.
pub const PEELS: usize = 4;
/// Layers of the peel image: 0 holds EMPTY_OUT (what the first peel must be beyond), 1..=PEELS
/// the front peels, the last the farthest crossing.
const LAYERS: usize = PEELS + 2;
const FARTHEST: usize = LAYERS - 1;
/// The peels store (tool-local z, triangle) exactly. RGBA rather than RG: rg32f storage images
/// need the shaderStorageImageExtendedFormats feature, rgba32f does not.
const PEEL_FORMAT: vk::Format = vk::Format::R32G32B32A32_SFLOAT;
/// Triangles are numbered in a float channel, exact up to 2^24.
pub const MAX_TRIANGLES: usize = 1 << 24;
const DEPTH_FORMAT: vk::Format = vk::Format::D32_SFLOAT;
/// Workgroup size (x and y) of clip_pair.comp and clip_dilate.comp.
const GROUP: u32 = 8;

#[derive(Debug, thiserror::Error)]
pub enum ClipGpuError {
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("clip-map resolution {res} exceeds what {device} can render ({max} texels per side)")]
    Resolution {
        res: usize,
        max: u32,
        device: String,
    },
    #[error("clip mesh triangle {triangle} refers to vertex {index}, but there are {vertices}")]
    BadIndex {
        triangle: usize,
        index: u32,
        vertices: usize,
    },
    #[error("clip mesh has {0} triangles; the GPU peels number at most 2^24")]
    TooManyTriangles(usize),
    #[error("a clip map of resolution {res} has {expected} texels, not {got}")]
    MapSize {
        res: usize,
        expected: usize,
        got: usize,
    },
}

/// CAO reports every failure as a [`GpuError`]; the clip-specific ones keep their message.
impl From<ClipGpuError> for GpuError {
    fn from(e: ClipGpuError) -> GpuError {
        match e {
            ClipGpuError::Gpu(e) => e,
            e => GpuError::Other(e.to_string()),
        }
    }
}

pub type Result<T> = std::result::Result<T, ClipGpuError>;

/// Push constants of clip_peel.{vert,frag}.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PeelPush {
    /// [`SAMPLE_OFFSET`] in local units.
    shift: [f32; 2],
    inv_extent: f32,
    z_lo: f32,
    z_scale: f32,
    /// 0: front peel, 1: farthest crossing.
    mode: u32,
}
crate::gpu::glsl_layout!(PeelPush, 24, shift: 0, inv_extent: 8, z_lo: 12, z_scale: 16, mode: 20);

/// What every peel pass of one build draws with: the peel layers and their depth attachment,
/// the tools' `count` corners, at `res` x `res`.
#[derive(Clone, Copy)]
struct PeelLayers<'a> {
    peels: &'a Image,
    depth: &'a Image,
    corners: &'a Buffer,
    count: u32,
    res: usize,
}

/// Push constants of clip_pair.comp (res only) and clip_dilate.comp.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct GridPush {
    res: i32,
    reach: i32,
}
crate::gpu::glsl_layout!(GridPush, 8, res: 0, reach: 4);

/// Builds clip maps on the GPU: pipelines made once, images and buffers per map (a map is built
/// once per shape and radius, and cached by CAO).
pub struct ClipMapGpu {
    gpu: Gpu,
    peel_set_layout: vk::DescriptorSetLayout,
    peel_layout: vk::PipelineLayout,
    /// Depth test LESS: the front peels.
    front: vk::Pipeline,
    /// Depth test GREATER: the farthest crossing.
    back: vk::Pipeline,
    pair: ComputePipeline,
    /// Per row, the span of texels holding an interval (what the dilation visits).
    rows: ComputePipeline,
    dilate: ComputePipeline,
}

impl ClipMapGpu {
    pub fn new(gpu: &Gpu) -> Result<ClipMapGpu> {
        let pair = ComputePipeline::new(
            gpu,
            include_bytes!(concat!(env!("OUT_DIR"), "/clip_pair.comp.spv")),
            &[
                vk::DescriptorType::STORAGE_IMAGE,
                vk::DescriptorType::STORAGE_BUFFER,
            ],
            std::mem::size_of::<GridPush>() as u32,
        )?;
        let rows = ComputePipeline::new(
            gpu,
            include_bytes!(concat!(env!("OUT_DIR"), "/clip_dilate_rows.comp.spv")),
            &[vk::DescriptorType::STORAGE_BUFFER; 2],
            std::mem::size_of::<GridPush>() as u32,
        )?;
        let dilate = ComputePipeline::new(
            gpu,
            include_bytes!(concat!(env!("OUT_DIR"), "/clip_dilate.comp.spv")),
            &[vk::DescriptorType::STORAGE_BUFFER; 4],
            std::mem::size_of::<GridPush>() as u32,
        )?;
        let stages = vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT;
        let peel_set_layout = push_set_layout(
            gpu,
            &[
                vk::DescriptorType::STORAGE_BUFFER,
                vk::DescriptorType::STORAGE_IMAGE,
            ],
            stages,
        )?;
        let d = &gpu.device;
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(stages)
            .size(std::mem::size_of::<PeelPush>() as u32)];
        // SAFETY: the info borrows `peel_set_layout` and `ranges`, which outlive the call.
        let peel_layout = match unsafe {
            d.create_pipeline_layout(
                &vk::PipelineLayoutCreateInfo::default()
                    .set_layouts(&[peel_set_layout])
                    .push_constant_ranges(&ranges),
                None,
            )
        } {
            Ok(l) => l,
            Err(e) => {
                // SAFETY: the set layout was just made; nothing uses it yet.
                unsafe { d.destroy_descriptor_set_layout(peel_set_layout, None) };
                return Err(GpuError::from(e).into());
            }
        };
        let pipelines = peel_pipelines(gpu, peel_layout);
        let [front, back] = match pipelines {
            Ok(p) => p,
            Err(e) => {
                // SAFETY: both layouts were just made, and the failed pipeline creation left
                // nothing using them.
                unsafe {
                    d.destroy_pipeline_layout(peel_layout, None);
                    d.destroy_descriptor_set_layout(peel_set_layout, None);
                }
                return Err(e.into());
            }
        };
        Ok(ClipMapGpu {
            gpu: gpu.clone(),
            peel_set_layout,
            peel_layout,
            front,
            back,
            pair,
            rows,
            dilate,
        })
    }

    /// The clip map of `mesh` at `res` texels per side (at least 8, as on the CPU) with its
    /// dilation for `radius` (tool-local units): the GPU counterpart of [`ClipMap::build`].
    pub fn build(&self, mesh: &TriMesh, res: usize, radius: f32) -> Result<ClipMap> {
        let res = res.max(8);
        self.check_resolution(res)?;
        let extent = ClipMap::extent_for(mesh.half_extent(), res, radius);
        let texel = 2.0 * extent / res as f32;
        let corners = triangle_corners(mesh)?;
        let (zmin, zmax) = if corners.is_empty() {
            (0.0, 0.0) // nothing is drawn; any valid mapping will do
        } else {
            corners.iter().fold((f32::MAX, f32::MIN), |(lo, hi), c| {
                (lo.min(c[2]), hi.max(c[2]))
            })
        };
        // Depth = z mapped into [1/4, 3/4]: nothing is clipped by the near and far planes, and
        // the clear values (1 for the front peels, 0 for the farthest) are never a fragment's.
        let margin = 0.5 * (zmax - zmin).max(1e-3);
        let (z_lo, z_hi) = (zmin - margin, zmax + margin);
        let push = PeelPush {
            shift: (SAMPLE_OFFSET * texel).to_array(),
            inv_extent: 1.0 / extent,
            z_lo,
            z_scale: 1.0 / (z_hi - z_lo),
            mode: 0,
        };

        let gpu = &self.gpu;
        let n = res * res;
        let texels_bytes = (n * 16) as u64;
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
        let image = |format, layers: usize, usage, aspect, name| {
            Image::new(
                gpu,
                ImageDesc {
                    image_type: vk::ImageType::TYPE_2D,
                    view_type: if layers > 1 {
                        vk::ImageViewType::TYPE_2D_ARRAY
                    } else {
                        vk::ImageViewType::TYPE_2D
                    },
                    format,
                    extent: vk::Extent3D {
                        width: res as u32,
                        height: res as u32,
                        depth: 1,
                    },
                    layers: layers as u32,
                    usage,
                    aspect,
                },
                name,
            )
        };
        let peels = image(
            PEEL_FORMAT,
            LAYERS,
            vk::ImageUsageFlags::COLOR_ATTACHMENT
                | vk::ImageUsageFlags::STORAGE
                | vk::ImageUsageFlags::TRANSFER_DST,
            vk::ImageAspectFlags::COLOR,
            "clip-peels",
        )?;
        let depth = image(
            DEPTH_FORMAT,
            1,
            vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT,
            vk::ImageAspectFlags::DEPTH,
            "clip-peel-depth",
        )?;
        // A host-visible buffer is fine for a few thousand triangles read once per pass.
        let corner_buf = Buffer::from_slice(
            gpu,
            if corners.is_empty() {
                &[[0.0f32; 4]][..]
            } else {
                &corners
            },
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "clip-corners",
        )?;
        let clip = Buffer::new(
            gpu,
            texels_bytes,
            usage,
            MemoryLocation::GpuOnly,
            "clip-map",
        )?;
        let dilation = Dilation::new(gpu, res, texel, radius)?;
        let readback = Buffer::new(
            gpu,
            2 * texels_bytes,
            vk::BufferUsageFlags::TRANSFER_DST,
            MemoryLocation::GpuToCpu,
            "clip-map-readback",
        )?;

        // SAFETY: `cmd` is recording (submit_and_wait); every image and buffer named is a local
        // that outlives the waited submission; the clear reaches layer 0 in GENERAL after the
        // transition above; the copies read `texels_bytes` from `clip` and `dilation.out`
        // (TRANSFER_SRC, that size each) into the two halves of `readback` (TRANSFER_DST, twice
        // that).
        gpu.submit_and_wait(|cmd| unsafe {
            peels.transition(cmd, vk::ImageLayout::UNDEFINED, vk::ImageLayout::GENERAL);
            depth.transition(
                cmd,
                vk::ImageLayout::UNDEFINED,
                vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
            );
            let before_all = vk::ClearColorValue {
                float32: [EMPTY_OUT, -1.0, 0.0, 0.0],
            };
            let layer0 = [peels.subresource_range().layer_count(1)];
            gpu.device.cmd_clear_color_image(
                cmd,
                peels.raw,
                vk::ImageLayout::GENERAL,
                &before_all,
                &layer0,
            );
            gpu.barrier(cmd);
            let layers = PeelLayers {
                peels: &peels,
                depth: &depth,
                corners: &corner_buf,
                count: corners.len() as u32,
                res,
            };
            for k in 0..PEELS {
                self.record_peel(cmd, &layers, push, k + 1);
                gpu.barrier(cmd);
            }
            let far = PeelPush { mode: 1, ..push };
            self.record_peel(cmd, &layers, far, FARTHEST);
            gpu.barrier(cmd);
            self.record_pair(cmd, &peels, &clip, res);
            gpu.barrier(cmd);
            self.record_dilate(cmd, &clip, &dilation, res);
            gpu.barrier(cmd);
            let regions = [
                vk::BufferCopy::default().size(texels_bytes),
                vk::BufferCopy::default()
                    .dst_offset(texels_bytes)
                    .size(texels_bytes),
            ];
            gpu.device
                .cmd_copy_buffer(cmd, clip.raw, readback.raw, &regions[..1]);
            gpu.device
                .cmd_copy_buffer(cmd, dilation.out.raw, readback.raw, &regions[1..]);
        })?;
        let texels: &[[f32; 4]] = bytemuck::cast_slice(readback.mapped()?);
        let (clip, dilated) = (texels[..n].to_vec(), texels[n..].to_vec());
        Ok(ClipMap {
            res,
            extent,
            radius,
            z_range: z_range(&dilated),
            clip,
            dilated,
        })
    }

    /// The dilation map of `clip` (res x res texels of `texel` size) for `radius` on the GPU: the
    /// counterpart of [`super::dilate`], for maps built elsewhere (and to test the two agree).
    pub fn dilate(
        &self,
        clip: &[[f32; 4]],
        res: usize,
        texel: f32,
        radius: f32,
    ) -> Result<Vec<[f32; 4]>> {
        let n = res * res;
        if clip.len() != n {
            return Err(ClipGpuError::MapSize {
                res,
                expected: n,
                got: clip.len(),
            });
        }
        let gpu = &self.gpu;
        let input = Buffer::from_slice(gpu, clip, vk::BufferUsageFlags::STORAGE_BUFFER, "clip")?;
        let dilation = Dilation::new(gpu, res, texel, radius)?;
        let readback = Buffer::new(
            gpu,
            (n * 16) as u64,
            vk::BufferUsageFlags::TRANSFER_DST,
            MemoryLocation::GpuToCpu,
            "dilation-readback",
        )?;
        // SAFETY: `cmd` is recording; `dilation.out` (TRANSFER_SRC) and `readback` (TRANSFER_DST)
        // both hold n * 16 bytes and outlive the waited submission.
        gpu.submit_and_wait(|cmd| unsafe {
            self.record_dilate(cmd, &input, &dilation, res);
            gpu.barrier(cmd);
            let region = [vk::BufferCopy::default().size((n * 16) as u64)];
            gpu.device
                .cmd_copy_buffer(cmd, dilation.out.raw, readback.raw, &region);
        })?;
        Ok(bytemuck::cast_slice(readback.mapped()?).to_vec())
    }

    fn check_resolution(&self, res: usize) -> Result<()> {
        let l = &self.gpu.limits;
        let max = l
            .max_image_dimension2_d
            .min(l.max_framebuffer_width)
            .min(l.max_framebuffer_height)
            .min(l.max_viewport_dimensions[0])
            .min(l.max_viewport_dimensions[1]);
        if res > max as usize {
            return Err(ClipGpuError::Resolution {
                res,
                max,
                device: self.gpu.device_name.clone(),
            });
        }
        Ok(())
    }

    /// One peel pass into layer `target` of `layers.peels`; a front peel reads layer
    /// `target - 1`.
    fn record_peel(
        &self,
        cmd: vk::CommandBuffer,
        layers: &PeelLayers,
        push: PeelPush,
        target: usize,
    ) {
        let PeelLayers {
            peels,
            depth,
            corners,
            count,
            res,
        } = *layers;
        let front = push.mode == 0;
        let (clear_z, clear_depth, pipeline) = if front {
            (EMPTY_IN, 1.0, self.front)
        } else {
            (EMPTY_OUT, 0.0, self.back)
        };
        // The farthest pass reads nothing; layer 0 stands in for its descriptor.
        let previous = if front { target - 1 } else { 0 };
        let color = [vk::RenderingAttachmentInfo::default()
            .image_view(peels.layer_views[target])
            .image_layout(vk::ImageLayout::GENERAL)
            .load_op(vk::AttachmentLoadOp::CLEAR)
            .store_op(vk::AttachmentStoreOp::STORE)
            .clear_value(vk::ClearValue {
                color: vk::ClearColorValue {
                    float32: [clear_z, 0.0, 0.0, 0.0],
                },
            })];
        let depth_att = vk::RenderingAttachmentInfo::default()
            .image_view(depth.view)
            .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
            .load_op(vk::AttachmentLoadOp::CLEAR)
            .store_op(vk::AttachmentStoreOp::DONT_CARE)
            .clear_value(vk::ClearValue {
                depth_stencil: vk::ClearDepthStencilValue {
                    depth: clear_depth,
                    stencil: 0,
                },
            });
        let area = vk::Rect2D {
            offset: vk::Offset2D { x: 0, y: 0 },
            extent: vk::Extent2D {
                width: res as u32,
                height: res as u32,
            },
        };
        let buffers = [corners.descriptor()];
        let images = [vk::DescriptorImageInfo::default()
            .image_view(peels.layer_views[previous])
            .image_layout(vk::ImageLayout::GENERAL)];
        let writes = [
            vk::WriteDescriptorSet::default()
                .dst_binding(0)
                .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                .buffer_info(&buffers),
            vk::WriteDescriptorSet::default()
                .dst_binding(1)
                .descriptor_type(vk::DescriptorType::STORAGE_IMAGE)
                .image_info(&images),
        ];
        let d = &self.gpu.device;
        // SAFETY: `cmd` is recording outside a render pass (build's submission); layer `target` of
        // `peels` (GENERAL) is the colour attachment and layer `previous`, a different one, is read
        // as a storage image; `depth` is in DEPTH_ATTACHMENT_OPTIMAL; the writes and the PeelPush
        // match `peel_layout`, this state's own like the pipelines.
        unsafe {
            d.cmd_begin_rendering(
                cmd,
                &vk::RenderingInfo::default()
                    .render_area(area)
                    .layer_count(1)
                    .color_attachments(&color)
                    .depth_attachment(&depth_att),
            );
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline);
            self.gpu.push_descriptor.cmd_push_descriptor_set(
                cmd,
                vk::PipelineBindPoint::GRAPHICS,
                self.peel_layout,
                0,
                &writes,
            );
            d.cmd_push_constants(
                cmd,
                self.peel_layout,
                vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT,
                0,
                bytemuck::bytes_of(&push),
            );
            d.cmd_set_viewport(
                cmd,
                0,
                &[vk::Viewport {
                    x: 0.0,
                    y: 0.0,
                    width: res as f32,
                    height: res as f32,
                    min_depth: 0.0,
                    max_depth: 1.0,
                }],
            );
            d.cmd_set_scissor(cmd, 0, &[area]);
            if count > 0 {
                d.cmd_draw(cmd, count, 1, 0, 0);
            }
            d.cmd_end_rendering(cmd);
        }
    }

    fn record_pair(&self, cmd: vk::CommandBuffer, peels: &Image, clip: &Buffer, res: usize) {
        let images = [vk::DescriptorImageInfo::default()
            .image_view(peels.view)
            .image_layout(vk::ImageLayout::GENERAL)];
        let buffers = [clip.descriptor()];
        let writes = [
            vk::WriteDescriptorSet::default()
                .dst_binding(0)
                .descriptor_type(vk::DescriptorType::STORAGE_IMAGE)
                .image_info(&images),
            vk::WriteDescriptorSet::default()
                .dst_binding(1)
                .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                .buffer_info(&buffers),
        ];
        let push = GridPush {
            res: res as i32,
            reach: 0,
        };
        let d = &self.gpu.device;
        // SAFETY: `cmd` is recording (build's submission); the writes match `pair`'s set layout
        // (storage image, storage buffer) with live resources, and GridPush is the size `pair` was
        // made with.
        unsafe {
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, self.pair.pipeline);
            self.gpu.push_descriptor.cmd_push_descriptor_set(
                cmd,
                vk::PipelineBindPoint::COMPUTE,
                self.pair.layout,
                0,
                &writes,
            );
            d.cmd_push_constants(
                cmd,
                self.pair.layout,
                vk::ShaderStageFlags::COMPUTE,
                0,
                bytemuck::bytes_of(&push),
            );
        }
        let groups = (res as u32).div_ceil(GROUP);
        self.pair.dispatch(cmd, [groups, groups, 1]);
    }

    fn record_dilate(&self, cmd: vk::CommandBuffer, clip: &Buffer, dil: &Dilation, res: usize) {
        let push = GridPush {
            res: res as i32,
            reach: dil.reach as i32,
        };
        self.rows
            .bind(cmd, &[clip, &dil.rows], bytemuck::bytes_of(&push));
        self.rows.dispatch(cmd, [(res as u32).div_ceil(64), 1, 1]);
        self.gpu.barrier(cmd);
        self.dilate.bind(
            cmd,
            &[clip, &dil.kernel, &dil.rows, &dil.out],
            bytemuck::bytes_of(&push),
        );
        let groups = (res as u32).div_ceil(GROUP);
        self.dilate.dispatch(cmd, [groups, groups, 1]);
    }
}

impl Drop for ClipMapGpu {
    fn drop(&mut self) {
        // SAFETY: the idle wait ends every build that used these; they are this state's own,
        // destroyed once (the compute pipelines free theirs).
        unsafe {
            let d = &self.gpu.device;
            let _ = d.device_wait_idle();
            d.destroy_pipeline(self.front, None);
            d.destroy_pipeline(self.back, None);
            d.destroy_pipeline_layout(self.peel_layout, None);
            d.destroy_descriptor_set_layout(self.peel_set_layout, None);
        }
    }
}

/// The dilation's kernel (uploaded: the row widths, then the heights), the clip map's non-empty
/// row spans and the output, for one map.
struct Dilation {
    reach: usize,
    kernel: Buffer,
    rows: Buffer,
    out: Buffer,
}

impl Dilation {
    fn new(gpu: &Gpu, res: usize, texel: f32, radius: f32) -> Result<Dilation> {
        let k = DilationKernel::new(texel, radius);
        let mut words: Vec<u32> = k.widths.iter().map(|&w| w as u32).collect();
        words.extend(k.heights.iter().map(|h| h.to_bits()));
        let kernel = Buffer::from_slice(
            gpu,
            &words,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "clip-dilation-kernel",
        )?;
        let rows = Buffer::new(
            gpu,
            (res * 8) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            MemoryLocation::GpuOnly,
            "clip-dilation-rows",
        )?;
        let out = Buffer::new(
            gpu,
            (res * res * 16) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC,
            MemoryLocation::GpuOnly,
            "clip-dilation",
        )?;
        Ok(Dilation {
            reach: k.reach,
            kernel,
            rows,
            out,
        })
    }
}

/// The mesh as a flat triangle list, three (x, y, z, 1) corners per triangle, for vertex pulling.
fn triangle_corners(mesh: &TriMesh) -> Result<Vec<[f32; 4]>> {
    if mesh.triangles.len() > MAX_TRIANGLES {
        return Err(ClipGpuError::TooManyTriangles(mesh.triangles.len()));
    }
    let mut corners = Vec::with_capacity(mesh.triangles.len() * 3);
    for (t, tri) in mesh.triangles.iter().enumerate() {
        for &i in tri {
            let v = mesh
                .vertices
                .get(i as usize)
                .ok_or(ClipGpuError::BadIndex {
                    triangle: t,
                    index: i,
                    vertices: mesh.vertices.len(),
                })?;
            corners.push([v.x, v.y, v.z, 1.0]);
        }
    }
    Ok(corners)
}

/// The front-peel (depth LESS) and farthest-crossing (depth GREATER) pipelines: one R32_SFLOAT
/// colour target (local z) and a D32 depth target, culling off, dynamic viewport and scissor.
fn peel_pipelines(gpu: &Gpu, layout: vk::PipelineLayout) -> crate::gpu::Result<[vk::Pipeline; 2]> {
    let desc = pipeline::GraphicsDesc {
        vs: include_bytes!(concat!(env!("OUT_DIR"), "/clip_peel.vert.spv")),
        fs: include_bytes!(concat!(env!("OUT_DIR"), "/clip_peel.frag.spv")),
        layout,
        vertex_bindings: &[],
        vertex_attributes: &[],
        color_format: PEEL_FORMAT,
        depth_format: DEPTH_FORMAT,
        blend: pipeline::opaque(),
        fs_constants: &[],
    };
    // Every crossing counts, front- or back-facing; one sample per texel at the CPU reference's
    // sample point.
    let none = pipeline::raster(vk::CullModeFlags::NONE);
    let p = pipeline::graphics_pipelines(
        gpu,
        &desc,
        &[
            (none, pipeline::depth(vk::CompareOp::LESS, true)),
            (none, pipeline::depth(vk::CompareOp::GREATER, true)),
        ],
    )?;
    Ok([p[0], p[1]])
}
