//! Scripted pose streams: deterministic, synthetic sessions that exercise one clipping
//! interaction each, so that tests, benchmarks and headless replays need neither a headset nor
//! a person.
//!
//! Every script has the same stage: the volume centred at `center`, the head 0.6 m in front of
//! it (+Z) looking down -Z with a symmetric ±0.6 rad field of view and a 64 mm IPD, the right
//! hand holding the tool. The motion is described in the tool's grip pose; which shape a hand
//! carves with and which button cycles it is the interaction layer's business, so scripts only
//! set trigger and grip values (the header's description names the shape each script is meant
//! for).

use super::hands::{synthetic_hand, HandGesture};
use super::stream::{PoseStreamWriter, StreamError, StreamHeader};
use super::{pose, Buttons, FrameInput, HandInput, LEFT, RIGHT};
use crate::rng::SplitMix64;
use crate::space::{symmetric_fov, Placement, Pose, DEFAULT_IPD};
use glam::{DVec3, Quat, Vec3};
use std::f64::consts::{PI, TAU};
use std::fmt;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The scripted interactions. Names are kebab-case (`sphere-sweep`) for CLIs and file names.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ScriptKind {
    /// Right hand sweeps left to right through the volume centre, trigger pressed (carving).
    SphereSweep,
    /// Right hand pushes in along -Z through the centre and pulls back out, trigger pressed.
    BoxPushPull,
    /// Right hand arcs over the top of the skull (left ear to right ear), tool pointing at the
    /// centre, trigger pressed.
    TorusPass,
    /// Both hands, triggers pressed, mirror-symmetric about the volume's sagittal plane: in
    /// towards the centre and back out while bobbing up and down.
    TwoTools,
    /// Left grip grabs and moves/rotates the volume; then both grips pressed, the hands move
    /// apart (scale up).
    GrabScale,
    /// A still right hand with physiological tremor (8-12 Hz, under 1 mm), trigger pressed.
    Tremor,
    /// The sphere sweep, and the left hand presses menu once a quarter of the way through (the
    /// next transfer function, recomputed progressively while the sweep goes on).
    TfSwitch,
    /// The sphere sweep by a tracked hand instead of a controller: its joints are recorded, a
    /// pinch from 10 % on is the trigger, and tracking is lost from 55 % to 70 %.
    HandPinch,
    /// Right hand carves without a pause along a closed figure-eight through the volume, one
    /// loop every [`CARVE_LOOP_S`] seconds, for as long as the stream lasts: soak runs.
    CarveLoop,
}

/// One loop of [`ScriptKind::CarveLoop`], in seconds (180 frames at 90 fps).
pub const CARVE_LOOP_S: f64 = 2.0;

impl ScriptKind {
    pub const ALL: [ScriptKind; 9] = [
        ScriptKind::SphereSweep,
        ScriptKind::BoxPushPull,
        ScriptKind::TorusPass,
        ScriptKind::TwoTools,
        ScriptKind::GrabScale,
        ScriptKind::Tremor,
        ScriptKind::TfSwitch,
        ScriptKind::HandPinch,
        ScriptKind::CarveLoop,
    ];

    /// The kebab-case name, as parsed by `FromStr` and used for `controllers/scripts/<name>.jsonl`.
    pub fn name(self) -> &'static str {
        match self {
            ScriptKind::SphereSweep => "sphere-sweep",
            ScriptKind::BoxPushPull => "box-push-pull",
            ScriptKind::TorusPass => "torus-pass",
            ScriptKind::TwoTools => "two-tools",
            ScriptKind::GrabScale => "grab-scale",
            ScriptKind::Tremor => "tremor",
            ScriptKind::TfSwitch => "tf-switch",
            ScriptKind::HandPinch => "hand-pinch",
            ScriptKind::CarveLoop => "carve-loop",
        }
    }

    /// Every name, comma-separated, for messages.
    pub fn names() -> String {
        ScriptKind::ALL.map(ScriptKind::name).join(", ")
    }

    /// What the script does, for the stream header and for people.
    pub fn description(self) -> &'static str {
        match self {
            ScriptKind::SphereSweep => {
                "sphere tool: right hand sweeps left to right through the volume centre, \
                 trigger pressed"
            }
            ScriptKind::BoxPushPull => {
                "box tool: right hand pushes in along -Z through the volume centre and pulls \
                 back out, trigger pressed"
            }
            ScriptKind::TorusPass => {
                "torus tool: right hand arcs over the top of the skull from left to right, tool \
                 -Z pointing at the volume centre, trigger pressed"
            }
            ScriptKind::TwoTools => {
                "two tools: both hands, triggers pressed, mirror-symmetric, in towards the \
                 centre and back out"
            }
            ScriptKind::GrabScale => {
                "no tool: left grip moves and rotates the volume, then both grips pressed and \
                 the hands move apart (scale up)"
            }
            ScriptKind::Tremor => {
                "sphere tool: a still right hand at the volume centre with physiological tremor \
                 (8-12 Hz, under 1 mm), trigger pressed"
            }
            ScriptKind::TfSwitch => {
                "sphere tool: right hand sweeps left to right through the volume centre, \
                 trigger pressed; the left hand presses menu (next transfer function) at 25 %"
            }
            ScriptKind::HandPinch => {
                "sphere tool on a tracked hand (joints, no controller): the right hand sweeps \
                 left to right through the volume centre, pinching (the trigger) from 10 %; \
                 tracking is lost from 55 % to 70 %"
            }
            ScriptKind::CarveLoop => {
                "sphere tool: right hand carves without a pause along a figure-eight through \
                 the volume, one loop every 2 s, trigger pressed (for soak runs of any length)"
            }
        }
    }
}

impl fmt::Display for ScriptKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for ScriptKind {
    type Err = ScriptError;

    fn from_str(s: &str) -> Result<Self, ScriptError> {
        ScriptKind::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| ScriptError::UnknownKind(s.to_string()))
    }
}

/// Scripts failed: unknown name, bad parameters, or the stream could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ScriptError {
    #[error("unknown script {0:?}; expected one of {names}", names = ScriptKind::names())]
    UnknownKind(String),
    #[error("script parameters: {0}")]
    Params(String),
    #[error(transparent)]
    Stream(#[from] StreamError),
}

/// What a script may vary. Everything else (head pose, IPD, fov, hand rest poses) is fixed so
/// that streams are comparable.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScriptParams {
    /// Number of frames.
    pub frames: usize,
    /// Frames per second; frame i is at t = i / fps.
    pub fps: f64,
    /// The volume centre in the world; the whole scene is laid out around it.
    pub center: Vec3,
    /// How far the motion reaches from the centre (m): about the half-size of a head.
    pub radius_m: f32,
    /// Seeds the tremor (the only random part; the other scripts ignore it).
    pub seed: u64,
}

impl Default for ScriptParams {
    /// Three seconds at 90 fps around [`Placement::default`]'s centre.
    fn default() -> Self {
        ScriptParams {
            frames: 270,
            fps: 90.0,
            center: Placement::default().center,
            radius_m: 0.09,
            seed: 1,
        }
    }
}

impl ScriptParams {
    /// Checks the parameters, so a CLI can say what is wrong instead of getting no frames.
    pub fn validate(&self) -> Result<(), ScriptError> {
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(ScriptError::Params(format!(
                "fps must be a positive number, not {}",
                self.fps
            )));
        }
        if !self.center.is_finite() {
            return Err(ScriptError::Params(format!(
                "center must be finite, not {}",
                self.center
            )));
        }
        if !(self.radius_m.is_finite() && self.radius_m > 0.0 && self.radius_m <= 10.0) {
            return Err(ScriptError::Params(format!(
                "radius_m must be in (0, 10] metres, not {}",
                self.radius_m
            )));
        }
        Ok(())
    }
}

/// The distance from the head to the volume centre (m), along +Z.
const HEAD_DISTANCE: f32 = 0.6;
/// Half the field of view (rad), each way.
const HALF_FOV: f32 = 0.6;

/// Generates the frames of a script. Deterministic: the same kind and parameters give
/// bit-identical frames on a given platform. Returns no frames if `params` fail
/// [`ScriptParams::validate`] (call it first to learn why).
pub fn generate(kind: ScriptKind, params: &ScriptParams) -> Vec<FrameInput> {
    if params.validate().is_err() {
        return Vec::new();
    }
    let stage = Stage::new(params);
    let n = params.frames;
    let tremor = Tremor::new(params.seed);
    let mut gesture = HandGesture::default();
    (0..n)
        .map(|i| {
            let time = i as f64 / params.fps;
            // Progress through the script, 0 ..= 1.
            let s = if n > 1 {
                i as f64 / (n - 1) as f64
            } else {
                0.0
            };
            let mut joints = [None; 2];
            let hands = match kind {
                ScriptKind::HandPinch => {
                    let mut hands = stage.sphere_sweep(s);
                    let pinch = if s < 0.1 { 0.06 } else { 0.01 };
                    let seen = !(0.55..0.7).contains(&s);
                    joints[RIGHT] = seen.then(|| synthetic_hand(hands[RIGHT].grip, pinch, 0.09));
                    hands[RIGHT] = gesture.update(joints[RIGHT].as_ref());
                    hands
                }
                ScriptKind::SphereSweep => stage.sphere_sweep(s),
                ScriptKind::BoxPushPull => stage.box_push_pull(s),
                ScriptKind::TorusPass => stage.torus_pass(s),
                ScriptKind::TwoTools => stage.two_tools(s),
                ScriptKind::GrabScale => stage.grab_scale(s),
                ScriptKind::Tremor => stage.tremor(&tremor, time),
                ScriptKind::TfSwitch => stage.tf_switch(s),
                ScriptKind::CarveLoop => stage.carve_loop(time),
            };
            FrameInput {
                time,
                views: stage.views,
                hands,
                joints,
                gaze: None,
            }
        })
        .collect()
}

/// The header a script's stream carries: source `script:<name>` and the script's description.
pub fn script_header(kind: ScriptKind) -> StreamHeader {
    StreamHeader::new(format!("script:{}", kind.name()), kind.description())
}

/// Generates a script and writes it as a pose stream to `path`.
pub fn write_script(
    kind: ScriptKind,
    params: &ScriptParams,
    path: &Path,
) -> Result<(), ScriptError> {
    params.validate()?;
    let write_err = |source| {
        ScriptError::Stream(StreamError::Write {
            path: PathBuf::from(path),
            source,
        })
    };
    // Not PoseStreamWriter::create: its io errors already name the file, and StreamError does.
    let file = File::create(path).map_err(write_err)?;
    let mut w =
        PoseStreamWriter::new(BufWriter::new(file), &script_header(kind)).map_err(write_err)?;
    for f in generate(kind, params) {
        w.write_frame(&f).map_err(write_err)?;
    }
    w.finish().map_err(write_err)?;
    Ok(())
}

/// The fixed layout around the volume centre. Motions are computed in f64 around the centre and
/// rounded to f32 once, so small motions (tremor) are not lost to f32 rounding of the offset.
struct Stage {
    center: DVec3,
    r: f64,
    views: [crate::space::View; 2],
}

/// One sinusoid of the tremor.
struct Wave {
    freq_hz: f64,
    phase: f64,
    amplitude: f64,
    axis: DVec3,
}

impl Wave {
    fn at(&self, t: f64) -> DVec3 {
        self.axis * (self.amplitude * (TAU * self.freq_hz * t + self.phase).sin())
    }
}

/// Physiological tremor: a sum of a few sinusoids between 8.5 and 11.5 Hz (inside the 8-12 Hz
/// band with room for spectral leakage), in position (each 0.2-0.35 mm, so at most about 1 mm
/// in all) and in orientation (each about 0.1-0.2 degrees).
struct Tremor {
    position: Vec<Wave>,
    rotation: Vec<Wave>,
}

impl Tremor {
    fn new(seed: u64) -> Self {
        let mut rng = SplitMix64(seed);
        let mut waves = |count, lo, hi| -> Vec<Wave> {
            (0..count)
                .map(|_| Wave {
                    freq_hz: rng.range(8.5, 11.5),
                    phase: rng.range(0.0, TAU),
                    amplitude: rng.range(lo, hi),
                    axis: rng.direction(),
                })
                .collect()
        };
        let position = waves(3, 0.2e-3, 0.35e-3);
        let rotation = waves(2, 0.0017, 0.0035);
        Tremor { position, rotation }
    }

    /// (position offset in m, rotation vector in rad) at time t.
    fn at(&self, t: f64) -> (DVec3, DVec3) {
        let sum = |w: &[Wave]| w.iter().map(|w| w.at(t)).sum::<DVec3>();
        (sum(&self.position), sum(&self.rotation))
    }
}

/// Cubic ease in/out on [0, 1], so motions start and stop without a jump in velocity.
fn smooth(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

/// Eased progress through the interval [a, b] of the script: 0 before, 1 after.
fn phase(s: f64, a: f64, b: f64) -> f64 {
    smooth((s - a) / (b - a))
}

fn lerp(a: DVec3, b: DVec3, s: f64) -> DVec3 {
    a + (b - a) * s
}

impl Stage {
    fn new(p: &ScriptParams) -> Self {
        let head = pose(
            p.center + Vec3::new(0.0, 0.0, HEAD_DISTANCE),
            Quat::IDENTITY,
        );
        Stage {
            center: p.center.as_dvec3(),
            r: p.radius_m as f64,
            views: FrameInput::head_views(head, DEFAULT_IPD, symmetric_fov(HALF_FOV)),
        }
    }

    /// A world point `offset` (in units of r) from the centre.
    fn at(&self, offset: DVec3) -> DVec3 {
        self.center + offset * self.r
    }

    /// A tracked hand with its grip at `position`, the aim ray 5 cm ahead of the grip along its
    /// -Z with the same orientation.
    fn hand(&self, position: DVec3, orientation: Quat, grip: f64, trigger: f64) -> HandInput {
        let grip_pose = Pose {
            position: position.as_vec3(),
            orientation: orientation.normalize(),
        };
        HandInput {
            tracked: true,
            grip: grip_pose,
            aim: Pose {
                position: (position + orientation.as_dquat() * DVec3::new(0.0, 0.0, -0.05))
                    .as_vec3(),
                orientation: grip_pose.orientation,
            },
            buttons: Buttons {
                grip: grip.clamp(0.0, 1.0) as f32,
                trigger: trigger.clamp(0.0, 1.0) as f32,
                ..Buttons::default()
            },
        }
    }

    /// An idle hand, tracked, hanging low in front of the body on its side, nothing pressed.
    fn idle(&self, side: usize) -> HandInput {
        let x = if side == LEFT { -0.25 } else { 0.25 };
        let position = self.center + DVec3::new(x, -0.3, 0.35);
        self.hand(position, Quat::IDENTITY, 0.0, 0.0)
    }

    fn with_right(&self, right: HandInput) -> [HandInput; 2] {
        [self.idle(LEFT), right]
    }

    fn sphere_sweep(&self, s: f64) -> [HandInput; 2] {
        let x = -1.0 + 2.0 * smooth(s);
        let p = self.at(DVec3::new(x, 0.0, 0.0));
        self.with_right(self.hand(p, Quat::IDENTITY, 0.0, 1.0))
    }

    fn box_push_pull(&self, s: f64) -> [HandInput; 2] {
        // +r (in front of the centre) -> -r at mid-script -> +r.
        let z = (TAU * s).cos();
        let p = self.at(DVec3::new(0.0, 0.0, z));
        self.with_right(self.hand(p, Quat::IDENTITY, 0.0, 1.0))
    }

    fn torus_pass(&self, s: f64) -> [HandInput; 2] {
        // A half circle of radius r over the top: left (-x) -> top (+y) -> right (+x).
        let a = PI * smooth(s);
        let offset = DVec3::new(-a.cos(), a.sin(), 0.0);
        let p = self.at(offset);
        let towards_center = (-offset).as_vec3().normalize();
        let q = Quat::from_rotation_arc(Vec3::NEG_Z, towards_center);
        self.with_right(self.hand(p, q, 0.0, 1.0))
    }

    fn two_tools(&self, s: f64) -> [HandInput; 2] {
        // Each hand 1.2 r out to the side, in to 0.3 r at mid-script, back out; bobbing in y.
        let x = 1.2 - 0.9 * (PI * s).sin();
        let y = 0.4 * (TAU * s).sin();
        // Tools angled 20 degrees inwards from -Z; the left hand mirrors the right.
        let yaw = 0.35;
        [
            self.hand(
                self.at(DVec3::new(-x, y, 0.0)),
                Quat::from_rotation_y(-yaw),
                0.0,
                1.0,
            ),
            self.hand(
                self.at(DVec3::new(x, y, 0.0)),
                Quat::from_rotation_y(yaw),
                0.0,
                1.0,
            ),
        ]
    }

    /// Phases (script progress s):
    /// - 0.00-0.10 left hand at the volume's left side, grip squeezing from 0.05
    /// - 0.10-0.45 left grip held: the hand moves (0.8, 0.4, 0.4) r and yaws 0.5 rad
    /// - 0.45-0.52 right hand comes in from idle to 2 r right of the left hand
    /// - 0.52-0.57 right grip squeezes
    /// - 0.60-0.95 both grips held: the hands move apart, 2 r -> 4 r
    /// - 0.95-1.00 both grips released
    fn grab_scale(&self, s: f64) -> [HandInput; 2] {
        let l0 = self.at(DVec3::new(-1.2, 0.0, 0.5));
        let l1 = l0 + DVec3::new(0.8, 0.4, 0.4) * self.r;
        let yaw = 0.5 * phase(s, 0.10, 0.45);
        let r1 = l1 + DVec3::new(2.0, 0.0, 0.0) * self.r;
        let spread = DVec3::X * self.r * phase(s, 0.60, 0.95);
        let release = 1.0 - phase(s, 0.95, 1.0);

        let left_pos = lerp(l0, l1, phase(s, 0.10, 0.45)) - spread;
        let left_grip = phase(s, 0.05, 0.10) * release;
        let left = self.hand(left_pos, Quat::from_rotation_y(yaw as f32), left_grip, 0.0);

        let idle = self.idle(RIGHT).grip.position.as_dvec3();
        let right_pos = lerp(idle, r1, phase(s, 0.45, 0.52)) + spread;
        let right_grip = phase(s, 0.52, 0.57) * release;
        let right = self.hand(right_pos, Quat::IDENTITY, right_grip, 0.0);
        [left, right]
    }

    fn tf_switch(&self, s: f64) -> [HandInput; 2] {
        let mut hands = self.sphere_sweep(s);
        // Held for a few frames (a real press), counted once.
        hands[LEFT].buttons.menu = (0.25..0.28).contains(&s);
        hands
    }

    /// A figure-eight in x-y with a slower swing in depth, at most about 0.85 r from the
    /// centre, so the tool is always inside and always moving; it yaws with the swing, so the
    /// clip maps of a non-round tool turn too.
    fn carve_loop(&self, t: f64) -> [HandInput; 2] {
        let a = TAU * t / CARVE_LOOP_S;
        let p = self.at(DVec3::new(
            0.6 * a.sin(),
            0.4 * (2.0 * a).sin(),
            0.4 * a.cos(),
        ));
        let q = Quat::from_rotation_y((0.5 * a.sin()) as f32);
        self.with_right(self.hand(p, q, 0.0, 1.0))
    }

    fn tremor(&self, tremor: &Tremor, t: f64) -> [HandInput; 2] {
        let (dp, dr) = tremor.at(t);
        let q = Quat::from_scaled_axis(dr.as_vec3());
        self.with_right(self.hand(self.center + dp, q, 0.0, 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::input::stream::read_stream;

    fn params(frames: usize) -> ScriptParams {
        ScriptParams {
            frames,
            ..ScriptParams::default()
        }
    }

    fn grip_pos(f: &FrameInput, hand: usize) -> Vec3 {
        f.hands[hand].grip.position
    }

    /// The parameters of the committed `controllers/scripts/<name>.jsonl` files: a few
    /// seconds at 90 fps each, so the files stay small.
    fn committed_params(kind: ScriptKind) -> ScriptParams {
        let frames = match kind {
            ScriptKind::GrabScale => 270,
            ScriptKind::Tremor => 256,
            _ => 180,
        };
        ScriptParams {
            frames,
            ..ScriptParams::default()
        }
    }

    fn scripts_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("controllers/scripts")
    }

    #[test]
    fn names_round_trip_and_unknown_names_are_listed() {
        for k in ScriptKind::ALL {
            assert_eq!(k.to_string().parse::<ScriptKind>().unwrap(), k);
        }
        assert_eq!(
            "box-push-pull".parse::<ScriptKind>().unwrap(),
            ScriptKind::BoxPushPull
        );
        let e = "sphere".parse::<ScriptKind>().unwrap_err().to_string();
        assert!(e.contains("\"sphere\"") && e.contains("grab-scale"), "{e}");
    }

    #[test]
    fn every_script_is_well_formed_and_deterministic() {
        for k in ScriptKind::ALL {
            for n in [0, 1, 2, 120] {
                let p = params(n);
                let frames = generate(k, &p);
                assert_eq!(frames.len(), n, "{k}");
                assert_eq!(frames, generate(k, &p), "{k} is not deterministic");
                for (i, f) in frames.iter().enumerate() {
                    assert_eq!(f.time, i as f64 / p.fps, "{k}");
                    if i > 0 {
                        assert!(f.time > frames[i - 1].time, "{k}");
                    }
                    // The reader's own checks: finite, unit quaternions, ranges.
                    let checked = crate::input::stream::check_frame(*f, None);
                    assert_eq!(checked.as_ref(), Ok(f), "{k} frame {i}");
                    for h in &f.hands {
                        for q in [h.grip.orientation, h.aim.orientation] {
                            assert!((q.length() - 1.0).abs() < 1e-6, "{k}: {q}");
                        }
                    }
                    let head = (f.views[0].pose.position + f.views[1].pose.position) * 0.5;
                    let expect = p.center + Vec3::new(0.0, 0.0, 0.6);
                    assert!((head - expect).length() < 1e-6, "{k}");
                    let ipd = f.views[0].pose.position.distance(f.views[1].pose.position);
                    assert!((ipd - 0.064).abs() < 1e-6, "{k}");
                }
            }
        }
    }

    #[test]
    fn invalid_params_give_no_frames_and_a_reason() {
        for bad in [
            ScriptParams {
                fps: 0.0,
                ..ScriptParams::default()
            },
            ScriptParams {
                fps: f64::NAN,
                ..ScriptParams::default()
            },
            ScriptParams {
                radius_m: -1.0,
                ..ScriptParams::default()
            },
            ScriptParams {
                center: Vec3::new(0.0, f32::INFINITY, 0.0),
                ..ScriptParams::default()
            },
        ] {
            assert!(generate(ScriptKind::SphereSweep, &bad).is_empty());
            let e = bad.validate().unwrap_err();
            assert!(e.to_string().starts_with("script parameters:"), "{e}");
        }
    }

    #[test]
    fn hand_pinch_records_joints_pinches_and_loses_tracking() {
        let frames = generate(ScriptKind::HandPinch, &params(100));
        for (i, f) in frames.iter().enumerate() {
            let s = i as f64 / 99.0;
            let r = &f.hands[RIGHT];
            let lost = (0.55..0.7).contains(&s);
            assert_eq!(f.joints[RIGHT].is_none(), lost, "frame {i}");
            assert_eq!(r.tracked, !lost, "frame {i}");
            assert!(f.joints[LEFT].is_none());
            if !lost {
                let j = f.joints[RIGHT].unwrap();
                assert_eq!(r.grip, j.poses[crate::input::hands::PALM], "frame {i}");
                let pinched = s >= 0.1;
                assert_eq!(
                    r.buttons.trigger,
                    if pinched { 1.0 } else { 0.0 },
                    "frame {i}"
                );
            }
        }
    }

    #[test]
    fn sphere_sweep_goes_left_to_right_through_the_centre_carving() {
        let p = ScriptParams::default();
        let c = p.center;
        let r = p.radius_m;
        let frames = generate(ScriptKind::SphereSweep, &p);
        let first = grip_pos(&frames[0], RIGHT);
        let last = grip_pos(frames.last().unwrap(), RIGHT);
        assert!(first.x < c.x - r / 2.0 && last.x > c.x + r / 2.0);
        let mid = grip_pos(&frames[frames.len() / 2], RIGHT);
        assert!(mid.distance(c) < r * 0.05, "passes through the centre");
        assert!(frames
            .windows(2)
            .all(|w| grip_pos(&w[1], RIGHT).x >= grip_pos(&w[0], RIGHT).x));
        assert!(frames.iter().all(|f| f.hands[RIGHT].buttons.trigger > 0.5));
        assert!(frames.iter().all(|f| f.hands[LEFT].buttons.trigger == 0.0));
    }

    #[test]
    fn box_push_pull_goes_in_then_out() {
        let p = ScriptParams::default();
        let (c, r) = (p.center, p.radius_m);
        let frames = generate(ScriptKind::BoxPushPull, &p);
        let z: Vec<f32> = frames.iter().map(|f| grip_pos(f, RIGHT).z).collect();
        let (imin, zmin) = z
            .iter()
            .copied()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(z[0] > c.z + r / 2.0 && zmin < c.z - r / 2.0);
        assert!(*z.last().unwrap() > c.z + r / 2.0);
        assert!(z[..=imin].windows(2).all(|w| w[1] <= w[0]), "pushed in");
        assert!(z[imin..].windows(2).all(|w| w[1] >= w[0]), "pulled out");
        assert!((imin as f32 / z.len() as f32 - 0.5).abs() < 0.05);
        for f in &frames {
            let g = grip_pos(f, RIGHT);
            assert!(
                (g.x - c.x).abs() < 1e-6 && (g.y - c.y).abs() < 1e-6,
                "along Z only"
            );
            assert!(f.hands[RIGHT].buttons.trigger > 0.5);
        }
    }

    #[test]
    fn torus_passes_over_the_top_pointing_at_the_centre() {
        let p = ScriptParams::default();
        let (c, r) = (p.center, p.radius_m);
        let frames = generate(ScriptKind::TorusPass, &p);
        let first = grip_pos(&frames[0], RIGHT);
        let last = grip_pos(frames.last().unwrap(), RIGHT);
        assert!(first.x < c.x - r / 2.0 && last.x > c.x + r / 2.0);
        let top = frames
            .iter()
            .map(|f| grip_pos(f, RIGHT).y)
            .fold(f32::MIN, f32::max);
        assert!(top > c.y + 0.9 * r, "over the top: {top}");
        for f in &frames {
            let h = &f.hands[RIGHT];
            assert!(h.grip.position.y >= c.y - 1e-6, "never below the centre");
            assert!((h.grip.position.distance(c) - r).abs() < 1e-4, "on the arc");
            let forward = h.grip.orientation * Vec3::NEG_Z;
            let to_c = (c - h.grip.position).normalize();
            assert!(forward.dot(to_c) > 0.999, "tool points at the centre");
            assert!(h.buttons.trigger > 0.5);
        }
    }

    #[test]
    fn two_tools_are_both_carving_and_mirror_symmetric() {
        let p = ScriptParams::default();
        let c = p.center;
        let frames = generate(ScriptKind::TwoTools, &p);
        let mut min_gap = f32::MAX;
        for f in &frames {
            let [l, r] = &f.hands;
            assert!(l.tracked && r.tracked);
            assert!(l.buttons.trigger > 0.5 && r.buttons.trigger > 0.5);
            let (lp, rp) = (l.grip.position - c, r.grip.position - c);
            assert!((lp.x + rp.x).abs() < 1e-6 && (lp.y - rp.y).abs() < 1e-6);
            assert!((lp.z - rp.z).abs() < 1e-6);
            let (lq, rq) = (l.grip.orientation, r.grip.orientation);
            let mirrored = Quat::from_xyzw(rq.x, -rq.y, -rq.z, rq.w);
            assert!(lq.abs_diff_eq(mirrored, 1e-6), "{lq} vs {rq}");
            min_gap = min_gap.min(lp.distance(rp));
        }
        let gap0 = grip_pos(&frames[0], LEFT).distance(grip_pos(&frames[0], RIGHT));
        assert!(min_gap < gap0 * 0.5, "the hands come in towards the centre");
    }

    #[test]
    fn grab_scale_grabs_with_the_left_then_spreads_both() {
        let p = ScriptParams::default();
        let r = p.radius_m;
        let frames = generate(ScriptKind::GrabScale, &p);
        let grip = |f: &FrameInput, h: usize| f.hands[h].buttons.grip;

        // One-handed phase: left grip held, right not; the left hand moves and turns.
        let one: Vec<&FrameInput> = frames
            .iter()
            .filter(|f| grip(f, LEFT) > 0.5 && grip(f, RIGHT) < 0.5)
            .collect();
        assert!(one.len() > 20);
        let (a, b) = (one[0], one[one.len() - 1]);
        assert!(grip_pos(a, LEFT).distance(grip_pos(b, LEFT)) > r / 2.0);
        let turned = a.hands[LEFT]
            .grip
            .orientation
            .angle_between(b.hands[LEFT].grip.orientation);
        assert!(turned > 0.3, "{turned}");

        // Two-handed phase: both grips held, the hands' distance increasing.
        let both: Vec<(usize, &FrameInput)> = frames
            .iter()
            .enumerate()
            .filter(|(_, f)| grip(f, LEFT) > 0.5 && grip(f, RIGHT) > 0.5)
            .collect();
        assert!(both.len() > 20);
        assert!(
            both.windows(2).all(|w| w[1].0 == w[0].0 + 1),
            "one contiguous phase"
        );
        assert!(
            one.iter().all(|f| f.time < both[0].1.time),
            "grab, then scale"
        );
        let dist: Vec<f32> = both
            .iter()
            .map(|(_, f)| grip_pos(f, LEFT).distance(grip_pos(f, RIGHT)))
            .collect();
        assert!(dist.windows(2).all(|w| w[1] >= w[0] - 1e-6));
        assert!(dist[dist.len() - 1] > dist[0] + r, "{dist:?}");
        let last = frames.last().unwrap();
        assert!(
            grip(last, LEFT) == 0.0 && grip(last, RIGHT) == 0.0,
            "released"
        );
    }

    #[test]
    fn carve_loop_moves_every_frame_inside_the_volume_and_repeats() {
        let p = params(1000);
        let frames = generate(ScriptKind::CarveLoop, &p);
        let (c, r) = (p.center, p.radius_m);
        let per_loop = (CARVE_LOOP_S * p.fps).round() as usize;
        for (i, f) in frames.iter().enumerate() {
            let h = &f.hands[RIGHT];
            assert_eq!(h.buttons.trigger, 1.0, "frame {i}");
            assert!(grip_pos(f, RIGHT).distance(c) < 0.9 * r, "frame {i}");
            if i > 0 {
                let step = grip_pos(f, RIGHT).distance(grip_pos(&frames[i - 1], RIGHT));
                assert!(step > 0.01 * r, "frame {i} moved only {step} m");
            }
            if i >= per_loop {
                let back = grip_pos(&frames[i - per_loop], RIGHT);
                assert!(grip_pos(f, RIGHT).abs_diff_eq(back, 1e-5), "frame {i}");
            }
        }
        // It covers the volume: left and right, up and down, front and back.
        for axis in 0..3 {
            let span = frames
                .iter()
                .map(|f| grip_pos(f, RIGHT)[axis])
                .fold((f32::MAX, f32::MIN), |(lo, hi), x| (lo.min(x), hi.max(x)));
            assert!(span.1 - span.0 > 0.7 * r, "axis {axis}: {span:?}");
        }
    }

    #[test]
    fn tremor_is_small_and_between_8_and_12_hz() {
        let p = ScriptParams {
            frames: 256,
            ..ScriptParams::default()
        };
        let frames = generate(ScriptKind::Tremor, &p);
        let pos: Vec<DVec3> = frames
            .iter()
            .map(|f| grip_pos(f, RIGHT).as_dvec3())
            .collect();
        let mean = pos.iter().sum::<DVec3>() / pos.len() as f64;
        let dev: Vec<DVec3> = pos.iter().map(|p| *p - mean).collect();
        let peak = dev.iter().map(|d| d.length()).fold(0.0, f64::max);
        assert!((0.3e-3..=1.2e-3).contains(&peak), "peak {peak}");
        assert!(
            mean.distance(p.center.as_dvec3()) < 0.2e-3,
            "a still hand at the centre"
        );

        // Hann-windowed DFT of each axis; energy per frequency bin summed over axes.
        let n = dev.len();
        let (mut band, mut total) = (0.0, 0.0);
        for k in 1..n / 2 {
            let freq = k as f64 * p.fps / n as f64;
            let mut energy = 0.0;
            for axis in 0..3 {
                let (mut re, mut im) = (0.0, 0.0);
                for (i, d) in dev.iter().enumerate() {
                    let w = 0.5 - 0.5 * (TAU * i as f64 / n as f64).cos();
                    let x = d[axis] * w;
                    let a = TAU * (k * i) as f64 / n as f64;
                    re += x * a.cos();
                    im -= x * a.sin();
                }
                energy += re * re + im * im;
            }
            total += energy;
            if (8.0..=12.0).contains(&freq) {
                band += energy;
            }
        }
        assert!(
            band / total > 0.9,
            "only {:.3} of the energy in 8-12 Hz",
            band / total
        );

        // Different seeds, different tremor; the trigger is held throughout.
        let other = generate(ScriptKind::Tremor, &ScriptParams { seed: 2, ..p });
        assert_ne!(frames, other);
        assert!(frames.iter().all(|f| f.hands[RIGHT].buttons.trigger > 0.5));
    }

    #[test]
    fn write_script_writes_a_readable_stream() {
        let path = std::env::temp_dir().join(format!(
            "cao-xr-script-{}-two-tools.jsonl",
            std::process::id()
        ));
        let p = params(30);
        write_script(ScriptKind::TwoTools, &p, &path).unwrap();
        let (header, frames) = read_stream(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        assert_eq!(header.source, "script:two-tools");
        assert_eq!(header.version, crate::input::stream::VERSION);
        assert_eq!(frames, generate(ScriptKind::TwoTools, &p));

        let bad = ScriptParams { fps: -1.0, ..p };
        assert!(matches!(
            write_script(ScriptKind::TwoTools, &bad, &path),
            Err(ScriptError::Params(_))
        ));
        let nowhere = path.join("missing-dir/x.jsonl");
        let e = write_script(ScriptKind::TwoTools, &p, &nowhere).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("missing-dir") && msg.contains("cannot write"),
            "{msg}"
        );
        assert_eq!(msg.matches("missing-dir").count(), 1, "{msg}");
    }

    /// The committed scripts read back and still match the generator (loosely: another
    /// platform's libm may differ in the last bits).
    #[test]
    fn committed_scripts_match_the_generator() {
        for k in ScriptKind::ALL {
            let path = scripts_dir().join(format!("{k}.jsonl"));
            if !path.exists() {
                continue;
            }
            let (header, frames) = read_stream(&path).unwrap();
            assert_eq!(header.source, format!("script:{k}"));
            let fresh = generate(k, &committed_params(k));
            assert_eq!(frames.len(), fresh.len(), "{k}: regenerate the scripts");
            for (a, b) in frames.iter().zip(&fresh) {
                for h in [LEFT, RIGHT] {
                    let (ga, gb) = (a.hands[h].grip, b.hands[h].grip);
                    assert!(ga.position.abs_diff_eq(gb.position, 1e-5), "{k}");
                    assert!(ga.orientation.abs_diff_eq(gb.orientation, 1e-5), "{k}");
                    assert_eq!(a.hands[h].buttons, b.hands[h].buttons, "{k}");
                }
            }
        }
    }

    /// Regenerates `controllers/scripts/*.jsonl`:
    /// `cargo test --lib input::script -- --ignored`.
    #[test]
    #[ignore]
    fn generate_committed_scripts() {
        std::fs::create_dir_all(scripts_dir()).unwrap();
        for k in ScriptKind::ALL {
            let path = scripts_dir().join(format!("{k}.jsonl"));
            write_script(k, &committed_params(k), &path).unwrap();
        }
    }
}
