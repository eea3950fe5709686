//! Volumes: scalar voxels with their physical geometry, loaders, the built-in phantom and the
//! fetched CT head.

pub mod ct_head;
mod data_source;
pub mod dicom;
pub mod distance;
pub mod labels;
pub mod markups;
pub mod metaimage;
pub mod nifti;
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

/// Voxel storage at the file's own precision (x fastest, then y, then z). Integer data that fit
/// 16 bits stay integers; everything else (floats, scaled data, wider integers) is `F32`, and
/// never holds NaN or infinities (the loaders refuse them).
#[derive(Clone, Debug, PartialEq)]
pub enum Voxels {
    U8(Vec<u8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    F32(Vec<f32>),
}

impl Voxels {
    /// Every `step`-th sample from `start`: one component of interleaved samples.
    pub fn strided(self, start: usize, step: usize) -> Voxels {
        fn pick<T>(v: Vec<T>, start: usize, step: usize) -> Vec<T> {
            v.into_iter().skip(start).step_by(step).collect()
        }
        match self {
            Voxels::U8(v) => Voxels::U8(pick(v, start, step)),
            Voxels::U16(v) => Voxels::U16(pick(v, start, step)),
            Voxels::I16(v) => Voxels::I16(pick(v, start, step)),
            Voxels::F32(v) => Voxels::F32(pick(v, start, step)),
        }
    }

    pub fn len(&self) -> usize {
        match self {
            Voxels::U8(v) => v.len(),
            Voxels::U16(v) => v.len(),
            Voxels::I16(v) => v.len(),
            Voxels::F32(v) => v.len(),
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
            Voxels::F32(v) => v[i],
        }
    }
    pub fn type_name(&self) -> &'static str {
        match self {
            Voxels::U8(_) => "uint8",
            Voxels::U16(_) => "uint16",
            Voxels::I16(_) => "int16",
            Voxels::F32(_) => "float32",
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
    /// The segmentation resampled into this grid (`--labels`), and how its structures are
    /// shown: part of the classification O of docs/design.md.
    pub labels: Option<std::sync::Arc<labels::LabelMap>>,
    /// Where this volume is a part of a larger one (a crop or a downsample of it), that
    /// volume's value range: it is classified over it ([`Volume::value_range`]), so that a
    /// normalised TF, the local histograms' bins and the lighting threshold mean there what
    /// they mean in the whole. None: its own values' range.
    pub whole_range: Option<(f32, f32)>,
}

/// Where a volume's voxels lie and what they measure: a [`Volume`]'s geometry without its
/// voxels (what the writers take with the samples to write).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    pub dims: [usize; 3],
    /// Millimetres between voxel centres along i, j, k.
    pub spacing: [f64; 3],
    /// Columns: unit vectors of the i, j, k axes in patient LPS space.
    pub directions: DMat3,
    /// LPS position (mm) of the centre of voxel (0,0,0).
    pub origin: DVec3,
    pub modality: Modality,
}

impl Volume {
    /// The volume's [`Grid`].
    pub fn grid(&self) -> Grid {
        Grid {
            dims: self.dims,
            spacing: self.spacing,
            directions: self.directions,
            origin: self.origin,
            modality: self.modality,
        }
    }
    pub fn voxel_count(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }
    /// The value range the volume is classified over: (min, max) of its stored values, or the
    /// whole volume's it is a part of ([`Volume::whole_range`]).
    pub fn value_range(&self) -> (f32, f32) {
        self.whole_range.unwrap_or_else(|| self.own_value_range())
    }

    /// (min, max) of the stored values.
    pub fn own_value_range(&self) -> (f32, f32) {
        fn mm<T: Copy + PartialOrd + Into<f32>>(v: &[T]) -> (f32, f32) {
            let Some(&first) = v.first() else {
                return (0.0, 0.0);
            };
            let mut lo = first;
            let mut hi = first;
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
            Voxels::F32(v) => mm(v),
        }
    }
    /// The same geometry (dims, spacing, orientation, name) with no voxels.
    pub fn clone_geometry(&self) -> Volume {
        Volume {
            whole_range: None,
            name: self.name.clone(),
            dims: self.dims,
            spacing: self.spacing,
            directions: self.directions,
            origin: self.origin,
            modality: self.modality,
            voxels: Voxels::U8(Vec::new()),
            labels: None,
        }
    }

    /// The factor [`Volume::downsample`] has reduced this volume by (1 for none), from the
    /// `-dsN` its name ends with. Downsampling by a then b gives the dims of a x b at once
    /// (ceil(ceil(d / a) / b) = ceil(d / ab)).
    pub fn downsampled_by(&self) -> usize {
        let mut name = self.name.as_str();
        let mut by = 1usize;
        while let Some((rest, n)) = name.rsplit_once("-ds") {
            match n.parse::<usize>() {
                Ok(n) if n > 1 => by = by.saturating_mul(n),
                _ => break,
            }
            name = rest;
        }
        by
    }

    /// The volume averaged over n x n x n blocks (`--downsample N`): dims ceil(dims / n), spacing
    /// x n, the same directions, the origin moved to the centre of the first new voxel. Blocks
    /// cut by the far edges average the voxels they hold. Integer voxels are rounded to the
    /// nearest integer and keep their type; float32 stays float32. The labels go along, each
    /// block taking the id most of its voxels hold ([`labels::LabelMap::downsample`]). `n <= 1`
    /// returns a copy.
    pub fn downsample(&self, n: usize) -> Volume {
        use rayon::prelude::*;
        if n <= 1 {
            return self.clone();
        }
        let d = self.dims;
        let nd = d.map(|x| x.div_ceil(n));
        let slice = nd[0] * nd[1];
        let mut mean = vec![0f64; slice * nd[2]];
        mean.par_chunks_mut(slice)
            .enumerate()
            .for_each(|(kk, out)| {
                for jj in 0..nd[1] {
                    for ii in 0..nd[0] {
                        let (mut sum, mut count) = (0f64, 0usize);
                        for k in kk * n..((kk + 1) * n).min(d[2]) {
                            for j in jj * n..((jj + 1) * n).min(d[1]) {
                                let row = self.index(0, j, k);
                                for i in ii * n..((ii + 1) * n).min(d[0]) {
                                    sum += self.voxels.get(row + i) as f64;
                                    count += 1;
                                }
                            }
                        }
                        out[ii + nd[0] * jj] = sum / count as f64;
                    }
                }
            });
        // The mean lies within the block's values, so rounding stays in the type's range.
        let voxels = match &self.voxels {
            Voxels::U8(_) => Voxels::U8(mean.iter().map(|&m| m.round() as u8).collect()),
            Voxels::U16(_) => Voxels::U16(mean.iter().map(|&m| m.round() as u16).collect()),
            Voxels::I16(_) => Voxels::I16(mean.iter().map(|&m| m.round() as i16).collect()),
            Voxels::F32(_) => Voxels::F32(mean.iter().map(|&m| m as f32).collect()),
        };
        let half = (n as f64 - 1.0) / 2.0;
        let shift = self.directions
            * DVec3::new(
                half * self.spacing[0],
                half * self.spacing[1],
                half * self.spacing[2],
            );
        Volume {
            name: format!("{}-ds{n}", self.name),
            dims: nd,
            spacing: self.spacing.map(|s| s * n as f64),
            directions: self.directions,
            origin: self.origin + shift,
            modality: self.modality,
            voxels,
            labels: self
                .labels
                .as_ref()
                .map(|l| std::sync::Arc::new(l.downsample(self.dims, n))),
            whole_range: Some(self.value_range()),
        }
    }

    /// The voxels of the box `lo .. lo + dims` (clamped to the volume), with their geometry
    /// (the origin moved to the box's first voxel) and labels; named `name[i0:i1,j0:j1,k0:k1]`.
    pub fn crop(&self, lo: [usize; 3], dims: [usize; 3]) -> Volume {
        let lo: [usize; 3] = std::array::from_fn(|a| lo[a].min(self.dims[a]));
        let dims: [usize; 3] = std::array::from_fn(|a| dims[a].min(self.dims[a] - lo[a]));
        let rows = (0..dims[2]).flat_map(|k| (0..dims[1]).map(move |j| (j, k)));
        let start = |(j, k): (usize, usize)| self.index(lo[0], lo[1] + j, lo[2] + k);
        macro_rules! take {
            ($v:expr, $t:ident) => {
                Voxels::$t(
                    rows.clone()
                        .flat_map(|r| $v[start(r)..start(r) + dims[0]].iter().copied())
                        .collect(),
                )
            };
        }
        let voxels = match &self.voxels {
            Voxels::U8(v) => take!(v, U8),
            Voxels::U16(v) => take!(v, U16),
            Voxels::I16(v) => take!(v, I16),
            Voxels::F32(v) => take!(v, F32),
        };
        let shift = DVec3::from_array(std::array::from_fn(|a| lo[a] as f64 * self.spacing[a]));
        Volume {
            name: format!(
                "{}[{}:{},{}:{},{}:{}]",
                self.name,
                lo[0],
                lo[0] + dims[0],
                lo[1],
                lo[1] + dims[1],
                lo[2],
                lo[2] + dims[2]
            ),
            dims,
            spacing: self.spacing,
            directions: self.directions,
            origin: self.origin + self.directions * shift,
            modality: self.modality,
            voxels,
            labels: self
                .labels
                .as_ref()
                .map(|l| std::sync::Arc::new(l.crop(self.dims, lo, dims))),
            whole_range: Some(self.value_range()),
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

/// Which volume of a 4-D series of `frames` volumes of `dims` to read: `frame`, or the only
/// one; a series of several without a pick is refused with the `FILE#T` syntax that picks one.
pub(crate) fn pick_frame(
    path: &Path,
    frames: u64,
    dims: [u64; 3],
    frame: Option<u64>,
) -> Result<u64, VolumeError> {
    match frame {
        None if frames > 1 => Err(VolumeError::unsupported(
            path,
            format!(
                "4-dimensional data: {frames} volumes of {} x {} x {}; pick one with {}#T \
                 (T = 0..{})",
                dims[0],
                dims[1],
                dims[2],
                path.display(),
                frames - 1
            ),
        )),
        None => Ok(0),
        Some(t) if t >= frames => Err(VolumeError::format(
            path,
            format!(
                "volume #{t} asked for, but the file holds {frames} (#0..#{})",
                frames.saturating_sub(1)
            ),
        )),
        Some(t) => Ok(t),
    }
}

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

/// Sample encodings of the NIfTI and MetaImage loaders, which (unlike NRRD) may come with
/// 32-bit, floating-point or scaled samples that are still integers in practice.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum WideType {
    U8,
    I8,
    U16,
    I16,
    I32,
    U32,
    F32,
    F64,
}

impl WideType {
    pub(crate) fn bytes(self) -> u64 {
        match self {
            WideType::U8 | WideType::I8 => 1,
            WideType::U16 | WideType::I16 => 2,
            WideType::I32 | WideType::U32 | WideType::F32 => 4,
            WideType::F64 => 8,
        }
    }
    /// The direct 8/16-bit encoding, if there is one.
    fn narrow(self) -> Option<SampleFormat> {
        match self {
            WideType::U8 => Some(SampleFormat::U8),
            WideType::I8 => Some(SampleFormat::I8),
            WideType::U16 => Some(SampleFormat::U16),
            WideType::I16 => Some(SampleFormat::I16),
            _ => None,
        }
    }
    /// Sample `i` of `b` (which holds whole samples) as f64; exact for every type but F64
    /// itself (f32 and 32-bit integers fit an f64 exactly).
    fn get(self, b: &[u8], i: usize, big_endian: bool) -> f64 {
        let n = self.bytes() as usize;
        let s = &b[i * n..(i + 1) * n];
        macro_rules! num {
            ($t:ty) => {{
                let a = s.try_into().unwrap_or_default();
                (if big_endian {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            WideType::U8 => s[0] as f64,
            WideType::I8 => s[0] as i8 as f64,
            WideType::U16 => num!(u16),
            WideType::I16 => num!(i16),
            WideType::I32 => num!(i32),
            WideType::U32 => num!(u32),
            WideType::F32 => num!(f32),
            WideType::F64 => num!(f64),
        }
    }
}

/// The voxel storage for values computed by `value(linear index)` (x fastest): int16 when every
/// value is an integer within int16, else uint16 when they are integers within uint16, else
/// float32 (f64 values are rounded to the nearest f32). NaN and infinite values are refused
/// with the voxel's (i, j, k) and value; so are finite values beyond the float32 range. The one
/// conversion every loader of wide, float or scaled data (NIfTI, MetaImage, NRRD, DICOM) uses.
// Used by the DICOM loader; the other loaders call it through `read_wide`.
pub(crate) fn voxels_from_values(
    path: &Path,
    dims: [usize; 3],
    value: impl Fn(usize) -> f64,
) -> Result<Voxels, VolumeError> {
    values_to_voxels(path, "", dims, value)
}

/// [`voxels_from_values`] with `what` prefixing the messages (e.g. the detached data file).
fn values_to_voxels(
    path: &Path,
    what: &str,
    dims: [usize; 3],
    value: impl Fn(usize) -> f64,
) -> Result<Voxels, VolumeError> {
    let count = dims[0] * dims[1] * dims[2];
    let ijk = |n: usize| {
        let (i, rest) = (n % dims[0].max(1), n / dims[0].max(1));
        (i, rest % dims[1].max(1), rest / dims[1].max(1))
    };
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut integral = true;
    for n in 0..count {
        let v = value(n);
        if !v.is_finite() || v.abs() > f32::MAX as f64 {
            let (i, j, k) = ijk(n);
            return Err(VolumeError::unsupported(
                path,
                format!(
                    "{what}voxel ({i},{j},{k}) has the value {v}{}: volumes must hold finite \
                     numbers",
                    if v.is_finite() {
                        " (beyond the float32 range)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        integral &= v.fract() == 0.0;
        lo = lo.min(v);
        hi = hi.max(v);
    }
    Ok(
        if integral && lo >= i16::MIN as f64 && hi <= i16::MAX as f64 {
            Voxels::I16((0..count).map(|n| value(n) as i16).collect())
        } else if integral && lo >= 0.0 && hi <= u16::MAX as f64 {
            Voxels::U16((0..count).map(|n| value(n) as u16).collect())
        } else {
            Voxels::F32((0..count).map(|n| value(n) as f32).collect())
        },
    )
}

/// The samples [`read_wide`] reads: a `dims` volume of type `ty` in the given byte order, and
/// the `(slope, inter)` of `value * slope + inter` when the values are scaled.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WideSamples {
    pub ty: WideType,
    pub dims: [usize; 3],
    pub big_endian: bool,
    pub scale: Option<(f64, f64)>,
}

/// Reads the samples of a `dims` volume of type `ty` from `r` and applies
/// `value * slope + inter` when `scale` is given (all of them `samples`'). 8/16-bit samples
/// without scaling are read as they are; everything else goes through [`voxels_from_values`]
/// (int16/uint16 when the values are integers that fit, float32 otherwise; NaN refused).
/// `exact`: the input is known to hold the data (see [`read_samples`]). Errors name `path`;
/// `what` prefixes data messages (e.g. the detached data file).
pub(crate) fn read_wide(
    path: &Path,
    what: &str,
    r: &mut dyn std::io::Read,
    samples: WideSamples,
    exact: bool,
) -> Result<Voxels, VolumeError> {
    let WideSamples {
        ty,
        dims,
        big_endian,
        scale,
    } = samples;
    let count = dims[0] * dims[1] * dims[2];
    let data_bytes = count as u64 * ty.bytes();
    let io = |e: std::io::Error| VolumeError::format(path, format!("{what}read error: {e}"));
    let short = |got: u64| data_source::truncated(path, what, data_bytes, got);
    if let (Some(f), None) = (ty.narrow(), scale) {
        let (v, got) = read_samples(r, f, count, big_endian, exact).map_err(io)?;
        if got < data_bytes || v.len() != count {
            return Err(short(got));
        }
        return Ok(v);
    }
    let want = usize::try_from(data_bytes)
        .map_err(|_| VolumeError::unsupported(path, "volume too large for this platform"))?;
    let mut bytes = Vec::with_capacity(if exact { want } else { want.min(1 << 24) });
    std::io::Read::read_to_end(&mut std::io::Read::take(&mut *r, data_bytes), &mut bytes)
        .map_err(io)?;
    if bytes.len() < want {
        return Err(short(bytes.len() as u64));
    }
    let (slope, inter) = scale.unwrap_or((1.0, 0.0));
    let what = match scale {
        Some(_) => format!("{what}after scaling, "),
        None => what.to_string(),
    };
    values_to_voxels(path, &what, dims, |i| {
        ty.get(&bytes, i, big_endian) * slope + inter
    })
}

/// Writes `path` through a temporary file next to it, renamed into place only when `body`
/// succeeded, so a failed write never leaves a half-written volume under the real name.
pub(crate) fn write_atomically(
    path: &Path,
    body: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
) -> Result<(), VolumeError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| VolumeError::format(path, "cannot write: not a file path"))?;
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let tmp = dir.join(format!(
        ".{}.tmp-{}-{stamp}",
        file_name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| -> std::io::Result<()> {
        let file = std::fs::File::create(&tmp)?;
        let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
        body(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(VolumeError::io(path, e));
    }
    Ok(())
}

/// Writes voxels in file order with the given byte order.
pub(crate) fn write_voxels(
    w: &mut dyn std::io::Write,
    v: &Voxels,
    big_endian: bool,
) -> std::io::Result<()> {
    match v {
        Voxels::U8(v) => w.write_all(v),
        Voxels::U16(v) => write_words(
            w,
            v,
            if big_endian {
                u16::to_be_bytes
            } else {
                u16::to_le_bytes
            },
        ),
        Voxels::I16(v) => write_words(
            w,
            v,
            if big_endian {
                i16::to_be_bytes
            } else {
                i16::to_le_bytes
            },
        ),
        Voxels::F32(v) => write_words(
            w,
            v,
            if big_endian {
                f32::to_be_bytes
            } else {
                f32::to_le_bytes
            },
        ),
    }
}

/// Writes `v` as bytes in chunks (no copy of the whole volume).
fn write_words<T: Copy, const N: usize>(
    w: &mut dyn std::io::Write,
    v: &[T],
    bytes: impl Fn(T) -> [u8; N],
) -> std::io::Result<()> {
    const CHUNK: usize = 1 << 16;
    let mut buf = Vec::with_capacity(CHUNK * N);
    for c in v.chunks(CHUNK) {
        buf.clear();
        for &x in c {
            buf.extend_from_slice(&bytes(x));
        }
        w.write_all(&buf)?;
    }
    Ok(())
}

/// Splits a 3x3 whose columns are the physical (LPS, mm) steps of the i, j, k axes into
/// spacings (column lengths) and unit directions. A sheared matrix keeps its column lengths and
/// normalised columns: the Volume model has no shear, so that is the closest it can say.
pub(crate) fn split_axes(path: &Path, m: DMat3) -> Result<([f64; 3], DMat3), VolumeError> {
    let cols = [m.x_axis, m.y_axis, m.z_axis];
    let mut spacing = [0.0; 3];
    let mut dirs = [DVec3::ZERO; 3];
    for a in 0..3 {
        let len = cols[a].length();
        if !(len.is_finite() && len > 0.0) {
            return Err(VolumeError::format(
                path,
                format!("axis {a} has a zero or invalid step vector {:?}", cols[a]),
            ));
        }
        spacing[a] = len;
        dirs[a] = cols[a] / len;
    }
    let d = DMat3::from_cols(dirs[0], dirs[1], dirs[2]);
    if d.determinant().abs() < 1e-6 {
        return Err(VolumeError::format(
            path,
            "the axis directions are degenerate (not independent)",
        ));
    }
    Ok((spacing, d))
}

/// Scratch directories for the loaders' tests.
#[cfg(test)]
pub(crate) mod test_scratch {
    use std::path::PathBuf;
    use std::sync::atomic::{AtomicUsize, Ordering};

    static COUNTER: AtomicUsize = AtomicUsize::new(0);

    /// A unique scratch directory, removed on drop.
    pub(crate) struct Scratch(pub(crate) PathBuf);

    impl Scratch {
        pub(crate) fn new(tag: &str) -> Self {
            let n = COUNTER.fetch_add(1, Ordering::SeqCst);
            let p = std::env::temp_dir().join(format!("cao-xr-{tag}-{}-{n}", std::process::id()));
            let _ = std::fs::remove_dir_all(&p);
            std::fs::create_dir_all(&p).unwrap();
            Scratch(p)
        }

        pub(crate) fn file(&self, name: &str) -> PathBuf {
            self.0.join(name)
        }
    }

    impl Drop for Scratch {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// The sample types every loader reads, as test cases: 60 little-endian samples (a 5 x 4 x 3
/// volume) of each type and the voxels they must load as.
#[cfg(test)]
pub(crate) mod test_types {
    use super::Voxels;

    pub(crate) struct TypeCase {
        /// Short name, for file names and messages.
        pub name: &'static str,
        pub nrrd: &'static str,
        pub nifti: (i16, i16),
        pub metaimage: &'static str,
        pub bytes: Vec<u8>,
        pub want: Voxels,
    }

    pub(crate) const N: usize = 60;

    pub(crate) fn cases() -> Vec<TypeCase> {
        let le = |v: Vec<Vec<u8>>| v.concat();
        vec![
            TypeCase {
                name: "u8",
                nrrd: "uint8",
                nifti: (2, 8),
                metaimage: "MET_UCHAR",
                bytes: (0..N).map(|i| (i * 4) as u8).collect(),
                want: Voxels::U8((0..N).map(|i| (i * 4) as u8).collect()),
            },
            TypeCase {
                name: "i8",
                nrrd: "int8",
                nifti: (256, 8),
                metaimage: "MET_CHAR",
                bytes: (0..N).map(|i| (i as i8 - 30) as u8).collect(),
                want: Voxels::I16((0..N).map(|i| i as i16 - 30).collect()),
            },
            TypeCase {
                name: "u16",
                nrrd: "uint16",
                nifti: (512, 16),
                metaimage: "MET_USHORT",
                bytes: le((0..N)
                    .map(|i| (i as u16 * 1000 + 7).to_le_bytes().to_vec())
                    .collect()),
                want: Voxels::U16((0..N).map(|i| i as u16 * 1000 + 7).collect()),
            },
            TypeCase {
                name: "i16",
                nrrd: "int16",
                nifti: (4, 16),
                metaimage: "MET_SHORT",
                bytes: le((0..N)
                    .map(|i| ((i as i16 - 30) * 1000).to_le_bytes().to_vec())
                    .collect()),
                want: Voxels::I16((0..N).map(|i| (i as i16 - 30) * 1000).collect()),
            },
            TypeCase {
                // beyond 16 bits: float32 (exact below 2^24)
                name: "u32",
                nrrd: "uint32",
                nifti: (768, 32),
                metaimage: "MET_UINT",
                bytes: le((0..N)
                    .map(|i| (i as u32 * 100_003).to_le_bytes().to_vec())
                    .collect()),
                want: Voxels::F32((0..N).map(|i| (i as u32 * 100_003) as f32).collect()),
            },
            TypeCase {
                name: "i32",
                nrrd: "int32",
                nifti: (8, 32),
                metaimage: "MET_INT",
                bytes: le((0..N)
                    .map(|i| ((i as i32 - 30) * 70_001).to_le_bytes().to_vec())
                    .collect()),
                want: Voxels::F32((0..N).map(|i| ((i as i32 - 30) * 70_001) as f32).collect()),
            },
            TypeCase {
                name: "f32",
                nrrd: "float",
                nifti: (16, 32),
                metaimage: "MET_FLOAT",
                bytes: le((0..N)
                    .map(|i| (i as f32 * 0.25 - 3.3).to_le_bytes().to_vec())
                    .collect()),
                want: Voxels::F32((0..N).map(|i| i as f32 * 0.25 - 3.3).collect()),
            },
            TypeCase {
                // converted to the nearest float32
                name: "f64",
                nrrd: "double",
                nifti: (64, 64),
                metaimage: "MET_DOUBLE",
                bytes: le((0..N)
                    .map(|i| (i as f64 * 0.1 - 2.0).to_le_bytes().to_vec())
                    .collect()),
                want: Voxels::F32((0..N).map(|i| (i as f64 * 0.1 - 2.0) as f32).collect()),
            },
        ]
    }

    /// The cases' first sample replaced by NaN (float types only): (case, bytes).
    pub(crate) fn nan_cases() -> Vec<(TypeCase, Vec<u8>)> {
        cases()
            .into_iter()
            .filter(|c| c.name == "f32" || c.name == "f64")
            .map(|c| {
                let mut b = c.bytes.clone();
                // voxel 27 = (2, 1, 1) in a 5 x 4 x 3 volume
                if c.name == "f32" {
                    b[27 * 4..28 * 4].copy_from_slice(&f32::NAN.to_le_bytes());
                } else {
                    b[27 * 8..28 * 8].copy_from_slice(&f64::NAN.to_le_bytes());
                }
                (c, b)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_downsampling_done_is_read_back_from_the_name() {
        let v = phantom::head(8);
        assert_eq!(v.downsampled_by(), 1);
        let twice = v.downsample(2).downsample(3);
        assert_eq!(twice.downsampled_by(), 6);
        // by 2 then 3 is by 6 at once
        assert_eq!(twice.dims, v.downsample(6).dims);
        // Classified over the full volume's range, whose extremes averaging has narrowed, as
        // a crop of it is.
        assert_ne!(twice.own_value_range(), v.value_range());
        assert_eq!(twice.value_range(), v.value_range());
        let part = v.downsample(2).crop([1, 1, 1], [2, 2, 2]);
        assert_eq!(part.value_range(), v.value_range());
        assert_eq!(v.value_range(), v.own_value_range());
        let odd = Volume {
            name: "scan-dsx".into(),
            ..v.clone()
        };
        assert_eq!(odd.downsampled_by(), 1);
    }

    #[test]
    fn values_pick_int16_uint16_or_float32() {
        let p = Path::new("v.nii");
        let d = [2, 2, 1];
        let v = voxels_from_values(p, d, |i| i as f64 * 100.0 - 200.0).unwrap();
        assert_eq!(v, Voxels::I16(vec![-200, -100, 0, 100]));
        let v = voxels_from_values(p, d, |i| i as f64 * 20000.0).unwrap();
        assert_eq!(v, Voxels::U16(vec![0, 20000, 40000, 60000]));
        let v = voxels_from_values(p, d, |i| i as f64 * 30000.0 - 1.0).unwrap();
        assert_eq!(v, Voxels::F32(vec![-1.0, 29999.0, 59999.0, 89999.0]));
        let v = voxels_from_values(p, d, |i| i as f64 * 0.5).unwrap();
        assert_eq!(v, Voxels::F32(vec![0.0, 0.5, 1.0, 1.5]));
        assert_eq!(v.type_name(), "float32");
        assert_eq!(v.get(3), 1.5);
    }

    #[test]
    fn values_refuse_nan_and_infinities_naming_the_voxel() {
        let p = Path::new("dir/scan.nii");
        let d = [3, 2, 2];
        // linear index 10 = (1, 1, 1)
        for (bad, shown) in [
            (f64::NAN, "NaN"),
            (f64::INFINITY, "inf"),
            (f64::NEG_INFINITY, "-inf"),
            (1e300, "float32 range"),
        ] {
            let e = voxels_from_values(p, d, |i| if i == 10 { bad } else { 1.0 })
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("dir/scan.nii") && e.contains("voxel (1,1,1)") && e.contains(shown),
                "{e}"
            );
        }
    }

    #[test]
    fn crop_keeps_the_voxels_and_their_patient_positions() {
        let vol = Volume {
            whole_range: None,
            name: "v".into(),
            dims: [5, 4, 3],
            spacing: [0.5, 1.0, 2.0],
            directions: DMat3::from_rotation_z(0.4),
            origin: DVec3::new(10.0, -5.0, 3.0),
            modality: Modality::Ct,
            voxels: Voxels::I16((0..60).map(|i| i as i16 * 10 - 300).collect()),
            labels: None,
        };
        // The far corner is clamped to the volume.
        let c = vol.crop([1, 2, 1], [3, 9, 1]);
        assert_eq!(c.dims, [3, 2, 1]);
        assert_eq!(c.name, "v[1:4,2:4,1:2]");
        let lps = |v: &Volume, i: [usize; 3]| {
            v.origin
                + v.directions
                    * DVec3::from_array(std::array::from_fn(|a| i[a] as f64 * v.spacing[a]))
        };
        for (i, j, k) in [(0, 0, 0), (2, 1, 0), (1, 0, 0)] {
            let whole = vol.index(1 + i, 2 + j, 1 + k);
            assert_eq!(c.voxels.get(c.index(i, j, k)), vol.voxels.get(whole));
            let d = lps(&c, [i, j, k]) - lps(&vol, [1 + i, 2 + j, 1 + k]);
            assert!(d.length() < 1e-9, "{d}");
        }
    }

    #[test]
    fn downsample_averages_blocks_and_keeps_the_world_size() {
        let dims = [5, 4, 3];
        let dirs = DMat3::from_rotation_z(0.4);
        let vol = Volume {
            whole_range: None,
            name: "v".into(),
            dims,
            spacing: [0.5, 1.0, 2.0],
            directions: dirs,
            origin: DVec3::new(10.0, -5.0, 3.0),
            modality: Modality::Ct,
            voxels: Voxels::I16((0..60).map(|i| i as i16 * 10 - 300).collect()),
            labels: None,
        };
        let ds = vol.downsample(2);
        assert_eq!(ds.dims, [3, 2, 2]);
        assert_eq!(ds.spacing, [1.0, 2.0, 4.0]);
        assert_eq!(ds.directions, dirs);
        assert_eq!(ds.modality, Modality::Ct);
        assert_eq!(ds.name, "v-ds2");
        // origin: the centre of old voxels 0..1 along each axis = old origin + half a step
        let want = vol.origin + dirs * DVec3::new(0.25, 0.5, 1.0);
        assert!(ds.origin.abs_diff_eq(want, 1e-12), "{:?}", ds.origin);
        // the world size changes by less than one new voxel per axis
        let (a, b) = (vol.extent_mm(), ds.extent_mm());
        for ax in 0..3 {
            assert!((b[ax] - a[ax]).abs() < ds.spacing[ax], "{a:?} {b:?}");
        }
        // voxel (0,0,0) averages i 0..1, j 0..1, k 0..1: linear 0,1,5,6,20,21,25,26
        let mean = |idx: &[usize]| {
            idx.iter().map(|&i| i as f64 * 10.0 - 300.0).sum::<f64>() / idx.len() as f64
        };
        let Voxels::I16(v) = &ds.voxels else {
            panic!("type changed: {}", ds.voxels.type_name())
        };
        assert_eq!(v[0] as f64, mean(&[0, 1, 5, 6, 20, 21, 25, 26]).round());
        // voxel (2,1,1): the edge block holds only i 4, j 2..3, k 2
        assert_eq!(v[ds.index(2, 1, 1)] as f64, mean(&[54, 59]).round());
        // rounding of integer types: 1,2 -> 1.5 rounds to 2
        let mut small = vol.clone();
        small.dims = [2, 1, 1];
        small.voxels = Voxels::U8(vec![1, 2]);
        assert_eq!(small.downsample(2).voxels, Voxels::U8(vec![2]));
        small.voxels = Voxels::F32(vec![1.0, 2.0]);
        assert_eq!(small.downsample(2).voxels, Voxels::F32(vec![1.5]));
        small.voxels = Voxels::U16(vec![65535, 65535]);
        assert_eq!(small.downsample(4).voxels, Voxels::U16(vec![65535]));
        // n = 1: unchanged
        assert_eq!(vol.downsample(1).voxels, vol.voxels);
        assert_eq!(vol.downsample(1).dims, dims);
        // n beyond every side: one voxel, the mean of all
        let one = vol.downsample(10);
        assert_eq!(one.dims, [1, 1, 1]);
        assert_eq!(
            one.voxels.get(0) as f64,
            mean(&(0..60).collect::<Vec<_>>()).round()
        );
        // Labels go along, block by block, and a crop keeps its box's.
        let mut labelled = vol.clone();
        labelled.labels = Some(std::sync::Arc::new(labels::LabelMap {
            source: "seg".into(),
            ids: (0..60).map(|i| (i % 5 >= 3) as u8).collect(),
            structures: vec![labels::Structure {
                value: 1,
                name: "liver".into(),
                colour: [1.0, 0.0, 0.0],
                opacity: 1.0,
                protected: false,
                margin_mm: None,
                voxels: 24,
            }],
        }));
        let ds = labelled.downsample(2).labels.expect("the labels go along");
        assert_eq!(ds.ids, vec![0, 1, 1, 0, 1, 1, 0, 1, 1, 0, 1, 1]);
        let crop = labelled.crop([3, 0, 0], [2, 4, 3]).labels.expect("kept");
        assert_eq!(crop.ids, vec![1; 24]);
        assert_eq!(
            (ds.structures[0].voxels, crop.structures[0].voxels),
            (8, 24)
        );
    }

    #[test]
    fn value_range_of_float_and_empty_voxels() {
        let mut v = crate::volume::phantom::head(8);
        v.voxels = Voxels::F32((0..512).map(|i| i as f32 * 0.5 - 7.25).collect());
        assert_eq!(v.value_range(), (-7.25, 248.25));
        assert_eq!(v.clone_geometry().value_range(), (0.0, 0.0));
    }
}
