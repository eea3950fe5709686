//! A tileable blue-noise threshold map (Ulichney's void-and-cluster), for the ray caster's
//! per-pixel start offset: jitter without the low-frequency blotches of a hash, so the residual
//! noise of the step is fine-grained and the eye averages it away. Deterministic by seed, and the
//! same for every frame (stereo must not shimmer).

use crate::rng::SplitMix64;
use std::sync::OnceLock;

/// Side of the tile in pixels.
pub const SIZE: usize = 64;
/// Gaussian of the energy filter (Ulichney's 1.5).
const SIGMA: f64 = 1.5;
/// Pixel offset of the right eye's tile, so the two eyes' patterns are decorrelated.
pub const RIGHT_EYE_OFFSET: [u32; 2] = [SIZE as u32 / 2, SIZE as u32 / 3];

/// The tile: `SIZE * SIZE` values (rows top-down), each rank r stored as (r + 0.5) / n, a
/// permutation of the evenly spaced values in (0, 1).
pub fn tile() -> &'static [f32] {
    static TILE: OnceLock<Vec<f32>> = OnceLock::new();
    TILE.get_or_init(|| void_and_cluster(SIZE, 0xB10E_5EED))
}

/// Toroidal Gaussian energy kernel, indexed by (dy * n + dx) with wrap-around.
fn kernel(n: usize) -> Vec<f64> {
    let mut k = vec![0.0; n * n];
    for dy in 0..n {
        for dx in 0..n {
            let wx = dx.min(n - dx) as f64;
            let wy = dy.min(n - dy) as f64;
            k[dy * n + dx] = (-(wx * wx + wy * wy) / (2.0 * SIGMA * SIGMA)).exp();
        }
    }
    k
}

/// Energy of every pixel from the set pixels of one colour, kept up to date incrementally.
struct Energy<'a> {
    n: usize,
    kernel: &'a [f64],
    e: Vec<f64>,
}

impl Energy<'_> {
    fn add(&mut self, p: usize, sign: f64) {
        let n = self.n;
        let (px, py) = (p % n, p / n);
        for y in 0..n {
            let dy = (y + n - py) % n;
            for x in 0..n {
                let dx = (x + n - px) % n;
                self.e[y * n + x] += sign * self.kernel[dy * n + dx];
            }
        }
    }

    /// The pixel of `pattern == want` with the highest (`max`) or lowest energy; the first in
    /// raster order on ties, so the result is deterministic.
    fn extreme(&self, pattern: &[bool], want: bool, max: bool) -> usize {
        let mut best = usize::MAX;
        for (i, &on) in pattern.iter().enumerate() {
            if on != want {
                continue;
            }
            if best == usize::MAX
                || (max && self.e[i] > self.e[best])
                || (!max && self.e[i] < self.e[best])
            {
                best = i;
            }
        }
        best
    }
}

fn void_and_cluster(n: usize, seed: u64) -> Vec<f32> {
    let total = n * n;
    let kernel = kernel(n);
    let energy_of = |pattern: &[bool]| {
        let mut en = Energy {
            n,
            kernel: &kernel,
            e: vec![0.0; total],
        };
        for (i, &on) in pattern.iter().enumerate() {
            if on {
                en.add(i, 1.0);
            }
        }
        en
    };
    // The initial binary pattern: a tenth of the pixels at random, then relaxed by moving the
    // tightest cluster's pixel into the largest void until that changes nothing.
    let mut rng = SplitMix64(seed);
    let mut initial = vec![false; total];
    let ones = total / 10;
    let mut placed = 0;
    while placed < ones {
        let i = (rng.next_u64() % total as u64) as usize;
        if !initial[i] {
            initial[i] = true;
            placed += 1;
        }
    }
    let mut en = energy_of(&initial);
    // It converges in a few hundred moves; the bound only guards against a cycle.
    for _ in 0..total {
        let cluster = en.extreme(&initial, true, true);
        initial[cluster] = false;
        en.add(cluster, -1.0);
        let void = en.extreme(&initial, false, false);
        initial[void] = true;
        en.add(void, 1.0);
        if void == cluster {
            break;
        }
    }
    let mut rank = vec![0usize; total];
    // Phase 1: the initial pattern's pixels, ranked downwards by removing the tightest cluster.
    let mut pattern = initial.clone();
    let mut en1 = energy_of(&pattern);
    for r in (0..ones).rev() {
        let c = en1.extreme(&pattern, true, true);
        pattern[c] = false;
        en1.add(c, -1.0);
        rank[c] = r;
    }
    // Phases 2 and 3: the rest, ranked upwards by filling the largest void.
    let mut pattern = initial;
    for r in ones..total {
        let v = en.extreme(&pattern, false, false);
        pattern[v] = true;
        en.add(v, 1.0);
        rank[v] = r;
    }
    rank.iter()
        .map(|&r| ((r as f64 + 0.5) / total as f64) as f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tile_is_a_permutation_of_evenly_spaced_thresholds() {
        let t = tile();
        assert_eq!(t.len(), SIZE * SIZE);
        let mut ranks: Vec<usize> = t
            .iter()
            .map(|&v| (v as f64 * t.len() as f64 - 0.5).round() as usize)
            .collect();
        ranks.sort_unstable();
        assert!(ranks.iter().enumerate().all(|(i, &r)| i == r));
    }

    /// Blue noise has little energy at low frequencies: the means of its 8x8 blocks stay much
    /// closer to 1/2 than white noise's do.
    #[test]
    fn low_frequencies_are_suppressed_against_white_noise() {
        const B: usize = 8;
        let block_spread = |v: &[f32]| {
            let mut s = 0.0;
            for by in 0..SIZE / B {
                for bx in 0..SIZE / B {
                    let mut m = 0.0;
                    for y in 0..B {
                        for x in 0..B {
                            m += v[(by * B + y) * SIZE + bx * B + x] as f64 / (B * B) as f64;
                        }
                    }
                    s += (m - 0.5).powi(2);
                }
            }
            (s / ((SIZE / B) * (SIZE / B)) as f64).sqrt()
        };
        let mut rng = SplitMix64(7);
        let white: Vec<f32> = (0..SIZE * SIZE).map(|_| rng.unit() as f32).collect();
        let (blue, white) = (block_spread(tile()), block_spread(&white));
        assert!(blue < 0.4 * white, "blue {blue} white {white}");
    }
}
