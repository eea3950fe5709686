//! Pose streams: [`FrameInput`]s recorded as JSON Lines, so that a session (headset, desktop or
//! script) can be replayed headless, bit for bit, and diffed and edited by hand.
//!
//! The first line is a header object (the reader also accepts comments before it), every
//! further non-empty line one frame; lines whose first non-blank character is `#` are
//! comments. The format is documented for people in
//! `controllers/scripts/README.md`; in short:
//!
//! (each object is on one line in a file; wrapped here)
//!
//! ```text
//! {"format":"cao-xr-pose-stream","version":4,"units":"m","reference_space":"STAGE",
//!  "view_configuration":"PRIMARY_STEREO","source":"script:tremor","description":"..."}
//! {"t":0.0,"views":[{"pose":{"p":[x,y,z],"q":[x,y,z,w]},"fov":[l,r,u,d]},{..}],
//!  "hands":[{"tracked":true,"grip":{"p":..,"q":..},"aim":{..},"grip_value":0.0,"trigger":1.0,
//!            "primary":false,"secondary":false,"menu":false,"stick_click":false,
//!            "stick":[0.0,0.0]},{..}],
//!  "joints":[null,{"p":[[x,y,z] x26],"q":[[x,y,z,w] x26],"r":[r x26]}],
//!  "gaze":{"p":[x,y,z],"q":[x,y,z,w]}}
//! ```
//!
//! The wire format is private serde structs mapped to and from [`FrameInput`], so the in-memory
//! type stays free of wire details and the wire stays compact (short keys, arrays for vectors).
//!
//! Numbers are written in their shortest round-tripping form (serde_json uses ryu) and read back
//! with serde_json's correctly rounded parser (its `float_roundtrip` feature; without it a
//! 17-digit f64 such as `t = 1/90` is often one ulp off), so writing and reading give back the
//! identical `FrameInput`; a test checks random f64 times and f32 bit patterns.
//!
//! The writer refuses what the reader would refuse, so a recording can always be replayed.

use super::hands::{HandJoints, JOINT_COUNT};
use super::{Buttons, FrameInput, HandInput};
use crate::space::{Fov, Pose, View};
use glam::{Quat, Vec2, Vec3};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The header's `format` string: what makes a file a pose stream.
pub const FORMAT: &str = "cao-xr-pose-stream";
/// The stream version this build writes and the newest it reads.
pub const VERSION: u64 = 4;
/// Positions are in metres (OpenXR's unit).
pub const UNITS: &str = "m";
/// Poses are in OpenXR's STAGE space: floor-level origin, +Y up.
pub const REFERENCE_SPACE: &str = "STAGE";
/// Two views, left eye then right eye.
pub const VIEW_CONFIGURATION: &str = "PRIMARY_STEREO";

/// How far a quaternion's length may be from 1 and still be accepted (it is then normalised).
/// Anything further off is a corrupt or hand-mangled file, not rounding.
pub const UNIT_TOLERANCE: f32 = 1e-3;
/// Lengths this close to 1 are f32 rounding of a unit quaternion and are kept bit for bit, so
/// that a round trip is exact.
const UNIT_EXACT: f32 = 1e-6;

/// The first line of a pose stream. Only `source`, `description` and `volume_at` are free;
/// [`StreamHeader::new`] fills in the rest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StreamHeader {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`VERSION`] when written by this build.
    pub version: u64,
    /// Always [`UNITS`].
    pub units: String,
    /// Always [`REFERENCE_SPACE`].
    pub reference_space: String,
    /// Always [`VIEW_CONFIGURATION`].
    pub view_configuration: String,
    /// Who produced the frames: `xr`, `desktop` or `script:NAME`.
    pub source: String,
    /// Free text for people.
    pub description: String,
    /// Where the session put the volume's centre (stage metres, `xr --volume-at`), so that a
    /// replay carves the same voxels; None: the default placement.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume_at: Option<[f32; 3]>,
}

impl StreamHeader {
    /// A current-version header with the given source (`xr`, `desktop`, `script:NAME`) and
    /// description.
    pub fn new(source: impl Into<String>, description: impl Into<String>) -> Self {
        StreamHeader {
            format: FORMAT.into(),
            version: VERSION,
            units: UNITS.into(),
            reference_space: REFERENCE_SPACE.into(),
            view_configuration: VIEW_CONFIGURATION.into(),
            source: source.into(),
            description: description.into(),
            volume_at: None,
        }
    }
}

impl Default for StreamHeader {
    fn default() -> Self {
        StreamHeader::new("", "")
    }
}

/// What is wrong with one line of a stream (the file and line are in [`StreamError::Line`]).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LineError {
    #[error("not valid JSON: {0}")]
    Syntax(String),
    /// Valid JSON, but not the expected shape: a missing or unknown field, a wrong type or
    /// array length.
    #[error("{0}")]
    Schema(String),
    #[error(
        "the line ends in the middle of an object; the recording was probably interrupted here \
         (delete this line to replay the frames before it)"
    )]
    Truncated,
    #[error(
        "not a cao-xr pose stream: the header's \"format\" is {found}, expected \"{}\" \
         (the first line must be the header)",
        FORMAT
    )]
    WrongFormat { found: String },
    #[error(
        "the header has no \"version\"; this build reads versions 1 to {} \
         (add \"version\":1 if the file follows that format)",
        VERSION
    )]
    MissingVersion,
    #[error(
        "version 0 is not a stream version (versions start at 1); this build reads versions 1 to {}",
        VERSION
    )]
    VersionZero,
    #[error(
        "stream version {found} is newer than this build reads (version {}); \
         use a newer cao-xr or re-record the stream",
        VERSION
    )]
    NewerVersion { found: u64 },
    #[error("the header's \"{field}\" is {found}; this build reads only \"{expected}\"")]
    Unsupported {
        field: &'static str,
        found: String,
        expected: &'static str,
    },
    #[error("{what} is not a finite number")]
    NonFinite { what: String },
    #[error("{what} = {value} is outside {lo}..={hi}")]
    OutOfRange {
        what: String,
        value: f64,
        lo: f64,
        hi: f64,
    },
    #[error(
        "{what} is not a unit quaternion (length {length}); lengths within {} of 1 are \
         normalised, this one is too far off (quaternions are written [x,y,z,w])",
        UNIT_TOLERANCE
    )]
    NotUnit { what: String, length: f32 },
    #[error("{what} is not a field of view: {reason}")]
    BadFov { what: String, reason: &'static str },
    #[error("t = {t} is negative; t counts seconds from the start of the stream")]
    NegativeTime { t: f64 },
    #[error("time goes backwards: t = {t} after t = {previous}")]
    TimeBackwards { t: f64, previous: f64 },
}

/// Reading a pose stream failed. Every message names the file, and the 1-based line where one
/// is to blame.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error("{path}: cannot open: {source}")]
    Open {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    #[error("{path}, line {line}: cannot read: {source}")]
    Read {
        path: PathBuf,
        line: usize,
        #[source]
        source: io::Error,
    },
    #[error("{path}: cannot write: {source}")]
    Write {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    #[error(
        "{path}: empty stream: expected a header line such as \
         {{\"format\":\"{}\",\"version\":{},...}}",
        FORMAT,
        VERSION
    )]
    NoHeader { path: PathBuf },
    #[error("{path}, line {line}: {problem}")]
    Line {
        path: PathBuf,
        line: usize,
        problem: LineError,
    },
}

impl StreamError {
    /// The 1-based line the error is about, if any.
    pub fn line(&self) -> Option<usize> {
        match self {
            StreamError::Read { line, .. } | StreamError::Line { line, .. } => Some(*line),
            _ => None,
        }
    }

    /// What is wrong with the line, for errors about a line's content.
    pub fn problem(&self) -> Option<&LineError> {
        match self {
            StreamError::Line { problem, .. } => Some(problem),
            _ => None,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Wire structs

/// The header as read: everything optional so that a missing field gets a precise message
/// rather than serde's. Unknown header fields are ignored (free metadata may grow without a
/// version bump); frames, in contrast, deny unknown fields so a typo is caught.
#[derive(Deserialize)]
#[serde(expecting = "a header object {\"format\":\"cao-xr-pose-stream\",\"version\":1,...}")]
struct WireHeader {
    format: Option<String>,
    version: Option<u64>,
    units: Option<String>,
    reference_space: Option<String>,
    view_configuration: Option<String>,
    #[serde(default)]
    source: String,
    #[serde(default)]
    description: String,
    #[serde(default)]
    volume_at: Option<[F32; 3]>,
}

#[derive(Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a frame object {\"t\":..,\"views\":[..],\"hands\":[..]}"
)]
struct WireFrame {
    t: f64,
    views: [WireView; 2],
    hands: [WireHand; 2],
    /// Tracked hand joints per hand, or null: required from version 3 on, absent before.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    joints: Option<[Option<WireJoints>; 2]>,
    /// The eyes' gaze pose (looking along its -Z), or null: required from version 4 on, absent
    /// before (the outer None).
    #[serde(
        default,
        deserialize_with = "present",
        skip_serializing_if = "Option::is_none"
    )]
    gaze: Option<Option<WirePose>>,
}

/// A field that is there, null or not (serde's default reads a null as absent).
fn present<'de, D: serde::Deserializer<'de>, T: Deserialize<'de>>(
    d: D,
) -> Result<Option<T>, D::Error> {
    T::deserialize(d).map(Some)
}

/// One hand's 26 joints (XR_EXT_hand_tracking's order): positions, orientations [x,y,z,w] and
/// radii (m).
#[derive(Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a hand's joints {\"p\":[[x,y,z] x26],\"q\":[[x,y,z,w] x26],\"r\":[r x26]}"
)]
struct WireJoints {
    p: Vec<[F32; 3]>,
    q: Vec<[F32; 4]>,
    r: Vec<F32>,
}

/// An f32 on the wire: written in its shortest round-tripping form, read through a correctly
/// rounded f64, so that a finite JSON number too large for an f32 reads as infinity and is
/// refused by name ([`check_frame`]) rather than as bad JSON.
#[derive(Clone, Copy)]
struct F32(f32);

impl Serialize for F32 {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f32(self.0)
    }
}

impl<'de> Deserialize<'de> for F32 {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        f64::deserialize(d).map(|v| F32(v as f32))
    }
}

fn wire<const N: usize>(a: [f32; N]) -> [F32; N] {
    a.map(F32)
}

fn unwire<const N: usize>(a: [F32; N]) -> [f32; N] {
    a.map(|x| x.0)
}

#[derive(Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a view {\"pose\":..,\"fov\":[l,r,u,d]}"
)]
struct WireView {
    pose: WirePose,
    /// [angle_left, angle_right, angle_up, angle_down], radians.
    fov: [F32; 4],
}

#[derive(Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a pose {\"p\":[x,y,z],\"q\":[x,y,z,w]}"
)]
struct WirePose {
    p: [F32; 3],
    /// [x, y, z, w], as glam and OpenXR store it.
    q: [F32; 4],
}

#[derive(Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a hand object {\"tracked\":..,\"grip\":..,..}"
)]
struct WireHand {
    tracked: bool,
    grip: WirePose,
    aim: WirePose,
    grip_value: F32,
    trigger: F32,
    primary: bool,
    secondary: bool,
    menu: bool,
    /// The thumbstick click: required from version 2 on, absent (so false) in version 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    stick_click: Option<bool>,
    stick: [F32; 2],
}

impl From<&Pose> for WirePose {
    fn from(p: &Pose) -> Self {
        WirePose {
            p: wire(p.position.to_array()),
            q: wire(p.orientation.to_array()),
        }
    }
}

impl From<&WirePose> for Pose {
    fn from(w: &WirePose) -> Self {
        Pose {
            position: Vec3::from_array(unwire(w.p)),
            orientation: Quat::from_array(unwire(w.q)),
        }
    }
}

impl From<&FrameInput> for WireFrame {
    fn from(f: &FrameInput) -> Self {
        WireFrame {
            t: f.time,
            views: f.views.each_ref().map(|v| WireView {
                pose: (&v.pose).into(),
                fov: wire([
                    v.fov.angle_left,
                    v.fov.angle_right,
                    v.fov.angle_up,
                    v.fov.angle_down,
                ]),
            }),
            hands: f.hands.each_ref().map(|h| WireHand {
                tracked: h.tracked,
                grip: (&h.grip).into(),
                aim: (&h.aim).into(),
                grip_value: F32(h.buttons.grip),
                trigger: F32(h.buttons.trigger),
                primary: h.buttons.primary,
                secondary: h.buttons.secondary,
                menu: h.buttons.menu,
                stick_click: Some(h.buttons.stick_click),
                stick: wire(h.buttons.thumbstick.to_array()),
            }),
            joints: Some(f.joints.each_ref().map(|j| {
                j.as_ref().map(|j| WireJoints {
                    p: j.poses
                        .iter()
                        .map(|p| wire(p.position.to_array()))
                        .collect(),
                    q: j.poses
                        .iter()
                        .map(|p| wire(p.orientation.to_array()))
                        .collect(),
                    r: j.radii.iter().map(|&r| F32(r)).collect(),
                })
            })),
            gaze: Some(f.gaze.as_ref().map(WirePose::from)),
        }
    }
}

/// A hand's joints from the wire, or why not (lengths; the values are checked by check_frame).
fn joints_from_wire(i: usize, w: &WireJoints) -> Result<HandJoints, LineError> {
    let n = JOINT_COUNT;
    if w.p.len() != n || w.q.len() != n || w.r.len() != n {
        return Err(LineError::Schema(format!(
            "joints[{i}]: expected {n} positions, orientations and radii, found {}, {} and {}",
            w.p.len(),
            w.q.len(),
            w.r.len()
        )));
    }
    let mut poses = [Pose::IDENTITY; JOINT_COUNT];
    let mut radii = [0.0; JOINT_COUNT];
    for k in 0..n {
        poses[k] = Pose {
            position: Vec3::from_array(unwire(w.p[k])),
            orientation: Quat::from_array(unwire(w.q[k])),
        };
        radii[k] = w.r[k].0;
    }
    Ok(HandJoints { poses, radii })
}

impl From<&WireFrame> for FrameInput {
    fn from(w: &WireFrame) -> Self {
        FrameInput {
            time: w.t,
            views: w.views.each_ref().map(|v| View {
                pose: (&v.pose).into(),
                fov: {
                    let [angle_left, angle_right, angle_up, angle_down] = unwire(v.fov);
                    Fov {
                        angle_left,
                        angle_right,
                        angle_up,
                        angle_down,
                    }
                },
            }),
            hands: w.hands.each_ref().map(|h| HandInput {
                tracked: h.tracked,
                grip: (&h.grip).into(),
                aim: (&h.aim).into(),
                buttons: Buttons {
                    grip: h.grip_value.0,
                    trigger: h.trigger.0,
                    primary: h.primary,
                    secondary: h.secondary,
                    menu: h.menu,
                    stick_click: h.stick_click.unwrap_or(false),
                    thumbstick: Vec2::from_array(unwire(h.stick)),
                },
            }),
            // Filled in by parse_frame, which can say what is wrong with them.
            joints: [None; 2],
            gaze: w.gaze.as_ref().and_then(|g| g.as_ref().map(Pose::from)),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Validation, shared by reader and writer

fn check_header(h: WireHeader) -> Result<StreamHeader, LineError> {
    match h.format.as_deref() {
        Some(FORMAT) => {}
        found => {
            return Err(LineError::WrongFormat {
                found: found.map_or("missing".into(), |s| format!("{s:?}")),
            })
        }
    }
    let version = match h.version {
        None => return Err(LineError::MissingVersion),
        Some(0) => return Err(LineError::VersionZero),
        Some(v) if v > VERSION => return Err(LineError::NewerVersion { found: v }),
        Some(v) => v,
    };
    let fixed = |field: &'static str, found: Option<String>, expected: &'static str| match found {
        Some(s) if s == expected => Ok(s),
        found => Err(LineError::Unsupported {
            field,
            found: found.map_or("missing".into(), |s| format!("{s:?}")),
            expected,
        }),
    };
    Ok(StreamHeader {
        format: FORMAT.into(),
        version,
        units: fixed("units", h.units, UNITS)?,
        reference_space: fixed("reference_space", h.reference_space, REFERENCE_SPACE)?,
        view_configuration: fixed(
            "view_configuration",
            h.view_configuration,
            VIEW_CONFIGURATION,
        )?,
        source: h.source,
        description: h.description,
        volume_at: match h.volume_at.map(|v| v.map(|x| x.0)) {
            Some(v) => {
                finite(|| "volume_at".into(), &v)?;
                Some(v)
            }
            None => None,
        },
    })
}

fn finite(what: impl Fn() -> String, v: &[f32]) -> Result<(), LineError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(LineError::NonFinite { what: what() })
    }
}

fn in_range(what: impl Fn() -> String, v: f32, lo: f32, hi: f32) -> Result<(), LineError> {
    finite(&what, &[v])?;
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(LineError::OutOfRange {
            what: what(),
            value: v as f64,
            lo: lo as f64,
            hi: hi as f64,
        })
    }
}

/// A unit quaternion as it is, one within [`UNIT_TOLERANCE`] normalised, anything else refused.
fn unit_quat(what: impl Fn() -> String, q: Quat) -> Result<Quat, LineError> {
    finite(&what, &q.to_array())?;
    let length = q.length();
    if (length - 1.0).abs() <= UNIT_EXACT {
        Ok(q)
    } else if (length - 1.0).abs() <= UNIT_TOLERANCE {
        Ok(q / length)
    } else {
        Err(LineError::NotUnit {
            what: what(),
            length,
        })
    }
}

fn check_pose(what: &str, p: Pose) -> Result<Pose, LineError> {
    finite(|| format!("{what}.p"), &p.position.to_array())?;
    Ok(Pose {
        position: p.position,
        orientation: unit_quat(|| format!("{what}.q"), p.orientation)?,
    })
}

fn check_fov(what: &str, f: &Fov) -> Result<(), LineError> {
    let a = [f.angle_left, f.angle_right, f.angle_up, f.angle_down];
    finite(|| what.to_string(), &a)?;
    let bad = |reason| {
        Err(LineError::BadFov {
            what: what.to_string(),
            reason,
        })
    };
    let half_pi = std::f32::consts::FRAC_PI_2;
    if a.iter().any(|x| x.abs() >= half_pi) {
        return bad("every angle must be within (-pi/2, pi/2)");
    }
    if f.angle_left >= f.angle_right {
        return bad("angle_left must be less than angle_right");
    }
    if f.angle_down >= f.angle_up {
        return bad("angle_down must be less than angle_up");
    }
    Ok(())
}

/// Checks one frame the way the reader does, normalising nearly-unit quaternions; names the
/// offending value by its wire path (`hands[1].grip.q`).
pub(super) fn check_frame(
    mut f: FrameInput,
    previous: Option<f64>,
) -> Result<FrameInput, LineError> {
    let t = f.time;
    if !t.is_finite() {
        return Err(LineError::NonFinite { what: "t".into() });
    }
    if t < 0.0 {
        return Err(LineError::NegativeTime { t });
    }
    if let Some(previous) = previous {
        if t < previous {
            return Err(LineError::TimeBackwards { t, previous });
        }
    }
    for (i, v) in f.views.iter_mut().enumerate() {
        v.pose = check_pose(&format!("views[{i}].pose"), v.pose)?;
        check_fov(&format!("views[{i}].fov"), &v.fov)?;
    }
    for (i, h) in f.hands.iter_mut().enumerate() {
        h.grip = check_pose(&format!("hands[{i}].grip"), h.grip)?;
        h.aim = check_pose(&format!("hands[{i}].aim"), h.aim)?;
        let b = &h.buttons;
        in_range(|| format!("hands[{i}].grip_value"), b.grip, 0.0, 1.0)?;
        in_range(|| format!("hands[{i}].trigger"), b.trigger, 0.0, 1.0)?;
        in_range(|| format!("hands[{i}].stick[0]"), b.thumbstick.x, -1.0, 1.0)?;
        in_range(|| format!("hands[{i}].stick[1]"), b.thumbstick.y, -1.0, 1.0)?;
    }
    if let Some(g) = f.gaze {
        f.gaze = Some(check_pose("gaze", g)?);
    }
    for (i, j) in f.joints.iter_mut().enumerate() {
        let Some(j) = j else { continue };
        for k in 0..JOINT_COUNT {
            j.poses[k] = check_pose(&format!("joints[{i}] joint {k}"), j.poses[k])?;
            let r = j.radii[k];
            if !(r.is_finite() && r > 0.0) {
                return Err(LineError::OutOfRange {
                    what: format!("joints[{i}].r[{k}]"),
                    value: r as f64,
                    lo: f32::MIN_POSITIVE as f64,
                    hi: f32::MAX as f64,
                });
            }
        }
    }
    Ok(f)
}

// ---------------------------------------------------------------------------------------------
// Writer

/// Writes a pose stream: the header on construction, then one line per frame.
///
/// Crash policy: every frame is flushed to the OS as soon as it is written, straight into the
/// target file, so a crash or a killed process keeps every frame recorded so far (at worst the
/// last line is cut short, and the reader says so: [`LineError::Truncated`]). The alternative,
/// a temp file renamed on `finish`, would keep an older recording intact but lose the whole of
/// a take that crashed, which for a surgeon's session is the worse loss. There is no fsync:
/// a power cut may still lose what the OS had not written.
///
/// It refuses (`io::ErrorKind::InvalidInput`) any header or frame the reader would refuse, so
/// every stream it writes replays.
pub struct PoseStreamWriter<W: Write> {
    out: W,
    /// For messages, when the writer was made by [`PoseStreamWriter::create`].
    path: Option<PathBuf>,
    frames: usize,
    last_t: Option<f64>,
    line: Vec<u8>,
}

impl<W: Write> PoseStreamWriter<W> {
    /// Writes the header line to `out`.
    pub fn new(out: W, header: &StreamHeader) -> io::Result<Self> {
        Self::with_path(out, header, None)
    }

    fn with_path(mut out: W, header: &StreamHeader, path: Option<PathBuf>) -> io::Result<Self> {
        let wire = WireHeader {
            format: Some(header.format.clone()),
            version: Some(header.version),
            units: Some(header.units.clone()),
            reference_space: Some(header.reference_space.clone()),
            view_configuration: Some(header.view_configuration.clone()),
            source: header.source.clone(),
            description: header.description.clone(),
            volume_at: header.volume_at.map(|v| v.map(F32)),
        };
        let invalid = |e: LineError| invalid_input(path.as_deref(), &format!("header: {e}"));
        let header = check_header(wire).map_err(invalid)?;
        if header.version != VERSION {
            // Frames are written in this version's format only.
            return Err(invalid_input(
                path.as_deref(),
                &format!(
                    "header: this build writes version {VERSION} streams, not version {}",
                    header.version
                ),
            ));
        }
        let mut line = serde_json::to_vec(&header).map_err(io::Error::other)?;
        line.push(b'\n');
        out.write_all(&line)
            .and_then(|_| out.flush())
            .map_err(|e| with_path(path.as_deref(), e))?;
        Ok(PoseStreamWriter {
            out,
            path,
            frames: 0,
            last_t: None,
            line,
        })
    }

    /// Appends one frame and flushes it. Quaternions within [`UNIT_TOLERANCE`] of unit length
    /// are written normalised.
    pub fn write_frame(&mut self, frame: &FrameInput) -> io::Result<()> {
        let frame = check_frame(*frame, self.last_t).map_err(|e| {
            let n = self.frames;
            invalid_input(
                self.path.as_deref(),
                &format!("frame {n} (line {}): {e}", n + 2),
            )
        })?;
        self.line.clear();
        serde_json::to_writer(&mut self.line, &WireFrame::from(&frame))
            .map_err(io::Error::other)?;
        self.line.push(b'\n');
        let res = self
            .out
            .write_all(&self.line)
            .and_then(|_| self.out.flush());
        res.map_err(|e| with_path(self.path.as_deref(), e))?;
        self.frames += 1;
        self.last_t = Some(frame.time);
        Ok(())
    }

    /// How many frames have been written.
    pub fn frames_written(&self) -> usize {
        self.frames
    }

    /// Flushes and hands back the underlying writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.out
            .flush()
            .map_err(|e| with_path(self.path.as_deref(), e))?;
        Ok(self.out)
    }
}

impl PoseStreamWriter<BufWriter<File>> {
    /// Creates (or truncates) `path` and writes the header. See the type's docs for what
    /// survives a crash. Error messages name the file.
    pub fn create(path: &Path, header: &StreamHeader) -> io::Result<Self> {
        let file = File::create(path).map_err(|e| with_path(Some(path), e))?;
        Self::with_path(BufWriter::new(file), header, Some(path.to_path_buf()))
    }
}

fn with_path(path: Option<&Path>, e: io::Error) -> io::Error {
    match path {
        Some(p) => io::Error::new(e.kind(), format!("{}: {e}", p.display())),
        None => e,
    }
}

fn invalid_input(path: Option<&Path>, msg: &str) -> io::Error {
    with_path(path, io::Error::new(io::ErrorKind::InvalidInput, msg))
}

// ---------------------------------------------------------------------------------------------
// Reader

/// Reads a pose stream frame by frame; the header is read and checked on construction.
///
/// Yields `Err` at the first bad line and then ends: a stream with a bad line in the middle is
/// not replayed past it, since the frames after it would be taken out of context.
pub struct PoseStreamReader<R> {
    input: R,
    path: PathBuf,
    header: StreamHeader,
    line_no: usize,
    last_t: Option<f64>,
    buf: String,
    done: bool,
}

impl PoseStreamReader<BufReader<File>> {
    /// Opens `path` and reads its header.
    pub fn open(path: &Path) -> Result<Self, StreamError> {
        let file = File::open(path).map_err(|source| StreamError::Open {
            path: path.to_path_buf(),
            source,
        })?;
        Self::new(BufReader::new(file), path)
    }
}

impl<R: BufRead> PoseStreamReader<R> {
    /// Reads the header from `input`; `name` stands for the file in messages.
    pub fn new(input: R, name: impl Into<PathBuf>) -> Result<Self, StreamError> {
        let mut reader = PoseStreamReader {
            input,
            path: name.into(),
            header: StreamHeader::default(),
            line_no: 0,
            last_t: None,
            buf: String::new(),
            done: false,
        };
        let Some(terminated) = reader.next_content_line()? else {
            return Err(StreamError::NoHeader { path: reader.path });
        };
        let header = serde_json::from_str::<WireHeader>(reader.buf.trim())
            .map_err(|e| json_error(&e, terminated))
            .and_then(check_header)
            .map_err(|problem| reader.line_error(problem))?;
        reader.header = header;
        Ok(reader)
    }

    pub fn header(&self) -> &StreamHeader {
        &self.header
    }

    /// The file name used in messages.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn line_error(&self, problem: LineError) -> StreamError {
        StreamError::Line {
            path: self.path.clone(),
            line: self.line_no,
            problem,
        }
    }

    /// Reads up to the next line that is neither blank nor a comment into `buf`. Returns
    /// whether it ended with a newline (a last line without one may be a cut-off recording),
    /// or None at the end.
    fn next_content_line(&mut self) -> Result<Option<bool>, StreamError> {
        loop {
            self.buf.clear();
            let n = self
                .input
                .read_line(&mut self.buf)
                .map_err(|source| StreamError::Read {
                    path: self.path.clone(),
                    line: self.line_no + 1,
                    source,
                })?;
            if n == 0 {
                return Ok(None);
            }
            self.line_no += 1;
            let text = self.buf.trim();
            if text.is_empty() || text.starts_with('#') {
                continue;
            }
            return Ok(Some(self.buf.ends_with('\n')));
        }
    }

    fn next_frame(&mut self) -> Result<Option<FrameInput>, StreamError> {
        let Some(terminated) = self.next_content_line()? else {
            return Ok(None);
        };
        let version = self.header.version;
        let frame = parse_frame(self.buf.trim(), terminated, self.last_t, version)
            .map_err(|problem| self.line_error(problem))?;
        self.last_t = Some(frame.time);
        Ok(Some(frame))
    }
}

impl<R: BufRead> Iterator for PoseStreamReader<R> {
    type Item = Result<FrameInput, StreamError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        match self.next_frame() {
            Ok(Some(frame)) => Some(Ok(frame)),
            Ok(None) => {
                self.done = true;
                None
            }
            Err(e) => {
                self.done = true;
                Some(Err(e))
            }
        }
    }
}

/// Reads a whole stream: its header and every frame, or the first error.
pub fn read_stream(path: &Path) -> Result<(StreamHeader, Vec<FrameInput>), StreamError> {
    let reader = PoseStreamReader::open(path)?;
    let header = reader.header().clone();
    let frames = reader.collect::<Result<Vec<_>, _>>()?;
    Ok((header, frames))
}

fn parse_frame(
    text: &str,
    terminated: bool,
    previous: Option<f64>,
    version: u64,
) -> Result<FrameInput, LineError> {
    let wire: WireFrame = serde_json::from_str(text).map_err(|e| json_error(&e, terminated))?;
    // The fields a version added are required from it on and unknown before it.
    for (i, h) in wire.hands.iter().enumerate() {
        match (version, h.stick_click) {
            (1, Some(_)) => {
                return Err(LineError::Schema(format!(
                    "hands[{i}].stick_click is a version 2 field, but the header says version 1"
                )))
            }
            (2.., None) => {
                return Err(LineError::Schema(format!(
                    "hands[{i}]: missing field `stick_click` (required from version 2 on)"
                )))
            }
            _ => {}
        }
    }
    let mut frame = FrameInput::from(&wire);
    match (version, &wire.joints) {
        (1 | 2, Some(_)) => {
            return Err(LineError::Schema(format!(
                "joints is a version 3 field, but the header says version {version}"
            )))
        }
        (3.., None) => {
            return Err(LineError::Schema(
                "missing field `joints` (required from version 3 on; null for a hand without)"
                    .into(),
            ))
        }
        (_, Some(js)) => {
            for (i, j) in js.iter().enumerate() {
                frame.joints[i] = j.as_ref().map(|j| joints_from_wire(i, j)).transpose()?;
            }
        }
        _ => {}
    }
    match (version, &wire.gaze) {
        (1..=3, Some(_)) => {
            return Err(LineError::Schema(format!(
                "gaze is a version 4 field, but the header says version {version}"
            )))
        }
        (4.., None) => {
            return Err(LineError::Schema(
                "missing field `gaze` (required from version 4 on; null without eye tracking)"
                    .into(),
            ))
        }
        _ => {}
    }
    check_frame(frame, previous)
}

/// serde_json's message without its position (always "line 1" here, which would contradict
/// the stream's line number), keeping the column.
fn json_error(e: &serde_json::Error, terminated: bool) -> LineError {
    use serde_json::error::Category;
    let full = e.to_string();
    let suffix = format!(" at line {} column {}", e.line(), e.column());
    let msg = match full.strip_suffix(&suffix) {
        Some(m) if e.column() > 0 => format!("{m} (column {})", e.column()),
        Some(m) => m.to_string(),
        None => full.clone(),
    };
    match e.classify() {
        Category::Eof if !terminated => LineError::Truncated,
        Category::Data => LineError::Schema(msg),
        _ => LineError::Syntax(msg),
    }
}

// ---------------------------------------------------------------------------------------------
// Replay timing

/// When to present each frame of a replay: `(index, due)` where `due` is the offset from the
/// start of the replay (frame 0 is due at zero), or None when replaying as fast as possible.
///
/// It does not sleep, so it is testable and the caller chooses the clock:
///
/// ```no_run
/// # use cao_xr::input::{replay_schedule, FrameInput};
/// # let frames: Vec<FrameInput> = vec![];
/// use std::time::Instant;
/// let start = Instant::now();
/// for (i, due) in replay_schedule(&frames, true) {
///     if let Some(wait) = due.and_then(|d| (start + d).checked_duration_since(Instant::now())) {
///         std::thread::sleep(wait);
///     }
///     // render frames[i]
/// }
/// ```
///
/// No frame is skipped: a caller running late just does not sleep until it has caught up.
pub fn replay_schedule(
    frames: &[FrameInput],
    realtime: bool,
) -> impl Iterator<Item = (usize, Option<Duration>)> + '_ {
    let t0 = frames.first().map_or(0.0, |f| f.time);
    frames.iter().enumerate().map(move |(i, f)| {
        let due = realtime
            .then(|| Duration::try_from_secs_f64((f.time - t0).max(0.0)).unwrap_or_default());
        (i, due)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::input::{LEFT, RIGHT};
    use crate::rng::SplitMix64;
    use crate::space::{symmetric_fov, DEFAULT_IPD};
    use std::io::Cursor;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Test data from the scripts' SplitMix64.
    struct Rng(SplitMix64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0.next_u64()
        }
        fn unit(&mut self) -> f32 {
            (self.next() >> 40) as f32 / (1u64 << 24) as f32
        }
        fn range(&mut self, lo: f32, hi: f32) -> f32 {
            lo + (hi - lo) * self.unit()
        }
        fn vec3(&mut self, r: f32) -> Vec3 {
            Vec3::new(self.range(-r, r), self.range(-r, r), self.range(-r, r))
        }
        fn quat(&mut self) -> Quat {
            let axis = (self.vec3(1.0) + Vec3::splat(1e-3)).normalize();
            let q = Quat::from_axis_angle(axis, self.range(-3.0, 3.0));
            unit_quat(String::new, q).unwrap()
        }
        fn pose(&mut self) -> Pose {
            Pose {
                position: self.vec3(2.0),
                orientation: self.quat(),
            }
        }
    }

    fn temp_path(name: &str) -> PathBuf {
        static N: AtomicUsize = AtomicUsize::new(0);
        let n = N.fetch_add(1, Ordering::Relaxed);
        std::env::temp_dir().join(format!("cao-xr-stream-{}-{n}-{name}", std::process::id()))
    }

    fn random_frames(n: usize, seed: u64) -> Vec<FrameInput> {
        let mut rng = Rng(SplitMix64(seed));
        let mut t = 0.0f64;
        (0..n)
            .map(|i| {
                // Mix "nice" times (i/90) and arbitrary 17-digit ones.
                t = if i % 2 == 0 {
                    i as f64 / 90.0
                } else {
                    t + (rng.next() >> 11) as f64 / (1u64 << 53) as f64 * 0.02
                };
                let head = rng.pose();
                let hand = |rng: &mut Rng, tracked| HandInput {
                    tracked,
                    grip: rng.pose(),
                    aim: rng.pose(),
                    buttons: Buttons {
                        grip: rng.unit(),
                        trigger: rng.unit(),
                        primary: rng.next() & 1 == 1,
                        secondary: rng.next() & 1 == 1,
                        menu: rng.next() & 1 == 1,
                        stick_click: rng.next() & 1 == 1,
                        thumbstick: Vec2::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)),
                    },
                };
                FrameInput {
                    time: t,
                    views: FrameInput::head_views(
                        head,
                        DEFAULT_IPD,
                        symmetric_fov(rng.range(0.3, 0.9)),
                    ),
                    hands: [hand(&mut rng, i % 3 != 0), hand(&mut rng, true)],
                    joints: [
                        None,
                        (i % 2 == 0).then(|| super::super::hands::synthetic_hand(head, 0.03, 0.05)),
                    ],
                    gaze: (i % 3 == 1).then(|| Pose {
                        position: head.position,
                        orientation: head.orientation
                            * Quat::from_rotation_y(rng.range(-0.4, 0.4))
                            * Quat::from_rotation_x(rng.range(-0.3, 0.3)),
                    }),
                }
            })
            .collect()
    }

    fn header_line() -> String {
        serde_json::to_string(&StreamHeader::new("test", "unit test")).unwrap()
    }

    fn frame_line(f: &FrameInput) -> String {
        serde_json::to_string(&WireFrame::from(f)).unwrap()
    }

    fn read_str(text: &str) -> Result<(StreamHeader, Vec<FrameInput>), StreamError> {
        let r = PoseStreamReader::new(Cursor::new(text.as_bytes()), "mem.jsonl")?;
        let h = r.header().clone();
        Ok((h, r.collect::<Result<Vec<_>, _>>()?))
    }

    fn err_str(text: &str) -> StreamError {
        read_str(text).expect_err("should be refused")
    }

    #[test]
    fn round_trip_is_exact_in_memory_and_on_disk() {
        let frames = random_frames(200, 7);
        let header = StreamHeader::new("desktop", "round trip, with \"quotes\" and ünïcode");
        let mut w = PoseStreamWriter::new(Vec::new(), &header).unwrap();
        for f in &frames {
            w.write_frame(f).unwrap();
        }
        assert_eq!(w.frames_written(), frames.len());
        let bytes = w.finish().unwrap();
        let r = PoseStreamReader::new(Cursor::new(&bytes), "mem").unwrap();
        assert_eq!(r.header(), &header);
        let back: Vec<FrameInput> = r.map(Result::unwrap).collect();
        assert_eq!(back, frames);

        let path = temp_path("round-trip.jsonl");
        let mut w = PoseStreamWriter::create(&path, &header).unwrap();
        for f in &frames {
            w.write_frame(f).unwrap();
        }
        w.finish().unwrap();
        let (h, back) = read_stream(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        assert_eq!(h, header);
        assert_eq!(back, frames);
    }

    #[test]
    fn the_volume_placement_round_trips_and_a_non_finite_one_is_refused() {
        let header = StreamHeader {
            volume_at: Some([0.125, 1.3, -0.55]),
            ..StreamHeader::new("xr", "placed")
        };
        let frames = random_frames(3, 5);
        let mut w = PoseStreamWriter::new(Vec::new(), &header).unwrap();
        for f in &frames {
            w.write_frame(f).unwrap();
        }
        let bytes = w.finish().unwrap();
        let (h, back) = read_str(std::str::from_utf8(&bytes).unwrap()).unwrap();
        assert_eq!(h, header);
        assert_eq!(back, frames);
        // Streams without it (every older one) read None.
        assert_eq!(read_str(&header_line()).unwrap().0.volume_at, None);
        let bad = header_line().replacen('{', "{\"volume_at\":[1e39,0,0],", 1);
        let e = err_str(&bad).to_string();
        assert!(e.contains("volume_at"), "{e}");
    }

    #[test]
    fn floats_survive_the_text_bit_for_bit() {
        // f32 fields go through serde_json (decimal -> f64 -> f32); t through str::parse.
        let mut rng = Rng(SplitMix64(99));
        let zero_frame = random_frames(1, 1)[0];
        for i in 0..20_000 {
            let bits = rng.next();
            // Any finite f32 with a sane exponent (about 1e-12 .. 1e12).
            let x = f32::from_bits(
                (bits as u32 & 0x807f_ffff) | (((bits >> 32) as u32 % 80 + 87) << 23),
            );
            let s = serde_json::to_string(&x).unwrap();
            let y: f32 = serde_json::from_str(&s).unwrap();
            assert_eq!(x.to_bits(), y.to_bits(), "{x:e} written as {s}");
            let t = f64::from_bits((bits >> 12) | (((i % 40) as u64 + 1003) << 52));
            let mut f = zero_frame;
            f.time = t;
            let back = parse_frame(&frame_line(&f), true, None, VERSION).unwrap();
            assert_eq!(back.time.to_bits(), t.to_bits(), "{t:e}");
        }
    }

    #[test]
    fn comments_and_blank_lines_are_skipped() {
        let frames = random_frames(3, 3);
        let text = format!(
            "# recorded by hand\n\n{}\n  # a comment\n{}\r\n\n   \n{}\n# end\n{}",
            header_line(),
            frame_line(&frames[0]),
            frame_line(&frames[1]),
            frame_line(&frames[2]),
        );
        let (_, back) = read_str(&text).unwrap();
        assert_eq!(back, frames);
    }

    #[test]
    fn a_bad_line_is_named_by_file_and_line() {
        let frames = random_frames(3, 4);
        let path = temp_path("malformed.jsonl");
        let text = format!(
            "{}\n{}\n# comment\n{{\"t\": 1.0, \"views\": [}}\n{}\n",
            header_line(),
            frame_line(&frames[0]),
            frame_line(&frames[1]),
        );
        std::fs::write(&path, text).unwrap();
        let err = read_stream(&path).unwrap_err();
        let msg = err.to_string();
        let _ = std::fs::remove_file(&path);
        assert!(msg.contains(&path.display().to_string()), "{msg}");
        assert!(msg.contains("line 4"), "{msg}");
        assert!(matches!(err.problem(), Some(LineError::Syntax(_))), "{msg}");
        assert_eq!(err.line(), Some(4));

        // The streaming reader gives the good frame first, then the error, then ends.
        std::fs::write(
            &path,
            format!("{}\n{}\nnot json\n", header_line(), frame_line(&frames[0])),
        )
        .unwrap();
        let mut r = PoseStreamReader::open(&path).unwrap();
        assert!(r.next().unwrap().is_ok());
        let e = r.next().unwrap().unwrap_err();
        assert!(e.to_string().contains("line 3"), "{e}");
        assert!(r.next().is_none());
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn missing_and_unknown_fields_are_named() {
        let f = random_frames(1, 5)[0];
        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        v["hands"][1].as_object_mut().unwrap().remove("trigger");
        let msg = err_str(&format!("{}\n{v}\n", header_line())).to_string();
        assert!(msg.contains("mem.jsonl, line 2"), "{msg}");
        assert!(msg.contains("missing field `trigger`"), "{msg}");

        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        v["hands"][0]["trigger_value"] = 0.5.into();
        let msg = err_str(&format!("{}\n{v}\n", header_line())).to_string();
        assert!(msg.contains("unknown field `trigger_value`"), "{msg}");

        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        v["views"].as_array_mut().unwrap().pop();
        let msg = err_str(&format!("{}\n{v}\n", header_line())).to_string();
        assert!(msg.contains("line 2") && msg.contains("length"), "{msg}");
    }

    #[test]
    fn versions_newer_than_2_missing_or_zero_are_refused_clearly() {
        let frame = frame_line(&random_frames(1, 6)[0]);
        let with = |version: &str| {
            let mut h: serde_json::Value = serde_json::from_str(&header_line()).unwrap();
            match version {
                "none" => {
                    h.as_object_mut().unwrap().remove("version");
                }
                v => h["version"] = serde_json::from_str(v).unwrap(),
            }
            err_str(&format!("{h}\n{frame}\n"))
        };
        let e = with("5");
        assert_eq!(e.problem(), Some(&LineError::NewerVersion { found: 5 }));
        let msg = e.to_string();
        assert!(msg.contains("line 1"), "{msg}");
        assert!(
            msg.contains("version 5") && msg.contains("version 4"),
            "{msg}"
        );
        assert_eq!(with("none").problem(), Some(&LineError::MissingVersion));
        assert!(with("none").to_string().contains("no \"version\""));
        assert_eq!(with("0").problem(), Some(&LineError::VersionZero));

        // And the writer will not produce one either.
        for v in [1, 3, 5] {
            let mut h = StreamHeader::new("x", "");
            h.version = v;
            let e = PoseStreamWriter::new(Vec::new(), &h).err().unwrap();
            assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "version {v}");
        }
    }

    #[test]
    fn version_1_streams_read_without_the_stick_click_and_version_2_requires_it() {
        let f = random_frames(1, 9)[0];
        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        assert!(v["hands"][1]["stick_click"].is_boolean(), "{v}");
        let header = |version: u64| {
            let mut h: serde_json::Value = serde_json::from_str(&header_line()).unwrap();
            h["version"] = version.into();
            h
        };
        // A version 1 frame has no stick_click (nor joints, nor gaze): it reads as not pressed.
        v.as_object_mut().unwrap().remove("joints");
        v.as_object_mut().unwrap().remove("gaze");
        for h in v["hands"].as_array_mut().unwrap() {
            h.as_object_mut().unwrap().remove("stick_click");
        }
        let (h1, frames) = read_str(&format!("{}\n{v}\n", header(1))).unwrap();
        assert_eq!(h1.version, 1);
        assert!(frames[0].hands.iter().all(|h| !h.buttons.stick_click));
        assert_eq!(frames[0].hands[1].buttons.menu, f.hands[1].buttons.menu);
        // Version 2 requires it, and version 1 does not know it.
        let e = err_str(&format!("{}\n{v}\n", header(2))).to_string();
        assert!(e.contains("line 2") && e.contains("stick_click"), "{e}");
        let v3 = frame_line(&f);
        let e = err_str(&format!("{}\n{v3}\n", header(1))).to_string();
        assert!(e.contains("version 2 field"), "{e}");
    }

    #[test]
    fn version_3_carries_the_joints_exactly_and_earlier_versions_do_not_know_them() {
        let frames = random_frames(4, 11);
        assert!(frames[0].joints[1].is_some() && frames[1].joints[1].is_none());
        let text = format!("{}\n{}\n", header_line(), frame_line(&frames[0]));
        let (_, back) = read_str(&text).unwrap();
        assert_eq!(back[0], frames[0], "joints round trip bit for bit");
        // A version 3 frame: no gaze.
        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&frames[0])).unwrap();
        v.as_object_mut().unwrap().remove("gaze");
        let with_header = |version: u64, v: &serde_json::Value| {
            let mut h: serde_json::Value = serde_json::from_str(&header_line()).unwrap();
            h["version"] = version.into();
            format!("{h}\n{v}\n")
        };
        let e = err_str(&with_header(2, &v)).to_string();
        assert!(e.contains("joints is a version 3 field"), "{e}");
        v["joints"][1]["r"].as_array_mut().unwrap().pop();
        let e = err_str(&with_header(3, &v)).to_string();
        assert!(e.contains("joints[1]") && e.contains("26"), "{e}");
        v["joints"][1]["r"]
            .as_array_mut()
            .unwrap()
            .push((-1.0).into());
        let e = err_str(&with_header(3, &v)).to_string();
        assert!(e.contains("joints[1].r[25]"), "{e}");
        v.as_object_mut().unwrap().remove("joints");
        let e = err_str(&with_header(3, &v)).to_string();
        assert!(e.contains("missing field `joints`"), "{e}");
    }

    #[test]
    fn version_4_carries_the_gaze_exactly_and_earlier_versions_do_not_know_it() {
        let frames = random_frames(3, 12);
        assert!(frames[1].gaze.is_some() && frames[0].gaze.is_none());
        let text = format!(
            "{}\n{}\n{}\n",
            header_line(),
            frame_line(&frames[0]),
            frame_line(&frames[1])
        );
        let (_, back) = read_str(&text).unwrap();
        assert_eq!(back[..], frames[..2], "the gaze round trips bit for bit");
        let with_header = |version: u64, v: &serde_json::Value| {
            let mut h: serde_json::Value = serde_json::from_str(&header_line()).unwrap();
            h["version"] = version.into();
            format!("{h}\n{v}\n")
        };
        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&frames[1])).unwrap();
        let e = err_str(&with_header(3, &v)).to_string();
        assert!(e.contains("gaze is a version 4 field"), "{e}");
        v["gaze"]["q"][3] = 2.0.into();
        let e = err_str(&with_header(4, &v)).to_string();
        assert!(e.contains("gaze.q"), "{e}");
        v.as_object_mut().unwrap().remove("gaze");
        let e = err_str(&with_header(4, &v)).to_string();
        assert!(e.contains("missing field `gaze`"), "{e}");
        // A null gaze is a frame without eye tracking.
        v["gaze"] = serde_json::Value::Null;
        let (_, back) = read_str(&with_header(4, &v)).unwrap();
        assert_eq!(back[0].gaze, None);
    }

    #[test]
    fn wrong_format_or_space_is_refused() {
        let frame = frame_line(&random_frames(1, 8)[0]);
        // A file of frames without a header.
        let e = err_str(&format!("{frame}\n"));
        assert!(
            matches!(e.problem(), Some(LineError::WrongFormat { .. })),
            "{e}"
        );
        assert!(e.to_string().contains("format"), "{e}");
        let h = header_line().replace(FORMAT, "cao-xr-pose-steam");
        let e = err_str(&format!("{h}\n{frame}\n"));
        assert!(e.to_string().contains("\"cao-xr-pose-steam\""), "{e}");
        let h = header_line().replace("STAGE", "LOCAL");
        let e = err_str(&format!("{h}\n{frame}\n"));
        assert!(e.to_string().contains("reference_space"), "{e}");
        let e = err_str("# only comments\n\n");
        assert!(matches!(e, StreamError::NoHeader { .. }), "{e}");
        assert!(e.to_string().starts_with("mem.jsonl: empty stream"), "{e}");
    }

    #[test]
    fn time_going_backwards_is_refused() {
        let mut frames = random_frames(3, 9);
        frames[0].time = 1.0;
        frames[1].time = 1.0; // equal is fine (a repeated display time)
        frames[2].time = 0.5;
        let text = format!(
            "{}\n{}\n{}\n{}\n",
            header_line(),
            frame_line(&frames[0]),
            frame_line(&frames[1]),
            frame_line(&frames[2])
        );
        let e = err_str(&text);
        assert_eq!(
            e.problem(),
            Some(&LineError::TimeBackwards {
                t: 0.5,
                previous: 1.0
            })
        );
        assert!(e.to_string().contains("line 4: time goes backwards"), "{e}");

        let mut w = PoseStreamWriter::new(Vec::new(), &StreamHeader::new("x", "")).unwrap();
        w.write_frame(&frames[0]).unwrap();
        w.write_frame(&frames[1]).unwrap();
        let e = w.write_frame(&frames[2]).unwrap_err();
        assert!(e.to_string().contains("frame 2 (line 4)"), "{e}");
    }

    #[test]
    fn quaternions_are_normalised_only_when_nearly_unit() {
        let mut f = random_frames(1, 10)[0];
        f.hands[RIGHT].grip.orientation = Quat::from_xyzw(0.0, 0.0, 0.0, 1.0005);
        let (_, back) = read_str(&format!("{}\n{}\n", header_line(), frame_line(&f))).unwrap();
        assert_eq!(back[0].hands[RIGHT].grip.orientation, Quat::IDENTITY);

        f.hands[RIGHT].grip.orientation = Quat::from_xyzw(0.0, 0.0, 0.0, 1.01);
        let e = err_str(&format!("{}\n{}\n", header_line(), frame_line(&f)));
        let msg = e.to_string();
        assert!(
            msg.contains("hands[1].grip.q is not a unit quaternion"),
            "{msg}"
        );

        // Zero quaternion (what an untracked OpenXR pose may hold).
        f.hands[RIGHT].grip.orientation = Quat::from_xyzw(0.0, 0.0, 0.0, 0.0);
        assert!(read_str(&format!("{}\n{}\n", header_line(), frame_line(&f))).is_err());
    }

    #[test]
    fn non_finite_and_out_of_range_values_are_refused() {
        let f = random_frames(1, 11)[0];
        let text = |v: &serde_json::Value| format!("{}\n{v}\n", header_line());
        // 1e39 is a finite JSON number but overflows f32.
        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        v["views"][0]["pose"]["p"][1] = serde_json::from_str("1e39").unwrap();
        let msg = err_str(&text(&v)).to_string();
        assert!(
            msg.contains("views[0].pose.p is not a finite number"),
            "{msg}"
        );
        // NaN is not JSON at all.
        let line = frame_line(&f).replacen("\"t\":", "\"t\":NaN,\"x\":", 1);
        let e = err_str(&format!("{}\n{line}\n", header_line()));
        assert!(matches!(e.problem(), Some(LineError::Syntax(_))), "{e}");

        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        v["hands"][0]["trigger"] = 1.5.into();
        let msg = err_str(&text(&v)).to_string();
        assert!(
            msg.contains("hands[0].trigger = 1.5 is outside 0..=1"),
            "{msg}"
        );

        let mut v: serde_json::Value = serde_json::from_str(&frame_line(&f)).unwrap();
        v["views"][1]["fov"] = serde_json::json!([0.5, -0.5, 0.5, -0.5]);
        let msg = err_str(&text(&v)).to_string();
        assert!(msg.contains("views[1].fov is not a field of view"), "{msg}");

        let mut w = PoseStreamWriter::new(Vec::new(), &StreamHeader::new("x", "")).unwrap();
        let mut bad = f;
        bad.hands[LEFT].aim.position.x = f32::NAN;
        let e = w.write_frame(&bad).unwrap_err();
        assert!(e.to_string().contains("hands[0].aim.p"), "{e}");
        assert_eq!(w.frames_written(), 0);
    }

    #[test]
    fn a_cut_off_last_line_says_so() {
        let frames = random_frames(2, 12);
        let last = frame_line(&frames[1]);
        let text = format!(
            "{}\n{}\n{}",
            header_line(),
            frame_line(&frames[0]),
            &last[..last.len() / 2]
        );
        let e = err_str(&text);
        assert_eq!(e.problem(), Some(&LineError::Truncated), "{e}");
        assert!(e.to_string().contains("line 3"), "{e}");
    }

    #[test]
    fn every_frame_is_on_disk_as_soon_as_it_is_written() {
        let frames = random_frames(3, 13);
        let path = temp_path("flush.jsonl");
        let mut w = PoseStreamWriter::create(&path, &StreamHeader::new("xr", "")).unwrap();
        w.write_frame(&frames[0]).unwrap();
        w.write_frame(&frames[1]).unwrap();
        // Read while the writer is still open (as after a crash, before any finish/drop).
        let (_, back) = read_stream(&path).unwrap();
        assert_eq!(back, &frames[..2]);
        drop(w);
        let _ = std::fs::remove_file(&path);

        let missing = temp_path("no-such-dir").join("x.jsonl");
        let e = PoseStreamWriter::create(&missing, &StreamHeader::new("xr", ""))
            .err()
            .unwrap();
        assert!(e.to_string().contains("no-such-dir"), "{e}");
        let e = read_stream(&missing).unwrap_err();
        assert!(matches!(e, StreamError::Open { .. }), "{e}");
        assert!(e.to_string().contains("x.jsonl"), "{e}");
    }

    #[test]
    fn replay_schedule_follows_recorded_time() {
        let mut frames = random_frames(4, 14);
        for (f, t) in frames.iter_mut().zip([10.0, 10.5, 10.5, 12.25]) {
            f.time = t;
        }
        let fast: Vec<_> = replay_schedule(&frames, false).collect();
        assert_eq!(fast, vec![(0, None), (1, None), (2, None), (3, None)]);
        let real: Vec<_> = replay_schedule(&frames, true)
            .map(|(_, d)| d.unwrap())
            .collect();
        assert_eq!(
            real,
            [0.0, 0.5, 0.5, 2.25].map(Duration::from_secs_f64).to_vec()
        );
        assert_eq!(replay_schedule(&[], true).count(), 0);
    }
}
