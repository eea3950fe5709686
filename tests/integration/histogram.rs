//! Local-histogram AO (Ropinski et al.) on lavapipe with validation on: the GPU's direct sums
//! against the CPU reference of docs/design.md's definition, analytic cases, the clustering
//! against the direct sums, the per-frame clip update against a direct recompute bit for bit, a
//! TF change as a table update, and the on-disk cache.

use crate::cao::{frames, read_ao};
use crate::common;

use cao_xr::ao::cao::{Cao, Mode};
use cao_xr::ao::histogram::{self, HistParams};
use cao_xr::ao::{AoConfig, AoMethod, LaoGpu, LaoParams};
use cao_xr::app::{histogram_state, precompute_histogram};
use cao_xr::gpu::{Buffer, Gpu};
use cao_xr::scene::ToolMode;
use cao_xr::space::Placement;
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{phantom, Modality, Volume, Voxels};
use glam::{DMat3, DVec3};

fn e_of(b: &Buffer) -> Vec<[f32; 3]> {
    bytemuck::cast_slice::<u8, u32>(&b.read_back().unwrap())
        .iter()
        .map(|&x| [0, 8, 16].map(|s| ((x >> s) & 0xff) as f32 / 255.0))
        .collect()
}

/// A cache folder of this test's own (made when the method writes its cache).
fn cache(tag: &str) -> common::Scratch {
    common::scratch("lh", tag)
}

/// The CAO state of the method on `vol` under `tf`, and its q (host).
fn setup(
    gpu: &Gpu,
    vol: &Volume,
    tf: &TransferFunction,
    p: HistParams,
    tag: &str,
) -> (Cao, Vec<f32>) {
    let lao = LaoGpu::new(gpu).unwrap();
    let h = histogram_state(gpu, vol, p, Some(&cache(tag)), false).unwrap();
    let v = precompute_histogram(gpu, &lao, vol, tf, &LaoParams::default(), h).unwrap();
    let q = v.opacity.clone();
    (v.into_cao(gpu, vol).unwrap(), q)
}

fn volume(dims: [usize; 3], spacing: f64, v: Vec<f32>) -> Volume {
    Volume {
        whole_range: None,
        name: "test".into(),
        dims,
        spacing: [spacing; 3],
        directions: DMat3::IDENTITY,
        origin: DVec3::ZERO,
        modality: Modality::Unknown,
        voxels: Voxels::F32(v),
        labels: None,
    }
}

/// Transparent below half the range, then opaque red towards the top.
fn red_tf() -> TransferFunction {
    TransferFunction::from_json(
        r#"{"name":"red","domain":"normalized","points":[
            {"value":0.0,"color":[0,0,0],"alpha":0.0},
            {"value":0.5,"color":[1,0,0],"alpha":0.0},
            {"value":1.0,"color":[1,0,0],"alpha":1.0}]}"#,
    )
    .unwrap()
}

#[test]
fn the_gpu_direct_sums_agree_with_the_cpu_reference() {
    let gpu = common::gpu();
    let vol = phantom::head(32);
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let mut sphere = Vec::new();
    for hemispheres in [false, true] {
        // 6.9 mm voxels: r = 20 mm reaches two voxels along each axis.
        let p = HistParams {
            radius_mm: 20.0,
            bins: 32,
            clusters: 0,
            hemispheres,
        };
        let (cao, q) = setup(&gpu, &vol, &tf, p, "reference");
        let h = cao.histogram().unwrap();
        let (want_q, shades, table) = histogram::direct_inputs(&vol, &tf, p.bins, &[]);
        assert_eq!(q, want_q);
        let nb = histogram::Neighbourhood::new(p.radius_mm, vol.spacing);
        let splits = if hemispheres {
            histogram::splits(&vol)
        } else {
            Vec::new()
        };
        let (want_a, want_e) =
            histogram::direct_reference(vol.dims, &q, &shades, &table, &nb, &splits);
        let got_a = read_ao(&cao.ao);
        let what = format!("the direct sums, hemispheres {hemispheres}");
        common::assert_agrees(&got_a, &want_a, &what);
        // Some bricks are clear (the shader skips their sums), some are not.
        let clear: u32 = histogram::clear_bricks(vol.dims, &q, h.reach_voxels())
            .iter()
            .map(|w| w.count_ones())
            .sum();
        assert!((1..64).contains(&clear), "{clear} of 64 bricks clear");
        assert!(
            got_a.iter().any(|&a| a < 0.7),
            "the phantom occludes somewhere"
        );
        if hemispheres {
            // The front faces away from the skin: outside it, the AO opens.
            let opened = got_a.iter().zip(&sphere).filter(|(h, s)| *h > *s).count();
            assert!(opened > got_a.len() / 20, "{opened} voxels opened");
            assert!(splits.iter().any(|s| s.is_none()), "some flat voxels");
        } else {
            sphere = got_a.clone();
        }
        // E is stored as 8 bits per channel.
        let got_e = e_of(&h.pre_e);
        for (i, (g, w)) in got_e.iter().zip(&want_e).enumerate() {
            for c in 0..3 {
                assert!(
                    (g[c] - w[c]).abs() <= 0.5 / 255.0 + 1e-4,
                    "voxel {i}: E {g:?} vs {w:?}"
                );
            }
        }
        assert!(want_e.iter().any(|e| e[0] > 0.1), "some bleeding colour");
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn analytic_cases_empty_opaque_and_one_coloured_voxel() {
    let gpu = common::gpu();
    let n = 15;
    let p = HistParams {
        radius_mm: 4.0,
        bins: 4,
        clusters: 0,
        // One sphere: the definitions this test checks.
        hemispheres: false,
    };
    // Empty: every voxel open, no colour.
    let (cao, _) = setup(
        &gpu,
        &volume([n; 3], 1.0, vec![0.0; n * n * n]),
        &red_tf(),
        p,
        "empty",
    );
    assert!(read_ao(&cao.ao).iter().all(|&a| a == 1.0));
    assert!(e_of(&cao.histogram().unwrap().pre_e)
        .iter()
        .all(|e| *e == [0.0; 3]));

    // Uniform and opaque: every voxel but one (the range's bottom, far away) in the top bin,
    // whose opacity is 0.75; deep inside O_env = q everywhere, so A = 1 - q.
    let mut v = vec![0.0f32; n * n * n];
    v[0] = -1.0; // the range's bottom, so the rest sits in the top bin
    for x in v.iter_mut().skip(1) {
        *x = 1.0;
    }
    let (cao, q) = setup(&gpu, &volume([n; 3], 1.0, v), &red_tf(), p, "opaque");
    let centre = n / 2 + n * (n / 2 + n * (n / 2));
    let a = read_ao(&cao.ao);
    assert!((q[centre] - 0.75).abs() < 1e-6, "{}", q[centre]);
    assert!((a[centre] - 0.25).abs() < 1e-5, "{}", a[centre]);

    // One opaque red voxel at the centre: its neighbours' O_env falls off as 1/d^2 within r,
    // is 0 beyond, and their bleeding colour is red.
    let mut v = vec![0.0f32; n * n * n];
    v[centre] = 1.0;
    let (cao, q) = setup(&gpu, &volume([n; 3], 1.0, v), &red_tf(), p, "single");
    let a = read_ao(&cao.ao);
    let e = e_of(&cao.histogram().unwrap().pre_e);
    let nb = histogram::Neighbourhood::new(4.0, [1.0; 3]);
    let occ = |d: usize| 1.0 - a[centre + d] as f64;
    for d in 1..=4 {
        let want = q[centre] as f64 / (d * d) as f64 / nb.total;
        assert!(
            (occ(d) - want).abs() < 1e-6 + cao_xr::ao::stored::ROUNDING as f64,
            "d = {d}: {} vs {want}",
            occ(d)
        );
        assert_eq!(e[centre + d], [1.0, 0.0, 0.0], "d = {d}");
    }
    assert!((occ(1) / occ(2) - 4.0).abs() < 1e-3, "1/d^2");
    assert_eq!(a[centre + 5], 1.0, "beyond r");
    assert_eq!(e[centre + 5], [0.0; 3]);
    assert_eq!(a[centre], 1.0, "the voxel itself is not in S_r");
    common::assert_no_validation_messages(&gpu);
}

/// Every voxel's local histograms as the clustering's rows are laid out (H_f's then H_b's with
/// the hemispheres, a flat voxel's second row marked by -1), in f64 from the definitions.
fn local_rows_reference(vol: &Volume, p: HistParams) -> (Vec<f64>, usize) {
    let shades =
        histogram::Shades::new(histogram::bins(vol, p.bins), p.bins, vol.labels.as_deref());
    let nb = histogram::Neighbourhood::new(p.radius_mm, vol.spacing);
    let splits = if p.hemispheres {
        histogram::splits(vol)
    } else {
        vec![None; vol.voxel_count()]
    };
    let (b, d) = (shades.count(), vol.dims);
    let mut rows = Vec::new();
    for (i, split) in splits.iter().enumerate() {
        let v = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])].map(|x| x as i32);
        // Per hemisphere (0: front, 1: back): the sums and the weights' total.
        let (mut h, mut total) = (vec![vec![0.0; b]; 2], [0.0; 2]);
        for (o, w) in nb.offsets.iter().zip(&nb.weights) {
            let back = split.is_some_and(|s| (0..3).map(|a| o[a] as f64 * s[a]).sum::<f64>() > 0.0);
            total[back as usize] += w;
            let u: [i32; 3] = std::array::from_fn(|a| v[a] + o[a]);
            if (0..3).all(|a| u[a] >= 0 && u[a] < d[a] as i32) {
                let j = u[0] as usize + d[0] * (u[1] as usize + d[1] * u[2] as usize);
                h[back as usize][shades.ids[j] as usize] += w;
            }
        }
        match split {
            Some(_) => {
                for (row, t) in h.iter().zip(total) {
                    rows.extend(row.iter().map(|x| if t > 0.0 { x / t } else { 0.0 }));
                }
            }
            None => {
                rows.extend(h[0].iter().map(|x| x / nb.total));
                if p.hemispheres {
                    rows.push(-1.0);
                    rows.extend(std::iter::repeat_n(0.0, b - 1));
                }
            }
        }
    }
    (rows, b)
}

/// The head phantom at 16^3 with a label map of 7 structures in every voxel: 557 shades at 128
/// bins.
fn seven_structures_everywhere() -> Volume {
    let mut many = phantom::head(16);
    let ids: Vec<u8> = (0..many.voxel_count()).map(|i| (i % 7) as u8 + 1).collect();
    let structures = (0..7)
        .map(|k| cao_xr::volume::labels::Structure {
            value: k + 1,
            name: format!("s{k}"),
            colour: [0.5; 3],
            opacity: 1.0,
            protected: false,
            margin_mm: None,
            voxels: 0,
        })
        .collect();
    many.labels = Some(std::sync::Arc::new(cao_xr::volume::labels::LabelMap {
        source: "test".into(),
        ids,
        structures,
    }));
    many
}

#[test]
fn the_gpu_local_histograms_are_the_definitions_with_few_shades_and_with_many() {
    // histogram_local.comp sums a voxel's rows in an array of its own up to 512 shades, and in
    // the rows in memory past that: both are checked against the definitions, hemispheres on.
    let gpu = common::gpu();
    for (vol, bins, fewer) in [
        (phantom::head(16), 32, true),
        (seven_structures_everywhere(), 128, false),
    ] {
        let p = HistParams {
            radius_mm: 30.0,
            bins,
            clusters: 0,
            hemispheres: true,
        };
        let (want, shades) = local_rows_reference(&vol, p);
        assert_eq!(shades <= 512, fewer, "{shades} shades");
        let h = histogram_state(&gpu, &vol, p, None, false).unwrap();
        let voxels: Vec<u32> = (0..vol.voxel_count() as u32).collect();
        let got = h.local_histograms(&voxels, None).unwrap();
        assert_eq!(got.len(), want.len());
        let worst = got
            .iter()
            .zip(&want)
            .map(|(&g, &w)| (g as f64 - w).abs())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-5,
            "{shades} shades: max |GPU - definition| = {worst}"
        );
        let split = want
            .chunks(shades)
            .skip(1)
            .step_by(2)
            .filter(|r| r[0] >= 0.0)
            .count();
        assert!(split > 100, "{split} voxels split");
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_host_sums_the_local_histograms_as_the_gpu_does_bit_for_bit() {
    // A CPU renderer's clustering sums the rows on the host (histogram::local_rows_f32): the
    // same bits as histogram_local.comp, for integer and float scalars, with one sphere and
    // with the hemispheres (flat voxels and split ones, at the border and inside), and past
    // 512 shades.
    let gpu = common::gpu();
    let head = phantom::head(16);
    let float = Volume {
        voxels: Voxels::F32(
            (0..head.voxel_count())
                .map(|i| head.voxels.get(i) * 0.37 + 0.1)
                .collect(),
        ),
        spacing: [6.0, 7.0, 9.0],
        ..phantom::head(16)
    };
    let cases = [
        ("integer", head.clone(), 32, true),
        ("integer", head, 32, false),
        ("float", float, 32, true),
        ("labelled", seven_structures_everywhere(), 128, true),
    ];
    for (scalars, vol, bins, hemispheres) in cases {
        let p = HistParams {
            radius_mm: 30.0,
            bins,
            clusters: 0,
            hemispheres,
        };
        let h = histogram_state(&gpu, &vol, p, None, false).unwrap();
        let voxels: Vec<u32> = (0..vol.voxel_count() as u32).rev().collect();
        let want = h.local_histograms(&voxels, None).unwrap();
        let got = h.local_histograms(&voxels, Some(&vol)).unwrap();
        if let Some(i) = common::first_bit_difference(&got, &want) {
            panic!(
                "{scalars} scalars, {bins} bins, hemispheres {hemispheres}: row entry {i} is {} \
                 on the host, {} on the GPU",
                got[i], want[i]
            );
        }
        assert!(want.iter().filter(|&&x| x > 0.0).count() > voxels.len());
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_gpu_clustering_is_its_cpu_twins() {
    // The GPU's rows (checked above against the definitions), trained and assigned on the host
    // as the docs say: LBG on the training sample's packed rows, then each row to its nearest
    // centroid among the nearest groups' members. histogram_assign.comp sums its distances in
    // the twin's order, so every row lands in the twin's cluster.
    let gpu = common::gpu();
    let vol = phantom::head(20);
    let p = HistParams {
        radius_mm: 24.0,
        bins: 32,
        clusters: 128,
        hemispheres: true,
    };
    let mut h = histogram_state(&gpu, &vol, p, None, false).unwrap();
    let shades = histogram::Shades::new(histogram::bins(&vol, p.bins), p.bins, None);
    let b = shades.count();
    let packing = histogram::Packing::new(&shades.ids, b, histogram::packed_dims(b));
    let dim = packing.packed;
    let pack_rows = |rows: &[f32]| -> Vec<Option<Vec<f32>>> {
        rows.chunks(b)
            .map(|r| (r[0] >= 0.0).then(|| packing.pack(r)))
            .collect()
    };
    let sample = h.training_sample();
    let trained: Vec<f32> = pack_rows(&h.local_histograms(&sample, None).unwrap())
        .into_iter()
        .flatten()
        .flatten()
        .collect();
    let centroids = histogram::lbg(&trained, dim, p.clusters);
    let groups = histogram::Groups::new(&centroids, dim);
    let all: Vec<u32> = (0..vol.voxel_count() as u32).collect();
    let mut want = Vec::new();
    for row in pack_rows(&h.local_histograms(&all, None).unwrap()) {
        // A flat voxel's second row takes its first's cluster.
        let c = match row {
            Some(packed) => groups.assign(&centroids, dim, &packed),
            None => *want.last().unwrap(),
        };
        want.push(c);
    }
    // Summed and assigned by the shaders, and on the host (a CPU renderer's default).
    for on_host in [false, true] {
        let got = h.recluster(&vol, on_host).unwrap();
        assert_eq!(got.ids.len(), want.len());
        let same = got.ids.iter().zip(&want).filter(|(g, w)| g == w).count();
        assert_eq!(
            same,
            want.len(),
            "on the host {on_host}: rows in the twin's cluster"
        );
        let used = got
            .ids
            .iter()
            .collect::<std::collections::HashSet<_>>()
            .len();
        assert!(used > 64, "{used} clusters used");
        assert!(
            Some(&got) == h.clusters(),
            "on the host {on_host}: not the clustering the state was made with"
        );
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_clustering_is_close_to_the_direct_sums_and_its_cache_is_reused_and_checked() {
    let gpu = common::gpu();
    let vol = phantom::head(20);
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let direct = HistParams {
        radius_mm: 24.0,
        bins: 32,
        clusters: 0,
        // One sphere: the definitions this test checks.
        hemispheres: false,
    };
    let clustered = HistParams {
        clusters: 512,
        ..direct
    };
    let (d, q) = setup(&gpu, &vol, &tf, direct, "direct");
    let dir = cache("clustered");
    let lao = LaoGpu::new(&gpu).unwrap();
    let run = |expect_cached: bool| {
        let h = histogram_state(&gpu, &vol, clustered, Some(&dir), false).unwrap();
        assert_eq!(h.timing.cached, expect_cached);
        let ids = h.clusters().unwrap().ids.clone();
        let v = precompute_histogram(&gpu, &lao, &vol, &tf, &LaoParams::default(), h).unwrap();
        (read_ao(&v.ao_buf), ids)
    };
    let (a, ids) = run(false);
    let want = read_ao(&d.ao);
    let (mut sum, mut count) = (0.0, 0);
    for i in 0..a.len() {
        if q[i] > 0.001 {
            sum += (a[i] as f64 - want[i] as f64).abs();
            count += 1;
        }
    }
    let mean = sum / count.max(1) as f64;
    assert!(
        count > 100 && mean <= 0.03,
        "mean |clustered - direct| = {mean} over {count}"
    );
    assert!(a != want, "the clusters are not the direct sums");
    assert!(
        ids.iter().collect::<std::collections::HashSet<_>>().len() > 64,
        "many clusters used"
    );
    // The second start reads the cache and gets the same clustering.
    let (b, ids2) = run(true);
    assert_eq!(ids, ids2);
    assert!(a == b);
    // A truncated cache is rebuilt, not trusted.
    let file = std::fs::read_dir(&dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let bytes = std::fs::read(&file).unwrap();
    std::fs::write(&file, &bytes[..bytes.len() / 2]).unwrap();
    let (c, _) = run(false);
    assert!(a == c);
    assert_eq!(
        std::fs::read(&file).unwrap().len(),
        bytes.len(),
        "rewritten whole"
    );
    // Two hemispheres: two histograms per voxel in one codebook, the front's values close to
    // the front's direct sums (and not the sphere's); their cache entry is their own.
    let hemispheres = |clusters| HistParams {
        clusters,
        hemispheres: true,
        ..direct
    };
    let (dh, _) = setup(&gpu, &vol, &tf, hemispheres(0), "direct-hemispheres");
    let want_h = read_ao(&dh.ao);
    let run_h = |expect_cached: bool| {
        let h = histogram_state(&gpu, &vol, hemispheres(512), Some(&dir), false).unwrap();
        assert_eq!(h.timing.cached, expect_cached);
        assert_eq!(h.clusters().unwrap().ids.len(), 2 * a.len());
        let v = precompute_histogram(&gpu, &lao, &vol, &tf, &LaoParams::default(), h).unwrap();
        read_ao(&v.ao_buf)
    };
    let ah = run_h(false);
    let mean_to = |want: &[f32]| {
        let (sum, count) = (0..a.len())
            .filter(|&i| q[i] > 0.001)
            .fold((0.0, 0), |(s, c), i| {
                (s + (ah[i] as f64 - want[i] as f64).abs(), c + 1)
            });
        sum / count as f64
    };
    let (to_front, to_sphere) = (mean_to(&want_h), mean_to(&want));
    assert!(
        to_front <= 0.03 && to_front < to_sphere / 2.0,
        "mean |clustered - direct|: {to_front} to the front's, {to_sphere} to the sphere's"
    );
    assert!(run_h(true) == ah, "the cached hemispheres");
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn under_a_small_gpu_budget_the_clustering_runs_in_smaller_batches_to_the_same_clusters() {
    // The clustering's transient histogram rows are sized by what the budget leaves: under half
    // of the unbudgeted peak they come in several batches, with the same clusters bit for bit.
    let gpu = common::gpu();
    let vol = phantom::head(20);
    let params = HistParams {
        radius_mm: 24.0,
        bins: 32,
        clusters: 256,
        hemispheres: true,
    };
    let cluster = |gpu: &Gpu| {
        let base = gpu.memory_in_use();
        gpu.reset_memory_peak();
        let h = histogram_state(gpu, &vol, params, None, false).unwrap();
        let c = h.clusters().unwrap();
        let out = (c.ids.clone(), c.reps.clone());
        drop(h);
        (out, gpu.memory_peak() - base)
    };
    let (whole, peak) = cluster(&gpu);
    gpu.set_memory_budget(Some(gpu.memory_in_use() + peak / 2));
    let (batched, peak_batched) = cluster(&gpu);
    assert!(peak_batched <= peak / 2, "{peak_batched} of {peak} bytes");
    assert!(whole == batched, "the same clusters");
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_clip_update_equals_a_direct_recompute_of_the_affected_voxels_bit_for_bit_every_frame() {
    let gpu = common::gpu();
    let vol = phantom::head(32);
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let placement = Placement::default();
    for (clusters, hemispheres) in [(0, false), (128, false), (0, true), (128, true)] {
        let p = HistParams {
            radius_mm: 14.0,
            bins: 16,
            clusters,
            hemispheres,
        };
        let (mut cao, _) = setup(&gpu, &vol, &tf, p, "frames");
        let (mut naive, _) = setup(&gpu, &vol, &tf, p, "frames");
        let pre = read_ao(&cao.ao);
        let pre_e = cao.histogram().unwrap().precomputed_e().unwrap();
        if clusters > 0 {
            // Each voxel's precomputed E is its (front) cluster's, in 8 bits.
            let (_, _, table) = histogram::direct_inputs(&vol, &tf, p.bins, &[]);
            let c = cao.histogram().unwrap().clusters().unwrap();
            let reps = c.tf_table(&table);
            let step = 1 + hemispheres as usize;
            for (v, e) in e_of(&pre_e).iter().enumerate() {
                let want = reps[c.ids[step * v] as usize];
                assert!(
                    (0..3).all(|k| (e[k] - want[k]).abs() <= 0.5 / 255.0 + 1e-4),
                    "N = {clusters}, voxel {v}: E {e:?}, its cluster's {want:?}"
                );
            }
        }
        let pre_e = pre_e.read_back().unwrap();
        let mut some = false;
        for (i, tools) in frames(placement.center).iter().enumerate() {
            let m = cao.run_frame(tools, &placement, Mode::Contextual).unwrap();
            naive.run_frame(tools, &placement, Mode::Naive).unwrap();
            let (a, b) = (read_ao(&cao.ao), read_ao(&naive.ao));
            let ea = cao.histogram().unwrap().e.read_back().unwrap();
            let eb = naive.histogram().unwrap().e.read_back().unwrap();
            let (ea, eb, pe): (&[u32], &[u32], &[u32]) = (
                bytemuck::cast_slice(&ea),
                bytemuck::cast_slice(&eb),
                bytemuck::cast_slice(&pre_e),
            );
            let mask = cao.read_mask().unwrap();
            for v in 0..a.len() {
                let ok = match mask[v] {
                    // Affected: the direct sums on the clipped volume, as the naive pass.
                    1 => a[v].to_bits() == b[v].to_bits() && ea[v] == eb[v],
                    // Unaffected: the precomputed (clustered or direct) values.
                    2 => a[v].to_bits() == pre[v].to_bits() && ea[v] == pe[v],
                    _ => a[v] == 1.0 && b[v] == 1.0,
                };
                assert!(
                    ok,
                    "N = {clusters}, frame {i}, voxel {v} (category {}): {} vs naive {} / pre {}",
                    mask[v], a[v], b[v], pre[v]
                );
            }
            if clusters == 0 {
                assert!(
                    a == b && ea == eb,
                    "N = 0, frame {i}: equal to the direct sums everywhere"
                );
            }
            if tools.is_empty() {
                assert!(a == pre, "frame {i}: with no tool the AO is V_PAO again");
            } else if tools[0].mode == ToolMode::Carve {
                some |= m.recomputed > 0 && a != pre;
                assert!(
                    m.visited < (32 * 32 * 32) as u64,
                    "frame {i}: boxes, not the volume"
                );
            }
        }
        assert!(some, "N = {clusters}: some frame recomputed something");
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn a_tf_change_is_a_table_update_shown_in_the_next_frame() {
    use cao_xr::app::frame_loop::FrameLoop;
    use cao_xr::input::{FrameInput, InteractionSettings};
    use cao_xr::space::{default_stereo_views, DEFAULT_IPD};
    use std::sync::Arc;
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(24));
    let p = HistParams {
        radius_mm: 20.0,
        bins: 32,
        clusters: 64,
        ..Default::default()
    };
    let skin = TransferFunction::preset("ct-skin").unwrap();
    // The same opacities in other colours: A stays, E changes.
    let mut recoloured = skin.clone();
    recoloured.name = "ct-skin-blue".into();
    for pt in &mut recoloured.points {
        pt.color = [pt.color[2], pt.color[1], pt.color[0]];
    }
    let bone = TransferFunction::preset("ct-bone").unwrap();
    let ao = AoConfig::new(AoMethod::Histogram(p), LaoParams::default());
    // The default cache: the phantom's clustering at these parameters is small.
    let mut fl = FrameLoop::new(
        &gpu,
        Arc::clone(&vol),
        vec![skin.clone(), recoloured, bone.clone()],
        ao,
        (32, 32),
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    let views = default_stereo_views(&vol, &Placement::default(), DEFAULT_IPD);
    let frame = |fl: &mut FrameLoop, i: usize, menu: bool| {
        let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
        input.hands[0].buttons.menu = menu;
        fl.frame(&input).unwrap()
    };
    let f0 = frame(&mut fl, 0, false);
    let (a0, e0) = (
        read_ao(&fl.cao.ao),
        fl.cao.histogram().unwrap().e.read_back().unwrap(),
    );
    let f1 = frame(&mut fl, 1, true);
    assert!(f1.stats.tf_progress.is_none(), "no progressive switch");
    assert_eq!(
        fl.shown_tf().name,
        "ct-skin-blue",
        "switched in the frame of the press"
    );
    assert!(
        read_ao(&fl.cao.ao) == a0,
        "no bin's opacity changed: A unchanged"
    );
    assert!(
        fl.cao.histogram().unwrap().e.read_back().unwrap() != e0,
        "E follows the colours"
    );
    assert!(f1.image != f0.image);
    frame(&mut fl, 2, false);
    frame(&mut fl, 3, true);
    assert_eq!(fl.shown_tf().name, "ct-bone");
    let got = read_ao(&fl.cao.ao);
    assert!(got != a0, "new opacities: new A");
    // ...equal to a fresh precompute under the new TF.
    let lao = LaoGpu::new(&gpu).unwrap();
    let h = histogram_state(&gpu, &vol, p, Some(&histogram::default_cache_dir()), false).unwrap();
    let fresh = precompute_histogram(&gpu, &lao, &vol, &bone, &LaoParams::default(), h).unwrap();
    assert!(
        got == read_ao(&fresh.ao_buf),
        "equal to a fresh precompute under ct-bone"
    );
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_stick_click_leaves_the_local_histograms_and_comes_back_to_them() {
    use cao_xr::app::frame_loop::FrameLoop;
    use cao_xr::input::{FrameInput, InteractionSettings};
    use cao_xr::space::{default_stereo_views, DEFAULT_IPD};
    use std::sync::Arc;
    let gpu = common::gpu();
    let vol = Arc::new(phantom::head(20));
    let p = HistParams {
        radius_mm: 24.0,
        bins: 16,
        clusters: 32,
        ..Default::default()
    };
    let lao = LaoParams {
        rays: 6,
        steps: 4,
        step_mm: 4.0,
    };
    let ao = AoConfig::new(AoMethod::Histogram(p), lao);
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let mut fl = FrameLoop::new(
        &gpu,
        Arc::clone(&vol),
        vec![tf],
        ao,
        (24, 24),
        InteractionSettings::default(),
        false,
    )
    .unwrap();
    fl.tf_samples_per_frame = 1e9;
    let names: Vec<String> = fl.ao_methods().iter().map(|m| m.name()).collect();
    assert_eq!(names[..2], ["histogram", "lao"]);
    let views = default_stereo_views(&vol, &Placement::default(), DEFAULT_IPD);
    let mut i = 0;
    let mut click = |fl: &mut FrameLoop| {
        // A press, then frames until no switch is in flight.
        for n in 0..50 {
            let mut input = FrameInput::without_hands(i as f64 / 60.0, views);
            input.hands[1].buttons.stick_click = n == 0;
            i += 1;
            if fl.frame(&input).unwrap().stats.tf_progress.is_none() && n > 0 {
                return;
            }
        }
        panic!("the switch never finished");
    };
    let first = read_ao(&fl.cao.ao);
    let first_frame = fl
        .frame(&FrameInput::without_hands(0.0, views))
        .unwrap()
        .image;
    click(&mut fl);
    assert_eq!(fl.cao.method_name(), "lao");
    assert!(read_ao(&fl.cao.ao) != first);
    for _ in 0..names.len() - 1 {
        click(&mut fl);
    }
    assert_eq!(fl.cao.method_name(), "histogram");
    assert!(
        read_ao(&fl.cao.ao) == first,
        "back to the same clustered AO"
    );
    let back = fl
        .frame(&FrameInput::without_hands(9.0, views))
        .unwrap()
        .image;
    assert!(
        back == first_frame,
        "and the same picture, bleeding included"
    );
    common::assert_no_validation_messages(&gpu);
}

/// docs/design.md's direct local-histogram AO with labels, written here from the definition
/// alone: q(u) = alpha(bin centre) times the structure's a_l (`shown`, by structure index), a
/// labelled member's colour its structure's, W over every member of S_r. Returns A and E (f64).
#[allow(clippy::type_complexity)]
fn direct_with_labels(
    vol: &Volume,
    tf: &TransferFunction,
    b: usize,
    r: f64,
    shown: &[f32],
) -> (Vec<f64>, Vec<[f64; 3]>) {
    let (lo, hi) = vol.value_range();
    let (lo, span) = (lo as f64, hi as f64 - lo as f64);
    let labels = vol.labels.as_deref().unwrap();
    let dims = vol.dims.map(|d| d as i64);
    let s = vol.spacing;
    let s_min = s.iter().copied().fold(f64::INFINITY, f64::min);
    let shade = |u: usize| -> (f64, [f64; 3]) {
        let k = ((b as f64 * (vol.voxels.get(u) as f64 - lo) / span).floor() as usize).min(b - 1);
        let c = tf.eval(
            (lo + (k as f64 + 0.5) * span / b as f64) as f32,
            vol.value_range(),
        );
        let alpha = c[3] as f64;
        match labels.ids[u] as usize {
            0 => (alpha, [c[0], c[1], c[2]].map(|x| x as f64)),
            id => (
                alpha * shown[id - 1] as f64,
                labels.structures[id - 1].colour.map(|x| x as f64),
            ),
        }
    };
    let reach = s.map(|x| (r / x).floor() as i64);
    let mut members = Vec::new();
    for z in -reach[2]..=reach[2] {
        for y in -reach[1]..=reach[1] {
            for x in -reach[0]..=reach[0] {
                let d = ((x as f64 * s[0]).powi(2)
                    + (y as f64 * s[1]).powi(2)
                    + (z as f64 * s[2]).powi(2))
                .sqrt();
                if d > 0.0 && d <= r {
                    members.push(([x, y, z], (s_min / d).powi(2)));
                }
            }
        }
    }
    let total: f64 = members.iter().map(|m| m.1).sum();
    let n = vol.voxel_count();
    (0..n)
        .map(|i| {
            let v = [
                i as i64 % dims[0],
                (i as i64 / dims[0]) % dims[1],
                i as i64 / (dims[0] * dims[1]),
            ];
            let (mut occ, mut rgb) = (0.0, [0.0; 3]);
            for (o, w) in &members {
                let u = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
                if (0..3).any(|a| u[a] < 0 || u[a] >= dims[a]) {
                    continue;
                }
                let (q, c) = shade((u[0] + dims[0] * (u[1] + dims[1] * u[2])) as usize);
                occ += w * q;
                for ch in 0..3 {
                    rgb[ch] += w * q * c[ch];
                }
            }
            let e = if occ > 0.0 {
                rgb.map(|x| x / occ)
            } else {
                [0.0; 3]
            };
            (1.0 - occ / total, e)
        })
        .unzip()
}

/// With a label map the histogram method's AO is that of what is shown (docs/design.md, O =
/// a_l · tf_alpha, a labelled voxel's colour its structure's): the GPU's direct sums equal an
/// implementation of the definition written in this test, as the label map shows the
/// structures and after the structure menu hides one and shows another translucent.
/// The 20³ head phantom with a green structure in its lower half and a blue one in a column
/// through the middle.
fn labelled_head() -> Volume {
    use cao_xr::volume::labels::{LabelMap, Structure};
    let n = 20;
    let mut vol = phantom::head(n);
    // A green structure in the lower half, a blue one in a column through the middle.
    let ids: Vec<u8> = (0..vol.voxel_count())
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            if (x as i32 - 10).abs() < 3 && (y as i32 - 10).abs() < 3 {
                2
            } else if z < n / 2 {
                1
            } else {
                0
            }
        })
        .collect();
    let structure = |name: &str, colour| Structure {
        value: 1,
        name: name.into(),
        colour,
        opacity: 1.0,
        protected: false,
        margin_mm: None,
        voxels: 0,
    };
    vol.labels = Some(std::sync::Arc::new(LabelMap {
        source: "test".into(),
        ids,
        structures: vec![
            structure("green", [0.1, 0.9, 0.2]),
            structure("blue", [0.1, 0.2, 0.9]),
        ],
    }));
    vol
}

/// What the structure menu does: the method's tables for the structures as `shown` (one table
/// update), then a frame with no tool.
fn show_structures(gpu: &Gpu, cao: &mut Cao, vol: &Volume, tf: &TransferFunction, shown: &[f32]) {
    let lao = LaoGpu::new(gpu).unwrap();
    let h = cao.histogram_mut().unwrap();
    let t = cao_xr::app::histogram_tables(gpu, &lao, vol.dims, h, (tf, shown)).unwrap();
    cao.replace_precomputed(t.opacity, t.pao).unwrap();
    cao.run_frame(&[], &Placement::default(), Mode::Contextual)
        .unwrap();
}

#[test]
fn the_direct_sums_follow_the_structures_shown_and_their_colours() {
    let gpu = common::gpu();
    let vol = labelled_head();
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let p = HistParams {
        radius_mm: 30.0,
        bins: 16,
        clusters: 0,
        // One sphere: the definitions this test checks.
        hemispheres: false,
    };
    let (mut cao, _) = setup(&gpu, &vol, &tf, p, "labels");
    let check = |cao: &Cao, shown: &[f32], what: &str| {
        let (want_a, want_e) = direct_with_labels(&vol, &tf, p.bins, p.radius_mm, shown);
        let want_a: Vec<f32> = want_a.iter().map(|&a| a as f32).collect();
        common::assert_agrees(&read_ao(&cao.ao), &want_a, what);
        let got_e = e_of(&cao.histogram().unwrap().pre_e);
        for (i, (g, w)) in got_e.iter().zip(&want_e).enumerate() {
            for c in 0..3 {
                assert!(
                    (g[c] as f64 - w[c]).abs() <= 0.5 / 255.0 + 1e-4,
                    "{what}: voxel {i}: E {g:?} vs {w:?}"
                );
            }
        }
        (want_a, want_e)
    };
    let (a_shown, e_shown) = check(&cao, &[1.0, 1.0], "structures shown");
    assert!(
        e_shown.iter().any(|e| e[1] > 0.5) && e_shown.iter().any(|e| e[2] > 0.5),
        "the structures' colours bleed"
    );
    // The menu hides the green one and shows the blue one translucent: one table update.
    let shown = [0.0, 0.3];
    show_structures(&gpu, &mut cao, &vol, &tf, &shown);
    let (a_hidden, _) = check(&cao, &shown, "green hidden, blue translucent");
    assert!(
        a_hidden.iter().zip(&a_shown).any(|(h, s)| h - s > 0.05),
        "hiding a structure opens its surroundings"
    );
    common::assert_no_validation_messages(&gpu);
}

/// The clustered method (N > 0) follows the structures too: its histograms count each
/// structure's voxels apart (docs/design.md, shades), so its AO stays within the clustering's
/// tolerance of the direct definition as the structures are shown, and after the menu hides one
/// (one table update, no new clustering).
#[test]
fn the_clustered_values_follow_the_structures_shown() {
    let gpu = common::gpu();
    let vol = labelled_head();
    let tf = TransferFunction::preset("ct-skin").unwrap();
    let p = HistParams {
        radius_mm: 30.0,
        bins: 16,
        clusters: 512,
        // One sphere: the definitions this test checks.
        hemispheres: false,
    };
    let (mut cao, _) = setup(&gpu, &vol, &tf, p, "labels-clustered");
    let near = |cao: &Cao, shown: &[f32], what: &str| {
        let (want, _) = direct_with_labels(&vol, &tf, p.bins, p.radius_mm, shown);
        let got = read_ao(&cao.ao);
        let mean = got
            .iter()
            .zip(&want)
            .map(|(g, w)| (*g as f64 - w).abs())
            .sum::<f64>()
            / got.len() as f64;
        assert!(mean <= 0.03, "{what}: mean |clustered - direct| = {mean}");
        got
    };
    let shown_ao = near(&cao, &[1.0, 1.0], "structures shown");
    let shown = [0.0, 1.0];
    show_structures(&gpu, &mut cao, &vol, &tf, &shown);
    let hidden_ao = near(&cao, &shown, "green hidden");
    assert!(
        hidden_ao.iter().zip(&shown_ao).any(|(h, s)| h - s > 0.05),
        "hiding a structure opens its surroundings in the clustered AO"
    );
    common::assert_no_validation_messages(&gpu);
}
