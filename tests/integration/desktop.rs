//! The desktop window under Xvfb: it opens, renders, records, closes cleanly and leaves a
//! screenshot; replaying its recording headless gives the identical images it showed.

use crate::common;
use std::path::Path;
use std::process::Command;

fn have_xvfb() -> bool {
    let found = Command::new("xvfb-run").arg("--help").output().is_ok();
    common::require_or_skip(
        "CAO_XR_REQUIRE_XVFB",
        found,
        "xvfb-run is missing (apt-get install xvfb xauth; scripts/test.sh installs it)",
    )
}

fn png_size(path: &Path) -> (u32, u32) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let info = dec.read_info().unwrap().info().clone();
    (info.width, info.height)
}

/// xvfb-run's options: any free display, and the X auth file in the test's own folder. Without
/// `-f`, xvfb-run makes a temporary folder of its own and exits 5 when removing it fails, which
/// CI once saw with the viewer itself ending cleanly.
fn xvfb_args(dir: &std::path::Path) -> Vec<String> {
    let auth = dir.join("xauth").to_string_lossy().into_owned();
    ["-a", "-f", &auth, "-s", "-screen 0 640x480x24"]
        .map(String::from)
        .to_vec()
}

#[test]
fn window_session_replays_into_the_images_it_showed() {
    if !have_xvfb() {
        return;
    }
    let dir = crate::common::scratch("desktop", "session");
    let (rec, shot, shown, replayed) = (
        dir.join("rec.jsonl"),
        dir.join("shot.png"),
        dir.join("shown"),
        dir.join("replayed"),
    );
    let bin = env!("CARGO_BIN_EXE_cao-xr");
    let common = [
        "phantom:32",
        "--rays",
        "6",
        "--steps",
        "4",
        "--size",
        "80x64",
    ];
    let out = Command::new("xvfb-run")
        .args(xvfb_args(&dir))
        .args([bin, "view"])
        .args(common)
        .args([
            "--frames",
            "10",
            "--demo",
            "--record",
            rec.to_str().unwrap(),
        ])
        .args([
            "--screenshot",
            shot.to_str().unwrap(),
            "--dump",
            shown.to_str().unwrap(),
        ])
        // Validation off by the environment, on by the flag: `--validation` must win.
        .arg("--validation")
        .env("CAO_XR_VALIDATION", "0")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "cao-xr view failed:\n{err}");
    assert!(
        err.contains("(validation on)"),
        "--validation ignored by view:\n{err}"
    );
    assert!(
        !err.contains("vulkan validation") && !err.contains("panicked"),
        "{err}"
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("closed after 10 frames"));
    assert_eq!(
        png_size(&shot),
        (160, 64),
        "the screenshot shows both eyes side by side"
    );

    let out = Command::new(bin)
        .arg("replay")
        .arg(&rec)
        .args(common)
        .args(["--out", replayed.to_str().unwrap()])
        .env("CAO_XR_VALIDATION", "1")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for i in 0..10 {
        let name = format!("frame-{i:05}.png");
        let (a, b) = (
            std::fs::read(shown.join(&name)).unwrap(),
            std::fs::read(replayed.join(&name)).unwrap(),
        );
        assert!(
            a == b,
            "frame {i}: the replay differs from what the window showed"
        );
    }
    // The demo carves: the session's recording holds a pressed trigger.
    assert!(std::fs::read_to_string(&rec)
        .unwrap()
        .contains("\"trigger\":1.0"));
}

/// A real SIGTERM or SIGINT mid-session: the window closes as after its last frame, the
/// recording holds every frame shown and its last line is whole, and the process still ends by
/// the signal (issue 19, item 3).
#[test]
fn a_signal_ends_a_recording_session_cleanly() {
    use std::os::unix::process::ExitStatusExt;
    if !have_xvfb() {
        return;
    }
    let bin = env!("CARGO_BIN_EXE_cao-xr");
    for sig in [libc::SIGTERM, libc::SIGINT] {
        let dir = crate::common::scratch("desktop", &format!("sig{sig}"));
        let (rec, shown, pid_file) = (dir.join("rec.jsonl"), dir.join("shown"), dir.join("pid"));
        // xvfb-run starts the viewer as its child: the shell notes its pid, then becomes it.
        let child = Command::new("xvfb-run")
            .args(xvfb_args(&dir))
            .args(["sh", "-c"])
            .arg("echo $$ > \"$0\"; exec \"$@\"")
            .arg(&pid_file)
            .args([bin, "view", "phantom:32", "--rays", "6", "--steps", "4"])
            .args(["--size", "80x64", "--demo", "--record"])
            .arg(&rec)
            .arg("--dump")
            .arg(&shown)
            .env("CAO_XR_VALIDATION", "1")
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // Some frames in, send the signal to the viewer itself.
        let t0 = std::time::Instant::now();
        while !shown.join("frame-00005.png").exists() {
            assert!(t0.elapsed().as_secs() < 120, "no frames after two minutes");
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let pid: i32 = std::fs::read_to_string(&pid_file)
            .unwrap()
            .trim()
            .parse()
            .unwrap();
        // SAFETY: kill(2) reads no memory of ours; `pid` is the viewer's (the shell exec'd into
        // it), which runs until signalled.
        unsafe { libc::kill(pid, sig) };
        let out = child.wait_with_output().unwrap();
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        // xvfb-run passes on the shell's status of a child ended by a signal: 128 + signal.
        assert!(
            out.status.code() == Some(128 + sig) || out.status.signal() == Some(sig),
            "{:?}\n{stderr}",
            out.status
        );
        let name = if sig == libc::SIGTERM {
            "SIGTERM"
        } else {
            "SIGINT"
        };
        assert!(
            stderr.contains(&format!("{name}: the session ended cleanly")),
            "{stderr}"
        );
        assert!(
            !stderr.contains("vulkan validation") && !stderr.contains("panicked"),
            "{stderr}"
        );
        let shown_frames: usize = stdout
            .lines()
            .find_map(|l| l.strip_prefix("closed after ")?.strip_suffix(" frames"))
            .unwrap_or_else(|| panic!("no 'closed after' line:\n{stdout}\n{stderr}"))
            .parse()
            .unwrap();
        assert!(shown_frames >= 6, "{shown_frames}");
        // The recording: whole lines, one frame per frame shown, read back without complaint.
        let text = std::fs::read_to_string(&rec).unwrap();
        assert!(text.ends_with('\n'), "the last line is cut");
        let (_, frames) = cao_xr::input::read_stream(&rec).unwrap();
        assert_eq!(frames.len(), shown_frames, "{name}");
        assert_eq!(
            std::fs::read_dir(&shown).unwrap().count(),
            shown_frames,
            "{name}: frames dumped"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
