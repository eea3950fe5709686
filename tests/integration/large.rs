//! Large volumes and long rays. Volumes past lavapipe's 128 MiB storage-buffer range
//! (`maxStorageBufferRange`, the limit that refused a routine 512 x 512 x 133 chest CT): every AO
//! method, run on a volume whose f32 buffers are larger than one descriptor can hold, gives bit
//! for bit the values of the same content in a small volume, where the content lies past the
//! first 128 MiB of every buffer. A 1024 x 1024 x 300 volume renders at full resolution under the
//! filters in a few bytes per voxel. Rays of more than 8192 samples reach what lies behind, with
//! and without empty-space skipping, bit for bit.

use std::path::Path;

fn tmp(name: &str) -> crate::common::Scratch {
    crate::common::scratch("large", name)
}

/// A little-endian int16 raw file of `dims`, air (-1000 HU) except `content` (of `cdims`)
/// placed with its lowest corner at `at`.
fn write_raw(path: &Path, dims: [usize; 3], content: &[i16], cdims: [usize; 3], at: [usize; 3]) {
    let mut v = vec![-1000i16; dims[0] * dims[1] * dims[2]];
    for z in 0..cdims[2] {
        for y in 0..cdims[1] {
            let src = cdims[0] * (y + cdims[1] * z);
            let dst = at[0] + dims[0] * (at[1] + y + dims[1] * (at[2] + z));
            v[dst..dst + cdims[0]].copy_from_slice(&content[src..src + cdims[0]]);
        }
    }
    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(path, bytes).unwrap();
}

/// Bone shells and soft tissue: a ball of bone (radius 10 voxels, 12 below the top) with a soft
/// core and a bone rod through it, so every method sees edges, gradients and several bins.
fn content(d: [usize; 3]) -> Vec<i16> {
    let mut v = Vec::with_capacity(d[0] * d[1] * d[2]);
    let c = [d[0] as f64 / 2.0, d[1] as f64 / 2.0, d[2] as f64 - 12.0];
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let p = [
                    x as f64 + 0.5 - c[0],
                    y as f64 + 0.5 - c[1],
                    z as f64 + 0.5 - c[2],
                ];
                let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                let rod = (p[0] * p[0] + p[2] * p[2]).sqrt() < 2.5 && p[1].abs() < 10.0;
                v.push(if rod || (7.0..10.0).contains(&r) {
                    1400
                } else if r < 7.0 {
                    40 + (x as i16 % 5) * 30
                } else {
                    -1000
                });
            }
        }
    }
    v
}

/// The AO volume (and the bleeding colour, for the histogram) `cao-xr ao` writes for the raw
/// volume at `raw` of `dims`.
fn ao(dir: &Path, tag: &str, raw: &Path, dims: [usize; 3], method: &[&str]) -> Vec<Vec<f32>> {
    let out = dir.join(format!("{tag}.nrrd"));
    let e = dir.join(format!("{tag}-e.nrrd"));
    let dims_arg = format!("{},{},{}", dims[0], dims[1], dims[2]);
    let mut args = vec![
        "ao",
        raw.to_str().unwrap(),
        "--raw-dims",
        &dims_arg,
        "--raw-type",
        "i16",
        "--tf",
        "ct-bone",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(method);
    let histogram = method.contains(&"histogram");
    if histogram {
        args.extend_from_slice(&["--bleeding-out", e.to_str().unwrap()]);
    }
    crate::common::run_cao_ok(&args);
    let mut vols = vec![read_f32_nrrd(&out)];
    if histogram {
        vols.push(read_f32_nrrd(&e));
    }
    for p in [&out, &e] {
        let _ = std::fs::remove_file(p);
    }
    vols
}

/// The float32 samples of a raw NRRD (any number of components).
fn read_f32_nrrd(path: &Path) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap();
    let split = bytes.windows(2).position(|w| w == b"\n\n").unwrap();
    let header = String::from_utf8_lossy(&bytes[..split]);
    assert!(
        header.contains("type: float") && header.contains("encoding: raw"),
        "{header}"
    );
    bytes[split + 2..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

#[test]
fn every_method_past_the_storage_buffer_range_equals_the_small_volume_bit_for_bit() {
    let dir = tmp("range");
    // At least 10 voxels of air around the material, except at the top, where the two volumes'
    // borders coincide: the filters clamp their box centres into the grid, so the content's
    // values equal the big volume's only where no clamp differs.
    let cdims = [40, 40, 32];
    let c = content(cdims);
    let small = dir.join("small.raw");
    write_raw(&small, cdims, &c, cdims, [0, 0, 0]);
    // 256 x 256 x 544 voxels: 142.6 MB per f32 volume, past 134217728 bytes (2^25 floats). The
    // content fills the last 32 slices, voxels 2^25 and on, so the volumes' top borders coincide
    // and every value it reads lies past what one 128 MiB descriptor could reach.
    let bdims = [256, 256, 544];
    let at = [100, 110, 512];
    assert!(at[2] * bdims[0] * bdims[1] >= 1 << 25);
    let big = dir.join("big.raw");
    write_raw(&big, bdims, &c, cdims, at);
    let methods: [(&str, &[&str]); 3] = [
        ("lao", &["--ao", "lao", "--rays", "14", "--steps", "6"]),
        (
            "filter-gauss",
            &["--ao", "filter-gauss", "--filter-radius-mm", "4"],
        ),
        (
            "histogram",
            &[
                "--ao",
                "histogram",
                "--clusters",
                "0",
                "--hist-radius-mm",
                "3",
                "--hist-bins",
                "16",
            ],
        ),
    ];
    for (name, args) in methods {
        let want = ao(&dir, &format!("{name}-small"), &small, cdims, args);
        let got = ao(&dir, &format!("{name}-big"), &big, bdims, args);
        assert!(
            want[0].iter().any(|&a| a < 0.9),
            "{name}: the content casts no occlusion"
        );
        for (w, g) in want.iter().zip(&got) {
            let comps = w.len() / (cdims[0] * cdims[1] * cdims[2]);
            assert_eq!(g.len(), comps * bdims[0] * bdims[1] * bdims[2], "{name}");
            for z in 0..cdims[2] {
                for y in 0..cdims[1] {
                    let s = comps * cdims[0] * (y + cdims[1] * z);
                    let b = comps * (at[0] + bdims[0] * (at[1] + y + bdims[1] * (at[2] + z)));
                    let row = comps * cdims[0];
                    if let Some(i) =
                        crate::common::first_bit_difference(&w[s..s + row], &g[b..b + row])
                    {
                        panic!(
                            "{name}: voxel ({}, {y}, {z}) of the content differs past the \
                             storage-buffer range: {} here, {} in the small volume",
                            i / comps,
                            g[b + i],
                            w[s + i]
                        );
                    }
                }
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_routine_chest_ct_renders_at_full_resolution_carved_with_every_method() {
    // 512 x 512 x 133 at 0.7 x 0.7 x 2.5 mm: the chest CT that was refused, "139460608 bytes per
    // f32 volume exceed the storage-buffer limit".
    let dir = tmp("chest");
    let dims = [512, 512, 133];
    let cdims = [200, 200, 100];
    let mut c = content([50, 50, 25]);
    // The content scaled up 4x in every axis, so the chest's body spans most of the slices.
    c = (0..cdims[0] * cdims[1] * cdims[2])
        .map(|i| {
            let (x, y, z) = (
                i % cdims[0],
                (i / cdims[0]) % cdims[1],
                i / (cdims[0] * cdims[1]),
            );
            c[x / 4 + 50 * (y / 4 + 50 * (z / 4))]
        })
        .collect();
    let raw = dir.join("chest.raw");
    write_raw(&raw, dims, &c, cdims, [156, 156, 20]);
    let mut pictures = Vec::new();
    for method in [
        &["--ao", "lao", "--rays", "6", "--steps", "4"][..],
        &["--ao", "filter-gauss"][..],
        &[
            "--ao",
            "histogram",
            "--clusters",
            "0",
            "--hist-radius-mm",
            "2",
            "--hist-bins",
            "16",
        ][..],
    ] {
        let out = dir.join(method[1]);
        let run = render_ct(&raw, dims, ("sphere:60", &out), method);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(run.status.success(), "{}: {stderr}", method[1]);
        assert!(!stderr.contains("downsample"), "{}: {stderr}", method[1]);
        let png = std::fs::read_dir(&out)
            .unwrap()
            .filter_map(|e| e.ok().map(|e| e.path()))
            .find(|p| p.extension().is_some_and(|e| e == "png"))
            .unwrap_or_else(|| panic!("{}: no PNG in {}", method[1], out.display()));
        pictures.push(std::fs::read(png).unwrap());
    }
    // Each method lit the carved chest its own way: three different pictures.
    assert!(pictures[0] != pictures[1] && pictures[1] != pictures[2] && pictures[0] != pictures[2]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `cao-xr render` of the i16 raw CT `raw` (`dims` voxels of 0.7 x 0.7 x 2.5 mm) under ct-bone at
/// 48 x 48, carved by `tool`, into `out`, with `extra` arguments.
fn render_ct(
    raw: &Path,
    dims: [usize; 3],
    (tool, out): (&str, &Path),
    extra: &[&str],
) -> std::process::Output {
    let dims = dims.map(|d| d.to_string()).join(",");
    let mut args = vec![
        "render",
        raw.to_str().unwrap(),
        "--raw-dims",
        &dims,
        "--raw-type",
        "i16",
        "--raw-spacing",
        "0.7,0.7,2.5",
        "--tf",
        "ct-bone",
        "--size",
        "48x48",
        "--tool",
        tool,
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    crate::common::run_cao(&args, &[])
}

#[test]
fn a_1024_by_1024_by_300_volume_renders_at_full_resolution_under_the_filters() {
    // 315 M voxels at 0.7 x 0.7 x 2.5 mm, carved: the filters hold their box statistics (32
    // bytes per voxel whole) and O_c only over a window of slices, so the GPU holds a few
    // bytes per voxel and nothing is downsampled.
    let dir = tmp("giga");
    let dims = [1024, 1024, 300];
    let raw = dir.join("giga.raw");
    write_raw(
        &raw,
        dims,
        &content([50, 50, 25]),
        [50, 50, 25],
        [487, 487, 140],
    );
    let out = dir.join("out");
    let run = render_ct(&raw, dims, ("sphere:20", &out), &["--ao", "filter-gauss"]);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr),
    );
    assert!(run.status.success(), "{stderr}");
    assert!(!stderr.contains("downsample"), "{stderr}");
    let held = crate::common::held_bytes_per_voxel(&stdout);
    assert!(held < 12.0, "{held} bytes per voxel held");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn rays_longer_than_8192_samples_reach_what_lies_behind_with_and_without_skipping() {
    // 16 x 1024 x 16 voxels of 4 x 0.25 x 4 mm (64 x 256 x 64 mm), long in j (posterior), the
    // viewing direction: air, and a bone plate at the far end. At the reference step (1/16 of
    // half the smallest spacing) a ray needs 32,000 samples to reach it; the old cap of 8192
    // stopped it a quarter of the way.
    let dir = tmp("long");
    let dims = [16, 1024, 16];
    let plate: Vec<i16> = vec![1500; 16 * 8 * 16];
    let raw = dir.join("long.raw");
    write_raw(&raw, dims, &plate, [16, 8, 16], [0, 1000, 0]);
    let render = |name: &str, extra: &[&str]| -> Vec<u8> {
        let out = dir.join(name);
        let mut args = vec![
            "render",
            raw.to_str().unwrap(),
            "--raw-dims",
            "16,1024,16",
            "--raw-spacing",
            "4,0.25,4",
            "--raw-type",
            "i16",
            "--tf",
            "ct-bone",
            "--rays",
            "6",
            "--steps",
            "2",
            "--size",
            "24x24",
            "--reference",
            "--background",
            "transparent",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        crate::common::run_cao_ok(&args);
        cao_xr::render::compare::read_png(&out.join("left.png"))
            .unwrap()
            .rgba
    };
    let plain = render("plain", &["--no-empty-skip"]);
    let opaque = plain.chunks_exact(4).filter(|p| p[3] > 128).count();
    assert!(
        opaque >= 9,
        "the plate behind 250 mm of air is not seen ({opaque} pixels)"
    );
    let skipping = render("skipping", &[]);
    assert!(
        plain == skipping,
        "empty-space skipping changed the reference picture"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
