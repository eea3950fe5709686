//! XR_EXT_eye_gaze_interaction: where the eyes look, so that the foveated ray cast spends its
//! full rate there. Used where the runtime offers the extension and the system says it tracks
//! the eyes; elsewhere (said once in the log) each eye's foveation centres on its lens.

use super::conversions::pose_from_xr;
use super::XrError;
use crate::space::Pose;
use openxr as xr;

/// The interaction profile and the input path the extension defines.
const PROFILE: &str = "/interaction_profiles/ext/eye_gaze_interaction";
const GAZE_POSE: &str = "/user/eyes_ext/input/gaze_ext/pose";

/// The gaze action in its own action set, with its binding suggested.
pub struct EyeGaze {
    pub set: xr::ActionSet,
    pose: xr::Action<xr::Posef>,
}

/// The gaze action's space; it belongs to one session.
pub struct GazeSpace(xr::Space);

impl EyeGaze {
    /// The gaze action where the runtime offers the extension (`enabled`) and `system` tracks
    /// the eyes; None otherwise, with the reason logged.
    pub fn new(
        instance: &xr::Instance,
        system: xr::SystemId,
        enabled: bool,
    ) -> Result<Option<EyeGaze>, XrError> {
        if !enabled {
            eprintln!("xr: no eye gaze: the runtime lacks XR_EXT_eye_gaze_interaction");
            return Ok(None);
        }
        match supports_eye_gaze(instance, system) {
            Ok(true) => {}
            Ok(false) => {
                eprintln!("xr: no eye gaze: the system does not track the eyes");
                return Ok(None);
            }
            Err(e) => {
                eprintln!("xr: no eye gaze: {e}");
                return Ok(None);
            }
        }
        let set = instance.create_action_set("eyes", "Eyes", 0)?;
        let pose = set.create_action("gaze_pose", "Gaze pose", &[])?;
        let binding = [xr::Binding::new(&pose, instance.string_to_path(GAZE_POSE)?)];
        instance
            .suggest_interaction_profile_bindings(instance.string_to_path(PROFILE)?, &binding)?;
        eprintln!("xr: eye gaze on (XR_EXT_eye_gaze_interaction)");
        Ok(Some(EyeGaze { set, pose }))
    }

    /// The gaze pose's space for `session`.
    pub fn space<G: xr::Graphics>(&self, session: &xr::Session<G>) -> Result<GazeSpace, XrError> {
        let space = self
            .pose
            .create_space(session, xr::Path::NULL, xr::Posef::IDENTITY)?;
        Ok(GazeSpace(space))
    }

    /// The gaze at `time` in `base`, where it is tracked now (call after xrSyncActions).
    pub fn read<G: xr::Graphics>(
        &self,
        session: &xr::Session<G>,
        space: &GazeSpace,
        base: &xr::Space,
        time: xr::Time,
    ) -> Result<Option<Pose>, XrError> {
        if !self.pose.is_active(session, xr::Path::NULL)? {
            return Ok(None);
        }
        let at = space.0.locate(base, time)?;
        let tracked = xr::SpaceLocationFlags::ORIENTATION_TRACKED
            | xr::SpaceLocationFlags::ORIENTATION_VALID
            | xr::SpaceLocationFlags::POSITION_VALID;
        Ok(at
            .location_flags
            .contains(tracked)
            .then(|| pose_from_xr(&at.pose)))
    }
}

/// XrSystemEyeGazeInteractionPropertiesEXT::supportsEyeGazeInteraction for `system`.
fn supports_eye_gaze(instance: &xr::Instance, system: xr::SystemId) -> xr::Result<bool> {
    let mut gaze = xr::sys::SystemEyeGazeInteractionPropertiesEXT::out(std::ptr::null_mut());
    let mut props = xr::sys::SystemProperties::out(gaze.as_mut_ptr() as *mut _);
    // SAFETY: both structures are typed and chained as xrGetSystemProperties expects; it fills
    // every field before they are read (a failure returns before any read).
    unsafe {
        let r =
            (instance.fp().get_system_properties)(instance.as_raw(), system, props.as_mut_ptr());
        if r.into_raw() < 0 {
            return Err(r);
        }
        Ok(gaze.assume_init().supports_eye_gaze_interaction.into())
    }
}
