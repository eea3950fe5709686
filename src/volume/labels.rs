//! Label maps: segmentations (TotalSegmentator, 3D Slicer, ITK-SNAP) resampled into a volume's
//! grid by the physical position of each voxel, and how each structure is shown.
//!
//! L(v) is the label at the LPS centre of volume voxel v, taken from the label map's voxel whose
//! centre is nearest in the label map's own index space (its directions and spacing applied,
//! never by index alone); outside the label map L = 0 (unlabelled). See docs/design.md.

use super::distance::MarginField;
use super::{dicom, nifti, nrrd, Volume, VolumeError};
use glam::{DMat3, DVec3};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

/// Structures a label map may hold: ids are one byte per voxel, 0 unlabelled.
pub const MAX_STRUCTURES: usize = 255;

/// One labelled structure.
#[derive(Clone, Debug, PartialEq)]
pub struct Structure {
    /// Its value in the file (a multi-label map's label value, a Slicer segment's LabelValue, a
    /// mask file's position in the folder).
    pub value: u32,
    pub name: String,
    /// Linear RGB in [0, 1].
    pub colour: [f32; 3],
    /// The opacity a_l its voxels' TF opacity is multiplied by (0: hidden, 1: shown).
    pub opacity: f32,
    /// Whether tools leave it standing (`--protect`).
    pub protected: bool,
    /// The safety margin in mm a tool is warned at (`--margin NAME=MM`).
    pub margin_mm: Option<f32>,
    /// Its voxels in the volume's grid.
    pub voxels: usize,
}

/// A label map in a volume's grid.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelMap {
    /// Where it came from (shown by `info`).
    pub source: String,
    /// Per volume voxel (x fastest): 1 + the index of its structure, 0 = unlabelled.
    pub ids: Vec<u8>,
    pub structures: Vec<Structure>,
}

/// The 256-bit set of ids (bit id = structure index + 1) of the structures `protected` marks, as
/// the clip shaders and the ray caster read it.
pub fn protected_bits(protected: &[bool]) -> [u32; 8] {
    let mut bits = [0u32; 8];
    for (k, _) in protected
        .iter()
        .enumerate()
        .filter(|(_, p)| **p)
        .take(MAX_STRUCTURES)
    {
        let id = k + 1;
        bits[id / 32] |= 1 << (id % 32);
    }
    bits
}

impl LabelMap {
    /// The opacity factor of voxel `i`: 1 unlabelled, else its structure's a_l.
    pub fn factor(&self, i: usize) -> f32 {
        self.factor_showing(i, &[])
    }

    /// [`LabelMap::factor`] with the structures' opacities `shown` (by structure index; past
    /// its end, the structure's own).
    pub fn factor_showing(&self, i: usize, shown: &[f32]) -> f32 {
        match self.ids[i] as usize {
            0 => 1.0,
            id => shown
                .get(id - 1)
                .copied()
                .unwrap_or(self.structures[id - 1].opacity),
        }
    }

    /// The map of a volume of `dims` averaged over n x n x n blocks ([`Volume::downsample`]):
    /// each block's id is the one most of its voxels hold, a structure before the unlabelled
    /// and the first structure among structures with as many (the voxel-count vote
    /// label-map pyramids take, so that no id is made up between two structures); the
    /// structures' voxel counts are the new grid's.
    pub fn downsample(&self, dims: [usize; 3], n: usize) -> LabelMap {
        let nd = dims.map(|x| x.div_ceil(n));
        let slice = nd[0] * nd[1];
        let mut ids = vec![0u8; slice * nd[2]];
        ids.par_chunks_mut(slice).enumerate().for_each(|(kk, out)| {
            let mut votes = [0u32; 256];
            for jj in 0..nd[1] {
                for ii in 0..nd[0] {
                    votes.fill(0);
                    for k in kk * n..((kk + 1) * n).min(dims[2]) {
                        for j in jj * n..((jj + 1) * n).min(dims[1]) {
                            let row = dims[0] * (j + dims[1] * k);
                            for i in ii * n..((ii + 1) * n).min(dims[0]) {
                                votes[self.ids[row + i] as usize] += 1;
                            }
                        }
                    }
                    // The first structure with the most votes; the unlabelled only where it
                    // has more than every structure.
                    let (best, most) = votes[1..].iter().enumerate().fold((0, 0), |b, (k, &v)| {
                        if v > b.1 {
                            (k + 1, v)
                        } else {
                            b
                        }
                    });
                    out[ii + nd[0] * jj] = if votes[0] > most { 0 } else { best as u8 };
                }
            }
        });
        self.with_ids(ids)
    }

    /// The map of the box `lo .. lo + size` of a volume of `dims` ([`Volume::crop`]; the box
    /// within the volume), its structures' voxel counts the box's.
    pub fn crop(&self, dims: [usize; 3], lo: [usize; 3], size: [usize; 3]) -> LabelMap {
        let mut ids = Vec::with_capacity(size.iter().product());
        for k in lo[2]..lo[2] + size[2] {
            for j in lo[1]..lo[1] + size[1] {
                let row = lo[0] + dims[0] * (j + dims[1] * k);
                ids.extend_from_slice(&self.ids[row..row + size[0]]);
            }
        }
        self.with_ids(ids)
    }

    /// These structures over `ids`, counted there.
    fn with_ids(&self, ids: Vec<u8>) -> LabelMap {
        let mut map = LabelMap {
            source: self.source.clone(),
            ids,
            structures: self.structures.clone(),
        };
        map.count_voxels();
        map
    }

    /// Sets every structure's voxel count from the ids.
    fn count_voxels(&mut self) {
        let mut counts = vec![0usize; self.structures.len() + 1];
        for &id in &self.ids {
            counts[id as usize] += 1;
        }
        for (k, s) in self.structures.iter_mut().enumerate() {
            s.voxels = counts[k + 1];
        }
    }

    /// Every structure's opacity a_l, by structure index.
    pub fn opacities(&self) -> Vec<f32> {
        self.structures.iter().map(|s| s.opacity).collect()
    }

    /// Whether any structure is protected from the tools.
    pub fn any_protected(&self) -> bool {
        self.structures.iter().any(|s| s.protected)
    }

    /// The 256-bit set of protected ids (bit id), as the clip shaders read it.
    pub fn protected_bits(&self) -> [u32; 8] {
        protected_bits(&self.protected())
    }

    /// Whether each structure is protected, by structure index.
    pub fn protected(&self) -> Vec<bool> {
        self.structures.iter().map(|s| s.protected).collect()
    }

    /// The structure called `name` (case and `-`/`_`/space insensitive), or an error listing them.
    pub fn find(&self, name: &str) -> Result<usize, String> {
        let norm = |s: &str| s.to_lowercase().replace(['-', ' '], "_");
        let want = norm(name);
        self.structures
            .iter()
            .position(|s| norm(&s.name) == want || s.value.to_string() == want)
            .ok_or_else(|| {
                let names: Vec<&str> = self.structures.iter().map(|s| s.name.as_str()).collect();
                format!(
                    "no structure '{name}' in the label map {} (it has: {})",
                    self.source,
                    names.join(", ")
                )
            })
    }

    /// Applies `--show`, `--hide`, `--opacity NAME=A` and `--protect` (names as [`find`]). With
    /// `show` given, every structure it does not name is hidden.
    ///
    /// [`find`]: LabelMap::find
    pub fn apply(&mut self, d: &LabelDisplay) -> Result<(), String> {
        if !d.show.is_empty() {
            let shown: Vec<usize> = d
                .show
                .iter()
                .map(|n| self.find(n))
                .collect::<Result<_, _>>()?;
            for (k, s) in self.structures.iter_mut().enumerate() {
                s.opacity = if shown.contains(&k) { 1.0 } else { 0.0 };
            }
        }
        for n in &d.hide {
            let k = self.find(n)?;
            self.structures[k].opacity = 0.0;
        }
        for spec in &d.opacity {
            let (k, a) = self.named_value(spec, "--opacity", "liver=0.3", 0.0..=1.0)?;
            self.structures[k].opacity = a;
        }
        for n in &d.protect {
            let k = self.find(n)?;
            self.structures[k].protected = true;
        }
        for spec in &d.margin {
            let (k, m) = self.named_value(spec, "--margin", "aorta=5", 0.0..=100.0)?;
            if m <= 0.0 {
                return Err(format!(
                    "--margin {spec}: the margin must be more than 0 mm"
                ));
            }
            self.structures[k].margin_mm = Some(m);
        }
        Ok(())
    }

    /// The structure and the number of a `NAME=VALUE` option (`flag` and an `example` for its
    /// messages), the number within `range`.
    fn named_value(
        &self,
        spec: &str,
        flag: &str,
        example: &str,
        range: std::ops::RangeInclusive<f32>,
    ) -> Result<(usize, f32), String> {
        let (n, v) = spec
            .rsplit_once('=')
            .ok_or_else(|| format!("{flag} {spec}: expected NAME=VALUE, e.g. {example}"))?;
        let v: f32 = v
            .trim()
            .parse()
            .ok()
            .filter(|v| range.contains(v))
            .ok_or_else(|| {
                format!(
                    "{flag} {spec}: the value must be a number in {}..{}",
                    range.start(),
                    range.end()
                )
            })?;
        Ok((self.find(n.trim())?, v))
    }

    /// The distance fields of the structures that carry a margin, in a grid of `dims` and
    /// `spacing` (the volume's): what [`crate::clip::margin`] checks the tools against.
    pub fn margin_fields(&self, dims: [usize; 3], spacing: [f64; 3]) -> Vec<MarginField> {
        self.structures
            .iter()
            .enumerate()
            .filter_map(|(k, s)| {
                let m = s.margin_mm?;
                MarginField::new(&self.ids, k as u8 + 1, dims, spacing, k, m)
            })
            .collect()
    }

    /// `info`'s table: value, name, colour, voxel count, volume in ml, and how it is shown.
    pub fn report(&self, spacing: [f64; 3]) -> String {
        let ml_per_voxel = spacing[0] * spacing[1] * spacing[2] / 1000.0;
        let mut s = format!(
            "labels {} ({} structures)\n  value  name                              colour    voxels      ml  shown\n",
            self.source,
            self.structures.len()
        );
        for st in &self.structures {
            let c = st.colour.map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8);
            s.push_str(&format!(
                "  {:>5}  {:<32}  #{:02x}{:02x}{:02x}  {:>8}  {:>8.2}  {}{}\n",
                st.value,
                st.name,
                c[0],
                c[1],
                c[2],
                st.voxels,
                st.voxels as f64 * ml_per_voxel,
                shown_as(st.opacity),
                if st.protected { ", protected" } else { "" }
            ));
            if let Some(m) = st.margin_mm {
                s.truncate(s.len() - 1);
                s.push_str(&format!(", margin {m} mm\n"));
            }
        }
        s
    }
}

/// How a structure of opacity `a` is shown, in words: "shown", "hidden" or the opacity.
pub fn shown_as(a: f32) -> String {
    match a {
        a if a <= 0.0 => "hidden".to_string(),
        a if a >= 1.0 => "shown".to_string(),
        a => format!("{a:.2}"),
    }
}

/// How the structures are shown, from the command line.
#[derive(Clone, Debug, Default)]
pub struct LabelDisplay {
    pub show: Vec<String>,
    pub hide: Vec<String>,
    pub opacity: Vec<String>,
    pub protect: Vec<String>,
    /// NAME=MM safety margins.
    pub margin: Vec<String>,
}

/// Structure names, and colours where the file gives them, by label value.
type Names = BTreeMap<u32, (String, Option<[f32; 3]>)>;

/// A label map as read, on its own grid: per voxel a label value, and what the file says of
/// its structures (name and colour by value).
struct Source {
    geometry: Volume,
    values: Vec<u32>,
    named: Names,
}

/// Reads the label map at `path` (a multi-label NIfTI or NRRD, a Slicer `.seg.nrrd`, or a folder
/// of one binary NIfTI mask per structure), names its structures (`names`: an ITK-SNAP label
/// description or a colour table; else the file's own; else TotalSegmentator's class table for
/// 117 or fewer labels; else "label N"), and resamples it into `vol`'s grid.
pub fn load(path: &Path, names: Option<&Path>, vol: &Volume) -> Result<LabelMap, VolumeError> {
    let mut src = match find_seg(path)? {
        Some(seg) => read_seg(&seg)?,
        None if path.is_dir() => read_mask_folder(path)?,
        None => read_label_file(path)?,
    };
    if let Some(n) = names {
        for (value, entry) in read_names(n)? {
            src.named.insert(value, entry);
        }
    }
    let mut values: Vec<u32> = {
        let mut seen = std::collections::BTreeSet::new();
        for &v in &src.values {
            if v != 0 {
                seen.insert(v);
            }
        }
        seen.into_iter().collect()
    };
    values.extend(src.named.keys().filter(|v| **v != 0));
    values.sort_unstable();
    values.dedup();
    if values.len() > MAX_STRUCTURES {
        return Err(VolumeError::unsupported(
            path,
            format!(
                "{} structures; at most {MAX_STRUCTURES} are shown at once",
                values.len()
            ),
        ));
    }
    let total_seg = src.named.is_empty() && values.last().is_some_and(|&m| m <= 117);
    let structures: Vec<Structure> = values
        .iter()
        .enumerate()
        .map(|(k, &value)| {
            let (name, colour) = match src.named.get(&value) {
                Some((n, c)) => (n.clone(), *c),
                None if total_seg => (TOTALSEGMENTATOR[value as usize - 1].to_string(), None),
                None => (format!("label {value}"), None),
            };
            Structure {
                value,
                name,
                colour: colour.unwrap_or_else(|| palette(k)),
                opacity: 1.0,
                protected: false,
                margin_mm: None,
                voxels: 0,
            }
        })
        .collect();
    let id_of: BTreeMap<u32, u8> = values
        .iter()
        .enumerate()
        .map(|(k, &v)| (v, k as u8 + 1))
        .collect();
    let ids = resample(&src.geometry, &src.values, vol, &|v| {
        if v == 0 {
            0
        } else {
            id_of[&v]
        }
    })
    .map_err(|m| VolumeError::format(path, m))?;
    let mut map = LabelMap {
        source: path.display().to_string(),
        ids,
        structures,
    };
    map.count_voxels();
    Ok(map)
}

/// LPS (mm) of the centre of voxel `index` of `g`.
fn lps(g: &Volume, index: DVec3) -> DVec3 {
    g.origin + g.directions * (index * DVec3::from_array(g.spacing))
}

/// Per voxel of `vol`, `id(L)` of the label `values` (on `src`'s grid) nearest its centre; an
/// error naming both extents when no voxel of `vol` lies inside the label map.
fn resample(
    src: &Volume,
    values: &[u32],
    vol: &Volume,
    id: &(dyn Fn(u32) -> u8 + Sync),
) -> Result<Vec<u8>, String> {
    let m = src.directions * DMat3::from_diagonal(DVec3::from_array(src.spacing));
    if m.determinant().abs() < 1e-12 {
        return Err("the label map's directions or spacing are degenerate".into());
    }
    // Refused before any voxel is resampled: the two boxes must meet.
    let (a, b) = (lps_box(vol), lps_box(src));
    if !(0..3).all(|k| a.0[k] < b.1[k] && b.0[k] < a.1[k]) {
        let f = |(lo, hi): (DVec3, DVec3)| {
            format!(
                "({:.1}, {:.1}, {:.1}) to ({:.1}, {:.1}, {:.1}) mm LPS",
                lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
            )
        };
        return Err(format!(
            "the label map does not overlap the volume: the label map spans {}, the volume {}",
            f(b),
            f(a)
        ));
    }
    let inv = m.inverse();
    let sd = src.dims;
    let row = vol.dims[0];
    let slice = row * vol.dims[1];
    Ok((0..vol.voxel_count())
        .into_par_iter()
        .map(|i| {
            let p = DVec3::new(
                (i % row) as f64,
                ((i / row) % vol.dims[1]) as f64,
                (i / slice) as f64,
            );
            let n = (inv * (lps(vol, p) - src.origin)).round();
            let inside = (0..3).all(|a| n[a] >= 0.0 && n[a] < sd[a] as f64);
            if !inside {
                return 0;
            }
            let (x, y, z) = (n.x as usize, n.y as usize, n.z as usize);
            id(values[x + sd[0] * (y + sd[1] * z)])
        })
        .collect())
}

/// The LPS bounding box (mm) of `g`'s voxels, their outer faces included.
fn lps_box(g: &Volume) -> (DVec3, DVec3) {
    let mut lo = DVec3::splat(f64::MAX);
    let mut hi = DVec3::splat(f64::MIN);
    for c in 0..8 {
        let corner = DVec3::from_array(std::array::from_fn(|a| {
            if c & (1 << a) == 0 {
                -0.5
            } else {
                g.dims[a] as f64 - 0.5
            }
        }));
        let p = lps(g, corner);
        lo = lo.min(p);
        hi = hi.max(p);
    }
    (lo, hi)
}

/// A label value per voxel from a volume's stored values (rounded; negatives are unlabelled).
fn label_values(v: &Volume) -> Vec<u32> {
    (0..v.voxel_count())
        .into_par_iter()
        .map(|i| {
            let x = v.voxels.get(i).round();
            if x > 0.0 {
                x as u32
            } else {
                0
            }
        })
        .collect()
}

/// The DICOM SEG at `path`, or the one in the folder `path` (a series folder with its
/// segmentation beside the images); None when there is none. Several in one folder are
/// refused with their names.
fn find_seg(path: &Path) -> Result<Option<std::path::PathBuf>, VolumeError> {
    if !path.is_dir() {
        return Ok(dicom::seg::is_seg(path).then(|| path.to_path_buf()));
    }
    let mut found: Vec<_> = std::fs::read_dir(path)
        .map_err(|e| VolumeError::io(path, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && dicom::seg::is_seg(p))
        .collect();
    found.sort();
    match found.len() {
        0 | 1 => Ok(found.pop()),
        _ => Err(VolumeError::unsupported(
            path,
            format!(
                "{} DICOM segmentations in one folder ({}): give one with --labels FILE",
                found.len(),
                found
                    .iter()
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        )),
    }
}

/// A DICOM SEG: its segment numbers as label values, named and coloured by its segment table.
fn read_seg(path: &Path) -> Result<Source, VolumeError> {
    let s = dicom::seg::read(path)?;
    Ok(Source {
        geometry: s.geometry,
        values: s.values,
        named: s.segments,
    })
}

/// A multi-label NIfTI or NRRD (a `.seg.nrrd` with its segments' names, colours and values).
fn read_label_file(path: &Path) -> Result<Source, VolumeError> {
    let lower = path.to_string_lossy().to_lowercase();
    let geometry = if lower.ends_with(".nii") || lower.ends_with(".nii.gz") {
        nifti::load(path)?
    } else if lower.ends_with(".nrrd") || lower.ends_with(".nhdr") {
        let mut layers = nrrd::load_all(path)?;
        let segments = slicer_segments(path)?;
        if let Some(s) = segments.iter().find(|s| s.layer >= layers.len()) {
            return Err(VolumeError::format(
                path,
                format!(
                    "{} is on layer {}, but the file holds {} layer(s)",
                    s.name,
                    s.layer,
                    layers.len()
                ),
            ));
        }
        if layers.len() > 1 {
            return Ok(combine_layers(layers, segments));
        }
        let named = segments
            .into_iter()
            .map(|s| (s.value, (s.name, s.colour)))
            .collect();
        let geometry = layers.remove(0);
        let values = label_values(&geometry);
        return Ok(Source {
            geometry,
            values,
            named,
        });
    } else {
        return Err(VolumeError::unsupported(
            path,
            "a label map is a .nii, .nii.gz, .nrrd or .seg.nrrd file, or a folder of NIfTI masks",
        ));
    };
    let values = label_values(&geometry);
    Ok(Source {
        geometry,
        values,
        named: BTreeMap::new(),
    })
}

/// One segment of a 3D Slicer segmentation: its layer, its value within that layer, its name
/// and colour.
struct Segment {
    layer: usize,
    value: u32,
    name: String,
    colour: Option<[f32; 3]>,
}

/// A 3D Slicer segmentation of several layers (segments that overlap, written as a 4-D file
/// whose first axis is the layer) as one label per voxel. Each segment keeps its value unless
/// a segment of another layer has the same value, when it takes the smallest free one. Where
/// segments overlap, the one of fewer voxels wins: a tumour inside the liver, a vessel through
/// it, stays itself (the larger keeps everything else).
/// Every segment's layer is one of `layers`.
fn combine_layers(mut layers: Vec<Volume>, segments: Vec<Segment>) -> Source {
    let per_layer: Vec<Vec<u32>> = layers.iter().map(label_values).collect();
    let clash = |s: &Segment| {
        segments
            .iter()
            .any(|o| o.layer != s.layer && o.value == s.value)
    };
    let mut taken: std::collections::BTreeSet<u32> = segments
        .iter()
        .filter(|s| !clash(s))
        .map(|s| s.value)
        .collect();
    let renumbered: Vec<(usize, u32)> = (0..segments.len())
        .map(|k| {
            if !clash(&segments[k]) {
                return (k, segments[k].value);
            }
            let free = (1..).find(|v| !taken.contains(v)).expect("a free value");
            taken.insert(free);
            (k, free)
        })
        .collect();
    let count = |s: &Segment| {
        per_layer[s.layer]
            .par_iter()
            .filter(|&&v| v == s.value)
            .count()
    };
    let size: BTreeMap<u32, usize> = renumbered
        .iter()
        .map(|&(k, v)| (v, count(&segments[k])))
        .collect();
    let mut values = vec![0u32; per_layer[0].len()];
    for &(k, new) in &renumbered {
        let s = &segments[k];
        values
            .par_iter_mut()
            .zip(&per_layer[s.layer])
            .filter(|(_, &v)| v == s.value)
            .for_each(|(out, _)| {
                if *out == 0 || overlap_wins((size[&new], new), (size[out], *out)) {
                    *out = new;
                }
            });
    }
    let named = renumbered
        .iter()
        .map(|&(k, v)| (v, (segments[k].name.clone(), segments[k].colour)))
        .collect();
    Source {
        geometry: layers.swap_remove(0),
        values,
        named,
    }
}

/// The `SegmentN_Name`, `SegmentN_Color`, `SegmentN_LabelValue` and `SegmentN_Layer` fields of
/// a 3D Slicer segmentation header (nothing for a plain NRRD).
fn slicer_segments(path: &Path) -> Result<Vec<Segment>, VolumeError> {
    use std::io::BufRead;
    let file = std::fs::File::open(path).map_err(|e| VolumeError::io(path, e))?;
    let mut fields: BTreeMap<usize, BTreeMap<String, String>> = BTreeMap::new();
    for line in std::io::BufReader::new(file).split(b'\n').take(100_000) {
        let line = line.map_err(|e| VolumeError::io(path, e))?;
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_end_matches('\r');
        if text.trim().is_empty() {
            break;
        }
        let Some((key, value)) = text.split_once(":=") else {
            continue;
        };
        let Some(rest) = key.strip_prefix("Segment") else {
            continue;
        };
        let Some((n, field)) = rest.split_once('_') else {
            continue;
        };
        if let Ok(n) = n.parse::<usize>() {
            fields
                .entry(n)
                .or_default()
                .insert(field.to_string(), value.trim().to_string());
        }
    }
    let mut segments = Vec::new();
    for (n, f) in &fields {
        let bad = |m: String| VolumeError::format(path, format!("Segment{n}: {m}"));
        let layer = match f.get("Layer") {
            Some(l) => l
                .parse::<usize>()
                .map_err(|_| bad(format!("Layer {l:?} is not a layer number")))?,
            None => 0,
        };
        let value = match f.get("LabelValue") {
            Some(v) => v
                .parse::<u32>()
                .map_err(|_| bad(format!("LabelValue {v:?} is not a label value")))?,
            None => *n as u32 + 1,
        };
        let name = f
            .get("Name")
            .cloned()
            .unwrap_or_else(|| format!("Segment{n}"));
        let colour = match f.get("Color") {
            None => None,
            Some(c) => {
                let v: Vec<f32> = c
                    .split_whitespace()
                    .filter_map(|x| x.parse().ok())
                    .collect();
                match v[..] {
                    [r, g, b] => Some([r, g, b]),
                    _ => return Err(bad(format!("Color {c:?} is not three numbers"))),
                }
            }
        };
        segments.push(Segment {
            layer,
            value,
            name,
            colour,
        });
    }
    Ok(segments)
}

/// Where two structures claim a voxel, whether `a` keeps it from `b`, each given as (voxel
/// count, label value): the smaller structure wins, so a tumour or a vessel inside an organ
/// stays itself (the organ keeps the rest); of two equal ones, the lower value. Every format
/// that can overlap resolves it so (a mask folder, a layered `.seg.nrrd`, a DICOM SEG).
pub(crate) fn overlap_wins(a: (usize, u32), b: (usize, u32)) -> bool {
    a < b
}

/// A folder of binary NIfTI masks (TotalSegmentator's default output): each file one
/// structure, named by the file, numbered in name order; where masks overlap, the smaller wins
/// ([`overlap_wins`]).
fn read_mask_folder(dir: &Path) -> Result<Source, VolumeError> {
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .map_err(|e| VolumeError::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let l = p.to_string_lossy().to_lowercase();
            l.ends_with(".nii") || l.ends_with(".nii.gz")
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(VolumeError::format(
            dir,
            "no .nii or .nii.gz masks in this folder",
        ));
    }
    let mut geometry: Option<Volume> = None;
    let mut values: Vec<u32> = Vec::new();
    let mut named = BTreeMap::new();
    // Each mask's size, for the overlaps (a mask is compared only with earlier ones, whose
    // sizes are known by then, so the masks need not all be held at once).
    let mut size: Vec<usize> = vec![0];
    for (k, f) in files.iter().enumerate() {
        let mask = nifti::load(f)?;
        let g = geometry.get_or_insert_with(|| mask.clone_geometry());
        let same = g.dims == mask.dims
            && (0..3).all(|a| (g.spacing[a] - mask.spacing[a]).abs() < 1e-4)
            && (g.origin - mask.origin).abs().max_element() < 1e-3
            && (g.directions - mask.directions)
                .to_cols_array()
                .iter()
                .all(|x| x.abs() < 1e-5);
        if !same {
            return Err(VolumeError::format(
                f,
                format!(
                    "its grid ({} x {} x {}) differs from {}'s: the masks of one folder share a grid",
                    mask.dims[0],
                    mask.dims[1],
                    mask.dims[2],
                    files[0].display()
                ),
            ));
        }
        if values.is_empty() {
            values = vec![0; mask.voxel_count()];
        }
        let value = k as u32 + 1;
        let inside = |i: usize| mask.voxels.get(i) >= 0.5;
        let n = (0..mask.voxel_count()).filter(|&i| inside(i)).count();
        size.push(n);
        for (i, v) in values.iter_mut().enumerate() {
            if inside(i) && (*v == 0 || overlap_wins((n, value), (size[*v as usize], *v))) {
                *v = value;
            }
        }
        let name = f
            .file_name()
            .and_then(|n| n.to_str())
            .map(|n| {
                n.trim_end_matches(".gz")
                    .trim_end_matches(".nii")
                    .to_string()
            })
            .unwrap_or_default();
        named.insert(value, (name, None));
    }
    Ok(Source {
        geometry: geometry.expect("at least one mask"),
        values,
        named,
    })
}

/// Names (and colours) by label value from an ITK-SNAP label description file
/// (`IDX R G B A VIS MSH "LABEL"`, colours 0..255) or a 3D Slicer colour table
/// (`VALUE NAME R G B A`).
fn read_names(path: &Path) -> Result<Names, VolumeError> {
    let text = std::fs::read_to_string(path).map_err(|e| VolumeError::io(path, e))?;
    let mut out = BTreeMap::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = || {
            VolumeError::format(
                path,
                format!(
                    "line {}: expected `VALUE R G B A VIS MSH \"NAME\"` (ITK-SNAP) or \
                     `VALUE NAME R G B A` (Slicer colour table), got {line:?}",
                    n + 1
                ),
            )
        };
        let (head, quoted) = match line.split_once('"') {
            Some((h, q)) => (h, Some(q.trim_end().trim_end_matches('"').to_string())),
            None => (line, None),
        };
        let words: Vec<&str> = head.split_whitespace().collect();
        let num = |s: &str| s.parse::<f32>().map_err(|_| bad());
        let value: u32 = words.first().and_then(|w| w.parse().ok()).ok_or_else(bad)?;
        let (name, rgb) = match quoted {
            Some(name) if words.len() >= 4 => {
                (name, [num(words[1])?, num(words[2])?, num(words[3])?])
            }
            None if words.len() >= 5 => (
                words[1].to_string(),
                [num(words[2])?, num(words[3])?, num(words[4])?],
            ),
            _ => return Err(bad()),
        };
        if value != 0 {
            out.insert(value, (name, Some(rgb.map(|c| c / 255.0))));
        }
    }
    Ok(out)
}

/// Colour `k` of a fixed palette: hues a golden angle apart, saturated and light enough to read
/// over bone and soft tissue.
pub fn palette(k: usize) -> [f32; 3] {
    let h = (k as f64 * 0.618_033_988_75 + 0.08).fract() * 6.0;
    let (s, v) = (0.65, 0.95);
    let c = v * s;
    let x = c * (1.0 - (h % 2.0 - 1.0).abs());
    let (r, g, b) = match h as usize {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [(r + m) as f32, (g + m) as f32, (b + m) as f32]
}

/// TotalSegmentator's class table (task `total`, v2): label value k + 1 is entry k.
pub const TOTALSEGMENTATOR: [&str; 117] = [
    "spleen",
    "kidney_right",
    "kidney_left",
    "gallbladder",
    "liver",
    "stomach",
    "pancreas",
    "adrenal_gland_right",
    "adrenal_gland_left",
    "lung_upper_lobe_left",
    "lung_lower_lobe_left",
    "lung_upper_lobe_right",
    "lung_middle_lobe_right",
    "lung_lower_lobe_right",
    "esophagus",
    "trachea",
    "thyroid_gland",
    "small_bowel",
    "duodenum",
    "colon",
    "urinary_bladder",
    "prostate",
    "kidney_cyst_left",
    "kidney_cyst_right",
    "sacrum",
    "vertebrae_S1",
    "vertebrae_L5",
    "vertebrae_L4",
    "vertebrae_L3",
    "vertebrae_L2",
    "vertebrae_L1",
    "vertebrae_T12",
    "vertebrae_T11",
    "vertebrae_T10",
    "vertebrae_T9",
    "vertebrae_T8",
    "vertebrae_T7",
    "vertebrae_T6",
    "vertebrae_T5",
    "vertebrae_T4",
    "vertebrae_T3",
    "vertebrae_T2",
    "vertebrae_T1",
    "vertebrae_C7",
    "vertebrae_C6",
    "vertebrae_C5",
    "vertebrae_C4",
    "vertebrae_C3",
    "vertebrae_C2",
    "vertebrae_C1",
    "heart",
    "aorta",
    "pulmonary_vein",
    "brachiocephalic_trunk",
    "subclavian_artery_right",
    "subclavian_artery_left",
    "common_carotid_artery_right",
    "common_carotid_artery_left",
    "brachiocephalic_vein_left",
    "brachiocephalic_vein_right",
    "atrial_appendage_left",
    "superior_vena_cava",
    "inferior_vena_cava",
    "portal_vein_and_splenic_vein",
    "iliac_artery_left",
    "iliac_artery_right",
    "iliac_vena_left",
    "iliac_vena_right",
    "humerus_left",
    "humerus_right",
    "scapula_left",
    "scapula_right",
    "clavicula_left",
    "clavicula_right",
    "femur_left",
    "femur_right",
    "hip_left",
    "hip_right",
    "spinal_cord",
    "gluteus_maximus_left",
    "gluteus_maximus_right",
    "gluteus_medius_left",
    "gluteus_medius_right",
    "gluteus_minimus_left",
    "gluteus_minimus_right",
    "autochthon_left",
    "autochthon_right",
    "iliopsoas_left",
    "iliopsoas_right",
    "brain",
    "skull",
    "rib_left_1",
    "rib_left_2",
    "rib_left_3",
    "rib_left_4",
    "rib_left_5",
    "rib_left_6",
    "rib_left_7",
    "rib_left_8",
    "rib_left_9",
    "rib_left_10",
    "rib_left_11",
    "rib_left_12",
    "rib_right_1",
    "rib_right_2",
    "rib_right_3",
    "rib_right_4",
    "rib_right_5",
    "rib_right_6",
    "rib_right_7",
    "rib_right_8",
    "rib_right_9",
    "rib_right_10",
    "rib_right_11",
    "rib_right_12",
    "sternum",
    "costal_cartilages",
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::{Modality, Voxels};

    fn grid(dims: [usize; 3], spacing: [f64; 3], origin: DVec3, directions: DMat3) -> Volume {
        Volume {
            whole_range: None,
            name: "g".into(),
            dims,
            spacing,
            directions,
            origin,
            modality: Modality::Ct,
            voxels: Voxels::U8(vec![0; dims[0] * dims[1] * dims[2]]),
            labels: None,
        }
    }

    #[test]
    fn resampling_goes_by_physical_position_not_by_index() {
        // The label map: 2 mm voxels, flipped in x, shifted by 10 mm; voxel (a, b, c) holds
        // label 1 + a.
        let flip = DMat3::from_diagonal(DVec3::new(-1.0, 1.0, 1.0));
        let src = grid([4, 2, 2], [2.0, 2.0, 2.0], DVec3::new(16.0, 0.0, 0.0), flip);
        let values: Vec<u32> = (0..16).map(|i| 1 + (i % 4) as u32).collect();
        // The volume: 1 mm voxels from x = 10 mm, identity directions.
        let vol = grid(
            [8, 4, 4],
            [1.0; 3],
            DVec3::new(10.0, 0.0, 0.0),
            DMat3::IDENTITY,
        );
        let ids = resample(&src, &values, &vol, &|v| v as u8).unwrap();
        for x in 0..8 {
            // LPS x = 10 + x; the label map's index a = (16 - (10 + x)) / 2, nearest.
            let a = (16.0 - (10.0 + x as f64)) / 2.0;
            let want = if a.round() >= 0.0 && a.round() < 4.0 {
                1 + a.round() as u8
            } else {
                0
            };
            assert_eq!(ids[vol.index(x, 0, 0)], want, "x = {x}");
        }
        let far = grid(
            [4, 4, 4],
            [1.0; 3],
            DVec3::new(500.0, 0.0, 0.0),
            DMat3::IDENTITY,
        );
        let e = resample(&src, &values, &far, &|v| v as u8).unwrap_err();
        assert!(e.contains("does not overlap") && e.contains("499.5"), "{e}");
    }

    /// A shown, unprotected structure of `value` called `name`.
    fn structure(name: &str, value: u32) -> Structure {
        Structure {
            value,
            name: name.into(),
            colour: palette(0),
            opacity: 1.0,
            protected: false,
            margin_mm: None,
            voxels: 0,
        }
    }

    #[test]
    fn display_options_name_structures_and_refuse_unknown_ones() {
        let s = structure;
        let mut m = LabelMap {
            source: "seg".into(),
            ids: vec![0, 1, 2, 3],
            structures: vec![s("liver", 5), s("portal_vein", 64), s("aorta", 52)],
        };
        m.apply(&LabelDisplay {
            hide: vec!["Aorta".into()],
            opacity: vec!["liver=0.25".into()],
            protect: vec!["portal-vein".into()],
            ..Default::default()
        })
        .unwrap();
        assert_eq!(
            [m.factor(0), m.factor(1), m.factor(2), m.factor(3)],
            [1.0, 0.25, 1.0, 0.0]
        );
        assert_eq!(m.protected_bits()[0], 1 << 2);
        let e = m
            .apply(&LabelDisplay {
                hide: vec!["tumour".into()],
                ..Default::default()
            })
            .unwrap_err();
        assert!(
            e.contains("no structure 'tumour'") && e.contains("portal_vein"),
            "{e}"
        );
        assert!(m
            .apply(&LabelDisplay {
                opacity: vec!["liver=2".into()],
                ..Default::default()
            })
            .is_err());
    }
    #[test]
    fn a_downsampled_map_takes_each_blocks_majority_and_a_crop_its_box() {
        let s = |name: &str| structure(name, 1);
        // 5 x 2 x 2 voxels, x fastest; blocks of 2: x 0..2, 2..4 and the cut block 4..5.
        #[rustfmt::skip]
        let ids = vec![
            1, 1, 2, 0, 3,
            1, 0, 2, 1, 0,
            0, 0, 2, 1, 0,
            0, 0, 0, 1, 3,
        ];
        let m = LabelMap {
            source: "seg".into(),
            ids,
            structures: vec![s("liver"), s("vessel"), s("tumour")],
        };
        let d = m.downsample([5, 2, 2], 2);
        // Block 0: three voxels of 1, five unlabelled: the unlabelled win. Block 1: three of
        // 2, three of 1, two unlabelled: the first structure with as many. Block 2 (cut):
        // two of 3, two unlabelled: the structure.
        assert_eq!(d.ids, vec![0, 1, 3]);
        assert_eq!(
            d.structures.iter().map(|s| s.voxels).collect::<Vec<_>>(),
            vec![1, 0, 1]
        );
        let c = m.crop([5, 2, 2], [2, 1, 0], [3, 1, 2]);
        assert_eq!(c.ids, vec![2, 1, 0, 0, 1, 3]);
        assert_eq!(
            c.structures.iter().map(|s| s.voxels).collect::<Vec<_>>(),
            vec![2, 1, 1]
        );
    }
}
