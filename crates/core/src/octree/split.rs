//! Sorting a node's triangle references into its eight children: the
//! exact triangle/box test (separating axes, in f64) against each child's
//! inflated box, behind bounding-box prefilters that give exactly its
//! answer, and the rule that stops splitting where nothing separates.

use super::child_bounds;
use crate::geometry::Bounds;
use glam::{DVec3, Vec3};

/// Whether splitting a node of `n` references into `subs` separates
/// anything: not when two or more children each receive every reference
/// (duplicate or coincident triangles spanning the node), which no depth
/// would separate, while each level would multiply the references by up to
/// four (a surface crosses 4 times the cells per level): such a node stays
/// a leaf. A single child with everything still localises them.
pub(super) fn separates(n: usize, subs: &[Vec<u32>; 8]) -> bool {
    let full = subs.iter().filter(|s| s.len() == n).count();
    let some = subs.iter().filter(|s| !s.is_empty()).count();
    !(full >= 2 && full == some)
}

/// `refs` sorted into the eight children of box `b`, in order: a triangle
/// goes to every child whose inflated box it overlaps. One pass over the
/// references; a child that the triangle's bounding box misses (most of
/// them: triangles are small beside a node) is rejected, and one that
/// contains the bounding box accepted, without the exact test. Both
/// prefilters err towards the exact test by far more than rounding, so
/// the result is exactly that of testing every child.
pub(super) fn split_refs(b: &Bounds, refs: &[u32], tris: &[[Vec3; 3]]) -> [Vec<u32>; 8] {
    let boxes: [(DVec3, DVec3); 8] = std::array::from_fn(|i| inflate(&child_bounds(b, i)));
    let slack = (b.extent().max_element() as f64 + b.max_abs() as f64) * 1e-9;
    let loose: [(DVec3, DVec3); 8] =
        std::array::from_fn(|i| (boxes[i].0 - slack, boxes[i].1 + slack));
    let tight: [(DVec3, DVec3); 8] =
        std::array::from_fn(|i| (boxes[i].0 + slack, boxes[i].1 - slack));
    let mut out: [Vec<u32>; 8] = Default::default();
    for &t in refs {
        let tri = &tris[t as usize];
        let lo = tri[0].min(tri[1]).min(tri[2]).as_dvec3();
        let hi = tri[0].max(tri[1]).max(tri[2]).as_dvec3();
        for i in 0..8 {
            let (l, h) = loose[i];
            if !(lo.cmple(h).all() && hi.cmpge(l).all()) {
                continue;
            }
            // A triangle inside the box overlaps it: only one that
            // crosses a face needs the exact test.
            let (tl, th) = tight[i];
            let inside = lo.cmpge(tl).all() && hi.cmple(th).all();
            if inside || tri_box_overlap(tri, &boxes[i]) {
                out[i].push(t);
            }
        }
    }
    out
}

/// The box a triangle must overlap to be referenced by a leaf: grown by a
/// margin far above f32 rounding of a point computed on the ray, so a hit
/// that rounds across a face is still found in either leaf.
fn inflate(b: &Bounds) -> (DVec3, DVec3) {
    let margin = (b.extent().max_element() as f64) * 1e-4 + (b.max_abs() as f64) * 1e-6;
    (b.min.as_dvec3() - margin, b.max.as_dvec3() + margin)
}

/// Triangle/box overlap by the separating axis theorem (Akenine-Möller
/// 2001), in f64.
pub fn tri_box_overlap(tri: &[Vec3; 3], b: &(DVec3, DVec3)) -> bool {
    let c = (b.0 + b.1) * 0.5;
    let h = (b.1 - b.0) * 0.5;
    let v = [
        tri[0].as_dvec3() - c,
        tri[1].as_dvec3() - c,
        tri[2].as_dvec3() - c,
    ];
    // Box face normals.
    for a in 0..3 {
        let lo = v[0][a].min(v[1][a]).min(v[2][a]);
        let hi = v[0][a].max(v[1][a]).max(v[2][a]);
        if lo > h[a] || hi < -h[a] {
            return false;
        }
    }
    let e = [v[1] - v[0], v[2] - v[1], v[0] - v[2]];
    // Triangle normal.
    let n = e[0].cross(e[1]);
    let r = h.x * n.x.abs() + h.y * n.y.abs() + h.z * n.z.abs();
    let s = n.dot(v[0]);
    if s.abs() > r {
        return false;
    }
    // Edge cross box axes.
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    for ed in &e {
        for ax in &axes {
            let a = ed.cross(*ax);
            if a.length_squared() == 0.0 {
                continue;
            }
            let p = [a.dot(v[0]), a.dot(v[1]), a.dot(v[2])];
            let lo = p[0].min(p[1]).min(p[2]);
            let hi = p[0].max(p[1]).max(p[2]);
            let r = h.x * a.x.abs() + h.y * a.y.abs() + h.z * a.z.abs();
            if lo > r || hi < -r {
                return false;
            }
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::{Octree, OctreeParams};

    /// The one-pass split with its bounding-box prefilter sends each
    /// triangle to exactly the children the exact test alone accepts,
    /// including triangles lying on, or a rounding step away from, the
    /// children's shared faces and the margin's edge.
    #[test]
    fn split_matches_the_exact_test_on_every_child() {
        let b = Bounds::new(Vec3::new(-1.0, -2.0, -3.0), Vec3::new(3.0, 2.0, 1.0));
        let m = b.center();
        let margin = inflate(&child_bounds(&b, 0)).0.x as f32 - b.min.x;
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut tris = Vec::new();
        for k in 0..20_000 {
            // A point on a face, on the margin's edge, one ulp either
            // side, or anywhere; then a small or a large triangle there.
            let mut p = b.min + (b.max - b.min) * Vec3::new(next(), next(), next());
            let a = k % 3;
            match k % 5 {
                0 => p[a] = m[a],
                1 => p[a] = b.min[a] + margin,
                2 => p[a] = f32::from_bits(m[a].to_bits() + 1),
                3 => p[a] = b.max[a] - margin.abs(),
                _ => {}
            }
            let size = if k % 7 == 0 { 2.0 } else { 0.01 };
            let d = |r: f32| (r - 0.5) * size;
            tris.push([
                p,
                p + Vec3::new(d(next()), d(next()), 0.0),
                p + Vec3::new(0.0, d(next()), d(next())),
            ]);
        }
        let refs: Vec<u32> = (0..tris.len() as u32).collect();
        let split = split_refs(&b, &refs, &tris);
        let mut kept = 0;
        for (i, got) in split.iter().enumerate() {
            let inflated = inflate(&child_bounds(&b, i));
            let want: Vec<u32> = refs
                .iter()
                .copied()
                .filter(|&t| tri_box_overlap(&tris[t as usize], &inflated))
                .collect();
            assert_eq!(*got, want, "child {i}");
            kept += got.len();
        }
        // Many triangles straddle faces: the test exercises both sides.
        assert!(kept > tris.len() + tris.len() / 10, "{kept}");
    }

    /// Duplicate triangles spanning a node cannot be separated by any
    /// depth: the build stops there instead of multiplying references by
    /// four a level down to the maximum depth (3,000 duplicates of one
    /// large triangle once took minutes and gigabytes), and a cluster in
    /// one child is still localised.
    #[test]
    fn duplicates_do_not_multiply_references() {
        let t = [
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.5),
        ];
        let mut tris = vec![t; 3000];
        let params = OctreeParams {
            max_leaf_tris: 1,
            max_depth: 16,
        };
        let o = Octree::build(&tris, params);
        assert_eq!(o.leaf_count(), 1, "nothing to separate");
        assert_eq!(o.reference_count(), 3000);
        // A few small triangles off in one corner are split away from them.
        tris.extend((0..8).map(|i| {
            let c = Vec3::new(0.9, 0.9, -0.9) + Vec3::splat(i as f32 * 0.01);
            [c, c + Vec3::X * 0.005, c + Vec3::Y * 0.005]
        }));
        let o = Octree::build(&tris, params);
        assert!(o.leaf_count() > 1);
        assert!(o.reference_count() < 3008 * 8, "{}", o.reference_count());
    }

    #[test]
    fn sat_rejects_and_accepts() {
        let b = (DVec3::ZERO, DVec3::ONE);
        let inside = [Vec3::splat(0.2), Vec3::splat(0.3), Vec3::new(0.2, 0.5, 0.4)];
        assert!(tri_box_overlap(&inside, &b));
        // A big triangle whose bounding box covers the unit box but whose
        // plane passes beside it.
        let beside = [
            Vec3::new(3.5, 0.0, 0.0),
            Vec3::new(0.0, 3.5, 0.0),
            Vec3::new(0.0, 0.0, 3.5),
        ];
        assert!(!tri_box_overlap(&beside, &b));
        let touching = [
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(1.0, 0.0, 1.0),
        ];
        assert!(tri_box_overlap(&touching, &b));
    }
}
