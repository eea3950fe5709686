//! `cao-xr xr --mirror`: a desktop window showing the left eye of the frames the headset loop
//! rendered, through the desktop window's presenter.

use super::common::{AppError, Result};
use crate::gpu::present::{Acquired, Presenter};
use crate::gpu::Gpu;
use crate::render::StereoTarget;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

/// A desktop window that shows the left eye of frames another loop rendered (`cao-xr xr
/// --mirror`). That loop is not a winit event loop, so the window's events are pumped once per
/// frame (`Mirror::show`); closing the window ends the mirror, not the session.
pub struct Mirror {
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
    /// Connects to the display; the window opens on the first `Mirror::show`. `gpu` must have
    /// been created with [`crate::gpu::GpuOptions::present`].
    pub fn new(gpu: &Gpu, size: (u32, u32)) -> Result<Mirror> {
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
    pub fn open(&self) -> bool {
        !self.state.closed
    }

    /// Handles the window's pending events, then acquires its next image: None once it was
    /// closed, or while its swapchain is recreated.
    pub fn acquire(&mut self) -> Result<Option<Acquired>> {
        use winit::platform::pump_events::{EventLoopExtPumpEvents, PumpStatus};
        if self.state.closed {
            return Ok(None);
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
        match &mut self.state.presenter {
            // SAFETY: the presenter was made on this window and GPU (`resumed`); a recreate inside
            // waits for the device to idle, so no frame in flight still uses the old images.
            Some(p) => Ok(unsafe { p.acquire()? }),
            None => Ok(None),
        }
    }

    /// Records the blit of the left eye of `target` (colour in TRANSFER_SRC_OPTIMAL when `cmd`
    /// gets there) into `image`, at the end of the frame's own command buffer.
    pub fn record_blit(
        &self,
        cmd: ash::vk::CommandBuffer,
        image: &Acquired,
        target: &StereoTarget,
    ) {
        if let Some(p) = &self.state.presenter {
            // The drawn part (a frame budget's render scale), enlarged to the window.
            let size = target.drawn();
            // SAFETY: the caller (the headset loop's `after`) records into a recording `cmd` with
            // the target's colour in TRANSFER_SRC_OPTIMAL there, and `image` was acquired from this
            // presenter this frame.
            unsafe { p.record_blit(cmd, image, target.color.raw, size, false, None) };
        }
    }

    /// Shows `image` once the frame that blitted into it (and signalled `image.rendered`) has
    /// finished.
    pub fn present(&mut self, image: Acquired) -> Result<()> {
        if let Some(p) = &mut self.state.presenter {
            // SAFETY: the headset loop presents only an image whose frame was submitted, and that
            // submission signals `image.rendered`.
            unsafe { p.queue_present(image, true)? };
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
        // SAFETY: `gpu` was made with `present` (gpu_options(.., mirror)); the presenter is
        // declared before the window and `close` clears it first, so the window outlives it.
        match unsafe { Presenter::new(&self.gpu, &window) } {
            Ok(p) => self.presenter = Some(p),
            Err(e) => {
                self.error = Some(e.into());
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
                    // SAFETY: Resized is pumped in `acquire` before this frame's image is acquired;
                    // recreate waits for the device to idle before it retires the old swapchain.
                    if let Err(e) = unsafe { p.recreate(size.width, size.height) } {
                        self.error = Some(e.into());
                    }
                }
            }
            _ => {}
        }
    }
}
