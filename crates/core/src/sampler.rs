//! Random numbers as a pure function of (pixel, sample index, dimension, seed).
//!
//! Like pbrt-v4's `IndependentSampler`, nothing here carries state between
//! calls: any thread or any worker of the farm that evaluates the same key gets
//! the same bits, which is what makes images independent of tiling and of where
//! a path vertex is shaded.

/// SplitMix64 finaliser (Steele, Lea and Flood 2014): a bijective mixer with
/// full avalanche, so neighbouring keys give unrelated outputs.
#[inline(always)]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The identity of one camera sample: which pixel, which sample of it, and the
/// job seed. Dimensions are passed per call.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct SampleKey {
    /// Linear pixel index `y * width + x`.
    pub pixel: u64,
    pub sample: u32,
    pub seed: u64,
}

impl SampleKey {
    pub fn new(pixel: u64, sample: u32, seed: u64) -> Self {
        Self {
            pixel,
            sample,
            seed,
        }
    }

    #[inline(always)]
    fn bits(&self, dim: u32) -> u64 {
        let a = mix64(self.seed ^ 0x9e37_79b9_7f4a_7c15);
        let b = mix64(a ^ self.pixel);
        mix64(b ^ (((self.sample as u64) << 32) | dim as u64))
    }

    /// A uniform value in [0, 1) for dimension `dim`; 24 random bits, so the
    /// value is exactly representable and never rounds up to 1.
    #[inline(always)]
    pub fn get1d(&self, dim: u32) -> f32 {
        (self.bits(dim) >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    /// Two values from dimensions `dim` and `dim + 1`.
    #[inline(always)]
    pub fn get2d(&self, dim: u32) -> [f32; 2] {
        [self.get1d(dim), self.get1d(dim + 1)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_in_unit_interval_and_uniform() {
        // Mean of U[0,1) is 1/2 with standard deviation 1/sqrt(12 n); 5 sigma.
        let n = 200_000u32;
        let key = SampleKey::new(17, 3, 42);
        let mut sum = 0.0f64;
        for d in 0..n {
            let u = key.get1d(d);
            assert!((0.0..1.0).contains(&u));
            sum += u as f64;
        }
        let mean = sum / n as f64;
        let sigma = (1.0 / (12.0 * n as f64)).sqrt();
        assert!((mean - 0.5).abs() < 5.0 * sigma, "mean {mean}");
    }

    #[test]
    fn keys_are_pure_and_distinct() {
        let a = SampleKey::new(1, 2, 3);
        assert_eq!(a.get1d(7), SampleKey::new(1, 2, 3).get1d(7));
        assert_ne!(a.get1d(7), SampleKey::new(1, 2, 4).get1d(7));
        assert_ne!(a.get1d(7), SampleKey::new(2, 2, 3).get1d(7));
        assert_ne!(a.get1d(7), SampleKey::new(1, 3, 3).get1d(7));
        assert_ne!(a.get1d(7), a.get1d(8));
    }
}
