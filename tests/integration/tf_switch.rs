//! Run-time transfer-function switch through the one frame loop, on lavapipe with validation on:
//! the menu button starts a progressive V_PAO recompute (one slab per frame), frames keep the old
//! TF and AO until the last slab, then switch over to exactly what a loop started with the new TF
//! shows, tools carving.

use crate::common;

use cao_xr::ao::cao::Mode;
use cao_xr::ao::filtered::{Estimator, FilterParams};
use cao_xr::ao::histogram::HistParams;
use cao_xr::ao::{AoConfig, AoMethod, LaoGpu, LaoParams};
use cao_xr::app::frame_loop::{precompute_seconds, Built, FrameLoop, FrameOutput};
use cao_xr::clip::Shape;
use cao_xr::gpu::Gpu;
use cao_xr::input::{FrameInput, InteractionSettings};
use cao_xr::scene::{Tool, ToolMode};
use cao_xr::space::{default_stereo_views, Placement, Pose};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{phantom, Volume};
use glam::{Quat, Vec3};
use std::sync::Arc;

const N: usize = 32;
const PARAMS: LaoParams = LaoParams {
    rays: 6,
    steps: 6,
    step_mm: 4.0,
};
/// Slices per slab the budget below buys.
const SLAB: usize = 4;

use crate::cao::read_ao;

/// A third TF for the restart: ct-skin with denser soft tissue.
fn soft() -> TransferFunction {
    let mut tf = TransferFunction::preset("ct-skin").unwrap();
    tf.name = "ct-soft".into();
    for p in &mut tf.points {
        if p.alpha > 0.0 && p.alpha < 0.1 {
            p.alpha = 0.3;
        }
    }
    tf.validate().unwrap();
    tf
}

fn new_loop(gpu: &Gpu, vol: &Arc<Volume>, tfs: Vec<TransferFunction>, mode: Mode) -> FrameLoop {
    new_loop_with(gpu, vol, tfs, mode, PARAMS.into())
}

fn new_loop_with(
    gpu: &Gpu,
    vol: &Arc<Volume>,
    tfs: Vec<TransferFunction>,
    mode: Mode,
    ao: AoConfig,
) -> FrameLoop {
    let mut fl = FrameLoop::new(
        gpu,
        Arc::clone(vol),
        tfs,
        ao,
        (48, 48),
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.mode = mode;
    fl.tf_samples_per_frame = LaoGpu::samples_per_slice(vol.dims, &PARAMS) * SLAB as f64;
    fl
}

/// Frame `i`'s tool: a carving sphere sweeping across the front of the head (inactive on
/// frames where `carve` says so).
fn tool(c: Vec3, i: usize, carve: bool) -> Tool {
    Tool {
        shape: Shape::Sphere,
        pose: Pose {
            position: c + Vec3::new(-0.05 + 0.01 * (i % 10) as f32, 0.03, 0.07),
            orientation: Quat::IDENTITY,
        },
        size: 0.035,
        mode: ToolMode::Carve,
        active: carve,
    }
}

/// One frame with the given tool and the menu button (left hand, untracked: buttons still act,
/// the tool stays where the scene put it).
fn frame(fl: &mut FrameLoop, vol: &Volume, tool: Tool, menu: bool, i: usize) -> FrameOutput {
    let views = default_stereo_views(vol, &Placement::default(), 0.064);
    let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
    input.hands[0].buttons.menu = menu;
    fl.scene.tools = vec![tool];
    fl.frame(&input).unwrap()
}

/// [`frame`] with the stick click instead of the menu button, and both eyes at one place when
/// `one_eye_pose`.
fn click_frame(
    fl: &mut FrameLoop,
    vol: &Volume,
    tool: Tool,
    click: bool,
    i: usize,
    one_eye_pose: bool,
) -> FrameOutput {
    let ipd = if one_eye_pose { 0.0 } else { 0.064 };
    let views = default_stereo_views(vol, &Placement::default(), ipd);
    let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
    input.hands[1].buttons.stick_click = click;
    fl.scene.tools = vec![tool];
    fl.frame(&input).unwrap()
}

fn filter(estimator: Estimator) -> AoMethod {
    AoMethod::Filter(FilterParams {
        radius_mm: 12.0,
        estimator,
        ..Default::default()
    })
}

#[test]
fn the_stick_click_switches_the_ao_method_to_exactly_a_fresh_start_of_it() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    let start = AoConfig::new(filter(Estimator::Penner), PARAMS);
    let names: Vec<String> = start.cycle().iter().map(|m| m.name()).collect();
    assert_eq!(
        names,
        ["filter-penner", "lao", "filter-cdf", "filter-gauss"]
    );
    let mut fl = new_loop_with(&gpu, &vol, tfs.clone(), Mode::Contextual, start);
    assert_eq!(fl.interaction.settings().ao_methods, 4);
    let c = Placement::default().center;
    let mut i = 0;
    // Penner -> LAO (progressive, a slab of slices per frame), then LAO -> cdf (one refilter).
    for (want, progressive) in [("lao", true), ("filter-cdf", false)] {
        let before = read_ao(&fl.cao.ao);
        let shown = fl.cao.method_name();
        let mut switching = 0;
        let (done, t) = loop {
            assert!(i < 100, "the switch to {want} never finished");
            let t = tool(c, i, true);
            let a = click_frame(&mut fl, &vol, t, switching == 0, i, false);
            i += 1;
            let Some(p) = a.stats.tf_progress.clone() else {
                break (a, t);
            };
            // The old method stays on screen until the new one is complete.
            assert_eq!((p.what, p.name.as_str()), ("AO", want), "frame {i}");
            assert_eq!(fl.cao.method_name(), shown, "frame {i}");
            switching += 1;
        };
        assert_eq!(fl.cao.method_name(), want);
        assert_eq!(fl.shown_tf().name, "ct-skin", "the TF stays");
        if progressive {
            assert!(
                switching > N / SLAB,
                "LAO went {switching} frames, not slab by slab"
            );
        }
        // Equal, bit for bit, to a loop started with that method, on the same carved frame.
        let mut fresh = new_loop_with(
            &gpu,
            &vol,
            tfs.clone(),
            Mode::Contextual,
            AoConfig::new(
                fl.ao_methods()[names.iter().position(|n| n == want).unwrap()],
                PARAMS,
            ),
        );
        assert_eq!(fresh.cao.method_name(), want);
        let f = click_frame(&mut fresh, &vol, t, false, i, false);
        let got = read_ao(&fl.cao.ao);
        let d = common::first_bit_difference(&got, &read_ao(&fresh.cao.ao));
        assert!(
            d.is_none(),
            "{want}: V_AO differs from a fresh start at {d:?}"
        );
        assert!(done.image == f.image, "{want}: the image differs");
        assert!(done.stats.metrics.recomputed > 0, "{want}: the tool carves");
        assert!(got != before, "{want}: the switch changed nothing");
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn both_eyes_sample_the_one_ambient_volume_under_every_method() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    let c = Placement::default().center;
    let mut lefts = Vec::new();
    for method in [
        AoMethod::Lao,
        filter(Estimator::Gauss),
        filter(Estimator::Cdf),
    ] {
        let mut fl = new_loop_with(
            &gpu,
            &vol,
            tfs.clone(),
            Mode::Contextual,
            AoConfig::new(method, PARAMS),
        );
        // Each eye has its own jitter pattern; without it the pictures can be compared.
        fl.settings.jitter = false;
        for i in 0..3 {
            let f = click_frame(&mut fl, &vol, tool(c, i, true), false, i, true);
            // One AO update per frame, for both eyes: with the eyes at one pose the two
            // pictures are the same bits.
            assert!(
                f.image.rgba[0] == f.image.rgba[1],
                "{}: frame {i}: the eyes differ",
                method.name()
            );
            assert!(f.stats.metrics.recomputed > 0);
            if i == 2 {
                lefts.push(f.image.rgba[0].clone());
            }
        }
    }
    // ...and the pictures are each method's own.
    assert!(lefts[0] != lefts[1] && lefts[1] != lefts[2] && lefts[0] != lefts[2]);
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn menu_switch_recomputes_progressively_then_equals_a_fresh_loop() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let (bone, skin) = (
        TransferFunction::preset("ct-bone").unwrap(),
        TransferFunction::preset("ct-skin").unwrap(),
    );
    let tfs = vec![bone.clone(), skin.clone(), soft()];
    let mut fl = new_loop(&gpu, &vol, tfs.clone(), Mode::Contextual);
    // The same frames, never switched.
    let mut still = new_loop(&gpu, &vol, tfs.clone(), Mode::Contextual);
    assert_eq!(fl.interaction.settings().tf_presets, 3);
    let c = Placement::default().center;

    // Menu once (-> ct-skin), then again after three slabs (-> ct-soft): the second press
    // restarts the recompute for the newest TF.
    let mut i = 0;
    let mut progress: Vec<(String, f32)> = Vec::new();
    let mut slab_frames = 0;
    let mut pressed_twice = false;
    let (switch_frame, switch_tool) = loop {
        assert!(i < 200, "the switch never finished: {progress:?}");
        let menu = i == 0 || (slab_frames == 3 && !pressed_twice);
        if menu && i > 0 {
            pressed_twice = true;
            slab_frames = 0;
        }
        let t = tool(c, i, i % 5 != 4);
        let a = frame(&mut fl, &vol, t, menu, i);
        let Some(p) = a.stats.tf_progress.clone() else {
            break (a, t);
        };
        // (a) Still the old TF and AO, bit for bit, while CAO goes on.
        let b = frame(&mut still, &vol, t, false, i);
        assert!(b.stats.tf_progress.is_none());
        assert_eq!(fl.shown_tf().name, "ct-bone", "frame {i}");
        let d = common::first_bit_difference(&read_ao(&fl.cao.ao), &read_ao(&still.cao.ao));
        assert!(
            d.is_none(),
            "frame {i}: V_AO changed during the recompute at {d:?}"
        );
        assert!(
            a.image == b.image,
            "frame {i}: image changed during the recompute"
        );
        assert_eq!(
            a.stats.metrics.recomputed, b.stats.metrics.recomputed,
            "frame {i}"
        );
        assert!(
            a.stats.metrics.recomputed > 0 || !t.active,
            "frame {i}: the tool carves"
        );
        // A slab ran this frame when this TF's fraction grew.
        let before = progress
            .last()
            .filter(|l| l.0 == p.name)
            .map_or(0.0, |l| l.1);
        assert!(
            p.fraction >= before,
            "frame {i}: progress went back: {progress:?}"
        );
        if p.fraction > before {
            slab_frames += 1;
        } else {
            assert_eq!(a.stats.tf_ms, 0.0, "frame {i}: no slab, no slab time");
        }
        progress.push((p.name.clone(), p.fraction));
        i += 1;
    };
    assert!(pressed_twice);
    let switched_at = i;

    // (b) The first TF got three slabs before the restart; the restarted one took exactly
    // ceil(N / SLAB) slab frames, SLAB / N each, and the switch came on the frame after the last.
    let steps = |name: &str| -> Vec<f32> {
        let mut v: Vec<f32> = progress
            .iter()
            .filter(|p| p.0 == name && p.1 > 0.0)
            .map(|p| p.1)
            .collect();
        v.dedup();
        v
    };
    let frac = |s: usize| (s * SLAB) as f32 / N as f32;
    assert_eq!(
        steps("ct-skin"),
        [frac(1), frac(2), frac(3)],
        "{progress:?}"
    );
    let expect: Vec<f32> = (1..=N.div_ceil(SLAB)).map(frac).collect();
    assert_eq!(steps("ct-soft"), expect, "{progress:?}");
    assert_eq!(slab_frames, N.div_ceil(SLAB));
    assert_eq!(progress.last().unwrap(), &("ct-soft".to_string(), 1.0));
    assert_eq!(fl.shown_tf().name, "ct-soft");
    assert_eq!(fl.scene.tf_index, 2);

    // (c) From the switch on: the same V_AO and images as a loop started with ct-soft, the same
    // V_AO as the naive full recompute, tools carving; with the tool off, V_AO is V_PAO'.
    let mut fresh = new_loop(&gpu, &vol, vec![soft(), bone, skin], Mode::Contextual);
    let mut naive = new_loop(&gpu, &vol, vec![soft()], Mode::Naive);
    let mut pao = None;
    let mut switch_frame = Some((switch_frame, switch_tool));
    for k in 0..3 {
        let i = switched_at + k;
        // k = 0: the switch frame the loop above rendered; then one more carving, one without.
        let (a, t) = switch_frame.take().unwrap_or_else(|| {
            let t = tool(c, i, k == 1);
            (frame(&mut fl, &vol, t, false, i), t)
        });
        let carve = t.active;
        let f = frame(&mut fresh, &vol, t, false, i);
        let n = frame(&mut naive, &vol, t, false, i);
        let ao = read_ao(&fl.cao.ao);
        let d = common::first_bit_difference(&ao, &read_ao(&fresh.cao.ao));
        assert!(
            d.is_none(),
            "frame {i}: V_AO differs from a fresh loop at {d:?}"
        );
        let d = common::first_bit_difference(&ao, &read_ao(&naive.cao.ao));
        assert!(
            d.is_none(),
            "frame {i}: V_AO differs from the naive recompute at {d:?}"
        );
        assert!(a.stats.tf_progress.is_none());
        assert!(
            a.image == f.image,
            "frame {i}: image differs from a fresh loop"
        );
        assert_eq!(
            a.stats.metrics.clipped, f.stats.metrics.clipped,
            "frame {i}"
        );
        assert_eq!(
            a.stats.metrics.recomputed, f.stats.metrics.recomputed,
            "frame {i}"
        );
        assert!(
            carve == (a.stats.metrics.recomputed > 0),
            "frame {i}: {:?}",
            a.stats.metrics
        );
        assert_eq!(
            n.stats.metrics.clipped, f.stats.metrics.clipped,
            "frame {i}"
        );
        if !carve {
            pao = Some(ao);
        }
    }
    // V_PAO' differs from the old V_PAO (the switch did something).
    let old = frame(&mut still, &vol, tool(c, 0, false), false, 0);
    assert!(old.stats.tf_progress.is_none());
    assert!(common::first_bit_difference(&pao.unwrap(), &read_ao(&still.cao.ao)).is_some());
    common::assert_no_validation_messages(&gpu);
}

/// Pressing menu back to the TF on screen mid-way drops the recompute (its buffers freed after
/// the frame's wait, validation silent) and nothing changes.
#[test]
fn cycling_back_to_the_shown_tf_cancels_the_switch() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(24));
    let tfs = vec![
        TransferFunction::preset("ct-bone").unwrap(),
        TransferFunction::preset("ct-skin").unwrap(),
    ];
    let mut fl = new_loop(&gpu, &vol, tfs.clone(), Mode::Contextual);
    let mut still = new_loop(&gpu, &vol, tfs, Mode::Contextual);
    let c = Placement::default().center;
    let mut slabs = 0;
    let mut i = 0;
    // Menu, then a second press once a slab ran: back to ct-bone.
    while slabs == 0 {
        assert!(i < 100, "no slab ever ran");
        let a = frame(&mut fl, &vol, tool(c, i, true), i == 0, i);
        let p = a
            .stats
            .tf_progress
            .expect("in flight until the second press");
        assert_eq!(p.name, "ct-skin");
        slabs += (p.fraction > 0.0) as usize;
        frame(&mut still, &vol, tool(c, i, true), false, i);
        i += 1;
    }
    for k in 0..3 {
        let a = frame(&mut fl, &vol, tool(c, i, true), k == 0, i);
        let b = frame(&mut still, &vol, tool(c, i, true), false, i);
        assert!(a.stats.tf_progress.is_none(), "frame {i}: dropped");
        assert_eq!(fl.scene.tf_index, 0);
        assert_eq!(fl.shown_tf().name, "ct-bone");
        let d = common::first_bit_difference(&read_ao(&fl.cao.ao), &read_ao(&still.cao.ao));
        assert!(d.is_none(), "frame {i}: V_AO changed at {d:?}");
        assert!(a.image == b.image, "frame {i}");
        i += 1;
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn a_fast_start_shows_the_filter_first_then_exactly_lao() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    // LAO deep enough that the filter's one pass is the faster first light.
    let deep = LaoParams {
        rays: 26,
        steps: 12,
        step_mm: 4.0,
    };
    let built = |after: f64| Built {
        config: deep.into(),
        size: (48, 48),
        interaction: InteractionSettings::default(),
        fast_start_after_s: Some(after),
    };
    let new = |after: f64| {
        let mut fl = FrameLoop::new_lit(
            &gpu,
            Arc::clone(&vol),
            tfs.clone(),
            built(after),
            None,
            false,
        )
        .unwrap();
        fl.tf_samples_per_frame = LaoGpu::samples_per_slice(vol.dims, &deep) * SLAB as f64;
        fl
    };
    // A precompute shorter than the threshold is waited for, as without a fast start.
    let waited = new(1e9);
    assert_eq!(waited.cao.method_name(), "lao");
    assert!(waited.tf_slab_share.is_none());
    drop(waited);
    // LAO cheaper than the filter's pass, but beyond the threshold: the first picture is open
    // and LAO is computed.
    let cheap = Built {
        config: PARAMS.into(),
        ..built(0.0)
    };
    let mut fl =
        FrameLoop::new_lit(&gpu, Arc::clone(&vol), tfs.clone(), cheap, None, false).unwrap();
    assert_eq!(fl.cao.method_name(), "none");
    let t = tool(Placement::default().center, 0, true);
    let p = click_frame(&mut fl, &vol, t, false, 0, false)
        .stats
        .tf_progress;
    assert_eq!(p.map(|p| (p.what, p.name)), Some(("AO", "lao".to_string())));
    drop(fl);

    // Frames with a carving tool until nothing is computed any more: the (shown method,
    // method computed) of each frame, and the last frame with its tool.
    let c = Placement::default().center;
    let run = |fl: &mut FrameLoop| {
        let budget = fl.tf_samples_per_frame;
        let (mut i, mut stages) = (0, Vec::new());
        let (done, t) = loop {
            assert!(i < 200, "LAO never arrived");
            let t = tool(c, i, true);
            let a = click_frame(fl, &vol, t, false, i, false);
            i += 1;
            let Some(p) = a.stats.tf_progress.clone() else {
                break (a, t);
            };
            assert_eq!(p.what, "AO", "frame {i}");
            stages.push((a.stats.ao_method.clone(), p.name));
        };
        assert_ne!(
            fl.tf_samples_per_frame, budget,
            "the slab budget follows the frame times"
        );
        assert_eq!(done.stats.ao_method, "lao");
        // Then exactly what a loop that waited for LAO shows, on the same carved frame.
        let mut fresh = new_loop_with(&gpu, &vol, tfs.clone(), Mode::Contextual, deep.into());
        let f = click_frame(&mut fresh, &vol, t, false, i, false);
        let d = common::first_bit_difference(&read_ao(&fl.cao.ao), &read_ao(&fresh.cao.ao));
        assert!(
            d.is_none(),
            "V_AO differs from a loop that waited, at {d:?}"
        );
        assert!(done.image == f.image, "the image differs");
        stages
    };
    let count = |stages: &[(String, String)], shown: &str, computing: &str| {
        stages
            .iter()
            .filter(|(s, c)| s == shown && c == computing)
            .count()
    };
    // The filter's pass within the threshold: it lights the first picture, and the frames
    // until LAO is complete, slab by slab.
    let gauss = AoConfig::new(filter(Estimator::Gauss), deep);
    let quick = precompute_seconds(&gpu, &vol, &gauss);
    assert!(quick < precompute_seconds(&gpu, &vol, &deep.into()));
    let mut fl = new(quick);
    assert_eq!(
        fl.cao.method_name(),
        "filter-gauss",
        "the first picture's method"
    );
    let stages = run(&mut fl);
    assert!(
        count(&stages, "filter-gauss", "lao") == stages.len() && stages.len() > 1,
        "LAO not slab by slab under the filter: {stages:?}"
    );
    drop(fl);
    // Even the filter's pass beyond it: the first picture waits for nothing (AO 1, method
    // "none"), and LAO follows slab by slab (the filter's one-go pass would hold a frame).
    let mut fl = new(quick / 2.0);
    assert_eq!(fl.cao.method_name(), "none", "the first picture's method");
    assert!(read_ao(&fl.cao.ao).iter().all(|&a| a == 1.0));
    let stages = run(&mut fl);
    assert!(
        count(&stages, "none", "lao") == stages.len() && stages.len() > 1,
        "LAO not slab by slab while open: {stages:?}"
    );
    common::assert_no_validation_messages(&gpu);
}

/// The local histograms configured and a fast start: the first picture is lit by the filter (or
/// by nothing, open), the clustering runs on a worker thread beside the frames, and once it is
/// done the frames show exactly what a loop that waited for it shows.
#[test]
fn a_fast_start_clusters_the_local_histograms_beside_the_frames() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    let hist = AoConfig::new(
        // Wide enough (S_r ~ 600 voxels of 6.9 mm) that it takes longer than the filter.
        AoMethod::Histogram(HistParams {
            radius_mm: 36.0,
            bins: 16,
            clusters: 64,
            hemispheres: true,
        }),
        PARAMS,
    );
    let gauss = AoConfig::new(filter(Estimator::Gauss), PARAMS);
    let quick = precompute_seconds(&gpu, &vol, &gauss);
    assert!(quick < precompute_seconds(&gpu, &vol, &hist));
    let c = Placement::default().center;
    for (after, first) in [(quick, "filter-gauss"), (quick / 2.0, "none")] {
        let built = Built {
            config: hist,
            size: (48, 48),
            interaction: InteractionSettings::default(),
            fast_start_after_s: Some(after),
        };
        let mut fl =
            FrameLoop::new_lit(&gpu, Arc::clone(&vol), tfs.clone(), built, None, false).unwrap();
        assert_eq!(fl.cao.method_name(), first, "the first picture's method");
        let (mut i, mut stages) = (0, Vec::new());
        let (done, t) = loop {
            assert!(i < 2000, "the local histograms never arrived");
            let t = tool(c, i, true);
            let a = click_frame(&mut fl, &vol, t, false, i, false);
            i += 1;
            let Some(p) = a.stats.tf_progress.clone() else {
                break (a, t);
            };
            assert_eq!((p.what, p.name.as_str()), ("AO", "histogram"), "frame {i}");
            stages.push(a.stats.ao_method.clone());
            // Frames keep coming while it clusters (lavapipe shares two cores with it).
            std::thread::sleep(std::time::Duration::from_millis(20));
        };
        assert!(
            !stages.is_empty() && stages.iter().all(|s| s == first),
            "{first}: {stages:?}"
        );
        assert_eq!(done.stats.ao_method, "histogram");
        let mut waited = new_loop_with(&gpu, &vol, tfs.clone(), Mode::Contextual, hist);
        let f = click_frame(&mut waited, &vol, t, false, i, false);
        let d = common::first_bit_difference(&read_ao(&fl.cao.ao), &read_ao(&waited.cao.ao));
        assert!(
            d.is_none(),
            "{first}: V_AO differs from a loop that waited, at {d:?}"
        );
        assert!(done.image == f.image, "{first}: the image differs");
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn a_frame_budget_lengthens_the_step_and_leaves_the_ao_alone() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    let mut held = new_loop(&gpu, &vol, tfs.clone(), Mode::Contextual);
    let mut free = new_loop(&gpu, &vol, tfs.clone(), Mode::Contextual);
    // A budget no frame can meet: the step grows to its bound over the frames.
    let base = held.settings.step_for(vol.spacing);
    held.set_frame_budget(Some(0.001));
    let c = Placement::default().center;
    let mut factors = Vec::new();
    for i in 0..12 {
        let t = tool(c, i, true);
        let a = click_frame(&mut held, &vol, t, false, i, false);
        let b = click_frame(&mut free, &vol, t, false, i, false);
        factors.push(a.stats.step_factor);
        // The step stays within its bound of the configured one.
        let step = held.settings.step_for(vol.spacing);
        let max = base * cao_xr::app::budget::MAX_STEP_FACTOR as f32;
        assert!(
            step >= base && step <= max * 1.0001,
            "frame {i}: step {step} mm of {base}"
        );
        assert_eq!(b.stats.step_factor, 1.0);
        // The AO is the same bits with and without the budget, every frame.
        let d = common::first_bit_difference(&read_ao(&held.cao.ao), &read_ao(&free.cao.ao));
        assert!(d.is_none(), "frame {i}: the budget changed V_AO at {d:?}");
        if i == 11 {
            assert!(
                a.image != b.image,
                "the longer step changed nothing on screen"
            );
            // Past the longest step and foveation, the render scale: each eye drawn at the
            // lowest scale, and read back at that size.
            assert!(a.stats.budget_foveates);
            assert_eq!(a.stats.render_scale, cao_xr::app::budget::MIN_RENDER_SCALE);
            assert_eq!((a.image.width, a.image.height), (24, 24));
        }
    }
    assert!(factors.windows(2).all(|w| w[1] >= w[0]), "{factors:?}");
    assert_eq!(
        *factors.last().unwrap(),
        cao_xr::app::budget::MAX_STEP_FACTOR,
        "{factors:?}"
    );
    // Off again: the configured step, at full scale.
    held.set_frame_budget(None);
    assert_eq!(held.settings.step_mm, free.settings.step_mm);
    let a = click_frame(&mut held, &vol, tool(c, 12, true), false, 12, false);
    let b = click_frame(&mut free, &vol, tool(c, 12, true), false, 12, false);
    assert!(a.image == b.image, "the budget left a mark once off");
    common::assert_no_validation_messages(&gpu);
}

/// A contextual loop of `size` pixels per eye.
fn sized_loop(
    gpu: &Gpu,
    vol: &Arc<Volume>,
    tfs: &[TransferFunction],
    size: (u32, u32),
) -> FrameLoop {
    let mut fl = FrameLoop::new(
        gpu,
        Arc::clone(vol),
        tfs.to_vec(),
        AoConfig::from(PARAMS),
        size,
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.mode = Mode::Contextual;
    fl
}

/// A foveated frame spends its full rate where the eyes look: within the radius around the
/// gaze's pixel in each eye every pixel is the unfoveated frame's, bit for bit, and around the
/// lens centre, away from the gaze, the coarse rays show.
#[test]
fn a_foveated_frame_follows_the_gaze() {
    use cao_xr::render::{fixation, fovea_centre, Foveation};
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    let size = (96u32, 96u32);
    let (mut full, mut foveated) = (
        sized_loop(&gpu, &vol, &tfs, size),
        sized_loop(&gpu, &vol, &tfs, size),
    );
    let radius = 0.2;
    foveated.settings.foveation = Some(Foveation { radius, factor: 3 });
    let views = default_stereo_views(&vol, &Placement::default(), 0.064);
    // Up and to the right of straight ahead.
    let head = views[0].pose.orientation;
    let gaze = head * Vec3::new(0.2, 0.15, -1.0).normalize();
    let mut input = FrameInput::without_hands(0.0, views);
    let look = Pose {
        position: views[0].pose.position.lerp(views[1].pose.position, 0.5),
        orientation: glam::Quat::from_rotation_arc(Vec3::NEG_Z, gaze),
    };
    input.gaze = Some(look);
    // The point it fixates, at the volume's depth: each eye's fovea is where that point is.
    let fixated = fixation(&look, Placement::default().center);
    let c = Placement::default().center;
    let run = |fl: &mut FrameLoop| {
        fl.scene.tools = vec![tool(c, 0, true)];
        fl.frame(&input).unwrap().image
    };
    let (a, b) = (run(&mut full), run(&mut foveated));
    let r = radius * 0.5 * (size.0 as f32).hypot(size.1 as f32);
    let (w, h) = (size.0 as usize, size.1 as usize);
    for (eye, view) in views.iter().enumerate() {
        let at = fovea_centre(view, Some(fixated), size);
        let lens = fovea_centre(view, None, size);
        assert!(
            (at[0] - lens[0]).hypot(at[1] - lens[1]) > 1.5 * r,
            "eye {eye}: the gaze {at:?} is too near the centre"
        );
        let (mut inside, mut near_lens_differs) = (0, false);
        for y in 0..h {
            for x in 0..w {
                let p = [x as f32 + 0.5, y as f32 + 0.5];
                let from = |q: [f32; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
                let i = (y * w + x) * 4;
                let (pa, pb) = (&a.rgba[eye][i..i + 4], &b.rgba[eye][i..i + 4]);
                if from(at) <= r - 1.0 {
                    assert_eq!(pa, pb, "eye {eye}, pixel {x},{y} near the gaze");
                    inside += 1;
                } else if from(lens) <= r {
                    near_lens_differs |= pa != pb;
                }
            }
        }
        assert!(inside > 400, "eye {eye}: {inside} pixels at full rate");
        assert!(
            near_lens_differs,
            "eye {eye}: the lens centre is at full rate"
        );
    }
    common::assert_no_validation_messages(&gpu);
}

/// A render scale below 1 draws each eye into the top-left part of its image, and every pixel
/// there is the one a target of that size holds, bit for bit: with every pixel cast, foveated,
/// and with the second eye reprojected.
#[test]
fn a_render_scaled_frame_is_the_frame_of_a_smaller_target() {
    use cao_xr::render::Foveation;
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(N));
    let tfs = vec![TransferFunction::preset("ct-skin").unwrap()];
    let sized = |size| sized_loop(&gpu, &vol, &tfs, size);
    let c = Placement::default().center;
    let foveated = Foveation {
        radius: 0.3,
        factor: 3,
    };
    // (name, foveation, reprojection)
    let cases = [
        ("every pixel cast", None, false),
        ("foveated", Some(foveated), false),
        ("reprojected", None, true),
    ];
    for (name, foveation, reproject) in cases {
        let (mut scaled, mut small) = (sized((64, 48)), sized((40, 30)));
        for fl in [&mut scaled, &mut small] {
            fl.settings.foveation = foveation;
            fl.settings.reproject = reproject;
        }
        scaled.set_render_scale(0.625);
        for i in 0..2 {
            let a = click_frame(&mut scaled, &vol, tool(c, i, true), false, i, false);
            let b = click_frame(&mut small, &vol, tool(c, i, true), false, i, false);
            assert_eq!((a.image.width, a.image.height), (40, 30), "{name}");
            assert!(a.image == b.image, "{name}, frame {i}: the pixels differ");
        }
        // Back to the whole image: the larger target's own picture.
        scaled.set_render_scale(1.0);
        let a = click_frame(&mut scaled, &vol, tool(c, 2, true), false, 2, false);
        assert_eq!((a.image.width, a.image.height), (64, 48), "{name}");
    }
    common::assert_no_validation_messages(&gpu);
}

/// An isosurface (`--iso`) is lit by the AO of its solid, and the left thumbstick moves the
/// isovalue: the very next frame shows the new surface and its AO, which equal a loop started
/// at the new isovalue bit for bit (the local histograms: one table update, no precompute).
#[test]
fn the_left_stick_moves_the_isovalue_and_the_next_frame_shows_its_surface_and_ao() {
    use cao_xr::ao::histogram::HistParams;
    use cao_xr::app::lighting::LightingOptions;
    use cao_xr::input::LEFT;
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(24));
    let tfs = vec![TransferFunction::preset("ct-bone").unwrap()];
    let method = AoMethod::Histogram(HistParams {
        radius_mm: 20.0,
        bins: 16,
        clusters: 0,
        ..Default::default()
    });
    let new = |iso: f32| {
        let mut lighting = LightingOptions::default();
        lighting.shading.iso = Some(iso);
        lighting.shading.jitter = false;
        let built = Built {
            config: AoConfig {
                method,
                ..PARAMS.into()
            },
            size: (48, 48),
            interaction: InteractionSettings::default(),
            fast_start_after_s: None,
        };
        FrameLoop::new_lit(
            &gpu,
            Arc::clone(&vol),
            tfs.clone(),
            built,
            Some(&lighting),
            false,
        )
        .unwrap()
    };
    let views = default_stereo_views(&vol, &Placement::default(), 0.064);
    let frame = |fl: &mut FrameLoop, i: usize, stick: f32| {
        let mut input = FrameInput::without_hands(i as f64 / 10.0, views);
        input.hands[LEFT].buttons.thumbstick.y = stick;
        fl.frame(&input).unwrap()
    };
    let (lo, hi) = vol.value_range();
    let start = lo + 0.5 * (hi - lo);
    let mut fl = new(start);
    let a = frame(&mut fl, 0, 0.0);
    assert_eq!(fl.scene.iso, Some(start));
    // Full stick up for 0.1 s: a quarter of the range per second, past the dead zone.
    let b = frame(&mut fl, 1, 1.0);
    let moved = fl.scene.iso.unwrap();
    assert!(moved > start + 0.02 * (hi - lo), "{start} -> {moved}");
    assert!(
        a.image != b.image,
        "the new surface is not shown in the next frame"
    );
    assert!(
        b.stats.tf_progress.is_none(),
        "a table update, nothing in flight"
    );
    // The same as a loop started at the new isovalue.
    let mut fresh = new(moved);
    let c = frame(&mut fresh, 1, 0.0);
    assert!(
        b.image == c.image,
        "the moved surface differs from a fresh start there"
    );
    let d = common::first_bit_difference(&read_ao(&fl.cao.ao), &read_ao(&fresh.cao.ao));
    assert!(d.is_none(), "V_AO differs from a fresh start at {d:?}");
    common::assert_no_validation_messages(&gpu);
}
