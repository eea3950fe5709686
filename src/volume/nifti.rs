//! NIfTI reader (NIfTI-1 and NIfTI-2) and NIfTI-1 writer: single-file `.nii`, or `.nii.gz`
//! (gzip of the same bytes).
//!
//! Reads 3-D scalar volumes of either byte order, and one chosen volume of a 4-D series (a
//! 4-D file with one time point counts as 3-D). NIfTI-2 differs only in its 540-byte layout
//! (64-bit dims and offsets, double-precision geometry). 8/16-bit integers are kept as they are;
//! 32-bit integers, floats and scaled data (`scl_slope`/`scl_inter`) become int16/uint16 when
//! every value is an integer that fits, else float32 (NaN and infinities are refused). The
//! geometry comes from the sform (preferred), the qform, or the voxel sizes alone, and is
//! converted from NIfTI's RAS+ world into LPS. The writer stores both an sform and (for
//! rotations) a qform.

use super::data_source::{self, DataSource, Described, Skip};
use super::{
    checked_size, pick_frame, read_wide, split_axes, write_atomically, write_voxels, Modality,
    Volume, VolumeError, Voxels, WideSamples, WideType,
};
use flate2::read::MultiGzDecoder;
use flate2::write::GzEncoder;
use flate2::Compression;
use glam::{DMat3, DQuat, DVec3};
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::Path;

/// Size of the NIfTI-1 header proper.
const HEADER_BYTES: usize = 348;
/// Size of the NIfTI-2 header proper.
const HEADER2_BYTES: usize = 540;
/// Where the writer puts the data: header + the 4-byte (empty) extension flag.
const WRITE_OFFSET: usize = 352;
/// RAS <-> LPS: NIfTI's world x points right and y anterior; ours left and posterior.
const RAS_TO_LPS: DVec3 = DVec3::new(-1.0, -1.0, 1.0);

/// Whether `path` names a gzip-compressed NIfTI (`.nii.gz`).
fn is_gzip_name(path: &Path) -> bool {
    path.file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase().ends_with(".gz"))
        .unwrap_or(false)
}

/// Field access into a header of either byte order.
struct Fields<'a> {
    b: &'a [u8],
    be: bool,
}

impl Fields<'_> {
    fn bytes<const N: usize>(&self, off: usize) -> [u8; N] {
        let mut a: [u8; N] = self.b[off..off + N].try_into().unwrap();
        if self.be {
            a.reverse();
        }
        a
    }
    fn i16(&self, off: usize) -> i16 {
        i16::from_le_bytes(self.bytes(off))
    }
    fn i32(&self, off: usize) -> i32 {
        i32::from_le_bytes(self.bytes(off))
    }
    fn i64(&self, off: usize) -> i64 {
        i64::from_le_bytes(self.bytes(off))
    }
    fn f32(&self, off: usize) -> f64 {
        f32::from_le_bytes(self.bytes(off)) as f64
    }
    fn f64(&self, off: usize) -> f64 {
        f64::from_le_bytes(self.bytes(off))
    }
}

/// The fields of a NIfTI-1 or NIfTI-2 header the loader uses, widened to one layout.
struct Header {
    /// 1 or 2.
    version: u8,
    /// Bytes of the header proper (348 or 540): the smallest vox_offset.
    bytes: usize,
    dim: [i64; 8],
    datatype: i16,
    bitpix: i16,
    pixdim: [f64; 8],
    vox_offset: f64,
    slope: f64,
    inter: f64,
    xyzt_units: u8,
    qform_code: i32,
    sform_code: i32,
    /// quatern_b, c, d.
    quatern: DVec3,
    qoffset: DVec3,
    srow: [[f64; 4]; 3],
}

impl Header {
    /// NIfTI-1: 348 bytes, 16-bit dims, 32-bit floats, magic at 344.
    fn v1(f: &Fields) -> Header {
        let v3 = |off| DVec3::new(f.f32(off), f.f32(off + 4), f.f32(off + 8));
        Header {
            version: 1,
            bytes: 348,
            dim: std::array::from_fn(|i| f.i16(40 + 2 * i) as i64),
            datatype: f.i16(70),
            bitpix: f.i16(72),
            pixdim: std::array::from_fn(|i| f.f32(76 + 4 * i)),
            vox_offset: f.f32(108),
            slope: f.f32(112),
            inter: f.f32(116),
            xyzt_units: f.b[123],
            qform_code: f.i16(252) as i32,
            sform_code: f.i16(254) as i32,
            quatern: v3(256),
            qoffset: v3(268),
            srow: std::array::from_fn(|r| std::array::from_fn(|c| f.f32(280 + 16 * r + 4 * c))),
        }
    }
    /// NIfTI-2: 540 bytes, 64-bit dims and offsets, doubles, magic at 4.
    fn v2(f: &Fields) -> Header {
        let v3 = |off| DVec3::new(f.f64(off), f.f64(off + 8), f.f64(off + 16));
        Header {
            version: 2,
            bytes: 540,
            dim: std::array::from_fn(|i| f.i64(16 + 8 * i)),
            datatype: f.i16(12),
            bitpix: f.i16(14),
            pixdim: std::array::from_fn(|i| f.f64(104 + 8 * i)),
            vox_offset: f.i64(168) as f64,
            slope: f.f64(176),
            inter: f.f64(184),
            xyzt_units: f.i32(500) as u8,
            qform_code: f.i32(344),
            sform_code: f.i32(348),
            quatern: v3(352),
            qoffset: v3(376),
            srow: std::array::from_fn(|r| std::array::from_fn(|c| f.f64(400 + 32 * r + 8 * c))),
        }
    }
}

/// Reads into `buf` until it is full or the input ends; the count read.
fn fill(r: &mut dyn Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Maps the NIfTI datatype code; `Err` names the type for the message.
fn parse_datatype(code: i16) -> Result<WideType, String> {
    Ok(match code {
        2 => WideType::U8,
        4 => WideType::I16,
        8 => WideType::I32,
        16 => WideType::F32,
        64 => WideType::F64,
        256 => WideType::I8,
        512 => WideType::U16,
        768 => WideType::U32,
        1 => return Err("binary (1 bit)".into()),
        32 | 1792 | 2048 => return Err(format!("complex ({code})")),
        128 | 2304 => return Err(format!("RGB/RGBA colour ({code})")),
        1024 | 1280 => return Err(format!("64-bit integer ({code})")),
        1536 => return Err("float128 (1536)".into()),
        _ => return Err(format!("unknown code {code}")),
    })
}

/// The qform rotation (RAS) from the quaternion (b, c, d), a = sqrt(1 - b² - c² - d²); as
/// nifti1_io does, a slightly over-long (b, c, d) is renormalised with a = 0.
fn quaternion_matrix(b: f64, c: f64, d: f64) -> DMat3 {
    let (mut a, mut b, mut c, mut d) = (1.0 - (b * b + c * c + d * d), b, c, d);
    if a < 1e-7 {
        let n = (b * b + c * c + d * d).sqrt();
        if n > 0.0 {
            (b, c, d) = (b / n, c / n, d / n);
        }
        a = 0.0;
    } else {
        a = a.sqrt();
    }
    DMat3::from_cols(
        DVec3::new(
            a * a + b * b - c * c - d * d,
            2.0 * (b * c + a * d),
            2.0 * (b * d - a * c),
        ),
        DVec3::new(
            2.0 * (b * c - a * d),
            a * a + c * c - b * b - d * d,
            2.0 * (c * d + a * b),
        ),
        DVec3::new(
            2.0 * (b * d + a * c),
            2.0 * (c * d - a * b),
            a * a + d * d - c * c - b * b,
        ),
    )
}

/// Loads a NIfTI-1 or NIfTI-2 volume from `.nii` or `.nii.gz`; a 4-D file only when it holds
/// one volume (see [`load_frame`]).
pub fn load(path: &Path) -> Result<Volume, VolumeError> {
    load_frame(path, None)
}

/// Loads volume `frame` (0-based) of a 4-D NIfTI file; `None` wants a 3-D file (or a 4-D one
/// holding one volume) and names the choice otherwise.
pub fn load_frame(path: &Path, frame: Option<u64>) -> Result<Volume, VolumeError> {
    let file = File::open(path).map_err(|e| VolumeError::io(path, e))?;
    let gzip = is_gzip_name(path);
    let mut reader: Box<dyn Read> = if gzip {
        Box::new(MultiGzDecoder::new(BufReader::new(file)))
    } else {
        Box::new(BufReader::new(file))
    };
    let (h, be) = read_header(path, &mut reader, gzip)?;
    let (dims, frame) = frame_dims(path, &h, frame)?;
    let samples = parse_samples(path, &h, dims)?;
    let geometry = parse_geometry(path, &h)?;
    let voxels = read_payload(path, reader, gzip, be, &h, &samples, frame)?;
    let volume = data_source::loaded_volume(path, dims, geometry, Modality::Unknown, voxels);
    // named without .nii.gz, not by the stem
    Ok(Volume {
        name: volume_name(path),
        ..volume
    })
}

/// Step 1: the header proper from `reader`: sizeof_hdr (348: NIfTI-1, 540: NIfTI-2) gives the
/// version and the byte order (big-endian: true), the magic says single-file. `gzip`: the
/// reader decompresses (for the messages).
fn read_header(
    path: &Path,
    reader: &mut dyn Read,
    gzip: bool,
) -> Result<(Header, bool), VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let what = if gzip { "gzip " } else { "" };
    let read_err = |e: std::io::Error| fmt(format!("{what}read error in the header: {e}"));
    let mut hdr = vec![0u8; HEADER2_BYTES];
    let mut got = fill(reader, &mut hdr[..4]).map_err(read_err)?;
    let first = i32::from_le_bytes([hdr[0], hdr[1], hdr[2], hdr[3]]);
    let want = match (first, first.swap_bytes()) {
        _ if got < 4 => HEADER_BYTES,
        (348 | 540, _) => first as usize,
        (_, s @ (348 | 540)) => s as usize,
        _ => {
            return Err(fmt(format!(
                "not a NIfTI file: sizeof_hdr is {first}, expected 348 (NIfTI-1) or 540 (NIfTI-2)"
            )))
        }
    };
    if got == 4 {
        got += fill(reader, &mut hdr[4..want]).map_err(read_err)?;
    }
    if got < want {
        return Err(fmt(format!(
            "truncated header: {got} of {want} bytes, not a NIfTI file"
        )));
    }
    let be = i32::from_le_bytes([hdr[0], hdr[1], hdr[2], hdr[3]]) as usize != want;
    let f = Fields { b: &hdr, be };
    let (h, magic, single, pair) = if want == HEADER_BYTES {
        (Header::v1(&f), &hdr[344..348], &b"n+1\0"[..], &b"ni1\0"[..])
    } else {
        (
            Header::v2(&f),
            &hdr[4..12],
            &b"n+2\0\r\n\x1a\n"[..],
            &b"ni2\0\r\n\x1a\n"[..],
        )
    };
    let v = h.version;
    if magic == pair {
        return Err(VolumeError::unsupported(
            path,
            format!(
                "a two-file NIfTI-{v} header (.hdr/.img, magic \"ni{v}\"); convert it to a single .nii"
            ),
        ));
    }
    if magic != single {
        return Err(fmt(format!(
            "bad magic {:?}, expected \"n+{v}\" for a single-file NIfTI-{v} .nii",
            String::from_utf8_lossy(magic)
        )));
    }
    Ok((h, be))
}

/// Step 2: the sizes of the spatial axes and the volume to read (a 4-D file is a series of
/// 3-D volumes: time points, echoes, phases; one is shown).
fn frame_dims(path: &Path, h: &Header, frame: Option<u64>) -> Result<([u64; 3], u64), VolumeError> {
    let dim = h.dim;
    let ndim = dim[0];
    if !(3..=7).contains(&ndim) {
        return Err(if (1..=2).contains(&ndim) {
            VolumeError::unsupported(
                path,
                format!(
                    "{ndim}-dimensional data (dim {:?}); a volume needs 3",
                    &dim[1..=ndim as usize]
                ),
            )
        } else {
            VolumeError::format(path, format!("invalid dim[0] = {ndim} (must be 1..7)"))
        });
    }
    let frames = if ndim >= 4 { dim[4] } else { 1 };
    if frames < 1 || (ndim > 4 && dim[5..=ndim as usize].iter().any(|&d| d != 1)) {
        return Err(VolumeError::unsupported(
            path,
            format!(
                "{ndim}-dimensional data (dim {:?}); only 3-D volumes and 4-D series of them \
                 are supported",
                &dim[1..=ndim as usize]
            ),
        ));
    }
    if dim[1..=3].iter().any(|&d| d < 1) {
        return Err(VolumeError::format(
            path,
            format!(
                "invalid sizes {} {} {} (must be positive)",
                dim[1], dim[2], dim[3]
            ),
        ));
    }
    let dims = [dim[1] as u64, dim[2] as u64, dim[3] as u64];
    let frame = pick_frame(path, frames as u64, dims, frame)?;
    Ok((dims, frame))
}

/// The samples' type, scaling and place.
struct Samples {
    ty: WideType,
    /// Sizes of the spatial axes.
    dims: [u64; 3],
    /// Bytes of one volume.
    data_bytes: u64,
    /// (slope, intercept), when the values are scaled.
    scale: Option<(f64, f64)>,
    /// Where the first volume's samples begin.
    vox_offset: u64,
}

/// Step 3: datatype and bitpix, the size of a volume, scl_slope/scl_inter and vox_offset.
fn parse_samples(path: &Path, h: &Header, dims: [u64; 3]) -> Result<Samples, VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let code = h.datatype;
    let ty = parse_datatype(code).map_err(|t| {
        VolumeError::unsupported(
            path,
            format!(
                "datatype {t}; supported are uint8, int8, int16, uint16, int32, uint32, \
                 float32 and float64"
            ),
        )
    })?;
    let bitpix = h.bitpix;
    if bitpix as u64 != ty.bytes() * 8 {
        return Err(fmt(format!(
            "bitpix {bitpix} does not match datatype {code} ({} bits)",
            ty.bytes() * 8
        )));
    }
    let (_, data_bytes) = checked_size(path, dims, ty.bytes())?;
    let (slope, inter) = (h.slope, h.inter);
    let scale = if slope == 0.0 || !slope.is_finite() || (slope == 1.0 && inter == 0.0) {
        None // "scl_slope = 0: no scaling", as the standard says
    } else if !inter.is_finite() {
        return Err(fmt(format!("invalid scl_inter {inter}")));
    } else {
        Some((slope, inter))
    };
    let vox_offset = h.vox_offset;
    if !(vox_offset.is_finite() && vox_offset >= h.bytes as f64) || vox_offset.fract() != 0.0 {
        return Err(fmt(format!(
            "invalid vox_offset {vox_offset} (must be a whole number >= {})",
            h.bytes
        )));
    }
    Ok(Samples {
        ty,
        dims,
        data_bytes,
        scale,
        vox_offset: vox_offset as u64,
    })
}

/// Step 4: (spacing, directions, origin) in LPS and mm, from the sform (preferred), the qform
/// or the voxel sizes alone.
fn parse_geometry(path: &Path, h: &Header) -> Result<([f64; 3], DMat3, DVec3), VolumeError> {
    // NIfTI's spatial unit (xyzt_units & 7) is metres, mm or microns; we work in mm.
    let unit = match h.xyzt_units & 7 {
        1 => 1000.0,
        3 => 0.001,
        _ => 1.0, // mm, or unknown (taken as mm, as most readers do)
    };
    let pixdim = h.pixdim;
    let pix = |a: usize| {
        let p = pixdim[a].abs();
        if p.is_finite() && p > 0.0 {
            p
        } else {
            1.0
        }
    };
    let (steps_ras, origin_ras) = if h.sform_code > 0 {
        let row = |r: usize| DVec3::from_slice(&h.srow[r]);
        let m = DMat3::from_cols(row(0), row(1), row(2)).transpose();
        let o = DVec3::new(h.srow[0][3], h.srow[1][3], h.srow[2][3]);
        (m, o)
    } else if h.qform_code > 0 {
        let r = quaternion_matrix(h.quatern.x, h.quatern.y, h.quatern.z);
        let qfac = if pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let m = DMat3::from_cols(
            r.x_axis * pix(1),
            r.y_axis * pix(2),
            r.z_axis * (pix(3) * qfac),
        );
        (m, h.qoffset)
    } else {
        // "method 1" of the standard: voxel sizes only, axes along RAS.
        (
            DMat3::from_diagonal(DVec3::new(pix(1), pix(2), pix(3))),
            DVec3::ZERO,
        )
    };
    if !(steps_ras.is_finite() && origin_ras.is_finite()) {
        return Err(VolumeError::format(
            path,
            "the sform/qform holds non-finite numbers",
        ));
    }
    let flip = DMat3::from_diagonal(RAS_TO_LPS);
    let (spacing, directions) = split_axes(path, flip * steps_ras * unit)?;
    let origin = origin_ras * RAS_TO_LPS * unit;
    Ok((spacing, directions, origin))
}

/// Step 5: reads volume `frame` (its samples follow the earlier volumes') from `reader`, which
/// has read the header: on through the gzip stream, or from the file opened anew at the data.
fn read_payload(
    path: &Path,
    mut reader: Box<dyn Read>,
    gzip: bool,
    be: bool,
    h: &Header,
    samples: &Samples,
    frame: u64,
) -> Result<Voxels, VolumeError> {
    let source = DataSource::attached(path);
    let data_bytes = samples.data_bytes;
    let vox_offset = data_source::frame_offset(path, samples.vox_offset, frame, data_bytes)?;
    let exact;
    if gzip {
        let skip = vox_offset - h.bytes as u64;
        source.skip_decoded(&mut reader, "gzip ", skip, data_bytes)?;
        exact = false;
    } else {
        drop(reader);
        let file = File::open(path).map_err(|e| VolumeError::io(path, e))?;
        let mut file = BufReader::new(file);
        let described = Described {
            shape: String::new(), // attached data: never more than described
            fields: "",
        };
        let start = source.locate_raw(&file, vox_offset, Skip::Bytes(0), data_bytes, &described)?;
        source.seek(&mut file, start)?;
        reader = Box::new(file);
        exact = true;
    }
    let what = source.what(if gzip { "gzip " } else { "" });
    let wide = WideSamples {
        ty: samples.ty,
        dims: samples.dims.map(|d| d as usize),
        big_endian: be,
        scale: samples.scale,
    };
    read_wide(path, &what, &mut reader, wide, exact)
}

/// The file name without `.nii`, `.nii.gz` or `.gz`.
fn volume_name(path: &Path) -> String {
    path.file_name()
        .map(|s| {
            let s = s.to_string_lossy();
            let l = s.to_ascii_lowercase();
            let cut = [".nii.gz", ".nii", ".gz"]
                .iter()
                .find(|e| l.ends_with(*e))
                .map_or(0, |e| e.len());
            s[..s.len() - cut].to_string()
        })
        .unwrap_or_else(|| "volume".into())
}

/// The 352 bytes (header + empty extension flag) the writer puts before the data of `vol`.
fn header(path: &Path, vol: &Volume, be: bool) -> Result<Vec<u8>, VolumeError> {
    if vol.dims.iter().any(|&d| d == 0 || d > i16::MAX as usize)
        || vol.voxel_count() != vol.voxels.len()
    {
        return Err(VolumeError::format(
            path,
            format!(
                "cannot write: sizes {:?} do not fit NIfTI-1 (1..32767) or the {} voxels",
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
    let mut h = vec![0u8; WRITE_OFFSET];
    let put_i16 = |h: &mut Vec<u8>, off: usize, v: i16| {
        h[off..off + 2].copy_from_slice(&if be { v.to_be_bytes() } else { v.to_le_bytes() })
    };
    let put_f32 = |h: &mut Vec<u8>, off: usize, v: f64| {
        let v = v as f32;
        h[off..off + 4].copy_from_slice(&if be { v.to_be_bytes() } else { v.to_le_bytes() })
    };
    let sizeof = 348i32;
    h[0..4].copy_from_slice(&if be {
        sizeof.to_be_bytes()
    } else {
        sizeof.to_le_bytes()
    });
    h[38] = b'r';
    put_i16(&mut h, 40, 3);
    for a in 0..3 {
        put_i16(&mut h, 42 + 2 * a, vol.dims[a] as i16);
    }
    for a in 3..7 {
        put_i16(&mut h, 42 + 2 * a, 1);
    }
    let (code, bitpix) = match vol.voxels {
        Voxels::U8(_) => (2, 8),
        Voxels::I16(_) => (4, 16),
        Voxels::U16(_) => (512, 16),
        Voxels::F32(_) => (16, 32),
    };
    put_i16(&mut h, 70, code);
    put_i16(&mut h, 72, bitpix);

    // RAS steps of the i, j, k axes.
    let flip = DMat3::from_diagonal(RAS_TO_LPS);
    let dirs_ras = flip * vol.directions;
    let steps = DMat3::from_cols(
        dirs_ras.x_axis * vol.spacing[0],
        dirs_ras.y_axis * vol.spacing[1],
        dirs_ras.z_axis * vol.spacing[2],
    );
    let origin_ras = vol.origin * RAS_TO_LPS;

    // qform: only for (possibly reflected) rotations; the reflection goes into qfac.
    let qfac = if dirs_ras.determinant() < 0.0 {
        -1.0
    } else {
        1.0
    };
    let rot = DMat3::from_cols(dirs_ras.x_axis, dirs_ras.y_axis, dirs_ras.z_axis * qfac);
    let orthonormal = (rot.transpose() * rot).abs_diff_eq(DMat3::IDENTITY, 1e-6);
    put_f32(&mut h, 76, qfac);
    for a in 0..3 {
        put_f32(&mut h, 80 + 4 * a, vol.spacing[a]);
    }
    put_f32(&mut h, 108, WRITE_OFFSET as f64);
    h[123] = 2 | 8; // mm, seconds
    if orthonormal {
        let mut q = DQuat::from_mat3(&rot).normalize();
        if q.w < 0.0 {
            q = -q;
        }
        put_i16(&mut h, 252, 1);
        put_f32(&mut h, 256, q.x);
        put_f32(&mut h, 260, q.y);
        put_f32(&mut h, 264, q.z);
        put_f32(&mut h, 268, origin_ras.x);
        put_f32(&mut h, 272, origin_ras.y);
        put_f32(&mut h, 276, origin_ras.z);
    }
    put_i16(&mut h, 254, 1);
    let rows = steps.transpose();
    for (r, (row, o)) in [rows.x_axis, rows.y_axis, rows.z_axis]
        .iter()
        .zip([origin_ras.x, origin_ras.y, origin_ras.z])
        .enumerate()
    {
        put_f32(&mut h, 280 + 16 * r, row.x);
        put_f32(&mut h, 284 + 16 * r, row.y);
        put_f32(&mut h, 288 + 16 * r, row.z);
        put_f32(&mut h, 292 + 16 * r, o);
    }
    let descrip = b"cao-xr";
    h[148..148 + descrip.len()].copy_from_slice(descrip);
    h[344..348].copy_from_slice(b"n+1\0");
    Ok(h)
}

/// Writes `vol` as a little-endian NIfTI-1 (`gzip`: gzip-compressed, for `.nii.gz`), with the
/// geometry as an sform (exact to f32) and, when the directions are a rotation or reflection, a
/// qform. Written under a temporary name and renamed when complete.
pub fn write(path: &Path, vol: &Volume, gzip: bool) -> Result<(), VolumeError> {
    write_with(path, vol, gzip, false)
}

fn write_with(path: &Path, vol: &Volume, gzip: bool, be: bool) -> Result<(), VolumeError> {
    let h = header(path, vol, be)?;
    write_atomically(path, |w| {
        if gzip {
            let mut enc = GzEncoder::new(w, Compression::default());
            enc.write_all(&h)?;
            write_voxels(&mut enc, &vol.voxels, be)?;
            enc.finish()?;
        } else {
            w.write_all(&h)?;
            write_voxels(w, &vol.voxels, be)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unique scratch directory for this module's tests, removed on drop.
    fn scratch(tag: &str) -> crate::volume::test_scratch::Scratch {
        crate::volume::test_scratch::Scratch::new(&format!("nifti-{tag}"))
    }

    fn sample(voxels: Voxels) -> Volume {
        Volume {
            whole_range: None,
            name: "t".into(),
            dims: [5, 4, 3],
            spacing: [0.7, 1.25, 3.0],
            directions: DMat3::from_rotation_z(0.3) * DMat3::from_rotation_x(-0.7),
            origin: DVec3::new(-12.5, 30.25, 7.0),
            modality: Modality::Unknown,
            voxels,
            labels: None,
        }
    }

    fn assert_same_geometry(a: &Volume, b: &Volume, tol: f64) {
        assert_eq!(a.dims, b.dims);
        for i in 0..3 {
            assert!(
                (a.spacing[i] - b.spacing[i]).abs() < tol,
                "{:?} {:?}",
                a.spacing,
                b.spacing
            );
        }
        assert!(
            a.directions.abs_diff_eq(b.directions, tol),
            "{:?} vs {:?}",
            a.directions,
            b.directions
        );
        assert!(
            a.origin.abs_diff_eq(b.origin, tol),
            "{:?} {:?}",
            a.origin,
            b.origin
        );
    }

    /// The load error of `good` edited by `f`, written as `name` in `s`.
    fn err_of_edited(
        s: &crate::volume::test_scratch::Scratch,
        name: &str,
        good: &[u8],
        f: &dyn Fn(&mut Vec<u8>),
    ) -> String {
        let p = s.file(name);
        let mut b = good.to_vec();
        f(&mut b);
        std::fs::write(&p, &b).unwrap();
        err_of(&p)
    }

    fn err_of(path: &Path) -> String {
        let e = load(path).expect_err("load should fail").to_string();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(e.contains(&name), "error {e:?} does not name {name}");
        e
    }

    /// A header for `vol`'s geometry with its datatype replaced, followed by `data`.
    fn custom(path: &Path, vol: &Volume, code: i16, bitpix: i16, data: &[u8], be: bool) {
        let mut h = header(path, vol, be).unwrap();
        let put = |h: &mut Vec<u8>, off: usize, v: i16| {
            h[off..off + 2].copy_from_slice(&if be { v.to_be_bytes() } else { v.to_le_bytes() })
        };
        put(&mut h, 70, code);
        put(&mut h, 72, bitpix);
        h.extend_from_slice(data);
        std::fs::write(path, h).unwrap();
    }

    fn set_f32(path: &Path, off: usize, v: f32) {
        let mut b = std::fs::read(path).unwrap();
        b[off..off + 4].copy_from_slice(&v.to_le_bytes());
        std::fs::write(path, b).unwrap();
    }

    #[test]
    fn round_trip_types_and_gzip() {
        let s = scratch("rt");
        let n = 60;
        let cases = [
            Voxels::U8((0..n).map(|i| (i * 37 % 256) as u8).collect()),
            Voxels::I16((0..n).map(|i| (i as i16 - 30) * 1000).collect()),
            Voxels::U16((0..n).map(|i| (i as u16) * 1000 + 7).collect()),
        ];
        for (c, vox) in cases.into_iter().enumerate() {
            let vol = sample(vox);
            for (gz, name) in [(false, format!("a{c}.nii")), (true, format!("a{c}.nii.gz"))] {
                let p = s.file(&name);
                write(&p, &vol, gz).unwrap();
                let back = load(&p).unwrap();
                assert_eq!(back.voxels, vol.voxels, "{name}");
                assert_same_geometry(&back, &vol, 1e-6);
                assert_eq!(back.modality, Modality::Unknown);
                assert_eq!(back.name, format!("a{c}"));
            }
        }
    }

    #[test]
    fn round_trip_every_sample_type() {
        use crate::volume::test_types::cases;
        let s = scratch("types");
        let vol = sample(Voxels::U8(vec![0; 60]));
        for c in cases() {
            let p = s.file(&format!("{}.nii", c.name));
            custom(&p, &vol, c.nifti.0, c.nifti.1, &c.bytes, false);
            let v = load(&p).unwrap();
            assert_eq!(v.voxels, c.want, "{}", c.name);
            assert_same_geometry(&v, &vol, 1e-6);
            for gz in [false, true] {
                let p2 = s.file(&format!(
                    "{}-back.nii{}",
                    c.name,
                    if gz { ".gz" } else { "" }
                ));
                write(&p2, &v, gz).unwrap();
                let back = load(&p2).unwrap();
                assert_eq!(back.voxels, c.want, "{} written back", c.name);
                assert_same_geometry(&back, &vol, 1e-6);
            }
        }
    }

    #[test]
    fn nan_voxels_are_refused() {
        let s = scratch("nan");
        let vol = sample(Voxels::U8(vec![0; 60]));
        for (c, bytes) in crate::volume::test_types::nan_cases() {
            let p = s.file(&format!("nan-{}.nii", c.name));
            custom(&p, &vol, c.nifti.0, c.nifti.1, &bytes, false);
            let e = err_of(&p);
            assert!(e.contains("voxel (2,1,1)") && e.contains("NaN"), "{e}");
        }
        // scaling that overflows to infinity is refused too
        let p = s.file("inf.nii");
        let data: Vec<u8> = (0..60).flat_map(|i| (i as f32).to_le_bytes()).collect();
        custom(&p, &vol, 16, 32, &data, false);
        set_f32(&p, 112, 3e38);
        let e = err_of(&p);
        assert!(
            e.contains("after scaling") && e.contains("voxel (2,0,0)") && e.contains("float32"),
            "{e}"
        );
    }

    #[test]
    fn qform_reflection_and_big_endian() {
        let s = scratch("qf");
        let mut vol = sample(Voxels::I16((0..60).map(|i| i * 3 - 90).collect()));
        // A reflected frame (det -1) exercises qfac.
        vol.directions = DMat3::from_cols(
            vol.directions.x_axis,
            vol.directions.y_axis,
            -vol.directions.z_axis,
        );
        let p = s.file("be.nii");
        write_with(&p, &vol, false, true).unwrap();
        let back = load(&p).unwrap();
        assert_eq!(back.voxels, vol.voxels);
        assert_same_geometry(&back, &vol, 1e-6);
        // The qform alone (sform_code 0) gives the same geometry.
        let mut b = std::fs::read(&p).unwrap();
        b[254..256].copy_from_slice(&0i16.to_be_bytes());
        std::fs::write(&p, &b).unwrap();
        let q = load(&p).unwrap();
        assert_same_geometry(&q, &vol, 1e-5);
        // Neither: voxel sizes along RAS, i.e. -x, -y, +z in LPS.
        b[252..254].copy_from_slice(&0i16.to_be_bytes());
        std::fs::write(&p, &b).unwrap();
        let plain = load(&p).unwrap();
        assert!(plain
            .directions
            .abs_diff_eq(DMat3::from_diagonal(DVec3::new(-1.0, -1.0, 1.0)), 1e-12));
        assert!((plain.spacing[0] - 0.7).abs() < 1e-6 && plain.origin == DVec3::ZERO);
    }

    #[test]
    fn sheared_sform_keeps_column_lengths() {
        let s = scratch("shear");
        let vol = sample(Voxels::U8(vec![1; 60]));
        let p = s.file("shear.nii");
        write(&p, &vol, false).unwrap();
        let mut b = std::fs::read(&p).unwrap();
        // sform rows: x = (2, 1, 0, 5), y = (0, 3, 0, 6), z = (0, 0, 4, 7); no qform.
        let rows = [
            [2.0f32, 1.0, 0.0, 5.0],
            [0.0, 3.0, 0.0, 6.0],
            [0.0, 0.0, 4.0, 7.0],
        ];
        for (r, row) in rows.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                b[280 + 16 * r + 4 * c..284 + 16 * r + 4 * c].copy_from_slice(&v.to_le_bytes());
            }
        }
        b[252..254].copy_from_slice(&0i16.to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        let v = load(&p).unwrap();
        let l = 10f64.sqrt();
        assert!((v.spacing[0] - 2.0).abs() < 1e-9);
        assert!((v.spacing[1] - l).abs() < 1e-6);
        assert!((v.spacing[2] - 4.0).abs() < 1e-9);
        assert!(v
            .directions
            .y_axis
            .abs_diff_eq(DVec3::new(-1.0 / l, -3.0 / l, 0.0), 1e-6));
        assert!(v.origin.abs_diff_eq(DVec3::new(-5.0, -6.0, 7.0), 1e-9));
    }

    #[test]
    fn scaling_and_wide_types() {
        let s = scratch("scl");
        let vol = sample(Voxels::U8(vec![0; 60]));
        // uint8 with slope 2, intercept -100 -> int16
        let p = s.file("scl.nii");
        let raw: Vec<u8> = (0..60).collect();
        custom(&p, &vol, 2, 8, &raw, false);
        set_f32(&p, 112, 2.0);
        set_f32(&p, 116, -100.0);
        let v = load(&p).unwrap();
        let want: Vec<i16> = (0..60).map(|i| i * 2 - 100).collect();
        assert_eq!(v.voxels, Voxels::I16(want));
        // slope 0 means "no scaling": the uint8 stay uint8.
        set_f32(&p, 112, 0.0);
        assert_eq!(load(&p).unwrap().voxels, Voxels::U8(raw.clone()));
        // non-integral scaling gives float32
        set_f32(&p, 112, 0.5);
        set_f32(&p, 116, 0.0);
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::F32((0..60).map(|i| i as f32 * 0.5).collect())
        );

        // float32 holding integers -> int16, big-endian too
        for be in [false, true] {
            let p = s.file(&format!("f32-{be}.nii"));
            let data: Vec<u8> = (0..60)
                .flat_map(|i| {
                    let x = i as f32 * 10.0 - 300.0;
                    if be {
                        x.to_be_bytes()
                    } else {
                        x.to_le_bytes()
                    }
                })
                .collect();
            custom(&p, &vol, 16, 32, &data, be);
            let v = load(&p).unwrap();
            assert_eq!(
                v.voxels,
                Voxels::I16((0..60).map(|i| i * 10 - 300).collect())
            );
        }
        // float64 with a fraction -> float32
        let p = s.file("f64.nii");
        let data: Vec<u8> = (0..60)
            .flat_map(|i| (i as f64 + 0.25).to_le_bytes())
            .collect();
        custom(&p, &vol, 64, 64, &data, false);
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::F32((0..60).map(|i| i as f32 + 0.25).collect())
        );
        // int32 beyond 16 bits -> float32; int32 within uint16 -> uint16; int8 -> int16
        let p = s.file("i32.nii");
        let data: Vec<u8> = (0..60)
            .flat_map(|i| (i * 100_000i32).to_le_bytes())
            .collect();
        custom(&p, &vol, 8, 32, &data, false);
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::F32((0..60).map(|i| i as f32 * 100_000.0).collect())
        );
        let data: Vec<u8> = (0..60).flat_map(|i| (i * 1000u32).to_le_bytes()).collect();
        custom(&p, &vol, 768, 32, &data, false);
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::U16((0..60).map(|i| i * 1000).collect())
        );
        let data: Vec<u8> = (0..60).map(|i| (i as i8 - 30) as u8).collect();
        custom(&p, &vol, 256, 8, &data, false);
        assert_eq!(
            load(&p).unwrap().voxels,
            Voxels::I16((0..60).map(|i| i - 30).collect())
        );
    }

    #[test]
    fn bad_inputs() {
        let s = scratch("bad");
        let vol = sample(Voxels::I16(vec![5; 60]));
        let good = s.file("good.nii");
        write(&good, &vol, false).unwrap();
        let bytes = std::fs::read(&good).unwrap();
        let case = |name: &str, f: &dyn Fn(&mut Vec<u8>)| err_of_edited(&s, name, &bytes, f);
        assert!(case("short.nii", &|b| b.truncate(100)).contains("truncated header"));
        assert!(case("data.nii", &|b| b.truncate(352 + 50)).contains("truncated data"));
        assert!(case("magic.nii", &|b| b[344..348].copy_from_slice(b"xyz\0")).contains("magic"));
        assert!(case("pair.nii", &|b| b[344..348].copy_from_slice(b"ni1\0")).contains("two-file"));
        assert!(case("size.nii", &|b| b[0] = 7).contains("sizeof_hdr"));
        assert!(case("dt.nii", &|b| b[70..72]
            .copy_from_slice(&128i16.to_le_bytes()))
        .contains("unsupported: datatype"));
        let e = case("complex.nii", &|b| {
            b[70..72].copy_from_slice(&32i16.to_le_bytes());
            b[72..74].copy_from_slice(&64i16.to_le_bytes());
        });
        assert!(e.contains("unsupported: datatype complex (32)"), "{e}");
        let e = case("unknown-dt.nii", &|b| {
            b[70..72].copy_from_slice(&77i16.to_le_bytes())
        });
        assert!(e.contains("unknown code 77"), "{e}");
        // data longer than the header says: trailing bytes are ignored (single-file .nii)
        let p = s.file("trailing.nii");
        let mut b = bytes.clone();
        b.extend_from_slice(&[1; 9]);
        std::fs::write(&p, &b).unwrap();
        assert_eq!(load(&p).unwrap().voxels, vol.voxels);
        assert!(case("bitpix.nii", &|b| b[72..74]
            .copy_from_slice(&8i16.to_le_bytes()))
        .contains("bitpix"));
        assert!(case("4d.nii", &|b| {
            b[40..42].copy_from_slice(&4i16.to_le_bytes());
            b[48..50].copy_from_slice(&2i16.to_le_bytes());
        })
        .contains("4-dimensional"));
        assert!(case("neg.nii", &|b| b[42..44]
            .copy_from_slice(&(-5i16).to_le_bytes()))
        .contains("invalid sizes"));
        assert!(case("huge.nii", &|b| {
            for a in 0..3 {
                b[42 + 2 * a..44 + 2 * a].copy_from_slice(&32000i16.to_le_bytes());
            }
        })
        .contains("too large"));
        assert!(case("off.nii", &|b| b[108..112]
            .copy_from_slice(&10f32.to_le_bytes()))
        .contains("vox_offset"));
        // 4-D with one time point is fine
        let p = s.file("t1.nii");
        let mut b = bytes.clone();
        b[40..42].copy_from_slice(&4i16.to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        assert_eq!(load(&p).unwrap().dims, [5, 4, 3]);
        // a corrupt / truncated gzip
        let gz = s.file("cut.nii.gz");
        write(&gz, &vol, true).unwrap();
        let g = std::fs::read(&gz).unwrap();
        std::fs::write(&gz, &g[..g.len() / 2]).unwrap();
        let e = err_of(&gz);
        assert!(e.contains("gzip"), "{e}");
        // missing file
        assert!(err_of(&s.file("missing.nii")).contains("missing.nii"));
        // never panics on mangled headers
        for i in 0..352 {
            let mut b = bytes.clone();
            b[i] ^= 0xA5;
            let p = s.file("mangled.nii");
            std::fs::write(&p, &b).unwrap();
            let _ = load(&p);
        }
    }

    /// A NIfTI-2 file laid out by hand from the standard (nifti2.h): int16, 3 x 2 x 2 (x `t`
    /// volumes), 0.5/2/3 mm, an sform with a 90-degree turn, big- or little-endian.
    fn nifti2_bytes(t: i64, be: bool) -> Vec<u8> {
        let mut h = vec![0u8; 544];
        let mut put = |off: usize, b: &[u8]| {
            let mut b = b.to_vec();
            if be {
                b.reverse();
            }
            h[off..off + b.len()].copy_from_slice(&b);
        };
        put(0, &540i32.to_le_bytes());
        put(12, &4i16.to_le_bytes());
        put(14, &16i16.to_le_bytes());
        for (i, d) in [4, 3, 2, 2, t, 1, 1, 1].iter().enumerate() {
            put(16 + 8 * i, &d.to_le_bytes());
        }
        for (i, p) in [1.0, 0.5, 2.0, 3.0, 1.0, 1.0, 1.0, 1.0].iter().enumerate() {
            put(104 + 8 * i, &f64::to_le_bytes(*p));
        }
        put(168, &544i64.to_le_bytes());
        put(348, &1i32.to_le_bytes()); // sform_code
                                       // RAS x = -2 j + 10, y = 0.5 i - 20, z = 3 k + 30
        let srow: [[f64; 4]; 3] = [
            [0.0, -2.0, 0.0, 10.0],
            [0.5, 0.0, 0.0, -20.0],
            [0.0, 0.0, 3.0, 30.0],
        ];
        for (r, row) in srow.iter().enumerate() {
            for (c, x) in row.iter().enumerate() {
                put(400 + 32 * r + 8 * c, &f64::to_le_bytes(*x));
            }
        }
        put(500, &2i32.to_le_bytes()); // mm
        h[4..12].copy_from_slice(b"n+2\0\r\n\x1a\n");
        for n in 0..12 * t as i16 {
            h.extend_from_slice(&if be {
                (n * 7).to_be_bytes()
            } else {
                (n * 7).to_le_bytes()
            });
        }
        h
    }

    #[test]
    fn nifti2_geometry_frames_and_bad_headers() {
        let s = scratch("nifti2");
        for be in [false, true] {
            let p = s.file("two.nii");
            std::fs::write(&p, nifti2_bytes(1, be)).unwrap();
            let v = load(&p).unwrap();
            assert_eq!(v.dims, [3, 2, 2]);
            assert_eq!(v.spacing, [0.5, 2.0, 3.0]);
            // RAS columns i = (0, 0.5, 0), j = (-2, 0, 0), origin (10, -20, 30), in LPS:
            assert_eq!(v.directions.x_axis, DVec3::new(0.0, -1.0, 0.0));
            assert_eq!(v.directions.y_axis, DVec3::new(1.0, 0.0, 0.0));
            assert_eq!(v.origin, DVec3::new(-10.0, 20.0, 30.0));
            assert_eq!(v.voxels, Voxels::I16((0..12).map(|n| n * 7).collect()));
        }
        // volume 2 of a 3-volume series; a missing pick and one out of range are refused
        let p = s.file("series.nii");
        std::fs::write(&p, nifti2_bytes(3, false)).unwrap();
        let v = load_frame(&p, Some(2)).unwrap();
        assert_eq!(v.voxels, Voxels::I16((24..36).map(|n| n * 7).collect()));
        assert!(err_of(&p).contains("3 volumes of 3 x 2 x 2"));
        let e = load_frame(&p, Some(3)).unwrap_err().to_string();
        assert!(e.contains("series.nii") && e.contains("holds 3"), "{e}");
        // truncated header, pair magic, short data; mangled headers never panic
        let good = nifti2_bytes(1, false);
        let case = |name: &str, f: &dyn Fn(&mut Vec<u8>)| err_of_edited(&s, name, &good, f);
        let e = case("short2.nii", &|b| b.truncate(400));
        assert!(e.contains("truncated header: 400 of 540"), "{e}");
        assert!(case("pair2.nii", &|b| b[4..7].copy_from_slice(b"ni2")).contains("NIfTI-2"));
        assert!(case("data2.nii", &|b| b.truncate(550)).contains("truncated data"));
        let e = case("huge2.nii", &|b| {
            for a in 1..4 {
                b[16 + 8 * a..24 + 8 * a].copy_from_slice(&(1i64 << 40).to_le_bytes());
            }
        });
        assert!(e.contains("too large"), "{e}");
        for i in 0..544 {
            let mut b = good.clone();
            b[i] ^= 0xA5;
            let p = s.file("mangled2.nii");
            std::fs::write(&p, &b).unwrap();
            let _ = load(&p);
            let _ = load_frame(&p, Some(u64::MAX));
        }
    }
}
