//! The one frame loop: FrameInput -> interaction -> Scene -> one GPU command buffer (CAO clip +
//! mask + update, AO into the texture, both eyes) -> images and metrics. Replay drives it from a
//! pose stream; the desktop window and OpenXR feed it the same FrameInput.

use super::{precompute_ao, Result};
use crate::ao::cao::{Cao, FrameMetrics, Mode};
use crate::ao::{LaoGpu, LaoParams};
use crate::gpu::{Gpu, GpuTimer};
use crate::input::{FrameInput, Interaction, InteractionSettings};
use crate::render::{scene_overlay, OverlayRenderer};
use crate::render::{
    world_from_tex, ClipBinding, FrameViews, RenderSettings, Renderer, StereoImage, StereoTarget,
    VolumeTextures,
};
use crate::scene::Scene;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;

/// What one frame produced.
pub struct FrameOutput {
    pub image: StereoImage,
    pub metrics: FrameMetrics,
    /// GPU time of the two eyes' ray cast.
    pub render_ms: f64,
    /// Wall time of the whole frame on the host, read-back included.
    pub frame_ms: f64,
}

/// What one frame cost, without its pictures.
pub struct FrameStats {
    pub metrics: FrameMetrics,
    pub render_ms: f64,
    pub frame_ms: f64,
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
}

impl FrameLoop {
    /// Classifies the volume, precomputes V_PAO (with a progress bar when asked) and sets up
    /// CAO and the renderer for `size` pixels per eye.
    pub fn new(
        gpu: &Gpu,
        vol: &Volume,
        tf: &TransferFunction,
        params: LaoParams,
        size: (u32, u32),
        interaction: InteractionSettings,
        show_progress: bool,
    ) -> Result<FrameLoop> {
        let lao = LaoGpu::new(gpu)?;
        let ao = precompute_ao(gpu, &lao, vol, tf, &params, show_progress)?;
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
            ..
        } = self;
        let model = world_from_tex(geometry, &scene.volume);
        let count = scene.tools.iter().filter(|t| t.active).count() as u32;
        let mut recorded = Ok(None);
        gpu.submit_and_wait(|cmd| {
            recorded = (|| {
                let pending = cao.record_frame(cmd, &scene.tools, &scene.volume, *mode)?;
                tex.cmd_update_ambient(cmd, &cao.ao);
                let (tools, maps) = cao.clip_buffers();
                let frame = FrameViews {
                    views: &input.views,
                    model,
                    clip: (count > 0).then_some(ClipBinding { tools, maps, count }),
                    sh: None,
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
                Ok::<_, crate::gpu::GpuError>(Some(pending))
            })();
        })?;
        let pending = recorded?.expect("recorded");
        let metrics = cao.read_metrics(pending)?;
        let render_ms = timer.read()?.first().map_or(0.0, |t| t.1);
        Ok(FrameStats {
            metrics,
            render_ms,
            frame_ms: t0.elapsed().as_secs_f64() * 1e3,
        })
    }
}
