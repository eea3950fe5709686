//! The one frame loop: FrameInput -> interaction -> Scene -> one GPU command buffer (CAO clip +
//! mask + update, both eyes reading V_AO where it lies) -> images and metrics. Replay drives it from a
//! pose stream; the desktop window and OpenXR feed it the same FrameInput.
//!
//! A transfer-function switch (`scene.tf_index` changed by the menu button) is progressive
//! ([`super::tf_switch`]): the frame shows the old TF and AO until the new one is done.
//!
//! With SH lighting ([`FrameLoop::set_lighting`]) one SH visibility volume serves both eyes: its
//! clip-aware update is recorded right after CAO's, and the environment is projected into the
//! volume's data frame every frame (turning it costs no recompute).

use super::budget::FrameBudget;
use super::common::{
    downsample_estimate, fit_advice, open_ao, precompute_method, AppError, Result, MAX_DOWNSAMPLE,
};
use super::inset::Inset;
use super::lighting::{LightingOptions, ShLighting};
use super::tf_switch::{default_tf_samples_per_frame, TfProgress, TfSwitcher};
use crate::ao::cao::{Cao, FrameMetrics, Mode, PendingFrame};
use crate::ao::filtered::{variance_volume, Estimator, FilterInput, VarianceModulation};
use crate::ao::histogram::Neighbourhood;
use crate::ao::sh::ShFrameMetrics;
use crate::ao::{AoConfig, AoMethod, LaoGpu};
use crate::clip::margin::MarginHit;
use crate::gpu::{Buffer, Gpu, GpuError, GpuTimer};
use crate::input::{FrameInput, Interaction, InteractionSettings};
use crate::render::text::{text_items, TEXT_HEIGHT};
use crate::render::{colors, joint_overlay, markup_overlay, scene_overlay, OverlayRenderer};
use crate::render::{
    ClipBinding, EyeSlot, Foveation, FrameViews, RenderSettings, Renderer, StereoImage,
    StereoTarget, VolumeTextures, MAX_FRAMES_IN_FLIGHT,
};
use crate::scene::Scene;
use crate::space::{world_from_tex, Pose, View};
use crate::volume::distance::MarginField;
use crate::volume::markups::Markups;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use ash::vk;
use std::sync::Arc;

/// What one frame produced: its pictures and what it cost.
pub struct FrameOutput {
    pub image: StereoImage,
    pub stats: FrameStats,
}

/// What one frame cost, without its pictures.
pub struct FrameStats {
    pub metrics: FrameMetrics,
    /// GPU time of the two eyes' ray cast.
    pub render_ms: f64,
    /// Wall time of the whole frame on the host (read-back included, for [`FrameLoop::frame`]).
    pub frame_ms: f64,
    /// GPU time of this frame's slab of a transfer-function switch (0 without one).
    pub tf_ms: f64,
    /// A transfer-function switch in flight (the frame still shows the old TF); None otherwise.
    pub tf_progress: Option<TfProgress>,
    /// The SH visibility update (zero without SH lighting or without a tool).
    pub sh: ShStats,
    /// GPU ms of the passes after the AO update.
    pub passes: PassTimes,
    /// The transfer function and the AO method this frame showed.
    pub tf_name: String,
    pub ao_method: String,
    /// Recorded while the frame before was still in flight (two frames in flight).
    pub overlapped: bool,
    /// The ray step, as a multiple of the configured one, that the frame budget chose after this
    /// frame ([`FrameLoop::set_frame_budget`]; 1 without one).
    pub step_factor: f64,
    /// The frames to come are foveated by the frame budget (past its longest step).
    pub budget_foveates: bool,
    /// The render scale the frame budget chose for the frames to come (past foveation; 1
    /// without one): each eye is drawn at this fraction of its image's size per axis.
    pub render_scale: f64,
    /// The tools inside a structure's safety margin this frame (`--margin`).
    pub margins: Vec<MarginHit>,
    /// The full-resolution box this frame, where the volume has one.
    pub inset: Option<InsetStats>,
}

impl FrameStats {
    /// What the frame budget chose: "step x1.50", with ", foveated" and ", scale 0.75" past it.
    pub fn budget(&self) -> String {
        let mut s = format!("step x{:.2}", self.step_factor);
        if self.budget_foveates {
            s += ", foveated";
        }
        if self.render_scale < 1.0 {
            s += &format!(", scale {:.2}", self.render_scale);
        }
        s
    }
}

/// A frame's full-resolution box ([`Inset`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct InsetStats {
    /// GPU ms of the boxes' CAO updates (0 while they are computed).
    pub ao_ms: f64,
    /// How far the finest level's box being computed has come (0 to 1), while one is.
    pub computing: Option<f32>,
}

impl InsetStats {
    /// "4.2 ms", or "40%" while the box is computed.
    pub fn state(&self) -> String {
        match self.computing {
            Some(c) => format!("{:.0}%", 100.0 * c),
            None => format!("{:.1} ms", self.ao_ms),
        }
    }
}

impl std::fmt::Display for InsetStats {
    /// "inset 4.2 ms", or "inset 40%" while the box is computed.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "inset {}", self.state())
    }
}

/// GPU ms of a frame's passes after CAO's (restore, clip + mask and update are in
/// [`FrameMetrics`], the SH update in [`ShStats`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct PassTimes {
    /// Each eye's ray cast (left, right).
    pub eye_ms: [f64; 2],
    /// The tools and hands over the volume, both eyes.
    pub overlay_ms: f64,
    /// The images to copy sources, the caller's copies (the headset's swapchain) and the
    /// read-back.
    pub copy_ms: f64,
}

/// One frame's clip-aware SH visibility update.
#[derive(Clone, Copy, Debug, Default)]
pub struct ShStats {
    /// SH voxels visited (recomputed where the clip reaches, copied elsewhere in the boxes).
    pub voxels: u64,
    pub gpu_ms: f64,
}

/// A frame budget ([`FrameLoop::set_frame_budget`]) and the settings it changes, as they were.
struct BudgetState {
    control: FrameBudget,
    /// The settings' step it replaced (0: automatic), and that step in mm, which it scales.
    configured_step: f32,
    base_step: f32,
    /// The settings' foveation: kept where set, else the budget's own past its longest step.
    configured_foveation: Option<Foveation>,
}

pub struct FrameLoop {
    pub gpu: Gpu,
    /// The one copy of the volume: its geometry for every frame, its voxels for classifying a
    /// new transfer function on a worker thread.
    volume: Arc<Volume>,
    pub cao: Cao,
    pub tex: VolumeTextures,
    renderer: Renderer,
    overlay: OverlayRenderer,
    target: StereoTarget,
    pub interaction: Interaction,
    pub scene: Scene,
    pub mode: Mode,
    pub settings: RenderSettings,
    /// Draw the tools and tracked hands over the volume (off for a still render of the cut;
    /// the markups are drawn either way).
    pub show_overlay: bool,
    /// The transfer functions `scene.tf_index` picks from, and the switch between them.
    tfs: TfSwitcher,
    /// Opacity samples (K*M per voxel) of V_PAO' one frame may record during a switch.
    pub tf_samples_per_frame: f64,
    /// When set, [`FrameLoop::tf_samples_per_frame`] follows the measured GPU times so that a
    /// switch's slab takes about this share of the eyes' ray cast (the frame rate drops to
    /// about 1 / (1 + share) while a switch runs); None keeps the budget fixed (replay, tests).
    pub tf_slab_share: Option<f64>,
    /// Environment lighting through the SH visibility volume ([`FrameLoop::set_lighting`]).
    pub lighting: Option<ShLighting>,
    /// Persistent command buffers, fences and timers, one set per frame in flight.
    slots: Slots,
    /// Frames [`FrameLoop::submit`] leaves in flight (1 or 2).
    depth: usize,
    /// The distance fields of the structures with a safety margin (`--margin`), in the shown
    /// volume's grid or, for a downsampled volume, in `margin_grid`: the full-resolution one
    /// ([`FrameLoop::measure_margins_in`]).
    margins: Arc<Vec<MarginField>>,
    margin_grid: Option<Volume>,
    /// A frame budget ([`FrameLoop::set_frame_budget`]).
    budget: Option<BudgetState>,
    /// Points and rulers drawn with the overlay (`--markups`).
    pub markups: Markups,
    /// A downsampled volume's boxes around the tools ([`Inset`]), a level each, the finest
    /// first: at full resolution, then (where the rest is shown coarser than by 2) at half.
    insets: Vec<Inset>,
    /// Where the box moves, its new AO is computed over the next frames, a slab each (of
    /// [`FrameLoop::tf_samples_per_frame`], at least an eighth of the box: [`Inset::refine`]),
    /// while the downsampled volume shows there
    /// ([`Inset::start_cut`]; the window, the headset and replays), rather than in the frame
    /// that moves it (renders, whose one frame shows the box, and tests).
    pub progressive_inset: bool,
    /// The box's update this frame ([`FrameLoop::update_inset`]), for the frame's stats.
    inset_stats: Option<InsetStats>,
}

/// How a frame loop is set up beside its volume and transfer functions ([`FrameLoop::new`]).
#[derive(Clone, Copy, Debug)]
pub struct Built {
    pub config: AoConfig,
    /// Pixels per eye.
    pub size: (u32, u32),
    pub interaction: InteractionSettings,
    /// A first picture in seconds: when the configured method's precompute would take longer
    /// than this many seconds ([`precompute_seconds`]: LAO on a large volume), the first
    /// frames are lit by [`fast_method`]'s one pass while the configured method is computed
    /// slab by slab, as a switch to it ([`super::tf_switch`]), the slab budget following the
    /// frame times ([`FrameLoop::tf_slab_share`]). None for replay and renders, whose frames
    /// must not depend on how fast the machine is.
    pub fast_start_after_s: Option<f64>,
}

/// The share of the eyes' GPU time a fast start's slabs take ([`FrameLoop::tf_slab_share`]).
pub const FAST_START_SLAB_SHARE: f64 = 1.0;

/// The desktop window's and the headset's [`Built::fast_start_after_s`].
pub const FAST_START_AFTER_S: f64 = 2.0;

/// About how long `config`'s method takes to precompute for `vol` on `gpu`. On a CPU device
/// (lavapipe on two cores, measured on the CT head, a 512 x 512 x 133 chest and the phantom):
/// LAO about 2e8 of its K·(M−1) opacity samples per second, the filters about 1.5e6 voxels per
/// second, the local histograms about 6e8 members of S_r per second clustered (every voxel's
/// local histograms, the training and the assignment, on the host's cores) and 3e8 direct
/// (`--clusters 0`: one pass of sums); on a GPU a hundred times the shaders' rate (1.2e8
/// clustered on lavapipe; an estimate).
pub fn precompute_seconds(gpu: &Gpu, vol: &Volume, config: &AoConfig) -> f64 {
    let voxels = vol.voxel_count() as f64;
    let speed = if gpu.is_cpu() { 1.0 } else { 100.0 };
    let p = &config.lao;
    match config.method {
        AoMethod::Lao => voxels * p.rays as f64 * p.steps.saturating_sub(1) as f64 / (2e8 * speed),
        AoMethod::Filter(_) => voxels / (1.5e6 * speed),
        AoMethod::Histogram(h) => {
            let members = Neighbourhood::new(h.radius_mm, vol.spacing).offsets.len() as f64;
            let rate = match (h.clusters > 0, gpu.is_cpu()) {
                (false, _) => 3e8,
                (true, true) => 6e8,
                (true, false) => 1.2e8,
            };
            voxels * members / (rate * speed)
        }
    }
}

/// The index in `methods` of the method a fast start shows first: filter-gauss (one filtering
/// pass) when the configured method (`methods[0]`) is LAO or the local histograms, else 0 (the
/// filters are fast themselves).
pub fn fast_method(methods: &[AoMethod]) -> usize {
    let gauss = |m: &AoMethod| matches!(m, AoMethod::Filter(f) if f.estimator == Estimator::Gauss);
    match methods.first() {
        Some(AoMethod::Lao | AoMethod::Histogram(_)) => methods.iter().position(gauss).unwrap_or(0),
        _ => 0,
    }
}

/// How a frame loop starts: showing method k of its cycle (precomputed first), or open (AO 1,
/// nothing precomputed) while the configured method is computed.
#[derive(Clone, Copy, PartialEq)]
enum Start {
    Shown(usize),
    Open,
}

/// Downsampling factors tried, from the estimate up, for the one that fits.
const FIT_TRIES: usize = 4;

/// The least share of the volume's side (on every axis) a full-resolution inset is wanted at:
/// smaller ones show the rest of the volume coarser, at most [`INSET_COARSER`] times.
const INSET_SHARE: f64 = 0.25;
const INSET_COARSER: usize = 2;
/// The middle level's downsampling factor, and how much larger (share of the side) than the
/// full-resolution box its box must be to be worth the rest of the volume shown coarser.
const MIDDLE_LEVEL: usize = 2;
const MIDDLE_GAIN: f64 = 1.5;

/// `loaded` and after them the marks a session placed ([`crate::scene::Scene::marks`]) as
/// markups in patient space, named as 3D Slicer names new ones: points "F-1", "F-2", ...,
/// rulers "L-1", "L-2", ... (numbered on from the loaded ones).
pub fn with_marks(loaded: &Markups, vol: &Volume, marks: &[crate::scene::Mark]) -> Markups {
    use crate::volume::markups::{MarkupLine, MarkupPoint};
    let lps = |p| crate::space::lps_from_local_mm(vol, p);
    let mut m = loaded.clone();
    for mark in marks {
        if mark.is_point() {
            let label = format!("F-{}", m.points.len() + 1);
            m.points.push(MarkupPoint {
                label,
                lps: lps(mark.ends[0]),
            });
        } else {
            let label = format!("L-{}", m.lines.len() + 1);
            m.lines.push(MarkupLine {
                label,
                ends: mark.ends.map(lps),
            });
        }
    }
    m
}

impl FrameLoop {
    /// Classifies the volume with the first of `tfs`, precomputes V_PAO (with a progress bar
    /// when asked) and sets up CAO and the renderer for `size` pixels per eye. The menu button
    /// cycles through `tfs` ([`super::tf_switch::tf_cycle`] makes the usual list). Running out
    /// of GPU memory is told as in [`FrameLoop::new_lit`].
    pub fn new(
        gpu: &Gpu,
        vol: Arc<Volume>,
        tfs: Vec<TransferFunction>,
        ao: impl Into<AoConfig>,
        size: (u32, u32),
        interaction: InteractionSettings,
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let built = Built {
            config: ao.into(),
            size,
            interaction,
            fast_start_after_s: None,
        };
        Self::new_lit(gpu, vol, tfs, built, None, show_progress)
    }

    /// [`FrameLoop::new`], then lit as `lighting` says ([`FrameLoop::set_lighting`]). A volume
    /// that runs out of GPU memory in either is not refused: it is shown downsampled by the
    /// smallest N that fits ([`downsample_estimate`]'s, checked by setting the downsampled
    /// volume up the same way; a few larger N are tried where it does not fit), told on stderr
    /// with what did not fit, and named `-dsN` on the stats line. Only where no N fits is it
    /// refused ([`fit_advice`]).
    pub fn new_lit(
        gpu: &Gpu,
        vol: Arc<Volume>,
        tfs: Vec<TransferFunction>,
        built: Built,
        lighting: Option<&LightingOptions>,
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let setup = |vol: Arc<Volume>, progress: bool| {
            let iso = lighting.and_then(|l| l.shading.iso);
            let mut fl = Self::build(gpu, vol, tfs.clone(), (built, iso), progress)?;
            if let Some(l) = lighting {
                fl.light(l, progress)?;
            }
            // The pre-integrated table the first frame would build (its staging included), and
            // room for what a frame holds beside the set-up, so that a set-up that fits also
            // draws with tools carving.
            fl.tex.prepare(&fl.settings)?;
            gpu.check_room(
                "a frame's tools, boxes, staging and read-back",
                fl.frame_reserve(),
            )?;
            Ok(fl)
        };
        let m = match setup(vol.clone(), show_progress) {
            Err(AppError::Gpu(GpuError::OutOfMemory(m))) => m,
            r => return r,
        };
        // the failed set-up is dropped: its memory is free for the tries
        let base = gpu.memory_in_use();
        let fitted = downsample_estimate(&vol, &m).and_then(|first| {
            (first..=(first + FIT_TRIES - 1).min(MAX_DOWNSAMPLE)).find_map(|n| {
                let coarse = Arc::new(vol.downsample(n));
                gpu.reset_memory_peak();
                setup(coarse.clone(), show_progress)
                    .ok()
                    .map(|fl| (coarse, fl))
            })
        });
        match fitted {
            Some((coarse, mut fl)) => {
                let per_voxel =
                    (gpu.memory_peak() - base) as f64 / coarse.voxel_count().max(1) as f64;
                let [x, y, z] = vol.dims;
                let [cx, cy, cz] = coarse.dims;
                eprintln!(
                    "volume {} ({x} x {y} x {z}) does not fit beside everything else on the GPU: \
                     {m}; shown downsampled by {} ({cx} x {cy} x {cz}, {}), the finest that fits",
                    vol.name,
                    coarse.downsampled_by(),
                    coarse.name
                );
                if !Inset::wanted() {
                    fl.measure_margins_in(&vol)?;
                    return Ok(fl);
                }
                // Full resolution around the tools: where the box that fits beside this
                // downsample is small, the rest of the volume is shown coarser for a larger one.
                let at = |n: usize| -> Result<(FrameLoop, f64)> {
                    let c = Arc::new(vol.downsample(n));
                    gpu.reset_memory_peak();
                    let fl = setup(c.clone(), show_progress)?;
                    let per_voxel = (gpu.memory_peak() - base) as f64 / c.voxel_count() as f64;
                    Ok((fl, per_voxel))
                };
                let inset = |fl: &mut FrameLoop, per_voxel| {
                    fl.add_inset(vol.clone(), built.config, (m.available, per_voxel), None)
                };
                // The downsample with the largest box (share of the side), the finest first.
                let mut n = coarse.downsampled_by();
                let last = (n + INSET_COARSER).min(MAX_DOWNSAMPLE);
                let mut best = (n, inset(&mut fl, per_voxel)?);
                while best.1 < INSET_SHARE && n < last {
                    n += 1;
                    drop(fl);
                    let (next, per_voxel) = at(n)?;
                    fl = next;
                    let share = inset(&mut fl, per_voxel)?;
                    if share > best.1 {
                        best = (n, share);
                    }
                }
                if best.0 != n {
                    drop(fl);
                    let (next, per_voxel) = at(best.0)?;
                    fl = next;
                    if best.1 > 0.0 {
                        inset(&mut fl, per_voxel)?;
                    }
                }
                // A middle level: where the rest is shown by 3 or coarser, showing it one step
                // coarser still frees room for a box at half resolution around the full one
                // (the same size), worth it where that box is half as large again.
                let n = best.0;
                let full = fl.inset().map(|i| (i.inner_size(), i.share()));
                let middle = Inset::middle_wanted() && (3..MAX_DOWNSAMPLE).contains(&n);
                if let Some((inner, share)) = full.filter(|_| middle) {
                    drop(fl);
                    let (mut next, per_voxel) = at(n + 1)?;
                    let mid = if next.add_inset(vol.clone(), built.config, (0, 0.0), Some(inner))?
                        > 0.0
                    {
                        let half = Arc::new(vol.downsample(MIDDLE_LEVEL));
                        next.add_level(half, built.config, (m.available, per_voxel), None)?
                    } else {
                        0.0
                    };
                    fl = if mid >= MIDDLE_GAIN * share {
                        next
                    } else {
                        eprintln!(
                            "volume {}: the box at half resolution is too small; back to the \
                             volume downsampled by {n}",
                            vol.name
                        );
                        drop(next);
                        let (mut back, per_voxel) = at(n)?;
                        inset(&mut back, per_voxel)?;
                        back
                    };
                }
                fl.measure_margins_in(&vol)?;
                Ok(fl)
            }
            None => Err(fit_advice(
                &vol,
                AppError::Gpu(GpuError::OutOfMemory(m)),
                None,
            )),
        }
    }

    /// Measures the safety margins in `whole`, the full-resolution volume this one is a
    /// downsample of (its distance fields, on the host), so that a tool's distance to a
    /// structure is as exact as at full resolution; the margins glow from the shown volume's
    /// fields, but in the full-resolution box ([`Inset::set_margins`]) from these.
    fn measure_margins_in(&mut self, whole: &Volume) -> Result<()> {
        let fields = whole
            .labels
            .as_deref()
            .map_or_else(Vec::new, |l| l.margin_fields(whole.dims, whole.spacing));
        if !fields.is_empty() {
            self.margins = Arc::new(fields);
            self.margin_grid = Some(whole.clone_geometry());
            for (level, inset) in self.insets.iter_mut().enumerate() {
                // A coarser level's boxes glow from its own grid's fields.
                let fields = match level {
                    0 => self.margins.clone(),
                    _ => Arc::new(inset.own_margin_fields()),
                };
                inset.set_margins(&self.gpu, fields)?;
            }
        }
        Ok(())
    }

    /// What this loop's frames hold beside its set-up, at most: the shown volume's
    /// [`super::inset::frame_reserve`] and the read-back of a waited frame (`render`'s, a
    /// screenshot's), made at its first use.
    fn frame_reserve(&self) -> u64 {
        super::inset::frame_reserve(self.volume.voxel_count()) + self.target.readback_bytes()
    }

    /// Shows the box around the tools at full resolution from `whole` ([`Inset`]), within
    /// `available` bytes of GPU memory at about `per_voxel` bytes per voxel, or of `inner`
    /// voxels where given; told on stderr. Returns the box's least share of the volume's side
    /// (0: none fits).
    fn add_inset(
        &mut self,
        whole: Arc<Volume>,
        config: AoConfig,
        (available, per_voxel): (u64, f64),
        inner: Option<[usize; 3]>,
    ) -> Result<f64> {
        self.tex.show_as(&whole, self.tfs.shown())?;
        // The first frame's pre-integrated table for the new step, as the set-up made one.
        self.tex.prepare(&self.settings)?;
        self.insets.clear();
        let share = self.add_level(whole, config, (available, per_voxel), inner)?;
        if share == 0.0 {
            self.drop_inset()?;
        }
        Ok(share)
    }

    /// Adds a level of boxes from `whole` (the full-resolution volume, or a finer downsample
    /// than the one shown) after the finer ones, as [`FrameLoop::add_inset`] does; told on
    /// stderr. Returns its boxes' least share of the volume's side (0: none fits, none added).
    fn add_level(
        &mut self,
        whole: Arc<Volume>,
        config: AoConfig,
        (available, per_voxel): (u64, f64),
        inner: Option<[usize; 3]>,
    ) -> Result<f64> {
        let (method, tf) = self.tfs.shown_ao();
        let config = AoConfig { method, ..config };
        let name = whole.name.clone();
        let frames = self.frame_reserve();
        let gpu = &self.gpu;
        let inset = match inner {
            Some(inner) => {
                let centre = whole.dims.map(|d| d as f64 * 0.5);
                match Inset::around(gpu, whole, (config, tf), (inner, centre)) {
                    Err(AppError::Gpu(GpuError::OutOfMemory(_))) => None,
                    r => Some(r?),
                }
            }
            None => Inset::new(gpu, whole, (config, tf), (available, per_voxel, frames))?,
        };
        match inset {
            Some(mut i) => {
                if !self.insets.is_empty() {
                    i.keep_one();
                }
                eprintln!("volume {name}: {}", i.describe());
                let share = i.share();
                self.insets.push(i);
                Ok(share)
            }
            None => {
                let what = match self.insets.is_empty() {
                    true => "full-resolution inset".to_string(),
                    false => format!("inset downsampled by {MIDDLE_LEVEL}"),
                };
                eprintln!("volume {name}: no {what} fits beside it");
                Ok(0.0)
            }
        }
    }

    /// Brings the inset up to the scene (no frame in flight): the shown TF and method, the box
    /// around the tools, and its AO update for this frame's tools, submitted and waited for
    /// on its own. Where the update runs out of GPU memory (the tools' boxes grow what a frame
    /// holds) the box is made smaller, or given up.
    fn update_inset(&mut self, views: &[View; 2], gaze: Option<Pose>) -> Result<()> {
        let (method, tf) = self.tfs.shown_ao();
        let (tools, placement) = (&self.scene.tools, &self.scene.volume);
        let shown = &*self.volume;
        // The structures as the shown volume's AO has them, and as the tools guard them now.
        let structures = self.tfs.shown_structures();
        let mut stats = InsetStats::default();
        let mut level = 0;
        while let Some(inset) = self.insets.get_mut(level) {
            let config = AoConfig {
                method,
                ..inset.config()
            };
            if !inset.computes(&config, &tf, structures) {
                inset.set_shown(&self.gpu, (config, tf.clone()), structures)?;
            }
            inset.set_protected(&self.scene.protected);
            // Cut again where the boxes should go (at once, or over the next frames), then the
            // next slab of each box being computed, then this frame's update of the boxes shown.
            let cuts = inset.wants_cuts((tools, views, gaze), shown, placement);
            let computing = inset.refining().is_some();
            let mut step = inset
                .make_cuts(&self.gpu, &cuts, self.progressive_inset)
                .and_then(|_| inset.refine(&self.gpu, self.tf_samples_per_frame));
            if step.is_ok() && (!cuts.cuts.is_empty() || computing && inset.refining().is_none()) {
                eprintln!("volume {}: {}", shown.name, inset.describe());
            }
            let metrics = loop {
                let run = |i: &mut Inset| i.run_frame(tools, (shown, placement), self.mode);
                match step.and_then(|_| run(&mut self.insets[level])) {
                    Err(AppError::Gpu(GpuError::OutOfMemory(m))) => {
                        // The coarsest level yields first: a middle box shrinks (or goes) so
                        // that the full-resolution boxes keep their size.
                        let last = self.insets.len() - 1;
                        let coarsest = &mut self.insets[last];
                        if coarsest.shrink(&self.gpu)? {
                            eprintln!("volume {}: {} ({m})", shown.name, coarsest.describe());
                        } else {
                            let (name, which) = (&shown.name, coarsest.level());
                            eprintln!("volume {name}: the inset is given up ({which}): {m}");
                            self.insets.remove(last);
                            if last == level {
                                break None;
                            }
                        }
                        step = Ok(());
                    }
                    r => break Some(r?),
                }
            };
            // A level given up goes; the others stay.
            let Some(metrics) = metrics else { continue };
            let inset = &self.insets[level];
            stats.ao_ms += metrics.iter().map(|m| m.gpu_ms()).sum::<f64>();
            // The progress told is the finest level's (a middle box being computed shows
            // the rest's voxels meanwhile, as the finer boxes go on).
            if level == 0 {
                stats.computing = inset.refining();
            }
            level += 1;
        }
        if self.insets.is_empty() {
            return self.drop_inset();
        }
        self.inset_stats = Some(stats);
        Ok(())
    }

    /// No inset: the downsampled volume alone, sampled as itself again (its step, its value
    /// range), with the pre-integrated table the next frame reads.
    fn drop_inset(&mut self) -> Result<()> {
        self.insets.clear();
        let shown = self.volume.clone();
        self.tex.show_as(&shown, self.tfs.shown())?;
        self.tex.prepare(&self.settings)?;
        Ok(())
    }

    /// The finest boxes around the tools of a downsampled volume (at full resolution, unless
    /// they were given up), if it has any.
    pub fn inset(&self) -> Option<&Inset> {
        self.insets.first()
    }

    /// The levels of boxes around the tools, the finest (full resolution) first.
    pub fn insets(&self) -> &[Inset] {
        &self.insets
    }

    fn build(
        gpu: &Gpu,
        vol: Arc<Volume>,
        tfs: Vec<TransferFunction>,
        (built, iso): (Built, Option<f32>),
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let Built {
            config,
            size,
            mut interaction,
            fast_start_after_s,
        } = built;
        let params = config.lao;
        let first = tfs.first().ok_or_else(|| {
            AppError::Usage(format!("{}: no transfer function to show", vol.name))
        })?;
        // With an isosurface the AO is its solid's, and the surface takes the TF's colour there.
        let tf = &match iso {
            Some(v) => first.iso_solid(v, vol.value_range()),
            None => first.clone(),
        };
        interaction.tf_presets = tfs.len();
        let methods = config.cycle();
        interaction.ao_methods = methods.len();
        let (lo, hi) = vol.value_range();
        interaction.iso_rate = 0.25 * (hi - lo);
        // The scene asks for the configured method (ao_index 0). A fast start (the configured
        // method takes long) shows the fast one first when that is quick itself, so the first
        // frame starts the switch to the configured one; else it shows no AO at once (open:
        // AO 1) and computes the configured one slab by slab (not the fast one first: the
        // filters refilter in one go, and a frame held for minutes is worse than AO later).
        let fast = fast_method(&methods);
        let seconds = |method| precompute_seconds(gpu, &vol, &AoConfig { method, ..config });
        let (configured, quick) = (seconds(methods[0]), seconds(methods[fast]));
        let start = match fast_start_after_s {
            Some(s) if configured > s && fast != 0 && quick <= s => Start::Shown(fast),
            Some(s) if configured > s => Start::Open,
            _ => Start::Shown(0),
        };
        let lao = LaoGpu::new(gpu)?;
        let (ao, shown) = match start {
            Start::Shown(k) => {
                let first = AoConfig {
                    method: methods[k],
                    ..config
                };
                let ao = precompute_method(gpu, &lao, &vol, tf, &first, show_progress)?;
                (ao, k)
            }
            Start::Open => (open_ao(gpu, &vol)?, 0),
        };
        let lao_dirs = lao.directions_buffer(&params, vol.spacing)?;
        // The CAO state first: it lets go of what only the precompute read (LAO's padded O)
        // and of V_PAO's GPU copy before the scalars are uploaded, so the peak holds not both.
        let cao = ao.into_cao(gpu, &vol)?;
        let mut tex = VolumeTextures::new(gpu, &vol, tf)?;
        let margins = vol
            .labels
            .as_ref()
            .map_or_else(Vec::new, |l| l.margin_fields(vol.dims, vol.spacing));
        if !margins.is_empty() {
            tex.set_glow(
                gpu,
                Some(&crate::volume::distance::glow(&margins, vol.dims)),
            )?;
        }
        let settings = RenderSettings {
            bleeding: config.bleeding,
            iso,
            ..Default::default()
        };
        Ok(FrameLoop {
            gpu: gpu.clone(),
            cao,
            tex,
            renderer: Renderer::new(gpu)?,
            overlay: OverlayRenderer::new(gpu)?,
            target: StereoTarget::new(gpu, size.0, size.1)?,
            interaction: Interaction::new(interaction),
            scene: Scene {
                structures: vol.labels.as_ref().map_or_else(Vec::new, |l| l.opacities()),
                protected: vol.labels.as_ref().map_or_else(Vec::new, |l| l.protected()),
                iso,
                ..Default::default()
            },
            mode: Mode::Contextual,
            settings,
            show_overlay: true,
            slots: Slots::new(gpu)?,
            depth: MAX_FRAMES_IN_FLIGHT,
            tfs: TfSwitcher::new(
                gpu,
                tfs,
                (methods, shown, start == Start::Open),
                (vol.labels.as_deref(), vol.value_range(), iso),
                (lao, lao_dirs, params),
            )?,
            tf_samples_per_frame: default_tf_samples_per_frame(gpu),
            tf_slab_share: (start != Start::Shown(0)).then_some(FAST_START_SLAB_SHARE),
            lighting: None,
            margins: Arc::new(margins),
            margin_grid: None,
            budget: None,
            markups: Markups::default(),
            insets: Vec::new(),
            progressive_inset: false,
            inset_stats: None,
            volume: vol,
        })
    }

    /// Lights the frames as `opts` says: with SH, precomputes the shared SH visibility volume
    /// of the shown TF's opacity (a progress bar when asked).
    /// Running out of GPU memory is told with [`fit_advice`] (the frame loop holds its
    /// memory meanwhile, so the `--downsample N` is [`downsample_estimate`]'s, untried;
    /// [`FrameLoop::new_lit`] tries it).
    pub fn set_lighting(&mut self, opts: &LightingOptions, show_progress: bool) -> Result<()> {
        self.light(opts, show_progress)
            .map_err(|e| fit_advice(&self.volume, e, None))
    }

    fn light(&mut self, opts: &LightingOptions, show_progress: bool) -> Result<()> {
        opts.apply(&mut self.settings);
        self.lighting = None;
        self.cao.sh_radius_mm = None;
        if opts.uses_sh() {
            if self
                .tfs
                .methods()
                .iter()
                .any(|m| matches!(m, AoMethod::Histogram(_)))
            {
                return Err(AppError::Usage(
                    "SH lighting is not combined with the local-histogram AO (--ao histogram): \
                     use --lighting ao, or another AO method"
                        .into(),
                ));
            }
            let scalar =
                |m: &AoMethod| matches!(m, AoMethod::Filter(f) if f.input == FilterInput::Scalar);
            if self.tfs.methods().iter().any(scalar) {
                return Err(AppError::Usage(
                    "SH lighting marches the opacity; with --filter-input scalar the filters' \
                     volumes hold the scalar instead: use --filter-input opacity, or --lighting ao"
                        .into(),
                ));
            }
            self.lighting = Some(ShLighting::new(
                &self.gpu,
                &self.volume,
                opts,
                &mut self.cao,
                show_progress,
            )?);
        }
        Ok(())
    }

    /// Variance opacity modulation: var_s of the volume's data over the centred box of
    /// `m.radius_mm`, and the ray caster's V_max; None turns it off.
    pub fn set_variance(&mut self, m: Option<VarianceModulation>) -> Result<()> {
        let var = m.map(|m| variance_volume(&self.volume, m.radius_mm));
        self.tex.set_variance(&self.gpu, var.as_deref())?;
        for inset in &mut self.insets {
            inset.set_variance(&self.gpu, m)?;
        }
        self.settings.variance_max = m.map_or(0.0, |m| m.max as f32);
        Ok(())
    }

    /// The transfer functions the menu cycles through.
    pub fn transfer_functions(&self) -> &[TransferFunction] {
        self.tfs.all()
    }

    /// The transfer function whose colours and AO the frames show.
    pub fn shown_tf(&self) -> &TransferFunction {
        self.tfs.shown()
    }

    /// The volume the frames show.
    pub fn volume(&self) -> &Volume {
        &self.volume
    }

    /// The structure menu's line: the selected structure and how the scene asks to show it,
    /// "structure 2/5 liver: hidden"; None without labels.
    pub fn structure_menu(&self) -> Option<String> {
        let (k, n) = self.menu_position()?;
        Some(format!(
            "structure {}/{n} {}",
            k + 1,
            self.selected_structure()?
        ))
    }

    /// "liver: translucent": the structure the menu selects and how it is shown (the headset
    /// writes it above the left hand).
    pub fn selected_structure(&self) -> Option<String> {
        let (k, _) = self.menu_position()?;
        let labels = self.volume.labels.as_ref()?;
        let protected = self.scene.protected.get(k).copied().unwrap_or(false);
        Some(format!(
            "{}: {}{}",
            labels.structures[k].name,
            crate::volume::labels::shown_as(self.scene.structures[k]),
            if protected { ", protected" } else { "" }
        ))
    }

    /// The selected structure's index and the number of structures, with a label map.
    fn menu_position(&self) -> Option<(usize, usize)> {
        let labels = self.volume.labels.as_ref()?;
        let n = self.scene.structures.len().min(labels.structures.len());
        (n > 0).then(|| (self.scene.structure_selected % n, n))
    }

    /// "margin aorta 3.2 mm < 5 mm (tool 0)" for each of `hits`, joined; None without hits.
    pub fn margin_warning(&self, hits: &[MarginHit]) -> Option<String> {
        let labels = self.volume.labels.as_ref()?;
        let line: Vec<String> = hits
            .iter()
            .map(|h| {
                format!(
                    "margin {} {:.1} mm < {} mm (tool {})",
                    labels.structures[h.structure].name, h.distance_mm, h.margin_mm, h.tool
                )
            })
            .collect();
        (!line.is_empty()).then(|| line.join(", "))
    }

    /// The AO methods the stick click cycles through (the first is the one configured).
    pub fn ao_methods(&self) -> &[AoMethod] {
        self.tfs.methods()
    }

    /// Holds a frame time of `target_ms` by lengthening the ray step (up to
    /// [`super::budget::MAX_STEP_FACTOR`] times the step of the settings now), then foveating,
    /// then lowering the render scale, from the measured GPU times ([`FrameBudget`]); the AO is
    /// never touched. None: the settings' step and foveation at full scale, always. Replay and
    /// renders run without one: their pictures must not depend on the machine.
    pub fn set_frame_budget(&mut self, target_ms: Option<f64>) {
        if let Some(b) = self.budget.take() {
            self.settings.step_mm = b.configured_step;
            self.settings.foveation = b.configured_foveation;
            self.target.set_render_scale(1.0);
        }
        let base = self.settings.step_for(self.tex.step_spacing);
        self.budget = target_ms.filter(|t| *t > 0.0).map(|t| BudgetState {
            control: FrameBudget::new(t),
            configured_step: self.settings.step_mm,
            base_step: base,
            configured_foveation: self.settings.foveation,
        });
    }

    /// The frame time a frame budget holds, if one does.
    pub fn frame_budget(&self) -> Option<f64> {
        self.budget.as_ref().map(|b| b.control.target_ms)
    }

    /// Frames the GPU may hold at once (1 or 2, [`crate::render::MAX_FRAMES_IN_FLIGHT`]).
    pub fn frames_in_flight(&self) -> usize {
        self.depth
    }

    /// Sets how many frames [`FrameLoop::submit`] leaves in flight; waits for the frame in
    /// flight first and returns it.
    pub fn set_frames_in_flight(&mut self, n: usize) -> Result<Option<Retired>> {
        if !(1..=MAX_FRAMES_IN_FLIGHT).contains(&n) {
            return Err(AppError::Usage(format!(
                "--frames-in-flight {n}: must be 1..={MAX_FRAMES_IN_FLIGHT}"
            )));
        }
        let r = self.flush()?;
        self.depth = n;
        Ok(r)
    }

    /// Runs one frame and reads both eyes back to the host (waits for it, whatever the depth).
    pub fn frame(&mut self, input: &FrameInput) -> Result<FrameOutput> {
        let r = self.now(input, true, |_, _| {})?;
        let image = r.image.expect("asked for the read-back");
        Ok(FrameOutput {
            image,
            stats: r.stats,
        })
    }

    /// Draws the frames to come at `scale` of the target's size per axis
    /// ([`StereoTarget::set_render_scale`]); a frame budget sets its own on every frame.
    pub fn set_render_scale(&mut self, scale: f64) {
        self.target.set_render_scale(scale);
    }

    /// The stereo target the last frame was rendered into (both layers in TRANSFER_SRC layout
    /// once it finished).
    pub fn target(&self) -> &StereoTarget {
        &self.target
    }

    /// Runs one frame on the GPU and waits for it: interaction, then AO update and both eyes in
    /// one command buffer, leaving the images in [`FrameLoop::target`].
    pub fn render(&mut self, input: &FrameInput) -> Result<FrameStats> {
        self.render_with(input, |_, _| {})
    }

    /// [`FrameLoop::render`], with `after` recorded at the end of the same command buffer, once
    /// both images are in TRANSFER_SRC_OPTIMAL ([`StereoTarget::cmd_finish`]).
    pub fn render_with(
        &mut self,
        input: &FrameInput,
        after: impl FnOnce(vk::CommandBuffer, &StereoTarget),
    ) -> Result<FrameStats> {
        Ok(self.now(input, false, after)?.stats)
    }

    /// One frame submitted and waited for, with no other frame in flight.
    fn now(
        &mut self,
        input: &FrameInput,
        read_back: bool,
        after: impl FnOnce(vk::CommandBuffer, &StereoTarget),
    ) -> Result<Retired> {
        if !self.slots.flights.is_empty() {
            return Err(AppError::Usage(
                "a frame is still in flight: FrameLoop::flush it before a waited frame".into(),
            ));
        }
        let depth = std::mem::replace(&mut self.depth, 1);
        let r = self.submit(input, read_back, after);
        self.depth = depth;
        Ok(r?.expect("with one frame in flight, submit retires it"))
    }

    /// Submits the frame of `input` (its interaction, AO update, both eyes, overlay, then
    /// `after` and, with `read_back`, the copy of both eyes to the host, all in the slot's
    /// persistent command buffer) and returns the frame that left the GPU: this one with one
    /// frame in flight, the one before with two (none on the first call; [`FrameLoop::flush`]
    /// gets the last). With two, this frame's input, interaction, uniforms and command
    /// recording run while the GPU renders the frame before, and the caller's work until the
    /// next call (the headset's wait for its next frame, the window's events, writing the
    /// returned frame's PNG) while it renders this one.
    pub fn submit(
        &mut self,
        input: &FrameInput,
        read_back: bool,
        after: impl FnOnce(vk::CommandBuffer, &StereoTarget),
    ) -> Result<Option<Retired>> {
        self.submit_signalling(input, read_back, after, None)
    }

    /// [`FrameLoop::submit`], whose submission also signals `signal` (a window's present
    /// waits on it).
    pub fn submit_signalling(
        &mut self,
        input: &FrameInput,
        read_back: bool,
        after: impl FnOnce(vk::CommandBuffer, &StereoTarget),
        signal: Option<vk::Semaphore>,
    ) -> Result<Option<Retired>> {
        let t0 = std::time::Instant::now();
        // The isovalue the settings start with becomes the scene's, which the hands then move.
        self.scene.iso = self.scene.iso.or(self.settings.iso);
        self.interaction.update(input, &mut self.scene);
        let shown = &*self.volume;
        let (grid, at) = match &self.margin_grid {
            Some(g) => (g, Inset::placed(g, shown, &self.scene.volume)),
            None => (shown, self.scene.volume),
        };
        let margins = self
            .cao
            .margin_hits(&self.scene.tools, (grid, &at), &self.margins)?;
        // Everything a frame writes from the host or reads back has one copy per slot (CAO's
        // tool table, maps, counters and timer, the SH timers, the uniforms, the read-back).
        // A transfer-function switch is the exception: it replaces buffers the frame in flight
        // reads and has one timer, so while one runs the frame before is waited for first.
        let mut retired = None;
        if !self.tfs.settled(&self.scene) {
            retired = self.retire()?;
        }
        // The budget's step: a new one rebuilds the pre-integration table and the empty bricks
        // the frame in flight reads, so that frame is waited for first.
        if let Some(b) = &self.budget {
            let step = b.base_step * b.control.step_factor() as f32;
            // Foveation as configured, or the default where the budget wants it.
            let foveation = b
                .configured_foveation
                .or(b.control.foveate().then(Foveation::default));
            // The render scale needs no wait: the target's images stay as they are.
            self.target.set_render_scale(b.control.render_scale());
            if step != self.settings.step_for(self.tex.step_spacing) {
                if retired.is_none() {
                    retired = self.retire()?;
                }
                self.settings.step_mm = step;
            }
            self.settings.foveation = foveation;
        }
        if !self.insets.is_empty() {
            // The inset's box and V_AO, which the frame in flight reads, change now.
            if retired.is_none() {
                retired = self.retire()?;
            }
            self.update_inset(&input.views, input.gaze)?;
        }
        self.record_and_submit(input, read_back, after, signal, (t0, margins))?;
        if retired.is_none() && self.slots.flights.len() >= self.depth {
            retired = self.retire()?;
        }
        Ok(retired)
    }

    /// Waits for the frame still in flight, if any, and returns it.
    pub fn flush(&mut self) -> Result<Option<Retired>> {
        self.retire()
    }

    /// Waits for the oldest frame in flight and reads what it produced.
    fn retire(&mut self) -> Result<Option<Retired>> {
        let Some(f) = self.slots.flights.front() else {
            return Ok(None);
        };
        // Waited for before it leaves the list: a frame whose wait failed stays in flight, so
        // the slots are never destroyed under it.
        self.gpu.wait_fences(&[self.slots.slots[f.slot].fence])?;
        let Some(f) = self.slots.flights.pop_front() else {
            return Ok(None);
        };
        let slot = &self.slots.slots[f.slot];
        self.tfs.picture_shown();
        let metrics = self.cao.read_metrics(f.pending)?;
        let sh = match (f.sh, self.lighting.as_ref()) {
            (Some(m), Some(l)) => ShStats {
                voxels: m.visited,
                gpu_ms: l.volume.read_frame_ms(&m)?,
            },
            _ => ShStats::default(),
        };
        let times = slot.timer.read()?;
        let ms = |name: &str| times.iter().find(|t| t.0 == name).map_or(0.0, |t| t.1);
        let passes = PassTimes {
            eye_ms: PASS_EYES.map(ms),
            overlay_ms: ms(PASS_OVERLAY),
            copy_ms: ms(PASS_COPY),
        };
        let tf_ms = if f.slab { self.tfs.read_ms()? } else { 0.0 };
        let render_ms = passes.eye_ms[0] + passes.eye_ms[1];
        let step_factor = match self.budget.as_mut() {
            Some(b) => {
                let other =
                    metrics.gpu_ms() + sh.gpu_ms + tf_ms + passes.overlay_ms + passes.copy_ms;
                b.control.observe(render_ms, other)
            }
            None => 1.0,
        };
        if let (Some(share), true) = (self.tf_slab_share, tf_ms > 0.0) {
            // Towards a slab of `share` times the ray cast, at most doubling or halving per frame.
            let scale = (share * render_ms.max(1.0) / tf_ms).clamp(0.5, 2.0);
            self.tf_samples_per_frame *= scale;
        }
        let image = match (&slot.readback, f.read_back) {
            (Some(bufs), true) => Some(self.target.image_from(bufs, f.drawn)?),
            _ => None,
        };
        Ok(Some(Retired {
            stats: FrameStats {
                metrics,
                render_ms,
                frame_ms: f.t0.elapsed().as_secs_f64() * 1e3,
                tf_ms,
                tf_progress: f.tf_progress,
                sh,
                passes,
                tf_name: f.tf_name,
                ao_method: f.ao_method,
                overlapped: f.overlapped,
                margins: f.margins,
                inset: f.inset,
                step_factor,
                budget_foveates: self.budget.as_ref().is_some_and(|b| b.control.foveate()),
                render_scale: self
                    .budget
                    .as_ref()
                    .map_or(1.0, |b| b.control.render_scale()),
            },
            image,
        }))
    }

    fn record_and_submit(
        &mut self,
        input: &FrameInput,
        read_back: bool,
        after: impl FnOnce(vk::CommandBuffer, &StereoTarget),
        signal: Option<vk::Semaphore>,
        (t0, margins): (std::time::Instant, Vec<MarginHit>),
    ) -> Result<()> {
        self.tfs.advance(
            &self.scene,
            &self.volume,
            self.tf_samples_per_frame,
            &mut self.cao,
            &mut self.tex,
            self.lighting.as_mut(),
        )?;
        let index = self.slots.next % self.depth;
        if read_back && self.slots.slots[index].readback.is_none() {
            self.slots.slots[index].readback = Some(self.target.readback_buffers(&self.gpu)?);
        }
        let menu = self.selected_structure();
        let FrameLoop {
            gpu,
            volume,
            cao,
            tex,
            renderer,
            overlay,
            interaction,
            target,
            scene,
            mode,
            settings,
            show_overlay,
            slots,
            tfs,
            lighting,
            markups,
            insets,
            inset_stats,
            ..
        } = self;
        let model = world_from_tex(volume, &scene.volume);
        let head = crate::space::head_of(&input.views);
        if let Some(l) = lighting.as_mut() {
            l.update_light(volume, &scene.volume, scene.light_yaw);
        }
        let count = scene.tools.iter().filter(|t| t.cuts()).count() as u32;
        // The structure menu's protection, for the clip and the ray caster alike.
        if volume.labels.is_some() {
            cao.set_protected(&scene.protected);
            tex.set_protected(&scene.protected);
        }
        tex.prepare(settings)?;
        // Whether the frame before is still in flight (submitted, not waited for) while this
        // one is recorded. (Whether the GPU is still busy with it is the driver's business:
        // lavapipe runs submitted work as late as the next wait.)
        let overlapped = !slots.flights.is_empty();
        let slot = &mut slots.slots[index];
        let (cmd, d) = (slot.cmd, &gpu.device);
        // SAFETY: `cmd` is this slot's, from a RESET_COMMAND_BUFFER pool only this thread uses; its
        // last submission has finished: `submit` retires frames so that fewer than `depth` are in
        // flight when the next slot (round robin over `depth`) is recorded, and `now` starts with
        // none.
        unsafe {
            // The pool resets the buffer on begin; its last submission has finished.
            d.begin_command_buffer(
                cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .map_err(crate::gpu::GpuError::from)?;
        }
        // The volume's CAO state, its textures and the stereo target are one copy: this
        // frame's passes come after the frame before's, which may still be running.
        gpu.barrier(cmd);
        let timer = &mut slot.timer;
        let recorded = (|| {
            let slab = tfs.record_slab(cmd, volume);
            let pending = cao.record_frame(cmd, &scene.tools, &scene.volume, *mode)?;
            timer.begin(cmd);
            let sh = lighting.as_mut().map(|l| l.record_frame(gpu, cmd, cao));
            timer.mark(cmd, PASS_SH);
            let (tools, maps, bricks) = cao.clip_buffers();
            let (tools, maps) = insets
                .iter()
                .find_map(|i| i.clip_buffers())
                .unwrap_or((tools, maps));
            let boxes: Vec<_> = insets
                .iter()
                .flat_map(|i| i.bindings(volume, &scene.volume))
                .collect();
            let frame = FrameViews {
                views: &input.views,
                model,
                clip: (count > 0).then_some(ClipBinding {
                    tools,
                    maps,
                    bricks,
                    count,
                    reach: &cao.reach_boxes,
                }),
                sh: lighting.as_ref().map(|l| l.binding()),
                ao: Some((&cao.ao).into()),
                bleeding: cao.method().bleeding(),
                insets: &boxes,
                gaze: input
                    .gaze
                    .map(|g| crate::render::fixation(&g, scene.volume.center)),
            };
            let mut settings = *settings;
            settings.iso = scene.iso;
            let eyes = EyeSlot {
                slot: index,
                after_eye: &mut |cmd, eye| timer.mark(cmd, PASS_EYES[eye]),
            };
            // The eyes read what this frame's passes wrote (V_AO, E, the clip state).
            gpu.barrier(cmd);
            renderer.record_eyes(cmd, eyes, target, tex, &frame, &settings)?;
            // Tools and tracked hands over the volume, depth-tested against it (not in a still
            // render of the cut), and the markups always.
            let mut items = Vec::new();
            if *show_overlay {
                let hands = [0, 1].map(|h| {
                    interaction
                        .hand_pose(h)
                        .filter(|_| interaction.is_tracked(h))
                });
                let warned: Vec<usize> = margins.iter().map(|h| h.tool).collect();
                let offset = interaction.settings().tool_offset;
                items = scene_overlay(scene, &hands, offset, &warned);
                let joints = input.joints.iter().flatten();
                let joints =
                    joints.flat_map(|j| j.poses.iter().copied().zip(j.radii.iter().copied()));
                joint_overlay(joints, &mut items);
                if let (Some(menu), Some(left)) = (&menu, hands[crate::input::LEFT]) {
                    // The structure menu above the hand that works it.
                    let at = left.position + head.orientation * glam::Vec3::new(0.0, 0.05, 0.0);
                    let h = 0.75 * TEXT_HEIGHT;
                    items.extend(text_items(menu, at, &head, h, colors::TEXT));
                }
            }
            let markups = with_marks(markups, volume, &scene.marks);
            markup_overlay(&markups, volume, &scene.volume, &head, &mut items);
            overlay.record(cmd, target, &input.views, &items)?;
            timer.mark(cmd, PASS_OVERLAY);
            target.cmd_finish(cmd);
            after(cmd, target);
            if let (true, Some(bufs)) = (read_back, &slot.readback) {
                target.cmd_read_back(gpu, cmd, bufs);
            }
            timer.mark(cmd, PASS_COPY);
            Ok::<_, crate::gpu::GpuError>((pending, slab, sh))
        })();
        // SAFETY: `cmd` was begun above, and every pass ends its own rendering before it returns,
        // also when recording stops at an error.
        let ended = unsafe { d.end_command_buffer(cmd) };
        let (pending, slab, sh) = recorded?;
        ended.map_err(crate::gpu::GpuError::from)?;
        // SAFETY: `cmd` was ended without error; the slot's fence is reset here and no submission
        // uses it (its last one finished, see begin above); `signal` is a presenter's semaphore for
        // the image acquired this frame, unsignalled since its last present waited on it; what the
        // commands name stays alive until the frame is retired (FrameLoop::drop flushes).
        unsafe {
            let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
            let signals: Vec<_> = signal
                .iter()
                .map(|s| {
                    vk::SemaphoreSubmitInfo::default()
                        .semaphore(*s)
                        .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
                })
                .collect();
            let submit = [vk::SubmitInfo2::default()
                .command_buffer_infos(&cmds)
                .signal_semaphore_infos(&signals)];
            d.reset_fences(&[slot.fence])
                .map_err(crate::gpu::GpuError::from)?;
            gpu.submit(&submit, slot.fence)?;
        }
        slots.next = index + 1;
        slots.flights.push_back(InFlight {
            slot: index,
            pending,
            slab,
            sh,
            tf_progress: tfs.progress(),
            tf_name: tfs.shown().name.clone(),
            ao_method: cao.method_name(),
            margins,
            inset: inset_stats.take(),
            read_back,
            drawn: target.drawn(),
            overlapped,
            t0,
        });
        Ok(())
    }
}

impl Drop for FrameLoop {
    fn drop(&mut self) {
        // Nothing the frames in flight use may go before they finished.
        let _ = self.flush();
    }
}

/// A frame that left the GPU: what it cost, and its pictures when they were asked for.
pub struct Retired {
    pub stats: FrameStats,
    pub image: Option<StereoImage>,
}

/// The timer marks of a frame's passes after CAO's own.
const PASS_SH: &str = "sh";
const PASS_EYES: [&str; 2] = ["left eye", "right eye"];
const PASS_OVERLAY: &str = "overlay";
const PASS_COPY: &str = "copy";
/// The start mark and the five above.
const PASS_MARKS: u32 = 7;

/// One frame slot: a persistent command buffer, the fence of its last submission, its timer
/// and its read-back buffers.
struct Slot {
    cmd: vk::CommandBuffer,
    fence: vk::Fence,
    timer: GpuTimer,
    readback: Option<[Buffer; 2]>,
}

/// What a submitted frame still has to report.
struct InFlight {
    slot: usize,
    pending: PendingFrame,
    slab: bool,
    sh: Option<ShFrameMetrics>,
    tf_progress: Option<TfProgress>,
    tf_name: String,
    ao_method: String,
    margins: Vec<MarginHit>,
    inset: Option<InsetStats>,
    read_back: bool,
    /// The size each eye was drawn at (the target's, or its render-scaled part).
    drawn: (u32, u32),
    overlapped: bool,
    t0: std::time::Instant,
}

/// The frame slots and the frames in flight, oldest first.
struct Slots {
    gpu: Gpu,
    pool: vk::CommandPool,
    slots: Vec<Slot>,
    flights: std::collections::VecDeque<InFlight>,
    next: usize,
}

impl Slots {
    fn new(gpu: &Gpu) -> Result<Slots> {
        let d = &gpu.device;
        let err = crate::gpu::GpuError::from;
        // SAFETY: a plain pool of this device, owned by Slots and destroyed in its Drop.
        let pool = unsafe {
            d.create_command_pool(
                &vk::CommandPoolCreateInfo::default()
                    .queue_family_index(gpu.queue_family)
                    .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                None,
            )
            .map_err(err)?
        };
        let mut s = Slots {
            gpu: gpu.clone(),
            pool,
            slots: Vec::new(),
            flights: Default::default(),
            next: 0,
        };
        for _ in 0..MAX_FRAMES_IN_FLIGHT {
            // SAFETY: `pool` was just created and only this thread uses it.
            let cmd = unsafe {
                d.allocate_command_buffers(
                    &vk::CommandBufferAllocateInfo::default()
                        .command_pool(pool)
                        .level(vk::CommandBufferLevel::PRIMARY)
                        .command_buffer_count(1),
                )
                .map_err(err)?[0]
            };
            // SAFETY: a plain fence of this device, destroyed in Slots' Drop.
            let fence = unsafe {
                d.create_fence(&vk::FenceCreateInfo::default(), None)
                    .map_err(err)?
            };
            let timer = GpuTimer::new(gpu, PASS_MARKS);
            let timer = match timer {
                Ok(t) => t,
                Err(e) => {
                    // SAFETY: the fence was just created and never submitted.
                    unsafe { d.destroy_fence(fence, None) };
                    return Err(e.into());
                }
            };
            s.slots.push(Slot {
                cmd,
                fence,
                timer,
                readback: None,
            });
        }
        Ok(s)
    }
}

impl Drop for Slots {
    fn drop(&mut self) {
        let d = &self.gpu.device;
        // SAFETY: the fences of the frames in flight are waited for first, so no command buffer of
        // the pool is pending when it and the fences go; after a failed wait both are leaked
        // instead.
        unsafe {
            let fences: Vec<vk::Fence> = self
                .flights
                .iter()
                .map(|f| self.slots[f.slot].fence)
                .collect();
            if !fences.is_empty() && self.gpu.wait_fences(&fences).is_err() {
                // A device that stopped answering may still use them (the timers' query pools
                // and read-back buffers too): leaked, not destroyed.
                std::mem::forget(std::mem::take(&mut self.slots));
                return;
            }
            for s in &self.slots {
                d.destroy_fence(s.fence, None);
            }
            d.destroy_command_pool(self.pool, None);
        }
    }
}
