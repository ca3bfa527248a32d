//! What a job reports: per-worker counters (all counted where the work
//! happened) and the job's derived figures.

use locus_core::dircache::CacheMemory;
use locus_core::stats::TraceStats;
use serde::{Deserialize, Serialize};

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
    /// Trace items received from peers.
    pub queries_in: u64,
    /// Answers sent to peers.
    pub answers_out: u64,
    /// Indexed by peer worker id (own entry stays zero).
    pub peers: Vec<PeerTraffic>,
    pub busy_s: f64,
    pub idle_s: f64,
    /// Times origination stopped because a peer's queue was full.
    pub backpressure_stalls: u64,
    pub tiles: u32,
    pub triangles: u64,
    pub leaves: u32,
    pub bvh_build_s: f64,
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
}

/// Job totals: counters add up, the BVH build time is the slowest
/// worker's, and per-peer traffic stays with each worker.
impl std::ops::AddAssign<&WorkerStats> for WorkerStats {
    fn add_assign(&mut self, o: &WorkerStats) {
        self.trace += o.trace;
        self.forwarded_out += o.forwarded_out;
        self.queries_in += o.queries_in;
        self.answers_out += o.answers_out;
        self.busy_s += o.busy_s;
        self.idle_s += o.idle_s;
        self.backpressure_stalls += o.backpressure_stalls;
        self.tiles += o.tiles;
        self.triangles += o.triangles;
        self.leaves += o.leaves;
        self.bvh_build_s = self.bvh_build_s.max(o.bvh_build_s);
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

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Phases {
    pub partition_s: f64,
    pub distribution_s: f64,
    pub render_s: f64,
    pub total_s: f64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Pearson correlation, over workers, of predicted and measured cost
    /// shares, for each model.
    pub analytic_r: f64,
    pub sampled_r: f64,
    /// Work counted by the sampled predictor's preview.
    pub preview_rays: u64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FarmReport {
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    pub partitioner: String,
    pub cost_model: String,
    pub leaves: u32,
    pub triangles: u64,
    pub phases: Phases,
    pub prediction: Prediction,
    pub workers: Vec<WorkerSummary>,
    pub totals: WorkerStats,
    /// Max over mean of busy time.
    pub load_imbalance: f64,
    /// Trace items forwarded over all local traces.
    pub forwarded_fraction: f64,
    pub bytes_per_sample: f64,
    pub samples_per_s: f64,
}
