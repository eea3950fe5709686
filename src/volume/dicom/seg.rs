//! DICOM Segmentation objects (SEG, SOP class 1.2.840.10008.5.1.4.1.1.66.4), as PACS and
//! highdicom write them: binary (1 bit per pixel, frames packed back to back) or fractional
//! (8 bits, thresholded at half the maximum) segments, one frame per (segment, plane), placed
//! by the per-frame plane positions; segment labels and recommended display colours (CIELab).
//! Only the frames that hold a segment need be present: the planes are put on one regular grid
//! along the normal, from the lowest to the highest.

use super::{floats, int, open, text, tolerant};
use crate::volume::{labels, Modality, Volume, VolumeError, Voxels};
use dicom_dictionary_std::tags;
use dicom_object::{InMemDicomObject, Tag};
use glam::{DMat3, DVec3};
use std::collections::BTreeMap;
use std::path::Path;

/// Segmentation Storage.
pub const SEG_SOP_CLASS: &str = "1.2.840.10008.5.1.4.1.1.66.4";

/// A segmentation on its own grid: per voxel the number of the first segment there (0: none),
/// and per segment number its label and colour (linear RGB).
pub struct Segmentation {
    pub geometry: Volume,
    pub values: Vec<u32>,
    pub segments: BTreeMap<u32, (String, Option<[f32; 3]>)>,
}

/// Whether `path` is a DICOM file of the Segmentation Storage class (read from its meta header).
pub fn is_seg(path: &Path) -> bool {
    tolerant::sniff(path).is_some_and(|start| {
        open(path, start, tolerant::Until::PixelData, "header").is_ok_and(|o| {
            o.meta()
                .media_storage_sop_class_uid()
                .trim_end_matches('\0')
                == SEG_SOP_CLASS
        })
    })
}

/// Reads a DICOM SEG file.
pub fn read(path: &Path) -> Result<Segmentation, VolumeError> {
    let fmt = |m: String| VolumeError::format(path, m);
    let start = tolerant::sniff(path).ok_or_else(|| fmt("not a DICOM file".into()))?;
    let obj = open(path, start, tolerant::Until::End, "file")?;
    let class = obj
        .meta()
        .media_storage_sop_class_uid()
        .trim_end_matches('\0');
    if class != SEG_SOP_CLASS {
        return Err(fmt(format!(
            "not a DICOM segmentation (SOP class {class}, not {SEG_SOP_CLASS})"
        )));
    }
    let ts = obj.meta().transfer_syntax().trim_end_matches('\0').trim();
    if !["1.2.840.10008.1.2", "1.2.840.10008.1.2.1"].contains(&ts) {
        return Err(VolumeError::unsupported(
            path,
            format!("a segmentation in transfer syntax {ts} (only native little-endian is read)"),
        ));
    }
    let need = |tag: Tag, name: &str| int(&obj, tag).ok_or_else(|| fmt(format!("no {name}")));
    let (rows, cols) = (need(tags::ROWS, "Rows")?, need(tags::COLUMNS, "Columns")?);
    let frames = need(tags::NUMBER_OF_FRAMES, "NumberOfFrames")?;
    let bits = need(tags::BITS_ALLOCATED, "BitsAllocated")?;
    if rows <= 0 || cols <= 0 || frames <= 0 || !(bits == 1 || bits == 8) {
        return Err(fmt(format!(
            "{cols} x {rows} pixels, {frames} frames of {bits} bits (a segmentation has 1 or 8)"
        )));
    }
    let (rows, cols, frames) = (rows as usize, cols as usize, frames as usize);
    let fractional = text(&obj, tags::SEGMENTATION_TYPE).as_deref() == Some("FRACTIONAL");
    let max_fraction = int(&obj, tags::MAXIMUM_FRACTIONAL_VALUE)
        .unwrap_or(255)
        .max(1) as f64;

    let segments = segment_table(&obj);
    let per_frame = obj
        .get(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .filter(|i| i.len() == frames)
        .ok_or_else(|| {
            fmt(format!(
                "no per-frame functional groups for its {frames} frames"
            ))
        })?;
    let shared = obj
        .get(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .and_then(|i| i.first());
    // A functional group's value: the frame's own, else the shared one.
    let group = |item: &InMemDicomObject, seq: Tag, tag: Tag| -> Option<Vec<f64>> {
        [Some(item), shared].into_iter().flatten().find_map(|g| {
            let inner = g.get(seq)?.items()?.first()?;
            let v = inner.get(tag)?.to_multi_float64().ok()?;
            v.iter().all(|x| x.is_finite()).then_some(v)
        })
    };
    let first = &per_frame[0];
    let iop = group(
        first,
        tags::PLANE_ORIENTATION_SEQUENCE,
        tags::IMAGE_ORIENTATION_PATIENT,
    )
    .filter(|v| v.len() >= 6)
    .ok_or_else(|| fmt("no ImageOrientationPatient".into()))?;
    let spacing = group(first, tags::PIXEL_MEASURES_SEQUENCE, tags::PIXEL_SPACING)
        .filter(|v| v.len() >= 2 && v[0] > 0.0 && v[1] > 0.0)
        .ok_or_else(|| fmt("no PixelSpacing".into()))?;
    let (row_dir, col_dir) = (
        DVec3::new(iop[0], iop[1], iop[2]).normalize_or_zero(),
        DVec3::new(iop[3], iop[4], iop[5]).normalize_or_zero(),
    );
    let normal = row_dir.cross(col_dir);
    if normal.length() < 0.5 {
        return Err(fmt(format!("degenerate ImageOrientationPatient {iop:?}")));
    }
    // Each frame: its segment and its plane's position along the normal.
    let mut placed = Vec::with_capacity(frames);
    for (f, item) in per_frame.iter().enumerate() {
        let ipp = group(
            item,
            tags::PLANE_POSITION_SEQUENCE,
            tags::IMAGE_POSITION_PATIENT,
        )
        .filter(|v| v.len() >= 3)
        .ok_or_else(|| fmt(format!("frame {}: no ImagePositionPatient", f + 1)))?;
        let segment = item
            .get(tags::SEGMENT_IDENTIFICATION_SEQUENCE)
            .and_then(|e| e.items())
            .and_then(|i| i.first())
            .and_then(|s| int(s, tags::REFERENCED_SEGMENT_NUMBER))
            .filter(|&n| n > 0 && n <= u32::MAX as i64)
            .ok_or_else(|| fmt(format!("frame {}: no ReferencedSegmentNumber", f + 1)))?;
        let p = DVec3::new(ipp[0], ipp[1], ipp[2]);
        placed.push((segment as u32, p, p.dot(normal)));
    }
    // The planes on one grid: from the lowest position, spaced as the file says (or as the
    // smallest gap between distinct planes).
    let mut depths: Vec<f64> = placed.iter().map(|p| p.2).collect();
    depths.sort_by(f64::total_cmp);
    depths.dedup_by(|a, b| (*a - *b).abs() < 1e-3);
    let gap = depths
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(f64::INFINITY, f64::min);
    let step = group(
        first,
        tags::PIXEL_MEASURES_SEQUENCE,
        tags::SPACING_BETWEEN_SLICES,
    )
    .and_then(|v| v.first().copied())
    .filter(|&s| s > 0.0)
    .or(gap.is_finite().then_some(gap))
    .or_else(|| {
        group(first, tags::PIXEL_MEASURES_SEQUENCE, tags::SLICE_THICKNESS)
            .and_then(|v| v.first().copied())
    })
    .filter(|&s| s > 0.0)
    .unwrap_or(1.0);
    let lowest = placed
        .iter()
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .expect("at least one frame");
    let (origin, d0) = (lowest.1, lowest.2);
    let slices = ((depths.last().copied().unwrap_or(d0) - d0) / step).round() as usize + 1;
    if slices > 65_536 || slices * rows * cols > 1 << 31 {
        return Err(fmt(format!(
            "its planes span {slices} slices of {step} mm: too many for one grid"
        )));
    }
    let pixel = obj
        .get(tags::PIXEL_DATA)
        .ok_or_else(|| fmt("no PixelData".into()))?
        .to_bytes()
        .map_err(|e| fmt(format!("cannot read PixelData: {e}")))?;
    let per_frame_px = rows * cols;
    let need_bytes = if bits == 1 {
        (frames * per_frame_px).div_ceil(8)
    } else {
        frames * per_frame_px
    };
    if pixel.len() < need_bytes {
        return Err(fmt(format!(
            "{frames} frames of {cols} x {rows} pixels of {bits} bit(s) need {need_bytes} bytes of \
             PixelData, the file holds {}",
            pixel.len()
        )));
    }
    let set = |f: usize, i: usize| -> bool {
        let n = f * per_frame_px + i;
        if bits == 1 {
            // bits packed little-endian, frame after frame without padding
            (pixel[n / 8] >> (n % 8)) & 1 == 1
        } else if fractional {
            pixel[n] as f64 >= 0.5 * max_fraction
        } else {
            pixel[n] != 0
        }
    };
    // Each segment's size, so that the smaller wins where segments overlap.
    let mut size: BTreeMap<u32, usize> = BTreeMap::new();
    for (f, &(segment, _, _)) in placed.iter().enumerate() {
        *size.entry(segment).or_default() += (0..per_frame_px).filter(|&i| set(f, i)).count();
    }
    let mut values = vec![0u32; slices * per_frame_px];
    for (f, &(segment, p, d)) in placed.iter().enumerate() {
        let k = ((d - d0) / step).round() as usize;
        // a frame off the first frame's in-plane position would need its own grid
        let shift = p - origin - normal * (d - d0);
        if shift.length() > 0.01 * spacing[0].min(spacing[1]) + 1e-3 {
            return Err(VolumeError::unsupported(
                path,
                format!(
                    "frame {}: its plane is shifted in-plane from the others",
                    f + 1
                ),
            ));
        }
        let slice = &mut values[k * per_frame_px..(k + 1) * per_frame_px];
        for (i, v) in slice.iter_mut().enumerate() {
            if set(f, i)
                && (*v == 0 || labels::overlap_wins((size[&segment], segment), (size[v], *v)))
            {
                *v = segment;
            }
        }
    }
    let geometry = Volume {
        whole_range: None,
        name: path.display().to_string(),
        dims: [cols, rows, slices],
        // PixelSpacing is (between rows, between columns)
        spacing: [spacing[1], spacing[0], step],
        directions: DMat3::from_cols(row_dir, col_dir, normal),
        origin,
        modality: Modality::Unknown,
        voxels: Voxels::U8(Vec::new()),
        labels: None,
    };
    Ok(Segmentation {
        geometry,
        values,
        segments,
    })
}

/// Segment number -> (SegmentLabel, the recommended display colour in linear RGB).
fn segment_table(obj: &InMemDicomObject) -> BTreeMap<u32, (String, Option<[f32; 3]>)> {
    let mut out = BTreeMap::new();
    for s in obj
        .get(tags::SEGMENT_SEQUENCE)
        .and_then(|e| e.items())
        .unwrap_or(&[])
    {
        let Some(n) = int(s, tags::SEGMENT_NUMBER).filter(|&n| n > 0 && n <= u32::MAX as i64)
        else {
            continue;
        };
        let label = text(s, tags::SEGMENT_LABEL)
            .filter(|l| !l.is_empty())
            .unwrap_or_else(|| format!("segment {n}"));
        let colour = floats::<3>(s, tags::RECOMMENDED_DISPLAY_CIE_LAB_VALUE).map(lab_to_rgb);
        out.insert(n as u32, (label, colour));
    }
    out
}

/// DICOM's scaled CIELab (L 0..100, a and b −128..127, each mapped onto 0..65535; D65 white)
/// to linear RGB (sRGB primaries) in [0, 1].
pub fn lab_to_rgb(v: [f64; 3]) -> [f32; 3] {
    let l = v[0] / 65535.0 * 100.0;
    let a = v[1] / 65535.0 * 255.0 - 128.0;
    let b = v[2] / 65535.0 * 255.0 - 128.0;
    let fy = (l + 16.0) / 116.0;
    let (fx, fz) = (fy + a / 500.0, fy - b / 200.0);
    let inv = |t: f64| {
        if t > 6.0 / 29.0 {
            t * t * t
        } else {
            3.0 * (6.0f64 / 29.0).powi(2) * (t - 4.0 / 29.0)
        }
    };
    let (x, y, z) = (0.950_47 * inv(fx), inv(fy), 1.088_83 * inv(fz));
    let r = 3.240_454_2 * x - 1.537_138_5 * y - 0.498_531_4 * z;
    let g = -0.969_266 * x + 1.876_010_8 * y + 0.041_556 * z;
    let bl = 0.055_643_4 * x - 0.204_025_9 * y + 1.057_225_2 * z;
    [r, g, bl].map(|c| c.clamp(0.0, 1.0) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dicom_cielab_white_and_red_are_linear_rgb_white_and_red() {
        // L 100, a 0, b 0: white
        let white = lab_to_rgb([65535.0, 128.0 * 257.0, 128.0 * 257.0]);
        assert!(white.iter().all(|&c| c > 0.98), "{white:?}");
        // sRGB red (L 53.24, a 80.09, b 67.20)
        let red = lab_to_rgb([
            53.24 / 100.0 * 65535.0,
            (80.09 + 128.0) / 255.0 * 65535.0,
            (67.20 + 128.0) / 255.0 * 65535.0,
        ]);
        assert!(red[0] > 0.97 && red[1] < 0.03 && red[2] < 0.03, "{red:?}");
    }
}
