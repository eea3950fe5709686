//! CAO on lavapipe with validation on: every frame of a scripted tool sequence gives exactly the
//! AO of the naive full recompute, and the cut is where the tools are.

use crate::common;

use ash::vk;
use cao_xr::ao::cao::{Cao, FrameMetrics, MethodGpu, Mode};
use cao_xr::ao::{LaoGpu, LaoParams};
use cao_xr::app::HeadlessRenderer;
use cao_xr::clip::Shape;
use cao_xr::gpu::{Buffer, Gpu};
use cao_xr::render::{ClipBinding, FrameViews, RenderSettings, StereoImage, VolumeTextures};
use cao_xr::scene::{Tool, ToolMode};
use cao_xr::space::{default_stereo_views, world_from_tex, Placement, Pose};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{phantom, Volume};
use glam::{Quat, Vec3};

const PARAMS: LaoParams = LaoParams {
    rays: 14,
    steps: 5,
    step_mm: 4.0,
};

pub(crate) fn setup(gpu: &Gpu, vol: &Volume) -> (Cao, Vec<f32>, Vec<f32>) {
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let o = tf.opacity_volume(vol);
    let lao = LaoGpu::new(gpu).unwrap();
    let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
    let obuf = cao_xr::ao::stored::upload(gpu, &o, usage, "o").unwrap();
    let skip = lao
        .skip_buffers(&o, vol.dims, vol.spacing, &PARAMS)
        .unwrap();
    let (pao, _) = lao
        .compute(&obuf, &skip, vol.dims, vol.spacing, &PARAMS, &mut |_, _| {})
        .unwrap();
    let pao_host = read_ao(&pao);
    // O as the GPU holds it.
    let o = cao_xr::ao::stored::quantised(&o);
    (
        Cao::new(
            gpu,
            vol,
            obuf.read_back().unwrap(),
            pao,
            MethodGpu::lao(gpu, vol, PARAMS, skip).unwrap(),
        )
        .unwrap(),
        o,
        pao_host,
    )
}

/// Both eyes of the clipped volume lit by this CAO state's V_AO.
fn render(
    gpu: &Gpu,
    vol: &Volume,
    cao: &Cao,
    tools: &[Tool],
    placement: &Placement,
) -> StereoImage {
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let tex = VolumeTextures::new(gpu, vol, &tf).unwrap();
    let mut hr = HeadlessRenderer::new(gpu).unwrap();
    let (t, m, b) = cao.clip_buffers();
    let clip = ClipBinding {
        tools: t,
        maps: m,
        bricks: b,
        count: tools.iter().filter(|t| t.active).count() as u32,
        reach: &cao.reach_boxes,
    };
    let views = default_stereo_views(vol, placement, 0.064);
    let model = world_from_tex(vol, placement);
    let frame = FrameViews {
        clip: Some(clip),
        ao: Some((&cao.ao).into()),
        bleeding: cao.method().bleeding(),
        ..FrameViews::new(&views, model)
    };
    hr.render(&tex, &frame, (64, 64), &RenderSettings::default())
        .unwrap()
}

/// A stored AO volume (16-bit unorm), whole (V_PAO) or in bricks (a CAO state's V_AO).
pub(crate) trait StoredAo {
    fn values(&self) -> Vec<f32>;
}

impl StoredAo for Buffer {
    fn values(&self) -> Vec<f32> {
        cao_xr::ao::stored::read(self, self.size as usize / 2).unwrap()
    }
}

impl StoredAo for cao_xr::ao::pool::AoPool {
    fn values(&self) -> Vec<f32> {
        self.read().unwrap()
    }
}

/// A stored AO volume (V_AO, V_PAO: 16-bit unorm) as values, x fastest.
pub(crate) fn read_ao(b: &impl StoredAo) -> Vec<f32> {
    b.values()
}

pub fn tool(shape: Shape, position: Vec3, rotation: Quat, size: f32, mode: ToolMode) -> Tool {
    Tool {
        shape,
        pose: Pose {
            position,
            orientation: rotation,
        },
        size,
        mode,
        active: true,
    }
}

/// A scripted sequence: sphere sweep, box in and out, torus over the skull and through its hole,
/// two tools, a probe, and frames with no tool (everything restored).
pub(crate) fn frames(c: Vec3) -> Vec<Vec<Tool>> {
    let mut f = Vec::new();
    let carve = ToolMode::Carve;
    for i in 0..4 {
        let x = -0.09 + 0.06 * i as f32;
        f.push(vec![tool(
            Shape::Sphere,
            c + Vec3::new(x, 0.05, 0.06),
            Quat::IDENTITY,
            0.03,
            carve,
        )]);
    }
    f.push(vec![]);
    for z in [0.12, 0.07, 0.12] {
        let r = Quat::from_rotation_y(0.4);
        f.push(vec![tool(
            Shape::Box,
            c + Vec3::new(0.0, 0.0, z),
            r,
            0.025,
            carve,
        )]);
    }
    for y in [0.12, 0.09] {
        let r = Quat::from_rotation_x(std::f32::consts::FRAC_PI_2);
        f.push(vec![tool(
            Shape::Torus,
            c + Vec3::new(0.0, y, 0.0),
            r,
            0.04,
            carve,
        )]);
    }
    f.push(vec![
        tool(
            Shape::Sphere,
            c + Vec3::new(-0.05, 0.0, 0.07),
            Quat::IDENTITY,
            0.025,
            carve,
        ),
        tool(
            Shape::Cylinder,
            c + Vec3::new(0.05, 0.02, 0.05),
            Quat::from_rotation_x(0.7),
            0.02,
            carve,
        ),
    ]);
    f.push(vec![tool(
        Shape::Sphere,
        c + Vec3::new(0.0, 0.02, 0.0),
        Quat::IDENTITY,
        0.07,
        ToolMode::Probe,
    )]);
    f.push(vec![tool(
        Shape::Sphere,
        c + Vec3::new(0.03, -0.02, 0.05),
        Quat::IDENTITY,
        0.03,
        carve,
    )]);
    f.push(vec![]);
    f
}

#[test]
fn cao_equals_naive_lao_bit_for_bit_every_frame() {
    let gpu = common::gpu();
    let vol = phantom::head(40);
    let (mut cao, _, pao) = setup(&gpu, &vol);
    let (mut naive, _, _) = setup(&gpu, &vol);
    let placement = Placement::default();
    let mut some_recomputed = false;
    for (i, tools) in frames(placement.center).iter().enumerate() {
        let m: FrameMetrics = cao.run_frame(tools, &placement, Mode::Contextual).unwrap();
        let n = naive.run_frame(tools, &placement, Mode::Naive).unwrap();
        let (a, b) = (read_ao(&cao.ao), read_ao(&naive.ao));
        let diff = common::first_bit_difference(&a, &b);
        assert!(
            diff.is_none(),
            "frame {i}: CAO differs from naive LAO at voxel {diff:?}"
        );
        assert_eq!(
            cao.read_clipped().unwrap(),
            naive.read_clipped().unwrap(),
            "frame {i}: clipped opacity"
        );
        assert_eq!(m.clipped, n.clipped, "frame {i}");
        if i % 4 == 0 || i == 9 {
            let (x, y) = (
                render(&gpu, &vol, &cao, tools, &placement),
                render(&gpu, &vol, &naive, tools, &placement),
            );
            assert!(x == y, "frame {i}: CAO and naive images differ");
        }
        if tools.is_empty() {
            assert_eq!(a, pao, "frame {i}: with no tool the AO is V_PAO again");
            assert_eq!(m.recomputed + m.clipped, 0);
        } else if tools[0].mode == ToolMode::Carve {
            assert!(
                m.recomputed > 0 && m.percent_recomputed() < 50.0,
                "frame {i}: {m:?}"
            );
            assert!(
                m.visited < (40 * 40 * 40) as u64,
                "frame {i}: boxes, not the volume"
            );
            some_recomputed = true;
        }
    }
    assert!(some_recomputed);
    common::assert_no_validation_messages(&gpu);
}

/// A whole restore in slabs of three z-slices (`Cao::restore_whole_by`, what a switch and a
/// new state do) leaves exactly the state the frames' own restores make: before every frame
/// of the scripted sequence (a probe included), one state is restored whole in slabs and the
/// other not, and after the frame both hold the same V_AO and O_c bits.
#[test]
fn a_whole_restore_in_slabs_leaves_the_frames_state() {
    let gpu = common::gpu();
    let vol = phantom::head(40);
    let (mut slabbed, _, _) = setup(&gpu, &vol);
    let (mut framed, _, _) = setup(&gpu, &vol);
    let placement = Placement::default();
    // O and V_PAO are 2 bytes each per voxel under LAO.
    let three_slices = 3 * 40 * 40 * 4;
    for (i, tools) in frames(placement.center).iter().enumerate() {
        slabbed.restore_whole_by(three_slices).unwrap();
        slabbed
            .run_frame(tools, &placement, Mode::Contextual)
            .unwrap();
        framed
            .run_frame(tools, &placement, Mode::Contextual)
            .unwrap();
        assert_same_state(&slabbed, &framed, i);
    }
    common::assert_no_validation_messages(&gpu);
}

/// Two CAO states after frame `i` hold the same V_AO and O_c bits.
pub fn assert_same_state(a: &Cao, b: &Cao, i: usize) {
    let diff = common::first_bit_difference(&read_ao(&a.ao), &read_ao(&b.ao));
    assert!(diff.is_none(), "frame {i}: V_AO differs at voxel {diff:?}");
    assert_eq!(
        a.read_clipped().unwrap(),
        b.read_clipped().unwrap(),
        "frame {i}: clipped opacity"
    );
}

/// Under LAO the GPU holds O_c only over the z-slices a frame's tools reach (`Cao::windowed`),
/// filled anew each frame, and whole while the SH visibility (which reads all of it) is on:
/// through the scripted sequence, with the SH radius set and cleared on the way, a windowed
/// state holds the same V_AO and O_c bits as one whose O_c is whole throughout, and a small
/// tool's window is a few slices.
#[test]
fn lao_holds_clipped_opacity_only_where_the_tools_reach() {
    let gpu = common::gpu();
    let vol = phantom::head(64);
    let (mut windowed, _, _) = setup(&gpu, &vol);
    let (mut whole, _, _) = setup(&gpu, &vol);
    whole.sh_radius_mm = Some(10.0);
    let placement = Placement::default();
    let c = placement.center;
    let small = vec![tool(
        Shape::Sphere,
        c,
        Quat::IDENTITY,
        0.01,
        ToolMode::Carve,
    )];
    let mut sequence = frames(c);
    sequence.push(small);
    for (i, tools) in sequence.iter().enumerate() {
        // Whole for two frames in the middle, as when the SH lighting is switched on and off.
        windowed.sh_radius_mm = (i == 4 || i == 5).then_some(10.0);
        for cao in [&mut windowed, &mut whole] {
            cao.run_frame(tools, &placement, Mode::Contextual).unwrap();
        }
        assert_eq!(windowed.windowed(), !(i == 4 || i == 5), "frame {i}");
        assert!(!whole.windowed());
        assert_same_state(&windowed, &whole, i);
        let (held, all) = (windowed.clipped().size, whole.clipped().size);
        assert!(held <= all, "frame {i}: {held} bytes of O_c, {all} whole");
    }
    // The small sphere's slices: its own, the dilation's and the LAO reach's either side.
    let [from, to] = windowed.clipped_slices();
    let all = whole.clipped_slices()[1];
    assert!(
        from > 0 && to < all && 2 * (to - from) < all,
        "slices {from}..{to} of {all} held"
    );
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_cut_is_where_the_tools_are() {
    let gpu = common::gpu();
    let vol = phantom::head(40);
    let (mut cao, o, pao) = setup(&gpu, &vol);
    let placement = Placement::default();
    let c = placement.center;
    let index_from_world = (world_from_tex(&vol, &placement)
        * glam::Mat4::from_scale(Vec3::new(1.0 / 40.0, 1.0 / 40.0, 1.0 / 40.0)))
    .inverse();
    let voxel_at = |w: Vec3| {
        let p = index_from_world.transform_point3(w);
        let q = p.to_array().map(|x| x.floor() as usize);
        q[0] + 40 * (q[1] + 40 * q[2])
    };
    // A sphere of 30 mm radius at the front of the head.
    let centre = c + Vec3::new(0.0, 0.02, 0.07);
    let tools = [tool(
        Shape::Sphere,
        centre,
        Quat::IDENTITY,
        0.03,
        ToolMode::Carve,
    )];
    cao.run_frame(&tools, &placement, Mode::Contextual).unwrap();
    let (ao, oc) = (read_ao(&cao.ao), cao.read_clipped().unwrap());
    let deep = voxel_at(centre + Vec3::new(0.0, 0.0, 0.012));
    assert!(o[deep] > 0.0, "the test voxel holds tissue before the cut");
    assert_eq!(
        (oc[deep], ao[deep]),
        (0.0, 1.0),
        "deep inside the tool: removed, AO 1"
    );
    // Voxels farther than the dilation radius from the sphere keep V_PAO exactly.
    let r_m = 0.03 + cao.dilation_radius_mm() as f32 * 1e-3 + 0.01;
    let mut checked = 0;
    for k in 0..40 {
        for j in 0..40 {
            for i in 0..40 {
                let w = world_from_tex(&vol, &placement).transform_point3(
                    Vec3::new(i as f32 + 0.5, j as f32 + 0.5, k as f32 + 0.5) / 40.0,
                );
                if (w - centre).length() > r_m {
                    let v = i + 40 * (j + 40 * k);
                    assert_eq!(
                        ao[v].to_bits(),
                        pao[v].to_bits(),
                        "voxel {i},{j},{k} far from the tool"
                    );
                    assert_eq!(oc[v], o[v]);
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 40 * 40 * 30);
    // A torus keeps the tissue in its hole (axis along the view, inside the head).
    let t = c + Vec3::new(0.0, 0.03, 0.0);
    let tools = [tool(
        Shape::Torus,
        t,
        Quat::IDENTITY,
        0.045,
        ToolMode::Carve,
    )];
    cao.run_frame(&tools, &placement, Mode::Contextual).unwrap();
    let oc = cao.read_clipped().unwrap();
    let hole = voxel_at(t);
    let tube = voxel_at(t + Vec3::new(0.045, 0.0, 0.0));
    assert!(
        o[hole] > 0.0 && o[tube] > 0.0,
        "test voxels hold tissue: {} {}",
        o[hole],
        o[tube]
    );
    assert_eq!(oc[hole], o[hole], "the hole is not cut");
    assert_eq!(oc[tube], 0.0, "the tube is");
    common::assert_no_validation_messages(&gpu);
}

/// Probes (only the inside kept) recompute only the voxels near their surface (the paper's
/// Sect. 3.4: a contraction instead of a dilation), clip everything beyond their box, and stay
/// bit-identical to the naive recompute on every frame: moving, growing, mixed with a carve
/// tool, and switching back to carving and to no tool.
#[test]
fn probes_cost_what_they_cover_and_stay_exact() {
    let gpu = common::gpu();
    let vol = phantom::head(40);
    let (mut cao, _, pao) = setup(&gpu, &vol);
    let (mut naive, _, _) = setup(&gpu, &vol);
    let placement = Placement::default();
    let c = placement.center;
    let total = (40 * 40 * 40) as u64;
    let probe = |r: f32, at: Vec3| tool(Shape::Sphere, c + at, Quat::IDENTITY, r, ToolMode::Probe);
    let carve = |r: f32, at: Vec3| tool(Shape::Sphere, c + at, Quat::IDENTITY, r, ToolMode::Carve);
    let mut seq: Vec<Vec<Tool>> = Vec::new();
    for r in [0.04, 0.06, 0.08] {
        seq.push(vec![probe(r, Vec3::ZERO)]);
        seq.push(vec![probe(r, Vec3::new(0.01, -0.005, 0.008))]);
    }
    seq.push(vec![
        probe(0.07, Vec3::ZERO),
        carve(0.03, Vec3::new(0.0, 0.02, 0.05)),
    ]);
    seq.push(vec![
        tool(
            Shape::Torus,
            c,
            Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
            0.06,
            ToolMode::Probe,
        ),
        carve(0.025, Vec3::new(0.03, 0.0, 0.0)),
    ]);
    seq.push(vec![carve(0.03, Vec3::new(0.0, 0.02, 0.05))]);
    seq.push(vec![probe(0.05, Vec3::new(0.02, 0.0, 0.0))]);
    seq.push(vec![]);
    let mut recomputed = Vec::new();
    for (i, tools) in seq.iter().enumerate() {
        let m = cao.run_frame(tools, &placement, Mode::Contextual).unwrap();
        let n = naive.run_frame(tools, &placement, Mode::Naive).unwrap();
        let (a, b) = (read_ao(&cao.ao), read_ao(&naive.ao));
        let diff = common::first_bit_difference(&a, &b);
        assert!(
            diff.is_none(),
            "frame {i}: CAO differs from naive LAO at voxel {diff:?}"
        );
        assert_eq!(
            cao.read_clipped().unwrap(),
            naive.read_clipped().unwrap(),
            "frame {i}: O_c"
        );
        assert_eq!(m.clipped, n.clipped, "frame {i}: clipped count");
        if i < 6 {
            recomputed.push(m.recomputed);
        }
        if i < 4 {
            // A probe of 40 or 60 mm: its box, not the volume (80 mm plus the reach covers the
            // 220 mm phantom).
            assert!(m.visited < total, "frame {i}: {m:?}");
        }
        if tools.is_empty() {
            assert_eq!(a, pao, "frame {i}: with no tool the AO is V_PAO again");
        }
    }
    println!("probe radius 40, 60, 80 mm: recomputed {recomputed:?}");
    // The recomputed voxels follow the probe's size: its surface, not the volume.
    assert!(
        recomputed[0] < recomputed[2] && recomputed[2] < recomputed[4],
        "{recomputed:?}"
    );
    // Deeper inside than the reach, a probe's voxels keep V_PAO.
    let big = cao
        .run_frame(&[probe(0.08, Vec3::ZERO)], &placement, Mode::Contextual)
        .unwrap();
    assert!(
        big.unaffected > 0,
        "the inside of a large probe keeps V_PAO: {big:?}"
    );
    common::assert_no_validation_messages(&gpu);
}

/// V_AO leaves out the bricks where every voxel's AO is 1 whatever a tool does (src/ao/pool.rs).
/// Under every method, with tools carving and a probe, its values and the pictures equal those
/// of V_AO stored whole, bit for bit, frame by frame: a head in the middle of a grid of air.
#[test]
fn v_ao_without_its_clear_bricks_equals_v_ao_stored_whole_bit_for_bit() {
    use cao_xr::ao::filtered::FilterParams;
    use cao_xr::ao::histogram::HistParams;
    use cao_xr::ao::{AoConfig, AoMethod};
    let gpu = common::gpu();
    let vol = cao_xr::app::bench_frame::padded(&phantom::head(32));
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let lao = LaoGpu::new(&gpu).unwrap();
    let placement = Placement::default();
    // The direct sums: clusters give the air AO slightly below 1, so no brick is left out.
    let histogram = HistParams {
        radius_mm: 12.0,
        bins: 16,
        clusters: 0,
        hemispheres: true,
    };
    let methods = [
        AoMethod::Lao,
        AoMethod::Filter(FilterParams::default()),
        AoMethod::Histogram(histogram),
    ];
    for method in methods {
        let config = AoConfig::new(method, PARAMS);
        let ao = cao_xr::app::precompute(&gpu, &lao, &vol, &tf, &config, false).unwrap();
        let mut every = ao.duplicate().unwrap().into_cao(&gpu, &vol).unwrap();
        every.store_in_bricks(Some(false)).unwrap();
        let mut pooled = ao.into_cao(&gpu, &vol).unwrap();
        // Without a budget, lavapipe's memory is the host's: V_AO is stored whole unless told.
        assert!(pooled.ao.whole());
        pooled.store_in_bricks(Some(true)).unwrap();
        let (kept, all) = pooled.ao.stored();
        let name = method.name();
        assert!(
            kept > 0 && kept < all,
            "{name}: {kept} of {all} bricks stored"
        );
        assert!(!pooled.ao.whole() && every.ao.whole());
        for (i, tools) in frames(placement.center).iter().enumerate() {
            pooled
                .run_frame(tools, &placement, Mode::Contextual)
                .unwrap();
            every
                .run_frame(tools, &placement, Mode::Contextual)
                .unwrap();
            let d = common::first_bit_difference(&read_ao(&pooled.ao), &read_ao(&every.ao));
            assert!(d.is_none(), "{name}, frame {i}: {d:?}");
            if i % 4 == 1 {
                let [a, b] = [&pooled, &every].map(|c| render(&gpu, &vol, c, tools, &placement));
                assert!(a.rgba == b.rgba, "{name}, frame {i}: the pictures differ");
            }
        }
    }
    common::assert_no_validation_messages(&gpu);
}
