//! Markups as 3D Slicer writes them (`.mrk.json`, the markups schema v1): points (type
//! "Fiducial") and rulers (type "Line", two control points), in patient space. Read in LPS or
//! RAS (`coordinateSystem`), held and written in LPS, millimetres.

use super::VolumeError;
use glam::DVec3;
use serde_json::{json, Value};
use std::path::Path;

/// One labelled point, LPS mm.
#[derive(Clone, Debug, PartialEq)]
pub struct MarkupPoint {
    pub label: String,
    pub lps: DVec3,
}

/// A ruler between two points, LPS mm.
#[derive(Clone, Debug, PartialEq)]
pub struct MarkupLine {
    pub label: String,
    pub ends: [DVec3; 2],
}

impl MarkupLine {
    /// Its length in mm (patient space is in mm whatever the voxels' spacing).
    pub fn length_mm(&self) -> f64 {
        self.ends[0].distance(self.ends[1])
    }
}

/// The markups of a session.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Markups {
    pub points: Vec<MarkupPoint>,
    pub lines: Vec<MarkupLine>,
}

/// Slicer's schema for markups files (the field its reader looks for).
const SCHEMA: &str = "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#";

impl Markups {
    pub fn is_empty(&self) -> bool {
        self.points.is_empty() && self.lines.is_empty()
    }

    /// "ruler A 42.3 mm, ruler B 7.0 mm": each line's label and length.
    pub fn lengths(&self) -> String {
        self.lines
            .iter()
            .map(|l| format!("{} {:.1} mm", l.label, l.length_mm()))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Reads a Slicer markups file: its Fiducial and Line markups (other types are refused by
    /// name, so nothing is silently dropped).
    pub fn read(path: &Path) -> Result<Markups, VolumeError> {
        let bad = |m: String| VolumeError::format(path, m);
        let text = std::fs::read_to_string(path).map_err(|e| VolumeError::io(path, e))?;
        let doc: Value = serde_json::from_str(&text).map_err(|e| bad(format!("not JSON: {e}")))?;
        let list = doc["markups"].as_array().ok_or_else(|| {
            bad("no \"markups\" list (a 3D Slicer .mrk.json file has one)".into())
        })?;
        let mut out = Markups::default();
        for (n, m) in list.iter().enumerate() {
            let kind = m["type"].as_str().unwrap_or("");
            let system = m["coordinateSystem"].as_str().unwrap_or("LPS");
            let flip = match system {
                "LPS" => DVec3::ONE,
                "RAS" => DVec3::new(-1.0, -1.0, 1.0),
                s => {
                    return Err(bad(format!(
                        "markup {n}: coordinate system '{s}' (LPS or RAS)"
                    )))
                }
            };
            let units = m["coordinateUnits"].as_str().unwrap_or("mm");
            if units != "mm" {
                return Err(bad(format!("markup {n}: units '{units}' (mm expected)")));
            }
            let points = m["controlPoints"].as_array().map_or(&[][..], |v| v);
            let mut read = Vec::new();
            for (k, p) in points.iter().enumerate() {
                let v = p["position"]
                    .as_array()
                    .and_then(|a| {
                        let x: Vec<f64> = a.iter().filter_map(Value::as_f64).collect();
                        (x.len() == 3 && x.iter().all(|c| c.is_finite())).then_some(x)
                    })
                    .ok_or_else(|| {
                        bad(format!(
                            "markup {n}, point {k}: no position of three numbers"
                        ))
                    })?;
                let label = p["label"].as_str().unwrap_or("").to_string();
                read.push((label, DVec3::new(v[0], v[1], v[2]) * flip));
            }
            let name = m["name"].as_str().unwrap_or("").to_string();
            match kind {
                "Fiducial" => {
                    for (label, lps) in read {
                        out.points.push(MarkupPoint { label, lps });
                    }
                }
                "Line" => {
                    let [a, b] = read.as_slice() else {
                        return Err(bad(format!(
                            "markup {n}: a line has two control points, not {}",
                            read.len()
                        )));
                    };
                    out.lines.push(MarkupLine {
                        label: if name.is_empty() { a.0.clone() } else { name },
                        ends: [a.1, b.1],
                    });
                }
                k => {
                    return Err(VolumeError::unsupported(
                        path,
                        format!("markup {n}: type '{k}' (points and lines are read)"),
                    ))
                }
            }
        }
        Ok(out)
    }

    /// Writes a Slicer markups file (LPS, mm): one Fiducial markup with every point, and one
    /// Line markup per ruler, with its length as Slicer's "length" measurement.
    pub fn write(&self, path: &Path) -> Result<(), VolumeError> {
        let point = |id: usize, label: &str, p: DVec3| {
            json!({ "id": (id + 1).to_string(), "label": label, "position": [p.x, p.y, p.z],
                    "positionStatus": "defined" })
        };
        let mut list = Vec::new();
        if !self.points.is_empty() {
            let cps: Vec<Value> = self
                .points
                .iter()
                .enumerate()
                .map(|(k, p)| point(k, &p.label, p.lps))
                .collect();
            list.push(json!({ "type": "Fiducial", "coordinateSystem": "LPS",
                              "coordinateUnits": "mm", "controlPoints": cps }));
        }
        for l in &self.lines {
            list.push(json!({
                "type": "Line", "name": l.label, "coordinateSystem": "LPS", "coordinateUnits": "mm",
                "controlPoints": [point(0, &format!("{}-1", l.label), l.ends[0]),
                                  point(1, &format!("{}-2", l.label), l.ends[1])],
                "measurements": [{ "name": "length", "enabled": true, "value": l.length_mm(),
                                   "units": "mm" }]
            }));
        }
        let doc = json!({ "@schema": SCHEMA, "markups": list });
        let text = serde_json::to_string_pretty(&doc).expect("JSON values serialise");
        // Beside its name, renamed once complete: an interrupted write leaves the file before.
        let partial = path.with_extension("json.partial");
        std::fs::write(&partial, text)
            .and_then(|()| std::fs::rename(&partial, path))
            .map_err(|e| VolumeError::io(path, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slicer_files_read_in_lps_and_round_trip() {
        let dir = std::env::temp_dir().join(format!("cao-markups-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // As Slicer writes them: a RAS line and LPS points.
        let slicer = dir.join("slicer.mrk.json");
        std::fs::write(
            &slicer,
            r#"{"@schema": "x", "markups": [
              {"type": "Line", "name": "L", "coordinateSystem": "RAS", "coordinateUnits": "mm",
               "controlPoints": [{"id": "1", "label": "L-1", "position": [10.0, 20.0, 30.0]},
                                 {"id": "2", "label": "L-2", "position": [13.0, 24.0, 30.0]}]},
              {"type": "Fiducial", "coordinateSystem": "LPS",
               "controlPoints": [{"id": "1", "label": "F-1", "position": [1.0, 2.0, 3.0]}]}]}"#,
        )
        .unwrap();
        let m = Markups::read(&slicer).unwrap();
        assert_eq!(m.lines.len(), 1);
        assert_eq!(m.lines[0].ends[0], DVec3::new(-10.0, -20.0, 30.0));
        assert_eq!(m.lines[0].length_mm(), 5.0);
        assert_eq!(m.lengths(), "L 5.0 mm");
        assert_eq!(m.points[0].lps, DVec3::new(1.0, 2.0, 3.0));
        let out = dir.join("out.mrk.json");
        m.write(&out).unwrap();
        assert_eq!(Markups::read(&out).unwrap(), m);
        // What is not a markup of ours is refused by name.
        std::fs::write(
            &slicer,
            r#"{"markups": [{"type": "Curve", "controlPoints": []}]}"#,
        )
        .unwrap();
        let e = Markups::read(&slicer).unwrap_err().to_string();
        assert!(e.contains("Curve") && e.contains("slicer.mrk.json"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
