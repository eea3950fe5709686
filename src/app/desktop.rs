//! `cao-xr view`: the desktop window. winit gives the window and the events, the one frame loop
//! renders both eyes, and a blit puts one eye or both side by side on an X11 swapchain.

use super::frame_loop::{tf_cycle, FrameLoop};
use super::lighting::LightingOptions;
use super::{AppError, Result};
use crate::ao::LaoParams;
use crate::gpu::{cmd_image_barrier, Buffer, Gpu, GpuError};
use crate::input::desktop::{DesktopInput, Key};
use crate::input::{InteractionSettings, PoseStreamWriter, StreamHeader};
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use ash::vk;
use glam::Vec2;
use std::path::PathBuf;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::raw_window_handle::{
    HasDisplayHandle, HasWindowHandle, RawDisplayHandle, RawWindowHandle,
};
use winit::window::{Window, WindowId};

#[derive(Clone, Debug, Default)]
pub struct ViewOptions {
    /// Pixels per eye of the render target.
    pub size: (u32, u32),
    /// Quit after this many frames.
    pub frames: Option<usize>,
    /// Record the session as a pose stream.
    pub record: Option<PathBuf>,
    /// Drive head and tool automatically (an orbit and a carving sweep) instead of the mouse.
    pub demo: bool,
    /// Save what the window showed last, as PNG, when it closes.
    pub screenshot: Option<PathBuf>,
    /// Also write every frame shown (both eyes side by side) as DIR/frame-00000.png ...
    pub dump: Option<PathBuf>,
    pub lighting: LightingOptions,
}

/// Interaction settings of desktop sessions (and of their replays): the emulated grip is the
/// tool, so there is no offset in the hand.
pub fn desktop_interaction() -> InteractionSettings {
    InteractionSettings {
        tool_offset: glam::Vec3::ZERO,
        ..Default::default()
    }
}

/// What the window showed: RGB rows, top down.
pub(crate) struct Screenshot {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
}

/// Window surface and swapchain; destroyed before the device goes. Shared by the desktop
/// window and the headset's mirror ([`Mirror`]).
pub(crate) struct Presenter {
    gpu: Gpu,
    surface_fn: ash::khr::surface::Instance,
    swapchain_fn: ash::khr::swapchain::Device,
    surface: vk::SurfaceKHR,
    swapchain: vk::SwapchainKHR,
    images: Vec<vk::Image>,
    format: vk::Format,
    extent: vk::Extent2D,
    fence: vk::Fence,
}

impl Presenter {
    pub(crate) unsafe fn new(gpu: &Gpu, window: &Window) -> Result<Presenter> {
        let err = |m: &str| AppError::Gpu(GpuError::Other(m.to_string()));
        let (RawWindowHandle::Xlib(w), RawDisplayHandle::Xlib(d)) = (
            window
                .window_handle()
                .map_err(|e| err(&e.to_string()))?
                .as_raw(),
            window
                .display_handle()
                .map_err(|e| err(&e.to_string()))?
                .as_raw(),
        ) else {
            return Err(err(
                "the desktop window needs X11 (set DISPLAY; Wayland is not supported)",
            ));
        };
        let display = d.display.ok_or_else(|| err("no X11 display"))?.as_ptr();
        let xlib = ash::khr::xlib_surface::Instance::new(&gpu.entry, &gpu.instance);
        let info = vk::XlibSurfaceCreateInfoKHR::default()
            .dpy(display as *mut vk::Display)
            .window(w.window as vk::Window);
        let surface = xlib
            .create_xlib_surface(&info, None)
            .map_err(GpuError::from)?;
        let surface_fn = ash::khr::surface::Instance::new(&gpu.entry, &gpu.instance);
        if !surface_fn
            .get_physical_device_surface_support(gpu.physical, gpu.queue_family, surface)
            .map_err(GpuError::from)?
        {
            surface_fn.destroy_surface(surface, None);
            return Err(err("the GPU's queue cannot present to this window"));
        }
        let swapchain_fn = ash::khr::swapchain::Device::new(&gpu.instance, &gpu.device);
        let fence = gpu
            .device
            .create_fence(&vk::FenceCreateInfo::default(), None)
            .map_err(GpuError::from)?;
        let mut p = Presenter {
            gpu: gpu.clone(),
            surface_fn,
            swapchain_fn,
            surface,
            swapchain: vk::SwapchainKHR::null(),
            images: Vec::new(),
            format: vk::Format::UNDEFINED,
            extent: vk::Extent2D::default(),
            fence,
        };
        let size = window.inner_size();
        p.recreate(size.width, size.height)?;
        Ok(p)
    }

    pub(crate) unsafe fn recreate(&mut self, width: u32, height: u32) -> Result<()> {
        let _ = self.gpu.device.device_wait_idle();
        let caps = self
            .surface_fn
            .get_physical_device_surface_capabilities(self.gpu.physical, self.surface)
            .map_err(GpuError::from)?;
        let formats = self
            .surface_fn
            .get_physical_device_surface_formats(self.gpu.physical, self.surface)
            .map_err(GpuError::from)?;
        let format = formats
            .iter()
            .find(|f| {
                matches!(
                    f.format,
                    vk::Format::B8G8R8A8_UNORM | vk::Format::R8G8B8A8_UNORM
                )
            })
            .or(formats.first())
            .copied()
            .ok_or_else(|| {
                AppError::Gpu(GpuError::Other(
                    "the window offers no surface format".into(),
                ))
            })?;
        let extent = if caps.current_extent.width != u32::MAX {
            caps.current_extent
        } else {
            vk::Extent2D {
                width: width.clamp(caps.min_image_extent.width, caps.max_image_extent.width),
                height: height.clamp(caps.min_image_extent.height, caps.max_image_extent.height),
            }
        };
        let count = if caps.max_image_count > 0 {
            (caps.min_image_count + 1).min(caps.max_image_count)
        } else {
            caps.min_image_count + 1
        };
        let old = self.swapchain;
        let info = vk::SwapchainCreateInfoKHR::default()
            .surface(self.surface)
            .min_image_count(count)
            .image_format(format.format)
            .image_color_space(format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(vk::CompositeAlphaFlagsKHR::OPAQUE)
            .present_mode(vk::PresentModeKHR::FIFO)
            .clipped(true)
            .old_swapchain(old);
        self.swapchain = self
            .swapchain_fn
            .create_swapchain(&info, None)
            .map_err(GpuError::from)?;
        if old != vk::SwapchainKHR::null() {
            self.swapchain_fn.destroy_swapchain(old, None);
        }
        self.images = self
            .swapchain_fn
            .get_swapchain_images(self.swapchain)
            .map_err(GpuError::from)?;
        self.format = format.format;
        self.extent = extent;
        Ok(())
    }

    /// Blits one eye (or both side by side) of the stereo target to the window and presents it;
    /// with `capture`, also returns the presented pixels as RGB.
    pub(crate) unsafe fn present(
        &mut self,
        src: &crate::render::StereoTarget,
        both: bool,
        capture: bool,
    ) -> Result<Option<Screenshot>> {
        let d = &self.gpu.device;
        let (index, _) = match self.swapchain_fn.acquire_next_image(
            self.swapchain,
            u64::MAX,
            vk::Semaphore::null(),
            self.fence,
        ) {
            Ok(r) => r,
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => {
                self.recreate(self.extent.width, self.extent.height)?;
                return Ok(None);
            }
            Err(e) => return Err(GpuError::from(e).into()),
        };
        d.wait_for_fences(&[self.fence], true, u64::MAX)
            .map_err(GpuError::from)?;
        d.reset_fences(&[self.fence]).map_err(GpuError::from)?;
        let image = self.images[index as usize];
        let range = vk::ImageSubresourceRange::default()
            .aspect_mask(vk::ImageAspectFlags::COLOR)
            .level_count(1)
            .layer_count(1);
        let (w, h) = (self.extent.width as i32, self.extent.height as i32);
        let bytes = (w * h * 4) as u64;
        let readback = if capture {
            Some(Buffer::new(
                &self.gpu,
                bytes,
                vk::BufferUsageFlags::TRANSFER_DST,
                gpu_allocator::MemoryLocation::GpuToCpu,
                "screenshot",
            )?)
        } else {
            None
        };
        self.gpu.submit_and_wait(|cmd| {
            cmd_image_barrier(
                d,
                cmd,
                image,
                range,
                vk::ImageLayout::UNDEFINED,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            );
            let eyes = if both { 2 } else { 1 };
            for eye in 0..eyes {
                let x0 = w * eye / eyes;
                let x1 = w * (eye + 1) / eyes;
                let region = [vk::ImageBlit::default()
                    .src_subresource(
                        vk::ImageSubresourceLayers::default()
                            .aspect_mask(vk::ImageAspectFlags::COLOR)
                            .base_array_layer(eye as u32)
                            .layer_count(1),
                    )
                    .src_offsets([
                        vk::Offset3D::default(),
                        vk::Offset3D {
                            x: src.width as i32,
                            y: src.height as i32,
                            z: 1,
                        },
                    ])
                    .dst_subresource(
                        vk::ImageSubresourceLayers::default()
                            .aspect_mask(vk::ImageAspectFlags::COLOR)
                            .layer_count(1),
                    )
                    .dst_offsets([
                        vk::Offset3D { x: x0, y: 0, z: 0 },
                        vk::Offset3D { x: x1, y: h, z: 1 },
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
            }
            let mut last = vk::ImageLayout::TRANSFER_DST_OPTIMAL;
            if let Some(buf) = &readback {
                cmd_image_barrier(
                    d,
                    cmd,
                    image,
                    range,
                    last,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                );
                let region = [vk::BufferImageCopy::default()
                    .image_subresource(
                        vk::ImageSubresourceLayers::default()
                            .aspect_mask(vk::ImageAspectFlags::COLOR)
                            .layer_count(1),
                    )
                    .image_extent(vk::Extent3D {
                        width: w as u32,
                        height: h as u32,
                        depth: 1,
                    })];
                d.cmd_copy_image_to_buffer(
                    cmd,
                    image,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    buf.raw,
                    &region,
                );
                last = vk::ImageLayout::TRANSFER_SRC_OPTIMAL;
            }
            cmd_image_barrier(d, cmd, image, range, last, vk::ImageLayout::PRESENT_SRC_KHR);
        })?;
        let swapchains = [self.swapchain];
        let indices = [index];
        match self.swapchain_fn.queue_present(
            self.gpu.queue,
            &vk::PresentInfoKHR::default()
                .swapchains(&swapchains)
                .image_indices(&indices),
        ) {
            Ok(_) | Err(vk::Result::ERROR_OUT_OF_DATE_KHR) | Err(vk::Result::SUBOPTIMAL_KHR) => {}
            Err(e) => return Err(GpuError::from(e).into()),
        }
        let Some(buf) = readback else { return Ok(None) };
        let bgra =
            self.format == vk::Format::B8G8R8A8_UNORM || self.format == vk::Format::B8G8R8A8_SRGB;
        let px = buf.mapped()?;
        let rgb = px
            .chunks_exact(4)
            .flat_map(|p| {
                if bgra {
                    [p[2], p[1], p[0]]
                } else {
                    [p[0], p[1], p[2]]
                }
            })
            .collect();
        Ok(Some(Screenshot {
            width: w as u32,
            height: h as u32,
            rgb,
        }))
    }
}

impl Drop for Presenter {
    fn drop(&mut self) {
        unsafe {
            let _ = self.gpu.device.device_wait_idle();
            self.gpu.device.destroy_fence(self.fence, None);
            self.swapchain_fn.destroy_swapchain(self.swapchain, None);
            self.surface_fn.destroy_surface(self.surface, None);
        }
    }
}

/// A desktop window that shows the left eye of frames another loop rendered (`cao-xr xr
/// --mirror`). That loop is not a winit event loop, so the window's events are pumped once per
/// frame ([`Mirror::show`]); closing the window ends the mirror, not the session.
pub(crate) struct Mirror {
    event_loop: EventLoop<()>,
    state: MirrorWindow,
}

struct MirrorWindow {
    gpu: Gpu,
    size: (u32, u32),
    // The presenter (surface, swapchain) goes before its window.
    presenter: Option<Presenter>,
    window: Option<Window>,
    closed: bool,
    error: Option<AppError>,
}

impl Mirror {
    /// Connects to the display; the window opens on the first [`Mirror::show`]. `gpu` must have
    /// been created with [`crate::gpu::GpuOptions::present`].
    pub(crate) fn new(gpu: &Gpu, size: (u32, u32)) -> Result<Mirror> {
        let event_loop = EventLoop::new().map_err(|e| {
            AppError::Usage(format!(
                "--mirror cannot open the display: {e} (is DISPLAY set?)"
            ))
        })?;
        Ok(Mirror {
            event_loop,
            state: MirrorWindow {
                gpu: gpu.clone(),
                size,
                presenter: None,
                window: None,
                closed: false,
                error: None,
            },
        })
    }

    /// Whether the window is still open (or yet to open).
    pub(crate) fn open(&self) -> bool {
        !self.state.closed
    }

    /// Handles the window's pending events, then shows the left eye of `target` (a finished
    /// frame: colour in TRANSFER_SRC_OPTIMAL).
    pub(crate) fn show(&mut self, target: &crate::render::StereoTarget) -> Result<()> {
        use winit::platform::pump_events::{EventLoopExtPumpEvents, PumpStatus};
        if self.state.closed {
            return Ok(());
        }
        let status = self
            .event_loop
            .pump_app_events(Some(std::time::Duration::ZERO), &mut self.state);
        if let Some(e) = self.state.error.take() {
            return Err(e);
        }
        if matches!(status, PumpStatus::Exit(_)) {
            self.state.close();
        }
        if let Some(p) = &mut self.state.presenter {
            unsafe { p.present(target, false, false)? };
        }
        Ok(())
    }
}

impl MirrorWindow {
    fn close(&mut self) {
        self.closed = true;
        self.presenter = None;
        self.window = None;
    }
}

impl ApplicationHandler for MirrorWindow {
    fn resumed(&mut self, el: &ActiveEventLoop) {
        if self.window.is_some() || self.closed {
            return;
        }
        let attrs = Window::default_attributes()
            .with_title("cao-xr mirror (left eye)")
            .with_inner_size(PhysicalSize::new(self.size.0, self.size.1));
        let window = match el.create_window(attrs) {
            Ok(w) => w,
            Err(e) => {
                self.error = Some(AppError::Usage(format!("cannot open a window: {e}")));
                return;
            }
        };
        match unsafe { Presenter::new(&self.gpu, &window) } {
            Ok(p) => self.presenter = Some(p),
            Err(e) => {
                self.error = Some(e);
                return;
            }
        }
        self.window = Some(window);
    }

    fn window_event(&mut self, _: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => self.close(),
            WindowEvent::KeyboardInput { event, .. }
                if event.physical_key == PhysicalKey::Code(KeyCode::Escape) =>
            {
                self.close()
            }
            WindowEvent::Resized(size) => {
                if let Some(p) = &mut self.presenter {
                    if let Err(e) = unsafe { p.recreate(size.width, size.height) } {
                        self.error = Some(e);
                    }
                }
            }
            _ => {}
        }
    }
}

struct App {
    opts: ViewOptions,
    fl: FrameLoop,
    input: DesktopInput,
    window: Option<Window>,
    presenter: Option<Presenter>,
    recorder: Option<PoseStreamWriter<std::io::BufWriter<std::fs::File>>>,
    both_eyes: bool,
    frame: usize,
    start: std::time::Instant,
    last: std::time::Instant,
    cursor: Option<Vec2>,
    drag: (bool, bool),
    last_shot: Option<Screenshot>,
    error: Option<AppError>,
    fps: f64,
}

fn key_of(code: KeyCode) -> Option<Key> {
    Some(match code {
        KeyCode::KeyW => Key::Forward,
        KeyCode::KeyS => Key::Back,
        KeyCode::KeyA => Key::Left,
        KeyCode::KeyD => Key::Right,
        KeyCode::KeyQ => Key::Down,
        KeyCode::KeyE => Key::Up,
        KeyCode::Space => Key::Trigger,
        KeyCode::Tab => Key::CycleShape,
        KeyCode::KeyP => Key::ToggleProbe,
        KeyCode::Equal | KeyCode::NumpadAdd => Key::Grow,
        KeyCode::Minus | KeyCode::NumpadSubtract => Key::Shrink,
        KeyCode::KeyM => Key::Menu,
        KeyCode::BracketLeft => Key::LightLeft,
        KeyCode::BracketRight => Key::LightRight,
        _ => return None,
    })
}

impl App {
    fn fail(&mut self, el: &ActiveEventLoop, e: AppError) {
        self.error.get_or_insert(e);
        el.exit();
    }

    fn redraw(&mut self, el: &ActiveEventLoop) -> Result<()> {
        let now = std::time::Instant::now();
        let dt = (now - self.last).as_secs_f32().min(0.1);
        self.last = now;
        if self.opts.demo {
            // A gentle orbit, and a carving sweep through the front of the volume.
            let t = self.frame as f32 / 60.0;
            self.input.yaw = 0.35 * (t * 0.8).sin();
            self.input.tool = glam::Vec3::new(0.06 * (t * 1.3).sin(), 0.03, 0.07);
            if self.frame == 2 {
                self.input.held.insert(Key::Trigger);
            }
        } else {
            self.input.step(dt);
        }
        let aspect = self.opts.size.0 as f32 / self.opts.size.1 as f32;
        let fi = self
            .input
            .frame_input(self.start.elapsed().as_secs_f64(), aspect);
        if let Some(r) = &mut self.recorder {
            r.write_frame(&fi).map_err(|e| AppError::Output {
                path: "record".into(),
                msg: e.to_string(),
            })?;
        }
        let stats = self.fl.render(&fi)?;
        if let Some(dir) = &self.opts.dump {
            let img = self.fl.target().read_back(&self.fl.gpu)?;
            let path = dir.join(format!("frame-{:05}.png", self.frame));
            crate::render::png_out::write_rgb(
                &path,
                img.width * 2,
                img.height,
                &img.side_by_side_rgb(),
            )?;
        }
        let capture = self.opts.screenshot.is_some();
        if let Some(p) = &mut self.presenter {
            if let Some(shot) = unsafe { p.present(self.fl.target(), self.both_eyes, capture)? } {
                self.last_shot = Some(shot);
            }
        }
        self.fps = 0.9 * self.fps + 0.1 / dt.max(1e-3) as f64;
        let m = &stats.metrics;
        let carving = self.fl.scene.tools.first().is_some_and(|t| t.active);
        if let Some(w) = &self.window {
            // The TF shown, or the one being computed and how far ("TF ct-skin 40%").
            let tf = match &stats.tf_progress {
                Some(p) => p.to_string(),
                None => format!("TF {}", self.fl.shown_tf().name),
            };
            let sh = match &self.fl.lighting {
                Some(l) => format!(
                    " | SH {:.1} ms, light {:.0} deg",
                    stats.sh.gpu_ms,
                    (l.yaw + self.fl.scene.light_yaw).to_degrees()
                ),
                None => String::new(),
            };
            w.set_title(&format!(
                "cao-xr | {:.1} fps | AO {:.1} ms{sh} | {:.2} % recomputed | carving {} | {:?} | {tf}",
                self.fps,
                m.gpu_ms(),
                m.percent_recomputed(),
                if carving { "on" } else { "off" },
                self.fl.scene.tools.first().map(|t| t.shape)
            ));
        }
        self.frame += 1;
        if self.opts.frames.is_some_and(|n| self.frame >= n) {
            el.exit();
        }
        Ok(())
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, el: &ActiveEventLoop) {
        if self.window.is_some() {
            return;
        }
        let (w, h) = self.opts.size;
        let attrs = Window::default_attributes()
            .with_title("cao-xr")
            .with_inner_size(PhysicalSize::new(w * 2, h));
        let window = match el.create_window(attrs) {
            Ok(w) => w,
            Err(e) => return self.fail(el, AppError::Usage(format!("cannot open a window: {e}"))),
        };
        match unsafe { Presenter::new(&self.fl.gpu, &window) } {
            Ok(p) => self.presenter = Some(p),
            Err(e) => return self.fail(el, e),
        }
        window.request_redraw();
        self.window = Some(window);
    }

    fn window_event(&mut self, el: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => el.exit(),
            WindowEvent::Resized(size) => {
                if let Some(p) = &mut self.presenter {
                    if let Err(e) = unsafe { p.recreate(size.width, size.height) } {
                        self.fail(el, e);
                    }
                }
            }
            WindowEvent::KeyboardInput { event, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else {
                    return;
                };
                let down = event.state == ElementState::Pressed;
                match code {
                    KeyCode::Escape if down => el.exit(),
                    KeyCode::Digit1 if down => self.both_eyes = false,
                    KeyCode::Digit2 if down => self.both_eyes = true,
                    _ => {
                        if let Some(k) = key_of(code) {
                            if down {
                                self.input.held.insert(k);
                            } else {
                                self.input.held.remove(&k);
                            }
                        }
                    }
                }
            }
            WindowEvent::MouseInput { state, button, .. } => {
                let down = state == ElementState::Pressed;
                match button {
                    MouseButton::Left => self.drag.0 = down,
                    MouseButton::Right => self.drag.1 = down,
                    _ => {}
                }
            }
            WindowEvent::CursorMoved { position, .. } => {
                let p = Vec2::new(position.x as f32, position.y as f32);
                if let Some(last) = self.cursor {
                    if self.drag.0 {
                        self.input.drag_orbit(p - last);
                    }
                    if self.drag.1 {
                        self.input.drag_tool(p - last);
                    }
                }
                self.cursor = Some(p);
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let lines = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y,
                    MouseScrollDelta::PixelDelta(p) => p.y as f32 / 40.0,
                };
                self.input.zoom(lines);
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw(el) {
                    self.fail(el, e);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _: &ActiveEventLoop) {
        if let Some(w) = &self.window {
            w.request_redraw();
        }
    }
}

/// Opens the window and runs until it is closed (or `frames` have been shown).
pub fn run(
    vol: &Volume,
    tf: &TransferFunction,
    params: LaoParams,
    opts: ViewOptions,
) -> Result<usize> {
    let gpu_opts = crate::gpu::GpuOptions {
        present: true,
        ..Default::default()
    };
    let gpu = Gpu::new(&gpu_opts)?;
    eprintln!(
        "GPU: {}{}",
        gpu.device_name,
        if gpu.validation_enabled() {
            " (validation on)"
        } else {
            ""
        }
    );
    let event_loop = EventLoop::new()
        .map_err(|e| AppError::Usage(format!("cannot open the display: {e} (is DISPLAY set?)")))?;
    let mut fl = FrameLoop::new(
        &gpu,
        vol,
        tf_cycle(tf, vol),
        params,
        opts.size,
        desktop_interaction(),
        true,
    )?;
    fl.set_lighting(&opts.lighting, true)?;
    let recorder = match &opts.record {
        Some(p) => Some(
            PoseStreamWriter::create(
                p,
                &StreamHeader::new("desktop", format!("cao-xr view of {}", vol.name)),
            )
            .map_err(|e| AppError::Output {
                path: p.display().to_string(),
                msg: e.to_string(),
            })?,
        ),
        None => None,
    };
    if let Some(d) = &opts.dump {
        std::fs::create_dir_all(d).map_err(|e| AppError::Output {
            path: d.display().to_string(),
            msg: e.to_string(),
        })?;
    }
    let target = fl.scene.volume.center;
    let now = std::time::Instant::now();
    let mut app = App {
        opts,
        fl,
        input: DesktopInput::new(target),
        window: None,
        presenter: None,
        recorder,
        both_eyes: true,
        frame: 0,
        start: now,
        last: now,
        cursor: None,
        drag: (false, false),
        last_shot: None,
        error: None,
        fps: 0.0,
    };
    event_loop
        .run_app(&mut app)
        .map_err(|e| AppError::Usage(format!("window event loop: {e}")))?;
    app.presenter = None;
    app.window = None;
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    if let Some(r) = app.recorder.take() {
        r.finish().map_err(|e| AppError::Output {
            path: "record".into(),
            msg: e.to_string(),
        })?;
    }
    if let (Some(path), Some(shot)) = (&app.opts.screenshot, &app.last_shot) {
        crate::render::png_out::write_rgb(path, shot.width, shot.height, &shot.rgb)?;
    }
    Ok(app.frame)
}
