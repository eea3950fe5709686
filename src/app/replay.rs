//! `cao-xr replay`: renders every frame of a pose stream headless through the one frame loop,
//! writing side-by-side PNGs, per-frame metrics (CSV) and an optional animated PNG preview.

use super::common::{AppError, Result};
use super::frame_loop::FrameLoop;
use super::session::SessionSpec;
use crate::ao::cao::Mode;
use crate::clip::Shape;
use crate::gpu::{Gpu, GpuMemory};
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
    /// The volume's centre (stage metres), instead of the stream's or the default.
    pub volume_at: Option<glam::Vec3>,
    /// Every this many frames, sample host and GPU memory ([`ReplayStats`]) and print the
    /// sample on stdout.
    pub stats_every: Option<usize>,
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
            volume_at: None,
            stats_every: None,
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
    /// Frames recorded while the frame before was still in flight (two frames in flight).
    pub overlapped: usize,
    /// The samples of `--stats-every`, in order.
    pub stats: Vec<ReplayStats>,
}

/// A sample of what the process holds after `frames` frames: for soak runs, where memory must
/// stay flat and frame time must not creep up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReplayStats {
    /// Frames rendered so far.
    pub frames: usize,
    /// Host resident set size (None without /proc).
    pub rss_bytes: Option<u64>,
    pub gpu: GpuMemory,
    /// CPU time of the whole process (user + system, all threads, lavapipe's included), s.
    pub cpu_s: f64,
    /// Wall time since the first frame began, s.
    pub wall_s: f64,
    /// Validation warnings and errors so far.
    pub validation_messages: usize,
}

impl std::fmt::Display for ReplayStats {
    /// One line of `key=value` pairs after the word `stats`, for scripts and tests to parse.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let rss = self
            .rss_bytes
            .map_or("unknown".to_string(), |b| b.to_string());
        write!(
            f,
            "stats frames={} rss_bytes={rss} gpu_allocated_bytes={} gpu_capacity_bytes={} \
             gpu_allocations={} cpu_s={:.3} wall_s={:.3} validation_messages={}",
            self.frames,
            self.gpu.allocated_bytes,
            self.gpu.capacity_bytes,
            self.gpu.allocations,
            self.cpu_s,
            self.wall_s,
            self.validation_messages
        )
    }
}

/// The process's resident set size in bytes (the second field of /proc/self/statm, in pages:
/// VmRSS); None where there is no procfs.
pub fn host_rss_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    // SAFETY: sysconf reads no memory of ours; _SC_PAGESIZE is a valid name.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    u64::try_from(page).ok().map(|p| pages * p)
}

/// CPU time this process has used so far (user + system, all threads), in seconds.
fn cpu_seconds() -> f64 {
    let mut u = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: `u` is writable storage for one rusage, which is all getrusage writes.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, u.as_mut_ptr()) } != 0 {
        return f64::NAN;
    }
    // SAFETY: `u` was zeroed (all zeroes is a valid rusage) and getrusage filled it.
    let u = unsafe { u.assume_init() };
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    secs(u.ru_utime) + secs(u.ru_stime)
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
        super::session::desktop_interaction()
    } else {
        InteractionSettings::default()
    };
    let mut fl = spec.frame_loop(gpu, opts.size, interaction, true, false)?;
    fl.mode = opts.mode;
    // A moved inset is computed over frames as in the window and the headset, a fixed budget
    // of slices a frame, so the frames are the same on any machine.
    fl.progressive_inset = true;
    // Where the session put the volume (`--volume-at` overrides the stream's header).
    if let Some(c) = opts
        .volume_at
        .or(header.volume_at.map(glam::Vec3::from_array))
    {
        fl.scene.volume.center = c;
    }
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
    let stats_every = opts.stats_every.filter(|&n| n > 0);
    // Frames written so far, in order, for the stats samples.
    let mut written = 0usize;
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
        let inset = f.inset.map_or(String::new(), |i| format!("  {i}"));
        let sh = if fl.lighting.is_some() {
            format!("  SH {:>8.1} ms", f.sh.gpu_ms)
        } else {
            String::new()
        };
        let margin = fl
            .margin_warning(&f.margins)
            .into_iter()
            .chain(fl.structure_menu())
            .map(|w| format!("  {w}"))
            .collect::<String>();
        eprintln!(
            "frame {i:>5}/{}  t {:>7.3} s  frame {:>8.1} ms  AO {} {:>8.1} ms{sh}  render {:>8.1} ms  recomputed {:>6.2} %{inset}{tf}{margin}",
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
        summary.overlapped += f.overlapped as usize;
        if i % every == 0 {
            let rgb = image.side_by_side_rgb();
            let path = out.join(format!("frame-{i:05}.png"));
            write_rgb(&path, image.width * 2, image.height, &rgb)?;
            summary.pngs += 1;
            if opts.preview.is_some() {
                kept.push(rgb);
            }
        }
        written += 1;
        if stats_every.is_some_and(|n| written % n == 0) {
            let sample = ReplayStats {
                frames: written,
                rss_bytes: host_rss_bytes(),
                gpu: fl.gpu.allocator_memory(),
                cpu_s: cpu_seconds(),
                wall_s: start.elapsed().as_secs_f64(),
                validation_messages: fl.gpu.validation_messages().len(),
            };
            println!("{sample}");
            summary.stats.push(sample);
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
    spec.save_markups(&fl, &out.join("markups.mrk.json"))?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// VmRSS as /proc/self/status states it, in bytes.
    fn status_vm_rss() -> u64 {
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
        let kb: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
        kb * 1024
    }

    #[test]
    fn host_rss_is_the_resident_set_and_follows_touched_memory() {
        let before = host_rss_bytes().unwrap();
        let status = status_vm_rss();
        // Other tests run in parallel threads, so only roughly the same moment.
        assert!(
            before.abs_diff(status) < 16 << 20,
            "statm {before} vs status {status}"
        );
        // 64 MB written page by page are resident.
        let mut block = vec![0u8; 64 << 20];
        for b in block.iter_mut().step_by(4096) {
            *b = 1;
        }
        let after = host_rss_bytes().unwrap();
        assert!(after >= before + (48 << 20), "{before} -> {after}");
        assert_eq!(std::hint::black_box(&block)[4096], 1);
    }

    #[test]
    fn a_stats_line_is_key_value_pairs() {
        let s = ReplayStats {
            frames: 1000,
            rss_bytes: Some(123),
            gpu: GpuMemory {
                allocated_bytes: 4,
                capacity_bytes: 5,
                allocations: 6,
            },
            cpu_s: 1.5,
            wall_s: 2.25,
            validation_messages: 0,
        };
        assert_eq!(
            s.to_string(),
            "stats frames=1000 rss_bytes=123 gpu_allocated_bytes=4 gpu_capacity_bytes=5 \
             gpu_allocations=6 cpu_s=1.500 wall_s=2.250 validation_messages=0"
        );
    }
}
