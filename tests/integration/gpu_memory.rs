//! GPU memory exhaustion (issues 19, 25): a volume that passes the limits check but does not
//! fit beside everything else the GPU holds, simulated with the allocator budget
//! `CAO_XR_GPU_BUDGET_MB`, is shown downsampled by the smallest N that fits, with what did not
//! fit told; the picture is `--downsample N`'s under the same budget. No abort, no panic, no
//! validation message. And a GPU that stops answering is an error, not a freeze.

use std::path::Path;
use std::process::Output;

/// `cao-xr render phantom:128` (2 Mi voxels: about 56 MiB on the GPU) under `budget`.
fn render(budget: &str, extra: &[&str], out: &Path) -> Output {
    let args = [
        &["render", "phantom:128", "--size", "64x48", "--rays", "6"][..],
        &["--steps", "4", "--out", out.to_str().unwrap()],
        extra,
    ]
    .concat();
    // Without the full-resolution inset (tests/integration/inset.rs), whose box is not part of
    // `--downsample N`'s picture; the local histograms' clusters cached beside the output, so
    // that the clustering runs under the budget.
    let cache = out.with_extension("cache");
    let env = [
        ("CAO_XR_GPU_BUDGET_MB", budget),
        ("CAO_XR_INSET", "0"),
        ("CAO_XR_DATA", cache.to_str().unwrap()),
    ];
    crate::common::run_cao(&args, &env)
}

fn tmp(name: &str) -> crate::common::Scratch {
    crate::common::scratch("gpu-memory", name)
}

/// The N of "shown downsampled by N" in the notice of a volume that did not fit.
fn shown_at(stderr: &str) -> usize {
    let at = stderr
        .find("shown downsampled by ")
        .unwrap_or_else(|| panic!("no downsample told: {stderr}"));
    stderr[at + 21..]
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

#[test]
fn a_volume_beyond_the_gpu_memory_budget_is_shown_at_the_finest_downsample_that_fits() {
    let dir = tmp("budget");
    // the budget runs out at different points (the first upload's staging copy, a device
    // buffer beside others, an image late in the set-up), with LAO, a filter, the local
    // histograms (whose clustering's batches follow the budget) and SH lighting.
    // The volume is not refused: it is shown downsampled by the smallest N that fits, told on
    // stderr with what did not fit, and the picture is the one `--downsample N` renders under
    // the same budget (which fits as it is: no notice), while `--downsample N - 1` does not fit
    // (its notice downsamples further). N moves with every buffer the frame loop gains, so it
    // is not written down here.
    // Budgets of 3 MiB and up: below that the ray caster's fixed 1 MiB pre-integration table
    // (and its staging) leaves no room for any downsampled volume.
    let cases: [(&str, &[&str]); 6] = [
        ("4", &[]),
        ("12", &[]),
        ("14", &[]),
        ("12", &["--ao", "filter-gauss"]),
        ("5", &["--ao", "histogram"]),
        ("5", &["--lighting", "sh"]),
    ];
    let ok = |out: &Output, what: &str| -> String {
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{what}: {stderr}");
        assert!(!stderr.contains("vulkan validation"), "{what}: {stderr}");
        stderr
    };
    for (budget, extra) in cases {
        let what = format!("budget {budget} MiB {extra:?}");
        let auto = dir.join("auto");
        let stderr = ok(&render(budget, extra, &auto), &what);
        for s in [
            "volume phantom-128 (128 x 128 x 128) does not fit beside everything else on the GPU",
            "out of GPU memory: ",
            " MiB budget (CAO_XR_GPU_BUDGET_MB) are in use",
            "the finest that fits",
        ] {
            assert!(stderr.contains(s), "{what}: no {s:?} in {stderr}");
        }
        let n = shown_at(&stderr);
        assert!(n >= 2, "{what}: {stderr}");
        assert!(stderr.contains(&format!("phantom-128-ds{n}")), "{stderr}");
        // --downsample N fits as it is and draws the same picture
        let fits = dir.join(format!("ds{n}"));
        let n_text = n.to_string();
        let with_n = [extra, &["--downsample", &n_text]].concat();
        let told = ok(&render(budget, &with_n, &fits), &what);
        assert!(!told.contains("does not fit"), "{what}: {told}");
        assert!(
            std::fs::read(fits.join("stereo.png")).unwrap()
                == std::fs::read(auto.join("stereo.png")).unwrap(),
            "{what}: the picture differs from --downsample {n}'s"
        );
        if n > 2 {
            let n_text = (n - 1).to_string();
            let smaller = [extra, &["--downsample", &n_text]].concat();
            let told = ok(&render(budget, &smaller, &dir.join("smaller")), &what);
            assert!(
                told.contains("does not fit"),
                "{what}: --downsample {} fits",
                n - 1
            );
        }
    }
    // a volume downsampled already: the factor counts from the file (2 then 2 is 4 at once)
    let out = render("5", &["--downsample", "2"], &dir.join("twice"));
    let stderr = ok(&out, "twice");
    assert!(
        stderr.contains("volume phantom-128-ds2 (64 x 64 x 64) does not fit"),
        "{stderr}"
    );
    assert_eq!(shown_at(&stderr), 4, "{stderr}");
    // not even the coarsest downsample fits: refused, with what did not fit
    let out = render("1", &[], &dir.join("none"));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("does not fit beside everything else on the GPU"),
        "{stderr}"
    );
    // a budget that is not a number is refused by name
    let out = render("lots", &[], &dir.join("bad"));
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("CAO_XR_GPU_BUDGET_MB=lots"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_write_past_a_buffers_end_is_an_error_not_a_panic() {
    let gpu = crate::common::gpu();
    let mut b = cao_xr::gpu::Buffer::from_slice(
        &gpu,
        &[0u32; 4],
        ash::vk::BufferUsageFlags::TRANSFER_SRC,
        "sixteen",
    )
    .unwrap();
    assert!(b.write(8, &[1; 8]).is_ok());
    let e = b.write(12, &[1; 8]).unwrap_err().to_string();
    assert!(
        e.contains("8 bytes at offset 12") && e.contains("16 bytes"),
        "{e}"
    );
    assert!(b.write(usize::MAX, &[1]).is_err());
    assert_eq!(&b.mapped().unwrap()[8..16], &[1; 8]);
}

/// A wait for the GPU is bounded: a fence that never signals (a device that stopped answering)
/// ends the wait with a clear error after the bound instead of freezing, and a lost device is
/// told by name.
#[test]
fn a_gpu_that_stops_answering_is_an_error_not_a_freeze() {
    use ash::vk;
    use cao_xr::gpu::GpuError;
    let gpu = crate::common::gpu();
    // SAFETY: a fence of this device, destroyed below after the wait returned.
    let fence = unsafe {
        gpu.device
            .create_fence(&vk::FenceCreateInfo::default(), None)
            .unwrap()
    };
    let bound = std::time::Duration::from_millis(200);
    let t0 = std::time::Instant::now();
    let err = gpu.wait_fences_within(&[fence], bound).unwrap_err();
    let waited = t0.elapsed();
    // SAFETY: never submitted, so no queue uses it.
    unsafe { gpu.device.destroy_fence(fence, None) };
    assert!(matches!(err, GpuError::Stalled(_)), "{err}");
    assert!(waited >= bound && waited < 20 * bound, "waited {waited:?}");
    let msg = err.to_string();
    assert!(
        msg.contains("stopped answering") && msg.contains("CAO_XR_GPU_TIMEOUT_S"),
        "{msg}"
    );
    let lost = GpuError::from(vk::Result::ERROR_DEVICE_LOST).to_string();
    assert!(lost.contains("device was lost"), "{lost}");
    assert!(gpu.timeout() >= std::time::Duration::from_secs(60));
    crate::common::assert_no_validation_messages(&gpu);
}

/// `info`'s bytes per voxel of each method ([`cao_xr::app::gpu_volumes`]) are what the GPU
/// then holds: at most what `render` measures held after its frame, and within 3 bytes per
/// voxel of it, 5 for the filters (a frame's images and tables, the O and V_PAO staged in its
/// tool's boxes and O_c over the slices the tool reaches come on top, f32 under the filters; a
/// whole O_c would be 2 to 4 more) on a 2 Mi-voxel volume carved by a 10 mm sphere, for LAO, a
/// filter and the local histograms' direct definition (a precompute's transient volumes may
/// make the peak higher).
#[test]
fn info_tells_the_gpu_bytes_per_voxel_each_method_holds() {
    use cao_xr::ao::histogram::HistParams;
    use cao_xr::ao::AoMethod;
    let dir = tmp("info");
    let vol = cao_xr::volume::phantom::head(128);
    let predicted = |m: AoMethod| -> f64 {
        let v = cao_xr::app::gpu_volumes(&vol, &m);
        v.iter().map(|x| x.1).sum()
    };
    let info = crate::common::run_cao_ok(&["info", "phantom:128"]);
    let info = String::from_utf8_lossy(&info.stdout).to_string();
    assert!(
        info.contains(&format!(
            "GPU         lao {:.1}, filters",
            predicted(AoMethod::Lao)
        )),
        "{info}"
    );
    let direct = HistParams {
        clusters: 0,
        radius_mm: 6.0,
        ..HistParams::default()
    };
    // The frame's own memory on top, in bytes per voxel: its images and O_c over the sphere's
    // slices with the filters' reach (f32 for the filters, 16-bit words else) and its staging.
    let cases: [(AoMethod, f64, &[&str]); 3] = [
        (AoMethod::Lao, 3.0, &["--ao", "lao"]),
        (
            AoMethod::Filter(Default::default()),
            5.0,
            &["--ao", "filter-gauss"],
        ),
        (
            AoMethod::Histogram(direct),
            3.0,
            &[
                "--ao",
                "histogram",
                "--clusters",
                "0",
                "--hist-radius-mm",
                "6",
            ],
        ),
    ];
    for (method, on_top, extra) in cases {
        let mut args = vec![
            "render",
            "phantom:128",
            "--size",
            "32x32",
            "--tool",
            "sphere:10",
        ];
        args.extend(extra);
        args.extend(["--out", dir.to_str().unwrap()]);
        let out = crate::common::run_cao_ok(&args);
        let stdout = String::from_utf8_lossy(&out.stdout);
        let measured = crate::common::held_bytes_per_voxel(&stdout);
        let p = predicted(method);
        assert!(
            p <= measured && measured <= p + on_top,
            "{extra:?}: {p:.1} bytes per voxel told, {measured} measured"
        );
    }
}

#[test]
fn the_session_peak_is_kept_where_a_fit_restarts_the_peak() {
    let gpu = crate::common::gpu();
    let usage = ash::vk::BufferUsageFlags::STORAGE_BUFFER;
    let held = gpu.memory_in_use();
    // 4 MiB held, then given back: a try that did not fit.
    let tried =
        cao_xr::gpu::Buffer::device_local(&gpu, &vec![0f32; 1 << 20], usage, "tried").unwrap();
    let with = gpu.session_memory_peak();
    assert!(with >= held + (4 << 20), "{with} bytes at the peak");
    drop(tried);
    // A fit measures each try from here (`reset_memory_peak`); what the run needed stays.
    gpu.reset_memory_peak();
    assert!(gpu.memory_peak() < with, "the measuring peak restarted");
    assert_eq!(gpu.session_memory_peak(), with, "the run's peak is kept");
}

/// The room a set-up leaves for its frames is checked against the budget and counted in no
/// peak: the peaks `render` and `bench scale` tell are what was allocated.
#[test]
fn a_room_check_is_refused_beyond_the_budget_and_counted_in_no_peak() {
    let gpu = crate::common::gpu();
    let held = gpu.memory_in_use();
    gpu.set_memory_budget(Some(held + (64 << 20)));
    gpu.reset_memory_peak();
    let (peak, session) = (gpu.memory_peak(), gpu.session_memory_peak());
    gpu.check_room("frames", 60 << 20).unwrap();
    assert_eq!(
        (
            gpu.memory_peak(),
            gpu.session_memory_peak(),
            gpu.memory_in_use()
        ),
        (peak, session, held),
        "a room check held or counted memory"
    );
    let e = gpu.check_room("frames", 65 << 20).unwrap_err();
    assert!(e.to_string().contains("frames needs 65.0 MiB"), "{e}");
}

/// Two threads submitting to the one queue at once (one-shot work, and a frame's own
/// submission): its use is synchronised (the validation layers' thread-safety checks report a
/// queue used by two threads at a time).
#[test]
fn the_queue_is_used_by_one_thread_at_a_time() {
    use ash::vk;
    let gpu = crate::common::gpu();
    std::thread::scope(|s| {
        s.spawn(|| {
            for _ in 0..300 {
                gpu.submit_and_wait(|cmd| gpu.barrier(cmd)).unwrap();
            }
        });
        s.spawn(|| {
            let d = &gpu.device;
            // SAFETY: the fence is this thread's, waited for before it is reset or destroyed;
            // an empty submission references nothing else.
            unsafe {
                let fence = d
                    .create_fence(&vk::FenceCreateInfo::default(), None)
                    .unwrap();
                for _ in 0..300 {
                    gpu.submit(&[], fence).unwrap();
                    d.wait_for_fences(&[fence], true, u64::MAX).unwrap();
                    d.reset_fences(&[fence]).unwrap();
                }
                d.destroy_fence(fence, None);
            }
        });
    });
    crate::common::assert_no_validation_messages(&gpu);
}
