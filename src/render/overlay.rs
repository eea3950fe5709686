//! Tools and hands drawn over the volume, so the surgeon sees where a cut will be before carving.
//!
//! The overlay runs after [`super::Renderer::record`] in the same command buffer and draws into
//! the same stereo target: colour and depth are loaded, not cleared, and the depth test (LESS,
//! no depth writes) runs against the depth the ray caster wrote where the volume became visible
//! (5 % accumulated opacity). A tool behind bone is therefore hidden by it, a tool in front of it
//! tints it, and translucent items never hide one another. [`StereoTarget::cmd_finish`] then
//! readies the images for copying.
//!
//! Every item is a closed mesh in its own local units placed by one model matrix: the built-in
//! tool shapes of [`crate::clip::mesh`], loaded OBJ/PLY meshes ([`OverlayRenderer::set_meshes`]),
//! a small cone for a controller and a thin rod for the right hand's tool offset. All meshes
//! are uploaded once; per draw only 96 bytes of push constants change.

use super::{StereoTarget, View, COLOR_FORMAT, DEPTH_FORMAT};
use crate::clip::Shape;
use crate::clip::TriMesh;
use crate::gpu::{pipeline, Buffer, Gpu, Result};
use crate::scene::{Scene, Tool, ToolMode, LEFT, RIGHT};
use crate::space::Pose;
use ash::vk;
use glam::{Mat4, Quat, Vec3};
use std::collections::HashMap;
use std::f32::consts::PI;

/// Straight-alpha colours of the overlay (see [`OverlayItem::color`]).
pub mod colors {
    /// A carving tool that cuts this frame: red, the colour of "this removes tissue".
    pub const CARVING: [f32; 4] = [0.95, 0.28, 0.22, 0.3];
    /// A carving tool that is switched off: a cool blue that does not read as a cut.
    pub const IDLE: [f32; 4] = [0.35, 0.6, 1.0, 0.2];
    /// A probe (keeps only its inside) that is on.
    pub const PROBING: [f32; 4] = [0.3, 0.9, 0.4, 0.3];
    /// A probe that is off: green fading to the idle blue.
    pub const PROBE_IDLE: [f32; 4] = [0.3, 0.8, 0.75, 0.2];
    /// A tracked controller.
    pub const HAND: [f32; 4] = [0.92, 0.92, 0.88, 0.6];
    /// A tracked hand's joints.
    pub const JOINT: [f32; 4] = [0.95, 0.8, 0.7, 0.7];
    /// The rod from the right grip to the centre of its tool.
    pub const OFFSET: [f32; 4] = [1.0, 0.85, 0.3, 0.6];
    /// Markups (points and rulers, `--markups`).
    pub const MARKUP: [f32; 4] = [0.25, 0.85, 1.0, 0.85];
    /// A measuring tool: the markups' colour, faint, so its centre point stands out.
    pub const MEASURING: [f32; 4] = [0.25, 0.85, 1.0, 0.12];
    /// Text (rulers' lengths, the structure menu): near white, opaque.
    pub const TEXT: [f32; 4] = [1.0, 1.0, 0.92, 1.0];
    /// A tool inside a structure's safety margin: amber, brighter than any other tool.
    pub const WARNING: [f32; 4] = [1.0, 0.7, 0.0, 0.55];
}

/// Length (m) of the controller marker: a cone pointing down the grip's -Z, 1.5 cm long.
pub const MARKER_SIZE: f32 = 0.01;
/// Radius (m) of the rod that shows the right hand's tool offset.
pub const OFFSET_ROD_RADIUS: f32 = 0.0012;

/// What an [`OverlayItem`] draws, in its local units.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum OverlayMesh {
    /// A tool shape as [`Tool::size`] scales it (the unit sphere, the cube of half-edge 1, ...).
    Tool(Shape),
    /// A controller: a cone with its tip at local (0, 0, -1) and its base (radius 0.5) at
    /// z = 0.5, so the way the hand points reads at a glance.
    Marker,
    /// A rod from local (0, 0, -1) to (0, 0, 1) of radius 1 (the unit cylinder), for segments.
    Rod,
    /// A character of text ([`super::text`], by glyph index): flat, facing local +Z, drawn over
    /// everything rather than depth-tested, so it stays readable.
    Glyph(u8),
}

/// One mesh to draw over the volume.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OverlayItem {
    pub mesh: OverlayMesh,
    /// Local -> world. Shading is exact for rigid transforms with a uniform scale; a
    /// non-uniform scale (the thin [`OverlayMesh::Rod`]) only skews the headlight term.
    pub model: Mat4,
    /// Straight (not premultiplied) RGBA: `rgb` the surface colour, `a` its opacity where the
    /// surface faces the eye (it grows towards the silhouette).
    pub color: [f32; 4],
}

/// The colour of a tool by what it does: carving red, probing green, idle (not cutting) blue.
pub fn tool_color(tool: &Tool) -> [f32; 4] {
    match (tool.mode, tool.active) {
        (ToolMode::Carve, true) => colors::CARVING,
        (ToolMode::Carve, false) => colors::IDLE,
        (ToolMode::Probe, true) => colors::PROBING,
        (ToolMode::Probe, false) => colors::PROBE_IDLE,
        (ToolMode::Measure, _) => colors::MEASURING,
    }
}

/// The overlay of a scene: every tool at its pose; for each tracked hand (`Some` grip pose,
/// [`LEFT`] then [`RIGHT`]) a marker at the grip; for a tracked right hand also a rod from the
/// grip to the centre of the tool it holds, `tool_offset` ahead in the grip's own axes (as the
/// interaction places it). No rod when the offset is under a millimetre: there is nothing to show.
pub fn scene_overlay(
    scene: &Scene,
    hands: &[Option<Pose>; 2],
    tool_offset: Vec3,
    warned: &[usize],
) -> Vec<OverlayItem> {
    let mut items: Vec<OverlayItem> = scene
        .tools
        .iter()
        .enumerate()
        .map(|(n, t)| OverlayItem {
            mesh: OverlayMesh::Tool(t.shape),
            model: t.pose.matrix() * Mat4::from_scale(Vec3::splat(t.size)),
            color: if warned.contains(&n) {
                colors::WARNING
            } else {
                tool_color(t)
            },
        })
        .collect();
    // A measuring tool marks at its centre: show the point it would place.
    for t in scene.tools.iter().filter(|t| t.mode == ToolMode::Measure) {
        items.push(markup_point(t.pose.position, 1.0));
    }
    for side in [LEFT, RIGHT] {
        let Some(grip) = hands[side] else { continue };
        items.push(OverlayItem {
            mesh: OverlayMesh::Marker,
            model: grip.matrix() * Mat4::from_scale(Vec3::splat(MARKER_SIZE)),
            color: colors::HAND,
        });
        let offset = grip.orientation * tool_offset;
        if side == RIGHT && offset.length() > 1e-3 {
            let half = 0.5 * offset.length();
            items.push(OverlayItem {
                mesh: OverlayMesh::Rod,
                model: Mat4::from_scale_rotation_translation(
                    Vec3::new(OFFSET_ROD_RADIUS, OFFSET_ROD_RADIUS, half),
                    Quat::from_rotation_arc(Vec3::Z, offset / (2.0 * half)),
                    grip.position + 0.5 * offset,
                ),
                color: colors::OFFSET,
            });
        }
    }
    items
}

/// Radius (m at true size) of a markup point's sphere and of a ruler's rod.
const MARKUP_POINT: f32 = 0.0025;
const MARKUP_ROD: f32 = 0.0008;

/// A markup point's sphere at world point `p`, for a volume at `scale`.
fn markup_point(p: Vec3, scale: f32) -> OverlayItem {
    OverlayItem {
        mesh: OverlayMesh::Tool(Shape::Sphere),
        model: Mat4::from_scale_rotation_translation(
            Vec3::splat(MARKUP_POINT * scale),
            Quat::IDENTITY,
            p,
        ),
        color: colors::MARKUP,
    }
}

/// The markups of `vol` placed at `placement`: a small sphere per point and per ruler end, a
/// thin rod along each ruler, and text facing `head`: each point's label beside it, each
/// ruler's length in mm above its middle; appended to `items`.
pub fn markup_overlay(
    markups: &crate::volume::markups::Markups,
    vol: &crate::volume::Volume,
    placement: &crate::space::Placement,
    head: &Pose,
    items: &mut Vec<OverlayItem>,
) {
    use super::text::{text_items, TEXT_HEIGHT};
    let at = |lps| crate::space::world_from_lps_point(vol, placement, lps);
    let s = placement.scale;
    let up = head.orientation * Vec3::Y;
    // Text clears the sphere or the rod it belongs to.
    let above = up * (MARKUP_POINT * s + TEXT_HEIGHT);
    for p in &markups.points {
        let at = at(p.lps);
        items.push(markup_point(at, s));
        items.extend(text_items(
            &p.label,
            at + above,
            head,
            TEXT_HEIGHT,
            colors::TEXT,
        ));
    }
    for l in &markups.lines {
        let (a, b) = (at(l.ends[0]), at(l.ends[1]));
        items.push(markup_point(a, s));
        items.push(markup_point(b, s));
        let length = format!("{:.1} mm", l.length_mm());
        items.extend(text_items(
            &length,
            a.lerp(b, 0.5) + above,
            head,
            TEXT_HEIGHT,
            colors::TEXT,
        ));
        let half = 0.5 * a.distance(b);
        if half > 1e-6 {
            items.push(OverlayItem {
                mesh: OverlayMesh::Rod,
                model: Mat4::from_scale_rotation_translation(
                    Vec3::new(MARKUP_ROD * s, MARKUP_ROD * s, half),
                    Quat::from_rotation_arc(Vec3::Z, (b - a) / (2.0 * half)),
                    0.5 * (a + b),
                ),
                color: colors::MARKUP,
            });
        }
    }
}

/// Small spheres at the tracked hands' joints, each (pose, radius) of `joints`, appended to
/// `items`.
pub fn joint_overlay(joints: impl IntoIterator<Item = (Pose, f32)>, items: &mut Vec<OverlayItem>) {
    for (p, r) in joints {
        items.push(OverlayItem {
            mesh: OverlayMesh::Tool(crate::clip::Shape::Sphere),
            model: Mat4::from_scale_rotation_translation(Vec3::splat(r), p.orientation, p.position),
            color: colors::JOINT,
        });
    }
}

/// The controller marker's mesh (see [`OverlayMesh::Marker`]).
pub fn marker_mesh() -> TriMesh {
    let n = 24u32;
    let mut m = TriMesh::default();
    m.vertices.push(Vec3::new(0.0, 0.0, -1.0));
    m.vertices.push(Vec3::new(0.0, 0.0, 0.5));
    for i in 0..n {
        let a = i as f32 / n as f32 * 2.0 * PI;
        m.vertices
            .push(Vec3::new(0.5 * a.cos(), 0.5 * a.sin(), 0.5));
    }
    for i in 0..n {
        let (a, b) = (2 + i, 2 + (i + 1) % n);
        m.triangles.push([0, a, b]);
        m.triangles.push([1, b, a]);
    }
    m
}

/// Adjacent faces that meet at less than this angle share a smooth normal; sharper edges
/// (the cube's, the cylinder's rims) stay crisp.
const CREASE_COS: f32 = 0.766; // cos 40 degrees

/// A mesh as the overlay draws it: interleaved position + normal, triangles counter-clockwise
/// seen from outside (flipped if the mesh encloses a negative volume), (nearly) zero-area
/// triangles dropped, and normals smoothed across edges flatter than 40 degrees.
pub fn shaded_vertices(mesh: &TriMesh) -> (Vec<[f32; 6]>, Vec<u32>) {
    let pos = |i: u32| mesh.vertices[i as usize];
    let signed_volume: f32 = mesh
        .triangles
        .iter()
        .map(|t| pos(t[0]).dot(pos(t[1]).cross(pos(t[2]))))
        .sum();
    let tris: Vec<[Vec3; 3]> = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(pos);
            if signed_volume < 0.0 {
                [a, c, b]
            } else {
                [a, b, c]
            }
        })
        .filter(|[a, b, c]| {
            // Relative to the edges: the sphere's pole "triangles" are slivers of rounding error.
            let longest = (*b - *a).length_squared().max((*c - *a).length_squared());
            (*b - *a).cross(*c - *a).length() > 1e-5 * longest
        })
        .collect();
    // Area-weighted face normals, and the faces at each (welded) position.
    let normals: Vec<Vec3> = tris
        .iter()
        .map(|[a, b, c]| (*b - *a).cross(*c - *a))
        .collect();
    let key = |p: Vec3| (p * 1e4).round().to_array().map(|c| c as i32);
    let mut at: HashMap<[i32; 3], Vec<usize>> = HashMap::new();
    for (f, t) in tris.iter().enumerate() {
        for p in t {
            at.entry(key(*p)).or_default().push(f);
        }
    }
    let mut vertices = Vec::new();
    let mut indices = Vec::with_capacity(tris.len() * 3);
    let mut seen: HashMap<[u32; 6], u32> = HashMap::new();
    for (f, t) in tris.iter().enumerate() {
        let nf = normals[f].normalize();
        for p in t {
            let n = at[&key(*p)]
                .iter()
                .map(|&g| normals[g])
                .filter(|ng| ng.normalize().dot(nf) > CREASE_COS)
                .sum::<Vec3>()
                .normalize_or(nf);
            let v = [p.x, p.y, p.z, n.x, n.y, n.z];
            let index = *seen.entry(v.map(f32::to_bits)).or_insert_with(|| {
                vertices.push(v);
                (vertices.len() - 1) as u32
            });
            indices.push(index);
        }
    }
    (vertices, indices)
}

/// One mesh on the GPU.
struct GpuMesh {
    vertices: Buffer,
    indices: Buffer,
    index_count: u32,
}

impl GpuMesh {
    fn new(gpu: &Gpu, mesh: &TriMesh, name: &str) -> Result<GpuMesh> {
        let (v, i) = shaded_vertices(mesh);
        GpuMesh::upload(gpu, &v, &i, name)
    }

    fn upload(gpu: &Gpu, v: &[[f32; 6]], i: &[u32], name: &str) -> Result<GpuMesh> {
        Ok(GpuMesh {
            vertices: Buffer::device_local(gpu, v, vk::BufferUsageFlags::VERTEX_BUFFER, name)?,
            indices: Buffer::device_local(gpu, i, vk::BufferUsageFlags::INDEX_BUFFER, name)?,
            index_count: i.len() as u32,
        })
    }
}

/// std430 mirror of the push-constant block in shaders/include/overlay.glsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ItemPush {
    mvp: [f32; 16],
    color: [f32; 4],
    eye_local: [f32; 4],
}
crate::gpu::glsl_layout!(ItemPush, 96, mvp: 0, color: 64, eye_local: 80);

/// Draws [`OverlayItem`]s into a [`StereoTarget`] the volume was just rendered into.
pub struct OverlayRenderer {
    gpu: Gpu,
    /// Back faces, then front faces: for each (convex) item, the far side blends under the near
    /// side, whatever order the mesh lists its triangles in. Then front faces with no depth
    /// test, for text.
    pipelines: [vk::Pipeline; 3],
    layout: vk::PipelineLayout,
    /// Sphere, box, cylinder (also the rod), torus, marker.
    builtin: Vec<GpuMesh>,
    /// The loaded meshes, by [`Shape::Mesh`] index.
    loaded: Vec<GpuMesh>,
    /// Every glyph in one mesh, and each glyph's `(first index, index count)` in it.
    glyphs: GpuMesh,
    glyph_ranges: Vec<(u32, u32)>,
}

impl OverlayRenderer {
    pub fn new(gpu: &Gpu) -> Result<OverlayRenderer> {
        let builtin = [
            (TriMesh::sphere(), "overlay-sphere"),
            (TriMesh::cube(), "overlay-box"),
            (TriMesh::cylinder(), "overlay-cylinder"),
            (TriMesh::torus(), "overlay-torus"),
            (marker_mesh(), "overlay-marker"),
        ]
        .iter()
        .map(|(m, name)| GpuMesh::new(gpu, m, name))
        .collect::<Result<Vec<_>>>()?;
        let (v, i, glyph_ranges) = super::text::glyph_meshes();
        let glyphs = GpuMesh::upload(gpu, &v, &i, "overlay-glyphs")?;
        // SAFETY: the layout info borrows `push`, which outlives the call; if the pipelines fail,
        // the layout, which nothing uses yet, is destroyed; else the returned renderer owns layout
        // and pipelines and its Drop destroys them.
        unsafe {
            let d = &gpu.device;
            let push = [vk::PushConstantRange::default()
                .stage_flags(vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT)
                .size(std::mem::size_of::<ItemPush>() as u32)];
            let layout = d.create_pipeline_layout(
                &vk::PipelineLayoutCreateInfo::default().push_constant_ranges(&push),
                None,
            )?;
            let bindings = [vk::VertexInputBindingDescription::default()
                .binding(0)
                .stride(std::mem::size_of::<[f32; 6]>() as u32)
                .input_rate(vk::VertexInputRate::VERTEX)];
            let attributes = [
                vk::VertexInputAttributeDescription::default()
                    .location(0)
                    .binding(0)
                    .format(vk::Format::R32G32B32_SFLOAT)
                    .offset(0),
                vk::VertexInputAttributeDescription::default()
                    .location(1)
                    .binding(0)
                    .format(vk::Format::R32G32B32_SFLOAT)
                    .offset(12),
            ];
            // The projection flips y (Vulkan NDC is y down), so a triangle that is
            // counter-clockwise seen from outside stays counter-clockwise in the framebuffer.
            // Hidden where the volume is nearer; no depth writes, so translucent items never hide
            // each other or the volume's depth (which read-back reports). Straight-alpha "over";
            // alpha accumulates like the ray caster's opacity.
            let desc = pipeline::GraphicsDesc {
                vs: include_bytes!(concat!(env!("OUT_DIR"), "/overlay.vert.spv")),
                fs: include_bytes!(concat!(env!("OUT_DIR"), "/overlay.frag.spv")),
                layout,
                vertex_bindings: &bindings,
                vertex_attributes: &attributes,
                color_format: COLOR_FORMAT,
                depth_format: DEPTH_FORMAT,
                blend: vk::PipelineColorBlendAttachmentState::default()
                    .blend_enable(true)
                    .src_color_blend_factor(vk::BlendFactor::SRC_ALPHA)
                    .dst_color_blend_factor(vk::BlendFactor::ONE_MINUS_SRC_ALPHA)
                    .color_blend_op(vk::BlendOp::ADD)
                    .src_alpha_blend_factor(vk::BlendFactor::ONE)
                    .dst_alpha_blend_factor(vk::BlendFactor::ONE_MINUS_SRC_ALPHA)
                    .alpha_blend_op(vk::BlendOp::ADD)
                    .color_write_mask(vk::ColorComponentFlags::RGBA),
                fs_constants: &[],
            };
            let depth = pipeline::depth(vk::CompareOp::LESS, false);
            // Back faces first, then front faces; text over everything.
            let variants = [
                (pipeline::raster(vk::CullModeFlags::FRONT), depth),
                (pipeline::raster(vk::CullModeFlags::BACK), depth),
                (
                    pipeline::raster(vk::CullModeFlags::BACK),
                    pipeline::depth(vk::CompareOp::ALWAYS, false),
                ),
            ];
            let res = pipeline::graphics_pipelines(gpu, &desc, &variants);
            let pipelines = match res {
                Ok(p) => p,
                Err(e) => {
                    d.destroy_pipeline_layout(layout, None);
                    return Err(e);
                }
            };
            Ok(OverlayRenderer {
                gpu: gpu.clone(),
                pipelines: [pipelines[0], pipelines[1], pipelines[2]],
                layout,
                builtin,
                loaded: Vec::new(),
                glyphs,
                glyph_ranges,
            })
        }
    }

    /// Uploads the session's loaded OBJ/PLY meshes (the same list, in the same order, that
    /// [`crate::ao::cao::Cao::meshes`] clips with). Items whose [`Shape::Mesh`] index has no
    /// uploaded mesh are skipped.
    pub fn set_meshes(&mut self, meshes: &[TriMesh]) -> Result<()> {
        self.loaded = meshes
            .iter()
            .map(|m| GpuMesh::new(&self.gpu, m, "overlay-mesh"))
            .collect::<Result<Vec<_>>>()?;
        Ok(())
    }

    /// The mesh that draws `mesh`, its index range, and the pipelines that draw it in order.
    fn draw_of(&self, mesh: OverlayMesh) -> Option<(&GpuMesh, (u32, u32), &[vk::Pipeline])> {
        if let OverlayMesh::Glyph(g) = mesh {
            let range = *self.glyph_ranges.get(g as usize)?;
            return Some((&self.glyphs, range, &self.pipelines[2..]));
        }
        let m = self.mesh(mesh)?;
        Some((m, (0, m.index_count), &self.pipelines[..2]))
    }

    fn mesh(&self, mesh: OverlayMesh) -> Option<&GpuMesh> {
        match mesh {
            OverlayMesh::Glyph(_) => None,
            OverlayMesh::Tool(Shape::Sphere) => self.builtin.first(),
            OverlayMesh::Tool(Shape::Box) => self.builtin.get(1),
            OverlayMesh::Tool(Shape::Cylinder) | OverlayMesh::Rod => self.builtin.get(2),
            OverlayMesh::Tool(Shape::Torus) => self.builtin.get(3),
            OverlayMesh::Marker => self.builtin.get(4),
            OverlayMesh::Tool(Shape::Mesh(i)) => self.loaded.get(i),
        }
    }

    /// Records `items` over what [`super::Renderer::record`] left in `target` (both images
    /// still attachments), both eyes. Items are drawn far to near from each eye (by the
    /// distance to their local origin), so overlapping translucent items blend in order, and
    /// text after them all. Call
    /// [`StereoTarget::cmd_finish`] afterwards. With no items nothing is recorded.
    pub fn record(
        &mut self,
        cmd: vk::CommandBuffer,
        target: &StereoTarget,
        views: &[View; 2],
        items: &[OverlayItem],
    ) -> Result<()> {
        if items.is_empty() {
            return Ok(());
        }
        let d = &self.gpu.device;
        // The ray caster's colour and depth writes, before this pass reads and blends them.
        self.gpu.barrier(cmd);
        // The ray caster's drawn part (a render scale's), which the view maps onto.
        let (width, height) = target.drawn();
        let area = vk::Rect2D {
            offset: vk::Offset2D::default(),
            extent: vk::Extent2D { width, height },
        };
        for (eye, view) in views.iter().enumerate() {
            let eye_pos = view.pose.position;
            let mut order: Vec<(f32, &OverlayItem)> = items
                .iter()
                .map(|it| (it.model.w_axis.truncate().distance(eye_pos), it))
                .collect();
            // Stable, and total on floats: the same items always draw in the same order. Text
            // comes last, so no translucent item tints it.
            let text = |it: &OverlayItem| matches!(it.mesh, OverlayMesh::Glyph(_));
            order.sort_by(|a, b| text(a.1).cmp(&text(b.1)).then(b.0.total_cmp(&a.0)));
            let view_proj = view.view_proj();
            let color_att = [vk::RenderingAttachmentInfo::default()
                .image_view(target.color.layer_views[eye])
                .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
                .load_op(vk::AttachmentLoadOp::LOAD)
                .store_op(vk::AttachmentStoreOp::STORE)];
            let depth_att = vk::RenderingAttachmentInfo::default()
                .image_view(target.depth.layer_views[eye])
                .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
                .load_op(vk::AttachmentLoadOp::LOAD)
                .store_op(vk::AttachmentStoreOp::STORE);
            let info = vk::RenderingInfo::default()
                .render_area(area)
                .layer_count(1)
                .color_attachments(&color_att)
                .depth_attachment(&depth_att);
            // SAFETY: `cmd` is recording with both target images in the attachment layouts
            // Renderer::record left (this method's contract); the views are layers of the live
            // target; vertex and index buffers are this renderer's meshes, kept until its Drop
            // waits for the device, and each index range is its mesh's own count or the glyph table
            // built with that mesh.
            unsafe {
                d.cmd_begin_rendering(cmd, &info);
                d.cmd_set_viewport(
                    cmd,
                    0,
                    &[vk::Viewport {
                        x: 0.0,
                        y: 0.0,
                        width: width as f32,
                        height: height as f32,
                        min_depth: 0.0,
                        max_depth: 1.0,
                    }],
                );
                d.cmd_set_scissor(cmd, 0, &[area]);
                for (_, item) in order {
                    let Some((mesh, (first, count), pipelines)) = self.draw_of(item.mesh) else {
                        continue;
                    };
                    let push = ItemPush {
                        mvp: (view_proj * item.model).to_cols_array(),
                        color: item.color,
                        eye_local: item
                            .model
                            .inverse()
                            .transform_point3(eye_pos)
                            .extend(1.0)
                            .into(),
                    };
                    d.cmd_bind_vertex_buffers(cmd, 0, &[mesh.vertices.raw], &[0]);
                    d.cmd_bind_index_buffer(cmd, mesh.indices.raw, 0, vk::IndexType::UINT32);
                    for &pipeline in pipelines {
                        d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline);
                        d.cmd_push_constants(
                            cmd,
                            self.layout,
                            vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT,
                            0,
                            bytemuck::bytes_of(&push),
                        );
                        d.cmd_draw_indexed(cmd, count, 1, first, 0, 0);
                    }
                }
                d.cmd_end_rendering(cmd);
            }
        }
        Ok(())
    }
}

impl Drop for OverlayRenderer {
    fn drop(&mut self) {
        // SAFETY: the idle wait ends every frame that drew with these; they are this renderer's
        // own, destroyed once.
        unsafe {
            let d = &self.gpu.device;
            let _ = d.device_wait_idle();
            for p in self.pipelines {
                d.destroy_pipeline(p, None);
            }
            d.destroy_pipeline_layout(self.layout, None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::space::{Fov, Pose};

    /// Vulkan's facing rule (spec, "Basic Polygon Rasterization"): with COUNTER_CLOCKWISE, a
    /// triangle is front-facing when a = -1/2 sum(x_i y_{i+1} - x_{i+1} y_i) in framebuffer
    /// coordinates is positive. The near side of every built-in mesh must be front-facing.
    #[test]
    fn near_faces_are_front_facing() {
        let view = View {
            pose: Pose {
                position: Vec3::new(0.0, 0.0, 5.0),
                orientation: Quat::IDENTITY,
            },
            fov: Fov {
                angle_left: -0.4,
                angle_right: 0.4,
                angle_up: 0.4,
                angle_down: -0.4,
            },
        };
        let vp = view.view_proj();
        let to_fb = |p: Vec3| {
            let c = vp * p.extend(1.0);
            // Viewport 100 x 100 at the origin: y grows downwards with NDC y.
            glam::Vec2::new((c.x / c.w + 1.0) * 50.0, (c.y / c.w + 1.0) * 50.0)
        };
        for (name, mesh) in [
            ("sphere", TriMesh::sphere()),
            ("box", TriMesh::cube()),
            ("cylinder", TriMesh::cylinder()),
            ("torus", TriMesh::torus()),
            ("marker", marker_mesh()),
        ] {
            let (v, i) = shaded_vertices(&mesh);
            let p = |k: u32| Vec3::new(v[k as usize][0], v[k as usize][1], v[k as usize][2]);
            // The triangle nearest the eye (largest centroid z) faces it.
            let near = i
                .chunks_exact(3)
                .max_by(|a, b| {
                    let z = |t: &[u32]| p(t[0]).z + p(t[1]).z + p(t[2]).z;
                    z(a).total_cmp(&z(b))
                })
                .unwrap();
            let f = [p(near[0]), p(near[1]), p(near[2])].map(to_fb);
            let a = -0.5
                * (0..3)
                    .map(|k| f[k].x * f[(k + 1) % 3].y - f[(k + 1) % 3].x * f[k].y)
                    .sum::<f32>();
            assert!(a > 0.0, "{name}: the near side is back-facing (a = {a})");
        }
    }

    #[test]
    fn normals_are_smooth_on_curves_and_crisp_on_edges() {
        let (v, _) = shaded_vertices(&TriMesh::sphere());
        for x in &v {
            let (p, n) = (Vec3::from_slice(&x[..3]), Vec3::from_slice(&x[3..]));
            assert!(p.normalize().dot(n) > 0.995, "sphere normal {n} at {p}");
        }
        let (v, i) = shaded_vertices(&TriMesh::cube());
        assert_eq!(v.len(), 24, "a cube has 6 faces x 4 corners of its own");
        assert_eq!(i.len(), 36);
        for x in &v {
            let n = Vec3::from_slice(&x[3..]);
            assert!(
                n.abs().max_element() > 0.999,
                "cube normal {n} is not a face's"
            );
        }
    }
}
