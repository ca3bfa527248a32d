//! Scheduler and workers: registration, job setup with the region's
//! geometry, demand-driven tiles, and the end-of-job report.
//!
//! A worker opens with [`Opening::Register`]; a client with
//! [`Opening::Submit`] (see [`crate::submit`]). Variants are only ever
//! appended.

use crate::report::WorkerStats;
use crate::submit::FetchPolicy;
use crate::submit::JobRequest;
use locus_core::dircache::CacheParams;
pub use locus_core::geometry::TriangleSet;
use locus_core::light::LightSet;
use locus_core::passes::Moments;
use locus_core::region::{ProcessorMap, WorkerId};
use locus_core::sampler::Sampler;
use locus_core::scene::{Camera, Material};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// The first message on a connection to the scheduler, after the handshake.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Opening {
    Register(Registration),
    Submit(Box<JobRequest>),
    /// A client takes up a job it submitted earlier (its link broke, or the
    /// scheduler restarted): the job's messages come on this link from now
    /// on, and a job already finished is sent at once.
    Attach {
        job: u64,
    },
    /// A job whose triangles follow in [`TrianglePart`]s, `triangles` in
    /// all: a scene of any size, in frames within the limit. `request`
    /// carries everything else (its triangle lists are empty).
    ///
    /// [`TrianglePart`]: crate::submit::TrianglePart
    SubmitInParts {
        request: Box<JobRequest>,
        triangles: u64,
        /// Whether every part carries its triangles' shading normals.
        normals: bool,
    },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Registration {
    /// Where peers reach this worker (host:port).
    pub listen: String,
    /// Threads its compute pool runs.
    pub cores: u32,
    /// Bytes of memory the worker's process may use (0: no limit); its
    /// region, BVH builds, fetched leaves and caches are planned to fit.
    pub memory_budget: u64,
    /// Resident bytes of the worker's process when it registered (0 when
    /// unknown): what the budget must hold besides any job.
    pub resident: u64,
    pub name: String,
    /// Whether it takes a BVH layout of a replicated region built by the
    /// scheduler ([`SchedulerToWorker::Layout`]). The
    /// embedded farm's workers do not: they build once for the process.
    pub layouts: bool,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum WorkerToScheduler {
    /// The region's BVH is built and the links to every peer are up.
    Ready {
        job: u64,
    },
    /// Demand-driven tiles: the worker has room for `count` more.
    NeedTiles {
        job: u64,
        count: u32,
    },
    TileDone(TileResult),
    Report {
        job: u64,
        stats: Box<WorkerStats>,
    },
    Failed {
        job: u64,
        reason: String,
    },
    /// The worker is alive, whatever its engine is doing.
    Heartbeat,
    /// A radiosity node's message to the coordinator.
    Node {
        job: u64,
        msg: Box<crate::radiosity::ToCoordinator>,
    },
    /// The worker's measurements of an overture level.
    Measured(Box<crate::overture::MeasuredChunk>),
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SchedulerToWorker {
    Welcome {
        worker: u32,
        /// How often each side says it is alive ([`Heartbeat`]); a link
        /// silent for [`HEARTBEATS_MISSED`] of these is lost.
        ///
        /// [`Heartbeat`]: SchedulerToWorker::Heartbeat
        heartbeat_ms: u32,
    },
    StartJob(Box<JobSetup>),
    /// One BVH part of the worker's region: the triangles of `leaves`
    /// (ascending, each triangle once); `last` closes the shipment. Workers
    /// shipped the same part share one `chunk` at the scheduler, which
    /// each connection encodes as it writes.
    Geometry {
        job: u64,
        leaves: Vec<u32>,
        chunk: std::sync::Arc<TriangleSet>,
        last: bool,
    },
    /// After the last part, where the job's setup announced it
    /// ([`JobSetup::layout`]): the BVH over the whole region, built once by
    /// the scheduler for every worker that holds it. The worker checks it
    /// against its triangles and stores them in its order instead of
    /// building; `None` (the scheduler's build failed) and it builds. One
    /// layout is shared by every worker's message (`Arc`): the scheduler
    /// holds it once however many workers take it, and each connection
    /// encodes it as it writes.
    Layout {
        job: u64,
        layout: Option<std::sync::Arc<locus_core::accel::Layout>>,
    },
    Tile(TileAssignment),
    NoMoreTiles {
        job: u64,
    },
    /// Every tile is in: report and drop the job.
    EndJob {
        job: u64,
    },
    /// The job failed elsewhere: drop it without reporting.
    AbortJob {
        job: u64,
        reason: String,
    },
    /// The scheduler is alive (sent every `heartbeat_ms` of [`Welcome`]).
    ///
    /// [`Welcome`]: SchedulerToWorker::Welcome
    Heartbeat,
    /// Be a node of a radiosity job: link to the other nodes, then wait for
    /// the coordinator's shots.
    StartNode(Box<crate::radiosity::NodeJob>),
    /// The coordinator's message to a radiosity node (a shot, `Finish`).
    Node {
        job: u64,
        msg: Box<crate::radiosity::ToNode>,
    },
    /// An overture level's records, every member's merged.
    Level(Box<crate::overture::LevelChunk>),
}

/// Heartbeats a link may miss before the other side counts it lost: a
/// worker (or scheduler) silent for this many intervals is stopped,
/// crashed or cut off.
pub const HEARTBEATS_MISSED: u32 = 5;

/// Per-job knobs of the ray traffic.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tuning {
    /// Most ray items per packet. Paper 003 used 50 samples per packet;
    /// here a packet leaves early whenever its sender runs out of work, so
    /// a large cap costs no latency and spreads a frame's fixed costs
    /// (a system call and a wake-up on each side) over many items.
    pub packet_size: u32,
    /// A partly filled packet is sent after this long even while its
    /// sender is busy.
    pub flush_us: u32,
    /// Camera samples a worker keeps in flight; bounds every queue. Enough
    /// that each worker always has work while its samples' forwarded
    /// queries travel (a sample in flight holds a few hundred bytes).
    pub max_inflight: u32,
    /// Tiles a worker holds at once.
    pub tiles_ahead: u32,
    /// Random polling for hot regions (paper 003, section 5.2): an idle
    /// worker asks a random peer for queued queries and traces them,
    /// fetching the peer's leaves they cross.
    pub random_polling: bool,
    /// Percent of the scene's triangle references that every worker holds
    /// beside its region when rays are forwarded: the leaves a preview's
    /// paths cross most per triangle (see the scheduler's
    /// `cost::shared_leaves`). A ray is never forwarded into such a leaf.
    pub shared_percent: u32,
}

impl Default for Tuning {
    fn default() -> Self {
        Self {
            packet_size: 1024,
            flush_us: 1000,
            max_inflight: 65536,
            tiles_ahead: 2,
            random_polling: false,
            shared_percent: 10,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobSetup {
    pub job: u64,
    pub me: WorkerId,
    /// Peer listen addresses, indexed by worker id.
    pub peers: Vec<String>,
    pub camera: Camera,
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    pub sampler: Sampler,
    pub materials: Vec<Material>,
    pub lights: LightSet,
    pub map: ProcessorMap,
    /// Largest coordinate of the scene, for BVH padding.
    pub magnitude: f32,
    pub tuning: Tuning,
    pub cache: Option<CacheParams>,
    /// The irradiance cache: its records' levels follow the geometry
    /// ([`SchedulerToWorker::Level`]), and the worker measures its share of
    /// those not known yet ([`crate::overture`]).
    pub irradiance: Option<crate::overture::IrradianceSetup>,
    pub fetch: FetchPolicy,
    /// How the worker keeps to its memory budget.
    pub plan: MemoryPlan,
    /// Triangles (global ids, ascending) of each leaf this worker owns, in
    /// leaf order: what it ships to a peer that fetches the leaf.
    pub own_leaves: Vec<(u32, Vec<u32>)>,
    /// Triangle references of every leaf, for the adaptive policy's
    /// rent-or-buy rule.
    pub leaf_tris: Vec<u32>,
    /// Triangles the region's geometry shipment holds in all, so the
    /// worker refuses a longer shipment.
    pub region_triangles: u64,
    /// Whether the scene's triangles carry shading normals (they ship and
    /// are held with them).
    pub normals: bool,
    /// Whether a [`SchedulerToWorker::Layout`] follows the last part: the
    /// region is the whole scene, the same for several workers, and the
    /// scheduler builds its BVH once for them all (only for a worker that
    /// takes layouts and builds its region as one BVH).
    pub layout: bool,
    /// The quality every BVH of the job's region is built at, decided
    /// once by the scheduler from the job's settings and counts
    /// ([`locus_core::accel::BvhSetting::quality`]), so that every worker
    /// builds alike and as one machine would.
    pub bvh_quality: locus_core::accel::BuildQuality,
}

/// How a worker keeps to its memory budget in one job, as the scheduler
/// planned it (see the scheduler's `memory` module): BVHs are built in
/// parts of at most `part_triangles`, fetched geometry stays under
/// `fetch_bytes`, and the directional caches under `cache_nodes` nodes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MemoryPlan {
    /// The budget planned for, in bytes (0: none).
    pub budget: u64,
    pub part_triangles: u32,
    pub fetch_bytes: u64,
    pub cache_nodes: u64,
}

/// The most samples one tile's pass may hold: a worker keeps each
/// sample's radiance until the pass is in (12 bytes each, 384 MiB here),
/// so that it can sum them in index order.
pub const MAX_TILE_PASS_SAMPLES: u64 = 1 << 25;

/// The most pixels one tile may hold: its pass's result (a [`TileResult`],
/// two sums of three f64 a pixel, 48 bytes) must fit one frame, beside its
/// few bytes of header (1,398,016 pixels: a 1,182-pixel square).
pub const MAX_TILE_PIXELS: u64 =
    (crate::MAX_FRAME_LEN as u64 - 4096) / std::mem::size_of::<Moments>() as u64;

/// The samples each pixel of a tile takes in one pass.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PassSamples {
    /// Samples `start..end` of every pixel: the pass's own.
    Even([u32; 2]),
    /// Adaptive sampling ([`locus_core::spread`]): pixel `p` of the tile
    /// (row-major) takes samples `first[p]..first[p] + count[p]`, the next
    /// of its own sequence; a count may be 0.
    Spread { first: Vec<u32>, count: Vec<u32> },
}

/// A tile in one of the job's progressive passes (`locus_core::passes`):
/// the worker renders each pixel of `x0..x1` by `y0..y1` over the samples
/// `samples` gives it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileAssignment {
    pub job: u64,
    pub tile: u32,
    pub pass: u32,
    pub samples: PassSamples,
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
    /// An even share, over the job's workers, of the camera samples in
    /// tile passes the scheduler still held when it handed this one out.
    /// A worker keeps no more samples in flight than this (and a floor
    /// that keeps its threads busy): near the job's end, samples in flight
    /// are work that no idle worker can take over, and a worker holding
    /// many more than the others would finish long after them.
    pub queue_share: u64,
}

impl TileAssignment {
    /// Pixels of the tile (0 if its bounds are reversed).
    pub fn pixels(&self) -> u32 {
        self.x1.saturating_sub(self.x0) * self.y1.saturating_sub(self.y0)
    }

    /// Pixel `p` of the tile, in the row-major order of its result's sums.
    pub fn pixel(&self, p: u32) -> (u32, u32) {
        let w = self.x1 - self.x0;
        (self.x0 + p % w, self.y0 + p / w)
    }

    /// The samples pixel `p` of the tile takes in this pass (empty if it
    /// takes none, or `p` is not the tile's).
    pub fn pixel_samples(&self, p: u32) -> Range<u32> {
        match &self.samples {
            PassSamples::Even([a, b]) => *a..(*b).max(*a),
            PassSamples::Spread { first, count } => {
                match (first.get(p as usize), count.get(p as usize)) {
                    (Some(&f), Some(&n)) => f..f.saturating_add(n),
                    _ => 0..0,
                }
            }
        }
    }

    /// Camera samples in this pass of the tile, over all its pixels.
    pub fn total_samples(&self) -> u64 {
        match &self.samples {
            PassSamples::Even([a, b]) => u64::from(self.pixels()) * u64::from(b.saturating_sub(*a)),
            PassSamples::Spread { count, .. } => count.iter().map(|&n| u64::from(n)).sum(),
        }
    }

    /// Why a worker cannot render this tile of a `width` by `height` image
    /// of `spp` samples per pixel, if it cannot. A spread pass may take a
    /// pixel past `spp`, up to [`locus_core::spread::MAX_SHARE`] times it.
    pub fn problem(&self, width: u32, height: u32, spp: u32) -> Option<String> {
        let t = self.tile;
        if self.pixels() as u64 > MAX_TILE_PIXELS {
            return Some(format!(
                "tile {t} holds {} pixels, more than {MAX_TILE_PIXELS}",
                self.pixels()
            ));
        }
        let n = self.total_samples();
        if n > MAX_TILE_PASS_SAMPLES {
            return Some(format!(
                "tile {t} holds {n} samples in pass {}, more than {MAX_TILE_PASS_SAMPLES}",
                self.pass
            ));
        }
        if self.x0 >= self.x1 || self.y0 >= self.y1 || self.x1 > width || self.y1 > height {
            return Some(format!(
                "tile {t} ({}..{} x {}..{}) is empty or outside the {width}x{height} image",
                self.x0, self.x1, self.y0, self.y1
            ));
        }
        match &self.samples {
            PassSamples::Even([a, b]) if a >= b || *b > spp => {
                Some(format!("tile {t} asks for samples {a}..{b} of {spp}"))
            }
            PassSamples::Even(_) => None,
            PassSamples::Spread { first, count } => {
                let pixels = self.pixels() as usize;
                if first.len() != pixels || count.len() != pixels {
                    return Some(format!(
                        "tile {t} spreads {} first samples and {} counts over {pixels} pixels",
                        first.len(),
                        count.len()
                    ));
                }
                let most = u64::from(spp) * u64::from(locus_core::spread::MAX_SHARE);
                let over = first
                    .iter()
                    .zip(count)
                    .position(|(&f, &n)| u64::from(f) + u64::from(n) > most)?;
                Some(format!(
                    "tile {t} asks for samples {}..{} of pixel {over}, past {most} ({spp} spp)",
                    first[over],
                    u64::from(first[over]) + u64::from(count[over])
                ))
            }
        }
    }
}

/// A tile's pass, rendered: per pixel (row-major), the sums of the pass's
/// samples and of their squares in index order, which the scheduler's film
/// adds in pass order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileResult {
    pub job: u64,
    pub tile: u32,
    pub pass: u32,
    pub sums: Vec<Moments>,
}
