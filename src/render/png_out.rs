//! PNG output of rendered views.

use super::StereoImage;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
#[error("{path}: {msg}")]
pub struct PngError {
    pub path: String,
    pub msg: String,
}

/// Writes an RGB8 image (rows top-down) as PNG, through a temporary file so that a failed write
/// never leaves a truncated picture behind.
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), PngError> {
    write_png(path, width, height, rgb, png::ColorType::Rgb)
}

/// [`write_rgb`] for RGBA8 with straight (not premultiplied) alpha, as PNG defines it.
pub fn write_rgba(path: &Path, width: u32, height: u32, rgba: &[u8]) -> Result<(), PngError> {
    write_png(path, width, height, rgba, png::ColorType::Rgba)
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    data: &[u8],
    color: png::ColorType,
) -> Result<(), PngError> {
    let err = |msg: String| PngError {
        path: path.display().to_string(),
        msg,
    };
    let tmp = path.with_extension("png.tmp");
    let file = std::fs::File::create(&tmp).map_err(|e| err(e.to_string()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(|e| err(e.to_string()))?;
    w.write_image_data(data).map_err(|e| err(e.to_string()))?;
    w.finish().map_err(|e| err(e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
}

impl StereoImage {
    /// RGB of one eye (alpha dropped: the background is already composited).
    pub fn rgb(&self, eye: usize) -> Vec<u8> {
        self.rgba[eye]
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect()
    }

    /// One eye as RGBA with straight alpha, from the renderer's premultiplied colour over a
    /// black background (what an ALPHA_BLEND runtime composites): rgb / alpha, 0 where alpha
    /// is 0.
    pub fn straight_rgba(&self, eye: usize) -> Vec<u8> {
        self.rgba[eye]
            .chunks_exact(4)
            .flat_map(|p| {
                let a = p[3] as u32;
                let c = |x: u8| match a {
                    0 => 0,
                    _ => ((x as u32 * 255 + a / 2) / a).min(255) as u8,
                };
                [c(p[0]), c(p[1]), c(p[2]), p[3]]
            })
            .collect()
    }

    /// Both eyes over an opaque background `bg` (0..1), from the renderer's premultiplied
    /// colour over black: c + (1 - a) bg per channel, rounded once. Compositing the
    /// [`StereoImage::straight_rgba`] PNG of the same frame over `bg` gives this within 1/255
    /// (the straight colour rounds once more, by at most a/2 of a step).
    pub fn over(&self, bg: [f32; 3]) -> StereoImage {
        let eye = |rgba: &Vec<u8>| -> Vec<u8> {
            rgba.chunks_exact(4)
                .flat_map(|p| {
                    let c = |k: usize| {
                        let v = p[k] as f32 + (255 - p[3]) as f32 * bg[k];
                        v.round().clamp(0.0, 255.0) as u8
                    };
                    [c(0), c(1), c(2), 255]
                })
                .collect()
        };
        StereoImage {
            rgba: [eye(&self.rgba[0]), eye(&self.rgba[1])],
            ..self.clone()
        }
    }

    /// DIR/left.png, DIR/right.png and DIR/stereo.png as RGBA with straight alpha
    /// ([`StereoImage::straight_rgba`]), for a render on a transparent background.
    pub fn write_pngs_rgba(&self, dir: &Path) -> Result<(), PngError> {
        std::fs::create_dir_all(dir).map_err(|e| PngError {
            path: dir.display().to_string(),
            msg: e.to_string(),
        })?;
        let (w, h) = (self.width, self.height);
        let (l, r) = (self.straight_rgba(0), self.straight_rgba(1));
        write_rgba(&dir.join("left.png"), w, h, &l)?;
        write_rgba(&dir.join("right.png"), w, h, &r)?;
        let row = w as usize * 4;
        let both: Vec<u8> = (0..h as usize)
            .flat_map(|y| [&l[y * row..(y + 1) * row], &r[y * row..(y + 1) * row]].concat())
            .collect();
        write_rgba(&dir.join("stereo.png"), w * 2, h, &both)
    }

    /// Left and right side by side.
    pub fn side_by_side_rgb(&self) -> Vec<u8> {
        let w = self.width as usize;
        let (l, r) = (self.rgb(0), self.rgb(1));
        let mut out = Vec::with_capacity(l.len() * 2);
        for y in 0..self.height as usize {
            out.extend_from_slice(&l[y * w * 3..(y + 1) * w * 3]);
            out.extend_from_slice(&r[y * w * 3..(y + 1) * w * 3]);
        }
        out
    }

    /// DIR/left.png, DIR/right.png and DIR/stereo.png (side by side).
    pub fn write_pngs(&self, dir: &Path) -> Result<(), PngError> {
        std::fs::create_dir_all(dir).map_err(|e| PngError {
            path: dir.display().to_string(),
            msg: e.to_string(),
        })?;
        write_rgb(&dir.join("left.png"), self.width, self.height, &self.rgb(0))?;
        write_rgb(
            &dir.join("right.png"),
            self.width,
            self.height,
            &self.rgb(1),
        )?;
        write_rgb(
            &dir.join("stereo.png"),
            self.width * 2,
            self.height,
            &self.side_by_side_rgb(),
        )
    }
}
