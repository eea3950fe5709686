//! `cao-xr xr`: the headset path. OpenXR (XR_KHR_vulkan_enable2) creates the renderer's Vulkan
//! instance and device, the session runs the full state machine, each frame's predicted display
//! time locates the eyes and hands, the one frame loop renders both eyes, and the stereo target
//! is copied into the runtime's swapchain and submitted as a projection layer.
//!
//! Choices, and why:
//! - One array swapchain with two layers (layer 0 = left eye), the same shape as the renderer's
//!   [`StereoTarget`](crate::render::StereoTarget), so both eyes go over in one blit region.
//! - UNORM swapchain formats are preferred: the renderer writes display-ready UNORM values, and
//!   a blit into an sRGB image would encode them a second time.
//! - STAGE space (DESIGN.md's world), LOCAL when the runtime has no STAGE.
//! - Bindings are data ([`bindings`]): a new controller is a new JSON file.

pub mod actions;
pub mod bindings;
pub mod debug;
pub mod vulkan;

use crate::ao::LaoParams;
use crate::app::frame_loop::FrameLoop;
use crate::app::AppError;
use crate::gpu::{cmd_image_barrier, Gpu, GpuError, GpuOptions};
use crate::input::{FrameInput, InteractionSettings, PoseStreamWriter, StreamHeader, RIGHT};
use crate::render::view::{Fov, Pose, View};
use crate::render::StereoTarget;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use ash::vk::{self, Handle};
use glam::{Quat, Vec3};
use openxr as xr;
use std::path::PathBuf;

const VIEW_TYPE: xr::ViewConfigurationType = xr::ViewConfigurationType::PRIMARY_STEREO;

#[derive(Debug, thiserror::Error)]
pub enum XrError {
    #[error("no OpenXR runtime: {0} (install an OpenXR loader and runtime, e.g. Monado, or use `cao-xr view`)")]
    NoRuntime(String),
    #[error("OpenXR call failed: {0}")]
    Xr(#[from] xr::sys::Result),
    #[error(transparent)]
    App(#[from] AppError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Bindings(#[from] bindings::BindingsError),
    #[error("{0}")]
    Runtime(String),
    #[error("{path}: {msg}")]
    Output { path: String, msg: String },
}

pub type Result<T> = std::result::Result<T, XrError>;

#[derive(Clone, Debug, Default)]
pub struct XrOptions {
    /// Submit this many rendered frames, then ask the runtime to end the session.
    pub frames: Option<usize>,
    /// Record every rendered frame's input as a pose stream.
    pub record: Option<PathBuf>,
    /// Pixels per eye; default: the runtime's recommended size.
    pub size: Option<(u32, u32)>,
    /// Directory of binding files; default [`bindings::default_dir`], else the built-in set.
    pub bindings: Option<PathBuf>,
    /// Hold the right trigger (carving on from the first frame), for controllers that cannot
    /// press buttons (simulated ones in tests). The held trigger is part of the recorded input,
    /// so a replay carves the same way.
    pub carve: bool,
    /// Where the volume's centre starts, in the reference space (default: the scene's).
    pub volume_at: Option<Vec3>,
    /// Also show the left eye in a desktop window (X11), presented after each headset frame.
    pub mirror: bool,
    pub lighting: crate::app::lighting::LightingOptions,
}

/// What a session did.
#[derive(Clone, Debug, Default)]
pub struct XrSummary {
    /// Frames rendered and submitted with a projection layer.
    pub frames: usize,
    /// Every session state entered, in order.
    pub states: Vec<String>,
    pub focused: bool,
    /// Haptic pulses sent (tool first touching tissue).
    pub pulses: usize,
    /// Frames in which at least one hand was tracked.
    pub tracked_frames: usize,
    /// The reference space used (STAGE or LOCAL).
    pub space: String,
    /// Frames submitted with depth (XR_KHR_composition_layer_depth) on every projection view.
    pub depth_frames: usize,
    /// Why depth was not submitted (None when it was offered and used).
    pub depth_missing: Option<String>,
}

/// Parses `X,Y,Z` (metres) for the command line.
pub fn parse_point(s: &str) -> std::result::Result<Vec3, String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|c| c.trim().parse::<f32>().ok().filter(|x| x.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("'{s}': expected X,Y,Z in metres, e.g. 0,1.4,-0.6"))?;
    match v[..] {
        [x, y, z] => Ok(Vec3::new(x, y, z)),
        _ => Err(format!("'{s}': expected three numbers X,Y,Z")),
    }
}

pub(crate) fn pose_from_xr(p: &xr::Posef) -> Pose {
    let q = Quat::from_xyzw(
        p.orientation.x,
        p.orientation.y,
        p.orientation.z,
        p.orientation.w,
    );
    Pose {
        position: Vec3::new(p.position.x, p.position.y, p.position.z),
        orientation: if q.length_squared() > 0.5 {
            q.normalize()
        } else {
            Quat::IDENTITY
        },
    }
}

fn fov_from_xr(f: &xr::Fovf) -> Fov {
    Fov {
        angle_left: f.angle_left,
        angle_right: f.angle_right,
        angle_up: f.angle_up,
        angle_down: f.angle_down,
    }
}

/// Whether an OpenXR loader is installed and a runtime answers with a head-mounted display;
/// the CLI's default run uses this to choose between the headset and the desktop window.
pub fn available() -> bool {
    (|| -> Result<()> {
        let (_, instance, _) = open_instance()?;
        instance.system(xr::FormFactor::HEAD_MOUNTED_DISPLAY)?;
        Ok(())
    })()
    .is_ok()
}

fn open_instance() -> Result<(xr::Entry, xr::Instance, xr::ExtensionSet)> {
    let entry = unsafe { xr::Entry::load(&()) }.map_err(|e| XrError::NoRuntime(e.to_string()))?;
    let available = entry
        .enumerate_extensions()
        .map_err(|e| XrError::NoRuntime(e.to_string()))?;
    if !available.khr_vulkan_enable2 {
        return Err(XrError::NoRuntime(
            "the runtime lacks XR_KHR_vulkan_enable2".into(),
        ));
    }
    let mut exts = xr::ExtensionSet::default();
    exts.khr_vulkan_enable2 = true;
    // For the messenger that reports the OpenXR validation layer (debug::XrMessenger).
    exts.ext_debug_utils = available.ext_debug_utils;
    // Depth submitted with each projection view, when the runtime takes it (reprojection).
    exts.khr_composition_layer_depth = available.khr_composition_layer_depth;
    let instance = entry
        .create_instance(
            &xr::ApplicationInfo {
                application_name: "cao-xr",
                application_version: 1,
                engine_name: "cao-xr",
                engine_version: 1,
                api_version: xr::Version::new(1, 0, 0),
            },
            &exts,
            &[],
            &(),
        )
        .map_err(|e| XrError::NoRuntime(format!("xrCreateInstance: {e}")))?;
    Ok((entry, instance, exts))
}

/// The runtime's swapchain: one image array with a layer per eye.
struct Swapchain {
    handle: xr::Swapchain<xr::Vulkan>,
    images: Vec<vk::Image>,
    extent: (u32, u32),
    format: vk::Format,
}

/// Runs a headset session until the runtime ends it (or `frames` were submitted).
pub fn run(
    vol: &Volume,
    tf: &TransferFunction,
    params: LaoParams,
    opts: XrOptions,
) -> Result<XrSummary> {
    let profiles = bindings::load(
        opts.bindings
            .clone()
            .or_else(bindings::default_dir)
            .as_deref(),
    )?;
    let (_entry, instance, exts) = open_instance()?;
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
    let mut factory = vulkan::XrVulkanFactory {
        instance: &instance,
        system,
        gipa: None,
    };
    let gpu_opts = GpuOptions {
        present: opts.mirror,
        ..Default::default()
    };
    let gpu = unsafe { Gpu::with_factory(&gpu_opts, &mut factory)? };
    eprintln!(
        "xr: GPU {}{}",
        gpu.device_name,
        if gpu.validation_enabled() {
            " (validation on)"
        } else {
            ""
        }
    );
    let actions = actions::HandActions::new(&instance, &profiles)?;
    eprintln!("xr: bindings for {}", actions.accepted.join(", "));

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
    session.attach_action_sets(&[&actions.set])?;
    let spaces = actions.spaces(&session)?;
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
    let (depth_swapchain, depth_missing) = if exts.khr_composition_layer_depth {
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
    let blend = instance.enumerate_environment_blend_modes(system, VIEW_TYPE)?[0];

    let fl = FrameLoop::new(
        &gpu,
        vol,
        crate::app::frame_loop::tf_cycle(tf, vol),
        params,
        extent,
        InteractionSettings::default(),
        false,
    )?;
    let mut fl = fl;
    fl.set_lighting(&opts.lighting, false)?;
    if let Some(c) = opts.volume_at {
        fl.scene.volume.center = c;
    }
    let mirror = if opts.mirror {
        Some(crate::app::desktop::Mirror::new(&gpu, extent)?)
    } else {
        None
    };
    let recorder = match &opts.record {
        Some(p) => Some(
            PoseStreamWriter::create(
                p,
                &StreamHeader::new(
                    "xr",
                    format!("cao-xr xr of {} on {}", vol.name, props.runtime_name),
                ),
            )
            .map_err(|e| XrError::Output {
                path: p.display().to_string(),
                msg: e.to_string(),
            })?,
        ),
        None => None,
    };
    let mut s = SessionLoop {
        opts,
        instance: &instance,
        session,
        waiter,
        stream,
        actions,
        spaces,
        base,
        swapchain,
        depth_swapchain,
        blend,
        fl,
        mirror,
        recorder,
        summary: XrSummary {
            space: space_name.into(),
            depth_missing,
            ..Default::default()
        },
    };
    let result = s.run();
    unsafe {
        let _ = gpu.device.device_wait_idle();
    }
    let SessionLoop {
        session,
        waiter,
        stream,
        spaces,
        base,
        swapchain,
        depth_swapchain,
        fl,
        mirror,
        recorder,
        summary,
        actions,
        ..
    } = s;
    // The runtime's objects go before the Vulkan device they use, and that before the XR
    // instance that created it.
    drop((
        swapchain,
        depth_swapchain,
        spaces,
        base,
        stream,
        waiter,
        session,
    ));
    drop(mirror);
    drop(fl);
    let messages = gpu.validation_messages();
    drop(gpu);
    drop(actions);
    let xr_messages = messenger.as_ref().map(|m| m.messages()).unwrap_or_default();
    drop(messenger);
    drop(instance);
    result?;
    if let Some(r) = recorder {
        r.finish().map_err(|e| XrError::Output {
            path: "record".into(),
            msg: e.to_string(),
        })?;
    }
    if !xr_messages.is_empty() {
        return Err(XrError::Runtime(format!(
            "{} OpenXR validation messages (first: {})",
            xr_messages.len(),
            xr_messages[0]
        )));
    }
    if !messages.is_empty() {
        return Err(XrError::Runtime(format!(
            "{} Vulkan validation messages (first: {})",
            messages.len(),
            messages[0]
        )));
    }
    Ok(summary)
}

fn create_swapchain(session: &xr::Session<xr::Vulkan>, extent: (u32, u32)) -> Result<Swapchain> {
    let offered: Vec<vk::Format> = session
        .enumerate_swapchain_formats()?
        .into_iter()
        .map(|f| vk::Format::from_raw(f as i32))
        .collect();
    let format = [
        vk::Format::R8G8B8A8_UNORM,
        vk::Format::B8G8R8A8_UNORM,
        vk::Format::R8G8B8A8_SRGB,
        vk::Format::B8G8R8A8_SRGB,
    ]
    .into_iter()
    .find(|f| offered.contains(f))
    .ok_or_else(|| {
        XrError::Runtime(format!(
            "the runtime offers no 8-bit RGBA swapchain format (offered: {offered:?})"
        ))
    })?;
    two_layer_swapchain(
        session,
        format,
        xr::SwapchainUsageFlags::COLOR_ATTACHMENT,
        extent,
    )
}

/// A two-layer array swapchain (layer 0 = left eye) that the frame's copy writes into.
fn two_layer_swapchain(
    session: &xr::Session<xr::Vulkan>,
    format: vk::Format,
    attachment: xr::SwapchainUsageFlags,
    extent: (u32, u32),
) -> Result<Swapchain> {
    let handle = session.create_swapchain(&xr::SwapchainCreateInfo {
        create_flags: xr::SwapchainCreateFlags::EMPTY,
        usage_flags: xr::SwapchainUsageFlags::TRANSFER_DST | attachment,
        format: format.as_raw() as _,
        sample_count: 1,
        width: extent.0,
        height: extent.1,
        face_count: 1,
        array_size: 2,
        mip_count: 1,
    })?;
    let images = handle
        .enumerate_images()?
        .into_iter()
        .map(vk::Image::from_raw)
        .collect();
    Ok(Swapchain {
        handle,
        images,
        extent,
        format,
    })
}

/// The depth swapchain for XR_KHR_composition_layer_depth: two layers like the colour one, in
/// the renderer's own depth format so the eyes' depth goes over with a plain copy (a depth
/// image cannot be blitted into another format). None when the runtime does not offer it.
fn create_depth_swapchain(
    session: &xr::Session<xr::Vulkan>,
    extent: (u32, u32),
) -> Result<Option<Swapchain>> {
    let format = crate::render::DEPTH_FORMAT;
    let offered = session.enumerate_swapchain_formats()?;
    if !offered.contains(&(format.as_raw() as _)) {
        return Ok(None);
    }
    two_layer_swapchain(
        session,
        format,
        xr::SwapchainUsageFlags::DEPTH_STENCIL_ATTACHMENT,
        extent,
    )
    .map(Some)
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

struct SessionLoop<'a> {
    opts: XrOptions,
    instance: &'a xr::Instance,
    session: xr::Session<xr::Vulkan>,
    waiter: xr::FrameWaiter,
    stream: xr::FrameStream<xr::Vulkan>,
    actions: actions::HandActions,
    spaces: actions::HandSpaces,
    base: xr::Space,
    swapchain: Swapchain,
    depth_swapchain: Option<Swapchain>,
    blend: xr::EnvironmentBlendMode,
    fl: FrameLoop,
    mirror: Option<crate::app::desktop::Mirror>,
    recorder: Option<PoseStreamWriter<std::io::BufWriter<std::fs::File>>>,
    summary: XrSummary,
}

impl SessionLoop<'_> {
    /// The session state machine: READY begins the session, STOPPING ends it (and a later
    /// READY begins it again), EXITING and LOSS_PENDING leave; frames run while it is running.
    fn run(&mut self) -> Result<()> {
        let mut events = xr::EventDataBuffer::new();
        let mut machine = StateMachine::default();
        let mut exit_requested = false;
        let mut t0: Option<i64> = None;
        let mut last_views: Option<[View; 2]> = None;
        let mut prev_clipped = 0u64;
        loop {
            while let Some(event) = self.instance.poll_event(&mut events)? {
                match event {
                    xr::Event::SessionStateChanged(e) => {
                        let state = e.state();
                        eprintln!("xr: session state {state:?}");
                        self.summary.states.push(format!("{state:?}"));
                        match machine.enter(state) {
                            Step::Begin => {
                                self.session.begin(VIEW_TYPE)?;
                            }
                            Step::End => {
                                self.session.end()?;
                            }
                            Step::Exit => return Ok(()),
                            Step::Lost => {
                                return Err(XrError::Runtime(
                                    "the runtime lost the session (LOSS_PENDING)".into(),
                                ))
                            }
                            Step::Nothing => {}
                        }
                        self.summary.focused |= machine.focused;
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
            if !machine.running {
                std::thread::sleep(std::time::Duration::from_millis(10));
                continue;
            }
            let done = self.opts.frames.is_some_and(|n| self.summary.frames >= n);
            if done && !exit_requested {
                eprintln!(
                    "xr: {} frames submitted, requesting exit",
                    self.summary.frames
                );
                self.session.request_exit()?;
                exit_requested = true;
            }
            let fs = self.waiter.wait()?;
            self.stream.begin()?;
            let time = fs.predicted_display_time;
            if !fs.should_render || done {
                self.stream.end(time, self.blend, &[])?;
                continue;
            }
            self.session
                .sync_actions(&[xr::ActiveActionSet::new(&self.actions.set)])?;
            let (flags, xr_views) = self.session.locate_views(VIEW_TYPE, time, &self.base)?;
            let valid = flags.contains(xr::ViewStateFlags::ORIENTATION_VALID)
                && flags.contains(xr::ViewStateFlags::POSITION_VALID);
            let views = if valid && xr_views.len() == 2 {
                let v = [0, 1].map(|i| View {
                    pose: pose_from_xr(&xr_views[i].pose),
                    fov: fov_from_xr(&xr_views[i].fov),
                });
                last_views = Some(v);
                v
            } else if let Some(v) = last_views {
                v
            } else {
                // No head pose yet: nothing sensible to draw.
                self.stream.end(time, self.blend, &[])?;
                continue;
            };
            let mut hands = self
                .actions
                .read(&self.session, &self.spaces, &self.base, time)?;
            if self.opts.carve {
                hands[RIGHT].buttons.trigger = hands[RIGHT].buttons.trigger.max(1.0);
            }
            if hands.iter().any(|h| h.tracked) {
                self.summary.tracked_frames += 1;
            }
            let start = *t0.get_or_insert(time.as_nanos());
            let input = FrameInput {
                time: (time.as_nanos() - start) as f64 * 1e-9,
                views,
                hands,
            };
            if let Some(r) = &mut self.recorder {
                r.write_frame(&input).map_err(|e| XrError::Output {
                    path: "record".into(),
                    msg: e.to_string(),
                })?;
            }
            // One command buffer per frame: the swapchain image is acquired and waited first,
            // the eyes are copied into it at the end of the frame's own command buffer, and it
            // is released once that submission finished.
            let sc = &mut self.swapchain;
            let index = sc.handle.acquire_image()?;
            sc.handle.wait_image(xr::Duration::INFINITE)?;
            let image = sc.images[index as usize];
            let extent = sc.extent;
            let depth_image = match &mut self.depth_swapchain {
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
            let d = self.fl.gpu.device.clone();
            let stats = self.fl.render_with(&input, |cmd, src| unsafe {
                record_blit(&d, cmd, src, image, extent);
                if let Some(depth) = depth_image {
                    record_depth_copy(&d, cmd, src, depth, extent);
                }
            });
            // Release even when the frame failed, so the swapchains are not left waited.
            sc.handle.release_image()?;
            if let Some(ds) = &mut self.depth_swapchain {
                ds.handle.release_image()?;
            }
            let stats = stats?;
            if stats.metrics.clipped > 0 && prev_clipped == 0 {
                self.actions.pulse(&self.session, RIGHT)?;
                self.summary.pulses += 1;
                eprintln!(
                    "xr: haptic pulse: the tool touched tissue at frame {}",
                    self.summary.frames
                );
            }
            prev_clipped = stats.metrics.clipped;
            self.present(time, &xr_views_or(&xr_views, &views))?;
            // The mirror shows the same finished frame, after the headset has it.
            if let Some(m) = &mut self.mirror {
                m.show(self.fl.target())?;
                if !m.open() {
                    eprintln!("xr: mirror window closed; the session goes on");
                    self.mirror = None;
                }
            }
            self.summary.frames += 1;
            if self.summary.frames % 100 == 0 {
                eprintln!("xr: {} frames submitted", self.summary.frames);
            }
        }
    }

    /// Submits the projection layer (the swapchain image was filled and released by then).
    fn present(&mut self, time: xr::Time, views: &[xr::View; 2]) -> Result<()> {
        let sc = &self.swapchain;
        let (w, h) = sc.extent;
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
        // is a standard Vulkan one: depth 0 at NEAR, 1 at FAR (render::view).
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
                near_z: crate::render::view::NEAR,
                far_z: crate::render::view::FAR,
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
        let layer = xr::CompositionLayerProjection::new()
            .space(&self.base)
            .views(&proj);
        self.stream.end(time, self.blend, &[&layer])?;
        if depth_info.is_some() {
            self.summary.depth_frames += 1;
        }
        Ok(())
    }
}

/// Records the copy of both eyes (the stereo target's colour, in TRANSFER_SRC_OPTIMAL) into the
/// acquired swapchain image, one blit region for both layers.
///
/// # Safety
/// `cmd` is recording on `d`, `image` is the waited swapchain image.
unsafe fn record_blit(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    src: &StereoTarget,
    image: vk::Image,
    (w, h): (u32, u32),
) {
    let range = vk::ImageSubresourceRange::default()
        .aspect_mask(vk::ImageAspectFlags::COLOR)
        .level_count(1)
        .layer_count(2);
    let layers = vk::ImageSubresourceLayers::default()
        .aspect_mask(vk::ImageAspectFlags::COLOR)
        .layer_count(2);
    // The runtime hands images over in COLOR_ATTACHMENT_OPTIMAL and wants them back so
    // (XR_KHR_vulkan_enable); the old contents are not needed.
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::UNDEFINED,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
    );
    let region = [vk::ImageBlit::default()
        .src_subresource(layers)
        .src_offsets([
            vk::Offset3D::default(),
            vk::Offset3D {
                x: src.width as i32,
                y: src.height as i32,
                z: 1,
            },
        ])
        .dst_subresource(layers)
        .dst_offsets([
            vk::Offset3D::default(),
            vk::Offset3D {
                x: w as i32,
                y: h as i32,
                z: 1,
            },
        ])];
    d.cmd_blit_image(
        cmd,
        src.color.raw,
        vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
        image,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        &region,
        vk::Filter::LINEAR,
    );
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
    );
}

/// Records the copy of both eyes' depth (the stereo target's, D32_SFLOAT in TRANSFER_SRC_OPTIMAL)
/// into the acquired depth swapchain image, which goes back to the runtime in
/// DEPTH_STENCIL_ATTACHMENT_OPTIMAL (XR_KHR_vulkan_enable).
///
/// # Safety
/// `cmd` is recording on `d`, `image` is the waited depth swapchain image.
unsafe fn record_depth_copy(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    src: &StereoTarget,
    image: vk::Image,
    (w, h): (u32, u32),
) {
    let range = vk::ImageSubresourceRange::default()
        .aspect_mask(vk::ImageAspectFlags::DEPTH)
        .level_count(1)
        .layer_count(2);
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::UNDEFINED,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
    );
    let layers = vk::ImageSubresourceLayers::default()
        .aspect_mask(vk::ImageAspectFlags::DEPTH)
        .layer_count(2);
    let region = [vk::ImageCopy::default()
        .src_subresource(layers)
        .dst_subresource(layers)
        .extent(vk::Extent3D {
            width: src.width.min(w),
            height: src.height.min(h),
            depth: 1,
        })];
    d.cmd_copy_image(
        cmd,
        src.depth.raw,
        vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
        image,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        &region,
    );
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::DEPTH_STENCIL_ATTACHMENT_OPTIMAL,
    );
}

/// The located views as submitted: the runtime's own when it gave two, else the ones rendered
/// (the last valid head pose) converted back.
fn xr_views_or(located: &[xr::View], rendered: &[View; 2]) -> [xr::View; 2] {
    if located.len() == 2 {
        return [located[0], located[1]];
    }
    rendered.map(|v| xr::View {
        pose: xr::Posef {
            orientation: xr::Quaternionf {
                x: v.pose.orientation.x,
                y: v.pose.orientation.y,
                z: v.pose.orientation.z,
                w: v.pose.orientation.w,
            },
            position: xr::Vector3f {
                x: v.pose.position.x,
                y: v.pose.position.y,
                z: v.pose.position.z,
            },
        },
        fov: xr::Fovf {
            angle_left: v.fov.angle_left,
            angle_right: v.fov.angle_right,
            angle_up: v.fov.angle_up,
            angle_down: v.fov.angle_down,
        },
    })
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

    #[test]
    fn points_parse_and_bad_ones_are_named() {
        assert_eq!(
            parse_point("0.2,1.3,-0.58").unwrap(),
            Vec3::new(0.2, 1.3, -0.58)
        );
        assert!(parse_point("1,2").unwrap_err().contains("'1,2'"));
        assert!(parse_point("a,b,c").is_err());
    }
}
