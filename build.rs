//! Compiles every shader in shaders/ (not shaders/include/) to SPIR-V with glslc, into OUT_DIR.
//! glslc's depfiles become rerun-if-changed lines, so editing an included file rebuilds too.

use std::path::{Path, PathBuf};
use std::process::Command;

const STAGES: &[&str] = &["comp", "vert", "frag"];

fn main() {
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    let dir = Path::new("shaders");
    println!("cargo:rerun-if-changed=shaders");
    println!("cargo:rerun-if-env-changed=GLSLC");
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    if Command::new(&glslc).arg("--version").output().is_err() {
        panic!(
            "\n\ncao-xr needs glslc to compile its shaders, and `{glslc}` was not found.\n\
             On Debian/Ubuntu: sudo apt-get install glslc   (or set GLSLC=/path/to/glslc)\n\n"
        );
    }
    let mut shaders: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("shaders/ directory is missing")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| STAGES.contains(&e))
        })
        .collect();
    shaders.sort();
    for src in shaders {
        let name = src.file_name().unwrap().to_str().unwrap();
        let spv = out.join(format!("{name}.spv"));
        let dep = out.join(format!("{name}.d"));
        let status = Command::new(&glslc)
            .args([
                "--target-env=vulkan1.2",
                "-O",
                "-Werror",
                "-Ishaders/include",
                "-MD",
                "-MF",
            ])
            .arg(&dep)
            .arg(&src)
            .arg("-o")
            .arg(&spv)
            .status()
            .expect("failed to run glslc");
        if !status.success() {
            panic!("glslc failed on {}", src.display());
        }
        // Depfile: "out.spv: a.comp include/b.glsl ..." with backslash-escaped spaces.
        let deps = std::fs::read_to_string(&dep).unwrap_or_default();
        if let Some((_, list)) = deps.split_once(": ") {
            for d in list.split_whitespace().filter(|d| *d != "\\") {
                println!("cargo:rerun-if-changed={d}");
            }
        }
    }
}
