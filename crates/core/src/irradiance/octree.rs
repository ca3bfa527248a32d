//! The octree of irradiance records (Ward, Rubinstein and Clear 1988,
//! section 3.3): a record is stored in the smallest node, containing its
//! point, whose edge is at least twice its radius of validity; a lookup
//! visits every node whose bounds, grown by half an edge on each side,
//! contain the point, so it meets every record whose sphere of validity
//! does and no others need be tested.

use crate::geometry::Bounds;
use glam::Vec3;

/// Depth below which nodes are not split: a record's radius of validity
/// is at least `edge / 2^MAX_DEPTH`-ish in any sane setting, and a bound
/// keeps a degenerate input from building a deep chain.
const MAX_DEPTH: u32 = 24;

#[derive(Clone, Debug, Default)]
struct Node {
    /// Index of each child in `nodes`, 0 for none (the root is never a
    /// child).
    children: [u32; 8],
    records: Vec<u32>,
}

/// Records by position and radius of validity.
#[derive(Clone, Debug)]
pub struct RecordOctree {
    center: Vec3,
    /// Half the root's edge.
    half: f32,
    nodes: Vec<Node>,
}

impl RecordOctree {
    /// An empty octree over `bounds` (a cube around them); records outside
    /// are kept at the root.
    pub fn new(bounds: &Bounds) -> Self {
        let (center, half) = if bounds.is_empty() {
            (Vec3::ZERO, 1.0)
        } else {
            (
                bounds.center(),
                (bounds.extent().max_element() * 0.5).max(1e-6),
            )
        };
        Self {
            center,
            half,
            nodes: vec![Node::default()],
        }
    }

    pub fn nodes(&self) -> usize {
        self.nodes.len()
    }

    /// Bytes the nodes and their lists hold.
    pub fn bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<Node>()
            + self
                .nodes
                .iter()
                .map(|n| n.records.capacity() * 4)
                .sum::<usize>()
    }

    fn child_of(center: Vec3, p: Vec3) -> usize {
        (p.x >= center.x) as usize
            | ((p.y >= center.y) as usize) << 1
            | ((p.z >= center.z) as usize) << 2
    }

    fn child_center(center: Vec3, half: f32, c: usize) -> Vec3 {
        let q = half * 0.5;
        let s = |bit: usize| if c & bit != 0 { q } else { -q };
        center + Vec3::new(s(1), s(2), s(4))
    }

    /// Stores record `id` at `p` with radius of validity `radius`.
    pub fn insert(&mut self, id: u32, p: Vec3, radius: f32) {
        let outside = (p - self.center).abs().max_element() > self.half;
        let (mut node, mut center, mut half) = (0usize, self.center, self.half);
        let mut depth = 0;
        // A child's grown bounds hold the record's sphere when its half
        // edge is at least the radius.
        while !outside && depth < MAX_DEPTH && half * 0.5 >= radius {
            let c = Self::child_of(center, p);
            let next = self.nodes[node].children[c];
            let next = if next == 0 {
                self.nodes.push(Node::default());
                let i = (self.nodes.len() - 1) as u32;
                self.nodes[node].children[c] = i;
                i
            } else {
                next
            };
            center = Self::child_center(center, half, c);
            half *= 0.5;
            node = next as usize;
            depth += 1;
        }
        self.nodes[node].records.push(id);
    }

    /// Calls `f` with every record whose node's grown bounds contain `p`:
    /// a superset of those whose sphere of validity contains it.
    pub fn visit(&self, p: Vec3, mut f: impl FnMut(u32)) {
        let mut stack = [(0u32, Vec3::ZERO, 0.0f32); 8 * MAX_DEPTH as usize + 8];
        let mut top = 1;
        stack[0] = (0, self.center, self.half);
        while top > 0 {
            top -= 1;
            let (i, center, half) = stack[top];
            let node = &self.nodes[i as usize];
            node.records.iter().for_each(|&r| f(r));
            for (c, &child) in node.children.iter().enumerate() {
                if child == 0 {
                    continue;
                }
                let cc = Self::child_center(center, half, c);
                // Grown bounds: the child's half edge plus half its edge.
                if (p - cc).abs().max_element() <= half {
                    stack[top] = (child, cc, half * 0.5);
                    top += 1;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::SampleKey;

    #[test]
    fn visits_every_record_whose_sphere_holds_the_point() {
        let b = Bounds::new(Vec3::splat(-2.0), Vec3::new(3.0, 1.0, 2.0));
        let mut o = RecordOctree::new(&b);
        let mut recs = Vec::new();
        for i in 0..2000u32 {
            let k = SampleKey::independent(i as u64, 0, 7);
            let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 6.0 - 2.5;
            let r = 0.01 + 0.6 * k.get1d(3) * k.get1d(3);
            o.insert(i, p, r);
            recs.push((p, r));
        }
        for i in 0..3000u32 {
            let k = SampleKey::independent(i as u64, 1, 7);
            let q = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 6.0 - 2.5;
            let mut seen = Vec::new();
            o.visit(q, |r| seen.push(r));
            seen.sort_unstable();
            let n = seen.len();
            seen.dedup();
            assert_eq!(seen.len(), n, "a record visited twice");
            for (id, (p, r)) in recs.iter().enumerate() {
                if (q - *p).length() < *r {
                    assert!(
                        seen.binary_search(&(id as u32)).is_ok(),
                        "missed {id} at {q}"
                    );
                }
            }
        }
        assert!(
            o.nodes() > 100,
            "{} nodes: the records all sat at the root",
            o.nodes()
        );
    }
}
