//! The foreign hull: a few boxes whose union holds every route node that
//! a worker cannot trace, so that one test of a ray piece against all of
//! them, eight lanes at a time, says that the piece crosses local leaves
//! only, where the route's walk would descend the octree node by node.
//! The eight lanes are one AVX2 instruction each where the processor has
//! AVX2 and two SSE ones where it does not: the same operations lane by
//! lane, so the answer is the same bit for bit on every worker.
//!
//! The test may say "not clear" for a piece that is clear (the boxes are
//! merged, and swallow some local space): the caller then walks, which is
//! exact. It never says "clear" for a piece that crosses a foreign leaf:
//! the boxes are inflated by far more than the test's rounding can move
//! a face (see [`Hull::new`]), so the answer is the walk's whatever the
//! precision, and images stay the same to the bit.

use crate::geometry::{Bounds, Ray};
use glam::{Vec3, Vec4};

/// Boxes in a hull at most: two groups of eight lanes.
const HULL_BOXES: usize = 16;

/// The largest share of the local space a hull may swallow.
const MAX_SWALLOWED: f64 = 0.25;

/// Boxes tested together: one AVX2 register of lanes.
const LANES: usize = 8;

/// Eight boxes' faces, per axis, lower then upper, lane by lane.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
struct Group {
    lo: [[f32; LANES]; 3],
    hi: [[f32; LANES]; 3],
}

/// At most [`HULL_BOXES`] inflated boxes covering the foreign route nodes.
#[derive(Clone, Debug, PartialEq)]
pub struct Hull {
    /// The boxes, eight to a group (the last group's unused lanes repeat
    /// its first box, which changes no answer). The largest boxes come
    /// first: a piece that crosses the hull most often meets one of them,
    /// and the test stops at the first group it meets.
    groups: Vec<Group>,
    /// Whether this processor tests a group in one AVX2 pass.
    avx2: bool,
    /// Rays starting in here are near enough to the boxes for the margin
    /// to cover the test's rounding.
    near: Bounds,
    /// Whether no box swallowed local space in merging: then a piece that
    /// is not clear crosses a foreign node (up to the margin).
    exact: bool,
}

fn union(a: &Bounds, b: &Bounds) -> Bounds {
    Bounds::new(a.min.min(b.min), a.max.max(b.max))
}

/// Merges `boxes` down to at most `k`, each step the pair whose union adds
/// the least volume beyond theirs (local space the hull then swallows).
/// The boxes come in the route's leaf order, depth first, which is a
/// Morton order: long lists are first halved by merging neighbours in it,
/// so the greedy steps see at most 128.
fn merge(mut boxes: Vec<Bounds>, k: usize) -> (Vec<Bounds>, bool) {
    while boxes.len() > 128 {
        boxes = boxes
            .chunks(2)
            .map(|c| c.iter().skip(1).fold(c[0], |u, b| union(&u, b)))
            .collect();
    }
    let mut exact = true;
    while boxes.len() > 1 {
        let mut best = (f64::INFINITY, 0, 1);
        for i in 0..boxes.len() {
            for j in i + 1..boxes.len() {
                let u = union(&boxes[i], &boxes[j]);
                let added = u.volume() - boxes[i].volume() - boxes[j].volume();
                if added < best.0 {
                    best = (added, i, j);
                }
            }
        }
        let (added, i, j) = best;
        let u = union(&boxes[i], &boxes[j]);
        // Boxes that share a face merge at no cost (their union is
        // theirs), however few there are; others only down to `k`.
        let free = added <= 1e-6 * u.volume();
        if !free && boxes.len() <= k {
            break;
        }
        exact &= free;
        boxes[i] = u;
        boxes.swap_remove(j);
    }
    (boxes, exact)
}

impl Hull {
    /// The hull of `foreign` (route nodes a worker cannot trace, in the
    /// route's leaf order) inside the octree's `root`; None when there are
    /// none, or when the boxes
    /// it merges them into swallow more than [`MAX_SWALLOWED`] of the
    /// local space.
    pub fn new(foreign: Vec<Bounds>, root: &Bounds) -> Option<Self> {
        if foreign.is_empty() {
            return None;
        }
        let halved = foreign.len() > 128;
        let foreign_volume: f64 = foreign.iter().map(Bounds::volume).sum();
        let ext = root.extent().max_element();
        // The test's faces move by at most 3 ulps of a face's distance to
        // the origin (one subtraction, one product, the reciprocal), below
        // 6 * 2^-24 * 3 `ext` for origins in `near`; a stored leaf face
        // may lie an ulp or two of the coordinates' magnitude from the
        // plane the walk computes. The margin is several times both.
        let margin = 1e-5 * ext + 1e-6 * root.max_abs();
        let (mut boxes, exact) = merge(foreign, HULL_BOXES);
        // A hull that swallows much of the local space says "not clear"
        // to most pieces, and costs every one of them its test: none is
        // kept then. (Merged boxes may overlap, which only overstates what
        // they swallow.)
        let swallowed = boxes.iter().map(Bounds::volume).sum::<f64>() - foreign_volume;
        if swallowed > MAX_SWALLOWED * (root.volume() - foreign_volume) {
            return None;
        }
        boxes.sort_by(|a, b| b.volume().total_cmp(&a.volume()));
        let groups = boxes
            .chunks(LANES)
            .map(|group| {
                let lane = |i: usize| group.get(i).unwrap_or(&group[0]);
                let face = |f: fn(&Bounds) -> Vec3, d: f32| -> [[f32; LANES]; 3] {
                    std::array::from_fn(|a| std::array::from_fn(|i| f(lane(i))[a] + d))
                };
                Group {
                    lo: face(|b| b.min, -margin),
                    hi: face(|b| b.max, margin),
                }
            })
            .collect();
        let near = Bounds::new(root.min - root.extent(), root.max + root.extent());
        Some(Self {
            groups,
            // Where the BVH's node test runs eight wide (AVX2 found at run
            // time, `LOCUS_NODE_TEST=narrow` not set).
            avx2: crate::accel::wide_available(),
            near,
            exact: exact && !halved,
        })
    }

    /// Whether every box is one foreign node's (inflated), none merged.
    pub fn exact(&self) -> bool {
        self.exact
    }

    /// Whether the piece `[ts, te]` of `ray` misses every box: then it
    /// crosses local route nodes only. False whenever the test cannot
    /// vouch for its rounding: an origin far outside the octree, or a
    /// direction component whose reciprocal is infinite (zero or
    /// subnormal), where a face through the origin would make a NaN.
    #[inline]
    pub fn clear(&self, ray: &Ray, ts: f32, te: f32) -> bool {
        let Some((o, inv)) = self.slab_ray(ray) else {
            return false;
        };
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only where the processor has AVX2.
            return unsafe { clear_avx2(&self.groups, o, inv, ts, te) };
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = self.avx2;
        clear_lanes(&self.groups, o, inv, ts, te)
    }

    /// [`Hull::clear`] on four lanes at a time, whatever the processor
    /// (for tests: it must agree with the path a processor takes).
    #[cfg(test)]
    fn clear_four_lanes(&self, ray: &Ray, ts: f32, te: f32) -> Option<bool> {
        let (o, inv) = self.slab_ray(ray)?;
        Some(clear_lanes(&self.groups, o, inv, ts, te))
    }

    /// The ray's origin and inverse direction for the slab test, or None
    /// where the test cannot vouch for its rounding (see [`Hull::clear`]).
    #[inline(always)]
    fn slab_ray(&self, ray: &Ray) -> Option<([f32; 3], [f32; 3])> {
        let inv = ray.dir.recip();
        (self.near.contains(ray.origin) && inv.is_finite())
            .then(|| (ray.origin.to_array(), inv.to_array()))
    }
}

/// The slab test of `[ts, te]` against every group, four lanes at a time.
#[inline]
fn clear_lanes(groups: &[Group], o: [f32; 3], inv: [f32; 3], ts: f32, te: f32) -> bool {
    let (o, inv) = (o.map(Vec4::splat), inv.map(Vec4::splat));
    let (ts, te) = (Vec4::splat(ts), Vec4::splat(te));
    for g in groups {
        for half in [0, 4] {
            let lanes = |f: &[f32; LANES]| Vec4::from_slice(&f[half..half + 4]);
            let (mut near, mut far) = (ts, te);
            for a in 0..3 {
                let t1 = (lanes(&g.lo[a]) - o[a]) * inv[a];
                let t2 = (lanes(&g.hi[a]) - o[a]) * inv[a];
                near = near.max(t1.min(t2));
                far = far.min(t1.max(t2));
            }
            if near.cmple(far).any() {
                return false;
            }
        }
    }
    true
}

/// [`clear_lanes`] eight lanes at a time: the same operations in the same
/// order on each lane (`min`, `max` and the comparison are the SSE ones
/// widened), so the same answer.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn clear_avx2(groups: &[Group], o: [f32; 3], inv: [f32; 3], ts: f32, te: f32) -> bool {
    use std::arch::x86_64::*;
    let (o, inv) = (o.map(|v| _mm256_set1_ps(v)), inv.map(|v| _mm256_set1_ps(v)));
    let (ts, te) = (_mm256_set1_ps(ts), _mm256_set1_ps(te));
    for g in groups {
        let (mut near, mut far) = (ts, te);
        for a in 0..3 {
            // SAFETY: `Group` is aligned to 32 bytes and each row is 8 f32s.
            let (lo, hi) = unsafe {
                (
                    _mm256_load_ps(g.lo[a].as_ptr()),
                    _mm256_load_ps(g.hi[a].as_ptr()),
                )
            };
            let t1 = _mm256_mul_ps(_mm256_sub_ps(lo, o[a]), inv[a]);
            let t2 = _mm256_mul_ps(_mm256_sub_ps(hi, o[a]), inv[a]);
            near = _mm256_max_ps(near, _mm256_min_ps(t1, t2));
            far = _mm256_min_ps(far, _mm256_max_ps(t1, t2));
        }
        if _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OS>(near, far)) != 0 {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::super::Route;
    use super::super::tests::random_piece;
    use crate::octree::tests::grid_octree;
    use crate::sampler::SampleKey;
    use std::ops::ControlFlow;

    /// Whenever the hull says a piece is clear, the route's walk finds
    /// only local nodes on it, up to and with the node holding its end
    /// (where a hit would lie), over owners that need no merging, owners
    /// whose hull swallows local space, and pieces that end exactly where
    /// a foreign node starts or start where a forwarded ray resumes; and
    /// it says so for most pieces that are clear.
    #[test]
    fn clear_pieces_cross_local_leaves_only() {
        let tree = grid_octree(24, 6, 6);
        let n = tree.leaves.len();
        let (lo, hi) = (tree.bounds.min, tree.bounds.max);
        // Owners: one slab foreign (an exact hull); two slabs and a few
        // scattered leaves (merged with some local space); a fifth of the
        // leaves scattered (a hull swallowing nearly all, not kept).
        for case in 0..3 {
            let owner: Vec<u16> = (0..n)
                .map(|l| {
                    let c = (tree.leaves[l].bounds.center() - lo) / (hi - lo);
                    let r = SampleKey::independent(l as u64, 0, 5).get1d(0);
                    let foreign = match case {
                        0 => c.x > 0.6,
                        1 => c.x > 0.6 || c.y < 0.2 || r < 0.01,
                        _ => r < 0.2,
                    };
                    foreign as u16
                })
                .collect();
            let mut route = Route::new(&tree, &owner);
            route.grow_local_boxes(|o| o == 0);
            let Some(hull) = route.hull.clone() else {
                assert_eq!(case, 2, "case {case}: no hull");
                continue;
            };
            assert!(case < 2, "a hull of scattered leaves was kept");
            assert_eq!(hull.exact(), case == 0, "case {case}");
            let (mut clear_said, mut clear_true, mut ends_on_border) = (0, 0, 0);
            let mut agreed = 0;
            for i in 0..20_000u64 {
                let Some((ray, length)) = random_piece(&tree, i) else {
                    continue;
                };
                let along = route.table.tree().leaves_along(&ray, 0.0, f32::INFINITY);
                let (mut ts, mut te) = (0.0, length);
                // A forwarded ray resumes where a foreign node ends; a
                // piece may end where one starts.
                let borders: Vec<(u16, f32, f32)> = along
                    .iter()
                    .map(|&(l, a, b)| (route.labels[l as usize], a, b))
                    .collect();
                if i % 4 == 1
                    && let Some(&(_, _, b)) = borders.iter().find(|x| x.0 != 0)
                {
                    ts = b;
                    te = te.max(b + 0.5);
                }
                if i % 4 == 2
                    && let Some(&(_, a, _)) = borders.iter().find(|x| x.0 != 0 && x.1 > 0.0)
                {
                    te = a;
                    ends_on_border += 1;
                }
                let mut labels = Vec::new();
                let _ = route.walk(&ray, 0.0, f32::INFINITY, ts, |l, a, _| {
                    if a > te {
                        return ControlFlow::Break(());
                    }
                    labels.push(l);
                    ControlFlow::Continue(())
                });
                let truly = labels.iter().all(|&l| l == 0);
                // A piece starting on a foreign node's face is inside its
                // margin: measured apart.
                let inner = i % 4 != 1;
                clear_true += (truly && inner) as usize;
                let said = hull.clear(&ray, ts, te);
                if let Some(four) = hull.clear_four_lanes(&ray, ts, te) {
                    assert_eq!(said, four, "case {case}: piece {i}: lanes disagree");
                    agreed += 1;
                }
                if said {
                    clear_said += inner as usize;
                    assert!(
                        truly,
                        "case {case}: piece {i} of {ray:?} on [{ts}, {te}] crosses {labels:?}"
                    );
                }
            }
            assert!(agreed > 10_000, "case {case}: {agreed} pieces compared");
            assert!(
                ends_on_border > 1000,
                "case {case}: {ends_on_border} pieces ending on a border"
            );
            // Exact hulls miss clear pieces only within their margin (the
            // pieces that end or start on a border are not counted).
            let share = clear_said as f64 / clear_true as f64;
            let want = if case == 0 { 0.95 } else { 0.2 };
            assert!(
                clear_true > 1000 && share > want,
                "case {case}: clear {clear_said} of {clear_true}"
            );
        }
    }
}
