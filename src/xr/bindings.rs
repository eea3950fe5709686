//! Suggested bindings as data: one JSON file per OpenXR interaction profile in
//! `controllers/bindings/`, so supporting a new controller is a new file, not a code change.
//!
//! JSON rather than TOML because serde_json is already a dependency and the format needs
//! nothing TOML adds. A file looks like:
//!
//! ```json
//! { "profile": "/interaction_profiles/khr/simple_controller",
//!   "bindings": { "trigger": ["/user/hand/left/input/select/click",
//!                             "/user/hand/right/input/select/click"] } }
//! ```
//!
//! The keys of `bindings` are the action names of [`ACTION_NAMES`]; each maps to
//! the full input (or output) paths it is bound to, both hands spelled out, so a profile whose
//! hands differ (Touch: X/Y on the left, A/B on the right) needs no special case.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Every action a binding file may name.
pub const ACTION_NAMES: &[&str] = &[
    "grip_pose",
    "aim_pose",
    "grip",
    "trigger",
    "primary",
    "secondary",
    "menu",
    "stick_click",
    "thumbstick",
    "haptic",
];

/// The files shipped in controllers/bindings/, compiled in so the binary works from any
/// directory (a run inside the Monado test root, an installed copy).
pub const BUILTIN: &[(&str, &str)] = &[
    (
        "khr_simple_controller.json",
        include_str!("../../controllers/bindings/khr_simple_controller.json"),
    ),
    (
        "oculus_touch_controller.json",
        include_str!("../../controllers/bindings/oculus_touch_controller.json"),
    ),
    (
        "valve_index_controller.json",
        include_str!("../../controllers/bindings/valve_index_controller.json"),
    ),
    (
        "htc_vive_controller.json",
        include_str!("../../controllers/bindings/htc_vive_controller.json"),
    ),
    (
        "microsoft_motion_controller.json",
        include_str!("../../controllers/bindings/microsoft_motion_controller.json"),
    ),
    (
        "ext_hand_interaction.json",
        include_str!("../../controllers/bindings/ext_hand_interaction.json"),
    ),
];

#[derive(Debug, thiserror::Error)]
pub enum BindingsError {
    #[error("{path}: {msg}")]
    File { path: String, msg: String },
    #[error("{path}: unknown action '{action}' (known: {known})")]
    UnknownAction {
        path: String,
        action: String,
        known: String,
    },
}

/// One interaction profile's suggested bindings.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProfileBindings {
    /// E.g. `/interaction_profiles/oculus/touch_controller`.
    pub profile: String,
    /// Action name -> the paths bound to it.
    pub bindings: BTreeMap<String, Vec<String>>,
    /// Free text for people.
    #[serde(default)]
    pub description: String,
    /// The OpenXR extension that defines the profile (e.g. XR_EXT_hand_interaction): the
    /// profile is suggested only when the runtime offers it.
    #[serde(default)]
    pub requires_extension: Option<String>,
}

/// Parses one file's text; `name` is used in messages.
pub fn parse(name: &str, text: &str) -> Result<ProfileBindings, BindingsError> {
    let b: ProfileBindings = serde_json::from_str(text).map_err(|e| BindingsError::File {
        path: name.into(),
        msg: e.to_string(),
    })?;
    if !b.profile.starts_with("/interaction_profiles/") {
        return Err(BindingsError::File {
            path: name.into(),
            msg: format!(
                "profile '{}' must start with /interaction_profiles/",
                b.profile
            ),
        });
    }
    for (action, paths) in &b.bindings {
        if !ACTION_NAMES.contains(&action.as_str()) {
            return Err(BindingsError::UnknownAction {
                path: name.into(),
                action: action.clone(),
                known: ACTION_NAMES.join(", "),
            });
        }
        if let Some(p) = paths.iter().find(|p| !p.starts_with("/user/")) {
            return Err(BindingsError::File {
                path: name.into(),
                msg: format!("binding '{p}' of '{action}' must start with /user/"),
            });
        }
    }
    Ok(b)
}

/// Where bindings are read from: `$CAO_XR_BINDINGS`, else `controllers/bindings` under the
/// current directory, else the compiled-in copies.
pub fn default_dir() -> Option<PathBuf> {
    if let Ok(d) = std::env::var("CAO_XR_BINDINGS") {
        return Some(PathBuf::from(d));
    }
    let local = PathBuf::from("controllers/bindings");
    local.is_dir().then_some(local)
}

/// Every `*.json` in `dir` (sorted by name), or the built-in set when `dir` is `None`.
pub fn load(dir: Option<&Path>) -> Result<Vec<ProfileBindings>, BindingsError> {
    let Some(dir) = dir else {
        return BUILTIN.iter().map(|(n, t)| parse(n, t)).collect();
    };
    let err = |msg: String| BindingsError::File {
        path: dir.display().to_string(),
        msg,
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| err(e.to_string()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(err("no *.json binding files".into()));
    }
    files
        .iter()
        .map(|p| {
            let text = std::fs::read_to_string(p).map_err(|e| BindingsError::File {
                path: p.display().to_string(),
                msg: e.to_string(),
            })?;
            parse(&p.display().to_string(), &text)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_bindings_parse_and_cover_the_required_profiles() {
        let all = load(None).unwrap();
        for want in [
            "khr/simple_controller",
            "oculus/touch_controller",
            "valve/index_controller",
            "htc/vive_controller",
            "microsoft/motion_controller",
        ] {
            let b = all
                .iter()
                .find(|b| b.profile.ends_with(want))
                .unwrap_or_else(|| panic!("{want} missing"));
            for a in ["grip_pose", "aim_pose", "haptic"] {
                assert_eq!(b.bindings[a].len(), 2, "{want}: {a} for both hands");
            }
        }
    }

    #[test]
    fn the_shipped_directory_matches_the_builtin_set() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("controllers/bindings");
        let by_profile = |mut v: Vec<ProfileBindings>| {
            v.sort_by(|a, b| a.profile.cmp(&b.profile));
            v
        };
        assert_eq!(
            by_profile(load(Some(&dir)).unwrap()),
            by_profile(load(None).unwrap())
        );
    }

    #[test]
    fn an_unknown_action_is_named() {
        let e = parse(
            "x.json",
            r#"{"profile":"/interaction_profiles/a/b","bindings":{"fire":["/user/hand/left/input/x/click"]}}"#,
        )
        .unwrap_err();
        assert!(e.to_string().contains("unknown action 'fire'"), "{e}");
    }
}
