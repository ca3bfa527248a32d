//! `locus submit` and the scheduler: a job (the loaded scene plus
//! settings), progress, and the result (film plus report).

use crate::report::FarmReport;
use glam::Vec3;
use locus_core::dircache::CacheParams;
use locus_core::scene::{Camera, Material, RenderSettings};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum Partitioner {
    /// Paper 000, section 2.1.
    #[default]
    RegionGrowing,
    /// Leaves in Morton order cut into chunks of equal predicted cost.
    Morton,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum CostModel {
    /// Surface area times triangle count (MacDonald and Booth).
    Analytic,
    /// Work counted per leaf while tracing a low-resolution preview.
    Sampled,
    /// `Sampled` from the quarter-size preview `adaptive` decides on
    /// whether to buy (the scheduler's `cost::DECISION_PREVIEW`).
    Small,
    /// `Small` where the full preview would cost a job more than it
    /// saves (fewer camera samples than triangle references: the
    /// scheduler's `cost::preview_pays`), but for an `adaptive` job whose
    /// scene does not fit every worker; `Sampled` otherwise.
    #[default]
    Auto,
}

/// What a worker does with a ray that reaches a leaf it does not own
/// (paper 000, section 2.2: data-parallel, demand-driven, hybrid).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum FetchPolicy {
    /// Forward the ray to the leaf's owner (pure data-parallel).
    Forward,
    /// Fetch the leaf's geometry from its owner and trace it here (pure
    /// demand-driven); the ray waits for the geometry.
    Fetch,
    /// Camera rays, and any ray entering a leaf that touches this
    /// worker's region, fetch; other rays (incoherent indirect and shadow
    /// rays far from home) forward.
    Hybrid,
    /// Rent or buy. At the start, for the whole scene: when it fits every
    /// worker and the cost preview predicts that forwarding its rays would
    /// cost more bytes than shipping it, every worker gets all of it.
    /// Otherwise per leaf, as the job runs: forward until the traffic the
    /// leaf has cost in forwarded queries reaches the bytes of its
    /// geometry, then fetch. The default: the fastest choice wherever the
    /// scene fits, and the least traffic where it does not.
    #[default]
    Adaptive,
}

impl FetchPolicy {
    pub const ALL: [FetchPolicy; 4] = [
        FetchPolicy::Forward,
        FetchPolicy::Fetch,
        FetchPolicy::Hybrid,
        FetchPolicy::Adaptive,
    ];
    pub fn name(self) -> &'static str {
        match self {
            FetchPolicy::Forward => "forward",
            FetchPolicy::Fetch => "fetch",
            FetchPolicy::Hybrid => "hybrid",
            FetchPolicy::Adaptive => "adaptive",
        }
    }
}

impl std::str::FromStr for FetchPolicy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| format!("unknown policy {s:?} (forward, fetch, hybrid, adaptive)"))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobOptions {
    /// Workers to use; 0 means every registered worker.
    pub workers: u32,
    pub partitioner: Partitioner,
    pub cost_model: CostModel,
    pub tile_size: u32,
    pub tuning: crate::control::Tuning,
    /// Directional caches per octree leaf (paper 000, section 2.4); None
    /// traces every ray.
    pub cache: Option<CacheParams>,
    /// Ward's irradiance cache at the first vertex; None path traces it.
    pub irradiance: Option<locus_core::irradiance::IrradianceParams>,
    pub fetch: FetchPolicy,
    /// Bytes of fetched leaf geometry (triangles plus BVH) a worker keeps.
    pub fetch_budget: u64,
    /// The job runs on when its client disconnects (`locus submit
    /// --detach`); its result waits for `locus attach`.
    pub detached: bool,
}

impl Default for JobOptions {
    fn default() -> Self {
        Self {
            workers: 0,
            partitioner: Partitioner::default(),
            cost_model: CostModel::default(),
            tile_size: 16,
            tuning: Default::default(),
            cache: None,
            irradiance: None,
            fetch: FetchPolicy::default(),
            fetch_budget: 256 << 20,
            detached: false,
        }
    }
}

/// Triangles of a job submitted in parts ([`crate::control::Opening::SubmitInParts`]),
/// in order: each triangle's corners and material.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrianglePart {
    #[serde(with = "locus_core::bulk")]
    pub tris: Vec<[Vec3; 3]>,
    #[serde(with = "locus_core::bulk")]
    pub material: Vec<u32>,
    /// Each triangle's shading normals, when the request has them (every
    /// part then carries them).
    #[serde(with = "locus_core::bulk")]
    pub normals: Vec<[Vec3; 3]>,
}

/// Triangles per [`TrianglePart`]: 40 MiB, within the frame limit (76 MiB
/// with shading normals, which travel in parts of half as many).
pub const REQUEST_PART_TRIANGLES: usize = 1 << 20;

/// A loaded scene: the client resolves mesh files, so the scheduler needs
/// no access to the user's disk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobRequest {
    pub name: String,
    pub camera: Camera,
    pub settings: RenderSettings,
    pub materials: Vec<Material>,
    #[serde(with = "locus_core::bulk")]
    pub tris: Vec<[Vec3; 3]>,
    #[serde(with = "locus_core::bulk")]
    pub tri_material: Vec<u32>,
    /// Shading normals at each triangle's vertices (all zero for a flat
    /// one); empty when no triangle has any.
    #[serde(with = "locus_core::bulk")]
    pub tri_normals: Vec<[Vec3; 3]>,
    pub options: JobOptions,
    /// Seconds the client took to read the scene, for the report.
    pub load_s: f64,
    pub kind: JobKind,
}

/// What a job computes from its scene.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum JobKind {
    /// Path-traced image (paper 000's farm).
    #[default]
    Render,
    /// Progressive refinement radiosity (paper 003's farm), and the image
    /// rendered from its solution.
    Radiosity(Box<crate::radiosity::RadiosityJob>),
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SchedulerToClient {
    Accepted {
        job: u64,
        workers: u32,
    },
    /// Pixel samples in the film so far, of `samples` in all; `pass`
    /// (from 0) is the earliest pass not yet complete, of `passes`.
    Progress {
        job: u64,
        samples_done: u64,
        samples: u64,
        pass: u32,
        passes: u32,
    },
    Done(Box<JobResult>),
    Failed {
        job: u64,
        reason: String,
    },
    /// A run of the finished image's pixels, row-major from `offset`: the
    /// image travels in these, in order, before `Done` (whose `pixels` is
    /// then empty), so no frame outgrows the frame limit however large
    /// the image.
    Pixels {
        job: u64,
        offset: u64,
        pixels: Vec<[f32; 3]>,
    },
    /// The job is taken, under this id, and waits behind `ahead` jobs: the
    /// id to attach to if the link breaks before the job ends.
    Queued {
        job: u64,
        ahead: u32,
    },
    /// A run of a radiosity solution's meshed triangles, in order from
    /// `offset`, before `Done`: each corner's position and radiance.
    Mesh {
        job: u64,
        offset: u64,
        tris: Vec<[(Vec3, Vec3); 3]>,
    },
    /// With adaptive sampling, a run of the samples each pixel got,
    /// row-major from `offset`, after the image's runs and before `Done`.
    Counts {
        job: u64,
        offset: u64,
        counts: Vec<u32>,
    },
}

/// Triangles per [`SchedulerToClient::Mesh`] message: 18 MiB.
pub const RESULT_CHUNK_TRIANGLES: usize = 1 << 18;

/// Pixels per [`SchedulerToClient::Pixels`] message: 12 MiB, well within
/// the frame limit.
pub const RESULT_CHUNK_PIXELS: usize = 1 << 20;

/// Counts per [`SchedulerToClient::Counts`] message: at most 5 MiB.
pub const RESULT_CHUNK_COUNTS: usize = 1 << 20;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobResult {
    pub job: u64,
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
    pub report: FarmReport,
    /// With adaptive sampling, the samples each pixel got (row-major; they
    /// arrive in [`SchedulerToClient::Counts`] runs).
    pub sample_counts: Option<Vec<u32>>,
    /// A radiosity job's solution report (its mesh came in
    /// [`SchedulerToClient::Mesh`] runs).
    pub radiosity: Option<Box<crate::radiosity::RadiosityReport>>,
}
