//! Random numbers as a pure function of (pixel, sample index, dimension, seed).
//!
//! Nothing here carries state between calls: any thread or any worker of the
//! farm that evaluates the same key gets the same bits, which is what makes
//! images independent of tiling and of where a path vertex is shaded.
//!
//! Two samplers ([`Sampler`]):
//! - **Sobol** (the default): each call's dimensions form a 1D or 2D pattern
//!   of their own, "padded" as in pbrt-v4's `PaddedSobolSampler`. A pixel's
//!   samples of one pattern are the first two dimensions of the Sobol
//!   sequence (a (0,2)-sequence), with the sample index shuffled and the
//!   values Owen-scrambled by a hash of (pixel, dimension, seed), after
//!   Burley, *Practical Hash-based Owen Scrambling* (JCGT 2020). The
//!   shuffle is itself a nested scramble of the index, so the samples of any
//!   aligned run of 2^k indices (a progressive pass) are a (0,k,2)-net.
//!   Pixels and patterns are independent randomisations, so the standard
//!   error over pixels remains an honest error bar.
//! - **Independent**: every dimension a hash of the whole key, like
//!   pbrt-v4's `IndependentSampler`.

use serde::{Deserialize, Serialize};

/// SplitMix64 finaliser (Steele, Lea and Flood 2014): a bijective mixer with
/// full avalanche, so neighbouring keys give unrelated outputs.
#[inline(always)]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Which sequence a job's samples come from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sampler {
    /// Shuffled, Owen-scrambled Sobol, padded per 1D or 2D pattern.
    #[default]
    Sobol,
    /// Independent uniform values.
    Independent,
}

impl Sampler {
    pub const ALL: [Sampler; 2] = [Sampler::Sobol, Sampler::Independent];

    /// The name the scene file and the command line use.
    pub fn name(self) -> &'static str {
        match self {
            Sampler::Sobol => "sobol",
            Sampler::Independent => "independent",
        }
    }
}

impl std::str::FromStr for Sampler {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| {
                let names: Vec<String> = Self::ALL
                    .iter()
                    .map(|k| format!("{:?}", k.name()))
                    .collect();
                format!("unknown sampler {s:?}: expected {}", names.join(" or "))
            })
    }
}

/// The identity of one camera sample: which pixel, which sample of it, the
/// job seed and sampler. Dimensions are passed per call.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SampleKey {
    /// Linear pixel index `y * width + x`.
    pub pixel: u64,
    pub sample: u32,
    pub seed: u64,
    pub sampler: Sampler,
}

/// 2^-24: values keep 24 bits, so they are exact in f32 and below 1.
const UNIT: f32 = 1.0 / (1u32 << 24) as f32;

impl SampleKey {
    pub fn new(pixel: u64, sample: u32, seed: u64, sampler: Sampler) -> Self {
        Self {
            pixel,
            sample,
            seed,
            sampler,
        }
    }

    /// A key of the independent sampler: uniform numbers for tests, cost
    /// estimates and generated rays, where no sequence is wanted.
    pub fn independent(pixel: u64, sample: u32, seed: u64) -> Self {
        Self::new(pixel, sample, seed, Sampler::Independent)
    }

    /// The parts of this key that every dimension shares, computed once:
    /// a path vertex draws several dimensions from one.
    #[inline(always)]
    pub fn draws(&self) -> Draws {
        Draws {
            sampler: self.sampler,
            // A hash of (seed, pixel). One mixing round: the seed and pixel
            // are each spread by an odd multiplier (a bijection) before
            // they meet.
            pixel_hash: mix64(self.seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ self.pixel),
            sample: self.sample,
            sample_reversed: self.sample.reverse_bits(),
        }
    }

    /// A uniform value in [0, 1) for dimension `dim`.
    #[inline(always)]
    pub fn get1d(&self, dim: u32) -> f32 {
        self.draws().get1d(dim)
    }

    /// Two values from dimensions `dim` and `dim + 1`, one 2D pattern.
    #[inline(always)]
    pub fn get2d(&self, dim: u32) -> [f32; 2] {
        self.draws().get2d(dim)
    }

    /// The 2D pattern of [`Self::get2d`] as 32-bit fractions (value times
    /// 2^32), for a caller that spends part of a coordinate on a discrete
    /// choice and keeps the rest (see [`crate::light::LightSet::sample`]).
    #[inline(always)]
    pub fn get2d_bits(&self, dim: u32) -> [u32; 2] {
        self.draws().get2d_bits(dim)
    }
}

/// What [`SampleKey::draws`] computes once: its values are the key's, to
/// the bit, for every dimension.
#[derive(Clone, Copy, Debug)]
pub struct Draws {
    sampler: Sampler,
    pixel_hash: u64,
    sample: u32,
    sample_reversed: u32,
}

impl Draws {
    #[inline(always)]
    fn bits(&self, dim: u32) -> u64 {
        mix64(self.pixel_hash ^ (((self.sample as u64) << 32) | dim as u64))
    }

    /// The pattern at `dim`: its hash, and the sample's shuffled Sobol index
    /// `i` as `reverse_bits(i)` (the first dimension's value before its
    /// scramble). The shuffle is a nested scramble of the index's bits
    /// reversed, so aligned runs of indices map to aligned runs.
    #[inline(always)]
    fn sobol_pattern(&self, dim: u32) -> (u32, u64) {
        let h = mix64(self.pixel_hash ^ (dim as u64) ^ 0x50b0_1000_0000_0000);
        (laine_karras(self.sample_reversed, h as u32), h)
    }

    /// A uniform value in [0, 1) for dimension `dim`.
    #[inline(always)]
    pub fn get1d(&self, dim: u32) -> f32 {
        let bits = match self.sampler {
            Sampler::Independent => (self.bits(dim) >> 32) as u32,
            Sampler::Sobol => {
                let (r, h) = self.sobol_pattern(dim);
                laine_karras(r.reverse_bits(), (h >> 32) as u32).reverse_bits()
            }
        };
        (bits >> 8) as f32 * UNIT
    }

    /// Two values from dimensions `dim` and `dim + 1`, one 2D pattern.
    #[inline(always)]
    pub fn get2d(&self, dim: u32) -> [f32; 2] {
        let [x, y] = self.get2d_bits(dim);
        [(x >> 8) as f32 * UNIT, (y >> 8) as f32 * UNIT]
    }

    /// The 2D pattern of [`Self::get2d`] as 32-bit fractions.
    #[inline(always)]
    pub fn get2d_bits(&self, dim: u32) -> [u32; 2] {
        match self.sampler {
            Sampler::Independent => [
                (self.bits(dim) >> 32) as u32,
                (self.bits(dim + 1) >> 32) as u32,
            ],
            Sampler::Sobol => {
                let (r, h) = self.sobol_pattern(dim);
                let i = r.reverse_bits();
                // Owen scrambles of the two dimensions' values, each done
                // on the value's bits reversed: the first dimension's value
                // reversed is the index itself. The two are reversed back
                // together, as one 64-bit word (x's bits land in the high
                // half): one reversal where two stood, on processors with
                // no instruction for it.
                let x = laine_karras(i, (h >> 32) as u32);
                let y = laine_karras(sobol_dim1_reversed(i), mix64(h) as u32);
                let both = (x as u64 | (y as u64) << 32).reverse_bits();
                [(both >> 32) as u32, both as u32]
            }
        }
    }
}

/// Generator matrix of the Sobol sequence's second dimension (primitive
/// polynomial x + 1), columns bit-reversed: column `b` is `v_b = v_{b-1} ^
/// (v_{b-1} >> 1)` from `v_0 = 2^31`, the binary Pascal matrix, so the value
/// of index `i` reversed is the XOR of the reversed columns of `i`'s set
/// bits. Tabled a byte at a time. The first dimension's matrix is the
/// identity reversed (the van der Corput sequence).
const SOBOL_DIM1_REVERSED: [[u32; 256]; 4] = {
    let mut v = [0u32; 32];
    v[0] = 1 << 31;
    let mut b = 1;
    while b < 32 {
        v[b] = v[b - 1] ^ (v[b - 1] >> 1);
        b += 1;
    }
    let mut t = [[0u32; 256]; 4];
    let mut k = 0;
    while k < 4 {
        let mut byte = 0;
        while byte < 256 {
            let mut x = 0u32;
            let mut j = 0;
            while j < 8 {
                if byte & (1 << j) != 0 {
                    x ^= v[8 * k + j].reverse_bits();
                }
                j += 1;
            }
            t[k][byte] = x;
            byte += 1;
        }
        k += 1;
    }
    t
};

/// The second Sobol dimension's value of index `i`, its bits reversed.
#[inline(always)]
fn sobol_dim1_reversed(i: u32) -> u32 {
    let t = &SOBOL_DIM1_REVERSED;
    t[0][(i & 0xff) as usize]
        ^ t[1][((i >> 8) & 0xff) as usize]
        ^ t[2][((i >> 16) & 0xff) as usize]
        ^ t[3][(i >> 24) as usize]
}

/// A Laine-Karras style permutation: each output bit depends only on the
/// input bits below it (pbrt-v4's `FastOwenScrambler`). Applied to a
/// fraction's bits reversed, that is Owen scrambling: each digit flipped by
/// a hash of the digits before it.
#[inline(always)]
fn laine_karras(mut v: u32, seed: u32) -> u32 {
    v ^= v.wrapping_mul(0x3d20_adea);
    v = v.wrapping_add(seed);
    v = v.wrapping_mul((seed >> 16) | 1);
    v ^= v.wrapping_mul(0x0552_6c56);
    v ^= v.wrapping_mul(0x53a2_2864);
    v
}

/// Owen scrambling of a 32-bit fraction (most significant bit first).
#[cfg(test)]
fn nested_uniform_scramble(x: u32, seed: u32) -> u32 {
    laine_karras(x.reverse_bits(), seed).reverse_bits()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_in_unit_interval_and_uniform() {
        // Mean of U[0,1) is 1/2 with standard deviation 1/sqrt(12 n); 5 sigma.
        for sampler in [Sampler::Independent, Sampler::Sobol] {
            let n = 200_000u32;
            let mut sum = 0.0f64;
            for d in 0..n {
                let u = SampleKey::new(17, d % 64, 42, sampler).get1d(d / 64);
                assert!((0.0..1.0).contains(&u));
                sum += u as f64;
            }
            let mean = sum / n as f64;
            let sigma = (1.0 / (12.0 * n as f64)).sqrt();
            assert!((mean - 0.5).abs() < 5.0 * sigma, "{sampler:?}: mean {mean}");
        }
    }

    /// The names the command line parses are the ones serde reads from a
    /// scene file.
    #[test]
    fn names_agree_with_the_scene_file() {
        for k in Sampler::ALL {
            assert_eq!(k.name().parse::<Sampler>(), Ok(k));
            let quoted = format!("\"{}\"", k.name());
            assert_eq!(serde_json::from_str::<Sampler>(&quoted).ok(), Some(k));
        }
        assert!(
            "halton"
                .parse::<Sampler>()
                .unwrap_err()
                .contains("\"sobol\" or")
        );
    }

    #[test]
    fn keys_are_pure_and_distinct() {
        for s in [Sampler::Independent, Sampler::Sobol] {
            let a = SampleKey::new(1, 2, 3, s);
            assert_eq!(a.get1d(7), SampleKey::new(1, 2, 3, s).get1d(7));
            assert_ne!(a.get1d(7), SampleKey::new(1, 2, 4, s).get1d(7));
            assert_ne!(a.get1d(7), SampleKey::new(2, 2, 3, s).get1d(7));
            assert_ne!(a.get1d(7), SampleKey::new(1, 3, 3, s).get1d(7));
            assert_ne!(a.get1d(7), a.get1d(8));
        }
    }

    /// The scramble is a bijection whose top `k` output bits depend only on
    /// the top `k` input bits: what keeps nets nets.
    #[test]
    fn owen_scramble_is_nested() {
        for seed in [0u32, 1, 0xdead_beef, 0x1234_5678] {
            for k in [1u32, 3, 8] {
                let mut seen = std::collections::HashSet::new();
                for x in 0..1u32 << 12 {
                    let v = x << 20;
                    let top = nested_uniform_scramble(v, seed) >> (32 - k);
                    // Same top bits in, same top bits out.
                    let w = v | 0x000f_ffff;
                    assert_eq!(top, nested_uniform_scramble(w, seed) >> (32 - k));
                    seen.insert(nested_uniform_scramble(v, seed));
                }
                assert_eq!(seen.len(), 1 << 12, "not a bijection");
            }
        }
    }

    /// A 2D pattern's two values are reversed back as one 64-bit word:
    /// the same bits as reversing each on its own, and as drawing each
    /// dimension through a key afresh (what every caller but the shading
    /// of a vertex does).
    #[test]
    fn the_paired_reversal_is_two_reversals() {
        for pixel in 0..64u64 {
            for sample in [0u32, 1, 2, 3, 7, 255, 1 << 20, u32::MAX] {
                let key = SampleKey::new(pixel, sample, 11, Sampler::Sobol);
                let d = key.draws();
                for dim in 0..12 {
                    let (r, h) = d.sobol_pattern(dim);
                    let i = r.reverse_bits();
                    let want = [
                        laine_karras(i, (h >> 32) as u32).reverse_bits(),
                        laine_karras(sobol_dim1_reversed(i), mix64(h) as u32).reverse_bits(),
                    ];
                    assert_eq!(d.get2d_bits(dim), want);
                    assert_eq!(key.get2d_bits(dim), want);
                    assert_eq!(key.get1d(dim).to_bits(), d.get1d(dim).to_bits());
                }
            }
        }
    }

    /// The tabled second dimension is the Sobol sequence's: its first
    /// values in index order (not Gray-code order): 0, 1/2, 3/4, 1/4, 5/8,
    /// 1/8, 3/8, 7/8, from the direction numbers 1/2, 3/4, 5/8.
    #[test]
    fn sobol_second_dimension() {
        let first: Vec<f64> = (0..8u32)
            .map(|i| sobol_dim1_reversed(i).reverse_bits() as f64 / 2f64.powi(32))
            .collect();
        assert_eq!(first, [0.0, 0.5, 0.75, 0.25, 0.625, 0.125, 0.375, 0.875]);
        // XOR-linear in the index: value(a ^ b) = value(a) ^ value(b).
        for (a, b) in [(3u32, 0x8000_0001), (0xdead_beef, 0x1234_5678)] {
            assert_eq!(
                sobol_dim1_reversed(a ^ b),
                sobol_dim1_reversed(a) ^ sobol_dim1_reversed(b)
            );
        }
    }

    /// Every aligned run of 2^k samples of a 2D pattern puts exactly one
    /// point in each elementary box 2^-a x 2^-b with a + b = k: a
    /// (0,k,2)-net, whatever the pixel, pattern and seed.
    #[test]
    fn aligned_runs_are_nets() {
        for (pixel, dim, seed) in [(0u64, 0u32, 0u64), (77, 5, 9), (1 << 40, 3, 123)] {
            for k in [2u32, 4, 6] {
                let n = 1u32 << k;
                for start in [0, n, 5 * n] {
                    let pts: Vec<[f32; 2]> = (start..start + n)
                        .map(|s| SampleKey::new(pixel, s, seed, Sampler::Sobol).get2d(dim))
                        .collect();
                    for a in 0..=k {
                        let b = k - a;
                        let mut boxes = vec![0u32; n as usize];
                        for p in &pts {
                            let i = (p[0] * (1u32 << a) as f32) as u32;
                            let j = (p[1] * (1u32 << b) as f32) as u32;
                            boxes[(i * (1 << b) + j) as usize] += 1;
                        }
                        assert!(
                            boxes.iter().all(|&c| c == 1),
                            "pixel {pixel} dim {dim} k {k} start {start} box {a}x{b}: {boxes:?}"
                        );
                    }
                    // 1D: one point per interval of 1/n.
                    let mut bins = vec![0u32; n as usize];
                    for s in start..start + n {
                        let u = SampleKey::new(pixel, s, seed, Sampler::Sobol).get1d(dim);
                        bins[(u * n as f32) as usize] += 1;
                    }
                    assert!(bins.iter().all(|&c| c == 1), "1D run: {bins:?}");
                }
            }
        }
    }

    /// Different patterns of one sample are independent: the correlation
    /// of dimension pairs over many pixels is zero within 5 standard
    /// errors (1/sqrt(n) for uncorrelated uniforms).
    #[test]
    fn patterns_are_uncorrelated() {
        let n = 64 * 1024u32;
        let mut sum = 0.0f64;
        for i in 0..n {
            let k = SampleKey::new((i / 64) as u64, i % 64, 5, Sampler::Sobol);
            let (u, v) = (k.get2d(2)[0] as f64 - 0.5, k.get2d(4)[0] as f64 - 0.5);
            sum += u * v * 12.0;
        }
        let corr = sum / n as f64;
        assert!(corr.abs() < 5.0 / (n as f64).sqrt(), "correlation {corr}");
    }

    /// The point of the sequence: a smooth 2D integral over 64 samples a
    /// pixel has far less error than with independent samples. Measured
    /// over 512 pixels (independent randomisations); Sobol's mean squared
    /// error must be under a quarter of independent sampling's.
    #[test]
    fn sobol_beats_independent_on_a_smooth_integral() {
        let f = |p: [f32; 2]| ((p[0] as f64) * 3.0).sin() * (p[1] as f64 + 0.5).powi(2);
        let exact = (1.0 - 3f64.cos()) / 3.0 * ((1.5f64.powi(3) - 0.5f64.powi(3)) / 3.0);
        let mse = |s: Sampler| {
            let mut e = 0.0;
            for pixel in 0..512u64 {
                let mean: f64 = (0..64)
                    .map(|i| f(SampleKey::new(pixel, i, 1, s).get2d(2)))
                    .sum::<f64>()
                    / 64.0;
                e += (mean - exact).powi(2);
            }
            e / 512.0
        };
        let (ind, sob) = (mse(Sampler::Independent), mse(Sampler::Sobol));
        assert!(
            sob < ind / 4.0,
            "Sobol MSE {sob:.3e} vs independent {ind:.3e}"
        );
    }
}
