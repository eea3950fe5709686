//! OpenXR for the headset front end (`app::headset`): XR_KHR_vulkan_enable2 creates the
//! renderer's Vulkan instance and device, the session runs the full state machine, each frame's
//! predicted display time locates the eyes and hands, and the stereo target is copied into the
//! runtime's swapchain and submitted as a projection layer.
//!
//! Choices, and why:
//! - One array swapchain with two layers (layer 0 = left eye), the same shape as the renderer's
//!   [`StereoTarget`](crate::render::StereoTarget), so both eyes go over in one blit region.
//! - UNORM swapchain formats are preferred: the renderer writes display-ready UNORM values, and
//!   a blit into an sRGB image would encode them a second time.
//! - STAGE space (docs/design.md's world), LOCAL when the runtime has no STAGE.
//! - Bindings are data ([`bindings`]): a new controller is a new JSON file.

pub mod actions;
pub mod bindings;
pub mod blend;
pub mod conversions;
pub mod debug;
pub mod gaze;
pub mod session;
pub mod swapchain;
pub mod vulkan;

pub use session::{StateMachine, Step, XrRuntime, XrSession};

use crate::gpu::GpuError;
use glam::Vec3;
use openxr as xr;
use std::path::PathBuf;

const VIEW_TYPE: xr::ViewConfigurationType = xr::ViewConfigurationType::PRIMARY_STEREO;

#[derive(Debug, thiserror::Error)]
pub enum XrError {
    #[error("no OpenXR runtime: {0} (install an OpenXR loader and runtime, e.g. Monado, or use `cao-xr view`)")]
    NoRuntime(String),
    #[error("OpenXR call failed: {0}")]
    Xr(#[from] xr::sys::Result),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Bindings(#[from] bindings::BindingsError),
    #[error("{0}")]
    Runtime(String),
    #[error("{path}: {msg}")]
    Output { path: String, msg: String },
}

pub type Result<T> = std::result::Result<T, XrError>;

#[derive(Clone, Debug, Default)]
pub struct XrOptions {
    /// Submit this many rendered frames, then ask the runtime to end the session.
    pub frames: Option<usize>,
    /// Record every rendered frame's input as a pose stream.
    pub record: Option<PathBuf>,
    /// Pixels per eye; default: the runtime's recommended size.
    pub size: Option<(u32, u32)>,
    /// Directory of binding files; default [`bindings::default_dir`], else the built-in set.
    pub bindings: Option<PathBuf>,
    /// Hold the right trigger (carving on from the first frame), for controllers that cannot
    /// press buttons (simulated ones in tests). The held trigger is part of the recorded input,
    /// so a replay carves the same way.
    pub carve: bool,
    /// Where the volume's centre starts, in the reference space (default: the scene's).
    pub volume_at: Option<Vec3>,
    /// Also show the left eye in a desktop window (X11), presented after each headset frame.
    pub mirror: bool,
    /// Vulkan validation on (`--validation`; also on in debug builds).
    pub validation: bool,
    /// `--blend`: the environment blend mode asked for.
    pub blend: blend::BlendRequest,
    /// `--passthrough`: the world should show through (a see-through blend mode).
    pub passthrough: bool,
    /// `--frames-in-flight`: 1 or 2 (default [`crate::render::MAX_FRAMES_IN_FLIGHT`]).
    pub frames_in_flight: Option<usize>,
    /// `--frame-budget-ms`: the frame time the ray step is scaled to hold (None: off).
    pub frame_budget_ms: Option<f64>,
}

/// What a session did.
#[derive(Clone, Debug, Default)]
pub struct XrSummary {
    /// Frames rendered and submitted with a projection layer.
    pub frames: usize,
    /// Every session state entered, in order.
    pub states: Vec<String>,
    pub focused: bool,
    /// Haptic pulses sent (tool first touching tissue).
    pub pulses: usize,
    /// Frames in which at least one hand was tracked.
    pub tracked_frames: usize,
    /// The reference space used (STAGE or LOCAL).
    pub space: String,
    /// Frames submitted with depth (XR_KHR_composition_layer_depth) on every projection view.
    pub depth_frames: usize,
    /// Why depth was not submitted (None when it was offered and used).
    pub depth_missing: Option<String>,
    /// Whether XR_EXT_hand_tracking is in use (offered and supported by the system), and in how
    /// many frames a tracked hand drove the interaction with its joints.
    pub hand_tracking: bool,
    pub hand_frames: usize,
    /// Whether XR_EXT_eye_gaze_interaction is in use, and in how many frames it tracked the
    /// gaze (the foveation's centre).
    pub eye_gaze: bool,
    pub gaze_frames: usize,
    /// The environment blend mode submitted with, and the runtime's offer (its order).
    pub blend: String,
    pub blend_offered: Vec<String>,
}

/// Parses `X,Y,Z` (metres) for the command line.
pub fn parse_point(s: &str) -> std::result::Result<Vec3, String> {
    crate::space::parse_triple::<f32>(s).map(Vec3::from_array)
}

/// Whether an OpenXR loader is installed and a runtime answers with a head-mounted display;
/// the CLI's default run uses this to choose between the headset and the desktop window.
pub fn available() -> bool {
    (|| -> Result<()> {
        let (_, instance, _) = open_instance()?;
        instance.system(xr::FormFactor::HEAD_MOUNTED_DISPLAY)?;
        Ok(())
    })()
    .is_ok()
}

pub(crate) fn open_instance() -> Result<(xr::Entry, xr::Instance, xr::ExtensionSet)> {
    // SAFETY: the system's OpenXR loader, like its Vulkan loader, is trusted to follow the
    // specification.
    let entry = unsafe { xr::Entry::load(&()) }.map_err(|e| XrError::NoRuntime(e.to_string()))?;
    let available = entry
        .enumerate_extensions()
        .map_err(|e| XrError::NoRuntime(e.to_string()))?;
    if !available.khr_vulkan_enable2 {
        return Err(XrError::NoRuntime(
            "the runtime lacks XR_KHR_vulkan_enable2".into(),
        ));
    }
    let mut exts = xr::ExtensionSet::default();
    exts.khr_vulkan_enable2 = true;
    // For the messenger that reports the OpenXR validation layer (debug::XrMessenger).
    exts.ext_debug_utils = available.ext_debug_utils;
    // Depth submitted with each projection view, when the runtime takes it (reprojection).
    exts.khr_composition_layer_depth = available.khr_composition_layer_depth;
    // Tracked hands drive the interaction where a controller is not active.
    exts.ext_hand_tracking = available.ext_hand_tracking;
    // Its interaction profile (pinch_ext, grasp_ext), for controllers/bindings/ext_hand_interaction.json.
    exts.ext_hand_interaction = available.ext_hand_interaction;
    // Where the eyes look, for the foveation's centres.
    exts.ext_eye_gaze_interaction = available.ext_eye_gaze_interaction;
    // Passthrough cameras composited under the volume (Quest, Pico), for --passthrough.
    exts.fb_passthrough = available.fb_passthrough;
    let instance = entry
        .create_instance(
            &xr::ApplicationInfo {
                application_name: "cao-xr",
                application_version: 1,
                engine_name: "cao-xr",
                engine_version: 1,
                api_version: xr::Version::new(1, 0, 0),
            },
            &exts,
            &[],
            &(),
        )
        .map_err(|e| XrError::NoRuntime(format!("xrCreateInstance: {e}")))?;
    Ok((entry, instance, exts))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_parse_and_bad_ones_are_named() {
        assert_eq!(
            parse_point("0.2,1.3,-0.58").unwrap(),
            Vec3::new(0.2, 1.3, -0.58)
        );
        assert!(parse_point("1,2").unwrap_err().contains("'1,2'"));
        assert!(parse_point("a,b,c").is_err());
    }
}
