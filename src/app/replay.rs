//! `cao-xr replay`: renders every frame of a pose stream headless through the one frame loop,
//! writing side-by-side PNGs, per-frame metrics (CSV) and an optional animated PNG preview.

use super::frame_loop::FrameLoop;
use super::session::SessionSpec;
use super::{AppError, Result};
use crate::ao::cao::Mode;
use crate::clip::Shape;
use crate::gpu::Gpu;
use crate::input::{read_stream, replay_schedule, InteractionSettings, StreamHeader};
use crate::render::png_out::write_rgb;
use crate::scene::{Tool, ToolMode};
use std::io::Write;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug)]
pub struct ReplayOptions {
    /// Keep one frame in `every` as PNG (and in the preview).
    pub every: usize,
    /// Also write an animated PNG of the kept frames here.
    pub preview: Option<PathBuf>,
    /// Pixels per eye.
    pub size: (u32, u32),
    pub mode: Mode,
    /// Wait for each frame's recorded time instead of running as fast as possible.
    pub realtime: bool,
    /// The right hand's tool shape; by default from the stream's description ("box tool: ...").
    pub shape: Option<Shape>,
    /// Frames in flight, 1 or 2 (default [`crate::render::MAX_FRAMES_IN_FLIGHT`]): the same
    /// images either way.
    pub frames_in_flight: Option<usize>,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        ReplayOptions {
            every: 1,
            preview: None,
            size: (320, 320),
            mode: Mode::Contextual,
            realtime: false,
            shape: None,
            frames_in_flight: None,
        }
    }
}

/// What the replay did, for the caller's summary line.
#[derive(Clone, Debug, Default)]
pub struct ReplaySummary {
    pub frames: usize,
    pub pngs: usize,
    pub mean_ao_ms: f64,
    pub mean_percent_recomputed: f64,
}

/// The shape a scripted stream names at the start of its description, e.g. "torus tool: ...".
pub fn shape_from_header(header: &StreamHeader) -> Option<Shape> {
    Shape::builtin(header.description.split_whitespace().next()?)
}

fn out_err(path: &Path, e: impl std::fmt::Display) -> AppError {
    AppError::Output {
        path: path.display().to_string(),
        msg: e.to_string(),
    }
}

pub fn replay(
    gpu: &Gpu,
    script: &Path,
    spec: &SessionSpec,
    out: &Path,
    opts: &ReplayOptions,
) -> Result<ReplaySummary> {
    let (header, frames) = read_stream(script).map_err(|e| AppError::Usage(e.to_string()))?;
    if frames.is_empty() {
        return Err(AppError::Usage(format!(
            "{}: the stream has no frames",
            script.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(|e| out_err(out, e))?;
    // Scripts and desktop sessions describe where the tool goes, so their grip is the tool:
    // no offset in the hand (as the desktop window ran it).
    let interaction = if header.source.starts_with("script:") || header.source == "desktop" {
        super::desktop::desktop_interaction()
    } else {
        InteractionSettings::default()
    };
    let mut fl = spec.frame_loop(gpu, opts.size, interaction, true)?;
    fl.mode = opts.mode;
    if let Some(n) = opts.frames_in_flight {
        fl.set_frames_in_flight(n)?;
    }
    fl.scene.tools.push(Tool {
        shape: opts
            .shape
            .or_else(|| shape_from_header(&header))
            .unwrap_or(Shape::Sphere),
        pose: crate::space::Pose::IDENTITY,
        size: fl.interaction.settings().tool_size,
        mode: ToolMode::Carve,
        active: false,
    });

    // Written beside its name and renamed once complete, so an interrupted replay leaves no
    // partial metrics.csv (the frames' PNGs are written the same way, each).
    let csv_final = out.join("metrics.csv");
    let csv_path = out.join("metrics.csv.partial");
    let mut csv = std::io::BufWriter::new(
        std::fs::File::create(&csv_path).map_err(|e| out_err(&csv_path, e))?,
    );
    writeln!(
        csv,
        "frame,time_s,frame_ms,ao_update_ms,restore_ms,clip_ms,update_ms,render_ms,clipped,recomputed,percent_recomputed,tf,tf_progress,tf_ms,sh_voxels,sh_ms,ao_method"
    )
    .map_err(|e| out_err(&csv_path, e))?;
    let every = opts.every.max(1);
    let mut kept: Vec<Vec<u8>> = Vec::new();
    let mut summary = ReplaySummary {
        frames: frames.len(),
        ..Default::default()
    };
    let start = std::time::Instant::now();
    // The frames submitted and not yet back, oldest first: with two in flight a frame's
    // metrics and PNG are written while the GPU renders the next.
    let mut submitted = std::collections::VecDeque::new();
    let mut write = |i: usize, shown: super::frame_loop::Retired, fl: &FrameLoop| -> Result<()> {
        let image = shown.image.as_ref().expect("replay reads every frame back");
        let f = &shown.stats;
        let m = &f.metrics;
        writeln!(
            csv,
            "{i},{:.6},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{},{},{:.4},{},{},{:.3},{},{:.3},{}",
            frames[i].time,
            f.frame_ms,
            m.gpu_ms(),
            m.restore_ms,
            m.clip_ms,
            m.update_ms,
            f.render_ms,
            m.clipped,
            m.recomputed,
            m.percent_recomputed(),
            // The TF this frame showed; tf_progress is empty when no switch is in flight.
            f.tf_name,
            f.tf_progress
                .as_ref()
                .map_or(String::new(), |p| format!("{:.4}", p.fraction)),
            f.tf_ms,
            f.sh.voxels,
            f.sh.gpu_ms,
            f.ao_method
        )
        .map_err(|e| out_err(&csv_path, e))?;
        let tf = f
            .tf_progress
            .as_ref()
            .map_or(String::new(), |p| format!("  {p}"));
        let sh = if fl.lighting.is_some() {
            format!("  SH {:>8.1} ms", f.sh.gpu_ms)
        } else {
            String::new()
        };
        eprintln!(
            "frame {i:>5}/{}  t {:>7.3} s  frame {:>8.1} ms  AO {} {:>8.1} ms{sh}  render {:>8.1} ms  recomputed {:>6.2} %{tf}",
            frames.len(),
            frames[i].time,
            f.frame_ms,
            f.ao_method,
            m.gpu_ms(),
            f.render_ms,
            m.percent_recomputed()
        );
        summary.mean_ao_ms += m.gpu_ms() / frames.len() as f64;
        summary.mean_percent_recomputed += m.percent_recomputed() / frames.len() as f64;
        if i % every == 0 {
            let rgb = image.side_by_side_rgb();
            let path = out.join(format!("frame-{i:05}.png"));
            write_rgb(&path, image.width * 2, image.height, &rgb)?;
            summary.pngs += 1;
            if opts.preview.is_some() {
                kept.push(rgb);
            }
        }
        Ok(())
    };
    for (i, due) in replay_schedule(&frames, opts.realtime) {
        if let Some(due) = due {
            if let Some(wait) = due.checked_sub(start.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        submitted.push_back(i);
        if let Some(shown) = fl.submit(&frames[i], true, |_, _| {})? {
            write(submitted.pop_front().expect("submitted"), shown, &fl)?;
        }
    }
    if let Some(shown) = fl.flush()? {
        write(submitted.pop_front().expect("submitted"), shown, &fl)?;
    }
    csv.flush().map_err(|e| out_err(&csv_path, e))?;
    drop(csv);
    std::fs::rename(&csv_path, &csv_final).map_err(|e| out_err(&csv_final, e))?;
    if let Some(p) = &opts.preview {
        let fps = frames.len() as f64 / (frames.last().unwrap().time - frames[0].time).max(1e-3);
        write_apng(
            p,
            opts.size.0 * 2,
            opts.size.1,
            &kept,
            (fps / every as f64).max(1.0),
        )?;
    }
    Ok(summary)
}

/// An animated PNG (APNG) of equally sized RGB frames, looping forever.
pub fn write_apng(
    path: &Path,
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    fps: f64,
) -> Result<()> {
    let err = |e: png::EncodingError| out_err(path, e);
    // Beside its name, renamed once complete.
    let tmp = path.with_extension("png.partial");
    let file = std::fs::File::create(&tmp).map_err(|e| out_err(path, e))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_animated(frames.len().max(1) as u32, 0)
        .map_err(err)?;
    enc.set_frame_delay(1000, (fps * 1000.0).round().clamp(1.0, 65535.0) as u16)
        .map_err(err)?;
    let mut w = enc.write_header().map_err(err)?;
    for f in frames {
        w.write_image_data(f).map_err(err)?;
    }
    w.finish().map_err(err)?;
    std::fs::rename(&tmp, path).map_err(|e| out_err(path, e))
}
