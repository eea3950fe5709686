//! The full-resolution inset: where a volume does not fit the GPU at full resolution and is
//! shown downsampled, the boxes around the carving tools (and where the eyes look) are shown at
//! full resolution, each with its own CAO state. A box is cropped from the full-resolution
//! volume with a margin of the AO method's reach on every side (where the volume goes on), so
//! that the AO inside it is the whole full-resolution volume's, voxel for voxel (docs/design.md,
//! "The inset"). The boxes follow what they are around: when that point moves a quarter of a box
//! away, the box is cut again around it and its AO computed anew; a second place to look at
//! splits the budget between two boxes.

use super::common::{histogram_state, precompute_method, Result};
use crate::ao::cao::{Cao, FrameMetrics, Mode};
use crate::ao::filtered::{variance_volume, FilterParams, VarianceModulation};
use crate::ao::histogram::HistParams;
use crate::ao::lao::LaoKernel;
use crate::ao::method::{AoVolume, MethodGpu};
use crate::ao::progressive::SlabScheduler;
use crate::ao::{AoConfig, AoMethod, LaoGpu};
use crate::gpu::{Buffer, Gpu, GpuError, Image};
use crate::render::InsetBinding;
use crate::scene::Tool;
use crate::shader_constants::MAX_INSETS;
use crate::space::{
    lps_from_local_mm, world_from_lps_point, world_from_tex, Placement, Pose, View,
};
use crate::volume::distance::MarginField;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use glam::{Vec3, Vec4Swizzles};
use std::sync::Arc;

/// How many full-resolution boxes the inset may show, at most [`FULL_BOXES`] (the default): "0"
/// turns it off (to compare with the downsampled volume alone), "1" keeps one box.
pub const INSET_ENV: &str = "CAO_XR_INSET";

/// "0" shows no middle level (a box at half resolution around the full-resolution ones, where
/// the rest is shown by 3 or coarser), to compare with the two levels alone.
pub const MIDDLE_ENV: &str = "CAO_XR_INSET_MIDDLE";

/// The full-resolution boxes at most: the ray caster's box slots ([`MAX_INSETS`]) less one for
/// a middle level's box.
pub const FULL_BOXES: usize = MAX_INSETS - 1;

/// Smallest side (voxels) of an inset worth showing.
pub const MIN_SIDE: usize = 16;

/// What a CAO frame holds beside its set-up, per voxel, at most (measured: the first frame's
/// whole restore stages O and V_PAO, then the tools' boxes and the window of O_c and its
/// staging copy stay in the frame slots; a frame that runs out of GPU memory is an error, as
/// without an inset), and a MiB more for the tools' maps and tables.
pub const FRAME_BYTES_PER_VOXEL: f64 = 12.0;
const FRAME_BYTES: f64 = (1 << 20) as f64;

/// What the frames of a shown volume of `voxels` hold beside its set-up, at most: room a set-up
/// must leave in the GPU budget, so that its frames do not run out.
pub fn frame_reserve(voxels: usize) -> u64 {
    (FRAME_BYTES_PER_VOXEL * voxels as f64 + 2.0 * FRAME_BYTES) as u64
}

/// A moved box is computed over at most this many frames ([`Inset::refine`]): each holds an
/// eighth of a cut's work at most, and the box is coarse for a few frames only.
pub const BUILD_FRAMES: usize = 8;

/// Tries at smaller sizes where an inset does not fit after all.
const FIT_TRIES: usize = 4;

/// Frames in a row with one place for boxes after which two boxes merge back into one of the
/// size one box had (a second of a headset's frames: a hand that leaves for a moment keeps its
/// box).
pub const MERGE_FRAMES: usize = 90;

/// Where the boxes belong this frame, and which to cut ([`Inset::wants_cuts`], for
/// [`Inset::make_cuts`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Cuts {
    /// The places boxes belong (full-resolution index points), the first first.
    pub places: Vec<[f64; 3]>,
    /// The boxes to cut and where (box, full-resolution index point); a box past the last asks
    /// for more boxes.
    pub cuts: Vec<(usize, [f64; 3])>,
}

/// The full-resolution volume, and the part of it on the GPU.
pub struct Inset {
    whole: Arc<Volume>,
    /// The whole volume's value range (what `tf` classifies against), found once.
    range: (f32, f32),
    /// The method the part's AO is computed with and the TF its O is classified with.
    config: AoConfig,
    tf: TransferFunction,
    /// Where the volume has labels: each structure's opacity a_l as shown (part of O), and
    /// whether the tools leave it standing.
    structures: Vec<f32>,
    protected: Vec<bool>,
    /// Variance opacity modulation, where it is on: the box's var_s is the full resolution's.
    variance: Option<VarianceModulation>,
    /// The safety margins' distance fields at full resolution, where structures have margins:
    /// the box glows from them.
    margins: Option<Arc<Vec<MarginField>>>,
    lao: LaoGpu,
    /// The inner boxes' size (they share it) and the margin on each side (full-resolution
    /// voxels).
    inner: [usize; 3],
    margin: [usize; 3],
    /// The boxes, the first one first: at least one, at most `most`.
    boxes: Vec<InsetBox>,
    /// How many boxes the inset may show ([`INSET_ENV`]).
    most: usize,
    /// The inner size of one box alone (what boxes merge back to), and the frames in a row
    /// that had one place for several boxes.
    single: [usize; 3],
    alone: usize,
}

/// One box: shown, being computed, or neither (none fitted after a shrink, or not cut yet).
#[derive(Default)]
struct InsetBox {
    part: Option<Part>,
    /// A box being computed slab by slab ([`Inset::start_cut`]), shown once it is done.
    build: Option<Build>,
}

/// A box whose AO (LAO, or the local histograms' direct sums) is computed a slab of z-slices
/// per frame ([`Inset::refine`]): meanwhile the picture there is the downsampled volume's.
struct Build {
    inner_lo: [usize; 3],
    crop_lo: [usize; 3],
    /// The crop with its voxels (its scalar image is made when the box is shown).
    crop: Volume,
    /// O on the host (the local histograms' q), and the method with its state.
    opacity: Vec<f32>,
    method: MethodGpu,
    /// The local histograms' q on the GPU (LAO reads its skipping data's padded O).
    q: Option<Buffer>,
    dirs: Buffer,
    pao: Buffer,
    slabs: SlabScheduler,
}

/// The box on the GPU: the crop (inner box and margin) with its CAO state and scalars.
struct Part {
    /// The inner box's first voxel, and the crop's (full-resolution indices).
    inner_lo: [usize; 3],
    crop_lo: [usize; 3],
    /// The crop's geometry (its voxels are on the GPU only).
    crop: Volume,
    cao: Cao,
    scalars: Image,
    /// Its structure ids, where the volume has labels.
    ids: Option<Image>,
    /// Its var_s, where variance modulation is on.
    variance: Option<Image>,
    /// Its margins' glow, where structures have margins.
    glow: Option<Image>,
}

impl Inset {
    /// Whether insets are wanted ([`INSET_ENV`]).
    pub fn wanted() -> bool {
        Self::most_boxes() > 0
    }

    /// How many boxes may be shown ([`INSET_ENV`]: a count up to [`FULL_BOXES`], the default).
    fn most_boxes() -> usize {
        std::env::var(INSET_ENV)
            .ok()
            .and_then(|v| v.trim().parse::<usize>().ok())
            .map_or(FULL_BOXES, |n| n.min(FULL_BOXES))
    }

    /// Whether a middle level is wanted ([`MIDDLE_ENV`]).
    pub fn middle_wanted() -> bool {
        !std::env::var(MIDDLE_ENV).is_ok_and(|v| v.trim() == "0")
    }

    /// Shows at most one box from now on (a middle level's: one around the first place).
    pub fn keep_one(&mut self) {
        self.most = 1;
        self.boxes.truncate(1);
    }

    /// The safety margins' distance fields in this inset's own grid (a middle level's; the
    /// full-resolution level takes the frame loop's).
    pub fn own_margin_fields(&self) -> Vec<MarginField> {
        let whole = &*self.whole;
        whole
            .labels
            .as_deref()
            .map_or_else(Vec::new, |l| l.margin_fields(whole.dims, whole.spacing))
    }

    /// The largest inset beside what the GPU holds now that fits `available` bytes in all,
    /// leaving `frames` bytes for the shown volume's frames (its [`frame_reserve`] and
    /// read-back): its inner box as near a cube in mm as the volume allows, cut first around the
    /// volume's centre. The first box is sized at `bytes_per_voxel` (the shown volume's set-up
    /// peak per voxel, its fixed costs included: too much; at least a [`MIN_SIDE`] box is
    /// tried), the next at what the first cost, while that makes it larger. None where not
    /// even a [`MIN_SIDE`] box fits.
    pub fn new(
        gpu: &Gpu,
        whole: Arc<Volume>,
        (config, tf): (AoConfig, TransferFunction),
        (available, bytes_per_voxel, frames): (u64, f64, u64),
    ) -> Result<Option<Inset>> {
        let frames = frames as f64;
        let free = available.saturating_sub(gpu.memory_in_use()) as f64 - frames;
        let centre = whole.dims.map(|d| d as f64 * 0.5);
        let mut inset = Inset::uncut(gpu, whole, (config, tf), [0; 3])?;
        let mut cost = bytes_per_voxel + FRAME_BYTES_PER_VOXEL;
        let mut shown: Option<[usize; 3]> = None;
        for _ in 0..FIT_TRIES {
            let mut want = inset.fitting(free, cost);
            if shown.is_none() {
                // The estimate is high: try the smallest box that is worth it, and measure.
                want = std::array::from_fn(|a| want[a].max(MIN_SIDE.min(inset.whole.dims[a])));
            }
            let grows = shown.is_none_or(|s| (0..3).any(|a| want[a] * 20 > s[a] * 23));
            if !grows || want.iter().any(|&n| n < MIN_SIDE) {
                break;
            }
            inset.boxes[0] = InsetBox::default();
            let before = gpu.memory_in_use();
            gpu.reset_memory_peak();
            inset.inner = want;
            inset.single = want;
            match inset.cut(gpu, centre) {
                Ok(()) => {
                    let voxels = inset.crop_voxels(want);
                    cost = (gpu.memory_peak() - before) as f64 / voxels + FRAME_BYTES_PER_VOXEL;
                    shown = Some(want);
                }
                Err(super::common::AppError::Gpu(GpuError::OutOfMemory(_))) => match shown {
                    // Back to the box that fitted.
                    Some(s) => {
                        inset.inner = s;
                        inset.single = s;
                        inset.cut(gpu, centre)?;
                        break;
                    }
                    None if want.iter().all(|&n| n <= MIN_SIDE) => break,
                    None => cost *= 1.5,
                },
                Err(e) => return Err(e),
            }
        }
        Ok(shown.map(|_| inset))
    }

    /// Voxels of the crop of an `inner` box (its margin included, as far as the volume goes).
    fn crop_voxels(&self, inner: [usize; 3]) -> f64 {
        (0..3)
            .map(|a| (inner[a] + 2 * self.margin[a]).min(self.whole.dims[a]) as f64)
            .product()
    }

    /// The largest inner box, as near a cube in mm as the volume allows, whose crop costs at
    /// most `free` bytes at `cost` per voxel.
    fn fitting(&self, free: f64, cost: f64) -> [usize; 3] {
        let whole = &*self.whole;
        let dims_for = |side_mm: f64| -> [usize; 3] {
            std::array::from_fn(|a| {
                ((side_mm / whole.spacing[a]).round() as usize).clamp(1, whole.dims[a])
            })
        };
        let longest = (0..3)
            .map(|a| whole.dims[a] as f64 * whole.spacing[a])
            .fold(0.0, f64::max);
        // The largest side (mm) that fits, by bisection.
        let (mut lo, mut hi) = (0.0, longest);
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if self.crop_voxels(dims_for(mid)) * cost <= free {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        dims_for(lo)
    }

    /// An inset of `inner` voxels (at most the volume's) cut around full-resolution index
    /// point `centre`.
    pub fn around(
        gpu: &Gpu,
        whole: Arc<Volume>,
        (config, tf): (AoConfig, TransferFunction),
        (inner, centre): ([usize; 3], [f64; 3]),
    ) -> Result<Inset> {
        let inner = std::array::from_fn(|a| inner[a].clamp(1, whole.dims[a]));
        let mut inset = Inset::uncut(gpu, whole, (config, tf), inner)?;
        inset.cut(gpu, centre)?;
        Ok(inset)
    }

    /// An inset of `inner` voxels with nothing on the GPU yet.
    fn uncut(
        gpu: &Gpu,
        whole: Arc<Volume>,
        (config, tf): (AoConfig, TransferFunction),
        inner: [usize; 3],
    ) -> Result<Inset> {
        let labels = whole.labels.as_deref();
        Ok(Inset {
            range: whole.value_range(),
            margin: margin_for(&whole, &config),
            structures: labels.map_or_else(Vec::new, |l| l.opacities()),
            protected: labels.map_or_else(Vec::new, |l| l.protected()),
            variance: None,
            margins: None,
            whole,
            config,
            tf,
            lao: LaoGpu::new(gpu)?,
            inner,
            boxes: vec![InsetBox::default()],
            most: Self::most_boxes().max(1),
            single: inner,
            alone: 0,
        })
    }

    /// The inner box's first voxel for a centre at full-resolution index point `centre`.
    fn inner_lo(&self, centre: [f64; 3]) -> [usize; 3] {
        std::array::from_fn(|a| {
            let lo = (centre[a] - 0.5 * self.inner[a] as f64).round().max(0.0) as usize;
            lo.min(self.whole.dims[a] - self.inner[a])
        })
    }

    /// Crops the first box around full-resolution index point `centre` and computes its AO at
    /// once (`Inset::cut_box`).
    pub fn cut(&mut self, gpu: &Gpu, centre: [f64; 3]) -> Result<()> {
        self.cut_box(gpu, 0, centre)
    }

    /// Crops box `b` around full-resolution index point `centre` ([`Inset::wants_cuts`]) and
    /// computes its AO (classified over the whole volume's value range: a crop's own is
    /// narrower); the old box goes first (its memory is the new one's), so no frame that
    /// reads it may be in flight.
    fn cut_box(&mut self, gpu: &Gpu, b: usize, centre: [f64; 3]) -> Result<()> {
        if matches!(self.config.method, AoMethod::Histogram(_)) {
            // The direct sums the box is built with over frames ([`Inset::start_cut`]), in one
            // slab.
            self.start_cut_box(gpu, b, centre)?;
            return self.refine(gpu, f64::INFINITY);
        }
        let (inner_lo, crop_lo, crop) = self.crop_at(b, centre);
        let ao = precompute_method(gpu, &self.lao, &crop, &self.tf, &self.config, false)?;
        self.show(gpu, b, (inner_lo, crop_lo, crop), ao)
    }

    /// Drops box `b` (shown or being computed), and crops the full-resolution volume for one
    /// around `centre`: the inner box's first voxel, the crop's, and the crop.
    fn crop_at(&mut self, b: usize, centre: [f64; 3]) -> ([usize; 3], [usize; 3], Volume) {
        self.boxes[b] = InsetBox::default();
        // The method may have changed since the last cut (a switch), and its reach with it.
        self.margin = margin_for(&self.whole, &self.config);
        let inner_lo = self.inner_lo(centre);
        let crop_lo: [usize; 3] =
            std::array::from_fn(|a| inner_lo[a].saturating_sub(self.margin[a]));
        let crop_hi: [usize; 3] = std::array::from_fn(|a| {
            (inner_lo[a] + self.inner[a] + self.margin[a]).min(self.whole.dims[a])
        });
        let mut crop = self
            .whole
            .crop(crop_lo, std::array::from_fn(|a| crop_hi[a] - crop_lo[a]));
        // Its structures as shown now: they classify its O and guard its voxels.
        if let Some(labels) = crop.labels.as_mut() {
            let structures = &mut Arc::make_mut(labels).structures;
            for (s, (&a, &p)) in structures
                .iter_mut()
                .zip(self.structures.iter().zip(&self.protected))
            {
                s.opacity = a;
                s.protected = p;
            }
        }
        (inner_lo, crop_lo, crop)
    }

    /// Shows the crop with its precomputed AO `ao` as box `b`: its CAO state and scalar image.
    fn show(
        &mut self,
        gpu: &Gpu,
        b: usize,
        (inner_lo, crop_lo, mut crop): ([usize; 3], [usize; 3], Volume),
        ao: AoVolume,
    ) -> Result<()> {
        let cao = ao.into_cao(gpu, &crop)?;
        let (scalars, _) = crate::render::scalar_image(gpu, &crop)?;
        let ids = crop
            .labels
            .take()
            .map(|l| crate::render::id_image(gpu, crop.dims, &l.ids))
            .transpose()?;
        let variance = self.crop_variance(gpu, crop_lo, crop.dims)?;
        let glow = self.crop_glow(gpu, crop_lo, crop.dims)?;
        crop.voxels = crate::volume::Voxels::U8(Vec::new());
        self.boxes[b].part = Some(Part {
            inner_lo,
            crop_lo,
            crop,
            cao,
            scalars,
            ids,
            variance,
            glow,
        });
        Ok(())
    }

    /// [`Inset::cut`] without holding the frames (the first box).
    pub fn start_cut(&mut self, gpu: &Gpu, centre: [f64; 3]) -> Result<()> {
        self.start_cut_box(gpu, 0, centre)
    }

    /// [`Inset::cut_box`] without holding the frames: under LAO (default kernel) and the local
    /// histograms (their direct sums) the crop's AO is computed over the next frames, a slab
    /// of z-slices each ([`Inset::refine`]), and the box is shown when it is done; until then
    /// the picture there is the downsampled volume's. The filters (one pass) cut at once. The
    /// old box goes first.
    fn start_cut_box(&mut self, gpu: &Gpu, b: usize, centre: [f64; 3]) -> Result<()> {
        let params = self.config.lao;
        let hist = match self.config.method {
            AoMethod::Lao if self.lao.kernel == LaoKernel::New => None,
            AoMethod::Histogram(hp) => Some(hp),
            _ => return self.cut_box(gpu, b, centre),
        };
        params.validate().map_err(super::common::AppError::Usage)?;
        let (inner_lo, crop_lo, crop) = self.crop_at(b, centre);
        // Each voxel's AO is its own, so the slabs give the bits one pass gives (LAO's kernel
        // reads the skipping data's padded O either way).
        let (opacity, method, q, per_slice) = match hist {
            None => {
                let opacity = self.tf.opacity_volume(&crop);
                let skip = self
                    .lao
                    .skip_buffers(&opacity, crop.dims, crop.spacing, &params)?;
                let method = MethodGpu::lao(gpu, &crop, params, skip)?;
                (
                    opacity,
                    method,
                    None,
                    LaoGpu::samples_per_slice(crop.dims, &params),
                )
            }
            Some(hp) => {
                let mut h = histogram_state(gpu, &crop, Self::direct(hp), None, false)?;
                let q = h.set_tf(&self.tf, &[])?;
                let words = crate::ao::stored::upload(
                    gpu,
                    &q,
                    ash::vk::BufferUsageFlags::STORAGE_BUFFER,
                    "opacity",
                )?;
                let per_slice = h.samples_per_slice();
                (q, MethodGpu::Histogram(h), Some(words), per_slice)
            }
        };
        let slabs = SlabScheduler::with_budget(crop.dims[2], per_slice, per_slice)
            .with_least_slab(crop.dims[2].div_ceil(BUILD_FRAMES));
        self.boxes[b].build = Some(Build {
            dirs: self.lao.directions_buffer(&params, crop.spacing)?,
            pao: self.lao.output_buffer(crop.dims)?,
            inner_lo,
            crop_lo,
            crop,
            opacity,
            method,
            q,
            slabs,
        });
        Ok(())
    }

    /// Cuts the boxes `cuts` asks for ([`Inset::wants_cuts`]: a box and the full-resolution
    /// index point it goes around), at once or, `progressive`, over the next frames. A box past
    /// the last asks for more boxes: all boxes are then made as much smaller as keeps them
    /// within the memory the boxes there hold, and cut again (where they are unless moved);
    /// where they would be smaller than [`MIN_SIDE`], no box is added. After [`MERGE_FRAMES`]
    /// frames in a row with one place (or none) and several boxes, none being computed, they
    /// merge back into one box of the size one box had, cut around that place (or where the
    /// first box is).
    pub fn make_cuts(&mut self, gpu: &Gpu, cuts: &Cuts, progressive: bool) -> Result<()> {
        let several = self.boxes.len() > 1 && cuts.places.len() <= 1;
        self.alone = if several { self.alone + 1 } else { 0 };
        let mut cuts = if self.alone >= MERGE_FRAMES && self.refining().is_none() {
            self.alone = 0;
            let at = cuts.places.first().copied().unwrap_or(self.centre_of(0));
            self.boxes.clear();
            self.boxes.push(InsetBox::default());
            self.inner = self.single;
            vec![(0, at)]
        } else {
            cuts.cuts.clone()
        };
        let boxes = cuts.iter().map(|&(b, _)| b + 1).max().unwrap_or(0);
        if boxes > self.boxes.len() {
            let held = self.boxes.len() as f64 * self.crop_voxels(self.inner);
            let inner = self.fitting(held / boxes as f64, 1.0);
            if inner.iter().any(|&n| n < MIN_SIDE) {
                cuts.retain(|&(b, _)| b < self.boxes.len());
            } else {
                for b in 0..self.boxes.len() {
                    if !cuts.iter().any(|&(c, _)| c == b) {
                        cuts.push((b, self.centre_of(b)));
                    }
                }
                // Every box is cut again at the new size: free them all first.
                self.boxes.clear();
                self.boxes.resize_with(boxes, InsetBox::default);
                self.inner = inner;
            }
        }
        for (b, centre) in cuts {
            if progressive {
                self.start_cut_box(gpu, b, centre)?;
            } else {
                self.cut_box(gpu, b, centre)?;
            }
        }
        Ok(())
    }

    /// The local histograms' parameters the box computes with: their direct sums (the
    /// definition the clusters approximate), the whole volume's bit for bit, with no codebook
    /// trained per cut.
    fn direct(hp: HistParams) -> HistParams {
        HistParams { clusters: 0, ..hp }
    }

    /// Computes the next slab of each box being cut ([`Inset::start_cut`]), at most `samples`
    /// opacity samples or a [`BUILD_FRAMES`]th of the box, whichever is more (at least a
    /// slice), submitted and waited for; shows a box once its last slab is done. Nothing
    /// without a box being computed.
    pub fn refine(&mut self, gpu: &Gpu, samples: f64) -> Result<()> {
        for i in 0..self.boxes.len() {
            let Some(b) = self.boxes[i].build.as_mut() else {
                continue;
            };
            // At most BUILD_FRAMES frames, however small the budget (`start_cut`'s least slab).
            b.slabs.set_budget(samples);
            if let Some(z) = b.slabs.next_slab() {
                let input = match (&b.method, &b.q) {
                    (MethodGpu::Lao(l), _) => &l.skip.padded,
                    (_, Some(q)) => q,
                    _ => unreachable!("a box being computed is LAO's or has q"),
                };
                let lao = &self.lao;
                gpu.submit_and_wait(|cmd| {
                    b.method
                        .record_precompute(cmd, lao, &b.dirs, input, &b.pao, z)
                })?;
            }
            if !b.slabs.is_finished() {
                continue;
            }
            let Build {
                inner_lo,
                crop_lo,
                crop,
                opacity,
                method,
                pao,
                ..
            } = self.boxes[i].build.take().expect("checked above");
            let ao = AoVolume {
                opacity,
                ao_buf: pao,
                timing: Default::default(),
                method,
            };
            self.show(gpu, i, (inner_lo, crop_lo, crop), ao)?;
        }
        Ok(())
    }

    /// How far the boxes being cut have come (0 to 1, the least), where one is.
    pub fn refining(&self) -> Option<f32> {
        self.boxes
            .iter()
            .filter_map(|b| b.build.as_ref())
            .map(|b| b.slabs.fraction())
            .reduce(f32::min)
    }

    /// "inset 160 x 160 x 64 at [176:336,...] and at [...] (+ margin 24 x 24 x 8) at full
    /// resolution", as stderr tells it.
    pub fn describe(&self) -> String {
        let [x, y, z] = self.inner;
        let [mx, my, mz] = self.margin;
        let span = |lo: [usize; 3]| {
            let r = |a: usize| format!("{}:{}", lo[a], lo[a] + self.inner[a]);
            format!("[{},{},{}]", r(0), r(1), r(2))
        };
        let at: Vec<String> = self
            .boxes
            .iter()
            .filter_map(|b| match (&b.part, &b.build) {
                (Some(p), _) => Some(format!(" at {}", span(p.inner_lo))),
                (None, Some(b)) => Some(format!(" being computed at {}", span(b.inner_lo))),
                (None, None) => None,
            })
            .collect();
        let at = at.join(" and");
        let level = self.level();
        format!("inset {x} x {y} x {z}{at} (+ margin {mx} x {my} x {mz}) {level}")
    }

    /// "at full resolution", or a middle level's "downsampled by 2".
    pub fn level(&self) -> String {
        match self.whole.downsampled_by() {
            1 => "at full resolution".to_string(),
            n => format!("downsampled by {n}"),
        }
    }

    /// "a 64 x 64 x 40 box at full resolution", or "2 boxes of 64 x 64 x 40 ...".
    pub fn summary(&self) -> String {
        let [x, y, z] = self.inner;
        let level = self.level();
        match self.boxes.len() {
            1 => format!("a {x} x {y} x {z} box {level}"),
            n => format!("{n} boxes of {x} x {y} x {z} {level}"),
        }
    }

    /// The inner boxes' size (full-resolution voxels).
    pub fn inner_size(&self) -> [usize; 3] {
        self.inner
    }

    /// How many boxes there are (shown, being computed, or waiting for a cut).
    pub fn boxes(&self) -> usize {
        self.boxes.len()
    }

    /// The inner boxes' least share of the volume's side.
    pub fn share(&self) -> f64 {
        (0..3)
            .map(|a| self.inner[a] as f64 / self.whole.dims[a] as f64)
            .fold(1.0, f64::min)
    }

    /// The first box (full-resolution voxel indices, \[lo, hi)), where it is on the GPU.
    pub fn inner_box(&self) -> Option<([usize; 3], [usize; 3])> {
        self.inner_box_of(0)
    }

    /// Box `b` (full-resolution voxel indices, \[lo, hi)), where it is on the GPU.
    pub fn inner_box_of(&self, b: usize) -> Option<([usize; 3], [usize; 3])> {
        let p = self.boxes.get(b)?.part.as_ref()?;
        Some((
            p.inner_lo,
            std::array::from_fn(|a| p.inner_lo[a] + self.inner[a]),
        ))
    }

    /// The placement of `part`, a grid sharing the patient space of `shown` placed at `p`:
    /// its box centre where `shown`'s places that patient point.
    pub fn placed(part: &Volume, shown: &Volume, p: &Placement) -> Placement {
        let centre = lps_from_local_mm(part, Vec3::ZERO);
        Placement {
            center: world_from_lps_point(shown, p, centre),
            ..*p
        }
    }

    /// Which boxes should be cut where (box, full-resolution index point) for `tools`, the
    /// eyes' `views` and their tracked `gaze` pose (looking along its -Z) over `shown` at `p`.
    /// The places the boxes belong (`Inset::foci`, the first first) each keep a box already
    /// around them (within a quarter of the box); the others go to the boxes none keeps and
    /// none is computing, then, while none is computing, to new boxes (past the last). A box
    /// being computed ([`Inset::start_cut`]) is finished where it is, however the tools move, so
    /// that moving tools always get a box; a box no place wants stays where it is.
    pub fn wants_cuts(
        &self,
        (tools, views, gaze): (&[Tool], &[View; 2], Option<Pose>),
        shown: &Volume,
        p: &Placement,
    ) -> Cuts {
        let places = self.foci((tools, views, gaze), shown, p);
        let mut kept = vec![false; self.boxes.len()];
        let mut left = Vec::new();
        for &f in &places {
            let want = self.inner_lo(f);
            let near = |lo: [usize; 3]| {
                (0..3).all(|a| (want[a] as f64 - lo[a] as f64).abs() <= 0.25 * self.inner[a] as f64)
            };
            match (0..self.boxes.len()).find(|&b| !kept[b] && self.lo_of(b).is_some_and(near)) {
                Some(b) => kept[b] = true,
                None => left.push(f),
            }
        }
        let computing = self.refining().is_some();
        let free = (0..self.boxes.len()).filter(|&b| !kept[b] && self.boxes[b].build.is_none());
        let new = (self.boxes.len()..self.most).filter(|_| !computing);
        Cuts {
            cuts: free.chain(new).zip(left).collect(),
            places,
        }
    }

    /// Where box `b` is (its inner box's first voxel), shown or being computed.
    fn lo_of(&self, b: usize) -> Option<[usize; 3]> {
        let b = &self.boxes[b];
        let part = b.part.as_ref().map(|p| p.inner_lo);
        part.or(b.build.as_ref().map(|b| b.inner_lo))
    }

    /// The places (full-resolution index points) boxes belong, the first first, at most as many
    /// as may be shown: the groups of the cutting tools (each the mean of the largest group of
    /// them within half the inner box of one of them on every axis, among groups as large the
    /// first tool's; then the same of the rest), then those of the tools the hands hold inside
    /// the volume (about to cut); then where the tracked gaze meets what is shown; with no tool
    /// there, where the
    /// gaze, or without one the eyes' lens centres, meets it (`Inset::gaze_point`). A place a
    /// box around an earlier one holds (within half a box) is left out.
    fn foci(
        &self,
        (tools, views, gaze): (&[Tool], &[View; 2], Option<Pose>),
        shown: &Volume,
        p: &Placement,
    ) -> Vec<[f64; 3]> {
        let whole = &*self.whole;
        let tex_from_world = world_from_tex(whole, &Self::placed(whole, shown, p)).inverse();
        let tex = |t: &Tool| tex_from_world.transform_point3(t.pose.position);
        let inside = |t: &Vec3| t.cmpge(Vec3::ZERO).all() && t.cmple(Vec3::ONE).all();
        let cutting: Vec<Vec3> = tools.iter().filter(|t| t.cuts()).map(tex).collect();
        let held: Vec<Vec3> = tools
            .iter()
            .filter(|t| !t.cuts())
            .map(tex)
            .filter(inside)
            .collect();
        let mut foci = self.tool_groups(&cutting);
        foci.extend(self.tool_groups(&held));
        let look = match gaze {
            Some(g) => Some((g.position, g.orientation * Vec3::NEG_Z)),
            None if foci.is_empty() => Some(centre_ray(views)),
            None => None,
        };
        if let Some((origin, dir)) = look {
            foci.extend(self.gaze_point(
                tex_from_world.transform_point3(origin),
                tex_from_world.transform_vector3(dir),
            ));
        }
        let half = self.half_box();
        let mut distinct: Vec<Vec3> = Vec::new();
        for f in foci {
            if !distinct.iter().any(|d| (f - *d).abs().cmple(half).all()) {
                distinct.push(f);
            }
        }
        distinct.truncate(self.most);
        distinct
            .iter()
            .map(|f| std::array::from_fn(|a| f[a] as f64 * whole.dims[a] as f64))
            .collect()
    }

    /// Half the inner box, in texture coordinates: points closer than this on every axis fit in
    /// one box.
    fn half_box(&self) -> Vec3 {
        let dims = Vec3::from_array(self.whole.dims.map(|d| d as f32));
        Vec3::from_array(self.inner.map(|n| n as f32)) * 0.5 / dims
    }

    /// The groups of tools at `points` (texture coordinates), the largest first: each the mean
    /// of the largest group of those left within half the inner box of one of them on every
    /// axis (among groups as large, the first tool's): two hands carving far apart get a box
    /// each, not one between them around neither.
    fn tool_groups(&self, points: &[Vec3]) -> Vec<Vec3> {
        let half = self.half_box();
        let mut left = points.to_vec();
        let mut means = Vec::new();
        while !left.is_empty() {
            let group = |p: &Vec3| -> Vec<Vec3> {
                left.iter()
                    .copied()
                    .filter(|q| (*q - *p).abs().cmple(half).all())
                    .collect()
            };
            let mut best = group(&left[0]);
            for p in &left[1..] {
                let g = group(p);
                if g.len() > best.len() {
                    best = g;
                }
            }
            means.push(best.iter().sum::<Vec3>() / best.len() as f32);
            left.retain(|q| !best.contains(q));
        }
        means
    }

    /// The first point (texture coordinates) on the ray from `origin` along `dir` (texture
    /// coordinates) where the opacity gathered through the whole volume (nearest voxels, half a
    /// voxel apart, classified with the box's TF, its opacity per mm) reaches a half: the
    /// surface the eyes' centres see. None where the ray misses the volume or sees through it.
    fn gaze_point(&self, origin: Vec3, dir: Vec3) -> Option<Vec3> {
        let whole = &*self.whole;
        let dims = Vec3::from_array(whole.dims.map(|d| d as f32));
        let mm = Vec3::from_array(whole.spacing.map(|s| s as f32)) * dims;
        // Where the ray is inside [0, 1]^3 (slabs).
        let (t0, t1) = (-origin / dir, (Vec3::ONE - origin) / dir);
        let near = t0.min(t1).max_element().max(0.0);
        let far = t0.max(t1).min_element();
        let voxels = (dir * dims).length();
        let hits = near < far; // false for NaN too
        if !hits || voxels == 0.0 {
            return None;
        }
        let dt = 0.5 / voxels;
        let step_mm = (dir * mm).length() * dt;
        let mut clear = 1.0f32;
        let mut t = near;
        while t < far {
            let at = origin + dir * t;
            let v = (at * dims).floor().min(dims - 1.0).max(Vec3::ZERO);
            let i = whole.index(v.x as usize, v.y as usize, v.z as usize);
            let structure = whole
                .labels
                .as_deref()
                .map_or(1.0, |l| l.factor_showing(i, &self.structures));
            let a = (self.tf.eval(whole.voxels.get(i), self.range)[3] * structure).clamp(0.0, 1.0);
            clear *= (1.0 - a).powf(step_mm);
            if clear <= 0.5 {
                return Some(at);
            }
            t += dt;
        }
        None
    }

    /// The method configuration the box's AO is computed with.
    pub fn config(&self) -> AoConfig {
        self.config
    }

    /// Whether the box's AO is `config`'s method on O classified with `tf` and the
    /// structures' opacities `structures`.
    pub fn computes(&self, config: &AoConfig, tf: &TransferFunction, structures: &[f32]) -> bool {
        self.config.method == config.method && self.tf == *tf && self.structures == structures
    }

    /// Classifies with `tf` and computes with `config` from now on (a TF or method switch),
    /// cutting the box again where it is; no frame may be in flight.
    pub fn set_method(&mut self, gpu: &Gpu, shown: (AoConfig, TransferFunction)) -> Result<()> {
        let structures = self.structures.clone();
        self.set_shown(gpu, shown, &structures)
    }

    /// [`Inset::set_method`] with the structures shown at opacities `structures` (by structure
    /// index: a run-time show or hide, which O follows).
    pub fn set_shown(
        &mut self,
        gpu: &Gpu,
        (config, tf): (AoConfig, TransferFunction),
        structures: &[f32],
    ) -> Result<()> {
        if self.computes(&config, &tf, structures) {
            return Ok(());
        }
        self.config = config;
        self.tf = tf;
        self.structures = structures.to_vec();
        self.cut_again(gpu)
    }

    /// Cuts every box again where it is, at once.
    fn cut_again(&mut self, gpu: &Gpu) -> Result<()> {
        for b in 0..self.boxes.len() {
            self.cut_box(gpu, b, self.centre_of(b))?;
        }
        Ok(())
    }

    /// Variance opacity modulation `m` (None: off) in the box from now on: var_s at full
    /// resolution, as the ray caster reads it there.
    pub fn set_variance(&mut self, gpu: &Gpu, m: Option<VarianceModulation>) -> Result<()> {
        self.variance = m;
        self.remake_images(gpu)
    }

    /// The safety margins' distance `fields` at full resolution: the box glows from them.
    pub fn set_margins(&mut self, gpu: &Gpu, fields: Arc<Vec<MarginField>>) -> Result<()> {
        self.margins = Some(fields);
        self.remake_images(gpu)
    }

    /// Makes the shown boxes' var_s and glow images anew (their settings changed).
    fn remake_images(&mut self, gpu: &Gpu) -> Result<()> {
        for b in 0..self.boxes.len() {
            let Some((crop_lo, dims)) = self.boxes[b]
                .part
                .as_ref()
                .map(|p| (p.crop_lo, p.crop.dims))
            else {
                continue;
            };
            let variance = self.crop_variance(gpu, crop_lo, dims)?;
            let glow = self.crop_glow(gpu, crop_lo, dims)?;
            if let Some(p) = self.boxes[b].part.as_mut() {
                (p.variance, p.glow) = (variance, glow);
            }
        }
        Ok(())
    }

    /// The crop's var_s image at `crop_lo` of `dims`, where variance modulation is on: computed
    /// over the crop grown by the box's half-widths and shifted by the whole volume's v_min, so
    /// that every voxel of the crop has the whole volume's var_s, bit for bit.
    fn crop_variance(
        &self,
        gpu: &Gpu,
        crop_lo: [usize; 3],
        dims: [usize; 3],
    ) -> Result<Option<Image>> {
        let Some(m) = self.variance else {
            return Ok(None);
        };
        let whole = &*self.whole;
        let h = FilterParams {
            radius_mm: m.radius_mm,
            ..Default::default()
        }
        .half_widths(whole.spacing);
        let lo: [usize; 3] = std::array::from_fn(|a| crop_lo[a].saturating_sub(h[a]));
        let hi: [usize; 3] =
            std::array::from_fn(|a| (crop_lo[a] + dims[a] + h[a]).min(whole.dims[a]));
        let mut grown = whole.crop(lo, std::array::from_fn(|a| hi[a] - lo[a]));
        grown.labels = None;
        let var = variance_volume(&grown, m.radius_mm);
        let mut part = Vec::with_capacity(dims.iter().product());
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                let at = grown.index(
                    crop_lo[0] - lo[0],
                    crop_lo[1] - lo[1] + j,
                    crop_lo[2] - lo[2] + k,
                );
                part.extend_from_slice(&var[at..at + dims[0]]);
            }
        }
        Ok(Some(crate::render::variance_image(gpu, dims, &part)?))
    }

    /// The crop's glow image at `crop_lo` of `dims`, where structures have margins.
    fn crop_glow(&self, gpu: &Gpu, crop_lo: [usize; 3], dims: [usize; 3]) -> Result<Option<Image>> {
        let Some(fields) = &self.margins else {
            return Ok(None);
        };
        let glow = crate::volume::distance::glow_in(fields, crop_lo, dims);
        Ok(Some(crate::render::glow_image(gpu, dims, &glow)?))
    }

    /// Which structures the tools leave standing (by structure index), from the next frame on.
    pub fn set_protected(&mut self, protected: &[bool]) {
        self.protected = protected.to_vec();
    }

    /// Records, submits and waits for one frame's update of each box shown ([`Cao::run_frame`]):
    /// what each did.
    pub fn run_frame(
        &mut self,
        tools: &[Tool],
        (shown, p): (&Volume, &Placement),
        mode: Mode,
    ) -> Result<Vec<FrameMetrics>> {
        let mut done = Vec::new();
        for part in self.boxes.iter_mut().filter_map(|b| b.part.as_mut()) {
            let placement = Self::placed(&part.crop, shown, p);
            if part.ids.is_some() {
                part.cao.set_protected(&self.protected);
            }
            done.push(part.cao.run_frame(tools, &placement, mode)?);
        }
        Ok(done)
    }

    /// The first box's crop on the GPU (the inner box and its margin): its first voxel and its
    /// size.
    pub fn crop_box(&self) -> Option<([usize; 3], [usize; 3])> {
        let p = self.boxes[0].part.as_ref()?;
        Some((p.crop_lo, p.crop.dims))
    }

    /// Gives up the last box where there are several (and adds none from now on: together
    /// they did not fit); with one, makes it a fifth smaller on each side, cut again where it
    /// is. False (and no box) where it would be smaller than [`MIN_SIDE`].
    pub fn shrink(&mut self, gpu: &Gpu) -> Result<bool> {
        if self.boxes.len() > 1 {
            self.boxes.pop();
            self.most = self.boxes.len();
            return Ok(true);
        }
        let centre = self.centre_of(0);
        self.boxes[0] = InsetBox::default();
        self.inner = self.inner.map(|n| n * 4 / 5);
        self.single = self.inner;
        if self.inner.iter().any(|&n| n < MIN_SIDE) {
            return Ok(false);
        }
        self.cut(gpu, centre)?;
        Ok(true)
    }

    /// Box `b`'s centre (full-resolution index point; the box shown or being computed), or the
    /// volume's with neither.
    fn centre_of(&self, b: usize) -> [f64; 3] {
        self.lo_of(b)
            .map_or(self.whole.dims.map(|d| d as f64 * 0.5), |lo| {
                std::array::from_fn(|a| lo[a] as f64 + 0.5 * self.inner[a] as f64)
            })
    }

    /// The boxes shown, as the ray caster reads them over `shown` placed at `p`.
    pub fn bindings<'a>(&'a self, shown: &Volume, p: &Placement) -> Vec<InsetBinding<'a>> {
        let binding = |part: &'a Part| {
            let crop = &part.crop;
            // The crop's texture coordinates from the shown volume's: the same axes, so a scale
            // and an offset per axis.
            let m = world_from_tex(crop, &Self::placed(crop, shown, p)).inverse()
                * world_from_tex(shown, p);
            let scale = Vec3::new(m.x_axis.x, m.y_axis.y, m.z_axis.z);
            let offset = m.w_axis.xyz();
            let inner = |lo: usize, a: usize| (lo - part.crop_lo[a]) as f32 / crop.dims[a] as f32;
            let lo = Vec3::from_array(std::array::from_fn(|a| inner(part.inner_lo[a], a)));
            let hi = Vec3::from_array(std::array::from_fn(|a| {
                inner(part.inner_lo[a] + self.inner[a], a)
            }));
            InsetBinding {
                scalars: &part.scalars,
                ao: (&part.cao.ao).into(),
                bleeding: part.cao.method().bleeding(),
                structures: part.ids.as_ref(),
                variance: part.variance.as_ref(),
                glow: part.glow.as_ref(),
                lo: (lo - offset) / scale,
                hi: (hi - offset) / scale,
                scale,
                offset,
            }
        };
        self.boxes
            .iter()
            .filter_map(|b| b.part.as_ref())
            .map(binding)
            .collect()
    }

    /// The clip tools and maps for this frame ([`Cao::clip_buffers`]) of the first box shown:
    /// the ray caster's shadow test uses them, so that a cut lies where it lies at full
    /// resolution (the maps are the tools' in their own space, and their texels follow the
    /// dilation radius, which follows the voxel size: every box's are the same).
    pub fn clip_buffers(&self) -> Option<(&crate::gpu::Buffer, &crate::gpu::Buffer)> {
        let part = self.boxes.iter().find_map(|b| b.part.as_ref())?;
        let (tools, maps, _) = part.cao.clip_buffers();
        Some((tools, maps))
    }

    /// The first box's CAO state, where it is on the GPU.
    pub fn cao(&self) -> Option<&Cao> {
        self.boxes[0].part.as_ref().map(|p| &p.cao)
    }
}

/// The ray through the centre of both eyes' pictures: their mean position and centre
/// direction (world space).
fn centre_ray(views: &[View; 2]) -> (Vec3, Vec3) {
    let dir = |v: &View| {
        let f = &v.fov;
        let x = 0.5 * (f.angle_left.tan() + f.angle_right.tan());
        let y = 0.5 * (f.angle_up.tan() + f.angle_down.tan());
        v.pose.orientation * Vec3::new(x, y, -1.0).normalize()
    };
    let [l, r] = views;
    (
        0.5 * (l.pose.position + r.pose.position),
        (dir(l) + dir(r)).normalize(),
    )
}

/// The margin (voxels per axis) that holds every voxel the AO of `config` reads around the
/// inner box: its reach at full resolution, and two voxels for the trilinear footprint and
/// rounding.
fn margin_for(whole: &Volume, config: &AoConfig) -> [usize; 3] {
    let reach_mm = config.reach_mm(whole.spacing);
    whole.spacing.map(|s| (reach_mm / s).ceil() as usize + 2)
}
