//! `cao-xr bench scale`: how cao-xr scales with the volume, on synthetic chest CTs of clinical
//! sizes ([`phantom::chest`], written as NIfTI and read back like a user's file): per size the
//! load time and the time to a first picture (a fast start, [`Built::fast_start_after_s`]); per
//! size and AO method the precompute, the GPU bytes per voxel, the peak host memory, the CAO
//! update of a fixed tool and the ray cast per eye.

use super::bench_ao::peak_rss_bytes;
use super::bench_frame::PassMedians;
use super::common::{load_volume, AppError, Result};
use super::frame_loop::{Built, FrameLoop, FAST_START_AFTER_S};
use crate::ao::{AoConfig, AoMethod};
use crate::gpu::Gpu;
use crate::input::{FrameInput, InteractionSettings};
use crate::scene::Tool;
use crate::space::{default_stereo_views, DEFAULT_IPD};
use crate::volume::transfer::TransferFunction;
use crate::volume::{nifti, phantom, Volume};
use std::sync::Arc;
use std::time::Instant;

/// What `bench scale` measures.
pub struct ScaleOptions {
    /// Grids of the synthetic chest CTs, all at `spacing`.
    pub sizes: Vec<[usize; 3]>,
    pub spacing: [f64; 3],
    /// The configured AO (its LAO and filter parameters); each of `methods` is run with them.
    pub config: AoConfig,
    pub methods: Vec<AoMethod>,
    pub tf: TransferFunction,
    /// Pixels per eye.
    pub eye: (u32, u32),
    /// Frames with the fixed tool (the first carves; the medians are over the rest).
    pub frames: usize,
    /// The fixed tool, placed in mm from the volume's centre (the same anatomy at every size).
    pub tool: Tool,
}

/// One size's figures.
#[derive(Clone, Debug)]
pub struct ScaleRow {
    pub dims: [usize; 3],
    pub load_s: f64,
    pub first_picture_s: f64,
    /// The method the first picture was lit by.
    pub first_method: String,
    pub methods: Vec<MethodRow>,
}

/// One method's figures at one size.
#[derive(Clone, Debug)]
pub struct MethodRow {
    pub method: String,
    pub precompute_s: f64,
    /// GPU bytes per voxel at peak (set-up included) and held while the tool carves.
    pub gpu_bytes_per_voxel: f64,
    pub gpu_held_bytes_per_voxel: f64,
    pub peak_rss: u64,
    /// Median GPU ms of restore + clip + update with the tool fixed, and of each.
    pub cao_ms: f64,
    pub cao_passes_ms: [f64; 3],
    pub voxels_recomputed: u64,
    /// Median GPU ms of one eye's ray cast.
    pub eye_ms: f64,
}

/// Starts the process's peak resident memory (VmHWM) again from what it holds now (Linux 4.0+);
/// elsewhere it keeps counting from the start.
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Writes each size's chest as NIfTI into `dir`, reads it back and measures; prints the tables
/// as rows finish.
pub fn bench_scale(gpu: &Gpu, opts: &ScaleOptions, dir: &std::path::Path) -> Result<Vec<ScaleRow>> {
    std::fs::create_dir_all(dir).map_err(|e| AppError::Output {
        path: dir.display().to_string(),
        msg: e.to_string(),
    })?;
    println!(
        "Scale on {} (synthetic chest CTs at {:?} mm, TF {}, LAO K = {} M = {}, {}x{} per eye, \
         a {:.0} mm {} fixed for {} frames; GPU ms are medians over the frames after the first)",
        gpu.device_name,
        opts.spacing,
        opts.tf.name,
        opts.config.lao.rays,
        opts.config.lao.steps,
        opts.eye.0,
        opts.eye.1,
        opts.tool.size * 1e3,
        format!("{:?}", opts.tool.shape).to_lowercase(),
        opts.frames,
    );
    println!(
        "{:<14} {:>8} {:>7} {:>9} {:<14} {:>10} {:>9} {:>9} {:>8} {:>9} {:>10} {:>9}",
        "volume",
        "Mvoxels",
        "load s",
        "first s",
        "method",
        "precomp s",
        "peak B/vx",
        "held B/vx",
        "RSS GiB",
        "CAO ms",
        "recomputed",
        "eye ms"
    );
    let mut rows = Vec::new();
    for &dims in &opts.sizes {
        let path = dir.join(format!("chest-{}x{}x{}.nii", dims[0], dims[1], dims[2]));
        nifti::write(&path, &phantom::chest(dims, opts.spacing), false)?;
        let t0 = Instant::now();
        let vol = Arc::new(load_volume(path.to_str(), None)?);
        let load_s = t0.elapsed().as_secs_f64();
        // The first picture as the window and the headset show it: loaded, a fast start of the
        // configured method, one frame.
        let (first_s, first_method) = {
            let mut fl = frame_loop(gpu, &vol, opts, opts.config, Some(FAST_START_AFTER_S))?;
            let stats = frames(&mut fl, opts, 1)?;
            (t0.elapsed().as_secs_f64(), stats[0].ao_method.clone())
        };
        let _ = std::fs::remove_file(&path);
        let mut row = ScaleRow {
            dims,
            load_s,
            first_picture_s: first_s,
            first_method,
            methods: Vec::new(),
        };
        for &method in &opts.methods {
            gpu.reset_memory_peak();
            reset_peak_rss();
            let config = AoConfig {
                method,
                ..opts.config
            };
            let t = Instant::now();
            let mut fl = frame_loop(gpu, &vol, opts, config, None)?;
            let precompute_s = t.elapsed().as_secs_f64();
            let stats = frames(&mut fl, opts, opts.frames.max(2))?;
            let steady = &stats[1..];
            let p = PassMedians::of(steady);
            let m = MethodRow {
                method: method.name(),
                precompute_s,
                gpu_bytes_per_voxel: gpu.memory_peak() as f64 / vol.voxel_count() as f64,
                gpu_held_bytes_per_voxel: gpu.memory_in_use() as f64 / vol.voxel_count() as f64,
                peak_rss: peak_rss_bytes(),
                cao_ms: p.ao(),
                cao_passes_ms: [p.restore, p.clip, p.update],
                voxels_recomputed: steady.last().map_or(0, |s| s.metrics.recomputed),
                eye_ms: 0.5 * (p.eyes[0] + p.eyes[1]),
            };
            let first = row.methods.is_empty();
            println!(
                "{:<14} {:>8} {:>7} {:>9} {:<14} {:>10.1} {:>9.1} {:>9.1} {:>8.2} {:>9.1} {:>10} {:>9.0}",
                if first {
                    format!("{}x{}x{}", dims[0], dims[1], dims[2])
                } else {
                    String::new()
                },
                if first {
                    format!("{:.1}", vol.voxel_count() as f64 / 1e6)
                } else {
                    String::new()
                },
                if first {
                    format!("{load_s:.1}")
                } else {
                    String::new()
                },
                if first {
                    format!("{first_s:.1}")
                } else {
                    String::new()
                },
                m.method,
                m.precompute_s,
                m.gpu_bytes_per_voxel,
                m.gpu_held_bytes_per_voxel,
                m.peak_rss as f64 / (1u64 << 30) as f64,
                m.cao_ms,
                m.voxels_recomputed,
                m.eye_ms
            );
            row.methods.push(m);
        }
        println!("{:<14} first picture lit by {}", "", row.first_method);
        rows.push(row);
    }
    // How the CAO update follows the tool, not the volume: each size against the first.
    if let Some(base) = rows.first() {
        for r in &rows[1..] {
            for (m, b) in r.methods.iter().zip(&base.methods) {
                let [r0, c0, u0] = b.cao_passes_ms;
                let [r1, c1, u1] = m.cao_passes_ms;
                println!(
                    "CAO update {:<14} {}x{}x{} / {}x{}x{}: {:.2}x (restore {:.2}x, clip + mask \
                     {:.2}x, update {:.2}x)",
                    m.method,
                    r.dims[0],
                    r.dims[1],
                    r.dims[2],
                    base.dims[0],
                    base.dims[1],
                    base.dims[2],
                    m.cao_ms / b.cao_ms,
                    r1 / r0,
                    c1 / c0,
                    u1 / u0
                );
            }
        }
    }
    Ok(rows)
}

fn frame_loop(
    gpu: &Gpu,
    vol: &Arc<Volume>,
    opts: &ScaleOptions,
    config: AoConfig,
    fast_start_after_s: Option<f64>,
) -> Result<FrameLoop> {
    let built = Built {
        config,
        size: opts.eye,
        interaction: InteractionSettings::default(),
        fast_start_after_s,
    };
    FrameLoop::new_lit(
        gpu,
        Arc::clone(vol),
        vec![opts.tf.clone()],
        built,
        None,
        false,
    )
}

/// `n` frames with the fixed tool, each waited for.
fn frames(
    fl: &mut FrameLoop,
    opts: &ScaleOptions,
    n: usize,
) -> Result<Vec<super::frame_loop::FrameStats>> {
    let views = default_stereo_views(fl.volume(), &fl.scene.volume, DEFAULT_IPD);
    fl.scene.tools = vec![opts.tool];
    (0..n)
        .map(|f| fl.render(&FrameInput::without_hands(f as f64 / 90.0, views)))
        .collect()
}
