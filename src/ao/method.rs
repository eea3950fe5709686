//! The one AO-method interface (docs/design.md, "AO methods"): [`MethodGpu`], the method a CAO
//! state drives with its GPU state, and [`MethodBuffers`], what every method's passes read and
//! write, by role. Each method's state and passes live in a file of their own (lao.rs,
//! filter_gpu.rs, histogram_gpu.rs); this file only delegates.

use super::cao::Mode;
use super::filter_gpu::FilterGpu;
use super::histogram_gpu::HistogramGpu;
use super::lao::{LaoLayout, LaoMethod, LaoParams, SkipBuffers};
use super::voxel_box::VoxelBox;
use super::AoMethod;
use crate::gpu::{Buffer, Gpu, Result};
use crate::volume::Volume;
use ash::vk;

/// The volumes a method's pass over voxel boxes reads and writes, by role. Where a pass reads
/// no mask or no V_PAO (a precompute), any buffer stands in.
#[derive(Clone, Copy)]
pub struct MethodBuffers<'a> {
    /// The density the method reads: O_c (laid out by [`super::cao::Cao::clipped_stride`]), or
    /// for a precompute the unclipped O (for the local histograms q, for the filters their
    /// density).
    pub density: &'a Buffer,
    /// CAO's voxel categories (shaders/include/mask.glsl).
    pub mask: &'a Buffer,
    /// V_PAO: the method's AO of the unclipped volume.
    pub pre_a: &'a Buffer,
    /// Where the pass writes its AO: V_AO, or V_PAO for a precompute.
    pub out_a: &'a Buffer,
}

impl<'a> MethodBuffers<'a> {
    /// A precompute's roles: `density` read, `out` written, nothing else read.
    pub fn precompute(density: &'a Buffer, out: &'a Buffer) -> MethodBuffers<'a> {
        MethodBuffers {
            density,
            mask: density,
            pre_a: out,
            out_a: out,
        }
    }
}

/// The AO method a CAO state drives, with its GPU state: what recomputes the category-b
/// voxels, whose reach the dilation covers, how O_c is laid out for it, and what it adds to a
/// restore. V_PAO holds that method's AO of the unclipped volume. [`super::AoMethod`] is the
/// configuration one of these is made from.
///
/// A method is one file holding its state and passes, and one arm here (docs/design.md, "AO
/// methods").
// One per CAO state: the sizes do not matter.
#[allow(clippy::large_enum_variant)]
pub enum MethodGpu {
    /// No method yet: AO 1 everywhere (V_PAO open), for a first picture before the configured
    /// method's precompute is done (a fast start, `app::frame_loop`). Its frames run the clip
    /// machinery alone, so the tools cut the picture while V_AO stays 1.
    Open,
    Lao(LaoMethod),
    Filter(FilterGpu),
    Histogram(HistogramGpu),
}

impl MethodGpu {
    /// LAO with `params` on `vol`, `skip` the skipping data of its O.
    pub fn lao(gpu: &Gpu, vol: &Volume, params: LaoParams, skip: SkipBuffers) -> Result<MethodGpu> {
        let geometry = (&vol.name[..], vol.dims, vol.spacing);
        Ok(MethodGpu::Lao(LaoMethod::new(gpu, geometry, params, skip)?))
    }

    /// The method's name, as `--ao` spells it (lao, filter-gauss, histogram, ...), or "none"
    /// ([`MethodGpu::Open`]).
    pub fn name(&self) -> String {
        match self {
            MethodGpu::Open => "none".into(),
            MethodGpu::Lao(_) => AoMethod::Lao.name(),
            MethodGpu::Filter(f) => AoMethod::Filter(f.params).name(),
            MethodGpu::Histogram(h) => AoMethod::Histogram(h.params).name(),
        }
    }

    /// The reach in mm: for LAO the farthest sample, (M - 1) D; for the filters the farthest
    /// box member; for the local histograms the farthest member of S_r.
    pub fn reach_mm(&self, spacing: [f64; 3]) -> f64 {
        match self {
            MethodGpu::Open => 0.0,
            MethodGpu::Lao(l) => l.reach_mm(),
            MethodGpu::Filter(f) => f.params.reach_mm(spacing),
            MethodGpu::Histogram(h) => h.reach_mm(),
        }
    }

    /// Whether O and O_c are f32 (the filters' density, whose gradients 16 bits would
    /// coarsen), not 16-bit.
    pub fn float_density(&self) -> bool {
        matches!(self, MethodGpu::Filter(_))
    }

    /// Where voxel v of O_c lies for this method: [0] + v.x + [1] v.y + [2] v.z (inside LAO's
    /// zero border for LAO); [3] is 1 where O_c is f32 ([`MethodGpu::float_density`]).
    pub fn clipped_stride(&self, dims: [usize; 3]) -> [i32; 4] {
        let [x, y, z, _] = match self {
            MethodGpu::Lao(l) => l.stride(),
            _ => LaoLayout::unpadded_stride(dims),
        };
        [x, y, z, self.float_density() as i32]
    }

    /// Voxels O_c holds for this method (LAO's zero border included).
    pub fn clipped_voxels(&self, dims: [usize; 3]) -> usize {
        match self {
            MethodGpu::Lao(l) => l.padded_len(),
            _ => dims.iter().product(),
        }
    }

    /// Whether the method has a bleeding volume ([`MethodGpu::bleeding`]).
    pub fn has_bleeding(&self) -> bool {
        matches!(self, MethodGpu::Histogram(_))
    }

    /// This frame's bleeding colour volume (RGBA8 per voxel), for the methods that have one.
    pub fn bleeding(&self) -> Option<&Buffer> {
        match self {
            MethodGpu::Histogram(h) => Some(&h.e),
            _ => None,
        }
    }

    /// Records what the method restores beside CAO's restore of V_AO (which comes first): its
    /// bleeding volume over `boxes`, as the background is (`clipped`: a probe is active).
    pub fn record_restore(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        clipped: bool,
    ) {
        if let MethodGpu::Histogram(h) = self {
            h.record_restore(cmd, bufs, boxes, clipped);
        }
    }

    /// Records the region recompute: the AO of the voxels of `boxes` from O_c into V_AO, CAO's
    /// categories as `mode` says.
    pub fn record_update(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        mode: Mode,
    ) {
        match self {
            MethodGpu::Open => {}
            MethodGpu::Lao(l) => l.record(cmd, bufs, boxes, mode),
            MethodGpu::Filter(f) => f.record(cmd, bufs, boxes, mode),
            MethodGpu::Histogram(h) => h.record(cmd, bufs, boxes, mode),
        }
    }

    /// What a CAO state keeps of the precompute's state: all but LAO's padded O and bricks
    /// ([`SkipBuffers::for_update`]). Call it once no submitted work reads them.
    pub fn for_update(self) -> Result<MethodGpu> {
        Ok(match self {
            MethodGpu::Lao(l) => MethodGpu::Lao(l.for_update()?),
            m => m,
        })
    }

    /// An independent copy (buffers of its own), for a second CAO state.
    pub fn duplicate(&self) -> Result<MethodGpu> {
        Ok(match self {
            MethodGpu::Open => MethodGpu::Open,
            MethodGpu::Lao(l) => MethodGpu::Lao(l.duplicate()?),
            MethodGpu::Filter(f) => MethodGpu::Filter(f.duplicate()?),
            MethodGpu::Histogram(h) => MethodGpu::Histogram(h.duplicate()?),
        })
    }

    /// GPU memory the method holds beyond the volumes every method has (O, O_c, the mask,
    /// V_PAO, V_AO).
    pub fn resident_bytes(&self) -> u64 {
        match self {
            MethodGpu::Open => 0,
            MethodGpu::Lao(l) => l.resident_bytes(),
            MethodGpu::Filter(f) => f.resident_bytes(),
            MethodGpu::Histogram(h) => h.resident_bytes(),
        }
    }

    /// The filters, when they are the method.
    pub fn filter(&self) -> Option<&FilterGpu> {
        match self {
            MethodGpu::Filter(f) => Some(f),
            _ => None,
        }
    }

    /// The local-histogram method's state, when it is the method.
    pub fn histogram(&self) -> Option<&HistogramGpu> {
        match self {
            MethodGpu::Histogram(h) => Some(h),
            _ => None,
        }
    }

    pub fn histogram_mut(&mut self) -> Option<&mut HistogramGpu> {
        match self {
            MethodGpu::Histogram(h) => Some(h),
            _ => None,
        }
    }
}

/// How a change of O (a TF switch, a structure shown or hidden) refreshes a method's V_PAO'
/// while the old one stays on screen ([`AoMethod::refresh`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refresh {
    /// In bounded slabs of slices, one per frame (LAO).
    Slabs,
    /// In one go (the filters: one refilter).
    OneGo,
    /// A table update and one pass, at once, the state kept (the local histograms' clusters).
    Table,
}

impl AoMethod {
    /// How a change of O refreshes this method's V_PAO'.
    pub fn refresh(&self) -> Refresh {
        match self {
            AoMethod::Lao => Refresh::Slabs,
            AoMethod::Filter(_) => Refresh::OneGo,
            AoMethod::Histogram(_) => Refresh::Table,
        }
    }
}
