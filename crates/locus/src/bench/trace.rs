//! `locus bench`: BVH build time, incoherent ray throughput of
//! [`locus_core::accel::Accel`] against raw obvhs traversal on the same
//! rays, and path-traced samples per second; with `--embree-python`,
//! Embree's throughput on the same rays and triangles (the embreex package,
//! through the script beside this file). Ratios are taken within one run
//! because the machines are shared and noisy.

use locus_core::generate::incoherent_rays;
use locus_core::geometry::Ray;
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
    pub embree: Option<EmbreeBench>,
}

/// Embree against locus on the same incoherent rays, one thread each.
#[derive(Clone, Debug, Serialize)]
pub struct EmbreeBench {
    pub embree_mrays_per_s: f64,
    pub embree_build_s: f64,
    /// locus's rays per second measured just before Embree's.
    pub locus_mrays_per_s: f64,
    /// locus over Embree (the tracer issue's target: at least 0.8).
    pub ratio: f64,
    /// Rays whose closest-hit distance agrees (both miss, or within 1e-4
    /// relative).
    pub hits_agree: usize,
}

/// Runs the measurements on one thread for the ray part (so the ratio is
/// not disturbed by scheduling) and `threads` for the render part.
/// The incoherent rays every measurement here traces: `n` of them, the
/// same for locus, raw obvhs and Embree.
pub fn rays(prep: &Prepared, n: usize) -> Vec<Ray> {
    incoherent_rays(prep, n, 12345)
}

/// locus's closest-hit distance of each ray (infinity for a miss), into
/// `out`, whose room is reused so that timed rounds do not allocate.
fn distances(prep: &Prepared, rs: &[Ray], out: &mut Vec<f32>) {
    let mut st = TraceStats::default();
    out.clear();
    out.extend(rs.iter().map(|r| {
        prep.accel
            .intersect(r, 0.0, f32::INFINITY, &mut st)
            .map_or(f32::INFINITY, |h| h.t)
    }));
}

pub fn run(prep: &Prepared, rs: &[Ray], rounds: usize, spp: u32, threads: usize) -> TraceBench {
    // The BVH that `Prepared::new` built and timed is the one measured.
    let accel = &prep.accel;
    let bvh_build_s = prep.timings.bvh_s;
    let rays = rs.len();
    let tris = accel.obvhs_triangles();
    let mut ours = Vec::new();
    distances(prep, rs, &mut ours);
    let agree = ours
        .into_iter()
        .zip(rs)
        .filter(|&(a, r)| agrees(a, accel.raw_obvhs_closest(&tris, r)))
        .count();
    // Interleave the two loops round by round so drifts in machine load hit
    // both alike; keep the best round of each.
    let (mut best_ours, mut best_raw) = (f64::INFINITY, f64::INFINITY);
    let mut sink = 0f32;
    for _ in 0..rounds.max(1) {
        let t = Instant::now();
        let mut st = TraceStats::default();
        for r in rs {
            if let Some(h) = accel.intersect(r, 0.0, f32::INFINITY, &mut st) {
                sink += h.t;
            }
        }
        best_ours = best_ours.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        for r in rs {
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
        embree: None,
    }
}

fn agrees(a: f32, b: f32) -> bool {
    a == b || (a - b).abs() <= 1e-4 * a.abs().max(1.0)
}

/// Writes the scene's triangles and `rays` incoherent rays to `dir`, times
/// locus on them, then has `python` trace them with Embree.
pub fn embree(
    prep: &Prepared,
    rs: &[Ray],
    rounds: usize,
    python: &str,
    dir: &std::path::Path,
) -> anyhow::Result<EmbreeBench> {
    use anyhow::{Context, bail};
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let write = |name: &str, floats: &mut dyn Iterator<Item = f32>| {
        let bytes: Vec<u8> = floats.flat_map(f32::to_le_bytes).collect();
        let p = dir.join(name);
        std::fs::write(&p, bytes).with_context(|| format!("writing {}", p.display()))
    };
    write(
        "tris.f32",
        &mut prep
            .scene
            .tris
            .iter()
            .flat_map(|t| t.iter().flat_map(|v| v.to_array())),
    )?;
    write(
        "rays.f32",
        &mut rs
            .iter()
            .flat_map(|r| r.origin.to_array().into_iter().chain(r.dir.to_array())),
    )?;
    std::fs::write(dir.join("rounds.txt"), rounds.max(1).to_string())?;
    let script = dir.join("embree_trace.py");
    std::fs::write(&script, include_str!("embree_trace.py"))
        .with_context(|| format!("writing {}", script.display()))?;
    let mut best = f64::INFINITY;
    let mut ours = Vec::with_capacity(rs.len());
    distances(prep, rs, &mut ours);
    for _ in 0..rounds.max(1) {
        let t = Instant::now();
        distances(prep, rs, &mut ours);
        best = best.min(t.elapsed().as_secs_f64());
    }
    let status = std::process::Command::new(python)
        .arg(&script)
        .arg(dir)
        .status()
        .with_context(|| format!("running {python}"))?;
    if !status.success() {
        bail!(
            "{} failed ({status}): is embreex installed (pip install embreex)?",
            script.display()
        );
    }
    #[derive(serde::Deserialize)]
    struct Out {
        mrays_per_s: f64,
        build_s: f64,
    }
    let out: Out = serde_json::from_slice(&std::fs::read(dir.join("embree.json"))?)
        .context("reading embree.json")?;
    let theirs = std::fs::read(dir.join("embree_t.f32")).context("reading embree_t.f32")?;
    let hits_agree = theirs
        .chunks_exact(4)
        .zip(&ours)
        .filter(|(b, a)| agrees(**a, f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
        .count();
    let locus = rs.len() as f64 / best / 1e6;
    Ok(EmbreeBench {
        embree_mrays_per_s: out.mrays_per_s,
        embree_build_s: out.build_s,
        locus_mrays_per_s: locus,
        ratio: locus / out.mrays_per_s,
        hits_agree,
    })
}
