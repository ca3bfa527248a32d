//! `locus bench`: BVH build time, incoherent ray throughput of
//! [`locus_core::accel::Accel`] against raw obvhs traversal on the same
//! rays, and path-traced samples per second. Ratios are taken within one
//! run because the machines are shared and noisy.

use locus_core::generate::incoherent_rays;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::stats::TraceStats;
use serde::Serialize;
use std::time::Instant;

#[derive(Clone, Debug, Serialize)]
pub struct TraceBench {
    pub triangles: usize,
    pub bvh_build_s: f64,
    pub rays: usize,
    pub locus_mrays_per_s: f64,
    pub obvhs_mrays_per_s: f64,
    /// locus time / obvhs time - 1.
    pub overhead: f64,
    pub hits_agree: usize,
    pub samples_per_s: f64,
    pub spp: u32,
    pub threads: usize,
}

/// Runs the measurements on one thread for the ray part (so the ratio is
/// not disturbed by scheduling) and `threads` for the render part.
pub fn run(prep: &Prepared, rays: usize, rounds: usize, spp: u32, threads: usize) -> TraceBench {
    // The BVH that `Prepared::new` built and timed is the one measured.
    let accel = &prep.accel;
    let bvh_build_s = prep.timings.bvh_s;
    let rs = incoherent_rays(prep, rays, 12345);
    let tris = accel.obvhs_triangles();
    let mut agree = 0;
    for r in &rs {
        let mut st = TraceStats::default();
        let a = accel
            .intersect(r, 0.0, f32::INFINITY, &mut st)
            .map(|h| h.t)
            .unwrap_or(f32::INFINITY);
        let b = accel.raw_obvhs_closest(&tris, r);
        if (a == b) || (a - b).abs() <= 1e-4 * a.abs().max(1.0) {
            agree += 1;
        }
    }
    // Interleave the two loops round by round so drifts in machine load hit
    // both alike; keep the best round of each.
    let (mut best_ours, mut best_raw) = (f64::INFINITY, f64::INFINITY);
    let mut sink = 0f32;
    for _ in 0..rounds.max(1) {
        let t = Instant::now();
        let mut st = TraceStats::default();
        for r in &rs {
            if let Some(h) = accel.intersect(r, 0.0, f32::INFINITY, &mut st) {
                sink += h.t;
            }
        }
        best_ours = best_ours.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        for r in &rs {
            let d = accel.raw_obvhs_closest(&tris, r);
            if d.is_finite() {
                sink += d;
            }
        }
        best_raw = best_raw.min(t.elapsed().as_secs_f64());
    }
    std::hint::black_box(sink);
    let mut opts = RenderOptions::from_scene(&prep.scene);
    opts.spp = spp;
    opts.threads = threads;
    let out = render(prep, &opts, &|_, _| {});
    TraceBench {
        triangles: prep.scene.tris.len(),
        bvh_build_s,
        rays,
        locus_mrays_per_s: rays as f64 / best_ours / 1e6,
        obvhs_mrays_per_s: rays as f64 / best_raw / 1e6,
        overhead: best_ours / best_raw - 1.0,
        hits_agree: agree,
        samples_per_s: out.stats.samples as f64 / out.render_s,
        spp,
        threads: if threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            threads
        },
    }
}
