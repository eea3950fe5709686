//! The scene a frame renders: where the volume is and which clipping tools cut it. Interaction
//! turns FrameInput into a Scene; the GPU frame only reads it.

use crate::clip::Shape;
use crate::space::{Placement, Pose};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ToolMode {
    /// The inside of the tool is removed.
    #[default]
    Carve,
    /// Only the inside of the tool is kept.
    Probe,
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
}
