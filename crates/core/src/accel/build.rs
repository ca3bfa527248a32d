//! How a BVH is built: obvhs's PLOC and reinsertion with locus's
//! parameters, the collapse to the wide BVH (`convert`), and what a
//! [`BuildQuality`] spends on the tree.

use super::convert;
use super::split::{split_boxes, unsplit_boxes};
use glam::Vec3;
use obvhs::BvhBuildParams;
use obvhs::aabb::Aabb;
use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
use obvhs::cwbvh::CwBvh;
use obvhs::ploc::PlocBuilder;

/// obvhs's `medium_build` with a PLOC search distance of 6 (`Low`) at
/// every level, where the preset searches 14 neighbours but only one in
/// the first three levels. Counted on the same paths (`locus render
/// SCENE --spp 1`, the report's `bvh_nodes` per `bvh_queries`), it
/// visits fewer nodes in about the same build time: the room 9.50 to
/// 8.31 per query, the conference room 6.17 to 6.10, the Cornell box
/// 2.11 to 1.37, the 4-million-triangle room 9.98 to 9.03; on the
/// room 5.9% fewer instructions per render. Larger searches and more
/// reinsertion cost build time for less than that. Which BVH is built
/// changes no answer: hits are exact, ties resolve by triangle id.
fn build_params() -> BvhBuildParams {
    BvhBuildParams {
        ploc_search_distance: obvhs::ploc::PlocSearchDistance::Low,
        search_depth_threshold: 0,
        ..BvhBuildParams::medium_build()
    }
}

/// obvhs's `build_cwbvh` (PLOC, then reinsertion, then the collapse to
/// the wide BVH) with the collapse done by `convert`: the same BVH in
/// about four fifths of the collapse's time.
pub(super) fn cwbvh(boxes: &[Aabb], quality: BuildQuality) -> CwBvh {
    let p = build_params();
    let search = match quality {
        BuildQuality::Full => p.ploc_search_distance,
        BuildQuality::Quick => obvhs::ploc::PlocSearchDistance::Minimum,
    };
    let mut bvh2 = PlocBuilder::with_capacity(boxes.len()).build(
        search,
        boxes,
        (0..boxes.len() as u32).collect(),
        p.sort_precision,
        p.search_depth_threshold,
    );
    if quality == BuildQuality::Full {
        ReinsertionOptimizer::default().run(&mut bvh2, p.reinsertion_batch_ratio, None);
    }
    convert::bvh2_to_cwbvh(&bvh2, p.max_prims_per_leaf)
}

/// How much a build spends on the BVH's quality.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum BuildQuality {
    /// Spatial pre-splits, PLOC searching 6 neighbours at every level
    /// ([`build_params`]) and reinsertion: the fewest steps a query takes.
    #[default]
    Full,
    /// No pre-splits, PLOC searching one neighbour, no reinsertion: a BVH
    /// with the same hits (they are exact, and ties go to the smaller id,
    /// whatever the tree) built with less work, for queries whose answer
    /// is the hits and not the steps taken to them (`adaptive`'s
    /// decision, which counts crossings between octree leaves).
    Quick,
}

/// A job with fewer camera samples than this many per triangle has its
/// BVHs built [`BuildQuality::Quick`]: one machine's, the farm's workers'
/// and the scheduler's preview.
///
/// A full build spends its time on fewer steps a query, which a job
/// earns back only if it traces enough queries a triangle. Measured on
/// this 2-core AMD EPYC (2026-12-07, `locus render SCENE --threads 2`
/// with the quality switched by a temporary environment variable, builds
/// alternating; the images were bit-identical, since hits are exact and
/// ties go to the smaller id in any tree): the 4-million-triangle room at
/// 320x240 and 16 spp (0.30 samples a triangle) built in 1.45-2.00 s
/// instead of 2.19-2.75 and rendered in 2.62-2.69 s instead of 2.54-2.60,
/// 5.05-5.66 s for the whole command against 5.78-6.35; the room at
/// 320x240 and 16 spp (3.8 samples a triangle) built in 0.095-0.105 s
/// instead of 0.139-0.175 and rendered in 2.19-2.24 s instead of
/// 2.06-2.14, a loss. The two break even at about 1.7 samples a triangle
/// on the room and 6 on the large one; one keeps well on the side where
/// the quick build wins.
pub const QUICK_BELOW_SAMPLES_PER_TRIANGLE: u64 = 1;

impl BuildQuality {
    /// What a summary line adds after a build's time: nothing for the
    /// usual full build.
    pub fn suffix(self) -> &'static str {
        match self {
            BuildQuality::Full => "",
            BuildQuality::Quick => " (quick)",
        }
    }

    /// The quality of the BVHs a job of `samples` camera samples traces
    /// over a scene of `triangles` (triangle references, for a farm's
    /// workers and scheduler, which count them leaf by leaf: a few more
    /// than the triangles): every renderer of the job asks this with the
    /// job's own counts, so they build alike.
    pub fn for_job(samples: u64, triangles: u64) -> Self {
        if samples < triangles.saturating_mul(QUICK_BELOW_SAMPLES_PER_TRIANGLE) {
            BuildQuality::Quick
        } else {
            BuildQuality::Full
        }
    }
}

/// What a job asks of its BVHs (the scene file's `[render] bvh`, the
/// command line's `--bvh`): [`BvhSetting::Auto`] decides by the job's
/// samples a triangle ([`BuildQuality::for_job`]); the others fix the
/// quality, which changes no image (hits are exact, ties go to the
/// smaller id in any tree), only the time spent building against the
/// time spent tracing.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum BvhSetting {
    #[default]
    Auto,
    Full,
    Quick,
}

impl BvhSetting {
    pub const ALL: [BvhSetting; 3] = [BvhSetting::Auto, BvhSetting::Full, BvhSetting::Quick];

    /// The name the scene file and the command line use.
    pub fn name(self) -> &'static str {
        match self {
            BvhSetting::Auto => "auto",
            BvhSetting::Full => "full",
            BvhSetting::Quick => "quick",
        }
    }

    /// The quality a job of `samples` camera samples over `triangles`
    /// builds its BVHs at. The scheduler decides this once for a farm's
    /// job and sends it to every worker, so all of them build alike.
    pub fn quality(self, samples: u64, triangles: u64) -> BuildQuality {
        match self {
            BvhSetting::Auto => BuildQuality::for_job(samples, triangles),
            BvhSetting::Full => BuildQuality::Full,
            BvhSetting::Quick => BuildQuality::Quick,
        }
    }
}

impl std::str::FromStr for BvhSetting {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|b| b.name() == s)
            .ok_or_else(|| format!("unknown BVH setting {s:?}: expected auto, full or quick"))
    }
}

/// Bytes a build holds per triangle at its peak beyond the result
/// (measured: obvhs's PLOC build with its boxes, Morton keys and BVH2, at
/// every preset, about 235 bytes plus 32 for the input boxes; the same,
/// within 1%, when obvhs builds in parallel). Memory budgets size chunked
/// builds with it.
pub const BUILD_BYTES_PER_TRIANGLE: usize = 280;

/// The boxes a build of `verts` at `quality` starts from, and the triangle
/// each belongs to: pre-split for a full build, one tight box a triangle
/// for a quick one.
pub(super) fn boxes(verts: &[[Vec3; 3]], quality: BuildQuality) -> (Vec<Aabb>, Vec<u32>) {
    match quality {
        BuildQuality::Full => split_boxes(verts),
        BuildQuality::Quick => unsplit_boxes(verts),
    }
}
