//! `cao-xr view`: the desktop window. winit gives the window and the events, the one frame loop
//! renders both eyes, and a blit puts one eye or both side by side on an X11 swapchain.

use super::common::{AppError, Result};
use super::frame_loop::FrameLoop;
use super::session::{
    desktop_interaction, record_error, recorder, start_gpu, Recorder, SessionSpec,
};
use crate::gpu::present::Presenter;
use crate::input::desktop::{DesktopInput, Key};
use crate::input::StreamHeader;
use glam::Vec2;
use std::path::PathBuf;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
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
    /// Vulkan validation on (`--validation`; also on in debug builds).
    pub validation: bool,
    /// `--frames-in-flight`: 1 or 2 (default [`crate::render::MAX_FRAMES_IN_FLIGHT`]).
    pub frames_in_flight: Option<usize>,
    /// `--frame-budget-ms`: the frame time the ray step is scaled to hold (None: off).
    pub frame_budget_ms: Option<f64>,
}

struct App {
    opts: ViewOptions,
    fl: FrameLoop,
    input: DesktopInput,
    // Fields drop in order: the presenter (its surface and swapchain) before the window it
    // draws into, on every path out, an early error's included.
    presenter: Option<Presenter>,
    window: Option<Window>,
    recorder: Option<Recorder>,
    both_eyes: bool,
    frame: usize,
    start: std::time::Instant,
    last: std::time::Instant,
    cursor: Option<Vec2>,
    drag: (bool, bool),
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
        KeyCode::KeyP => Key::CycleMode,
        KeyCode::Equal | KeyCode::NumpadAdd => Key::Grow,
        KeyCode::Minus | KeyCode::NumpadSubtract => Key::Shrink,
        KeyCode::KeyM => Key::Menu,
        KeyCode::KeyO => Key::NextAo,
        KeyCode::KeyN => Key::NextStructure,
        KeyCode::KeyH => Key::ShowStructure,
        KeyCode::KeyK => Key::ProtectStructure,
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
            r.write_frame(&fi).map_err(record_error)?;
        }
        // With two frames in flight the stats are the frame before's. The window's image is
        // acquired first; the frame's own command buffer blits into it and signals its
        // present, so nothing here waits for the GPU but the frame loop's retire.
        let acquired = match &mut self.presenter {
            // SAFETY: the presenter was made on this window and GPU (`resumed`); a recreate inside
            // waits for the device to idle, so no frame in flight still uses the old images.
            Some(p) => unsafe { p.acquire()? },
            None => None,
        };
        let (presenter, both) = (&self.presenter, self.both_eyes);
        let retired = self.fl.submit_signalling(
            &fi,
            false,
            |cmd, t| {
                if let (Some(p), Some(a)) = (presenter, &acquired) {
                    // SAFETY: `cmd` is the frame's recording command buffer and `after` runs after
                    // cmd_finish, so `t.color` (two layers, its drawn part within) is in
                    // TRANSFER_SRC_OPTIMAL; `a` was acquired from `p` above. The drawn part (a
                    // frame budget's render scale) is enlarged to the window.
                    unsafe { p.record_blit(cmd, a, t.color.raw, t.drawn(), both, None) };
                }
            },
            acquired.as_ref().map(|a| a.rendered),
        );
        // A failure ends the session; its acquired image goes with the swapchain.
        let retired = retired?;
        if let (Some(p), Some(a)) = (&mut self.presenter, acquired) {
            // SAFETY: submit_signalling returned Ok, so the frame's submission, which signals
            // `a.rendered`, was made.
            unsafe { p.queue_present(a, true)? };
        }
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
        self.fps = 0.9 * self.fps + 0.1 / dt.max(1e-3) as f64;
        if let (Some(w), Some(stats)) = (&self.window, retired.map(|r| r.stats)) {
            let m = &stats.metrics;
            let carving = self.fl.scene.tools.first().is_some_and(|t| t.cuts());
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
            let step = match self.opts.frame_budget_ms {
                Some(_) => format!(" | {}", stats.budget()),
                None => String::new(),
            };
            let margin = self
                .fl
                .margin_warning(&stats.margins)
                .into_iter()
                .chain(self.fl.structure_menu())
                .map(|w| format!(" | {w}"))
                .collect::<String>();
            // A downsampled volume's full-resolution box around the tools.
            // "inset 64x64x40 4.2 ms", or "inset 64x64x40 40%" while a moved one is computed.
            let inset = self.fl.inset().map_or(String::new(), |i| {
                let [x, y, z] = i.inner_size();
                let now = stats
                    .inset
                    .map_or(String::new(), |s| format!(" {}", s.state()));
                let n = match i.boxes() {
                    1 => String::new(),
                    n => format!("{n} x "),
                };
                // A middle level's box: "/ 96x96x60 by 2".
                let mid: String = self.fl.insets()[1..]
                    .iter()
                    .map(|m| {
                        let [x, y, z] = m.inner_size();
                        format!(" / {x}x{y}x{z} {}", m.level())
                    })
                    .collect();
                format!(" | inset {n}{x}x{y}x{z}{mid}{now}")
            });
            w.set_title(&format!(
                "cao-xr | {:.1} fps | AO {} {:.1} ms{sh} | {:.2} % recomputed | carving {} | {:?} | {tf}{step}{inset}{margin}",
                self.fps,
                self.fl.cao.method_name(),
                m.gpu_ms(),
                m.percent_recomputed(),
                if carving { "on" } else { "off" },
                self.fl.scene.tools.first().map(|t| t.shape)
            ));
        }
        self.frame += 1;
        if self.opts.frames.is_some_and(|n| self.frame >= n) || super::interrupt::caught().is_some()
        {
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
        // SAFETY: `gpu` was made with `present` (start_gpu(.., true)); the window must outlive the
        // presenter: `run` clears `presenter` before `window` (an early `?` in `run` does not: App
        // then drops its `window` field first).
        match unsafe { Presenter::new(&self.fl.gpu, &window) } {
            Ok(p) => self.presenter = Some(p),
            Err(e) => return self.fail(el, e.into()),
        }
        window.request_redraw();
        self.window = Some(window);
    }

    fn window_event(&mut self, el: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => el.exit(),
            WindowEvent::Resized(size) => {
                if let Some(p) = &mut self.presenter {
                    // SAFETY: Resized comes between redraws, when no image is acquired; recreate
                    // waits for the device to idle before it retires the old swapchain.
                    if let Err(e) = unsafe { p.recreate(size.width, size.height) } {
                        self.fail(el, e.into());
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
pub fn run(spec: &SessionSpec, opts: ViewOptions) -> Result<usize> {
    let gpu = start_gpu(opts.validation, true)?;
    let event_loop = EventLoop::new()
        .map_err(|e| AppError::Usage(format!("cannot open the display: {e} (is DISPLAY set?)")))?;
    let mut fl = spec.frame_loop(&gpu, opts.size, desktop_interaction(), true, true)?;
    if let Some(n) = opts.frames_in_flight {
        fl.set_frames_in_flight(n)?;
    }
    fl.set_frame_budget(opts.frame_budget_ms);
    let header = StreamHeader::new("desktop", format!("cao-xr view of {}", spec.volume.name));
    let recorder = recorder(opts.record.as_deref(), &header)?;
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
        error: None,
        fps: 0.0,
    };
    super::interrupt::catch();
    event_loop
        .run_app(&mut app)
        .map_err(|e| AppError::Usage(format!("window event loop: {e}")))?;
    // The screenshot: the last frame, blitted and presented once more and read back.
    let shot = match (
        &app.opts.screenshot,
        &mut app.presenter,
        app.error.is_none(),
    ) {
        (Some(_), Some(p), true) => {
            app.fl.flush()?;
            let t = app.fl.target();
            // SAFETY: `flush` waited for the last frame, so the target's colour (two layers,
            // its drawn part within) is in TRANSFER_SRC_OPTIMAL and nothing else writes it.
            unsafe { p.present(t.color.raw, t.drawn(), app.both_eyes, true)? }
        }
        _ => None,
    };
    app.presenter = None;
    app.window = None;
    spec.save_markups(&app.fl, &super::session::default_markups_path())?;
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    if let Some(r) = app.recorder.take() {
        r.finish().map_err(record_error)?;
    }
    if let (Some(path), Some(shot)) = (&app.opts.screenshot, &shot) {
        crate::render::png_out::write_rgb(path, shot.width, shot.height, &shot.rgb)?;
    }
    Ok(app.frame)
}
