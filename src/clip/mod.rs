//! Clipping tools: meshes, and the clip camera's depth maps with their dilation maps.
//!
//! The clip camera is orthographic, looks along the tool's local +Z and rides on the tool, so its
//! maps depend only on the shape (and, for the dilation, on the radius in tool units). Each texel
//! holds up to two depth intervals of the shape along local Z (two peels: concave shapes such as
//! a torus seen from its side) and one interval of the dilated shape (the 2D Minkowski sum of the
//! depth maps with a sphere, conservatively widened by one texel).
//!
//! [`ClipMapGpu`] builds the maps on the GPU (rasterised depth peels, a compute-shader dilation);
//! [`ClipMap::build`] is the CPU reference it is tested against, sampling the same points with
//! the same crossing rule and dilating with the same kernel.

pub mod bricks;
pub mod gpu;
pub mod margin;
pub mod mesh;

pub use gpu::{ClipGpuError, ClipMapGpu};
pub use mesh::{MeshError, TriMesh};

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A clipping tool's shape, in tool-local metres scaled by `Tool::size` (unit size = 1):
/// sphere of radius 1, cube of half-edge 1, cylinder of radius 1 and half-height 1 along local Z,
/// torus of major radius 1 and minor radius [`TORUS_MINOR`] around local Z, or a loaded mesh.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Shape {
    Sphere,
    Box,
    Cylinder,
    Torus,
    /// Index into the meshes loaded for this session (OBJ/PLY).
    Mesh(usize),
}

pub use crate::shader_constants::TORUS_MINOR;

/// The built-in shapes in the order a "cycle shape" button visits them.
pub const BUILTIN_SHAPES: [Shape; 4] = [Shape::Sphere, Shape::Box, Shape::Cylinder, Shape::Torus];

impl Shape {
    /// The shape's code in `ClipTool.offsets.w` (shaders/include/clip.glsl).
    pub fn code(self) -> u32 {
        use crate::shader_constants::*;
        match self {
            Shape::Sphere => SHAPE_SPHERE,
            Shape::Box => SHAPE_BOX,
            Shape::Cylinder => SHAPE_CYLINDER,
            Shape::Torus => SHAPE_TORUS,
            Shape::Mesh(_) => SHAPE_MESH,
        }
    }

    /// The built-in shape of this name (`sphere`, `box`, `cylinder`, `torus`), as the CLI and
    /// scripted streams spell it.
    pub fn builtin(name: &str) -> Option<Shape> {
        Some(match name {
            "sphere" => Shape::Sphere,
            "box" => Shape::Box,
            "cylinder" => Shape::Cylinder,
            "torus" => Shape::Torus,
            _ => return None,
        })
    }
}

pub use crate::shader_constants::{EMPTY_IN, EMPTY_OUT};
/// Default clip-map resolution (texels per side).
pub const DEFAULT_RESOLUTION: usize = 128;

/// Depth maps of one shape for one dilation radius, in tool-local units.
#[derive(Clone, Debug)]
pub struct ClipMap {
    pub res: usize,
    /// The map covers local x, y in [-extent, extent].
    pub extent: f32,
    /// The dilation radius this map was built for.
    pub radius: f32,
    /// Per texel: (in0, out0, in1, out1), the shape's first two intervals along local Z.
    pub clip: Vec<[f32; 4]>,
    /// Per texel: the dilated shape's interval along local Z, then the contracted shape's (a
    /// probe's region of unchanged AO; see [`dilate`]).
    pub dilated: Vec<[f32; 4]>,
    /// Local Z range of the dilated shape.
    pub z_range: (f32, f32),
}

/// Where in its texel each map samples the shape, in texels from the centre: an irrational
/// sub-texel offset, so that the sample points of meshes with round coordinates (axis-aligned
/// faces, a torus whose outline lies on a texel row) do not fall exactly on their silhouettes,
/// where the CPU's fill rule and the rasteriser's could legitimately disagree. Both builders
/// sample here: the GPU shifts its projection by this much.
pub const SAMPLE_OFFSET: Vec2 = Vec2::new(0.013_725_6, 0.021_194_3);

impl ClipMap {
    pub fn texel(&self) -> f32 {
        2.0 * self.extent / self.res as f32
    }

    /// Texel of local (x, y), if on the map.
    pub fn texel_of(&self, x: f32, y: f32) -> Option<usize> {
        let inv = self.res as f32 / (2.0 * self.extent);
        let (u, v) = ((x + self.extent) * inv, (y + self.extent) * inv);
        if u < 0.0 || v < 0.0 || u >= self.res as f32 || v >= self.res as f32 {
            return None;
        }
        Some(v as usize * self.res + u as usize)
    }

    /// (inside the shape, inside the dilated shape) of a tool-local point, as the shaders test it.
    pub fn test(&self, p: Vec3) -> (bool, bool) {
        let Some(t) = self.texel_of(p.x, p.y) else {
            return (false, false);
        };
        let c = self.clip[t];
        let d = self.dilated[t];
        let inside = (p.z >= c[0] && p.z <= c[1]) || (p.z >= c[2] && p.z <= c[3]);
        (inside, p.z >= d[0] && p.z <= d[1])
    }

    /// Whether a tool-local point is inside the shape contracted by the radius (see [`dilate`]),
    /// as the shaders test it.
    pub fn contracted(&self, p: Vec3) -> bool {
        self.texel_of(p.x, p.y).is_some_and(|t| {
            let d = self.dilated[t];
            p.z >= d[2] && p.z <= d[3]
        })
    }

    /// The map's extent for a mesh of half-extent `half` (x, y), a dilation `radius` and `res`
    /// texels: room for the dilation plus two texels, extent = e0 + r + 4 * extent / res. Shared
    /// by the CPU and GPU builders so both sample the same texel centres.
    pub fn extent_for(half: Vec3, res: usize, radius: f32) -> f32 {
        (half.x.max(half.y) + radius) / (1.0 - 4.0 / res as f32)
    }

    /// Ray-casts the mesh along local Z through every texel's sample point ([`SAMPLE_OFFSET`]; a
    /// scan conversion on the CPU) and builds the dilation for `radius` (tool-local units). This
    /// is the reference for [`ClipMapGpu`], which rasterises the same crossings.
    ///
    /// A sample that falls exactly on a triangle edge or vertex counts for exactly one of two
    /// triangles on either side of it (a fill rule, as a GPU rasteriser has), and for both or
    /// neither of two folding over at a silhouette, so no sample loses or doubles a crossing.
    pub fn build(mesh: &TriMesh, res: usize, radius: f32) -> ClipMap {
        let res = res.max(8);
        let extent = Self::extent_for(mesh.half_extent(), res, radius);
        let texel = 2.0 * extent / res as f32;
        let centre = |i: usize| -extent + (i as f32 + 0.5) * texel;
        let offset = SAMPLE_OFFSET * texel;
        // Scan-convert: every triangle adds its depth to the texels whose sample point it covers.
        let mut hits: Vec<Vec<f32>> = vec![Vec::new(); res * res];
        for tri in &mesh.triangles {
            let [a, b, c] = tri.map(|i| mesh.vertices[i as usize]);
            let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
            let first = |v: f32| (((v + extent) / texel - 0.5).floor().max(0.0)) as usize;
            let last =
                |v: f32| ((((v + extent) / texel - 0.5).ceil()).max(0.0) as usize).min(res - 1);
            let Some(tri) = ScanTriangle::new(a, b, c) else {
                continue; // seen edge-on: adds no crossing
            };
            for j in first(lo.y)..=last(hi.y) {
                for i in first(lo.x)..=last(hi.x) {
                    let p = Vec2::new(centre(i), centre(j)) + offset;
                    if let Some(z) = tri.depth_at(p) {
                        hits[j * res + i].push(z);
                    }
                }
            }
        }
        let clip: Vec<[f32; 4]> = hits
            .into_iter()
            .map(|mut z| {
                z.sort_by(|a, b| a.total_cmp(b));
                intervals(&z)
            })
            .collect();
        let dilated = dilate(&clip, res, texel, radius);
        let z_range = z_range(&dilated);
        ClipMap {
            res,
            extent,
            radius,
            clip,
            dilated,
            z_range,
        }
    }
}

/// A triangle as the CPU scan conversion sees it, along local Z.
struct ScanTriangle {
    v: [Vec3; 3],
    /// Twice its signed area in the XY plane.
    area: f32,
    /// Whether the edge opposite each corner owns the samples exactly on it (see `owns`).
    own: [bool; 3],
}

impl ScanTriangle {
    /// None for a triangle seen edge-on (no area: it adds no crossing).
    fn new(a: Vec3, b: Vec3, c: Vec3) -> Option<ScanTriangle> {
        let area = edge(a, b, c.truncate());
        if area.abs() < 1e-12 {
            return None;
        }
        let s = area.signum();
        Some(ScanTriangle {
            v: [a, b, c],
            area,
            own: [owns(b, c, s), owns(c, a, s), owns(a, b, s)],
        })
    }

    /// The local z where the ray along Z through `p` crosses the triangle, if it does.
    fn depth_at(&self, p: Vec2) -> Option<f32> {
        let [a, b, c] = self.v;
        let e = [edge(b, c, p), edge(c, a, p), edge(a, b, p)];
        let s = self.area.signum();
        let covered = (0..3).all(|k| s * e[k] > 0.0 || (e[k] == 0.0 && self.own[k]));
        covered.then(|| (e[0] * a.z + e[1] * b.z + e[2] * c.z) / self.area)
    }
}

/// Twice the signed area of (u, v, p) in the XY plane: the edge function of the directed edge
/// u -> v at p. Swapping u and v negates it exactly (the same two products, subtracted the other
/// way), so of two triangles on either side of an edge at most one covers a sample next to it,
/// however the products round: the scan conversion is watertight.
fn edge(u: Vec3, v: Vec3, p: Vec2) -> f32 {
    (u.x - p.x) * (v.y - p.y) - (v.x - p.x) * (u.y - p.y)
}

/// The fill rule for samples exactly on the edge u -> v of a triangle whose signed area has sign
/// `s`: the edge owns them if the triangle lies on its +x side (or, for an edge parallel to x, on
/// its +y side), as if the sample sat an infinitesimal step towards (+x, then +y). Of two
/// triangles on either side of an edge exactly one owns it, of two folding over at a silhouette
/// edge both or neither, and around a shared vertex exactly one triangle covers it.
fn owns(u: Vec3, v: Vec3, s: f32) -> bool {
    // The inward normal of the edge: the gradient of s * edge(u, v, p) in p.
    let n = Vec2::new(u.y - v.y, v.x - u.x) * s;
    n.x > 0.0 || (n.x == 0.0 && n.y > 0.0)
}

/// The clip intervals of a texel from its sorted crossings along local Z:
/// - none or one crossing (a grazing ray): empty;
/// - two or three (the odd one grazing): the first interval, the unmatched last crossing dropped;
/// - four or more: the first interval, and everything from the third crossing to the last hulled
///   into the second (a mesh needing more than two peels clips like its hull there, as the paper
///   says; an odd count of five or more keeps its last crossing in that hull).
///
/// The GPU builder applies the same rule to its four front peels and its farthest crossing.
pub fn intervals(z: &[f32]) -> [f32; 4] {
    match z.len() {
        0 | 1 => [EMPTY_IN, EMPTY_OUT, EMPTY_IN, EMPTY_OUT],
        2 | 3 => [z[0], z[1], EMPTY_IN, EMPTY_OUT],
        n => [z[0], z[1], z[2], z[n - 1]],
    }
}

/// Local Z range of the non-empty texels of a dilation map.
pub fn z_range(dilated: &[[f32; 4]]) -> (f32, f32) {
    dilated
        .iter()
        .filter(|d| d[0] <= d[1])
        .fold((f32::MAX, f32::MIN), |(lo, hi), d| {
            (lo.min(d[0]), hi.max(d[1]))
        })
}

/// The sphere of the dilation as a kernel over texel offsets (the half-spherical depth map of the
/// paper's Fig. 7).
///
/// Distances between texels are shortened by one texel diagonal: a texel stands for every point
/// of its square, so the result contains the exact Minkowski sum of the continuous shape. The CPU
/// and GPU dilations share this table, so they do the same float operations.
#[derive(Clone, Debug, PartialEq)]
pub struct DilationKernel {
    /// Offsets up to this many texels (per axis) can reach a texel.
    pub reach: usize,
    /// For |di|, |dj| in 0..=reach at `[dj * (reach + 1) + di]`: the half-height of the sphere
    /// around a surface point that far away, or [`EMPTY_OUT`] beyond the sphere (a value that
    /// moves no hull: EMPTY_IN - h and z + EMPTY_OUT stay EMPTY_IN, -EMPTY_OUT stays below).
    pub heights: Vec<f32>,
    /// For |dj| in 0..=reach: the largest |di| inside the sphere, or -1 if none.
    pub widths: Vec<i32>,
}

impl DilationKernel {
    pub fn new(texel: f32, radius: f32) -> DilationKernel {
        let reach = (radius / texel).ceil() as usize + 2;
        let diag = texel * std::f32::consts::SQRT_2;
        let mut heights = Vec::with_capacity((reach + 1) * (reach + 1));
        let mut widths = vec![-1; reach + 1];
        for (dj, width) in widths.iter_mut().enumerate() {
            for di in 0..=reach {
                let dist = ((di * di + dj * dj) as f32).sqrt() * texel;
                let d = (dist - diag).max(0.0);
                heights.push(if d > radius {
                    EMPTY_OUT
                } else {
                    *width = di as i32;
                    (radius * radius - d * d).sqrt()
                });
            }
        }
        DilationKernel {
            reach,
            heights,
            widths,
        }
    }
}

/// The dilated and the contracted shape, per texel (dilated in, dilated out, contracted in,
/// contracted out). The reference for shaders/clip_dilate.comp.
///
/// Dilated: the hull along Z of the spheres of `radius` centred on the surface points of all
/// texels within reach (see [`DilationKernel`]).
///
/// Contracted (the paper's Sect. 3.4 for probes): the points whose sphere of `radius` lies inside
/// the shape as the clip map tests it. With the same kernel, a point of texel p at depth z is
/// kept if for every texel q of the sphere's disc z - h(q) and z + h(q) lie in q's first
/// interval; an empty texel or one off the map in the disc empties p. Taking only the first
/// interval keeps less than the exact contraction of a two-interval texel: conservative.
/// An empty result is (EMPTY_IN, EMPTY_OUT).
pub fn dilate(clip: &[[f32; 4]], res: usize, texel: f32, radius: f32) -> Vec<[f32; 4]> {
    let kernel = DilationKernel::new(texel, radius);
    let reach = kernel.reach as i64;
    (0..res * res)
        .into_par_iter()
        .map(|t| {
            let (pi, pj) = ((t % res) as i64, (t / res) as i64);
            let (mut lo, mut hi) = (EMPTY_IN, EMPTY_OUT);
            let (mut c_lo, mut c_hi) = (EMPTY_OUT, EMPTY_IN);
            let mut contracted = true;
            for qj in pj - reach..=pj + reach {
                for qi in pi - reach..=pi + reach {
                    let k =
                        (qj - pj).unsigned_abs() * (reach as u64 + 1) + (qi - pi).unsigned_abs();
                    let h = kernel.heights[k as usize];
                    if h < 0.0 {
                        continue;
                    }
                    if qi < 0 || qj < 0 || qi >= res as i64 || qj >= res as i64 {
                        contracted = false;
                        continue;
                    }
                    let c = clip[qj as usize * res + qi as usize];
                    if c[0] > c[1] {
                        contracted = false;
                        continue;
                    }
                    let last_out = if c[2] <= c[3] { c[3] } else { c[1] };
                    lo = lo.min(c[0] - h);
                    hi = hi.max(last_out + h);
                    c_lo = c_lo.max(c[0] + h);
                    c_hi = c_hi.min(c[1] - h);
                }
            }
            if !contracted || c_lo > c_hi {
                (c_lo, c_hi) = (EMPTY_IN, EMPTY_OUT);
            }
            [lo, hi, c_lo, c_hi]
        })
        .collect()
}

/// The mesh of a scene shape (`meshes` holds the loaded OBJ/PLY meshes).
pub fn shape_mesh(shape: Shape, meshes: &[TriMesh]) -> Option<TriMesh> {
    Some(match shape {
        Shape::Sphere => TriMesh::sphere(),
        Shape::Box => TriMesh::cube(),
        Shape::Cylinder => TriMesh::cylinder(),
        Shape::Torus => TriMesh::torus(),
        Shape::Mesh(i) => meshes.get(i)?.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_map_matches_the_sphere() {
        let m = ClipMap::build(&TriMesh::sphere(), 128, 0.3);
        for p in [
            Vec3::ZERO,
            Vec3::new(0.5, -0.3, 0.2),
            Vec3::new(0.0, 0.0, 0.95),
        ] {
            assert!(m.test(p).0, "{p} is inside the sphere");
        }
        for p in [Vec3::new(0.0, 0.0, 1.1), Vec3::new(0.8, 0.8, 0.0)] {
            assert!(!m.test(p).0, "{p} is outside the sphere");
        }
        // The dilation covers the sphere grown by the radius, and not much more.
        assert!(m.test(Vec3::new(0.0, 0.0, 1.25)).1);
        assert!(m.test(Vec3::new(0.0, 1.25, 0.0)).1);
        assert!(!m.test(Vec3::new(0.0, 0.0, 1.45)).1);
        assert!(!m.test(Vec3::new(1.2, 1.2, 0.0)).1);
    }

    #[test]
    fn the_contraction_keeps_only_points_whose_sphere_is_inside() {
        // A probe's unaffected region: every point of the contraction has its whole sphere of
        // the radius inside the shape as the map tests it (what makes a probe exact).
        let mut rng = crate::rng::SplitMix64(7);
        let mut v3 = || Vec3::new(rng.unit() as f32, rng.unit() as f32, rng.unit() as f32);
        for (mesh, r) in [
            (TriMesh::sphere(), 0.3f32),
            (TriMesh::cube(), 0.25),
            (TriMesh::torus(), 0.1),
        ] {
            let m = ClipMap::build(&mesh, 64, r);
            let mut kept = 0;
            for _ in 0..4000 {
                let p = v3() * 2.4 - 1.2;
                if !m.contracted(p) {
                    continue;
                }
                kept += 1;
                for _ in 0..16 {
                    let (d, l) = (v3() * 2.0 - 1.0, v3().x);
                    // Mostly near the sphere's surface, where a miss would show.
                    let q = p + d.normalize_or_zero() * r * (0.5 + 0.5 * l.sqrt());
                    assert!(m.test(q).0, "{p} is contracted but {q} is outside");
                }
            }
            assert!(kept > 0, "a contraction by {r} keeps something");
        }
        // Not more than the shape shrunk by the radius, and empty once the radius is larger.
        let m = ClipMap::build(&TriMesh::sphere(), 64, 0.3);
        assert!(m.contracted(Vec3::ZERO) && m.contracted(Vec3::new(0.0, 0.0, 0.6)));
        assert!(!m.contracted(Vec3::new(0.0, 0.0, 0.75)));
        assert!(!m.contracted(Vec3::new(0.75, 0.0, 0.0)));
        let none = ClipMap::build(&TriMesh::sphere(), 64, 1.1);
        assert!(none.dilated.iter().all(|d| d[2] > d[3]));
    }

    #[test]
    fn torus_keeps_its_hole_and_box_is_square() {
        let t = ClipMap::build(&TriMesh::torus(), 128, 0.1);
        assert!(!t.test(Vec3::ZERO).0, "the hole is not clipped");
        assert!(t.test(Vec3::new(1.0, 0.0, 0.0)).0, "the tube is");
        assert!(t.test(Vec3::new(0.0, -1.0, 0.2)).0);
        assert!(!t.test(Vec3::new(1.0, 0.0, TORUS_MINOR + 0.05)).0);
        let b = ClipMap::build(&TriMesh::cube(), 64, 0.2);
        assert!(b.test(Vec3::new(0.95, -0.95, 0.9)).0);
        assert!(!b.test(Vec3::new(1.05, 0.0, 0.0)).0);
        assert!(b.test(Vec3::new(1.15, 0.0, 0.0)).1);
    }

    /// Crossings of the ray through `p` with `tris` (corner indices into `v`).
    fn crossings(v: &[Vec3], tris: &[[usize; 3]], p: Vec2) -> usize {
        tris.iter()
            .filter_map(|t| ScanTriangle::new(v[t[0]], v[t[1]], v[t[2]]))
            .filter(|t| t.depth_at(p).is_some())
            .count()
    }

    #[test]
    fn samples_on_edges_and_vertices_are_covered_once() {
        // A fan of six triangles around the origin, alternately wound: every point of the
        // hexagon, edges and centre included, is covered exactly once.
        let mut v = vec![Vec3::ZERO];
        for k in 0..6 {
            let a = k as f32 * std::f32::consts::FRAC_PI_3;
            v.push(Vec3::new(a.cos(), a.sin(), 0.0));
        }
        let tris: Vec<[usize; 3]> = (0..6)
            .map(|k| {
                let (b, c) = (1 + k, 1 + (k + 1) % 6);
                if k % 2 == 0 {
                    [0, b, c]
                } else {
                    [0, c, b]
                }
            })
            .collect();
        for p in [
            Vec2::ZERO,
            Vec2::new(0.5, 0.0),
            Vec2::new(-0.25, 0.0),
            v[2].truncate() * 0.5,
            Vec2::new(0.1, 0.05),
        ] {
            assert_eq!(crossings(&v, &tris, p), 1, "{p}");
        }
        // A square split on its diagonal, samples on the diagonal.
        let v = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            .map(|(x, y)| Vec3::new(x, y, 0.0))
            .to_vec();
        for t in [-0.5f32, 0.0, 0.3] {
            assert_eq!(crossings(&v, &[[0, 1, 2], [0, 2, 3]], Vec2::splat(t)), 1);
        }
        // A fold: two triangles on the same side of a shared edge give a sample on it two
        // crossings or none, never one.
        let v = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.5, 1.0, -1.0),
            Vec3::new(0.5, 1.0, 1.0),
        ];
        for p in [
            Vec2::new(0.5, 0.0),
            Vec2::new(0.0, 0.0),
            Vec2::new(0.3, 0.0),
        ] {
            assert_eq!(crossings(&v, &[[0, 1, 2], [1, 0, 3]], p) % 2, 0, "{p}");
        }
    }

    #[test]
    fn crossings_pair_into_intervals() {
        let e = [EMPTY_IN, EMPTY_OUT, EMPTY_IN, EMPTY_OUT];
        assert_eq!(intervals(&[]), e);
        assert_eq!(intervals(&[0.5]), e, "a grazing ray clips nothing");
        assert_eq!(intervals(&[0.0, 1.0]), [0.0, 1.0, EMPTY_IN, EMPTY_OUT]);
        assert_eq!(intervals(&[0.0, 1.0, 2.0]), [0.0, 1.0, EMPTY_IN, EMPTY_OUT]);
        assert_eq!(intervals(&[0.0, 1.0, 2.0, 3.0]), [0.0, 1.0, 2.0, 3.0]);
        assert_eq!(intervals(&[0.0, 1.0, 2.0, 3.0, 4.0]), [0.0, 1.0, 2.0, 4.0]);
        assert_eq!(intervals(&[0., 1., 2., 3., 4., 5.]), [0.0, 1.0, 2.0, 5.0]);
    }

    #[test]
    fn side_view_of_a_torus_needs_two_peels() {
        // A torus turned on its side: rays through the hole region cross the tube twice.
        let mut m = TriMesh::torus();
        for v in &mut m.vertices {
            *v = Vec3::new(v.x, v.z, v.y);
        }
        let map = ClipMap::build(&m, 128, 0.05);
        assert!(map.test(Vec3::new(0.0, 0.0, 1.0)).0 && map.test(Vec3::new(0.0, 0.0, -1.0)).0);
        assert!(
            !map.test(Vec3::ZERO).0,
            "the hole between the two crossings stays"
        );
    }
}
