//! What every front end (the desktop window, the headset, replay and the one-frame render) sets
//! up the same way: the GPU from the command line's options and its banner, the frame loop with
//! its transfer-function cycle and lighting, and the pose-stream recorder.

use super::common::{AppError, Result};
use super::frame_loop::{with_marks, FrameLoop};
use super::lighting::LightingOptions;
use super::tf_switch::tf_cycle;
use crate::ao::filtered::VarianceModulation;
use crate::ao::AoConfig;
use crate::gpu::{Gpu, GpuOptions};
use crate::input::{InteractionSettings, PoseStreamWriter, StreamHeader};
use crate::volume::markups::Markups;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Interaction settings of desktop sessions (and of their replays): the emulated grip is the
/// tool, so there is no offset in the hand.
pub fn desktop_interaction() -> InteractionSettings {
    InteractionSettings {
        tool_offset: glam::Vec3::ZERO,
        ..Default::default()
    }
}

/// GPU options from the command line: `--validation` turns the Khronos layer on (it is also on
/// in debug builds and with CAO_XR_VALIDATION=1); `present` for a window or a mirror.
pub fn gpu_options(validation: bool, present: bool) -> GpuOptions {
    let mut opts = GpuOptions::default();
    opts.validation |= validation;
    opts.present = present;
    opts
}

/// "llvmpipe (LLVM 15.0.6, 256 bits) (validation on)": the device, and whether validation is on.
pub fn gpu_banner(gpu: &Gpu) -> String {
    let validation = if gpu.validation_enabled() {
        " (validation on)"
    } else {
        ""
    };
    format!("{}{validation}", gpu.device_name)
}

/// Starts Vulkan as the command line says and prints the banner on stderr.
pub fn start_gpu(validation: bool, present: bool) -> Result<Gpu> {
    let gpu = Gpu::new(&gpu_options(validation, present))?;
    eprintln!("GPU: {}", gpu_banner(&gpu));
    Ok(gpu)
}

/// What a session shows: the volume, the TF it starts with (the menu cycles through the
/// presets after it), the AO method and its parameters, the lighting and the variance opacity
/// modulation.
pub struct SessionSpec {
    pub volume: Arc<Volume>,
    pub tf: TransferFunction,
    pub ao: AoConfig,
    pub lighting: LightingOptions,
    /// Variance opacity modulation, when asked for (`--variance-max`).
    pub variance: Option<VarianceModulation>,
    /// Points and rulers drawn over the volume (`--markups`).
    pub markups: Markups,
    /// Where the session's markups are written when it ends (`--save-markups`).
    pub save_markups: Option<std::path::PathBuf>,
}

impl SessionSpec {
    /// The frame loop for `size` pixels per eye: V_PAO (and V_PSH with SH lighting) precomputed,
    /// the menu cycling through [`tf_cycle`], lit as asked. With `fast_start` (the window and
    /// the headset) a long LAO precompute does not hold the first picture
    /// ([`super::frame_loop::Built::fast_start_after_s`]).
    pub fn frame_loop(
        &self,
        gpu: &Gpu,
        size: (u32, u32),
        interaction: InteractionSettings,
        show_progress: bool,
        fast_start: bool,
    ) -> Result<FrameLoop> {
        let tfs = tf_cycle(&self.tf, &self.volume);
        let built = super::frame_loop::Built {
            config: self.ao,
            size,
            interaction,
            fast_start_after_s: fast_start.then_some(super::frame_loop::FAST_START_AFTER_S),
        };
        let lighting = Some(&self.lighting);
        let vol = Arc::clone(&self.volume);
        let mut fl = FrameLoop::new_lit(gpu, vol, tfs, built, lighting, show_progress)?;
        fl.set_variance(self.variance)?;
        fl.markups = self.markups.clone();
        fl.progressive_inset = fast_start;
        Ok(fl)
    }
}

impl SessionSpec {
    /// Writes the markups, with the points and rulers the session placed
    /// ([`crate::scene::Scene::marks`]), to `--save-markups`; without it, to `default` when the
    /// session placed any (what a surgeon measured is never lost). Call it however the session
    /// ended. Returns the path written.
    pub fn save_markups(&self, fl: &FrameLoop, default: &Path) -> Result<Option<PathBuf>> {
        let path = match &self.save_markups {
            Some(p) => p.clone(),
            None if fl.scene.marks.is_empty() => return Ok(None),
            None => default.to_path_buf(),
        };
        let all = with_marks(&self.markups, &self.volume, &fl.scene.marks);
        all.write(&path)?;
        eprintln!(
            "markups: {} points and {} rulers written to {}{}",
            all.points.len(),
            all.lines.len(),
            path.display(),
            if all.lines.is_empty() {
                String::new()
            } else {
                format!(" ({})", all.lengths())
            }
        );
        Ok(Some(path))
    }
}

/// `cao-xr-markups-<seconds since 1970>.mrk.json` in the current folder: where a window or a
/// headset session writes the markups it placed without `--save-markups`.
pub fn default_markups_path() -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from(format!("cao-xr-markups-{secs}.mrk.json"))
}

/// A session's input as it is being recorded.
pub type Recorder = PoseStreamWriter<std::io::BufWriter<std::fs::File>>;

/// A recorder writing to `path` when one is asked for.
pub fn recorder(path: Option<&Path>, header: &StreamHeader) -> Result<Option<Recorder>> {
    path.map(|p| {
        PoseStreamWriter::create(p, header).map_err(|e| AppError::Output {
            path: p.display().to_string(),
            msg: e.to_string(),
        })
    })
    .transpose()
}

/// The error of a failed write to the recording.
pub fn record_error(e: impl std::fmt::Display) -> AppError {
    AppError::Output {
        path: "record".into(),
        msg: e.to_string(),
    }
}
