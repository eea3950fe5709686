//! Safety margins: whether a tool comes within a structure's margin. A tool is inside the
//! margin m_l of structure l when a voxel centre inside the tool (as the clip shaders test it)
//! has dist_l < m_l ([`MarginField`], exact in mm); sampling the tool at voxel centres puts
//! the distance within half a voxel diagonal of the tool region's.

use super::ClipMap;
use crate::volume::distance::MarginField;
use glam::{Mat4, Vec3};
use rayon::prelude::*;

/// A tool inside a structure's margin.
#[derive(Clone, Debug, PartialEq)]
pub struct MarginHit {
    /// Index of the tool in the scene.
    pub tool: usize,
    /// Index of the structure in the label map.
    pub structure: usize,
    /// The smallest dist_l over the voxel centres inside the tool (0 where it touches l).
    pub distance_mm: f32,
    pub margin_mm: f32,
}

/// The margins tool `tool` (its clip `map`, `local_from_index` taking voxel index coordinates,
/// centres at i + 0.5, into the tool's local frame) is inside, looking at the voxels of
/// `[lo, hi)` (the tool's voxel box) only.
pub fn hits(
    tool: usize,
    map: &ClipMap,
    local_from_index: Mat4,
    (lo, hi): ([usize; 3], [usize; 3]),
    fields: &[MarginField],
) -> Vec<MarginHit> {
    fields
        .iter()
        .filter_map(|f| {
            // the tool's box within the field's (beyond it, dist_l exceeds the margin)
            let a = [0, 1, 2].map(|a| lo[a].max(f.min[a]));
            let b = [0, 1, 2].map(|a| hi[a].min(f.min[a] + f.dims[a]));
            if (0..3).any(|x| a[x] >= b[x]) {
                return None;
            }
            let nearest = (a[2]..b[2])
                .into_par_iter()
                .map(|k| {
                    let mut m = f32::INFINITY;
                    for j in a[1]..b[1] {
                        for i in a[0]..b[0] {
                            let d = f.at([i, j, k]);
                            if d >= m {
                                continue;
                            }
                            let c = Vec3::new(i as f32 + 0.5, j as f32 + 0.5, k as f32 + 0.5);
                            if map.test(local_from_index.transform_point3(c)).0 {
                                m = d;
                            }
                        }
                    }
                    m
                })
                .reduce(|| f32::INFINITY, f32::min);
            (nearest < f.margin_mm).then_some(MarginHit {
                tool,
                structure: f.structure,
                distance_mm: nearest,
                margin_mm: f.margin_mm,
            })
        })
        .collect()
}
