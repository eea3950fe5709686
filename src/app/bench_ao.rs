//! `cao-xr bench ao`: every AO method side by side in one run: the full compute, the per-frame
//! clip update of the `bench cao` sphere sweep, the time from a TF change to the new AO, the
//! method's own GPU memory, the filters' error against their exact box openness, and how each
//! method's picture differs from LAO's at K = 54 (PSNR, SSIM of three fixed views).

use super::bench::{median, sweep_tools, BenchOn};
use super::common::{
    histogram_state, histogram_tables, precompute, precompute_histogram, AoVolume,
    HeadlessRenderer, Result,
};
use crate::ao::cao::Mode;
use crate::ao::filtered::{Estimator, FilterParams};
use crate::ao::histogram::{self, HistParams};
use crate::ao::{AoConfig, AoMethod, LaoGpu, LaoParams};
use crate::gpu::Buffer;
use crate::render::compare::{luma, psnr, ssim};
use crate::render::{FrameViews, RenderSettings, VolumeTextures};
use crate::space::{default_stereo_views, world_from_tex, Placement, DEFAULT_IPD};
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use glam::Quat;
use rayon::prelude::*;

/// Pixels per side of the comparison renders.
const VIEW_SIZE: u32 = 256;

#[derive(Clone, Debug)]
pub struct AoBenchRow {
    pub volume: String,
    pub method: String,
    pub radius_mm: Option<f64>,
    pub full_ms: f64,
    pub clip_ms: f64,
    pub tf_change_ms: f64,
    pub resident_mb: f64,
    /// Mean |openness - the exact box openness| (filters only).
    pub error: Option<f64>,
    pub psnr_db: f64,
    pub ssim: f64,
}

/// A stored AO volume of `vol` as values.
fn read(b: &Buffer, vol: &Volume) -> Result<Vec<f32>> {
    Ok(crate::ao::stored::read(b, vol.voxel_count())?)
}

/// Left-eye luma of the volume lit by `ao` from three fixed views (turned 0 and +-40 degrees).
fn pictures(
    hr: &mut HeadlessRenderer,
    tex: &VolumeTextures,
    vol: &Volume,
    ao: &Buffer,
) -> Result<Vec<Vec<f64>>> {
    [0.0f32, 40.0, -40.0]
        .iter()
        .map(|deg| {
            let placement = Placement {
                rotation: Quat::from_rotation_y(deg.to_radians()),
                ..Default::default()
            };
            let views = default_stereo_views(vol, &placement, DEFAULT_IPD);
            let frame = FrameViews {
                ao: Some(ao.into()),
                ..FrameViews::new(&views, world_from_tex(vol, &placement))
            };
            let size = (VIEW_SIZE, VIEW_SIZE);
            let img = hr.render(tex, &frame, size, &RenderSettings::default())?;
            Ok(luma(&img.rgba[0]))
        })
        .collect()
}

/// The method's own GPU memory beyond the volumes every method has (O, O_c, the mask, V_PAO,
/// V_AO): LAO's skipping data, the filters' two statistics volumes.
fn resident_bytes(v: &AoVolume) -> u64 {
    v.method.resident_bytes()
}

/// One table for every volume: LAO at `base`, then each filter estimator at each radius.
pub fn bench_ao(
    on: BenchOn<'_>,
    tf_after: &TransferFunction,
    radii: &[f64],
    base: &LaoParams,
    frames: usize,
    runs: usize,
) -> Result<Vec<AoBenchRow>> {
    let BenchOn { gpu, volumes, tf } = on;
    let lao = LaoGpu::new(gpu)?;
    let mut hr = HeadlessRenderer::new(gpu)?;
    let placement = Placement::default();
    println!(
        "AO methods on {} (full = wall ms of the compute submissions, waited; clip = GPU ms; medians of {runs} run(s); clip: the mean CAO update per frame of a \
         25 mm sphere sweeping {frames} frames; TF change = wall ms until the new AO is complete, \
         {} -> {}; MB = the method's own GPU memory; error = mean |A - exact box openness|; \
         PSNR/SSIM of three views against LAO at K = 54)",
        gpu.device_name, tf.name, tf_after.name
    );
    println!(
        "{:<12} {:<14} {:>5} {:>10} {:>9} {:>10} {:>7} {:>8} {:>8} {:>6}",
        "volume", "method", "R mm", "full ms", "clip ms", "TF ms", "MB", "error", "PSNR dB", "SSIM"
    );
    let mut rows = Vec::new();
    for vol in volumes {
        let tex = VolumeTextures::new(gpu, vol, tf)?;
        let reference = {
            let cfg = AoConfig::from(LaoParams { rays: 54, ..*base });
            let v = precompute(gpu, &lao, vol, tf, &cfg, false)?;
            pictures(&mut hr, &tex, vol, &v.ao_buf)?
        };
        let mut methods = vec![(AoMethod::Lao, None)];
        for &r in radii {
            let exact = FilterParams {
                radius_mm: r,
                estimator: Estimator::Exact,
                ..Default::default()
            };
            let cfg = AoConfig::new(AoMethod::Filter(exact), *base);
            let exact_ao = read(&precompute(gpu, &lao, vol, tf, &cfg, false)?.ao_buf, vol)?;
            for estimator in [Estimator::Cdf, Estimator::Gauss, Estimator::Penner] {
                let p = FilterParams { estimator, ..exact };
                methods.push((AoMethod::Filter(p), Some(exact_ao.clone())));
            }
        }
        let sweep = sweep_tools(vol, 25.0, frames);
        for (method, exact) in methods {
            let cfg = AoConfig::new(method, *base);
            let (mut full, mut clip) = (Vec::new(), Vec::new());
            let mut last = None;
            for _ in 0..runs.max(1) {
                let v = precompute(gpu, &lao, vol, tf, &cfg, false)?;
                // The submissions' wall time, waited: lavapipe's timestamps around LAO's slabs
                // read near zero after other work in the same run.
                full.push(v.timing.wall_ms);
                last = Some(v);
            }
            let v = last.expect("at least one run");
            let resident_mb = resident_bytes(&v) as f64 / (1 << 20) as f64;
            let ao = read(&v.ao_buf, vol)?;
            let error = exact.map(|e| {
                ao.iter()
                    .zip(&e)
                    .map(|(a, b)| (a - b).abs() as f64)
                    .sum::<f64>()
                    / ao.len() as f64
            });
            let pics = pictures(&mut hr, &tex, vol, &v.ao_buf)?;
            let n = pics.len() as f64;
            let psnr_db = pics
                .iter()
                .zip(&reference)
                .map(|(a, b)| psnr(a, b))
                .sum::<f64>()
                / n;
            let side = VIEW_SIZE as usize;
            let ssim = pics
                .iter()
                .zip(&reference)
                .map(|(a, b)| ssim(a, b, side, side))
                .sum::<f64>()
                / n;
            let mut cao = v.into_cao(gpu, vol)?;
            for _ in 0..runs.max(1) {
                let mut ms = 0.0;
                for tools in &sweep {
                    ms += cao.run_frame(tools, &placement, Mode::Contextual)?.gpu_ms();
                }
                clip.push(ms / sweep.len().max(1) as f64);
            }
            drop(cao);
            let t0 = std::time::Instant::now();
            drop(precompute(gpu, &lao, vol, tf_after, &cfg, false)?);
            let tf_change_ms = t0.elapsed().as_secs_f64() * 1e3;
            let row = AoBenchRow {
                volume: vol.name.clone(),
                method: method.name(),
                radius_mm: match method {
                    AoMethod::Filter(p) => Some(p.radius_mm),
                    AoMethod::Histogram(h) => Some(h.radius_mm),
                    AoMethod::Lao => None,
                },
                full_ms: median(&mut full),
                clip_ms: median(&mut clip),
                tf_change_ms,
                resident_mb,
                error,
                psnr_db,
                ssim,
            };
            println!(
                "{:<12} {:<14} {:>5} {:>10.1} {:>9.1} {:>10.1} {:>7.2} {:>8} {:>8.2} {:>6.3}",
                row.volume,
                if row.method == "lao" {
                    format!("lao K={}", base.rays)
                } else {
                    row.method.clone()
                },
                row.radius_mm.map_or("-".into(), |r| format!("{r}")),
                row.full_ms,
                row.clip_ms,
                row.tf_change_ms,
                row.resident_mb,
                row.error.map_or("-".into(), |e| format!("{e:.4}")),
                row.psnr_db,
                row.ssim
            );
            rows.push(row);
        }
        if let Some(lao_row) = rows
            .iter()
            .rev()
            .find(|r| r.volume == vol.name && r.method == "lao")
        {
            let fastest = rows
                .iter()
                .filter(|r| r.volume == vol.name && r.method != "lao")
                .map(|r| r.full_ms)
                .fold(f64::MAX, f64::min);
            println!(
                "{:<12} the fastest filter costs {:.3} of LAO's full compute",
                vol.name,
                fastest / lao_row.full_ms
            );
        }
    }
    Ok(rows)
}

/// Peak resident memory of this process so far (VmHWM), in bytes; 0 where /proc lacks it.
pub(crate) fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// One row of [`bench_histogram`].
#[derive(Clone, Debug)]
pub struct HistBenchRow {
    pub volume: String,
    pub clusters: usize,
    /// Two hemispheres per voxel (else one sphere).
    pub hemispheres: bool,
    pub histograms_s: f64,
    pub training_s: f64,
    pub assignment_s: f64,
    pub total_s: f64,
    pub peak_host_mb: f64,
    pub gpu_mb: f64,
    pub tf_change_ms: f64,
    pub clip_ms: f64,
    pub mean_error: f64,
    pub p99_error: f64,
}

/// Voxels (with q > 0.001) the clustered openness is compared with the direct sums on.
const ERROR_SAMPLE: usize = 4096;

/// The local-histogram AO at each of `clusters`: the precompute phase by phase (no cache), the
/// process's peak memory and the method's GPU memory, the TF change (one table update and one
/// pass), the mean CAO update per frame of the sphere sweep, and the clustered openness against
/// the direct sums (mean and p99 of |A - A_direct| over a sample of voxels with q > 0.001).
pub fn bench_histogram(
    on: BenchOn<'_>,
    tf_after: &TransferFunction,
    params: HistParams,
    clusters: &[usize],
    hemispheres: bool,
    base: &LaoParams,
    frames: usize,
) -> Result<Vec<HistBenchRow>> {
    let BenchOn { gpu, volumes, tf } = on;
    let lao = LaoGpu::new(gpu)?;
    let placement = Placement::default();
    println!(
        "Local-histogram AO on {} (r = {} mm, B = {} bins; no cache; s = wall seconds of each \
         phase; host MB = the process's peak RSS; GPU MB = the method's buffers and CAO's five \
         volumes; TF = wall ms of a {} -> {} change (table + one pass); clip = mean GPU ms of the \
         25 mm sphere sweep's CAO update over {frames} frames; error = |A - direct sum| over {} \
         voxels with q > 0.001; H = 1: one sphere, 2: two hemispheres, the error then against \
         the front's direct sums)",
        gpu.device_name, params.radius_mm, params.bins, tf.name, tf_after.name, ERROR_SAMPLE
    );
    println!(
        "{:<12} {:>5} {:>2} {:>8} {:>8} {:>8} {:>8} {:>8} {:>7} {:>8} {:>8} {:>8} {:>8}",
        "volume",
        "N",
        "H",
        "hist s",
        "train s",
        "assign s",
        "total s",
        "host MB",
        "GPU MB",
        "TF ms",
        "clip ms",
        "mean err",
        "p99 err"
    );
    let mut rows = Vec::new();
    for vol in volumes {
        let (q, shades, table) = histogram::direct_inputs(vol, tf, params.bins, &[]);
        let nb = histogram::Neighbourhood::new(params.radius_mm, vol.spacing);
        // The error sample: voxels with q > 0.001, spread deterministically.
        let candidates: Vec<usize> = (0..q.len()).filter(|&i| q[i] > 0.001).collect();
        let step = (candidates.len() / ERROR_SAMPLE).max(1);
        let sample: Vec<usize> = candidates.iter().step_by(step).copied().collect();
        let splits = if hemispheres {
            histogram::splits(vol)
        } else {
            Vec::new()
        };
        // The direct sums at the sample: the sphere's, and the front hemisphere's.
        let direct = |split: bool| -> Vec<f32> {
            sample
                .par_iter()
                .map(|&i| {
                    let s = if split { splits[i] } else { None };
                    histogram::direct_at(vol.dims, &q, &shades, &table, &nb, s, i).0
                })
                .collect()
        };
        let direct = [
            direct(false),
            if hemispheres {
                direct(true)
            } else {
                Vec::new()
            },
        ];
        let sweep = sweep_tools(vol, 25.0, frames);
        // With hemispheres, each N twice, one sphere then two hemispheres, side by side.
        let shapes: &[bool] = if hemispheres {
            &[false, true]
        } else {
            &[false]
        };
        for (n, split) in clusters
            .iter()
            .flat_map(|&n| shapes.iter().map(move |&h| (n, h)))
        {
            let p = HistParams {
                clusters: n,
                hemispheres: split,
                ..params
            };
            let t0 = std::time::Instant::now();
            let h = histogram_state(gpu, vol, p, None, false)?;
            let total_s = t0.elapsed().as_secs_f64();
            let timing = h.timing;
            let v = precompute_histogram(gpu, &lao, vol, tf, base, h)?;
            let a = read(&v.ao_buf, vol)?;
            let mut err: Vec<f64> = sample
                .iter()
                .zip(&direct[split as usize])
                .map(|(&i, d)| (a[i] as f64 - *d as f64).abs())
                .collect();
            let mean_error = err.iter().sum::<f64>() / err.len().max(1) as f64;
            err.sort_by(f64::total_cmp);
            let p99_error = err
                .get((err.len() * 99 / 100).min(err.len().saturating_sub(1)))
                .copied()
                .unwrap_or(0.0);
            let voxels = vol.voxel_count() as f64;
            let gpu_mb = (resident_bytes(&v) as f64 + 5.0 * 4.0 * voxels) / (1 << 20) as f64;
            let mut cao = v.into_cao(gpu, vol)?;
            let mut ms = 0.0;
            for tools in &sweep {
                ms += cao.run_frame(tools, &placement, Mode::Contextual)?.gpu_ms();
            }
            let clip_ms = ms / sweep.len().max(1) as f64;
            let t1 = std::time::Instant::now();
            let h = cao
                .histogram_mut()
                .expect("the method is the local histograms");
            drop(histogram_tables(gpu, &lao, vol.dims, h, (tf_after, &[]))?);
            let tf_change_ms = t1.elapsed().as_secs_f64() * 1e3;
            let row = HistBenchRow {
                volume: vol.name.clone(),
                clusters: n,
                hemispheres: split,
                histograms_s: timing.histograms_ms / 1e3,
                training_s: timing.training_ms / 1e3,
                assignment_s: timing.assignment_ms / 1e3,
                total_s,
                peak_host_mb: peak_rss_bytes() as f64 / (1 << 20) as f64,
                gpu_mb,
                tf_change_ms,
                clip_ms,
                mean_error,
                p99_error,
            };
            println!(
                "{:<12} {:>5} {:>2} {:>8.1} {:>8.1} {:>8.1} {:>8.1} {:>8.0} {:>7.0} {:>8.1} {:>8.1} {:>8.4} {:>8.4}",
                row.volume,
                row.clusters,
                1 + row.hemispheres as u8,
                row.histograms_s,
                row.training_s,
                row.assignment_s,
                row.total_s,
                row.peak_host_mb,
                row.gpu_mb,
                row.tf_change_ms,
                row.clip_ms,
                row.mean_error,
                row.p99_error
            );
            rows.push(row);
        }
        // LAO's TF change in the same run: its V_PAO' recomputed (the progressive switch
        // spreads exactly this work over frames).
        let t = std::time::Instant::now();
        drop(precompute(
            gpu,
            &lao,
            vol,
            tf_after,
            &AoConfig::from(*base),
            false,
        )?);
        println!(
            "{:<12} LAO K={}'s TF change (a full V_PAO' recompute, spread over frames by the \
             progressive switch) takes {:.1} ms in this run",
            vol.name,
            base.rays,
            t.elapsed().as_secs_f64() * 1e3
        );
    }
    Ok(rows)
}
