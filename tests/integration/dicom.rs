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

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("cao-dicom-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
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
        "skipped 1 file(s): 1 not DICOM Part 10",
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
