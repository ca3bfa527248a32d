//! Adaptive sampling: the samples of a pass spread over the pixels by how
//! much error each pixel still carries.
//!
//! A render that spreads its samples runs its first passes
//! ([`crate::passes::passes`]) evenly, as every render does, up to
//! [`pilot_end`]. Each later pass holds the same number of samples as the
//! even pass would, but gives them to the pixels in proportion to the
//! square root of their relative variance (what a pixel adds to the
//! relMSE, a sample's variance over `mean^2 + 1e-2`), less what each pixel
//! already has: the counts that minimise the image's relMSE for a given
//! total (stop 76 in `docs/benchmarks/quality.md`). Giving each pixel the
//! same error instead (a noise threshold) is, for the mean over pixels, no
//! better than an even spread.
//!
//! The counts are a pure function of the film's f64 sums after the pass
//! before ([`spread`]), which are the same to the bit on any thread count,
//! and a pixel's samples stay a prefix `0..n` of its sequence: so a render
//! is reproducible, and any renderer that holds the same sums gives the
//! same counts. Counts decided from the samples make the estimator
//! slightly biased (a pixel that drew low values early is given fewer
//! later); the unbiasedness and white-furnace tests run without it.

use crate::passes::{PixelSum, passes};

/// The fewest samples every pixel gets before any is spread: fewer say
/// too little of a pixel's spread.
pub const PILOT_SAMPLES: u32 = 8;

/// A pixel gets at most this many times the render's samples a pixel: a
/// pixel whose spread is an outlier (a firefly in its first samples)
/// cannot take a pass to itself.
pub const MAX_SHARE: u32 = 8;

/// Every pixel's weight is at least this share of the mean weight, so that
/// a pixel whose first samples happened to agree (a small light missed by
/// all of them) still gets some.
pub const FLOOR: f64 = 0.1;

/// The sample index at which the render of `spp` samples a pixel starts
/// spreading them: the end of the first pass ([`passes`]) that reaches
/// [`PILOT_SAMPLES`] and an eighth of `spp`. Equal to `spp` (nothing
/// spread) when no later pass is left.
pub fn pilot_end(spp: u32) -> u32 {
    let need = PILOT_SAMPLES.max(spp / 8);
    passes(spp)
        .iter()
        .map(|p| p.end)
        .find(|&e| e >= need)
        .unwrap_or(spp)
}

/// A pixel's relative variance a sample: over its channels, the unbiased
/// variance of its samples over `mean^2 + 1e-2`, the relMSE's denominator
/// ([`crate::metrics::compare`]). Zero below two samples.
fn relative_variance(p: &PixelSum, n: u32) -> f64 {
    let Some(v) = p.variance_of_mean(n) else {
        return 0.0;
    };
    let m = p.mean(n);
    let per_sample = n as f64;
    (0..3)
        .map(|c| v[c] * per_sample / ((m[c] as f64).powi(2) + 1e-2))
        .sum::<f64>()
        / 3.0
}

/// Each pixel's weight: the square root of its relative variance averaged
/// over its 3x3 neighbourhood (the eight samples of a pilot give a noisy
/// variance; neighbours usually carry similar noise), floored at
/// [`FLOOR`] of the mean weight. All ones where no pixel varies.
fn weights(width: usize, height: usize, sums: &[PixelSum], counts: &[u32]) -> Vec<f64> {
    let v: Vec<f64> = sums
        .iter()
        .zip(counts)
        .map(|(p, &n)| relative_variance(p, n))
        .collect();
    let mut w = vec![0.0; v.len()];
    for y in 0..height {
        let ys = y.saturating_sub(1)..(y + 2).min(height);
        for x in 0..width {
            let xs = x.saturating_sub(1)..(x + 2).min(width);
            let (mut s, mut k) = (0.0, 0.0);
            for yy in ys.clone() {
                for xx in xs.clone() {
                    s += v[yy * width + xx];
                    k += 1.0;
                }
            }
            w[y * width + x] = (s / k).sqrt();
        }
    }
    let mean = w.iter().sum::<f64>() / w.len().max(1) as f64;
    if !(mean > 0.0 && mean.is_finite()) {
        return vec![1.0; w.len()];
    }
    for x in &mut w {
        *x = if x.is_finite() {
            x.max(FLOOR * mean)
        } else {
            mean
        };
    }
    w
}

/// The samples each pixel of a `width` by `height` image gets in the next
/// pass, `budget` of them in all, from the film's sums so far (`sums`,
/// row-major, pixel `i` of `counts[i]` samples): pixel `i`'s total is
/// brought towards `lambda * w_i` (water-filling, never taking samples
/// back), its count for the pass is at most `cap - counts[i]`, and the
/// counts add up to `budget` unless every pixel is at its cap. Rounded so
/// that the running total rounds the running total of the exact shares,
/// which keeps the sum exact and every count within one of its share.
pub fn spread(
    width: u32,
    height: u32,
    sums: &[PixelSum],
    counts: &[u32],
    budget: u64,
    cap: u32,
) -> Vec<u32> {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(sums.len(), w * h, "the film is the image's size");
    assert_eq!(counts.len(), w * h, "a count a pixel");
    let weight = weights(w, h, sums, counts);
    let room: Vec<f64> = counts
        .iter()
        .map(|&c| cap.saturating_sub(c) as f64)
        .collect();
    let share = |lambda: f64, i: usize| (lambda * weight[i] - counts[i] as f64).clamp(0.0, room[i]);
    let total = |lambda: f64| (0..w * h).map(|i| share(lambda, i)).sum::<f64>();
    let want = budget as f64;
    let most = room.iter().sum::<f64>();
    let lambda = if most <= want {
        f64::INFINITY
    } else {
        // The total is continuous and non-decreasing in lambda: bracket
        // the budget, then halve the bracket to f64's precision.
        let mut hi = 1.0;
        while total(hi) < want {
            hi *= 2.0;
        }
        let mut lo = 0.0;
        for _ in 0..64 {
            let mid = 0.5 * (lo + hi);
            if total(mid) < want {
                lo = mid
            } else {
                hi = mid
            }
        }
        hi
    };
    let exact: Vec<f64> = (0..w * h)
        .map(|i| {
            if lambda.is_finite() {
                share(lambda, i)
            } else {
                room[i]
            }
        })
        .collect();
    let scale = if lambda.is_finite() {
        want / exact.iter().sum::<f64>()
    } else {
        1.0
    };
    let mut out = Vec::with_capacity(w * h);
    let (mut run, mut given) = (0.0f64, 0u64);
    for (i, x) in exact.iter().enumerate() {
        run += x * scale;
        let upto = ((run + 0.5).floor() as u64).min(budget);
        let n = (upto.saturating_sub(given)).min(room[i] as u64) as u32;
        given += n as u64;
        out.push(n);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::TraceStats;
    use glam::Vec3;

    /// A pixel of `n` samples alternating between `lo` and `hi`.
    fn pixel(n: u32, lo: f32, hi: f32) -> PixelSum {
        let mut p = PixelSum::default();
        let mut st = TraceStats::default();
        for s in 0..n {
            p.add(Vec3::splat(if s % 2 == 0 { lo } else { hi }), &mut st);
        }
        p
    }

    #[test]
    fn the_pilot_is_a_pass_end() {
        for spp in [1, 2, 7, 8, 9, 16, 64, 100, 256, 1024, 4096] {
            let e = pilot_end(spp);
            assert!(e <= spp, "{spp}: {e}");
            assert!(e == spp || e >= PILOT_SAMPLES.max(spp / 8), "{spp}: {e}");
            assert!(passes(spp).iter().any(|p| p.end == e), "{spp}: {e}");
        }
        assert_eq!(pilot_end(64), 8);
        assert_eq!(pilot_end(256), 32);
        assert_eq!(pilot_end(4), 4);
    }

    #[test]
    fn counts_add_up_to_the_budget_and_follow_the_noise() {
        // A 16x8 image: the left half noisy, the right half four times
        // less spread (sixteen times less variance), everything at 8.
        let (w, h) = (16u32, 8u32);
        let sums: Vec<PixelSum> = (0..w * h)
            .map(|i| {
                if i % w < w / 2 {
                    pixel(8, 0.0, 1.0)
                } else {
                    pixel(8, 0.375, 0.625)
                }
            })
            .collect();
        let counts = vec![8; (w * h) as usize];
        let budget = 8 * (w * h) as u64;
        let n = spread(w, h, &sums, &counts, budget, 64);
        assert_eq!(n.iter().map(|&c| c as u64).sum::<u64>(), budget);
        // Away from the seam (whose neighbourhoods mix both), the noisy
        // pixels' weight is four times the quiet ones' (sqrt of 16). Each
        // row's 128 samples bring the totals to lambda times the weight,
        // less the 8 each has: lambda = 22.6 gives the seven noisy columns
        // 15.7 each and the two mixed ones 11.6 and 6.5, which leaves the
        // quiet ones (at 5.9 < 8) none.
        let row = |y: u32| &n[(y * w) as usize..((y + 1) * w) as usize];
        for y in 0..h {
            let r = row(y);
            assert!(r[..6].iter().all(|&c| (15..=17).contains(&c)), "{r:?}");
            assert!(r[10..].iter().all(|&c| c == 0), "{r:?}");
        }
    }

    #[test]
    fn caps_bound_every_pixel_and_the_rest_goes_elsewhere() {
        let (w, h) = (8u32, 8u32);
        let sums: Vec<PixelSum> = (0..w * h)
            .map(|i| {
                if i < 8 {
                    pixel(8, 0.0, 100.0)
                } else {
                    pixel(8, 1.0, 1.1)
                }
            })
            .collect();
        let counts = vec![8; 64];
        let n = spread(w, h, &sums, &counts, 8 * 64, 24);
        assert!(n.iter().all(|&c| c <= 16), "{n:?}");
        assert_eq!(n.iter().map(|&c| c as u64).sum::<u64>(), 8 * 64);
        // With room for less than the budget, every pixel is filled.
        let n = spread(w, h, &sums, &counts, 1 << 20, 24);
        assert!(n.iter().all(|&c| c == 16), "{n:?}");
    }

    #[test]
    fn a_still_image_is_spread_evenly() {
        let sums = vec![pixel(8, 0.5, 0.5); 12];
        let n = spread(4, 3, &sums, &[8; 12], 12 * 8, 64);
        assert_eq!(n, vec![8; 12]);
        // One noisy pixel among still ones: its neighbourhood fills to the
        // cap, and the floor of a tenth of the mean weight shares the rest
        // among the still pixels, rather than nothing.
        let mut sums = vec![pixel(8, 0.5, 0.5); 100];
        sums[0] = pixel(8, 0.0, 1.0);
        let n = spread(10, 10, &sums, &[8; 100], 100 * 8, 64);
        assert_eq!(&n[..2], &[56, 56], "{n:?}");
        assert!(n[99] > 0, "{n:?}");
        assert_eq!(n.iter().map(|&c| c as u64).sum::<u64>(), 800);
    }

    #[test]
    fn the_counts_are_a_pure_function_of_the_sums() {
        let (w, h) = (13u32, 7u32);
        let sums: Vec<PixelSum> = (0..w * h)
            .map(|i| pixel(8 + i % 3, 0.1 * (i % 5) as f32, 1.0 + 0.3 * (i % 7) as f32))
            .collect();
        let counts: Vec<u32> = (0..w * h).map(|i| 8 + i % 3).collect();
        let a = spread(w, h, &sums, &counts, 1000, 80);
        let b = spread(w, h, &sums.clone(), &counts.clone(), 1000, 80);
        assert_eq!(a, b);
        assert_eq!(a.iter().map(|&c| c as u64).sum::<u64>(), 1000);
    }
}
