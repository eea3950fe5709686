//! The OpenXR side of a headset session, apart from what it renders: the runtime (instance,
//! system, the Vulkan device it creates), the session with its state machine, spaces, actions
//! and swapchains, and each frame's wait, locate, acquire, release and submit. The frame loop
//! that fills the images is the caller's (`app::headset`).

use super::blend::{choose_blend, BlendMode, Composition};
use super::conversions::pose_from_xr;
use super::conversions::{frame_views, projection_views};
use super::swapchain::{
    create_depth_swapchain, create_swapchain, layer_rect, record_blit, record_depth_copy, Swapchain,
};
use super::{
    actions, bindings, debug, gaze, open_instance, vulkan, Result, XrError, XrOptions, XrSummary,
    VIEW_TYPE,
};
use crate::gpu::{Gpu, GpuOptions};
use crate::input::hands::{HandGesture, HandJoints};
use crate::input::{FrameInput, RIGHT};
use crate::render::StereoTarget;
use crate::space::View;
use ash::vk::{self, Handle};
use openxr as xr;

/// The runtime: its instance and head-mounted system. It outlives the session and the Gpu it
/// creates; its fields drop top to bottom (the messenger before the instance).
pub struct XrRuntime {
    messenger: Option<debug::XrMessenger>,
    pub instance: xr::Instance,
    pub system: xr::SystemId,
    exts: xr::ExtensionSet,
    /// The runtime's name, as it reports it ("Monado(XRT) by Collabora et al ...").
    pub name: String,
    _entry: xr::Entry,
}

impl XrRuntime {
    /// Loads the runtime, finds its head-mounted display and checks it takes Vulkan 1.3.
    pub fn open() -> Result<XrRuntime> {
        let (entry, instance, exts) = open_instance()?;
        let messenger = debug::XrMessenger::new(&instance);
        let props = instance.properties()?;
        eprintln!(
            "xr: runtime {} {}",
            props.runtime_name, props.runtime_version
        );
        let system = instance
            .system(xr::FormFactor::HEAD_MOUNTED_DISPLAY)
            .map_err(|e| XrError::NoRuntime(format!("no head-mounted display: {e}")))?;
        let reqs = instance.graphics_requirements::<xr::Vulkan>(system)?;
        let want = xr::Version::new(1, 3, 0);
        if want < reqs.min_api_version_supported {
            return Err(XrError::Runtime(format!(
                "the runtime needs Vulkan {} or newer; cao-xr uses 1.3",
                reqs.min_api_version_supported
            )));
        }
        Ok(XrRuntime {
            messenger,
            name: props.runtime_name,
            instance,
            system,
            exts,
            _entry: entry,
        })
    }

    /// The Vulkan context, created through the runtime (XR_KHR_vulkan_enable2) on the physical
    /// device it names.
    pub fn create_gpu(&self, opts: &GpuOptions) -> Result<Gpu> {
        let mut factory = vulkan::XrVulkanFactory {
            instance: &self.instance,
            system: self.system,
            gipa: None,
        };
        // SAFETY: XrVulkanFactory hands the renderer's infos to xrCreateVulkanInstanceKHR /
        // xrCreateVulkanDeviceKHR as they are (the runtime only adds what it needs), as
        // with_factory requires; `self.instance` outlives the factory.
        Ok(unsafe { Gpu::with_factory(opts, &mut factory)? })
    }

    /// What the OpenXR validation layer reported so far.
    pub fn messages(&self) -> Vec<String> {
        self.messenger
            .as_ref()
            .map(|m| m.messages())
            .unwrap_or_default()
    }
}

/// What the loop must do on entering a session state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// READY: xrBeginSession, then run frames.
    Begin,
    /// STOPPING: stop frames, xrEndSession (a later READY begins again).
    End,
    /// EXITING: the runtime is done with the session; leave cleanly.
    Exit,
    /// LOSS_PENDING: the session is lost; leave with an error.
    Lost,
    Nothing,
}

/// The session state machine, apart from the calls it leads to, so the paths a runtime rarely
/// takes (a session that stops and begins again, a lost session) are tested without one.
#[derive(Clone, Copy, Debug, Default)]
pub struct StateMachine {
    /// Between xrBeginSession and xrEndSession: frames must be waited, begun and ended.
    pub running: bool,
    /// FOCUSED was reached at least once.
    pub focused: bool,
}

impl StateMachine {
    pub fn enter(&mut self, state: xr::SessionState) -> Step {
        match state {
            xr::SessionState::READY if !self.running => {
                self.running = true;
                Step::Begin
            }
            xr::SessionState::STOPPING if self.running => {
                self.running = false;
                Step::End
            }
            xr::SessionState::FOCUSED => {
                self.focused = true;
                Step::Nothing
            }
            xr::SessionState::EXITING => Step::Exit,
            xr::SessionState::LOSS_PENDING => Step::Lost,
            _ => Step::Nothing,
        }
    }
}

/// One frame the runtime wants drawn: when it will be displayed, and the input located for
/// that time (the views to render and submit, the hands).
pub struct XrFrame {
    pub time: xr::Time,
    pub input: FrameInput,
}

/// The swapchain images acquired for one frame, for the copy at the end of its command buffer.
pub struct FrameImages {
    color: vk::Image,
    depth: Option<vk::Image>,
    extent: (u32, u32),
}

impl FrameImages {
    /// Records the copy of both eyes (and their depth) from the finished stereo target.
    ///
    /// # Safety
    /// `cmd` is recording on `d`, the images are still acquired.
    pub unsafe fn record_copy(&self, d: &ash::Device, cmd: vk::CommandBuffer, src: &StereoTarget) {
        record_blit(d, cmd, src, self.color, self.extent);
        if let Some(depth) = self.depth {
            record_depth_copy(d, cmd, src, depth, self.extent);
        }
    }
}

/// A session with the runtime. Its fields are declared in teardown order (Rust drops them top
/// to bottom): swapchains and spaces before the session, and all of it before the runtime and
/// the Gpu, which the caller holds and which outlive it.
pub struct XrSession<'a> {
    /// XR_FB_passthrough's layer and feature, when frames composite over its cameras (the layer
    /// drops before the feature it was made from).
    fb_passthrough: Option<(xr::PassthroughLayerFB, xr::Passthrough)>,
    swapchain: Swapchain,
    depth_swapchain: Option<Swapchain>,
    spaces: actions::HandSpaces,
    /// XR_EXT_eye_gaze_interaction's action and its space, where the system tracks the eyes.
    gaze: Option<(gaze::EyeGaze, gaze::GazeSpace)>,
    base: xr::Space,
    stream: xr::FrameStream<xr::Vulkan>,
    waiter: xr::FrameWaiter,
    /// XR_EXT_hand_tracking's trackers (left, right), dropped before the session.
    hand_trackers: Option<[xr::HandTracker; 2]>,
    gestures: [HandGesture; 2],
    session: xr::Session<xr::Vulkan>,
    actions: actions::HandActions,
    runtime: &'a XrRuntime,
    /// The environment blend mode every frame is submitted with (and XR_FB_passthrough's
    /// layer under it, or not).
    pub blend: Composition,
    machine: StateMachine,
    exit_requested: bool,
    /// The first frame's display time: input times count from it.
    t0: Option<i64>,
    last_views: Option<[View; 2]>,
    pub summary: XrSummary,
}

impl<'a> XrSession<'a> {
    /// Creates the session on `gpu` (made by [`XrRuntime::create_gpu`]), its actions from the
    /// binding files, the STAGE (else LOCAL) space and the swapchains.
    pub fn new(runtime: &'a XrRuntime, gpu: &Gpu, opts: &XrOptions) -> Result<Self> {
        let (instance, system) = (&runtime.instance, runtime.system);
        // The blend mode first: a mode the runtime does not offer ends here, before a session.
        let offered: Vec<BlendMode> = instance
            .enumerate_environment_blend_modes(system, VIEW_TYPE)?
            .into_iter()
            .filter_map(BlendMode::from_xr)
            .collect();
        let blend = choose_blend(
            &offered,
            opts.blend,
            opts.passthrough,
            runtime.exts.fb_passthrough,
        )
        .map_err(XrError::Runtime)?;
        eprintln!(
            "xr: blend mode {} (the runtime offers {})",
            blend.name(),
            offered
                .iter()
                .map(|m| m.name())
                .collect::<Vec<_>>()
                .join(", ")
        );
        let profiles = bindings::load(
            opts.bindings
                .clone()
                .or_else(bindings::default_dir)
                .as_deref(),
        )?;
        let actions = actions::HandActions::new(instance, &profiles)?;
        eprintln!("xr: bindings for {}", actions.accepted.join(", "));
        let eye_gaze = gaze::EyeGaze::new(instance, system, runtime.exts.ext_eye_gaze_interaction)?;
        // SAFETY: the handles are the live instance, physical device and device of `gpu`, which
        // XrRuntime::create_gpu made through this runtime with queue 0 of `queue_family`; the
        // caller keeps `gpu` alive longer than the session (headset::run does).
        let (session, waiter, stream) = unsafe {
            instance.create_session::<xr::Vulkan>(
                system,
                &xr::vulkan::SessionCreateInfo {
                    instance: gpu.instance.handle().as_raw() as _,
                    physical_device: gpu.physical.as_raw() as _,
                    device: gpu.device.handle().as_raw() as _,
                    queue_family_index: gpu.queue_family,
                    queue_index: 0,
                },
            )?
        };
        let mut sets = vec![&actions.set];
        sets.extend(eye_gaze.as_ref().map(|g| &g.set));
        session.attach_action_sets(&sets)?;
        let spaces = actions.spaces(&session)?;
        let gaze = match eye_gaze {
            Some(g) => {
                let space = g.space(&session)?;
                Some((g, space))
            }
            None => None,
        };
        let (space, space_name) = if session
            .enumerate_reference_spaces()?
            .contains(&xr::ReferenceSpaceType::STAGE)
        {
            (xr::ReferenceSpaceType::STAGE, "STAGE")
        } else {
            (xr::ReferenceSpaceType::LOCAL, "LOCAL")
        };
        let base = session.create_reference_space(space, xr::Posef::IDENTITY)?;
        eprintln!("xr: reference space {space_name}");

        let views = instance.enumerate_view_configuration_views(system, VIEW_TYPE)?;
        if views.len() != 2 {
            return Err(XrError::Runtime(format!(
                "PRIMARY_STEREO has {} views, expected 2",
                views.len()
            )));
        }
        let extent = opts.size.unwrap_or((
            views[0].recommended_image_rect_width,
            views[0].recommended_image_rect_height,
        ));
        let extent = (
            extent.0.clamp(1, views[0].max_image_rect_width),
            extent.1.clamp(1, views[0].max_image_rect_height),
        );
        let swapchain = create_swapchain(&session, extent)?;
        eprintln!(
            "xr: swapchain {}x{} x2 layers, {:?}, {} images",
            extent.0,
            extent.1,
            swapchain.format,
            swapchain.images.len()
        );
        let (depth_swapchain, depth_missing) = if runtime.exts.khr_composition_layer_depth {
            match create_depth_swapchain(&session, extent)? {
                Some(d) => {
                    eprintln!(
                        "xr: depth swapchain {}x{} x2 layers, {:?}, {} images (XR_KHR_composition_layer_depth)",
                        extent.0,
                        extent.1,
                        d.format,
                        d.images.len()
                    );
                    (Some(d), None)
                }
                None => (
                    None,
                    Some("the runtime offers no D32_SFLOAT depth swapchain".to_string()),
                ),
            }
        } else {
            (
                None,
                Some("runtime lacks XR_KHR_composition_layer_depth".to_string()),
            )
        };
        if let Some(why) = &depth_missing {
            eprintln!("xr: no depth layer: {why}");
        }
        let eye_gaze_ok = gaze.is_some();
        let hand_trackers = hand_trackers(runtime, &session);
        let hand_trackers_ok = hand_trackers.is_some();
        let fb_passthrough = if blend.fb_passthrough {
            // Created running: openxr 0.22's Passthrough::start calls the pause function.
            let running = xr::PassthroughFlagsFB::IS_RUNNING_AT_CREATION;
            let feature = session.create_passthrough(running)?;
            let layer = session.create_passthrough_layer(
                &feature,
                running,
                xr::PassthroughLayerPurposeFB::RECONSTRUCTION,
            )?;
            Some((layer, feature))
        } else {
            None
        };
        Ok(XrSession {
            fb_passthrough,
            hand_trackers,
            gestures: [HandGesture::default(); 2],
            swapchain,
            depth_swapchain,
            spaces,
            gaze,
            base,
            stream,
            waiter,
            session,
            actions,
            runtime,
            blend,
            machine: StateMachine::default(),
            exit_requested: false,
            t0: None,
            last_views: None,
            summary: XrSummary {
                space: space_name.into(),
                depth_missing,
                hand_tracking: hand_trackers_ok,
                eye_gaze: eye_gaze_ok,
                blend: blend.name(),
                blend_offered: offered.iter().map(|m| m.name().to_string()).collect(),
                ..Default::default()
            },
        })
    }

    /// Pixels per eye of the swapchain images.
    pub fn extent(&self) -> (u32, u32) {
        self.swapchain.extent
    }

    /// Handles the pending events through the state machine: READY begins the session,
    /// STOPPING ends it (a later READY begins it again). Returns false once the runtime is done
    /// with the session (EXITING); a lost session or instance is an error.
    pub fn poll_events(&mut self) -> Result<bool> {
        let mut events = xr::EventDataBuffer::new();
        while let Some(event) = self.runtime.instance.poll_event(&mut events)? {
            match event {
                xr::Event::SessionStateChanged(e) => {
                    let state = e.state();
                    eprintln!("xr: session state {state:?}");
                    self.summary.states.push(format!("{state:?}"));
                    match self.machine.enter(state) {
                        Step::Begin => {
                            self.session.begin(VIEW_TYPE)?;
                        }
                        Step::End => {
                            self.session.end()?;
                        }
                        Step::Exit => return Ok(false),
                        Step::Lost => {
                            return Err(XrError::Runtime(
                                "the runtime lost the session (LOSS_PENDING)".into(),
                            ))
                        }
                        Step::Nothing => {}
                    }
                    self.summary.focused |= self.machine.focused;
                }
                xr::Event::InstanceLossPending(_) => {
                    return Err(XrError::Runtime(
                        "the runtime is going away (instance loss pending)".into(),
                    ))
                }
                xr::Event::EventsLost(e) => {
                    eprintln!("xr: {} events lost", e.lost_event_count())
                }
                _ => {}
            }
        }
        Ok(true)
    }

    /// Between xrBeginSession and xrEndSession: frames must be waited, begun and ended.
    pub fn running(&self) -> bool {
        self.machine.running
    }

    /// Asks the runtime to end the session (once); it answers with STOPPING, then EXITING.
    pub fn request_exit(&mut self) -> Result<()> {
        if !self.exit_requested {
            eprintln!(
                "xr: {} frames submitted, requesting exit",
                self.summary.frames
            );
            self.session.request_exit()?;
            self.exit_requested = true;
        }
        Ok(())
    }

    /// Waits for and begins the next frame, and locates the eyes and hands at its predicted
    /// display time; with `carve` the right trigger is held. None when there is nothing to
    /// draw (the runtime says not to render, `skip`, or no valid head pose yet): that frame is
    /// ended empty here.
    pub fn begin_frame(&mut self, skip: bool, carve: bool) -> Result<Option<XrFrame>> {
        let fs = self.waiter.wait()?;
        self.stream.begin()?;
        let time = fs.predicted_display_time;
        if !fs.should_render || skip {
            self.stream.end(time, self.blend.blend.to_xr(), &[])?;
            return Ok(None);
        }
        let mut active = vec![xr::ActiveActionSet::new(&self.actions.set)];
        active.extend(
            self.gaze
                .as_ref()
                .map(|g| xr::ActiveActionSet::new(&g.0.set)),
        );
        self.session.sync_actions(&active)?;
        let (flags, located) = self.session.locate_views(VIEW_TYPE, time, &self.base)?;
        let Some(views) = frame_views(flags, &located, &mut self.last_views) else {
            self.stream.end(time, self.blend.blend.to_xr(), &[])?;
            return Ok(None);
        };
        let mut hands = self
            .actions
            .read(&self.session, &self.spaces, &self.base, time)?;
        // A hand whose controller is not active drives the interaction with its joints.
        let mut joints = [None; 2];
        if let Some(trackers) = &self.hand_trackers {
            for (h, tracker) in trackers.iter().enumerate() {
                let active = self.actions.controller_active(&self.session, h)?;
                if active {
                    continue;
                }
                joints[h] = self
                    .base
                    .locate_hand_joints(tracker, time)?
                    .and_then(|locs| hand_joints_from_xr(&locs));
                hands[h] = self.gestures[h].update(joints[h].as_ref());
            }
            if joints.iter().any(|j| j.is_some()) {
                self.summary.hand_frames += 1;
            }
        }
        if carve {
            hands[RIGHT].buttons.trigger = hands[RIGHT].buttons.trigger.max(1.0);
        }
        if hands.iter().any(|h| h.tracked) {
            self.summary.tracked_frames += 1;
        }
        let gaze = match &self.gaze {
            Some((g, space)) => g.read(&self.session, space, &self.base, time)?,
            None => None,
        };
        self.summary.gaze_frames += gaze.is_some() as usize;
        let start = *self.t0.get_or_insert(time.as_nanos());
        Ok(Some(XrFrame {
            time,
            input: FrameInput {
                time: (time.as_nanos() - start) as f64 * 1e-9,
                views,
                hands,
                joints,
                gaze,
            },
        }))
    }

    /// Acquires and waits this frame's swapchain images; [`XrSession::release`] gives them back.
    pub fn acquire(&mut self) -> Result<FrameImages> {
        let sc = &mut self.swapchain;
        let index = sc.handle.acquire_image()?;
        sc.handle.wait_image(xr::Duration::INFINITE)?;
        let depth = match &mut self.depth_swapchain {
            Some(ds) => {
                let i = ds.handle.acquire_image();
                let i = i.and_then(|i| ds.handle.wait_image(xr::Duration::INFINITE).map(|_| i));
                match i {
                    Ok(i) => Some(ds.images[i as usize]),
                    Err(e) => {
                        sc.handle.release_image()?;
                        return Err(e.into());
                    }
                }
            }
            None => None,
        };
        Ok(FrameImages {
            color: sc.images[index as usize],
            depth,
            extent: sc.extent,
        })
    }

    /// Gives the acquired images back (also after a failed frame, so none is left waited).
    pub fn release(&mut self) -> Result<()> {
        self.swapchain.handle.release_image()?;
        if let Some(ds) = &mut self.depth_swapchain {
            ds.handle.release_image()?;
        }
        Ok(())
    }

    /// A short haptic pulse on `hand`.
    pub fn pulse(&mut self, hand: usize) -> Result<()> {
        self.actions.pulse(&self.session, hand)?;
        self.summary.pulses += 1;
        Ok(())
    }

    /// Ends the frame with its projection layer, submitting the views the image was rendered
    /// with (the swapchain images were filled from `src` and released by then) and the part of
    /// the images it filled ([`layer_rect`]: all, or less under a render scale).
    pub fn end_frame(&mut self, frame: &XrFrame, src: &StereoTarget) -> Result<()> {
        let (time, views) = (frame.time, projection_views(&frame.input.views));
        let sc = &self.swapchain;
        let (w, h) = layer_rect(src, sc.extent);
        let rect = xr::Rect2Di {
            offset: xr::Offset2Di { x: 0, y: 0 },
            extent: xr::Extent2Di {
                width: w as i32,
                height: h as i32,
            },
        };
        let proj = [0u32, 1].map(|eye| {
            xr::CompositionLayerProjectionView::new()
                .pose(views[eye as usize].pose)
                .fov(views[eye as usize].fov)
                .sub_image(
                    xr::SwapchainSubImage::new()
                        .swapchain(&sc.handle)
                        .image_array_index(eye)
                        .image_rect(rect),
                )
        });
        // XR_KHR_composition_layer_depth: each view's depth, chained to it. The projection
        // is a standard Vulkan one: depth 0 at NEAR, 1 at FAR (crate::space).
        let depth_info = self.depth_swapchain.as_ref().map(|ds| {
            [0u32, 1].map(|eye| xr::sys::CompositionLayerDepthInfoKHR {
                ty: xr::sys::CompositionLayerDepthInfoKHR::TYPE,
                next: std::ptr::null(),
                sub_image: xr::sys::SwapchainSubImage {
                    swapchain: ds.handle.as_raw(),
                    image_rect: rect,
                    image_array_index: eye,
                },
                min_depth: 0.0,
                max_depth: 1.0,
                near_z: crate::space::NEAR,
                far_z: crate::space::FAR,
            })
        });
        let proj = match &depth_info {
            Some(info) => [0, 1].map(|eye| {
                let mut raw = *proj[eye].as_raw();
                raw.next = &info[eye] as *const _ as *const std::ffi::c_void;
                // SAFETY: `info` outlives the xrEndFrame below, the only use of the chain.
                unsafe { xr::CompositionLayerProjectionView::from_raw(raw) }
            }),
            None => proj,
        };
        let mut layer = xr::CompositionLayerProjection::new()
            .space(&self.base)
            .views(&proj);
        if self.blend.source_alpha() {
            // Premultiplied colour, alpha = the volume's accumulated opacity: the runtime
            // composites the layer over the world (or the passthrough layer) by its alpha.
            layer = layer.layer_flags(xr::CompositionLayerFlags::BLEND_TEXTURE_SOURCE_ALPHA);
        }
        let mode = self.blend.blend.to_xr();
        match &self.fb_passthrough {
            // The cameras' layer first, so the volume's layer composites over it.
            Some((cameras, _)) => {
                let raw = xr::sys::CompositionLayerPassthroughFB {
                    ty: xr::sys::CompositionLayerPassthroughFB::TYPE,
                    next: std::ptr::null(),
                    flags: xr::CompositionLayerFlags::BLEND_TEXTURE_SOURCE_ALPHA,
                    space: <xr::sys::Space as xr::sys::Handle>::NULL,
                    layer_handle: cameras.as_raw(),
                };
                // SAFETY: openxr 0.22 builds this layer but does not export its builder; every
                // XrCompositionLayer* begins with the base header (type, next), which is all
                // that CompositionLayerBase wraps (repr(transparent)), and `raw` outlives the
                // xrEndFrame below.
                let under: &xr::CompositionLayerBase<xr::Vulkan> =
                    unsafe { &*(&raw as *const _ as *const xr::CompositionLayerBase<xr::Vulkan>) };
                self.stream.end(time, mode, &[under, &layer])?;
            }
            None => self.stream.end(time, mode, &[&layer])?,
        }
        if depth_info.is_some() {
            self.summary.depth_frames += 1;
        }
        self.summary.frames += 1;
        Ok(())
    }
}

/// Both hands' trackers when the runtime offers XR_EXT_hand_tracking and the system supports
/// it; None (logged) otherwise, so a runtime without hands still runs with controllers.
fn hand_trackers(
    runtime: &XrRuntime,
    session: &xr::Session<xr::Vulkan>,
) -> Option<[xr::HandTracker; 2]> {
    if !runtime.exts.ext_hand_tracking {
        eprintln!("xr: no hand tracking: the runtime lacks XR_EXT_hand_tracking");
        return None;
    }
    match runtime.instance.supports_hand_tracking(runtime.system) {
        Ok(true) => {}
        Ok(false) => {
            eprintln!("xr: no hand tracking: the system does not support it");
            return None;
        }
        Err(e) => {
            eprintln!("xr: no hand tracking: {e}");
            return None;
        }
    }
    let make = |hand| session.create_hand_tracker(hand);
    match (make(xr::Hand::LEFT), make(xr::Hand::RIGHT)) {
        (Ok(l), Ok(r)) => {
            eprintln!("xr: hand tracking on (XR_EXT_hand_tracking)");
            Some([l, r])
        }
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("xr: no hand tracking: xrCreateHandTrackerEXT failed: {e}");
            None
        }
    }
}

/// The 26 joints as [`HandJoints`], when every one has a valid position and orientation.
fn hand_joints_from_xr(locs: &xr::HandJointLocations) -> Option<HandJoints> {
    let valid = xr::SpaceLocationFlags::POSITION_VALID | xr::SpaceLocationFlags::ORIENTATION_VALID;
    if !locs.iter().all(|l| l.location_flags.contains(valid)) {
        return None;
    }
    let poses = std::array::from_fn(|k| pose_from_xr(&locs[k].pose));
    let radii = std::array::from_fn(|k| locs[k].radius);
    Some(HandJoints { poses, radii })
}

#[cfg(test)]
mod tests {
    use super::*;
    use xr::SessionState as S;

    #[test]
    fn a_session_that_stops_begins_again_and_exits_cleanly() {
        let mut m = StateMachine::default();
        let run = [
            S::IDLE,
            S::READY,
            S::SYNCHRONIZED,
            S::VISIBLE,
            S::FOCUSED,
            S::VISIBLE,
            S::SYNCHRONIZED,
            S::STOPPING,
            S::IDLE,
            S::READY,
            S::SYNCHRONIZED,
            S::STOPPING,
            S::IDLE,
            S::EXITING,
        ];
        let steps: Vec<Step> = run.iter().map(|s| m.enter(*s)).collect();
        let count = |k| steps.iter().filter(|s| **s == k).count();
        assert_eq!(count(Step::Begin), 2);
        assert_eq!(count(Step::End), 2);
        assert_eq!(steps.last(), Some(&Step::Exit));
        assert!(m.focused && !m.running);
    }

    #[test]
    fn loss_pending_is_an_error_and_running_state_is_tracked() {
        let mut m = StateMachine::default();
        assert_eq!(m.enter(S::READY), Step::Begin);
        assert!(m.running);
        assert_eq!(m.enter(S::LOSS_PENDING), Step::Lost);
    }
}
