//! A record's hemisphere: `M x N` strata, uniform in `sin^2 theta` (so each
//! holds an equal share of the cosine-weighted hemisphere) and in `phi`;
//! one jittered ray per stratum. From the radiance and the first-hit
//! distance of each ray this computes the irradiance, the harmonic mean
//! distance of the surfaces around, and Ward and Heckbert's (1992)
//! rotational and translational gradients, in the form for
//! cosine-distributed strata that Křivánek et al. give ("Practical Global
//! Illumination with Irradiance Caching", 2009, eq. 2.x) with the
//! `cos theta` factor of the corrected `v`-term.

use crate::geometry::{basis, sin_cos_turns};
use glam::Vec3;
use std::f32::consts::PI;

/// How a record's rays are split: `m` strata in theta, `n` in phi, with
/// `n` about `pi m` as in Radiance, so strata are about square.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Strata {
    pub m: u32,
    pub n: u32,
}

impl Strata {
    /// About `divisions` rays (Radiance's `-ad`), at least 2 x 3.
    pub fn of(divisions: u32) -> Self {
        let m = ((divisions as f32 / PI).sqrt().round() as u32).max(2);
        let n = (divisions / m).max(3);
        Self { m, n }
    }

    pub fn rays(&self) -> u32 {
        self.m * self.n
    }
}

/// A record's tangent frame about its normal `ns`.
#[derive(Clone, Copy, Debug)]
pub struct Hemisphere {
    pub strata: Strata,
    pub t: Vec3,
    pub b: Vec3,
    pub ns: Vec3,
}

/// What one stratum's ray found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub radiance: Vec3,
    /// Distance to the first surface; infinite for a ray that escaped or
    /// that was not cast (below the surface).
    pub dist: f32,
}

/// Irradiance, harmonic mean distance and gradients at one point.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Estimate {
    pub e: Vec3,
    pub harmonic: f32,
    /// d E / d axis, per world axis (x, y, z), as RGB.
    pub grad_t: [Vec3; 3],
    /// The rotational gradient per world axis, as RGB: a normal turned by
    /// the small rotation vector `w` changes E by `sum_i w_i grad_r[i]`.
    pub grad_r: [Vec3; 3],
}

/// The mean of `tan theta` over theta stratum `j` of `m` (uniform in
/// `s = sin^2 theta`, where its integral is `asin(sqrt s) - sqrt(s (1 - s))`).
/// Ward and Heckbert take its value at the stratum's centre, which misses
/// a third of the last stratum's share: 6% of the rotational gradient at
/// 36 strata.
fn mean_tan(j: u32, m: f32) -> f32 {
    let f = |s: f32| s.sqrt().asin() - (s * (1.0 - s)).max(0.0).sqrt();
    let (s0, s1) = (j as f32 / m, ((j + 1) as f32 / m).min(1.0));
    (f(s1) - f(s0)) * m
}

impl Hemisphere {
    pub fn new(ns: Vec3, strata: Strata) -> Self {
        let (t, b) = basis(ns);
        Self { strata, t, b, ns }
    }

    /// The unit direction in the tangent plane at azimuth `turns` (of a
    /// full turn): records are the same bits on every processor (see
    /// [`crate::geometry::sin_cos_turns`]).
    fn planar(&self, turns: f32) -> Vec3 {
        let (s, c) = sin_cos_turns(turns);
        self.t * c + self.b * s
    }

    /// The direction of stratum `(j, k)` jittered by `u`.
    pub fn direction(&self, j: u32, k: u32, u: [f32; 2]) -> Vec3 {
        let Strata { m, n } = self.strata;
        let s2 = ((j as f32 + u[0]) / m as f32).min(1.0);
        let (sin, cos) = (s2.sqrt(), (1.0 - s2).max(0.0).sqrt());
        let turns = (k as f32 + u[1]) / n as f32;
        (self.planar(turns) * sin + self.ns * cos).normalize()
    }

    /// The estimate from `samples[j * n + k]`.
    pub fn estimate(&self, samples: &[Sample]) -> Estimate {
        let Strata { m, n } = self.strata;
        assert_eq!(samples.len(), (m * n) as usize);
        let at = |j: u32, k: u32| &samples[(j * n + k) as usize];
        let (mf, nf) = (m as f32, n as f32);
        let mut e = Vec3::ZERO;
        let mut inv_dist = 0.0f32;
        let mut grad_r = [Vec3::ZERO; 3];
        let mut grad_t = [Vec3::ZERO; 3];
        let add = |g: &mut [Vec3; 3], dir: Vec3, v: Vec3| {
            for (a, ga) in g.iter_mut().enumerate() {
                *ga += v * dir[a];
            }
        };
        for k in 0..n {
            let u_k = self.planar((k as f32 + 0.5) / nf);
            // A quarter turn on from `u_k` about the normal, whichever
            // handedness `basis` gives the tangent frame.
            let v_k = self.ns.cross(u_k);
            let v_minus = self.ns.cross(self.planar(k as f32 / nf));
            let kp = (k + n - 1) % n;
            for j in 0..m {
                let s = at(j, k);
                e += s.radiance;
                if s.dist.is_finite() && s.dist > 0.0 {
                    inv_dist += 1.0 / s.dist;
                }
                let sin2_minus = j as f32 / mf;
                let sin2_c = (j as f32 + 0.5) / mf;
                let (sin_c, cos_c) = (sin2_c.sqrt(), (1.0 - sin2_c).sqrt());
                // Turning the normal towards `u_k` (a rotation about
                // `v_k`) brings this stratum's light nearer the normal.
                add(&mut grad_r, v_k, s.radiance * mean_tan(j, mf));
                // Across the theta boundary below this stratum.
                if j > 0 {
                    let o = at(j - 1, k);
                    let d = s.dist.min(o.dist);
                    if d.is_finite() && d > 0.0 {
                        let (sin_m, cos2_m) = (sin2_minus.sqrt(), 1.0 - sin2_minus);
                        let f = 2.0 * PI * sin_m * cos2_m / (nf * d);
                        add(&mut grad_t, u_k, (s.radiance - o.radiance) * f);
                    }
                }
                // Across the phi boundary before this stratum.
                let o = at(j, kp);
                let d = s.dist.min(o.dist);
                if d.is_finite() && d > 0.0 {
                    let cos_minus = (1.0 - sin2_minus).sqrt();
                    let cos_plus = (1.0 - (j as f32 + 1.0) / mf).max(0.0).sqrt();
                    let f = cos_c * (cos_minus - cos_plus) / (sin_c * d);
                    add(&mut grad_t, v_minus, (s.radiance - o.radiance) * f);
                }
            }
        }
        let w = PI / (mf * nf);
        Estimate {
            e: e * w,
            harmonic: if inv_dist > 0.0 {
                mf * nf / inv_dist
            } else {
                f32::INFINITY
            },
            grad_t,
            grad_r: grad_r.map(|g| g * w),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strata_split_the_divisions_about_square() {
        for d in [16u32, 64, 256, 1024, 4096] {
            let s = Strata::of(d);
            let r = s.rays() as f32 / d as f32;
            assert!((0.8..=1.2).contains(&r), "{d}: {s:?}");
            let aspect = s.n as f32 / (PI * s.m as f32);
            assert!((0.6..=1.6).contains(&aspect), "{d}: {s:?}");
        }
    }

    /// Radiance `L(w) = a + b . w` from infinitely far: irradiance about
    /// `ns` is `pi a + (2 pi / 3) b . ns`, so turning the normal to `n2`
    /// changes it by `(2 pi / 3) b . (n2 - ns)`, which the rotational
    /// gradient predicts as `(ns x n2) . grad_r`; nothing is near, so the
    /// translational gradient is zero and the harmonic mean infinite.
    #[test]
    fn irradiance_and_rotational_gradient_of_a_linear_sky() {
        let ns = Vec3::new(0.3, 0.4, 0.866).normalize();
        let h = Hemisphere::new(ns, Strata::of(4096));
        let (a, b) = (1.0f32, Vec3::new(0.5, -0.3, 0.4));
        let Strata { m, n } = h.strata;
        let mut samples = Vec::new();
        for j in 0..m {
            for k in 0..n {
                let d = h.direction(j, k, [0.5, 0.5]);
                samples.push(Sample {
                    radiance: Vec3::splat(a + b.dot(d)),
                    dist: f32::INFINITY,
                });
            }
        }
        let est = h.estimate(&samples);
        let want = PI * a + 2.0 * PI / 3.0 * b.dot(ns);
        assert!(
            (est.e.x - want).abs() < 2e-3 * want,
            "{} vs {want}",
            est.e.x
        );
        for w in [Vec3::X, Vec3::Y, Vec3::Z, Vec3::new(1.0, -2.0, 0.5)] {
            let n2 = (ns + 0.02 * w.cross(ns)).normalize();
            let rot = ns.cross(n2);
            let got: f32 = (0..3).map(|i| rot[i] * est.grad_r[i].x).sum();
            let want = 2.0 * PI / 3.0 * b.dot(n2 - ns);
            assert!(
                (got - want).abs() < 0.05 * want.abs() + 1e-4,
                "{w}: {got} vs {want}"
            );
        }
        assert!(
            est.grad_t.iter().all(|g| *g == Vec3::ZERO),
            "{:?}",
            est.grad_t
        );
        assert!(est.harmonic.is_infinite());
    }

    /// The hemisphere of a point on the floor `z = 0` facing a wall of
    /// radiance 1 in the plane `x = d`, of height `height`, under a black
    /// sky.
    fn wall(h: &Hemisphere, d: f32, height: f32) -> Estimate {
        let Strata { m, n } = h.strata;
        let mut samples = Vec::new();
        for j in 0..m {
            for k in 0..n {
                let w = h.direction(j, k, [0.5, 0.5]);
                let t = if w.x > 0.0 { d / w.x } else { f32::INFINITY };
                let hits = t.is_finite() && t * w.z < height;
                samples.push(if hits {
                    Sample {
                        radiance: Vec3::ONE,
                        dist: t,
                    }
                } else {
                    Sample {
                        radiance: Vec3::ZERO,
                        dist: f32::INFINITY,
                    }
                });
            }
        }
        h.estimate(&samples)
    }

    /// Moving towards the wall, the irradiance grows as the finite
    /// difference of two records says; the translational gradient agrees
    /// (within the first-order error of Ward and Heckbert's estimate).
    #[test]
    fn translational_gradient_follows_a_wall() {
        let h = Hemisphere::new(Vec3::Z, Strata::of(4096));
        // The reference integrates finely enough that a stratum's step
        // across the wall's edge is far below the difference.
        let fine = Hemisphere::new(Vec3::Z, Strata::of(1 << 20));
        for (d, height) in [(1.0f32, 1.0f32), (0.5, 2.0), (2.0, 0.7)] {
            let dx = 0.05 * d;
            let (near, far) = (wall(&fine, d - dx, height), wall(&fine, d + dx, height));
            let fd = (near.e.x - far.e.x) / (2.0 * dx);
            let here = wall(&h, d, height);
            let g = here.grad_t[0].x;
            assert!(fd > 0.0, "{fd}");
            assert!(
                (g - fd).abs() < 0.15 * fd,
                "d {d}, height {height}: gradient {g} vs {fd}"
            );
            // Along the wall nothing changes.
            assert!(here.grad_t[1].x.abs() < 0.05 * fd, "{:?}", here.grad_t);
        }
    }
}
