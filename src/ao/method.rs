//! The one AO-method interface (docs/design.md, "AO methods"): [`MethodGpu`], the method a CAO
//! state drives with its GPU state, and [`MethodBuffers`], what every method's passes read and
//! write, by role. Each method's state and passes live in a file of their own (lao.rs,
//! filter_gpu.rs, histogram_gpu.rs); this file only delegates.

use super::cao::{Cao, Mode};
use super::filter_gpu::FilterGpu;
use super::filtered::FilterParams;
use super::histogram_gpu::HistogramGpu;
use super::lao::{
    LaoGpu, LaoKernel, LaoLayout, LaoMethod, LaoParams, LaoTiming, SkipBuffers, SkipData, SlabInput,
};
use super::voxel_box::VoxelBox;
use super::AoMethod;
use crate::gpu::{Buffer, Gpu, GpuError, Result};
use crate::volume::transfer::TransferFunction;
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
    /// Where voxel v of `density` lies: \[0] + v.x + \[1] v.y + \[2] v.z (\[3]: 1 where it is
    /// f32), as [`super::cao::Cao::clipped_stride`] says; a precompute's O has no border.
    pub density_stride: [i32; 4],
    /// CAO's voxel categories (shaders/include/mask.glsl).
    pub mask: &'a Buffer,
    /// V_PAO: the method's AO of the unclipped volume, in a frame's boxes as CAO stages them
    /// (the host keeps it whole): each pass is told where each box starts.
    pub pre_a: &'a Buffer,
    /// Where the pass writes its AO: V_AO, or V_PAO for a precompute.
    pub out_a: &'a Buffer,
    /// How `out_a` is laid out: V_AO's brick table ([`super::pool::AoPool`]), or a precompute's
    /// one-word table of a volume stored whole ([`super::pool::whole_table`]).
    pub ao_table: &'a Buffer,
}

impl<'a> MethodBuffers<'a> {
    /// A precompute's roles: `density` read, `out` written whole (`whole`:
    /// [`super::pool::whole_table`]), nothing else read.
    pub fn precompute(
        density: &'a Buffer,
        dims: [usize; 3],
        (out, whole): (&'a Buffer, &'a Buffer),
    ) -> MethodBuffers<'a> {
        MethodBuffers {
            density,
            density_stride: LaoLayout::unpadded_stride(dims),
            mask: density,
            pre_a: out,
            out_a: out,
            ao_table: whole,
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

    /// The state of the method a change of O (a TF switch, a structure shown or hidden)
    /// switches to, once the new O is classified: the filters' `filter` (made for the new method
    /// before classifying), else LAO with `params` on `skip`, the skipping data of the new O
    /// (uploaded with `lao`).
    pub fn switched(
        gpu: &Gpu,
        lao: &LaoGpu,
        vol: &Volume,
        params: LaoParams,
        filter: Option<FilterGpu>,
        skip: Option<SkipData>,
    ) -> Result<MethodGpu> {
        match (filter, skip) {
            (Some(f), _) => Ok(MethodGpu::Filter(f)),
            (None, skip) => {
                let skip = skip.ok_or_else(|| {
                    GpuError::Other(format!("{}: LAO without skipping data", vol.name))
                })?;
                let skip = lao.upload_skip(&skip)?;
                MethodGpu::lao(gpu, vol, params, skip)
            }
        }
    }

    /// Records slices `z` of the method's precompute after a change of O, from the unclipped O
    /// `opacity` into V_PAO' `pao` ([`AoMethod::refresh`]): LAO's slab with `lao` (its old
    /// kernel reads the ray steps `dirs`, [`LaoGpu::directions_buffer`]); the filters refilter
    /// the whole volume whatever `z`; the local histograms sum slices `z` over q (`opacity`;
    /// a TF switch refreshes them at once, with a table); no method records nothing. Records
    /// no barrier.
    pub fn record_precompute(
        &self,
        cmd: vk::CommandBuffer,
        lao: &LaoGpu,
        dirs: &Buffer,
        opacity: &Buffer,
        pao: &Buffer,
        z: std::ops::Range<usize>,
    ) {
        match self {
            MethodGpu::Filter(f) => f.record_precompute(cmd, opacity, pao),
            MethodGpu::Lao(l) => {
                let input = SlabInput {
                    opacity,
                    dirs,
                    skip: &l.skip,
                };
                lao.record_slab(cmd, &input, pao, l.dims, &l.params, z);
            }
            MethodGpu::Histogram(h) => h.record_precompute(cmd, (opacity, pao), z),
            MethodGpu::Open => {}
        }
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

    /// Bytes per voxel of O and O_c: 4 where they are f32 ([`MethodGpu::float_density`]), else
    /// 2 (16-bit words, [`super::stored`]).
    pub fn density_bytes(&self) -> usize {
        if self.float_density() {
            4
        } else {
            2
        }
    }

    /// Where voxel v of O_c lies for this method: \[0] + v.x + \[1] v.y + \[2] v.z (inside LAO's
    /// zero border for LAO); \[3] is 1 where O_c is f32 ([`MethodGpu::float_density`]).
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

    /// How many z-slices either side of a voxel the method's region recompute reads O_c (LAO's
    /// border, the local histograms' S_r, the filters' box centre and half-width), where CAO
    /// holds O_c only in the slices a frame reads ([`super::cao::Cao::windowed`]); None where
    /// it holds O_c whole (no method reads it).
    pub fn window_reach(&self) -> Option<usize> {
        match self {
            MethodGpu::Lao(l) => Some(l.pad()[2]),
            MethodGpu::Histogram(h) => Some(h.reach_voxels()[2]),
            MethodGpu::Filter(f) => Some(f.reach_slices()),
            MethodGpu::Open => None,
        }
    }

    /// The zero border around O_c on each axis (LAO's; none for the others).
    pub fn clipped_pad(&self) -> [usize; 3] {
        match self {
            MethodGpu::Lao(l) => l.pad(),
            _ => [0; 3],
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
    /// `at[k]`: where box k's V_PAO starts in `bufs.pre_a`, in voxels (the frame's staged
    /// boxes, [`super::cao::Cao`]'s restore and update).
    pub fn record_restore(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        at: &[i32],
        clipped: bool,
    ) {
        if let MethodGpu::Histogram(h) = self {
            h.record_restore(cmd, bufs, boxes, at, clipped);
        }
    }

    /// Records the region recompute: the AO of the voxels of `boxes` from O_c into V_AO, CAO's
    /// categories as `mode` says.
    /// `at[k]`: where box k's V_PAO starts in `bufs.pre_a`, in voxels (the frame's staged
    /// boxes, [`super::cao::Cao`]'s restore and update).
    pub fn record_update(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        at: &[i32],
        mode: Mode,
    ) {
        match self {
            MethodGpu::Open => {}
            MethodGpu::Lao(l) => l.record(cmd, bufs, boxes, at, mode),
            MethodGpu::Filter(f) => f.record(cmd, bufs, boxes, at, mode),
            MethodGpu::Histogram(h) => h.record(cmd, bufs, boxes, at, mode),
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

/// A volume's classification and precomputed AO, resident on the GPU: what a CAO state is
/// made from ([`AoVolume::into_cao`]).
pub struct AoVolume {
    /// O of docs/design.md, on the host (for the filters: the density they filter, O or the
    /// normalised scalar; for the local histograms q).
    pub opacity: Vec<f32>,
    /// V_PAO: the AO method's openness of the unclipped volume (stored, x fastest).
    pub ao_buf: Buffer,
    pub timing: LaoTiming,
    /// The method's GPU state (it goes to the CAO state with the volumes; for LAO the exact
    /// empty-space skipping data of O, valid for every clipped O too).
    pub method: MethodGpu,
}

impl AoVolume {
    /// A second, independent copy on the GPU (to run two CAO states side by side).
    pub fn duplicate(&self) -> Result<AoVolume> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
        Ok(AoVolume {
            opacity: self.opacity.clone(),
            ao_buf: self.ao_buf.duplicate(usage, "pao")?,
            timing: self.timing.clone(),
            method: self.method.duplicate()?,
        })
    }

    /// Hands O, V_PAO and the method to a CAO state for per-frame clipping.
    pub fn into_cao(self, gpu: &Gpu, vol: &Volume) -> Result<Cao> {
        let words = self.stored_opacity(vol.voxel_count() as u64);
        drop(self.opacity);
        Cao::new(gpu, vol, words, self.ao_buf, self.method)
    }

    /// O as the GPU reads it ([`Cao::clipped_stride`]): the filters' f32 density, else 16-bit
    /// words ([`super::stored`]); zero before a method is computed.
    fn stored_opacity(&self, voxels: u64) -> Vec<u8> {
        match &self.method {
            MethodGpu::Open => vec![0; super::stored::bytes(voxels) as usize],
            m if m.float_density() => bytemuck::cast_slice(&self.opacity).to_vec(),
            _ => bytemuck::cast_slice(&super::stored::words(&self.opacity)).to_vec(),
        }
    }

    /// LAO's precompute of `opacity` (O of `vol`, host) with `params`, `progress(done, total)`
    /// told slab by slab.
    pub fn lao(
        gpu: &Gpu,
        lao: &LaoGpu,
        vol: &Volume,
        opacity: Vec<f32>,
        params: &LaoParams,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<AoVolume> {
        let skip = lao.skip_buffers(&opacity, vol.dims, vol.spacing, params)?;
        // Only the old kernel reads O without its border: the default one reads the skipping
        // data's padded copy, and the CAO state takes O from the host.
        let unpadded = match lao.kernel {
            LaoKernel::Old => Some(super::stored::upload(
                gpu,
                &opacity,
                vk::BufferUsageFlags::STORAGE_BUFFER,
                "opacity",
            )?),
            LaoKernel::New => None,
        };
        let o = unpadded.as_ref().unwrap_or(&skip.padded);
        let (ao_buf, timing) = lao.compute(o, &skip, vol.dims, vol.spacing, params, progress)?;
        Ok(AoVolume {
            opacity,
            ao_buf,
            timing,
            method: MethodGpu::lao(gpu, vol, *params, skip)?,
        })
    }

    /// The filters' precompute (one pass) over `density`, the density of `vol` they filter.
    pub fn filter(
        gpu: &Gpu,
        vol: &Volume,
        density: Vec<f32>,
        params: FilterParams,
    ) -> Result<AoVolume> {
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
        // f32: the filters' gradients of it need more than 16 bits (`Cao::clipped_stride`).
        let opacity_buf = Buffer::device_local(gpu, &density, usage, "opacity")?;
        let filter = FilterGpu::new(gpu, vol.dims, vol.spacing, params)?;
        let t0 = std::time::Instant::now();
        let (ao_buf, gpu_ms) = filter.compute(&opacity_buf)?;
        let timing = LaoTiming {
            gpu_ms,
            wall_ms: t0.elapsed().as_secs_f64() * 1e3,
            ..Default::default()
        };
        drop(opacity_buf);
        Ok(AoVolume {
            opacity: density,
            ao_buf,
            timing,
            method: MethodGpu::Filter(filter),
        })
    }

    /// V_PAO and the bleeding volume of the local-histogram method `h` under `tf`: one table
    /// update and one pass (the clusters' values, or with N = 0 the direct sums).
    pub fn histogram(
        gpu: &Gpu,
        lao: &LaoGpu,
        vol: &Volume,
        tf: &TransferFunction,
        mut h: HistogramGpu,
    ) -> Result<AoVolume> {
        let t0 = std::time::Instant::now();
        let t = histogram_tables(gpu, lao, vol.dims, &mut h, (tf, &[]))?;
        let timing = LaoTiming {
            gpu_ms: t.gpu_ms,
            wall_ms: t0.elapsed().as_secs_f64() * 1e3,
            ..Default::default()
        };
        Ok(AoVolume {
            opacity: t.q,
            ao_buf: t.pao,
            timing,
            method: MethodGpu::Histogram(h),
        })
    }

    /// The AO of no method yet ([`MethodGpu::Open`]): V_PAO 1 everywhere, filled on the GPU,
    /// and O zero, so a first picture waits for no classification, upload or precompute (the
    /// switch to a method classifies and computes its own).
    pub fn open(gpu: &Gpu, vol: &Volume) -> Result<AoVolume> {
        let ao_buf = super::stored::buffer(gpu, vol.dims, "pao")?;
        // A fill writes whole 4-byte words: the last 16-bit word of an odd count is copied in.
        let tail = Buffer::device_local(
            gpu,
            &[super::stored::pack(1.0)],
            vk::BufferUsageFlags::TRANSFER_SRC,
            "pao-tail",
        )?;
        gpu.submit_and_wait(|cmd| unsafe {
            // SAFETY: the buffers were just made with these usages, and nothing else uses them.
            let d = &gpu.device;
            // Every 16-bit word all ones: AO_OPEN, AO 1.
            d.cmd_fill_buffer(cmd, ao_buf.raw, 0, vk::WHOLE_SIZE, u32::MAX);
            gpu.barrier(cmd);
            let last = ao_buf.size - super::stored::BYTES_PER_VOXEL;
            let region = vk::BufferCopy::default().dst_offset(last).size(2);
            d.cmd_copy_buffer(cmd, tail.raw, ao_buf.raw, &[region]);
        })?;
        Ok(AoVolume {
            opacity: Vec::new(),
            ao_buf,
            timing: LaoTiming::default(),
            method: MethodGpu::Open,
        })
    }
}

/// What [`histogram_tables`] made: q (host and GPU), V_PAO, and the pass's GPU ms.
pub struct HistogramTables {
    pub q: Vec<f32>,
    pub opacity: Buffer,
    pub pao: Buffer,
    pub gpu_ms: f64,
}

/// The local-histogram method `h` under `tf` and the structures as `structures` shows them (its
/// first TF, a TF change or a structure shown or hidden): its tables, then q (the opacity CAO
/// clips) and V_PAO with the bleeding volume in one pass.
pub fn histogram_tables(
    gpu: &Gpu,
    lao: &LaoGpu,
    dims: [usize; 3],
    h: &mut HistogramGpu,
    (tf, structures): (&TransferFunction, &[f32]),
) -> Result<HistogramTables> {
    let q = h.set_tf(tf, structures)?;
    let opacity = super::stored::upload(gpu, &q, vk::BufferUsageFlags::STORAGE_BUFFER, "opacity")?;
    let pao = lao.output_buffer(dims)?;
    let mut timer = crate::gpu::GpuTimer::new(gpu, 2)?;
    gpu.submit_and_wait(|cmd| {
        timer.begin(cmd);
        h.record_precompute(cmd, (&opacity, &pao), 0..dims[2]);
        timer.mark(cmd, "histogram");
    })?;
    let gpu_ms = timer.read()?.iter().map(|t| t.1).sum();
    Ok(HistogramTables {
        q,
        opacity,
        pao,
        gpu_ms,
    })
}
