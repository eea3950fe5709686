//! `cao-xr bench frame`: what a frame of the frame loop costs on the GPU, pass by pass, as
//! medians over a carving sweep, and the ratios that say how it scales: two eyes against one,
//! the CAO update against the tool's radius and against a volume twice as large per axis, and
//! frames per second with one and with two frames in flight.

use super::bench::{median, sweep_tools};
use super::common::{precompute_ao, AppError, Result};
use super::frame_loop::{FrameLoop, FrameStats};
use crate::ao::cao::{Cao, Mode};
use crate::ao::{LaoGpu, LaoParams};
use crate::gpu::Gpu;
use crate::input::{FrameInput, InteractionSettings};
use crate::render::{Foveation, RenderSettings};
use crate::scene::Tool;
use crate::space::{default_stereo_views, Placement, DEFAULT_IPD};
use crate::volume::transfer::TransferFunction;
use crate::volume::{Volume, Voxels};
use std::sync::Arc;

/// Tool radii (mm) the CAO update is measured against; the middle one is the sweep's.
pub const RADII_MM: [f32; 3] = [10.0, 25.0, 50.0];
/// The radius of the sweep every other row uses.
const SWEEP_RADIUS_MM: f32 = RADII_MM[1];

/// Median GPU ms of each pass over a sweep.
#[derive(Clone, Copy, Debug, Default)]
pub struct PassMedians {
    pub restore: f64,
    pub clip: f64,
    pub update: f64,
    pub eyes: [f64; 2],
    pub overlay: f64,
    pub copy: f64,
}

impl PassMedians {
    pub fn of(frames: &[FrameStats]) -> PassMedians {
        let m =
            |f: &dyn Fn(&FrameStats) -> f64| median(&mut frames.iter().map(f).collect::<Vec<_>>());
        PassMedians {
            restore: m(&|s| s.metrics.restore_ms),
            clip: m(&|s| s.metrics.clip_ms),
            update: m(&|s| s.metrics.update_ms),
            eyes: [m(&|s| s.passes.eye_ms[0]), m(&|s| s.passes.eye_ms[1])],
            overlay: m(&|s| s.passes.overlay_ms),
            copy: m(&|s| s.passes.copy_ms),
        }
    }

    /// Restore + clip + update: the CAO update.
    pub fn ao(&self) -> f64 {
        self.restore + self.clip + self.update
    }

    /// Every pass, both eyes.
    pub fn two_eyes(&self) -> f64 {
        self.ao() + self.eyes[0] + self.eyes[1] + self.overlay + self.copy
    }

    /// The frame with the left eye alone: the shared AO work, that eye's ray cast and half of
    /// the overlay and the copy (both draw or copy each eye alike).
    pub fn one_eye(&self) -> f64 {
        self.ao() + self.eyes[0] + 0.5 * (self.overlay + self.copy)
    }
}

/// What `bench frame` measured.
#[derive(Clone, Debug)]
pub struct FrameBench {
    pub passes: PassMedians,
    /// (radius mm, median CAO update ms, mean % recomputed) for each of [`RADII_MM`].
    pub by_radius: Vec<(f32, f64, f64)>,
    /// Median CAO update ms of the same sweep on the volume and on it padded to twice its
    /// size per axis (same spacing).
    pub original_ms: f64,
    pub padded_ms: f64,
    pub padded_dims: [usize; 3],
    /// Frames per second of the sweep with each frame read back and encoded as PNG (as replay
    /// does), with one and with two frames in flight.
    pub fps: [f64; 2],
    /// Median ms of both eyes' ray cast with and without empty-space skipping.
    pub skip_ms: [f64; 2],
    /// Both eyes' ray cast unfoveated and with the default foveation (ms), and the foveated
    /// left eye's PSNR against the unfoveated (dB).
    pub foveated: [f64; 3],
    /// Two eyes against one without and with the second eye reprojected (skipping empty
    /// space, interleaved), and the reprojected right eye's PSNR against its own rays (dB).
    pub reprojected: [f64; 3],
}

/// `vol` in the middle of a grid twice as large per axis at the same spacing, the rest filled
/// with its lowest value (air): a bigger head around the same anatomy, at the same place.
pub fn padded(vol: &Volume) -> Volume {
    let d = vol.dims;
    let big = d.map(|n| 2 * n);
    // An odd size leaves the volume half a voxel off centre.
    let off = d.map(|n| n / 2);
    fn pad<T: Copy>(src: &[T], fill: T, d: [usize; 3], big: [usize; 3], off: [usize; 3]) -> Vec<T> {
        let mut out = vec![fill; big[0] * big[1] * big[2]];
        for k in 0..d[2] {
            for j in 0..d[1] {
                let s = d[0] * (j + d[1] * k);
                let t = off[0] + big[0] * (off[1] + j + big[1] * (off[2] + k));
                out[t..t + d[0]].copy_from_slice(&src[s..s + d[0]]);
            }
        }
        out
    }
    let lo = vol.value_range().0;
    let voxels = match &vol.voxels {
        Voxels::U8(v) => Voxels::U8(pad(v, lo as u8, d, big, off)),
        Voxels::U16(v) => Voxels::U16(pad(v, lo as u16, d, big, off)),
        Voxels::I16(v) => Voxels::I16(pad(v, lo as i16, d, big, off)),
        Voxels::F32(v) => Voxels::F32(pad(v, lo, d, big, off)),
    };
    let shift = vol.directions
        * glam::DVec3::new(
            off[0] as f64 * vol.spacing[0],
            off[1] as f64 * vol.spacing[1],
            off[2] as f64 * vol.spacing[2],
        );
    Volume {
        name: format!("{} padded", vol.name),
        dims: big,
        origin: vol.origin - shift,
        voxels,
        ..vol.clone_geometry()
    }
}

/// Median CAO update ms (restore + clip + update) of the sweep `tools` on `vol`, and the mean
/// percentage recomputed.
fn cao_sweep(
    gpu: &Gpu,
    lao: &LaoGpu,
    vol: &Volume,
    tf: &TransferFunction,
    params: LaoParams,
    tools: &[Vec<Tool>],
) -> Result<(f64, f64)> {
    let mut cao = precompute_ao(gpu, lao, vol, tf, &params, false)?.into_cao(gpu, vol)?;
    let (mut ms, pct) = cao_frames(&mut cao, tools)?;
    Ok((median(&mut ms), pct))
}

/// The CAO update ms of each frame of the sweep `tools`, and the mean percentage recomputed.
fn cao_frames(cao: &mut Cao, tools: &[Vec<Tool>]) -> Result<(Vec<f64>, f64)> {
    let placement = Placement::default();
    let (mut ms, mut pct) = (Vec::new(), 0.0);
    for t in tools {
        let m = cao.run_frame(t, &placement, Mode::Contextual)?;
        ms.push(m.gpu_ms());
        pct += m.percent_recomputed() / tools.len() as f64;
    }
    Ok((ms, pct))
}

/// The sweep through the frame loop, one frame per tool set: each frame's stats, and the wall
/// time of the whole sweep. With `encode`, every frame is read back and encoded as PNG (the
/// host's work of a replay) when it leaves the GPU.
fn loop_sweep(
    fl: &mut FrameLoop,
    tools: &[Vec<Tool>],
    encode: bool,
) -> Result<(Vec<FrameStats>, f64)> {
    let views = default_stereo_views(fl.volume(), &fl.scene.volume, DEFAULT_IPD);
    let mut stats = Vec::new();
    let mut keep = |r: super::frame_loop::Retired| -> Result<()> {
        if let Some(img) = &r.image {
            png_bytes(img.width * 2, img.height, &img.side_by_side_rgb())?;
        }
        stats.push(r.stats);
        Ok(())
    };
    let t0 = std::time::Instant::now();
    for (f, t) in tools.iter().enumerate() {
        fl.scene.tools = t.clone();
        let input = FrameInput::without_hands(f as f64 / 90.0, views);
        if let Some(r) = fl.submit(&input, encode, |_, _| {})? {
            keep(r)?;
        }
    }
    if let Some(r) = fl.flush()? {
        keep(r)?;
    }
    Ok((stats, t0.elapsed().as_secs_f64()))
}

fn png_bytes(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>> {
    let err = |e: png::EncodingError| AppError::Usage(format!("PNG encoding: {e}"));
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(err)?;
    w.write_image_data(rgb).map_err(err)?;
    w.finish().map_err(err)?;
    Ok(out)
}

/// Measures `vol` (see the module) with `frames` frames per sweep at `size` pixels per eye;
/// the fps rows take the median of `runs` interleaved runs. Prints the table as it goes.
pub fn bench_frame(
    gpu: &Gpu,
    vol: &Volume,
    tf: &TransferFunction,
    params: LaoParams,
    size: (u32, u32),
    frames: usize,
    runs: usize,
) -> Result<FrameBench> {
    let frames = frames.max(2);
    let sweep = sweep_tools(vol, SWEEP_RADIUS_MM, frames);
    println!(
        "Frame on {} ({}: {}x{}x{}, K = {}, {}x{} per eye, a sphere of {SWEEP_RADIUS_MM} mm \
         radius carving in {frames} frames; GPU ms, medians over the frames)",
        gpu.device_name,
        vol.name,
        vol.dims[0],
        vol.dims[1],
        vol.dims[2],
        params.rays,
        size.0,
        size.1
    );
    let mut fl = FrameLoop::new(
        gpu,
        Arc::new(vol.clone()),
        vec![tf.clone()],
        params,
        size,
        InteractionSettings::default(),
        false,
    )?;
    // Every sample visited (`--no-empty-skip`); the skipping sweep follows.
    fl.settings.skip_empty = false;
    let (stats, _) = loop_sweep(&mut fl, &sweep, true)?;
    let p = PassMedians::of(&stats);
    println!("{:<28} {:>9}", "pass", "ms");
    for (name, ms) in [
        ("restore", p.restore),
        ("clip + mask", p.clip),
        ("AO update", p.update),
        ("ray cast, left eye", p.eyes[0]),
        ("ray cast, right eye", p.eyes[1]),
        ("overlay", p.overlay),
        ("copy", p.copy),
        ("frame", p.two_eyes()),
    ] {
        println!("{name:<28} {ms:>9.2}");
    }
    println!(
        "two eyes / one eye          {:>9.2}x  ({:.2} ms / {:.2} ms; one eye: the AO, the left \
         eye, half the overlay and copy)",
        p.two_eyes() / p.one_eye(),
        p.two_eyes(),
        p.one_eye()
    );
    // The same sweep skipping empty bricks (the default, the same images): what it saves.
    fl.settings.skip_empty = true;
    let (skipped, _) = loop_sweep(&mut fl, &sweep, false)?;
    let skipped = PassMedians::of(&skipped);
    let skip_ms = [skipped.eyes[0] + skipped.eyes[1], p.eyes[0] + p.eyes[1]];
    let (empty, bricks) = fl.tex.empty_bricks();
    println!(
        "ray cast, both eyes, skipping  {:>9.2} ms  {:>5.2}x faster with empty-space skipping  \
         ({empty} of {bricks} bricks empty)",
        skip_ms[0],
        skip_ms[1] / skip_ms[0]
    );
    let foveated = foveation_rows(&mut fl, &sweep, runs)?;
    fl.settings.foveation = None;
    let reprojected = reprojection_rows(&mut fl, &sweep, runs)?;
    fl.settings.reproject = false;
    render_scale_rows(&mut fl, &sweep, runs)?;
    fl.set_render_scale(1.0);
    ablation_rows(&mut fl, &sweep, runs)?;

    let lao = LaoGpu::new(gpu)?;
    let mut by_radius = Vec::new();
    for r in RADII_MM {
        let (ms, pct) = cao_sweep(gpu, &lao, vol, tf, params, &sweep_tools(vol, r, frames))?;
        by_radius.push((r, ms, pct));
    }
    for &(r, ms, pct) in &by_radius {
        println!(
            "CAO update, radius {r:>2} mm   {ms:>9.2} ms  {:>6.2}x of {} mm  ({pct:.2} % recomputed)",
            ms / by_radius[0].1,
            RADII_MM[0]
        );
    }

    // The original and the padded volume's sweeps interleaved, `runs` times, so that a
    // machine busy for a while slows both alike; medians over all their frames.
    let big = padded(vol);
    let (mut cao_small, mut cao_big) = (
        precompute_ao(gpu, &lao, vol, tf, &params, false)?.into_cao(gpu, vol)?,
        precompute_ao(gpu, &lao, &big, tf, &params, false)?.into_cao(gpu, &big)?,
    );
    let (mut small_ms, mut big_ms) = (Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        small_ms.extend(cao_frames(&mut cao_small, &sweep)?.0);
        big_ms.extend(cao_frames(&mut cao_big, &sweep)?.0);
    }
    drop((cao_small, cao_big));
    let (original_ms, padded_ms) = (median(&mut small_ms), median(&mut big_ms));
    println!(
        "CAO update, {}x{}x{} (2x per axis, same spacing, same tool) / original   {:>6.2}x  \
         ({padded_ms:.2} ms / {original_ms:.2} ms, medians of {} interleaved run(s))",
        big.dims[0],
        big.dims[1],
        big.dims[2],
        padded_ms / original_ms,
        runs.max(1)
    );

    // Interleaved, so that a machine busy for a while slows both alike.
    let (mut one, mut two) = (Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        for (depth, out) in [(1, &mut one), (2, &mut two)] {
            fl.set_frames_in_flight(depth)?;
            let (s, secs) = loop_sweep(&mut fl, &sweep, true)?;
            out.push(s.len() as f64 / secs);
        }
    }
    let fps = [median(&mut one), median(&mut two)];
    println!(
        "fps, 1 frame in flight       {:>9.1}\nfps, 2 frames in flight      {:>9.1}  ({:.2}x; \
         each frame read back and encoded as PNG, median of {} run(s))",
        fps[0],
        fps[1],
        fps[1] / fps[0],
        runs.max(1)
    );
    Ok(FrameBench {
        passes: p,
        by_radius,
        original_ms,
        padded_ms,
        padded_dims: big.dims,
        fps,
        skip_ms,
        foveated,
        reprojected,
    })
}

/// What each feature of a sample costs: the sweep's ray cast of both eyes with the default
/// settings and with one feature changed at a time, interleaved `runs` times (medians over all
/// frames); the share of the default's time that each feature's absence saves (or, for one
/// that is off by default, costs).
fn ablation_rows(fl: &mut FrameLoop, sweep: &[Vec<Tool>], runs: usize) -> Result<()> {
    type Change = fn(&mut RenderSettings);
    let rows: [(&str, Change); 8] = [
        ("the default", |_| {}),
        ("no AO lookup", |s| s.use_ao = false),
        ("no gradients (ambient only)", |s| {
            let ao = s.use_ao;
            crate::render::Shading::Ao.apply(s);
            s.use_ao = ao;
        }),
        ("no pre-integration", |s| s.preintegrated = false),
        ("no cut-face lighting", |s| s.cut_lighting = false),
        ("no empty-space skipping", |s| s.skip_empty = false),
        ("clip test at every sample in reach", |s| {
            s.clip_bricks = false
        }),
        ("tricubic scalars (off by default)", |s| s.tricubic = true),
    ];
    let no_tools = vec![Vec::new(); sweep.len()];
    let base = fl.settings;
    // The rows above, then the sweep without its tool: the clip tests' share.
    let mut ms = vec![Vec::new(); rows.len() + 1];
    for _ in 0..runs.max(1) {
        for (k, out) in ms.iter_mut().enumerate() {
            let mut s = base;
            if let Some((_, change)) = rows.get(k) {
                change(&mut s);
            }
            fl.settings = s;
            let tools = if k < rows.len() { sweep } else { &no_tools[..] };
            // Two frames untimed first: a change of settings rebuilds tables on the host
            // (pre-integration, empty bricks), which on a CPU device competes with the GPU's
            // threads for the cores.
            loop_sweep(fl, &tools[..2.min(tools.len())], false)?;
            let (stats, _) = loop_sweep(fl, tools, false)?;
            out.extend(
                stats
                    .iter()
                    .map(|s| s.passes.eye_ms[0] + s.passes.eye_ms[1]),
            );
        }
    }
    fl.settings = base;
    let ms: Vec<f64> = ms.into_iter().map(|mut m| median(&mut m)).collect();
    println!(
        "per-feature ablation, ray cast of both eyes (medians of {} interleaved run(s)):",
        runs.max(1)
    );
    let names = rows
        .iter()
        .map(|r| r.0)
        .chain(["no carving tool (no clip tests)"]);
    for (name, &m) in names.zip(&ms) {
        println!(
            "  {name:<34} {m:>9.2} ms  {:>+6.1} % of the default",
            100.0 * (m - ms[0]) / ms[0]
        );
    }
    Ok(())
}

/// The sweep's ray cast of both eyes unfoveated, with the default [`Foveation`] and with other
/// rings, interleaved `runs` times (medians over all their frames), and the PSNR of each last
/// frame's left eye against the same frame unfoveated. Returns [unfoveated ms, default
/// foveated ms, its PSNR dB].
fn foveation_rows(fl: &mut FrameLoop, sweep: &[Vec<Tool>], runs: usize) -> Result<[f64; 3]> {
    // The default first, then other rings for comparison.
    let mut rings = vec![Foveation::default()];
    rings.extend(
        [(0.33, 2), (0.25, 2), (0.33, 3), (0.25, 3), (0.2, 4)]
            .map(|(radius, factor)| Foveation { radius, factor })
            .into_iter()
            .filter(|f| *f != Foveation::default()),
    );
    let configs: Vec<Option<Foveation>> = std::iter::once(None)
        .chain(rings.iter().copied().map(Some))
        .collect();
    let mut ms = vec![Vec::new(); configs.len()];
    let mut pictures = vec![None; configs.len()];
    for _ in 0..runs.max(1) {
        for (k, f) in configs.iter().enumerate() {
            fl.settings.foveation = *f;
            let (stats, _) = loop_sweep(fl, sweep, false)?;
            ms[k].extend(
                stats
                    .iter()
                    .map(|s| s.passes.eye_ms[0] + s.passes.eye_ms[1]),
            );
            pictures[k] = last_frame_again(fl)?.map(|p| crate::render::compare::luma(&p.rgba[0]));
        }
    }
    let ms: Vec<f64> = ms.into_iter().map(|mut m| median(&mut m)).collect();
    let psnr = |k: usize| match (&pictures[0], &pictures[k]) {
        (Some(a), Some(b)) => crate::render::compare::psnr(a, b),
        _ => f64::NAN,
    };
    for (k, f) in rings.iter().enumerate() {
        println!(
            "ray cast, both eyes, foveated  {:>9.2} ms  {:>5.2}x faster than {:.2} ms \
             (radius {} of the half-diagonal, 1 ray per {f}x{f} beyond{}; left eye {:.1} dB \
             against unfoveated; medians of {} interleaved run(s))",
            ms[k + 1],
            ms[0] / ms[k + 1],
            ms[0],
            f.radius,
            if k == 0 { ", the default" } else { "" },
            psnr(k + 1),
            runs.max(1),
            f = f.factor,
        );
    }
    Ok([ms[0], ms[1], psnr(1)])
}

/// The sweep with both eyes cast and with the second eye reprojected from the first
/// ([`crate::render::RenderSettings::reproject`]), unfoveated and foveated (the default rings),
/// interleaved `runs` times: two eyes against one for each (medians over all their frames), and
/// the PSNR of the last frame's right eye reprojected against the same eye cast. Returns [ratio
/// cast, ratio reprojected, PSNR dB], unfoveated.
fn reprojection_rows(fl: &mut FrameLoop, sweep: &[Vec<Tool>], runs: usize) -> Result<[f64; 3]> {
    let configs = [
        (None, false),
        (None, true),
        (Some(Foveation::default()), false),
        (Some(Foveation::default()), true),
    ];
    let mut stats = [(); 4].map(|_| Vec::new());
    let mut pictures = [(); 4].map(|_| None);
    for _ in 0..runs.max(1) {
        for (k, &(foveation, reproject)) in configs.iter().enumerate() {
            fl.settings.foveation = foveation;
            fl.settings.reproject = reproject;
            stats[k].extend(loop_sweep(fl, sweep, false)?.0);
            pictures[k] = last_frame_again(fl)?.map(|p| crate::render::compare::luma(&p.rgba[1]));
        }
    }
    fl.settings.foveation = None;
    let medians = stats.map(|s| PassMedians::of(&s));
    let psnr = |k: usize| match (&pictures[k - 1], &pictures[k]) {
        (Some(a), Some(b)) => crate::render::compare::psnr(a, b),
        _ => f64::NAN,
    };
    let names = [
        "cast",
        "reprojected",
        "foveated, cast",
        "foveated, reprojected",
    ];
    for (k, (name, p)) in names.iter().zip(&medians).enumerate() {
        println!(
            "two eyes / one eye, {name:<12} {:>6.2}x  ({:.2} ms / {:.2} ms; right eye {:.2} ms, \
             left {:.2} ms{}; skipping, medians of {} interleaved run(s))",
            p.two_eyes() / p.one_eye(),
            p.two_eyes(),
            p.one_eye(),
            p.eyes[1],
            p.eyes[0],
            if k % 2 == 0 {
                String::new()
            } else {
                format!("; right eye {:.1} dB against its own rays", psnr(k))
            },
            runs.max(1)
        );
    }
    let [cast, re, ..] = medians;
    let psnr = psnr(1);
    Ok([
        cast.two_eyes() / cast.one_eye(),
        re.two_eyes() / re.one_eye(),
        psnr,
    ])
}

/// The render scales the frame budget takes, measured: the sweep's ray cast of both eyes at
/// each (interleaved `runs` times, medians over all frames), and the last frame's left eye
/// enlarged back to full size (bilinear, as a compositor or the window's blit does) against the
/// full-size picture.
fn render_scale_rows(fl: &mut FrameLoop, sweep: &[Vec<Tool>], runs: usize) -> Result<()> {
    let scales = [1.0, 0.75, super::budget::MIN_RENDER_SCALE];
    let mut ms = vec![Vec::new(); scales.len()];
    let mut pictures = vec![None; scales.len()];
    for _ in 0..runs.max(1) {
        for (k, &s) in scales.iter().enumerate() {
            fl.set_render_scale(s);
            let (stats, _) = loop_sweep(fl, sweep, false)?;
            ms[k].extend(
                stats
                    .iter()
                    .map(|s| s.passes.eye_ms[0] + s.passes.eye_ms[1]),
            );
            pictures[k] = last_frame_again(fl)?;
        }
    }
    let (w, h) = (fl.target().width, fl.target().height);
    let full = |p: &crate::render::StereoImage| {
        let luma = crate::render::compare::luma(&p.rgba[0]);
        enlarged(&luma, (p.width, p.height), (w, h))
    };
    let reference = pictures[0].as_ref().map(full);
    let ms: Vec<f64> = ms.into_iter().map(|mut m| median(&mut m)).collect();
    for (k, &s) in scales.iter().enumerate().skip(1) {
        let psnr = match (&reference, pictures[k].as_ref().map(full)) {
            (Some(a), Some(b)) => crate::render::compare::psnr(a, &b),
            _ => f64::NAN,
        };
        println!(
            "ray cast, both eyes, scale {s:<4} {:>7.2} ms  {:>5.2}x faster than {:.2} ms (each \
             eye drawn at {s} of its size per axis; left eye enlarged back {psnr:.1} dB against \
             full size; medians of {} interleaved run(s))",
            ms[k],
            ms[0] / ms[k],
            ms[0],
            runs.max(1)
        );
    }
    Ok(())
}

/// The sweep's last frame (its tools as they are) once more, read back: the picture a row
/// compares.
fn last_frame_again(fl: &mut FrameLoop) -> Result<Option<crate::render::StereoImage>> {
    let views = default_stereo_views(fl.volume(), &fl.scene.volume, DEFAULT_IPD);
    fl.submit(&FrameInput::without_hands(0.0, views), true, |_, _| {})?;
    Ok(fl.flush()?.and_then(|r| r.image))
}

/// `values` (`from` pixels, rows top-down) resampled to `to` pixels, bilinear between pixel
/// centres (clamped at the border): what a blit with a linear filter makes of a smaller image.
fn enlarged(values: &[f64], from: (u32, u32), to: (u32, u32)) -> Vec<f64> {
    let (fw, fh) = (from.0 as usize, from.1 as usize);
    let at = |x: usize, y: usize| values[y.min(fh - 1) * fw + x.min(fw - 1)];
    let axis = |i: u32, n: u32, of: usize| {
        let p = ((i as f64 + 0.5) * of as f64 / n as f64 - 0.5).max(0.0);
        (p.floor() as usize, p.fract())
    };
    (0..to.1)
        .flat_map(|y| (0..to.0).map(move |x| (x, y)))
        .map(|(x, y)| {
            let ((x0, fx), (y0, fy)) = (axis(x, to.0, fw), axis(y, to.1, fh));
            let row = |y: usize| at(x0, y) * (1.0 - fx) + at(x0 + 1, y) * fx;
            row(y0) * (1.0 - fy) + row(y0 + 1) * fy
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn enlarging_is_bilinear_between_pixel_centres() {
        // The same size: unchanged.
        let v: Vec<f64> = (0..12).map(|i| i as f64).collect();
        assert_eq!(enlarged(&v, (4, 3), (4, 3)), v);
        // A 2 x 1 ramp to 4 x 1: the outer pixels clamp, the inner ones are a quarter and
        // three quarters of the way (pixel centres 0.25 and 0.75 of a source pixel apart).
        assert_eq!(
            enlarged(&[0.0, 4.0], (2, 1), (4, 1)),
            vec![0.0, 1.0, 3.0, 4.0]
        );
        // Rows too.
        assert_eq!(
            enlarged(&[0.0, 8.0], (1, 2), (1, 4)),
            vec![0.0, 2.0, 6.0, 8.0]
        );
    }

    #[test]
    fn padding_centres_the_volume_in_twice_the_grid_at_the_same_spacing() {
        let v = crate::volume::phantom::head(6);
        let p = padded(&v);
        assert_eq!(p.dims, [12, 12, 12]);
        assert_eq!(p.spacing, v.spacing);
        let lo = v.value_range().0;
        for k in 0..12 {
            for j in 0..12 {
                for i in 0..12 {
                    let inside = [i, j, k].iter().all(|&a| (3..9).contains(&a));
                    let want = if inside {
                        v.voxels.get(v.index(i - 3, j - 3, k - 3))
                    } else {
                        lo
                    };
                    assert_eq!(p.voxels.get(p.index(i, j, k)), want, "{i} {j} {k}");
                }
            }
        }
        // Same world place: the centre of voxel (3,3,3) is where (0,0,0) was.
        assert!((p.origin + glam::DVec3::splat(3.0 * v.spacing[0]) - v.origin).length() < 1e-9);
        let at = |vol: &Volume, idx: f32| {
            let n = vol.dims[0] as f32;
            crate::space::world_from_tex(vol, &Placement::default())
                .transform_point3(glam::Vec3::splat((idx + 0.5) / n))
        };
        assert!((at(&v, 0.0) - at(&p, 3.0)).length() < 1e-6);
    }
}
