//! Entry points of the fuzz targets in `fuzz/`, one per parser of outside data (volumes,
//! transfer functions, pose streams, tool meshes, environment images), kept in the library so
//! that a unit test runs them on the committed seeds and they cannot rot.
//!
//! Each takes arbitrary bytes, runs the real parser, and checks what a parser of untrusted input
//! promises: it returns (never panics), and what it accepts is whole and consistent (a volume's
//! voxel count matches its sizes and every value is finite; a transfer function evaluates to
//! colours and opacities in \[0,1]). A broken promise panics, which the fuzzer reports.

use crate::clip::TriMesh;
use crate::light::EquirectImage;
use crate::volume::transfer::TransferFunction;
use crate::volume::{dicom, metaimage, nifti, nrrd, Volume, VolumeError};
use std::path::PathBuf;

/// A per-thread scratch file named `name` (in /dev/shm when there is one: no disk traffic).
fn scratch(name: &str) -> PathBuf {
    let base = if std::path::Path::new("/dev/shm").is_dir() {
        PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let dir = base.join(format!(
        "cao-xr-fuzz-{}-{:?}",
        std::process::id(),
        std::thread::current().id()
    ));
    let _ = std::fs::create_dir_all(&dir);
    dir.join(name)
}

/// Runs `parse` on `bytes` written to the scratch file `name` (the parsers read files: detached
/// data and byte offsets are part of what they parse), then removes it. An error must name the
/// file (or, for a DICOM series, the directory it is in).
fn with_file<T, E: std::fmt::Display>(
    name: &str,
    bytes: &[u8],
    parse: impl FnOnce(&std::path::Path) -> Result<T, E>,
) -> Result<T, String> {
    let path = scratch(name);
    if std::fs::write(&path, bytes).is_err() {
        return Err(format!("fuzz: cannot write {}", path.display()));
    }
    let r = parse(&path).map_err(|e| e.to_string());
    let dir = path.parent().map(|d| d.display().to_string());
    if let Some(dir) = path.parent() {
        let _ = std::fs::remove_dir_all(dir);
    }
    if let Err(msg) = &r {
        assert!(
            msg.contains(name) || dir.is_some_and(|d| msg.contains(&d)),
            "error does not name the file: {msg}"
        );
    }
    r
}

/// Loads `bytes` as the volume file `name` with `load` and checks what it accepts.
fn load_file(
    name: &str,
    bytes: &[u8],
    load: fn(&std::path::Path) -> Result<Volume, VolumeError>,
) -> Result<Volume, String> {
    let v = with_file(name, bytes, load)?;
    check_volume(&v);
    Ok(v)
}

/// What every loaded volume must satisfy.
fn check_volume(v: &Volume) {
    assert!(v.dims.iter().all(|&d| d > 0), "dims {:?}", v.dims);
    assert_eq!(v.voxels.len(), v.voxel_count(), "partial volume");
    assert!(v.spacing.iter().all(|s| s.is_finite() && *s > 0.0));
    assert!(v.directions.is_finite() && v.origin.is_finite());
    let (lo, hi) = v.value_range();
    assert!(lo.is_finite() && hi.is_finite() && lo <= hi, "{lo} .. {hi}");
}

/// NRRD (`.nrrd`, attached or naming a detached data file); a 4-D series' second volume when
/// it holds several.
pub fn nrrd(bytes: &[u8]) -> Result<Volume, String> {
    load_file("fuzz.nrrd", bytes, |p| {
        nrrd::load(p).or_else(|_| nrrd::load_frame(p, Some(1)))
    })
}

/// NIfTI-1 or NIfTI-2: `.nii.gz` when the bytes start with the gzip magic, else `.nii`; a 4-D
/// file's second volume when it holds several.
pub fn nifti(bytes: &[u8]) -> Result<Volume, String> {
    let name = if bytes.starts_with(&[0x1f, 0x8b]) {
        "fuzz.nii.gz"
    } else {
        "fuzz.nii"
    };
    load_file(name, bytes, |p| {
        nifti::load(p).or_else(|_| nifti::load_frame(p, Some(1)))
    })
}

/// MetaImage (`.mha`, local or detached data, raw or zlib).
pub fn metaimage(bytes: &[u8]) -> Result<Volume, String> {
    load_file("fuzz.mha", bytes, metaimage::load)
}

/// DICOM: the bytes as the one file of a series directory, loaded as that directory (a
/// single-slice series is a volume one voxel deep).
pub fn dicom(bytes: &[u8]) -> Result<Volume, String> {
    load_file("fuzz.dcm", bytes, |path| {
        dicom::load_series(path.parent().unwrap_or(path), None)
    })
}

/// A transfer-function JSON file; an accepted one is evaluated over data and normalised ranges.
pub fn transfer_json(bytes: &[u8]) -> Result<TransferFunction, String> {
    let text = std::str::from_utf8(bytes).map_err(|e| e.to_string())?;
    let tf = TransferFunction::from_json(text)?;
    for range in [(-1024.0, 3071.0), (0.0, 0.0), (0.0, 1.0), (-3e38, 3e38)] {
        for rgba in tf.lut(range, 33) {
            assert!(
                rgba.iter().all(|c| (0.0..=1.0).contains(c)),
                "{rgba:?} for {range:?}"
            );
        }
        for p in &tf.points {
            let rgba = tf.eval(p.value, range);
            assert!(rgba.iter().all(|c| (0.0..=1.0).contains(c)), "{rgba:?}");
        }
    }
    Ok(tf)
}

/// A pose stream (JSON Lines): the header and every frame up to the first bad line.
pub fn pose_stream(bytes: &[u8]) -> Result<usize, String> {
    use crate::input::stream::PoseStreamReader;
    let reader = PoseStreamReader::new(std::io::Cursor::new(bytes), "fuzz.jsonl")
        .map_err(|e| e.to_string())?;
    let mut frames = 0;
    for f in reader {
        let f = f.map_err(|e| e.to_string())?;
        assert!(f.time.is_finite(), "frame time {}", f.time);
        frames += 1;
    }
    Ok(frames)
}

/// A clipping-tool mesh: PLY when the bytes start with its magic, else OBJ; an accepted mesh
/// has finite vertices within the unit box it is scaled to and triangles that index them.
pub fn mesh(bytes: &[u8]) -> Result<TriMesh, String> {
    let name = if bytes.starts_with(b"ply") {
        "fuzz.ply"
    } else {
        "fuzz.obj"
    };
    let m = with_file(name, bytes, TriMesh::load)?;
    assert!(!m.triangles.is_empty());
    assert!(m
        .vertices
        .iter()
        .all(|v| v.is_finite() && v.abs().max_element() <= 1.0 + 1e-5));
    let n = m.vertices.len() as u32;
    assert!(m.triangles.iter().flatten().all(|&i| i < n));
    Ok(m)
}

/// A Radiance `.hdr` environment image; an accepted one has every texel, finite and
/// non-negative.
pub fn environment_hdr(bytes: &[u8]) -> Result<EquirectImage, String> {
    let img = with_file("fuzz.hdr", bytes, EquirectImage::load_hdr)?;
    assert_eq!(img.pixels().len(), img.width() * img.height());
    assert!(img
        .pixels()
        .iter()
        .flatten()
        .all(|c| c.is_finite() && *c >= 0.0));
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The committed seeds: `ok-*` must be accepted, `bad-*` refused, by the target's entry.
    fn seeds(target: &str) -> Vec<(String, Vec<u8>)> {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("fuzz/seeds")
            .join(target);
        let mut v: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| {
                let p = e.unwrap().path();
                let name = p.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read(&p).unwrap())
            })
            .collect();
        v.sort();
        assert!(v.len() >= 2, "{target}: too few seeds");
        v
    }

    fn check<T, E: std::fmt::Display>(target: &str, entry: fn(&[u8]) -> Result<T, E>) {
        for (name, bytes) in seeds(target) {
            let r = entry(&bytes);
            if name.starts_with("ok-") {
                if let Err(e) = r {
                    panic!("{target}/{name} refused: {e}");
                }
            } else {
                assert!(r.is_err(), "{target}/{name} accepted");
            }
        }
    }

    #[test]
    fn fuzz_entries_accept_the_good_seeds_and_refuse_the_bad() {
        check("nrrd", nrrd);
        check("nifti", nifti);
        check("metaimage", metaimage);
        check("dicom", dicom);
        check("transfer_json", transfer_json);
        check("pose_stream", pose_stream);
        check("mesh", mesh);
        check("environment_hdr", environment_hdr);
    }

    /// Writes the volume seeds (run once with --ignored; the files are committed).
    #[test]
    #[ignore]
    fn write_seeds() {
        use crate::volume::{Modality, Voxels};
        use glam::{DMat3, DVec3};
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds");
        let vol = |voxels| Volume {
            whole_range: None,
            name: "s".into(),
            dims: [3, 2, 2],
            spacing: [0.5, 1.0, 2.0],
            directions: DMat3::from_rotation_z(0.3),
            origin: DVec3::new(1.0, -2.0, 3.0),
            modality: Modality::Ct,
            voxels,
            labels: None,
        };
        let i16s = vol(Voxels::I16((0..12).map(|i| i * 100 - 600).collect()));
        let f32s = vol(Voxels::F32((0..12).map(|i| i as f32 * 0.5).collect()));
        let u8s = vol(Voxels::U8((0..12).collect()));
        for d in ["nrrd", "nifti", "metaimage"] {
            std::fs::create_dir_all(root.join(d)).unwrap();
        }
        nrrd::write_volume(&root.join("nrrd/ok-i16.nrrd"), &i16s, false).unwrap();
        nrrd::write_volume(&root.join("nrrd/ok-f32-gzip.nrrd"), &f32s, true).unwrap();
        nrrd::write_volume(&root.join("nrrd/ok-u8.nrrd"), &u8s, false).unwrap();
        nifti::write(&root.join("nifti/ok-i16.nii"), &i16s, false).unwrap();
        nifti::write(&root.join("nifti/ok-f32.nii.gz"), &f32s, true).unwrap();
        metaimage::write(&root.join("metaimage/ok-i16.mha"), &i16s, false).unwrap();
        metaimage::write(&root.join("metaimage/ok-f32-zlib.mha"), &f32s, true).unwrap();
        // truncated copies
        for (dir, name) in [
            ("nrrd", "ok-i16.nrrd"),
            ("nifti", "ok-i16.nii"),
            ("metaimage", "ok-i16.mha"),
        ] {
            let b = std::fs::read(root.join(dir).join(name)).unwrap();
            let cut = name.replace("ok-", "bad-truncated-");
            std::fs::write(root.join(dir).join(cut), &b[..b.len() - 5]).unwrap();
        }
    }
}
