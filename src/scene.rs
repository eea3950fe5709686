//! The scene a frame renders: where the volume is and which clipping tools cut it. Interaction
//! turns FrameInput into a Scene; the GPU frame only reads it.

use crate::render::{Placement, Pose};
use serde::{Deserialize, Serialize};

/// A clipping tool's shape, in tool-local metres scaled by [`Tool::size`] (unit size = 1):
/// sphere of radius 1, cube of half-edge 1, cylinder of radius 1 and half-height 1 along local Z,
/// torus of major radius 1 and minor radius [`TORUS_MINOR`] around local Z, or a loaded mesh.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Shape {
    Sphere,
    Box,
    Cylinder,
    Torus,
    /// Index into the meshes loaded for this session (OBJ/PLY).
    Mesh(usize),
}

/// Minor (tube) radius of the unit torus.
pub const TORUS_MINOR: f32 = 0.35;

/// The built-in shapes in the order a "cycle shape" button visits them.
pub const BUILTIN_SHAPES: [Shape; 4] = [Shape::Sphere, Shape::Box, Shape::Cylinder, Shape::Torus];

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
    /// Turn of the environment light about the world's up axis (radians), on top of the
    /// session's starting turn; SH lighting re-projects the light, no visibility recompute.
    #[serde(default)]
    pub light_yaw: f32,
}
