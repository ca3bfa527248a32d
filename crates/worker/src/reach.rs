//! What a worker can trace in one job: its reach.
//!
//! A [`Reach`] is an immutable snapshot: the BVH parts over the worker's
//! own region and every fetched leaf merged so far ([`AccelSet`]), the
//! fetched leaves still waiting to be merged (each traced through its own
//! small BVH), and the octree collapsed over a [`Label`] per leaf: `Local`
//! for what the parts hold, `Pending` for waiting leaves, `Remote` for the
//! rest. Tracing batches hold a snapshot while the engine makes the next
//! one, so a snapshot never changes under a ray.
//!
//! Merging is how fetched geometry comes to cost what the worker's own
//! does: [`merge`] rebuilds only the parts whose run of leaves (in leaf
//! order, which is Morton order) the new leaves fall into, splitting a part
//! that grows past the part size, so no build needs more memory than the
//! worker's plan allows. A region joined into one BVH is never rebuilt
//! ([`Part::mergeable`]): fetched leaves then make parts of their own.
//! With every leaf held, the route is a single local node and a worker
//! traces exactly as one machine does.

use crate::fetch::FetchedLeaf;
use locus_core::accel::Accel;
use locus_core::accel_set::{AccelSet, Part};
use locus_core::geometry::TriangleSet;
use locus_core::octree::Octree;
use locus_core::region::{Route, WorkerId};
use std::sync::Arc;

/// How a worker sees a leaf.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Label {
    /// Its triangles are in the BVH parts.
    Local,
    /// Fetched, traced through `pending[i]`'s own BVH until merged.
    Pending(u32),
    /// Another worker's. `leaf` is `u32::MAX` when the job never fetches,
    /// so that a whole remote subtree of one owner collapses to one node.
    Remote { owner: WorkerId, leaf: u32 },
}

/// Route nodes up to which local boxes are grown.
const GROW_LIMIT: usize = 4096;

pub struct Reach {
    pub accel: AccelSet,
    pub route: Route<Label>,
    pub pending: Vec<Arc<FetchedLeaf>>,
    /// Every leaf is local: rays are traced as on one machine.
    pub all_local: bool,
}

impl Reach {
    /// The snapshot for parts `accel` holding the leaves marked in `local`,
    /// and `pending` fetched leaves. With `per_leaf` remote leaves keep
    /// their identity (a fetch policy asks for them by leaf). A leaf with
    /// no triangles (`leaf_tris`) is local on every worker, so a ray
    /// crosses empty space without a forward, and no empty leaf is
    /// fetched.
    pub fn new(
        tree: &Octree,
        owner: &[WorkerId],
        leaf_tris: &[u32],
        local: &[bool],
        accel: AccelSet,
        pending: Vec<Arc<FetchedLeaf>>,
        per_leaf: bool,
    ) -> Self {
        let mut label: Vec<Label> = owner
            .iter()
            .enumerate()
            .map(|(l, &o)| {
                if local[l] {
                    Label::Local
                } else {
                    Label::Remote {
                        owner: o,
                        leaf: if per_leaf { l as u32 } else { u32::MAX },
                    }
                }
            })
            .collect();
        for (i, p) in pending.iter().enumerate() {
            label[p.leaf as usize] = Label::Pending(i as u32);
        }
        let free = |l: usize| leaf_tris.get(l) == Some(&0);
        let all_local = label
            .iter()
            .enumerate()
            .all(|(l, &x)| x == Label::Local || free(l));
        // An empty leaf is local everywhere, never a peer's: merged into a
        // neighbour's route node, as it once was, the empty space beside
        // another worker's detail was that worker's, and a ray bouncing
        // off a shared wall through it was forwarded there without
        // meeting a triangle of its (on the room with 2 workers, a third
        // of the forwards and four in five of the camera rays').
        for (l, x) in label.iter_mut().enumerate() {
            if free(l) && !matches!(x, Label::Pending(_)) {
                *x = Label::Local;
            }
        }
        let mut route = Route::new(tree, &label);
        // Grown boxes spare most walks; they are worth their cost on a
        // route that will be traced many times (not one that changes with
        // every fetched leaf) and not too large to grow quickly.
        if pending.is_empty() && !all_local && route.leaves() <= GROW_LIMIT {
            route.grow_local_boxes(|l| l == Label::Local);
        }
        Self {
            accel,
            route,
            pending,
            all_local,
        }
    }
}

/// Where a leaf's triangles are found while parts are rebuilt.
pub struct LeafSource<'a> {
    pub leaf: u32,
    /// The leaf's triangle ids.
    pub ids: &'a [u32],
    /// A BVH holding them.
    pub accel: &'a Accel,
}

/// One part over `run`, its triangles gathered from their sources and
/// each kept once.
fn build_run(run: &[LeafSource], magnitude: f32) -> Arc<Part> {
    let n: usize = run.iter().map(|s| s.ids.len()).sum();
    type Tri = (u32, [glam::Vec3; 3], u32, [glam::Vec3; 3]);
    let mut tris: Vec<Tri> = Vec::with_capacity(n);
    for s in run {
        for &id in s.ids {
            if let Some(p) = s.accel.find(id) {
                let (v, m) = s.accel.triangle(p);
                tris.push((id, v, m, s.accel.shading(p)));
            }
        }
    }
    tris.sort_unstable_by_key(|t| t.0);
    tris.dedup_by_key(|t| t.0);
    let mut set = TriangleSet::with_capacity(tris.len());
    for (id, v, m, sn) in tris {
        set.push(id, v, m, sn);
    }
    let leaves = run.iter().map(|s| s.leaf).collect();
    Arc::new(Part::new(Accel::from_set(set, magnitude), leaves))
}

/// The part a fetched `leaf` joins in a merge: of the parts a merge may
/// build again ([`Part::mergeable`], whose leaf runs ascend and do not
/// overlap), the one whose run it falls in, else the one before it, else
/// the first; None where no part may be built again (a region joined into
/// one BVH), and the leaf starts a part of fetched leaves.
pub fn merge_target(parts: &[Arc<Part>], leaf: u32) -> Option<usize> {
    parts
        .iter()
        .rposition(|p| p.mergeable && p.leaves.first().is_some_and(|&first| first <= leaf))
        .or_else(|| parts.iter().position(|p| p.mergeable))
}

/// Merges `new` leaves (ascending, none of them in `parts`) into `parts`:
/// a new leaf joins its [`merge_target`]. Parts that get no new leaf are
/// kept as they are; the others are rebuilt, cut into runs of at most
/// `max_part` triangles, and leaves without a target make parts of their
/// own after the rest. `ids(leaf)` gives any involved leaf's triangle ids;
/// a new leaf's triangles come from its own BVH. Returns the new parts and
/// the triangles built.
pub fn merge(
    parts: &[Arc<Part>],
    new: &[Arc<FetchedLeaf>],
    ids: &dyn Fn(u32) -> Option<Arc<[u32]>>,
    max_part: usize,
    magnitude: f32,
) -> (Vec<Arc<Part>>, usize) {
    // Which part each new leaf joins; those without one (a worker without
    // a region, or whose region is joined) make parts of their own.
    let mut joins: Vec<Vec<&FetchedLeaf>> = vec![Vec::new(); parts.len()];
    let mut alone: Vec<&FetchedLeaf> = Vec::new();
    for f in new {
        match merge_target(parts, f.leaf) {
            Some(k) => joins[k].push(f),
            None => alone.push(f),
        }
    }
    let mut out = Vec::with_capacity(parts.len());
    let mut built = 0;
    for (p, add) in parts.iter().zip(joins) {
        if add.is_empty() {
            out.push(p.clone());
            continue;
        }
        let old: Vec<(u32, Arc<[u32]>)> = p
            .leaves
            .iter()
            .filter_map(|&l| Some((l, ids(l)?)))
            .collect();
        let mut run: Vec<LeafSource> = old
            .iter()
            .map(|(l, i)| LeafSource {
                leaf: *l,
                ids: i,
                accel: &p.accel,
            })
            .chain(add.iter().map(|f| f.source()))
            .collect();
        run.sort_by_key(|s| s.leaf);
        let (mut parts, n) = cut_run(&run, max_part, magnitude);
        built += n;
        out.append(&mut parts);
    }
    if !alone.is_empty() {
        let run: Vec<LeafSource> = alone.iter().map(|f| f.source()).collect();
        let (mut parts, n) = cut_run(&run, max_part, magnitude);
        built += n;
        out.append(&mut parts);
    }
    (out, built)
}

/// Builds `run` (ascending leaves) as parts of at most `max_part`
/// triangles each (counting repeats, the safe side for memory); returns
/// them and the triangles built.
pub fn cut_run(run: &[LeafSource], max_part: usize, magnitude: f32) -> (Vec<Arc<Part>>, usize) {
    let mut out = Vec::new();
    let mut built = 0;
    let mut start = 0;
    let mut count = 0;
    for (i, s) in run.iter().enumerate() {
        if i > start && count + s.ids.len() > max_part.max(1) {
            let p = build_run(&run[start..i], magnitude);
            built += p.accel.len();
            out.push(p);
            start = i;
            count = 0;
        }
        count += s.ids.len();
    }
    if start < run.len() {
        let p = build_run(&run[start..], magnitude);
        built += p.accel.len();
        out.push(p);
    }
    (out, built)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use locus_core::accel::BuildQuality;
    use locus_core::octree::OctreeParams;
    use locus_core::sampler::SampleKey;
    use locus_core::stats::TraceStats;

    /// Merging fetched leaves into parts in any grouping gives the hits of
    /// one BVH over the same leaves, keeps untouched parts and respects the
    /// part size; over a region joined into one BVH, the joined part is
    /// kept as it is and the fetched leaves make parts of their own.
    #[test]
    fn merged_parts_answer_as_one_bvh() {
        merge_rounds(false);
        merge_rounds(true);
    }

    fn merge_rounds(joined: bool) {
        let tris: Vec<[Vec3; 3]> = (0..4000u64)
            .map(|i| {
                let k = SampleKey::independent(i, 0, 3);
                let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 10.0;
                [
                    p,
                    p + Vec3::new(k.get1d(3), 0.0, 0.4),
                    p + Vec3::new(0.0, k.get1d(4), 0.3),
                ]
            })
            .collect();
        let oct = Octree::build(
            &tris,
            OctreeParams {
                max_leaf_tris: 24,
                max_depth: 6,
            },
        );
        let n = oct.leaves.len() as u32;
        let leaf_ids = |l: u32| -> Option<Arc<[u32]>> {
            Some(Arc::from(oct.leaves.get(l as usize)?.tris.as_slice()))
        };
        let fetched = |l: u32| {
            let ids = &oct.leaves[l as usize].tris;
            let set = TriangleSet {
                ids: ids.clone(),
                verts: ids.iter().map(|&i| tris[i as usize]).collect(),
                material: vec![0; ids.len()],
                normals: Vec::new(),
            };
            Arc::new(FetchedLeaf::build(l, set, 12.0))
        };
        // Own: every third leaf, as parts of 150 triangles.
        let own: Vec<(u32, &[u32])> = (0..n)
            .filter(|l| l % 3 == 0)
            .map(|l| (l, oct.leaves[l as usize].tris.as_slice()))
            .collect();
        let tri = |id: u32| (tris[id as usize], 0, locus_core::geometry::FLAT);
        let mut parts =
            locus_core::accel_set::build_parts(&own, 150, 12.0, BuildQuality::Full, &tri);
        if joined {
            parts = locus_core::accel_set::join(parts);
            assert_eq!(parts.len(), 1);
            assert!(!parts[0].mergeable);
        }
        let region = parts[0].clone();
        let first = parts.len();
        // Fetch the rest in two rounds.
        for round in [1u32, 2] {
            let new: Vec<Arc<FetchedLeaf>> =
                (0..n).filter(|l| l % 3 == round).map(fetched).collect();
            let before = parts.clone();
            let (p, built) = merge(&parts, &new, &leaf_ids, 150, 12.0);
            assert!(built > 0);
            // Parts no new leaf fell into are the same objects.
            let kept = p
                .iter()
                .filter(|x| before.iter().any(|b| Arc::ptr_eq(b, x)))
                .count();
            assert!(p.len() >= first && kept < p.len());
            if joined {
                // The joined region is kept, and no other part holds one
                // of its leaves.
                assert!(Arc::ptr_eq(&p[0], &region));
                assert!(
                    p[1..]
                        .iter()
                        .all(|x| x.mergeable && x.leaves.iter().all(|&l| l % 3 != 0))
                );
            }
            parts = p;
            for x in parts.iter().filter(|x| x.mergeable) {
                let own_ids: usize = x
                    .leaves
                    .iter()
                    .map(|&l| oct.leaves[l as usize].tris.len())
                    .sum();
                assert!(
                    x.leaves.len() == 1 || own_ids <= 150,
                    "a part of {own_ids} references"
                );
                assert!(x.leaves.is_sorted());
            }
        }
        let all: Vec<u32> = (0..tris.len() as u32).collect();
        let one = Accel::build(&tris, &all, 12.0);
        let set = AccelSet::from_parts(parts);
        let mut st = TraceStats::default();
        let mut hits = 0;
        for i in 0..3000u64 {
            let k = SampleKey::independent(i, 1, 4);
            let o = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 10.0;
            let d = (Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) - 0.5).normalize();
            let r = locus_core::geometry::Ray::new(o, d);
            let a = one.intersect(&r, 0.0, f32::INFINITY, &mut st);
            let b = set
                .closest(&r, 0.0, f32::INFINITY, &mut st)
                .map(|h| h.hit.hit);
            assert_eq!(a, b, "ray {i}");
            hits += a.is_some() as usize;
        }
        assert!(hits > 1000);
    }

    /// A floor of 200 triangles, 20 by 10, in the plane y = 0.
    fn floor() -> Vec<[Vec3; 3]> {
        (0..200)
            .map(|i| {
                let p = Vec3::new((i % 20) as f32, 0.0, (i / 20) as f32);
                [p, p + Vec3::X * 0.9, p + Vec3::Z * 0.9]
            })
            .collect()
    }

    /// The octree of the reach tests over `tris`, and its leaves' triangle
    /// counts.
    fn octree_of(tris: &[[Vec3; 3]]) -> (Octree, Vec<u32>) {
        let oct = Octree::build(
            tris,
            OctreeParams {
                max_leaf_tris: 8,
                max_depth: 6,
            },
        );
        let leaf_tris = oct.leaves.iter().map(|l| l.tris.len() as u32).collect();
        (oct, leaf_tris)
    }

    /// BVH parts over the `local` leaves' triangles.
    fn local_parts(
        oct: &Octree,
        tris: &[[Vec3; 3]],
        local: &[bool],
    ) -> Vec<Arc<locus_core::accel_set::Part>> {
        let own: Vec<(u32, &[u32])> = (0..oct.leaves.len())
            .filter(|&l| local[l])
            .map(|l| (l as u32, oct.leaves[l].tris.as_slice()))
            .collect();
        let tri = |id: u32| (tris[id as usize], 0, locus_core::geometry::FLAT);
        locus_core::accel_set::build_parts(&own, 1000, 20.0, BuildQuality::Full, &tri)
    }

    /// Empty space is anyone's: a worker that holds every leaf with
    /// triangles traces as one machine does, whoever owns the empty ones,
    /// and is never sent to fetch them.
    #[test]
    fn empty_leaves_of_others_are_local() {
        let tris = floor();
        let (oct, leaf_tris) = octree_of(&tris);
        assert!(
            leaf_tris.contains(&0),
            "the floor leaves empty space above it"
        );
        let owner: Vec<WorkerId> = leaf_tris.iter().map(|&n| u16::from(n == 0)).collect();
        let local: Vec<bool> = owner.iter().map(|&o| o == 0).collect();
        let parts = local_parts(&oct, &tris, &local);
        for per_leaf in [false, true] {
            let r = Reach::new(
                &oct,
                &owner,
                &leaf_tris,
                &local,
                AccelSet::from_parts(parts.clone()),
                Vec::new(),
                per_leaf,
            );
            assert!(r.all_local && r.route.leaves() == 1, "per leaf: {per_leaf}");
            // Counted as holding triangles, the same leaves are remote.
            let r = Reach::new(
                &oct,
                &owner,
                &vec![1; leaf_tris.len()],
                &local,
                AccelSet::from_parts(parts.clone()),
                Vec::new(),
                per_leaf,
            );
            assert!(!r.all_local && r.route.leaves() > 1, "per leaf: {per_leaf}");
        }
    }

    /// Empty space beside another worker's triangles is local too: a ray
    /// through any empty leaf meets only local labels there, where the
    /// route once merged such a leaf into the neighbouring owner's node
    /// and forwarded rays that crossed it.
    #[test]
    fn empty_space_beside_a_peers_triangles_is_not_the_peers() {
        // A floor, its far half another worker's, and the air above it.
        let tris: Vec<[Vec3; 3]> = floor()
            .into_iter()
            .chain(std::iter::once([
                Vec3::new(0.0, 8.0, 0.0),
                Vec3::new(0.5, 8.0, 0.0),
                Vec3::new(0.0, 8.0, 0.5),
            ]))
            .collect();
        let (oct, leaf_tris) = octree_of(&tris);
        let far = |l: usize| oct.leaves[l].bounds.center().x > 10.0;
        // Empty leaves go with the side they stand over, as a partition
        // may hand them out.
        let owner: Vec<WorkerId> = (0..oct.leaves.len()).map(|l| u16::from(far(l))).collect();
        let local: Vec<bool> = owner.iter().map(|&o| o == 0).collect();
        let parts = local_parts(&oct, &tris, &local);
        let r = Reach::new(
            &oct,
            &owner,
            &leaf_tris,
            &local,
            AccelSet::from_parts(parts),
            Vec::new(),
            false,
        );
        assert!(!r.all_local, "the far half of the floor is the peer's");
        let mut empty_far = 0;
        for l in (0..oct.leaves.len()).filter(|&l| leaf_tris[l] == 0) {
            let b = oct.leaves[l].bounds;
            empty_far += usize::from(far(l));
            // Along x through the leaf's centre, from its face to its face.
            let c = b.center();
            let ray = locus_core::geometry::Ray::new(Vec3::new(b.min.x, c.y, c.z), Vec3::X);
            let len = b.max.x - b.min.x;
            let _ = r.route.walk(&ray, 0.0, len, 0.0, |label, ta, tb| {
                if tb > 0.01 * len && ta < 0.99 * len {
                    assert_eq!(label, Label::Local, "empty leaf {l} on [{ta}, {tb}]");
                }
                std::ops::ControlFlow::Continue(())
            });
        }
        assert!(
            empty_far > 0,
            "the test needs empty leaves over the peer's half"
        );
    }
}
