//! Image error metrics: the one implementation behind `locus diff` and
//! `locus render --reference`, and the error every report estimates from
//! the image's own samples ([`ErrorEstimate`]).

use crate::image_io::{Image, ImageError};
use crate::passes::PixelSum;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ErrorMetrics {
    /// Root mean squared error over all channels.
    pub rmse: f64,
    /// Mean over channels of (a - b)^2 / (b^2 + 1e-2), pbrt's relMSE, with
    /// `b` the reference; the epsilon keeps black pixels from dominating.
    pub rel_mse: f64,
    /// Mean absolute error over all channels.
    pub mae: f64,
    /// Perceptual: mean SSIM (Wang et al. 2004) of tone-mapped luminance,
    /// see [`ssim`]; 1 for identical images, lower is worse.
    pub ssim: f64,
    /// Channels counted (3 per pixel).
    pub count: usize,
}

/// The error an image carries, read from its own samples where no
/// reference is at hand: each pixel mean's variance, the spread of its
/// samples over their number ([`PixelSum::variance_of_mean`]), in place of
/// its squared difference from a reference. `rel_mse` is [`compare`]'s with
/// the image's own values in the denominator. The samples' spread is the
/// error of independent samples; the Sobol sampler's samples of a pixel are
/// stratified and usually leave less (`locus bench quality` prints both).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorEstimate {
    pub rmse: f64,
    pub rel_mse: f64,
    /// Samples per pixel it was read from.
    pub samples: u32,
}

/// The sums behind an [`ErrorEstimate`], pixel by pixel. One machine (from
/// its image and variance image) and the farm's film (from its pixel sums)
/// add the same pixels' f32 means and variances in the same row-major
/// order, so their estimates agree to the bit.
#[derive(Clone, Copy, Debug, Default)]
pub struct ErrorSum {
    se: f64,
    rel: f64,
    channels: usize,
}

impl ErrorSum {
    /// Adds a pixel of mean `m` whose mean has the variance `v`.
    #[inline]
    pub fn add(&mut self, m: [f32; 3], v: [f32; 3]) {
        for c in 0..3 {
            let v = v[c] as f64;
            self.se += v;
            self.rel += v / ((m[c] as f64).powi(2) + 1e-2);
        }
        self.channels += 3;
    }

    /// The estimate of the pixels added, each of `samples` samples.
    pub fn finish(&self, samples: u32) -> ErrorEstimate {
        let n = self.channels.max(1) as f64;
        ErrorEstimate {
            rmse: (self.se / n).sqrt(),
            rel_mse: self.rel / n,
            samples,
        }
    }
}

/// [`ErrorEstimate`] of `image`, whose pixel means have the variances
/// `variance`, each from `samples` samples.
pub fn estimate_error(image: &Image, variance: &Image, samples: u32) -> ErrorEstimate {
    let mut e = ErrorSum::default();
    for (m, v) in image.pixels.iter().zip(&variance.pixels) {
        e.add(*m, *v);
    }
    e.finish(samples)
}

/// [`ErrorEstimate`] of pixels kept as their sums (row-major), each of
/// `samples` samples; None for fewer than two samples a pixel, whose
/// spread says nothing.
pub fn estimate_error_of_sums<'a>(
    sums: impl IntoIterator<Item = &'a PixelSum>,
    samples: u32,
) -> Option<ErrorEstimate> {
    estimate_error_of_counted(sums.into_iter().map(|p| (p, samples)), samples)
}

/// [`estimate_error_of_sums`] of pixels that each have their own number of
/// samples, as an adaptive render's do ([`crate::spread`]); `label` is the
/// samples a pixel the estimate reports. None if any pixel has fewer than
/// two.
pub fn estimate_error_of_counted<'a>(
    pixels: impl IntoIterator<Item = (&'a PixelSum, u32)>,
    label: u32,
) -> Option<ErrorEstimate> {
    let mut e = ErrorSum::default();
    for (p, n) in pixels {
        e.add(p.mean(n), p.variance_of_mean_f32(n)?);
    }
    Some(e.finish(label))
}

/// Whether a render with a noise target may stop after a pass: the
/// estimate of its pixels' sums so far (row-major, each of `samples`
/// samples) is at or below `target` (a relMSE). Never below two samples a
/// pixel, whose spread says nothing. One machine and the farm's film ask it
/// of the same sums at the same pass ends, so they stop at the same pass.
pub fn meets_target<'a>(
    sums: impl IntoIterator<Item = &'a PixelSum>,
    samples: u32,
    target: f64,
) -> bool {
    meets_target_counted(sums.into_iter().map(|p| (p, samples)), samples, target)
}

/// [`meets_target`] of pixels that each have their own number of samples
/// (an adaptive render's, [`estimate_error_of_counted`]).
pub fn meets_target_counted<'a>(
    pixels: impl IntoIterator<Item = (&'a PixelSum, u32)>,
    label: u32,
    target: f64,
) -> bool {
    estimate_error_of_counted(pixels, label).is_some_and(|e| e.rel_mse <= target)
}

/// Error of `image` against `reference`.
pub fn compare(image: &Image, reference: &Image) -> Result<ErrorMetrics, ImageError> {
    if (image.width, image.height) != (reference.width, reference.height) {
        return Err(ImageError::SizeMismatch {
            a: (image.width, image.height),
            b: (reference.width, reference.height),
        });
    }
    let (mut se, mut rel, mut ae) = (0f64, 0f64, 0f64);
    for (a, b) in image.pixels.iter().zip(&reference.pixels) {
        for c in 0..3 {
            let (x, r) = (a[c] as f64, b[c] as f64);
            let d = x - r;
            se += d * d;
            rel += d * d / (r * r + 1e-2);
            ae += d.abs();
        }
    }
    let n = image.pixels.len() * 3;
    let nf = n.max(1) as f64;
    Ok(ErrorMetrics {
        rmse: (se / nf).sqrt(),
        rel_mse: rel / nf,
        mae: ae / nf,
        ssim: ssim(image, reference),
        count: n,
    })
}

/// Mean of `channel` over the pixels and its standard error. Pixels are
/// independent estimates when their sample keys are disjoint (as every
/// pixel's are), so the error of the mean follows from their spread: the
/// tolerance of every statistical test of an image mean.
pub fn mean_and_standard_error(pixels: &[[f32; 3]], channel: usize) -> (f64, f64) {
    let n = pixels.len() as f64;
    let mean = pixels.iter().map(|p| p[channel] as f64).sum::<f64>() / n;
    let var = pixels
        .iter()
        .map(|p| (p[channel] as f64 - mean).powi(2))
        .sum::<f64>()
        / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// Window edge and stride of [`ssim`].
const SSIM_WINDOW: usize = 8;
const SSIM_STRIDE: usize = 4;

/// Mean structural similarity of two images of equal size: luminance
/// (Rec. 709) tone-mapped by `L / (1 + L)` into [0, 1), so that HDR
/// highlights do not swamp it, then SSIM with the standard constants
/// (K1 = 0.01, K2 = 0.03, dynamic range 1) over 8 x 8 windows every 4
/// pixels (the whole image when it is smaller than a window).
pub fn ssim(a: &Image, b: &Image) -> f64 {
    let lum = |im: &Image| -> Vec<f64> {
        im.pixels
            .iter()
            .map(|p| {
                let l = (0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]) as f64;
                let l = if l.is_finite() { l.max(0.0) } else { 0.0 };
                l / (1.0 + l)
            })
            .collect()
    };
    let (x, y) = (lum(a), lum(b));
    let (w, h) = (a.width as usize, a.height as usize);
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let (ww, wh) = (SSIM_WINDOW.min(w), SSIM_WINDOW.min(h));
    let (mut sum, mut count) = (0.0, 0usize);
    let mut y0 = 0;
    while y0 + wh <= h {
        let mut x0 = 0;
        while x0 + ww <= w {
            let (mut mx, mut my, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for j in y0..y0 + wh {
                for i in x0..x0 + ww {
                    let (u, v) = (x[j * w + i], y[j * w + i]);
                    mx += u;
                    my += v;
                }
            }
            let n = (ww * wh) as f64;
            mx /= n;
            my /= n;
            for j in y0..y0 + wh {
                for i in x0..x0 + ww {
                    let (u, v) = (x[j * w + i] - mx, y[j * w + i] - my);
                    sxx += u * u;
                    syy += v * v;
                    sxy += u * v;
                }
            }
            let d = (n - 1.0).max(1.0);
            let (vx, vy, cxy) = (sxx / d, syy / d, sxy / d);
            sum += ((2.0 * mx * my + c1) * (2.0 * cxy + c2))
                / ((mx * mx + my * my + c1) * (vx + vy + c2));
            count += 1;
            x0 += SSIM_STRIDE;
        }
        y0 += SSIM_STRIDE;
    }
    if count == 0 { 1.0 } else { sum / count as f64 }
}

impl std::fmt::Display for ErrorMetrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "RMSE {:.6e}  relMSE {:.6e}  MAE {:.6e}  SSIM {:.4}",
            self.rmse, self.rel_mse, self.mae, self.ssim
        )
    }
}

impl ErrorEstimate {
    /// The estimate in words, read from the spread of `samples` (such as
    /// "16 samples a pixel").
    pub fn read_from(&self, samples: &str) -> String {
        format!(
            "RMSE {:.6e}  relMSE {:.6e} (from the spread of {samples})",
            self.rmse, self.rel_mse
        )
    }
}

impl std::fmt::Display for ErrorEstimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let samples = format!("{} samples a pixel", self.samples);
        f.write_str(&self.read_from(&samples))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_of_known_difference() {
        let mut a = Image::new(2, 1);
        let b = Image::new(2, 1);
        a.pixels[0] = [1.0, 0.0, 0.0];
        let m = compare(&a, &b).unwrap();
        assert!((m.rmse - (1.0f64 / 6.0).sqrt()).abs() < 1e-12);
        assert!((m.mae - 1.0 / 6.0).abs() < 1e-12);
        assert!((m.rel_mse - 100.0 / 6.0).abs() < 1e-9);
        assert_eq!(compare(&a, &a).unwrap().rmse, 0.0);
        assert!(compare(&a, &Image::new(1, 2)).is_err());
    }

    #[test]
    fn mean_and_standard_error_of_known_values() {
        let px = [[0.0, 1.0, 0.0], [0.0, 3.0, 0.0]];
        let (m, se) = mean_and_standard_error(&px, 1);
        assert_eq!(m, 2.0);
        // Sample variance 2, over n = 2: se = 1.
        assert!((se - 1.0).abs() < 1e-12);
    }

    /// SSIM is 1 for identical images and falls as noise grows, while the
    /// mean stays the same (which RMSE alone would not tell apart from a
    /// shift).
    #[test]
    fn ssim_falls_with_noise() {
        let mut base = Image::new(32, 24);
        for (i, p) in base.pixels.iter_mut().enumerate() {
            let v = 0.2 + 0.6 * ((i % 32) as f32 / 32.0);
            *p = [v, v, v];
        }
        let noisy = |amp: f32| {
            let mut im = base.clone();
            for (i, p) in im.pixels.iter_mut().enumerate() {
                let k = crate::sampler::SampleKey::independent(i as u64, 0, 1);
                let n = (k.get1d(0) - 0.5) * 2.0 * amp;
                *p = [p[0] + n, p[1] + n, p[2] + n];
            }
            im
        };
        assert!((ssim(&base, &base) - 1.0).abs() < 1e-12);
        let (s1, s2) = (ssim(&noisy(0.05), &base), ssim(&noisy(0.2), &base));
        assert!(s1 < 0.999 && s2 < s1, "{s1} {s2}");
        assert!(s2 > 0.0);
    }
}
