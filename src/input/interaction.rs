//! Interaction rules: what a surgeon's hands do to the [`Scene`].
//!
//! The layer between [`FrameInput`] and [`Scene`] (DESIGN.md, "One frame, as data"). It is plain
//! data in, plain data out, driven only by the frames' own timestamps, so a recorded or scripted
//! pose stream replays to the same scenes bit for bit.
//!
//! The rules, meant to be learnt in a minute:
//!
//! | control                 | effect                                                        |
//! |-------------------------|---------------------------------------------------------------|
//! | right hand              | holds tool 0, [`InteractionSettings::tool_offset`] ahead      |
//! | trigger                 | toggles carving of that hand's tool (on/off)                  |
//! | thumbstick up/down      | grows/shrinks that hand's tool                                |
//! | primary (A/X)           | cycles that hand's tool shape                                 |
//! | secondary (B/Y)         | toggles that hand's tool between carve and probe              |
//! | left grip               | grabs the volume: it moves and turns with the hand            |
//! | both grips              | scale (hand distance), move (midpoint), turn (hand axis)      |
//! | menu (either hand)      | next transfer-function preset                                 |
//! | thumbstick left/right   | turns the environment light about the up axis (SH lighting)   |
//!
//! The left hand gets a tool of its own (tool 1) the first time its trigger is pulled, so a
//! two-handed carve (the `two-tools` script) works while a surgeon who only grabs with the left
//! never sees a second tool. Tools from index 2 on (placed by something else) are left alone.
//!
//! A hand that loses tracking freezes: its tool stays where it was, and any grab that needs it
//! is released; the volume only moves again after a fresh grip press.

use super::{FrameInput, HandInput, LEFT, RIGHT};
use crate::render::view::{Placement, Pose};
use crate::scene::{Scene, Shape, Tool, ToolMode, BUILTIN_SHAPES};
use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};
use std::f32::consts::TAU;

/// Index in [`Scene::tools`] of the tool the right hand holds (created if missing).
pub const RIGHT_TOOL: usize = 0;
/// Index in [`Scene::tools`] of the tool the left hand holds, once it has one.
pub const LEFT_TOOL: usize = 1;

/// An analogue button (trigger, grip) counts as pressed once it rises past this value...
pub const PRESS_THRESHOLD: f32 = 0.5;
/// ...and as released only once it falls below this one, so a finger resting near the
/// threshold does not chatter between on and off.
pub const RELEASE_THRESHOLD: f32 = 0.3;

/// Longest frame time (s) any rule integrates over: after a stall (a breakpoint, a dropped
/// session) a held thumbstick must not resize the tool by seconds' worth at once.
pub const MAX_DT: f32 = 0.1;

/// A cutoff (Hz) that suits hand tremor when smoothing is on: physiological tremor sits at
/// 8-12 Hz, a surgeon's deliberate motion well under 1 Hz when still and fast when moving (the
/// One Euro filter raises its cutoff with speed).
pub const SUGGESTED_SMOOTHING_HZ: f32 = 1.0;

/// Cutoff (Hz) of the low-pass on the speed estimate that drives the One Euro cutoff (Casiez
/// et al. use 1 Hz and so do we: it keeps tremor from raising the cutoff).
const DERIVATIVE_CUTOFF_HZ: f32 = 1.0;

/// Two-hand grabs start from at least this hand distance (m), so hands that start together
/// cannot multiply the scale by a huge ratio.
const MIN_TWO_HAND_DISTANCE: f32 = 0.01;

/// Tunables of the interaction. `Default` gives the behaviour described in the module docs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct InteractionSettings {
    /// Where the tool sits in the hand's grip frame (m). Default 8 cm ahead along the grip's
    /// -Z, so the tool is in front of the controller rather than inside the fist, and the
    /// surgeon sees what it cuts.
    pub tool_offset: Vec3,
    /// Hand-tremor smoothing: `None` (default) passes the tracked poses through untouched;
    /// `Some(cutoff_hz)` runs a One Euro filter on each hand's grip pose with that minimum
    /// cutoff ([`SUGGESTED_SMOOTHING_HZ`] is a good start). Off by default because any filter
    /// adds some lag, and a surgeon should opt into it. A cutoff that is not a positive number
    /// means off.
    pub smoothing: Option<f32>,
    /// One Euro speed coefficient for positions (Hz per m/s): how much the cutoff rises with
    /// hand speed, i.e. how quickly a deliberate move is followed.
    pub smoothing_beta: f32,
    /// One Euro speed coefficient for orientations (Hz per rad/s).
    pub smoothing_beta_rot: f32,
    /// Size of a newly created tool (m; a sphere's radius).
    pub tool_size: f32,
    /// Smallest tool size the thumbstick reaches (m).
    pub min_size: f32,
    /// Largest tool size the thumbstick reaches (m).
    pub max_size: f32,
    /// Resize speed: at full stick the size is multiplied by `exp(resize_rate)` per second
    /// (exponential, so small and large tools change at the same relative pace).
    pub resize_rate: f32,
    /// Thumbstick values with |y| below this are ignored (sticks rarely rest at exactly 0);
    /// beyond it the deflection is rescaled so that full stick is still full rate.
    pub stick_dead_zone: f32,
    /// Light turn speed (rad/s) at full sideways stick, either hand.
    pub light_turn_rate: f32,
    /// Number of transfer-function presets the menu button cycles through (0: it does nothing).
    pub tf_presets: usize,
    /// Number of loaded meshes ([`Shape::Mesh`]) that the primary button cycles through after
    /// the built-in shapes.
    pub mesh_count: usize,
    /// Smallest volume scale two hands can reach (1 = true size).
    pub min_scale: f32,
    /// Largest volume scale two hands can reach.
    pub max_scale: f32,
}

impl Default for InteractionSettings {
    fn default() -> Self {
        InteractionSettings {
            tool_offset: Vec3::new(0.0, 0.0, -0.08),
            smoothing: None,
            smoothing_beta: 20.0,
            smoothing_beta_rot: 2.0,
            tool_size: 0.025,
            min_size: 0.005,
            max_size: 0.15,
            resize_rate: 1.0,
            stick_dead_zone: 0.15,
            light_turn_rate: 1.5,
            tf_presets: crate::volume::transfer::PRESETS.len(),
            mesh_count: 0,
            min_scale: 0.1,
            max_scale: 10.0,
        }
    }
}

/// What the hands are doing to the volume.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GrabMode {
    /// The volume stays where it is.
    None,
    /// The left hand holds it: it follows the hand rigidly.
    OneHand,
    /// Both hands hold it: it scales with their distance, follows their midpoint and turns
    /// with the line between them.
    TwoHands,
}

/// The state captured when a grab (or a change between one and two hands) begins; the volume
/// is always computed from it and the current hands, never accumulated frame by frame, so it
/// cannot drift.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Grab {
    None,
    OneHand {
        grip0: Pose,
        volume0: Placement,
    },
    TwoHands {
        left0: Vec3,
        right0: Vec3,
        volume0: Placement,
    },
}

impl Grab {
    fn mode(&self) -> GrabMode {
        match self {
            Grab::None => GrabMode::None,
            Grab::OneHand { .. } => GrabMode::OneHand,
            Grab::TwoHands { .. } => GrabMode::TwoHands,
        }
    }
}

/// Edge detection with hysteresis on an analogue value. A NaN value changes nothing.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Latch {
    pressed: bool,
}

impl Latch {
    /// Updates the latch; true on the frame it becomes pressed.
    fn update(&mut self, value: f32) -> bool {
        if !self.pressed && value > PRESS_THRESHOLD {
            self.pressed = true;
            return true;
        }
        if self.pressed && value < RELEASE_THRESHOLD {
            self.pressed = false;
        }
        false
    }
}

/// Rising-edge detection on a digital button.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Edge {
    down: bool,
}

impl Edge {
    fn update(&mut self, down: bool) -> bool {
        let rose = down && !self.down;
        self.down = down;
        rose
    }
}

/// The buttons' memory for one hand.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct HandButtons {
    trigger: Latch,
    grip: Latch,
    primary: Edge,
    secondary: Edge,
    menu: Edge,
}

/// What this frame's buttons did on one hand (rising edges).
#[derive(Clone, Copy, Debug, Default)]
struct Pressed {
    trigger: bool,
    grip: bool,
    primary: bool,
    secondary: bool,
    menu: bool,
}

impl HandButtons {
    fn update(&mut self, hand: &HandInput) -> Pressed {
        let b = &hand.buttons;
        Pressed {
            trigger: self.trigger.update(b.trigger),
            grip: self.grip.update(b.grip),
            primary: self.primary.update(b.primary),
            secondary: self.secondary.update(b.secondary),
            menu: self.menu.update(b.menu),
        }
    }
}

/// One Euro filter parameters (Casiez, Roussel, Vogel 2012).
#[derive(Clone, Copy, Debug)]
struct OneEuroParams {
    min_cutoff: f32,
    beta: f32,
    beta_rot: f32,
}

/// The One Euro filter's state for one hand's pose: filtered position and orientation, and
/// the filtered speeds that set the cutoff.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PoseFilter {
    pose: Pose,
    velocity: Vec3,
    angular_speed: f32,
}

/// Smoothing factor of a first-order low-pass with the given cutoff over a step `dt` (s).
fn alpha(cutoff_hz: f32, dt: f32) -> f32 {
    let tau = 1.0 / (TAU * cutoff_hz);
    1.0 / (1.0 + tau / dt)
}

/// The rotation angle (rad, 0..=pi) of a unit quaternion, accurate for tiny angles (unlike
/// `acos` of the dot product, which loses tremor-sized rotations to f32 rounding).
fn rotation_angle(q: Quat) -> f32 {
    2.0 * q.xyz().length().atan2(q.w.abs())
}

impl PoseFilter {
    fn new(pose: Pose) -> Self {
        PoseFilter {
            pose,
            velocity: Vec3::ZERO,
            angular_speed: 0.0,
        }
    }

    /// Feeds one raw pose `dt` seconds after the last; returns the filtered pose. With
    /// `dt == 0` (a repeated timestamp) the estimate stays put: the filter is time-based, so a
    /// frame that takes no time cannot move it.
    fn update(&mut self, raw: Pose, dt: f32, p: &OneEuroParams) -> Pose {
        if dt <= 0.0 {
            return self.pose;
        }
        let a_d = alpha(DERIVATIVE_CUTOFF_HZ, dt);

        // Position: the speed estimate is low-passed, then sets the cutoff of the value.
        let raw_velocity = (raw.position - self.pose.position) / dt;
        self.velocity = self.velocity.lerp(raw_velocity, a_d);
        let cutoff = p.min_cutoff + p.beta.max(0.0) * self.velocity.length();
        let position = self.pose.position.lerp(raw.position, alpha(cutoff, dt));

        // Orientation: the same with the angular speed, and slerp in place of lerp.
        let delta = self.pose.orientation.conjugate() * raw.orientation;
        let raw_speed = rotation_angle(delta) / dt;
        self.angular_speed += a_d * (raw_speed - self.angular_speed);
        let cutoff_rot = p.min_cutoff + p.beta_rot.max(0.0) * self.angular_speed;
        let orientation = self
            .pose
            .orientation
            .slerp(raw.orientation, alpha(cutoff_rot, dt))
            .normalize();

        let pose = Pose {
            position,
            orientation,
        };
        // Never let a numerical accident poison the state.
        if pose_is_valid(&pose) && self.velocity.is_finite() && self.angular_speed.is_finite() {
            self.pose = pose;
        } else {
            *self = PoseFilter::new(raw);
        }
        self.pose
    }
}

fn pose_is_valid(p: &Pose) -> bool {
    p.position.is_finite() && p.orientation.is_finite()
}

/// The hand's grip pose if it is tracked and usable: finite, with a quaternion that can be
/// normalised. Anything else is treated as untracked for this frame.
fn usable_grip(hand: &HandInput) -> Option<Pose> {
    if !hand.tracked || !hand.grip.position.is_finite() || !hand.grip.orientation.is_finite() {
        return None;
    }
    // Finite, so the length is too.
    let len = hand.grip.orientation.length();
    if len <= 1e-3 {
        return None;
    }
    Some(Pose {
        position: hand.grip.position,
        orientation: hand.grip.orientation / len,
    })
}

/// Clamp that cannot panic (f32::clamp does when min > max or either is NaN): with nonsense
/// bounds it still returns some number in or near them.
fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    x.max(lo).min(hi)
}

/// Per-hand state: tracking, the (smoothed) grip pose, buttons and whether it holds the volume.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Hand {
    tracked: bool,
    /// The last usable (smoothed) grip pose; `None` until the hand was first tracked.
    pose: Option<Pose>,
    filter: Option<PoseFilter>,
    buttons: HandButtons,
    /// The grip was pressed while tracked and has been held and tracked ever since.
    holding: bool,
}

/// The interaction state machine: feed it every frame's input with [`Interaction::update`].
#[derive(Clone, Debug, PartialEq)]
pub struct Interaction {
    settings: InteractionSettings,
    hands: [Hand; 2],
    grab: Grab,
    last_time: Option<f64>,
    dt: f32,
}

impl Interaction {
    pub fn new(settings: InteractionSettings) -> Self {
        Interaction {
            settings,
            hands: [Hand::default(); 2],
            grab: Grab::None,
            last_time: None,
            dt: 0.0,
        }
    }

    pub fn settings(&self) -> &InteractionSettings {
        &self.settings
    }

    /// Whether the hand (`LEFT` or `RIGHT`) had a usable pose in the last frame. An index other
    /// than 0 or 1 is never tracked.
    pub fn is_tracked(&self, hand: usize) -> bool {
        self.hands.get(hand).is_some_and(|h| h.tracked)
    }

    /// The hand's grip pose as the rules use it (smoothed when smoothing is on): the current
    /// one while tracked, the last known one while not, `None` if never tracked. For drawing
    /// controllers, tooltips, rays.
    pub fn hand_pose(&self, hand: usize) -> Option<Pose> {
        self.hands.get(hand).and_then(|h| h.pose)
    }

    /// Whether the hand's grip holds: pressed while the hand was tracked, and held and tracked
    /// ever since. The left grip holding grabs the volume; the right grip only counts together
    /// with the left one (two-hand scaling).
    pub fn is_holding(&self, hand: usize) -> bool {
        self.hands.get(hand).is_some_and(|h| h.holding)
    }

    /// What the hands are doing to the volume.
    pub fn grab_mode(&self) -> GrabMode {
        self.grab.mode()
    }

    /// The index in [`Scene::tools`] of the tool the hand holds, if it has one in `scene`.
    pub fn tool_of(&self, hand: usize, scene: &Scene) -> Option<usize> {
        let index = match hand {
            RIGHT => RIGHT_TOOL,
            LEFT => LEFT_TOOL,
            _ => return None,
        };
        (index < scene.tools.len()).then_some(index)
    }

    /// The frame time (s) the last update integrated over (0 on the first frame; at most
    /// [`MAX_DT`]).
    pub fn last_dt(&self) -> f32 {
        self.dt
    }

    /// The tool a hand creates: a sphere of the default size, carving, off.
    fn new_tool(&self, pose: Pose) -> Tool {
        Tool {
            shape: Shape::Sphere,
            pose,
            size: self.settings.tool_size,
            mode: ToolMode::Carve,
            active: false,
        }
    }

    /// The tool's pose for a grip pose: the grip frame moved by the offset in its own axes.
    fn tool_pose(&self, grip: Pose) -> Pose {
        Pose {
            position: grip.position + grip.orientation * self.settings.tool_offset,
            orientation: grip.orientation,
        }
    }

    fn smoothing(&self) -> Option<OneEuroParams> {
        let s = &self.settings;
        match s.smoothing {
            Some(hz) if hz.is_finite() && hz > 0.0 => Some(OneEuroParams {
                min_cutoff: hz,
                beta: if s.smoothing_beta.is_finite() {
                    s.smoothing_beta
                } else {
                    0.0
                },
                beta_rot: if s.smoothing_beta_rot.is_finite() {
                    s.smoothing_beta_rot
                } else {
                    0.0
                },
            }),
            _ => None,
        }
    }

    /// Applies one frame's input to the scene.
    ///
    /// Rules where the issue left a choice:
    /// - The tool follows its hand whenever the hand is tracked, grip or no grip: a tool that
    ///   needs a squeezed grip to stay in the hand tires the hand within minutes, and it would
    ///   overload the grip, which (with the left one) scales the volume.
    /// - The trigger toggles carving (press once: on, press again: off) rather than
    ///   carving while held, so a long careful cut needs no sustained finger pressure. Edges
    ///   use hysteresis (on past [`PRESS_THRESHOLD`], re-armed below [`RELEASE_THRESHOLD`]) and
    ///   start from "released", so a trigger already held on the first frame turns carving on.
    /// - Buttons act whether or not the hand is tracked (they do not need a pose); only grabs
    ///   need tracking.
    /// - A hand whose pose is not usable (untracked, or a non-finite or zero quaternion) is
    ///   untracked for this frame: its tool freezes, its grabs end, and it must press the grip
    ///   again to grab once tracked.
    pub fn update(&mut self, input: &FrameInput, scene: &mut Scene) {
        // Frame time from the timestamps: 0 on the first frame, after a non-finite time or when
        // time runs backwards (a replay restarting); at most MAX_DT.
        self.dt = match (self.last_time, input.time.is_finite()) {
            (Some(last), true) => ((input.time - last) as f32).clamp(0.0, MAX_DT),
            _ => 0.0,
        };
        if input.time.is_finite() {
            self.last_time = Some(input.time);
        }
        let dt = self.dt;

        // Poses (smoothed) and buttons, per hand.
        let smoothing = self.smoothing();
        let mut pressed = [Pressed::default(); 2];
        for (side, hand) in input.hands.iter().enumerate() {
            let state = &mut self.hands[side];
            pressed[side] = state.buttons.update(hand);
            match usable_grip(hand) {
                Some(raw) => {
                    let pose = match (&smoothing, &mut state.filter) {
                        (Some(p), Some(f)) => f.update(raw, dt, p),
                        (Some(_), filter @ None) => {
                            *filter = Some(PoseFilter::new(raw));
                            raw
                        }
                        (None, _) => raw,
                    };
                    state.tracked = true;
                    state.pose = Some(pose);
                    if pressed[side].grip {
                        state.holding = true;
                    }
                }
                None => {
                    // Re-acquisition starts the filter afresh from the new pose rather than
                    // gliding from where the hand was lost.
                    state.tracked = false;
                    state.filter = None;
                    state.holding = false;
                }
            }
            if !state.buttons.grip.pressed {
                state.holding = false;
            }
        }

        self.update_tools(input, &pressed, dt, scene);
        self.update_grab(scene);

        // Sideways stick turns the environment light (both hands add up).
        for hand in &input.hands {
            let x = self.deflection(hand.buttons.thumbstick.x);
            scene.light_yaw = (scene.light_yaw + self.settings.light_turn_rate * x * dt) % TAU;
        }

        // Menu: either hand (both on the same frame count once).
        if (pressed[LEFT].menu || pressed[RIGHT].menu) && self.settings.tf_presets > 0 {
            scene.tf_index =
                (scene.tf_index % self.settings.tf_presets + 1) % self.settings.tf_presets;
        }
    }

    fn update_tools(
        &mut self,
        input: &FrameInput,
        pressed: &[Pressed; 2],
        dt: f32,
        scene: &mut Scene,
    ) {
        if scene.tools.is_empty() {
            let pose = self.hands[RIGHT]
                .pose
                .map_or(Pose::IDENTITY, |g| self.tool_pose(g));
            scene.tools.push(self.new_tool(pose));
        }
        if pressed[LEFT].trigger && scene.tools.len() <= LEFT_TOOL {
            let pose = self.hands[LEFT]
                .pose
                .map_or(Pose::IDENTITY, |g| self.tool_pose(g));
            scene.tools.push(self.new_tool(pose));
        }

        for (side, index) in [(RIGHT, RIGHT_TOOL), (LEFT, LEFT_TOOL)] {
            let Some(mut tool) = scene.tools.get(index).copied() else {
                continue;
            };
            let p = &pressed[side];
            if p.trigger {
                tool.active = !tool.active;
            }
            if p.primary {
                tool.shape = self.next_shape(tool.shape);
            }
            if p.secondary {
                tool.mode = match tool.mode {
                    ToolMode::Carve => ToolMode::Probe,
                    ToolMode::Probe => ToolMode::Carve,
                };
            }
            tool.size = self.resized(tool.size, input.hands[side].buttons.thumbstick.y, dt);
            // Follow the hand while it is tracked; freeze otherwise.
            let hand = &self.hands[side];
            if hand.tracked {
                if let Some(grip) = hand.pose {
                    tool.pose = self.tool_pose(grip);
                }
            }
            scene.tools[index] = tool;
        }
    }

    /// The shape after `shape` in the cycle: the built-ins, then the loaded meshes, then round.
    fn next_shape(&self, shape: Shape) -> Shape {
        let meshes = self.settings.mesh_count;
        match shape {
            Shape::Mesh(i) if i + 1 < meshes => Shape::Mesh(i + 1),
            Shape::Mesh(_) => BUILTIN_SHAPES[0],
            builtin => {
                let i = BUILTIN_SHAPES
                    .iter()
                    .position(|s| *s == builtin)
                    .unwrap_or(0);
                if i + 1 < BUILTIN_SHAPES.len() {
                    BUILTIN_SHAPES[i + 1]
                } else if meshes > 0 {
                    Shape::Mesh(0)
                } else {
                    BUILTIN_SHAPES[0]
                }
            }
        }
    }

    /// The size after a frame of thumbstick `y`: exponential in time, dead zone around the
    /// centre, clamped to the settings' range. A size that is not a positive number (a scene
    /// from elsewhere) is replaced by the default size.
    fn resized(&self, size: f32, y: f32, dt: f32) -> f32 {
        let s = &self.settings;
        let size = if size.is_finite() && size > 0.0 {
            size
        } else {
            s.tool_size
        };
        let deflection = self.deflection(y);
        if deflection == 0.0 || dt <= 0.0 {
            return size;
        }
        let resized = clamp(
            size * (s.resize_rate * deflection * dt).exp(),
            s.min_size,
            s.max_size,
        );
        if resized.is_finite() && resized > 0.0 {
            resized
        } else {
            size
        }
    }

    /// A stick axis after the dead zone, rescaled so that full stick is still 1 (0 for
    /// non-numbers).
    fn deflection(&self, v: f32) -> f32 {
        let dead = clamp(self.settings.stick_dead_zone, 0.0, 0.99);
        let v = if v.is_finite() {
            clamp(v, -1.0, 1.0)
        } else {
            0.0
        };
        if v.abs() <= dead {
            return 0.0;
        }
        v.signum() * (v.abs() - dead) / (1.0 - dead)
    }

    /// The grab state machine. Whenever who holds the volume changes (a grab starts, the
    /// second hand joins or leaves), the current hands and volume are captured afresh, so the
    /// volume never jumps at a change; it then follows the hands relative to that capture.
    fn update_grab(&mut self, scene: &mut Scene) {
        let left = self.hands[LEFT]
            .holding
            .then_some(self.hands[LEFT].pose)
            .flatten();
        let right = self.hands[RIGHT]
            .holding
            .then_some(self.hands[RIGHT].pose)
            .flatten();
        // The right grip alone does not grab: the right hand is the tool hand.
        let wanted = match (left, right) {
            (Some(_), Some(_)) => GrabMode::TwoHands,
            (Some(_), None) => GrabMode::OneHand,
            _ => GrabMode::None,
        };
        if wanted != self.grab.mode() {
            let volume0 = scene.volume;
            self.grab = match (left, right) {
                (Some(l), Some(r)) => Grab::TwoHands {
                    left0: l.position,
                    right0: r.position,
                    volume0,
                },
                (Some(l), None) => Grab::OneHand { grip0: l, volume0 },
                _ => Grab::None,
            };
            // The capture frame leaves the volume exactly where it is (recomputing it from
            // the capture would be the same up to rounding).
            return;
        }

        let moved = match (self.grab, left, right) {
            (Grab::OneHand { grip0, volume0 }, Some(l), _) => {
                // new = grip_now * inverse(grip0) * volume0, the centre turning about the hand.
                // Written as the capture plus a displacement, so a still hand leaves the centre
                // where it was to the last bit rather than re-deriving it through the hand.
                let turn = (l.orientation * grip0.orientation.conjugate()).normalize();
                let arm = volume0.center - grip0.position;
                Placement {
                    center: volume0.center + (l.position - grip0.position) + (turn * arm - arm),
                    rotation: (turn * volume0.rotation).normalize(),
                    scale: volume0.scale,
                }
            }
            (
                Grab::TwoHands {
                    left0,
                    right0,
                    volume0,
                },
                Some(l),
                Some(r),
            ) => self.two_hand_placement(left0, right0, volume0, l.position, r.position),
            _ => return,
        };
        // A rule that met nonsense settings (a NaN or negative scale bound) leaves the volume be.
        if moved.center.is_finite()
            && moved.rotation.is_finite()
            && moved.scale > 0.0
            && moved.scale.is_finite()
        {
            scene.volume = moved;
        }
    }

    /// Two hands: the scale follows the ratio of the hands' distance to the one at the grab
    /// (clamped to the settings' range), the volume turns with the line between the hands
    /// (shortest arc), and both scale and turn pivot about the hands' midpoint, which the
    /// volume follows.
    fn two_hand_placement(
        &self,
        left0: Vec3,
        right0: Vec3,
        volume0: Placement,
        left: Vec3,
        right: Vec3,
    ) -> Placement {
        let (mid0, mid) = ((left0 + right0) * 0.5, (left + right) * 0.5);
        let (axis0, axis) = (right0 - left0, right - left);
        let d0 = axis0.length().max(MIN_TWO_HAND_DISTANCE);
        let scale = clamp(
            volume0.scale * axis.length() / d0,
            self.settings.min_scale,
            self.settings.max_scale,
        );
        let ratio = if volume0.scale > 0.0 {
            scale / volume0.scale
        } else {
            1.0
        };
        let turn =
            if axis0.length() >= MIN_TWO_HAND_DISTANCE && axis.length() >= MIN_TWO_HAND_DISTANCE {
                Quat::from_rotation_arc(axis0.normalize(), axis.normalize())
            } else {
                Quat::IDENTITY
            };
        Placement {
            center: mid + turn * ((volume0.center - mid0) * ratio),
            rotation: (turn * volume0.rotation).normalize(),
            scale,
        }
    }
}

impl Default for Interaction {
    fn default() -> Self {
        Interaction::new(InteractionSettings::default())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::input::script::{generate, ScriptKind, ScriptParams};
    use crate::input::{pose, symmetric_fov, Buttons};
    use std::f32::consts::FRAC_PI_2;

    const FPS: f64 = 90.0;

    /// A frame at `time` with both hands as given.
    fn frame(time: f64, left: HandInput, right: HandInput) -> FrameInput {
        let head = pose(Vec3::new(0.0, 1.6, 0.0), Quat::IDENTITY);
        FrameInput {
            time,
            views: FrameInput::head_views(head, 0.064, symmetric_fov(0.6)),
            hands: [left, right],
        }
    }

    /// A tracked hand at `position` / `orientation`, nothing pressed.
    fn hand(position: Vec3, orientation: Quat) -> HandInput {
        let grip = pose(position, orientation);
        HandInput {
            tracked: true,
            grip,
            aim: grip,
            buttons: Buttons::default(),
        }
    }

    fn at(position: Vec3) -> HandInput {
        hand(position, Quat::IDENTITY)
    }

    fn gripping(mut h: HandInput) -> HandInput {
        h.buttons.grip = 1.0;
        h
    }

    fn triggering(mut h: HandInput, value: f32) -> HandInput {
        h.buttons.trigger = value;
        h
    }

    fn untracked(mut h: HandInput) -> HandInput {
        h.tracked = false;
        h
    }

    fn idle_left() -> HandInput {
        at(Vec3::new(-0.3, 1.0, -0.2))
    }

    fn idle_right() -> HandInput {
        at(Vec3::new(0.3, 1.0, -0.2))
    }

    /// Runs frames at FPS from frame number `start`; returns the next frame number.
    fn run(
        ix: &mut Interaction,
        scene: &mut Scene,
        start: usize,
        hands: impl IntoIterator<Item = (HandInput, HandInput)>,
    ) -> usize {
        let mut i = start;
        for (l, r) in hands {
            ix.update(&frame(i as f64 / FPS, l, r), scene);
            i += 1;
        }
        i
    }

    fn close(a: Vec3, b: Vec3, tol: f32) -> bool {
        a.distance(b) <= tol
    }

    fn same_rotation(a: Quat, b: Quat, tol: f32) -> bool {
        a.dot(b).abs() >= 1.0 - tol
    }

    #[test]
    fn the_right_hand_gets_a_sphere_that_follows_it_ahead_of_the_grip() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let q = Quat::from_rotation_y(FRAC_PI_2); // grip -Z now points to world -X
        let g = Vec3::new(0.2, 1.2, -0.4);
        run(&mut ix, &mut scene, 0, [(idle_left(), hand(g, q))]);
        assert_eq!(scene.tools.len(), 1, "only the right hand's tool");
        let t = scene.tools[RIGHT_TOOL];
        assert_eq!(t.shape, Shape::Sphere);
        assert_eq!(t.mode, ToolMode::Carve);
        assert!(!t.active);
        assert_eq!(t.size, 0.025);
        assert!(close(t.pose.position, g + Vec3::new(-0.08, 0.0, 0.0), 1e-6));
        assert!(same_rotation(t.pose.orientation, q, 1e-6));
        // No grip needed: it follows the hand everywhere.
        let g2 = g + Vec3::new(0.05, -0.1, 0.02);
        run(&mut ix, &mut scene, 1, [(idle_left(), hand(g2, q))]);
        let p = scene.tools[RIGHT_TOOL].pose.position;
        assert!(close(p, g2 + Vec3::new(-0.08, 0.0, 0.0), 1e-6));
        assert_eq!(ix.tool_of(RIGHT, &scene), Some(RIGHT_TOOL));
        assert_eq!(ix.tool_of(LEFT, &scene), None);
    }

    #[test]
    fn grab_moves_and_turns_the_volume_with_the_left_hand() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let v0 = scene.volume;
        let g0 = Vec3::new(-0.15, 1.4, -0.5);
        let mut i = run(&mut ix, &mut scene, 0, [(at(g0), idle_right())]);
        i = run(&mut ix, &mut scene, i, [(gripping(at(g0)), idle_right())]);
        assert_eq!(ix.grab_mode(), GrabMode::OneHand);
        assert_eq!(scene.volume, v0, "grabbing alone does not move it");

        // Translate 10 cm right and 5 cm up.
        let shift = Vec3::new(0.1, 0.05, 0.0);
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(g0 + shift)), idle_right())],
        );
        assert!(close(scene.volume.center, v0.center + shift, 1e-6));
        assert!(same_rotation(scene.volume.rotation, v0.rotation, 1e-6));

        // Then turn the hand 90 degrees about +Y: the centre swings about the hand.
        let turn = Quat::from_rotation_y(FRAC_PI_2);
        let g1 = g0 + shift;
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(hand(g1, turn)), idle_right())],
        );
        let expect = g1 + turn * (v0.center - g0);
        assert!(
            close(scene.volume.center, expect, 1e-5),
            "{} vs {expect}",
            scene.volume.center
        );
        assert!(same_rotation(
            scene.volume.rotation,
            turn * v0.rotation,
            1e-6
        ));
        assert_eq!(scene.volume.scale, v0.scale);

        // Released: the hand moves on, the volume stays.
        let placed = scene.volume;
        i = run(&mut ix, &mut scene, i, [(hand(g1, turn), idle_right())]);
        run(&mut ix, &mut scene, i, [(at(g0), idle_right())]);
        assert_eq!(ix.grab_mode(), GrabMode::None);
        assert_eq!(scene.volume, placed);
    }

    #[test]
    fn grip_hysteresis_keeps_a_loosening_grab() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let g = Vec3::new(0.0, 1.4, -0.4);
        let with_grip = |v: f32, p: Vec3| {
            let mut h = at(p);
            h.buttons.grip = v;
            (h, idle_right())
        };
        run(
            &mut ix,
            &mut scene,
            0,
            [
                with_grip(0.6, g),
                with_grip(0.35, g),
                with_grip(0.35, g + Vec3::X * 0.1),
            ],
        );
        assert_eq!(ix.grab_mode(), GrabMode::OneHand, "0.35 is still held");
        let c = Placement::default().center + Vec3::X * 0.1;
        assert!(close(scene.volume.center, c, 1e-6));
        run(&mut ix, &mut scene, 3, [with_grip(0.2, g)]);
        assert_eq!(ix.grab_mode(), GrabMode::None);
    }

    #[test]
    fn two_hands_moving_apart_twice_as_far_scale_the_volume_twice() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let c = scene.volume.center;
        let (l0, r0) = (c - Vec3::X * 0.1, c + Vec3::X * 0.1);
        let mut i = run(
            &mut ix,
            &mut scene,
            0,
            [(gripping(at(l0)), gripping(at(r0)))],
        );
        assert_eq!(ix.grab_mode(), GrabMode::TwoHands);
        for k in 1..=30 {
            let s = 0.1 * (1.0 + k as f32 / 30.0);
            i = run(
                &mut ix,
                &mut scene,
                i,
                [(gripping(at(c - Vec3::X * s)), gripping(at(c + Vec3::X * s)))],
            );
        }
        assert!(
            (scene.volume.scale - 2.0).abs() < 1e-5,
            "{}",
            scene.volume.scale
        );
        assert!(
            close(scene.volume.center, c, 1e-6),
            "the midpoint did not move"
        );
        assert!(same_rotation(scene.volume.rotation, Quat::IDENTITY, 1e-6));

        // Both hands up 10 cm: the volume follows the midpoint, keeping its scale.
        let up = Vec3::Y * 0.1;
        let (l, r) = (c - Vec3::X * 0.2 + up, c + Vec3::X * 0.2 + up);
        i = run(&mut ix, &mut scene, i, [(gripping(at(l)), gripping(at(r)))]);
        assert!(close(scene.volume.center, c + up, 1e-6));
        assert!((scene.volume.scale - 2.0).abs() < 1e-5);

        // Far apart: clamped at the maximum scale.
        let far = Vec3::X * 5.0;
        run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(c - far)), gripping(at(c + far)))],
        );
        assert_eq!(scene.volume.scale, 10.0);
    }

    #[test]
    fn two_hand_scale_pivots_about_the_midpoint_and_turns_with_the_hands() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let c = scene.volume.center;
        // Hands 20 cm apart, their midpoint 10 cm left of the volume centre.
        let m0 = c - Vec3::X * 0.1;
        let (l0, r0) = (m0 - Vec3::Z * 0.1, m0 + Vec3::Z * 0.1);
        let i = run(
            &mut ix,
            &mut scene,
            0,
            [(gripping(at(l0)), gripping(at(r0)))],
        );
        // Spread to 30 cm and turn the hand axis 90 degrees about +Y (+Z -> +X).
        let (l1, r1) = (m0 - Vec3::X * 0.15, m0 + Vec3::X * 0.15);
        run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(l1)), gripping(at(r1)))],
        );
        let turn = Quat::from_rotation_y(FRAC_PI_2);
        assert!((scene.volume.scale - 1.5).abs() < 1e-5);
        let expect = m0 + turn * (Vec3::X * 0.1 * 1.5);
        assert!(
            close(scene.volume.center, expect, 1e-5),
            "{}",
            scene.volume.center
        );
        assert!(same_rotation(scene.volume.rotation, turn, 1e-5));
    }

    #[test]
    fn joining_and_leaving_hands_never_make_the_volume_jump() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let c = scene.volume.center;
        let (l, r) = (c - Vec3::X * 0.1, c + Vec3::X * 0.1);
        let mut i = run(&mut ix, &mut scene, 0, [(gripping(at(l)), at(r))]);
        let before = scene.volume;
        i = run(&mut ix, &mut scene, i, [(gripping(at(l)), gripping(at(r)))]);
        assert_eq!(ix.grab_mode(), GrabMode::TwoHands);
        assert_eq!(scene.volume, before);
        // Spread, then let go with the right: one-handed from where it is.
        let r2 = r + Vec3::X * 0.2;
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(l)), gripping(at(r2)))],
        );
        let scaled = scene.volume;
        i = run(&mut ix, &mut scene, i, [(gripping(at(l)), at(r2))]);
        assert_eq!(ix.grab_mode(), GrabMode::OneHand);
        assert_eq!(scene.volume, scaled);
        run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(l + Vec3::Y * 0.1)), at(r2))],
        );
        assert!(close(
            scene.volume.center,
            scaled.center + Vec3::Y * 0.1,
            1e-6
        ));
        assert_eq!(scene.volume.scale, scaled.scale);
    }

    #[test]
    fn the_right_grip_alone_does_not_grab() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let v0 = scene.volume;
        let r = Vec3::new(0.2, 1.3, -0.5);
        run(
            &mut ix,
            &mut scene,
            0,
            [
                (idle_left(), gripping(at(r))),
                (idle_left(), gripping(at(r + Vec3::X * 0.1))),
            ],
        );
        assert_eq!(ix.grab_mode(), GrabMode::None);
        assert_eq!(scene.volume, v0);
    }

    #[test]
    fn lost_tracking_freezes_the_tool() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let a = Vec3::new(0.1, 1.3, -0.4);
        let mut i = run(
            &mut ix,
            &mut scene,
            0,
            [(idle_left(), triggering(at(a), 1.0))],
        );
        let held = scene.tools[RIGHT_TOOL];
        assert!(held.active);
        // Untracked, the runtime's stale pose wanders off: the tool does not.
        for k in 1..=20 {
            let stale = a + Vec3::new(0.5, -1.0, 0.3) * (k as f32 / 20.0);
            i = run(
                &mut ix,
                &mut scene,
                i,
                [(idle_left(), untracked(at(stale)))],
            );
            assert!(!ix.is_tracked(RIGHT));
            assert_eq!(scene.tools[RIGHT_TOOL].pose, held.pose);
        }
        assert!(
            scene.tools[RIGHT_TOOL].active,
            "freezing keeps carving as it was"
        );
        // Tracked again: it resumes from the new pose.
        let b = a + Vec3::Y * 0.05;
        run(&mut ix, &mut scene, i, [(idle_left(), at(b))]);
        assert!(ix.is_tracked(RIGHT));
        let p = scene.tools[RIGHT_TOOL].pose.position;
        assert!(close(p, b + Vec3::new(0.0, 0.0, -0.08), 1e-6));
    }

    #[test]
    fn lost_tracking_releases_the_grab_and_the_volume_does_not_jump_back() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let g = Vec3::new(-0.2, 1.4, -0.5);
        let mut i = run(
            &mut ix,
            &mut scene,
            0,
            [
                (gripping(at(g)), idle_right()),
                (gripping(at(g + Vec3::X * 0.05)), idle_right()),
            ],
        );
        let placed = scene.volume;
        // Lost mid-grab with the grip still squeezed; the stale pose jumps around.
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(untracked(gripping(at(g + Vec3::Y))), idle_right())],
        );
        assert_eq!(ix.grab_mode(), GrabMode::None);
        assert_eq!(scene.volume, placed);
        // Re-tracked elsewhere, grip still held: no jump, no grab.
        for k in 0..10 {
            let p = g + Vec3::new(0.3, 0.1, 0.0) + Vec3::Z * (0.01 * k as f32);
            i = run(&mut ix, &mut scene, i, [(gripping(at(p)), idle_right())]);
            assert_eq!(scene.volume, placed);
            assert!(!ix.is_holding(LEFT));
        }
        // Released and pressed again: grabs from where it is.
        let p = g + Vec3::new(0.3, 0.1, 0.0);
        i = run(&mut ix, &mut scene, i, [(at(p), idle_right())]);
        i = run(&mut ix, &mut scene, i, [(gripping(at(p)), idle_right())]);
        assert_eq!(scene.volume, placed);
        run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(p + Vec3::X * 0.1)), idle_right())],
        );
        assert!(close(
            scene.volume.center,
            placed.center + Vec3::X * 0.1,
            1e-6
        ));
    }

    #[test]
    fn losing_the_right_hand_in_a_two_hand_grab_leaves_a_one_hand_grab() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let c = scene.volume.center;
        let (l, r) = (c - Vec3::X * 0.1, c + Vec3::X * 0.1);
        let mut i = run(&mut ix, &mut scene, 0, [(gripping(at(l)), gripping(at(r)))]);
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(l)), gripping(at(r + Vec3::X * 0.2)))],
        );
        let scaled = scene.volume;
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(l)), untracked(gripping(at(r))))],
        );
        assert_eq!(ix.grab_mode(), GrabMode::OneHand);
        assert_eq!(scene.volume, scaled, "the stale right pose is not used");
        // The right hand back, grip still held: one hand until a new press.
        run(&mut ix, &mut scene, i, [(gripping(at(l)), gripping(at(r)))]);
        assert_eq!(ix.grab_mode(), GrabMode::OneHand);
        assert!(close(scene.volume.center, scaled.center, 1e-6));
        assert_eq!(scene.volume.scale, scaled.scale);
    }

    #[test]
    fn trigger_toggles_carving_with_hysteresis() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let r = Vec3::new(0.1, 1.3, -0.4);
        let values = [0.0, 0.6, 0.4, 0.6, 0.45, 0.2, 0.55, 0.9, 0.1, 0.29, 0.51];
        let expect = [
            false, true, true, true, true, true, false, false, false, false, true,
        ];
        for (i, (v, e)) in values.into_iter().zip(expect).enumerate() {
            run(
                &mut ix,
                &mut scene,
                i,
                [(idle_left(), triggering(at(r), v))],
            );
            assert_eq!(scene.tools[RIGHT_TOOL].active, e, "frame {i}, trigger {v}");
        }
    }

    #[test]
    fn a_trigger_held_from_the_first_frame_carves() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let r = Vec3::new(0.1, 1.3, -0.4);
        for i in 0..50 {
            run(
                &mut ix,
                &mut scene,
                i,
                [(idle_left(), triggering(at(r), 1.0))],
            );
            assert!(scene.tools[RIGHT_TOOL].active);
        }
    }

    #[test]
    fn the_left_trigger_gives_the_left_hand_a_tool_of_its_own() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let l = Vec3::new(-0.1, 1.3, -0.4);
        let r = Vec3::new(0.1, 1.3, -0.4);
        run(&mut ix, &mut scene, 0, [(at(l), at(r))]);
        assert_eq!(scene.tools.len(), 1);
        run(&mut ix, &mut scene, 1, [(triggering(at(l), 1.0), at(r))]);
        assert_eq!(scene.tools.len(), 2);
        assert_eq!(ix.tool_of(LEFT, &scene), Some(LEFT_TOOL));
        let t = scene.tools[LEFT_TOOL];
        assert!(t.active && !scene.tools[RIGHT_TOOL].active);
        assert!(close(t.pose.position, l + Vec3::new(0.0, 0.0, -0.08), 1e-6));
        let l2 = l - Vec3::X * 0.1;
        run(&mut ix, &mut scene, 2, [(triggering(at(l2), 1.0), at(r))]);
        let p = scene.tools[LEFT_TOOL].pose.position;
        assert!(close(p, l2 + Vec3::new(0.0, 0.0, -0.08), 1e-6));
    }

    #[test]
    fn the_stick_resizes_exponentially_within_bounds() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let r = Vec3::new(0.1, 1.3, -0.4);
        let stick = |y: f32| {
            let mut h = at(r);
            h.buttons.thumbstick.y = y;
            (idle_left(), h)
        };
        // Inside the dead zone: nothing.
        let mut i = run(&mut ix, &mut scene, 0, (0..90).map(|_| stick(0.14)));
        assert_eq!(scene.tools[RIGHT_TOOL].size, 0.025);
        // Full stick for 0.5 s (45 frames of 1/90 s): exp(0.5) times larger.
        i = run(&mut ix, &mut scene, i, (0..45).map(|_| stick(1.0)));
        let grown = scene.tools[RIGHT_TOOL].size;
        assert!((grown / 0.025 - 0.5f32.exp()).abs() < 1e-3, "{grown}");
        // Half-way past the dead zone: half the rate, downwards.
        let half = -(0.15 + 0.85 / 2.0);
        i = run(&mut ix, &mut scene, i, (0..90).map(|_| stick(half)));
        let shrunk = scene.tools[RIGHT_TOOL].size;
        assert!((shrunk / grown - (-0.5f32).exp()).abs() < 1e-3, "{shrunk}");
        // Held long: clamped at the bounds.
        i = run(&mut ix, &mut scene, i, (0..900).map(|_| stick(1.0)));
        assert_eq!(scene.tools[RIGHT_TOOL].size, 0.15);
        run(&mut ix, &mut scene, i, (0..900).map(|_| stick(-1.0)));
        assert_eq!(scene.tools[RIGHT_TOOL].size, 0.005);
    }

    #[test]
    fn the_stick_sideways_turns_the_light_and_leaves_the_tool() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let r = Vec3::new(0.1, 1.3, -0.4);
        let stick = |x: f32, left_x: f32| {
            let mut h = at(r);
            h.buttons.thumbstick.x = x;
            let mut l = idle_left();
            l.buttons.thumbstick.x = left_x;
            (l, h)
        };
        // Inside the dead zone: nothing.
        let mut i = run(&mut ix, &mut scene, 0, (0..90).map(|_| stick(0.14, -0.1)));
        assert_eq!(scene.light_yaw, 0.0);
        // Full stick right for 0.5 s (45 frames of 1/90 s): rate * 0.5 rad; the tool keeps its size.
        i = run(&mut ix, &mut scene, i, (0..45).map(|_| stick(1.0, 0.0)));
        let turned = scene.light_yaw;
        assert!((turned - 0.75).abs() < 1e-4, "{turned}");
        assert_eq!(scene.tools[RIGHT_TOOL].size, 0.025);
        // Both hands add up: left full left cancels right full right.
        i = run(&mut ix, &mut scene, i, (0..45).map(|_| stick(1.0, -1.0)));
        assert!((scene.light_yaw - turned).abs() < 1e-6);
        // Left alone, half-way past the dead zone: half the rate, the other way.
        run(
            &mut ix,
            &mut scene,
            i,
            (0..45).map(|_| stick(0.0, -(0.15 + 0.85 / 2.0))),
        );
        assert!(
            (scene.light_yaw - (turned - 0.375)).abs() < 1e-4,
            "{}",
            scene.light_yaw
        );
    }

    #[test]
    fn frame_time_is_clamped() {
        let mut ix = Interaction::default();
        let mut scene = Scene::default();
        let mut h = at(Vec3::new(0.1, 1.3, -0.4));
        h.buttons.thumbstick.y = 1.0;
        ix.update(&frame(0.0, idle_left(), h), &mut scene);
        assert_eq!(ix.last_dt(), 0.0);
        assert_eq!(scene.tools[RIGHT_TOOL].size, 0.025, "no time, no resize");
        ix.update(&frame(100.0, idle_left(), h), &mut scene);
        assert_eq!(ix.last_dt(), MAX_DT);
        let s = scene.tools[RIGHT_TOOL].size;
        assert!((s / 0.025 - MAX_DT.exp()).abs() < 1e-5);
        ix.update(&frame(50.0, idle_left(), h), &mut scene);
        assert_eq!(ix.last_dt(), 0.0, "time running backwards");
        assert_eq!(scene.tools[RIGHT_TOOL].size, s);
    }

    #[test]
    fn primary_cycles_shapes_and_secondary_toggles_the_mode() {
        let settings = InteractionSettings {
            mesh_count: 2,
            ..InteractionSettings::default()
        };
        let mut ix = Interaction::new(settings);
        let mut scene = Scene::default();
        let r = Vec3::new(0.1, 1.3, -0.4);
        let press = |primary: bool, secondary: bool| {
            let mut h = at(r);
            h.buttons.primary = primary;
            h.buttons.secondary = secondary;
            (idle_left(), h)
        };
        let mut i = run(&mut ix, &mut scene, 0, [press(false, false)]);
        let mut seen = vec![scene.tools[RIGHT_TOOL].shape];
        for _ in 0..6 {
            // Held for three frames: one step per press.
            i = run(&mut ix, &mut scene, i, [press(true, false); 3]);
            i = run(&mut ix, &mut scene, i, [press(false, false)]);
            seen.push(scene.tools[RIGHT_TOOL].shape);
        }
        use Shape::*;
        assert_eq!(
            seen,
            [Sphere, Box, Cylinder, Torus, Mesh(0), Mesh(1), Sphere]
        );

        assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Carve);
        i = run(&mut ix, &mut scene, i, [press(false, true); 2]);
        assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Probe);
        i = run(&mut ix, &mut scene, i, [press(false, false)]);
        run(&mut ix, &mut scene, i, [press(false, true)]);
        assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Carve);

        // Without meshes the built-ins wrap round; a stale mesh index goes back to the sphere.
        let ix = Interaction::default();
        assert_eq!(ix.next_shape(Torus), Sphere);
        assert_eq!(ix.next_shape(Mesh(7)), Sphere);
    }

    #[test]
    fn menu_cycles_the_transfer_function_presets() {
        let mut ix = Interaction::new(InteractionSettings {
            tf_presets: 3,
            ..InteractionSettings::default()
        });
        let mut scene = Scene::default();
        let menu = |l: bool, r: bool| {
            let (mut a, mut b) = (idle_left(), idle_right());
            a.buttons.menu = l;
            b.buttons.menu = r;
            (a, b)
        };
        let mut i = 0;
        let mut seen = vec![];
        for (l, r) in [(true, false), (false, true), (true, true), (false, false)] {
            i = run(&mut ix, &mut scene, i, [menu(l, r), menu(l, r)]);
            seen.push(scene.tf_index);
            i = run(&mut ix, &mut scene, i, [menu(false, false)]);
        }
        assert_eq!(seen, [1, 2, 0, 0], "either hand, once per press, modulo 3");

        // No presets: the menu does nothing (and does not divide by zero).
        let mut ix = Interaction::new(InteractionSettings {
            tf_presets: 0,
            ..InteractionSettings::default()
        });
        run(&mut ix, &mut scene, 0, [menu(true, true)]);
        assert_eq!(scene.tf_index, 0);
    }

    #[test]
    fn nonsense_input_is_ignored_without_panicking() {
        let mut ix = Interaction::new(InteractionSettings {
            smoothing: Some(SUGGESTED_SMOOTHING_HZ),
            ..InteractionSettings::default()
        });
        let mut scene = Scene::default();
        let r = Vec3::new(0.1, 1.3, -0.4);
        let mut i = run(&mut ix, &mut scene, 0, [(idle_left(), at(r))]);
        let good = scene.tools[RIGHT_TOOL];
        let v0 = scene.volume;
        let nan = Vec3::splat(f32::NAN);
        let bad_hands = [
            at(nan),
            hand(r, Quat::from_xyzw(f32::NAN, 0.0, 0.0, 1.0)),
            hand(r, Quat::from_xyzw(0.0, 0.0, 0.0, 0.0)),
            at(Vec3::new(f32::INFINITY, 0.0, 0.0)),
        ];
        for b in bad_hands {
            let mut b = gripping(b);
            b.buttons.trigger = f32::NAN;
            b.buttons.thumbstick.y = f32::NAN;
            i = run(&mut ix, &mut scene, i, [(gripping(b), b)]);
            assert!(!ix.is_tracked(RIGHT));
            assert_eq!(scene.tools[RIGHT_TOOL], good);
            assert_eq!(scene.volume, v0);
        }
        // A NaN time is a frame without time; a scene with a nonsense size is repaired.
        let mut h = at(r);
        h.buttons.thumbstick.y = 1.0;
        ix.update(&frame(f64::NAN, idle_left(), h), &mut scene);
        assert_eq!(ix.last_dt(), 0.0);
        scene.tools[RIGHT_TOOL].size = f32::NAN;
        ix.update(&frame(i as f64 / FPS, idle_left(), h), &mut scene);
        assert!(scene.tools[RIGHT_TOOL].size.is_finite());

        // Nonsense settings do not panic either.
        let mut ix = Interaction::new(InteractionSettings {
            min_size: 1.0,
            max_size: 0.0,
            min_scale: f32::NAN,
            max_scale: -1.0,
            stick_dead_zone: 7.0,
            resize_rate: f32::INFINITY,
            smoothing: Some(-3.0),
            ..InteractionSettings::default()
        });
        let mut scene = Scene::default();
        run(
            &mut ix,
            &mut scene,
            0,
            (0..5).map(|k| {
                let mut r = gripping(at(Vec3::X * 0.1 * k as f32));
                r.buttons.thumbstick.y = 1.0;
                (gripping(at(Vec3::ZERO)), r)
            }),
        );
    }

    /// RMS distance of points from their mean.
    fn rms_spread(points: &[Vec3]) -> f32 {
        let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
        let ms = points.iter().map(|p| p.distance_squared(mean)).sum::<f32>() / points.len() as f32;
        ms.sqrt()
    }

    fn tool_positions(settings: InteractionSettings, frames: &[FrameInput]) -> Vec<Vec3> {
        let mut ix = Interaction::new(settings);
        let mut scene = Scene::default();
        frames
            .iter()
            .map(|f| {
                ix.update(f, &mut scene);
                scene.tools[RIGHT_TOOL].pose.position
            })
            .collect()
    }

    fn smoothed() -> InteractionSettings {
        InteractionSettings {
            smoothing: Some(SUGGESTED_SMOOTHING_HZ),
            ..InteractionSettings::default()
        }
    }

    #[test]
    fn tremor_smoothing_reduces_jitter() {
        let p = ScriptParams {
            frames: 360,
            ..ScriptParams::default()
        };
        let frames = generate(ScriptKind::Tremor, &p);
        // Skip the first half second, where the filter settles on the hand.
        let raw = tool_positions(InteractionSettings::default(), &frames)[45..].to_vec();
        let smooth = tool_positions(smoothed(), &frames)[45..].to_vec();
        let (r, s) = (rms_spread(&raw), rms_spread(&smooth));
        assert!(r > 0.2e-3, "the script trembles: {r}");
        assert!(s <= 0.5 * r, "smoothed {s} vs raw {r}");
        // In fact a lot better than half: a 1 Hz cutoff against 8-12 Hz tremor.
        assert!(s <= 0.25 * r, "smoothed {s} vs raw {r}");
    }

    #[test]
    fn smoothing_follows_a_deliberate_move() {
        // Still for 0.5 s, a 10 cm move over 0.5 s (eased), still for 1 s.
        let start = Vec3::new(0.1, 1.3, -0.4);
        let at_time = |t: f64| {
            let s = ((t - 0.5) / 0.5).clamp(0.0, 1.0) as f32;
            let eased = s * s * (3.0 - 2.0 * s);
            start + Vec3::X * 0.1 * eased
        };
        let frames: Vec<FrameInput> = (0..180)
            .map(|i| {
                let t = i as f64 / FPS;
                frame(t, idle_left(), at(at_time(t)))
            })
            .collect();
        let offset = InteractionSettings::default().tool_offset;
        let raw = tool_positions(InteractionSettings::default(), &frames);
        let smooth = tool_positions(smoothed(), &frames);
        for (i, f) in frames.iter().enumerate() {
            let truth = at_time(f.time) + offset;
            assert!(close(raw[i], truth, 1e-6), "off means untouched");
            let lag = smooth[i].distance(truth);
            // About 6 mm at the move's peak speed (0.3 m/s) with the defaults.
            assert!(lag < 0.01, "lag {lag} m at t = {}", f.time);
            if f.time >= 1.0 + 0.2 {
                assert!(lag < 1e-3, "still {lag} m behind at t = {}", f.time);
            }
        }
        let end = smooth.last().unwrap().distance(at_time(2.0) + offset);
        assert!(end < 0.5e-3, "settles: {end}");
    }

    #[test]
    fn smoothing_also_steadies_the_orientation() {
        // A still hand whose orientation trembles 0.2 degrees at 10 Hz: the tool 8 cm ahead
        // swings; smoothed, much less.
        let g = Vec3::new(0.1, 1.3, -0.4);
        let frames: Vec<FrameInput> = (0..270)
            .map(|i| {
                let t = i as f64 / FPS;
                let a = 0.0035 * (TAU * 10.0 * t as f32).sin();
                frame(t, idle_left(), hand(g, Quat::from_rotation_x(a)))
            })
            .collect();
        let raw = rms_spread(&tool_positions(InteractionSettings::default(), &frames)[45..]);
        let smooth = rms_spread(&tool_positions(smoothed(), &frames)[45..]);
        assert!(smooth < 0.25 * raw, "smoothed {smooth} vs raw {raw}");
    }

    /// Every script through the interaction: the scenes it gives are what the script's
    /// description promises.
    #[test]
    fn scripts_replay_to_plausible_scenes() {
        let p = ScriptParams::default();
        let (c, r) = (p.center, p.radius_m);
        for kind in ScriptKind::ALL {
            for settings in [InteractionSettings::default(), smoothed()] {
                let mut ix = Interaction::new(settings);
                let mut scene = Scene::default();
                let mut scenes = Vec::new();
                for f in generate(kind, &p) {
                    ix.update(&f, &mut scene);
                    scenes.push(scene.clone());
                }
                let n = scenes.len() as f32;
                let active = |t: usize| {
                    scenes
                        .iter()
                        .filter(|s| s.tools.get(t).is_some_and(|t| t.active))
                        .count() as f32
                        / n
                };
                let tool_x = |s: &Scene| s.tools[RIGHT_TOOL].pose.position.x;
                let (first, last) = (&scenes[0], scenes.last().unwrap());
                let unmoved = scenes.iter().all(|s| s.volume == Placement::default());
                match kind {
                    ScriptKind::SphereSweep => {
                        assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                        assert!(tool_x(first) < c.x - r / 2.0, "{kind}");
                        assert!(tool_x(last) > c.x + r / 2.0, "{kind}");
                        assert_eq!(scenes[0].tools.len(), 1, "{kind}");
                        assert!(unmoved, "{kind}");
                    }
                    ScriptKind::BoxPushPull => {
                        assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                        let z: Vec<f32> =
                            scenes.iter().map(|s| s.tools[0].pose.position.z).collect();
                        let zmin = z.iter().copied().fold(f32::MAX, f32::min);
                        assert!(zmin < c.z - r / 2.0 && z[0] > zmin + 1.5 * r, "{kind}");
                        assert!(unmoved, "{kind}");
                    }
                    ScriptKind::TorusPass => {
                        assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                        for s in &scenes {
                            let t = s.tools[RIGHT_TOOL].pose;
                            let forward = t.orientation * Vec3::NEG_Z;
                            let to_c = (c - t.position).normalize();
                            assert!(forward.dot(to_c) > 0.99, "{kind}: points at the centre");
                        }
                        assert!(unmoved, "{kind}");
                    }
                    ScriptKind::TwoTools => {
                        assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                        assert!(active(LEFT_TOOL) > 0.9, "{kind}");
                        // The tools point 20 degrees inwards, so at mid-script they meet at
                        // the centre; at the start they are well apart, the left one left.
                        let (lx, rx) = (first.tools[LEFT_TOOL].pose.position.x, tool_x(first));
                        assert!(
                            lx < c.x - r / 2.0 && rx > c.x + r / 2.0,
                            "{kind}: {lx} {rx}"
                        );
                        let s = &scenes[scenes.len() / 2];
                        let gap = s.tools[LEFT_TOOL]
                            .pose
                            .position
                            .distance(s.tools[0].pose.position);
                        assert!(gap < 0.01, "{kind}: the tools meet at mid-script: {gap}");
                        assert!(unmoved, "{kind}");
                    }
                    ScriptKind::GrabScale => {
                        assert!(active(RIGHT_TOOL) == 0.0, "{kind}");
                        let moved = scenes.iter().any(|s| {
                            s.volume.scale == 1.0
                                && s.volume.center.distance(c) > r / 2.0
                                && s.volume.rotation.angle_between(Quat::IDENTITY) > 0.3
                        });
                        assert!(moved, "{kind}: grabbed, moved and turned before scaling");
                        let scale = last.volume.scale;
                        assert!((scale - 2.0).abs() < 0.05, "{kind}: scale {scale}");
                        assert_eq!(ix.grab_mode(), GrabMode::None, "{kind}: released");
                        let max_step = scenes
                            .windows(2)
                            .map(|w| w[1].volume.center.distance(w[0].volume.center))
                            .fold(0.0, f32::max);
                        assert!(max_step < 0.01, "{kind}: the volume jumped {max_step} m");
                    }
                    ScriptKind::TfSwitch => {
                        assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                        let tf: Vec<usize> = scenes.iter().map(|s| s.tf_index).collect();
                        let switches = tf.windows(2).filter(|w| w[0] != w[1]).count();
                        assert_eq!((tf[0], *tf.last().unwrap(), switches), (0, 1, 1), "{kind}");
                        assert!(unmoved, "{kind}");
                    }
                    ScriptKind::Tremor => {
                        assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                        let expect = c + settings.tool_offset;
                        for s in &scenes {
                            let d = s.tools[RIGHT_TOOL].pose.position.distance(expect);
                            assert!(d < 2e-3, "{kind}: {d}");
                        }
                        assert!(unmoved, "{kind}");
                    }
                }
                // Same frames, same scenes.
                let mut again = Interaction::new(settings);
                let mut scene2 = Scene::default();
                for f in generate(kind, &p) {
                    again.update(&f, &mut scene2);
                }
                assert_eq!(&scene2, last, "{kind}: deterministic");
            }
        }
    }
}
