//! The shortest way into cao-xr: the phantom head, carved by a sphere that sweeps across its
//! face through the one frame loop, CAO-lit, written as PNGs.
//!
//! ```text
//! VK_DRIVER_FILES=/usr/share/vulkan/icd.d/lvp_icd.x86_64.json cargo run --example carve
//! ```
//!
//! Each frame: the scene's tools move, `FrameLoop::frame` runs the clip + mask pass, the AO
//! update where the cut changed it (CAO: bit for bit a full LAO pass), and both eyes' ray cast,
//! and reads the pictures back. Swap `FrameLoop` input for a recorded pose stream and you have
//! `cao-xr replay`; for OpenXR poses and you have the headset.

use cao_xr::ao::{AoConfig, AoMethod, LaoParams};
use cao_xr::app::frame_loop::FrameLoop;
use cao_xr::clip::Shape;
use cao_xr::gpu::{Gpu, GpuOptions};
use cao_xr::input::{FrameInput, InteractionSettings};
use cao_xr::scene::{Tool, ToolMode};
use cao_xr::space::{default_stereo_views, Placement, Pose, DEFAULT_IPD};
use cao_xr::volume::phantom;
use cao_xr::volume::transfer::TransferFunction;
use glam::{Quat, Vec3};
use std::path::Path;
use std::sync::Arc;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Vulkan: lavapipe or a GPU, whatever VK_DRIVER_FILES (or the system) offers.
    let gpu = Gpu::new(&GpuOptions::default())?;
    println!("GPU: {}", gpu.device_name);

    // A 64^3 procedural CT head in Hounsfield units, and a transfer function for skin.
    let volume = Arc::new(phantom::head(64));
    let tf = TransferFunction::preset("ct-skin").ok_or("no ct-skin preset")?;

    // LAO with 14 rays of 8 steps of 2 mm: precomputed once here, then kept exact per frame.
    let lao = LaoParams {
        rays: 14,
        steps: 8,
        step_mm: 2.0,
    };
    let ao = AoConfig::new(AoMethod::Lao, lao);
    let mut frames = FrameLoop::new(
        &gpu,
        Arc::clone(&volume),
        vec![tf],
        ao,
        (256, 256),
        InteractionSettings::default(),
        true,
    )?;

    // Where the volume stands in the world (metres), and two eyes looking at it.
    let placement = Placement::default();
    let views = default_stereo_views(&volume, &placement, DEFAULT_IPD);
    let out = Path::new("out/example-carve");
    // The cut itself, without the tool drawn over it.
    frames.show_overlay = false;

    // A 35 mm sphere sweeping left to right through the face (the face looks towards +Z).
    for i in 0..5 {
        let x = -0.04 + 0.02 * i as f32;
        frames.scene.tools = vec![Tool {
            shape: Shape::Sphere,
            pose: Pose {
                position: placement.center + Vec3::new(x, 0.02, 0.07),
                orientation: Quat::IDENTITY,
            },
            size: 0.035,
            mode: ToolMode::Carve,
            active: true,
        }];
        let frame = frames.frame(&FrameInput::without_hands(i as f64 / 90.0, views))?;
        let m = &frame.stats.metrics;
        println!(
            "frame {i}: {} voxels clipped, {} recomputed ({:.2} %), AO update {:.1} ms, \
             ray cast {:.1} ms",
            m.clipped,
            m.recomputed,
            m.percent_recomputed(),
            m.gpu_ms(),
            frame.stats.render_ms
        );
        let dir = out.join(format!("frame-{i}"));
        frame.image.over([0.06, 0.07, 0.09]).write_pngs(&dir)?;
    }
    println!(
        "wrote {}/frame-*/left.png, right.png, stereo.png",
        out.display()
    );
    Ok(())
}
