//! What a BVH built in parts costs a ray, as a worker under a memory
//! budget builds its region (`accel_set::build_parts`, runs of octree
//! leaves in Morton order), traced as a set of parts and joined into one
//! BVH (`accel_set::join`), against one BVH built over everything:
//!
//!     cargo build --release -p locus --example trace_parts
//!     target/release/examples/trace_parts scenes/generated/room.toml 16 5
//!     valgrind --tool=callgrind --toggle-collect='trace_parts::round*' \
//!         target/release/examples/trace_parts scenes/generated/room.toml 16 1
//!
//! Arguments: the scene, the number of parts (about; default 16) and the
//! rounds (default 5), each round tracing `locus bench`'s 500,000
//! incoherent rays through the three in turn. Prints each one's best
//! round in rays per second, with BVH queries, node visits and triangle
//! tests a ray, and checks that all three find the same closest hits.

use locus_core::accel::BuildQuality;
use locus_core::accel_set::{self, AccelSet};
use locus_core::geometry::{FLAT, Ray};
use locus_core::octree::{Octree, OctreeParams};
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use std::time::Instant;

/// One round: `closest` over every ray, its seconds, the stats and each
/// ray's hit.
#[inline(never)]
fn round(
    rays: &[Ray],
    hits: &mut Vec<Option<(f32, u32)>>,
    closest: impl Fn(&Ray, &mut TraceStats) -> Option<(f32, u32)>,
) -> (f64, TraceStats) {
    let mut st = TraceStats::default();
    hits.clear();
    let t = Instant::now();
    for r in rays {
        hits.push(closest(r, &mut st));
    }
    (t.elapsed().as_secs_f64(), st)
}

/// The closest hit through a set of parts.
fn in_set(s: &AccelSet) -> impl Fn(&Ray, &mut TraceStats) -> Option<(f32, u32)> + '_ {
    move |r, st| {
        s.closest(r, 0.0, f32::INFINITY, st)
            .map(|h| (h.hit.hit.t, h.hit.hit.tri))
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        anyhow::bail!("usage: trace_parts SCENE [PARTS] [ROUNDS]");
    };
    let want: usize = args.get(1).map_or(Ok(16), |a| a.parse())?;
    let rounds: usize = args.get(2).map_or(Ok(5), |a| a.parse())?;
    let prep = Prepared::new(Scene::load(std::path::Path::new(path))?);
    let scene = &prep.scene;
    let tree = Octree::build(&scene.tris, OctreeParams::default());
    let leaves: Vec<(u32, &[u32])> = tree
        .leaves
        .iter()
        .enumerate()
        .map(|(i, l)| (i as u32, l.tris.as_slice()))
        .collect();
    let refs: usize = leaves.iter().map(|(_, t)| t.len()).sum();
    let tri = |id: u32| {
        let i = id as usize;
        (
            scene.tris[i],
            scene.tri_material[i],
            scene.tri_normals.get(i).copied().unwrap_or(FLAT),
        )
    };
    let parts = accel_set::build_parts(
        &leaves,
        refs.div_ceil(want.max(1)),
        scene.magnitude(),
        BuildQuality::Full,
        &tri,
    );
    let set = AccelSet::from_parts(parts.clone());
    let joined = AccelSet::from_parts(accel_set::join(parts));
    let rays = locus::bench::trace::rays(&prep, 500_000);
    println!(
        "{} triangles; {} parts; joined into {}",
        scene.tris.len(),
        set.parts().len(),
        joined.parts().len()
    );
    let names = ["one BVH", "parts as a set", "parts joined"];
    let mut best = [(f64::INFINITY, TraceStats::default()); 3];
    let mut hits = [Vec::new(), Vec::new(), Vec::new()];
    for _ in 0..rounds.max(1) {
        let [h0, h1, h2] = &mut hits;
        let r = [
            round(&rays, h0, |r, st| {
                prep.accel
                    .closest(r, 0.0, f32::INFINITY, st)
                    .map(|h| (h.hit.t, h.hit.tri))
            }),
            round(&rays, h1, in_set(&set)),
            round(&rays, h2, in_set(&joined)),
        ];
        for (b, r) in best.iter_mut().zip(r) {
            if r.0 < b.0 {
                *b = r;
            }
        }
    }
    anyhow::ensure!(hits[0] == hits[1], "the set's hits differ from one BVH's");
    anyhow::ensure!(
        hits[0] == hits[2],
        "the joined BVH's hits differ from one BVH's"
    );
    let n = rays.len() as f64;
    for (name, (s, st)) in names.iter().zip(&best) {
        println!(
            "{name}: {:.2} Mrays/s, {:.2} queries, {:.2} nodes and {:.2} triangle tests a ray",
            n / s / 1e6,
            st.bvh_queries as f64 / n,
            st.bvh_nodes as f64 / n,
            st.tri_tests as f64 / n,
        );
    }
    println!("every closest hit the same in all three");
    Ok(())
}
