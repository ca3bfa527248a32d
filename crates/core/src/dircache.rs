//! The directional cache of paper 000 (sections 2.4 and 3.2): per octree
//! leaf, an adaptive quadtree over the whole sphere of directions that
//! stores the radiance arriving at the leaf from beyond its locality radius.
//!
//! # What is cached
//!
//! A continuation (diffuse) ray from a vertex in leaf `L` is traced locally
//! up to the perimeter: the sphere of radius `radius x edge(L)` around `L`'s
//! centre. A hit inside the sphere is shaded exactly. A ray that reaches the
//! perimeter asks `L`'s cache about its direction; a reliable node answers,
//! otherwise the rest of the ray is traced and its answer updates the node.
//!
//! What a node stores, and what a continuation ray that reaches the
//! perimeter returns, is the radiance arriving along the ray **without the
//! emission of the surface it hits first**: the radiance that surface
//! reflects towards the leaf (its own direct light by next-event estimation
//! plus its indirect light). Light beyond the perimeter is counted by
//! next-event estimation at the asking vertex with weight one; light inside
//! the sphere is found both ways and combined by MIS, exactly as without
//! caches ([`crate::integrator::shade`], `PathRay::emit_within`). A MIS
//! weight on the stored value would depend on the pdf at the ray's origin,
//! which differs across the leaf; with this split a cached answer counts
//! nothing twice and misses nothing, and near lights keep MIS's low noise.
//!
//! # The quadtree
//!
//! Directions map to the unit square by `u = (z + 1) / 2`, `v = phi / 2pi`
//! (Lambert's cylindrical projection, equal-area), so every node at depth
//! `d` spans `4pi / 4^d` steradians. A leaf node splits into four:
//! - first stage: when its sample count reaches `split_samples`, while its
//!   solid angle is above `fine_solid_angle`;
//! - second stage (small enough): only when it has at least `trust_samples`
//!   and its relative variance exceeds `split_rel_variance`;
//! - never below `max_depth`, nor when the leaf's or the worker's node budget
//!   is spent.
//!
//! On a split the children inherit the parent's mean with a count of one
//! (paper 000, footnote 1). A node answers when it is in the second stage
//! and holds at least [`DirCache::samples_needed`]: `answer_samples`, or
//! more where the leaf's samples are so noisy that fewer would leave the
//! standard error above `answer_rel_error` of the mean (or of
//! `answer_floor`). Its own variance only decides splitting.
//!
//! Means and variances use Welford's update in f64, stable for large means
//! with tiny variances.

use crate::geometry::{Bounds, Ray};
use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

/// The cache's settings (one per job or render). In a preset file any
/// field may be left out (the default is used); unknown ones are an error.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CacheParams {
    /// Locality radius in units of the leaf's edge length. A radius of 0.87
    /// or more contains the whole leaf.
    pub radius: f32,
    pub split_samples: u32,
    /// Solid angle (sr) below which a node enters the second stage.
    pub fine_solid_angle: f64,
    pub trust_samples: u32,
    pub split_rel_variance: f64,
    pub max_depth: u32,
    pub answer_samples: u32,
    pub answer_rel_error: f64,
    /// Radiance below which relative error is measured against this value,
    /// so dark directions (where any small error is fine) can answer.
    pub answer_floor: f64,
    /// Node budget per leaf cache and for all caches together.
    pub max_nodes_per_leaf: usize,
    pub max_nodes_total: usize,
}

impl Default for CacheParams {
    fn default() -> Self {
        Self {
            radius: 2.0,
            split_samples: 8,
            fine_solid_angle: 4.0 * PI / 64.0,
            trust_samples: 16,
            // Per-ray values of a path tracer vary by about their mean
            // (path length, light sample); only variance well above that
            // tells of directional structure worth splitting for.
            split_rel_variance: 4.0,
            max_depth: 8,
            answer_samples: 16,
            answer_rel_error: 0.2,
            answer_floor: 0.02,
            max_nodes_per_leaf: 4096,
            max_nodes_total: 2_000_000,
        }
    }
}

impl CacheParams {
    /// Checks values a user may have typed.
    pub fn check(&self) -> Result<(), String> {
        if !(self.radius.is_finite() && self.radius >= 0.0) {
            return Err(format!(
                "cache radius {} must be finite and >= 0",
                self.radius
            ));
        }
        if self.split_samples < 2 || self.trust_samples < 2 || self.answer_samples < 2 {
            return Err("cache sample thresholds must be at least 2".into());
        }
        if self.max_depth > 15 {
            return Err(format!("cache max_depth {} is above 15", self.max_depth));
        }
        for (name, v) in [
            ("fine_solid_angle", self.fine_solid_angle),
            ("split_rel_variance", self.split_rel_variance),
            ("answer_rel_error", self.answer_rel_error),
            ("answer_floor", self.answer_floor),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("cache {name} {v} must be finite and >= 0"));
            }
        }
        Ok(())
    }
}

/// The locality sphere of a leaf: its centre, and `radius` leaf edges.
pub fn locality_sphere(bounds: &Bounds, radius: f32) -> (DVec3, f64) {
    (
        bounds.center().as_dvec3(),
        radius as f64 * bounds.extent().max_element() as f64,
    )
}

/// Distance along `ray` at which it leaves `sphere`; 0 when the origin is
/// already outside it.
pub fn perimeter(sphere: (DVec3, f64), ray: &Ray) -> f32 {
    let (c, r) = sphere;
    let o = ray.origin.as_dvec3() - c;
    let d = ray.dir.as_dvec3();
    let a = d.length_squared();
    let b = o.dot(d);
    let cc = o.length_squared() - r * r;
    if cc >= 0.0 || a == 0.0 {
        return 0.0;
    }
    // cc < 0: one root ahead, one behind.
    let disc = (b * b - a * cc).max(0.0);
    ((-b + disc.sqrt()) / a) as f32
}

/// Equal-area map of a unit direction to `[0, 1)^2`.
#[inline]
pub fn dir_to_square(d: Vec3) -> [f64; 2] {
    let d = d.as_dvec3().normalize();
    let u = ((d.z + 1.0) * 0.5).clamp(0.0, 1.0 - f64::EPSILON);
    let mut phi = d.y.atan2(d.x);
    if phi < 0.0 {
        phi += 2.0 * PI;
    }
    let v = (phi / (2.0 * PI)).clamp(0.0, 1.0 - f64::EPSILON);
    [u, v]
}

/// Inverse of [`dir_to_square`].
pub fn square_to_dir(p: [f64; 2]) -> DVec3 {
    let z = 2.0 * p[0] - 1.0;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * p[1];
    DVec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Running mean (RGB) and variance (of luminance) by Welford's update.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Running {
    pub count: u32,
    pub mean: DVec3,
    /// Mean of luminance and its sum of squared deviations.
    pub lum_mean: f64,
    pub m2: f64,
}

#[inline]
fn luminance(c: DVec3) -> f64 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

impl Running {
    pub fn add(&mut self, x: DVec3) {
        self.count += 1;
        let n = self.count as f64;
        self.mean += (x - self.mean) / n;
        let l = luminance(x);
        let d = l - self.lum_mean;
        self.lum_mean += d / n;
        self.m2 += d * (l - self.lum_mean);
    }

    /// Sample variance of luminance (0 with fewer than two samples).
    pub fn variance(&self) -> f64 {
        if self.count < 2 {
            0.0
        } else {
            self.m2.max(0.0) / (self.count - 1) as f64
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Node {
    stats: Running,
    /// Index of the first of four children, or 0 for a leaf.
    first_child: u32,
}

/// One leaf's quadtree.
#[derive(Clone, Debug)]
pub struct DirCache {
    nodes: Vec<Node>,
    /// Every sample the cache took, whatever its direction: the noise
    /// level that sets how many samples a node needs before it answers.
    all: Running,
}

/// What a lookup found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Lookup {
    Answer(Vec3),
    Miss,
}

impl Default for DirCache {
    fn default() -> Self {
        Self::new()
    }
}

impl DirCache {
    pub fn new() -> Self {
        Self {
            nodes: vec![Node {
                stats: Running::default(),
                first_child: 0,
            }],
            all: Running::default(),
        }
    }

    pub fn nodes(&self) -> usize {
        self.nodes.len()
    }

    pub fn bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<Node>() + std::mem::size_of::<Self>()
    }

    /// The leaf node holding `p`, its depth and its cell.
    fn descend(&self, p: [f64; 2]) -> (usize, u32) {
        let (mut n, mut depth) = (0usize, 0u32);
        let (mut u, mut v) = (p[0], p[1]);
        while self.nodes[n].first_child != 0 {
            let (cu, cv) = ((u >= 0.5) as usize, (v >= 0.5) as usize);
            u = u * 2.0 - cu as f64;
            v = v * 2.0 - cv as f64;
            n = self.nodes[n].first_child as usize + cu + 2 * cv;
            depth += 1;
        }
        (n, depth)
    }

    fn solid_angle(depth: u32) -> f64 {
        4.0 * PI / 4f64.powi(depth as i32)
    }

    /// Samples a second-stage node needs before it answers: enough that
    /// the standard error of its mean is `answer_rel_error` of the mean,
    /// with the noise measured over all of the leaf's samples. Judging a
    /// node by its own variance would be biased: a node that happened to
    /// miss the rare bright samples looks both dark and calm, and would be
    /// frozen at a low mean.
    pub fn samples_needed(&self, p: &CacheParams) -> u32 {
        let scale = p.answer_rel_error * self.all.lum_mean.max(p.answer_floor);
        let n = if scale > 0.0 {
            (self.all.variance() / (scale * scale)).ceil()
        } else {
            f64::INFINITY
        };
        (n.min(u32::MAX as f64) as u32).max(p.answer_samples)
    }

    pub fn lookup(&self, dir: Vec3, p: &CacheParams) -> Lookup {
        let (n, depth) = self.descend(dir_to_square(dir));
        let s = &self.nodes[n].stats;
        if Self::solid_angle(depth) > p.fine_solid_angle || s.count < self.samples_needed(p) {
            return Lookup::Miss;
        }
        Lookup::Answer(s.mean.as_vec3())
    }

    /// Adds a traced answer; splits the node per the module's rules when the
    /// budgets allow (`total` counts nodes over all caches).
    pub fn update(&mut self, dir: Vec3, value: Vec3, p: &CacheParams, total: &AtomicUsize) {
        if !value.is_finite() {
            return;
        }
        let (n, depth) = self.descend(dir_to_square(dir));
        self.nodes[n].stats.add(value.as_dvec3());
        self.all.add(value.as_dvec3());
        let s = self.nodes[n].stats;
        let coarse = Self::solid_angle(depth) > p.fine_solid_angle;
        let split = if coarse {
            s.count >= p.split_samples
        } else {
            s.count >= p.trust_samples
                && s.variance() > p.split_rel_variance * s.lum_mean.max(p.answer_floor).powi(2)
        };
        if !split || depth >= p.max_depth || self.nodes.len() + 4 > p.max_nodes_per_leaf {
            return;
        }
        if total.fetch_add(4, Ordering::Relaxed) + 4 > p.max_nodes_total {
            total.fetch_sub(4, Ordering::Relaxed);
            return;
        }
        let first = self.nodes.len() as u32;
        let child = Running {
            count: 1,
            mean: s.mean,
            lum_mean: s.lum_mean,
            m2: 0.0,
        };
        for _ in 0..4 {
            self.nodes.push(Node {
                stats: child,
                first_child: 0,
            });
        }
        self.nodes[n].first_child = first;
    }
}

/// Counters of cache use, summed over rays.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CacheStats {
    /// Continuation rays that hit inside the locality sphere.
    pub local: u64,
    /// Rays that reached the perimeter and were traced beyond it.
    pub global: u64,
    /// Rays that reached the perimeter and were answered by the cache.
    pub lookups: u64,
    /// Of all these, the rays whose locality sphere went on in another
    /// worker's region as a segment query (the farm only): they are
    /// counted local where they hit, or global or a lookup at home when
    /// they got beyond.
    #[serde(default)]
    pub segments: u64,
}

impl std::ops::AddAssign for CacheStats {
    fn add_assign(&mut self, o: Self) {
        self.local += o.local;
        self.global += o.global;
        self.lookups += o.lookups;
        self.segments += o.segments;
    }
}

impl CacheStats {
    /// Lookups over rays that reached the perimeter (paper 000, Table 3).
    pub fn hit_ratio(&self) -> f64 {
        let p = self.global + self.lookups;
        if p == 0 {
            0.0
        } else {
            self.lookups as f64 / p as f64
        }
    }
}

/// The caches of a set of octree leaves, created on first use.
pub struct LeafCaches {
    pub params: CacheParams,
    caches: Vec<Mutex<Option<DirCache>>>,
    nodes: AtomicUsize,
}

/// Memory a set of caches holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CacheMemory {
    pub leaves_with_cache: u64,
    pub nodes: u64,
    pub bytes: u64,
    pub max_leaf_bytes: u64,
}

impl LeafCaches {
    pub fn new(leaves: usize, params: CacheParams) -> Self {
        Self {
            params,
            caches: (0..leaves).map(|_| Mutex::new(None)).collect(),
            nodes: AtomicUsize::new(0),
        }
    }

    pub fn lookup(&self, leaf: u32, dir: Vec3) -> Lookup {
        let Some(m) = self.caches.get(leaf as usize) else {
            return Lookup::Miss;
        };
        let g = m.lock().unwrap_or_else(|e| e.into_inner());
        match g.as_ref() {
            Some(c) => c.lookup(dir, &self.params),
            None => Lookup::Miss,
        }
    }

    /// A continuation ray from `leaf` along `dir` that reached its
    /// perimeter: the cache's answer (counted a lookup), or None (counted a
    /// global ray, which the caller traces on from the perimeter and whose
    /// radiance then updates this cache). One machine and a farm worker,
    /// whichever finds the ray at its perimeter, decide here.
    pub fn at_perimeter(&self, leaf: u32, dir: Vec3, st: &mut CacheStats) -> Option<Vec3> {
        match self.lookup(leaf, dir) {
            Lookup::Answer(v) => {
                st.lookups += 1;
                Some(v)
            }
            Lookup::Miss => {
                st.global += 1;
                None
            }
        }
    }

    pub fn update(&self, leaf: u32, dir: Vec3, value: Vec3) {
        let Some(m) = self.caches.get(leaf as usize) else {
            return;
        };
        let mut g = m.lock().unwrap_or_else(|e| e.into_inner());
        let c = g.get_or_insert_with(|| {
            self.nodes.fetch_add(1, Ordering::Relaxed);
            DirCache::new()
        });
        c.update(dir, value, &self.params, &self.nodes);
    }

    pub fn memory(&self) -> CacheMemory {
        let mut m = CacheMemory::default();
        for c in &self.caches {
            let g = c.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(c) = g.as_ref() {
                m.leaves_with_cache += 1;
                m.nodes += c.nodes() as u64;
                m.bytes += c.bytes() as u64;
                m.max_leaf_bytes = m.max_leaf_bytes.max(c.bytes() as u64);
            }
        }
        m.bytes += (self.caches.len() * std::mem::size_of::<Mutex<Option<DirCache>>>()) as u64;
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equal_area_map_round_trips() {
        let mut worst: f64 = 0.0;
        for i in 0..2000u32 {
            let p = [
                (i as f64 * 0.618_033_988_7).fract(),
                (i as f64 * 0.754_877_666_2).fract(),
            ];
            let d = square_to_dir(p);
            let q = dir_to_square(d.as_vec3());
            let back = square_to_dir(q);
            worst = worst.max((back - d).length());
        }
        // f32 directions: the round trip is good to f32 precision.
        assert!(worst < 1e-5, "worst round-trip error {worst}");
        // Poles and the seam map inside the square.
        for d in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            -Vec3::X,
            Vec3::new(1.0, -1e-30, 0.0),
        ] {
            let q = dir_to_square(d);
            assert!(
                (0.0..1.0).contains(&q[0]) && (0.0..1.0).contains(&q[1]),
                "{d:?} -> {q:?}"
            );
        }
    }

    #[test]
    fn equal_area_cells_get_equal_shares_of_uniform_directions() {
        // Uniform directions on the sphere (z uniform, phi uniform) fall
        // evenly into the 16 cells of depth 2: a chi-square check.
        let n = 64_000u32;
        let mut counts = [0u32; 16];
        for i in 0..n {
            let z = 2.0 * ((i as f64 + 0.5) / n as f64) - 1.0;
            let phi = 2.0 * PI * (i as f64 * 0.618_033_988_7).fract();
            let r = (1.0 - z * z).sqrt();
            let d = Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
            let [u, v] = dir_to_square(d);
            counts[(u * 4.0) as usize + 4 * (v * 4.0) as usize] += 1;
        }
        let e = n as f64 / 16.0;
        let chi2: f64 = counts.iter().map(|&c| (c as f64 - e).powi(2) / e).sum();
        // 15 degrees of freedom: 99.9% quantile is 37.7.
        assert!(chi2 < 37.7, "chi2 {chi2}, counts {counts:?}");
    }

    #[test]
    fn welford_matches_two_pass_on_adversarial_values() {
        // Large means with tiny variances: the naive sum of squares loses
        // every digit here.
        for (base, spread) in [(1e6, 1e-3), (1e9, 1.0), (3.0, 1e-9), (0.0, 1.0)] {
            let xs: Vec<f64> = (0..1000)
                .map(|i| base + spread * ((i * 7919 % 1000) as f64 / 1000.0 - 0.5))
                .collect();
            let mut r = Running::default();
            for &x in &xs {
                // Luminance weights sum to one, so a grey value's luminance
                // is the value itself.
                r.add(DVec3::splat(x));
            }
            let mean = xs.iter().sum::<f64>() / xs.len() as f64;
            let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (xs.len() - 1) as f64;
            let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-300);
            assert!(
                rel(r.lum_mean, mean) < 1e-12,
                "mean {} vs {mean}",
                r.lum_mean
            );
            assert!(
                rel(r.variance(), var) < 1e-6,
                "variance {} vs {var} (base {base})",
                r.variance()
            );
            let naive = xs.iter().map(|x| x * x).sum::<f64>() / xs.len() as f64 - mean * mean;
            if base >= 1e6 {
                // The naive formula is what we avoid: show it fails here.
                assert!(rel(naive * 1000.0 / 999.0, var) > 1e-3);
            }
        }
    }

    fn params() -> CacheParams {
        CacheParams {
            split_samples: 4,
            fine_solid_angle: 4.0 * PI / 16.0,
            trust_samples: 8,
            split_rel_variance: 0.1,
            max_depth: 4,
            answer_samples: 8,
            answer_rel_error: 0.05,
            ..CacheParams::default()
        }
    }

    #[test]
    fn first_stage_splits_on_count_and_children_inherit_the_mean() {
        let p = params();
        let total = AtomicUsize::new(0);
        let mut c = DirCache::new();
        let d = Vec3::new(0.3, 0.2, 0.9).normalize();
        for _ in 0..3 {
            c.update(d, Vec3::ONE, &p, &total);
        }
        assert_eq!(c.nodes(), 1, "no split before split_samples");
        c.update(d, Vec3::ONE, &p, &total);
        assert_eq!(c.nodes(), 5, "split at split_samples");
        let (n, depth) = c.descend(dir_to_square(d));
        assert_eq!(depth, 1);
        assert_eq!(c.nodes[n].stats.count, 1);
        assert_eq!(c.nodes[n].stats.mean, DVec3::ONE);
        // Depth 2 is 4pi/16: the second stage; a constant signal never
        // splits there however many samples come.
        for _ in 0..100 {
            c.update(d, Vec3::ONE, &p, &total);
        }
        let (_, depth) = c.descend(dir_to_square(d));
        assert_eq!(depth, 2);
        assert_eq!(c.lookup(d, &p), Lookup::Answer(Vec3::ONE));
        // Other directions have not been sampled: no answer there.
        assert_eq!(c.lookup(-d, &p), Lookup::Miss);
    }

    #[test]
    fn second_stage_splits_only_on_trusted_high_variance_and_respects_depth() {
        let p = params();
        let total = AtomicUsize::new(0);
        let mut c = DirCache::new();
        let d = Vec3::new(-0.5, 0.4, -0.2).normalize();
        // Drive to the second stage with a constant value.
        for _ in 0..8 {
            c.update(d, Vec3::splat(2.0), &p, &total);
        }
        let before = c.nodes();
        let (_, depth) = c.descend(dir_to_square(d));
        assert_eq!(depth, 2);
        // The depth-2 node holds 2 samples (one inherited, one added). High
        // variance, but fewer than trust_samples (8) in it: no split.
        assert_eq!(c.nodes[c.descend(dir_to_square(d)).0].stats.count, 2);
        for i in 0..5 {
            c.update(
                d,
                Vec3::splat(if i % 2 == 0 { 0.0 } else { 4.0 }),
                &p,
                &total,
            );
        }
        assert_eq!(c.nodes(), before);
        assert_eq!(
            c.lookup(d, &p),
            Lookup::Miss,
            "7 samples are not enough to answer"
        );
        // Enough samples and still noisy: splits, down to max_depth only.
        for i in 0..10_000 {
            c.update(
                d,
                Vec3::splat(if i % 2 == 0 { 0.0 } else { 4.0 }),
                &p,
                &total,
            );
        }
        let (_, depth) = c.descend(dir_to_square(d));
        assert_eq!(depth, p.max_depth);
        // At max_depth the noisy node keeps averaging; with thousands of
        // samples its standard error is small and it answers with the mean.
        match c.lookup(d, &p) {
            Lookup::Answer(v) => assert!((v.x - 2.0).abs() < 0.1, "{v:?}"),
            Lookup::Miss => panic!("a well-sampled node must answer"),
        }
    }

    #[test]
    fn node_budgets_hold() {
        let p = CacheParams {
            max_nodes_per_leaf: 41,
            max_nodes_total: 1000,
            ..params()
        };
        let total = AtomicUsize::new(0);
        let mut c = DirCache::new();
        for i in 0..20_000u32 {
            let d = square_to_dir([
                (i as f64 * 0.618_033_988_7).fract(),
                (i as f64 * 0.754_877_666_2).fract(),
            ]);
            c.update(d.as_vec3(), Vec3::splat((i % 3) as f32), &p, &total);
        }
        assert!(c.nodes() <= 41, "{} nodes", c.nodes());
        let p2 = CacheParams {
            max_nodes_total: 30,
            ..params()
        };
        let caches = LeafCaches::new(8, p2);
        for leaf in 0..8 {
            for i in 0..2000u32 {
                let d = square_to_dir([
                    (i as f64 * 0.618_033_988_7).fract(),
                    (i as f64 * 0.754_877_666_2).fract(),
                ]);
                caches.update(leaf, d.as_vec3(), Vec3::splat((i % 3) as f32));
            }
        }
        // Roots are always allowed; splits stop at the worker's budget.
        let m = caches.memory();
        assert_eq!(m.leaves_with_cache, 8);
        assert!(m.nodes <= 30 + 8, "{} nodes", m.nodes);
    }

    #[test]
    fn perimeter_is_where_the_ray_leaves_the_sphere() {
        let b = Bounds::new(Vec3::ZERO, Vec3::ONE);
        let sphere = locality_sphere(&b, 2.0);
        // Centre (0.5,0.5,0.5), radius 2: from the centre along +x, 2.
        let r = Ray::new(Vec3::splat(0.5), Vec3::X);
        assert!((perimeter(sphere, &r) - 2.0).abs() < 1e-6);
        // Origin outside the sphere: the perimeter is at the origin.
        let r = Ray::new(Vec3::new(10.0, 0.5, 0.5), -Vec3::X);
        assert_eq!(perimeter(sphere, &r), 0.0);
    }
}
