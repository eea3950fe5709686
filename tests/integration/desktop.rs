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

#[test]
fn window_session_replays_into_the_images_it_showed() {
    if !have_xvfb() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("cao-desktop-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
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
        .args(["-a", "-s", "-screen 0 640x480x24", bin, "view"])
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
