//! Tools and hands over the volume, on lavapipe with validation on: a tool tints where it
//! projects and nowhere else, hides behind opaque bone, and the scene's overlay lists what the
//! hands and tools are.

use crate::common;

use cao_xr::clip::Shape;
use cao_xr::gpu::Gpu;
use cao_xr::render::overlay::colors;
use cao_xr::render::{
    scene_overlay, FrameViews, OverlayItem, OverlayMesh, OverlayRenderer, RenderSettings, Renderer,
    StereoImage, StereoTarget, VolumeTextures,
};
use cao_xr::scene::{Scene, Tool, ToolMode};
use cao_xr::space::{world_from_tex, Fov, Placement, Pose, View};
use cao_xr::volume::transfer::TransferFunction;

use glam::{Quat, Vec3};

const W: u32 = 128;
const HALF: f32 = 0.2; // half field of view, radians
const DIST: f32 = 0.6;
const IPD: f32 = 0.064;

fn views() -> [View; 2] {
    let fov = Fov {
        angle_left: -HALF,
        angle_right: HALF,
        angle_up: HALF,
        angle_down: -HALF,
    };
    let centre = Placement::default().center;
    [-0.5f32, 0.5].map(|s| View {
        pose: Pose {
            position: centre + Vec3::new(s * IPD, 0.0, DIST),
            orientation: Quat::IDENTITY,
        },
        fov,
    })
}

/// Renders the ball, then each overlay in `overlays` (an empty list still runs the pass), each
/// into its own frame; returns one image per overlay.
fn render(gpu: &Gpu, overlays: &[Vec<OverlayItem>]) -> Vec<StereoImage> {
    let vol = common::ball();
    let tf = TransferFunction::preset("ct-bone").unwrap();
    let tex = VolumeTextures::new(gpu, &vol, &tf).unwrap();
    let mut renderer = Renderer::new(gpu).unwrap();
    let mut overlay = OverlayRenderer::new(gpu).unwrap();
    let target = StereoTarget::new(gpu, W, W).unwrap();
    let v = views();
    let frame = FrameViews::new(&v, world_from_tex(&vol, &Placement::default()));
    let settings = RenderSettings::default();
    tex.prepare(&settings).unwrap();
    let images = overlays
        .iter()
        .map(|items| {
            gpu.submit_and_wait(|cmd| {
                renderer
                    .record(cmd, &target, &tex, &frame, &settings)
                    .unwrap();
                overlay.record(cmd, &target, &v, items).unwrap();
                target.cmd_finish(cmd);
            })
            .unwrap();
            target.read_back(gpu).unwrap()
        })
        .collect();
    drop((tex, renderer, overlay, target));
    common::assert_no_validation_messages(gpu);
    images
}

fn sphere_tool(centre: Vec3, radius: f32, mode: ToolMode, active: bool) -> Tool {
    Tool {
        shape: Shape::Sphere,
        pose: Pose {
            position: centre,
            orientation: Quat::IDENTITY,
        },
        size: radius,
        mode,
        active,
    }
}

/// Projected centre (pixels) and an upper bound of the projected radius (pixels) of a sphere.
fn project(view: &View, centre: Vec3, radius: f32) -> (f32, f32, f32) {
    let c = view.view_proj() * centre.extend(1.0);
    let x = (c.x / c.w + 1.0) * 0.5 * W as f32;
    let y = (c.y / c.w + 1.0) * 0.5 * W as f32;
    let d = (centre - view.pose.position).length();
    // Half-angle asin(r/d), off-axis stretch bounded by the 1/cos^2 of the field's edge.
    let r = (radius / d).asin().tan() / HALF.tan() * 0.5 * W as f32 / HALF.cos().powi(2);
    (x, y, r)
}

fn px(img: &StereoImage, eye: usize, x: usize, y: usize) -> [u8; 4] {
    let i = 4 * (x + y * W as usize);
    img.rgba[eye][i..i + 4].try_into().unwrap()
}

fn dist3(a: [u8; 4], c: [f32; 4]) -> f32 {
    (0..3)
        .map(|k| (a[k] as f32 / 255.0 - c[k]).powi(2))
        .sum::<f32>()
        .sqrt()
}

#[test]
fn a_tool_in_front_tints_where_it_projects_and_nowhere_else() {
    let gpu = common::gpu();
    let centre = Placement::default().center + Vec3::new(0.004, 0.003, 0.1);
    let radius = 0.01;
    let tool = sphere_tool(centre, radius, ToolMode::Carve, true);
    let scene = Scene {
        tools: vec![tool],
        ..Default::default()
    };
    let items = scene_overlay(&scene, &[None, None], Vec3::ZERO, &[]);
    assert_eq!(items.len(), 1);
    let imgs = render(&gpu, &[Vec::new(), items.clone(), items]);
    let (base, over) = (&imgs[0], &imgs[1]);
    assert!(
        imgs[1] == imgs[2],
        "the same overlay twice gives different images"
    );
    assert_eq!(base.depth, over.depth, "the overlay must not write depth");
    for (eye, view) in views().iter().enumerate() {
        let (cx, cy, r) = project(view, centre, radius);
        let (mut inside, mut changed_inside) = (0, 0);
        for y in 0..W as usize {
            for x in 0..W as usize {
                let d = ((x as f32 + 0.5 - cx).powi(2) + (y as f32 + 0.5 - cy).powi(2)).sqrt();
                let (a, b) = (px(base, eye, x, y), px(over, eye, x, y));
                if d > r + 1.5 {
                    assert_eq!(
                        a, b,
                        "eye {eye}: pixel ({x}, {y}) far from the tool changed"
                    );
                } else if d < r - 1.5 {
                    inside += 1;
                    changed_inside += (a != b) as usize;
                }
            }
        }
        assert!(
            inside > 50,
            "eye {eye}: the tool projects to {inside} pixels"
        );
        assert_eq!(
            changed_inside, inside,
            "eye {eye}: every pixel well inside the tool's projection is tinted"
        );
        let (a, b) = (
            px(base, eye, cx as usize, cy as usize),
            px(over, eye, cx as usize, cy as usize),
        );
        assert!(
            dist3(b, colors::CARVING) < dist3(a, colors::CARVING),
            "eye {eye}: centre {a:?} -> {b:?} does not move towards the carving colour"
        );
    }
}

#[test]
fn a_tool_behind_the_ball_is_hidden_by_it_and_drawn_around_it() {
    let gpu = common::gpu();
    // 30 mm sphere 70 mm behind the ball's centre: its front (40 mm behind the centre) is
    // behind the whole ball, its silhouette is wider than the ball's.
    let centre = Placement::default().center + Vec3::new(0.0, 0.0, -0.07);
    let radius = 0.03;
    let scene = Scene {
        tools: vec![sphere_tool(centre, radius, ToolMode::Carve, false)],
        ..Default::default()
    };
    let items = scene_overlay(&scene, &[None, None], Vec3::ZERO, &[]);
    let imgs = render(&gpu, &[Vec::new(), items]);
    let (base, over) = (&imgs[0], &imgs[1]);
    for eye in 0..2 {
        let (mut covered, mut around) = (0, 0);
        for y in 0..W as usize {
            for x in 0..W as usize {
                let i = x + y * W as usize;
                let (a, b) = (px(base, eye, x, y), px(over, eye, x, y));
                if base.depth[eye][i] < 1.0 {
                    covered += 1;
                    assert_eq!(a, b, "eye {eye}: ({x}, {y}) is bone, yet the tool shows");
                } else if a != b {
                    around += 1;
                }
            }
        }
        assert!(
            covered > 120,
            "eye {eye}: the ball covers only {covered} pixels"
        );
        assert!(
            around > 200,
            "eye {eye}: the tool shows around the ball in {around} pixels"
        );
    }
    // Beside the ball (22 mm left of its centre, within the tool's silhouette, which parallax
    // shifts left in the left eye) the tool is drawn.
    let view = &views()[0];
    let side = Placement::default().center + Vec3::new(-0.022, 0.0, 0.0);
    let (x, y, _) = project(view, side, 0.0);
    let (a, b) = (
        px(base, 0, x as usize, y as usize),
        px(over, 0, x as usize, y as usize),
    );
    assert_ne!(a, b, "beside the ball the tool must show");
    assert!(dist3(b, colors::IDLE) < dist3(a, colors::IDLE));
}

#[test]
fn scene_overlay_lists_tools_tracked_hands_and_the_right_offset() {
    let centre = Placement::default().center;
    let scene = Scene {
        tools: vec![
            sphere_tool(centre, 0.02, ToolMode::Carve, true),
            Tool {
                shape: Shape::Torus,
                ..sphere_tool(centre + Vec3::X * 0.1, 0.03, ToolMode::Probe, false)
            },
        ],
        ..Default::default()
    };
    let left = Pose {
        position: Vec3::new(-0.2, 1.2, -0.3),
        orientation: Quat::IDENTITY,
    };
    let right = Pose {
        position: Vec3::new(0.2, 1.2, -0.3),
        orientation: Quat::from_rotation_y(0.5),
    };
    let offset = Vec3::new(0.0, 0.0, -0.08);
    let count = |items: &[OverlayItem], m: fn(&OverlayMesh) -> bool| {
        items.iter().filter(|i| m(&i.mesh)).count()
    };
    let tools = |m: &OverlayMesh| matches!(m, OverlayMesh::Tool(_));
    let markers = |m: &OverlayMesh| matches!(m, OverlayMesh::Marker);
    let rods = |m: &OverlayMesh| matches!(m, OverlayMesh::Rod);

    let both = scene_overlay(&scene, &[Some(left), Some(right)], offset, &[]);
    assert_eq!(both.len(), 5, "2 tools + 2 markers + 1 offset rod");
    assert_eq!(
        (
            count(&both, tools),
            count(&both, markers),
            count(&both, rods)
        ),
        (2, 2, 1)
    );
    assert_eq!(both[0].mesh, OverlayMesh::Tool(Shape::Sphere));
    assert_eq!(both[1].mesh, OverlayMesh::Tool(Shape::Torus));
    assert_ne!(
        both[0].color, both[1].color,
        "carving and idle probe differ"
    );
    // Tools sit at their pose, at their size.
    let m = both[1].model;
    assert!((m.transform_point3(Vec3::ZERO) - scene.tools[1].pose.position).length() < 1e-6);
    assert!((m.transform_vector3(Vec3::X).length() - 0.03).abs() < 1e-6);
    // The rod runs from the right grip to the tool centre, offset ahead in the grip's axes.
    let rod = both.iter().find(|i| i.mesh == OverlayMesh::Rod).unwrap();
    let tool_centre = right.position + right.orientation * offset;
    let ends = [-Vec3::Z, Vec3::Z].map(|p| rod.model.transform_point3(p));
    assert!((ends[0] - right.position).length() < 1e-5, "{ends:?}");
    assert!((ends[1] - tool_centre).length() < 1e-5, "{ends:?}");
    // Markers sit at the grips.
    let marker_at: Vec<Vec3> = both
        .iter()
        .filter(|i| i.mesh == OverlayMesh::Marker)
        .map(|i| i.model.transform_point3(Vec3::ZERO))
        .collect();
    assert_eq!(marker_at, vec![left.position, right.position]);

    let right_only = scene_overlay(&scene, &[None, Some(right)], offset, &[]);
    assert_eq!(
        (
            count(&right_only, tools),
            count(&right_only, markers),
            count(&right_only, rods)
        ),
        (2, 1, 1)
    );
    let left_only = scene_overlay(&scene, &[Some(left), None], offset, &[]);
    assert_eq!(
        (
            count(&left_only, tools),
            count(&left_only, markers),
            count(&left_only, rods)
        ),
        (2, 1, 0),
        "the offset belongs to the right hand"
    );
    let none = scene_overlay(&scene, &[None, None], offset, &[]);
    assert_eq!(none.len(), 2, "untracked hands draw nothing");
    // A tool inside a safety margin is drawn in the warning colour, the others as they are.
    let warned = scene_overlay(&scene, &[None, None], offset, &[1]);
    assert_eq!(warned[1].color, cao_xr::render::colors::WARNING);
    assert_eq!(warned[0].color, none[0].color);
    assert_ne!(none[1].color, cao_xr::render::colors::WARNING);
    assert!(scene_overlay(&Scene::default(), &[None, None], offset, &[]).is_empty());
}

#[test]
fn a_tracked_hand_pinches_carves_and_its_joints_are_drawn_and_replay_identically() {
    use cao_xr::app::frame_loop::FrameLoop;
    use cao_xr::input::{
        generate, read_stream, write_script, InteractionSettings, ScriptKind, ScriptParams,
    };
    use std::sync::Arc;
    let gpu = common::gpu();
    let vol = Arc::new(cao_xr::volume::phantom::head(24));
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let lao = cao_xr::ao::LaoParams {
        rays: 6,
        steps: 4,
        step_mm: 4.0,
    };
    let p = ScriptParams {
        frames: 40,
        ..ScriptParams::default()
    };
    // Through the pose stream: the joints are recorded (version 3) and read back.
    let path = std::env::temp_dir().join(format!("cao-hand-pinch-{}.jsonl", std::process::id()));
    write_script(ScriptKind::HandPinch, &p, &path).unwrap();
    let (header, frames) = read_stream(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!(header.version, cao_xr::input::stream::VERSION);
    assert_eq!(
        frames,
        generate(ScriptKind::HandPinch, &p),
        "the joints survive the stream"
    );
    let run = |strip: bool| {
        let mut fl = FrameLoop::new(
            &gpu,
            Arc::clone(&vol),
            vec![tf.clone()],
            lao,
            (48, 48),
            InteractionSettings::default(),
            false,
        )
        .unwrap();
        frames
            .iter()
            .map(|f| {
                let mut f = *f;
                if strip {
                    f.joints = [None; 2];
                }
                let out = fl.frame(&f).unwrap();
                (out.image, out.stats.metrics.recomputed)
            })
            .collect::<Vec<_>>()
    };
    let (a, b, bare) = (run(false), run(false), run(true));
    assert!(
        a.iter().zip(&b).all(|(x, y)| x.0 == y.0),
        "replays render identically"
    );
    assert!(a.iter().any(|f| f.1 > 0), "the pinch carved");
    // Joints are drawn where the hand is tracked (where they are not inside the volume, which
    // hides them, as it hides a tool), and only there.
    let (mut tracked, mut drawn) = (0, 0);
    for (i, ((img, _), (plain, _))) in a.iter().zip(&bare).enumerate() {
        if frames[i].joints[1].is_some() {
            tracked += 1;
            drawn += (img != plain) as usize;
        } else {
            assert!(img == plain, "frame {i}: no joints, nothing drawn");
        }
    }
    assert!(
        tracked > 20 && drawn * 2 > tracked,
        "joints drawn in {drawn} of {tracked} frames"
    );
    common::assert_no_validation_messages(&gpu);
}

/// An empty (clear) anisotropic raw volume written into `dir`, 20 x 16 x 12 int16 voxels of
/// 0.7 x 0.9 x 2.5 mm (identity directions, origin 0: LPS = index * spacing), and the arguments
/// that load it, with a cheap LAO: only what is drawn over it shows.
fn clear_volume(dir: &std::path::Path) -> Vec<String> {
    let raw = dir.join("v.raw");
    std::fs::write(&raw, vec![0u8; 2 * 20 * 16 * 12]).unwrap();
    let raw = raw.to_str().unwrap();
    [
        raw,
        "--raw-dims",
        "20,16,12",
        "--raw-type",
        "i16",
        "--raw-spacing",
        "0.7,0.9,2.5",
    ]
    .into_iter()
    .chain(["--rays", "6", "--steps", "2"])
    .map(String::from)
    .collect()
}

#[test]
fn markups_from_slicer_are_drawn_where_they_are_and_rulers_read_their_length_in_mm() {
    use cao_xr::volume::markups::{MarkupLine, MarkupPoint, Markups};
    use glam::DVec3;
    // An anisotropic volume: a ruler between two voxel centres reads the length in mm.
    let dir = common::scratch("overlay", "markups");
    let volume = clear_volume(&dir);
    let (spacing, a, b) = ([0.7, 0.9, 2.5], [2.0, 3.0, 1.0], [14.0, 11.0, 9.0]);
    // raw volumes have identity directions and the origin at 0: LPS = index * spacing
    let lps = |i: [f64; 3]| DVec3::new(i[0] * spacing[0], i[1] * spacing[1], i[2] * spacing[2]);
    let want = lps(a).distance(lps(b));
    let ruler = Markups {
        points: vec![],
        lines: vec![MarkupLine {
            label: "span".into(),
            ends: [lps(a), lps(b)],
        }],
    };
    let file = dir.join("r.mrk.json");
    ruler.write(&file).unwrap();
    // The raw volume rendered into `out`, with `extra` arguments; its stdout.
    let render = |out: &std::path::Path, extra: &[&str]| {
        let mut args = vec!["render"];
        args.extend(volume.iter().map(String::as_str));
        args.extend(["--size", "16x16", "--out", out.to_str().unwrap()]);
        args.extend_from_slice(extra);
        String::from_utf8_lossy(&common::run_cao_ok(&args).stdout).to_string()
    };
    let (marked, plain) = (dir.join("r"), dir.join("plain"));
    let text = render(&marked, &["--markups", file.to_str().unwrap()]);
    assert!(
        text.contains(&format!("rulers: span {want:.1} mm")),
        "{want} mm: {text}"
    );
    // render draws the markups (not the tools): the same render without them differs.
    render(&plain, &[]);
    let png = |d: &std::path::Path| std::fs::read(d.join("left.png")).unwrap();
    assert!(png(&marked) != png(&plain), "render drew no ruler");
    // A point in front of the head is drawn, in the markup colour, in the frame loop's overlay.
    let gpu = common::gpu();
    let vol = std::sync::Arc::new(cao_xr::volume::phantom::head(32));
    let mut fl = cao_xr::app::frame_loop::FrameLoop::new(
        &gpu,
        vol.clone(),
        vec![TransferFunction::preset("ct-skin").unwrap()],
        cao_xr::ao::LaoParams {
            rays: 6,
            steps: 2,
            step_mm: 4.0,
        },
        (256, 256),
        cao_xr::input::InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.settings.jitter = false;
    let views = cao_xr::space::default_stereo_views(&vol, &Placement::default(), 0.064);
    let input = cao_xr::input::FrameInput::without_hands(0.0, views);
    let plain = fl.frame(&input).unwrap().image;
    // 150 mm anterior of the centre voxel (LPS -y is anterior): between the face and the eyes.
    let centre = vol.origin + DVec3::splat(16.0 * vol.spacing[0]);
    fl.markups = Markups {
        points: vec![MarkupPoint {
            label: "p".into(),
            lps: centre - DVec3::new(0.0, 150.0, 0.0),
        }],
        lines: vec![],
    };
    let marked = fl.frame(&input).unwrap().image;
    let changed: Vec<usize> = (0..plain.rgba[0].len() / 4)
        .filter(|&p| plain.rgba[0][4 * p..4 * p + 4] != marked.rgba[0][4 * p..4 * p + 4])
        .collect();
    assert!(!changed.is_empty(), "the point is not drawn");
    // near the middle of the picture, where the centre's line of sight is
    let (x, y) = (changed[0] % 256, changed[0] / 256);
    assert!(
        (96..160).contains(&x) && (96..160).contains(&y),
        "drawn at {x},{y}"
    );
    assert!(
        changed.len() < 400,
        "{} pixels changed for a small point",
        changed.len()
    );
    common::assert_no_validation_messages(&gpu);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A ruler drawn in a replayed session with a measuring tool: the replay writes it to
/// `--save-markups` with its length in mm, and the picture writes that length beside it.
#[test]
fn a_ruler_drawn_with_the_measuring_tool_is_saved_for_slicer_and_its_length_is_written_beside_it() {
    use cao_xr::input::{pose, Buttons, FrameInput, HandInput, PoseStreamWriter, StreamHeader};
    use cao_xr::volume::markups::Markups;
    let dir = common::scratch("overlay", "measure");
    let volume = clear_volume(&dir);
    // Frames: the right hand (a script's grip is its tool's centre) cycles carve -> probe ->
    // measure, presses the trigger at a, drags to b and lets go there.
    let (a, b) = (Vec3::new(-0.03, 1.39, -0.5), Vec3::new(0.03, 1.40, -0.5));
    let head = pose(Vec3::new(0.0, 1.4, 0.0), Quat::IDENTITY);
    let views = FrameInput::head_views(head, IPD, cao_xr::space::symmetric_fov(0.25));
    let hand = |p: Vec3, trigger: f32, secondary: bool| {
        let grip = pose(p, Quat::IDENTITY);
        HandInput {
            tracked: true,
            grip,
            aim: grip,
            buttons: Buttons {
                trigger,
                secondary,
                ..Buttons::default()
            },
        }
    };
    let mut steps = vec![(a, 0.0, false)];
    steps.extend([
        (a, 0.0, true),
        (a, 0.0, false),
        (a, 0.0, true),
        (a, 0.0, false),
    ]);
    steps.extend((0..=6).map(|k| (a.lerp(b, k as f32 / 6.0), 1.0, false)));
    steps.extend([(b, 0.0, false), (b, 0.0, false)]);
    let stream = dir.join("measure.jsonl");
    let header = StreamHeader::new("script:measure", "a ruler from a to b");
    let mut w = PoseStreamWriter::create(&stream, &header).unwrap();
    for (i, &(p, trigger, secondary)) in steps.iter().enumerate() {
        let mut f = FrameInput::without_hands(i as f64 / 30.0, views);
        f.hands[cao_xr::input::RIGHT] = hand(p, trigger, secondary);
        w.write_frame(&f).unwrap();
    }
    w.finish().unwrap();
    let (out, saved) = (dir.join("out"), dir.join("ruler.mrk.json"));
    let last = steps.len() - 1;
    let replay = |extra: &[&str]| {
        let mut args = vec!["replay", stream.to_str().unwrap()];
        args.extend(volume.iter().map(String::as_str));
        args.extend(["--size", "192x192", "--out", out.to_str().unwrap()]);
        args.extend_from_slice(extra);
        let o = common::run_cao_ok(&args);
        String::from_utf8_lossy(&o.stderr).to_string()
    };
    let log = replay(&["--save-markups", saved.to_str().unwrap()]);
    // 6.08 cm in the world at true size.
    let want = a.distance(b) as f64 * 1e3;
    let m = Markups::read(&saved).unwrap();
    assert_eq!((m.points.len(), m.lines.len()), (0, 1), "{log}");
    assert!(
        (m.lines[0].length_mm() - want).abs() < 0.01,
        "{m:?}, {want} mm"
    );
    assert_eq!(m.lines[0].label, "L-1");
    assert!(log.contains(&format!("L-1 {want:.1} mm")), "{log}");
    // The last frame writes "60.8 mm" in near-white above the ruler's middle; the clear volume
    // leaves the rest the background.
    let pic = cao_xr::render::compare::read_png(&out.join(format!("frame-{last:05}.png"))).unwrap();
    let white: Vec<(usize, usize)> = (0..pic.width * pic.height)
        .filter(|&p| pic.rgba[4 * p..4 * p + 3].iter().all(|&c| c > 225))
        .map(|p| (p % pic.width, p / pic.width))
        .collect();
    let left: Vec<_> = white.iter().filter(|(x, _)| *x < 192).collect();
    assert!(
        left.len() > 100,
        "{} text pixels in the left eye",
        left.len()
    );
    // Above the middle (at the eye's height: y < 96), centred on it: the middle is half the
    // eyes' distance to the right of the left eye's axis, 0.5 m ahead.
    let px_per_tan = 96.0 / 0.25f64.tan();
    let middle = 96.0 + (IPD as f64 / 2.0 / 0.5) * px_per_tan;
    let x0 = left.iter().map(|p| p.0).min().unwrap() as f64;
    let x1 = left.iter().map(|p| p.0).max().unwrap() as f64 + 1.0;
    assert!(left.iter().all(|p| p.1 < 96), "{left:?}");
    assert!(
        ((x0 + x1) / 2.0 - middle).abs() < 6.0,
        "{x0}..{x1}, middle {middle}"
    );
    // 7 cells of 12 mm, the last ("m") lit to its 7th column.
    let width = (x1 - x0) / px_per_tan * 0.5;
    assert!((0.075..0.085).contains(&width), "{width} m wide");
    // No --save-markups: the replay writes them into its --out.
    replay(&[]);
    assert_eq!(Markups::read(&out.join("markups.mrk.json")).unwrap(), m);
    let _ = std::fs::remove_dir_all(&dir);
}
