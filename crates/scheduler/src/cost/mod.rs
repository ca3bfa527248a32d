//! Predicted cost of each octree leaf, two ways.
//!
//! - Analytic, after MacDonald and Booth: the chance that a ray visits a
//!   leaf grows with its surface area, and the work once inside with its
//!   triangle count, so cost = area x (1 + triangles). The 1 keeps empty
//!   leaves, which rays still cross, from costing nothing.
//! - Sampled, after Reinhard, Kok and Chalmers: trace a low-resolution
//!   preview of the real workload (camera rays, then each path's shadow
//!   rays and bounces to the scene's depth) leaf by leaf, and count the BVH
//!   node visits and triangle tests each leaf's interval costs, plus what
//!   the work that is not tracing costs where it happens: shading each hit
//!   ([`VERTEX_COST`]) in the leaf hit, and starting each camera sample
//!   ([`ORIGIN_COST`]) in the leaf its ray starts in, whose owner renders
//!   the sample's tile. A leaf without triangles is crossed by whoever
//!   holds the ray, so its work and its crossings count for the leaves
//!   with triangles on either side of it.
//!
//! [`preview`] at full resolution is also how the bench measures per-leaf
//! cost to judge both predictions.
//!
//! The scheduler takes the sampled preview on a BVH of the whole scene
//! ([`sampled_in_parts`]): [`FULL_PREVIEW`] for the regions it draws, and,
//! for `adaptive`, the smaller [`DECISION_PREVIEW`] first, whose crossings
//! decide by [`buying_pays`] whether every worker gets the whole scene.
//! Its crossings also pick the leaves every worker holds beside its
//! region ([`shared`]). The preview's tracing, leaf by leaf, and the walks
//! it keeps are in `tracing`.

use locus_core::accel::{Accel, BuildQuality, Hit};
use locus_core::accel_set::{AccelSet, MAX_PARTS, build_parts};
use locus_core::geometry::{FLAT, Ray};
use locus_core::light::LightSet;
use locus_core::octree::Octree;
use locus_core::region::WorkerId;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use locus_protocol::packet::TYPICAL_FORWARD_BYTES;

mod shared;
mod tracing;

/// Preview rays crossing from one leaf into another, per ordered pair
/// `(from, into)`. Keyed by FxHash: the preview's crossings and the
/// partition's leaf graph fill maps of hundreds of thousands of entries,
/// where SipHash (which guards against keys chosen to collide, not a
/// danger for leaf numbers the scheduler made itself) took a fifth of
/// the partition's instructions. Nothing reads such a map in its
/// iteration order without sorting first.
pub type Crossings = rustc_hash::FxHashMap<(u32, u32), u32>;
pub use shared::{shared_leaves, traffic};
pub use tracing::preview;

/// What the preview traces through: one BVH, or a set built in parts.
pub trait Geometry: Sync {
    fn closest(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> Option<Hit>;
    fn occluded(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> bool;
}

impl Geometry for Accel {
    fn closest(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> Option<Hit> {
        self.intersect(ray, t0, t1, st)
    }
    fn occluded(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> bool {
        Accel::occluded(self, ray, t0, t1, st)
    }
}

impl Geometry for AccelSet {
    fn closest(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> Option<Hit> {
        AccelSet::closest(self, ray, t0, t1, st).map(|h| h.hit.hit)
    }
    fn occluded(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> bool {
        AccelSet::occluded(self, ray, t0, t1, st)
    }
}

pub fn analytic(tree: &Octree) -> Vec<f64> {
    tree.leaves
        .iter()
        .map(|l| {
            let e = l.bounds.extent().as_dvec3();
            let area = 2.0 * (e.x * e.y + e.y * e.z + e.z * e.x);
            area * (1.0 + l.tris.len() as f64)
        })
        .collect()
}

/// Per-leaf work of a preview, the rays it traced, and how often a ray
/// went on from one leaf straight into another: a ray crossing from one
/// worker's leaf into another's is a forwarded query, so these counts are
/// the traffic a partition's borders cause.
pub struct Preview {
    pub cost: Vec<f64>,
    pub rays: u64,
    /// BVH steps (node visits and triangle tests) counted, leaf interval
    /// by leaf interval: more than a BVH of a whole region takes for the
    /// same rays, since each interval enters the scene's BVH from its root.
    pub steps: u64,
    /// Paths traced (one per preview pixel), against which crossings scale
    /// to a job's samples.
    pub paths: u64,
    /// Crossings per ordered pair of leaves `(from, into)`: a path that
    /// went on from leaf `from` straight into leaf `into` (counted by
    /// [`Preview::crossings_beside`] with nothing shared). The direction
    /// matters because the two ends of a forwarded query pay unequally
    /// (see `partition::FORWARD_COST`).
    pub crossings: Crossings,
    /// The leaves with triangles each ray went through, in order, path
    /// by path: each ray's run ended by [`WALK_END`] (a path's ray) or
    /// [`SHADOW_END`] (its shadow ray), each path by [`PATH_END`]. What
    /// [`Preview::crossings_beside`] and [`Preview::first_leaves`] follow.
    pub walks: Vec<u32>,
    /// Beside each entry of [`Preview::walks`] (0 beside the markers):
    /// the work of that ray in that leaf and in the empty leaves it
    /// crossed next, in [`Preview::cost`]'s units. Whoever holds the path
    /// there does it, so the work in a leaf every worker holds is charged
    /// to the leaf that holds the path ([`Preview::charged`]).
    pub walk_costs: Vec<u32>,
    /// The pixel of each path, in the order of [`Preview::walks`].
    pub pixels: Vec<(u32, u32)>,
}

/// Ends the run of leaves of a path's ray (the camera ray or a bounce) in
/// [`Preview::walks`].
pub const WALK_END: u32 = u32::MAX;
/// Ends the run of leaves of a shadow ray in [`Preview::walks`].
pub const SHADOW_END: u32 = u32::MAX - 1;
/// Ends a path in [`Preview::walks`].
pub const PATH_END: u32 = u32::MAX - 2;

/// What a path vertex costs beyond the BVH work of its rays, in the
/// preview's BVH steps (node visits and triangle tests), charged to the
/// leaf of the hit: its shading, the light's sample, and starting its
/// shadow and continuation queries through the worker's route and path
/// kernel.
///
/// Fitted to callgrind (`crates/locus/src/bench/fit_costs.py` over 36
/// workers of 8 `forward_cost.py` runs, room and conference room, 2 to 8
/// workers): a worker spends 4,527 instructions a vertex and 76 a step of
/// its region's BVH. The preview counts about 2.75 steps for each of
/// those, because every leaf interval of a ray enters the whole scene's
/// BVH again from its root (35.2 steps a ray on the room against one
/// machine's 12.3, 31.4 against 11.9 on the conference room: the last two
/// columns of `locus bench-farm`'s prediction table): a preview
/// step is about 28 instructions, and a vertex 164 of them. Charged 20
/// (the BVH's work taken at one machine's 125 instructions a step), the
/// preview put too little where paths bounce, and the worker holding the
/// camera took 0.31 of the work at 4 workers where 0.24 was predicted.
pub const VERTEX_COST: u64 = 164;

/// What starting a camera sample costs the worker that renders its tile,
/// in the preview's BVH steps: the camera ray, the sample's slot, its
/// radiance added to the tile, the tile's bookkeeping (2,304 instructions
/// in the fit above). A tile goes to the owner of the leaves its camera
/// rays start in (see `tiles::affinity`; past the camera's own leaf,
/// which every worker holds), so that leaf is charged.
pub const ORIGIN_COST: u64 = 83;

/// Bounces the preview follows at most: paths past a dozen vertices carry
/// too little of the work to change the prediction.
const PREVIEW_BOUNCES: u32 = 12;

/// The sampled prediction the scheduler uses: about 8192 preview pixels
/// (every pixel of a small image), paths to the scene's full depth. One
/// bounce was once used, and it put half the farm's work where two thirds
/// of it went: deep paths cross different leaves than first bounces.
pub fn sampled(scene: &Scene, tree: &Octree, accel: &dyn Geometry, lights: &LightSet) -> Preview {
    sampled_paths(scene, tree, accel, lights, FULL_PREVIEW.paths)
}

/// [`sampled`] with about `paths` preview pixels (every pixel where the
/// image has fewer).
pub fn sampled_paths(
    scene: &Scene,
    tree: &Octree,
    accel: &dyn Geometry,
    lights: &LightSet,
    paths: u32,
) -> Preview {
    let pixels = scene.camera.width as f64 * scene.camera.height as f64;
    let div = (pixels / paths.max(1) as f64).sqrt().floor().max(1.0) as u32;
    preview(
        scene,
        tree,
        accel,
        lights,
        div,
        scene.settings.max_depth.min(PREVIEW_BOUNCES),
        scene.settings.seed ^ 0x5eed,
    )
}

/// How the scheduler takes a sampled preview: on a BVH over the whole
/// scene built in parts of at most `part` triangles, tracing about `paths`
/// paths.
#[derive(Clone, Copy, Debug)]
pub struct PreviewSize {
    pub part: usize,
    pub paths: u32,
    pub quality: BuildQuality,
}

/// The preview regions are drawn from: one part up to 512k triangles
/// (which keeps a build within about 200 MB whatever the scene's size),
/// 8,192 paths. A job builds it at the quality its workers build their
/// regions at (the job's `bvh_quality`): by default full, but for a job
/// of fewer camera samples than triangles, whose workers build quick BVHs
/// and whose preview then counts the steps of such a tree (on the
/// 4-million-triangle room at 320x240 and 16 spp the preview took
/// 0.98-1.11 s instead of 1.65-1.83, at 0.069-0.070 forwards a ray under
/// `forward` either way).
pub const FULL_PREVIEW: PreviewSize = PreviewSize {
    part: 512 << 10,
    paths: 8192,
    quality: BuildQuality::Full,
};

/// A job under
/// [`CostModel::Auto`](locus_protocol::submit::CostModel::Auto) traces
/// the full preview only when it has at least this many camera samples a
/// triangle reference; a smaller one draws its regions from the
/// [`DECISION_PREVIEW`] (a quarter of the paths over quick BVHs in small
/// parts), which `adaptive` decides on whether to buy anyway. An
/// `adaptive` job whose scene does not fit every worker keeps the full
/// preview: it fetches leaves by what its preview counted, and fetched
/// far more from the small one's counts (the 4-million-triangle room
/// below: 8.25 s of render against 5.12).
///
/// The preview's cost grows with the scene (a BVH over all of it) and its
/// gain with the job (fewer forwards, better balance, for every sample).
/// Measured on this 2-core AMD EPYC (2026-12-07, the embedded farm, two
/// workers of one thread, `forward`, the whole job from submission, the
/// full preview (`--cost sampled`) against the small one (`--cost auto`)
/// against the analytic model (`--cost analytic`)): the room at 160x90
/// and 1 spp (0.044 samples a reference) 0.47, 0.28 and 0.20 s, at 4 spp
/// 0.56, 0.38 and 0.35; the conference room at 320x180 and 1 spp 0.48,
/// 0.34 and 0.28, at 4 spp (0.83) 0.85, 0.75 and 0.72; the Country
/// Kitchen (1.44 million triangles) at 160x90 and 1 spp 2.29, 1.47 and
/// 1.07, at 4 spp 2.45, 1.70 and 1.27; the 4-million-triangle room on
/// four workers at 320x240 and 16 spp (0.30) 7.89, 6.43 and 7.31 (the
/// render 4.19, 4.58 and 5.90 s: analytic regions balance it badly).
/// Regions from the small preview render about as fast as the full
/// one's. Where the full preview pays, from measurements before the
/// small one was tried (full against analytic): the room at 320x180 and
/// 4 spp (0.71) 0.98 against 1.03 s, at 16 spp (2.84) 2.57 against 3.31;
/// the conference room at 16 spp (3.3) 2.06 against 2.33; the kitchen at
/// 320x180 and 16 spp (0.64) 5.12 against 4.94. One sample a reference
/// is on the right side of all but the room's 0.71 (5%). The small
/// preview against the full one above it (`--cost small` against
/// `--cost sampled`): the room at 320x180 and 4 spp (0.71) 0.75-0.77 s
/// against 0.96-0.98, at 16 spp (2.84) 2.31-2.35 against 2.46-2.58 with
/// the render 2.04-2.10 against 1.97-2.08; the conference room at 16 spp
/// (3.3) 1.90-2.07 against 2.02-2.06, the render 3-7% slower. So the
/// small preview can still win the whole job at three samples a
/// reference, at a slower render; the rule stays at one, where the
/// standard benchmarks' jobs
/// (the room at 3.8) keep their regions and the full preview's margin
/// grows with the workers a partition places work between.
pub const PREVIEW_FROM_SAMPLES_PER_TRIANGLE: u64 = 1;

/// Whether a job of `samples` camera samples over `references` triangle
/// references pays for the full preview when its cost model is
/// `CostModel::Auto` ([`PREVIEW_FROM_SAMPLES_PER_TRIANGLE`]).
pub fn preview_pays(samples: u64, references: u64) -> bool {
    samples >= references.saturating_mul(PREVIEW_FROM_SAMPLES_PER_TRIANGLE)
}

/// The preview `adaptive` decides with whether to buy the whole scene.
/// Parts this small build several at once and each faster (obvhs's
/// conversion to the wide BVH is serial, and its tables then fit the
/// caches): the room's preview BVH, on 2 threads, in 67 ms against 175-188
/// ms in one part. The rent-or-buy rule counts crossings between leaves,
/// which hits decide, not how the BVH is cut; a quarter of the paths
/// counted 1.921 crossings a path on the room against the full preview's
/// 1.904, 1.545 against 1.554 on the conference room. The leaf costs, which
/// count BVH steps, do move with the cut (the room's regions drawn from
/// parts of 64k forwarded 0.302 queries a ray against 0.274), which is why
/// regions that carry rays are drawn from [`FULL_PREVIEW`].
///
/// For the same reason its parts are built [`BuildQuality::Quick`] (no
/// spatial pre-splits, PLOC searching one neighbour, no reinsertion): the
/// crossings, paths and rays are the full build's to the count
/// (`a_quick_decision_preview_counts_what_a_full_one_does`), and on the
/// room it spares about 680 M instructions (callgrind, the embedded
/// farm's whole job, by the self costs of the build's steps: reinsertion
/// and pre-splits about 280 M, PLOC's neighbour search about 400 M), 0.08
/// to 0.07 s of the preview on two threads.
pub const DECISION_PREVIEW: PreviewSize = PreviewSize {
    part: 32 << 10,
    paths: 2048,
    quality: BuildQuality::Quick,
};

/// The sampled preview (see [`sampled`]) of the size given.
pub fn sampled_in_parts(
    scene: &Scene,
    tree: &Octree,
    lights: &LightSet,
    size: PreviewSize,
) -> Preview {
    let leaves: Vec<(u32, &[u32])> = tree
        .leaves
        .iter()
        .enumerate()
        .map(|(i, l)| (i as u32, l.tris.as_slice()))
        .collect();
    let tri = |id: u32| {
        let i = id as usize;
        let n = scene.tri_normals.get(i).copied().unwrap_or(FLAT);
        (scene.tris[i], scene.tri_material[i], n)
    };
    let accel = AccelSet::from_parts(build_parts(
        &leaves,
        size.part.max(scene.tris.len().div_ceil(MAX_PARTS)),
        scene.magnitude(),
        size.quality,
        &tri,
    ));
    sampled_paths(scene, tree, &accel, lights, size.paths)
}

/// The adaptive policy's rent-or-buy rule for the whole job, decided from
/// the preview: whether the queries the partition `owner` would forward
/// (each preview crossing between two workers' leaves, scaled from the
/// preview's `paths` to the job's `samples`) cost more bytes than shipping
/// every worker the triangle references it lacks (`scene_bytes`, all the
/// references as shipped). Without a preview it cannot tell, and rents
/// (the workers decide leaf by leaf as they go).
pub fn buying_pays(
    crossings: &Crossings,
    owner: &[WorkerId],
    workers: usize,
    scene_bytes: u64,
    samples: u64,
    paths: u64,
) -> bool {
    if paths == 0 {
        return false;
    }
    let rent = cut(crossings, owner) as f64
        * (samples as f64 / paths as f64)
        * TYPICAL_FORWARD_BYTES as f64;
    // Each worker lacks everything but its own references.
    let buy = (workers.saturating_sub(1) as u64 * scene_bytes) as f64;
    rent >= buy
}

/// The crossings between two workers' leaves under the partition `owner`:
/// the queries it forwards if every path is started by the owner of its
/// first leaf. A tile has one owner for paths whose first leaves scatter,
/// and [`Preview::forwards_from`] counts what that adds.
pub fn cut(crossings: &Crossings, owner: &[WorkerId]) -> u64 {
    crossings
        .iter()
        .filter(|((a, b), _)| owner.get(*a as usize) != owner.get(*b as usize))
        .map(|(_, &c)| c as u64)
        .sum()
}

/// How well each prediction matches the per-leaf cost of the real
/// workload, per leaf.
#[derive(Clone, Debug)]
pub struct Quality {
    pub leaves: usize,
    /// Pearson r of analytic and sampled predictions against measured.
    pub analytic_r: f64,
    pub sampled_r: f64,
    /// Rays the sampled prediction traced, and the measurement.
    pub sampled_rays: u64,
    pub measured_rays: u64,
    /// BVH steps a ray of the measurement, counted as the preview counts
    /// them: against what the render's own BVH takes a ray, how many
    /// instructions a step of the preview's costs stands for.
    pub measured_steps_per_ray: f64,
}

/// Measures per-leaf cost with the full workload at one sample per pixel
/// (every pixel, the scene's full path depth, an independent seed) and
/// compares both predictions with it.
pub fn quality(scene: &Scene, tree: &Octree, accel: &dyn Geometry, lights: &LightSet) -> Quality {
    let analytic = analytic(tree);
    let sampled = sampled(scene, tree, accel, lights);
    let measured = preview(
        scene,
        tree,
        accel,
        lights,
        1,
        scene.settings.max_depth,
        scene.settings.seed ^ 0x03ea_50ed,
    );
    Quality {
        leaves: tree.leaves.len(),
        analytic_r: correlation(&analytic, &measured.cost),
        sampled_r: correlation(&sampled.cost, &measured.cost),
        sampled_rays: sampled.rays,
        measured_rays: measured.rays,
        measured_steps_per_ray: measured.steps as f64 / measured.rays.max(1) as f64,
    }
}

/// The leaf holding the camera, if the camera is inside the scene: every
/// camera ray starts in it, so its owner would start every sample (at 8
/// workers it did 1.4-1.6 times the mean work). The farm gives it to every
/// worker instead (an empty one costs nothing to hold), so that any worker
/// starts samples ([`crate::tiles`]).
pub fn camera_leaf(tree: &Octree, camera: &locus_core::scene::Camera) -> Option<u32> {
    tree.leaf_at(camera.position)
}

/// Pearson correlation; 0 when either side has no variance.
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()) as f64;
    if n < 2.0 {
        return 0.0;
    }
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    if saa == 0.0 || sbb == 0.0 {
        0.0
    } else {
        sab / (saa * sbb).sqrt()
    }
}

/// Each worker's share of the total cost under an ownership.
pub fn shares(cost: &[f64], owner: &[u16], workers: usize) -> Vec<f64> {
    let mut s = vec![0.0; workers];
    for (c, &o) in cost.iter().zip(owner) {
        s[o as usize] += c;
    }
    let total: f64 = s.iter().sum();
    if total > 0.0 {
        s.iter_mut().for_each(|x| *x /= total);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::geometry::TRIANGLE_BYTES;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// The Cornell box, its octree for `workers` and lights, and their
    /// preview (image divided by `div`, 3 bounces, seed 7) on one BVH over
    /// the scene: what the preview's tests start from.
    pub(super) struct Cornell {
        pub scene: Scene,
        pub tree: Octree,
        pub lights: LightSet,
        pub pv: Preview,
    }

    pub(super) fn cornell_preview(workers: usize, div: u32) -> Cornell {
        let scene = crate::cornell_box();
        let tree = crate::job::octree_for(&scene, workers);
        let lights = LightSet::build(&scene);
        let accel = locus_core::render::whole_scene_accel(&scene);
        let pv = preview(&scene, &tree, &accel, &lights, div, 3, 7);
        Cornell {
            scene,
            tree,
            lights,
            pv,
        }
    }

    /// The scene's BVH with its work left uncounted, and its hits counted:
    /// what the preview then charges is the work that is not tracing.
    struct Untraced(Accel, AtomicU64);

    impl Geometry for Untraced {
        fn closest(&self, ray: &Ray, t0: f32, t1: f32, _: &mut TraceStats) -> Option<Hit> {
            let h = self.0.intersect(ray, t0, t1, &mut TraceStats::default());
            self.1.fetch_add(u64::from(h.is_some()), Ordering::Relaxed);
            h
        }
        fn occluded(&self, ray: &Ray, t0: f32, t1: f32, _: &mut TraceStats) -> bool {
            self.0.occluded(ray, t0, t1, &mut TraceStats::default())
        }
    }

    /// The decision preview's quick build finds the hits a full build
    /// finds, so it counts the same crossings, paths and rays, in a scene
    /// large enough to split triangles and to be cut into several parts.
    #[test]
    fn a_quick_decision_preview_counts_what_a_full_one_does() {
        use locus_core::generate::{RoomParams, conference_room, room_materials};
        let params = RoomParams {
            chairs_per_side: 3,
            detail: 6,
            leg_segments: 8,
            ..Default::default()
        };
        let scene = Scene::from_triangles(
            "room".into(),
            locus_core::scene::Camera {
                position: glam::Vec3::new(0.6, 1.6, 0.6),
                look_at: glam::Vec3::new(8.0, 0.7, 5.0),
                up: glam::Vec3::Y,
                fov_y: 60.0,
                width: 48,
                height: 32,
            },
            locus_core::scene::RenderSettings {
                max_depth: 5,
                seed: 7,
                ..Default::default()
            },
            room_materials(),
            conference_room(&params).tagged_triangles(),
        );
        let tree = crate::job::octree_for(&scene, 4);
        let lights = LightSet::build(&scene);
        let size = |quality| PreviewSize {
            part: 2048,
            paths: 512,
            quality,
        };
        let full = sampled_in_parts(&scene, &tree, &lights, size(BuildQuality::Full));
        let quick = sampled_in_parts(&scene, &tree, &lights, size(BuildQuality::Quick));
        assert!(
            scene.tris.len() > 3 * 2048,
            "{} triangles",
            scene.tris.len()
        );
        assert!(
            full.crossings.len() > 20,
            "{} crossings",
            full.crossings.len()
        );
        assert_eq!(quick.crossings, full.crossings);
        assert_eq!((quick.paths, quick.rays), (full.paths, full.rays));
    }

    /// `steps` is the BVH work the preview charged, and only that: the
    /// same preview with the BVH's work left uncounted charges the rest.
    #[test]
    fn the_preview_counts_its_bvh_steps() {
        let Cornell {
            scene,
            tree,
            lights,
            pv: traced,
        } = cornell_preview(4, 16);
        let g = Untraced(
            locus_core::render::whole_scene_accel(&scene),
            AtomicU64::new(0),
        );
        let rest = preview(&scene, &tree, &g, &lights, 16, 3, 7);
        let sum = |p: &Preview| p.cost.iter().sum::<f64>() as u64;
        assert!(traced.steps > traced.rays, "{} steps", traced.steps);
        assert_eq!(rest.steps, 0);
        assert_eq!(sum(&traced) - sum(&rest), traced.steps);
    }

    /// Besides the BVH work, every path vertex is charged [`VERTEX_COST`]
    /// and every camera sample [`ORIGIN_COST`]: with the BVH's work left
    /// uncounted, the preview's costs add up to exactly those.
    #[test]
    fn the_preview_charges_shading_where_paths_bounce() {
        let scene = crate::cornell_box();
        let tree = crate::job::octree_for(&scene, 4);
        let lights = LightSet::build(&scene);
        let g = Untraced(
            locus_core::render::whole_scene_accel(&scene),
            AtomicU64::new(0),
        );
        let pv = preview(&scene, &tree, &g, &lights, 16, 3, 7);
        let vertices = g.1.load(Ordering::Relaxed);
        assert!(vertices > pv.paths && pv.paths > 100);
        let charged = pv.cost.iter().sum::<f64>() as u64;
        // What is not shading is starting samples: one for each camera
        // ray that enters the scene's octree, which all but the few along
        // the image's edges do.
        let starts = charged
            .checked_sub(VERTEX_COST * vertices)
            .unwrap_or_else(|| panic!("{charged} charged for {vertices} vertices"));
        assert_eq!(starts % ORIGIN_COST, 0, "{charged} charged");
        let started = starts / ORIGIN_COST;
        assert!(
            started <= pv.paths && started * 10 >= pv.paths * 9,
            "{started} of {} samples started",
            pv.paths
        );
    }

    /// A leaf without triangles is crossed by whoever holds the ray: the
    /// preview counts crossings between leaves with triangles only, and
    /// charges empty leaves no BVH work beyond what no leaf with triangles
    /// could take (a ray that meets none). The walks carry each leaf's
    /// work entry by entry.
    #[test]
    fn crossings_skip_empty_leaves() {
        let Cornell {
            scene,
            tree,
            lights,
            pv,
        } = cornell_preview(8, 8);
        let empty: Vec<bool> = tree.leaves.iter().map(|l| l.tris.is_empty()).collect();
        assert!(empty.iter().any(|&e| e), "the test needs empty leaves");
        assert!(!pv.crossings.is_empty());
        for &(a, b) in pv.crossings.keys() {
            assert!(!empty[a as usize] && !empty[b as usize], "{a} -> {b}");
        }
        // With the BVH's work uncounted, the rest is shading and starts.
        let g = Untraced(
            locus_core::render::whole_scene_accel(&scene),
            AtomicU64::new(0),
        );
        let rest = preview(&scene, &tree, &g, &lights, 8, 3, 7);
        let bvh = |l: usize| pv.cost[l] - rest.cost[l];
        let on_empty: f64 = (0..empty.len()).filter(|&l| empty[l]).map(bvh).sum();
        assert!(
            on_empty < 0.01 * pv.steps as f64,
            "{on_empty} of {} BVH steps on empty leaves",
            pv.steps
        );
        let all: f64 = (0..empty.len()).map(bvh).sum();
        assert_eq!(all as u64, pv.steps);
        // Every leaf with triangles (the camera's aside, which no walk
        // enters) has its cost in its walks' entries, to the unit.
        let camera = camera_leaf(&tree, &scene.camera);
        let mut walked = vec![0u64; empty.len()];
        assert_eq!(pv.walk_costs.len(), pv.walks.len());
        for (&l, &c) in pv.walks.iter().zip(&pv.walk_costs) {
            match walked.get_mut(l as usize) {
                Some(w) => *w += c as u64,
                None => assert_eq!(c, 0, "a marker carries work"),
            }
        }
        for l in (0..empty.len()).filter(|&l| !empty[l] && Some(l as u32) != camera) {
            assert_eq!(walked[l], pv.cost[l] as u64, "leaf {l}");
        }
    }

    /// Rent or buy for the whole scene: buying pays once the predicted
    /// forwards cost as many bytes as the references every worker lacks.
    #[test]
    fn buying_pays_when_the_rays_would_cost_more_than_the_geometry() {
        // Leaves 0, 1 on worker 0 and leaf 2 on worker 1; only the border
        // between 1 and 2 separates workers.
        let owner = [0u16, 0, 1];
        let crossings: Crossings = [((0, 1), 1000), ((1, 2), 10)].into_iter().collect();
        let buy = 3000 * TRIANGLE_BYTES;
        let refs = buy;
        // 10 preview crossings per 100 paths: the job forwards samples / 10.
        let samples_even = buy * 10 / TYPICAL_FORWARD_BYTES + 10;
        assert!(buying_pays(&crossings, &owner, 2, refs, samples_even, 100));
        assert!(!buying_pays(
            &crossings,
            &owner,
            2,
            refs,
            samples_even / 2,
            100
        ));
        // More workers lack more.
        assert!(!buying_pays(&crossings, &owner, 3, refs, samples_even, 100));
        // No preview: no prediction, rent.
        assert!(!buying_pays(&crossings, &owner, 2, refs, u64::MAX, 0));
        // Crossings inside one worker's region cost nothing.
        let inside: Crossings = [((0, 1), 1_000_000)].into_iter().collect();
        assert!(!buying_pays(&inside, &owner, 2, refs, samples_even, 100));
    }
}
