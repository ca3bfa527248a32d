//! Image error metrics: the one implementation behind `locus diff` and
//! `locus render --reference`.

use crate::image_io::{Image, ImageError};
use serde::Serialize;

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ErrorMetrics {
    /// Root mean squared error over all channels.
    pub rmse: f64,
    /// Mean over channels of (a - b)^2 / (b^2 + 1e-2), pbrt's relMSE, with
    /// `b` the reference; the epsilon keeps black pixels from dominating.
    pub rel_mse: f64,
    /// Mean absolute error over all channels.
    pub mae: f64,
    /// Channels counted (3 per pixel).
    pub count: usize,
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
        count: n,
    })
}

impl std::fmt::Display for ErrorMetrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "RMSE {:.6e}  relMSE {:.6e}  MAE {:.6e}",
            self.rmse, self.rel_mse, self.mae
        )
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
}
