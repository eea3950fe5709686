//! MetaImage reader and writer (ITK's `.mha`, header and data in one file, and `.mhd`, a text
//! header naming a separate data file).
//!
//! Reads 3-D scalar images, raw or zlib-compressed, either byte order. MET_UCHAR, MET_CHAR,
//! MET_SHORT and MET_USHORT are read as they are; MET_INT, MET_UINT, MET_FLOAT and MET_DOUBLE
//! become int16/uint16 when every value is an integer that fits, else float32 (NaN and
//! infinities are refused). MetaImage
//! geometry is already in LPS, so it is taken as written.

use super::data_source::{self, DataSource, Described, Skip};
use super::{
    checked_size, read_wide, split_axes, write_atomically, write_voxels, Modality, Volume,
    VolumeError, Voxels, WideSamples, WideType,
};
use flate2::read::ZlibDecoder;
use flate2::write::ZlibEncoder;
use flate2::Compression;
use glam::{DMat3, DVec3};
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};

/// Longest accepted header (a binary file must not make us read gigabytes of "lines").
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Maps a MetaImage element type; `Err` carries the message.
fn parse_type(s: &str) -> Result<WideType, String> {
    Ok(match s.trim().to_ascii_uppercase().as_str() {
        "MET_UCHAR" => WideType::U8,
        "MET_CHAR" => WideType::I8,
        "MET_SHORT" => WideType::I16,
        "MET_USHORT" => WideType::U16,
        "MET_INT" | "MET_LONG" => WideType::I32,
        "MET_UINT" | "MET_ULONG" => WideType::U32,
        "MET_FLOAT" => WideType::F32,
        "MET_DOUBLE" => WideType::F64,
        t if t.ends_with("_ARRAY") => return Err(format!("vector element type {t}")),
        t => return Err(format!("element type {t}")),
    })
}

/// Reads `Key = Value` lines up to and including `ElementDataFile` (which ends the header).
/// Returns the fields (keys lower-cased) and the byte offset just after the header.
fn read_header<R: BufRead>(
    path: &Path,
    r: &mut R,
) -> Result<(HashMap<String, String>, u64), VolumeError> {
    let mut fields = HashMap::new();
    let mut line = Vec::new();
    let mut total = 0u64;
    loop {
        line.clear();
        let n = (&mut *r)
            .take(MAX_HEADER_BYTES + 1 - total.min(MAX_HEADER_BYTES))
            .read_until(b'\n', &mut line)
            .map_err(|e| VolumeError::io(path, e))?;
        total += n as u64;
        if n == 0 {
            return Err(VolumeError::format(
                path,
                if fields.is_empty() {
                    "empty file, not a MetaImage header".to_string()
                } else {
                    "header ends without `ElementDataFile`".to_string()
                },
            ));
        }
        if total > MAX_HEADER_BYTES {
            return Err(VolumeError::format(
                path,
                format!("header longer than {MAX_HEADER_BYTES} bytes without `ElementDataFile`"),
            ));
        }
        let text = std::str::from_utf8(&line).map_err(|_| {
            VolumeError::format(path, "not a MetaImage header (binary data in the header)")
        })?;
        let text = text.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let Some(eq) = text.find('=') else {
            return Err(VolumeError::format(
                path,
                format!("header line {text:?} is not `Key = Value`: not a MetaImage header"),
            ));
        };
        let key = text[..eq].trim().to_ascii_lowercase();
        let value = text[eq + 1..].trim().to_string();
        let done = key == "elementdatafile";
        fields.insert(key, value);
        if done {
            return Ok((fields, total));
        }
    }
}

/// Parses `n` whitespace-separated numbers.
fn numbers<T: std::str::FromStr>(s: &str, n: usize) -> Option<Vec<T>> {
    let v: Vec<T> = s
        .split_whitespace()
        .map(|x| x.parse::<T>())
        .collect::<Result<_, _>>()
        .ok()?;
    (v.len() == n).then_some(v)
}

fn boolean(s: &str) -> Option<bool> {
    match s.trim().to_ascii_lowercase().as_str() {
        "true" | "1" | "yes" => Some(true),
        "false" | "0" | "no" => Some(false),
        _ => None,
    }
}

/// Loads a 3-D MetaImage (`.mha` or `.mhd` + data file).
pub fn load(path: &Path) -> Result<Volume, VolumeError> {
    let file = File::open(path).map_err(|e| VolumeError::io(path, e))?;
    let mut reader = BufReader::new(file);
    let (h, header_end) = read_header(path, &mut reader)?;
    let fields = Fields { path, h: &h };
    let shape = fields.shape()?;
    let storage = fields.storage()?;
    let geometry = fields.geometry()?;
    let modality = match fields
        .get(&["modality"])
        .map(str::to_ascii_uppercase)
        .as_deref()
    {
        Some("MET_MOD_CT") => Modality::Ct,
        Some("MET_MOD_MR") => Modality::Mr,
        _ => Modality::Unknown,
    };
    let df = fields.required("elementdatafile", "ElementDataFile")?;
    let (source, data, start) = if df.eq_ignore_ascii_case("local") {
        (DataSource::attached(path), reader, header_end)
    } else {
        let (source, data) = DataSource::detached(path, "ElementDataFile =", df)?;
        (source, data, 0)
    };
    let voxels = read_payload(&source, data, start, &shape, &storage)?;
    let volume = data_source::loaded_volume(path, shape.dims, geometry, modality, voxels);
    Ok(volume)
}

/// The header's fields (keys lower-cased) and the file they came from, for the messages.
struct Fields<'a> {
    path: &'a Path,
    h: &'a HashMap<String, String>,
}

/// The samples a header describes.
struct Shape {
    dims: [u64; 3],
    ty: WideType,
    /// The element type as written (for messages).
    ty_s: String,
    data_bytes: u64,
}

/// How the samples are stored.
struct Storage {
    big_endian: bool,
    compressed: bool,
    compressed_size: Option<u64>,
    /// `HeaderSize`: bytes before the data, or -1 (the data are the file's last bytes).
    header_size: i64,
}

impl Fields<'_> {
    fn fmt(&self, m: String) -> VolumeError {
        VolumeError::format(self.path, m)
    }

    /// The first of `keys` present.
    fn get(&self, keys: &[&str]) -> Option<&str> {
        keys.iter().find_map(|k| self.h.get(*k).map(String::as_str))
    }

    /// A required field's value, or the error naming it.
    fn required(&self, key: &str, name: &str) -> Result<&str, VolumeError> {
        self.get(&[key])
            .ok_or_else(|| self.fmt(format!("missing required field `{name}`")))
    }

    /// Step 1: `ObjectType`, `NDims`, `DimSize`, `ElementNumberOfChannels`, `ElementType`.
    fn shape(&self) -> Result<Shape, VolumeError> {
        let path = self.path;
        if let Some(t) = self.get(&["objecttype"]) {
            if !t.eq_ignore_ascii_case("image") {
                return Err(VolumeError::unsupported(
                    path,
                    format!("ObjectType {t:?} (only Image)"),
                ));
            }
        }
        let ndims = self.required("ndims", "NDims")?;
        if ndims != "3" {
            return Err(VolumeError::unsupported(
                path,
                format!("NDims {ndims}: only 3-dimensional images are supported"),
            ));
        }
        let ds = self.required("dimsize", "DimSize")?;
        let d: Vec<u64> =
            numbers(ds, 3).ok_or_else(|| self.fmt(format!("invalid DimSize {ds:?} (3 sizes)")))?;
        let dims = [d[0], d[1], d[2]];
        if let Some(c) = self.get(&["elementnumberofchannels"]) {
            if c.trim() != "1" {
                return Err(VolumeError::unsupported(
                    path,
                    format!("ElementNumberOfChannels {c} (only scalar images)"),
                ));
            }
        }
        let ts = self.required("elementtype", "ElementType")?;
        let ty = parse_type(ts).map_err(|m| {
            VolumeError::unsupported(
                path,
                format!(
                    "{m}; supported are MET_UCHAR, MET_CHAR, MET_SHORT, MET_USHORT, MET_INT, \
                     MET_UINT, MET_FLOAT and MET_DOUBLE"
                ),
            )
        })?;
        let (_, data_bytes) = checked_size(path, dims, ty.bytes())?;
        Ok(Shape {
            dims,
            ty,
            ty_s: ts.to_string(),
            data_bytes,
        })
    }

    /// Step 2: `BinaryData`, the byte order, `CompressedData(Size)` and `HeaderSize`.
    fn storage(&self) -> Result<Storage, VolumeError> {
        if let Some(b) = self.get(&["binarydata"]) {
            if boolean(b) == Some(false) {
                return Err(VolumeError::unsupported(
                    self.path,
                    "BinaryData = False (ASCII data)",
                ));
            }
        }
        let big_endian = match self.get(&["binarydatabyteordermsb", "elementbyteordermsb"]) {
            Some(s) => {
                boolean(s).ok_or_else(|| self.fmt(format!("invalid byte order flag {s:?}")))?
            }
            None => false,
        };
        let compressed = match self.get(&["compresseddata"]) {
            Some(s) => {
                boolean(s).ok_or_else(|| self.fmt(format!("invalid CompressedData {s:?}")))?
            }
            None => false,
        };
        let compressed_size: Option<u64> = match self.get(&["compresseddatasize"]) {
            Some(s) => Some(
                s.parse()
                    .map_err(|_| self.fmt(format!("invalid CompressedDataSize {s:?}")))?,
            ),
            None => None,
        };
        let header_size: i64 = match self.get(&["headersize"]) {
            Some(s) => s
                .parse()
                .ok()
                .filter(|&v| v >= -1)
                .ok_or_else(|| self.fmt(format!("invalid HeaderSize {s:?} (must be >= -1)")))?,
            None => 0,
        };
        Ok(Storage {
            big_endian,
            compressed,
            compressed_size,
            header_size,
        })
    }

    /// Step 3: (spacing, directions, origin) from `ElementSpacing`, `TransformMatrix` and
    /// `Offset` (already LPS).
    fn geometry(&self) -> Result<([f64; 3], DMat3, DVec3), VolumeError> {
        let spacing = match self.get(&["elementspacing", "elementsize"]) {
            Some(s) => {
                let v: Vec<f64> = numbers(s, 3)
                    .ok_or_else(|| self.fmt(format!("invalid ElementSpacing {s:?}")))?;
                if v.iter().any(|x| !(x.is_finite() && *x > 0.0)) {
                    return Err(
                        self.fmt(format!("invalid ElementSpacing {s:?} (must be positive)"))
                    );
                }
                [v[0], v[1], v[2]]
            }
            None => [1.0; 3],
        };
        // ITK's convention: the i-th triple of TransformMatrix is the direction of axis i.
        let directions = match self.get(&["transformmatrix", "orientation", "rotation"]) {
            Some(s) => {
                let v: Vec<f64> = numbers(s, 9)
                    .filter(|v: &Vec<f64>| v.iter().all(|x| x.is_finite()))
                    .ok_or_else(|| {
                        self.fmt(format!("invalid TransformMatrix {s:?} (9 numbers)"))
                    })?;
                let m =
                    DMat3::from_cols_array(&[v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]]);
                split_axes(self.path, m)?.1
            }
            None => DMat3::IDENTITY,
        };
        let origin = match self.get(&["offset", "position", "origin"]) {
            Some(s) => {
                let v: Vec<f64> = numbers(s, 3)
                    .filter(|v: &Vec<f64>| v.iter().all(|x| x.is_finite()))
                    .ok_or_else(|| self.fmt(format!("invalid Offset {s:?} (3 numbers)")))?;
                DVec3::new(v[0], v[1], v[2])
            }
            None => DVec3::ZERO,
        };
        Ok((spacing, directions, origin))
    }
}

/// Step 4: reads the samples, `start` bytes into `data` (after the header of a `.mha`), raw or
/// zlib-compressed, after `HeaderSize`.
fn read_payload(
    source: &DataSource,
    mut data: BufReader<File>,
    start: u64,
    shape: &Shape,
    storage: &Storage,
) -> Result<Voxels, VolumeError> {
    let path = source.header();
    let samples = WideSamples {
        ty: shape.ty,
        dims: shape.dims.map(|d| d as usize),
        big_endian: storage.big_endian,
        scale: None,
    };
    if storage.compressed {
        if storage.header_size == -1 {
            return Err(VolumeError::unsupported(
                path,
                "HeaderSize = -1 with compressed data",
            ));
        }
        let start = start.saturating_add(storage.header_size as u64);
        if start > source.file_len(&data)? {
            return Err(source.truncated("zlib ", shape.data_bytes, 0));
        }
        source.seek(&mut data, start)?;
        let limit = storage.compressed_size.unwrap_or(u64::MAX);
        let mut dec = ZlibDecoder::new(data.take(limit));
        let what = source.what("zlib ");
        read_wide(path, &what, &mut dec, samples, false)
    } else {
        let skip = match storage.header_size {
            -1 => Skip::Tail,
            s => Skip::Bytes(s as u64),
        };
        let d = shape.dims;
        let described = Described {
            shape: format!("{} x {} x {} {}", d[0], d[1], d[2], shape.ty_s),
            fields: "DimSize or ElementType",
        };
        let start = source.locate_raw(&data, start, skip, shape.data_bytes, &described)?;
        source.seek(&mut data, start)?;
        read_wide(path, &source.what(""), &mut data, samples, true)
    }
}

/// Writes `vol` as little-endian MetaImage: `.mhd` gets its data in `<stem>.raw` (`.zraw` when
/// `compressed`) next to it, anything else (`.mha`) holds the data itself. `compressed`: zlib,
/// compressed in memory first because the header must state `CompressedDataSize`. Each file is
/// written under a temporary name and renamed when complete (the data file before the header).
pub fn write(path: &Path, vol: &Volume, compressed: bool) -> Result<(), VolumeError> {
    if vol.dims.contains(&0) || vol.voxel_count() != vol.voxels.len() {
        return Err(VolumeError::format(
            path,
            format!(
                "cannot write: sizes {:?} do not match {} voxels",
                vol.dims,
                vol.voxels.len()
            ),
        ));
    }
    if vol.spacing.iter().any(|s| !(s.is_finite() && *s > 0.0))
        || !vol.directions.is_finite()
        || !vol.origin.is_finite()
    {
        return Err(VolumeError::format(
            path,
            "cannot write: spacing, directions or origin are invalid",
        ));
    }
    let payload = if compressed {
        let mut enc = ZlibEncoder::new(Vec::new(), Compression::default());
        write_voxels(&mut enc, &vol.voxels, false).map_err(|e| VolumeError::io(path, e))?;
        Some(enc.finish().map_err(|e| VolumeError::io(path, e))?)
    } else {
        None
    };
    let detached = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mhd"));
    let d = vol.directions;
    let v3 = |v: DVec3| format!("{} {} {}", v.x + 0.0, v.y + 0.0, v.z + 0.0);
    let mut h = String::new();
    h.push_str("ObjectType = Image\nNDims = 3\nBinaryData = True\n");
    h.push_str("BinaryDataByteOrderMSB = False\n");
    h.push_str(&format!(
        "CompressedData = {}\n",
        if compressed { "True" } else { "False" }
    ));
    if let Some(p) = &payload {
        h.push_str(&format!("CompressedDataSize = {}\n", p.len()));
    }
    h.push_str(&format!(
        "TransformMatrix = {} {} {}\n",
        v3(d.x_axis),
        v3(d.y_axis),
        v3(d.z_axis)
    ));
    h.push_str(&format!("Offset = {}\n", v3(vol.origin)));
    h.push_str("CenterOfRotation = 0 0 0\n");
    h.push_str(&format!(
        "ElementSpacing = {} {} {}\n",
        vol.spacing[0], vol.spacing[1], vol.spacing[2]
    ));
    h.push_str(&format!(
        "DimSize = {} {} {}\n",
        vol.dims[0], vol.dims[1], vol.dims[2]
    ));
    match vol.modality {
        Modality::Ct => h.push_str("Modality = MET_MOD_CT\n"),
        Modality::Mr => h.push_str("Modality = MET_MOD_MR\n"),
        Modality::Unknown => {}
    }
    let et = match vol.voxels {
        Voxels::U8(_) => "MET_UCHAR",
        Voxels::I16(_) => "MET_SHORT",
        Voxels::U16(_) => "MET_USHORT",
        Voxels::F32(_) => "MET_FLOAT",
    };
    h.push_str(&format!("ElementType = {et}\n"));
    let body = |w: &mut dyn Write| match &payload {
        Some(p) => w.write_all(p),
        None => write_voxels(w, &vol.voxels, false),
    };
    if detached {
        let stem = path
            .file_stem()
            .ok_or_else(|| VolumeError::format(path, "cannot write: not a file path"))?
            .to_string_lossy()
            .into_owned();
        let data_name = format!("{stem}.{}", if compressed { "zraw" } else { "raw" });
        let data_path: PathBuf = path.with_file_name(&data_name);
        write_atomically(&data_path, body)?;
        h.push_str(&format!("ElementDataFile = {data_name}\n"));
        write_atomically(path, |w| w.write_all(h.as_bytes()))
    } else {
        h.push_str("ElementDataFile = LOCAL\n");
        write_atomically(path, |w| {
            w.write_all(h.as_bytes())?;
            body(w)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unique scratch directory for this module's tests, removed on drop.
    fn scratch(tag: &str) -> crate::volume::test_scratch::Scratch {
        crate::volume::test_scratch::Scratch::new(&format!("mha-{tag}"))
    }

    fn sample(voxels: Voxels) -> Volume {
        Volume {
            whole_range: None,
            name: "t".into(),
            dims: [5, 4, 3],
            spacing: [0.7, 1.25, 3.0],
            directions: DMat3::from_rotation_z(0.3) * DMat3::from_rotation_x(-0.7),
            origin: DVec3::new(-12.5, 30.25, 7.0),
            modality: Modality::Ct,
            voxels,
            labels: None,
        }
    }

    fn assert_same_geometry(a: &Volume, b: &Volume) {
        assert_eq!(a.dims, b.dims);
        for i in 0..3 {
            assert!(
                (a.spacing[i] - b.spacing[i]).abs() < 1e-9,
                "{:?}",
                a.spacing
            );
        }
        assert!(
            a.directions.abs_diff_eq(b.directions, 1e-9),
            "{:?} vs {:?}",
            a.directions,
            b.directions
        );
        assert!(a.origin.abs_diff_eq(b.origin, 1e-9));
    }

    fn err_of(path: &Path) -> String {
        let e = load(path).expect_err("load should fail").to_string();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(e.contains(&name), "error {e:?} does not name {name}");
        e
    }

    const GEOMETRY: &str = "ObjectType = Image\nNDims = 3\nDimSize = 5 4 3\n\
                            ElementSpacing = 0.5 2 3\nOffset = 1 2 3\n";

    fn write_file(path: &Path, header: &str, data: &[u8]) {
        let mut b = header.as_bytes().to_vec();
        b.extend_from_slice(data);
        std::fs::write(path, b).unwrap();
    }

    #[test]
    fn round_trips_mha_mhd_raw_and_zlib() {
        let s = scratch("rt");
        let n = 60;
        let cases = [
            Voxels::U8((0..n).map(|i| (i * 37 % 256) as u8).collect()),
            Voxels::I16((0..n).map(|i| (i as i16 - 30) * 1000).collect()),
            Voxels::U16((0..n).map(|i| (i as u16) * 1000 + 7).collect()),
        ];
        for (c, vox) in cases.into_iter().enumerate() {
            let vol = sample(vox);
            for ext in ["mha", "mhd"] {
                for z in [false, true] {
                    let p = s.file(&format!("v{c}{z}.{ext}"));
                    write(&p, &vol, z).unwrap();
                    let back = load(&p).unwrap();
                    assert_eq!(back.voxels, vol.voxels, "{}", p.display());
                    assert_same_geometry(&back, &vol);
                    assert_eq!(back.modality, Modality::Ct);
                }
            }
        }
        assert!(s.file("v0false.raw").exists() && s.file("v0true.zraw").exists());
    }

    #[test]
    fn round_trip_every_sample_type() {
        use crate::volume::test_types::cases;
        let s = scratch("types");
        let want_geometry = Volume {
            spacing: [0.5, 2.0, 3.0],
            directions: DMat3::IDENTITY,
            origin: DVec3::new(1.0, 2.0, 3.0),
            ..sample(Voxels::U8(vec![]))
        };
        for c in cases() {
            let p = s.file(&format!("{}.mha", c.name));
            write_file(
                &p,
                &format!(
                    "{GEOMETRY}ElementType = {}\nElementDataFile = LOCAL\n",
                    c.metaimage
                ),
                &c.bytes,
            );
            let v = load(&p).unwrap();
            assert_eq!(v.voxels, c.want, "{}", c.name);
            assert_same_geometry(&v, &want_geometry);
            for (ext, z) in [("mha", false), ("mhd", true)] {
                let p2 = s.file(&format!("{}-back-{z}.{ext}", c.name));
                write(&p2, &v, z).unwrap();
                let back = load(&p2).unwrap();
                assert_eq!(back.voxels, c.want, "{} written back", c.name);
                assert_same_geometry(&back, &want_geometry);
            }
        }
    }

    #[test]
    fn nan_voxels_are_refused() {
        let s = scratch("nan");
        for (c, bytes) in crate::volume::test_types::nan_cases() {
            let p = s.file(&format!("nan-{}.mha", c.name));
            write_file(
                &p,
                &format!(
                    "{GEOMETRY}ElementType = {}\nElementDataFile = LOCAL\n",
                    c.metaimage
                ),
                &bytes,
            );
            let e = err_of(&p);
            assert!(e.contains("voxel (2,1,1)") && e.contains("NaN"), "{e}");
        }
    }

    #[test]
    fn data_longer_than_the_header_says() {
        let s = scratch("long");
        let vol = sample(Voxels::I16((0..60).collect()));
        // inside the .mha: trailing bytes are ignored
        let p = s.file("trailing.mha");
        write(&p, &vol, false).unwrap();
        let mut b = std::fs::read(&p).unwrap();
        b.extend_from_slice(&[7; 13]);
        std::fs::write(&p, &b).unwrap();
        assert_eq!(load(&p).unwrap().voxels, vol.voxels);
        // a separate raw file with more bytes than DimSize x ElementType: refused
        let p = s.file("long.mhd");
        write(&p, &vol, false).unwrap();
        std::fs::write(s.file("long.raw"), [0u8; 122]).unwrap();
        let e = err_of(&p);
        assert!(
            e.contains("long.raw")
                && e.contains("122 bytes")
                && e.contains("describes 120")
                && e.contains("MET_SHORT"),
            "{e}"
        );
        // a zlib stream cut short
        let p = s.file("cut.mha");
        write(&p, &vol, true).unwrap();
        let b = std::fs::read(&p).unwrap();
        std::fs::write(&p, &b[..b.len() - 20]).unwrap();
        let e = err_of(&p);
        assert!(e.contains("zlib"), "{e}");
    }

    #[test]
    fn hand_written_headers() {
        let s = scratch("hand");
        // Big-endian shorts, Position + Orientation spellings, data at the end (HeaderSize -1).
        let p = s.file("be.mha");
        let data: Vec<u8> = (0..60i16)
            .flat_map(|i| (i * 100 - 3000).to_be_bytes())
            .collect();
        let h = "ObjectType = Image\nNDims = 3\nDimSize = 5 4 3\nElementSize = 0.5 2 3\n\
                 Position = 1 2 3\nOrientation = 0 1 0 -1 0 0 0 0 1\n\
                 AnatomicalOrientation = RAI\nElementByteOrderMSB = True\nHeaderSize = -1\n\
                 ElementType = MET_SHORT\nElementDataFile = LOCAL\n";
        let mut junk = vec![0u8; 7];
        junk.extend_from_slice(&data);
        write_file(&p, h, &junk);
        let v = load(&p).unwrap();
        assert_eq!(
            v.voxels,
            Voxels::I16((0..60).map(|i| i * 100 - 3000).collect())
        );
        assert_eq!(v.spacing, [0.5, 2.0, 3.0]);
        assert_eq!(v.origin, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(v.directions.x_axis, DVec3::new(0.0, 1.0, 0.0));
        assert_eq!(v.directions.y_axis, DVec3::new(-1.0, 0.0, 0.0));
        assert_eq!(v.modality, Modality::Unknown);

        // MET_FLOAT holding integers -> int16; MET_CHAR -> int16; MET_UINT -> uint16
        let p = s.file("f.mha");
        let data: Vec<u8> = (0..60)
            .flat_map(|i| (i as f32 - 20.0).to_le_bytes())
            .collect();
        write_file(
            &p,
            &format!("{GEOMETRY}ElementType = MET_FLOAT\nElementDataFile = LOCAL\n"),
            &data,
        );
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::I16((0..60).map(|i| i - 20).collect())
        );
        let data: Vec<u8> = (0..60).map(|i| (i as i8 - 30) as u8).collect();
        write_file(
            &p,
            &format!("{GEOMETRY}ElementType = MET_CHAR\nElementDataFile = LOCAL\n"),
            &data,
        );
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::I16((0..60).map(|i| i - 30).collect())
        );
        let data: Vec<u8> = (0..60u32).flat_map(|i| (i * 1000).to_le_bytes()).collect();
        write_file(
            &p,
            &format!("{GEOMETRY}ElementType = MET_UINT\nElementDataFile = LOCAL\n"),
            &data,
        );
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::U16((0..60).map(|i| i * 1000).collect())
        );
        // MET_DOUBLE with fractions -> float32
        let data: Vec<u8> = (0..60)
            .flat_map(|i| (i as f64 * 0.1).to_le_bytes())
            .collect();
        write_file(
            &p,
            &format!("{GEOMETRY}ElementType = MET_DOUBLE\nElementDataFile = LOCAL\n"),
            &data,
        );
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::F32((0..60).map(|i| (i as f64 * 0.1) as f32).collect())
        );
    }

    #[test]
    fn bad_inputs() {
        let s = scratch("bad");
        let local = |name: &str, extra: &str, data: &[u8]| {
            let p = s.file(name);
            write_file(
                &p,
                &format!("{GEOMETRY}{extra}ElementDataFile = LOCAL\n"),
                data,
            );
            err_of(&p)
        };
        let short = "ElementType = MET_SHORT\n";
        assert!(local("trunc.mha", short, &[0; 100]).contains("truncated data"));
        assert!(local("type.mha", "ElementType = MET_FLOAT_ARRAY\n", &[]).contains("unsupported"));
        assert!(local("type2.mha", "ElementType = MET_BOGUS\n", &[]).contains("MET_BOGUS"));
        assert!(local("notype.mha", "", &[]).contains("ElementType"));
        assert!(local(
            "ascii.mha",
            "BinaryData = False\nElementType = MET_UCHAR\n",
            &[]
        )
        .contains("ASCII"));
        assert!(local(
            "z.mha",
            "CompressedData = True\nElementType = MET_UCHAR\n",
            &[1, 2, 3]
        )
        .contains("zlib"));
        let p = s.file("huge.mha");
        write_file(&p, "NDims = 3\nDimSize = 100000 100000 100000\nElementType = MET_SHORT\nElementDataFile = LOCAL\n", &[]);
        assert!(err_of(&p).contains("too large"));
        let p = s.file("dims.mha");
        write_file(
            &p,
            "NDims = 2\nDimSize = 4 4\nElementType = MET_SHORT\nElementDataFile = LOCAL\n",
            &[],
        );
        assert!(err_of(&p).contains("NDims 2"));
        let p = s.file("dimsize.mha");
        write_file(
            &p,
            "NDims = 3\nDimSize = 4 4\nElementType = MET_SHORT\nElementDataFile = LOCAL\n",
            &[],
        );
        assert!(err_of(&p).contains("DimSize"));
        let p = s.file("garbage.mha");
        std::fs::write(&p, [0xffu8, 0xfe, 0, 1, 2, b'\n']).unwrap();
        assert!(err_of(&p).contains("not a MetaImage"));
        let p = s.file("noend.mha");
        std::fs::write(&p, "NDims = 3\n").unwrap();
        assert!(err_of(&p).contains("ElementDataFile"));
        let p = s.file("missing.mhd");
        write_file(
            &p,
            &format!("{GEOMETRY}{short}ElementDataFile = gone.raw\n"),
            &[],
        );
        let e = err_of(&p);
        assert!(e.contains("gone.raw"), "{e}");
        let p = s.file("rot.mha");
        write_file(
            &p,
            &format!(
                "{GEOMETRY}TransformMatrix = 1 0 0 1 0 0 0 0 1\n{short}ElementDataFile = LOCAL\n"
            ),
            &[0; 120],
        );
        assert!(err_of(&p).contains("degenerate"));
        assert!(err_of(&s.file("nope.mha")).contains("nope.mha"));
        // a truncated detached data file names both files
        let vol = sample(Voxels::I16(vec![3; 60]));
        let p = s.file("det.mhd");
        write(&p, &vol, false).unwrap();
        std::fs::write(s.file("det.raw"), [0u8; 10]).unwrap();
        let e = err_of(&p);
        assert!(e.contains("det.raw") && e.contains("truncated"), "{e}");
        // mangled headers never panic
        let p = s.file("m.mha");
        write(&p, &vol, true).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 0x5a;
            std::fs::write(&p, &b).unwrap();
            let _ = load(&p);
        }
    }
}
