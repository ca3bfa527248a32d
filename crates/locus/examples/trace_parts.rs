//! What a BVH built in parts costs a ray, as a worker under a memory
//! budget builds its region, against one BVH built over everything: parts
//! that are runs of octree leaves in Morton order (`accel_set::build_parts`,
//! as a fetching worker's are) traced as a set and joined into one BVH
//! (`accel_set::join`), and parts cut by centroid
//! (`accel_set::cut_by_centroids`, as a joining worker's are) joined:
//!
//!     cargo build --release -p locus --example trace_parts
//!     target/release/examples/trace_parts scenes/generated/room.toml 16 5
//!     valgrind --tool=callgrind --toggle-collect='trace_parts::round*' \
//!         target/release/examples/trace_parts scenes/generated/room.toml 16 1
//!
//! Arguments: the scene, the number of parts (about; default 16) and the
//! rounds (default 5), each round tracing `locus bench`'s 500,000
//! incoherent rays through the four in turn. Prints each one's best
//! round in rays per second, with BVH queries, node visits and triangle
//! tests a ray, and checks that all four find the same closest hits.

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
    // As a joining worker's region is cut (`accel_set::cut_by_centroids`).
    let centroid = |id: u32| {
        let t = scene.tris[id as usize];
        (t[0] + t[1] + t[2]) / 3.0
    };
    let all: Vec<u32> = (0..scene.tris.len() as u32).collect();
    let cut: Vec<_> = accel_set::cut_by_centroids(all, &centroid, refs.div_ceil(want.max(1)))
        .iter()
        .flat_map(|g| {
            let one = [(0, g.as_slice())];
            accel_set::build_parts(&one, g.len(), scene.magnitude(), BuildQuality::Full, &tri)
        })
        .collect();
    let cut_parts = cut.len();
    let cut_joined = AccelSet::from_parts(accel_set::join(cut));
    let rays = locus::bench::trace::rays(&prep, 500_000);
    println!(
        "{} triangles; {} leaf-run parts, joined into {}; {} centroid-cut parts",
        scene.tris.len(),
        set.parts().len(),
        joined.parts().len(),
        cut_parts
    );
    let names = [
        "one BVH",
        "leaf-run parts as a set",
        "leaf-run parts joined",
        "centroid-cut parts joined",
    ];
    let mut best = [(f64::INFINITY, TraceStats::default()); 4];
    let mut hits = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
    for _ in 0..rounds.max(1) {
        let [h0, h1, h2, h3] = &mut hits;
        let r = [
            round(&rays, h0, |r, st| {
                prep.accel
                    .closest(r, 0.0, f32::INFINITY, st)
                    .map(|h| (h.hit.t, h.hit.tri))
            }),
            round(&rays, h1, in_set(&set)),
            round(&rays, h2, in_set(&joined)),
            round(&rays, h3, in_set(&cut_joined)),
        ];
        for (b, r) in best.iter_mut().zip(r) {
            if r.0 < b.0 {
                *b = r;
            }
        }
    }
    anyhow::ensure!(hits[0] == hits[1], "the set's hits differ from one BVH's");
    anyhow::ensure!(hits[0] == hits[3], "the centroid-cut parts' hits differ");
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
    println!("every closest hit the same in all four");
    Ok(())
}
