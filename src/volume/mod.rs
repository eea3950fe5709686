//! Volumes: scalar voxels with their physical geometry, loaders, the built-in phantom and the
//! fetched CT head.

pub mod ct_head;
pub mod nrrd;
pub mod phantom;
pub mod raw;
pub mod transfer;

use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

/// Errors of volume I/O. Every message names the file and what is wrong with it.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Format { path: PathBuf, msg: String },
    #[error("{path}: unsupported: {msg}")]
    Unsupported { path: PathBuf, msg: String },
}

impl VolumeError {
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }
    pub fn format(path: &Path, msg: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }
    pub fn unsupported(path: &Path, msg: impl Into<String>) -> Self {
        Self::Unsupported {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }
}

/// Voxel storage at the file's own precision (x fastest, then y, then z).
#[derive(Clone, Debug, PartialEq)]
pub enum Voxels {
    U8(Vec<u8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
}

impl Voxels {
    pub fn len(&self) -> usize {
        match self {
            Voxels::U8(v) => v.len(),
            Voxels::U16(v) => v.len(),
            Voxels::I16(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Value of voxel `i` (linear index) in data units; exact for every supported type.
    pub fn get(&self, i: usize) -> f32 {
        match self {
            Voxels::U8(v) => v[i] as f32,
            Voxels::U16(v) => v[i] as f32,
            Voxels::I16(v) => v[i] as f32,
        }
    }
    pub fn type_name(&self) -> &'static str {
        match self {
            Voxels::U8(_) => "uint8",
            Voxels::U16(_) => "uint16",
            Voxels::I16(_) => "int16",
        }
    }
}

/// What the scalars measure; decides which transfer-function presets make sense.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Modality {
    /// Hounsfield units.
    Ct,
    Mr,
    Unknown,
}

/// A scalar volume. Voxel (i,j,k) has its centre at index-space point (i+0.5, j+0.5, k+0.5);
/// physical millimetres along the volume's own axes are index * spacing.
#[derive(Clone, Debug)]
pub struct Volume {
    pub name: String,
    pub dims: [usize; 3],
    /// Millimetres between voxel centres along i, j, k.
    pub spacing: [f64; 3],
    /// Columns: unit vectors of the i, j, k axes in patient LPS space (x = patient left,
    /// y = posterior, z = superior). Identity for an axial stack stored L-to-R... see README.
    pub directions: DMat3,
    /// LPS position (mm) of the centre of voxel (0,0,0), as the file says; informative only.
    pub origin: DVec3,
    pub modality: Modality,
    pub voxels: Voxels,
}

impl Volume {
    pub fn voxel_count(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }
    /// (min, max) of the stored values.
    pub fn value_range(&self) -> (f32, f32) {
        fn mm<T: Copy + PartialOrd + Into<f32>>(v: &[T]) -> (f32, f32) {
            let mut lo = v[0];
            let mut hi = v[0];
            for &x in v {
                if x < lo {
                    lo = x
                }
                if x > hi {
                    hi = x
                }
            }
            (lo.into(), hi.into())
        }
        match &self.voxels {
            Voxels::U8(v) => mm(v),
            Voxels::U16(v) => mm(v),
            Voxels::I16(v) => mm(v),
        }
    }
    /// The same geometry (dims, spacing, orientation, name) with no voxels.
    pub fn clone_geometry(&self) -> Volume {
        Volume {
            name: self.name.clone(),
            dims: self.dims,
            spacing: self.spacing,
            directions: self.directions,
            origin: self.origin,
            modality: self.modality,
            voxels: Voxels::U8(Vec::new()),
        }
    }

    /// Physical extent in mm along i, j, k.
    pub fn extent_mm(&self) -> DVec3 {
        DVec3::new(
            self.dims[0] as f64 * self.spacing[0],
            self.dims[1] as f64 * self.spacing[1],
            self.dims[2] as f64 * self.spacing[2],
        )
    }
}

/// Refuse headers that describe absurd volumes before anything is allocated.
pub(crate) const MAX_VOXELS: u64 = 1 << 31;
/// Largest amount of sample data (bytes) any loader accepts.
pub(crate) const MAX_DATA_BYTES: u64 = 8 << 30;

/// Checks `dims` against [`MAX_VOXELS`] / [`MAX_DATA_BYTES`]; returns (voxel count, data bytes).
pub(crate) fn checked_size(
    path: &Path,
    dims: [u64; 3],
    bytes_per_voxel: u64,
) -> Result<(usize, u64), VolumeError> {
    if dims.contains(&0) {
        return Err(VolumeError::format(
            path,
            format!("sizes {} {} {} contain a zero", dims[0], dims[1], dims[2]),
        ));
    }
    let voxels = dims[0]
        .checked_mul(dims[1])
        .and_then(|v| v.checked_mul(dims[2]))
        .filter(|&v| v <= MAX_VOXELS)
        .ok_or_else(|| {
            VolumeError::unsupported(
                path,
                format!(
                    "sizes {} x {} x {} are too large (more than {} voxels)",
                    dims[0], dims[1], dims[2], MAX_VOXELS
                ),
            )
        })?;
    let bytes = voxels * bytes_per_voxel;
    if bytes > MAX_DATA_BYTES {
        return Err(VolumeError::unsupported(
            path,
            format!(
                "sizes {} x {} x {} need {} bytes of data, more than the limit of {} bytes",
                dims[0], dims[1], dims[2], bytes, MAX_DATA_BYTES
            ),
        ));
    }
    let voxels = usize::try_from(voxels)
        .map_err(|_| VolumeError::unsupported(path, "volume too large for this platform"))?;
    Ok((voxels, bytes))
}

/// Sample encodings the loaders read (int8 is widened to int16).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum SampleFormat {
    U8,
    I8,
    U16,
    I16,
}

impl SampleFormat {
    pub(crate) fn bytes(self) -> u64 {
        match self {
            SampleFormat::U8 | SampleFormat::I8 => 1,
            SampleFormat::U16 | SampleFormat::I16 => 2,
        }
    }
}

/// Reads up to `count` samples from `r` in chunks (no second full-size byte buffer). Returns the
/// voxels (fewer than `count` when the input ends early) and the number of bytes consumed.
/// `exact` reserves all of `count` up front (use it when the input is known to be long
/// enough); otherwise the storage grows with the data, so a short compressed stream claiming a
/// huge volume does not allocate the full size.
pub(crate) fn read_samples(
    r: &mut dyn std::io::Read,
    format: SampleFormat,
    count: usize,
    big_endian: bool,
    exact: bool,
) -> std::io::Result<(Voxels, u64)> {
    fn run<T: Copy, const N: usize>(
        r: &mut dyn std::io::Read,
        count: usize,
        exact: bool,
        conv: fn([u8; N]) -> T,
    ) -> std::io::Result<(Vec<T>, u64)> {
        const CHUNK: usize = 1 << 20;
        let mut out: Vec<T> = Vec::with_capacity(if exact { count } else { count.min(CHUNK) });
        let mut buf = vec![0u8; CHUNK * N];
        let mut total = 0u64;
        while out.len() < count {
            let want = (count - out.len()).min(CHUNK) * N;
            let mut filled = 0;
            while filled < want {
                match r.read(&mut buf[filled..want]) {
                    Ok(0) => break,
                    Ok(n) => filled += n,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => return Err(e),
                }
            }
            total += filled as u64;
            if out.capacity() - out.len() < filled / N {
                // grow geometrically, never beyond `count`
                let extra = out.capacity().max(filled / N).min(count - out.len());
                out.reserve_exact(extra);
            }
            out.extend(buf[..filled - filled % N].chunks_exact(N).map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                conv(a)
            }));
            if filled < want {
                break;
            }
        }
        Ok((out, total))
    }
    Ok(match format {
        SampleFormat::U8 => {
            let (v, n) = run(r, count, exact, |b: [u8; 1]| b[0])?;
            (Voxels::U8(v), n)
        }
        SampleFormat::I8 => {
            let (v, n) = run(r, count, exact, |b: [u8; 1]| b[0] as i8 as i16)?;
            (Voxels::I16(v), n)
        }
        SampleFormat::U16 => {
            let conv = if big_endian {
                u16::from_be_bytes
            } else {
                u16::from_le_bytes
            };
            let (v, n) = run(r, count, exact, conv)?;
            (Voxels::U16(v), n)
        }
        SampleFormat::I16 => {
            let conv = if big_endian {
                i16::from_be_bytes
            } else {
                i16::from_le_bytes
            };
            let (v, n) = run(r, count, exact, conv)?;
            (Voxels::I16(v), n)
        }
    })
}
