//! Closed triangle meshes of the clipping tools: the built-in shapes, and OBJ / PLY files.

use super::TORUS_MINOR;
use glam::Vec3;
use std::f32::consts::PI;
use std::path::Path;

#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub vertices: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

#[derive(Debug, thiserror::Error)]
#[error("{path}: {msg}")]
pub struct MeshError {
    pub path: String,
    pub msg: String,
}

impl TriMesh {
    /// Half-extent of the axis-aligned box around the origin that holds the mesh.
    pub fn half_extent(&self) -> Vec3 {
        self.vertices.iter().fold(Vec3::ZERO, |m, v| m.max(v.abs()))
    }

    /// A grid of (u, v) samples mapped by `f`, triangulated; `wrap_u`/`wrap_v` close the seams.
    fn param(nu: usize, nv: usize, f: impl Fn(f32, f32) -> Vec3) -> TriMesh {
        let mut m = TriMesh::default();
        for j in 0..=nv {
            for i in 0..nu {
                m.vertices
                    .push(f(i as f32 / nu as f32, j as f32 / nv as f32));
            }
        }
        for j in 0..nv {
            for i in 0..nu {
                let a = (j * nu + i) as u32;
                let b = (j * nu + (i + 1) % nu) as u32;
                let c = a + nu as u32;
                let d = b + nu as u32;
                m.triangles.push([a, b, d]);
                m.triangles.push([a, d, c]);
            }
        }
        m
    }

    pub fn sphere() -> TriMesh {
        TriMesh::param(48, 24, |u, v| {
            let (t, p) = (v * PI, u * 2.0 * PI);
            Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos())
        })
    }

    pub fn torus() -> TriMesh {
        TriMesh::param(64, 32, |u, v| {
            let (a, b) = (u * 2.0 * PI, v * 2.0 * PI);
            let r = 1.0 + TORUS_MINOR * b.cos();
            Vec3::new(r * a.cos(), r * a.sin(), TORUS_MINOR * b.sin())
        })
    }

    pub fn cylinder() -> TriMesh {
        let n = 48;
        let mut m = TriMesh::default();
        for z in [-1.0f32, 1.0] {
            for i in 0..n {
                let a = i as f32 / n as f32 * 2.0 * PI;
                m.vertices.push(Vec3::new(a.cos(), a.sin(), z));
            }
        }
        let (bot, top) = (m.vertices.len() as u32, m.vertices.len() as u32 + 1);
        m.vertices.push(Vec3::new(0.0, 0.0, -1.0));
        m.vertices.push(Vec3::new(0.0, 0.0, 1.0));
        for i in 0..n as u32 {
            let j = (i + 1) % n as u32;
            let n = n as u32;
            m.triangles.push([i, j, j + n]);
            m.triangles.push([i, j + n, i + n]);
            m.triangles.push([bot, j, i]);
            m.triangles.push([top, i + n, j + n]);
        }
        m
    }

    pub fn cube() -> TriMesh {
        let mut m = TriMesh::default();
        for i in 0..8 {
            m.vertices.push(Vec3::new(
                if i & 1 == 0 { -1.0 } else { 1.0 },
                if i & 2 == 0 { -1.0 } else { 1.0 },
                if i & 4 == 0 { -1.0 } else { 1.0 },
            ));
        }
        let quads = [
            [0, 2, 3, 1],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 4, 6, 2],
            [1, 3, 7, 5],
        ];
        for q in quads {
            m.triangles.push([q[0], q[1], q[2]]);
            m.triangles.push([q[0], q[2], q[3]]);
        }
        m
    }

    /// Loads an OBJ (v / f lines; polygons fanned) or PLY (ASCII or binary little-endian; x y z
    /// float vertices and a face list) mesh, recentred on its bounding-box centre and scaled so
    /// its largest half-extent is 1.
    pub fn load(path: &Path) -> Result<TriMesh, MeshError> {
        let err = |msg: String| MeshError {
            path: path.display().to_string(),
            msg,
        };
        let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_lowercase();
        let mut m = match ext.as_str() {
            "obj" => parse_obj(&String::from_utf8_lossy(&bytes)).map_err(err)?,
            "ply" => parse_ply(&bytes).map_err(err)?,
            _ => return Err(err("unknown mesh format (expected .obj or .ply)".into())),
        };
        if m.triangles.is_empty() {
            return Err(err("no triangles".into()));
        }
        // (NaN would slip through the min/max below; found by the mesh fuzz target)
        if let Some((i, v)) = m.vertices.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(err(format!("vertex {i} has a non-finite coordinate {v}")));
        }
        let (lo, hi) = m
            .vertices
            .iter()
            .fold((Vec3::MAX, Vec3::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
        let (c, half) = ((lo + hi) * 0.5, ((hi - lo) * 0.5).max_element());
        if !(half.is_finite() && half > 0.0) {
            return Err(err("degenerate mesh (zero or non-finite size)".into()));
        }
        for v in &mut m.vertices {
            *v = (*v - c) / half;
        }
        Ok(m)
    }
}

fn check_indices(m: &TriMesh) -> Result<(), String> {
    let n = m.vertices.len() as u32;
    match m.triangles.iter().flatten().find(|&&i| i >= n) {
        Some(i) => Err(format!("face refers to vertex {i}, but there are only {n}")),
        None => Ok(()),
    }
}

fn parse_obj(text: &str) -> Result<TriMesh, String> {
    let mut m = TriMesh::default();
    for (ln, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let c: Vec<f32> = it
                    .take(3)
                    .map(|x| {
                        x.parse()
                            .map_err(|_| format!("line {}: bad vertex", ln + 1))
                    })
                    .collect::<Result<_, _>>()?;
                if c.len() != 3 || c.iter().any(|x| !x.is_finite()) {
                    return Err(format!(
                        "line {}: a vertex needs three finite coordinates",
                        ln + 1
                    ));
                }
                m.vertices.push(Vec3::new(c[0], c[1], c[2]));
            }
            Some("f") => {
                let n = m.vertices.len() as i64;
                let idx: Vec<u32> = it
                    .map(|t| {
                        let i: i64 = t
                            .split('/')
                            .next()
                            .unwrap_or("")
                            .parse()
                            .map_err(|_| format!("line {}: bad face index '{t}'", ln + 1))?;
                        let i = if i < 0 { n + i } else { i - 1 };
                        u32::try_from(i)
                            .map_err(|_| format!("line {}: face index {t} out of range", ln + 1))
                    })
                    .collect::<Result<_, _>>()?;
                if idx.len() < 3 {
                    return Err(format!("line {}: a face needs three vertices", ln + 1));
                }
                for k in 1..idx.len() - 1 {
                    m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            _ => {}
        }
    }
    check_indices(&m)?;
    Ok(m)
}

fn parse_ply(bytes: &[u8]) -> Result<TriMesh, String> {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .ok_or("not a PLY file (no end_header)")?;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "PLY header is not text")?;
    if !header.starts_with("ply") {
        return Err("not a PLY file (no 'ply' magic)".into());
    }
    let body = &bytes[end + 11..];
    let (mut nv, mut nf, mut format, mut vprops, mut in_vertex) =
        (0usize, 0usize, "", Vec::new(), false);
    for line in header.lines() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.as_slice() {
            ["format", f, ..] => format = f,
            ["element", "vertex", n] => {
                nv = n.parse().map_err(|_| "bad vertex count")?;
                in_vertex = true;
            }
            ["element", "face", n] => {
                nf = n.parse().map_err(|_| "bad face count")?;
                in_vertex = false;
            }
            ["element", ..] => in_vertex = false,
            ["property", "list", ..] => {}
            ["property", ty, name] if in_vertex => vprops.push((ty.to_string(), name.to_string())),
            _ => {}
        }
    }
    if nv > 50_000_000 || nf > 100_000_000 {
        return Err(format!(
            "{nv} vertices / {nf} faces is more than a clipping tool needs"
        ));
    }
    let pos = |n: &str| {
        vprops
            .iter()
            .position(|p| p.1 == n)
            .ok_or(format!("vertex has no '{n}' property"))
    };
    let (px, py, pz) = (pos("x")?, pos("y")?, pos("z")?);
    let mut m = TriMesh::default();
    match format {
        "ascii" => {
            let text = std::str::from_utf8(body).map_err(|_| "PLY body is not text")?;
            let mut lines = text.lines().filter(|l| !l.trim().is_empty());
            for _ in 0..nv {
                let c: Vec<f32> = lines
                    .next()
                    .ok_or("fewer vertices than declared")?
                    .split_whitespace()
                    .map(|x| x.parse().unwrap_or(f32::NAN))
                    .collect();
                let get = |i: usize| {
                    c.get(i)
                        .copied()
                        .filter(|x| x.is_finite())
                        .ok_or("bad vertex line")
                };
                m.vertices.push(Vec3::new(get(px)?, get(py)?, get(pz)?));
            }
            for _ in 0..nf {
                let idx: Vec<u32> = lines
                    .next()
                    .ok_or("fewer faces than declared")?
                    .split_whitespace()
                    .skip(1)
                    .map(|x| x.parse().map_err(|_| "bad face line"))
                    .collect::<Result<_, _>>()?;
                if idx.len() < 3 {
                    return Err("a face needs three vertices".into());
                }
                for k in 1..idx.len() - 1 {
                    m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
        }
        "binary_little_endian" => {
            // Vertices: every property float32 (the common case for meshes); faces: uchar count,
            // int32 indices.
            if vprops.iter().any(|p| p.0 != "float" && p.0 != "float32") {
                return Err("binary PLY vertices must be float32 properties".into());
            }
            let stride = vprops.len() * 4;
            let need = nv * stride;
            if body.len() < need {
                return Err(format!(
                    "truncated: {} bytes of vertices expected, {} present",
                    need,
                    body.len()
                ));
            }
            let f = |o: usize| f32::from_le_bytes([body[o], body[o + 1], body[o + 2], body[o + 3]]);
            for v in 0..nv {
                let b = v * stride;
                m.vertices
                    .push(Vec3::new(f(b + 4 * px), f(b + 4 * py), f(b + 4 * pz)));
            }
            let mut o = need;
            for _ in 0..nf {
                let n = *body.get(o).ok_or("truncated faces")? as usize;
                o += 1;
                if body.len() < o + 4 * n || n < 3 {
                    return Err("truncated or degenerate face".into());
                }
                let i = |k: usize| {
                    u32::from_le_bytes([
                        body[o + 4 * k],
                        body[o + 4 * k + 1],
                        body[o + 4 * k + 2],
                        body[o + 4 * k + 3],
                    ])
                };
                for k in 1..n - 1 {
                    m.triangles.push([i(0), i(k), i(k + 1)]);
                }
                o += 4 * n;
            }
        }
        f => {
            return Err(format!(
                "unsupported PLY format '{f}' (ascii and binary_little_endian are)"
            ))
        }
    }
    check_indices(&m)?;
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_and_ply_load_the_same_tetrahedron() {
        let dir = std::env::temp_dir().join(format!("cao-mesh-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let obj = dir.join("t.obj");
        std::fs::write(
            &obj,
            "v 0 0 0\nv 2 0 0\nv 0 2 0\nv 0 0 2\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
        )
        .unwrap();
        let ply = dir.join("t.ply");
        std::fs::write(&ply, "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n2 0 0\n0 2 0\n0 0 2\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n").unwrap();
        let a = TriMesh::load(&obj).unwrap();
        let b = TriMesh::load(&ply).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.half_extent(), Vec3::ONE, "normalised to unit half-extent");
        let bad = dir.join("bad.obj");
        std::fs::write(&bad, "v 0 0 0\nf 1 2 3\n").unwrap();
        let e = TriMesh::load(&bad).unwrap_err().to_string();
        assert!(e.contains("bad.obj") && e.contains("vertex 1"), "{e}");
        // non-finite coordinates: OBJ refuses them as it parses, binary PLY after reading
        let nan = dir.join("nan.obj");
        std::fs::write(&nan, "v 0 0 0\nv NaN 1 0\nv 0 0 1\nf 1 2 3\n").unwrap();
        let e = TriMesh::load(&nan).unwrap_err().to_string();
        assert!(e.contains("nan.obj") && e.contains("line 2"), "{e}");
        let nan = dir.join("nan.ply");
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
            property float y\nproperty float z\nelement face 1\n\
            property list uchar int vertex_indices\nend_header\n"
            .to_vec();
        for x in [0.0, 0.0, 0.0, f32::NAN, 1.0, 0.0, 0.0, 0.0, 1.0] {
            b.extend(f32::to_le_bytes(x));
        }
        b.push(3);
        for i in [0i32, 1, 2] {
            b.extend(i.to_le_bytes());
        }
        std::fs::write(&nan, b).unwrap();
        let e = TriMesh::load(&nan).unwrap_err().to_string();
        assert!(
            e.contains("nan.ply") && e.contains("vertex 1 has a non-finite"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn builtin_shapes_have_unit_extent() {
        for m in [TriMesh::sphere(), TriMesh::cube(), TriMesh::cylinder()] {
            assert!((m.half_extent() - Vec3::ONE).abs().max_element() < 1e-5);
        }
        let t = TriMesh::torus().half_extent();
        assert!((t.x - 1.0 - TORUS_MINOR).abs() < 1e-5 && (t.z - TORUS_MINOR).abs() < 1e-5);
    }
}
