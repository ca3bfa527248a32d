//! Named statistics counters, in the manner of pbrt's `STAT_COUNTER`:
//! every figure in a report is counted where the work happens, per tile,
//! and summed, never estimated.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TraceStats {
    pub camera_rays: u64,
    pub shadow_rays: u64,
    pub indirect_rays: u64,
    pub bvh_nodes: u64,
    pub tri_tests: u64,
    /// Closest-hit and any-hit BVH queries: on one machine one per ray; on
    /// a farm worker one per run of owned leaves it traces.
    pub bvh_queries: u64,
    /// Samples whose radiance was NaN or infinite and were replaced by zero.
    pub invalid_samples: u64,
    pub samples: u64,
    /// Directional cache use by continuation rays.
    pub cache: crate::dircache::CacheStats,
    /// Irradiance cache use at first vertices.
    pub irradiance: crate::irradiance::IrradianceUse,
}

impl TraceStats {
    pub fn rays(&self) -> u64 {
        self.camera_rays + self.shadow_rays + self.indirect_rays
    }
}

impl std::ops::AddAssign for TraceStats {
    fn add_assign(&mut self, o: Self) {
        self.camera_rays += o.camera_rays;
        self.shadow_rays += o.shadow_rays;
        self.indirect_rays += o.indirect_rays;
        self.bvh_nodes += o.bvh_nodes;
        self.tri_tests += o.tri_tests;
        self.bvh_queries += o.bvh_queries;
        self.invalid_samples += o.invalid_samples;
        self.samples += o.samples;
        self.cache += o.cache;
        self.irradiance += o.irradiance;
    }
}
