//! DICOM series written by an independent writer (dcmtk's dump2dcm, compressed copies by
//! dcmcrle / dcmcjpeg / dcmcjpls) load back with the right voxels and geometry; bad series are
//! refused with the file and the problem named.
//!
//! Without dcmtk these tests are skipped with a message, unless CAO_XR_REQUIRE_DCMTK is set
//! (scripts/test.sh sets it; scripts/setup.sh installs dcmtk).

use crate::common;
use cao_xr::volume::dicom::{self, Pick};
use cao_xr::volume::{Modality, Volume, Voxels};
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};
use std::process::Command;

fn have_dcmtk() -> bool {
    let ok = Command::new("dump2dcm")
        .arg("--version")
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    common::require_or_skip(
        "CAO_XR_REQUIRE_DCMTK",
        ok,
        "dcmtk (dump2dcm) is missing (apt-get install dcmtk)",
    )
}

fn tmp(name: &str) -> crate::common::Scratch {
    crate::common::scratch("dicom", name)
}

fn run(cmd: &mut Command) {
    let out = cmd.output().expect("run a dcmtk tool");
    assert!(
        out.status.success(),
        "{:?} failed: {}{}",
        cmd,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A decimal string of at most 16 characters (the DS limit).
fn ds(v: f64) -> String {
    for prec in (0..=6).rev() {
        let s = format!("{v:.prec$}");
        let s = if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        };
        if s.len() <= 16 {
            return if s == "-0" { "0".into() } else { s };
        }
    }
    panic!("{v} does not fit a DS")
}

fn ds_list(v: &[f64]) -> String {
    v.iter().map(|&x| ds(x)).collect::<Vec<_>>().join("\\")
}

/// What one series looks like on disk.
#[derive(Clone)]
struct Spec {
    cols: usize,
    rows: usize,
    slices: usize,
    row_dir: DVec3,
    col_dir: DVec3,
    /// IPP of slice k = origin + k * step.
    origin: DVec3,
    step: DVec3,
    /// (row spacing, column spacing) as in PixelSpacing.
    pixel_spacing: [f64; 2],
    bits_stored: u16,
    signed: bool,
    modality: &'static str,
    uid: String,
    description: &'static str,
    number: i32,
    /// (slope, intercept) of slice k.
    rescale: Vec<(f64, f64)>,
    /// Stored values, x fastest, slice by slice (in slice order k).
    stored: Vec<i32>,
    /// TriggerTime (ms) of every slice, for one phase of a multi-phase series.
    trigger_ms: Option<f64>,
    /// Added to the InstanceNumber (and SOP instance UID) of every slice.
    instance_base: usize,
}

impl Spec {
    /// 24 x 20 x 12, oblique (row (0.6, 0.8, 0), column (0, 0, -1)), 0.5 x 0.75 mm pixels,
    /// 2.5 mm slices, signed 16-bit stored values with slope 1 intercept -1024 (some stored
    /// values negative).
    fn oblique() -> Spec {
        let (cols, rows, slices) = (24, 20, 12);
        let row_dir = DVec3::new(0.6, 0.8, 0.0);
        let col_dir = DVec3::new(0.0, 0.0, -1.0);
        let n = row_dir.cross(col_dir);
        let mut stored = Vec::new();
        for k in 0..slices {
            for j in 0..rows {
                for i in 0..cols {
                    stored.push(((i * 97 + j * 31 + k * 211) % 4000) as i32 - 1024 - 900);
                }
            }
        }
        Spec {
            cols,
            rows,
            slices,
            row_dir,
            col_dir,
            origin: DVec3::new(-10.5, 20.25, 33.0),
            step: n * 2.5,
            pixel_spacing: [0.75, 0.5],
            bits_stored: 16,
            signed: true,
            modality: "CT",
            uid: "1.2.826.0.1.3680043.2.1143.7001".into(),
            description: "oblique test",
            number: 3,
            rescale: vec![(1.0, -1024.0); slices],
            stored,
            trigger_ms: None,
            instance_base: 0,
        }
    }

    /// The same series cut to its first `n` slices.
    fn first_slices(mut self, n: usize) -> Spec {
        self.slices = n;
        self.rescale.truncate(n);
        self.stored.truncate(n * self.cols * self.rows);
        self
    }

    fn normal(&self) -> DVec3 {
        self.row_dir.cross(self.col_dir)
    }

    /// The volume the series should load as.
    fn expected(&self) -> Volume {
        let plane = self.cols * self.rows;
        let v: Vec<i16> = self
            .stored
            .iter()
            .enumerate()
            .map(|(n, &s)| {
                let (slope, inter) = self.rescale[n / plane];
                (s as f64 * slope + inter) as i16
            })
            .collect();
        Volume {
            whole_range: None,
            name: String::new(),
            dims: [self.cols, self.rows, self.slices],
            spacing: [
                self.pixel_spacing[1],
                self.pixel_spacing[0],
                self.step.dot(self.normal()),
            ],
            directions: DMat3::from_cols(self.row_dir, self.col_dir, self.normal()),
            origin: self.origin,
            modality: Modality::Ct,
            voxels: Voxels::I16(v),
            labels: None,
        }
    }

    /// The dcmtk dump of slice `k` (pixel data read from `raw`).
    fn dump(&self, k: usize, raw: &Path) -> String {
        let ipp = self.origin + self.step * k as f64;
        let (slope, inter) = self.rescale[k];
        let sop = if self.modality == "MR" {
            "MRImageStorage"
        } else {
            "CTImageStorage"
        };
        format!(
            "(0008,0016) UI ={sop}\n\
             (0008,0018) UI [{uid}.{k1}]\n\
             (0008,0060) CS [{modality}]\n\
             (0008,103e) LO [{desc}]\n\
             (0010,0010) PN [Test^Phantom]\n\
             (0020,000d) UI [1.2.826.0.1.3680043.2.1143.1]\n\
             (0020,000e) UI [{uid}]\n\
             (0020,0011) IS [{number}]\n\
             (0020,0013) IS [{k1}]\n\
             {trigger}\
             (0020,0032) DS [{ipp}]\n\
             (0020,0037) DS [{iop}]\n\
             (0028,0002) US 1\n\
             (0028,0004) CS [MONOCHROME2]\n\
             (0028,0010) US {rows}\n\
             (0028,0011) US {cols}\n\
             (0028,0030) DS [{ps}]\n\
             (0018,0050) DS [7]\n\
             (0028,0100) US 16\n\
             (0028,0101) US {bs}\n\
             (0028,0102) US {hb}\n\
             (0028,0103) US {pr}\n\
             (0028,1052) DS [{inter}]\n\
             (0028,1053) DS [{slope}]\n\
             (7fe0,0010) OW ={raw}\n",
            uid = self.uid,
            k1 = self.instance_base + k + 1,
            trigger = self
                .trigger_ms
                .map_or(String::new(), |t| format!("(0018,1060) DS [{}]\n", ds(t))),
            modality = self.modality,
            desc = self.description,
            number = self.number,
            ipp = ds_list(&ipp.to_array()),
            iop = ds_list(&[
                self.row_dir.x,
                self.row_dir.y,
                self.row_dir.z,
                self.col_dir.x,
                self.col_dir.y,
                self.col_dir.z
            ]),
            rows = self.rows,
            cols = self.cols,
            ps = ds_list(&self.pixel_spacing),
            bs = self.bits_stored,
            hb = self.bits_stored - 1,
            pr = self.signed as u8,
            inter = ds(inter),
            slope = ds(slope),
            raw = raw.display(),
        )
    }

    /// Writes one file per slice into `dir` (explicit VR little endian), named so that the
    /// directory order is not the slice order. Returns the files in slice order.
    fn write(&self, dir: &Path) -> Vec<PathBuf> {
        std::fs::create_dir_all(dir).unwrap();
        let work = dir.with_extension("work");
        std::fs::create_dir_all(&work).unwrap();
        let plane = self.cols * self.rows;
        let mut files = Vec::new();
        for k in 0..self.slices {
            let raw = work.join(format!("s{k}.raw"));
            let bytes: Vec<u8> = self.stored[k * plane..(k + 1) * plane]
                .iter()
                .flat_map(|&s| (s as u16).to_le_bytes())
                .collect();
            std::fs::write(&raw, bytes).unwrap();
            let dump = work.join(format!("s{k}.txt"));
            std::fs::write(&dump, self.dump(k, &raw)).unwrap();
            // shuffled on disk: names sort in a different order than the slices
            let name = format!("IM{:04}", (k * 7 + 3) % self.slices * 13 + k % 3);
            let out = dir.join(name);
            run(Command::new("dump2dcm").arg("+te").arg(&dump).arg(&out));
            files.push(out);
        }
        let _ = std::fs::remove_dir_all(&work);
        files
    }
}

/// Every file of `from` converted by `tool args` into `to`.
fn convert(from: &Path, to: &Path, tool: &str, args: &[&str]) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        run(Command::new(tool)
            .args(args)
            .arg(&p)
            .arg(to.join(p.file_name().unwrap())));
    }
}

fn transfer_syntax_of(dir: &Path) -> String {
    let f = std::fs::read_dir(dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    dicom_object::open_file(&f)
        .unwrap()
        .meta()
        .transfer_syntax()
        .trim_end_matches('\0')
        .to_string()
}

fn assert_same(got: &Volume, want: &Volume, what: &str) {
    assert_eq!(got.dims, want.dims, "{what}: dims");
    for a in 0..3 {
        assert!(
            (got.spacing[a] - want.spacing[a]).abs() < 1e-6,
            "{what}: spacing {:?} vs {:?}",
            got.spacing,
            want.spacing
        );
    }
    assert!(
        got.directions.abs_diff_eq(want.directions, 1e-6),
        "{what}: directions {:?} vs {:?}",
        got.directions,
        want.directions
    );
    assert!(
        got.origin.abs_diff_eq(want.origin, 1e-6),
        "{what}: origin {:?} vs {:?}",
        got.origin,
        want.origin
    );
    assert_eq!(got.modality, want.modality, "{what}: modality");
    assert_eq!(got.voxels.type_name(), want.voxels.type_name(), "{what}");
    if got.voxels != want.voxels {
        let n = (0..want.voxels.len())
            .find(|&i| got.voxels.get(i) != want.voxels.get(i))
            .unwrap_or(0);
        panic!(
            "{what}: voxel {n} is {} instead of {}",
            got.voxels.get(n),
            want.voxels.get(n)
        );
    }
}

fn err_of(r: Result<Volume, cao_xr::volume::VolumeError>) -> String {
    match r {
        Ok(v) => panic!("loaded {:?} where an error was expected", v.dims),
        Err(e) => e.to_string(),
    }
}

#[test]
fn oblique_series_round_trips_uncompressed_rle_jpeg_lossless_and_deflate() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("roundtrip");
    let spec = Spec::oblique();
    let plain = root.join("plain");
    spec.write(&plain);
    let want = spec.expected();
    let got = dicom::load_series(&plain, None).unwrap();
    assert_same(&got, &want, "explicit VR little endian");
    assert!(got.name.contains("oblique test"), "{}", got.name);

    let cases: [(&str, &str, &[&str], &str); 4] = [
        ("rle", "dcmcrle", &[], "1.2.840.10008.1.2.5"),
        ("jpeg-sv1", "dcmcjpeg", &["+e1"], "1.2.840.10008.1.2.4.70"),
        (
            "jpeg-lossless",
            "dcmcjpeg",
            &["+el"],
            "1.2.840.10008.1.2.4.57",
        ),
        ("implicit", "dcmconv", &["+ti"], "1.2.840.10008.1.2"),
    ];
    for (name, tool, args, ts) in cases {
        let d = root.join(name);
        convert(&plain, &d, tool, args);
        assert_eq!(transfer_syntax_of(&d), ts, "{name}: the converter's output");
        let got = dicom::load_series(&d, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_same(&got, &want, name);
    }
    // deflated explicit VR little endian, written by dump2dcm itself
    let d = root.join("deflate");
    convert(&plain, &d, "dcmconv", &["+td"]);
    assert_eq!(transfer_syntax_of(&d), "1.2.840.10008.1.2.1.99");
    assert_same(
        &dicom::load_series(&d, None).unwrap(),
        &want,
        "deflated explicit VR",
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn twelve_bit_unsigned_with_per_slice_rescale_and_junk_high_bits() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("12bit");
    let mut spec = Spec::oblique();
    // sagittal: rows run along -z (superior to inferior), columns along +y (posterior)
    spec.row_dir = DVec3::new(0.0, 1.0, 0.0);
    spec.col_dir = DVec3::new(0.0, 0.0, -1.0);
    spec.step = spec.normal() * 1.25;
    spec.bits_stored = 12;
    spec.signed = false;
    spec.modality = "MR";
    spec.rescale = (0..spec.slices).map(|k| (2.0, k as f64 - 7.0)).collect();
    for s in &mut spec.stored {
        *s = s.rem_euclid(4096);
    }
    let want = {
        let mut v = spec.expected();
        v.modality = Modality::Mr;
        v
    };
    // bits above BitsStored hold junk (old overlays): they must be masked off
    let mut junk = spec.clone();
    junk.signed = false;
    for (n, s) in junk.stored.iter_mut().enumerate() {
        if n % 5 == 0 {
            *s |= 0xa000;
        }
    }
    let d = root.join("series");
    junk.write(&d);
    let got = dicom::load_series(&d, None).unwrap();
    assert_same(&got, &want, "12-bit");
    assert_eq!(got.modality, Modality::Mr);
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn phases_at_the_same_positions_are_listed_as_volumes_and_picked() {
    if !have_dcmtk() {
        return;
    }
    // a cardiac-style series: one SeriesInstanceUID, 4 positions, 2 phases (TriggerTime 400 ms
    // with the lower InstanceNumbers, 0 ms with the higher: the trigger time orders them)
    let root = tmp("phases");
    let mut late = Spec::oblique().first_slices(4);
    late.trigger_ms = Some(400.0);
    let mut early = late.clone();
    early.trigger_ms = Some(0.0);
    early.instance_base = 100;
    early.stored.iter_mut().for_each(|v| *v += 5);
    late.write(&root.join("late"));
    let early_files = early.write(&root.join("early"));
    let scan = dicom::scan(&root).unwrap();
    assert_eq!(scan.series.len(), 2, "{}", scan.listing());
    let listing = scan.listing();
    assert!(
        listing.contains("oblique test [volume 1 of 2]")
            && listing.contains("oblique test [volume 2 of 2]"),
        "{listing}"
    );
    for (n, want) in [(1, &early), (2, &late)] {
        let v = dicom::load_series(&root, Some(&Pick::Index(n))).unwrap();
        assert_same(&v, &want.expected(), &format!("volume {n}"));
        assert!(v.name.contains(&format!("[volume {n} of 2]")), "{}", v.name);
    }
    let e = err_of(dicom::load_series(&root, None));
    assert!(e.contains("2 DICOM series") && e.contains("#N"), "{e}");
    let e = err_of(dicom::load_series(
        &root,
        Some(&Pick::Uid(late.uid.clone())),
    ));
    assert!(e.contains("holds 2 volumes at the same positions"), "{e}");
    // a phase missing one slice is not split: the duplicate positions are refused by name
    std::fs::remove_file(&early_files[1]).unwrap();
    let e = err_of(dicom::load_series(&root, None));
    assert!(e.contains("same position"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn several_series_are_listed_and_picked() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("pick");
    let a = Spec::oblique();
    let mut b = Spec::oblique().first_slices(4);
    b.uid = "1.2.826.0.1.3680043.2.1143.7002".into();
    b.description = "second";
    b.number = 7;
    a.write(&root.join("a"));
    b.write(&root.join("b").join("deeper"));
    std::fs::write(root.join("README.txt"), "not dicom").unwrap();
    let e = err_of(dicom::load_series(&root, None));
    for s in [
        "2 DICOM series",
        "#1",
        "#2",
        "1.2.826.0.1.3680043.2.1143.7001",
        "1.2.826.0.1.3680043.2.1143.7002",
        "oblique test",
        "second",
        "12 slices",
        "4 slices",
        "20 x 24",
        "#N",
        "skipped 1 file(s): 1 not DICOM",
    ] {
        assert!(e.contains(s), "missing {s:?} in: {e}");
    }
    assert!(e.starts_with(&root.display().to_string()), "{e}");
    let first = dicom::load_series(&root, Some(&Pick::Index(1))).unwrap();
    assert_eq!(first.dims, [24, 20, 12]);
    let second = dicom::load_spec(&format!("{}#2", root.display())).unwrap();
    assert_eq!(second.dims, [24, 20, 4]);
    let by_uid = dicom::load_spec(&format!(
        "{}#1.2.826.0.1.3680043.2.1143.7002",
        root.display()
    ))
    .unwrap();
    assert_eq!(by_uid.dims, [24, 20, 4]);
    let e = err_of(dicom::load_spec(&format!("{}#9", root.display())));
    assert!(e.contains("no series #9") && e.contains("#N"), "{e}");
    let e = err_of(dicom::load_spec(&format!("{}#1.2.3", root.display())));
    assert!(e.contains("no series with SeriesInstanceUID 1.2.3"), "{e}");

    // the CLI: info lists the series, loads a pick, refuses a bad pick
    let cli = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_cao-xr"))
            .args(args)
            .output()
            .unwrap()
    };
    let out = cli(&["info", root.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("2 DICOM series") && text.contains("pick one"),
        "{text}"
    );
    let out = cli(&["info", &format!("{}#2", root.display())]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("dims        24 x 20 x 4"), "{text}");
    assert!(
        text.contains("spacing     0.5000 x 0.7500 x 2.5000 mm"),
        "{text}"
    );
    assert!(text.contains("modality    Ct"), "{text}");
    let out = cli(&["info", &format!("{}#9", root.display())]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no series #9"));
    let _ = std::fs::remove_dir_all(&root);
}

/// A DICOM file whose header cannot be read (here garbage from inside its header on) beside a series is
/// skipped and told, as Slicer's import does; the series loads. Cut off from the series itself,
/// it leaves a gap that is refused, and the refusal names the unreadable file.
#[test]
fn unreadable_dicom_files_are_skipped_and_told() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("unreadable");
    let spec = Spec::oblique();
    let cut = |from: &std::path::Path, to: &std::path::Path| {
        let mut bytes = std::fs::read(from).unwrap();
        bytes.truncate(400);
        bytes.extend([0xFF; 800]);
        std::fs::write(to, &bytes).unwrap();
    };

    let d = root.join("beside");
    let files = spec.write(&d);
    let stray = d.join("stray.dcm");
    cut(&files[0], &stray);
    let whole = dicom::load_series(&d, None).unwrap();
    assert_eq!(whole.dims[2], files.len());
    let scan = dicom::scan(&d).unwrap();
    assert_eq!(scan.unreadable.len(), 1);
    let listing = scan.listing();
    assert!(
        listing.contains("1 DICOM file(s) could not be read") && listing.contains("stray.dcm"),
        "{listing}"
    );

    let d = root.join("in-the-series");
    let files = spec.write(&d);
    cut(&files[5].clone(), &files[5]);
    let e = err_of(dicom::load_series(&d, None));
    assert!(e.contains("not evenly spaced"), "{e}");
    let name = files[5].file_name().unwrap().to_str().unwrap();
    assert!(e.contains("could not be read") && e.contains(name), "{e}");

    // Alone in its folder: its own error.
    let d = root.join("alone");
    std::fs::create_dir_all(&d).unwrap();
    cut(&stray, &d.join("only.dcm"));
    let e = err_of(dicom::load_series(&d, None));
    assert!(
        e.contains("only.dcm") && !e.contains("no DICOM image files"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn bad_series_are_refused_with_the_file_and_problem_named() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("bad");
    let spec = Spec::oblique();

    // a slice missing from the middle
    let d = root.join("gap");
    let files = spec.write(&d);
    std::fs::remove_file(&files[5]).unwrap();
    let e = err_of(dicom::load_series(&d, None));
    assert!(
        e.contains("not evenly spaced") && e.contains("5.0000 mm"),
        "{e}"
    );
    let (before, after) = (
        files[4].file_name().unwrap().to_str().unwrap(),
        files[6].file_name().unwrap().to_str().unwrap(),
    );
    assert!(e.contains(before) && e.contains(after), "{e}");

    // a truncated slice file
    let d = root.join("truncated");
    let files = spec.write(&d);
    let bytes = std::fs::read(&files[3]).unwrap();
    std::fs::write(&files[3], &bytes[..bytes.len() - 300]).unwrap();
    let e = err_of(dicom::load_series(&d, None));
    let name = files[3].file_name().unwrap().to_str().unwrap();
    assert!(e.contains(name), "{e}");

    // a header that says more rows than the pixel data holds
    let d = root.join("lying");
    let files = spec.write(&d);
    for f in &files {
        run(Command::new("dcmodify")
            .args(["-nb", "-m", "(0028,0010)=40"])
            .arg(f));
    }
    let e = err_of(dicom::load_series(&d, None));
    assert!(e.contains("pixel data") && e.contains("bytes"), "{e}");

    // an element whose length claims gigabytes the file does not hold: refused before the
    // parser allocates it
    let d = root.join("claims-gigabytes");
    let files = spec.write(&d);
    let mut bytes = std::fs::read(&files[5]).unwrap();
    let at = bytes
        .windows(6)
        .position(|w| w == b"\xe0\x7f\x10\x00OW")
        .expect("explicit VR little endian PixelData header");
    bytes[at + 8..at + 12].copy_from_slice(&0xF000_0000u32.to_le_bytes());
    std::fs::write(&files[5], &bytes).unwrap();
    let e = err_of(dicom::load_series(&d, None));
    let name = files[5].file_name().unwrap().to_str().unwrap();
    assert!(
        e.contains(name) && e.contains("(7FE0,0010) declares 4026531840 bytes"),
        "{e}"
    );

    // a header promising a 4000 x 4000 image in a 2 kB file: refused from the header, before
    // a volume is allocated for it
    let d = root.join("huge-rows");
    let files = spec.write(&d);
    for f in &files {
        run(Command::new("dcmodify")
            .args(["-nb", "-m", "(0028,0010)=4000", "-m", "(0028,0011)=4000"])
            .arg(f));
    }
    let e = err_of(dicom::load_series(&d, None));
    assert!(
        e.contains("4000 x 4000") && e.contains("lies about the image size"),
        "{e}"
    );

    // mixed geometry inside one series
    let d = root.join("mixed");
    let files = spec.write(&d);
    run(Command::new("dcmodify")
        .args(["-nb", "-m", "(0028,0030)=0.9\\0.9"])
        .arg(&files[7]));
    let e = err_of(dicom::load_series(&d, None));
    let name = files[7].file_name().unwrap().to_str().unwrap();
    assert!(
        e.contains("mixed series") && e.contains("PixelSpacing") && e.contains(name),
        "{e}"
    );

    // two acquisitions at the same positions in one series
    let d = root.join("twice");
    let files = spec.write(&d);
    let copy = d.join("ZZ-second-acquisition");
    std::fs::copy(&files[2], &copy).unwrap();
    let e = err_of(dicom::load_series(&d, None));
    assert!(
        e.contains("same position") && e.contains("ZZ-second-acquisition"),
        "{e}"
    );

    // JPEG-LS: no pure-Rust decoder
    let d = root.join("plain-for-jls");
    spec.write(&d);
    let jls = root.join("jpegls");
    convert(&d, &jls, "dcmcjpls", &[]);
    let e = err_of(dicom::load_series(&jls, None));
    assert!(
        e.contains("unsupported") && e.contains("1.2.840.10008.1.2.4.80") && e.contains("jpegls"),
        "{e}"
    );

    // RGB
    let d = root.join("rgb");
    std::fs::create_dir_all(&d).unwrap();
    let raw = root.join("rgb.raw");
    std::fs::write(&raw, vec![7u8; 4 * 4 * 3]).unwrap();
    let dump = root.join("rgb.txt");
    std::fs::write(
        &dump,
        format!(
            "(0008,0016) UI =SecondaryCaptureImageStorage\n(0008,0018) UI [1.2.3.4.5]\n\
             (0020,000e) UI [1.2.3.4]\n(0028,0002) US 3\n(0028,0004) CS [RGB]\n\
             (0028,0006) US 0\n(0028,0010) US 4\n(0028,0011) US 4\n(0028,0100) US 8\n\
             (0028,0101) US 8\n(0028,0102) US 7\n(0028,0103) US 0\n(7fe0,0010) OB ={}\n",
            raw.display()
        ),
    )
    .unwrap();
    run(Command::new("dump2dcm").arg(&dump).arg(d.join("rgb.dcm")));
    let e = err_of(dicom::load_series(&d, None));
    assert!(
        e.contains("rgb.dcm") && e.contains("RGB") && e.contains("greyscale"),
        "{e}"
    );

    // no DICOM at all, and an empty directory
    let d = root.join("none");
    std::fs::create_dir_all(&d).unwrap();
    let e = err_of(dicom::load_series(&d, None));
    assert!(e.contains("no DICOM image files"), "{e}");
    std::fs::write(d.join("notes.txt"), "hello").unwrap();
    let e = err_of(dicom::load_series(&d, None));
    assert!(
        e.contains("no DICOM image files") && e.contains("notes.txt"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn phantom_series_has_the_geometry_of_its_nrrd() {
    if !have_dcmtk() {
        return;
    }
    use cao_xr::space::{world_from_tex, Placement};
    use cao_xr::volume::{nrrd, phantom};
    let root = tmp("phantom");
    let head = phantom::head(32);
    let Voxels::I16(v) = &head.voxels else {
        panic!("phantom is int16")
    };
    let spec = Spec {
        cols: 32,
        rows: 32,
        slices: 32,
        row_dir: head.directions.x_axis,
        col_dir: head.directions.y_axis,
        origin: head.origin,
        step: head.directions.z_axis * head.spacing[2],
        pixel_spacing: [head.spacing[1], head.spacing[0]],
        bits_stored: 16,
        signed: true,
        modality: "CT",
        uid: "1.2.826.0.1.3680043.2.1143.7003".into(),
        description: "phantom",
        number: 1,
        rescale: vec![(1.0, 0.0); 32],
        stored: v.iter().map(|&x| x as i32).collect(),
        trigger_ms: None,
        instance_base: 0,
    };
    let d = root.join("head");
    spec.write(&d);
    let nrrd_path = root.join("head.nrrd");
    nrrd::write_volume(&nrrd_path, &head, false).unwrap();
    let from_nrrd = nrrd::load(&nrrd_path).unwrap();
    let from_dicom = dicom::load_series(&d, None).unwrap();
    assert_eq!(from_dicom.voxels, from_nrrd.voxels);
    let p = Placement::default();
    let (a, b) = (
        world_from_tex(&from_dicom, &p),
        world_from_tex(&from_nrrd, &p),
    );
    assert!(a.abs_diff_eq(b, 1e-6), "DICOM {a:?} vs NRRD {b:?}");
    // upright: the head's superior axis (k) points up (+Y) in the world
    assert!(a.z_axis.y > 0.0 && a.z_axis.x.abs() < 1e-6 && a.z_axis.z.abs() < 1e-6);
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn enhanced_multi_frame_places_each_frame_by_its_functional_groups() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("enhanced");
    let (cols, rows) = (4usize, 3usize);
    let stored = |f: usize, n: usize| (f * 100 + n * 7) as i32 - 150;
    let item = |body: String| {
        format!(
            "(fffe,e000) na (Item with undefined length #=1)\n{body}(fffe,e00d) na (ItemDelimitationItem)\n"
        )
    };
    let seq = |tag: &str, items: String| {
        format!(
            "({tag}) SQ (Sequence with undefined length #=1)\n{items}(fffe,e0dd) na (SequenceDelimitationItem)\n"
        )
    };
    // One enhanced CT file in `dir`: frame f at z = z_of[f], intercept -10 f, and with
    // `temporal` its TemporalPositionIndex.
    let write = |dir: &Path, z_of: &[f64], temporal: Option<&[u32]>| {
        let frames = z_of.len();
        let raw = root.join("px.raw");
        let bytes: Vec<u8> = (0..frames)
            .flat_map(|f| (0..cols * rows).map(move |n| stored(f, n)))
            .flat_map(|s| (s as i16).to_le_bytes())
            .collect();
        std::fs::write(&raw, bytes).unwrap();
        let shared = seq(
            "5200,9229",
            item(
                seq(
                    "0020,9116",
                    item("(0020,0037) DS [1\\0\\0\\0\\1\\0]\n".into()),
                ) + &seq("0028,9110", item("(0028,0030) DS [0.8\\0.6]\n".into())),
            ),
        );
        let per_frame = seq(
            "5200,9230",
            (0..frames)
                .map(|f| {
                    let content = temporal.map_or(String::new(), |t| {
                        seq("0020,9111", item(format!("(0020,9128) UL {}\n", t[f])))
                    });
                    item(
                        content
                            + &seq(
                                "0020,9113",
                                item(format!("(0020,0032) DS [-5\\7\\{}]\n", z_of[f])),
                            )
                            + &seq(
                                "0028,9145",
                                item(format!(
                                    "(0028,1052) DS [{}]\n(0028,1053) DS [1]\n",
                                    -(f as i32) * 10
                                )),
                            ),
                    )
                })
                .collect(),
        );
        let dump = format!(
            "(0008,0016) UI =EnhancedCTImageStorage\n(0008,0018) UI [1.2.826.0.1.3680043.2.1143.9.1]\n\
             (0008,0060) CS [CT]\n(0020,000e) UI [1.2.826.0.1.3680043.2.1143.9]\n\
             (0028,0002) US 1\n(0028,0004) CS [MONOCHROME2]\n(0028,0008) IS [{frames}]\n\
             (0028,0010) US {rows}\n(0028,0011) US {cols}\n(0028,0100) US 16\n(0028,0101) US 16\n\
             (0028,0102) US 15\n(0028,0103) US 1\n{shared}{per_frame}(7fe0,0010) OW ={}\n",
            raw.display()
        );
        let txt = root.join("mf.txt");
        std::fs::write(&txt, dump).unwrap();
        std::fs::create_dir_all(dir).unwrap();
        run(Command::new("dump2dcm")
            .arg("+te")
            .arg(&txt)
            .arg(dir.join("enhanced.dcm")));
    };
    // what frames `order` hold, in that order (rescaled)
    let planes = |order: &[usize]| -> Voxels {
        Voxels::I16(
            order
                .iter()
                .flat_map(|&f| (0..cols * rows).map(move |n| (stored(f, n) - f as i32 * 10) as i16))
                .collect(),
        )
    };
    // two temporal positions at two z: frames (z, t) = (0, 2) (0, 1) (2, 1) (2, 2)
    let phases = root.join("phases");
    write(&phases, &[0.0, 0.0, 2.0, 2.0], Some(&[2, 1, 1, 2]));
    for (n, order) in [(1, [1, 2]), (2, [0, 3])] {
        let v = dicom::load_series(&phases, Some(&Pick::Index(n))).unwrap();
        assert_eq!((v.dims, v.spacing[2]), ([4, 3, 2], 2.0));
        assert_eq!(v.voxels, planes(&order), "temporal position {n}");
    }
    // frame f lies at z = z_of[f] (shuffled)
    let z_of: [f64; 5] = [4.0, 0.0, 8.0, 2.0, 6.0];
    let plain = root.join("plain");
    write(&plain, &z_of, None);
    let rle = root.join("rle");
    convert(&plain, &rle, "dcmcrle", &[]);
    let mut order: Vec<usize> = (0..z_of.len()).collect();
    order.sort_by(|&a, &b| z_of[a].total_cmp(&z_of[b]));
    let want = planes(&order);
    for d in [&plain, &rle] {
        let v = dicom::load_series(d, None).unwrap_or_else(|e| panic!("{}: {e}", d.display()));
        assert_eq!(v.dims, [4, 3, 5]);
        assert_eq!(v.spacing, [0.6, 0.8, 2.0]);
        assert_eq!(v.directions, DMat3::IDENTITY);
        assert_eq!(v.origin, DVec3::new(-5.0, 7.0, 0.0));
        assert_eq!(v.voxels, want, "{}", d.display());
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// Real-world files that nobody here wrote: pydicom's test data (Debian's python3-pydicom, or
/// `CAO_XR_PYDICOM_DATA=.../pydicom/data/test_files`). Skipped with a message when absent.
#[test]
fn pydicom_sample_files_load_with_their_header_geometry() {
    let data = std::env::var_os("CAO_XR_PYDICOM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/lib/python3/dist-packages/pydicom/data/test_files"));
    let why = format!(
        "pydicom's sample files are not at {} (apt-get install python3-pydicom)",
        data.display()
    );
    if !common::require_or_skip(
        "CAO_XR_REQUIRE_PYDICOM",
        data.join("MR_small.dcm").exists(),
        &why,
    ) {
        return;
    }
    let root = tmp("pydicom");
    let one = |name: &str| {
        let d = root.join(name);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::copy(data.join(format!("{name}.dcm")), d.join("f.dcm")).unwrap();
        dicom::load_series(&d, None)
    };
    // MR_small: 64 x 64, PixelSpacing 0.3125\0.3125, SliceThickness 0.8 (one slice)
    let mr = one("MR_small").unwrap();
    assert_eq!(mr.dims, [64, 64, 1]);
    assert_eq!(mr.spacing, [0.3125, 0.3125, 0.8]);
    assert_eq!(mr.modality, Modality::Mr);
    assert_eq!(mr.value_range(), (127.0, 2145.0));
    for v in [
        "MR_small_RLE",
        "MR_small_jp2klossless",
        "MR_small_implicit",
        "MR_small_bigendian",
        "MR_small_expb",
    ] {
        let got = one(v).unwrap_or_else(|e| panic!("{v}: {e}"));
        assert_eq!(got.voxels, mr.voxels, "{v}");
        assert_eq!(got.directions, mr.directions, "{v}");
    }
    // pydicom's truncated MR: refused before the parser allocates the promised pixel data
    let e = err_of(one("MR_truncated"));
    assert!(
        e.contains("f.dcm") && e.contains("(7FE0,0010) declares 8192 bytes"),
        "{e}"
    );
    let e = err_of(one("MR_small_jpeg_ls_lossless"));
    assert!(e.contains("1.2.840.10008.1.2.4.80"), "{e}");
    // CT_small: 128 x 128, PixelSpacing 0.661468\0.661468, SliceThickness 5, HU
    let ct = one("CT_small").unwrap();
    assert_eq!(ct.dims, [128, 128, 1]);
    assert!((ct.spacing[0] - 0.661468).abs() < 1e-9 && ct.spacing[2] == 5.0);
    assert_eq!(ct.modality, Modality::Ct);
    // a PACS-like export: 13 series, DICOMDIRs and localisers, one clean CT stack
    let tree = data.join("dicomdirtests");
    if tree.is_dir() {
        let scan = dicom::scan(&tree).unwrap();
        assert_eq!(scan.series.len(), 13, "{}", scan.listing());
        let gated = scan
            .series
            .iter()
            .position(|s| s.description.starts_with("SmartScore"))
            .unwrap();
        let v = dicom::load_series(&tree, Some(&Pick::Index(gated + 1))).unwrap();
        assert_eq!(v.dims, [16, 16, 5]);
        assert!((v.spacing[2] - 2.5).abs() < 1e-6, "{:?}", v.spacing);
    }
    let _ = std::fs::remove_dir_all(&root);
}

// ---- DICOM as scanners write it (issue 19). Each quirk is written here (dcmtk plus byte
// edits), loaded, and compared with pydicom's `pixel_array` (rescaled), dims and orientation.

/// A Python with pydicom and numpy: `python3` on PATH, else the system's (a pyenv or venv
/// python3 may lack the Debian packages).
fn pydicom_python() -> Option<&'static str> {
    let py = ["python3", "/usr/bin/python3"].into_iter().find(|py| {
        Command::new(py)
            .args(["-c", "import pydicom, numpy"])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    common::require_or_skip(
        "CAO_XR_REQUIRE_PYDICOM",
        py.is_some(),
        "pydicom with numpy is missing (apt-get install python3-pydicom)",
    )
    .then_some(py)
    .flatten()
}

/// pydicom's reading of each file: the image and its geometry, or its error.
const PYDICOM_READ: &str = r#"
import json, sys, warnings
import pydicom
from pydicom import uid
warnings.simplefilter("ignore")
def floats(ds, keyword):
    v = ds.get(keyword)
    if v is None or v == "":
        return None
    return [float(x) for x in (v if isinstance(v, pydicom.multival.MultiValue) else [v])]
out = []
for f in sys.argv[1:]:
    r = {"file": f}
    try:
        ds = pydicom.dcmread(f, force=True)
        if "TransferSyntaxUID" not in ds.file_meta:
            # no file meta (ACR-NEMA): the encoding pydicom found reading the data set
            ds.file_meta.TransferSyntaxUID = (uid.ImplicitVRLittleEndian if ds.is_implicit_VR
                else uid.ExplicitVRLittleEndian if ds.is_little_endian else uid.ExplicitVRBigEndian)
        a = ds.pixel_array
        r["rows"], r["cols"] = int(ds.Rows), int(ds.Columns)
        r["frames"] = int(ds.get("NumberOfFrames", 1) or 1)
        r["samples"] = int(ds.get("SamplesPerPixel", 1) or 1)
        r["ipp"] = floats(ds, "ImagePositionPatient")
        r["iop"] = floats(ds, "ImageOrientationPatient")
        r["spacing"] = floats(ds, "PixelSpacing")
        if r["frames"] == 1 and r["samples"] == 1:
            slope = float(ds.get("RescaleSlope", 1) or 1)
            inter = float(ds.get("RescaleIntercept", 0) or 0)
            r["values"] = (a.astype("float64") * slope + inter).ravel().tolist()
    except Exception as e:
        r["error"] = repr(e)
    out.append(r)
json.dump(out, sys.stdout)
"#;

/// Runs [`PYDICOM_READ`] on `files`.
fn pydicom_read(py: &str, files: &[PathBuf]) -> Vec<serde_json::Value> {
    let out = Command::new(py)
        .arg("-c")
        .arg(PYDICOM_READ)
        .args(files)
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "pydicom script: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    match serde_json::from_slice(&out.stdout).unwrap() {
        serde_json::Value::Array(v) => v,
        v => panic!("pydicom script: {v}"),
    }
}

fn json_floats(v: &serde_json::Value) -> Option<Vec<f64>> {
    v.as_array()
        .map(|a| a.iter().map(|x| x.as_f64().unwrap()).collect())
}

/// A single-frame series as pydicom reads it: planes sorted along the slice normal.
struct PyVolume {
    dims: [usize; 3],
    /// (column spacing, row spacing, slice step) where the files say.
    spacing: Option<[f64; 3]>,
    directions: Option<DMat3>,
    origin: Option<DVec3>,
    values: Vec<f64>,
}

/// What pydicom makes of the single-frame series `files`; `Err` with pydicom's errors.
fn pydicom_volume(py: &str, files: &[PathBuf]) -> Result<PyVolume, String> {
    let read = pydicom_read(py, files);
    let errors: Vec<String> = read
        .iter()
        .filter_map(|r| Some(format!("{}: {}", r["file"], r.get("error")?)))
        .collect();
    if !errors.is_empty() {
        return Err(errors.join("; "));
    }
    let iop = json_floats(&read[0]["iop"]);
    let dirs = iop.as_ref().map(|v| {
        // written with a few decimals: unit vectors again
        let r = DVec3::new(v[0], v[1], v[2]).normalize();
        let c = DVec3::new(v[3], v[4], v[5]).normalize();
        DMat3::from_cols(r, c, r.cross(c))
    });
    let normal = dirs.map_or(DVec3::Z, |d| d.z_axis);
    let ipp = |r: &serde_json::Value| json_floats(&r["ipp"]).map(|v| DVec3::new(v[0], v[1], v[2]));
    let mut order: Vec<&serde_json::Value> = read.iter().collect();
    order.sort_by(|a, b| {
        let (a, b) = (ipp(a).unwrap_or_default(), ipp(b).unwrap_or_default());
        a.dot(normal).total_cmp(&b.dot(normal))
    });
    let n = order.len();
    let step = match (ipp(order[0]), ipp(order[n - 1])) {
        (Some(a), Some(b)) if n > 1 => (b - a).dot(normal) / (n - 1) as f64,
        _ => f64::NAN,
    };
    Ok(PyVolume {
        dims: [
            read[0]["cols"].as_u64().unwrap() as usize,
            read[0]["rows"].as_u64().unwrap() as usize,
            n,
        ],
        spacing: json_floats(&read[0]["spacing"]).map(|s| [s[1], s[0], step]),
        directions: dirs,
        origin: ipp(order[0]),
        values: order
            .iter()
            .flat_map(|r| json_floats(&r["values"]).expect("a single-frame greyscale image"))
            .collect(),
    })
}

/// The loaded volume has pydicom's dims, orientation, position and (rescaled) values.
fn assert_as_pydicom(got: &Volume, want: &PyVolume, what: &str) {
    assert_eq!(got.dims, want.dims, "{what}: dims");
    if let Some(d) = want.directions {
        assert!(
            got.directions.abs_diff_eq(d, 1e-5),
            "{what}: directions {:?} vs pydicom's {d:?}",
            got.directions
        );
    }
    if let Some(o) = want.origin {
        assert!(
            got.origin.abs_diff_eq(o, 1e-5),
            "{what}: origin {:?} vs pydicom's {o:?}",
            got.origin
        );
    }
    if let Some(s) = want.spacing {
        let axes = if want.dims[2] > 1 { 3 } else { 2 };
        for a in 0..axes {
            assert!(
                (got.spacing[a] - s[a]).abs() < 1e-5,
                "{what}: spacing {:?} vs pydicom's {s:?}",
                got.spacing
            );
        }
    }
    assert_eq!(got.voxels.len(), want.values.len(), "{what}: voxel count");
    for (i, &w) in want.values.iter().enumerate() {
        let g = got.voxels.get(i) as f64;
        assert!(
            (g - w).abs() <= 1e-5 * w.abs().max(1.0),
            "{what}: voxel {i} is {g}, pydicom says {w}"
        );
    }
}

/// pydicom's reading of the quirky files where pydicom reads them, else of the clean files
/// they were made from (the edits leave the pixels alone). Says which, for the test's log.
fn pydicom_reference(py: &str, quirky: &[PathBuf], clean: &[PathBuf], what: &str) -> PyVolume {
    match pydicom_volume(py, quirky) {
        Ok(v) => v,
        Err(e) => {
            eprintln!(
                "{what}: pydicom cannot read the edited files ({e}); compared with the originals"
            );
            pydicom_volume(py, clean).unwrap()
        }
    }
}

/// Does dcmtk's dcmdump read the file without an error?
fn dcmtk_reads(f: &Path) -> bool {
    Command::new("dcmdump")
        .arg(f)
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Where the data set of a Part 10 file starts (after the file meta group).
fn data_set_start(b: &[u8]) -> usize {
    assert_eq!(&b[128..132], b"DICM");
    assert_eq!(&b[132..136], b"\x02\x00\x00\x00", "(0002,0000) first");
    144 + u32::from_le_bytes([b[140], b[141], b[142], b[143]]) as usize
}

/// The offset of element (group, element)'s header in explicit VR little endian data.
fn element_at(b: &[u8], group: u16, element: u16) -> usize {
    let tag = [group.to_le_bytes(), element.to_le_bytes()].concat();
    let from = data_set_start(b);
    from + b[from..]
        .windows(6)
        .position(|w| w[..4] == tag[..] && w[4].is_ascii_uppercase() && w[5].is_ascii_uppercase())
        .unwrap_or_else(|| panic!("({group:04X},{element:04X}) not in the file"))
}

/// Writes a short-form (2-byte length) explicit-VR element with `vr` instead, encoded as dcmtk
/// reads a non-standard VR: two upper-case letters with a 4-byte length, anything else with a
/// 2-byte length.
fn with_vr(mut b: Vec<u8>, group: u16, element: u16, vr: [u8; 2]) -> Vec<u8> {
    let at = element_at(&b, group, element);
    let len = u16::from_le_bytes([b[at + 6], b[at + 7]]);
    let mut head = b[at..at + 4].to_vec();
    head.extend_from_slice(&vr);
    if vr.iter().all(u8::is_ascii_uppercase) {
        head.extend_from_slice(&[0, 0]);
        head.extend_from_slice(&(len as u32).to_le_bytes());
    } else {
        head.extend_from_slice(&len.to_le_bytes());
    }
    b.splice(at..at + 8, head);
    b
}

/// Copies `files` into `dir` (same names), each through `edit(k, bytes)`.
fn edited(files: &[PathBuf], dir: &Path, edit: impl Fn(usize, Vec<u8>) -> Vec<u8>) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir).unwrap();
    files
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let out = dir.join(f.file_name().unwrap());
            std::fs::write(&out, edit(k, std::fs::read(f).unwrap())).unwrap();
            out
        })
        .collect()
}

/// A clean 4-slice oblique series (with its expected volume) and pydicom, or None to skip.
fn quirk_setup(root: &Path) -> Option<(&'static str, Spec, Vec<PathBuf>)> {
    if !have_dcmtk() {
        return None;
    }
    let py = pydicom_python()?;
    let spec = Spec::oblique().first_slices(4);
    let files = spec.write(&root.join("clean"));
    Some((py, spec, files))
}

#[test]
fn trailing_padding_or_garbage_after_the_pixel_data_is_ignored() {
    let root = tmp("trailing");
    let Some((py, spec, clean)) = quirk_setup(&root) else {
        return;
    };
    let d = root.join("trailing");
    let files = edited(&clean, &d, |k, mut b| {
        match k {
            // megabytes of zeros: (0000,0000) elements to dcmtk, not a whole number of
            // dicom-rs's 12-byte UN headers
            0 => b.resize(b.len() + 3_000_008, 0),
            1 => b.extend_from_slice(b"GARBAGE after the pixel data\x01\x02\x03"),
            2 => b.extend((0..2560u32).map(|i| (i * 97 % 251) as u8)),
            _ => b.extend_from_slice(&[0; 7]),
        }
        b
    });
    assert!(dcmtk_reads(&files[0]), "dcmtk reads the zero padding");
    let got = dicom::load_series(&d, None).unwrap();
    assert_same(&got, &spec.expected(), "trailing padding and garbage");
    let want = pydicom_volume(py, &files).expect("pydicom reads these files");
    assert_as_pydicom(&got, &want, "trailing padding and garbage");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn empty_and_non_standard_vrs_are_read_by_the_dictionary() {
    let root = tmp("vr");
    let Some((py, spec, clean)) = quirk_setup(&root) else {
        return;
    };
    let d = root.join("vr");
    let files = edited(&clean, &d, |_, b| {
        let b = with_vr(b, 0x0020, 0x0032, [0, 0]); // ImagePositionPatient
        let b = with_vr(b, 0x0028, 0x0010, [0, 0]); // Rows
        let b = with_vr(b, 0x0028, 0x1052, *b"  "); // RescaleIntercept
        let b = with_vr(b, 0x0020, 0x0013, *b"??"); // InstanceNumber
        with_vr(b, 0x0008, 0x103e, *b"ZZ") // SeriesDescription: a "future" VR
    });
    for f in &files {
        assert!(dcmtk_reads(f), "dcmtk reads {}", f.display());
    }
    let got = dicom::load_series(&d, None).unwrap();
    assert_same(&got, &spec.expected(), "non-standard VRs");
    assert!(got.name.contains("oblique test"), "{}", got.name);
    let want = pydicom_reference(py, &files, &clean, "non-standard VRs");
    assert_as_pydicom(&got, &want, "non-standard VRs");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn group_0000_command_elements_in_the_data_set_are_skipped() {
    let root = tmp("group0");
    let Some((py, spec, clean)) = quirk_setup(&root) else {
        return;
    };
    let d = root.join("group0");
    let files = edited(&clean, &d, |k, mut b| {
        let at = data_set_start(&b);
        // as a GE MR series writes it: (0000,0000) with two zero bytes for its VR first
        let mut cmd = vec![0, 0, 0, 0, 0, 0, 4, 0];
        cmd.extend_from_slice(&0x1c8u32.to_le_bytes());
        // then AffectedSOPClassUID with its VR, and CommandField without one
        cmd.extend_from_slice(b"\x00\x00\x02\x00UI\x1a\x001.2.840.10008.5.1.4.1.1.2\0");
        cmd.extend_from_slice(b"\x00\x00\x00\x01\x00\x00\x02\x00\x01\x00");
        if k % 2 == 1 {
            // elsewhere in the data set too
            let mid = element_at(&b, 0x0028, 0x0002);
            b.splice(mid..mid, cmd.iter().copied());
        }
        b.splice(at..at, cmd);
        b
    });
    for f in &files {
        assert!(dcmtk_reads(f), "dcmtk reads {}", f.display());
    }
    let got = dicom::load_series(&d, None).unwrap();
    assert_same(&got, &spec.expected(), "group 0000");
    let want = pydicom_reference(py, &files, &clean, "group 0000");
    assert_as_pydicom(&got, &want, "group 0000");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn acr_nema_files_without_preamble_or_file_meta_load() {
    let root = tmp("acr");
    let Some((py, spec, clean)) = quirk_setup(&root) else {
        return;
    };
    let bare = |b: Vec<u8>| b[data_set_start(&b)..].to_vec();
    // implicit VR little endian, the old ACR-NEMA encoding
    let implicit = root.join("implicit-dcmconv");
    convert(&root.join("clean"), &implicit, "dcmconv", &["+ti"]);
    let implicit_files: Vec<PathBuf> = clean
        .iter()
        .map(|f| implicit.join(f.file_name().unwrap()))
        .collect();
    for (name, from) in [("acr-implicit", &implicit_files), ("bare-explicit", &clean)] {
        let d = root.join(name);
        let files = edited(from, &d, |_, b| bare(b));
        assert_ne!(&std::fs::read(&files[0]).unwrap()[128..132], b"DICM");
        for f in &files {
            assert!(dcmtk_reads(f), "dcmtk reads {}", f.display());
        }
        let got = dicom::load_series(&d, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_same(&got, &spec.expected(), name);
        let want = pydicom_volume(py, &files).expect("pydicom reads these files");
        assert_as_pydicom(&got, &want, name);
    }
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn odd_value_lengths_are_read_as_dcmtk_reads_them() {
    let root = tmp("odd");
    let Some((py, spec, clean)) = quirk_setup(&root) else {
        return;
    };
    // a string element padded to an even length loses its padding byte
    let unpadded = |mut b: Vec<u8>, group: u16, element: u16| {
        let at = element_at(&b, group, element);
        let len = u16::from_le_bytes([b[at + 6], b[at + 7]]) as usize;
        if matches!(b[at + 8 + len - 1], b' ' | 0) {
            b.remove(at + 8 + len - 1);
            b[at + 6..at + 8].copy_from_slice(&(len as u16 - 1).to_le_bytes());
        }
        b
    };
    let d = root.join("odd");
    let files = edited(&clean, &d, |k, b| {
        let mut b = unpadded(b, 0x0028, 0x1052); // RescaleIntercept "-1024 "
        b = unpadded(b, 0x0020, 0x0013); // InstanceNumber
        b = unpadded(b, 0x0018, 0x0050); // SliceThickness
                                         // Rows (US) with a stray third byte
        let at = element_at(&b, 0x0028, 0x0010);
        b[at + 6] = 3;
        b.insert(at + 10, 0xee);
        if k == 1 {
            // 16-bit pixel data with one byte too many
            let at = element_at(&b, 0x7fe0, 0x0010);
            let len = u32::from_le_bytes([b[at + 8], b[at + 9], b[at + 10], b[at + 11]]);
            b[at + 8..at + 12].copy_from_slice(&(len + 1).to_le_bytes());
            b.push(0x55);
        }
        b
    });
    let bytes = std::fs::read(&files[0]).unwrap();
    let ri = element_at(&bytes, 0x0028, 0x1052);
    assert_eq!(bytes[ri + 6], 5, "RescaleIntercept has an odd length");
    for f in &files {
        assert!(dcmtk_reads(f), "dcmtk reads {}", f.display());
    }
    let got = dicom::load_series(&d, None).unwrap();
    assert_same(&got, &spec.expected(), "odd lengths");
    let want = pydicom_reference(py, &files, &clean, "odd lengths");
    assert_as_pydicom(&got, &want, "odd lengths");

    // 8-bit pixel data of an odd length (5 x 5), as dcmtk writes it before padding
    let d = root.join("odd-8bit");
    std::fs::create_dir_all(&d).unwrap();
    let raw = root.join("px8.raw");
    std::fs::write(&raw, (10..35u8).collect::<Vec<u8>>()).unwrap();
    let dump = root.join("px8.txt");
    std::fs::write(
        &dump,
        format!(
            "(0008,0016) UI =SecondaryCaptureImageStorage\n(0008,0018) UI [1.2.3.4.8.1]\n\
             (0020,000e) UI [1.2.3.4.8]\n(0028,0002) US 1\n(0028,0004) CS [MONOCHROME2]\n\
             (0028,0010) US 5\n(0028,0011) US 5\n(0028,0100) US 8\n(0028,0101) US 8\n\
             (0028,0102) US 7\n(0028,0103) US 0\n(7fe0,0010) OB ={}\n",
            raw.display()
        ),
    )
    .unwrap();
    let padded = root.join("px8.dcm");
    run(Command::new("dump2dcm").arg("+te").arg(&dump).arg(&padded));
    let f = d.join("px8");
    let mut b = std::fs::read(&padded).unwrap();
    let at = element_at(&b, 0x7fe0, 0x0010);
    assert_eq!(b.len(), at + 12 + 26, "dcmtk pads 25 bytes to 26");
    b[at + 8] = 25;
    b.pop();
    std::fs::write(&f, b).unwrap();
    let got = dicom::load_series(&d, None).unwrap();
    assert_eq!(got.dims, [5, 5, 1]);
    assert_as_pydicom(&got, &pydicom_volume(py, &[f]).unwrap(), "odd 8-bit");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn files_without_extension_load_among_other_files() {
    let root = tmp("mixed");
    let Some((py, spec, _)) = quirk_setup(&root) else {
        return;
    };
    // the series' files have no extension (IM0042...), beside what an export also holds
    let d = root.join("export");
    let files = spec.write(&d);
    assert!(files.iter().all(|f| f.extension().is_none()));
    std::fs::write(d.join("README.txt"), "exported images").unwrap();
    std::fs::write(d.join("LOCKFILE"), "").unwrap();
    std::fs::write(d.join("preview.png"), b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR").unwrap();
    std::fs::write(
        d.join("VERSION"),
        (0..4096u32)
            .map(|i| (i * 131 % 253) as u8)
            .collect::<Vec<u8>>(),
    )
    .unwrap();
    // a DICOM object without an image (a report) of another series
    let sr = root.join("sr.txt");
    std::fs::write(
        &sr,
        "(0008,0016) UI =BasicTextSRStorage\n(0008,0018) UI [1.2.3.4.9.1]\n\
         (0008,0060) CS [SR]\n(0020,000e) UI [1.2.3.4.9]\n",
    )
    .unwrap();
    run(Command::new("dump2dcm").arg(&sr).arg(d.join("SR000001")));
    let scan = dicom::scan(&d).unwrap();
    assert_eq!(scan.series.len(), 1, "{}", scan.listing());
    let listing = scan.listing();
    assert!(
        listing.contains("skipped 5 file(s): 4 not DICOM, 1 without an image"),
        "{listing}"
    );
    let got = dicom::load_series(&d, None).unwrap();
    assert_same(&got, &spec.expected(), "export folder");
    let want = pydicom_volume(py, &files).unwrap();
    assert_as_pydicom(&got, &want, "export folder");
    // one of the files, without an extension, stands for its series
    let one = dicom::load_file_series(&files[2]).unwrap();
    assert_same(&one, &spec.expected(), "one extensionless file");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn one_dcm_file_as_the_volume_loads_its_series() {
    if !have_dcmtk() {
        return;
    }
    let root = tmp("one-file");
    let d = root.join("folder");
    // two series in one folder, as .dcm files, and a 4-D series beside them
    let a = Spec::oblique().first_slices(5);
    let mut b = Spec::oblique().first_slices(3);
    b.uid = "1.2.826.0.1.3680043.2.1143.7009".into();
    b.stored.iter_mut().for_each(|v| *v += 7);
    let mut late = Spec::oblique().first_slices(2);
    late.uid = "1.2.826.0.1.3680043.2.1143.7010".into();
    late.trigger_ms = Some(400.0);
    let mut early = late.clone();
    early.trigger_ms = Some(0.0);
    early.instance_base = 100;
    early.stored.iter_mut().for_each(|v| *v -= 3);
    let mut named = Vec::new();
    for (tag, spec) in [("a", &a), ("b", &b), ("late", &late), ("early", &early)] {
        let files = spec.write(&root.join(tag));
        let mut to = Vec::new();
        for (k, f) in files.iter().enumerate() {
            let t = d.join(format!("{tag}{k}.dcm"));
            std::fs::create_dir_all(&d).unwrap();
            std::fs::rename(f, &t).unwrap();
            to.push(t);
        }
        named.push(to);
    }
    std::fs::write(d.join("notes.dcm"), "not DICOM, named so").unwrap();
    let got = dicom::load_file_series(&named[0][3]).unwrap();
    assert_same(&got, &a.expected(), "series a from one file");
    let got = dicom::load_file_series(&named[1][0]).unwrap();
    assert_same(&got, &b.expected(), "series b from one file");
    // a 4-D series: the volume the file is part of
    let got = dicom::load_file_series(&named[2][1]).unwrap();
    assert_same(
        &got,
        &late.expected(),
        "the late phase from one of its files",
    );
    let got = dicom::load_file_series(&named[3][0]).unwrap();
    assert_same(
        &got,
        &early.expected(),
        "the early phase from one of its files",
    );
    // the CLI: a .dcm VOLUME argument
    let cli = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_cao-xr"))
            .args(args)
            .output()
            .unwrap()
    };
    let out = cli(&["info", named[0][1].to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("dims        24 x 20 x 5"), "{text}");
    let out = cli(&["info", d.join("notes.dcm").to_str().unwrap()]);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        e.contains("notes.dcm") && e.contains("not a DICOM image") && e.contains("not DICOM"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Every image in pydicom's test files (real files from many writers, some with the quirks
/// above: no file meta, explicit VR without meta, trailing padding, odd lengths...) that
/// pydicom reads as one greyscale frame loads here with pydicom's values and geometry, on its
/// own as a one-file series. Where pydicom fails, loading may fail too; a file that loads
/// must then be one we read more of (none is expected).
#[test]
fn pydicom_test_images_load_as_pydicom_reads_them() {
    let data = std::env::var_os("CAO_XR_PYDICOM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/lib/python3/dist-packages/pydicom/data/test_files"));
    if !common::require_or_skip(
        "CAO_XR_REQUIRE_PYDICOM",
        data.join("MR_small.dcm").exists(),
        "pydicom's sample files are missing (apt-get install python3-pydicom)",
    ) {
        return;
    }
    let Some(py) = pydicom_python() else {
        return;
    };
    if !have_dcmtk() {
        return;
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(&data)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file() && p.extension().is_some_and(|e| e == "dcm"))
        .collect();
    files.sort();
    let root = tmp("pydicom-all");
    let mut compared = Vec::new();
    let mut failures: Vec<(PathBuf, String)> = Vec::new();
    for r in pydicom_read(py, &files) {
        let f = PathBuf::from(r["file"].as_str().unwrap());
        let name = f.file_name().unwrap().to_str().unwrap().to_string();
        let d = root.join(&name);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::copy(&f, d.join(&name)).unwrap();
        let ours = dicom::load_series(&d, None);
        if r.get("values").is_none() {
            // pydicom read the data set but found no image in it: we read its header too
            let no_image = r["error"]
                .as_str()
                .is_some_and(|e| e.contains("Unable to convert the pixel data"));
            if no_image {
                if let Err(e) = dicom::scan(&d) {
                    let e = e.to_string();
                    if !e.contains("no DICOM image files") {
                        failures.push((f.clone(), format!("{name} (no image): {e}")));
                    }
                }
            }
            // colour, multi-frame, or pydicom fails: not compared
            continue;
        }
        match ours {
            Ok(v) => {
                let want = pydicom_volume(py, std::slice::from_ref(&f)).unwrap();
                assert_as_pydicom(&v, &want, &name);
                compared.push(name);
            }
            Err(e) => failures.push((f.clone(), format!("{name}: {e}"))),
        }
    }
    eprintln!("compared with pydicom: {}", compared.join(", "));
    // what we refuse as unsupported (JPEG-LS, 1-bit or 32-bit samples) is named so, and a
    // file dcmtk refuses too (pydicom reads truncated files lazily) may be refused; anything
    // else pydicom reads, we read
    let (excused, failures): (Vec<_>, Vec<_>) = failures
        .into_iter()
        .partition(|(f, e)| e.contains(": unsupported: ") || !dcmtk_reads(f));
    let failures: Vec<String> = failures.into_iter().map(|(_, e)| e).collect();
    for (_, e) in excused {
        eprintln!("refused, as unsupported or as by dcmtk: {e}");
    }
    assert!(
        failures.is_empty(),
        "pydicom reads these, we do not:\n{}",
        failures.join("\n")
    );
    for must in [
        "MR_small.dcm",
        "CT_small.dcm",
        "MR_small_padded.dcm",
        "image_dfl.dcm",
    ] {
        assert!(compared.iter().any(|c| c == must), "{must} not compared");
    }
    let _ = std::fs::remove_dir_all(&root);
}
