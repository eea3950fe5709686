//! Filtered AO (Ruiz et al.) on lavapipe with validation on: the GPU against the CPU reference of
//! docs/design.md's definition for every estimator and both inputs, and, as an AO method of CAO,
//! the per-frame clip update equal to the filters run on the whole clipped volume, bit for bit,
//! on every frame of a carving, probing and empty sequence.

use crate::cao::{frames, read_ao};
use crate::common;

use cao_xr::ao::cao::{Cao, Mode};
use cao_xr::ao::filtered::{self, Estimator, FilterInput, FilterParams};
use cao_xr::ao::{AoConfig, AoMethod, LaoGpu, LaoParams};
use cao_xr::app::precompute;
use cao_xr::clip::Shape;
use cao_xr::gpu::Gpu;
use cao_xr::scene::ToolMode;
use cao_xr::space::Placement;
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{phantom, Volume};

fn config(estimator: Estimator, input: FilterInput, radius_mm: f64) -> AoConfig {
    AoConfig::new(
        AoMethod::Filter(FilterParams {
            radius_mm,
            estimator,
            input,
        }),
        LaoParams::default(),
    )
}

/// A CAO state whose method is the filters, and the density they filtered (host copy).
fn setup(gpu: &Gpu, vol: &Volume, ao: &AoConfig) -> (Cao, Vec<f32>) {
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let lao = LaoGpu::new(gpu).unwrap();
    let v = precompute(gpu, &lao, vol, &tf, ao, false).unwrap();
    let density = v.opacity.clone();
    (v.into_cao(gpu, vol).unwrap(), density)
}

#[test]
fn the_gpu_filters_agree_with_the_cpu_reference() {
    let gpu = common::gpu();
    // 32^3 voxels of 6.9 mm: R = 14 mm gives boxes of 5^3 centred up to 2 voxels away.
    let vol = phantom::head(32);
    for input in [FilterInput::Opacity, FilterInput::Scalar] {
        for estimator in Estimator::ALL {
            let ao = config(estimator, input, 14.0);
            let (cao, density) = setup(&gpu, &vol, &ao);
            let AoMethod::Filter(p) = ao.method else {
                unreachable!()
            };
            let want = filtered::filtered_ao(&density, vol.dims, vol.spacing, &p);
            let got = read_ao(&cao.ao);
            common::assert_agrees(&got, &want, &format!("{estimator:?} {input:?}"));
            // Not trivially open: the phantom has surfaces, so some voxels are occluded.
            assert!(got.iter().any(|&a| a < 0.5), "{estimator:?} {input:?}");
        }
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_filters_clip_update_equals_a_full_refilter_bit_for_bit_every_frame() {
    let gpu = common::gpu();
    let vol = phantom::head(40);
    let placement = Placement::default();
    for estimator in [Estimator::Gauss, Estimator::Cdf] {
        // 5.5 mm voxels: boxes of 5^3 (h = 2), centred up to 2 voxels away.
        let ao = config(estimator, FilterInput::Opacity, 11.0);
        let (mut cao, _) = setup(&gpu, &vol, &ao);
        let (mut naive, _) = setup(&gpu, &vol, &ao);
        let pre = read_ao(&cao.ao);
        let mut some_recomputed = false;
        for (i, tools) in frames(placement.center).iter().enumerate() {
            let m = cao.run_frame(tools, &placement, Mode::Contextual).unwrap();
            naive.run_frame(tools, &placement, Mode::Naive).unwrap();
            let (a, b) = (read_ao(&cao.ao), read_ao(&naive.ao));
            let diff = common::first_bit_difference(&a, &b);
            assert!(
                diff.is_none(),
                "{estimator:?} frame {i}: the clip update differs from a full refilter at voxel {diff:?}"
            );
            if tools.is_empty() {
                assert_eq!(a, pre, "frame {i}: with no tool the AO is V_PAO again");
            } else if tools[0].mode == ToolMode::Carve && tools[0].shape == Shape::Sphere {
                assert!(m.recomputed > 0, "{estimator:?} frame {i}: {m:?}");
                assert!(
                    m.visited < (40 * 40 * 40) as u64,
                    "frame {i}: boxes, not the volume"
                );
                assert!(a != pre, "{estimator:?} frame {i}: the cut changed nothing");
                some_recomputed = true;
            }
        }
        assert!(some_recomputed);
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn statistics_split_into_slabs_equal_one_buffer_bit_for_bit_every_frame() {
    // The box statistics (16 bytes per voxel) split into slabs of 3 slices, 14 slabs for 40
    // slices with a short last one, against one buffer: the precompute and every clip update of
    // a carving sequence are the same bits.
    let (whole, split) = (common::gpu(), common::gpu());
    let vol = phantom::head(40);
    let slice = (40 * 40 * 16) as u64;
    split.set_max_slab_bytes(3 * slice + 5);
    let slabs = cao_xr::gpu::SlabBuffer::new(&split, vol.dims, 16, "probe").unwrap();
    assert_eq!((slabs.slab_count(), slabs.slices_per_slab), (14, 3));
    let placement = Placement::default();
    let ao = config(Estimator::Gauss, FilterInput::Opacity, 11.0);
    let (mut one, _) = setup(&whole, &vol, &ao);
    let (mut many, _) = setup(&split, &vol, &ao);
    assert!(common::first_bit_difference(&read_ao(&one.ao), &read_ao(&many.ao)).is_none());
    for (i, tools) in frames(placement.center).iter().enumerate() {
        one.run_frame(tools, &placement, Mode::Contextual).unwrap();
        many.run_frame(tools, &placement, Mode::Contextual).unwrap();
        let diff = common::first_bit_difference(&read_ao(&one.ao), &read_ao(&many.ao));
        assert!(
            diff.is_none(),
            "frame {i}: slabs differ from one buffer at voxel {diff:?}"
        );
    }
    common::assert_no_validation_messages(&split);
}

#[test]
fn statistics_in_chunks_and_a_window_of_opacity_equal_whole_ones_bit_for_bit_every_frame() {
    // The box statistics computed 3 slices at a time (a window of 3 + 2 x 4 margin slices of
    // 40), O_c held only over the slices a frame's tools reach, against whole statistics and a
    // whole O_c (SH on): the precompute and every clip update of a carving sequence, a small
    // sphere last, are the same bits.
    let (whole, chunked) = (common::gpu(), common::gpu());
    chunked.set_scratch_slices(3);
    let vol = phantom::head(40);
    let placement = Placement::default();
    let ao = config(Estimator::Gauss, FilterInput::Opacity, 11.0);
    let (mut one, _) = setup(&whole, &vol, &ao);
    let (mut many, _) = setup(&chunked, &vol, &ao);
    one.sh_radius_mm = Some(10.0);
    let slices = |c: &Cao| c.filter().unwrap().stats_slices();
    assert_eq!((slices(&one), slices(&many)), (40, 11));
    assert!(common::first_bit_difference(&read_ao(&one.ao), &read_ao(&many.ao)).is_none());
    let c = placement.center;
    let mut sequence = frames(c);
    sequence.push(vec![crate::cao::tool(
        cao_xr::clip::Shape::Sphere,
        c,
        glam::Quat::IDENTITY,
        0.01,
        ToolMode::Carve,
    )]);
    for (i, tools) in sequence.iter().enumerate() {
        one.run_frame(tools, &placement, Mode::Contextual).unwrap();
        many.run_frame(tools, &placement, Mode::Contextual).unwrap();
        assert!(many.windowed() && !one.windowed());
        crate::cao::assert_same_state(&one, &many, i);
    }
    // The small sphere's slices, and the filters' reach either side: not the whole volume.
    let [from, to] = many.clipped_slices();
    assert!(from > 0 && to < 40, "slices {from}..{to} of 40 held");
    common::assert_no_validation_messages(&chunked);
}

#[test]
fn a_tf_switch_refilters_to_the_new_tfs_filtered_ao() {
    use cao_xr::app::frame_loop::FrameLoop;
    use cao_xr::input::{FrameInput, InteractionSettings};
    use cao_xr::space::{default_stereo_views, DEFAULT_IPD};
    use std::sync::Arc;
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(24));
    let ao = config(Estimator::Gauss, FilterInput::Opacity, 20.0);
    let (bone, skin) = (
        TransferFunction::preset("ct-bone").unwrap(),
        TransferFunction::preset("ct-skin").unwrap(),
    );
    let settings = InteractionSettings::default();
    let mut fl = FrameLoop::new(
        &gpu,
        Arc::clone(&vol),
        vec![bone, skin.clone()],
        ao,
        (16, 16),
        settings,
        false,
    )
    .unwrap();
    let views = default_stereo_views(&vol, &Placement::default(), DEFAULT_IPD);
    let before = read_ao(&fl.cao.ao);
    for i in 0..60 {
        let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
        input.hands[0].buttons.menu = i == 0;
        let f = fl.frame(&input).unwrap();
        if fl.shown_tf().name == "ct-skin" && f.stats.tf_progress.is_none() {
            break;
        }
    }
    assert_eq!(fl.shown_tf().name, "ct-skin", "the switch never finished");
    // Equal to the filters of a fresh start with the new TF (the frames carve nothing).
    let lao = LaoGpu::new(&gpu).unwrap();
    let fresh = precompute(&gpu, &lao, &vol, &skin, &ao, false).unwrap();
    let want = read_ao(&fresh.ao_buf);
    let got = read_ao(&fl.cao.ao);
    assert!(
        got == want,
        "the switched AO is not the new TF's filtered AO"
    );
    assert!(got != before, "the switch changed nothing");
    common::assert_no_validation_messages(&gpu);
}

/// Sum of |pixel - background| over both eyes of a render, from its stereo.png.
fn ink(dir: &std::path::Path) -> f64 {
    let dec = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(dir.join("stereo.png")).unwrap(),
    ));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    let px = &buf[..info.buffer_size()];
    let bg = [px[0], px[1], px[2]];
    px.chunks(info.color_type.samples())
        .map(|p| {
            (0..3)
                .map(|c| (p[c] as f64 - bg[c] as f64).abs())
                .sum::<f64>()
        })
        .sum()
}

#[test]
fn variance_modulation_fades_homogeneous_tissue_and_keeps_boundaries() {
    let dir = crate::common::scratch("filtered", "variance");
    let run = |name: &str, extra: &[&str]| {
        let out_dir = dir.join(name);
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_cao-xr"))
            .args([
                "render",
                "phantom:32",
                "--tf",
                "ct-soft-tissue",
                "--size",
                "48x48",
            ])
            .args([
                "--rays",
                "6",
                "--steps",
                "4",
                "--out",
                out_dir.to_str().unwrap(),
            ])
            .args(extra)
            .env("CAO_XR_VALIDATION", "1")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success() && !err.contains("vulkan validation"),
            "{err}"
        );
        ink(&out_dir)
    };
    let plain = run("plain", &[]);
    // A V_max far above any variance fades everything; a moderate one only the homogeneous
    // tissue, so some picture remains.
    let faded = run("huge", &["--variance-max", "1e12"]);
    let moderate = run(
        "moderate",
        &["--variance-max", "2000", "--filter-radius-mm", "8"],
    );
    assert!(plain > 0.0);
    assert!(faded < 0.05 * plain, "V_max 1e12: {faded} vs {plain}");
    assert!(
        moderate > faded && moderate != plain,
        "{moderate} vs {plain}, {faded}"
    );
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_cao-xr"))
        .args(["render", "phantom:16", "--variance-max=-3", "--out"])
        .arg(dir.join("bad"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--variance-max"));
    let _ = std::fs::remove_dir_all(&dir);
}
