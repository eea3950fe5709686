//! `cao-xr xr`: the headset front end. The runtime creates the Vulkan device, each frame the
//! session locates the eyes and hands, the one frame loop renders both eyes and copies them into
//! the swapchain in the same command buffer, and the session submits the views it rendered.

use super::common::Result;
use super::frame_loop::{FrameLoop, FrameStats};
use super::mirror::Mirror;
use super::session::{gpu_banner, gpu_options, record_error, recorder, Recorder, SessionSpec};
use crate::clip::margin::MarginHit;
use crate::input::{tool_hand, InteractionSettings, StreamHeader, RIGHT};
use crate::xr::session::{XrRuntime, XrSession};
use crate::xr::{XrError, XrOptions, XrSummary};

/// Runs a headset session until the runtime ends it (or `frames` were submitted).
pub fn run(spec: &SessionSpec, opts: XrOptions) -> Result<XrSummary> {
    let runtime = XrRuntime::open()?;
    let gpu = runtime.create_gpu(&gpu_options(opts.validation, opts.mirror))?;
    eprintln!("xr: GPU {}", gpu_banner(&gpu));
    // The session's objects are locals of this block: leaving it drops them in reverse order
    // (the mirror, the frame loop, then the session), all before the device they use, and the
    // validation messages of their teardown are read after.
    let (result, summary, recorder) = {
        let mut xs = XrSession::new(&runtime, &gpu, &opts)?;
        let extent = xs.extent();
        let mut fl = spec.frame_loop(&gpu, extent, InteractionSettings::default(), false, true)?;
        if let Some(n) = opts.frames_in_flight {
            fl.set_frames_in_flight(n)?;
        }
        fl.set_frame_budget(opts.frame_budget_ms);
        if let Some(c) = opts.volume_at {
            fl.scene.volume.center = c;
        }
        if xs.blend.see_through() {
            // ADDITIVE adds the colour to the world (black adds nothing); ALPHA_BLEND lays the
            // premultiplied colour over it by alpha (the ray caster's alpha, 0 where it misses).
            fl.settings.background = [0.0; 3];
        }
        let mut mirror = opts.mirror.then(|| Mirror::new(&gpu, extent)).transpose()?;
        let description = format!("cao-xr xr of {} on {}", spec.volume.name, runtime.name);
        let header = StreamHeader {
            volume_at: opts.volume_at.map(|c| c.to_array()),
            ..StreamHeader::new("xr", description)
        };
        let mut recorder = recorder(opts.record.as_deref(), &header)?;
        super::interrupt::catch();
        let result = frames(&mut xs, &mut fl, &mut mirror, &mut recorder, &opts);
        // The last frame's stats are not needed; waiting for it is.
        let result = result.and_then(|()| fl.flush().map(|_| ()));
        let saved = spec.save_markups(&fl, &super::session::default_markups_path());
        let result = result.and(saved.map(|_| ()));
        // SAFETY: the device is alive (`gpu` is held here) and no other thread uses its queue.
        unsafe {
            let _ = gpu.device.device_wait_idle();
        }
        (result, std::mem::take(&mut xs.summary), recorder)
    };
    let messages = gpu.validation_messages();
    let xr_messages = runtime.messages();
    result?;
    if let Some(r) = recorder {
        r.finish().map_err(record_error)?;
    }
    if !xr_messages.is_empty() {
        return Err(XrError::Runtime(format!(
            "{} OpenXR validation messages (first: {})",
            xr_messages.len(),
            xr_messages[0]
        ))
        .into());
    }
    if !messages.is_empty() {
        return Err(XrError::Runtime(format!(
            "{} Vulkan validation messages (first: {})",
            messages.len(),
            messages[0]
        ))
        .into());
    }
    Ok(summary)
}

/// The frames of a running session, until the runtime ends it.
fn frames(
    xs: &mut XrSession,
    fl: &mut FrameLoop,
    mirror: &mut Option<Mirror>,
    recorder: &mut Option<Recorder>,
    opts: &XrOptions,
) -> Result<()> {
    let mut last = Reacted::default();
    while xs.poll_events()? {
        if !xs.running() {
            if super::interrupt::caught().is_some() {
                // Nothing is being shown to end gracefully: stop waiting for the runtime.
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
            continue;
        }
        // SIGINT/SIGTERM end the session as its frame count does.
        let done = opts.frames.is_some_and(|n| xs.summary.frames >= n)
            || super::interrupt::caught().is_some();
        if done {
            // The frame still in flight is told to the hands now, while the session runs: the
            // next frame may not begin (the runtime stops it), and a carve it starts must pulse.
            if let Some(r) = fl.flush()? {
                react(xs, fl, r.stats, &mut last)?;
            }
            xs.request_exit()?;
        }
        let Some(frame) = xs.begin_frame(done, opts.carve)? else {
            continue;
        };
        if let Some(r) = recorder {
            r.write_frame(&frame.input).map_err(record_error)?;
        }
        // One command buffer per frame: the swapchain images are acquired and waited first,
        // the eyes are copied into them at the end of the frame's own command buffer, and they
        // are released once that submission was made (the runtime waits for it), even if it
        // failed. The mirror's image is blitted in the same command buffer, after the
        // headset's copies, and presented once the submission signals it. With two frames in
        // flight the stats are the frame before's.
        let shown = match mirror {
            Some(m) => m.acquire()?,
            None => None,
        };
        // The runtime may use the queue in its swapchain calls and at the frame's end.
        let images = {
            let _queue = fl.gpu.queue_guard();
            xs.acquire()?
        };
        let d = fl.gpu.device.clone();
        let view = mirror.as_ref().zip(shown.as_ref());
        let retired = fl.submit_signalling(
            &frame.input,
            false,
            // SAFETY: `cmd` is recording and `after` runs once the target is in
            // TRANSFER_SRC_OPTIMAL; `images` were acquired and waited by `xs.acquire` and are
            // released only after this submission; the mirror's image was acquired this frame.
            |cmd, src| unsafe {
                images.record_copy(&d, cmd, src);
                if let Some((m, image)) = view {
                    m.record_blit(cmd, image, src);
                }
            },
            shown.as_ref().map(|a| a.rendered),
        );
        {
            let _queue = fl.gpu.queue_guard();
            xs.release()?;
        }
        let mut retired: Vec<_> = retired?.into_iter().collect();
        if done {
            // The session's last frame: its stats (a carve or a margin it starts) count too.
            retired.extend(fl.flush()?);
        }
        for r in retired {
            react(xs, fl, r.stats, &mut last)?;
        }
        {
            let _queue = fl.gpu.queue_guard();
            xs.end_frame(&frame, fl.target())?;
        }
        if let Some(m) = mirror {
            if let Some(image) = shown {
                m.present(image)?;
            }
            if !m.open() {
                eprintln!("xr: mirror window closed; the session goes on");
                *mirror = None;
            }
        }
        if xs.summary.frames % 100 == 0 {
            eprintln!("xr: {} frames submitted", xs.summary.frames);
        }
    }
    Ok(())
}

/// What the frame before told the hands: whether its tool clipped, and its margins.
#[derive(Default)]
struct Reacted {
    clipped: u64,
    margins: Vec<MarginHit>,
    /// The structure menu's line, told again when it changes.
    menu: Option<String>,
    /// What the frame budget chose, told again when it changes.
    budget: String,
}

/// The hands' answer to a frame that left the GPU: a pulse on the right hand when its tool
/// starts to clip tissue, and on the hand whose tool enters a safety margin (with a line naming
/// the structure and the distance on every frame it stays inside).
fn react(xs: &mut XrSession, fl: &FrameLoop, stats: FrameStats, last: &mut Reacted) -> Result<()> {
    if stats.metrics.clipped > 0 && last.clipped == 0 {
        xs.pulse(RIGHT)?;
        eprintln!(
            "xr: haptic pulse: the tool touched tissue at frame {}",
            xs.summary.frames
        );
    }
    for h in &stats.margins {
        let entered = !last
            .margins
            .iter()
            .any(|p| (p.tool, p.structure) == (h.tool, h.structure));
        if let (true, Some(hand)) = (entered, tool_hand(h.tool)) {
            xs.pulse(hand)?;
        }
    }
    if let Some(w) = fl.margin_warning(&stats.margins) {
        eprintln!("xr: frame {}: {w}", xs.summary.frames);
    }
    let menu = fl.structure_menu();
    if menu != last.menu {
        if let Some(m) = &menu {
            eprintln!("xr: frame {}: {m}", xs.summary.frames);
        }
    }
    let budget = stats.budget();
    if fl.frame_budget().is_some() && budget != last.budget {
        eprintln!("xr: frame {}: frame budget: {budget}", xs.summary.frames);
    }
    *last = Reacted {
        clipped: stats.metrics.clipped,
        margins: stats.margins,
        menu,
        budget,
    };
    Ok(())
}
