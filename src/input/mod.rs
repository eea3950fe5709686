//! Input as data: one [`FrameInput`] per frame, whatever produced it.
//!
//! OpenXR, the desktop window and pose-stream replay are only different sources of the same
//! value (docs/design.md, "One frame, as data"); the interaction layer turns it into a scene. Keeping
//! it a plain `Copy` value is what makes a frame recordable ([`stream`]), scriptable ([`script`])
//! and replayable bit for bit.
//!
//! Everything is in the OpenXR STAGE space: metres, +Y up, right-handed, a user standing at the
//! origin looking down -Z.

pub mod desktop;
pub mod hands;
pub mod interaction;
pub mod script;
pub mod stream;

pub use interaction::{
    tool_hand, GrabMode, Interaction, InteractionSettings, LEFT_TOOL, RIGHT_TOOL,
    SUGGESTED_SMOOTHING_HZ,
};
pub use script::{generate, script_header, write_script, ScriptError, ScriptKind, ScriptParams};
pub use stream::{
    read_stream, replay_schedule, LineError, PoseStreamReader, PoseStreamWriter, StreamError,
    StreamHeader,
};

use crate::space::{Fov, Pose, View};
use glam::{Quat, Vec2, Vec3};
use serde::{Deserialize, Serialize};

pub use crate::scene::{LEFT, RIGHT};

/// Everything one frame's input says: when, where the eyes are, where the hands are and what
/// they press.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameInput {
    /// Seconds since the start of the stream (or of the session). Replay paces itself by it.
    pub time: f64,
    /// The two eyes, left then right, as OpenXR's PRIMARY_STEREO reports them.
    pub views: [View; 2],
    /// The two hands: [`LEFT`] = 0, [`RIGHT`] = 1.
    pub hands: [HandInput; 2],
    /// Tracked hand joints, per hand, where a hand (not a controller) drives it: drawn in the
    /// overlay and recorded; `hands` already holds what they mean ([`hands::HandGesture`]).
    #[serde(default)]
    pub joints: [Option<hands::HandJoints>; 2],
    /// Where the eyes look (XR_EXT_eye_gaze_interaction's gaze pose: along its -Z), where the
    /// headset tracks them; the foveated ray cast centres on it.
    #[serde(default)]
    pub gaze: Option<Pose>,
}

impl FrameInput {
    /// Two eyes `ipd` metres apart along the head's local x axis (left eye at -ipd/2), both with
    /// the head's orientation and the same field of view, as a desktop or scripted source
    /// stands in for a headset.
    pub fn head_views(head: Pose, ipd: f32, fov: Fov) -> [View; 2] {
        [-0.5f32, 0.5].map(|side| View {
            pose: Pose {
                position: head.position + head.orientation * Vec3::new(side * ipd, 0.0, 0.0),
                orientation: head.orientation,
            },
            fov,
        })
    }

    /// A frame with both hands untracked.
    pub fn without_hands(time: f64, views: [View; 2]) -> Self {
        FrameInput {
            time,
            views,
            hands: [HandInput::default(); 2],
            joints: [None; 2],
            gaze: None,
        }
    }
}

/// One hand controller. OpenXR gives two poses per hand: `grip` (where the hand holds the
/// controller; tools ride on it) and `aim` (the pointing ray, -Z forward; menus and selection).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandInput {
    /// False when the runtime lost the controller: the poses are then stale and must not move
    /// anything, but they must still be valid (the last known ones, or identity) so that the
    /// frame can be recorded; a source must not pass on OpenXR's undefined untracked poses.
    pub tracked: bool,
    pub grip: Pose,
    pub aim: Pose,
    pub buttons: Buttons,
}

impl Default for HandInput {
    /// Untracked, identity poses, nothing pressed.
    fn default() -> Self {
        HandInput {
            tracked: false,
            grip: Pose::IDENTITY,
            aim: Pose::IDENTITY,
            buttons: Buttons::default(),
        }
    }
}

/// The controller's buttons and axes, named by role, not by a vendor's labels (the bindings map
/// a profile's paths onto these).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Buttons {
    /// Grip squeeze, 0 (released) ..= 1 (fully squeezed).
    pub grip: f32,
    /// Index trigger, 0 ..= 1.
    pub trigger: f32,
    /// Primary face button (A / X).
    pub primary: bool,
    /// Secondary face button (B / Y).
    pub secondary: bool,
    pub menu: bool,
    /// Thumbstick (or trackpad) click: next AO method.
    pub stick_click: bool,
    /// Thumbstick (or touchpad), each axis -1 ..= 1, +x right, +y up.
    pub thumbstick: Vec2,
}

/// A pose from a position and an orientation (a shorthand for scripts and tests).
pub fn pose(position: Vec3, orientation: Quat) -> Pose {
    Pose {
        position,
        orientation,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::space::{symmetric_fov, DEFAULT_IPD};

    #[test]
    fn head_views_put_the_left_eye_left_along_the_head_x() {
        // Head turned 90 degrees to the left (about +Y): its local +x now points to world -Z.
        let head = pose(
            Vec3::new(0.0, 1.6, 0.0),
            Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
        );
        let views = FrameInput::head_views(head, DEFAULT_IPD, symmetric_fov(0.6));
        let l = views[LEFT].pose.position;
        let r = views[RIGHT].pose.position;
        assert!((l - Vec3::new(0.0, 1.6, 0.032)).length() < 1e-6, "{l}");
        assert!((r - Vec3::new(0.0, 1.6, -0.032)).length() < 1e-6, "{r}");
        assert_eq!(views[LEFT].pose.orientation, head.orientation);
        assert_eq!(views[LEFT].fov, views[RIGHT].fov);
    }

    #[test]
    fn hand_default_is_untracked_at_identity() {
        let h = HandInput::default();
        assert!(!h.tracked);
        assert_eq!(h.grip, Pose::IDENTITY);
        assert_eq!(h.aim, Pose::IDENTITY);
        assert_eq!(h.buttons.trigger, 0.0);
        assert!(!h.buttons.primary);
    }
}
