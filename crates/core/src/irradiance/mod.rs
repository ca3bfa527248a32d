//! Ward's irradiance cache (Ward, Rubinstein and Clear, "A Ray Tracing
//! Solution for Diffuse Interreflection", 1988; Radiance's ambient cache),
//! for the diffuse interreflection at the first path vertex.
//!
//! A record holds the irradiance arriving at one point from the surfaces
//! around it (their emission excluded: next-event estimation takes all of
//! the direct light at a vertex the cache answers), measured with a
//! stratified hemisphere of rays ([`hemisphere`]), the harmonic mean
//! distance `R` of the surfaces those rays hit, and Ward and Heckbert's
//! translational and rotational gradients. Record `i` is valid at point `p`
//! with normal `n` while its weight
//! `w_i = 1 / (|p - p_i| / R_i + sqrt(1 - n . n_i))` exceeds `1 / a`
//! (`a`: the accuracy, Radiance's `-aa`), and the cache answers with the
//! weighted mean of the valid records' extrapolations
//! `E_i + (n_i x n) . grad_r E_i + (p - p_i) . grad_t E_i`. Records are
//! found through an [`octree`] of records.
//!
//! Records are placed by an [`overture`] before the image is rendered, as
//! Radiance's overture pass does, but coarse to fine over a pixel grid and
//! against the records of the coarser levels only, so that which records
//! exist (and so the image) does not depend on the number of threads. The
//! render then only reads the cache, and a sample whose first vertex no
//! record covers is path traced as without the cache.
//!
//! The cache is biased by design (it interpolates); its error is reported
//! against the converged reference like every other setting's.

pub mod hemisphere;
pub mod octree;
pub mod overture;

use crate::geometry::Bounds;
use glam::Vec3;
use hemisphere::Estimate;
use octree::RecordOctree;
use serde::{Deserialize, Serialize};

/// The irradiance cache's settings, named after Radiance's ambient
/// parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IrradianceParams {
    /// Ward's `a` (Radiance's `-aa`): the largest interpolation error a
    /// record is trusted to, which scales the distance over which it is
    /// valid.
    pub accuracy: f32,
    /// Rays per record (`-ad`), split into strata about square.
    pub divisions: u32,
    /// The scene's extent over the smallest radius of validity (`-ar`):
    /// records are never closer than this resolves, however near the
    /// surfaces around them.
    pub resolution: f32,
    /// Extrapolate with the translational and rotational gradients, and
    /// limit a record's radius where its irradiance changes fast.
    pub gradients: bool,
    /// Spacing in pixels of the overture's coarsest level (a power of
    /// two); each level halves it down to one pixel.
    pub spacing: u32,
    /// At most this many records; points beyond are path traced.
    pub max_records: usize,
}

impl Default for IrradianceParams {
    fn default() -> Self {
        Self {
            accuracy: 0.2,
            divisions: 512,
            resolution: 128.0,
            gradients: true,
            spacing: 16,
            max_records: 1 << 20,
        }
    }
}

impl IrradianceParams {
    pub fn check(&self) -> Result<(), String> {
        if !(self.accuracy > 0.0 && self.accuracy <= 1.0) {
            return Err(format!(
                "irradiance accuracy must be in (0, 1], not {}",
                self.accuracy
            ));
        }
        if !(16..=65_536).contains(&self.divisions) {
            return Err(format!(
                "irradiance divisions must be 16 to 65536, not {}",
                self.divisions
            ));
        }
        if !(self.resolution >= 1.0 && self.resolution <= 1e6) {
            return Err(format!(
                "irradiance resolution must be 1 to 1e6, not {}",
                self.resolution
            ));
        }
        if !self.spacing.is_power_of_two() || self.spacing > 256 {
            return Err(format!(
                "irradiance spacing must be a power of two up to 256, not {}",
                self.spacing
            ));
        }
        if self.max_records == 0 || self.max_records > 1 << 26 {
            return Err(format!(
                "irradiance max_records must be 1 to {}, not {}",
                1u32 << 26,
                self.max_records
            ));
        }
        Ok(())
    }
}

/// One irradiance record.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub p: Vec3,
    pub n: Vec3,
    pub e: Vec3,
    /// Harmonic mean distance, clamped and gradient-limited.
    pub r: f32,
    pub grad_t: [Vec3; 3],
    pub grad_r: [Vec3; 3],
}

impl Record {
    /// The record's extrapolation to `(p, n)` and Ward's error term
    /// `1 / w`, or None where it is not valid (behind `p`'s surface, or
    /// past the accuracy).
    #[inline]
    fn extrapolate(&self, p: Vec3, n: Vec3, accuracy: f32) -> Option<(f32, Vec3)> {
        let d = p - self.p;
        let err = d.length() / self.r + (1.0 - n.dot(self.n)).max(0.0).sqrt();
        // Ward's test that the record is not in front of the point: a
        // record on a surface before it sees other light.
        if err >= accuracy || d.dot(n + self.n) < -0.1 * self.r {
            return None;
        }
        let rot = self.n.cross(n);
        let mut e = self.e;
        for a in 0..3 {
            e += self.grad_t[a] * d[a] + self.grad_r[a] * rot[a];
        }
        Some((err, e.max(Vec3::ZERO)))
    }
}

/// Counts of the cache's use by the render: first vertices it answered,
/// and those it did not cover and were path traced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct IrradianceUse {
    pub interpolated: u64,
    pub traced: u64,
}

impl std::ops::AddAssign for IrradianceUse {
    fn add_assign(&mut self, o: Self) {
        self.interpolated += o.interpolated;
        self.traced += o.traced;
    }
}

/// Records and the octree that finds them.
#[derive(Clone, Debug)]
pub struct IrradianceCache {
    pub params: IrradianceParams,
    records: Vec<Record>,
    octree: RecordOctree,
    /// Bounds on a record's harmonic mean distance.
    r_min: f32,
    r_max: f32,
}

impl IrradianceCache {
    /// An empty cache for a scene within `bounds`.
    pub fn new(params: IrradianceParams, bounds: &Bounds) -> Self {
        let extent = if bounds.is_empty() {
            1.0
        } else {
            bounds.extent().max_element().max(1e-6)
        };
        // Validity radii `a R` between extent / resolution and an eighth
        // of the scene.
        let a = params.accuracy;
        Self {
            params,
            records: Vec::new(),
            octree: RecordOctree::new(bounds),
            r_min: extent / (params.resolution * a),
            r_max: (extent / (8.0 * a)).max(extent / (params.resolution * a)),
        }
    }

    fn push(&mut self, r: Record) {
        let id = self.records.len() as u32;
        self.octree.insert(id, r.p, self.params.accuracy * r.r);
        self.records.push(r);
    }

    pub fn len(&self) -> usize {
        self.records.len()
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    pub fn records(&self) -> &[Record] {
        &self.records
    }

    /// Bytes the records and the octree hold.
    pub fn bytes(&self) -> usize {
        self.records.capacity() * std::mem::size_of::<Record>() + self.octree.bytes()
    }

    /// Whether another record fits under `max_records`.
    pub fn is_full(&self) -> bool {
        self.records.len() >= self.params.max_records
    }

    /// Adds the record measured at `p` about `n`, valid at least as far
    /// as `min_valid` (Tabellion and Lamorlette's screen-space clamp: the
    /// overture places records at most a pixel apart, so none need be
    /// valid for less than the pixel's footprint); false when the cache is
    /// full.
    pub fn insert(&mut self, p: Vec3, n: Vec3, est: &Estimate, min_valid: f32) -> bool {
        if self.is_full() {
            return false;
        }
        // Křivánek et al.'s limit: no record is trusted farther than where
        // its gradient would take its irradiance to zero.
        let g = Vec3::new(
            est.grad_t[0].element_sum(),
            est.grad_t[1].element_sum(),
            est.grad_t[2].element_sum(),
        )
        .length();
        let e_sum = est.e.element_sum();
        let mut r = est.harmonic;
        if self.params.gradients && g > 0.0 {
            r = r.min(e_sum / g);
        }
        let lo = self.r_min.max(min_valid / self.params.accuracy);
        let r = if r.is_nan() {
            lo
        } else {
            r.clamp(lo, self.r_max.max(lo))
        };
        let (mut grad_t, grad_r) = if self.params.gradients {
            (est.grad_t, est.grad_r)
        } else {
            ([Vec3::ZERO; 3], [Vec3::ZERO; 3])
        };
        // Where the clamps made the record valid farther than its gradient
        // allows (a record near a corner, or a noisy gradient), the
        // gradient is scaled down so that it changes the irradiance by at
        // most E over the record's radius of validity.
        let reach = g * r * self.params.accuracy;
        if self.params.gradients && reach > e_sum {
            let k = if e_sum > 0.0 { e_sum / reach } else { 0.0 };
            grad_t = grad_t.map(|v| v * k);
        }
        self.push(Record {
            p,
            n,
            e: est.e,
            r,
            grad_t,
            grad_r,
        });
        true
    }

    /// The irradiance at `p` about unit normal `n` from the records valid
    /// there (Ward's weighted mean), or None where none is.
    pub fn interpolate(&self, p: Vec3, n: Vec3) -> Option<Vec3> {
        let (mut sum, mut wsum) = (Vec3::ZERO, 0.0f32);
        let a = self.params.accuracy;
        self.octree.visit(p, |i| {
            if let Some((err, e)) = self.records[i as usize].extrapolate(p, n, a) {
                let w = 1.0 / err.max(1e-6);
                sum += e * w;
                wsum += w;
            }
        });
        (wsum > 0.0).then(|| sum / wsum)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::SampleKey;

    /// The octree's answer is the brute-force weighted mean over every
    /// record.
    #[test]
    fn interpolation_through_the_octree_matches_brute_force() {
        let b = Bounds::new(Vec3::ZERO, Vec3::splat(4.0));
        let params = IrradianceParams {
            accuracy: 0.3,
            ..Default::default()
        };
        let mut c = IrradianceCache::new(params, &b);
        let key = |i: u64, s: u32| SampleKey::independent(i, s, 3);
        let unit = |k: &SampleKey, d: u32| {
            Vec3::new(k.get1d(d), k.get1d(d + 1), k.get1d(d + 2) + 0.5).normalize()
        };
        for i in 0..800u64 {
            let k = key(i, 0);
            let est = Estimate {
                e: Vec3::new(k.get1d(3), 1.0, 2.0),
                harmonic: 0.05 + 2.0 * k.get1d(4),
                grad_t: [Vec3::splat(0.1), Vec3::ZERO, Vec3::splat(-0.05)],
                grad_r: [Vec3::ZERO, Vec3::splat(0.2), Vec3::ZERO],
            };
            let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 4.0;
            assert!(c.insert(p, unit(&k, 5), &est, 0.0));
        }
        let mut answered = 0;
        for i in 0..2000u64 {
            let k = key(i, 1);
            let (p, n) = (
                Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 4.0,
                unit(&k, 5),
            );
            let (mut sum, mut wsum) = (Vec3::ZERO, 0.0f32);
            for r in c.records() {
                if let Some((err, e)) = r.extrapolate(p, n, params.accuracy) {
                    sum += e / err.max(1e-6);
                    wsum += 1.0 / err.max(1e-6);
                }
            }
            let brute = (wsum > 0.0).then(|| sum / wsum);
            let got = c.interpolate(p, n);
            match (got, brute) {
                (Some(g), Some(b)) => {
                    answered += 1;
                    assert!((g - b).abs().max_element() <= 1e-4 * b.abs().max_element().max(1.0));
                }
                (None, None) => {}
                other => panic!("octree and brute force differ at {p}: {other:?}"),
            }
        }
        assert!(
            answered > 200 && answered < 1900,
            "{answered} of 2000 answered"
        );
    }

    /// A cache rebuilt from shipped measurements, added in the same order,
    /// answers the same bits; a broken measurement is refused.
    #[test]
    fn shipped_measurements_rebuild_the_same_cache() {
        use overture::Measured;
        let b = Bounds::new(Vec3::ZERO, Vec3::splat(2.0));
        let mut c = IrradianceCache::new(IrradianceParams::default(), &b);
        let mut sent = Vec::new();
        for i in 0..300u64 {
            let k = SampleKey::independent(i, 0, 5);
            let m = Measured {
                p: Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 2.0,
                n: Vec3::Z,
                footprint: 0.0,
                est: Estimate {
                    e: Vec3::splat(k.get1d(0) + 0.1),
                    harmonic: 0.1 + k.get1d(1),
                    grad_t: [Vec3::splat(k.get1d(2) - 0.5), Vec3::ZERO, Vec3::ZERO],
                    grad_r: [Vec3::ZERO; 3],
                },
            };
            assert!(c.add(&m));
            sent.push(m);
        }
        let bytes = postcard::to_allocvec(&sent).unwrap();
        assert!(bytes.len() as u64 <= 8 + sent.len() as u64 * Measured::WIRE_BYTES);
        let got: Vec<Measured> = postcard::from_bytes(&bytes).unwrap();
        let mut back = IrradianceCache::new(IrradianceParams::default(), &b);
        for m in &got {
            m.check().unwrap();
            back.add(m);
        }
        for i in 0..500u64 {
            let k = SampleKey::independent(i, 1, 5);
            let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0;
            let (x, y) = (c.interpolate(p, Vec3::Z), back.interpolate(p, Vec3::Z));
            assert_eq!(
                x.map(|v| v.to_array().map(f32::to_bits)),
                y.map(|v| v.to_array().map(f32::to_bits))
            );
        }
        let mut bad = sent[7];
        bad.est.e.x = f32::NAN;
        assert!(bad.check().is_err());
        let mut bad = sent[3];
        bad.n = Vec3::splat(2.0);
        assert!(bad.check().is_err());
        let mut bad = sent[4];
        bad.est.harmonic = -1.0;
        assert!(bad.check().is_err());
    }

    #[test]
    fn bad_parameters_are_refused() {
        let ok = IrradianceParams::default();
        assert!(ok.check().is_ok());
        for bad in [
            IrradianceParams {
                accuracy: 0.0,
                ..ok
            },
            IrradianceParams {
                accuracy: f32::NAN,
                ..ok
            },
            IrradianceParams { divisions: 4, ..ok },
            IrradianceParams {
                resolution: 0.5,
                ..ok
            },
            IrradianceParams { spacing: 12, ..ok },
            IrradianceParams {
                max_records: 0,
                ..ok
            },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn a_full_cache_refuses_records() {
        let b = Bounds::new(Vec3::ZERO, Vec3::ONE);
        let p = IrradianceParams {
            max_records: 2,
            ..Default::default()
        };
        let mut c = IrradianceCache::new(p, &b);
        let est = Estimate {
            e: Vec3::ONE,
            harmonic: 1.0,
            grad_t: [Vec3::ZERO; 3],
            grad_r: [Vec3::ZERO; 3],
        };
        assert!(c.insert(Vec3::ZERO, Vec3::Z, &est, 0.0));
        assert!(c.insert(Vec3::ONE, Vec3::Z, &est, 0.0));
        assert!(!c.insert(Vec3::splat(0.5), Vec3::Z, &est, 0.0));
        assert_eq!(c.len(), 2);
    }
}
