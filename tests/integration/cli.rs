//! The command line end to end: `ao` checked against an independent LAO implementation written
//! from docs/design.md, `render` writes pictures, `bench lao` prints its table, bad input is refused.

use std::path::{Path, PathBuf};
use std::process::Output;

fn cao(args: &[&str]) -> Output {
    crate::common::run_cao(args, &[])
}

fn tmp(name: &str) -> crate::common::Scratch {
    crate::common::scratch("cli", name)
}

/// Writes the scripted pose stream KIND of `frames` frames to DIR/NAME (`cao-xr script`).
fn script(dir: &Path, name: &str, kind: &str, frames: usize) -> PathBuf {
    let path = dir.join(name);
    let out = cao(&[
        "script",
        kind,
        "--frames",
        &frames.to_string(),
        "--out",
        path.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    path
}

/// Replays `stream` on a 24^3 phantom (few rays, 32x32 per eye, `extra` arguments added) into
/// DIR/NAME, and reads back its first `frames` PNGs and what it printed on stdout.
fn replay_pngs(
    stream: &Path,
    dir: &Path,
    name: &str,
    extra: &[&str],
    frames: usize,
) -> (Vec<Vec<u8>>, String) {
    let out_dir = dir.join(name);
    let mut args = vec![
        "replay",
        stream.to_str().unwrap(),
        "phantom:24",
        "--rays",
        "6",
        "--steps",
        "3",
        "--size",
        "32x32",
        "--out",
        out_dir.to_str().unwrap(),
    ];
    args.extend(extra);
    let out = cao(&args);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let pngs = (0..frames)
        .map(|i| std::fs::read(out_dir.join(format!("frame-{i:05}.png"))).unwrap())
        .collect();
    (pngs, String::from_utf8_lossy(&out.stdout).to_string())
}

/// A float32 / int16 little-endian raw NRRD read with nothing but the header text.
fn read_nrrd_f32(path: &Path) -> (Vec<usize>, Vec<f64>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    let split = bytes.windows(2).position(|w| w == b"\n\n").unwrap();
    let header = std::str::from_utf8(&bytes[..split]).unwrap();
    let field = |k: &str| {
        header
            .lines()
            .find_map(|l| l.strip_prefix(&format!("{k}: ")))
            .unwrap_or_else(|| panic!("no {k} in {header}"))
            .to_string()
    };
    assert_eq!(field("type"), "float");
    assert_eq!(field("encoding"), "raw");
    let dims: Vec<usize> = field("sizes")
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    // Spacing = lengths of the space direction vectors.
    let dirs = field("space directions");
    let spacing: Vec<f64> = dirs
        .split(')')
        .filter(|v| v.contains('('))
        .map(|v| {
            let c: Vec<f64> = v
                .trim()
                .trim_start_matches('(')
                .split(',')
                .map(|x| x.trim().parse().unwrap())
                .collect();
            (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt()
        })
        .collect();
    let data = bytes[split + 2..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    (dims, spacing, data)
}

/// LAO written straight from docs/design.md, in mm, sharing no code with cao-xr.
fn independent_lao(
    o: &[f32],
    n: &[usize],
    s: &[f64],
    dirs: &[[f64; 3]],
    m: usize,
    d: f64,
) -> Vec<f64> {
    let at = |q: [i64; 3]| -> f64 {
        if (0..3).any(|a| q[a] < 0 || q[a] >= n[a] as i64) {
            0.0
        } else {
            o[q[0] as usize + n[0] * (q[1] as usize + n[1] * q[2] as usize)] as f64
        }
    };
    let sample = |p: [f64; 3]| -> f64 {
        // Voxel centres at (q + 0.5) * spacing.
        let c: Vec<f64> = (0..3).map(|a| p[a] / s[a] - 0.5).collect();
        let q: Vec<i64> = c.iter().map(|x| x.floor() as i64).collect();
        let f: Vec<f64> = (0..3).map(|a| c[a] - q[a] as f64).collect();
        let mut acc = 0.0;
        for corner in 0..8 {
            let b = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
            let w: f64 = (0..3)
                .map(|a| if b[a] == 1 { f[a] } else { 1.0 - f[a] })
                .product();
            acc += w * at([q[0] + b[0] as i64, q[1] + b[1] as i64, q[2] + b[2] as i64]);
        }
        acc
    };
    let mut out = Vec::new();
    for k in 0..n[2] {
        for j in 0..n[1] {
            for i in 0..n[0] {
                let x = [
                    (i as f64 + 0.5) * s[0],
                    (j as f64 + 0.5) * s[1],
                    (k as f64 + 0.5) * s[2],
                ];
                let mut a = 0.0;
                for dk in dirs {
                    let alphas: Vec<f64> = (1..m)
                        .map(|step| {
                            let p = [0, 1, 2].map(|ax| x[ax] + step as f64 * d * dk[ax]);
                            1.0 - (1.0 - sample(p)).powf(d)
                        })
                        .collect();
                    let mut ak = 0.0;
                    for mm in 1..=m {
                        ak += alphas[..mm - 1].iter().map(|al| 1.0 - al).product::<f64>();
                    }
                    a += ak / m as f64;
                }
                out.push(a / dirs.len() as f64);
            }
        }
    }
    out
}

#[test]
fn ao_command_agrees_with_an_independent_implementation() {
    let dir = tmp("ao");
    let vol = dir.join("head.nrrd");
    assert!(
        cao(&["phantom", "--size", "24", "--out", vol.to_str().unwrap()])
            .status
            .success()
    );
    let ao = dir.join("ao.nrrd");
    let op = dir.join("opacity.nrrd");
    let out = cao(&[
        "ao",
        vol.to_str().unwrap(),
        "--tf",
        "ct-skin",
        "--rays",
        "14",
        "--steps",
        "6",
        "--step-mm",
        "4.5",
        "--out",
        ao.to_str().unwrap(),
        "--opacity-out",
        op.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("ao.json")).unwrap()).unwrap();
    for key in [
        "directions",
        "steps",
        "step_mm",
        "spacing_mm",
        "dims",
        "transfer_function",
    ] {
        assert!(side.get(key).is_some(), "sidecar lacks {key}");
    }
    let dirs: Vec<[f64; 3]> = serde_json::from_value(side["directions"].clone()).unwrap();
    assert_eq!(dirs.len(), 14);
    let (dims, spacing, a) = read_nrrd_f32(&ao);
    let (odims, _, o) = read_nrrd_f32(&op);
    assert_eq!(dims, vec![24, 24, 24]);
    assert_eq!(odims, dims);
    assert!(o.iter().any(|&x| x > 0.0));
    let want = independent_lao(&o, &dims, &spacing, &dirs, 6, 4.5);
    let worst = a
        .iter()
        .zip(&want)
        .map(|(x, y)| (*x as f64 - y).abs())
        .fold(0.0, f64::max);
    assert!(
        worst < 1e-4,
        "cao-xr ao differs from the independent LAO by {worst}"
    );
    assert!(a.iter().any(|&x| x < 0.7), "expected some occlusion");
}

/// Filtered AO written straight from docs/design.md ("Filtered AO, exactly"), sharing no code
/// with cao-xr: brute force over every voxel's tangent box.
fn independent_filter(d: &[f32], dims: &[usize], s: &[f64], r: f64, estimator: &str) -> Vec<f64> {
    let at = |p: [i64; 3]| -> f64 {
        if (0..3).all(|a| p[a] >= 0 && (p[a] as usize) < dims[a]) {
            d[p[0] as usize + dims[0] * (p[1] as usize + dims[1] * p[2] as usize)] as f64
        } else {
            0.0
        }
    };
    let h: Vec<i64> = s.iter().map(|s| ((r / s).round() as i64).max(1)).collect();
    let n = ((2 * h[0] + 1) * (2 * h[1] + 1) * (2 * h[2] + 1)) as f64;
    let mut out = Vec::new();
    for z in 0..dims[2] as i64 {
        for y in 0..dims[1] as i64 {
            for x in 0..dims[0] as i64 {
                let v = [x, y, z];
                let g: Vec<f64> = (0..3)
                    .map(|a| {
                        let (mut p, mut q) = (v, v);
                        p[a] += 1;
                        q[a] -= 1;
                        (at(p) - at(q)) / (2.0 * s[a])
                    })
                    .collect();
                let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
                let mut c = v;
                if len > 0.0 {
                    for a in 0..3 {
                        let off = (-r * g[a] / len / s[a]).round() as i64;
                        c[a] = (v[a] + off).clamp(0, dims[a] as i64 - 1);
                    }
                }
                let dv = at(v);
                let mut m = Vec::new();
                for k in -h[2]..=h[2] {
                    for j in -h[1]..=h[1] {
                        for i in -h[0]..=h[0] {
                            m.push(at([c[0] + i, c[1] + j, c[2] + k]));
                        }
                    }
                }
                let (lo, hi) = m
                    .iter()
                    .fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(*x), b.max(*x)));
                let mu = if lo == hi {
                    lo
                } else {
                    m.iter().sum::<f64>() / n
                };
                let var = if lo == hi {
                    0.0
                } else {
                    (m.iter().map(|x| x * x).sum::<f64>() / n - mu * mu).max(0.0)
                };
                let erf = |x: f64| {
                    let a = 0.147;
                    x.signum()
                        * (1.0
                            - (-x * x * (4.0 / std::f64::consts::PI + a * x * x)
                                / (1.0 + a * x * x))
                                .exp())
                        .sqrt()
                };
                out.push(match estimator {
                    "exact" => m.iter().filter(|x| **x <= dv).count() as f64 / n,
                    "cdf" if dv >= hi => 1.0,
                    "cdf" if dv <= lo => 0.0,
                    "cdf" if mu >= hi => 0.0,
                    "cdf" => {
                        let beta = (mu - lo) / (hi - mu);
                        if beta <= 0.0 {
                            1.0
                        } else {
                            ((dv - lo) / (hi - lo)).powf(beta)
                        }
                    }
                    _ if var <= 1e-12 => (dv >= mu) as u8 as f64,
                    "gauss" => 0.5 * (1.0 + erf((dv - mu) / (2.0 * var).sqrt())),
                    _ if dv <= mu => 0.0,
                    _ => (dv - mu).powi(2) / (var + (dv - mu).powi(2)),
                });
            }
        }
    }
    out
}

#[test]
fn ao_command_filters_agree_with_an_independent_implementation() {
    let dir = tmp("ao-filter");
    let vol = dir.join("head.nrrd");
    assert!(
        cao(&["phantom", "--size", "20", "--out", vol.to_str().unwrap()])
            .status
            .success()
    );
    for estimator in ["cdf", "gauss", "penner", "exact"] {
        let (ao, op) = (dir.join(format!("{estimator}.nrrd")), dir.join("d.nrrd"));
        let out = cao(&[
            "ao",
            vol.to_str().unwrap(),
            "--tf",
            "ct-skin",
            "--ao",
            &format!("filter-{estimator}"),
            "--filter-radius-mm",
            "20",
            "--out",
            ao.to_str().unwrap(),
            "--opacity-out",
            op.to_str().unwrap(),
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let side: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(ao.with_extension("json")).unwrap())
                .unwrap();
        assert_eq!(side["method"], "filter");
        assert_eq!(side["estimator"], estimator);
        assert_eq!(side["input"], "opacity");
        assert_eq!(side["radius_mm"], 20.0);
        for key in ["half_widths", "spacing_mm", "dims"] {
            assert!(side.get(key).is_some(), "sidecar lacks {key}");
        }
        let (dims, spacing, a) = read_nrrd_f32(&ao);
        let (_, _, d) = read_nrrd_f32(&op);
        assert!(d.iter().any(|&x| x > 0.0));
        let want = independent_filter(&d, &dims, &spacing, 20.0, estimator);
        crate::common::assert_agrees(&a, &want, &format!("filter-{estimator}"));
        assert!(
            a.iter().any(|&x| x < 0.5),
            "filter-{estimator}: no occlusion"
        );
    }
    let bad = cao(&[
        "ao",
        vol.to_str().unwrap(),
        "--ao",
        "filter-blur",
        "--out",
        "x.nrrd",
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("filter-gauss"));
}

/// The local histograms' direct openness written straight from docs/design.md, sharing no code
/// with cao-xr: A = 1 - sum w q / W over S_r, W over every member (in the grid or not).
fn independent_histogram_openness(q: &[f32], dims: &[usize], s: &[f64], r: f64) -> Vec<f64> {
    let s_min = s.iter().cloned().fold(f64::MAX, f64::min);
    let h: Vec<i64> = s.iter().map(|s| (r / s).floor() as i64).collect();
    let mut members = Vec::new();
    for z in -h[2]..=h[2] {
        for y in -h[1]..=h[1] {
            for x in -h[0]..=h[0] {
                let d2 = (x as f64 * s[0]).powi(2)
                    + (y as f64 * s[1]).powi(2)
                    + (z as f64 * s[2]).powi(2);
                if d2 > 0.0 && d2 <= r * r {
                    members.push(([x, y, z], s_min * s_min / d2));
                }
            }
        }
    }
    let total: f64 = members.iter().map(|m| m.1).sum();
    let mut out = Vec::new();
    for z in 0..dims[2] as i64 {
        for y in 0..dims[1] as i64 {
            for x in 0..dims[0] as i64 {
                let mut occ = 0.0;
                for (o, w) in &members {
                    let p = [x + o[0], y + o[1], z + o[2]];
                    if (0..3).all(|a| p[a] >= 0 && (p[a] as usize) < dims[a]) {
                        occ += w * q
                            [p[0] as usize + dims[0] * (p[1] as usize + dims[1] * p[2] as usize)]
                            as f64;
                    }
                }
                out.push(1.0 - occ / total);
            }
        }
    }
    out
}

#[test]
fn ao_command_histogram_agrees_with_an_independent_implementation_and_the_cpu_reference() {
    let dir = tmp("ao-histogram");
    let vol = dir.join("head.nrrd");
    assert!(
        cao(&["phantom", "--size", "20", "--out", vol.to_str().unwrap()])
            .status
            .success()
    );
    let run = |tag: &str, extra: &[&str]| {
        let (a, q, e) = (
            dir.join(format!("{tag}-a.nrrd")),
            dir.join(format!("{tag}-q.nrrd")),
            dir.join(format!("{tag}-e.nrrd")),
        );
        let mut args = vec![
            "ao",
            vol.to_str().unwrap(),
            "--tf",
            "ct-skin",
            "--ao",
            "histogram",
            "--hist-hemispheres=false",
            "--clusters",
            "0",
            "--hist-radius-mm",
            "25",
            "--hist-bins",
            "32",
            "--out",
            a.to_str().unwrap(),
            "--opacity-out",
            q.to_str().unwrap(),
            "--bleeding-out",
            e.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let out = cao(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        (a, q, e)
    };
    let (a, q, e) = run("gpu", &[]);
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(a.with_extension("json")).unwrap()).unwrap();
    assert_eq!(side["method"], "histogram");
    assert_eq!(side["radius_mm"], 25.0);
    assert_eq!(side["bins"], 32);
    assert_eq!(side["clusters"], 0);
    assert_eq!(side["hemispheres"], false);
    for key in ["spacing_mm", "dims"] {
        assert!(side.get(key).is_some(), "sidecar lacks {key}");
    }
    let (dims, spacing, got) = read_nrrd_f32(&a);
    let (_, _, qv) = read_nrrd_f32(&q);
    assert!(qv.iter().any(|&x| x > 0.0));
    let want = independent_histogram_openness(&qv, &dims, &spacing, 25.0);
    crate::common::assert_agrees(&got, &want, "histogram --clusters 0");
    assert!(got.iter().any(|&x| x < 0.8), "no occlusion");
    // E: RGB, equal to the CPU reference's within the GPU's 8 bits.
    let text = std::fs::read(&e).unwrap();
    let header = String::from_utf8_lossy(
        &text[..text
            .windows(2)
            .position(|w| {
                w == b"

"
            })
            .unwrap()],
    )
    .to_string();
    assert!(
        header.contains("sizes: 3 20 20 20")
            && header.contains("kinds: RGB-color domain domain domain"),
        "{header}"
    );
    let (_, _, ce) = run("cpu", &["--cpu"]);
    let floats = |p: &Path| -> Vec<f32> {
        let b = std::fs::read(p).unwrap();
        let at = b
            .windows(2)
            .position(|w| {
                w == b"

"
            })
            .unwrap()
            + 2;
        b[at..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect()
    };
    let (ge, ce) = (floats(&e), floats(&ce));
    assert_eq!(ge.len(), 3 * 20 * 20 * 20);
    let worst = ge
        .iter()
        .zip(&ce)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(
        worst <= 0.5 / 255.0 + 1e-4,
        "E differs from the CPU reference by {worst}"
    );
    assert!(ce.iter().any(|&x| x > 0.1), "some bleeding colour");
    // A render under the method, carved, with and without bleeding.
    let render = |tag: &str, bleeding: &str| {
        let out = dir.join(tag);
        let o = cao(&[
            "render",
            vol.to_str().unwrap(),
            "--tf",
            "ct-skin",
            "--ao",
            "histogram",
            "--clusters",
            "16",
            "--hist-radius-mm",
            "25",
            "--hist-bins",
            "16",
            "--bleeding",
            bleeding,
            "--size",
            "32x32",
            "--tool",
            "sphere:40",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        std::fs::read(out.join("stereo.png")).unwrap()
    };
    assert!(
        render("bleed", "0.9") != render("plain", "0"),
        "--bleeding changes the picture"
    );
    // The bleeding colour is the local histograms' alone.
    let bad = cao(&[
        "ao",
        vol.to_str().unwrap(),
        "--out",
        dir.join("x.nrrd").to_str().unwrap(),
        "--bleeding-out",
        dir.join("y.nrrd").to_str().unwrap(),
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("histogram"));
}

/// The two hemispheres' front openness written straight from docs/design.md, sharing no code
/// with cao-xr: Δ from the scalar's clamped central differences; flat where |Δ_i / (2 s_i)| is
/// below 0.004 of the value range per mm (S_r kept); else H_f = the members o with o . Δ <= 0,
/// A = 1 - sum over H_f of w q / sum over H_f of w (out-of-grid members in the denominator).
fn independent_hemisphere_openness(
    f: &[f64],
    q: &[f32],
    dims: &[usize],
    s: &[f64],
    r: f64,
) -> Vec<f64> {
    let (lo, hi) = f
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    let flat = 0.004 * (hi - lo);
    let at = |p: [i64; 3]| p[0] as usize + dims[0] * (p[1] as usize + dims[1] * p[2] as usize);
    let s_min = s.iter().cloned().fold(f64::MAX, f64::min);
    let mut out = Vec::new();
    for z in 0..dims[2] as i64 {
        for y in 0..dims[1] as i64 {
            for x in 0..dims[0] as i64 {
                let v = [x, y, z];
                let delta: Vec<f64> = (0..3)
                    .map(|a| {
                        let (mut up, mut down) = (v, v);
                        up[a] = (v[a] + 1).min(dims[a] as i64 - 1);
                        down[a] = (v[a] - 1).max(0);
                        f[at(up)] - f[at(down)]
                    })
                    .collect();
                let g: f64 = (0..3).map(|a| (delta[a] / (2.0 * s[a])).powi(2)).sum();
                let split = g.sqrt() >= flat;
                let (mut occ, mut total) = (0.0, 0.0);
                let h: Vec<i64> = s.iter().map(|s| (r / s).floor() as i64).collect();
                for oz in -h[2]..=h[2] {
                    for oy in -h[1]..=h[1] {
                        for ox in -h[0]..=h[0] {
                            let o = [ox, oy, oz];
                            let d2: f64 = (0..3).map(|a| (o[a] as f64 * s[a]).powi(2)).sum();
                            if d2 == 0.0 || d2 > r * r {
                                continue;
                            }
                            let dot: f64 = (0..3).map(|a| o[a] as f64 * delta[a]).sum();
                            if split && dot > 0.0 {
                                continue;
                            }
                            let w = s_min * s_min / d2;
                            total += w;
                            let p = [x + ox, y + oy, z + oz];
                            if (0..3).all(|a| p[a] >= 0 && (p[a] as usize) < dims[a]) {
                                occ += w * q[at(p)] as f64;
                            }
                        }
                    }
                }
                out.push(1.0 - occ / total);
            }
        }
    }
    out
}

#[test]
fn ao_command_hemispheres_agree_with_an_independent_implementation() {
    let dir = tmp("ao-hemispheres");
    // A 16-bit CT-like volume on an anisotropic grid: an ellipsoid of "bone" (1200) in "soft
    // tissue" (40) with a tilted slab of air (-1000) through it, so gradients point every way.
    let (dims, s) = ([18usize, 16, 12], [1.0f64, 1.25, 1.6]);
    let mut f = Vec::new();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let p = [x as f64 * s[0], y as f64 * s[1], z as f64 * s[2]];
                let e = ((p[0] - 9.0) / 6.0).powi(2)
                    + ((p[1] - 9.0) / 5.0).powi(2)
                    + ((p[2] - 9.0) / 7.0).powi(2);
                let slab = (p[0] + 0.5 * p[1] - 0.7 * p[2] - 6.0).abs() < 1.5;
                f.push(if slab {
                    -1000i16
                } else if e < 1.0 {
                    1200
                } else {
                    40
                });
            }
        }
    }
    let vol = dir.join("ct.nrrd");
    let mut file = format!(
        "NRRD0004\ntype: short\ndimension: 3\nsizes: {} {} {}\nspace: left-posterior-superior\n\
         space directions: ({},0,0) (0,{},0) (0,0,{})\nspace origin: (0,0,0)\nendian: little\n\
         encoding: raw\n\n",
        dims[0], dims[1], dims[2], s[0], s[1], s[2]
    )
    .into_bytes();
    file.extend(f.iter().flat_map(|v| v.to_le_bytes()));
    std::fs::write(&vol, file).unwrap();
    let tf = dir.join("bone.json");
    std::fs::write(
        &tf,
        r#"{"name":"bone","domain":"normalized","points":[
            {"value":0.0,"color":[0,0,0],"alpha":0.0},
            {"value":0.5,"color":[1,1,1],"alpha":0.0},
            {"value":0.6,"color":[1,1,1],"alpha":1.0},
            {"value":1.0,"color":[1,1,1],"alpha":1.0}]}"#,
    )
    .unwrap();
    let (a, q) = (dir.join("a.nrrd"), dir.join("q.nrrd"));
    let out = cao(&[
        "ao",
        vol.to_str().unwrap(),
        "--tf",
        tf.to_str().unwrap(),
        "--ao",
        "histogram",
        "--clusters",
        "0",
        "--hist-radius-mm",
        "4",
        "--hist-bins",
        "16",
        "--out",
        a.to_str().unwrap(),
        "--opacity-out",
        q.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(a.with_extension("json")).unwrap()).unwrap();
    // The hemispheres are the default.
    assert_eq!(side["hemispheres"], true);
    let (got_dims, _, got) = read_nrrd_f32(&a);
    assert_eq!(got_dims, dims);
    let (_, _, qv) = read_nrrd_f32(&q);
    let fv: Vec<f64> = f.iter().map(|&v| v as f64).collect();
    let want = independent_hemisphere_openness(&fv, &qv, &dims, &s, 4.0);
    crate::common::assert_agrees(&got, &want, "histogram --hist-hemispheres --clusters 0");
    // Just outside the bone the front faces away from it: open, where the sphere is not.
    let i = 9 + dims[0] * (7 + dims[1]); // (9, 7, 1)
    assert!(qv[i] == 0.0 && want[i] > 0.99, "open outside: {}", want[i]);
    let sphere = independent_histogram_openness(&qv, &dims, &s, 4.0);
    let opened = want
        .iter()
        .zip(&sphere)
        .filter(|(h, s)| **h > **s + 0.05)
        .count();
    assert!(opened > 50, "{opened} voxels opened");
}

/// A PNG's pixels: (width, height, channels, bytes).
fn read_png(path: &Path) -> (usize, usize, usize, Vec<u8>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (
        info.width as usize,
        info.height as usize,
        info.color_type.samples(),
        buf,
    )
}

#[test]
fn a_transparent_render_composites_over_a_background_as_the_opaque_render_with_it() {
    let dir = tmp("transparent");
    let render = |tag: &str, bg: &str| {
        let out = dir.join(tag);
        let o = cao(&[
            "render",
            "phantom:24",
            "--rays",
            "6",
            "--steps",
            "4",
            "--size",
            "40x40",
            "--tool",
            "sphere:50",
            "--background",
            bg,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        read_png(&out.join("left.png"))
    };
    let (w, h, ch, rgba) = render("rgba", "transparent");
    assert_eq!((w, h, ch), (40, 40, 4), "RGBA");
    assert_eq!(rgba[3], 0, "a ray that misses the volume has alpha 0");
    assert!(
        rgba.chunks(4).any(|p| p[3] == 255),
        "the volume is opaque somewhere"
    );
    assert!(
        rgba.chunks(4).any(|p| p[3] > 0 && p[3] < 255),
        "and translucent somewhere"
    );
    let bg = [0.2f64, 0.5, 0.8];
    let (_, _, ch, opaque) = render("opaque", "0.2,0.5,0.8");
    assert_eq!(ch, 3);
    let mut worst = 0.0f64;
    for (p, q) in rgba.chunks(4).zip(opaque.chunks(3)) {
        let a = p[3] as f64 / 255.0;
        for c in 0..3 {
            let over = p[c] as f64 / 255.0 * a + bg[c] * (1.0 - a);
            worst = worst.max((over - q[c] as f64 / 255.0).abs());
        }
    }
    // The issue's bar: within 1/255 per channel (the opaque PNG rounds once, the straight
    // colour by at most half a step times alpha).
    assert!(
        worst <= 1.0 / 255.0 + 1e-9,
        "the composite is {:.2}/255 off",
        worst * 255.0
    );
    let bad = cao(&[
        "render",
        "phantom:8",
        "--background",
        "purple",
        "--out",
        dir.join("x").to_str().unwrap(),
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("transparent"));
}

#[test]
fn a_negative_isovalue_is_taken_with_or_without_an_equals_sign() {
    let dir = tmp("iso-negative");
    let render = |iso: &[&str], name: &str| {
        let out_dir = dir.join(name);
        let mut args = vec!["render", "phantom:24", "--size", "24x24", "--rays", "6"];
        args.extend_from_slice(iso);
        args.extend_from_slice(&["--out", out_dir.to_str().unwrap()]);
        let out = cao(&args);
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{iso:?}: {stderr}");
        std::fs::read(out_dir.join("stereo.png")).unwrap()
    };
    let spaced = render(&["--iso", "-500"], "spaced");
    assert_eq!(spaced, render(&["--iso=-500"], "equals"));
    assert_ne!(spaced, render(&["--iso", "300"], "positive"));
}

/// `render ARGS EXTRA --out DIR/NAME` under validation: its left and right eyes.
fn render_eyes(
    dir: &Path,
    name: &str,
    args: &[&str],
    extra: &[&str],
) -> [(usize, usize, usize, Vec<u8>); 2] {
    let out_dir = dir.join(name);
    let mut all = vec!["render"];
    all.extend_from_slice(args);
    all.extend_from_slice(extra);
    all.extend_from_slice(&["--out", out_dir.to_str().unwrap()]);
    let out = cao(&all);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{extra:?}: {stderr}");
    assert!(!stderr.contains("vulkan validation"), "{stderr}");
    ["left.png", "right.png"].map(|e| read_png(&out_dir.join(e)))
}

/// Foveation (`--foveate RADIUS,FACTOR`): within the radius of each eye's centre the picture is
/// the unfoveated one bit for bit; beyond it the coarse rays, interpolated, keep the whole
/// picture within 32 dB, and they are not the full-rate rays (some pixel there differs).
#[test]
fn a_foveated_eye_is_exact_in_its_centre_and_close_beyond() {
    let dir = tmp("foveate");
    let args = [
        "phantom:48",
        "--size",
        "96x80",
        "--rays",
        "6",
        "--tool",
        "sphere:40",
    ];
    let render = |extra: &[&str], name: &str| render_eyes(&dir, name, &args, extra);
    let (full, fov) = (
        render(&[], "full"),
        render(&["--foveate", "0.25,3"], "foveated"),
    );
    // The centre is each eye's lens centre: `render`'s eyes look straight ahead through
    // frusta made off-axis to frame the volume, so it lies a little off the image's centre.
    let views = cao_xr::space::default_stereo_views(
        &cao_xr::volume::phantom::head(48),
        &cao_xr::space::Placement::default(),
        cao_xr::space::DEFAULT_IPD,
    );
    for (eye, (a, b)) in full.iter().zip(&fov).enumerate() {
        let (w, h, c) = (a.0, a.1, a.2);
        assert_eq!((w, h, c), (b.0, b.1, b.2));
        let radius = 0.25 * 0.5 * (w as f64).hypot(h as f64);
        let lens = cao_xr::render::fovea_centre(&views[eye], None, (w as u32, h as u32));
        let (mut centre, mut beyond_differs, mut se) = (0, false, 0.0);
        for y in 0..h {
            for x in 0..w {
                let r = (x as f64 + 0.5 - lens[0] as f64).hypot(y as f64 + 0.5 - lens[1] as f64);
                let (pa, pb) = (&a.3[(y * w + x) * c..][..c], &b.3[(y * w + x) * c..][..c]);
                if r <= radius - 0.01 {
                    assert_eq!(pa, pb, "eye {eye}, pixel {x},{y} in the centre");
                    centre += 1;
                } else {
                    beyond_differs |= pa != pb;
                }
                se += (0..3)
                    .map(|k| (pa[k] as f64 - pb[k] as f64).powi(2))
                    .sum::<f64>();
            }
        }
        let psnr = 10.0 * (255.0f64.powi(2) / (se / (3 * w * h) as f64)).log10();
        assert!(centre > w * h / 20, "eye {eye}: {centre} centre pixels");
        assert!(
            beyond_differs,
            "eye {eye}: the periphery was cast at full rate"
        );
        assert!(
            psnr >= 32.0,
            "eye {eye}: {psnr:.1} dB against the unfoveated picture"
        );
    }
}

/// `--reproject` with a carving tool and the AO: the left eye is the one without it, byte for
/// byte; the right eye is within 40 dB of its own rays, and reprojected (some pixel differs).
#[test]
fn a_reprojected_right_eye_keeps_the_left_and_stays_close() {
    let dir = tmp("reproject");
    let args = [
        "phantom:96",
        "--size",
        "160x160",
        "--rays",
        "6",
        "--tool",
        "sphere:30",
    ];
    let render = |extra: &[&str], name: &str| render_eyes(&dir, name, &args, extra);
    let (full, re) = (render(&[], "full"), render(&["--reproject"], "reprojected"));
    assert!(full[0] == re[0], "the left eye changed");
    let (a, b) = (&full[1].3, &re[1].3);
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum();
    let psnr = 10.0 * (255.0f64.powi(2) / (se / a.len() as f64)).log10();
    assert!(a != b, "nothing was reprojected");
    assert!(
        psnr >= 40.0,
        "the right eye is {psnr:.1} dB from its own rays"
    );
}

/// Scattering (`--hist-scattering W --hist-anisotropy g --light-from X,Y,Z`) adds to each ray
/// the bleeding colour times the Henyey-Greenstein phase of the angle between the light's travel
/// and the way to the eye, the same for every sample of a ray, on top of the picture without
/// it. Under `--shading ao` nothing else depends on the light, so: with g = 0 where the light
/// stands changes no pixel; lit from behind the volume (the eye looks into the light) the
/// added light is (1 - g^2) / (1 - g)^3 = 1.875 times g = 0's for g = 0.2, and lit from the
/// eye's side (1 - g^2) / (1 + g)^3 = 0.556 times (rays off the axis see the light a little
/// askew: a few per cent less); without the local histograms it adds nothing.
#[test]
fn scattering_follows_the_henyey_greenstein_phase() {
    let dir = tmp("scattering");
    let render = |ao: &str, extra: &[&str], name: &str| {
        let out_dir = dir.join(name);
        let mut args = vec!["render", "phantom:40", "--size", "64x64", "--rays", "6"];
        args.extend_from_slice(&["--shading", "ao", "--ao", ao, "--clusters", "0"]);
        args.extend_from_slice(&["--hist-hemispheres", "--out", out_dir.to_str().unwrap()]);
        args.extend_from_slice(extra);
        let out = cao(&args);
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{extra:?}: {stderr}");
        assert!(!stderr.contains("vulkan validation"), "{stderr}");
        ["left.png", "right.png"].map(|e| read_png(&out_dir.join(e)).3)
    };
    let (behind, front) = (["--light-from", "0,0,-1"], ["--light-from", "0,0,1"]);
    let lit = |g: &str, light: [&str; 2], name: &str| {
        let mut args = vec!["--hist-scattering", "0.1", "--hist-anisotropy", g];
        args.extend_from_slice(&light);
        render("histogram", &args, name)
    };
    let off = render("histogram", &[], "off");
    let even = lit("0", behind, "even-behind");
    assert!(
        even == lit("0", front, "even-front"),
        "g = 0 depends on the light"
    );
    // The light added, summed over both eyes' colour channels (alpha is the same throughout).
    let added = |img: &[Vec<u8>; 2]| -> f64 {
        img.iter()
            .zip(&off)
            .flat_map(|(a, b)| a.chunks(4).zip(b.chunks(4)))
            .map(|(a, b)| (0..3).map(|k| a[k] as f64 - b[k] as f64).sum::<f64>())
            .sum()
    };
    let base = added(&even);
    assert!(base > 1000.0, "scattering added only {base} levels");
    let back = added(&lit("0.2", behind, "back")) / base;
    let fore = added(&lit("0.2", front, "fore")) / base;
    assert!(
        (1.75..=1.9).contains(&back),
        "lit from behind: {back:.3} x g = 0's"
    );
    assert!(
        (0.52..=0.59).contains(&fore),
        "lit from the front: {fore:.3} x g = 0's"
    );
    // LAO has no bleeding colour to scatter.
    let lao = render("lao", &[], "lao");
    assert!(lao == render("lao", &["--hist-scattering", "1"], "lao-scattering"));
}

#[test]
fn render_writes_three_pngs() {
    let dir = tmp("render");
    let out = cao(&[
        "render",
        "phantom:32",
        "--size",
        "48x40",
        "--rays",
        "6",
        "--steps",
        "4",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for (name, w) in [("left.png", 48), ("right.png", 48), ("stereo.png", 96)] {
        let dec = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(dir.join(name)).unwrap(),
        ));
        let info = dec.read_info().unwrap().info().clone();
        assert_eq!((info.width, info.height), (w, 40), "{name}");
    }
}

#[test]
fn bench_ao_prints_every_method_in_one_table() {
    let out = cao(&[
        "bench",
        "ao",
        "phantom:16",
        "--runs",
        "1",
        "--frames",
        "2",
        "--radii",
        "20",
        "--rays",
        "6",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for method in ["lao K=6", "filter-cdf", "filter-gauss", "filter-penner"] {
        let row = text
            .lines()
            .find(|l| l.starts_with("phantom-16") && l.contains(method))
            .unwrap_or_else(|| panic!("no {method} row:\n{text}"));
        // full, clip, TF, MB, error, PSNR, SSIM after the method and radius
        let cols: Vec<&str> = row.split_whitespace().collect();
        let ssim: f64 = cols.last().unwrap().parse().unwrap();
        assert!((0.0..=1.0).contains(&ssim), "{row}");
        if method != "lao K=6" {
            let error: f64 = cols[cols.len() - 3].parse().unwrap();
            assert!((0.0..1.0).contains(&error), "{row}");
        }
    }
    assert!(text.contains("the fastest filter costs"), "{text}");
}

#[test]
fn bench_lao_prints_a_table() {
    let out = cao(&[
        "bench",
        "lao",
        "phantom:16",
        "--runs",
        "2",
        "--rays",
        "6,14",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("Msamples/s"), "{text}");
    let rows: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("phantom-16"))
        .collect();
    assert_eq!(rows.len(), 2, "{text}");
    // Both kernels by default, side by side: their ratio, and the new one computes the old
    // one's values (to float rounding, which may tip a stored 16-bit word by one step).
    for row in rows {
        let cols: Vec<&str> = row.split_whitespace().collect();
        let ratio: f64 = cols[cols.len() - 2].trim_end_matches('x').parse().unwrap();
        let diff: f64 = cols[cols.len() - 1].parse().unwrap();
        assert!(ratio > 0.0 && diff <= 1.0 / 65535.0 + 1e-7, "{row}");
    }
}

#[test]
fn bad_input_is_refused_with_the_file_named() {
    let dir = tmp("bad");
    let missing = dir.join("nope.nrrd");
    let out = cao(&[
        "render",
        missing.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("nope.nrrd"));
    let broken = dir.join("broken.nrrd");
    std::fs::write(&broken, "NRRD0004\ntype: short\ndimension: 3\nsizes: 10 10 10\nencoding: raw\nendian: little\n\n\x01\x02").unwrap();
    let out = cao(&["info", broken.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("broken.nrrd"), "{err}");
    let out = cao(&[
        "render",
        "phantom:16",
        "--tf",
        "no-such-tf",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-tf"));
}

#[test]
fn bench_cao_verifies_and_prints_the_speedup() {
    let out = cao(&[
        "bench",
        "cao",
        "phantom:32",
        "--rays",
        "6",
        "--frames",
        "3",
        "--runs",
        "1",
        "--steps",
        "4",
        "--verify",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("speedup") && text.contains("bit for bit"),
        "{text}"
    );
    let row = text
        .lines()
        .find(|l| l.starts_with("phantom-32"))
        .expect("a phantom-32 row");
    let speedup: f64 = row
        .split_whitespace()
        .nth(6)
        .unwrap()
        .trim_end_matches('x')
        .parse()
        .unwrap();
    assert!(speedup > 0.0, "{row}");
    // Then a probe of 20, 40 and 60 mm (verified too): the 60 mm one, deeper than the reach,
    // recomputes less than its inside.
    let probes: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| l.starts_with("phantom-32"))
        .skip(1)
        .map(|l| {
            l.split_whitespace()
                .skip(2)
                .map(|c| c.parse().unwrap())
                .collect()
        })
        .collect();
    assert_eq!(probes.len(), 3, "{text}");
    let big = &probes[2];
    assert!(big[1] == 60.0 && big[5] < big[6], "{text}");
}

#[test]
fn render_with_a_tool_reports_the_cut() {
    let dir = tmp("carve");
    let out = cao(&[
        "render",
        "phantom:32",
        "--size",
        "32x32",
        "--rays",
        "6",
        "--steps",
        "4",
        "--tool",
        "sphere:40",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("CAO:") && text.contains("recomputed"),
        "{text}"
    );
    let bad = cao(&[
        "render",
        "phantom:16",
        "--tool",
        "blob",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--tool 'blob'"));
}

#[test]
fn render_lit_by_an_environment_through_the_sh_volume() {
    let dir = tmp("sh");
    let render = |name: &str, extra: &[&str]| {
        let out_dir = dir.join(name);
        let mut args = vec![
            "render",
            "phantom:24",
            "--size",
            "32x32",
            "--rays",
            "6",
            "--steps",
            "4",
            "--tool",
            "sphere:40",
            "--sh-directions",
            "16",
            "--sh-downsample",
            "2",
            "--out",
            out_dir.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let out = cao(&args);
        (out, out_dir.join("left.png"))
    };
    let (ao, ao_png) = render("ao", &[]);
    assert!(
        ao.status.success(),
        "{}",
        String::from_utf8_lossy(&ao.stderr)
    );
    let (sh, sh_png) = render("sh", &["--lighting", "sh", "--light", "sky"]);
    assert!(
        sh.status.success(),
        "{}",
        String::from_utf8_lossy(&sh.stderr)
    );
    let (turned, turned_png) = render(
        "turned",
        &["--lighting", "sh", "--light", "sky", "--light-yaw", "-90"],
    );
    assert!(turned.status.success());
    let read = |p: &Path| std::fs::read(p).unwrap();
    assert_ne!(
        read(&ao_png),
        read(&sh_png),
        "SH lighting changes the picture"
    );
    assert_ne!(
        read(&sh_png),
        read(&turned_png),
        "so does turning the light"
    );

    let missing = dir.join("no-such-room.hdr");
    let (bad, _) = render(
        "bad",
        &["--lighting", "ao+sh", "--light", missing.to_str().unwrap()],
    );
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("no-such-room.hdr"), "{err}");
    let (bad, _) = render("bad", &["--lighting", "sunny"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("ao, sh or ao+sh"));
    let (bad, _) = render("bad", &["--lighting", "sh", "--sh-coeffs", "9"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("SH"));
}

#[test]
fn replay_with_sh_lighting_updates_the_sh_volume_where_the_tool_carves() {
    let dir = tmp("replay-sh");
    let script = script(&dir, "sweep.jsonl", "sphere-sweep", 8);
    let frames = dir.join("frames");
    let out = cao(&[
        "replay",
        script.to_str().unwrap(),
        "phantom:24",
        "--rays",
        "6",
        "--steps",
        "3",
        "--size",
        "16x16",
        "--every",
        "1000",
        "--lighting",
        "ao+sh",
        "--sh-directions",
        "16",
        "--sh-downsample",
        "2",
        "--out",
        frames.to_str().unwrap(),
    ]);
    let stats = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stats}");
    assert!(
        stats
            .lines()
            .filter(|l| l.starts_with("frame "))
            .all(|l| l.contains(" SH ")),
        "{stats}"
    );
    let csv = std::fs::read_to_string(frames.join("metrics.csv")).unwrap();
    // (voxels recomputed by CAO, SH voxels updated) per frame
    let rows: Vec<(u64, u64)> = csv
        .lines()
        .skip(1)
        .map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            (c[9].parse().unwrap(), c[14].parse().unwrap())
        })
        .collect();
    assert_eq!(rows.len(), 8);
    assert!(rows.iter().any(|r| r.0 > 0), "the sweep carves: {csv}");
    for r in &rows {
        assert_eq!(
            r.0 > 0,
            r.1 > 0,
            "SH updates exactly on carving frames: {csv}"
        );
    }
}

#[test]
fn replay_writes_frames_metrics_and_preview() {
    let dir = tmp("replay");
    let script = script(&dir, "sweep.jsonl", "sphere-sweep", 6);
    let frames = dir.join("frames");
    let preview = dir.join("preview.png");
    let out = cao(&[
        "replay",
        script.to_str().unwrap(),
        "phantom:24",
        "--rays",
        "6",
        "--steps",
        "3",
        "--size",
        "32x32",
        "--every",
        "2",
        "--out",
        frames.to_str().unwrap(),
        "--preview",
        preview.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for i in [0, 2, 4] {
        assert!(
            frames.join(format!("frame-{i:05}.png")).exists(),
            "frame {i}"
        );
    }
    assert!(
        !frames.join("frame-00001.png").exists(),
        "--every 2 keeps one frame in two"
    );
    let csv = std::fs::read_to_string(frames.join("metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 7, "{csv}");
    assert!(csv.starts_with("frame,time_s,frame_ms,ao_update_ms"));
    let stats = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        stats.lines().filter(|l| l.starts_with("frame ")).count(),
        6,
        "a stats line per frame"
    );
    let apng = std::fs::read(&preview).unwrap();
    assert!(
        apng.windows(4).any(|w| w == b"acTL"),
        "the preview is animated"
    );
}

/// The menu press of `tf-switch` starts a progressive recompute: the old TF stays until it is
/// done, metrics.csv and the stats lines show the progress, then the new TF is shown.
#[test]
fn replay_switches_the_transfer_function_on_menu() {
    let dir = tmp("tf-switch");
    let script = script(&dir, "tf.jsonl", "tf-switch", 24);
    let frames = dir.join("frames");
    let out = cao(&[
        "replay",
        script.to_str().unwrap(),
        "phantom:24",
        "--rays",
        "6",
        "--steps",
        "3",
        "--size",
        "16x16",
        "--every",
        "1000",
        "--out",
        frames.to_str().unwrap(),
    ]);
    let stats = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stats}");
    let csv = std::fs::read_to_string(frames.join("metrics.csv")).unwrap();
    let mut lines = csv.lines();
    assert!(
        lines
            .next()
            .unwrap()
            .ends_with(",tf,tf_progress,tf_ms,sh_voxels,sh_ms,ao_method"),
        "{csv}"
    );
    // (tf shown, progress of a switch in flight)
    let rows: Vec<(String, Option<f32>)> = lines
        .map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            (c[11].to_string(), c[12].parse().ok())
        })
        .collect();
    assert_eq!(rows.len(), 24);
    let first_new = rows
        .iter()
        .position(|r| r.0 == "ct-soft-tissue")
        .expect(&csv);
    assert!(
        rows[first_new..]
            .iter()
            .all(|r| r == &("ct-soft-tissue".into(), None)),
        "{csv}"
    );
    assert!(rows[..first_new].iter().all(|r| r.0 == "ct-bone"), "{csv}");
    // The press (at 25 %) starts it; it runs until the frame before the switch.
    let started = rows.iter().position(|r| r.1.is_some()).expect(&csv);
    assert!((5..first_new).contains(&started), "{csv}");
    let progress: Vec<f32> = rows[started..first_new]
        .iter()
        .map(|r| r.1.unwrap())
        .collect();
    assert!(progress.windows(2).all(|w| w[0] <= w[1]), "{csv}");
    assert_eq!(*progress.last().unwrap(), 1.0, "{csv}");
    assert!(stats.contains("TF ct-soft-tissue 100%"), "{stats}");
}

#[test]
fn every_committed_script_replays_without_validation_messages() {
    let scripts = Path::new(env!("CARGO_MANIFEST_DIR")).join("controllers/scripts");
    let mut n = 0;
    for e in std::fs::read_dir(&scripts).unwrap() {
        let p = e.unwrap().path();
        if p.extension().and_then(|x| x.to_str()) != Some("jsonl") {
            continue;
        }
        let dir = tmp(&format!(
            "script-{}",
            p.file_stem().unwrap().to_string_lossy()
        ));
        // cao() fails the test on any validation message or panic.
        let out = cao(&[
            "replay",
            p.to_str().unwrap(),
            "phantom:16",
            "--rays",
            "6",
            "--steps",
            "3",
            "--size",
            "16x16",
            "--every",
            "1000",
            "--out",
            dir.to_str().unwrap(),
        ]);
        assert!(
            out.status.success(),
            "{}: {}",
            p.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        n += 1;
    }
    assert!(n >= 7, "expected the seven scripts, found {n}");
}

#[test]
fn info_reads_nifti_and_metaimage() {
    use cao_xr::volume::{metaimage, nifti, Modality, Volume, Voxels};
    use glam::{DMat3, DVec3};
    let dir = tmp("medio");
    let vol = Volume {
        whole_range: None,
        name: "m".into(),
        dims: [6, 5, 4],
        spacing: [0.5, 0.75, 2.5],
        directions: DMat3::from_rotation_y(0.4),
        origin: DVec3::new(10.0, -20.0, 30.0),
        modality: Modality::Unknown,
        voxels: Voxels::I16((0..120).map(|i| i * 10 - 500).collect()),
        labels: None,
    };
    let files = [
        dir.join("v.nii"),
        dir.join("v.nii.gz"),
        dir.join("v.mha"),
        dir.join("v.mhd"),
    ];
    nifti::write(&files[0], &vol, false).unwrap();
    nifti::write(&files[1], &vol, true).unwrap();
    metaimage::write(&files[2], &vol, false).unwrap();
    metaimage::write(&files[3], &vol, true).unwrap();
    for f in &files {
        let out = cao(&["info", f.to_str().unwrap()]);
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{}: {}",
            f.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(text.contains("dims        6 x 5 x 4"), "{text}");
        assert!(text.contains("type        int16"), "{text}");
        assert!(
            text.contains("spacing     0.5000 x 0.7500 x 2.5000 mm"),
            "{text}"
        );
        assert!(text.contains("values      -500 .. 690"), "{text}");
    }
    // A broken NIfTI is refused with the file named.
    let broken = dir.join("broken.nii");
    std::fs::write(&broken, [0u8; 40]).unwrap();
    let out = cao(&["info", broken.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("broken.nii"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn info_picks_the_transfer_function_and_downsamples() {
    use cao_xr::volume::{nrrd, Modality, Volume, Voxels};
    use glam::{DMat3, DVec3};
    let dir = tmp("auto-tf");
    let info = |args: &[&str]| {
        let out = cao(&[&["info"], args].concat());
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        text
    };
    // The CT phantom: ct-bone and the CT presets.
    let text = info(&["phantom:16"]);
    assert!(text.contains("tf          ct-bone"), "{text}");
    assert!(
        text.contains("presets     ct-bone, ct-soft-tissue, ct-muscle-bone, ct-lung, ct-angio"),
        "{text}"
    );
    // --tf overrides; the old name `mri` still resolves.
    let text = info(&["phantom:16", "--tf", "mri"]);
    assert!(text.contains("tf          mr-default"), "{text}");
    // Float data of unknown modality outside the HU range: float32, mr-default.
    let mut vol = Volume {
        whole_range: None,
        name: "f".into(),
        dims: [6, 5, 4],
        spacing: [0.5, 0.75, 2.5],
        directions: DMat3::IDENTITY,
        origin: DVec3::ZERO,
        modality: Modality::Unknown,
        voxels: Voxels::F32((0..120).map(|i| i as f32 * 0.25).collect()),
        labels: None,
    };
    let f = dir.join("f.nrrd");
    nrrd::write_volume(&f, &vol, false).unwrap();
    let text = info(&[f.to_str().unwrap()]);
    assert!(text.contains("type        float32"), "{text}");
    assert!(text.contains("values      0 .. 29.75"), "{text}");
    assert!(text.contains("tf          mr-default"), "{text}");
    assert!(text.contains("presets     mr-default, mr-angio"), "{text}");
    // HU-like values, modality unknown: ct-bone. Downsampled by 2: half the dims, twice the
    // spacing, the type kept.
    vol.voxels = Voxels::I16((0..120).map(|i| i * 20 - 1000).collect());
    let h = dir.join("hu.nrrd");
    nrrd::write_volume(&h, &vol, false).unwrap();
    let text = info(&[h.to_str().unwrap()]);
    assert!(text.contains("tf          ct-bone"), "{text}");
    let text = info(&[h.to_str().unwrap(), "--downsample", "2"]);
    assert!(text.contains("dims        3 x 3 x 2"), "{text}");
    assert!(
        text.contains("spacing     1.0000 x 1.5000 x 5.0000 mm"),
        "{text}"
    );
    assert!(text.contains("type        int16"), "{text}");
    let out = cao(&["info", h.to_str().unwrap(), "--downsample", "0"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--downsample"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_voxels_and_lying_headers_are_refused_by_the_cli() {
    let dir = tmp("bad-voxels");
    let run = |name: &str, header: &str, data: &[u8]| {
        let p = dir.join(name);
        let mut b = header.as_bytes().to_vec();
        b.extend_from_slice(data);
        std::fs::write(&p, b).unwrap();
        let out = cao(&["info", p.to_str().unwrap()]);
        assert!(!out.status.success(), "{name} was accepted");
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(err.contains(name), "{err}");
        err
    };
    // NaN voxel: the file, the voxel and the value.
    let mut data: Vec<u8> = (0..8).flat_map(|i| (i as f32).to_le_bytes()).collect();
    data[5 * 4..6 * 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let err = run(
        "nan.nrrd",
        "NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2 2\nendian: little\nencoding: raw\n\n",
        &data,
    );
    assert!(
        err.contains("voxel (1,0,1)") && err.contains("NaN"),
        "{err}"
    );
    // Sizes that claim 10^15 voxels: refused before anything is allocated.
    let err = run(
        "absurd.nrrd",
        "NRRD0004\ntype: short\ndimension: 3\nsizes: 100000 100000 100000\nendian: little\nencoding: raw\n\n",
        &[0; 16],
    );
    assert!(err.contains("too large"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_dicom_file_that_trips_a_codec_gets_an_error_not_a_panic() {
    // An RLE slice the dicom fuzz target found: the RLE decoder unwraps on it.
    let dir = tmp("rle-panic");
    let seed =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/dicom/bad-rle-decoder-panic.dcm");
    std::fs::copy(&seed, dir.join("slice.dcm")).unwrap();
    let out = cao(&["info", dir.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("slice.dcm") && err.contains("decoder failed"),
        "{err}"
    );
}

#[test]
fn every_subcommand_has_consistent_help() {
    // clap checks a command's arguments (unique names, defaults that parse) when it builds it.
    for cmd in [
        &["start"][..],
        &["render"],
        &["replay"],
        &["view"],
        &["xr"],
        &["ao"],
        &["info"],
        &["bench", "lao"],
        &["bench", "cao"],
        &["bench", "sh"],
        &["bench", "frame"],
        &["bench", "quality"],
        &["compare"],
        &["fetch-ct"],
        &["phantom"],
        &["script"],
    ] {
        let mut args = cmd.to_vec();
        args.push("--help");
        let out = cao(&args);
        assert!(
            out.status.success(),
            "{cmd:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

#[test]
fn a_signal_during_the_ao_precompute_leaves_no_output_under_the_final_name() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tmp("signal");
    for sig in [libc::SIGTERM, libc::SIGINT] {
        let out = dir.join(format!("ao-{sig}.nrrd"));
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_cao-xr"))
            .args([
                "ao",
                "phantom:128",
                "--rays",
                "54",
                "--steps",
                "16",
                "--out",
            ])
            .arg(&out)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        // Well inside the precompute (about a minute on lavapipe).
        std::thread::sleep(std::time::Duration::from_secs(2));
        assert!(
            child.try_wait().unwrap().is_none(),
            "finished before the signal"
        );
        // SAFETY: kill(2) reads no memory of ours; `child` is not waited for yet, so its pid cannot
        // have been reused.
        unsafe { libc::kill(child.id() as i32, sig) };
        let status = child.wait().unwrap();
        assert_eq!(status.signal(), Some(sig), "{status:?}");
        assert!(!out.exists(), "a partial {} exists", out.display());
        assert!(!out.with_extension("json").exists());
    }
}

#[test]
fn a_signal_during_a_replay_leaves_no_partial_metrics_under_the_final_name() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tmp("signal-replay");
    let script = script(&dir, "long.jsonl", "sphere-sweep", 5000);
    let out = dir.join("frames");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_cao-xr"))
        .args([
            "replay",
            script.to_str().unwrap(),
            "phantom:32",
            "--rays",
            "6",
            "--size",
            "32x32",
        ])
        .args(["--every", "1", "--out", out.to_str().unwrap()])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Wait for the first frames, then stop it.
    let t0 = std::time::Instant::now();
    while !out.join("frame-00002.png").exists() {
        assert!(t0.elapsed().as_secs() < 120, "no frame after two minutes");
        assert!(
            child.try_wait().unwrap().is_none(),
            "the replay ended early"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    // SAFETY: kill(2) reads no memory of ours; `child` is not waited for yet, so its pid cannot
    // have been reused.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let status = child.wait().unwrap();
    assert_eq!(status.signal(), Some(libc::SIGTERM), "{status:?}");
    assert!(!out.join("metrics.csv").exists(), "a partial metrics.csv");
    // Every frame written is a whole PNG.
    for e in std::fs::read_dir(&out).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "png") {
            let (w, _, _, _) = read_png(&p);
            assert_eq!(w, 64, "{}", p.display());
        }
    }
}

#[test]
fn compare_measures_a_render_against_the_reference_and_refuses_bad_pictures() {
    let dir = tmp("compare");
    let render = |name: &str, extra: &[&str]| {
        let out_dir = dir.join(name);
        let mut args = vec!["render", "phantom:24", "--rays", "6", "--size", "48x48"];
        args.extend_from_slice(extra);
        args.extend(["--out", out_dir.to_str().unwrap()]);
        let o = cao(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        out_dir
    };
    let (def, reference) = (
        render("default", &[]),
        render("reference", &["--reference"]),
    );
    let flat = render("flat", &["--shading", "ao"]);
    let diff = dir.join("diff.png");
    let psnr_of = |a: &Path, b: &Path, extra: &[&str]| -> f64 {
        let mut args = vec!["compare", a.to_str().unwrap(), b.to_str().unwrap()];
        args.extend_from_slice(extra);
        let o = cao(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let text = String::from_utf8_lossy(&o.stdout).to_string();
        assert!(text.contains("SSIM") && text.contains("48x48"), "{text}");
        text.split_whitespace().nth(1).unwrap().parse().unwrap()
    };
    let near = psnr_of(
        &reference.join("left.png"),
        &def.join("left.png"),
        &["--diff", diff.to_str().unwrap()],
    );
    // Another shading mode is a different picture: much further from the reference.
    let far = psnr_of(&reference.join("left.png"), &flat.join("left.png"), &[]);
    assert!(
        near > 30.0 && far < near - 5.0,
        "near {near} dB, far {far} dB"
    );
    assert!(psnr_of(&def.join("left.png"), &def.join("left.png"), &[]).is_infinite());
    let (w, h, _, _) = read_png(&diff);
    assert_eq!((w, h), (48, 48));
    // Pictures of different sizes, and a file that is no PNG, are refused by name.
    let o = cao(&[
        "compare",
        def.join("left.png").to_str().unwrap(),
        def.join("stereo.png").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("differ in size"));
    let junk = dir.join("junk.png");
    std::fs::write(&junk, b"not a picture").unwrap();
    let o = cao(&[
        "compare",
        junk.to_str().unwrap(),
        def.join("left.png").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("junk.png"));
    // A shading mode or tint that does not exist is refused with what does.
    let o = cao(&["render", "phantom:16", "--shading", "toon"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("phong+ao"));
    let o = cao(&["render", "phantom:16", "--cut-tint", "2,0,0"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("0..1"));
}

#[test]
fn bench_quality_prints_every_step_multiple_against_the_reference() {
    let out = cao(&[
        "bench",
        "quality",
        "phantom:20",
        "--size",
        "32",
        "--runs",
        "1",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let rows: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("phantom-20"))
        .collect();
    // Per view: the reference, then 1x, 2x, 4x each with pre-integration on and off.
    assert_eq!(rows.len(), 2 * 7, "{text}");
    assert!(
        rows.iter().filter(|r| r.contains(" ref ")).count() == 2,
        "{text}"
    );
    assert!(
        text.contains("PSNR dB") && text.contains("render ms"),
        "{text}"
    );
}

#[test]
fn bench_frame_prints_every_pass_and_every_ratio() {
    let out = cao(&[
        "bench",
        "frame",
        "phantom:16",
        "--rays",
        "6",
        "--steps",
        "4",
        "--frames",
        "3",
        "--runs",
        "1",
        "--size",
        "32x32",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    // The number after a row's label (ms, a ratio "1.23x" or fps), finite and not negative
    // (a pass over a 16^3 volume may print 0.00 ms).
    let value = |label: &str| -> f64 {
        let line = text
            .lines()
            .find(|l| l.starts_with(label))
            .unwrap_or_else(|| panic!("no row '{label}' in\n{text}"));
        let v: f64 = line[label.len()..]
            .split_whitespace()
            .next()
            .unwrap()
            .trim_end_matches('x')
            .parse()
            .unwrap_or_else(|e| panic!("{line}: {e}"));
        assert!(v.is_finite() && v >= 0.0, "{line}");
        v
    };
    for pass in [
        "restore",
        "clip + mask",
        "AO update",
        "ray cast, left eye",
        "ray cast, right eye",
        "copy",
    ] {
        value(pass);
    }
    let frame = value("frame ");
    let eyes = value("ray cast, left eye") + value("ray cast, right eye");
    assert!(
        eyes > 0.0 && frame >= eyes,
        "the frame holds both eyes\n{text}"
    );
    // Both eyes cost more than one (the right eye is not free), and the ratio is the frame
    // over the one-eye frame it prints (on so small a volume the eyes' times are noise, so no
    // bar here: the README quotes the real one).
    let two_one = value("two eyes / one eye");
    let line = text.lines().find(|l| l.starts_with("two eyes")).unwrap();
    let ms: Vec<f64> = line
        .split(['(', '/', ';'])
        .filter_map(|p| p.trim().strip_suffix(" ms")?.parse().ok())
        .collect();
    assert_eq!(ms.len(), 2, "{line}");
    assert!(two_one > 1.0, "{line}");
    assert!((two_one - ms[0] / ms[1]).abs() < 0.01, "{line}");
    let r: Vec<f64> = [10, 25, 50]
        .map(|mm| value(&format!("CAO update, radius {mm} mm")))
        .to_vec();
    assert!(r.iter().all(|&ms| ms > 0.0), "{text}");
    let padded = text
        .lines()
        .find(|l| l.contains("32x32x32 (2x per axis, same spacing, same tool) / original"))
        .unwrap_or_else(|| panic!("no 2x-volume row in\n{text}"));
    assert!(padded.contains('x'), "{padded}");
    assert!(value("fps, 1 frame in flight") > 0.0, "{text}");
    assert!(value("fps, 2 frames in flight") > 0.0, "{text}");
    // Empty-space skipping: the sweep again skipping, and the bricks it skipped.
    let skipping = value("ray cast, both eyes, skipping");
    assert!(skipping > 0.0, "{text}");
    let line = text
        .lines()
        .find(|l| l.starts_with("ray cast, both eyes, skipping"))
        .unwrap();
    assert!(
        line.contains("x faster with empty-space skipping"),
        "{line}"
    );
    assert!(line.contains("bricks empty)"), "{line}");
    // The second eye cast and reprojected, unfoveated and foveated.
    for name in [
        "cast",
        "reprojected",
        "foveated, cast",
        "foveated, reprojected",
    ] {
        assert!(
            value(&format!("two eyes / one eye, {name} ")) > 1.0,
            "{name}\n{text}"
        );
    }
    // The frame budget's render scales: each measured, with its picture against full size.
    for s in ["0.75", "0.5 "] {
        let label = format!("ray cast, both eyes, scale {s}");
        assert!(value(&label) > 0.0, "{text}");
        let line = text.lines().find(|l| l.starts_with(&label)).unwrap();
        let db: f64 = line
            .split(" dB against full size")
            .next()
            .and_then(|l| l.rsplit(' ').next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no PSNR in {line}"));
        assert!(db.is_finite() && db > 10.0, "{line}");
    }
}

#[test]
fn replays_with_one_and_two_frames_in_flight_give_the_same_pngs() {
    let dir = tmp("in-flight");
    let script = script(&dir, "two-tools.jsonl", "two-tools", 8);
    let run = |n: &str| {
        let name = format!("depth-{n}");
        let (pngs, said) = replay_pngs(&script, &dir, &name, &["--frames-in-flight", n], 8);
        let overlapped: usize = said
            .split("; ")
            .nth(1)
            .and_then(|t| t.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no overlap count in: {said}"));
        (pngs, overlapped)
    };
    let ((one, alone), (two, overlapped)) = (run("1"), run("2"));
    for (i, (a, b)) in one.iter().zip(&two).enumerate() {
        assert!(a == b, "frame {i} differs between 1 and 2 frames in flight");
    }
    // With two in flight every frame after the first is recorded before the one before was
    // waited for; with one, none is.
    assert_eq!(alone, 0);
    assert_eq!(overlapped, 7);
    // The carving moves: frames that differ from each other, so a frame shown twice or one
    // frame late would not pass.
    assert!(one.windows(2).any(|w| w[0] != w[1]));
    let out = cao(&[
        "replay",
        script.to_str().unwrap(),
        "--frames-in-flight",
        "3",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--frames-in-flight"), "{err}");
}

/// A stream recorded with the volume placed elsewhere (`xr --volume-at`) replays there: the same
/// PNGs as `replay --volume-at` at that place, not those of the default placement.
#[test]
fn a_replay_puts_the_volume_where_the_session_had_it() {
    let dir = tmp("volume-at");
    let script = script(&dir, "sweep.jsonl", "sphere-sweep", 4);
    // The same stream, its header saying where the volume was (3 cm to the right).
    let text = std::fs::read_to_string(&script).unwrap();
    let placed = dir.join("placed.jsonl");
    std::fs::write(
        &placed,
        text.replacen('{', "{\"volume_at\":[0.03,1.4,-0.6],", 1),
    )
    .unwrap();
    let replay =
        |stream: &Path, name: &str, extra: &[&str]| replay_pngs(stream, &dir, name, extra, 4).0;
    let default = replay(&script, "default", &[]);
    let from_header = replay(&placed, "header", &[]);
    let from_flag = replay(&script, "flag", &["--volume-at", "0.03,1.4,-0.6"]);
    assert!(
        from_header == from_flag,
        "the header's placement was not used"
    );
    assert!(from_header != default, "the placement changed nothing");
    let _ = std::fs::remove_dir_all(&dir);
}
