//! 1D RGBA transfer functions from control points, defined on the data's own values (Hounsfield
//! units for CT) or on the normalised value range. Alpha is opacity per 1 mm of path.

use super::{Modality, Volume};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Domain {
    /// Control-point values are data values (HU for CT).
    #[default]
    Data,
    /// Control-point values are fractions of the volume's value range, 0 = min, 1 = max.
    Normalized,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlPoint {
    pub value: f32,
    /// Linear RGB in \[0,1].
    pub color: [f32; 3],
    /// Opacity per 1 mm of path, in \[0,1].
    pub alpha: f32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransferFunction {
    pub name: String,
    #[serde(default)]
    pub domain: Domain,
    pub points: Vec<ControlPoint>,
}

#[derive(Debug, thiserror::Error)]
pub enum TfError {
    #[error("{path}: {msg}")]
    File { path: String, msg: String },
    #[error("unknown transfer function '{0}': not a preset ({presets}) nor an existing file", presets = PRESETS.join(", "))]
    Unknown(String),
}

/// Every preset, named the way radiology workstations name them. CT presets are defined on
/// Hounsfield units, MR presets on the normalised value range (MR has no absolute scale).
pub const PRESETS: &[&str] = &[
    "ct-bone",
    "ct-soft-tissue",
    "ct-muscle-bone",
    "ct-lung",
    "ct-angio",
    "ct-skin",
    "mr-default",
    "mr-angio",
];

/// The presets that suit CT data (Hounsfield units), the default first.
pub const CT_PRESETS: &[&str] = &[
    "ct-bone",
    "ct-soft-tissue",
    "ct-muscle-bone",
    "ct-lung",
    "ct-angio",
    "ct-skin",
];

/// The presets that suit MR (and other non-HU) data, the default first.
pub const MR_PRESETS: &[&str] = &["mr-default", "mr-angio"];

/// Older names still accepted by `--tf`: (alias, preset).
pub const ALIASES: &[(&str, &str)] = &[("mri", "mr-default")];

/// The presets suited to `modality` (the menu button's cycle list): CT or MR; for unknown
/// modality all of them (use [`presets_for_volume`] to decide from the values).
pub fn presets_for(modality: Modality) -> Vec<&'static str> {
    match modality {
        Modality::Ct => CT_PRESETS.to_vec(),
        Modality::Mr => MR_PRESETS.to_vec(),
        Modality::Unknown => PRESETS.to_vec(),
    }
}

/// The presets suited to `vol`: the CT list when [`looks_like_ct`], else the MR list.
pub fn presets_for_volume(vol: &Volume) -> Vec<&'static str> {
    if looks_like_ct(vol) {
        CT_PRESETS.to_vec()
    } else {
        MR_PRESETS.to_vec()
    }
}

/// Whether `vol` holds Hounsfield units: its modality says CT, or (modality unknown) its values
/// span air to bone (min <= -900 HU and max >= 300 HU), which MR intensities never do.
pub fn looks_like_ct(vol: &Volume) -> bool {
    match vol.modality {
        Modality::Ct => true,
        Modality::Mr => false,
        Modality::Unknown => {
            let (lo, hi) = vol.value_range();
            lo <= -900.0 && hi >= 300.0
        }
    }
}

fn cp(value: f32, color: [f32; 3], alpha: f32) -> ControlPoint {
    ControlPoint {
        value,
        color,
        alpha,
    }
}

impl TransferFunction {
    /// The preset `name` (or an [`ALIASES`] name, giving the preset it stands for).
    pub fn preset(name: &str) -> Option<TransferFunction> {
        let name = ALIASES
            .iter()
            .find(|(a, _)| *a == name)
            .map_or(name, |(_, p)| *p);
        let bone = [0.93, 0.89, 0.80];
        let marrow = [0.80, 0.55, 0.40];
        let skin = [0.90, 0.65, 0.55];
        let fat = [0.85, 0.75, 0.45];
        let muscle = [0.75, 0.28, 0.22];
        let blood = [0.95, 0.15, 0.10];
        let (domain, points) = match name {
            // Cortical bone opaque and ivory; everything below ~150 HU transparent.
            "ct-bone" => (
                Domain::Data,
                vec![
                    cp(-1024.0, [0.0; 3], 0.0),
                    cp(150.0, marrow, 0.0),
                    cp(350.0, marrow, 0.25),
                    cp(700.0, bone, 0.8),
                    cp(1500.0, [1.0, 0.98, 0.94], 0.95),
                    cp(4000.0, [1.0; 3], 1.0),
                ],
            ),
            // A thin translucent skin surface (fat and skin) over opaque bone.
            "ct-skin" => (
                Domain::Data,
                vec![
                    cp(-1024.0, [0.0; 3], 0.0),
                    cp(-400.0, skin, 0.0),
                    cp(-150.0, skin, 0.06),
                    cp(100.0, skin, 0.06),
                    cp(180.0, marrow, 0.0),
                    cp(300.0, marrow, 0.2),
                    cp(700.0, bone, 0.8),
                    cp(4000.0, [1.0; 3], 1.0),
                ],
            ),
            // Soft-tissue window (about -100..+300 HU): fat faint yellow, muscle and organs
            // red and fairly dense, bone opaque.
            "ct-soft-tissue" => (
                Domain::Data,
                vec![
                    cp(-1024.0, [0.0; 3], 0.0),
                    cp(-200.0, fat, 0.0),
                    cp(-100.0, fat, 0.02),
                    cp(0.0, fat, 0.03),
                    cp(40.0, muscle, 0.12),
                    cp(80.0, [0.80, 0.35, 0.30], 0.2),
                    cp(200.0, [0.90, 0.70, 0.60], 0.3),
                    cp(300.0, bone, 0.6),
                    cp(1000.0, bone, 0.9),
                    cp(4000.0, [1.0; 3], 1.0),
                ],
            ),
            // Skin and fat clear, muscle red and translucent, bone opaque.
            "ct-muscle-bone" => (
                Domain::Data,
                vec![
                    cp(-1024.0, [0.0; 3], 0.0),
                    cp(-50.0, muscle, 0.0),
                    cp(40.0, muscle, 0.08),
                    cp(120.0, [0.80, 0.32, 0.25], 0.1),
                    cp(200.0, marrow, 0.3),
                    cp(500.0, bone, 0.85),
                    cp(4000.0, [1.0; 3], 1.0),
                ],
            ),
            // Lung window: air clear, parenchyma (-950..-500 HU) a faint translucent haze,
            // vessels and airway walls (-500..-100 HU) red and denser; the chest wall and
            // mediastinum (soft tissue) clear so the lungs stay visible; bone a faint hint.
            "ct-lung" => (
                Domain::Data,
                vec![
                    cp(-1024.0, [0.0; 3], 0.0),
                    cp(-950.0, [0.90, 0.70, 0.65], 0.0),
                    cp(-850.0, [0.90, 0.70, 0.65], 0.012),
                    cp(-600.0, [0.90, 0.65, 0.60], 0.02),
                    cp(-500.0, [0.85, 0.30, 0.30], 0.2),
                    cp(-200.0, [0.85, 0.35, 0.30], 0.35),
                    cp(-50.0, [0.80, 0.40, 0.35], 0.0),
                    cp(200.0, bone, 0.0),
                    cp(400.0, bone, 0.08),
                    cp(4000.0, [1.0; 3], 0.15),
                ],
            ),
            // CT angiography: contrast-filled vessels (about 150..500 HU) bright red, bone
            // (above ~500 HU) ivory, soft tissue clear.
            "ct-angio" => (
                Domain::Data,
                vec![
                    cp(-1024.0, [0.0; 3], 0.0),
                    cp(100.0, blood, 0.0),
                    cp(150.0, blood, 0.3),
                    cp(300.0, [1.0, 0.25, 0.20], 0.6),
                    cp(500.0, [1.0, 0.55, 0.45], 0.6),
                    cp(700.0, bone, 0.8),
                    cp(4000.0, [1.0; 3], 1.0),
                ],
            ),
            // MR intensities have no absolute scale: defined on the normalised range.
            // Background clear, tissue from translucent to bright.
            "mr-default" => (
                Domain::Normalized,
                vec![
                    cp(0.0, [0.0; 3], 0.0),
                    cp(0.08, [0.6, 0.45, 0.4], 0.0),
                    cp(0.2, [0.85, 0.7, 0.6], 0.15),
                    cp(0.5, [0.95, 0.9, 0.85], 0.5),
                    cp(1.0, [1.0; 3], 0.8),
                ],
            ),
            // MR angiography (time of flight): only the brightest signal, flowing blood, in red.
            "mr-angio" => (
                Domain::Normalized,
                vec![
                    cp(0.0, [0.0; 3], 0.0),
                    cp(0.35, blood, 0.0),
                    cp(0.5, blood, 0.2),
                    cp(0.8, [1.0, 0.6, 0.5], 0.7),
                    cp(1.0, [1.0; 3], 0.9),
                ],
            ),
            _ => return None,
        };
        Some(TransferFunction {
            name: name.into(),
            domain,
            points,
        })
    }

    /// The automatic choice for `vol`: `ct-bone` for CT (Hounsfield) data, `mr-default` for MR
    /// and anything else (see [`looks_like_ct`]).
    pub fn default_for(vol: &Volume) -> TransferFunction {
        let name = if looks_like_ct(vol) {
            CT_PRESETS[0]
        } else {
            MR_PRESETS[0]
        };
        Self::preset(name).expect("the default presets exist")
    }

    /// A preset name or the path of a JSON file.
    pub fn resolve(spec: &str) -> Result<TransferFunction, TfError> {
        if let Some(tf) = Self::preset(spec) {
            return Ok(tf);
        }
        let path = Path::new(spec);
        if path.exists() {
            return Self::load(path);
        }
        Err(TfError::Unknown(spec.into()))
    }

    pub fn load(path: &Path) -> Result<TransferFunction, TfError> {
        let err = |msg: String| TfError::File {
            path: path.display().to_string(),
            msg,
        };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        Self::from_json(&text).map_err(err)
    }

    /// Parses and validates the JSON text of a transfer function (the message names no file).
    pub fn from_json(text: &str) -> Result<TransferFunction, String> {
        let tf: TransferFunction =
            serde_json::from_str(text).map_err(|e| format!("not a transfer function: {e}"))?;
        tf.validate()?;
        Ok(tf)
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.points.len() < 2 {
            return Err("needs at least two control points".into());
        }
        for (i, p) in self.points.iter().enumerate() {
            let in01 = |x: f32| (0.0..=1.0).contains(&x);
            if !p.value.is_finite() || !in01(p.alpha) || !p.color.iter().all(|&c| in01(c)) {
                return Err(format!(
                    "control point {i}: value must be finite, colour and alpha within [0,1]"
                ));
            }
            if i > 0 && p.value <= self.points[i - 1].value {
                return Err(format!("control point {i}: values must increase strictly"));
            }
        }
        Ok(())
    }

    /// The control-point axis mapped to data values for a volume whose values span `range`.
    fn data_value(&self, v: f32, range: (f32, f32)) -> f64 {
        let (lo, hi) = match self.domain {
            Domain::Data => return v as f64,
            Domain::Normalized => range,
        };
        lo as f64 + v as f64 * (hi as f64 - lo as f64)
    }

    /// RGBA at data value `value` (piecewise linear, clamped at the ends).
    pub fn eval(&self, value: f32, range: (f32, f32)) -> [f32; 4] {
        let x = value as f64;
        let pts = &self.points;
        let rgba = |p: &ControlPoint| [p.color[0], p.color[1], p.color[2], p.alpha];
        if x <= self.data_value(pts[0].value, range) {
            return rgba(&pts[0]);
        }
        for w in pts.windows(2) {
            let (a, b) = (
                self.data_value(w[0].value, range),
                self.data_value(w[1].value, range),
            );
            if x <= b {
                let t = if b > a { (x - a) / (b - a) } else { 1.0 };
                let (ca, cb) = (rgba(&w[0]), rgba(&w[1]));
                return std::array::from_fn(|i| {
                    (ca[i] as f64 + t * (cb[i] as f64 - ca[i] as f64)) as f32
                });
            }
        }
        rgba(pts.last().unwrap())
    }

    /// The opacity volume O of docs/design.md (before clipping): tf alpha of every voxel's value,
    /// times its structure's opacity a_l where the volume has labels (0 hidden, 1 unlabelled).
    pub fn opacity_volume(&self, vol: &Volume) -> Vec<f32> {
        // No opacities given: each structure keeps its label map's own.
        self.opacity_volume_showing(vol, &[])
    }

    /// [`TransferFunction::opacity_volume`] with the structures' opacities a_l given (by
    /// structure index; a structure past the end keeps its label map's own): what a run-time
    /// show / hide classifies.
    pub fn opacity_volume_showing(&self, vol: &Volume, structures: &[f32]) -> Vec<f32> {
        let range = vol.value_range();
        let labels = vol.labels.as_deref();
        (0..vol.voxel_count())
            .into_par_iter()
            .map(|i| {
                let a = self.eval(vol.voxels.get(i), range)[3];
                labels.map_or(a, |l| a * l.factor_showing(i, structures))
            })
            .collect()
    }

    /// The solid of the isosurface at data value `iso`: clear below it, opaque (1 per mm) from
    /// it up, in this TF's colour at `iso` throughout. Its opacity is what the AO of an
    /// isosurface is computed on (`--iso`), and its colour what the surface is drawn in.
    pub fn iso_solid(&self, iso: f32, range: (f32, f32)) -> TransferFunction {
        let [r, g, b, _] = self.eval(iso, range);
        let below = iso - 1e-4 * (range.1 - range.0).abs().max(1.0);
        let point = |value, alpha| ControlPoint {
            value,
            color: [r, g, b],
            alpha,
        };
        TransferFunction {
            name: format!("{} iso {iso}", self.name),
            domain: Domain::Data,
            points: vec![point(below, 0.0), point(iso, 1.0)],
        }
    }

    /// `n` RGBA entries sampled uniformly over `range` (for the ray caster's 1D texture).
    pub fn lut(&self, range: (f32, f32), n: usize) -> Vec<[f32; 4]> {
        (0..n)
            .map(|i| {
                let t = i as f64 / (n - 1) as f64;
                let v = range.0 as f64 + t * (range.1 as f64 - range.0 as f64);
                self.eval(v as f32, range)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_are_valid_and_bone_is_opaque_air_transparent() {
        for name in PRESETS {
            let tf = TransferFunction::preset(name).unwrap();
            tf.validate().unwrap();
        }
        let bone = TransferFunction::preset("ct-bone").unwrap();
        let r = (-1024.0, 3071.0);
        assert_eq!(bone.eval(-1000.0, r)[3], 0.0);
        assert!(bone.eval(1200.0, r)[3] > 0.8);
        let skin = TransferFunction::preset("ct-skin").unwrap();
        assert!(skin.eval(0.0, r)[3] > 0.0 && skin.eval(0.0, r)[3] < 0.2);
    }

    #[test]
    fn radiology_presets_show_what_their_names_say() {
        let r = (-1024.0, 3071.0);
        let a = |name: &str, hu: f32| TransferFunction::preset(name).unwrap().eval(hu, r)[3];
        let rgb = |name: &str, hu: f32| TransferFunction::preset(name).unwrap().eval(hu, r);
        // every preset: air is clear
        for name in PRESETS {
            assert_eq!(a(name, -1000.0), 0.0, "{name}");
        }
        // bone: nothing below 150 HU, cortical bone opaque
        assert_eq!(a("ct-bone", 60.0), 0.0);
        assert!(a("ct-bone", 1000.0) > 0.8);
        // soft tissue: fat faint, muscle clearly visible, bone most opaque
        assert!(a("ct-soft-tissue", -100.0) > 0.0 && a("ct-soft-tissue", -100.0) < 0.05);
        assert!(a("ct-soft-tissue", 60.0) > 0.1);
        assert!(a("ct-soft-tissue", 1000.0) > a("ct-soft-tissue", 60.0));
        // muscle and bone: fat clear, muscle translucent and red, bone opaque
        assert_eq!(a("ct-muscle-bone", -100.0), 0.0);
        let m = rgb("ct-muscle-bone", 60.0);
        assert!(m[3] > 0.0 && m[3] < 0.2 && m[0] > 2.0 * m[1], "{m:?}");
        assert!(a("ct-muscle-bone", 800.0) > 0.8);
        // lung: parenchyma a faint haze, vessels denser, soft tissue clear
        let p = a("ct-lung", -800.0);
        assert!(p > 0.0 && p < 0.05, "{p}");
        assert!(a("ct-lung", -300.0) > 5.0 * p);
        assert_eq!(a("ct-lung", 40.0), 0.0);
        // angio: soft tissue clear, contrast vessels bright red, bone visible
        assert_eq!(a("ct-angio", 50.0), 0.0);
        let v = rgb("ct-angio", 300.0);
        assert!(v[3] >= 0.5 && v[0] > 3.0 * v[1], "{v:?}");
        assert!(a("ct-angio", 1200.0) > 0.8);
        // MR presets live on the normalised range
        for name in MR_PRESETS {
            assert_eq!(
                TransferFunction::preset(name).unwrap().domain,
                Domain::Normalized
            );
        }
        for name in CT_PRESETS {
            assert_eq!(TransferFunction::preset(name).unwrap().domain, Domain::Data);
        }
        // the old name still works
        assert_eq!(
            TransferFunction::resolve("mri").unwrap(),
            TransferFunction::preset("mr-default").unwrap()
        );
    }

    #[test]
    fn default_and_cycle_list_follow_the_modality() {
        use crate::volume::Voxels;
        let mut vol = crate::volume::phantom::head(8);
        assert_eq!(vol.modality, Modality::Ct);
        assert_eq!(TransferFunction::default_for(&vol).name, "ct-bone");
        assert_eq!(presets_for_volume(&vol), CT_PRESETS);
        vol.modality = Modality::Mr;
        assert_eq!(TransferFunction::default_for(&vol).name, "mr-default");
        assert_eq!(presets_for_volume(&vol), MR_PRESETS);
        // unknown modality: decided from the values
        vol.modality = Modality::Unknown;
        let n = vol.voxel_count();
        vol.voxels = Voxels::I16((0..n).map(|i| (i as i16) * 8 - 1024).collect());
        assert_eq!(vol.value_range(), (-1024.0, 3064.0));
        assert_eq!(TransferFunction::default_for(&vol).name, "ct-bone");
        vol.voxels = Voxels::U16((0..n).map(|i| i as u16 * 3).collect());
        assert_eq!(TransferFunction::default_for(&vol).name, "mr-default");
        vol.voxels = Voxels::F32((0..n).map(|i| i as f32 * 0.01).collect());
        assert_eq!(TransferFunction::default_for(&vol).name, "mr-default");
        assert_eq!(presets_for(Modality::Ct), CT_PRESETS);
        assert_eq!(presets_for(Modality::Mr), MR_PRESETS);
        assert_eq!(presets_for(Modality::Unknown), PRESETS);
        // every list entry is a preset
        for name in CT_PRESETS.iter().chain(MR_PRESETS) {
            assert!(PRESETS.contains(name) && TransferFunction::preset(name).is_some());
        }
    }

    #[test]
    fn interpolates_linearly_and_clamps() {
        let tf = TransferFunction {
            name: "t".into(),
            domain: Domain::Data,
            points: vec![cp(0.0, [0.0; 3], 0.0), cp(100.0, [1.0; 3], 1.0)],
        };
        assert_eq!(tf.eval(25.0, (0.0, 1.0))[3], 0.25);
        assert_eq!(tf.eval(-5.0, (0.0, 1.0))[3], 0.0);
        assert_eq!(tf.eval(500.0, (0.0, 1.0))[3], 1.0);
        let n = TransferFunction {
            domain: Domain::Normalized,
            points: vec![cp(0.0, [0.0; 3], 0.0), cp(1.0, [1.0; 3], 1.0)],
            ..tf.clone()
        };
        // Normalised 0..1 maps onto the volume's range 0..200: 50 is a quarter.
        assert_eq!(n.eval(50.0, (0.0, 200.0))[3], 0.25);
    }

    #[test]
    fn json_round_trip_and_bad_files_name_the_file() {
        let dir = std::env::temp_dir().join(format!("cao-tf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.json");
        let tf = TransferFunction::preset("ct-skin").unwrap();
        std::fs::write(&good, serde_json::to_string_pretty(&tf).unwrap()).unwrap();
        assert_eq!(
            TransferFunction::resolve(good.to_str().unwrap()).unwrap(),
            tf
        );
        let bad = dir.join("bad.json");
        std::fs::write(
            &bad,
            r#"{"name":"x","points":[{"value":5,"color":[1,1,1],"alpha":2}]}"#,
        )
        .unwrap();
        let e = TransferFunction::resolve(bad.to_str().unwrap())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("bad.json") && e.contains("two control points"),
            "{e}"
        );
        let e = TransferFunction::resolve("no-such-preset")
            .unwrap_err()
            .to_string();
        assert!(e.contains("ct-bone"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
