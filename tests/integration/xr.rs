//! The OpenXR path against a real runtime: Monado (null compositor, simulated HMD and two
//! simulated controllers) in a Debian trixie root built by scripts/xr-root.sh, driven by
//! scripts/xr-session.sh. One session of 300 frames with the right controller holding a
//! carving tool; the session must reach FOCUSED, submit every frame, end cleanly, record the
//! controllers as FrameInput, submit depth with every projection view, and neither the Vulkan nor the OpenXR validation layer may
//! report an error.
//!
//! A second session runs Monado's `remote` driver instead, whose controllers carry simulated
//! hands: a client in the test moves the right hand into the volume and pinches, the joints drive
//! cao-xr, the pinch carves, and the recording holds the joints and replays the carve.
//!
//! Needs root (chroot, mounts) and, the first time, Debian's archive. Without them the test is
//! skipped, unless CAO_XR_REQUIRE_XR=1 (scripts/test.sh sets it), which makes it fail instead.

use crate::common;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Mutex, MutexGuard};

const FRAMES: usize = 300;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// One Monado at a time: each session brings up a runtime with a lavapipe compositor, and
/// several at once on a loaded 2-core machine pushed start-up past the script's wait in CI.
static ONE_RUNTIME: Mutex<()> = Mutex::new(());

/// The built root, building it if needed, and the right to run a session in it; None (skip)
/// when it cannot be had and is not required.
fn xr_root() -> Option<(PathBuf, MutexGuard<'static, ()>)> {
    // A failed session poisons the lock; the next one may still run.
    let turn = ONE_RUNTIME.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new(repo().join("scripts/xr-root.sh")).output();
    let why = match out {
        Ok(o) if o.status.success() => {
            let path = String::from_utf8_lossy(&o.stdout).trim().to_string();
            return Some((PathBuf::from(path), turn));
        }
        Ok(o) => format!(
            "scripts/xr-root.sh failed ({}):\n{}",
            o.status,
            String::from_utf8_lossy(&o.stderr)
        ),
        Err(e) => format!("cannot run scripts/xr-root.sh: {e}"),
    };
    let why = format!("the Monado test root is not available: {why}");
    common::require_or_skip("CAO_XR_REQUIRE_XR", false, &why);
    None
}

/// scripts/xr-session.sh in `root` with the cao-xr under test, and its fresh output folder
/// (CARGO_TARGET_TMPDIR/xr-NAME-PID); the caller adds cao-xr's arguments.
fn session(root: &Path, name: &str) -> (Command, PathBuf) {
    let out =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("xr-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let mut cmd = Command::new(repo().join("scripts/xr-session.sh"));
    cmd.arg(root).arg(env!("CARGO_BIN_EXE_cao-xr")).arg(&out);
    (cmd, out)
}

/// Neither validation layer reported anything: Vulkan's (on, and silent) and OpenXR's (the
/// debug messenger and the core validation layer's log in `out`).
fn assert_validation_silent(out: &Path, stderr: &str, context: &str) {
    assert!(
        stderr.contains("(validation on)"),
        "Vulkan validation was off\n{context}"
    );
    assert!(
        !stderr.contains("vulkan validation:"),
        "Vulkan validation reported\n{context}"
    );
    assert!(
        !stderr.contains("openxr validation:"),
        "the OpenXR debug messenger reported\n{context}"
    );
    let xr_val = std::fs::read_to_string(out.join("xr-validation.txt"))
        .expect("the OpenXR core validation layer wrote no log (was it enabled?)");
    assert!(
        xr_val.contains("Core Validation Layer is initialized"),
        "{xr_val}"
    );
    assert!(
        !xr_val.contains("VALID_ERROR"),
        "OpenXR core validation reported errors:\n{xr_val}"
    );
}

#[test]
fn monado_session_reaches_focused_submits_frames_and_records_the_hands() {
    let Some((root, _turn)) = xr_root() else {
        return;
    };
    let frames = FRAMES.to_string();
    let (mut session, out) = session(&root, "focused");
    let run = session
        .args(["phantom:32", "--rays", "6", "--size", "96x96", "--carve"])
        // Monado's simulated right controller rests at (0.2, 1.3, -0.5); its tool sits 8 cm
        // ahead. Put the volume there so the tool carves and the touch pulse fires.
        .args(["--volume-at", "0.2,1.3,-0.58"])
        .args(["--frames", &frames, "--record", "rec.jsonl"])
        // A budget no frame meets: every knob turned (asserted below).
        .args(["--frame-budget-ms", "0.01"])
        // Validation off by the environment, on by the flag: `--validation` must win.
        .arg("--validation")
        .env("CAO_XR_VALIDATION", "0")
        .output()
        .expect("run scripts/xr-session.sh");
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    let monado = std::fs::read_to_string(out.join("monado.log")).unwrap_or_default();
    let context = format!("stdout:\n{stdout}\nstderr:\n{stderr}\nmonado.log:\n{monado}");
    assert!(
        run.status.success(),
        "cao-xr xr failed ({})\n{context}",
        run.status
    );

    // The state machine, in the order OpenXR specifies for a session that is asked to exit.
    let summary = stdout
        .lines()
        .find(|l| l.starts_with("xr session ended cleanly"))
        .unwrap_or_else(|| panic!("no summary line\n{context}"));
    assert!(
        summary.contains(&format!("{FRAMES} frames submitted")),
        "{summary}"
    );
    assert!(summary.contains("focused true"), "{summary}");
    // Monado offers XR_EXT_hand_tracking, but its simulated devices track no hands: the session
    // says so and runs on the controllers.
    assert!(
        stdout.contains("hand tracking: off, joints drove 0 frames"),
        "{context}"
    );
    assert!(
        stderr.contains("xr: no hand tracking: the system does not support it"),
        "{context}"
    );
    // Monado offers XR_EXT_eye_gaze_interaction, but its simulated HMD tracks no eyes (the
    // system's property, read through the chained structure): the foveation centres on the
    // lenses, and the session says so.
    assert!(
        stderr.contains("xr: no eye gaze: the system does not track the eyes"),
        "{context}"
    );
    assert!(
        stdout.contains("eye gaze: off, tracked in 0 frames"),
        "{context}"
    );
    // Monado's simulated HMD offers OPAQUE only; auto takes it.
    assert!(
        summary.contains("blend opaque (offered opaque)"),
        "{summary}"
    );
    assert!(
        summary.contains("IDLE>READY>SYNCHRONIZED>VISIBLE>FOCUSED>")
            && summary.contains(">STOPPING>IDLE>EXITING"),
        "{summary}"
    );
    assert!(stderr.contains("xr: session state FOCUSED"), "{context}");
    // The frame budget took the longest step, foveated, and drew the eyes into the lowest
    // part of the swapchain images it takes, which Monado composited (the layer's image
    // rectangle) without a validation message.
    assert!(
        stderr.contains("frame budget: step x3.00, foveated, scale 0.50"),
        "{context}"
    );
    // The tool touched tissue once: one haptic pulse, on the first frame it clipped.
    assert!(summary.contains("haptic pulses 1"), "{summary}\n{context}");

    // Depth went with every projection view (XR_KHR_composition_layer_depth): Monado in the
    // root offers the extension and D32_SFLOAT swapchains.
    assert!(
        stdout.contains(&format!("depth layer: submitted with {FRAMES} frames")),
        "depth layer not submitted with every frame\n{context}"
    );

    assert_validation_silent(&out, &stderr, &context);

    // The controllers arrived as FrameInput: every recorded frame has both hands tracked, at
    // the simulated controllers' places (left of and right of the centre, in front of the
    // user), and the held trigger that carves.
    let (header, recorded) = cao_xr::input::read_stream(&out.join("rec.jsonl")).unwrap();
    assert_eq!(header.source, "xr");
    assert_eq!(header.reference_space, "STAGE");
    assert!(
        recorded.len() >= FRAMES,
        "{} frames recorded",
        recorded.len()
    );
    for (i, f) in recorded.iter().enumerate() {
        let [l, r] = &f.hands;
        assert!(l.tracked && r.tracked, "frame {i}: hands not tracked");
        assert!(
            l.grip.position.x < r.grip.position.x,
            "frame {i}: left hand not left of right"
        );
        assert!(r.grip.position.length() > 0.1, "frame {i}: grip at origin");
        assert_eq!(r.buttons.trigger, 1.0, "frame {i}");
        assert!(
            f.views[0].pose.position.x < f.views[1].pose.position.x,
            "frame {i}: eyes"
        );
    }
    // Frame times come from the predicted display times: strictly increasing.
    assert!(recorded.windows(2).all(|w| w[1].time > w[0].time));
    // The simulated head moves, so the views were located per frame, not once.
    let first = recorded[0].views[0].pose;
    assert!(
        recorded.iter().any(|f| f.views[0].pose != first),
        "the head never moved: views not located per frame"
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn monado_refuses_a_blend_mode_it_does_not_offer_and_lists_what_it_offers() {
    let Some((root, _turn)) = xr_root() else {
        return;
    };
    for (n, args) in [["--blend", "alpha-blend"], ["--passthrough", "--frames"]]
        .iter()
        .enumerate()
    {
        let (mut cmd, _out) = session(&root, &format!("blend-{n}"));
        cmd.args(["phantom:16", "--rays", "6", "--size", "32x32"]);
        match args {
            ["--blend", mode] => cmd.args(["--blend", mode, "--frames", "5"]),
            _ => cmd.args(["--passthrough", "--frames", "5"]),
        };
        let run = cmd.output().expect("run scripts/xr-session.sh");
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{args:?} was accepted:\n{stderr}");
        let want = match args {
            ["--blend", _] => "--blend alpha-blend: the runtime does not offer it; it offers: opaque",
            _ => "--passthrough needs the alpha-blend or additive blend mode or XR_FB_passthrough; the runtime offers only: opaque (nor XR_FB_passthrough)",
        };
        assert!(stderr.contains(want), "{args:?}: no '{want}' in\n{stderr}");
    }
}

#[test]
fn killing_the_runtime_mid_session_ends_it_at_once_with_a_clear_error_and_a_valid_recording() {
    let Some((root, _turn)) = xr_root() else {
        return;
    };
    let (mut session, out) = session(&root, "kill");
    let run = session
        .args(["phantom:16", "--rays", "6", "--size", "32x32"])
        .args(["--frames", "1000000", "--record", "rec.jsonl"])
        // monado-service is killed (SIGKILL) 6 s after it is up.
        .env("CAO_XR_KILL_RUNTIME_AFTER", "6")
        .output()
        .expect("run scripts/xr-session.sh");
    let ended = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("the XrInstance was lost"), "{stderr}");
    let killed: f64 = std::fs::read_to_string(out.join("runtime-killed.txt"))
        .expect("the runtime was killed")
        .trim()
        .parse()
        .unwrap();
    // The session ends within a second or so (the rest is the script's teardown).
    assert!(
        ended - killed < 3.0,
        "ended {:.2} s after the kill",
        ended - killed
    );
    // Every frame up to the kill was recorded, and the recording replays.
    let rec = out.join("rec.jsonl");
    let (_, frames) = cao_xr::input::read_stream(&rec).unwrap();
    assert!(!frames.is_empty(), "no frame recorded before the kill");
    let replay = Command::new(env!("CARGO_BIN_EXE_cao-xr"))
        .args([
            "replay",
            rec.to_str().unwrap(),
            "phantom:16",
            "--rays",
            "6",
            "--size",
            "16x16",
        ])
        .args([
            "--every",
            "100000",
            "--out",
            out.join("replay").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(
        replay.status.success(),
        "{}",
        String::from_utf8_lossy(&replay.stderr)
    );
}

/// Monado's `remote` driver (P_OVERRIDE_ACTIVE_CONFIG=remote; Monado 25.0.0,
/// src/xrt/drivers/remote/r_interface.h, r_hub.c, r_device.c): an HMD and two Index controllers
/// whose hands Monado simulates from five finger curls. A client connects to TCP port 4242,
/// reads two `struct r_remote_data` (the reset state, then the latest) and then sends one
/// whenever it likes; the driver keeps the latest. Little-endian, 376 bytes: a u64 header, the
/// head (128 bytes), the left and the right controller (120 bytes each).
mod remote {
    use glam::Vec3;
    use std::io::{Read, Write};
    use std::net::{Ipv4Addr, TcpStream};
    use std::time::{Duration, Instant};

    const PORT: u16 = 4242;
    const FRAME: usize = 376;
    /// R_HEADER_VALUE; r_hub.c does not check it, but it names the layout version.
    const HEADER: &[u8; 8] = b"mndrmt3\0";
    /// r_head_data::center: after two views of 48 bytes.
    const HEAD_CENTER: usize = 8 + 2 * 48;
    const CONTROLLER: [usize; 2] = [136, 256];
    // Within r_remote_controller_data: the pose (quaternion x, y, z, w, then the position),
    // hand_curl[5] (little, ring, middle, index, thumb; 0 open, 1 curled), then after the
    // trigger, squeeze, stick and trackpad values the bools hand_tracking_active and active.
    const POSE: usize = 0;
    const CURL: usize = 52;
    const HAND_TRACKING_ACTIVE: usize = 104;
    const ACTIVE: usize = 105;

    /// One controller as the driver sees it.
    #[derive(Clone, Copy, Debug, PartialEq)]
    pub struct Controller {
        pub position: Vec3,
        /// Little, ring, middle, index, thumb.
        pub curl: [f32; 5],
        pub hand_tracking_active: bool,
        /// An active controller drives cao-xr itself; an inactive one leaves it to the joints.
        pub active: bool,
    }

    fn f32_at(b: &[u8], at: usize) -> f32 {
        f32::from_le_bytes(b[at..at + 4].try_into().unwrap())
    }

    fn decode(frame: &[u8], at: usize) -> Controller {
        let c = &frame[at..];
        let p = |k: usize| f32_at(c, POSE + 16 + 4 * k);
        Controller {
            position: Vec3::new(p(0), p(1), p(2)),
            curl: std::array::from_fn(|k| f32_at(c, CURL + 4 * k)),
            hand_tracking_active: c[HAND_TRACKING_ACTIVE] != 0,
            active: c[ACTIVE] != 0,
        }
    }

    /// `c` into a copy of the reset frame at `at`, upright (identity orientation), at rest.
    fn encode(frame: &mut [u8], at: usize, c: &Controller) {
        let o = &mut frame[at..];
        let pose = [0.0, 0.0, 0.0, 1.0, c.position.x, c.position.y, c.position.z];
        for (k, v) in pose.iter().chain(&[0.0; 6]).enumerate() {
            o[POSE + 4 * k..][..4].copy_from_slice(&f32::to_le_bytes(*v));
        }
        for (k, v) in c.curl.iter().enumerate() {
            o[CURL + 4 * k..][..4].copy_from_slice(&v.to_le_bytes());
        }
        o[HAND_TRACKING_ACTIVE] = c.hand_tracking_active as u8;
        o[ACTIVE] = c.active as u8;
    }

    /// What the client read and did.
    #[derive(Debug)]
    pub struct Run {
        /// The reset state the driver sent first: left, right, and the head centre's height.
        pub reset: [Controller; 2],
        pub head_height: f32,
        pub frames_sent: usize,
        /// Open-to-pinched changes sent.
        pub pinches: usize,
        /// Why it stopped: the session's end closes the connection.
        pub ended: String,
    }

    /// Joins the network namespace of process `pid` (this thread only), connects to the
    /// driver, checks the layout against the reset state it sends, and then, until Monado
    /// closes the connection (or `limit` passes), holds the left hand open where the reset put
    /// it and the right hand open at `right_at` for `open` seconds, then pinched (thumb and index
    /// curled) as long, and so on: both controllers inactive, so the joints drive cao-xr.
    pub fn drive(pid: u32, right_at: Vec3, open: Duration, limit: Duration) -> Result<Run, String> {
        join_netns(pid)?;
        let start = Instant::now();
        let mut stream = loop {
            match TcpStream::connect((Ipv4Addr::LOCALHOST, PORT)) {
                Ok(s) => break s,
                Err(e) if start.elapsed() > Duration::from_secs(30) => {
                    return Err(format!("cannot connect to 127.0.0.1:{PORT}: {e}"))
                }
                Err(_) => std::thread::sleep(Duration::from_millis(100)),
            }
        };
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .map_err(|e| e.to_string())?;
        let mut two = [0u8; 2 * FRAME];
        stream
            .read_exact(&mut two)
            .map_err(|e| format!("reading the driver's two first frames: {e}"))?;
        let reset = &two[..FRAME];
        let mut run = Run {
            reset: CONTROLLER.map(|at| decode(reset, at)),
            head_height: f32_at(reset, HEAD_CENTER + 16 + 4),
            frames_sent: 0,
            pinches: 0,
            ended: String::new(),
        };
        let mut frame = reset.to_vec();
        frame[..8].copy_from_slice(HEADER);
        let left = Controller {
            active: false,
            hand_tracking_active: true,
            curl: [0.0; 5],
            ..run.reset[0]
        };
        encode(&mut frame, CONTROLLER[0], &left);
        let mut was_pinched = false;
        loop {
            let t = start.elapsed();
            if t > limit {
                run.ended = format!("time limit {limit:?}");
                return Ok(run);
            }
            let pinched = (t.as_secs_f64() / open.as_secs_f64()) as u64 % 2 == 1;
            run.pinches += (pinched && !was_pinched) as usize;
            was_pinched = pinched;
            let c = if pinched { 1.0 } else { 0.0 };
            let right = Controller {
                position: right_at,
                curl: [0.0, 0.0, 0.0, c, c],
                hand_tracking_active: true,
                active: false,
            };
            encode(&mut frame, CONTROLLER[1], &right);
            if let Err(e) = stream.write_all(&frame) {
                run.ended = format!("disconnected: {e}");
                return Ok(run);
            }
            run.frames_sent += 1;
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// setns(2) into /proc/PID/ns/net: a network namespace is per thread.
    fn join_netns(pid: u32) -> Result<(), String> {
        use std::os::fd::AsRawFd;
        let path = format!("/proc/{pid}/ns/net");
        let ns = std::fs::File::open(&path).map_err(|e| format!("{path}: {e}"))?;
        // SAFETY: a valid open descriptor; only this thread changes namespace.
        if unsafe { libc::setns(ns.as_raw_fd(), libc::CLONE_NEWNET) } != 0 {
            return Err(format!("setns {path}: {}", std::io::Error::last_os_error()));
        }
        Ok(())
    }
}

/// Frames of the remote-hand session: enough for several pinches at lavapipe's pace.
const REMOTE_FRAMES: usize = 150;
/// Monado simulates the palm this far ahead (-z) of the controller's pose (measured: 6.4 cm).
const PALM_AHEAD: f32 = 0.064;

#[test]
fn monado_remote_hand_pinches_and_carves_and_the_recording_holds_the_joints() {
    use cao_xr::input::hands::{PALM, PINCH_OFF, PINCH_ON};
    use glam::Vec3;
    use std::time::{Duration, Instant};
    let Some((root, _turn)) = xr_root() else {
        return;
    };
    let (mut session, out) = session(&root, "remote");
    std::fs::create_dir_all(&out).unwrap();
    let log = |name| std::fs::File::create(out.join(name)).unwrap();
    let frames = REMOTE_FRAMES.to_string();
    let mut session = session
        // No --carve: the pinch is the trigger. The volume sits where it does by default, so
        // that the recording replays the same carve.
        .args(["phantom:32", "--rays", "6", "--size", "64x64"])
        .args(["--frames", &frames, "--record", "rec.jsonl"])
        .env("CAO_XR_MONADO", "remote")
        .stdout(log("session-stdout.txt"))
        .stderr(log("session-stderr.txt"))
        .spawn()
        .expect("run scripts/xr-session.sh");
    let read = |name| std::fs::read_to_string(out.join(name)).unwrap_or_default();

    // The client joins the session's network namespace once the script has made it.
    let waited = Instant::now();
    let pid = loop {
        if let Ok(pid) = read("netns.pid").trim().parse::<u32>() {
            break pid;
        }
        let ended = session.try_wait().unwrap();
        if ended.is_some() || waited.elapsed() > Duration::from_secs(120) {
            let _ = session.kill();
            let _ = session.wait();
            panic!(
                "no network namespace from the session ({ended:?})\n{}",
                read("session-stderr.txt")
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    // The tool (tool_offset ahead of the palm) at the volume's centre.
    let tool_offset = cao_xr::input::InteractionSettings::default().tool_offset;
    let centre = cao_xr::space::Placement::default().center;
    let right_at = centre - tool_offset + Vec3::new(0.0, 0.0, PALM_AHEAD);
    let client = std::thread::spawn(move || {
        remote::drive(
            pid,
            right_at,
            Duration::from_millis(1500),
            Duration::from_secs(600),
        )
    });
    let status = session.wait().unwrap();
    let client = client.join().unwrap();
    let stdout = read("session-stdout.txt");
    let stderr = read("session-stderr.txt");
    let monado = read("monado.log");
    let context =
        format!("client: {client:?}\nstdout:\n{stdout}\nstderr:\n{stderr}\nmonado.log:\n{monado}");
    assert!(status.success(), "cao-xr xr failed ({status})\n{context}");

    // The driver is compiled in, made the controllers the hand trackers, and its wire format is
    // the one above: the reset state reads back as r_hub.c sets it.
    assert!(
        monado.contains("Using builder remote")
            && monado.contains("hand_tracking.right: Remote Right Controller"),
        "{context}"
    );
    let run = client.unwrap_or_else(|e| panic!("the remote client failed: {e}\n{context}"));
    let [l, r] = run.reset;
    assert_eq!(l.position, Vec3::new(-0.2, 1.3, -0.5), "{run:?}");
    assert_eq!(r.position, Vec3::new(0.2, 1.3, -0.5), "{run:?}");
    assert!(l.active && r.active && l.hand_tracking_active && r.hand_tracking_active);
    assert_eq!(run.head_height, 1.6, "{run:?}");
    assert!(run.ended.starts_with("disconnected"), "{run:?}");
    assert!(run.pinches >= 2, "{run:?}");

    // The joints drove every frame, and neither validation layer said anything.
    let summary = stdout
        .lines()
        .find(|l| l.starts_with("xr session ended cleanly"))
        .unwrap_or_else(|| panic!("no summary line\n{context}"));
    assert!(
        summary.contains(&format!(
            "{REMOTE_FRAMES} frames submitted, {REMOTE_FRAMES} with tracked hands"
        )),
        "{summary}"
    );
    assert!(
        stderr.contains("xr: hand tracking on (XR_EXT_hand_tracking)"),
        "{context}"
    );
    assert!(
        stdout.contains(&format!(
            "hand tracking: on, joints drove {REMOTE_FRAMES} frames"
        )),
        "{context}"
    );
    assert_validation_silent(&out, &stderr, &context);

    // The recording (pose stream v3) holds both hands' joints on every frame; the right palm is
    // where the client put the hand, and the trigger is the pinch, with its hysteresis.
    let rec = out.join("rec.jsonl");
    let (header, recorded) = cao_xr::input::read_stream(&rec).unwrap();
    assert_eq!(header.version, cao_xr::input::stream::VERSION);
    assert!(recorded.len() >= REMOTE_FRAMES, "{} frames", recorded.len());
    let mut presses = 0;
    let mut releases = 0;
    for (i, f) in recorded.iter().enumerate() {
        let [Some(lj), Some(rj)] = &f.joints else {
            panic!(
                "frame {i}: joints missing: {:?}",
                f.joints.map(|j| j.is_some())
            )
        };
        assert!(f.hands.iter().all(|h| h.tracked), "frame {i}");
        let palm = rj.poses[PALM].position;
        assert!(
            palm.distance(right_at - Vec3::new(0.0, 0.0, PALM_AHEAD)) < 0.01,
            "frame {i}: right palm at {palm}"
        );
        assert!(lj.poses[PALM].position.x < -0.1, "frame {i}: left palm");
        assert_eq!(
            f.hands[0].buttons.trigger, 0.0,
            "frame {i}: the open left hand pinched"
        );
        let d = rj.pinch_distance();
        let pinched = f.hands[RIGHT_HAND].buttons.trigger == 1.0;
        if pinched {
            assert!(d <= PINCH_OFF, "frame {i}: pinching {d} m apart");
        } else {
            assert!(d >= PINCH_ON, "frame {i}: not pinching {d} m apart");
        }
        if i > 0 {
            let was = recorded[i - 1].hands[RIGHT_HAND].buttons.trigger == 1.0;
            presses += (pinched && !was) as usize;
            releases += (!pinched && was) as usize;
        }
    }
    assert!(
        presses >= 1 && releases >= 1,
        "{presses} pinches, {releases} releases"
    );

    // The recording replays the carve. A pinch toggles carving (as a trigger press does), so with
    // the tool inside the volume it clips from the first pinch to the second, from the third to
    // the fourth, and so on; and each start of a carve was one haptic pulse in the session.
    let replay = Command::new(env!("CARGO_BIN_EXE_cao-xr"))
        .arg("replay")
        .arg(&rec)
        .args([
            "phantom:32",
            "--rays",
            "6",
            "--size",
            "16x16",
            "--every",
            "100000",
        ])
        .arg("--out")
        .arg(out.join("replay"))
        .output()
        .unwrap();
    assert!(
        replay.status.success(),
        "{}",
        String::from_utf8_lossy(&replay.stderr)
    );
    let csv = std::fs::read_to_string(out.join("replay/metrics.csv")).unwrap();
    let mut lines = csv.lines();
    let col = lines
        .next()
        .unwrap()
        .split(',')
        .position(|c| c == "clipped")
        .unwrap();
    let clipped: Vec<u64> = lines
        .map(|l| l.split(',').nth(col).unwrap().parse().unwrap())
        .collect();
    assert_eq!(clipped.len(), recorded.len());
    let mut carving = false;
    let mut was = false;
    let mut carves = 0;
    for (i, (f, c)) in recorded.iter().zip(&clipped).enumerate() {
        let pinched = f.hands[RIGHT_HAND].buttons.trigger == 1.0;
        if pinched && !was {
            carving = !carving;
            carves += carving as usize;
        }
        was = pinched;
        assert_eq!(*c > 0, carving, "frame {i}: {c} voxels clipped");
    }
    assert!(carves >= 1, "the pinch never carved");
    assert!(
        summary.contains(&format!("haptic pulses {carves},")),
        "{carves} carves in the recording\n{summary}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

const RIGHT_HAND: usize = cao_xr::input::RIGHT;

/// A real SIGTERM mid-session: the session is ended as at its frame count (the runtime told,
/// the recording finished whole), and the process still ends by the signal (issue 19, item 3).
#[test]
fn sigterm_mid_session_ends_it_cleanly_with_a_whole_recording() {
    let Some((root, _turn)) = xr_root() else {
        return;
    };
    let (mut session, out) = session(&root, "sig");
    let run = session
        .args(["phantom:16", "--rays", "6", "--size", "32x32"])
        .args(["--frames", "1000000", "--record", "rec.jsonl"])
        .env("CAO_XR_SIGNAL_AFTER", "TERM 8")
        .output()
        .expect("run scripts/xr-session.sh");
    let (stdout, stderr) = (
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr),
    );
    // The shell's view of a child ended by SIGTERM: 128 + 15.
    assert_eq!(run.status.code(), Some(128 + 15), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("SIGTERM: the session ended cleanly"),
        "{stderr}"
    );
    let submitted: usize = stdout
        .lines()
        .find_map(|l| {
            l.strip_prefix("xr session ended cleanly: ")?
                .split_once(" frames submitted")
                .map(|(n, _)| n.to_string())
        })
        .unwrap_or_else(|| panic!("no summary:\n{stdout}\n{stderr}"))
        .parse()
        .unwrap();
    assert!(submitted > 0, "{stdout}");
    let rec = out.join("rec.jsonl");
    let text = std::fs::read_to_string(&rec).unwrap();
    assert!(text.ends_with('\n'), "the last line is cut");
    let (_, frames) = cao_xr::input::read_stream(&rec).unwrap();
    assert!(
        frames.len().abs_diff(submitted) <= 1,
        "{} frames recorded, {submitted} submitted",
        frames.len()
    );
}
