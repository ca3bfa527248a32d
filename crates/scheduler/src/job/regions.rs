//! Drawing a job's regions: the leaves every worker holds as its own (the
//! camera's, [`cost::camera_leaf`], and those [`cost::shared_leaves`]
//! picks from the preview's crossings), and the partition of the rest
//! among the workers within what their memory caps leave beside the
//! shared leaves. Where tiles go by affinity, the shared leaves are then
//! picked again by the forwards each saves under those regions
//! ([`cost::Preview::share_values`]) while the forwards predicted fall
//! ([`Draw::drawn`]).

use crate::cost::Crossings;
use crate::{cost, partition};
use locus_core::octree::Octree;
use locus_core::region::WorkerId;
use locus_core::render::Tile;
use locus_core::scene::Camera;
use locus_protocol::submit::Partitioner;

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
    /// Where tiles go by affinity (`tiles::affinities`), the camera and
    /// the tiles: each path starts with its tile's worker, which the
    /// forwards predicted for a choice of shared leaves depend on.
    pub view: Option<(&'a Camera, &'a [Tile])>,
}

/// Per tile, the worker it goes to; per preview path, the worker that
/// starts it (its tile's).
pub(super) struct Starts {
    pub tiles: Vec<Option<WorkerId>>,
    pub paths: Vec<Option<WorkerId>>,
    /// Per tile and worker, the tile's votes ([`crate::tiles::votes`]).
    pub votes: Vec<u32>,
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
        match pv.filter(|_| self.targets.len() > 1) {
            Some(pv) => self.share(&cost::traffic(&pv.crossings, self.refs.len())),
            None => self.camera_only(),
        }
    }

    /// The camera's leaf and the leaves with the most `traffic` per
    /// triangle ([`cost::shared_leaves`]) that fit in at most the share
    /// asked for and half of the smallest cap.
    fn share(&self, traffic: &[u64]) -> Vec<bool> {
        let mut shared = self.camera_only();
        let room = self.caps.iter().flatten().min().map_or(u64::MAX, |c| c / 2);
        let most = (self.all_refs * self.shared_percent.min(100) as u64 / 100).min(room);
        for l in cost::shared_leaves(self.refs, traffic, &shared, most) {
            shared[l as usize] = true;
        }
        shared
    }

    /// Which worker each tile goes to and so which starts each preview
    /// path, under these `shared` leaves and `owner`s
    /// (`tiles::affinities`); None without tiles by affinity.
    pub fn starts(
        &self,
        pv: &cost::Preview,
        shared: &[bool],
        first: &[Option<u32>],
        owner: &[WorkerId],
    ) -> Option<Starts> {
        let (camera, tiles) = self.view?;
        let workers = self.targets.len();
        let votes = crate::tiles::votes(owner, tiles, &pv.pixel_firsts(first), workers);
        let by_tile =
            crate::tiles::affinities(camera, self.tree, owner, shared, tiles, &votes, workers);
        let tile_of = crate::tiles::locator(tiles);
        let paths = pv
            .pixels
            .iter()
            .map(|&(x, y)| tile_of(x, y).and_then(|t| by_tile[t]))
            .collect();
        Some(Starts {
            tiles: by_tile,
            paths,
            votes,
        })
    }

    /// Each leaf's owner, and the leaf costs it balanced: the shared ones'
    /// references left out (every
    /// worker holds them beside its region, within its cap) and their
    /// work charged to the leaves that hold the paths there
    /// ([`cost::Preview::charged`]): whoever holds a ray traces it.
    pub fn regions(&self, pv: Option<&cost::Preview>, shared: &[bool]) -> Result<Regions, String> {
        // Regions grow along the crossings that remain once the shared
        // leaves are passed over: a ray from one leaf through shared ones
        // into another is forwarded between those two. Both follow every
        // preview path, each on its own, so they are counted side by side,
        // from the paths' first leaves found once for both.
        let first = pv.map(|pv| pv.first_leaves(shared));
        let (chosen, crossings) = match (pv, &first) {
            (Some(pv), Some(first)) => rayon::join(
                || pv.charged_from(shared, first),
                || pv.crossings_beside_from(shared, first),
            ),
            _ => (unshared(self.analytic, shared), Crossings::default()),
        };
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
        Ok(Regions {
            owner,
            balanced: chosen,
            first,
        })
    }

    /// The shared leaves and the regions beside them, or, where the
    /// budgets cannot hold both, the regions with the camera's leaf
    /// alone shared; with the leaf costs the regions balanced.
    ///
    /// Where tiles go by affinity, the shared leaves are then picked
    /// again. The first pick, by the preview's crossings, cannot tell a
    /// border between two workers from one inside a region, where
    /// crossings cost nothing. So each leaf's worth in sharing under the
    /// regions drawn is counted ([`cost::Preview::share_values`]), the
    /// leaves are picked again by it and the regions drawn again beside
    /// them, up to [`REPICKS`] times while the forwards predicted fall
    /// ([`cost::Preview::forwards_from`], each path started by its tile's
    /// worker).
    pub fn drawn(&self, pv: Option<&cost::Preview>) -> Result<Drawn, String> {
        let shared = self.pick_shared(pv);
        let mut best = match self.regions(pv, &shared) {
            Ok(r) => self.judged(pv, shared, r),
            Err(_) => {
                let shared = self.camera_only();
                let r = self.regions(pv, &shared)?;
                return Ok(self.judged(pv, shared, r));
            }
        };
        for round in 0..REPICKS {
            let (Some(pv), Some(j)) = (pv, &best.judged) else {
                break;
            };
            let worth: Vec<u64> = j.values.iter().map(|&v| v.max(0) as u64).collect();
            let shared = self.share(&worth);
            let Ok(r) = self.regions(Some(pv), &shared) else {
                break;
            };
            let next = self.judged(Some(pv), shared, r);
            let (before, after) = (
                j.forwards,
                next.judged.as_ref().map_or(u64::MAX, |n| n.forwards),
            );
            tracing::debug!(
                round,
                before,
                after,
                "shared leaves picked again by their worth"
            );
            if after >= before {
                break;
            }
            best = next;
        }
        Ok(best)
    }

    /// `shared` leaves and the regions beside them, with the forwards
    /// they are predicted to cost where tiles go by affinity.
    fn judged(&self, pv: Option<&cost::Preview>, shared: Vec<bool>, r: Regions) -> Drawn {
        let Regions {
            owner,
            balanced,
            first,
        } = r;
        let judged = pv.filter(|_| self.targets.len() > 1).and_then(|pv| {
            let starts = self.starts(pv, &shared, first.as_deref()?, &owner)?;
            let (forwards, values) = rayon::join(
                || pv.forwards_from(&shared, &owner, &starts.paths),
                || pv.share_values(&shared, &owner, &starts.paths),
            );
            Some(Judged {
                forwards,
                values,
                starts,
            })
        });
        Drawn {
            shared,
            owner,
            balanced,
            judged,
        }
    }
}

/// How many times the shared leaves are picked again by their worth
/// under the regions drawn beside the last pick.
const REPICKS: usize = 4;

/// One drawing of the regions beside a set of shared leaves
/// ([`Draw::regions`]).
pub(super) struct Regions {
    pub owner: Vec<WorkerId>,
    /// The leaf costs the regions balanced.
    pub balanced: Vec<f64>,
    /// Per preview path, its first leaf beside the shared ones
    /// ([`cost::Preview::first_leaves`]), found once for the drawing and
    /// then for where its tiles go ([`Draw::starts`]); None without a
    /// preview.
    pub first: Option<Vec<Option<u32>>>,
}

/// A job's regions as [`Draw::drawn`] draws them.
pub(super) struct Drawn {
    /// Per leaf, whether every worker holds it.
    pub shared: Vec<bool>,
    pub owner: Vec<WorkerId>,
    /// The leaf costs the regions balanced.
    pub balanced: Vec<f64>,
    /// Where tiles go by affinity and the preview ran: the tiles' and
    /// paths' workers and the forwards predicted.
    pub judged: Option<Judged>,
}

/// What a drawing of the regions is predicted to cost in forwards.
pub(super) struct Judged {
    pub starts: Starts,
    /// Queries the preview's paths forward ([`cost::Preview::forwards_from`]).
    pub forwards: u64,
    /// Each leaf's worth in sharing ([`cost::Preview::share_values`]).
    values: Vec<i64>,
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

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::light::LightSet;

    /// Where tiles go by affinity, the shared leaves picked again by their
    /// worth are kept only where the preview predicts fewer forwards than
    /// with the crossings' pick, within the same share of the references;
    /// without tiles by affinity the crossings' pick stands. The forwards
    /// a drawing is judged by are the preview's paths started by their
    /// tiles' workers.
    #[test]
    fn shared_leaves_picked_again_only_where_they_forward_less() {
        let scene = crate::cornell_box();
        let tiles = locus_core::render::tiles(
            scene.camera.width,
            scene.camera.height,
            16,
            locus_core::render::TileOrder::Scanline,
        );
        let lights = LightSet::build(&scene);
        let mut checked = 0;
        for workers in [2usize, 3, 4] {
            let tree = super::super::octree_for(&scene, workers);
            let refs: Vec<u64> = tree.leaves.iter().map(|l| l.tris.len() as u64).collect();
            let all_refs: u64 = refs.iter().sum();
            let pv = cost::sampled_in_parts(&scene, &tree, &lights, cost::FULL_PREVIEW);
            let analytic = cost::analytic(&tree);
            let targets = vec![1.0 / workers as f64; workers];
            let caps = vec![None; workers];
            let mut draw = Draw {
                tree: &tree,
                refs: &refs,
                all_refs,
                targets: &targets,
                caps: &caps,
                analytic: &analytic,
                camera: cost::camera_leaf(&tree, &scene.camera),
                partitioner: Partitioner::RegionGrowing,
                shared_percent: 10,
                view: Some((&scene.camera, &tiles)),
            };
            let crossings = draw.pick_shared(Some(&pv));
            let first = draw.judged(
                Some(&pv),
                crossings.clone(),
                draw.regions(Some(&pv), &crossings).expect("regions"),
            );
            let before = first.judged.as_ref().expect("judged").forwards;
            let drawn = draw.drawn(Some(&pv)).expect("drawn");
            let j = drawn.judged.as_ref().expect("judged");
            assert!(j.forwards <= before, "{workers}: {} > {before}", j.forwards);
            if drawn.shared != crossings {
                assert!(j.forwards < before);
                checked += 1;
            }
            let held: u64 = (0..refs.len())
                .filter(|&l| drawn.shared[l] && Some(l as u32) != draw.camera)
                .map(|l| refs[l])
                .sum();
            assert!(held <= all_refs / 10, "{held} of {all_refs}");
            let tile_of = crate::tiles::locator(&tiles);
            let starts: Vec<Option<WorkerId>> = pv
                .pixels
                .iter()
                .map(|&(x, y)| tile_of(x, y).and_then(|t| j.starts.tiles[t]))
                .collect();
            assert_eq!(starts, j.starts.paths);
            assert_eq!(
                j.forwards,
                pv.forwards_from(&drawn.shared, &drawn.owner, &starts)
            );
            draw.view = None;
            let plain = draw.drawn(Some(&pv)).expect("drawn");
            assert_eq!(plain.shared, crossings);
            assert_eq!(plain.owner, first.owner);
            assert!(plain.judged.is_none());
        }
        assert!(checked > 0, "no farm size picked its shared leaves again");
    }
}
