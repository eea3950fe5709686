//! Clipping tools: meshes, and the clip camera's depth maps with their dilation maps.
//!
//! The clip camera is orthographic, looks along the tool's local +Z and rides on the tool, so its
//! maps depend only on the shape (and, for the dilation, on the radius in tool units). Each texel
//! holds up to two depth intervals of the shape along local Z (two peels: concave shapes such as
//! a torus seen from its side) and one interval of the dilated shape (the 2D Minkowski sum of the
//! depth maps with a sphere, conservatively widened by one texel).

pub mod mesh;

pub use mesh::{MeshError, TriMesh};

use glam::{Vec2, Vec3};
use rayon::prelude::*;

/// Depth of an empty interval: `EMPTY_IN > z > EMPTY_OUT` holds for no z.
pub const EMPTY_IN: f32 = 1e30;
pub const EMPTY_OUT: f32 = -1e30;
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
    /// Per texel: (in, out, -, -), the dilated shape's interval along local Z.
    pub dilated: Vec<[f32; 4]>,
    /// Local Z range of the dilated shape.
    pub z_range: (f32, f32),
}

/// Sub-texel offset of the sample points, irrational so that texel centres never fall exactly on
/// the edges of the (often axis-aligned) meshes.
const JITTER: Vec2 = Vec2::new(0.013_725_6, 0.021_194_3);

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

    /// Ray-casts the mesh along local Z through every texel (a scan conversion on the CPU) and
    /// builds the dilation for `radius` (tool-local units).
    pub fn build(mesh: &TriMesh, res: usize, radius: f32) -> ClipMap {
        let half = mesh.half_extent();
        let res = res.max(8);
        // Room for the dilation plus two texels: extent = e0 + r + 4 * extent / res.
        let extent = (half.x.max(half.y) + radius) / (1.0 - 4.0 / res as f32);
        let texel = 2.0 * extent / res as f32;
        let centre = |i: usize| -extent + (i as f32 + 0.5) * texel;
        // Scan-convert: every triangle adds its depth to the texels whose sample point it covers.
        let mut hits: Vec<Vec<f32>> = vec![Vec::new(); res * res];
        for tri in &mesh.triangles {
            let [a, b, c] = tri.map(|i| mesh.vertices[i as usize]);
            let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
            let first = |v: f32| (((v + extent) / texel - 0.5).floor().max(0.0)) as usize;
            let last =
                |v: f32| ((((v + extent) / texel - 0.5).ceil()).max(0.0) as usize).min(res - 1);
            let area = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
            if area.abs() < 1e-12 {
                continue; // seen edge-on: adds no crossing
            }
            for j in first(lo.y)..=last(hi.y) {
                for i in first(lo.x)..=last(hi.x) {
                    let p = Vec2::new(centre(i), centre(j)) + JITTER * texel;
                    let w0 = ((b.x - p.x) * (c.y - p.y) - (c.x - p.x) * (b.y - p.y)) / area;
                    let w1 = ((c.x - p.x) * (a.y - p.y) - (a.x - p.x) * (c.y - p.y)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 > 0.0 && w1 > 0.0 && w2 > 0.0 {
                        hits[j * res + i].push(w0 * a.z + w1 * b.z + w2 * c.z);
                    }
                }
            }
        }
        let clip: Vec<[f32; 4]> = hits
            .into_iter()
            .map(|mut z| {
                z.sort_by(|a, b| a.total_cmp(b));
                if z.len() % 2 == 1 {
                    z.pop(); // a grazing ray: drop the unmatched crossing
                }
                match z.len() {
                    0 => [EMPTY_IN, EMPTY_OUT, EMPTY_IN, EMPTY_OUT],
                    2 => [z[0], z[1], EMPTY_IN, EMPTY_OUT],
                    // Two or more intervals: keep the first, hull the rest into the second.
                    _ => [z[0], z[1], z[2], z[z.len() - 1]],
                }
            })
            .collect();
        let dilated = dilate(&clip, res, texel, radius);
        let z_range = dilated
            .iter()
            .filter(|d| d[0] <= d[1])
            .fold((f32::MAX, f32::MIN), |(lo, hi), d| {
                (lo.min(d[0]), hi.max(d[1]))
            });
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

/// The dilated shape: for every texel, the hull along Z of the spheres of `radius` centred on
/// the surface points of all texels within reach. Distances between texels are shortened by one
/// texel diagonal, so the result contains the exact Minkowski sum of the continuous shape.
fn dilate(clip: &[[f32; 4]], res: usize, texel: f32, radius: f32) -> Vec<[f32; 4]> {
    let reach = (radius / texel).ceil() as i64 + 2;
    let diag = texel * std::f32::consts::SQRT_2;
    (0..res * res)
        .into_par_iter()
        .map(|t| {
            let (pi, pj) = ((t % res) as i64, (t / res) as i64);
            let (mut lo, mut hi) = (EMPTY_IN, EMPTY_OUT);
            for qj in (pj - reach).max(0)..=(pj + reach).min(res as i64 - 1) {
                for qi in (pi - reach).max(0)..=(pi + reach).min(res as i64 - 1) {
                    let c = clip[qj as usize * res + qi as usize];
                    if c[0] > c[1] {
                        continue;
                    }
                    let dist = (((qi - pi).pow(2) + (qj - pj).pow(2)) as f32).sqrt() * texel;
                    let d = (dist - diag).max(0.0);
                    if d > radius {
                        continue;
                    }
                    let h = (radius * radius - d * d).sqrt();
                    let last_out = if c[2] <= c[3] { c[3] } else { c[1] };
                    lo = lo.min(c[0] - h);
                    hi = hi.max(last_out + h);
                }
            }
            [lo, hi, 0.0, 0.0]
        })
        .collect()
}

/// The mesh of a scene shape (`meshes` holds the loaded OBJ/PLY meshes).
pub fn shape_mesh(shape: crate::scene::Shape, meshes: &[TriMesh]) -> Option<TriMesh> {
    use crate::scene::Shape;
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
    use crate::scene::TORUS_MINOR;

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
