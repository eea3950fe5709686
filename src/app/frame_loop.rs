//! The one frame loop: FrameInput -> interaction -> Scene -> one GPU command buffer (CAO clip +
//! mask + update, AO into the texture, both eyes) -> images and metrics. Replay drives it from a
//! pose stream; the desktop window and OpenXR feed it the same FrameInput.
//!
//! A transfer-function switch (`scene.tf_index` changed by the menu button) is progressive: O'
//! and its skipping data are classified on a worker thread, then each frame records one slab of
//! V_PAO' (bounded by [`FrameLoop::tf_samples_per_frame`]) ahead of its CAO passes, while the
//! frame still shows the old TF and AO; with SH lighting, slabs of V_PSH' follow. The frame after
//! the last slab switches the LUT, the CAO state and the SH volume over at once.
//!
//! With SH lighting ([`FrameLoop::set_lighting`]) one SH visibility volume serves both eyes: its
//! clip-aware update is recorded right after CAO's, and the environment is projected into the
//! volume's data frame every frame (turning it costs no recompute).

use super::lighting::{LightingOptions, ShLighting};
use super::{precompute_ao, AppError, Result};
use crate::ao::cao::{Cao, FrameMetrics, Mode};
use crate::ao::lao::{SkipBuffers, SkipData};
use crate::ao::progressive::{HostTask, SlabScheduler};
use crate::ao::sh::ShVolume;
use crate::ao::{LaoGpu, LaoParams};
use crate::gpu::{Buffer, Gpu, GpuTimer};
use crate::input::{FrameInput, Interaction, InteractionSettings};
use crate::render::{scene_overlay, OverlayRenderer};
use crate::render::{
    world_from_tex, ClipBinding, FrameViews, RenderSettings, Renderer, StereoImage, StereoTarget,
    VolumeTextures,
};
use crate::scene::Scene;
use crate::volume::transfer::{presets_for_volume, TransferFunction};
use crate::volume::Volume;
use ash::vk;
use std::sync::Arc;

/// How far a transfer-function switch has come: V_PAO' (and V_PSH', half each) of `name` is
/// `fraction` done (0 while the host still classifies). Shown as "TF ct-skin 40%".
#[derive(Clone, Debug, PartialEq)]
pub struct TfProgress {
    pub name: String,
    pub fraction: f32,
}

impl std::fmt::Display for TfProgress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "TF {} {:.0}%", self.name, 100.0 * self.fraction)
    }
}

/// The transfer functions the menu cycles through: `first` (the one asked for), then the
/// presets suited to the volume ([`presets_for_volume`]: CT or MR), each once.
pub fn tf_cycle(first: &TransferFunction, vol: &Volume) -> Vec<TransferFunction> {
    let mut tfs = vec![first.clone()];
    for tf in presets_for_volume(vol)
        .into_iter()
        .filter_map(TransferFunction::preset)
    {
        if !tfs.iter().any(|t| t.name == tf.name) {
            tfs.push(tf);
        }
    }
    tfs
}

/// Default V_PAO' budget per frame, in opacity samples (K*M per voxel): a few ms on a GPU; on a
/// CPU device (lavapipe, ~20 M samples/s) about a tenth of a second.
pub fn default_tf_samples_per_frame(gpu: &Gpu) -> f64 {
    if gpu.is_cpu() {
        2e6
    } else {
        2e8
    }
}

/// A transfer-function switch in flight.
struct TfSwitch {
    /// Index into [`FrameLoop::tfs`] of the TF being computed.
    index: usize,
    stage: SwitchStage,
}

// At most one exists per loop: its size does not matter.
#[allow(clippy::large_enum_variant)]
enum SwitchStage {
    /// O' and its skipping data, on a worker thread.
    Classifying(HostTask<(Vec<f32>, SkipData)>),
    /// One slab of V_PAO' per frame, then (with SH lighting) one slab of V_PSH'.
    Computing {
        opacity: Buffer,
        skip: SkipBuffers,
        pao: Buffer,
        slabs: SlabScheduler,
        sh: Option<(ShVolume, SlabScheduler)>,
    },
}

impl TfSwitch {
    fn fraction(&self) -> f32 {
        match &self.stage {
            SwitchStage::Classifying(_) => 0.0,
            SwitchStage::Computing {
                slabs, sh: None, ..
            } => slabs.fraction(),
            SwitchStage::Computing {
                slabs,
                sh: Some((_, sh_slabs)),
                ..
            } => 0.5 * (slabs.fraction() + sh_slabs.fraction()),
        }
    }
}

/// What one frame produced.
pub struct FrameOutput {
    pub image: StereoImage,
    pub metrics: FrameMetrics,
    /// GPU time of the two eyes' ray cast.
    pub render_ms: f64,
    /// Wall time of the whole frame on the host, read-back included.
    pub frame_ms: f64,
    /// GPU time of this frame's slab of a transfer-function switch (0 without one).
    pub tf_ms: f64,
    /// A transfer-function switch in flight (the frame still shows the old TF); None otherwise.
    pub tf_progress: Option<TfProgress>,
    /// The SH visibility update (zero without SH lighting or without a tool).
    pub sh: ShStats,
}

/// What one frame cost, without its pictures.
pub struct FrameStats {
    pub metrics: FrameMetrics,
    pub render_ms: f64,
    pub frame_ms: f64,
    pub tf_ms: f64,
    pub tf_progress: Option<TfProgress>,
    pub sh: ShStats,
}

/// One frame's clip-aware SH visibility update.
#[derive(Clone, Copy, Debug, Default)]
pub struct ShStats {
    /// SH voxels visited (recomputed where the clip reaches, copied elsewhere in the boxes).
    pub voxels: u64,
    pub gpu_ms: f64,
}

pub struct FrameLoop {
    pub gpu: Gpu,
    geometry: Volume,
    pub cao: Cao,
    pub tex: VolumeTextures,
    renderer: Renderer,
    overlay: OverlayRenderer,
    target: StereoTarget,
    pub interaction: Interaction,
    pub scene: Scene,
    pub mode: Mode,
    pub settings: RenderSettings,
    timer: GpuTimer,
    /// The transfer functions `scene.tf_index` picks from.
    tfs: Vec<TransferFunction>,
    /// Index of the TF whose LUT and AO are shown.
    shown_tf: usize,
    /// The volume's voxels, for classifying on a worker thread (only with more than one TF).
    source: Option<Arc<Volume>>,
    lao: LaoGpu,
    lao_dirs: Buffer,
    switch: Option<TfSwitch>,
    tf_timer: GpuTimer,
    /// Opacity samples (K*M per voxel) of V_PAO' one frame may record during a switch.
    pub tf_samples_per_frame: f64,
    /// Environment lighting through the SH visibility volume ([`FrameLoop::set_lighting`]).
    pub lighting: Option<ShLighting>,
}

impl FrameLoop {
    /// Classifies the volume with the first of `tfs`, precomputes V_PAO (with a progress bar
    /// when asked) and sets up CAO and the renderer for `size` pixels per eye. The menu button
    /// cycles through `tfs` ([`tf_cycle`] makes the usual list).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        gpu: &Gpu,
        vol: &Volume,
        tfs: Vec<TransferFunction>,
        params: LaoParams,
        size: (u32, u32),
        mut interaction: InteractionSettings,
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let tf = tfs.first().ok_or_else(|| {
            AppError::Usage(format!("{}: no transfer function to show", vol.name))
        })?;
        interaction.tf_presets = tfs.len();
        let lao = LaoGpu::new(gpu)?;
        let ao = precompute_ao(gpu, &lao, vol, tf, &params, show_progress)?;
        let lao_dirs = lao.directions_buffer(&params, vol.spacing)?;
        Ok(FrameLoop {
            gpu: gpu.clone(),
            geometry: vol.clone_geometry(),
            cao: ao.into_cao(gpu, vol, params)?,
            tex: VolumeTextures::new(gpu, vol, tf)?,
            renderer: Renderer::new(gpu)?,
            overlay: OverlayRenderer::new(gpu)?,
            target: StereoTarget::new(gpu, size.0, size.1)?,
            interaction: Interaction::new(interaction),
            scene: Scene::default(),
            mode: Mode::Contextual,
            settings: RenderSettings::default(),
            timer: GpuTimer::new(gpu, 2)?,
            source: (tfs.len() > 1).then(|| Arc::new(vol.clone())),
            tfs,
            shown_tf: 0,
            lao,
            lao_dirs,
            switch: None,
            tf_timer: GpuTimer::new(gpu, 2)?,
            tf_samples_per_frame: default_tf_samples_per_frame(gpu),
            lighting: None,
        })
    }

    /// Lights the frames as `opts` says: with SH, precomputes the shared SH visibility volume
    /// of the shown TF's opacity (a progress bar when asked).
    pub fn set_lighting(&mut self, opts: &LightingOptions, show_progress: bool) -> Result<()> {
        opts.apply(&mut self.settings);
        self.lighting = None;
        self.cao.sh_radius_mm = None;
        if opts.uses_sh() {
            self.lighting = Some(ShLighting::new(
                &self.gpu,
                &self.geometry,
                opts,
                &mut self.cao,
                show_progress,
            )?);
        }
        Ok(())
    }

    /// The transfer functions the menu cycles through.
    pub fn transfer_functions(&self) -> &[TransferFunction] {
        &self.tfs
    }

    /// The transfer function whose colours and AO the frames show.
    pub fn shown_tf(&self) -> &TransferFunction {
        &self.tfs[self.shown_tf]
    }

    /// Follows `scene.tf_index`: starts, restarts or drops a switch, hands finished host work to
    /// the GPU, and switches over once every slab of V_PAO' has executed. Runs before the frame
    /// is recorded, after the previous frame's wait, so no submitted work uses what it drops.
    fn advance_tf_switch(&mut self) -> Result<()> {
        let want = self.scene.tf_index % self.tfs.len();
        let target = self.switch.as_ref().map_or(self.shown_tf, |s| s.index);
        if want != target {
            // Dropping the switch in flight frees O', V_PAO' and skip': safe, because every
            // frame waits for its command buffer, so none of them is in use any more; an
            // unfinished classification thread is detached and its result discarded.
            self.switch = None;
            if want != self.shown_tf {
                self.switch = Some(self.start_tf_switch(want)?);
            }
        }
        let Some(sw) = self.switch.as_mut() else {
            return Ok(());
        };
        if let SwitchStage::Classifying(task) = &mut sw.stage {
            let Some(done) = task.poll() else {
                return Ok(());
            };
            let name = &self.tfs[sw.index].name;
            let (opacity, skip) = done.map_err(|msg| {
                AppError::Usage(format!(
                    "{}: classifying with transfer function '{name}' failed: {msg}",
                    self.geometry.name
                ))
            })?;
            let dims = self.geometry.dims;
            let sh = match &self.lighting {
                Some(l) => {
                    let v = ShVolume::new(&self.gpu, &self.geometry, l.volume.params)?;
                    let slabs = SlabScheduler::with_budget(
                        v.grid.dims[2],
                        v.samples_per_slice(),
                        self.tf_samples_per_frame,
                    );
                    Some((v, slabs))
                }
                None => None,
            };
            sw.stage = SwitchStage::Computing {
                sh,
                opacity: Buffer::device_local(
                    &self.gpu,
                    &opacity,
                    vk::BufferUsageFlags::STORAGE_BUFFER,
                    "opacity",
                )?,
                skip: self.lao.upload_skip(&skip)?,
                pao: self.lao.output_buffer(dims)?,
                slabs: SlabScheduler::with_budget(
                    dims[2],
                    LaoGpu::samples_per_slice(dims, &self.cao.params),
                    self.tf_samples_per_frame,
                ),
            };
        }
        let finished = matches!(&sw.stage, SwitchStage::Computing { slabs, sh, .. }
            if slabs.is_finished() && sh.as_ref().is_none_or(|s| s.1.is_finished()));
        if finished {
            let sw = self.switch.take().expect("checked above");
            let SwitchStage::Computing {
                opacity,
                skip,
                pao,
                sh,
                ..
            } = sw.stage
            else {
                unreachable!("finished implies computing")
            };
            self.tex.set_transfer_function(&self.tfs[sw.index])?;
            self.cao.replace_precomputed(opacity, pao, skip)?;
            if let (Some((mut v, _)), Some(l)) = (sh, self.lighting.as_mut()) {
                self.gpu.submit_and_wait(|cmd| v.record_publish(cmd))?;
                l.volume = v;
            }
            self.shown_tf = sw.index;
        }
        Ok(())
    }

    fn start_tf_switch(&self, index: usize) -> Result<TfSwitch> {
        let vol = self
            .source
            .clone()
            .expect("more than one TF keeps the voxels");
        let tf = self.tfs[index].clone();
        let params = self.cao.params;
        let task = HostTask::spawn("cao-xr-classify", move || {
            let opacity = tf.opacity_volume(&vol);
            let skip = SkipData::new(&opacity, vol.dims, vol.spacing, &params);
            (opacity, skip)
        })
        .map_err(|e| {
            AppError::Usage(format!(
                "{}: cannot start a thread to classify with transfer function '{}': {e}",
                self.geometry.name, self.tfs[index].name
            ))
        })?;
        Ok(TfSwitch {
            index,
            stage: SwitchStage::Classifying(task),
        })
    }

    /// Runs one frame and reads both eyes back to the host.
    pub fn frame(&mut self, input: &FrameInput) -> Result<FrameOutput> {
        let t0 = std::time::Instant::now();
        let stats = self.render(input)?;
        let image = self.target.read_back(&self.gpu)?;
        Ok(FrameOutput {
            image,
            metrics: stats.metrics,
            render_ms: stats.render_ms,
            frame_ms: t0.elapsed().as_secs_f64() * 1e3,
            tf_ms: stats.tf_ms,
            tf_progress: stats.tf_progress,
            sh: stats.sh,
        })
    }

    /// The stereo target the last frame was rendered into (both layers in TRANSFER_SRC layout).
    pub fn target(&self) -> &StereoTarget {
        &self.target
    }

    /// Runs one frame on the GPU: interaction, then AO update and both eyes in one command
    /// buffer, leaving the images in [`FrameLoop::target`].
    pub fn render(&mut self, input: &FrameInput) -> Result<FrameStats> {
        self.render_with(input, |_, _| {})
    }

    /// [`FrameLoop::render`], with `after` recorded at the end of the same command buffer, once
    /// both images are in TRANSFER_SRC_OPTIMAL ([`StereoTarget::cmd_finish`]): the headset
    /// copies the eyes into the runtime's swapchain there, so a frame is one submission.
    pub fn render_with(
        &mut self,
        input: &FrameInput,
        after: impl FnOnce(ash::vk::CommandBuffer, &StereoTarget),
    ) -> Result<FrameStats> {
        let t0 = std::time::Instant::now();
        self.interaction.update(input, &mut self.scene);
        self.advance_tf_switch()?;
        let FrameLoop {
            gpu,
            geometry,
            cao,
            tex,
            renderer,
            overlay,
            interaction,
            target,
            scene,
            mode,
            settings,
            timer,
            lao,
            lao_dirs,
            switch,
            tf_timer,
            lighting,
            ..
        } = self;
        let model = world_from_tex(geometry, &scene.volume);
        if let Some(l) = lighting.as_mut() {
            l.update_light(geometry, &scene.volume, scene.light_yaw);
        }
        let count = scene.tools.iter().filter(|t| t.active).count() as u32;
        let mut recorded = Ok(None);
        gpu.submit_and_wait(|cmd| {
            recorded = (|| {
                // One slab of V_PAO' (or, once those are done, of V_PSH') for a TF switch: it
                // writes only buffers of its own, which no other pass of this frame reads, so
                // it needs no barrier here.
                let mut slab = false;
                if let Some(TfSwitch {
                    stage:
                        SwitchStage::Computing {
                            opacity,
                            skip,
                            pao,
                            slabs,
                            sh,
                        },
                    ..
                }) = switch.as_mut()
                {
                    if let Some(z) = slabs.next_slab() {
                        tf_timer.begin(cmd);
                        let dims = geometry.dims;
                        lao.record_slab(cmd, opacity, lao_dirs, skip, pao, dims, &cao.params, z);
                        tf_timer.mark(cmd, "tf-slab");
                        slab = true;
                    } else if let Some((v, sh_slabs)) = sh.as_mut() {
                        if sh_slabs.done() == 0 {
                            v.record_pyramid(cmd, opacity);
                        }
                        if let Some(z) = sh_slabs.next_slab() {
                            tf_timer.begin(cmd);
                            v.record_precompute_slab(cmd, z);
                            tf_timer.mark(cmd, "tf-slab");
                            slab = true;
                        }
                    }
                }
                let pending = cao.record_frame(cmd, &scene.tools, &scene.volume, *mode)?;
                tex.cmd_update_ambient(cmd, &cao.ao);
                let sh = lighting.as_mut().map(|l| l.record_frame(gpu, cmd, cao));
                let (tools, maps) = cao.clip_buffers();
                let frame = FrameViews {
                    views: &input.views,
                    model,
                    clip: (count > 0).then_some(ClipBinding { tools, maps, count }),
                    sh: lighting.as_ref().map(|l| l.binding()),
                };
                timer.begin(cmd);
                renderer.record(cmd, target, tex, &frame, settings)?;
                timer.mark(cmd, "render");
                // Tools and tracked hands over the volume, depth-tested against it.
                let hands = [0, 1].map(|h| {
                    interaction
                        .hand_pose(h)
                        .filter(|_| interaction.is_tracked(h))
                });
                let items = scene_overlay(scene, &hands, interaction.settings().tool_offset);
                overlay.record(cmd, target, &input.views, &items)?;
                target.cmd_finish(cmd);
                after(cmd, target);
                Ok::<_, crate::gpu::GpuError>(Some((pending, slab, sh)))
            })();
        })?;
        let (pending, slab, sh) = recorded?.expect("recorded");
        let metrics = cao.read_metrics(pending)?;
        let sh = match (sh, lighting.as_ref()) {
            (Some(m), Some(l)) => ShStats {
                voxels: m.visited,
                gpu_ms: l.volume.read_frame_ms(&m)?,
            },
            _ => ShStats::default(),
        };
        let render_ms = timer.read()?.first().map_or(0.0, |t| t.1);
        let tf_ms = if slab {
            tf_timer.read()?.first().map_or(0.0, |t| t.1)
        } else {
            0.0
        };
        let tf_progress = self.switch.as_ref().map(|sw| TfProgress {
            name: self.tfs[sw.index].name.clone(),
            fraction: sw.fraction(),
        });
        Ok(FrameStats {
            metrics,
            render_ms,
            frame_ms: t0.elapsed().as_secs_f64() * 1e3,
            tf_ms,
            tf_progress,
            sh,
        })
    }
}
