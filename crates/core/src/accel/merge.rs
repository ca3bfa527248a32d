//! Several finished BVHs joined into one under a few new top nodes.
//!
//! A worker with a memory budget builds its region in parts, each small
//! enough for a build's peak (about five times what the finished BVH
//! keeps) to fit beside what the worker already holds. Traced as a set
//! ([`crate::accel_set::AccelSet`]), every part a ray's segment enters is
//! a query of its own, with its own setup and its own descent from a root:
//! on the 4-million-triangle room at 4 workers of 160 MiB, 18 parts a
//! worker and about six part queries a ray. Joined, the parts' nodes and
//! triangles are moved into one array each, and wide nodes over the
//! parts' roots (eight to a node, parts in the order given, which for a
//! region is Morton order) make one tree: one query a ray, and a ray
//! descends into a part only where it meets the part's box, as it would
//! meet any node. Nothing is built again, so the join needs little more
//! memory than the parts: the largest of them once more (each part is
//! freed as it is moved) and 8 bytes a triangle for its index by id.
//!
//! Hits are exact and ties go to the smaller global id, so the joined BVH
//! gives every ray the answer the set gave.

use super::convert::{frame, internal_meta, quantise, slots};
use super::{Accel, pages};
use crate::geometry::{Bounds, FLAT};
use glam::Vec3A;
use obvhs::aabb::Aabb;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::node::CwBvhNode;

/// The node stack a traversal keeps (`walk::STACK`, obvhs's
/// `TRAVERSAL_STACK_SIZE`) bounds the depth a joined tree may reach: a
/// traversal pushes at most one entry a level.
const MAX_DEPTH: usize = 30;

/// A node of the new top: its box and its children.
struct Top {
    aabb: Aabb,
    children: Vec<Child>,
}

enum Child {
    Part(usize),
    Node(Top),
}

impl Child {
    fn aabb(&self, parts: &[Accel]) -> Aabb {
        match self {
            Child::Part(i) => parts[*i].bvh.total_aabb,
            Child::Node(t) => t.aabb,
        }
    }
}

impl Accel {
    /// The parts as one BVH (see the module's doc); the parts back,
    /// untouched, when the joined tree would be deeper than a traversal's
    /// node stack holds.
    pub fn join(parts: Vec<Accel>) -> Result<Accel, Vec<Accel>> {
        let full = parts.iter().filter(|a| !a.is_empty()).count();
        if full >= 2 {
            let deepest = parts.iter().filter(|a| !a.is_empty()).map(depth).max();
            if top_levels(full) + deepest.unwrap_or(0) > MAX_DEPTH {
                return Err(parts);
            }
        }
        let (mut full, empty): (Vec<Accel>, Vec<Accel>) =
            parts.into_iter().partition(|a| !a.is_empty());
        if full.len() <= 1 {
            return Ok(full
                .pop()
                .or_else(|| empty.into_iter().next())
                .unwrap_or_else(|| Accel::build(&[], &[], 1.0)));
        }
        let top = top_tree(&full);
        debug_assert_eq!(depth_of_top(&top), top_levels(full.len()));
        Ok(join_under(full, top))
    }
}

/// Wide nodes over the parts, eight children to a node, consecutive parts
/// together: `parts.len() >= 2`.
fn top_tree(parts: &[Accel]) -> Top {
    let mut level: Vec<Child> = (0..parts.len()).map(Child::Part).collect();
    loop {
        if level.len() <= 8 {
            return Top {
                aabb: union(level.iter().map(|c| c.aabb(parts))),
                children: level,
            };
        }
        // Groups as even as eight a node allows.
        let groups = level.len().div_ceil(8);
        let (size, extra) = (level.len() / groups, level.len() % groups);
        let mut it = level.into_iter();
        level = (0..groups)
            .map(|g| {
                let children: Vec<Child> =
                    it.by_ref().take(size + usize::from(g < extra)).collect();
                Child::Node(Top {
                    aabb: union(children.iter().map(|c| c.aabb(parts))),
                    children,
                })
            })
            .collect();
    }
}

/// Levels of top nodes over `n >= 2` parts ([`top_tree`]).
fn top_levels(mut n: usize) -> usize {
    let mut levels = 1;
    while n > 8 {
        n = n.div_ceil(8);
        levels += 1;
    }
    levels
}

fn union(boxes: impl Iterator<Item = Aabb>) -> Aabb {
    boxes.fold(Aabb::INVALID, |u, b| u.union(&b))
}

fn depth_of_top(t: &Top) -> usize {
    1 + t
        .children
        .iter()
        .map(|c| match c {
            Child::Part(_) => 0,
            Child::Node(n) => depth_of_top(n),
        })
        .max()
        .unwrap_or(0)
}

/// Levels of wide nodes from a part's root to its deepest node.
fn depth(a: &Accel) -> usize {
    let nodes = &a.bvh.nodes;
    let mut deepest = 0;
    let mut stack = vec![(0usize, 1usize)];
    while let Some((i, d)) = stack.pop() {
        deepest = deepest.max(d);
        let n = &nodes[i];
        let mut rank = 0;
        for slot in 0..8 {
            if n.imask & (1 << slot) != 0 {
                stack.push((n.child_base_idx as usize + rank, d + 1));
                rank += 1;
            }
        }
    }
    deepest
}

/// Moves every part's nodes and triangles into one BVH under `top`.
fn join_under(parts: Vec<Accel>, top: Top) -> Accel {
    let boxes: usize = parts.iter().map(|p| p.meta.len()).sum();
    let part_nodes: usize = parts.iter().map(|p| p.bvh.nodes.len()).sum();
    let with_normals = parts.iter().any(|p| !p.normals.is_empty());
    let mut nodes = Vec::new();
    let mut roots = Vec::new();
    emit(&mut nodes, &mut roots, &parts, &top, 0, true);
    let top_nodes = nodes.len();
    let mut joined = pages::collect(top_nodes + part_nodes, nodes);
    let mut verts = pages::collect(boxes, std::iter::empty());
    let mut meta = pages::collect(boxes, std::iter::empty());
    let mut normals = if with_normals {
        pages::collect(boxes, std::iter::empty())
    } else {
        Vec::new()
    };
    let mut ids: Vec<(u32, u32)> = Vec::with_capacity(boxes);
    let mut bounds = Bounds::EMPTY;
    let mut splits = false;
    for (i, p) in parts.into_iter().enumerate() {
        // A part's root takes its place among the top's nodes; the rest
        // of its nodes follow the nodes before, its triangles the
        // triangles before.
        let (node_off, prim_off) = (joined.len() as u32, verts.len() as u32);
        let fix = |mut n: CwBvhNode| {
            n.child_base_idx = n.child_base_idx.wrapping_sub(1).wrapping_add(node_off);
            n.primitive_base_idx += prim_off;
            n
        };
        let Accel {
            bvh,
            verts: v,
            meta: m,
            normals: s,
            by_id,
            bounds: b,
        } = p;
        joined[roots[i]] = fix(bvh.nodes[0]);
        joined.extend(bvh.nodes[1..].iter().copied().map(fix));
        splits |= bvh.uses_spatial_splits;
        drop(bvh);
        ids.extend(by_id.iter().map(|&q| (m[q as usize].id, q + prim_off)));
        drop(by_id);
        if with_normals {
            if s.is_empty() {
                normals.extend(std::iter::repeat_n(FLAT, v.len()));
            } else {
                normals.extend(s);
            }
        }
        verts.extend(v);
        meta.extend(m);
        if !b.is_empty() {
            bounds.grow(b.min);
            bounds.grow(b.max);
        }
    }
    // One position per triangle by id: a triangle two parts both hold (it
    // crosses their leaves) stands at its first.
    ids.sort_unstable();
    ids.dedup_by_key(|e| e.0);
    let by_id = ids.into_iter().map(|(_, q)| q).collect();
    Accel {
        bvh: CwBvh {
            nodes: joined,
            primitive_indices: Vec::new(),
            total_aabb: top.aabb,
            exact_node_aabbs: None,
            uses_spatial_splits: splits,
        },
        verts,
        meta,
        normals,
        by_id,
        bounds,
    }
}

/// Writes top node `t` at `at` (appending it when `push`), its children's
/// block after the nodes so far, and their subtrees; a part's root is a
/// placeholder whose index goes to `roots[part]`.
fn emit(
    nodes: &mut Vec<CwBvhNode>,
    roots: &mut Vec<usize>,
    parts: &[Accel],
    t: &Top,
    at: usize,
    push: bool,
) {
    if push {
        nodes.push(CwBvhNode::default());
    }
    if roots.is_empty() {
        roots.resize(parts.len(), usize::MAX);
    }
    let centres: Vec<Vec3A> = t.children.iter().map(|c| c.aabb(parts).center()).collect();
    let mut in_slot = [None; 8];
    for (c, s) in slots(t.aabb.center(), &centres)
        .into_iter()
        .take(t.children.len())
        .enumerate()
    {
        in_slot[s] = Some(c);
    }
    let mut node = CwBvhNode::default();
    let (p, rcp_e) = frame(&mut node, &t.aabb);
    node.child_base_idx = nodes.len() as u32;
    let mut inner = Vec::new();
    for (i, slot) in in_slot.iter().enumerate() {
        let Some(c) = slot else { continue };
        quantise(&mut node, i, &t.children[*c].aabb(parts), p, rcp_e);
        node.imask |= 1u8 << i;
        node.child_meta[i] = internal_meta(i);
        inner.push(*c);
    }
    let base = nodes.len();
    nodes.resize(base + inner.len(), CwBvhNode::default());
    nodes[at] = node;
    for (k, &c) in inner.iter().enumerate() {
        match &t.children[c] {
            Child::Part(i) => roots[*i] = base + k,
            Child::Node(n) => emit(nodes, roots, parts, n, base + k, false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// `n` one-triangle BVHs along the x axis, each triangle's id 0.
    fn parts(n: usize) -> Vec<Accel> {
        (0..n)
            .map(|i| {
                let p = Vec3::new(i as f32 * 2.0, (i % 3) as f32, 0.0);
                Accel::build(&[[p, p + Vec3::X, p + Vec3::Y]], &[0], 100.0)
            })
            .collect()
    }

    /// The top has at most eight children a node, the parts in order
    /// under it, and as many levels as [`top_levels`] counts.
    #[test]
    fn top_trees_hold_every_part_in_order_eight_to_a_node() {
        fn leaves(t: &Top, out: &mut Vec<usize>) {
            assert!((2..=8).contains(&t.children.len()) || out.is_empty() && t.children.len() <= 8);
            for c in &t.children {
                match c {
                    Child::Part(i) => out.push(*i),
                    Child::Node(n) => leaves(n, out),
                }
            }
        }
        let all = parts(600);
        for n in (2..=80).chain([511, 512, 513, 600]) {
            let t = top_tree(&all[..n]);
            let mut order = Vec::new();
            leaves(&t, &mut order);
            assert_eq!(order, (0..n).collect::<Vec<_>>(), "{n} parts");
            assert_eq!(depth_of_top(&t), top_levels(n), "{n} parts");
        }
        assert_eq!(top_levels(8), 1);
        assert_eq!(top_levels(9), 2);
        assert_eq!(top_levels(64), 2);
        assert_eq!(top_levels(65), 3);
    }

    /// Empty parts are left out, and one part left is the join.
    #[test]
    fn empty_parts_are_left_out() {
        assert!(Accel::join(Vec::new()).ok().is_some_and(|a| a.is_empty()));
        let mut ps = parts(1);
        ps.insert(0, Accel::build(&[], &[], 1.0));
        let one = Accel::join(ps).ok().expect("a part");
        assert_eq!(one.len(), 1);
        assert_eq!(one.bvh.nodes.len(), 1);
    }

    /// A joined BVH is as deep as its top and its deepest part, holds
    /// every triangle once, and finds each one along a ray through it.
    #[test]
    fn joined_parts_are_one_tree_over_every_triangle() {
        for n in [2usize, 8, 9, 70] {
            let mut ps = parts(n);
            for (i, p) in ps.iter_mut().enumerate() {
                p.meta[0].id = i as u32;
            }
            let deepest = ps.iter().map(depth).max().unwrap();
            let one = Accel::join(ps).unwrap_or_else(|_| panic!("{n} parts refused"));
            assert_eq!(depth(&one), top_levels(n) + deepest, "{n} parts");
            assert_eq!(one.len(), n);
            let mut st = crate::stats::TraceStats::default();
            for i in 0..n {
                let p = one.find(i as u32).expect("every triangle");
                let [a, b, c] = one.triangle(p).0;
                let centre = (a + b + c) / 3.0;
                let ray = crate::geometry::Ray::new(
                    centre + Vec3::Z,
                    Vec3::new(0.01, 0.02, -1.0).normalize(),
                );
                let hit = one.intersect(&ray, 0.0, f32::INFINITY, &mut st);
                assert_eq!(
                    hit.map(|h| h.tri),
                    Some(i as u32),
                    "{n} parts, triangle {i}"
                );
            }
        }
    }
}
