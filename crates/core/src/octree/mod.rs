//! The octree the farm partitions: leaves are the unit of ownership.
//!
//! Leaves hold at most `max_leaf_tris` triangle references or stop at
//! `max_depth`. A triangle is referenced by every leaf whose (slightly
//! inflated) box it overlaps, so a point anywhere inside a leaf finds every
//! triangle through it in that leaf's list. Empty leaves are kept: rays
//! cross them and regions own them.
//!
//! [`Octree::walk`] enumerates the leaves along a ray front to back as
//! half-open parameter intervals `[ta, tb)` that exactly partition the
//! clipped ray, which is what a processor vector (paper 003, section 3.3)
//! is made of.

use crate::geometry::{Bounds, Ray};
use glam::Vec3;
use std::ops::ControlFlow;

mod split;
pub use split::tri_box_overlap;
use split::{separates, split_refs};

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct OctreeParams {
    pub max_leaf_tris: usize,
    pub max_depth: u32,
}

impl Default for OctreeParams {
    fn default() -> Self {
        Self {
            max_leaf_tris: 512,
            max_depth: 7,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Leaf {
    pub bounds: Bounds,
    pub depth: u32,
    /// Global triangle ids, ascending.
    pub tris: Vec<u32>,
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
enum Node {
    /// Index of the first of eight consecutive children; child `i` has
    /// bit 0 = upper x half, bit 1 = upper y, bit 2 = upper z.
    Interior {
        first_child: u32,
    },
    Leaf {
        leaf: u32,
    },
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Octree {
    pub bounds: Bounds,
    nodes: Vec<Node>,
    node_bounds: Vec<Bounds>,
    pub leaves: Vec<Leaf>,
    pub params: OctreeParams,
}

impl Octree {
    /// Builds over `tris`. The root is a cube around the scene bounds,
    /// enlarged by 1% so that no geometry touches the root's faces, where a
    /// clip computed in a different precision could cut it off.
    pub fn build(tris: &[[Vec3; 3]], params: OctreeParams) -> Self {
        let mut sb = Bounds::of_triangles(tris);
        if sb.is_empty() {
            sb = Bounds::new(Vec3::splat(-1.0), Vec3::splat(1.0));
        }
        let c = sb.center();
        let half = (sb.extent().max_element() * 0.5)
            .max(sb.max_abs() * 1e-6)
            .max(1e-30)
            * 1.01;
        let bounds = Bounds::new(c - Vec3::splat(half), c + Vec3::splat(half));
        let all: Vec<u32> = (0..tris.len() as u32).collect();
        let sub = Self::build_sub(bounds, all, 0, tris, params);
        Octree {
            bounds,
            nodes: sub.nodes,
            node_bounds: sub.node_bounds,
            leaves: sub.leaves,
            params,
        }
    }

    /// The subtree over `refs` in box `b`: its top levels in parallel,
    /// each child built on its own and spliced in child order, which lays
    /// out nodes and leaves exactly as the sequential build does.
    fn build_sub(
        b: Bounds,
        refs: Vec<u32>,
        depth: u32,
        tris: &[[Vec3; 3]],
        params: OctreeParams,
    ) -> Sub {
        let split = refs.len() > params.max_leaf_tris && depth < params.max_depth;
        if !split || depth >= PARALLEL_DEPTH {
            let mut t = Octree {
                bounds: b,
                nodes: vec![Node::Leaf { leaf: 0 }],
                node_bounds: vec![b],
                leaves: Vec::new(),
                params,
            };
            t.subdivide(0, b, refs, depth, tris);
            return Sub {
                nodes: t.nodes,
                node_bounds: t.node_bounds,
                leaves: t.leaves,
            };
        }
        use rayon::prelude::*;
        let subs = split_refs(&b, &refs, tris);
        if !separates(refs.len(), &subs) {
            return Sub {
                nodes: vec![Node::Leaf { leaf: 0 }],
                node_bounds: vec![b],
                leaves: vec![Leaf {
                    bounds: b,
                    depth,
                    tris: refs,
                }],
            };
        }
        let children: Vec<Sub> = subs
            .into_par_iter()
            .enumerate()
            .map(|(i, sub)| Self::build_sub(child_bounds(&b, i), sub, depth + 1, tris, params))
            .collect();
        let mut out = Sub {
            nodes: vec![Node::Interior { first_child: 1 }],
            node_bounds: vec![b],
            leaves: Vec::new(),
        };
        out.nodes.extend([Node::Leaf { leaf: u32::MAX }; 8]);
        out.node_bounds.extend((0..8).map(|i| child_bounds(&b, i)));
        for (k, c) in children.into_iter().enumerate() {
            // Child k's root goes to slot 1 + k, its descendants after
            // everything placed so far.
            let base = out.nodes.len() as u32;
            let leaf_base = out.leaves.len() as u32;
            let map = |n: Node| match n {
                Node::Interior { first_child } => Node::Interior {
                    first_child: base + first_child - 1,
                },
                Node::Leaf { leaf } => Node::Leaf {
                    leaf: leaf + leaf_base,
                },
            };
            out.nodes[1 + k] = map(c.nodes[0]);
            out.nodes.extend(c.nodes[1..].iter().map(|&n| map(n)));
            out.node_bounds.extend_from_slice(&c.node_bounds[1..]);
            out.leaves.extend(c.leaves);
        }
        out
    }

    fn subdivide(
        &mut self,
        node: usize,
        b: Bounds,
        refs: Vec<u32>,
        depth: u32,
        tris: &[[Vec3; 3]],
    ) {
        let subs = (refs.len() > self.params.max_leaf_tris && depth < self.params.max_depth)
            .then(|| split_refs(&b, &refs, tris))
            .filter(|subs| separates(refs.len(), subs));
        let Some(subs) = subs else {
            let leaf = self.leaves.len() as u32;
            self.leaves.push(Leaf {
                bounds: b,
                depth,
                tris: refs,
            });
            self.nodes[node] = Node::Leaf { leaf };
            return;
        };
        let first = self.nodes.len() as u32;
        self.nodes[node] = Node::Interior { first_child: first };
        let children: Vec<Bounds> = (0..8).map(|i| child_bounds(&b, i)).collect();
        for cb in &children {
            self.nodes.push(Node::Leaf { leaf: u32::MAX });
            self.node_bounds.push(*cb);
        }
        drop(refs);
        for (i, (cb, sub)) in children.into_iter().zip(subs).enumerate() {
            self.subdivide(first as usize + i, cb, sub, depth + 1, tris);
        }
    }

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    /// Total triangle references over all leaves (a triangle overlapping k
    /// leaves counts k times).
    pub fn reference_count(&self) -> usize {
        self.leaves.iter().map(|l| l.tris.len()).sum()
    }

    /// Whether every leaf whose box shares volume with `b` passes `ok`.
    pub fn all_overlapping(&self, b: &Bounds, ok: &dyn Fn(u32) -> bool) -> bool {
        let mut stack = vec![0usize];
        while let Some(n) = stack.pop() {
            let nb = &self.node_bounds[n];
            if (0..3).any(|a| nb.min[a] >= b.max[a] || b.min[a] >= nb.max[a]) {
                continue;
            }
            match self.nodes[n] {
                Node::Interior { first_child } => {
                    stack.extend(first_child as usize..first_child as usize + 8)
                }
                Node::Leaf { leaf } => {
                    if !ok(leaf) {
                        return false;
                    }
                }
            }
        }
        true
    }

    /// The leaf containing `p` (upper halves win ties, as in [`Self::walk`]).
    pub fn leaf_at(&self, p: Vec3) -> Option<u32> {
        if !self.bounds.contains(p) {
            return None;
        }
        let mut n = 0usize;
        loop {
            match self.nodes[n] {
                Node::Leaf { leaf } => return Some(leaf),
                Node::Interior { first_child } => {
                    let m = self.node_bounds[n].center();
                    let i = (p.x >= m.x) as usize
                        | ((p.y >= m.y) as usize) << 1
                        | ((p.z >= m.z) as usize) << 2;
                    n = first_child as usize + i;
                }
            }
        }
    }

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
                let m = self.node_bounds[n].center().to_array();
                // Plane crossings inside the interval, with their axes. A
                // ray that does not move along an axis has an infinite
                // inverse there: its crossing is infinite or NaN, never
                // inside.
                let mut cuts = [(tb, 3usize); 3];
                let mut k = 0;
                for (a, &c) in m.iter().enumerate() {
                    let t = ((c as f64 - ray.o[a]) * ray.inv[a]) as f32;
                    if t > ta && t < tb {
                        cuts[k] = (t, a);
                        k += 1;
                    }
                }
                // A sorting network for at most three cuts (unused slots
                // hold tb and stay last).
                let swap = |c: &mut [(f32, usize); 3], i: usize, j: usize| {
                    if c[j].0 < c[i].0 {
                        c.swap(i, j);
                    }
                };
                swap(&mut cuts, 0, 1);
                swap(&mut cuts, 1, 2);
                swap(&mut cuts, 0, 1);
                // The first piece's octant from its midpoint; each crossing
                // then moves to the other half along its axis. Pieces are
                // found from the same cuts in every tree that keeps this
                // node, so ends agree wherever they are compared.
                let first_end = if k > 0 { cuts[0].0 } else { tb };
                let tm = 0.5 * (ta as f64 + first_end as f64);
                let mut oct = 0usize;
                for (a, &c) in m.iter().enumerate() {
                    let upper = ray.o[a] + tm * ray.d[a] >= c as f64;
                    oct |= (upper as usize) << a;
                }
                let mut start = ta;
                for (end, axis) in cuts[..k].iter().copied().chain([(tb, 3)]) {
                    if end > start {
                        if end > resume {
                            self.walk_node(first_child as usize + oct, ray, start, end, resume, f)?;
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

    /// For each leaf, the leaves sharing part of a face with it (positive
    /// area of contact), ascending. Sibling faces are bit-identical (see
    /// `child_bounds`), so contact is decided exactly.
    pub fn face_neighbours(&self) -> Vec<Vec<u32>> {
        let mut out = vec![Vec::new(); self.leaves.len()];
        let mut stack = Vec::new();
        for (i, l) in self.leaves.iter().enumerate() {
            let b = l.bounds;
            stack.clear();
            stack.push(0usize);
            while let Some(n) = stack.pop() {
                let nb = self.node_bounds[n];
                if (0..3).any(|a| nb.min[a] > b.max[a] || nb.max[a] < b.min[a]) {
                    continue;
                }
                match self.nodes[n] {
                    Node::Interior { first_child } => {
                        stack.extend(first_child as usize..first_child as usize + 8)
                    }
                    Node::Leaf { leaf } if leaf as usize != i => {
                        let touch =
                            (0..3).filter(|&a| nb.min[a] == b.max[a] || nb.max[a] == b.min[a]);
                        let overlap =
                            (0..3).filter(|&a| nb.min[a] < b.max[a] && b.min[a] < nb.max[a]);
                        if touch.count() == 1 && overlap.count() == 2 {
                            out[i].push(leaf);
                        }
                    }
                    Node::Leaf { .. } => {}
                }
            }
            out[i].sort_unstable();
        }
        out
    }

    /// The tree without its triangle lists: the replicated top of the tree
    /// (paper 003, section 3.3) that every worker holds.
    pub fn without_triangles(&self) -> Octree {
        let mut t = Octree {
            bounds: self.bounds,
            nodes: self.nodes.clone(),
            node_bounds: self.node_bounds.clone(),
            leaves: Vec::with_capacity(self.leaves.len()),
            params: self.params,
        };
        t.leaves.extend(self.leaves.iter().map(|l| Leaf {
            bounds: l.bounds,
            depth: l.depth,
            tris: Vec::new(),
        }));
        t
    }

    /// Checks the links of a tree that arrived from elsewhere: children lie
    /// after their parent and inside the node list, every leaf is reached
    /// exactly once. A tree that passes can be walked without panicking.
    pub fn check_structure(&self) -> Result<(), String> {
        if self.nodes.is_empty() || self.node_bounds.len() != self.nodes.len() {
            return Err("node and node bound lists are empty or differ in length".into());
        }
        let mut seen = vec![false; self.leaves.len()];
        for (n, node) in self.nodes.iter().enumerate() {
            match *node {
                Node::Interior { first_child } => {
                    let f = first_child as usize;
                    if f <= n || f + 8 > self.nodes.len() {
                        return Err(format!("node {n} has children outside the tree"));
                    }
                }
                Node::Leaf { leaf } => match seen.get_mut(leaf as usize) {
                    Some(s) if !*s => *s = true,
                    _ => return Err(format!("node {n} names leaf {leaf}, missing or shared")),
                },
            }
        }
        if seen.iter().any(|s| !s) {
            return Err("a leaf is not reachable from any node".into());
        }
        Ok(())
    }

    /// The tree with every subtree whose leaves all carry one label merged
    /// into a single leaf, and the label of each merged leaf. A merged node
    /// keeps its bounds bit for bit, and the walk splits a node's interval
    /// into children whose intervals concatenate to exactly the node's, so
    /// walking the merged tree gives the same interval boundaries wherever
    /// the label changes: the processor map walks far fewer nodes this way.
    pub fn collapse<L: Copy + PartialEq>(&self, label: &[L]) -> (Octree, Vec<L>) {
        assert_eq!(label.len(), self.leaves.len(), "one label per leaf");
        let mut uniform: Vec<Option<L>> = vec![None; self.nodes.len()];
        // Children are stored after their parent, so a reverse sweep sees
        // every child before its parent.
        for n in (0..self.nodes.len()).rev() {
            uniform[n] = match self.nodes[n] {
                Node::Leaf { leaf } => Some(label[leaf as usize]),
                Node::Interior { first_child } => {
                    let f = first_child as usize;
                    let l0 = uniform[f];
                    if l0.is_some() && (f + 1..f + 8).all(|c| uniform[c] == l0) {
                        l0
                    } else {
                        None
                    }
                }
            };
        }
        let mut out = Octree {
            bounds: self.bounds,
            nodes: vec![Node::Leaf { leaf: u32::MAX }],
            node_bounds: vec![self.node_bounds[0]],
            leaves: Vec::new(),
            params: self.params,
        };
        let mut labels = Vec::new();
        let mut stack = vec![(0usize, 0usize, 0u32)];
        while let Some((src, dst, depth)) = stack.pop() {
            match (uniform[src], self.nodes[src]) {
                (Some(l), _) => {
                    out.nodes[dst] = Node::Leaf {
                        leaf: out.leaves.len() as u32,
                    };
                    out.leaves.push(Leaf {
                        bounds: self.node_bounds[src],
                        depth,
                        tris: Vec::new(),
                    });
                    labels.push(l);
                }
                (None, Node::Interior { first_child }) => {
                    let first = out.nodes.len();
                    out.nodes[dst] = Node::Interior {
                        first_child: first as u32,
                    };
                    for c in 0..8 {
                        out.nodes.push(Node::Leaf { leaf: u32::MAX });
                        out.node_bounds
                            .push(self.node_bounds[first_child as usize + c]);
                        stack.push((first_child as usize + c, first + c, depth + 1));
                    }
                }
                (None, Node::Leaf { .. }) => unreachable!("a leaf always has a label"),
            }
        }
        (out, labels)
    }

    /// Groups the leaves into whole subtrees, each as large as it can be
    /// while its leaves' `weight` sums to at most `max` (a leaf heavier
    /// than that is a group of its own). Returns each leaf's group and each
    /// group's bounds; groups are numbered in depth-first (Morton) order.
    /// A partition made of whole groups collapses to a route no deeper
    /// than the groups are.
    pub fn subtree_groups(&self, weight: &[f64], max: f64) -> (Vec<u32>, Vec<Bounds>) {
        let mut sum = vec![0.0f64; self.nodes.len()];
        // Children are stored after their parent: a reverse sweep sums
        // every subtree before its parent.
        for n in (0..self.nodes.len()).rev() {
            sum[n] = match self.nodes[n] {
                Node::Leaf { leaf } => weight.get(leaf as usize).copied().unwrap_or(0.0),
                Node::Interior { first_child } => {
                    let f = first_child as usize;
                    sum[f..f + 8].iter().sum()
                }
            };
        }
        let mut group = vec![0u32; self.leaves.len()];
        let mut bounds = Vec::new();
        let mut stack = vec![0usize];
        while let Some(n) = stack.pop() {
            match self.nodes[n] {
                Node::Interior { first_child } if sum[n] > max => {
                    // Children in reverse so that they pop in order.
                    stack.extend((first_child as usize..first_child as usize + 8).rev());
                }
                _ => {
                    let g = bounds.len() as u32;
                    bounds.push(self.node_bounds[n]);
                    let mut sub = vec![n];
                    while let Some(m) = sub.pop() {
                        match self.nodes[m] {
                            Node::Leaf { leaf } => group[leaf as usize] = g,
                            Node::Interior { first_child } => {
                                sub.extend(first_child as usize..first_child as usize + 8)
                            }
                        }
                    }
                }
            }
        }
        (group, bounds)
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

/// Levels of the octree built in parallel (8^2 tasks): enough to keep a
/// few cores busy, few enough that splicing costs nothing.
const PARALLEL_DEPTH: u32 = 2;

/// A subtree built on its own: its root is `nodes[0]`, its indices are its
/// own.
struct Sub {
    nodes: Vec<Node>,
    node_bounds: Vec<Bounds>,
    leaves: Vec<Leaf>,
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

fn child_bounds(b: &Bounds, i: usize) -> Bounds {
    // The midpoint is computed once per node so siblings share their faces
    // bit for bit.
    let m = b.center();
    let mut lo = b.min;
    let mut hi = m;
    for a in 0..3 {
        if i >> a & 1 == 1 {
            lo[a] = m[a];
            hi[a] = b.max[a];
        }
    }
    Bounds::new(lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid_tris(n: usize) -> Vec<[Vec3; 3]> {
        let mut v = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let p = Vec3::new(i as f32, j as f32, (i * j % 5) as f32);
                v.push([p, p + Vec3::X * 0.9, p + Vec3::Y * 0.9]);
            }
        }
        v
    }

    /// Subtree groups are whole subtrees (a partition by groups collapses
    /// to at most one route node per group), within their weight bound
    /// unless a single leaf, and numbered in leaf (Morton) order.
    #[test]
    fn subtree_groups_are_whole_subtrees_within_their_bound() {
        let tree = Octree::build(
            &grid_tris(40),
            OctreeParams {
                max_leaf_tris: 8,
                max_depth: 7,
            },
        );
        let n = tree.leaves.len();
        let weight: Vec<f64> = (0..n).map(|l| 1.0 + (l % 7) as f64).collect();
        let total: f64 = weight.iter().sum();
        for max in [0.0, total / 64.0, total / 8.0, total] {
            let (group, bounds) = tree.subtree_groups(&weight, max);
            let g = bounds.len();
            assert!(group.windows(2).all(|p| p[0] <= p[1]), "Morton order");
            assert_eq!(tree.collapse(&group).1.len(), g, "whole subtrees");
            let mut sum = vec![0.0; g];
            let mut count = vec![0; g];
            for (l, &k) in group.iter().enumerate() {
                sum[k as usize] += weight[l];
                count[k as usize] += 1;
                let (b, lb) = (bounds[k as usize], tree.leaves[l].bounds);
                assert!(b.contains(lb.min) && b.contains(lb.max));
            }
            for k in 0..g {
                assert!(
                    sum[k] <= max || count[k] == 1,
                    "group {k}: {} > {max}",
                    sum[k]
                );
            }
            if max >= total {
                assert_eq!(g, 1);
            }
            if max == 0.0 {
                assert_eq!(g, n);
            }
        }
    }

    /// The parallel build lays out nodes and leaves exactly as one
    /// depth-first pass does.
    #[test]
    fn parallel_build_equals_the_sequential_one() {
        let tris = grid_tris(60);
        for p in [
            OctreeParams {
                max_leaf_tris: 4,
                max_depth: 7,
            },
            OctreeParams {
                max_leaf_tris: 64,
                max_depth: 3,
            },
        ] {
            let par = Octree::build(&tris, p);
            let mut seq = Octree {
                bounds: par.bounds,
                nodes: vec![Node::Leaf { leaf: 0 }],
                node_bounds: vec![par.bounds],
                leaves: Vec::new(),
                params: p,
            };
            seq.subdivide(0, par.bounds, (0..tris.len() as u32).collect(), 0, &tris);
            assert!(par.leaves.len() > 64);
            assert_eq!(par, seq);
            par.check_structure().unwrap();
        }
    }

    #[test]
    fn leaves_respect_limits() {
        let tris = grid_tris(40);
        let p = OctreeParams {
            max_leaf_tris: 16,
            max_depth: 6,
        };
        let o = Octree::build(&tris, p);
        for l in &o.leaves {
            assert!(l.tris.len() <= 16 || l.depth == 6);
        }
        // Every triangle is referenced somewhere.
        let mut seen = vec![false; tris.len()];
        for l in &o.leaves {
            for &t in &l.tris {
                seen[t as usize] = true;
            }
        }
        assert!(seen.iter().all(|&s| s));
    }

    #[test]
    fn walk_partitions_the_ray() {
        let tris = grid_tris(30);
        let o = Octree::build(
            &tris,
            OctreeParams {
                max_leaf_tris: 8,
                max_depth: 5,
            },
        );
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

    /// Label-change points along a walk: (label before, label after, t).
    fn changes(o: &Octree, labels: &[u8], r: &Ray) -> Vec<(u8, u8, u32)> {
        let segs = o.leaves_along(r, 0.0, f32::INFINITY);
        let mut v = vec![(u8::MAX, labels[segs[0].0 as usize], segs[0].1.to_bits())];
        for w in segs.windows(2) {
            let (a, b) = (labels[w[0].0 as usize], labels[w[1].0 as usize]);
            if a != b {
                v.push((a, b, w[1].1.to_bits()));
            }
        }
        v.push((
            labels[segs.last().unwrap().0 as usize],
            u8::MAX,
            segs.last().unwrap().2.to_bits(),
        ));
        v
    }

    #[test]
    fn collapse_keeps_every_label_boundary_bit_for_bit() {
        let tris = grid_tris(30);
        let o = Octree::build(
            &tris,
            OctreeParams {
                max_leaf_tris: 4,
                max_depth: 7,
            },
        );
        // Labels by octant of the leaf centre, plus a scattered minority, so
        // both large uniform subtrees and ragged borders occur.
        let c = o.bounds.center();
        let labels: Vec<u8> = o
            .leaves
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let m = l.bounds.center();
                if i % 17 == 0 {
                    9
                } else {
                    (m.x > c.x) as u8 + 2 * (m.y > c.y) as u8
                }
            })
            .collect();
        let (small, small_labels) = o.collapse(&labels);
        small.check_structure().unwrap();
        assert!(small.leaves.len() < o.leaves.len());
        let mut rng = 0x9e3779b97f4a7c15u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 40) as f32 / (1u64 << 24) as f32
        };
        let lo = o.bounds.min - Vec3::ONE;
        let ext = o.bounds.extent() + 2.0;
        let mut tested = 0;
        for i in 0..2000 {
            let p = lo + Vec3::new(next(), next(), next()) * ext;
            // Every fourth ray runs along the root's splitting planes.
            let (p, d) = if i % 4 == 0 {
                (Vec3::new(c.x, c.y, p.z), Vec3::new(next() - 0.5, 0.0, 0.0))
            } else {
                (p, Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5))
            };
            if d.length() < 1e-3 {
                continue;
            }
            let r = Ray::new(p, d.normalize());
            if o.leaves_along(&r, 0.0, f32::INFINITY).is_empty() {
                continue;
            }
            tested += 1;
            assert_eq!(
                changes(&o, &labels, &r),
                changes(&small, &small_labels, &r),
                "ray {i}"
            );
        }
        assert!(tested > 500);
        // One label everywhere: the whole tree is one leaf.
        let (one, l) = o.collapse(&vec![3u8; o.leaves.len()]);
        assert_eq!((one.leaves.len(), l), (1, vec![3]));
    }

    #[test]
    fn check_structure_refuses_broken_links() {
        let o = Octree::build(
            &grid_tris(10),
            OctreeParams {
                max_leaf_tris: 4,
                max_depth: 4,
            },
        );
        o.check_structure().unwrap();
        let mut cyc = o.clone();
        cyc.nodes[0] = Node::Interior { first_child: 0 };
        assert!(cyc.check_structure().is_err());
        let mut out = o.clone();
        let last = out.nodes.len() - 1;
        out.nodes[last] = Node::Leaf { leaf: 1 << 30 };
        assert!(out.check_structure().is_err());
        let mut shared = o.clone();
        shared.nodes[last] = Node::Leaf { leaf: 0 };
        assert!(shared.check_structure().is_err());
    }
}
