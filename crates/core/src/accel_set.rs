//! Several BVHs traced as one: the triangles a worker can trace, built in
//! parts so that no build needs more memory than its budget allows.
//!
//! An obvhs build holds about [`BUILD_BYTES_PER_TRIANGLE`] bytes per
//! triangle at its peak, five times what the finished BVH keeps; a worker
//! holding a million triangles under a budget of a few hundred megabytes
//! cannot build them at once. [`build_parts`] cuts a list of octree leaves,
//! in leaf order (the octree's depth-first order, which is Morton order),
//! into runs of at most `max_part` triangles and builds one BVH per run:
//! each part is a compact piece of space, so a ray enters few of them.
//!
//! A query visits the parts the ray's segment crosses in order of entry
//! and stops at the first part that starts beyond the closest hit so far;
//! ties go to the smaller global id across parts as within one, so the
//! answer is the one a single BVH over the union would give.

use crate::accel::{Accel, AccelHit, BUILD_BYTES_PER_TRIANGLE, BuildQuality, Surface, closer};
use crate::geometry::{Bounds, Ray, TriangleSet};
use crate::stats::TraceStats;
use glam::Vec3;
use std::sync::Arc;

/// One BVH of a set, and the octree leaves whose triangles it holds.
#[derive(Clone)]
pub struct Part {
    pub accel: Accel,
    /// Octree leaves (ascending) this part was built from; empty when it
    /// was not built from leaves.
    pub leaves: Vec<u32>,
    /// Whether a fetching worker may build this part again with fetched
    /// leaves added (from its leaves' triangles): not once it is a
    /// region's parts joined ([`join`]), which would build the whole
    /// region again, and whose parts were cut by centroid, where a part
    /// does not hold whole leaves.
    pub mergeable: bool,
    /// The BVH's bounds, grown slightly so that the f32 slab test below is
    /// conservative.
    bounds: Bounds,
}

impl Part {
    pub fn new(accel: Accel, leaves: Vec<u32>) -> Self {
        let b = accel.bounds();
        let bounds = if b.is_empty() {
            b
        } else {
            let g = b.extent().max_element() * 1e-5 + b.max_abs() * 1e-6;
            Bounds::new(b.min - Vec3::splat(g), b.max + Vec3::splat(g))
        };
        Self {
            accel,
            leaves,
            mergeable: true,
            bounds,
        }
    }

    /// This part, never to be built again with fetched leaves added
    /// ([`Part::mergeable`]).
    fn fixed(mut self) -> Self {
        self.mergeable = false;
        self
    }

    /// Entry and exit of the ray's segment `[t0, t1)` into the part's
    /// bounds, or None when it misses them.
    #[inline(always)]
    fn span(&self, o: Vec3, inv: Vec3, t0: f32, t1: f32) -> Option<f32> {
        let a = (self.bounds.min - o) * inv;
        let b = (self.bounds.max - o) * inv;
        let lo = a.min(b).max_element().max(t0);
        let hi = a.max(b).min_element().min(t1);
        // NaN (0 * inf on a face) compares false and keeps the part.
        if lo > hi { None } else { Some(lo) }
    }
}

/// A hit in one part of a set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SetHit {
    pub hit: AccelHit,
    pub part: u32,
}

/// `parts` joined into one BVH ([`Accel::join`]) over all their leaves:
/// one query a ray where a set of them makes one for every part the ray
/// enters, with the same answers. A part that another holder shares (the
/// embedded farm's workers share identical builds) is copied, every other
/// one moved. The parts come back as they were when the joined tree would
/// be too deep to walk. Either way, two or more parts that come through
/// here are never built again by a merge ([`Part::mergeable`]).
pub fn join(parts: Vec<Arc<Part>>) -> Vec<Arc<Part>> {
    if parts.len() < 2 {
        return parts;
    }
    let (accels, leaves): (Vec<Accel>, Vec<Vec<u32>>) = parts
        .into_iter()
        .map(|p| {
            let part = Arc::unwrap_or_clone(p);
            (part.accel, part.leaves)
        })
        .unzip();
    match Accel::join(accels) {
        Ok(one) => {
            let mut all: Vec<u32> = leaves.into_iter().flatten().collect();
            all.sort_unstable();
            all.dedup();
            vec![Arc::new(Part::new(one, all).fixed())]
        }
        Err(accels) => accels
            .into_iter()
            .zip(leaves)
            .map(|(a, l)| Arc::new(Part::new(a, l).fixed()))
            .collect(),
    }
}

/// The most parts a set may have: a query keeps their entries on the stack.
pub const MAX_PARTS: usize = 256;

/// Several BVHs queried as one.
#[derive(Clone, Default)]
pub struct AccelSet {
    parts: Vec<Arc<Part>>,
}

fn inverse(d: Vec3) -> Vec3 {
    let inv = |x: f32| {
        if x.abs() < 1e-30 {
            1e30f32.copysign(x)
        } else {
            1.0 / x
        }
    };
    Vec3::new(inv(d.x), inv(d.y), inv(d.z))
}

impl AccelSet {
    pub fn single(accel: Accel) -> Self {
        Self {
            parts: vec![Arc::new(Part::new(accel, Vec::new()))],
        }
    }

    /// A set of at most [`MAX_PARTS`] parts.
    pub fn from_parts(parts: Vec<Arc<Part>>) -> Self {
        assert!(parts.len() <= MAX_PARTS, "at most {MAX_PARTS} parts");
        Self { parts }
    }

    pub fn parts(&self) -> &[Arc<Part>] {
        &self.parts
    }

    /// The parts joined into one BVH ([`join`]).
    pub fn joined(self) -> AccelSet {
        Self {
            parts: join(self.parts),
        }
    }

    /// Triangles over all parts (a triangle in two parts counts twice).
    pub fn len(&self) -> usize {
        self.parts.iter().map(|p| p.accel.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Heap bytes of every part.
    pub fn bytes(&self) -> usize {
        self.parts
            .iter()
            .map(|p| p.accel.bytes() + p.leaves.len() * 4)
            .sum()
    }

    /// Closest hit with `t0 <= t < t1` over every part; ties in t go to the
    /// smaller global id.
    #[inline]
    pub fn closest(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> Option<SetHit> {
        if let [p] = self.parts.as_slice() {
            return p
                .accel
                .closest(ray, t0, t1, stats)
                .map(|hit| SetHit { hit, part: 0 });
        }
        let inv = inverse(ray.dir);
        let mut entries = [(0f32, 0u16); MAX_PARTS];
        let mut n = 0;
        for (i, p) in self.parts.iter().enumerate() {
            if let Some(e) = p.span(ray.origin, inv, t0, t1) {
                // Insertion sort by entry: sets have few parts.
                let mut k = n;
                while k > 0 && entries[k - 1].0 > e {
                    entries[k] = entries[k - 1];
                    k -= 1;
                }
                entries[k] = (e, i as u16);
                n += 1;
            }
        }
        let mut best: Option<SetHit> = None;
        for &(entry, i) in &entries[..n] {
            // A part entered beyond the best hit cannot hold a closer one;
            // one entered exactly there may hold an equal-t smaller id.
            let hi = match best {
                Some(b) if entry > b.hit.hit.t => break,
                Some(b) => next_up(b.hit.hit.t).min(t1),
                None => t1,
            };
            let h = self.parts[i as usize].accel.closest(ray, t0, hi, stats);
            let h = h.map(|hit| SetHit {
                hit,
                part: i as u32,
            });
            best = match (best, h) {
                (Some(b), Some(h)) => {
                    if closer(Some(b.hit), Some(h.hit)) == Some(h.hit) {
                        Some(h)
                    } else {
                        Some(b)
                    }
                }
                (b, None) => b,
                (None, h) => h,
            };
        }
        best
    }

    /// Whether anything in any part blocks `[t0, t1)`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> bool {
        if let [p] = self.parts.as_slice() {
            return p.accel.occluded(ray, t0, t1, stats);
        }
        let inv = inverse(ray.dir);
        self.parts.iter().any(|p| {
            p.span(ray.origin, inv, t0, t1).is_some() && p.accel.occluded(ray, t0, t1, stats)
        })
    }

    #[inline(always)]
    pub fn surface(&self, h: &SetHit) -> Surface {
        self.parts[h.part as usize].accel.surface(&h.hit)
    }

    /// Vertices, material and shading normals of global triangle `id`, if
    /// a part holds it.
    pub fn find(&self, id: u32) -> Option<([Vec3; 3], u32, [Vec3; 3])> {
        self.parts.iter().find_map(|p| {
            let prim = p.accel.find(id)?;
            let (v, m) = p.accel.triangle(prim);
            Some((v, m, p.accel.shading(prim)))
        })
    }
}

/// The next f32 above a finite `t`, so that a query's exclusive end admits
/// hits at exactly `t`.
#[inline(always)]
pub fn next_up(t: f32) -> f32 {
    if t.is_nan() || t == f32::INFINITY {
        t
    } else if t == 0.0 {
        f32::from_bits(1)
    } else if t > 0.0 {
        f32::from_bits(t.to_bits() + 1)
    } else {
        f32::from_bits(t.to_bits() - 1)
    }
}

/// Triangles per part that a build may hold at once within `budget`
/// bytes, at least `floor` (a budget too small for even that is refused
/// by the scheduler before any build).
pub fn part_size_for(budget: u64, floor: usize) -> usize {
    ((budget / BUILD_BYTES_PER_TRIANGLE as u64) as usize).max(floor)
}

/// Build memory [`build_parts`] spends on parts built at once, at most
/// (and one part's, whatever its size): the scheduler's full preview, in
/// parts of 512k triangles, still builds one at a time, as before parts
/// were built at once; its decision preview's parts of 32k build 29 at once.
pub const PARALLEL_BUILD_BYTES: usize = 256 << 20;

/// Cuts `leaves` (ascending leaf ids, each with its triangle ids) into runs
/// of at most `max_part` distinct triangles and builds one part per run.
/// `triangle(id)` gives a triangle's vertices, material and shading normals;
/// a leaf larger than `max_part` is a part of its own. The parts are built
/// on the calling rayon pool, as many at once as fit
/// [`PARALLEL_BUILD_BYTES`]: each build is mostly serial (obvhs's
/// conversion to the wide BVH is), so several parts build in about their
/// share of the time where the pool has threads to spare. A worker with a
/// memory budget builds its parts one by one elsewhere.
pub fn build_parts(
    leaves: &[(u32, &[u32])],
    max_part: usize,
    magnitude: f32,
    quality: BuildQuality,
    triangle: &(dyn Fn(u32) -> ([Vec3; 3], u32, [Vec3; 3]) + Sync),
) -> Vec<Arc<Part>> {
    use rayon::prelude::*;
    let mut runs: Vec<(usize, usize)> = Vec::new();
    let (mut start, mut count) = (0, 0usize);
    for (i, (_, tris)) in leaves.iter().enumerate() {
        // Counting with duplicates overestimates a run, which is the safe
        // side for memory.
        if i > start && count + tris.len() > max_part.max(1) {
            runs.push((start, i));
            (start, count) = (i, 0);
        }
        count += tris.len();
    }
    if start < leaves.len() {
        runs.push((start, leaves.len()));
    }
    let at_once =
        (PARALLEL_BUILD_BYTES / max_part.max(1).saturating_mul(BUILD_BYTES_PER_TRIANGLE)).max(1);
    let build = |&(a, b): &(usize, usize)| {
        let run = &leaves[a..b];
        let ids = crate::octree::distinct_triangles(run.iter().map(|(_, t)| *t));
        let mut set = TriangleSet::with_capacity(ids.len());
        for &id in &ids {
            let (v, m, n) = triangle(id);
            set.push(id, v, m, n);
        }
        drop(ids);
        let accel = Accel::from_set_with(set, magnitude, quality);
        Arc::new(Part::new(accel, run.iter().map(|&(l, _)| l).collect()))
    };
    let mut parts = Vec::with_capacity(runs.len());
    for chunk in runs.chunks(at_once) {
        parts.par_extend(chunk.par_iter().map(build));
    }
    parts
}

/// Cuts `ids` (distinct triangle ids) into `ceil(len / max_part)` groups
/// of about equal size for parts that will be joined ([`join`]): each cut
/// splits a set at the centroid (`centroid(id)`) that leaves each side its
/// share of the groups, across the longest axis of the set's centroids,
/// depth first. Groups come out ascending within and neighbours in space
/// next to each other, so the join's top nodes, eight consecutive parts
/// each, are the first three levels of this cut, and each part's box is
/// tight around its own triangles.
///
/// Runs of octree leaves in Morton order ([`build_parts`]) make parts
/// whose boxes a leaf's overhanging triangles widen into their
/// neighbours', and that share the triangles of the leaves they both
/// touch: on the room's 324,928 triangles in 18 parts, joined, a ray
/// visited 11.2 nodes and made 2.85 triangle tests against one BVH's
/// 5.9 and 2.28; cut here, 7.4 and 2.31 (`examples/trace_parts.rs`).
/// Leaf runs stay where a region is not joined: a worker without a memory
/// budget builds its region whole, and merges fetched leaves into the part
/// whose run they fall in.
pub fn cut_by_centroids(
    mut ids: Vec<u32>,
    centroid: &dyn Fn(u32) -> Vec3,
    max_part: usize,
) -> Vec<Vec<u32>> {
    let groups = ids.len().div_ceil(max_part.max(1)).max(1);
    let mut out = Vec::with_capacity(groups);
    cut_into(&mut ids, groups, centroid, &mut out);
    out
}

fn cut_into(
    ids: &mut [u32],
    groups: usize,
    centroid: &dyn Fn(u32) -> Vec3,
    out: &mut Vec<Vec<u32>>,
) {
    if groups <= 1 || ids.len() <= 1 {
        let mut g = ids.to_vec();
        g.sort_unstable();
        out.push(g);
        return;
    }
    let (lo, hi) = ids.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), &i| {
            let c = centroid(i);
            (lo.min(c), hi.max(c))
        },
    );
    let axis = (hi - lo).max_position();
    let left = groups / 2;
    let at = ids.len() * left / groups;
    // Ties on the axis go by id, so the cut is the same on every machine.
    ids.select_nth_unstable_by(at, |&a, &b| {
        centroid(a)[axis]
            .total_cmp(&centroid(b)[axis])
            .then(a.cmp(&b))
    });
    let (l, r) = ids.split_at_mut(at);
    cut_into(l, left, centroid, out);
    cut_into(r, groups - left, centroid, out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::{Octree, OctreeParams};
    use crate::sampler::SampleKey;

    /// Small leaves over `tris`, so that runs of them make many parts.
    fn octree(tris: &[[Vec3; 3]]) -> Octree {
        Octree::build(
            tris,
            OctreeParams {
                max_leaf_tris: 16,
                max_depth: 6,
            },
        )
    }

    /// Every leaf of `oct` with its triangle ids, in leaf order.
    fn leaf_list(oct: &Octree) -> Vec<(u32, &[u32])> {
        oct.leaves
            .iter()
            .enumerate()
            .map(|(i, l)| (i as u32, l.tris.as_slice()))
            .collect()
    }

    fn soup() -> Vec<[Vec3; 3]> {
        let mut v = Vec::new();
        for i in 0..3000u64 {
            let k = SampleKey::independent(i, 0, 5);
            let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 10.0;
            let a = Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) - 0.5;
            let b = Vec3::new(k.get1d(6), k.get1d(7), k.get1d(8)) - 0.5;
            v.push([p, p + a, p + b]);
        }
        v
    }

    /// A centroid cut makes `ceil(n / max)` groups of at most `max`
    /// triangles, every id once, ascending within a group; the groups
    /// built and joined answer as one BVH over all, duplicates' ties
    /// included; and each group's box is tighter than the leaf runs'.
    #[test]
    fn centroid_cut_parts_join_into_one_bvh() {
        let mut tris = soup();
        for i in 0..200 {
            tris.push(tris[i * 7]);
        }
        let all: Vec<u32> = (0..tris.len() as u32).collect();
        let one = Accel::build(&tris, &all, 12.0);
        let centroid = |id: u32| {
            let t = tris[id as usize];
            (t[0] + t[1] + t[2]) / 3.0
        };
        let tri = |id: u32| (tris[id as usize], 0, crate::geometry::FLAT);
        let mut st = TraceStats::default();
        for max in [1usize, 7, 40, 300, 3199, 3200, 1 << 20] {
            let groups = cut_by_centroids(all.clone(), &centroid, max);
            assert_eq!(groups.len(), all.len().div_ceil(max), "max {max}");
            assert!(
                groups
                    .iter()
                    .all(|g| !g.is_empty() && g.len() <= max && g.is_sorted())
            );
            let mut seen: Vec<u32> = groups.iter().flatten().copied().collect();
            seen.sort_unstable();
            assert_eq!(seen, all, "max {max}");
            if max == 1 {
                continue;
            }
            let parts: Vec<Arc<Part>> = groups
                .iter()
                .flat_map(|g| build_parts(&[(0, g)], g.len(), 12.0, BuildQuality::Full, &tri))
                .collect();
            assert_eq!(parts.len(), groups.len());
            let joined = AccelSet::from_parts(join(parts));
            assert_eq!(joined.parts().len(), 1);
            for i in 0..2000u64 {
                let k = SampleKey::independent(i, 2, 9);
                let o = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 12.0 - 1.0;
                let d = (Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) - 0.5).normalize();
                let r = Ray::new(o, d);
                let a = one.intersect(&r, 0.0, f32::INFINITY, &mut st);
                let b = joined
                    .closest(&r, 0.0, f32::INFINITY, &mut st)
                    .map(|h| h.hit.hit);
                assert_eq!(a, b, "max {max}, ray {i}");
            }
        }
        // The cut's boxes overlap less than leaf runs of the same size.
        let oct = octree(&tris);
        let leaves = leaf_list(&oct);
        let volume = |parts: &[Arc<Part>]| -> f32 {
            parts
                .iter()
                .map(|p| p.accel.bounds().extent().element_product())
                .sum()
        };
        let runs = build_parts(&leaves, 300, 12.0, BuildQuality::Full, &tri);
        let cut: Vec<Arc<Part>> = cut_by_centroids(all.clone(), &centroid, 300)
            .iter()
            .flat_map(|g| build_parts(&[(0, g)], g.len(), 12.0, BuildQuality::Full, &tri))
            .collect();
        assert!(
            cut.len() <= runs.len(),
            "{} against {}",
            cut.len(),
            runs.len()
        );
        assert!(
            volume(&cut) < volume(&runs),
            "{} against {}",
            volume(&cut),
            volume(&runs)
        );
    }

    /// Parts of every size give exactly the hits and occlusion of one BVH
    /// over the union, including equal-distance ties between parts.
    #[test]
    fn parts_answer_as_one_bvh() {
        let mut tris = soup();
        // Exact duplicates in different places of the leaf order: equal-t
        // hits that must resolve to the smaller id.
        for i in 0..200 {
            tris.push(tris[i * 7]);
        }
        let oct = octree(&tris);
        let all: Vec<u32> = (0..tris.len() as u32).collect();
        let one = Accel::build(&tris, &all, 12.0);
        let leaves = leaf_list(&oct);
        let tri = |id: u32| (tris[id as usize], 0, crate::geometry::FLAT);
        let mut st = TraceStats::default();
        let sizes = [40usize, 300, 1000, 1 << 20].map(|m| (m, BuildQuality::Full));
        for (max_part, quality) in sizes.into_iter().chain([(300, BuildQuality::Quick)]) {
            let set = AccelSet::from_parts(build_parts(&leaves, max_part, 12.0, quality, &tri));
            // The same parts joined into one BVH answer the same.
            let joined = set.clone().joined();
            assert_eq!(joined.parts().len(), 1);
            assert_eq!(joined.parts()[0].accel.len(), one.len());
            assert_eq!(
                joined.parts()[0].leaves,
                (0..leaves.len() as u32).collect::<Vec<_>>()
            );
            for id in 0..tris.len() as u32 {
                let p = joined.parts()[0].accel.find(id).expect("every triangle");
                assert_eq!(joined.parts()[0].accel.triangle(p).0, tris[id as usize]);
            }
            assert!(max_part < 1 << 20 || set.parts().len() == 1);
            assert!(max_part > 40 || set.parts().len() > 50);
            // Built several at once, the parts still come in leaf order,
            // every leaf once.
            let order: Vec<u32> = set.parts().iter().flat_map(|p| p.leaves.clone()).collect();
            assert_eq!(order, (0..leaves.len() as u32).collect::<Vec<_>>());
            let mut hits = 0;
            for i in 0..3000u64 {
                let k = SampleKey::independent(i, 1, 9);
                let o = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 12.0 - 1.0;
                let d = (Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) - 0.5).normalize();
                let r = Ray::new(o, d);
                let t1 = if i % 4 == 0 { 3.0 } else { f32::INFINITY };
                let a = one.intersect(&r, 0.0, t1, &mut st);
                let b = set.closest(&r, 0.0, t1, &mut st).map(|h| h.hit.hit);
                assert_eq!(a, b, "part size {max_part}, {quality:?}, ray {i}");
                let c = joined.closest(&r, 0.0, t1, &mut st).map(|h| h.hit.hit);
                assert_eq!(a, c, "joined, part size {max_part}, {quality:?}, ray {i}");
                let occluded = one.occluded(&r, 0.0, t1, &mut st);
                assert_eq!(occluded, set.occluded(&r, 0.0, t1, &mut st));
                assert_eq!(occluded, joined.occluded(&r, 0.0, t1, &mut st));
                hits += a.is_some() as usize;
            }
            assert!(hits > 500, "only {hits} hits");
        }
    }

    #[test]
    fn next_up_is_the_next_float() {
        assert_eq!(next_up(1.0), 1.0 + f32::EPSILON);
        assert!(next_up(0.0) > 0.0);
        assert!(next_up(-1.0) > -1.0 && next_up(-1.0) < -0.9999);
        assert_eq!(next_up(f32::INFINITY), f32::INFINITY);
    }
}
