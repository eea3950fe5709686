//! The hands' action set: poses, buttons and haptics for both hands, with suggested bindings
//! from [`super::bindings`], read each frame into the same [`HandInput`] the desktop and replay
//! paths produce.

use super::bindings::ProfileBindings;
use super::conversions::pose_from_xr;
use super::XrError;
use crate::input::{Buttons, HandInput, LEFT, RIGHT};
use glam::Vec2;
use openxr as xr;

/// The action set, its actions and the per-hand pose spaces.
pub struct HandActions {
    pub set: xr::ActionSet,
    hands: [xr::Path; 2],
    grip_pose: xr::Action<xr::Posef>,
    aim_pose: xr::Action<xr::Posef>,
    grip: xr::Action<f32>,
    trigger: xr::Action<f32>,
    primary: xr::Action<bool>,
    secondary: xr::Action<bool>,
    menu: xr::Action<bool>,
    stick_click: xr::Action<bool>,
    thumbstick: xr::Action<xr::Vector2f>,
    haptic: xr::Action<xr::Haptic>,
    /// Profiles the runtime accepted, for the log.
    pub accepted: Vec<String>,
    /// Last known hand state, so a hand that loses tracking keeps valid (stale) poses.
    last: [HandInput; 2],
}

/// A hand's pose spaces; they belong to one session.
pub struct HandSpaces {
    grip: [xr::Space; 2],
    aim: [xr::Space; 2],
}

impl HandActions {
    /// Creates the action set and suggests every profile's bindings. A profile the runtime does
    /// not know (or a path it rejects) is skipped with a warning, so one odd file cannot stop a
    /// session.
    pub fn new(instance: &xr::Instance, profiles: &[ProfileBindings]) -> Result<Self, XrError> {
        let hands = [
            instance.string_to_path("/user/hand/left")?,
            instance.string_to_path("/user/hand/right")?,
        ];
        let set = instance.create_action_set("hands", "Hands", 0)?;
        let grip_pose = set.create_action("grip_pose", "Grip pose", &hands)?;
        let aim_pose = set.create_action("aim_pose", "Aim pose", &hands)?;
        let grip = set.create_action("grip", "Grip", &hands)?;
        let trigger = set.create_action("trigger", "Trigger", &hands)?;
        let primary = set.create_action("primary", "Primary button", &hands)?;
        let secondary = set.create_action("secondary", "Secondary button", &hands)?;
        let menu = set.create_action("menu", "Menu", &hands)?;
        let stick_click = set.create_action("stick_click", "Thumbstick click", &hands)?;
        let thumbstick = set.create_action("thumbstick", "Thumbstick", &hands)?;
        let haptic = set.create_action("haptic", "Haptic pulse", &hands)?;
        let mut a = HandActions {
            set,
            hands,
            grip_pose,
            aim_pose,
            grip,
            trigger,
            primary,
            secondary,
            menu,
            stick_click,
            thumbstick,
            haptic,
            accepted: Vec::new(),
            last: [HandInput::default(); 2],
        };
        for p in profiles {
            let enabled = match p.requires_extension.as_deref() {
                None => true,
                Some("XR_EXT_hand_interaction") => instance.exts().ext_hand_interaction.is_some(),
                Some(_) => false,
            };
            if !enabled {
                eprintln!(
                    "xr: bindings for {} not suggested: the runtime lacks {}",
                    p.profile,
                    p.requires_extension.as_deref().unwrap_or_default()
                );
                continue;
            }
            match a.suggest(instance, p) {
                Ok(()) => a.accepted.push(p.profile.clone()),
                Err(e) => eprintln!("xr: bindings for {} not used: {e}", p.profile),
            }
        }
        Ok(a)
    }

    fn suggest(&self, instance: &xr::Instance, p: &ProfileBindings) -> Result<(), xr::sys::Result> {
        let profile = instance.string_to_path(&p.profile)?;
        let mut list = Vec::new();
        for (name, paths) in &p.bindings {
            for path in paths {
                let path = instance.string_to_path(path)?;
                list.push(match name.as_str() {
                    "grip_pose" => xr::Binding::new(&self.grip_pose, path),
                    "aim_pose" => xr::Binding::new(&self.aim_pose, path),
                    "grip" => xr::Binding::new(&self.grip, path),
                    "trigger" => xr::Binding::new(&self.trigger, path),
                    "primary" => xr::Binding::new(&self.primary, path),
                    "secondary" => xr::Binding::new(&self.secondary, path),
                    "menu" => xr::Binding::new(&self.menu, path),
                    "stick_click" => xr::Binding::new(&self.stick_click, path),
                    "thumbstick" => xr::Binding::new(&self.thumbstick, path),
                    "haptic" => xr::Binding::new(&self.haptic, path),
                    // bindings::parse rejects any other name.
                    _ => continue,
                });
            }
        }
        instance.suggest_interaction_profile_bindings(profile, &list)
    }

    /// The pose spaces of both hands for `session`.
    pub fn spaces<G: xr::Graphics>(&self, session: &xr::Session<G>) -> Result<HandSpaces, XrError> {
        let mk = |a: &xr::Action<xr::Posef>, h| a.create_space(session, h, xr::Posef::IDENTITY);
        Ok(HandSpaces {
            grip: [
                mk(&self.grip_pose, self.hands[LEFT])?,
                mk(&self.grip_pose, self.hands[RIGHT])?,
            ],
            aim: [
                mk(&self.aim_pose, self.hands[LEFT])?,
                mk(&self.aim_pose, self.hands[RIGHT])?,
            ],
        })
    }

    /// Reads both hands at `time` in `base`. Call after xrSyncActions. An untracked hand keeps
    /// its last known poses with `tracked = false` (OpenXR's poses are undefined then).
    pub fn read<G: xr::Graphics>(
        &mut self,
        session: &xr::Session<G>,
        spaces: &HandSpaces,
        base: &xr::Space,
        time: xr::Time,
    ) -> Result<[HandInput; 2], XrError> {
        let valid =
            xr::SpaceLocationFlags::POSITION_VALID | xr::SpaceLocationFlags::ORIENTATION_VALID;
        for h in [LEFT, RIGHT] {
            let path = self.hands[h];
            let grip = spaces.grip[h].locate(base, time)?;
            let aim = spaces.aim[h].locate(base, time)?;
            let active = self.grip_pose.is_active(session, path)?;
            let tracked = active && grip.location_flags.contains(valid);
            let last = &mut self.last[h];
            last.tracked = tracked;
            if tracked {
                last.grip = pose_from_xr(&grip.pose);
                last.aim = if aim.location_flags.contains(valid) {
                    pose_from_xr(&aim.pose)
                } else {
                    last.grip
                };
            }
            let f = |a: &xr::Action<f32>| a.state(session, path).map(|s| s.current_state);
            let b = |a: &xr::Action<bool>| a.state(session, path).map(|s| s.current_state);
            let stick = self.thumbstick.state(session, path)?.current_state;
            last.buttons = Buttons {
                grip: f(&self.grip)?,
                trigger: f(&self.trigger)?,
                primary: b(&self.primary)?,
                secondary: b(&self.secondary)?,
                menu: b(&self.menu)?,
                stick_click: b(&self.stick_click)?,
                thumbstick: Vec2::new(stick.x, stick.y),
            };
        }
        Ok(self.last)
    }

    /// Whether hand `h`'s controller is active (its grip pose action is bound and delivering):
    /// when it is not, a tracked hand takes its place.
    pub fn controller_active<G: xr::Graphics>(
        &self,
        session: &xr::Session<G>,
        h: usize,
    ) -> Result<bool, XrError> {
        Ok(self.grip_pose.is_active(session, self.hands[h])?)
    }

    /// A short pulse on one hand (the tool touching tissue).
    pub fn pulse<G: xr::Graphics>(
        &self,
        session: &xr::Session<G>,
        hand: usize,
    ) -> Result<(), XrError> {
        let v = xr::HapticVibration::new()
            .amplitude(0.6)
            .frequency(xr::FREQUENCY_UNSPECIFIED)
            .duration(xr::Duration::from_nanos(40_000_000));
        self.haptic.apply_feedback(session, self.hands[hand], &v)?;
        Ok(())
    }
}
