//! Regions: which worker owns which octree leaf, and how a worker traces
//! the part of a ray that it can trace itself.
//!
//! The [`ProcessorMap`] is the top of the tree that every worker holds
//! (paper 003, section 3.3): all leaf bounds and their owners, no
//! triangles. Walking it along a ray yields the ray's processor vector, the
//! ordered owners of the leaves it crosses. A [`Route`] is the octree
//! collapsed over any per-leaf label (every subtree of one label becomes
//! one node), which is what rays walk: a worker labels the leaves it can
//! trace `local` and the rest by owner, and walks a node per change of
//! label rather than one per leaf.
//!
//! [`trace_local`] is the one piece of code that traces a ray through what
//! a worker holds. It asks the local BVHs first, over the whole rest of the
//! ray, and walks the route only as far as that answer needs: up to the
//! hit, or to the first leaf it cannot trace. Because leaf intervals
//! partition the ray, references are made from inflated leaf boxes and
//! equal-distance hits resolve by global triangle id, chaining workers this
//! way gives exactly the closest hit (and the occlusion answer) of one BVH
//! over the whole scene.
//!
//! Most of what a worker traces never leaves its region, so [`trace_local`]
//! first tries to show that the piece of a ray it needs crosses local
//! leaves only without walking: the sender's span ([`Resume`]), the boxes
//! grown around local nodes, and the foreign hull ([`Hull`]), a few boxes
//! holding every node the worker cannot trace.

use crate::accel_set::{AccelSet, SetHit};
use crate::geometry::{Bounds, Ray};
use crate::octree::{Octree, WalkTable};
use crate::stats::TraceStats;
use glam::{Vec3, Vec4};
use serde::{Deserialize, Serialize};
use std::ops::ControlFlow;

mod hull;
pub use hull::Hull;

/// Index of a worker in a job (its place in the job's worker list).
pub type WorkerId = u16;

/// The octree collapsed over a label per leaf.
#[derive(Clone, Debug, PartialEq)]
pub struct Route<L> {
    /// The collapsed tree, laid out for walking.
    table: WalkTable,
    labels: Vec<L>,
    /// Per route node, a box around it that leaves of its own locality
    /// cover entirely (see [`Route::grow_local_boxes`]); its own bounds
    /// until grown.
    boxes: Vec<Bounds>,
    /// The largest grown boxes, none inside another, tried before
    /// anything else: most pieces a worker traces lie in one of them, and
    /// they need no descent of the tree.
    largest: Option<LargestBoxes>,
    /// Boxes holding every node that the grown boxes' `local` rejects.
    hull: Option<Hull>,
}

impl<L: Copy + PartialEq> Route<L> {
    /// `label[leaf]` for every leaf of `tree`.
    pub fn new(tree: &Octree, label: &[L]) -> Self {
        Self::from_collapsed(tree.collapse(label))
    }

    fn from_collapsed((tree, labels): (Octree, Vec<L>)) -> Self {
        let boxes = tree.leaves.iter().map(|l| l.bounds).collect();
        Self {
            table: WalkTable::new(tree),
            labels,
            boxes,
            largest: None,
            hull: None,
        }
    }

    /// Grows, for every node `local` accepts, a box around it that only
    /// local nodes cover: greedily, face by face, each step as thick as
    /// the box (halved down to the finest node while it fails). A ray
    /// piece inside such a box crosses local leaves only, however many, so
    /// [`trace_local`] need not walk it.
    pub fn grow_local_boxes(&mut self, local: impl Fn(L) -> bool) {
        let root = self.table.tree().bounds;
        let finest = self
            .table
            .tree()
            .leaves
            .iter()
            .map(|l| l.bounds.extent().min_element())
            .fold(f32::INFINITY, f32::min);
        let ok = |l: u32| local(self.labels[l as usize]);
        let mut boxes = self.boxes.clone();
        let mut stack = Vec::new();
        for (i, out) in boxes.iter_mut().enumerate() {
            if !local(self.labels[i]) {
                continue;
            }
            let mut b = self.table.tree().leaves[i].bounds;
            for _round in 0..3 {
                let mut grew = false;
                for dir in 0..6 {
                    let (a, up) = (dir / 2, dir % 2 == 0);
                    let mut step = b.extent()[a].max(finest);
                    while step >= finest {
                        let mut slab = b;
                        if up {
                            slab.min[a] = b.max[a];
                            slab.max[a] = (b.max[a] + step).min(root.max[a]);
                        } else {
                            slab.max[a] = b.min[a];
                            slab.min[a] = (b.min[a] - step).max(root.min[a]);
                        }
                        if slab.max[a] <= slab.min[a] {
                            break;
                        }
                        if self.table.tree().all_overlapping(&slab, &ok, &mut stack) {
                            if up {
                                b.max[a] = slab.max[a];
                            } else {
                                b.min[a] = slab.min[a];
                            }
                            grew = true;
                            break;
                        }
                        step *= 0.5;
                    }
                }
                if !grew {
                    break;
                }
            }
            *out = b;
        }
        self.largest = LargestBoxes::new(
            (0..boxes.len())
                .filter(|&i| local(self.labels[i]))
                .map(|i| boxes[i]),
        );
        self.boxes = boxes;
        let foreign = (0..self.labels.len())
            .filter(|&i| !local(self.labels[i]))
            .map(|i| self.table.tree().leaves[i].bounds)
            .collect();
        self.hull = Hull::new(foreign, &root);
    }

    /// Nodes rays walk (for reports: how much the merge saved).
    pub fn leaves(&self) -> usize {
        self.labels.len()
    }

    /// The route node containing `p`: its label, and the box around it
    /// that its locality covers (its bounds unless grown).
    #[inline]
    pub fn containing(&self, p: glam::Vec3) -> Option<(L, &Bounds)> {
        let l = self.table.tree().leaf_at(p)? as usize;
        Some((self.labels[l], &self.boxes[l]))
    }

    /// The labelled intervals along `ray` within `[t0, t1)` from `resume`,
    /// front to back; adjacent intervals may carry the same label.
    #[inline]
    pub fn walk<F>(&self, ray: &Ray, t0: f32, t1: f32, resume: f32, mut f: F) -> ControlFlow<()>
    where
        F: FnMut(L, f32, f32) -> ControlFlow<()>,
    {
        self.table.walk_from(ray, t0, t1, resume, |l, a, b| {
            f(self.labels[l as usize], a, b)
        })
    }
}

/// On the wire a processor map is the tree and its owners; the route is
/// rebuilt (and the parts checked) on arrival.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "MapParts", into = "MapParts")]
pub struct ProcessorMap {
    /// The octree with empty triangle lists.
    pub tree: Octree,
    /// Owner of each leaf.
    pub owner: Vec<WorkerId>,
    /// `tree` collapsed by owner.
    pub route: Route<WorkerId>,
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

impl ProcessorMap {
    pub fn new(tree: &Octree, owner: Vec<WorkerId>) -> Self {
        assert_eq!(tree.leaves.len(), owner.len(), "one owner per leaf");
        // Boxes are grown by whoever traces through the route: which
        // nodes are local depends on the worker.
        Self {
            route: Route::new(tree, &owner),
            tree: tree.without_triangles(),
            owner,
        }
    }

    /// Owner of the first leaf on `[0, t_max)`, or `None` when the ray
    /// misses the scene.
    pub fn first_owner(&self, ray: &Ray, t_max: f32) -> Option<(WorkerId, f32)> {
        let mut first = None;
        let _ = self
            .route
            .walk(ray, 0.0, t_max, f32::NEG_INFINITY, |o, ta, _| {
                first = Some((o, ta));
                ControlFlow::Break(())
            });
        first
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

/// Where a ray resumes, and how far beyond that it is known to lie in
/// leaves the tracer holds: a worker that forwards a ray has walked the
/// route node it forwards it into (one owner's subtree, or one leaf), so
/// the receiver need not walk `[at, local_until)` again.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Resume {
    pub at: f32,
    pub local_until: f32,
}

impl Resume {
    /// A ray traced from its origin, with nothing known.
    pub const START: Resume = Resume::at(f32::NEG_INFINITY);

    /// Resuming at `t`, with nothing known beyond.
    pub const fn at(t: f32) -> Self {
        Self {
            at: t,
            local_until: t,
        }
    }

    /// Resuming at `at` in a route node that ends at `end`, all of it held
    /// by the receiver.
    pub const fn within(at: f32, end: f32) -> Self {
        Self {
            at,
            local_until: end,
        }
    }
}

/// What the local BVHs hold along a ray beyond where it was first asked:
/// computed once per ray and kept while the ray is traced piece by piece
/// (a later piece starts beyond an earlier one, where the answer is the
/// same: see [`trace_local`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Known {
    #[default]
    Unknown,
    Closest(Option<SetHit>),
    /// The segment is not blocked by anything local.
    Clear,
}

/// Up to four grown boxes in the lanes of one SSE register each way, so
/// that whether a piece's two ends lie in one of them is one test.
#[derive(Clone, Copy, Debug, PartialEq)]
struct LargestBoxes {
    /// Per axis, the boxes' lower and upper faces; unused lanes repeat
    /// the first box.
    min: [Vec4; 3],
    max: [Vec4; 3],
}

impl LargestBoxes {
    /// The largest of `boxes` by volume, then each next largest that no
    /// box already taken contains, up to four; None without boxes.
    fn new(boxes: impl Iterator<Item = Bounds>) -> Option<Self> {
        let mut all: Vec<Bounds> = boxes.collect();
        all.sort_by(|a, b| b.volume().total_cmp(&a.volume()));
        let mut taken: Vec<Bounds> = Vec::with_capacity(4);
        for b in all {
            if taken.len() == 4 {
                break;
            }
            if !taken.iter().any(|t| t.contains(b.min) && t.contains(b.max)) {
                taken.push(b);
            }
        }
        let lane = |i: usize| taken.get(i).unwrap_or(&taken[0]);
        let faces = |f: fn(&Bounds) -> Vec3| -> [Vec4; 3] {
            std::array::from_fn(|a| Vec4::from_array(std::array::from_fn(|i| f(lane(i))[a])))
        };
        (!taken.is_empty()).then(|| Self {
            min: faces(|b| b.min),
            max: faces(|b| b.max),
        })
    }

    /// Whether one box holds both `p` and `q` (each lane is
    /// [`Bounds::contains`] twice).
    #[inline(always)]
    fn hold(&self, p: Vec3, q: Vec3) -> bool {
        let inside = |a: usize| {
            let (p, q) = (Vec4::splat(p[a]), Vec4::splat(q[a]));
            p.cmpge(self.min[a])
                & p.cmple(self.max[a])
                & q.cmpge(self.min[a])
                & q.cmple(self.max[a])
        };
        (inside(0) & inside(1) & inside(2)).any()
    }
}

/// Where tracing through local geometry ends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RunEnd<L> {
    /// The closest hit of the whole ray, in a local leaf.
    Hit(SetHit),
    /// Something local blocks the segment (any-hit queries).
    Occluded,
    /// The ray leaves the scene, or its segment ends, without a hit.
    Miss,
    /// The first leaf not traced here spans `[ta, tb)`; nothing local lies
    /// on the ray before `ta`.
    Foreign { label: L, ta: f32, tb: f32 },
}

/// Whether the piece `[ts, te]` of `ray` lies in one of the largest grown boxes,
/// misses the foreign hull, or lies in one box that local leaves cover (a
/// local node, grown) or two that both hold its middle; the last is not
/// tried when the hull is exact (a piece it does not clear crosses a
/// foreign node). A box
/// is convex, so points decide: the piece's ends and its middle. Boxes are
/// found from points a little inside the piece: its start may lie on a
/// face (a forwarded ray resumes on its region's border).
#[inline]
fn covered<L: Copy + PartialEq>(
    route: &Route<L>,
    local: &impl Fn(L) -> bool,
    ray: &Ray,
    ts: f32,
    te: f32,
) -> bool {
    let local_box = |t: f32| match route.containing(ray.at(t)) {
        Some((l, b)) if local(l) => Some(*b),
        _ => None,
    };
    let (start, end) = (ray.at(ts), ray.at(te));
    if route.largest.is_some_and(|l| l.hold(start, end)) {
        return true;
    }
    if let Some(h) = &route.hull {
        if h.clear(ray, ts, te) {
            return true;
        }
        if h.exact() {
            return false;
        }
    }
    let tm = 0.5 * (ts + te);
    let Some(mid) = local_box(tm) else {
        return false;
    };
    let (has_start, has_end) = (mid.contains(start), mid.contains(end));
    if has_start && has_end {
        return true;
    }
    // The other end's box must hold the middle too.
    let step = 0.0625 * (te - ts);
    let (t, p) = if has_start {
        (te - step, end)
    } else if has_end {
        (ts + step, start)
    } else {
        return false;
    };
    match local_box(t) {
        Some(b) => b.contains(p) && b.contains(ray.at(tm)),
        None => false,
    }
}

/// Traces `ray` on `[0, t_max)` from `resume.at` through the leaves `local`
/// accepts, whose triangles `accel` holds (it may hold others too); the
/// caller vouches that `[resume.at, resume.local_until)` lies in such
/// leaves.
///
/// The BVHs are asked first over the whole rest of the ray:
/// - closest hit `h`: the route is walked until the interval holding `h`;
///   if every interval up to it is local, `h` is the answer (any closer hit
///   would lie in a local leaf, whose triangles `accel` has). Otherwise the
///   first foreign interval is returned, and `h` (which lies in it or
///   beyond) stays valid for the rest of the ray in `known`.
/// - any hit: any triangle blocking the segment makes it occluded,
///   whichever leaf it lies in, so the route is walked only when nothing
///   local blocks it, to find the first foreign interval.
#[allow(clippy::too_many_arguments)]
pub fn trace_local<L: Copy + PartialEq>(
    route: &Route<L>,
    local: impl Fn(L) -> bool,
    accel: &AccelSet,
    ray: &Ray,
    t_max: f32,
    resume: Resume,
    any: bool,
    known: &mut Known,
    stats: &mut TraceStats,
) -> RunEnd<L> {
    let t0 = resume.at.max(0.0);
    // The hit is taken from the BVH's answer, not read back from `known`
    // just written: a read that spans several narrower stores waits for
    // them (about a tenth of this function's time on the clock, `perf`).
    let hit = match *known {
        // A hit before `t0` reaches here only from a caller that skipped
        // a foreign interval holding it: ask again rather than trust it.
        Known::Closest(h) if h.is_none_or(|h| h.hit.hit.t >= t0) => h,
        Known::Clear => None,
        _ if any => {
            if accel.occluded(ray, t0, t_max, stats) {
                *known = Known::Unknown;
                return RunEnd::Occluded;
            }
            *known = Known::Clear;
            None
        }
        _ => {
            let h = accel.closest(ray, t0, t_max, stats);
            *known = Known::Closest(h);
            h
        }
    };
    // The usual case needs no walk: the piece of the ray that matters (up
    // to the hit, or the whole segment when nothing local blocks it) lies
    // in a box that local leaves cover (a local node, grown). A box is
    // convex, so its two ends decide; every triangle crossing that piece
    // crosses a local leaf, which references it, so the local BVHs have
    // seen it. (Points computed in f32 stray far less than the margin by
    // which leaves reference triangles.)
    let piece_end = match hit {
        Some(h) => Some(h.hit.hit.t),
        None if any && t_max.is_finite() => Some(t_max),
        None => None,
    };
    if let Some(te) = piece_end {
        // The sender's walk already showed `[at, local_until)` to lie in
        // leaves held here: a piece ending inside it needs no walk at all.
        let inside = if any {
            te <= resume.local_until
        } else {
            te < resume.local_until
        };
        if inside {
            return match hit {
                Some(h) => RunEnd::Hit(h),
                None => RunEnd::Miss,
            };
        }
        let ts = t0.max(resume.local_until);
        if covered(route, &local, ray, ts, te) {
            return match hit {
                Some(h) => RunEnd::Hit(h),
                None => RunEnd::Miss,
            };
        }
    } else if route
        .hull
        .as_ref()
        .is_some_and(|h| h.clear(ray, t0.max(resume.local_until), t_max))
    {
        // Nothing local on the rest of the ray, and nothing foreign.
        return RunEnd::Miss;
    }
    let mut end = RunEnd::Miss;
    // Nothing local is hit on `[at, local_until)`: the walk starts beyond.
    let from = resume.at.max(resume.local_until);
    let _ = route.walk(ray, 0.0, t_max, from, |label, ta, tb| {
        if !local(label) {
            end = RunEnd::Foreign { label, ta, tb };
            return ControlFlow::Break(());
        }
        match hit {
            Some(h) if h.hit.hit.t < tb => {
                end = RunEnd::Hit(h);
                ControlFlow::Break(())
            }
            _ => ControlFlow::Continue(()),
        }
    });
    end
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::tests::grid_octree;
    use crate::sampler::SampleKey;
    use glam::Vec3;

    /// Piece `i` of the region tests: a ray between two points drawn in
    /// `tree`'s root, and the distance between them (None when they meet).
    pub(crate) fn random_piece(tree: &Octree, i: u64) -> Option<(Ray, f32)> {
        let (lo, hi) = (tree.bounds.min, tree.bounds.max);
        let k = SampleKey::independent(i, 3, 9);
        let u = |d: u32| k.get1d(d);
        let p = lo + (hi - lo) * Vec3::new(u(0), u(1), u(2));
        let q = lo + (hi - lo) * Vec3::new(u(3), u(4), u(5));
        let dir = (q - p).try_normalize()?;
        Some((Ray::new(p, dir), (q - p).length()))
    }

    /// The largest boxes are the four largest that no larger one holds,
    /// and `hold` says, for many point pairs, exactly whether one of them
    /// holds both (against [`Bounds::contains`], box by box).
    #[test]
    fn largest_boxes_hold_what_one_box_holds() {
        let b = |lo: [f32; 3], hi: [f32; 3]| Bounds::new(Vec3::from(lo), Vec3::from(hi));
        let boxes = [
            b([0.0, 0.0, 0.0], [4.0, 4.0, 4.0]),
            b([1.0, 1.0, 1.0], [2.0, 2.0, 2.0]), // inside the first
            b([3.0, 0.0, 0.0], [8.0, 2.0, 2.0]),
            b([0.0, 5.0, 0.0], [2.0, 8.0, 1.0]),
            b([6.0, 6.0, 6.0], [7.0, 7.0, 7.0]),
            b([7.5, 7.5, 7.5], [8.0, 8.0, 8.0]), // the smallest: left out
        ];
        let l = LargestBoxes::new(boxes.iter().copied()).unwrap();
        let kept = [boxes[0], boxes[2], boxes[3], boxes[4]];
        let (mut both, mut neither) = (0, 0);
        for i in 0..20_000u64 {
            let k = SampleKey::independent(i, 1, 11);
            let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 8.0;
            let q = Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 8.0;
            let want = kept.iter().any(|b| b.contains(p) && b.contains(q));
            assert_eq!(l.hold(p, q), want, "{p} {q}");
            both += want as usize;
            neither += !want as usize;
        }
        // Points on faces count as inside, as in `Bounds::contains`.
        assert!(l.hold(Vec3::new(8.0, 2.0, 0.0), Vec3::new(3.0, 0.0, 2.0)));
        assert!(!l.hold(Vec3::new(7.75, 7.75, 7.75), Vec3::splat(7.8)));
        assert!(both > 100 && neither > 100, "{both} {neither}");
        assert!(LargestBoxes::new(std::iter::empty()).is_none());
    }

    /// Whenever [`covered`] says a piece lies in boxes of local leaves, the
    /// walk finds only local leaves along it; and it says so for many
    /// pieces that cross several route nodes, which is what spares walks.
    #[test]
    fn covered_pieces_cross_local_leaves_only() {
        let tree = grid_octree(24, 6, 6);
        let n = tree.leaves.len();
        let hi = tree.bounds.max;
        let (mut said, mut multi) = (0, 0);
        for scattered in [false, true] {
            // Scattered owners leave foreign holes inside local space.
            let owner: Vec<u16> = (0..n)
                .map(|l| match scattered {
                    true => (SampleKey::independent(l as u64, 0, 5).get1d(0) < 0.2) as u16,
                    false => (tree.leaves[l].bounds.center().x > 0.6 * hi.x) as u16,
                })
                .collect();
            let mut route = Route::new(&tree, &owner);
            route.grow_local_boxes(|o| o == 0);
            let local = |o: u16| o == 0;
            for i in 0..20_000u64 {
                let Some((ray, te)) = random_piece(&tree, i) else {
                    continue;
                };
                if !covered(&route, &local, &ray, 0.0, te) {
                    continue;
                }
                said += 1;
                let mut labels = Vec::new();
                let _ = route.walk(&ray, 0.0, te, f32::NEG_INFINITY, |l, _, _| {
                    labels.push(l);
                    ControlFlow::Continue(())
                });
                assert!(
                    labels.iter().all(|&l| local(l)),
                    "scattered {scattered}: piece {i} of {ray:?} to {te} crosses {labels:?}"
                );
                multi += (labels.len() > 1) as usize;
            }
        }
        assert!(
            said > 2000 && multi > 500,
            "covered {said}, {multi} across nodes"
        );
    }
}
