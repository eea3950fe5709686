//! How alike two pictures are: PSNR and SSIM (Wang et al. 2004) on luma, for comparing an AO
//! method's render with a reference render.

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
