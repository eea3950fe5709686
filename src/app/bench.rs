//! `cao-xr bench lao`: LAO precompute time and throughput, medians of several runs.

use super::{precompute_ao, Result};
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
    pub gpu_ms: f64,
    pub wall_ms: f64,
    /// Opacity samples per second of GPU time (K*(M-1) per voxel).
    pub samples_per_s: f64,
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

/// Runs the full LAO precompute `runs` times per volume and K; prints each row as it finishes.
pub fn bench_lao(
    gpu: &Gpu,
    volumes: &[Volume],
    tf: &TransferFunction,
    ks: &[u32],
    base: &LaoParams,
    runs: usize,
) -> Result<Vec<LaoBenchRow>> {
    let lao = LaoGpu::new(gpu)?;
    println!(
        "LAO precompute on {} ({} run(s) each, medians)",
        gpu.device_name, runs
    );
    println!(
        "{:<14} {:>13} {:>4} {:>4} {:>11} {:>11} {:>14}",
        "volume", "dims", "K", "M", "gpu ms", "wall ms", "Msamples/s"
    );
    let mut rows = Vec::new();
    for vol in volumes {
        for &k in ks {
            let params = LaoParams { rays: k, ..*base };
            let (mut g, mut w) = (Vec::new(), Vec::new());
            let mut samples = 0;
            for _ in 0..runs.max(1) {
                let r = precompute_ao(gpu, &lao, vol, tf, &params, false)?;
                g.push(r.timing.gpu_ms);
                w.push(r.timing.wall_ms);
                samples = r.timing.samples;
            }
            let gpu_ms = median(&mut g);
            let row = LaoBenchRow {
                volume: vol.name.clone(),
                dims: vol.dims,
                rays: k,
                steps: params.steps,
                runs: runs.max(1),
                gpu_ms,
                wall_ms: median(&mut w),
                samples_per_s: samples as f64 / (gpu_ms * 1e-3),
            };
            println!(
                "{:<14} {:>13} {:>4} {:>4} {:>11.1} {:>11.1} {:>14.1}",
                row.volume,
                format!("{}x{}x{}", row.dims[0], row.dims[1], row.dims[2]),
                row.rays,
                row.steps,
                row.gpu_ms,
                row.wall_ms,
                row.samples_per_s * 1e-6
            );
            rows.push(row);
        }
    }
    Ok(rows)
}
