//! `cao-xr bench quality`: how far the ray caster's pictures are from the reference render
//! (1/16 of the default step, point samples, no jitter) and what they cost, for step multiples
//! 1, 2 and 4 with and without pre-integration, on two views of each volume.

use super::bench::median;
use super::common::Result;
use super::frame_loop::FrameLoop;
use crate::ao::LaoParams;
use crate::gpu::Gpu;
use crate::input::{FrameInput, InteractionSettings};
use crate::render::compare::{luma, psnr, ssim};
use crate::render::{RenderSettings, StereoImage};
use crate::space::{default_stereo_views, Placement, DEFAULT_IPD};
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use glam::Quat;
use std::sync::Arc;

/// The two views: from the front, and turned 90 degrees about the vertical and tilted.
pub fn views() -> [(&'static str, Placement); 2] {
    let turned = Quat::from_rotation_y(std::f32::consts::FRAC_PI_2) * Quat::from_rotation_x(0.4);
    [
        ("front", Placement::default()),
        (
            "side",
            Placement {
                rotation: turned,
                ..Placement::default()
            },
        ),
    ]
}

#[derive(Clone, Debug)]
pub struct QualityRow {
    pub volume: String,
    pub view: &'static str,
    pub step_mm: f32,
    pub multiple: f32,
    pub preintegrated: bool,
    pub psnr_db: f64,
    pub ssim: f64,
    /// GPU time of both eyes' ray cast (median of the runs).
    pub render_ms: f64,
}

/// One frame of `fl` with `settings` and the volume at `placement`; its picture and GPU ms.
fn render(
    fl: &mut FrameLoop,
    vol: &Volume,
    settings: RenderSettings,
    placement: Placement,
) -> Result<(StereoImage, f64)> {
    fl.settings = settings;
    fl.scene.volume = placement;
    let views = default_stereo_views(vol, &placement, DEFAULT_IPD);
    let out = fl.frame(&FrameInput::without_hands(0.0, views))?;
    Ok((out.image, out.stats.render_ms))
}

/// The table for each volume, `size` pixels per eye; each row's time is the median of `runs`.
pub fn bench_quality(
    gpu: &Gpu,
    volumes: &[Volume],
    tf: &TransferFunction,
    lao: LaoParams,
    size: u32,
    runs: usize,
) -> Result<Vec<QualityRow>> {
    println!(
        "{:<14} {:<6} {:>8} {:>5} {:>8} {:>8} {:>7} {:>10}",
        "volume", "view", "step mm", "x", "pre-int", "PSNR dB", "SSIM", "render ms"
    );
    let mut rows = Vec::new();
    for vol in volumes {
        let arc = Arc::new(vol.clone());
        let mut fl = FrameLoop::new(
            gpu,
            Arc::clone(&arc),
            vec![tf.clone()],
            lao,
            (size, size),
            InteractionSettings::default(),
            true,
        )?;
        fl.show_overlay = false;
        let default = RenderSettings::default();
        let step = default.step_for(vol.spacing);
        for (view, placement) in views() {
            let (reference, ref_ms) =
                render(&mut fl, vol, default.reference(vol.spacing), placement)?;
            let want = luma(&reference.rgba[0]);
            println!(
                "{:<14} {:<6} {:>8.3} {:>5} {:>8} {:>8} {:>7} {:>10.1}",
                vol.name,
                view,
                step / crate::render::REFERENCE_REFINEMENT,
                "1/16",
                "ref",
                "-",
                "-",
                ref_ms
            );
            for multiple in [1.0f32, 2.0, 4.0] {
                for preintegrated in [true, false] {
                    let settings = RenderSettings {
                        step_mm: step * multiple,
                        preintegrated,
                        ..default
                    };
                    let mut times = Vec::new();
                    let mut picture = None;
                    for _ in 0..runs.max(1) {
                        let (img, ms) = render(&mut fl, vol, settings, placement)?;
                        times.push(ms);
                        picture = Some(img);
                    }
                    let got = luma(&picture.expect("one run at least").rgba[0]);
                    let row = QualityRow {
                        volume: vol.name.clone(),
                        view,
                        step_mm: step * multiple,
                        multiple,
                        preintegrated,
                        psnr_db: psnr(&want, &got),
                        ssim: ssim(&want, &got, size as usize, size as usize),
                        render_ms: median(&mut times),
                    };
                    println!(
                        "{:<14} {:<6} {:>8.3} {:>5} {:>8} {:>8.2} {:>7.4} {:>10.1}",
                        row.volume,
                        row.view,
                        row.step_mm,
                        format!("{multiple}x"),
                        if preintegrated { "on" } else { "off" },
                        row.psnr_db,
                        row.ssim,
                        row.render_ms
                    );
                    rows.push(row);
                }
            }
        }
    }
    Ok(rows)
}
