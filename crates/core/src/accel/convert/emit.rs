//! The collapse's second pass: the wide nodes emitted from the decisions,
//! in obvhs's order (a node's children in one block, then each internal
//! child's subtree in slot order). It runs on one thread: emitting
//! subtrees at once into buffers of their own and appending them took
//! a build 32 bytes a triangle more at its peak, beyond what the memory
//! plans charge (see `docs/benchmarks/loading.md`).

use super::{Decisions, Kind, Tree};
use glam::{UVec3, Vec3A, vec3a};
use obvhs::PerComponent;
use obvhs::aabb::Aabb;
use obvhs::cwbvh::BRANCHING;
use obvhs::cwbvh::node::CwBvhNode;

/// 1 / 255: a child plane is quantised to 8 bits of its node's extent.
const DENOM: f32 = 1.0 / 255.0;

/// The wide nodes, emitted as obvhs's `convert_to_cwbvh` emits them.
pub(super) struct Emit<'a> {
    t: &'a Tree,
    d: &'a Decisions,
    pub(super) nodes: Vec<CwBvhNode>,
    pub(super) primitive_indices: Vec<u32>,
}

impl<'a> Emit<'a> {
    /// An emission whose first wide node, at index 0, is still to come.
    pub(super) fn new(t: &'a Tree, d: &'a Decisions, prims: usize) -> Self {
        let mut nodes = Vec::with_capacity(prims.max(1));
        nodes.push(CwBvhNode::default());
        Self {
            t,
            d,
            nodes,
            primitive_indices: Vec::with_capacity(prims),
        }
    }

    /// Wide node `at8` from entry `at2`, and the wide nodes below it, in
    /// obvhs's order: the node's children in one block, then each
    /// internal child's subtree in slot order.
    pub(super) fn node(&mut self, at8: usize, at2: usize) {
        let (base, inner, n) = self.head(at8, at2);
        for (k, &c) in inner[..n].iter().enumerate() {
            self.node(base + k, c as usize);
        }
    }

    /// Writes wide node `at8` from entry `at2`, its leaf children's
    /// primitives and room for its internal children; returns where that
    /// room starts and the internal children's entries, in slot order.
    fn head(&mut self, at8: usize, at2: usize) -> (usize, [u32; 8], usize) {
        let mut node = self.nodes[at8];
        let (p, rcp_e) = frame(&mut node, &self.t.nodes[at2].aabb());
        let mut children = [u32::MAX; 8];
        let mut count = 0;
        self.children(at2, &mut children, &mut count, 0);
        self.order(at2, &mut children, count);
        node.imask = 0;
        node.primitive_base_idx = self.primitive_indices.len() as u32;
        node.child_base_idx = self.nodes.len() as u32;
        let (mut internal, mut prims) = (0usize, 0u32);
        for (i, &c) in children.iter().enumerate() {
            if c == u32::MAX {
                continue;
            }
            quantise(&mut node, i, &self.t.nodes[c as usize].aabb(), p, rcp_e);
            match self.d.kind(c as usize, 0) {
                Kind::Leaf => {
                    let n = self.leaf_prims(c as usize);
                    node.child_meta[i] = prims as u8
                        | match n {
                            1 => 0b0010_0000,
                            2 => 0b0110_0000,
                            3 => 0b1110_0000,
                            _ => panic!("a wide leaf of {n} primitives"),
                        };
                    prims += n;
                }
                Kind::Internal => {
                    node.imask |= 1u8 << i;
                    node.child_meta[i] = internal_meta(i);
                    internal += 1;
                }
                Kind::Distribute => unreachable!("a child slot that distributes"),
            }
        }
        self.nodes
            .resize(self.nodes.len() + internal, CwBvhNode::default());
        self.nodes[at8] = node;
        let (mut inner, mut n) = ([u32::MAX; 8], 0);
        for (i, &c) in children.iter().enumerate() {
            if c != u32::MAX && node.imask & (1 << i) != 0 {
                inner[n] = c;
                n += 1;
            }
        }
        (node.child_base_idx as usize, inner, n)
    }

    /// Appends the primitives below `i`, left to right, and counts them.
    fn leaf_prims(&mut self, i: usize) -> u32 {
        let end = self.t.end(i);
        let before = self.primitive_indices.len();
        self.primitive_indices.extend(
            self.t.prims[i..end]
                .iter()
                .copied()
                .filter(|&p| p != u32::MAX),
        );
        (self.primitive_indices.len() - before) as u32
    }

    /// The wide node's children under `i` with decision `slot`.
    fn children(&self, i: usize, out: &mut [u32; 8], count: &mut usize, slot: usize) {
        if self.t.is_leaf(i) {
            out[*count] = i as u32;
            *count += 1;
            return;
        }
        let dec = self.d.get(i, slot);
        for (child, s) in [
            (i + 1, dec.left),
            (self.t.nodes[i].right as usize, dec.right),
        ] {
            if self.d.kind(child, s as usize) == Kind::Distribute {
                self.children(child, out, count, s as usize);
            } else {
                out[*count] = child as u32;
                *count += 1;
            }
        }
    }

    /// The children in their slots ([`slots`]).
    fn order(&self, i: usize, children: &mut [u32; 8], count: usize) {
        let centres: Vec<Vec3A> = children[..count]
            .iter()
            .map(|&c| self.t.nodes[c as usize].aabb().center())
            .collect();
        let slot = slots(self.t.nodes[i].aabb().center(), &centres);
        let original = std::mem::replace(children, [u32::MAX; 8]);
        for c in 0..count {
            children[slot[c]] = original[c];
        }
    }
}

/// Sets `node`'s frame over `aabb`: its origin and per-axis scale, a
/// power of two stored as its exponent, so that 255 steps span the box.
/// Returns the origin and the scale's reciprocal, for [`quantise`].
pub(in crate::accel) fn frame(node: &mut CwBvhNode, aabb: &Aabb) -> (Vec3A, Vec3A) {
    let p = aabb.min;
    node.p = p.into();
    let e = ((aabb.max - aabb.min).max(Vec3A::splat(1e-20)) * DENOM)
        .log2()
        .ceil()
        .exp2();
    let rcp_e = 1.0 / e;
    let e: UVec3 = e.per_comp(|c: f32| c.to_bits() >> 23);
    node.e = [e.x as u8, e.y as u8, e.z as u8];
    (p, rcp_e)
}

/// Writes child `i`'s box `b` into `node`, quantised outward in the frame
/// [`frame`] set.
pub(in crate::accel) fn quantise(node: &mut CwBvhNode, i: usize, b: &Aabb, p: Vec3A, rcp_e: Vec3A) {
    let lo = ((b.min - p - 0.0) * rcp_e)
        .floor()
        .clamp(Vec3A::ZERO, Vec3A::splat(255.0));
    let hi = ((b.max - p + 0.0) * rcp_e)
        .ceil()
        .clamp(Vec3A::ZERO, Vec3A::splat(255.0));
    node.child_min_x[i] = lo.x as u8;
    node.child_min_y[i] = lo.y as u8;
    node.child_min_z[i] = lo.z as u8;
    node.child_max_x[i] = hi.x as u8;
    node.child_max_y[i] = hi.y as u8;
    node.child_max_z[i] = hi.z as u8;
}

/// The meta byte of an internal child in slot `i`.
pub(in crate::accel) fn internal_meta(i: usize) -> u8 {
    (24 + i as u8) | 0b0010_0000
}

/// obvhs's greedy assignment of a node's children (their box centres) to
/// its eight slots, by their centres along each octant's diagonal seen
/// from the node's `centre`, so that a ray's octant gives its traversal
/// order: child `c` goes to slot `result[c]`.
pub(in crate::accel) fn slots(centre: Vec3A, children: &[Vec3A]) -> [usize; BRANCHING] {
    let directions: [Vec3A; 8] = std::array::from_fn(|s| {
        vec3a(
            if s & 0b100 != 0 { -1.0 } else { 1.0 },
            if s & 0b010 != 0 { -1.0 } else { 1.0 },
            if s & 0b001 != 0 { -1.0 } else { 1.0 },
        )
    });
    let count = children.len();
    let mut cost = [[f32::MAX; 8]; BRANCHING];
    for (s, d) in directions.iter().enumerate() {
        for c in 0..count {
            cost[c][s] = d.dot(children[c] - centre);
        }
    }
    let mut assignment = [usize::MAX; BRANCHING];
    let mut filled = [false; 8];
    loop {
        let (mut min, mut slot, mut index) = (f32::MAX, usize::MAX, usize::MAX);
        for c in 0..count {
            if assignment[c] == usize::MAX {
                for (s, &f) in filled.iter().enumerate() {
                    if !f && cost[c][s] < min {
                        (min, slot, index) = (cost[c][s], s, c);
                    }
                }
            }
        }
        if slot == usize::MAX {
            break;
        }
        filled[slot] = true;
        assignment[index] = slot;
    }
    assignment
}
