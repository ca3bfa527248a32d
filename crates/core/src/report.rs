//! The JSON report written beside every image.

use crate::metrics::{ErrorEstimate, ErrorMetrics};
use crate::render::RenderOptions;
use crate::scene::LoadStats;
use crate::stats::TraceStats;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, Serialize)]
pub struct PhaseTimes {
    pub load_s: f64,
    /// 0 when no octree was needed (directional caches off).
    pub octree_s: f64,
    pub bvh_s: f64,
    /// The quality the BVH was built at ([`crate::accel::BvhSetting::quality`]).
    pub bvh_quality: crate::accel::BuildQuality,
    pub render_s: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct RenderReport {
    pub scene: String,
    pub image: String,
    pub width: u32,
    pub height: u32,
    pub options: RenderOptions,
    pub threads_used: usize,
    pub triangles: usize,
    pub load: LoadStats,
    /// The octree's leaves and references, when caches needed one.
    pub octree_leaves: Option<usize>,
    pub octree_references: Option<usize>,
    pub emitters: usize,
    pub times: PhaseTimes,
    pub stats: TraceStats,
    pub samples_per_second: f64,
    pub rays_per_second: f64,
    pub error_vs_reference: Option<ErrorMetrics>,
    /// The error the image carries, from its samples' spread: the report's
    /// error where no reference is given.
    pub error_estimate: Option<ErrorEstimate>,
    /// Samples each pixel got: `options.spp`, or fewer where
    /// `options.target_rel_mse` was met at an earlier pass's end.
    pub spp_rendered: u32,
    /// With adaptive sampling, the fewest and most samples a pixel got and
    /// their mean, counted from the render's counts.
    pub sample_counts: Option<SampleCounts>,
    /// What the directional caches held at the end (when on).
    pub cache_memory: Option<crate::dircache::CacheMemory>,
    /// How the irradiance cache was built (when on); its time is part of
    /// `times.render_s`.
    pub irradiance: Option<crate::irradiance::overture::OvertureStats>,
}

/// The spread of an adaptive render's samples over its pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleCounts {
    pub min: u32,
    pub max: u32,
    pub mean: f64,
}

impl SampleCounts {
    /// Of each pixel's count; None for no pixels.
    pub fn of(counts: &[u32]) -> Option<Self> {
        let min = *counts.iter().min()?;
        let max = *counts.iter().max()?;
        let sum: u64 = counts.iter().map(|&c| c as u64).sum();
        Some(Self {
            min,
            max,
            mean: sum as f64 / counts.len() as f64,
        })
    }
}

impl RenderReport {
    pub fn write(&self, path: &std::path::Path) -> std::io::Result<()> {
        let s = serde_json::to_string_pretty(self).map_err(std::io::Error::other)?;
        std::fs::write(path, s)
    }
}
