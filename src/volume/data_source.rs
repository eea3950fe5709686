//! Where a loader's samples come from, and the checks every format makes on them, with one
//! wording each: a detached data file resolved next to its header (multi-file lists and a
//! missing file refused, naming both files), truncation ("truncated data: expected N bytes,
//! found M", naming the file), a detached raw file longer than its header describes, a skip
//! that cannot be honoured, and the extent of a series' volumes. NRRD, NIfTI and MetaImage use
//! it, so bad input is told the same way in every format; and the one [`Volume`] a loader
//! returns ([`loaded_volume`]).

use super::{Modality, Volume, VolumeError, Voxels};
use glam::{DMat3, DVec3};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// The volume a loader read from `path`: named by the file's stem, `dims` voxels on the header's
/// `(spacing, directions, origin)` (LPS), no labels.
pub(crate) fn loaded_volume(
    path: &Path,
    dims: [u64; 3],
    geometry: ([f64; 3], DMat3, DVec3),
    modality: Modality,
    voxels: Voxels,
) -> Volume {
    let (spacing, directions, origin) = geometry;
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "volume".into());
    Volume {
        whole_range: None,
        name,
        dims: dims.map(|d| d as usize),
        spacing,
        directions,
        origin,
        modality,
        voxels,
        labels: None,
    }
}

/// The one truncation message: `what` prefixes it (the detached data file and the codec, e.g.
/// `data file x.raw: gzip `); `expected` and `found` count the bytes of the data proper.
pub(crate) fn truncated(path: &Path, what: &str, expected: u64, found: u64) -> VolumeError {
    VolumeError::format(
        path,
        format!("{what}truncated data: expected {expected} bytes, found {found}"),
    )
}

/// Bytes that `frames` volumes of `data_bytes` bytes each take, refused beyond what any file
/// can sensibly hold (64 times the largest volume read).
pub(crate) fn series_bytes(path: &Path, frames: u64, data_bytes: u64) -> Result<u64, VolumeError> {
    data_bytes
        .checked_mul(frames)
        .filter(|&b| b <= super::MAX_DATA_BYTES.saturating_mul(64))
        .ok_or_else(|| {
            VolumeError::format(
                path,
                format!("{frames} volumes of {data_bytes} bytes are too large"),
            )
        })
}

/// Where volume `frame` of a series of `data_bytes`-byte volumes begins, `base` bytes into the
/// data (the earlier volumes lie whole before it).
pub(crate) fn frame_offset(
    path: &Path,
    base: u64,
    frame: u64,
    data_bytes: u64,
) -> Result<u64, VolumeError> {
    frame
        .checked_mul(data_bytes)
        .and_then(|b| b.checked_add(base))
        .ok_or_else(|| {
            VolumeError::format(path, format!("volume #{frame} lies beyond any file size"))
        })
}

/// Where raw samples start after the header (or the start of a detached data file).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Skip {
    /// This many bytes further on (NRRD `byte skip`, MetaImage `HeaderSize`).
    Bytes(u64),
    /// The data are the file's last bytes (`byte skip: -1`, `HeaderSize = -1`).
    Tail,
}

/// How the header describes the samples, for the message on a detached raw file longer than
/// that: `shape` (e.g. `2 x 2 x 2 uint8`) and the header fields to blame (e.g. `sizes or type`).
pub(crate) struct Described<'a> {
    pub shape: String,
    pub fields: &'a str,
}

/// The file that holds a header's samples: the header itself (attached data) or a detached data
/// file. Errors name the header (the file the user gave) and, when detached, the data file.
#[derive(Clone, Debug)]
pub(crate) struct DataSource {
    header: PathBuf,
    detached: Option<PathBuf>,
}

impl DataSource {
    /// Samples that follow the header in `header` itself.
    pub(crate) fn attached(header: &Path) -> Self {
        DataSource {
            header: header.to_path_buf(),
            detached: None,
        }
    }

    /// The detached data file `name` (given in the header's field `field`, e.g. `data file:`),
    /// relative to the header's directory unless absolute, opened. A list or a pattern of
    /// several files is refused, as is a file that cannot be opened (naming both files).
    pub(crate) fn detached(
        header: &Path,
        field: &str,
        name: &str,
    ) -> Result<(Self, BufReader<File>), VolumeError> {
        let tokens: Vec<&str> = name.split_whitespace().collect();
        let list = tokens
            .first()
            .is_some_and(|t| t.eq_ignore_ascii_case("list"));
        if list || (tokens.len() >= 4 && tokens[0].contains('%')) {
            return Err(VolumeError::unsupported(
                header,
                format!("multi-file data (`{field} {name}`); only a single data file is read"),
            ));
        }
        let dp = Path::new(name);
        let dp = if dp.is_absolute() {
            dp.to_path_buf()
        } else {
            header.parent().unwrap_or(Path::new(".")).join(dp)
        };
        let f = File::open(&dp).map_err(|e| {
            VolumeError::format(
                header,
                format!("cannot open the detached data file {}: {e}", dp.display()),
            )
        })?;
        let source = DataSource {
            header: header.to_path_buf(),
            detached: Some(dp),
        };
        Ok((source, BufReader::new(f)))
    }

    /// The header (the file the user gave), which every error names.
    pub(crate) fn header(&self) -> &Path {
        &self.header
    }

    /// Whether the samples are in a file of their own.
    pub(crate) fn is_detached(&self) -> bool {
        self.detached.is_some()
    }

    /// The prefix of every data message, followed by `codec` (`"gzip "`, `"zlib "` or `""`):
    /// `data file x.raw: ` for detached data, nothing otherwise.
    pub(crate) fn what(&self, codec: &str) -> String {
        match &self.detached {
            Some(d) => format!("data file {}: {codec}", d.display()),
            None => codec.to_string(),
        }
    }

    /// A format error about the data.
    pub(crate) fn error(&self, msg: impl std::fmt::Display) -> VolumeError {
        VolumeError::format(&self.header, format!("{}{msg}", self.what("")))
    }

    /// A read error on the data.
    pub(crate) fn io_error(&self, e: std::io::Error) -> VolumeError {
        self.error(format_args!("read error: {e}"))
    }

    /// [`truncated`] for this source's data, read through `codec`.
    pub(crate) fn truncated(&self, codec: &str, expected: u64, found: u64) -> VolumeError {
        truncated(&self.header, &self.what(codec), expected, found)
    }

    /// Length of the (raw) file `file`.
    pub(crate) fn file_len(&self, file: &BufReader<File>) -> Result<u64, VolumeError> {
        Ok(file
            .get_ref()
            .metadata()
            .map_err(|e| self.io_error(e))?
            .len())
    }

    /// Moves `file` to byte `pos`.
    pub(crate) fn seek(&self, file: &mut BufReader<File>, pos: u64) -> Result<(), VolumeError> {
        file.seek(SeekFrom::Start(pos))
            .map_err(|e| self.io_error(e))?;
        Ok(())
    }

    /// Where `need` bytes of raw samples begin in `file`: `skip` after byte `start`, or the last
    /// `need` bytes. Refuses a file that ends before them (truncated) and a detached file that
    /// holds more than them (`described` says what the header claims), and leaves `file`
    /// wherever it was.
    pub(crate) fn locate_raw(
        &self,
        file: &BufReader<File>,
        start: u64,
        skip: Skip,
        need: u64,
        described: &Described,
    ) -> Result<u64, VolumeError> {
        let len = self.file_len(file)?;
        let begin = match skip {
            Skip::Tail => len
                .checked_sub(need)
                .filter(|&b| b >= start)
                .ok_or_else(|| self.truncated("", need, len.saturating_sub(start)))?,
            Skip::Bytes(b) => start.saturating_add(b),
        };
        let avail = len.saturating_sub(begin);
        if avail < need {
            return Err(self.truncated("", need, avail));
        }
        // A detached raw file holds the samples and nothing else: more bytes than the header
        // describes means its sizes or type are wrong. (Attached data may be followed by
        // anything; a tail skip takes the last bytes on purpose.)
        if self.is_detached() && skip != Skip::Tail && avail > need {
            return Err(self.error(format_args!(
                "{avail} bytes after the skips, but the header describes {need} ({}): wrong {}?",
                described.shape, described.fields
            )));
        }
        Ok(begin)
    }

    /// Skips `skip` bytes of the decoded stream `dec` (`codec`, e.g. `"gzip "`) before `need`
    /// bytes of samples: a stream that ends first is truncated (none of the samples found).
    pub(crate) fn skip_decoded(
        &self,
        dec: &mut dyn Read,
        codec: &str,
        skip: u64,
        need: u64,
    ) -> Result<(), VolumeError> {
        let skipped = std::io::copy(&mut dec.take(skip), &mut std::io::sink())
            .map_err(|e| self.error(format_args!("{codec}data are corrupt: {e}")))?;
        if skipped < skip {
            return Err(self.truncated(codec, need, 0));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::test_scratch::Scratch;

    fn described() -> Described<'static> {
        Described {
            shape: "2 x 2 x 2 uint8".into(),
            fields: "sizes or type",
        }
    }

    #[test]
    fn detached_files_resolve_next_to_the_header_and_missing_ones_name_both() {
        let s = Scratch::new("data-source");
        std::fs::write(s.file("d.raw"), [1u8, 2, 3]).unwrap();
        let header = s.file("h.nhdr");
        let (src, _) = DataSource::detached(&header, "data file:", "d.raw").unwrap();
        assert!(src.is_detached());
        assert!(src.what("gzip ").ends_with("d.raw: gzip "));
        let e = DataSource::detached(&header, "data file:", "gone.raw")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("h.nhdr") && e.contains("gone.raw") && e.contains("cannot open"),
            "{e}"
        );
        for list in ["LIST", "list", "d%03d.raw 0 9 1"] {
            let e = DataSource::detached(&header, "ElementDataFile =", list)
                .unwrap_err()
                .to_string();
            assert!(e.contains("unsupported: multi-file"), "{e}");
        }
    }

    #[test]
    fn raw_regions_are_checked_the_same_way() {
        let s = Scratch::new("data-source-raw");
        std::fs::write(s.file("d.raw"), [0u8; 10]).unwrap();
        let header = s.file("h.mhd");
        let (det, file) = DataSource::detached(&header, "ElementDataFile =", "d.raw").unwrap();
        let d = described();
        assert_eq!(det.locate_raw(&file, 0, Skip::Bytes(2), 8, &d).unwrap(), 2);
        assert_eq!(det.locate_raw(&file, 0, Skip::Tail, 4, &d).unwrap(), 6);
        let e = det.locate_raw(&file, 0, Skip::Bytes(4), 8, &d).unwrap_err();
        let e = e.to_string();
        assert!(
            e.contains("h.mhd")
                && e.contains("d.raw")
                && e.contains("truncated data: expected 8 bytes, found 6"),
            "{e}"
        );
        let e = det.locate_raw(&file, 4, Skip::Tail, 8, &d).unwrap_err();
        assert!(e.to_string().contains("expected 8 bytes, found 6"), "{e}");
        let e = det.locate_raw(&file, 0, Skip::Bytes(0), 8, &d).unwrap_err();
        let e = e.to_string();
        assert!(
            e.contains("10 bytes") && e.contains("describes 8") && e.contains("2 x 2 x 2 uint8"),
            "{e}"
        );
        // attached data may be followed by anything
        let att = DataSource::attached(&s.file("d.raw"));
        assert_eq!(att.locate_raw(&file, 0, Skip::Bytes(0), 8, &d).unwrap(), 0);
        // a decoded stream shorter than its skip
        let e = att
            .skip_decoded(&mut &[0u8; 3][..], "gzip ", 5, 8)
            .unwrap_err();
        assert!(
            e.to_string()
                .contains("gzip truncated data: expected 8 bytes, found 0"),
            "{e}"
        );
    }

    #[test]
    fn series_extents_are_checked() {
        let p = Path::new("s.nrrd");
        assert_eq!(series_bytes(p, 3, 8).unwrap(), 24);
        assert!(series_bytes(p, u64::MAX, 2)
            .unwrap_err()
            .to_string()
            .contains("too large"));
        assert_eq!(frame_offset(p, 352, 2, 10).unwrap(), 372);
        assert!(frame_offset(p, 1, u64::MAX, 2)
            .unwrap_err()
            .to_string()
            .contains("beyond any file size"));
    }
}
