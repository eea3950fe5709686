//! The one frame loop: FrameInput -> interaction -> Scene -> one GPU command buffer (CAO clip +
//! mask + update, AO into the texture, both eyes) -> images and metrics. Replay drives it from a
//! pose stream; the desktop window and OpenXR feed it the same FrameInput.
//!
//! A transfer-function switch (`scene.tf_index` changed by the menu button) is progressive
//! ([`super::tf_switch`]): the frame shows the old TF and AO until the new one is done.
//!
//! With SH lighting ([`FrameLoop::set_lighting`]) one SH visibility volume serves both eyes: its
//! clip-aware update is recorded right after CAO's, and the environment is projected into the
//! volume's data frame every frame (turning it costs no recompute).

use super::lighting::{LightingOptions, ShLighting};
use super::tf_switch::{default_tf_samples_per_frame, TfProgress, TfSwitcher};
use super::{precompute_method, AppError, Result};
use crate::ao::cao::{Cao, FrameMetrics, Mode};
use crate::ao::filtered::{variance_volume, FilterInput, VarianceModulation};
use crate::ao::{AoConfig, AoMethod, LaoGpu};
use crate::gpu::{Gpu, GpuError, GpuTimer};
use crate::input::{FrameInput, Interaction, InteractionSettings};
use crate::render::{joint_overlay, scene_overlay, OverlayRenderer};
use crate::render::{
    ClipBinding, FrameViews, RenderSettings, Renderer, StereoImage, StereoTarget, VolumeTextures,
};
use crate::scene::Scene;
use crate::space::world_from_tex;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
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
    /// Draw the tools and tracked hands over the volume (off for a still render of the cut).
    pub show_overlay: bool,
    timer: GpuTimer,
    /// The transfer functions `scene.tf_index` picks from, and the switch between them.
    tfs: TfSwitcher,
    /// Opacity samples (K*M per voxel) of V_PAO' one frame may record during a switch.
    pub tf_samples_per_frame: f64,
    /// Environment lighting through the SH visibility volume ([`FrameLoop::set_lighting`]).
    pub lighting: Option<ShLighting>,
}

/// How a frame loop is set up beside its volume and transfer functions ([`FrameLoop::new`]).
#[derive(Clone, Copy, Debug)]
pub struct Built {
    pub config: AoConfig,
    /// Pixels per eye.
    pub size: (u32, u32),
    pub interaction: InteractionSettings,
}

/// Downsampling factors tried, from the estimate up, for the one that fits.
const FIT_TRIES: usize = 4;

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
        };
        Self::new_lit(gpu, vol, tfs, built, None, show_progress)
    }

    /// [`FrameLoop::new`], then lit as `lighting` says ([`FrameLoop::set_lighting`]). Running
    /// out of GPU memory in either is told with [`super::fit_advice`] and the `--downsample N`
    /// that fits: [`super::downsample_estimate`]'s, checked by setting the downsampled volume
    /// up the same way (a few larger N are tried where it does not fit).
    pub fn new_lit(
        gpu: &Gpu,
        vol: Arc<Volume>,
        tfs: Vec<TransferFunction>,
        built: Built,
        lighting: Option<&LightingOptions>,
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let setup = |vol: Arc<Volume>, progress: bool| {
            let mut fl = Self::build(gpu, vol, tfs.clone(), built, progress)?;
            if let Some(l) = lighting {
                fl.light(l, progress)?;
            }
            Ok(fl)
        };
        let m = match setup(vol.clone(), show_progress) {
            Err(AppError::Gpu(GpuError::OutOfMemory(m))) => m,
            r => return r,
        };
        // the failed set-up is dropped: its memory is free for the tries
        let fits = super::downsample_estimate(&vol, &m).and_then(|first| {
            (first..=(first + FIT_TRIES - 1).min(super::MAX_DOWNSAMPLE))
                .find(|&n| setup(Arc::new(vol.downsample(n)), false).is_ok())
        });
        Err(super::fit_advice(
            &vol,
            AppError::Gpu(GpuError::OutOfMemory(m)),
            fits,
        ))
    }

    fn build(
        gpu: &Gpu,
        vol: Arc<Volume>,
        tfs: Vec<TransferFunction>,
        built: Built,
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let Built {
            config,
            size,
            mut interaction,
        } = built;
        let ao = config;
        let params = ao.lao;
        let tf = tfs.first().ok_or_else(|| {
            AppError::Usage(format!("{}: no transfer function to show", vol.name))
        })?;
        interaction.tf_presets = tfs.len();
        let methods = ao.cycle();
        interaction.ao_methods = methods.len();
        let lao = LaoGpu::new(gpu)?;
        let ao = precompute_method(gpu, &lao, &vol, tf, &ao, show_progress)?;
        let lao_dirs = lao.directions_buffer(&params, vol.spacing)?;
        let mut tex = VolumeTextures::new(gpu, &vol, tf)?;
        let histogram = methods.iter().any(|m| matches!(m, AoMethod::Histogram(_)));
        tex.set_bleeding(gpu, histogram)?;
        let settings = RenderSettings {
            bleeding: config.bleeding,
            ..Default::default()
        };
        Ok(FrameLoop {
            gpu: gpu.clone(),
            cao: ao.into_cao(gpu, &vol, params)?,
            tex,
            renderer: Renderer::new(gpu)?,
            overlay: OverlayRenderer::new(gpu)?,
            target: StereoTarget::new(gpu, size.0, size.1)?,
            interaction: Interaction::new(interaction),
            scene: Scene::default(),
            mode: Mode::Contextual,
            settings,
            show_overlay: true,
            timer: GpuTimer::new(gpu, 2)?,
            tfs: TfSwitcher::new(gpu, tfs, methods, lao, lao_dirs)?,
            tf_samples_per_frame: default_tf_samples_per_frame(gpu),
            lighting: None,
            volume: vol,
        })
    }

    /// Lights the frames as `opts` says: with SH, precomputes the shared SH visibility volume
    /// of the shown TF's opacity (a progress bar when asked).
    /// Running out of GPU memory is told with [`super::fit_advice`] (the frame loop holds its
    /// memory meanwhile, so the `--downsample N` is [`super::downsample_estimate`]'s, untried;
    /// [`FrameLoop::new_lit`] tries it).
    pub fn set_lighting(&mut self, opts: &LightingOptions, show_progress: bool) -> Result<()> {
        self.light(opts, show_progress)
            .map_err(|e| super::fit_advice(&self.volume, e, None))
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

    /// The AO methods the stick click cycles through (the first is the one configured).
    pub fn ao_methods(&self) -> &[AoMethod] {
        self.tfs.methods()
    }

    /// Runs one frame and reads both eyes back to the host.
    pub fn frame(&mut self, input: &FrameInput) -> Result<FrameOutput> {
        let t0 = std::time::Instant::now();
        let mut stats = self.render(input)?;
        let image = self.target.read_back(&self.gpu)?;
        stats.frame_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(FrameOutput { image, stats })
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
        self.tfs.advance(
            (self.scene.tf_index, self.scene.ao_index),
            &self.volume,
            self.tf_samples_per_frame,
            &mut self.cao,
            &mut self.tex,
            self.lighting.as_mut(),
        )?;
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
            timer,
            tfs,
            lighting,
            ..
        } = self;
        let model = world_from_tex(volume, &scene.volume);
        if let Some(l) = lighting.as_mut() {
            l.update_light(volume, &scene.volume, scene.light_yaw);
        }
        let count = scene.tools.iter().filter(|t| t.active).count() as u32;
        tex.prepare(settings)?;
        let mut recorded = Ok(None);
        gpu.submit_and_wait(|cmd| {
            recorded = (|| {
                let slab = tfs.record_slab(cmd, volume, cao);
                let pending = cao.record_frame(cmd, &scene.tools, &scene.volume, *mode)?;
                tex.cmd_update_ambient(cmd, &cao.ao);
                if let Some(h) = cao.histogram() {
                    tex.cmd_update_bleeding(cmd, &h.e);
                }
                let sh = lighting.as_mut().map(|l| l.record_frame(gpu, cmd, cao));
                let (tools, maps) = cao.clip_buffers();
                let frame = FrameViews {
                    views: &input.views,
                    model,
                    clip: (count > 0).then_some(ClipBinding { tools, maps, count }),
                    sh: lighting.as_ref().map(|l| l.binding()),
                };
                // The bleeding volume is the local histograms' alone.
                let mut settings = *settings;
                if cao.histogram().is_none() {
                    settings.bleeding = 0.0;
                }
                timer.begin(cmd);
                renderer.record(cmd, target, tex, &frame, &settings)?;
                timer.mark(cmd, "render");
                if *show_overlay {
                    // Tools and tracked hands over the volume, depth-tested against it.
                    let hands = [0, 1].map(|h| {
                        interaction
                            .hand_pose(h)
                            .filter(|_| interaction.is_tracked(h))
                    });
                    let mut items =
                        scene_overlay(scene, &hands, interaction.settings().tool_offset);
                    joint_overlay(&input.joints, &mut items);
                    overlay.record(cmd, target, &input.views, &items)?;
                }
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
        let tf_ms = if slab { tfs.read_ms()? } else { 0.0 };
        Ok(FrameStats {
            metrics,
            render_ms,
            frame_ms: t0.elapsed().as_secs_f64() * 1e3,
            tf_ms,
            tf_progress: tfs.progress(),
            sh,
        })
    }
}
