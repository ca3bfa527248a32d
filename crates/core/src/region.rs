//! Regions: which worker owns which octree leaf, and how a worker traces the
//! part of a ray that crosses its own region.
//!
//! The [`ProcessorMap`] is the top of the tree that every worker holds (paper
//! 003, section 3.3): all leaf bounds and their owners, no triangles. Walking
//! it along a ray yields the ray's processor vector: the ordered owners of
//! the leaves it crosses. [`trace_run`] traces one maximal run of owned
//! leaves with the ray clipped to the run's interval and says where the ray
//! must go next. Because leaf intervals partition the ray, references are
//! made from inflated leaf boxes and equal-distance hits resolve by global
//! triangle id, chaining runs over any partition gives exactly the closest
//! hit (and the occlusion answer) of one BVH over the whole scene.

use crate::accel::{Accel, Hit};
use crate::geometry::Ray;
use crate::octree::Octree;
use crate::stats::TraceStats;
use serde::{Deserialize, Serialize};
use std::ops::ControlFlow;

/// Index of a worker in a job (its place in the job's worker list).
pub type WorkerId = u16;

/// On the wire a processor map is the tree and its owners; the routing
/// tree is rebuilt (and the parts checked) on arrival.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "MapParts", into = "MapParts")]
pub struct ProcessorMap {
    /// The octree with empty triangle lists.
    pub tree: Octree,
    /// Owner of each leaf.
    pub owner: Vec<WorkerId>,
    /// `tree` with every single-owner subtree merged into one leaf
    /// ([`Octree::collapse`]): what rays walk. It finds the same run
    /// boundaries as `tree` while visiting a node per region crossing
    /// rather than per leaf.
    route: Octree,
    route_owner: Vec<WorkerId>,
}

#[derive(Serialize, Deserialize)]
struct MapParts {
    tree: Octree,
    owner: Vec<WorkerId>,
}

impl TryFrom<MapParts> for ProcessorMap {
    type Error = String;
    fn try_from(p: MapParts) -> Result<Self, String> {
        p.tree.check_structure()?;
        if p.tree.leaves.len() != p.owner.len() {
            return Err("processor map: one owner per leaf expected".into());
        }
        Ok(ProcessorMap::new(&p.tree, p.owner))
    }
}

impl From<ProcessorMap> for MapParts {
    fn from(m: ProcessorMap) -> Self {
        MapParts {
            tree: m.tree,
            owner: m.owner,
        }
    }
}

/// Where a traced run leaves the ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RunResult {
    /// The closest hit of the whole ray lies in this run.
    Hit(Hit),
    /// Something blocks the segment (any-hit queries).
    Occluded,
    /// Nothing here; the next leaf along the ray starts at `t` and belongs to
    /// `to`.
    Forward { to: WorkerId, t: f32 },
    /// The ray leaves the scene (or its segment ends) without a hit.
    Miss,
}

impl ProcessorMap {
    pub fn new(tree: &Octree, owner: Vec<WorkerId>) -> Self {
        assert_eq!(tree.leaves.len(), owner.len(), "one owner per leaf");
        let (route, route_owner) = tree.collapse(&owner);
        Self {
            tree: tree.without_triangles(),
            owner,
            route,
            route_owner,
        }
    }

    /// Nodes in the routing tree (for reports: how much the merge saved).
    pub fn route_leaves(&self) -> usize {
        self.route.leaves.len()
    }

    /// Owner of the first leaf on `[0, t_max)`, or `None` when the ray
    /// misses the scene.
    pub fn first_owner(&self, ray: &Ray, t_max: f32) -> Option<(WorkerId, f32)> {
        let mut first = None;
        let _ = self.route.walk(ray, 0.0, t_max, |leaf, ta, _| {
            first = Some((self.route_owner[leaf as usize], ta));
            ControlFlow::Break(())
        });
        first
    }

    /// Traces, on worker `me` whose BVH is `accel`, the run of `me`'s leaves
    /// that starts at `resume` on the segment `[0, t_max)`. With `any_hit`
    /// the answer is `Occluded` instead of the closest hit.
    #[allow(clippy::too_many_arguments)]
    pub fn trace_run(
        &self,
        me: WorkerId,
        accel: &Accel,
        ray: &Ray,
        t_max: f32,
        resume: f32,
        any_hit: bool,
        stats: &mut TraceStats,
    ) -> RunResult {
        let mut run: Option<(f32, f32)> = None;
        let mut next: Option<(WorkerId, f32)> = None;
        let _ = self
            .route
            .walk_from(ray, 0.0, t_max, resume, |leaf, ta, tb| {
                let o = self.route_owner[leaf as usize];
                if o == me {
                    run = Some(match run {
                        Some((s, _)) => (s, tb),
                        None => (ta, tb),
                    });
                    ControlFlow::Continue(())
                } else {
                    next = Some((o, ta));
                    ControlFlow::Break(())
                }
            });
        if let Some((s, e)) = run {
            if any_hit {
                if accel.occluded(ray, s, e, stats) {
                    return RunResult::Occluded;
                }
            } else if let Some(h) = accel.intersect(ray, s, e, stats) {
                return RunResult::Hit(h);
            }
        }
        match next {
            Some((to, t)) => RunResult::Forward { to, t },
            None => RunResult::Miss,
        }
    }

    /// Triangles (global ids, ascending) referenced by the leaves of `w`.
    pub fn region_triangles(tree: &Octree, owner: &[WorkerId], w: WorkerId) -> Vec<u32> {
        let mut ids: Vec<u32> = tree
            .leaves
            .iter()
            .zip(owner)
            .filter(|(_, o)| **o == w)
            .flat_map(|(l, _)| l.tris.iter().copied())
            .collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }
}
