//! Picture quality of the ray caster on lavapipe with validation on: the default settings
//! against the reference render (a 16x finer step, point samples, no jitter), cut faces lit by
//! the tool's normal, and a jitter pattern that is fixed per eye.

use crate::common;
use cao_xr::ao::lao::LaoParams;
use cao_xr::app::frame_loop::FrameLoop;
use cao_xr::gpu::Gpu;
use cao_xr::input::{FrameInput, InteractionSettings};
use cao_xr::render::compare::{luma, psnr, ssim};
use cao_xr::render::{RenderSettings, StereoImage};
use cao_xr::scene::{Tool, ToolMode};
use cao_xr::space::{default_stereo_views, Placement, Pose, DEFAULT_IPD};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{phantom, Volume};
use glam::{DVec3, Quat, Vec3};
use std::sync::Arc;

const W: u32 = 128;

fn frame_loop(gpu: &Gpu, vol: &Arc<Volume>, lao: LaoParams) -> FrameLoop {
    let tf = TransferFunction::preset("ct-bone").unwrap();
    let mut fl = FrameLoop::new(
        gpu,
        Arc::clone(vol),
        vec![tf],
        lao,
        (W, W),
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.show_overlay = false;
    fl
}

/// LAO with 6 rays: enough AO for these pictures, quick on lavapipe.
fn few_rays() -> LaoParams {
    LaoParams {
        rays: 6,
        ..Default::default()
    }
}

/// One frame of `fl` with `settings`, the volume at `placement`, eyes `ipd` apart.
fn frame(
    fl: &mut FrameLoop,
    settings: RenderSettings,
    placement: Placement,
    ipd: f32,
) -> StereoImage {
    fl.settings = settings;
    fl.scene.volume = placement;
    let views = default_stereo_views(fl.volume(), &placement, ipd);
    fl.frame(&FrameInput::without_hands(0.0, views))
        .unwrap()
        .image
}

/// PSNR (dB) and SSIM of the left eye of `b` against that of `a`, on luma.
fn quality(a: &StereoImage, b: &StereoImage) -> (f64, f64) {
    let (la, lb) = (luma(&a.rgba[0]), luma(&b.rgba[0]));
    (psnr(&la, &lb), ssim(&la, &lb, W as usize, W as usize))
}

/// The bar: at the default step PSNR >= 35 dB and SSIM >= 0.97 against the reference
/// on two views; with pre-integration a step twice the default still >= 32 dB, closer to the
/// reference than point samples at that step (what pre-integration buys).
#[test]
fn the_default_render_is_within_35_db_of_the_reference_on_two_views() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(40));
    let mut fl = frame_loop(&gpu, &vol, few_rays());
    let default = RenderSettings::default();
    let step = default.step_for(vol.spacing);
    for (name, placement) in cao_xr::app::bench_quality::views() {
        let reference = frame(
            &mut fl,
            default.reference(vol.spacing),
            placement,
            DEFAULT_IPD,
        );
        let got = frame(&mut fl, default, placement, DEFAULT_IPD);
        let (p, s) = quality(&reference, &got);
        eprintln!("{name}: default PSNR {p:.2} dB SSIM {s:.4}");
        assert!(
            p >= 35.0 && s >= 0.97,
            "{name}: PSNR {p:.2} dB, SSIM {s:.4}"
        );
        let coarse = RenderSettings {
            step_mm: 2.0 * step,
            ..default
        };
        let (p2, _) = quality(&reference, &frame(&mut fl, coarse, placement, DEFAULT_IPD));
        let point = RenderSettings {
            preintegrated: false,
            ..coarse
        };
        let (p2_point, _) = quality(&reference, &frame(&mut fl, point, placement, DEFAULT_IPD));
        eprintln!("{name}: 2x step PSNR {p2:.2} dB pre-integrated, {p2_point:.2} dB point samples");
        assert!(p2 >= 32.0, "{name}: 2x step pre-integrated PSNR {p2:.2} dB");
        assert!(
            p2 > p2_point,
            "{name}: pre-integration does not beat point samples"
        );
    }
    common::assert_no_validation_messages(&gpu);
}

/// A solid cube (1 mm voxels) with a closed spherical cavity at its centre.
fn cube_with_cavity(n: usize, cavity_mm: f64) -> Volume {
    let c = DVec3::splat(n as f64 / 2.0);
    common::ct_volume("cube-with-cavity", n, 1.0, |[i, j, k]| {
        let p = DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5);
        let solid = [i, j, k].iter().all(|&x| (4..n - 4).contains(&x));
        solid && (p - c).length() > cavity_mm
    })
}

/// Mean luma of the left eye's pixels whose distance from the image centre, in pixels, lies in
/// [r0, r1).
fn ring_mean(img: &StereoImage, r0: f64, r1: f64) -> f64 {
    let l = luma(&img.rgba[0]);
    let c = W as f64 / 2.0;
    let (mut sum, mut n) = (0.0, 0);
    for y in 0..W as usize {
        for x in 0..W as usize {
            let r = ((x as f64 + 0.5 - c).powi(2) + (y as f64 + 0.5 - c).powi(2)).sqrt();
            if (r0..r1).contains(&r) {
                sum += l[y * W as usize + x];
                n += 1;
            }
        }
    }
    assert!(n > 0);
    sum / n as f64
}

/// A box tool cuts the front off a solid cube just in front of a closed cavity: the cut face
/// (a plane facing the headlight) must read brighter than the cavity seen through the hole in
/// it, which the AO darkens. The data's gradient is zero inside the solid, so with cut-face
/// lighting off the cut face is lit by the ambient term alone and the order flips.
#[test]
fn the_cut_face_is_lit_by_the_tools_normal_and_the_cavity_behind_it_darkens() {
    let gpu = common::gpu();
    let n = 40;
    let vol = Arc::new(cube_with_cavity(n, 6.0));
    let lao = LaoParams {
        rays: 14,
        steps: 12,
        step_mm: 1.0,
    };
    let mut fl = frame_loop(&gpu, &vol, lao);
    let placement = Placement::default();
    // A box of half-edge 30 mm whose back face is 2 mm in front of the cavity's centre (towards
    // the eye).
    let cut_mm = 2.0;
    fl.scene.tools = vec![Tool {
        shape: cao_xr::clip::Shape::builtin("box").unwrap(),
        pose: Pose {
            position: placement.center + Vec3::new(0.0, 0.0, (cut_mm + 30.0) * 1e-3),
            orientation: Quat::IDENTITY,
        },
        size: 0.03,
        mode: ToolMode::Carve,
        active: true,
    }];
    // Pixels per mm at the volume's centre plane: the views frame its bounding sphere.
    let views = default_stereo_views(&vol, &placement, 0.0);
    let half_width_mm = views[0].pose.position.z - placement.center.z;
    let px_per_mm = W as f64 / (2.0 * (half_width_mm * views[0].fov.angle_up.tan()) as f64 * 1e3);
    let hole_mm = (6.0f64 * 6.0 - cut_mm as f64 * cut_mm as f64).sqrt();
    let measure = |fl: &mut FrameLoop, cut_lighting: bool| {
        let img = frame(
            fl,
            RenderSettings {
                cut_lighting,
                ..RenderSettings::default()
            },
            placement,
            0.0,
        );
        let cavity = ring_mean(&img, 0.0, 0.5 * hole_mm * px_per_mm);
        let face = ring_mean(&img, (hole_mm + 3.0) * px_per_mm, 13.0 * px_per_mm);
        (face, cavity)
    };
    let (face, cavity) = measure(&mut fl, true);
    eprintln!("cut lighting on: cut face {face:.1}, cavity {cavity:.1}");
    assert!(
        face > 1.15 * cavity,
        "the cut face ({face:.1}) does not read brighter than the cavity ({cavity:.1})"
    );
    let (face_off, cavity_off) = measure(&mut fl, false);
    eprintln!("cut lighting off: cut face {face_off:.1}, cavity {cavity_off:.1}");
    assert!(
        face_off <= 1.15 * cavity_off,
        "without cut-face lighting the cut face ({face_off:.1}) still beats the cavity \
         ({cavity_off:.1}): the test does not measure the tool's normal"
    );
    assert!(
        (cavity - cavity_off).abs() < 2.0,
        "the cavity's light changed: {cavity} vs {cavity_off}"
    );
    common::assert_no_validation_messages(&gpu);
}

/// Each eye has its own blue-noise pattern, the same every frame: with both eyes at one pose the
/// two pictures differ only by their jitter, and a second frame repeats the first bit for bit.
#[test]
fn the_jitter_pattern_is_fixed_per_eye() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(32));
    let mut fl = frame_loop(&gpu, &vol, few_rays());
    let coarse = RenderSettings {
        step_mm: 4.0,
        ..RenderSettings::default()
    };
    let p = Placement::default();
    let a = frame(&mut fl, coarse, p, 0.0);
    let b = frame(&mut fl, coarse, p, 0.0);
    assert!(a == b, "the same frame rendered twice differs");
    assert!(
        a.rgba[0] != a.rgba[1],
        "both eyes got the same jitter pattern"
    );
    let still = frame(
        &mut fl,
        RenderSettings {
            jitter: false,
            ..coarse
        },
        p,
        0.0,
    );
    assert!(
        still.rgba[0] == still.rgba[1],
        "without jitter the two eyes at one pose differ"
    );
    assert!(still.rgba[0] != a.rgba[0], "the jitter changed nothing");
    common::assert_no_validation_messages(&gpu);
}

/// Empty-space skipping changes no pixel: the phantom, seen from the front and turned, with a
/// carving sphere that reaches from the air into the skull and with a probe, pre-integrated,
/// point-sampled, tricubic and as the reference (1/16 of the step), each frame equals the one
/// that visits every sample, colour and depth, bit for bit, while a good share of the bricks is
/// skipped.
#[test]
fn empty_space_skipping_changes_no_pixel() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(48));
    let mut fl = frame_loop(&gpu, &vol, few_rays());
    let turned = Placement {
        rotation: Quat::from_rotation_y(0.7) * Quat::from_rotation_x(0.4),
        ..Placement::default()
    };
    let sphere = |mode, offset: Vec3| Tool {
        shape: cao_xr::clip::Shape::builtin("sphere").unwrap(),
        pose: Pose {
            position: Placement::default().center + offset,
            orientation: Quat::IDENTITY,
        },
        size: 0.05,
        mode,
        active: true,
    };
    let tools = [
        vec![],
        // Centred on the skin at the front: half in the air, half in the head.
        vec![sphere(ToolMode::Carve, Vec3::new(0.02, 0.0, 0.09))],
        vec![sphere(ToolMode::Probe, Vec3::new(0.0, 0.02, 0.0))],
    ];
    let base = RenderSettings::default();
    let variants = [
        base,
        RenderSettings {
            preintegrated: false,
            ..base
        },
        RenderSettings {
            tricubic: true,
            ..base
        },
    ];
    for placement in [Placement::default(), turned] {
        for t in &tools {
            fl.scene.tools = t.clone();
            for settings in variants {
                let on = frame(
                    &mut fl,
                    RenderSettings {
                        skip_empty: true,
                        ..settings
                    },
                    placement,
                    DEFAULT_IPD,
                );
                let (empty, all) = fl.tex.empty_bricks();
                assert!(
                    empty * 4 > all,
                    "only {empty} of {all} bricks empty: nothing to skip"
                );
                let off = frame(
                    &mut fl,
                    RenderSettings {
                        skip_empty: false,
                        ..settings
                    },
                    placement,
                    DEFAULT_IPD,
                );
                assert!(
                    on == off,
                    "{} tool(s), pre-integrated {}, tricubic {}: skipping changed the image",
                    t.len(),
                    settings.preintegrated,
                    settings.tricubic
                );
            }
        }
    }
    // Long rays of tiny steps (the reference), where skipping a run of samples in an inner loop
    // lost visible samples on lavapipe (seen on the CT head).
    fl.scene.tools.clear();
    let reference = base.reference(vol.spacing);
    let on = frame(
        &mut fl,
        RenderSettings {
            skip_empty: true,
            ..reference
        },
        turned,
        DEFAULT_IPD,
    );
    assert!(
        on == frame(&mut fl, reference, turned, DEFAULT_IPD),
        "reference"
    );
    common::assert_no_validation_messages(&gpu);
}

/// The clip test per brick changes no pixel: the phantom, from the front and turned, carved by a
/// sphere that hides many bricks whole, by that sphere and a turned box that overlaps it (the
/// first hider decides the cut face), and cut down to a probe, pre-integrated and
/// point-sampled: each frame equals the one that tests the maps at every sample, colour and
/// depth, bit for bit, while bricks of every kind (open, hidden whole, cut) are seen.
#[test]
fn clip_bricks_change_no_pixel() {
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(64));
    let mut fl = frame_loop(&gpu, &vol, few_rays());
    let turned = Placement {
        rotation: Quat::from_rotation_y(0.7) * Quat::from_rotation_x(0.4),
        ..Placement::default()
    };
    let tool = |shape: &str, mode, offset: Vec3, size: f32, turn: f32| Tool {
        shape: cao_xr::clip::Shape::builtin(shape).unwrap(),
        pose: Pose {
            position: Placement::default().center + offset,
            orientation: Quat::from_rotation_z(turn) * Quat::from_rotation_x(0.5 * turn),
        },
        size,
        mode,
        active: true,
    };
    let big = tool(
        "sphere",
        ToolMode::Carve,
        Vec3::new(0.02, 0.0, 0.05),
        0.07,
        0.0,
    );
    let tools = [
        vec![big],
        vec![
            tool(
                "box",
                ToolMode::Carve,
                Vec3::new(0.02, 0.08, 0.05),
                0.025,
                0.6,
            ),
            big,
        ],
        vec![tool(
            "sphere",
            ToolMode::Probe,
            Vec3::new(0.0, 0.02, 0.0),
            0.06,
            0.0,
        )],
    ];
    let base = RenderSettings::default();
    for placement in [Placement::default(), turned] {
        for t in &tools {
            fl.scene.tools = t.clone();
            for preintegrated in [true, false] {
                let settings = RenderSettings {
                    preintegrated,
                    ..base
                };
                let on = frame(&mut fl, settings, placement, DEFAULT_IPD);
                let [open, hidden, cut] = fl.cao.clip_brick_counts;
                assert!(
                    open > 0 && hidden > 0 && cut > 0,
                    "{} tool(s): {open} open, {hidden} hidden, {cut} cut bricks",
                    t.len()
                );
                let off = frame(
                    &mut fl,
                    RenderSettings {
                        clip_bricks: false,
                        ..settings
                    },
                    placement,
                    DEFAULT_IPD,
                );
                assert!(
                    on == off,
                    "{} tool(s), pre-integrated {preintegrated}: the clip test per brick changed the image",
                    t.len()
                );
            }
        }
    }
    common::assert_no_validation_messages(&gpu);
}

/// Pixels of the left eye within `r` pixels of the image centre whose luma differs from the
/// median of their 3x3 neighbourhood by more than `tol` (of 255): speckle.
fn speckles(img: &StereoImage, r: f64, tol: f64) -> usize {
    let l = luma(&img.rgba[0]);
    let w = W as usize;
    let c = W as f64 / 2.0;
    let mut n = 0;
    for y in 1..w - 1 {
        for x in 1..w - 1 {
            if ((x as f64 + 0.5 - c).powi(2) + (y as f64 + 0.5 - c).powi(2)).sqrt() >= r {
                continue;
            }
            let mut around: Vec<f64> = (0..9)
                .map(|k| l[(y + k / 3 - 1) * w + x + k % 3 - 1])
                .collect();
            around.sort_by(f64::total_cmp);
            if (l[y * w + x] - around[4]).abs() > tol {
                n += 1;
            }
        }
    }
    n
}

/// A sphere carves a bowl into the front of a solid cube, its clip camera looking across the
/// view, so the clip map's silhouette (where its depths are steepest) runs through the middle
/// of the bowl. The bowl is lit by the sphere's exact normal: smooth shading, no speckle, where
/// normals differenced from the clip map speckled along that line.
#[test]
fn a_sphere_cut_is_lit_smoothly_by_its_exact_normal() {
    let gpu = common::gpu();
    let n = 40;
    let vol = Arc::new(cube_with_cavity(n, 0.0));
    let mut fl = frame_loop(&gpu, &vol, few_rays());
    let placement = Placement::default();
    let radius_mm = 12.0;
    // The cube's front face is 16 mm in front of its centre, towards the eye.
    fl.scene.tools = vec![Tool {
        shape: cao_xr::clip::Shape::builtin("sphere").unwrap(),
        pose: Pose {
            position: placement.center + Vec3::new(0.0, 0.0, 16e-3),
            orientation: Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        },
        size: radius_mm * 1e-3,
        mode: ToolMode::Carve,
        active: true,
    }];
    let views = default_stereo_views(&vol, &placement, 0.0);
    let half_width_mm = views[0].pose.position.z - placement.center.z;
    let px_per_mm = W as f64 / (2.0 * (half_width_mm * views[0].fov.angle_up.tan()) as f64 * 1e3);
    // No specular term: its highlight is a real peak a few pixels wide.
    let settings = RenderSettings {
        specular: 0.0,
        ..RenderSettings::default()
    };
    let img = frame(&mut fl, settings, placement, 0.0);
    // Inside the bowl's rim (the rim itself is a real edge).
    let inside = 0.8 * radius_mm as f64 * px_per_mm;
    let bowl = ring_mean(&img, 0.0, inside);
    assert!(bowl > 60.0, "the bowl is dark ({bowl:.0}): not lit");
    // The AO's voxel grid shades the bowl in faint rings (a few levels); clip-map normals left
    // a band of pixels 60-100 levels off.
    let s = speckles(&img, inside, 32.0);
    assert!(s == 0, "{s} speckled pixels in the bowl");
    common::assert_no_validation_messages(&gpu);
}
