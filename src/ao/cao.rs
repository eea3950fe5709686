//! Contextual Ambient Occlusion: per frame, the tools clip the volume (shadow test against their
//! clip-camera maps, anti-aliased), a mask sorts voxels into clipped (a), affected (b) and
//! unaffected (c), and LAO is recomputed for b only; c keeps V_PAO, a gets 1.
//!
//! Beyond the paper, the clip and update passes run only over the voxel boxes the dilated tools
//! can reach, and the previous frame's boxes are restored first, so the per-frame cost follows
//! the tools, not the volume. The result equals the naive full recompute ([`Mode::Naive`]) bit
//! for bit: both use the same kernels on the same clipped opacity.

use super::filter_gpu::FilterGpu;
use super::histogram_gpu::HistogramGpu;
use super::lao::LaoLayout;
use super::method::MethodBuffers;
pub use super::method::MethodGpu;
use super::pool::{reach_voxels, AoPool};
use super::voxel_box::{dispatch_box, merge_boxes, VoxelBox};
use crate::clip::bricks::{self, BrickTool};
use crate::clip::margin::{self, MarginHit};
use crate::clip::Shape;
use crate::clip::{shape_mesh, ClipMap, ClipMapGpu, TriMesh};
use crate::gpu::{
    Buffer, ComputePipeline, Gpu, GpuError, GpuTimer, Reach, Result, MAX_FRAMES_IN_FLIGHT,
};
use crate::scene::{Tool, ToolMode};
use crate::space::{world_from_tex, Placement};
use crate::volume::distance::MarginField;
use crate::volume::Volume;
use ash::vk;
use glam::{Mat4, Vec3};
use gpu_allocator::MemoryLocation;
use std::collections::HashMap;

pub use crate::shader_constants::MAX_TOOLS;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Mode {
    /// Recompute only where the tools changed the AO (and only inside their boxes).
    #[default]
    Contextual,
    /// Recompute LAO for every voxel every frame (the paper's "LAO" column).
    Naive,
}

/// What one frame did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameMetrics {
    /// Voxels clipped away (a), affected and recomputed (b), unaffected (c).
    pub clipped: u64,
    pub recomputed: u64,
    pub unaffected: u64,
    /// Voxels the clip pass visited (the tools' boxes, or the whole volume).
    pub visited: u64,
    pub restore_ms: f64,
    pub clip_ms: f64,
    pub update_ms: f64,
}

impl FrameMetrics {
    pub fn percent_recomputed(&self) -> f64 {
        let total = self.clipped + self.recomputed + self.unaffected;
        100.0 * self.recomputed as f64 / total.max(1) as f64
    }
    pub fn gpu_ms(&self) -> f64 {
        self.restore_ms + self.clip_ms + self.update_ms
    }
}

/// std430 mirror of ClipTool in shaders/include/clip.glsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ClipToolGpu {
    pub local_from_index: [f32; 16],
    pub local_from_world: [f32; 16],
    pub map: [f32; 4],
    pub offsets: [u32; 4],
    /// The SH dilation map's extent, texels per unit and resolution (see [`Cao::sh_radius_mm`]).
    pub sh_map: [f32; 4],
}
crate::gpu::glsl_layout!(ClipToolGpu, 176,
    local_from_index: 0, local_from_world: 64, map: 128, offsets: 144, sh_map: 160);

/// Push constants of cao_restore.comp and clip_mask.comp: a box, and where its voxels lie in
/// O_c ([`Cao::clipped_stride`]). `box_max[3]` is where the box's O and V_PAO start in the
/// frame's staged boxes (the box's voxels x fastest, [`Cao::stage`]), in voxels.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ClipPush {
    dims: [i32; 4],
    box_min: [i32; 4],
    box_max: [i32; 4],
    stride: [i32; 4],
}
crate::gpu::glsl_layout!(ClipPush, 64, dims: 0, box_min: 16, box_max: 32, stride: 48);

/// The volume's CAO state on the GPU and the passes that update it every frame.
pub struct Cao {
    gpu: Gpu,
    restore: ComputePipeline,
    clip: ComputePipeline,
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    /// The volume's geometry (no voxels), for its model matrix.
    geometry: Volume,
    max_spacing_mm: f64,
    /// O as the GPU stored it (16-bit words, or f32 for the filters' density), held on the
    /// host: a frame's restore and clip passes read only their boxes' O, which each frame
    /// stages ([`Cao::stage`]), so the GPU holds no whole O.
    opacity: Vec<u8>,
    /// O_c: the anti-aliased clipped opacity, laid out as the method reads it
    /// ([`MethodGpu::clipped_stride`]: for LAO inside the zero border its kernel reads, which
    /// stays 0). Stored in 16 bits ([`super::stored`]), but for the filters' f32 density.
    /// Only the z-slices `clipped_slices` of that grid: all of them, kept by the restores, or
    /// while [`Cao::windowed`] the slices this frame's LAO update reads, filled anew each
    /// frame from the host's O (the GPU then holds no whole O_c).
    clipped: Buffer,
    clipped_slices: [usize; 2],
    mask: Buffer,
    /// V_PAO's 16-bit words, held on the host like O: a frame's passes read it only in the
    /// boxes they restore or update, staged with O ([`Cao::stage`]).
    pao: Vec<u8>,
    /// V_AO: this frame's ambient occlusion, in the bricks where it can differ from 1.
    pub ao: AoPool,
    /// O, V_PAO or the method changed since V_AO's bricks were chosen: the next whole restore
    /// chooses them anew ([`Cao::choose_bricks`]).
    bricks_stale: bool,
    /// Whether V_AO is stored in bricks (where they save enough): with None where GPU memory
    /// is short ([`super::pool::memory_short`]), else as [`Cao::store_in_bricks`] said.
    bricks: Option<bool>,
    /// What the host writes or reads back per frame, one set per frame in flight, so the next
    /// frame is recorded while the GPU still runs this one; [`Cao::record_frame`] takes the
    /// next slot.
    slots: Vec<FrameSlot>,
    slot: usize,
    /// Builds the tools' clip and dilation maps (rasterised peels, compute dilation).
    map_builder: ClipMapGpu,
    map_cache: HashMap<(Shape, u32, usize), ClipMap>,
    /// Loaded OBJ/PLY meshes, for Shape::Mesh.
    pub meshes: Vec<TriMesh>,
    pub clip_resolution: usize,
    prev_boxes: Vec<VoxelBox>,
    /// Where the last recorded frame may have changed V_AO (and the bleeding colour): its
    /// restore and tool boxes, merged (no two overlap). What the textures copy: the first frame
    /// after [`Cao::set_method`] or [`Cao::replace_precomputed`] restores, and so copies, the
    /// whole volume, and so does a new state's first frame (`Cao::unshown`).
    pub changed: Vec<VoxelBox>,
    /// V_AO holds values no texture was given yet (a new state's V_PAO): the next frame's
    /// changed box is the whole volume.
    unshown: bool,
    /// The state of every voxel outside `prev_boxes`: clipped away (a probe was active: only its
    /// inside is kept) or unclipped (O_c = O, V_AO = V_PAO).
    background_clipped: bool,
    /// When set, the tools also get dilation maps of this radius (the SH visibility reach) and
    /// [`Cao::sh_boxes`] holds their voxel boxes after each recorded frame.
    pub sh_radius_mm: Option<f64>,
    pub sh_boxes: Vec<VoxelBox>,
    /// Tools uploaded for the last recorded frame.
    pub tool_count: u32,
    /// Per tool of the last recorded frame, an index-space box holding every point it hides
    /// (the whole volume for a probe): the ray caster skips no sample inside one.
    pub reach_boxes: Vec<VoxelBox>,
    /// The last frame's bricks that no tool cuts, that one tool hides whole, and that a tool's
    /// surface may cross ([`bricks::counts`]).
    pub clip_brick_counts: [usize; 3],
    /// The AO method.
    method: MethodGpu,
    /// The structure of every voxel, a byte each (a 4-byte stand-in without labels), and the
    /// protected structures' 256-bit set: the carving tools leave those voxels standing.
    labels: Buffer,
    protect: Buffer,
    any_protected: bool,
    /// The protected set the next recorded frame writes into `protect` (the structure menu
    /// changed it), in its own command buffer so that frames still in flight keep theirs.
    protect_pending: Option<[u32; 8]>,
    protect_bits: [u32; 8],
}

/// The label map's structure ids packed four to a word, as clip_mask.comp reads them (one
/// zero word without labels), and the protected set.
fn label_buffers(gpu: &Gpu, vol: &Volume) -> Result<(Buffer, Buffer, bool)> {
    let storage = vk::BufferUsageFlags::STORAGE_BUFFER;
    let (words, bits, any) = match vol.labels.as_deref() {
        Some(l) => {
            let words: Vec<u32> = l
                .ids
                .chunks(4)
                .map(|c| c.iter().rev().fold(0u32, |w, &id| (w << 8) | id as u32))
                .collect();
            (words, l.protected_bits(), l.any_protected())
        }
        None => (vec![0u32], [0u32; 8], false),
    };
    Ok((
        Buffer::device_local(gpu, &words, storage, "cao-labels")?,
        Buffer::from_slice(
            gpu,
            &bits,
            storage | vk::BufferUsageFlags::TRANSFER_DST,
            "cao-protect",
        )?,
        any,
    ))
}

impl Cao {
    /// `opacity` is O as the GPU reads it (16-bit words, or f32 for the filters' density: the
    /// host keeps it) and `pao` its AO under `method` (V_PAO), a device buffer read back and
    /// dropped (the host keeps it too).
    pub fn new(
        gpu: &Gpu,
        vol: &Volume,
        opacity: Vec<u8>,
        pao: Buffer,
        method: MethodGpu,
    ) -> Result<Cao> {
        // Before anything else is allocated: what only the precompute reads goes.
        let method = method.for_update()?;
        let open = matches!(method, MethodGpu::Open);
        let es = method.density_bytes();
        if opacity.len() < vol.voxel_count() * es {
            return Err(GpuError::Other(format!(
                "{}: O of {} bytes for {} voxels",
                vol.name,
                opacity.len(),
                vol.voxel_count()
            )));
        }
        // No method yet: V_PAO is 1 (every word all ones, `AoVolume::open`), written here
        // rather than read back (a first picture waits for this).
        let pao_words = if open {
            vec![u8::MAX; pao.size as usize]
        } else {
            pao.read_back()?
        };
        // An open state copies V_PAO into V_AO on the GPU; a computed method restores from
        // the host's words (Cao::restore_whole).
        let pao = open.then_some(pao);
        let (dims, spacing) = (vol.dims, vol.spacing);
        let geometry = vol.clone_geometry();
        let (labels, protect, any_protected) = label_buffers(gpu, vol)?;
        let spv = |bytes: &[u8]| bytes.to_vec();
        let restore = ComputePipeline::with_addresses(
            gpu,
            &spv(include_bytes!(concat!(
                env!("OUT_DIR"),
                "/cao_restore.comp.spv"
            ))),
            &[[Reach::Address; 7].as_slice(), &[Reach::Descriptor]].concat(),
            std::mem::size_of::<ClipPush>() as u32,
            &[],
        )?;
        let clip = ComputePipeline::with_addresses(
            gpu,
            &spv(include_bytes!(concat!(
                env!("OUT_DIR"),
                "/clip_mask.comp.spv"
            ))),
            &[
                Reach::Address,
                Reach::Address,
                Reach::Address,
                Reach::Descriptor,
                Reach::Descriptor,
                Reach::Descriptor,
                Reach::Address,
                Reach::Descriptor,
                Reach::Address,
                Reach::Address,
            ],
            std::mem::size_of::<ClipPush>() as u32,
            &[],
        )?;
        let n = (dims[0] * dims[1] * dims[2]) as u64;
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER
            | vk::BufferUsageFlags::TRANSFER_SRC
            | vk::BufferUsageFlags::TRANSFER_DST;
        let reach = reach_voxels(method.reach_mm(spacing), spacing);
        let words = (&opacity[..], es, &pao_words[..]);
        let kept = super::pool::kept_bricks(gpu, dims, words, reach, (None, 0));
        let (ao, staging) =
            gpu.submit_and_wait(|cmd| AoPool::new(gpu, dims, kept.as_deref(), cmd))??;
        drop(staging);
        // Two bits per voxel (shaders/include/mask.glsl), in whole words.
        let mask = Buffer::new(
            gpu,
            n.div_ceil(16) * 4,
            storage,
            MemoryLocation::GpuOnly,
            "cao-mask",
        )?;
        let (clipped, clipped_slices) = initial_clipped(gpu, dims, &method)?;
        let slots = (0..MAX_FRAMES_IN_FLIGHT)
            .map(|_| FrameSlot::new(gpu, dims))
            .collect::<Result<Vec<_>>>()?;
        let mut cao = Cao {
            gpu: gpu.clone(),
            restore,
            clip,
            dims,
            spacing,
            geometry,
            max_spacing_mm: spacing.iter().cloned().fold(0.0, f64::max),
            opacity,
            clipped,
            clipped_slices,
            mask,
            pao: pao_words,
            ao,
            bricks_stale: false,
            bricks: None,
            slots,
            slot: 0,
            map_builder: ClipMapGpu::new(gpu)?,
            map_cache: HashMap::new(),
            meshes: Vec::new(),
            clip_resolution: crate::clip::DEFAULT_RESOLUTION,
            prev_boxes: Vec::new(),
            changed: Vec::new(),
            unshown: !matches!(method, MethodGpu::Open),
            background_clipped: false,
            sh_radius_mm: None,
            sh_boxes: Vec::new(),
            tool_count: 0,
            reach_boxes: Vec::new(),
            clip_brick_counts: [0; 3],
            method,
            labels,
            protect,
            any_protected,
            protect_pending: None,
            protect_bits: vol.labels.as_deref().map_or([0; 8], |l| l.protected_bits()),
        };
        match pao {
            // No method yet: V_AO = V_PAO = 1 (no brick is stored but where the pool keeps
            // them all: every word all ones); O_c and the mask are first read after the first
            // switch, whose whole restore writes them (a restore of a large volume takes
            // seconds on a CPU device, and the first picture waits for it).
            // SAFETY: `cmd` is recording (submit_and_wait); the pool's words were made with
            // TRANSFER_DST (AoPool::new) in whole 4-byte words, so a WHOLE_SIZE fill stays
            // inside, and the pool outlives the waited submission.
            Some(_) => cao.gpu.submit_and_wait(|cmd| unsafe {
                cao.gpu
                    .device
                    .cmd_fill_buffer(cmd, cao.ao.words.raw, 0, vk::WHOLE_SIZE, u32::MAX);
            })?,
            // Start unclipped: O_c = O (inside a zero border), V_AO = V_PAO everywhere (and
            // the local histograms' bleeding volume its precomputed one).
            None => cao.restore_whole()?,
        }
        Ok(cao)
    }

    /// Restores the whole volume now (O_c = O, V_AO = V_PAO, or clipped away while a probe is
    /// active; the method's own restore too), in slabs of z-slices each submitted and waited,
    /// so that at most [`RESTORE_SLAB_BYTES`] of O and V_PAO are staged at once, not the
    /// whole of both. The next frame then restores only its own boxes, and tells the whole
    /// volume changed. Call it only when no submitted command buffer still uses the CAO state
    /// (after [`Cao::new`]'s setup, or after a switch's [`Cao::set_method`] or
    /// [`Cao::replace_precomputed`]); without it the next frame restores the whole volume at
    /// once.
    pub fn restore_whole(&mut self) -> Result<()> {
        self.restore_whole_by(RESTORE_SLAB_BYTES)
    }

    /// [`Cao::restore_whole`] staging at most `slab_bytes` at once (at least one z-slice).
    pub fn restore_whole_by(&mut self, slab_bytes: u64) -> Result<()> {
        if matches!(self.method, MethodGpu::Open) {
            return Ok(());
        }
        let [nx, ny, nz] = self.dims;
        let es = self.method.density_bytes();
        let per_slice = (nx * ny * (es + super::stored::BYTES_PER_VOXEL as usize)) as u64;
        let slices = ((slab_bytes / per_slice) as usize).clamp(1, nz.max(1));
        let clipped = self.background_clipped;
        let gpu = self.gpu.clone();
        let (mut made, mut chosen) = (Ok(None), Ok(None));
        gpu.submit_and_wait(|cmd| {
            made = self.make_whole(cmd);
            chosen = self.choose_bricks(cmd);
        })?;
        // No submitted work reads the old O_c or V_AO (this method's contract).
        drop((made?, chosen?));
        let mut staged = None;
        for z0 in (0..nz).step_by(slices) {
            let b = VoxelBox {
                min: [0, 0, z0 as i32],
                max: [nx as i32, ny as i32, (z0 + slices).min(nz) as i32],
            };
            let (s, at) = self.stage_into(staged.take(), std::iter::once(&b))?;
            self.gpu.submit_and_wait(|cmd| {
                self.record_restore(cmd, &[b], clipped, (&s.opacity, &s.pao), &at);
                let bufs = MethodBuffers {
                    density: &self.clipped,
                    density_stride: self.clipped_stride(),
                    mask: &self.mask,
                    pre_a: &s.pao,
                    out_a: &self.ao.words,
                    ao_table: &self.ao.table,
                };
                self.method.record_restore(cmd, &bufs, &[b], &at, clipped);
            })?;
            staged = Some(s);
        }
        self.prev_boxes.clear();
        self.unshown = true;
        Ok(())
    }

    /// Swaps in a new O and its V_PAO (a transfer-function switch) and makes the
    /// next [`Cao::record_frame`] restore the whole volume from them first, so its clip and
    /// update passes (over the current tools' boxes) start from exactly the state a fresh
    /// [`Cao::new`] has. The old buffers are dropped here: call it only when no submitted
    /// command buffer still uses them (after the frame's wait).
    /// A method whose state follows O (LAO's skipping data) comes with [`Cao::set_method`].
    pub fn replace_precomputed(&mut self, opacity: Buffer, pao: Buffer) -> Result<()> {
        let n = (self.dims[0] * self.dims[1] * self.dims[2]) as u64;
        // O is 16-bit or f32 (by the method set next), and may be rounded up to whole words.
        let bytes = super::stored::bytes(n);
        if opacity.size < bytes || pao.size != bytes {
            return Err(GpuError::Other(format!(
                "{}: new opacity ({} bytes) or V_PAO ({} bytes, not {bytes}) \
                 does not match the {:?} volume",
                self.geometry.name, opacity.size, pao.size, self.dims
            )));
        }
        self.opacity = opacity.read_back()?;
        self.pao = pao.read_back()?;
        self.prev_boxes = vec![VoxelBox::whole(self.dims)];
        self.bricks_stale = true;
        Ok(())
    }

    /// Where O, V_PAO or the method changed: V_AO's bricks chosen anew for them (the next
    /// restore, a whole one, fills them), the table copied in by `cmd`. Returns the old V_AO,
    /// which frames in flight may still read, and the table's staging, which `cmd` reads.
    fn choose_bricks(&mut self, cmd: vk::CommandBuffer) -> Result<Option<(AoPool, Buffer)>> {
        if !std::mem::take(&mut self.bricks_stale) {
            return Ok(None);
        }
        let reach = reach_voxels(self.reach_mm(), self.spacing);
        let words = (
            &self.opacity[..],
            self.method.density_bytes(),
            &self.pao[..],
        );
        // The old V_AO, still held, goes once the frames that read it have finished.
        let freed = self.ao.words.size + self.ao.table.size;
        let kept =
            super::pool::kept_bricks(&self.gpu, self.dims, words, reach, (self.bricks, freed));
        let (new, staging) = AoPool::new(&self.gpu, self.dims, kept.as_deref(), cmd)?;
        Ok(Some((std::mem::replace(&mut self.ao, new), staging)))
    }

    /// Stores V_AO in bricks from now on (where they leave out a quarter of it), or whole, or
    /// with None in bricks only where GPU memory is short (the default), restoring the whole
    /// volume into it. Call it as [`Cao::restore_whole`].
    pub fn store_in_bricks(&mut self, bricks: Option<bool>) -> Result<()> {
        self.bricks = bricks;
        self.bricks_stale = true;
        self.restore_whole()
    }

    /// Where voxel v of O_c lies: [`Cao::clipped`] at \[0] + v.x + \[1] v.y + \[2] v.z, inside LAO's
    /// zero border while the method is LAO; \[3] is 1 where O and O_c are f32 (the filters'
    /// density, whose gradients 16 bits would coarsen), 0 where they are 16-bit.
    pub fn clipped_stride(&self) -> [i32; 4] {
        let mut s = self.method.clipped_stride(self.dims);
        s[0] -= s[2] * self.clipped_slices[0] as i32;
        s
    }

    /// Whether O_c is held only in the z-slices each frame's update reads (`Cao::clipped`):
    /// under every method that reads it ([`MethodGpu::window_reach`]), unless the SH
    /// visibility, which reads the whole O_c, is on.
    pub fn windowed(&self) -> bool {
        self.method.window_reach().is_some() && self.sh_radius_mm.is_none()
    }

    /// The z-slices of O_c's grid (LAO's zero border included) the GPU holds now, [from, to).
    pub fn clipped_slices(&self) -> [usize; 2] {
        self.clipped_slices
    }

    /// The z-slices of the whole grid O_c lies in (LAO's zero border included).
    fn whole_slices(&self) -> [usize; 2] {
        [0, self.dims[2] + 2 * self.method.clipped_pad()[2]]
    }

    /// Bytes of O_c's z-slices `slices`.
    fn clipped_bytes(&self, slices: [usize; 2]) -> u64 {
        let es = self.method.density_bytes();
        let [_, _, sz, _] = self.method.clipped_stride(self.dims);
        sz as u64 * (slices[1] - slices[0]) as u64 * es as u64
    }

    /// Where O_c must be whole but is a window (the SH visibility came on, or a new method's
    /// empty one): a whole zero O_c replaces it, zeroed in `cmd`, to be filled by a whole
    /// restore recorded after it. Returns the old one, which frames in flight may still read.
    fn make_whole(&mut self, cmd: vk::CommandBuffer) -> Result<Option<Buffer>> {
        let whole = self.whole_slices();
        if self.windowed() || self.clipped_slices == whole {
            return Ok(None);
        }
        let new = Buffer::new(
            &self.gpu,
            self.clipped_bytes(whole).next_multiple_of(4),
            clipped_usage(),
            MemoryLocation::GpuOnly,
            "cao-clipped",
        )?;
        // SAFETY: `cmd` is recording outside a render pass (the callers' contract); `new` has
        // TRANSFER_DST and a size in whole words, so a WHOLE_SIZE fill stays inside it; the
        // caller keeps it (in `self`) past the submission.
        unsafe {
            self.gpu
                .device
                .cmd_fill_buffer(cmd, new.raw, 0, vk::WHOLE_SIZE, 0);
        }
        self.gpu.barrier(cmd);
        self.clipped_slices = whole;
        Ok(Some(std::mem::replace(&mut self.clipped, new)))
    }

    /// The z-slices of O_c this frame's update over `boxes` reads: theirs and the method's
    /// reach beyond them on both sides (LAO's farthest sample's footprint, its zero border;
    /// the local histograms' S_r), within the grid.
    fn window_of(&self, boxes: &[VoxelBox]) -> [usize; 2] {
        let pad = self.method.clipped_pad()[2];
        let reach = self.method.window_reach().unwrap_or(0);
        let mut z = boxes
            .iter()
            .filter(|b| b.voxels() > 0)
            .map(|b| b.min[2]..b.max[2]);
        let Some(first) = z.next() else {
            return [0, 0];
        };
        let (lo, hi) = z.fold((first.start, first.end), |(lo, hi), r| {
            (lo.min(r.start), hi.max(r.end))
        });
        // Voxel z lies at z + pad in the padded grid and reads `reach` slices either side.
        let whole = self.whole_slices()[1];
        [
            (lo as usize + pad).saturating_sub(reach),
            (hi as usize + pad + reach).min(whole),
        ]
    }

    /// O_c's background (O, or 0 while a probe is active) over the padded grid's z-slices
    /// `slices`, inside LAO's zero border: what a window starts as before the clip pass.
    fn window_bytes(&self, slices: [usize; 2]) -> Vec<u8> {
        use rayon::prelude::*;
        let es = self.method.density_bytes();
        let [px, py, pz] = self.method.clipped_pad();
        let [nx, ny, nz] = self.dims;
        let plane = (nx + 2 * px) * (ny + 2 * py) * es;
        let mut out = vec![0u8; plane * (slices[1] - slices[0])];
        if self.background_clipped {
            return out;
        }
        out.par_chunks_mut(plane.max(1))
            .zip(slices[0]..slices[1])
            .filter(|(_, s)| (pz..pz + nz).contains(s))
            .for_each(|(slice, s)| {
                let z = s - pz;
                for y in 0..ny {
                    let dst = ((y + py) * (nx + 2 * px) + px) * es;
                    let src = (nx * (y + ny * z)) * es;
                    slice[dst..dst + nx * es].copy_from_slice(&self.opacity[src..src + nx * es]);
                }
            });
        out
    }

    /// O_c, laid out by [`Cao::clipped_stride`].
    pub fn clipped(&self) -> &Buffer {
        &self.clipped
    }

    /// O_c read back, x fastest, without a border.
    /// Outside a window ([`Cao::windowed`]) it is the background: O, or 0 while a probe is
    /// active.
    pub fn read_clipped(&self) -> Result<Vec<f32>> {
        let [o, sy, sz, f32] = self.clipped_stride().map(|s| s as i64);
        let held = self.clipped_bytes(self.clipped_slices) as usize / self.method.density_bytes();
        let value = |bytes: &[u8], i: usize| match f32 {
            1 => f32::from_le_bytes(bytes[4 * i..4 * i + 4].try_into().unwrap()),
            _ => super::stored::unpack(u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]])),
        };
        let all = self.clipped.read_back()?;
        let [nx, ny, nz] = self.dims;
        let mut out = Vec::with_capacity(nx * ny * nz);
        for z in 0..nz {
            for y in 0..ny {
                let row = o + sy * y as i64 + sz * z as i64;
                let background = nx * (y + ny * z);
                for x in 0..nx {
                    out.push(match usize::try_from(row + x as i64) {
                        Ok(i) if i < held => value(&all, i),
                        _ if self.background_clipped => 0.0,
                        _ => value(&self.opacity, background + x),
                    });
                }
            }
        }
        Ok(out)
    }

    /// Sets the AO method and returns the one it replaces. V_PAO must already hold the new
    /// method's AO of the unclipped volume ([`Cao::replace_precomputed`]). Call it only when no
    /// submitted command buffer still uses O_c (or what the old method reads): a method that
    /// lays O_c out otherwise gets a new one.
    pub fn set_method(&mut self, method: MethodGpu) -> Result<MethodGpu> {
        let method = method.for_update()?;
        // The next frame's whole restore fills it, or its windows.
        (self.clipped, self.clipped_slices) = initial_clipped(&self.gpu, self.dims, &method)?;
        // The next frame restores the whole volume from the new method's values (its bleeding
        // volume included), into V_AO's bricks for the new method's reach.
        self.prev_boxes = vec![VoxelBox::whole(self.dims)];
        self.bricks_stale = true;
        Ok(std::mem::replace(&mut self.method, method))
    }

    /// The AO method and its GPU state.
    pub fn method(&self) -> &MethodGpu {
        &self.method
    }

    /// The AO method's name, as `--ao` spells it (lao, filter-gauss, histogram, ...), or
    /// "none" before one is computed ([`MethodGpu::Open`]).
    pub fn method_name(&self) -> String {
        self.method.name()
    }

    /// The filters, when they are the AO method.
    pub fn filter(&self) -> Option<&FilterGpu> {
        self.method.filter()
    }

    /// The local-histogram method's state, when it is the AO method.
    pub fn histogram(&self) -> Option<&HistogramGpu> {
        self.method.histogram()
    }

    pub fn histogram_mut(&mut self) -> Option<&mut HistogramGpu> {
        self.method.histogram_mut()
    }

    /// The AO method's reach in mm ([`MethodGpu::reach_mm`]).
    pub fn reach_mm(&self) -> f64 {
        self.method.reach_mm(self.spacing)
    }

    /// The dilation radius in mm: the method's reach, the trilinear footprint around its
    /// farthest sample and the anti-aliasing spread around the clipped voxel (a voxel diagonal
    /// each), plus 1 %.
    pub fn dilation_radius_mm(&self) -> f64 {
        let diag = 3f64.sqrt() * self.max_spacing_mm;
        (self.reach_mm() + 2.0 * diag) * 1.01
    }

    /// The cached map of `tool`, built now if missing: with the GPU builder when `on_gpu`, else
    /// with the CPU reference ([`ClipMap::build`]). A GPU build needs a submission of its own,
    /// so it cannot happen while a frame is being recorded (the recording holds the command
    /// pool): [`Cao::prepare_maps`] builds the maps before, and recording uses the CPU only for a
    /// map nobody prepared.
    /// `radius_mm` is the dilation radius (the LAO one or [`Cao::sh_radius_mm`]).
    fn map_for(
        &mut self,
        tool: &Tool,
        placement: &Placement,
        on_gpu: bool,
        radius_mm: f64,
    ) -> Result<ClipMap> {
        // Radius in tool units, rounded up to 1/256 so the cache stays small and stays conservative.
        let r_world = radius_mm * 1e-3 * placement.scale as f64;
        let r_local = r_world / tool.size.max(1e-6) as f64;
        let q = (r_local * 256.0).ceil() as u32;
        let key = (tool.shape, q, self.clip_resolution);
        if let Some(m) = self.map_cache.get(&key) {
            return Ok(m.clone());
        }
        let mesh = shape_mesh(tool.shape, &self.meshes).ok_or_else(|| {
            GpuError::Other(format!("tool shape {:?} has no mesh loaded", tool.shape))
        })?;
        let radius = q as f32 / 256.0;
        let map = if on_gpu {
            self.map_builder
                .build(&mesh, self.clip_resolution, radius)?
        } else {
            ClipMap::build(&mesh, self.clip_resolution, radius)
        };
        self.map_cache.insert(key, map.clone());
        Ok(map)
    }

    /// The safety margins each of `tools` (active or not: the warning comes before the cut) is
    /// inside ([`crate::clip::margin`]), with `fields` in `grid` placed at `placement`: this
    /// volume's, or the full-resolution one it is a downsample of (the tools' maps are the
    /// same; the voxel centres tested are the grid's).
    pub fn margin_hits(
        &mut self,
        tools: &[Tool],
        (grid, placement): (&Volume, &Placement),
        fields: &[MarginField],
    ) -> Result<Vec<MarginHit>> {
        if fields.is_empty() {
            return Ok(Vec::new());
        }
        let (world_from_index, dims) = (world_from_index(grid, placement), grid.dims);
        let radius = self.dilation_radius_mm();
        let mut hits = Vec::new();
        for (n, tool) in tools.iter().enumerate() {
            // the active tools' maps are cached already; an idle tool's is built on the CPU once
            let map = self.map_for(tool, placement, false, radius)?;
            let world_from_local = tool.pose.matrix() * Mat4::from_scale(Vec3::splat(tool.size));
            let local_from_index = world_from_local.inverse() * world_from_index;
            let b = box_in(&map, local_from_index.inverse(), dims);
            let range = (b.min.map(|v| v as usize), b.max.map(|v| v as usize));
            hits.extend(margin::hits(n, &map, local_from_index, range, fields));
        }
        Ok(hits)
    }

    /// Voxel index coordinates (centres at i + 0.5) to the world.
    fn world_from_index(&self, placement: &Placement) -> Mat4 {
        world_from_index(&self.geometry, placement)
    }

    /// Builds on the GPU, and caches, the clip maps the active tools need and the cache lacks.
    /// Call it before [`Cao::record_frame`], outside any command recording; [`Cao::run_frame`]
    /// does.
    pub fn prepare_maps(&mut self, tools: &[Tool], placement: &Placement) -> Result<()> {
        let radii = [Some(self.dilation_radius_mm()), self.sh_radius_mm];
        for tool in tools.iter().filter(|t| t.cuts()).take(MAX_TOOLS) {
            for r in radii.iter().flatten() {
                self.map_for(tool, placement, true, *r)?;
            }
        }
        Ok(())
    }

    /// Uploads the active tools' maps and transforms; returns their voxel boxes.
    fn prepare_tools(
        &mut self,
        tools: &[Tool],
        placement: &Placement,
    ) -> Result<(u32, Vec<VoxelBox>)> {
        let active: Vec<&Tool> = tools.iter().filter(|t| t.cuts()).take(MAX_TOOLS).collect();
        let world_from_index = self.world_from_index(placement);
        let mut gpu_tools = Vec::new();
        let mut texels: Vec<[f32; 4]> = Vec::new();
        let mut boxes = Vec::new();
        let mut sh_boxes = Vec::new();
        let mut reach = Vec::new();
        let mut brick_tools = Vec::new();
        let lao_radius = self.dilation_radius_mm();
        for tool in active {
            let map = self.map_for(tool, placement, false, lao_radius)?;
            let world_from_local = tool.pose.matrix() * Mat4::from_scale(Vec3::splat(tool.size));
            let local_from_world = world_from_local.inverse();
            let local_from_index = local_from_world * world_from_index;
            let clip_off = texels.len() as u32;
            texels.extend_from_slice(&map.clip);
            let dil_off = texels.len() as u32;
            texels.extend_from_slice(&map.dilated);
            let map_params =
                |m: &ClipMap| [m.extent, m.res as f32 / (2.0 * m.extent), m.res as f32, 0.0];
            // The SH dilation (a second map of the same shape), or the LAO one standing in.
            let (sh_off, sh_map) = match self.sh_radius_mm {
                Some(r) => {
                    let sh = self.map_for(tool, placement, false, r)?;
                    let off = texels.len() as u32;
                    texels.extend_from_slice(&sh.dilated);
                    sh_boxes.push(match tool.mode {
                        ToolMode::Probe => VoxelBox::whole(self.dims),
                        // (a measuring tool never cuts: `Tool::cuts`)
                        ToolMode::Carve | ToolMode::Measure => {
                            self.box_of(&sh, local_from_index.inverse())
                        }
                    });
                    (off, map_params(&sh))
                }
                None => (dil_off, map_params(&map)),
            };
            gpu_tools.push(ClipToolGpu {
                local_from_index: local_from_index.to_cols_array(),
                local_from_world: local_from_world.to_cols_array(),
                map: [
                    map.extent,
                    map.res as f32 / (2.0 * map.extent),
                    map.res as f32,
                    if tool.mode == ToolMode::Probe {
                        1.0
                    } else {
                        0.0
                    },
                ],
                offsets: [clip_off, dil_off, sh_off, tool.shape.code()],
                sh_map,
            });
            // A probe's box holds its inside and the voxels anti-aliased at its surface; every
            // voxel beyond is clipped away (the background, see `record_frame`).
            let b = self.box_of(&map, local_from_index.inverse());
            let r = match tool.mode {
                ToolMode::Probe => VoxelBox::whole(self.dims),
                ToolMode::Carve | ToolMode::Measure => b,
            };
            reach.push(r);
            brick_tools.push((map, local_from_index, tool.mode == ToolMode::Probe, r));
            boxes.push(b);
        }
        let bricks = bricks::classify(
            self.dims,
            &brick_tools
                .iter()
                .map(|(map, m, probe, r)| BrickTool {
                    map,
                    local_from_index: *m,
                    probe: *probe,
                    reach: (r.min, r.max),
                })
                .collect::<Vec<_>>(),
        );
        self.clip_brick_counts = bricks::counts(&bricks);
        if !gpu_tools.is_empty() {
            let slot = &mut self.slots[self.slot];
            slot.tools.write(0, bytemuck::cast_slice(&gpu_tools))?;
            let bytes: &[u8] = bytemuck::cast_slice(&texels);
            if slot
                .maps
                .as_ref()
                .is_none_or(|m| m.size < bytes.len() as u64)
            {
                // The slot's last frame has left the GPU (the caller waited for it), so its
                // smaller map buffer may go.
                slot.maps = Some(Buffer::new(
                    &self.gpu,
                    bytes.len() as u64,
                    vk::BufferUsageFlags::STORAGE_BUFFER,
                    MemoryLocation::CpuToGpu,
                    "cao-maps",
                )?);
            }
            slot.maps.as_mut().unwrap().write(0, bytes)?;
            slot.bricks
                .write(0, bytemuck::cast_slice(&bricks::pack(&bricks)))?;
        }
        self.reach_boxes = reach;
        let boxes = boxes.into_iter().filter(|b| b.voxels() > 0).collect();
        self.sh_boxes = merge_boxes(sh_boxes.into_iter().filter(|b| b.voxels() > 0).collect());
        Ok((gpu_tools.len() as u32, merge_boxes(boxes)))
    }

    /// Voxel box (index space, padded by one voxel) around the dilated shape.
    fn box_of(&self, map: &ClipMap, index_from_local: Mat4) -> VoxelBox {
        box_in(map, index_from_local, self.dims)
    }

    fn dims4(&self) -> [i32; 4] {
        [
            self.dims[0] as i32,
            self.dims[1] as i32,
            self.dims[2] as i32,
            0,
        ]
    }

    /// Puts the voxels of `boxes` in the background state: unclipped, or clipped away. Box k's
    /// O and V_PAO start at voxel `at[k]` of `o` and `pao` ([`Cao::stage`]). A window of O_c
    /// ([`Cao::windowed`]) is left alone: each frame fills its own.
    fn record_restore(
        &self,
        cmd: vk::CommandBuffer,
        boxes: &[VoxelBox],
        clipped: bool,
        (o, pao): (&Buffer, &Buffer),
        at: &[i32],
    ) {
        let flags = clipped as i32 | (self.windowed() as i32) << 1;
        for (b, &at) in boxes.iter().zip(at) {
            let push = ClipPush {
                dims: self.dims4(),
                box_min: [b.min[0], b.min[1], b.min[2], flags],
                box_max: [b.max[0], b.max[1], b.max[2], at],
                stride: self.clipped_stride(),
            };
            let bufs = [
                o,
                &self.clipped,
                &self.mask,
                pao,
                &self.ao.words,
                o,
                &self.clipped,
                &self.ao.table,
            ];
            self.restore.bind(cmd, &bufs, bytemuck::bytes_of(&push));
            dispatch_box(&self.restore, cmd, b);
        }
    }

    /// Which structures the tools leave standing (by structure index), from the next recorded
    /// frame on: a change goes into that frame's command buffer, before its clip pass.
    pub fn set_protected(&mut self, protected: &[bool]) {
        let bits = crate::volume::labels::protected_bits(protected);
        if bits != self.protect_bits {
            self.protect_bits = bits;
            self.any_protected = bits.iter().any(|&w| w != 0);
            self.protect_pending = Some(bits);
        }
    }

    /// Records one frame's AO update (restore, clip + mask, update) into `cmd`; read the
    /// metrics with [`Cao::read_metrics`] once it has executed. V_AO is then in [`Cao::ao`].
    /// Call [`Cao::prepare_maps`] first for GPU-built clip maps of new tool shapes or sizes.
    /// The frame's tool table, maps, counters and timer are the next of
    /// [`MAX_FRAMES_IN_FLIGHT`] slots: the frame recorded that many frames ago must have
    /// finished. The device-side state (O_c, the mask, V_AO) is one copy, so `cmd` must order
    /// this frame after the one before (a barrier first: `Gpu::barrier`).
    pub fn record_frame(
        &mut self,
        cmd: vk::CommandBuffer,
        tools: &[Tool],
        placement: &Placement,
        mode: Mode,
    ) -> Result<PendingFrame> {
        self.slot = (self.slot + 1) % self.slots.len();
        let (count, mut boxes) = self.prepare_tools(tools, placement)?;
        self.tool_count = count;
        if mode == Mode::Naive {
            boxes = vec![VoxelBox::whole(self.dims)];
        }
        // With a probe active every voxel outside the tools' boxes is outside the probe: clipped
        // away. A change of background restores the whole volume once; otherwise last frame's
        // boxes go back to it.
        let clipped = tools
            .iter()
            .filter(|t| t.cuts())
            .take(MAX_TOOLS)
            .any(|t| t.mode == ToolMode::Probe);
        let mut restore: Vec<VoxelBox> = std::mem::take(&mut self.prev_boxes);
        if clipped != self.background_clipped {
            restore = vec![VoxelBox::whole(self.dims)];
        }
        self.background_clipped = clipped;
        // The naive pass rewrites every voxel, so it needs no restore.
        if mode == Mode::Naive {
            restore.clear();
        }
        // O_c made whole again is filled by a whole restore; a window, by a copy of the
        // background over the slices this frame's update reads.
        let mut retired = self.make_whole(cmd)?;
        if retired.is_some() && mode == Mode::Contextual {
            restore = vec![VoxelBox::whole(self.dims)];
        }
        // Chosen anew after a change of O or method, whose whole restore this frame records.
        let retired_ao = self.choose_bricks(cmd)?;
        if self.windowed() {
            let slices = self.window_of(&boxes);
            let bytes = self.window_bytes(slices);
            let need = (bytes.len() as u64).max(4);
            if !fits(&self.clipped, need) {
                let whole = self.clipped_bytes(self.whole_slices()).max(4);
                let new = Buffer::new(
                    &self.gpu,
                    grown(need).min(whole),
                    clipped_usage(),
                    MemoryLocation::GpuOnly,
                    "cao-clipped",
                )?;
                retired = Some(std::mem::replace(&mut self.clipped, new));
            }
            self.clipped_slices = slices;
            let slot = &mut self.slots[self.slot];
            let window = staging(&self.gpu, slot.window.take(), &bytes, "cao-clipped-window")?;
            if !bytes.is_empty() {
                // SAFETY: `cmd` is recording outside a render pass (this method's contract);
                // both buffers hold `bytes.len()` bytes from 0 (`fits`, `staging`), `window`
                // has TRANSFER_SRC, `clipped` TRANSFER_DST, and both are kept (the slot,
                // `self`) until the frame has finished; the barrier below orders the copy
                // before the clip pass, and the caller's one before it orders it after the
                // last frame's update.
                unsafe {
                    let region = [vk::BufferCopy::default().size(bytes.len() as u64)];
                    self.gpu
                        .device
                        .cmd_copy_buffer(cmd, window.raw, self.clipped.raw, &region);
                }
            }
            slot.window = Some(window);
        }
        let slot = &mut self.slots[self.slot];
        // What frames in flight may still read goes when this slot's frame has finished.
        slot.retired = (retired, retired_ao);
        // SAFETY: `cmd` is recording outside a render pass (this method's contract); `counts` (16
        // bytes, TRANSFER_DST) is this frame slot's, whose last frame has finished; `protect` was
        // made from the same 8 words with TRANSFER_DST, and 32 bytes is a valid inline update.
        unsafe {
            self.gpu
                .device
                .cmd_fill_buffer(cmd, slot.counts.raw, 0, 16, 0);
            if let Some(bits) = self.protect_pending.take() {
                self.gpu.device.cmd_update_buffer(
                    cmd,
                    self.protect.raw,
                    0,
                    bytemuck::cast_slice(&bits),
                );
            }
        }
        slot.timer.begin(cmd);
        // Held out of the slot while recording, and put back below.
        let (staged, at) = self.stage(&restore, &boxes)?;
        let (o, pao) = (&staged.opacity, &staged.pao);
        let (at_restore, at_boxes) = at.split_at(restore.len());
        self.record_restore(cmd, &restore, clipped, (o, pao), at_restore);
        let bufs = MethodBuffers {
            density: &self.clipped,
            density_stride: self.clipped_stride(),
            mask: &self.mask,
            pre_a: pao,
            out_a: &self.ao.words,
            ao_table: &self.ao.table,
        };
        // The method's own restore (the local histograms' bleeding colour of last frame's
        // boxes, restored like V_AO).
        self.method
            .record_restore(cmd, &bufs, &restore, at_restore, clipped);
        self.gpu.barrier(cmd);
        self.slots[self.slot].timer.mark(cmd, "restore");
        let slot = &self.slots[self.slot];
        let (tools, maps, _) = slot.clip_buffers();
        for (b, &at) in boxes.iter().zip(at_boxes) {
            let [x, y, z, _] = self.dims4();
            let push = ClipPush {
                dims: [x, y, z, self.any_protected as i32],
                box_min: [b.min[0], b.min[1], b.min[2], count as i32],
                box_max: [b.max[0], b.max[1], b.max[2], at],
                stride: self.clipped_stride(),
            };
            let bufs = [
                o,
                &self.clipped,
                &self.mask,
                tools,
                maps,
                &slot.counts,
                &self.labels,
                &self.protect,
                o,
                &self.clipped,
            ];
            self.clip.bind(cmd, &bufs, bytemuck::bytes_of(&push));
            dispatch_box(&self.clip, cmd, b);
        }
        self.gpu.barrier(cmd);
        self.slots[self.slot].timer.mark(cmd, "clip");
        self.method
            .record_update(cmd, &bufs, &boxes, at_boxes, mode);
        self.gpu.barrier(cmd);
        self.slots[self.slot].timer.mark(cmd, "update");
        self.slots[self.slot].staged = Some(staged);
        let visited = boxes.iter().map(|b| b.voxels()).sum();
        let touched = restore.into_iter().chain(boxes.iter().copied());
        self.changed = if std::mem::take(&mut self.unshown) {
            vec![VoxelBox::whole(self.dims)]
        } else {
            merge_boxes(touched.filter(|b| b.voxels() > 0).collect())
        };
        self.prev_boxes = boxes;
        Ok(PendingFrame {
            visited,
            mode,
            clipped_outside: clipped,
            slot: self.slot,
        })
    }

    /// Metrics of a recorded frame, after its command buffer finished (and before its slot
    /// is recorded again).
    pub fn read_metrics(&mut self, pending: PendingFrame) -> Result<FrameMetrics> {
        let n = self.dims.iter().product::<usize>() as u64;
        let slot = &mut self.slots[pending.slot];
        // The frame has finished: O and V_PAO staged for a whole-volume restore (a switch, a
        // probe coming or going) go now, not when the slot comes round again.
        if slot.staged.as_ref().is_some_and(|s| s.pao.size >= n) {
            slot.staged = None;
        }
        if slot.window.as_ref().is_some_and(|w| w.size >= n) {
            slot.window = None;
        }
        let slot = &self.slots[pending.slot];
        let c: &[u32] = bytemuck::cast_slice(&slot.counts.mapped()?[..12]);
        let total = (self.dims[0] * self.dims[1] * self.dims[2]) as u64;
        let times = slot.timer.read()?;
        let ms = |name: &str| times.iter().find(|t| t.0 == name).map_or(0.0, |t| t.1);
        let (mut clipped, affected) = (c[0] as u64, c[1] as u64);
        if pending.clipped_outside {
            // The voxels outside the boxes, all clipped away (the counts cover the boxes).
            clipped += total - pending.visited;
        }
        // The naive baseline recomputes every voxel that is not clipped away.
        let recomputed = match pending.mode {
            Mode::Contextual => affected,
            Mode::Naive => total - clipped,
        };
        Ok(FrameMetrics {
            clipped,
            recomputed,
            unaffected: total - clipped - recomputed,
            visited: pending.visited,
            restore_ms: ms("restore"),
            clip_ms: ms("clip"),
            update_ms: ms("update"),
        })
    }

    /// Records, submits and waits for one frame's AO update.
    pub fn run_frame(
        &mut self,
        tools: &[Tool],
        placement: &Placement,
        mode: Mode,
    ) -> Result<FrameMetrics> {
        self.prepare_maps(tools, placement)?;
        let gpu = self.gpu.clone();
        let mut pending = Ok(PendingFrame {
            visited: 0,
            mode,
            clipped_outside: false,
            slot: 0,
        });
        gpu.submit_and_wait(|cmd| pending = self.record_frame(cmd, tools, placement, mode))?;
        self.read_metrics(pending?)
    }

    /// O, the unclipped opacity the precomputed volumes were computed from, uploaded whole
    /// (host-visible: the GPU keeps no whole O), and where its voxels lie (in
    /// [`Cao::clipped_stride`]'s form: no border).
    pub fn opacity(&self) -> Result<(Buffer, [i32; 4])> {
        let [x, y, z, _] = LaoLayout::unpadded_stride(self.dims);
        let o = Buffer::from_slice(
            &self.gpu,
            &self.opacity,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "opacity",
        )?;
        Ok((o, [x, y, z, self.method.float_density() as i32]))
    }

    /// Stages this frame's O and V_PAO: the voxels of every box of `restore`, then of `boxes`,
    /// each x fastest, into this frame slot's staging buffers, taken out of the slot (each made
    /// anew where it is too small or more than four times too large; dropped once a frame
    /// that staged a whole volume has finished, [`Cao::read_metrics`]). Returns them and where
    /// each box starts, in voxels.
    fn stage(&mut self, restore: &[VoxelBox], boxes: &[VoxelBox]) -> Result<(Staged, Vec<i32>)> {
        let old = self.slots[self.slot].staged.take();
        self.stage_into(old, restore.iter().chain(boxes))
    }

    /// [`Cao::stage`] into `old`'s buffers where they fit.
    fn stage_into<'a>(
        &self,
        old: Option<Staged>,
        boxes: impl Iterator<Item = &'a VoxelBox>,
    ) -> Result<(Staged, Vec<i32>)> {
        let es = self.method.density_bytes();
        let pes = super::stored::BYTES_PER_VOXEL as usize;
        let nx = self.dims[0];
        let ny = self.dims[1];
        let mut at = Vec::new();
        let (mut o, mut pao): (Vec<u8>, Vec<u8>) = (Vec::new(), Vec::new());
        for b in boxes {
            let start = pao.len() / pes;
            at.push(i32::try_from(start).map_err(|_| {
                GpuError::Other(format!(
                    "{}: a frame's boxes hold more than 2^31 voxels",
                    self.geometry.name
                ))
            })?);
            let [x0, y0, z0] = b.min.map(|v| v as usize);
            let [x1, y1, z1] = b.max.map(|v| v as usize);
            for z in z0..z1 {
                for y in y0..y1 {
                    let row = x0 + nx * (y + ny * z);
                    o.extend_from_slice(&self.opacity[row * es..(row + x1 - x0) * es]);
                    pao.extend_from_slice(&self.pao[row * pes..(row + x1 - x0) * pes]);
                }
            }
        }
        let (old_o, old_pao) = old.map_or((None, None), |s| (Some(s.opacity), Some(s.pao)));
        let staged = Staged {
            opacity: staging(&self.gpu, old_o, &o, "cao-opacity-boxes")?,
            pao: staging(&self.gpu, old_pao, &pao, "cao-pao-boxes")?,
        };
        Ok((staged, at))
    }

    /// The last frame's voxel categories read back, one per voxel (0: clipped, 1: affected,
    /// 2: unaffected; restored boxes read 2, or 0 while a probe is active). The GPU holds two
    /// bits each, sixteen to a word (shaders/include/mask.glsl).
    pub fn read_mask(&self) -> Result<Vec<u8>> {
        let bytes = self.mask.read_back()?;
        let n = self.dims.iter().product::<usize>();
        Ok((0..n)
            .map(|i| {
                let w = &bytes[4 * (i / 16)..][..4];
                let word = u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
                ((word >> (2 * (i % 16))) & 3) as u8
            })
            .collect())
    }

    /// The tool table and clip maps of the frame recorded last, for the passes after CAO's in
    /// the same command buffer (the ray caster's clipping, the SH update).
    pub fn clip_buffers(&self) -> (&Buffer, &Buffer, &Buffer) {
        self.slots[self.slot].clip_buffers()
    }
}

/// The most O and V_PAO bytes [`Cao::restore_whole`] stages at once (at least one z-slice):
/// small beside a clinical CT's volumes, and few enough submissions for a quick restore.
pub const RESTORE_SLAB_BYTES: u64 = 8 << 20;

/// What one frame in flight writes from the host or reads back: the tools' table and maps, the
/// category counters and the pass timer.
struct FrameSlot {
    tools: Buffer,
    maps: Option<Buffer>,
    /// The ray caster's clip state per brick ([`bricks::classify`]).
    bricks: Buffer,
    counts: Buffer,
    /// This frame's O and V_PAO, box by box ([`Cao::stage`]).
    staged: Option<Staged>,
    /// This frame's O_c background over its window's slices ([`Cao::windowed`]).
    window: Option<Buffer>,
    /// An O_c and a V_AO this frame replaced, which earlier frames still in flight may read.
    retired: (Option<Buffer>, Option<(AoPool, Buffer)>),
    timer: GpuTimer,
}

/// A frame's O and V_PAO in its boxes ([`Cao::stage`]).
struct Staged {
    opacity: Buffer,
    pao: Buffer,
}

/// `bytes` in a host-visible storage buffer: `old` where it [`fits`], else one made anew
/// ([`grown`]).
fn staging(gpu: &Gpu, old: Option<Buffer>, bytes: &[u8], name: &str) -> Result<Buffer> {
    let need = (bytes.len() as u64).max(4);
    let mut buf = match old {
        Some(b) if fits(&b, need) => b,
        _ => Buffer::new(
            gpu,
            grown(need),
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC,
            MemoryLocation::CpuToGpu,
            name,
        )?,
    };
    buf.write(0, bytes)?;
    Ok(buf)
}

impl FrameSlot {
    fn new(gpu: &Gpu, dims: [usize; 3]) -> Result<FrameSlot> {
        let n = bricks::grid(dims);
        Ok(FrameSlot {
            bricks: Buffer::new(
                gpu,
                (n[0] * n[1] * n[2]).div_ceil(4) as u64 * 4,
                vk::BufferUsageFlags::STORAGE_BUFFER,
                MemoryLocation::CpuToGpu,
                "cao-clip-bricks",
            )?,
            tools: Buffer::new(
                gpu,
                (MAX_TOOLS.max(1) * std::mem::size_of::<ClipToolGpu>()) as u64,
                vk::BufferUsageFlags::STORAGE_BUFFER,
                MemoryLocation::CpuToGpu,
                "cao-tools",
            )?,
            maps: None,
            counts: Buffer::new(
                gpu,
                16,
                vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_DST,
                MemoryLocation::GpuToCpu,
                "cao-counts",
            )?,
            staged: None,
            window: None,
            retired: (None, None),
            timer: GpuTimer::new(gpu, 8)?,
        })
    }

    /// The tools, their maps (the tool table stands in while no map was uploaded) and the
    /// bricks' clip states.
    fn clip_buffers(&self) -> (&Buffer, &Buffer, &Buffer) {
        (
            &self.tools,
            self.maps.as_ref().unwrap_or(&self.tools),
            &self.bricks,
        )
    }
}

/// Whether `b` holds `need` bytes and is not more than four times too large (a reused buffer,
/// so that boxes changing size frame by frame neither make it anew nor let it creep).
fn fits(b: &Buffer, need: u64) -> bool {
    b.size >= need && b.size <= 4 * need.max(1 << 20)
}

/// The size a reused buffer is made with for `need` bytes: a quarter more, in 64 KiB steps, so
/// that boxes growing a little frame by frame do not make it anew each time.
fn grown(need: u64) -> u64 {
    (need + need / 4).next_multiple_of(1 << 16)
}

fn clipped_usage() -> vk::BufferUsageFlags {
    vk::BufferUsageFlags::STORAGE_BUFFER
        | vk::BufferUsageFlags::TRANSFER_SRC
        | vk::BufferUsageFlags::TRANSFER_DST
}

/// O_c as a CAO state under `method` starts, and the z-slices it holds: for LAO and the local
/// histograms an empty window ([`Cao::windowed`]; made whole at the first restore or frame
/// where the SH visibility needs it), else the whole volume, zero (a whole restore fills it).
fn initial_clipped(
    gpu: &Gpu,
    dims: [usize; 3],
    method: &MethodGpu,
) -> Result<(Buffer, [usize; 2])> {
    if method.window_reach().is_some() {
        let b = Buffer::new(
            gpu,
            4,
            clipped_usage(),
            MemoryLocation::GpuOnly,
            "cao-clipped",
        )?;
        return Ok((b, [0, 0]));
    }
    Ok((clipped_buffer(gpu, dims, method)?, [0, dims[2]]))
}

/// O_c for `method`, zero throughout (LAO's zero border stays so).
fn clipped_buffer(gpu: &Gpu, dims: [usize; 3], method: &MethodGpu) -> Result<Buffer> {
    let voxels = method.clipped_voxels(dims) as u64;
    // Whole 4-byte words: the fill below writes whole words.
    let bytes = (voxels.max(1) * method.density_bytes() as u64).next_multiple_of(4);
    let b = Buffer::new(
        gpu,
        bytes,
        clipped_usage(),
        MemoryLocation::GpuOnly,
        "cao-clipped",
    )?;
    // SAFETY: `cmd` is recording (submit_and_wait); `b` has TRANSFER_DST and a size in whole words,
    // so a WHOLE_SIZE fill stays inside it; it outlives the waited submission.
    gpu.submit_and_wait(|cmd| unsafe {
        gpu.device.cmd_fill_buffer(cmd, b.raw, 0, vk::WHOLE_SIZE, 0);
    })?;
    Ok(b)
}

/// A recorded frame whose metrics are not read yet.
#[derive(Clone, Copy, Debug)]
pub struct PendingFrame {
    visited: u64,
    mode: Mode,
    /// Every voxel outside the boxes is clipped away (a probe is active).
    clipped_outside: bool,
    /// The [`FrameSlot`] holding its counters and timer.
    slot: usize,
}

/// Voxel index coordinates (centres at i + 0.5) of `grid` placed at `placement` to the world.
fn world_from_index(grid: &Volume, placement: &Placement) -> Mat4 {
    let d = grid.dims.map(|n| 1.0 / n as f32);
    world_from_tex(grid, placement) * Mat4::from_scale(Vec3::from_array(d))
}

/// The voxel box of a grid of `dims` that holds what `map`'s tool (its local frame to voxel
/// index coordinates: `index_from_local`) may hide, a voxel more on every side.
fn box_in(map: &ClipMap, index_from_local: Mat4, dims: [usize; 3]) -> VoxelBox {
    let (e, (z0, z1)) = (map.extent, map.z_range);
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for c in 0..8 {
        let p = Vec3::new(
            if c & 1 == 0 { -e } else { e },
            if c & 2 == 0 { -e } else { e },
            if c & 4 == 0 { z0 } else { z1 },
        );
        let q = index_from_local.transform_point3(p);
        lo = lo.min(q);
        hi = hi.max(q);
    }
    let clamp = |v: f32, a: usize| (v as i32).clamp(0, dims[a] as i32);
    VoxelBox {
        min: [0, 1, 2].map(|a| clamp(lo[a].floor() - 1.0, a)),
        max: [0, 1, 2].map(|a| clamp(hi[a].ceil() + 1.0, a)),
    }
}
