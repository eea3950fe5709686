//! Text over the volume (a ruler's length, the structure menu), readable in the headset.
//!
//! Glyphs are the 8 x 8 bitmap font of the `font8x8` crate. Each printable ASCII character is a
//! flat mesh of its lit pixels (one quad per run of pixels in a row), all of them in one vertex
//! and one index buffer. A line of text is one [`OverlayItem`] per character, turned to face
//! the head and drawn over everything (no depth test; see [`OverlayMesh::Glyph`]), so a number
//! stays readable wherever its ruler is, inside a cut or behind bone.

use super::overlay::{OverlayItem, OverlayMesh};
use crate::space::Pose;
use glam::{Mat4, Vec3};

/// The first and last character with a glyph; anything else is drawn as `FALLBACK`.
pub const FIRST: u8 = b' ';
pub const LAST: u8 = b'~';
const FALLBACK: u8 = b'?';

/// Text height (m) at arm's length: 12 mm is about 1.1 degrees at 0.6 m, some 20 pixels of a
/// current headset's eye buffer.
pub const TEXT_HEIGHT: f32 = 0.012;

/// The glyph index (0 for [`FIRST`]) that draws byte `c`.
pub fn glyph_index(c: u8) -> u8 {
    let c = if (FIRST..=LAST).contains(&c) {
        c
    } else {
        FALLBACK
    };
    c - FIRST
}

/// Every glyph's mesh in one list, in glyph-local units: the character cell [0, 1] x [0, 1] at
/// z = 0 (y up, the baseline of the font's bottom row at 0), facing +Z, with the normal +Z, each
/// quad counter-clockwise seen from +Z. Returns the vertices (position, normal), the indices,
/// and each glyph's `(first index, index count)`.
#[allow(clippy::type_complexity)]
pub fn glyph_meshes() -> (Vec<[f32; 6]>, Vec<u32>, Vec<(u32, u32)>) {
    let (mut vertices, mut indices, mut ranges) = (Vec::new(), Vec::new(), Vec::new());
    for c in FIRST..=LAST {
        let first = indices.len() as u32;
        let rows = font8x8::legacy::BASIC_LEGACY[c as usize];
        for (row, bits) in rows.iter().enumerate() {
            // Runs of lit pixels in this row (bit 0 is the leftmost pixel).
            let mut col = 0;
            while col < 8 {
                if bits >> col & 1 == 0 {
                    col += 1;
                    continue;
                }
                let start = col;
                while col < 8 && bits >> col & 1 == 1 {
                    col += 1;
                }
                let (x0, x1) = (start as f32 / 8.0, col as f32 / 8.0);
                let (y0, y1) = ((7 - row) as f32 / 8.0, (8 - row) as f32 / 8.0);
                let base = vertices.len() as u32;
                for (x, y) in [(x0, y0), (x1, y0), (x1, y1), (x0, y1)] {
                    vertices.push([x, y, 0.0, 0.0, 0.0, 1.0]);
                }
                indices.extend([0, 1, 2, 0, 2, 3].map(|k| base + k));
            }
        }
        ranges.push((first, indices.len() as u32 - first));
    }
    (vertices, indices, ranges)
}

/// The items that write `text` at `anchor` (world), `height` metres tall, in the plane of the
/// head's view and upright in it: centred on the anchor, the anchor at the text's vertical
/// middle. Spaces take their place and draw nothing.
pub fn text_items(
    text: &str,
    anchor: Vec3,
    head: &Pose,
    height: f32,
    color: [f32; 4],
) -> Vec<OverlayItem> {
    let right = head.orientation * Vec3::X;
    let up = head.orientation * Vec3::Y;
    let n = text.len() as f32;
    let start = anchor - right * (0.5 * n * height) - up * (0.5 * height);
    text.bytes()
        .enumerate()
        .filter(|(_, c)| *c != b' ')
        .map(|(k, c)| OverlayItem {
            mesh: OverlayMesh::Glyph(glyph_index(c)),
            model: Mat4::from_scale_rotation_translation(
                Vec3::splat(height),
                head.orientation,
                start + right * (k as f32 * height),
            ),
            color,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;

    #[test]
    fn glyphs_are_the_fonts_lit_pixels() {
        let (v, i, ranges) = glyph_meshes();
        assert_eq!(ranges.len(), (LAST - FIRST + 1) as usize);
        assert_eq!(ranges[0].1, 0, "a space draws nothing");
        // The area of each glyph's quads is its lit pixels' (1/64 each), and every quad lies
        // in the cell.
        for c in FIRST..=LAST {
            let (first, count) = ranges[glyph_index(c) as usize];
            let lit: u32 = font8x8::legacy::BASIC_LEGACY[c as usize]
                .iter()
                .map(|r| r.count_ones())
                .sum();
            let area: f32 = i[first as usize..(first + count) as usize]
                .chunks_exact(3)
                .map(|t| {
                    let p = |k: u32| Vec3::from_slice(&v[k as usize][..3]);
                    0.5 * (p(t[1]) - p(t[0])).cross(p(t[2]) - p(t[0])).z
                })
                .sum();
            assert!(
                (area - lit as f32 / 64.0).abs() < 1e-6,
                "{:?}: area {area}, {lit} pixels",
                c as char
            );
        }
        assert!(v
            .iter()
            .all(|x| (0.0..=1.0).contains(&x[0]) && (0.0..=1.0).contains(&x[1]) && x[5] == 1.0));
        // '1' has its top row's pixels at columns 2 and 3 (font8x8: bit 0 is the left).
        let (first, _) = ranges[glyph_index(b'1') as usize];
        let top: Vec<[f32; 2]> = (0..4)
            .map(|k| {
                [
                    v[(i[first as usize] + k) as usize][0],
                    v[(i[first as usize] + k) as usize][1],
                ]
            })
            .collect();
        assert_eq!(top[0], [0.25, 0.875]);
        assert_eq!(top[2], [0.5, 1.0]);
        assert_eq!(glyph_index(0xc3), glyph_index(b'?'));
    }

    #[test]
    fn text_faces_the_head_left_to_right_centred_on_its_anchor() {
        let head = Pose {
            position: Vec3::new(0.0, 1.6, 0.0),
            orientation: Quat::from_rotation_y(0.6),
        };
        let anchor = Vec3::new(0.2, 1.3, -0.5);
        let items = text_items("12 mm", anchor, &head, 0.01, [1.0; 4]);
        assert_eq!(items.len(), 4, "the space draws nothing");
        let right = head.orientation * Vec3::X;
        let origins: Vec<Vec3> = items.iter().map(|it| it.model.w_axis.truncate()).collect();
        for w in origins.windows(2) {
            assert!((w[1] - w[0]).dot(right) > 0.0099, "left to right");
        }
        // The cells span 5 characters centred on the anchor.
        let left = origins[0] + head.orientation * Vec3::new(0.0, 0.005, 0.0);
        assert!((left + right * 0.025 - anchor).length() < 1e-6);
        // Glyph-local +Z (the quads' front) points back towards the head.
        let z = items[0].model.transform_vector3(Vec3::Z).normalize();
        assert!((z - head.orientation * Vec3::Z).length() < 1e-6);
        assert!(matches!(items[2].mesh, OverlayMesh::Glyph(g) if g == b'm' - FIRST));
    }
}
