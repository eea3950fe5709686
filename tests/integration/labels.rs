//! Labelled anatomy: label maps written by nibabel on grids of their own are resampled into the
//! volume's grid by physical position exactly as nibabel's own reading gives; a Slicer
//! segmentation's names, colours and values are read; hiding a structure removes it from O; and
//! a carve with protected structures equals the full recompute of the selectively clipped volume
//! bit for bit, leaving the protected voxels standing.

use crate::cao::read_ao;
use crate::common;
use cao_xr::ao::cao::Mode;
use cao_xr::scene::{Tool, ToolMode};
use cao_xr::space::{Placement, Pose};
use cao_xr::volume::labels::{LabelMap, Structure};
use cao_xr::volume::transfer::TransferFunction;
use glam::{Quat, Vec3};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

fn tmp(name: &str) -> crate::common::Scratch {
    crate::common::scratch("labels", name)
}

/// A Python with nibabel and numpy (`python3` on PATH, else the system's).
fn nibabel_python() -> Option<&'static str> {
    let py = ["python3", "/usr/bin/python3"].into_iter().find(|py| {
        Command::new(py)
            .args(["-c", "import nibabel, numpy"])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    common::require_or_skip(
        "CAO_XR_REQUIRE_NIBABEL",
        py.is_some(),
        "nibabel with numpy is missing (apt-get install python3-nibabel)",
    )
    .then_some(py)
    .flatten()
}

/// Writes, with nibabel: a CT (48 x 40 x 32 at 1 x 1 x 1.5 mm, an origin of its own), a
/// multi-label map on another grid (2 mm voxels, x flipped, shifted 0.3 mm off the CT's
/// lattice, cropped), the same structures as a folder of binary masks, and one that lies
/// elsewhere. Prints nibabel's own reading of the label map resampled into the CT's grid (the
/// nearest label voxel to each CT voxel's centre, through both affines): voxels per value, and
/// the value at a few CT voxels.
const WRITE: &str = r#"
import json, os, sys
import numpy as np, nibabel as nib
out = sys.argv[1]
dims = (48, 40, 32)
A = np.diag([1.0, 1.0, 1.5, 1.0]); A[:3, 3] = [-20.0, 30.0, 5.0]
x, y, z = np.meshgrid(*[np.arange(d) for d in dims], indexing='ij')
ct = np.full(dims, -1000, np.int16)
r2 = (x - 24) ** 2 + (y - 20) ** 2 + ((z - 16) * 1.5) ** 2
ct[r2 < 14 ** 2] = 60
ct[r2 < 6 ** 2] = 1200
nib.save(nib.Nifti1Image(ct, A), os.path.join(out, "ct.nii.gz"))
ld = (20, 18, 20)
B = np.diag([-2.0, 2.0, 2.0, 1.0]); B[:3, 3] = [20.3, 29.7, 4.3]
lx, ly, lz = np.meshgrid(*[np.arange(d) for d in ld], indexing='ij')
ras = np.stack([lx, ly, lz, np.ones(ld)], -1) @ B.T
lab = np.zeros(ld, np.uint8)
d = np.linalg.norm(ras[..., :3] - np.array([4.0, 50.0, 29.0]), axis=-1)
lab[d < 14] = 5
lab[d < 6] = 52
lab[(np.abs(ras[..., 0] - 4) < 3) & (np.abs(ras[..., 2] - 29) < 3)] = 64
nib.save(nib.Nifti1Image(lab, B), os.path.join(out, "labels.nii.gz"))
os.makedirs(os.path.join(out, "masks"), exist_ok=True)
# The liver's mask is the whole ball, overlapping the aorta's and the portal vein's: the smaller
# structure wins, so the folder reads as the label map does.
for name, mask in [("liver", d < 14), ("aorta", lab == 52), ("portal_vein", lab == 64)]:
    nib.save(nib.Nifti1Image(mask.astype(np.uint8), B),
             os.path.join(out, "masks", name + ".nii.gz"))
far = B.copy(); far[:3, 3] += 400.0
nib.save(nib.Nifti1Image(lab, far), os.path.join(out, "far.nii.gz"))
vi = np.stack([x, y, z, np.ones(dims)], -1) @ A.T
n = np.rint((vi @ np.linalg.inv(B).T)[..., :3]).astype(int)
inside = np.all((n >= 0) & (n < np.array(ld)), -1)
nn = np.where(inside[..., None], n, 0)
res = np.where(inside, lab[nn[..., 0], nn[..., 1], nn[..., 2]], 0)
counts = {str(int(v)): int((res == v).sum()) for v in np.unique(lab) if v != 0}
probes = [[int(i), int(j), int(k), int(res[i, j, k])]
          for i, j, k in [(24, 20, 16), (24, 20, 10), (30, 20, 16), (10, 5, 3), (24, 8, 16)]]
print(json.dumps({"counts": counts, "probes": probes}))
"#;

/// `cao-xr info` rows of the structures table: (value, name, voxels).
fn info_structures(args: &[&str]) -> Vec<(u32, String, usize)> {
    let out = common::run_cao(args, &[]);
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text.lines()
        .skip_while(|l| !l.trim_start().starts_with("value  name"))
        .skip(1)
        .map(|l| {
            // value, name (to the colour's `#`), colour, voxels, ml, shown
            let (value, rest) = l.trim_start().split_once(' ').unwrap();
            let (name, rest) = rest.split_once(" #").unwrap();
            let voxels = rest.split_whitespace().nth(1).unwrap();
            (
                value.parse().unwrap(),
                name.trim().to_string(),
                voxels.parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn label_maps_written_by_nibabel_resample_by_position_as_nibabel_reads_them() {
    let Some(py) = nibabel_python() else { return };
    let dir = tmp("nibabel");
    let out = Command::new(py)
        .args(["-c", WRITE, dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let want: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let ct = dir.join("ct.nii.gz");
    let ct = ct.to_str().unwrap();
    let count = |v: u32| want["counts"][v.to_string()].as_u64().unwrap() as usize;

    // The multi-label map: TotalSegmentator's class table names values 5, 52 and 64.
    let labels = dir.join("labels.nii.gz");
    let rows = info_structures(&["info", ct, "--labels", labels.to_str().unwrap()]);
    let names: Vec<(u32, &str, usize)> = rows.iter().map(|r| (r.0, r.1.as_str(), r.2)).collect();
    assert_eq!(
        names,
        vec![
            (5, "liver", count(5)),
            (52, "aorta", count(52)),
            (64, "portal_vein_and_splenic_vein", count(64)),
        ]
    );
    assert!(
        count(5) > 1000 && count(52) > 100 && count(64) > 100,
        "{want}"
    );

    // The label at single voxels, through `ao --opacity-out` with every structure but one hidden:
    // O is 0 wherever the voxel's structure is hidden.
    let o_of = |extra: &[&str]| -> Vec<f32> {
        let (ao, op) = (dir.join("ao.nrrd"), dir.join("o.nrrd"));
        let mut args = vec![
            "ao",
            ct,
            "--tf",
            "ct-soft-tissue",
            "--rays",
            "6",
            "--steps",
            "2",
            "--labels",
            labels.to_str().unwrap(),
            "--out",
            ao.to_str().unwrap(),
            "--opacity-out",
            op.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        common::run_cao_ok(&args);
        let bytes = std::fs::read(&op).unwrap();
        let split = bytes.windows(2).position(|w| w == b"\n\n").unwrap();
        bytes[split + 2..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    };
    let all = o_of(&[]);
    let only_aorta = o_of(&["--show", "aorta"]);
    // The CT's i and j axes run right-to-left and anterior-to-posterior in LPS (its RAS affine):
    // the loader keeps the file's voxel order, so voxel (i, j, k) is nibabel's (i, j, k).
    for p in want["probes"].as_array().unwrap() {
        let [i, j, k, label] = [0, 1, 2, 3].map(|n| p[n].as_u64().unwrap() as usize);
        let v = i + 48 * (j + 40 * k);
        let kept = only_aorta[v] == all[v];
        match label {
            52 => assert!(kept, "voxel {i},{j},{k} (aorta) lost its opacity"),
            0 => assert!(kept, "voxel {i},{j},{k} (unlabelled) changed"),
            _ => assert!(
                only_aorta[v] == 0.0,
                "voxel {i},{j},{k} (label {label}) is hidden but has O = {}",
                only_aorta[v]
            ),
        }
    }
    assert!(
        all.iter().zip(&only_aorta).any(|(a, b)| a > b),
        "nothing was hidden"
    );

    // A folder of masks names the structures by file, with the same voxels (the liver's mask
    // overlaps the others, which are smaller and keep their voxels).
    let masks = dir.join("masks");
    let rows = info_structures(&["info", ct, "--labels", masks.to_str().unwrap()]);
    let by_name: Vec<(&str, usize)> = rows.iter().map(|r| (r.1.as_str(), r.2)).collect();
    assert_eq!(
        by_name,
        vec![
            ("aorta", count(52)),
            ("liver", count(5)),
            ("portal_vein", count(64))
        ]
    );

    // An ITK-SNAP label description names them instead.
    let names = dir.join("names.txt");
    std::fs::write(
        &names,
        "# ITK-SnAP Label Description File\n\
         \x20   0     0    0    0        0  0  0    \"Clear Label\"\n\
         \x20   5   221  130  101        1  1  1    \"Liver\"\n\
         \x20  52   255    0    0        1  1  1    \"Aorta\"\n\
         \x20  64     0  151  206        1  1  1    \"Portal vein\"\n",
    )
    .unwrap();
    let out = common::run_cao(
        &[
            "info",
            ct,
            "--labels",
            labels.to_str().unwrap(),
            "--label-names",
            names.to_str().unwrap(),
        ],
        &[],
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("Liver") && text.contains("#dd8265") && text.contains("Portal vein"),
        "{text}"
    );

    // Rendered: a carve through the liver takes everything but the protected vessels, which
    // stand in their own colours; without protection they go too.
    let render = |name: &str, extra: &[&str]| -> Vec<u8> {
        let out = dir.join(name);
        let mut args = vec![
            "render",
            ct,
            "--labels",
            labels.to_str().unwrap(),
            "--tf",
            "ct-soft-tissue",
            "--rays",
            "6",
            "--steps",
            "3",
            "--size",
            "64x64",
            "--background",
            "transparent",
            "--tool",
            "sphere:30:0,0,15",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        common::run_cao_ok(&args);
        cao_xr::render::compare::read_png(&out.join("left.png"))
            .unwrap()
            .rgba
    };
    let coverage = |rgba: &[u8]| rgba.chunks_exact(4).filter(|p| p[3] > 32).count();
    let protected = render(
        "protected",
        &["--protect", "aorta,portal_vein_and_splenic_vein"],
    );
    let open = render("open", &[]);
    assert!(
        coverage(&protected) > coverage(&open) + 10,
        "protected vessels cover {} pixels, the open carve {}",
        coverage(&protected),
        coverage(&open)
    );
    // A label map elsewhere is refused with both extents.
    let far = dir.join("far.nii.gz");
    let out = common::run_cao(&["info", ct, "--labels", far.to_str().unwrap()], &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("far.nii.gz")
            && err.contains("does not overlap")
            && err.contains("the volume"),
        "{err}"
    );
    // A structure nobody labelled is named in the refusal.
    let out = common::run_cao(
        &[
            "info",
            ct,
            "--labels",
            labels.to_str().unwrap(),
            "--hide",
            "tumour",
        ],
        &[],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("no structure 'tumour'"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_slicer_segmentation_gives_its_segments_names_colours_and_values() {
    let dir = tmp("seg");
    let path = dir.join("vessels.seg.nrrd");
    // As 3D Slicer writes a one-layer segmentation: a cropped box with its own origin.
    // 32 mm around the phantom's centre, where its middle 2 x 2 x 2 voxels lie (at +-6.875 mm):
    // value 3 in the left half, 7 in the right.
    let (w, h, d) = (16usize, 16usize, 16usize);
    let data: Vec<u8> = (0..w * h * d)
        .map(|i| if i % w < 8 { 3 } else { 7 })
        .collect();
    let header = format!(
        "NRRD0004\n# Complete NRRD file format specification at:\n\
         type: unsigned char\ndimension: 3\nspace: left-posterior-superior\n\
         sizes: {w} {h} {d}\nspace directions: (2,0,0) (0,2,0) (0,0,2)\n\
         kinds: domain domain domain\nencoding: raw\nspace origin: (-15,-15,-15)\n\
         Segment0_Color:=0.9 0.1 0.1\nSegment0_ID:=Segment_1\nSegment0_LabelValue:=3\n\
         Segment0_Layer:=0\nSegment0_Name:=hepatic artery\n\
         Segment1_Color:=0.2 0.3 0.9\nSegment1_ID:=Segment_2\nSegment1_LabelValue:=7\n\
         Segment1_Layer:=0\nSegment1_Name:=portal vein\n\n"
    );
    let mut bytes = header.into_bytes();
    bytes.extend_from_slice(&data);
    std::fs::write(&path, bytes).unwrap();
    let rows = info_structures(&["info", "phantom:16", "--labels", path.to_str().unwrap()]);
    let got: Vec<(u32, &str)> = rows.iter().map(|r| (r.0, r.1.as_str())).collect();
    assert_eq!(got, vec![(3, "hepatic artery"), (7, "portal vein")]);
    let out = common::run_cao(
        &["info", "phantom:16", "--labels", path.to_str().unwrap()],
        &[],
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("#e61a1a") && text.contains("#334de6"),
        "{text}"
    );
    // Each segment holds 4 of the phantom's middle voxels, by position.
    assert!(rows.iter().all(|r| r.2 == 4), "{rows:?}");
    // A second layer (overlapping segments) is refused by name, not misread.
    let mut two_bytes = std::fs::read(&path).unwrap();
    let at = two_bytes
        .windows(16)
        .position(|w| w == b"Segment1_Layer:=")
        .unwrap()
        + 16;
    two_bytes[at] = b'1';
    let two = dir.join("two.seg.nrrd");
    std::fs::write(&two, two_bytes).unwrap();
    let out = common::run_cao(
        &["info", "phantom:16", "--labels", two.to_str().unwrap()],
        &[],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("layer 1"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The phantom head with two structures: a vessel (a rod through the skull, id 1) and the
/// tissue around it (a ball, id 2).
pub(crate) fn labelled_head(n: usize, protect_vessel: bool) -> cao_xr::volume::Volume {
    let mut vol = cao_xr::volume::phantom::head(n);
    let c = n as f64 / 2.0;
    let ids: Vec<u8> = (0..vol.voxel_count())
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            let p = [x as f64 + 0.5 - c, y as f64 + 0.5 - c, z as f64 + 0.5 - c];
            if (p[0] * p[0] + p[1] * p[1]).sqrt() < 2.5 {
                1
            } else if (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() < 0.4 * n as f64 {
                2
            } else {
                0
            }
        })
        .collect();
    let structure = |value, name: &str, protected| Structure {
        value,
        name: name.into(),
        colour: [0.8, 0.1, 0.1],
        opacity: 1.0,
        protected,
        margin_mm: None,
        voxels: 0,
    };
    vol.labels = Some(Arc::new(LabelMap {
        source: "test".into(),
        ids,
        structures: vec![
            structure(1, "vessel", protect_vessel),
            structure(2, "tissue", false),
        ],
    }));
    vol
}

#[test]
fn carving_around_a_protected_structure_equals_the_full_recompute_and_leaves_it_standing() {
    let gpu = common::gpu();
    let vol = labelled_head(40, true);
    let (mut cao, o, _) = crate::cao::setup(&gpu, &vol);
    let (mut naive, _, _) = crate::cao::setup(&gpu, &vol);
    let placement = Placement::default();
    let c = placement.center;
    let carve = |position: Vec3, size: f32| Tool {
        shape: cao_xr::clip::Shape::Sphere,
        pose: Pose {
            position,
            orientation: Quat::IDENTITY,
        },
        size,
        mode: ToolMode::Carve,
        active: true,
    };
    // Through the vessel's middle, along it, and a frame with no tool.
    let frames = [
        vec![carve(c, 0.06)],
        vec![carve(c + Vec3::new(0.0, 0.03, 0.02), 0.05)],
        vec![carve(c + Vec3::new(0.02, -0.02, 0.0), 0.04), carve(c, 0.03)],
        vec![],
    ];
    let ids = &vol.labels.as_ref().unwrap().ids;
    let mut spared_somewhere = false;
    for (f, tools) in frames.iter().enumerate() {
        cao.run_frame(tools, &placement, Mode::Contextual).unwrap();
        naive.run_frame(tools, &placement, Mode::Naive).unwrap();
        let (a, b) = (crate::cao::read_ao(&cao.ao), crate::cao::read_ao(&naive.ao));
        let diff = common::first_bit_difference(&a, &b);
        assert!(
            diff.is_none(),
            "frame {f}: CAO differs from the full recompute at {diff:?}"
        );
        let oc = cao.read_clipped().unwrap();
        assert_eq!(oc, naive.read_clipped().unwrap(), "frame {f}");
        // Inside the cut the vessel keeps O, the tissue around it is carved.
        let vessel_kept = (0..o.len()).all(|i| ids[i] != 1 || oc[i] == o[i]);
        assert!(vessel_kept, "frame {f}: a protected voxel lost opacity");
        if !tools.is_empty() {
            let carved_tissue = (0..o.len()).any(|i| ids[i] == 2 && o[i] > 0.0 && oc[i] == 0.0);
            assert!(carved_tissue, "frame {f}: the tissue was not carved");
            spared_somewhere = true;
        }
    }
    assert!(spared_somewhere);
    // Without protection the same carve takes the vessel too.
    let open = labelled_head(40, false);
    let (mut plain, o, _) = crate::cao::setup(&gpu, &open);
    plain
        .run_frame(&frames[0], &placement, Mode::Contextual)
        .unwrap();
    let oc = plain.read_clipped().unwrap();
    let ids = &open.labels.as_ref().unwrap().ids;
    assert!(
        (0..o.len()).any(|i| ids[i] == 1 && o[i] > 0.0 && oc[i] == 0.0),
        "without protection the vessel should be carved"
    );
    common::assert_no_validation_messages(&gpu);
}

/// The structure menu protects and unprotects a structure mid-carve (`Cao::set_protected`):
/// from that frame on the carve takes it or leaves it standing, and CAO still equals the full
/// recompute bit for bit on every frame.
#[test]
fn protecting_a_structure_mid_carve_stays_exact() {
    let gpu = common::gpu();
    let vol = labelled_head(32, false);
    let (mut cao, o, _) = crate::cao::setup(&gpu, &vol);
    let (mut naive, _, _) = crate::cao::setup(&gpu, &vol);
    let placement = Placement::default();
    let c = placement.center;
    let ids = &vol.labels.as_ref().unwrap().ids;
    // The vessel (structure 0) open, protected, protected, open again; the tool moving on.
    let protect = [false, true, true, false];
    for (f, &p) in protect.iter().enumerate() {
        let tools = [Tool {
            shape: cao_xr::clip::Shape::Sphere,
            pose: Pose {
                position: c + Vec3::new(0.005 * f as f32, 0.01, 0.0),
                orientation: Quat::IDENTITY,
            },
            size: 0.05,
            mode: ToolMode::Carve,
            active: true,
        }];
        for state in [&mut cao, &mut naive] {
            state.set_protected(&[p, false]);
        }
        cao.run_frame(&tools, &placement, Mode::Contextual).unwrap();
        naive.run_frame(&tools, &placement, Mode::Naive).unwrap();
        let (a, b) = (crate::cao::read_ao(&cao.ao), crate::cao::read_ao(&naive.ao));
        let diff = common::first_bit_difference(&a, &b);
        assert!(diff.is_none(), "frame {f}: CAO differs at {diff:?}");
        let oc = cao.read_clipped().unwrap();
        let vessel_kept = (0..o.len()).all(|i| ids[i] != 1 || oc[i] == o[i]);
        assert_eq!(
            vessel_kept, p,
            "frame {f}: protected {p}, kept {vessel_kept}"
        );
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn hidden_structures_leave_o_and_translucent_ones_scale_it() {
    let mut vol = labelled_head(24, false);
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let base = {
        let mut plain = vol.clone();
        plain.labels = None;
        tf.opacity_volume(&plain)
    };
    let mut map = (**vol.labels.as_ref().unwrap()).clone();
    map.apply(&cao_xr::volume::labels::LabelDisplay {
        hide: vec!["vessel".into()],
        opacity: vec!["tissue=0.5".into()],
        ..Default::default()
    })
    .unwrap();
    let ids = map.ids.clone();
    vol.labels = Some(Arc::new(map));
    let o = tf.opacity_volume(&vol);
    for i in 0..o.len() {
        let want = match ids[i] {
            1 => 0.0,
            2 => base[i] * 0.5,
            _ => base[i],
        };
        assert_eq!(o[i], want, "voxel {i} (structure {})", ids[i]);
    }
    assert!(ids.iter().zip(&base).any(|(&id, &b)| id == 1 && b > 0.0));
}

#[test]
fn a_tool_entering_a_safety_margin_is_told_with_the_exact_distance() {
    use cao_xr::app::frame_loop::FrameLoop;
    use cao_xr::input::{FrameInput, InteractionSettings};
    use cao_xr::space::{default_stereo_views, world_from_tex};
    let gpu = common::gpu();
    let n = 48;
    let mut vol = labelled_head(n, false);
    let margin = 20.0;
    let mut map = (**vol.labels.as_ref().unwrap()).clone();
    map.apply(&cao_xr::volume::labels::LabelDisplay {
        margin: vec![format!("vessel={margin}")],
        ..Default::default()
    })
    .unwrap();
    assert!(map.report(vol.spacing).contains("margin 20 mm"));
    vol.labels = Some(Arc::new(map));
    let vol = Arc::new(vol);
    let params = cao_xr::ao::LaoParams {
        rays: 6,
        steps: 4,
        step_mm: 4.0,
    };
    let new_loop_on = |gpu: &cao_xr::gpu::Gpu, vol: Arc<cao_xr::volume::Volume>| {
        let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
        let settings = InteractionSettings::default();
        FrameLoop::new(gpu, vol, tfs, params, (32, 32), settings, false).unwrap()
    };
    let new_loop = |vol| new_loop_on(&gpu, vol);
    let mut fl = new_loop(Arc::clone(&vol));
    // Under 4/5 of what the volume needs (its set-up and its frames' room) it is shown
    // downsampled, and the distances are still measured at full resolution.
    let tight = common::gpu();
    let need = gpu.session_memory_peak() + cao_xr::app::inset::frame_reserve(vol.voxel_count());
    tight.set_memory_budget(Some(need * 4 / 5));
    let mut coarse = new_loop_on(&tight, Arc::clone(&vol));
    assert!(
        coarse.volume().name.contains("-ds"),
        "{}",
        coarse.volume().name
    );
    let placement = Placement::default();
    // The vessel's voxel centres in the world, for the brute-force distance.
    let model = world_from_tex(&vol, &placement);
    let ids = &vol.labels.as_ref().unwrap().ids;
    let vessel: Vec<Vec3> = (0..ids.len())
        .filter(|&i| ids[i] == 1)
        .map(|i| {
            let p = [i % n, (i / n) % n, i / (n * n)].map(|v| (v as f32 + 0.5) / n as f32);
            model.transform_point3(Vec3::from_array(p))
        })
        .collect();
    let half_diagonal = 0.5 * 3f32.sqrt() * vol.spacing[0] as f32;
    let radius = 0.01;
    let views = default_stereo_views(&vol, &placement, 0.064);
    let mut seen = [false; 2];
    // Sideways from the vessel, from far to touching; carving or only held.
    for (f, dx) in [0.07f32, 0.05, 0.04, 0.032, 0.02, 0.0]
        .into_iter()
        .enumerate()
    {
        let centre = placement.center + Vec3::new(dx, 0.0, 0.0);
        let tool = Tool {
            shape: cao_xr::clip::Shape::Sphere,
            pose: Pose {
                position: centre,
                orientation: Quat::IDENTITY,
            },
            size: radius,
            mode: ToolMode::Carve,
            active: f % 2 == 0,
        };
        let brute = vessel
            .iter()
            .map(|v| ((v.distance(centre) - radius) * 1e3).max(0.0))
            .fold(f32::INFINITY, f32::min);
        coarse.scene.tools = vec![tool];
        let told = coarse
            .frame(&FrameInput::without_hands(f as f64, views))
            .unwrap();
        if let Some(h) = told.stats.margins.first() {
            assert!(
                (h.distance_mm - brute).abs() <= half_diagonal,
                "frame {f}, downsampled: reported {} mm, brute force {brute} mm",
                h.distance_mm
            );
        }
        fl.scene.tools = vec![tool];
        let out = fl
            .frame(&FrameInput::without_hands(f as f64, views))
            .unwrap();
        let hit = out.stats.margins.first();
        if (brute - margin).abs() > half_diagonal {
            for (hit, what) in [(hit, "full"), (told.stats.margins.first(), "downsampled")] {
                assert_eq!(
                    hit.is_some(),
                    brute < margin,
                    "frame {f}, {what}: {brute} mm, {hit:?}"
                );
            }
        }
        if let Some(h) = hit {
            assert_eq!((h.tool, h.structure, h.margin_mm), (0, 0, margin));
            assert!(
                (h.distance_mm - brute).abs() <= half_diagonal,
                "frame {f}: reported {} mm, brute force {brute} mm",
                h.distance_mm
            );
            let line = fl.margin_warning(&out.stats.margins).unwrap();
            assert!(line.starts_with("margin vessel "), "{line}");
        }
        seen[hit.is_some() as usize] = true;
    }
    assert_eq!(
        seen,
        [true, true],
        "frames both outside and inside the margin"
    );
    // The margin glows (emission only): without tools, the same frame without the margin is
    // nowhere brighter and somewhere darker.
    let mut plain = (*vol).clone();
    let mut map = (**plain.labels.as_ref().unwrap()).clone();
    map.structures[0].margin_mm = None;
    plain.labels = Some(Arc::new(map));
    let mut dark = new_loop(Arc::new(plain));
    let shot = |fl: &mut FrameLoop| {
        fl.settings.jitter = false;
        fl.scene.tools.clear();
        fl.frame(&FrameInput::without_hands(0.0, views))
            .unwrap()
            .image
            .rgba[0]
            .clone()
    };
    let (glowing, plain) = (shot(&mut fl), shot(&mut dark));
    assert!(
        glowing.iter().zip(&plain).all(|(g, p)| g >= p),
        "the glow darkened a pixel"
    );
    assert!(glowing != plain, "no glow");
    common::assert_no_validation_messages(&gpu);
}

/// A Python with `package` (pinned, so that the files it writes do not change under us): a
/// private virtual environment in the cache, made once with pip (`python3 -m venv`); `imports`
/// must import there. Skipped, or failed with `require` set, where it cannot be made.
fn private_python(package: &str, imports: &str, require: &str) -> Option<PathBuf> {
    let home = std::env::var_os("HOME").map(PathBuf::from)?;
    let venv = home.join(".cache/cao-xr").join(package.replace("==", "-"));
    let py = venv.join("bin/python");
    let works = |py: &PathBuf| {
        Command::new(py)
            .args(["-c", &format!("import {imports}")])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !works(&py) {
        let made = Command::new("python3")
            .args(["-m", "venv"])
            .arg(&venv)
            .status()
            .is_ok_and(|s| s.success())
            && Command::new(venv.join("bin/pip"))
                .args(["install", "-q", package])
                .status()
                .is_ok_and(|s| s.success());
        if !made {
            let _ = std::fs::remove_dir_all(&venv);
        }
    }
    common::require_or_skip(
        require,
        works(&py),
        &format!("{package} could not be installed into a private Python environment (python3-venv, pip)"),
    )
    .then_some(py)
}

/// Runs `tests/data/SCRIPT DIR` with `py`; its standard output (what the script read back).
fn run_data_script(py: &Path, script: &str, dir: &Path) -> Vec<u8> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(script);
    let out = Command::new(py).arg(script).arg(dir).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
}

/// highdicom, for DICOM SEG.
fn highdicom_python() -> Option<PathBuf> {
    private_python(
        "highdicom==0.28.2",
        "highdicom, pydicom, numpy",
        "CAO_XR_REQUIRE_HIGHDICOM",
    )
}

#[test]
fn overlapping_slicer_segments_written_by_pynrrd_read_as_pynrrd_reads_them() {
    let Some(py) = private_python("pynrrd==1.1.3", "nrrd, numpy", "CAO_XR_REQUIRE_PYNRRD") else {
        return;
    };
    let dir = tmp("seg-layers");
    let stdout = run_data_script(&py, "write_seg_nrrd.py", &dir);
    // pynrrd's reading, under the rule that the smaller segment wins where segments overlap.
    let want: std::collections::BTreeMap<String, usize> = serde_json::from_slice(&stdout).unwrap();
    let (vol, seg) = (dir.join("volume.nrrd"), dir.join("overlap.seg.nrrd"));
    let rows = info_structures(&[
        "info",
        vol.to_str().unwrap(),
        "--labels",
        seg.to_str().unwrap(),
    ]);
    // Two layers both use value 1: the liver keeps it, the tumour takes the first free value.
    let got: Vec<(u32, &str)> = rows.iter().map(|r| (r.0, r.1.as_str())).collect();
    assert_eq!(got, [(1, "liver"), (2, "portal vein"), (3, "tumour")]);
    for (_, name, voxels) in &rows {
        assert_eq!(
            Some(voxels),
            want.get(name),
            "{name}: {rows:?} against {want:?}"
        );
    }
    assert!(
        want["tumour"] > 50,
        "the tumour lies inside the liver: {want:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dicom_segmentations_written_by_highdicom_resample_by_position_as_highdicom_reads_them() {
    let Some(py) = highdicom_python() else { return };
    let dir = tmp("dicom-seg");
    let stdout = run_data_script(&py, "write_dicom_seg.py", &dir);
    let want: serde_json::Value = serde_json::from_slice(&stdout).unwrap();
    let voxels = |name: &str| -> Vec<usize> {
        want[name]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect()
    };
    let (tumour, liver) = (voxels("tumour"), voxels("liver"));
    assert!(!tumour.is_empty() && !liver.is_empty(), "{want}");
    let expected = vec![
        (1, "tumour".to_string(), tumour.len()),
        (2, "liver".to_string(), liver.len()),
    ];
    let ct = dir.join("ct");
    let ct = ct.to_str().unwrap();
    // An opacity everywhere, so that O shows where a hidden structure is.
    let tf = dir.join("flat.json");
    std::fs::write(
        &tf,
        r#"{ "name": "flat", "domain": "data", "points": [
            { "value": -2000, "color": [1, 1, 1], "alpha": 0.5 },
            { "value": 3000, "color": [1, 1, 1], "alpha": 0.5 } ] }"#,
    )
    .unwrap();
    let hidden_voxels = |seg: &Path, name: &str| -> Vec<usize> {
        let (op, ao) = (dir.join("o.nrrd"), dir.join("ao.nrrd"));
        let args = [
            "ao",
            ct,
            "--tf",
            tf.to_str().unwrap(),
            "--rays",
            "6",
            "--steps",
            "2",
            "--labels",
            seg.to_str().unwrap(),
            "--hide",
            name,
            "--out",
            ao.to_str().unwrap(),
            "--opacity-out",
            op.to_str().unwrap(),
        ];
        common::run_cao_ok(&args);
        let bytes = std::fs::read(&op).unwrap();
        let split = bytes.windows(2).position(|w| w == b"\n\n").unwrap();
        bytes[split + 2..]
            .chunks_exact(4)
            .enumerate()
            .filter(|(_, c)| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) == 0.0)
            .map(|(i, _)| i)
            .collect()
    };
    // Binary and fractional, each given as a file: segment numbers, labels, voxel counts, and
    // each segment's voxels where highdicom puts them.
    for kind in ["binary", "fractional"] {
        let seg = dir.join(format!("seg-{kind}.dcm"));
        let rows = info_structures(&["info", ct, "--labels", seg.to_str().unwrap()]);
        assert_eq!(rows, expected, "{kind}");
        assert_eq!(
            hidden_voxels(&seg, "tumour"),
            tumour,
            "{kind}: the tumour's voxels"
        );
        assert_eq!(
            hidden_voxels(&seg, "liver"),
            liver,
            "{kind}: the liver's voxels"
        );
    }
    // The recommended display colour (CIELab of pure red for the tumour) reads as red.
    let seg = dir.join("seg-binary.dcm");
    let out = common::run_cao_ok(&["info", ct, "--labels", seg.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("tumour                            #ff0000"),
        "{text}"
    );
    // Beside the series in its folder: the series still loads (the SEG is not an image), and
    // --labels with the folder finds the SEG.
    std::fs::copy(&seg, dir.join("ct/seg.dcm")).unwrap();
    let rows = info_structures(&["info", ct, "--labels", ct]);
    assert_eq!(rows, expected, "the SEG in the series folder");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The structure menu (the left hand's X selects, Y cycles shown / translucent / hidden) hides a
/// structure at run time as a TF switch does: the old picture and AO stay until V_PAO' is
/// complete, slab by slab ("labels tissue hidden x%"), a second press mid-way restarts it, and
/// from then on V_AO and the picture equal a loop started with the structure hidden, carving.
#[test]
fn the_structure_menu_hides_a_structure_progressively_then_equals_a_fresh_start() {
    use cao_xr::ao::{AoConfig, LaoGpu, LaoParams};
    use cao_xr::app::frame_loop::{FrameLoop, FrameOutput};
    use cao_xr::input::{FrameInput, InteractionSettings};
    use cao_xr::space::default_stereo_views;

    const N: usize = 32;
    const PARAMS: LaoParams = LaoParams {
        rays: 6,
        steps: 6,
        step_mm: 4.0,
    };
    let gpu = common::gpu();
    let vol = Arc::new(labelled_head(N, false));
    let mut hidden = labelled_head(N, false);
    Arc::get_mut(hidden.labels.as_mut().unwrap())
        .unwrap()
        .structures[1]
        .opacity = 0.0;
    let hidden = Arc::new(hidden);
    let tf = TransferFunction::preset("ct-bone").unwrap();
    let new_loop = |vol: &Arc<cao_xr::volume::Volume>, mode: Mode| {
        let mut fl = FrameLoop::new(
            &gpu,
            Arc::clone(vol),
            vec![tf.clone()],
            AoConfig::from(PARAMS),
            (48, 48),
            InteractionSettings::default(),
            false,
        )
        .unwrap();
        fl.mode = mode;
        fl.tf_samples_per_frame = LaoGpu::samples_per_slice(vol.dims, &PARAMS) * 8.0;
        fl
    };
    let c = Placement::default().center;
    let tool = |i: usize| Tool {
        shape: cao_xr::clip::Shape::Sphere,
        pose: Pose {
            position: c + Vec3::new(-0.03 + 0.01 * (i % 6) as f32, 0.02, 0.05),
            orientation: Quat::IDENTITY,
        },
        size: 0.03,
        mode: ToolMode::Carve,
        active: i % 4 != 3,
    };
    // Frame i with the left hand's X (`next`) and Y (`cycle`) buttons.
    let frame = |fl: &mut FrameLoop, i: usize, next: bool, cycle: bool| -> FrameOutput {
        let views = default_stereo_views(&vol, &Placement::default(), 0.064);
        let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
        input.hands[0].buttons.primary = next;
        input.hands[0].buttons.secondary = cycle;
        fl.scene.tools = vec![tool(i)];
        fl.frame(&input).unwrap()
    };

    let mut fl = new_loop(&vol, Mode::Contextual);
    let mut still = new_loop(&vol, Mode::Contextual);
    assert_eq!(fl.scene.structures, [1.0, 1.0]);
    assert_eq!(
        fl.structure_menu().as_deref(),
        Some("structure 1/2 vessel: shown")
    );
    // X selects the tissue; Y makes it translucent; Y again (after a release, mid-way through
    // that switch) hides it, restarting the recompute.
    let presses = [(true, false), (false, true), (false, false), (false, false)];
    let mut progress = Vec::new();
    let mut i = 0;
    let switched = loop {
        assert!(i < 100, "the switch never finished: {progress:?}");
        let (next, mut cycle) = presses.get(i).copied().unwrap_or((false, false));
        if i == 4 {
            cycle = true;
        }
        let a = frame(&mut fl, i, next, cycle);
        let b = frame(&mut still, i, false, false);
        match a.stats.tf_progress {
            Some(p) if i > 0 => {
                // The old structures, picture and AO while V_PAO' is computed.
                assert!(a.image == b.image, "frame {i}: the picture changed early");
                let d = common::first_bit_difference(&read_ao(&fl.cao.ao), &read_ao(&still.cao.ao));
                assert!(d.is_none(), "frame {i}: V_AO changed early at {d:?}");
                progress.push(p.to_string());
            }
            None if i > 4 => break a,
            _ => {}
        }
        i += 1;
    };
    assert_eq!(fl.scene.structures, [1.0, 0.0]);
    assert_eq!(
        fl.structure_menu().as_deref(),
        Some("structure 2/2 tissue: hidden")
    );
    assert!(
        progress.iter().any(|p| p.starts_with("labels tissue 0.30")),
        "{progress:?}"
    );
    assert!(
        progress
            .iter()
            .any(|p| p.starts_with("labels tissue hidden")),
        "{progress:?}"
    );
    assert!(
        progress.len() > 3,
        "LAO should arrive over several frames: {progress:?}"
    );

    // From the switch on: bit for bit a loop started with the tissue hidden (and its naive
    // full recompute), carving and not.
    let mut fresh = new_loop(&hidden, Mode::Contextual);
    let mut naive = new_loop(&hidden, Mode::Naive);
    let mut shown = Some(switched);
    for k in 0..3 {
        let at = i + k;
        let a = shown
            .take()
            .unwrap_or_else(|| frame(&mut fl, at, false, false));
        let f = frame(&mut fresh, at, false, false);
        frame(&mut naive, at, false, false);
        let ao = read_ao(&fl.cao.ao);
        let d = common::first_bit_difference(&ao, &read_ao(&fresh.cao.ao));
        assert!(
            d.is_none(),
            "frame {at}: V_AO differs from a fresh start at {d:?}"
        );
        let d = common::first_bit_difference(&ao, &read_ao(&naive.cao.ao));
        assert!(
            d.is_none(),
            "frame {at}: V_AO differs from the full recompute at {d:?}"
        );
        assert!(
            a.image == f.image,
            "frame {at}: the picture differs from a fresh start"
        );
        let b = frame(&mut still, at, false, false);
        assert!(
            a.image != b.image,
            "frame {at}: hiding the tissue changed nothing"
        );
    }
    common::assert_no_validation_messages(&gpu);
}

/// In the headset the structure menu is written above the left hand ("vessel: shown"), facing
/// the head, only while that hand is tracked; a press of Y rewrites it ("vessel: 0.30", translucent).
#[test]
fn the_structure_menu_is_written_above_the_left_hand() {
    use cao_xr::app::frame_loop::FrameLoop;
    use cao_xr::input::{pose, FrameInput, HandInput, InteractionSettings, LEFT};
    use cao_xr::space::default_stereo_views;
    const SIZE: usize = 160;
    let gpu = common::gpu();
    let vol = Arc::new(labelled_head(24, false));
    let mut fl = FrameLoop::new(
        &gpu,
        Arc::clone(&vol),
        vec![TransferFunction::preset("ct-bone").unwrap()],
        cao_xr::ao::LaoParams {
            rays: 6,
            steps: 2,
            step_mm: 4.0,
        },
        (SIZE as u32, SIZE as u32),
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.settings.jitter = false;
    let views = default_stereo_views(&vol, &Placement::default(), 0.064);
    // The left hand 10 cm in front of the volume's centre and 4 cm below it: the text is 5 cm
    // above the grip.
    let grip = Placement::default().center + Vec3::new(0.0, -0.04, 0.1);
    let hand = |tracked: bool, secondary: bool| {
        let g = pose(grip, Quat::IDENTITY);
        let mut h = HandInput {
            tracked,
            grip: g,
            aim: g,
            ..HandInput::default()
        };
        h.buttons.secondary = secondary;
        h
    };
    let mut frame = |i: usize, tracked: bool, secondary: bool| {
        let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
        input.hands[LEFT] = hand(tracked, secondary);
        fl.frame(&input).unwrap().image.rgba[0].clone()
    };
    let untracked = frame(0, false, false);
    let shown = frame(1, true, false);
    // Pixels that changed, within the text's rows (2.5 cm either side of its middle) and
    // outside them (the hand's marker).
    let vp = views[0].view_proj();
    let row_of = |p: Vec3| {
        let c = vp * p.extend(1.0);
        ((c.y / c.w + 1.0) * 0.5 * SIZE as f32) as usize
    };
    let middle = grip + Vec3::new(0.0, 0.05, 0.0);
    let (top, bottom) = (
        row_of(middle + Vec3::Y * 0.006),
        row_of(middle - Vec3::Y * 0.006),
    );
    let changed = |a: &[u8], b: &[u8], rows: std::ops::Range<usize>| {
        (rows.start * SIZE..rows.end * SIZE)
            .filter(|&p| a[4 * p..4 * p + 4] != b[4 * p..4 * p + 4])
            .count()
    };
    let text_rows = top..bottom + 1;
    let in_text = changed(&untracked, &shown, text_rows.clone());
    assert!(
        in_text > 40,
        "{in_text} pixels of text in rows {text_rows:?}"
    );
    // Y rewrites it: another word, other pixels in the same rows.
    let translucent = frame(2, true, true);
    assert_eq!(fl.selected_structure().as_deref(), Some("vessel: 0.30"));
    assert!(changed(&shown, &translucent, text_rows.clone()) > 10);
    common::assert_no_validation_messages(&gpu);
}
