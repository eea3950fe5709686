//! Graphics pipelines. Everything the project's draws share is fixed here: triangle lists, one
//! sample, dynamic viewport and scissor, dynamic rendering into one colour and one depth
//! attachment. A caller names its shaders, layout, vertex input, formats and blending, and one
//! (rasterisation, depth) pair per pipeline variant.

use super::{shader_module, specialization_entries, Gpu, Result};
use ash::vk;

pub struct GraphicsDesc<'a> {
    pub vs: &'a [u8],
    pub fs: &'a [u8],
    pub layout: vk::PipelineLayout,
    pub vertex_bindings: &'a [vk::VertexInputBindingDescription],
    pub vertex_attributes: &'a [vk::VertexInputAttributeDescription],
    pub color_format: vk::Format,
    pub depth_format: vk::Format,
    pub blend: vk::PipelineColorBlendAttachmentState,
    /// The fragment shader's specialization constants, constant_id 0.. (u32 each).
    pub fs_constants: &'a [u32],
}

/// Rasterisation state with culling `cull` (front faces counter-clockwise), filled triangles.
pub fn raster(cull: vk::CullModeFlags) -> vk::PipelineRasterizationStateCreateInfo<'static> {
    vk::PipelineRasterizationStateCreateInfo::default()
        .polygon_mode(vk::PolygonMode::FILL)
        .cull_mode(cull)
        .front_face(vk::FrontFace::COUNTER_CLOCKWISE)
        .line_width(1.0)
}

/// Depth test with `op`, writing depth when `write`.
pub fn depth(op: vk::CompareOp, write: bool) -> vk::PipelineDepthStencilStateCreateInfo<'static> {
    vk::PipelineDepthStencilStateCreateInfo::default()
        .depth_test_enable(true)
        .depth_write_enable(write)
        .depth_compare_op(op)
}

/// Writes all channels, no blending.
pub fn opaque() -> vk::PipelineColorBlendAttachmentState {
    vk::PipelineColorBlendAttachmentState::default().color_write_mask(vk::ColorComponentFlags::RGBA)
}

/// One pipeline per (rasterisation, depth) variant, in order.
pub fn graphics_pipelines(
    gpu: &Gpu,
    desc: &GraphicsDesc,
    variants: &[(
        vk::PipelineRasterizationStateCreateInfo<'static>,
        vk::PipelineDepthStencilStateCreateInfo<'static>,
    )],
) -> Result<Vec<vk::Pipeline>> {
    let d = &gpu.device;
    let vs = shader_module(gpu, desc.vs)?;
    let fs = match shader_module(gpu, desc.fs) {
        Ok(fs) => fs,
        Err(e) => {
            // SAFETY: `vs` was just created, and nothing uses it yet.
            unsafe { d.destroy_shader_module(vs, None) };
            return Err(e);
        }
    };
    let entries = specialization_entries(desc.fs_constants.len());
    let specialization = vk::SpecializationInfo::default()
        .map_entries(&entries)
        .data(bytemuck::cast_slice(desc.fs_constants));
    let stages = [
        vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::VERTEX)
            .module(vs)
            .name(c"main"),
        vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::FRAGMENT)
            .module(fs)
            .name(c"main")
            .specialization_info(&specialization),
    ];
    let vertex_input = vk::PipelineVertexInputStateCreateInfo::default()
        .vertex_binding_descriptions(desc.vertex_bindings)
        .vertex_attribute_descriptions(desc.vertex_attributes);
    let input_assembly = vk::PipelineInputAssemblyStateCreateInfo::default()
        .topology(vk::PrimitiveTopology::TRIANGLE_LIST);
    let viewport = vk::PipelineViewportStateCreateInfo::default()
        .viewport_count(1)
        .scissor_count(1);
    let multisample = vk::PipelineMultisampleStateCreateInfo::default()
        .rasterization_samples(vk::SampleCountFlags::TYPE_1);
    let blend_att = [desc.blend];
    let blend = vk::PipelineColorBlendStateCreateInfo::default().attachments(&blend_att);
    let dyn_states = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
    let dynamic = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dyn_states);
    let formats = [desc.color_format];
    let mut rendering: Vec<_> = variants
        .iter()
        .map(|_| {
            vk::PipelineRenderingCreateInfo::default()
                .color_attachment_formats(&formats)
                .depth_attachment_format(desc.depth_format)
        })
        .collect();
    let infos: Vec<_> = variants
        .iter()
        .zip(rendering.iter_mut())
        .map(|((raster, depth), rendering)| {
            vk::GraphicsPipelineCreateInfo::default()
                .stages(&stages)
                .vertex_input_state(&vertex_input)
                .input_assembly_state(&input_assembly)
                .viewport_state(&viewport)
                .rasterization_state(raster)
                .multisample_state(&multisample)
                .depth_stencil_state(depth)
                .color_blend_state(&blend)
                .dynamic_state(&dynamic)
                .layout(desc.layout)
                .push_next(rendering)
        })
        .collect();
    // SAFETY: every info borrows locals (stages, states, the rendering chain) that outlive the
    // call; the modules are live and `desc.layout` is a live layout of this device.
    let res = unsafe { d.create_graphics_pipelines(vk::PipelineCache::null(), &infos, None) };
    // SAFETY: a module may be destroyed once the pipelines were created from it (or creation
    // failed).
    unsafe {
        d.destroy_shader_module(vs, None);
        d.destroy_shader_module(fs, None);
    }
    res.map_err(|(created, e)| {
        for p in created.into_iter().filter(|p| *p != vk::Pipeline::null()) {
            // SAFETY: a pipeline the failed call did create; nothing has used it.
            unsafe { d.destroy_pipeline(p, None) };
        }
        e.into()
    })
}
