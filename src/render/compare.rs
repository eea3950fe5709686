//! How alike two pictures are: PSNR and SSIM (Wang et al. 2004) on luma, for comparing an AO
//! method's render with a reference render, and `cao-xr compare` on two PNG files.

use std::path::Path;

/// A PNG file as 8-bit RGBA.
pub struct Picture {
    pub width: usize,
    pub height: usize,
    pub rgba: Vec<u8>,
}

/// Reads any 8- or 16-bit PNG (grey, grey + alpha, RGB, RGBA, palette) as 8-bit RGBA; the
/// error names the file.
pub fn read_png(path: &Path) -> Result<Picture, String> {
    let fail = |e: &dyn std::fmt::Display| format!("{}: {e}", path.display());
    let file = std::fs::File::open(path).map_err(|e| fail(&e))?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(file));
    dec.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = dec.read_info().map_err(|e| fail(&e))?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| fail(&"the picture is too large"))?;
    let mut buf = vec![0; size];
    let info = reader.next_frame(&mut buf).map_err(|e| fail(&e))?;
    let px = &buf[..info.buffer_size()];
    let rgba: Vec<u8> = match info.color_type {
        png::ColorType::Rgba => px.to_vec(),
        png::ColorType::Rgb => px
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect(),
        png::ColorType::Grayscale => px.iter().flat_map(|&g| [g, g, g, 255]).collect(),
        png::ColorType::GrayscaleAlpha => px
            .chunks_exact(2)
            .flat_map(|p| [p[0], p[0], p[0], p[1]])
            .collect(),
        png::ColorType::Indexed => return Err(fail(&"a palette the decoder did not expand")),
    };
    Ok(Picture {
        width: info.width as usize,
        height: info.height as usize,
        rgba,
    })
}

/// How far picture `b` is from `a`.
#[derive(Clone, Copy, Debug)]
pub struct Comparison {
    pub psnr: f64,
    pub ssim: f64,
    /// The largest difference of luma, 0..255.
    pub max_diff: f64,
}

/// PSNR and SSIM of two equally sized pictures, and their difference image (luma difference
/// times [`DIFF_GAIN`], grey, so small errors show).
pub fn compare(a: &Picture, b: &Picture) -> Result<(Comparison, Vec<u8>), String> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(format!(
            "the pictures differ in size: {}x{} and {}x{}",
            a.width, a.height, b.width, b.height
        ));
    }
    let (la, lb) = (luma(&a.rgba), luma(&b.rgba));
    let diff: Vec<u8> = la
        .iter()
        .zip(&lb)
        .flat_map(|(x, y)| {
            let d = ((x - y).abs() * DIFF_GAIN).min(255.0) as u8;
            [d, d, d]
        })
        .collect();
    let max_diff = la
        .iter()
        .zip(&lb)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    Ok((
        Comparison {
            psnr: psnr(&la, &lb),
            ssim: ssim(&la, &lb, a.width, a.height),
            max_diff,
        },
        diff,
    ))
}

/// The difference image's gain: a luma error of 32 shows white.
pub const DIFF_GAIN: f64 = 8.0;

/// Rec. 601 luma of 8-bit RGBA pixels, 0..255.
pub fn luma(rgba: &[u8]) -> Vec<f64> {
    rgba.chunks_exact(4)
        .map(|p| 0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64)
        .collect()
}

/// Peak signal-to-noise ratio in dB (peak 255); infinite for equal pictures.
pub fn psnr(a: &[f64], b: &[f64]) -> f64 {
    let mse = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len().max(1) as f64;
    10.0 * (255.0f64 * 255.0 / mse).log10()
}

/// Mean SSIM over every 7 x 7 window (uniform weights, as scikit-image's default), with
/// C1 = (0.01 * 255)^2 and C2 = (0.03 * 255)^2; 1 for equal pictures.
pub fn ssim(a: &[f64], b: &[f64], width: usize, height: usize) -> f64 {
    const R: usize = 3;
    let (c1, c2) = ((0.01f64 * 255.0).powi(2), (0.03f64 * 255.0).powi(2));
    let n = ((2 * R + 1) * (2 * R + 1)) as f64;
    let mut total = 0.0;
    let mut count = 0usize;
    for y in R..height.saturating_sub(R) {
        for x in R..width.saturating_sub(R) {
            let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for j in y - R..=y + R {
                for i in x - R..=x + R {
                    let (p, q) = (a[j * width + i], b[j * width + i]);
                    sa += p;
                    sb += q;
                    saa += p * p;
                    sbb += q * q;
                    sab += p * q;
                }
            }
            let (ma, mb) = (sa / n, sb / n);
            // Sample (co)variances, as the reference implementation uses.
            let k = n / (n - 1.0);
            let (va, vb) = (k * (saa / n - ma * ma), k * (sbb / n - mb * mb));
            let cov = k * (sab / n - ma * mb);
            total += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                / ((ma * ma + mb * mb + c1) * (va + vb + c2));
            count += 1;
        }
    }
    if count == 0 {
        1.0
    } else {
        total / count as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equal_pictures_are_perfect_and_noise_lowers_both_measures() {
        let (w, h) = (20, 16);
        let a: Vec<f64> = (0..w * h).map(|i| ((i * 37) % 200) as f64).collect();
        assert_eq!(psnr(&a, &a), f64::INFINITY);
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-12);
        let b: Vec<f64> = a
            .iter()
            .enumerate()
            .map(|(i, x)| x + if i % 3 == 0 { 20.0 } else { 0.0 })
            .collect();
        // 107 of the 320 pixels off by 20: MSE = 400 * 107 / 320.
        let mse = 400.0 * 107.0 / 320.0;
        assert!((psnr(&a, &b) - 10.0 * (255.0f64.powi(2) / mse).log10()).abs() < 1e-9);
        let s = ssim(&a, &b, w, h);
        assert!(s < 1.0 && s > 0.5, "{s}");
        let flat = vec![128.0; w * h];
        assert!(ssim(&a, &flat, w, h) < s);
        assert_eq!(luma(&[255, 255, 255, 255, 0, 0, 0, 255]), vec![255.0, 0.0]);
    }
}
