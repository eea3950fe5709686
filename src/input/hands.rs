//! Tracked hands (XR_EXT_hand_tracking's 26 joints) as a controller: the grip pose comes from
//! the palm, the aim from the index finger, a pinch (thumb tip to index tip) is the trigger and a
//! grasp (the middle, ring and little finger tips curled to the palm) is the grip, each with
//! hysteresis so a hand resting near the threshold does not chatter. The rules are plain data in,
//! plain data out: the front end that reads the joints keeps a [`HandGesture`] per hand and puts
//! the resulting [`HandInput`] (and the joints, for drawing and recording) in the FrameInput, so
//! a replay needs no gesture state and renders the same frames.

use super::{Buttons, HandInput};
use crate::space::Pose;
use glam::{Quat, Vec3};

/// XR_EXT_hand_tracking's joints, in its order.
pub const JOINT_COUNT: usize = 26;
pub const PALM: usize = 0;
pub const WRIST: usize = 1;
pub const THUMB_TIP: usize = 5;
pub const INDEX_PROXIMAL: usize = 7;
pub const INDEX_TIP: usize = 10;
pub const MIDDLE_TIP: usize = 15;
pub const RING_TIP: usize = 20;
pub const LITTLE_TIP: usize = 25;

/// A pinch starts below this thumb-to-index tip distance (m)...
pub const PINCH_ON: f32 = 0.02;
/// ...and ends above this one.
pub const PINCH_OFF: f32 = 0.04;
/// A grasp starts when the middle, ring and little tips are this close to the palm on average
/// (m)...
pub const GRASP_ON: f32 = 0.045;
/// ...and ends when they are this far.
pub const GRASP_OFF: f32 = 0.065;

/// One hand's tracked joints: each joint's pose (its -Z along the bone towards the tip, as
/// OpenXR defines it) and radius (m).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HandJoints {
    pub poses: [Pose; JOINT_COUNT],
    pub radii: [f32; JOINT_COUNT],
}

impl HandJoints {
    fn at(&self, j: usize) -> Vec3 {
        self.poses[j].position
    }

    /// Thumb tip to index tip (m).
    pub fn pinch_distance(&self) -> f32 {
        self.at(THUMB_TIP).distance(self.at(INDEX_TIP))
    }

    /// Mean distance of the middle, ring and little tips to the palm (m).
    pub fn curl_distance(&self) -> f32 {
        [MIDDLE_TIP, RING_TIP, LITTLE_TIP]
            .iter()
            .map(|&j| self.at(j).distance(self.at(PALM)))
            .sum::<f32>()
            / 3.0
    }

    /// The aim: at the index tip, pointing along the index finger (proximal joint to tip) as
    /// -Z; the palm's orientation when the finger has no length.
    pub fn aim(&self) -> Pose {
        let dir = self.at(INDEX_TIP) - self.at(INDEX_PROXIMAL);
        let orientation = match dir.try_normalize() {
            Some(d) => {
                let palm = self.poses[PALM].orientation;
                // The rotation that takes the palm's -Z onto the finger, applied to the palm.
                Quat::from_rotation_arc(palm * -Vec3::Z, d) * palm
            }
            None => self.poses[PALM].orientation,
        };
        Pose {
            position: self.at(INDEX_TIP),
            orientation: orientation.normalize(),
        }
    }

    /// Whether every position and orientation is finite and every radius positive.
    pub fn is_valid(&self) -> bool {
        self.poses.iter().all(|p| {
            p.position.is_finite() && p.orientation.is_finite() && p.orientation.length() > 0.5
        }) && self.radii.iter().all(|r| r.is_finite() && *r > 0.0)
    }
}

/// One hand's pinch and grasp state (the hysteresis), and its last input.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HandGesture {
    pub pinching: bool,
    pub grasping: bool,
    last: HandInput,
}

impl HandGesture {
    /// This frame's controller-shaped input from the joints. Without joints (or with broken
    /// ones) the hand is untracked: it freezes like a controller that lost tracking, keeping its
    /// last poses and gestures, so a hand found again still pinching does not press again.
    pub fn update(&mut self, joints: Option<&HandJoints>) -> HandInput {
        let Some(j) = joints.filter(|j| j.is_valid()) else {
            return HandInput {
                tracked: false,
                ..self.last
            };
        };
        let pinch = j.pinch_distance();
        self.pinching = if self.pinching {
            pinch <= PINCH_OFF
        } else {
            pinch < PINCH_ON
        };
        let curl = j.curl_distance();
        self.grasping = if self.grasping {
            curl <= GRASP_OFF
        } else {
            curl < GRASP_ON
        };
        self.last = HandInput {
            tracked: true,
            grip: j.poses[PALM],
            aim: j.aim(),
            buttons: Buttons {
                trigger: if self.pinching { 1.0 } else { 0.0 },
                grip: if self.grasping { 1.0 } else { 0.0 },
                ..Default::default()
            },
        };
        self.last
    }
}

/// A synthetic open hand at `palm` (palm facing -Y, fingers along -Z), with the thumb tip
/// `pinch` metres from the index tip and the finger tips `curl` metres from the palm: for
/// scripts and tests.
pub fn synthetic_hand(palm: Pose, pinch: f32, curl: f32) -> HandJoints {
    let mut local = [Vec3::ZERO; JOINT_COUNT];
    local[WRIST] = Vec3::new(0.0, 0.0, 0.08);
    // Each finger: metacarpal, proximal, intermediate, distal, tip along -Z from the palm,
    // spread along x; the tips of the last three pulled back to `curl` from the palm.
    // The thumb has 4 joints from index 2, every other finger 5 from 6, 11, 16, 21.
    for (f, x) in [-0.04f32, -0.02, 0.0, 0.02, 0.04].into_iter().enumerate() {
        let (first, joints) = if f == 0 { (2, 4) } else { (6 + 5 * (f - 1), 5) };
        for k in 0..joints {
            let t = (k + 1) as f32 / joints as f32;
            local[first + k] = Vec3::new(x, 0.0, 0.02 - 0.09 * t);
        }
    }
    for tip in [MIDDLE_TIP, RING_TIP, LITTLE_TIP] {
        let d = local[tip].normalize_or_zero();
        local[tip] = d * curl;
    }
    // The thumb tip `pinch` away from the index tip, towards the thumb's side.
    local[THUMB_TIP] = local[INDEX_TIP] + Vec3::new(-pinch, 0.0, 0.0);
    let poses = local.map(|p| Pose {
        position: palm.position + palm.orientation * p,
        orientation: palm.orientation,
    });
    HandJoints {
        poses,
        radii: [0.008; JOINT_COUNT],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hand(pinch: f32, curl: f32) -> HandJoints {
        let palm = Pose {
            position: Vec3::new(0.1, 1.2, -0.4),
            orientation: Quat::from_rotation_y(0.3),
        };
        synthetic_hand(palm, pinch, curl)
    }

    #[test]
    fn a_pinch_is_the_trigger_with_hysteresis() {
        let mut g = HandGesture::default();
        let trigger = |g: &mut HandGesture, d: f32| g.update(Some(&hand(d, 0.09))).buttons.trigger;
        let seq = [0.05, 0.03, 0.019, 0.03, 0.039, 0.041, 0.03, 0.01];
        let got: Vec<f32> = seq.iter().map(|&d| trigger(&mut g, d)).collect();
        assert_eq!(
            got,
            [0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0],
            "on below 2 cm, off above 4 cm"
        );
        assert!((hand(0.03, 0.09).pinch_distance() - 0.03).abs() < 1e-5);
    }

    #[test]
    fn a_grasp_is_the_grip_and_the_poses_come_from_palm_and_index() {
        let mut g = HandGesture::default();
        let grip = |g: &mut HandGesture, c: f32| g.update(Some(&hand(0.06, c))).buttons.grip;
        let got: Vec<f32> = [0.09, 0.05, 0.04, 0.06, 0.07, 0.05]
            .iter()
            .map(|&c| grip(&mut g, c))
            .collect();
        assert_eq!(got, [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]);
        let j = hand(0.06, 0.09);
        let h = g.update(Some(&j));
        assert!(h.tracked);
        assert_eq!(h.grip, j.poses[PALM]);
        // The aim points along the index finger, from its tip.
        let along = (j.poses[INDEX_TIP].position - j.poses[INDEX_PROXIMAL].position).normalize();
        assert!((h.aim.orientation * -Vec3::Z).abs_diff_eq(along, 1e-4));
        assert_eq!(h.aim.position, j.poses[INDEX_TIP].position);
    }

    #[test]
    fn a_lost_or_broken_hand_is_untracked_and_holds_its_last_pose_and_gestures() {
        let mut g = HandGesture::default();
        assert!(!g.update(None).tracked, "never seen: untracked");
        let seen = g.update(Some(&hand(0.01, 0.03)));
        assert_eq!(seen.buttons.trigger, 1.0);
        assert!(g.pinching && g.grasping);
        let lost = g.update(None);
        assert!(!lost.tracked);
        assert_eq!(
            (lost.grip, lost.buttons),
            (seen.grip, seen.buttons),
            "frozen"
        );
        let mut bad = hand(0.01, 0.03);
        bad.poses[3].position.x = f32::NAN;
        assert!(!g.update(Some(&bad)).tracked);
        // Found again, still pinching: the trigger stays held (no second press).
        assert_eq!(g.update(Some(&hand(0.03, 0.09))).buttons.trigger, 1.0);
    }
}
