//! Walking the octree along a ray: the leaves it crosses as half-open
//! intervals that partition it, computed in f64 by one expression so that
//! every worker and every collapsed tree agrees on each interval end bit
//! for bit.

use super::{Node, Octree};
use crate::geometry::{Bounds, Ray};
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

#[cfg(test)]
mod tests {
    use super::super::tests::grid_octree;
    use crate::geometry::Ray;
    use glam::Vec3;

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
