//! The stereo ray caster on lavapipe with validation on: determinism, parallax, depth.

use crate::common;

use cao_xr::app::HeadlessRenderer;
use cao_xr::render::{RenderSettings, StereoImage, VolumeTextures};
use cao_xr::space::{Fov, Placement, Pose, View};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::Volume;
use glam::{Quat, Vec3};

const W: u32 = 128;
const HALF: f32 = 0.2; // half field of view, radians
const DIST: f32 = 0.6;
const IPD: f32 = 0.064;

fn views(placement: &Placement) -> [View; 2] {
    let fov = Fov {
        angle_left: -HALF,
        angle_right: HALF,
        angle_up: HALF,
        angle_down: -HALF,
    };
    [-0.5f32, 0.5].map(|s| View {
        pose: Pose {
            position: placement.center + Vec3::new(s * IPD, 0.0, DIST),
            orientation: Quat::IDENTITY,
        },
        fov,
    })
}

fn render(vol: &Volume, settings: &RenderSettings) -> (StereoImage, [View; 2]) {
    let gpu = common::gpu();
    let mut hr = HeadlessRenderer::new(&gpu).unwrap();
    let tf = TransferFunction::preset("ct-bone").unwrap();
    let tex = VolumeTextures::new(&gpu, vol, &tf).unwrap();
    let placement = Placement::default();
    let v = views(&placement);
    let frame = cao_xr::render::FrameViews {
        views: &v,
        model: cao_xr::space::world_from_tex(vol, &placement),
        clip: None,
        sh: None,
        ao: None,
        bleeding: None,
        inset: None,
    };
    let img = hr.render(&tex, &frame, (W, W), settings).unwrap();
    drop((tex, hr));
    common::assert_no_validation_messages(&gpu);
    (img, v)
}

#[test]
fn rendering_twice_is_bit_identical() {
    let vol = common::ball();
    let s = RenderSettings::default();
    let (a, _) = render(&vol, &s);
    let (b, _) = render(&vol, &s);
    assert!(a == b, "two renders of the same frame differ");
}

#[test]
fn eyes_differ_by_the_parallax_of_their_offset() {
    let (img, _) = render(&common::ball(), &RenderSettings::default());
    assert_ne!(
        img.rgba[0], img.rgba[1],
        "left and right images must differ"
    );
    let (lx, ly) = common::centroid(&img, 0).expect("the left eye saw nothing");
    let (rx, ry) = common::centroid(&img, 1).expect("the right eye saw nothing");
    // The ball is centred between the eyes at distance DIST: it appears right of centre in the
    // left eye and left of centre in the right eye, by (IPD/2)/DIST / tan(HALF) half-widths.
    let expect = (IPD as f64 / 2.0 / DIST as f64) / (HALF as f64).tan() * W as f64 / 2.0;
    let c = W as f64 / 2.0;
    assert!(
        (lx - c - expect).abs() < 1.0,
        "left centroid {lx}, expected {}",
        c + expect
    );
    assert!(
        (c - rx - expect).abs() < 1.0,
        "right centroid {rx}, expected {}",
        c - expect
    );
    assert!(
        (ly - c).abs() < 0.5 && (ry - c).abs() < 0.5,
        "no vertical parallax: {ly} {ry}"
    );
}

#[test]
fn depth_is_the_front_surface_of_the_volume() {
    let (img, views) = render(&common::ball(), &RenderSettings::default());
    for (eye, view) in views.iter().enumerate() {
        // Pixel where the ball's centre projects; the front surface is 16 mm nearer.
        let centre = Placement::default().center;
        let clip = view.view_proj() * centre.extend(1.0);
        let px = ((clip.x / clip.w + 1.0) * 0.5 * W as f32) as usize;
        let py = ((clip.y / clip.w + 1.0) * 0.5 * W as f32) as usize;
        let d = img.depth[eye][px + py * W as usize];
        assert!(d < 1.0, "eye {eye}: no depth written at the ball");
        // Unproject the stored depth to view-space distance along -Z.
        let ndc = glam::Vec4::new(
            ((px as f32 + 0.5) / W as f32) * 2.0 - 1.0,
            ((py as f32 + 0.5) / W as f32) * 2.0 - 1.0,
            d,
            1.0,
        );
        let w = view.view_proj().inverse() * ndc;
        let p = w.truncate() / w.w;
        let along = view.pose.position.z - p.z;
        let expected = DIST - 0.016;
        // Within one sampling step (1 mm) plus a voxel of trilinear smoothing (2 mm).
        assert!(
            (along - expected).abs() < 0.0035,
            "eye {eye}: depth at {along} m, front at {expected} m"
        );
    }
    // Background pixels keep the far plane.
    assert_eq!(img.depth[0][0], 1.0);
}
