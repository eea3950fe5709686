//! Interaction rules: what a surgeon's hands do to the [`Scene`].
//!
//! The layer between [`FrameInput`] and [`Scene`] (docs/design.md, "One frame, as data"). It is plain
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
//! | left stick up/down (iso) | raises/lowers the isovalue (`--iso`) instead                 |
//! | primary (A/X)           | cycles that hand's tool shape (measuring: removes the last mark) |
//! | secondary (B/Y)         | cycles that hand's tool: carve, probe, measure                |
//! | trigger (measuring)     | press, drag, release: a ruler; a click: a point               |
//! | left grip               | grabs the volume: it moves and turns with the hand            |
//! | both grips              | scale (hand distance), move (midpoint), turn (hand axis)      |
//! | menu (either hand)      | next transfer-function preset                                 |
//! | stick click (either)    | next AO method (LAO, the filters)                             |
//! | thumbstick left/right   | turns the environment light about the up axis (SH lighting)   |
//! | left primary (labels)   | the structure menu: selects the next labelled structure       |
//! | left secondary (labels) | shows the selected structure translucent, hidden, shown       |
//! | left stick click (labels) | protects the selected structure from the tools, or not      |
//!
//! With a label map (`scene.structures` not empty) the left hand's primary and secondary buttons
//! and its stick click are the structure menu rather than its tool's shape and mode and the AO
//! cycle: a surgeon hides the ribs, sees through the liver or spares the portal vein with the
//! hand that does not carve.
//!
//! A measuring tool cuts nothing. Its centre places marks ([`Scene::marks`], in the volume's own
//! millimetres, so they move with it): the trigger pressed starts one there, its far end follows
//! the tool while the trigger is held, and the release leaves it; a mark under
//! [`Mark::POINT_MM`] long is a point. The overlay writes each ruler's length beside it.
//!
//! The left hand gets a tool of its own (tool 1) the first time its trigger is pulled, so a
//! two-handed carve (the `two-tools` script) works while a surgeon who only grabs with the left
//! never sees a second tool. Tools from index 2 on (placed by something else) are left alone.
//!
//! A hand that loses tracking freezes: its tool stays where it was, and any grab that needs it
//! is released; the volume only moves again after a fresh grip press.

use super::{FrameInput, HandInput, LEFT, RIGHT};
use crate::clip::{Shape, BUILTIN_SHAPES};
use crate::scene::{Mark, Scene, Tool, ToolMode};
use crate::space::{Placement, Pose};
use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};
use std::f32::consts::TAU;

/// Index in [`Scene::tools`] of the tool the right hand holds (created if missing).
pub const RIGHT_TOOL: usize = 0;
/// Index in [`Scene::tools`] of the tool the left hand holds, once it has one.
pub const LEFT_TOOL: usize = 1;

/// The opacity the structure menu's "translucent" sets.
pub const TRANSLUCENT: f32 = 0.3;

/// The structure menu: `next` selects the next structure, `cycle` shows the selected one
/// translucent (from shown), hidden (from translucent or any opacity between) or shown (from
/// hidden), `protect` toggles whether the tools leave it standing.
fn structure_menu(scene: &mut Scene, next: bool, cycle: bool, protect: bool) {
    let n = scene.structures.len();
    if next {
        scene.structure_selected = (scene.structure_selected + 1) % n;
    }
    if protect {
        scene.protected.resize(n, false);
        let p = &mut scene.protected[scene.structure_selected % n];
        *p = !*p;
    }
    if cycle {
        let a = &mut scene.structures[scene.structure_selected % n];
        *a = match *a {
            a if a >= 1.0 => TRANSLUCENT,
            a if a > 0.0 => 0.0,
            _ => 1.0,
        };
    }
}

/// The hand ([`RIGHT`] or [`LEFT`]) that holds tool `index` of [`Scene::tools`], if one does.
pub fn tool_hand(index: usize) -> Option<usize> {
    match index {
        RIGHT_TOOL => Some(RIGHT),
        LEFT_TOOL => Some(LEFT),
        _ => None,
    }
}

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
    /// Number of AO methods the stick click cycles through (0 or 1: it does nothing).
    pub ao_methods: usize,
    /// Number of loaded meshes ([`Shape::Mesh`]) that the primary button cycles through after
    /// the built-in shapes.
    pub mesh_count: usize,
    /// How fast the left thumbstick moves an isovalue ([`Scene::iso`]): data units per second
    /// at full stick (a quarter of the volume's value range, set by the frame loop).
    pub iso_rate: f32,
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
            ao_methods: 0,
            mesh_count: 0,
            iso_rate: 0.0,
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
    stick_click: Edge,
}

/// What this frame's buttons did on one hand (rising edges).
#[derive(Clone, Copy, Debug, Default)]
struct Pressed {
    trigger: bool,
    grip: bool,
    primary: bool,
    secondary: bool,
    menu: bool,
    stick_click: bool,
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
            stick_click: self.stick_click.update(b.stick_click),
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
    /// The mark (an index into [`Scene::marks`]) this hand's measuring tool is drawing.
    drawing: Option<usize>,
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

        if !scene.structures.is_empty() {
            let menu = &mut pressed[LEFT];
            structure_menu(
                scene,
                std::mem::take(&mut menu.primary),
                std::mem::take(&mut menu.secondary),
                std::mem::take(&mut menu.stick_click),
            );
        }
        self.update_tools(input, &pressed, dt, scene);
        self.update_grab(scene);
        if let Some(iso) = &mut scene.iso {
            let stick = self.deflection(input.hands[LEFT].buttons.thumbstick.y);
            let moved = *iso + self.settings.iso_rate * stick * dt;
            if moved.is_finite() {
                *iso = moved;
            }
        }

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
        let n = self.settings.ao_methods;
        if (pressed[LEFT].stick_click || pressed[RIGHT].stick_click) && n > 0 {
            scene.ao_index = (scene.ao_index % n + 1) % n;
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
            let measuring = tool.mode == ToolMode::Measure;
            if p.trigger && !measuring {
                tool.active = !tool.active;
            }
            if p.primary && measuring {
                scene.marks.pop();
            } else if p.primary {
                tool.shape = self.next_shape(tool.shape);
            }
            if p.secondary {
                tool.mode = match tool.mode {
                    ToolMode::Carve => ToolMode::Probe,
                    ToolMode::Probe => ToolMode::Measure,
                    ToolMode::Measure => ToolMode::Carve,
                };
                // A measuring tool never cuts; back to carving it starts switched off.
                tool.active = false;
            }
            // With an isosurface the left stick moves the isovalue rather than resizing.
            if side == RIGHT || scene.iso.is_none() {
                tool.size = self.resized(tool.size, input.hands[side].buttons.thumbstick.y, dt);
            }
            // Follow the hand while it is tracked; freeze otherwise.
            let hand = &self.hands[side];
            if hand.tracked {
                if let Some(grip) = hand.pose {
                    tool.pose = self.tool_pose(grip);
                }
            }
            self.measure(side, &tool, p.trigger, scene);
            scene.tools[index] = tool;
        }
    }

    /// A measuring tool's marks: the trigger's press starts one at the tool's centre, the far
    /// end follows while it is held, the release leaves it. Any other mode ends a mark in hand.
    fn measure(&mut self, side: usize, tool: &Tool, pressed: bool, scene: &mut Scene) {
        let hand = &mut self.hands[side];
        if tool.mode != ToolMode::Measure {
            hand.drawing = None;
            return;
        }
        let at = scene.volume.local_mm(tool.pose.position);
        if let Some(mark) = hand.drawing.and_then(|k| scene.marks.get_mut(k)) {
            mark.ends[1] = at;
        } else if pressed {
            scene.marks.push(Mark { ends: [at, at] });
            hand.drawing = Some(scene.marks.len() - 1);
        }
        if !hand.buttons.trigger.pressed {
            hand.drawing = None;
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
mod tests;
