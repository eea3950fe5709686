//! DICOM series: a directory of slice files (or enhanced multi-frame objects) read with the
//! dicom-rs crates and pure-Rust codecs (uncompressed, deflate, RLE lossless, JPEG
//! baseline/extended/lossless, JPEG 2000).
//!
//! Files are grouped by SeriesInstanceUID and sorted along the slice normal
//! n = row direction x column direction; the slice spacing is measured from
//! ImagePositionPatient, never taken from SliceThickness when positions exist. Geometry:
//! i = columns (row direction), j = rows (column direction), k = increasing position along n,
//! all in LPS, which is DICOM's patient space already. Values are rescaled per slice
//! (RescaleSlope/RescaleIntercept, e.g. to Hounsfield units).
//!
//! Several series in one directory are listed; one is picked with `DIR#N` (1-based index in
//! the listing) or `DIR#UID` (see [`parse_spec`]).

use super::{checked_size, voxels_from_values, Modality, Volume, VolumeError, Voxels};
use dicom_dictionary_std::tags;
use dicom_object::file::ReadPreamble;
use dicom_object::{DefaultDicomObject, InMemDicomObject, OpenFileOptions, Tag};
use glam::{DMat3, DVec3};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub mod seg;
mod tolerant;

/// Which series of a directory to load.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Pick {
    /// 1-based index in the listing ([`Scan::listing`]).
    Index(usize),
    /// SeriesInstanceUID.
    Uid(String),
}

/// Splits a VOLUME argument `DIR`, `DIR#N` or `DIR#UID` into the directory and the pick. A
/// path that exists as written is taken whole (a directory may have '#' in its name).
pub fn parse_spec(spec: &str) -> (PathBuf, Option<Pick>) {
    if Path::new(spec).exists() {
        return (PathBuf::from(spec), None);
    }
    match spec.rsplit_once('#') {
        Some((dir, pick)) if !dir.is_empty() && !pick.is_empty() => {
            let pick = match pick.parse::<usize>() {
                Ok(n) => Pick::Index(n),
                Err(_) => Pick::Uid(pick.to_string()),
            };
            (PathBuf::from(dir), Some(pick))
        }
        _ => (PathBuf::from(spec), None),
    }
}

/// Is `spec` a DICOM series argument: an existing directory, or `DIR#PICK` with an existing
/// directory?
pub fn is_series_spec(spec: &str) -> bool {
    parse_spec(spec).0.is_dir()
}

/// One image plane: a single-frame file, or one frame of a multi-frame file.
#[derive(Clone, Debug)]
struct Slice {
    path: PathBuf,
    frame: u32,
    /// Frames in the file (1 for a classic single-frame image).
    frames_in_file: u32,
    rows: u16,
    cols: u16,
    samples: u16,
    photometric: String,
    bits_allocated: u16,
    bits_stored: u16,
    high_bit: u16,
    signed: bool,
    /// (row spacing, column spacing) as in PixelSpacing.
    pixel_spacing: Option<[f64; 2]>,
    iop: Option<[f64; 6]>,
    ipp: Option<[f64; 3]>,
    slice_thickness: Option<f64>,
    spacing_between: Option<f64>,
    slope: f64,
    intercept: f64,
    instance: Option<i64>,
    /// What tells the volumes of a 4-D series apart: TemporalPositionIdentifier, TriggerTime,
    /// AcquisitionNumber, EchoNumbers (compared in that order).
    phase_key: PhaseKey,
    transfer_syntax: String,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, PartialOrd)]
struct PhaseKey(Option<i64>, Option<f64>, Option<i64>, Option<i64>);

/// One series found in a directory.
#[derive(Clone, Debug)]
pub struct Series {
    pub uid: String,
    pub modality: String,
    pub description: String,
    pub number: Option<i64>,
    /// (t, P): volume t (1-based) of a series that holds P volumes at the same positions
    /// (cardiac phases, time points, echoes), split by `split_phases`.
    pub phase: Option<(usize, usize)>,
    slices: Vec<Slice>,
}

impl Series {
    /// Image planes (slices or frames) in the series.
    pub fn slice_count(&self) -> usize {
        self.slices.len()
    }
    /// The description, with "volume t of P" for one volume of a 4-D series.
    pub fn label(&self) -> String {
        let d = if self.description.is_empty() {
            "(no description)"
        } else {
            &self.description
        };
        match self.phase {
            Some((t, p)) => format!("{d} [volume {t} of {p}]"),
            None => d.to_string(),
        }
    }
    /// (rows, columns) of the first slice.
    pub fn rows_cols(&self) -> (u16, u16) {
        self.slices
            .first()
            .map(|s| (s.rows, s.cols))
            .unwrap_or((0, 0))
    }
}

/// What a directory holds: its image series (sorted by series number, then UID) and the
/// files that were not DICOM images.
#[derive(Clone, Debug)]
pub struct Scan {
    pub dir: PathBuf,
    pub series: Vec<Series>,
    /// Files skipped, with the reason (not DICOM, DICOMDIR, no image).
    pub skipped: Vec<(PathBuf, String)>,
    /// DICOM files whose header cannot be read, with the error: skipped too, as Slicer's
    /// import does, and told (a slice of the loaded series among them leaves a gap, refused).
    pub unreadable: Vec<String>,
}

impl Scan {
    /// The numbered series list, one line each, plus a line on skipped files.
    pub fn listing(&self) -> String {
        let mut s = String::new();
        for (i, se) in self.series.iter().enumerate() {
            let (r, c) = se.rows_cols();
            let _ = writeln!(
                s,
                "  #{:<3} {:<4} {:>5} slices  {} x {}  {}  {}",
                i + 1,
                if se.modality.is_empty() {
                    "?"
                } else {
                    &se.modality
                },
                se.slice_count(),
                r,
                c,
                se.label(),
                se.uid
            );
        }
        if !self.skipped.is_empty() {
            let mut why: BTreeMap<&str, usize> = BTreeMap::new();
            for (_, r) in &self.skipped {
                *why.entry(r.as_str()).or_default() += 1;
            }
            let parts: Vec<String> = why.iter().map(|(r, n)| format!("{n} {r}")).collect();
            let _ = writeln!(
                s,
                "  skipped {} file(s): {}",
                self.skipped.len(),
                parts.join(", ")
            );
        }
        if let Some(note) = self.unreadable_note() {
            let _ = writeln!(s, "  {note}");
        }
        s
    }

    /// A line on the DICOM files whose header cannot be read, if any.
    pub fn unreadable_note(&self) -> Option<String> {
        let first = self.unreadable.first()?;
        Some(format!(
            "{} DICOM file(s) could not be read and were skipped (first: {first})",
            self.unreadable.len()
        ))
    }

    /// Loads `series` (one of this scan's): the note on unreadable files goes to stderr, and
    /// into the error should the load fail.
    fn load(&self, series: &Series) -> Result<Volume, VolumeError> {
        let note = self.unreadable_note();
        if let Some(n) = &note {
            eprintln!("warning: {}: {n}", self.dir.display());
        }
        load_chosen(&self.dir, series).map_err(|e| match (note, e) {
            (Some(n), VolumeError::Format { path, msg }) => VolumeError::Format {
                path,
                msg: format!("{msg}; {n}"),
            },
            (_, e) => e,
        })
    }

    /// The series `pick` names, or the only one.
    pub fn choose(&self, pick: Option<&Pick>) -> Result<&Series, VolumeError> {
        let how = || {
            format!(
                "pick one as {d}#N (N = 1..{n} in this list) or {d}#SERIES_UID",
                d = self.dir.display(),
                n = self.series.len()
            )
        };
        match pick {
            None if self.series.len() == 1 => Ok(&self.series[0]),
            None => Err(VolumeError::format(
                &self.dir,
                format!(
                    "{} DICOM series in this directory:\n{}{}",
                    self.series.len(),
                    self.listing(),
                    how()
                ),
            )),
            Some(Pick::Index(n)) => self.series.get(n.wrapping_sub(1)).ok_or_else(|| {
                VolumeError::format(
                    &self.dir,
                    format!(
                        "no series #{n}: the directory holds {}:\n{}{}",
                        self.series.len(),
                        self.listing(),
                        how()
                    ),
                )
            }),
            Some(Pick::Uid(u)) => {
                let found: Vec<&Series> = self.series.iter().filter(|s| &s.uid == u).collect();
                match found[..] {
                    [one] => Ok(one),
                    [] => Err(VolumeError::format(
                        &self.dir,
                        format!(
                            "no series with SeriesInstanceUID {u}:\n{}{}",
                            self.listing(),
                            how()
                        ),
                    )),
                    _ => Err(VolumeError::format(
                        &self.dir,
                        format!(
                            "SeriesInstanceUID {u} holds {} volumes at the same positions:\n{}\
                             pick one as {}#N",
                            found.len(),
                            self.listing(),
                            self.dir.display()
                        ),
                    )),
                }
            }
        }
    }
}

const DICOMDIR_SOP_CLASS: &str = "1.2.840.10008.1.3.10";
/// Directory levels scanned below the series directory (PACS exports nest a few deep).
const MAX_DEPTH: usize = 16;

/// Reads the headers of every file under `dir` (recursively) and groups the images by series.
/// Errors when the directory has no DICOM image at all (with a broken DICOM file's own error
/// when there is one); DICOM files whose header cannot be read beside readable images are kept
/// in [`Scan::unreadable`].
pub fn scan(dir: &Path) -> Result<Scan, VolumeError> {
    if !dir.is_dir() {
        return Err(VolumeError::format(dir, "not a directory"));
    }
    let mut files = Vec::new();
    collect_files(dir, 0, &mut files)?;
    scan_files(dir, files)
}

/// Reads the headers of `files` and groups the images by series (see [`scan`]).
fn scan_files(dir: &Path, mut files: Vec<PathBuf>) -> Result<Scan, VolumeError> {
    files.sort();
    let results: Vec<Result<Result<Planes, String>, VolumeError>> =
        files.par_iter().map(|p| read_header(p)).collect();
    let mut by_uid: BTreeMap<String, Series> = BTreeMap::new();
    let (mut skipped, mut unreadable): (_, Vec<VolumeError>) = (Vec::new(), Vec::new());
    for (path, r) in files.iter().zip(results) {
        match r {
            Err(e) => unreadable.push(e),
            Ok(Err(reason)) => skipped.push((path.clone(), reason)),
            Ok(Ok(planes)) => {
                for (uid, modality, description, number, slice) in planes {
                    by_uid
                        .entry(uid.clone())
                        .or_insert_with(|| Series {
                            uid,
                            modality,
                            description,
                            number,
                            phase: None,
                            slices: Vec::new(),
                        })
                        .slices
                        .push(slice);
                }
            }
        }
    }
    // A segmentation beside an image series is read by --labels, not offered as a volume (alone
    // in a folder it still loads, as its segment values, as other DICOM readers show it).
    if by_uid.values().any(|s| s.modality != "SEG") {
        let segs: Vec<String> = by_uid
            .iter()
            .filter(|(_, s)| s.modality == "SEG")
            .map(|(uid, _)| uid.clone())
            .collect();
        for uid in segs {
            if let Some(s) = by_uid.remove(&uid) {
                let mut paths: Vec<PathBuf> = s.slices.into_iter().map(|p| p.path).collect();
                paths.dedup();
                for p in paths {
                    skipped.push((p, "a DICOM segmentation (read it with --labels)".into()));
                }
            }
        }
    }
    if by_uid.is_empty() {
        // A broken DICOM file and no image beside it: its own error.
        if let Some(e) = unreadable.into_iter().next() {
            return Err(e);
        }
        return Err(VolumeError::format(
            dir,
            format!(
                "no DICOM image files in this directory ({} file(s) looked at{})",
                files.len(),
                if files.is_empty() {
                    String::new()
                } else {
                    format!(
                        ", none a DICOM image: e.g. {}: {}",
                        skipped[0].0.display(),
                        skipped[0].1
                    )
                }
            ),
        ));
    }
    let mut series: Vec<Series> = by_uid.into_values().flat_map(split_phases).collect();
    series.sort_by(|a, b| {
        (a.number.is_none(), a.number, &a.uid, a.phase).cmp(&(
            b.number.is_none(),
            b.number,
            &b.uid,
            b.phase,
        ))
    });
    Ok(Scan {
        dir: dir.to_path_buf(),
        series,
        skipped,
        unreadable: unreadable.iter().map(|e| e.to_string()).collect(),
    })
}

/// A series whose planes (slices, or frames of enhanced multi-frame files) lie P > 1 times at
/// every one of its positions (cardiac phases, time points or echoes under one
/// SeriesInstanceUID) becomes P series: at each position the planes are ordered by their
/// [`PhaseKey`] (then InstanceNumber and frame), and series t takes the t-th. Anything else is
/// returned whole (a stray duplicate is refused later, by name).
fn split_phases(series: Series) -> Vec<Series> {
    let sl = &series.slices;
    let Some(iop) = sl[0].iop else {
        return vec![series];
    };
    let normal = DVec3::new(iop[0], iop[1], iop[2]).cross(DVec3::new(iop[3], iop[4], iop[5]));
    if sl.len() < 2 || normal.length() < 0.5 || sl.iter().any(|s| s.ipp.is_none()) {
        return vec![series];
    }
    // positions along the normal; planes within 0.01 mm of a position's first share it
    let along = |i: usize| DVec3::from(sl[i].ipp.unwrap_or_default()).dot(normal);
    let mut by_pos: Vec<usize> = (0..sl.len()).collect();
    by_pos.sort_by(|&a, &b| along(a).total_cmp(&along(b)));
    let mut at: Vec<Vec<usize>> = Vec::new();
    for i in by_pos {
        match at.last_mut() {
            Some(g) if along(i) - along(g[0]) < 0.01 => g.push(i),
            _ => at.push(vec![i]),
        }
    }
    let p = at[0].len();
    if p < 2 || at.iter().any(|v| v.len() != p) {
        return vec![series];
    }
    let mut phases: Vec<Vec<Slice>> = vec![Vec::new(); p];
    for idx in &mut at {
        idx.sort_by(|&a, &b| {
            (sl[a].phase_key, sl[a].instance, sl[a].frame)
                .partial_cmp(&(sl[b].phase_key, sl[b].instance, sl[b].frame))
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        for (t, &i) in idx.iter().enumerate() {
            phases[t].push(sl[i].clone());
        }
    }
    phases
        .into_iter()
        .enumerate()
        .map(|(t, slices)| Series {
            uid: series.uid.clone(),
            modality: series.modality.clone(),
            description: series.description.clone(),
            number: series.number,
            phase: Some((t + 1, p)),
            slices,
        })
        .collect()
}

fn collect_files(dir: &Path, depth: usize, out: &mut Vec<PathBuf>) -> Result<(), VolumeError> {
    let rd = std::fs::read_dir(dir).map_err(|e| VolumeError::io(dir, e))?;
    for entry in rd {
        let entry = entry.map_err(|e| VolumeError::io(dir, e))?;
        let p = entry.path();
        // follows symlinks; the depth limit stops link cycles
        if p.is_dir() {
            if depth < MAX_DEPTH {
                collect_files(&p, depth + 1, out)?;
            }
        } else if p.is_file() {
            out.push(p);
        }
    }
    Ok(())
}

/// A file's image planes, each with its series keys (UID, modality, description, number).
type Planes = Vec<(String, String, String, Option<i64>, Slice)>;
/// A file's format (its first plane) and where each of its frames goes in the volume.
type PlaneSlots<'a> = (&'a Slice, Vec<(u32, &'a mut [u16])>);

/// Reads a file through the tolerant pass ([`tolerant`]), then dicom-object; `what` (header,
/// file) names the part read in dicom-object's errors.
fn open(
    path: &Path,
    start: tolerant::Start,
    until: tolerant::Until,
    what: &str,
) -> Result<DefaultDicomObject, VolumeError> {
    let bytes = tolerant::read(path, start, until)?;
    OpenFileOptions::new()
        .read_preamble(ReadPreamble::Never)
        .from_reader(&bytes[..])
        .map_err(|e| VolumeError::format(path, format!("cannot read the DICOM {what}: {e}")))
}

/// The image planes of one file with their series keys; `Ok(Err(reason))` for a file that is
/// not a DICOM image (skipped); `Err` for a DICOM file whose header is broken.
fn read_header(path: &Path) -> Result<Result<Planes, String>, VolumeError> {
    let Some(start) = tolerant::sniff(path) else {
        return Ok(Err("not DICOM".into()));
    };
    // media directories (also damaged ones, which real exports carry) hold no image
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_uppercase());
    if file_name.is_some_and(|n| n.starts_with("DICOMDIR")) {
        return Ok(Err("DICOMDIR".into()));
    }
    let obj = open(path, start, tolerant::Until::PixelData, "header")?;
    if obj
        .meta()
        .media_storage_sop_class_uid()
        .trim_end_matches('\0')
        == DICOMDIR_SOP_CLASS
    {
        return Ok(Err("DICOMDIR".into()));
    }
    let (Some(rows), Some(cols)) = (int(&obj, tags::ROWS), int(&obj, tags::COLUMNS)) else {
        return Ok(Err("without an image (no Rows/Columns)".into()));
    };
    let fmt = |m: String| VolumeError::format(path, m);
    let rows = u16::try_from(rows).map_err(|_| fmt(format!("invalid Rows {rows}")))?;
    let cols = u16::try_from(cols).map_err(|_| fmt(format!("invalid Columns {cols}")))?;
    let uid = text(&obj, tags::SERIES_INSTANCE_UID).unwrap_or_default();
    let modality = text(&obj, tags::MODALITY).unwrap_or_default();
    let description = text(&obj, tags::SERIES_DESCRIPTION).unwrap_or_default();
    let number = int(&obj, tags::SERIES_NUMBER);
    let frames = match int(&obj, tags::NUMBER_OF_FRAMES) {
        None => 1,
        Some(n) if n >= 1 && n <= u32::MAX as i64 => n as u32,
        Some(n) => return Err(fmt(format!("invalid NumberOfFrames {n}"))),
    };
    let u16_of = |tag: Tag, name: &str, default: Option<u16>| -> Result<u16, VolumeError> {
        match int(&obj, tag) {
            Some(v) => u16::try_from(v).map_err(|_| fmt(format!("invalid {name} {v}"))),
            None => default.ok_or_else(|| fmt(format!("no {name}"))),
        }
    };
    let bits_allocated = u16_of(tags::BITS_ALLOCATED, "BitsAllocated", None)?;
    let bits_stored = u16_of(tags::BITS_STORED, "BitsStored", Some(bits_allocated))?;
    let high_bit = u16_of(
        tags::HIGH_BIT,
        "HighBit",
        Some(bits_stored.saturating_sub(1)),
    )?;
    let base = Slice {
        path: path.to_path_buf(),
        frame: 0,
        frames_in_file: frames,
        rows,
        cols,
        samples: u16_of(tags::SAMPLES_PER_PIXEL, "SamplesPerPixel", Some(1))?,
        photometric: text(&obj, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_default(),
        bits_allocated,
        bits_stored,
        high_bit,
        signed: int(&obj, tags::PIXEL_REPRESENTATION) == Some(1),
        pixel_spacing: floats::<2>(&obj, tags::PIXEL_SPACING)
            .or_else(|| floats::<2>(&obj, tags::IMAGER_PIXEL_SPACING)),
        iop: floats::<6>(&obj, tags::IMAGE_ORIENTATION_PATIENT),
        ipp: floats::<3>(&obj, tags::IMAGE_POSITION_PATIENT),
        slice_thickness: floats::<1>(&obj, tags::SLICE_THICKNESS).map(|v| v[0]),
        spacing_between: floats::<1>(&obj, tags::SPACING_BETWEEN_SLICES).map(|v| v[0]),
        slope: floats::<1>(&obj, tags::RESCALE_SLOPE).map_or(1.0, |v| v[0]),
        intercept: floats::<1>(&obj, tags::RESCALE_INTERCEPT).map_or(0.0, |v| v[0]),
        instance: int(&obj, tags::INSTANCE_NUMBER),
        phase_key: PhaseKey(
            int(&obj, tags::TEMPORAL_POSITION_IDENTIFIER),
            floats::<1>(&obj, tags::TRIGGER_TIME).map(|v| v[0]),
            int(&obj, tags::ACQUISITION_NUMBER),
            int(&obj, tags::ECHO_NUMBERS),
        ),
        transfer_syntax: obj
            .meta()
            .transfer_syntax()
            .trim_end_matches('\0')
            .to_string(),
    };
    // Native pixel data must fit in the file; checked before the volume is allocated for it.
    // (Grey-scale only: colour, subsampled and 1-bit data are refused later as unsupported.)
    let native = [
        "1.2.840.10008.1.2",
        "1.2.840.10008.1.2.1",
        "1.2.840.10008.1.2.2",
    ];
    if native.contains(&base.transfer_syntax.trim_end()) && base.samples == 1 {
        let need = (rows as u64 * cols as u64 * frames as u64 * bits_allocated as u64).div_ceil(8);
        let have = std::fs::metadata(path).map_or(u64::MAX, |m| m.len());
        if need > have {
            return Err(fmt(format!(
                "{frames} frame(s) of {cols} x {rows} pixels of {bits_allocated} bits need {need} \
                 bytes of pixel data but the file holds {have} (truncated, or a header that lies \
                 about the image size)"
            )));
        }
    }
    let key = |s: Slice| {
        (
            uid.clone(),
            modality.clone(),
            description.clone(),
            number,
            s,
        )
    };
    if frames == 1 {
        return Ok(Ok(vec![key(base)]));
    }
    // Enhanced multi-frame: geometry and rescale per frame from the functional groups
    // (per-frame first, then shared).
    let per_frame = obj
        .get(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .ok_or_else(|| {
            VolumeError::unsupported(
                path,
                format!(
                    "a multi-frame object ({frames} frames) without per-frame functional groups \
                     (only enhanced CT/MR multi-frame objects place their frames in space)"
                ),
            )
        })?;
    if per_frame.len() != frames as usize {
        return Err(fmt(format!(
            "NumberOfFrames is {frames} but the per-frame functional groups list {}",
            per_frame.len()
        )));
    }
    let shared = obj
        .get(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .and_then(|i| i.first());
    let mut planes = Vec::with_capacity(frames as usize);
    for (f, item) in per_frame.iter().enumerate() {
        let group = |seq: Tag, tag: Tag| -> Option<Vec<f64>> {
            [Some(item), shared].into_iter().flatten().find_map(|g| {
                let inner = g.get(seq)?.items()?.first()?;
                inner.get(tag)?.to_multi_float64().ok()
            })
        };
        let arr = |v: Option<Vec<f64>>| -> Option<Vec<f64>> {
            v.filter(|v| v.iter().all(|x| x.is_finite()))
        };
        let mut s = base.clone();
        s.frame = f as u32;
        if let Some(v) = arr(group(
            tags::FRAME_CONTENT_SEQUENCE,
            tags::TEMPORAL_POSITION_INDEX,
        )) {
            s.phase_key.0 = v.first().map(|&t| t as i64);
        }
        if let Some(v) = arr(group(
            tags::PLANE_POSITION_SEQUENCE,
            tags::IMAGE_POSITION_PATIENT,
        ))
        .filter(|v| v.len() >= 3)
        {
            s.ipp = Some([v[0], v[1], v[2]]);
        }
        if let Some(v) = arr(group(
            tags::PLANE_ORIENTATION_SEQUENCE,
            tags::IMAGE_ORIENTATION_PATIENT,
        ))
        .filter(|v| v.len() >= 6)
        {
            s.iop = Some([v[0], v[1], v[2], v[3], v[4], v[5]]);
        }
        if let Some(v) =
            arr(group(tags::PIXEL_MEASURES_SEQUENCE, tags::PIXEL_SPACING)).filter(|v| v.len() >= 2)
        {
            s.pixel_spacing = Some([v[0], v[1]]);
        }
        if let Some(v) = arr(group(tags::PIXEL_MEASURES_SEQUENCE, tags::SLICE_THICKNESS)) {
            s.slice_thickness = v.first().copied();
        }
        if let Some(v) = arr(group(
            tags::PIXEL_MEASURES_SEQUENCE,
            tags::SPACING_BETWEEN_SLICES,
        )) {
            s.spacing_between = v.first().copied();
        }
        if let Some(v) = arr(group(
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_SLOPE,
        )) {
            s.slope = v.first().copied().unwrap_or(1.0);
        }
        if let Some(v) = arr(group(
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_INTERCEPT,
        )) {
            s.intercept = v.first().copied().unwrap_or(0.0);
        }
        planes.push(key(s));
    }
    Ok(Ok(planes))
}

fn text(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    let s = obj.get(tag)?.to_str().ok()?;
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    Some(s.to_string())
}

fn int(obj: &InMemDicomObject, tag: Tag) -> Option<i64> {
    obj.get(tag)?.to_int::<i64>().ok()
}

/// The first `N` numbers of a numeric element, if it has at least `N` finite ones.
fn floats<const N: usize>(obj: &InMemDicomObject, tag: Tag) -> Option<[f64; N]> {
    let v = obj.get(tag)?.to_multi_float64().ok()?;
    if v.len() < N || v[..N].iter().any(|x| !x.is_finite()) {
        return None;
    }
    let mut a = [0.0; N];
    a.copy_from_slice(&v[..N]);
    Some(a)
}

/// Loads a DICOM series directory. With several series in it, `pick` chooses one (else the
/// error lists them).
pub fn load_series(dir: &Path, pick: Option<&Pick>) -> Result<Volume, VolumeError> {
    let scan = scan(dir)?;
    let series = scan.choose(pick)?;
    scan.load(series)
}

/// Is `path` one DICOM file (a VOLUME argument that loads the series it belongs to)?
pub fn is_dicom_file(path: &Path) -> bool {
    path.is_file() && tolerant::sniff(path).is_some()
}

/// Loads the series one file belongs to, as Slicer's DICOM import does: the files directly in
/// its folder that share its SeriesInstanceUID (for a 4-D series, the volume the file is part
/// of).
pub fn load_file_series(file: &Path) -> Result<Volume, VolumeError> {
    // the file's own problem first, before any other file of the folder is looked at
    if let Err(reason) = read_header(file)? {
        return Err(VolumeError::format(
            file,
            format!("not a DICOM image to load a series from ({reason})"),
        ));
    }
    let dir = match file.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| VolumeError::io(dir, e))? {
        let p = entry.map_err(|e| VolumeError::io(dir, e))?.path();
        if p.is_file() {
            files.push(p);
        }
    }
    let scan = scan_files(dir, files)?;
    let name = file.file_name();
    let series = scan
        .series
        .iter()
        .find(|s| s.slices.iter().any(|sl| sl.path.file_name() == name))
        .ok_or_else(|| VolumeError::format(file, "its series was not found in its folder"))?;
    scan.load(series)
}

/// Loads the DICOM series that `spec` (`DIR`, `DIR#N`, `DIR#UID`) names.
pub fn load_spec(spec: &str) -> Result<Volume, VolumeError> {
    let (dir, pick) = parse_spec(spec);
    load_series(&dir, pick.as_ref())
}

/// Geometry of a sorted series.
struct Geometry {
    /// Slices in k order.
    order: Vec<usize>,
    spacing: [f64; 3],
    directions: DMat3,
    origin: DVec3,
}

fn name_of(p: &Path) -> String {
    p.display().to_string()
}

/// Checks that every slice shares the first one's pixel format and plane geometry, sorts them
/// along the slice normal and measures the spacing.
fn geometry(series: &Series) -> Result<Geometry, VolumeError> {
    let first = &series.slices[0];
    // pixel format first: a colour series fails here with the clearest message
    check_pixel_format(first)?;
    for s in &series.slices[1..] {
        check_same_as_first(series, s)?;
    }
    let plane = Plane::of(first)?;
    match first.ipp {
        // No positions anywhere: stack by InstanceNumber, spacing from the header.
        None => stack_by_instance(series, &plane),
        Some(_) => stack_by_position(series, &plane),
    }
}

/// Refuses a first slice whose samples cannot make a greyscale volume.
fn check_pixel_format(first: &Slice) -> Result<(), VolumeError> {
    let p0 = &first.path;
    if first.samples != 1 || first.photometric.starts_with("PALETTE") {
        return Err(VolumeError::unsupported(
            p0,
            format!(
                "{} samples per pixel ({}): only greyscale images (1 sample per pixel, \
                 MONOCHROME1/2) make a volume",
                first.samples,
                if first.photometric.is_empty() {
                    "no PhotometricInterpretation"
                } else {
                    &first.photometric
                }
            ),
        ));
    }
    if !matches!(first.bits_allocated, 8 | 16) {
        return Err(VolumeError::unsupported(
            p0,
            format!(
                "BitsAllocated {}: only 8- and 16-bit samples are read",
                first.bits_allocated
            ),
        ));
    }
    if first.bits_stored == 0
        || first.bits_stored > first.bits_allocated
        || first.high_bit >= first.bits_allocated
        || first.high_bit + 1 < first.bits_stored
    {
        return Err(VolumeError::format(
            p0,
            format!(
                "inconsistent BitsAllocated {} / BitsStored {} / HighBit {}",
                first.bits_allocated, first.bits_stored, first.high_bit
            ),
        ));
    }
    Ok(())
}

/// Refuses slice `s` unless it has the series' first slice's size, pixel format, pixel spacing
/// and orientation, and a position exactly when the first has one.
fn check_same_as_first(series: &Series, s: &Slice) -> Result<(), VolumeError> {
    let first = &series.slices[0];
    let clash = |what: &str, a: String, b: String| {
        VolumeError::format(
            &s.path,
            format!(
                "mixed series {}: {what} is {b} here but {a} in {} (one series must share one \
                 geometry and pixel format)",
                series.uid,
                name_of(&first.path)
            ),
        )
    };
    let close = |a: &[f64], b: &[f64], tol: f64| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol);
    if (s.rows, s.cols) != (first.rows, first.cols) {
        return Err(clash(
            "Rows x Columns",
            format!("{} x {}", first.rows, first.cols),
            format!("{} x {}", s.rows, s.cols),
        ));
    }
    let format_of = |x: &Slice| {
        (
            x.samples,
            x.bits_allocated,
            x.bits_stored,
            x.high_bit,
            x.signed,
        )
    };
    if format_of(s) != format_of(first) {
        let f = |x: &Slice| {
            format!(
                "{} sample(s) of {}/{} bits (high bit {}, {})",
                x.samples,
                x.bits_stored,
                x.bits_allocated,
                x.high_bit,
                if x.signed { "signed" } else { "unsigned" }
            )
        };
        return Err(clash("the pixel format", f(first), f(s)));
    }
    let ps = |x: &Slice| x.pixel_spacing.map_or("none".into(), |v| format!("{v:?}"));
    match (first.pixel_spacing, s.pixel_spacing) {
        (Some(a), Some(b)) if close(&a, &b, 1e-4 * a[0].abs().max(1.0)) => {}
        (None, None) => {}
        _ => return Err(clash("PixelSpacing", ps(first), ps(s))),
    }
    let io = |x: &Slice| x.iop.map_or("none".into(), |v| format!("{v:?}"));
    match (first.iop, s.iop) {
        (Some(a), Some(b)) if close(&a, &b, 1e-4) => {}
        (None, None) => {}
        _ => return Err(clash("ImageOrientationPatient", io(first), io(s))),
    }
    if s.ipp.is_some() != first.ipp.is_some() {
        let had = |x: &Slice| if x.ipp.is_some() { "present" } else { "absent" };
        return Err(clash(
            "ImagePositionPatient",
            had(first).into(),
            had(s).into(),
        ));
    }
    Ok(())
}

/// The image plane shared by a series' slices: pixel spacing and the row and column
/// directions.
struct Plane {
    row_sp: f64,
    col_sp: f64,
    row_dir: DVec3,
    col_dir: DVec3,
    /// Slice spacing from the header alone (SpacingBetweenSlices, else SliceThickness, else 1).
    header_spacing: f64,
}

impl Plane {
    fn of(first: &Slice) -> Result<Plane, VolumeError> {
        let p0 = &first.path;
        let [row_sp, col_sp] = match first.pixel_spacing {
            Some(v) if v[0] > 0.0 && v[1] > 0.0 => v,
            Some(v) => {
                return Err(VolumeError::format(
                    p0,
                    format!("PixelSpacing {v:?} is not positive"),
                ))
            }
            // no spacing at all (e.g. secondary capture): unit pixels
            None => [1.0, 1.0],
        };
        let header_spacing = [first.spacing_between, first.slice_thickness]
            .into_iter()
            .flatten()
            .find(|v| *v > 0.0)
            .unwrap_or(1.0);
        let (row_dir, col_dir) = match first.iop {
            Some(v) => {
                let r = DVec3::new(v[0], v[1], v[2]);
                let c = DVec3::new(v[3], v[4], v[5]);
                if r.length() < 0.5
                    || c.length() < 0.5
                    || r.normalize().dot(c.normalize()).abs() > 1e-2
                {
                    return Err(VolumeError::format(
                        p0,
                        format!("ImageOrientationPatient {v:?} is not two orthogonal unit vectors"),
                    ));
                }
                let r = r.normalize();
                // re-orthogonalise the rounding in the file away
                let c = (c - r * r.dot(c)).normalize();
                (r, c)
            }
            None if first.ipp.is_none() => (DVec3::X, DVec3::Y),
            None => {
                return Err(VolumeError::format(
                    p0,
                    "ImagePositionPatient without ImageOrientationPatient: cannot place the slices",
                ))
            }
        };
        Ok(Plane {
            row_sp,
            col_sp,
            row_dir,
            col_dir,
            header_spacing,
        })
    }

    fn normal(&self) -> DVec3 {
        self.row_dir.cross(self.col_dir)
    }

    /// The geometry of slices in `order` stacked along `k_dir`, `k_sp` apart, from `origin`.
    fn stack(&self, order: Vec<usize>, k_dir: DVec3, k_sp: f64, origin: DVec3) -> Geometry {
        Geometry {
            order,
            spacing: [self.col_sp, self.row_sp, k_sp],
            directions: DMat3::from_cols(self.row_dir, self.col_dir, k_dir),
            origin,
        }
    }
}

/// Slices without positions: stacked in InstanceNumber (and frame) order, which must tell every
/// slice apart, spaced as the header says.
fn stack_by_instance(series: &Series, plane: &Plane) -> Result<Geometry, VolumeError> {
    let sl = &series.slices;
    let n = sl.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&i| (sl[i].instance, sl[i].frame));
    for w in order.windows(2) {
        let (a, b) = (&sl[w[0]], &sl[w[1]]);
        if n > 1 && (a.instance.is_none() || (a.instance == b.instance && a.frame == b.frame)) {
            return Err(VolumeError::format(
                &b.path,
                format!(
                    "no ImagePositionPatient and no distinct InstanceNumber (clashes with \
                     {}): cannot order the slices",
                    name_of(&a.path)
                ),
            ));
        }
    }
    Ok(plane.stack(order, plane.normal(), plane.header_spacing, DVec3::ZERO))
}

/// Slices with positions: sorted along the slice normal, which must find them distinct, evenly
/// spaced and on one line (a tilted gantry's sheared stack included).
fn stack_by_position(series: &Series, plane: &Plane) -> Result<Geometry, VolumeError> {
    let sl = &series.slices;
    let n = sl.len();
    let normal = plane.normal();
    let pos = |i: usize| DVec3::from(sl[i].ipp.unwrap_or_default());
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| pos(a).dot(normal).total_cmp(&pos(b).dot(normal)));
    let d: Vec<f64> = order
        .windows(2)
        .map(|w| (pos(w[1]) - pos(w[0])).dot(normal))
        .collect();
    let at = |k: usize| {
        format!(
            "{}{}",
            name_of(&sl[order[k]].path),
            frame_tag(&sl[order[k]])
        )
    };
    // two planes at one position: several acquisitions/echoes/phases in one series
    let min_pix = plane.row_sp.min(plane.col_sp);
    for (k, &step) in d.iter().enumerate() {
        if step.abs() < 1e-3 * min_pix.max(0.1) {
            return Err(VolumeError::format(
                &sl[order[k + 1]].path,
                format!(
                    "mixed series {}: {} and {} lie at the same position ({:.3} mm along the \
                     slice normal): several acquisitions, echoes or time points in one series \
                     cannot make one volume",
                    series.uid,
                    at(k + 1),
                    at(k),
                    pos(order[k]).dot(normal)
                ),
            ));
        }
    }
    let origin = pos(order[0]);
    if n == 1 {
        return Ok(plane.stack(order, normal, plane.header_spacing, origin));
    }
    let mut sorted = d.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    // positions are written with a few decimals: allow rounding, not a missing slice
    let tol = 0.05 * median + 0.01;
    for (k, &step) in d.iter().enumerate() {
        if (step - median).abs() > tol {
            return Err(VolumeError::format(
                &sl[order[k + 1]].path,
                format!(
                    "slices are not evenly spaced: {:.4} mm from {} to {}, where the usual step \
                     is {:.4} mm (a missing slice, or slices from different stacks?)",
                    step,
                    at(k),
                    at(k + 1),
                    median
                ),
            ));
        }
    }
    // The mean step over the whole stack; it leaves the normal only under gantry tilt, where
    // k follows the tilted stack (a sheared grid) so the anatomy keeps its true shape.
    let step = (pos(order[n - 1]) - origin) / (n - 1) as f64;
    for (k, &i) in order.iter().enumerate() {
        let off = pos(i) - (origin + step * k as f64);
        if off.length() > tol {
            return Err(VolumeError::format(
                &sl[i].path,
                format!(
                    "slice positions do not lie on one line: {} is {:.3} mm off the line \
                     through the first and last slice",
                    at(k),
                    off.length()
                ),
            ));
        }
    }
    let along = step.dot(normal);
    let lateral = (step - normal * along).length();
    let (k_dir, k_sp) = if lateral <= 1e-3 * along {
        (normal, along)
    } else {
        (step.normalize(), step.length())
    };
    Ok(plane.stack(order, k_dir, k_sp, origin))
}

fn frame_tag(s: &Slice) -> String {
    if s.frames_in_file > 1 {
        format!(" (frame {})", s.frame + 1)
    } else {
        String::new()
    }
}

/// Decoded stored values of one plane as raw bit patterns (masked to BitsStored, shifted from
/// HighBit; sign extension happens in [`to_voxels`]).
fn decode_planes(
    path: &Path,
    frames: Vec<(u32, &mut [u16])>,
    fmt: &Slice,
) -> Result<(), VolumeError> {
    use dicom_pixeldata::PixelDecoder;
    let start = tolerant::sniff(path)
        .ok_or_else(|| VolumeError::format(path, "no longer a DICOM file (changed on disk?)"))?;
    let obj = open(path, start, tolerant::Until::End, "file")?;
    check_transfer_syntax(path, obj.meta().transfer_syntax())?;
    let px_count = fmt.rows as usize * fmt.cols as usize;
    let bytes = (fmt.bits_allocated / 8) as usize;
    let pixel_data = obj
        .get(tags::PIXEL_DATA)
        .ok_or_else(|| VolumeError::format(path, "no pixel data (PixelData element missing)"))?;
    // RLE: dicom-rs trusts each fragment's header (it allocates the segment count it reads
    // and slices by its offsets); PS3.5 G.3.1 allows at most 15 segments in a 64-byte header.
    if obj.meta().transfer_syntax().trim_end_matches(['\0', ' ']) == "1.2.840.10008.1.2.5" {
        for (i, f) in pixel_data
            .value()
            .fragments()
            .unwrap_or_default()
            .iter()
            .enumerate()
        {
            let segments = f
                .get(0..4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
            if f.len() < 64 || !matches!(segments, Some(1..=15)) {
                return Err(VolumeError::format(
                    path,
                    format!(
                        "RLE fragment {} is not an RLE frame ({} bytes, {} segments; a 64-byte \
                         header with 1 to 15 segments is required)",
                        i + 1,
                        f.len(),
                        segments.unwrap_or(0)
                    ),
                ));
            }
        }
    }
    // native data: the header must not promise more pixels than the element holds
    if let Some(p) = pixel_data.value().primitive() {
        let have = p.calculate_byte_len() as u64;
        let need = px_count as u64 * bytes as u64 * fmt.frames_in_file as u64;
        if have < need {
            return Err(VolumeError::format(
                path,
                format!(
                    "pixel data holds {have} bytes; {} frame(s) of {} x {} pixels of {} bits \
                     need {need} (Rows/Columns/BitsAllocated do not match the data)",
                    fmt.frames_in_file, fmt.cols, fmt.rows, fmt.bits_allocated
                ),
            ));
        }
    }
    let shift = fmt.high_bit + 1 - fmt.bits_stored;
    let mask: u32 = if fmt.bits_stored >= 16 {
        0xffff
    } else {
        (1u32 << fmt.bits_stored) - 1
    };
    for (frame, out) in frames {
        let decoded = quietly(|| obj.decode_pixel_data_frame(frame))
            .ok_or_else(|| {
                VolumeError::format(path, "the pixel data decoder failed (corrupt data?)")
            })?
            .map_err(|e| {
                VolumeError::format(
                    path,
                    format!(
                        "cannot decode the pixel data{}: {e}",
                        frame_tag_n(fmt, frame)
                    ),
                )
            })?;
        let data = decoded.data();
        let need = px_count * bytes;
        if data.len() < need {
            return Err(VolumeError::format(
                path,
                format!(
                    "pixel data{} holds {} bytes; {} x {} pixels of {} bits need {}",
                    frame_tag_n(fmt, frame),
                    data.len(),
                    fmt.cols,
                    fmt.rows,
                    fmt.bits_allocated,
                    need
                ),
            ));
        }
        match bytes {
            1 => {
                for (o, &b) in out.iter_mut().zip(&data[..need]) {
                    *o = ((b as u32 >> shift) & mask) as u16;
                }
            }
            _ => {
                for (o, c) in out.iter_mut().zip(data[..need].chunks_exact(2)) {
                    let v = u16::from_ne_bytes([c[0], c[1]]) as u32;
                    *o = ((v >> shift) & mask) as u16;
                }
            }
        }
    }
    Ok(())
}

/// Refuses transfer syntaxes that no compiled-in decoder reads (JPEG-LS, JPEG XL, unknown).
fn check_transfer_syntax(path: &Path, uid: &str) -> Result<(), VolumeError> {
    use dicom_encoding::transfer_syntax::TransferSyntaxIndex;
    use dicom_transfer_syntax_registry::TransferSyntaxRegistry;
    let uid = uid.trim_end_matches('\0');
    match TransferSyntaxRegistry.get(uid) {
        None => Err(VolumeError::unsupported(
            path,
            format!("unknown transfer syntax {uid}"),
        )),
        Some(ts) if !ts.can_decode_all() => Err(VolumeError::unsupported(
            path,
            format!(
                "transfer syntax {uid} ({}) has no pure-Rust decoder here; convert the series \
                 to an uncompressed, RLE, JPEG or JPEG 2000 syntax first (e.g. with dcmtk's \
                 dcmdjpls or gdcmconv --raw)",
                ts.name()
            ),
        )),
        Some(_) => Ok(()),
    }
}

thread_local! {
    static IN_CODEC: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs a codec on untrusted data, with a panic inside it (some pure-Rust decoders unwrap on
/// corrupt input) turned into None and its message kept off stderr: the caller names the file
/// instead. Panics anywhere else still reach the previous panic hook.
fn quietly<T>(f: impl FnOnce() -> T) -> Option<T> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !IN_CODEC.with(std::cell::Cell::get) {
                previous(info)
            }
        }));
    });
    IN_CODEC.with(|c| c.set(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    IN_CODEC.with(|c| c.set(false));
    r.ok()
}

fn frame_tag_n(s: &Slice, frame: u32) -> String {
    if s.frames_in_file > 1 {
        format!(" (frame {})", frame + 1)
    } else {
        String::new()
    }
}

/// Stored values -> voxel values: sign extension from `bits_stored`, then `v * slope +
/// intercept` per plane (`rescale[k]` for plane k), typed by [`voxels_from_values`] (int16 or
/// uint16 when every value is an integer that fits, float32 otherwise).
fn to_voxels(
    path: &Path,
    raw: Vec<u16>,
    dims: [usize; 3],
    bits_stored: u16,
    signed: bool,
    rescale: &[(f64, f64)],
) -> Result<Voxels, VolumeError> {
    let sign_bit = 1u32 << (bits_stored.clamp(1, 16) - 1);
    let stored = move |r: u16| -> i32 {
        let r = r as u32;
        if signed && r & sign_bit != 0 {
            r as i32 - (sign_bit << 1) as i32
        } else {
            r as i32
        }
    };
    let plane = (dims[0] * dims[1]).max(1);
    voxels_from_values(path, dims, |n| {
        let (slope, inter) = rescale[n / plane];
        stored(raw[n]) as f64 * slope + inter
    })
}

/// Loads one scanned series: geometry, then every plane decoded into its place.
fn load_chosen(dir: &Path, series: &Series) -> Result<Volume, VolumeError> {
    let g = geometry(series)?;
    let sl = &series.slices;
    let first = &sl[0];
    let dims = [first.cols as u64, first.rows as u64, sl.len() as u64];
    let (count, _) = checked_size(dir, dims, 2)?;
    for s in sl {
        if !(s.slope.is_finite() && s.intercept.is_finite() && s.slope != 0.0) {
            return Err(VolumeError::format(
                &s.path,
                format!(
                    "invalid RescaleSlope {} / RescaleIntercept {}",
                    s.slope, s.intercept
                ),
            ));
        }
    }
    let mut checked = std::collections::BTreeSet::new();
    for s in sl {
        if checked.insert(s.transfer_syntax.as_str()) {
            check_transfer_syntax(&s.path, &s.transfer_syntax)?;
        }
    }
    let plane = first.cols as usize * first.rows as usize;
    let mut raw = vec![0u16; count];
    // each plane's slot, grouped by file so a multi-frame file is opened once
    let mut by_file: BTreeMap<&Path, PlaneSlots> = BTreeMap::new();
    for (k, chunk) in raw.chunks_mut(plane).enumerate() {
        let s = &sl[g.order[k]];
        by_file
            .entry(&s.path)
            .or_insert_with(|| (s, Vec::new()))
            .1
            .push((s.frame, chunk));
    }
    by_file
        .into_par_iter()
        .try_for_each(|(path, (s, frames))| decode_planes(path, frames, s))?;
    let rescale: Vec<(f64, f64)> = g
        .order
        .iter()
        .map(|&i| (sl[i].slope, sl[i].intercept))
        .collect();
    let voxels = to_voxels(
        dir,
        raw,
        dims.map(|d| d as usize),
        first.bits_stored,
        first.signed,
        &rescale,
    )?;
    let modality = match series.modality.as_str() {
        "CT" => Modality::Ct,
        "MR" => Modality::Mr,
        _ => Modality::Unknown,
    };
    let base = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "dicom".into());
    let name = if series.description.is_empty() && series.phase.is_none() {
        base
    } else {
        format!("{base} ({})", series.label())
    };
    Ok(Volume {
        whole_range: None,
        name,
        dims: [dims[0] as usize, dims[1] as usize, dims[2] as usize],
        spacing: g.spacing,
        directions: g.directions,
        origin: g.origin,
        modality,
        voxels,
        labels: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn picks_parse_from_the_volume_argument() {
        assert_eq!(
            parse_spec("/no/such/dir#3"),
            (PathBuf::from("/no/such/dir"), Some(Pick::Index(3)))
        );
        assert_eq!(
            parse_spec("/no/such/dir#1.2.840.99"),
            (
                PathBuf::from("/no/such/dir"),
                Some(Pick::Uid("1.2.840.99".into()))
            )
        );
        assert_eq!(
            parse_spec("/no/such/dir"),
            (PathBuf::from("/no/such/dir"), None)
        );
        assert_eq!(
            parse_spec("/no/such/dir#"),
            (PathBuf::from("/no/such/dir#"), None)
        );
        // an existing path with '#' in its name is taken whole
        let s = super::super::test_scratch::Scratch::new("dicom#pick");
        let whole = s.0.to_str().unwrap().to_string();
        assert_eq!(parse_spec(&whole), (s.0.clone(), None));
    }

    #[test]
    fn stored_values_are_sign_extended_and_rescaled_per_slice() {
        let p = Path::new("x");
        // 12-bit signed: 0xfff is -1, 0x800 is -2048
        let v = to_voxels(
            p,
            vec![0xfff, 0x800, 5, 7],
            [2, 1, 2],
            12,
            true,
            &[(1.0, 0.0), (2.0, -3.0)],
        )
        .unwrap();
        assert_eq!(v, Voxels::I16(vec![-1, -2048, 7, 11]));
        // beyond int16 but non-negative: uint16
        let v = to_voxels(p, vec![60000, 1], [2, 1, 1], 16, false, &[(1.0, 10.0)]).unwrap();
        assert_eq!(v, Voxels::U16(vec![60010, 11]));
        // non-integral after rescale (e.g. PET, scaled MR): float32
        let v = to_voxels(p, vec![1, 2], [2, 1, 1], 16, false, &[(0.5, 0.0)]).unwrap();
        assert_eq!(v, Voxels::F32(vec![0.5, 1.0]));
        let v = to_voxels(p, vec![65535, 0], [2, 1, 1], 16, false, &[(2.0, 0.0)]).unwrap();
        assert_eq!(v, Voxels::F32(vec![131070.0, 0.0]));
    }
}
