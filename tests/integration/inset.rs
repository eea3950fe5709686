//! Issue 25, item 4: a volume larger than the GPU budget is shown downsampled with the box
//! around the tools at full resolution (the inset, `cao_xr::app::inset`). Its AO inside the box
//! is the whole full-resolution volume's, bit for bit, on every frame of a carving; its picture
//! where only the box is seen is the full-resolution one; and with the budget for the whole
//! volume the picture is the full one.

use crate::cao::{frames, read_ao, tool};
use crate::common;

use cao_xr::ao::cao::Mode;
use cao_xr::ao::filtered::{Estimator, FilterInput, FilterParams};
use cao_xr::ao::histogram::HistParams;
use cao_xr::ao::{AoConfig, AoMethod, LaoGpu, LaoParams};
use cao_xr::app::inset::{Cuts, Inset, BUILD_FRAMES, MERGE_FRAMES};
use cao_xr::app::precompute;
use cao_xr::clip::Shape;
use cao_xr::input::FrameInput;
use cao_xr::scene::ToolMode;
use cao_xr::space::{Fov, Placement, Pose};
use cao_xr::volume::phantom;
use cao_xr::volume::transfer::TransferFunction;
use glam::{Quat, Vec3};
use std::sync::Arc;

/// The phantom at 48^3 (voxels of 4.6 mm), its TF and a short LAO: the volume the insets are
/// cut from.
fn small_head() -> (Arc<cao_xr::volume::Volume>, TransferFunction, LaoParams) {
    let params = LaoParams {
        rays: 14,
        steps: 5,
        step_mm: 4.0,
    };
    let tf = TransferFunction::preset("ct-skin").unwrap();
    (Arc::new(phantom::head(48)), tf, params)
}

#[test]
fn the_insets_ao_inside_its_box_is_the_whole_volumes_bit_for_bit_every_frame() {
    let gpu = common::gpu();
    // The box sits against the volume's x = 0 face (its margin cut there) and well inside on y
    // and z.
    let (vol, tf, lao_params) = small_head();
    let gauss = AoMethod::Filter(FilterParams {
        radius_mm: 11.0,
        estimator: Estimator::Gauss,
        input: FilterInput::Opacity,
    });
    let placement = Placement::default();
    let lao = LaoGpu::new(&gpu).unwrap();
    // Cut under LAO, then switched to the filter, whose reach (and margin) is wider.
    let mut inset = Inset::around(
        &gpu,
        vol.clone(),
        (AoConfig::new(AoMethod::Lao, lao_params), tf.clone()),
        ([20, 16, 24], [12.0, 30.0, 24.0]),
    )
    .unwrap();
    // The local histograms' box is their direct sums (the definition the clusters
    // approximate), binned over the whole's range: the whole's direct AO and E.
    let hist = |clusters| {
        AoMethod::Histogram(HistParams {
            radius_mm: 10.0,
            bins: 16,
            clusters,
            hemispheres: true,
        })
    };
    for (method, at_full) in [
        (AoMethod::Lao, AoMethod::Lao),
        (gauss, gauss),
        (hist(64), hist(0)),
    ] {
        let ao = AoConfig::new(method, lao_params);
        let full = AoConfig::new(at_full, lao_params);
        let mut whole = whole_cao(&gpu, &lao, &vol, (&tf, &full));
        inset.set_method(&gpu, (ao, tf.clone())).unwrap();
        let margin = (whole.reach_mm() / vol.spacing[1]).ceil() as usize;
        let (lo, _) = inset.inner_box().unwrap();
        assert!(
            lo[1] - inset.crop_box().unwrap().0[1] > margin,
            "{method:?}: the margin holds the reach"
        );
        let (crop_lo, _) = inset.crop_box().unwrap();
        assert_eq!(
            crop_lo[0], 0,
            "{method:?}: the margin is cut by the volume's face"
        );
        assert!(crop_lo[1] > 0 && crop_lo[2] > 0, "{method:?}: {crop_lo:?}");
        // The box holds occluded voxels on the frames (the comparison is not of open space).
        assert!(carve_both(&vol, &mut whole, &mut inset) > 0, "{method:?}");
    }
    // With no tool cutting, the box goes to a tool a hand holds inside the volume (off by
    // more than a quarter of the box here, and before where the eyes look), and stays for one
    // outside it while the eyes look away.
    let inset = Inset::around(
        &gpu,
        vol.clone(),
        (AoConfig::new(AoMethod::Lao, lao_params), tf.clone()),
        ([16, 16, 16], [24.0; 3]),
    )
    .unwrap();
    let held = |offset: Vec3| {
        let mut t = tool(
            Shape::Sphere,
            placement.center + offset,
            Quat::IDENTITY,
            0.02,
            ToolMode::Carve,
        );
        t.active = false;
        t
    };
    // Eyes half a metre in front of the volume, 5 cm to its side, looking at it; and turned away.
    let eyes = |turn: f32| {
        let head = Pose {
            position: placement.center + Vec3::new(0.05, 0.0, 0.5),
            orientation: Quat::from_rotation_y(turn),
        };
        let fov = Fov {
            angle_left: -0.5,
            angle_right: 0.5,
            angle_up: 0.5,
            angle_down: -0.5,
        };
        FrameInput::head_views(head, 0.064, fov)
    };
    let (looking, away) = (eyes(0.0), eyes(std::f32::consts::PI));
    // Where the one box there is goes (None: it stays).
    let first = |cuts: Cuts| {
        let cuts = cuts.cuts;
        assert!(cuts.len() <= 1, "{cuts:?}: one place, one box");
        cuts.first().map(|&(b, c)| {
            assert_eq!(b, 0, "{cuts:?}");
            c
        })
    };
    let near_corner = first(inset.wants_cuts(
        (&[held(Vec3::splat(0.07))], &looking, None),
        &vol,
        &placement,
    ));
    let centre = near_corner.expect("a held tool inside the volume moves the box");
    assert!(
        centre.iter().all(|&c| !(12.0..=36.0).contains(&c)),
        "{centre:?}"
    );
    // Two hands far apart (more than the box): the box goes around the first, not between them,
    // and a second box is asked for around the other.
    let apart = [held(Vec3::splat(0.07)), held(Vec3::splat(-0.07))];
    let two = inset
        .wants_cuts((&apart, &looking, None), &vol, &placement)
        .cuts;
    assert_eq!(two.len(), 2, "two tools far apart: {two:?}");
    assert_eq!(two[0], (0, centre), "two tools far apart");
    assert_eq!(two[1].0, 1, "{two:?}: a new box");
    // On the other side of the volume's centre on every axis, as far out.
    let opposite = |c: [f64; 3]| (0..3).all(|a| (c[a] - 24.0) * (centre[a] - 24.0) < -144.0);
    assert!(
        opposite(two[1].1),
        "{two:?}: the second box is around the other tool"
    );
    // Two hands close together (within half the box): one box around both, on the first's
    // side.
    let close = [held(Vec3::splat(0.07)), held(Vec3::splat(0.06))];
    let one = first(inset.wants_cuts((&close, &looking, None), &vol, &placement));
    let same_side = |c: [f64; 3]| (0..3).all(|a| (c[a] - 24.0) * (centre[a] - 24.0) > 100.0);
    assert!(one.is_some_and(same_side), "{one:?}");
    let outside = first(inset.wants_cuts(
        (&[held(Vec3::new(0.4, 0.0, 0.0))], &away, None),
        &vol,
        &placement,
    ));
    assert_eq!(outside, None);
    // With no tool inside, the box goes where the eyes' centres meet the head: a voxel the TF
    // shows, on the centre ray, off the volume's centre by more than a quarter of the box.
    let gaze = first(inset.wants_cuts(
        (&[held(Vec3::new(0.4, 0.0, 0.0))], &looking, None),
        &vol,
        &placement,
    ))
    .expect("the eyes' centres move the box");
    let dims = vol.dims.map(|d| d as f32);
    let tex = Vec3::from_array(std::array::from_fn(|a| gaze[a] as f32 / dims[a]));
    let world = cao_xr::space::world_from_tex(&vol, &placement).transform_point3(tex);
    let ray = placement.center + Vec3::new(0.05, 0.0, 0.5);
    let off_ray = (world - ray).cross(Vec3::Z).length();
    assert!(
        off_ray < 0.005,
        "{gaze:?} is {off_ray} m off the centre ray"
    );
    let voxel = gaze.map(|c| c as usize);
    let value = vol.voxels.get(vol.index(voxel[0], voxel[1], voxel[2]));
    assert!(tf.eval(value, vol.value_range())[3] > 0.0, "{gaze:?}");
    assert!(
        (0..3).any(|a| (gaze[a] - 24.0).abs() > 4.0),
        "{gaze:?} is the box's centre"
    );
    let blind = first(inset.wants_cuts((&[], &away, None), &vol, &placement));
    assert_eq!(blind, None, "eyes turned away leave the box");
    // A tracked gaze, from the same eyes 4 cm lower towards the head's centre: the box goes
    // where it meets the head, on the gaze ray and not on the centre ray.
    let from = placement.center + Vec3::new(0.05, -0.04, 0.5);
    let look = Pose {
        position: from,
        orientation: Quat::from_rotation_arc(Vec3::NEG_Z, (placement.center - from).normalize()),
    };
    let followed = first(inset.wants_cuts((&[], &away, Some(look)), &vol, &placement))
        .expect("the gaze moves the box");
    let tex = Vec3::from_array(std::array::from_fn(|a| followed[a] as f32 / dims[a]));
    let world = cao_xr::space::world_from_tex(&vol, &placement).transform_point3(tex);
    let dir = (placement.center - from).normalize();
    let off_gaze = (world - from).cross(dir).length();
    assert!(
        off_gaze < 0.005,
        "{followed:?} is {off_gaze} m off the gaze"
    );
    assert!(
        (world - ray).cross(Vec3::Z).length() > 0.02,
        "{followed:?} is on the centre ray"
    );
    // A tool cutting near a corner while the tracked gaze meets the head elsewhere: the box
    // goes to the tool, and a second box is asked for where the eyes look.
    let mut cutting = held(Vec3::splat(0.07));
    cutting.active = true;
    let both = inset.wants_cuts((&[cutting], &away, Some(look)), &vol, &placement);
    assert_eq!(both.cuts, vec![(0, centre), (1, followed)]);
    // A tool cutting and the other hand's tool held far from it inside the volume (about to
    // cut): the box goes to the cutting one, a second to the held one (before the gaze).
    let cut_and_hold = [held(Vec3::splat(-0.07)), cutting];
    let hands = inset.wants_cuts((&cut_and_hold, &away, Some(look)), &vol, &placement);
    assert_eq!(hands.cuts.len(), 2, "{hands:?}");
    assert_eq!(hands.cuts[0], (0, centre), "{hands:?}");
    assert!(opposite(hands.cuts[1].1), "{hands:?}");
    // A 16^3 box is too small to split: the one box goes to the tool.
    let mut small = inset;
    small.make_cuts(&gpu, &both, false).unwrap();
    assert_eq!(small.boxes(), 1);
    let inside = |b: Option<([usize; 3], [usize; 3])>, c: [f64; 3]| {
        let (lo, hi) = b.expect("a box shown");
        (0..3).all(|a| (lo[a] as f64) <= c[a] && c[a] < hi[a] as f64)
    };
    assert!(inside(small.inner_box(), centre));
    drop(small);
    // A larger one, asked for by two hands far apart, is split in two, each of about half its
    // crop, one around each hand, both shown to the ray caster.
    let mut large = Inset::around(
        &gpu,
        vol.clone(),
        (AoConfig::new(AoMethod::Lao, lao_params), tf.clone()),
        ([28, 28, 28], [24.0; 3]),
    )
    .unwrap();
    let (_, crop) = large.crop_box().unwrap();
    let both = large.wants_cuts((&apart, &away, None), &vol, &placement);
    assert_eq!(both.cuts.len(), 2, "{both:?}");
    large.make_cuts(&gpu, &both, false).unwrap();
    assert_eq!(large.boxes(), 2, "{}", large.describe());
    let side = large.inner_size();
    assert!(side.iter().all(|&n| (16..28).contains(&n)), "{side:?}");
    for (b, &(_, c)) in both.cuts.iter().enumerate() {
        assert!(inside(large.inner_box_of(b), c), "box {b}: {both:?}");
    }
    let voxels = |dims: [usize; 3]| dims.iter().product::<usize>();
    assert!(
        2 * voxels(large.crop_box().unwrap().1) <= voxels(crop),
        "two crops hold what one did"
    );
    assert_eq!(large.bindings(&vol, &placement).len(), 2);
    // Asked for nothing new, they stay.
    let again = large.wants_cuts((&apart, &away, None), &vol, &placement);
    assert_eq!(again.cuts, vec![], "{}", large.describe());
    // One hand gone: after MERGE_FRAMES frames with one place the two merge back into one box
    // of the first size, around that place.
    let one_hand = large.wants_cuts((&apart[..1], &away, None), &vol, &placement);
    assert_eq!(one_hand.cuts, vec![], "the first box is around the hand");
    for frame in 1..=MERGE_FRAMES {
        assert_eq!(large.boxes(), 2, "frame {frame}");
        large.make_cuts(&gpu, &one_hand, false).unwrap();
    }
    assert_eq!(large.boxes(), 1);
    assert_eq!(large.inner_size(), [28; 3]);
    assert!(inside(large.inner_box(), one_hand.places[0]));
    common::assert_no_validation_messages(&gpu);
}

/// The CAO state of the whole volume `vol` under `tf` and `ao`: what the box is compared with.
fn whole_cao(
    gpu: &cao_xr::gpu::Gpu,
    lao: &LaoGpu,
    vol: &cao_xr::volume::Volume,
    (tf, ao): (&TransferFunction, &AoConfig),
) -> cao_xr::ao::cao::Cao {
    precompute(gpu, lao, vol, tf, ao, false)
        .unwrap()
        .into_cao(gpu, vol)
        .unwrap()
}

/// Runs the scripted carving's frames on `whole` (the whole volume `vol`'s CAO state) and on
/// `inset`, and requires the box's AO (and bleeding colour, where the method has one) to be the
/// whole's, bit for bit, on every frame; returns how many frames had occluded voxels in the
/// box.
fn carve_both(
    vol: &cao_xr::volume::Volume,
    whole: &mut cao_xr::ao::cao::Cao,
    inset: &mut Inset,
) -> usize {
    let placement = Placement::default();
    let (lo, hi) = inset.inner_box().unwrap();
    let (crop_lo, crop) = inset.crop_box().unwrap();
    let mut carved = 0;
    for (f, tools) in frames(placement.center).iter().enumerate() {
        whole
            .run_frame(tools, &placement, Mode::Contextual)
            .unwrap();
        inset
            .run_frame(tools, (vol, &placement), Mode::Contextual)
            .unwrap();
        let part = inset.cao().unwrap();
        let (want, got) = (read_ao(&whole.ao), read_ao(&part.ao));
        let words = |b: Option<&cao_xr::gpu::Buffer>| -> Vec<u32> {
            b.map_or_else(Vec::new, |b| {
                bytemuck::cast_slice(&b.read_back().unwrap()).to_vec()
            })
        };
        let (want_e, got_e) = (
            words(whole.method().bleeding()),
            words(part.method().bleeding()),
        );
        assert_eq!(want_e.is_empty(), got_e.is_empty());
        let mut changed = 0;
        for k in lo[2]..hi[2] {
            for j in lo[1]..hi[1] {
                for i in lo[0]..hi[0] {
                    let (v, c) = (
                        vol.index(i, j, k),
                        [i - crop_lo[0], j - crop_lo[1], k - crop_lo[2]],
                    );
                    let u = c[0] + crop[0] * (c[1] + crop[1] * c[2]);
                    let (w, g) = (want[v], got[u]);
                    assert_eq!(
                        g.to_bits(),
                        w.to_bits(),
                        "frame {f}: voxel ({i}, {j}, {k}): {g} against {w}"
                    );
                    if !want_e.is_empty() {
                        assert_eq!(got_e[u], want_e[v], "frame {f}: E at ({i}, {j}, {k})");
                    }
                    changed += (w < 1.0) as usize;
                }
            }
        }
        carved += (changed > 0) as usize;
    }
    carved
}

/// Under a TF on the normalised value range (MR's), the box is classified over the whole
/// volume's range, not its crop's narrower one: its AO is still the whole's, bit for bit.
#[test]
fn under_a_normalised_tf_the_boxs_ao_is_the_whole_volumes() {
    let gpu = common::gpu();
    let (vol, _, lao_params) = small_head();
    let tf = TransferFunction::preset("mr-default").unwrap();
    let lao = LaoGpu::new(&gpu).unwrap();
    let ao = AoConfig::new(AoMethod::Lao, lao_params);
    let mut inset = Inset::around(
        &gpu,
        vol.clone(),
        (ao, tf.clone()),
        ([16, 16, 16], [24.0, 30.0, 24.0]),
    )
    .unwrap();
    let (crop_lo, crop) = inset.crop_box().unwrap();
    let part = vol.crop(crop_lo, crop);
    assert_ne!(
        part.own_value_range(),
        vol.value_range(),
        "the crop's own range is the whole's"
    );
    assert_eq!(
        part.value_range(),
        vol.value_range(),
        "classified as the whole"
    );
    let mut whole = whole_cao(&gpu, &lao, &vol, (&tf, &ao));
    assert!(carve_both(&vol, &mut whole, &mut inset) > 0);
    common::assert_no_validation_messages(&gpu);
}

/// With labels, the box's AO is still the whole volume's, bit for bit, on every frame of a
/// carving: its crop carries the structures (a translucent one scales O, a protected one stands
/// inside the tools), and a structure shown differently at run time is cut again with it.
#[test]
fn a_labelled_boxs_ao_is_the_whole_volumes_with_its_structures() {
    let gpu = common::gpu();
    let (_, tf, lao_params) = small_head();
    let mut vol = crate::labels::labelled_head(48, true);
    // The tissue ball at 0.4 of its TF opacity; the vessel through it protected.
    Arc::make_mut(vol.labels.as_mut().unwrap()).structures[1].opacity = 0.4;
    let vol = Arc::new(vol);
    let lao = LaoGpu::new(&gpu).unwrap();
    let ao = AoConfig::new(AoMethod::Lao, lao_params);
    let mut inset = Inset::around(
        &gpu,
        vol.clone(),
        (ao, tf.clone()),
        ([20, 20, 24], [24.0, 30.0, 24.0]),
    )
    .unwrap();
    // Shown as a run-time menu leaves them: the tissue at 0.4 again (cut anew), protected.
    inset
        .set_shown(&gpu, (ao, tf.clone()), &[1.0, 0.25])
        .unwrap();
    inset
        .set_shown(&gpu, (ao, tf.clone()), &[1.0, 0.4])
        .unwrap();
    inset.set_protected(&[true, false]);
    let mut whole = whole_cao(&gpu, &lao, &vol, (&tf, &ao));
    let (lo, hi) = inset.inner_box().unwrap();
    let ids = &vol.labels.as_ref().unwrap().ids;
    let mut labelled = [0; 3];
    for k in lo[2]..hi[2] {
        for j in lo[1]..hi[1] {
            for i in lo[0]..hi[0] {
                labelled[ids[vol.index(i, j, k)] as usize] += 1;
            }
        }
    }
    assert!(labelled.iter().all(|&n| n > 0), "{labelled:?}");
    assert!(carve_both(&vol, &mut whole, &mut inset) > 0);
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn a_box_computed_over_frames_is_the_box_cut_at_once() {
    let gpu = common::gpu();
    let (vol, tf, params) = small_head();
    let hist = AoMethod::Histogram(HistParams {
        radius_mm: 10.0,
        bins: 16,
        clusters: 64,
        hemispheres: true,
    });
    for method in [AoMethod::Lao, hist] {
        let config = (AoConfig::new(method, params), tf.clone());
        computed_over_frames(&gpu, &vol, config);
    }
    common::assert_no_validation_messages(&gpu);
}

/// [`a_box_computed_over_frames_is_the_box_cut_at_once`] under one method.
fn computed_over_frames(
    gpu: &cao_xr::gpu::Gpu,
    vol: &Arc<cao_xr::volume::Volume>,
    config: (AoConfig, TransferFunction),
) {
    let method = config.0.method;
    let placement = Placement::default();
    let inner = [16, 16, 16];
    let mut inset = Inset::around(gpu, vol.clone(), config.clone(), (inner, [24.0; 3])).unwrap();
    // A tool a hand holds near a corner: the box is wanted there.
    let mut held = tool(
        Shape::Sphere,
        placement.center + Vec3::splat(0.07),
        Quat::IDENTITY,
        0.02,
        ToolMode::Carve,
    );
    held.active = false;
    let head = Pose {
        position: placement.center + Vec3::new(0.0, 0.0, 0.5),
        orientation: Quat::IDENTITY,
    };
    let fov = Fov {
        angle_left: -0.5,
        angle_right: 0.5,
        angle_up: 0.5,
        angle_down: -0.5,
    };
    let eyes = FrameInput::head_views(head, 0.064, fov);
    let wanted = |inset: &Inset| {
        let cuts = inset
            .wants_cuts((&[held], &eyes, None), vol, &placement)
            .cuts;
        assert!(cuts.iter().all(|&(b, _)| b == 0), "{cuts:?}");
        cuts.first().map(|&(_, c)| c)
    };
    let there = wanted(&inset).expect("the held tool moves the box");
    let at_once = Inset::around(gpu, vol.clone(), config, (inner, there)).unwrap();
    let (_, crop) = at_once.crop_box().unwrap();

    inset.start_cut(gpu, there).unwrap();
    // A frame's budget of no samples: the box's work is spread over BUILD_FRAMES frames.
    let budget = 0.0;
    let mut refined = 0;
    while inset.refining().is_some() {
        assert!(
            inset.cao().is_none() && inset.bindings(vol, &placement).is_empty(),
            "{method:?}, frame {refined}: the old box is gone and the new one not shown yet"
        );
        assert_eq!(
            wanted(&inset),
            None,
            "frame {refined}: the box being computed is not cut again"
        );
        inset.refine(gpu, budget).unwrap();
        refined += 1;
        assert!(refined <= BUILD_FRAMES, "done within BUILD_FRAMES frames");
    }
    assert!(refined > 1, "{method:?} {crop:?}: over frames");
    assert_eq!(inset.inner_box(), at_once.inner_box());
    assert_eq!(inset.crop_box(), at_once.crop_box());
    assert_eq!(wanted(&inset), None, "the box shown is where the tool is");
    // The same bits as the box cut at once, unclipped and on every frame of a carving.
    let mut at_once = at_once;
    let bits = |i: &Inset| {
        read_ao(&i.cao().unwrap().ao)
            .iter()
            .map(|v| v.to_bits())
            .collect::<Vec<_>>()
    };
    assert!(bits(&inset) == bits(&at_once), "{method:?} unclipped");
    for (f, tools) in frames(placement.center).iter().enumerate() {
        for i in [&mut inset, &mut at_once] {
            i.run_frame(tools, (vol, &placement), Mode::Contextual)
                .unwrap();
        }
        assert!(bits(&inset) == bits(&at_once), "{method:?} frame {f}");
    }
}

/// `render phantom:192` with a probe (only its inside stays) into `out`, under `env`: what it
/// told.
fn render(out: &std::path::Path, env: &[(&str, &str)]) -> String {
    render_with(out, &[], env)
}

/// [`render`] with more arguments.
fn render_with(out: &std::path::Path, more: &[&str], env: &[(&str, &str)]) -> String {
    render_through("probe-sphere:20", out, more, env)
}

/// [`render_with`] seen through the probe `tool` (`--tool`'s form).
fn render_through(
    tool: &str,
    out: &std::path::Path,
    more: &[&str],
    env: &[(&str, &str)],
) -> String {
    let mut args = vec![
        "render",
        "phantom:192",
        "--size",
        "256x256",
        "--rays",
        "6",
        "--steps",
        "4",
        "--tool",
        tool,
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(more);
    let run = common::run_cao(&args, env);
    let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
    assert!(run.status.success(), "{env:?}: {stderr}");
    // The notices (stderr) and the statistics (stdout) together.
    stderr + &String::from_utf8_lossy(&run.stdout)
}

/// The PSNR (dB) of picture `b` against `a` (`cao-xr compare`).
fn psnr(a: &std::path::Path, b: &std::path::Path) -> f64 {
    let out = common::run_cao_ok(&["compare", a.to_str().unwrap(), b.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let at = text
        .find("PSNR ")
        .unwrap_or_else(|| panic!("no PSNR in {text}"));
    let v = text[at + 5..].split_whitespace().next().unwrap();
    if v == "inf" {
        f64::INFINITY
    } else {
        v.parse().unwrap()
    }
}

/// The whole set-up's GPU memory peak (MiB), as `render` tells it.
fn peak_of(told: &str) -> u64 {
    let at = told.find("GPU memory: peak ").expect("the peak is told");
    let mib = told[at + 17..].split_whitespace().next().unwrap();
    mib.parse().unwrap()
}

/// The left eye's pictures in `dirs`: the share of the pixels the first shows (not background)
/// that each of the others shows within 2/255 per channel. Panics where the first shows
/// fewer than 400.
fn shares_as_first(dirs: &[&std::path::Path]) -> Vec<f64> {
    use cao_xr::render::compare::{read_png, Picture};
    let pics: Vec<Picture> = dirs
        .iter()
        .map(|d| read_png(&d.join("left.png")).unwrap())
        .collect();
    let f = &pics[0];
    let px = |p: &Picture, k: usize| p.rgba[4 * k..4 * k + 4].to_vec();
    let background = px(f, 0);
    let seen: Vec<usize> = (0..f.width * f.height)
        .filter(|&k| px(f, k) != background)
        .collect();
    assert!(seen.len() > 400, "{} pixels seen", seen.len());
    let near = |p: &Picture, k: usize| {
        px(p, k)
            .iter()
            .zip(px(f, k))
            .all(|(a, b)| a.abs_diff(b) <= 2)
    };
    pics[1..]
        .iter()
        .map(|p| seen.iter().filter(|&&k| near(p, k)).count() as f64 / seen.len() as f64)
        .collect()
}

#[test]
fn under_a_quarter_of_the_budget_the_tools_neighbourhood_is_shown_at_full_resolution() {
    let dir = common::scratch("inset", "quarter");
    let full = dir.join("full");
    let stderr = render(&full, &[]);
    let peak = peak_of(&stderr);
    let quarter = (peak / 4).to_string();
    let budget = [("CAO_XR_GPU_BUDGET_MB", quarter.as_str())];
    let inset = dir.join("inset");
    let told = render(&inset, &budget);
    assert!(told.contains("shown downsampled by"), "{told}");
    // The peak told is the whole run's: at least what the full-resolution try held when it
    // ran out ("... while 11.5 MiB of the 14.0 MiB budget ... are in use").
    let at = told
        .find(" MiB of the ")
        .expect("the try that did not fit is told");
    let held_then: f64 = told[..at].rsplit(' ').next().unwrap().parse().unwrap();
    assert!(
        peak_of(&told) as f64 >= held_then.floor(),
        "peak {} MiB against {held_then} MiB held: {told}",
        peak_of(&told)
    );
    // The box followed the probe (30 mm up, 70 mm to the front: not the volume's centre).
    let last = told
        .lines()
        .rfind(|l| l.starts_with("volume ") && l.contains(" at full resolution"))
        .unwrap_or_else(|| panic!("no inset told: {told}"));
    assert!(
        last.contains("phantom-192-ds"),
        "the box was not cut again: {told}"
    );
    let coarse = dir.join("coarse");
    render(&coarse, &[budget[0], ("CAO_XR_INSET", "0")]);
    let pic = |d: &std::path::Path| d.join("left.png");
    let (with, without) = (
        psnr(&pic(&full), &pic(&inset)),
        psnr(&pic(&full), &pic(&coarse)),
    );
    assert!(
        with >= 60.0,
        "with the inset {with} dB (without {without} dB)"
    );
    // Only the probe's inside is seen, all of it in the box: the full-resolution picture but for
    // rounding (the box's texture coordinates are the shown volume's scaled and offset): within
    // 2/255 per channel.
    let shares = shares_as_first(&[&full, &inset, &coarse]);
    let (same_with, same_without) = (shares[0], shares[1]);
    assert!(
        same_with >= 0.99 && same_without < 0.5,
        "pixels as at full resolution: {same_with} with the inset, {same_without} without"
    );
    // With the budget of the whole volume, the picture is the full one.
    let all = (2 * peak).to_string();
    let enough = dir.join("enough");
    let told = render(&enough, &[("CAO_XR_GPU_BUDGET_MB", all.as_str())]);
    assert!(!told.contains("downsampled"), "{told}");
    assert_eq!(
        std::fs::read(pic(&enough)).unwrap(),
        std::fs::read(pic(&full)).unwrap()
    );
}

/// A label map in `phantom:192`'s grid, written as NIfTI into `dir`: voxel x gets `id(x, r)`, r
/// its distance from the volume's centre in voxels.
fn phantom_labels(dir: &std::path::Path, id: impl Fn([usize; 3], f64) -> u8) -> std::path::PathBuf {
    let n = 192;
    let head = phantom::head(n);
    let c = n as f64 / 2.0;
    let ids = (0..head.voxel_count())
        .map(|v| {
            let x = [v % n, (v / n) % n, v / (n * n)];
            let r2: f64 = x.iter().map(|&i| (i as f64 + 0.5 - c).powi(2)).sum();
            id(x, r2.sqrt())
        })
        .collect();
    let mut seg = head.clone_geometry();
    seg.voxels = cao_xr::volume::Voxels::U8(ids);
    let path = dir.join("seg.nii");
    cao_xr::volume::nifti::write(&path, &seg, false).unwrap();
    path
}

/// `render` (into a folder, under an environment; what it told) into `dir`'s `full`, then under
/// a quarter of that run's GPU peak into `inset` (a box must be shown) and, without the box,
/// `coarse`: the share of the full picture's pixels each of the last two shows within 2/255
/// (in the box, the first must be about all), and what the coarse run told.
fn past_the_budget(
    dir: &std::path::Path,
    render: impl Fn(&std::path::Path, &[(&str, &str)]) -> String,
) -> ([f64; 2], String) {
    let full = dir.join("full");
    let quarter = (peak_of(&render(&full, &[])) / 4).to_string();
    let budget = ("CAO_XR_GPU_BUDGET_MB", quarter.as_str());
    let (inset, coarse) = (dir.join("inset"), dir.join("coarse"));
    let told = render(&inset, &[budget]);
    assert!(told.contains(" at full resolution"), "{told}");
    let told = render(&coarse, &[budget, ("CAO_XR_INSET", "0")]);
    let shares = shares_as_first(&[&full, &inset, &coarse]);
    ([shares[0], shares[1]], told)
}

/// The shares [`past_the_budget`] gives: about all of the full picture's pixels with the box,
/// fewer than `without` of them from the downsampled volume alone.
fn assert_full_in_box(shares: [f64; 2], without: f64) {
    assert!(
        shares[0] >= 0.99 && shares[1] < without,
        "pixels as at full resolution: {} with the inset, {} without",
        shares[0],
        shares[1]
    );
}

/// A labelled volume past the budget keeps its structures: the downsampled volume has them by
/// each block's majority (the picture `--downsample N` gives), and the box at full resolution,
/// where the picture is the full-resolution one.
#[test]
fn a_labelled_volume_past_the_budget_shows_its_structures_at_full_resolution_in_the_box() {
    let dir = common::scratch("inset", "labels");
    // Two structures in a checkerboard of 2-voxel cells through the head (what a downsample by
    // 3 or more cannot show), the second at 0.3 of its TF opacity.
    let path = phantom_labels(&dir, |x, r| {
        if r < 0.45 * 192.0 {
            1 + ((x[0] / 2 + x[1] / 2 + x[2] / 2) % 2) as u8
        } else {
            0
        }
    });
    let labels = ["--labels", path.to_str().unwrap(), "--opacity", "2=0.3"];
    let (shares, told) = past_the_budget(&dir, |out, env| render_with(out, &labels, env));
    let at = told.find("shown downsampled by ").expect("downsampled");
    let by = told[at + 21..].split_whitespace().next().unwrap();
    let given = dir.join("given");
    render_with(&given, &[&labels[..], &["--downsample", by]].concat(), &[]);
    assert!(
        std::fs::read(dir.join("coarse/left.png")).unwrap()
            == std::fs::read(given.join("left.png")).unwrap(),
        "downsampled by {by} for the budget, and as given, the pictures differ"
    );
    assert_full_in_box(shares, 0.5);
}

/// A safety margin past the budget glows in the box from the full-resolution distances, as in
/// the full-resolution picture (the downsampled volume's blocky ball glows otherwise).
#[test]
fn a_safety_margin_glows_in_the_box_as_at_full_resolution() {
    let dir = common::scratch("inset", "glow");
    // A ball of 14 voxels' radius at the centre with a 4 mm margin, seen through a probe there.
    let path = phantom_labels(&dir, |_, r| (r < 14.0) as u8);
    let margin = ["--labels", path.to_str().unwrap(), "--margin", "1=4"];
    let render = |out: &std::path::Path, env: &[(&str, &str)]| {
        render_through("probe-sphere:36:0,0,0", out, &margin, env)
    };
    let (shares, _) = past_the_budget(&dir, render);
    assert_full_in_box(shares, 0.9);
}

/// The local histograms past the budget: the box holds their direct sums at full resolution,
/// binned over the whole volume's range, and the ray caster reads its AO and its bleeding colour
/// E there, so the picture in the box is the full-resolution one (the direct sums, as
/// `--clusters 0` gives them at full resolution).
#[test]
fn the_local_histograms_in_the_box_are_the_full_resolutions() {
    let dir = common::scratch("inset", "histogram");
    let more = [
        "--ao",
        "histogram",
        "--clusters",
        "0",
        "--hist-radius-mm",
        "4",
        "--bleeding",
        "1",
    ];
    let (shares, _) = past_the_budget(&dir, |out, env| render_with(out, &more, env));
    assert_full_in_box(shares, 0.5);
}

/// Variance opacity modulation past the budget: the box's var_s is the full resolution's (the
/// downsampled volume's is that of averaged voxels), so the picture there is the full one.
#[test]
fn variance_modulation_in_the_box_is_the_full_resolutions() {
    let dir = common::scratch("inset", "variance");
    let more = ["--variance-max", "20000"];
    let (shares, _) = past_the_budget(&dir, |out, env| render_with(out, &more, env));
    assert_full_in_box(shares, 0.5);
}

/// `replay` of a sphere sweeping left to right through a transfer function switch (`script
/// tf-switch --frames 24`) on `phantom:160` at 96 x 64 under 13 MiB, into `dir`: what it told
/// on stderr, and its output folder.
fn replay_sweep(dir: &std::path::Path) -> (String, std::path::PathBuf) {
    let script = dir.join("tf-switch.jsonl");
    let script_arg = script.to_str().unwrap();
    common::run_cao_ok(&["script", "tf-switch", "--frames", "24", "--out", script_arg]);
    let out = dir.join("replay");
    let args = [
        "replay",
        script_arg,
        "phantom:160",
        "--size",
        "96x64",
        "--out",
        out.to_str().unwrap(),
    ];
    let run = common::run_cao(&args, &[("CAO_XR_GPU_BUDGET_MB", "13")]);
    let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
    assert!(run.status.success(), "{stderr}");
    (stderr, out)
}

#[test]
fn the_inset_follows_a_moving_tool_through_a_transfer_function_switch() {
    let dir = common::scratch("inset", "replay");
    let (stderr, out) = replay_sweep(&dir);
    // The sphere sweeps from left to right: the box is cut again where it goes, further right
    // each time.
    let firsts: Vec<usize> = stderr
        .lines()
        .filter(|l| l.contains("phantom-160-ds") && l.contains(" at full resolution"))
        .map(|l| {
            let at = l.find(" at [").unwrap_or_else(|| panic!("no box in {l}"));
            l[at + 5..].split(':').next().unwrap().parse().unwrap()
        })
        .collect();
    assert!(firsts.len() >= 3, "{stderr}");
    assert!(firsts.windows(2).all(|w| w[1] >= w[0]), "{firsts:?}");
    // Moved boxes are computed over frames: the stats line says how far, then what the box's
    // update cost once it is shown.
    let insets: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("frame "))
        .filter_map(|l| l.split("  inset ").nth(1))
        .collect();
    assert_eq!(insets.len(), 24, "every frame tells the box: {stderr}");
    let computing = |i: &&str| {
        i.split_whitespace()
            .next()
            .is_some_and(|t| t.ends_with('%'))
    };
    assert!(insets.iter().any(computing), "{insets:?}");
    let shown = insets
        .iter()
        .filter(|i| i.split_whitespace().nth(1) == Some("ms"));
    assert!(shown.count() >= 2, "{insets:?}");
    let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 25, "a header and a row per frame");
}

#[test]
fn where_no_inset_fits_the_picture_is_the_finest_downsample_alone() {
    // Under 7 MiB the filters' wide margin leaves a frame with the sphere no room for a box
    // beside the volume downsampled by 5 (the set-up finds none, or the first frame gives it
    // up): with two levels the volume is shown exactly as without insets.
    let dir = common::scratch("inset", "none");
    let render = |out: &std::path::Path, inset: &str| {
        let args = [
            "render",
            "phantom:192",
            "--size",
            "128x128",
            "--ao",
            "filter-gauss",
            "--tool",
            "sphere:40",
            "--out",
            out.to_str().unwrap(),
        ];
        // (Two levels: a middle one would stay where the full-resolution box is given up.)
        let env = [
            ("CAO_XR_GPU_BUDGET_MB", "7"),
            ("CAO_XR_INSET", inset),
            ("CAO_XR_INSET_MIDDLE", "0"),
        ];
        let run = common::run_cao(&args, &env);
        let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
        assert!(run.status.success(), "{stderr}");
        stderr
    };
    let (with, without) = (dir.join("with"), dir.join("without"));
    let told = render(&with, "1");
    assert!(
        told.contains("no full-resolution inset fits") || told.contains("the inset is given up"),
        "{told}"
    );
    render(&without, "0");
    let png = |d: &std::path::Path| std::fs::read(d.join("stereo.png")).unwrap();
    assert!(png(&with) == png(&without), "the pictures differ: {told}");
}

/// The small head shown downsampled by `by` with its own LAO, drawn by the ray caster with
/// boxes bound over it ([`BoxScene::picture`]); the tests of the box slots share it.
struct BoxScene {
    vol: Arc<cao_xr::volume::Volume>,
    tf: TransferFunction,
    config: AoConfig,
    placement: Placement,
    coarse: Arc<cao_xr::volume::Volume>,
    coarse_cao: cao_xr::ao::cao::Cao,
    tex: cao_xr::render::VolumeTextures,
    hr: cao_xr::app::HeadlessRenderer,
}

impl BoxScene {
    fn new(gpu: &cao_xr::gpu::Gpu, by: usize) -> BoxScene {
        let (vol, tf, lao_params) = small_head();
        let config = AoConfig::new(AoMethod::Lao, lao_params);
        let coarse = Arc::new(vol.downsample(by));
        let lao = LaoGpu::new(gpu).unwrap();
        let coarse_cao = whole_cao(gpu, &lao, &coarse, (&tf, &config));
        let mut tex = cao_xr::render::VolumeTextures::new(gpu, &coarse, &tf).unwrap();
        tex.show_as(&vol, &tf).unwrap();
        BoxScene {
            vol,
            tf,
            config,
            placement: Placement::default(),
            coarse,
            coarse_cao,
            tex,
            hr: cao_xr::app::HeadlessRenderer::new(gpu).unwrap(),
        }
    }

    /// An inset of `inner` voxels from `whole` (the head, or a downsample of it) around
    /// `centre`.
    fn inset(
        &self,
        gpu: &cao_xr::gpu::Gpu,
        whole: Arc<cao_xr::volume::Volume>,
        (inner, centre): ([usize; 3], [f64; 3]),
    ) -> Inset {
        let shown = (self.config, self.tf.clone());
        Inset::around(gpu, whole, shown, (inner, centre)).unwrap()
    }

    /// Both eyes' pictures (96 x 96) with `insets` bound, in that order.
    fn picture(&mut self, insets: &[cao_xr::render::InsetBinding]) -> [Vec<u8>; 2] {
        use cao_xr::render::{FrameViews, RenderSettings};
        use cao_xr::space::{default_stereo_views, world_from_tex, DEFAULT_IPD};
        let views = default_stereo_views(&self.coarse, &self.placement, DEFAULT_IPD);
        let frame = FrameViews {
            ao: Some((&self.coarse_cao.ao).into()),
            insets,
            ..FrameViews::new(&views, world_from_tex(&self.coarse, &self.placement))
        };
        let settings = RenderSettings::default();
        self.hr
            .render(&self.tex, &frame, (96, 96), &settings)
            .unwrap()
            .rgba
    }
}

/// The bytes the left eyes of two pictures differ in.
fn bytes_differing(a: &[Vec<u8>; 2], b: &[Vec<u8>; 2]) -> usize {
    a[0].iter().zip(&b[0]).filter(|(x, y)| x != y).count()
}

/// Two boxes shown at once: the ray caster reads the second box's images, V_AO and place as it
/// reads the first's. The same two boxes in either order give the same picture bit for bit
/// (each holds the whole volume's AO and scalars, so where they overlap either is right), and
/// the second box changes the picture the first alone gives.
#[test]
fn a_second_box_is_read_as_the_first() {
    let gpu = common::gpu();
    let mut scene = BoxScene::new(&gpu, 2);
    let mut inset = scene.inset(&gpu, scene.vol.clone(), ([28, 28, 28], [24.0; 3]));
    // Two boxes on either side of the head's front.
    inset
        .make_cuts(
            &gpu,
            &Cuts {
                places: vec![[12.0, 24.0, 14.0], [36.0, 24.0, 34.0]],
                cuts: vec![(0, [12.0, 24.0, 14.0]), (1, [36.0, 24.0, 34.0])],
            },
            false,
        )
        .unwrap();
    assert_eq!(inset.boxes(), 2, "{}", inset.describe());
    let boxes = inset.bindings(&scene.coarse, &scene.placement);
    assert_eq!(boxes.len(), 2);
    let both = scene.picture(&boxes);
    let swapped = scene.picture(&[boxes[1], boxes[0]]);
    let first = scene.picture(&boxes[..1]);
    assert_eq!(
        bytes_differing(&both, &swapped),
        0,
        "the order of the boxes matters"
    );
    let changed = bytes_differing(&both, &first);
    assert!(changed > 100, "the second box changes {changed} bytes");
    drop(boxes);
    drop((inset, scene));
    common::assert_no_validation_messages(&gpu);
}

/// A middle level's box (from the volume downsampled by 2) in the third slot: read exactly as
/// a box in the first slot is (two empty boxes before it change nothing, bit for bit), and
/// under the full-resolution boxes where they overlap (each level shows: the picture with all
/// three is neither the full boxes' alone nor the middle box's alone).
#[test]
fn a_middle_levels_box_is_read_in_the_third_slot_under_the_full_ones() {
    let gpu = common::gpu();
    let mut scene = BoxScene::new(&gpu, 4);
    let centre = |v: &cao_xr::volume::Volume| v.dims.map(|d| d as f64 * 0.5);
    let full = scene.inset(&gpu, scene.vol.clone(), ([16; 3], centre(&scene.vol)));
    let half = Arc::new(scene.vol.downsample(2));
    let middle = scene.inset(&gpu, half.clone(), ([18; 3], centre(&half)));
    assert!(
        middle.describe().contains("downsampled by 2"),
        "{}",
        middle.describe()
    );
    let (f, m) = (
        full.bindings(&scene.coarse, &scene.placement)[0],
        middle.bindings(&scene.coarse, &scene.placement)[0],
    );
    let empty = cao_xr::render::InsetBinding { hi: f.lo, ..f };
    let alone = scene.picture(&[m]);
    assert_eq!(
        bytes_differing(&alone, &scene.picture(&[empty, empty, m])),
        0,
        "the third slot is read otherwise than the first"
    );
    let all = scene.picture(&[f, empty, m]);
    let (fine, none) = (scene.picture(&[f]), scene.picture(&[]));
    assert!(
        bytes_differing(&alone, &none) > 100,
        "the middle box changes nothing"
    );
    assert!(
        bytes_differing(&all, &alone) > 100,
        "the full box is not read over the middle one"
    );
    assert!(
        bytes_differing(&all, &fine) > 100,
        "the middle box is not read around the full one"
    );
    drop((full, middle, scene));
    common::assert_no_validation_messages(&gpu);
}

/// Two spheres carving far apart under a third of the whole volume's GPU peak: the volume is
/// shown downsampled by 3 or more with a box at full resolution around each sphere and, around
/// them, a box at half resolution (the rest one step coarser for it); the picture is nearer the
/// full-resolution one than with the two levels alone (`CAO_XR_INSET_MIDDLE=0`) and than the
/// finest downsample alone.
#[test]
fn a_middle_level_brings_the_picture_nearer_the_full_one() {
    let dir = common::scratch("inset", "middle");
    let spheres = ["--tool", "sphere:25:45,-30,45"];
    let render = |out: &std::path::Path, env: &[(&str, &str)]| {
        render_through("sphere:25:-45,30,45", out, &spheres, env)
    };
    let full = dir.join("full");
    let third = (peak_of(&render(&full, &[])) / 3).to_string();
    let budget = ("CAO_XR_GPU_BUDGET_MB", third.as_str());
    let (three, two, alone) = (dir.join("three"), dir.join("two"), dir.join("alone"));
    let told = render(&three, &[budget]);
    let boxes = told
        .lines()
        .find(|l| l.starts_with("GPU memory held after the frame"))
        .unwrap_or_else(|| panic!("{told}"));
    assert!(
        boxes.contains("2 boxes of") && boxes.contains("box downsampled by 2"),
        "{told}"
    );
    render(&two, &[budget, ("CAO_XR_INSET_MIDDLE", "0")]);
    render(&alone, &[budget, ("CAO_XR_INSET", "0")]);
    let pic = |d: &std::path::Path| d.join("left.png");
    let [with, without, finest] = [&three, &two, &alone].map(|d| psnr(&pic(&full), &pic(d)));
    assert!(
        with > without + 2.0 && with > finest,
        "PSNR with the middle level {with} dB, without {without} dB, the finest downsample alone \
         {finest} dB"
    );
}

/// A frame that runs out of GPU memory with three levels makes the middle box smaller (or gives
/// it up) first: the full-resolution box keeps its size. A sphere sweeping through a transfer
/// function switch on `phantom:160` under 13 MiB (shown downsampled by 4, a 49³ box at full
/// resolution and a 58³ one at half) runs out in a frame that cuts the boxes again.
#[test]
fn a_frame_out_of_memory_shrinks_the_middle_box_first() {
    let dir = common::scratch("inset", "yield");
    let (told, _) = replay_sweep(&dir);
    let short = |l: &&str| l.starts_with("volume ") && l.contains("(out of GPU memory");
    let shrunk: Vec<&str> = told.lines().filter(short).collect();
    assert!(
        !shrunk.is_empty() && shrunk.iter().all(|l| l.contains("downsampled by 2")),
        "the middle box did not yield first: {told}"
    );
    // Every full-resolution box the frames tell (past the set-up's tries) has one size.
    let sizes: std::collections::BTreeSet<Vec<&str>> = told
        .lines()
        .filter(|l| l.starts_with("volume phantom-160-ds") && l.contains(" at full resolution"))
        .filter_map(|l| Some(l.split(" inset ").nth(1)?.split(' ').take(5).collect()))
        .collect();
    assert!(
        sizes.len() == 1 && !told.contains("given up (at full resolution)"),
        "the full-resolution box was made smaller ({sizes:?}): {told}"
    );
}
