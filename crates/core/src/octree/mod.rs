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
//!
//! This module builds the tree and answers point and neighbour queries;
//! `walk` walks it along rays (and lays it out as a [`WalkTable`] for
//! walking many), `group` merges and groups its subtrees by
//! labels and weights, and `split` holds the triangle-box tests the build
//! splits by.

use crate::geometry::Bounds;
use glam::Vec3;

mod group;
mod split;
mod walk;
pub use split::tri_box_overlap;
use split::{separates, split_refs};
pub use walk::WalkTable;

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
    /// `stack` is scratch the caller keeps between calls: a route's boxes
    /// are grown by thousands of these, and a stack grown afresh each time
    /// (1, 4, 8, 16, 32 entries) cost more in reallocations than the
    /// descent itself.
    pub fn all_overlapping(
        &self,
        b: &Bounds,
        ok: &dyn Fn(u32) -> bool,
        stack: &mut Vec<usize>,
    ) -> bool {
        stack.clear();
        stack.push(0);
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

/// The distinct triangle ids (ascending) of several leaves' lists: the
/// triangles a region or a part holds, each once. Marked in a bitmap over
/// the lists' range rather than gathered and sorted: for a job of two
/// workers that both hold the room (325,000 triangles in 932 leaves),
/// sorting cost the scheduler 296 M instructions, marking 72 M.
pub fn distinct_triangles<'a>(lists: impl IntoIterator<Item = &'a [u32]>) -> Vec<u32> {
    let lists: Vec<&[u32]> = lists.into_iter().filter(|l| !l.is_empty()).collect();
    let (Some(lo), Some(hi)) = (
        lists.iter().filter_map(|l| l.iter().min()).min(),
        lists.iter().filter_map(|l| l.iter().max()).max(),
    ) else {
        return Vec::new();
    };
    let mut bits = vec![0u64; ((hi - lo) as usize >> 6) + 1];
    let mut count = 0usize;
    for &id in lists.iter().flat_map(|l| l.iter()) {
        let k = (id - lo) as usize;
        let (w, b) = (k >> 6, 1u64 << (k & 63));
        count += (bits[w] & b == 0) as usize;
        bits[w] |= b;
    }
    let mut out = Vec::with_capacity(count);
    for (w, &word) in bits.iter().enumerate() {
        let mut m = word;
        while m != 0 {
            out.push(lo + (w as u32) * 64 + m.trailing_zeros());
            m &= m - 1;
        }
    }
    out
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// The distinct ids are what gathering, sorting and deduplicating
    /// give, for lists that overlap, repeat, sit far apart or are empty.
    #[test]
    fn distinct_triangles_are_the_sorted_union() {
        use crate::sampler::SampleKey;
        for case in 0..40u64 {
            let k = SampleKey::independent(case, 0, 3);
            let lists: Vec<Vec<u32>> = (0..(k.get1d(0) * 6.0) as u32)
                .map(|l| {
                    let base = (k.get1d(1 + l) * 1e6) as u32 * (case as u32 % 3);
                    let mut v: Vec<u32> = (0..(k.get1d(10 + l) * 300.0) as u32)
                        .map(|i| base + (i * 7 + l) % 500)
                        .collect();
                    v.sort_unstable();
                    v
                })
                .collect();
            let mut want: Vec<u32> = lists.iter().flatten().copied().collect();
            want.sort_unstable();
            want.dedup();
            let got = distinct_triangles(lists.iter().map(|l| l.as_slice()));
            assert_eq!(got, want, "case {case}");
        }
    }

    /// The octree of `grid_tris(n)` with these limits.
    pub(crate) fn grid_octree(n: usize, max_leaf_tris: usize, max_depth: u32) -> Octree {
        Octree::build(
            &grid_tris(n),
            OctreeParams {
                max_leaf_tris,
                max_depth,
            },
        )
    }

    pub(crate) fn grid_tris(n: usize) -> Vec<[Vec3; 3]> {
        let mut v = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let p = Vec3::new(i as f32, j as f32, (i * j % 5) as f32);
                v.push([p, p + Vec3::X * 0.9, p + Vec3::Y * 0.9]);
            }
        }
        v
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
    fn check_structure_refuses_broken_links() {
        let o = grid_octree(10, 4, 4);
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
