//! Reshaping the octree by labels and weights: merging subtrees of one
//! label (the processor map walks far fewer nodes) and grouping leaves into
//! whole subtrees of bounded weight (what the partitioner grows regions
//! from).

use super::{Leaf, Node, Octree};
use crate::geometry::Bounds;

impl Octree {
    /// The tree with every subtree whose leaves all carry one label merged
    /// into a single leaf, and the label of each merged leaf. A merged node
    /// keeps its bounds bit for bit, and the walk splits a node's interval
    /// into children whose intervals concatenate to exactly the node's, so
    /// walking the merged tree gives the same interval boundaries wherever
    /// the label changes: the processor map walks far fewer nodes this way.
    pub fn collapse<L: Copy + PartialEq>(&self, label: &[L]) -> (Octree, Vec<L>) {
        assert_eq!(label.len(), self.leaves.len(), "one label per leaf");
        self.collapse_free(label, |_| false, label[0])
    }

    /// [`Self::collapse`] where the leaves `free` accepts take any label: a
    /// subtree merges when its other leaves carry one label, and takes that
    /// label; a subtree of free leaves alone takes `fill`. A farm's route
    /// once made its empty leaves free this way; it now labels them local
    /// on every worker (`locus_worker::reach`), since merged into a
    /// neighbour's node they took that neighbour's owner.
    pub fn collapse_free<L: Copy + PartialEq>(
        &self,
        label: &[L],
        free: impl Fn(usize) -> bool,
        fill: L,
    ) -> (Octree, Vec<L>) {
        assert_eq!(label.len(), self.leaves.len(), "one label per leaf");
        /// What a subtree's leaves carry.
        #[derive(Clone, Copy, PartialEq)]
        enum Uniform<L> {
            /// Free leaves only.
            Any,
            One(L),
            Mixed,
        }
        let mut uniform: Vec<Uniform<L>> = vec![Uniform::Mixed; self.nodes.len()];
        // Children are stored after their parent, so a reverse sweep sees
        // every child before its parent.
        for n in (0..self.nodes.len()).rev() {
            uniform[n] = match self.nodes[n] {
                Node::Leaf { leaf } if free(leaf as usize) => Uniform::Any,
                Node::Leaf { leaf } => Uniform::One(label[leaf as usize]),
                Node::Interior { first_child } => {
                    let f = first_child as usize;
                    uniform[f..f + 8]
                        .iter()
                        .try_fold(Uniform::Any, |acc, &u| match (acc, u) {
                            (_, Uniform::Mixed) => None,
                            (a, Uniform::Any) => Some(a),
                            (Uniform::Any, u) => Some(u),
                            (a, u) if a == u => Some(a),
                            _ => None,
                        })
                        .unwrap_or(Uniform::Mixed)
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
            let one = match uniform[src] {
                Uniform::Any => Some(fill),
                Uniform::One(l) => Some(l),
                Uniform::Mixed => None,
            };
            match (one, self.nodes[src]) {
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
}

#[cfg(test)]
mod tests {
    use super::super::tests::grid_octree;
    use super::super::*;
    use crate::geometry::Ray;
    use glam::Vec3;

    /// Subtree groups are whole subtrees (a partition by groups collapses
    /// to at most one route node per group), within their weight bound
    /// unless a single leaf, and numbered in leaf (Morton) order.
    #[test]
    fn subtree_groups_are_whole_subtrees_within_their_bound() {
        let tree = grid_octree(40, 8, 7);
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

    /// Deterministic uniform numbers in [0, 1) (xorshift64) for test rays.
    fn uniform(seed: u64) -> impl FnMut() -> f32 {
        let mut rng = seed;
        move || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 40) as f32 / (1u64 << 24) as f32
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
        let o = grid_octree(30, 4, 7);
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
        let mut next = uniform(0x9e3779b97f4a7c15);
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

    /// Free leaves take their neighbours' label: every leaf that is not
    /// free keeps its own wherever a ray crosses it, free leaves never add
    /// a route node, and free space apart from any other label is `fill`.
    #[test]
    fn free_leaves_join_their_neighbours() {
        let o = grid_octree(30, 4, 7);
        let c = o.bounds.center();
        // Halves by x, with a scattered minority that ragged borders (and
        // free leaves that are not really free) would keep apart.
        let labels: Vec<u8> = o
            .leaves
            .iter()
            .enumerate()
            .map(|(i, l)| {
                if i % 17 == 0 {
                    9
                } else {
                    (l.bounds.center().x > c.x) as u8
                }
            })
            .collect();
        // The empty leaves, and every third leaf besides.
        let free = |l: usize| o.leaves[l].tris.is_empty() || l.is_multiple_of(3);
        let (small, small_labels) = o.collapse_free(&labels, free, 7);
        small.check_structure().unwrap();
        let (plain, _) = o.collapse(&labels);
        assert!(small.leaves.len() < plain.leaves.len(), "free leaves merge");
        // Empty space above the grid, under nodes of both labels.
        assert!(small_labels.contains(&7), "free space apart takes the fill");
        let mut next = uniform(0x2545f4914f6cdd1d);
        let (lo, ext) = (o.bounds.min - Vec3::ONE, o.bounds.extent() + 2.0);
        let mut checked = 0;
        for _ in 0..2000 {
            let p = lo + Vec3::new(next(), next(), next()) * ext;
            let d = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
            if d.length() < 1e-3 {
                continue;
            }
            let r = Ray::new(p, d.normalize());
            let route = small.leaves_along(&r, 0.0, f32::INFINITY);
            for (l, ta, tb) in o.leaves_along(&r, 0.0, f32::INFINITY) {
                if free(l as usize) {
                    continue;
                }
                // Every route interval overlapping a kept leaf's carries
                // the leaf's label.
                for &(n, a, b) in &route {
                    if a < tb && b > ta {
                        assert_eq!(small_labels[n as usize], labels[l as usize]);
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 1000, "{checked}");
        // Nothing but free leaves: one node of the fill label.
        let (one, l) = o.collapse_free(&labels, |_| true, 7);
        assert_eq!((one.leaves.len(), l), (1, vec![7]));
    }
}
