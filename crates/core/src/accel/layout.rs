//! A BVH's shape without its triangles: the nodes, the order its boxes
//! take the set's triangles in, and its bounds. [`super::Accel`] is always
//! assembled from a triangle set and a layout: its own build makes the
//! layout on the spot, and a worker of a job that replicates the scene can
//! be shipped the layout that the scheduler built once for every worker,
//! instead of building the same BVH again on each (`fetch` on N workers
//! built N times; the kitchen on two workers spent more in its builds than
//! in rendering).
//!
//! A shipped layout comes from a peer, so [`Layout::check`] proves, in one
//! pass over its nodes, what the traversal relies on before any ray walks
//! it: every child and box it can name exists, the nodes form a tree no
//! deeper than the traversal's stack, and it was built over exactly the
//! set at hand (its triangle count and the hash of their ids). A layout
//! that passes cannot make a traversal read outside the BVH, loop, or visit
//! a node twice; a wrong one (from a scheduler that lies) can only give
//! wrong answers, as wrong triangles could.

use super::build::{self, BuildQuality};
use crate::geometry::{Bounds, SPAWN_OFFSET_REL, TriangleSet};
use glam::{Vec3, Vec3A};
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::node::CwBvhNode;
use serde::{Deserialize, Serialize};

/// The deepest tree the traversal walks correctly: its node stack holds
/// 32 groups (`walk::STACK`), at most one pushed per level below the root.
const MAX_DEPTH: u32 = 31;

/// A BVH over a triangle set, less the triangles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "Wire", into = "Wire")]
pub struct Layout {
    /// Triangles of the set it was built over, and [`ids_hash`] of their
    /// ids: it is taken only for that set.
    pub(super) triangles: u32,
    pub(super) ids_hash: u64,
    pub(super) nodes: Vec<CwBvhNode>,
    /// Per BVH box, the position in the set of its triangle (a split
    /// triangle has several boxes).
    pub(super) order: Vec<u32>,
    pub(super) bounds: Bounds,
    pub(super) splits: bool,
}

/// A hash of a set's ids that is the same on every machine and build (the
/// standard library's is not promised to be): FNV-1a over the words.
pub fn ids_hash(ids: &[u32]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &id in ids {
        h = (h ^ id as u64).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h ^ ids.len() as u64
}

impl Layout {
    /// Builds the BVH over `set`: each triangle's box (split where that
    /// pays, at `quality` Full) padded by 2^-18 of `magnitude`, because
    /// obvhs's slab test rounds in f32 and could otherwise reject a box
    /// that a ray grazes at a vertex or an edge.
    pub fn build(set: &TriangleSet, magnitude: f32, quality: BuildQuality) -> Self {
        assert!(set.is_consistent(), "one vertex triple and material per id");
        Self::build_over(&set.verts, &set.ids, magnitude, quality)
    }

    /// [`Self::build`] over the set whose triangle `i` is `verts[i]`, with
    /// global id `ids[i]`: a layout needs no materials or normals, so a
    /// scheduler laying out the whole scene lays it out in place rather
    /// than gathering a copy of it.
    pub fn build_over(
        verts: &[[Vec3; 3]],
        ids: &[u32],
        magnitude: f32,
        quality: BuildQuality,
    ) -> Self {
        assert_eq!(verts.len(), ids.len(), "one vertex triple per id");
        let pad = Vec3A::splat(magnitude * SPAWN_OFFSET_REL + f32::MIN_POSITIVE);
        let mut bounds = Bounds::EMPTY;
        let (mut boxes, of_box) = build::boxes(verts, quality);
        // Padded after the split: the clipped corners are rounded in f32,
        // and the pad covers that as it covers a grazing ray's box test.
        for b in &mut boxes {
            b.min -= pad;
            b.max += pad;
            bounds.grow(b.min.into());
            bounds.grow(b.max.into());
        }
        let mut bvh = if boxes.is_empty() {
            CwBvh::default()
        } else {
            build::cwbvh(&boxes, quality)
        };
        drop(boxes);
        // Traversal reports positions in the primitive order: each box's
        // triangle, in that order.
        let order = std::mem::take(&mut bvh.primitive_indices)
            .into_iter()
            .map(|p| of_box[p as usize])
            .collect();
        Self {
            triangles: ids.len() as u32,
            ids_hash: ids_hash(ids),
            nodes: bvh.nodes,
            order,
            bounds,
            splits: bvh.uses_spatial_splits,
        }
    }

    /// Heap bytes of the nodes and the order, as they travel.
    pub fn bytes(&self) -> usize {
        self.nodes.len() * NODE_WORDS * 4 + self.order.len() * 4
    }

    /// Nodes of the tree.
    pub fn nodes(&self) -> usize {
        self.nodes.len()
    }

    /// Whether this layout can be walked over `set` (see the module's
    /// doc), or why not.
    pub fn check(&self, set: &TriangleSet) -> Result<(), String> {
        let n = set.len();
        if !set.is_consistent() {
            return Err("its triangle set's lists differ in length".into());
        }
        if self.triangles as usize != n || self.ids_hash != ids_hash(&set.ids) {
            return Err(format!(
                "it was built over other triangles ({} against the {n} held)",
                self.triangles
            ));
        }
        let boxes = self.order.len();
        // Splits add at most a twentieth (`build::split_boxes`); twice is
        // far beyond anything a build makes.
        if boxes > 2 * n + 64 {
            return Err(format!("{boxes} boxes for {n} triangles"));
        }
        let mut seen = vec![false; n];
        for &p in &self.order {
            match seen.get_mut(p as usize) {
                Some(s) => *s = true,
                None => return Err(format!("a box names triangle {p} of {n}")),
            }
        }
        if seen.iter().any(|s| !s) {
            return Err("it leaves triangles out".into());
        }
        let b = &self.bounds;
        if boxes > 0 && !(b.min.is_finite() && b.max.is_finite() && b.min.cmple(b.max).all()) {
            return Err("its bounds are not finite".into());
        }
        match (boxes, self.nodes.len()) {
            (0, 0) => Ok(()),
            (0, _) => Err("nodes without boxes".into()),
            (_, 0) => Err("boxes without nodes".into()),
            (_, k) if k > boxes => Err(format!("{k} nodes for {boxes} boxes")),
            _ => self.check_tree(boxes),
        }
    }

    /// The nodes from the root (node 0) form a tree whose every child and
    /// box exists, no deeper than [`MAX_DEPTH`]. What is checked is what
    /// the traversal (obvhs's `traverse!` with `get_child_and_index_bits`,
    /// which `cwnode`'s tests mirror) derives from a node:
    /// - a child entry with meta bits 3 and 4 set is an inner child: its
    ///   hit sets bit `24 + ((meta & 7) ^ octant)` times `meta >> 5`, and the
    ///   traversal then visits node `child_base_idx + (imask's bits below
    ///   slot meta & 7)`. So its count must be 1 and its slot in `imask`,
    ///   and the `imask.count_ones()` nodes from `child_base_idx` must
    ///   exist, come after their parent and have no other parent.
    /// - any other entry sets bits `(meta >> 5) << (meta & 31)`, boxes
    ///   `primitive_base_idx + bit`: they must stay below bit 24 (above are
    ///   inner children) and inside the order.
    fn check_tree(&self, boxes: usize) -> Result<(), String> {
        let nodes = &self.nodes;
        let mut parented = vec![false; nodes.len()];
        parented[0] = true;
        let mut todo = vec![(0usize, 0u32)];
        while let Some((i, depth)) = todo.pop() {
            if depth > MAX_DEPTH {
                return Err(format!("a tree deeper than {MAX_DEPTH} levels"));
            }
            let node = &nodes[i];
            for &meta in &node.child_meta {
                let (count, at) = ((meta >> 5) as u32, (meta & 0x1f) as u32);
                if meta & 0x18 == 0x18 {
                    if count != 1 || node.imask & (1 << (meta & 7)) == 0 {
                        return Err(format!("node {i} has a child entry its mask lacks"));
                    }
                } else if count != 0 {
                    let top = at + 31 - count.leading_zeros();
                    if top >= 24 || node.primitive_base_idx as u64 + top as u64 >= boxes as u64 {
                        return Err(format!("node {i} names a box the layout does not have"));
                    }
                }
            }
            let inner = node.imask.count_ones() as usize;
            if inner == 0 {
                continue;
            }
            let first = node.child_base_idx as usize;
            if first <= i || first + inner > nodes.len() {
                return Err(format!("node {i} names children outside the tree"));
            }
            for (c, p) in parented[first..first + inner].iter_mut().enumerate() {
                if std::mem::replace(p, true) {
                    return Err(format!("node {} has two parents", first + c));
                }
                todo.push((first + c, depth + 1));
            }
        }
        Ok(())
    }
}

/// 32-bit words a node travels as.
const NODE_WORDS: usize = 20;

/// A node as little-endian words, field by field (its bytes in memory are
/// the processor's order).
fn node_words(n: &CwBvhNode) -> [u32; NODE_WORDS] {
    let word = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let mut w = [0u32; NODE_WORDS];
    w[0] = n.p.x.to_bits();
    w[1] = n.p.y.to_bits();
    w[2] = n.p.z.to_bits();
    w[3] = word(&[n.e[0], n.e[1], n.e[2], n.imask]);
    w[4] = n.child_base_idx;
    w[5] = n.primitive_base_idx;
    let bytes = [
        n.child_meta,
        n.child_min_x,
        n.child_max_x,
        n.child_min_y,
        n.child_max_y,
        n.child_min_z,
        n.child_max_z,
    ];
    for (k, b) in bytes.iter().enumerate() {
        w[6 + 2 * k] = word(&b[..4]);
        w[7 + 2 * k] = word(&b[4..]);
    }
    w
}

fn words_node(w: &[u32; NODE_WORDS]) -> CwBvhNode {
    let eight = |k: usize| {
        let (a, b) = (w[6 + 2 * k].to_le_bytes(), w[7 + 2 * k].to_le_bytes());
        [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3]]
    };
    let e = w[3].to_le_bytes();
    CwBvhNode {
        p: Vec3::new(
            f32::from_bits(w[0]),
            f32::from_bits(w[1]),
            f32::from_bits(w[2]),
        ),
        e: [e[0], e[1], e[2]],
        imask: e[3],
        child_base_idx: w[4],
        primitive_base_idx: w[5],
        child_meta: eight(0),
        child_min_x: eight(1),
        child_max_x: eight(2),
        child_min_y: eight(3),
        child_max_y: eight(4),
        child_min_z: eight(5),
        child_max_z: eight(6),
    }
}

/// A layout as it travels: its lists as byte strings ([`crate::bulk`]).
#[derive(Serialize, Deserialize)]
struct Wire {
    triangles: u32,
    ids_hash: u64,
    #[serde(with = "crate::bulk")]
    nodes: Vec<[u32; NODE_WORDS]>,
    #[serde(with = "crate::bulk")]
    order: Vec<u32>,
    bounds: Bounds,
    splits: bool,
}

impl From<Layout> for Wire {
    fn from(l: Layout) -> Self {
        Self {
            triangles: l.triangles,
            ids_hash: l.ids_hash,
            nodes: l.nodes.iter().map(node_words).collect(),
            order: l.order,
            bounds: l.bounds,
            splits: l.splits,
        }
    }
}

impl From<Wire> for Layout {
    fn from(w: Wire) -> Self {
        Self {
            triangles: w.triangles,
            ids_hash: w.ids_hash,
            nodes: w.nodes.iter().map(words_node).collect(),
            order: w.order,
            bounds: w.bounds,
            splits: w.splits,
        }
    }
}

#[cfg(test)]
mod tests;
