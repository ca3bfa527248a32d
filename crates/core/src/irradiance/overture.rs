//! Placing the records before the render, coarse to fine.
//!
//! Level `s` looks at the pixel centres on a grid of spacing `s` (from the
//! coarsest spacing down to 1, halving, each level skipping the points
//! the coarser ones looked at). A point whose camera ray hits a diffuse
//! surface that the records of the *coarser* levels do not cover gets a
//! record. So the records a level adds depend only on the levels before
//! it, all of a level's records are measured in parallel, and the set of
//! records is the same for any number of threads. Points of one level can
//! both get a record where one would have done; the finer levels then
//! find them covered, so the waste stays at the coarse levels where
//! points are few.
//!
//! Because a level's records depend only on the levels before it, a farm
//! shares the overture out level by level ([`run`] with a [`Share`]):
//! every member finds the same candidates, measures those [`measurer`]
//! gives it, and the level's [`Measured`] points, every member's merged in
//! candidate order, come back to all of them; each adds them in that order
//! and so holds the same cache as one machine.

use super::IrradianceCache;
use super::hemisphere::{Hemisphere, Sample, Strata};
use crate::geometry::Bounds;
use crate::integrator::{Frame, PathRay, vertex_dim};
use crate::path::{Kernel, RayKind, Traced, Tracer};
use crate::region::Resume;
use crate::sampler::SampleKey;
use crate::stats::TraceStats;
use glam::Vec3;
use serde::{Deserialize, Serialize};
use std::f32::consts::PI;
use std::time::Instant;

/// Mixed into the job seed for records' rays, so they share no random
/// numbers with the camera samples of the same pixel.
const RECORD_SALT: u64 = 0x1aad_ca5e_0000_0001;

/// What building the cache did.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct OvertureStats {
    pub records: u64,
    /// Pixel centres looked at.
    pub points: u64,
    /// Points a record would have covered but `max_records` was reached.
    pub refused: u64,
    pub levels: u32,
    /// Every ray traced to place and measure the records.
    pub trace: TraceStats,
    pub seconds: f64,
    /// Bytes the records and their octree hold.
    pub bytes: u64,
}

/// A point that needs a record: its pixel, frame, and the width of a
/// pixel there.
struct Candidate {
    pixel: u64,
    frame: Frame,
    footprint: f32,
}

/// A point measured for a record: where it lies, about which shading
/// normal, the width of its pixel there, and what its rays found. Any
/// machine that adds the same measurements in the same order holds the
/// same records ([`IrradianceCache::add`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measured {
    pub p: Vec3,
    pub n: Vec3,
    pub footprint: f32,
    pub est: super::hemisphere::Estimate,
}

impl Measured {
    /// Bytes one takes on the wire (postcard writes an f32 as 4 bytes).
    pub const WIRE_BYTES: u64 = 4 * (3 + 3 + 1 + 3 + 1 + 2 * 9);

    /// Checks a measurement a peer sent: finite, a unit normal, and no
    /// negative distance or footprint.
    pub fn check(&self) -> Result<(), String> {
        let e = &self.est;
        let ok = self.p.is_finite()
            && (self.n.length() - 1.0).abs() < 1e-3
            && self.footprint.is_finite()
            && self.footprint >= 0.0
            && e.e.is_finite()
            && e.grad_t.iter().chain(&e.grad_r).all(|g| g.is_finite())
            // Infinite (every ray escaped) and NaN are clamped on adding.
            && (e.harmonic >= 0.0 || e.harmonic.is_nan());
        if ok {
            Ok(())
        } else {
            Err("an irradiance measurement is not finite or not normalised".into())
        }
    }
}

impl IrradianceCache {
    /// Adds the record `m` measures; false when the cache is full.
    pub fn add(&mut self, m: &Measured) -> bool {
        self.insert(m.p, m.n, &m.est, m.footprint)
    }
}

/// The member that measures candidate `i` of a level, members weighted by
/// `shares` (their threads): a weighted round robin, so that every
/// member's candidates spread over the whole image and cost alike.
pub fn measurer(i: u32, shares: &[u32]) -> usize {
    let total: u64 = shares.iter().map(|&s| s.max(1) as u64).sum();
    let mut slot = i as u64 % total.max(1);
    for (w, &s) in shares.iter().enumerate() {
        let s = s.max(1) as u64;
        if slot < s {
            return w;
        }
        slot -= s;
    }
    0
}

/// The spacing of each of the overture's levels, coarsest first.
pub fn level_spacings(params: &super::IrradianceParams) -> Vec<u32> {
    let mut v = vec![params.spacing.max(1)];
    while let Some(&s) = v.last().filter(|&&s| s > 1) {
        v.push(s / 2);
    }
    v
}

/// How one member takes part in an overture: it is member `me` of those
/// weighted by `shares`, and measures its candidates from level `resume`
/// on (the levels before are known and only received).
#[derive(Clone, Copy, Debug)]
pub struct Share<'a> {
    pub me: usize,
    pub shares: &'a [u32],
    pub resume: u32,
}

impl Share<'_> {
    /// One machine: it measures every level.
    pub const ALONE: Share<'static> = Share {
        me: 0,
        shares: &[1],
        resume: 0,
    };
}

/// The camera ray through the centre of pixel `(x, y)`: the frame of its
/// first hit where that vertex scatters diffusely, and the width of a
/// pixel at that distance.
fn centre_frame<T: Tracer>(
    kernel: &Kernel,
    tracer: &T,
    x: u32,
    y: u32,
    st: &mut TraceStats,
) -> Option<(Frame, f32)> {
    let ray = kernel.camera.ray(x, y, [0.5, 0.5]);
    st.camera_rays += 1;
    let t = tracer.trace(
        &ray,
        f32::INFINITY,
        Resume::START,
        false,
        RayKind::Camera,
        st,
    );
    let Traced::Hit(h) = t else { return None };
    let mat = &kernel.materials[h.material as usize];
    if kernel.max_depth == 0 || mat.albedo.max_element() <= 0.0 {
        return None;
    }
    let cam = kernel.camera;
    let pixel_angle = 2.0 * (cam.fov_y.to_radians() * 0.5).tan() / cam.height.max(1) as f32;
    let f = Frame::at(ray.dir, &h.verts, &h.hit, h.shading);
    // A pixel seen at a slant covers more of the surface.
    let slant = f.n.dot(-ray.dir).max(0.1);
    Some((f, h.hit.t * pixel_angle / slant))
}

/// Measures the record at `c`: one jittered ray per stratum, each traced
/// as a path whose first hit's emission is left to next-event estimation.
fn measure<T: Tracer>(
    kernel: &Kernel,
    tracer: &T,
    c: &Candidate,
    strata: Strata,
    st: &mut TraceStats,
) -> super::hemisphere::Estimate {
    let f = &c.frame;
    let h = Hemisphere::new(f.ns, strata);
    let mut chain = Vec::new();
    let mut samples = Vec::with_capacity(strata.rays() as usize);
    for j in 0..strata.m {
        for k in 0..strata.n {
            let sample = j * strata.n + k;
            let key = SampleKey::new(c.pixel, sample, kernel.seed ^ RECORD_SALT, kernel.sampler);
            let dir = h.direction(j, k, key.get2d(vertex_dim(1) + 3));
            let cos = f.ns.dot(dir);
            // Below the geometric surface (a shading normal leans past
            // it): the continuation would end there, as in `shade`.
            if cos <= 0.0 || (f.shaded && f.n.dot(dir) <= 0.0) {
                samples.push(Sample {
                    radiance: Vec3::ZERO,
                    dist: f32::INFINITY,
                });
                continue;
            }
            let q = PathRay {
                ray: crate::geometry::Ray::new(f.origin, dir),
                key,
                depth: 1,
                prev_pdf: cos / PI,
                beta: Vec3::ONE,
                emit_within: 0.0,
            };
            let (l, dist) = kernel.first_hit(tracer, &q, &mut chain, st);
            let l = if l.is_finite() { l } else { Vec3::ZERO };
            samples.push(Sample { radiance: l, dist });
        }
    }
    h.estimate(&samples)
}

/// Builds the cache for a whole scene held in memory (the farm's
/// scheduler, which has every triangle, when its workers do not): one BVH
/// over the scene exactly as one machine builds it, and the kernel the
/// scene's settings give, so the records are the ones a render on one
/// machine makes. The levels in `known` (measured before, by anyone) are
/// taken as they are; every level's measurements are returned, to be sent
/// to the workers.
pub fn for_scene(
    scene: &crate::scene::Scene,
    lights: &crate::light::LightSet,
    params: super::IrradianceParams,
    known: &[Vec<Measured>],
) -> (IrradianceCache, OvertureStats, Vec<Vec<Measured>>) {
    let accel = crate::render::whole_scene_accel(scene);
    let kernel = Kernel::exact(
        &scene.materials,
        lights,
        &scene.camera,
        scene.settings.seed,
        scene.settings.sampler,
        scene.settings.max_depth,
    );
    let bounds = Bounds::of_triangles(&scene.tris);
    let share = Share {
        resume: known.len() as u32,
        ..Share::ALONE
    };
    let mut levels = Vec::new();
    let mut keep = |level: u32, mine: Vec<(u32, Measured)>, _: &TraceStats| {
        let l = match known.get(level as usize) {
            Some(k) => k.clone(),
            None => mine.into_iter().map(|(_, m)| m).collect(),
        };
        levels.push(l.clone());
        Ok::<_, std::convert::Infallible>(l)
    };
    let tracer = crate::path::WholeScene(&accel);
    let (cache, stats) = match run(&kernel, &tracer, params, &bounds, share, &mut keep) {
        Ok(r) => r,
        Err(e) => match e {},
    };
    (cache, stats, levels)
}

/// The irradiance at `frame` measured as a record would be, with about
/// `divisions` rays keyed by `pixel`: what interpolation is compared with.
pub fn traced<T: Tracer>(
    kernel: &Kernel,
    tracer: &T,
    frame: &Frame,
    pixel: u64,
    divisions: u32,
    st: &mut TraceStats,
) -> super::hemisphere::Estimate {
    let c = Candidate {
        pixel,
        frame: *frame,
        footprint: 0.0,
    };
    measure(kernel, tracer, &c, Strata::of(divisions), st)
}

/// The points of level `s` (`first`: the coarsest, which takes all).
fn level_points(width: u32, height: u32, s: u32, first: bool) -> Vec<(u32, u32)> {
    let mut v = Vec::new();
    for y in (0..height).step_by(s as usize) {
        for x in (0..width).step_by(s as usize) {
            if first || x % (2 * s) != 0 || y % (2 * s) != 0 {
                v.push((x, y));
            }
        }
    }
    v
}

/// The points whose first hit scatters diffusely where `cache` has no
/// record valid, in the order of `points`.
fn uncovered<T: Tracer + Sync>(
    kernel: &Kernel,
    tracer: &T,
    cache: &IrradianceCache,
    points: &[(u32, u32)],
    trace: &mut TraceStats,
) -> Vec<Candidate> {
    use rayon::prelude::*;
    let w = kernel.camera.width as u64;
    let found: Vec<(Option<Candidate>, TraceStats)> = points
        .par_iter()
        .map(|&(x, y)| {
            let mut st = TraceStats::default();
            let c = centre_frame(kernel, tracer, x, y, &mut st)
                .filter(|(f, _)| cache.interpolate(f.p, f.ns).is_none())
                .map(|(frame, footprint)| Candidate {
                    pixel: y as u64 * w + x as u64,
                    frame,
                    footprint,
                });
            (c, st)
        })
        .collect();
    let mut candidates = Vec::new();
    for (c, st) in found {
        *trace += st;
        candidates.extend(c);
    }
    candidates
}

/// Builds the cache for `kernel`'s camera on the calling rayon pool, alone.
/// `kernel` must have no irradiance cache of its own.
pub fn build<T: Tracer + Sync>(
    kernel: &Kernel,
    tracer: &T,
    params: super::IrradianceParams,
    bounds: &Bounds,
) -> (IrradianceCache, OvertureStats) {
    let alone = |_: u32, mine: Vec<(u32, Measured)>, _: &TraceStats| {
        Ok::<_, std::convert::Infallible>(mine.into_iter().map(|(_, m)| m).collect())
    };
    match run(kernel, tracer, params, bounds, Share::ALONE, alone) {
        Ok(r) => r,
        Err(e) => match e {},
    }
}

/// Runs the overture as one member of `share`: level by level, finds the
/// candidates and measures its own (from `share.resume` on), hands them to
/// `exchange` with the rays that measuring them traced, and adds what
/// `exchange` returns: the level's measurements of every member, in
/// candidate order. An error from `exchange` ends it.
pub fn run<T: Tracer + Sync, E>(
    kernel: &Kernel,
    tracer: &T,
    params: super::IrradianceParams,
    bounds: &Bounds,
    share: Share,
    mut exchange: impl FnMut(u32, Vec<(u32, Measured)>, &TraceStats) -> Result<Vec<Measured>, E>,
) -> Result<(IrradianceCache, OvertureStats), E> {
    use rayon::prelude::*;
    let start = Instant::now();
    let mut cache = IrradianceCache::new(params, bounds);
    let mut stats = OvertureStats::default();
    let strata = Strata::of(params.divisions);
    let (w, h) = (kernel.camera.width, kernel.camera.height);
    for (k, &s) in level_spacings(&params).iter().enumerate() {
        let level = k as u32;
        stats.levels += 1;
        let mut mine = Vec::new();
        let mut level_trace = TraceStats::default();
        if level >= share.resume {
            let points = level_points(w, h, s, k == 0);
            stats.points += points.len() as u64;
            let mut candidates = uncovered(kernel, tracer, &cache, &points, &mut level_trace);
            let room = params.max_records.saturating_sub(cache.len());
            stats.refused += candidates.len().saturating_sub(room) as u64;
            candidates.truncate(room);
            let own: Vec<(u32, &Candidate)> = (0u32..)
                .zip(&candidates)
                .filter(|(i, _)| measurer(*i, share.shares) == share.me)
                .collect();
            let measured: Vec<_> = own
                .par_iter()
                .map(|&(i, c)| {
                    let mut st = TraceStats::default();
                    let est = measure(kernel, tracer, c, strata, &mut st);
                    let m = Measured {
                        p: c.frame.p,
                        n: c.frame.ns,
                        footprint: c.footprint,
                        est,
                    };
                    ((i, m), st)
                })
                .collect();
            for (m, st) in measured {
                level_trace += st;
                mine.push(m);
            }
        }
        stats.trace += level_trace;
        for m in exchange(level, mine, &level_trace)? {
            cache.add(&m);
        }
    }
    stats.records = cache.len() as u64;
    stats.bytes = cache.bytes() as u64;
    stats.seconds = start.elapsed().as_secs_f64();
    Ok((cache, stats))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_visit_every_pixel_once() {
        let (w, h) = (37, 21);
        let mut seen = vec![0u32; (w * h) as usize];
        let mut s = 16;
        let mut first = true;
        loop {
            for (x, y) in level_points(w, h, s, first) {
                seen[(y * w + x) as usize] += 1;
            }
            if s == 1 {
                break;
            }
            s /= 2;
            first = false;
        }
        assert!(seen.iter().all(|&n| n == 1), "{seen:?}");
    }
}
