//! The scene a frame renders: where the volume is and which clipping tools cut it. Interaction
//! turns FrameInput into a Scene; the GPU frame only reads it.

use crate::clip::Shape;
use crate::space::{Placement, Pose};
use serde::{Deserialize, Serialize};

/// Index of the left hand in a pair of hands (`FrameInput::hands`, the overlay's hand poses),
/// and of the left eye in a pair of views.
pub const LEFT: usize = 0;
/// Index of the right hand (and of the right eye).
pub const RIGHT: usize = 1;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ToolMode {
    /// The inside of the tool is removed.
    #[default]
    Carve,
    /// Only the inside of the tool is kept.
    Probe,
    /// The tool cuts nothing: its centre places points and rulers ([`Scene::marks`]).
    Measure,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tool {
    pub shape: Shape,
    /// Tool-local to world (the clip camera rides on this pose).
    pub pose: Pose,
    /// Metres per tool-local unit (the sphere's radius, the cube's half-edge, ...).
    pub size: f32,
    pub mode: ToolMode,
    /// Whether the tool cuts this frame (carving on/off); an inactive tool is only drawn.
    pub active: bool,
}

impl Tool {
    /// Whether the tool clips this frame: switched on, and not a measuring tool.
    pub fn cuts(&self) -> bool {
        self.active && self.mode != ToolMode::Measure
    }
}

/// A point (both ends equal) or a ruler placed with a measuring tool, in the volume's own
/// millimetres ([`Placement::local_mm`]), so it moves with the volume when the volume is
/// grabbed and converts to patient space exactly ([`crate::space::lps_from_local_mm`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Mark {
    pub ends: [glam::Vec3; 2],
}

impl Mark {
    /// A mark shorter than this (mm) is a point: a click without a drag.
    pub const POINT_MM: f32 = 1.0;

    pub fn is_point(&self) -> bool {
        self.ends[0].distance(self.ends[1]) < Mark::POINT_MM
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    pub volume: Placement,
    pub tools: Vec<Tool>,
    /// Index of the transfer-function preset in use.
    pub tf_index: usize,
    /// Index of the AO method in use (in the session's cycle; the stick click advances it).
    #[serde(default)]
    pub ao_index: usize,
    /// Turn of the environment light about the world's up axis (radians), on top of the
    /// session's starting turn; SH lighting re-projects the light, no visibility recompute.
    #[serde(default)]
    pub light_yaw: f32,
    /// Each labelled structure's opacity a_l (1 shown, 0 hidden, between: translucent), by
    /// structure index; starts as the command line set it. The structure menu changes it, and
    /// every AO method follows as after a TF change.
    #[serde(default)]
    pub structures: Vec<f32>,
    /// The structure the menu acts on (an index into `structures`).
    #[serde(default)]
    pub structure_selected: usize,
    /// Whether the tools leave each structure standing (by structure index); starts as
    /// `--protect` set it, and the structure menu toggles the selected one.
    #[serde(default)]
    pub protected: Vec<bool>,
    /// The isovalue of the isosurface shown (`--iso`, data units), when one is: the left
    /// thumbstick moves it, and the AO follows as after a TF change.
    #[serde(default)]
    pub iso: Option<f32>,
    /// Points and rulers placed in this session with a measuring tool, oldest first (the
    /// last one may still be drawn: its trigger held).
    #[serde(default)]
    pub marks: Vec<Mark>,
}
