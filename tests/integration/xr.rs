//! The OpenXR path against a real runtime: Monado (null compositor, simulated HMD and two
//! simulated controllers) in a Debian trixie root built by scripts/xr-root.sh, driven by
//! scripts/xr-session.sh. One session of 300 frames with the right controller holding a
//! carving tool; the session must reach FOCUSED, submit every frame, end cleanly, record the
//! controllers as FrameInput, submit depth with every projection view, and neither the Vulkan nor the OpenXR validation layer may
//! report an error.
//!
//! Needs root (chroot, mounts) and, the first time, Debian's archive. Without them the test is
//! skipped, unless CAO_XR_REQUIRE_XR=1 (scripts/test.sh sets it), which makes it fail instead.

use crate::common;
use std::path::{Path, PathBuf};
use std::process::Command;

const FRAMES: usize = 300;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The built root, building it if needed; None (skip) when it cannot be had and is not required.
fn xr_root() -> Option<PathBuf> {
    let out = Command::new(repo().join("scripts/xr-root.sh")).output();
    let why = match out {
        Ok(o) if o.status.success() => {
            let path = String::from_utf8_lossy(&o.stdout).trim().to_string();
            return Some(PathBuf::from(path));
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

#[test]
fn monado_session_reaches_focused_submits_frames_and_records_the_hands() {
    let Some(root) = xr_root() else { return };
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("xr-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let frames = FRAMES.to_string();
    let run = Command::new(repo().join("scripts/xr-session.sh"))
        .arg(&root)
        .arg(env!("CARGO_BIN_EXE_cao-xr"))
        .arg(&out)
        .args(["phantom:32", "--rays", "6", "--size", "96x96", "--carve"])
        // Monado's simulated right controller rests at (0.2, 1.3, -0.5); its tool sits 8 cm
        // ahead. Put the volume there so the tool carves and the touch pulse fires.
        .args(["--volume-at", "0.2,1.3,-0.58"])
        .args(["--frames", &frames, "--record", "rec.jsonl"])
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
    // The tool touched tissue once: one haptic pulse, on the first frame it clipped.
    assert!(summary.contains("haptic pulses 1"), "{summary}\n{context}");

    // Depth went with every projection view (XR_KHR_composition_layer_depth): Monado in the
    // root offers the extension and D32_SFLOAT swapchains.
    assert!(
        stdout.contains(&format!("depth layer: submitted with {FRAMES} frames")),
        "depth layer not submitted with every frame\n{context}"
    );

    // Neither validation layer reported anything wrong.
    assert!(
        stderr.contains("(validation on)"),
        "Vulkan validation was off: --validation ignored\n{context}"
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
    let Some(root) = xr_root() else { return };
    for (n, args) in [["--blend", "alpha-blend"], ["--passthrough", "--frames"]]
        .iter()
        .enumerate()
    {
        let out = Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("xr-blend-{n}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let mut cmd = Command::new(repo().join("scripts/xr-session.sh"));
        cmd.arg(&root)
            .arg(env!("CARGO_BIN_EXE_cao-xr"))
            .arg(&out)
            .args(["phantom:16", "--rays", "6", "--size", "32x32"]);
        match args {
            ["--blend", mode] => cmd.args(["--blend", mode, "--frames", "5"]),
            _ => cmd.args(["--passthrough", "--frames", "5"]),
        };
        let run = cmd.output().expect("run scripts/xr-session.sh");
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{args:?} was accepted:\n{stderr}");
        let want = match args {
            ["--blend", _] => "--blend alpha-blend: the runtime does not offer it; it offers: opaque",
            _ => "--passthrough needs the alpha-blend or additive blend mode; the runtime offers only: opaque",
        };
        assert!(stderr.contains(want), "{args:?}: no '{want}' in\n{stderr}");
    }
}

#[test]
fn killing_the_runtime_mid_session_ends_it_at_once_with_a_clear_error_and_a_valid_recording() {
    let Some(root) = xr_root() else { return };
    let out =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("xr-kill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let run = Command::new(repo().join("scripts/xr-session.sh"))
        .arg(&root)
        .arg(env!("CARGO_BIN_EXE_cao-xr"))
        .arg(&out)
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

/// A real SIGTERM mid-session: the session is ended as at its frame count (the runtime told,
/// the recording finished whole), and the process still ends by the signal (issue 19, item 3).
#[test]
fn sigterm_mid_session_ends_it_cleanly_with_a_whole_recording() {
    let Some(root) = xr_root() else { return };
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("xr-sig-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let run = Command::new(repo().join("scripts/xr-session.sh"))
        .arg(&root)
        .arg(env!("CARGO_BIN_EXE_cao-xr"))
        .arg(&out)
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
