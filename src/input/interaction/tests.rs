//! Tests of the interaction layer: tools, grabbing, scaling, smoothing, buttons.

use super::*;
use crate::input::script::{generate, ScriptKind, ScriptParams};
use crate::input::{pose, Buttons};
use crate::space::{symmetric_fov, DEFAULT_IPD};
use std::f32::consts::FRAC_PI_2;

const FPS: f64 = 90.0;

/// A frame at `time` with both hands as given.
fn frame(time: f64, left: HandInput, right: HandInput) -> FrameInput {
    let head = pose(Vec3::new(0.0, 1.6, 0.0), Quat::IDENTITY);
    FrameInput {
        time,
        views: FrameInput::head_views(head, DEFAULT_IPD, symmetric_fov(0.6)),
        hands: [left, right],
        joints: [None; 2],
        gaze: None,
    }
}

/// A tracked hand at `position` / `orientation`, nothing pressed.
fn hand(position: Vec3, orientation: Quat) -> HandInput {
    let grip = pose(position, orientation);
    HandInput {
        tracked: true,
        grip,
        aim: grip,
        buttons: Buttons::default(),
    }
}

fn at(position: Vec3) -> HandInput {
    hand(position, Quat::IDENTITY)
}

fn gripping(mut h: HandInput) -> HandInput {
    h.buttons.grip = 1.0;
    h
}

fn triggering(mut h: HandInput, value: f32) -> HandInput {
    h.buttons.trigger = value;
    h
}

fn untracked(mut h: HandInput) -> HandInput {
    h.tracked = false;
    h
}

fn idle_left() -> HandInput {
    at(Vec3::new(-0.3, 1.0, -0.2))
}

fn idle_right() -> HandInput {
    at(Vec3::new(0.3, 1.0, -0.2))
}

/// Runs frames at FPS from frame number `start`; returns the next frame number.
fn run(
    ix: &mut Interaction,
    scene: &mut Scene,
    start: usize,
    hands: impl IntoIterator<Item = (HandInput, HandInput)>,
) -> usize {
    let mut i = start;
    for (l, r) in hands {
        ix.update(&frame(i as f64 / FPS, l, r), scene);
        i += 1;
    }
    i
}

fn close(a: Vec3, b: Vec3, tol: f32) -> bool {
    a.distance(b) <= tol
}

fn same_rotation(a: Quat, b: Quat, tol: f32) -> bool {
    a.dot(b).abs() >= 1.0 - tol
}

#[test]
fn the_right_hand_gets_a_sphere_that_follows_it_ahead_of_the_grip() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let q = Quat::from_rotation_y(FRAC_PI_2); // grip -Z now points to world -X
    let g = Vec3::new(0.2, 1.2, -0.4);
    run(&mut ix, &mut scene, 0, [(idle_left(), hand(g, q))]);
    assert_eq!(scene.tools.len(), 1, "only the right hand's tool");
    let t = scene.tools[RIGHT_TOOL];
    assert_eq!(t.shape, Shape::Sphere);
    assert_eq!(t.mode, ToolMode::Carve);
    assert!(!t.active);
    assert_eq!(t.size, 0.025);
    assert!(close(t.pose.position, g + Vec3::new(-0.08, 0.0, 0.0), 1e-6));
    assert!(same_rotation(t.pose.orientation, q, 1e-6));
    // No grip needed: it follows the hand everywhere.
    let g2 = g + Vec3::new(0.05, -0.1, 0.02);
    run(&mut ix, &mut scene, 1, [(idle_left(), hand(g2, q))]);
    let p = scene.tools[RIGHT_TOOL].pose.position;
    assert!(close(p, g2 + Vec3::new(-0.08, 0.0, 0.0), 1e-6));
    assert_eq!(ix.tool_of(RIGHT, &scene), Some(RIGHT_TOOL));
    assert_eq!(ix.tool_of(LEFT, &scene), None);
}

#[test]
fn grab_moves_and_turns_the_volume_with_the_left_hand() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let v0 = scene.volume;
    let g0 = Vec3::new(-0.15, 1.4, -0.5);
    let mut i = run(&mut ix, &mut scene, 0, [(at(g0), idle_right())]);
    i = run(&mut ix, &mut scene, i, [(gripping(at(g0)), idle_right())]);
    assert_eq!(ix.grab_mode(), GrabMode::OneHand);
    assert_eq!(scene.volume, v0, "grabbing alone does not move it");

    // Translate 10 cm right and 5 cm up.
    let shift = Vec3::new(0.1, 0.05, 0.0);
    i = run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(g0 + shift)), idle_right())],
    );
    assert!(close(scene.volume.center, v0.center + shift, 1e-6));
    assert!(same_rotation(scene.volume.rotation, v0.rotation, 1e-6));

    // Then turn the hand 90 degrees about +Y: the centre swings about the hand.
    let turn = Quat::from_rotation_y(FRAC_PI_2);
    let g1 = g0 + shift;
    i = run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(hand(g1, turn)), idle_right())],
    );
    let expect = g1 + turn * (v0.center - g0);
    assert!(
        close(scene.volume.center, expect, 1e-5),
        "{} vs {expect}",
        scene.volume.center
    );
    assert!(same_rotation(
        scene.volume.rotation,
        turn * v0.rotation,
        1e-6
    ));
    assert_eq!(scene.volume.scale, v0.scale);

    // Released: the hand moves on, the volume stays.
    let placed = scene.volume;
    i = run(&mut ix, &mut scene, i, [(hand(g1, turn), idle_right())]);
    run(&mut ix, &mut scene, i, [(at(g0), idle_right())]);
    assert_eq!(ix.grab_mode(), GrabMode::None);
    assert_eq!(scene.volume, placed);
}

#[test]
fn grip_hysteresis_keeps_a_loosening_grab() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let g = Vec3::new(0.0, 1.4, -0.4);
    let with_grip = |v: f32, p: Vec3| {
        let mut h = at(p);
        h.buttons.grip = v;
        (h, idle_right())
    };
    run(
        &mut ix,
        &mut scene,
        0,
        [
            with_grip(0.6, g),
            with_grip(0.35, g),
            with_grip(0.35, g + Vec3::X * 0.1),
        ],
    );
    assert_eq!(ix.grab_mode(), GrabMode::OneHand, "0.35 is still held");
    let c = Placement::default().center + Vec3::X * 0.1;
    assert!(close(scene.volume.center, c, 1e-6));
    run(&mut ix, &mut scene, 3, [with_grip(0.2, g)]);
    assert_eq!(ix.grab_mode(), GrabMode::None);
}

#[test]
fn two_hands_moving_apart_twice_as_far_scale_the_volume_twice() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let c = scene.volume.center;
    let (l0, r0) = (c - Vec3::X * 0.1, c + Vec3::X * 0.1);
    let mut i = run(
        &mut ix,
        &mut scene,
        0,
        [(gripping(at(l0)), gripping(at(r0)))],
    );
    assert_eq!(ix.grab_mode(), GrabMode::TwoHands);
    for k in 1..=30 {
        let s = 0.1 * (1.0 + k as f32 / 30.0);
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(gripping(at(c - Vec3::X * s)), gripping(at(c + Vec3::X * s)))],
        );
    }
    assert!(
        (scene.volume.scale - 2.0).abs() < 1e-5,
        "{}",
        scene.volume.scale
    );
    assert!(
        close(scene.volume.center, c, 1e-6),
        "the midpoint did not move"
    );
    assert!(same_rotation(scene.volume.rotation, Quat::IDENTITY, 1e-6));

    // Both hands up 10 cm: the volume follows the midpoint, keeping its scale.
    let up = Vec3::Y * 0.1;
    let (l, r) = (c - Vec3::X * 0.2 + up, c + Vec3::X * 0.2 + up);
    i = run(&mut ix, &mut scene, i, [(gripping(at(l)), gripping(at(r)))]);
    assert!(close(scene.volume.center, c + up, 1e-6));
    assert!((scene.volume.scale - 2.0).abs() < 1e-5);

    // Far apart: clamped at the maximum scale.
    let far = Vec3::X * 5.0;
    run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(c - far)), gripping(at(c + far)))],
    );
    assert_eq!(scene.volume.scale, 10.0);
}

#[test]
fn two_hand_scale_pivots_about_the_midpoint_and_turns_with_the_hands() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let c = scene.volume.center;
    // Hands 20 cm apart, their midpoint 10 cm left of the volume centre.
    let m0 = c - Vec3::X * 0.1;
    let (l0, r0) = (m0 - Vec3::Z * 0.1, m0 + Vec3::Z * 0.1);
    let i = run(
        &mut ix,
        &mut scene,
        0,
        [(gripping(at(l0)), gripping(at(r0)))],
    );
    // Spread to 30 cm and turn the hand axis 90 degrees about +Y (+Z -> +X).
    let (l1, r1) = (m0 - Vec3::X * 0.15, m0 + Vec3::X * 0.15);
    run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(l1)), gripping(at(r1)))],
    );
    let turn = Quat::from_rotation_y(FRAC_PI_2);
    assert!((scene.volume.scale - 1.5).abs() < 1e-5);
    let expect = m0 + turn * (Vec3::X * 0.1 * 1.5);
    assert!(
        close(scene.volume.center, expect, 1e-5),
        "{}",
        scene.volume.center
    );
    assert!(same_rotation(scene.volume.rotation, turn, 1e-5));
}

#[test]
fn joining_and_leaving_hands_never_make_the_volume_jump() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let c = scene.volume.center;
    let (l, r) = (c - Vec3::X * 0.1, c + Vec3::X * 0.1);
    let mut i = run(&mut ix, &mut scene, 0, [(gripping(at(l)), at(r))]);
    let before = scene.volume;
    i = run(&mut ix, &mut scene, i, [(gripping(at(l)), gripping(at(r)))]);
    assert_eq!(ix.grab_mode(), GrabMode::TwoHands);
    assert_eq!(scene.volume, before);
    // Spread, then let go with the right: one-handed from where it is.
    let r2 = r + Vec3::X * 0.2;
    i = run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(l)), gripping(at(r2)))],
    );
    let scaled = scene.volume;
    i = run(&mut ix, &mut scene, i, [(gripping(at(l)), at(r2))]);
    assert_eq!(ix.grab_mode(), GrabMode::OneHand);
    assert_eq!(scene.volume, scaled);
    run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(l + Vec3::Y * 0.1)), at(r2))],
    );
    assert!(close(
        scene.volume.center,
        scaled.center + Vec3::Y * 0.1,
        1e-6
    ));
    assert_eq!(scene.volume.scale, scaled.scale);
}

#[test]
fn the_right_grip_alone_does_not_grab() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let v0 = scene.volume;
    let r = Vec3::new(0.2, 1.3, -0.5);
    run(
        &mut ix,
        &mut scene,
        0,
        [
            (idle_left(), gripping(at(r))),
            (idle_left(), gripping(at(r + Vec3::X * 0.1))),
        ],
    );
    assert_eq!(ix.grab_mode(), GrabMode::None);
    assert_eq!(scene.volume, v0);
}

#[test]
fn lost_tracking_freezes_the_tool() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let a = Vec3::new(0.1, 1.3, -0.4);
    let mut i = run(
        &mut ix,
        &mut scene,
        0,
        [(idle_left(), triggering(at(a), 1.0))],
    );
    let held = scene.tools[RIGHT_TOOL];
    assert!(held.active);
    // Untracked, the runtime's stale pose wanders off: the tool does not.
    for k in 1..=20 {
        let stale = a + Vec3::new(0.5, -1.0, 0.3) * (k as f32 / 20.0);
        i = run(
            &mut ix,
            &mut scene,
            i,
            [(idle_left(), untracked(at(stale)))],
        );
        assert!(!ix.is_tracked(RIGHT));
        assert_eq!(scene.tools[RIGHT_TOOL].pose, held.pose);
    }
    assert!(
        scene.tools[RIGHT_TOOL].active,
        "freezing keeps carving as it was"
    );
    // Tracked again: it resumes from the new pose.
    let b = a + Vec3::Y * 0.05;
    run(&mut ix, &mut scene, i, [(idle_left(), at(b))]);
    assert!(ix.is_tracked(RIGHT));
    let p = scene.tools[RIGHT_TOOL].pose.position;
    assert!(close(p, b + Vec3::new(0.0, 0.0, -0.08), 1e-6));
}

#[test]
fn lost_tracking_releases_the_grab_and_the_volume_does_not_jump_back() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let g = Vec3::new(-0.2, 1.4, -0.5);
    let mut i = run(
        &mut ix,
        &mut scene,
        0,
        [
            (gripping(at(g)), idle_right()),
            (gripping(at(g + Vec3::X * 0.05)), idle_right()),
        ],
    );
    let placed = scene.volume;
    // Lost mid-grab with the grip still squeezed; the stale pose jumps around.
    i = run(
        &mut ix,
        &mut scene,
        i,
        [(untracked(gripping(at(g + Vec3::Y))), idle_right())],
    );
    assert_eq!(ix.grab_mode(), GrabMode::None);
    assert_eq!(scene.volume, placed);
    // Re-tracked elsewhere, grip still held: no jump, no grab.
    for k in 0..10 {
        let p = g + Vec3::new(0.3, 0.1, 0.0) + Vec3::Z * (0.01 * k as f32);
        i = run(&mut ix, &mut scene, i, [(gripping(at(p)), idle_right())]);
        assert_eq!(scene.volume, placed);
        assert!(!ix.is_holding(LEFT));
    }
    // Released and pressed again: grabs from where it is.
    let p = g + Vec3::new(0.3, 0.1, 0.0);
    i = run(&mut ix, &mut scene, i, [(at(p), idle_right())]);
    i = run(&mut ix, &mut scene, i, [(gripping(at(p)), idle_right())]);
    assert_eq!(scene.volume, placed);
    run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(p + Vec3::X * 0.1)), idle_right())],
    );
    assert!(close(
        scene.volume.center,
        placed.center + Vec3::X * 0.1,
        1e-6
    ));
}

#[test]
fn losing_the_right_hand_in_a_two_hand_grab_leaves_a_one_hand_grab() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let c = scene.volume.center;
    let (l, r) = (c - Vec3::X * 0.1, c + Vec3::X * 0.1);
    let mut i = run(&mut ix, &mut scene, 0, [(gripping(at(l)), gripping(at(r)))]);
    i = run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(l)), gripping(at(r + Vec3::X * 0.2)))],
    );
    let scaled = scene.volume;
    i = run(
        &mut ix,
        &mut scene,
        i,
        [(gripping(at(l)), untracked(gripping(at(r))))],
    );
    assert_eq!(ix.grab_mode(), GrabMode::OneHand);
    assert_eq!(scene.volume, scaled, "the stale right pose is not used");
    // The right hand back, grip still held: one hand until a new press.
    run(&mut ix, &mut scene, i, [(gripping(at(l)), gripping(at(r)))]);
    assert_eq!(ix.grab_mode(), GrabMode::OneHand);
    assert!(close(scene.volume.center, scaled.center, 1e-6));
    assert_eq!(scene.volume.scale, scaled.scale);
}

#[test]
fn trigger_toggles_carving_with_hysteresis() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let r = Vec3::new(0.1, 1.3, -0.4);
    let values = [0.0, 0.6, 0.4, 0.6, 0.45, 0.2, 0.55, 0.9, 0.1, 0.29, 0.51];
    let expect = [
        false, true, true, true, true, true, false, false, false, false, true,
    ];
    for (i, (v, e)) in values.into_iter().zip(expect).enumerate() {
        run(
            &mut ix,
            &mut scene,
            i,
            [(idle_left(), triggering(at(r), v))],
        );
        assert_eq!(scene.tools[RIGHT_TOOL].active, e, "frame {i}, trigger {v}");
    }
}

#[test]
fn a_trigger_held_from_the_first_frame_carves() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let r = Vec3::new(0.1, 1.3, -0.4);
    for i in 0..50 {
        run(
            &mut ix,
            &mut scene,
            i,
            [(idle_left(), triggering(at(r), 1.0))],
        );
        assert!(scene.tools[RIGHT_TOOL].active);
    }
}

#[test]
fn the_left_trigger_gives_the_left_hand_a_tool_of_its_own() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let l = Vec3::new(-0.1, 1.3, -0.4);
    let r = Vec3::new(0.1, 1.3, -0.4);
    run(&mut ix, &mut scene, 0, [(at(l), at(r))]);
    assert_eq!(scene.tools.len(), 1);
    run(&mut ix, &mut scene, 1, [(triggering(at(l), 1.0), at(r))]);
    assert_eq!(scene.tools.len(), 2);
    assert_eq!(ix.tool_of(LEFT, &scene), Some(LEFT_TOOL));
    let t = scene.tools[LEFT_TOOL];
    assert!(t.active && !scene.tools[RIGHT_TOOL].active);
    assert!(close(t.pose.position, l + Vec3::new(0.0, 0.0, -0.08), 1e-6));
    let l2 = l - Vec3::X * 0.1;
    run(&mut ix, &mut scene, 2, [(triggering(at(l2), 1.0), at(r))]);
    let p = scene.tools[LEFT_TOOL].pose.position;
    assert!(close(p, l2 + Vec3::new(0.0, 0.0, -0.08), 1e-6));
}

#[test]
fn the_stick_resizes_exponentially_within_bounds() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let r = Vec3::new(0.1, 1.3, -0.4);
    let stick = |y: f32| {
        let mut h = at(r);
        h.buttons.thumbstick.y = y;
        (idle_left(), h)
    };
    // Inside the dead zone: nothing.
    let mut i = run(&mut ix, &mut scene, 0, (0..90).map(|_| stick(0.14)));
    assert_eq!(scene.tools[RIGHT_TOOL].size, 0.025);
    // Full stick for 0.5 s (45 frames of 1/90 s): exp(0.5) times larger.
    i = run(&mut ix, &mut scene, i, (0..45).map(|_| stick(1.0)));
    let grown = scene.tools[RIGHT_TOOL].size;
    assert!((grown / 0.025 - 0.5f32.exp()).abs() < 1e-3, "{grown}");
    // Half-way past the dead zone: half the rate, downwards.
    let half = -(0.15 + 0.85 / 2.0);
    i = run(&mut ix, &mut scene, i, (0..90).map(|_| stick(half)));
    let shrunk = scene.tools[RIGHT_TOOL].size;
    assert!((shrunk / grown - (-0.5f32).exp()).abs() < 1e-3, "{shrunk}");
    // Held long: clamped at the bounds.
    i = run(&mut ix, &mut scene, i, (0..900).map(|_| stick(1.0)));
    assert_eq!(scene.tools[RIGHT_TOOL].size, 0.15);
    run(&mut ix, &mut scene, i, (0..900).map(|_| stick(-1.0)));
    assert_eq!(scene.tools[RIGHT_TOOL].size, 0.005);
}

#[test]
fn the_stick_sideways_turns_the_light_and_leaves_the_tool() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let r = Vec3::new(0.1, 1.3, -0.4);
    let stick = |x: f32, left_x: f32| {
        let mut h = at(r);
        h.buttons.thumbstick.x = x;
        let mut l = idle_left();
        l.buttons.thumbstick.x = left_x;
        (l, h)
    };
    // Inside the dead zone: nothing.
    let mut i = run(&mut ix, &mut scene, 0, (0..90).map(|_| stick(0.14, -0.1)));
    assert_eq!(scene.light_yaw, 0.0);
    // Full stick right for 0.5 s (45 frames of 1/90 s): rate * 0.5 rad; the tool keeps its size.
    i = run(&mut ix, &mut scene, i, (0..45).map(|_| stick(1.0, 0.0)));
    let turned = scene.light_yaw;
    assert!((turned - 0.75).abs() < 1e-4, "{turned}");
    assert_eq!(scene.tools[RIGHT_TOOL].size, 0.025);
    // Both hands add up: left full left cancels right full right.
    i = run(&mut ix, &mut scene, i, (0..45).map(|_| stick(1.0, -1.0)));
    assert!((scene.light_yaw - turned).abs() < 1e-6);
    // Left alone, half-way past the dead zone: half the rate, the other way.
    run(
        &mut ix,
        &mut scene,
        i,
        (0..45).map(|_| stick(0.0, -(0.15 + 0.85 / 2.0))),
    );
    assert!(
        (scene.light_yaw - (turned - 0.375)).abs() < 1e-4,
        "{}",
        scene.light_yaw
    );
}

#[test]
fn frame_time_is_clamped() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    let mut h = at(Vec3::new(0.1, 1.3, -0.4));
    h.buttons.thumbstick.y = 1.0;
    ix.update(&frame(0.0, idle_left(), h), &mut scene);
    assert_eq!(ix.last_dt(), 0.0);
    assert_eq!(scene.tools[RIGHT_TOOL].size, 0.025, "no time, no resize");
    ix.update(&frame(100.0, idle_left(), h), &mut scene);
    assert_eq!(ix.last_dt(), MAX_DT);
    let s = scene.tools[RIGHT_TOOL].size;
    assert!((s / 0.025 - MAX_DT.exp()).abs() < 1e-5);
    ix.update(&frame(50.0, idle_left(), h), &mut scene);
    assert_eq!(ix.last_dt(), 0.0, "time running backwards");
    assert_eq!(scene.tools[RIGHT_TOOL].size, s);
}

#[test]
fn primary_cycles_shapes_and_secondary_cycles_the_mode() {
    let settings = InteractionSettings {
        mesh_count: 2,
        ..InteractionSettings::default()
    };
    let mut ix = Interaction::new(settings);
    let mut scene = Scene::default();
    let r = Vec3::new(0.1, 1.3, -0.4);
    let press = |primary: bool, secondary: bool| {
        let mut h = at(r);
        h.buttons.primary = primary;
        h.buttons.secondary = secondary;
        (idle_left(), h)
    };
    let mut i = run(&mut ix, &mut scene, 0, [press(false, false)]);
    let mut seen = vec![scene.tools[RIGHT_TOOL].shape];
    for _ in 0..6 {
        // Held for three frames: one step per press.
        i = run(&mut ix, &mut scene, i, [press(true, false); 3]);
        i = run(&mut ix, &mut scene, i, [press(false, false)]);
        seen.push(scene.tools[RIGHT_TOOL].shape);
    }
    use Shape::*;
    assert_eq!(
        seen,
        [Sphere, Box, Cylinder, Torus, Mesh(0), Mesh(1), Sphere]
    );

    assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Carve);
    i = run(&mut ix, &mut scene, i, [press(false, true); 2]);
    assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Probe);
    i = run(&mut ix, &mut scene, i, [press(false, false)]);
    i = run(&mut ix, &mut scene, i, [press(false, true)]);
    assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Measure);
    i = run(&mut ix, &mut scene, i, [press(false, false)]);
    run(&mut ix, &mut scene, i, [press(false, true)]);
    assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Carve);

    // Without meshes the built-ins wrap round; a stale mesh index goes back to the sphere.
    let ix = Interaction::default();
    assert_eq!(ix.next_shape(Torus), Sphere);
    assert_eq!(ix.next_shape(Mesh(7)), Sphere);
}

#[test]
fn a_measuring_tool_draws_rulers_and_points_in_the_volumes_millimetres_and_cuts_nothing() {
    let mut ix = Interaction::default();
    let mut scene = Scene::default();
    // A turned, half-size volume: marks are in its own mm, not in world metres.
    scene.volume.rotation = Quat::from_rotation_y(0.5);
    scene.volume.scale = 0.5;
    let (a, b) = (Vec3::new(0.1, 1.3, -0.4), Vec3::new(0.14, 1.33, -0.4));
    let offset = InteractionSettings::default().tool_offset;
    let placement = scene.volume;
    let local = |grip: Vec3| placement.local_mm(grip + offset);
    let with = |p: Vec3, trigger: f32, secondary: bool, primary: bool| {
        let mut h = triggering(at(p), trigger);
        h.buttons.secondary = secondary;
        h.buttons.primary = primary;
        (idle_left(), h)
    };
    let mut i = run(&mut ix, &mut scene, 0, [with(a, 0.0, false, false)]);
    // Carve -> probe -> measure.
    for _ in 0..2 {
        i = run(&mut ix, &mut scene, i, [with(a, 0.0, true, false)]);
        i = run(&mut ix, &mut scene, i, [with(a, 0.0, false, false)]);
    }
    assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Measure);
    // Press at a, drag to b (the far end follows while held), release there.
    i = run(&mut ix, &mut scene, i, [with(a, 1.0, false, false)]);
    assert_eq!(scene.marks.len(), 1);
    let mid = a.lerp(b, 0.5);
    i = run(&mut ix, &mut scene, i, [with(mid, 1.0, false, false)]);
    assert!(close(scene.marks[0].ends[1], local(mid), 1e-3));
    i = run(&mut ix, &mut scene, i, [with(b, 1.0, false, false)]);
    i = run(&mut ix, &mut scene, i, [with(b, 0.0, false, false)]);
    // Moving on after the release leaves the ruler where it was.
    i = run(&mut ix, &mut scene, i, [with(a, 0.0, false, false)]);
    assert_eq!(scene.marks.len(), 1);
    let m = scene.marks[0];
    assert!(close(m.ends[0], local(a), 1e-3) && close(m.ends[1], local(b), 1e-3));
    // 5 cm in the world at half size is 100 mm of the volume.
    assert!(
        (m.ends[0].distance(m.ends[1]) - 100.0).abs() < 1e-2,
        "{m:?}"
    );
    assert!(!m.is_point());
    assert!(
        !scene.tools[RIGHT_TOOL].cuts(),
        "a measuring tool never cuts"
    );
    // A click is a point.
    i = run(&mut ix, &mut scene, i, [with(b, 1.0, false, false)]);
    i = run(&mut ix, &mut scene, i, [with(b, 0.0, false, false)]);
    assert_eq!(scene.marks.len(), 2);
    assert!(scene.marks[1].is_point());
    // Primary removes the last mark; back to carving, the trigger cuts again.
    i = run(&mut ix, &mut scene, i, [with(b, 0.0, false, true)]);
    assert_eq!(scene.marks, [m]);
    i = run(&mut ix, &mut scene, i, [with(b, 0.0, true, false)]);
    i = run(&mut ix, &mut scene, i, [with(b, 1.0, false, false)]);
    run(&mut ix, &mut scene, i, [with(a, 1.0, false, false)]);
    assert_eq!(scene.tools[RIGHT_TOOL].mode, ToolMode::Carve);
    assert!(scene.tools[RIGHT_TOOL].cuts());
    assert_eq!(scene.marks, [m], "carving places no marks");
}

#[test]
fn with_labels_the_left_stick_click_protects_the_selected_structure_not_the_ao_method() {
    let mut ix = Interaction::new(InteractionSettings {
        ao_methods: 3,
        ..InteractionSettings::default()
    });
    let mut scene = Scene {
        structures: vec![1.0, 1.0],
        protected: vec![false, false],
        ..Scene::default()
    };
    let buttons = |click_left: bool, next: bool, click_right: bool| {
        let (mut l, mut r) = (idle_left(), idle_right());
        l.buttons.stick_click = click_left;
        l.buttons.primary = next;
        r.buttons.stick_click = click_right;
        (l, r)
    };
    let mut i = run(&mut ix, &mut scene, 0, [buttons(true, false, false)]);
    assert_eq!(scene.protected, [true, false]);
    assert_eq!(scene.ao_index, 0, "the left click is the menu's");
    i = run(&mut ix, &mut scene, i, [buttons(false, true, false)]);
    i = run(&mut ix, &mut scene, i, [buttons(true, false, false)]);
    assert_eq!(scene.protected, [true, true]);
    i = run(&mut ix, &mut scene, i, [buttons(false, false, false)]);
    i = run(&mut ix, &mut scene, i, [buttons(true, false, false)]);
    assert_eq!(scene.protected, [true, false], "a second click unprotects");
    run(&mut ix, &mut scene, i, [buttons(false, false, true)]);
    assert_eq!(
        scene.ao_index, 1,
        "the right click still cycles the AO method"
    );
    // Without labels the left click cycles the AO method as before.
    let mut plain = Scene::default();
    let mut ix = Interaction::new(InteractionSettings {
        ao_methods: 3,
        ..InteractionSettings::default()
    });
    run(&mut ix, &mut plain, 0, [buttons(true, false, false)]);
    assert_eq!(plain.ao_index, 1);
    assert!(plain.protected.is_empty());
}

#[test]
fn menu_cycles_the_transfer_function_presets() {
    let mut ix = Interaction::new(InteractionSettings {
        tf_presets: 3,
        ..InteractionSettings::default()
    });
    let mut scene = Scene::default();
    let menu = |l: bool, r: bool| {
        let (mut a, mut b) = (idle_left(), idle_right());
        a.buttons.menu = l;
        b.buttons.menu = r;
        (a, b)
    };
    let mut i = 0;
    let mut seen = vec![];
    for (l, r) in [(true, false), (false, true), (true, true), (false, false)] {
        i = run(&mut ix, &mut scene, i, [menu(l, r), menu(l, r)]);
        seen.push(scene.tf_index);
        i = run(&mut ix, &mut scene, i, [menu(false, false)]);
    }
    assert_eq!(seen, [1, 2, 0, 0], "either hand, once per press, modulo 3");

    // No presets: the menu does nothing (and does not divide by zero).
    let mut ix = Interaction::new(InteractionSettings {
        tf_presets: 0,
        ..InteractionSettings::default()
    });
    run(&mut ix, &mut scene, 0, [menu(true, true)]);
    assert_eq!(scene.tf_index, 0);
}

#[test]
fn the_stick_click_cycles_the_ao_methods_and_leaves_the_tf_alone() {
    let mut ix = Interaction::new(InteractionSettings {
        tf_presets: 3,
        ao_methods: 4,
        ..InteractionSettings::default()
    });
    let mut scene = Scene::default();
    let click = |l: bool, r: bool| {
        let (mut a, mut b) = (idle_left(), idle_right());
        a.buttons.stick_click = l;
        b.buttons.stick_click = r;
        (a, b)
    };
    let mut i = 0;
    let mut seen = vec![];
    for (l, r) in [
        (true, false),
        (false, true),
        (true, true),
        (false, true),
        (true, false),
    ] {
        // Held for two frames: one press.
        i = run(&mut ix, &mut scene, i, [click(l, r), click(l, r)]);
        seen.push(scene.ao_index);
        i = run(&mut ix, &mut scene, i, [click(false, false)]);
    }
    assert_eq!(
        seen,
        [1, 2, 3, 0, 1],
        "either hand, once per press, modulo 4"
    );
    assert_eq!(scene.tf_index, 0);

    // One method: nothing to cycle.
    let mut ix = Interaction::new(InteractionSettings {
        ao_methods: 0,
        ..InteractionSettings::default()
    });
    let mut scene = Scene::default();
    run(&mut ix, &mut scene, 0, [click(true, true)]);
    assert_eq!(scene.ao_index, 0);
}

#[test]
fn nonsense_input_is_ignored_without_panicking() {
    let mut ix = Interaction::new(InteractionSettings {
        smoothing: Some(SUGGESTED_SMOOTHING_HZ),
        ..InteractionSettings::default()
    });
    let mut scene = Scene::default();
    let r = Vec3::new(0.1, 1.3, -0.4);
    let mut i = run(&mut ix, &mut scene, 0, [(idle_left(), at(r))]);
    let good = scene.tools[RIGHT_TOOL];
    let v0 = scene.volume;
    let nan = Vec3::splat(f32::NAN);
    let bad_hands = [
        at(nan),
        hand(r, Quat::from_xyzw(f32::NAN, 0.0, 0.0, 1.0)),
        hand(r, Quat::from_xyzw(0.0, 0.0, 0.0, 0.0)),
        at(Vec3::new(f32::INFINITY, 0.0, 0.0)),
    ];
    for b in bad_hands {
        let mut b = gripping(b);
        b.buttons.trigger = f32::NAN;
        b.buttons.thumbstick.y = f32::NAN;
        i = run(&mut ix, &mut scene, i, [(gripping(b), b)]);
        assert!(!ix.is_tracked(RIGHT));
        assert_eq!(scene.tools[RIGHT_TOOL], good);
        assert_eq!(scene.volume, v0);
    }
    // A NaN time is a frame without time; a scene with a nonsense size is repaired.
    let mut h = at(r);
    h.buttons.thumbstick.y = 1.0;
    ix.update(&frame(f64::NAN, idle_left(), h), &mut scene);
    assert_eq!(ix.last_dt(), 0.0);
    scene.tools[RIGHT_TOOL].size = f32::NAN;
    ix.update(&frame(i as f64 / FPS, idle_left(), h), &mut scene);
    assert!(scene.tools[RIGHT_TOOL].size.is_finite());

    // Nonsense settings do not panic either.
    let mut ix = Interaction::new(InteractionSettings {
        min_size: 1.0,
        max_size: 0.0,
        min_scale: f32::NAN,
        max_scale: -1.0,
        stick_dead_zone: 7.0,
        resize_rate: f32::INFINITY,
        smoothing: Some(-3.0),
        ..InteractionSettings::default()
    });
    let mut scene = Scene::default();
    run(
        &mut ix,
        &mut scene,
        0,
        (0..5).map(|k| {
            let mut r = gripping(at(Vec3::X * 0.1 * k as f32));
            r.buttons.thumbstick.y = 1.0;
            (gripping(at(Vec3::ZERO)), r)
        }),
    );
}

/// RMS distance of points from their mean.
fn rms_spread(points: &[Vec3]) -> f32 {
    let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
    let ms = points.iter().map(|p| p.distance_squared(mean)).sum::<f32>() / points.len() as f32;
    ms.sqrt()
}

fn tool_positions(settings: InteractionSettings, frames: &[FrameInput]) -> Vec<Vec3> {
    let mut ix = Interaction::new(settings);
    let mut scene = Scene::default();
    frames
        .iter()
        .map(|f| {
            ix.update(f, &mut scene);
            scene.tools[RIGHT_TOOL].pose.position
        })
        .collect()
}

fn smoothed() -> InteractionSettings {
    InteractionSettings {
        smoothing: Some(SUGGESTED_SMOOTHING_HZ),
        ..InteractionSettings::default()
    }
}

#[test]
fn tremor_smoothing_reduces_jitter() {
    let p = ScriptParams {
        frames: 360,
        ..ScriptParams::default()
    };
    let frames = generate(ScriptKind::Tremor, &p);
    // Skip the first half second, where the filter settles on the hand.
    let raw = tool_positions(InteractionSettings::default(), &frames)[45..].to_vec();
    let smooth = tool_positions(smoothed(), &frames)[45..].to_vec();
    let (r, s) = (rms_spread(&raw), rms_spread(&smooth));
    assert!(r > 0.2e-3, "the script trembles: {r}");
    assert!(s <= 0.5 * r, "smoothed {s} vs raw {r}");
    // In fact a lot better than half: a 1 Hz cutoff against 8-12 Hz tremor.
    assert!(s <= 0.25 * r, "smoothed {s} vs raw {r}");
}

#[test]
fn smoothing_follows_a_deliberate_move() {
    // Still for 0.5 s, a 10 cm move over 0.5 s (eased), still for 1 s.
    let start = Vec3::new(0.1, 1.3, -0.4);
    let at_time = |t: f64| {
        let s = ((t - 0.5) / 0.5).clamp(0.0, 1.0) as f32;
        let eased = s * s * (3.0 - 2.0 * s);
        start + Vec3::X * 0.1 * eased
    };
    let frames: Vec<FrameInput> = (0..180)
        .map(|i| {
            let t = i as f64 / FPS;
            frame(t, idle_left(), at(at_time(t)))
        })
        .collect();
    let offset = InteractionSettings::default().tool_offset;
    let raw = tool_positions(InteractionSettings::default(), &frames);
    let smooth = tool_positions(smoothed(), &frames);
    for (i, f) in frames.iter().enumerate() {
        let truth = at_time(f.time) + offset;
        assert!(close(raw[i], truth, 1e-6), "off means untouched");
        let lag = smooth[i].distance(truth);
        // About 6 mm at the move's peak speed (0.3 m/s) with the defaults.
        assert!(lag < 0.01, "lag {lag} m at t = {}", f.time);
        if f.time >= 1.0 + 0.2 {
            assert!(lag < 1e-3, "still {lag} m behind at t = {}", f.time);
        }
    }
    let end = smooth.last().unwrap().distance(at_time(2.0) + offset);
    assert!(end < 0.5e-3, "settles: {end}");
}

#[test]
fn smoothing_also_steadies_the_orientation() {
    // A still hand whose orientation trembles 0.2 degrees at 10 Hz: the tool 8 cm ahead
    // swings; smoothed, much less.
    let g = Vec3::new(0.1, 1.3, -0.4);
    let frames: Vec<FrameInput> = (0..270)
        .map(|i| {
            let t = i as f64 / FPS;
            let a = 0.0035 * (TAU * 10.0 * t as f32).sin();
            frame(t, idle_left(), hand(g, Quat::from_rotation_x(a)))
        })
        .collect();
    let raw = rms_spread(&tool_positions(InteractionSettings::default(), &frames)[45..]);
    let smooth = rms_spread(&tool_positions(smoothed(), &frames)[45..]);
    assert!(smooth < 0.25 * raw, "smoothed {smooth} vs raw {raw}");
}

/// Every script through the interaction: the scenes it gives are what the script's
/// description promises.
#[test]
fn scripts_replay_to_plausible_scenes() {
    let p = ScriptParams::default();
    let (c, r) = (p.center, p.radius_m);
    for kind in ScriptKind::ALL {
        for settings in [InteractionSettings::default(), smoothed()] {
            let mut ix = Interaction::new(settings);
            let mut scene = Scene::default();
            let mut scenes = Vec::new();
            for f in generate(kind, &p) {
                ix.update(&f, &mut scene);
                scenes.push(scene.clone());
            }
            let n = scenes.len() as f32;
            let active = |t: usize| {
                scenes
                    .iter()
                    .filter(|s| s.tools.get(t).is_some_and(|t| t.active))
                    .count() as f32
                    / n
            };
            let tool_x = |s: &Scene| s.tools[RIGHT_TOOL].pose.position.x;
            let (first, last) = (&scenes[0], scenes.last().unwrap());
            let unmoved = scenes.iter().all(|s| s.volume == Placement::default());
            match kind {
                ScriptKind::HandPinch => {
                    // The pinch (from 10 %) switched carving on, once.
                    assert!(!scenes[0].tools[RIGHT_TOOL].active, "{kind}");
                    assert!(active(RIGHT_TOOL) > 0.85, "{kind}");
                    assert!(last.tools[RIGHT_TOOL].active, "{kind}");
                    // Tracking lost from 55 % to 70 %: the tool freezes, then follows again.
                    let at = |f: f64| &scenes[(f * (n - 1.0) as f64) as usize];
                    let frozen = at(0.56).tools[RIGHT_TOOL].pose;
                    assert_eq!(at(0.69).tools[RIGHT_TOOL].pose, frozen, "{kind}");
                    assert!(tool_x(last) > frozen.position.x + 0.01, "{kind}");
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::SphereSweep => {
                    assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                    assert!(tool_x(first) < c.x - r / 2.0, "{kind}");
                    assert!(tool_x(last) > c.x + r / 2.0, "{kind}");
                    assert_eq!(scenes[0].tools.len(), 1, "{kind}");
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::BoxPushPull => {
                    assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                    let z: Vec<f32> = scenes.iter().map(|s| s.tools[0].pose.position.z).collect();
                    let zmin = z.iter().copied().fold(f32::MAX, f32::min);
                    assert!(zmin < c.z - r / 2.0 && z[0] > zmin + 1.5 * r, "{kind}");
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::TorusPass => {
                    assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                    for s in &scenes {
                        let t = s.tools[RIGHT_TOOL].pose;
                        let forward = t.orientation * Vec3::NEG_Z;
                        let to_c = (c - t.position).normalize();
                        assert!(forward.dot(to_c) > 0.99, "{kind}: points at the centre");
                    }
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::TwoTools => {
                    assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                    assert!(active(LEFT_TOOL) > 0.9, "{kind}");
                    // The tools point 20 degrees inwards, so at mid-script they meet at
                    // the centre; at the start they are well apart, the left one left.
                    let (lx, rx) = (first.tools[LEFT_TOOL].pose.position.x, tool_x(first));
                    assert!(
                        lx < c.x - r / 2.0 && rx > c.x + r / 2.0,
                        "{kind}: {lx} {rx}"
                    );
                    let s = &scenes[scenes.len() / 2];
                    let gap = s.tools[LEFT_TOOL]
                        .pose
                        .position
                        .distance(s.tools[0].pose.position);
                    assert!(gap < 0.01, "{kind}: the tools meet at mid-script: {gap}");
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::GrabScale => {
                    assert!(active(RIGHT_TOOL) == 0.0, "{kind}");
                    let moved = scenes.iter().any(|s| {
                        s.volume.scale == 1.0
                            && s.volume.center.distance(c) > r / 2.0
                            && s.volume.rotation.angle_between(Quat::IDENTITY) > 0.3
                    });
                    assert!(moved, "{kind}: grabbed, moved and turned before scaling");
                    let scale = last.volume.scale;
                    assert!((scale - 2.0).abs() < 0.05, "{kind}: scale {scale}");
                    assert_eq!(ix.grab_mode(), GrabMode::None, "{kind}: released");
                    let max_step = scenes
                        .windows(2)
                        .map(|w| w[1].volume.center.distance(w[0].volume.center))
                        .fold(0.0, f32::max);
                    assert!(max_step < 0.01, "{kind}: the volume jumped {max_step} m");
                }
                ScriptKind::TfSwitch => {
                    assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                    let tf: Vec<usize> = scenes.iter().map(|s| s.tf_index).collect();
                    let switches = tf.windows(2).filter(|w| w[0] != w[1]).count();
                    assert_eq!((tf[0], *tf.last().unwrap(), switches), (0, 1, 1), "{kind}");
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::CarveLoop => {
                    // Carving from the first frame, and the tool never stands still.
                    assert!(active(RIGHT_TOOL) == 1.0, "{kind}");
                    for w in scenes.windows(2) {
                        let (a, b) = (w[0].tools[RIGHT_TOOL].pose, w[1].tools[RIGHT_TOOL].pose);
                        assert!(a.position.distance(b.position) > 1e-4, "{kind}");
                    }
                    assert!(unmoved, "{kind}");
                }
                ScriptKind::Tremor => {
                    assert!(active(RIGHT_TOOL) > 0.9, "{kind}");
                    let expect = c + settings.tool_offset;
                    for s in &scenes {
                        let d = s.tools[RIGHT_TOOL].pose.position.distance(expect);
                        assert!(d < 2e-3, "{kind}: {d}");
                    }
                    assert!(unmoved, "{kind}");
                }
            }
            // Same frames, same scenes.
            let mut again = Interaction::new(settings);
            let mut scene2 = Scene::default();
            for f in generate(kind, &p) {
                again.update(&f, &mut scene2);
            }
            assert_eq!(&scene2, last, "{kind}: deterministic");
        }
    }
}
