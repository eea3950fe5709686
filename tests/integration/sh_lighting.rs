//! SH environment lighting through the one frame loop, on lavapipe with validation on: turning
//! the light changes the picture with no visibility recomputed; a tool carving recomputes only
//! its SH boxes; a transfer-function switch recomputes the SH volume progressively (one slab per
//! frame, after V_PAO') and then holds exactly what a loop started with the new TF holds.

use crate::common;

use cao_xr::ao::sh::ShParams;
use cao_xr::ao::LaoParams;
use cao_xr::app::frame_loop::{FrameLoop, FrameOutput};
use cao_xr::app::lighting::{LightingMode, LightingOptions};
use cao_xr::clip::Shape;
use cao_xr::gpu::Gpu;
use cao_xr::input::{FrameInput, InteractionSettings};
use cao_xr::scene::{Tool, ToolMode};
use cao_xr::space::{default_stereo_views, Placement, Pose};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{phantom, Volume};
use glam::{Quat, Vec3};
use std::sync::Arc;

const PARAMS: LaoParams = LaoParams {
    rays: 6,
    steps: 4,
    step_mm: 4.0,
};

fn lighting() -> LightingOptions {
    LightingOptions {
        mode: LightingMode::Sh,
        environment: "studio".into(),
        sh: ShParams {
            coeffs: 16,
            directions: 24,
            patterns: 8,
            downsample: 2,
            length_mm: 40.0,
            ..Default::default()
        },
        yaw_deg: 0.0,
        shading: Default::default(),
    }
}

fn new_loop(gpu: &Gpu, vol: &Arc<Volume>, tfs: Vec<TransferFunction>) -> FrameLoop {
    let mut fl = FrameLoop::new(
        gpu,
        Arc::clone(vol),
        tfs,
        PARAMS,
        (48, 48),
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.set_lighting(&lighting(), false).unwrap();
    fl
}

fn sphere(active: bool) -> Tool {
    Tool {
        shape: Shape::Sphere,
        pose: Pose {
            position: Placement::default().center + Vec3::new(0.0, 0.02, 0.06),
            orientation: Quat::IDENTITY,
        },
        size: 0.04,
        mode: ToolMode::Carve,
        active,
    }
}

fn frame(
    fl: &mut FrameLoop,
    vol: &Volume,
    tool: Option<Tool>,
    menu: bool,
    i: usize,
) -> FrameOutput {
    let views = default_stereo_views(vol, &Placement::default(), 0.064);
    let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
    input.hands[0].buttons.menu = menu;
    fl.scene.tools = tool.into_iter().collect();
    fl.frame(&input).unwrap()
}

fn sh_words(fl: &FrameLoop) -> Vec<u32> {
    fl.lighting.as_ref().unwrap().volume.read_back().unwrap()
}

#[test]
fn turning_the_light_changes_the_image_but_no_visibility() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(24));
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let mut fl = new_loop(&gpu, &vol, vec![tf]);
    let a = frame(&mut fl, &vol, None, false, 0);
    let before = sh_words(&fl);
    assert_eq!(a.stats.sh.voxels, 0, "no tool, no SH update");
    fl.lighting.as_mut().unwrap().yaw = 120f32.to_radians();
    let b = frame(&mut fl, &vol, None, false, 1);
    assert_eq!(
        b.stats.sh.voxels, 0,
        "turning the light recomputes no visibility"
    );
    assert_eq!(sh_words(&fl), before);
    let changed = a.image.rgba[0]
        .iter()
        .zip(&b.image.rgba[0])
        .filter(|(x, y)| x != y)
        .count();
    assert!(
        changed > a.image.rgba[0].len() / 50,
        "the light turned but only {changed} pixel values changed"
    );
    // Back to where it was: the same picture, bit for bit.
    fl.lighting.as_mut().unwrap().yaw = 0.0;
    let c = frame(&mut fl, &vol, None, false, 2);
    assert!(c.image == a.image);
    // The sideways stick turns it too (any hand; a tenth of a second at full stick).
    let views = default_stereo_views(&vol, &Placement::default(), 0.064);
    let mut input = FrameInput::without_hands(3.0 / 60.0 + 0.1, views);
    input.hands[1].buttons.thumbstick.x = 1.0;
    let d = fl.frame(&input).unwrap();
    assert!(fl.scene.light_yaw > 0.1, "{}", fl.scene.light_yaw);
    assert_eq!(d.stats.sh.voxels, 0);
    assert!(d.image != c.image);
    assert_eq!(sh_words(&fl), before);
}

#[test]
fn a_carving_tool_recomputes_only_its_sh_boxes_and_opens_the_shadow() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(32));
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let mut fl = new_loop(&gpu, &vol, vec![tf]);
    let a = frame(&mut fl, &vol, None, false, 0);
    let pre = sh_words(&fl);
    let b = frame(&mut fl, &vol, Some(sphere(true)), false, 1);
    let count = fl.lighting.as_ref().unwrap().volume.grid.count() as u64;
    assert!(
        b.stats.sh.voxels > 0 && b.stats.sh.voxels < count,
        "{} of {count}",
        b.stats.sh.voxels
    );
    let carved = sh_words(&fl);
    assert_ne!(carved, pre, "the carve changed some visibility");
    assert!(a.image != b.image);
    // The tool put away: every voxel back to V_PSH.
    frame(&mut fl, &vol, Some(sphere(false)), false, 2);
    assert_eq!(sh_words(&fl), pre);
}

#[test]
fn tf_switch_recomputes_sh_progressively_then_equals_a_fresh_loop() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(24));
    let bone = TransferFunction::preset("ct-bone").unwrap();
    let skin = TransferFunction::preset("ct-skin").unwrap();
    let mut fl = new_loop(&gpu, &vol, vec![bone, skin.clone()]);
    // About four slices per slab, for both volumes.
    let sh_slice = {
        let v = &fl.lighting.as_ref().unwrap().volume;
        v.samples_per_slice()
    };
    fl.tf_samples_per_frame = sh_slice * 4.0;
    let first = frame(&mut fl, &vol, None, false, 0);
    assert!(first.stats.tf_progress.is_none());
    let old = sh_words(&fl);
    let mut fractions = Vec::new();
    let mut i = 1;
    loop {
        assert!(i < 400, "the switch never finished: {fractions:?}");
        let f = frame(&mut fl, &vol, None, i == 1, i);
        let Some(p) = f.stats.tf_progress else { break };
        // Until the switch-over the frames keep the old visibility.
        assert_eq!(sh_words(&fl), old, "frame {i}");
        fractions.push(p.fraction);
        i += 1;
    }
    assert_eq!(fl.shown_tf().name, "ct-skin");
    let sh_frames = fractions.iter().filter(|&&f| f > 0.5 && f < 1.0).count();
    assert!(
        sh_frames >= 2,
        "the SH volume took more than one slab: {fractions:?}"
    );
    assert!(fractions.windows(2).all(|w| w[0] <= w[1]), "{fractions:?}");

    let mut fresh = new_loop(&gpu, &vol, vec![skin]);
    frame(&mut fresh, &vol, None, false, 0);
    let new = sh_words(&fl);
    assert_ne!(new, old);
    assert_eq!(
        new,
        sh_words(&fresh),
        "progressive V_PSH' == a fresh precompute"
    );
    // Carving after the switch: the same clip-aware update as the fresh loop's.
    let a = frame(&mut fl, &vol, Some(sphere(true)), false, i);
    let b = frame(&mut fresh, &vol, Some(sphere(true)), false, i);
    assert_eq!(a.stats.sh.voxels, b.stats.sh.voxels);
    assert_eq!(sh_words(&fl), sh_words(&fresh));
    assert!(a.image == b.image);
}
