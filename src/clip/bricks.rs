//! The ray caster's clip test per brick. A sample used to test every tool's map (a matrix, two
//! map reads) wherever a tool could reach: 44 % of a carving frame's ray cast. Per brick of
//! the ray caster's empty-space grid (2^RAY_BRICK_SHIFT voxels a side) the host now works out
//! once per frame whether the tools leave all of it standing, one tool hides all of it, or a
//! tool's surface may cross it; only there does a sample test the maps (raycast.frag
//! `hider_at`). Both verdicts are proved on the maps themselves, over the brick grown by half
//! a voxel (far more than the rounding between the host's and the shader's arithmetic), so the
//! image is bit for bit that of a test at every sample.

use super::ClipMap;
use crate::shader_constants::{CLIP_BRICK_CUT, CLIP_BRICK_OPEN, RAY_BRICK_SHIFT};
use glam::{Mat4, Vec3};
use rayon::prelude::*;

/// One clipping tool as the ray caster tests it (shaders/raycast.frag `hiding_tool`).
pub struct BrickTool<'a> {
    pub map: &'a ClipMap,
    /// Voxel index coordinates (centres at i + 0.5) to tool-local units.
    pub local_from_index: Mat4,
    /// A probe hides everything outside its shape; a carving tool what is inside.
    pub probe: bool,
    /// The index box (min inclusive, max exclusive) outside which a carving tool hides nothing.
    pub reach: ([i32; 3], [i32; 3]),
}

/// How much of a region a shape (or a tool) covers.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Cover {
    None,
    All,
    Some,
}

/// Per brick, x fastest: [`CLIP_BRICK_OPEN`] where no tool hides any point, 1 + t where tool t
/// hides every point and no tool before it hides any (t is the first hider of each sample),
/// [`CLIP_BRICK_CUT`] elsewhere. Packed four to a word for the shader.
pub fn classify(dims: [usize; 3], tools: &[BrickTool]) -> Vec<u8> {
    let n = grid(dims);
    let mut out = vec![CLIP_BRICK_OPEN as u8; n[0] * n[1] * n[2]];
    if tools.is_empty() {
        return out;
    }
    out.par_chunks_mut(n[0] * n[1])
        .enumerate()
        .for_each(|(z, slab)| {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    slab[y * n[0] + x] = state([x, y, z], tools);
                }
            }
        });
    out
}

/// The brick grid of a volume of `dims`.
pub fn grid(dims: [usize; 3]) -> [usize; 3] {
    dims.map(|d| d.div_ceil(1 << RAY_BRICK_SHIFT))
}

fn state(b: [usize; 3], tools: &[BrickTool]) -> u8 {
    // The brick grown by half a voxel: the points a sample assigned to it can be at.
    let size = (1usize << RAY_BRICK_SHIFT) as f32;
    let lo = Vec3::from_array(b.map(|v| v as f32 * size - 0.5));
    let hi = lo + Vec3::splat(size + 1.0);
    for (t, tool) in tools.iter().enumerate() {
        match tool_cover(tool, lo, hi) {
            Cover::None => continue,
            Cover::All => return 1 + t as u8,
            Cover::Some => return CLIP_BRICK_CUT as u8,
        }
    }
    CLIP_BRICK_OPEN as u8
}

/// What `tool` hides of the index region [lo, hi].
fn tool_cover(tool: &BrickTool, lo: Vec3, hi: Vec3) -> Cover {
    if tool.probe {
        return match shape_cover(tool, lo, hi) {
            Cover::None => Cover::All,
            Cover::All => Cover::None,
            Cover::Some => Cover::Some,
        };
    }
    let (rmin, rmax) = tool.reach;
    let (rmin, rmax) = (
        Vec3::from_array(rmin.map(|v| v as f32)),
        Vec3::from_array(rmax.map(|v| v as f32)),
    );
    if hi.cmplt(rmin).any() || lo.cmpge(rmax).any() {
        return Cover::None;
    }
    match shape_cover(tool, lo, hi) {
        Cover::All if lo.cmpge(rmin).all() && hi.cmplt(rmax).all() => Cover::All,
        Cover::All => Cover::Some,
        c => c,
    }
}

/// How much of the index region [lo, hi] lies inside the tool's shape as its clip map tells it.
fn shape_cover(tool: &BrickTool, lo: Vec3, hi: Vec3) -> Cover {
    let (mut l, mut h) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for c in 0..8 {
        let p = Vec3::new(
            if c & 1 == 0 { lo.x } else { hi.x },
            if c & 2 == 0 { lo.y } else { hi.y },
            if c & 4 == 0 { lo.z } else { hi.z },
        );
        let q = tool.local_from_index.transform_point3(p);
        l = l.min(q);
        h = h.max(q);
    }
    let map = tool.map;
    let inv = map.res as f32 / (2.0 * map.extent);
    let res = map.res as i64;
    // The texels the region's points fall in, one more on each side.
    let texel = |v: f32| ((v + map.extent) * inv).floor() as i64;
    let (i0, i1) = (texel(l.x) - 1, texel(h.x) + 1);
    let (j0, j1) = (texel(l.y) - 1, texel(h.y) + 1);
    // Points off the map are outside the shape.
    let mut all = i0 >= 0 && j0 >= 0 && i1 < res && j1 < res;
    let mut none = true;
    for j in j0.max(0)..=j1.min(res - 1) {
        for i in i0.max(0)..=i1.min(res - 1) {
            let c = map.clip[(j * res + i) as usize];
            let holds = |a: f32, b: f32| a <= l.z && h.z <= b;
            let misses = |a: f32, b: f32| h.z < a || l.z > b;
            all &= holds(c[0], c[1]) || holds(c[2], c[3]);
            none &= misses(c[0], c[1]) && misses(c[2], c[3]);
            if !all && !none {
                return Cover::Some;
            }
        }
    }
    match (all, none) {
        (true, _) => Cover::All,
        (_, true) => Cover::None,
        _ => Cover::Some,
    }
}

/// How many bricks of `states` are open, hidden whole by a tool, and cut.
pub fn counts(states: &[u8]) -> [usize; 3] {
    let mut c = [0; 3];
    for &s in states {
        c[match s as u32 {
            CLIP_BRICK_OPEN => 0,
            CLIP_BRICK_CUT => 2,
            _ => 1,
        }] += 1;
    }
    c
}

/// `classify`'s bytes, four to a little-endian word, as the shader reads them.
pub fn pack(states: &[u8]) -> Vec<u32> {
    states
        .chunks(4)
        .map(|c| c.iter().rev().fold(0u32, |w, &s| (w << 8) | s as u32))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clip::mesh::TriMesh;
    use crate::rng::SplitMix64;

    /// Every point of each brick, as the per-sample rule tests it, agrees with the brick's state.
    #[test]
    fn every_point_agrees_with_its_brick() {
        let dims = [48, 44, 40];
        let sphere = ClipMap::build(&TriMesh::sphere(), 64, 0.2);
        let cube = ClipMap::build(&TriMesh::cube(), 64, 0.2);
        // A sphere of 13 voxels' radius carving, a turned cube of half-edge 8 carving, a probe.
        let place = |centre: Vec3, size: f32, turn: f32| {
            (Mat4::from_translation(centre)
                * Mat4::from_rotation_z(turn)
                * Mat4::from_rotation_x(0.4 * turn)
                * Mat4::from_scale(Vec3::splat(size)))
            .inverse()
        };
        let reach = |m: Mat4, map: &ClipMap| {
            let e = map.extent;
            let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
            for c in 0..8 {
                let p = Vec3::new(
                    if c & 1 == 0 { -e } else { e },
                    if c & 2 == 0 { -e } else { e },
                    if c & 4 == 0 {
                        map.z_range.0
                    } else {
                        map.z_range.1
                    },
                );
                let q = m.inverse().transform_point3(p);
                lo = lo.min(q);
                hi = hi.max(q);
            }
            (
                lo.to_array().map(|v| v.floor() as i32 - 1),
                hi.to_array().map(|v| v.ceil() as i32 + 1),
            )
        };
        let carve = |map, m| BrickTool {
            map,
            local_from_index: m,
            probe: false,
            reach: reach(m, map),
        };
        let s = place(Vec3::new(20.0, 20.0, 18.0), 13.0, 0.0);
        let c = place(Vec3::new(32.0, 26.0, 24.0), 8.0, 0.7);
        let p = place(Vec3::new(24.0, 22.0, 20.0), 15.0, 0.3);
        let sets: Vec<Vec<BrickTool>> = vec![
            vec![carve(&sphere, s)],
            vec![carve(&sphere, s), carve(&cube, c)],
            vec![BrickTool {
                map: &sphere,
                local_from_index: p,
                probe: true,
                reach: ([0; 3], [48, 44, 40]),
            }],
        ];
        let mut rng = SplitMix64(7);
        for tools in &sets {
            let states = classify(dims, tools);
            let n = grid(dims);
            for (k, &st) in states.iter().enumerate() {
                let b = [k % n[0], (k / n[0]) % n[1], k / (n[0] * n[1])];
                if st as u32 == CLIP_BRICK_CUT {
                    continue;
                }
                for _ in 0..200 {
                    let v = Vec3::from_array(std::array::from_fn(|a| {
                        ((b[a] * 8) as f64 + 8.0 * rng.unit()).min(dims[a] as f64) as f32
                    }));
                    let hider = tools.iter().position(|t| {
                        let inside = t.map.test(t.local_from_index.transform_point3(v)).0;
                        let (r0, r1) = t.reach;
                        let in_reach = (0..3).all(|a| v[a] >= r0[a] as f32 && v[a] < r1[a] as f32);
                        if t.probe {
                            !inside
                        } else {
                            in_reach && inside
                        }
                    });
                    let want = hider.map_or(CLIP_BRICK_OPEN as u8, |t| 1 + t as u8);
                    assert_eq!(st, want, "brick {b:?} point {v}");
                }
            }
            // Not vacuous: some bricks of each kind.
            let seen = counts(&states);
            assert!(seen.iter().all(|&c| c > 0), "{seen:?}");
        }
    }

    #[test]
    fn packs_four_to_a_word() {
        assert_eq!(pack(&[1, 2, 3, 4, 255]), vec![0x0403_0201, 0xff]);
    }
}
