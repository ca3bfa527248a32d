//! What a job reports: per-worker counters (all counted where the work
//! happened) and the job's derived figures.

use locus_core::dircache::CacheMemory;
use locus_core::path::Query;
use locus_core::stats::TraceStats;
use serde::{Deserialize, Serialize};

/// Queries forwarded to peers, by what they ask: which of a path's rays
/// leave a worker's region says where a partition or a tile's placement
/// costs (a camera ray forwarded is a tile started away from where its
/// paths go; a bounce, a border its paths cross).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ForwardKinds {
    /// Camera rays.
    pub camera: u64,
    /// A path's later rays (directional-cache segments too), by the path
    /// vertices before them: 1, 2, 3, and 4 or more.
    pub bounces: [u64; 4],
    /// Shadow rays.
    pub shadow: u64,
}

impl ForwardKinds {
    /// Counts query `q`, forwarded.
    pub fn count(&mut self, q: &Query) {
        match q {
            Query::Path(p) | Query::Segment(p) if p.depth == 0 => self.camera += 1,
            Query::Path(p) | Query::Segment(p) => {
                self.bounces[(p.depth as usize).min(4) - 1] += 1;
            }
            Query::Shadow(_) => self.shadow += 1,
        }
    }

    /// Every query counted.
    pub fn total(&self) -> u64 {
        self.camera + self.bounces.iter().sum::<u64>() + self.shadow
    }
}

impl std::ops::AddAssign for ForwardKinds {
    fn add_assign(&mut self, o: Self) {
        self.camera += o.camera;
        for (a, b) in self.bounces.iter_mut().zip(o.bounces) {
            *a += b;
        }
        self.shadow += o.shadow;
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PeerTraffic {
    pub msgs_sent: u64,
    pub bytes_sent: u64,
    pub msgs_recv: u64,
    pub bytes_recv: u64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorkerStats {
    /// Rays by kind as originated here, plus BVH work done here.
    pub trace: TraceStats,
    /// Trace items sent to a peer.
    pub forwarded_out: u64,
    /// The same, by what they ask.
    pub forwards: ForwardKinds,
    /// Trace items received from peers.
    pub queries_in: u64,
    /// Answers sent to peers.
    pub answers_out: u64,
    /// Indexed by peer worker id (own entry stays zero).
    pub peers: Vec<PeerTraffic>,
    pub busy_s: f64,
    pub idle_s: f64,
    /// Of `busy_s`, the time the engine's thread waited for batches out on
    /// its tracing pool with nothing else to do. An engine that never
    /// waits holds its pool back: its serial bookkeeping, not its tracing
    /// threads, sets the pace.
    pub engine_wait_s: f64,
    /// Times origination stopped because a peer's queue was full.
    pub backpressure_stalls: u64,
    pub tiles: u32,
    /// Of `tiles`, those traced whole, a pool task each, with no slot per
    /// sample: by a worker that held every leaf when the tile started.
    pub whole_tiles: u32,
    pub triangles: u64,
    pub leaves: u32,
    pub bvh_build_s: f64,
    /// Of the worker's BVH parts, those another worker of its process
    /// built for the same triangles (the embedded farm's workers share
    /// them): this worker's `bvh_build_s` was then spent waiting.
    pub shared_parts: u32,
    /// Of the worker's BVH parts, those whose layout the scheduler built
    /// once for every worker of a replicated job: this worker's
    /// `bvh_build_s` was spent checking it and gathering its triangles.
    pub shipped_layouts: u32,
    /// Directional caches held at the end of the job.
    pub cache_memory: CacheMemory,
    /// Remote leaves this worker asked for (merged requests count once).
    pub fetch_requests: u64,
    /// Leaf geometry frames received, and their bytes on the wire.
    pub fetched_leaves: u64,
    pub fetched_bytes: u64,
    /// Leaves this worker shipped to peers that fetched them.
    pub leaves_served: u64,
    /// Largest weight the fetched-leaf cache reached, and its bound.
    pub fetch_cache_peak: u64,
    pub fetch_cache_bound: u64,
    /// Rays that waited for a fetch, and ray crossings of fetched leaves.
    pub fetch_waits: u64,
    pub fetched_leaf_traces: u64,
    /// CPU seconds the worker spent on the job: its whole process's when it
    /// runs alone (a daemon), otherwise its own threads' (engine, tracing
    /// pool, builder); counted by the kernel, not estimated.
    pub cpu_s: f64,
    /// Of `cpu_s`, what went before tracing: receiving and building the
    /// region, linking the peers (0 when the worker shares its process).
    pub setup_cpu_s: f64,
    /// Peak resident memory of the worker's process during the job, read
    /// from the kernel (VmHWM, reset at the job's start); 0 when the worker
    /// shares its process (the embedded farm), where it cannot be told
    /// apart.
    pub peak_rss: u64,
    /// The budget the worker kept to (0: none).
    pub memory_budget: u64,
    /// Bytes of the region's own BVH parts, geometry included.
    pub region_bytes: u64,
    /// BVH parts the worker's geometry was built in (at the end).
    pub parts: u32,
    /// Most bytes of fetched geometry held at once, merged into parts or
    /// waiting to be.
    pub fetched_held_peak: u64,
    /// Rebuilds of BVH parts that merged fetched leaves, and their time.
    pub rebuilds: u32,
    pub rebuild_s: f64,
    /// Random polling: polls sent, polls answered with work, and queries
    /// handed to pollers and received from the polled.
    pub polls: u64,
    pub polls_answered: u64,
    pub handed_out: u64,
    pub handed_in: u64,
}

/// Job totals: counters add up; the BVH build time, the peaks and the
/// budget are the largest worker's; per-peer traffic stays with each
/// worker.
impl std::ops::AddAssign<&WorkerStats> for WorkerStats {
    fn add_assign(&mut self, o: &WorkerStats) {
        self.trace += o.trace;
        self.forwarded_out += o.forwarded_out;
        self.forwards += o.forwards;
        self.queries_in += o.queries_in;
        self.answers_out += o.answers_out;
        self.busy_s += o.busy_s;
        self.idle_s += o.idle_s;
        self.engine_wait_s += o.engine_wait_s;
        self.backpressure_stalls += o.backpressure_stalls;
        self.tiles += o.tiles;
        self.whole_tiles += o.whole_tiles;
        self.triangles += o.triangles;
        self.leaves += o.leaves;
        self.bvh_build_s = self.bvh_build_s.max(o.bvh_build_s);
        self.shared_parts += o.shared_parts;
        self.shipped_layouts += o.shipped_layouts;
        let (a, b) = (&mut self.cache_memory, &o.cache_memory);
        a.leaves_with_cache += b.leaves_with_cache;
        a.nodes += b.nodes;
        a.bytes += b.bytes;
        a.max_leaf_bytes = a.max_leaf_bytes.max(b.max_leaf_bytes);
        self.fetch_requests += o.fetch_requests;
        self.fetched_leaves += o.fetched_leaves;
        self.fetched_bytes += o.fetched_bytes;
        self.leaves_served += o.leaves_served;
        self.fetch_cache_peak = self.fetch_cache_peak.max(o.fetch_cache_peak);
        self.fetch_cache_bound = self.fetch_cache_bound.max(o.fetch_cache_bound);
        self.fetch_waits += o.fetch_waits;
        self.fetched_leaf_traces += o.fetched_leaf_traces;
        self.cpu_s += o.cpu_s;
        self.setup_cpu_s += o.setup_cpu_s;
        self.peak_rss = self.peak_rss.max(o.peak_rss);
        self.memory_budget = self.memory_budget.max(o.memory_budget);
        self.region_bytes += o.region_bytes;
        self.parts += o.parts;
        self.fetched_held_peak = self.fetched_held_peak.max(o.fetched_held_peak);
        self.rebuilds += o.rebuilds;
        self.rebuild_s += o.rebuild_s;
        self.polls += o.polls;
        self.polls_answered += o.polls_answered;
        self.handed_out += o.handed_out;
        self.handed_in += o.handed_in;
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorkerSummary {
    pub id: u16,
    pub addr: String,
    pub predicted_cost_share: f64,
    /// Share of the job's BVH node visits plus triangle tests.
    pub measured_cost_share: f64,
    pub stats: WorkerStats,
}

/// Where a job's time went, phase by phase (seconds of wall time).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Phases {
    /// Reading and parsing the scene, on the submitting side (0 when the
    /// client did not say).
    pub load_s: f64,
    /// Everything the scheduler does before distribution: the three below
    /// and cutting out the regions.
    pub prepare_s: f64,
    pub octree_s: f64,
    /// Cost prediction: the preview's BVH and its rays.
    pub preview_s: f64,
    /// Assigning leaves to workers.
    pub partition_s: f64,
    /// From the end of preparation until every worker is ready: shipping
    /// regions, building their BVHs, linking the peers.
    pub distribution_s: f64,
    /// The slowest worker's region BVH build (part of distribution).
    pub bvh_s: f64,
    /// The scheduler's build of a replicated region's BVH layout, once for
    /// the workers that take it (part of distribution, beside the
    /// shipping; 0 without one).
    pub layout_s: f64,
    /// From the first tile handed out until the last tile is in.
    pub render_s: f64,
    /// From the submission until the result is sent.
    pub total_s: f64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Pearson correlation, over workers, of predicted and measured cost
    /// shares, for each model. None where it says nothing: with fewer than
    /// three workers (over two points it is +1 or -1 whatever the
    /// prediction), or with the scene replicated (no partition placed the
    /// work; each worker's share is what tiles it took).
    pub analytic_r: Option<f64>,
    pub sampled_r: Option<f64>,
    /// Work counted by the sampled predictor's preview.
    pub preview_rays: u64,
    /// The queries a camera sample's path forwards, as the preview counts
    /// them under the partition (its crossings between two workers' leaves
    /// beside the shared ones, each tile started where its paths go
    /// first), against which the farm's counted forwards a sample tell how
    /// well the partition was predicted. None without a preview, with the
    /// scene replicated, or under random polling (tiles go to whoever
    /// asks, so no worker is known to start a path).
    pub forwards_per_path: Option<f64>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FarmReport {
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    /// The sampler's name ("sobol", "independent").
    pub sampler: String,
    pub partitioner: String,
    pub cost_model: String,
    /// The fetch policy asked for.
    pub policy: String,
    /// Whether every worker held the whole scene (`fetch`, or `adaptive`
    /// when its rent-or-buy rule bought everything at the start).
    pub replicated: bool,
    /// The quality every BVH of the job was built at (the scheduler's
    /// preview and layout, the workers' regions).
    #[serde(default)]
    pub bvh_quality: locus_core::accel::BuildQuality,
    pub leaves: u32,
    pub triangles: u64,
    /// Nodes of the processor map's route (the octree collapsed by owner):
    /// how ragged the region borders are.
    pub route_leaves: u32,
    /// Leaves every worker held beside its region (the camera's and the
    /// most crossed per triangle: `Tuning::shared_percent`), and their
    /// triangle references.
    pub shared_leaves: u32,
    pub shared_refs: u64,
    pub phases: Phases,
    pub prediction: Prediction,
    pub workers: Vec<WorkerSummary>,
    pub totals: WorkerStats,
    /// Max over mean of the workers' render-phase CPU time (of their busy
    /// time where CPU time was not counted).
    pub load_imbalance: f64,
    /// Max over mean of the workers' whole CPU time on the job, setup
    /// (receiving and building the region) included; the render-phase
    /// figure where CPU time was not counted. A partition places both: a
    /// worker with fewer triangles to build starts rendering first and
    /// takes more tiles, which `load_imbalance` charges as imbalance and
    /// this figure, rightly, does not.
    pub total_imbalance: f64,
    /// Trace items forwarded over all local traces.
    pub forwarded_fraction: f64,
    pub bytes_per_sample: f64,
    pub samples_per_s: f64,
    /// What the job survived. The counters above are the last attempt's:
    /// a lost worker never reports.
    pub recovery: Recovery,
    /// The irradiance cache's overture, when it was on.
    pub irradiance: Option<IrradianceReport>,
    /// The error the image carries, from its samples' spread (as one
    /// machine's report gives it); None for one sample a pixel.
    pub error_estimate: Option<locus_core::metrics::ErrorEstimate>,
    /// The noise target (an estimated relMSE) the job stopped at, if any.
    pub target_rel_mse: Option<f64>,
    /// Samples each pixel got: `spp`, or fewer where the noise target was
    /// met at an earlier pass's end; with adaptive sampling, the mean.
    pub spp_rendered: u32,
    /// With adaptive sampling, the fewest and most samples a pixel got and
    /// their mean, counted from the film's counts.
    pub sample_counts: Option<locus_core::report::SampleCounts>,
}

/// How the irradiance cache's records were made and shared: measured
/// level by level by the workers (where each holds the whole scene) or by
/// the scheduler, and every level sent to every worker.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IrradianceReport {
    pub records: u64,
    /// Rays traced to place and measure them, by whoever measured (those
    /// of an attempt that was cut short included).
    pub rays: u64,
    /// Seconds of measuring: per level the slowest measurer's, summed.
    pub seconds: f64,
    /// Whether the workers measured them (else the scheduler did).
    pub by_workers: bool,
    /// Bytes of measurements the workers sent the scheduler, as encoded.
    pub bytes_gathered: u64,
    /// Bytes of records sent to the workers, all of them together, as
    /// encoded.
    pub bytes_sent: u64,
}

/// Workers a job lost and the attempts it took: after a loss the job is
/// partitioned again over the workers left and only its unfinished tiles
/// are rendered again; the image is the same bits either way.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Recovery {
    /// Attempts the job took (1: nothing failed).
    pub attempts: u32,
    /// Each worker lost during the job: its address and why.
    pub lost: Vec<(String, String)>,
    /// Tile passes finished in earlier attempts (or before a scheduler
    /// restart) and kept.
    pub tile_passes_kept: u64,
    /// The work of aborted attempts, as their workers reported it when
    /// they stopped (a lost worker reports nothing): the report's totals
    /// are the last attempt's.
    pub aborted: locus_core::stats::TraceStats,
    /// Reports of aborted attempts received.
    pub aborted_reports: u32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::geometry::Ray;
    use locus_core::integrator::{PathRay, ShadowRay};
    use locus_core::sampler::SampleKey;

    /// Each query goes to its kind's count, bounces by the vertices before
    /// them (the deepest count together), and the counts add up.
    #[test]
    fn forwards_are_counted_by_kind_and_depth() {
        let ray = Ray::new(glam::Vec3::ZERO, glam::Vec3::X);
        let path = |depth| {
            let mut p = PathRay::camera(ray, SampleKey::independent(0, 0, 1));
            p.depth = depth;
            p
        };
        let mut k = ForwardKinds::default();
        for d in [0, 1, 1, 2, 3, 4, 7, 12] {
            k.count(&Query::Path(path(d)));
        }
        k.count(&Query::Segment(path(2)));
        k.count(&Query::Shadow(ShadowRay { ray, t_max: 1.0 }));
        let want = ForwardKinds {
            camera: 1,
            bounces: [2, 2, 1, 3],
            shadow: 1,
        };
        assert_eq!(k, want);
        assert_eq!(k.total(), 10);
        let mut sum = k;
        sum += want;
        assert_eq!(sum.bounces, [4, 4, 2, 6]);
        assert_eq!(sum.total(), 20);
    }
}
