//! Shared by the tests: a validated Vulkan context and a check that it stayed silent, the skip
//! rule for what a test needs from outside, and small volumes and picture measures.

use cao_xr::gpu::{Gpu, GpuOptions};

/// Whether the REQUIRE variable `var` is set (to anything but 0).
pub fn required(var: &str) -> bool {
    std::env::var(var).is_ok_and(|v| v != "0")
}

/// Whether a test can run: `available` (a tool, a file, a root it needs), else it is skipped
/// with `why`, unless the variable `require` (CAO_XR_REQUIRE_XVFB, _DCMTK, _PYDICOM, _FOREIGN,
/// _XR, all set by scripts/test.sh) is set to anything but 0: then the test fails with `why`.
pub fn require_or_skip(require: &str, available: bool, why: &str) -> bool {
    if available {
        return true;
    }
    assert!(!required(require), "{why} and {require} is set");
    eprintln!("SKIPPED: {why}");
    false
}

/// A Vulkan context with the Khronos validation layer on (required: a missing layer fails).
pub fn gpu() -> Gpu {
    let opts = GpuOptions {
        present: false,
        validation: true,
        device_name: None,
    };
    Gpu::new(&opts)
        .expect("Vulkan with validation (install mesa-vulkan-drivers and vulkan-validationlayers)")
}

/// Fails the test if validation reported any warning or error.
pub fn assert_no_validation_messages(gpu: &Gpu) {
    let m = gpu.validation_messages();
    assert!(
        m.is_empty(),
        "{} validation message(s):\n{}",
        m.len(),
        m.join("\n")
    );
}

/// A 24^3 volume (2 mm voxels) holding a solid bone ball of radius 16 mm at its centre.
pub fn ball() -> cao_xr::volume::Volume {
    use glam::DVec3;
    ct_volume("ball", 24, 2.0, |[i, j, k]| {
        let d = DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) - DVec3::splat(12.0);
        d.length() < 8.0
    })
}

/// An n^3 CT volume of isotropic `spacing` mm: bone (1500 HU) at the voxels (i, j, k) where
/// `bone` holds, air (-1000 HU) elsewhere.
pub fn ct_volume(
    name: &str,
    n: usize,
    spacing: f64,
    bone: impl Fn([usize; 3]) -> bool,
) -> cao_xr::volume::Volume {
    use cao_xr::volume::{Modality, Volume, Voxels};
    use glam::{DMat3, DVec3};
    let mut v = vec![-1000i16; n * n * n];
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                if bone([i, j, k]) {
                    v[i + n * (j + n * k)] = 1500;
                }
            }
        }
    }
    Volume {
        whole_range: None,
        name: name.into(),
        dims: [n; 3],
        spacing: [spacing; 3],
        directions: DMat3::IDENTITY,
        origin: DVec3::ZERO,
        modality: Modality::Ct,
        voxels: Voxels::I16(v),
        labels: None,
    }
}

/// Alpha-weighted mean (column, row) of one eye, in pixels from the top left; None when that eye
/// drew nothing.
pub fn centroid(img: &cao_xr::render::StereoImage, eye: usize) -> Option<(f64, f64)> {
    let w = img.width as usize;
    let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
    for (i, px) in img.rgba[eye].chunks_exact(4).enumerate() {
        let a = px[3] as f64;
        sx += a * ((i % w) as f64 + 0.5);
        sy += a * ((i / w) as f64 + 0.5);
        sw += a;
    }
    (sw > 0.0).then(|| (sx / sw, sy / sw))
}

/// Asserts the GPU's `got` agrees with a reference: at least 99.9 % of values within 1e-4 and a
/// mean |difference| of at most 1e-5 (the bar every AO method's GPU kernel meets).
pub fn assert_agrees<T: Copy + Into<f64>>(got: &[f32], want: &[T], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    let diffs: Vec<f64> = got
        .iter()
        .zip(want)
        .map(|(a, b)| (*a as f64 - (*b).into()).abs())
        .collect();
    let close = diffs.iter().filter(|d| **d <= 1e-4).count() as f64 / diffs.len().max(1) as f64;
    let mean = diffs.iter().sum::<f64>() / diffs.len().max(1) as f64;
    assert!(
        close >= 0.999 && mean <= 1e-5,
        "{what}: {:.4} % within 1e-4, mean |diff| {mean:e}",
        100.0 * close
    );
}

/// Runs the cao-xr binary with validation on and the environment `env` added; it must neither
/// panic nor report a validation message, whatever its exit status.
pub fn run_cao(args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cao-xr"))
        .args(args)
        .env("CAO_XR_VALIDATION", "1")
        .envs(env.iter().copied())
        .output()
        .expect("run cao-xr");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "cao-xr panicked:\n{stderr}");
    assert!(
        !stderr.contains("vulkan validation"),
        "validation messages:\n{stderr}"
    );
    out
}

/// A test's scratch folder: removed when it goes out of scope, unless the test is failing (then
/// it is kept, and named on stderr, for a look at what the test wrote).
pub struct Scratch(std::path::PathBuf);

impl std::ops::Deref for Scratch {
    type Target = std::path::PathBuf;
    fn deref(&self) -> &std::path::PathBuf {
        &self.0
    }
}

impl AsRef<std::path::Path> for Scratch {
    fn as_ref(&self) -> &std::path::Path {
        &self.0
    }
}

impl AsRef<std::ffi::OsStr> for Scratch {
    fn as_ref(&self) -> &std::ffi::OsStr {
        self.0.as_os_str()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("kept for a look: {}", self.0.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A fresh, empty scratch folder for test module `module`'s `name`, removed when the test ends.
pub fn scratch(module: &str, name: &str) -> Scratch {
    let d = std::env::temp_dir().join(format!("cao-{module}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    Scratch(d)
}

#[test]
fn a_scratch_folder_is_removed_when_its_test_ends() {
    let kept = {
        let d = scratch("common", "removed");
        std::fs::create_dir_all(d.join("a/b")).unwrap();
        std::fs::write(d.join("a/b/c.txt"), "x").unwrap();
        d.to_path_buf()
    };
    assert!(!kept.exists(), "{} is still there", kept.display());
}

/// [`run_cao`], which must succeed: a failure fails the test with the arguments and stderr.
/// The GPU bytes per voxel `render` told it held after its frame, from its stdout.
pub fn held_bytes_per_voxel(stdout: &str) -> f64 {
    stdout
        .split("held after the frame: ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("nothing held told in {stdout}"))
}

pub fn run_cao_ok(args: &[&str]) -> std::process::Output {
    let out = run_cao(args, &[]);
    assert!(
        out.status.success(),
        "cao-xr {}:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The first index where `a` and `b` differ bit for bit (exactness checks), or None.
pub fn first_bit_difference(a: &[f32], b: &[f32]) -> Option<usize> {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .position(|(x, y)| x.to_bits() != y.to_bits())
}
