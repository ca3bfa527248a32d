//! A worker's region as the BVH parts it is shipped in ([`PartRun`]):
//! runs of whole leaves in leaf order ([`cut_parts`]), or, for a worker
//! that joins its parts into one BVH, groups cut by the triangles'
//! centroids ([`cut_by_centroids`]).

use locus_core::accel_set;
use locus_core::geometry::TriangleSet;
use locus_core::scene::Scene;
use std::sync::{Arc, Mutex, PoisonError, Weak};

/// One BVH part as a worker is shipped it: a run of leaves, and the
/// distinct triangles they reference (ascending). Workers shipped the same
/// leaves in parts of the same size (every worker of a job that replicates
/// the scene) share one list, computed once while the job is prepared, off
/// the scheduler's runtime, and its triangles gathered once
/// ([`PartRun::gather`]).
#[derive(Clone, Debug)]
pub struct PartRun {
    pub leaves: Vec<u32>,
    pub ids: Arc<Vec<u32>>,
    /// The triangles last gathered for this run, while a message to some
    /// worker still holds them (shared by the run's clones).
    gathered: Arc<Mutex<Weak<TriangleSet>>>,
}

impl PartialEq for PartRun {
    fn eq(&self, other: &Self) -> bool {
        self.leaves == other.leaves && self.ids == other.ids
    }
}

impl PartRun {
    pub fn new(leaves: Vec<u32>, ids: Vec<u32>) -> Self {
        Self {
            leaves,
            ids: Arc::new(ids),
            gathered: Default::default(),
        }
    }

    /// The run's triangles as they are shipped: gathered from `scene`
    /// once for every worker the run goes to, while any of their messages
    /// still holds them, where each worker's shipment gathered its own
    /// copy (a replicated job's whole scene, once a worker, at the same
    /// time). A second caller waits for a gather under way. Blocks: call it
    /// off the runtime.
    pub fn gather(&self, scene: &Scene) -> Arc<TriangleSet> {
        let mut slot = self.gathered.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(set) = slot.upgrade() {
            return set;
        }
        let set = Arc::new(TriangleSet::gather(
            self.ids.to_vec(),
            &scene.tris,
            &scene.tri_material,
            &scene.tri_normals,
        ));
        *slot = Arc::downgrade(&set);
        set
    }
}

/// Cuts a worker's leaves (in leaf order) into runs of at most `max`
/// triangle references; returns the runs with their distinct triangles,
/// and how many those are in all (a triangle in two runs counts twice).
pub(super) fn cut_parts(own: &[(u32, Vec<u32>)], max: u64) -> (Vec<PartRun>, u64) {
    let mut runs = Vec::new();
    let mut spans: Vec<(usize, usize)> = Vec::new();
    let (mut start, mut count) = (0, 0u64);
    for (i, (_, t)) in own.iter().enumerate() {
        if i > start && count + t.len() as u64 > max.max(1) {
            spans.push((start, i));
            start = i;
            count = 0;
        }
        count += t.len() as u64;
    }
    if start < own.len() {
        spans.push((start, own.len()));
    }
    let mut total = 0;
    for (a, b) in spans {
        let ids = part_triangles(&own[a..b]);
        total += ids.len() as u64;
        runs.push(PartRun::new(
            own[a..b].iter().map(|(l, _)| *l).collect(),
            ids,
        ));
    }
    (runs, total)
}

/// Cuts a worker's region into parts of at most `max` distinct triangles
/// by their centroids ([`accel_set::cut_by_centroids`]), for a worker that
/// joins its parts. Each leaf goes with the part that holds its first
/// triangle (an empty leaf with the first part), so every leaf is named
/// once; returns the parts and their triangles in all.
pub(super) fn cut_by_centroids(
    own: &[(u32, Vec<u32>)],
    max: usize,
    scene: &Scene,
) -> (Vec<PartRun>, u64) {
    let ids = part_triangles(own);
    let total = ids.len() as u64;
    let centroid = |id: u32| {
        let t = scene.tris[id as usize];
        (t[0] + t[1] + t[2]) / 3.0
    };
    let groups = accel_set::cut_by_centroids(ids, &centroid, max);
    let mut leaves = vec![Vec::new(); groups.len()];
    for (l, t) in own {
        let g = t
            .iter()
            .min()
            .and_then(|first| groups.iter().position(|g| g.binary_search(first).is_ok()))
            .unwrap_or(0);
        leaves[g].push(*l);
    }
    let runs = groups
        .into_iter()
        .zip(leaves)
        .map(|(ids, leaves)| PartRun::new(leaves, ids))
        .collect();
    (runs, total)
}

/// The distinct triangles (ascending) of a run of leaves.
pub fn part_triangles(run: &[(u32, Vec<u32>)]) -> Vec<u32> {
    locus_core::octree::distinct_triangles(run.iter().map(|(_, t)| t.as_slice()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A region cut by centroid for a joining worker: parts of at most the
    /// size asked, each triangle of the region in exactly one, every leaf
    /// named by exactly one part (ascending within it).
    #[test]
    fn a_centroid_cut_holds_the_region_once_and_names_every_leaf_once() {
        let scene = crate::cornell_box();
        let tree = super::super::octree_for(&scene, 2);
        // Two regions: the first half of the leaves and the rest.
        let all: Vec<(u32, Vec<u32>)> = (0..tree.leaves.len())
            .map(|l| (l as u32, tree.leaves[l].tris.clone()))
            .collect();
        let (a, b) = all.split_at(all.len() / 2);
        for own in [a, b] {
            let region = part_triangles(own);
            for max in [1, 3, 7, region.len()] {
                let (runs, total) = cut_by_centroids(own, max, &scene);
                assert_eq!(runs.len(), region.len().div_ceil(max));
                assert_eq!(total as usize, region.len());
                let mut ids: Vec<u32> = runs.iter().flat_map(|r| r.ids.iter().copied()).collect();
                assert!(runs.iter().all(|r| r.ids.len() <= max && r.ids.is_sorted()));
                ids.sort_unstable();
                assert_eq!(ids, region, "max {max}");
                let mut leaves: Vec<u32> = runs.iter().flat_map(|r| r.leaves.clone()).collect();
                assert!(runs.iter().all(|r| r.leaves.is_sorted_by(|a, b| a < b)));
                leaves.sort_unstable();
                let want: Vec<u32> = own.iter().map(|(l, _)| *l).collect();
                assert_eq!(leaves, want, "max {max}");
            }
        }
    }
}
