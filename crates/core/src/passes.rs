//! Progressive passes and the one pixel mean of one machine and the farm.
//!
//! A pixel's samples are split into passes that double in size, the same
//! for every renderer of a job: a farm hands out every tile of a pass
//! before the next pass, so a preview sharpens over the whole image
//! instead of filling tile by tile. Within a pass, samples are summed in
//! index order; the passes' sums are then added in pass order. Floating
//! point addition is not associative, so this order is part of the image:
//! one machine sums the same way ([`crate::render::render_pixel`]), and the
//! farm's film adds each pass's sums in pass order however they arrive,
//! which keeps the two bit-identical by construction.

use crate::stats::TraceStats;
use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// The most passes a render is split into: each pass is another message
/// per tile, and past this the first passes are too small to show.
pub const MAX_PASSES: u32 = 8;

/// The passes of a render of `spp` samples per pixel: consecutive sample
/// ranges, each (but the first) about as large as all before it, at most
/// [`MAX_PASSES`] of them, covering `0..spp`.
pub fn passes(spp: u32) -> Vec<Range<u32>> {
    let spp = spp.max(1);
    let n = (32 - spp.leading_zeros()).min(MAX_PASSES);
    let mut v = Vec::with_capacity(n as usize);
    let mut start = 0;
    for i in 0..n {
        // The end of pass i is spp / 2^(n-1-i), rounded up: the last ends
        // at spp, and each earlier one at half the next.
        let shift = n - 1 - i;
        let end = ((spp as u64 + (1u64 << shift) - 1) >> shift) as u32;
        if end > start {
            v.push(start..end);
            start = end;
        }
    }
    v
}

/// What a pixel's samples add up to: per channel, their sum and the sum of
/// their squares (f64), the first for the pixel's value, the second for the
/// error it carries ([`crate::metrics::estimate_error`]). This is what a
/// tile's pass sends and the scheduler's film and store keep.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Moments {
    pub sum: [f64; 3],
    pub squares: [f64; 3],
}

/// A pixel's samples summed in sample-index order (f64), with non-finite
/// values dropped and counted.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelSum {
    sum: DVec3,
    squares: DVec3,
}

impl PixelSum {
    #[inline]
    pub fn add(&mut self, l: Vec3, st: &mut TraceStats) {
        st.samples += 1;
        if l.is_finite() {
            let l = l.as_dvec3();
            self.sum += l;
            self.squares += l * l;
        } else {
            st.invalid_samples += 1;
        }
    }

    /// Adds the sums of the pixel's next pass.
    #[inline]
    pub fn add_pass(&mut self, pass: Moments) {
        self.sum += DVec3::from_array(pass.sum);
        self.squares += DVec3::from_array(pass.squares);
    }

    /// The sums, to send or keep.
    pub fn total(&self) -> Moments {
        Moments {
            sum: self.sum.to_array(),
            squares: self.squares.to_array(),
        }
    }

    /// Sums kept earlier.
    pub fn from_total(total: Moments) -> Self {
        Self {
            sum: DVec3::from_array(total.sum),
            squares: DVec3::from_array(total.squares),
        }
    }

    /// The mean over `samples` samples.
    pub fn mean(&self, samples: u32) -> [f32; 3] {
        let m = self.sum / samples.max(1) as f64;
        [m.x as f32, m.y as f32, m.z as f32]
    }

    /// Per channel, the variance of the mean over `samples` samples as
    /// their spread gives it: the unbiased sample variance over `samples`
    /// (a non-finite sample counts as zero, as in the mean). None for
    /// fewer than two samples.
    pub fn variance_of_mean(&self, samples: u32) -> Option<[f64; 3]> {
        if samples < 2 {
            return None;
        }
        let n = samples as f64;
        let v = ((self.squares - self.sum * self.sum / n) / (n - 1.0)).max(DVec3::ZERO) / n;
        Some(v.to_array())
    }

    /// [`Self::variance_of_mean`] as an image holds it (f32).
    pub fn variance_of_mean_f32(&self, samples: u32) -> Option<[f32; 3]> {
        self.variance_of_mean(samples).map(|v| v.map(|c| c as f32))
    }
}

/// One pixel's samples `sample(s)`, evaluated here in the passes of
/// [`passes`] and summed: the one definition both renderers reproduce. Its
/// mean is the pixel's value; its squares, the error the value carries.
/// Never inlined, so that profiles (`bench/forward_cost.py`) can count a
/// render's work by it; a call per pixel costs nothing next to its samples.
#[inline(never)]
pub fn pixel_mean(
    spp: u32,
    st: &mut TraceStats,
    mut sample: impl FnMut(u32, &mut TraceStats) -> Vec3,
) -> PixelSum {
    let mut total = PixelSum::default();
    for pass in passes(spp) {
        total.add_pass(pass_sum(pass, st, &mut sample));
    }
    total
}

/// One pass of a pixel's samples `sample(s)`, summed in index order: what
/// [`pixel_mean`] adds pass by pass, and what a render that stops at a
/// noise target renders one pass of the whole image at a time with.
#[inline]
pub fn pass_sum(
    pass: Range<u32>,
    st: &mut TraceStats,
    mut sample: impl FnMut(u32, &mut TraceStats) -> Vec3,
) -> Moments {
    let mut p = PixelSum::default();
    for s in pass {
        let l = sample(s, st);
        p.add(l, st);
    }
    p.total()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passes_cover_every_sample_once_and_double() {
        for spp in (1..=300).chain([1000, 1024, 4095, 65536, crate::limits::MAX_SPP]) {
            let p = passes(spp);
            assert!(
                !p.is_empty() && p.len() <= MAX_PASSES as usize,
                "spp {spp}: {p:?}"
            );
            assert_eq!(p[0].start, 0);
            assert_eq!(p.last().unwrap().end, spp);
            for w in p.windows(2) {
                assert_eq!(w[0].end, w[1].start, "spp {spp}: {p:?}");
                // Each pass holds about as many samples as all before it.
                let (before, this) = (w[1].start, w[1].end - w[1].start);
                assert!(this + 1 >= before && this <= before + 1, "spp {spp}: {p:?}");
            }
        }
        assert_eq!(passes(1), vec![0..1]);
        assert_eq!(passes(16), vec![0..1, 1..2, 2..4, 4..8, 8..16]);
        assert_eq!(
            passes(1024),
            vec![
                0..8,
                8..16,
                16..32,
                32..64,
                64..128,
                128..256,
                256..512,
                512..1024
            ]
        );
    }

    #[test]
    fn the_pass_order_is_part_of_the_sum() {
        // Summed straight through, these samples give another f64 than in
        // passes: the reason both renderers share `pixel_mean`'s order.
        // 2^53 + 1 rounds back to 2^53 in f64.
        let big = 2f32.powi(53);
        let xs = [big, 1.0, 1.0, -big];
        let mut st = TraceStats::default();
        let mut straight = PixelSum::default();
        for &x in &xs {
            straight.add(Vec3::splat(x), &mut st);
        }
        let passed = pixel_mean(4, &mut st, |s, _| Vec3::splat(xs[s as usize])).mean(4);
        assert_eq!((straight.mean(4), passed), ([0.0; 3], [0.25; 3]));
        // And a film that adds the same passes' sums in order agrees.
        let mut film = PixelSum::default();
        for pass in passes(4) {
            let mut p = PixelSum::default();
            for s in pass {
                p.add(Vec3::splat(xs[s as usize]), &mut st);
            }
            film.add_pass(p.total());
        }
        assert_eq!(film.mean(4), passed);
    }

    #[test]
    fn non_finite_samples_count_as_zero() {
        let mut st = TraceStats::default();
        let m = pixel_mean(
            4,
            &mut st,
            |s, _| if s == 2 { Vec3::NAN } else { Vec3::ONE },
        );
        assert_eq!(m.mean(4), [0.75; 3]);
        assert_eq!((st.samples, st.invalid_samples), (4, 1));
        // The variance counts it as zero too: samples 1, 1, 0, 1.
        let v = m.variance_of_mean(4).unwrap();
        assert!((v[0] - 0.25 / 4.0).abs() < 1e-15, "{v:?}");
    }

    /// The variance of the mean from the sums and squares, as a two-pass
    /// computation over the samples gives it, whether the samples came in
    /// one pass or were summed in passes and added up (as the film does);
    /// and none from a single sample.
    #[test]
    fn variance_of_the_mean_from_the_sums() {
        let xs: Vec<f32> = (0..37)
            .map(|i| ((i * 7919) % 101) as f32 * 0.37 + 2.0)
            .collect();
        let n = xs.len() as f64;
        let mean = xs.iter().map(|&x| x as f64).sum::<f64>() / n;
        let var = xs.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / (n - 1.0);
        let mut st = TraceStats::default();
        let sums = pixel_mean(37, &mut st, |s, _| Vec3::new(xs[s as usize], 0.0, 1.0));
        let v = sums.variance_of_mean(37).unwrap();
        assert!(
            (v[0] / (var / n) - 1.0).abs() < 1e-9,
            "{} against {}",
            v[0],
            var / n
        );
        assert_eq!((v[1], v[2]), (0.0, 0.0));
        let mut kept = PixelSum::default();
        for pass in passes(37) {
            let mut p = PixelSum::default();
            for s in pass {
                p.add(Vec3::splat(xs[s as usize]), &mut st);
            }
            kept = PixelSum::from_total(kept.total());
            kept.add_pass(p.total());
        }
        assert_eq!(kept.variance_of_mean(37).unwrap()[0], v[0]);
        assert_eq!(sums.variance_of_mean(1), None);
    }
}
