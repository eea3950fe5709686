//! Clip maps on the GPU (lavapipe, validation on) against the CPU reference: the rasterised peels
//! give the CPU's intervals except at a few silhouette texels, the compute dilation of a clip map
//! equals the CPU's, and the dilated shape holds the shape.

use crate::common;

use cao_xr::clip::TORUS_MINOR;
use cao_xr::clip::{dilate, ClipMap, ClipMapGpu, TriMesh, EMPTY_IN, EMPTY_OUT, SAMPLE_OFFSET};
use glam::Vec3;
use std::time::Instant;

/// The shapes, with a dilation radius each; the torus also on its side (two peels needed).
fn shapes() -> Vec<(&'static str, TriMesh, f32)> {
    let mut side = TriMesh::torus();
    for v in &mut side.vertices {
        *v = Vec3::new(v.x, v.z, v.y);
    }
    vec![
        ("sphere", TriMesh::sphere(), 0.3),
        ("cube", TriMesh::cube(), 0.2),
        ("cylinder", TriMesh::cylinder(), 0.25),
        ("torus", TriMesh::torus(), 0.1),
        ("torus on its side", side, 0.05),
    ]
}

/// How many intervals a clip texel holds.
fn intervals(c: &[f32; 4]) -> usize {
    (c[0] <= c[1]) as usize + (c[2] <= c[3]) as usize
}

/// Texels where the GPU map's interval count differs from the CPU's, texels where both hold
/// intervals but some depth differs by more than `tol`, texels covered by either, and the largest
/// depth difference among the texels with the same interval count.
fn compare(cpu: &ClipMap, gpu: &ClipMap, tol: f32) -> (usize, usize, usize, f32) {
    let (mut count, mut depth, mut covered, mut max) = (0, 0, 0, 0.0f32);
    for (a, b) in cpu.clip.iter().zip(&gpu.clip) {
        let (na, nb) = (intervals(a), intervals(b));
        covered += (na + nb > 0) as usize;
        if na != nb {
            count += 1;
            continue;
        }
        let d = (0..2 * na).map(|k| (a[k] - b[k]).abs()).fold(0.0, f32::max);
        max = max.max(d);
        depth += (d > tol) as usize;
    }
    (count, depth, covered, max)
}

#[test]
fn gpu_peels_match_the_cpu_scan_conversion() {
    let gpu = common::gpu();
    let builder = ClipMapGpu::new(&gpu).unwrap();
    for res in [64, 128] {
        for (name, mesh, radius) in shapes() {
            let cpu = ClipMap::build(&mesh, res, radius);
            let g = builder.build(&mesh, res, radius).unwrap();
            assert_eq!(
                (g.res, g.extent, g.radius),
                (cpu.res, cpu.extent, cpu.radius)
            );
            let (count, depth, covered, max) = compare(&cpu, &g, 1e-4);
            println!(
                "{name} @ {res}: {covered} texels covered, {count} with another interval count, \
                 {depth} with a depth off by > 1e-4 (largest difference {max:.2e})"
            );
            // Silhouette texels only: the rasteriser's snapped vertices against the CPU's exact
            // ones. A torus on its side has silhouettes inside its hole too.
            assert!(
                count + depth <= covered / 50,
                "{name} @ {res}: {count} + {depth} of {covered} texels differ"
            );
            // Empty intervals are exactly (EMPTY_IN, EMPTY_OUT) on both.
            let empty = |a: f32, b: f32| a <= b || (a, b) == (EMPTY_IN, EMPTY_OUT);
            assert!(g
                .clip
                .iter()
                .all(|c| empty(c[0], c[1]) && empty(c[2], c[3])));
            assert!(g.dilated.iter().all(|d| empty(d[0], d[1])));
            let (z0, z1) = (cpu.z_range, g.z_range);
            assert!(
                (z0.0 - z1.0).abs() < 0.02 && (z0.1 - z1.1).abs() < 0.02,
                "{name}: z ranges {z0:?} {z1:?}"
            );
        }
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn grazing_rays_clip_nothing_across_the_hole() {
    // A torus on its side, moved so that its lower outline (a ring of vertices, where the front
    // and back of the tube fold over) runs exactly through a row of sample points. Each ray there
    // grazes the near and the far part of the ring; crossings must pair up within each part (or
    // vanish), never into one interval through the hole.
    let gpu = common::gpu();
    let builder = ClipMapGpu::new(&gpu).unwrap();
    for res in [64, 128] {
        let mut mesh = TriMesh::torus();
        for v in &mut mesh.vertices {
            *v = Vec3::new(v.x, v.z, v.y);
        }
        let radius = 0.05;
        let bottom = mesh.vertices.iter().map(|v| v.y).fold(f32::MAX, f32::min);
        let extent = ClipMap::extent_for(mesh.half_extent(), res, radius);
        let texel = 2.0 * extent / res as f32;
        let row = ((bottom + extent) / texel) as usize;
        let sample_y = -extent + (row as f32 + 0.5) * texel + SAMPLE_OFFSET.y * texel;
        let shift = sample_y - bottom;
        for v in &mut mesh.vertices {
            v.y = if v.y == bottom { sample_y } else { v.y + shift };
        }
        assert_eq!(ClipMap::extent_for(mesh.half_extent(), res, radius), extent);
        for (who, m) in [
            ("GPU", builder.build(&mesh, res, radius).unwrap()),
            ("CPU", ClipMap::build(&mesh, res, radius)),
        ] {
            let hole = 1.0 - TORUS_MINOR - 2.0 * texel;
            for (t, c) in m.clip.iter().enumerate() {
                let x = -extent + ((t % res) as f32 + 0.5) * texel;
                if x.abs() < hole {
                    let across = (c[0] <= 0.0 && c[1] >= 0.0) || (c[2] <= 0.0 && c[3] >= 0.0);
                    assert!(!across, "{who} @ {res}: texel {t} clips the hole: {c:?}");
                }
            }
        }
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn gpu_dilation_equals_the_cpu_dilation() {
    let gpu = common::gpu();
    let builder = ClipMapGpu::new(&gpu).unwrap();
    for (name, mesh, radius) in shapes() {
        let cpu = ClipMap::build(&mesh, 96, radius);
        let g = builder
            .dilate(&cpu.clip, cpu.res, cpu.texel(), radius)
            .unwrap();
        let max = cpu
            .dilated
            .iter()
            .zip(&g)
            .map(|(a, b)| (a[0] - b[0]).abs().max((a[1] - b[1]).abs()))
            .fold(0.0f32, f32::max);
        println!("{name}: largest dilation difference {max:e}");
        assert!(max <= 1e-5, "{name}: dilations differ by {max}");
        // The contraction (z, w) from the same min / max of the same sums: bit for bit.
        let contracted = |m: &[[f32; 4]]| m.iter().map(|d| [d[2], d[3]]).collect::<Vec<_>>();
        assert_eq!(
            contracted(&cpu.dilated),
            contracted(&g),
            "{name}: contractions"
        );
        assert!(
            cpu.dilated.iter().any(|d| d[2] <= d[3]),
            "{name}: something is contracted"
        );
        // And the GPU build's own dilation is the dilation of its own clip map.
        let built = builder.build(&mesh, 96, radius).unwrap();
        let again = dilate(&built.clip, built.res, built.texel(), radius);
        assert!(built
            .dilated
            .iter()
            .zip(&again)
            .all(|(a, b)| (a[0] - b[0]).abs() <= 1e-5 && (a[1] - b[1]).abs() <= 1e-5));
    }
    assert!(builder.dilate(&[[0.0; 4]; 3], 2, 0.1, 0.1).is_err());
    // No triangles: nothing clipped, nothing dilated, as on the CPU.
    let (none, cpu) = (
        builder.build(&TriMesh::default(), 32, 0.2).unwrap(),
        ClipMap::build(&TriMesh::default(), 32, 0.2),
    );
    assert_eq!((none.clip, none.dilated), (cpu.clip, cpu.dilated));
    assert_eq!(none.z_range, cpu.z_range);
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn the_dilated_shape_holds_the_shape() {
    let gpu = common::gpu();
    let builder = ClipMapGpu::new(&gpu).unwrap();
    for (name, mesh, radius) in shapes() {
        let m = builder.build(&mesh, 128, radius).unwrap();
        let reach = (radius / m.texel()).floor() as usize;
        for (t, (c, d)) in m.clip.iter().zip(&m.dilated).enumerate() {
            if c[0] <= c[1] {
                let last = if c[2] <= c[3] { c[3] } else { c[1] };
                assert!(
                    d[0] <= c[0] - radius && d[1] >= last + radius,
                    "{name}: texel {t}: clip {c:?}, dilated {d:?}"
                );
                // Grown sideways by at least the radius too.
                let (i, j) = (t % m.res, t / m.res);
                for (di, dj) in [(reach, 0), (0, reach)] {
                    for (x, y) in [(i + di, j + dj), (i.wrapping_sub(di), j.wrapping_sub(dj))] {
                        if x < m.res && y < m.res {
                            let e = m.dilated[y * m.res + x];
                            assert!(e[0] <= c[0] && e[1] >= c[1], "{name}: texel {t}");
                        }
                    }
                }
            }
        }
        let (z0, z1) = m.z_range;
        let (lo, hi) = m
            .clip
            .iter()
            .filter(|c| c[0] <= c[1])
            .fold((f32::MAX, f32::MIN), |(l, h), c| {
                (l.min(c[0]), h.max(c[1]).max(c[3]))
            });
        assert!(z0 <= lo - radius && z1 >= hi + radius, "{name}: z range");
    }
    common::assert_no_validation_messages(&gpu);
}

#[test]
fn build_times_gpu_and_cpu() {
    let gpu = common::gpu();
    let builder = ClipMapGpu::new(&gpu).unwrap();
    let time = |f: &mut dyn FnMut()| {
        f(); // warm-up: first use of the pipelines, allocator blocks
        let t = Instant::now();
        f();
        t.elapsed().as_secs_f64() * 1e3
    };
    for res in [128, 256] {
        for (name, mesh, radius) in [
            ("sphere", TriMesh::sphere(), 0.3),
            ("torus", TriMesh::torus(), 0.1),
        ] {
            let g = time(&mut || {
                builder.build(&mesh, res, radius).unwrap();
            });
            let c = time(&mut || {
                ClipMap::build(&mesh, res, radius);
            });
            println!(
                "clip map {name} @ {res} (radius {radius}): GPU {g:.1} ms ({}), CPU {c:.1} ms",
                gpu.device_name
            );
        }
    }
    common::assert_no_validation_messages(&gpu);
}
