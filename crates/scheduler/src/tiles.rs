//! Which worker renders which tile.
//!
//! Any worker can render any sample (sampling is a pure function of pixel,
//! sample and seed), but a path is held by the worker that starts it until
//! it enters a leaf that worker does not hold: a tile rendered by another
//! worker than the owner of the leaves its paths reach first costs a
//! forward per path before much work is done. With leaves shared by every
//! worker (walls, floors) a path may bounce between them several times
//! first. So each tile has an affinity: the owner that most of the
//! preview's paths in the tile reach first beside the shared leaves
//! ([`affinities`], from `cost::Preview::first_leaves`), or where the
//! preview has none there, the owner of the first leaf along its camera
//! rays (the majority of its centre and corner rays, [`affinity`]); and a
//! worker asking for tiles gets the tiles of its affinity, then tiles
//! without one (rays that miss the scene). A worker with no such tiles
//! left takes one of the worker with the most left: the partition
//! balanced the work it predicted, but not the run's own turns. Of that
//! worker's earliest pass it takes the tile with the most preview paths
//! it starts without forwarding them ([`votes`],
//! [`TileQueue::taken_from`]).
//!
//! Within each queue tiles keep the job's shuffled order, so that the
//! tiles in flight at any moment are spread over the image.

use crate::film::Unit;
use locus_core::octree::Octree;
use locus_core::region::WorkerId;
use locus_core::render::Tile;
use locus_core::scene::Camera;
use std::collections::VecDeque;

/// The owner of the first leaf along most of a tile's camera rays (its
/// centre and its four corners; the centre's wins a tie), or None when
/// most of them miss the scene. The `shared` leaves (which every worker
/// holds: `cost::camera_leaf`, `cost::shared_leaves`) are passed over.
/// `owner` gives each of `tree`'s leaves its worker.
pub fn affinity(
    camera: &Camera,
    tree: &Octree,
    owner: &[WorkerId],
    shared: &[bool],
    t: &Tile,
) -> Option<WorkerId> {
    let (x1, y1) = (t.x1.saturating_sub(1), t.y1.saturating_sub(1));
    let points = [
        ((t.x0 + x1) / 2, (t.y0 + y1) / 2),
        (t.x0, t.y0),
        (x1, t.y0),
        (t.x0, y1),
        (x1, y1),
    ];
    let owners: Vec<Option<WorkerId>> = points
        .iter()
        .map(|&(x, y)| {
            let ray = camera.ray(x, y, [0.5, 0.5]);
            let mut first = None;
            let _ = tree.walk(&ray, 0.0, f32::INFINITY, |leaf, _, _| {
                if shared.get(leaf as usize).copied().unwrap_or(false) {
                    return std::ops::ControlFlow::Continue(());
                }
                first = owner.get(leaf as usize).copied();
                std::ops::ControlFlow::Break(())
            });
            first
        })
        .collect();
    let count = |o: Option<WorkerId>| owners.iter().filter(|&&x| x == o).count();
    let centre = owners[0];
    owners
        .iter()
        .copied()
        .max_by_key(|&o| (count(o), o == centre))
        .flatten()
}

/// The tile holding a pixel, by index into `tiles` (a grid of tiles, as
/// [`crate::film`] cuts the image), if any does.
pub fn locator(tiles: &[Tile]) -> impl Fn(u32, u32) -> Option<usize> + '_ {
    let size = tiles
        .iter()
        .map(|t| (t.x1 - t.x0).max(t.y1 - t.y0))
        .max()
        .unwrap_or(1)
        .max(1);
    let cell: rustc_hash::FxHashMap<(u32, u32), usize> = tiles
        .iter()
        .enumerate()
        .map(|(i, t)| ((t.x0 / size, t.y0 / size), i))
        .collect();
    move |x, y| {
        let &i = cell.get(&(x / size, y / size))?;
        let t = &tiles[i];
        ((t.x0..t.x1).contains(&x) && (t.y0..t.y1).contains(&y)).then_some(i)
    }
}

/// Each tile's affinity: of `workers`, the one that most of the preview
/// paths in it reach first beside the shared leaves (its [`votes`];
/// empty where there is no preview), the lowest such worker on a tie;
/// where none of a tile's preview paths reached such a leaf, [`affinity`].
pub fn affinities(
    camera: &Camera,
    tree: &Octree,
    owner: &[WorkerId],
    shared: &[bool],
    tiles: &[Tile],
    votes: &[u32],
    workers: usize,
) -> Vec<Option<WorkerId>> {
    use rayon::prelude::*;
    tiles
        .par_iter()
        .enumerate()
        .map(|(i, t)| {
            let v = votes.get(i * workers..(i + 1) * workers).unwrap_or(&[]);
            // The first of the most voted (max_by_key keeps the last).
            match (0..v.len()).rev().max_by_key(|&w| v[w]) {
                Some(w) if v[w] > 0 => Some(w as WorkerId),
                _ => affinity(camera, tree, owner, shared, t),
            }
        })
        .collect()
}

/// Per tile and worker (`tile * workers + worker`), the preview paths in
/// the tile (`firsts`: each path's pixel and the first leaf beside the
/// shared ones that it entered, `cost::Preview::pixel_firsts`) whose
/// first leaf that worker owns: how many of the tile's paths each worker
/// would start without forwarding them.
pub fn votes(
    owner: &[WorkerId],
    tiles: &[Tile],
    firsts: &[((u32, u32), Option<u32>)],
    workers: usize,
) -> Vec<u32> {
    let tile_of = locator(tiles);
    let mut votes = vec![0u32; tiles.len() * workers];
    for &((x, y), leaf) in firsts {
        let o = leaf
            .and_then(|l| owner.get(l as usize))
            .map(|&o| o as usize);
        if let Some((i, o)) = tile_of(x, y).zip(o.filter(|&o| o < workers)) {
            votes[i * workers + o] += 1;
        }
    }
    votes
}

/// Camera samples each worker may keep in flight: the job's
/// `max_inflight` for every worker in all, shared out by the tiles each
/// will originate (its own, and an even part of those without affinity),
/// at least a quarter of `max_inflight` each. A worker that originates
/// every tile must keep the whole farm's samples in flight, or the others,
/// which work only on what it forwards them, run dry.
pub fn inflight(affinity: &[Option<WorkerId>], workers: usize, max_inflight: u32) -> Vec<u32> {
    let workers = workers.max(1);
    let mut tiles = vec![0.0f64; workers];
    for a in affinity {
        match a {
            Some(w) if (*w as usize) < workers => tiles[*w as usize] += 1.0,
            _ => tiles.iter_mut().for_each(|t| *t += 1.0 / workers as f64),
        }
    }
    let total = (affinity.len() as f64).max(1.0);
    let all = max_inflight as f64 * workers as f64;
    tiles
        .iter()
        .map(|t| {
            let n = if affinity.is_empty() {
                max_inflight as f64
            } else {
                all * t / total
            };
            (n.round() as u32).clamp(
                (max_inflight / 4).max(1),
                crate::job::MAX_INFLIGHT.max(max_inflight),
            )
        })
        .collect()
}

/// How many of another worker's tile passes a worker out of tiles chooses
/// among ([`TileQueue::taken_from`]).
const TAKE_WINDOW: usize = 256;

/// Tile passes waiting to be handed out: one queue per worker and one for
/// tiles of no worker in particular.
pub struct TileQueue {
    own: Vec<VecDeque<Unit>>,
    shared: VecDeque<Unit>,
    sizes: Sizes,
    /// Per tile and worker, the preview paths the worker would start
    /// without forwarding them ([`votes`]); empty without a preview.
    votes: Vec<u32>,
    /// Camera samples in the units waiting, by `sizes`.
    samples: u64,
}

/// How many camera samples a tile pass holds: its tile's pixels times its
/// pass's samples a pixel ([`crate::film::Film::sizes`]). Units outside
/// them hold none.
#[derive(Clone, Debug, Default)]
pub struct Sizes {
    pub tile_pixels: Vec<u64>,
    pub pass_samples: Vec<u64>,
}

impl Sizes {
    pub fn of(&self, u: Unit) -> u64 {
        let pixels = self.tile_pixels.get(u.tile as usize).copied().unwrap_or(0);
        pixels * self.pass_samples.get(u.pass as usize).copied().unwrap_or(0)
    }
}

impl TileQueue {
    /// `order` lists units in handout order (pass by pass); `affinity[t]`
    /// is tile `t`'s worker, if any.
    pub fn new(
        order: impl IntoIterator<Item = Unit>,
        affinity: &[Option<WorkerId>],
        workers: usize,
        sizes: Sizes,
    ) -> Self {
        let mut own = vec![VecDeque::new(); workers.max(1)];
        let mut shared = VecDeque::new();
        let mut samples = 0;
        for u in order {
            samples += sizes.of(u);
            match affinity.get(u.tile as usize).copied().flatten() {
                Some(w) if (w as usize) < own.len() => own[w as usize].push_back(u),
                _ => shared.push_back(u),
            }
        }
        Self {
            own,
            shared,
            sizes,
            samples,
            votes: Vec::new(),
        }
    }

    /// The queue with each tile's [`votes`], by which a worker out of
    /// tiles picks what it takes from another's.
    pub fn with_votes(mut self, votes: Vec<u32>) -> Self {
        self.votes = votes;
        self
    }

    /// Where worker `w` takes a tile pass from worker `v`'s queue: of its
    /// earliest pass (of its first [`TAKE_WINDOW`]), the one whose tile
    /// has the most preview paths that `w` starts without forwarding them
    /// (the first such on a tie). Every tile in `v`'s queue is one whose
    /// paths mostly reach `v`'s leaves first, so the camera rays of
    /// whichever is taken are mostly forwarded back to `v`; some less so
    /// than others (on the room at 2 workers, a run whose workers took
    /// many of each other's tiles forwarded 67,811 camera rays where
    /// others forwarded about 12,000 to 23,000).
    fn taken_from(&self, v: usize, w: usize) -> Option<usize> {
        let q = &self.own[v];
        let pass = q.front()?.pass;
        let workers = self.own.len();
        let votes = |u: &Unit| match w < workers {
            true => self.votes.get(u.tile as usize * workers + w).copied(),
            false => None,
        };
        let mut best = 0;
        // Within the first few of the pass (the queue keeps the job's
        // shuffled order, so they are spread over the image): a worker
        // asking again and again scans no whole queue of a large image.
        let window = q.iter().take(TAKE_WINDOW).enumerate();
        for (i, u) in window.take_while(|(_, u)| u.pass == pass) {
            if votes(u) > votes(&q[best]) {
                best = i;
            }
        }
        Some(best)
    }

    /// The next tile pass for worker `w`: its own or a shared one,
    /// whichever is of the earlier pass (its own on a tie), so that no
    /// worker runs passes ahead of the image; with neither left, one of
    /// the worker with the most left ([`TileQueue::taken_from`]: the
    /// partition balanced the work it
    /// predicted, but not the shared leaves', which falls to whoever
    /// holds the rays, nor its own errors: a worker whose tiles ran out
    /// first would otherwise wait for the others); None if it is of a
    /// pass not yet `open` (see [`crate::film::Film::open_passes`]) or
    /// none is left.
    pub fn next_for(&mut self, w: usize, open: u32) -> Option<Unit> {
        let shared_pass = self.shared.front().map(|u| u.pass);
        let own_pass = self.own.get(w).and_then(|q| q.front()).map(|u| u.pass);
        let (q, at) = match (own_pass, shared_pass) {
            (Some(o), Some(s)) if o <= s => (&mut self.own[w], 0),
            (Some(_), None) => (&mut self.own[w], 0),
            (None, None) => {
                let most =
                    (0..self.own.len()).max_by_key(|&v| (self.own[v].len(), usize::MAX - v))?;
                let at = self.taken_from(most, w)?;
                (&mut self.own[most], at)
            }
            _ => (&mut self.shared, 0),
        };
        if q.front()?.pass >= open {
            return None;
        }
        let u = q.remove(at)?;
        self.samples -= self.sizes.of(u);
        Some(u)
    }

    /// Returns a unit `next_for` gave that could not be handed out (its
    /// worker's channel was full): it goes first to whichever worker asks
    /// next. It was of the earliest pass waiting, so the shared queue stays
    /// in pass order.
    pub fn put_back(&mut self, u: Unit) {
        self.samples += self.sizes.of(u);
        self.shared.push_front(u);
    }

    /// Camera samples in the tile passes waiting.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Tile passes not yet handed out.
    pub fn len(&self) -> usize {
        self.own.iter().map(VecDeque::len).sum::<usize>() + self.shared.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::region::ProcessorMap;

    fn tiles(q: &mut TileQueue, w: usize, n: usize) -> Vec<(u32, u32)> {
        (0..n)
            .map_while(|_| q.next_for(w, u32::MAX))
            .map(|u| (u.tile, u.pass))
            .collect()
    }

    #[test]
    fn workers_get_their_own_tiles_then_shared_ones_then_others() {
        let aff = [Some(1), None, Some(0), Some(1), None, Some(7)];
        let order = [5, 4, 3, 2, 1, 0].map(|tile| Unit { tile, pass: 0 });
        let mut q = TileQueue::new(order, &aff, 2, Sizes::default());
        assert_eq!(q.len(), 6);
        // Worker 0: its tile 2, then shared tiles in order (tile 5's
        // worker does not exist, so it is shared).
        assert_eq!(tiles(&mut q, 0, 2), [(2, 0), (5, 0)]);
        // Worker 1: its own, in order.
        assert_eq!(tiles(&mut q, 1, 3), [(3, 0), (0, 0), (4, 0)]);
        assert_eq!(tiles(&mut q, 0, 9), [(1, 0)]);
        assert_eq!(q.next_for(9, u32::MAX), None);
        assert!(q.is_empty());
    }

    /// A worker with no tiles of its own and none shared left takes the
    /// next of the worker with the most left, in pass order, never of a
    /// pass not yet open.
    #[test]
    fn a_worker_out_of_tiles_takes_the_busiest_workers_next() {
        // Tiles 0-3 worker 0's, tile 4 worker 2's, none worker 1's; two
        // passes.
        let aff = [Some(0), Some(0), Some(0), Some(0), Some(2)];
        let order = (0..2).flat_map(|pass| (0..5).map(move |tile| Unit { tile, pass }));
        let mut q = TileQueue::new(order, &aff, 3, Sizes::default());
        assert!(!q.is_empty());
        assert_eq!(tiles(&mut q, 1, 2), [(0, 0), (1, 0)]);
        // Worker 0 has 6 left, worker 2 has 2: worker 2 gets its own.
        assert_eq!(tiles(&mut q, 2, 1), [(4, 0)]);
        // Pass 1 is not open: worker 1 gets worker 0's last of pass 0.
        assert_eq!(q.next_for(1, 1), Some(Unit { tile: 2, pass: 0 }));
        assert_eq!(q.next_for(1, 1), Some(Unit { tile: 3, pass: 0 }));
        assert_eq!(q.next_for(1, 1), None);
        assert!(!q.is_empty());
        assert_eq!(tiles(&mut q, 1, 9).len(), 5);
        assert!(q.is_empty());
    }

    /// A worker out of tiles takes, of the busiest worker's earliest
    /// pass, the tile with the most preview paths it starts without
    /// forwarding them (the first on a tie) among the first
    /// [`TAKE_WINDOW`], never one of a later pass; without votes, the
    /// front. The votes follow the paths' first leaves.
    #[test]
    fn a_worker_out_of_tiles_takes_the_tile_it_forwards_least_of() {
        // Four tiles in a row, each of 4x1 pixels; leaves 0-3, leaf l
        // worker l % 2's. Tile t's paths: the pixels' first leaves.
        let grid: Vec<Tile> = (0..4)
            .map(|i| Tile {
                x0: 4 * i,
                y0: 0,
                x1: 4 * i + 4,
                y1: 1,
            })
            .collect();
        let owner = [0, 1, 0, 1];
        let firsts: Vec<((u32, u32), Option<u32>)> =
            [[0, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 3], [1, 1, 0, 0]]
                .iter()
                .enumerate()
                .flat_map(|(t, ls)| {
                    ls.iter()
                        .enumerate()
                        .map(move |(i, &l)| ((4 * t as u32 + i as u32, 0), Some(l)))
                })
                .collect();
        let votes = votes(&owner, &grid, &firsts, 2);
        assert_eq!(votes, [4, 0, 2, 2, 3, 1, 2, 2]);
        let aff = [Some(0), Some(0), Some(0), Some(0)];
        let order = || (0..2).flat_map(|pass| (0..4).map(move |tile| Unit { tile, pass }));
        let mut q = TileQueue::new(order(), &aff, 2, Sizes::default()).with_votes(votes);
        // Worker 1 has none: of pass 0, tile 1 (2 votes, before tile 3's 2).
        assert_eq!(tiles(&mut q, 1, 2), [(1, 0), (3, 0)]);
        assert_eq!(tiles(&mut q, 0, 1), [(0, 0)]);
        // Pass 0's last tile before any of pass 1, though tile 1 of pass 1
        // has more votes for worker 1.
        assert_eq!(tiles(&mut q, 1, 2), [(2, 0), (1, 1)]);
        let mut plain = TileQueue::new(order(), &aff, 2, Sizes::default());
        assert_eq!(tiles(&mut plain, 1, 2), [(0, 0), (1, 0)]);
        // Only the first TAKE_WINDOW of a pass are looked at.
        let n = TAKE_WINDOW as u32 + 1;
        let aff = vec![Some(0); n as usize];
        let mut votes = vec![0; 2 * n as usize];
        votes[2 * (n as usize - 2) + 1] = 1;
        votes[2 * (n as usize - 1) + 1] = 5;
        let order = (0..n).map(|tile| Unit { tile, pass: 0 });
        let mut q = TileQueue::new(order, &aff, 2, Sizes::default()).with_votes(votes);
        assert_eq!(tiles(&mut q, 1, 1), [(n - 2, 0)]);
    }

    #[test]
    fn no_worker_runs_a_pass_ahead_of_the_shared_tiles() {
        // Tile 0 is worker 0's, tiles 1 and 2 nobody's; two passes.
        let aff = [Some(0), None, None];
        let order = (0..2).flat_map(|pass| (0..3).map(move |tile| Unit { tile, pass }));
        let mut q = TileQueue::new(order, &aff, 2, Sizes::default());
        assert_eq!(
            tiles(&mut q, 0, 9),
            [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1)]
        );
    }

    #[test]
    fn a_closed_pass_is_held_back_without_saying_none_is_left() {
        // Tile 0 is worker 0's, tile 1 nobody's; two passes, the second
        // closed (a noise target's barrier until the first is in).
        let aff = [Some(0), None];
        let order = (0..2).flat_map(|pass| (0..2).map(move |tile| Unit { tile, pass }));
        let mut q = TileQueue::new(order, &aff, 2, Sizes::default());
        assert_eq!(q.next_for(0, 1), Some(Unit { tile: 0, pass: 0 }));
        assert_eq!(q.next_for(1, 1), Some(Unit { tile: 1, pass: 0 }));
        assert_eq!(q.next_for(0, 1), None);
        assert_eq!(q.next_for(1, 1), None);
        assert!(!q.is_empty(), "held back, not gone");
        assert_eq!(q.len(), 2);
        // Opened: the second pass goes out as the first did.
        assert_eq!(tiles(&mut q, 0, 1), [(0, 1)]);
        assert_eq!(tiles(&mut q, 1, 9), [(1, 1)]);
        assert!(q.is_empty());
    }

    #[test]
    fn samples_in_flight_follow_the_tiles_a_worker_originates() {
        // Worker 0 originates every tile: it keeps the farm's samples.
        assert_eq!(inflight(&[Some(0); 8], 4, 1000), [4000, 250, 250, 250]);
        // No affinity: the job's figure each.
        assert_eq!(inflight(&[None; 8], 4, 1000), [1000; 4]);
        // Half and half; no tiles at all.
        assert_eq!(inflight(&[Some(0), Some(1)], 2, 1000), [1000, 1000]);
        assert_eq!(inflight(&[], 3, 1000), [1000; 3]);
    }

    #[test]
    fn a_tile_belongs_to_the_owner_its_camera_rays_meet_first() {
        use glam::Vec3;
        use locus_core::octree::{Octree, OctreeParams};
        // A floor of triangles from x = -10 to 10; the left half (x < 0)
        // is worker 0's, the right half worker 1's.
        let mut tris = Vec::new();
        for i in -10..10 {
            let x = i as f32;
            tris.push([
                Vec3::new(x, 0.0, -5.0),
                Vec3::new(x + 1.0, 0.0, -5.0),
                Vec3::new(x, 0.0, 5.0),
            ]);
        }
        let tree = Octree::build(
            &tris,
            OctreeParams {
                max_leaf_tris: 2,
                max_depth: 6,
            },
        );
        let owner: Vec<WorkerId> = tree
            .leaves
            .iter()
            .map(|l| (l.bounds.center().x >= 0.0) as WorkerId)
            .collect();
        let map = ProcessorMap::new(&tree, owner);
        // A camera far above the floor's left half, looking down: every
        // ray starts outside the octree and first enters a left leaf.
        let camera = Camera {
            position: Vec3::new(-5.0, 20.0, 0.0),
            look_at: Vec3::new(-5.0, 0.0, 0.0),
            up: Vec3::Z,
            fov_y: 10.0,
            width: 32,
            height: 32,
        };
        let tile = |x0, y0| Tile {
            x0,
            y0,
            x1: x0 + 8,
            y1: y0 + 8,
        };
        assert_eq!(
            affinity(&camera, &map.tree, &map.owner, &[], &tile(0, 0)),
            Some(0)
        );
        assert_eq!(
            affinity(&camera, &map.tree, &map.owner, &[], &tile(24, 24)),
            Some(0)
        );
        // Looking away from the scene: no affinity.
        let away = Camera {
            look_at: Vec3::new(-5.0, 40.0, 0.0),
            ..camera
        };
        assert_eq!(
            affinity(&away, &map.tree, &map.owner, &[], &tile(8, 8)),
            None
        );

        // With the preview's paths: a tile goes to the owner most of its
        // paths reach first, whatever its camera rays meet first; on a tie
        // to the lower worker; without a path that reached a leaf (or
        // only paths outside it), by its camera rays.
        let grid: Vec<Tile> = (0..4)
            .flat_map(|y| (0..4).map(move |x| tile(x * 8, y * 8)))
            .collect();
        let left = map.owner.iter().position(|&o| o == 0).unwrap() as u32;
        let right = map.owner.iter().position(|&o| o == 1).unwrap() as u32;
        let firsts = [
            // Tile (0, 0): three paths reach worker 1 first, one worker 0.
            ((1, 1), Some(right)),
            ((7, 7), Some(right)),
            ((3, 0), Some(right)),
            ((2, 2), Some(left)),
            // Tile (8, 0): one each.
            ((9, 1), Some(right)),
            ((15, 7), Some(left)),
            // Tile (16, 0): a path that met shared leaves only.
            ((16, 0), None),
            // Tile (24, 24): its own camera rays decide.
        ];
        let workers = map.owner.iter().map(|&o| o as usize + 1).max().unwrap_or(1);
        let v = votes(&map.owner, &grid, &firsts, workers);
        let a = affinities(&camera, &map.tree, &map.owner, &[], &grid, &v, workers);
        assert_eq!(a.len(), 16);
        assert_eq!(a[0], Some(1));
        assert_eq!(a[1], Some(0));
        assert_eq!(
            a[2],
            affinity(&camera, &map.tree, &map.owner, &[], &grid[2])
        );
        assert_eq!(a[15], Some(0));
        // Every tile without paths, by its camera rays.
        let by_rays: Vec<_> = grid
            .iter()
            .map(|t| affinity(&camera, &map.tree, &map.owner, &[], t))
            .collect();
        assert_eq!(
            affinities(&camera, &map.tree, &map.owner, &[], &grid, &[], workers),
            by_rays
        );
    }

    /// A camera inside the scene: its rays all start in its leaf, whose
    /// owner would get every tile; with that leaf shared (every worker
    /// holds it) a tile goes to the owner of the leaf its rays enter next.
    #[test]
    fn the_shared_camera_leaf_is_passed_over() {
        use glam::Vec3;
        use locus_core::octree::{Octree, OctreeParams};
        let mut tris = Vec::new();
        for i in 0..8 {
            for j in 0..8 {
                for k in 0..8 {
                    let c = Vec3::new(i as f32, j as f32, k as f32) * 2.5 - 9.0;
                    tris.push([c, c + Vec3::X * 0.3, c + Vec3::Y * 0.3]);
                }
            }
        }
        let tree = Octree::build(
            &tris,
            OctreeParams {
                max_leaf_tris: 4,
                max_depth: 6,
            },
        );
        let camera = Camera {
            position: Vec3::new(-8.5, -8.5, -8.5),
            look_at: Vec3::splat(9.0),
            up: Vec3::Y,
            fov_y: 20.0,
            width: 32,
            height: 32,
        };
        let cam = tree.leaf_at(camera.position).expect("the camera is inside");
        // The camera's leaf is worker 0's, every other worker 1's.
        let owner: Vec<WorkerId> = (0..tree.leaves.len())
            .map(|l| (l as u32 != cam) as WorkerId)
            .collect();
        let map = ProcessorMap::new(&tree, owner);
        let tile = Tile {
            x0: 8,
            y0: 8,
            x1: 24,
            y1: 24,
        };
        assert_eq!(
            affinity(&camera, &map.tree, &map.owner, &[], &tile),
            Some(0)
        );
        let mut shared = vec![false; tree.leaves.len()];
        shared[cam as usize] = true;
        assert_eq!(
            affinity(&camera, &map.tree, &map.owner, &shared, &tile),
            Some(1)
        );
    }

    /// The queue counts the samples it holds, through hand-outs and
    /// units put back, against the sum over what it still holds.
    #[test]
    fn the_queue_counts_the_samples_it_holds() {
        let sizes = Sizes {
            tile_pixels: vec![256, 256, 64, 16],
            pass_samples: vec![1, 3, 12],
        };
        let order: Vec<Unit> = (0..3)
            .flat_map(|pass| (0..4).map(move |tile| Unit { tile, pass }))
            .collect();
        let aff = [Some(0), Some(1), None, Some(1)];
        let mut q = TileQueue::new(order.clone(), &aff, 2, sizes.clone());
        let all: u64 = order.iter().map(|&u| sizes.of(u)).sum();
        assert_eq!(q.samples(), all);
        let mut out = Vec::new();
        for step in 0..order.len() {
            let w = step % 2;
            let Some(u) = q.next_for(w, 3) else { break };
            out.push(u);
            if step % 5 == 4 {
                q.put_back(out.pop().unwrap());
            }
            let held: u64 = all - out.iter().map(|&u| sizes.of(u)).sum::<u64>();
            assert_eq!(q.samples(), held, "step {step}");
        }
        while let Some(u) = q.next_for(0, 3) {
            out.push(u);
        }
        assert_eq!((q.samples(), q.len(), out.len()), (0, 0, order.len()));
        // Units outside the sizes hold nothing.
        assert_eq!(sizes.of(Unit { tile: 9, pass: 0 }), 0);
    }
}
