//! What the subcommands do, as library calls: open a volume, precompute AO, render both eyes,
//! write the results. The CLI in main.rs only parses arguments and calls these. app/'s imports
//! run one way: common.rs is what every file here builds on and imports none of them; the
//! frame loop and the front ends (frame_loop, session, desktop, headset, replay, the benches)
//! import it and each other without cycles; this file, the roof, holds what runs them (`render`,
//! `start`) and re-exports common's names as `app::*`.

pub mod bench;
pub mod bench_ao;
pub mod bench_frame;
pub mod bench_quality;
pub mod bench_scale;
pub mod budget;
pub mod common;
pub mod desktop;
pub mod frame_loop;
pub mod headset;
pub mod inset;
pub mod interrupt;
pub mod lighting;
pub mod mirror;
pub mod replay;
pub mod session;
pub mod tf_switch;

pub use common::*;

use crate::ao::cao::FrameMetrics;
use crate::gpu::Gpu;
use crate::input::{FrameInput, InteractionSettings};
use crate::render::RenderSettings;
use crate::scene::Tool;
use crate::space::{default_stereo_views, Placement, DEFAULT_IPD};
use frame_loop::FrameLoop;
use session::SessionSpec;
use std::path::Path;
use std::sync::Arc;

/// `cao-xr render`: one frame of the frame loop (V_PAO, the tools' CAO update, both eyes from
/// the default pair of eye poses, no overlay), written as PNGs in `out`. Returns the CAO metrics
/// when tools were given.
pub fn render_to_dir(
    gpu: &Gpu,
    spec: &SessionSpec,
    tools: &[Tool],
    size: (u32, u32),
    settings: &RenderSettings,
    out: &Path,
) -> Result<Option<FrameMetrics>> {
    let vol = &spec.volume;
    let built = frame_loop::Built {
        config: spec.ao,
        size,
        interaction: InteractionSettings::default(),
        fast_start_after_s: None,
    };
    let lighting = Some(&spec.lighting);
    let tfs = vec![spec.tf.clone()];
    let mut fl = FrameLoop::new_lit(gpu, Arc::clone(vol), tfs, built, lighting, true)?;
    fl.settings = RenderSettings {
        bleeding: spec.ao.bleeding,
        ..*settings
    };
    // Premultiplied over black on the GPU; an opaque background is composited on the host from
    // the same 8-bit colour and alpha, so the transparent PNG of a frame composited over a
    // background equals the opaque one within 1/255.
    fl.settings.background = [0.0; 3];
    // the lighting's shading on these settings (new_lit applied it to the defaults)
    spec.lighting.apply(&mut fl.settings);
    fl.set_variance(spec.variance)?;
    fl.show_overlay = false;
    fl.markups = spec.markups.clone();
    fl.scene.tools = tools.to_vec();
    // Framed on the volume shown (downsampled where the full one did not fit).
    let views = default_stereo_views(fl.volume(), &fl.scene.volume, DEFAULT_IPD);
    let frame = fl.frame(&FrameInput::without_hands(0.0, views))?;
    // What the frame loop holds once set up (the peak, printed by the caller, may be a
    // precompute's), per voxel of the volume as given, as the peak is told.
    let shown = fl.volume();
    let as_shown = if shown.dims == spec.volume.dims {
        String::new()
    } else {
        let [x, y, z] = shown.dims;
        let levels: Vec<String> = fl.insets().iter().map(|i| i.summary()).collect();
        let inset = match levels.is_empty() {
            true => String::new(),
            false => format!(", with {}", levels.join(" and ")),
        };
        format!(" (shown downsampled to {x} x {y} x {z}{inset})")
    };
    println!(
        "GPU memory held after the frame: {:.1} bytes per voxel{as_shown}",
        gpu.memory_in_use() as f64 / spec.volume.voxel_count().max(1) as f64
    );
    if let Some(w) = fl.margin_warning(&frame.stats.margins) {
        println!("{w}");
    }
    if !spec.markups.lines.is_empty() {
        println!("rulers: {}", spec.markups.lengths());
    }
    if settings.transparent {
        frame.image.write_pngs_rgba(out)?;
    } else {
        frame.image.over(settings.background).write_pngs(out)?;
    }
    Ok((!tools.is_empty()).then_some(frame.stats.metrics))
}

/// `cao-xr start`: a headset session when an OpenXR runtime answers, else the desktop window
/// when there is a display, else a headless render of the volume carved by a 40 mm sphere to
/// out/render. Says on stderr which and why; returns the closing line.
pub fn start(spec: &SessionSpec, validation: bool) -> Result<String> {
    if crate::xr::available() {
        eprintln!("start: an OpenXR runtime answered: starting the headset session");
        let opts = crate::xr::XrOptions {
            validation,
            frame_budget_ms: Some(budget::HEADSET_FRAME_MS),
            ..Default::default()
        };
        let s = headset::run(spec, opts)?;
        Ok(format!(
            "headset session ended cleanly after {} frames",
            s.frames
        ))
    } else if std::env::var_os("DISPLAY").is_some() {
        eprintln!("start: no OpenXR runtime answered; DISPLAY is set: opening the desktop window");
        let opts = desktop::ViewOptions {
            size: (480, 480),
            validation,
            ..Default::default()
        };
        let n = desktop::run(spec, opts)?;
        Ok(format!("closed after {n} frames"))
    } else {
        eprintln!(
            "start: no OpenXR runtime and no display: rendering headless to out/render \
             (a 40 mm sphere carving the front; cao-xr replay plays pose streams)"
        );
        let gpu = session::start_gpu(validation, false)?;
        let tools = [parse_tool("sphere:40:0,40,80", &Placement::default())?];
        let out = Path::new("out/render");
        render_to_dir(
            &gpu,
            spec,
            &tools,
            (640, 640),
            &RenderSettings::default(),
            out,
        )?;
        Ok(format!(
            "wrote {0}/left.png {0}/right.png {0}/stereo.png",
            out.display()
        ))
    }
}
