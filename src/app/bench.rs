//! `cao-xr bench lao`: LAO precompute time and throughput, medians of several runs.

use super::common::{precompute_ao, progress_bar, AppError, Result};
use crate::ao::cao::Cao;
use crate::ao::lao::LaoKernel;
use crate::ao::stored;
use crate::ao::{LaoGpu, LaoParams};
use crate::gpu::Gpu;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;

#[derive(Clone, Debug)]
pub struct LaoBenchRow {
    pub volume: String,
    pub dims: [usize; 3],
    pub rays: u32,
    pub steps: u32,
    pub runs: usize,
    /// Per kernel measured (in the order asked): median GPU ms, wall ms and opacity samples per
    /// second of GPU time (nominal: K*(M-1) per voxel).
    pub kernels: Vec<(LaoKernel, LaoBenchTime)>,
    /// With two kernels: the largest |A_second - A_first| over the volume.
    pub max_diff: Option<f32>,
}

#[derive(Clone, Copy, Debug)]
pub struct LaoBenchTime {
    pub gpu_ms: f64,
    pub wall_ms: f64,
    pub samples_per_s: f64,
}

/// What a bench table measures on: the GPU, the volumes (a row or more each) and the one
/// transfer function they are classified with (fixed, so that tables compare).
#[derive(Clone, Copy)]
pub struct BenchOn<'a> {
    pub gpu: &'a Gpu,
    pub volumes: &'a [Volume],
    pub tf: &'a TransferFunction,
}

pub fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Runs the full LAO precompute `runs` times per volume, K and kernel, the kernels interleaved
/// run by run (so that both see the same machine load); prints each row as it finishes. With
/// two kernels it prints their ratio of samples/s and their largest difference.
pub fn bench_lao(
    on: BenchOn<'_>,
    ks: &[u32],
    base: &LaoParams,
    runs: usize,
    kernels: &[LaoKernel],
) -> Result<Vec<LaoBenchRow>> {
    let BenchOn { gpu, volumes, tf } = on;
    use ash::vk;
    let runs = runs.max(1);
    let laos = kernels
        .iter()
        .map(|&k| {
            let mut l = LaoGpu::new(gpu)?;
            l.kernel = k;
            Ok(l)
        })
        .collect::<Result<Vec<_>>>()?;
    let name = |k: LaoKernel| match k {
        LaoKernel::Old => "old",
        LaoKernel::New => "new",
    };
    println!(
        "LAO precompute on {} ({runs} run(s) each, kernels interleaved, medians; Msamples/s: \
         K*(M-1) samples per voxel per second of GPU time)",
        gpu.device_name
    );
    let mut head = format!("{:<14} {:>13} {:>4} {:>4}", "volume", "dims", "K", "M");
    for &k in kernels {
        head += &format!(
            " {:>11} {:>14}",
            format!("{} ms", name(k)),
            format!("{} Msamples/s", name(k))
        );
    }
    if kernels.len() == 2 {
        head += &format!(" {:>8} {:>10}", "ratio", "max diff");
    }
    println!("{head}");
    let mut rows = Vec::new();
    for vol in volumes {
        crate::render::check_volume_fits_gpu(gpu, vol)?;
        let opacity = tf.opacity_volume(vol);
        let obuf = crate::ao::stored::upload(
            gpu,
            &opacity,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "opacity",
        )?;
        for &k in ks {
            let params = LaoParams { rays: k, ..*base };
            params.validate().map_err(AppError::Usage)?;
            let skip = laos[0].skip_buffers(&opacity, vol.dims, vol.spacing, &params)?;
            let mut times = vec![(Vec::new(), Vec::new()); laos.len()];
            let mut outs = vec![Vec::new(); laos.len()];
            let mut samples = 0;
            for _ in 0..runs {
                for (i, lao) in laos.iter().enumerate() {
                    let (out, t) =
                        lao.compute(&obuf, &skip, vol.dims, vol.spacing, &params, &mut |_, _| {})?;
                    times[i].0.push(t.gpu_ms);
                    times[i].1.push(t.wall_ms);
                    samples = t.samples;
                    outs[i] = stored::read(&out, vol.voxel_count())?;
                }
            }
            let kernel_times: Vec<(LaoKernel, LaoBenchTime)> = kernels
                .iter()
                .zip(&mut times)
                .map(|(&k, (g, w))| {
                    let gpu_ms = median(g);
                    let t = LaoBenchTime {
                        gpu_ms,
                        wall_ms: median(w),
                        samples_per_s: samples as f64 / (gpu_ms * 1e-3),
                    };
                    (k, t)
                })
                .collect();
            let max_diff = (outs.len() == 2).then(|| {
                outs[0]
                    .iter()
                    .zip(&outs[1])
                    .map(|(x, y)| (x - y).abs())
                    .fold(0.0f32, f32::max)
            });
            let row = LaoBenchRow {
                volume: vol.name.clone(),
                dims: vol.dims,
                rays: k,
                steps: params.steps,
                runs,
                kernels: kernel_times,
                max_diff,
            };
            let mut line = format!(
                "{:<14} {:>13} {:>4} {:>4}",
                row.volume,
                format!("{}x{}x{}", row.dims[0], row.dims[1], row.dims[2]),
                row.rays,
                row.steps
            );
            for (_, t) in &row.kernels {
                line += &format!(" {:>11.1} {:>14.1}", t.gpu_ms, t.samples_per_s * 1e-6);
            }
            if let (Some(d), [(_, a), (_, b)]) = (row.max_diff, row.kernels.as_slice()) {
                line += &format!(" {:>7.2}x {:>10.1e}", b.samples_per_s / a.samples_per_s, d);
            }
            println!("{line}");
            rows.push(row);
        }
    }
    Ok(rows)
}

#[derive(Clone, Debug)]
pub struct CaoBenchRow {
    pub volume: String,
    pub dims: [usize; 3],
    pub rays: u32,
    pub frames: usize,
    pub naive_frames: usize,
    pub naive_ms: f64,
    pub cao_ms: f64,
    pub percent_recomputed: f64,
}

/// A sphere tool of `radius_mm` sweeping left to right through the front half of the volume.
pub fn sweep_tools(vol: &Volume, radius_mm: f32, frames: usize) -> Vec<Vec<crate::scene::Tool>> {
    use crate::clip::Shape;
    use crate::scene::{Tool, ToolMode};
    use crate::space::{Placement, Pose};
    let p = Placement::default();
    let ext = vol.extent_mm();
    let half = (ext.max_element() * 0.5) as f32 * 1e-3;
    (0..frames)
        .map(|f| {
            let t = if frames > 1 {
                f as f32 / (frames - 1) as f32
            } else {
                0.5
            };
            let x = (-0.6 + 1.2 * t) * half;
            vec![Tool {
                shape: Shape::Sphere,
                pose: Pose {
                    position: p.center + glam::Vec3::new(x, 0.15 * half, 0.45 * half),
                    orientation: glam::Quat::IDENTITY,
                },
                size: radius_mm * 1e-3,
                mode: ToolMode::Carve,
                active: true,
            }]
        })
        .collect()
}

/// The frames of a sweep of `frames` on which the naive recompute is timed: `naive` of them (at
/// most all), spread evenly, each once.
pub fn naive_timed_frames(frames: usize, naive: usize) -> Vec<usize> {
    let n = naive.clamp(1, frames.max(1));
    (0..n).map(|j| (2 * j + 1) * frames / (2 * n)).collect()
}

/// Mean GPU ms per frame of CAO and of the naive full recompute over a sphere sweep, medians of
/// `runs` runs, both measured in the same run; then a probe of each of `probe_radii` (mm). With `verify`, every naive frame is compared with
/// the CAO frame bit for bit; the first difference is an error naming the frame and voxel.
pub fn bench_cao(
    on: BenchOn<'_>,
    ks: &[u32],
    base: &LaoParams,
    frames: usize,
    runs: usize,
    verify: bool,
    probe_radii: &[f32],
) -> Result<Vec<CaoBenchRow>> {
    let BenchOn { gpu, volumes, tf } = on;
    use crate::ao::cao::Mode;
    let lao = LaoGpu::new(gpu)?;
    let placement = crate::space::Placement::default();
    println!(
        "CAO vs naive LAO per frame on {} (sphere of 25 mm radius sweeping; GPU ms, mean over the \
         frames, median of {runs} run(s))",
        gpu.device_name
    );
    println!(
        "{:<14} {:>13} {:>4} {:>7} {:>12} {:>10} {:>8} {:>12}",
        "volume", "dims", "K", "frames", "naive ms", "CAO ms", "speedup", "% recomputed"
    );
    let mut rows = Vec::new();
    for vol in volumes {
        // A naive frame of a large volume takes a minute on a CPU device: time fewer of them.
        let large = gpu.is_cpu() && vol.voxel_count() > 2_000_000;
        let naive_frames = if large { frames.min(2) } else { frames };
        for &k in ks {
            let params = LaoParams { rays: k, ..*base };
            let ao = precompute_ao(gpu, &lao, vol, tf, &params, false)?;
            let mut naive = ao.duplicate()?.into_cao(gpu, vol)?;
            let mut cao = ao.into_cao(gpu, vol)?;
            let sweep = sweep_tools(vol, 25.0, frames);
            let timed = naive_timed_frames(frames, naive_frames);
            let (mut c_runs, mut n_runs, mut pct) = (Vec::new(), Vec::new(), 0.0);
            for _ in 0..runs.max(1) {
                let (mut c_ms, mut n_ms) = (0.0, 0.0);
                for (f, tools) in sweep.iter().enumerate() {
                    let m = cao.run_frame(tools, &placement, Mode::Contextual)?;
                    c_ms += m.gpu_ms();
                    pct += m.percent_recomputed();
                    // Naive frames spread evenly over the sweep when only a few are timed (each
                    // is a full recompute, independent of the frames before it).
                    if timed.contains(&f) {
                        n_ms += naive.run_frame(tools, &placement, Mode::Naive)?.gpu_ms();
                        if verify {
                            verify_frame(&cao, &naive, vol, &format!("K={k} frame {f}"))?;
                        }
                    }
                }
                c_runs.push(c_ms / frames as f64);
                n_runs.push(n_ms / timed.len() as f64);
            }
            let row = CaoBenchRow {
                volume: vol.name.clone(),
                dims: vol.dims,
                rays: k,
                frames,
                naive_frames: timed.len(),
                naive_ms: median(&mut n_runs),
                cao_ms: median(&mut c_runs),
                percent_recomputed: pct / (frames * runs.max(1)) as f64,
            };
            println!(
                "{:<14} {:>13} {:>4} {:>7} {:>12.1} {:>10.1} {:>7.1}x {:>12.2}",
                row.volume,
                format!("{}x{}x{}", row.dims[0], row.dims[1], row.dims[2]),
                row.rays,
                if timed.len() < frames {
                    format!("{frames}/{}", timed.len())
                } else {
                    frames.to_string()
                },
                row.naive_ms,
                row.cao_ms,
                row.naive_ms / row.cao_ms,
                row.percent_recomputed
            );
            rows.push(row);
        }
    }
    if rows.iter().any(|r| r.naive_frames < r.frames) {
        println!("(frames a/b: CAO timed on a frames, naive LAO on b of them, on this CPU device)");
    }
    if !probe_radii.is_empty() {
        bench_probes(on, ks, base, frames, runs, verify, probe_radii)?;
    }
    if verify {
        println!("verify: every naive frame equals the CAO frame bit for bit");
    }
    Ok(rows)
}

/// The first difference between the CAO and the naive V_AO, as an error naming the frame and
/// voxel.
fn verify_frame(cao: &Cao, naive: &Cao, vol: &Volume, what: &str) -> Result<()> {
    let (a, b) = (cao.ao.read()?, naive.ao.read()?);
    match a
        .iter()
        .zip(&b)
        .position(|(x, y)| x.to_bits() != y.to_bits())
    {
        None => Ok(()),
        Some(v) => Err(AppError::Usage(format!(
            "verify: {} {what}: voxel {v} ({}, {}, {}) has CAO {} but naive LAO {}",
            vol.name,
            v % vol.dims[0],
            (v / vol.dims[0]) % vol.dims[1],
            v / (vol.dims[0] * vol.dims[1]),
            a[v],
            b[v]
        ))),
    }
}

/// A probe (only its inside kept) of each radius sweeping like the carve tool: GPU ms per frame
/// (mean over the frames, median of `runs`), the share of voxels recomputed, and the share
/// inside the probe, which is what a probe recomputed every frame before it had a contraction.
fn bench_probes(
    on: BenchOn<'_>,
    ks: &[u32],
    base: &LaoParams,
    frames: usize,
    runs: usize,
    verify: bool,
    radii: &[f32],
) -> Result<()> {
    let BenchOn { gpu, volumes, tf } = on;
    use crate::ao::cao::Mode;
    use crate::scene::ToolMode;
    let lao = LaoGpu::new(gpu)?;
    let placement = crate::space::Placement::default();
    println!();
    println!(
        "CAO per frame with a probe sphere sweeping (GPU ms, mean over {frames} frames, median of \
         {runs} run(s); % inside: what a probe recomputed before its contraction)"
    );
    println!(
        "{:<14} {:>13} {:>4} {:>10} {:>10} {:>10} {:>10} {:>12} {:>9}",
        "volume",
        "dims",
        "K",
        "radius mm",
        "CAO ms",
        "clip ms",
        "update ms",
        "% recomputed",
        "% inside"
    );
    for vol in volumes {
        for &k in ks {
            let params = LaoParams { rays: k, ..*base };
            let ao = precompute_ao(gpu, &lao, vol, tf, &params, false)?;
            let mut naive = if verify {
                Some(ao.duplicate()?.into_cao(gpu, vol)?)
            } else {
                None
            };
            let mut cao = ao.into_cao(gpu, vol)?;
            let total = vol.voxel_count() as f64;
            for &r in radii {
                let mut sweep = sweep_tools(vol, r, frames);
                for t in sweep.iter_mut().flatten() {
                    t.mode = ToolMode::Probe;
                }
                let (mut ms, mut clip, mut update) = (Vec::new(), Vec::new(), Vec::new());
                let (mut pct, mut inside) = (0.0, 0.0);
                for _ in 0..runs.max(1) {
                    let (mut m_ms, mut c_ms, mut u_ms) = (0.0, 0.0, 0.0);
                    for (f, tools) in sweep.iter().enumerate() {
                        let m = cao.run_frame(tools, &placement, Mode::Contextual)?;
                        m_ms += m.gpu_ms();
                        c_ms += m.clip_ms;
                        u_ms += m.update_ms;
                        pct += m.percent_recomputed();
                        inside += 100.0 * (total - m.clipped as f64) / total;
                        if let Some(n) = naive.as_mut() {
                            n.run_frame(tools, &placement, Mode::Naive)?;
                            verify_frame(&cao, n, vol, &format!("K={k} probe {r} mm frame {f}"))?;
                        }
                    }
                    ms.push(m_ms / frames as f64);
                    clip.push(c_ms / frames as f64);
                    update.push(u_ms / frames as f64);
                }
                let n = (frames * runs.max(1)) as f64;
                println!(
                    "{:<14} {:>13} {:>4} {:>10.0} {:>10.1} {:>10.1} {:>10.1} {:>12.2} {:>9.2}",
                    vol.name,
                    format!("{}x{}x{}", vol.dims[0], vol.dims[1], vol.dims[2]),
                    k,
                    r,
                    median(&mut ms),
                    median(&mut clip),
                    median(&mut update),
                    pct / n,
                    inside / n
                );
            }
        }
    }
    Ok(())
}

#[derive(Clone, Debug)]
pub struct ShBenchRow {
    pub volume: String,
    pub downsample: u32,
    pub sh_dims: [usize; 3],
    pub coeffs: u32,
    pub directions: u32,
    /// Precompute (pyramid + SH volume) GPU ms with the hierarchy, and with the full-resolution
    /// march, medians.
    pub hierarchy_ms: f64,
    pub flat_ms: f64,
    /// Mean absolute difference of the hierarchical coefficients from the full-resolution
    /// march's (same patterns), in units of Y_0 (the coefficient of full visibility).
    pub mean_abs_diff: f64,
}

/// SH visibility precompute time at each downsampling, coefficient count and direction count,
/// with the hierarchy on and off (both in the same run), and the error of the hierarchy.
pub fn bench_sh(
    on: BenchOn<'_>,
    downsample: &[u32],
    coeffs: &[u32],
    directions: &[u32],
    base: &crate::ao::sh::ShParams,
    runs: usize,
) -> Result<Vec<ShBenchRow>> {
    let BenchOn { gpu, volumes, tf } = on;
    use crate::ao::sh::{packed_coeff, ShVolume, Y0};
    use ash::vk;
    println!(
        "SH visibility precompute on {} (ray length {} mm, {} steps per level; GPU ms, median of \
         {runs} run(s); error = mean |hierarchical - full march| / Y_0)",
        gpu.device_name, base.length_mm, base.steps_per_level
    );
    println!(
        "{:<14} {:>5} {:>11} {:>6} {:>5} {:>12} {:>12} {:>8} {:>9}",
        "volume", "rate", "SH dims", "coeffs", "N", "hierarchy ms", "full ms", "speedup", "error"
    );
    let mut rows = Vec::new();
    for vol in volumes {
        let opacity = tf.opacity_volume(vol);
        let obuf = crate::ao::stored::upload(
            gpu,
            &opacity,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "opacity",
        )?;
        for &ds in downsample {
            for &c in coeffs {
                for &n in directions {
                    let run = |hierarchy: bool| -> Result<(f64, Vec<u32>, [usize; 3])> {
                        let p = crate::ao::sh::ShParams {
                            coeffs: c,
                            directions: n,
                            downsample: ds,
                            hierarchy,
                            ..*base
                        };
                        let mut ms = Vec::new();
                        let mut packed = Vec::new();
                        let mut dims = [0; 3];
                        for _ in 0..runs.max(1) {
                            let mut shv = ShVolume::new(gpu, vol, p)?;
                            // a run can take minutes on lavapipe: show it, then clear it
                            let label = if hierarchy { "hierarchy" } else { "full march" };
                            let bar = progress_bar(shv.grid.dims[2] as u64, label);
                            let t = shv.precompute(
                                (&obuf, crate::ao::lao::LaoLayout::unpadded_stride(vol.dims)),
                                &mut |done, _| bar.set_position(done as u64),
                            );
                            bar.finish_and_clear();
                            ms.push(t?.gpu_ms);
                            packed = shv.read_back()?;
                            dims = shv.grid.dims;
                        }
                        Ok((median(&mut ms), packed, dims))
                    };
                    let (h_ms, h, dims) = run(true)?;
                    let (f_ms, f, _) = run(false)?;
                    let count: usize = dims.iter().product();
                    let mut sum = 0.0;
                    for i in 0..count {
                        for k in 0..c as usize {
                            sum += (packed_coeff(&h, count, i, k) - packed_coeff(&f, count, i, k))
                                .abs();
                        }
                    }
                    let row = ShBenchRow {
                        volume: vol.name.clone(),
                        downsample: ds,
                        sh_dims: dims,
                        coeffs: c,
                        directions: n,
                        hierarchy_ms: h_ms,
                        flat_ms: f_ms,
                        mean_abs_diff: sum / (count * c as usize) as f64 / Y0,
                    };
                    println!(
                        "{:<14} {:>5} {:>11} {:>6} {:>5} {:>12.1} {:>12.1} {:>7.1}x {:>9.4}",
                        row.volume,
                        format!("1:{ds}"),
                        format!("{}x{}x{}", dims[0], dims[1], dims[2]),
                        c,
                        n,
                        row.hierarchy_ms,
                        row.flat_ms,
                        row.flat_ms / row.hierarchy_ms,
                        row.mean_abs_diff
                    );
                    rows.push(row);
                }
            }
        }
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_naive_recompute_is_timed_on_as_many_distinct_frames_as_it_is_divided_by() {
        for frames in 1..40 {
            for naive in 1..=frames + 2 {
                let t = naive_timed_frames(frames, naive);
                assert_eq!(t.len(), naive.min(frames), "{frames} frames, {naive} naive");
                assert!(t.windows(2).all(|w| w[0] < w[1]), "{frames}/{naive}: {t:?}");
                assert!(t.iter().all(|&f| f < frames), "{frames}/{naive}: {t:?}");
            }
        }
        // The case that timed one frame and divided by two.
        assert_eq!(naive_timed_frames(3, 2), vec![0, 2]);
    }
}
