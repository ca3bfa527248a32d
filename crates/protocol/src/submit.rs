//! `locus submit` and the scheduler: a job (the loaded scene plus
//! settings), progress, and the result (film plus report).

use crate::report::FarmReport;
use glam::Vec3;
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
    #[default]
    Sampled,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobOptions {
    /// Workers to use; 0 means every registered worker.
    pub workers: u32,
    pub partitioner: Partitioner,
    pub cost_model: CostModel,
    pub tile_size: u32,
    pub tuning: crate::control::Tuning,
}

impl Default for JobOptions {
    fn default() -> Self {
        Self {
            workers: 0,
            partitioner: Partitioner::default(),
            cost_model: CostModel::default(),
            tile_size: 16,
            tuning: Default::default(),
        }
    }
}

/// A loaded scene: the client resolves mesh files, so the scheduler needs
/// no access to the user's disk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobRequest {
    pub name: String,
    pub camera: Camera,
    pub settings: RenderSettings,
    pub materials: Vec<Material>,
    pub tris: Vec<[Vec3; 3]>,
    pub tri_material: Vec<u32>,
    pub options: JobOptions,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SchedulerToClient {
    Accepted {
        job: u64,
        workers: u32,
    },
    Progress {
        job: u64,
        tiles_done: u32,
        tiles: u32,
    },
    Done(Box<JobResult>),
    Failed {
        job: u64,
        reason: String,
    },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobResult {
    pub job: u64,
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
    pub report: FarmReport,
}
