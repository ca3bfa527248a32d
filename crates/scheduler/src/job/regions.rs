//! Drawing a job's regions: the leaves every worker holds as its own (the
//! camera's, [`cost::camera_leaf`], and those [`cost::shared_leaves`]
//! picks from the preview's crossings), and the partition of the rest
//! among the workers within what their memory caps leave beside the
//! shared leaves.

use crate::{cost, partition};
use locus_core::octree::Octree;
use locus_core::region::WorkerId;
use locus_protocol::submit::Partitioner;
use std::collections::HashMap;

/// What a job's regions are drawn from.
pub(super) struct Draw<'a> {
    pub tree: &'a Octree,
    /// Triangle references per leaf, and in all.
    pub refs: &'a [u64],
    pub all_refs: u64,
    /// Each worker's share of the work, and the references it can hold.
    pub targets: &'a [f64],
    pub caps: &'a [Option<u64>],
    /// The leaf costs balanced where there is no preview.
    pub analytic: &'a [f64],
    /// The camera's leaf, shared whenever there are workers to share it.
    pub camera: Option<u32>,
    pub partitioner: Partitioner,
    /// `Tuning::shared_percent`.
    pub shared_percent: u32,
}

impl Draw<'_> {
    /// The camera's leaf alone shared.
    pub fn camera_only(&self) -> Vec<bool> {
        let mut shared = vec![false; self.tree.leaves.len()];
        if let Some(l) = self.camera {
            shared[l as usize] = true;
        }
        shared
    }

    /// The camera's leaf and, where the preview counted crossings, the
    /// leaves worth sharing among more than one worker: at most the
    /// share asked for and half of the smallest cap, so that regions
    /// keep room beside them.
    fn pick_shared(&self, pv: Option<&cost::Preview>) -> Vec<bool> {
        let mut shared = self.camera_only();
        if let Some(pv) = pv.filter(|_| self.targets.len() > 1) {
            let room = self.caps.iter().flatten().min().map_or(u64::MAX, |c| c / 2);
            let most = (self.all_refs * self.shared_percent.min(100) as u64 / 100).min(room);
            for l in cost::shared_leaves(self.refs, &pv.crossings, &shared, most) {
                shared[l as usize] = true;
            }
        }
        shared
    }

    /// Each leaf's owner, and the leaf costs it balanced: the shared ones'
    /// references left out (every
    /// worker holds them beside its region, within its cap) and their
    /// work charged to the leaves that hold the paths there
    /// ([`cost::Preview::charged`]): whoever holds a ray traces it.
    pub fn regions(
        &self,
        pv: Option<&cost::Preview>,
        shared: &[bool],
    ) -> Result<(Vec<WorkerId>, Vec<f64>), String> {
        let chosen = pv.map_or_else(|| unshared(self.analytic, shared), |pv| pv.charged(shared));
        // Regions grow along the crossings that remain once the shared
        // leaves are passed over: a ray from one leaf through shared ones
        // into another is forwarded between those two.
        let crossings = pv.map_or_else(HashMap::new, |pv| pv.crossings_beside(shared));
        // The camera's leaf has always counted towards its nominal owner.
        let beside = |l: usize| shared[l] && Some(l as u32) != self.camera;
        let extra: u64 = (0..self.refs.len())
            .filter(|&l| beside(l))
            .map(|l| self.refs[l])
            .sum();
        let caps: Vec<Option<u64>> = self
            .caps
            .iter()
            .map(|c| c.map(|c| c.saturating_sub(extra)))
            .collect();
        let refs: Vec<u64> = (0..self.refs.len())
            .map(|l| if beside(l) { 0 } else { self.refs[l] })
            .collect();
        let lim = partition::Limits {
            targets: self.targets,
            caps: &caps,
            refs: &refs,
        };
        let owner = match self.partitioner {
            Partitioner::RegionGrowing => {
                let graph = partition::LeafGraph::new(self.tree, &crossings);
                partition::region_growing(self.tree, &graph, &chosen, &lim)
            }
            Partitioner::Morton => partition::morton(&chosen, &lim),
        }?;
        Ok((owner, chosen))
    }

    /// The shared leaves and the regions beside them, or, where the
    /// budgets cannot hold both, the regions with the camera's leaf
    /// alone shared; with the leaf costs the regions balanced.
    pub fn drawn(&self, pv: Option<&cost::Preview>) -> Result<Drawn, String> {
        let shared = self.pick_shared(pv);
        let (owner, balanced) = match self.regions(pv, &shared) {
            Ok(r) => r,
            Err(_) => {
                let shared = self.camera_only();
                let (owner, balanced) = self.regions(pv, &shared)?;
                return Ok(Drawn {
                    shared,
                    owner,
                    balanced,
                });
            }
        };
        Ok(Drawn {
            shared,
            owner,
            balanced,
        })
    }
}

/// A job's regions as [`Draw::drawn`] draws them.
pub(super) struct Drawn {
    /// Per leaf, whether every worker holds it.
    pub shared: Vec<bool>,
    pub owner: Vec<WorkerId>,
    /// The leaf costs the regions balanced.
    pub balanced: Vec<f64>,
}

/// The analytic costs the partition balances where there is no preview
/// (and the report's analytic shares): the shared leaves' left out, since
/// each worker traces there what its own rays bring, which without the
/// preview's paths cannot be placed.
pub(super) fn unshared(c: &[f64], shared: &[bool]) -> Vec<f64> {
    c.iter()
        .zip(shared)
        .map(|(&c, &s)| if s { 0.0 } else { c })
        .collect()
}
