//! Walking the octree along a ray: the leaves it crosses as half-open
//! intervals that partition it, computed in f64 by one expression so that
//! every worker and every collapsed tree agrees on each interval end bit
//! for bit.

use super::{Node, Octree};
use crate::geometry::{Bounds, Ray};
use std::mem::MaybeUninit;
use std::ops::ControlFlow;

impl Octree {
    /// Visits the leaves along `ray` within `[t0, t1)`, front to back, as
    /// half-open intervals that partition the part of `[t0, t1)` inside the
    /// root. A ray lying exactly in a splitting plane is assigned to the
    /// upper side, so every point of the ray belongs to exactly one leaf.
    pub fn walk<F>(&self, ray: &Ray, t0: f32, t1: f32, f: F) -> ControlFlow<()>
    where
        F: FnMut(u32, f32, f32) -> ControlFlow<()>,
    {
        self.walk_from(ray, t0, t1, f32::NEG_INFINITY, f)
    }

    /// The walk of [`Self::walk`] resumed at `resume`: leaves ending at or
    /// before it are skipped and the first one is clipped to start there.
    /// Every leaf is classified exactly as in the full walk from `t0`, so a
    /// worker that receives a forwarded ray continues the very processor
    /// vector its sender computed, even for rays through leaf corners.
    pub fn walk_from<F>(
        &self,
        ray: &Ray,
        t0: f32,
        t1: f32,
        resume: f32,
        mut f: F,
    ) -> ControlFlow<()>
    where
        F: FnMut(u32, f32, f32) -> ControlFlow<()>,
    {
        let w = WalkRay::new(ray);
        let Some((a, b)) = w.clip(&self.bounds, t0, t1) else {
            return ControlFlow::Continue(());
        };
        self.walk_node(0, &w, a, b, resume, &mut f)
    }

    fn walk_node<F>(
        &self,
        n: usize,
        ray: &WalkRay,
        ta: f32,
        tb: f32,
        resume: f32,
        f: &mut F,
    ) -> ControlFlow<()>
    where
        F: FnMut(u32, f32, f32) -> ControlFlow<()>,
    {
        if tb <= resume {
            return ControlFlow::Continue(());
        }
        match self.nodes[n] {
            Node::Leaf { leaf } => f(leaf, ta.max(resume), tb),
            Node::Interior { first_child } => {
                let (cuts, k, mut oct) = ray.cuts(&self.centre(n), ta, tb);
                let mut start = ta;
                for (end, axis) in cuts[..k].iter().copied().chain([(tb, 3)]) {
                    if end > start {
                        if end > resume {
                            let child = first_child as usize + oct as usize;
                            self.walk_node(child, ray, start, end, resume, f)?;
                        }
                        start = end;
                    }
                    if axis < 3 {
                        oct ^= 1 << axis;
                    }
                }
                ControlFlow::Continue(())
            }
        }
    }

    /// Interior node `n`'s centre, the planes that split it, widened to
    /// f64 (exactly) for the crossings.
    fn centre(&self, n: usize) -> [f64; 3] {
        self.node_bounds[n].center().to_array().map(f64::from)
    }

    /// Leaves along the ray as `(leaf, ta, tb)`.
    pub fn leaves_along(&self, ray: &Ray, t0: f32, t1: f32) -> Vec<(u32, f32, f32)> {
        let mut v = Vec::new();
        let _ = self.walk(ray, t0, t1, |l, a, b| {
            v.push((l, a, b));
            ControlFlow::Continue(())
        });
        v
    }
}

/// How deep a [`WalkTable`] may be and still walk on its fixed stack
/// (each interior node on the way down leaves at most three pieces for
/// later); a deeper one walks by [`Octree::walk_from`]'s recursion.
const TABLE_DEPTH: usize = 24;

/// An octree laid out for walking many rays: each interior node's centre
/// already widened to f64 beside its children's index, and the walk a
/// loop over a fixed stack rather than a recursion that saves registers
/// at every node. It visits the same leaves with the same interval ends,
/// bit for bit, as [`Octree::walk_from`]: the same expressions in the same
/// precision, on the same centres.
#[derive(Clone, Debug, PartialEq)]
pub struct WalkTable {
    tree: Octree,
    nodes: Vec<WalkNode>,
    /// Whether every leaf lies within [`TABLE_DEPTH`] of the root.
    shallow: bool,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum WalkNode {
    Interior { centre: [f64; 3], first_child: u32 },
    Leaf(u32),
}

impl WalkTable {
    pub fn new(tree: Octree) -> Self {
        let mut nodes = Vec::with_capacity(tree.nodes.len());
        let mut depth = vec![0usize; tree.nodes.len()];
        let mut deepest = 0;
        // A tree whose children came before their parent would fool the
        // depths below: it walks by recursion.
        let mut ordered = true;
        for (n, node) in tree.nodes.iter().enumerate() {
            nodes.push(match *node {
                Node::Leaf { leaf } => WalkNode::Leaf(leaf),
                Node::Interior { first_child } => {
                    // Children follow their parent in the node array, so a
                    // parent's depth is known before its children's.
                    ordered &= first_child as usize > n;
                    let below = depth[n] + 1;
                    for c in 0..8 {
                        if let Some(d) = depth.get_mut(first_child as usize + c) {
                            *d = below;
                        }
                    }
                    WalkNode::Interior {
                        centre: tree.centre(n),
                        first_child,
                    }
                }
            });
            deepest = deepest.max(depth[n]);
        }
        Self {
            tree,
            nodes,
            shallow: ordered && deepest <= TABLE_DEPTH,
        }
    }

    /// The tree walked.
    pub fn tree(&self) -> &Octree {
        &self.tree
    }

    /// [`Octree::walk_from`] over the table's tree.
    pub fn walk_from<F>(
        &self,
        ray: &Ray,
        t0: f32,
        t1: f32,
        resume: f32,
        mut f: F,
    ) -> ControlFlow<()>
    where
        F: FnMut(u32, f32, f32) -> ControlFlow<()>,
    {
        if !self.shallow {
            return self.tree.walk_from(ray, t0, t1, resume, f);
        }
        let w = WalkRay::new(ray);
        let Some((ta, tb)) = w.clip(&self.tree.bounds, t0, t1) else {
            return ControlFlow::Continue(());
        };
        if tb <= resume {
            return ControlFlow::Continue(());
        }
        // Pieces still to visit, the next one on top; every piece ends
        // beyond `resume`. Entries below `sp` are written before they are
        // read, so the stack needs no zeroing (which cost more than the
        // walk saves).
        let mut stack = [const { MaybeUninit::<(u32, f32, f32)>::uninit() }; 3 * TABLE_DEPTH + 1];
        let mut sp = 0;
        let (mut n, mut ta, mut tb) = (0usize, ta, tb);
        loop {
            match self.nodes[n] {
                WalkNode::Leaf(leaf) => {
                    f(leaf, ta.max(resume), tb)?;
                }
                WalkNode::Interior {
                    centre: m,
                    first_child,
                } => {
                    // The pieces, back to front, onto the stack: the front
                    // one is then on top.
                    let (cuts, k, mut oct) = w.cuts(&m, ta, tb);
                    for &(_, axis) in &cuts[..k] {
                        oct ^= 1 << axis;
                    }
                    let mut end = tb;
                    for i in (0..=k).rev() {
                        let start = if i > 0 { cuts[i - 1].0 } else { ta };
                        if end > start {
                            if end <= resume {
                                break;
                            }
                            stack[sp].write((first_child + oct, start, end));
                            sp += 1;
                            end = start;
                        }
                        if i > 0 {
                            oct ^= 1 << cuts[i - 1].1;
                        }
                    }
                }
            }
            if sp == 0 {
                return ControlFlow::Continue(());
            }
            sp -= 1;
            // SAFETY: every entry below the old `sp` was written above.
            let (c, a, b) = unsafe { stack[sp].assume_init() };
            (n, ta, tb) = (c as usize, a, b);
        }
    }
}

/// A ray prepared for walking: origin, direction and inverse direction in
/// f64. A plane crossing is `(m - o) * inv`; every worker and every
/// collapsed tree computes each crossing with this same expression, so
/// interval ends agree bit for bit wherever they are compared.
struct WalkRay {
    o: [f64; 3],
    d: [f64; 3],
    inv: [f64; 3],
    /// Whether the ray moves along each axis (a zero component never
    /// crosses that axis's planes).
    moves: [bool; 3],
}

impl WalkRay {
    /// Entry and exit of the ray into `b` within `[t0, t1)` (products with
    /// the inverse direction, in f64), or None when it misses.
    #[inline(always)]
    fn clip(&self, b: &Bounds, t0: f32, t1: f32) -> Option<(f32, f32)> {
        let (mut lo, mut hi) = (t0 as f64, t1 as f64);
        for a in 0..3 {
            let (bmin, bmax) = (b.min[a] as f64, b.max[a] as f64);
            if !self.moves[a] {
                if self.o[a] < bmin || self.o[a] > bmax {
                    return None;
                }
                continue;
            }
            let (x, y) = (
                (bmin - self.o[a]) * self.inv[a],
                (bmax - self.o[a]) * self.inv[a],
            );
            lo = lo.max(x.min(y));
            hi = hi.min(x.max(y));
        }
        (lo < hi).then_some((lo as f32, hi as f32))
    }

    /// The plane crossings of the node centred at `m` inside `(ta, tb)`,
    /// front to back with their axes (the unused ones hold `tb`), how many,
    /// and the octant of the first piece. Both walks (the tree's and the
    /// table's) cut nodes here, so their interval ends agree to the bit.
    /// A ray that does not move along an axis has an infinite inverse
    /// there: its crossing is infinite or NaN, never inside.
    #[inline(always)]
    fn cuts(&self, m: &[f64; 3], ta: f32, tb: f32) -> ([(f32, u32); 3], usize, u32) {
        let mut cuts = [(tb, 3u32); 3];
        let mut k = 0;
        for (a, &c) in m.iter().enumerate() {
            let t = ((c - self.o[a]) * self.inv[a]) as f32;
            if t > ta && t < tb {
                cuts[k] = (t, a as u32);
                k += 1;
            }
        }
        // A sorting network for at most three cuts (unused slots hold tb
        // and stay last).
        let swap = |c: &mut [(f32, u32); 3], i: usize, j: usize| {
            if c[j].0 < c[i].0 {
                c.swap(i, j);
            }
        };
        swap(&mut cuts, 0, 1);
        swap(&mut cuts, 1, 2);
        swap(&mut cuts, 0, 1);
        // The first piece's octant from its midpoint; each crossing then
        // moves to the other half along its axis. Pieces are found from
        // the same cuts in every tree that keeps this node, so ends agree
        // wherever they are compared.
        let first_end = if k > 0 { cuts[0].0 } else { tb };
        let tm = 0.5 * (ta as f64 + first_end as f64);
        let mut oct = 0u32;
        for (a, &c) in m.iter().enumerate() {
            let upper = self.o[a] + tm * self.d[a] >= c;
            oct |= (upper as u32) << a;
        }
        (cuts, k, oct)
    }

    #[inline(always)]
    fn new(ray: &Ray) -> Self {
        let o = [
            ray.origin.x as f64,
            ray.origin.y as f64,
            ray.origin.z as f64,
        ];
        let d = [ray.dir.x as f64, ray.dir.y as f64, ray.dir.z as f64];
        let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        Self {
            o,
            d,
            inv,
            moves: [d[0] != 0.0, d[1] != 0.0, d[2] != 0.0],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::grid_octree;
    use super::super::{Octree, OctreeParams};
    use super::WalkTable;
    use crate::geometry::Ray;
    use crate::sampler::SampleKey;
    use glam::Vec3;
    use std::ops::ControlFlow;

    /// Every leaf interval of `walk`, and whether it stopped at `stop`.
    fn intervals(
        walk: impl FnOnce(&mut dyn FnMut(u32, f32, f32) -> ControlFlow<()>) -> ControlFlow<()>,
        stop: usize,
    ) -> (Vec<(u32, u32, u32)>, bool) {
        let mut v = Vec::new();
        let flow = walk(&mut |l, a, b| {
            v.push((l, a.to_bits(), b.to_bits()));
            if v.len() == stop {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        });
        (v, flow.is_break())
    }

    /// Rays for the table tests: between random points of a box twice
    /// its root's size, along the root's middle planes (a third of them
    /// exactly on a plane, where ends tie), and through node corners.
    fn table_rays(tree: &Octree, n: u64) -> Vec<Ray> {
        let (lo, hi, c) = (tree.bounds.min, tree.bounds.max, tree.bounds.center());
        let ext = hi - lo;
        (0..n)
            .filter_map(|i| {
                let k = SampleKey::independent(i, 7, 11);
                let u = |d: u32| Vec3::new(k.get1d(d), k.get1d(d + 1), k.get1d(d + 2));
                let mut p = lo - 0.5 * ext + 2.0 * ext * u(0);
                let q = lo + ext * u(3);
                match i % 3 {
                    0 => p.x = c.x,
                    1 => p = lo + ext * (u(6) * 8.0).floor() / 8.0,
                    _ => {}
                }
                let mut d = q - p;
                if i % 5 == 0 {
                    d.x = 0.0;
                }
                Some(Ray::new(p, d.try_normalize()?))
            })
            .collect()
    }

    /// The table walks exactly the tree's walk: the same leaves, the same
    /// interval ends bit for bit, resumed anywhere, stopped anywhere.
    #[test]
    fn the_table_walks_as_the_tree_does() {
        for tree in [
            grid_octree(30, 3, 7),
            grid_octree(12, 1, 4),
            grid_octree(8, 100, 7),
        ] {
            let table = WalkTable::new(tree.clone());
            assert!(table.shallow);
            let (mut compared, mut several) = (0, 0);
            for (i, ray) in table_rays(&tree, 3000).iter().enumerate() {
                let (all, _) = intervals(|f| tree.walk(ray, 0.0, f32::INFINITY, f), 0);
                several += (all.len() > 3) as usize;
                let resumes = [f32::NEG_INFINITY, 0.0]
                    .into_iter()
                    .chain(all.iter().flat_map(|&(_, a, b)| {
                        let (a, b) = (f32::from_bits(a), f32::from_bits(b));
                        [a, b, 0.5 * (a + b)]
                    }));
                for (j, resume) in resumes.enumerate() {
                    let t1 = if j % 4 == 3 {
                        0.7 * resume.abs()
                    } else {
                        f32::INFINITY
                    };
                    let stop = (i + j) % 5;
                    let want = intervals(|f| tree.walk_from(ray, 0.0, t1, resume, f), stop);
                    let got = intervals(|f| table.walk_from(ray, 0.0, t1, resume, f), stop);
                    assert_eq!(
                        got, want,
                        "ray {i} {ray:?}, resume {resume}, t1 {t1}, stop {stop}"
                    );
                    compared += 1;
                }
            }
            // (The last tree is one leaf: the root's own clip.)
            let long_enough = several > 300 || tree.leaves.len() == 1;
            assert!(
                compared > 10_000 && long_enough,
                "{compared} walks, {several} long"
            );
        }
    }

    /// A tree deeper than the table's stack walks by the tree's recursion,
    /// to the same leaves.
    #[test]
    fn a_deep_table_falls_back_to_the_recursion() {
        // Triangles crowding one corner split it down to depth 30.
        let tris: Vec<[Vec3; 3]> = (0..64)
            .map(|i| {
                let p = Vec3::splat(1.0 + i as f32 * 1e-7);
                [p, p + Vec3::X * 1e-8, p + Vec3::Y * 1e-8]
            })
            .chain([[Vec3::ZERO, Vec3::X * 1e3, Vec3::Y * 1e3]])
            .collect();
        let tree = Octree::build(
            &tris,
            OctreeParams {
                max_leaf_tris: 1,
                max_depth: 30,
            },
        );
        let table = WalkTable::new(tree.clone());
        assert!(!table.shallow);
        for ray in table_rays(&tree, 500) {
            let want = intervals(|f| tree.walk_from(&ray, 0.0, f32::INFINITY, 1.0, f), 0);
            let got = intervals(|f| table.walk_from(&ray, 0.0, f32::INFINITY, 1.0, f), 0);
            assert_eq!(got, want);
        }
    }

    #[test]
    fn walk_partitions_the_ray() {
        let o = grid_octree(30, 8, 5);
        let c = o.bounds.center();
        // Rays along the root's splitting planes and through node corners.
        let rays = [
            Ray::new(Vec3::new(o.bounds.min.x - 1.0, c.y, c.z), Vec3::X),
            Ray::new(o.bounds.min - Vec3::ONE, Vec3::ONE.normalize()),
            Ray::new(Vec3::new(c.x, c.y, o.bounds.max.z + 1.0), -Vec3::Z),
            Ray::new(
                Vec3::new(0.1, 0.2, 0.3),
                Vec3::new(0.3, 0.5, 0.1).normalize(),
            ),
        ];
        for r in rays {
            let segs = o.leaves_along(&r, 0.0, f32::INFINITY);
            assert!(!segs.is_empty());
            let (a, b) = o.bounds.clip(&r, 0.0, f32::INFINITY).unwrap();
            assert_eq!(segs[0].1, a);
            assert_eq!(segs.last().unwrap().2, b);
            for w in segs.windows(2) {
                assert_eq!(w[0].2, w[1].1, "segments must be contiguous");
            }
            for &(l, ta, tb) in &segs {
                assert!(ta < tb);
                let m = r.at(0.5 * (ta + tb));
                let lb = o.leaves[l as usize].bounds;
                let tol = lb.extent().max_element() * 1e-4;
                assert!(m.cmpge(lb.min - tol).all() && m.cmple(lb.max + tol).all());
                // Away from faces, f32 rounding of the midpoint cannot move
                // it into a neighbour, so the point lookup must agree.
                if m.cmpgt(lb.min + tol).all() && m.cmplt(lb.max - tol).all() {
                    assert_eq!(o.leaf_at(m), Some(l));
                }
            }
        }
    }
}
