//! The binary BVH that obvhs's PLOC builder makes, collapsed into its
//! compressed eight-wide BVH: obvhs's `bvh2_to_cwbvh` (Ylitie, Karras
//! and Laine's dynamic programme over the binary tree), node for node and
//! byte for byte, but in memory order.
//!
//! PLOC numbers the binary nodes bottom-up, so a node's children lie far
//! from it in memory (on the room, 99.5% more than a thousand nodes
//! away), and obvhs's conversion, which recurses from the root through
//! the nodes and through a table of seven decisions a node (56 bytes, 36
//! MB for the room's 650,000 nodes), missed the cache at nearly every
//! step: 80-90 ms of the room's 175-190 ms build, on one thread. Here the
//! tree is first copied in depth-first order (one pass that reads the
//! binary nodes where they lie), so that a node's left child is the next
//! entry and its subtree a contiguous range; the costs are then filled
//! from the last entry back to the first, every child before its parent,
//! and the wide nodes emitted by the same recursion as obvhs's, on the
//! copy. The costs are decided on the rayon pool the collapse runs in,
//! the two subtrees of a large entry at once (each entry depends on its
//! own subtree only, and a subtree is a contiguous range of the copy).
//! The arithmetic, its order and every tie are obvhs's, so the result is
//! the same BVH on any number of threads (a test compares the two over
//! many trees, shared out and not):
//! which BVH is built changes no hit, but the preview's BVH steps, and so
//! the regions drawn from them, would move with it.

use glam::Vec3;
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;
use obvhs::cwbvh::CwBvh;

mod emit;
use emit::Emit;
pub(super) use emit::{frame, internal_meta, quantise, slots};

/// obvhs's SAH weight of a primitive against a node.
const PRIM_COST: f32 = 0.3;
/// A slot's decision: a leaf of primitives, an internal wide node, or
/// its children's slots shared between its two binary children.
#[derive(Clone, Copy, PartialEq, Eq, Default)]
enum Kind {
    Leaf,
    Internal,
    #[default]
    Distribute,
}

/// One of a binary node's seven decisions: the cost of its subtree as at
/// most `i + 1` wide children, and how it gets them.
#[derive(Clone, Copy, Default)]
struct Decision {
    cost: f32,
    kind: Kind,
    left: u8,
    right: u8,
}

const NONE: u8 = u8::MAX;

/// A binary node in depth-first order: its box, and the entry of its right
/// child (its left child is the next entry), or `u32::MAX` for a leaf.
/// 28 bytes where obvhs's binary node takes 48: the copy is written once
/// and read back twice, and its first writes each fault a page in.
struct Node {
    min: Vec3,
    max: Vec3,
    right: u32,
}

impl Node {
    fn new(b: &Aabb, right: u32) -> Self {
        Self {
            min: b.min.into(),
            max: b.max.into(),
            right,
        }
    }

    fn aabb(&self) -> Aabb {
        Aabb::new(self.min.into(), self.max.into())
    }
}

/// The binary tree in depth-first order.
struct Tree {
    nodes: Vec<Node>,
    /// Per entry: a leaf's primitive, or `u32::MAX`.
    prims: Vec<u32>,
    /// Per entry: the primitives below it (1 for a leaf).
    count: Vec<u32>,
}

impl Tree {
    fn from_bvh2(bvh2: &Bvh2) -> Self {
        let n = bvh2.nodes.len();
        let mut t = Tree {
            nodes: Vec::with_capacity(n),
            prims: Vec::with_capacity(n),
            count: Vec::new(),
        };
        // (binary node, the entry of its parent whose right child it is)
        let mut stack: Vec<(u32, u32)> = vec![(0, u32::MAX)];
        while let Some((b, parent)) = stack.pop() {
            let at = t.nodes.len() as u32;
            if parent != u32::MAX {
                t.nodes[parent as usize].right = at;
            }
            let node = &bvh2.nodes[b as usize];
            if node.is_leaf() {
                assert!(
                    node.prim_count == 1,
                    "the BVH8 conversion expects one primitive a binary leaf"
                );
                t.nodes.push(Node::new(node.aabb(), u32::MAX));
                t.prims
                    .push(bvh2.primitive_indices[node.first_index as usize]);
            } else {
                t.nodes.push(Node::new(node.aabb(), 0));
                t.prims.push(u32::MAX);
                // Left first: pushed last.
                stack.push((node.first_index + 1, at));
                stack.push((node.first_index, u32::MAX));
            }
        }
        t.count = vec![0; n];
        for i in (0..t.nodes.len()).rev() {
            t.count[i] = match t.nodes[i].right {
                u32::MAX => 1,
                r => t.count[i + 1] + t.count[r as usize],
            };
        }
        t
    }

    fn is_leaf(&self, i: usize) -> bool {
        self.nodes[i].right == u32::MAX
    }

    /// The entries of `i`'s subtree: `i` up to the next entry that is not
    /// below it.
    fn end(&self, i: usize) -> usize {
        // A full binary tree of c leaves has 2c - 1 nodes.
        i + 2 * self.count[i] as usize - 1
    }
}

/// Every entry's seven decisions: their costs, which parents read, apart
/// from how each is taken, which only the emission reads (a byte each,
/// where obvhs keeps eight bytes a decision: 35 bytes a node for 56).
struct Decisions {
    cost: Vec<[f32; 7]>,
    how: Vec<[u8; 7]>,
}

impl Decisions {
    /// Decision `s` of entry `i`.
    fn get(&self, i: usize, s: usize) -> Decision {
        let h = self.how[i][s];
        Decision {
            cost: self.cost[i][s],
            kind: match h & 3 {
                0 => Kind::Leaf,
                1 => Kind::Internal,
                _ => Kind::Distribute,
            },
            left: (h >> 2) & 7,
            right: h >> 5,
        }
    }

    fn kind(&self, i: usize, s: usize) -> Kind {
        self.get(i, s).kind
    }
}

/// A decision's kind and its children's slots in a byte. A slot is 0 to
/// 6, and is only read where a smaller sum was found.
fn pack(d: &Decision) -> u8 {
    let kind = match d.kind {
        Kind::Leaf => 0,
        Kind::Internal => 1,
        Kind::Distribute => 2,
    };
    kind | (d.left.min(7) << 2) | (d.right.min(7) << 5)
}

/// Every entry's seven decisions, children before parents (obvhs's
/// `calculate_cost`): each depends on its own subtree only, so the two
/// subtrees of a large one are decided at once ([`SHARE_BELOW`]).
fn decide(t: &Tree, max_prims_per_leaf: u32, share_below: usize) -> Decisions {
    let n = t.nodes.len();
    let mut d = Decisions {
        cost: vec![[0.0; 7]; n],
        how: vec![[0; 7]; n],
    };
    decide_subtree(
        t,
        max_prims_per_leaf,
        share_below,
        0,
        &mut d.cost,
        &mut d.how,
    );
    d
}

/// The decisions of the subtree of entry `root`, whose entries are
/// `root..root + cost.len()` (`cost` and `how` hold just those).
fn decide_subtree(
    t: &Tree,
    max_prims_per_leaf: u32,
    share_below: usize,
    root: usize,
    cost: &mut [[f32; 7]],
    how: &mut [[u8; 7]],
) {
    let right = t.nodes[root].right;
    if right == u32::MAX || cost.len() < share_below {
        // Children before parents: the subtree's entries from its last.
        for i in (0..cost.len()).rev() {
            let e = root + i;
            let r = t.nodes[e].right;
            let children = (r != u32::MAX).then(|| (cost[i + 1], cost[r as usize - root]));
            (cost[i], how[i]) = decide_entry(t, e, children, max_prims_per_leaf);
        }
        return;
    }
    let left_len = right as usize - root - 1;
    let (own_cost, below_cost) = cost.split_at_mut(1);
    let (own_how, below_how) = how.split_at_mut(1);
    let (lc, rc) = below_cost.split_at_mut(left_len);
    let (lh, rh) = below_how.split_at_mut(left_len);
    rayon::join(
        || decide_subtree(t, max_prims_per_leaf, share_below, root + 1, lc, lh),
        || decide_subtree(t, max_prims_per_leaf, share_below, right as usize, rc, rh),
    );
    (own_cost[0], own_how[0]) = decide_entry(t, root, Some((lc[0], rc[0])), max_prims_per_leaf);
}

/// Entry `i`'s seven costs and how each is taken, from its children's
/// costs (None for a leaf).
#[inline(always)]
fn decide_entry(
    t: &Tree,
    i: usize,
    children: Option<([f32; 7], [f32; 7])>,
    max_prims_per_leaf: u32,
) -> ([f32; 7], [u8; 7]) {
    let half_area = t.nodes[i].aabb().half_area();
    let Some((l, r)) = children else {
        let leaf = Decision {
            cost: half_area * 1.0 * PRIM_COST,
            kind: Kind::Leaf,
            left: 0,
            right: 0,
        };
        return ([leaf.cost; 7], [pack(&leaf); 7]);
    };
    let out = decisions_of(&l, &r, t.count[i], max_prims_per_leaf, half_area);
    // A loop, inlined: as two `map`s in a function of its own, the room's
    // collapse ran 43 M more instructions.
    let (mut cost, mut how) = ([0.0; 7], [0; 7]);
    for (k, o) in out.iter().enumerate() {
        cost[k] = o.cost;
        how[k] = pack(o);
    }
    (cost, how)
}

/// An internal node's seven decisions from its children's costs `l` and
/// `r`, its `prims` primitives and its box's half area.
fn decisions_of(
    l: &[f32; 7],
    r: &[f32; 7],
    prims: u32,
    max_prims_per_leaf: u32,
    half_area: f32,
) -> [Decision; 7] {
    let mut out = [Decision::default(); 7];
    // The slot of one child (i = 1 in the paper).
    let cost_leaf = if prims <= max_prims_per_leaf {
        (prims as f32) * half_area * PRIM_COST
    } else {
        f32::INFINITY
    };
    let (mut best, mut bl, mut br) = (f32::INFINITY, NONE, NONE);
    for k in 0..7 {
        let c = l[k] + r[6 - k];
        if c < best {
            (best, bl, br) = (c, k as u8, 6 - k as u8);
        }
    }
    let cost_internal = best + half_area;
    let (cost, kind) = if cost_leaf < cost_internal {
        (cost_leaf, Kind::Leaf)
    } else {
        (cost_internal, Kind::Internal)
    };
    out[0] = Decision {
        cost,
        kind,
        left: bl,
        right: br,
    };
    // Up to s + 1 children (i = 2..7 in the paper): the cheapest way to
    // share them between the two children, if cheaper than one fewer.
    for s in 1..7 {
        let (mut best, mut bl, mut br) = (out[s - 1].cost, NONE, NONE);
        for k in 0..s {
            let c = l[k] + r[s - k - 1];
            if c < best {
                (best, bl, br) = (c, k as u8, (s - k - 1) as u8);
            }
        }
        out[s] = if bl != NONE {
            Decision {
                cost: best,
                kind: Kind::Distribute,
                left: bl,
                right: br,
            }
        } else {
            out[s - 1]
        };
    }
    out
}

/// A subtree of at least this many entries has its two halves decided at
/// once on the rayon pool the collapse runs in; below it a task costs
/// more to hand out than it saves.
const SHARE_BELOW: usize = 1 << 15;

/// `bvh2` as a compressed wide BVH whose leaves hold at most
/// `max_prims_per_leaf` (1 to 3) primitives: obvhs's
/// `bvh2_to_cwbvh(bvh2, max_prims_per_leaf, true, false)`.
pub fn bvh2_to_cwbvh(bvh2: &Bvh2, max_prims_per_leaf: u32) -> CwBvh {
    bvh2_to_cwbvh_sharing(bvh2, max_prims_per_leaf, SHARE_BELOW)
}

fn bvh2_to_cwbvh_sharing(bvh2: &Bvh2, max_prims_per_leaf: u32, share_below: usize) -> CwBvh {
    if bvh2.nodes.is_empty() {
        return CwBvh::default();
    }
    let t = Tree::from_bvh2(bvh2);
    let d = decide(&t, max_prims_per_leaf.clamp(1, 3), share_below);
    let mut e = Emit::new(&t, &d, bvh2.primitive_indices.len());
    e.node(0, 0);
    CwBvh {
        nodes: e.nodes,
        primitive_indices: e.primitive_indices,
        total_aabb: *bvh2.nodes[0].aabb(),
        exact_node_aabbs: None,
        uses_spatial_splits: bvh2.uses_spatial_splits,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Vec3A, vec3a};
    use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
    use obvhs::cwbvh::node::CwBvhNode;
    use obvhs::ploc::{PlocBuilder, PlocSearchDistance, SortPrecision};

    /// Boxes of `n` triangles of mixed sizes from a fixed-seed generator,
    /// some clustered, some long and thin, some repeated exactly.
    fn boxes(n: usize, seed: u64) -> Vec<Aabb> {
        let mut s = seed;
        let mut next = move || {
            s = crate::sampler::mix64(s.wrapping_add(0x9e37_79b9_7f4a_7c15));
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        (0..n)
            .map(|i| {
                let c = if i % 7 == 0 {
                    vec3a(0.5, 0.5, 0.5) + vec3a(next(), next(), next()) * 0.01
                } else {
                    vec3a(next(), next(), next()) * 100.0
                };
                let size = match i % 5 {
                    0 => vec3a(next() * 40.0, 0.01, 0.01),
                    1 => Vec3A::ZERO,
                    _ => vec3a(next(), next(), next()),
                };
                if i % 11 == 3 && i > 0 {
                    // The same box as a neighbour: ties in every cost.
                    return Aabb::new(vec3a(1.0, 2.0, 3.0), vec3a(1.5, 2.5, 3.5));
                }
                Aabb::new(c, c + size)
            })
            .collect()
    }

    fn same(a: &CwBvh, b: &CwBvh) {
        assert_eq!(a.nodes.len(), b.nodes.len());
        for (i, (x, y)) in a.nodes.iter().zip(&b.nodes).enumerate() {
            let bits = |n: &CwBvhNode| n.p.to_array().map(f32::to_bits);
            assert!(x == y && bits(x) == bits(y), "wide node {i} differs");
        }
        assert_eq!(a.primitive_indices, b.primitive_indices);
        assert_eq!(a.total_aabb.min, b.total_aabb.min);
        assert_eq!(a.total_aabb.max, b.total_aabb.max);
        assert_eq!(a.uses_spatial_splits, b.uses_spatial_splits);
    }

    #[test]
    fn matches_obvhs_node_for_node() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        for (n, seed) in [
            (1, 1),
            (2, 2),
            (3, 3),
            (9, 4),
            (25, 5),
            (1000, 6),
            (20_000, 7),
        ] {
            let b = boxes(n, seed);
            for reinsert in [false, true] {
                let mut bvh2 = PlocBuilder::with_capacity(n).build(
                    PlocSearchDistance::Low,
                    &b,
                    (0..n as u32).collect(),
                    SortPrecision::U64,
                    0,
                );
                if reinsert {
                    ReinsertionOptimizer::default().run(&mut bvh2, 0.05, None);
                }
                for leaf in 1..=3 {
                    let ours = bvh2_to_cwbvh(&bvh2, leaf);
                    let theirs =
                        obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh(&bvh2, leaf, true, false);
                    same(&ours, &theirs);
                    // Shared out down to the smallest subtrees, and at a
                    // middling size, on a pool of three threads: still
                    // obvhs's BVH, node for node.
                    for share_below in [2, 64] {
                        let shared =
                            pool.install(|| bvh2_to_cwbvh_sharing(&bvh2, leaf, share_below));
                        same(&shared, &theirs);
                    }
                }
            }
        }
    }

    #[test]
    fn an_empty_tree_is_an_empty_bvh() {
        let b = bvh2_to_cwbvh(&Bvh2::default(), 3);
        assert!(b.nodes.is_empty() && b.primitive_indices.is_empty());
    }
}
