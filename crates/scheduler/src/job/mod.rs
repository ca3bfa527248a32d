//! Preparing a job on the scheduler: checking the submitted scene
//! ([`validate`](mod@validate)), building the octree, predicting leaf costs, choosing
//! the leaves every worker holds and partitioning the rest within the
//! workers' shares and memory budgets ([`regions`]), and planning each
//! worker's BVH parts ([`parts`]) and memory ([`crate::memory`]).

use crate::{cost, memory};
use locus_core::geometry::Bounds;
use locus_core::irradiance::overture::{Measured, OvertureStats};
use locus_core::light::LightSet;
use locus_core::octree::Octree;
use locus_core::region::ProcessorMap;
use locus_core::region::WorkerId;
use locus_core::scene::{LoadStats, Scene};
use locus_protocol::control::MemoryPlan;
use locus_protocol::submit::{CostModel, FetchPolicy, JobOptions, JobRequest};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

pub use parts::{PartRun, part_triangles};
use parts::{cut_by_centroids, cut_parts};

mod parts;
mod regions;
mod validate;
pub use validate::{MAX_INFLIGHT, MAX_PACKET_ITEMS, MAX_TILES, validate};

pub struct Prepared {
    pub scene: Arc<Scene>,
    pub map: ProcessorMap,
    pub lights: LightSet,
    /// Per worker: its leaves with their triangle lists.
    pub own_leaves: Vec<Vec<(u32, Vec<u32>)>>,
    /// Per worker: its BVH parts, each a run of leaves it holds (its own,
    /// or every leaf when the job replicates the scene).
    pub parts: Vec<Vec<PartRun>>,
    /// Whether every worker holds the whole scene (`fetch` with room).
    pub replicated: bool,
    /// Per worker: triangles its shipment holds (a triangle in two parts
    /// counts twice).
    pub region_triangles: Vec<u64>,
    pub plans: Vec<MemoryPlan>,
    /// Per tile, the worker its camera rays meet first ([`crate::tiles`]);
    /// none when the scene is replicated.
    pub tile_affinity: Vec<Option<WorkerId>>,
    /// Per tile and worker, the preview paths in the tile that the worker
    /// starts without forwarding them ([`crate::tiles::votes`]), by which
    /// a worker out of tiles picks another's; empty without a preview or
    /// tiles by affinity.
    pub tile_votes: Vec<u32>,
    /// The leaves every worker holds as its own, ascending: the camera's
    /// ([`cost::camera_leaf`]) and those [`cost::shared_leaves`] picks
    /// ([`Self::map_for`]).
    pub shared_leaves: Vec<u32>,
    /// Per worker, the camera samples it keeps in flight.
    pub max_inflight: Vec<u32>,
    /// Triangle references per leaf.
    pub leaf_tris: Vec<u32>,
    /// The quality every BVH of the job is built at, decided here once
    /// from its settings and counts (`BvhSetting::quality`) and sent to
    /// every worker in its setup.
    pub bvh_quality: locus_core::accel::BuildQuality,
    /// The irradiance cache's overture, when it is on.
    pub irradiance: Option<PreparedOverture>,
    /// Each worker's threads.
    pub member_cores: Vec<u32>,
    /// Each worker's share of the predicted cost, as the partition
    /// balanced it: the analytic costs with the shared leaves counting for
    /// no one, the sampled ones with their work charged to the leaves that
    /// hold the paths there ([`cost::Preview::charged`]).
    pub analytic_share: Vec<f64>,
    pub sampled_share: Vec<f64>,
    /// The cost model the regions were drawn from: `Analytic` or
    /// `Sampled` (which `Small` and `Auto` are, from one preview or the
    /// other).
    pub cost_model: CostModel,
    /// Whether they were drawn from the small preview
    /// ([`cost::DECISION_PREVIEW`]): asked for, or the full one would not
    /// pay ([`cost::preview_pays`]).
    pub small_preview: bool,
    pub preview_rays: u64,
    /// The queries the preview predicts a path forwards under the
    /// partition and the tiles' affinities; none without a preview, with
    /// the scene replicated, or under random polling (tiles go to whoever
    /// asks).
    pub forwards_per_path: Option<f64>,
    pub leaves: u32,
    pub timings: PrepTimings,
    /// Seconds the scheduler spent building a replicated region's BVH
    /// layout (f64 bits; 0 without one), written by the build's task
    /// ([`crate::distribute`]).
    pub layout_s: Arc<std::sync::atomic::AtomicU64>,
}

impl Prepared {
    /// Worker `w`'s predicted share of the job's work under `model`: the
    /// partition's where the partition places the work; its share of the
    /// cores where every worker holds the scene, since tiles then go to
    /// whichever worker asks (the partition still drawn there places
    /// nothing: on the room, 35% and 65% predicted against 49% and 51%
    /// measured).
    pub fn predicted_share(&self, w: usize) -> f64 {
        if self.replicated {
            let cores = crate::actor::shares(&self.member_cores);
            let all: u64 = cores.iter().map(|&c| c as u64).sum();
            return cores.get(w).map_or(0.0, |&c| c as f64 / all.max(1) as f64);
        }
        match self.cost_model {
            CostModel::Analytic => self.analytic_share[w],
            _ => self.sampled_share[w],
        }
    }

    /// Worker `w`'s processor map: the job's, with the shared leaves its
    /// own. Every other leaf has one owner on every map, so where any two
    /// workers' maps are compared (a forwarded query's route node) they
    /// agree.
    pub fn map_for(&self, w: WorkerId) -> ProcessorMap {
        if self.shared_leaves.is_empty() {
            return self.map.clone();
        }
        let mut owner = self.map.owner.clone();
        for &l in &self.shared_leaves {
            owner[l as usize] = w;
        }
        ProcessorMap::new(&self.map.tree, owner)
    }
}

/// Who measures an attempt's irradiance records: its workers, where each
/// holds the whole scene; else the scheduler, here, every level the job
/// does not know yet.
pub struct PreparedOverture {
    pub by_workers: bool,
    /// The scene's bounds (the record octree's).
    pub bounds: Bounds,
    /// Levels measured here, after those known before.
    pub measured: Vec<Vec<Measured>>,
    pub stats: Option<OvertureStats>,
}

/// Where preparation's time went.
#[derive(Clone, Copy, Debug, Default)]
pub struct PrepTimings {
    pub total_s: f64,
    pub octree_s: f64,
    pub preview_s: f64,
    pub partition_s: f64,
}

/// What the scheduler knows of a worker when it plans a job.
#[derive(Clone, Copy, Debug)]
pub struct Member {
    pub cores: u32,
    pub budget: u64,
    pub resident: u64,
}

/// The job's octree: the scene's own parameters, refined until there are a
/// few leaves per worker (regions are made of leaves) or leaves hold one
/// triangle.
pub fn octree_for(scene: &Scene, workers: usize) -> Octree {
    let mut params = scene.settings.octree;
    let mut tree = Octree::build(&scene.tris, params);
    while workers > 1 && tree.leaves.len() < 4 * workers && params.max_leaf_tris > 1 {
        params.max_leaf_tris /= 2;
        params.max_depth = params.max_depth.max(8);
        tree = Octree::build(&scene.tris, params);
    }
    tree
}

/// The submitted scene, its triangles moved out of the request: kept by
/// the running job for its whole life, so that an attempt after a lost
/// worker is prepared again from it without the client.
pub fn scene_of(req: &mut JobRequest) -> Arc<Scene> {
    Arc::new(Scene {
        path: PathBuf::from(&req.name),
        camera: req.camera.clone(),
        settings: req.settings.clone(),
        materials: req.materials.clone(),
        tris: std::mem::take(&mut req.tris),
        tri_material: std::mem::take(&mut req.tri_material),
        tri_normals: std::mem::take(&mut req.tri_normals),
        load_stats: LoadStats::default(),
    })
}

/// Builds the job's octree, predicts leaf costs, partitions the leaves
/// among `members` by their cores within their memory budgets, and plans
/// each worker's parts and memory. Fails when the budgets cannot hold the
/// scene.
pub fn prepare(
    scene: Arc<Scene>,
    options: &JobOptions,
    members: &[Member],
    tiles: &[locus_core::render::Tile],
    known: &[Arc<Vec<Measured>>],
) -> Result<Prepared, String> {
    let t = Instant::now();
    let workers = members.len().max(1);
    let t_oct = Instant::now();
    let tree = octree_for(&scene, workers);
    let octree_s = t_oct.elapsed().as_secs_f64();
    let caches = options.cache.is_some();
    let tb = memory::TriangleBytes::of(!scene.tri_normals.is_empty());
    let usable: Vec<Option<u64>> = members
        .iter()
        .map(|m| memory::usable(m.budget, m.resident))
        .collect();
    let caps: Vec<Option<u64>> = usable
        .iter()
        .map(|&u| memory::region_cap(u, caches, tb))
        .collect();
    let cores: f64 = members.iter().map(|m| m.cores.max(1) as f64).sum();
    let targets: Vec<f64> = members
        .iter()
        .map(|m| m.cores.max(1) as f64 / cores)
        .collect();
    let refs: Vec<u64> = tree.leaves.iter().map(|l| l.tris.len() as u64).collect();
    let all_refs: u64 = refs.iter().sum();
    // Shipping geometry instead of rays, when every worker's plan can
    // hold the whole scene, is cheapest done once, now: each worker builds
    // one BVH over everything and no ray ever waits. `fetch` always does
    // so (and its regions carry no traffic, so no preview is needed to
    // draw them); `adaptive` does when the preview predicts that the rays
    // would cost more bytes than the geometry (see [`cost::buying_pays`]).
    let fits_everywhere = workers > 1
        && all_refs * tb.region <= options.fetch_budget
        && caps.iter().all(|c| c.is_none_or(|c| c >= all_refs));
    let replicate_now = options.fetch == FetchPolicy::Fetch && fits_everywhere;
    // A lone worker holds every leaf: there is nothing to partition and no
    // ray to forward, so the preview (a quarter of a second on the room)
    // would predict nothing the job uses.
    let needs_preview = workers > 1 && !replicate_now;
    // The job's BVH quality, decided here once and sent to every worker:
    // the regions' preview counts BVH steps on a tree built as the
    // workers will build theirs, and a replicated job's layout is built
    // the same way.
    let samples = scene.camera.samples(scene.settings.spp);
    let bvh_quality = scene.settings.bvh.quality(samples, all_refs);
    // A job too small for the full preview to pay draws its regions from
    // the small one `adaptive` decides to buy on ([`cost::preview_pays`]),
    // but for an `adaptive` job whose scene does not fit every worker: it
    // fetches leaves by what its preview counted, and fetched far more
    // from the small one's counts.
    let preview_pays = match options.cost_model {
        CostModel::Small => false,
        CostModel::Auto => {
            cost::preview_pays(samples, all_refs)
                || (options.fetch == FetchPolicy::Adaptive && !fits_everywhere)
        }
        CostModel::Sampled | CostModel::Analytic => true,
    };
    // Every sampled model is `Sampled` from here on; `small_preview`
    // below says which preview it came from.
    let cost_model = match options.cost_model {
        CostModel::Analytic => CostModel::Analytic,
        _ => CostModel::Sampled,
    };
    let t_pre = Instant::now();
    let lights = LightSet::build(&scene);
    let analytic = cost::analytic(&tree);
    let sampled_model = cost_model == CostModel::Sampled && needs_preview;
    // `adaptive` with the whole scene fitting everywhere asks first only
    // whether to buy, on a preview BVH of small parts built at once (see
    // [`cost::DECISION_PREVIEW`]); only a job that then rents, and so draws regions
    // that carry rays, pays for the preview those regions are drawn from.
    let decide_first = sampled_model && options.fetch == FetchPolicy::Adaptive && fits_everywhere;
    // The preview the regions are drawn from.
    let regions_preview = if preview_pays {
        cost::PreviewSize {
            quality: bvh_quality,
            ..cost::FULL_PREVIEW
        }
    } else {
        cost::DECISION_PREVIEW
    };
    let first = if decide_first {
        cost::DECISION_PREVIEW
    } else {
        regions_preview
    };
    let mut pv = sampled_model.then(|| cost::sampled_in_parts(&scene, &tree, &lights, first));
    let mut preview_s = t_pre.elapsed().as_secs_f64();
    // The camera's leaf is every worker's (below), and so is its work:
    // each worker shades there what its own rays bring. It weighs on no
    // one region. So are the leaves [`cost::shared_leaves`] picks from the
    // preview's crossings, where they fit every worker's budget.
    let drawing = regions::Draw {
        tree: &tree,
        refs: &refs,
        all_refs,
        targets: &targets,
        caps: &caps,
        analytic: &analytic,
        camera: (workers > 1)
            .then(|| cost::camera_leaf(&tree, &scene.camera))
            .flatten(),
        partitioner: options.partitioner,
        shared_percent: options.tuning.shared_percent,
        view: (workers >= 2 && !options.tuning.random_polling).then_some((&scene.camera, tiles)),
    };
    let t_part = Instant::now();
    // Regions drawn only to decide whether to buy are drawn again from the
    // full preview if the job rents: the shared leaves are not picked
    // again for them.
    let mut drawn = if decide_first {
        regions::Draw {
            view: None,
            ..drawing
        }
        .drawn(pv.as_ref())?
    } else {
        drawing.drawn(pv.as_ref())?
    };
    let mut partition_s = t_part.elapsed().as_secs_f64();
    // The rent counts every crossing between two owners' leaves, those
    // into or out of a shared leaf too (no query is forwarded into one):
    // it leans towards buying, which on a fast network is the quicker.
    let buys = |pv: &Option<cost::Preview>, owner: &[WorkerId]| {
        pv.as_ref().is_some_and(|pv| {
            let bytes = all_refs * tb.shipped;
            cost::buying_pays(&pv.crossings, owner, workers, bytes, samples, pv.paths)
        })
    };
    let replicated = replicate_now
        || (options.fetch == FetchPolicy::Adaptive && fits_everywhere && buys(&pv, &drawn.owner));
    // Every ray a preview traced is counted, the decision's too.
    let mut decision_rays = 0;
    if decide_first && !replicated {
        // The decision preview is the job's whole preview where the full
        // one would not pay.
        if preview_pays {
            decision_rays = pv.as_ref().map_or(0, |pv| pv.rays);
            let t = Instant::now();
            pv = Some(cost::sampled_in_parts(
                &scene,
                &tree,
                &lights,
                regions_preview,
            ));
            preview_s += t.elapsed().as_secs_f64();
        }
        let t = Instant::now();
        drawn = drawing.drawn(pv.as_ref())?;
        partition_s += t.elapsed().as_secs_f64();
    }
    let regions::Drawn {
        mut shared,
        owner,
        balanced,
        judged,
    } = drawn;
    // Under random polling tiles go to whoever asks: a worker that has
    // fetched a hot region's leaves renders its tiles, and the owner's
    // queued work is handed to idle pollers. With affinity, a worker with
    // no tiles of its own would live on forwarded and handed work alone.
    let by_affinity = !replicated && workers >= 2 && !options.tuning.random_polling;
    // Where each tile goes, by where the preview's paths in it go first
    // beside the shared leaves, and so which worker starts each path; and
    // the queries a path forwards, predicted from the preview's paths with
    // each started by its tile's worker.
    let judged = judged.filter(|_| by_affinity);
    let forwards_per_path = pv
        .as_ref()
        .zip(judged.as_ref())
        .filter(|(pv, _)| pv.paths > 0)
        .map(|(pv, j)| j.forwards as f64 / pv.paths as f64);
    // What the regions balanced (the shared leaves' work charged to the
    // leaves that hold the paths there), or, with the whole scene
    // replicated below, every leaf's own.
    let sampled = match pv.as_ref() {
        Some(pv) if replicated => pv.cost.clone(),
        _ => balanced,
    };
    let preview_rays = pv.as_ref().map_or(0, |pv| decision_rays + pv.rays);
    let leaf_ids: Vec<Vec<u32>> = tree
        .leaves
        .iter()
        .map(|l| {
            let mut ids = l.tris.clone();
            ids.sort_unstable();
            ids.dedup();
            ids
        })
        .collect();
    // Every worker holds the shared leaves (the camera's, see
    // `cost::camera_leaf`, and `cost::shared_leaves`), as its own: each
    // gets a processor map in which it owns them, so no ray is ever
    // forwarded into one and any worker starts samples.
    if replicated {
        shared.fill(false);
    }
    let shared_leaves: Vec<u32> = (0..tree.leaves.len() as u32)
        .filter(|&l| shared[l as usize])
        .collect();
    let mut own_leaves = vec![Vec::new(); workers];
    for (i, &o) in owner.iter().enumerate() {
        if shared[i] {
            for own in &mut own_leaves {
                own.push((i as u32, leaf_ids[i].clone()));
            }
        } else {
            own_leaves[o as usize].push((i as u32, leaf_ids[i].clone()));
        }
    }
    let everything: Vec<(u32, Vec<u32>)> = if replicated {
        (0..tree.leaves.len() as u32)
            .map(|l| (l, leaf_ids[l as usize].clone()))
            .collect()
    } else {
        Vec::new()
    };
    let map = ProcessorMap::new(&tree, owner);
    let (tile_affinity, tile_votes) = match judged {
        Some(j) => (j.starts.tiles, j.starts.votes),
        // Without a preview, by the camera's rays alone.
        None if by_affinity => (
            crate::tiles::affinities(
                &scene.camera,
                &tree,
                &map.owner,
                &shared,
                tiles,
                &[],
                workers,
            ),
            Vec::new(),
        ),
        None => (vec![None; tiles.len()], Vec::new()),
    };
    // Nothing below needs the preview's walks, which are large.
    drop(pv);
    let mut plans = Vec::with_capacity(workers);
    let mut parts = Vec::with_capacity(workers);
    let mut region_triangles = Vec::with_capacity(workers);
    // Cut once per distinct (leaves held, part size, cut): on the room,
    // four of the five passes over 325,000 triangles' ids were repeats.
    let mut cut: HashMap<(usize, u32, bool), (Vec<PartRun>, u64)> = HashMap::new();
    // A worker with a memory budget joins its region's parts into one BVH
    // (`accel_set::join`), whatever comes to it later (fetched leaves make
    // parts of their own), and so does one that holds the scene
    // replicated: they are cut by centroid, tight and apart, rather than as
    // runs of whole leaves, which joined trace at 0.55-0.74 of one BVH.
    for (w, m) in members.iter().enumerate() {
        let held_leaves = if replicated {
            &everything
        } else {
            &own_leaves[w]
        };
        let held: u64 = held_leaves.iter().map(|(_, t)| t.len() as u64).sum();
        let plan = memory::plan(
            m.budget,
            usable[w],
            held,
            options.cache.map(|c| c.max_nodes_total as u64),
            options.fetch_budget,
            tb,
        );
        let held_by = if replicated { usize::MAX } else { w };
        let by_centroid = plan.budget > 0;
        let (p, n) = cut
            .entry((held_by, plan.part_triangles, by_centroid))
            .or_insert_with(|| {
                if by_centroid {
                    cut_by_centroids(held_leaves, plan.part_triangles as usize, &scene)
                } else {
                    cut_parts(held_leaves, plan.part_triangles as u64)
                }
            })
            .clone();
        plans.push(plan);
        parts.push(p);
        region_triangles.push(n);
    }
    // The irradiance cache's overture, once the job is known to fit:
    // workers that hold the whole scene measure its levels between them;
    // for others it is measured here, on every triangle (a BVH over the
    // whole scene, like one machine's), from the first level not known.
    let bounds = Bounds::of_triangles(&scene.tris);
    let irradiance = options.irradiance.map(|p| {
        if replicated || workers == 1 {
            return PreparedOverture {
                by_workers: true,
                bounds,
                measured: Vec::new(),
                stats: None,
            };
        }
        let before: Vec<Vec<Measured>> = known.iter().map(|l| l.to_vec()).collect();
        let (_, stats, mut levels) =
            locus_core::irradiance::overture::for_scene(&scene, &lights, p, &before);
        PreparedOverture {
            by_workers: false,
            bounds,
            measured: levels.split_off(before.len()),
            stats: Some(stats),
        }
    });
    Ok(Prepared {
        bvh_quality,
        shared_leaves,
        irradiance,
        member_cores: members.iter().map(|m| m.cores).collect(),
        leaf_tris: tree.leaves.iter().map(|l| l.tris.len() as u32).collect(),
        analytic_share: cost::shares(&regions::unshared(&analytic, &shared), &map.owner, workers),
        sampled_share: cost::shares(&sampled, &map.owner, workers),
        cost_model,
        small_preview: sampled_model && !preview_pays,
        preview_rays,
        forwards_per_path,
        leaves: tree.leaves.len() as u32,
        max_inflight: crate::tiles::inflight(&tile_affinity, workers, options.tuning.max_inflight)
            .into_iter()
            .zip(members)
            // A worker with a budget keeps its queues within the plan's
            // room for them.
            .map(|(n, m)| memory::inflight_cap(n, m.budget, options.tuning.random_polling))
            .collect(),
        map,
        tile_affinity,
        tile_votes,
        own_leaves,
        parts,
        replicated,
        region_triangles,
        plans,
        lights,
        scene,
        layout_s: Default::default(),
        timings: PrepTimings {
            total_s: t.elapsed().as_secs_f64(),
            octree_s,
            preview_s,
            partition_s,
        },
    })
}

#[cfg(test)]
mod tests;
