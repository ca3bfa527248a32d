//! Traces `locus bench`'s incoherent rays through a scene's BVH and
//! nothing else, so that callgrind can count the tracer alone and two
//! orders of the same rays can be timed in one process:
//!
//!     cargo build --release -p locus --example trace_rays
//!     valgrind --tool=callgrind --toggle-collect='locus_core::accel::Accel::closest_avx2' \
//!         target/release/examples/trace_rays scenes/generated/room.toml 1
//!     target/release/examples/trace_rays scenes/generated/room.toml 8 --sorted
//!
//! Arguments: the scene, the rounds (default 5), and `--sorted` to time the
//! rays also sorted by direction octant and origin cell, alternating round
//! by round with their random order: how much faster the same work runs
//! when consecutive rays share cache lines bounds what memory costs the
//! tracer. Prints the best round's rays per second, the node visits and
//! triangle tests a query and the sum of hit distances (the same in both
//! orders, up to the order of the sum).

use locus_core::geometry::Ray;
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use std::time::Instant;

/// One round over `rays`: seconds, node visits, triangle tests and the sum
/// of distances.
fn round(prep: &Prepared, rays: &[Ray]) -> (f64, u64, u64, f64) {
    let mut st = TraceStats::default();
    let mut sum = 0f64;
    let t = Instant::now();
    for r in rays {
        if let Some(h) = prep.accel.intersect(r, 0.0, f32::INFINITY, &mut st) {
            sum += f64::from(h.t);
        }
    }
    (t.elapsed().as_secs_f64(), st.bvh_nodes, st.tri_tests, sum)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        anyhow::bail!("usage: trace_rays SCENE [ROUNDS] [--sorted]");
    };
    let rounds: usize = match args.get(1).filter(|a| !a.starts_with("--")) {
        Some(r) => r.parse()?,
        None => 5,
    };
    let sorted = args.iter().any(|a| a == "--sorted");
    let prep = Prepared::new(Scene::load(std::path::Path::new(path))?);
    let random = locus::bench::trace::rays(&prep, 500_000);
    let mut orders = vec![("random order", random.clone())];
    if sorted {
        let b = prep.accel.bounds();
        let mut s = random;
        s.sort_by_key(|r| {
            let q = (r.origin - b.min) / (b.max - b.min) * 15.99;
            let d = r.dir;
            let octant =
                u32::from(d.x < 0.0) | u32::from(d.y < 0.0) << 1 | u32::from(d.z < 0.0) << 2;
            (octant, q.x as u32, q.y as u32, q.z as u32)
        });
        orders.push(("sorted by octant and origin cell", s));
    }
    let mut best = vec![(f64::INFINITY, 0, 0, 0.0); orders.len()];
    for _ in 0..rounds.max(1) {
        for (k, (_, rays)) in orders.iter().enumerate() {
            let r = round(&prep, rays);
            if r.0 < best[k].0 {
                best[k] = r;
            }
        }
    }
    for ((name, rays), (s, nodes, tests, sum)) in orders.iter().zip(best) {
        let per_query = |n: u64| n as f64 / rays.len() as f64;
        println!(
            "{name}: {:.2} Mrays/s, {:.3} nodes and {:.3} triangle tests a query, distances sum to {sum:.1}",
            rays.len() as f64 / s / 1e6,
            per_query(nodes),
            per_query(tests)
        );
    }
    Ok(())
}
