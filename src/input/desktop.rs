//! Mouse and keyboard as a head and a right hand, producing the same FrameInput as OpenXR.
//!
//! Keys: left drag orbits the head around the volume, the wheel zooms; W/S move the tool away /
//! towards the head, A/D left / right, Q/E down / up (also right drag in the view plane); Space
//! (held) is the trigger and toggles carving; Tab cycles the tool shape; P switches carve/probe;
//! +/- resize the tool; M cycles transfer-function presets; O cycles the AO method; N selects the
//! next labelled structure and H shows it translucent / hidden / shown (the left hand's primary
//! and secondary buttons, the structure menu); 1 / 2 show one eye / both; Esc quits.

use super::{Buttons, FrameInput, HandInput, LEFT, RIGHT};
use crate::space::{symmetric_fov, Pose, DEFAULT_IPD};
use glam::{Quat, Vec2, Vec3};

/// Keys and buttons the desktop mapping understands (the window translates its events).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Key {
    Forward,
    Back,
    Left,
    Right,
    Down,
    Up,
    Trigger,
    CycleShape,
    CycleMode,
    Grow,
    Shrink,
    Menu,
    /// The stick click: next AO method.
    NextAo,
    /// Sideways stick: turn the environment light.
    LightLeft,
    LightRight,
    /// The structure menu (the left hand's primary and secondary buttons and stick click):
    /// select the next structure; show it translucent, hidden, shown; protect it or not.
    NextStructure,
    ShowStructure,
    ProtectStructure,
}

/// The emulated head and right hand.
#[derive(Clone, Debug)]
pub struct DesktopInput {
    /// Orbit of the head around `target` (radians) and its distance (m).
    pub yaw: f32,
    pub pitch: f32,
    pub distance: f32,
    pub target: Vec3,
    /// The tool's position relative to `target`, in the head's orbit frame (m).
    pub tool: Vec3,
    pub held: std::collections::HashSet<Key>,
    pub ipd: f32,
    /// Vertical half field of view (rad); the horizontal follows the eye image's aspect.
    pub half_fov: f32,
    /// Metres the tool moves per second while a move key is held.
    pub tool_speed: f32,
}

impl DesktopInput {
    pub fn new(target: Vec3) -> Self {
        DesktopInput {
            yaw: 0.0,
            pitch: 0.0,
            distance: 0.6,
            target,
            tool: Vec3::new(0.0, 0.0, 0.08),
            held: Default::default(),
            ipd: DEFAULT_IPD,
            half_fov: 0.45,
            tool_speed: 0.1,
        }
    }

    fn orbit(&self) -> Quat {
        Quat::from_rotation_y(self.yaw) * Quat::from_rotation_x(self.pitch)
    }

    /// Left-drag: orbit by a cursor motion in pixels.
    pub fn drag_orbit(&mut self, delta: Vec2) {
        self.yaw -= delta.x * 0.005;
        self.pitch = (self.pitch - delta.y * 0.005).clamp(-1.4, 1.4);
    }

    /// Right-drag: move the tool in the view plane by a cursor motion in pixels.
    pub fn drag_tool(&mut self, delta: Vec2) {
        self.tool += Vec3::new(delta.x, -delta.y, 0.0) * 0.0005;
    }

    pub fn zoom(&mut self, lines: f32) {
        self.distance = (self.distance * (1.0 - 0.1 * lines)).clamp(0.15, 3.0);
    }

    /// Integrates held move keys over `dt` seconds.
    pub fn step(&mut self, dt: f32) {
        let mut v = Vec3::ZERO;
        for (k, d) in [
            (Key::Forward, Vec3::NEG_Z),
            (Key::Back, Vec3::Z),
            (Key::Left, Vec3::NEG_X),
            (Key::Right, Vec3::X),
            (Key::Down, Vec3::NEG_Y),
            (Key::Up, Vec3::Y),
        ] {
            if self.held.contains(&k) {
                v += d;
            }
        }
        self.tool += v * self.tool_speed * dt;
    }

    /// This frame's FrameInput at `time`, for eye images of `aspect` (width / height).
    pub fn frame_input(&self, time: f64, aspect: f32) -> FrameInput {
        let orbit = self.orbit();
        let head = Pose {
            position: self.target + orbit * Vec3::new(0.0, 0.0, self.distance),
            orientation: orbit,
        };
        let mut fov = symmetric_fov(self.half_fov);
        let h = (self.half_fov.tan() * aspect).atan();
        fov.angle_left = -h;
        fov.angle_right = h;
        let views = FrameInput::head_views(head, self.ipd, fov);
        let grip = Pose {
            position: self.target + orbit * self.tool,
            orientation: orbit,
        };
        let pressed = |k| self.held.contains(&k);
        let right = HandInput {
            tracked: true,
            grip,
            aim: grip,
            buttons: Buttons {
                trigger: if pressed(Key::Trigger) { 1.0 } else { 0.0 },
                primary: pressed(Key::CycleShape),
                secondary: pressed(Key::CycleMode),
                menu: pressed(Key::Menu),
                stick_click: pressed(Key::NextAo),
                thumbstick: Vec2::new(
                    (pressed(Key::LightRight) as i32 - pressed(Key::LightLeft) as i32) as f32,
                    (pressed(Key::Grow) as i32 - pressed(Key::Shrink) as i32) as f32,
                ),
                ..Default::default()
            },
        };
        let mut hands = [HandInput::default(), HandInput::default()];
        hands[RIGHT] = right;
        // The left hand is not tracked, but its buttons act (the structure menu).
        hands[LEFT].tracked = false;
        hands[LEFT].buttons.primary = pressed(Key::NextStructure);
        hands[LEFT].buttons.secondary = pressed(Key::ShowStructure);
        hands[LEFT].buttons.stick_click = pressed(Key::ProtectStructure);
        FrameInput {
            time,
            views,
            hands,
            joints: [None; 2],
            gaze: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_move_the_tool_and_the_head_orbits() {
        let mut d = DesktopInput::new(Vec3::new(0.0, 1.4, -0.6));
        let f0 = d.frame_input(0.0, 1.0);
        d.held.insert(Key::Right);
        d.step(0.5);
        let f1 = d.frame_input(0.5, 1.0);
        let moved = f1.hands[RIGHT].grip.position - f0.hands[RIGHT].grip.position;
        assert!(
            (moved.x - 0.05).abs() < 1e-5 && moved.y.abs() < 1e-6,
            "{moved}"
        );
        d.drag_orbit(Vec2::new(-100.0, 0.0));
        let f2 = d.frame_input(1.0, 1.0);
        let head = (f2.views[0].pose.position + f2.views[1].pose.position) * 0.5;
        assert!(
            (head - d.target).length() - d.distance < 1e-5,
            "the head stays on its orbit"
        );
        assert!(head.x > 0.0, "dragging left orbits the head to the right");
        d.held.insert(Key::Trigger);
        assert_eq!(d.frame_input(1.1, 1.0).hands[RIGHT].buttons.trigger, 1.0);
        assert!(!d.frame_input(1.1, 1.0).hands[LEFT].tracked);
    }
}
