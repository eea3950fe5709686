//! Headerless raw volumes: the caller supplies sizes, sample type, spacing and byte order.

use super::{checked_size, read_samples, Modality, SampleFormat, Volume, VolumeError};
use glam::{DMat3, DVec3};
use std::fs::File;
use std::io::{BufReader, Seek, SeekFrom};
use std::path::Path;

/// Sample type of a raw file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RawType {
    U8,
    U16,
    I16,
}

impl RawType {
    pub fn bytes(self) -> u64 {
        match self {
            RawType::U8 => 1,
            RawType::U16 | RawType::I16 => 2,
        }
    }
}

impl std::str::FromStr for RawType {
    type Err = String;
    /// `u8`/`uint8`, `u16`/`uint16`, `i16`/`int16` (case-insensitive).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "u8" | "uint8" => Ok(RawType::U8),
            "u16" | "uint16" => Ok(RawType::U16),
            "i16" | "int16" => Ok(RawType::I16),
            other => Err(format!(
                "unknown raw sample type {other:?} (expected u8|uint8, u16|uint16 or i16|int16)"
            )),
        }
    }
}

impl std::fmt::Display for RawType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RawType::U8 => "uint8",
            RawType::U16 => "uint16",
            RawType::I16 => "int16",
        })
    }
}

/// How to read a raw file: x varies fastest, then y, then z.
#[derive(Clone, Debug, PartialEq)]
pub struct RawSpec {
    pub dims: [usize; 3],
    pub ty: RawType,
    /// Millimetres between voxel centres along i, j, k.
    pub spacing: [f64; 3],
    pub big_endian: bool,
    /// Bytes to skip at the start of the file.
    pub header_bytes: u64,
}

/// Loads a headerless raw volume. The file must hold exactly `header_bytes` plus the samples.
/// Geometry: identity directions, zero origin; modality unknown.
pub fn load(path: &Path, spec: &RawSpec) -> Result<Volume, VolumeError> {
    let dims = spec.dims.map(|d| d as u64);
    let (_, data_bytes) = checked_size(path, dims, spec.ty.bytes())?;
    if spec.spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(VolumeError::format(
            path,
            format!("invalid spacing {:?} (must be positive)", spec.spacing),
        ));
    }
    let mut file = File::open(path).map_err(|e| VolumeError::io(path, e))?;
    let len = file.metadata().map_err(|e| VolumeError::io(path, e))?.len();
    let expected = spec.header_bytes.saturating_add(data_bytes);
    if len != expected {
        return Err(VolumeError::format(
            path,
            format!(
                "file is {len} bytes but {} x {} x {} {} samples{} need {expected} bytes ({})",
                dims[0],
                dims[1],
                dims[2],
                spec.ty,
                if spec.header_bytes > 0 {
                    format!(" after a {}-byte header", spec.header_bytes)
                } else {
                    String::new()
                },
                if len < expected {
                    "file too short"
                } else {
                    "file too long: trailing bytes"
                }
            ),
        ));
    }
    file.seek(SeekFrom::Start(spec.header_bytes))
        .map_err(|e| VolumeError::io(path, e))?;
    let format = match spec.ty {
        RawType::U8 => SampleFormat::U8,
        RawType::U16 => SampleFormat::U16,
        RawType::I16 => SampleFormat::I16,
    };
    let count = spec.dims.iter().product();
    let (voxels, got) = read_samples(
        &mut BufReader::new(file),
        format,
        count,
        spec.big_endian,
        true,
    )
    .map_err(|e| VolumeError::io(path, e))?;
    if got != data_bytes {
        return Err(VolumeError::format(
            path,
            format!(
                "file shrank while reading: expected {data_bytes} bytes of samples, read {got}"
            ),
        ));
    }
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "raw".into());
    Ok(Volume {
        whole_range: None,
        name,
        dims: spec.dims,
        spacing: spec.spacing,
        directions: DMat3::IDENTITY,
        origin: DVec3::ZERO,
        modality: Modality::Unknown,
        voxels,
        labels: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::Voxels;
    use std::path::PathBuf;

    fn temp(name: &str) -> PathBuf {
        use std::sync::atomic::{AtomicUsize, Ordering};
        static N: AtomicUsize = AtomicUsize::new(0);
        std::env::temp_dir().join(format!(
            "volcrate-raw-{}-{}-{name}",
            std::process::id(),
            N.fetch_add(1, Ordering::SeqCst)
        ))
    }

    #[test]
    fn parses_types() {
        assert_eq!("u8".parse::<RawType>(), Ok(RawType::U8));
        assert_eq!("UINT16".parse::<RawType>(), Ok(RawType::U16));
        assert_eq!("int16".parse::<RawType>(), Ok(RawType::I16));
        assert_eq!("i16".parse::<RawType>(), Ok(RawType::I16));
        assert!("f32".parse::<RawType>().unwrap_err().contains("f32"));
    }

    #[test]
    fn loads_all_types() {
        let spec = |ty, big_endian, header_bytes| RawSpec {
            dims: [3, 2, 2],
            ty,
            spacing: [0.5, 0.5, 2.0],
            big_endian,
            header_bytes,
        };
        let p = temp("u8.raw");
        let mut bytes = vec![0xAAu8; 5];
        bytes.extend(0u8..12);
        std::fs::write(&p, &bytes).unwrap();
        let v = load(&p, &spec(RawType::U8, false, 5)).unwrap();
        assert_eq!(v.voxels, Voxels::U8((0..12).collect()));
        assert_eq!(v.dims, [3, 2, 2]);
        assert_eq!(v.spacing, [0.5, 0.5, 2.0]);
        assert_eq!(v.directions, DMat3::IDENTITY);
        std::fs::remove_file(&p).unwrap();

        let vals: Vec<i16> = (0..12).map(|i| i * 1000 - 6000).collect();
        for big in [false, true] {
            let p = temp("i16.raw");
            let bytes: Vec<u8> = vals
                .iter()
                .flat_map(|v| {
                    if big {
                        v.to_be_bytes()
                    } else {
                        v.to_le_bytes()
                    }
                })
                .collect();
            std::fs::write(&p, &bytes).unwrap();
            let v = load(&p, &spec(RawType::I16, big, 0)).unwrap();
            assert_eq!(v.voxels, Voxels::I16(vals.clone()));
            let v = load(&p, &spec(RawType::U16, big, 0)).unwrap();
            assert_eq!(
                v.voxels,
                Voxels::U16(vals.iter().map(|&x| x as u16).collect())
            );
            std::fs::remove_file(&p).unwrap();
        }
    }

    #[test]
    fn wrong_size_errors() {
        let p = temp("short.raw");
        std::fs::write(&p, [0u8; 23]).unwrap();
        let spec = RawSpec {
            dims: [3, 2, 2],
            ty: RawType::U16,
            spacing: [1.0; 3],
            big_endian: false,
            header_bytes: 0,
        };
        let e = load(&p, &spec).unwrap_err().to_string();
        assert!(
            e.contains("short.raw") && e.contains("23") && e.contains("24"),
            "{e}"
        );
        std::fs::write(&p, [0u8; 25]).unwrap();
        let e = load(&p, &spec).unwrap_err().to_string();
        assert!(
            e.contains("25") && e.contains("24") && e.contains("trailing"),
            "{e}"
        );
        let e = load(
            &p,
            &RawSpec {
                header_bytes: 1,
                ..spec.clone()
            },
        )
        .map(|_| ());
        assert!(e.is_ok());
        let e = load(
            &p,
            &RawSpec {
                dims: [100000, 100000, 100000],
                ..spec.clone()
            },
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("too large"), "{e}");
        let e = load(
            &p,
            &RawSpec {
                spacing: [1.0, 0.0, 1.0],
                ..spec.clone()
            },
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("spacing"), "{e}");
        std::fs::remove_file(&p).unwrap();
        let e = load(&p, &spec).unwrap_err().to_string();
        assert!(e.contains("short.raw"), "{e}");
    }
}
