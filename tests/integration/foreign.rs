//! Volumes that nobody on this project wrote load with the size, spacing, orientation and
//! voxels that other people's tools give them, and render:
//! - NIfTI files from nibabel's test data, ITK's examples and mricron's Colin27 MRI template,
//!   checked against niftilib's `nifti_tool` (the NIfTI reference library) for every corner and
//!   whole slices; ITK's example MetaImage with detached data;
//! - a CT series from pydicom's sample files against dcm2niix's NIfTI and NRRD conversions of
//!   it and teem's (`unu`) permuted, flipped, detached gzip big-endian and float re-encodings,
//!   voxel for voxel in patient space;
//! - the CT head from Debian's invesalius-examples, through its NRRD conversion, upright.
//!
//! The files come from scripts/foreign-data.sh (run by scripts/test.sh) and Debian's
//! python3-pydicom, nifti-bin, dcm2niix and teem-apps. With CAO_XR_REQUIRE_FOREIGN set, a
//! missing file or tool fails the test; otherwise it is skipped with a message.

use crate::common;

use cao_xr::app::{load_volume, HeadlessRenderer};
use cao_xr::render::{FrameViews, RenderSettings, StereoImage, VolumeTextures};
use cao_xr::space::{default_stereo_views, world_from_tex, Placement};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{ct_head, dicom, Volume, Voxels};
use glam::{DMat4, DVec3, DVec4};
use std::path::{Path, PathBuf};
use std::process::Command;

/// `Some(path)` when present; else a skip message (or a failure when required).
fn present(path: PathBuf, how: &str) -> Option<PathBuf> {
    let why = format!("{} is missing ({how})", path.display());
    common::require_or_skip("CAO_XR_REQUIRE_FOREIGN", path.exists(), &why).then_some(path)
}

fn has_tool(name: &str, package: &str) -> bool {
    let ok = Command::new(name).arg("-h").output().is_ok();
    let why = format!("`{name}` is missing (apt-get install {package})");
    common::require_or_skip("CAO_XR_REQUIRE_FOREIGN", ok, &why)
}

fn foreign_dir() -> PathBuf {
    std::env::var_os("CAO_XR_FOREIGN_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| ct_head::cache_dir().join("foreign"))
}

fn run(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    assert!(
        out.status.success(),
        "{cmd:?} failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn open(path: &Path) -> Volume {
    load_volume(Some(path.to_str().unwrap()), None)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// LPS position (mm) of the centre of voxel `ijk` (fractional indices allowed).
fn lps_of(v: &Volume, ijk: DVec3) -> DVec3 {
    v.origin + v.directions * (DVec3::from(v.spacing) * ijk)
}

/// Fractional voxel indices of the LPS point `p`.
fn index_of(v: &Volume, p: DVec3) -> DVec3 {
    (v.directions.inverse() * (p - v.origin)) / DVec3::from(v.spacing)
}

fn corners(dims: [usize; 3]) -> impl Iterator<Item = DVec3> {
    (0..8).map(move |c| {
        DVec3::new(
            if c & 1 == 0 {
                0.0
            } else {
                dims[0] as f64 - 1.0
            },
            if c & 2 == 0 {
                0.0
            } else {
                dims[1] as f64 - 1.0
            },
            if c & 4 == 0 {
                0.0
            } else {
                dims[2] as f64 - 1.0
            },
        )
    })
}

/// What niftilib makes of a NIfTI header.
struct Nim {
    dims: [usize; 3],
    /// Voxel indices -> RAS mm: the sform when sform_code > 0, else the qform (which niftilib
    /// builds from pixdim when qform_code is 0), as the NIfTI-1 standard orders them.
    ras_from_ijk: DMat4,
    slope: f64,
    inter: f64,
}

fn nifti_tool(path: &Path) -> Nim {
    let mut cmd = Command::new("nifti_tool");
    cmd.arg("-disp_nim");
    for f in [
        "nx",
        "ny",
        "nz",
        "sform_code",
        "qform_code",
        "sto_xyz",
        "qto_xyz",
        "scl_slope",
        "scl_inter",
    ] {
        cmd.args(["-field", f]);
    }
    let text = run(cmd.arg("-infiles").arg(path));
    // rows: name offset nvals values...
    let field = |name: &str| -> Vec<f64> {
        text.lines()
            .map(|l| l.split_whitespace().collect::<Vec<_>>())
            .find(|t| t.first() == Some(&name) && t.len() > 3)
            .unwrap_or_else(|| panic!("nifti_tool printed no {name} for {}", path.display()))[3..]
            .iter()
            .map(|s| s.parse().unwrap())
            .collect()
    };
    let m = if field("sform_code")[0] > 0.0 {
        field("sto_xyz")
    } else {
        field("qto_xyz")
    };
    Nim {
        dims: [field("nx")[0], field("ny")[0], field("nz")[0]].map(|x| x as usize),
        ras_from_ijk: DMat4::from_cols_slice(&m).transpose(), // printed row by row
        slope: field("scl_slope")[0],
        inter: field("scl_inter")[0],
    }
}

/// niftilib's stored values of slice `k` of volume `t`, x fastest, scaled as the header says.
fn nifti_tool_slice(path: &Path, nim: &Nim, k: usize, t: usize) -> Vec<f64> {
    let (k, t) = (k.to_string(), t.to_string());
    let text = run(Command::new("nifti_tool")
        .args(["-disp_ci", "-1", "-1", &k, &t, "0", "0", "0", "-quiet"])
        .arg("-infiles")
        .arg(path));
    let raw = text.split_whitespace().map(|s| s.parse::<f64>().unwrap());
    if nim.slope == 0.0 {
        raw.collect()
    } else {
        raw.map(|x| x * nim.slope + nim.inter).collect()
    }
}

/// Same dims, the same patient-space position of every corner voxel, the same voxel spacing and
/// the same values on three whole slices as niftilib; of volume `t` for a 4-D file.
fn assert_matches_niftilib(path: &Path, t: Option<usize>) -> Volume {
    let name = match t {
        Some(t) => format!("{}#{t}", path.display()),
        None => path.display().to_string(),
    };
    let v = open(Path::new(&name));
    let nim = nifti_tool(path);
    assert_eq!(v.dims, nim.dims, "{name}: dims");
    for ijk in corners(v.dims) {
        let ras = nim.ras_from_ijk * DVec4::from((ijk, 1.0));
        let want = DVec3::new(-ras.x, -ras.y, ras.z); // RAS -> LPS
        let got = lps_of(&v, ijk);
        assert!(
            (got - want).length() < 1e-3,
            "{name}: voxel {ijk} is at LPS {got}, niftilib says {want}"
        );
    }
    for a in 0..3 {
        let col = nim.ras_from_ijk.col(a).truncate().length();
        assert!(
            (v.spacing[a] - col).abs() < 1e-5 * col,
            "{name}: spacing {:?}, niftilib's axis {a} is {col} mm",
            v.spacing
        );
    }
    let [nx, ny, nz] = v.dims;
    for k in [0, nz / 2, nz - 1] {
        let want = nifti_tool_slice(path, &nim, k, t.unwrap_or(0));
        assert_eq!(want.len(), nx * ny, "{name}: nifti_tool's slice {k}");
        for (n, w) in want.iter().enumerate() {
            let got = v.voxels.get(v.index(n % nx, n / nx, k)) as f64;
            assert!(
                (got - w).abs() <= 1e-6 * w.abs().max(1.0),
                "{name}: voxel ({}, {}, {k}) is {got}, niftilib says {w}",
                n % nx,
                n / nx
            );
        }
    }
    v
}

/// Renders both eyes with no AO from the default eye poses, with validation on.
fn render(vol: &Volume, tf: &TransferFunction, size: u32) -> StereoImage {
    let gpu = common::gpu();
    let mut hr = HeadlessRenderer::new(&gpu).unwrap();
    let tex = VolumeTextures::new(&gpu, vol, tf).unwrap();
    let placement = Placement::default();
    let views = default_stereo_views(vol, &placement, 0.064);
    let frame = FrameViews::new(&views, world_from_tex(vol, &placement));
    let settings = RenderSettings {
        use_ao: false,
        ..RenderSettings::default()
    };
    let img = hr.render(&tex, &frame, (size, size), &settings).unwrap();
    drop((tex, hr));
    common::assert_no_validation_messages(&gpu);
    img
}

#[test]
fn nifti_files_from_nibabel_and_mricron_match_niftilib() {
    let dir = foreign_dir();
    let how = "scripts/foreign-data.sh fetches them";
    if !has_tool("nifti_tool", "nifti-bin") {
        return;
    }
    // anatomical: big-endian int16, RAS flipped in x; reoriented_anat_moved: float32, moved;
    // standard: uint8, sform only; example4d: 4-D int16 with a qform, volume 1 of 2;
    // example_nifti2: NIfTI-2 (64-bit dims, double geometry), 4-D, oblique;
    // ch2bet: the Colin27 brain, 181 x 217 x 181 at 1 mm, MNI sform.
    let mut brain = None;
    for (f, t) in [
        ("anatomical.nii", None),
        ("reoriented_anat_moved.nii", None),
        ("standard.nii.gz", None),
        ("example4d.nii.gz", Some(1)),
        ("example_nifti2.nii.gz", Some(0)),
        ("example_nifti2.nii.gz", Some(1)),
        ("KmeansTest_T1UCharRaw.nii.gz", None), // written by ITK
        ("ch2bet.nii.gz", None),
    ] {
        let Some(p) = present(dir.join(f), how) else {
            return;
        };
        let v = assert_matches_niftilib(&p, t);
        if f == "ch2bet.nii.gz" {
            brain = Some(v);
        }
    }
    let brain = brain.unwrap();
    // true physical size: an adult brain template, about 18 x 22 x 18 cm
    let ext = brain.extent_mm();
    assert!(
        (ext - DVec3::new(181.0, 217.0, 181.0)).abs().max_element() < 1e-3,
        "{ext}"
    );
    // it renders: something is drawn, roughly in the middle of the picture
    let img = render(
        &brain.downsample(4),
        &TransferFunction::preset("mr-default").unwrap(),
        96,
    );
    let (cx, cy) = common::centroid(&img, 0).expect("the brain template rendered nothing");
    assert!(
        (cx - 48.0).abs() < 12.0 && (cy - 48.0).abs() < 12.0,
        "{cx} {cy}"
    );

    // a 4-D file without a volume number is refused, naming the file and the choice
    for (f, n) in [("example4d.nii.gz", 2), ("example_nifti2.nii.gz", 2)] {
        let p = dir.join(f);
        let e = load_volume(Some(p.to_str().unwrap()), None)
            .err()
            .unwrap_or_else(|| panic!("{f} loaded"))
            .to_string();
        assert!(
            e.contains(f) && e.contains(&format!("{n} volumes")) && e.contains("#T"),
            "{e}"
        );
    }
}

#[test]
fn an_itk_metaimage_with_detached_data_loads_whole() {
    // ITK's example: three 181 x 217 MRI slices, uchar, 1 mm, data in a separate .raw
    let dir = foreign_dir();
    let how = "scripts/foreign-data.sh fetches it";
    let (Some(mha), Some(raw)) = (
        present(dir.join("BrainProtonDensity3Slices.mha"), how),
        present(dir.join("BrainProtonDensity3Slices.raw"), how),
    ) else {
        return;
    };
    let v = open(&mha);
    assert_eq!(v.dims, [181, 217, 3]);
    assert_eq!(v.spacing, [1.0; 3]);
    assert_eq!(v.voxels, Voxels::U8(std::fs::read(&raw).unwrap()));
}

#[test]
fn a_pydicom_ct_series_matches_dcm2niix_and_teem_in_patient_space() {
    let data = std::env::var_os("CAO_XR_PYDICOM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/lib/python3/dist-packages/pydicom/data/test_files"));
    // a GE LightSpeed calcium-score CT: 5 axial slices 2.5 mm apart (downsampled to 16 x 16)
    let Some(series) = present(
        data.join("dicomdirtests/98892001/CT5N"),
        "apt-get install python3-pydicom",
    ) else {
        return;
    };
    if !has_tool("dcm2niix", "dcm2niix") || !has_tool("teem-unu", "teem-apps") {
        return;
    }
    let root = crate::common::scratch("foreign", "tools");
    let dcm = dicom::load_series(&series, None).unwrap();
    assert_eq!(dcm.dims, [16, 16, 5]);
    // it renders: soft tissue (its values span -888..85 HU) is drawn
    let img = render(
        &dcm,
        &TransferFunction::preset("ct-soft-tissue").unwrap(),
        64,
    );
    assert!(
        common::centroid(&img, 0).is_some(),
        "the CT series rendered nothing"
    );

    run(Command::new("dcm2niix")
        .args(["-z", "n", "-f", "ct", "-o"])
        .arg(&root)
        .arg(&series));
    run(Command::new("dcm2niix")
        .args(["-e", "y", "-f", "ctn", "-o"])
        .arg(&root)
        .arg(&series));
    let unu = |args: &[&str], from: &str, to: &str| {
        run(Command::new("teem-unu")
            .args(args)
            .arg("-i")
            .arg(root.join(from))
            .arg("-o")
            .arg(root.join(to)));
    };
    unu(
        &["permute", "-p", "2", "0", "1"],
        "ctn.nrrd",
        "permuted.nrrd",
    );
    unu(&["flip", "-a", "1"], "ctn.nrrd", "flipped.nrrd");
    unu(
        &["save", "-f", "nrrd", "-e", "gzip", "-en", "big"],
        "permuted.nrrd",
        "big.nhdr",
    );
    unu(&["convert", "-t", "float"], "flipped.nrrd", "float.nrrd");
    // a 4-D series of two volumes, the second one HU higher (teem's join keeps no geometry)
    run(Command::new("teem-unu")
        .args(["2op", "+"])
        .arg(root.join("ctn.nrrd"))
        .args(["1", "-t", "short", "-o"])
        .arg(root.join("plus1.nrrd")));
    run(Command::new("teem-unu")
        .args(["join", "-a", "3", "-incr", "-i"])
        .args([root.join("ctn.nrrd"), root.join("plus1.nrrd")])
        .arg("-o")
        .arg(root.join("series.nrrd")));

    for f in [
        "ct.nii",
        "ctn.nrrd",
        "permuted.nrrd",
        "flipped.nrrd",
        "big.nhdr",
        "float.nrrd",
    ] {
        let other = open(&root.join(f));
        assert_eq!(other.voxel_count(), dcm.voxel_count(), "{f}");
        let mut sorted = other.spacing;
        sorted.sort_by(f64::total_cmp);
        let mut want = dcm.spacing;
        want.sort_by(f64::total_cmp);
        for a in 0..3 {
            assert!(
                (sorted[a] - want[a]).abs() < 1e-4,
                "{f}: spacing {:?}",
                other.spacing
            );
        }
        // every DICOM voxel centre is a voxel centre of the other file, holding the same value
        for k in 0..dcm.dims[2] {
            for j in 0..dcm.dims[1] {
                for i in 0..dcm.dims[0] {
                    let ijk = DVec3::new(i as f64, j as f64, k as f64);
                    let q = index_of(&other, lps_of(&dcm, ijk));
                    let r = q.round();
                    assert!(
                        (q - r).abs().max_element() < 1e-3
                            && r.cmpge(DVec3::ZERO).all()
                            && r.cmplt(DVec3::from(other.dims.map(|d| d as f64))).all(),
                        "{f}: DICOM voxel {ijk} falls at {q} in it"
                    );
                    let (a, b) = (
                        dcm.voxels.get(dcm.index(i, j, k)),
                        other
                            .voxels
                            .get(other.index(r.x as usize, r.y as usize, r.z as usize)),
                    );
                    assert_eq!(a, b, "{f}: voxel {ijk} holds {b}, the DICOM series {a}");
                }
            }
        }
    }
    let ctn = open(&root.join("ctn.nrrd"));
    let series = root.join("series.nrrd").display().to_string();
    for t in 0..2 {
        let v = open(Path::new(&format!("{series}#{t}")));
        assert_eq!(v.dims, ctn.dims);
        for n in 0..v.voxel_count() {
            assert_eq!(
                v.voxels.get(n),
                ctn.voxels.get(n) + t as f32,
                "{series}#{t}"
            );
        }
    }
    let e = load_volume(Some(&series), None).unwrap_err().to_string();
    assert!(e.contains("2 volumes") && e.contains("#T"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

/// Mean world position (m) of the voxels whose value is above `hu`, through the model matrix
/// the ray caster uses.
fn world_centroid_above(vol: &Volume, hu: f32) -> DVec3 {
    let model = world_from_tex(vol, &Placement::default()).as_dmat4();
    let (mut sum, mut n) = (DVec3::ZERO, 0usize);
    for k in 0..vol.dims[2] {
        for j in 0..vol.dims[1] {
            for i in 0..vol.dims[0] {
                if vol.voxels.get(vol.index(i, j, k)) > hu {
                    let tex = (DVec3::new(i as f64, j as f64, k as f64) + 0.5)
                        / DVec3::from(vol.dims.map(|d| d as f64));
                    sum += model.transform_point3(tex);
                    n += 1;
                }
            }
        }
    }
    assert!(n > 0, "no voxel above {hu} HU");
    sum / n as f64
}

/// A transfer function that shows only values above `hu`, opaque.
fn above(hu: f32) -> TransferFunction {
    TransferFunction::from_json(&format!(
        r#"{{ "name": "above-{hu}", "domain": "data", "points": [
            {{ "value": {}, "color": [1, 1, 1], "alpha": 0 }},
            {{ "value": {hu}, "color": [1, 1, 1], "alpha": 1 }} ] }}"#,
        hu - 1.0
    ))
    .unwrap()
}

#[test]
fn the_ct_head_loads_from_its_nrrd_conversion_and_stands_upright() {
    let path = ct_head::cached_path();
    if !path.exists() && common::required("CAO_XR_REQUIRE_FOREIGN") {
        ct_head::fetch(&mut |m| eprintln!("{m}")).unwrap();
    }
    let Some(path) = present(path, "`cao-xr fetch-ct` converts it") else {
        return;
    };
    let vol = open(&path);
    assert_eq!(vol.dims, [256, 256, 108]);
    // true size: about 24.5 x 24.5 x 16.2 cm, from the teeth to the top of the skull
    let ext = vol.extent_mm();
    assert!(
        (ext.x - 245.0).abs() < 1.0 && (ext.z - 162.0).abs() < 1e-6,
        "{ext}"
    );
    // Enamel (above 2000 HU, the densest tissue in a head) sits in the upper jaw: below the
    // middle of the skull and in front of it, i.e. towards a viewer looking down -Z.
    let skull = world_centroid_above(&vol, 300.0);
    let teeth = world_centroid_above(&vol, 2000.0);
    assert!(
        teeth.y < skull.y - 0.03,
        "teeth at {teeth}, skull at {skull}"
    );
    assert!(
        teeth.z > skull.z + 0.05,
        "teeth at {teeth}, skull at {skull}"
    );

    // and so in the picture: the teeth are drawn below the middle of the skull
    let small = vol.downsample(2);
    let bone = render(&small, &TransferFunction::preset("ct-bone").unwrap(), 128);
    let enamel = render(&small, &above(1800.0), 128);
    let (bx, by) = common::centroid(&bone, 0).expect("the CT head rendered nothing");
    let (tx, ty) = common::centroid(&enamel, 0).expect("no enamel rendered");
    assert!(ty > by + 10.0, "teeth drawn at row {ty}, skull at row {by}");
    assert!(
        (tx - bx).abs() < 10.0,
        "teeth at column {tx}, skull at {bx}"
    );
}
