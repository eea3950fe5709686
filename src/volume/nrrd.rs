//! NRRD reader and writer (teem's "nearly raw raster data", magic NRRD0001..NRRD0005).
//!
//! Reads 3-D scalar volumes of 8-, 16- and 32-bit integers, float and double, attached
//! (`.nrrd`) or detached (`.nhdr` + `data file:`), raw or gzip encoded, with `space
//! directions`/`spacings`, and converts the geometry into LPS; and one volume of a 4-D series
//! whose last axis is not spatial. Writes NRRD0004 in LPS, raw or gzip.

use super::data_source::{self, DataSource, Described, Skip};
use super::{
    checked_size, pick_frame, read_wide, Grid, Modality, Volume, VolumeError, Voxels, WideSamples,
    WideType,
};
use flate2::read::MultiGzDecoder;
use flate2::write::GzEncoder;
use flate2::Compression;
use glam::{DMat3, DVec3};
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, Write};
use std::path::Path;

/// Longest accepted header (a malformed file must not make us read gigabytes of "lines").
const MAX_HEADER_BYTES: u64 = 1 << 20;
/// Key of the modality key/value pair written by [`write`] (`modality:=CT`).
const MODALITY_KEY: &str = "modality";

/// Maps every NRRD spelling of a supported type; `Err` carries the kind of type for the message.
fn parse_type(s: &str) -> Result<WideType, &'static str> {
    let s = s.trim().to_ascii_lowercase();
    let s = s.split_whitespace().collect::<Vec<_>>().join(" ");
    Ok(match s.as_str() {
        "signed char" | "int8" | "int8_t" | "char" => WideType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => WideType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            WideType::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => WideType::U16,
        "int" | "signed int" | "int32" | "int32_t" => WideType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => WideType::U32,
        "float" => WideType::F32,
        "double" => WideType::F64,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t"
        | "ulonglong"
        | "unsigned long long"
        | "unsigned long long int"
        | "uint64"
        | "uint64_t" => return Err("64-bit integer"),
        "block" => return Err("block"),
        _ => return Err("unknown"),
    })
}

/// How the `space` field maps its axes onto LPS (a sign per x/y/z axis).
fn space_signs(path: &Path, space: &str) -> Result<[f64; 3], VolumeError> {
    Ok(match space.trim().to_ascii_lowercase().as_str() {
        "left-posterior-superior" | "lps" => [1.0, 1.0, 1.0],
        "right-anterior-superior" | "ras" => [-1.0, -1.0, 1.0],
        "left-anterior-superior" | "las" => [1.0, -1.0, 1.0],
        // Scanner coordinates are DICOM's patient LPS; the generic 3-D spaces are taken as is.
        "scanner-xyz" | "3d-right-handed" | "3d-left-handed" => [1.0, 1.0, 1.0],
        s @ ("right-anterior-superior-time"
        | "left-anterior-superior-time"
        | "left-posterior-superior-time"
        | "scanner-xyz-time"
        | "3d-right-handed-time"
        | "3d-left-handed-time") => {
            return Err(VolumeError::unsupported(
                path,
                format!("space {s:?} (time-varying spaces are not supported)"),
            ))
        }
        s => return Err(VolumeError::format(path, format!("unknown space {s:?}"))),
    })
}

/// Parses a vector like `(0.9,0,0)`; `None` when malformed.
fn parse_vector(s: &str) -> Option<DVec3> {
    let inner = s.trim().strip_prefix('(')?.strip_suffix(')')?;
    let parts: Vec<f64> = inner
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .ok()?;
    if parts.len() != 3 || parts.iter().any(|v| !v.is_finite()) {
        return None;
    }
    Some(DVec3::new(parts[0], parts[1], parts[2]))
}

/// Splits `(a,b,c) (d,e,f) none` into its items (a parenthesised vector or a bare word).
fn split_vectors(s: &str) -> Option<Vec<String>> {
    let mut out = Vec::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        if rest.starts_with('(') {
            let end = rest.find(')')?;
            out.push(rest[..=end].to_string());
            rest = rest[end + 1..].trim_start();
        } else {
            let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
            out.push(rest[..end].to_string());
            rest = rest[end..].trim_start();
        }
    }
    Some(out)
}

/// How a file's volumes lie: one (3-D data), a series along the last axis, or components
/// interleaved along the first (a 3D Slicer segmentation's layers, a vector per voxel).
#[derive(Clone, Copy, PartialEq)]
enum Layout {
    One,
    Series,
    Interleaved,
}

/// The volume to read of a file with `sizes`, how many it holds and how they lie: (0, 1, One)
/// for 3-D data; 4-D data has one non-spatial axis (a `none` space direction or a non-spatial
/// kind), the last (a series) or the first (interleaved components), and several need `frame`.
fn series_frame(
    path: &Path,
    h: &Header,
    sizes: &[u64],
    frame: Option<u64>,
) -> Result<(u64, u64, Layout), VolumeError> {
    if sizes.len() == 3 {
        return Ok((0, 1, Layout::One));
    }
    // which axes are spatial: from the space directions, else the kinds
    let spatial: Vec<bool> = if let Some(sd) = &h.space_directions {
        split_vectors(sd)
            .unwrap_or_default()
            .iter()
            .map(|v| v != "none")
            .collect()
    } else if let Some(k) = &h.kinds {
        k.split_whitespace()
            .map(|k| matches!(k.to_ascii_lowercase().as_str(), "domain" | "space"))
            .collect()
    } else {
        vec![true, true, true, false] // nothing says otherwise: the last axis is the series
    };
    if spatial.len() != 4 || spatial.iter().filter(|&&s| s).count() != 3 {
        return Err(VolumeError::unsupported(
            path,
            "4-D data with other than three spatial axes",
        ));
    }
    let (layout, list) = match spatial.iter().position(|&s| !s) {
        Some(3) => (Layout::Series, 3),
        Some(0) => (Layout::Interleaved, 0),
        _ => {
            return Err(VolumeError::unsupported(
                path,
                "4-D data whose non-spatial axis is in the middle; only a series (the last \
                 axis) or interleaved components (the first) are read",
            ))
        }
    };
    let frames = sizes[list];
    if frames == 0 {
        return Err(VolumeError::format(
            path,
            "sizes: the series axis has size 0",
        ));
    }
    let d = spatial_axes(layout).map(|a| sizes[a]);
    let frame = pick_frame(path, frames, d, frame)?;
    Ok((frame, frames, layout))
}

/// The spatial axes of a file laid out as `layout`.
fn spatial_axes(layout: Layout) -> [usize; 3] {
    match layout {
        Layout::Interleaved => [1, 2, 3],
        Layout::One | Layout::Series => [0, 1, 2],
    }
}

/// The fields of a header that matter here, as written.
#[derive(Default)]
struct Header {
    ty: Option<String>,
    dimension: Option<String>,
    sizes: Option<String>,
    endian: Option<String>,
    encoding: Option<String>,
    space: Option<String>,
    space_dimension: Option<String>,
    space_directions: Option<String>,
    spacings: Option<String>,
    space_origin: Option<String>,
    byte_skip: Option<String>,
    line_skip: Option<String>,
    data_file: Option<String>,
    kinds: Option<String>,
    modality: Option<String>,
}

/// Reads the header lines up to the first empty line (or end of file). Returns the header and
/// whether it was terminated by an empty line (data may follow).
fn read_header<R: BufRead>(path: &Path, r: &mut R) -> Result<(Header, bool), VolumeError> {
    let mut h = Header::default();
    let mut line = Vec::new();
    let mut total = 0u64;
    let mut first = true;
    loop {
        line.clear();
        let n = (&mut *r)
            .take(MAX_HEADER_BYTES + 1 - total.min(MAX_HEADER_BYTES))
            .read_until(b'\n', &mut line)
            .map_err(|e| VolumeError::io(path, e))?;
        total += n as u64;
        if n == 0 {
            if first {
                return Err(VolumeError::format(
                    path,
                    "empty file, not a NRRD (no NRRD000x magic)",
                ));
            }
            return Ok((h, false));
        }
        if total > MAX_HEADER_BYTES {
            return Err(VolumeError::format(
                path,
                format!("header longer than {MAX_HEADER_BYTES} bytes without an empty line"),
            ));
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_end_matches(['\n', '\r']);
        if first {
            first = false;
            let ok = text.len() == 8
                && text.starts_with("NRRD000")
                && matches!(text.as_bytes()[7], b'1'..=b'5');
            if !ok {
                return Err(VolumeError::format(
                    path,
                    "not a NRRD file: missing NRRD0001..NRRD0005 magic on the first line",
                ));
            }
            continue;
        }
        if text.trim().is_empty() {
            return Ok((h, true));
        }
        if text.starts_with('#') {
            continue;
        }
        // A key/value pair `key:=value` (keys may hold single colons), unless a field's
        // `: ` comes first.
        let kv = text
            .find(":=")
            .filter(|&p| text.find(": ").is_none_or(|f| p < f));
        if let Some(p) = kv {
            let key = text[..p].trim().to_ascii_lowercase();
            if key == MODALITY_KEY || key == "cao-xr modality" {
                h.modality = Some(text[p + 2..].trim().to_string());
            }
            continue;
        }
        let Some(colon) = text.find(':') else {
            return Err(VolumeError::format(
                path,
                format!("header line {text:?} is neither a field nor a key/value pair"),
            ));
        };
        let (name, rest) = (text[..colon].trim(), &text[colon + 1..]);
        let value = Some(rest.trim().to_string());
        match name.to_ascii_lowercase().as_str() {
            "type" => h.ty = value,
            "dimension" => h.dimension = value,
            "sizes" => h.sizes = value,
            "endian" => h.endian = value,
            "encoding" => h.encoding = value,
            "space" => h.space = value,
            "space dimension" => h.space_dimension = value,
            "space directions" => h.space_directions = value,
            "spacings" => h.spacings = value,
            "space origin" => h.space_origin = value,
            "byte skip" | "byteskip" => h.byte_skip = value,
            "line skip" | "lineskip" => h.line_skip = value,
            "data file" | "datafile" => {
                // `data file: LIST` ends the header; the file names follow, one per line.
                let list = rest.split_whitespace().next() == Some("LIST");
                h.data_file = value;
                if list {
                    return Ok((h, false));
                }
            }
            "cao-xr modality" => h.modality = value,
            "kinds" => h.kinds = value,
            // content, centers, units, min/max, measurement frame, ...: not needed.
            _ => {}
        }
    }
}

/// The shortest voxel spacing a space direction may give (mm).
const MIN_SPACING_MM: f64 = 1e-6;

/// Loads a 3-D NRRD (`.nrrd` with attached data or `.nhdr` with a detached data file).
pub fn load(path: &Path) -> Result<Volume, VolumeError> {
    load_frame(path, None)
}

/// Every volume of a file: the one of 3-D data, each of a series, or each interleaved component
/// (a 3D Slicer segmentation's layers), in order.
pub fn load_all(path: &Path) -> Result<Vec<Volume>, VolumeError> {
    let file = File::open(path).map_err(|e| VolumeError::io(path, e))?;
    let (h, _) = read_header(path, &mut BufReader::new(file))?;
    let sizes: Vec<u64> = h
        .sizes
        .as_deref()
        .unwrap_or_default()
        .split_whitespace()
        .filter_map(|s| s.parse().ok())
        .collect();
    // A header load_frame refuses is refused there, with its reason.
    let count = match series_frame(path, &h, &sizes, Some(0)) {
        Ok((_, n, _)) if sizes.len() == 4 => n,
        _ => 1,
    };
    (0..count).map(|t| load_frame(path, Some(t))).collect()
}

/// Loads volume `frame` (0-based) of a 4-D NRRD whose last axis is a series (time, phases,
/// echoes: a `none` space direction, or a non-spatial kind); `None` wants a 3-D file (or a
/// series of one) and names the choice otherwise.
pub fn load_frame(path: &Path, frame: Option<u64>) -> Result<Volume, VolumeError> {
    let file = File::open(path).map_err(|e| VolumeError::io(path, e))?;
    let mut reader = BufReader::new(file);
    let (h, terminated) = read_header(path, &mut reader)?;
    let shape = parse_shape(path, &h, frame)?;
    let encoding = parse_encoding(path, &h, &shape)?;
    let geometry = parse_geometry(path, &h, &shape)?;
    let modality = match h.modality.as_deref().map(str::trim) {
        Some(m) if m.eq_ignore_ascii_case("ct") => Modality::Ct,
        Some(m) if m.eq_ignore_ascii_case("mr") || m.eq_ignore_ascii_case("mri") => Modality::Mr,
        _ => Modality::Unknown,
    };
    let (line_skip, byte_skip) = parse_skips(path, &h, encoding.gzip)?;
    let (source, data) = open_source(path, &h, reader, terminated)?;
    let voxels = read_payload(&source, data, &shape, &encoding, line_skip, byte_skip)?;
    let volume = data_source::loaded_volume(path, shape.dims, geometry, modality, voxels);
    Ok(volume)
}

/// The samples a header describes and the volume to read of them.
struct Shape {
    ty: WideType,
    /// The type as written (for messages).
    ty_s: String,
    dim: u64,
    sizes: Vec<u64>,
    /// The volume to read, of `frames` laid out as `layout`.
    frame: u64,
    frames: u64,
    layout: Layout,
    /// Sizes of the spatial axes.
    dims: [u64; 3],
    /// Bytes of one volume.
    data_bytes: u64,
    /// Bytes of every volume (each must be in the file).
    total_bytes: u64,
}

/// A required header field's value, or the error naming it.
fn required(path: &Path, v: &Option<String>, name: &str) -> Result<String, VolumeError> {
    v.clone()
        .ok_or_else(|| VolumeError::format(path, format!("missing required field `{name}`")))
}

/// Step 1: `type`, `dimension` and `sizes`, the series axis and the volume `frame` picks.
fn parse_shape(path: &Path, h: &Header, frame: Option<u64>) -> Result<Shape, VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let ty_s = required(path, &h.ty, "type")?;
    let ty = parse_type(&ty_s).map_err(|kind| {
        VolumeError::unsupported(
            path,
            format!(
                "sample type {ty_s:?} ({kind}); supported are 8-, 16- and 32-bit integers, \
                 float and double"
            ),
        )
    })?;
    let dim_s = required(path, &h.dimension, "dimension")?;
    let dim: u64 = dim_s
        .parse()
        .map_err(|_| fmt(format!("invalid dimension {dim_s:?}")))?;
    if dim != 3 && dim != 4 {
        return Err(VolumeError::unsupported(
            path,
            format!("dimension {dim}: only 3-dimensional volumes and 4-D series are supported"),
        ));
    }
    let sizes_s = required(path, &h.sizes, "sizes")?;
    let sizes: Vec<u64> = sizes_s
        .split_whitespace()
        .map(|s| s.parse::<u64>())
        .collect::<Result<_, _>>()
        .map_err(|_| fmt(format!("invalid sizes {sizes_s:?}")))?;
    if sizes.len() as u64 != dim {
        return Err(fmt(format!(
            "sizes {sizes_s:?} must have {dim} entries (dimension {dim})"
        )));
    }
    let (frame, frames, layout) = series_frame(path, h, &sizes, frame)?;
    let dims = spatial_axes(layout).map(|a| sizes[a]);
    let (_, data_bytes) = checked_size(path, dims, ty.bytes())?;
    // every volume of a series is checked to be in the file; the chosen one is read
    let total_bytes = data_source::series_bytes(path, frames, data_bytes)?;
    Ok(Shape {
        ty,
        ty_s,
        dim,
        sizes,
        frame,
        frames,
        layout,
        dims,
        data_bytes,
        total_bytes,
    })
}

/// How the samples are stored.
struct Encoding {
    gzip: bool,
    big_endian: bool,
}

/// Step 2: `encoding` and `endian` (required for samples wider than a byte).
fn parse_encoding(path: &Path, h: &Header, shape: &Shape) -> Result<Encoding, VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let enc_s = required(path, &h.encoding, "encoding")?;
    let gzip = match enc_s.to_ascii_lowercase().as_str() {
        "raw" => false,
        "gzip" | "gz" => true,
        "bzip2" | "bz2" | "ascii" | "text" | "txt" | "hex" | "zrl" => {
            return Err(VolumeError::unsupported(
                path,
                format!("encoding {enc_s:?} (only raw and gzip are supported)"),
            ))
        }
        _ => return Err(fmt(format!("unknown encoding {enc_s:?}"))),
    };
    let big_endian = match h.endian.as_deref().map(str::to_ascii_lowercase).as_deref() {
        Some("little") => false,
        Some("big") => true,
        Some(other) => return Err(fmt(format!("invalid endian {other:?} (little or big)"))),
        None if shape.ty.bytes() > 1 => {
            return Err(fmt(format!(
                "missing required field `endian` for type {:?}",
                shape.ty_s
            )))
        }
        None => false,
    };
    Ok(Encoding { gzip, big_endian })
}

/// Step 3: the geometry in LPS, (spacing, directions, origin), from `space`, `space
/// dimension`, `space directions` (else `spacings`) and `space origin`.
fn parse_geometry(
    path: &Path,
    h: &Header,
    shape: &Shape,
) -> Result<([f64; 3], DMat3, DVec3), VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let signs = match &h.space {
        Some(s) => space_signs(path, s)?,
        None => [1.0; 3],
    };
    if let Some(sd) = &h.space_dimension {
        if sd.trim() != "3" {
            return Err(VolumeError::unsupported(
                path,
                format!("space dimension {sd:?} (only 3 is supported)"),
            ));
        }
    }
    let flip = DVec3::from_array(signs);
    let (spacing, directions) = if let Some(sd) = &h.space_directions {
        space_directions(path, sd, shape, flip)?
    } else if let Some(sp) = &h.spacings {
        (spacings(path, sp, shape)?, DMat3::IDENTITY)
    } else {
        ([1.0; 3], DMat3::IDENTITY)
    };
    let origin = match &h.space_origin {
        Some(o) => {
            parse_vector(o).ok_or_else(|| fmt(format!("invalid space origin {o:?}")))? * flip
        }
        None => DVec3::ZERO,
    };
    Ok((spacing, directions, origin))
}

/// The spacing and unit directions of `space directions` `sd` (a vector per spatial axis,
/// `none` for the series or component axis), flipped into LPS by `flip`.
fn space_directions(
    path: &Path,
    sd: &str,
    shape: &Shape,
    flip: DVec3,
) -> Result<([f64; 3], DMat3), VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let items = split_vectors(sd)
        .filter(|v| {
            v.len() as u64 == shape.dim
                && match shape.layout {
                    Layout::One => true,
                    Layout::Series => v[3] == "none",
                    Layout::Interleaved => v[0] == "none",
                }
        })
        .ok_or_else(|| {
            fmt(format!(
                "space directions {sd:?} must be three vectors (and `none` for a series or \
                 component axis)"
            ))
        })?;
    let mut spacing = [1.0f64; 3];
    let mut cols = [DVec3::ZERO; 3];
    let axes = spatial_axes(shape.layout);
    for (a, item) in axes.iter().map(|&i| &items[i]).enumerate() {
        let v = parse_vector(item).ok_or_else(|| {
            fmt(format!(
                "space directions: axis {a} has {item:?}, expected (x,y,z)"
            ))
        })?;
        let len = v.length();
        // A vector a millionth of a millimetre long is no voxel spacing: refused like zero.
        if !len.is_finite() || len < MIN_SPACING_MM {
            return Err(fmt(format!(
                "space directions: axis {a} has a zero (or near-zero, {len:e} mm) vector"
            )));
        }
        spacing[a] = len;
        cols[a] = v / len * flip;
    }
    let directions = DMat3::from_cols(cols[0], cols[1], cols[2]);
    if directions.determinant().abs() < 1e-6 {
        return Err(fmt(format!(
            "space directions {sd:?} are degenerate (not independent)"
        )));
    }
    Ok((spacing, directions))
}

/// The voxel spacing of `spacings` `sp` (`nan` for an axis keeps 1 mm).
fn spacings(path: &Path, sp: &str, shape: &Shape) -> Result<[f64; 3], VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let vals: Vec<f64> = sp
        .split_whitespace()
        .map(|s| s.parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| fmt(format!("invalid spacings {sp:?}")))?;
    if vals.len() as u64 != shape.dim {
        return Err(fmt(format!(
            "spacings {sp:?} must have {} entries",
            shape.dim
        )));
    }
    let mut spacing = [1.0f64; 3];
    for (a, v) in spatial_axes(shape.layout)
        .iter()
        .map(|&i| vals[i])
        .enumerate()
    {
        if v.is_nan() {
            continue; // "nan": no spacing known, keep 1 mm
        }
        if !(v.is_finite() && v != 0.0) {
            return Err(fmt(format!("spacings: axis {a} has invalid spacing {v}")));
        }
        spacing[a] = v.abs();
    }
    Ok(spacing)
}

/// Step 4: `line skip` and `byte skip` (-1: the data are the file's last bytes, raw only).
fn parse_skips(path: &Path, h: &Header, gzip: bool) -> Result<(u64, Skip), VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let line_skip: u64 = match &h.line_skip {
        Some(s) => s
            .parse()
            .map_err(|_| fmt(format!("invalid line skip {s:?}")))?,
        None => 0,
    };
    let byte_skip: i64 = match &h.byte_skip {
        Some(s) => s
            .parse()
            .map_err(|_| fmt(format!("invalid byte skip {s:?}")))?,
        None => 0,
    };
    if byte_skip < -1 {
        return Err(fmt(format!(
            "invalid byte skip {byte_skip} (must be >= -1)"
        )));
    }
    if byte_skip == -1 && gzip {
        return Err(VolumeError::unsupported(
            path,
            "byte skip -1 with gzip encoding",
        ));
    }
    if gzip && byte_skip as u64 > super::MAX_DATA_BYTES {
        return Err(fmt(format!("byte skip {byte_skip} is too large")));
    }
    let skip = match byte_skip {
        -1 => Skip::Tail,
        b => Skip::Bytes(b as u64),
    };
    Ok((line_skip, skip))
}

/// Step 5: the file holding the samples: the detached `data file`, or the header's own
/// remainder (which needs the empty line that ends the header).
fn open_source(
    path: &Path,
    h: &Header,
    reader: BufReader<File>,
    terminated: bool,
) -> Result<(DataSource, BufReader<File>), VolumeError> {
    match &h.data_file {
        Some(df) => DataSource::detached(path, "data file:", df),
        None if !terminated => Err(VolumeError::format(
            path,
            "header ends without an empty line and no `data file`; no data follows",
        )),
        None => Ok((DataSource::attached(path), reader)),
    }
}

/// Step 6: skips the lines and bytes before the samples and reads the chosen volume (of a
/// series: every volume must be in the file; of interleaved components: the one picked out).
fn read_payload(
    source: &DataSource,
    mut data: BufReader<File>,
    shape: &Shape,
    encoding: &Encoding,
    line_skip: u64,
    byte_skip: Skip,
) -> Result<Voxels, VolumeError> {
    let mut line = Vec::new();
    for n in 0..line_skip {
        line.clear();
        let got = (&mut data)
            .take(1 << 20)
            .read_until(b'\n', &mut line)
            .map_err(|e| source.io_error(e))?;
        if got == 0 {
            return Err(source.error(format_args!(
                "end of file while skipping line {} of {line_skip}",
                n + 1
            )));
        }
    }
    // A series' volume lies whole after the ones before it; interleaved components are read
    // together (as one volume `frames` times wider) and the one asked for picked out.
    let (frame, frames, dims) = (shape.frame, shape.frames, shape.dims);
    let (frame_skip, read_dims) = match shape.layout {
        Layout::Interleaved => (0, [dims[0] * frames, dims[1], dims[2]]),
        Layout::One | Layout::Series => (
            data_source::frame_offset(source.header(), 0, frame, shape.data_bytes)?,
            dims,
        ),
    };
    let read_bytes = read_dims.iter().product::<u64>() * shape.ty.bytes();
    let read_dims = read_dims.map(|d| d as usize);
    let codec = if encoding.gzip { "gzip " } else { "" };
    let what = source.what(codec);
    let header = source.header();
    let samples = WideSamples {
        ty: shape.ty,
        dims: read_dims,
        big_endian: encoding.big_endian,
        scale: None,
    };
    let voxels = if encoding.gzip {
        let mut dec = MultiGzDecoder::new(data);
        let skip = match byte_skip {
            Skip::Bytes(b) => b + frame_skip,
            Skip::Tail => frame_skip, // refused with gzip by parse_skips
        };
        source.skip_decoded(&mut dec, codec, skip, read_bytes)?;
        read_wide(header, &what, &mut dec, samples, false)?
    } else {
        let pos = data.stream_position().map_err(|e| source.io_error(e))?;
        let described = Described {
            shape: format!(
                "{} {}",
                shape
                    .sizes
                    .iter()
                    .map(u64::to_string)
                    .collect::<Vec<_>>()
                    .join(" x "),
                shape.ty_s
            ),
            fields: "sizes or type",
        };
        let start = source.locate_raw(&data, pos, byte_skip, shape.total_bytes, &described)?;
        source.seek(&mut data, start + frame_skip)?;
        read_wide(header, &what, &mut data, samples, true)?
    };
    Ok(match shape.layout {
        Layout::Interleaved => voxels.strided(frame as usize, frames as usize),
        Layout::One | Layout::Series => voxels,
    })
}

/// Samples to write.
#[derive(Clone, Copy, Debug)]
pub enum NrrdData<'a> {
    U8(&'a [u8]),
    U16(&'a [u16]),
    I16(&'a [i16]),
    F32(&'a [f32]),
}

impl NrrdData<'_> {
    fn len(&self) -> usize {
        match self {
            NrrdData::U8(v) => v.len(),
            NrrdData::U16(v) => v.len(),
            NrrdData::I16(v) => v.len(),
            NrrdData::F32(v) => v.len(),
        }
    }
    fn type_name(&self) -> &'static str {
        match self {
            NrrdData::U8(_) => "uint8",
            NrrdData::U16(_) => "uint16",
            NrrdData::I16(_) => "int16",
            NrrdData::F32(_) => "float",
        }
    }
    /// Writes the samples little-endian, in chunks.
    fn write_le(&self, w: &mut dyn Write) -> std::io::Result<()> {
        const CHUNK: usize = 1 << 16;
        fn chunks<T: Copy, const N: usize>(
            v: &[T],
            w: &mut dyn Write,
            f: fn(T) -> [u8; N],
        ) -> std::io::Result<()> {
            let mut buf = Vec::with_capacity(CHUNK * N);
            for c in v.chunks(CHUNK) {
                buf.clear();
                for &x in c {
                    buf.extend_from_slice(&f(x));
                }
                w.write_all(&buf)?;
            }
            Ok(())
        }
        match self {
            NrrdData::U8(v) => w.write_all(v),
            NrrdData::U16(v) => chunks(v, w, u16::to_le_bytes),
            NrrdData::I16(v) => chunks(v, w, i16::to_le_bytes),
            NrrdData::F32(v) => chunks(v, w, f32::to_le_bytes),
        }
    }
}

fn fmt_vec(v: DVec3) -> String {
    // `+ 0.0` turns -0 into 0.
    format!("({},{},{})", v.x + 0.0, v.y + 0.0, v.z + 0.0)
}

/// Writes a 3-D NRRD0004 file in LPS space on `grid`: `directions` columns are the unit vectors
/// of the i, j, k axes, `spacing` their lengths (mm), `origin` the centre of voxel (0,0,0).
/// The file is written next to `path` under a temporary name and renamed when complete.
pub fn write(path: &Path, grid: &Grid, data: NrrdData, gzip: bool) -> Result<(), VolumeError> {
    write_components(path, 1, grid, data, gzip)
}

/// [`write()`] for an RGB volume: `data` holds r, g, b per voxel (x fastest after the colour),
/// written as a 4-D NRRD whose first axis is "RGB-color" (as Slicer and teem read it).
pub fn write_rgb(path: &Path, grid: &Grid, data: &[f32]) -> Result<(), VolumeError> {
    let dims = grid.dims;
    let vol = [dims[0] * 3, dims[1], dims[2]];
    if data.len() != vol.iter().product::<usize>() {
        return Err(VolumeError::format(
            path,
            format!(
                "cannot write: {} samples are not RGB of {dims:?}",
                data.len()
            ),
        ));
    }
    write_components(path, 3, grid, NrrdData::F32(data), false)
}

fn write_components(
    path: &Path,
    components: usize,
    grid: &Grid,
    data: NrrdData,
    gzip: bool,
) -> Result<(), VolumeError> {
    let Grid {
        dims,
        spacing,
        directions,
        origin,
        modality,
    } = *grid;
    let expected = dims.iter().try_fold(components, |a, &d| a.checked_mul(d));
    if dims.contains(&0) || expected != Some(data.len()) {
        return Err(VolumeError::format(
            path,
            format!(
                "cannot write: sizes {} x {} x {} do not match {} samples",
                dims[0],
                dims[1],
                dims[2],
                data.len()
            ),
        ));
    }
    if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(VolumeError::format(
            path,
            format!("cannot write: invalid spacing {spacing:?}"),
        ));
    }
    let cols = [directions.x_axis, directions.y_axis, directions.z_axis];
    if cols.iter().any(|c| !c.is_finite() || c.length() < 1e-6) || !origin.is_finite() {
        return Err(VolumeError::format(
            path,
            "cannot write: directions or origin are not finite / zero",
        ));
    }

    let mut header = String::from("NRRD0004\n");
    header.push_str("# Complete NRRD file format specification at:\n");
    header.push_str("# http://teem.sourceforge.net/nrrd/format.html\n");
    header.push_str(&format!("type: {}\n", data.type_name()));
    let (dimension, size, direction, kind) = match components {
        1 => ("3", String::new(), "", ""),
        c => ("4", format!("{c} "), "none ", "RGB-color "),
    };
    header.push_str(&format!("dimension: {dimension}\n"));
    header.push_str("space: left-posterior-superior\n");
    header.push_str(&format!(
        "sizes: {size}{} {} {}\n",
        dims[0], dims[1], dims[2]
    ));
    header.push_str(&format!(
        "space directions: {direction}{} {} {}\n",
        fmt_vec(cols[0] * spacing[0]),
        fmt_vec(cols[1] * spacing[1]),
        fmt_vec(cols[2] * spacing[2])
    ));
    header.push_str(&format!("kinds: {kind}domain domain domain\n"));
    header.push_str("endian: little\n");
    header.push_str(&format!(
        "encoding: {}\n",
        if gzip { "gzip" } else { "raw" }
    ));
    header.push_str(&format!("space origin: {}\n", fmt_vec(origin)));
    match modality {
        Modality::Ct => header.push_str(&format!("{MODALITY_KEY}:=CT\n")),
        Modality::Mr => header.push_str(&format!("{MODALITY_KEY}:=MR\n")),
        Modality::Unknown => {}
    }
    header.push('\n');

    super::write_atomically(path, |w| {
        w.write_all(header.as_bytes())?;
        if gzip {
            let mut enc = GzEncoder::new(w, Compression::default());
            data.write_le(&mut enc)?;
            enc.finish()?;
            Ok(())
        } else {
            data.write_le(w)
        }
    })
}

/// Writes `vol` with [`write()`].
pub fn write_volume(path: &Path, vol: &Volume, gzip: bool) -> Result<(), VolumeError> {
    let data = match &vol.voxels {
        Voxels::U8(v) => NrrdData::U8(v),
        Voxels::U16(v) => NrrdData::U16(v),
        Voxels::I16(v) => NrrdData::I16(v),
        Voxels::F32(v) => NrrdData::F32(v),
    };
    write(path, &vol.grid(), data, gzip)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unique scratch directory for this module's tests, removed on drop.
    fn scratch(tag: &str) -> crate::volume::test_scratch::Scratch {
        crate::volume::test_scratch::Scratch::new(&format!("nrrd-{tag}"))
    }

    fn rotation() -> DMat3 {
        DMat3::from_rotation_z(0.3) * DMat3::from_rotation_x(-0.7)
    }

    fn assert_geometry(v: &Volume, dims: [usize; 3], spacing: [f64; 3], dirs: DMat3, o: DVec3) {
        assert_eq!(v.dims, dims);
        for a in 0..3 {
            assert!(
                (v.spacing[a] - spacing[a]).abs() < 1e-9,
                "{:?} {:?}",
                v.spacing,
                spacing
            );
        }
        assert!(
            v.directions.abs_diff_eq(dirs, 1e-9),
            "{:?} vs {:?}",
            v.directions,
            dirs
        );
        assert!(v.origin.abs_diff_eq(o, 1e-9), "{:?} vs {:?}", v.origin, o);
    }

    fn write_file(path: &Path, header: &str, data: &[u8]) {
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend_from_slice(data);
        std::fs::write(path, bytes).unwrap();
    }

    fn err_of(path: &Path) -> String {
        let e = load(path).expect_err("load should fail").to_string();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(e.contains(&name), "error {e:?} does not name {name}");
        e
    }

    #[test]
    fn round_trip_all_types() {
        let s = scratch("rt");
        let dims = [5, 4, 3];
        let n = 60;
        let spacing = [0.7, 1.25, 3.0];
        let dirs = rotation();
        let origin = DVec3::new(-12.5, 30.25, 7.0);
        let u8s: Vec<u8> = (0..n).map(|i| (i * 37 % 256) as u8).collect();
        let u16s: Vec<u16> = (0..n).map(|i| (i * 1103 % 65536) as u16).collect();
        let i16s: Vec<i16> = (0..n).map(|i| (i * 977 - 30000) as i16).collect();
        for gzip in [false, true] {
            let cases = [
                (
                    NrrdData::U8(&u8s),
                    Voxels::U8(u8s.clone()),
                    Modality::Unknown,
                ),
                (
                    NrrdData::U16(&u16s),
                    Voxels::U16(u16s.clone()),
                    Modality::Mr,
                ),
                (
                    NrrdData::I16(&i16s),
                    Voxels::I16(i16s.clone()),
                    Modality::Ct,
                ),
            ];
            for (data, want, modality) in cases {
                let p = s.file(&format!("v-{}-{gzip}.nrrd", want.type_name()));
                let grid = Grid {
                    dims,
                    spacing,
                    directions: dirs,
                    origin,
                    modality,
                };
                write(&p, &grid, data, gzip).unwrap();
                let v = load(&p).unwrap();
                assert_geometry(&v, dims, spacing, dirs, origin);
                assert_eq!(v.voxels, want);
                assert_eq!(v.modality, modality);
                // write_volume reproduces the same file
                let p2 = s.file(&format!("w-{}-{gzip}.nrrd", want.type_name()));
                write_volume(&p2, &v, gzip).unwrap();
                let v2 = load(&p2).unwrap();
                assert_geometry(&v2, dims, spacing, dirs, origin);
                assert_eq!(v2.voxels, want);
            }
        }
        // No temporary files left behind.
        let names: Vec<_> = std::fs::read_dir(&s.0)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert!(
            names.iter().all(|n| !n.to_string_lossy().starts_with('.')),
            "{names:?}"
        );
    }

    #[test]
    fn f32_header_and_payload() {
        let s = scratch("f32");
        let dims = [3, 2, 2];
        let vals: Vec<f32> = (0..12).map(|i| i as f32 * 0.5 - 2.0).collect();
        let dirs = DMat3::from_cols(-DVec3::X, DVec3::Z, DVec3::Y);
        for gzip in [false, true] {
            let p = s.file(&format!("f-{gzip}.nrrd"));
            write(
                &p,
                &Grid {
                    dims,
                    spacing: [0.5, 2.0, 1.5],
                    directions: dirs,
                    origin: DVec3::ZERO,
                    modality: Modality::Ct,
                },
                NrrdData::F32(&vals),
                gzip,
            )
            .unwrap();
            let bytes = std::fs::read(&p).unwrap();
            let end = bytes.windows(2).position(|w| w == b"\n\n").unwrap() + 2;
            let header = std::str::from_utf8(&bytes[..end]).unwrap();
            assert!(header.starts_with("NRRD0004\n"));
            for line in [
                "type: float\n",
                "dimension: 3\n",
                "space: left-posterior-superior\n",
                "sizes: 3 2 2\n",
                "space directions: (-0.5,0,0) (0,0,2) (0,1.5,0)\n",
                "kinds: domain domain domain\n",
                "endian: little\n",
                "space origin: (0,0,0)\n",
                "modality:=CT\n",
            ] {
                assert!(header.contains(line), "{line:?} missing in {header}");
            }
            assert!(header.contains(if gzip {
                "encoding: gzip\n"
            } else {
                "encoding: raw\n"
            }));
            let mut payload = bytes[end..].to_vec();
            if gzip {
                let mut out = Vec::new();
                MultiGzDecoder::new(&payload[..])
                    .read_to_end(&mut out)
                    .unwrap();
                payload = out;
            }
            let back: Vec<f32> = payload
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                .collect();
            assert_eq!(back, vals);
            assert_eq!(load(&p).unwrap().voxels, Voxels::F32(vals.clone()));
        }
    }

    #[test]
    fn write_refuses_mismatched_data() {
        let s = scratch("mismatch");
        let p = s.file("bad.nrrd");
        let e = write(
            &p,
            &Grid {
                dims: [2, 2, 2],
                spacing: [1.0; 3],
                directions: DMat3::IDENTITY,
                origin: DVec3::ZERO,
                modality: Modality::Ct,
            },
            NrrdData::U8(&[1, 2, 3]),
            false,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("bad.nrrd") && e.contains("3 samples"), "{e}");
        assert!(!p.exists());
    }

    #[test]
    fn near_zero_space_directions_are_refused_like_zero_ones() {
        let s = scratch("tiny");
        for (name, dir) in [("zero", "(0,0,0)"), ("tiny", "(1e-12,0,0)")] {
            let p = s.file(&format!("{name}.nrrd"));
            write_file(
                &p,
                &format!(
                    "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 1 1\nencoding: raw\n\
                     space: left-posterior-superior\n\
                     space directions: {dir} (0,1,0) (0,0,1)\n\n"
                ),
                &[1, 2],
            );
            let e = load(&p).unwrap_err().to_string();
            assert!(e.contains("axis 0 has a zero"), "{name}: {e}");
        }
    }

    #[test]
    fn big_endian_and_spellings() {
        let s = scratch("be");
        let p = s.file("be.nrrd");
        let vals: [i16; 8] = [-1000, -1, 0, 1, 255, 256, 3000, -32768];
        let data: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
        write_file(
            &p,
            "NRRD0005\n# comment\ncontent: test\ntype: signed short int\ndimension: 3\n\
             sizes: 2 2 2\nendian: big\nencoding: raw\nspacings: 0.5 0.25 2\n\
             kinds: domain domain domain\ncao-xr modality:=MR\n\n",
            &data,
        );
        let v = load(&p).unwrap();
        assert_eq!(v.voxels, Voxels::I16(vals.to_vec()));
        assert_geometry(
            &v,
            [2, 2, 2],
            [0.5, 0.25, 2.0],
            DMat3::IDENTITY,
            DVec3::ZERO,
        );
        assert_eq!(v.modality, Modality::Mr);
        assert_eq!(v.name, "be");

        let p = s.file("be16.nrrd");
        let vals: [u16; 8] = [0, 1, 256, 65535, 4095, 2, 3, 4];
        let data: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
        write_file(
            &p,
            "NRRD0001\ntype: unsigned short\ndimension: 3\nsizes: 2 2 2\nendian: big\n\
             encoding: raw\n\n",
            &data,
        );
        assert_eq!(load(&p).unwrap().voxels, Voxels::U16(vals.to_vec()));

        // int8 is widened to int16; CRLF line ends; no endian needed for one byte.
        let p = s.file("i8.nrrd");
        write_file(
            &p,
            "NRRD0004\r\ntype: int8\r\ndimension: 3\r\nsizes: 2 1 1\r\nencoding: raw\r\n\r\n",
            &[0x80, 0x7f],
        );
        assert_eq!(load(&p).unwrap().voxels, Voxels::I16(vec![-128, 127]));
    }

    #[test]
    fn data_longer_than_the_header_says() {
        let s = scratch("long");
        // attached: trailing bytes are ignored (teem does the same)
        let p = s.file("trailing.nrrd");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n",
            &[1, 2, 3, 4, 5, 6, 7, 8, 99, 99],
        );
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::U8(vec![1, 2, 3, 4, 5, 6, 7, 8])
        );
        // detached raw: refused, naming both files, both sizes and the type
        std::fs::write(s.file("long.raw"), [0u8; 9]).unwrap();
        let p = s.file("long.nhdr");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\
             data file: long.raw\n",
            &[],
        );
        let e = err_of(&p);
        assert!(
            e.contains("long.raw")
                && e.contains("9 bytes")
                && e.contains("describes 8")
                && e.contains("2 x 2 x 2 uint8"),
            "{e}"
        );
        // detached shorter: truncated
        std::fs::write(s.file("long.raw"), [0u8; 7]).unwrap();
        let e = err_of(&p);
        assert!(e.contains("long.raw") && e.contains("truncated"), "{e}");
    }

    #[test]
    fn detached_header_and_skips() {
        let s = scratch("nhdr");
        let sub = s.file("data");
        std::fs::create_dir_all(&sub).unwrap();
        let mut payload = b"junk line one\nline two\nXYZ".to_vec();
        payload.extend_from_slice(&[1, 2, 3, 4, 5, 6, 7, 8]);
        std::fs::write(sub.join("vol.raw"), &payload).unwrap();
        let p = s.file("vol.nhdr");
        write_file(
            &p,
            "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\
             data file: data/vol.raw\nline skip: 2\nbyte skip: 3\n",
            &[],
        );
        let v = load(&p).unwrap();
        assert_eq!(v.voxels, Voxels::U8(vec![1, 2, 3, 4, 5, 6, 7, 8]));
        assert_eq!(v.name, "vol");

        // byte skip -1: the data are the last bytes of the file.
        let p = s.file("tail.nhdr");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 1\nencoding: raw\n\
             datafile: data/vol.raw\nbyte skip: -1\n",
            &[],
        );
        assert_eq!(load(&p).unwrap().voxels, Voxels::U8(vec![5, 6, 7, 8]));

        // gzip detached with byte skip after decompression.
        let mut raw = vec![9u8, 9, 9];
        raw.extend(10u16.to_le_bytes());
        raw.extend(500u16.to_le_bytes());
        let mut enc = GzEncoder::new(Vec::new(), Compression::fast());
        enc.write_all(&raw).unwrap();
        std::fs::write(s.file("g.raw.gz"), enc.finish().unwrap()).unwrap();
        let p = s.file("g.nhdr");
        write_file(
            &p,
            "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 1 1 2\nencoding: gz\n\
             endian: little\nbyte skip: 3\ndata file: g.raw.gz\n",
            &[],
        );
        assert_eq!(load(&p).unwrap().voxels, Voxels::U16(vec![10, 500]));

        // missing data file: message names header and data file.
        let p = s.file("missing.nhdr");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\
             data file: nowhere.raw\n",
            &[],
        );
        let e = err_of(&p);
        assert!(e.contains("nowhere.raw"), "{e}");

        let p = s.file("list.nhdr");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\
             data file: LIST\na.raw\nb.raw\n",
            &[],
        );
        let e = err_of(&p);
        assert!(e.contains("unsupported") && e.contains("LIST"), "{e}");
    }

    #[test]
    fn ras_and_las_become_lps() {
        let s = scratch("ras");
        let p = s.file("ras.nrrd");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nspace: right-anterior-superior\nsizes: 1 1 2\n\
             space directions: (0.9,0,0) (0,0.8,0) (0,0.6,1.2)\nencoding: raw\n\
             space origin: (10,-20,30)\ncao-xr modality: CT\nDICOM:tag:=a: b\n\n",
            &[7, 8],
        );
        let v = load(&p).unwrap();
        assert_eq!(v.modality, Modality::Ct);
        let len_k = (0.36f64 + 1.44).sqrt();
        let dirs = DMat3::from_cols(
            DVec3::new(-1.0, 0.0, 0.0),
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::new(0.0, -0.6 / len_k, 1.2 / len_k),
        );
        assert_geometry(
            &v,
            [1, 1, 2],
            [0.9, 0.8, len_k],
            dirs,
            DVec3::new(-10.0, 20.0, 30.0),
        );

        let p = s.file("las.nrrd");
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nspace: LAS\nsizes: 1 1 2\n\
             space directions: (2,0,0) (0,2,0) (0,0,2)\nencoding: raw\n\
             space origin: (1,2,3)\n\n",
            &[7, 8],
        );
        let v = load(&p).unwrap();
        let dirs = DMat3::from_cols(DVec3::X, -DVec3::Y, DVec3::Z);
        assert_geometry(&v, [1, 1, 2], [2.0; 3], dirs, DVec3::new(1.0, -2.0, 3.0));
    }

    #[test]
    fn bad_inputs() {
        let s = scratch("bad");
        let good = "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 2 2 2\nendian: little\n\
                    encoding: raw\n\n";

        let p = s.file("truncated.nrrd");
        write_file(&p, good, &[0u8; 15]);
        let e = err_of(&p);
        assert!(
            e.contains("truncated") && e.contains("16") && e.contains("15"),
            "{e}"
        );

        let p = s.file("truncated_gz.nrrd");
        let mut enc = GzEncoder::new(Vec::new(), Compression::fast());
        enc.write_all(&[0u8; 10]).unwrap();
        write_file(&p, &good.replace("raw", "gzip"), &enc.finish().unwrap());
        let e = err_of(&p);
        assert!(
            e.contains("truncated") && e.contains("16") && e.contains("10"),
            "{e}"
        );

        let p = s.file("corrupt_gz.nrrd");
        write_file(
            &p,
            &good.replace("raw", "gzip"),
            b"this is not gzip data at all",
        );
        let e = err_of(&p);
        assert!(e.contains("gzip"), "{e}");

        let p = s.file("nomagic.nrrd");
        write_file(&p, &good.replace("NRRD0004", "NRRD0009"), &[0u8; 16]);
        assert!(err_of(&p).contains("magic"));
        let p = s.file("binary.nrrd");
        std::fs::write(&p, [0u8, 1, 2, 255, 254]).unwrap();
        assert!(err_of(&p).contains("magic"));
        let p = s.file("empty.nrrd");
        std::fs::write(&p, []).unwrap();
        assert!(err_of(&p).contains("magic"));

        let p = s.file("dim2.nrrd");
        write_file(
            &p,
            &good
                .replace("dimension: 3", "dimension: 2")
                .replace("2 2 2", "4 2"),
            &[0u8; 16],
        );
        assert!(err_of(&p).contains("dimension"));

        let p = s.file("absurd.nrrd");
        write_file(
            &p,
            &good.replace("2 2 2", "100000 100000 100000"),
            &[0u8; 16],
        );
        assert!(err_of(&p).contains("too large"));
        let p = s.file("overflow.nrrd");
        write_file(
            &p,
            &good.replace("2 2 2", "18446744073709551615 2 2"),
            &[0u8; 16],
        );
        assert!(err_of(&p).contains("too large"));
        let p = s.file("zero.nrrd");
        write_file(&p, &good.replace("2 2 2", "2 0 2"), &[]);
        assert!(err_of(&p).contains("zero"));

        let p = s.file("bzip.nrrd");
        write_file(&p, &good.replace("raw", "bzip2"), &[0u8; 16]);
        let e = err_of(&p);
        assert!(e.contains("unsupported") && e.contains("encoding"), "{e}");

        let p = s.file("int64.nrrd");
        write_file(&p, &good.replace("uint16", "int64"), &[0u8; 64]);
        let e = err_of(&p);
        assert!(
            e.contains("unsupported") && e.contains("int64") && e.contains("64-bit"),
            "{e}"
        );
        let p = s.file("block.nrrd");
        write_file(&p, &good.replace("uint16", "block"), &[0u8; 64]);
        assert!(err_of(&p).contains("block"));
        // a double stream shorter than the header says
        let p = s.file("short_double.nrrd");
        write_file(&p, &good.replace("uint16", "double"), &[0u8; 63]);
        let e = err_of(&p);
        assert!(
            e.contains("truncated") && e.contains("64") && e.contains("63"),
            "{e}"
        );

        let p = s.file("noendian.nrrd");
        write_file(&p, &good.replace("endian: little\n", ""), &[0u8; 16]);
        assert!(err_of(&p).contains("endian"));
        let p = s.file("nosizes.nrrd");
        write_file(&p, &good.replace("sizes: 2 2 2\n", ""), &[0u8; 16]);
        assert!(err_of(&p).contains("sizes"));
        let p = s.file("badsizes.nrrd");
        write_file(&p, &good.replace("2 2 2", "2 x 2"), &[0u8; 16]);
        assert!(err_of(&p).contains("sizes"));
        let p = s.file("badvec.nrrd");
        write_file(
            &p,
            &good.replace(
                "encoding",
                "space directions: (1,0,0) (0,1) (0,0,1)\nencoding",
            ),
            &[0u8; 16],
        );
        assert!(err_of(&p).contains("space directions"));
        let p = s.file("flat.nrrd");
        write_file(
            &p,
            &good.replace(
                "encoding",
                "space directions: (1,0,0) (2,0,0) (0,0,1)\nencoding",
            ),
            &[0u8; 16],
        );
        assert!(err_of(&p).contains("degenerate"));
        let p = s.file("unterminated.nrrd");
        write_file(&p, good.trim_end(), &[]);
        assert!(err_of(&p).contains("empty line"));
        let p = s.file("garbage_line.nrrd");
        write_file(
            &p,
            &good.replace("encoding", "what is this\nencoding"),
            &[0u8; 16],
        );
        assert!(err_of(&p).contains("what is this"));

        let p = s.file("does-not-exist.nrrd");
        assert!(err_of(&p).contains("No such file"));
    }

    #[test]
    fn round_trip_every_sample_type() {
        use crate::volume::test_types::cases;
        let s = scratch("types");
        let dirs = rotation();
        let origin = DVec3::new(3.5, -2.0, 41.0);
        for c in cases() {
            for gzip in [false, true] {
                let p = s.file(&format!("{}-{gzip}.nrrd", c.name));
                let mut data = c.bytes.clone();
                if gzip {
                    let mut enc = GzEncoder::new(Vec::new(), Compression::fast());
                    enc.write_all(&data).unwrap();
                    data = enc.finish().unwrap();
                }
                write_file(
                    &p,
                    &format!(
                        "NRRD0004\ntype: {}\ndimension: 3\nspace: left-posterior-superior\n\
                         sizes: 5 4 3\nspace directions: {} {} {}\nendian: little\n\
                         encoding: {}\nspace origin: {}\n\n",
                        c.nrrd,
                        fmt_vec(dirs.x_axis * 0.7),
                        fmt_vec(dirs.y_axis * 1.25),
                        fmt_vec(dirs.z_axis * 3.0),
                        if gzip { "gzip" } else { "raw" },
                        fmt_vec(origin)
                    ),
                    &data,
                );
                let v = load(&p).unwrap();
                assert_eq!(v.voxels, c.want, "{}", c.name);
                assert_geometry(&v, [5, 4, 3], [0.7, 1.25, 3.0], dirs, origin);
                // written back (F32 as float) and read again: the same voxels and geometry
                let p2 = s.file(&format!("{}-{gzip}-back.nrrd", c.name));
                write_volume(&p2, &v, gzip).unwrap();
                let back = load(&p2).unwrap();
                assert_eq!(back.voxels, c.want, "{} written back", c.name);
                assert_geometry(&back, [5, 4, 3], [0.7, 1.25, 3.0], dirs, origin);
            }
        }
    }

    #[test]
    fn nan_voxels_are_refused() {
        let s = scratch("nan");
        for (c, bytes) in crate::volume::test_types::nan_cases() {
            let p = s.file(&format!("nan-{}.nrrd", c.name));
            write_file(
                &p,
                &format!(
                    "NRRD0004\ntype: {}\ndimension: 3\nsizes: 5 4 3\nendian: little\n\
                     encoding: raw\n\n",
                    c.nrrd
                ),
                &bytes,
            );
            let e = err_of(&p);
            assert!(e.contains("voxel (2,1,1)") && e.contains("NaN"), "{e}");
        }
    }

    #[test]
    fn multi_chunk_data() {
        // More samples than one read chunk (1 Mi samples), raw and gzip.
        let s = scratch("chunks");
        let dims = [130, 100, 90];
        let vals: Vec<i16> = (0..130 * 100 * 90)
            .map(|i: i32| ((i % 4001) * 7 % 4001 - 2000) as i16)
            .collect();
        for gzip in [false, true] {
            let p = s.file(&format!("big-{gzip}.nrrd"));
            let dirs = DMat3::from_cols(DVec3::X, -DVec3::Y, DVec3::Z);
            write(
                &p,
                &Grid {
                    dims,
                    spacing: [0.8, 0.8, 2.5],
                    directions: dirs,
                    origin: DVec3::ZERO,
                    modality: Modality::Ct,
                },
                NrrdData::I16(&vals),
                gzip,
            )
            .unwrap();
            let v = load(&p).unwrap();
            assert_eq!(v.voxels, Voxels::I16(vals.clone()));
            assert_geometry(&v, dims, [0.8, 0.8, 2.5], dirs, DVec3::ZERO);
        }
    }

    #[test]
    fn gzip_claiming_a_huge_volume_fails_cheaply() {
        // 2^31 one-byte voxels are within the limits, but the stream holds 100 bytes: the
        // loader must report truncation without allocating gigabytes first.
        let s = scratch("claim");
        let p = s.file("claim.nrrd");
        let mut enc = GzEncoder::new(Vec::new(), Compression::fast());
        enc.write_all(&[1u8; 100]).unwrap();
        write_file(
            &p,
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2048 1024 1024\nencoding: gzip\n\n",
            &enc.finish().unwrap(),
        );
        let e = err_of(&p);
        assert!(
            e.contains("truncated") && e.contains("2147483648") && e.contains("100"),
            "{e}"
        );
    }

    #[test]
    fn never_panics_on_mangled_headers() {
        let s = scratch("fuzz");
        let base = "NRRD0004\ntype: int16\ndimension: 3\nsizes: 3 2 2\nendian: little\n\
                    encoding: raw\nspace: RAS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n\
                    space origin: (1,2,3)\nbyte skip: 0\nline skip: 0\n\n";
        let data = [0u8; 24];
        let mut file = Vec::from(base.as_bytes());
        file.extend_from_slice(&data);
        let p = s.file("fuzz.nrrd");
        // Truncate at every length and flip every header byte: must return, never panic.
        for cut in 0..file.len() {
            std::fs::write(&p, &file[..cut]).unwrap();
            let _ = load(&p);
        }
        for i in 0..base.len() {
            for b in [b'\n', b'-', b'9', b' ', b'(', 0xff] {
                let mut m = file.clone();
                m[i] = b;
                std::fs::write(&p, &m).unwrap();
                let _ = load(&p);
            }
        }
        std::fs::write(&p, &file).unwrap();
        assert!(load(&p).is_ok());
    }

    #[test]
    fn four_d_series_pick_a_volume() {
        let s = scratch("series");
        let samples: Vec<i16> = (0..72).collect();
        let le: Vec<u8> = samples.iter().flat_map(|v| v.to_le_bytes()).collect();
        let head = |dims: &str, extra: &str| {
            format!(
                "NRRD0004\ntype: short\ndimension: {}\nsizes: {dims}\nendian: little\n{extra}",
                dims.split_whitespace().count()
            )
        };
        let seq =
            "space: left-posterior-superior\nspace directions: (1,0,0) (0,2,0) (0,0,3) none\n\
                   kinds: domain domain domain list\n";
        let attached = |name: &str, hdr: String, data: &[u8]| {
            let p = s.file(name);
            let mut b = hdr.into_bytes();
            b.push(b'\n');
            b.extend_from_slice(data);
            std::fs::write(&p, b).unwrap();
            p
        };
        let want = |t: i16| Voxels::I16((24 * t..24 * t + 24).collect());
        // raw and gzip: volume 2 of 3
        let raw = attached(
            "seq.nrrd",
            head("2 3 4 3", &format!("{seq}encoding: raw\n")),
            &le,
        );
        let mut gz = GzEncoder::new(Vec::new(), Compression::fast());
        gz.write_all(&le).unwrap();
        let gzp = attached(
            "seqgz.nrrd",
            head("2 3 4 3", &format!("{seq}encoding: gzip\n")),
            &gz.finish().unwrap(),
        );
        for p in [&raw, &gzp] {
            let v = load_frame(p, Some(2)).unwrap();
            assert_eq!((v.dims, v.spacing), ([2, 3, 4], [1.0, 2.0, 3.0]));
            assert_eq!(v.voxels, want(2));
            let e = err_of(p);
            assert!(
                e.contains("3 volumes of 2 x 3 x 4") && e.contains("#T"),
                "{e}"
            );
            let e = load_frame(p, Some(3)).unwrap_err().to_string();
            assert!(e.contains("holds 3"), "{e}");
        }
        // by kinds alone, and a series of one (spacings with nan for the series axis)
        let p = attached(
            "kinds.nrrd",
            head("2 3 4 3", "kinds: space space space time\nencoding: raw\n"),
            &le,
        );
        assert_eq!(load_frame(&p, Some(1)).unwrap().voxels, want(1));
        let p = attached(
            "one.nrrd",
            head("2 3 4 1", "spacings: 1 2 3 nan\nencoding: raw\n"),
            &le[..48],
        );
        assert_eq!(load(&p).unwrap().voxels, want(0));
        // a series must be in the file whole, even when an early volume is picked
        let p = attached(
            "cut.nrrd",
            head("2 3 4 3", &format!("{seq}encoding: raw\n")),
            &le[..100],
        );
        let e = load_frame(&p, Some(0)).unwrap_err().to_string();
        assert!(e.contains("truncated data: expected 144 bytes"), "{e}");
        // interleaved components (a 3D Slicer segmentation's layers, a vector axis first): one
        // is picked, on the grid of the other three axes
        let layers = "space directions: none (1,0,0) (0,2,0) (0,0,3)\n\
                      kinds: list domain domain domain\n";
        let p = attached(
            "layers.nrrd",
            head("3 2 3 4", &format!("{layers}encoding: raw\n")),
            &le,
        );
        assert!(err_of(&p).contains("pick one"));
        let v = load_frame(&p, Some(1)).unwrap();
        assert_eq!((v.dims, v.spacing), ([2, 3, 4], [1.0, 2.0, 3.0]));
        assert_eq!(v.voxels, Voxels::I16((0..24).map(|i| 3 * i + 1).collect()));
        // a non-spatial axis in the middle is refused
        let mid = "space directions: (1,0,0) none (0,2,0) (0,0,3)\n";
        let p = attached(
            "mid.nrrd",
            head("2 3 3 4", &format!("{mid}encoding: raw\n")),
            &le,
        );
        assert!(err_of(&p).contains("in the middle"), "{}", err_of(&p));
        let p = attached("zero.nrrd", head("2 3 4 0", "encoding: raw\n"), &[]);
        assert!(err_of(&p).contains("size 0"));
        let p = attached("five.nrrd", head("2 3 4 3 1", "encoding: raw\n"), &le);
        assert!(err_of(&p).contains("dimension 5"));
    }
}
